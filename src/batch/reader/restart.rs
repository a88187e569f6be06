//! What follows a reading child's death: the run it died on read again first by a new child
//! (a crash after other runs), or recorded failed and the archive taken up after it by a
//! new child, or the rest of the archive given up, or the archive noted damaged (a death
//! while closing it), every delivery counted so that the progress total stays exact.

use std::path::Path;
use std::sync::atomic::Ordering;

use super::{Counts, Delivery};

/// The archive a reading child is in: the paths of the runs it announced (this shard's),
/// those delivered (by this child or those before it in the archive, failed ones
/// included), the last one's path, the archive's entries of every shard and those seen so
/// far (and those of other shards since the last of this shard's, and how many of those a
/// new child sends again and are no news), the runs a child died on (in a row, and in
/// all), the run read again by a new child after a crash (its index, and how the child
/// before crashed on it), and whether the archive was given up while its child went on.
#[derive(Debug, Clone, Default)]
pub(super) struct Reading {
    pub(super) paths: Vec<String>,
    pub(super) delivered: usize,
    pub(super) last: Option<String>,
    pub(super) entries: usize,
    pub(super) seen: usize,
    pub(super) skipped_since: usize,
    pub(super) resent: usize,
    pub(super) died_in_row: usize,
    pub(super) deaths: usize,
    pub(super) retried: Option<(usize, String)>,
    pub(super) abandoned: bool,
}

impl Reading {
    /// The runs of this shard not dealt with yet.
    pub(super) fn rest(&self) -> usize {
        self.paths.len().saturating_sub(self.delivered)
    }

    /// One run of this shard dealt with, `path`: read, or failed.
    pub(super) fn dealt_with(&mut self, path: &str) {
        self.delivered += 1;
        self.seen += 1;
        self.skipped_since = 0;
        // Whatever a child reading a run again had to send again came before that run.
        self.resent = 0;
        self.last = Some(path.to_string());
    }

    /// Counts the archive's entries of other shards after the last frame seen, when no child
    /// will send them (the child died at the archive's end); they are then seen.
    fn count_unseen(&mut self, counts: &Counts) {
        let unseen = self.entries.saturating_sub(self.seen);
        counts.runs_in_inputs.fetch_add(unseen, Ordering::Relaxed);
        self.seen += unseen;
    }

    /// How a child crashed on the run to read next, when a new child is to read it again.
    pub(super) fn retrying(&self) -> Option<&str> {
        match &self.retried {
            Some((at, how)) if *at == self.delivered => Some(how),
            _ => None,
        }
    }

    /// What giving the rest up costs, for the messages that do.
    pub(super) fn rest_not_read(&self) -> String {
        let rest = match &self.last {
            Some(last) => format!(
                "the archive's {} run(s) after {last} are not read",
                self.rest()
            ),
            None => format!("none of the archive's {} run(s) is read", self.rest()),
        };
        match self.retrying() {
            Some(how) => format!(
                "{rest} ({} among them, to be read again first by a new child: a child that \
                 had read other runs crashed on it, {how})",
                self.paths[self.delivered]
            ),
            None => rest,
        }
    }
}

/// How a reading child ended early: `detail` says how, in words.
#[derive(Debug, Clone)]
pub(super) struct Death {
    pub(super) detail: String,
    pub(super) how: How,
    /// Whether it died before it had sent a run or closed an archive: a new child starting
    /// there repeats its steps exactly, so a crash there is the run's own.
    pub(super) first_run: bool,
}

/// What ended a reading child.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum How {
    /// It crashed (libhdf5, the HDF5 binding, the kernel's OOM killer).
    Crashed,
    /// One step took longer than `--timeout`; it was stopped.
    Hung,
    /// What it sent could not be read while it was still running: a bug of skelid's, not
    /// the file's doing.
    StreamBroke,
}

/// For the tests: a crash on the first run a child read.
#[cfg(test)]
impl From<String> for Death {
    fn from(detail: String) -> Death {
        Death {
            detail,
            how: How::Crashed,
            first_run: true,
        }
    }
}

#[cfg(test)]
impl From<&str> for Death {
    fn from(detail: &str) -> Death {
        detail.to_string().into()
    }
}

/// Runs in a row of one archive that may each stop a reading child (a crash, or a step past
/// `--timeout`) before the rest of the archive is given up: a run that crashes libhdf5
/// costs that run alone, an archive corrupt throughout (or a disk that stopped answering)
/// is not retried run after run all night. A run read again after a crash (see
/// [`after_death`]) counts once, however the second child fares.
pub const DEATHS_IN_A_ROW: usize = 3;

