//! `skelid run`: every run of every archive through the identification, in parallel.
//! Each finished run is committed to the output folder's journal at once (see
//! [`crate::journal`]), so a batch killed at any moment loses only the runs in flight, and
//! the same command run again skips what is committed. `--shard K/N` takes a stable share
//! of the runs; [`merge`] joins the shards' folders.
//!
//! libhdf5 is not thread-safe: the hdf5 crate serialises every call behind one global lock.
//! So only one reader ([`reader`]) and one writer touch HDF5, and the workers do all the
//! CPU work in between, the compression of the results included (see [`run_campaigns`]).
//! Memory: a worker holds one run (its samples and tracks) at a time, and the queues hold
//! one run per worker each, so peak memory is about `3 × jobs × one run`, not the
//! campaign size.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use rayon::prelude::*;

pub mod reader;

use crate::backend::Backend;
use crate::identify::{identify, IdentifyOptions};
use crate::ingest::IngestOptions;
use crate::journal::{
    failed_key, placements, results_group, run_key, settings_fingerprint, settings_record, Entry,
    Journal, Prepared, Stored, RUNS_DIR,
};
use crate::profile::{self, Stage};
use crate::report::html::{self, RunPlots};
use crate::report::{write_summary, ReportError, ResultsWriter, RunOutcome, SummaryRow};
use crate::track::Method;

/// Why a batch or a merge could not go on.
#[derive(Debug, thiserror::Error)]
pub enum BatchError {
    /// Writing an output failed.
    #[error(transparent)]
    Report(#[from] ReportError),
    /// A merge found outputs that do not fit together.
    #[error("cannot merge: {0}")]
    Merge(String),
    /// The batch stopped after runs were identified: they are kept in the journal.
    #[error(
        "{cause}; the runs identified so far are committed in {}: fix the cause and run \
         the same command again to resume from them (they are not redone)",
        journal.display()
    )]
    Interrupted {
        /// What stopped it (in the message, not the error chain, so it is said once).
        cause: Box<BatchError>,
        /// The journal folder (`DIR/runs`).
        journal: PathBuf,
    },
    /// The worker threads asked for (`--jobs`) could not be started.
    #[error("cannot start {jobs} worker thread(s): {detail}")]
    Threads {
        /// Threads asked for.
        jobs: usize,
        /// The system's reason.
        detail: String,
    },
}

/// A share of the runs: the K-th of N (1-based).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Shard {
    /// K, 1..=N.
    pub index: usize,
    /// N.
    pub count: usize,
}

impl Shard {
    /// Parses `K/N`.
    pub fn parse(s: &str) -> Result<Shard, String> {
        let (k, n) = s
            .split_once('/')
            .ok_or_else(|| format!("--shard takes K/N (e.g. 2/8), not {s:?}"))?;
        let k: usize = k
            .trim()
            .parse()
            .map_err(|_| format!("bad K in --shard {s}"))?;
        let n: usize = n
            .trim()
            .parse()
            .map_err(|_| format!("bad N in --shard {s}"))?;
        if n == 0 || k == 0 || k > n {
            return Err(format!("--shard {s}: K must be between 1 and N"));
        }
        Ok(Shard { index: k, count: n })
    }

    /// Whether this shard takes the run `path` of the archive named `source`: a hash of
    /// the two, so the split does not depend on the order the archives were given in.
    pub fn takes(&self, source: &str, path: &str) -> bool {
        // The archive's file name, not the path it was given by.
        let name = crate::journal::base_name(source);
        let h = blake3::hash(format!("{name}\0{path}").as_bytes());
        let v = u64::from_le_bytes(h.as_bytes()[..8].try_into().expect("8 bytes"));
        (v % self.count as u64) as usize == self.index - 1
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// How the archives are opened.
pub enum Isolation<'a> {
    /// Read in this process (trusted files, tests).
    None,
    /// Read the archives in a child process of this executable ([`reader`]), so that a
    /// file on which libhdf5 crashes or hangs is reported failed instead of ending the batch.
    Child {
        /// The skelid executable.
        exe: &'a Path,
        /// Time allowed per archive.
        timeout: Duration,
    },
}

/// Everything a batch is told besides its inputs and output folder.
pub struct BatchOptions<'a> {
    /// Methods, in order.
    pub methods: Vec<Method>,
    /// Identification options.
    pub identify: IdentifyOptions,
    /// How archives are opened.
    pub isolation: Isolation<'a>,
    /// Only this share of the runs.
    pub shard: Option<Shard>,
    /// Redo runs already committed.
    pub force: bool,
    /// Runs identified at once (threads); `None`: one per core. Memory in use is about
    /// this many times one run's working set, whatever the campaign's size.
    pub jobs: Option<usize>,
    /// Runs drawn in full in report.html (the table always lists every run).
    pub report_runs: usize,
    /// Where the wavelet transform's first pass runs.
    pub backend: &'a Backend,
}

