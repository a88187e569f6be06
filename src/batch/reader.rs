//! The batch's one reader: opens the archives in order, reads every run of this shard and
//! hands each to the workers through a bounded queue, so workers never touch an input
//! archive and compute never waits on a read.
//!
//! Isolated reading (the default of `skelid run`) happens in a child process of this
//! executable ([`READ_SUBCOMMAND`]) that streams the runs back over a pipe: libhdf5 crashes
//! or loops forever on some corrupt files, and no in-process handling catches a segfault.
//! One child reads archive after archive, so a campaign of a thousand files costs one
//! process start, not a thousand, and every sample is read once (the old per-file probe
//! read them all a second time before the work started). When the child dies or stalls on
//! a run, that run is recorded failed with the reason and a new child opens the archive
//! again and reads on after it ([`DEATHS_IN_A_ROW`] bounds the retries); when it dies
//! opening or closing an archive, that archive is recorded unreadable and a new child takes
//! the remaining ones. Runs a dead child had already delivered stand.
//!
//! Protocol: the parent writes to the child's stdin the runs of the first archive to pass
//! over (this shard's, as a decimal count; 0 but after a death) and the archive paths, one a
//! line. Child to parent, one frame after another: a little-endian `u32` length, a JSON
//! [`Frame`], then for a [`Frame::Run`] that was read the samples as little-endian `f64`
//! (input first when there is one, then output). A run whose channels lie in the archive as
//! plain float64 bytes ([`Archive::placed`]) is sent without its samples, only where they
//! lie and what the file was: the parent reads them from the file itself with one plain
//! read each (no libhdf5 in the parent), after checking that it opened the same file, and
//! checks them as the child would have. The pipe carried every sample twice through the
//! kernel and woke the other side every 64 kB: on this project's 2-core machine that cost
//! the child and the parent more CPU than libhdf5's reading, time that `--jobs 1` hides on
//! the second core and `--jobs 2` cannot. The price: those plain reads are the parent's,
//! outside the watchdog, so a file system that hangs exactly between the child's reading
//! of an archive's structure and the parent's reading of its samples hangs the batch.

