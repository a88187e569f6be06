//! One writer an output folder: a batch (or a merge) holds an exclusive lock on the folder's
//! `skelid.log` from its start to its end, so that a second one into the same folder (a
//! cron job fired again while last night's batch still runs, the same command typed in a
//! second terminal) is refused at once, naming the first, instead of both failing with
//! "cannot write: No such file or directory" and the folder left without its results.h5.
//! The lock is the kernel's (`flock`): it goes with the process, however it ends, so a
//! killed batch leaves nothing to clean up; the log, not a file of its own, carries it, so
//! the folder holds no new file.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use super::BatchError;
use crate::report::ReportError;

/// The file whose lock is the folder's: the batch's log.
const LOG: &str = "skelid.log";

/// The folders this process holds, so that an interruption changes only its own folder.
static HELD: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// The lock of an output folder, held until dropped.
pub(super) struct FolderLock {
    _file: File,
    folder: PathBuf,
    /// Why the folder could not be locked, where its file system offers no locks (some NFS
    /// mounts): the work goes on, unguarded, and the log says so.
    pub(super) unguarded: Option<String>,
}

impl FolderLock {
    /// Takes `out`'s lock, making the folder: refused ([`BatchError::InUse`]) while another
    /// process holds it. `what` names the work for the refusal ("batch", "merge").
    pub(super) fn take(out: &Path, what: &str) -> Result<FolderLock, BatchError> {
        let report = |file: &Path, e: std::io::Error| ReportError {
            file: file.display().to_string(),
            detail: e.to_string(),
        };
        std::fs::create_dir_all(out).map_err(|e| report(out, e))?;
        let path = out.join(LOG);
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .read(true)
            .open(&path)
            .map_err(|e| report(&path, e))?;
        let unguarded = match file.try_lock() {
            Ok(()) => None,
            Err(TryLockError::WouldBlock) => {
                return Err(BatchError::InUse {
                    folder: out.to_path_buf(),
                    holder: holder(&file),
                    advice: format!(
                        "wait for it to end (or stop it: the command that started it then \
                         resumes its work), or give this {what} another folder"
                    ),
                })
            }
            Err(TryLockError::Error(e)) => Some(format!(
                "{} cannot be locked ({e}): a second batch or merge into this folder would \
                 not be refused",
                path.display()
            )),
        };
        let folder = std::path::absolute(out).unwrap_or_else(|_| out.to_path_buf());
        held().push(folder.clone());
        Ok(FolderLock {
            _file: file,
            folder,
            unguarded,
        })
    }
}

impl Drop for FolderLock {
    fn drop(&mut self) {
        let mut held = held();
        if let Some(i) = held.iter().position(|f| *f == self.folder) {
            held.swap_remove(i);
        }
    }
}

fn held() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    HELD.lock().unwrap_or_else(|p| p.into_inner())
}

/// Whether this process holds `out`'s lock (a batch or merge of its own is writing it).
pub(super) fn holds(out: &Path) -> bool {
    let folder = std::path::absolute(out).unwrap_or_else(|_| out.to_path_buf());
    held().contains(&folder)
}

/// Refuses `dir` as an input while a batch is still writing it (a shard not yet finished,
/// or run again): its manifest and results may be the previous run's or half the new one.
/// A folder without a log, or whose file system has no locks, passes.
pub(super) fn finished(dir: &Path) -> Result<(), BatchError> {
    let Ok(file) = File::open(dir.join(LOG)) else {
        return Ok(());
    };
    match file.try_lock_shared() {
        Err(TryLockError::WouldBlock) => Err(BatchError::InUse {
            folder: dir.to_path_buf(),
            holder: holder(&file),
            advice: "merge once it has ended".into(),
        }),
        // The shared lock goes with `file`, at once.
        Ok(()) | Err(TryLockError::Error(_)) => Ok(()),
    }
}

