//! `skelid gap --self-check`: how often the diagnosis names the right effect. Each case is
//! a paper-like rig simulated with one effect of the vocabulary (or none) that the model
//! handed to the diagnosis lacks, with encoder noise and a few percent of error in the
//! model's own parameters; the diagnosis runs blind and its verdict is scored.

use std::collections::BTreeMap;
use std::fmt;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

use super::search::{diagnose, Diagnosis, Reference, Score, SearchOptions};
use super::GapError;
use crate::identify::Identifier;
use crate::model::{EffectKind, RigModel};
use crate::rig::{
    effect_value, encoder_step, level_sweep_at, measure, measure_over, paper_chirp_at, random_rig,
    structure_effect_value, structure_mode, structure_run, two_level_chirp_at, Chain,
    ENCODER_NOISE, PAPER_LEVEL, SECOND_LEVEL, STRUCTURE_LEVELS,
};

/// The accelerometer noise of a [`Rigs::Structure`] case, as a share of its RMS.
pub const STRUCTURE_NOISE: f64 = 0.01;
use crate::simulate::{Drive, Excitation};

/// The parameter of a case's effect is the demo's value times a factor drawn log-uniformly
/// from [1/RANGE, RANGE].
pub const RANGE: f64 = 2.0;
/// Standard deviation of the relative error put into each of the model's stiffness, damping
/// and clearance (clipped at twice this).
pub const NOMINAL_ERROR: f64 = 0.03;

/// One self-check case: the truth, how it is measured, and the model the diagnosis is
/// given.
#[derive(Debug, Clone)]
pub struct Case {
    /// Case number.
    pub index: usize,
    /// The effect in the data, `None` for an effect-free case.
    pub effect: Option<EffectKind>,
    /// Its parameter.
    pub value: f64,
    /// The rig that made the data.
    pub truth: RigModel,
    /// The model the diagnosis starts from (no effect, parameters a few percent off).
    pub nominal: RigModel,
    /// First level of the sweep (rad of base angle; the paper's is 0.04).
    pub level: f64,
    /// Noise, offsets and the `gravity_stiffness` attribute of the measurement.
    pub chain: Chain,
    /// Noise seed of the simulation.
    pub seed: u64,
    /// The rigs it was drawn from.
    pub rigs: Rigs,
}

/// The rigs the self-check draws.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Rigs {
    /// The paper's rig, its chirp's level, encoder noise of 2e-5 rad.
    #[default]
    Paper,
    /// Random paper-like rigs over issue 20's ranges ([`random_rig`]): joint, level,
    /// 17–20 bit/rev encoders with DC offsets and sub-step noise, a perturbed
    /// `gravity_stiffness`. Their `quantization` case is a coarse encoder of 12–14 bit/rev
    /// whose steps carry acquisition noise of 1/60–1/15 of a step.
    Random,
    /// One mode of a structure like the F-16's wing torsion ([`structure_mode`]: 7.3 Hz,
    /// 0.5 % of critical, 1 kg of modal mass) under a model of `kind = "force"`, swept down
    /// by a force at the four [`STRUCTURE_LEVELS`], measured by an accelerometer with 1 %
    /// noise; levels 1 and 3 are fitted together, 2 and 4 held out. The classes are the
    /// force vocabulary's effects a mode without clearance can hide ([`STRUCTURE_CLASSES`]).
    Structure,
}

/// The classes of a [`Rigs::Structure`] self-check, in turn: the effects of a force model
/// without clearance (contact damping needs a contact), and none.
pub const STRUCTURE_CLASSES: [Option<EffectKind>; 6] = [
    Some(EffectKind::CoulombFriction),
    Some(EffectKind::CubicStiffness),
    Some(EffectKind::SensorDelay),
    Some(EffectKind::Quantization),
    Some(EffectKind::Microslip),
    None,
];

