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

use std::f64::consts::PI;

use num_complex::Complex64;
use rayon::prelude::*;
use thiserror::Error;

use crate::filter::{local_line_weighted, local_slope, lowpass_zero_phase};
use crate::ridge::{argmax_ridge, dp_ridge};
use crate::skeleton::{self, GridEstimate, GridPoint, ScaleValue};
use crate::transform::band::{interpolate, ScalePlan};
use crate::transform::{hilbert, log_frequencies, Morlet, Spectrum};

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
    /// (up to ±16 σ_t); 0 turns it off.
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
    /// Backend that evaluated the all-scale transform and the ridge: `cpu` or `gpu`.
    pub backend: &'static str,
    /// The first pass's |W| on its coarse grid, when asked for (`--keep-scalogram`).
    pub scalogram: Option<Scalogram>,
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

fn check_signal(x: &[f64], fs: f64) -> Result<(), TrackError> {
    if x.len() < MIN_SAMPLES {
        return Err(TrackError::TooShort { samples: x.len() });
    }
    if !(fs.is_finite() && fs > 0.0) {
        return Err(TrackError::BadOption(format!(
            "sample rate {fs} Hz must be a positive number"
        )));
    }
    if let Some(i) = x.iter().position(|v| !v.is_finite()) {
        return Err(TrackError::NoSignal(format!(
            "sample {i} is {}; remove or interpolate non-finite samples first",
            x[i]
        )));
    }
    Ok(())
}

/// Envelope, frequency and derivatives by the Hilbert transform.
///
/// Derivatives are spectral (z', z'' by FFT); with a cut-off they, A and f are low-passed by
/// the same zero-phase filter. Valid: away from the ends by two periods of the median
/// frequency (where the FFT's periodic extension distorts z).
pub fn track_hilbert(x: &[f64], fs: f64, opt: &HilbertOptions) -> Result<Track, TrackError> {
    crate::profile::time(crate::profile::Stage::Hilbert, || hilbert_inner(x, fs, opt))
}

fn hilbert_inner(x: &[f64], fs: f64, opt: &HilbertOptions) -> Result<Track, TrackError> {
    check_signal(x, fs)?;
    if let Some(c) = opt.cutoff {
        if !(c > 0.0 && c < 1.0) {
            return Err(TrackError::BadOption(format!(
                "Hilbert cut-off {c} must be a fraction of Nyquist between 0 and 1 (e.g. 0.005)"
            )));
        }
    }
    let n = x.len();
    let an = hilbert::analytic(x, fs);
    let mut amplitude = Vec::with_capacity(n);
    let mut frequency = Vec::with_capacity(n);
    let mut d_amplitude = Vec::with_capacity(n);
    let mut d2_amplitude = Vec::with_capacity(n);
    let mut d_frequency = Vec::with_capacity(n);
    for i in 0..n {
        let z = an.z[i];
        let a = z.norm();
        if a == 0.0 {
            amplitude.push(0.0);
            frequency.push(0.0);
            d_amplitude.push(0.0);
            d2_amplitude.push(0.0);
            d_frequency.push(0.0);
            continue;
        }
        let r1 = an.dz[i] / z; // A'/A + jφ'
        let r2 = an.d2z[i] / z; // A''/A − φ'² + j(2A'φ'/A + φ'')
        let w = r1.im;
        amplitude.push(a);
        frequency.push(w / (2.0 * PI));
        d_amplitude.push(a * r1.re);
        d2_amplitude.push(a * (r2.re + w * w));
        d_frequency.push((r2.im - 2.0 * r1.re * w) / (2.0 * PI));
    }
    let mut phase: Vec<f64> = an.z.iter().map(|z| z.arg()).collect();
    unwrap_phase(&mut phase, &frequency, |i| i as f64 / fs);
    if let Some(c) = opt.cutoff {
        for v in [
            &mut amplitude,
            &mut frequency,
            &mut d_amplitude,
            &mut d2_amplitude,
            &mut d_frequency,
        ] {
            *v = lowpass_zero_phase(v, c);
        }
    }
    let mut sorted: Vec<f64> = frequency.iter().map(|f| f.abs()).collect();
    let mid = sorted.len() / 2;
    let median_f = *sorted.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
    let edge = if median_f > 0.0 {
        ((2.0 * fs / median_f).ceil() as usize).min(n / 2)
    } else {
        n / 2
    };
    let valid = (0..n).map(|i| i >= edge && i + edge < n).collect();
    let noise = hilbert_noise(x, fs);
    Ok(Track {
        method: Method::Hilbert,
        sample_rate: fs,
        amplitude,
        frequency,
        phase,
        d_amplitude,
        d2_amplitude,
        d_frequency,
        valid,
        offset: an.mean,
        noise,
        band: (0.0, fs / 2.0),
        backend: "cpu",
        scalogram: None,
    })
}

