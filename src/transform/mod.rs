//! Time–frequency transforms: the analytic signal (Hilbert) and the complex-Morlet wavelet
//! transform, computed in the frequency domain.
//!
//! The wavelet transform comes in two implementations behind the same definition:
//! [`band`] evaluates each scale from only the FFT bins inside the wavelet's pass band
//! (a demodulated, decimated inverse FFT), which is what the pipeline uses; [`naive`] is the
//! plain full-length transform (one inverse FFT of the padded length per scale), kept as the
//! reference the fast one is tested and benchmarked against.

pub mod band;
pub mod hilbert;
pub mod naive;
pub mod parallel;

use std::collections::HashMap;
use std::f64::consts::PI;
use std::sync::{Arc, Mutex, OnceLock};

use num_complex::Complex64;
use realfft::RealFftPlanner;
use rustfft::{Fft, FftPlanner};

/// Relative level below which the wavelet's Gaussian spectrum is treated as zero.
pub const SPECTRUM_TOLERANCE: f64 = 1e-10;

/// Complex Morlet mother wavelet ψ(t) = (π f_b)^(-1/2) e^{j2π f_c t} e^{-t²/f_b}
/// ("cmor f_b-f_c"); its Fourier transform is Ψ(f) = exp(-π² f_b (f - f_c)²).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Morlet {
    /// Bandwidth parameter f_b (s² at scale 1): larger is longer in time, finer in frequency.
    pub bandwidth: f64,
    /// Centre frequency f_c (Hz at scale 1).
    pub centre: f64,
}

impl Default for Morlet {
    fn default() -> Self {
        // One carrier period of Gaussian standard deviation: σ_f/f = 16 %, so a third
        // harmonic lies 79 nepers down the wavelet's spectrum while edges stay short.
        Self {
            bandwidth: 1.0,
            centre: 1.0,
        }
    }
}

impl Morlet {
    /// Checks the parameters are usable.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.bandwidth.is_finite() && self.bandwidth > 0.0) {
            return Err(format!(
                "wavelet bandwidth f_b = {} must be a positive number",
                self.bandwidth
            ));
        }
        if !(self.centre.is_finite() && self.centre > 0.0) {
            return Err(format!(
                "wavelet centre frequency f_c = {} must be a positive number",
                self.centre
            ));
        }
        Ok(())
    }

    /// Scale whose pass band is centred on `freq` Hz.
    pub fn scale_for(&self, freq: f64) -> f64 {
        self.centre / freq
    }

    /// Ψ(s f): the wavelet's spectrum at scale `s` and frequency `f` (peak 1 at f = f_c/s).
    ///
    /// Below 0.3 f_c/s the Gaussian is brought smoothly (C^∞) to zero at f = 0. Cutting it
    /// off at f = 0 instead — the analytic wavelet's usual definition — leaves a step of
    /// height e^{-π² f_b f_c²} there, i.e. a time response decaying only as 1/t, through
    /// which a loud onset leaks into quiet samples seconds later (5e-5 for f_b f_c² = 1).
    #[inline]
    pub fn spectrum(&self, s: f64, f: f64) -> f64 {
        let x = s * f;
        if x <= 0.0 {
            return 0.0;
        }
        let d = x - self.centre;
        let g = (-PI * PI * self.bandwidth * d * d).exp();
        let u = x / (TAPER * self.centre);
        if u >= 1.0 {
            g
        } else {
            g * smooth_step(u)
        }
    }

    /// Ψ(s f) at the evenly spaced frequencies f = (`first` + k) `df`, k = 0..`count`,
    /// appended to `out`: the same values as [`spectrum`](Self::spectrum), but the Gaussian
    /// by a two-term product recurrence (re-anchored every [`ANCHOR`] bins so that rounding
    /// cannot build up) instead of an `exp` per bin, which dominated the band evaluation.
    pub fn spectrum_run(&self, s: f64, first: usize, df: f64, count: usize, out: &mut Vec<f64>) {
        let a = PI * PI * self.bandwidth;
        let d = s * df;
        // The recurrence holds above the taper; bins below it are evaluated directly.
        let taper_end = ((TAPER * self.centre / d).ceil() as usize).max(first);
        let end = first + count;
        let direct = taper_end.min(end);
        out.extend((first..direct).map(|m| self.spectrum(s, m as f64 * df)));
        let mut m = direct;
        while m < end {
            let stop = (m + ANCHOR).min(end);
            let x = m as f64 * d - self.centre;
            let mut g = (-a * x * x).exp();
            let mut r = (-a * (2.0 * x * d + d * d)).exp();
            let q = (-2.0 * a * d * d).exp();
            for _ in m..stop {
                out.push(g);
                g *= r;
                r *= q;
            }
            m = stop;
        }
    }

    /// Standard deviation in time (s) of the Gaussian window at scale `s`.
    pub fn time_sigma(&self, s: f64) -> f64 {
        s * (self.bandwidth / 2.0).sqrt()
    }

    /// Relative frequency resolution σ_f/f of the pass band (independent of scale).
    pub fn relative_resolution(&self) -> f64 {
        1.0 / (PI * self.centre * (2.0 * self.bandwidth).sqrt())
    }

    /// Pass band (Hz) at scale `s` outside which Ψ(s f) < `tol`.
    pub fn band(&self, s: f64, tol: f64) -> (f64, f64) {
        let r = ((1.0 / tol).ln() / self.bandwidth).sqrt() / PI;
        (((self.centre - r) / s).max(0.0), (self.centre + r) / s)
    }

    /// Half-length (s) of the time window outside which |ψ_s| < `tol` of its peak.
    pub fn support(&self, s: f64, tol: f64) -> f64 {
        s * (self.bandwidth * (1.0 / tol).ln()).sqrt()
    }
}

