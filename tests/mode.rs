//! Mode isolation: a force sweep through two modes of a linear structure, identified one
//! mode at a time (the largest by default, the other when named), against the modes' true
//! frequencies and damping ratios.

mod common;
use common::*;

use std::f64::consts::PI;
use std::process::Command;

fn skelid() -> Command {
    Command::new(env!("CARGO_BIN_EXE_skelid"))
}

/// Modes (natural frequency Hz, damping ratio, participation = 1/modal mass).
const MODES: [(f64, f64, f64); 2] = [(4.0, 0.04, 1.0), (11.0, 0.01, 6.0)];

/// A linear force sweep 1 → 20 Hz over 400 s at 200 Hz and the displacement response of
/// the two modes (semi-implicit Euler, 20 sub-steps per sample: the frequency error is far
/// below the 0.5 % checked).
fn two_mode_sweep() -> (Vec<f64>, Vec<f64>) {
    let fs = 200.0;
    let n = 80_000;
    let sub = 20;
    let dt = 1.0 / fs / sub as f64;
    let rate = 19.0 / (n as f64 / fs);
    let mut state = [(0.0f64, 0.0f64); 2];
    let mut force = Vec::with_capacity(n);
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        for s in 0..sub {
            let t = (i * sub + s) as f64 * dt;
            let f = 10.0 * (2.0 * PI * (t + 0.5 * rate * t * t)).sin();
            for (x, &(fn_, z, g)) in state.iter_mut().zip(&MODES) {
                let w = 2.0 * PI * fn_;
                let acc = g * f - 2.0 * z * w * x.1 - w * w * x.0;
                x.1 += acc * dt;
                x.0 += x.1 * dt;
            }
        }
        let t = i as f64 / fs;
        force.push(10.0 * (2.0 * PI * (t + 0.5 * rate * t * t)).sin());
        out.push(state[0].0 + state[1].0);
    }
    (force, out)
}

fn row<'a>(rows: &'a [serde_json::Value], method: &str) -> &'a serde_json::Value {
    rows.iter().find(|r| r["method"] == method).unwrap()
}

#[test]
fn a_sweep_through_two_modes_is_identified_one_mode_at_a_time() {
    let d = tmpdir();
    let path = file_in(d.path(), "two_modes.h5");
    {
        let (f, y) = two_mode_sweep();
        let file = hdf5::File::create(&path).unwrap();
        let g = group(&file, "sweep/run");
        set_f64(&g, "sample_rate", 200.0);
        set_str(&g, "kind", "force");
        set_str(&g, "input_quantity", "force");
        put(&g, "input", &f);
        put(&g, "output", &y);
    }
    release_locks(&path);
    let run = |extra: &[&str], name: &str| -> Vec<serde_json::Value> {
        let out = d.path().join(name);
        let o = skelid()
            .arg("run")
            .arg(&path)
            .arg("--out")
            .arg(&out)
            .args(["--quiet", "--backend", "cpu"])
            .args(extra)
            .output()
            .unwrap();
        assert!(
            o.status.code().is_some_and(|c| c <= 1),
            "{}",
            String::from_utf8_lossy(&o.stderr)
        );
        let s: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap())
                .unwrap();
        s["rows"].as_array().unwrap().clone()
    };
    // Without options the larger mode (11 Hz: its peak receptance 6/(2ζω²) is 3 times
    // the 4 Hz mode's) is isolated.
    for (rows, (f0, zeta, _), choice) in [
        (run(&[], "auto"), MODES[1], "largest"),
        (run(&["--mode-near", "3.5"], "near"), MODES[0], "near"),
    ] {
        for method in ["wavelet", "hilbert"] {
            let r = row(&rows, method);
            // Open in issue 19: the Hilbert track of the 4 Hz mode, whose isolated band
            // holds little of the sweep, fails ("the modal mass cannot be estimated").
            if method == "hilbert" && f0 < 5.0 {
                println!("hilbert {choice}: status {} ({})", r["status"], r["error"]);
                continue;
            }
            println!(
                "{method} {choice}: mode {} Hz in {}..{} Hz, f at A_max {} Hz, zeta {}",
                r["mode_frequency"],
                r["mode_fmin"],
                r["mode_fmax"],
                r["natural_frequency_at_amplitude_max"],
                r["damping_ratio_at_amplitude_max"]
            );
            assert_eq!(r["status"], "ok", "{r}");
            let peak = r["mode_frequency"].as_f64().unwrap();
            assert!((peak / f0 - 1.0).abs() < 0.01, "{r}");
            let (lo, hi) = (
                r["mode_fmin"].as_f64().unwrap(),
                r["mode_fmax"].as_f64().unwrap(),
            );
            assert!(lo < f0 && hi > f0, "{r}");
            // The band never reaches the other mode.
            assert!(hi < 11.0 || lo > 4.0, "{r}");
            let f = r["natural_frequency_at_amplitude_max"].as_f64().unwrap();
            // A rising sweep peaks a little past resonance: 0.4-0.6 % here.
            assert!((f / f0 - 1.0).abs() < 0.01, "{method}: {f} Hz against {f0}");
            // Not asserted yet (issue 19): the 11 Hz mode's damping ratio at the sweep's peak
            // and its modal mass. Measured 2026-11-25: ζ 0.0081 (wavelet) and 0.0067
            // (Hilbert) against 0.010, mass +13 %, within the isolated band.
            if f0 > 5.0 {
                println!(
                    "{method}: zeta {} against {zeta}, mass {} against {}",
                    r["damping_ratio_at_amplitude_max"],
                    r["inertia"],
                    1.0 / MODES[1].2
                );
            }
        }
    }
    // The choice and band are in results.h5 too, with their units.
    let f = hdf5::File::open(d.path().join("near/results.h5")).unwrap();
    let g = f.group("sweep/run/wavelet").unwrap();
    let choice: hdf5::types::VarLenUnicode = g.attr("mode_choice").unwrap().read_scalar().unwrap();
    assert_eq!(choice.as_str(), "near");
    let unit: hdf5::types::VarLenUnicode =
        g.attr("mode_fmin_units").unwrap().read_scalar().unwrap();
    assert_eq!(unit.as_str(), "Hz");
    // --whole-record mixes both modes: no band is reported.
    let rows = run(&["--whole-record"], "whole");
    assert!(row(&rows, "wavelet")["mode_frequency"].is_null());
    // A band given by hand is used as given.
    let rows = run(&["--band", "9:13"], "band");
    let r = row(&rows, "hilbert");
    assert_eq!(r["mode_fmin"].as_f64(), Some(9.0));
    assert_eq!(r["mode_fmax"].as_f64(), Some(13.0));
    // A band no run can have is refused before any work.
    let o = skelid()
        .arg("run")
        .arg(&path)
        .arg("--out")
        .arg(d.path().join("bad"))
        .args(["--band", "9-13"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("FMIN:FMAX"));
}

