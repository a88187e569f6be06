//! One writer an output folder: a batch (or a merge) holds an exclusive lock on the folder's
//! `skelid.log` from its start to its end, so that a second one into the same folder (a
//! cron job fired again while last night's batch still runs, the same command typed in a
//! second terminal) is refused at once, naming the first, instead of both failing with
//! "cannot write: No such file or directory" and the folder left without its results.h5.
//! The lock is the kernel's (`flock`): it goes with the process, however it ends, so a
//! killed batch leaves nothing to clean up; the log, not a file of its own, carries it, so
//! the folder holds no new file.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use super::BatchError;
use crate::report::ReportError;

/// The file whose lock is the folder's: the batch's log.
const LOG: &str = "skelid.log";

/// The folders this process holds, each with why it is unguarded (if it is): an
/// interruption changes only its own folders, and a lock taken again says what the first
/// said.
static HELD: Mutex<Vec<(PathBuf, Option<String>)>> = Mutex::new(Vec::new());

/// The lock of an output folder, held until dropped.
pub struct FolderLock {
    /// The log, locked; `None` in a lock taken again by the process that holds it.
    file: Option<File>,
    folder: PathBuf,
    /// Why the folder could not be locked, where its file system refuses locks (Lustre
    /// mounted without `flock`, some NFS): the work goes on, unguarded.
    pub unguarded: Option<String>,
}

impl FolderLock {
    /// Takes `out`'s lock, making the folder, and records in its log who took it: refused
    /// ([`BatchError::InUse`]) while another process holds it. `what` names the work for
    /// the log and the refusal ("batch", "merge", "demo"). Taken again by the process that
    /// holds it (the command line takes it before its own first write, the batch again),
    /// it is granted at once, unguarded as the first, and lets go of nothing when dropped.
    pub fn take(out: &Path, what: &str) -> Result<FolderLock, BatchError> {
        let folder = std::path::absolute(out).unwrap_or_else(|_| out.to_path_buf());
        if let Some((_, unguarded)) = held().iter().find(|(f, _)| *f == folder) {
            return Ok(FolderLock {
                file: None,
                folder,
                unguarded: unguarded.clone(),
            });
        }
        let report = |file: &Path, e: std::io::Error| ReportError {
            file: file.display().to_string(),
            detail: e.to_string(),
        };
        std::fs::create_dir_all(out).map_err(|e| report(out, e))?;
        let path = out.join(LOG);
        let mut file = OpenOptions::new()
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
        // At once, so that a refusal names this process, not the folder's last batch.
        let _ = writeln!(
            file,
            "{:.3} {TAKEN}{} for a {what}",
            now_s(),
            std::process::id()
        );
        held().push((folder.clone(), unguarded.clone()));
        Ok(FolderLock {
            file: Some(file),
            folder,
            unguarded,
        })
    }
}

impl Drop for FolderLock {
    fn drop(&mut self) {
        if self.file.is_none() {
            return;
        }
        let mut held = held();
        if let Some(i) = held.iter().position(|(f, _)| *f == self.folder) {
            held.swap_remove(i);
        }
    }
}

/// How the log records a lock taken: "lock: taken by pid 4242 for a batch".
const TAKEN: &str = "lock: taken by pid ";

fn held() -> std::sync::MutexGuard<'static, Vec<(PathBuf, Option<String>)>> {
    HELD.lock().unwrap_or_else(|p| p.into_inner())
}

