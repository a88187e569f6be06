//! A signal prepared for the wavelet track, and the CPU's first pass. In: samples, sample
//! rate, options and an optional guide frequency; out: a [`WaveletPrep`] (spectrum, scales,
//! their band plans, the coarse grid), and from it a [`CoarseRidge`] (the ridge on the coarse
//! grid and each scale's noise median) — on the CPU here, on a GPU in `gpu::ridge`.

use rayon::prelude::*;

use crate::ridge::{argmax_ridge, dp_ridge};
use crate::transform::band::{self, interpolate, ScalePlan};
use crate::transform::{log_frequencies, Morlet, Spectrum};

use super::{
    band_with_mean, checked_mean, checked_mean_copied, Device, RidgeSearch, Track, TrackError,
    WaveletOptions, MIN_NOISE_STEPS, PASS1_OVERSAMPLE, PASS1_TOLERANCE,
};

/// One scale's first pass on the CPU: its ridge scores, noise median, kept |W|² (when a
/// scalogram is kept) and noise gain.
struct Column {
    score: Vec<f32>,
    median: Option<f64>,
    power: Vec<f32>,
    gain: f64,
}

/// Envelope, frequency and derivatives along the complex-Morlet ridge of `x`.
///
/// `guide`, when given, is a reference frequency (Hz) per sample — typically the input
/// channel's ridge — that the ridge is pulled towards.
pub fn track_wavelet(
    x: &[f64],
    fs: f64,
    opt: &WaveletOptions,
    guide: Option<&[f64]>,
) -> Result<Track, TrackError> {
    let prep = WaveletPrep::new(x, fs, opt, guide)?;
    let ridge = prep.coarse_ridge();
    Ok(prep.finish(ridge, Device::Cpu))
}

/// A wavelet track set up to its first pass: the spectrum, the scales and their band
/// plans, and the coarse grid. The first pass (all scales, then the ridge) is what a
/// backend evaluates — [`coarse_ridge`](Self::coarse_ridge) on the CPU, `gpu::ridge` on
/// a GPU for many runs at once; [`finish`](Self::finish) does the rest on the CPU.
#[derive(Clone)]
pub struct WaveletPrep {
    pub(super) n: usize,
    pub(super) fs: f64,
    pub(super) opt: WaveletOptions,
    /// ln of the guide's frequency at each coarse step (NaN where it has none).
    pub(super) guide: Option<Vec<f64>>,
    pub(super) fmin: f64,
    pub(super) fmax: f64,
    /// Analysed frequencies (Hz), one per scale, log-spaced.
    pub freqs: Vec<f64>,
    /// The record's padded spectrum.
    pub spec: Spectrum,
    /// First-pass band plan per scale.
    pub plans: Vec<ScalePlan>,
    /// Samples between coarse steps.
    pub h: usize,
    /// Coarse steps.
    pub steps: usize,
    /// 1/(mean power of the record): ridge scores are log-power relative to it.
    pub unit: f64,
    /// Keep the first pass's |W| grid in the track (costs S × steps × 4 bytes).
    pub keep_scalogram: bool,
    /// White-noise variance per sample from the spectrum above the band (from 1.5 fmax to
    /// fs/2; `None` where too few bins lie there), for the completion's noise floor.
    pub(super) noise_above_band: Option<f64>,
    /// Where the padded spectrum is computed by a GPU ([`new_deferred`](Self::new_deferred)):
    /// what it needs and what the CPU needs to compute it instead.
    pub(crate) deferred: Option<Box<Deferred>>,
}

/// A prepared signal's share that a GPU computes: its padded spectrum (the kept bins of
/// [`WaveletPrep::spec`], which is [`Spectrum::pending`]), the white-noise median above
/// the band, and from them what the first pass and refinement read. The CPU computes the
/// same itself ([`WaveletPrep::materialize`]) where the GPU does not serve the signal.
#[derive(Clone)]
pub(crate) struct Deferred {
    /// The record's samples less their mean (x − mean, as the CPU's transform takes them),
    /// in a buffer from [`SampleBuffers`].
    pub(crate) centred: Vec<f64>,
    /// The bins (inclusive) whose median |X|² is the white-noise floor above the band
    /// ([`Spectrum::noise_bins`] from 1.5 fmax to fs/2), if enough lie there.
    pub(crate) noise_bins: Option<(usize, usize)>,
    /// The exponent `c` of the power of two 2^−c the spectrum is scaled by on the device
    /// ([`bounding_exponent`](crate::transform::bounding_exponent) of Σ|x − mean|, which
    /// bounds every |X_k|): its bins are then at most about 1, as the refinement's f32
    /// estimate needs them (near 1, not exactly at it; a record whose energy lies mostly
    /// outside its band has its band's bins further below).
    pub(crate) scale_exponent: i32,
}

impl Drop for Deferred {
    /// Gives the samples' buffer back for the next signal's.
    fn drop(&mut self) {
        SampleBuffers::give_back(std::mem::take(&mut self.centred));
    }
}

/// Buffers that deferred signals' samples were held in, for later ones to reuse. Each
/// signal's buffer is taken on the worker that prepares it and let go on the one that
/// completes its track, and glibc gave a third of them back as fresh pages to fault in and
/// zero: a `bench` repetition of 80 campaign runs on 2 cores took 1 500 more page faults
/// and its preparation 0.013–0.016 s instead of 0.009 s.
struct SampleBuffers;