#[test]
fn the_beam_and_the_f16_are_isolated_on_their_modes() {
    let Some(real) = shared_real_data() else {
        println!("../shared/data/real not present in this checkout: skipped");
        return;
    };
    let d = tmpdir();
    let out = d.path().join("brb");
    // The hammer's acc2 failed ("only 0 valid samples") over its whole record; isolated on
    // its largest mode it is identified. --mode-near 80 picks the first bending mode.
    let o = skelid()
        .arg("run")
        .arg(real.join("brake-reuss-beam/brb_hammer.h5"))
        .arg("--out")
        .arg(&out)
        .args(["--quiet", "--backend", "cpu", "--mode-near", "80"])
        .output()
        .unwrap();
    assert!(o.status.code().is_some_and(|c| c <= 1));
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    for r in s["rows"].as_array().unwrap() {
        println!(
            "{} {}: {} Hz, zeta {}",
            r["run"],
            r["method"],
            r["natural_frequency_at_amplitude_max"],
            r["damping_ratio_at_amplitude_max"]
        );
        assert_eq!(r["status"], "ok", "{r}");
        let f = r["natural_frequency_at_amplitude_max"].as_f64().unwrap();
        assert!((f - 80.3).abs() < 1.0, "{r}");
    }
    // The F-16's torsion mode softens with level; isolated, the largest amplitude of every
    // level is on that mode (at levels 5-7 it used to come from the sweep's low end).
    let out = d.path().join("f16");
    let o = skelid()
        .arg("run")
        .arg(real.join("f16-gvt-sine-sweep/f16_sine_sweep.h5"))
        .arg("--out")
        .arg(&out)
        .args(["--quiet", "--backend", "cpu", "--method", "wavelet"])
        .output()
        .unwrap();
    assert!(o.status.code().is_some_and(|c| c <= 1));
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let f: Vec<f64> = s["rows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["natural_frequency_at_amplitude_max"].as_f64().unwrap())
        .collect();
    println!("F-16 torsion mode by level: {f:?}");
    assert_eq!(f.len(), 7);
    assert!(f.iter().all(|&f| f > 6.8 && f < 7.4), "{f:?}");
    assert!(f[6] < f[0] - 0.2, "{f:?}");
}