use std::io::{BufRead, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use super::Shard;
use crate::child::ChildCommand;
use crate::ingest::{Archive, IngestOptions, PlacedRun, Run, RunMeta};
use crate::inspect::crash_detail;
use crate::profile::Stage;

/// One message of the reader's stream.
// A frame is serialised once per run onto the reader's pipe and dropped: the run's
// metadata inline costs nothing worth a box.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Serialize, Deserialize)]
pub enum Frame {
    /// The archive (index into the list given) is open; its runs follow.
    Open {
        /// Archive index.
        archive: usize,
        /// Groups of the archive with datasets that are not runs.
        #[serde(default)]
        not_runs: Vec<crate::ingest::NotARun>,
        /// This shard's runs in the archive, known once it is open: the progress's total
        /// counts them before they are read.
        #[serde(default)]
        runs: Option<usize>,
        /// Their group paths, in the order they will be read: when the child dies reading
        /// one, the parent knows which run killed it, records that run failed, and a new
        /// child goes on after it.
        #[serde(default)]
        paths: Vec<String>,
        /// The archive's runs of every shard (this shard's are sent, the others' skipped):
        /// those after a run the child died on, as the archive's last, are counted unsent.
        #[serde(default)]
        entries: Option<usize>,
    },
    /// One run of this shard; samples follow when `meta` is `Ok` and it is not `placed`.
    Run {
        /// Archive index.
        archive: usize,
        /// Group path.
        path: String,
        /// The run's metadata, or why it cannot be read.
        meta: Result<RunMeta, String>,
        /// Whether the run has input samples (sent before the output's, or placed).
        has_input: bool,
        /// Where the samples lie in the archive, when they are not sent: the parent reads
        /// them there.
        placed: Option<PlacedRun>,
    },
    /// A run of another shard (counted, not read).
    Skip {
        /// Archive index.
        archive: usize,
    },
    /// The archive is done; `error` when it could not be opened at all.
    Close {
        /// Archive index.
        archive: usize,
        /// Why the archive could not be opened.
        error: Option<String>,
    },
}

/// A run's samples as read: input (when the run has one), output.
pub type Samples = (Option<Vec<f64>>, Vec<f64>);

/// What the reader delivers.
pub enum Delivery {
    /// A run of this shard, or why it could not be read.
    Run {
        /// Archive file name as given.
        source: String,
        /// Group path.
        path: String,
        /// The run (boxed: a run's metadata is far larger than the other variant).
        run: Box<Result<Run, String>>,
    },
    /// An archive that could not be read (or not to the end), with the reason.
    Unreadable {
        /// The archive.
        file: PathBuf,
        /// Why.
        error: String,
    },
}

/// Counts the reader keeps while it reads, for the progress display and the manifest.
#[derive(Default)]
pub struct Counts {
    /// Runs seen in the archives so far, all shards (an unreadable archive counts one).
    pub runs_in_inputs: AtomicUsize,
    /// Deliveries of this shard so far.
    pub delivered: AtomicUsize,
    /// What the total is estimated from, changed together (see [`Tally`]).
    pub tally: Mutex<Tally>,
    /// Groups with datasets that are not runs, with their archive (as given).
    pub not_runs: std::sync::Mutex<Vec<(String, crate::ingest::NotARun)>>,
}

/// This shard's runs as far as the reader knows them, under one lock: an archive's opening
/// changes several of them, and a total read between two of the changes was one too high.
#[derive(Debug, Default, Clone, Copy)]
pub struct Tally {
    /// Runs known: an archive not yet opened counts one, an opened one the runs it
    /// announced, one the reading child died in the runs it delivered and one for its
    /// failure.
    pub known: usize,
    /// Archives neither opened nor found unreadable yet.
    pub unopened: usize,
    /// Archives opened.
    pub opened: usize,
    /// The runs of this shard the opened archives announced together.
    pub announced: usize,
}

impl Tally {
    /// The total projected: each archive not yet opened at the mean of those opened (its
    /// one in `known` replaced), exact once every archive is open.
    pub fn projected(&self) -> usize {
        if self.opened == 0 {
            return self.known;
        }
        let mean = self.announced as f64 / self.opened as f64;
        self.known.saturating_sub(self.unopened) + (self.unopened as f64 * mean).round() as usize
    }
}

impl Counts {
    /// The best guess of this shard's total while reading ([`Tally::projected`]), never
    /// below the runs delivered. Before 2026-12-07 the archive being read counted one, so
    /// one archive of 1000 runs showed a total one ahead of the runs done all night, and
    /// ten of 100 runs a total of 109 while the first was read.
    pub fn estimate(&self) -> usize {
        let tally = *self.tally.lock().unwrap_or_else(|p| p.into_inner());
        tally
            .projected()
            .max(self.delivered.load(Ordering::Relaxed))
    }

    /// Changes the tally, under its lock.
    fn tally(&self, change: impl FnOnce(&mut Tally)) {
        change(&mut self.tally.lock().unwrap_or_else(|p| p.into_inner()));
    }
}

/// The archive a reading child is in: the runs it announced (this shard's) and their
/// paths, those delivered (by this child or those before it in the archive, failed ones
/// included), the last one's path, the archive's entries of every shard and those seen so
/// far, the runs a child died on (in a row, and in all), and whether the archive was
/// given up while its child went on.
#[derive(Debug, Clone, Default)]
struct Reading {
    announced: Option<usize>,
    paths: Vec<String>,
    delivered: usize,
    last: Option<String>,
    entries: Option<usize>,
    seen: usize,
    died_in_row: usize,
    deaths: usize,
    abandoned: bool,
}

impl Reading {
    /// The runs of this shard not dealt with yet.
    fn rest(&self) -> usize {
        self.paths.len().saturating_sub(self.delivered)
    }
}

/// Runs in a row of one archive that may each stop a reading child (a crash, or a step past
/// `--timeout`) before the rest of the archive is given up: a run that crashes libhdf5
/// costs that run alone, an archive corrupt throughout (or a disk that stopped answering)
/// is not retried run after run all night.
pub const DEATHS_IN_A_ROW: usize = 3;

/// Runs of one archive that may stop a reading child in all, in a row or not, before the
/// rest of it is given up: with the default `--timeout` of 300 s, at most 50 minutes of
/// hangs an archive.
pub const DEATHS_IN_AN_ARCHIVE: usize = 10;

/// Why the reader stopped early: the consumer went away.
#[derive(Debug)]
pub struct Stopped;

/// Reads `files` in order and calls `deliver` for each run and each unreadable archive;
/// stops early when `deliver` says so. `isolate`: the executable to run the reading child
/// of and the time one step of it may take, opening an archive or reading a run (not
/// counting the parent's own handling of what it sent: a placed run's read, and the time
/// `deliver` blocks).
pub fn read_all(
    files: &[PathBuf],
    options: &IngestOptions,
    shard: Option<Shard>,
    isolate: Option<(&ChildCommand, Duration)>,
    counts: &Counts,
    deliver: &mut dyn FnMut(Delivery) -> Result<(), Stopped>,
) -> Result<(), Stopped> {
    counts.tally(|t| {
        t.known = files.len();
        t.unopened = files.len();
    });
    if let Some((command, timeout)) = isolate {
        let mut next = 0;
        // Where a new child takes up the archive a child died in.
        let mut resume: Option<Reading> = None;
        while next < files.len() {
            let start = resume.take();
            let end = read_in_child(
                command,
                &files[next..],
                options,
                timeout,
                counts,
                start.clone(),
                deliver,
            )?;
            match end {
                ChildEnd::Finished => break,
                // The child could not be started: read in-process rather than not at all,
                // but not the rest of an archive a child just died in (libhdf5 may crash
                // on it again, and take the batch with it).
                ChildEnd::NotStarted => {
                    if let Some(r) = start {
                        deliver(not_restarted(counts, &files[next], &r))?;
                        next += 1;
                    }
                    return read_in_process(&files[next..], options, shard, counts, deliver);
                }
                ChildEnd::Died {
                    done,
                    detail,
                    reading,
                    reopening,
                } => {
                    next += done;
                    let (failures, resume_at) =
                        after_death(counts, &files[next], detail, reading, reopening);
                    for d in failures {
                        deliver(d)?;
                    }
                    match resume_at {
                        Some(r) => resume = Some(r),
                        None => next += 1,
                    }
                }
            }
        }
        Ok(())
    } else {
        read_in_process(files, options, shard, counts, deliver)
    }
}

/// What a reading child's death in `file` (`detail`: how it died; `reading`: where it was,
/// once it had opened the archive; `reopening`: where a child before it had died, when this
/// one died opening the archive again) delivers, counted, and where a new child takes the
/// archive up (`None`: at the next archive). Dying on a run fails that run alone, until
/// [`DEATHS_IN_A_ROW`]; dying while opening or closing the archive fails the archive.
fn after_death(
    counts: &Counts,
    file: &Path,
    detail: String,
    reading: Option<Reading>,
    reopening: Option<Reading>,
) -> (Vec<Delivery>, Option<Reading>) {
    if let (None, Some(r)) = (&reading, &reopening) {
        let error = corrupt(file, reopen_failed(&detail, r));
        return (vec![unreadable(counts, file, error, Some(r))], None);
    }
    match reading {
        // Given up already (it changed between two children): nothing more to say.
        Some(r) if r.abandoned => (Vec::new(), None),
        Some(mut r) if r.rest() > 0 => {
            let path = r.paths[r.delivered].clone();
            r.died_in_row += 1;
            r.deaths += 1;
            let last = r.rest() == 1;
            let gives_up = r.died_in_row >= DEATHS_IN_A_ROW || r.deaths >= DEATHS_IN_AN_ARCHIVE;
            let then = if last {
                "it was the archive's last run"
            } else if gives_up {
                "the reading child is not started on this archive again"
            } else {
                "the archive's other runs are read by a new reading child"
            };
            let failed = died_in_run(counts, file, &path, &format!("{detail}; {then}"), &mut r);
            if last {
                // Other shards' runs after it, never sent as skipped, are counted here
                // rather than by opening the archive again.
                let unseen = r.entries.map_or(0, |n| n.saturating_sub(r.seen));
                counts.runs_in_inputs.fetch_add(unseen, Ordering::Relaxed);
                return (vec![failed], None);
            }
            if !gives_up {
                return (vec![failed], Some(r));
            }
            let why = if r.died_in_row >= DEATHS_IN_A_ROW {
                format!("{} runs in a row", r.died_in_row)
            } else {
                format!("{} of its runs", r.deaths)
            };
            let error = corrupt(
                file,
                format!(
                    "{why} stopped the reading child, the last {path}, so the archive's {} \
                     run(s) after it are not read",
                    r.rest()
                ),
            );
            (
                vec![failed, unreadable(counts, file, error, Some(&r))],
                None,
            )
        }
        reading => {
            let error = match &reading {
                Some(r) if r.deaths > 0 => format!(
                    "{detail}; its {} run(s) were read and {} failed before",
                    r.delivered - r.deaths,
                    r.deaths
                ),
                Some(r) => format!("{detail}; its {} run(s) were read", r.delivered),
                None => detail,
            };
            let error = corrupt(file, error);
            (
                vec![unreadable(counts, file, error, reading.as_ref())],
                None,
            )
        }
    }
}

/// The rest of an archive a child died in, given up because no new child could be started
/// to read on (`r`: where the last one died).
fn not_restarted(counts: &Counts, file: &Path, r: &Reading) -> Delivery {
    let error = crate::ingest::IngestError::Unreadable {
        file: file.display().to_string(),
        detail: format!(
            "no new reading child could be started after a run stopped the last, so the \
             archive's {} run(s) after {} are not read",
            r.rest(),
            r.last.as_deref().unwrap_or("the first")
        ),
    };
    unreadable(counts, file, error.to_string(), Some(r))
}

/// Why an archive was given up when a child could not open it again after a run stopped
/// the one before (`detail`: how it failed).
fn reopen_failed(detail: &str, r: &Reading) -> String {
    format!(
        "{detail} (opening it again after a run stopped the reading child), so the \
         archive's {} run(s) after {} are not read",
        r.rest(),
        r.last.as_deref().unwrap_or("the first")
    )
}

/// The error of an archive libhdf5 could not read through, as the reader words it.
fn corrupt(file: &Path, detail: String) -> String {
    crate::ingest::IngestError::Corrupt {
        file: file.display().to_string(),
        run: None,
        detail,
    }
    .to_string()
}

/// The failure of the run `path` that a reading child died on (`detail`: how, and what
/// follows), delivered and counted like a run read: it was announced with its archive.
/// `reading` moves past it.
fn died_in_run(
    counts: &Counts,
    file: &Path,
    path: &str,
    detail: &str,
    reading: &mut Reading,
) -> Delivery {
    counts.runs_in_inputs.fetch_add(1, Ordering::Relaxed);
    counts.delivered.fetch_add(1, Ordering::Relaxed);
    reading.delivered += 1;
    reading.seen += 1;
    reading.last = Some(path.to_string());
    let error = crate::ingest::IngestError::Corrupt {
        file: file.display().to_string(),
        run: Some(path.to_string()),
        detail: detail.to_string(),
    };
    Delivery::Run {
        source: file.display().to_string(),
        path: path.to_string(),
        run: Box::new(Err(error.to_string())),
    }
}

/// Reads in this process (trusted files, tests) through the same frames the child sends.
fn read_in_process(
    files: &[PathBuf],
    options: &IngestOptions,
    shard: Option<Shard>,
    counts: &Counts,
    deliver: &mut dyn FnMut(Delivery) -> Result<(), Stopped>,
) -> Result<(), Stopped> {
    let mut stopped = false;
    let mut assemble = Assembler::new(files, counts, options, None);
    serve(files, options, shard, false, 0, &mut |frame, samples| {
        if stopped {
            return false;
        }
        if let Some(d) = assemble.frame(frame, samples) {
            stopped = deliver(d).is_err();
        }
        !stopped
    });
    if stopped {
        Err(Stopped)
    } else {
        Ok(())
    }
}

/// Turns frames into deliveries and keeps the counts.
struct Assembler<'a> {
    files: &'a [PathBuf],
    counts: &'a Counts,
    /// Archives of this list finished.
    done: usize,
    /// The dataset names, for a placed run's errors.
    options: &'a IngestOptions,
    /// The archive whose placed runs are being read, kept open between its runs.
    open: Option<(usize, std::fs::File)>,
    /// The archive being read, once its child has opened it.
    reading: Option<Reading>,
    /// Where a child before this one died in the first archive: its opening is then no news
    /// (announced and counted already), and reading goes on from there.
    resumed: Option<Reading>,
}