/// The buffers kept, and their bytes.
static SAMPLE_BUFFERS: std::sync::Mutex<(Vec<Vec<f64>>, usize)> =
    std::sync::Mutex::new((Vec::new(), 0));

/// Bytes of buffers kept at most: about two batches of 30 000-sample records in flight.
const SAMPLE_BUFFER_BYTES: usize = 512 << 20;

impl SampleBuffers {
    /// `x − mean` in a kept buffer that holds it, or a new one, with the sums of the
    /// record's variance by Parseval's theorem and of Σ|x − mean| ([`ParsevalSums`]) taken
    /// as each value is written. Centring and summing apart read the samples twice: in a
    /// group of signals, whose buffers are cold, the two took 39 µs a 30 000-sample signal
    /// on one core here, the one pass 33 µs (80 campaign signals' deferred preparations
    /// 19.7–20.1 → 19.0–19.2 ms on one core; a 2^20-sample record's 9.1–9.7 → 8.3–8.9 ms
    /// on two).
    fn centred(x: &[f64], mean: f64) -> (Vec<f64>, ParsevalSums) {
        let mut out = Self::take(x.len());
        let sums = centre_into(&mut out, x, mean);
        (out, sums)
    }

    /// The samples copied into a kept buffer that holds them, or a new one, and their mean
    /// with [`checked_mean`]'s checks and bits ([`checked_mean_copied`]), for a record short
    /// enough ([`WARM_SAMPLES`]) that the copy stays in the core's cache to be centred there.
    /// The buffer goes back if the record is refused, here or later ([`HeldSamples`]).
    fn copied_with_mean(x: &[f64], fs: f64) -> Result<(HeldSamples, f64), TrackError> {
        let mut held = HeldSamples(Self::take(x.len()));
        let mean = checked_mean_copied(x, fs, &mut held.0)?;
        Ok((held, mean))
    }

    /// A kept buffer that holds `len` values (its contents left as they were), or a new one.
    fn take(len: usize) -> Vec<f64> {
        let reused = {
            let mut kept = SAMPLE_BUFFERS.lock().unwrap_or_else(|p| p.into_inner());
            let (buffers, bytes) = &mut *kept;
            // The smallest that holds it, and none more than twice its size: a long
            // record's buffer is not spent on a short one's.
            buffers
                .iter()
                .enumerate()
                .filter(|(_, b)| b.capacity() >= len && b.capacity() <= 2 * len.max(1))
                .min_by_key(|(_, b)| b.capacity())
                .map(|(i, _)| i)
                .map(|i| {
                    let b = buffers.swap_remove(i);
                    *bytes -= b.capacity() * 8;
                    b
                })
        };
        reused.unwrap_or_else(|| Vec::with_capacity(len))
    }

    /// Keeps `buffer` for a later signal, unless the kept ones are at their limit.
    fn give_back(buffer: Vec<f64>) {
        let size = buffer.capacity() * 8;
        if size == 0 {
            return;
        }
        let mut kept = SAMPLE_BUFFERS.lock().unwrap_or_else(|p| p.into_inner());
        let (buffers, bytes) = &mut *kept;
        if *bytes + size <= SAMPLE_BUFFER_BYTES {
            *bytes += size;
            buffers.push(buffer);
        }
    }
}

/// A buffer from [`SampleBuffers`] that goes back to them if dropped before its samples
/// are moved on (a preparation refused after its record was copied: a bad option, a
/// record with no band).
struct HeldSamples(Vec<f64>);

impl Drop for HeldSamples {
    fn drop(&mut self) {
        SampleBuffers::give_back(std::mem::take(&mut self.0));
    }
}

/// What the first pass finds: the ridge on the coarse grid and the noise level per scale.
#[derive(Debug, Clone, PartialEq)]
pub struct CoarseRidge {
    /// Scale index of the ridge at every coarse step.
    pub path: Vec<usize>,
    /// Median coarse |W|² inside the cone of influence, per scale (`None` where
    /// [`WaveletPrep::noise_steps`] has none): the white-noise floor estimate.
    pub median_power: Vec<Option<f64>>,
    /// Coarse |W|², scale-major, when the prepared signal asked to keep its scalogram.
    pub power: Option<Vec<f32>>,
    /// Noise gain per scale ([`ScalePlan::noise_gain`]): W's variance per unit of white
    /// noise variance and sample.
    pub gains: Vec<f64>,
}

/// The record's variance as the ridge scores' unit reads it: the padded spectrum's power
/// over bins 1..=L/2, twice, over N L (bin 0, the mean, is zeroed).
fn spectral_variance(spec: &Spectrum, n: usize) -> f64 {
    crate::transform::lane_sum_by(spec.all_bins(), |b| b.norm_sqr()) * 2.0
        / (n as f64 * spec.padded_len as f64)
}

/// `out` = `x − mean` (whatever it held before, written once, never zeroed first: a long
/// record's buffer is 8 MB), and the [`ParsevalSums`] of those values, summed as they are
/// written: the bits of the same sums taken over `out` in a pass of their own (the tests'
/// `parseval_variance`).
fn centre_into(out: &mut Vec<f64>, x: &[f64], mean: f64) -> ParsevalSums {
    let n = x.len();
    out.clear();
    out.reserve(n);
    let mut sums = ParsevalSums::default();
    {
        let spare = &mut out.spare_capacity_mut()[..n];
        let mut from = x.chunks_exact(8);
        let mut to = spare.chunks_exact_mut(8);
        for (c, o) in (&mut from).zip(&mut to) {
            let y: [f64; 8] = std::array::from_fn(|k| c[k] - mean);
            for (o, &v) in o.iter_mut().zip(&y) {
                o.write(v);
            }
            sums.add_eight(&y);
        }
        for (k, (&v, o)) in from.remainder().iter().zip(to.into_remainder()).enumerate() {
            sums.add(k, *o.write(v - mean));
        }
    }
    // SAFETY: the loops above wrote each of the first n values: the chunks of eight and
    // their remainder cover `x`, and `spare` is as long.
    unsafe { out.set_len(n) };
    sums
}