/// Runs in flight by default on a GPU backend: the signals of concurrent runs share one
/// GPU submission, so more runs than cores keep the device fed (about 12 MB each).
pub const GPU_JOBS: usize = 32;

/// Where a batch stands, for progress displays.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct Progress {
    /// Runs finished (identified now, or found committed).
    pub done: usize,
    /// Runs in this batch (this shard's).
    pub total: usize,
    /// Of `done`, found committed by an earlier invocation and skipped.
    pub skipped: usize,
    /// Of `done`, failed.
    pub failed: usize,
    /// Results (run × method) so far whose verdict is `suspect` ([`crate::quality`]).
    pub suspect: usize,
    /// Results (run × method) so far whose verdict is `bad`.
    pub bad: usize,
}

/// What a batch produced.
#[derive(Debug)]
pub struct BatchSummary {
    /// One row per run × method (failed runs included).
    pub rows: Vec<SummaryRow>,
    /// `results.h5` path.
    pub results: PathBuf,
    /// Runs that failed entirely.
    pub failed_runs: usize,
    /// Runs in this batch.
    pub runs: usize,
    /// Runs skipped because an earlier invocation had committed them.
    pub skipped: usize,
    /// Groups of the inputs that hold datasets but are not runs (other dataset names).
    pub not_runs: Vec<GroupNotRun>,
}

/// A group of an input archive that holds datasets but is not a run.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct GroupNotRun {
    /// Archive as given.
    pub archive: String,
    /// The group and its datasets.
    #[serde(flatten)]
    pub group: crate::ingest::NotARun,
}

/// The output folder's record of a batch: what was asked and which runs it holds.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    /// `skelid-batch/1`.
    pub format: String,
    /// Settings fingerprint (version, methods, options).
    pub settings: String,
    /// The shard, when the batch was one.
    pub shard: Option<Shard>,
    /// Runs seen in the inputs before sharding (unreadable archives count one each).
    pub runs_in_inputs: usize,
    /// The runs of this folder.
    pub runs: Vec<ManifestRun>,
    /// The settings spelled out ([`crate::journal::settings_record`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub settings_full: Option<serde_json::Value>,
    /// Groups of the inputs that hold datasets but are not runs, so none goes unseen.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub not_runs: Vec<GroupNotRun>,
}

/// One run of a manifest.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct ManifestRun {
    /// Archive file name.
    pub source: String,
    /// Run path.
    pub path: String,
    /// Journal key.
    pub key: String,
    /// `ok` or `failed`.
    pub status: String,
}

impl Manifest {
    /// The manifest of a folder holding `entries`, which it puts in (archive, path) order
    /// for every output.
    fn new(
        settings: String,
        shard: Option<Shard>,
        runs_in_inputs: usize,
        entries: &mut [Entry],
        not_runs: Vec<GroupNotRun>,
        settings_full: Option<serde_json::Value>,
    ) -> Manifest {
        entries.sort_by(|a, b| (&a.source, &a.path).cmp(&(&b.source, &b.path)));
        Manifest {
            format: "skelid-batch/1".into(),
            settings,
            shard,
            runs_in_inputs,
            not_runs,
            settings_full,
            runs: entries
                .iter()
                .map(|e| ManifestRun {
                    source: e.source.clone(),
                    path: e.path.clone(),
                    key: e.key.clone(),
                    status: if e.failed { "failed" } else { "ok" }.into(),
                })
                .collect(),
        }
    }
}

/// Manifest file name in an output folder.
pub const MANIFEST: &str = "manifest.json";

/// What the workers hand the writer.
enum Finished {
    /// A run found committed by an earlier invocation, with its stored results (and its
    /// report plots, decoded by the worker, when it may be drawn).
    Skipped(Entry, Stored, Option<RunPlots>),
    /// A run identified and committed to the journal now, with its report plots.
    Committed(Entry, Prepared, Option<RunPlots>),
    /// A run identified now whose journal file could not be written.
    Failed(ReportError),
}

