//! The gap metric on simulated rigs with known parameters: the paper rig with friction is
//! "measured" (demo case, encoder noise on), then models are simulated under its measured
//! input and identified the same way. The right model shows a small gap; a wrong stiffness
//! or damping shows a gap tens of times larger, in the domain the parameter governs among
//! others (a wrong stiffness also moves the jump-down, which the time domain sees first).

use skelid::backend::Backend;
use skelid::demo::cases;
use skelid::gap::{gap, simulate_like, Simulated};
use skelid::identify::{Identification, Identifier, IdentifyOptions};
use skelid::model::RigModel;
use skelid::rig::simulate_case;
use skelid::run::Run;
use skelid::simulate::Excitation;
use skelid::track::Method;

/// Default options on the CPU, as `skelid gap` identifies.
fn identifier() -> Identifier<'static> {
    static ENGINE: std::sync::OnceLock<(IdentifyOptions, Backend)> = std::sync::OnceLock::new();
    let (options, backend) = ENGINE.get_or_init(|| (IdentifyOptions::default(), Backend::cpu()));
    Identifier { options, backend }
}

fn identified(r: &Run) -> Identification {
    identifier().identify(r, Method::Wavelet).unwrap()
}

/// The demo's paper rig (friction included, encoder noise on) as a measured run: its true
/// model, the run, and the run identified.
fn paper_rig() -> (RigModel, Run, Identification) {
    let c = cases()
        .into_iter()
        .find(|c| c.path == "/demo/paper_rig")
        .unwrap();
    let measured = simulate_case(&c).into_run();
    let m = identified(&measured);
    (c.model, measured, m)
}

/// The model simulated under the measured run's input, identified.
fn simulated(measured: &Run, model: &RigModel) -> Simulated {
    simulate_like(measured, model, identifier()).unwrap()
}

#[test]
fn the_gap_sees_where_a_model_is_wrong() {
    let (truth, measured, m) = paper_rig();
    let mut stiff = truth.clone();
    stiff.stiffness *= 1.3;
    let mut damped = truth.clone();
    damped.damping *= 3.0;
    let g_truth = gap(&m, &measured, &simulated(&measured, &truth));
    let g_stiff = gap(&m, &measured, &simulated(&measured, &stiff));
    let g_damped = gap(&m, &measured, &simulated(&measured, &damped));
    for (name, g) in [
        ("truth", &g_truth),
        ("k ×1.3", &g_stiff),
        ("c ×3", &g_damped),
    ] {
        println!(
            "{name}: gap {:.4} (time {:?}, backbone {:?}, damping {:?}); top region {:?}",
            g.total,
            g.time,
            g.backbone,
            g.damping,
            g.regions.first()
        );
        let shares: f64 = g.regions.iter().map(|r| r.share).sum();
        assert!((shares - 1.0).abs() < 1e-9, "{shares}");
    }
    // Noise and the identification's own scatter: under 2 %.
    assert!(g_truth.total < 0.02, "{}", g_truth.total);
    assert!(g_stiff.total > 10.0 * g_truth.total && g_damped.total > 10.0 * g_truth.total);
    // √1.3 − 1 = 0.14 in full contact; at resonance the orbit spends part of each cycle in
    // the free play, the stiffer model's resonance comes at other instants, where it is
    // compared at its nearest resonant one, and the climbs onto the resonant branch are
    // left out: the backbone still sees several percent, ten times the truth's.
    let b = g_stiff.backbone.unwrap();
    assert!(b > 0.03 && b > 10.0 * g_truth.backbone.unwrap(), "{b}");
    let d = g_damped.damping.unwrap();
    assert!(d > 0.1 && d > 10.0 * g_truth.damping.unwrap(), "{d}");
    // The wrong stiffness moves the jump-down (about 17 s in the measurement): the time
    // domain's largest region holds it.
    let top = g_stiff.regions.iter().find(|r| r.domain == "time").unwrap();
    assert!(top.t0 <= 17.0 && top.t1 >= 15.0, "{top:?}");
}

