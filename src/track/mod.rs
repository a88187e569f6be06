//! Instantaneous characteristics of one signal: envelope A(t), frequency f(t), phase φ(t)
//! and the derivatives ForceVib needs, by the Hilbert transform or along a complex-Morlet
//! wavelet ridge.
//!
//! The wavelet path (CPU backend):
//! 1. one real FFT of the mean-removed, zero-padded record ([`Spectrum`]);
//! 2. per scale, in parallel, the band-limited transform ([`ScalePlan`]) sampled on a coarse
//!    grid (log-magnitude only, S × N/h values of 4 bytes) and a white-noise floor estimate;
//! 3. a penalised dynamic-programming ridge on that grid, optionally pulled towards a
//!    reference ridge (a forced response follows its excitation);
//! 4. an estimation grid σ_t/8 apart at the ridge's scale; per scale the ridge visits, W,
//!    W′ and W″ (spectral derivatives), kept only around the ridge, then per grid point the
//!    three-scale parabola ([`skeleton::estimate`]);
//! 5. the window's bias from decay and sweep removed by the local model
//!    ([`skeleton::correct`]) at every grid point, then interpolated to every sample;
//! 6. samples flagged not valid: cone of influence, ridge at the edge of the scale range,
//!    in-band SNR below `min_snr`, correction that did not converge or exceeded ×2.

//!
//! Files: `hilbert` (the analytic-signal track), `wavelet` (a signal prepared up to its
//! first pass, and the CPU's first pass), `grid` (the estimation grid and the CPU's
//! refinement), `complete` (the track from the skeleton on the grid, on either backend),
//! `unwrap` (the phase made continuous).

mod complete;
mod grid;
mod hilbert;
mod unwrap;
mod wavelet;

pub use hilbert::track_hilbert;
pub use wavelet::{track_wavelet, CoarseRidge, WaveletPrep};

use thiserror::Error;

use crate::transform::{Morlet, Spectrum};

/// Decimated rate over pass band for the coarse ridge grid (|W| only, near the band centre).
const PASS1_OVERSAMPLE: f64 = 1.0;
/// Relative level at which the coarse pass cuts the wavelet's spectrum (a third fewer bins
/// than the exact passes; |W| to 1e-3 is ample for choosing a ridge and a noise floor).
const PASS1_TOLERANCE: f64 = 1e-3;
/// Decimated rate over pass band for the values interpolated to the estimation grid.
const PASS2_OVERSAMPLE: f64 = 1.0;
/// Fewest coarse steps inside a scale's cone of influence for their median to estimate
/// that scale's noise floor.
const MIN_NOISE_STEPS: usize = 8;
/// Estimation grid spacing as a fraction of the ridge scale's σ_t.
const GRID_DIVISION: f64 = 8.0;

/// Shortest record either method accepts.
pub const MIN_SAMPLES: usize = 64;

/// Why a signal could not be tracked.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum TrackError {
    /// Too few samples.
    #[error("the signal has {samples} samples; tracking needs at least {MIN_SAMPLES}")]
    TooShort {
        /// Samples given.
        samples: usize,
    },
    /// An option is out of range.
    #[error("{0}")]
    BadOption(String),
    /// Nothing but a constant or non-finite values.
    #[error("the signal has no oscillating content to track ({0})")]
    NoSignal(String),
}

/// Which estimator of the instantaneous characteristics.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// Complex-Morlet ridge and skeleton.
    Wavelet,
    /// Analytic signal by FFT.
    Hilbert,
}

impl Method {
    /// Name used in files and on the command line.
    pub fn as_str(self) -> &'static str {
        match self {
            Method::Wavelet => "wavelet",
            Method::Hilbert => "hilbert",
        }
    }
}

/// How the ridge is chosen at each time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum RidgeSearch {
    /// Penalised dynamic programming over the whole record.
    Dynamic,
    /// The largest |W| at each time (what most tools do; for comparison).
    Argmax,
}

