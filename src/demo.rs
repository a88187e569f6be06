//! The built-in demo campaign: the paper's rig under its chirp, plus one variant per effect
//! of the vocabulary, a linear joint, a force-input oscillator and a free decay. Every run
//! carries its true parameters as attributes (`true_*`, and the whole model as TOML in
//! `true_model`), so identification can be scored against them.

use crate::campaign::{Attr, RunData};
use crate::ingest::{Quantity, RunKind};
use crate::model::{EffectKind, RigModel};
use crate::simulate::{simulate, Drive, Excitation, Rolloff, SimOutput, SimSettings};

/// Encoder noise of the demo (rad, std), about a 16-bit encoder's least count.
pub const DEMO_NOISE: f64 = 2e-5;

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

/// The parameter each effect takes in the demo's variant runs.
pub fn demo_effect_value(kind: EffectKind) -> f64 {
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

/// A demo run before simulation: where it goes, what drives it, and the truth.
#[derive(Debug, Clone)]
pub struct DemoCase {
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

/// The demo campaign's cases.
pub fn cases() -> Vec<DemoCase> {
    let mut out = Vec::new();
    let mut paper = RigModel::paper();
    paper.effects.set(EffectKind::CoulombFriction, Some(2.5));
    out.push(DemoCase {
        path: "/demo/paper_rig".into(),
        model: paper,
        drive: Drive::Base(paper_chirp()),
        seed: 11,
        description:
            "paper's rig: 1.5 deg clearance, 11 Hz contact mode, viscous + Coulomb damping".into(),
    });
    for (i, kind) in EffectKind::ALL.into_iter().enumerate() {
        let mut m = RigModel::paper();
        m.effects.set(kind, Some(demo_effect_value(kind)));
        out.push(DemoCase {
            path: format!("/demo/effects/{}", kind.name()),
            model: m,
            drive: Drive::Base(paper_chirp()),
            seed: 100 + i as u64,
            description: format!("nominal rig plus {} only", kind.name()),
        });
    }
    let mut linear = RigModel::paper();
    linear.clearance = 0.0;
    out.push(DemoCase {
        path: "/demo/linear".into(),
        model: linear,
        drive: Drive::Base(paper_chirp()),
        seed: 21,
        description: "linear joint (no clearance)".into(),
    });
    out.push(DemoCase {
        path: "/demo/force_oscillator".into(),
        model: RigModel {
            inertia: 2.0,
            stiffness: 2.0 * (std::f64::consts::TAU * 5.0).powi(2),
            damping: 2.0 * 0.02 * 2.0 * std::f64::consts::TAU * 5.0,
            clearance: 0.0,
            gravity_stiffness: 0.0,
            effects: Default::default(),
        },
        drive: Drive::Force(Excitation::Chirp {
            f0: 1.0,
            f1: 10.0,
            duration: 30.0,
            amplitude: 10.0,
            rolloff: None,
        }),
        seed: 31,
        description: "force-input linear oscillator, 5 Hz, 2 % damping, sine sweep 1-10 Hz".into(),
    });
    out.push(DemoCase {
        path: "/demo/free_decay".into(),
        model: RigModel::paper(),
        drive: Drive::Free {
            initial_offset: 0.08,
        },
        seed: 41,
        description: "free decay from 0.08 rad with the paper's clearance".into(),
    });
    out
}

/// Simulates one case into a run ready to write (30 s at 1 kHz unless free decay: 5 s).
pub fn simulate_case(case: &DemoCase) -> RunData {
    let duration = if matches!(case.drive, Drive::Free { .. }) {
        5.0
    } else {
        30.0
    };
    let settings = SimSettings {
        sample_rate: 1000.0,
        duration,
        substeps: 4,
        output_noise: DEMO_NOISE,
        input_noise: if matches!(case.drive, Drive::Force(_)) {
            0.01
        } else {
            DEMO_NOISE
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
