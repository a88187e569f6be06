//! The sim-to-real gap between two identifications of one run — the measurement and the
//! model simulated under the measurement's own input — as one dimensionless number with its
//! breakdown into domains and regions (DESIGN.md, "Simulation and the sim-to-real gap").
//!
//! The three domains compare what a model gets right or wrong, never the raw response:
//! after the jump-down of a chirp, which flank of the clearance the link settles on is a
//! coin-flip that moves z's mean, not its envelope, its backbone or its damping.
//! - **time**: the response envelope over time, e = how far ln A_meas(t) lies outside the
//!   range of ln A_sim over t ± 0.25 s (and the other way round), at every valid sample
//!   (a relative error; 0.1 ≈ 10 %), weighted by the measured amplitude;
//! - **backbone**: the natural frequency at each amplitude bin of the measured skeleton,
//!   e = (f0_sim(A) − f0_meas(A)) / rms f0_meas, the simulated skeleton interpolated in
//!   ln A (relative to the curve's own scale, not to each bin's f0: in free play f0 is
//!   close to zero and a ratio there would weigh the noise);
//! - **damping**: the damping force 2h0·Aω at each bin, e = (D_sim(A) − D_meas(A)) / rms D_meas.
//!
//! The skeletons compared are those of the samples at resonance (|ω/ω0 − 1| < 0.1), and
//! each sample of the time domain weighs by its amplitude: what a model gets right or wrong
//! is its resonance; the small free flight inside the clearance after a jump-down is chaotic
//! in a real rig and in its model alike.
//!
//! Each domain's gap is the RMS of its e (bins weighted by their sample counts); the gap is
//! the RMS of the domains present, `sqrt((g_time² + g_backbone² + g_damping²) / 3)`.
//!
//! A gap can be measured on part of a run only ([`Blocks`]): the search fits on alternate
//! time blocks and scores on the others ([`search`]); [`selfcheck`] measures how well the
//! whole diagnosis does on simulated rigs with a known missing effect.

pub mod search;
pub mod selfcheck;

use crate::fit::Bin;
use crate::identify::{identify, identify_with_input_track, Identification, IdentifyOptions};
use crate::ingest::Run;
use crate::model::RigModel;
use crate::simulate::{simulate, Drive, Excitation, SimSettings, MEASURED_INPUT_CUTOFF};
use crate::track::Method;

pub use search::{diagnose, Candidate, Diagnosis, SearchOptions};

/// Time windows the time domain is split into for the regions.
const TIME_WINDOWS: usize = 8;
/// Amplitude ranges the skeleton domains are split into for the regions.
const AMPLITUDE_RANGES: usize = 4;

/// Where part of the gap lies (FORMATS.md §5, `regions`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Region {
    /// Start of the time range (s).
    pub t0: f64,
    /// End of the time range (s).
    pub t1: f64,
    /// Lowest response amplitude in the region (signal units).
    pub amp_lo: f64,
    /// Highest response amplitude.
    pub amp_hi: f64,
    /// Lowest response frequency (Hz).
    pub f_lo: f64,
    /// Highest response frequency (Hz).
    pub f_hi: f64,
    /// `time`, `backbone` or `damping`.
    pub domain: &'static str,
    /// Fraction of the total squared gap in this region (all regions sum to 1).
    pub share: f64,
}

/// The gap and its breakdown.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Gap {
    /// The dimensionless gap.
    pub total: f64,
    /// Per domain (`None` where the two identifications share nothing to compare).
    pub time: Option<f64>,
    /// Backbone domain.
    pub backbone: Option<f64>,
    /// Damping domain.
    pub damping: Option<f64>,
    /// Regions, largest share first.
    pub regions: Vec<Region>,
}

/// One domain's squared errors with their weights and where they lie.
struct Errors {
    /// (weight, squared error, region index)
    terms: Vec<(f64, f64, usize)>,
    regions: Vec<Region>,
}

impl Errors {
    /// Weighted mean square.
    fn mean_square(&self) -> Option<f64> {
        let w: f64 = self.terms.iter().map(|t| t.0).sum();
        (w > 0.0).then(|| self.terms.iter().map(|t| t.0 * t.1).sum::<f64>() / w)
    }
}

/// Alternate time blocks of a run: the even ones (from t = 0) to fit on, the odd ones
/// withheld to score on. With a sine sweep every part covers the whole band, a block at a
/// time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Blocks {
    /// Block length (s).
    pub seconds: f64,
}

/// Which samples of a run a gap is measured on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    /// The even blocks, which fits see.
    Fit,
    /// The odd blocks, withheld from every fit.
    Holdout,
}

