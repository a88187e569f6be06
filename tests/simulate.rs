//! The rig simulator against physics: convergence, energy balance, stick–slip, free flight
//! inside the clearance, the direction of every effect, the force variant against the
//! analytic steady state, and a sampled (measured) input against the analytic one.

use skelid::model::{EffectKind, RigModel};
use skelid::simulate::{mechanical_energy, simulate, Drive, Excitation, Rolloff, SimSettings};

fn chirp() -> Excitation {
    skelid::rig::paper_chirp()
}

fn settings(duration: f64, substeps: usize) -> SimSettings {
    SimSettings {
        sample_rate: 1000.0,
        duration,
        substeps,
        output_noise: 0.0,
        input_noise: 0.0,
        seed: 1,
    }
}

fn with(kind: EffectKind, v: f64) -> RigModel {
    let mut m = RigModel::paper();
    m.effects.set(kind, Some(v));
    m
}

fn max_abs(x: &[f64]) -> f64 {
    x.iter().fold(0.0, |a, b| a.max(b.abs()))
}

fn mean(x: &[f64]) -> f64 {
    x.iter().sum::<f64>() / x.len() as f64
}

#[test]
fn halving_the_step_changes_the_response_by_less_than_a_millionth() {
    let mut m = RigModel::paper();
    m.effects.set(EffectKind::CoulombFriction, Some(2.5));
    let drive = Drive::Base(chirp());
    // Up to the jump-down: after it, which flank the link settles on is chaotic in any model.
    let a = simulate(&m, &drive, &settings(16.0, 2));
    let b = simulate(&m, &drive, &settings(16.0, 4));
    let c = simulate(&m, &drive, &settings(16.0, 8));
    let diff = |x: &[f64], y: &[f64]| {
        x.iter()
            .zip(y)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max)
            / max_abs(y)
    };
    let d1 = diff(&a.relative, &b.relative);
    let d2 = diff(&b.relative, &c.relative);
    println!(
        "relative motion, max change / max |z|: h -> h/2: {d1:.2e}, h/2 -> h/4: {d2:.2e}; events located: {}",
        c.events
    );
    assert!(
        d2 < 1e-6,
        "halving the step changed z by {d2:e} of its peak"
    );
    assert!(c.events > 100, "corners and stick-slip events are located");
}

#[test]
fn undamped_free_decay_conserves_energy_across_clearance_corners() {
    for clearance in [0.0, 0.0262] {
        let m = RigModel {
            damping: 0.0,
            clearance,
            ..RigModel::paper()
        };
        let sim = simulate(
            &m,
            &Drive::Free {
                initial_offset: 0.06,
            },
            &settings(10.0, 4),
        );
        let e0 = mechanical_energy(&m, 0.06, 0.0);
        // Energy from the exact relative velocity the simulator reports.
        let drift = sim
            .output
            .iter()
            .zip(&sim.relative_velocity)
            .map(|(&th, &om)| (mechanical_energy(&m, th, om) - e0).abs() / e0)
            .fold(0.0, f64::max);
        println!(
            "clearance {clearance}: max relative energy drift over 10 s = {drift:.2e} ({} events)",
            sim.events
        );
        assert!(drift < 1e-6, "energy drift {drift:e}");
    }
}

#[test]
fn large_friction_makes_the_link_stick_to_the_base() {
    let sticky = with(EffectKind::CoulombFriction, 12.0);
    let sim = simulate(&sticky, &Drive::Base(chirp()), &settings(20.0, 4));
    let stuck = sim.stuck.iter().filter(|&&s| s == 1).count();
    // Longest interval with zero relative velocity.
    let (mut run, mut longest) = (0, 0);
    for (s, v) in sim.stuck.iter().zip(&sim.relative_velocity) {
        if *s == 1 {
            assert!(v.abs() < 1e-9, "stuck but relative velocity {v}");
            run += 1;
            longest = longest.max(run);
        } else {
            run = 0;
        }
    }
    let breakaways = sim
        .stuck
        .windows(2)
        .filter(|w| w[0] == 1 && w[1] == 0)
        .count();
    println!(
        "friction 12 N m: stuck {stuck} of {} samples, longest stick {longest} ms, {breakaways} stick-to-slip transitions",
        sim.stuck.len()
    );
    assert!(stuck > sim.stuck.len() / 10 && stuck < sim.stuck.len() * 9 / 10);
    assert!(
        longest > 20 && breakaways > 10,
        "real stick-slip: intervals of both"
    );
    let free = simulate(
        &RigModel::paper(),
        &Drive::Base(chirp()),
        &settings(20.0, 4),
    );
    assert_eq!(free.stuck.iter().filter(|&&s| s == 1).count(), 0);
}

