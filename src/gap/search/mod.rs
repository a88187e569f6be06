//! The diagnosis of one run (DESIGN.md, "Simulation and the sim-to-real gap", steps 2–3):
//! refit the model's own parameters (the baseline), then add each effect of the vocabulary
//! and fit it with them on the even time blocks, score every model on the odd blocks the
//! fits never saw, and give the verdict.
//!
//! The search is kept affordable by screening: each effect is first scanned alone over a
//! coarse grid of its parameter on the baseline and on the nominal model (ten simulations
//! an effect), and the best point of each side is refined by the simplex together with the
//! model's own parameters. The scan gives the simplex a start in the right basin: started
//! from a guess, the dry friction fit stopped in a local minimum at two thirds of the true
//! torque, and started from the baseline only, an effect the baseline had absorbed (contact
//! damping into 60 % more viscous damping) stayed absorbed. Quantization is not searched:
//! its step is read off the lattice the samples lie on; the mode's own parameters are
//! refitted with the step held where the lattice is new to the model (on the time domain
//! alone, against the model refitted there without it, in a force or free model). A force
//! or free model's `cubic_stiffness + microslip` pair gets a second start in the basin of
//! a bolted joint that holds until a sharp onset ([`joint`]).

use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use rayon::prelude::*;

mod candidate;
mod fit;
mod iwan;
mod joint;

use candidate::{fitter, ready_for, refit, Side};
pub use candidate::{signature, Candidate};
pub use fit::{effect_start, nelder_mead, refit_baseline, refit_with, Fitted};
use fit::{start_for, Coordinates};

use super::{
    decimate, decimation_for, measured_resolution, resolution_per_step, simulate_given, Blocks,
    GapError, Part, Target,
};
use crate::fit::DeadZoneFit;
use crate::identify::{Identification, Identifier, IdentifyOptions};
use crate::mode::ModeChoice;
use crate::model::{EffectKind, ModelKind, RigModel};
use crate::run::{Run, RunKind};
use crate::track::Method;

/// A candidate's held-out shrink must reach this for a verdict: in the self-check's
/// effect-free cases, candidates that fitted the fitting blocks better than the baseline
/// reduced the withheld blocks' gap by up to 44 % (README, "Sim-to-real gap").
pub const MIN_SHRINK: f64 = 0.5;
/// ... and the held-out gap must fall by at least this much in absolute terms: below it the
/// baseline already matches to within the noise and the identification's own scatter (on
/// the self-check's noisy paper rigs, models that fit the fitting blocks equally well
/// differ on the withheld ones by up to 0.0013 where no effect is missing).
pub const MIN_DROP: f64 = 0.002;
/// A best single effect whose held-out shrink reaches this, short of [`MIN_SHRINK`], gets
/// one more simplex before the verdict.
pub const BORDERLINE: f64 = 0.3;
/// Pairs of effects are tried when the best single effect leaves more than this fraction of
/// the baseline gap on the withheld blocks.
pub const PAIR_WHEN_LEFT: f64 = 0.4;
/// The share of the fitting runs' time-domain gap a force or free model's converter step
/// must remove on the baseline before it is fitted there ([`fitted_on_time`]); the force
/// self-check's steps remove 20–40 %.
const STEP_MOVES: f64 = 0.01;
/// Multiples of an effect's starting value scanned before any simplex.
const SCAN: [f64; 5] = [0.125, 0.35, 1.0, 2.8, 8.0];

/// How hard the search works.
#[derive(Debug, Clone)]
pub struct SearchOptions {
    /// Fit and held-out blocks.
    pub blocks: Blocks,
    /// Simulations for the baseline refit.
    pub baseline_evaluations: usize,
    /// Scan points refined by the simplex (each effect's best on the baseline and on the
    /// nominal model, and a joint's start read off the skeleton, best first).
    pub refine: usize,
    /// Simulations per refined candidate (and per pair).
    pub candidate_evaluations: usize,
    /// Whether pairs of effects are tried when one alone leaves a large gap.
    pub pairs: bool,
    /// Whether the inertia is refitted too (it is held at the model's value otherwise).
    pub fit_inertia: bool,
    /// Whether the baseline refits the effects the nominal model already has beside its own
    /// parameters (they are held at the model's values otherwise): a model from an earlier
    /// diagnosis updated on other runs.
    pub refit_effects: bool,
    /// The effects to try.
    pub effects: Vec<EffectKind>,
    /// Whether the gap scores the waveform within a cycle as a fourth domain (the third
    /// harmonic of the relative motion against its first, at resonance): what separates a
    /// hardening contact from a stiffer, wider one on a single sweep. On by default.
    pub waveform: bool,
    /// How far apart the encoders' zeros may be (rad), overriding each run's
    /// `zero_tolerance` attribute: a shift of the measured relative motion within it is
    /// not counted in the gap (an offset clearance smaller than it cannot be told from the
    /// sensors' zeros).
    pub zero_tolerance: Option<f64>,
}

impl Default for SearchOptions {
    fn default() -> Self {
        SearchOptions {
            blocks: Blocks { seconds: 1.0 },
            baseline_evaluations: 150,
            refine: 12,
            candidate_evaluations: 45,
            pairs: true,
            fit_inertia: false,
            refit_effects: false,
            effects: EffectKind::ALL.to_vec(),
            waveform: true,
            zero_tolerance: None,
        }
    }
}

/// A model's gap on the fitting blocks and on the withheld ones.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Score {
    /// Gap on the even blocks (what fits minimise).
    pub fit: f64,
    /// Gap on the odd blocks (what fits never see).
    pub holdout: f64,
    /// The held-out gap's time, backbone, damping and waveform domains (`None` where not
    /// scored).
    pub domains: [Option<f64>; 4],
    /// The fitting blocks' time domain (`None` where not scored): what a fit on the time
    /// domain alone minimises ([`Score::fit_on`]).
    pub fit_time: Option<f64>,
    /// The kind of the model scored: which domains an effect acts in depends on it
    /// ([`EffectKind::acts_on_time_alone`]).
    pub model_kind: ModelKind,
}

impl Score {
    const FAILED: Score = Score {
        fit: f64::INFINITY,
        holdout: f64::INFINITY,
        domains: [None; 4],
        fit_time: None,
        model_kind: ModelKind::BaseMotion,
    };

    /// The gap on the fitting blocks on the domains `kinds` act in: the time domain's
    /// where [`holdout_on`](Self::holdout_on) reads the time domain alone, the whole fit
    /// gap otherwise (the fits of every other effect minimise the whole).
    pub fn fit_on(&self, kinds: &[EffectKind]) -> f64 {
        self.fit_gap(self.scores_time_alone(kinds))
    }

    /// The fitting blocks' time domain when `time_alone` (infinite where not scored), their
    /// whole gap otherwise.
    pub fn fit_gap(&self, time_alone: bool) -> f64 {
        if time_alone {
            self.fit_time.unwrap_or(f64::INFINITY)
        } else {
            self.fit
        }
    }

    /// The held-out gap on the domains `kinds` act in: the whole held-out gap; or, when
    /// every effect of `kinds` acts on the time domain alone
    /// ([`EffectKind::acts_on_time_alone`]), that domain's; or, when no effect of `kinds`
    /// shapes the waveform within a cycle ([`EffectKind::shapes_waveform`]), the time,
    /// backbone and damping domains' (a domain such an effect cannot change would only
    /// dilute what it explains).
    pub fn holdout_on(&self, kinds: &[EffectKind]) -> f64 {
        if !self.holdout.is_finite() {
            return self.holdout;
        }
        if self.scores_time_alone(kinds) {
            return self.domains[0].unwrap_or(self.holdout);
        }
        if !self.scores_without_waveform(kinds) {
            return self.holdout;
        }
        let ms: f64 = self.domains[..3].iter().flatten().map(|d| d * d).sum();
        (ms / 3.0).sqrt()
    }

    /// Whether [`holdout_on`](Self::holdout_on) reads the time domain alone for `kinds`.
    pub fn scores_time_alone(&self, kinds: &[EffectKind]) -> bool {
        self.domains[0].is_some()
            && !kinds.is_empty()
            && kinds.iter().all(|k| k.acts_on_time_alone(self.model_kind))
    }

    /// Whether [`holdout_on`](Self::holdout_on) leaves the waveform domain out for `kinds`:
    /// it is scored, and `kinds` has effects, none of which shapes the waveform.
    pub fn scores_without_waveform(&self, kinds: &[EffectKind]) -> bool {
        self.domains[3].is_some() && !kinds.is_empty() && !kinds.iter().any(|k| k.shapes_waveform())
    }

