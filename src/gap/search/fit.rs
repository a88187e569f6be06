//! The fits of the search: the coordinates the simplex moves in, the baseline refit of the
//! model's own parameters, each effect's starting value (from the skeleton where it can be
//! read off), and the Nelder–Mead simplex itself. In: a reference run and a model; out: the
//! fitted model with its score.

use super::{Reference, Score, SearchOptions};
use crate::identify::Identification;
use crate::model::{EffectKind, ModelKind, RigModel, JOINT_SHARE};

/// A model found by a fit, with its score.
#[derive(Debug, Clone)]
pub struct Fitted {
    /// The model.
    pub model: RigModel,
    /// Its gaps.
    pub score: Score,
}

/// The coordinates the simplex moves in: the model's own parameters relative to `base`
/// (stiffness, damping, clearance and, when asked, inertia by their logarithms, so they stay
/// positive; the gravity stiffness in units of 1 % of k/J, keeping the nominal's sign) and
/// the effects' parameters in units of their starting values (by their logarithms for
/// those that cannot be negative).
pub(super) struct Coordinates<'a> {
    pub(super) base: &'a RigModel,
    pub(super) inertia: bool,
    pub(super) effects: Vec<(EffectKind, f64)>,
    /// Whether the fit minimises the fitting blocks' time domain alone instead of their
    /// whole gap ([`Score::fit_on`]): where the effect fitted acts on that domain alone.
    pub(super) time_alone: bool,
}

