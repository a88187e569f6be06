//! `skelid inspect`: what is in a set of archives, and what is wrong with it.

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Serialize};

use crate::batch::reader::{read_all, Counts, Delivery};
use crate::child::ChildCommand;
use crate::ingest::{IngestOptions, RunMeta};

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
    /// Runs found: empty when the archive could not be opened, those read before when it
    /// was given up part-way (`error` says why).
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
    /// Read to the end, but the reading child died closing it: how, and what that means.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub damaged: Option<String>,
}

impl ArchiveReport {
    /// Number of problems (file-level, per run, and a crash while closing).
    pub fn problems(&self) -> usize {
        self.error.is_some() as usize
            + self.damaged.is_some() as usize
            + self.runs.iter().filter(|r| r.error.is_some()).count()
    }
}

/// The human-readable table.
pub fn render_table(reports: &[ArchiveReport]) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    for rep in reports {
        let _ = writeln!(s, "{}", rep.file);
        if let Some(e) = &rep.error {
            let _ = writeln!(s, "  ERROR {e}");
            // Given up part-way: the runs read before still listed.
            if rep.runs.is_empty() {
                continue;
            }
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
        if let Some(d) = &rep.damaged {
            let _ = writeln!(s, "  DAMAGED {d}");
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

/// Inspects each archive through `skelid run`'s reader (`command`: its reading child, see
/// [`crate::batch::reader`]), reading every run's samples to check them: libhdf5 crashes
/// (segfault) or loops on some corrupt files, which no in-process handling catches. A run
/// that kills the reading child, or takes more than `timeout` (as does opening the
/// archive), is that run's error and a new child reads on after it; an archive it cannot
/// open is the archive's. Archives are inspected in parallel, each by a child of its own;
/// `done` hears of each as it is finished, in any order. Until 2026-12-07 one child read a
/// whole archive under one `timeout`: a run that crashed it lost the listing of every run,
/// and a large archive could not be listed in time at all.
pub fn inspect_isolated(
    command: &ChildCommand,
    paths: &[PathBuf],
    options: &IngestOptions,
    timeout: Duration,
    done: &(dyn Fn(&ArchiveReport) + Sync),
) -> Vec<ArchiveReport> {
    use rayon::prelude::*;
    paths
        .par_iter()
        .map(|p| {
            let report = inspect_archive(p, options, Some((command, timeout)));
            done(&report);
            report
        })
        .collect()
}

/// Inspects one archive, through a reading child when `isolate` gives its command and the
/// time one step may take, else in this process.
pub fn inspect_archive(
    path: &Path,
    options: &IngestOptions,
    isolate: Option<(&ChildCommand, Duration)>,
) -> ArchiveReport {
    let counts = Counts::default();
    let mut report = ArchiveReport {
        file: path.display().to_string(),
        runs: Vec::new(),
        error: None,
        error_kind: None,
        not_runs: Vec::new(),
        damaged: None,
    };
    let files = [path.to_path_buf()];
    // The reader stops early only when told to, and this never tells it.
    let _ = read_all(&files, options, None, isolate, &counts, &mut |d| {
        match d {
            Delivery::Run {
                path,
                run,
                error_kind,
                ..
            } => report.runs.push(match *run {
                Ok(run) => RunReport {
                    path,
                    meta: Some(run.meta),
                    status: "ok".into(),
                    error: None,
                    error_kind: None,
                },
                Err(error) => RunReport {
                    path,
                    meta: None,
                    status: "error".into(),
                    error: Some(error),
                    error_kind,
                },
            }),
            Delivery::Unreadable {
                error, error_kind, ..
            } => {
                report.error = Some(error);
                report.error_kind = Some(error_kind);
            }
        }
        Ok(())
    });
    report.not_runs = counts.take_not_runs().into_iter().map(|(_, g)| g).collect();
    report.damaged = counts.take_damaged().into_iter().map(|d| d.detail).next();
    report
}

/// What a reading child's end says: how it ended (exit status or signal) and the end of
/// its stderr, which says where libhdf5 gave up when it says anything; `step`: what it was
/// doing to the archive ("opening it", "reading it", "closing it").
pub fn crash_detail(status: std::process::ExitStatus, stderr: &[u8], step: &str) -> String {
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
    // The end of the child's stderr says where libhdf5 gave up, when it says anything: its
    // messages on one line, without the frames of a Rust backtrace (the child inherits
    // RUST_BACKTRACE), whose last 300 characters were all the log kept of a panic.
    let stderr = String::from_utf8_lossy(stderr);
    let mut said = String::new();
    for line in stderr.lines().map(str::trim) {
        if line.is_empty() || is_backtrace_line(line) {
            continue;
        }
        // A line ending in a colon introduces the next (a panic's place, its message).
        if !said.is_empty() {
            said.push_str(if said.ends_with(':') { " " } else { "; " });
        }
        said.push_str(&without_thread_id(line));
    }
    let tail = &said[said.floor_char_boundary(said.len().saturating_sub(300))..];
    if tail.is_empty() {
        format!("libhdf5 crashed {step} ({how})")
    } else {
        format!("libhdf5 crashed {step} ({how}): {tail}")
    }
}

/// A panic's line without its thread's id (`thread 'main' (20938) panicked` reads
/// `thread 'main' panicked`): the id differs in every child, and a failed run's journal key
/// hashes its error, so that a run failing the same way on a rerun is found committed.
fn without_thread_id(line: &str) -> String {
    if let Some(rest) = line.strip_prefix("thread '") {
        if let Some((name, after)) = rest.split_once("' (") {
            if let Some((id, tail)) = after.split_once(')') {
                if !id.is_empty() && id.bytes().all(|b| b.is_ascii_digit()) {
                    return format!("thread '{name}'{tail}");
                }
            }
        }
    }
    line.to_string()
}

/// Whether a line of stderr (trimmed) belongs to a Rust backtrace: its header, a frame
/// (`12: name`), a frame's place (`at src/x.rs:1:2`), or the note about them.
fn is_backtrace_line(line: &str) -> bool {
    let frame = line
        .split_once(": ")
        .is_some_and(|(n, _)| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
    // `at ./src/main.rs:40:37`: a path ending in a line and a column.
    let place = line.strip_prefix("at ").is_some_and(|p| {
        let mut end = p.rsplitn(3, ':');
        let numeric = |s: Option<&str>| {
            s.is_some_and(|s| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit()))
        };
        numeric(end.next()) && numeric(end.next()) && end.next().is_some()
    });
    frame
        || place
        || line == "stack backtrace:"
        || (line.starts_with("note: ") && line.contains("backtrace"))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A child's panic reads as its message on one line, not as the end of a backtrace,
    /// and without the thread's id, which differs in every child; libhdf5's own error
    /// stack is kept.
    #[test]
    fn a_crash_says_what_the_child_said_without_its_backtrace() {
        use std::os::unix::process::ExitStatusExt;
        let stderr = "\nthread 'main' (20938) panicked at src/h5util.rs:80:25:\n\
            memory allocation of 8223683306334676351 bytes failed\nstack backtrace:\n   \
            0: __rustc::rust_begin_unwind\n   27: main\n             at ./src/main.rs:40:37\n\
            note: Some details are omitted, run with `RUST_BACKTRACE=full` for a verbose \
            backtrace.\nthread caused non-unwinding panic. aborting.\n";
        let said = crash_detail(
            std::process::ExitStatus::from_raw(6),
            stderr.as_bytes(),
            "reading it",
        );
        println!("{said}");
        assert_eq!(
            said,
            "libhdf5 crashed reading it (signal 6): thread 'main' panicked at \
             src/h5util.rs:80:25: memory allocation of 8223683306334676351 bytes failed; \
             thread caused non-unwinding panic. aborting."
        );
        // A line of the child's own that starts with "at" stays.
        let hdf5 = "HDF5-DIAG: Error detected in HDF5 (1.14.5) thread 1:\n  \
            #000: H5D.c line 1061 in H5Dread(): can't read data\n    major: Dataset\n\
            at the end\n";
        let said = crash_detail(
            std::process::ExitStatus::from_raw(11),
            hdf5.as_bytes(),
            "reading it",
        );
        assert!(
            said.ends_with(
                "thread 1: #000: H5D.c line 1061 in H5Dread(): can't read data; major: Dataset; \
                 at the end"
            ),
            "{said}"
        );
        assert_eq!(
            crash_detail(std::process::ExitStatus::from_raw(9), b"", "reading it"),
            "libhdf5 crashed reading it (signal 9)"
        );
    }
}