/// Bins between exact evaluations in [`Morlet::spectrum_run`]: the recurrence's relative
/// error grows as (bins since the anchor)² × 1e-16, so 10⁻¹¹ at most.
const ANCHOR: usize = 256;

/// Where the low-frequency taper of [`Morlet::spectrum`] ends, as a fraction of f_c/s.
pub const TAPER: f64 = 0.3;

/// C^∞ step from 0 at u = 0 to 1 at u = 1.
#[inline]
fn smooth_step(u: f64) -> f64 {
    let a = (-1.0 / u).exp();
    let b = if u < 1.0 {
        (-1.0 / (1.0 - u)).exp()
    } else {
        0.0
    };
    a / (a + b)
}

/// Log-spaced analysis frequencies (Hz), from `fmin` to `fmax` inclusive.
pub fn log_frequencies(fmin: f64, fmax: f64, count: usize) -> Vec<f64> {
    if count == 1 {
        return vec![(fmin * fmax).sqrt()];
    }
    let r = (fmax / fmin).ln() / (count - 1) as f64;
    (0..count).map(|k| fmin * (r * k as f64).exp()).collect()
}

/// The one-sided spectrum of a signal, mean removed and zero-padded so that the transform
/// at one end of the record never sees the other end (no circular wrap-around).
#[derive(Debug, Clone)]
pub struct Spectrum {
    /// The bins kept of 0..=L/2 of the real FFT of the padded signal (bin 0, the mean, is
    /// zeroed): all of them, or after [`keep`](Self::keep) those from `first` on. Empty in
    /// a [`pending`](Self::pending) spectrum, whose bins a GPU computes.
    bins: Vec<Complex64>,
    /// The bin that `bins[0]` holds.
    first: usize,
    /// Bins kept: `bins.len()`, or in a pending spectrum how many it will hold.
    count: usize,
    /// Whether the bins are computed elsewhere (a GPU) and not held here.
    pending: bool,
    /// Padded length L (even).
    pub padded_len: usize,
    /// Number of real samples N (the record occupies padded indices 0..N).
    pub samples: usize,
    /// Sample rate, Hz.
    pub sample_rate: f64,
    /// The mean removed before the transform (the record's DC offset).
    pub mean: f64,
}

