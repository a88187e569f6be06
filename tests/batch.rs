//! `skelid run` as an overnight batch: killed with SIGKILL several times and resumed, it
//! ends with exactly the results of an uninterrupted run; three shards run as separate
//! processes and merged equal one unsharded run; merge refuses what does not fit.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

mod common;
use common::summary_rows;

fn skelid() -> Command {
    Command::new(env!("CARGO_BIN_EXE_skelid"))
}

/// A campaign folder: the demo archive under three names (33 runs).
fn campaign(dir: &Path) -> PathBuf {
    let demo = dir.join("demo");
    let st = skelid()
        .args(["demo", "--out"])
        .arg(&demo)
        .output()
        .expect("run skelid demo");
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    let c = dir.join("campaign");
    std::fs::create_dir_all(&c).unwrap();
    for name in ["a.h5", "b.h5", "c.h5"] {
        std::fs::copy(demo.join("demo_campaign.h5"), c.join(name)).unwrap();
    }
    c
}

/// Waits (up to 2 minutes) until the batch into `out` has committed a run.
fn wait_for_a_commit(out: &Path) {
    let log = out.join("skelid.log");
    let deadline = std::time::Instant::now() + Duration::from_secs(120);
    while !std::fs::read_to_string(&log).is_ok_and(|t| t.contains(" done ")) {
        assert!(std::time::Instant::now() < deadline, "no run committed");
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn run(args: &[&str], inputs: &Path, out: &Path) -> std::process::Output {
    skelid()
        .arg("run")
        .arg(inputs)
        .arg("--out")
        .arg(out)
        .args(["--quiet"])
        .args(args)
        .output()
        .expect("run skelid run")
}

/// An output folder's `manifest.json`.
fn manifest_of(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).unwrap()).unwrap()
}

/// An output folder's `skelid.log`.
fn log_of(out: &Path) -> String {
    std::fs::read_to_string(out.join("skelid.log")).unwrap()
}

/// `skelid merge DIRS --out OUT`, its output.
fn merge<P: AsRef<std::ffi::OsStr>>(dirs: &[P], out: &Path) -> std::process::Output {
    skelid()
        .arg("merge")
        .args(dirs)
        .arg("--out")
        .arg(out)
        .output()
        .expect("run skelid merge")
}

/// Rows equal field by field; numbers to 1e-12 relative. The same run identified twice can
/// differ in the last bit (the order of parallel floating-point work), nothing more.
fn assert_same_rows(a: &[serde_json::Value], b: &[serde_json::Value]) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        let (x, y) = (x.as_object().unwrap(), y.as_object().unwrap());
        assert_eq!(x.keys().collect::<Vec<_>>(), y.keys().collect::<Vec<_>>());
        for (k, v) in x {
            let w = &y[k];
            match (v.as_f64(), w.as_f64()) {
                (Some(p), Some(q)) => assert!(
                    (p - q).abs() <= 1e-12 * p.abs().max(q.abs()).max(1e-300),
                    "{k}: {p} vs {q} in {x:?}"
                ),
                _ => assert_eq!(v, w, "{k} in {x:?}"),
            }
        }
    }
}

/// Every run group of results.h5 with its status and one fitted value.
fn results(out: &Path) -> Vec<(String, String, Option<f64>)> {
    let f = hdf5::File::open(out.join("results.h5")).expect("results.h5 readable");
    let mut v = Vec::new();
    fn walk(g: &hdf5::Group, path: String, v: &mut Vec<(String, String, Option<f64>)>) {
        if let Ok(a) = g.attr("status") {
            let s: hdf5::types::VarLenUnicode = a.read_scalar().unwrap();
            let c = g
                .group("wavelet")
                .ok()
                .and_then(|w| w.attr("clearance").ok())
                .and_then(|a| a.read_scalar::<f64>().ok());
            v.push((path, s.to_string(), c));
            return;
        }
        for name in g.member_names().unwrap() {
            if let Ok(sub) = g.group(&name) {
                walk(&sub, format!("{path}/{name}"), v);
            }
        }
    }
    walk(&f.group("/").unwrap(), String::new(), &mut v);
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

fn assert_same_results(a: &[(String, String, Option<f64>)], b: &[(String, String, Option<f64>)]) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert_eq!((&x.0, &x.1), (&y.0, &y.1));
        match (x.2, y.2) {
            (Some(p), Some(q)) => {
                assert!((p - q).abs() <= 1e-12 * p.abs().max(q.abs()).max(1e-300))
            }
            (p, q) => assert_eq!(p, q),
        }
    }
}

/// Ctrl-C (SIGINT) and a scheduler's SIGTERM (to a `--force` batch) in the middle of a
/// batch: status 130, the terminal and the log say how many runs are committed and how to
/// resume (without `--force` for that one), no `results.h5.tmp` is left, and the command
/// (without `--force`) then skips those runs.
#[test]
fn an_interrupted_batch_says_so_and_leaves_no_temporary_file() {
    let tmp = tempfile::tempdir().unwrap();
    let inputs = campaign(tmp.path());
    for (signal, name, flags, advice) in [
        (
            libc::SIGINT,
            "SIGINT",
            &[][..],
            "the same command resumes without redoing them",
        ),
        (
            libc::SIGTERM,
            "SIGTERM",
            &["--force"][..],
            "the same command without --force resumes from them",
        ),
    ] {
        let out = tmp.path().join(name);
        let child = skelid()
            .arg("run")
            .arg(&inputs)
            .arg("--out")
            .arg(&out)
            .arg("--quiet")
            .args(flags)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        // Signalled once the first run is committed: the batch is under way, not done
        // (33 runs, a few seconds here).
        let log = out.join("skelid.log");
        wait_for_a_commit(&out);
        // SAFETY: kill(2) on our own child's pid, which has not been waited for.
        assert_eq!(unsafe { libc::kill(child.id() as libc::pid_t, signal) }, 0);
        let o = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(130), "{name}: {err}");
        assert!(
            err.contains("interrupted (Ctrl-C, SIGTERM or SIGHUP): ") && err.contains(advice),
            "{name}: {err}"
        );
        assert!(!out.join("results.h5.tmp").exists(), "{name}: .tmp left");
        let logged = std::fs::read_to_string(&log).unwrap();
        assert!(
            logged.contains("interrupted (Ctrl-C, SIGTERM or SIGHUP): "),
            "{logged}"
        );
        let committed = std::fs::read_dir(out.join("runs"))
            .unwrap()
            .filter(|e| {
                e.as_ref()
                    .is_ok_and(|e| e.path().extension().is_some_and(|x| x == "run"))
            })
            .count();
        // Said as counted when the signal came; a worker may finish its commit (a
        // rename) in the moment before the process ends.
        let said: usize = err
            .split("interrupted (Ctrl-C, SIGTERM or SIGHUP): ")
            .nth(1)
            .and_then(|t| t.split(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("{err}"));
        assert!(
            said <= committed && committed > 0,
            "{said} {committed}: {err}"
        );
        let o = run(&[], &inputs, &out);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let said = String::from_utf8_lossy(&o.stdout);
        assert!(
            said.contains(&format!("{committed} already done earlier")),
            "{committed}: {said}"
        );
    }
}

