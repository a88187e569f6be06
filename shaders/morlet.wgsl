// The complex Morlet wavelet's spectrum in `real` (src/transform/mod.rs, Morlet::spectrum),
// shared by scales.wgsl and refine.wgsl: the host (src/gpu/morlet.rs) appends this file to
// each before it sets `real`, and fills the `wavelet` uniform at binding 0. With it, what
// else both stages share: the bin weights an item holds, and the cubic interpolation weights.

struct Wavelet {
    bandwidth: vec2<f32>, // f_b as hi + lo (the pair holds f64 to 48 bits)
    centre: vec2<f32>,    // f_c as hi + lo
    taper: vec2<f32>,     // Ψ is brought to 0 below taper·centre/s by a C∞ step; hi + lo
    _pad0: u32,
    _pad1: u32,
};

@group(0) @binding(0) var<uniform> wavelet: Wavelet;

const PI_R: real = 3.141592653589793;

// A value held as two f32 (hi + lo), in `real`.
fn pair(v: vec2<f32>) -> real {
    return real(v.x) + real(v.y);
}

// e^x for x ≤ 0 in `real` (WGSL has no f64 exp): x = k ln 2 + r with |r| ≤ ln 2 / 2, a
// degree-13 Taylor polynomial for e^r (error below 1e-16 there), scaled by 2^k.
fn exp_real(x: real) -> real {
    let k = round(x * real(1.4426950408889634));
    // ln 2 in two parts, the first with trailing zero bits, so that k·LN2_HI is exact.
    let r = (x - k * real(0.693145751953125)) - k * real(1.4286068203094172e-6);
    var p = real(1.0 / 6227020800.0);
    p = p * r + real(1.0 / 479001600.0);
    p = p * r + real(1.0 / 39916800.0);
    p = p * r + real(1.0 / 3628800.0);
    p = p * r + real(1.0 / 362880.0);
    p = p * r + real(1.0 / 40320.0);
    p = p * r + real(1.0 / 5040.0);
    p = p * r + real(1.0 / 720.0);
    p = p * r + real(1.0 / 120.0);
    p = p * r + real(1.0 / 24.0);
    p = p * r + real(1.0 / 6.0);
    p = p * r + real(0.5);
    p = p * r + real(1.0);
    p = p * r + real(1.0);
    if (k < real(-1000.0)) {
        return real(0.0);
    }
    return ldexp(p, i32(k));
}

// What weighs one scale's spectrum bins, as f32 pairs (hi + lo; scalars, so that the
// struct keeps both stages' items at 4-byte alignment): the scale s (s), the bin spacing
// of the padded spectrum (Hz) and norm = 2/L. Each stage's `Item` holds one.
struct BinWeights {
    scale_hi: f32,
    scale_lo: f32,
    df_hi: f32,
    df_lo: f32,
    norm_hi: f32,
    norm_lo: f32,
};

// The bin spacing (Hz) of `b`, in `real`.
fn bin_df(b: BinWeights) -> real {
    return pair(vec2<f32>(b.df_hi, b.df_lo));
}

// The weight norm·Ψ(s·f_m) of spectrum bin m: what both stages' scatters multiply X[m] by.
fn bin_weight(bin: u32, b: BinWeights) -> real {
    let scale = pair(vec2<f32>(b.scale_hi, b.scale_lo));
    return pair(vec2<f32>(b.norm_hi, b.norm_lo)) * psi(scale, real(bin) * bin_df(b));
}

// The cubic Lagrange weights of the four samples at −1, 0, 1, 2 for a value at u ∈ [0, 1):
// how both stages read their decimated sequences between samples.
fn cubic_weights(u: real) -> vec4<real> {
    let one = real(1.0);
    let two = real(2.0);
    return vec4<real>(
        -u * (u - one) * (u - two) / real(6.0),
        (u + one) * (u - one) * (u - two) / two,
        -(u + one) * u * (u - two) / two,
        (u + one) * u * (u - one) / real(6.0),
    );
}

// Ψ(s·f): the Morlet spectrum at scale s (s) and frequency f (Hz).
fn psi(scale: real, f: real) -> real {
    let x = scale * f;
    if (x <= real(0.0)) {
        return real(0.0);
    }
    let centre = pair(wavelet.centre);
    let d = x - centre;
    let g = exp_real(-PI_R * PI_R * pair(wavelet.bandwidth) * d * d);
    let u = x / (pair(wavelet.taper) * centre);
    if (u >= real(1.0)) {
        return g;
    }
    let a = exp_real(real(-1.0) / u);
    let b = exp_real(real(-1.0) / (real(1.0) - u));
    return g * a / (a + b);
}