/// Identifies every run of `files` (this shard's share), skipping runs committed by an
/// earlier invocation unless `force`, and writes `out/results.h5`, `out/summary.json`,
/// `out/summary.csv` and `out/manifest.json`. `progress` is called after each run.
///
/// Three stages joined by bounded queues, so that compute never waits on I/O and memory
/// stays about `jobs` runs whatever the campaign's size: one reader (in a child process
/// when isolated, see [`reader`]) that alone touches the input archives; `jobs` workers
/// that identify each run and encode its results (the compression included); and one
/// writer that alone writes the output folder (journal files, log, progress).
pub fn run_campaigns(
    files: &[PathBuf],
    ingest: &IngestOptions,
    opt: &BatchOptions<'_>,
    out: &Path,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<BatchSummary, BatchError> {
    let journal = Journal::open(out)?;
    let settings = settings_fingerprint(&opt.methods, &opt.identify);
    let mut log = Log::open(out)?;
    log.line(&format!(
        "start: {} archive(s){}, settings {settings}{}",
        files.len(),
        opt.shard.map_or(String::new(), |s| format!(", shard {s}")),
        if opt.force { ", --force" } else { "" }
    ));
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let jobs = match opt.jobs {
        Some(n) => n.max(1),
        None if opt.backend.is_gpu() => GPU_JOBS.max(cores),
        None => cores,
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(jobs)
        .build()
        .map_err(|e| BatchError::Threads {
            jobs,
            detail: e.to_string(),
        })?;
    let counts = reader::Counts::default();
    let isolate = match opt.isolation {
        Isolation::Child { exe, timeout } => Some((exe, timeout)),
        Isolation::None => None,
    };
    // A worker holds one run, the queues one run per worker each: about 3 × jobs runs.
    let (work_tx, work_rx) = std::sync::mpsc::sync_channel::<reader::Delivery>(jobs);
    let (done_tx, done_rx) = std::sync::mpsc::sync_channel::<Finished>(jobs);
    let record = settings_record(&opt.methods, &opt.identify, ingest);
    let results = ResultsWriter::create(out)?;
    results.write_settings(&record)?;
    let drawn = Drawn::new(opt.report_runs);
    let written = std::thread::scope(|scope| {
        let counts = &counts;
        scope.spawn(move || {
            reader::read_all(files, ingest, opt.shard, isolate, counts, &mut |d| {
                work_tx.send(d).map_err(|_| reader::Stopped)
            })
        });
        let drawn = &drawn;
        let writer =
            scope.spawn(|| write_finished(&results, done_rx, log, counts, progress, drawn));
        // A failed send means the writer stopped on an error, which it returns; the
        // workers then stop, and the reader with them.
        let _ = pool.install(|| {
            work_rx.into_iter().par_bridge().try_for_each(|d| {
                let finished = prepare(d, &journal, &settings, opt, drawn);
                done_tx.send(finished).map_err(|_| ())
            })
        });
        drop(done_tx);
        writer.join().expect("the writer does not panic")
    });
    let stopped = |e: BatchError| BatchError::Interrupted {
        cause: Box::new(e),
        journal: out.join(RUNS_DIR),
    };
    let written = match written {
        Ok(w) => w,
        Err(e) => {
            results.abandon();
            return Err(stopped(e));
        }
    };
    let Written {
        mut entries,
        skipped,
        failed,
        mut log,
    } = written;
    let total = entries.len();
    let runs_in_inputs = counts.runs_in_inputs.load(Ordering::Relaxed);
    let (t0, cpu0) = (Instant::now(), profile::thread_cpu());
    entries.sort_by(|(a, _), (b, _)| (&a.source, &a.path).cmp(&(&b.source, &b.path)));
    let (mut entries, written_at): (Vec<Entry>, Vec<String>) = entries.into_iter().unzip();
    if let Err(e) = place_runs(&results, &entries, &written_at) {
        results.abandon();
        return Err(stopped(e));
    }
    let results = results.finish().map_err(|e| stopped(e.into()))?;
    let not_runs: Vec<GroupNotRun> =
        std::mem::take(&mut *counts.not_runs.lock().unwrap_or_else(|p| p.into_inner()))
            .into_iter()
            .map(|(archive, group)| GroupNotRun { archive, group })
            .collect();
    for g in &not_runs {
        log.line(&format!("skipped (not a run) {}: {}", g.archive, g.group));
    }
    let manifest = Manifest::new(
        settings,
        opt.shard,
        runs_in_inputs,
        &mut entries,
        not_runs.clone(),
        Some(record),
    );
    let (rows, failed_runs) = write_outputs(
        &results,
        out,
        &entries,
        &manifest,
        opt.report_runs,
        Some(&drawn),
    )
    .map_err(stopped)?;
    profile::add(Stage::Write, profile::thread_cpu().saturating_sub(cpu0));
    log.line(&format!(
        "where the time went (CPU seconds since the process started): {}",
        profile::snapshot().line()
    ));
    log.line(&format!(
        "end: {total} run(s), {failed} failed, {skipped} skipped; wrote {} and the summaries, report and manifest in {:.2} s",
        results.display(),
        t0.elapsed().as_secs_f64()
    ));
    Ok(BatchSummary {
        rows,
        results,
        failed_runs,
        runs: total,
        skipped,
        not_runs,
    })
}

/// A worker's part: the key, the skip test, the identification and the encoding.
fn prepare(
    d: reader::Delivery,
    journal: &Journal,
    settings: &str,
    opt: &BatchOptions<'_>,
    drawn: &Drawn,
) -> Finished {
    let (key, outcome) = match d {
        reader::Delivery::Unreadable { file, error } => {
            let o = unreadable(&file, &error);
            let key = failed_key(
                &o.source,
                &o.path,
                &o.error_text().unwrap_or_default(),
                settings,
            );
            (key, Err(o))
        }
        reader::Delivery::Run { source, path, run } => {
            let key = match &*run {
                Ok(run) => run_key(run, &source, settings),
                Err(e) => failed_key(&source, &path, e, settings),
            };
            (key, Ok((source, path, *run)))
        }
    };
    if !opt.force {
        if let Some((e, stored)) = journal.load(&key) {
            let plots = match &stored {
                Stored::Encoded(run) if drawn.wants(&e) => Some(run_plots(run)),
                _ => None,
            };
            return Finished::Skipped(e, stored, plots);
        }
    }
    let outcome = match outcome {
        Err(recorded) => recorded,
        Ok((source, path, run)) => identify_run(source, path, run, opt),
    };
    let prepared = profile::time(Stage::Encode, || Prepared::new(&outcome));
    match profile::time(Stage::Write, || journal.commit(&key, prepared)) {
        Ok((entry, prepared)) => {
            let plots = drawn.wants(&entry).then(|| run_plots(prepared.encoded()));
            Finished::Committed(entry, prepared, plots)
        }
        Err(e) => Finished::Failed(e),
    }
}

/// The report's plots of an encoded run (its group in results.h5 is set when drawn).
fn run_plots(run: &crate::report::encoded::EncodedRun) -> RunPlots {
    profile::time(Stage::Encode, || html::encoded_plots(run))
}

/// Every method of `opt` on one run as read (or its read error), timed.
fn identify_run(
    source: String,
    path: String,
    run: Result<crate::run::Run, String>,
    opt: &BatchOptions<'_>,
) -> RunOutcome {
    let mut outcome = RunOutcome::new(path, source);
    match run {
        Err(e) => outcome.error = Some(e),
        Ok(run) => {
            outcome.sample_rate = Some(run.meta.sample_rate);
            outcome.samples = run.output.len();
            outcome.inertia = run.meta.inertia;
            outcome.units = crate::units::Units::of(&run.meta);
            for &m in &opt.methods {
                let t0 = Instant::now();
                outcome.methods.push((
                    m,
                    identify_guarded(&run, m, &opt.identify, opt.backend),
                    t0.elapsed().as_secs_f64(),
                ));
            }
            // Base-motion runs only: the others have no model to simulate yet.
            if let Some(n) = opt.identify.refine {
                if run.meta.kind == crate::run::RunKind::BaseMotion {
                    // The refinement's simulations are identified one after another, each
                    // waiting on the last: a GPU's batching gains nothing there, and its
                    // gathering window would be added to each, so they run on the CPU.
                    let cpu = Backend::cpu();
                    let identifier = crate::identify::Identifier {
                        options: &opt.identify,
                        backend: &cpu,
                    };
                    outcome.refined =
                        Some(crate::refine::refine(&run, n, identifier).map_err(|e| e.to_string()));
                }
            }
        }
    }
    outcome
}

/// The writer: commits each finished run, logs it and reports progress. Returns the
/// entries, the skipped and failed counts and the log; stops at the first write error.
fn write_finished(
    results: &ResultsWriter,
    done: std::sync::mpsc::Receiver<Finished>,
    mut log: Log,
    counts: &reader::Counts,
    progress: &(dyn Fn(Progress) + Sync),
    drawn: &Drawn,
) -> Result<Written, BatchError> {
    let (mut entries, mut skipped, mut failed) = (Vec::new(), 0, 0);
    let (mut suspect, mut bad) = (0, 0);
    let mut used = std::collections::HashSet::new();
    for f in done {
        // Finishing order is not the final order: a path already used (the same path in
        // two archives) goes aside now and is put in its place at the end.
        let (path, source) = match f {
            Finished::Skipped(ref e, ..) | Finished::Committed(ref e, ..) => {
                (results_group(&e.path, &e.source), e.source.clone())
            }
            Finished::Failed(e) => return Err(e.into()),
        };
        let dst = if used.insert(path.clone()) {
            path
        } else {
            format!("{path}@{source}#{}", entries.len())
        };
        let t0 = profile::thread_cpu();
        let (e, was_skipped, plots) = match f {
            Finished::Skipped(e, Stored::Encoded(run), plots) => {
                results.write_encoded_as(&run, &dst)?;
                (e, true, plots)
            }
            Finished::Skipped(e, Stored::Legacy(file), plots) => {
                results.copy_run_from(&file, &e.path, &dst)?;
                (e, true, plots)
            }
            Finished::Committed(e, p, plots) => {
                results.write_encoded_as(p.encoded(), &dst)?;
                (e, false, plots)
            }
            Finished::Failed(_) => unreachable!("returned above"),
        };
        profile::add(Stage::Write, profile::thread_cpu().saturating_sub(t0));
        log.line(&format!(
            "{} {}:{} {}{}",
            if was_skipped {
                "skipped (committed earlier)"
            } else {
                "done"
            },
            e.source,
            e.path,
            if e.failed { "failed" } else { "ok" },
            e.rows
                .iter()
                .filter(|r| !r.error.is_empty())
                .map(|r| format!(" [{}: {}]", r.method, r.error))
                .collect::<String>()
        ));
        skipped += usize::from(was_skipped);
        failed += usize::from(e.failed);
        suspect += e.rows.iter().filter(|r| r.quality == "suspect").count();
        bad += e.rows.iter().filter(|r| r.quality == "bad").count();
        drawn.offer(&e, plots);
        entries.push((e, dst));
        progress(Progress {
            done: entries.len(),
            total: counts.estimate().max(entries.len()),
            skipped,
            failed,
            suspect,
            bad,
        });
    }
    Ok(Written {
        entries,
        skipped,
        failed,
        log,
    })
}

/// What the writer leaves: every entry with the group it was written to in results.h5.
struct Written {
    entries: Vec<(Entry, String)>,
    skipped: usize,
    failed: usize,
    log: Log,
}

/// The report plots of the runs that come first in the report's order (archive, then
/// path), at most as many as it draws: kept as runs finish, so that the end of a batch
/// reads none of them back from results.h5 (that read-back, serial under libhdf5's lock,
/// was 6 % of a 200-run batch's CPU time and all of its tail).
///
/// Shared by the workers and the writer: a worker decodes a run's plots only when the run
/// can still be drawn ([`Drawn::wants`]), since once `keep` runs are held a run that comes
/// after all of them never will be (decoding every run's was 3.6 ms of CPU per run).
struct Drawn {
    keep: usize,
    /// `None` where the plots must be read back: none were decoded (a legacy journal
    /// file), or two runs share the archive name and path.
    plots: std::sync::Mutex<BTreeMap<(String, String), Option<RunPlots>>>,
}

impl Drawn {
    fn new(keep: usize) -> Drawn {
        Drawn {
            keep,
            plots: std::sync::Mutex::new(BTreeMap::new()),
        }
    }

    fn held(&self) -> std::sync::MutexGuard<'_, BTreeMap<(String, String), Option<RunPlots>>> {
        self.plots.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Whether run `e` may still be drawn: fewer than `keep` runs are held, or it comes
    /// before the last of them. Once false for a run it stays false (the last held run
    /// only moves earlier).
    fn wants(&self, e: &Entry) -> bool {
        if self.keep == 0 {
            return false;
        }
        let held = self.held();
        held.len() < self.keep
            || held
                .last_key_value()
                .is_some_and(|(k, _)| (&e.source, &e.path) <= (&k.0, &k.1))
    }

    /// Keeps `plots` of the run `e` if it is among the first `keep` so far.
    fn offer(&self, e: &Entry, plots: Option<RunPlots>) {
        if self.keep == 0 {
            return;
        }
        let mut held = self.held();
        match held.entry((e.source.clone(), e.path.clone())) {
            std::collections::btree_map::Entry::Occupied(mut o) => {
                o.insert(None);
            }
            std::collections::btree_map::Entry::Vacant(v) => {
                v.insert(plots);
            }
        }
        if held.len() > self.keep {
            held.pop_last();
        }
    }

    /// The plots of run `e`, drawn as the run at `group` of results.h5.
    fn take(&self, e: &Entry, group: &str) -> Option<RunPlots> {
        let mut p = self
            .held()
            .get_mut(&(e.source.clone(), e.path.clone()))?
            .take()?;
        p.path = group.to_string();
        Some(p)
    }
}

/// Puts every run of `results` at its final group (see [`placements`]): link moves, through
/// a staging group so that two runs may trade places.
fn place_runs(
    results: &ResultsWriter,
    entries: &[Entry],
    written_at: &[String],
) -> Result<(), BatchError> {
    const STAGING: &str = "/_skelid_staging";
    let moves: Vec<(&String, String)> = written_at
        .iter()
        .zip(placements(entries))
        .filter(|(at, want)| *at != want)
        .collect();
    for (i, (at, _)) in moves.iter().enumerate() {
        results.move_run(at, &format!("{STAGING}/{i}"))?;
    }
    for (i, (_, want)) in moves.iter().enumerate() {
        results.move_run(&format!("{STAGING}/{i}"), want)?;
    }
    if !moves.is_empty() {
        results.remove(STAGING)?;
    }
    Ok(())
}

/// One method on one run, with a panic inside any stage turned into that run's error.
fn identify_guarded(
    run: &crate::run::Run,
    method: Method,
    options: &IdentifyOptions,
    backend: &Backend,
) -> Result<crate::identify::Identification, String> {
    guarded(|| identify(run, method, options, backend).map_err(|e| e.to_string()))
}

/// Runs `f`, turning a panic into an error that names it.
pub fn guarded<T>(f: impl FnOnce() -> Result<T, String>) -> Result<T, String> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => Err(format!(
            "internal error (panic) in the identification: {}",
            crate::backend::panic_message(p.as_ref())
        )),
    }
}