#[test]
fn inside_the_clearance_the_undamped_link_flies_freely() {
    // c = 0: between contacts nothing acts on the link, so θ is a straight line in time.
    let m = RigModel {
        damping: 0.0,
        ..RigModel::paper()
    };
    let sim = simulate(&m, &Drive::Base(chirp()), &settings(12.0, 4));
    let d = m.half_gap();
    let mut worst = 0.0f64;
    let mut n = 0;
    for i in 1..sim.output.len() - 1 {
        if sim.relative[i - 1..=i + 1]
            .iter()
            .all(|z| z.abs() < d * 0.999)
        {
            let acc = (sim.output[i + 1] - 2.0 * sim.output[i] + sim.output[i - 1]) * 1e6;
            worst = worst.max(acc.abs());
            n += 1;
        }
    }
    let in_contact = sim.relative.iter().filter(|z| z.abs() > d).count();
    println!("free flight: {n} samples inside the gap, max |θ''| there = {worst:.2e} rad/s^2; {in_contact} samples in contact");
    assert!(n > 1000 && in_contact > 1000);
    assert!(worst < 1e-6, "link accelerates inside the gap: {worst}");
}

#[test]
fn every_effect_changes_the_output_in_the_expected_direction() {
    let base = Drive::Base(chirp());
    let s = settings(16.0, 4);
    let nominal = simulate(&RigModel::paper(), &base, &s);

    // Dry friction dissipates: lower peak relative motion.
    let f = simulate(&with(EffectKind::CoulombFriction, 5.0), &base, &s);
    println!(
        "coulomb: peak |z| {:.4} vs nominal {:.4}",
        max_abs(&f.relative),
        max_abs(&nominal.relative)
    );
    assert!(max_abs(&f.relative) < 0.95 * max_abs(&nominal.relative));

    // A positive preload torque pushes the link to the positive flank.
    let p = simulate(&with(EffectKind::GravityPreload, 20.0), &base, &s);
    println!(
        "preload: mean z {:.5} vs nominal {:.5}",
        mean(&p.relative),
        mean(&nominal.relative)
    );
    assert!(mean(&p.relative) > mean(&nominal.relative) + 0.002);

    // A shifted clearance shifts the mean relative motion the same way.
    let o = simulate(&with(EffectKind::AsymmetricClearance, 0.004), &base, &s);
    let shift = mean(&o.relative) - mean(&nominal.relative);
    println!("asymmetric clearance 0.004: mean z shift {shift:.5}");
    assert!(shift > 0.002 && shift < 0.006);

    // Hardening contact: a free decay oscillates faster.
    let free = Drive::Free {
        initial_offset: 0.08,
    };
    let crossings = |x: &[f64]| {
        x.windows(2)
            .filter(|w| w[0].signum() != w[1].signum())
            .count()
    };
    let lin = simulate(&RigModel::paper(), &free, &settings(2.0, 4));
    let hard = simulate(
        &with(EffectKind::CubicStiffness, 1e7),
        &free,
        &settings(2.0, 4),
    );
    println!(
        "cubic: {} vs {} zero crossings in 2 s",
        crossings(&hard.output),
        crossings(&lin.output)
    );
    assert!(crossings(&hard.output) > crossings(&lin.output));

    // Contact damping: the free decay dies faster.
    let cd = simulate(
        &with(EffectKind::ContactDamping, 30.0),
        &free,
        &settings(2.0, 4),
    );
    let late = |x: &[f64]| max_abs(&x[1000..]);
    println!(
        "contact damping: late amplitude {:.4} vs {:.4}",
        late(&cd.output),
        late(&lin.output)
    );
    assert!(late(&cd.output) < 0.8 * late(&lin.output));

    // Sensor delay: the output is the nominal output 5 samples later.
    let dl = simulate(&with(EffectKind::SensorDelay, 0.005), &base, &s);
    let err = (5..dl.output.len())
        .map(|i| (dl.output[i] - nominal.output[i - 5]).abs())
        .fold(0.0, f64::max);
    println!("sensor delay: max |y_delayed(t) - y(t - 5 ms)| = {err:.2e}");
    assert!(err < 1e-9);
    assert_eq!(dl.input, nominal.input, "the input encoder is not delayed");

    // Quantization: every sample on the grid, within half a step of the truth.
    let q = 2e-4;
    let qs = simulate(&with(EffectKind::Quantization, q), &base, &s);
    for (a, b) in qs.output.iter().zip(&nominal.output) {
        assert!(((a / q).round() * q - a).abs() < 1e-12);
        assert!((a - b).abs() <= 0.5 * q + 1e-12);
    }
    println!("quantization: every sample a multiple of {q}");
}

