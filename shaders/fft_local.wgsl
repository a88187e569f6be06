// Whole transforms in workgroup memory: one workgroup per sequence, every Stockham pass
// of `fft.wgsl` (same radices, twiddles, output order and roots table) run between
// barriers on the sequence held in `sh`, so that the data crosses global memory twice (in
// and out) instead of twice a pass. For lengths up to CAP, which the host sets from the
// adapter's workgroup storage (`src/gpu/fft.rs`, which compiles a few capacities so that
// short sequences reserve less); longer ones take `fft.wgsl`'s passes. The host turns off
// wgpu's zeroing of `sh`: every value is written before it is read.
//
// In a pass each invocation first reads and twists the R inputs of its butterflies into
// registers, then, after a barrier, writes their R outputs: one buffer suffices because no
// write happens before every read of the pass has. The result overwrites the input.
//
// `real` is f32; the host compiles an f64 copy as for `fft.wgsl`.

alias real = f32;

// Complex values one workgroup holds, and values one invocation holds in a pass
// (ceil(CAP / WG) + 4 covers ceil(n / (R·WG))·R for every n ≤ CAP and R ≤ 5); both set by
// the host.
const CAP: u32 = 1024u;
const MAXV: u32 = 8u;
const WG: u32 = 256u;

struct Local {
    n: u32,        // transform length
    batch: u32,    // transforms held back to back in `data`
    inverse: u32,  // 1: e^{+j...}
    passes: u32,   // radix passes
    radix: array<vec4<u32>, 4>,  // radix of pass s at radix[s / 4][s % 4]
};

@group(0) @binding(0) var<uniform> p: Local;
@group(0) @binding(1) var<storage, read_write> data: array<vec2<real>>;
@group(0) @binding(2) var<storage, read> roots: array<vec2<real>>;

var<workgroup> sh: array<vec2<real>, CAP>;

fn cmul(a: vec2<real>, b: vec2<real>) -> vec2<real> {
    return vec2<real>(a.x * b.x - a.y * b.y, a.x * b.y + a.y * b.x);
}

// e^{∓j2π m/n} (minus for the forward transform).
fn root(m: u32) -> vec2<real> {
    let w = roots[m % p.n];
    if (p.inverse == 1u) {
        return vec2<real>(w.x, -w.y);
    }
    return w;
}

@compute @workgroup_size(256)
fn local_fft(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    // The sequence is the workgroup's: the same for every invocation, so the barriers
    // below stay in uniform control flow.
    let t = (wg.z * groups.y + wg.y) * groups.x + wg.x;
    if (t >= p.batch) {
        return;
    }
    let n = p.n;
    let base = t * n;
    for (var i = local; i < n; i = i + WG) {
        sh[i] = data[base + i];
    }
    workgroupBarrier();
    var ns = 1u;
    // Declared once: a `var` is zeroed where it is declared.
    var v: array<vec2<real>, MAXV>;
    for (var s = 0u; s < p.passes; s = s + 1u) {
        let r = p.radix[s / 4u][s % 4u];
        let per = n / r;
        // e^{∓j2π i k/(ns R)} = root(i·k·n/(ns R)), as in fft.wgsl.
        let twist = n / (ns * r);
        var c = 0u;
        for (var j = local; j < per; j = j + WG) {
            let k = j % ns;
            for (var i = 0u; i < r; i = i + 1u) {
                v[c + i] = cmul(sh[j + i * per], root(i * k * twist));
            }
            c = c + r;
        }
        workgroupBarrier();
        c = 0u;
        for (var j = local; j < per; j = j + WG) {
            let k = j % ns;
            let out = (j / ns) * ns * r + k;
            for (var q = 0u; q < r; q = q + 1u) {
                var acc = v[c];
                for (var i = 1u; i < r; i = i + 1u) {
                    acc = acc + cmul(v[c + i], root(((q * i) % r) * per));
                }
                sh[out + q * ns] = acc;
            }
            c = c + r;
        }
        workgroupBarrier();
        ns = ns * r;
    }
    for (var i = local; i < n; i = i + WG) {
        data[base + i] = sh[i];
    }
}