/// Options of the wavelet method.
#[derive(Debug, Clone, serde::Serialize)]
pub struct WaveletOptions {
    /// Mother wavelet.
    pub wavelet: Morlet,
    /// Lowest analysis frequency (Hz); chosen from the spectrum when `None`.
    pub fmin: Option<f64>,
    /// Highest analysis frequency (Hz); chosen from the spectrum when `None`.
    pub fmax: Option<f64>,
    /// Number of log-spaced scales.
    pub scales: usize,
    /// Ridge search.
    pub ridge: RidgeSearch,
    /// Cost of moving the ridge by one frequency-resolution cell (σ_f/f) between grid steps,
    /// in nepers of |W|.
    pub penalty: f64,
    /// Cost per squared resolution cell of leaving the reference ridge, when one is given.
    pub guide_weight: f64,
    /// Samples whose ridge magnitude is below this multiple of the in-band noise are not valid.
    pub min_snr: f64,
    /// Cone of influence: samples closer to an end than this many σ_t are not valid.
    pub coi: f64,
    /// Remove the window's bias from decay and sweep (the local-model correction).
    pub correct: bool,
    /// Below this in-band SNR, average ln A and f over a window that grows as (SNR)⁻²
    /// (up to ±16 σ_t), in part from √2 times it down; 0 turns it off.
    pub smooth_snr: f64,
}

impl Default for WaveletOptions {
    fn default() -> Self {
        Self {
            wavelet: Morlet::default(),
            fmin: None,
            fmax: None,
            scales: 64,
            ridge: RidgeSearch::Dynamic,
            penalty: 1.0,
            guide_weight: 1.0,
            min_snr: 10.0,
            coi: 3.0,
            correct: true,
            smooth_snr: 100.0,
        }
    }
}

impl WaveletOptions {
    /// Refuses what no record can be analysed with, before any work: the wavelet, the
    /// number of scales, and a band whose ends are not positive or not in order. (The band
    /// against a record's Nyquist frequency is checked per record.)
    pub fn validate(&self) -> Result<(), String> {
        self.wavelet.validate()?;
        if !(3..=4096).contains(&self.scales) {
            return Err(format!("{} scales: use between 3 and 4096", self.scales));
        }
        for (name, f) in [("fmin", self.fmin), ("fmax", self.fmax)] {
            if let Some(f) = f {
                if !(f.is_finite() && f > 0.0) {
                    return Err(format!("{name} = {f} Hz must be a positive frequency"));
                }
            }
        }
        if let (Some(lo), Some(hi)) = (self.fmin, self.fmax) {
            if lo >= hi {
                return Err(format!(
                    "fmin = {lo} Hz must be below fmax = {hi} Hz (the band is fmin..fmax)"
                ));
            }
        }
        Ok(())
    }
}

/// Options of the Hilbert method.
#[derive(Debug, Clone, Default)]
pub struct HilbertOptions {
    /// Zero-phase low-pass of envelope, frequency and their derivatives, cut-off as a
    /// fraction of the Nyquist frequency (the paper uses 0.0005–0.01); `None`: unfiltered.
    pub cutoff: Option<f64>,
}

/// Instantaneous characteristics of one signal, one value per sample.
#[derive(Debug, Clone)]
pub struct Track {
    /// Method that produced it.
    pub method: Method,
    /// Sample rate (Hz).
    pub sample_rate: f64,
    /// Envelope A (signal units).
    pub amplitude: Vec<f64>,
    /// Instantaneous frequency f = φ'/2π (Hz).
    pub frequency: Vec<f64>,
    /// Unwrapped phase φ (rad).
    pub phase: Vec<f64>,
    /// A' (units/s).
    pub d_amplitude: Vec<f64>,
    /// A'' (units/s²).
    pub d2_amplitude: Vec<f64>,
    /// f' (Hz/s); ω' = 2π f'.
    pub d_frequency: Vec<f64>,
    /// Trusted samples (not edge, not below the noise, ridge found).
    pub valid: Vec<bool>,
    /// Mean removed before the transform (the record's offset), signal units.
    pub offset: f64,
    /// Estimated white-noise standard deviation per sample (signal units).
    pub noise: f64,
    /// Analysis range (Hz) of the wavelet method; the whole band for Hilbert.
    pub band: (f64, f64),
    /// Where the all-scale transform and the ridge were evaluated.
    pub backend: Device,
    /// The first pass's |W| on its coarse grid, when asked for (`--keep-scalogram`).
    pub scalogram: Option<Scalogram>,
}

/// Where a track's wavelet transform was evaluated (results.h5 `backend`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Device {
    /// The CPU backend (every Hilbert track too).
    Cpu,
    /// The GPU backend.
    Gpu,
}