#[test]
fn the_baseline_refit_recovers_mis_set_parameters() {
    use skelid::gap::search::{refit_baseline, Reference};
    use skelid::gap::{Blocks, SearchOptions};
    let (truth, measured, _) = paper_rig();
    // The rig as its owner wrote it down: stiffness 20 % high, clearance 15 % low; the
    // friction is part of this model (the refit must not need an effect to close the gap).
    let mut nominal = truth.clone();
    nominal.stiffness *= 1.2;
    nominal.clearance *= 0.85;
    let reference = Reference::new(&measured, Blocks { seconds: 1.0 }, identifier()).unwrap();
    let nominal_score = reference.score(&nominal);
    let opt = SearchOptions {
        baseline_evaluations: 120,
        ..SearchOptions::default()
    };
    let fitted = refit_baseline(&reference, &nominal, &opt);
    println!(
        "nominal gap {:.4}/{:.4} (fit/held out), baseline {:.4}/{:.4}: k {:.0} (true {:.0}), \
         c {:.2} (true {:.2}), clearance {:.5} (true {:.5})",
        nominal_score.fit,
        nominal_score.holdout,
        fitted.score.fit,
        fitted.score.holdout,
        fitted.model.stiffness,
        truth.stiffness,
        fitted.model.damping,
        truth.damping,
        fitted.model.clearance,
        truth.clearance
    );
    // Fitted on the even blocks, better on the odd ones too.
    assert!(fitted.score.holdout < 0.25 * nominal_score.holdout);
    assert!((fitted.model.stiffness / truth.stiffness - 1.0).abs() < 0.05);
    assert!((fitted.model.clearance / truth.clearance - 1.0).abs() < 0.05);
}

#[test]
fn the_held_out_blocks_interleave_the_fitting_ones() {
    use skelid::gap::{Blocks, Part};
    let b = Blocks { seconds: 2.0 };
    let fit = b.mask(10_000, 1000.0, Part::Fit);
    let hold = b.mask(10_000, 1000.0, Part::Holdout);
    assert!(fit.iter().zip(&hold).all(|(a, b)| a != b));
    assert!(fit[0] && fit[1999] && !fit[2000] && hold[2000] && fit[4000]);
    assert_eq!(fit.iter().filter(|&&x| x).count(), 6000);
}

#[test]
fn the_missing_friction_is_named_and_a_complete_model_gets_no_verdict() {
    use skelid::gap::search::Reference;
    use skelid::gap::{diagnose, Blocks, SearchOptions};
    use skelid::model::EffectKind;
    let (truth, measured, _) = paper_rig();
    let reference = Reference::new(&measured, Blocks { seconds: 1.0 }, identifier()).unwrap();
    let opt = SearchOptions {
        baseline_evaluations: 100,
        candidate_evaluations: 40,
        pairs: false,
        ..SearchOptions::default()
    };
    // The rig has dry friction (2.5 N m); this model does not.
    let mut nominal = truth.clone();
    nominal.effects.set(EffectKind::CoulombFriction, None);
    let d = diagnose(&reference, &nominal, &opt).unwrap();
    for c in &d.candidates {
        println!(
            "{}: {:?} gap {:.4}/{:.4} shrink {:.2}",
            c.name(),
            c.params(),
            c.score.fit,
            c.score.holdout,
            c.shrink
        );
    }
    println!(
        "baseline {:.4}/{:.4}, verdict {}",
        d.baseline.score.fit,
        d.baseline.score.holdout,
        d.verdict_name()
    );
    assert_eq!(d.candidates[0].name(), "coulomb_friction");
    let torque = d.candidates[0].effects[0].1;
    assert!((torque / 2.5 - 1.0).abs() < 0.3, "{torque}");
    // Handed the true model, nothing is missing: no verdict.
    let d = diagnose(&reference, &truth, &opt).unwrap();
    println!(
        "true model: baseline {:.4}/{:.4}, best {} {:.4}, verdict {}",
        d.baseline.score.fit,
        d.baseline.score.holdout,
        d.candidates[0].name(),
        d.candidates[0].score.holdout,
        d.verdict_name()
    );
    assert_eq!(d.verdict_name(), "none");
}