/// [`centre_into`] where the samples are already in the buffer: `y` = `y − mean`, with
/// the same sums in the same order, so the same bits.
fn centre_in_place(y: &mut [f64], mean: f64) -> ParsevalSums {
    let mut sums = ParsevalSums::default();
    let mut chunks = y.chunks_exact_mut(8);
    for c in &mut chunks {
        for v in c.iter_mut() {
            *v -= mean;
        }
        sums.add_eight((&*c).try_into().expect("eight values"));
    }
    for (k, v) in chunks.into_remainder().iter_mut().enumerate() {
        *v -= mean;
        sums.add(k, *v);
    }
    sums
}

/// Records of up to this many samples (1 MiB of f64, half a core's L2 here) are copied
/// once, their mean summed and the copy centred where the cache still holds it, and the
/// band's FFT reads it there ([`SampleBuffers::copied_with_mean`], [`centre_in_place`]).
/// Read from the record in memory three times instead (the mean, the band, the
/// centring), the mean and the centring alone were 30 % of 80 campaign records' deferred
/// preparations in `perf`; copied once, 400 campaign records' preparations on one core
/// took 71.7–72.2 ms instead of 78.2–79.3. A longer record's copy would leave the cache
/// before it is centred, and a second write of it would cost more than the reads saved.
const WARM_SAMPLES: usize = 1 << 17;

/// The sums of [`ParsevalSums`] over `y` in a pass of their own: what [`centre_into`] must
/// find as it writes.
#[cfg(test)]
fn parseval_variance(y: &[f64], padded_len: usize) -> (f64, f64) {
    let mut sums = ParsevalSums::default();
    let mut chunks = y.chunks_exact(8);
    for c in &mut chunks {
        sums.add_eight(c.try_into().expect("eight values"));
    }
    for (k, &v) in chunks.remainder().iter().enumerate() {
        sums.add(k, v);
    }
    sums.variance(y.len(), padded_len)
}

/// [`spectral_variance`] from the samples less their mean, `y`, by Parseval's theorem,
/// for a spectrum not held here, and Σ|y|, which bounds every bin. For y zero-padded to L
/// (even), Σ_{k=0}^{L−1} |Y_k|² = L Σ y², and the bins k and L − k are conjugate, so twice
/// bins 1..=L/2 is L Σ y² − Y_0² + Y_{L/2}², with Y_0 = Σ y and Y_{L/2} = Σ (−1)^j y_j.
/// Σ y, Σ y² and Σ |y| go in eight lanes side by side (one chain of additions was a tenth
/// of a deferred preparation); lane k holds the samples j ≡ k (mod 8), whose sign in the
/// alternating sum is (−1)^k.
#[derive(Default)]
struct ParsevalSums {
    sum: [f64; 8],
    sq: [f64; 8],
    abs: [f64; 8],
}

impl ParsevalSums {
    /// Eight consecutive samples, the first in lane 0.
    #[inline(always)]
    fn add_eight(&mut self, y: &[f64; 8]) {
        for (k, &v) in y.iter().enumerate() {
            self.add(k, v);
        }
    }

    /// One sample, in lane `k`.
    #[inline(always)]
    fn add(&mut self, k: usize, v: f64) {
        self.sum[k] += v;
        self.sq[k] += v * v;
        self.abs[k] += v.abs();
    }

    /// The variance of `n` samples zero-padded to `padded_len`, and Σ |y|.
    fn variance(&self, n: usize, padded_len: usize) -> (f64, f64) {
        let total = |a: [f64; 8]| ((a[0] + a[4]) + (a[1] + a[5])) + ((a[2] + a[6]) + (a[3] + a[7]));
        let s = self.sum;
        let alt = ((s[0] - s[1]) + (s[2] - s[3])) + ((s[4] - s[5]) + (s[6] - s[7]));
        let (sum, sq, abs) = (total(self.sum), total(self.sq), total(self.abs));
        let l = padded_len as f64;
        let variance = (l * sq - sum * sum + alt * alt) / (n as f64 * l);
        (variance, abs)
    }
}

/// The first and last of `steps` coarse steps `h` samples apart whose sample lies at least
/// `edge` samples from both ends of a record of `n` samples; `(steps, 0)` when none does.
/// Found from the closed form and checked against the predicate around it: the GPU
/// dispatcher asks it of every scale of every signal, and a scan over the steps cost
/// ~40 µs a signal of serial host time.
pub(crate) fn inner_range(n: usize, h: usize, steps: usize, edge: f64) -> (usize, usize) {
    if steps == 0 || n == 0 {
        return (steps, 0);
    }
    let from_start = |j: usize| (j * h) as f64 >= edge;
    let from_end = |j: usize| (n - 1).checked_sub(j * h).is_some_and(|d| d as f64 >= edge);
    let guess = |x: f64| {
        if x.is_nan() || x <= 0.0 {
            0
        } else {
            (x as usize).min(steps - 1)
        }
    };
    // The first step far enough from the start (monotone in j).
    let mut a = guess((edge / h as f64).ceil());
    while a > 0 && from_start(a - 1) {
        a -= 1;
    }
    while a < steps && !from_start(a) {
        a += 1;
    }
    // The last step far enough from the end (monotone the other way).
    let mut b = guess(((n - 1) as f64 - edge) / h as f64);
    while b + 1 < steps && from_end(b + 1) {
        b += 1;
    }
    while b > 0 && !from_end(b) {
        b -= 1;
    }
    let first = if a < steps && from_end(a) { a } else { steps };
    let last = if from_end(b) && from_start(b) { b } else { 0 };
    (first, last)
}