/// One batch a folder: a second `skelid run` into a folder whose batch still runs (a cron
/// job fired again, the command typed in a second terminal) is refused at once, naming the
/// first, and changes nothing; the first ends as if alone. Until 2026-12-07 both failed
/// ("results.h5: cannot write: No such file or directory", "runs/….run: cannot write")
/// and the folder was left without its results.h5. A merge of that folder, or into it, is
/// refused while it runs; once it has ended the same command works.
#[test]
fn a_second_batch_into_a_folder_in_use_is_refused_and_changes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let inputs = campaign(tmp.path());
    let out = tmp.path().join("night1");
    // A finished folder, made first: the batch below must outlast every refusal.
    let done = tmp.path().join("done");
    assert!(run(&["--method", "wavelet"], &inputs.join("a.h5"), &done)
        .status
        .success());
    // 33 runs read 0.2 s apiece: about 7 s, time for the refusals below.
    let first = skelid()
        .arg("run")
        .arg(&inputs)
        .arg("--out")
        .arg(&out)
        .args(["--quiet", "--method", "wavelet"])
        .env("SKELID_READ_PAUSE_MS", "200")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    wait_for_a_commit(&out);
    let second = run(&["--method", "wavelet"], &inputs, &out);
    let err = String::from_utf8_lossy(&second.stderr);
    println!("{err}");
    assert_eq!(second.status.code(), Some(2), "{err}");
    let holder = format!(
        "is in use by skelid's batch of pid {}, started ",
        first.id()
    );
    assert!(err.contains(&holder), "{err}");
    assert!(
        err.contains("wait for it to end (or stop it: the command that started it then resumes its work), or give this batch another folder"),
        "{err}"
    );
    // A merge of the running folder, and one into it (of a finished folder), likewise.
    let m = merge(&[&out], &tmp.path().join("merged"));
    let err = String::from_utf8_lossy(&m.stderr);
    assert!(
        m.status.code() == Some(2)
            && err.contains(&holder)
            && err.contains("merge once it has ended"),
        "{err}"
    );
    assert!(
        !tmp.path().join("merged").exists(),
        "a refused merge makes nothing"
    );
    let m = merge(&[&done], &out);
    let err = String::from_utf8_lossy(&m.stderr);
    assert!(
        m.status.code() == Some(2)
            && err.contains(&holder)
            && err.contains("give this merge another folder"),
        "{err}"
    );

    // A demo into it is refused before it writes its archive there.
    let d = skelid().args(["demo", "--out"]).arg(&out).output().unwrap();
    let err = String::from_utf8_lossy(&d.stderr);
    assert!(
        d.status.code() == Some(2)
            && err.contains(&holder)
            && err.contains("give this demo another folder"),
        "{err}"
    );
    assert!(!out.join("demo_campaign.h5").exists());

    let o = first.wait_with_output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(
        String::from_utf8_lossy(&o.stdout).contains("33 run(s), 0 failed"),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    assert_eq!(results(&out).len(), 33);
    let log = log_of(&out);
    assert_eq!(
        log.matches(" start: ").count(),
        1,
        "the refused wrote nothing: {log}"
    );
    assert_eq!(log.matches(" lock: taken by pid ").count(), 1, "{log}");
    assert_eq!(log.matches(" merge: ").count(), 0, "{log}");
    // Ended, the folder is free: the same command resumes (nothing to redo), and merges.
    let again = run(&["--method", "wavelet"], &inputs, &out);
    assert!(
        String::from_utf8_lossy(&again.stdout).contains("33 already done earlier"),
        "{}",
        String::from_utf8_lossy(&again.stderr)
    );
    let m = merge(&[&out], &tmp.path().join("merged"));
    assert!(m.status.success(), "{}", String::from_utf8_lossy(&m.stderr));
    assert!(log_of(&tmp.path().join("merged")).contains(" merge: 1 shard folder(s)"));
}