#[test]
fn a_coarse_encoder_is_read_off_the_samples_and_named() {
    use skelid::gap::search::Reference;
    use skelid::gap::{diagnose, Blocks, SearchOptions};
    use skelid::model::EffectKind;
    // The demo's rig with a 2e-4 rad encoder step on both channels.
    let c = cases()
        .into_iter()
        .find(|c| c.path == "/demo/effects/quantization")
        .unwrap();
    let q = c.model.effects.get(EffectKind::Quantization).unwrap();
    let measured = simulate_case(&c).into_run();
    let m = identified(&measured);
    // The gap sees the resolution the model lacks, as the noise floor it leaves at small
    // amplitude, and nothing of it once the model has it.
    let mut without = c.model.clone();
    without.effects.set(EffectKind::Quantization, None);
    let g_with = gap(&m, &measured, &simulated(&measured, &c.model));
    let g_without = gap(&m, &measured, &simulated(&measured, &without));
    println!(
        "gap with the encoder's step {:.4} (time {:?}), without {:.4} (time {:?})",
        g_with.total, g_with.time, g_without.total, g_without.time
    );
    assert!(g_without.total > 2.0 * g_with.total);
    assert!(g_without.backbone == g_with.backbone && g_without.damping == g_with.damping);

    // Diagnosed against the model without it (and one other effect as a rival): the step
    // is the lattice's, to the last digit; the rig without the encoder's step gets no
    // quantisation verdict.
    let opt = SearchOptions {
        baseline_evaluations: 60,
        candidate_evaluations: 30,
        pairs: false,
        effects: vec![EffectKind::CoulombFriction, EffectKind::Quantization],
        ..SearchOptions::default()
    };
    let reference = Reference::new(&measured, Blocks { seconds: 1.0 }, identifier()).unwrap();
    let d = diagnose(&reference, &without, &opt).unwrap();
    let named = &d.candidates[d.verdict.expect("a verdict")];
    println!(
        "verdict {} {:?}, shrink {:.2}, baseline {:.4}",
        named.name(),
        named.params(),
        named.shrink,
        d.baseline.score.holdout
    );
    assert_eq!(named.name(), "quantization");
    assert!((named.effects[0].1 / q - 1.0).abs() < 1e-9);
    assert!(named.shrink > 0.5);
    // A sensor's noise floor leaves the waveform within a cycle as it is: its shrink is
    // taken without that domain, which its gaps (scored by default) include.
    assert!(named.score.domains[3].is_some());
    assert_eq!(named.shrink_domains(), ["time", "backbone", "damping"]);
    let (_, clean, _) = paper_rig();
    let reference = Reference::new(&clean, Blocks { seconds: 1.0 }, identifier()).unwrap();
    assert_eq!(reference.resolution(), 0.0);
}