impl WaveletPrep {
    /// Checks the signal and options, chooses the band and scales, and takes the spectrum.
    pub fn new(
        x: &[f64],
        fs: f64,
        opt: &WaveletOptions,
        guide: Option<&[f64]>,
    ) -> Result<WaveletPrep, TrackError> {
        crate::profile::time(crate::profile::Stage::FirstPass, || {
            Self::prepare(x, fs, opt, guide, false)
        })
    }

    /// [`new`](Self::new) without the padded spectrum, which a GPU computes from the
    /// samples this keeps (`gpu::spectrum`): the band (its own, shorter FFT), the scales and
    /// their plans are the CPU's to the bit, and so is everything once the CPU has the
    /// spectrum ([`materialize`](Self::materialize)). The ridge scores' unit is the same
    /// sum by Parseval's theorem from the samples (within rounding of the spectrum's).
    pub fn new_deferred(
        x: &[f64],
        fs: f64,
        opt: &WaveletOptions,
        guide: Option<&[f64]>,
    ) -> Result<WaveletPrep, TrackError> {
        crate::profile::time(crate::profile::Stage::FirstPass, || {
            Self::prepare(x, fs, opt, guide, true)
        })
    }

    /// The white-noise variance per sample above the band (from 1.5 fmax to fs/2) that the
    /// completion's noise floor takes, if known yet (a deferred signal's comes from the GPU).
    pub fn noise_floor_above_band(&self) -> Option<f64> {
        self.noise_above_band
    }

    /// Whether the padded spectrum is left to a GPU ([`new_deferred`](Self::new_deferred)).
    pub fn is_deferred(&self) -> bool {
        self.deferred.is_some()
    }

    /// Computes on the CPU what [`new_deferred`](Self::new_deferred) left to a GPU, for a
    /// signal the GPU did not serve: afterwards the prepared signal is [`new`](Self::new)'s
    /// to the bit (unit and white-noise floor from the spectrum too). Nothing to do for one
    /// prepared by `new`.
    pub fn materialize(&mut self) {
        let Some(d) = self.deferred.take() else {
            return;
        };
        let kept = self.spec.kept();
        let pad = self.spec.padded_len - self.n;
        // The samples are less their mean already: x − mean − 0 is x − mean, bit for bit.
        let mut spec = Spectrum::with_mean(&d.centred, 0.0, self.fs, pad);
        spec.mean = self.spec.mean;
        debug_assert_eq!(spec.padded_len, self.spec.padded_len);
        self.noise_above_band = spec.white_noise_variance(1.5 * self.fmax, self.fs / 2.0);
        self.unit = 1.0 / spectral_variance(&spec, self.n).max(f64::MIN_POSITIVE);
        self.spec = spec;
        self.spec.keep(kept);
    }

    /// Sets the white-noise variance above the band that a GPU found for a deferred signal
    /// (from its median |X|² over [`Deferred::noise_bins`]).
    pub(crate) fn set_noise_median(&mut self, median_power: Option<f64>) {
        self.noise_above_band = median_power.map(|m| self.spec.noise_variance_of(m));
    }

