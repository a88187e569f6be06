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

use super::{complex_plan, plan_len, Morlet, Spectrum, SPECTRUM_TOLERANCE};

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
    /// Bin spacing of the padded spectrum (Hz).
    bin_hz: f64,
    /// Decimated length M.
    pub len: usize,
}

impl ScalePlan {
    /// Plans scale `s` for `spec`, with the decimated rate `oversample` × the pass band,
    /// demodulated by the wavelet's centre frequency (baseband content near zero).
    pub fn new(spec: &Spectrum, wavelet: &Morlet, s: f64, oversample: f64) -> ScalePlan {
        Self::with_tolerance(spec, wavelet, s, oversample, SPECTRUM_TOLERANCE)
    }

    /// As [`new`](Self::new), with the pass band cut where Ψ falls below `tolerance`
    /// instead of [`SPECTRUM_TOLERANCE`]: fewer bins for a coarse look (values then carry a
    /// relative error of order `tolerance`).
    pub fn with_tolerance(
        spec: &Spectrum,
        wavelet: &Morlet,
        s: f64,
        oversample: f64,
        tolerance: f64,
    ) -> ScalePlan {
        let l = spec.padded_len;
        let df = spec.sample_rate / l as f64;
        let (f_lo, f_hi) = wavelet.band(s, tolerance);
        let lo = ((f_lo / df).ceil() as usize).max(1);
        let hi = ((f_hi / df).floor() as usize).min(l / 2);
        let freq = wavelet.centre / s;
        let centre_bin = ((freq / df).round() as usize).clamp(lo, hi.max(lo));
        let width = if hi >= lo { hi - lo + 1 } else { 0 };
        let reach = (centre_bin - lo.min(centre_bin)).max(hi.saturating_sub(centre_bin));
        let need = ((width as f64 * oversample).ceil() as usize).max(2 * reach + 2);
        let len = plan_len(need.max(16)).min(l);
        ScalePlan {
            scale: s,
            freq,
            lo,
            hi,
            centre_bin,
            bin_hz: df,
            len,
        }
    }