    /// 1 − (this held-out gap / `base`'s), both on the domains `kinds` act in; −∞ where
    /// either is not a finite gap above zero (a failed simulation, or no sample compared),
    /// so such a model ranks last.
    pub fn shrink_against(&self, base: &Score, kinds: &[EffectKind]) -> f64 {
        let (h, b) = (self.holdout_on(kinds), base.holdout_on(kinds));
        if h.is_finite() && b.is_finite() && b > 0.0 {
            1.0 - h / b
        } else {
            f64::NEG_INFINITY
        }
    }

    /// Whether this model clears the verdict's held-out margins against `reference` on
    /// the domains `kinds` act in: its gap at most (1 − [`MIN_SHRINK`]) of the
    /// reference's, and lower by at least [`MIN_DROP`].
    pub fn clears_margins(&self, reference: &Score, kinds: &[EffectKind]) -> bool {
        let (h, r) = (self.holdout_on(kinds), reference.holdout_on(kinds));
        h.is_finite() && h <= (1.0 - MIN_SHRINK) * r && r - h >= MIN_DROP
    }
}

/// How a measured run takes part in a [`Reference`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Role {
    /// One run alone: fits see its even time blocks, gaps are scored on the odd ones.
    Blocks(Blocks),
    /// Fitted on whole (one of several runs fitted together).
    Fit,
    /// Held out whole: scored, never fitted on.
    Holdout,
}

impl Role {
    /// `fit` or `holdout` for a run of several; `blocks` for one alone.
    pub fn name(&self) -> &'static str {
        match self {
            Role::Blocks(_) => "blocks",
            Role::Fit => "fit",
            Role::Holdout => "holdout",
        }
    }
}

/// One measured run of a reference, identified once, with the parts of it that fits see
/// and that gaps are scored on.
struct Measured {
    /// The run as measured (a force run without an `inertia` attribute gets the modal mass
    /// its identification estimated, so that every simulation of it is read with the same).
    run: Run,
    /// The decimation of the run as compared (see [`super::decimate`]).
    factor: usize,
    identified: Identification,
    resolution: f64,
    /// The user's identification options with the mode band fixed to the one the
    /// measurement was identified in: a simulation is isolated on the same band, not on its
    /// own largest peak.
    options: IdentifyOptions,
    role: Role,
    /// Of a free decay: the mode's displacement and velocity at the record's (cut) first
    /// sample, where every simulation starts.
    start: Option<(f64, f64)>,
    /// Of a free decay: where in its record it was cut.
    release: Option<Release>,
    fit: Option<Target>,
    holdout: Option<Target>,
    whole: Target,
}

/// The targets of `run` as its `role` says (fit, held-out, whole), from `identified`, its
/// identification of the run as `compared` (decimated), scored as the search's defaults:
/// the waveform domain on (where the run has one), the run's own zero tolerance, and its
/// measured `resolution`. An accelerometer's lattice is in m/s²: the gap compares it with
/// the displacement the identification tracks.
fn targets(
    identified: &Identification,
    run: &Run,
    compared: &Run,
    role: Role,
    resolution: f64,
) -> (Option<Target>, Option<Target>, Target) {
    let (n, fs) = (compared.output.len(), compared.meta.sample_rate);
    let tracked = super::as_displacement(resolution, run, Some(identified));
    let target = |mask| {
        Target::new(identified, compared, mask)
            .with_resolution(tracked)
            .with_waveform(true)
    };
    let (fit, holdout) = match role {
        Role::Blocks(blocks) => (
            Some(target(Some(blocks.mask(n, fs, Part::Fit)))),
            Some(target(Some(blocks.mask(n, fs, Part::Holdout)))),
        ),
        Role::Fit => (Some(target(None)), None),
        Role::Holdout => (None, Some(target(None))),
    };
    (fit, holdout, target(None))
}

/// Refuses alternate blocks of which the fitting or the held-out part holds no valid
/// sample of `identified` (a block as long as the record, or the valid stretch within one
/// block): a held-out gap over nothing read 0, a perfect score.
fn both_parts_seen(
    identified: &Identification,
    [fit, holdout]: [&Option<Target>; 2],
    blocks: Blocks,
    run: &Run,
) -> Result<(), GapError> {
    let valid = &identified.response.valid;
    let seen = |t: &Option<Target>| {
        t.as_ref()
            .and_then(|t| t.mask.as_ref())
            .is_none_or(|m| m.iter().zip(valid).any(|(&a, &b)| a && b))
    };
    let part = match (seen(fit), seen(holdout)) {
        (true, true) => return Ok(()),
        (false, _) => "fit on (the even blocks)",
        (true, false) => "score the gap on (the odd blocks)",
    };
    let fs = run.meta.sample_rate;
    let length = run.output.len() as f64 / fs;
    let span =
        |i: Option<usize>| i.map_or(f64::NAN, |i| i as f64 / identified.response.sample_rate);
    let (first, last) = (
        span(valid.iter().position(|&v| v)),
        span(valid.iter().rposition(|&v| v)),
    );
    Err(GapError::Unusable(format!(
        "the measured run {}: alternate {} s blocks leave no valid sample to {part}: the run \
         is {length:.2} s long as compared{}, its first valid sample at {first:.2} s and its \
         last at {last:.2} s; give longer runs, or shorter blocks (skelid gap's \
         --holdout-block), at most a third of that stretch ({:.2} s)",
        run.meta.path,
        blocks.seconds,
        if run.meta.kind == RunKind::Free {
            " (from its release)"
        } else {
            ""
        },
        (last - first) / 3.0
    )))
}

/// Base-motion runs of one rig share its clearance: a run is scored with the dead zone
/// identified on the fitted run that reached furthest into the contact, when that run
/// reached further than it did. A run that never touches cannot measure the clearance, and
/// the dead zone its own backbone gives is noise (2e-5 rad on the two-run self-check's low
/// level, against the rig's 0.013): read as the contact, it had every sample of that run
/// "touching", and the free flight's drift, which dry friction leaves wherever the link
/// stuck, scored as an offset clearance would — the true model with the friction scored
/// worse than the baseline without it. One record holding both levels had one dead zone,
/// the right one. Held-out runs are never the source (nothing of theirs reaches a fit); one
/// that reached further than every fitted run keeps its own. Force and free runs (modes of
/// structures) keep their own: their models have no clearance to share unless one is added
/// as an effect.
fn share_contact(runs: &mut [Measured]) {
    if runs.len() < 2 || runs.iter().any(|m| m.run.meta.kind != RunKind::BaseMotion) {
        return;
    }
    let source = runs
        .iter()
        .filter(|m| m.role != Role::Holdout)
        .map(|m| (m.reach(), m.identified.dead_zone))
        .max_by(|a, b| a.0.total_cmp(&b.0));
    let Some((reach, Some(contact))) = source else {
        return;
    };
    for m in runs.iter_mut() {
        let own = m.identified.dead_zone.map(|d| d.half_gap.value);
        if m.reach() < reach && own != Some(contact.half_gap.value) {
            m.set_contact(contact);
        }
    }
}

