//! Candidates: one or two effects added to the baseline and fitted with its own
//! parameters, scored on the held-out blocks; what each effect leaves in the skeleton, for
//! the report. In: the baseline, the identification and an effect; out: a [`Candidate`].

use std::collections::BTreeMap;

use super::fit::{backbone_hardening, smooth_cubic, Coordinates, Fitted};
use super::{Reference, Score, SearchOptions};
use crate::identify::Identification;
use crate::model::{EffectKind, RigModel};

/// What each effect leaves in the skeleton domain (DESIGN.md), for the report.
pub fn signature(kind: EffectKind) -> &'static str {
    match kind {
        EffectKind::CoulombFriction => {
            "dry friction: the damping force stays up at small amplitude (2h0 rising as 1/(A·ω))"
        }
        EffectKind::GravityPreload => {
            "preload: the link leans on one flank, so the backbone stiffens at small amplitude"
        }
        EffectKind::AsymmetricClearance => {
            "offset clearance: contact on one flank first, the backbone bends earlier (or \
             encoders whose zeros differ by the offset: the two are the same in the relative \
             angle; zero both encoders together to tell them apart)"
        }
        EffectKind::CubicStiffness => "hardening contact: the backbone keeps rising with amplitude",
        EffectKind::ContactDamping => "contact damping: damping grows once the link touches",
        EffectKind::SensorDelay => {
            "sensor delay: a phase error growing with frequency distorts the relative motion"
        }
        EffectKind::Quantization => "quantization: a noise floor at small amplitude",
        EffectKind::Microslip => {
            "microslip: the joint slips a little more each cycle as the amplitude grows, so the \
             backbone softens and the damping rises with amplitude without a gap ever opening"
        }
    }
}

/// Which model a scan point added its effect to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Side {
    Baseline,
    Nominal,
    /// The baseline with a joint read off the skeleton ([`super::iwan`]).
    Skeleton,
}

/// `base` with its own parameters made ready for `kind` to be added: for dry friction, the
/// viscous damping put back where the skeleton's damping fit separated the two (without
/// friction the baseline has put all the damping into c); for a hardening contact, the
/// contact stiffness the backbone asks for beside it (without it the baseline has made the
/// contact stiffer); for a joint's cubic term without clearance, the linear stiffness the
/// fitted runs' backbones pooled ask for beside it (the baseline has averaged the
/// softening or hardening into k, and the cubic term added on top counted it twice: the
/// force self-check's cubic fits stopped at 0.65–0.8 times the truth). Computed once per
/// model and effect, not per scan point.
pub(super) fn ready_for(
    base: &RigModel,
    ids: &[&Identification],
    kind: EffectKind,
    waveform: bool,
) -> RigModel {
    let identified = ids[0];
    let mut m = base.clone();
    if let (EffectKind::CoulombFriction, Some((c, _))) = (kind, identified.damping) {
        let c = c.value * base.inertia;
        if c > 0.0 && c < base.damping {
            m.damping = c;
        }
    }
    if kind == EffectKind::CubicStiffness {
        let stiffness = if base.clearance > 0.0 {
            backbone_hardening(base, identified, waveform).map(|(k, _)| k)
        } else {
            smooth_cubic(base, ids).map(|(k, _)| k)
        };
        if let Some(k) = stiffness {
            m.stiffness = k;
        }
    }
    m
}

/// One candidate explanation: effects added to the baseline and fitted.
#[derive(Debug, Clone)]
pub struct Candidate {
    /// The effects and their fitted parameters.
    pub effects: Vec<(EffectKind, f64)>,
    /// The whole fitted model.
    pub model: RigModel,
    /// Its gaps.
    pub score: Score,
    /// 1 − gap_holdout / baseline_gap, both on the domains its effects act in
    /// ([`Score::holdout_on`]).
    pub shrink: f64,
    /// Whether the simplex refined it (otherwise it is the best point of the scan).
    pub refined: bool,
    /// The model without its effects that its shrink and significance are taken against,
    /// where that is not the baseline: a force model's converter step, fitted on the time
    /// domain alone, is weighed against the model refitted there without it.
    pub against: Option<Fitted>,
}

impl Candidate {
    /// `a` or `a+b`.
    pub fn name(&self) -> String {
        let names: Vec<&str> = self.effects.iter().map(|(k, _)| k.name()).collect();
        names.join("+")
    }