impl<'a> Assembler<'a> {
    fn new(
        files: &'a [PathBuf],
        counts: &'a Counts,
        options: &'a IngestOptions,
        resumed: Option<Reading>,
    ) -> Self {
        Assembler {
            files,
            counts,
            done: 0,
            options,
            open: None,
            reading: None,
            resumed,
        }
    }

    /// Why the child was stopped after `timeout` without a frame: which step hung.
    fn hang_detail(&self, timeout: Duration) -> String {
        let step = match &self.reading {
            None => "opening it".to_string(),
            Some(r) if r.announced == Some(r.delivered) => {
                format!("closing it after its {} run(s)", r.delivered)
            }
            Some(r) => {
                let of = r.announced.map_or(String::new(), |n| format!(" of {n}"));
                match &r.last {
                    None => format!("reading its first run{of}"),
                    Some(path) => format!(
                        "reading its run {}{of}, the one after {path}",
                        r.delivered + 1
                    ),
                }
            }
        };
        format!(
            "{step}, the reading child went {} s without progress; libhdf5 loops on some \
             corrupt files (a run that is very large, or a slow disk, needs a longer \
             --timeout)",
            timeout.as_secs()
        )
    }

    fn frame(&mut self, frame: Frame, samples: Option<Samples>) -> Option<Delivery> {
        let c = self.counts;
        // The frames of an archive given up while its child went on are not news.
        let abandoned = self.reading.as_ref().is_some_and(|r| r.abandoned);
        match frame {
            Frame::Open {
                archive,
                not_runs,
                runs,
                paths,
                entries,
            } => {
                if archive == 0 {
                    if let Some(r) = self.resumed.take() {
                        return self.reopened(r, &paths, entries);
                    }
                }
                // The archive's one among the runs known becomes its runs (the child always
                // announces them; an archive that did not would count one until read).
                c.tally(|t| {
                    t.unopened = t.unopened.saturating_sub(1);
                    if let Some(n) = runs {
                        t.known = t.known + n - 1;
                        t.opened += 1;
                        t.announced += n;
                    }
                });
                self.reading = Some(Reading {
                    announced: runs,
                    paths,
                    entries,
                    ..Reading::default()
                });
                let file = self.files[archive].display().to_string();
                c.not_runs
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .extend(not_runs.into_iter().map(|g| (file.clone(), g)));
                None
            }
            Frame::Skip { .. } | Frame::Run { .. } if abandoned => None,
            Frame::Skip { .. } => {
                c.runs_in_inputs.fetch_add(1, Ordering::Relaxed);
                if let Some(r) = &mut self.reading {
                    r.seen += 1;
                }
                None
            }
            Frame::Run {
                archive,
                path,
                meta,
                placed,
                ..
            } => {
                c.runs_in_inputs.fetch_add(1, Ordering::Relaxed);
                c.delivered.fetch_add(1, Ordering::Relaxed);
                if let Some(r) = &mut self.reading {
                    r.delivered += 1;
                    r.seen += 1;
                    r.last = Some(path.clone());
                    r.died_in_row = 0;
                }
                let run = meta.and_then(|meta| {
                    let (input, output) = match placed {
                        Some(p) => crate::profile::time(Stage::Read, || {
                            self.read_placed_run(archive, &meta, p)
                        })?,
                        None => samples.unwrap_or_default(),
                    };
                    Ok(Run {
                        meta,
                        input,
                        output,
                    })
                });
                Some(Delivery::Run {
                    source: self.files[archive].display().to_string(),
                    path,
                    run: Box::new(run),
                })
            }
            Frame::Close { archive, error } => {
                self.done = archive + 1;
                self.open = None;
                self.reading = None;
                // An archive that could not be opened again after a run stopped a child:
                // its runs not dealt with are no longer expected.
                let resumed = if archive == 0 {
                    self.resumed.take()
                } else {
                    None
                };
                let file = &self.files[archive];
                error.map(|error| match resumed {
                    Some(r) => {
                        let error = format!("{error} {}", reopen_failed("", &r).trim_start());
                        unreadable(c, file, error, Some(&r))
                    }
                    None => unreadable(c, file, error, None),
                })
            }
        }
    }

    /// Takes up the archive a child before this one died in (`r`), now opened again with
    /// `paths`: reading goes on after the run it died on, unless the archive changed in
    /// between (a bench still appending runs, a file replaced), when the runs the count
    /// passes over are no longer those dealt with, and the rest is given up.
    fn reopened(
        &mut self,
        mut r: Reading,
        paths: &[String],
        entries: Option<usize>,
    ) -> Option<Delivery> {
        if r.paths == paths && r.entries == entries {
            self.reading = Some(r);
            return None;
        }
        let file = &self.files[0];
        let error = corrupt(
            file,
            format!(
                "the archive changed while it was read (opened again after a run stopped \
                 the reading child, it held other runs), so the archive's {} run(s) after {} \
                 are not read",
                r.rest(),
                r.last.as_deref().unwrap_or("the first")
            ),
        );
        let given_up = unreadable(self.counts, file, error, Some(&r));
        r.abandoned = true;
        self.reading = Some(r);
        Some(given_up)
    }

    /// A placed run's samples, read from its archive (opened once for all its runs), or
    /// why they cannot be ([`crate::ingest::read_placed`]).
    fn read_placed_run(
        &mut self,
        archive: usize,
        meta: &RunMeta,
        placed: PlacedRun,
    ) -> Result<Samples, String> {
        let path = &self.files[archive];
        let name = path.display().to_string();
        if self.open.as_ref().is_none_or(|(a, _)| *a != archive) {
            let file = std::fs::File::open(path).map_err(|e| {
                crate::ingest::IngestError::Unreadable {
                    file: name.clone(),
                    detail: e.to_string(),
                }
                .to_string()
            })?;
            self.open = Some((archive, file));
        }
        let (_, file) = self.open.as_ref().expect("opened above");
        crate::ingest::read_placed(file, &name, meta, self.options, placed)
            .map_err(|e| e.to_string())
    }
}

