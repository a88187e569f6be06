//! The sim-to-real gap between two identifications of one run — the measurement and the
//! model simulated under the measurement's own input — as one dimensionless number with its
//! breakdown into domains and regions (DESIGN.md, "Simulation and the sim-to-real gap").
//!
//! The three domains compare what a model gets right or wrong, never the raw response:
//! after the jump-down of a chirp, which flank of the clearance the link settles on is a
//! coin-flip that moves z's mean, not its envelope, its backbone or its damping.
//! - **time**: the response envelope over time, e = how far ln A_meas(t) lies outside the
//!   range of ln A_sim over t ± 0.25 s (and the other way round), weighted by the measured
//!   amplitude (a relative error; 0.1 ≈ 10 %); where both touch both flanks, plus the error
//!   of the centre of the motion relative to the measured amplitude; where the measurement
//!   chains' resolutions differ, plus the quantisation error one has and the other lacks,
//!   relative to the measured amplitude (at most 1);
//! - **backbone**: the natural frequency at each sample where the measurement is at
//!   resonance (|ω/ω0 − 1| < 0.1), e = (f0_sim − f0_meas) / rms f0_meas, both smoothed over
//!   ±[`SMOOTH`], the model taken at the same instant or its nearest resonant one;
//! - **damping**: the damping force 2h0·Aω at the same samples, e = (D_sim − D_meas) /
//!   rms D_meas.
//!
//! Left out, as coin-flips of the rig's noise: the grazing band ([`GRAZING`], time domain),
//! and in every domain the settling after a jump-down ([`SETTLE_DECAY_TIMES`]) and the
//! climb between each measured jump-up and the model's nearest ([`JUMP_UP_SPAN`]).
//!
//! Each domain's gap is the RMS of its e; the gap is the RMS of the domains present,
//! `sqrt((g_time² + g_backbone² + g_damping²) / 3)`.
//!
//! A gap can be measured on part of a run only ([`Blocks`]): the search fits on alternate
//! time blocks and scores on the others ([`search`]); [`selfcheck`] measures how well the
//! whole diagnosis does on simulated rigs with a known missing effect.

mod finished;
pub mod search;
pub mod selfcheck;

use crate::identify::{Identification, Identifier};
use crate::model::RigModel;
use crate::run::Run;
use crate::simulate::{simulate, Drive, Excitation, SimSettings, MEASURED_INPUT_CUTOFF};
use crate::track::Method;

pub use finished::{GapRun, Whole};
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

/// The gap between `measured` (identified from `measured_run`) and `simulated`, the model
/// simulated under the same run's input.
pub fn gap(measured: &Identification, measured_run: &Run, simulated: &Simulated) -> Gap {
    let features = simulated.features();
    Target::new(measured, measured_run, None)
        .with_resolution(measured_resolution(measured_run))
        .gap(measured, &features)
}

/// What the gap compares of one identification, computed once per identification: its log
/// envelope (NaN where not valid) with the running extremes over ±[`TIME_TOLERANCE`], its
/// natural frequency and damping force at resonance, smoothed over ±[`SMOOTH`] (NaN off
/// resonance), and, where the run's channels are displacements, the centre of the relative
/// motion (its mean over one period).
pub struct Features {
    ln: Vec<f64>,
    lo: Vec<f64>,
    hi: Vec<f64>,
    f0: Vec<f64>,
    force: Vec<f64>,
    centre: Option<Vec<f64>>,
    resolution: f64,
}

/// Half-width (s) of the running mean the instantaneous natural frequency and damping force
/// are smoothed with before they are compared (the encoder noise's scatter, sample to
/// sample, would otherwise set the floor of both skeleton domains).
pub const SMOOTH: f64 = 0.1;