impl Coordinates<'_> {
    /// Whether the inertia is a coordinate: when asked, and always for a force model,
    /// whose modal mass is a parameter like the others.
    fn fits_inertia(&self) -> bool {
        self.inertia || self.base.kind == ModelKind::Force
    }

    /// Index of the first effect coordinate.
    pub(super) fn own(&self) -> usize {
        4 + self.fits_inertia() as usize
    }

    pub(super) fn model(&self, x: &[f64]) -> RigModel {
        let b = self.base;
        let mut m = b.clone();
        // A force model's mass coordinate carries every force of the model with it (see
        // [`Coordinates::force_gain`]).
        let gain = self.force_gain(x);
        m.stiffness = b.stiffness * x[0].exp() * gain;
        m.damping = b.damping.max(1e-9) * x[1].exp() * gain;
        m.clearance = b.clearance * x[2].exp();
        // The gravity stiffness keeps the nominal model's sign (a rig whose link hangs
        // cannot turn into an inverted pendulum): reflected at zero, so the simplex sees no
        // flat region. Zero counts as positive.
        let c = b.gravity_stiffness + 0.01 * b.stiffness / b.inertia * x[3];
        m.gravity_stiffness = if b.gravity_stiffness < 0.0 {
            -c.abs()
        } else {
            c.abs()
        };
        if self.fits_inertia() {
            m.inertia = b.inertia * x[4].exp();
        }
        let mut at = self.own();
        for &(kind, start) in &self.effects {
            let u = x[at];
            let v = if by_log(kind) {
                start * u.exp()
            } else {
                start * u
            };
            m.effects
                .set(kind, Some(if is_force(kind) { v * gain } else { v }));
            at += 1;
            // The microslip's joint stiffness moves by its logarithm from the base's (or
            // the share a new joint starts with), never past the model's stiffness.
            if kind == EffectKind::Microslip {
                let kj = joint_start(b) * x[at].exp() * gain;
                m.effects.set_joint_stiffness(kj.min(m.stiffness));
                at += 1;
                // The spread through a logistic map: always in (0, 1), and a step of the
                // simplex moves it whichever end it starts near.
                let s0 = spread_start(b);
                let u = (s0 / (1.0 - s0)).ln() + x[at];
                m.effects
                    .set_spread((1.0 / (1.0 + (-u).exp())).clamp(1e-3, 1.0));
                at += 1;
                // A fine population (where the base has one) moves by the logarithms of
                // its stiffness and of its largest slip.
                if let Some(p) = b.effects.microslip.filter(|p| p.has_fine()) {
                    m.effects.set_fine(
                        p.fine_stiffness * x[at].exp() * gain,
                        p.fine_slip * x[at + 1].exp(),
                    );
                    at += 2;
                }
            }
            // A cubic term's limit (where the base has one) moves by its logarithm.
            if kind == EffectKind::CubicStiffness {
                if let Some(l) = b.effects.cubic_limit() {
                    m.effects.set_cubic_limit(l * x[at].exp());
                    at += 1;
                }
            }
        }
        within_stiffness(&mut m);
        m
    }

    /// The factor a force model's mass coordinate scales every force of the model by:
    /// its stiffness, damping, and the effects' forces and stiffnesses ([`is_force`]),
    /// so that moving the mass keeps the natural frequency, the damping ratio and the
    /// joint's strength relative to the mode, and only scales the response to the
    /// measured force. With the mass moving alone, each step of it detuned the mode
    /// (k/m), and the simplex crawled along that valley: the force self-check's cubic and
    /// friction fits stopped with a modal mass 3–7 % off and a fit gap three to five times
    /// the truth's. 1 for the other kinds (the mass is not a coordinate there unless asked,
    /// and scaling every force with it would leave a base-driven rig unchanged).
    fn force_gain(&self, x: &[f64]) -> f64 {
        if self.base.kind == ModelKind::Force && self.fits_inertia() {
            x[4].exp()
        } else {
            1.0
        }
    }

    /// The point of `base` itself, every effect at its starting value.
    pub(super) fn origin(&self) -> Vec<f64> {
        let mut x = vec![0.0; self.own()];
        for &(k, _) in &self.effects {
            x.push(if by_log(k) { 0.0 } else { 1.0 });
            if k == EffectKind::Microslip {
                x.extend([0.0, 0.0]);
                if has_fine(self.base) {
                    x.extend([0.0, 0.0]);
                }
            }
            if k == EffectKind::CubicStiffness && self.base.effects.cubic_limit().is_some() {
                x.push(0.0);
            }
        }
        x
    }

    /// A simplex around `x`: a step of 0.05 in each log parameter (0.1 % of k/J in the
    /// gravity stiffness) and of half the starting value in each effect's. Without a
    /// clearance its coordinate is left out, and a force model's gravity stiffness.
    pub(super) fn simplex(&self, x: &[f64]) -> Vec<Vec<f64>> {
        let mut simplex = vec![x.to_vec()];
        for d in 0..x.len() {
            if d == 2 && self.base.clearance <= 0.0 {
                continue;
            }
            if d == 3 && self.base.kind != ModelKind::BaseMotion {
                continue;
            }
            let mut v = x.to_vec();
            v[d] += if d >= self.own() { 0.5 } else { 0.05 };
            simplex.push(v);
        }
        simplex
    }

    /// [`fit`](Self::fit) with three fifths of `evaluations`, then again from a fresh
    /// simplex around its best point with the rest (a fresh simplex escapes the collapsed
    /// one's stall); the better of the two.
    pub(super) fn fit_restarted(
        &self,
        reference: &Reference,
        start: Vec<f64>,
        evaluations: usize,
    ) -> Fitted {
        let first = evaluations * 3 / 5;
        let fitted = self.fit(reference, start, first);
        let effects = self
            .effects
            .iter()
            .map(|&(k, v)| (k, fitted.model.effects.get(k).unwrap_or(v)))
            .collect();
        let again = Coordinates {
            base: &fitted.model,
            inertia: self.inertia,
            effects,
            time_alone: self.time_alone,
        };
        let refined = again.fit(reference, again.origin(), evaluations - first);
        if self.cost(&refined.score) < self.cost(&fitted.score) {
            refined
        } else {
            fitted
        }
    }

    /// What the fit minimises: the fitting blocks' whole gap, or their time domain's.
    pub(super) fn cost(&self, score: &Score) -> f64 {
        score.fit_gap(self.time_alone)
    }

    /// Minimises the gap on the fitting blocks from `start`.
    pub(super) fn fit(&self, reference: &Reference, start: Vec<f64>, evaluations: usize) -> Fitted {
        // The best model seen, with both its gaps: the simplex itself keeps only the value
        // it minimises.
        let mut best: Option<Fitted> = None;
        let mut cost = |x: &[f64]| {
            let model = self.model(x);
            let score = reference.score(&model);
            let c = self.cost(&score);
            if best.as_ref().is_none_or(|f| c < self.cost(&f.score)) {
                best = Some(Fitted { model, score });
            }
            c
        };
        nelder_mead(&mut cost, self.simplex(&start), evaluations, 1e-3);
        best.expect("the simplex evaluates its first vertex")
    }
}

/// Effects whose parameter is a force or a stiffness (scaled with a force model's mass,
/// [`Coordinates::force_gain`]).
fn is_force(kind: EffectKind) -> bool {
    matches!(
        kind,
        EffectKind::CoulombFriction
            | EffectKind::CubicStiffness
            | EffectKind::Microslip
            | EffectKind::GravityPreload
            | EffectKind::ContactDamping
    )
}

