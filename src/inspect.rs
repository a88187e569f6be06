//! `skelid inspect`: what is in a set of archives, and what is wrong with it.

use std::path::PathBuf;

use std::path::Path;
use std::time::Duration;

use serde::{Deserialize, Serialize};

use crate::child::ChildCommand;
use crate::ingest::{Archive, IngestError, IngestOptions, RunMeta};

/// One run's line in the report.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunReport {
    /// Run path.
    pub path: String,
    /// Metadata when readable.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub meta: Option<RunMeta>,
    /// `ok` or `error`.
    pub status: String,
    /// The problem, when there is one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Machine-readable error kind.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error_kind: Option<String>,
}

/// One archive's part of the report.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ArchiveReport {
    /// File as given.
    pub file: String,
    /// Runs found (empty when the file itself failed).
    pub runs: Vec<RunReport>,
    /// File-level problem.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Machine-readable error kind.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error_kind: Option<String>,
    /// Groups holding datasets that are not runs (other dataset names).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub not_runs: Vec<crate::ingest::NotARun>,
}

impl ArchiveReport {
    /// Number of problems (file-level and per run).
    pub fn problems(&self) -> usize {
        self.error.is_some() as usize + self.runs.iter().filter(|r| r.error.is_some()).count()
    }
}

fn run_report(path: String, r: Result<RunMeta, IngestError>) -> RunReport {
    match r {
        Ok(meta) => RunReport {
            path,
            meta: Some(meta),
            status: "ok".into(),
            error: None,
            error_kind: None,
        },
        Err(e) => RunReport {
            path,
            meta: None,
            status: "error".into(),
            error_kind: Some(e.kind().to_string()),
            error: Some(e.to_string()),
        },
    }
}

/// Inspects one archive, reading every run's samples to check them.
pub fn inspect_archive(path: &std::path::Path, options: &IngestOptions) -> ArchiveReport {
    let file = path.display().to_string();
    match Archive::open(path, options) {
        Err(e) => ArchiveReport {
            file,
            runs: vec![],
            error_kind: Some(e.kind().to_string()),
            error: Some(e.to_string()),
            not_runs: vec![],
        },
        Ok(archive) => {
            let runs = archive
                .runs
                .iter()
                .map(|entry| {
                    let checked = entry
                        .meta
                        .clone()
                        .and_then(|m| archive.load(&m).map(|run| run.meta));
                    run_report(entry.path.clone(), checked)
                })
                .collect();
            ArchiveReport {
                file,
                runs,
                error: None,
                error_kind: None,
                not_runs: archive.not_runs.clone(),
            }
        }
    }
}

/// Inspects many archives.
pub fn inspect(paths: &[PathBuf], options: &IngestOptions) -> Vec<ArchiveReport> {
    paths.iter().map(|p| inspect_archive(p, options)).collect()
}

/// The human-readable table.
pub fn render_table(reports: &[ArchiveReport]) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    for rep in reports {
        let _ = writeln!(s, "{}", rep.file);
        if let Some(e) = &rep.error {
            let _ = writeln!(s, "  ERROR {e}");
            continue;
        }
        let w = rep
            .runs
            .iter()
            .map(|r| r.path.len())
            .max()
            .unwrap_or(4)
            .max(4);
        let _ = writeln!(
            s,
            "  {:<w$}  {:>9}  {:>9}  {:>8}  {:<11}  {:<26}  attributes",
            "run", "samples", "rate Hz", "dur s", "kind", "quantities (in -> out)"
        );
        for r in &rep.runs {
            match &r.meta {
                Some(m) => {
                    let q = format!(
                        "{} -> {}",
                        m.input_quantity.map(|q| q.as_str()).unwrap_or("-"),
                        m.output_quantity.as_str()
                    );
                    let mut attrs = Vec::new();
                    if let Some(j) = m.inertia {
                        attrs.push(format!("inertia={j}"));
                    }
                    if m.gravity_stiffness != 0.0 {
                        attrs.push(format!("C={}", m.gravity_stiffness));
                    }
                    if let Some(u) = &m.units {
                        attrs.push(format!("units={u}"));
                    }
                    if let Some(x) = &m.excitation {
                        let short: String = x.chars().take(48).collect();
                        attrs.push(format!("excitation=\"{short}\""));
                    }
                    let _ = writeln!(
                        s,
                        "  {:<w$}  {:>9}  {:>9.1}  {:>8.2}  {:<11}  {:<26}  {}",
                        r.path,
                        m.samples,
                        m.sample_rate,
                        m.duration,
                        m.kind.as_str(),
                        q,
                        attrs.join(" ")
                    );
                }
                None => {
                    let _ = writeln!(
                        s,
                        "  {:<w$}  ERROR {}",
                        r.path,
                        r.error.as_deref().unwrap_or("")
                    );
                }
            }
        }
        for g in &rep.not_runs {
            let _ = writeln!(s, "  skipped: {g}");
        }
        let ok = rep.runs.iter().filter(|r| r.error.is_none()).count();
        let _ = writeln!(
            s,
            "  {} run(s), {} ok, {} with problems{}",
            rep.runs.len(),
            ok,
            rep.runs.len() - ok,
            match rep.not_runs.len() {
                0 => String::new(),
                n => format!(", {n} group(s) skipped as not runs"),
            }
        );
    }
    s
}

