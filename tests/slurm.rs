//! The Slurm recipe for real: a single-node Slurm (Debian's slurm-wlm and munge, configured
//! in a temporary folder by scripts/slurm/local-cluster.sh) runs a 3-task job array of
//! `skelid run --shard K/3` over the demo campaign and the merge queued after it
//! (scripts/slurm/submit.sh); the merged results must equal an unsharded run's, and stay
//! so when one task is run again alone (`SKELID_SHARDS`) and merged again. Skipped,
//! loudly, only where Slurm cannot start (the daemons' logs are printed).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

mod common;
use common::summary_rows as rows;

fn skelid() -> Command {
    Command::new(env!("CARGO_BIN_EXE_skelid"))
}

fn script(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scripts/slurm")
        .join(name)
}

/// Stops the cluster's daemons however the test ends.
struct Cluster(PathBuf);

impl Drop for Cluster {
    fn drop(&mut self) {
        let _ = Command::new("bash")
            .arg(script("local-cluster.sh"))
            .arg("stop")
            .arg(&self.0)
            .output();
    }
}

/// Equal values; numbers to 1e-12 relative. A worker that identified other runs before
/// this one (as a shard's does) may round a value's last bit differently (seen: a fitted
/// clearance of 1.3e-17 rad, zero within its error); the same invocation is bit-for-bit
/// reproducible.
fn same(a: &serde_json::Value, b: &serde_json::Value) -> bool {
    match (a.as_f64(), b.as_f64()) {
        (Some(x), Some(y)) => (x - y).abs() <= 1e-12 * x.abs().max(y.abs()),
        _ => match (a.as_object(), b.as_object()) {
            (Some(p), Some(q)) => p.len() == q.len() && p.iter().all(|(k, v)| same(v, &q[k])),
            _ => a == b,
        },
    }
}

#[test]
fn a_three_task_job_array_and_its_merge_equal_an_unsharded_run() {
    let d = tempfile::tempdir().unwrap();
    let cluster = d.path().join("cluster");
    let started = Command::new("bash")
        .arg(script("local-cluster.sh"))
        .arg("start")
        .arg(&cluster)
        .output()
        .unwrap();
    let _stop = Cluster(cluster.clone());
    if !started.status.success() {
        eprintln!(
            "SKIPPED: Slurm cannot start on this machine, so the job-array recipe was NOT \
             tested:\n{}",
            String::from_utf8_lossy(&started.stderr)
        );
        return;
    }
    let conf = cluster.join("slurm.conf");
    let demo = d.path().join("demo");
    let o = skelid()
        .args(["demo", "--out"])
        .arg(&demo)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let archive = demo.join("demo_campaign.h5");
    let sharded = d.path().join("sharded");
    let o = Command::new("bash")
        .arg(script("submit.sh"))
        .args(["--tasks", "3", "--out"])
        .arg(&sharded)
        .arg(&archive)
        .args(["--", "--backend", "cpu"])
        .env("SLURM_CONF", &conf)
        .env("SKELID", env!("CARGO_BIN_EXE_skelid"))
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "{said}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(said.contains("(3 tasks)"), "{said}");
    // Wait for the queue to empty (the merge is last).
    let drained = || {
        let t0 = Instant::now();
        loop {
            let q = Command::new("squeue")
                .arg("-h")
                .env("SLURM_CONF", &conf)
                .output()
                .unwrap();
            assert!(q.status.success(), "{}", String::from_utf8_lossy(&q.stderr));
            if q.stdout.is_empty() {
                break;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(600),
                "the jobs did not finish in 10 minutes: {}",
                String::from_utf8_lossy(&q.stdout)
            );
            std::thread::sleep(Duration::from_millis(500));
        }
    };
    drained();
    let logs = || -> String {
        let mut s = String::new();
        for e in std::fs::read_dir(&sharded).unwrap().flatten() {
            if e.file_name().to_string_lossy().ends_with(".log") {
                s += &format!(
                    "--- {}\n{}",
                    e.path().display(),
                    std::fs::read_to_string(e.path()).unwrap_or_default()
                );
            }
        }
        s
    };
    // Three shares, each with some of the runs, and the merge of them.
    let mut shares = 0;
    for k in 1..=3 {
        let share = rows(&sharded.join(format!("shard-{k}")));
        assert!(!share.is_empty(), "shard {k} is empty\n{}", logs());
        shares += share.len();
    }
    let merged = sharded.join("merged");
    assert!(merged.join("results.h5").is_file(), "{}", logs());
    // One worker, as each array task has (one CPU each).
    let whole = d.path().join("whole");
    let o = skelid()
        .arg("run")
        .arg(&archive)
        .args(["--backend", "cpu", "--jobs", "1", "--quiet", "--out"])
        .arg(&whole)
        .output()
        .unwrap();
    assert!(o.status.code() == Some(0) || o.status.code() == Some(1));
    let (merged_rows, whole_rows) = (rows(&merged), rows(&whole));
    assert_eq!(merged_rows.len(), 22, "11 runs × 2 methods");
    assert_eq!(shares, 22);
    for (m, w) in merged_rows.iter().zip(&whole_rows) {
        for (key, value) in w.as_object().unwrap() {
            assert!(
                same(&m[key], value),
                "{} {}: {key} merged {} against unsharded {value}",
                w["run"],
                w["method"],
                m[key]
            );
        }
        assert_eq!(m.as_object().unwrap().len(), w.as_object().unwrap().len());
    }

    // Task 2 of 3 run again alone (as after its archive is copied again), then the merge:
    // the task is still shard 2/3, and the merged results are unchanged.
    let sbatch = |args: &[&std::ffi::OsStr]| {
        let o = Command::new("sbatch")
            .args(args)
            .env("SLURM_CONF", &conf)
            .env("SKELID", env!("CARGO_BIN_EXE_skelid"))
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    std::fs::remove_file(sharded.join("shard-2/manifest.json")).unwrap();
    let log = sharded.join("again-%j.log");
    let array = script("skelid-array.sbatch");
    sbatch(&[
        "--array=2".as_ref(),
        "--export=ALL,SKELID_SHARDS=3".as_ref(),
        "--output".as_ref(),
        log.as_os_str(),
        array.as_os_str(),
        sharded.as_os_str(),
        archive.as_os_str(),
        "--backend".as_ref(),
        "cpu".as_ref(),
    ]);
    drained();
    let manifest: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(sharded.join("shard-2/manifest.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(manifest["shard"]["count"], 3, "{}", logs());
    let merge = script("skelid-merge.sbatch");
    sbatch(&[
        "--output".as_ref(),
        log.as_os_str(),
        merge.as_os_str(),
        sharded.as_os_str(),
        "3".as_ref(),
    ]);
    drained();
    assert_eq!(rows(&merged).len(), 22, "{}", logs());
    for (m, w) in rows(&merged).iter().zip(&merged_rows) {
        assert!(same(m, w), "{m} against {w}");
    }
}