/// The one-sided spectrum, bins 0..=len/2, of `x` with `mean` taken off every sample and
/// zero-padded to `len` samples (even, at least `x.len()`), by realfft's serial plan: what
/// [`parallel::real_spectrum`] computes on every core.
pub fn serial_spectrum(x: &[f64], mean: f64, len: usize) -> Vec<Complex64> {
    let mut buf: Vec<f64> = Vec::with_capacity(len);
    buf.extend(x.iter().map(|v| v - mean));
    buf.resize(len, 0.0);
    let fft = real_plan(len);
    let mut bins = fft.make_output_vec();
    fft.process(&mut buf, &mut bins)
        .expect("buffer sizes come from the plan");
    bins
}

/// The exponent `c` of the power of two that brings `bound` to at most 1 and above ½
/// (`2^−c · bound ∈ (½, 1]`); 0 for a bound that is not a positive finite number. What a
/// spectrum on a GPU is scaled by, so that its values suit the refinement's f32 estimate.
pub fn bounding_exponent(bound: f64) -> i32 {
    if bound > 0.0 && bound.is_finite() {
        bound.log2().ceil() as i32
    } else {
        0
    }
}

/// The mean a [`Spectrum`] removes: the samples summed by [`lane_sum_by`] over their
/// count. Not finite when any sample is not (a NaN or an infinity reaches the sum).
pub fn mean_of(x: &[f64]) -> f64 {
    lane_sum_by(x, |v| *v) / x.len().max(1) as f64
}

/// Partial sums [`lane_sum_by`] keeps side by side.
const LANES: usize = 8;

/// The sum of `f` over `x`, in [`LANES`] interleaved partial sums added pairwise at the
/// end. A single running sum is a chain of additions that each wait for the one before
/// (four cycles apiece): a campaign run's 30 000 samples took 25 µs so, 4 µs in eight
/// chains (measured alone; the preparation is 500 µs). Eight chains keep the adder busy,
/// and round no worse (pairwise at the top, chains eight times shorter below).
pub fn lane_sum_by<T>(x: &[T], f: impl Fn(&T) -> f64) -> f64 {
    let mut acc = [0.0f64; LANES];
    let chunks = x.chunks_exact(LANES);
    let tail = chunks.remainder();
    for c in chunks {
        for (a, v) in acc.iter_mut().zip(c) {
            *a += f(v);
        }
    }
    let mut s = ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]));
    for v in tail {
        s += f(v);
    }
    s
}

impl Spectrum {
    /// FFT of `x` zero-padded by at least `pad` samples after its mean is removed: realfft's,
    /// or from [`parallel::PARALLEL_MIN`] points on, [`parallel::real_spectrum`] on every core.
    pub fn new(x: &[f64], sample_rate: f64, pad: usize) -> Spectrum {
        Self::with_mean(x, mean_of(x), sample_rate, pad)
    }

    /// [`new`](Self::new) with the record's mean already taken ([`mean_of`]): a record
    /// transformed twice (its band, then its padded spectrum) sums its samples once.
    pub fn with_mean(x: &[f64], mean: f64, sample_rate: f64, pad: usize) -> Spectrum {
        let n = x.len();
        let padded_len = fast_len((n + pad).max(2));
        let mut bins = if parallel::takes(padded_len) {
            parallel::real_spectrum(x, mean, padded_len)
        } else {
            serial_spectrum(x, mean, padded_len)
        };
        bins[0] = Complex64::new(0.0, 0.0);
        Spectrum {
            count: bins.len(),
            bins,
            first: 0,
            pending: false,
            padded_len,
            samples: n,
            sample_rate,
            mean,
        }
    }

    /// The spectrum [`with_mean`](Self::with_mean) would make of `samples` samples, without
    /// its bins: its length, rate and mean, for a GPU to transform the samples itself (the
    /// same padded length, so the same plans). [`bins`](Self::bins) panics on it.
    pub fn pending(samples: usize, mean: f64, sample_rate: f64, pad: usize) -> Spectrum {
        let padded_len = fast_len((samples + pad).max(2));
        Spectrum {
            bins: Vec::new(),
            first: 0,
            count: padded_len / 2 + 1,
            pending: true,
            padded_len,
            samples,
            sample_rate,
            mean,
        }
    }

    /// Whether the bins are not held here ([`pending`](Self::pending)).
    pub fn is_pending(&self) -> bool {
        self.pending
    }