fn hilbert_noise(x: &[f64], fs: f64) -> f64 {
    Spectrum::new(x, fs, 0)
        .white_noise_variance(fs / 4.0, fs / 2.0)
        .unwrap_or(0.0)
        .sqrt()
}

/// Makes a wrapped phase continuous, choosing at each step the branch closest to the
/// advance predicted by the frequency; `time(i)` is point i's time (s).
fn unwrap_phase(phase: &mut [f64], freq: &[f64], time: impl Fn(usize) -> f64) {
    for i in 1..phase.len() {
        let dt = time(i) - time(i - 1);
        let predicted = phase[i - 1] + PI * (freq[i - 1] + freq[i]) * dt;
        let d = phase[i] - predicted;
        phase[i] -= 2.0 * PI * ((d + PI) / (2.0 * PI)).floor();
    }
}

/// Analysis band chosen from the record's spectrum: where the smoothed power stands above
/// both 1e-4 of its peak and ten times the noise floor, widened by 25 %, no lower than the
/// frequency whose cone of influence leaves half the record, no higher than 0.45 fs.
pub fn default_band(x: &[f64], fs: f64, wavelet: &Morlet) -> Result<(f64, f64), TrackError> {
    let spec = Spectrum::new(x, fs, 0);
    let p: Vec<f64> = spec.bins.iter().map(|c| c.norm_sqr()).collect();
    let w = (p.len() / 1024).max(1);
    let mut smooth = vec![0.0; p.len()];
    let mut acc = 0.0;
    for i in 0..p.len() {
        acc += p[i];
        if i >= w {
            acc -= p[i - w];
        }
        smooth[i] = acc / w.min(i + 1) as f64;
    }
    let peak = smooth.iter().cloned().fold(0.0, f64::max);
    if peak <= 0.0 {
        return Err(TrackError::NoSignal("the record is constant".into()));
    }
    let floor = spec
        .white_noise_variance(fs / 4.0, fs / 2.0)
        .map(|v| v * x.len() as f64)
        .unwrap_or(0.0);
    let thr = (peak * 1e-4).max(10.0 * floor);
    let above: Vec<usize> = (1..smooth.len()).filter(|&m| smooth[m] > thr).collect();
    let (Some(&lo), Some(&hi)) = (above.first(), above.last()) else {
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
            "the signal's band (up to {:.3} Hz) lies below the lowest frequency a {duration:.1} s record can resolve ({record_floor:.3} Hz); give --fmin/--fmax or a narrower wavelet (--bandwidth)",
            spec.bin_freq(hi)
        )));
    }
    Ok((fmin, fmax))
}

/// Scale values W, W', W'' kept around the ridge for one scale and one stretch of time.
struct Segment {
    /// First decimated index held (may be negative: periodic).
    first: isize,
    w: Vec<Complex64>,
    d1: Vec<Complex64>,
    d2: Vec<Complex64>,
    /// Samples (inclusive range) this segment serves.
    samples: (usize, usize),
}

/// One scale's first pass on the CPU: its ridge scores, noise median, kept |W|² (when a
/// scalogram is kept) and noise gain.
struct Column {
    score: Vec<f32>,
    median: Option<f64>,
    power: Vec<f32>,
    gain: f64,
}