/// Runs of one archive that may stop a reading child in all, in a row or not, before the
/// rest of it is given up: with the default `--timeout` of 300 s, at most 50 minutes of
/// hangs an archive.
pub const DEATHS_IN_AN_ARCHIVE: usize = 10;

/// What a reading child's death in `file` (`death`: how it died; `reading`: where it was,
/// once it had opened the archive; `reopening`: where a child before it had died, when this
/// one died opening the archive again) delivers, counted, and where a new child takes the
/// archive up (`None`: at the next archive). Dying on a run fails that run alone, until
/// [`DEATHS_IN_A_ROW`]; dying while opening the archive fails the archive (once `read_all`
/// has had it opened again by a new child, where the crash followed other steps); dying while
/// closing it, every run dealt with, fails nothing ([`closed_badly`]) unless it was
/// skelid's stream that broke, which fails the archive as before.
pub(super) fn after_death(
    counts: &Counts,
    file: &Path,
    death: Death,
    reading: Option<Reading>,
    reopening: Option<Reading>,
) -> (Vec<Delivery>, Option<Reading>) {
    let stream_broke = death.how == How::StreamBroke;
    let detail = death.detail;
    if let (None, Some(r)) = (&reading, &reopening) {
        let error = corrupt(file, reopen_failed(&detail, r));
        return (vec![given_up(counts, file, error, Some(r))], None);
    }
    match reading {
        // Given up already (it changed between two children): nothing more to say.
        Some(r) if r.abandoned => (Vec::new(), None),
        Some(mut r) if r.rest() == 0 && !stream_broke => {
            closed_badly(counts, file, &detail, &mut r);
            (Vec::new(), None)
        }
        Some(mut r) if r.rest() == 0 => {
            r.count_unseen(counts);
            let detail = format!("{detail}; its {} run(s) were dealt with", r.delivered);
            (
                vec![given_up(counts, file, corrupt(file, detail), Some(&r))],
                None,
            )
        }
        Some(mut r) => {
            let path = r.paths[r.delivered].clone();
            // A crash after other steps of the same child may be theirs (libhdf5's heap
            // corrupted by an earlier run, and this one innocent): a new child reads the run
            // again, first thing, once. A hang is not retried: it would cost --timeout again.
            if death.how == How::Crashed && !death.first_run && r.retrying().is_none() {
                // Other shards' runs since the last of this shard's are sent again: counted
                // already.
                r.resent = r.skipped_since;
                counts.note(format!(
                    "{}: the reading child crashed on {path} after reading other runs \
                     ({detail}); a new reading child reads {path} again, first",
                    file.display()
                ));
                r.retried = Some((r.delivered, detail));
                return (Vec::new(), Some(r));
            }
            let detail = if r.retrying().is_some() {
                format!(
                    "{detail} (a new reading child, reading it first after another had \
                     crashed on it, was stopped by it too)"
                )
            } else {
                detail
            };
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
                r.count_unseen(counts);
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
            (vec![failed, given_up(counts, file, error, Some(&r))], None)
        }
        None => (
            vec![given_up(counts, file, corrupt(file, detail), None)],
            None,
        ),
    }
}

/// An archive whose runs of this shard were all dealt with (`r`) and that a reading child
/// died closing (`detail`: how), noted in [`Counts::damaged`] and not recorded failed: each
/// run was read and checked before, or already failed on its own. Until 2026-12-07 this was
/// a failed `/_unreadable/` entry and exit status 1 on a batch whose every run was
/// identified (one archive in 400 of the fuzz batch). The other shards' runs after the last
/// of this shard's, if their frames had not come, are counted here.
fn closed_badly(counts: &Counts, file: &Path, detail: &str, r: &mut Reading) {
    r.count_unseen(counts);
    let dealt = match (r.delivered, r.deaths) {
        (0, _) => "none of its runs is this shard's".to_string(),
        (n, 0) => format!("its {n} run(s) read"),
        (n, d) => format!("its {n} run(s) dealt with, {d} of them failed on their own"),
    };
    let note = format!(
        "read to the end ({dealt}), but not closed: {detail}. That costs no run (each was \
         dealt with before), but the file is likely damaged: copy it again from the bench, \
         or check it with h5check"
    );
    let damaged = crate::batch::DamagedArchive {
        archive: file.display().to_string(),
        detail: note,
    };
    (counts.damaged.lock().unwrap_or_else(|p| p.into_inner())).push(damaged);
}