    fn prepare(
        x: &[f64],
        fs: f64,
        opt: &WaveletOptions,
        guide: Option<&[f64]>,
        defer: bool,
    ) -> Result<WaveletPrep, TrackError> {
        // A short deferred record is read from memory once (`WARM_SAMPLES`): what the band
        // and the centred samples need is taken from its copy, centred in place.
        let (mean, mut warm) = if defer && x.len() <= WARM_SAMPLES {
            let (mut copy, mean) = SampleBuffers::copied_with_mean(x, fs)?;
            let sums = centre_in_place(&mut copy.0, mean);
            (mean, Some((copy, sums)))
        } else {
            (checked_mean(x, fs)?, None)
        };
        let wl = opt.wavelet;
        wl.validate().map_err(TrackError::BadOption)?;
        if opt.scales < 3 || opt.scales > 4096 {
            return Err(TrackError::BadOption(format!(
                "{} scales: use between 3 and 4096",
                opt.scales
            )));
        }
        if let Some(g) = guide {
            if g.len() != x.len() {
                return Err(TrackError::BadOption(format!(
                    "the reference ridge has {} samples, the signal {}",
                    g.len(),
                    x.len()
                )));
            }
        }
        let n = x.len();
        let (fmin, fmax) = match (opt.fmin, opt.fmax) {
            (Some(a), Some(b)) => (a, b),
            (a, b) => {
                // x − mean − 0 is x − mean, bit for bit: the same band either way.
                let (da, db) = match &warm {
                    Some((centred, _)) => band_with_mean(&centred.0, 0.0, fs, &wl)?,
                    None => band_with_mean(x, mean, fs, &wl)?,
                };
                (a.unwrap_or(da), b.unwrap_or(db))
            }
        };
        if !(fmin > 0.0 && fmax > fmin && fmax <= fs / 2.0) {
            return Err(TrackError::BadOption(format!(
                "frequency range {fmin}..{fmax} Hz must satisfy 0 < fmin < fmax ≤ fs/2 = {} Hz",
                fs / 2.0
            )));
        }
        let freqs = log_frequencies(fmin, fmax, opt.scales);
        let s_count = freqs.len();
        let pad = (wl.support(wl.scale_for(fmin), 1e-8) * fs).ceil() as usize;
        let mut spec = if defer {
            Spectrum::pending(n, mean, fs, pad.min(4 * n))
        } else {
            Spectrum::with_mean(x, mean, fs, pad.min(4 * n))
        };
        // The median above the band is taken here, while the FFT has just left the spectrum
        // in the cache: the completion, which needs it, comes after the transforms (and on
        // a GPU, after the batch), used to read the bins back from memory. Beside the plans, so
        // that a long record's (700 000 bins at 2^20 samples) is not serial.
        let (noise_above_band, plans) = rayon::join(
            || {
                (!defer)
                    .then(|| spec.white_noise_variance(1.5 * fmax, fs / 2.0))
                    .flatten()
            },
            || -> Vec<ScalePlan> {
                freqs
                    .iter()
                    .map(|&f| {
                        let s = wl.scale_for(f);
                        ScalePlan::with_tolerance(&spec, &wl, s, PASS1_OVERSAMPLE, PASS1_TOLERANCE)
                    })
                    .collect()
            },
        );
        let sigma_t_min = wl.time_sigma(wl.scale_for(fmax)) * fs;
        let h = ((sigma_t_min / 2.0).floor() as usize)
            .max(s_count.div_ceil(4))
            .max(1);
        let steps = (n - 1) / h + 1;
        let (variance, deferred) = if defer {
            let (centred, sums) = match warm.take() {
                Some((mut held, sums)) => (std::mem::take(&mut held.0), sums),
                None => SampleBuffers::centred(x, mean),
            };
            let (variance, abs_sum) = sums.variance(n, spec.padded_len);
            let deferred = Deferred {
                centred,
                noise_bins: spec.noise_bins(1.5 * fmax, fs / 2.0),
                scale_exponent: crate::transform::bounding_exponent(abs_sum),
            };
            (variance, Some(Box::new(deferred)))
        } else {
            (spectral_variance(&spec, n), None)
        };
        // From here on only the pass bands are read, the first pass's and the refinement's
        // (exact, wider: `exact_plan`); the signal waits for its transforms, on a GPU for
        // its whole batch, with those bins alone: an eighth to a thirteenth of a campaign
        // run's spectrum. Holding every bin, the two GPU batches in flight of a 1000-run
        // campaign held 0.7 GB of spectra.
        let exact: Vec<ScalePlan> = plans
            .iter()
            .map(|p| super::grid::exact_plan(&spec, &wl, p.scale))
            .collect();
        let (first, count) = band::covered(plans.iter().chain(&exact), spec.bin_count());
        spec.keep(first..first + count);
        let guide = guide.map(|g| {
            (0..steps)
                .map(|j| {
                    let f = g[j * h];
                    if f > 0.0 && f.is_finite() {
                        f.ln()
                    } else {
                        f64::NAN
                    }
                })
                .collect()
        });
        Ok(WaveletPrep {
            n,
            fs,
            opt: opt.clone(),
            guide,
            fmin,
            fmax,
            freqs,
            spec,
            plans,
            h,
            steps,
            unit: 1.0 / variance.max(f64::MIN_POSITIVE),
            keep_scalogram: false,
            noise_above_band,
            deferred,
        })
    }

    /// Coarse steps inside scale `k`'s cone of influence (an inclusive range; empty when
    /// `first > last`): outside it a long scale sees the record's onset or end.
    pub fn inner_steps(&self, k: usize) -> (usize, usize) {
        let wl = self.opt.wavelet;
        let n = self.n;
        let edge = self.opt.coi * wl.time_sigma(self.plans[k].scale) * self.fs;
        inner_range(n, self.h, self.steps, edge)
    }

    /// The coarse steps whose median power estimates scale `k`'s noise floor: its inner
    /// steps, when there are at least `MIN_NOISE_STEPS` of them.
    pub fn noise_steps(&self, k: usize) -> Option<(usize, usize)> {
        let (first, last) = self.inner_steps(k);
        (last + 1 >= first + MIN_NOISE_STEPS).then_some((first, last))
    }

    /// ln f − ln g over the wavelet's relative resolution, per scale, at coarse step `j`,
    /// when the guide has a usable frequency there: the guide's pull is weight × that².
    pub fn guide_at(&self, j: usize) -> Option<f64> {
        let g = self.guide.as_ref()?[j];
        (!g.is_nan()).then_some(g)
    }

    /// The ridge penalty per squared scale step (the DP's λ).
    pub fn penalty(&self) -> f32 {
        let cell = (self.fmax / self.fmin).ln()
            / (self.freqs.len() - 1) as f64
            / self.opt.wavelet.relative_resolution();
        (self.opt.penalty * cell * cell) as f32
    }

    /// Weight of the guide's pull and the wavelet's relative resolution.
    pub fn guide_weight(&self) -> (f64, f64) {
        (
            self.opt.guide_weight,
            self.opt.wavelet.relative_resolution(),
        )
    }

    /// Whether the ridge is the penalised path (else the per-step argmax).
    pub fn dynamic_ridge(&self) -> bool {
        self.opt.ridge == RidgeSearch::Dynamic
    }