#[test]
fn two_levels_map_the_skeleton_far_enough_to_read_a_hardening_off_its_backbone() {
    use skelid::gap::search::effect_start;
    use skelid::model::EffectKind;
    use skelid::rig::{paper_chirp, two_level_chirp, RigCase, SECOND_LEVEL};
    use skelid::simulate::Drive;
    // The drive: 3 to 9 Hz twice, the second at 1.75 times the first, starting and ending
    // at rest.
    let x = two_level_chirp();
    let at = |t: f64| x.eval(t).v;
    assert!(at(0.0).abs() < 1e-12 && at(29.999).abs() < 1e-4);
    let peak = |t0: f64, t1: f64| {
        (0..1000)
            .map(|i| at(t0 + (t1 - t0) * i as f64 / 1000.0).abs())
            .fold(0.0, f64::max)
    };
    let ratio = peak(16.0, 18.0) / peak(1.0, 3.0);
    assert!((ratio / SECOND_LEVEL - 1.0).abs() < 0.05, "{ratio}");

    // A rig with a hardening contact (k3 = 6e6 N m/rad³): under the paper's chirp its
    // resonance spans 7 mrad of amplitude, under two levels 12 mrad reaching 9 mrad
    // further, and the backbone there gives k3 to within 15 % from a model whose own
    // parameters are a few percent off.
    let k3 = 6.0e6;
    let mut truth = RigModel::paper();
    truth.effects.set(EffectKind::CubicStiffness, Some(k3));
    let mut nominal = RigModel::paper();
    nominal.stiffness *= 1.03;
    nominal.clearance *= 1.02;
    let span = |drive: Excitation| {
        let run = simulate_case(&RigCase {
            path: "/hardening".into(),
            model: truth.clone(),
            drive: Drive::Base(drive),
            seed: 5,
            description: String::new(),
        })
        .into_run();
        let id = identified(&run);
        let r = &id.response;
        let at_resonance: Vec<f64> = (0..id.used.len())
            .filter(|&i| id.used[i] && id.at_resonance(i, IdentifyOptions::default().resonance))
            .map(|i| r.amplitude[i])
            .collect();
        let lo = at_resonance.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = at_resonance.iter().copied().fold(0.0, f64::max);
        (
            lo,
            hi,
            effect_start(EffectKind::CubicStiffness, &nominal, &id),
        )
    };
    let (lo1, hi1, start1) = span(paper_chirp());
    let (lo2, hi2, start) = span(two_level_chirp());
    println!(
        "resonant amplitude: paper chirp {lo1:.4}–{hi1:.4} rad (k3 from the backbone \
         {start1:.3e}), two levels {lo2:.4}–{hi2:.4} rad (k3 {start:.3e}); true k3 {k3:.1e}"
    );
    assert!(hi2 - lo2 > 1.5 * (hi1 - lo1) && hi2 > hi1 + 0.005);
    assert!((start / k3 - 1.0).abs() < 0.15, "{start}");
    // One level cannot tell: its backbone puts the hardening into the contact stiffness.
    assert!((start1 / k3 - 1.0).abs() > 0.5, "{start1}");
}

#[test]
fn an_encoder_zero_within_the_stated_tolerance_is_not_an_offset_clearance() {
    use skelid::gap::search::Reference;
    use skelid::gap::Blocks;
    use skelid::model::EffectKind;
    let (truth, measured, _) = paper_rig();
    // The link encoder zeroed 3e-4 rad off the base encoder: the measured relative motion
    // oscillates about +3e-4, exactly as if the clearance's centre were there.
    let zero = 3e-4;
    let mut shifted = measured.clone();
    shifted.output.iter_mut().for_each(|y| *y += zero);
    let mut offset_clearance = truth.clone();
    offset_clearance
        .effects
        .set(EffectKind::AsymmetricClearance, Some(zero));
    let blocks = Blocks { seconds: 1.0 };
    let strict = Reference::new(&shifted, blocks, identifier()).unwrap();
    let (t, o) = (strict.score(&truth), strict.score(&offset_clearance));
    println!("no tolerance: truth {t:?}, offset clearance {o:?}");
    // The blind spot: told nothing of the encoders, the gap prefers the offset clearance.
    assert!(o.holdout < t.holdout, "{} vs {}", o.holdout, t.holdout);
    // Told that the zeros may be 4e-4 apart, it no longer does: the truth scores as on the
    // record whose zeros agree, and the offset clearance gains nothing.
    let tolerant = Reference::new(&shifted, blocks, identifier())
        .unwrap()
        .with_zero_tolerance(Some(4e-4));
    let clean = Reference::new(&measured, blocks, identifier())
        .unwrap()
        .with_zero_tolerance(Some(4e-4));
    let (tt, ot, tc) = (
        tolerant.score(&truth),
        tolerant.score(&offset_clearance),
        clean.score(&truth),
    );
    println!("tolerance 4e-4: truth {tt:?}, offset clearance {ot:?}; zeros agreeing {tc:?}");
    assert!(tt.holdout < t.holdout, "{} vs {}", tt.holdout, t.holdout);
    assert!(
        (tt.holdout - tc.holdout).abs() < 1e-3 * tc.holdout,
        "{tt:?} vs {tc:?}"
    );
    assert!(
        ot.holdout >= 0.99 * tt.holdout,
        "{} vs {}",
        ot.holdout,
        tt.holdout
    );
    // The run's own attribute says the same as the option.
    let mut attributed = shifted.clone();
    attributed.meta.zero_tolerance = 4e-4;
    let by_attribute = Reference::new(&attributed, blocks, identifier()).unwrap();
    assert_eq!(by_attribute.score(&truth).holdout, tt.holdout);
}