/// The delivery of an archive that could not be read (to the end), counted: it stands for
/// one run of the inputs and is done with. `reading`: where its child died in it, when it
/// had opened it (its runs not delivered are no longer expected; the failure counts one).
fn unreadable(counts: &Counts, file: &Path, error: String, reading: Option<&Reading>) -> Delivery {
    counts.runs_in_inputs.fetch_add(1, Ordering::Relaxed);
    counts.delivered.fetch_add(1, Ordering::Relaxed);
    counts.tally(|t| match reading {
        None => t.unopened = t.unopened.saturating_sub(1),
        // Its runs not delivered no longer count; its failure does.
        Some(Reading {
            announced: Some(n),
            delivered,
            ..
        }) => t.known = (t.known + delivered + 1).saturating_sub(*n),
        Some(_) => {}
    });
    Delivery::Unreadable {
        file: file.to_path_buf(),
        error,
    }
}

/// Reads `files` in this process and hands every frame (with the run's samples) to `emit`,
/// which returns false to stop. The child's side of the protocol, and the in-process reader.
/// With `place` (the child), a run whose channels lie as plain float64 bytes goes without
/// its samples, only where they lie ([`Archive::placed`]), for the parent to read. `after`:
/// this shard's runs of the first archive that a child before this one dealt with (the last
/// of them the one it died on), passed over without a frame.
pub fn serve(
    files: &[PathBuf],
    options: &IngestOptions,
    shard: Option<Shard>,
    place: bool,
    after: usize,
    emit: &mut dyn FnMut(Frame, Option<Samples>) -> bool,
) {
    for (i, f) in files.iter().enumerate() {
        // Listed only: each run's attributes are read with the run, so that libhdf5 crashing
        // on one run's corrupt attribute costs that run, not the archive.
        let opened = crate::profile::time(Stage::Read, || Archive::open_listed(f, options));
        let archive = match opened {
            Ok(a) => a,
            Err(e) => {
                let close = Frame::Close {
                    archive: i,
                    error: Some(e.to_string()),
                };
                if !emit(close, None) {
                    return;
                }
                continue;
            }
        };
        let takes = |path: &str| shard.is_none_or(|s| s.takes(archive.file_name(), path));
        let paths: Vec<String> = (archive.listed.iter())
            .filter(|e| takes(&e.path))
            .map(|e| e.path.clone())
            .collect();
        let open = Frame::Open {
            archive: i,
            not_runs: archive.not_runs.clone(),
            runs: Some(paths.len()),
            paths,
            entries: Some(archive.listed.len()),
        };
        if !emit(open, None) {
            return;
        }
        // The entries up to the `after`-th run of this shard, other shards' included: the
        // child before this one sent their frames.
        let mut passed = if i == 0 { after } else { 0 };
        for entry in &archive.listed {
            if passed > 0 {
                passed -= usize::from(takes(&entry.path));
                continue;
            }
            if !takes(&entry.path) {
                if !emit(Frame::Skip { archive: i }, None) {
                    return;
                }
                continue;
            }
            let meta = crate::profile::time(Stage::Read, || archive.read_meta(entry));
            let placed = match &meta {
                Ok(m) if place => archive.placed(m),
                _ => None,
            };
            let (meta, samples) = match (&meta, placed) {
                (Ok(m), Some(_)) => (Ok(m.clone()), None),
                (meta, _) => {
                    let run = meta.as_ref().map_err(|e| e.to_string()).and_then(|m| {
                        crate::profile::time(Stage::Read, || archive.load(m))
                            .map_err(|e| e.to_string())
                    });
                    match run {
                        Ok(run) => (Ok(run.meta), Some((run.input, run.output))),
                        Err(e) => (Err(e), None),
                    }
                }
            };
            let has_input = match placed {
                Some(p) => p.input.is_some(),
                None => samples.as_ref().is_some_and(|s| s.0.is_some()),
            };
            let frame = Frame::Run {
                archive: i,
                path: entry.path.clone(),
                meta,
                has_input,
                placed,
            };
            if !emit(frame, samples) {
                return;
            }
        }
        // Closed before it is said closed: a close that hangs or crashes in libhdf5 is then
        // this archive's failure, not the next one's.
        drop(archive);
        if !emit(
            Frame::Close {
                archive: i,
                error: None,
            },
            None,
        ) {
            return;
        }
    }
}

/// Bytes buffered on each side of the reading child's pipe. Small on purpose: a frame's
/// header goes through the buffer, but a run's samples (hundreds of kilobytes) are longer,
/// so the buffers pass them straight between the pipe and the values instead of copying
/// them once more on each side, as a 1 MB buffer did.
const FRAME_BUFFER: usize = 64 << 10;

/// The child's main: from standard input, the runs of the first archive to pass over (a
/// decimal count on the first line, see [`serve`]'s `after`), then the archive paths one a
/// line; frames to standard output.
pub fn serve_stdio(options: &IngestOptions, shard: Option<Shard>) -> std::io::Result<()> {
    let mut lines = std::io::stdin()
        .lock()
        .lines()
        .collect::<std::io::Result<Vec<String>>>()?
        .into_iter();
    let after = lines
        .next()
        .and_then(|l| l.trim().parse::<usize>().ok())
        .ok_or_else(|| std::io::Error::other("the first line is not the runs to pass over"))?;
    let files: Vec<PathBuf> = lines.filter(|l| !l.is_empty()).map(PathBuf::from).collect();
    let mut out = std::io::BufWriter::with_capacity(FRAME_BUFFER, std::io::stdout().lock());
    let mut failure = None;
    // `SKELID_READ_PAUSE_MS`: each run read this much slower, to rehearse `--timeout` on a
    // slow disk (the tests use it).
    let pause = std::env::var("SKELID_READ_PAUSE_MS")
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .map(Duration::from_millis);
    let faults = Faults::from_env();
    serve(
        &files,
        options,
        shard,
        true,
        after,
        &mut |frame, samples| {
            if let Frame::Run { path, .. } = &frame {
                if let Some(pause) = pause {
                    std::thread::sleep(pause);
                }
                faults.meet(path);
            }
            match write_frame(&mut out, &frame, samples.as_ref()) {
                Ok(()) => true,
                Err(e) => {
                    // The parent went away (a stopped batch): nothing left to do.
                    failure = Some(e);
                    false
                }
            }
        },
    );
    match failure {
        Some(e) => Err(e),
        None => out.flush(),
    }
}

/// `SKELID_READ_FAULT=crash:PATH,hang:PATH,…`: the reading child aborts, or stops answering,
/// where it would send the run of that group path (in any archive), as when libhdf5 crashes
/// or loops on that run's corrupt data; to rehearse a campaign with a bad run (the tests
/// use it).
#[derive(Default)]
struct Faults {
    crash: Vec<String>,
    hang: Vec<String>,
}

impl Faults {
    fn from_env() -> Faults {
        let mut faults = Faults::default();
        let spec = std::env::var("SKELID_READ_FAULT").unwrap_or_default();
        for item in spec.split(',') {
            match item.split_once(':') {
                Some(("crash", path)) => faults.crash.push(path.to_string()),
                Some(("hang", path)) => faults.hang.push(path.to_string()),
                _ => {}
            }
        }
        faults
    }