    /// Number of bins of the one-sided spectrum, L/2 + 1, whichever of them are kept.
    pub fn bin_count(&self) -> usize {
        self.padded_len / 2 + 1
    }

    /// Bins `range` (absolute bin numbers), which must have been kept.
    #[inline]
    pub fn bins(&self, range: std::ops::Range<usize>) -> &[Complex64] {
        if range.is_empty() {
            return &[];
        }
        assert!(
            !self.pending,
            "bins {range:?} asked of a spectrum computed on the GPU, not held here"
        );
        let kept = self.kept();
        assert!(
            range.start >= kept.start && range.end <= kept.end,
            "bins {range:?} asked of a spectrum that kept {kept:?}"
        );
        &self.bins[range.start - self.first..range.end - self.first]
    }

    /// Every bin, 0..=L/2, of a spectrum that has kept them all.
    pub fn all_bins(&self) -> &[Complex64] {
        self.bins(0..self.bin_count())
    }

    /// The bins kept (absolute bin numbers).
    pub fn kept(&self) -> std::ops::Range<usize> {
        self.first..self.first + self.count
    }

    /// Keeps only bins `range` (within those kept), in memory of their own size: a prepared
    /// signal waits for its transforms (on a GPU, for its whole batch) holding only the bins
    /// its pass bands read, a tenth of the spectrum or less, instead of all of it.
    pub fn keep(&mut self, range: std::ops::Range<usize>) {
        if self.pending {
            let kept = self.kept();
            assert!(
                range.is_empty() || (range.start >= kept.start && range.end <= kept.end),
                "bins {range:?} kept of a spectrum that holds {kept:?}"
            );
        } else {
            self.bins = self.bins(range.clone()).to_vec();
        }
        self.first = range.start;
        self.count = range.len();
    }

    /// The bins from `f_lo` to `f_hi` (Hz) over which [`white_noise_variance`] takes its
    /// median (inclusive), `None` where fewer than 17 lie there.
    ///
    /// [`white_noise_variance`]: Self::white_noise_variance
    pub fn noise_bins(&self, f_lo: f64, f_hi: f64) -> Option<(usize, usize)> {
        let df = self.sample_rate / self.padded_len as f64;
        let lo = ((f_lo / df).ceil() as usize).max(1);
        let hi = ((f_hi / df).floor() as usize).min(self.bin_count() - 1);
        (hi >= lo + 16).then_some((lo, hi))
    }

    /// Frequency (Hz) of bin `m`.
    #[inline]
    pub fn bin_freq(&self, m: usize) -> f64 {
        m as f64 * self.sample_rate / self.padded_len as f64
    }

    /// Power-spectrum estimate of a white noise floor: variance per sample σ_n² for which
    /// E|X[m]|² = N σ_n², from the median over bins between `f_lo` and `f_hi`.
    pub fn white_noise_variance(&self, f_lo: f64, f_hi: f64) -> Option<f64> {
        let (lo, hi) = self.noise_bins(f_lo, f_hi)?;
        let band = self.bins(lo..hi + 1);
        Some(self.noise_variance_of(nth_power(band, band.len() / 2)))
    }

    /// [`white_noise_variance`](Self::white_noise_variance) from the median |X|² of its
    /// bins (found here, or by a GPU).
    pub fn noise_variance_of(&self, median_power: f64) -> f64 {
        // |X|² of complex Gaussian noise is exponential: median = ln 2 × mean.
        median_power / std::f64::consts::LN_2 / self.samples as f64
    }
}

/// The `rank`-th smallest (from 0) of the bins' |X|², exactly the value that sorting them
/// by `total_cmp` puts there. Non-negative floats order as their bit patterns, so the
/// selection compares integers: a third cheaper than comparing by `total_cmp` (60 against
/// 90 µs for the 21 000 bins above a campaign run's band, whose median was then a fifth
/// of a wavelet track's completion; it is taken in the preparation now).
pub fn nth_power(bins: &[Complex64], rank: usize) -> f64 {
    assert!(rank < bins.len(), "rank {rank} of {} bins", bins.len());
    let mut signs = 0u64;
    let mut keys: Vec<u64> = bins
        .iter()
        .map(|c| {
            let k = c.norm_sqr().to_bits();
            signs |= k;
            k
        })
        .collect();
    // A NaN with its sign bit set orders first by total_cmp and last by its bits.
    if signs >> 63 != 0 {
        let mut p: Vec<f64> = keys.into_iter().map(f64::from_bits).collect();
        return *p.select_nth_unstable_by(rank, f64::total_cmp).1;
    }
    f64::from_bits(*keys.select_nth_unstable(rank).1)
}

