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

/// What the kernel is asked to do with a range of a file's cached pages.
#[derive(Clone, Copy)]
enum Hint {
    /// Start writing its dirty pages to disk, without waiting for them
    /// (`sync_file_range(WRITE)`).
    StartWriteback,
    /// Drop its clean pages (`posix_fadvise(DONTNEED)`, which keeps every page that is
    /// dirty, under writeback, or only partly inside the range).
    DropClean,
}

/// Gives the kernel `hint` for `len` bytes at `offset` (0: to the end). Only a hint: a
/// failure (a file system without writeback, e.g. tmpfs, or a range beyond what `off_t`
/// holds on a 32-bit target) means nothing is done, and correctness never depends on it.
#[cfg(target_os = "linux")]
fn give(file: &File, offset: u64, len: u64, hint: Hint) {
    use std::os::fd::AsRawFd;
    let fd = file.as_raw_fd();
    match hint {
        Hint::StartWriteback => {
            let (Ok(offset), Ok(len)) = (
                libc::off64_t::try_from(offset),
                libc::off64_t::try_from(len),
            ) else {
                return;
            };
            // SAFETY: a plain system call on an open descriptor.
            unsafe { libc::sync_file_range(fd, offset, len, libc::SYNC_FILE_RANGE_WRITE) };
        }
        Hint::DropClean => {
            let (Ok(offset), Ok(len)) = (libc::off_t::try_from(offset), libc::off_t::try_from(len))
            else {
                return;
            };
            // SAFETY: as above.
            unsafe { libc::posix_fadvise(fd, offset, len, libc::POSIX_FADV_DONTNEED) };
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn give(_file: &File, _offset: u64, _len: u64, _hint: Hint) {}

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

/// The parts the releaser holds, oldest first: each was started to disk when it came, and
/// leaves once [`WINDOW_BYTES`] more have followed it (by then it is most likely on disk,
/// and its pages can be dropped), or once more than [`WINDOW_PARTS`] are held.
#[derive(Default)]
struct Window {
    held: VecDeque<Part>,
    /// Bytes of the parts held.
    bytes: u64,
}

impl Window {
    /// Takes `part` in and returns the oldest parts that have left the window.
    fn push(&mut self, part: Part) -> Vec<Part> {
        self.bytes += part.size;
        self.held.push_back(part);
        let mut gone = Vec::new();
        while let Some(oldest) = self.held.front() {
            let after = self.bytes - oldest.size;
            if after < WINDOW_BYTES && self.held.len() <= WINDOW_PARTS {
                break;
            }
            self.bytes = after;
            gone.extend(self.held.pop_front());
        }
        gone
    }

    /// Lets go of every part held.
    fn drain(&mut self) -> Vec<Part> {
        self.bytes = 0;
        self.held.drain(..).collect()
    }
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
                    let mut window = Window::default();
                    loop {
                        let gone = match rx.recv_timeout(IDLE) {
                            Ok(part) => {
                                give(&part.file, part.offset, part.len, Hint::StartWriteback);
                                window.push(part)
                            }
                            // Nothing new for a while: what is on disk by now is dropped
                            // (pages still under writeback are simply kept), and the files
                            // (a deleted one's space included) are let go.
                            Err(RecvTimeoutError::Timeout) => window.drain(),
                            Err(RecvTimeoutError::Disconnected) => break,
                        };
                        for old in gone {
                            give(&old.file, old.offset, old.len, Hint::DropClean);
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

/// Hands over `len` bytes at `offset` of `file`, written and final (a run's data that a
/// batch's worker put into results.h5 itself), for release as [`Extents`] hands its own.
pub fn release_extent(file: &Arc<File>, offset: u64, len: u64) {
    if releasing() && len > 0 {
        hand_over(Part {
            file: file.clone(),
            offset,
            len,
            size: len,
        });
    }
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
            self.hand_over_pending();
        }
    }

    /// Hands every extent noted so far over to the releaser.
    fn hand_over_pending(&mut self) {
        for (offset, len) in self.pending.drain(..) {
            release_extent(&self.file, offset, len);
        }
        self.pending_bytes = 0;
    }

    /// Extents noted and not yet handed over, as (offset, length).
    #[cfg(test)]
    pub(crate) fn pending(&self) -> &[(u64, u64)] {
        &self.pending
    }
}

impl Drop for Extents {
    /// The last round, shorter than [`ROUND_BYTES`], goes too: the file is finished (or
    /// abandoned) when its writer lets go of this.
    fn drop(&mut self) {
        self.hand_over_pending();
    }
}

/// Which of the 4 KiB pages of the first `len` bytes of `file` are in the page cache
/// (`mincore` over a mapping): for the tests of what is released.
#[cfg(all(test, target_os = "linux"))]
pub(crate) fn resident(file: &File, len: usize) -> Vec<bool> {
    use std::os::fd::AsRawFd;
    let mut vec = vec![0u8; len.div_ceil(4096)];
    // SAFETY: a read-only shared mapping of an open file, unmapped before returning; `vec`
    // has one byte per page of it.
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
    vec.iter().map(|&b| b & 1 == 1).collect()
}

/// A temporary folder on the source tree's file system (tmpfs, which may hold /tmp, has no
/// disk to drop pages to), for the tests of what is released; `None`, with a note that the
/// test is skipped, where pages are not the 4 KiB their counts assume.
#[cfg(all(test, target_os = "linux"))]
pub(crate) fn disk_tempdir() -> Option<tempfile::TempDir> {
    // SAFETY: a query without side effects.
    if unsafe { libc::sysconf(libc::_SC_PAGESIZE) } != 4096 {
        eprintln!("skipped: the page counts assume 4 KiB pages");
        return None;
    }
    Some(tempfile::tempdir_in(env!("CARGO_MANIFEST_DIR")).unwrap())
}

/// Waits (up to 10 s, looking every 50 ms) until at most `at_most` of the pages `pages`
/// of `file` are in the page cache, and returns how many are. Polled: `mincore` holds a
/// page for an instant, and a drop that meets it keeps it.
#[cfg(all(test, target_os = "linux"))]
pub(crate) fn cached_after_release(file: &File, pages: &[usize], at_most: usize) -> usize {
    let len = file.metadata().unwrap().len() as usize;
    let cached = || {
        let map = resident(file, len);
        pages.iter().filter(|&&p| map[p]).count()
    };
    let t0 = std::time::Instant::now();
    while cached() > at_most && t0.elapsed().as_secs() < 10 {
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let n = cached();
    eprintln!("{n} of {} pages still cached", pages.len());
    n
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

    /// A part leaves the window when the bytes that followed it reach [`WINDOW_BYTES`], not
    /// before; or, whatever their size, when more than [`WINDOW_PARTS`] are held; and all
    /// leave when the releaser goes idle.
    #[test]
    fn parts_leave_the_window_once_enough_has_followed() {
        let file = Arc::new(tempfile::tempfile().unwrap());
        let part = |offset: u64, size: u64| Part {
            file: file.clone(),
            offset,
            len: size,
            size,
        };
        let offsets = |parts: Vec<Part>| parts.iter().map(|p| p.offset).collect::<Vec<_>>();
        let mut w = Window::default();
        let quarter = WINDOW_BYTES / 4;
        assert!(w.push(part(0, 1 << 20)).is_empty());
        for i in 1..4 {
            assert!(w.push(part(i, quarter)).is_empty(), "part {i}");
        }
        // Three quarters followed the first part: it stays; the fourth makes the window.
        assert_eq!(offsets(w.push(part(4, quarter))), [0]);
        // One part larger than the window pushes out all before it, and stays itself.
        assert_eq!(offsets(w.push(part(5, WINDOW_BYTES + 1))), [1, 2, 3, 4]);
        assert_eq!(offsets(w.push(part(6, 1))), [] as [u64; 0]);
        assert_eq!(offsets(w.drain()), [5, 6]);
        assert_eq!(w.bytes, 0);
        // Tiny parts: by count.
        for i in 0..WINDOW_PARTS as u64 {
            assert!(w.push(part(i, 1)).is_empty());
        }
        assert_eq!(offsets(w.push(part(999, 1))), [0]);
        assert_eq!(w.held.len(), WINDOW_PARTS);
    }

    /// How many of the file's pages are in the page cache.
    #[cfg(target_os = "linux")]
    fn resident_pages(file: &File, len: usize) -> usize {
        resident(file, len).into_iter().filter(|&r| r).count()
    }

    /// The pages of data on disk are dropped, those of a part-covered page kept: the
    /// point of the module, checked on the file system of the source tree.
    #[cfg(target_os = "linux")]
    #[test]
    fn clean_pages_are_dropped_and_part_covered_ones_kept() {
        let Some(dir) = disk_tempdir() else { return };
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
        give(&f, 3 * 4096 + 1, 7 * 4096, Hint::DropClean);
        assert_eq!(resident_pages(&f, len), 64 - 6);
        give(&f, 0, 0, Hint::DropClean);
        assert_eq!(resident_pages(&f, len), 0);
        assert_eq!(std::fs::read(&path).unwrap(), vec![3u8; len]);
    }

    /// A file handed over is dropped from the page cache once more than the window has
    /// followed it (or the releaser has gone idle), and every file stays whole. On the
    /// source tree's file system, as above.
    #[cfg(target_os = "linux")]
    #[test]
    fn released_files_leave_the_cache_and_keep_their_contents() {
        let Some(dir) = disk_tempdir() else { return };
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
        let every: Vec<usize> = (0..256).collect();
        assert_eq!(cached_after_release(&probe, &every, 0), 0);
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