/// Everything kept for one scale after the second pass.
struct ScaleData {
    plan: ScalePlan,
    step: f64,
    segments: Vec<Segment>,
}

impl ScaleData {
    fn segment(&self, n: usize) -> Option<&Segment> {
        let i = self.segments.partition_point(|s| s.samples.1 < n);
        self.segments.get(i).filter(|s| s.samples.0 <= n)
    }

    fn value(&self, spec: &Spectrum, n: usize) -> Option<ScaleValue> {
        let seg = self.segment(n)?;
        let x = n as f64 / self.step - seg.first as f64;
        let w = interpolate(&seg.w, x);
        let w1 = interpolate(&seg.d1, x);
        let w2 = interpolate(&seg.d2, x);
        let d1 = w1 / w;
        Some(ScaleValue {
            scale: self.plan.scale,
            ln_amp: w.norm().max(1e-300).ln(),
            phase: w.arg() + self.plan.carrier(spec, n as f64),
            d1,
            d2: w2 / w - d1 * d1,
        })
    }
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
    Ok(prep.finish(ridge, "cpu"))
}

/// A wavelet track set up to its first pass: the spectrum, the scales and their band
/// plans, and the coarse grid. The first pass (all scales, then the ridge) is what a
/// backend evaluates — [`coarse_ridge`](Self::coarse_ridge) on the CPU, `gpu::ridge` on
/// a GPU for many runs at once; [`finish`](Self::finish) does the rest on the CPU.
pub struct WaveletPrep {
    n: usize,
    fs: f64,
    opt: WaveletOptions,
    /// ln of the guide's frequency at each coarse step (NaN where it has none).
    guide: Option<Vec<f64>>,
    fmin: f64,
    fmax: f64,
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

impl WaveletPrep {
    /// Checks the signal and options, chooses the band and scales, and takes the spectrum.
    pub fn new(
        x: &[f64],
        fs: f64,
        opt: &WaveletOptions,
        guide: Option<&[f64]>,
    ) -> Result<WaveletPrep, TrackError> {
        crate::profile::time(crate::profile::Stage::FirstPass, || {
            Self::prepare(x, fs, opt, guide)
        })
    }