/// `x.floor()`, bit for bit (signed zeros, infinities and NaN included), without a call:
/// the baseline x86-64 target has no rounding instruction, so `f64::floor` is a function
/// call, and it sat in the innermost loops of the interpolation and the phase unwrapping.
#[inline]
pub fn exact_floor(x: f64) -> f64 {
    // Below 2^52 in magnitude a truncation through i64 is exact; above, every float is an
    // integer already (and NaN and the infinities fail the test and come back as they are).
    if x.abs() < 4_503_599_627_370_496.0 {
        let t = x as i64 as f64;
        if t > x {
            t - 1.0
        } else {
            t.copysign(x)
        }
    } else {
        x
    }
}

/// Smallest length ≥ `n` that is even and has only the factors 2, 3 and 5 (fast for rustfft).
pub fn fast_len(n: usize) -> usize {
    let mut m = n.max(2);
    loop {
        if m.is_multiple_of(2) {
            let mut r = m;
            for p in [2, 3, 5] {
                while r.is_multiple_of(p) {
                    r /= p;
                }
            }
            if r == 1 {
                return m;
            }
        }
        m += 1;
    }
}

/// Smallest length ≥ `n` of the form 2^k × {1, 9/8, 5/4, 3/2, 15/8}: few distinct lengths
/// (five per octave, all fast for rustfft), so that the plans of hundreds of scales come
/// from a handful of cached ones, at most 25 % longer than asked.
pub fn plan_len(n: usize) -> usize {
    let p = n.max(2).next_power_of_two();
    if p < 16 {
        return p;
    }
    let eighth = p / 16;
    [9, 10, 12, 15]
        .iter()
        .map(|&k| k * eighth)
        .find(|&m| m >= n)
        .unwrap_or(p)
}

/// A complex FFT plan of length `len`, shared by all threads (plans are cached).
pub fn complex_plan(len: usize, inverse: bool) -> Arc<dyn Fft<f64>> {
    static PLANS: Plans<dyn Fft<f64>> = OnceLock::new();
    cached(&PLANS, (len, inverse), || {
        let mut planner = FftPlanner::new();
        if inverse {
            planner.plan_fft_inverse(len)
        } else {
            planner.plan_fft_forward(len)
        }
    })
}

/// A real-to-complex FFT plan of length `len`, cached.
pub fn real_plan(len: usize) -> Arc<dyn realfft::RealToComplex<f64>> {
    static PLANS: Plans<dyn realfft::RealToComplex<f64>> = OnceLock::new();
    cached(&PLANS, (len, false), || {
        RealFftPlanner::new().plan_fft_forward(len)
    })
}

/// A complex-to-real (inverse) FFT plan of length `len`, cached.
pub fn real_inverse_plan(len: usize) -> Arc<dyn realfft::ComplexToReal<f64>> {
    static PLANS: Plans<dyn realfft::ComplexToReal<f64>> = OnceLock::new();
    cached(&PLANS, (len, true), || {
        RealFftPlanner::new().plan_fft_inverse(len)
    })
}

/// Plans by (length, inverse), each made by a planner of its own. rustfft's planner builds
/// a new length from the sub-FFTs it already holds, so one shared planner would make a
/// length's plan, and its rounding, depend on which lengths were asked for before, in
/// whatever order threads asked: the same run gave other gaps in another process.
type Plans<T> = OnceLock<Mutex<HashMap<(usize, bool), Arc<T>>>>;