    fn meet(&self, path: &str) {
        if self.crash.iter().any(|p| p == path) {
            // No core file left behind where core dumps are on.
            let none = libc::rlimit {
                rlim_cur: 0,
                rlim_max: 0,
            };
            // SAFETY: setrlimit reads the struct given and touches no other memory.
            unsafe { libc::setrlimit(libc::RLIMIT_CORE, &none) };
            std::process::abort();
        }
        if self.hang.iter().any(|p| p == path) {
            loop {
                std::thread::sleep(Duration::from_secs(3600));
            }
        }
    }
}

fn write_frame(
    out: &mut impl Write,
    frame: &Frame,
    samples: Option<&Samples>,
) -> std::io::Result<()> {
    let header = serde_json::to_vec(frame).map_err(std::io::Error::other)?;
    out.write_all(&(header.len() as u32).to_le_bytes())?;
    out.write_all(&header)?;
    if let Some((input, output)) = samples {
        for v in input.iter().chain(std::iter::once(output)) {
            out.write_all(&(v.len() as u64).to_le_bytes())?;
            // The samples' bytes as they lie in memory where that is little-endian (one
            // copy, not 60 000 calls: a tenth of the reader's CPU time).
            if cfg!(target_endian = "little") {
                out.write_all(bytemuck::cast_slice(v))?;
            } else {
                for x in v {
                    out.write_all(&x.to_le_bytes())?;
                }
            }
        }
    }
    // Each frame reaches the parent at once: its watchdog measures progress by them.
    out.flush()
}

/// Reads one frame; `None` at a clean end of the stream.
fn read_frame(inp: &mut impl Read) -> std::io::Result<Option<(Frame, Option<Samples>)>> {
    let mut len = [0u8; 4];
    match inp.read_exact(&mut len) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
        Err(e) => return Err(e),
    }
    let mut header = vec![0u8; u32::from_le_bytes(len) as usize];
    inp.read_exact(&mut header)?;
    let frame: Frame = serde_json::from_slice(&header).map_err(std::io::Error::other)?;
    let samples = match &frame {
        Frame::Run {
            meta: Ok(_),
            has_input,
            placed: None,
            ..
        } => {
            let input = if *has_input {
                Some(read_vector(inp)?)
            } else {
                None
            };
            Some((input, read_vector(inp)?))
        }
        _ => None,
    };
    Ok(Some((frame, samples)))
}

fn read_vector(inp: &mut impl Read) -> std::io::Result<Vec<f64>> {
    let mut n = [0u8; 8];
    inp.read_exact(&mut n)?;
    let n = u64::from_le_bytes(n) as usize;
    // Read straight into the values, little-endian bits put in order where need be.
    let mut v = vec![0f64; n];
    inp.read_exact(bytemuck::cast_slice_mut(&mut v))?;
    if cfg!(target_endian = "big") {
        for x in &mut v {
            *x = f64::from_bits(u64::from_le(x.to_bits()));
        }
    }
    Ok(v)
}

/// How one reading child ended.
// One a child, returned once: the two readings inline cost nothing worth a box.
#[allow(clippy::large_enum_variant)]
enum ChildEnd {
    /// Every archive given to it was read.
    Finished,
    /// It could not be started.
    NotStarted,
    /// It died (or was stopped) after finishing `done` archives; `detail` says how,
    /// `reading` where it was in the next one when it had opened it, and `reopening` where
    /// it was to take that archive up when it died before opening it.
    Died {
        done: usize,
        detail: String,
        reading: Option<Reading>,
        reopening: Option<Reading>,
    },
}

/// Time the child's current step (opening an archive, reading one run) has taken, not
/// counting the time the parent spent on what the child sent before (reading a placed
/// run's samples, handing runs on): the child then waits on a full pipe through no fault of
/// its own, or is ahead, which costs it nothing either.
struct Clock {
    /// When the step began; `None` while the parent handles what the child sent.
    since: Option<Instant>,
    finished: bool,
    timed_out: bool,
}

/// The environment variable that gives the reader child the batch's process id.
pub const BATCH_PID: &str = "SKELID_BATCH_PID";