/// Effect parameters that cannot be negative move by their logarithm.
pub(super) fn by_log(kind: EffectKind) -> bool {
    matches!(
        kind,
        EffectKind::CoulombFriction
            | EffectKind::ContactDamping
            | EffectKind::SensorDelay
            | EffectKind::Quantization
            | EffectKind::Microslip
    )
}

/// The joint stiffness a microslip starts from on `model`: its own, or [`JOINT_SHARE`] of
/// the stiffness for a model without one.
pub(super) fn joint_start(model: &RigModel) -> f64 {
    model
        .effects
        .joint_stiffness()
        .filter(|k| *k > 0.0)
        .unwrap_or(JOINT_SHARE * model.stiffness)
}

/// A joint with a fine population shrunk, both populations in proportion, to within the
/// model's stiffness (with a margin that rounding cannot cross, so that the model written
/// validates), whichever coordinates moved it: the joint's own, or the stiffness under a
/// joint held (a baseline refit). Never to zero: a population clamped away would lose its
/// coordinates in the restarted simplex. A joint without a fine population is left as
/// before ([`Coordinates::model`] clamps its stiffness alone, and the rig again).
fn within_stiffness(m: &mut RigModel) {
    let Some(p) = m.effects.microslip.filter(|p| p.has_fine()) else {
        return;
    };
    let room = m.stiffness * (1.0 - 1e-9);
    let total = p.joint_stiffness + p.fine_stiffness;
    if total > room {
        let scale = room / total;
        m.effects.set_joint_stiffness(p.joint_stiffness * scale);
        m.effects.set_fine(p.fine_stiffness * scale, p.fine_slip);
    }
}

/// Whether `model`'s microslip has a fine population (whose two parameters are then
/// coordinates of its fits).
fn has_fine(model: &RigModel) -> bool {
    model.effects.microslip.is_some_and(|p| p.has_fine())
}

/// The spread a microslip's fit starts from on `model`: its own (kept off the ends of
/// (0, 1), where the logistic map is flat), or the middle for a model without one.
pub(super) fn spread_start(model: &RigModel) -> f64 {
    model
        .effects
        .microslip
        .map_or(0.5, |p| p.spread)
        .clamp(0.05, 0.95)
}

/// `ln(v / nominal)`, or 0 where either is not positive.
pub(super) fn log_ratio(v: f64, nominal: f64) -> f64 {
    if v > 0.0 && nominal > 0.0 {
        (v / nominal).ln()
    } else {
        0.0
    }
}

/// The effects `model` has, each with its parameter: what the baseline moves beside the
/// model's own parameters with [`SearchOptions::refit_effects`].
pub(super) fn own_effects(model: &RigModel) -> Vec<(EffectKind, f64)> {
    EffectKind::EVERY
        .iter()
        .filter_map(|&k| model.effects.get(k).map(|v| (k, v)))
        .collect()
}

/// The baseline: the model's own parameters — stiffness, damping, clearance, gravity
/// stiffness, and the inertia when asked — refitted on the fitting blocks, so that a
/// mis-set parameter is never taken for a missing effect; with
/// [`SearchOptions::refit_effects`], the effects the model already has too. The simplex
/// restarts once from its best point (a fresh simplex escapes the collapsed one's stall).
pub fn refit_baseline(reference: &Reference, nominal: &RigModel, opt: &SearchOptions) -> Fitted {
    let effects = if opt.refit_effects {
        own_effects(nominal)
    } else {
        Vec::new()
    };
    let coords = Coordinates {
        base: nominal,
        inertia: opt.fit_inertia,
        effects,
        time_alone: false,
    };
    // Start from the nominal model or from what the identification found, whichever is
    // closer: the skeleton fit is near the truth when the nominal values are far off.
    let mut start = coords.origin();
    let id = reference.identified();
    if let Some(dz) = id.dead_zone {
        let j = nominal.inertia;
        let c = id.damping.map_or(nominal.damping, |(c, _)| c.value * j);
        let mut found = coords.origin();
        found[0] = log_ratio(dz.stiffness.value * j, nominal.stiffness);
        found[1] = log_ratio(c, nominal.damping);
        found[2] = log_ratio(2.0 * dz.half_gap.value, nominal.clearance);
        let (a, b) = rayon::join(
            || reference.score(&coords.model(&found)).fit,
            || reference.score(&coords.model(&start)).fit,
        );
        if a < b {
            start = found;
        }
    }
    coords.fit_restarted(reference, start, opt.baseline_evaluations)
}

