//! The gap metric on simulated rigs with known parameters: the paper rig with friction is
//! "measured" (demo case, encoder noise on), then models are simulated under its measured
//! input and identified the same way. The right model shows a small gap; a wrong stiffness
//! or damping shows a gap tens of times larger, in the domain the parameter governs among
//! others (a wrong stiffness also moves the jump-down, which the time domain sees first).

use skelid::demo::{cases, simulate_case};
use skelid::gap::{gap, simulate_like};
use skelid::identify::{identify, Identification, IdentifyOptions};
use skelid::ingest::{Run, RunMeta};
use skelid::model::RigModel;
use skelid::track::Method;

fn run(path: &str, input: Vec<f64>, output: Vec<f64>, m: &RigModel) -> Run {
    let (kind, iq, oq) = (
        skelid::ingest::RunKind::BaseMotion,
        Some(skelid::ingest::Quantity::Displacement),
        skelid::ingest::Quantity::Displacement,
    );
    let n = output.len();
    Run {
        meta: RunMeta {
            path: path.into(),
            samples: n,
            sample_rate: 1000.0,
            duration: n as f64 / 1000.0,
            kind,
            input_quantity: iq,
            output_quantity: oq,
            inertia: Some(m.inertia),
            gravity_stiffness: m.gravity_stiffness,
            units: None,
            excitation: None,
            attributes: Default::default(),
        },
        input: Some(input),
        output,
    }
}

fn identified(r: &Run) -> Identification {
    identify(r, Method::Wavelet, &IdentifyOptions::default()).unwrap()
}

/// The demo's paper rig (friction included, encoder noise on) as a measured run: its true
/// model, the run, and the run identified.
fn paper_rig() -> (RigModel, Run, Identification) {
    let c = cases()
        .into_iter()
        .find(|c| c.path == "/demo/paper_rig")
        .unwrap();
    let rd = simulate_case(&c);
    let measured = run(&c.path, rd.input.unwrap(), rd.output, &c.model);
    let m = identified(&measured);
    (c.model, measured, m)
}

/// The model simulated under the measured run's input, identified.
fn simulated(measured: &Run, model: &RigModel) -> Identification {
    simulate_like(measured, model).unwrap()
}

#[test]
fn the_gap_sees_where_a_model_is_wrong() {
    let (truth, measured, m) = paper_rig();
    let mut stiff = truth.clone();
    stiff.stiffness *= 1.3;
    let mut damped = truth.clone();
    damped.damping *= 3.0;
    let g_truth = gap(&m, &simulated(&measured, &truth));
    let g_stiff = gap(&m, &simulated(&measured, &stiff));
    let g_damped = gap(&m, &simulated(&measured, &damped));
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
    // √1.3 − 1 = 0.14 in contact: the backbone sees the stiffness.
    let b = g_stiff.backbone.unwrap();
    assert!(b > 0.1 && b > 10.0 * g_truth.backbone.unwrap(), "{b}");
    let d = g_damped.damping.unwrap();
    assert!(d > 0.1 && d > 10.0 * g_truth.damping.unwrap(), "{d}");
    // The wrong stiffness moves the jump-down (about 17 s in the measurement): the time
    // domain's largest region holds it.
    let top = g_stiff.regions.iter().find(|r| r.domain == "time").unwrap();
    assert!(top.t0 <= 17.0 && top.t1 >= 15.0, "{top:?}");
}

#[test]
fn the_baseline_refit_recovers_mis_set_parameters() {
    use skelid::gap::{model_gap, refit_baseline};
    let (truth, measured, m) = paper_rig();
    // The rig as its owner wrote it down: stiffness 20 % high, clearance 15 % low; the
    // friction is part of this model (the refit must not need an effect to close the gap).
    let mut nominal = truth.clone();
    nominal.stiffness *= 1.2;
    nominal.clearance *= 0.85;
    let t0 = std::time::Instant::now();
    let nominal_gap = model_gap(&measured, &m, &nominal);
    let (fitted, baseline_gap, evaluations) = refit_baseline(&measured, &m, &nominal, 200);
    println!(
        "nominal gap {nominal_gap:.4}, baseline gap {baseline_gap:.4} after {evaluations} \
         evaluations ({:.1} s): k {:.0} (true {:.0}), c {:.2} (true {:.2}), clearance {:.5} \
         (true {:.5})",
        t0.elapsed().as_secs_f64(),
        fitted.stiffness,
        truth.stiffness,
        fitted.damping,
        truth.damping,
        fitted.clearance,
        truth.clearance
    );
    assert!(
        baseline_gap < 0.25 * nominal_gap,
        "{baseline_gap} vs {nominal_gap}"
    );
    assert!((fitted.stiffness / truth.stiffness - 1.0).abs() < 0.05);
    assert!((fitted.clearance / truth.clearance - 1.0).abs() < 0.05);
}

#[test]
fn the_missing_effect_closes_the_gap_and_a_wrong_one_does_not() {
    use skelid::gap::{fit_effect, refit_baseline};
    use skelid::model::EffectKind;
    let (truth, measured, m) = paper_rig();
    // The rig has dry friction (2.5 N m); its model does not.
    let mut nominal = truth.clone();
    nominal.effects.set(EffectKind::CoulombFriction, None);
    let (base, baseline_gap, _) = refit_baseline(&measured, &m, &nominal, 150);
    let (with_friction, friction_gap, _) =
        fit_effect(&measured, &m, &base, EffectKind::CoulombFriction, 150);
    let (_, cubic_gap, _) = fit_effect(&measured, &m, &base, EffectKind::CubicStiffness, 150);
    let torque = with_friction
        .effects
        .get(EffectKind::CoulombFriction)
        .unwrap();
    println!(
        "baseline gap {baseline_gap:.4}; with coulomb_friction {friction_gap:.4} (torque \
         {torque:.2}, true 2.5); with cubic_stiffness {cubic_gap:.4}"
    );
    assert!(
        friction_gap < 0.5 * baseline_gap,
        "{friction_gap} vs {baseline_gap}"
    );
    assert!(
        friction_gap < 0.5 * cubic_gap,
        "{friction_gap} vs {cubic_gap}"
    );
    // The torque is found in the right range but not yet accurately: the simplex, started
    // from the baseline, stops in a local minimum (1.68 against 2.5; README).
    assert!(torque > 0.5 && torque < 5.0, "{torque}");
}
