//! Written data handed back to the kernel once it is on its way to disk, so that the next
//! writes reuse its page-cache pages instead of taking fresh ones.
//!
//! Why: on a virtual machine whose memory the host backs only when first touched (as on
//! this project's 2-core machines and the device machines, each started fresh), every page
//! the page cache takes from untouched memory costs a fault in the host during the copy:
//! 400 MB written cost 0.88 s of kernel time there, against 0.11 s when written in rounds
//! whose pages are dropped once on disk and reused. A batch writes each run twice (its
//! journal file and its chunks in results.h5, about 2 MB each for the throughput campaign),
//! and on fresh memory those copies doubled the time of the writer thread, which no number
//! of cores shares.
//!
//! So the data a batch will not read again is handed to one background thread, which
//! starts it to disk without waiting (`sync_file_range`) and drops its pages once
//! [`WINDOW_BYTES`] more have followed (`posix_fadvise(DONTNEED)`, which leaves dirty,
//! locked and partly covered pages alone). The writing threads only queue it. Correctness
//! never depends on it: a dropped page is read back from disk if it is ever needed. Linux
//! only (elsewhere nothing is handed over); `SKELID_PAGECACHE=keep` turns it off.

use std::collections::VecDeque;
use std::fs::File;
use std::sync::mpsc::{channel, RecvTimeoutError, Sender};
use std::sync::{Arc, Mutex, OnceLock};

/// Bytes handed over and not yet dropped: what was handed over last may still be under
/// writeback, which `DONTNEED` skips.
const WINDOW_BYTES: u64 = 16 << 20;

/// Parts held at most, whatever their size: each journal file among them holds a descriptor
/// open (a file's extents share one).
const WINDOW_PARTS: usize = 256;

/// How long the releaser waits for more before it lets go of what it holds.
const IDLE: std::time::Duration = std::time::Duration::from_secs(1);

/// Bytes of a growing file noted by [`Extents`] before they are handed over together.
const ROUND_BYTES: u64 = 4 << 20;

/// Starts writing the dirty pages of `len` bytes at `offset` (0: to the end) to disk,
/// without waiting for them.
#[cfg(target_os = "linux")]
fn start_writeback(file: &File, offset: u64, len: u64) {
    use std::os::fd::AsRawFd;
    // SAFETY: a plain system call on an open descriptor; a failure (a file system without
    // writeback, e.g. tmpfs) only means nothing is started.
    unsafe {
        libc::sync_file_range(
            file.as_raw_fd(),
            offset as libc::off64_t,
            len as libc::off64_t,
            libc::SYNC_FILE_RANGE_WRITE,
        );
    }
}

/// Drops the clean cached pages wholly inside `len` bytes at `offset` (0: to the end).
#[cfg(target_os = "linux")]
fn drop_clean(file: &File, offset: u64, len: u64) {
    use std::os::fd::AsRawFd;
    // SAFETY: as above; the kernel keeps every page that is dirty, under writeback, or
    // only partly inside the range.
    unsafe {
        libc::posix_fadvise(
            file.as_raw_fd(),
            offset as libc::off_t,
            len as libc::off_t,
            libc::POSIX_FADV_DONTNEED,
        );
    }
}

#[cfg(not(target_os = "linux"))]
fn start_writeback(_file: &File, _offset: u64, _len: u64) {}

#[cfg(not(target_os = "linux"))]
fn drop_clean(_file: &File, _offset: u64, _len: u64) {}

/// Whether written data is released at all: not with `SKELID_PAGECACHE=keep` in the
/// environment, which leaves it in the page cache as before (for side-by-side timings).
pub fn releasing() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| {
        cfg!(target_os = "linux")
            && std::env::var_os("SKELID_PAGECACHE").is_none_or(|v| v != "keep")
    })
}

/// Part of a file handed over for release: `len` bytes at `offset`, `len` 0 for the whole
/// file, whose size is then `size`.
struct Part {
    file: Arc<File>,
    offset: u64,
    len: u64,
    size: u64,
}