/// `start`'s own parameters (stiffness, damping, clearance, gravity stiffness) and the
/// parameters of `effects` (each from its starting value) fitted together on the fitting
/// blocks, for at most `evaluations` simulations, the simplex restarted once from its best
/// point like the baseline's. The simulation-refined identification ([`crate::refine`]).
pub fn refit_with(
    reference: &Reference,
    start: &RigModel,
    effects: &[(EffectKind, f64)],
    evaluations: usize,
) -> Fitted {
    let coords = Coordinates {
        base: start,
        inertia: false,
        effects: effects.to_vec(),
        time_alone: false,
    };
    coords.fit_restarted(reference, coords.origin(), evaluations)
}

/// A starting value for `kind`'s parameter on `model`, from the identification where it
/// says something (the Coulomb level of the damping fit) and otherwise a small fraction of
/// the model's own scales: the torque of 10 % of the half-gap's contact deflection, a tenth
/// of the half-gap, the cubic term that adds 10 % of k at one half-gap of penetration, the
/// viscous damping itself, 2 ms, 2 % of the half-gap. The scan spans ×1/8 to ×8 around it.
pub fn effect_start(kind: EffectKind, model: &RigModel, identified: &Identification) -> f64 {
    start_for(kind, model, &[identified], false)
}

/// [`effect_start`] over every run the fits see (`ids`, the first fit run first), for a
/// search whose gap scores the waveform domain when `waveform`: there a hardening the
/// backbone cannot see starts from the generic value (see [`backbone_hardening`]). A joint's
/// cubic term without clearance is read off their backbones pooled: on the force
/// self-check's levels 1 and 3 the first level alone gave k3 from −0.03 to −0.9 times a
/// softening's truth (once with the wrong sign), the loudest alone about 0.7 times, and the
/// two pooled 0.8–0.93 times (the scan's ×1/8–×8 missed three of seven truths from the
/// first). Every other start is read off the first run.
pub(super) fn start_for(
    kind: EffectKind,
    model: &RigModel,
    ids: &[&Identification],
    waveform: bool,
) -> f64 {
    let identified = ids[0];
    let half = (0.5 * model.clearance).max(1e-6);
    match kind {
        EffectKind::CoulombFriction => identified
            .damping
            .map(|(_, f)| f.value * model.inertia)
            .filter(|f| *f > 0.0)
            .unwrap_or_else(|| generic_friction(model, identified)),
        EffectKind::GravityPreload => 0.1 * model.stiffness * half,
        EffectKind::AsymmetricClearance => 0.1 * half,
        EffectKind::CubicStiffness if model.clearance <= 0.0 => smooth_cubic(model, ids)
            .map_or_else(|| generic_smooth_cubic(model, identified), |(_, k3)| k3),
        EffectKind::CubicStiffness => backbone_hardening(model, identified, waveform)
            .map_or(generic_cubic(model), |(_, k3)| k3),
        // Half the joint's elements slipping at the largest measured amplitude.
        EffectKind::Microslip => joint_start(model) * largest_amplitude(identified),
        EffectKind::ContactDamping => model.damping.max(1e-6),
        EffectKind::SensorDelay => 0.002,
        EffectKind::Quantization => 0.02 * half,
    }
}

/// The dry friction to start from where the damping fit gives none. Behind a clearance, a
/// hundredth of the force the contact spring gives at a half-gap (as before); without one
/// (a mode of a structure) the half-gap is no length at all and that start was 1e-5 N on a
/// 1 kg mode, thousands of times below any friction the record could show. There: the friction
/// that dissipates a third of the viscous damping's energy per cycle at the largest
/// measured amplitude, 4·F·A = π·c·ω·A²/3.
fn generic_friction(model: &RigModel, identified: &Identification) -> f64 {
    if model.clearance > 0.0 {
        return 0.01 * model.stiffness * (0.5 * model.clearance).max(1e-6);
    }
    let omega = (model.stiffness / model.inertia).sqrt();
    std::f64::consts::PI * model.damping * omega * largest_amplitude(identified) / 12.0
}

/// The largest amplitude the identification tracked (signal units; 1 when it tracked none).
fn largest_amplitude(id: &Identification) -> f64 {
    id.amplitude_range().map_or(1.0, |(_, hi)| hi)
}