impl Rigs {
    /// Its name on the command line and in self-check.json.
    pub fn name(self) -> &'static str {
        match self {
            Rigs::Paper => "paper",
            Rigs::Random => "random",
            Rigs::Structure => "structure",
        }
    }

    /// What it is, in words.
    pub fn describe(self) -> &'static str {
        match self {
            Rigs::Paper => "paper's rig",
            Rigs::Random => {
                "random paper-like rigs (17-20 bit/rev encoders, DC offsets, a gravity attribute ±10 % off)"
            }
            Rigs::Structure => {
                "one 7.3 Hz mode of a structure swept by a force at four levels (1 and 3 fitted together, 2 and 4 held out), an accelerometer"
            }
        }
    }
}

/// What the cases hold: every class in turn, or one effect at a fixed size (a rung of the
/// detection-limit ladder).
#[derive(Debug, Clone, Copy, Default)]
pub struct Draw {
    /// The rigs.
    pub rigs: Rigs,
    /// Only this effect, at `factor` times its demo value ([`effect_value`]); every class
    /// in turn at a factor log-uniform in [1/RANGE, RANGE] when `None`.
    pub only: Option<(EffectKind, f64)>,
}

/// `n` cases from `seed`: the eight classes (seven effects and none) in turn, so that any
/// eight consecutive cases hold one of each, on the paper's rig.
pub fn cases(n: usize, seed: u64) -> Vec<Case> {
    draw(n, seed, Draw::default())
}

/// `n` cases from `seed` as `d` says.
pub fn draw(n: usize, seed: u64, d: Draw) -> Vec<Case> {
    let mut rng = StdRng::seed_from_u64(seed);
    let normal = Normal::new(0.0, NOMINAL_ERROR).expect("a positive deviation");
    (0..n)
        .map(|index| {
            let (mut truth, level, mut chain) = match d.rigs {
                Rigs::Paper => {
                    let m = RigModel::paper();
                    let chain = Chain::encoders(ENCODER_NOISE, m.gravity_stiffness);
                    (m, PAPER_LEVEL, chain)
                }
                Rigs::Random => {
                    let (r, ()) = random_rig(&mut rng, |_| ());
                    (r.model, r.amplitude, r.chain)
                }
                Rigs::Structure => {
                    // The accelerometer's noise, its share of the RMS.
                    let chain = Chain::encoders(STRUCTURE_NOISE, 0.0);
                    (structure_mode(), STRUCTURE_LEVELS[0], chain)
                }
            };
            let (effect, factor) = match d.only {
                Some((k, f)) => (Some(k), f),
                None => (
                    match d.rigs {
                        Rigs::Structure => STRUCTURE_CLASSES[index % STRUCTURE_CLASSES.len()],
                        _ => EffectKind::ALL.get(index % 8).copied(),
                    },
                    (rng.random_range(-1.0..1.0) * RANGE.ln()).exp(),
                ),
            };
            // The bench's own encoders (a random rig's 17–20 bit/rev), known to its model.
            let known_encoder = truth.effects.get(EffectKind::Quantization);
            let mut value = effect.map_or(0.0, |k| match d.rigs {
                // A structure's cubic term softens in one round of the classes and hardens
                // in the next: a bolted joint may do either.
                Rigs::Structure => {
                    let v = structure_effect_value(k).unwrap_or(0.0) * factor;
                    let round = index / STRUCTURE_CLASSES.len();
                    if k == EffectKind::CubicStiffness && round % 2 == 1 {
                        -v
                    } else {
                        v
                    }
                }
                _ => effect_value(k) * factor,
            });
            if d.rigs == Rigs::Random && effect == Some(EffectKind::Quantization) {
                // A coarse encoder in place of the fine one, blurred by the acquisition
                // chain after it (the lattice detector's hard case).
                if d.only.is_none() {
                    value = encoder_step(rng.random_range(12..=14u32));
                }
                chain.acquisition_noise = value / rng.random_range(15.0..60.0);
            }
            if let Some(k) = effect {
                truth.set_effect(k, Some(value));
            }
            let mut err = || {
                let e: f64 = normal.sample(&mut rng);
                1.0 + e.clamp(-2.0 * NOMINAL_ERROR, 2.0 * NOMINAL_ERROR)
            };
            let mut nominal = truth.clone();
            nominal.effects = Default::default();
            nominal.effects.set(EffectKind::Quantization, known_encoder);
            nominal.gravity_stiffness = chain.gravity_attribute;
            nominal.stiffness *= err();
            nominal.damping *= err();
            nominal.clearance *= err();
            if d.rigs == Rigs::Structure {
                // A finite-element model's modal mass is no better known than its stiffness.
                nominal.inertia *= err();
            }
            Case {
                index,
                effect,
                value,
                truth,
                nominal,
                level,
                chain,
                seed: rng.random(),
                rigs: d.rigs,
            }
        })
        .collect()
}