    fn prepare(
        x: &[f64],
        fs: f64,
        opt: &WaveletOptions,
        guide: Option<&[f64]>,
    ) -> Result<WaveletPrep, TrackError> {
        check_signal(x, fs)?;
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
                let (da, db) = default_band(x, fs, &wl)?;
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
        let spec = Spectrum::new(x, fs, pad.min(4 * n));
        let plans: Vec<ScalePlan> = freqs
            .iter()
            .map(|&f| {
                let s = wl.scale_for(f);
                ScalePlan::with_tolerance(&spec, &wl, s, PASS1_OVERSAMPLE, PASS1_TOLERANCE)
            })
            .collect();
        let sigma_t_min = wl.time_sigma(wl.scale_for(fmax)) * fs;
        let h = ((sigma_t_min / 2.0).floor() as usize)
            .max(s_count.div_ceil(4))
            .max(1);
        let steps = (n - 1) / h + 1;
        let variance = spec.bins.iter().map(|b| b.norm_sqr()).sum::<f64>() * 2.0
            / (n as f64 * spec.padded_len as f64);
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
        })
    }

    /// Coarse steps inside scale `k`'s cone of influence (an inclusive range; empty when
    /// `first > last`): outside it a long scale sees the record's onset or end.
    pub fn inner_steps(&self, k: usize) -> (usize, usize) {
        let wl = self.opt.wavelet;
        let n = self.n;
        let edge = self.opt.coi * wl.time_sigma(self.plans[k].scale) * self.fs;
        let inside =
            |j: usize| (j * self.h) as f64 >= edge && ((n - 1 - j * self.h) as f64) >= edge;
        let first = (0..self.steps).find(|&j| inside(j)).unwrap_or(self.steps);
        let last = (0..self.steps).rev().find(|&j| inside(j)).unwrap_or(0);
        (first, last)
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
    pub fn finish(self, ridge: CoarseRidge, backend: &'static str) -> Track {
        crate::profile::time(crate::profile::Stage::Refine, || {
            let grid = self.grid(&ridge.path);
            let estimates = self.estimate_grid(&grid);
            self.complete(ridge, &grid, &estimates, backend)
        })
    }

    /// The ridge's scale index at sample `i`, linear between coarse steps.
    fn ridge_at(&self, path: &[usize], i: usize) -> usize {
        let (h, steps) = (self.h, self.steps);
        let j = i / h;
        let u = (i % h) as f64 / h as f64;
        let a = path[j] as f64;
        let b = path[(j + 1).min(steps - 1)] as f64;
        (a + u * (b - a)).round() as usize
    }

    /// The estimation grid: σ_t/`GRID_DIVISION` apart at the ridge's scale, from the first
    /// sample to the last. Everything after it is computed on this grid; the per-sample track
    /// is interpolated at the end. Each point carries the ridge's scale there, kept one scale
    /// inside the range so that it has a neighbour on each side.
    pub fn grid(&self, path: &[usize]) -> Vec<GridPoint> {
        let wl = self.opt.wavelet;
        let (n, fs, s_count) = (self.n, self.fs, self.freqs.len());
        let mut grid = Vec::new();
        let mut i = 0usize;
        while i < n {
            let k = self.ridge_at(path, i);
            grid.push(GridPoint {
                sample: i,
                centre: k.clamp(1, s_count - 2),
            });
            let st = wl.time_sigma(wl.scale_for(self.freqs[k])) * fs;
            i += ((st / GRID_DIVISION).floor() as usize).max(1);
        }
        if grid.last().expect("n ≥ 1").sample != n - 1 {
            let k = self.ridge_at(path, n - 1);
            grid.push(GridPoint {
                sample: n - 1,
                centre: k.clamp(1, s_count - 2),
            });
        }
        grid
    }

    /// Per scale, the stretches of samples (inclusive) where `grid` needs its W, W′, W″:
    /// within ±2 of the ridge (the best of its three neighbours, and that one's neighbours
    /// for the parabola). Empty for a scale the ridge never comes near.
    pub fn wanted(&self, grid: &[GridPoint]) -> Vec<Vec<(usize, usize)>> {
        let s_count = self.freqs.len();
        let mut wanted: Vec<Vec<(usize, usize)>> = vec![Vec::new(); s_count];
        for (g, p) in grid.iter().enumerate() {
            let c = p.centre;
            let (lo, hi) = (c.saturating_sub(2), (c + 2).min(s_count - 1));
            let prev = g.checked_sub(1).map(|q| grid[q].sample);
            for runs in &mut wanted[lo..=hi] {
                match runs.last_mut() {
                    Some(r) if Some(r.1) == prev => r.1 = p.sample,
                    _ => runs.push((p.sample, p.sample)),
                }
            }
        }
        wanted
    }

    /// The pass-2 plan of scale `k`: the exact pass band (the first pass cut it at 1e-3),
    /// for the W, W′, W″ the skeleton is estimated from.
    pub fn exact_plan(&self, k: usize) -> ScalePlan {
        ScalePlan::new(
            &self.spec,
            &self.opt.wavelet,
            self.plans[k].scale,
            PASS2_OVERSAMPLE,
        )
    }

    /// Whether the window's bias is removed ([`WaveletOptions::correct`]).
    pub fn corrects(&self) -> bool {
        self.opt.correct
    }

    /// The skeleton at every grid point on the CPU: W, W′, W″ of the scales the ridge comes
    /// near (pass 2), then per point the three-scale estimate and its bias correction
    /// ([`skeleton::estimate_point`]).
    pub fn estimate_grid(&self, grid: &[GridPoint]) -> Vec<GridEstimate> {
        let wl = self.opt.wavelet;
        let s_count = self.freqs.len();
        let spec = &self.spec;
        let data: Vec<ScaleData> = self
            .wanted(grid)
            .into_par_iter()
            .enumerate()
            .map(|(k, runs)| {
                let plan = self.exact_plan(k);
                let step = plan.step(spec);
                if runs.is_empty() {
                    return ScaleData {
                        plan,
                        step,
                        segments: Vec::new(),
                    };
                }
                let [w, d1, d2] = plan.evaluate_with_derivatives(spec, &wl).map(|d| d.values);
                let m = w.len() as isize;
                let take = |v: &[Complex64], a: isize, b: isize| -> Vec<Complex64> {
                    (a..=b).map(|i| v[i.rem_euclid(m) as usize]).collect()
                };
                let segments = runs
                    .iter()
                    .map(|&(s0, s1)| {
                        let a = (s0 as f64 / step).floor() as isize - 2;
                        let b = (s1 as f64 / step).floor() as isize + 3;
                        Segment {
                            first: a,
                            w: take(&w, a, b),
                            d1: take(&d1, a, b),
                            d2: take(&d2, a, b),
                            samples: (s0, s1),
                        }
                    })
                    .collect();
                ScaleData {
                    plan,
                    step,
                    segments,
                }
            })
            .collect();
        let scales: Vec<f64> = self.freqs.iter().map(|&f| wl.scale_for(f)).collect();
        grid.par_iter()
            .map(|p| {
                skeleton::estimate_point(
                    &wl,
                    &scales,
                    &self.freqs,
                    p.centre,
                    self.opt.correct,
                    |k| {
                        (k < s_count)
                            .then(|| data[k].value(spec, p.sample))
                            .flatten()
                    },
                )
            })
            .collect()
    }

    /// The track from the skeleton on the grid, on the CPU whichever backend estimated it:
    /// the white-noise floor (from the first pass's per-scale medians and the spectrum above
    /// the band), validity (cone of influence, band, SNR, failed corrections), low-SNR
    /// smoothing, the phase unwrapped, σ′, and every sample interpolated from the grid.
    pub fn complete(
        self,
        ridge: CoarseRidge,
        grid: &[GridPoint],
        est: &[GridEstimate],
        backend: &'static str,
    ) -> Track {
        let scalogram = ridge.power.as_ref().map(|p| Scalogram {
            frequency: self.freqs.clone(),
            time: (0..self.steps)
                .map(|j| (j * self.h) as f64 / self.fs)
                .collect(),
            magnitude: p.iter().map(|v| v.max(0.0).sqrt()).collect(),
        });
        let WaveletPrep {
            n,
            fs,
            opt,
            fmin,
            fmax,
            spec,
            ..
        } = self;
        let opt = &opt;
        let wl = opt.wavelet;
        // White-noise floor: the lower of the quietest quarter of the scales (median over
        // time) and the spectrum above the analysis band, where only noise should be left.
        let gains = ridge.gains;
        let mut per_scale: Vec<f64> = ridge
            .median_power
            .iter()
            .zip(&gains)
            .filter_map(|(m, g)| m.map(|m| m / std::f64::consts::LN_2 / (n as f64 * g)))
            .collect();
        let from_scales = if per_scale.is_empty() {
            f64::INFINITY
        } else {
            let q = per_scale.len() / 4;
            *per_scale.select_nth_unstable_by(q, |a, b| a.total_cmp(b)).1
        };
        let from_spectrum = spec
            .white_noise_variance(1.5 * fmax, fs / 2.0)
            .unwrap_or(f64::INFINITY);
        let noise_var = from_scales.min(from_spectrum);
        let noise_var = if noise_var.is_finite() {
            noise_var
        } else {
            0.0
        };
        let noise_w: Vec<f64> = gains
            .iter()
            .map(|g| (noise_var * n as f64 * g).sqrt())
            .collect();
        let offset = spec.mean;
        drop(spec);
        let g_count = grid.len();

        let t: Vec<f64> = grid.iter().map(|p| p.sample as f64 / fs).collect();
        let half: Vec<f64> = est.iter().map(|e| wl.time_sigma(e.scale)).collect();
        let mut ln_amp: Vec<f64> = est.iter().map(|e| e.ln_amp).collect();
        let mut phase: Vec<f64> = est.iter().map(|e| e.phase).collect();
        let decay: Vec<f64> = est.iter().map(|e| e.decay).collect();
        let mut frequency: Vec<f64> = est.iter().map(|e| e.frequency).collect();
        let sweep: Vec<f64> = est.iter().map(|e| e.sweep).collect();
        // A failed solve invalidates the grid points around it.
        let mut fix_ok = vec![true; g_count];
        for (g, e) in est.iter().enumerate() {
            if !e.corrected {
                let b = (g + 1).min(g_count - 1);
                fix_ok[g.saturating_sub(1)..=b].fill(false);
            }
        }

        // The sweep rate as the frequency track's own slope over ±σ_t: where the window saw a
        // signal the local model cannot describe, it disagrees with the model's β.
        let fslope = coarse_slope(&t, &frequency, &half);
        let mut valid: Vec<bool> = (0..g_count)
            .map(|g| {
                let e = &est[g];
                let i = grid[g].sample;
                let st = half[g];
                let margin = st * (opt.coi + (decay[g] * st).abs()) * fs;
                let inside = i as f64 >= margin && (n - 1 - i) as f64 >= margin;
                // The window spans ±coi σ_t, over which a sweep moves the frequency by β coi σ_t:
                // the model needs all of that inside the analysed band (and clear of DC).
                let reach = sweep[g].abs().max(fslope[g].abs()) * opt.coi * st;
                let in_band = frequency[g] - reach >= fmin && frequency[g] + reach <= fmax;
                // A loose threshold first: the final one is applied after smoothing, so that
                // noise which happens to lift a point over it does not select that point.
                let audible = e.observed_ln_amp.exp() >= 0.5 * opt.min_snr * noise_w[e.best];
                e.peaked && fix_ok[g] && inside && in_band && audible && frequency[g] > 0.0
            })
            .collect();
        if opt.smooth_snr > 0.0 {
            let snr: Vec<f64> = est
                .iter()
                .map(|e| e.observed_ln_amp.exp() / noise_w[e.best])
                .collect();
            smooth_low_snr(
                &t,
                &half,
                &snr,
                &mut ln_amp,
                &mut frequency,
                &valid,
                opt.smooth_snr,
            );
        }
        for g in 0..g_count {
            valid[g] = valid[g] && ln_amp[g].exp() >= opt.min_snr * noise_w[est[g].best];
        }
        unwrap_phase(&mut phase, &frequency, |g| t[g]);
        // A'' = A (σ² − σ'); σ' by a local least-squares slope over ±σ_t of the grid.
        let dsigma = coarse_slope(&t, &decay, &half);

        // Per sample: ln A, f, σ, β, σ' linear between grid points (they vary over σ_t, the
        // grid is σ_t/8), the phase cubic (Hermite, with 2πf as its slope at both ends).
        let mut out = Track {
            method: Method::Wavelet,
            sample_rate: fs,
            amplitude: vec![0.0; n],
            frequency: vec![0.0; n],
            phase: vec![0.0; n],
            d_amplitude: vec![0.0; n],
            d2_amplitude: vec![0.0; n],
            d_frequency: vec![0.0; n],
            valid: vec![false; n],
            offset,
            noise: noise_var.sqrt(),
            band: (fmin, fmax),
            backend,
            scalogram,
        };
        for g in 0..g_count {
            let a = grid[g].sample;
            let b = grid.get(g + 1).map_or(a, |p| p.sample);
            let gb = (g + 1).min(g_count - 1);
            let span = (b - a).max(1) as f64;
            let dt = span / fs;
            let last = if g + 1 == g_count { a } else { b - 1 };
            let lerp = |v: &[f64], u: f64| v[g] + u * (v[gb] - v[g]);
            let w0 = 2.0 * PI * frequency[g] * dt;
            let w1 = 2.0 * PI * frequency[gb] * dt;
            let both = valid[g] && valid[gb];
            // ln A is linear over the segment, so A is geometric: one exp per segment, not
            // per sample (the product drifts by ~1e-14 over a segment).
            let geometric = ln_amp[g].is_finite() && ln_amp[gb].is_finite();
            let ratio = ((ln_amp[gb] - ln_amp[g]) / span).exp();
            let mut next_amp = ln_amp[g].exp();
            for i in a..=last {
                let u = (i - a) as f64 / span;
                let amp = if geometric {
                    let amp = next_amp;
                    next_amp *= ratio;
                    amp
                } else if u < 0.5 {
                    ln_amp[g].exp()
                } else {
                    ln_amp[gb].exp()
                };
                let sig = lerp(&decay, u);
                let (u2, u3) = (u * u, u * u * u);
                out.amplitude[i] = amp;
                out.frequency[i] = lerp(&frequency, u);
                out.phase[i] = (2.0 * u3 - 3.0 * u2 + 1.0) * phase[g]
                    + (u3 - 2.0 * u2 + u) * w0
                    + (3.0 * u2 - 2.0 * u3) * phase[gb]
                    + (u3 - u2) * w1;
                out.d_amplitude[i] = -sig * amp;
                out.d2_amplitude[i] = amp * (sig * sig - lerp(&dsigma, u));
                out.d_frequency[i] = lerp(&sweep, u);
                out.valid[i] = both;
            }
        }
        out
    }
}