/// Two levels of the paper's rig with dry friction recorded as two runs, fitted together:
/// the low level never touches the contact, so its own backbone cannot measure the
/// clearance (it gives a dead zone of noise). Both runs are scored with the clearance of
/// the run that reached the contact, and then the true model is the one that fits: read
/// as touching everywhere, the low run's free flight (which the friction leaves wherever
/// the link stuck) had scored the true model worse than the model without the friction.
#[test]
fn runs_of_one_rig_are_scored_with_the_clearance_the_contact_showed() {
    use skelid::gap::search::Reference;
    use skelid::gap::Blocks;
    use skelid::model::EffectKind;
    use skelid::rig::{
        level_sweep_at, measure_over, Chain, ENCODER_NOISE, PAPER_LEVEL, SECOND_LEVEL,
    };
    use skelid::simulate::Drive;
    let mut truth = RigModel::paper();
    truth.effects.set(EffectKind::CoulombFriction, Some(4.8));
    let chain = Chain::encoders(ENCODER_NOISE, truth.gravity_stiffness);
    let runs: Vec<Run> = [1.0, SECOND_LEVEL]
        .iter()
        .enumerate()
        .map(|(i, f)| {
            let drive = Drive::Base(level_sweep_at(PAPER_LEVEL * f));
            let path = format!("/two_runs/level_{}", i + 1);
            measure_over(&path, &truth, &drive, &chain, 7 + i as u64, "test", 15.0).into_run()
        })
        .collect();
    // The low level alone: a dead zone far inside the clearance, or none.
    let alone = identified(&runs[0])
        .dead_zone
        .map_or(0.0, |d| d.half_gap.value);
    let half = truth.clearance / 2.0;
    println!("low level's own half-gap {alone:.3e} rad, the rig's {half:.3e}");
    assert!(alone < 0.5 * half, "{alone}");

    let reference =
        Reference::blocks_together(&[&runs[0], &runs[1]], Blocks { seconds: 1.0 }, identifier())
            .unwrap();
    for i in 0..2 {
        let dz = reference
            .measured(i)
            .1
            .dead_zone
            .expect("the shared clearance");
        let h = dz.half_gap.value;
        assert!(
            (h / half - 1.0).abs() < 0.1,
            "run {i}: half-gap {h} against {half}"
        );
    }
    // Fitted on one level and held out on the other: the clearance comes from a fitted run
    // only, and a held-out run that reached further keeps its own.
    let half_gap = |r: &Reference, i: usize| r.measured(i).1.dead_zone.map(|d| d.half_gap.value);
    let high_held = Reference::together(&[&runs[0]], &[&runs[1]], identifier()).unwrap();
    let own = half_gap(&high_held, 1).expect("the touching level's own clearance");
    assert!((own / half - 1.0).abs() < 0.1, "held-out level: {own}");
    let low_held = Reference::together(&[&runs[1]], &[&runs[0]], identifier()).unwrap();
    assert_eq!(half_gap(&low_held, 1), half_gap(&low_held, 0));
    let mut without = truth.clone();
    without.effects.set(EffectKind::CoulombFriction, None);
    let (t, w) = (reference.score(&truth), reference.score(&without));
    println!(
        "held-out gap: truth {:.4}, without the friction {:.4}",
        t.holdout, w.holdout
    );
    assert!(
        t.holdout < 0.02 && w.holdout > 5.0 * t.holdout,
        "{} {}",
        t.holdout,
        w.holdout
    );
}
