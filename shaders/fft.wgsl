// One pass of a batched, out-of-place Stockham autosort FFT, mixed radix 2, 3, 4 and 5.
//
// A transform of length n = R1·R2·…·Rp takes p passes; pass i has radix R = Ri and
// ns = R1·…·R(i-1) (1 for the first). Each invocation reads R values n/R apart, twists
// them by e^{∓j2π i k/(ns R)} (k = j mod ns), takes their R-point DFT and writes the
// results ns apart at (j/ns)·ns·R + k — so that after the last pass the output is in
// natural order (no bit reversal). Govindaraju et al., "High performance discrete Fourier
// transforms on graphics processors" (SC 2008), with the radix per pass.
//
// Every root of unity comes from one table of e^{-j2πm/n}, m < n, computed on the host in
// double precision (f32 sin/cos of large angles on a GPU would cost accuracy); a table past
// 65 536 roots is expanded on the device from about 2·√n of them (`expand_roots`, below).
// The inverse is unnormalised, as rustfft's.
//
// `real` is f32; the host compiles a second copy with `alias real = f64;` (wgpu's
// SHADER_F64) for transforms whose quiet stretches f32 cannot resolve (src/gpu/fft.rs).

alias real = f32;

struct Pass {
    n: u32,        // transform length
    radix: u32,    // this pass's radix R (2..5)
    ns: u32,       // product of the earlier passes' radices
    batch: u32,    // transforms held back to back in the buffers
    inverse: u32,  // 1: e^{+j...}
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
};

@group(0) @binding(0) var<uniform> pass_: Pass;
@group(0) @binding(1) var<storage, read> src: array<vec2<real>>;
@group(0) @binding(2) var<storage, read_write> dst: array<vec2<real>>;
@group(0) @binding(3) var<storage, read> roots: array<vec2<real>>;

fn cmul(a: vec2<real>, b: vec2<real>) -> vec2<real> {
    return vec2<real>(a.x * b.x - a.y * b.y, a.x * b.y + a.y * b.x);
}

// e^{∓j2π m/n} (minus for the forward transform).
fn root(m: u32) -> vec2<real> {
    let w = roots[m % pass_.n];
    if (pass_.inverse == 1u) {
        return vec2<real>(w.x, -w.y);
    }
    return w;
}

@compute @workgroup_size(64)
fn stockham_pass(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let r = pass_.radix;
    let per = pass_.n / r;
    let id = ((wg.z * groups.y + wg.y) * groups.x + wg.x) * 64u + local;
    if (id >= per * pass_.batch) {
        return;
    }
    let base = (id / per) * pass_.n;
    let j = id % per;
    let ns = pass_.ns;
    let k = j % ns;
    // e^{∓j2π i k/(ns R)} = root(i·k·n/(ns R)); i·k·n/(ns R) < n, no overflow.
    let twist = pass_.n / (ns * r);
    var v: array<vec2<real>, 5>;
    for (var i = 0u; i < r; i = i + 1u) {
        v[i] = cmul(src[base + j + i * per], root(i * k * twist));
    }
    // The R-point DFT; ω_R^{qi} = root((qi mod R)·n/R).
    let out = base + (j / ns) * ns * r + k;
    for (var q = 0u; q < r; q = q + 1u) {
        var acc = v[0];
        for (var i = 1u; i < r; i = i + 1u) {
            acc = acc + cmul(v[i], root(((q * i) % r) * per));
        }
        dst[out + q * ns] = acc;
    }
}

// A long root table from two short ones, so that the host computes and uploads about
// 2·√n roots instead of n (a long record's tables were 87 MB): `src` holds e^{-j2πr/n}
// for r < B (B = pass_.ns, a power of two), then e^{-j2πqB/n} for q < ⌈n/B⌉, and
// e^{-j2πm/n} = e^{-j2π(m mod B)/n}·e^{-j2π⌊m/B⌋B/n}. Where either factor is 1 (m < B, or
// m a multiple of B) the product is the host's root exactly; elsewhere within a couple of
// ulps of it (two rounded factors, one rounded product).
@compute @workgroup_size(64)
fn expand_roots(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let m = ((wg.z * groups.y + wg.y) * groups.x + wg.x) * 64u + local;
    if (m >= pass_.n) {
        return;
    }
    let b = pass_.ns;
    dst[m] = cmul(src[b + m / b], src[m % b]);
}