/// The releaser's queue: one thread for the process, started by the first hand-over, that
/// does the system calls so that the threads that write (the batch's workers and its one
/// writer) neither spend their time on them nor wait in them.
fn releaser() -> Option<&'static Mutex<Sender<Part>>> {
    static QUEUE: OnceLock<Option<Mutex<Sender<Part>>>> = OnceLock::new();
    QUEUE
        .get_or_init(|| {
            let (tx, rx) = channel::<Part>();
            std::thread::Builder::new()
                .name("skelid-release".into())
                .spawn(move || {
                    let mut held = VecDeque::new();
                    let mut held_bytes = 0;
                    loop {
                        let limit = match rx.recv_timeout(IDLE) {
                            Ok(part) => {
                                start_writeback(&part.file, part.offset, part.len);
                                held_bytes += part.size;
                                held.push_back(part);
                                WINDOW_BYTES
                            }
                            // Nothing new for a while: what is on disk by now is dropped
                            // (pages still under writeback are simply kept), and the files
                            // (a deleted one's space included) are let go.
                            Err(RecvTimeoutError::Timeout) => 0,
                            Err(RecvTimeoutError::Disconnected) => break,
                        };
                        while held_bytes > limit
                            || held.len() > WINDOW_PARTS
                            || (limit == 0 && !held.is_empty())
                        {
                            let Some(old) = held.pop_front() else { break };
                            drop_clean(&old.file, old.offset, old.len);
                            held_bytes -= old.size;
                        }
                    }
                })
                .ok()
                .map(|_| Mutex::new(tx))
        })
        .as_ref()
}

/// Hands `part` to the releaser; without one (its thread could not start) nothing is
/// released, which costs speed only.
fn hand_over(part: Part) {
    if let Some(queue) = releaser() {
        let _ = queue.lock().unwrap_or_else(|e| e.into_inner()).send(part);
    }
}

/// Hands over a file just written in full (a journal's run file) for release: it is
/// started to disk, and its pages are dropped once some more data has followed.
pub fn release_file(file: File, size: u64) {
    hand_over(Part {
        file: Arc::new(file),
        offset: 0,
        len: 0,
        size,
    });
}

/// Writes `bytes` as the whole of a new file at `path` and hands it over for release.
pub fn write_new_file(path: &std::path::Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut f = File::create(path)?;
    std::io::Write::write_all(&mut f, bytes)?;
    // Closed here, before the caller renames it (on NFS the close is what makes the data
    // visible to other machines); the releaser gets a descriptor of its own.
    drop(f);
    if releasing() {
        if let Ok(f) = File::open(path) {
            release_file(f, bytes.len() as u64);
        }
    }
    Ok(())
}

/// The extents of a growing file that will not be read or written again (results.h5's
/// chunks), handed over for release a few megabytes at a time.
pub struct Extents {
    file: Arc<File>,
    pending: Vec<(u64, u64)>,
    pending_bytes: u64,
}

impl Extents {
    /// Follows the file at `path` (opened for reading: the calls need no more), or `None`
    /// where it cannot be opened.
    pub fn open(path: &std::path::Path) -> Option<Extents> {
        if !releasing() {
            return None;
        }
        let file = Arc::new(File::open(path).ok()?);
        Some(Extents {
            file,
            pending: Vec::new(),
            pending_bytes: 0,
        })
    }

    /// Notes `len` bytes at `offset`, written and final.
    pub fn wrote(&mut self, offset: u64, len: u64) {
        if len == 0 {
            return;
        }
        // Chunks are allocated one after another at the end of the file: most extend the
        // previous extent.
        match self.pending.last_mut() {
            Some((o, l)) if *o + *l == offset => *l += len,
            _ => self.pending.push((offset, len)),
        }
        self.pending_bytes += len;
        if self.pending_bytes >= ROUND_BYTES {
            for (offset, len) in self.pending.drain(..) {
                hand_over(Part {
                    file: self.file.clone(),
                    offset,
                    len,
                    size: len,
                });
            }
            self.pending_bytes = 0;
        }
    }

    /// Extents noted and not yet handed over, as (offset, length).
    #[cfg(test)]
    pub(crate) fn pending(&self) -> &[(u64, u64)] {
        &self.pending
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    /// Extents that follow one another merge; a gap (metadata between two chunks) starts
    /// a new one; a round's worth hands them all over.
    #[test]
    fn extents_merge_when_adjacent_and_go_by_rounds() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        std::fs::write(&path, vec![7u8; 1 << 16]).unwrap();
        let mut e = Extents::open(&path).unwrap();
        e.wrote(0, 100);
        e.wrote(100, 50);
        e.wrote(4096, 10);
        e.wrote(5000, 0);
        assert_eq!(e.pending(), [(0, 150), (4096, 10)]);
        e.wrote(4106, ROUND_BYTES);
        assert!(e.pending().is_empty());
        e.wrote(1 << 30, 10);
        assert_eq!(e.pending(), [(1 << 30, 10)]);
        // Nothing of it touches the data.
        assert_eq!(std::fs::read(&path).unwrap(), vec![7u8; 1 << 16]);
    }

