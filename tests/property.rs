//! A property test of `skelid run` as a whole: 200 random combinations of bad or odd
//! options and of archives laid out as test benches write them (runs at the root, other
//! dataset names, channel matrices, missing sample rates, short, NaN, garbage files, empty
//! folders). Whatever the combination, `run`
//! - never exits 0 having done nothing (an exit 0 means results for at least one run, all
//!   identified);
//! - never drops a run without listing it: every group that holds datasets is a row of the
//!   summary (identified or failed) or a `not_runs` entry of the manifest;
//! - never leaves a temporary file, in the output folder or beside the archives.

mod common;
use common::*;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use std::path::{Path, PathBuf};
use std::process::Command;

fn skelid() -> Command {
    Command::new(env!("CARGO_BIN_EXE_skelid"))
}

/// A swept sine whose frequency passes the band the identification looks at.
fn sweep(n: usize, fs: f64, f0: f64, phase: f64) -> Vec<f64> {
    (0..n)
        .map(|i| {
            let t = i as f64 / fs;
            (std::f64::consts::TAU * (f0 * t + 2.0 * t * t) + phase).sin()
        })
        .collect()
}

/// What a group of an archive is, and so how it must come out.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Layout {
    /// A run as FORMATS.md §1 lays it out.
    Good,
    /// A run whose datasets have other names (`Force`, `Acceleration`).
    OtherNames,
    /// A run whose output is a 3×N channel matrix.
    Matrix,
    /// A run without a sample rate.
    NoRate,
    /// A run of 100 samples.
    Short,
    /// A run with NaN samples.
    WithNaN,
    /// A group without datasets (nothing to list).
    Empty,
}

const LAYOUTS: [Layout; 7] = [
    Layout::Good,
    Layout::OtherNames,
    Layout::Matrix,
    Layout::NoRate,
    Layout::Short,
    Layout::WithNaN,
    Layout::Empty,
];

/// Writes one archive of random groups; returns the paths of the groups that hold
/// datasets (each must come out listed).
fn archive(path: &Path, rng: &mut StdRng) -> Vec<String> {
    let f = hdf5::File::create(path).unwrap();
    let fs = 1000.0;
    let n = rng.random_range(600..1400);
    let mut listed = Vec::new();
    // MATLAB v7.3 as MATLAB writes it, now and then: variables at the root and `Fs`.
    if rng.random_bool(0.2) {
        let root = f.group("/").unwrap();
        put(&root, "input", &sweep(n, fs, 5.0, 0.0));
        put(&root, "output", &sweep(n, fs, 5.0, 0.3));
        root.new_dataset_builder()
            .with_data(&[fs])
            .create("Fs")
            .unwrap();
        set_str(&root, "kind", "base_motion");
        listed.push("/".to_string());
        f.close().unwrap();
        return listed;
    }
    let runs = rng.random_range(1..4);
    for k in 0..runs {
        let layout = LAYOUTS[rng.random_range(0..LAYOUTS.len())];
        let p = format!("/runs/r{k}");
        let g = group(&f, &p);
        if layout != Layout::NoRate {
            set_f64(&g, "sample_rate", fs);
        }
        let m = if layout == Layout::Short { 100 } else { n };
        let mut out = sweep(m, fs, 5.0, 0.4);
        if layout == Layout::WithNaN {
            out[m / 2] = f64::NAN;
        }
        match layout {
            Layout::Empty => continue,
            Layout::OtherNames => {
                put(&g, "Force", &sweep(m, fs, 5.0, 0.0));
                put(&g, "Acceleration", &out);
            }
            Layout::Matrix => {
                put(&g, "input", &sweep(m, fs, 5.0, 0.0));
                let rows: Vec<f64> = (0..3).flat_map(|_| out.iter().copied()).collect();
                g.new_dataset::<f64>()
                    .shape((3, m))
                    .create("output")
                    .unwrap()
                    .write_raw(&rows)
                    .unwrap();
            }
            _ => {
                put(&g, "input", &sweep(m, fs, 5.0, 0.0));
                put(&g, "output", &out);
            }
        }
        listed.push(p);
    }
    f.close().unwrap();
    listed
}

