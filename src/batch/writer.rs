//! The batch's one writer: finished runs into `results.h5` as they arrive (placed in the
//! report's order at the end), the log and the progress, then the batch's end (summaries,
//! report.html, manifest). In: finished runs from the workers; out: the output folder.

use std::collections::BTreeMap;
use std::path::Path;

use crate::journal::{placements, results_group, Entry, Stored};
use crate::profile::{self, Stage};
use crate::report::html::{self, DrawnRun};
use crate::report::{write_summary, ReportError, ResultsFile, RunOutcome, SummaryRow};

use super::*;

/// The writer: commits each finished run, logs it and reports progress (the output disk's
/// room included, with a warning in the log the first time the runs left do not fit).
/// Returns the entries, the skipped and failed counts and the log; stops at the first
/// write error.
pub(super) fn write_finished(
    results: &ResultsFile,
    done: std::sync::mpsc::Receiver<(Finished, super::memory::Admission<'_>)>,
    mut log: Log,
    counts: &reader::Counts,
    progress: &(dyn Fn(Progress) + Sync),
    drawn: &Drawn,
    mut disk: disk::DiskWatch,
) -> Result<Written, BatchError> {
    let (mut entries, mut skipped, mut failed) = (Vec::new(), 0, 0);
    let (mut suspect, mut bad) = (0, 0);
    let mut used = std::collections::HashSet::new();
    let (start, cpu0) = (std::time::Instant::now(), profile::thread_cpu());
    // The reader's news logged so far (damaged archives, its notes): each is logged after
    // the run the writer has in hand when it comes, so that a batch stopped later has it.
    let mut logged = (0, 0);
    // A run's admission (its results' bytes, within the memory budget) ends with its turn.
    for (f, _admitted) in done {
        // Finishing order is not the final order: a path already used (the same path in
        // two archives) goes aside now and is put in its place at the end.
        let path = match f {
            Finished::Skipped(ref e, ..) | Finished::Committed(ref e, ..) => {
                results_group(&e.path, &e.source)
            }
            Finished::Failed(e) => return Err(e.into()),
        };
        let dst = if used.insert(path.clone()) {
            path
        } else {
            pending(entries.len())
        };
        let t0 = profile::thread_cpu();
        let (e, was_skipped, plots) = match f {
            Finished::Skipped(e, Stored::Encoded(run), plots, placed) => {
                let placed = placed_or_logged(placed, &e, &mut log);
                results.write_placed_as(&run, placed.as_ref(), &dst)?;
                // Its data in results.h5; done now, it would take its journal file too.
                disk.wrote(run.data_bytes(), 2 * run.data_bytes());
                (e, true, plots)
            }
            Finished::Skipped(e, Stored::Legacy(file), plots, _) => {
                results.copy_run_from(&file, &e.path, &dst)?;
                (e, true, plots)
            }
            Finished::Committed(e, p, plots, placed) => {
                let placed = placed_or_logged(placed, &e, &mut log);
                results.write_placed_as(p.encoded(), placed.as_ref(), &dst)?;
                // Its journal file (less one it replaced) and its data in results.h5.
                let bytes = p.journal_growth() + p.encoded().data_bytes();
                disk.wrote(bytes, bytes);
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
                .map(|r| match r.method.as_str() {
                    // A whole run's or archive's failure belongs to no method.
                    "" => format!(" [{}]", r.error),
                    m => format!(" [{m}: {}]", r.error),
                })
                .collect::<String>()
        ));
        skipped += usize::from(was_skipped);
        failed += usize::from(e.failed);
        suspect += e.rows.iter().filter(|r| r.quality == "suspect").count();
        bad += e.rows.iter().filter(|r| r.quality == "bad").count();
        drawn.offer(&e, plots);
        entries.push((e, dst));
        let (done, total) = (entries.len(), counts.estimate().max(entries.len()));
        let room = disk.room(total - done);
        let short = disk.warning(room);
        if let Some(w) = &short {
            log.line(&format!("warning: {w}"));
        }
        logged = log_reader_news(counts, &mut log, logged);
        progress(Progress {
            done,
            total,
            skipped,
            failed,
            suspect,
            bad,
            disk: room,
            disk_short_now: short.is_some(),
        });
    }
    log_reader_news(counts, &mut log, logged);
    Ok(Written {
        entries,
        skipped,
        failed,
        log,
        busy: (
            profile::thread_cpu().saturating_sub(cpu0).as_secs_f64(),
            start.elapsed().as_secs_f64(),
        ),
    })
}

/// Logs the damaged archives ([`reader::Counts::damaged`]) and the reader's notes
/// ([`reader::Counts::notes`]) after the first `logged` of each; returns how many of each
/// are logged now.
fn log_reader_news(
    counts: &reader::Counts,
    log: &mut Log,
    logged: (usize, usize),
) -> (usize, usize) {
    let damaged = counts.damaged.lock().unwrap_or_else(|p| p.into_inner());
    for d in damaged.iter().skip(logged.0) {
        log.line(&format!("warning: {d}"));
    }
    let notes = counts.notes.lock().unwrap_or_else(|p| p.into_inner());
    for line in notes.iter().skip(logged.1) {
        log.line(&format!("reader: {line}"));
    }
    (damaged.len(), notes.len())
}

/// The data a worker placed, or `None` after logging why its write failed: the writer then
/// writes them itself, and a disk that is full or failing shows in skelid.log at the run
/// where it first did, even where the writer's own write succeeds.
fn placed_or_logged(
    placed: Placement,
    e: &Entry,
    log: &mut Log,
) -> Option<crate::report::PlacedData> {
    placed.unwrap_or_else(|err| {
        log.line(&format!(
            "warning {}:{} its worker could not write its data into results.h5.tmp ({err}); \
             the writer writes them",
            e.source, e.path
        ));
        None
    })
}

/// What the writer leaves: every entry with the group it was written to in results.h5.
pub(super) struct Written {
    pub(super) entries: Vec<(Entry, String)>,
    pub(super) skipped: usize,
    pub(super) failed: usize,
    pub(super) log: Log,
    /// The writer's CPU seconds and the wall seconds it ran: busy all the time, it sets
    /// the batch's pace, whatever the cores.
    pub(super) busy: (f64, f64),
}

/// The report plots of the runs that come first in the report's order (archive, then
/// path), at most as many as it draws: kept as runs finish, so that the end of a batch
/// decodes none of them again (reading them back from results.h5, serial under libhdf5's
/// lock, was 6 % of a 200-run batch's CPU time and all of its tail; [`page_runs`] draws
/// the rest from their journal files).
///
/// Shared by the workers and the writer: a worker decodes a run's plots only when the run
/// can still be drawn ([`Drawn::wants`]), since once `keep` runs are held a run that comes
/// after all of them never will be (decoding every run's was 3.6 ms of CPU per run).
pub(super) struct Drawn {
    pub(super) keep: usize,
    /// `None` where the plots must be drawn at the end ([`page_runs`]): none were decoded
    /// (a legacy journal file), or two runs share the archive name and path.
    pub(super) plots: std::sync::Mutex<BTreeMap<(String, String), Option<DrawnRun>>>,
}

impl Drawn {
    pub(super) fn new(keep: usize) -> Drawn {
        Drawn {
            keep,
            plots: std::sync::Mutex::new(BTreeMap::new()),
        }
    }

    pub(super) fn held(
        &self,
    ) -> std::sync::MutexGuard<'_, BTreeMap<(String, String), Option<DrawnRun>>> {
        self.plots.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Whether run `e` may still be drawn: fewer than `keep` runs are held, or it comes
    /// before the last of them. Once false for a run it stays false (the last held run
    /// only moves earlier).
    pub(super) fn wants(&self, e: &Entry) -> bool {
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
    pub(super) fn offer(&self, e: &Entry, plots: Option<DrawnRun>) {
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

    /// The held runs among the first `report_runs` of `entries` (in the report's order),
    /// each named by its group in results.h5; `None` for one [`page_runs`] draws.
    pub(super) fn take_shown(
        &self,
        entries: &[Entry],
        report_runs: usize,
    ) -> Vec<Option<DrawnRun>> {
        let shown = &entries[..entries.len().min(report_runs)];
        placements(shown)
            .iter()
            .zip(shown)
            .map(|(group, e)| self.take(e, group))
            .collect()
    }

    /// The plots of run `e`, drawn as the run at `group` of results.h5.
    pub(super) fn take(&self, e: &Entry, group: &str) -> Option<DrawnRun> {
        let mut p = self
            .held()
            .get_mut(&(e.source.clone(), e.path.clone()))?
            .take()?;
        p.run.path = group.to_string();
        Some(p)
    }
}

/// Where results.h5 holds a run until [`place_runs`] moves it to its group: one whose path
/// was already used when it finished (the same path in another archive), the `n`th to
/// finish. Inside the staging group, which is gone at the end: no run path can clash.
fn pending(n: usize) -> String {
    format!("{STAGING}/pending{n}")
}

/// The group of results.h5 that runs pass through on their way to their own.
const STAGING: &str = "/_skelid_staging";

/// Puts every run of `results` at its final group (see [`placements`]): link moves, through
/// [`STAGING`] so that two runs may trade places.
pub(super) fn place_runs(
    results: &ResultsFile,
    entries: &[Entry],
    written_at: &[String],
) -> Result<(), BatchError> {
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

/// The runs report.html draws (the first of `entries`, as many as `held`): each held one
/// as it is, the others drawn from their journal files as the run at their group of
/// results.h5, in parallel. Read back from results.h5 they went through libhdf5's lock one
/// at a time (0.77 s of a 1.3 s merge of 200 campaign runs).
pub(super) fn page_runs(
    journal: &Journal,
    entries: &[Entry],
    held: Vec<Option<DrawnRun>>,
) -> Vec<Result<DrawnRun, String>> {
    use rayon::prelude::*;
    let shown = &entries[..held.len()];
    placements(shown)
        .into_par_iter()
        .zip(shown)
        .zip(held)
        .map(|((group, e), h)| {
            if let Some(d) = h {
                return Ok(d);
            }
            let mut plots = match journal.load(&e.key) {
                Some((_, Stored::Encoded(run))) => html::encoded_plots(&run),
                Some((_, Stored::Legacy(f))) => html::read_run(&f, &e.path)?,
                None => {
                    return Err(format!(
                        "{}: missing or damaged",
                        journal.file(&e.key).display()
                    ))
                }
            };
            plots.path = group;
            Ok(DrawnRun::new(plots))
        })
        .collect()
}

/// The summaries and report.html (drawing `runs`, the first of `entries`), side by side:
/// neither reads results.h5.
pub(super) fn write_pages(
    out: &Path,
    entries: &[Entry],
    manifest: &Manifest,
    runs: Vec<Result<DrawnRun, String>>,
) -> Result<Vec<SummaryRow>, BatchError> {
    let rows: Vec<SummaryRow> = entries.iter().flat_map(|e| e.rows.clone()).collect();
    let omitted = entries.len() - runs.len();
    let title = std::fs::canonicalize(out).unwrap_or_else(|_| out.to_path_buf());
    // Worded as skelid.log words them; the first few, as on the terminal, so that a campaign
    // of many groups that are not runs does not push the results down the page.
    const SHOWN: usize = 20;
    let mut inputs_to_check: Vec<String> = (manifest.incomplete_archives.iter())
        .filter_map(IncompleteArchive::unread_note)
        .chain(manifest.damaged_archives.iter().map(ToString::to_string))
        .chain(
            (manifest.not_runs.iter())
                .map(|g| format!("skipped (not a run) {}: {}", g.archive, g.group)),
        )
        .collect();
    if inputs_to_check.len() > SHOWN {
        let more = inputs_to_check.len() - SHOWN;
        inputs_to_check.truncate(SHOWN);
        inputs_to_check.push(format!(
            "… and {more} more (all in manifest.json and skelid.log)"
        ));
    }
    let (summary, report) = rayon::join(
        || write_summary(out, &rows),
        || {
            html::write_report(
                out,
                &html::ReportPage {
                    title: &title.display().to_string(),
                    settings: &manifest.settings,
                    rows: &rows,
                    runs,
                    omitted,
                    inputs_to_check: &inputs_to_check,
                },
            )
        },
    );
    summary?;
    report?;
    Ok(rows)
}

/// `manifest.json`, written last: a folder with one is complete.
pub(super) fn write_manifest(out: &Path, manifest: &Manifest) -> Result<(), BatchError> {
    let text = serde_json::to_string_pretty(manifest).map_err(|e| ReportError {
        file: MANIFEST.into(),
        detail: e.to_string(),
    })?;
    crate::report::write_atomic(&out.join(MANIFEST), text.as_bytes())?;
    Ok(())
}

/// `<out>/skelid.log`: one line per event, appended, with seconds since the Unix epoch.
pub(super) struct Log {
    pub(super) file: std::fs::File,
}

impl Log {
    pub(super) fn open(out: &Path) -> Result<Log, ReportError> {
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

    pub(super) fn line(&mut self, text: &str) {
        use std::io::Write;
        let t = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        // One system call a line (formatted straight to the unbuffered file, it took one
        // a piece). A log line that cannot be written must not stop the batch.
        let _ = self.file.write_all(format!("{t:.3} {text}\n").as_bytes());
    }
}

/// Where the failure of an archive that could not be opened (or read to its end) is
/// recorded: `/_unreadable/<file name>`.
pub(super) const UNREADABLE: &str = "/_unreadable/";

/// The record of an archive that could not be opened: one failed entry under
/// [`UNREADABLE`]`<file name>`.
pub(super) fn unreadable(file: &Path, error: &dyn std::fmt::Display) -> RunOutcome {
    let name = file_name(file);
    RunOutcome {
        error: Some(format!("archive unreadable: {error}")),
        ..RunOutcome::new(format!("{UNREADABLE}{}", name.replace('/', "_")), name)
    }
}

pub(super) fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| p.display().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A worker's failed write of a run's data is a warning in skelid.log naming the run
    /// and the error, and leaves the writer to write the data; a run placed, or with
    /// nothing to place, logs nothing.
    #[test]
    fn a_failed_placement_is_logged_and_left_to_the_writer() {
        let dir = tempfile::tempdir().unwrap();
        let mut log = Log::open(dir.path()).unwrap();
        let entry = Entry {
            key: "k".into(),
            path: "/runs/run_007".into(),
            source: "campaign.h5".into(),
            failed: false,
            rows: Vec::new(),
        };
        assert!(placed_or_logged(Ok(None), &entry, &mut log).is_none());
        let err = std::io::Error::from_raw_os_error(libc::ENOSPC);
        assert!(placed_or_logged(Err(err), &entry, &mut log).is_none());
        let text = std::fs::read_to_string(dir.path().join("skelid.log")).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 1, "{text}");
        assert!(
            lines[0].contains("warning campaign.h5:/runs/run_007"),
            "{text}"
        );
        assert!(lines[0].contains("No space left on device"), "{text}");
    }
}