/// The summaries, report.html (the first `report_runs` runs drawn, from `drawn` where it
/// holds them, else read back from results.h5) and the manifest of a folder's entries
/// (results.h5 is written by then).
fn write_outputs(
    results: &Path,
    out: &Path,
    entries: &[Entry],
    manifest: &Manifest,
    report_runs: usize,
    drawn_plots: Option<&Drawn>,
) -> Result<(Vec<SummaryRow>, usize), BatchError> {
    let rows: Vec<SummaryRow> = entries.iter().flat_map(|e| e.rows.clone()).collect();
    write_summary(out, &rows)?;
    let drawn = entries.len().min(report_runs);
    let title = std::fs::canonicalize(out).unwrap_or_else(|_| out.to_path_buf());
    html::write_report(
        out,
        &html::ReportPage {
            title: &title.display().to_string(),
            settings: &manifest.settings,
            rows: &rows,
            runs: placements(&entries[..drawn])
                .iter()
                .zip(entries)
                .map(
                    |(group, e)| match drawn_plots.and_then(|d| d.take(e, group)) {
                        Some(p) => Ok(p),
                        None => html::read_run(results, group),
                    },
                )
                .collect(),
            omitted: entries.len() - drawn,
        },
    )?;
    let text = serde_json::to_string_pretty(manifest).map_err(|e| ReportError {
        file: MANIFEST.into(),
        detail: e.to_string(),
    })?;
    crate::report::write_atomic(&out.join(MANIFEST), text.as_bytes())?;
    Ok((rows, entries.iter().filter(|e| e.failed).count()))
}