impl Device {
    /// The name written to results.h5 and printed.
    pub fn as_str(self) -> &'static str {
        match self {
            Device::Cpu => "cpu",
            Device::Gpu => "gpu",
        }
    }
}

/// |W| of every scale on the first pass's coarse time grid.
#[derive(Debug, Clone)]
pub struct Scalogram {
    /// Frequency of each scale (Hz).
    pub frequency: Vec<f64>,
    /// Time of each coarse step (s).
    pub time: Vec<f64>,
    /// |W| (signal units), scale-major: `[k · time.len() + j]`.
    pub magnitude: Vec<f32>,
}

impl Track {
    /// Number of samples.
    pub fn len(&self) -> usize {
        self.amplitude.len()
    }
    /// True for an empty track.
    pub fn is_empty(&self) -> bool {
        self.amplitude.is_empty()
    }
    /// Fraction of samples marked valid.
    pub fn valid_fraction(&self) -> f64 {
        self.valid.iter().filter(|&&v| v).count() as f64 / self.len().max(1) as f64
    }
    /// Times (s) of the samples.
    pub fn time(&self) -> Vec<f64> {
        (0..self.len())
            .map(|i| i as f64 / self.sample_rate)
            .collect()
    }
}

/// Refuses a record too short, a sample rate that is not a positive number, or any
/// sample that is not finite.
fn check_signal(x: &[f64], fs: f64) -> Result<(), TrackError> {
    check_shape(x, fs)?;
    check_finite(x)
}

/// [`check_signal`]'s checks and the record's mean ([`mean_of`](crate::transform::mean_of))
/// in one pass over the samples: a NaN or an infinity makes the mean so, and only then are
/// the samples searched for the first one (a second pass over every record, 19 µs of a
/// campaign run's 500 µs preparation, measured alone).
fn checked_mean(x: &[f64], fs: f64) -> Result<f64, TrackError> {
    check_shape(x, fs)?;
    let mean = crate::transform::mean_of(x);
    if !mean.is_finite() {
        check_finite(x)?;
    }
    Ok(mean)
}

/// [`checked_mean`] of `x` taken over its copy in `out` (what it held before dropped),
/// where the copy has just left the samples in the cache: the same checks, messages and
/// bits, and `x` read from memory once, not once for each.
fn checked_mean_copied(x: &[f64], fs: f64, out: &mut Vec<f64>) -> Result<f64, TrackError> {
    out.clear();
    out.extend_from_slice(x);
    checked_mean(out, fs)
}

/// [`check_signal`]'s checks of the length and the sample rate alone.
fn check_shape(x: &[f64], fs: f64) -> Result<(), TrackError> {
    if x.len() < MIN_SAMPLES {
        return Err(TrackError::TooShort { samples: x.len() });
    }
    if !(fs.is_finite() && fs > 0.0) {
        return Err(TrackError::BadOption(format!(
            "sample rate {fs} Hz must be a positive number"
        )));
    }
    Ok(())
}

/// [`check_signal`]'s check that every sample is finite, naming the first that is not.
fn check_finite(x: &[f64]) -> Result<(), TrackError> {
    non_finite(x).map_or(Ok(()), |why| Err(TrackError::NoSignal(why)))
}

/// The first sample of `x` that is not finite, in words and with what to do ("sample 7 is
/// NaN; remove or interpolate non-finite samples first"); `None` where every one is.
pub(crate) fn non_finite(x: &[f64]) -> Option<String> {
    let i = x.iter().position(|v| !v.is_finite())?;
    Some(format!(
        "sample {i} is {}; remove or interpolate non-finite samples first",
        x[i]
    ))
}