fn cached<T: ?Sized>(
    plans: &Plans<T>,
    key: (usize, bool),
    make: impl FnOnce() -> Arc<T>,
) -> Arc<T> {
    let mut cache = plans
        .get_or_init(|| Mutex::new(HashMap::new()))
        .lock()
        .unwrap_or_else(|p| p.into_inner());
    cache.entry(key).or_insert_with(make).clone()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `lane_sum_by` at every length from 0 to 40 (every tail after the lanes): exact where
    /// every partial sum is (integers), within a few ulps of an exactly rounded sum of
    /// random values over six decades, and not finite whenever one term is not.
    #[test]
    fn lane_sums_are_the_sum_at_every_length_and_carry_any_nan_or_infinity() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let mut worst = 0.0f64;
        for len in 0..=40usize {
            let ints: Vec<f64> = (0..len)
                .map(|_| rng.random_range(-1000..1000) as f64)
                .collect();
            let exact: f64 = ints.iter().map(|&v| v as i64).sum::<i64>() as f64;
            assert_eq!(lane_sum_by(&ints, |v| *v), exact, "{len} integers");
            let x: Vec<f64> = (0..len)
                .map(|_| rng.random_range(-1.0..1.0) * 10f64.powf(rng.random_range(-3.0..3.0)))
                .collect();
            // The reference: every term split into i128 multiples of 2^-80 (exact for these
            // magnitudes to far below an ulp of the total), summed exactly.
            let scale = 2f64.powi(80);
            let fixed: i128 = x.iter().map(|&v| (v * scale).round() as i128).sum();
            let reference = fixed as f64 / scale;
            let magnitude = x.iter().map(|v| v.abs()).sum::<f64>();
            let bound = 1e-14 * magnitude + 1e-20;
            let got = lane_sum_by(&x, |v| *v);
            if magnitude > 0.0 {
                worst = worst.max((got - reference).abs() / magnitude);
            }
            assert!(
                (got - reference).abs() <= bound,
                "{len}: {got} against {reference}"
            );
            for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                for at in 0..len {
                    let mut y = x.clone();
                    y[at] = bad;
                    assert!(
                        !lane_sum_by(&y, |v| *v).is_finite(),
                        "{bad} at {at} of {len}"
                    );
                    assert!(!mean_of(&y).is_finite());
                }
            }
        }
        println!("worst error of the lane sums: {worst:.2e} of the terms' absolute sum");
        // Opposite infinities in different lanes meet only in the final additions.
        let mut y = vec![1.0; 19];
        y[1] = f64::INFINITY;
        y[6] = f64::NEG_INFINITY;
        assert!(lane_sum_by(&y, |v| *v).is_nan());
    }

    /// `exact_floor` against `f64::floor`, bit for bit, over values built to be hard:
    /// signed zeros, the integers and their neighbours a few ulps away, the 2^52 boundary,
    /// huge values, infinities, NaN, and random values over 40 decades of either sign.
    #[test]
    fn exact_floor_is_floor_to_the_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let mut xs = vec![
            0.0,
            -0.0,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            -f64::NAN,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
            f64::MAX,
            f64::MIN,
            4_503_599_627_370_496.0,
            9.3e18,
            -9.3e18,
        ];
        for k in [
            0.0f64,
            1.0,
            2.0,
            3.0,
            1e6,
            4_503_599_627_370_495.0,
            4_503_599_627_370_496.0,
        ] {
            for sign in [1.0, -1.0] {
                let v = sign * k;
                xs.push(v);
                for ulps in 1..4u64 {
                    xs.push(f64::from_bits(v.to_bits() + ulps));
                    xs.push(f64::from_bits(v.to_bits().saturating_sub(ulps)));
                }
                xs.push(v + 0.5);
                xs.push(v - 0.5);
            }
        }
        for _ in 0..100_000 {
            let e = rng.random_range(-20.0..20.0f64);
            xs.push(rng.random_range(-1.0..1.0) * 10f64.powf(e));
        }
        for x in xs {
            assert_eq!(
                exact_floor(x).to_bits(),
                x.floor().to_bits(),
                "floor({x:e})"
            );
        }
    }

    /// The selection by bit patterns against sorting by `total_cmp`, at every rank of sets
    /// built to be hard: ties, zeros, values a few ulps apart, a range of 600 decades,
    /// infinities and NaNs of either sign.
    #[test]
    fn nth_power_is_the_value_sorting_puts_at_each_rank() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let near = |v: f64, ulps: u64| f64::from_bits(v.to_bits() + ulps);
        let mut sets: Vec<Vec<Complex64>> = vec![
            vec![Complex64::new(0.0, 0.0); 5],
            vec![Complex64::new(3.0, 4.0)],
            (0..300)
                .map(|i| Complex64::new(near(1.5, i % 7).sqrt(), 0.0))
                .collect(),
        ];
        for n in [2, 17, 1000, 4099] {
            sets.push(
                (0..n)
                    .map(|_| {
                        let e = rng.random_range(-300.0..300.0f64);
                        Complex64::new(
                            rng.random_range(-1.0..1.0) * 10f64.powf(e / 2.0),
                            rng.random_range(-1.0..1.0),
                        )
                    })
                    .collect(),
            );
            // Complex Gaussian noise, as above a band, with exact ties mixed in.
            sets.push(
                (0..n)
                    .map(|i| {
                        if i % 5 == 0 {
                            Complex64::new(0.5, 0.5)
                        } else {
                            Complex64::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0))
                        }
                    })
                    .collect(),
            );
        }
        let mut odd = sets[5].clone();
        odd[3] = Complex64::new(f64::INFINITY, 0.0);
        odd[9] = Complex64::new(f64::NAN, 0.0);
        sets.push(odd.clone());
        odd[11] = Complex64::new(-f64::NAN, 0.0);
        sets.push(odd);
        for bins in &sets {
            let mut sorted: Vec<f64> = bins.iter().map(Complex64::norm_sqr).collect();
            sorted.sort_by(f64::total_cmp);
            let n = sorted.len();
            // Every rank up to 1000 values; beyond, a spread of them and both ends.
            let ranks = (0..n).filter(|r| n <= 1000 || r % 37 == 0 || *r == n - 1 || *r == n / 2);
            for (rank, want) in ranks.map(|r| (r, &sorted[r])) {
                let got = nth_power(bins, rank);
                assert_eq!(
                    got.to_bits(),
                    want.to_bits(),
                    "rank {rank} of {}",
                    bins.len()
                );
            }
        }
    }

    /// A plan's output, bit for bit, is that of a planner that planned nothing before,
    /// whatever lengths were planned first. 18432 = 9·2^11: rustfft's own planner, asked
    /// for it after its divisors, builds it from them and rounds differently (most of its
    /// bins differ in the last bits), which made one run's gap differ between processes.
    #[test]
    fn a_plan_rounds_the_same_whatever_was_planned_before() {
        let len = 18432;
        let x: Vec<Complex64> = (0..len)
            .map(|i| {
                Complex64::new(
                    ((i * 7919) % 1000) as f64 / 1e3 - 0.5,
                    (i % 97) as f64 / 97.0,
                )
            })
            .collect();
        for other in [576, 1152, 2304, 4608, 9216, 36864] {
            complex_plan(other, false);
            real_plan(2 * other);
        }
        let mut ours = x.clone();
        complex_plan(len, false).process(&mut ours);
        let mut fresh = x.clone();
        FftPlanner::new().plan_fft_forward(len).process(&mut fresh);
        assert!(
            ours == fresh,
            "complex plan depends on what was planned before"
        );

        let real: Vec<f64> = (0..2 * len).map(|i| x[i / 2].re + (i % 3) as f64).collect();
        let ours = real_spectrum(&real_plan(2 * len), &real);
        let fresh = real_spectrum(&RealFftPlanner::new().plan_fft_forward(2 * len), &real);
        assert!(
            ours == fresh,
            "real plan depends on what was planned before"
        );
    }

    fn real_spectrum(plan: &Arc<dyn realfft::RealToComplex<f64>>, x: &[f64]) -> Vec<Complex64> {
        let mut input = x.to_vec();
        let mut out = plan.make_output_vec();
        plan.process(&mut input, &mut out)
            .expect("lengths match the plan");
        out
    }

    #[test]
    fn plan_len_is_short_and_smooth() {
        assert_eq!(plan_len(1), 2);
        assert_eq!(plan_len(16), 16);
        assert_eq!(plan_len(17), 18);
        assert_eq!(plan_len(1025), 1152);
        for n in 16..5000 {
            let m = plan_len(n);
            let mut r = m;
            for p in [2, 3, 5] {
                while r.is_multiple_of(p) {
                    r /= p;
                }
            }
            assert!(r == 1 && m >= n && 4 * m <= 5 * n + 4, "{n} -> {m}");
        }
    }

    #[test]
    fn fast_len_is_even_and_smooth() {
        assert_eq!(fast_len(1), 2);
        assert_eq!(fast_len(7), 8);
        assert_eq!(fast_len(1001), 1024);
        assert_eq!(fast_len(1025), 1080);
        for n in [3, 17, 999, 108_477] {
            let m = fast_len(n);
            assert!(m >= n && m.is_multiple_of(2) && m < n + n / 4 + 4);
        }
    }

    #[test]
    fn a_spectrum_that_keeps_some_bins_gives_exactly_those() {
        let x: Vec<f64> = (0..1000)
            .map(|i| (0.37 * i as f64).sin() + 0.01 * i as f64)
            .collect();
        let full = Spectrum::new(&x, 100.0, 200);
        let count = full.bin_count();
        assert_eq!(count, full.all_bins().len());
        let mut part = full.clone();
        part.keep(40..90);
        assert_eq!(part.kept(), 40..90);
        assert_eq!(
            part.bin_count(),
            count,
            "the spectrum's size is the whole one's"
        );
        assert_eq!(part.bins(40..90), full.bins(40..90));
        assert_eq!(part.bins(55..56), &full.all_bins()[55..56]);
        // An empty range reads nothing, wherever it lies.
        assert!(part.bins(7..7).is_empty() && part.bins(500..500).is_empty());
        // Keeping again narrows; nothing is kept of an empty range.
        part.keep(50..60);
        assert_eq!(part.bins(50..60), full.bins(50..60));
        let mut none = full.clone();
        none.keep(70..70);
        assert!(none.kept().is_empty());
        // Bins not kept are refused, not read from elsewhere.
        for range in [39..41, 59..61, 0..count] {
            let r = range.clone();
            let asked = std::panic::catch_unwind(|| part.bins(r).len());
            assert!(asked.is_err(), "{range:?} of a spectrum keeping 50..60");
        }
    }

    #[test]
    fn spectrum_run_equals_pointwise_evaluation() {
        for w in [
            Morlet::default(),
            Morlet {
                bandwidth: 6.0,
                centre: 1.5,
            },
        ] {
            for (s, df, first, count) in [
                (0.02, 4.8e-4, 1, 300_000),
                (2.0, 4.8e-4, 1, 3000),
                (0.1, 0.01, 17, 5000),
                (1.0, 0.37, 0, 9),
            ] {
                let mut run = Vec::new();
                w.spectrum_run(s, first, df, count, &mut run);
                assert_eq!(run.len(), count);
                for (k, v) in run.iter().enumerate() {
                    let exact = w.spectrum(s, (first + k) as f64 * df);
                    assert!(
                        (v - exact).abs() <= 1e-11 * exact.max(1e-12),
                        "s={s} bin {}: {v} vs {exact}",
                        first + k
                    );
                }
            }
        }
    }

    #[test]
    fn band_contains_everything_above_tolerance() {
        let w = Morlet::default();
        let s = w.scale_for(10.0);
        let (lo, hi) = w.band(s, 1e-10);
        // Broad wavelets reach down to DC, where the taper takes the spectrum to zero.
        assert_eq!(lo, 0.0);
        assert_eq!(w.spectrum(s, 0.0), 0.0);
        assert!((w.spectrum(s, hi) - 1e-10).abs() < 1e-12);
        assert!((w.spectrum(s, 10.0) - 1.0).abs() < 1e-15);
        let narrow = Morlet {
            bandwidth: 8.0,
            centre: 2.0,
        };
        let s = narrow.scale_for(10.0);
        let (lo, hi) = narrow.band(s, 1e-10);
        assert!(lo > 0.0);
        assert!((narrow.spectrum(s, lo) - 1e-10).abs() < 1e-12);
        assert!((narrow.spectrum(s, hi) - 1e-10).abs() < 1e-12);
    }
}