/// What the diagnosis made of one case.
#[derive(Debug, Clone)]
pub struct Outcome {
    /// The case.
    pub case: Case,
    /// The verdict (`none`, an effect, or `a+b`).
    pub verdict: String,
    /// Held-out shrink of the verdict (None when `none`).
    pub shrink: Option<f64>,
    /// |fitted| / |true| − 1 of the effect's parameter when the verdict is right (signs
    /// of a preload or an offset mirror each other's response and are not identified).
    pub param_error: Option<f64>,
    /// The true model's gaps, scored like the candidates.
    pub truth_score: Score,
    /// The diagnosis.
    pub diagnosis: Diagnosis,
}

impl Outcome {
    /// The true class's name.
    pub fn truth(&self) -> &'static str {
        self.case.effect.map_or("none", EffectKind::name)
    }
    /// Whether the verdict names the true effect (or `none` for an effect-free case).
    pub fn right(&self) -> bool {
        self.verdict == self.truth()
    }

    /// The true model's held-out shrink against the refitted baseline, on the domains its
    /// effect acts in.
    pub fn truth_shrink(&self) -> f64 {
        let kinds: Vec<EffectKind> = self.case.effect.into_iter().collect();
        self.truth_score
            .shrink_against(&self.diagnosis.baseline.score, &kinds)
    }

    /// Whether the record separates the hidden effect from the refitted baseline at all:
    /// the true model itself clears the verdict's held-out margins against it (shrink ≥
    /// [`MIN_SHRINK`](super::search::MIN_SHRINK), drop ≥
    /// [`MIN_DROP`](super::search::MIN_DROP); the rule's other half, a better fit on the
    /// fitting blocks, is not asked of a model nobody fitted). Where it does not, no search
    /// could name the effect under the rule: the record does not carry it.
    pub fn separable(&self) -> bool {
        let kinds: Vec<EffectKind> = self.case.effect.into_iter().collect();
        self.case.effect.is_some()
            && self
                .truth_score
                .clears_margins(&self.diagnosis.baseline.score, &kinds)
    }
}

/// The format name of self-check.json (FORMATS.md).
pub const FORMAT: &str = "skelid-gap-self-check/1";

/// One case's entry in self-check.json.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CaseRecord {
    /// Case number.
    pub case: usize,
    /// The true class (`none` or an effect).
    pub effect: &'static str,
    /// The effect's true parameter (0 for `none`).
    pub value: f64,
    /// The verdict.
    pub verdict: String,
    /// Whether the verdict names the true class.
    pub right: bool,
    /// Held-out shrink of the verdict.
    pub shrink: Option<f64>,
    /// |fitted| / |true| − 1 of the effect's parameter when the verdict is right.
    pub param_error: Option<f64>,
    /// Held-out gap of the refitted baseline.
    pub baseline_gap: f64,
    /// Wall time of the diagnosis (s).
    pub seconds: f64,
    /// Simulations it took.
    pub simulations: usize,
    /// First level of the sweep (rad).
    pub level: f64,
    /// DC offsets of the input and output channels (rad; an offset between them reads as
    /// an offset clearance).
    pub offsets: [f64; 2],
    /// Held-out gap of the true model.
    pub truth_gap: f64,
    /// The true model's held-out shrink against the baseline.
    pub truth_shrink: f64,
    /// Whether the true model itself clears the verdict's held-out margins against the
    /// baseline ([`Outcome::separable`]).
    pub separable: bool,
    /// The true model's gaps on the fitting and the held-out blocks, and the held-out
    /// domains.
    pub truth: ScoreRecord,
    /// The refitted baseline's.
    pub baseline: ScoreRecord,
    /// Every candidate tried, best first: what the search saw.
    pub candidates: Vec<CandidateRecord>,
}