impl Blocks {
    /// One flag per sample of an `n`-sample record at `fs` Hz: true inside `part`.
    pub fn mask(&self, n: usize, fs: f64, part: Part) -> Vec<bool> {
        let per = (self.seconds * fs).round().max(1.0) as usize;
        (0..n)
            .map(|i| (i / per).is_multiple_of(2) == (part == Part::Fit))
            .collect()
    }
}

/// The gap between `measured` and `simulated`, two identifications of the same run.
pub fn gap(measured: &Identification, simulated: &Identification) -> Gap {
    Target::new(measured, None).gap(measured, simulated, &Envelope::of(&simulated.response))
}

/// A track's log envelope (NaN where not valid) and its running extremes over
/// ±[`TIME_TOLERANCE`]: what the time domain compares, computed once per track.
pub struct Envelope {
    ln: Vec<f64>,
    lo: Vec<f64>,
    hi: Vec<f64>,
}

impl Envelope {
    /// The envelope of `track`.
    pub fn of(track: &crate::track::Track) -> Envelope {
        let ln: Vec<f64> = (0..track.len())
            .map(|i| {
                if track.valid[i] && track.amplitude[i] > 0.0 {
                    track.amplitude[i].ln()
                } else {
                    f64::NAN
                }
            })
            .collect();
        let half = (TIME_TOLERANCE * track.sample_rate).round() as usize;
        let (lo, hi) = window_extremes(&ln, half);
        Envelope { ln, lo, hi }
    }
}

/// The measured side of a comparison on one part of a run, prepared once for all the
/// models compared with it: the part's samples, its skeleton at resonance, its envelope.
pub struct Target {
    mask: Option<Vec<bool>>,
    resonant: Vec<Bin>,
    envelope: Envelope,
}

impl Target {
    /// `measured` on the samples flagged in `mask` (the whole run when `None`).
    pub fn new(measured: &Identification, mask: Option<Vec<bool>>) -> Target {
        Target {
            resonant: resonant(measured, mask.as_deref()),
            envelope: Envelope::of(&measured.response),
            mask,
        }
    }

    /// The gap of `simulated` (whose envelope is `sim_envelope`) against `measured`, the
    /// identification this target was prepared from. The time domain keeps the part's
    /// samples; the simulated skeleton is rebuilt from them.
    pub fn gap(
        &self,
        measured: &Identification,
        simulated: &Identification,
        sim_envelope: &Envelope,
    ) -> Gap {
        let mask = self.mask.as_deref();
        let s_res = resonant(simulated, mask);
        let m_res = &self.resonant;
        let domains = [
            time_errors(measured, &self.envelope, sim_envelope, mask),
            backbone_errors(m_res, &s_res, measured, mask, false),
            backbone_errors(m_res, &s_res, measured, mask, true),
        ];
        combine(domains)
    }
}

/// The skeleton at resonance of the samples in `mask`. Both skeleton domains are compared
/// at resonance, where the backbone is defined: off resonance (the free flight after a
/// jump-down, resting on a flank or touching it now and then) the first-harmonic stiffness
/// and damping are the coin-flip of which regime the link fell into, and would make the gap
/// jump with every small change of a model.
fn resonant(id: &Identification, mask: Option<&[bool]>) -> Vec<Bin> {
    let opt = IdentifyOptions::default();
    match mask {
        None => id.resonant_bins.clone(),
        Some(m) => id.skeleton_within(m, opt.bins, Some(opt.resonance)),
    }
}

/// The domains' errors as one gap with its regions.
fn combine(domains: [Errors; 3]) -> Gap {
    let ms: Vec<Option<f64>> = domains.iter().map(Errors::mean_square).collect();
    let total_ms = ms.iter().flatten().sum::<f64>() / 3.0;
    let mut regions = Vec::new();
    for (d, m) in domains.into_iter().zip(&ms) {
        if m.is_none() {
            continue;
        }
        let w: f64 = d.terms.iter().map(|t| t.0).sum();
        let mut per = vec![0.0; d.regions.len()];
        for &(wt, e2, r) in &d.terms {
            per[r] += wt * e2 / w;
        }
        // A region's share of the total: its part of the domain's mean square, over 3.
        for (mut region, part) in d.regions.into_iter().zip(per) {
            region.share = if total_ms > 0.0 {
                part / 3.0 / total_ms
            } else {
                0.0
            };
            regions.push(region);
        }
    }
    regions.retain(|r| r.share > 0.0);
    regions.sort_by(|a, b| b.share.total_cmp(&a.share));
    Gap {
        total: total_ms.sqrt(),
        time: ms[0].map(f64::sqrt),
        backbone: ms[1].map(f64::sqrt),
        damping: ms[2].map(f64::sqrt),
        regions,
    }
}