    /// Its effects' kinds.
    pub fn kinds(&self) -> Vec<EffectKind> {
        self.effects.iter().map(|e| e.0).collect()
    }

    /// The domains its [`shrink`](Self::shrink) is taken on ([`Score::holdout_on`]).
    pub fn shrink_domains(&self) -> &'static [&'static str] {
        const ALL: [&str; 4] = ["time", "backbone", "damping", "waveform"];
        if self.score.scores_time_alone(&self.kinds()) {
            &ALL[..1]
        } else if self.score.domains[3].is_none()
            || self.score.scores_without_waveform(&self.kinds())
        {
            &ALL[..3]
        } else {
            &ALL
        }
    }

    /// Whether its shrink leaves out domains that its gaps include (a sensor effect scored
    /// with the waveform on, or a force model's converter step, read on the time domain
    /// alone): then the shrink is not read off the gaps beside it.
    pub fn shrink_on_fewer_domains(&self) -> bool {
        let kinds = self.kinds();
        self.score.scores_time_alone(&kinds) || self.score.scores_without_waveform(&kinds)
    }

    /// The fitted effect parameters by name (`effect.param` for a pair, whose parameters
    /// may share a name).
    pub fn params(&self) -> BTreeMap<String, f64> {
        let pair = self.effects.len() > 1;
        let key = |k: EffectKind, param: &str| {
            if pair {
                format!("{}.{}", k.name(), param)
            } else {
                param.to_string()
            }
        };
        self.effects
            .iter()
            .flat_map(|&(k, v)| {
                let joint = (k == EffectKind::Microslip)
                    .then_some(self.model.effects.microslip)
                    .flatten()
                    .into_iter()
                    .flat_map(move |p| {
                        let fine = p.has_fine().then(|| {
                            [
                                (key(k, "fine_stiffness"), p.fine_stiffness),
                                (key(k, "fine_slip"), p.fine_slip),
                            ]
                        });
                        [
                            (key(k, "joint_stiffness"), p.joint_stiffness),
                            (key(k, "spread"), p.spread),
                        ]
                        .into_iter()
                        .chain(fine.into_iter().flatten())
                    });
                let limit = (k == EffectKind::CubicStiffness)
                    .then(|| self.model.effects.cubic_limit())
                    .flatten()
                    .map(|l| (key(k, "limit"), l));
                std::iter::once((key(k, k.param()), v))
                    .chain(joint)
                    .chain(limit)
            })
            .collect()
    }
}

impl Candidate {
    /// The candidate a fit of `kinds` gave.
    pub(super) fn from_fit(f: Fitted, kinds: &[EffectKind], base: &Score, refined: bool) -> Self {
        let mut effects: Vec<(EffectKind, f64)> = kinds
            .iter()
            .map(|&k| (k, f.model.effects.get(k).unwrap_or(0.0)))
            .collect();
        effects.sort_by_key(|e| e.0);
        Candidate {
            effects,
            shrink: f.score.shrink_against(base, kinds),
            model: f.model,
            score: f.score,
            refined,
            against: None,
        }
    }
}

/// `effects` (each from its current value) fitted by the simplex together with the own
/// parameters of `from` (the model the effects are added to).
pub(super) fn refit(
    reference: &Reference,
    from: &RigModel,
    effects: &[(EffectKind, f64)],
    opt: &SearchOptions,
    baseline: &Score,
) -> Candidate {
    // The effects leave the base (the simplex sets them), but a microslip's joint
    // stiffness stays to start from, and a cubic term's limit (the simplex sets k3 alone,
    // and fits the limit where the base has one).
    let mut base = from.clone();
    for &(k, _) in effects {
        if !matches!(k, EffectKind::Microslip | EffectKind::CubicStiffness) {
            base.effects.set(k, None);
        }
    }
    let coords = Coordinates {
        base: &base,
        inertia: opt.fit_inertia,
        effects: effects.to_vec(),
        time_alone: false,
    };
    let f = coords.fit(reference, coords.origin(), opt.candidate_evaluations);
    let kinds: Vec<EffectKind> = effects.iter().map(|e| e.0).collect();
    Candidate::from_fit(f, &kinds, baseline, true)
}

/// Whichever of two fits of the same effects is better on the fitting blocks (marked
/// refined either way: the simplex was run).
pub(super) fn fitter(a: Candidate, b: Candidate) -> Candidate {
    let mut best = if a.score.fit <= b.score.fit { a } else { b };
    best.refined = true;
    best
}