/// Slope of `y` at every coarse time by a least-squares line over ±`half` (0 where too few
/// points fall in the window).
fn coarse_slope(t: &[f64], y: &[f64], half: &[f64]) -> Vec<f64> {
    (0..t.len())
        .into_par_iter()
        .map(|c| local_slope(t, y, t[c], half[c]).unwrap_or(0.0))
        .collect()
}

/// Longest averaging window, in σ_t either side, that low-SNR smoothing may use.
const MAX_SMOOTH: f64 = 16.0;

/// Where the in-band SNR x is below `target`, replaces ln A and f by a weighted (SNR²)
/// least-squares line over the valid grid points within ±σ_t·min(16, (target/x)²): noise
/// drops as the window grows, and a decay or a linear sweep (ln A and f linear in time) is
/// not biased by it.
fn smooth_low_snr(
    t: &[f64],
    sigma_t: &[f64],
    snr: &[f64],
    ln_amp: &mut [f64],
    frequency: &mut [f64],
    valid: &[bool],
    target: f64,
) {
    let pts: Vec<usize> = (0..t.len()).filter(|&g| valid[g]).collect();
    if pts.len() < 3 {
        return;
    }
    let tv: Vec<f64> = pts.iter().map(|&g| t[g]).collect();
    let ln_a: Vec<f64> = pts.iter().map(|&g| ln_amp[g]).collect();
    let f: Vec<f64> = pts.iter().map(|&g| frequency[g]).collect();
    // ln Â and f̂ have variances ∝ 1/SNR²: weigh each point by SNR².
    let w: Vec<f64> = pts.iter().map(|&g| snr[g].powi(2)).collect();
    let smoothed: Vec<Option<(f64, f64)>> = pts
        .par_iter()
        .enumerate()
        .map(|(c, &g)| {
            if snr[g] >= target {
                return None;
            }
            let half = sigma_t[g] * (target / snr[g]).powi(2).min(MAX_SMOOTH);
            match (
                local_line_weighted(&tv, &ln_a, Some(&w), tv[c], half),
                local_line_weighted(&tv, &f, Some(&w), tv[c], half),
            ) {
                (Some((a, _)), Some((b, _))) => Some((a, b)),
                _ => None,
            }
        })
        .collect();
    for (&g, v) in pts.iter().zip(smoothed) {
        if let Some((a, b)) = v {
            ln_amp[g] = a;
            frequency[g] = b;
        }
    }
}