/// Half-width (s) of the time tolerance of the time domain: a sample's envelope is matched
/// against the other's envelope anywhere within ±this. The instant of a jump-down is as
/// sensitive as the flank the link settles on (a 0.2 % change in k moves it by tenths of a
/// second), and an exact-time comparison would score that instant, not the envelope; the
/// backbone domain holds the frequency errors a tolerance in time forgives.
pub const TIME_TOLERANCE: f64 = 0.25;

/// The grazing band of the time domain, in multiples of the measured half-gap δ: the
/// forced orbit first touches at 8δ/π² ≈ 0.81δ.
pub const GRAZING: (f64, f64) = (0.7, 1.05);

/// Running minimum and maximum of `x` over `[i − half, i + half]`, skipping NaN (an empty
/// window gives +∞, −∞). Monotone deques: O(n).
fn window_extremes(x: &[f64], half: usize) -> (Vec<f64>, Vec<f64>) {
    use std::collections::VecDeque;
    let n = x.len();
    let (mut lo, mut hi) = (vec![f64::INFINITY; n], vec![f64::NEG_INFINITY; n]);
    let (mut qmin, mut qmax): (VecDeque<usize>, VecDeque<usize>) =
        (VecDeque::new(), VecDeque::new());
    let mut next = 0;
    for i in 0..n {
        while next < n && next <= i + half {
            if x[next].is_finite() {
                while qmin.back().is_some_and(|&j| x[j] >= x[next]) {
                    qmin.pop_back();
                }
                qmin.push_back(next);
                while qmax.back().is_some_and(|&j| x[j] <= x[next]) {
                    qmax.pop_back();
                }
                qmax.push_back(next);
            }
            next += 1;
        }
        while qmin.front().is_some_and(|&j| j + half < i) {
            qmin.pop_front();
        }
        while qmax.front().is_some_and(|&j| j + half < i) {
            qmax.pop_front();
        }
        if let (Some(&a), Some(&b)) = (qmin.front(), qmax.front()) {
            lo[i] = x[a];
            hi[i] = x[b];
        }
    }
    (lo, hi)
}

/// How far `v` lies outside `[lo, hi]` (0 inside; NaN where the window was empty).
fn outside(v: f64, lo: f64, hi: f64) -> f64 {
    if lo > hi {
        f64::NAN
    } else {
        (v - hi).max(lo - v).max(0.0)
    }
}

fn time_errors(m: &Identification, ea: &Envelope, eb: &Envelope, mask: Option<&[bool]>) -> Errors {
    let inside = |i: usize| mask.is_none_or(|m| m.get(i).copied().unwrap_or(false));
    let a = &m.response;
    let n = ea.ln.len().min(eb.ln.len());
    let fs = a.sample_rate;
    let window = n.div_ceil(TIME_WINDOWS).max(1);
    let (la, lb) = (&ea.ln, &eb.ln);
    // Each sample weighs by its amplitude: the free flight inside the clearance after a
    // jump-down is small and chaotic (which flank, how often it touches), and its relative
    // envelope error would otherwise weigh as much as the resonance's.
    let peak = (0..n)
        .filter(|&i| a.valid[i])
        .map(|i| a.amplitude[i])
        .fold(0f64, f64::max)
        .max(f64::MIN_POSITIVE);
    // The grazing band, from the measurement's own clearance: an orbit that just touches
    // the flanks is hypersensitive (a grazing bifurcation), in the rig and in any model of
    // it, so its envelope there is a coin-flip like the jump-down's flank.
    let grazing = |amp: f64| {
        m.dead_zone.is_some_and(|dz| {
            let d = dz.half_gap.value;
            amp > GRAZING.0 * d && amp < GRAZING.1 * d
        })
    };
    let mut terms = Vec::new();
    let mut regions = Vec::new();
    for (w, start) in (0..n).step_by(window).enumerate() {
        let end = (start + window).min(n);
        let (mut alo, mut ahi, mut flo, mut fhi) = (f64::INFINITY, 0f64, f64::INFINITY, 0f64);
        for i in start..end {
            if !inside(i) || !la[i].is_finite() || grazing(a.amplitude[i]) {
                continue;
            }
            // Both ways: the measurement within the model's tolerance band and the model's
            // own envelope (where it has one) within the measurement's.
            let e1 = outside(la[i], eb.lo[i], eb.hi[i]);
            if !e1.is_finite() {
                continue;
            }
            let e2 = if lb[i].is_finite() {
                outside(lb[i], ea.lo[i], ea.hi[i])
            } else {
                e1
            };
            terms.push((a.amplitude[i] / peak, 0.5 * (e1 * e1 + e2 * e2), w));
            alo = alo.min(a.amplitude[i]);
            ahi = ahi.max(a.amplitude[i]);
            flo = flo.min(a.frequency[i]);
            fhi = fhi.max(a.frequency[i]);
        }
        regions.push(Region {
            t0: start as f64 / fs,
            t1: end as f64 / fs,
            amp_lo: if alo.is_finite() { alo } else { 0.0 },
            amp_hi: ahi,
            f_lo: if flo.is_finite() { flo } else { 0.0 },
            f_hi: fhi,
            domain: "time",
            share: 0.0,
        });
    }
    Errors { terms, regions }
}