/// The mean of each bin's power and the `w − 1` before it (of all before it in the first
/// `w` bins), by running sums, and the largest of those means (0 if none is above). The
/// first `w` bins, whose count grows, are one chain; the rest is cut into stretches of
/// [`STRETCH`] bins, each cut into [`LANES`] lanes slid side by side from their own first
/// window's sum. One chain of two additions a bin was a fifth of a signal's deferred
/// preparation; a stretch's lanes hide each other's latency, and a long record's
/// stretches go on every core. Where the lanes start is fixed by `w` and the length
/// alone, so the bits do not depend on the threads.
fn running_mean(p: &[f64], w: usize) -> (Vec<f64>, f64) {
    use rayon::prelude::*;
    let n = p.len();
    let mut smooth: Vec<f64> = Vec::with_capacity(n);
    let head = w.min(n);
    let out = &mut smooth.spare_capacity_mut()[..n];
    let (first, rest) = out.split_at_mut(head);
    let mut acc = 0.0;
    let mut peak = 0.0f64;
    for (i, o) in first.iter_mut().enumerate() {
        acc += p[i];
        let v = acc / (i + 1) as f64;
        o.write(v);
        peak = peak.max(v);
    }
    let peak = rest
        .par_chunks_mut(STRETCH)
        .enumerate()
        .map(|(c, o)| slide(p, w, head + c * STRETCH, o))
        .reduce(|| peak, f64::max);
    // SAFETY: the first `head` values were written above, and `slide` writes every value
    // of its stretch.
    unsafe { smooth.set_len(n) };
    (smooth, peak)
}

/// Bins a task of [`running_mean`] slides over (a long record's 524 288 bins go on every
/// core; a campaign record's 15 000 are one task).
const STRETCH: usize = 1 << 16;

/// Lanes of [`running_mean`] slid side by side in one stretch.
const LANES: usize = 4;

/// The window means of `out.len()` bins from bin `start` (at least `w`) of `p`, written to
/// `out`, and their largest: [`LANES`] equal lanes side by side, the bins left over after
/// them on the last lane's chain.
fn slide(p: &[f64], w: usize, start: usize, out: &mut [std::mem::MaybeUninit<f64>]) -> f64 {
    let len = out.len();
    let lane = len / LANES;
    let width = w as f64;
    // Each lane's sum over the window before its first bin, so that its first step (one
    // bin in, one out) gives its first bin's window.
    let window = |at: usize| p[at - w..at].iter().sum::<f64>();
    let mut acc = [0.0f64; LANES];
    let mut peak = [0.0f64; LANES];
    for (k, a) in acc.iter_mut().enumerate() {
        *a = window(start + k * lane);
    }
    for t in 0..lane {
        for k in 0..LANES {
            let i = start + k * lane + t;
            acc[k] += p[i];
            acc[k] -= p[i - w];
            let v = acc[k] / width;
            out[k * lane + t].write(v);
            peak[k] = peak[k].max(v);
        }
    }
    let mut last = acc[LANES - 1];
    let mut top = peak.iter().copied().fold(0.0f64, f64::max);
    for (t, o) in out.iter_mut().enumerate().skip(LANES * lane) {
        let i = start + t;
        last += p[i];
        last -= p[i - w];
        let v = last / width;
        o.write(v);
        top = top.max(v);
    }
    top
}

/// Analysis band chosen from the record's spectrum: where the smoothed power stands above
/// both 1e-4 of its peak and ten times the noise floor, widened by 25 %, no lower than the
/// frequency whose cone of influence leaves half the record, no higher than 0.45 fs.
pub fn default_band(x: &[f64], fs: f64, wavelet: &Morlet) -> Result<(f64, f64), TrackError> {
    band_with_mean(x, crate::transform::mean_of(x), fs, wavelet)
}

/// [`default_band`] of a record whose mean is already taken.
pub(crate) fn band_with_mean(
    x: &[f64],
    mean: f64,
    fs: f64,
    wavelet: &Morlet,
) -> Result<(f64, f64), TrackError> {
    let spec = Spectrum::with_mean(x, mean, fs, 0);
    // The noise floor's median beside the smoothing, so that a long record's (524 000
    // bins at 2^20 samples) does not wait for it.
    let w = (spec.bin_count() / 1024).max(1);
    let ((smooth, peak), floor) = rayon::join(
        || {
            use rayon::prelude::*;
            let p: Vec<f64> = spec.all_bins().par_iter().map(|c| c.norm_sqr()).collect();
            running_mean(&p, w)
        },
        || {
            spec.white_noise_variance(fs / 4.0, fs / 2.0)
                .map(|v| v * x.len() as f64)
                .unwrap_or(0.0)
        },
    );
    if peak <= 0.0 {
        return Err(TrackError::NoSignal("the record is constant".into()));
    }
    let thr = (peak * 1e-4).max(10.0 * floor);
    let above = |m: &usize| smooth[*m] > thr;
    let (Some(lo), Some(hi)) = (
        (1..smooth.len()).find(above),
        (1..smooth.len()).rfind(above),
    ) else {
        return Err(TrackError::NoSignal(
            "no part of the spectrum stands above the noise".into(),
        ));
    };
    let duration = x.len() as f64 / fs;
    let record_floor = 12.0 * wavelet.centre * (wavelet.bandwidth / 2.0).sqrt() / duration;
    let fmin = (spec.bin_freq(lo.saturating_sub(w / 2).max(1)) / 1.25).max(record_floor);
    let fmax = (spec.bin_freq(hi + w / 2) * 1.25).min(0.45 * fs);
    if fmin >= fmax {
        return Err(TrackError::NoSignal(format!(
            "the signal's band (up to {:.3} Hz) lies below the lowest frequency a {duration:.1} s record can resolve ({record_floor:.3} Hz); give {} or a narrower wavelet ({})",
            spec.bin_freq(hi),
            crate::hint::Hint::FrequencyRange,
            crate::hint::Hint::Bandwidth
        )));
    }
    Ok((fmin, fmax))
}

