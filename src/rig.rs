//! The rig as skelid's own checks simulate it: the paper's standard drives (its chirp, and a
//! two-level sweep), the magnitude each effect of the vocabulary takes when it is present,
//! and how a simulated rig becomes a campaign run carrying its truth (`true_*` attributes,
//! the whole model as TOML). The demo campaign, the gap's self-check and `skelid validate`
//! draw their runs from here.

use crate::campaign::{Attr, RunData};
use crate::model::{EffectKind, RigModel};
use crate::run::{Quantity, RunKind};
use crate::simulate::{simulate, Drive, Excitation, Rolloff, SimOutput, SimSettings};

/// Encoder noise of simulated rigs (rad, std), about a 16-bit encoder's least count.
pub const ENCODER_NOISE: f64 = 2e-5;

/// The paper's chirp: 0 → 12 Hz in 30 s, amplitude falling at high frequency (servo roll-off).
pub fn paper_chirp() -> Excitation {
    Excitation::Chirp {
        f0: 0.0,
        f1: 12.0,
        duration: 30.0,
        amplitude: 0.04,
        rolloff: Some(Rolloff {
            corner_hz: 1.8,
            order: 2,
        }),
    }
}

/// The sweep a rig is run through twice in one 30 s record: the paper's chirp rate
/// (0.4 Hz/s) over the band of the contact resonance, 3 to 9 Hz in 15 s, once at the
/// paper's level and once at [`SECOND_LEVEL`] times it. One sweep maps only the part of the
/// skeleton its level reaches (the paper's closing caveat); two levels show whether the
/// backbone keeps rising with amplitude, which one level cannot tell from a stiffer contact
/// behind a wider clearance. Started at 3 Hz, the first sweep leaves the link on the low
/// branch (it never touches, like the paper's record after 16.25 s); the second jumps onto
/// the resonant branch and rides it up to about 2.7 times the half-gap.
pub fn two_level_chirp() -> Excitation {
    let fs = 1000.0;
    let half = 15.0;
    let sweep = |amplitude: f64| Excitation::Chirp {
        f0: 3.0,
        f1: 9.0,
        duration: half,
        amplitude,
        rolloff: Some(Rolloff {
            corner_hz: 1.8,
            order: 2,
        }),
    };
    let (a, b) = (sweep(0.04), sweep(0.04 * SECOND_LEVEL));
    // Each sweep fades in and out over a second: the base starts and stops smoothly rather
    // than with a step of its velocity at 3 Hz.
    let taper = |u: f64| 0.5 - 0.5 * (std::f64::consts::PI * u.clamp(0.0, 1.0)).cos();
    let n = (2.0 * half * fs) as usize;
    let samples = (0..n)
        .map(|i| {
            let t = i as f64 / fs;
            let (sweep, t) = if t < half { (&a, t) } else { (&b, t - half) };
            sweep.eval(t).v * taper(t) * taper(half - t)
        })
        .collect();
    Excitation::sampled(samples, fs)
}

/// The second level of [`two_level_chirp`], relative to the paper's.
pub const SECOND_LEVEL: f64 = 1.75;

/// The parameter each effect takes where it is present (the demo's variant runs, the
/// self-check's scale of 1).
pub fn effect_value(kind: EffectKind) -> f64 {
    match kind {
        EffectKind::CoulombFriction => 2.5,
        EffectKind::GravityPreload => 20.0,
        EffectKind::AsymmetricClearance => 0.004,
        EffectKind::CubicStiffness => 1.0e7,
        EffectKind::ContactDamping => 20.0,
        EffectKind::SensorDelay => 0.005,
        EffectKind::Quantization => 2.0e-4,
    }
}

/// A rig run before simulation: where it goes, what drives it, and the truth.
#[derive(Debug, Clone)]
pub struct RigCase {
    /// Run path in the archive.
    pub path: String,
    /// True model.
    pub model: RigModel,
    /// Drive.
    pub drive: Drive,
    /// Noise seed.
    pub seed: u64,
    /// Human description.
    pub description: String,
}

/// Simulates one case into a run ready to write (30 s at 1 kHz unless free decay: 5 s).
pub fn simulate_case(case: &RigCase) -> RunData {
    let duration = if matches!(case.drive, Drive::Free { .. }) {
        5.0
    } else {
        30.0
    };
    let settings = SimSettings {
        sample_rate: 1000.0,
        duration,
        substeps: 4,
        output_noise: ENCODER_NOISE,
        input_noise: if matches!(case.drive, Drive::Force(_)) {
            0.01
        } else {
            ENCODER_NOISE
        },
        seed: case.seed,
    };
    let sim = simulate(&case.model, &case.drive, &settings);
    run_data(
        &case.path,
        &case.model,
        &case.drive,
        sim,
        settings.sample_rate,
        &case.description,
    )
}

/// A simulation as a campaign run: kind and quantities from the drive, truth as attributes.
pub fn run_data(
    path: &str,
    model: &RigModel,
    drive: &Drive,
    sim: SimOutput,
    sample_rate: f64,
    description: &str,
) -> RunData {
    let (kind, input, input_quantity) = match drive {
        Drive::Base(_) => (
            RunKind::BaseMotion,
            Some(sim.input),
            Some(Quantity::Displacement),
        ),
        Drive::Force(_) => (RunKind::Force, Some(sim.input), Some(Quantity::Force)),
        Drive::Free { .. } => (RunKind::Free, None, None),
    };
    RunData {
        path: path.to_string(),
        input,
        output: sim.output,
        sample_rate,
        kind,
        input_quantity,
        output_quantity: Quantity::Displacement,
        attrs: truth_attrs(model, description, kind),
    }
}

/// `inertia`, `gravity_stiffness`, and the `true_*` attributes of a model.
pub fn truth_attrs(m: &RigModel, description: &str, kind: RunKind) -> Vec<(String, Attr)> {
    let mut a = vec![
        ("inertia".to_string(), Attr::Num(m.inertia)),
        (
            "gravity_stiffness".to_string(),
            Attr::Num(m.gravity_stiffness),
        ),
        (
            "units".to_string(),
            Attr::Text(if kind == RunKind::Force {
                "input N, output m".into()
            } else {
                "rad".into()
            }),
        ),
        (
            "excitation".to_string(),
            Attr::Text(description.to_string()),
        ),
        ("true_inertia".to_string(), Attr::Num(m.inertia)),
        ("true_stiffness".to_string(), Attr::Num(m.stiffness)),
        ("true_damping".to_string(), Attr::Num(m.damping)),
        ("true_clearance".to_string(), Attr::Num(m.clearance)),
        (
            "true_gravity_stiffness".to_string(),
            Attr::Num(m.gravity_stiffness),
        ),
        ("true_model".to_string(), Attr::Text(m.to_toml())),
    ];
    for (k, v) in m.effects.present() {
        a.push((format!("true_{}_{}", k.name(), k.param()), Attr::Num(v)));
    }
    a
}
