//! Band-limited evaluation of one wavelet scale.
//!
//! W(s, t) = (1/L) Σ_m 2 X[m] Ψ(s f_m) e^{j2π m t / L} has non-negligible terms only for the
//! bins m where Ψ(s f_m) exceeds [`SPECTRUM_TOLERANCE`](super::SPECTRUM_TOLERANCE). Shifting
//! those bins down by a centre bin c and placing them in a buffer of length M ≪ L gives,
//! after one inverse FFT of length M, the *baseband* values w[n] = W(t_n) e^{-j2π c t_n / L}
//! at the decimated times t_n = n L / M — exactly, not approximately, because everything
//! left out is below tolerance. The magnitude and the ratios W'/W, W''/W (what the ridge
//! and skeleton need) do not depend on the demodulation, so baseband values serve directly.

use std::f64::consts::PI;

use num_complex::Complex64;

use super::{complex_plan, fast_len, Morlet, Spectrum, SPECTRUM_TOLERANCE};

/// Which time derivative of W a call evaluates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Derivative {
    /// W itself.
    Zero,
    /// ∂W/∂t (1/s).
    First,
    /// ∂²W/∂t² (1/s²).
    Second,
}

/// The bins and decimated length for one scale.
#[derive(Debug, Clone)]
pub struct ScalePlan {
    /// Scale s (s).
    pub scale: f64,
    /// Centre frequency of the pass band, f_c/s (Hz).
    pub freq: f64,
    lo: usize,
    hi: usize,
    centre_bin: usize,
    /// Decimated length M.
    pub len: usize,
}

impl ScalePlan {
    /// Plans scale `s` for `spec`, with the decimated rate `oversample` × the pass band.
    pub fn new(spec: &Spectrum, wavelet: &Morlet, s: f64, oversample: f64) -> ScalePlan {
        let l = spec.padded_len;
        let df = spec.sample_rate / l as f64;
        let (f_lo, f_hi) = wavelet.band(s, SPECTRUM_TOLERANCE);
        let lo = ((f_lo / df).ceil() as usize).max(1);
        let hi = ((f_hi / df).floor() as usize).min(l / 2);
        let freq = wavelet.centre / s;
        let centre_bin = ((freq / df).round() as usize).clamp(lo, hi.max(lo));
        let width = if hi >= lo { hi - lo + 1 } else { 0 };
        let reach = (centre_bin - lo.min(centre_bin)).max(hi.saturating_sub(centre_bin));
        let need = ((width as f64 * oversample).ceil() as usize).max(2 * reach + 2);
        let len = fast_len(need.max(16)).min(l);
        ScalePlan {
            scale: s,
            freq,
            lo,
            hi,
            centre_bin,
            len,
        }
    }

    /// Padded samples between consecutive decimated values, L / M.
    pub fn step(&self, spec: &Spectrum) -> f64 {
        spec.padded_len as f64 / self.len as f64
    }

    /// Phase (rad) that turns a baseband value at padded sample time `t` back into W:
    /// W(t) = w(t) e^{j carrier(t)}.
    pub fn carrier(&self, spec: &Spectrum, t: f64) -> f64 {
        2.0 * PI * self.centre_bin as f64 * t / spec.padded_len as f64
    }

    /// Number of bins inside the pass band.
    pub fn bins(&self) -> usize {
        if self.hi >= self.lo {
            self.hi - self.lo + 1
        } else {
            0
        }
    }

    /// Σ_m (2Ψ/L)²: for white noise of variance σ² per sample over N samples, the variance
    /// of W at this scale is σ² N × this.
    pub fn noise_gain(&self, spec: &Spectrum, wavelet: &Morlet) -> f64 {
        let l = spec.padded_len as f64;
        (self.lo..=self.hi)
            .map(|m| {
                let g = 2.0 * wavelet.spectrum(self.scale, spec.bin_freq(m)) / l;
                g * g
            })
            .sum()
    }

    /// Baseband values of W (or a time derivative) at the decimated times t_n = n L/M.
    pub fn evaluate(
        &self,
        spec: &Spectrum,
        wavelet: &Morlet,
        derivative: Derivative,
        buf: &mut Vec<Complex64>,
    ) -> Decimated {
        let m_len = self.len;
        buf.clear();
        buf.resize(m_len, Complex64::new(0.0, 0.0));
        let norm = 2.0 / spec.padded_len as f64;
        for m in self.lo..=self.hi.min(spec.bins.len() - 1) {
            let f = spec.bin_freq(m);
            let g = norm * wavelet.spectrum(self.scale, f);
            let v = spec.bins[m] * g;
            let v = match derivative {
                Derivative::Zero => v,
                Derivative::First => v * Complex64::new(0.0, 2.0 * PI * f),
                Derivative::Second => v * (-(2.0 * PI * f).powi(2)),
            };
            let idx = (m as isize - self.centre_bin as isize).rem_euclid(m_len as isize) as usize;
            buf[idx] += v;
        }
        complex_plan(m_len, true).process(buf);
        Decimated {
            step: self.step(spec),
            values: buf.clone(),
        }
    }
}

/// A baseband sequence on the decimated grid t_n = n × step (padded samples), periodic.
#[derive(Debug, Clone)]
pub struct Decimated {
    /// Padded samples per value.
    pub step: f64,
    /// Values.
    pub values: Vec<Complex64>,
}

impl Decimated {
    /// Value at padded sample time `t` by cubic Lagrange interpolation (the baseband content
    /// near a ridge sits close to zero frequency, where four points are ample).
    #[inline]
    pub fn at(&self, t: f64) -> Complex64 {
        interpolate(&self.values, t / self.step)
    }
}

/// Cubic Lagrange interpolation of a periodic sequence at fractional index `x`.
#[inline]
pub fn interpolate(v: &[Complex64], x: f64) -> Complex64 {
    let n = v.len() as isize;
    let i = x.floor();
    let u = x - i;
    let i = i as isize;
    let at = |k: isize| v[(i + k).rem_euclid(n) as usize];
    let w0 = -u * (u - 1.0) * (u - 2.0) / 6.0;
    let w1 = (u + 1.0) * (u - 1.0) * (u - 2.0) / 2.0;
    let w2 = -(u + 1.0) * u * (u - 2.0) / 2.0;
    let w3 = (u + 1.0) * u * (u - 1.0) / 6.0;
    at(-1) * w0 + at(0) * w1 + at(1) * w2 + at(2) * w3
}