/// The linear stiffness and cubic term of a joint without clearance that the backbones of
/// `ids` ask for, with `model`'s mass: the least squares of m·ω0² = k + ¾·k3·A² over the
/// samples at resonance (its describing function); k3 negative for a softening. `None`
/// with fewer than ten such samples.
pub(super) fn smooth_cubic(model: &RigModel, ids: &[&Identification]) -> Option<(f64, f64)> {
    let points: Vec<(f64, f64)> = ids
        .iter()
        .flat_map(|id| {
            let n = id.used.len().min(id.response.len());
            (0..n)
                .filter(|&i| id.resonant(i) && id.response.valid[i])
                .map(|i| {
                    let a = id.response.amplitude[i];
                    (0.75 * a * a, model.inertia * id.modal.stiffness[i])
                })
                .filter(|(x, y)| x.is_finite() && y.is_finite())
        })
        .collect();
    if points.len() < 10 {
        return None;
    }
    let m = points.len() as f64;
    let (sx, sy) = points
        .iter()
        .fold((0.0, 0.0), |(a, b), (x, y)| (a + x, b + y));
    let (mx, my) = (sx / m, sy / m);
    let (sxx, sxy) = points.iter().fold((0.0, 0.0), |(a, b), (x, y)| {
        (a + (x - mx) * (x - mx), b + (x - mx) * (y - my))
    });
    let k3 = sxy / sxx;
    let k = my - k3 * mx;
    (sxx > 0.0 && k3.is_finite() && k3 != 0.0 && k > 0.0).then_some((k, k3))
}

/// The cubic term of a joint without clearance that changes its stiffness by 10 % at the
/// largest measured amplitude: the start where the backbone does not give one.
fn generic_smooth_cubic(model: &RigModel, id: &Identification) -> f64 {
    let a = largest_amplitude(id);
    0.1 * model.stiffness / (a * a)
}

/// The cubic term that adds 10 % of k at one half-gap of penetration (N m/rad³): the
/// hardening's start where the backbone does not show one.
fn generic_cubic(model: &RigModel) -> f64 {
    let half = (0.5 * model.clearance).max(1e-6);
    0.1 * model.stiffness / (half * half)
}

/// [`cubic_from_backbone`] where the search should start a hardening from it. With the
/// waveform domain scored (`waveform`), only where the backbone shows a hardening: k3 of at
/// least an eighth of the generic start (the scan's lower end). A sweep that maps too
/// little of the skeleton (the paper's one chirp) puts a hardening into the contact
/// stiffness, and its least squares gives a k3 tens of times too small; the scan never
/// reaches the truth from there (and from the stiff contact it implies), while from the
/// generic start on the unbent model it does: on the paper's rig the waveform's detection
/// limit fell from 1e7 to 5e6 N m/rad³ (README). Without the waveform a hardening on one
/// chirp cannot be named either way, and the search is as it was.
pub(super) fn backbone_hardening(
    model: &RigModel,
    id: &Identification,
    waveform: bool,
) -> Option<(f64, f64)> {
    cubic_from_backbone(model, id).filter(|&(_, k3)| !waveform || k3 >= generic_cubic(model) / 8.0)
}

/// The contact stiffness and hardening the measured backbone asks for behind `model`'s
/// clearance: the least squares of J·(ω0² + C) = k·r(A) + k3·c3(A) over the samples at
/// resonance, with r the dead zone's exact-orbit stiffness ratio at `model`'s half-gap and
/// c3 the first harmonic of a cubic penetration spring (its describing function). `None`
/// when the backbone does not rise faster than the dead zone alone explains.
pub(super) fn cubic_from_backbone(model: &RigModel, id: &Identification) -> Option<(f64, f64)> {
    let delta = 0.5 * model.clearance;
    if delta <= 0.0 {
        return None;
    }
    let n = id.used.len().min(id.response.len());
    let (mut s11, mut s13, mut s33, mut s1y, mut s3y) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for i in (0..n).filter(|&i| id.resonant(i)) {
        let a = id.response.amplitude[i];
        let r = crate::fit::dead_zone_orbit_ratio(delta, a);
        if r <= 0.0 {
            continue;
        }
        let c = cubic_describing(delta, a);
        let y = model.inertia * (id.modal.stiffness[i] + model.gravity_stiffness);
        s11 += r * r;
        s13 += r * c;
        s33 += c * c;
        s1y += r * y;
        s3y += c * y;
    }
    let det = s11 * s33 - s13 * s13;
    if det <= 1e-12 * s11 * s33 || !det.is_finite() {
        return None;
    }
    let k = (s33 * s1y - s13 * s3y) / det;
    let k3 = (s11 * s3y - s13 * s1y) / det;
    (k3.is_finite() && k3 > 0.0 && k > 0.0).then_some((k, k3))
}

/// First-harmonic stiffness of a unit cubic penetration spring, sgn(x)·(|x| − δ)³ past a
/// half-gap δ, at amplitude A: (4/(πA)) ∫ (A cos θ − δ)³ cos θ dθ over |θ| < acos(δ/A)/…
/// (midpoint rule, 64 points).
pub(super) fn cubic_describing(delta: f64, a: f64) -> f64 {
    if a <= delta {
        return 0.0;
    }
    let top = (delta / a).acos();
    let m = 64;
    let h = top / m as f64;
    let sum: f64 = (0..m)
        .map(|j| {
            let t = (j as f64 + 0.5) * h;
            (a * t.cos() - delta).powi(3) * t.cos()
        })
        .sum();
    4.0 / (std::f64::consts::PI * a) * sum * h
}