/// Joins the output folders of the shards of one batch into `out` (drawing the first
/// `report_runs` runs in its report.html): refuses folders made
/// with different settings, a shard given twice or missing, a run present in two shards,
/// or a shard whose runs are not all committed.
pub fn merge(dirs: &[PathBuf], out: &Path, report_runs: usize) -> Result<BatchSummary, BatchError> {
    let bad = |m: String| BatchError::Merge(m);
    let mut manifests = Vec::new();
    for d in dirs {
        let f = d.join(MANIFEST);
        let text = std::fs::read_to_string(&f).map_err(|e| {
            bad(format!(
                "{}: {e} (is {} the output folder of a finished `skelid run`?)",
                f.display(),
                d.display()
            ))
        })?;
        let m: Manifest = serde_json::from_str(&text)
            .map_err(|e| bad(format!("{}: not a skelid manifest: {e}", f.display())))?;
        manifests.push((d.clone(), m));
    }
    let Some((_, first)) = manifests.first() else {
        return Err(bad("no folders given".into()));
    };
    let settings = first.settings.clone();
    let count = first.shard.map_or(1, |s| s.count);
    let mut seen_shards = BTreeMap::new();
    for (d, m) in &manifests {
        if m.settings != settings {
            return Err(bad(format!(
                "{} was made with other settings (skelid version, methods or options) than {}",
                d.display(),
                manifests[0].0.display()
            )));
        }
        if m.runs_in_inputs != first.runs_in_inputs {
            return Err(bad(format!(
                "{} saw {} runs in its inputs, {} saw {}: the shards were not given the same archives",
                d.display(),
                m.runs_in_inputs,
                manifests[0].0.display(),
                first.runs_in_inputs
            )));
        }
        let s = m.shard.unwrap_or(Shard { index: 1, count: 1 });
        if s.count != count {
            return Err(bad(format!(
                "{} is shard {s}, others are of {count}",
                d.display()
            )));
        }
        if let Some(other) = seen_shards.insert(s.index, d.clone()) {
            return Err(bad(format!(
                "shard {s} is given twice: {} and {}",
                other.display(),
                d.display()
            )));
        }
    }
    let missing: Vec<String> = (1..=count)
        .filter(|k| !seen_shards.contains_key(k))
        .map(|k| format!("{k}/{count}"))
        .collect();
    if !missing.is_empty() {
        return Err(bad(format!(
            "shard(s) {} missing: run them (or pass their folders) before merging",
            missing.join(", ")
        )));
    }
    let journal = Journal::open(out)?;
    let mut owner: BTreeMap<(String, String), PathBuf> = BTreeMap::new();
    let mut entries = Vec::new();
    for (d, m) in &manifests {
        let src = Journal::open(d)?;
        for r in &m.runs {
            if let Some(other) = owner.insert((r.source.clone(), r.path.clone()), d.clone()) {
                return Err(bad(format!(
                    "run {} of {} is in both {} and {}",
                    r.path,
                    r.source,
                    other.display(),
                    d.display()
                )));
            }
            let e = src.lookup(&r.key).ok_or_else(|| {
                bad(format!(
                    "{}: run {} is listed but its file {} is missing or unreadable",
                    d.display(),
                    r.path,
                    src.file(&r.key).display()
                ))
            })?;
            let from = src.file(&r.key);
            let dst = out
                .join(RUNS_DIR)
                .join(from.file_name().expect("a journal file has a name"));
            if !dst.exists() {
                std::fs::copy(&from, &dst).map_err(|e| ReportError {
                    file: dst.display().to_string(),
                    detail: e.to_string(),
                })?;
            }
            entries.push(e);
        }
    }
    if entries.len() != first.runs_in_inputs {
        return Err(bad(format!(
            "the shards hold {} runs but their inputs had {}",
            entries.len(),
            first.runs_in_inputs
        )));
    }
    let manifest = Manifest::new(
        settings,
        None,
        first.runs_in_inputs,
        &mut entries,
        first.not_runs.clone(),
        first.settings_full.clone(),
    );
    let results = journal.assemble(out, &entries, manifest.settings_full.as_ref())?;
    let (rows, failed_runs) = write_outputs(&results, out, &entries, &manifest, report_runs, None)?;
    Ok(BatchSummary {
        rows,
        results,
        failed_runs,
        runs: entries.len(),
        skipped: 0,
        not_runs: manifest.not_runs.clone(),
    })
}