    #[cfg(target_os = "linux")]
    fn page_size() -> usize {
        // SAFETY: a query without side effects.
        unsafe { libc::sysconf(libc::_SC_PAGESIZE) as usize }
    }

    /// How many of the file's pages are in the page cache (`mincore` over a mapping).
    #[cfg(target_os = "linux")]
    fn resident_pages(file: &File, len: usize) -> usize {
        use std::os::fd::AsRawFd;
        let page = 4096;
        let pages = len.div_ceil(page);
        let mut vec = vec![0u8; pages];
        // SAFETY: a read-only shared mapping of an open file, unmapped before returning;
        // `vec` has one byte per page of it.
        unsafe {
            let p = libc::mmap(
                std::ptr::null_mut(),
                len,
                libc::PROT_READ,
                libc::MAP_SHARED,
                file.as_raw_fd(),
                0,
            );
            assert_ne!(p, libc::MAP_FAILED);
            assert_eq!(libc::mincore(p, len, vec.as_mut_ptr()), 0);
            libc::munmap(p, len);
        }
        vec.iter().filter(|&&b| b & 1 == 1).count()
    }

    /// The pages of data on disk are dropped, those of a part-covered page kept: the
    /// point of the module, checked on the file system of the source tree (tmpfs, which
    /// may hold /tmp, has no disk to drop pages to).
    #[cfg(target_os = "linux")]
    #[test]
    fn clean_pages_are_dropped_and_part_covered_ones_kept() {
        if page_size() != 4096 {
            eprintln!("skipped: the counts assume 4 KiB pages");
            return;
        }
        let dir = tempfile::tempdir_in(env!("CARGO_MANIFEST_DIR")).unwrap();
        let path = dir.path().join("f");
        let len = 64 * 4096;
        // Readable too: the check maps it.
        let mut f = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(&path)
            .unwrap();
        // A page a write: the page cache then holds single pages, not the large folios a
        // long write may get, which are dropped only when wholly inside the range.
        for _ in 0..64 {
            f.write_all(&[3u8; 4096]).unwrap();
        }
        f.sync_all().unwrap();
        assert_eq!(resident_pages(&f, len), 64);
        // Bytes 12 289..40 961: pages 4 to 9 wholly inside, 3 and 10 only partly.
        drop_clean(&f, 3 * 4096 + 1, 7 * 4096);
        assert_eq!(resident_pages(&f, len), 64 - 6);
        drop_clean(&f, 0, 0);
        assert_eq!(resident_pages(&f, len), 0);
        assert_eq!(std::fs::read(&path).unwrap(), vec![3u8; len]);
    }

    /// A file handed over is dropped from the page cache once more than the window has
    /// followed it (or the releaser has gone idle), and every file stays whole. Polled
    /// every 50 ms: `mincore` holds a page for an instant, and a drop meeting it keeps it. On the source tree's file system, as above.
    #[cfg(target_os = "linux")]
    #[test]
    fn released_files_leave_the_cache_and_keep_their_contents() {
        if page_size() != 4096 {
            eprintln!("skipped: the counts assume 4 KiB pages");
            return;
        }
        let dir = tempfile::tempdir_in(env!("CARGO_MANIFEST_DIR")).unwrap();
        let write = |name: &str, byte: u8, len: usize| {
            let mut f = File::create(dir.path().join(name)).unwrap();
            f.write_all(&vec![byte; len]).unwrap();
            f
        };
        // Already on disk, so that the drop cannot meet it under writeback.
        let first = write("first", 1, 1 << 20);
        first.sync_all().unwrap();
        let probe = File::open(dir.path().join("first")).unwrap();
        assert_eq!(resident_pages(&probe, 1 << 20), 256);
        release_file(first, 1 << 20);
        let more = WINDOW_BYTES as usize / (4 << 20) + 1;
        for i in 0..more {
            let f = write(&format!("more{i}"), 2, 4 << 20);
            release_file(f, 4 << 20);
        }
        let t0 = std::time::Instant::now();
        while resident_pages(&probe, 1 << 20) > 0 && t0.elapsed().as_secs() < 10 {
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        assert_eq!(resident_pages(&probe, 1 << 20), 0);
        assert_eq!(
            std::fs::read(dir.path().join("first")).unwrap(),
            vec![1u8; 1 << 20]
        );
        for i in 0..more {
            let back = std::fs::read(dir.path().join(format!("more{i}"))).unwrap();
            assert!(back.len() == 4 << 20 && back.iter().all(|&b| b == 2));
        }
    }
}