/// The rest of an archive a child died in, given up because no new child could be started
/// to read on (`r`: where the last one died).
pub(super) fn not_restarted(counts: &Counts, file: &Path, r: &Reading) -> Delivery {
    let error = crate::ingest::IngestError::Unreadable {
        file: file.display().to_string(),
        detail: format!(
            "no new reading child could be started after a run stopped the last, so {}",
            r.rest_not_read()
        ),
    };
    given_up(counts, file, error, Some(r))
}

/// Whether a new child is to open `file` again, first thing, after a child died opening it
/// (`death`; `retried`: that child was itself the new one). Once, after a crash that
/// followed other steps of the same child, which may be theirs (libhdf5's heap corrupted
/// by an earlier archive); each noted for the log. Otherwise the archive fails as
/// [`after_death`] says, with the last child's death as its error: after a retry, a fresh
/// child's, the same in every shard (whose children meet other archives before it).
pub(super) fn open_again(counts: &Counts, file: &Path, death: &Death, retried: bool) -> bool {
    if retried {
        counts.note(format!(
            "{}: the new reading child, opening it first, was stopped by it too ({}): it is \
             recorded unreadable",
            file.display(),
            death.detail
        ));
        return false;
    }
    if death.how != How::Crashed || death.first_run {
        return false;
    }
    counts.note(format!(
        "{}: the reading child crashed opening it after reading other archives ({}); a new \
         reading child opens it again, first",
        file.display(),
        death.detail
    ));
    true
}

/// The archive a child crashed opening (`detail`: how), given up because no new child could
/// be started to open it again: not read in the batch's own process either.
pub(super) fn not_reopened(counts: &Counts, file: &Path, detail: String) -> Delivery {
    counts.note(format!(
        "{}: no new reading child could be started to open it again",
        file.display()
    ));
    given_up(counts, file, corrupt(file, detail), None)
}

/// Why an archive was given up when a child could not open it again after a run stopped
/// the one before (`detail`: how it failed).
pub(super) fn reopen_failed(detail: &str, r: &Reading) -> String {
    format!(
        "{detail} (opening it again after a run stopped the reading child), so {}",
        r.rest_not_read()
    )
}

/// The error of an archive libhdf5 could not read through, as the reader words it.
pub(super) fn corrupt(file: &Path, detail: String) -> crate::ingest::IngestError {
    crate::ingest::IngestError::Corrupt {
        file: file.display().to_string(),
        run: None,
        detail,
    }
}

/// The failure of the run `path` that a reading child died on (`detail`: how, and what
/// follows), delivered and counted like a run read: it was announced with its archive.
/// `reading` moves past it.
pub(super) fn died_in_run(
    counts: &Counts,
    file: &Path,
    path: &str,
    detail: &str,
    reading: &mut Reading,
) -> Delivery {
    counts.delivery();
    reading.dealt_with(path);
    let error = crate::ingest::IngestError::Corrupt {
        file: file.display().to_string(),
        run: Some(path.to_string()),
        detail: detail.to_string(),
    };
    Delivery::Run {
        source: file.display().to_string(),
        path: path.to_string(),
        run: Box::new(Err(error.to_string())),
        error_kind: Some(error.kind().to_string()),
    }
}

/// The delivery of an archive that could not be read (to the end), counted: it stands for
/// one run of the inputs and is done with. `reading`: where its child died in it, when it
/// had opened it (its runs not delivered are no longer expected; the failure counts one).
pub(super) fn unreadable(
    counts: &Counts,
    file: &Path,
    error: String,
    error_kind: String,
    reading: Option<&Reading>,
) -> Delivery {
    counts.delivery();
    counts.tally(|t| match reading {
        None => t.unopened = t.unopened.saturating_sub(1),
        // Its runs not delivered no longer count; its failure does.
        Some(r) => t.known = (t.known + r.delivered + 1).saturating_sub(r.paths.len()),
    });
    let incomplete = crate::batch::IncompleteArchive {
        archive: file.display().to_string(),
        runs_in_archive: reading.map(|r| r.entries),
        // Every frame seen counted one run of the inputs, and so did this failure.
        counted: reading.map_or(1, |r| r.seen + 1),
        runs_not_read: reading.map_or(0, Reading::rest),
        shard: None,
        shard_log: None,
    };
    (counts.incomplete.lock().unwrap_or_else(|p| p.into_inner())).push(incomplete);
    Delivery::Unreadable {
        file: file.to_path_buf(),
        error,
        error_kind,
    }
}

/// [`unreadable`] with the reader's own `error`.
pub(super) fn given_up(
    counts: &Counts,
    file: &Path,
    error: crate::ingest::IngestError,
    reading: Option<&Reading>,
) -> Delivery {
    let kind = error.kind().to_string();
    unreadable(counts, file, error.to_string(), kind, reading)
}
