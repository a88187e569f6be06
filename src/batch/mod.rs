//! `skelid run`: every run of every archive through the identification, in parallel.
//! Each finished run is committed to the output folder's journal at once (see
//! [`crate::journal`]), so a batch killed at any moment loses only the runs in flight, and
//! the same command run again skips what is committed. `--shard K/N` takes a stable share
//! of the runs; [`merge`] joins the shards' folders.
//!
//! libhdf5 is not thread-safe: the hdf5 crate serialises every call behind one global lock.
//! So only one reader ([`reader`]) and one writer touch HDF5, and the workers do all the
//! CPU work in between, the compression of the results included (see [`run_campaigns`]).
//! Memory: a worker holds one run (its samples and tracks) at a time, one more waits for it
//! in the pool, and the queues hold a run's samples or results per worker each, so peak
//! memory is about `3 × jobs × one run`, not the campaign size; each run is admitted within
//! a memory budget ([`memory`]) before it is queued, and counted until it is written.

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

pub mod disk;
mod lock;
mod manifest;
pub mod memory;
mod merge;
pub mod reader;
mod worker;
mod writer;

pub use lock::FolderLock;
pub use manifest::{
    DamagedArchive, GroupNotRun, IncompleteArchive, Manifest, ManifestRun, MANIFEST,
};
pub use merge::merge;
pub use worker::guarded;
use worker::{prepare_caught, Work};
use writer::{
    page_runs, place_runs, unreadable, write_finished, write_manifest, write_pages, Drawn, Log,
    Written, UNREADABLE,
};

