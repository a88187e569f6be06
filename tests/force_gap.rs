//! The gap for one mode of a structure driven by a force (`kind = "force"`), with several
//! runs (levels) fitted together and others held out: simulated structures with a known
//! joint, through the library and through `skelid gap --fit/--holdout`.

mod common;

use std::process::Command;

use skelid::backend::Backend;
use skelid::gap::search::Reference;
use skelid::gap::{diagnose, SearchOptions};
use skelid::identify::{Identifier, IdentifyOptions};
use skelid::model::{EffectKind, RigModel};
use skelid::rig::{structure_effect_value, structure_mode, structure_run, STRUCTURE_LEVELS};

fn identifier() -> Identifier<'static> {
    static ENGINE: std::sync::OnceLock<(IdentifyOptions, Backend)> = std::sync::OnceLock::new();
    let (options, backend) = ENGINE.get_or_init(|| (IdentifyOptions::default(), Backend::cpu()));
    Identifier { options, backend }
}

/// `skelid gap --model MODEL ARCHIVE ARGS --out OUT`, its output printed; gap.json.
fn gap(
    model: &std::path::Path,
    archive: &std::path::Path,
    args: &[&str],
    out: &std::path::Path,
) -> serde_json::Value {
    let o = Command::new(env!("CARGO_BIN_EXE_skelid"))
        .args(["gap", "--model"])
        .arg(model)
        .arg(archive)
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    println!("{text}\n{}", String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success());
    serde_json::from_str(&std::fs::read_to_string(out.join("gap.json")).unwrap()).unwrap()
}

/// The structure with a microslip joint (a tenth of its stiffness, half slipping at 10 mm).
fn jointed() -> RigModel {
    let mut truth = structure_mode();
    truth.set_effect(
        EffectKind::Microslip,
        structure_effect_value(EffectKind::Microslip),
    );
    truth
}

/// The structure's sweeps at every level, 1 % accelerometer noise.
fn levels(truth: &RigModel) -> Vec<skelid::campaign::RunData> {
    STRUCTURE_LEVELS
        .iter()
        .enumerate()
        .map(|(i, &level)| {
            structure_run(
                &format!("/gvt/level_{}", i + 1),
                truth,
                level,
                0.01,
                7 + i as u64,
            )
        })
        .collect()
}

/// The four levels as the force self-check splits them: 1 and 3 fitted, 2 and 4 held out.
fn fit_1_3_hold_2_4(runs: &[skelid::run::Run]) -> Reference<'static> {
    Reference::together(&[&runs[0], &runs[2]], &[&runs[1], &runs[3]], identifier()).unwrap()
}

#[test]
fn runs_fitted_together_are_scored_on_the_held_out_ones() {
    let truth = jointed();
    let runs: Vec<_> = levels(&truth).into_iter().map(|r| r.into_run()).collect();
    let reference = fit_1_3_hold_2_4(&runs);
    assert_eq!(reference.len(), 4);
    // The truth matches every level to within the noise and the identification's scatter;
    // the linear mode it softens from misses the levels where the joint slips.
    let t = reference.score(&truth);
    let linear = reference.score(&structure_mode());
    println!("truth {t:?}\nlinear {linear:?}");
    assert!(t.fit < 0.03 && t.holdout < 0.03, "{t:?}");
    assert!(linear.holdout > 5.0 * t.holdout, "{linear:?}");
    // Swapped, the held-out runs are fitted on: the same two numbers exchanged.
    let swapped = Reference::together(&[&runs[1], &runs[3]], &[&runs[0], &runs[2]], identifier())
        .unwrap()
        .score(&truth);
    assert!((swapped.fit - t.holdout).abs() < 1e-9 && (swapped.holdout - t.fit).abs() < 1e-9);
    // A force run's mass is estimated once per run and every simulation read with it.
    for i in 0..4 {
        let (run, _, _) = reference.measured(i);
        assert!(run.meta.inertia.is_some_and(|m| m > 0.0), "{i}");
    }
}