impl Features {
    /// The features of `id`, identified from `run`.
    pub fn of(id: &Identification, run: &Run) -> Features {
        let track = &id.response;
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
        let resonant = |i: usize| id.resonant(i);
        let n = id.used.len().min(track.len());
        let (raw_f0, raw_force): (Vec<f64>, Vec<f64>) = (0..n)
            .map(|i| {
                if !resonant(i) {
                    return (f64::NAN, f64::NAN);
                }
                let w = 2.0 * std::f64::consts::PI * track.frequency[i];
                (
                    id.modal.stiffness[i].max(0.0).sqrt() / (2.0 * std::f64::consts::PI),
                    2.0 * id.modal.damping[i] * track.amplitude[i] * w,
                )
            })
            .unzip();
        let half = (SMOOTH * track.sample_rate).round() as usize;
        Features {
            centre: relative_motion(run).map(|z| centre(&z, track)),
            ln,
            lo,
            hi,
            f0: mean_around(&raw_f0, |i| raw_f0[i].is_finite().then_some(half)),
            force: mean_around(&raw_force, |i| raw_force[i].is_finite().then_some(half)),
            resolution: 0.0,
        }
    }

    /// The same features with the measurement chain's resolution set: the RMS quantisation
    /// error of the response (see [`measured_resolution`] and [`model_resolution`]).
    pub fn with_resolution(mut self, resolution: f64) -> Features {
        self.resolution = resolution;
        self
    }
}

/// The relative motion z = y − x of a base-motion run whose channels are displacements
/// (`None` otherwise: an integrated velocity or acceleration has lost its mean).
fn relative_motion(run: &Run) -> Option<Vec<f64>> {
    use crate::run::{Quantity, RunKind};
    let x = run.input.as_ref()?;
    let displacement = run.meta.output_quantity == Quantity::Displacement
        && run.meta.input_quantity.unwrap_or_default() == Quantity::Displacement;
    (run.meta.kind == RunKind::BaseMotion && displacement && x.len() == run.output.len())
        .then(|| run.output.iter().zip(x).map(|(y, x)| y - x).collect())
}

/// The step of the lattice a sampled channel lies on, when it lies on one: the smallest
/// change between consecutive samples, accepted when at least [`LATTICE_SHARE`] of the
/// samples sit within 0.1 % of a step from a whole number of steps above the first (an
/// encoder's or an ADC's least count). A continuous signal, noisy or not, puts about 0.2 %
/// of its samples there by chance.
pub fn lattice_step(x: &[f64]) -> Option<f64> {
    let step = x
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .filter(|d| *d > 0.0 && d.is_finite())
        .fold(f64::INFINITY, f64::min);
    let (lo, hi) = x
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    // A handful of levels is a lattice of anything: ask for a few of them at least.
    if !step.is_finite() || x.len() < 100 || (hi - lo) < 4.0 * step {
        return None;
    }
    let on = x
        .iter()
        .filter(|&&v| {
            let u = (v - x[0]) / step;
            (u - u.round()).abs() < 1e-3
        })
        .count();
    (on as f64 >= LATTICE_SHARE * x.len() as f64).then_some(step)
}

/// Share of the samples that must lie on a lattice for [`lattice_step`] to accept it.
pub const LATTICE_SHARE: f64 = 0.99;

/// The channels the response track is made of: the output, and for a base-motion run the
/// input too (the joint's relative motion is their difference).
fn response_channels(run: &Run) -> Vec<&[f64]> {
    let mut ch = vec![run.output.as_slice()];
    if run.meta.kind == crate::run::RunKind::BaseMotion {
        ch.extend(run.input.as_deref());
    }
    ch
}

/// The RMS quantisation error of a measured run's response, from the lattices its channels
/// lie on: `sqrt(Σ q²/12)` over the response's channels (0 where none is quantised). Read
/// from the samples as recorded: a filtered or decimated run has lost its lattice.
pub fn measured_resolution(run: &Run) -> f64 {
    response_channels(run)
        .into_iter()
        .filter_map(lattice_step)
        .map(|q| q * q / 12.0)
        .sum::<f64>()
        .sqrt()
}

/// The RMS quantisation error a model's measurement chain puts on `run`'s response: its
/// quantisation step q on every channel the simulator quantises (the output, and the
/// input of a base-motion run), `q·sqrt(channels/12)`.
pub fn model_resolution(model: &RigModel, run: &Run) -> f64 {
    let q = model
        .effects
        .get(crate::model::EffectKind::Quantization)
        .unwrap_or(0.0);
    q * resolution_per_step(run)
}

/// The RMS quantisation error of `run`'s response per unit of quantisation step,
/// `sqrt(channels/12)`.
pub fn resolution_per_step(run: &Run) -> f64 {
    (response_channels(run).len() as f64 / 12.0).sqrt()
}