    /// The wavelet analysed with.
    pub fn wavelet(&self) -> Morlet {
        self.opt.wavelet
    }

    /// Noise gain per scale ([`ScalePlan::noise_gain`]), as [`CoarseRidge::gains`] holds
    /// them; over the scales on every core (a long record's, 2^20 samples at 256 scales,
    /// took 19 ms on one). The CPU's first pass has them from its own weights and the GPU's
    /// sums them on the device (`scales.wgsl`'s `noise_gain`); this is the reference
    /// those are checked against.
    pub fn noise_gains(&self) -> Vec<f64> {
        let wavelet = self.wavelet();
        self.plans
            .par_iter()
            .with_min_len(8)
            .map(|plan| plan.noise_gain(&self.spec, &wavelet))
            .collect()
    }

    /// Record length (samples).
    pub fn len(&self) -> usize {
        self.n
    }

    /// Always false: a prepared record has at least `MIN_SAMPLES` samples.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The first pass on the CPU: per scale, in parallel, the band-limited transform on the
    /// coarse grid, then the ridge through the log-power scores.
    pub fn coarse_ridge(&self) -> CoarseRidge {
        crate::profile::time(crate::profile::Stage::FirstPass, || {
            self.coarse_ridge_inner()
        })
    }

    fn coarse_ridge_inner(&self) -> CoarseRidge {
        let wl = self.opt.wavelet;
        let (steps, h, s_count) = (self.steps, self.h, self.freqs.len());
        let columns: Vec<Column> = self
            .plans
            .par_iter()
            .enumerate()
            .map_init(Vec::new, |buf, (k, plan)| {
                let gain = plan.evaluate_into(&self.spec, &wl, buf);
                let step = plan.step(&self.spec);
                let power: Vec<f64> = (0..steps)
                    .map(|j| interpolate(buf, (j * h) as f64 / step).norm_sqr())
                    .collect();
                // Scores in f32 relative to the record's power (a constant shift, which the
                // ridge does not see); anything 380 dB down is floored.
                let mut col: Vec<f32> = power
                    .iter()
                    .map(|&p| 0.5 * ((p * self.unit) as f32).max(f32::MIN_POSITIVE).ln())
                    .collect();
                let median = self.noise_steps(k).map(|(first, last)| {
                    let mut inner = power[first..=last].to_vec();
                    let mid = inner.len() / 2;
                    *inner.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1
                });
                let (first, last) = self.inner_steps(k);
                // Inside its cone of influence a long scale sees the record's onset or end
                // (a broadband transient) rather than the signal: keep the ridge away.
                let floor = col.iter().cloned().fold(f32::INFINITY, f32::min);
                for (j, c) in col.iter_mut().enumerate() {
                    if j < first || j > last {
                        *c = floor;
                    }
                }
                let kept = if self.keep_scalogram {
                    power.iter().map(|&p| p as f32).collect()
                } else {
                    Vec::new()
                };
                Column {
                    score: col,
                    median,
                    power: kept,
                    gain,
                }
            })
            .collect();
        let mut scores = vec![0f32; steps * s_count];
        for (k, col) in columns.iter().enumerate() {
            for j in 0..steps {
                scores[j * s_count + k] = col.score[j];
            }
        }
        if self.guide.is_some() {
            let ln_f: Vec<f64> = self.freqs.iter().map(|f| f.ln()).collect();
            let (weight, r) = self.guide_weight();
            for j in 0..steps {
                if let Some(lg) = self.guide_at(j) {
                    for k in 0..s_count {
                        let d = (ln_f[k] - lg) / r;
                        scores[j * s_count + k] -= (weight * d * d) as f32;
                    }
                }
            }
        }
        let path = if self.dynamic_ridge() {
            dp_ridge(&scores, s_count, self.penalty())
        } else {
            argmax_ridge(&scores, s_count)
        };
        let power = self.keep_scalogram.then(|| {
            columns
                .iter()
                .flat_map(|c| c.power.iter().copied())
                .collect()
        });
        CoarseRidge {
            path,
            median_power: columns.iter().map(|c| c.median).collect(),
            power,
            gains: columns.iter().map(|c| c.gain).collect(),
        }
    }