impl Measured {
    fn new(run: &Run, role: Role, identifier: Identifier<'_>) -> Result<Self, GapError> {
        let free = run.meta.kind == RunKind::Free;
        if run.input.is_none() && !free {
            return Err(GapError::Unusable(format!(
                "{}: the run has no input channel to drive the model with (a free decay is \
                 simulated from its own state by a model of kind = \"free\")",
                run.meta.path
            )));
        }
        let unusable = |e| GapError::Unusable(format!("the measured run {}: {e}", run.meta.path));
        let mut full = identifier
            .identify(run, Method::Wavelet)
            .map_err(unusable)?;
        let mut run = run.clone();
        let mut options = identifier.options.clone();
        if let Some(b) = full.mode {
            options.mode = ModeChoice::Band(b.fmin, b.fmax);
        }
        if run.meta.kind == RunKind::Force && run.meta.inertia.is_none() {
            if let Some((m, _)) = full.mass {
                run.meta.inertia = Some(m);
            }
        }
        let fixed = Identifier {
            options: &options,
            backend: identifier.backend,
        };
        // A free decay is compared from where its envelope peaks, once the band-pass has
        // let go of the impact: the record is cut there, and every simulation starts from
        // the mode's state at that sample (both then have the same edge at their start).
        let (mut start, mut release) = (None, None);
        if free {
            let fs = run.meta.sample_rate;
            let hit = impact(&run);
            let settled = settled_after(hit, full.mode, fs);
            let (i0, state, past_spread) = release_point(&full, settled).ok_or_else(|| {
                GapError::Unusable(format!(
                    "the measured run {}: no valid sample of the mode to start its decay from",
                    run.meta.path
                ))
            })?;
            release = Some(Release {
                at_s: i0 as f64 / fs,
                hit_s: hit as f64 / fs,
                spread_s: full.mode.map_or(0.0, |b| b.spread()),
                past_spread,
            });
            run.output.drain(..i0);
            run.meta.samples = run.output.len();
            start = Some(state);
            full = fixed.identify(&run, Method::Wavelet).map_err(unusable)?;
        } else if options.mode != identifier.options.mode || run.meta.inertia.is_some() {
            full = fixed.identify(&run, Method::Wavelet).map_err(unusable)?;
        }
        let factor = decimation_for(&full);
        let compared = decimate(run.clone(), factor);
        let identified = if factor > 1 {
            fixed
                .identify(&compared, Method::Wavelet)
                .map_err(unusable)?
        } else {
            full
        };
        let resolution = measured_resolution(&run);
        let (fit, holdout, whole) = targets(&identified, &run, &compared, role, resolution);
        if let Role::Blocks(blocks) = role {
            both_parts_seen(&identified, [&fit, &holdout], blocks, &run)?;
        }
        Ok(Measured {
            whole,
            fit,
            holdout,
            role,
            run,
            factor,
            identified,
            resolution,
            options,
            start,
            release,
        })
    }

    /// The largest valid amplitude of its measured response (signal units): how far into
    /// the contact the run reached.
    fn reach(&self) -> f64 {
        let r = &self.identified.response;
        (0..r.len())
            .filter(|&i| r.valid[i])
            .map(|i| r.amplitude[i])
            .fold(0.0, f64::max)
    }

    /// Scores this run with `contact` as the measured clearance (its jumps, grazing band
    /// and where the centre of the motion is compared), its targets prepared again.
    fn set_contact(&mut self, contact: DeadZoneFit) {
        self.identified.dead_zone = Some(contact);
        let compared = decimate(self.run.clone(), self.factor);
        (self.fit, self.holdout, self.whole) = targets(
            &self.identified,
            &self.run,
            &compared,
            self.role,
            self.resolution,
        );
    }

    fn targets(&mut self) -> impl Iterator<Item = &mut Target> {
        self.fit
            .iter_mut()
            .chain(self.holdout.iter_mut())
            .chain(std::iter::once(&mut self.whole))
    }

    fn simulate(
        &self,
        model: &RigModel,
        backend: &crate::backend::Backend,
    ) -> Result<super::Simulated, GapError> {
        let identifier = Identifier {
            options: &self.options,
            backend,
        };
        match self.start {
            Some(state) => super::simulate_released(
                &self.run,
                Some(&self.identified),
                model,
                state,
                self.factor,
                identifier,
            ),
            None => simulate_given(
                &self.run,
                Some(&self.identified),
                model,
                self.factor,
                identifier,
            ),
        }
    }
}

/// The first sample a free decay may be released from: [`ModeBand::spread`] after its
/// impact at sample `hit` ([`impact`]) of a record at `fs` Hz, where the band-pass has let
/// go of it; the first sample where the mode was not isolated. Released at its envelope's peak, within that
/// spread, the Brake–Reuss beam's weakest sensor read a damping ratio of 1.38 % at its
/// largest amplitude, against 0.18–0.25 % on every sensor past it (README, "The
/// Brake–Reuss beam").
fn settled_after(hit: usize, band: Option<crate::mode::ModeBand>, fs: f64) -> usize {
    band.map_or(0, |b| hit + (b.spread() * fs).ceil() as usize)
}

/// The record's largest finite sample: a hammer test's hit.
fn impact(run: &Run) -> usize {
    run.output
        .iter()
        .enumerate()
        .filter(|(_, v)| v.is_finite())
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
        .map_or(0, |(i, _)| i)
}

/// Where a free decay's comparison starts in its record, for the user: every time the
/// diagnosis reports (gap regions, the envelope's plot) is the record's own, from its
/// first sample.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Release {
    /// The first sample compared, the mode's envelope peak past the impact (s).
    pub at_s: f64,
    /// The record's largest sample, taken as the hammer's hit (s).
    pub hit_s: f64,
    /// How long after the hit the band-pass still carries the impact (s; 0 where no band
    /// isolated the mode): [`crate::mode::ModeBand::spread`].
    pub spread_s: f64,
    /// Whether a valid sample lay past hit + spread. If none did, the decay is released at
    /// the record's own envelope peak, where the band-pass may still carry the impact.
    pub past_spread: bool,
}

impl Release {
    /// Where it lies, in words: "the mode's envelope peak past the band-pass's 0.157 s
    /// spread of the hit at 0.126 s".
    pub fn describe(&self) -> String {
        let peak = "the mode's envelope peak";
        if !self.past_spread {
            format!(
                "the whole record's envelope peak, not past the band-pass's {:.3} s spread of \
                 the hit at {:.3} s",
                self.spread_s, self.hit_s
            )
        } else if self.spread_s > 0.0 {
            format!(
                "{peak} past the band-pass's {:.3} s spread of the hit at {:.3} s",
                self.spread_s, self.hit_s
            )
        } else {
            format!("{peak} from the hit at {:.3} s on", self.hit_s)
        }
    }

    /// The warning a release inside the impact's spread deserves (`None` past it).
    pub fn warning(&self) -> Option<String> {
        (!self.past_spread).then(|| {
            format!(
                "no valid sample of the mode {:.3} s after the hit at t = {:.3} s (the \
                 band-pass's spread of the impact); the decay is compared from its envelope's \
                 peak at t = {:.3} s, where the impact may still show (a longer record, or a \
                 band with a higher lower edge, waits less)",
                self.spread_s, self.hit_s, self.at_s
            )
        })
    }
}

/// Where a free decay is released from: the valid sample of its mode's largest envelope
/// from sample `settled` on ([`settled_after`]; from the record's start where no
/// sample past it is valid), with the mode's displacement A·cos φ and velocity A′·cos φ −
/// A·ω·sin φ there, from the analytic signal the identification tracked.
/// The flag is whether it lies past `settled`.
fn release_point(id: &Identification, settled: usize) -> Option<(usize, (f64, f64), bool)> {
    let t = &id.response;
    let valid = |i: &usize| t.valid[*i] && t.amplitude[*i].is_finite();
    let past = (settled..t.len()).any(|i| valid(&i));
    let from = if past { settled } else { 0 };
    let i = (from..t.len())
        .filter(valid)
        .max_by(|&a, &b| t.amplitude[a].total_cmp(&t.amplitude[b]))?;
    let (a, phi) = (t.amplitude[i], t.phase[i]);
    let w = std::f64::consts::TAU * t.frequency[i];
    let da = t
        .d_amplitude
        .get(i)
        .copied()
        .filter(|v| v.is_finite())
        .unwrap_or(0.0);
    Some((i, (a * phi.cos(), da * phi.cos() - a * w * phi.sin()), past))
}

/// The measured runs, identified once, that models are scored against: one run split into
/// alternate time blocks, or several runs of one structure, some fitted together and the
/// others held out whole.
pub struct Reference<'a> {
    runs: Vec<Measured>,
    evaluations: AtomicUsize,
    on_score: Option<Box<dyn Fn(usize) + Send + Sync + 'a>>,
    /// How the measurement and every simulation are identified.
    identifier: Identifier<'a>,
}

impl<'a> Reference<'a> {
    /// Identifies `run` (wavelet method, with `identifier`'s options and backend, as every
    /// simulation will be), decimated as far as its band allows, and splits it into
    /// `blocks`. It scores as [`SearchOptions::default`] searches: the waveform domain on
    /// (where the run has one) and the run's `zero_tolerance`; [`scored_as`](Self::scored_as)
    /// sets both from other options.
    pub fn new(run: &Run, blocks: Blocks, identifier: Identifier<'a>) -> Result<Self, GapError> {
        Self::of(
            vec![Measured::new(run, Role::Blocks(blocks), identifier)?],
            identifier,
        )
    }