use crate::backend::Backend;
use crate::hint::Hint;
use crate::identify::IdentifyOptions;
use crate::ingest::IngestOptions;
use crate::journal::{
    settings_fingerprint, settings_record, Entry, Journal, Prepared, Stored, RUNS_DIR,
};
use crate::profile::{self, Stage};
use crate::report::html::DrawnRun;
use crate::report::{ReportError, ResultsFile, SummaryRow};
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
    /// Another process is writing the folder (a batch or merge into it, still running).
    #[error("{} is in use by {holder}: {advice}", folder.display())]
    InUse {
        /// The output folder, or the shard folder a merge was given.
        folder: PathBuf,
        /// Who: the last lock its log records taken ("skelid's batch of pid 4242, started
        /// 3 min 12 s ago").
        holder: String,
        /// What to do.
        advice: String,
    },
    /// The batch's reader or writer thread could not be started.
    #[error("cannot start the batch's {role} thread: {detail}")]
    SerialThread {
        /// `reader` or `writer`.
        role: &'static str,
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
            .ok_or_else(|| format!("{} takes K/N (e.g. 2/8), not {s:?}", Hint::Shard))?;
        let k: usize = k
            .trim()
            .parse()
            .map_err(|_| format!("bad K in {} {s}", Hint::Shard))?;
        let n: usize = n
            .trim()
            .parse()
            .map_err(|_| format!("bad N in {} {s}", Hint::Shard))?;
        if n == 0 || k == 0 || k > n {
            return Err(format!("{} {s}: K must be between 1 and N", Hint::Shard));
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
    /// file or run on which libhdf5 crashes or hangs is reported failed instead of ending the
    /// batch.
    Child {
        /// The reader child's command (its hidden command with the ingest options and the
        /// shard, built by the front end; the archives go on its stdin).
        command: &'a crate::child::ChildCommand,
        /// Time one step of the reading child may take (opening an archive, reading one
        /// run) before that archive, or that run, is recorded failed (see
        /// [`reader::DEATHS_IN_A_ROW`]).
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
    /// Each run's figures written as files too (`None`: only report.html draws them).
    pub figures: Option<Figures>,
    /// Bytes the runs in flight may take together (`None`: three quarters of the memory
    /// available when the batch starts; see [`memory`]).
    pub memory: Option<u64>,
}

/// Where and how a batch writes each run's figures: `DIR/ARCHIVE/RUN/NN-title.EXT`
/// ([`crate::report::figure_files`]), written by the worker that identified the run, or
/// that found it committed by an earlier invocation.
#[derive(Debug, Clone)]
pub struct Figures {
    /// The folder (the CLI's `OUT/figures`).
    pub dir: std::path::PathBuf,
    /// The files' format.
    pub format: crate::report::figure_files::FigureFormat,
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
    /// The output disk's free bytes and what the runs left need at the batch's rate so
    /// far; `None` for the first few runs, or where the disk cannot be asked.
    pub disk: Option<disk::Room>,
    /// True on the one report where the runs left were first found not to fit the disk
    /// ([`disk::Room::warning`] says it; skelid.log has it too).
    #[serde(skip)]
    pub disk_short_now: bool,
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
    /// Archives read to the end that the reading child died closing: no run lost, the
    /// files likely damaged ([`DamagedArchive`]).
    pub damaged: Vec<DamagedArchive>,
    /// Archives given up before their end or never opened ([`IncompleteArchive`]).
    pub incomplete: Vec<IncompleteArchive>,
    /// Where the memory budget held runs back, what it did (the batch then ran fewer runs
    /// at once than `--jobs`).
    pub memory_held_back: Option<memory::Usage>,
    /// Why the output folder could not be locked, where its file system refuses locks
    /// ([`FolderLock::unguarded`], the same where the caller had taken the folder first).
    pub unguarded: Option<String>,
}

/// Where a worker put a run's data in results.h5: `Ok(None)` where it put none (no placer,
/// nothing to place), an error where its write failed (the writer then writes them).
pub(super) type Placement = std::io::Result<Option<crate::report::PlacedData>>;

/// What the workers hand the writer.
pub(super) enum Finished {
    /// A run found committed by an earlier invocation, with its stored results (and its
    /// report figures, drawn by the worker, when it may be shown), and where the worker
    /// put its data in results.h5.
    Skipped(Entry, Stored, Option<DrawnRun>, Placement),
    /// A run identified and committed to the journal now, with its report figures and
    /// where the worker put its data in results.h5.
    Committed(Entry, Prepared, Option<DrawnRun>, Placement),
    /// A run identified now whose journal file could not be written.
    Failed(ReportError),
}

impl Finished {
    /// Bytes of the results it holds in memory until the writer is done with it.
    fn data_bytes(&self) -> u64 {
        match self {
            Finished::Skipped(_, Stored::Encoded(run), ..) => run.data_bytes(),
            Finished::Committed(_, p, ..) => p.encoded().data_bytes(),
            Finished::Skipped(_, Stored::Legacy(_), ..) | Finished::Failed(_) => 0,
        }
    }
}

/// What a batch (or a merge) into `out` leaves when it is stopped from outside (Ctrl-C, a
/// scheduler's SIGTERM): its committed (or, merging, linked) runs stay in `out/runs`, the
/// unfinished `results.h5.tmp` goes, and `skelid.log` records it with `advice` (how to go
/// on); nothing, where this process does not hold the folder ([`FolderLock`]). Returns
/// the line said. Every commit is a rename, so no run file is left half written; the
/// workers' writes into the removed file go nowhere. The batch's own threads keep running
/// while this runs, so in rare moments a `.tmp` made or renamed just then may stay (the
/// next batch removes it), and the count may miss a run committed in the same instant.
pub fn record_interruption(out: &Path, why: &str, advice: &str) -> String {
    if !lock::holds(out) {
        // Before this process's batch took the folder (or after it let it go): the folder
        // may be another batch's, whose results.h5.tmp is not ours to take away.
        return format!(
            "interrupted ({why}) while this process was not writing {}: nothing there was \
             removed",
            out.display()
        );
    }
    let _ = std::fs::remove_file(crate::campaign::tmp_path(&out.join("results.h5")));
    let committed = std::fs::read_dir(out.join(crate::journal::RUNS_DIR)).map_or(0, |d| {
        d.flatten()
            .filter(|e| e.path().extension().is_some_and(|x| x == "run"))
            .count()
    });
    let line = format!(
        "interrupted ({why}): {committed} run(s) committed in {}; {advice}",
        out.join(crate::journal::RUNS_DIR).display()
    );
    if let Ok(mut log) = writer::Log::open(out) {
        log.line(&line);
    }
    line
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
    // Before anything in the folder is touched: a second batch into it is refused whole.
    let lock = lock::FolderLock::take(out, "batch")?;
    let journal = Journal::open(out)?;
    let disk = disk::DiskWatch::start(out);
    let settings = settings_fingerprint(&opt.methods, &opt.identify);
    let mut log = Log::open(out)?;
    log.line(&format!(
        "start: {} archive(s){}, settings {settings}{}",
        files.len(),
        opt.shard.map_or(String::new(), |s| format!(", shard {s}")),
        if opt.force {
            format!(", {}", crate::hint::Hint::Force)
        } else {
            String::new()
        }
    ));
    if let Some(why) = &lock.unguarded {
        log.line(&format!("note: {why}"));
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let jobs = match opt.jobs {
        Some(n) => n.max(1),
        None if opt.backend.is_gpu() => GPU_JOBS.max(cores),
        None => cores,
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(jobs)
        .start_handler(|_| crate::backend::lower_compute_priority())
        .build()
        .map_err(|e| BatchError::Threads {
            jobs,
            detail: e.to_string(),
        })?;
    let counts = reader::Counts::default();
    let (budget, budget_from) = match opt.memory {
        Some(m) => (memory::Budget::new(m, jobs), "--memory"),
        None => match memory::available_bytes() {
            Some(a) => (
                memory::Budget::new(a / 4 * 3, jobs),
                "three quarters of what was available",
            ),
            None => (
                memory::Budget::new(u64::MAX, jobs),
                "not known here: no bound",
            ),
        },
    };
    if budget.limit() < u64::MAX {
        log.line(&format!(
            "memory: the runs in flight may take {} together ({budget_from}); a run of n \
             samples takes about {} + n × {} B",
            disk::size(budget.limit()),
            disk::size(memory::run_bytes(0, &opt.methods)),
            memory::run_bytes(1, &opt.methods) - memory::run_bytes(0, &opt.methods),
        ));
    }
    let isolate = match opt.isolation {
        Isolation::Child { command, timeout } => Some((command, timeout)),
        Isolation::None => None,
    };
    // The queues hold one run per worker each, the reader admitting each within the memory
    // budget.
    let (work_tx, work_rx) =
        std::sync::mpsc::sync_channel::<(reader::Delivery, memory::Admission<'_>)>(jobs);
    let (done_tx, done_rx) =
        std::sync::mpsc::sync_channel::<(Finished, memory::Admission<'_>)>(jobs);
    let record = settings_record(&opt.methods, &opt.identify, ingest);
    let results = ResultsFile::create(out, journal.has_legacy_files())?;
    results.write_settings(&record)?;
    let placer = results.placer();
    let drawn = Drawn::new(opt.report_runs);
    let written = std::thread::scope(|scope| {
        let (counts, budget) = (&counts, &budget);
        serial_thread(scope, "reader", move || {
            reader::read_all(files, ingest, opt.shard, isolate, counts, &mut |d| {
                let samples = match &d {
                    reader::Delivery::Run { run, .. } => {
                        run.as_ref().as_ref().map_or(0, |r| r.output.len())
                    }
                    reader::Delivery::Unreadable { .. } => 0,
                };
                let admitted = budget.admit(memory::run_bytes(samples, &opt.methods));
                work_tx.send((d, admitted)).map_err(|_| reader::Stopped)
            })
        })?;
        let drawn = &drawn;
        let writer = serial_thread(scope, "writer", || {
            write_finished(&results, done_rx, log, counts, progress, drawn, disk)
        })?;
        // This thread hands the queued runs to the pool, each as a job of its own, and
        // keeps at most two a worker handed over, so that a worker done with a run finds
        // the next one waiting. No pool thread ever waits on the queue: one waiting there
        // with a piece of another run's nested work on its stack (rayon steals while it
        // waits) would hold that run's admission while the reader waits for memory, and
        // the batch would hang. (Runner threads that each handed one run at a time to the
        // pool left it idle between runs: `--jobs 2` 18 % slower on 200 runs.)
        let stopped = std::sync::atomic::AtomicBool::new(false);
        let handed = Slots::new(2 * jobs);
        let work = Work {
            journal: &journal,
            settings: &settings,
            opt,
            drawn,
            placer: placer.as_ref(),
        };
        let work = &work;
        // The writer ends early only on an error: then no more runs are handed over, and
        // those handed over but not started are let go.
        let writer_stopped = || stopped.load(Ordering::Relaxed) || writer.is_finished();
        pool.in_place_scope_fifo(|s| {
            for (d, mut admitted) in work_rx.iter() {
                if writer_stopped() {
                    break;
                }
                let place = handed.take();
                if writer_stopped() {
                    break;
                }
                let (done_tx, stopped) = (done_tx.clone(), &stopped);
                s.spawn_fifo(move |_| {
                    if stopped.load(Ordering::Relaxed) {
                        return;
                    }
                    let finished = prepare_caught(d, work);
                    // The run's working set is gone; what waits for the writer is its
                    // results.
                    admitted.shrink(finished.data_bytes());
                    // A failed send: the writer stopped on an error, which it returns.
                    if done_tx.send((finished, admitted)).is_err() {
                        stopped.store(true, Ordering::Relaxed);
                    }
                    drop(place);
                });
            }
        });
        // The queue goes, and with it the admissions still in it: a reader waiting for
        // memory wakes to find the batch gone.
        drop((work_rx, done_tx));
        writer.join().expect("the writer does not panic")
    });
    // The workers are done: their descriptor of results.h5.tmp closes before the file is
    // finished and renamed (on NFS the close is what makes the data visible elsewhere).
    drop(placer);
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
        busy: (busy_s, ran_s),
    } = written;
    let total = entries.len();
    let runs_in_inputs = counts.runs_in_inputs.load(Ordering::Relaxed);
    let (t0, cpu0) = (Instant::now(), profile::thread_cpu());
    entries.sort_by(|(a, _), (b, _)| manifest::order(a, b));
    let (mut entries, written_at): (Vec<Entry>, Vec<String>) = entries.into_iter().unzip();
    if let Err(e) = place_runs(&results, &entries, &written_at) {
        results.abandon();
        return Err(stopped(e));
    }
    let not_runs: Vec<GroupNotRun> = (counts.take_not_runs().into_iter())
        .map(|(archive, group)| GroupNotRun { archive, group })
        .collect();
    for g in &not_runs {
        log.line(&format!("skipped (not a run) {}: {}", g.archive, g.group));
    }
    // Logged by the writer as they were found.
    let damaged = counts.take_damaged();
    let mut manifest = Manifest::new(
        settings,
        opt.shard,
        runs_in_inputs,
        &mut entries,
        not_runs.clone(),
        Some(record),
    );
    manifest.damaged_archives = damaged.clone();
    manifest.incomplete_archives = (counts.take_incomplete().into_iter())
        .map(|a| IncompleteArchive {
            shard: opt.shard,
            ..a
        })
        .collect();
    let held = drawn.take_shown(&entries, opt.report_runs);
    // The page reads nothing back from results.h5 (runs the workers did not draw are drawn
    // from their journal files): results.h5 is closed (its metadata flushed, a third of
    // this end) while the summaries and the page are written.
    let (closed, pages) = std::thread::scope(|s| {
        let closing = s.spawn(|| results.finish());
        let runs = page_runs(&journal, &entries, held);
        let pages = write_pages(out, &entries, &manifest, runs);
        (closing.join(), pages)
    });
    let results = match closed {
        Ok(r) => r.map_err(|e| stopped(e.into()))?,
        Err(panic) => std::panic::resume_unwind(panic),
    };
    let rows = pages.map_err(stopped)?;
    write_manifest(out, &manifest).map_err(stopped)?;
    let failed_runs = entries.iter().filter(|e| e.failed).count();
    profile::add(Stage::Write, profile::thread_cpu().saturating_sub(cpu0));
    log.line(&format!(
        "where the time went (CPU seconds since the process started): {}",
        profile::snapshot().line()
    ));
    log.line(&format!(
        "the writer (one thread: results.h5, this log, the progress) was busy {busy_s:.2} s \
         of the {ran_s:.2} s it ran ({:.0} %); near 100 % it, not the cores, sets the pace",
        100.0 * busy_s / ran_s.max(1e-9)
    ));
    let usage = budget.usage();
    let memory_held_back = (usage.waits > 0).then_some(usage);
    if let Some(u) = memory_held_back {
        log.line(&format!("memory: {}", memory::held_back(&u)));
    }
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
        damaged,
        incomplete: manifest.incomplete_archives.clone(),
        memory_held_back,
        unguarded: lock.unguarded.clone(),
    })
}

/// A count of places, taken and given back across threads: the runs handed to the pool.
struct Slots {
    free: std::sync::Mutex<usize>,
    given: std::sync::Condvar,
}

impl Slots {
    fn new(n: usize) -> Slots {
        Slots {
            free: std::sync::Mutex::new(n),
            given: std::sync::Condvar::new(),
        }
    }

    /// Waits for a place and takes it, until the returned guard is dropped (a job that
    /// panics gives it back too, as it unwinds).
    fn take(&self) -> Place<'_> {
        let mut free = self.free.lock().unwrap_or_else(|p| p.into_inner());
        while *free == 0 {
            free = self.given.wait(free).unwrap_or_else(|p| p.into_inner());
        }
        *free -= 1;
        Place(self)
    }
}

/// A place taken from [`Slots`].
struct Place<'a>(&'a Slots);

impl Drop for Place<'_> {
    fn drop(&mut self) {
        *self.0.free.lock().unwrap_or_else(|p| p.into_inner()) += 1;
        self.0.given.notify_one();
    }
}