/// Whether this process holds `out`'s lock (a batch or merge of its own is writing it).
pub(super) fn holds(out: &Path) -> bool {
    let folder = std::path::absolute(out).unwrap_or_else(|_| out.to_path_buf());
    held().iter().any(|(f, _)| *f == folder)
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

/// Who holds a folder's lock, from the last lock its log records taken: "skelid's batch of
/// pid 4242, started 3 min 12 s ago", or "another skelid process" where it says none.
fn holder(log: &File) -> String {
    let mut tail = String::new();
    let mut log = log;
    let len = log.metadata().map_or(0, |m| m.len());
    // The last lock taken is near the end: the lines after it are one batch's.
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

/// [`holder`]'s words from a log's text and the time now (Unix seconds): the last lock
/// it records taken.
fn describe(log: &str, now: f64) -> String {
    let taken = log.lines().rev().find_map(|l| {
        let (t, text) = l.split_once(' ')?;
        let (pid, what) = text.strip_prefix(TAKEN)?.split_once(" for a ")?;
        Some((t.parse::<f64>().ok()?, pid, what))
    });
    let Some((t, pid, what)) = taken else {
        return "another skelid process".into();
    };
    format!(
        "skelid's {what} of pid {pid}, started {} ago",
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

    /// A folder another holder has locked (a second open of its log stands in for another
    /// process: flock conflicts between two opens as between two processes; tests/batch.rs
    /// has two processes) is refused, naming that holder from the log, and reads as not
    /// finished; once let go it is taken, the taker recorded in the log, taken again at once
    /// by the same process, and held until the first lock is dropped.
    #[test]
    fn a_held_folder_is_refused_naming_its_holder_until_let_go() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("night1");
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(
            out.join(LOG),
            format!("100.000 {TAKEN}4242 for a batch\n{:.3} done /a\n", now_s()),
        )
        .unwrap();
        let other = File::open(out.join(LOG)).unwrap();
        other.try_lock().unwrap();
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
        assert!(!holds(&out));
        assert!(matches!(finished(&out), Err(BatchError::InUse { .. })));
        drop(other);
        finished(&out).unwrap();

        let first = FolderLock::take(&out, "demo").unwrap();
        assert!(first.unguarded.is_none(), "{:?}", first.unguarded);
        assert!(holds(&out));
        let log = std::fs::read_to_string(out.join(LOG)).unwrap();
        let mine = format!("{TAKEN}{} for a demo", std::process::id());
        assert!(log.lines().last().unwrap().ends_with(&mine), "{log}");
        let again = FolderLock::take(&out, "batch").unwrap();
        assert!(again.file.is_none());
        drop(again);
        assert!(holds(&out), "the inner lock lets go of nothing");
        let blocked = File::open(out.join(LOG)).unwrap();
        assert!(blocked.try_lock_shared().is_err(), "still locked");
        drop(first);
        assert!(!holds(&out));
        finished(&out).unwrap();
        // A folder no batch ever wrote.
        finished(&tmp.path().join("nothing")).unwrap();
        // A folder this process holds unguarded (its file system refused the lock): taken
        // again, for the batch inside the command, it says so again, for the batch's log.
        let bare = std::path::absolute(tmp.path().join("bare")).unwrap();
        held().push((bare.clone(), Some("no locks here".into())));
        let inner = FolderLock::take(&bare, "batch").unwrap();
        assert_eq!(inner.unguarded.as_deref(), Some("no locks here"));
        assert!(
            inner.file.is_none() && !bare.exists(),
            "nothing made or opened"
        );
        held().retain(|(f, _)| *f != bare);
    }

    #[test]
    fn the_holder_is_described_from_the_last_lock_taken_in_its_log() {
        let log = format!(
            "10.000 {TAKEN}7 for a batch\n\
             10.100 start: 2 archive(s), settings a\n\
             20.000 done /r1\n\
             30.000 {TAKEN}99 for a merge\n\
             30.010 merge: 2 shard folder(s)\n\
             31.500 end\n"
        );
        assert_eq!(
            describe(&log, 30.0 + 192.4),
            "skelid's merge of pid 99, started 3 min 12 s ago"
        );
        assert_eq!(
            describe(&format!("10.000 {TAKEN}7 for a batch\n"), 55.0),
            "skelid's batch of pid 7, started 45 s ago"
        );
        assert_eq!(describe("", 1.0), "another skelid process");
        assert_eq!(
            describe("10.000 start: 1 archive(s)\nno time here\n", 1.0),
            "another skelid process"
        );
        assert_eq!(duration(7265.0), "2 h 01 min");
    }
}