/// The mean of `z` over one period of `track`'s frequency around each sample (NaN where
/// the track is not valid): the centre the motion oscillates about.
fn centre(z: &[f64], track: &crate::track::Track) -> Vec<f64> {
    mean_around(z, |i| {
        let f = *track.frequency.get(i)?;
        (track.valid[i] && f > 0.0).then(|| (0.5 * track.sample_rate / f).round() as usize)
    })
}

/// For each index, the index of the nearest finite value of `x` (the earlier one on a tie),
/// `None` when `x` has none.
fn nearest_finite(x: &[f64]) -> Vec<Option<usize>> {
    let mut before = vec![None; x.len()];
    let mut last = None;
    for (i, v) in x.iter().enumerate() {
        if v.is_finite() {
            last = Some(i);
        }
        before[i] = last;
    }
    let mut next = None;
    let mut out = vec![None; x.len()];
    for i in (0..x.len()).rev() {
        if x[i].is_finite() {
            next = Some(i);
        }
        out[i] = match (before[i], next) {
            (Some(b), Some(a)) => Some(if i - b <= a - i { b } else { a }),
            (b, a) => b.or(a),
        };
    }
    out
}

/// At each sample where `half` gives a half-width, the mean of the finite values of `x`
/// over `[i − half, i + half]` (NaN elsewhere, and where the window holds none).
fn mean_around(x: &[f64], half: impl Fn(usize) -> Option<usize>) -> Vec<f64> {
    let mut sum = vec![0.0; x.len() + 1];
    let mut count = vec![0usize; x.len() + 1];
    for (i, &v) in x.iter().enumerate() {
        let ok = v.is_finite();
        sum[i + 1] = sum[i] + if ok { v } else { 0.0 };
        count[i + 1] = count[i] + ok as usize;
    }
    (0..x.len())
        .map(|i| {
            let Some(h) = half(i) else {
                return f64::NAN;
            };
            let (a, b) = (i.saturating_sub(h), (i + h + 1).min(x.len()));
            match count[b] - count[a] {
                0 => f64::NAN,
                k => (sum[b] - sum[a]) / k as f64,
            }
        })
        .collect()
}

/// The measured side of a comparison on one part of a run, prepared once for all the
/// models compared with it: the part's samples, the measurement's features and its jumps.
pub struct Target {
    mask: Option<Vec<bool>>,
    features: Features,
    jumps: Option<Jumps>,
}

/// Where a response jumps between the low and the resonant branch, on the measurement's
/// scales (its half-gap and decay time).
struct Jumps {
    /// The settling windows after each jump-down (sample ranges).
    downs: Vec<(usize, usize)>,
    /// The jump-ups onto the resonant branch (a record may sweep more than once), each as
    /// the climb's first sample and the first sample above the grazing band.
    ups: Vec<(usize, usize)>,
}

impl Jumps {
    /// The jumps of the log envelope `ln` (NaN where not valid) at `fs` Hz, for a
    /// measurement of half-gap `half_gap` whose settling lasts `settle` seconds.
    fn of(ln: &[f64], fs: f64, half_gap: f64, settle: f64) -> Jumps {
        Jumps {
            downs: settling(ln, fs, half_gap, settle),
            ups: jump_ups(ln, half_gap),
        }
    }
}

impl Target {
    /// `measured` (identified from `run`) on the samples flagged in `mask` (the whole run
    /// when `None`).
    pub fn new(measured: &Identification, run: &Run, mask: Option<Vec<bool>>) -> Target {
        let features = Features::of(measured, run);
        let jumps = measured.dead_zone.map(|dz| {
            let fs = measured.response.sample_rate;
            Jumps::of(
                &features.ln,
                fs,
                dz.half_gap.value,
                settle_seconds(measured),
            )
        });
        Target {
            features,
            jumps,
            mask,
        }
    }

    /// The same target with the measurement's resolution set (its RMS quantisation error,
    /// [`measured_resolution`] of the run as recorded).
    pub fn with_resolution(mut self, resolution: f64) -> Target {
        self.features.resolution = resolution;
        self
    }