/// One reading child over `files`, from where `start` says a child before it died in the
/// first.
fn read_in_child(
    command: &ChildCommand,
    files: &[PathBuf],
    options: &IngestOptions,
    timeout: Duration,
    counts: &Counts,
    start: Option<Reading>,
    deliver: &mut dyn FnMut(Delivery) -> Result<(), Stopped>,
) -> Result<ChildEnd, Stopped> {
    let mut cmd = Command::new(&command.exe);
    cmd.args(&command.args);
    // Whom the child is to die with: it checks that its parent is still this process
    // once it has asked the kernel to kill it when the parent ends.
    cmd.env(BATCH_PID, std::process::id().to_string());
    let child = cmd
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn();
    let Ok(mut child) = child else {
        return Ok(ChildEnd::NotStarted);
    };
    let mut stdin = child.stdin.take().expect("piped stdin");
    let mut stdout =
        std::io::BufReader::with_capacity(FRAME_BUFFER, child.stdout.take().expect("piped"));
    let mut stderr = child.stderr.take().expect("piped stderr");
    let after = start.as_ref().map_or(0, |r| r.delivered);
    let list: String = std::iter::once(format!("{after}\n"))
        .chain(files.iter().map(|f| format!("{}\n", f.display())))
        .collect();
    // The child reads its whole list before it writes anything, so this cannot deadlock.
    let feeder = std::thread::spawn(move || {
        let _ = stdin.write_all(list.as_bytes());
    });
    let err_tail = std::thread::spawn(move || {
        let mut buf = Vec::new();
        let _ = stderr.read_to_end(&mut buf);
        buf
    });
    let child = Arc::new(Mutex::new(child));
    let clock = Arc::new(Mutex::new(Clock {
        since: Some(Instant::now()),
        finished: false,
        timed_out: false,
    }));
    let watchdog = {
        let (child, clock) = (Arc::clone(&child), Arc::clone(&clock));
        std::thread::spawn(move || loop {
            std::thread::sleep(Duration::from_millis(20));
            let mut c = clock.lock().unwrap_or_else(|p| p.into_inner());
            if c.finished {
                return;
            }
            let running = c.since.map_or(Duration::ZERO, |s| s.elapsed());
            if running > timeout {
                c.timed_out = true;
                c.finished = true;
                let _ = child.lock().unwrap_or_else(|p| p.into_inner()).kill();
                return;
            }
        })
    };
    let set = |f: &dyn Fn(&mut Clock)| f(&mut clock.lock().unwrap_or_else(|p| p.into_inner()));
    let mut assemble = Assembler::new(files, counts, options, start);
    let mut result = Ok(());
    let mut broken: Option<std::io::Error> = None;
    loop {
        match crate::profile::time(Stage::Read, || read_frame(&mut stdout)) {
            Ok(Some((frame, samples))) => {
                // Every frame is progress: the next step (opening an archive, reading a
                // run) starts a clock of its own. Until 2026-12-07 only a new archive did,
                // so `--timeout` bounded a whole archive, and one holding a campaign of
                // large runs was cut off part-way as if libhdf5 had hung on it. What follows
                // is the parent's own work (a placed run's samples read from the archive,
                // the hand-over to the workers): the clock stands still meanwhile.
                set(&|c| c.since = None);
                if let Some(d) = assemble.frame(frame, samples) {
                    result = deliver(d);
                }
                set(&|c| c.since = Some(Instant::now()));
                // An archive given up while this child reads it: the child is stopped
                // rather than left to read it to the end for nothing.
                let abandoned = assemble.reading.as_ref().is_some_and(|r| r.abandoned);
                if result.is_err() || abandoned {
                    break;
                }
            }
            Ok(None) => break,
            Err(e) => {
                broken = Some(e);
                break;
            }
        }
    }
    let timed_out = {
        let mut c = clock.lock().unwrap_or_else(|p| p.into_inner());
        c.finished = true;
        c.timed_out
    };
    let _ = watchdog.join();
    let status = {
        let mut ch = child.lock().unwrap_or_else(|p| p.into_inner());
        let abandoned = assemble.reading.as_ref().is_some_and(|r| r.abandoned);
        if result.is_err() || broken.is_some() || abandoned {
            let _ = ch.kill();
        }
        ch.wait()
    };
    let _ = feeder.join();
    let err = err_tail.join().unwrap_or_default();
    result?;
    let done = assemble.done;
    if done == files.len() {
        return Ok(ChildEnd::Finished);
    }
    let detail = if timed_out {
        assemble.hang_detail(timeout)
    } else if let Some(e) = broken {
        // Not libhdf5's doing: what the child sent could not be read (a bug of skelid's).
        format!("the reading child's stream broke ({e}); please report it")
    } else {
        match status {
            Ok(s) => crash_detail(s, &err),
            Err(e) => format!("libhdf5 crashed reading it ({e})"),
        }
    };
    Ok(ChildEnd::Died {
        done,
        detail,
        reading: assemble.reading,
        reopening: assemble.resumed,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An archive of `runs` runs of 1000 samples each, named `r1`, `r2`, ….
    fn archive_of(path: &Path, runs: usize) {
        let f = hdf5::File::create(path).unwrap();
        let x: Vec<f64> = (0..1000).map(|i| (i as f64 * 0.03).sin()).collect();
        for r in 1..=runs {
            let g = f.create_group(&format!("r{r}")).unwrap();
            g.new_attr::<f64>()
                .create("sample_rate")
                .unwrap()
                .write_scalar(&1000.0)
                .unwrap();
            for name in ["input", "output"] {
                g.new_dataset_builder().with_data(&x).create(name).unwrap();
            }
        }
    }

    /// The total projected while reading, written out: the opened archives' runs, the
    /// failures, and the mean of the opened archives for each archive not yet opened.
    fn projected(opened_runs: usize, failures: usize, unopened: usize, opened: usize) -> usize {
        opened_runs
            + failures
            + (unopened as f64 * opened_runs as f64 / opened as f64).round() as usize
    }

    /// Counts as `read_all` starts them for `archives` archives.
    fn counts_for(archives: usize) -> Counts {
        let counts = Counts::default();
        counts.tally(|t| {
            t.known = archives;
            t.unopened = archives;
        });
        counts
    }

    /// The frame of an archive (index `archive`) opened with this shard's `paths` among
    /// `entries` runs of every shard.
    fn opened(archive: usize, paths: Vec<String>, entries: usize) -> Frame {
        Frame::Open {
            archive,
            not_runs: Vec::new(),
            runs: Some(paths.len()),
            paths,
            entries: Some(entries),
        }
    }

    /// `/r1` … `/rN`.
    fn names(n: usize) -> Vec<String> {
        (1..=n).map(|r| format!("/r{r}")).collect()
    }

    /// The frame of a run whose metadata is not the test's concern.
    fn run_frame(archive: usize, path: &str) -> Frame {
        Frame::Run {
            archive,
            path: path.into(),
            meta: Err("not read in this test".into()),
            has_input: false,
            placed: None,
        }
    }

    /// The progress's total counts an open archive by the runs it holds, not as one: read
    /// run by run, a single archive of many runs showed a total one ahead of the runs done.
    /// Archives not yet opened count at the mean of those opened, an unreadable one at one;
    /// a shard counts only its own runs; the total is exact once every archive is open.
    #[test]
    fn the_total_counts_the_open_archives_runs_before_they_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.h5"), dir.path().join("b.h5"));
        archive_of(&a, 5);
        archive_of(&b, 3);
        let files = [a.clone(), b.clone(), dir.path().join("missing.h5")];
        let estimates = |shard: Option<Shard>| {
            let counts = Counts::default();
            let mut seen = Vec::new();
            let options = IngestOptions::default();
            read_all(&files, &options, shard, None, &counts, &mut |d| {
                let source = match d {
                    Delivery::Run { source, .. } => source,
                    Delivery::Unreadable { file, .. } => file.display().to_string(),
                };
                seen.push((
                    crate::journal::base_name(&source).to_string(),
                    counts.estimate(),
                ));
                Ok(())
            })
            .unwrap();
            (seen, counts.estimate())
        };
        let expect = |in_a: usize, in_b: usize, file: &str| match file {
            // a.h5 open: its runs, b.h5 and missing.h5 one each, projected at a's mean.
            "a.h5" => projected(in_a, 0, 2, 1),
            "b.h5" => projected(in_a + in_b, 0, 1, 2),
            _ => in_a + in_b + 1,
        };
        let (seen, total) = estimates(None);
        println!("{seen:?}");
        assert_eq!(total, 9, "5 + 3 runs and the unreadable archive");
        assert_eq!(seen.len(), 9);
        for (file, estimate) in &seen {
            assert_eq!(*estimate, expect(5, 3, file), "{file}: {seen:?}");
        }
        assert_eq!((expect(5, 3, "a.h5"), expect(5, 3, "b.h5")), (15, 12));
        let shard = Shard { index: 1, count: 2 };
        let ours = |f: &Path, n: usize| {
            let name = f.file_name().unwrap().to_str().unwrap();
            (1..=n)
                .filter(|r| shard.takes(name, &format!("/r{r}")))
                .count()
        };
        let (seen, total) = estimates(Some(shard));
        let (in_a, in_b) = (ours(&a, 5), ours(&b, 3));
        println!("shard {shard}: {in_a} of a.h5, {in_b} of b.h5: {seen:?}");
        assert_eq!(total, in_a + in_b + 1);
        for (file, estimate) in &seen {
            assert_eq!(*estimate, expect(in_a, in_b, file), "{file}: {seen:?}");
        }
    }

    /// A reading child that dies on a run fails that run alone: a new child takes the
    /// archive up after it, until three runs in a row have stopped a child, when the rest of
    /// the archive is given up as one failure. A child that dies opening the archive again
    /// gives it up too. Every run announced is delivered once (read, or failed), and the
    /// total stays exact throughout.
    #[test]
    fn a_child_dying_on_a_run_fails_that_run_and_a_new_child_goes_on_after_it() {
        let files = [PathBuf::from("a.h5"), PathBuf::from("b.h5")];
        let (counts, options) = (counts_for(2), IngestOptions::default());
        let open = |archive, runs| opened(archive, names(runs), runs);
        let run = run_frame;
        let mut seen: Vec<(String, String)> = Vec::new();
        let mut see = |d: Delivery| {
            seen.push(match d {
                Delivery::Run { path, run, .. } => (path, run.err().unwrap_or_default()),
                Delivery::Unreadable { error, .. } => ("unreadable".into(), error),
            })
        };
        // A child reads /r1 and /r2 of a.h5's 8 runs, and dies on /r3.
        let mut assemble = Assembler::new(&files, &counts, &options, None);
        assemble.frame(open(0, 8), None);
        assert_eq!(counts.estimate(), 8 + 8, "b.h5 projected at a.h5's 8 runs");
        for p in ["/r1", "/r2"] {
            see(assemble.frame(run(0, p), None).unwrap());
        }
        let hung = assemble.hang_detail(Duration::from_secs(7));
        println!("{hung}");
        assert!(
            hung.starts_with("reading its run 3 of 8, the one after /r2"),
            "{hung}"
        );
        let died = |a: Assembler, how: &str| {
            after_death(&counts, &files[0], how.into(), a.reading, a.resumed)
        };
        let (failed, mut resume) = died(assemble, "libhdf5 crashed reading it (signal 11)");
        failed.into_iter().for_each(&mut see);
        assert_eq!(counts.estimate(), 16, "the failed run was one of the 8");
        // The next child passes over /r1-/r3 (its opening no news), reads /r4, dies on /r5;
        // two more die on /r6 and /r7: three in a row, so /r8 is given up.
        let mut assemble = Assembler::new(&files, &counts, &options, resume.take());
        assemble.frame(open(0, 8), None);
        see(assemble.frame(run(0, "/r4"), None).unwrap());
        let hung = assemble.hang_detail(Duration::from_secs(7));
        assert!(
            hung.starts_with("reading its run 5 of 8, the one after /r4"),
            "{hung}"
        );
        let (failed, resumed) = died(assemble, &hung);
        failed.into_iter().for_each(&mut see);
        resume = resumed;
        for _ in 0..2 {
            let mut assemble = Assembler::new(&files, &counts, &options, resume.take());
            assemble.frame(open(0, 8), None);
            let (failed, resumed) = died(assemble, "libhdf5 crashed reading it (signal 6)");
            failed.into_iter().for_each(&mut see);
            resume = resumed;
        }
        assert!(resume.is_none(), "a.h5 given up");
        assert_eq!(counts.estimate(), 8 + 8, "7 runs and a failure for /r8");
        // b.h5: /r1 read, /r2 stops the child, the next dies opening it again.
        let mut assemble = Assembler::new(&files[1..], &counts, &options, None);
        assemble.frame(open(0, 3), None);
        see(assemble.frame(run(0, "/r1"), None).unwrap());
        let death = |a: Assembler| {
            after_death(
                &counts,
                &files[1],
                "libhdf5 crashed reading it (signal 11)".into(),
                a.reading,
                a.resumed,
            )
        };
        let (failed, resume) = death(assemble);
        failed.into_iter().for_each(&mut see);
        let (failed, resume) = death(Assembler::new(&files[1..], &counts, &options, resume));
        failed.into_iter().for_each(&mut see);
        assert!(resume.is_none());
        for (path, error) in &seen {
            println!("{path}: {error}");
        }
        let paths: Vec<&str> = seen.iter().map(|(p, _)| p.as_str()).collect();
        assert_eq!(
            paths,
            [
                "/r1",
                "/r2",
                "/r3",
                "/r4",
                "/r5",
                "/r6",
                "/r7",
                "unreadable"
            ]
            .into_iter()
            .chain(["/r1", "/r2", "unreadable"])
            .collect::<Vec<_>>()
        );
        let error = |i: usize| seen[i].1.as_str();
        assert!(
            error(2).starts_with(
                "a.h5: truncated or corrupt HDF5 file (run /r3): libhdf5 crashed reading it \
                 (signal 11); the archive's other runs"
            ) && error(2).ends_with("the archive's other runs are read by a new reading child"),
            "{}",
            error(2)
        );
        assert!(error(4).contains("reading its run 5 of 8, the one after /r4, the reading child went 7 s without progress"));
        assert!(
            error(6)
                .ends_with("(signal 6); the reading child is not started on this archive again"),
            "{}",
            error(6)
        );
        assert!(
            error(7).ends_with("3 runs in a row stopped the reading child, the last /r7, so the archive's 1 run(s) after it are not read"),
            "{}",
            error(7)
        );
        assert!(
            error(10).contains("(opening it again after a run stopped the reading child), so the archive's 1 run(s) after /r2 are not read"),
            "{}",
            error(10)
        );
        assert_eq!(counts.delivered.load(Ordering::Relaxed), 11);
        assert_eq!(counts.estimate(), 11, "8 of a.h5 and 3 of b.h5, each once");
    }

    /// The ends of a resumed archive: a child that finds it gone or changed when it opens it
    /// again gives up the rest of it (once, however its child goes on); a death on the
    /// archive's last run counts the other shards' runs after it without a new child. The
    /// counts stay exact throughout.
    #[test]
    fn a_resumed_archive_gone_changed_or_at_its_last_run_is_counted_once() {
        let files = [PathBuf::from("a.h5"), PathBuf::from("b.h5")];
        let options = IngestOptions::default();
        let open = |paths, entries| opened(0, paths, entries);
        let run = |path: &str| run_frame(0, path);
        // A child read /r1 of a.h5's 4 runs and died on /r2: where a new child starts.
        let died_on_r2 = |counts: &Counts| {
            counts.tally(|t| {
                t.known = 2;
                t.unopened = 2;
            });
            let mut a = Assembler::new(&files, counts, &options, None);
            a.frame(open(names(4), 4), None);
            a.frame(run("/r1"), None).unwrap();
            let (failed, resume) =
                after_death(counts, &files[0], "crashed".into(), a.reading, a.resumed);
            assert_eq!(failed.len(), 1);
            resume.expect("a new child goes on")
        };
        let error_of = |d: Option<Delivery>| match d {
            Some(Delivery::Unreadable { error, .. }) => error,
            _ => panic!("the archive given up"),
        };

        // Gone: the new child cannot open it. /r3 and /r4 become one failure.
        let counts = Counts::default();
        let mut a = Assembler::new(&files, &counts, &options, Some(died_on_r2(&counts)));
        let close = Frame::Close {
            archive: 0,
            error: Some("a.h5: cannot read the file: No such file or directory".into()),
        };
        let error = error_of(a.frame(close, None));
        println!("{error}");
        assert!(error.ends_with("No such file or directory (opening it again after a run stopped the reading child), so the archive's 2 run(s) after /r2 are not read"), "{error}");
        assert!(a.resumed.is_none());
        assert_eq!(counts.delivered.load(Ordering::Relaxed), 3);
        // b.h5 projected at the 4 runs a.h5 announced.
        assert_eq!(
            counts.estimate(),
            3 + 4,
            "/r1, /r2 and a failure of a.h5, and b.h5"
        );

        // Changed: opened again, it holds other runs. Given up once; the child's frames of
        // it after that are no news, and its death in it delivers nothing more.
        let counts = Counts::default();
        let mut a = Assembler::new(&files, &counts, &options, Some(died_on_r2(&counts)));
        let other = vec![
            "/r0".to_string(),
            "/r1".into(),
            "/r2".into(),
            "/r3".into(),
            "/r4".into(),
        ];
        let error = error_of(a.frame(open(other, 5), None));
        println!("{error}");
        assert!(
            error.contains("the archive changed while it was read"),
            "{error}"
        );
        assert!(a.frame(run("/r3"), None).is_none());
        let (more, resume) =
            after_death(&counts, &files[0], "crashed".into(), a.reading, a.resumed);
        assert!(more.is_empty() && resume.is_none());
        assert_eq!(counts.delivered.load(Ordering::Relaxed), 3);
        assert_eq!(counts.estimate(), 3 + 4);

        // The last run: a shard's 2 runs among 5 entries, the fourth entry the last of them;
        // the child dies on it. The fifth, another shard's, is counted without a new child.
        let counts = counts_for(1);
        let mut a = Assembler::new(&files[..1], &counts, &options, None);
        a.frame(open(vec!["/r2".into(), "/r4".into()], 5), None);
        a.frame(Frame::Skip { archive: 0 }, None);
        a.frame(run("/r2"), None).unwrap();
        a.frame(Frame::Skip { archive: 0 }, None);
        let (failed, resume) =
            after_death(&counts, &files[0], "crashed".into(), a.reading, a.resumed);
        let Some(Delivery::Run { path, run, .. }) = failed.into_iter().next() else {
            panic!("the run failed");
        };
        let error = run.err().unwrap();
        assert_eq!(path, "/r4");
        assert!(
            error.ends_with("crashed; it was the archive's last run"),
            "{error}"
        );
        assert!(resume.is_none(), "no new child for it");
        assert_eq!(counts.runs_in_inputs.load(Ordering::Relaxed), 5);
        assert_eq!(counts.estimate(), 2);
    }

    /// Deaths not in a row still end an archive: the tenth gives up the rest, each read run
    /// between them resetting only the count in a row. Where no new child can be started,
    /// the rest of the archive is given up at once, as unreadable, not read in-process.
    #[test]
    fn ten_deaths_in_an_archive_give_up_its_rest_and_so_does_no_child() {
        let files = [PathBuf::from("a.h5")];
        let (counts, options) = (counts_for(1), IngestOptions::default());
        let run = |path: &str| run_frame(0, path);
        let mut resume = None;
        let mut failures = Vec::new();
        // Every other run kills the child: /r2, /r4, … /r20 is the tenth.
        for k in 0..10 {
            let mut a = Assembler::new(&files, &counts, &options, resume.take());
            a.frame(opened(0, names(30), 30), None);
            a.frame(run(&format!("/r{}", 2 * k + 1)), None).unwrap();
            let (died, resumed) =
                after_death(&counts, &files[0], "crashed".into(), a.reading, a.resumed);
            failures.extend(died.into_iter().map(|d| match d {
                Delivery::Run { path, run, .. } => (path, run.err().unwrap()),
                Delivery::Unreadable { error, .. } => ("unreadable".into(), error),
            }));
            resume = resumed;
            assert_eq!(resume.is_some(), k < 9, "after death {}", k + 1);
        }
        let last = failures.last().unwrap();
        println!("{}", last.1);
        assert_eq!(failures.len(), 11, "ten runs and the rest");
        assert!(last.1.ends_with("10 of its runs stopped the reading child, the last /r20, so the archive's 10 run(s) after it are not read"), "{}", last.1);
        assert_eq!(counts.delivered.load(Ordering::Relaxed), 21);
        assert_eq!(
            counts.estimate(),
            21,
            "20 runs dealt with and the rest as one"
        );

        // No child to read on after /r2: the rest (28 runs) as one failure, counted exact.
        let counts = counts_for(1);
        let mut a = Assembler::new(&files, &counts, &options, None);
        a.frame(opened(0, names(30), 30), None);
        a.frame(run("/r1"), None).unwrap();
        let (_, resumed) = after_death(&counts, &files[0], "crashed".into(), a.reading, a.resumed);
        let Delivery::Unreadable { error, .. } =
            not_restarted(&counts, &files[0], &resumed.unwrap())
        else {
            panic!("the rest given up");
        };
        println!("{error}");
        assert_eq!(error, "a.h5: cannot read the file: no new reading child could be started after a run stopped the last, so the archive's 28 run(s) after /r2 are not read");
        assert_eq!(counts.estimate(), 3);
        assert_eq!(counts.delivered.load(Ordering::Relaxed), 3);
    }

    /// A child told to pass over the runs a child before it dealt with sends no frame for
    /// them (nor for other shards' runs among them), and reads on from the next.
    #[test]
    fn a_new_child_passes_over_the_runs_dealt_with() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.h5"), dir.path().join("b.h5"));
        archive_of(&a, 9);
        archive_of(&b, 2);
        let files = [a, b];
        let shard = Shard { index: 1, count: 2 };
        let frames = |shard: Option<Shard>, after: usize| {
            let mut frames = Vec::new();
            serve(
                &files,
                &IngestOptions::default(),
                shard,
                true,
                after,
                &mut |f, _| {
                    frames.push(match f {
                        Frame::Open { archive, runs, .. } => format!("open {archive} {runs:?}"),
                        Frame::Run { archive, path, .. } => format!("{archive}{path}"),
                        Frame::Skip { archive } => format!("skip {archive}"),
                        Frame::Close { archive, .. } => format!("close {archive}"),
                    });
                    true
                },
            );
            frames
        };
        assert_eq!(
            frames(None, 4),
            [
                "open 0 Some(9)",
                "0/r5",
                "0/r6",
                "0/r7",
                "0/r8",
                "0/r9",
                "close 0"
            ]
            .into_iter()
            .chain(["open 1 Some(2)", "1/r1", "1/r2", "close 1"])
            .collect::<Vec<_>>()
        );
        // With a shard: the frames after its second run, as they came when read whole.
        let whole = frames(Some(shard), 0);
        let second = whole
            .iter()
            .enumerate()
            .filter(|(_, f)| f.starts_with("0/"))
            .nth(1);
        let (at, _) = second.expect("the shard has two runs of a.h5");
        let mut expected = vec![whole[0].clone()];
        expected.extend(whole[at + 1..].iter().cloned());
        println!("shard {shard}: {whole:?}");
        assert_eq!(frames(Some(shard), 2), expected);
    }

    /// A placed run whose archive was replaced after the child read it (an export that
    /// writes a new file and renames it over the old one) is refused with the reason,
    /// and the same frame over the unchanged file reads the run.
    #[test]
    fn a_placed_run_of_a_replaced_archive_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.h5");
        {
            let f = hdf5::File::create(&path).unwrap();
            let g = f.create_group("run").unwrap();
            g.new_attr::<f64>()
                .create("sample_rate")
                .unwrap()
                .write_scalar(&1000.0)
                .unwrap();
            let x: Vec<f64> = (0..1000).map(|i| (i as f64 * 0.03).sin()).collect();
            for name in ["input", "output"] {
                g.new_dataset_builder().with_data(&x).create(name).unwrap();
            }
        }
        let files = [path.clone()];
        let options = IngestOptions::default();
        let mut sent = Vec::new();
        serve(&files, &options, None, true, 0, &mut |frame, samples| {
            if let Frame::Run { .. } = frame {
                assert!(samples.is_none(), "placed, not sent");
                sent.push(frame);
            }
            true
        });
        let frame = sent.pop().expect("one run");
        let counts = Counts::default();
        let deliver =
            |frame| match Assembler::new(&files, &counts, &options, None).frame(frame, None) {
                Some(Delivery::Run { run, .. }) => run.map(|r| r.output.len()),
                _ => panic!("a run"),
            };
        let resent = |f: &Frame| serde_json::from_slice(&serde_json::to_vec(f).unwrap()).unwrap();
        assert_eq!(deliver(resent(&frame)), Ok(1000));
        let copy = dir.path().join("b.h5");
        std::fs::copy(&path, &copy).unwrap();
        std::fs::rename(&copy, &path).unwrap();
        let refused = deliver(frame).unwrap_err();
        assert!(
            refused.contains("changed while run /run was being read"),
            "{refused}"
        );
    }
}
