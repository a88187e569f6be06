//! The room left on the output folder's disk: how fast the batch fills it and whether its
//! remaining runs fit. A full disk loses no run (each is committed as it finishes, and the
//! same command resumes), but found at 6 am it loses the night; said early it costs a
//! `rm`. In: the folder and the runs done and left; out: the free and needed bytes, and a
//! warning to say once.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Bytes free to this process's user on the file system holding `dir` (`statvfs`), or
/// `None` where it cannot be read.
pub fn free_bytes(dir: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
    let mut st = std::mem::MaybeUninit::<libc::statvfs>::zeroed();
    // SAFETY: `c` is a NUL-terminated path and `st` a statvfs the call fills on success.
    let rc = unsafe { libc::statvfs(c.as_ptr(), st.as_mut_ptr()) };
    if rc != 0 {
        return None;
    }
    // SAFETY: filled by the successful call above.
    let st = unsafe { st.assume_init() };
    #[allow(clippy::unnecessary_cast)] // the fields' types differ between platforms
    Some((st.f_bavail as u64).saturating_mul(st.f_frsize as u64))
}

/// Where the disk stands after some runs: what is free and what the runs left need at the
/// rate the batch has used it so far.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Room {
    /// Bytes free on the output's file system now.
    pub free_bytes: u64,
    /// Bytes the runs left need, at the batch's rate so far.
    pub needed_bytes: u64,
    /// Bytes a run took so far (its journal file and its share of results.h5).
    pub per_run_bytes: u64,
    /// Runs the estimate is for.
    pub runs_left: usize,
}

impl Room {
    /// Whether the runs left do not fit.
    pub fn short(&self) -> bool {
        self.needed_bytes > self.free_bytes
    }

    /// The warning for a disk that will fill before the batch ends, naming `dir`.
    pub fn warning(&self, dir: &Path) -> String {
        let fits = self.free_bytes / self.per_run_bytes.max(1);
        format!(
            "the disk holding {} will be full before the batch ends: at {} a run so far \
             (its journal file and its share of results.h5), the {} run(s) left need about \
             {} and {} is free, room for about {fits} more; the batch then stops, keeping \
             every run finished, and the same command resumes: free some space there now, \
             or stop it (Ctrl-C) and move the folder to a larger disk",
            dir.display(),
            size(self.per_run_bytes),
            self.runs_left,
            size(self.needed_bytes),
            size(self.free_bytes),
        )
    }
}

/// A size in bytes as a person reads it (decimal units: 1 MB is 10^6 bytes, as `df -H`).
pub fn size(bytes: u64) -> String {
    let b = bytes as f64;
    match bytes {
        0..=999 => format!("{bytes} B"),
        1_000..=999_999 => format!("{:.1} kB", b / 1e3),
        1_000_000..=999_999_999 => format!("{:.1} MB", b / 1e6),
        1_000_000_000..=999_999_999_999 => format!("{:.2} GB", b / 1e9),
        _ => format!("{:.2} TB", b / 1e12),
    }
}

/// Runs to finish before the rate is trusted (the first few include the files' headers).
const RUNS_BEFORE_ESTIMATE: usize = 8;
/// At most one `statvfs` this often (on NFS it is a round trip to the server).
const CHECK_EVERY: Duration = Duration::from_secs(1);

/// Watches the output's disk from the writer thread, run after run.
pub struct DiskWatch {
    dir: PathBuf,
    /// Free bytes when the batch started, and this process's pretended ones.
    start: Option<u64>,
    pretend: Option<u64>,
    last: Option<(Instant, Room)>,
    warned: bool,
}

impl DiskWatch {
    /// Starts watching the disk holding `dir`. `SKELID_DISK_FREE` (bytes) pretends the disk
    /// has at most that much free at the start, so that tests and rehearsals see the warning
    /// without filling a disk.
    pub fn start(dir: &Path) -> DiskWatch {
        let pretend = std::env::var("SKELID_DISK_FREE")
            .ok()
            .and_then(|v| v.trim().parse::<u64>().ok());
        DiskWatch {
            dir: dir.to_path_buf(),
            start: free_bytes(dir),
            pretend,
            last: None,
            warned: false,
        }
    }