/// A model's gaps in self-check.json.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ScoreRecord {
    /// Gap on the fitting blocks.
    pub gap_fit: f64,
    /// Gap on the held-out blocks.
    pub gap_holdout: f64,
    /// The held-out gap's domains: time, backbone, damping, waveform (null where not
    /// scored).
    pub domains: [Option<f64>; 4],
}

impl From<&Score> for ScoreRecord {
    fn from(s: &Score) -> ScoreRecord {
        ScoreRecord {
            gap_fit: s.fit,
            gap_holdout: s.holdout,
            domains: s.domains,
        }
    }
}

/// A candidate in self-check.json.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CandidateRecord {
    /// `effect` or `a+b`.
    pub name: String,
    /// Fitted effect parameters.
    pub params: BTreeMap<String, f64>,
    /// Held-out shrink against the baseline (or `against`), on the domains its effects
    /// act in.
    pub shrink: f64,
    /// Whether the simplex refined it.
    pub refined: bool,
    /// Its gaps.
    #[serde(flatten)]
    pub score: ScoreRecord,
    /// The gaps of the model its shrink is taken against where that is not the baseline
    /// ([`Candidate::against`](super::Candidate::against)).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub against: Option<ScoreRecord>,
}

impl From<&Outcome> for CaseRecord {
    fn from(o: &Outcome) -> CaseRecord {
        CaseRecord {
            case: o.case.index,
            effect: o.truth(),
            value: o.case.value,
            verdict: o.verdict.clone(),
            right: o.right(),
            shrink: o.shrink,
            param_error: o.param_error,
            baseline_gap: o.diagnosis.baseline.score.holdout,
            seconds: o.diagnosis.seconds,
            simulations: o.diagnosis.evaluations,
            level: o.case.level,
            offsets: [o.case.chain.offsets.0, o.case.chain.offsets.1],
            truth_gap: o.truth_score.holdout,
            truth_shrink: o.truth_shrink(),
            separable: o.separable(),
            truth: (&o.truth_score).into(),
            baseline: (&o.diagnosis.baseline.score).into(),
            candidates: o
                .diagnosis
                .candidates
                .iter()
                .map(|c| CandidateRecord {
                    name: c.name(),
                    params: c.params(),
                    shrink: c.shrink,
                    refined: c.refined,
                    score: (&c.score).into(),
                    against: c.against.as_ref().map(|f| (&f.score).into()),
                })
                .collect(),
        }
    }
}

/// self-check.json: what was run, the summary, and every case.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Document {
    /// [`FORMAT`].
    pub format: &'static str,
    /// The seed the cases were drawn from.
    pub seed: u64,
    /// The drive's name.
    pub sweep: &'static str,
    /// The rigs' name ([`Rigs::name`]).
    pub rigs: &'static str,
    /// The scores.
    pub summary: Summary,
    /// One record per case diagnosed.
    pub cases: Vec<CaseRecord>,
}

/// What the self-check's rigs are driven by.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Sweep {
    /// The paper's chirp: 0 to 12 Hz in 30 s, one level.
    #[default]
    Paper,
    /// 3 to 9 Hz at the paper's rate, at two levels in one record ([`two_level_chirp`]).
    TwoLevel,
    /// The same two sweeps recorded as two runs ([`level_sweep_at`]), fitted together on
    /// their even time blocks and scored on their odd ones.
    TwoRuns,
}

impl Sweep {
    /// The base motion it drives a rig with, at its first `level` (rad; the paper's 0.04).
    pub fn excitation_at(self, level: f64) -> Excitation {
        match self {
            Sweep::Paper => paper_chirp_at(level),
            Sweep::TwoLevel => two_level_chirp_at(level),
            Sweep::TwoRuns => level_sweep_at(level),
        }
    }