/// Linear interpolation of `value(bin)` over ln A at `amp` (None outside the bins' range:
/// the ends of a resonant skeleton are thin, a few dozen samples that a model reaches or not
/// by chance).
fn at_amplitude(bins: &[Bin], amp: f64, value: impl Fn(&Bin) -> f64) -> Option<f64> {
    let i = bins.iter().position(|b| b.amplitude >= amp)?;
    if bins[i].amplitude == amp {
        return Some(value(&bins[i]));
    }
    if i == 0 {
        return None;
    }
    let lo = &bins[i - 1];
    let hi = &bins[i];
    let u = (amp / lo.amplitude).ln() / (hi.amplitude / lo.amplitude).ln();
    Some(value(lo) + u * (value(hi) - value(lo)))
}

/// The backbone (`damping` false) or damping-force (`damping` true) errors at the measured
/// bins, with regions by amplitude range (their time and frequency spans taken from the
/// measured track).
fn backbone_errors(
    meas: &[Bin],
    sim: &[Bin],
    m: &Identification,
    mask: Option<&[bool]>,
    damping: bool,
) -> Errors {
    let inside = |i: usize| mask.is_none_or(|m| m.get(i).copied().unwrap_or(false));
    let domain = if damping { "damping" } else { "backbone" };
    let mut sim: Vec<Bin> = sim
        .iter()
        .filter(|b| b.amplitude > 0.0 && b.stiffness.is_finite() && b.damping.is_finite())
        .copied()
        .collect();
    sim.sort_by(|a, b| a.amplitude.total_cmp(&b.amplitude));
    let meas: Vec<&Bin> = meas
        .iter()
        .filter(|b| b.amplitude > 0.0 && b.stiffness.is_finite() && b.damping.is_finite())
        .collect();
    let value = |b: &Bin| {
        if damping {
            b.damping_force()
        } else {
            b.stiffness.max(0.0).sqrt()
        }
    };
    let scale =
        (meas.iter().map(|b| value(b).powi(2)).sum::<f64>() / meas.len().max(1) as f64).sqrt();
    let (lo, hi) = meas.iter().fold((f64::INFINITY, 0f64), |(l, h), b| {
        (l.min(b.amplitude), h.max(b.amplitude))
    });
    let range_of = |a: f64| -> usize {
        if hi <= lo {
            return 0;
        }
        let u = (a / lo).ln() / (hi / lo).ln();
        ((u * AMPLITUDE_RANGES as f64) as usize).min(AMPLITUDE_RANGES - 1)
    };
    let mut terms = Vec::new();
    for b in &meas {
        let e = at_amplitude(&sim, b.amplitude, value)
            .filter(|_| scale > 0.0)
            .map(|v| (v - value(b)) / scale);
        if let Some(e) = e {
            terms.push((b.count as f64, e * e, range_of(b.amplitude)));
        }
    }
    // A model whose skeleton shares no amplitude with the measured one (too damped to reach
    // the measured resonance, say) misses all of it.
    if terms.is_empty() && !meas.is_empty() && scale > 0.0 {
        terms = meas
            .iter()
            .map(|b| (b.count as f64, 1.0, range_of(b.amplitude)))
            .collect();
    }
    // Each amplitude range's time and frequency span, from the measured track.
    let r = &m.response;
    let regions = (0..AMPLITUDE_RANGES)
        .map(|k| {
            let a_lo = lo * (hi / lo).powf(k as f64 / AMPLITUDE_RANGES as f64);
            let a_hi = lo * (hi / lo).powf((k + 1) as f64 / AMPLITUDE_RANGES as f64);
            let (mut t0, mut t1, mut f_lo, mut f_hi) = (f64::INFINITY, 0f64, f64::INFINITY, 0f64);
            for i in 0..r.len() {
                if inside(i) && r.valid[i] && r.amplitude[i] >= a_lo && r.amplitude[i] <= a_hi {
                    let t = i as f64 / r.sample_rate;
                    t0 = t0.min(t);
                    t1 = t1.max(t);
                    f_lo = f_lo.min(r.frequency[i]);
                    f_hi = f_hi.max(r.frequency[i]);
                }
            }
            Region {
                t0: if t0.is_finite() { t0 } else { 0.0 },
                t1,
                amp_lo: a_lo,
                amp_hi: a_hi,
                f_lo: if f_lo.is_finite() { f_lo } else { 0.0 },
                f_hi,
                domain,
                share: 0.0,
            }
        })
        .collect();
    Errors { terms, regions }
}