#[cfg(test)]
mod tests {
    use super::running_mean;

    /// The band's running mean against each window summed afresh: its first `w` bins
    /// (one chain, as before the lanes) to the bit, every other bin within the running
    /// sums' rounding, the peak the largest mean to the bit, and the same bits in a pool
    /// of one thread and of three. Lengths cross the lanes' and the stretches' seams.
    #[test]
    fn the_running_mean_is_each_windows_mean_and_its_peak_the_largest() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(17);
        let in_pool = |threads: usize, p: &[f64], w: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a pool")
                .install(|| running_mean(p, w))
        };
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        // The largest difference from a window summed afresh, relative to the mean.
        let mut worst = 0.0f64;
        for len in [0usize, 1, 2, 5, 7, 64, 1000, 70_001, 140_003] {
            // Powers within one decade, so that a window one bin off (a bin's power over
            // `w`) stands far above the sums' rounding.
            let p: Vec<f64> = (0..len).map(|_| rng.random_range(1.0..10.0)).collect();
            let windows: Vec<usize> = if len > 10_000 {
                vec![1, 3, 14, 512]
            } else {
                (1..=len + 2)
                    .filter(|w| *w <= 9 || w % 97 == 0 || *w >= len)
                    .collect()
            };
            for w in windows {
                let (got, peak) = in_pool(1, &p, w);
                let (again, again_peak) = in_pool(3, &p, w);
                assert_eq!(bits(&got), bits(&again), "{len} bins, window {w}: threads");
                assert_eq!(peak.to_bits(), again_peak.to_bits());
                assert_eq!(got.len(), len);
                let mut chain = 0.0;
                for (i, g) in got.iter().enumerate() {
                    let from = (i + 1).saturating_sub(w);
                    let count = (i + 1 - from) as f64;
                    if i < w {
                        chain += p[i];
                        assert_eq!(g.to_bits(), (chain / count).to_bits(), "head bin {i}");
                    }
                    let fresh = p[from..=i].iter().sum::<f64>() / count;
                    worst = worst.max((g - fresh).abs() / fresh);
                    // Each slide rounds twice; a lane slides at most a stretch.
                    let tol = 4.0 * f64::EPSILON * (i.min(1 << 16) + w) as f64 * 10.0;
                    assert!(
                        (g - fresh).abs() <= tol,
                        "{len} bins, window {w}, bin {i}: {g} against {fresh}"
                    );
                }
                let largest = got.iter().copied().fold(0.0, f64::max);
                assert_eq!(peak.to_bits(), largest.to_bits(), "{len} bins, window {w}");
            }
        }
        eprintln!("running means within {worst:.1e} (relative) of each window summed afresh");
        // Powers over 30 decades: the first w bins still the chain's bits, the peak still
        // the largest mean.
        let p: Vec<f64> = (0..5000)
            .map(|_| 10f64.powf(rng.random_range(-20.0..10.0)))
            .collect();
        for w in [1, 5, 97, 4999, 6000] {
            let (got, peak) = running_mean(&p, w);
            let mut chain = 0.0;
            for i in 0..w.min(p.len()) {
                chain += p[i];
                assert_eq!(got[i].to_bits(), (chain / (i + 1) as f64).to_bits());
            }
            let largest = got.iter().copied().fold(0.0, f64::max);
            assert_eq!(peak.to_bits(), largest.to_bits(), "window {w}");
        }
    }
}