    /// Where the disk stands after `done` runs with `left` still to come: measured again at
    /// most once a second, `None` before the first few runs or where it cannot be read.
    pub fn room(&mut self, done: usize, left: usize) -> Option<Room> {
        if done < RUNS_BEFORE_ESTIMATE {
            return None;
        }
        if let Some((at, room)) = self.last {
            if at.elapsed() < CHECK_EVERY {
                return Some(Room {
                    needed_bytes: room.per_run_bytes.saturating_mul(left as u64),
                    runs_left: left,
                    ..room
                });
            }
        }
        let (start, now) = (self.start?, free_bytes(&self.dir)?);
        let used = start.saturating_sub(now);
        let free = match self.pretend {
            Some(p) => now.min(p.saturating_sub(used)),
            None => now,
        };
        let per_run = used / done as u64;
        let room = Room {
            free_bytes: free,
            needed_bytes: per_run.saturating_mul(left as u64),
            per_run_bytes: per_run,
            runs_left: left,
        };
        self.last = Some((Instant::now(), room));
        Some(room)
    }

    /// The warning to say now: the first time the runs left do not fit, and never again
    /// (the figures go on in the progress either way).
    pub fn warning(&mut self, room: Option<Room>) -> Option<String> {
        let room = room.filter(|r| r.short() && !self.warned)?;
        self.warned = true;
        Some(room.warning(&self.dir))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The file system's free bytes agree with `df`'s idea of them: a file written takes
    /// them away.
    #[test]
    fn writing_a_file_takes_its_bytes_from_the_free_ones() {
        let dir = tempfile::tempdir().unwrap();
        let before = free_bytes(dir.path()).expect("statvfs of a temporary folder");
        assert!(before > 0);
        let data = vec![7u8; 8 << 20];
        std::fs::write(dir.path().join("f"), &data).unwrap();
        let f = std::fs::File::open(dir.path().join("f")).unwrap();
        f.sync_all().unwrap();
        let after = free_bytes(dir.path()).unwrap();
        println!("free {before} → {after} bytes after writing {}", data.len());
        // Other processes share the disk: only the sign and a loose size are certain.
        assert!(
            before.saturating_sub(after) >= 4 << 20,
            "{before} → {after}"
        );
        assert!(free_bytes(Path::new("/no/such/folder")).is_none());
    }

    #[test]
    fn the_warning_says_the_rate_the_need_and_the_room() {
        let room = Room {
            free_bytes: 250_000_000,
            needed_bytes: 400_000_000,
            per_run_bytes: 2_000_000,
            runs_left: 200,
        };
        assert!(room.short());
        let w = room.warning(Path::new("/data/night1"));
        println!("{w}");
        for part in [
            "/data/night1",
            "2.0 MB a run",
            "200 run(s) left need about 400.0 MB",
            "250.0 MB is free, room for about 125 more",
        ] {
            assert!(w.contains(part), "{part:?} in {w}");
        }
        assert!(!Room {
            needed_bytes: 250_000_000,
            ..room
        }
        .short());
        assert_eq!(size(999), "999 B");
        assert_eq!(size(1_500), "1.5 kB");
        assert_eq!(size(2_345_000_000), "2.35 GB");
    }

    /// Said once, the first time the runs left do not fit; nothing before the rate is
    /// known.
    #[test]
    fn the_warning_is_said_once() {
        let dir = tempfile::tempdir().unwrap();
        let mut watch = DiskWatch::start(dir.path());
        assert_eq!(watch.room(3, 100), None, "too few runs for a rate");
        let room = Room {
            free_bytes: 10,
            needed_bytes: 20,
            per_run_bytes: 1,
            runs_left: 20,
        };
        assert!(watch
            .warning(Some(Room {
                needed_bytes: 5,
                ..room
            }))
            .is_none());
        assert!(watch.warning(Some(room)).is_some());
        assert!(watch.warning(Some(room)).is_none());
    }
}