#[test]
fn killed_batches_resume_to_the_uninterrupted_result() {
    let tmp = tempfile::tempdir().unwrap();
    let inputs = campaign(tmp.path());
    let clean = tmp.path().join("clean");
    let o = run(&[], &inputs, &clean);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let expected_rows = summary_rows(&clean);
    let expected = results(&clean);
    assert_eq!(expected.len(), 33, "{expected:?}");

    let out = tmp.path().join("killed");
    let committed_now = || {
        std::fs::read_dir(out.join("runs"))
            .map(|d| {
                d.filter(|e| {
                    e.as_ref()
                        .is_ok_and(|e| e.path().extension().is_some_and(|x| x == "run"))
                })
                .count()
            })
            .unwrap_or(0)
    };
    let mut committed = Vec::new();
    // Each batch is killed once it has committed runs of its own (the first, then 8 more
    // each time; or after 20 s): mid-batch on a machine of any speed, where fixed delays
    // landed after the end on a fast one (a release build finished the 33 runs in 1.1 s).
    for round in 0..4 {
        let wanted = committed_now() + if round == 0 { 1 } else { 8 };
        let mut child = skelid()
            .arg("run")
            .arg(&inputs)
            .arg("--out")
            .arg(&out)
            .arg("--quiet")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        while committed_now() < wanted
            && child.try_wait().unwrap().is_none()
            && std::time::Instant::now() < deadline
        {
            std::thread::sleep(Duration::from_millis(2));
        }
        let _ = child.kill(); // SIGKILL (an error only where it had ended already)
        child.wait().unwrap();
        // Whatever was visible is whole: committed run files and, if present, results.h5.
        committed.push(committed_now());
        if out.join("results.h5").exists() {
            results(&out);
        }
    }
    println!("runs committed after each SIGKILL: {committed:?} of 33");
    assert!(
        committed.iter().any(|&n| n > 0 && n < 33),
        "no kill landed mid-batch: {committed:?}"
    );
    let o = run(&[], &inputs, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(said.contains("already done earlier"), "{said}");
    assert_same_rows(&summary_rows(&out), &expected_rows);
    assert_same_results(&results(&out), &expected);

    // A second rerun does nothing new; --force redoes all, to the same result.
    let o = run(&[], &inputs, &out);
    assert!(String::from_utf8_lossy(&o.stdout).contains("33 already done"));
    let o = run(&["--force"], &inputs, &out);
    assert!(String::from_utf8_lossy(&o.stdout).contains(" 0 already done"));
    assert_same_rows(&summary_rows(&out), &expected_rows);
    // results.h5 replaced whole (the previous one set aside, then deleted).
    assert_same_results(&results(&out), &expected);
    // The one writer's load, logged at each batch's end: one thread's CPU time within the
    // wall time it ran.
    let log = log_of(&out);
    let line = log
        .lines()
        .rev()
        .find(|l| l.contains("the writer"))
        .expect("the writer's load in the log");
    let seconds: Vec<f64> = line
        .split_whitespace()
        .zip(line.split_whitespace().skip(1))
        .filter(|(_, unit)| *unit == "s")
        .filter_map(|(v, _)| v.parse().ok())
        .collect();
    assert!(
        seconds.len() == 2 && seconds[0] > 0.0 && seconds[0] <= seconds[1] * 1.01,
        "{line}"
    );
}

/// One archive of 11 runs: the progress's total is 11 from the first run on (it counted
/// the open archive as one run, 6, 7, 8, … 11). A disk that cannot hold the runs left is
/// said once, on the terminal and in skelid.log, with the progress's `disk` figures;
/// a disk with room says nothing.
#[test]
fn progress_counts_an_archives_runs_and_warns_of_a_disk_too_small() {
    let tmp = tempfile::tempdir().unwrap();
    let archive = campaign(tmp.path()).join("a.h5");
    let batch = |out: &Path, free: Option<&str>| {
        let mut c = skelid();
        // One worker: the reader is then still in the archive when the first runs end
        // (with a worker a core, a many-core machine would read all 11 first).
        c.arg("run").arg(&archive).arg("--out").arg(out).args([
            "--method",
            "wavelet",
            "--json-progress",
            "--jobs",
            "1",
        ]);
        if let Some(bytes) = free {
            // Pretends 1 MB free at the start: a demo run takes about 2 MB.
            c.env("SKELID_DISK_FREE", bytes);
        }
        let o = c.output().expect("run skelid run");
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
        let progress: Vec<serde_json::Value> = stderr
            .lines()
            .filter(|l| l.starts_with('{'))
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        (stderr, progress)
    };
    let short = tmp.path().join("short");
    let (said, progress) = batch(&short, Some("1000000"));
    assert_eq!(progress.len(), 11);
    for p in &progress {
        assert_eq!(p["total"], 11, "{p}");
    }
    let warning = "will be full before the batch ends";
    let warnings: Vec<&str> = said
        .lines()
        .filter(|l| l.starts_with("warning: ") && l.contains(warning))
        .collect();
    println!("{}", warnings.join("\n"));
    assert_eq!(warnings.len(), 1, "{said}");
    assert!(
        warnings[0].starts_with("warning: the disk holding "),
        "{said}"
    );
    let log = log_of(&short);
    assert_eq!(log.matches(warning).count(), 1, "{log}");
    // The figures from the eighth run on: the rate, and no more than the pretended room.
    let last = &progress[10]["disk"];
    println!("last progress's disk: {last}");
    assert_eq!(last["runs_left"], 0);
    assert!(last["per_run_bytes"].as_u64().unwrap() > 100_000, "{last}");
    assert!(last["free_bytes"].as_u64().unwrap() <= 1_000_000, "{last}");
    assert!(progress[..7].iter().all(|p| p["disk"].is_null()));
    assert!(!progress[7]["disk"].is_null(), "from the eighth run");
    let keyed: Vec<&serde_json::Value> = progress
        .iter()
        .filter(|p| p.get("disk_warning").is_some())
        .collect();
    assert_eq!(keyed.len(), 1, "the warning in the JSON too, once");
    assert_eq!(
        keyed[0]["disk_warning"].as_str(),
        Some(&warnings[0]["warning: ".len()..])
    );

    let roomy = tmp.path().join("roomy");
    let (said, progress) = batch(&roomy, None);
    assert!(!said.contains(warning), "{said}");
    assert!(progress[10]["disk"]["free_bytes"].as_u64().unwrap() > 1_000_000);
}

/// `--timeout` bounds one step of the reading child (opening an archive, reading a run),
/// not a whole archive: the demo's 11 runs read 0.5 s apiece (5.5 s in all) pass a 2 s
/// timeout whole; until 2026-12-07 the archive was cut off after about four runs as if
/// libhdf5 had hung on it. A run that takes longer than the timeout still stops the child
/// and fails; three in a row give up the rest of the archive, with the step that hung.
#[test]
fn the_reading_timeout_bounds_a_step_not_a_whole_archive() {
    let tmp = tempfile::tempdir().unwrap();
    let archive = campaign(tmp.path()).join("a.h5");
    let batch = |out: &Path, pause_ms: &str| {
        let o = skelid()
            .arg("run")
            .arg(&archive)
            .arg("--out")
            .arg(out)
            .args(["--method", "hilbert", "--quiet", "--timeout", "2"])
            .env("SKELID_READ_PAUSE_MS", pause_ms)
            .output()
            .expect("run skelid run");
        let manifest = manifest_of(out);
        let log = log_of(out);
        (o, manifest["runs"].as_array().unwrap().clone(), log)
    };
    let slow = tmp.path().join("slow");
    let (o, runs, log) = batch(&slow, "500");
    assert!(!log.contains("corrupt"), "{log}");
    assert_eq!(runs.len(), 11, "{}", String::from_utf8_lossy(&o.stderr));

    let hung = tmp.path().join("hung");
    let (o, runs, log) = batch(&hung, "6000");
    assert_eq!(o.status.code(), Some(1), "a failed archive is a failed run");
    let paths: Vec<&str> = runs.iter().map(|r| r["path"].as_str().unwrap()).collect();
    let first = [
        "/demo/effects/asymmetric_clearance",
        "/demo/effects/contact_damping",
        "/demo/effects/coulomb_friction",
    ];
    assert_eq!(paths[..3], first, "{log}");
    assert_eq!(paths[3..], ["/_unreadable/a.h5"], "{log}");
    // The lines in the order the workers finished, not necessarily the runs'.
    let lines: Vec<&str> = log.lines().filter(|l| l.contains("corrupt")).collect();
    println!("{}", lines.join("\n"));
    assert_eq!(lines.len(), 4);
    for i in 0..4 {
        let step = match i {
            0 => "reading its first run of 11".to_string(),
            _ => format!(
                "reading its run {} of 11, the one after {}",
                i + 1,
                first[i - 1]
            ),
        };
        let said = match i {
            3 => "3 runs in a row stopped the reading child, the last \
                  /demo/effects/coulomb_friction, so the archive's 8 run(s) after it are not read"
                .to_string(),
            _ => format!("{step}, the reading child went 2 s without progress"),
        };
        assert!(lines.iter().any(|l| l.contains(&said)), "{said}");
    }
    for line in lines {
        assert!(
            !line.contains("[: "),
            "a failure of no method names none: {line}"
        );
    }
}

/// A run that crashes the reading child (libhdf5 on a corrupt chunk, or the child killed)
/// or stops it answering fails alone: a new child reads the archive on from the next run.
/// Until 2026-12-07 the rest of the archive was recorded unreadable with it, so one bad run
/// of a bench's single archive lost the night. The runs read are identified as in a batch
/// without the faults, every run announced is in the manifest once, and the same command
/// without the faults reads and identifies the failed runs.
#[test]
fn a_run_that_crashes_the_reading_child_fails_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let c = campaign(tmp.path());
    let files = [c.join("a.h5"), c.join("b.h5")];
    let batch = |out: &Path, faults: &str| {
        let o = skelid()
            .arg("run")
            .args(&files)
            .arg("--out")
            .arg(out)
            .args([
                "--method",
                "hilbert",
                "--quiet",
                "--jobs",
                "2",
                // 5 s: a loaded machine stalling between two faults could make three in a row.
                "--timeout",
                "5",
            ])
            .env("SKELID_READ_FAULT", faults)
            .output()
            .expect("run skelid run");
        assert!(
            matches!(o.status.code(), Some(0 | 1)),
            "{}",
            String::from_utf8_lossy(&o.stderr)
        );
        let manifest = manifest_of(out);
        (manifest, summary_rows(out))
    };
    let clean = tmp.path().join("clean");
    let (manifest, rows) = batch(&clean, "");
    assert_eq!(manifest["runs"].as_array().unwrap().len(), 22);
    // Three faults, two in a row in the same archives: never three, so nothing given up.
    let (crash, hang) = ("/demo/linear", "/demo/effects/gravity_preload");
    let faults = format!("crash:{crash},hang:{hang},crash:/demo/effects/cubic_stiffness");
    let faulty = tmp.path().join("faulty");
    let (manifest, faulty_rows) = batch(&faulty, &faults);
    let runs = manifest["runs"].as_array().unwrap();
    assert_eq!(runs.len(), 22, "{manifest}");
    assert_eq!(manifest["runs_in_inputs"], 22);
    let failed: Vec<(String, String)> = (faulty_rows.iter())
        .filter(|r| r["error"].as_str().is_some_and(|e| e.contains("corrupt")))
        .map(|r| {
            let run = format!("{}:{}", r["source"].as_str().unwrap(), r["run"]);
            (run, r["error"].as_str().unwrap().to_string())
        })
        .collect();
    for (run, error) in &failed {
        println!("{run}: {error}");
    }
    assert_eq!(failed.len(), 6, "three runs in each archive");
    for (run, error) in &failed {
        assert!(error.contains("the archive's other runs are read by a new reading child"));
        if run.contains(hang) {
            assert!(error.contains("the one after /demo/effects/cubic_stiffness, the reading child went 5 s without progress"), "{error}");
        } else {
            assert!(
                error.contains("libhdf5 crashed reading it (signal 6)"),
                "{error}"
            );
        }
    }
    // Every other run as in the batch without faults.
    let faulted = |r: &serde_json::Value| {
        let run = r["run"].as_str().unwrap();
        run == crash || run == hang || run == "/demo/effects/cubic_stiffness"
    };
    let kept: Vec<serde_json::Value> = rows.iter().filter(|r| !faulted(r)).cloned().collect();
    let read: Vec<serde_json::Value> = faulty_rows
        .iter()
        .filter(|r| !faulted(r))
        .cloned()
        .collect();
    assert_eq!(kept.len(), 16);
    assert_same_rows(&kept, &read);
    // The same command without the faults reads and identifies the failed runs.
    let (manifest, rows_after) = batch(&faulty, "");
    assert_eq!(manifest["runs"].as_array().unwrap().len(), 22);
    assert_same_rows(&rows, &rows_after);
    // A crash that only a child with earlier runs behind it meets (an earlier run corrupted
    // libhdf5's heap): the run, read again first by a new child, is identified, so every
    // run is, as without the fault.
    let innocent = tmp.path().join("innocent");
    let (manifest, innocent_rows) = batch(&innocent, &format!("crash-after-others:{crash}"));
    assert_eq!(manifest["runs"].as_array().unwrap().len(), 22);
    assert_eq!(manifest["runs_in_inputs"], 22);
    assert_same_rows(&rows, &innocent_rows);
    // Said in the log: the earlier runs of that child may deserve a look.
    let log = log_of(&innocent);
    let said = format!("the reading child crashed on {crash} after reading other runs");
    assert_eq!(log.matches(&said).count(), 2, "once in each archive: {log}");
    assert!(log.contains(&format!("a new reading child reads {crash} again, first")));
    // The same at an archive's opening: b.h5, opened by a child that read a.h5 before,
    // crashes it; a new child opens b.h5 first and reads it, so every run is identified.
    // Until 2026-12-07 b.h5 was recorded unreadable, its 11 runs lost.
    let opening = tmp.path().join("opening");
    let (manifest, opening_rows) = batch(&opening, "crash-opening-after-others:b.h5");
    assert_eq!(manifest["runs"].as_array().unwrap().len(), 22);
    assert_same_rows(&rows, &opening_rows);
    let log = log_of(&opening);
    assert!(
        log.contains(
            "b.h5: the reading child crashed opening it after reading other archives \
             (libhdf5 crashed opening it (signal 6)); a new reading child opens it again, first"
        ),
        "{log}"
    );
    // An archive that crashes every child opening it is recorded unreadable, once, with
    // the new child's crash (what a fresh child says, the same in every shard); the log
    // says that child was stopped by it too.
    let bad = tmp.path().join("bad");
    let (manifest, bad_rows) = batch(&bad, "crash-opening:b.h5");
    assert_eq!(manifest["runs"].as_array().unwrap().len(), 12);
    let error = (bad_rows.iter())
        .find(|r| r["run"] == "/_unreadable/b.h5")
        .and_then(|r| r["error"].as_str())
        .expect("b.h5 unreadable");
    assert!(
        error.ends_with("truncated or corrupt HDF5 file: libhdf5 crashed opening it (signal 6)"),
        "{error}"
    );
    let log = log_of(&bad);
    assert!(
        log.contains("b.h5: the new reading child, opening it first, was stopped by it too"),
        "{log}"
    );
}