    /// Several runs of one structure: models are fitted on the `fit` runs together (the
    /// fit's gap is the RMS of theirs) and scored on the `holdout` runs (likewise), each
    /// driven by its own measured input. The first fit run is the one the search reads
    /// its starting values from.
    pub fn together(
        fit: &[&Run],
        holdout: &[&Run],
        identifier: Identifier<'a>,
    ) -> Result<Self, GapError> {
        if fit.is_empty() || holdout.is_empty() {
            return Err(GapError::Unusable(
                "runs fitted together need at least one fit run and one held-out run".into(),
            ));
        }
        let roles = fit
            .iter()
            .map(|r| (*r, Role::Fit))
            .chain(holdout.iter().map(|r| (*r, Role::Holdout)))
            .collect::<Vec<_>>();
        let runs = roles
            .par_iter()
            .map(|(r, role)| Measured::new(r, *role, identifier))
            .collect::<Result<Vec<_>, _>>()?;
        Self::of(runs, identifier)
    }

    /// Several runs of one rig (levels, say) fitted together on the even time `blocks` of
    /// each and scored on the odd ones: the one-run scheme over several records.
    pub fn blocks_together(
        runs: &[&Run],
        blocks: Blocks,
        identifier: Identifier<'a>,
    ) -> Result<Self, GapError> {
        if runs.is_empty() {
            return Err(GapError::Unusable("no run to fit".into()));
        }
        let runs = runs
            .par_iter()
            .map(|r| Measured::new(r, Role::Blocks(blocks), identifier))
            .collect::<Result<Vec<_>, _>>()?;
        Self::of(runs, identifier)
    }

    fn of(mut runs: Vec<Measured>, identifier: Identifier<'a>) -> Result<Self, GapError> {
        share_contact(&mut runs);
        Ok(Reference {
            runs,
            evaluations: AtomicUsize::new(0),
            on_score: None,
            identifier,
        })
    }

    /// The (first) run: the one the search reads its starting values from.
    pub fn run(&self) -> &Run {
        &self.runs[0].run
    }

    /// Its identification (of the run as compared).
    pub fn identified(&self) -> &Identification {
        &self.runs[0].identified
    }

    /// The identifications of the runs the fits see (a run alone on alternate blocks is
    /// one of them), the first fit run's first.
    pub fn fitted_identifications(&self) -> Vec<&Identification> {
        self.runs
            .iter()
            .filter(|m| m.role != Role::Holdout)
            .map(|m| &m.identified)
            .collect()
    }

    /// The skeletons of what the fits see of each run they see (the first fit run's
    /// first): a fit run's whole, a run alone on alternate blocks its fitting blocks
    /// only, so that a start read off them never saw the blocks it is scored on.
    pub fn fitted_skeletons(&self) -> Vec<Vec<crate::fit::Bin>> {
        self.runs
            .iter()
            .filter_map(|m| {
                let fit = m.fit.as_ref()?;
                Some(
                    m.identified
                        .skeleton_within(fit.mask.as_deref(), m.options.bins),
                )
            })
            .collect()
    }

    /// The RMS quantisation error of its response, read from the samples as recorded
    /// ([`super::measured_resolution`]; 0 when no channel lies on a lattice).
    pub fn resolution(&self) -> f64 {
        self.runs[0].resolution
    }

    /// How many measured runs it holds.
    pub fn len(&self) -> usize {
        self.runs.len()
    }

    /// Whether it holds no run (never: every constructor gives it one).
    pub fn is_empty(&self) -> bool {
        self.runs.is_empty()
    }

    /// Run `i`'s measurement, identification and role.
    pub fn measured(&self, i: usize) -> (&Run, &Identification, Role) {
        let m = &self.runs[i];
        (&m.run, &m.identified, m.role)
    }

    /// Where run `i`, a free decay, was cut from its record (`None` for other kinds).
    pub fn release(&self, i: usize) -> Option<Release> {
        self.runs[i].release
    }

    /// The same reference with its parts exchanged: fits see the odd blocks (the held-out
    /// runs) and gaps are scored on the even ones (the fit runs): a second, independent fit.
    pub fn swapped(mut self) -> Self {
        for m in &mut self.runs {
            std::mem::swap(&mut m.fit, &mut m.holdout);
        }
        self
    }

    /// The same reference, scoring the waveform domain too when `on` (see
    /// [`SearchOptions::waveform`]).
    pub fn with_waveform(mut self, on: bool) -> Self {
        for m in &mut self.runs {
            m.targets().for_each(|t| t.set_waveform(on));
        }
        self
    }

    /// The same reference scored as `opt` asks: the waveform domain and the encoders' zero
    /// tolerance.
    pub fn scored_as(self, opt: &SearchOptions) -> Self {
        self.with_waveform(opt.waveform)
            .with_zero_tolerance(opt.zero_tolerance)
    }

    /// The same reference with the encoders' zero tolerance set to `tolerance` (rad) when
    /// given, instead of the run's attribute (see [`SearchOptions::zero_tolerance`]).
    pub fn with_zero_tolerance(mut self, tolerance: Option<f64>) -> Self {
        if let Some(t) = tolerance {
            for m in &mut self.runs {
                m.targets().for_each(|target| target.set_zero_tolerance(t));
            }
        }
        self
    }

    /// The encoders' zero tolerance this reference scores with (rad).
    pub fn zero_tolerance(&self) -> f64 {
        self.runs[0].whole.zero_tolerance()
    }

    /// Calls `f` with the number of simulations so far after each one (progress displays).
    pub fn on_score(mut self, f: impl Fn(usize) + Send + Sync + 'a) -> Self {
        self.on_score = Some(Box::new(f));
        self
    }

    /// Simulates `model` under every run and scores it on both parts (infinite where a
    /// response cannot be identified: a model that far off is simply bad). Over several
    /// runs each part's gap is the RMS of its runs' (each domain likewise).
    pub fn score(&self, model: &RigModel) -> Score {
        let n = self.evaluations.fetch_add(1, Ordering::Relaxed) + 1;
        if let Some(f) = &self.on_score {
            f(n);
        }
        let gaps: Option<Vec<(Option<super::Gap>, Option<super::Gap>)>> = self
            .runs
            .par_iter()
            .map(|m| {
                let s = m.simulate(model, self.identifier.backend).ok()?;
                let features = s.features();
                let id = &m.identified;
                Some((
                    m.fit.as_ref().map(|t| t.gap(id, &features)),
                    m.holdout.as_ref().map(|t| t.gap(id, &features)),
                ))
            })
            .collect();
        let Some(gaps) = gaps else {
            return Score::FAILED;
        };
        let rms = |values: Vec<f64>| -> Option<f64> {
            (!values.is_empty())
                .then(|| (values.iter().map(|v| v * v).sum::<f64>() / values.len() as f64).sqrt())
        };
        let fitted: Vec<&super::Gap> = gaps.iter().filter_map(|g| g.0.as_ref()).collect();
        let fits: Vec<f64> = fitted.iter().map(|g| g.total).collect();
        let held: Vec<&super::Gap> = gaps.iter().filter_map(|g| g.1.as_ref()).collect();
        let domain =
            |d: fn(&super::Gap) -> Option<f64>| rms(held.iter().filter_map(|g| d(g)).collect());
        Score {
            fit: rms(fits).unwrap_or(f64::INFINITY),
            holdout: rms(held.iter().map(|g| g.total).collect()).unwrap_or(f64::INFINITY),
            domains: [
                domain(|g| g.time),
                domain(|g| g.backbone),
                domain(|g| g.damping),
                domain(|g| g.waveform),
            ],
            fit_time: rms(fitted.iter().filter_map(|g| g.time).collect()),
            model_kind: model.kind,
        }
    }

    /// The gap of `model` over the whole (first) run, with the simulation's identification
    /// (for the report's regions and plots). A free decay's are in the time of its record as
    /// cut: [`super::GapRun`] moves them to the record's own ([`Release::at_s`] later).
    pub fn whole(&self, model: &RigModel) -> Result<super::Whole, GapError> {
        self.whole_of(0, model)
    }

    /// [`whole`](Self::whole) of run `i`.
    pub fn whole_of(&self, i: usize, model: &RigModel) -> Result<super::Whole, GapError> {
        let m = &self.runs[i];
        let s = m.simulate(model, self.identifier.backend)?;
        let gap = m.whole.gap(&m.identified, &s.features());
        Ok(super::Whole {
            gap,
            identified: s.identified,
        })
    }

    /// Simulations run so far.
    pub fn evaluations(&self) -> usize {
        self.evaluations.load(Ordering::Relaxed)
    }
}