/// Options, some impossible, some odd, some fine.
fn options(rng: &mut StdRng) -> Vec<String> {
    let pool: [&[&str]; 16] = [
        &["--method", "hilbert"],
        &["--method", "wavelet"],
        &["--bins", "12"],
        &["--fmin", "20", "--fmax", "5"],
        &["--bins", "1"],
        &["--resonance", "1.5"],
        &["--cutoff", "0"],
        &["--inertia", "-1"],
        &["--kind", "bogus"],
        &["--output-name", "output[7]"],
        &["--output-name", "output[1]"],
        &["--input-name", "Force", "--output-name", "Acceleration"],
        &["--run-glob", "/nothing/matches*"],
        &["--sample-rate", "0"],
        &["--scales", "0"],
        &["--jobs", "2"],
    ];
    let mut out = Vec::new();
    for _ in 0..rng.random_range(0..3) {
        out.extend(
            pool[rng.random_range(0..pool.len())]
                .iter()
                .map(|s| s.to_string()),
        );
    }
    out
}

fn temporaries(dir: &Path, found: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            temporaries(&p, found);
        } else if p
            .file_name()
            .is_some_and(|n| n.to_string_lossy().ends_with(".tmp"))
        {
            found.push(p);
        }
    }
}

#[test]
fn two_hundred_random_bad_options_and_odd_archives_never_pass_silently() {
    let mut rng = StdRng::seed_from_u64(20261124);
    let mut exits = std::collections::BTreeMap::<i32, usize>::new();
    for case in 0..200 {
        let d = tmpdir();
        let inputs = d.path().join("in");
        std::fs::create_dir_all(&inputs).unwrap();
        let mut expected: Vec<(String, String)> = Vec::new();
        let files = rng.random_range(0..3);
        for i in 0..files {
            let name = format!("a{i}.h5");
            let p = inputs.join(&name);
            if rng.random_bool(0.1) {
                // Not HDF5 at all: its one "run" is the file, and it fails.
                let junk: Vec<u8> = (0..rng.random_range(0..600))
                    .map(|_| rng.random())
                    .collect();
                std::fs::write(&p, junk).unwrap();
                expected.push((name, String::new()));
            } else {
                for g in archive(&p, &mut rng) {
                    expected.push((name.clone(), g));
                }
                release_locks(&p);
            }
        }
        let out = d.path().join("out");
        let opts = options(&mut rng);
        let o = skelid()
            .arg("run")
            .arg(&inputs)
            .arg("--out")
            .arg(&out)
            .args(["--quiet", "--backend", "cpu"])
            .args(&opts)
            .output()
            .unwrap();
        let code = o.status.code().unwrap_or(-1);
        *exits.entry(code).or_default() += 1;
        let said = format!(
            "case {case}: {opts:?} on {expected:?}: exit {code}\n{}{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        );
        let mut tmp = Vec::new();
        temporaries(d.path(), &mut tmp);
        assert!(tmp.is_empty(), "temporary files left: {tmp:?}\n{said}");
        let summary = std::fs::read_to_string(out.join("summary.json")).ok();
        let Some(summary) = summary else {
            // Nothing written: that is never a success, and it says why.
            assert_ne!(code, 0, "exit 0 without results\n{said}");
            assert!(!o.stderr.is_empty(), "{said}");
            continue;
        };
        let summary: serde_json::Value = serde_json::from_str(&summary).unwrap();
        let rows = summary["rows"].as_array().unwrap();
        if code == 0 {
            assert!(!rows.is_empty(), "exit 0 having done nothing\n{said}");
            assert!(
                rows.iter()
                    .any(|r| r["status"] == "ok" && r["quality"] != "bad"),
                "{said}"
            );
        }
        let manifest: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).unwrap())
                .unwrap();
        let not_runs = manifest["not_runs"].as_array().cloned().unwrap_or_default();
        let glob_matches_nothing = opts.iter().any(|o| o == "/nothing/matches*");
        for (file, group) in &expected {
            if glob_matches_nothing && !group.is_empty() {
                continue;
            }
            // An archive that could not be read at all is one failed row, which names the
            // datasets it saw.
            let in_rows = rows.iter().any(|r| {
                r["source"]
                    .as_str()
                    .is_some_and(|s| s.ends_with(file.as_str()))
                    && (group.is_empty()
                        || (r["status"] == "failed"
                            && r["run"]
                                .as_str()
                                .is_some_and(|p| p.starts_with("/_unreadable/")))
                        || r["run"] == group.as_str()
                        || (group == "/" && r["run"].as_str().is_some()))
            });
            let in_not_runs = not_runs.iter().any(|n| {
                n["archive"]
                    .as_str()
                    .is_some_and(|a| a.ends_with(file.as_str()))
                    && n["path"] == group.as_str()
            });
            assert!(
                in_rows || in_not_runs,
                "{file}:{group} is neither a row nor listed as not a run\n{said}\n{summary}"
            );
        }
    }
    println!("exit codes over 200 cases: {exits:?}");
    assert!(
        exits.len() >= 2,
        "the cases reach more than one outcome: {exits:?}"
    );
}
