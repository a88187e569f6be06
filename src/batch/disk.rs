//! The room left on the output folder's disk: how fast the batch fills it (by its own
//! count of what it wrote) and whether its remaining runs fit. A full disk loses no run
//! (each is committed as it finishes, and the same command resumes), but found at 6 am it
//! loses the night; said early it costs a `rm`. In: the folder and the runs done and left;
//! out: the free and needed bytes, and a warning to say once.

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
    /// Bytes a run costs, by the runs so far (its journal file and its share of results.h5).
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

/// Runs to finish before the rate is trusted: the first ones may not be typical (a failed
/// or unreadable run stores little).
const RUNS_BEFORE_ESTIMATE: usize = 8;
/// At most one `statvfs` this often (on NFS it is a round trip to the server).
const CHECK_EVERY: Duration = Duration::from_secs(1);

/// Watches the output's disk from the writer thread, run after run.
pub struct DiskWatch {
    dir: PathBuf,
    /// Bytes this process pretends were free at most at the start (`SKELID_DISK_FREE`).
    pretend: Option<u64>,
    /// Bytes the batch has written so far, by its own count, so that other programs
    /// writing to or deleting from the same disk do not move the rate.
    written: u64,
    /// What the runs done so far would have cost done now: a run found committed would
    /// also have written its journal file.
    cost: u64,
    /// Runs costed (a run found in an earlier version's journal is not: its size is not
    /// known).
    runs: usize,
    /// The last `statvfs` reading and when it was taken.
    last: Option<(Instant, u64)>,
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
            pretend,
            written: 0,
            cost: 0,
            runs: 0,
            last: None,
            warned: false,
        }
    }

    /// Counts a finished run: the `bytes` the batch has just written for it, and the
    /// bytes it would have cost had it been identified now (`cost`).
    pub fn wrote(&mut self, bytes: u64, cost: u64) {
        self.written = self.written.saturating_add(bytes);
        self.cost = self.cost.saturating_add(cost);
        self.runs += 1;
    }

    /// Where the disk stands with `left` runs still to come, `None` before the first few
    /// runs or where the disk cannot be asked. The runs still in the workers' hands may
    /// have written some of their bytes already: those count against the free bytes and
    /// again in the need, so the need is high by up to about two runs a worker.
    pub fn room(&mut self, left: usize) -> Option<Room> {
        if self.runs < RUNS_BEFORE_ESTIMATE {
            return None;
        }
        let now = match self.last {
            Some((at, free)) if at.elapsed() < CHECK_EVERY => free,
            _ => {
                let free = free_bytes(&self.dir)?;
                self.last = Some((Instant::now(), free));
                free
            }
        };
        let free = match self.pretend {
            Some(p) => now.min(p.saturating_sub(self.written)),
            None => now,
        };
        let per_run = self.cost / self.runs as u64;
        Some(Room {
            free_bytes: free,
            needed_bytes: per_run.saturating_mul(left as u64),
            per_run_bytes: per_run,
            runs_left: left,
        })
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

    /// The file system's free bytes are `df`'s (an independent reading of the same
    /// statistics), within what other programs may write or delete meanwhile.
    #[test]
    fn free_bytes_are_dfs() {
        let dir = tempfile::tempdir().unwrap();
        let ours = free_bytes(dir.path()).expect("statvfs of a temporary folder");
        assert!(free_bytes(Path::new("/no/such/folder")).is_none());
        let out = std::process::Command::new("df")
            .args(["-B1", "--output=avail"])
            .arg(dir.path())
            .output();
        let text = match &out {
            Ok(o) if o.status.success() => String::from_utf8_lossy(&o.stdout).into_owned(),
            _ => String::new(),
        };
        let Some(theirs) = text
            .lines()
            .nth(1)
            .and_then(|l| l.trim().parse::<u64>().ok())
        else {
            println!("no GNU df here: compared with nothing");
            return;
        };
        println!("free: ours {ours} bytes, df's {theirs}");
        assert!(
            ours.abs_diff(theirs) <= (64 << 20).max(theirs / 20),
            "{ours} against {theirs}"
        );
    }

    /// The warning names the folder, the rate, the need and the room, in decimal units.
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

    /// The rate is the batch's own bytes a run, whatever else happens on the disk, with a
    /// run found committed costed as if done now; the warning is said once, the first time
    /// the runs left do not fit, and nothing before the rate is known.
    #[test]
    fn the_rate_is_the_batchs_own_and_the_warning_is_said_once() {
        let dir = tempfile::tempdir().unwrap();
        let mut watch = DiskWatch::start(dir.path());
        watch.pretend = Some(10_000_000);
        for _ in 0..6 {
            watch.wrote(1_000_000, 1_000_000);
        }
        // A run found committed: half a new one's bytes written, a whole one's cost.
        watch.wrote(500_000, 1_000_000);
        assert_eq!(watch.room(100), None, "too few runs for a rate");
        watch.wrote(1_000_000, 1_000_000);
        let room = watch.room(5).expect("a rate after 8 runs");
        println!("{room:?}");
        assert_eq!(room.per_run_bytes, 1_000_000);
        assert_eq!(room.needed_bytes, 5_000_000);
        assert_eq!(
            room.free_bytes, 2_500_000,
            "10 MB pretended, 7.5 MB written"
        );
        assert!(room.short());
        let roomy = Room {
            needed_bytes: 1_000_000,
            ..room
        };
        assert!(watch.warning(Some(roomy)).is_none());
        assert!(watch.warning(Some(room)).is_some());
        assert!(watch.warning(Some(room)).is_none(), "said once");
        // The bytes written since the last reading of the disk count at once.
        watch.wrote(1_000_000, 1_000_000);
        let later = watch.room(2).unwrap();
        assert_eq!(
            (later.free_bytes, later.needed_bytes),
            (1_500_000, 2_000_000)
        );
    }
}