/// Everything the diagnosis of one run found.
#[derive(Debug, Clone)]
pub struct Diagnosis {
    /// Run path.
    pub run: String,
    /// The model as given.
    pub nominal: RigModel,
    /// Its gaps.
    pub nominal_score: Score,
    /// The model with its own parameters refitted.
    pub baseline: Fitted,
    /// Candidates, best (largest held-out shrink, [`Candidate::shrink`]) first.
    pub candidates: Vec<Candidate>,
    /// Index of the verdict in `candidates`, `None` when nothing is significant.
    pub verdict: Option<usize>,
    /// Simulations run.
    pub evaluations: usize,
    /// Wall time (s).
    pub seconds: f64,
}

impl Diagnosis {
    /// The verdict's name, or `none`.
    pub fn verdict_name(&self) -> String {
        self.verdict
            .map_or_else(|| "none".into(), |i| self.candidates[i].name())
    }

    /// The model to carry on with: the verdict's, or the baseline when there is none.
    pub fn fitted_model(&self) -> &RigModel {
        self.verdict
            .map_or(&self.baseline.model, |i| &self.candidates[i].model)
    }
}

/// Whether `c` explains significantly more than `reference`, the score of the model it
/// extends: better on the blocks it was fitted on (a scan point that fits worse but happens
/// to score well on the withheld blocks is luck), and by the margins on the withheld ones.
fn significant(reference: &Score, c: &Candidate) -> bool {
    let kinds = c.kinds();
    c.score.fit_on(&kinds) < reference.fit_on(&kinds) && c.score.clears_margins(reference, &kinds)
}

/// Best first: the largest shrink of the held-out gap, each on the domains its effects act
/// in (with every domain scored for every effect, the smallest held-out gap first); ties,
/// and the models with no finite shrink, by held-out gap.
fn best_first(candidates: &mut [Candidate]) {
    candidates.sort_by(|a, b| {
        b.shrink
            .total_cmp(&a.shrink)
            .then(a.score.holdout.total_cmp(&b.score.holdout))
    });
}

