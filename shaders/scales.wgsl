// Band-limited complex-Morlet scales for a batch of runs (host: src/gpu/scales.rs).
//
// `scatter`: for each item (one run × one scale) fills its length-M buffer with the
// weighted, demodulated pass band: slot (m − c) mod M gets 2·X[m]·Ψ(s·f_m)/L for the bins
// m = lo..=hi, every other slot 0 — the input of the item's inverse FFT, whose output is
// the baseband w[q] = W(t_q)·e^{-j2π c t_q/L} at the decimated times t_q = q·L/M
// (src/transform/band.rs explains why this is exact).
//
// `power`: |W|² on the coarse time grid by cubic Lagrange interpolation of the periodic
// baseband sequence, at positions the host computed in f64 (f32 cannot hold j·h·M/L),
// their fractions as f32 pairs.
//
// `noise_gain`: each item's Σ_m (2Ψ(s·f_m)/L)² over its pass band, W's variance per unit
// of white-noise variance and sample (the host's `ScalePlan::noise_gain`), which turns the
// scale's noise median into the white-noise floor. Computed here, from the same weights
// the scatter applies, so that the worker completing a track does not evaluate Ψ over
// every bin of every scale again (about 0.2 ms a 30 000-sample signal at 128 scales).
//
// Precision: the spectrum, Ψ (morlet.wgsl), the FFTs (fft.wgsl) and the interpolation are
// in `real`, which the host sets to f64 where the adapter has SHADER_F64; |W|² goes to the
// ridge as f32. An f32 FFT's rounding is relative to the whole sequence: where a loud
// stretch shares a scale with quiet ones (a hammer's ring-down, a sweep's silent lead-in),
// the quiet steps' |W|² are wrong by up to tens of per cent, and with them the ridge there
// and the noise floor (the median), so that the CPU and GPU backends decided differently.

alias real = f32;

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
    gain: u32,      // index of the item's noise gain in `gains`
    weights: BinWeights, // s, the bin spacing and 2/L (morlet.wgsl)
};

// Binding 0, the `wavelet` uniform, and Ψ are in morlet.wgsl.
@group(0) @binding(1) var<storage, read> items: array<Item>;
@group(0) @binding(2) var<storage, read> spectrum: array<vec2<real>>;
@group(0) @binding(3) var<storage, read_write> data: array<vec2<real>>;
@group(0) @binding(4) var<storage, read_write> power: array<f32>;
@group(0) @binding(5) var<storage, read> index: array<u32>;
@group(0) @binding(6) var<storage, read> frac: array<vec2<f32>>;  // hi + lo
@group(0) @binding(7) var<storage, read_write> gains: array<vec2<f32>>;  // hi + lo

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
    var v = vec2<real>(real(0.0), real(0.0));
    if (bin <= it.hi) {
        v = spectrum[it.spec + d] * bin_weight(bin, it.weights);
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
    let w = cubic_weights(pair(frac[it.positions + j]));
    let m = it.m;
    let v = data[it.data + (i + m - 1u) % m] * w.x + data[it.data + i % m] * w.y
          + data[it.data + (i + 1u) % m] * w.z + data[it.data + (i + 2u) % m] * w.w;
    power[it.power + j] = f32(dot(v, v));
}

// Each invocation's share of an item's noise gain, summed in a tree.
var<workgroup> gain_sums: array<real, 64>;

// One workgroup per item (y, then z; one along x): its bins strided over the invocations,
// the 64 partial sums added pairwise, written as an f32 pair (hi + lo: 48 bits of an f64).
@compute @workgroup_size(64)
fn noise_gain(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let n = wg.z * groups.y + wg.y;
    // Uniform across the workgroup (its id and the array's length), so the barriers
    // below stay in uniform control flow.
    if (n >= arrayLength(&items)) {
        return;
    }
    let it = items[n];
    var acc = real(0.0);
    // hi < lo (a band past the spectrum's end) sums nothing: the gain is 0, as on the host.
    for (var bin = it.lo + local; bin <= it.hi; bin += 64u) {
        let w = bin_weight(bin, it.weights);
        acc += w * w;
    }
    gain_sums[local] = acc;
    workgroupBarrier();
    for (var half = 32u; half > 0u; half = half >> 1u) {
        if (local < half) {
            gain_sums[local] = gain_sums[local] + gain_sums[local + half];
        }
        workgroupBarrier();
    }
    if (local == 0u) {
        let g = gain_sums[0];
        let hi = f32(g);
        gains[it.gain] = vec2<f32>(hi, f32(g - real(hi)));
    }
}
