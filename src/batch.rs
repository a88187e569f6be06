//! `skelid run`: every run of every archive through the identification, in parallel, each
//! result written to `results.h5` as soon as it is done, failed runs recorded with their
//! error, then the summaries.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use rayon::prelude::*;

use crate::identify::{identify, IdentifyOptions};
use crate::ingest::{Archive, IngestOptions};
use crate::inspect::inspect_isolated;
use crate::report::{
    summary_rows, write_summary, ReportError, ResultsWriter, RunOutcome, SummaryRow,
};
use crate::track::Method;

/// What a batch produced.
#[derive(Debug)]
pub struct BatchSummary {
    /// One row per run × method (failed runs included).
    pub rows: Vec<SummaryRow>,
    /// `results.h5` path.
    pub results: PathBuf,
    /// Runs that failed entirely.
    pub failed_runs: usize,
    /// Runs seen.
    pub runs: usize,
}

/// How the archives are opened.
pub enum Isolation<'a> {
    /// Read in this process (trusted files, tests).
    None,
    /// First probe every archive in a child process of this executable, so that a file
    /// on which libhdf5 crashes or hangs is reported failed instead of ending the batch.
    Child {
        /// The skelid executable.
        exe: &'a Path,
        /// Time allowed per archive.
        timeout: Duration,
    },
}

/// Identifies every run of `files` with `methods`, writing `out/results.h5`,
/// `out/summary.json` and `out/summary.csv`. `progress` is called after each run with
/// (done, total).
pub fn run_campaigns(
    files: &[PathBuf],
    ingest: &IngestOptions,
    methods: &[Method],
    options: &IdentifyOptions,
    isolation: Isolation<'_>,
    out: &Path,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<BatchSummary, ReportError> {
    let writer = Mutex::new(ResultsWriter::create(out)?);
    let mut outcomes_failed: Vec<RunOutcome> = Vec::new();
    let mut readable: Vec<PathBuf> = files.to_vec();
    if let Isolation::Child { exe, timeout } = isolation {
        let reports = inspect_isolated(exe, files, ingest, timeout);
        readable.clear();
        for (f, r) in files.iter().zip(reports) {
            match r.error {
                Some(e) => outcomes_failed.push(unreadable(f, &e)),
                None => readable.push(f.clone()),
            }
        }
    }
    let mut archives = Vec::new();
    for f in &readable {
        match Archive::open(f, ingest) {
            Ok(a) => archives.push(a),
            Err(e) => outcomes_failed.push(unreadable(f, &e)),
        }
    }
    let jobs: Vec<(usize, usize)> = archives
        .iter()
        .enumerate()
        .flat_map(|(a, ar)| (0..ar.runs.len()).map(move |r| (a, r)))
        .collect();
    let total = jobs.len() + outcomes_failed.len();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let rows = Mutex::new(Vec::new());
    let write = |o: RunOutcome| -> Result<(), ReportError> {
        let r = writer
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .write_run(&o);
        rows.lock()
            .unwrap_or_else(|p| p.into_inner())
            .push((o.status() == "failed", summary_rows(&o)));
        let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        progress(d, total);
        r
    };
    for o in outcomes_failed {
        write(o)?;
    }
    jobs.par_iter()
        .map(|&(a, r)| {
            let archive = &archives[a];
            let entry = &archive.runs[r];
            let source = archive.file_name().to_string();
            let mut outcome = RunOutcome::new(entry.path.clone(), source);
            let run = entry
                .meta
                .as_ref()
                .map_err(|e| e.to_string())
                .and_then(|m| archive.load(m).map_err(|e| e.to_string()));
            match run {
                Err(e) => outcome.error = Some(e),
                Ok(run) => {
                    outcome.sample_rate = Some(run.meta.sample_rate);
                    outcome.samples = run.output.len();
                    outcome.inertia = run.meta.inertia;
                    for &m in methods {
                        let t0 = Instant::now();
                        let r = identify(&run, m, options).map_err(|e| e.to_string());
                        outcome.methods.push((m, r, t0.elapsed().as_secs_f64()));
                    }
                }
            }
            write(outcome)
        })
        .collect::<Result<Vec<()>, ReportError>>()?;
    let results = writer
        .into_inner()
        .unwrap_or_else(|p| p.into_inner())
        .finish()?;
    let mut collected = rows.into_inner().unwrap_or_else(|p| p.into_inner());
    collected.sort_by(|a, b| {
        let key = |r: &Vec<SummaryRow>| r.first().map(|x| (x.source.clone(), x.run.clone()));
        key(&a.1).cmp(&key(&b.1))
    });
    let failed_runs = collected.iter().filter(|r| r.0).count();
    let rows: Vec<SummaryRow> = collected.into_iter().flat_map(|r| r.1).collect();
    write_summary(out, &rows)?;
    Ok(BatchSummary {
        rows,
        results,
        failed_runs,
        runs: total,
    })
}

/// The record of an archive that could not be opened: one failed "run" at its root.
fn unreadable(file: &Path, error: &dyn std::fmt::Display) -> RunOutcome {
    RunOutcome {
        error: Some(format!("archive unreadable: {error}")),
        ..RunOutcome::new("/".into(), file_name(file))
    }
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| p.display().to_string())
}