/// An archive that crashes the reading child as it is closed, after every run of it was
/// read, loses no run: its runs are identified as in a batch without the fault, nothing is
/// recorded failed for it, the next archive is read by a new child, and the batch warns of
/// the damaged file on the terminal, in skelid.log and in manifest.json. Until 2026-12-07
/// it was a failed `/_unreadable/` entry and exit status 1. Sharded, each shard notes it
/// and the merge keeps it once.
#[test]
fn an_archive_that_crashes_libhdf5_when_closed_loses_no_run() {
    let tmp = tempfile::tempdir().unwrap();
    let c = campaign(tmp.path());
    let files = [c.join("a.h5"), c.join("b.h5")];
    let batch = |out: &Path, faults: &str, shard: Option<&str>| {
        let o = skelid()
            .arg("run")
            .args(&files)
            .arg("--out")
            .arg(out)
            .args(["--method", "hilbert", "--quiet"])
            .args(shard.map(|s| ["--shard", s]).into_iter().flatten())
            .env("SKELID_READ_FAULT", faults)
            .output()
            .expect("run skelid run");
        let manifest = manifest_of(out);
        (o, manifest)
    };
    let clean = tmp.path().join("clean");
    let (o, manifest) = batch(&clean, "", None);
    let status = o.status.code();
    assert!(matches!(status, Some(0 | 1)), "{o:?}");
    assert!(manifest.get("damaged_archives").is_none(), "{manifest}");
    let faulty = tmp.path().join("faulty");
    let (o, manifest) = batch(&faulty, "crash-closing:a.h5", None);
    let said = String::from_utf8_lossy(&o.stderr);
    println!("{said}");
    assert_eq!(o.status.code(), status, "{said}");
    assert_eq!(manifest["runs"].as_array().unwrap().len(), 22, "{manifest}");
    assert_eq!(manifest["runs_in_inputs"], 22);
    assert!(!manifest.to_string().contains("_unreadable"), "{manifest}");
    let damaged = manifest["damaged_archives"].as_array().unwrap();
    assert_eq!(damaged.len(), 1, "{manifest}");
    assert!(damaged[0]["archive"].as_str().unwrap().ends_with("a.h5"));
    let detail = damaged[0]["detail"].as_str().unwrap();
    assert!(
        detail.starts_with(
            "read to the end (its 11 run(s) read), but not closed: libhdf5 crashed closing \
             it (signal 6). That costs no run"
        ),
        "{detail}"
    );
    assert!(said.contains("warning: damaged archive ") && said.contains("a.h5: read to the end"));
    assert!(String::from_utf8_lossy(&o.stdout).contains("1 archive(s) damaged (no run lost"));
    let log = log_of(&faulty);
    assert!(log.contains("warning: damaged archive "), "{log}");
    let page = |dir: &Path| std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(page(&faulty)
        .contains("<h2>Inputs to check</h2>\n<ul class=\"warn\">\n<li>damaged archive "));
    // With --strict, for pipelines that stop on anything doubtful, a damaged archive gives
    // status 1, where the same good results without it give 0.
    let strict = |out: &Path, faults: &str| {
        skelid()
            .arg("run")
            .args(&files)
            .arg("--out")
            .arg(out)
            .args([
                "--quiet",
                "--strict",
                "--run-glob",
                "/demo/force_oscillator",
            ])
            .env("SKELID_READ_FAULT", faults)
            .output()
            .expect("run skelid run")
            .status
            .code()
    };
    assert_eq!(strict(&tmp.path().join("strict-clean"), ""), Some(0));
    assert_eq!(
        strict(&tmp.path().join("strict-damaged"), "crash-closing:a.h5"),
        Some(1)
    );
    assert!(!page(&clean).contains("Inputs to check"));
    assert_same_rows(&summary_rows(&clean), &summary_rows(&faulty));
    // Two shards, each reading (and closing) both archives: merged, a.h5 once.
    let shards: Vec<PathBuf> = ["1/2", "2/2"]
        .iter()
        .map(|s| {
            let out = tmp.path().join(format!("shard{}", &s[..1]));
            let (o, manifest) = batch(&out, "crash-closing:a.h5", Some(s));
            assert_eq!(manifest["runs_in_inputs"], 22, "{o:?}");
            assert_eq!(manifest["damaged_archives"].as_array().unwrap().len(), 1);
            out
        })
        .collect();
    let merged = tmp.path().join("merged");
    let o = merge(&shards, &merged);
    let said = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), status, "{said}");
    assert_eq!(
        said.matches("warning: damaged archive ").count(),
        1,
        "{said}"
    );
    let manifest = manifest_of(&merged);
    let damaged = manifest["damaged_archives"].as_array().unwrap();
    assert_eq!(damaged.len(), 1);
    // Its run count is one shard's, so the shard is named.
    let detail = damaged[0]["detail"].as_str().unwrap();
    assert!(
        detail.starts_with("shard 1/2: read to the end (its "),
        "{detail}"
    );
    assert!(page(&merged).contains("<li>damaged archive "));
    assert_same_rows(&summary_rows(&clean), &summary_rows(&merged));
}