#[test]
fn skelid_gap_names_the_microslip_of_a_bolted_joint_from_levels_fitted_together() {
    let dir = common::tmpdir();
    let archive = dir.path().join("gvt.h5");
    skelid::campaign::write_campaign(&archive, &[], &levels(&jointed()), false).unwrap();
    // The nominal: the linear mode, a few percent off, as a FE model would give it.
    let mut nominal = structure_mode();
    nominal.stiffness *= 1.02;
    nominal.damping *= 1.1;
    nominal.inertia *= 0.97;
    let model = dir.path().join("mode.toml");
    std::fs::write(&model, nominal.to_toml()).unwrap();
    assert!(nominal.to_toml().contains("kind = \"force\""));
    let out = dir.path().join("gap");
    let doc = gap(
        &model,
        &archive,
        &[
            "--fit",
            "/gvt/level_1,/gvt/level_3",
            "--holdout",
            "/gvt/level_[24]",
        ],
        &out,
    );
    let runs = doc["runs"].as_array().unwrap();
    let roles: Vec<(&str, &str)> = runs
        .iter()
        .map(|r| (r["run"].as_str().unwrap(), r["role"].as_str().unwrap()))
        .collect();
    assert_eq!(
        roles,
        [
            ("/gvt/level_1", "fit"),
            ("/gvt/level_3", "fit"),
            ("/gvt/level_2", "holdout"),
            ("/gvt/level_4", "holdout")
        ]
    );
    assert_eq!(doc["settings"]["model_kind"], "force");
    assert_eq!(doc["settings"]["refit_effects"], false);
    // A force model is compared within ±2 % of resonance unless told otherwise.
    assert_eq!(doc["settings"]["resonance"], 0.02);
    let r = &runs[3];
    assert_eq!(r["verdict"], "microslip", "{r}");
    assert_eq!(
        r["holdout_runs"],
        serde_json::json!(["/gvt/level_2", "/gvt/level_4"])
    );
    let best = &r["candidates"][0];
    assert!(best["shrink"].as_f64().unwrap() >= 0.5, "{best}");
    // The force model's vocabulary: no preload, no offset, no contact damping without a
    // clearance.
    for c in r["candidates"].as_array().unwrap() {
        let e = c["effect"].as_str().unwrap();
        assert!(
            !e.contains("preload") && !e.contains("asymmetric") && !e.contains("contact"),
            "{e}"
        );
    }
    // Predicted at the top level's largest amplitude, the fitted model's backbone
    // frequency is nearer the measured one than the baseline's.
    let at = &r["at_largest_amplitude"];
    let f = |k: &str| at[k]["frequency"].as_f64().unwrap();
    assert!(
        (f("fitted") - f("measured")).abs() < (f("baseline") - f("measured")).abs(),
        "{at}"
    );
    // Each run's own gap under each model, by domain: the held-out runs' together are the
    // diagnosis's held-out gap (the root mean square of theirs), in total and domain by
    // domain, for the verdict's model as for the baseline.
    let held: Vec<&serde_json::Value> = runs.iter().filter(|r| r["role"] == "holdout").collect();
    // Over the runs where the value is present, as the score takes a domain.
    let rms = |get: &dyn Fn(&serde_json::Value) -> Option<f64>| {
        let v: Vec<f64> = held.iter().filter_map(|r| get(r)).collect();
        assert!(!v.is_empty());
        (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
    };
    // The verdict's candidate is the one whose model was written as the fitted one.
    let verdict = r["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["model"] == r["fitted_model"])
        .unwrap();
    assert_eq!(verdict["effect"], r["verdict"]);
    for (model, score) in [("fitted", verdict), ("baseline", &r["baseline"])] {
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 + 1e-6 * b.abs();
        let total = rms(&|r| r["whole_run_gap"][model].as_f64());
        println!(
            "{model}: held-out runs' RMS {total:.6}, held-out gap {}",
            score["gap_holdout"]
        );
        assert!(
            close(total, score["gap_holdout"].as_f64().unwrap()),
            "{model}: {total} {score}"
        );
        for domain in ["time", "backbone", "damping"] {
            let d = rms(&|r| r["whole_run_domains"][model][domain].as_f64());
            assert!(
                close(d, score["domains"][domain].as_f64().unwrap()),
                "{model} {domain}: {d} {score}"
            );
        }
    }
    // With a verdict there is no other candidate to show beside it.
    assert!(r["whole_run_domains"].get("best_candidate").is_none());
    assert!(r["whole_run_gap"].get("best_candidate").is_none());
    // The page says the same, in the mode's units (metres, not the rig's radians).
    let page = std::fs::read_to_string(out.join("gap.html")).unwrap();
    assert_eq!(
        page.matches("this run's own gap").count(),
        runs.len(),
        "{page}"
    );
    assert!(
        page.contains("envelope A (m)") && page.contains("A·ω (m/s)"),
        "{page}"
    );
    for unit in ["rad)", "rad/", "rad–", "rad,", "rad<", "rad "] {
        assert!(!page.contains(unit), "{unit}: {page}");
    }
    assert!(
        page.contains("µm–") || page.contains("mm–"),
        "regions in metres: {page}"
    );
    // The fitted model reads back, a force model with its joint.
    let fitted = std::fs::read_dir(&out)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .find(|p| p.to_string_lossy().ends_with(".fitted.toml"))
        .expect("a fitted model");
    let m = RigModel::load(&fitted).unwrap();
    assert_eq!(m.kind, skelid::model::ModelKind::Force);
    assert!(m.effects.joint_stiffness().is_some());
}

#[test]
fn skelid_gap_names_the_microslip_of_a_free_decay_started_from_the_record_s_own_state() {
    let dir = common::tmpdir();
    let archive = dir.path().join("hammer.h5");
    let decay = skelid::rig::structure_decay("/hammer/acc1", &jointed(), 0.02, 0.01, 3);
    skelid::campaign::write_campaign(&archive, &[], &[decay], false).unwrap();
    // The nominal: the linear mode, a few percent off, as a free-decay model.
    let mut nominal = structure_mode();
    nominal.kind = skelid::model::ModelKind::Free;
    nominal.stiffness *= 1.02;
    nominal.damping *= 1.1;
    let model = dir.path().join("mode.toml");
    std::fs::write(&model, nominal.to_toml()).unwrap();
    assert!(nominal.to_toml().contains("kind = \"free\""));
    let out = dir.path().join("gap");
    let doc = gap(&model, &archive, &[], &out);
    assert_eq!(doc["settings"]["model_kind"], "free");
    assert_eq!(doc["settings"]["resonance"], 0.1);
    let r = &doc["runs"][0];
    assert_eq!(r["verdict"], "microslip", "{r}");
    assert!(r["candidates"][0]["shrink"].as_f64().unwrap() >= 0.5);
    // Where the record was cut, and every region in the record's own seconds from there.
    let rel = &r["release"];
    let at = rel["at_s"].as_f64().unwrap();
    assert_eq!(rel["past_spread"], true, "{rel}");
    assert!(
        at >= rel["hit_s"].as_f64().unwrap() + rel["spread_s"].as_f64().unwrap() - 0.01,
        "{rel}"
    );
    let t0 = r["regions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|g| g["t0"].as_f64().unwrap())
        .fold(f64::INFINITY, f64::min);
    assert!(
        t0 >= at - 1e-9 && t0 < at + 1.0,
        "regions from {t0} s, released at {at} s"
    );
    let page = std::fs::read_to_string(out.join("gap.html")).unwrap();
    assert!(
        page.contains(&format!("compared from t = {at:.3} s")),
        "{page}"
    );
    // The truth's own decay, softening and damping more at large amplitude, is what the
    // fitted model reproduces: nearer the measurement at its largest amplitude than the
    // linear baseline.
    let at = &r["at_largest_amplitude"];
    let f = |k: &str| at[k]["frequency"].as_f64().unwrap();
    assert!(
        (f("fitted") - f("measured")).abs() < (f("baseline") - f("measured")).abs(),
        "{at}"
    );
}

#[test]
fn an_accelerometers_converter_step_is_read_on_the_time_domain_and_separates_there() {
    // The structure recorded by an accelerometer with a 0.5 m/s² converter step: the
    // true model with the step against the same model without it.
    let mut truth = structure_mode();
    truth.set_effect(
        EffectKind::Quantization,
        structure_effect_value(EffectKind::Quantization),
    );
    let runs: Vec<_> = levels(&truth).into_iter().map(|r| r.into_run()).collect();
    let reference = fit_1_3_hold_2_4(&runs);
    assert!(
        reference.resolution() > 0.0,
        "the lattice is read off the samples"
    );
    let with = reference.score(&truth);
    let without = reference.score(&structure_mode());
    let q = [EffectKind::Quantization];
    // The step is scored where it acts: the time domain alone.
    assert!(with.scores_time_alone(&q));
    assert_eq!(with.holdout_on(&q), with.domains[0].unwrap());
    // There the record carries it: the step explains most of the held-out time-domain gap
    // and clears the verdict's margins, while the damping domain, filled by the 1 %
    // accelerometer noise, hardly moves (on all three domains it shrank the gap by 7 %).
    let shrink = with.shrink_against(&without, &q);
    println!("with {with:?}\nwithout {without:?}\ntime-domain shrink {shrink:.3}");
    assert!(shrink > 0.8, "{shrink}");
    assert!(with.clears_margins(&without, &q));
    let (dw, dwo) = (with.domains[2].unwrap(), without.domains[2].unwrap());
    assert!((dw - dwo).abs() < 0.2 * dwo, "{dw} vs {dwo}");
    // The diagnosis from a model a few percent off, as the self-check's: the step is
    // fitted on the time domain and weighed against the model refitted there without it.
    let mut nominal = structure_mode();
    nominal.inertia *= 0.97;
    nominal.stiffness *= 1.02;
    nominal.damping *= 0.97;
    let opt = SearchOptions {
        effects: q.to_vec(),
        ..Default::default()
    };
    let d = diagnose(&reference, &nominal, &opt).unwrap();
    let c = &d.candidates[0];
    let against = c
        .against
        .as_ref()
        .expect("weighed against a time-domain refit");
    println!(
        "baseline {:?}
step {:?}
against {:?}",
        d.baseline.score, c.score, against.score
    );
    assert_eq!(d.verdict_name(), "quantization");
    assert!((c.effects[0].1 / truth.effects.get(q[0]).unwrap() - 1.0).abs() < 0.05);
    // Refitted on the time domain without the step, the model does not reach the record's
    // floor: the step does, as far as the truth.
    assert!(against.score.fit_on(&q) <= d.baseline.score.fit_on(&q));
    assert!(c.shrink > 0.8, "{}", c.shrink);
    assert!(c.score.holdout_on(&q) < 0.2 * d.baseline.score.holdout_on(&q));
}

#[test]
fn with_no_verdict_each_run_shows_the_best_candidate_s_own_gap() {
    // The linear mode itself at the four levels, a microslip searched for on a small budget:
    // nothing to find, no verdict, and the best candidate is shown beside the baseline run by
    // run (the F-16's case).
    let runs: Vec<_> = levels(&structure_mode())
        .into_iter()
        .map(|r| r.into_run())
        .collect();
    let reference = fit_1_3_hold_2_4(&runs);
    let opt = SearchOptions {
        baseline_evaluations: 10,
        candidate_evaluations: 5,
        refine: 1,
        pairs: false,
        effects: vec![EffectKind::Microslip],
        ..SearchOptions::default()
    };
    let d = diagnose(&reference, &structure_mode(), &opt).unwrap();
    assert_eq!(d.verdict, None, "{:?}", d.candidates[0].shrink);
    let best = &d.candidates[0];
    let held: Vec<serde_json::Value> = skelid::gap::GapRun::every(&reference, &d)
        .into_iter()
        .map(Result::unwrap)
        .filter(|r| r.role == skelid::gap::search::Role::Holdout)
        .map(|r| skelid::gap::export::run_json(&r))
        .collect();
    assert_eq!(held.len(), 2);
    // Its held-out gap is the root mean square of the held-out runs' own, in total and by
    // domain, as the baseline's is.
    let rms = |get: &dyn Fn(&serde_json::Value) -> Option<f64>| {
        let v: Vec<f64> = held.iter().filter_map(get).collect();
        assert_eq!(v.len(), held.len());
        (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
    };
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 + 1e-6 * b.abs();
    let total = rms(&|r| r["whole_run_gap"]["best_candidate"].as_f64());
    println!(
        "best candidate {}: held-out runs' RMS {total:.6}, held-out gap {:.6}",
        best.name(),
        best.score.holdout
    );
    assert!(close(total, best.score.holdout), "{total} {:?}", best.score);
    for (i, domain) in ["time", "backbone", "damping"].into_iter().enumerate() {
        let got = rms(&|r| r["whole_run_domains"]["best_candidate"][domain].as_f64());
        assert!(
            close(got, best.score.domains[i].unwrap()),
            "{domain}: {got}"
        );
    }
    // The fitted model is the baseline's, and so are its gaps.
    for r in &held {
        assert_eq!(r["whole_run_gap"]["fitted"], r["whole_run_gap"]["baseline"]);
        assert_eq!(
            r["whole_run_domains"]["fitted"],
            r["whole_run_domains"]["baseline"]
        );
        assert_eq!(
            r["at_largest_amplitude"]["best_candidate"]["effect"],
            best.name()
        );
    }
}