    /// Its name on the command line and in self-check.json.
    pub fn name(self) -> &'static str {
        match self {
            Sweep::Paper => "paper",
            Sweep::TwoLevel => "two-level",
            Sweep::TwoRuns => "two-runs",
        }
    }

    /// What it is, in words.
    pub fn describe(self) -> &'static str {
        match self {
            Sweep::Paper => "its chirp",
            Sweep::TwoLevel => {
                "a 3-9 Hz sweep at the paper's rate, at its level then 1.75 times it,"
            }
            Sweep::TwoRuns => {
                "a 3-9 Hz sweep at the paper's rate, at its level and 1.75 times it as two runs fitted together,"
            }
        }
    }
}

/// Simulates `case` under `sweep` (30 s at 1 kHz, the demo's encoder noise) and diagnoses
/// it blind, identifying with `identifier`.
pub fn run_case(
    case: &Case,
    opt: &SearchOptions,
    sweep: Sweep,
    identifier: Identifier<'_>,
) -> Result<Outcome, GapError> {
    let path = format!("/self_check/case_{:03}", case.index);
    let reference = if case.rigs == Rigs::Structure {
        let runs: Vec<crate::run::Run> = STRUCTURE_LEVELS
            .iter()
            .enumerate()
            .map(|(i, &level)| {
                let p = format!("{path}/level_{}", i + 1);
                structure_run(
                    &p,
                    &case.truth,
                    level,
                    case.chain.noise,
                    case.seed + i as u64,
                )
                .into_run()
            })
            .collect();
        Reference::together(&[&runs[0], &runs[2]], &[&runs[1], &runs[3]], identifier)?
    } else if sweep == Sweep::TwoRuns {
        let runs: Vec<crate::run::Run> = [1.0, SECOND_LEVEL]
            .iter()
            .enumerate()
            .map(|(i, &f)| {
                let drive = Drive::Base(sweep.excitation_at(case.level * f));
                let p = format!("{path}/level_{}", i + 1);
                measure_over(
                    &p,
                    &case.truth,
                    &drive,
                    &case.chain,
                    case.seed + i as u64,
                    "self-check case",
                    15.0,
                )
                .into_run()
            })
            .collect();
        Reference::blocks_together(&[&runs[0], &runs[1]], opt.blocks, identifier)?
    } else {
        let drive = Drive::Base(sweep.excitation_at(case.level));
        let run = measure(
            &path,
            &case.truth,
            &drive,
            &case.chain,
            case.seed,
            "self-check case",
        )
        .into_run();
        Reference::new(&run, opt.blocks, identifier)?
    }
    .scored_as(opt);
    let vocabulary = case.nominal.vocabulary();
    let searched;
    let opt = if case.rigs == Rigs::Structure && opt.effects == EffectKind::ALL {
        searched = SearchOptions {
            effects: vocabulary,
            ..opt.clone()
        };
        &searched
    } else {
        opt
    };
    let diagnosis = diagnose(&reference, &case.nominal, opt)?;
    // The truth itself, scored like any candidate: whether the record can tell the hidden
    // effect from the refitted baseline at all.
    let truth_score = reference.score(&case.truth);
    let verdict = diagnosis.verdict_name();
    let chosen = diagnosis.verdict.map(|i| &diagnosis.candidates[i]);
    let shrink = chosen.map(|c| c.shrink);
    let param_error = match (case.effect, chosen) {
        (Some(k), Some(c)) if c.effects.len() == 1 && c.effects[0].0 == k => {
            Some(c.effects[0].1.abs() / case.value.abs() - 1.0)
        }
        _ => None,
    };
    Ok(Outcome {
        case: case.clone(),
        verdict,
        shrink,
        param_error,
        truth_score,
        diagnosis,
    })
}