#[test]
fn force_variant_matches_the_analytic_steady_state() {
    let (m, k, c) = (2.0, 2000.0, 5.0);
    let model = RigModel {
        kind: skelid::model::ModelKind::BaseMotion,
        band: None,
        inertia: m,
        stiffness: k,
        damping: c,
        clearance: 0.0,
        gravity_stiffness: 0.0,
        effects: Default::default(),
    };
    for f in [3.0, 5.0, 7.0] {
        let drive = Drive::Force(Excitation::SteppedSine {
            freqs: vec![f],
            dwell: 20.0,
            amplitude: 10.0,
        });
        let sim = simulate(&model, &drive, &settings(20.0, 4));
        let w = std::f64::consts::TAU * f;
        let analytic = 10.0 / ((k - m * w * w).powi(2) + (c * w).powi(2)).sqrt();
        let measured = max_abs(&sim.output[15000..]);
        let rel = (measured - analytic).abs() / analytic;
        println!("force variant at {f} Hz: amplitude {measured:.6} vs analytic {analytic:.6} ({rel:.2e})");
        assert!(rel < 2e-3);
    }
}

#[test]
fn a_sampled_input_drives_the_rig_like_the_analytic_one() {
    let m = RigModel::paper();
    let e = Excitation::Chirp {
        f0: 0.0,
        f1: 6.0,
        duration: 12.0,
        amplitude: 0.03,
        rolloff: Some(Rolloff {
            corner_hz: 2.0,
            order: 2,
        }),
    };
    let s = settings(12.0, 4);
    let analytic = simulate(&m, &Drive::Base(e.clone()), &s);
    let sampled = simulate(
        &m,
        &Drive::Base(Excitation::sampled(analytic.input.clone(), 1000.0)),
        &s,
    );
    let err = analytic
        .relative
        .iter()
        .zip(&sampled.relative)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max)
        / max_abs(&analytic.relative);
    println!("sampled vs analytic drive: max relative-motion difference {err:.2e} of peak");
    assert!(err < 1e-3);
}

#[test]
fn a_noisy_measured_input_with_dry_friction_neither_chatters_nor_hangs() {
    let m = with(EffectKind::CoulombFriction, 2.5);
    let mut s = settings(10.0, 4);
    s.input_noise = 2e-5;
    let reference = simulate(&m, &Drive::Base(chirp()), &settings(10.0, 4));
    let noisy = simulate(&m, &Drive::Base(chirp()), &s).input;
    // Raw noisy samples: bounded work (event cap) even though the input is rough.
    let raw = simulate(
        &m,
        &Drive::Base(Excitation::sampled(noisy.clone(), 1000.0)),
        &settings(10.0, 4),
    );
    let raw_events = raw.events;
    // Band-limited as `Excitation::measured` does: close to the noise-free response.
    let smooth = simulate(
        &m,
        &Drive::Base(Excitation::measured(&noisy, 1000.0, 50.0)),
        &settings(10.0, 4),
    );
    let err = reference
        .relative
        .iter()
        .zip(&smooth.relative)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max)
        / max_abs(&reference.relative);
    println!(
        "noisy input: raw {raw_events} events, band-limited {} events (noise-free {}); band-limited vs noise-free z: {err:.2e} of peak",
        smooth.events, reference.events
    );
    assert!(raw_events <= 16 * 10_000, "event cap holds");
    assert!(smooth.events < 3 * reference.events + 100);
    assert!(err < 0.05);
}
