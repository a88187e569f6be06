//! The rig as skelid's own checks simulate it: the paper's standard drives (its chirp, and a
//! two-level sweep), the magnitude each effect of the vocabulary takes when it is present,
//! and how a simulated rig becomes a campaign run carrying its truth (`true_*` attributes,
//! the whole model as TOML). The demo campaign, the gap's self-check and `skelid validate`
//! draw their runs from here.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

use crate::campaign::{Attr, RunData};
use crate::model::{EffectKind, RigModel};
use crate::run::{Quantity, RunKind};
use crate::simulate::{simulate, Drive, Excitation, Rolloff, SimOutput, SimSettings};

/// Encoder noise of simulated rigs (rad, std), about a 16-bit encoder's least count.
pub const ENCODER_NOISE: f64 = 2e-5;

/// The paper's chirp: 0 → 12 Hz in 30 s, amplitude falling at high frequency (servo roll-off).
pub fn paper_chirp() -> Excitation {
    paper_chirp_at(PAPER_LEVEL)
}

/// The peak base angle of the paper's chirp (rad).
pub const PAPER_LEVEL: f64 = 0.04;

/// [`paper_chirp`] at another peak base angle `level` (rad).
pub fn paper_chirp_at(level: f64) -> Excitation {
    Excitation::Chirp {
        f0: 0.0,
        f1: 12.0,
        duration: 30.0,
        amplitude: level,
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
    two_level_chirp_at(PAPER_LEVEL)
}

/// One of [`two_level_chirp`]'s sweeps alone, at `level` (rad): 3 to 9 Hz in 15 s at the
/// paper's rate, faded in and out over a second (a run of its own, as a bench records
/// each level).
pub fn level_sweep_at(level: f64) -> Excitation {
    let fs = 1000.0;
    let half = 15.0;
    let sweep = Excitation::Chirp {
        f0: 3.0,
        f1: 9.0,
        duration: half,
        amplitude: level,
        rolloff: Some(Rolloff {
            corner_hz: 1.8,
            order: 2,
        }),
    };
    let taper = |u: f64| 0.5 - 0.5 * (std::f64::consts::PI * u.clamp(0.0, 1.0)).cos();
    let samples = (0..(half * fs) as usize)
        .map(|i| {
            let t = i as f64 / fs;
            sweep.eval(t).v * taper(t) * taper(half - t)
        })
        .collect();
    Excitation::sampled(samples, fs)
}

/// [`two_level_chirp`] whose first level is `level` (rad; the paper's [`PAPER_LEVEL`]), the second
/// [`SECOND_LEVEL`] times it.
pub fn two_level_chirp_at(level: f64) -> Excitation {
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
    let (a, b) = (sweep(level), sweep(level * SECOND_LEVEL));
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
        // With the joint stiffness at its default share (a tenth of the rig's 15 000 N m/rad)
        // the joint slips through within the contact's first 7 mrad of deflection.
        EffectKind::Microslip => 5.0,
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
        Drive::Free { .. } | Drive::Released { .. } => (RunKind::Free, None, None),
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

/// How a test bench measures a paper-like rig besides its encoders' resolution: noise
/// before and after the encoders, DC offsets, and the `gravity_stiffness` attribute it
/// writes down.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Chain {
    /// White noise on each channel before the encoders quantise it (rad, std).
    pub noise: f64,
    /// White noise on each channel after the encoders, from the acquisition chain (rad,
    /// std): it blurs the encoders' steps.
    pub acquisition_noise: f64,
    /// DC offsets of the input and output channels (rad).
    pub offsets: (f64, f64),
    /// The `gravity_stiffness` attribute the run carries (1/s²; the truth, perturbed).
    pub gravity_attribute: f64,
    /// The `zero_tolerance` attribute the run carries when positive: how far apart the
    /// bench knows its encoders' zeros may be (rad).
    pub zero_tolerance: f64,
}

impl Chain {
    /// Encoders with white `noise` (rad, std) before them and nothing after: no acquisition
    /// noise, no offsets, no zero tolerance; the run carries `gravity_attribute` (1/s²).
    pub fn encoders(noise: f64, gravity_attribute: f64) -> Chain {
        Chain {
            noise,
            acquisition_noise: 0.0,
            offsets: (0.0, 0.0),
            gravity_attribute,
            zero_tolerance: 0.0,
        }
    }
}

/// How far apart the zeros of a random rig's two encoders may be (rad): each is zeroed to
/// ±2e-4 rad.
pub const RANDOM_ZERO_TOLERANCE: f64 = 4e-4;

/// A paper-like rig drawn at random over issue 20's ranges, with its measurement chain.
#[derive(Debug, Clone)]
pub struct RandomRig {
    /// The truth: the joint, and its encoders as the `quantization` effect.
    pub model: RigModel,
    /// Encoder resolution (bit/rev).
    pub bits: u32,
    /// Peak base angle of the paper's chirp (rad).
    pub amplitude: f64,
    /// Noise, offsets and the gravity attribute.
    pub chain: Chain,
}

/// Draws a rig over issue 20's ranges: gravity stiffness C 0.5–2 1/s², contact frequency
/// 9.7–11.4 Hz, total clearance 1.3–1.7°, viscous damping 10–21 N m s/rad, the paper's
/// chirp at 0.032–0.048 rad, encoders of 17–20 bit/rev on both channels with DC offsets up
/// to ±2e-4 rad (and a `zero_tolerance` attribute that says so) and white noise of 0.1–0.5
/// of their step, and a `gravity_stiffness` attribute ±10 % off the truth. No acquisition
/// noise after the encoders.
///
/// `between` makes its own draws after the joint's and before the chain's, and its result
/// is returned beside the rig: `skelid validate` draws its effect's size there, as it always
/// has, so that a seed gives the rigs it gave before this function was shared.
pub fn random_rig<T>(rng: &mut StdRng, between: impl FnOnce(&mut StdRng) -> T) -> (RandomRig, T) {
    let f_contact = rng.random_range(9.7..11.4);
    let gravity = rng.random_range(0.5..2.0);
    let bits = rng.random_range(17..=20u32);
    // The paper rig's inertia: the effects' magnitudes of [`effect_value`] are torques for it.
    let inertia = RigModel::paper().inertia;
    let mut model = RigModel {
        kind: crate::model::ModelKind::BaseMotion,
        band: None,
        inertia,
        stiffness: inertia * (std::f64::consts::TAU * f_contact).powi(2),
        damping: rng.random_range(10.0..21.0),
        clearance: rng.random_range(1.3f64..1.7).to_radians(),
        gravity_stiffness: gravity,
        effects: Default::default(),
    };
    let step = encoder_step(bits);
    model.effects.set(EffectKind::Quantization, Some(step));
    let drawn = between(rng);
    // The order of the draws is `skelid validate`'s since its first version.
    let amplitude = rng.random_range(0.032..0.048);
    let offsets = (rng.random_range(-2e-4..2e-4), rng.random_range(-2e-4..2e-4));
    let noise = step * rng.random_range(0.1..0.5);
    let gravity_attribute = gravity * rng.random_range(0.9..1.1);
    let rig = RandomRig {
        model,
        bits,
        amplitude,
        chain: Chain {
            noise,
            acquisition_noise: 0.0,
            offsets,
            gravity_attribute,
            zero_tolerance: RANDOM_ZERO_TOLERANCE,
        },
    };
    (rig, drawn)
}

/// The step of an encoder of `bits` bit/rev (rad).
pub fn encoder_step(bits: u32) -> f64 {
    std::f64::consts::TAU / f64::from(1u32 << bits)
}

/// Simulates `model` under `drive` (30 s at 1 kHz) and measures it through `chain`: noise
/// before the encoders (the model's `quantization`), acquisition noise after them, the
/// offsets, and the chain's `gravity_stiffness` and `zero_tolerance` attributes.
pub fn measure(
    path: &str,
    model: &RigModel,
    drive: &Drive,
    chain: &Chain,
    seed: u64,
    description: &str,
) -> RunData {
    measure_over(
        path,
        model,
        drive,
        chain,
        seed,
        description,
        SimSettings::default().duration,
    )
}

/// [`measure`] over `duration` seconds.
pub fn measure_over(
    path: &str,
    model: &RigModel,
    drive: &Drive,
    chain: &Chain,
    seed: u64,
    description: &str,
    duration: f64,
) -> RunData {
    let settings = SimSettings {
        output_noise: chain.noise,
        input_noise: chain.noise,
        seed,
        duration,
        ..SimSettings::default()
    };
    let sim = simulate(model, drive, &settings);
    let mut data = run_data(path, model, drive, sim, settings.sample_rate, description);
    for (name, value) in &mut data.attrs {
        if name == "gravity_stiffness" {
            *value = Attr::Num(chain.gravity_attribute);
        }
    }
    if chain.zero_tolerance > 0.0 {
        data.attrs
            .push(("zero_tolerance".into(), Attr::Num(chain.zero_tolerance)));
    }
    // The acquisition noise has its own stream: the simulation's stays as it was.
    let mut rng = StdRng::seed_from_u64(seed ^ 0x05ee_dac9_u64);
    let blur = Normal::new(0.0, chain.acquisition_noise.max(0.0)).expect("a finite std");
    let mut add = |x: &mut [f64], offset: f64| {
        for v in x.iter_mut() {
            *v += offset;
            if chain.acquisition_noise > 0.0 {
                *v += blur.sample(&mut rng);
            }
        }
    };
    if let Some(x) = &mut data.input {
        add(x, chain.offsets.0);
    }
    add(&mut data.output, chain.offsets.1);
    data
}

/// One mode of a structure like the F-16's wing torsion, scaled to a 1 kg modal mass: 7.3 Hz,
/// 0.5 % of critical damping, no clearance (`kind = "force"`). The force self-check's
/// nominal model and, with an effect, its truths.
pub fn structure_mode() -> RigModel {
    let k = (std::f64::consts::TAU * 7.3_f64).powi(2);
    RigModel {
        kind: crate::model::ModelKind::Force,
        band: None,
        inertia: 1.0,
        stiffness: k,
        damping: 2.0 * 0.005 * k.sqrt(),
        clearance: 0.0,
        gravity_stiffness: 0.0,
        effects: Default::default(),
    }
}

/// The parameter each effect takes in a [`structure_mode`] where it is present (the force
/// self-check's scale of 1); `None` for the effects a force model has no use for.
pub fn structure_effect_value(kind: EffectKind) -> Option<f64> {
    Some(match kind {
        // A third of the viscous damping's force at the middle level's resonance.
        EffectKind::CoulombFriction => 0.05,
        // Softening by about 4 % in frequency at the top level's resonant amplitude.
        EffectKind::CubicStiffness => -2.0e5,
        EffectKind::SensorDelay => 0.004,
        // An accelerometer's converter step (m/s²): its noise, q/√12, about the 1 %
        // accelerometer noise at the lowest level.
        EffectKind::Quantization => 0.5,
        // A tenth of the stiffness in the joint, half of it slipping at 10 mm.
        EffectKind::Microslip => 0.1 * structure_mode().stiffness * 0.01,
        _ => return None,
    })
}

/// Force levels (N) of the structure's sweeps: the fitted and held-out runs of the force
/// self-check alternate over them.
pub const STRUCTURE_LEVELS: [f64; 4] = [0.2, 0.4, 0.7, 1.0];

/// The sweep a [`structure_mode`] is driven by: a sine sweep down from 9 to 5.5 Hz in
/// 35 s (0.1 Hz/s) of `level` N, as a shaker does a ground-vibration test.
pub fn structure_sweep(level: f64) -> Excitation {
    Excitation::Chirp {
        f0: 9.0,
        f1: 5.5,
        duration: 35.0,
        amplitude: level,
        rolloff: None,
    }
}

/// `model` driven by [`structure_sweep`]`(level)` as a run of a ground-vibration test:
/// 400 Hz, the force with 1 % noise, the response an accelerometer (m/s²) with white
/// noise of `noise` of its RMS; no `inertia` attribute (a shaker test does not know its
/// modal mass).
pub fn structure_run(path: &str, model: &RigModel, level: f64, noise: f64, seed: u64) -> RunData {
    let fs = 400.0;
    let drive = Drive::Force(structure_sweep(level));
    let settings = SimSettings {
        sample_rate: fs,
        duration: 35.0,
        substeps: 4,
        output_noise: 0.0,
        input_noise: 0.01 * level,
        seed,
    };
    // The accelerometer's converter quantises what it records, noise and all: the model's
    // quantisation step is in m/s² and applies to the acceleration, not to the motion.
    let step = model.effects.get(EffectKind::Quantization);
    let mut unquantised = model.clone();
    unquantised.effects.set(EffectKind::Quantization, None);
    let sim = simulate(&unquantised, &drive, &settings);
    let d = crate::simulate::derivative_4th;
    let mut acc = d(&d(&sim.output, fs), fs);
    let rms = (acc.iter().map(|a| a * a).sum::<f64>() / acc.len() as f64).sqrt();
    let mut rng = StdRng::seed_from_u64(seed ^ 0x5eed);
    let normal = Normal::new(0.0, noise * rms).expect("a finite noise level");
    acc.iter_mut().for_each(|a| *a += normal.sample(&mut rng));
    if let Some(q) = step.filter(|q| *q > 0.0) {
        acc.iter_mut().for_each(|a| *a = (*a / q).round() * q);
    }
    let description = format!("sine sweep down 9 -> 5.5 Hz at 0.1 Hz/s, {level} N");
    let mut data = run_data(path, model, &drive, sim, fs, &description);
    data.output = acc;
    data.output_quantity = Quantity::Acceleration;
    data.attrs.retain(|(k, _)| k != "inertia" && k != "units");
    data.attrs
        .push(("units".into(), Attr::Text("input N, output m/s^2".into())));
    data
}

/// The [`structure_run`]s of `model` at the levels `levels` (indices into
/// [`STRUCTURE_LEVELS`]), named `/gvt/level_{index + 1}`, with 1 % response noise and
/// seeds `seed + index`: the runs the gap's tests fit and hold out.
pub fn structure_levels(model: &RigModel, levels: &[usize], seed: u64) -> Vec<crate::run::Run> {
    levels
        .iter()
        .map(|&i| {
            let path = format!("/gvt/level_{}", i + 1);
            structure_run(&path, model, STRUCTURE_LEVELS[i], 0.01, seed + i as u64).into_run()
        })
        .collect()
}

/// `model` (a [`structure_mode`] with its effects) ringing down from `offset` (m) after an
/// impact, as a hammer test records it: 1 s at rest, the impact as a release from `offset`,
/// 12 s of decay, 400 Hz, an accelerometer (m/s²) with white noise of `noise` of the
/// decay's RMS; a free-decay run (`kind = free`, no input, no inertia).
pub fn structure_decay(
    path: &str,
    model: &RigModel,
    offset: f64,
    noise: f64,
    seed: u64,
) -> RunData {
    let fs = 400.0;
    let drive = Drive::Free {
        initial_offset: offset,
    };
    let settings = SimSettings {
        sample_rate: fs,
        duration: 12.0,
        substeps: 4,
        output_noise: 0.0,
        input_noise: 0.0,
        seed,
    };
    let sim = simulate(model, &drive, &settings);
    let d = crate::simulate::derivative_4th;
    let decay = d(&d(&sim.output, fs), fs);
    let rms = (decay.iter().map(|a| a * a).sum::<f64>() / decay.len() as f64).sqrt();
    let mut acc = vec![0.0; fs as usize];
    acc.extend(decay);
    let mut rng = StdRng::seed_from_u64(seed ^ 0x5eed);
    let normal = Normal::new(0.0, noise * rms).expect("a finite noise level");
    acc.iter_mut().for_each(|a| *a += normal.sample(&mut rng));
    let description = format!("free decay from {offset} m after an impact");
    let mut data = run_data(path, model, &drive, sim, fs, &description);
    data.output = acc;
    data.output_quantity = Quantity::Acceleration;
    data.attrs.retain(|(k, _)| k != "inertia" && k != "units");
    data.attrs
        .push(("units".into(), Attr::Text("output m/s^2".into())));
    data
}

/// The tests' plain hammer record: the linear [`structure_mode`] ringing down from 20 mm
/// after a hit 1 s in ([`structure_decay`]), noise-free.
#[cfg(test)]
pub(crate) fn plain_decay() -> crate::run::Run {
    structure_decay("/hammer/acc1", &structure_mode(), 0.02, 0.0, 1).into_run()
}