/// The self-check's figures.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Summary {
    /// Cases run.
    pub cases: usize,
    /// Cases that failed outright (their errors).
    pub errors: Vec<String>,
    /// truth → verdict → count.
    pub confusion: BTreeMap<String, BTreeMap<String, usize>>,
    /// Right verdicts over cases with an effect.
    pub top1: f64,
    /// Per effect: right verdicts over its cases.
    pub per_effect: BTreeMap<String, f64>,
    /// Effect-free cases given an effect, over effect-free cases.
    pub false_alarms: f64,
    /// Median held-out shrink where the verdict is right.
    pub median_shrink: Option<f64>,
    /// Median |relative error| of the effect parameter where the verdict is right.
    pub median_param_error: Option<f64>,
    /// Median wall time per case (s).
    pub median_seconds: f64,
    /// Median simulations per case.
    pub median_evaluations: f64,
    /// Cases with an effect whose true model itself clears the verdict's held-out margins
    /// against the refitted baseline ([`Outcome::separable`]).
    pub separable: usize,
    /// Right verdicts over those cases.
    pub top1_separable: f64,
    /// Per effect: its cases that are separable, over its cases.
    pub separable_per_effect: BTreeMap<String, f64>,
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

/// Sums up outcomes (and the errors of cases that could not be diagnosed).
pub fn summarize(outcomes: &[Outcome], errors: Vec<String>) -> Summary {
    let mut confusion: BTreeMap<String, BTreeMap<String, usize>> = BTreeMap::new();
    for o in outcomes {
        *confusion
            .entry(o.truth().to_string())
            .or_default()
            .entry(o.verdict.clone())
            .or_default() += 1;
    }
    let with: Vec<&Outcome> = outcomes
        .iter()
        .filter(|o| o.case.effect.is_some())
        .collect();
    let free: Vec<&Outcome> = outcomes
        .iter()
        .filter(|o| o.case.effect.is_none())
        .collect();
    let rate = |v: &[&Outcome], f: &dyn Fn(&Outcome) -> bool| {
        if v.is_empty() {
            0.0
        } else {
            v.iter().filter(|o| f(o)).count() as f64 / v.len() as f64
        }
    };
    // Per effect: the share of its cases for which `f` holds.
    let per_effect_rate = |f: &dyn Fn(&Outcome) -> bool| -> BTreeMap<String, f64> {
        EffectKind::EVERY
            .iter()
            .filter_map(|k| {
                let of: Vec<&Outcome> = with
                    .iter()
                    .copied()
                    .filter(|o| o.case.effect == Some(*k))
                    .collect();
                (!of.is_empty()).then(|| (k.name().to_string(), rate(&of, f)))
            })
            .collect()
    };
    let per_effect = per_effect_rate(&|o| o.right());
    let separable_per_effect = per_effect_rate(&|o| o.separable());
    let right: Vec<&Outcome> = with.iter().copied().filter(|o| o.right()).collect();
    let separable: Vec<&Outcome> = with.iter().copied().filter(|o| o.separable()).collect();
    Summary {
        separable: separable.len(),
        top1_separable: rate(&separable, &|o| o.right()),
        separable_per_effect,
        cases: outcomes.len() + errors.len(),
        errors,
        confusion,
        top1: rate(&with, &|o| o.right()),
        per_effect,
        false_alarms: rate(&free, &|o| o.verdict != "none"),
        median_shrink: median(right.iter().filter_map(|o| o.shrink).collect()),
        median_param_error: median(
            right
                .iter()
                .filter_map(|o| o.param_error.map(f64::abs))
                .collect(),
        ),
        median_seconds: median(outcomes.iter().map(|o| o.diagnosis.seconds).collect())
            .unwrap_or(0.0),
        median_evaluations: median(
            outcomes
                .iter()
                .map(|o| o.diagnosis.evaluations as f64)
                .collect(),
        )
        .unwrap_or(0.0),
    }
}

/// A short column label for an effect or `none`.
fn short(name: &str) -> String {
    name.split('+')
        .map(|p| match p {
            "coulomb_friction" => "fric",
            "gravity_preload" => "prel",
            "asymmetric_clearance" => "asym",
            "cubic_stiffness" => "cubic",
            "contact_damping" => "cdamp",
            "sensor_delay" => "delay",
            "quantization" => "quant",
            "microslip" => "slip",
            other => other,
        })
        .collect::<Vec<_>>()
        .join("+")
}