    /// The pass band's first and last bins and the demodulation bin (lo, hi, c).
    pub fn band(&self) -> (usize, usize, usize) {
        (self.lo, self.hi, self.centre_bin)
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

    /// The demodulation bin's angular frequency (rad/s): W′/W = w′/w + j·this for the
    /// baseband w of a transform whose derivatives are taken at f − f_c.
    pub fn carrier_rate(&self) -> f64 {
        2.0 * PI * self.bin_hz * self.centre_bin as f64
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
        Self::gain_of(spec, &self.weights(spec, wavelet))
    }

    /// Baseband values of W at the decimated times t_n = n L/M.
    pub fn evaluate(&self, spec: &Spectrum, wavelet: &Morlet) -> Decimated {
        let mut values = Vec::new();
        let weighted = self.weighted(spec, &self.weights(spec, wavelet));
        self.inverse(&weighted, 0, &mut values);
        Decimated {
            step: self.step(spec),
            values,
        }
    }

    /// The baseband values of W written into `buf` (reused across scales), and the noise
    /// gain of [`noise_gain`](Self::noise_gain), from one evaluation of the spectrum.
    pub fn evaluate_into(
        &self,
        spec: &Spectrum,
        wavelet: &Morlet,
        buf: &mut Vec<Complex64>,
    ) -> f64 {
        let psi = self.weights(spec, wavelet);
        self.inverse(&self.weighted(spec, &psi), 0, buf);
        Self::gain_of(spec, &psi)
    }

    /// Baseband values of W, ∂W/∂t (1/s) and ∂²W/∂t² (1/s²) at the decimated times (the
    /// wavelet's spectrum evaluated once for the three).
    pub fn evaluate_with_derivatives(&self, spec: &Spectrum, wavelet: &Morlet) -> [Decimated; 3] {
        let weighted = self.weighted(spec, &self.weights(spec, wavelet));
        [0, 1, 2].map(|order| {
            let mut values = Vec::new();
            self.inverse(&weighted, order, &mut values);
            Decimated {
                step: self.step(spec),
                values,
            }
        })
    }

    /// Ψ(s f_m) over the pass band.
    fn weights(&self, spec: &Spectrum, wavelet: &Morlet) -> Vec<f64> {
        let hi = self.hi.min(spec.bin_count() - 1);
        let mut psi = Vec::with_capacity(self.bins());
        if hi >= self.lo {
            let df = spec.sample_rate / spec.padded_len as f64;
            wavelet.spectrum_run(self.scale, self.lo, df, hi - self.lo + 1, &mut psi);
        }
        psi
    }

    fn gain_of(spec: &Spectrum, psi: &[f64]) -> f64 {
        let k = 2.0 / spec.padded_len as f64;
        psi.iter().map(|g| (k * g) * (k * g)).sum()
    }

    /// 2 X Ψ / L over the pass band.
    fn weighted(&self, spec: &Spectrum, psi: &[f64]) -> Vec<Complex64> {
        let norm = 2.0 / spec.padded_len as f64;
        spec.bins(self.lo..self.lo + psi.len())
            .iter()
            .zip(psi)
            .map(|(x, g)| x * (norm * g))
            .collect()
    }

    /// The demodulated inverse FFT of the weighted bins times (j2πf)^order, into `out`.
    fn inverse(&self, weighted: &[Complex64], order: i32, out: &mut Vec<Complex64>) {
        let m_len = self.len;
        out.clear();
        out.resize(m_len, Complex64::new(0.0, 0.0));
        let df = self.bin_hz;
        // Bin m lands at (m - c) mod M; a band wider than M folds onto itself (only when
        // the plan is capped at the padded length, where the fold is the identity).
        let mut idx =
            (self.lo as isize - self.centre_bin as isize).rem_euclid(m_len as isize) as usize;
        for (k, &v) in weighted.iter().enumerate() {
            let omega = 2.0 * PI * df * (self.lo + k) as f64;
            out[idx] += match order {
                0 => v,
                1 => Complex64::new(-omega * v.im, omega * v.re),
                _ => v * (-omega * omega),
            };
            idx += 1;
            if idx == m_len {
                idx = 0;
            }
        }
        complex_plan(m_len, true).process(out);
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

/// The spectrum bins that the pass bands of `plans` read, in a spectrum of `bins` bins:
/// the first and how many, from the lowest band's first bin to the highest band's last
/// (clamped to the spectrum; none where every band lies past its end). A GPU upload of a
/// record's spectrum holds just these.
pub fn covered<'a>(plans: impl IntoIterator<Item = &'a ScalePlan>, bins: usize) -> (usize, usize) {
    let last = bins.saturating_sub(1);
    let (lo, hi) = plans.into_iter().fold((usize::MAX, 0), |(l, h), p| {
        (l.min(p.lo), h.max(p.hi.min(last)))
    });
    if bins == 0 || lo > hi {
        (0, 0)
    } else {
        (lo, hi + 1 - lo)
    }
}

/// Cubic Lagrange interpolation of a periodic sequence at fractional index `x`.
#[inline]
pub fn interpolate(v: &[Complex64], x: f64) -> Complex64 {
    Taps::new(v.len(), x).apply(v)
}

/// Where cubic Lagrange interpolation at a fractional index reads a periodic sequence, and
/// with which weights: found once for sequences of one length read at the same index (W,
/// W′ and W″ of a scale). The interpolation sits in the CPU backend's innermost loops (the
/// first pass's every step of every scale, the refinement's every grid point): `floor`,
/// which the baseline x86-64 target has no instruction for, and a remainder per tap (four
/// integer divisions) were a tenth of that backend's time.
#[derive(Debug, Clone, Copy)]
pub struct Taps {
    at: [usize; 4],
    w: [f64; 4],
}

impl Taps {
    /// The taps at fractional index `x` of a sequence of `n` values (indices wrap around).
    #[inline]
    pub fn new(n: usize, x: f64) -> Taps {
        let i = super::exact_floor(x);
        let u = x - i;
        let i = i as isize;
        // Inside the sequence, as nearly every read is, the taps need no wrapping, and the
        // remainder (a 64-bit division, tens of cycles) is for the reads near its ends.
        // (`i < n − 2` rather than `i + 2 < n`: an x of 2^63 or more saturates `i`.)
        let at = if i >= 1 && i < n as isize - 2 {
            let first = (i - 1) as usize;
            [first, first + 1, first + 2, first + 3]
        } else {
            // Wrapping as a release build always did: an x of −2^63 or less saturates `i`.
            let first = i.wrapping_sub(1).rem_euclid(n as isize) as usize;
            let next = |k: usize| if k + 1 == n { 0 } else { k + 1 };
            let a1 = next(first);
            let a2 = next(a1);
            [first, a1, a2, next(a2)]
        };
        Taps {
            at,
            w: [
                -u * (u - 1.0) * (u - 2.0) / 6.0,
                (u + 1.0) * (u - 1.0) * (u - 2.0) / 2.0,
                -(u + 1.0) * u * (u - 2.0) / 2.0,
                (u + 1.0) * u * (u - 1.0) / 6.0,
            ],
        }
    }

    /// The interpolated value of `v` (of the length the taps were found for).
    #[inline]
    pub fn apply(&self, v: &[Complex64]) -> Complex64 {
        let [a0, a1, a2, a3] = self.at;
        let [w0, w1, w2, w3] = self.w;
        v[a0] * w0 + v[a1] * w1 + v[a2] * w2 + v[a3] * w3
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transform::naive;

    /// The taps against the interpolation written out with `floor` and a remainder per
    /// tap, bit for bit: indices on both sides of zero, past the end, sequences shorter
    /// than the four taps; and positions so far out that the index saturates, or not a
    /// number, which must not panic.
    #[test]
    fn taps_are_the_written_out_interpolation_to_the_bit() {
        let reference = |v: &[Complex64], x: f64| {
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
        };
        for n in [1usize, 2, 3, 4, 5, 17, 1000] {
            let v: Vec<Complex64> = (0..n)
                .map(|k| Complex64::new((0.7 * k as f64).sin(), (1.3 * k as f64).cos()))
                .collect();
            let mut x = -3.0 * n as f64 - 0.37;
            while x < 3.0 * n as f64 {
                for x in [x, x.floor(), -0.0] {
                    let (a, b) = (interpolate(&v, x), reference(&v, x));
                    assert_eq!(
                        (a.re.to_bits(), a.im.to_bits()),
                        (b.re.to_bits(), b.im.to_bits()),
                        "n {n}, x {x}"
                    );
                }
                x += 0.173;
            }
            // Far out of range or not a number (the index saturates): no panic, and a NaN
            // where the fraction is one.
            for x in [
                f64::INFINITY,
                f64::NEG_INFINITY,
                f64::NAN,
                1e300,
                -1e300,
                9.3e18,
            ] {
                let a = interpolate(&v, x);
                assert_eq!(a.re.is_nan(), !x.is_finite(), "n {n}, x {x}");
            }
        }
    }

    /// W at a fractional padded time by the defining sum over every positive bin.
    fn direct(spec: &Spectrum, w: &Morlet, s: f64, t: f64) -> Complex64 {
        direct_derivative(spec, w, s, t, 0)
    }

    /// ∂^order W/∂t^order by the defining sum.
    fn direct_derivative(spec: &Spectrum, w: &Morlet, s: f64, t: f64, order: i32) -> Complex64 {
        let l = spec.padded_len as f64;
        spec.all_bins()
            .iter()
            .enumerate()
            .skip(1)
            .map(|(m, b)| {
                let g = 2.0 * w.spectrum(s, spec.bin_freq(m)) / l;
                let jw = Complex64::new(0.0, 2.0 * PI * spec.bin_freq(m)).powi(order);
                b * g * jw * Complex64::from_polar(1.0, 2.0 * PI * m as f64 * t / l)
            })
            .sum()
    }

    #[test]
    fn band_limited_values_equal_the_full_transform() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let fs = 200.0;
        let x: Vec<f64> = (0..3001).map(|_| rng.random_range(-1.0..1.0)).collect();
        let spec = Spectrum::new(&x, fs, 400);
        let scale_of = |peak: f64| {
            spec.all_bins()
                .iter()
                .skip(1)
                .map(|b| b.norm())
                .fold(peak, f64::max)
        };
        let big = scale_of(0.0);
        for w in [
            Morlet::default(),
            Morlet {
                bandwidth: 6.0,
                centre: 1.5,
            },
        ] {
            for f in [0.7, 3.0, 17.0, 60.0] {
                let s = w.scale_for(f);
                let plan = ScalePlan::new(&spec, &w, s, 2.0);
                let dec = plan.evaluate(&spec, &w);
                let derivs = plan.evaluate_with_derivatives(&spec, &w);
                assert_eq!(derivs[0].values, dec.values);
                let mut buf = Vec::new();
                let gain = plan.evaluate_into(&spec, &w, &mut buf);
                assert_eq!(buf, dec.values);
                let l = spec.padded_len as f64;
                let direct_gain: f64 = (1..spec.bin_count())
                    .map(|m| (2.0 * w.spectrum(s, spec.bin_freq(m)) / l).powi(2))
                    .sum();
                assert!((gain - direct_gain).abs() < 1e-9 * direct_gain);
                let mut full = Vec::new();
                naive::scale(&spec, &w, s, &mut full);
                for n in (0..plan.len).step_by((plan.len / 17).max(1)) {
                    let t = n as f64 * dec.step;
                    let ours = dec.values[n] * Complex64::from_polar(1.0, plan.carrier(&spec, t));
                    let truth = direct(&spec, &w, s, t);
                    assert!(
                        (ours - truth).norm() < 1e-9 * big,
                        "f={f} n={n}: {ours} vs {truth}"
                    );
                    for order in [1, 2] {
                        let d = derivs[order as usize].values[n]
                            * Complex64::from_polar(1.0, plan.carrier(&spec, t));
                        let truth = direct_derivative(&spec, &w, s, t, order);
                        let unit = big * (2.0 * PI * 2.6 * f).powi(order);
                        assert!((d - truth).norm() < 1e-9 * unit, "order {order}");
                    }
                    if t.fract() == 0.0 {
                        assert!((full[t as usize] - truth).norm() < 1e-9 * big);
                    }
                }
            }
        }
    }
}
