//! The batch's one reader: opens the archives in order, reads every run of this shard and
//! hands each to the workers through a bounded queue, so workers never touch an input
//! archive and compute never waits on a read.
//!
//! Isolated reading (the default of `skelid run`) happens in a child process of this
//! executable (`skelid __read-archives`) that streams the runs back over a pipe: libhdf5 crashes
//! or loops forever on some corrupt files, and no in-process handling catches a segfault.
//! One child reads archive after archive, so a campaign of a thousand files costs one
//! process start, not a thousand, and every sample is read once (the old per-file probe
//! read them all a second time before the work started). When the child dies or stalls on
//! a run, that run is recorded failed with the reason and a new child opens the archive
//! again and reads on after it ([`DEATHS_IN_A_ROW`] bounds the retries); when it dies
//! opening an archive, that archive is recorded unreadable, and when it dies closing one
//! whose runs were all dealt with, that archive is noted damaged ([`Counts::damaged`]);
//! either way a new child takes the remaining ones. Runs a dead child had already delivered stand.
//!
//! Protocol: the parent writes to the child's stdin the runs of the first archive to pass
//! over (this shard's, as a decimal count; 0 for a fresh start) and the archive paths, one a
//! line. Child to parent, one frame after another: a little-endian `u32` length, a JSON
//! [`Frame`], then for a [`Frame::Run`] that was read the samples as little-endian `f64`
//! (input first when there is one, then output). A run whose channels lie in the archive as
//! plain float64 bytes ([`crate::ingest::Archive::placed`]) is sent without its samples, only where they
//! lie and what the file was: the parent reads them from the file itself with one plain
//! read each (no libhdf5 in the parent), after checking that it opened the same file, and
//! checks them as the child would have. The pipe carried every sample twice through the
//! kernel and woke the other side every 64 kB: on this project's 2-core machine that cost
//! the child and the parent more CPU than libhdf5's reading, time that `--jobs 1` hides on
//! the second core and `--jobs 2` cannot. The price: those plain reads are the parent's,
//! outside the watchdog, so a file system that hangs exactly between the child's reading
//! of an archive's structure and the parent's reading of its samples hangs the batch.
//!
//! The parts: `frame` the stream, [`serve`] the child's side, `child` one child started
//! and watched, `assemble` the parent's side, `restart` what follows a child's death.

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Duration;

use super::Shard;
use crate::child::ChildCommand;
use crate::ingest::{IngestOptions, Run};

mod assemble;
mod child;
mod frame;
mod restart;
mod serve;
#[cfg(test)]
mod tests;

use assemble::Assembler;
pub use child::BATCH_PID;
use child::{read_in_child, ChildEnd};
pub use frame::{Frame, Samples};
use restart::{after_death, not_reopened, not_restarted, open_again, Reading};
pub use restart::{DEATHS_IN_AN_ARCHIVE, DEATHS_IN_A_ROW};
pub use serve::{serve, serve_stdio};

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
        /// The kind of the run's error ([`crate::ingest::IngestError::kind`]).
        error_kind: Option<String>,
    },
    /// An archive that could not be read (or not to the end), with the reason.
    Unreadable {
        /// The archive.
        file: PathBuf,
        /// Why.
        error: String,
        /// The kind of `error` ([`crate::ingest::IngestError::kind`]).
        error_kind: String,
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
    /// Archives read to the end that a reading child died closing, with how: their runs
    /// stand, no failure is recorded, and the batch warns of them.
    pub damaged: std::sync::Mutex<Vec<super::DamagedArchive>>,
    /// Archives given up before their end or never opened, each delivered as one
    /// [`Delivery::Unreadable`], with what they counted and left unread.
    pub incomplete: std::sync::Mutex<Vec<super::IncompleteArchive>>,
    /// What the reader did that the log should say and no delivery does (a run read again
    /// after a crash), one line each, in order.
    pub notes: std::sync::Mutex<Vec<String>>,
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

    /// One delivery of this shard, a run of the inputs (read, failed, or an archive as one).
    pub(super) fn delivery(&self) {
        self.runs_in_inputs.fetch_add(1, Ordering::Relaxed);
        self.delivered.fetch_add(1, Ordering::Relaxed);
    }

    /// The groups that are not runs gathered so far, taken out, with their archives.
    pub fn take_not_runs(&self) -> Vec<(String, crate::ingest::NotARun)> {
        std::mem::take(&mut *self.not_runs.lock().unwrap_or_else(|p| p.into_inner()))
    }

    /// The damaged archives gathered so far ([`Counts::damaged`]), taken out.
    pub fn take_damaged(&self) -> Vec<super::DamagedArchive> {
        std::mem::take(&mut *self.damaged.lock().unwrap_or_else(|p| p.into_inner()))
    }

    /// The archives given up gathered so far ([`Counts::incomplete`]), taken out.
    pub fn take_incomplete(&self) -> Vec<super::IncompleteArchive> {
        std::mem::take(&mut *self.incomplete.lock().unwrap_or_else(|p| p.into_inner()))
    }

    /// A line for the log ([`Counts::notes`]).
    pub(super) fn note(&self, line: String) {
        self.notes
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push(line);
    }

    /// Changes the tally, under its lock.
    pub(super) fn tally(&self, change: impl FnOnce(&mut Tally)) {
        change(&mut self.tally.lock().unwrap_or_else(|p| p.into_inner()));
    }
}

/// Why the reader stopped early: the consumer went away.
#[derive(Debug)]
pub struct Stopped;

/// Reads `files` in order and calls `deliver` for each run and each unreadable archive;
/// stops early when `deliver` says so. `isolate`: the executable to run the reading child
/// of and the time one step of it may take, opening an archive or reading a run (not
/// counting the parent's own handling of what it sent: a placed run's read, and the time
/// `deliver` blocks). A child's death is followed as [`after_death`] says, and a crash
/// opening an archive after other archives is first checked by a new child opening it.
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
        // The archive a new child opens again, first, after another crashed opening it, and
        // how that one crashed.
        let mut reopened: Option<(usize, String)> = None;
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
                    } else if let Some((at, detail)) = reopened.take().filter(|r| r.0 == next) {
                        // Nor the archive a child just crashed opening.
                        deliver(not_reopened(counts, &files[at], detail))?;
                        next += 1;
                    }
                    return read_in_process(&files[next..], options, shard, counts, deliver);
                }
                ChildEnd::Died {
                    done,
                    death,
                    reading,
                    reopening,
                } => {
                    next += done;
                    let opening = reading.is_none() && reopening.is_none();
                    let retried = reopened.as_ref().is_some_and(|r| r.0 == next);
                    if opening && open_again(counts, &files[next], &death, retried) {
                        reopened = Some((next, death.detail));
                        continue;
                    }
                    let (failures, resume_at) =
                        after_death(counts, &files[next], death, reading, reopening);
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
