//! Written data handed back to the kernel once it is on its way to disk, so that the next
//! writes reuse its page-cache pages instead of taking fresh ones.
//!
//! Why: on a virtual machine whose host takes freed guest memory back (virtio-balloon free
//! page reporting, as on this project's 2-core machines), every page the page cache takes
//! from the free lists is a fresh host page, faulted in during the copy. Writing 400 MB
//! there cost 0.88 s of kernel time; written in rounds whose pages are dropped once on
//! disk, 0.11 s. A batch writes each run twice (its journal file and results.h5, about
//! 2 MB each for the throughput campaign's runs), and those copies were a fifth of the
//! batch's CPU time, the writer thread's included, which no number of cores shares.
//!
//! So the data a batch will not read again is started to disk without waiting
//! (`sync_file_range`) and its pages dropped a round later (`posix_fadvise(DONTNEED)`,
//! which leaves dirty, locked and partly covered pages alone). Correctness never depends
//! on it: a dropped page is read back from disk if it is ever needed. Linux only; elsewhere
//! these calls do nothing.

use std::cell::RefCell;
use std::collections::VecDeque;
use std::fs::File;

/// How many of a thread's whole files stay cached: the newest may still be under
/// writeback, which `DONTNEED` would skip.
const FILES_KEPT: usize = 2;

/// Bytes of a growing file written between two rounds of [`Extents`].
const ROUND_BYTES: u64 = 8 << 20;

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

thread_local! {
    /// The calling thread's files handed to [`release_file`], oldest first.
    static RECENT: RefCell<VecDeque<File>> = const { RefCell::new(VecDeque::new()) };
}

/// Hands a file just written in full (a journal's run file) over for release: its writing
/// to disk starts now, and its pages are dropped once this thread has written a few more.
pub fn release_file(file: File) {
    start_writeback(&file, 0, 0);
    RECENT.with(|recent| {
        let mut recent = recent.borrow_mut();
        recent.push_back(file);
        while recent.len() > FILES_KEPT {
            if let Some(old) = recent.pop_front() {
                drop_clean(&old, 0, 0);
            }
        }
    });
}

/// The extents of a growing file that will not be read or written again (results.h5's
/// chunks), released in rounds: each round starts the last one's extents to disk and
/// drops the pages of the round before, by then on disk.
pub struct Extents {
    file: File,
    started: Vec<(u64, u64)>,
    pending: Vec<(u64, u64)>,
    pending_bytes: u64,
}

impl Extents {
    /// Follows the file at `path` (opened for reading: the calls need no more), or `None`
    /// where it cannot be opened.
    pub fn open(path: &std::path::Path) -> Option<Extents> {
        let file = File::open(path).ok()?;
        Some(Extents {
            file,
            started: Vec::new(),
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
            self.round();
        }
    }

    fn round(&mut self) {
        for &(o, l) in &self.started {
            drop_clean(&self.file, o, l);
        }
        for &(o, l) in &self.pending {
            start_writeback(&self.file, o, l);
        }
        self.started = std::mem::take(&mut self.pending);
        self.pending_bytes = 0;
    }

    /// Extents noted and not yet dropped, as (offset, length).
    pub fn held(&self) -> impl Iterator<Item = &(u64, u64)> {
        self.started.iter().chain(&self.pending)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    /// Extents that follow one another merge; a gap (metadata between two chunks) starts
    /// a new one; a round hands the pending extents to `started` and drops the older ones.
    #[test]
    fn extents_merge_when_adjacent_and_rotate_by_rounds() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        std::fs::write(&path, vec![7u8; 1 << 16]).unwrap();
        let mut e = Extents::open(&path).unwrap();
        e.wrote(0, 100);
        e.wrote(100, 50);
        e.wrote(4096, 10);
        e.wrote(5000, 0);
        assert_eq!(e.pending, vec![(0, 150), (4096, 10)]);
        assert!(e.started.is_empty());
        e.wrote(8192, ROUND_BYTES);
        assert!(e.pending.is_empty());
        assert_eq!(e.started, vec![(0, 150), (4096, 10), (8192, ROUND_BYTES)]);
        e.wrote(1 << 30, ROUND_BYTES);
        assert_eq!(e.started, vec![(1 << 30, ROUND_BYTES)]);
        assert_eq!(e.held().count(), 1);
        // The data are untouched by all of it.
        assert_eq!(std::fs::read(&path).unwrap(), vec![7u8; 1 << 16]);
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
    /// point of the module, checked on the file system of the build folder (tmpfs, which
    /// may hold /tmp, has no disk to drop pages to).
    #[cfg(target_os = "linux")]
    #[test]
    fn clean_pages_are_dropped_and_part_covered_ones_kept() {
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

    /// Files handed over stay readable and whole; only the newest few stay open.
    #[test]
    fn released_files_keep_their_contents() {
        let dir = tempfile::tempdir().unwrap();
        for i in 0..5u8 {
            let path = dir.path().join(format!("{i}"));
            let mut f = File::create(&path).unwrap();
            f.write_all(&vec![i; 10_000]).unwrap();
            release_file(f);
        }
        RECENT.with(|r| assert_eq!(r.borrow().len(), FILES_KEPT));
        for i in 0..5u8 {
            assert_eq!(
                std::fs::read(dir.path().join(format!("{i}"))).unwrap(),
                vec![i; 10_000]
            );
        }
    }
}