/// An archive no reading child can open (not HDF5: a bench's copy cut short) is every
/// shard's failure: merged, it is kept once and the merge equals the unsharded batch. An
/// archive one shard's children give up part-way (three of its runs in a row crash them)
/// while the other shard reads it to the end merges too: the runs read by either are kept,
/// the one shard's runs left unread are counted and named on the terminal, in the manifest
/// and in the report. Both were refused ("is in both", "saw N runs") until 2026-12-07.
#[test]
fn shards_merge_past_an_unreadable_archive_and_one_given_up_part_way() {
    let tmp = tempfile::tempdir().unwrap();
    let c = campaign(tmp.path());
    std::fs::write(c.join("bad.h5"), b"not an HDF5 file: a copy cut short").unwrap();
    // Another archive of that file name, in another folder: its own failure, kept too.
    std::fs::create_dir(c.join("other")).unwrap();
    std::fs::write(c.join("other/bad.h5"), b"nor is this one").unwrap();
    let files = [c.join("a.h5"), c.join("bad.h5"), c.join("other/bad.h5")];
    let batch = |out: &Path, faults: &str, shard: Option<&str>| {
        skelid()
            .arg("run")
            .args(&files)
            .arg("--out")
            .arg(out)
            .args(["--method", "hilbert", "--quiet"])
            .args(shard.map(|s| ["--shard", s]).into_iter().flatten())
            .env("SKELID_READ_FAULT", faults)
            .output()
            .expect("run skelid run")
    };
    let whole = tmp.path().join("whole");
    let o = batch(&whole, "", None);
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    let shards = |tag: &str, faults: &str| -> Vec<(PathBuf, String)> {
        ["1/2", "2/2"]
            .iter()
            .map(|s| {
                let out = tmp.path().join(format!("{tag}{}", &s[..1]));
                let o = batch(&out, faults, Some(s));
                assert_eq!(o.status.code(), Some(1), "{o:?}");
                (out, String::from_utf8_lossy(&o.stderr).into_owned())
            })
            .collect()
    };
    let paths_of = |m: &serde_json::Value| -> Vec<String> {
        (m["runs"].as_array().unwrap().iter())
            .map(|r| r["path"].as_str().unwrap().to_string())
            .collect()
    };

    // The two bad.h5 alone: merged, it is the unsharded batch.
    let clean = shards("clean", "");
    let merged = tmp.path().join("merged-clean");
    let o = merge(&[&clean[0].0, &clean[1].0], &merged);
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    assert_same_rows(&summary_rows(&whole), &summary_rows(&merged));
    assert_same_results(&results(&whole), &results(&merged));
    let manifest = manifest_of(&merged);
    assert_eq!(manifest["runs_in_inputs"], 13);
    let incomplete = manifest["incomplete_archives"].as_array().unwrap();
    assert_eq!(incomplete.len(), 2, "{manifest}");
    for i in incomplete {
        assert!(i["archive"].as_str().unwrap().ends_with("bad.h5"));
        assert!(
            i["runs_in_archive"].is_null() && i["shard"].is_null(),
            "{i}"
        );
    }
    let failed: Vec<String> = (results(&merged).into_iter())
        .map(|r| r.0)
        .filter(|p| p.starts_with("/_unreadable/"))
        .collect();
    assert_eq!(
        failed,
        ["/_unreadable/bad.h5", "/_unreadable/bad.h5@bad.h5"]
    );

    // The shard with at least 4 runs of a.h5: its first three stop three children in a row.
    let (k, own) = (clean.iter().enumerate())
        .map(|(k, (d, _))| (k, paths_of(&manifest_of(d))))
        .find(|(_, p)| p.iter().filter(|p| !p.starts_with("/_unreadable/")).count() >= 4)
        .expect("a shard with 4 of the 11 runs");
    let own: Vec<String> = own
        .into_iter()
        .filter(|p| !p.starts_with("/_unreadable/"))
        .collect();
    let faults: Vec<String> = own[..3].iter().map(|p| format!("crash:{p}")).collect();
    let faulty = shards("faulty", &faults.join(","));
    let unread = own.len() - 3;
    let said = format!(
        "warning: archive {} was given up part-way by shard {}/2's reading child: {unread} of \
         that shard's runs of it are neither identified nor failed in these results",
        files[0].display(),
        k + 1
    );
    assert!(faulty[k].1.contains(&said), "{}", faulty[k].1);
    assert!(!faulty[1 - k].1.contains("given up part-way"));
    let manifest = manifest_of(&faulty[k].0);
    let given_up = &manifest["incomplete_archives"][0];
    assert!(given_up["archive"].as_str().unwrap().ends_with("a.h5"));
    assert_eq!(given_up["runs_in_archive"], 11, "{manifest}");
    assert_eq!(given_up["runs_not_read"], unread, "{manifest}");

    // Merged, the shards given the other way round: every run either shard kept, bad.h5's
    // failure once, the unread runs counted and named.
    let merged = tmp.path().join("merged-faulty");
    let o = merge(&[&faulty[1].0, &faulty[0].0], &merged);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains(&said), "{err}");
    let log = faulty[k].0.join("skelid.log");
    assert!(
        err.contains(&format!("under /_unreadable/ and {})", log.display())),
        "the shard's log named: {err}"
    );
    let last = String::from_utf8_lossy(&o.stdout);
    assert!(
        last.contains(&format!(", {unread} run(s) left unread (see the warnings)")),
        "{last}"
    );
    let mut kept = results(&faulty[0].0);
    kept.extend(results(&faulty[1].0));
    kept.sort_by(|a, b| a.0.cmp(&b.0));
    kept.dedup_by(|a, b| a.0 == b.0 && a.0.starts_with("/_unreadable/bad.h5"));
    assert_same_results(&results(&merged), &kept);
    let mut expected: Vec<String> = (results(&whole).into_iter())
        .map(|r| r.0)
        .filter(|p| !own[3..].contains(p))
        .chain(["/_unreadable/a.h5".to_string()])
        .collect();
    expected.sort();
    let found: Vec<String> = results(&merged).into_iter().map(|r| r.0).collect();
    assert_eq!(found, expected);
    let manifest = manifest_of(&merged);
    assert_eq!(manifest["runs_in_inputs"], found.len());
    let incomplete = manifest["incomplete_archives"].as_array().unwrap();
    assert_eq!(incomplete.len(), 3, "{manifest}");
    let page = std::fs::read_to_string(merged.join("report.html")).unwrap();
    assert!(
        page.contains("was given up part-way by shard"),
        "Inputs to check"
    );
    // A merged folder is not a shard.
    let o = merge(&[&merged], &tmp.path().join("again"));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("is a merged folder"), "{err}");
}