/// Why a gap could not be computed.
#[derive(Debug, thiserror::Error)]
pub enum GapError {
    /// The run cannot drive a base-motion simulation.
    #[error("{0}")]
    Unusable(String),
    /// The simulated response could not be identified.
    #[error("the model's simulated response could not be identified: {0}")]
    Simulated(String),
}

/// The model simulated under `measured`'s own input, identified like the measurement.
pub fn simulate_like(measured: &Run, model: &RigModel) -> Result<Identification, GapError> {
    simulate_given(measured, None, model)
}

/// [`simulate_like`], reusing the measurement's input track when `identified` is given
/// (the simulation is driven by that very input, so tracking it again only costs time).
pub fn simulate_given(
    measured: &Run,
    identified: Option<&Identification>,
    model: &RigModel,
) -> Result<Identification, GapError> {
    let input = measured.input.as_ref().ok_or_else(|| {
        GapError::Unusable("the run has no input channel to drive the model with".into())
    })?;
    let fs = measured.meta.sample_rate;
    let drive = Drive::Base(Excitation::measured(
        input,
        fs,
        MEASURED_INPUT_CUTOFF * fs / 2.0,
    ));
    let settings = SimSettings {
        sample_rate: fs,
        duration: input.len() as f64 / fs,
        ..SimSettings::default()
    };
    let out = simulate(model, &drive, &settings);
    let mut run = measured.clone();
    run.input = Some(out.input);
    run.output = out.output;
    let opt = IdentifyOptions::default();
    match identified.and_then(|i| i.input.as_ref()) {
        Some(tx) => identify_with_input_track(&run, Method::Wavelet, &opt, tx),
        None => identify(&run, Method::Wavelet, &opt),
    }
    .map_err(|e| GapError::Simulated(e.to_string()))
}

/// The gap of `model` against the identified measurement (`f64::INFINITY` when the
/// simulated response cannot be identified: a model that far off is simply bad).
pub fn model_gap(measured: &Run, identified: &Identification, model: &RigModel) -> f64 {
    simulate_given(measured, Some(identified), model)
        .map_or(f64::INFINITY, |s| gap(identified, &s).total)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::Bin;

    fn bin(a: f64, k: f64, d: f64) -> Bin {
        Bin {
            amplitude: a,
            stiffness: k,
            stiffness_spread: 0.0,
            damping: d,
            damping_spread: 0.0,
            velocity: a * k.sqrt(),
            count: 10,
        }
    }

    #[test]
    fn window_extremes_match_a_naive_scan() {
        let x: Vec<f64> = (0..200)
            .map(|i| {
                if i % 17 == 3 {
                    f64::NAN
                } else {
                    ((i * 37) % 101) as f64
                }
            })
            .collect();
        for half in [0, 1, 5, 300] {
            let (lo, hi) = window_extremes(&x, half);
            for i in 0..x.len() {
                let w = &x[i.saturating_sub(half)..(i + half + 1).min(x.len())];
                let f = w.iter().filter(|v| v.is_finite());
                let (l, h) = f.fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                    (l.min(v), h.max(v))
                });
                assert_eq!((lo[i], hi[i]), (l, h), "i {i} half {half}");
            }
        }
    }

    #[test]
    fn interpolation_in_log_amplitude_is_exact_for_a_log_linear_curve() {
        let bins: Vec<Bin> = (0..10)
            .map(|i| {
                let a = 0.001 * 1.5f64.powi(i);
                bin(a, 100.0 + 7.0 * a.ln(), 1.0)
            })
            .collect();
        let a = 0.0042;
        let v = at_amplitude(&bins, a, |b| b.stiffness).unwrap();
        assert!((v - (100.0 + 7.0 * a.ln())).abs() < 1e-9, "{v}");
        assert!(at_amplitude(&bins, 1e-6, |b| b.stiffness).is_none());
        assert!(at_amplitude(&bins, 1.0, |b| b.stiffness).is_none());
    }
}
