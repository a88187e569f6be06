//! `skelid validate`: how accurate the identification is on paper-like rigs that the demo
//! does not cover. Each rig is drawn at random over the ranges of issue 20 (gravity
//! stiffness, contact frequency, clearance, damping, the chirp's level, an encoder of 17–20
//! bit/rev with DC offsets and sub-LSB noise, a perturbed `gravity_stiffness` attribute, and
//! one effect that leaves the joint itself alone: dry friction, a sensor delay, contact
//! damping, or none), simulated, and identified blind by the skeleton (wavelet and
//! Hilbert) and by the simulation-refined identification ([`crate::refine`]). The errors
//! against the truth make the table.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::identify::Identifier;
use crate::model::{EffectKind, RigModel};
use crate::refine::{refine, Refined};
use crate::rig::{effect_value, measure, paper_chirp_at, random_rig, Chain};
use crate::simulate::Drive;
use crate::track::Method;

/// One random rig, its drive and its measurement chain.
#[derive(Debug, Clone)]
pub struct Rig {
    /// Rig number.
    pub index: usize,
    /// The truth (its `quantization` effect is the encoder).
    pub truth: RigModel,
    /// The effect besides the encoder, if any.
    pub effect: Option<EffectKind>,
    /// Peak base angle of the chirp (rad).
    pub amplitude: f64,
    /// Encoder resolution (bit/rev).
    pub bits: u32,
    /// Noise, DC offsets and the `gravity_stiffness` attribute given to the identification.
    pub chain: Chain,
    /// Noise seed.
    pub seed: u64,
}

/// The effects drawn, in turn.
const EFFECTS: [Option<EffectKind>; 4] = [
    Some(EffectKind::CoulombFriction),
    Some(EffectKind::SensorDelay),
    Some(EffectKind::ContactDamping),
    None,
];

/// `n` rigs from `seed` ([`random_rig`]), each with one effect of [`EFFECTS`] in turn at
/// 0.5–2 times its demo value.
pub fn rigs(n: usize, seed: u64) -> Vec<Rig> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..n)
        .map(|index| {
            let effect = EFFECTS[index % EFFECTS.len()];
            let (r, factor) =
                random_rig(&mut rng, |rng| effect.map(|_| rng.random_range(0.5..2.0)));
            let mut truth = r.model;
            if let (Some(e), Some(factor)) = (effect, factor) {
                truth.effects.set(e, Some(effect_value(e) * factor));
            }
            Rig {
                index,
                truth,
                effect,
                amplitude: r.amplitude,
                bits: r.bits,
                chain: r.chain,
                seed: rng.random(),
            }
        })
        .collect()
}

/// What each estimator made of one rig: relative errors of the total clearance and of
/// k/J (`None` where the estimator gave none).
#[derive(Debug, Clone)]
pub struct Outcome {
    /// The rig.
    pub rig: Rig,
    /// Skeleton, wavelet method: (clearance, k/J) relative errors.
    pub wavelet: Option<(f64, f64)>,
    /// Skeleton, Hilbert method.
    pub hilbert: Option<(f64, f64)>,
    /// Simulation-refined.
    pub refined: Option<(f64, f64)>,
    /// The refined estimate itself, or why there is none.
    pub refinement: Result<Refined, String>,
}

/// Simulates `rig` (30 s at 1 kHz under the paper's chirp at the rig's level), identifies
/// it blind with both methods (by `identifier`) and refines it with `evaluations`
/// simulations per half.
pub fn run_rig(rig: &Rig, evaluations: usize, identifier: Identifier<'_>) -> Outcome {
    let drive = Drive::Base(paper_chirp_at(rig.amplitude));
    let run = measure(
        &format!("/validate/rig_{:03}", rig.index),
        &rig.truth,
        &drive,
        &rig.chain,
        rig.seed,
        "validation rig",
    )
    .into_run();
    let k_true = rig.truth.stiffness / rig.truth.inertia;
    let c_true = rig.truth.clearance;
    let errors = |c: f64, k: f64| (c / c_true - 1.0, k / k_true - 1.0);
    let skeleton = |m: Method| {
        let id = identifier.identify(&run, m).ok()?;
        let dz = id.dead_zone?;
        Some(errors(2.0 * dz.half_gap.value, dz.stiffness.value))
    };
    let refinement = refine(&run, evaluations, identifier).map_err(|e| e.to_string());
    Outcome {
        rig: rig.clone(),
        wavelet: skeleton(Method::Wavelet),
        hilbert: skeleton(Method::Hilbert),
        refined: refinement
            .as_ref()
            .ok()
            .map(|r| errors(r.clearance.value, r.stiffness.value)),
        refinement,
    }
}

/// Median and 90th percentile of |x| (NaN for none).
pub fn median_p90(xs: &[f64]) -> (f64, f64) {
    let mut v: Vec<f64> = xs
        .iter()
        .map(|x| x.abs())
        .filter(|x| x.is_finite())
        .collect();
    if v.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| {
        let pos = q * (v.len() - 1) as f64;
        let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
        v[lo] + (v[hi] - v[lo]) * (pos - lo as f64)
    };
    (at(0.5), at(0.9))
}

/// One estimator's (clearance, k/J) errors of an outcome.
type Pick = fn(&Outcome) -> Option<(f64, f64)>;

/// The error table: per estimator, the median and 90th percentile of |error| of the
/// clearance and of k/J, and how many rigs it gave an estimate for.
pub fn table(outcomes: &[Outcome]) -> String {
    let mut t = format!(
        "{:<22} {:>8} {:>20} {:>20}\n",
        "estimate", "rigs", "clearance med / p90", "k/J med / p90"
    );
    let rows: [(&str, Pick); 3] = [
        ("skeleton, wavelet", |o| o.wavelet),
        ("skeleton, hilbert", |o| o.hilbert),
        ("refined (simulation)", |o| o.refined),
    ];
    for (name, pick) in rows {
        let got: Vec<(f64, f64)> = outcomes.iter().filter_map(pick).collect();
        let (cm, cp) = median_p90(&got.iter().map(|e| e.0).collect::<Vec<_>>());
        let (km, kp) = median_p90(&got.iter().map(|e| e.1).collect::<Vec<_>>());
        t.push_str(&format!(
            "{name:<22} {:>3} / {:<2} {:>9.2} / {:<6.2}% {:>9.2} / {:<6.2}%\n",
            got.len(),
            outcomes.len(),
            100.0 * cm,
            100.0 * cp,
            100.0 * km,
            100.0 * kp
        ));
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_against_a_sorted_list() {
        let xs: Vec<f64> = (0..=10).map(|i| -(i as f64)).collect();
        assert_eq!(median_p90(&xs), (5.0, 9.0));
        assert!(median_p90(&[]).0.is_nan());
    }

    #[test]
    fn rigs_stay_inside_the_issue_s_ranges() {
        for r in rigs(40, 7) {
            let m = &r.truth;
            let f = m.contact_frequency_hz();
            assert!((9.7..11.4).contains(&f), "{f}");
            assert!((1.3..1.7).contains(&m.clearance.to_degrees()));
            assert!((10.0..21.0).contains(&m.damping));
            assert!((0.5..2.0).contains(&m.gravity_stiffness));
            assert!((17..=20).contains(&r.bits));
            let step = m.effects.get(EffectKind::Quantization).unwrap();
            assert!(r.chain.noise < step && r.chain.offsets.0.abs() <= 2e-4);
        }
    }
}
