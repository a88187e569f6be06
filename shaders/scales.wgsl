// Band-limited complex-Morlet scales for a batch of runs (host: src/gpu/scales.rs).
//
// `scatter`: for each item (one run × one scale) fills its length-M buffer with the
// weighted, demodulated pass band: slot (m − c) mod M gets 2·X[m]·Ψ(s·f_m)/L for the bins
// m = lo..=hi, every other slot 0 — the input of the item's inverse FFT, whose output is
// the baseband w[q] = W(t_q)·e^{-j2π c t_q/L} at the decimated times t_q = q·L/M
// (src/transform/band.rs explains why this is exact).
//
// `power`: |W|² on the coarse time grid by cubic Lagrange interpolation of the periodic
// baseband sequence, at positions the host computed in f64 (f32 cannot hold j·h·M/L).

struct Item {
    spec: u32,      // offset in `spectrum` of bin lo (only the runs' pass bands are there)
    lo: u32,        // first bin of the pass band
    hi: u32,        // last bin of the pass band
    centre: u32,    // demodulation bin c
    m: u32,         // decimated length M (the item's FFT length)
    data: u32,      // offset of the item's M values in `data`
    power: u32,     // offset of the item's coarse power values in `power`
    positions: u32, // offset of its table in `index`/`frac`
    steps: u32,     // coarse steps
    scale: f32,     // wavelet scale s (s)
    df: f32,        // bin spacing of the padded spectrum (Hz)
    norm: f32,      // 2/L
};

struct Wavelet {
    bandwidth: f32,
    centre: f32,
    taper: f32,     // Ψ is brought to 0 below taper·centre/s by a C∞ step
    _pad: u32,
};

@group(0) @binding(0) var<uniform> wavelet: Wavelet;
@group(0) @binding(1) var<storage, read> items: array<Item>;
@group(0) @binding(2) var<storage, read> spectrum: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read_write> data: array<vec2<f32>>;
@group(0) @binding(4) var<storage, read_write> power: array<f32>;
@group(0) @binding(5) var<storage, read> index: array<u32>;
@group(0) @binding(6) var<storage, read> frac: array<f32>;

const PI: f32 = 3.14159265358979;

// The Morlet spectrum of src/transform/mod.rs (Morlet::spectrum), in f32.
fn psi(scale: f32, f: f32) -> f32 {
    let x = scale * f;
    if (x <= 0.0) {
        return 0.0;
    }
    let d = x - wavelet.centre;
    let g = exp(-PI * PI * wavelet.bandwidth * d * d);
    let u = x / (wavelet.taper * wavelet.centre);
    if (u >= 1.0) {
        return g;
    }
    let a = exp(-1.0 / u);
    let b = exp(-1.0 / (1.0 - u));
    return g * a / (a + b);
}

// One workgroup row per item (y, then z when the items exceed one dimension), slots along
// x (strided when an item is longer than one dimension's workgroups).
@compute @workgroup_size(64)
fn scatter(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let n = wg.z * groups.y + wg.y;
    if (n >= arrayLength(&items)) {
        return;
    }
    let it = items[n];
    for (var q = wg.x * 64u + local; q < it.m; q += groups.x * 64u) {
        scatter_one(it, q);
    }
}

fn scatter_one(it: Item, q: u32) {
    // The bin that lands on slot q: m = lo + ((q − (lo − c)) mod M), if inside the band.
    let first = (it.lo + it.m - it.centre % it.m) % it.m;  // slot of bin lo
    let d = (q + it.m - first) % it.m;
    let bin = it.lo + d;
    var v = vec2<f32>(0.0, 0.0);
    if (bin <= it.hi) {
        let w = it.norm * psi(it.scale, f32(bin) * it.df);
        v = spectrum[it.spec + d] * w;
    }
    data[it.data + q] = v;
}

// One workgroup row per item (y, then z), coarse steps along x (strided, as in scatter).
@compute @workgroup_size(64)
fn power_grid(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let n = wg.z * groups.y + wg.y;
    if (n >= arrayLength(&items)) {
        return;
    }
    let it = items[n];
    for (var j = wg.x * 64u + local; j < it.steps; j += groups.x * 64u) {
        power_one(it, j);
    }
}

fn power_one(it: Item, j: u32) {
    let i = index[it.positions + j];
    let u = frac[it.positions + j];
    let w0 = -u * (u - 1.0) * (u - 2.0) / 6.0;
    let w1 = (u + 1.0) * (u - 1.0) * (u - 2.0) / 2.0;
    let w2 = -(u + 1.0) * u * (u - 2.0) / 2.0;
    let w3 = (u + 1.0) * u * (u - 1.0) / 6.0;
    let m = it.m;
    let v = data[it.data + (i + m - 1u) % m] * w0 + data[it.data + i % m] * w1
          + data[it.data + (i + 1u) % m] * w2 + data[it.data + (i + 2u) % m] * w3;
    power[it.power + j] = dot(v, v);
}