/// A memory budget smaller than two runs holds the second back: the runs go one at a time
/// on two workers, the log and the terminal say so, and the results are those of the batch
/// without a bound. A budget of no bytes, or not a number, is refused before anything runs.
#[test]
fn a_memory_budget_holds_runs_back_and_changes_no_result() {
    let tmp = tempfile::tempdir().unwrap();
    let archive = campaign(tmp.path()).join("a.h5");
    let batch = |out: &Path, extra: &[&str]| {
        skelid()
            .arg("run")
            .arg(&archive)
            .arg("--out")
            .arg(out)
            .args(["--method", "hilbert", "--quiet", "--jobs", "2"])
            .args(extra)
            .output()
            .expect("run skelid run")
    };
    let free = tmp.path().join("free");
    // A bound no run meets, whatever this machine (or its cgroup) has available.
    let o = batch(&free, &["--memory", "1000"]);
    // The demo's run without relative motion fails by Hilbert alone: exit status 1.
    let status = o.status.code();
    assert!(
        matches!(status, Some(0 | 1)),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(!String::from_utf8_lossy(&o.stderr).contains("waited for memory"));
    // 10 MB: a demo run (30 000 samples) is estimated at about 18 MB, so each runs alone.
    let held = tmp.path().join("held");
    let o = batch(&held, &["--memory", "0.01"]);
    let said = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), status, "{said}");
    println!("{said}");
    assert!(
        // How many waited depends on whether the reader came before the worker was done.
        said.contains("run(s) waited for memory, so at most 1 were in flight at once"),
        "{said}"
    );
    let log = log_of(&held);
    assert!(
        log.contains("memory: the runs in flight may take 10.0 MB together (--memory)"),
        "{log}"
    );
    assert!(log.contains("at most 1 were in flight at once"), "{log}");
    assert_same_rows(&summary_rows(&free), &summary_rows(&held));
    for bad in ["0", "-1", "lots"] {
        let o = batch(&tmp.path().join("bad"), &["--memory", bad]);
        let said = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{said}");
        assert!(said.contains("--memory takes the gigabytes"), "{said}");
    }
    assert!(
        !tmp.path().join("bad").exists(),
        "nothing written for a refused option"
    );
}