/// `<out>/skelid.log`: one line per event, appended, with seconds since the Unix epoch.
struct Log {
    file: std::fs::File,
}

impl Log {
    fn open(out: &Path) -> Result<Log, ReportError> {
        let path = out.join("skelid.log");
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|e| ReportError {
                file: path.display().to_string(),
                detail: e.to_string(),
            })?;
        Ok(Log { file })
    }

    fn line(&mut self, text: &str) {
        use std::io::Write;
        let t = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        // A log line that cannot be written must not stop the batch.
        let _ = writeln!(self.file, "{t:.3} {text}");
    }
}

/// The record of an archive that could not be opened: one failed entry under
/// `/_unreadable/<file name>`.
fn unreadable(file: &Path, error: &dyn std::fmt::Display) -> RunOutcome {
    let name = file_name(file);
    RunOutcome {
        error: Some(format!("archive unreadable: {error}")),
        ..RunOutcome::new(format!("/_unreadable/{}", name.replace('/', "_")), name)
    }
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| p.display().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(source: &str) -> Entry {
        Entry {
            key: source.into(),
            path: "/runs/r".into(),
            source: source.into(),
            failed: false,
            rows: Vec::new(),
        }
    }

    fn plots(source: &str) -> RunPlots {
        RunPlots {
            path: "/runs/r".into(),
            source: source.into(),
            status: "ok".into(),
            error: None,
            methods: Vec::new(),
        }
    }

    #[test]
    fn the_report_keeps_the_first_runs_in_its_order_whatever_order_they_finish_in() {
        let drawn = Drawn::new(2);
        for s in ["c.h5", "a.h5"] {
            assert!(drawn.wants(&entry(s)), "fewer than 2 held: {s} is wanted");
            drawn.offer(&entry(s), Some(plots(s)));
        }
        // Full with a and c: d comes after both and is never drawn; b comes before c.
        assert!(!drawn.wants(&entry("d.h5")));
        assert!(drawn.wants(&entry("b.h5")));
        drawn.offer(&entry("b.h5"), Some(plots("b.h5")));
        assert!(!drawn.wants(&entry("c.h5")), "c was pushed out by b");
        // A second run with a's archive name and path: both are read back from the file.
        drawn.offer(&entry("a.h5"), Some(plots("a.h5")));
        assert!(drawn.take(&entry("a.h5"), "/runs/r").is_none());
        let b = drawn.take(&entry("b.h5"), "/runs/r@b.h5").expect("kept");
        assert_eq!(
            (b.source.as_str(), b.path.as_str()),
            ("b.h5", "/runs/r@b.h5")
        );
        assert!(drawn.take(&entry("c.h5"), "/runs/r").is_none());
        assert!(
            !Drawn::new(0).wants(&entry("a.h5")),
            "nothing drawn: nothing decoded"
        );
    }

    #[test]
    fn a_panic_becomes_the_runs_error() {
        let r: Result<(), String> = guarded(|| panic!("index out of bounds"));
        let e = r.unwrap_err();
        assert!(
            e.contains("panic") && e.contains("index out of bounds"),
            "{e}"
        );
        assert_eq!(guarded(|| Ok::<_, String>(3)), Ok(3));
    }

    #[test]
    fn shards_partition_the_runs_whatever_the_order() {
        let runs: Vec<(String, String)> = (0..300)
            .map(|i| (format!("/data/c{}.h5", i % 7), format!("/runs/run_{i:03}")))
            .collect();
        let n = 3;
        let mut counts = [0; 3];
        for (src, path) in &runs {
            let owners: Vec<usize> = (1..=n)
                .filter(|&k| Shard { index: k, count: n }.takes(src, path))
                .collect();
            assert_eq!(owners.len(), 1);
            counts[owners[0] - 1] += 1;
            // The folder the archive was given from does not matter.
            let moved = src.replace("/data/", "/elsewhere/");
            assert!(Shard {
                index: owners[0],
                count: n
            }
            .takes(&moved, path));
        }
        assert!(counts.iter().all(|&c| c > 70), "{counts:?}");
        assert!(Shard::parse("0/3").is_err() && Shard::parse("4/3").is_err());
        assert_eq!(Shard::parse("2/3"), Ok(Shard { index: 2, count: 3 }));
    }
}