impl fmt::Display for Summary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let rows: Vec<&str> = EffectKind::EVERY
            .iter()
            .map(|k| k.name())
            .chain(["none"])
            .filter(|r| self.confusion.contains_key(*r))
            .collect();
        // The columns: the effects that are rows, then any other verdict.
        let mut cols: Vec<String> = rows
            .iter()
            .filter(|r| **r != "none")
            .map(|r| r.to_string())
            .collect();
        cols.push("none".into());
        for v in self.confusion.values().flat_map(|m| m.keys()) {
            if !cols.contains(v) {
                cols.push(v.clone());
            }
        }
        writeln!(
            f,
            "confusion matrix (rows: effect in the data; columns: verdict)"
        )?;
        // A pair's short name (`cubic+quant`) is wider than one effect's: every column is
        // as wide as the widest name, plus a space.
        let w = cols
            .iter()
            .map(|c| short(c).len())
            .max()
            .unwrap_or(5)
            .max(6)
            + 1;
        write!(f, "{:<22}", "")?;
        for c in &cols {
            write!(f, "{:>w$}", short(c))?;
        }
        writeln!(f)?;
        for r in rows {
            write!(f, "{r:<22}")?;
            for c in &cols {
                let n = self.confusion[r].get(c).copied().unwrap_or(0);
                if n == 0 {
                    write!(f, "{:>w$}", ".")?;
                } else {
                    write!(f, "{n:>w$}")?;
                }
            }
            writeln!(f)?;
        }
        writeln!(f)?;
        writeln!(
            f,
            "top-1 accuracy (cases with an effect): {:.0} %",
            100.0 * self.top1
        )?;
        for (k, v) in &self.per_effect {
            let sep = self.separable_per_effect.get(k).copied().unwrap_or(0.0);
            writeln!(
                f,
                "  {k:<22} {:>3.0} %   (the record separates it in {:.0} %)",
                100.0 * v,
                100.0 * sep
            )?;
        }
        writeln!(
            f,
            "false alarms (effect-free cases):     {:.0} %",
            100.0 * self.false_alarms
        )?;
        if self.separable > 0 {
            writeln!(
                f,
                "separable cases (the true model itself clears the verdict's held-out margins \
                 against the refitted baseline): {}; top-1 among them {:.0} %",
                self.separable,
                100.0 * self.top1_separable
            )?;
        } else {
            writeln!(
                f,
                "separable cases (the true model itself clears the verdict's held-out margins \
                 against the refitted baseline): none"
            )?;
        }
        match self.median_shrink {
            Some(s) => writeln!(
                f,
                "median held-out shrink (right verdicts): {:.0} %",
                100.0 * s
            )?,
            None => writeln!(f, "median held-out shrink: no right verdict")?,
        }
        if let Some(e) = self.median_param_error {
            writeln!(
                f,
                "median effect-parameter error (right verdicts): {:.0} %",
                100.0 * e
            )?;
        }
        writeln!(
            f,
            "cost: median {:.1} s and {:.0} simulations per run",
            self.median_seconds, self.median_evaluations
        )?;
        for e in &self.errors {
            writeln!(f, "error: {e}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cases_cycle_through_every_class_with_parameters_in_range() {
        let c = cases(16, 7);
        for (i, case) in c.iter().enumerate() {
            assert_eq!(case.effect, EffectKind::ALL.get(i % 8).copied());
            if let Some(k) = case.effect {
                let f = case.value / effect_value(k);
                assert!((1.0 / RANGE..=RANGE).contains(&f), "{f}");
                assert_eq!(case.truth.effects.present(), vec![(k, case.value)]);
            }
            assert!(case.nominal.effects.is_empty());
            let e = case.nominal.stiffness / case.truth.stiffness - 1.0;
            assert!(e.abs() <= 2.0 * NOMINAL_ERROR + 1e-12, "{e}");
        }
        // Deterministic in the seed.
        assert_eq!(cases(16, 7)[5].value, c[5].value);
    }

    #[test]
    fn structure_cases_cycle_through_the_force_vocabulary_and_soften_then_harden() {
        let c = draw(
            12,
            5,
            Draw {
                rigs: Rigs::Structure,
                only: None,
            },
        );
        for (i, case) in c.iter().enumerate() {
            assert_eq!(case.effect, STRUCTURE_CLASSES[i % 6]);
            assert_eq!(case.truth.kind, crate::model::ModelKind::Force);
            assert_eq!(
                case.nominal.vocabulary(),
                crate::model::EffectKind::FORCE
                    .iter()
                    .copied()
                    .filter(|k| *k != EffectKind::ContactDamping)
                    .collect::<Vec<_>>()
            );
            assert!(case.nominal.effects.is_empty());
            let m = case.nominal.inertia / case.truth.inertia - 1.0;
            assert!(m.abs() <= 2.0 * NOMINAL_ERROR + 1e-12 && m != 0.0, "{m}");
            if let Some(k) = case.effect {
                let f = case.value / structure_effect_value(k).unwrap();
                let f = if k == EffectKind::CubicStiffness && i >= 6 {
                    -f
                } else {
                    f
                };
                assert!((1.0 / RANGE..=RANGE).contains(&f), "{k}: {f}");
                assert_eq!(case.truth.effects.get(k), Some(case.value));
            }
            if case.effect == Some(EffectKind::Microslip) {
                let kj = case.truth.effects.joint_stiffness().unwrap();
                assert!((kj / case.truth.stiffness - crate::model::JOINT_SHARE).abs() < 1e-12);
            }
        }
        // The cubic term softens in the first round and hardens in the second.
        assert!(c[1].value < 0.0 && c[7].value > 0.0);
    }

    #[test]
    fn random_rigs_stay_in_issue_20_s_ranges_and_their_quantization_is_a_coarse_blurred_encoder() {
        let random = Draw {
            rigs: Rigs::Random,
            only: None,
        };
        let c = draw(24, 3, random);
        for case in &c {
            let m = &case.truth;
            assert!((9.7..11.4).contains(&m.contact_frequency_hz()));
            assert!((1.3..1.7).contains(&m.clearance.to_degrees()));
            assert!((0.032..0.048).contains(&case.level));
            assert!(case.chain.offsets.1.abs() <= 2e-4);
            assert_eq!(case.nominal.gravity_stiffness, case.chain.gravity_attribute);
            let g = case.chain.gravity_attribute / m.gravity_stiffness - 1.0;
            assert!(g.abs() <= 0.1 + 1e-12, "{g}");
            // The model knows the bench's fine encoders, and nothing else beyond the joint.
            let known = case.nominal.effects.present();
            assert_eq!(known.len(), 1);
            assert_eq!(known[0].0, EffectKind::Quantization);
            assert!(known[0].1 < 5e-5, "{known:?}");
            let step = m.effects.get(EffectKind::Quantization).unwrap();
            if case.effect == Some(EffectKind::Quantization) {
                // 12-14 bit/rev, steps blurred by 1/60-1/15 of a step.
                assert_eq!(step, case.value);
                let bits = (std::f64::consts::TAU / step).log2();
                assert!(
                    (12.0..=14.0).contains(&bits.round()) && (bits - bits.round()).abs() < 1e-9
                );
                let blur = case.chain.acquisition_noise / step;
                assert!((1.0 / 60.0..=1.0 / 15.0).contains(&blur), "{blur}");
            } else {
                // The fine encoder of 17-20 bit/rev, no blur after it.
                assert!(step < 5e-5 && case.chain.acquisition_noise == 0.0);
                assert!(case.chain.noise < step);
            }
        }
        // One effect at a fixed size: every case holds it at that size.
        let one = draw(
            3,
            3,
            Draw {
                rigs: Rigs::Paper,
                only: Some((EffectKind::SensorDelay, 0.25)),
            },
        );
        for case in &one {
            assert_eq!(case.effect, Some(EffectKind::SensorDelay));
            assert_eq!(case.value, 0.25 * effect_value(EffectKind::SensorDelay));
            assert_eq!(case.chain.offsets, (0.0, 0.0));
        }
    }
}