/// Who holds a folder's lock, from the last start its log records: "skelid's batch of pid
/// 4242, started 3 min 12 s ago", or less where the log says less.
fn holder(log: &File) -> String {
    let mut tail = String::new();
    let mut log = log;
    let len = log.metadata().map_or(0, |m| m.len());
    // The last start is near the end: the lines after it are the runs of one batch.
    let from = len.saturating_sub(1 << 20);
    if log.seek(SeekFrom::Start(from)).is_ok() {
        let _ = log.take(1 << 20).read_to_string(&mut tail);
    }
    describe(&tail, now_s())
}

fn now_s() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// [`holder`]'s words from a log's text and the time now (Unix seconds).
fn describe(log: &str, now: f64) -> String {
    let start = log.lines().rev().find_map(|l| {
        let (t, text) = l.split_once(' ')?;
        let what = if text.starts_with("start: ") {
            "batch"
        } else if text.starts_with("merge: ") {
            "merge"
        } else {
            return None;
        };
        Some((t.parse::<f64>().ok()?, what, text))
    });
    let Some((t, what, text)) = start else {
        return "another skelid process".into();
    };
    let pid = text
        .rsplit_once("pid ")
        .and_then(|(_, p)| p.split(|c: char| !c.is_ascii_digit()).next())
        .filter(|p| !p.is_empty())
        .map_or(String::new(), |p| format!(" of pid {p}"));
    format!(
        "skelid's {what}{pid}, started {} ago",
        duration((now - t).max(0.0))
    )
}

/// "45 s", "3 min 12 s", "2 h 05 min".
fn duration(s: f64) -> String {
    let s = s.round() as u64;
    match s {
        0..60 => format!("{s} s"),
        60..3600 => format!("{} min {} s", s / 60, s % 60),
        _ => format!("{} h {:02} min", s / 3600, s % 3600 / 60),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A second lock on a held folder is refused with the holder's start, its pid and the
    /// time since, and granted once the first is dropped; a shard's folder reads as
    /// finished only then. (flock conflicts between two opens in one process as between
    /// two processes; tests/batch.rs has two processes.)
    #[test]
    fn a_held_folder_is_refused_naming_its_holder_until_let_go() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("night1");
        let first = FolderLock::take(&out, "batch").unwrap();
        assert!(first.unguarded.is_none(), "{:?}", first.unguarded);
        assert!(holds(&out));
        std::fs::write(
            out.join(LOG),
            format!(
                "100.000 start: 1 archive(s), settings x, pid 4242\n{:.3} done /a\n",
                now_s()
            ),
        )
        .unwrap();
        let refused = FolderLock::take(&out, "batch").err().expect("refused");
        let said = refused.to_string();
        println!("{said}");
        assert!(
            said.contains("is in use by skelid's batch of pid 4242, started"),
            "{said}"
        );
        assert!(said.contains(" h "), "started long ago: {said}");
        assert!(
            said.ends_with("or give this batch another folder"),
            "{said}"
        );
        assert!(matches!(finished(&out), Err(BatchError::InUse { .. })));
        drop(first);
        assert!(!holds(&out));
        finished(&out).unwrap();
        let again = FolderLock::take(&out, "merge").unwrap();
        assert!(holds(&out));
        drop(again);
        // A folder no batch ever wrote.
        finished(&tmp.path().join("nothing")).unwrap();
    }

    #[test]
    fn the_holder_is_described_from_the_last_start_in_its_log() {
        let log = "10.000 start: 2 archive(s), settings a, pid 7\n\
                   20.000 done /r1\n\
                   30.000 merge: 2 shard folder(s), pid 99\n\
                   31.500 copied\n";
        assert_eq!(
            describe(log, 30.0 + 192.4),
            "skelid's merge of pid 99, started 3 min 12 s ago"
        );
        assert_eq!(
            describe("10.000 start: 1 archive(s), settings a\n", 55.0),
            "skelid's batch, started 45 s ago"
        );
        assert_eq!(describe("", 1.0), "another skelid process");
        assert_eq!(
            describe("garbage\nno time here\n", 1.0),
            "another skelid process"
        );
        assert_eq!(duration(7265.0), "2 h 01 min");
    }
}