/// Inspects each archive in a child process (`command`, then the archive's path), so that a
/// crash or hang inside libhdf5 on a corrupt file becomes an error naming that file
/// instead of killing the whole batch. libhdf5 segfaults on some corrupted object headers,
/// which no in-process error handling can catch. Children run in parallel.
pub fn inspect_isolated(
    command: &ChildCommand,
    paths: &[PathBuf],
    options: &IngestOptions,
    timeout: Duration,
) -> Vec<ArchiveReport> {
    use rayon::prelude::*;
    paths
        .par_iter()
        .map(|p| probe_one(command, p, options, timeout))
        .collect()
}

fn failed(file: String, detail: String) -> ArchiveReport {
    let e = IngestError::Corrupt {
        file: file.clone(),
        run: None,
        detail,
    };
    ArchiveReport {
        file,
        runs: vec![],
        error_kind: Some(e.kind().to_string()),
        error: Some(e.to_string()),
        not_runs: vec![],
    }
}

fn probe_one(
    command: &ChildCommand,
    path: &Path,
    options: &IngestOptions,
    timeout: Duration,
) -> ArchiveReport {
    use crate::child::{run_json, ChildFailure};
    let file = path.display().to_string();
    let mut args = command.args.clone();
    args.push(path.as_os_str().to_owned());
    match run_json::<ArchiveReport>(&command.exe, &args, Some(timeout)) {
        Ok(report) => report,
        // Cannot isolate (e.g. no executable): read in-process rather than not at all.
        Err(ChildFailure::Spawn(_)) => inspect_archive(path, options),
        Err(ChildFailure::Hang) => failed(file, hang_detail(timeout)),
        Err(ChildFailure::Crash { status, stderr }) => failed(file, crash_detail(status, &stderr)),
    }
}

/// Why a reading child was stopped after `timeout`.
pub fn hang_detail(timeout: Duration) -> String {
    format!(
        "reading it did not finish within {} s; libhdf5 loops on some corrupt files (a sound \
         archive that is large, or on a slow disk, needs a longer --timeout)",
        timeout.as_secs()
    )
}

/// What a reading child's end says: how it ended (exit status or signal) and the end of
/// its stderr, which says where libhdf5 gave up when it says anything.
pub fn crash_detail(status: std::process::ExitStatus, stderr: &[u8]) -> String {
    let how = match status.code() {
        Some(c) => format!("exit status {c}"),
        None => {
            #[cfg(unix)]
            {
                use std::os::unix::process::ExitStatusExt;
                format!("signal {}", status.signal().unwrap_or(0))
            }
            #[cfg(not(unix))]
            {
                "abnormal termination".to_string()
            }
        }
    };
    // The end of the child's stderr says where libhdf5 gave up, when it says anything.
    let stderr = String::from_utf8_lossy(stderr);
    let stderr = stderr.trim();
    let tail = &stderr[stderr.floor_char_boundary(stderr.len().saturating_sub(300))..];
    if tail.is_empty() {
        format!("libhdf5 crashed reading it ({how})")
    } else {
        format!("libhdf5 crashed reading it ({how}): {tail}")
    }
}