    /// The gap of a simulation (its `features`) against `measured`, the identification this
    /// target was prepared from, on the target's samples.
    pub fn gap(&self, measured: &Identification, sim: &Features) -> Gap {
        let mask = self.mask.as_deref();
        let ours = &self.features;
        let fs = measured.response.sample_rate;
        let (mut settling, mut jump_up) = (Vec::new(), Vec::new());
        if let (Some(mj), Some(dz)) = (&self.jumps, measured.dead_zone) {
            let settle = settle_seconds(measured);
            let sj = Jumps::of(&sim.ln, fs, dz.half_gap.value, settle);
            // The settling after a jump-down: the free flight that follows bounces between
            // the flanks for several decay times, and which flank it ends on is the
            // coin-flip again. It is left out where both have jumped within a second of
            // each other (from the first jump to the later end); a model that has not
            // jumped where the measurement has is still scored there.
            settling = paired_settling(&mj.downs, &sj.downs, fs.round() as usize);
            // Between the two jump-ups onto the resonant branch, and while the later one
            // joins the branch: where the branches coexist, the instant of the jump-up is as
            // much a coin-flip as the flank after a jump-down (the noise of the rig decides
            // it), while the jump-down's instant, which the damping sets, stays scored.
            let join = (JOIN_DECAY_TIMES / SETTLE_DECAY_TIMES * settle * fs).round() as usize;
            for &(climb, a) in &mj.ups {
                let partner = sj.ups.iter().min_by_key(|b| a.abs_diff(b.1));
                if let Some(&(climb_b, b)) =
                    partner.filter(|b| a.abs_diff(b.1) as f64 <= JUMP_UP_SPAN * fs)
                {
                    // From a tolerance before the earlier climb: a sample there is matched
                    // against the other's envelope over ±TIME_TOLERANCE, its climb included.
                    let lead = (TIME_TOLERANCE * fs).round() as usize;
                    jump_up.push(climb.min(climb_b).saturating_sub(lead)..a.max(b) + join);
                }
            }
        }
        let keep = |i: usize| {
            mask.is_none_or(|m| m.get(i).copied().unwrap_or(false))
                && !settling.get(i).copied().unwrap_or(false)
                && !jump_up.iter().any(|r| r.contains(&i))
        };
        let domains = [
            time_errors(measured, ours, sim, &keep),
            resonance_errors(measured, &ours.f0, &sim.f0, &keep, "backbone"),
            resonance_errors(measured, &ours.force, &sim.force, &keep, "damping"),
        ];
        combine(domains)
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

/// The longest time (s) between the measured and the simulated jump-up that is forgiven as
/// a coin-flip; a model that jumps up later than that is scored there.
pub const JUMP_UP_SPAN: f64 = 3.0;

/// Decay times the later of two jump-ups takes to join the resonant branch.
pub const JOIN_DECAY_TIMES: f64 = 3.0;

/// Decay times a jump-down's settling lasts in the time domain.
pub const SETTLE_DECAY_TIMES: f64 = 12.0;

/// How long (s) the settling after a jump-down lasts: [`SETTLE_DECAY_TIMES`] decay times
/// 1/h of the measured viscous damping (4 s where the damping was not identified).
fn settle_seconds(m: &Identification) -> f64 {
    m.damping
        .map(|(c, _)| c.value)
        .filter(|c| c.is_finite() && *c > 0.0)
        .map_or(4.0, |c| SETTLE_DECAY_TIMES * 2.0 / c)
}

/// The jump-ups of a log envelope `ln` (NaN where not valid) onto the resonant branch of a
/// rig of half-gap `half_gap`: the first sample above the grazing band (1.05 `half_gap`),
/// and the first above it after each fall below it (0.7 `half_gap`), each with the start of
/// its climb, the sample after the last one below the band (the envelope of a climb is
/// often not valid: the ridge jumps with it).
fn jump_ups(ln: &[f64], half_gap: f64) -> Vec<(usize, usize)> {
    let (high, low) = ((GRAZING.1 * half_gap).ln(), (GRAZING.0 * half_gap).ln());
    let mut ups = Vec::new();
    let mut below = true;
    let mut last_low = 0;
    for (i, &v) in ln.iter().enumerate() {
        if below && v > high {
            ups.push((last_low.min(i), i));
            below = false;
        } else if v < low {
            below = true;
            last_low = i + 1;
        }
    }
    ups
}

/// Flags the samples of a log envelope `ln` (NaN where not valid) that follow a jump-down
/// by less than `settle` seconds: a fall from above the grazing band (1.05 `half_gap`) to
/// below it (0.7 `half_gap`) within a second.
fn settling(ln: &[f64], fs: f64, half_gap: f64, settle: f64) -> Vec<(usize, usize)> {
    let (high, low) = ((GRAZING.1 * half_gap).ln(), (GRAZING.0 * half_gap).ln());
    let within = fs.round() as usize;
    let span = (settle * fs).round() as usize;
    let mut windows = Vec::new();
    let mut last_high: Option<usize> = None;
    for (i, &v) in ln.iter().enumerate() {
        if v > high {
            last_high = Some(i);
        } else if v < low && last_high.is_some_and(|h| i - h <= within) {
            windows.push((i, (i + span).min(ln.len())));
            last_high = None;
        }
    }
    windows
}

/// The samples inside a settling window of `a` that has a partner in `b` starting within
/// `within` samples (or the other way round), from the earlier start to the later end.
fn paired_settling(a: &[(usize, usize)], b: &[(usize, usize)], within: usize) -> Vec<bool> {
    let n = a.iter().chain(b).map(|w| w.1).max().unwrap_or(0);
    let mut out = vec![false; n];
    for &(s0, e0) in a {
        for &(s1, e1) in b {
            if s0.abs_diff(s1) <= within {
                out[s0.min(s1)..e0.max(e1)].fill(true);
            }
        }
    }
    out
}

/// How far `v` lies outside `[lo, hi]` (0 inside; NaN where the window was empty).
fn outside(v: f64, lo: f64, hi: f64) -> f64 {
    if lo > hi {
        f64::NAN
    } else {
        (v - hi).max(lo - v).max(0.0)
    }
}

fn time_errors(
    m: &Identification,
    ea: &Features,
    eb: &Features,
    keep: &dyn Fn(usize) -> bool,
) -> Errors {
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
    // Where both touch both flanks, the centre the motion oscillates about, relative to the
    // measured amplitude: an offset clearance or a preload moves it, and the envelope alone
    // cannot tell (a shifted dead zone shifts z, not its envelope). Off contact the centre
    // is wherever the free flight drifted, and is not compared.
    let centre_error = |i: usize| -> f64 {
        let (Some(dz), Some(cm), Some(cs)) = (m.dead_zone, &ea.centre, &eb.centre) else {
            return 0.0;
        };
        let high = (GRAZING.1 * dz.half_gap.value).ln();
        let touching = la[i] > high && lb[i] > high;
        let e = (cs.get(i).copied().unwrap_or(f64::NAN) - cm[i]) / a.amplitude[i];
        if touching && e.is_finite() {
            e
        } else {
            0.0
        }
    };
    // The measurement chain's resolution: the quantisation error one of the two has and
    // the other lacks, relative to the measured amplitude. It is the noise floor a coarse
    // encoder leaves at small amplitude, and weighs most there; an error as large as the
    // amplitude counts as a miss (1), like an envelope the other lacks.
    let resolution_gap = (eb.resolution - ea.resolution).abs();
    let resolution_error = |i: usize| -> f64 {
        if resolution_gap == 0.0 {
            0.0
        } else {
            (resolution_gap / a.amplitude[i]).min(1.0).powi(2)
        }
    };
    let mut terms = Vec::new();
    let mut regions = Vec::new();
    for (w, start) in (0..n).step_by(window).enumerate() {
        let end = (start + window).min(n);
        let (mut alo, mut ahi, mut flo, mut fhi) = (f64::INFINITY, 0f64, f64::INFINITY, 0f64);
        for i in start..end {
            if !keep(i) || !la[i].is_finite() || grazing(a.amplitude[i]) {
                continue;
            }
            // Both ways: the measurement within the model's tolerance band and the model's
            // own envelope (where it has one) within the measurement's.
            // A model with no valid envelope within the tolerance misses the sample.
            let e1 = outside(la[i], eb.lo[i], eb.hi[i]);
            let e1 = if e1.is_finite() { e1 } else { 1.0 };
            let e2 = if lb[i].is_finite() {
                outside(lb[i], ea.lo[i], ea.hi[i])
            } else {
                e1
            };
            terms.push((
                a.amplitude[i] / peak,
                0.5 * (e1 * e1 + e2 * e2) + centre_error(i).powi(2) + resolution_error(i),
                w,
            ));
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

/// The backbone (natural frequency) or damping-force errors at the samples where both are
/// at resonance, e = (v_sim − v_meas) / rms v_meas, with regions by amplitude range (their
/// time and frequency spans taken from the measured track).
///
/// The comparison is made at the same instants, not over amplitude bins: a sweep passes
/// its resonance twice — riding up the backbone and falling off it before the jump — with
/// different damping estimates at the same amplitude, and a binned skeleton mixes the two
/// branches in proportions that jump with every small change of a model.
fn resonance_errors(
    m: &Identification,
    meas: &[f64],
    sim: &[f64],
    keep: &dyn Fn(usize) -> bool,
    domain: &'static str,
) -> Errors {
    let r = &m.response;
    let ours: Vec<usize> = (0..meas.len())
        .filter(|&i| keep(i) && meas[i].is_finite())
        .collect();
    let scale =
        (ours.iter().map(|&i| meas[i].powi(2)).sum::<f64>() / ours.len().max(1) as f64).sqrt();
    let (lo, hi) = ours.iter().fold((f64::INFINITY, 0f64), |(l, h), &i| {
        (l.min(r.amplitude[i]), h.max(r.amplitude[i]))
    });
    let range_of = |a: f64| -> usize {
        if hi <= lo {
            return 0;
        }
        let u = (a / lo).ln() / (hi / lo).ln();
        ((u.max(0.0) * AMPLITUDE_RANGES as f64) as usize).min(AMPLITUDE_RANGES - 1)
    };
    // Where the model is not at resonance at that instant, its value at the nearest instant
    // it is: a model whose resonance comes early or late is then off by the frequency the
    // sweep had moved on by, a graded error, instead of being compared nowhere.
    let nearest = nearest_finite(sim);
    let mut terms: Vec<(f64, f64, usize)> = Vec::new();
    if scale > 0.0 {
        for &i in &ours {
            // A model never at resonance (too damped to reach the measured resonance, say)
            // misses all of it.
            let e = nearest
                .get(i)
                .copied()
                .flatten()
                .map_or(1.0, |j| (sim[j] - meas[i]) / scale);
            terms.push((1.0, e * e, range_of(r.amplitude[i])));
        }
    }
    // Each amplitude range's time and frequency span, from the measured track.
    let regions = (0..AMPLITUDE_RANGES)
        .map(|k| {
            let a_lo = lo * (hi / lo).powf(k as f64 / AMPLITUDE_RANGES as f64);
            let a_hi = lo * (hi / lo).powf((k + 1) as f64 / AMPLITUDE_RANGES as f64);
            let (mut t0, mut t1, mut f_lo, mut f_hi) = (f64::INFINITY, 0f64, f64::INFINITY, 0f64);
            for &i in &ours {
                if r.amplitude[i] >= a_lo && r.amplitude[i] <= a_hi {
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

/// A model simulated under a measured run's own input: the simulated run and its
/// identification (made like the measurement's).
pub struct Simulated {
    /// The simulated run (the measured one with its channels replaced).
    pub run: Run,
    /// Its identification.
    pub identified: Identification,
    /// The RMS quantisation error the model's measurement chain puts on the response
    /// ([`model_resolution`]).
    pub resolution: f64,
}

impl Simulated {
    /// What the gap compares of it.
    pub fn features(&self) -> Features {
        Features::of(&self.identified, &self.run).with_resolution(self.resolution)
    }
}

/// The model simulated under `measured`'s own input, identified like the measurement.
pub fn simulate_like(
    measured: &Run,
    model: &RigModel,
    identifier: Identifier<'_>,
) -> Result<Simulated, GapError> {
    simulate_given(measured, None, model, 1, identifier)
}

/// Samples per cycle of the highest tracked frequency that a run decimated for the search
/// keeps.
pub const SAMPLES_PER_CYCLE: f64 = 20.0;

/// The factor a run can be decimated by before it is identified for the search: its rate
/// over [`SAMPLES_PER_CYCLE`] samples of the highest frequency either of its tracks
/// reaches (1 to 8). The identification's cost falls with the samples, and the 1 kHz of a
/// sweep that ends at 12 Hz carries nothing the envelope, backbone or damping need.
pub fn decimation_for(id: &Identification) -> usize {
    let highest = |t: &crate::track::Track| {
        (0..t.len())
            .filter(|&i| t.valid[i])
            .map(|i| t.frequency[i])
            .fold(0f64, f64::max)
    };
    let f = highest(&id.response).max(id.input.as_ref().map_or(0.0, highest));
    if f <= 0.0 {
        return 1;
    }
    ((id.response.sample_rate / (SAMPLES_PER_CYCLE * f)).floor() as usize).clamp(1, 8)
}

/// `run` low-passed (zero-phase, at 40 % of the new Nyquist frequency) and kept one sample
/// in `factor`; itself when `factor` is 1. The measurement and every simulation compared
/// with it go through the same filter.
pub fn decimate(run: Run, factor: usize) -> Run {
    if factor <= 1 {
        return run;
    }
    let down = |x: &[f64]| -> Vec<f64> {
        crate::filter::lowpass_zero_phase(x, 0.4 / factor as f64)
            .into_iter()
            .step_by(factor)
            .collect()
    };
    let output = down(&run.output);
    let mut meta = run.meta.clone();
    meta.sample_rate = run.meta.sample_rate / factor as f64;
    meta.samples = output.len();
    Run {
        meta,
        input: run.input.as_deref().map(down),
        output,
    }
}

/// [`simulate_like`], decimated by `factor` before it is identified (see [`decimate`]),
/// reusing the measurement's input track when `identified` is given (the simulation is
/// driven by that very input, so tracking it again only costs time).
pub fn simulate_given(
    measured: &Run,
    identified: Option<&Identification>,
    model: &RigModel,
    factor: usize,
    identifier: Identifier<'_>,
) -> Result<Simulated, GapError> {
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
    // The encoder's quantisation enters the gap as the resolution it gives the response,
    // not by quantising this noise-free simulation: a real encoder quantises a noisy signal
    // whose noise dithers the steps away from the envelope, while a noise-free response
    // quantised turns into a staircase whose envelope and frequency jitter sample to sample
    // (the true model of a quantised rig then fitted worse than the same model without it).
    let resolution = model_resolution(model, measured);
    let mut unquantised = model.clone();
    unquantised
        .effects
        .set(crate::model::EffectKind::Quantization, None);
    let out = simulate(&unquantised, &drive, &settings);
    let run = Run {
        meta: measured.meta.clone(),
        input: Some(out.input),
        output: out.output,
    };
    let run = decimate(run, factor);
    let identified = match identified.and_then(|i| i.input.as_ref()) {
        Some(tx) => identifier.identify_with_input_track(&run, Method::Wavelet, tx),
        None => identifier.identify(&run, Method::Wavelet),
    }
    .map_err(|e| GapError::Simulated(e.to_string()))?;
    Ok(Simulated {
        run,
        identified,
        resolution,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn mean_around_matches_a_naive_mean_of_the_finite_values() {
        let x: Vec<f64> = (0..300)
            .map(|i| {
                if i % 7 == 2 {
                    f64::NAN
                } else {
                    ((i * 13) % 29) as f64
                }
            })
            .collect();
        for half in [0, 3, 50, 400] {
            let y = mean_around(&x, |i| x[i].is_finite().then_some(half));
            for i in 0..x.len() {
                if !x[i].is_finite() {
                    assert!(y[i].is_nan());
                    continue;
                }
                let w: Vec<f64> = x[i.saturating_sub(half)..(i + half + 1).min(x.len())]
                    .iter()
                    .copied()
                    .filter(|v| v.is_finite())
                    .collect();
                let mean = w.iter().sum::<f64>() / w.len() as f64;
                assert!((y[i] - mean).abs() < 1e-9, "i {i} half {half}");
            }
        }
    }

    /// A 3 Hz sine of 0.02 amplitude sampled at 1 kHz, plus Gaussian noise of `noise` std
    /// (seeded: the same every run).
    fn noisy_sine(n: usize, noise: f64) -> Vec<f64> {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand::rngs::StdRng::seed_from_u64(12345);
        let normal = Normal::new(0.0, noise).expect("a positive deviation");
        (0..n)
            .map(|i| {
                0.02 * (2.0 * std::f64::consts::PI * 3.0 * i as f64 / 1000.0).sin()
                    + normal.sample(&mut rng)
            })
            .collect()
    }

    #[test]
    fn the_lattice_of_a_quantised_channel_is_found_and_a_continuous_one_has_none() {
        let x = noisy_sine(5000, 1e-4);
        assert_eq!(lattice_step(&x), None);
        for q in [1e-4, 3.7e-4, 2e-3] {
            let on: Vec<f64> = x.iter().map(|v| (v / q).round() * q).collect();
            let step = lattice_step(&on).unwrap();
            assert!((step / q - 1.0).abs() < 1e-9, "{q}: {step}");
            // A lattice need not pass through zero (an ADC's offset).
            let shifted: Vec<f64> = on.iter().map(|v| v + 0.3 * q).collect();
            let step = lattice_step(&shifted).unwrap();
            assert!((step / q - 1.0).abs() < 1e-9, "{q}: {step}");
            // Stored as f32, the lattice survives.
            let single: Vec<f64> = on.iter().map(|&v| v as f32 as f64).collect();
            assert!(lattice_step(&single).is_some(), "{q}");
        }
        // A constant or nearly constant channel says nothing.
        assert_eq!(lattice_step(&[0.5; 1000]), None);
        let two: Vec<f64> = (0..1000).map(|i| (i % 2) as f64 * 1e-3).collect();
        assert_eq!(lattice_step(&two), None);
    }

    #[test]
    fn a_base_motion_run_counts_both_channels_and_a_model_matches_it() {
        use crate::run::{Quantity, RunKind, RunMeta};
        let q = 2e-4;
        let y: Vec<f64> = noisy_sine(3000, 1e-4)
            .iter()
            .map(|v| (v / q).round() * q)
            .collect();
        let x: Vec<f64> = y.iter().map(|v| (0.5 * v / q).round() * q).collect();
        let meta = RunMeta {
            path: "/q".into(),
            samples: y.len(),
            sample_rate: 1000.0,
            duration: 3.0,
            kind: RunKind::BaseMotion,
            input_quantity: Some(Quantity::Displacement),
            output_quantity: Quantity::Displacement,
            inertia: None,
            gravity_stiffness: 0.0,
            units: None,
            excitation: None,
            attributes: Default::default(),
            mode_band: None,
            mode_near: None,
        };
        let run = Run {
            meta,
            input: Some(x),
            output: y,
        };
        let r = measured_resolution(&run);
        assert!((r - q * (2.0f64 / 12.0).sqrt()).abs() < 1e-12, "{r}");
        let mut model = RigModel::paper();
        assert_eq!(model_resolution(&model, &run), 0.0);
        model
            .effects
            .set(crate::model::EffectKind::Quantization, Some(q));
        assert!((model_resolution(&model, &run) - r).abs() < 1e-12);
        // Filtered, the lattice is gone: read the resolution before decimating.
        assert_eq!(measured_resolution(&decimate(run, 4)), 0.0);
    }

    #[test]
    fn settling_follows_each_jump_down_and_pairs_within_a_second() {
        let fs = 100.0;
        let d: f64 = 0.01;
        // High (2δ) for 1 s, a jump to 0.2δ, high again from 5 s, a second jump at 6 s.
        let ln: Vec<f64> = (0..1000)
            .map(|i| {
                if i < 100 || (500..600).contains(&i) {
                    (2.0 * d).ln()
                } else {
                    (0.2 * d).ln()
                }
            })
            .collect();
        let w = settling(&ln, fs, d, 2.0);
        assert_eq!(w, vec![(100, 300), (600, 800)]);
        // Both climbs onto the high branch are jump-ups.
        assert_eq!(jump_ups(&ln, d), vec![(0, 0), (500, 500)]);
        // A climb through invalid samples starts after the last sample below the band.
        let mut climb = ln.clone();
        climb[498] = f64::NAN;
        climb[499] = (0.9 * d).ln();
        climb[500] = f64::NAN;
        climb[501] = (2.0 * d).ln();
        assert_eq!(jump_ups(&climb[..600], d), vec![(0, 0), (498, 501)]);
        // A partner 0.5 s later widens the window; one 3 s later pairs with nothing.
        let flags = paired_settling(&w, &[(150, 350), (900, 1000)], 100);
        assert!(flags[100] && flags[349] && !flags[350]);
        assert!(!flags.get(600).copied().unwrap_or(false));
    }
}