#[test]
fn three_shards_merged_equal_one_run() {
    let tmp = tempfile::tempdir().unwrap();
    let inputs = campaign(tmp.path());
    let whole = tmp.path().join("whole");
    assert!(run(&["--method", "wavelet"], &inputs, &whole)
        .status
        .success());
    let shards: Vec<PathBuf> = (1..=3)
        .map(|k| tmp.path().join(format!("shard{k}")))
        .collect();
    let children: Vec<_> = shards
        .iter()
        .enumerate()
        .map(|(i, dir)| {
            skelid()
                .arg("run")
                .arg(&inputs)
                .arg("--out")
                .arg(dir)
                .args(["--quiet", "--method", "wavelet", "--shard"])
                .arg(format!("{}/3", i + 1))
                .output()
                .unwrap()
        })
        .collect();
    let sizes: Vec<usize> = shards.iter().map(|d| results(d).len()).collect();
    for c in &children {
        assert!(c.status.success(), "{}", String::from_utf8_lossy(&c.stderr));
    }
    println!("shard sizes: {sizes:?}");
    assert_eq!(sizes.iter().sum::<usize>(), 33);
    assert!(sizes.iter().all(|&s| s > 0));

    let merged = tmp.path().join("merged");
    // A merge stopped by a scheduler's SIGTERM part-way (its runs linked, results.h5.tmp
    // begun) says so, status 130, removes the .tmp, and the same merge then finishes it,
    // below.
    let stopped = skelid()
        .arg("merge")
        .args(&shards)
        .arg("--out")
        .arg(&merged)
        .env("SKELID_MERGE_PAUSE_MS", "20000")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while !merged.join("results.h5.tmp").exists() {
        assert!(
            std::time::Instant::now() < deadline,
            "the merge did not begin results.h5"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    // SAFETY: kill(2) on our own child's pid, which has not been waited for.
    assert_eq!(
        unsafe { libc::kill(stopped.id() as libc::pid_t, libc::SIGTERM) },
        0
    );
    let o = stopped.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(130), "{err}");
    let said = "the same `skelid merge` finishes it, keeping the runs linked so far";
    assert!(
        err.contains("interrupted (Ctrl-C, SIGTERM or SIGHUP): ") && err.contains(said),
        "{err}"
    );
    assert!(log_of(&merged).contains(said));
    assert!(!merged.join("results.h5").exists() && !merged.join("results.h5.tmp").exists());
    let m = merge(&shards, &merged);
    assert!(m.status.success(), "{}", String::from_utf8_lossy(&m.stderr));
    assert_same_rows(&summary_rows(&merged), &summary_rows(&whole));
    assert_same_results(&results(&merged), &results(&whole));
    // Every run path is in all three archives: a.h5's run at the path itself, the others
    // beside it, named after their archive's file and saying where they came from.
    let found = results(&whole);
    let plain: Vec<&str> = found
        .iter()
        .map(|r| r.0.as_str())
        .filter(|p| !p.contains('@'))
        .collect();
    assert_eq!((found.len(), plain.len()), (33, 11), "{found:?}");
    let file = hdf5::File::open(whole.join("results.h5")).unwrap();
    for p in plain {
        for archive in ["a.h5", "b.h5", "c.h5"] {
            let at = if archive == "a.h5" {
                p.to_string()
            } else {
                format!("{p}@{archive}")
            };
            let source: hdf5::types::VarLenUnicode = file
                .group(&at)
                .and_then(|g| g.attr("source"))
                .and_then(|a| a.read_scalar())
                .unwrap_or_else(|e| panic!("{at}: {e}"));
            assert!(
                source.as_str().ends_with(&format!("/{archive}")),
                "{at}: {source}"
            );
        }
    }
    assert!(file.group("/_skelid_staging").is_err());
    // The merged folder's report lists every run of every shard.
    let page = std::fs::read_to_string(merged.join("report.html")).unwrap();
    assert_eq!(
        page.matches("<tr class=").count(),
        summary_rows(&whole).len()
    );
    // Its runs, drawn from the shards' journal files at the end, are drawn as the batch's
    // workers drew them as they finished: the same text and figures, to the byte.
    let sections = |page: &str| -> Vec<String> {
        page.split("<section id=\"run-")
            .skip(1)
            .map(|s| s.split("</section>").next().unwrap().to_string())
            .collect()
    };
    let whole_page = std::fs::read_to_string(whole.join("report.html")).unwrap();
    assert_eq!(sections(&whole_page).len(), 33);
    assert!(sections(&whole_page)[0].contains("<svg"));
    assert_eq!(sections(&page), sections(&whole_page));

    // A missing shard, a shard given twice, an unsharded folder among shards: refused.
    let refuse = |dirs: &[&PathBuf], what: &str| {
        let m = merge(dirs, &tmp.path().join("refused"));
        let err = String::from_utf8_lossy(&m.stderr);
        assert!(!m.status.success() && err.contains(what), "{err}");
    };
    // The merged folder's journal files (hard links to the shards' where they can be)
    // keep what was merged when a shard is run again: a rerun renames new files over the
    // shard's names, never writes into them.
    let files = |dir: &Path| -> Vec<(std::ffi::OsString, Vec<u8>)> {
        let mut f: Vec<_> = std::fs::read_dir(dir.join("runs"))
            .unwrap()
            .map(|e| {
                let e = e.unwrap();
                (e.file_name(), std::fs::read(e.path()).unwrap())
            })
            .collect();
        f.sort();
        f
    };
    use std::os::unix::fs::MetadataExt;
    let inodes = |dir: &Path| -> std::collections::BTreeSet<u64> {
        (std::fs::read_dir(dir.join("runs")).unwrap())
            .map(|e| e.unwrap().metadata().unwrap().ino())
            .collect()
    };
    let merged_files = files(&merged);
    assert_eq!(merged_files.len(), 33);
    let shared = inodes(&shards[0]).intersection(&inodes(&merged)).count();
    println!("{shared} journal files of shard 1 linked into the merged folder");
    assert!(shared > 0, "one file system holds both: linked, not copied");
    let rerun = run(
        &["--method", "wavelet", "--force", "--shard", "1/3"],
        &inputs,
        &shards[0],
    );
    assert!(rerun.status.success());
    assert_eq!(files(&merged), merged_files);
    assert_eq!(
        inodes(&shards[0]).intersection(&inodes(&merged)).count(),
        0,
        "the rerun's files are new ones, not the merged folder's rewritten"
    );
    refuse(&[&shards[0], &shards[1]], "3/3 missing");
    refuse(&[&shards[0], &shards[1], &shards[1]], "given twice");
    refuse(&[&shards[0], &shards[1], &whole], "others are of 3");
}

/// The batch's reader child ends with the batch, however the batch ends: killed with
/// SIGKILL while its reader cannot move (stopped here, as one hung in libhdf5 on a stalled
/// network file system would be, where no broken pipe can end it), the reader does not
/// stay behind.
#[cfg(target_os = "linux")]
#[test]
fn a_batch_killed_from_outside_takes_its_reader_child_with_it() {
    let tmp = tempfile::tempdir().unwrap();
    let inputs = campaign(tmp.path());
    // 660 runs more, as hard links (no space): far more than the pipe to the batch
    // holds, so that the reader is still at work, waiting on the pipe, when the batch
    // is killed.
    for i in 0..60 {
        std::fs::hard_link(inputs.join("a.h5"), inputs.join(format!("l{i:02}.h5"))).unwrap();
    }
    // One worker: the batch takes in few runs ahead of its work, whatever the cores.
    let batch = skelid()
        .arg("run")
        .arg(&inputs)
        .args(["--jobs", "1", "--quiet", "--out"])
        .arg(tmp.path().join("out"))
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // Killed and reaped however the test ends, so that a failure leaves no batch running.
    struct Reaped(std::process::Child);
    impl Drop for Reaped {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let mut batch = Reaped(batch);
    let batch_id = batch.0.id().to_string();
    // Field `n` of /proc/PID/stat as proc(5) numbers them (3 the state, 4 the parent, 22
    // the start time); the command, field 2, may hold spaces, and its last ')' ends it.
    let stat = |pid: &str, n: usize| -> Option<String> {
        let text = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
        let rest = &text[text.rfind(')')? + 2..];
        rest.split(' ').nth(n - 3).map(str::to_string)
    };
    // The reader child: the process whose parent is the batch and whose command line
    // names the reader's subcommand.
    let reader = || -> Option<String> {
        std::fs::read_dir("/proc").ok()?.flatten().find_map(|e| {
            let pid = e.file_name().to_string_lossy().into_owned();
            let cmd = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
            (stat(&pid, 4).as_ref() == Some(&batch_id)
                && String::from_utf8_lossy(&cmd).contains("__read-archives"))
            .then_some(pid)
        })
    };
    // Once a run is committed, the reader is under way (past its start, where it asks
    // for its end to follow the batch's), and 692 runs are still to come.
    wait_for_a_commit(&tmp.path().join("out"));
    let pid = reader().expect("the reader child, still reading");
    let pid_t: libc::pid_t = pid.parse().unwrap();
    // Its start time, so that a process given the same pid later is not taken for it.
    let born = stat(&pid, 22).expect("the reader's start time");
    // SAFETY: kill(2) with a pid read from /proc and a signal number.
    assert_eq!(unsafe { libc::kill(pid_t, libc::SIGSTOP) }, 0);
    batch.0.kill().unwrap();
    batch.0.wait().unwrap();
    let killed = std::time::Instant::now();
    // Gone, or a zombie waiting for whoever adopted it to reap it: not stopped, not running.
    let alive = || {
        stat(&pid, 22).as_ref() == Some(&born)
            && stat(&pid, 3).is_some_and(|state| state != "Z" && state != "X")
    };
    while alive() && killed.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(20));
    }
    let left = alive();
    println!(
        "reader {pid}: {} {:.3} s after the batch was killed",
        if left { "still there" } else { "gone" },
        killed.elapsed().as_secs_f64()
    );
    if left {
        // Not left behind, whatever the outcome.
        // SAFETY: as above.
        unsafe { libc::kill(pid_t, libc::SIGKILL) };
    }
    assert!(!left, "the reader child {pid} outlived the batch");
}