/// Starts one of the batch's serial threads, named `skelid-ROLE` so that `perf --comm`,
/// `top -H` and the traces tell it apart from the workers.
fn serial_thread<'scope, T: Send + 'scope>(
    scope: &'scope std::thread::Scope<'scope, '_>,
    role: &'static str,
    f: impl FnOnce() -> T + Send + 'scope,
) -> Result<std::thread::ScopedJoinHandle<'scope, T>, BatchError> {
    std::thread::Builder::new()
        .name(format!("skelid-{role}"))
        .spawn_scoped(scope, f)
        .map_err(|e| BatchError::SerialThread {
            role,
            detail: e.to_string(),
        })
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

    fn plots(source: &str) -> DrawnRun {
        DrawnRun::new(crate::report::html::RunPlots {
            path: "/runs/r".into(),
            source: source.into(),
            status: crate::report::Status::Ok,
            error: None,
            methods: Vec::new(),
        })
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
        // A second run with a's archive name and path: both are drawn at the end.
        drawn.offer(&entry("a.h5"), Some(plots("a.h5")));
        assert!(drawn.take(&entry("a.h5"), "/runs/r").is_none());
        let b = drawn.take(&entry("b.h5"), "/runs/r@b.h5").expect("kept");
        assert_eq!(
            (b.run.source.as_str(), b.run.path.as_str()),
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
