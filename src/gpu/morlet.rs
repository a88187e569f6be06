//! Host side of `shaders/morlet.wgsl`, the Morlet spectrum Ψ in `real` that the first pass
//! (`scales.wgsl`) and the refinement (`refine.wgsl`) weigh each bin with: the source of a
//! stage with it appended, and its `wavelet` uniform.

use super::Real;
use crate::transform::{Morlet, TAPER};

/// `shaders/morlet.wgsl`.
const WGSL: &str = include_str!("../../shaders/morlet.wgsl");

/// A stage's shader with `morlet.wgsl` appended, in precision `real` ([`Real::source`]).
pub fn source(real: Real, stage_wgsl: &str) -> String {
    real.source(&format!("{stage_wgsl}\n{WGSL}"))
}

/// `x` as two f32 whose sum holds it to 48 bits (the shader's `pair`).
pub fn split(x: f64) -> [f32; 2] {
    let hi = x as f32;
    [hi, (x - f64::from(hi)) as f32]
}

/// The shader's `BinWeights`: what weighs one scale's spectrum bins, as f32 pairs. Each
/// stage's item holds one.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct BinWeights {
    scale: [f32; 2],
    df: [f32; 2],
    norm: [f32; 2],
}

impl BinWeights {
    /// Scale `scale` (s) of a spectrum of `sample_rate` (Hz) padded to `padded_len` samples.
    pub fn new(scale: f64, sample_rate: f64, padded_len: usize) -> BinWeights {
        Self::scaled(scale, sample_rate, padded_len, 1.0)
    }

    /// [`new`](Self::new) with every weight times `factor` (a power of two, so that the
    /// pair holds it exactly): what scaling the spectrum by it would give.
    pub fn scaled(scale: f64, sample_rate: f64, padded_len: usize, factor: f64) -> BinWeights {
        BinWeights {
            scale: split(scale),
            df: split(sample_rate / padded_len as f64),
            norm: split(2.0 / padded_len as f64 * factor),
        }
    }
}

/// The shader's `Wavelet` uniform: f_b, f_c and the taper as f32 pairs (hi + lo).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct WaveletParams {
    bandwidth: [f32; 2],
    centre: [f32; 2],
    taper: [f32; 2],
    /// A uniform's size is a multiple of 16 bytes.
    _pad: [u32; 2],
}

impl WaveletParams {
    /// The uniform for `wavelet`.
    pub fn new(wavelet: &Morlet) -> WaveletParams {
        WaveletParams {
            bandwidth: split(wavelet.bandwidth),
            centre: split(wavelet.centre),
            taper: split(TAPER),
            _pad: [0; 2],
        }
    }
}