/// Minimises `f` from the initial `simplex` (n + 1 points of any dimension ≥ n) by Nelder
/// and Mead's method (standard coefficients), for at most `budget` evaluations or until the
/// simplex's values agree within `tol`. Returns the best point and its value.
pub fn nelder_mead(
    f: &mut impl FnMut(&[f64]) -> f64,
    simplex: Vec<Vec<f64>>,
    budget: usize,
    tol: f64,
) -> (Vec<f64>, f64) {
    let mut pts: Vec<(Vec<f64>, f64)> = simplex
        .into_iter()
        .map(|x| {
            let v = f(&x);
            (x, v)
        })
        .collect();
    let mut used = pts.len();
    let dim = pts[0].0.len();
    let combine = |a: &[f64], b: &[f64], t: f64| -> Vec<f64> {
        a.iter().zip(b).map(|(a, b)| a + t * (b - a)).collect()
    };
    while used < budget {
        pts.sort_by(|a, b| a.1.total_cmp(&b.1));
        let (lo, hi) = (pts[0].1, pts[pts.len() - 1].1);
        if (hi - lo).abs() <= tol * lo.abs().max(1e-12) {
            break;
        }
        let n = pts.len() - 1;
        let centroid: Vec<f64> = (0..dim)
            .map(|d| pts[..n].iter().map(|p| p.0[d]).sum::<f64>() / n as f64)
            .collect();
        let worst = pts[n].clone();
        let reflected = combine(&centroid, &worst.0, -1.0);
        let fr = f(&reflected);
        used += 1;
        if fr < pts[0].1 {
            let expanded = combine(&centroid, &worst.0, -2.0);
            let fe = f(&expanded);
            used += 1;
            pts[n] = if fe < fr {
                (expanded, fe)
            } else {
                (reflected, fr)
            };
        } else if fr < pts[n - 1].1 {
            pts[n] = (reflected, fr);
        } else {
            let contracted = combine(&centroid, &worst.0, 0.5);
            let fc = f(&contracted);
            used += 1;
            if fc < worst.1 {
                pts[n] = (contracted, fc);
            } else {
                // Shrink towards the best point.
                let best = pts[0].0.clone();
                for p in pts.iter_mut().skip(1) {
                    p.0 = combine(&best, &p.0, 0.5);
                    p.1 = f(&p.0);
                    used += 1;
                }
            }
        }
    }
    pts.sort_by(|a, b| a.1.total_cmp(&b.1));
    pts.swap_remove(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::Backend;
    use crate::identify::{Identifier, IdentifyOptions};
    use crate::rig::{structure_levels, structure_mode};
    use crate::track::Method;

    #[test]
    fn a_force_models_mass_coordinate_moves_every_force_with_it() {
        // Moving the mass alone must keep the mode's frequency, damping ratio and the
        // joint's strength relative to it: only the response to the force scales.
        let mut base = structure_mode();
        base.set_effect(EffectKind::Microslip, Some(2.0));
        let effects = vec![
            (EffectKind::CubicStiffness, -2e5),
            (EffectKind::CoulombFriction, 0.05),
            (EffectKind::SensorDelay, 0.004),
            (EffectKind::Microslip, 2.0),
        ];
        let coords = Coordinates {
            base: &base,
            inertia: false,
            effects,
            time_alone: false,
        };
        let x0 = coords.origin();
        let mut x1 = x0.clone();
        x1[4] = 0.3;
        let (a, b) = (coords.model(&x0), coords.model(&x1));
        let per_mass = |m: &RigModel, v: f64| v / m.inertia;
        assert!((b.inertia / a.inertia - 0.3f64.exp()).abs() < 1e-12);
        for (va, vb) in [
            (a.stiffness, b.stiffness),
            (a.damping, b.damping),
            (
                a.effects.get(EffectKind::CubicStiffness).unwrap(),
                b.effects.get(EffectKind::CubicStiffness).unwrap(),
            ),
            (
                a.effects.get(EffectKind::CoulombFriction).unwrap(),
                b.effects.get(EffectKind::CoulombFriction).unwrap(),
            ),
            (
                a.effects.get(EffectKind::Microslip).unwrap(),
                b.effects.get(EffectKind::Microslip).unwrap(),
            ),
            (
                a.effects.microslip.unwrap().joint_stiffness,
                b.effects.microslip.unwrap().joint_stiffness,
            ),
        ] {
            assert!((per_mass(&a, va) / per_mass(&b, vb) - 1.0).abs() < 1e-12);
        }
        // A delay is no force; the base-motion rig's mass (when fitted) moves alone.
        assert_eq!(
            a.effects.get(EffectKind::SensorDelay),
            b.effects.get(EffectKind::SensorDelay)
        );
        let rig = RigModel::paper();
        let coords = Coordinates {
            base: &rig,
            inertia: true,
            effects: Vec::new(),
            time_alone: false,
        };
        let mut x = coords.origin();
        x[4] = 0.3;
        let moved = coords.model(&x);
        assert_eq!(moved.stiffness, rig.stiffness);
        assert!((moved.inertia / rig.inertia - 0.3f64.exp()).abs() < 1e-12);
    }

    #[test]
    fn a_cubic_terms_limit_has_a_coordinate_of_its_own_and_is_no_force() {
        let mut base = structure_mode();
        base.set_effect(EffectKind::CubicStiffness, Some(-2e5));
        base.effects.set_cubic_limit(4e-3);
        let coords = Coordinates {
            base: &base,
            inertia: true,
            effects: vec![(EffectKind::CubicStiffness, -2e5)],
            time_alone: false,
        };
        let x0 = coords.origin();
        assert_eq!(x0.len(), coords.own() + 2);
        assert_eq!(
            coords.model(&x0).effects.cubic_stiffness,
            base.effects.cubic_stiffness
        );
        // Its coordinate moves the limit by its logarithm, and nothing else.
        let mut x = x0.clone();
        x[coords.own() + 1] = 0.5;
        let p = coords.model(&x).effects.cubic_stiffness.unwrap();
        assert!((p.limit / 4e-3 - 0.5f64.exp()).abs() < 1e-12);
        assert_eq!(p.k3, -2e5);
        // The mass coordinate scales k3 (a force) but not the limit (a displacement).
        let mut x = x0.clone();
        x[4] = 0.3;
        let p = coords.model(&x).effects.cubic_stiffness.unwrap();
        assert!((p.k3 / -2e5 - 0.3f64.exp()).abs() < 1e-12);
        assert_eq!(p.limit, 4e-3);
        // A cubic term without a limit has no such coordinate.
        let mut unlimited = base.clone();
        unlimited.effects.set_cubic_limit(0.0);
        let coords = Coordinates {
            base: &unlimited,
            ..coords
        };
        assert_eq!(coords.origin().len(), coords.own() + 1);
    }

    #[test]
    fn a_fine_population_has_two_coordinates_of_its_own_and_stays_within_the_stiffness() {
        let mut base = structure_mode();
        base.set_effect(EffectKind::Microslip, Some(2.0));
        base.effects.set_fine(0.01 * base.stiffness, 3e-3);
        // A spread the logistic map gives back exactly (a full one starts at 0.95).
        base.effects.set_spread(0.5);
        // The microslip first, so that the cubic term's coordinate follows the fine ones.
        let coords = Coordinates {
            base: &base,
            inertia: false,
            effects: vec![
                (EffectKind::Microslip, 2.0),
                (EffectKind::CubicStiffness, -2e5),
            ],
            time_alone: false,
        };
        let x0 = coords.origin();
        // Own (5), the slip force, joint stiffness, spread, the fine pair, the cubic term.
        assert_eq!(x0.len(), coords.own() + 6);
        let m0 = coords.model(&x0);
        assert_eq!(m0.effects.microslip, base.effects.microslip);
        assert_eq!(m0.effects.get(EffectKind::CubicStiffness), Some(-2e5));
        // Each fine coordinate moves its parameter by its logarithm, and nothing else.
        let at = coords.own() + 3;
        for (d, stiff) in [(0, true), (1, false)] {
            let mut x = x0.clone();
            x[at + d] = 0.5;
            let m = coords.model(&x);
            let (p, q) = (m.effects.microslip.unwrap(), m0.effects.microslip.unwrap());
            let (moved, kept) = if stiff {
                (
                    (p.fine_stiffness, q.fine_stiffness),
                    (p.fine_slip, q.fine_slip),
                )
            } else {
                (
                    (p.fine_slip, q.fine_slip),
                    (p.fine_stiffness, q.fine_stiffness),
                )
            };
            assert!((moved.0 / moved.1 - 0.5f64.exp()).abs() < 1e-12);
            assert_eq!(kept.0, kept.1);
            assert_eq!(p.joint_stiffness, q.joint_stiffness);
            assert_eq!(m.effects.get(EffectKind::CubicStiffness), Some(-2e5));
        }
        // The mass coordinate carries the fine population's stiffness with it.
        let mut x = x0.clone();
        x[4] = 0.3;
        let m = coords.model(&x);
        let ratio = m.effects.microslip.unwrap().fine_stiffness
            / m0.effects.microslip.unwrap().fine_stiffness;
        assert!((ratio - 0.3f64.exp()).abs() < 1e-12);
        // Both populations pushed past the stiffness: shrunk together, both left, and the
        // model validates.
        let mut x = x0.clone();
        x[coords.own() + 1] = 3.0; // the joint to 20 times its start (2·k)
        x[at] = 3.0;
        let m = coords.model(&x);
        let p = m.effects.microslip.unwrap();
        assert!(p.joint_stiffness + p.fine_stiffness <= m.stiffness);
        assert!(p.fine_stiffness > 0.0 && p.has_fine());
        m.validate().unwrap();
    }

    /// The force self-check's structure with a cubic term k3 (N/m³ per kg).
    fn softening(k3: f64) -> RigModel {
        let mut m = structure_mode();
        m.set_effect(EffectKind::CubicStiffness, Some(k3));
        m
    }

    /// `--refit-effects`: a nominal model whose cubic term is 2.5 times the truth's. The
    /// ordinary baseline holds the term and bends the mode's own parameters around it; the
    /// baseline with the model's effects refitted finds the truth's term and fits better.
    #[test]
    fn the_baseline_refits_the_models_own_effects_only_when_asked() {
        let k3 = -2.0e5;
        let truth = softening(k3);
        let (options, backend) = (IdentifyOptions::default(), Backend::cpu());
        let identifier = Identifier {
            options: &options,
            backend: &backend,
        };
        let runs = structure_levels(&truth, &[0, 2, 3], 5);
        let reference =
            Reference::together(&[&runs[0], &runs[2]], &[&runs[1]], identifier).unwrap();
        let mut nominal = truth.clone();
        nominal.set_effect(EffectKind::CubicStiffness, Some(2.5 * k3));
        assert_eq!(
            own_effects(&nominal),
            [(EffectKind::CubicStiffness, 2.5 * k3)]
        );
        assert!(own_effects(&structure_mode()).is_empty());
        let fitted = |refit_effects| {
            let opt = SearchOptions {
                baseline_evaluations: 100,
                refit_effects,
                ..SearchOptions::default()
            };
            refit_baseline(&reference, &nominal, &opt)
        };
        let (held, refitted) = (fitted(false), fitted(true));
        let k3_of = |f: &Fitted| f.model.effects.get(EffectKind::CubicStiffness).unwrap();
        println!(
            "k3: held {:.4e} (fit gap {:.4}), refitted {:.4e} (fit gap {:.4}), truth {k3:.4e} (fit gap {:.4})",
            k3_of(&held),
            held.score.fit,
            k3_of(&refitted),
            refitted.score.fit,
            reference.score(&truth).fit
        );
        assert_eq!(k3_of(&held), 2.5 * k3);
        assert!((k3_of(&refitted) / k3 - 1.0).abs() < 0.25);
        assert!(refitted.score.fit < 0.8 * held.score.fit);
    }

    #[test]
    fn a_joints_cubic_term_starts_near_the_truth_from_the_fitted_levels_backbones_pooled() {
        // The force self-check's structure softening by about 4 % at the top level, its
        // levels 1 and 3 as the fits see them.
        let k3 = -2.0e5;
        let truth = softening(k3);
        let (options, backend) = (IdentifyOptions::default(), Backend::cpu());
        let identifier = Identifier {
            options: &options,
            backend: &backend,
        };
        let ids: Vec<Identification> = structure_levels(&truth, &[0, 2], 3)
            .iter()
            .map(|run| identifier.identify(run, Method::Wavelet).unwrap())
            .collect();
        let refs: Vec<&Identification> = ids.iter().collect();
        let model = structure_mode();
        let pooled = start_for(EffectKind::CubicStiffness, &model, &refs, true);
        let first = start_for(EffectKind::CubicStiffness, &model, &refs[..1], true);
        println!("k3 start: pooled {pooled:.4e}, first level alone {first:.4e}, truth {k3:.4e}");
        assert!((pooled / k3 - 1.0).abs() < 0.3, "{pooled}");
        // The lowest level's backbone barely bends: alone it starts the scan further off.
        assert!(
            (pooled - k3).abs() < (first - k3).abs(),
            "{pooled} vs {first}"
        );
    }
}