    /// Everything after the first pass, on the CPU: the estimation grid
    /// ([`grid`](Self::grid)), the skeleton at every grid point
    /// ([`estimate_grid`](Self::estimate_grid)), then [`complete`](Self::complete).
    /// `backend` names who computed `ridge`.
    pub fn finish(self, ridge: CoarseRidge, backend: Device) -> Track {
        crate::profile::time(crate::profile::Stage::Refine, || {
            let grid = self.grid(&ridge.path);
            let estimates = self.estimate_grid(&grid);
            self.complete(ridge, &grid, &estimates, backend)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::inner_range;

    /// Records of odd and even lengths, with an offset, a chirp, a tone near Nyquist (whose
    /// bin L/2 the Parseval sum must count) and noise, by automatic and given bands.
    fn deferral_records() -> Vec<(Vec<f64>, f64, super::super::WaveletOptions)> {
        use super::super::WaveletOptions;
        use super::WARM_SAMPLES;
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(23);
        let mut out = Vec::new();
        // The last one is longer than `WARM_SAMPLES`: its samples read apart for the mean, the
        // band and the centring, the others' copied once.
        for (n, fs) in [
            (3001usize, 200.0),
            (30_000, 1000.0),
            (12_345, 500.0),
            (WARM_SAMPLES + 4_003, 1000.0),
        ] {
            let x: Vec<f64> = (0..n)
                .map(|i| {
                    let t = i as f64 / fs;
                    3.0 + (2.0 * std::f64::consts::PI * (2.0 + 0.5 * t) * t).sin()
                        + 0.05 * (0.98 * std::f64::consts::PI * fs * t).cos()
                        + 0.01 * rng.random_range(-1.0..1.0)
                })
                .collect();
            out.push((x.clone(), fs, WaveletOptions::default()));
            out.push((
                x,
                fs,
                WaveletOptions {
                    fmin: Some(1.0),
                    fmax: Some(20.0),
                    scales: 40,
                    ..WaveletOptions::default()
                },
            ));
        }
        out
    }

    /// A deferred preparation is the CPU's in everything the GPU does not compute (band,
    /// scales, plans, kept bins, grid), its unit within rounding of the spectrum's (Parseval),
    /// its scaling a power of two that bounds every bin; and once materialized it is the
    /// CPU's to the bit.
    #[test]
    fn a_deferred_preparation_is_the_cpus_and_materializes_to_it() {
        use super::super::WaveletPrep;
        for (x, fs, opt) in deferral_records() {
            let cpu = WaveletPrep::new(&x, fs, &opt, None).unwrap();
            let mut gpu = WaveletPrep::new_deferred(&x, fs, &opt, None).unwrap();
            assert!(gpu.is_deferred() && !cpu.is_deferred());
            assert!(gpu.spec.is_pending());
            assert_eq!(
                (gpu.fmin, gpu.fmax, gpu.h, gpu.steps),
                (cpu.fmin, cpu.fmax, cpu.h, cpu.steps)
            );
            assert_eq!(gpu.freqs, cpu.freqs);
            assert_eq!(gpu.spec.padded_len, cpu.spec.padded_len);
            assert_eq!(gpu.spec.kept(), cpu.spec.kept());
            assert_eq!(gpu.spec.mean.to_bits(), cpu.spec.mean.to_bits());
            assert_eq!(gpu.noise_above_band, None);
            let unit = (gpu.unit - cpu.unit).abs() / cpu.unit;
            println!(
                "{} samples at {fs} Hz, band {:?}: unit by Parseval within {unit:.1e}",
                x.len(),
                (opt.fmin, opt.fmax)
            );
            assert!(unit < 1e-12, "unit {unit:e}");
            let d = gpu.deferred.as_ref().unwrap();
            let big = cpu
                .spec
                .bins(cpu.spec.kept())
                .iter()
                .map(|c| c.norm())
                .fold(0.0, f64::max);
            let scaled = big * 2f64.powi(-d.scale_exponent);
            assert!(
                scaled <= 1.0 && scaled > 1e-4,
                "largest kept bin scaled to {scaled}"
            );
            assert_eq!(
                d.noise_bins.is_some(),
                cpu.noise_above_band.is_some(),
                "noise bins where the CPU has a floor"
            );
            // The grid reads only the ridge and the plans: the same.
            let ridge = cpu.coarse_ridge();
            assert_eq!(gpu.grid(&ridge.path), cpu.grid(&ridge.path));
            gpu.materialize();
            assert!(!gpu.is_deferred() && !gpu.spec.is_pending());
            assert_eq!(gpu.unit.to_bits(), cpu.unit.to_bits());
            assert_eq!(gpu.noise_above_band, cpu.noise_above_band);
            assert_eq!(gpu.spec.kept(), cpu.spec.kept());
            assert_eq!(
                gpu.spec.bins(gpu.spec.kept()),
                cpu.spec.bins(cpu.spec.kept())
            );
            let (a, b) = (gpu.coarse_ridge(), cpu.coarse_ridge());
            assert_eq!(a, b);
        }
    }

    /// A NaN or an infinity anywhere in a record (in the lanes of the mean's sum or in its
    /// tail) is refused, and the first one named, as before the finite check was folded
    /// into the mean (`checked_mean`): at its sample index, with its value, before any
    /// option is looked at.
    #[test]
    fn a_non_finite_sample_is_refused_and_the_first_one_named_wherever_it_falls() {
        use super::super::{TrackError, WaveletOptions, WaveletPrep};
        let n = 1003;
        let clean: Vec<f64> = (0..n).map(|i| (i as f64 * 0.3).sin()).collect();
        let bad_option = WaveletOptions {
            scales: 2,
            ..WaveletOptions::default()
        };
        for (first, value) in [
            (0, f64::NAN),
            (7, f64::INFINITY),
            (500, f64::NEG_INFINITY),
            (1001, f64::NAN),
            (1002, f64::INFINITY),
        ] {
            let mut x = clean.clone();
            x[first] = value;
            // A later one of the other sign, so that two infinities could cancel to NaN.
            if first + 1 < n {
                x[n - 1] = -value;
            }
            // The CPU's preparation, and the GPU's (deferred: a record this short is copied
            // and its mean summed over the copy).
            for prepare in [WaveletPrep::new, WaveletPrep::new_deferred] {
                for opt in [WaveletOptions::default(), bad_option.clone()] {
                    match prepare(&x, 1000.0, &opt, None) {
                        Err(TrackError::NoSignal(m)) => {
                            assert!(m.starts_with(&format!("sample {first} is {value};")), "{m}")
                        }
                        Err(e) => panic!("sample {first} = {value}: {e}"),
                        Ok(_) => panic!("sample {first} = {value} was accepted"),
                    }
                }
            }
        }
        // The finite record is accepted, and the bad option still refused on it.
        for prepare in [WaveletPrep::new, WaveletPrep::new_deferred] {
            assert!(prepare(&clean, 1000.0, &WaveletOptions::default(), None).is_ok());
            assert!(matches!(
                prepare(&clean, 1000.0, &bad_option, None),
                Err(TrackError::BadOption(_))
            ));
        }
    }

    /// A campaign-like run (a 1–12 Hz chirp at 1 kHz, 30 s) waits for its transforms with
    /// the bins every pass band reads, the first pass's and the refinement's, and few more.
    #[test]
    fn a_prepared_signal_keeps_the_bins_its_pass_bands_read_and_few_others() {
        use super::super::{WaveletOptions, WaveletPrep};
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let fs = 1000.0;
        let x: Vec<f64> = (0..30_000)
            .map(|i| {
                let t = i as f64 / fs;
                (2.0 * std::f64::consts::PI * (t + 11.0 / 60.0 * t * t)).sin()
                    + 0.01 * rng.random_range(-1.0..1.0)
            })
            .collect();
        let prep = WaveletPrep::new(&x, fs, &WaveletOptions::default(), None).unwrap();
        let kept = prep.spec.kept();
        for k in 0..prep.freqs.len() {
            for plan in [&prep.plans[k], &prep.exact_plan(k)] {
                let (lo, hi, _) = plan.band();
                assert!(
                    kept.start <= lo && hi < kept.end,
                    "scale {k}: bins {lo}..={hi}, kept {kept:?}"
                );
            }
        }
        let share = kept.len() as f64 / prep.spec.bin_count() as f64;
        println!(
            "kept bins {kept:?} of {}: {:.1} % of the spectrum",
            prep.spec.bin_count(),
            100.0 * share
        );
        assert!(
            share < 0.25,
            "{} of {} bins kept",
            kept.len(),
            prep.spec.bin_count()
        );
    }

    /// The scan the closed form replaced: every step tested in turn.
    fn scanned(n: usize, h: usize, steps: usize, edge: f64) -> (usize, usize) {
        let inside = |j: usize| {
            (j * h) as f64 >= edge && (n - 1).checked_sub(j * h).is_some_and(|d| d as f64 >= edge)
        };
        let first = (0..steps).find(|&j| inside(j)).unwrap_or(steps);
        let last = (0..steps).rev().find(|&j| inside(j)).unwrap_or(0);
        (first, last)
    }

    /// The one pass that centres and sums writes exactly the centred samples and finds the
    /// bits of the sums taken apart over them: every remainder of eight, into a new buffer,
    /// one of the same length, a longer one and a shorter one, each holding other values.
    /// So does a short record's way: copied with its mean (`checked_mean`'s bits), then
    /// centred in place.
    #[test]
    fn centring_and_summing_in_one_pass_is_the_two_passes_to_the_bit() {
        use super::{centre_in_place, centre_into, parseval_variance};
        use crate::track::{checked_mean, checked_mean_copied};
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        for n in (1..=41).chain(64..=72).chain([30_001]) {
            let x: Vec<f64> = (0..n).map(|_| 2.5 + rng.random_range(-1.0..1.0)).collect();
            let mean = crate::transform::mean_of(&x);
            let centred: Vec<f64> = x.iter().map(|v| v - mean).collect();
            let l = 2 * n + 6;
            let (variance, abs) = parseval_variance(&centred, l);
            let fs = 1000.0;
            for held in [0, n, n + 9, n / 2] {
                for copied in [false, true] {
                    let mut out: Vec<f64> = vec![f64::NAN; held];
                    out.reserve(3);
                    let sums = if copied {
                        let Ok(m) = checked_mean_copied(&x, fs, &mut out) else {
                            // Too short for a track: refused as checked_mean refuses it.
                            assert!(checked_mean(&x, fs).is_err(), "{n} samples");
                            continue;
                        };
                        assert_eq!(m.to_bits(), checked_mean(&x, fs).unwrap().to_bits());
                        assert_eq!(m.to_bits(), mean.to_bits(), "{n} samples: the mean");
                        centre_in_place(&mut out, m)
                    } else {
                        centre_into(&mut out, &x, mean)
                    };
                    let (v, a) = sums.variance(n, l);
                    let way = if copied { "copied" } else { "centred" };
                    assert_eq!(out.len(), n, "{n} samples {way} into a buffer of {held}");
                    assert!(
                        out.iter()
                            .zip(&centred)
                            .all(|(p, q)| p.to_bits() == q.to_bits()),
                        "{n} samples {way} into a buffer of {held}: the centred values differ"
                    );
                    assert_eq!(
                        (v.to_bits(), a.to_bits()),
                        (variance.to_bits(), abs.to_bits()),
                        "{n} samples {way} into a buffer of {held}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_inner_range_is_the_scans_for_every_record_step_and_edge() {
        let mut checked = 0;
        for n in [1usize, 2, 7, 64, 100, 1000, 30_000] {
            for h in [1usize, 3, 8, 25] {
                let steps = n.div_ceil(h);
                for edge in [
                    -1.0, 0.0, 0.5, 1.0, 2.9, 3.0, 3.1, 24.0, 25.0, 49.99, 50.0, 333.3, 499.5,
                    500.0, 14_999.0, 15_000.0, 1e9,
                ] {
                    assert_eq!(
                        inner_range(n, h, steps, edge),
                        scanned(n, h, steps, edge),
                        "n {n}, h {h}, edge {edge}"
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked > 400);
    }
}
