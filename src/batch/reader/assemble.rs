//! The parent's side of the stream: frames turned into deliveries, a placed run's samples
//! read from its archive, the counts kept, and where a reading child is in its archive.

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::Duration;

use super::frame::{Frame, Samples};
use super::restart::{corrupt, given_up, reopen_failed, unreadable, Reading};
use super::{Counts, Delivery};
use crate::ingest::{IngestOptions, PlacedRun, Run, RunMeta};
use crate::profile::Stage;

/// Turns frames into deliveries and keeps the counts.
pub(super) struct Assembler<'a> {
    pub(super) files: &'a [PathBuf],
    pub(super) counts: &'a Counts,
    /// Archives of this list finished.
    pub(super) done: usize,
    /// The dataset names, for a placed run's errors.
    pub(super) options: &'a IngestOptions,
    /// The archive whose placed runs are being read, kept open between its runs.
    pub(super) open: Option<(usize, std::fs::File)>,
    /// The archive being read, once its child has opened it.
    pub(super) reading: Option<Reading>,
    /// Where a child before this one died in the first archive: its opening is then no news
    /// (announced and counted already), and reading goes on from there.
    pub(super) resumed: Option<Reading>,
    /// Runs this child has sent and archives it has closed: none when it dies on its first
    /// run, which a new child would then read exactly as it did.
    pub(super) steps: usize,
}

impl<'a> Assembler<'a> {
    pub(super) fn new(
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
            steps: 0,
        }
    }

    /// Why the child was stopped after `timeout` without a frame: which step hung.
    pub(super) fn hang_detail(&self, timeout: Duration) -> String {
        // A large run is no reason to hang closing an archive.
        let slow = "a run that is very large, or a slow disk, needs";
        let (step, slow, stopped) = match &self.reading {
            None => ("opening it".to_string(), slow, ""),
            Some(r) if r.rest() == 0 => (
                format!("closing it after its {} run(s)", r.delivered),
                "a slow disk needs",
                " and was stopped",
            ),
            Some(r) => {
                let of = r.paths.len();
                let step = match &r.last {
                    None => format!("reading its first run of {of}"),
                    Some(path) => format!(
                        "reading its run {} of {of}, the one after {path}",
                        r.delivered + 1
                    ),
                };
                (step, slow, "")
            }
        };
        format!(
            "{step}, the reading child went {} s without progress{stopped}; libhdf5 loops on \
             some corrupt files ({slow} a longer --timeout)",
            timeout.as_secs()
        )
    }

    pub(super) fn frame(&mut self, frame: Frame, samples: Option<Samples>) -> Option<Delivery> {
        let c = self.counts;
        // The frames of an archive given up while its child went on are not news.
        let abandoned = self.reading.as_ref().is_some_and(|r| r.abandoned);
        match frame {
            Frame::Open {
                archive,
                not_runs,
                paths,
                entries,
            } => {
                if archive == 0 {
                    if let Some(r) = self.resumed.take() {
                        return self.reopened(r, &paths, entries);
                    }
                }
                // The archive's one among the runs known becomes its runs.
                c.tally(|t| {
                    t.unopened = t.unopened.saturating_sub(1);
                    t.known = t.known + paths.len() - 1;
                    t.opened += 1;
                    t.announced += paths.len();
                });
                self.reading = Some(Reading {
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
                if let Some(r) = &mut self.reading {
                    // Sent again by a child reading a run again after a crash: no news.
                    if r.resent > 0 {
                        r.resent -= 1;
                        return None;
                    }
                    r.seen += 1;
                    r.skipped_since += 1;
                }
                c.runs_in_inputs.fetch_add(1, Ordering::Relaxed);
                None
            }
            Frame::Run {
                archive,
                path,
                meta,
                error_kind,
                placed,
                ..
            } => {
                c.delivery();
                self.steps += 1;
                if let Some(r) = &mut self.reading {
                    r.dealt_with(&path);
                    r.died_in_row = 0;
                }
                let mut error_kind = error_kind;
                let run = meta.and_then(|meta| {
                    let (input, output) = match placed {
                        Some(p) => crate::profile::time(Stage::Read, || {
                            self.read_placed_run(archive, &meta, p)
                        })
                        .map_err(|e| {
                            error_kind = Some(e.kind().to_string());
                            e.to_string()
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
                    error_kind,
                })
            }
            Frame::Close {
                archive,
                error,
                error_kind,
            } => {
                self.done = archive + 1;
                self.steps += 1;
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
                // The child names a kind with every error; "unreadable" if one did not.
                let kind = error_kind.unwrap_or_else(|| "unreadable".into());
                error.map(|error| match resumed {
                    Some(r) => unreadable(c, file, reopen_failed(&error, &r), kind, Some(&r)),
                    None => unreadable(c, file, error, kind, None),
                })
            }
        }
    }

    /// Takes up the archive a child before this one died in (`r`), now opened again with
    /// `paths`: reading goes on after the run it died on, unless the archive changed in
    /// between (a bench still appending runs, a file replaced), when the runs the count
    /// passes over are no longer those dealt with, and the rest is given up.
    pub(super) fn reopened(
        &mut self,
        mut r: Reading,
        paths: &[String],
        entries: usize,
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
                 the reading child, it held other runs), so {}",
                r.rest_not_read()
            ),
        );
        let gone = given_up(self.counts, file, error, Some(&r));
        r.abandoned = true;
        self.reading = Some(r);
        Some(gone)
    }

    /// A placed run's samples, read from its archive (opened once for all its runs), or
    /// why they cannot be ([`crate::ingest::read_placed`]).
    pub(super) fn read_placed_run(
        &mut self,
        archive: usize,
        meta: &RunMeta,
        placed: PlacedRun,
    ) -> Result<Samples, crate::ingest::IngestError> {
        let path = &self.files[archive];
        let name = path.display().to_string();
        if self.open.as_ref().is_none_or(|(a, _)| *a != archive) {
            let file =
                std::fs::File::open(path).map_err(|e| crate::ingest::IngestError::Unreadable {
                    file: name.clone(),
                    detail: e.to_string(),
                })?;
            self.open = Some((archive, file));
        }
        let (_, file) = self.open.as_ref().expect("opened above");
        crate::ingest::read_placed(file, &name, meta, self.options, placed)
    }
}