/// Diagnoses one measured run against the `nominal` model: baseline, candidates, verdict.
pub fn diagnose(
    reference: &Reference,
    nominal: &RigModel,
    opt: &SearchOptions,
) -> Result<Diagnosis, GapError> {
    let t0 = Instant::now();
    let nominal_score = reference.score(nominal);
    let baseline = refit_baseline(reference, nominal, opt);
    if !baseline.score.fit.is_finite() {
        return Err(GapError::Simulated(
            "neither the nominal model nor any refit of it gives a response that can be \
             identified: check the model's units against the run's"
                .into(),
        ));
    }
    let base = baseline.score;
    let starts = scan(reference, nominal, &nominal_score, &baseline, opt);
    let mut candidates = singles(reference, starts, opt, &base);
    if let Some(q) = quantization(reference, nominal, &nominal_score, &baseline, opt, &base) {
        candidates.push(q);
    }
    best_first(&mut candidates);
    borderline(reference, &mut candidates, opt, &base);
    if pairs(reference, &mut candidates, opt, &base) && joint::applies(nominal, opt) {
        if let Some(pair) = joint::second_start(reference, &baseline, opt, &base) {
            reduce(
                reference,
                &mut candidates,
                std::slice::from_ref(&pair),
                &base,
            );
            joint::put(&mut candidates, pair);
            best_first(&mut candidates);
        }
    }
    let verdict = verdict(&baseline, &candidates);
    Ok(Diagnosis {
        run: reference.run().meta.path.clone(),
        nominal: nominal.clone(),
        nominal_score,
        baseline,
        candidates,
        verdict,
        evaluations: reference.evaluations(),
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// The scan: the best point of each effect's coarse grid on each side (the baseline, and
/// the nominal model where it differs and can be identified), and a joint's start read
/// off the skeleton as a side of its own ([`iwan`]).
fn scan(
    reference: &Reference,
    nominal: &RigModel,
    nominal_score: &Score,
    baseline: &Fitted,
    opt: &SearchOptions,
) -> Vec<(Side, EffectKind, f64, Fitted)> {
    let id = reference.identified();
    let fitted = &reference.fitted_identifications();
    // Scan: each effect alone over a coarse grid of its parameter, added to the baseline and
    // to the nominal model. The baseline may have absorbed part of the missing effect by
    // bending its own parameters (dry friction or contact damping into more viscous
    // damping, hardening into a stiffer contact), and then the effect added to it fits
    // worse than the truth would: the nominal model, a few percent off but unbent, starts
    // the effect in the truth's basin.
    let grid: Vec<(Side, RigModel, EffectKind, f64)> = opt
        .effects
        .iter()
        .filter(|&&k| k != EffectKind::Quantization)
        .flat_map(|&k| {
            let mut bases = vec![(Side::Baseline, baseline.model.clone())];
            if nominal_score.fit.is_finite() && nominal != &baseline.model {
                bases.push((Side::Nominal, nominal.clone()));
            }
            // A preload and an offset can lean either way: both signs are scanned.
            // So can a joint's cubic term without clearance (a softening bolted joint).
            let signs: &[f64] = match k {
                EffectKind::GravityPreload | EffectKind::AsymmetricClearance => &[1.0, -1.0],
                EffectKind::CubicStiffness if nominal.clearance <= 0.0 => &[1.0, -1.0],
                _ => &[1.0],
            };
            bases.into_iter().flat_map(move |(side, b)| {
                let s = start_for(k, &b, fitted, opt.waveform);
                let b = ready_for(&b, fitted, k, opt.waveform);
                signs
                    .iter()
                    .flat_map(move |sign| SCAN.iter().map(move |f| sign * f))
                    .map(move |f| (side, b.clone(), k, s * f))
            })
        })
        .collect();
    // Contact damping is also scanned on the baseline with its viscous damping lowered by
    // what the contact damping dissipates at resonance: the baseline has put it into c, and
    // added on top it only over-damps (on random rigs the simplex then stopped with a fit
    // worse than the baseline's, three times in five).
    let share = contact_share(id);
    let mut grid: Vec<(Side, RigModel, EffectKind, f64)> = grid
        .into_iter()
        .flat_map(|(side, b, k, v)| {
            let traded = (side == Side::Baseline && k == EffectKind::ContactDamping && share > 0.0)
                .then(|| {
                    let mut t = b.clone();
                    t.damping = (b.damping - v * share).max(0.2 * b.damping);
                    (side, t, k, v)
                });
            std::iter::once((side, b, k, v)).chain(traded)
        })
        .collect();
    // A joint is also started where the skeleton puts it, on the baseline with what the
    // joint's describing function takes over from its stiffness and damping ([`iwan`]): a
    // side of its own, so that the simplex refines it beside the ordinary start.
    // Not where the refit already has a joint: the skeleton's joint would be counted on
    // top of it.
    if opt.effects.contains(&EffectKind::Microslip)
        && nominal.kind != ModelKind::BaseMotion
        && nominal.clearance <= 0.0
        && baseline.model.effects.microslip.is_none()
    {
        if let Some(m) = iwan::start(&baseline.model, &reference.fitted_skeletons()) {
            let v = m
                .effects
                .get(EffectKind::Microslip)
                .expect("set by the start");
            grid.push((Side::Skeleton, m, EffectKind::Microslip, v));
        }
    }
    let scanned: Vec<(Side, EffectKind, f64, Fitted)> = grid
        .par_iter()
        .map(|(side, b, k, v)| {
            let (k, v) = (*k, *v);
            let mut model = b.clone();
            model.set_effect(k, Some(v));
            let score = reference.score(&model);
            (*side, k, v, Fitted { model, score })
        })
        .collect();
    // The best scan point of each effect on each side.
    let mut starts: Vec<(Side, EffectKind, f64, Fitted)> = Vec::new();
    for (side, k, v, f) in scanned {
        if !f.score.fit.is_finite() {
            continue;
        }
        match starts.iter_mut().find(|b| b.0 == side && b.1 == k) {
            Some(b) if f.score.fit < b.3.score.fit => *b = (side, k, v, f),
            Some(_) => {}
            None => starts.push((side, k, v, f)),
        }
    }
    starts
}

/// The share of a resonant cycle's viscous dissipation that falls in contact, on the
/// measurement's resonant samples (0 without a clearance): for z = A sin ωt, contact where
/// |z| > δ, the share of ∫ż² there is 1 − (2θ₀ + sin 2θ₀)/π with θ₀ = asin(δ/A). Contact
/// damping c_c dissipates at resonance what a viscous c_c × share would.
fn contact_share(id: &Identification) -> f64 {
    let Some(dz) = id.dead_zone else {
        return 0.0;
    };
    let delta = dz.half_gap.value;
    let track = &id.response;
    let n = id.used.len().min(track.len());
    let shares: Vec<f64> = (0..n)
        .filter(|&i| track.valid[i] && id.resonant(i))
        .map(|i| contact_share_at(delta, track.amplitude[i]))
        .collect();
    if shares.is_empty() {
        0.0
    } else {
        shares.iter().sum::<f64>() / shares.len() as f64
    }
}

/// The share of ∫ż² over a cycle of z = A sin ωt spent where |z| > `delta`.
fn contact_share_at(delta: f64, a: f64) -> f64 {
    if a <= delta || delta <= 0.0 {
        return 0.0;
    }
    let t0 = (delta / a).asin();
    1.0 - (2.0 * t0 + (2.0 * t0).sin()) / std::f64::consts::PI
}

/// The single effects: the best scan starts refined by the simplex with the model's own
/// parameters, the better fit of each effect kept, and the two best refined once more.
fn singles(
    reference: &Reference,
    mut starts: Vec<(Side, EffectKind, f64, Fitted)>,
    opt: &SearchOptions,
    base: &Score,
) -> Vec<Candidate> {
    // The best starts are refined by the simplex together with the model's own parameters;
    // each effect keeps its better fit.
    starts.sort_by(|a, b| a.3.score.fit.total_cmp(&b.3.score.fit));
    let refine = opt.refine.min(starts.len());
    let fits: Vec<Candidate> = starts
        .into_par_iter()
        .enumerate()
        .map(|(i, (_, k, v, scanned))| {
            let scanned = Candidate::from_fit(scanned, &[k], base, false);
            if i < refine {
                let refined = refit(reference, &scanned.model, &[(k, v)], opt, base);
                fitter(refined, scanned)
            } else {
                scanned
            }
        })
        .collect();
    let mut candidates: Vec<Candidate> = Vec::new();
    for c in fits {
        match candidates
            .iter_mut()
            .find(|b| b.effects[0].0 == c.effects[0].0)
        {
            Some(b) if c.score.fit < b.score.fit || (c.refined && !b.refined) => *b = c,
            Some(_) => {}
            None => candidates.push(c),
        }
    }
    // The two best on the fitting blocks get a second simplex from where the first stopped
    // (as the baseline does): a fit that has to unbend the baseline's own parameters on
    // the way is often cut short by the first budget.
    candidates.sort_by(|a, b| a.score.fit.total_cmp(&b.score.fit));
    let again: Vec<Candidate> = candidates
        .par_iter()
        .take(2)
        .map(|c| fitter(refit(reference, &c.model, &c.effects, opt, base), c.clone()))
        .collect();
    for (i, c) in again.into_iter().enumerate() {
        candidates[i] = c;
    }
    candidates
}

/// The quantisation candidate, when the vocabulary has it.
fn quantization(
    reference: &Reference,
    nominal: &RigModel,
    nominal_score: &Score,
    baseline: &Fitted,
    opt: &SearchOptions,
    base: &Score,
) -> Option<Candidate> {
    let id = reference.identified();
    // Quantisation is a property of the sensor, not of the dynamics: its step is read off
    // the lattice the samples lie on, and the candidate starts as the baseline with that
    // step (refitted below where the lattice is new to the model). Searched like the
    // others, it only cost simulations: the simulation does not change with it (see
    // [`super::simulate_given`]). Without a lattice in the data it is scored at its
    // starting value, to show it does not help.
    if !opt.effects.contains(&EffectKind::Quantization) {
        return None;
    }
    let kind = EffectKind::Quantization;
    let step = if reference.resolution() > 0.0 {
        reference.resolution() / resolution_per_step(reference.run())
    } else {
        effect_start(kind, &baseline.model, id)
    };
    let known = baseline.model.effects.get(kind);
    let model = with_step(&baseline.model, step);
    let score = reference.score(&model);
    let scored = Candidate::from_fit(Fitted { model, score }, &[kind], base, false);
    // A lattice the model does not know (no step, or one 10 % off): the baseline has bent
    // its own parameters to mimic the coarse encoder's noise floor at small amplitude, so
    // they are refitted with the step held (a 14-bit/rev case scored once shrank the gap by
    // 15 %, the truth by 71 %). Not marked refined: the step is read, not searched, and
    // stays out of the pairs.
    let new = reference.resolution() > 0.0 && known.is_none_or(|q| (step / q - 1.0).abs() > 0.1);
    if !new {
        return Some(scored);
    }
    // The starts: the baseline, and the nominal model as the scan starts the other effects
    // (the baseline's parameters stay bent under the step held: force self-check,
    // time-domain shrink 20–40 % from the baseline where the truth's was 96–99 %).
    let mut starts = vec![baseline.model.clone()];
    if nominal_score.fit.is_finite() && nominal != &baseline.model {
        starts.push(nominal.clone());
    }
    if scored.score.scores_time_alone(&[kind]) {
        // A step whose floor hardly moves the fitting runs' time domain on the baseline has
        // nothing to explain there, and its fits only cost simulations: the F-16's
        // 24-bit converter (1.2e-5 m/s²) changed it by 2e-9, and the four fits took 180
        // simulations, two minutes of that diagnosis, for a shrink of 0.
        let moves = scored.score.fit_on(&[kind]) < (1.0 - STEP_MOVES) * base.fit_on(&[kind]);
        if !moves {
            return Some(scored);
        }
        return Some(fitted_on_time(reference, opt, &starts, step, base, scored));
    }
    let mut better = scored;
    for start in &starts {
        let refitted = refit_own(reference, opt, &with_step(start, step), false);
        let c = Candidate::from_fit(refitted, &[kind], base, false);
        better = fitter(c, better);
    }
    better.refined = false;
    Some(better)
}

/// A force or free model's converter step, which is scored on the time domain alone
/// ([`EffectKind::acts_on_time_alone`]): fitted there, and weighed against the model
/// refitted there without it from the same `starts` with the same budget. Fitted on the
/// whole gap, whose fitting blocks are mostly the damping domain's noise on a force
/// sweep, the step's candidate fitted those blocks better than the truth did and kept
/// 60–80 % of the baseline's time-domain gap (force self-check cases 3, 33, 39); a model
/// refitted on the time domain alone but without the step would shrink it too, so the
/// shrink and the verdict's margins are taken against that model (`against`), not the
/// baseline.
fn fitted_on_time(
    reference: &Reference,
    opt: &SearchOptions,
    starts: &[RigModel],
    step: f64,
    base: &Score,
    scored: Candidate,
) -> Candidate {
    let kind = [EffectKind::Quantization];
    let on_time = |f: &Fitted| f.score.fit_on(&kind);
    let best = |fits: Vec<Fitted>| {
        fits.into_iter()
            .min_by(|a, b| on_time(a).total_cmp(&on_time(b)))
            .expect("the baseline is always a start")
    };
    let (without, with): (Vec<Fitted>, Vec<Fitted>) = starts
        .par_iter()
        .map(|s| {
            let with = with_step(s, step);
            (
                refit_own(reference, opt, s, true),
                refit_own(reference, opt, &with, true),
            )
        })
        .unzip();
    let (without, with) = (best(without), best(with));
    // The step alone on the baseline (scored already) may still be the best on time.
    let with = if on_time(&with) <= scored.score.fit_on(&kind) {
        with
    } else {
        Fitted {
            model: scored.model,
            score: scored.score,
        }
    };
    // Against the better of the time-fitted model without the step and the baseline.
    if on_time(&without) >= base.fit_on(&kind) {
        return Candidate::from_fit(with, &kind, base, false);
    }
    let mut c = Candidate::from_fit(with, &kind, &without.score, false);
    c.against = Some(without);
    c
}

/// `start`'s own parameters refitted (no effect searched), on the whole fit gap or on its
/// time domain alone.
fn refit_own(
    reference: &Reference,
    opt: &SearchOptions,
    start: &RigModel,
    time_alone: bool,
) -> Fitted {
    let coords = Coordinates {
        base: start,
        inertia: opt.fit_inertia,
        effects: Vec::new(),
        time_alone,
    };
    coords.fit(reference, coords.origin(), opt.candidate_evaluations)
}

/// `model` with the converter step `step`.
fn with_step(model: &RigModel, step: f64) -> RigModel {
    let mut m = model.clone();
    m.effects.set(EffectKind::Quantization, Some(step));
    m
}

/// Work spent once more on the best single effect when it falls just short of the rule
/// (held-out shrink from [`BORDERLINE`] up to [`MIN_SHRINK`]): a second simplex from where
/// it stopped. A hardening the true model separates with a 99 % shrink stopped at 49 % on a
/// random rig: the fit had to unbend the baseline's stiffer, wider contact on the way.
fn borderline(
    reference: &Reference,
    candidates: &mut [Candidate],
    opt: &SearchOptions,
    base: &Score,
) {
    let Some(c) = candidates.first() else {
        return;
    };
    if !c.refined || !(BORDERLINE..MIN_SHRINK).contains(&c.shrink) {
        return;
    }
    let again = refit(reference, &c.model, &c.effects, opt, base);
    candidates[0] = fitter(again, c.clone());
    best_first(candidates);
}

/// The pairs of effects, added to `candidates` (best first) when the best single
/// effect leaves much of the gap; whether they were.
fn pairs(
    reference: &Reference,
    candidates: &mut Vec<Candidate>,
    opt: &SearchOptions,
    base: &Score,
) -> bool {
    // Pairs, when the best single effect leaves much of the gap: from the better single's
    // model, the other effect at its own fitted value.
    let leaves_much = candidates
        .first()
        .is_some_and(|s| 1.0 - s.shrink > PAIR_WHEN_LEFT);
    if opt.pairs && leaves_much && base.holdout > MIN_DROP {
        let singles: Vec<&Candidate> = candidates.iter().filter(|c| c.refined).take(3).collect();
        let mut pairs = Vec::new();
        for (i, a) in singles.iter().enumerate() {
            for b in &singles[i + 1..] {
                pairs.push(if a.score.fit <= b.score.fit {
                    (*a, *b)
                } else {
                    (*b, *a)
                });
            }
        }
        let fitted: Vec<Candidate> = pairs
            .par_iter()
            .map(|(a, b)| {
                let effects = [a.effects[0], b.effects[0]];
                refit(reference, &a.model, &effects, opt, base)
            })
            .collect();
        reduce(reference, candidates, &fitted, base);
        candidates.extend(fitted);
        best_first(candidates);
        return true;
    }
    false
}

/// Each pair of `fitted` without one of its effects, put in place of that single effect's
/// candidate where it fits the fitting blocks better: the pair's simplex also moved the
/// model's own parameters further (or started them in another basin), and that gain
/// belongs to the single effect, not to the second one (a hardening contact once came out
/// as cubic_stiffness+quantization).
fn reduce(reference: &Reference, candidates: &mut [Candidate], fitted: &[Candidate], base: &Score) {
    let reduced: Vec<Candidate> = fitted
        .par_iter()
        .flat_map(|p| {
            (0..2).into_par_iter().map(move |without| {
                let (kind, _) = p.effects[without];
                let mut model = p.model.clone();
                model.effects.set(kind, None);
                let score = reference.score(&model);
                let keep = p.effects[1 - without].0;
                Candidate::from_fit(Fitted { model, score }, &[keep], base, true)
            })
        })
        .collect();
    for r in reduced {
        if let Some(c) = candidates
            .iter_mut()
            .find(|c| c.effects.len() == 1 && c.effects[0].0 == r.effects[0].0)
        {
            if r.score.fit < c.score.fit {
                *c = r;
            }
        }
    }
}

/// The verdict, an index into `candidates`: the best single effect if significant against
/// the baseline; a pair only if it is significant against the best single effect too.
fn verdict(baseline: &Fitted, candidates: &[Candidate]) -> Option<usize> {
    let single = candidates.iter().position(|c| c.effects.len() == 1);
    let mut verdict = single.filter(|&i| {
        let c = &candidates[i];
        significant(c.against.as_ref().map_or(&baseline.score, |f| &f.score), c)
    });
    if let Some(p) = candidates.iter().position(|c| c.effects.len() == 2) {
        let beats_single = single.is_none_or(|s| significant(&candidates[s].score, &candidates[p]));
        if significant(&baseline.score, &candidates[p]) && beats_single {
            verdict = Some(p);
        }
    }
    verdict
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_free_decay_is_released_one_band_pass_spread_after_its_impact() {
        use super::{impact, settled_after};
        use crate::mode::{Chosen, ModeBand};
        let mut run = crate::rig::plain_decay();
        // A hammer's hit, the record's largest sample, 5 s in.
        let hit = 2000;
        let largest = run.output.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
        run.output[hit] = -2.0 * largest;
        let band = ModeBand {
            fmin: 6.0,
            fmax: 9.0,
            peak: 7.3,
            chosen: Chosen::Given,
        };
        // 1/(6 Hz · (1 − 1/1.1)) = 1.833 s at 400 Hz: 734 samples.
        assert_eq!(impact(&run), hit);
        let fs = run.meta.sample_rate;
        assert_eq!(settled_after(hit, Some(band), fs), hit + 734);
        // Where the mode was not isolated, nothing spread the impact.
        assert_eq!(settled_after(hit, None, fs), 0);
    }

    #[test]
    fn a_decay_with_nothing_valid_past_the_spread_is_released_at_its_peak_with_a_warning() {
        use super::{release_point, Reference, Release};
        use crate::backend::Backend;
        use crate::gap::Blocks;
        use crate::identify::{Identifier, IdentifyOptions};
        let run = crate::rig::plain_decay();
        // The mode isolated on its band, as `--band 6 9` does: 1.833 s of spread.
        let options = IdentifyOptions {
            mode: crate::mode::ModeChoice::Band(6.0, 9.0),
            ..IdentifyOptions::default()
        };
        let backend = Backend::cpu();
        let identifier = Identifier {
            options: &options,
            backend: &backend,
        };
        let id = identifier
            .identify(&run, crate::track::Method::Wavelet)
            .unwrap();
        let n = id.response.len();
        let t = &id.response;
        let peak = (0..n)
            .filter(|&i| t.valid[i])
            .max_by(|&a, &b| t.amplitude[a].total_cmp(&t.amplitude[b]))
            .unwrap();
        // Past the record's end nothing is valid: released at the whole record's peak,
        // flagged; from its start, the same sample, unflagged.
        let (late, _, past_late) = release_point(&id, n + 10).unwrap();
        let (early, _, past_early) = release_point(&id, 0).unwrap();
        assert_eq!((late, past_late), (peak, false));
        assert_eq!((early, past_early), (peak, true));
        let flagged = Release {
            at_s: 0.5,
            hit_s: 0.25,
            spread_s: 1.8,
            past_spread: false,
        };
        let w = flagged
            .warning()
            .expect("a release inside the spread is warned of");
        assert!(w.contains("1.800 s after the hit at t = 0.250 s"), "{w}");
        assert!(w.contains("peak at t = 0.500 s"), "{w}");
        assert!(flagged
            .describe()
            .contains("not past the band-pass's 1.800 s spread"));
        let settled = Release {
            past_spread: true,
            ..flagged
        };
        assert_eq!(settled.warning(), None);
        assert!(settled
            .describe()
            .contains("past the band-pass's 1.800 s spread"));
        let unbanded = Release {
            spread_s: 0.0,
            ..settled
        };
        assert!(unbanded.describe().ends_with("from the hit at 0.250 s on"));
        // The reference keeps where it cut the record, in the record's own seconds: past
        // the hit (the record's largest sample) by at least the band-pass's spread.
        let reference = Reference::new(&run, Blocks { seconds: 1.0 }, identifier).unwrap();
        let rel = reference.release(0).expect("a free decay is released");
        println!("{rel:?}");
        let fs = run.meta.sample_rate;
        assert!(rel.past_spread, "{rel:?}");
        assert!(rel.at_s >= rel.hit_s + rel.spread_s - 1.0 / fs, "{rel:?}");
        assert!(
            (rel.spread_s - 1.0 / (6.0 * (1.0 - 1.0 / 1.1))).abs() < 1e-12,
            "{rel:?}"
        );
        assert_eq!(
            reference.run().output.len(),
            run.output.len() - (rel.at_s * fs).round() as usize
        );
    }

    #[test]
    fn blocks_that_leave_a_part_without_a_valid_sample_are_refused() {
        use super::Reference;
        use crate::backend::Backend;
        use crate::gap::Blocks;
        use crate::identify::{Identifier, IdentifyOptions};
        // A 12 s decay (11 s as compared from its release), valid over most of it.
        let run = crate::rig::plain_decay();
        let (options, backend) = (IdentifyOptions::default(), Backend::cpu());
        let identifier = Identifier {
            options: &options,
            backend: &backend,
        };
        for seconds in [1.0, 4.0] {
            assert!(Reference::new(&run, Blocks { seconds }, identifier).is_ok());
        }
        // One block longer than the record: nothing held out, whose gap had read 0.
        for seconds in [20.0, 1000.0] {
            let e = Reference::new(&run, Blocks { seconds }, identifier)
                .err()
                .expect("refused")
                .to_string();
            assert!(
                e.contains("leave no valid sample to score the gap on"),
                "{e}"
            );
            assert!(
                e.contains("or shorter blocks (skelid gap's --holdout-block)"),
                "{e}"
            );
        }
    }

    #[test]
    fn the_contact_share_of_a_sine_matches_its_integral() {
        use super::contact_share_at;
        // Against the integral itself, by the midpoint rule over one cycle.
        for ratio in [0.05, 0.3, 0.6, 0.9, 0.99] {
            let n = 200_000;
            let (mut all, mut touching) = (0.0, 0.0);
            for k in 0..n {
                let t = (k as f64 + 0.5) / n as f64 * std::f64::consts::TAU;
                let v2 = t.cos().powi(2);
                all += v2;
                if t.sin().abs() > ratio {
                    touching += v2;
                }
            }
            let share = contact_share_at(ratio, 1.0);
            assert!((share - touching / all).abs() < 1e-4, "{ratio}: {share}");
        }
        assert_eq!(contact_share_at(1.0, 1.0), 0.0);
        assert_eq!(contact_share_at(2.0, 1.0), 0.0);
        assert!((contact_share_at(1e-9, 1.0) - 1.0).abs() < 1e-8);
    }

    #[test]
    fn shrink_is_taken_on_the_domains_an_effect_acts_in_and_failures_rank_last() {
        use super::{best_first, Candidate, Score};
        use crate::model::{EffectKind, RigModel};
        let score = |holdout: f64, d: [Option<f64>; 4]| Score {
            fit: holdout,
            holdout,
            domains: d,
            fit_time: d[0],
            model_kind: crate::model::ModelKind::BaseMotion,
        };
        let rms = |d: &[f64]| (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt();
        let base = score(
            rms(&[0.02, 0.01, 0.01, 0.04]),
            [Some(0.02), Some(0.01), Some(0.01), Some(0.04)],
        );
        let q = [EffectKind::Quantization];
        let f = [EffectKind::CoulombFriction];
        // Quantization leaves the waveform out; every other effect, and none, keep it.
        assert!((base.holdout_on(&q) - rms(&[0.02, 0.01, 0.01])).abs() < 1e-15);
        assert_eq!(base.holdout_on(&f), base.holdout);
        assert_eq!(base.holdout_on(&[]), base.holdout);
        let three = score(0.02, [Some(0.02), Some(0.01), Some(0.01), None]);
        assert_eq!(three.holdout_on(&q), three.holdout);
        // A quantization candidate that halves the time domain and leaves the waveform as
        // it was: its gain is read on the three domains it can change.
        let cand = score(0.0, [Some(0.005), Some(0.01), Some(0.01), Some(0.04)]);
        let s = cand.shrink_against(&base, &q);
        assert!((s - (1.0 - rms(&[0.005, 0.01, 0.01]) / rms(&[0.02, 0.01, 0.01]))).abs() < 1e-12);
        // In a force model the converter's step acts on the time domain alone: its shrink
        // is that domain's, and it leaves the other effects' as they were.
        let force = |s: Score| Score {
            model_kind: crate::model::ModelKind::Force,
            ..s
        };
        let (fbase, fcand) = (force(base), force(cand));
        assert!(fbase.scores_time_alone(&q) && !fbase.scores_time_alone(&f));
        assert!(!base.scores_time_alone(&q));
        assert_eq!(fbase.holdout_on(&q), 0.02);
        assert!((fcand.shrink_against(&fbase, &q) - 0.75).abs() < 1e-12);
        // And it is fitted there: its fit gap is the fitting blocks' time domain.
        assert_eq!(fbase.fit_on(&q), fbase.fit_time.unwrap());
        assert_eq!(fbase.fit_on(&f), fbase.fit);
        assert_eq!(base.fit_on(&q), base.fit);
        assert_eq!(fbase.holdout_on(&f), fbase.holdout);
        assert!(!force(score(0.02, [None; 4])).scores_time_alone(&q));
        // A pair with an effect of the joint is read like the joint's.
        let qf = [EffectKind::Quantization, EffectKind::CoulombFriction];
        assert_eq!(fbase.holdout_on(&qf), fbase.holdout);
        // No finite gap, or a baseline of zero: −∞, never NaN.
        let failed = Score::FAILED;
        assert_eq!(failed.shrink_against(&base, &f), f64::NEG_INFINITY);
        let zero = score(0.0, [None; 4]);
        assert_eq!(zero.shrink_against(&zero, &f), f64::NEG_INFINITY);
        // Best first by shrink; failures last whatever their sign.
        let m = RigModel::paper();
        let c = |shrink: f64, holdout: f64| Candidate {
            effects: vec![(EffectKind::CoulombFriction, 1.0)],
            model: m.clone(),
            score: score(holdout, [None; 4]),
            shrink,
            refined: true,
            against: None,
        };
        let mut v = vec![
            c(f64::NEG_INFINITY, f64::INFINITY),
            c(0.2, 0.8),
            c(0.9, 0.1),
            c(0.2, 0.7),
        ];
        best_first(&mut v);
        let order: Vec<(f64, f64)> = v.iter().map(|c| (c.shrink, c.score.holdout)).collect();
        assert_eq!(
            order,
            vec![
                (0.9, 0.1),
                (0.2, 0.7),
                (0.2, 0.8),
                (f64::NEG_INFINITY, f64::INFINITY)
            ]
        );
    }

    use super::fit::{cubic_describing, Coordinates};
    use super::*;

    #[test]
    fn a_refit_keeps_the_gravity_stiffness_sign_of_the_nominal_model() {
        // A refit once gave -91.9 1/s² to a rig whose nominal gravity stiffness was 0.
        for nominal in [0.0, 2.0, -2.0] {
            let base = RigModel {
                gravity_stiffness: nominal,
                ..RigModel::paper()
            };
            let coords = Coordinates {
                base: &base,
                inertia: false,
                effects: Vec::new(),
                time_alone: false,
            };
            for step in [-1e3, -50.0, -1.0, 0.0, 1.0, 50.0, 1e3] {
                let c = coords.model(&[0.0, 0.0, 0.0, step]).gravity_stiffness;
                if nominal < 0.0 {
                    assert!(c <= 0.0, "nominal {nominal}, step {step}: {c}");
                } else {
                    assert!(c >= 0.0, "nominal {nominal}, step {step}: {c}");
                }
            }
            // The nominal model itself is where the simplex starts.
            let c0 = coords.model(&[0.0; 4]).gravity_stiffness;
            assert_eq!(c0, nominal);
        }
    }

    #[test]
    fn the_cubic_describing_function_matches_its_closed_forms() {
        // Without a gap, x³ at amplitude A has the first-harmonic stiffness 3A²/4.
        let a = 0.03;
        let c = cubic_describing(0.0, a);
        assert!((c / (0.75 * a * a) - 1.0).abs() < 1e-4, "{c}");
        // Past a gap it grows from 0 at the flank, and stays below the gapless value.
        assert_eq!(cubic_describing(0.01, 0.009), 0.0);
        let (lo, hi) = (cubic_describing(0.01, 0.012), cubic_describing(0.01, 0.03));
        assert!(lo > 0.0 && lo < hi && hi < 0.75 * a * a);
    }

    #[test]
    fn nelder_mead_finds_the_minimum_of_a_rosenbrock_valley() {
        let mut f = |x: &[f64]| (1.0 - x[0]).powi(2) + 100.0 * (x[1] - x[0] * x[0]).powi(2);
        let simplex = vec![vec![-1.2, 1.0], vec![-1.0, 1.0], vec![-1.2, 1.2]];
        let (x, v) = nelder_mead(&mut f, simplex, 2000, 1e-14);
        assert!(
            (x[0] - 1.0).abs() < 1e-3 && (x[1] - 1.0).abs() < 2e-3,
            "{x:?} {v}"
        );
    }
}
