//! `results.h5` laid out byte by byte, without libhdf5: the batch's one writer puts each
//! encoded run's dataset headers and strings into the file as it arrives, and the groups
//! above the runs when the batch ends; the run's data (its chunks) the worker that encoded
//! it has put there already, at a place reserved for it at the file's end ([`Placer`]), or
//! else the writer writes them too (runs copied from the journal by `skelid merge`).
//! In: encoded runs; out: the file, which any HDF5 reader (libhdf5 1.8 and later) reads as
//! it reads [`super::ResultsWriter`]'s.
//!
//! Why: libhdf5 makes the 6 groups, 51 datasets and 172 attributes of a run one call at a
//! time under its one lock, 2.2–2.9 ms a run, and that serial writer was most of what kept
//! `--jobs 2` from 1.8× `--jobs 1` on two cores (README, throughput). Here a run is a few
//! buffered writes: its chunks, one heap of its strings, its headers.
//!
//! Datasets are version 1 headers with the messages libhdf5 writes; a run's groups are
//! version 2 headers holding their links (HDF5 1.8's "compact" groups); the groups above
//! the runs, written at the end, get a symbol table as libhdf5 writes one where they hold
//! more than [`COMPACT_MAX`] links ([`super::hdf5_format`]). A run's group is written once
//! its run is: the groups above it stay in memory (a name and an address per run) until
//! [`DirectWriter::finish`] writes them, so that runs can still be moved into the
//! report's order. A group written earlier that must change (a run whose path lies inside
//! another run's group) is read back and written again.

use std::collections::BTreeMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use super::encoded::{self, EncodedRun, Item, Scalar};
use super::hdf5_format::{self as h5, AttrValue, HeapId, Message};
use super::ReportError;

/// Metadata bytes gathered before they are written (chunks go straight to the file).
const META_FLUSH: usize = 1 << 20;

/// Links a group written at the end may hold in its header (libhdf5's own limit for a
/// compact group); one with more gets a symbol table, whose lookups by name take
/// logarithmic time: h5py read a 20 000-run `/runs` written compact 6 times slower by
/// name and 30 times slower with `visititems` than libhdf5's.
const COMPACT_MAX: usize = 8;

/// Bytes of a name (a link's, an attribute's): HDF5's messages give them 16 bits.
const NAME_MAX: usize = 0xff00;

/// A results file being written without libhdf5 (see the module's comment): written as
/// `<path>.tmp` and renamed into place by [`finish`](Self::finish).
pub struct DirectWriter {
    path: PathBuf,
    tmp: PathBuf,
    inner: std::sync::Mutex<Inner>,
}

struct Inner {
    io: Io,
    root: Group,
    /// Why the writer stopped: after any failed call the file is not finished, only
    /// abandoned (what was written may be half a run, and the file's end uncertain).
    failed: Option<String>,
}

/// The file being written: everything is put at its end, reserved from [`Space`] (which
/// the batch's workers reserve from too, see [`Placer`]), metadata through a buffer.
struct Io {
    file: Arc<File>,
    /// Metadata not yet written, which belongs at `meta_at`.
    meta: Vec<u8>,
    meta_at: u64,
    space: Arc<Space>,
    /// The chunks written so far, released from the page cache in rounds.
    extents: Option<crate::pagecache::Extents>,
}

/// The file's end: every byte below it is reserved, by the writer or by a [`Placer`].
struct Space {
    end: AtomicU64,
}

impl Space {
    /// Reserves `len` bytes at the end; their address.
    fn reserve(&self, len: u64) -> u64 {
        self.end.fetch_add(len, Ordering::Relaxed)
    }
}

/// What a batch's workers use to put a run's data (its chunks and contiguous datasets)
/// into the file themselves, in parallel, each at a place reserved for it, so that the one
/// writer thread lays out only the run's headers ([`DirectWriter::write_placed_as`]). The
/// data were most of that thread's time: the kernel's copy into the page cache and ext4's
/// reservations, 62 % of the writer's CPU by `perf` on 200 runs (README, *Throughput*).
#[derive(Clone)]
pub struct Placer {
    file: Arc<File>,
    space: Arc<Space>,
    /// The file opened again for the page-cache releaser, when it releases.
    release: Option<Arc<File>>,
}

/// A run's data as a [`Placer`] put it in the file: each dataset's chunks as (address,
/// length), in the run's order (a contiguous dataset: one; an empty one: none).
pub struct PlacedData {
    space: Arc<Space>,
    addrs: Vec<Vec<(u64, u64)>>,
    /// Which run they are: its path and the address of its items (a run moved keeps it;
    /// a run freed may hand it to the next, whose path then tells them apart), so that
    /// data placed from one run are never taken for another's of the same shape.
    run: (String, usize),
}

impl Placer {
    /// Writes `run`'s data at a place reserved for it in one system call (or a few);
    /// `Ok(None)` when there is nothing to place. Whatever is not placed (`None`, or an
    /// error, which the batch logs) the writer writes itself, as for a run from the
    /// journal, and reports what fails then.
    pub fn place(&self, run: &EncodedRun) -> std::io::Result<Option<PlacedData>> {
        let mut parts: Vec<&[u8]> = Vec::new();
        let mut addrs = Vec::new();
        let mut len = 0u64;
        for d in datasets(run) {
            let mut at = Vec::new();
            for b in data_parts(d) {
                at.push((len, b.len() as u64));
                len += b.len() as u64;
                parts.push(b);
            }
            addrs.push(at);
        }
        if len == 0 {
            return Ok(None);
        }
        let base = self.space.reserve(len);
        // A failed write leaves its reserved range unused: the file is longer, never wrong.
        write_parts_at(&self.file, &parts, base)?;
        if let Some(f) = &self.release {
            crate::pagecache::release_extent(f, base, len);
        }
        for (a, _) in addrs.iter_mut().flatten() {
            *a += base;
        }
        Ok(Some(PlacedData {
            space: self.space.clone(),
            addrs,
            run: (run.path.clone(), run.items.as_ptr() as usize),
        }))
    }
}

impl PlacedData {
    /// Whether these are `run`'s data, placed in the file whose end is `space`: the very
    /// run they were placed from (its path and the address of its items) and every
    /// dataset's every part as long as the run's. Else the writer writes the data itself.
    fn fits(&self, space: &Arc<Space>, run: &EncodedRun) -> bool {
        Arc::ptr_eq(&self.space, space)
            && self.run.0 == run.path
            && self.run.1 == run.items.as_ptr() as usize
            && datasets(run).count() == self.addrs.len()
            && datasets(run).zip(&self.addrs).all(|(d, at)| {
                data_parts(d)
                    .map(|b| b.len() as u64)
                    .eq(at.iter().map(|&(_, len)| len))
            })
    }
}

/// The datasets of `run`, in its order.
fn datasets(run: &EncodedRun) -> impl Iterator<Item = &encoded::Dataset> {
    run.items.iter().filter_map(|i| match i {
        Item::Dataset(d) => Some(d),
        _ => None,
    })
}

/// A dataset's data as the file holds them, in order: its chunks, or its contiguous bytes
/// (none for an empty dataset).
fn data_parts(d: &encoded::Dataset) -> impl Iterator<Item = &[u8]> {
    let (plain, chunks): (&[u8], &[serde_bytes::ByteBuf]) = match &d.storage {
        encoded::Storage::Plain(v) => (bytemuck::cast_slice(v), &[]),
        encoded::Storage::Chunked { chunks, .. } => (&[], chunks),
    };
    (!plain.is_empty())
        .then_some(plain)
        .into_iter()
        .chain(chunks.iter().map(|c| c.as_slice()))
}

/// Writes `parts` one after another at `offset`: one `pwritev` for up to 1024 of them, and
/// again for what a short write leaves.
fn write_parts_at(file: &File, parts: &[&[u8]], offset: u64) -> std::io::Result<()> {
    use std::io::IoSlice;
    use std::os::fd::AsRawFd;
    let mut slices: Vec<IoSlice<'_>> = parts
        .iter()
        .filter(|p| !p.is_empty())
        .map(|p| IoSlice::new(p))
        .collect();
    let mut left = &mut slices[..];
    let mut at = offset;
    while !left.is_empty() {
        let n = left.len().min(1024) as libc::c_int;
        let off = libc::off_t::try_from(at)
            .map_err(|_| std::io::Error::other(format!("offset {at} beyond the system's")))?;
        // SAFETY: `IoSlice` is ABI-compatible with `iovec` (std guarantees it on unix), and
        // the `n` slices it points to live until the call returns.
        let wrote = unsafe { libc::pwritev(file.as_raw_fd(), left.as_ptr().cast(), n, off) };
        match wrote {
            0 => return Err(std::io::ErrorKind::WriteZero.into()),
            n if n < 0 => {
                let e = std::io::Error::last_os_error();
                if e.kind() != std::io::ErrorKind::Interrupted {
                    return Err(e);
                }
            }
            n => {
                at += n as u64;
                IoSlice::advance_slices(&mut left, n as usize);
            }
        }
    }
    Ok(())
}

/// A group not yet written: its attribute messages and its links by name.
#[derive(Default)]
struct Group {
    attrs: Vec<Message>,
    links: BTreeMap<String, Node>,
}

/// What a link points to.
enum Node {
    /// A group still in memory.
    Open(Group),
    /// An object header written at `addr`; `group` when it is a group's.
    Written { addr: u64, group: bool },
}

impl DirectWriter {
    /// Starts `<dir>/results.h5`.
    pub fn create(dir: &Path) -> Result<DirectWriter, ReportError> {
        Self::create_at(&dir.join("results.h5"))
    }

    /// Starts a results file at `path` (written as `path.tmp` until [`finish`](Self::finish)).
    pub fn create_at(path: &Path) -> Result<DirectWriter, ReportError> {
        let err = |detail: String| ReportError {
            file: path.display().to_string(),
            detail,
        };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| err(e.to_string()))?;
        }
        let tmp = crate::campaign::tmp_path(path);
        // Read too: a group written earlier may be read back ([`Io::unseal`]).
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(&tmp)
            .map_err(|e| err(e.to_string()))?;
        let extents = crate::pagecache::Extents::open(&tmp);
        // The superblock is written last, when the root's address and the end are known.
        let io = Io {
            file: Arc::new(file),
            meta: vec![0; h5::SUPERBLOCK_LEN],
            meta_at: 0,
            space: Arc::new(Space {
                end: AtomicU64::new(h5::SUPERBLOCK_LEN as u64),
            }),
            extents,
        };
        let w = DirectWriter {
            path: path.to_path_buf(),
            tmp,
            inner: std::sync::Mutex::new(Inner {
                io,
                root: Group::default(),
                failed: None,
            }),
        };
        w.set_root_attr("format", "skelid-results/1")?;
        w.set_root_attr("skelid_version", env!("CARGO_PKG_VERSION"))?;
        Ok(w)
    }

    fn err(&self, detail: String) -> ReportError {
        ReportError {
            file: self.path.display().to_string(),
            detail,
        }
    }

    fn inner(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Runs `f` on the file unless an earlier call failed; a failure stops the writer.
    fn apply(
        &self,
        what: &str,
        f: impl FnOnce(&mut Io, &mut Group) -> Result<(), String>,
    ) -> Result<(), ReportError> {
        let mut inner = self.inner();
        let Inner { io, root, failed } = &mut *inner;
        if let Some(why) = failed {
            return Err(self.err(format!(
                "{what}: the file was left unfinished by an earlier error ({why})"
            )));
        }
        f(io, root).map_err(|e| {
            let e = format!("{what}: {e}");
            *failed = Some(e.clone());
            self.err(e)
        })
    }

    /// Sets (or replaces) a string attribute on the file's root.
    pub fn set_root_attr(&self, name: &str, value: &str) -> Result<(), ReportError> {
        self.apply(&format!("attribute {name}"), |io, root| {
            check_name(name)?;
            let id = io.strings(&[value])?.pop().expect("one string");
            root.attrs.retain(|m| m.attribute_name() != Some(name));
            root.attrs.push(h5::attribute(name, AttrValue::Text(id)));
            Ok(())
        })
    }

    /// Stores a batch's settings on the file's root: `settings` (the fingerprint) and
    /// `settings_json` (everything, [`crate::journal::settings_record`]).
    pub fn write_settings(&self, record: &serde_json::Value) -> Result<(), ReportError> {
        if let Some(f) = record.get("fingerprint").and_then(|f| f.as_str()) {
            self.set_root_attr("settings", f)?;
        }
        self.set_root_attr("settings_json", &record.to_string())
    }

    /// Adds one encoded run under the group path `dst` (its own path, or another).
    pub fn write_encoded_as(&self, run: &EncodedRun, dst: &str) -> Result<(), ReportError> {
        self.write_placed_as(run, None, dst)
    }

    /// [`write_encoded_as`](Self::write_encoded_as) for a run whose data a worker has put
    /// in this file already ([`Placer::place`]): only its headers and strings are written.
    /// Data placed in another file, or from another run, are written again here.
    pub fn write_placed_as(
        &self,
        run: &EncodedRun,
        placed: Option<&PlacedData>,
        dst: &str,
    ) -> Result<(), ReportError> {
        self.apply(&format!("run {}", run.path), |io, root| {
            let placed = placed.filter(|p| p.fits(&io.space, run));
            write_run(io, root, run, placed, dst)
        })
    }

    /// A handle for the batch's workers to put runs' data into this file themselves.
    pub fn placer(&self) -> Placer {
        let inner = self.inner();
        Placer {
            file: inner.io.file.clone(),
            space: inner.io.space.clone(),
            release: crate::pagecache::releasing()
                .then(|| File::open(&self.tmp).ok().map(Arc::new))
                .flatten(),
        }
    }

    /// Adds one encoded run under its own path.
    pub fn write_encoded(&self, run: &EncodedRun) -> Result<(), ReportError> {
        self.write_encoded_as(run, &run.path)
    }

    /// Moves the object at group path `from` to `to` (no data is copied), creating `to`'s
    /// parent groups.
    pub fn move_run(&self, from: &str, to: &str) -> Result<(), ReportError> {
        self.apply(&format!("moving {from} to {to}"), |io, root| {
            let (src_parent, src) = split(from)?;
            let (dst_parent, dst) = split(to)?;
            let n = src_parent.len();
            if dst_parent.len() > n && dst_parent[..n] == src_parent[..] && dst_parent[n] == src {
                return Err(format!("{to} lies inside {from}"));
            }
            // The destination is checked before the source is taken, so that a refused
            // move loses nothing.
            if open(io, root, &dst_parent, true)?.links.contains_key(dst) {
                return Err(format!("{to} exists already"));
            }
            let node = open(io, root, &src_parent, false)?
                .links
                .remove(src)
                .ok_or_else(|| format!("{from} does not exist"))?;
            open(io, root, &dst_parent, true)?
                .links
                .insert(dst.to_string(), node);
            Ok(())
        })
    }

    /// Removes the object at `path` (a group and everything under it).
    pub fn remove(&self, path: &str) -> Result<(), ReportError> {
        self.apply(&format!("removing {path}"), |io, root| {
            let (parent, name) = split(path)?;
            open(io, root, &parent, false)?
                .links
                .remove(name)
                .map(|_| ())
                .ok_or_else(|| format!("{path} does not exist"))
        })
    }

    /// Writes the groups still in memory and the superblock, closes the file and renames
    /// it into place (as [`super::ResultsWriter::finish`] does).
    pub fn finish(self) -> Result<PathBuf, ReportError> {
        let DirectWriter { path, tmp, inner } = self;
        let Inner {
            mut io,
            root,
            failed,
        } = inner.into_inner().unwrap_or_else(|p| p.into_inner());
        let closed = (|| -> std::io::Result<()> {
            if let Some(why) = failed {
                return Err(std::io::Error::other(format!(
                    "not finished after an earlier error: {why}"
                )));
            }
            let root = io.seal(root, true)?;
            io.flush()?;
            // Every reservation was written, but a worker's that failed: the end of
            // the file is where the last one ends.
            let end = io.space.end.load(Ordering::Acquire);
            if io.file.metadata()?.len() < end {
                io.file.set_len(end)?;
            }
            io.file.write_all_at(&h5::superblock(root, end), 0)?;
            Ok(())
        })();
        let Io { file, extents, .. } = io;
        drop(file);
        drop(extents);
        if let Err(e) = closed {
            let _ = std::fs::remove_file(&tmp);
            return Err(ReportError {
                file: path.display().to_string(),
                detail: e.to_string(),
            });
        }
        super::results::put_in_place(&tmp, &path)
    }

    /// Closes and deletes the unfinished file.
    pub fn abandon(self) {
        let DirectWriter { tmp, inner, .. } = self;
        drop(inner);
        let _ = std::fs::remove_file(&tmp);
    }
}

/// A path's parent components and last name (`.` components skipped, as libhdf5 reads
/// them); an error for the root and for names no header can hold.
fn split(path: &str) -> Result<(Vec<&str>, &str), String> {
    let mut parts = rel_parts(path);
    for p in &parts {
        check_name(p)?;
    }
    let name = parts
        .pop()
        .ok_or_else(|| "a run path must name a group below the root".to_string())?;
    Ok((parts, name))
}

/// An error for a name HDF5 cannot store: one holding a NUL byte, or too long.
fn check_name(name: &str) -> Result<(), String> {
    if name.contains('\0') {
        return Err(format!("the name {name:?} holds a NUL byte"));
    }
    if name.len() > NAME_MAX {
        return Err(format!(
            "a name of {} bytes (at most {NAME_MAX})",
            name.len()
        ));
    }
    Ok(())
}

/// The group at `parts` below `g`, read back into memory where it was written; created
/// (with its parents) where absent when `create`, an error otherwise.
fn open<'g>(
    io: &mut Io,
    mut g: &'g mut Group,
    parts: &[&str],
    create: bool,
) -> Result<&'g mut Group, String> {
    for part in parts {
        // Looked up by `&str`: a name is allocated only for a group created here.
        if !g.links.contains_key(*part) {
            if !create {
                return Err(format!("no group {part}"));
            }
            g.links
                .insert(part.to_string(), Node::Open(Group::default()));
        }
        let node = g.links.get_mut(*part).expect("inserted above");
        if let Node::Written { addr, group } = *node {
            if !group {
                return Err(format!("{part} is a dataset, not a group"));
            }
            *node = Node::Open(io.unseal(addr).map_err(|e| e.to_string())?);
        }
        g = match node {
            Node::Open(g) => g,
            Node::Written { .. } => unreachable!("opened above"),
        };
    }
    Ok(g)
}

/// Writes one encoded run into `root`'s tree at `dst` (see [`DirectWriter::write_encoded_as`]),
/// its data where `placed` (which fits it) says a worker put them.
fn write_run(
    io: &mut Io,
    root: &mut Group,
    run: &EncodedRun,
    placed: Option<&PlacedData>,
    dst: &str,
) -> Result<(), String> {
    // The placed addresses of each dataset in turn (they fit the run: see the caller).
    let mut placed = placed.map(|p| p.addrs.iter());
    // Every string of the run in one heap collection (or a few), written first: the
    // attributes name their strings by address.
    let texts: Vec<&str> = run
        .items
        .iter()
        .filter_map(|i| match i {
            Item::Attr {
                value: Scalar::Str(s),
                ..
            } => Some(s.as_str()),
            Item::DatasetAttr { value, .. } => Some(value.as_str()),
            _ => None,
        })
        .collect();
    let mut ids = io.strings(&texts)?.into_iter();
    let (parts, name) = split(dst)?;
    let parent = open(io, root, &parts, true)?;
    let fresh = !parent.links.contains_key(name);
    let g = open(io, parent, &[name], true)?;
    // The datasets' headers wait for their attributes (a dataset's units follow it).
    let mut datasets: Vec<(String, String, Vec<Message>)> = Vec::new();
    for item in &run.items {
        match item {
            Item::Group(rel) => {
                let (parts, last) = split(rel)?;
                let at = open(io, g, &parts, true)?;
                if at.links.contains_key(last) {
                    return Err(format!("group {rel} exists already"));
                }
                at.links
                    .insert(last.to_string(), Node::Open(Group::default()));
            }
            Item::Attr { group, name, value } => {
                check_name(name)?;
                let at = open(io, g, &rel_parts(group), true)?;
                if at.attrs.iter().any(|m| m.attribute_name() == Some(name)) {
                    return Err(format!("attribute {name} of {group:?} set twice"));
                }
                let v = match value {
                    Scalar::F64(x) => AttrValue::F64(*x),
                    Scalar::Str(_) => AttrValue::Text(ids.next().expect("counted")),
                };
                at.attrs.push(h5::attribute(name, v));
            }
            Item::Dataset(d) => {
                check_name(&d.name)?;
                let at = placed.as_mut().and_then(|p| p.next()).map(Vec::as_slice);
                let messages = io.dataset(d, at).map_err(|e| e.to_string())?;
                datasets.push((d.group.clone(), d.name.clone(), messages));
            }
            Item::DatasetAttr {
                group,
                dataset,
                name,
                ..
            } => {
                check_name(name)?;
                let id = ids.next().expect("counted");
                let (.., m) = datasets
                    .iter_mut()
                    .rev()
                    .find(|(g, n, _)| g == group && n == dataset)
                    .ok_or_else(|| format!("no dataset {dataset} in {group:?} for {name}"))?;
                if m.iter().any(|m| m.attribute_name() == Some(name)) {
                    return Err(format!("attribute {name} of {dataset} set twice"));
                }
                m.push(h5::attribute(name, AttrValue::Text(id)));
            }
        }
    }
    for (group, name, messages) in datasets {
        let addr = io
            .put_meta(&h5::header_v1(&messages))
            .map_err(|e| e.to_string())?;
        let at = open(io, g, &rel_parts(&group), true)?;
        if at.links.contains_key(&name) {
            return Err(format!("{name} exists already in {group:?}"));
        }
        at.links.insert(name, Node::Written { addr, group: false });
    }
    // A run's group is final once written, unless it already held something.
    if fresh {
        let parent = open(io, root, &parts, false)?;
        let node = match parent.links.remove(name) {
            Some(Node::Open(g)) => Node::Written {
                addr: io.seal(g, false).map_err(|e| e.to_string())?,
                group: true,
            },
            Some(written) => written,
            None => unreachable!("the run's group was created above"),
        };
        parent.links.insert(name.to_string(), node);
    }
    Ok(())
}

/// The components of a path relative to a run's group ("" for the group itself).
fn rel_parts(rel: &str) -> Vec<&str> {
    rel.split('/').filter(|p| !p.is_empty()).collect()
}

impl Io {
    /// Where the buffered metadata ends.
    fn meta_end(&self) -> u64 {
        self.meta_at + self.meta.len() as u64
    }

    /// Appends metadata at the file's end; its address.
    fn put_meta(&mut self, bytes: &[u8]) -> std::io::Result<u64> {
        let at = self.space.reserve(bytes.len() as u64);
        self.put_meta_at(at, bytes)?;
        Ok(at)
    }

    /// Buffers metadata reserved at `at`: after what is buffered when a worker reserved
    /// nothing in between, else in a buffer of its own (the old one written first).
    fn put_meta_at(&mut self, at: u64, bytes: &[u8]) -> std::io::Result<()> {
        if at != self.meta_end() {
            self.flush()?;
            self.meta_at = at;
        }
        self.meta.extend_from_slice(bytes);
        if self.meta.len() >= META_FLUSH {
            self.flush()?;
        }
        Ok(())
    }

    /// Appends metadata whose bytes depend on their own address (a chunk index's nodes, a
    /// symbol table), made by `build` for the file's end as it stands, and made again
    /// should a worker reserve space meanwhile; what `build` returns beside the bytes.
    fn put_meta_built<T>(&mut self, build: impl Fn(u64) -> (Vec<u8>, T)) -> std::io::Result<T> {
        loop {
            let at = self.space.end.load(Ordering::Acquire);
            let (bytes, made) = build(at);
            let end = at + bytes.len() as u64;
            if self
                .space
                .end
                .compare_exchange(at, end, Ordering::AcqRel, Ordering::Acquire)
                .is_ok()
            {
                self.put_meta_at(at, &bytes)?;
                return Ok(made);
            }
        }
    }

    /// Appends raw data (a chunk, a contiguous dataset) at the file's end: written at once,
    /// with the buffered metadata before it when they adjoin, in one call and without
    /// copying it; its address.
    fn put_data(&mut self, bytes: &[u8]) -> std::io::Result<u64> {
        let len = bytes.len() as u64;
        let at = self.space.reserve(len);
        if at == self.meta_end() {
            write_parts_at(&self.file, &[&self.meta, bytes], self.meta_at)?;
        } else {
            self.flush()?;
            self.file.write_all_at(bytes, at)?;
        }
        self.meta.clear();
        self.meta_at = at + len;
        if let Some(e) = self.extents.as_mut() {
            e.wrote(at, len);
        }
        Ok(at)
    }

    /// Writes the buffered metadata.
    fn flush(&mut self) -> std::io::Result<()> {
        if !self.meta.is_empty() {
            self.file.write_all_at(&self.meta, self.meta_at)?;
            self.meta_at = self.meta_end();
            self.meta.clear();
        }
        Ok(())
    }

    /// Writes `texts` into global heap collections; their heap IDs, in order.
    fn strings(&mut self, texts: &[&str]) -> Result<Vec<HeapId>, String> {
        let mut ids = Vec::with_capacity(texts.len());
        for part in texts.chunks(h5::HEAP_OBJECTS) {
            if let Some(t) = part.iter().find(|t| t.contains('\0')) {
                return Err(format!("a string attribute holds a NUL byte: {t:?}"));
            }
            let objects: Vec<&[u8]> = part.iter().map(|t| t.as_bytes()).collect();
            let collection = self
                .put_meta(&h5::heap_collection(&objects))
                .map_err(|e| e.to_string())?;
            ids.extend(part.iter().enumerate().map(|(i, t)| HeapId {
                collection,
                index: i as u32 + 1,
                len: t.len() as u32,
            }));
        }
        Ok(ids)
    }

    /// Writes a dataset's data (unless `placed` gives where a worker put them: an address
    /// and length a chunk, or one for contiguous bytes, checked by [`PlacedData::fits`])
    /// and its chunk index; the messages of its header.
    fn dataset(
        &mut self,
        d: &encoded::Dataset,
        placed: Option<&[(u64, u64)]>,
    ) -> std::io::Result<Vec<Message>> {
        let elem = d.elem;
        let storage = match &d.storage {
            // An empty dataset is made chunked by the hdf5 crate (libhdf5 has no
            // contiguous storage of no bytes): chunks of one element, none written.
            encoded::Storage::Plain(v) if v.is_empty() => h5::Storage::Chunked {
                btree: h5::UNDEF,
                chunk: 1,
                shuffle: false,
                level: None,
            },
            // The datatype says little-endian: the floats' bytes as they are in memory (as
            // `encoded` compresses them).
            encoded::Storage::Plain(v) => {
                let bytes: &[u8] = bytemuck::cast_slice(v);
                let addr = match placed {
                    Some(&[(at, _)]) => at,
                    _ => self.put_data(bytes)?,
                };
                h5::Storage::Contiguous {
                    addr,
                    len: bytes.len() as u64,
                }
            }
            encoded::Storage::Chunked { level, chunks } => {
                let step = encoded::chunk_len(d.len) as u64;
                let mut index = Vec::with_capacity(chunks.len());
                for (i, c) in chunks.iter().enumerate() {
                    let len = u32::try_from(c.len()).map_err(|_| {
                        std::io::Error::other(format!("chunk {i} of {} over 4 GB", d.name))
                    })?;
                    let addr = match placed {
                        Some(p) => p[i].0,
                        None => self.put_data(c)?,
                    };
                    index.push(h5::Chunk {
                        addr,
                        len,
                        offset: i as u64 * step,
                    });
                }
                let btree = if index.is_empty() {
                    h5::UNDEF
                } else {
                    self.put_meta_built(|at| h5::chunk_btree(&index, step, elem.size() as u64, at))?
                };
                h5::Storage::Chunked {
                    btree,
                    chunk: step as u32,
                    shuffle: elem != encoded::Elem::U8,
                    level: Some(*level),
                }
            }
        };
        Ok(h5::dataset(elem, d.len as u64, &storage))
    }

    /// Writes group `g` and the groups below it still in memory; its header's address.
    /// A run's groups (`at_end` false) keep their links in their header, so that a later
    /// run can still be put inside one ([`Io::unseal`]); at the batch's end a group of
    /// more than [`COMPACT_MAX`] links gets a symbol table.
    fn seal(&mut self, g: Group, at_end: bool) -> std::io::Result<u64> {
        let mut links = Vec::with_capacity(g.links.len());
        // In name order, as a symbol table needs (a BTreeMap orders as strcmp does).
        for (name, node) in g.links {
            let addr = match node {
                Node::Open(child) => self.seal(child, at_end)?,
                Node::Written { addr, .. } => addr,
            };
            links.push((name, addr));
        }
        if at_end && links.len() > COMPACT_MAX {
            let links: Vec<(&str, u64)> = links.iter().map(|(n, a)| (n.as_str(), *a)).collect();
            return self.put_meta_built(|at| h5::symbol_table_group(&links, &g.attrs, at));
        }
        let mut messages = h5::group_opening();
        messages.extend(links.iter().map(|(name, addr)| h5::link(name, *addr)));
        messages.extend(g.attrs);
        self.put_meta(&h5::header_v2(&messages))
    }

    /// The group whose header was written at `addr`, back in memory.
    fn unseal(&mut self, addr: u64) -> std::io::Result<Group> {
        self.flush()?;
        let bad = || std::io::Error::other(format!("no group header at {addr}"));
        let mut prefix = [0u8; 10];
        self.file.read_exact_at(&mut prefix, addr)?;
        let mut bytes = vec![0; h5::v2_len(&prefix).ok_or_else(bad)?];
        self.file.read_exact_at(&mut bytes, addr)?;
        let mut g = Group::default();
        for m in h5::parse_v2(&bytes).ok_or_else(bad)? {
            if let Some((name, target)) = m.as_link() {
                let mut sig = [0u8; 4];
                self.file.read_exact_at(&mut sig, target)?;
                g.links.insert(
                    name,
                    Node::Written {
                        addr: target,
                        group: &sig == b"OHDR",
                    },
                );
            } else if m.attribute_name().is_some() {
                g.attrs.push(m);
            } else if !m.opens_group() {
                return Err(bad());
            }
        }
        Ok(g)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::h5util::all_attrs;
    use crate::report::{ResultsFile, ResultsWriter};

    /// A run with what results.h5 holds: groups two deep, number and text attributes (an
    /// empty and a non-ASCII one among them), compressed signals of one and of several
    /// chunks, a short contiguous one and an empty one, a mask, units on datasets.
    fn run(path: &str, seed: f64) -> EncodedRun {
        let mut e = EncodedRun::new(path);
        e.str_attr("", "status", "ok");
        e.str_attr("", "error", "");
        e.f64_attr("", "sample_rate", 1000.0 + seed);
        e.f64_attr("", "nan", f64::NAN);
        e.group("wavelet");
        e.group("wavelet/skeleton");
        e.str_attr("wavelet", "note", "amplitude in µm, ±5 %");
        let v: Vec<f64> = (0..70_000)
            .map(|i| (i as f64 * 1e-3 + seed).sin())
            .collect();
        e.signal("wavelet", "amplitude", &v, true);
        e.dataset_attr("wavelet", "amplitude", "units", "m");
        e.signal("wavelet", "short", &v[..40], true);
        e.dataset_attr("wavelet", "short", "units", "Hz");
        e.signal("wavelet/skeleton", "empty", &[], false);
        e.signal("", "plain", &v[..1000], false);
        e.bytes("wavelet", "valid", &vec![seed as u8 % 2; 30_000], 4);
        e.f64_attr("wavelet/skeleton", "bins", 40.0);
        e
    }

    /// `runs` (each at its path) then each of `moves`, written once by each writer (the
    /// batch's [`crate::report::ResultsFile`] dispatches the same calls): the two files.
    fn both(dir: &Path, runs: &[EncodedRun], moves: &[(&str, &str)]) -> (PathBuf, PathBuf) {
        let (a, b) = (dir.join("direct.h5"), dir.join("libhdf5.h5"));
        for w in [
            ResultsFile::Direct(DirectWriter::create_at(&a).unwrap()),
            ResultsFile::Library(ResultsWriter::create_at(&b).unwrap()),
        ] {
            for r in runs {
                w.write_encoded_as(r, &r.path).unwrap();
            }
            for (from, to) in moves {
                w.move_run(from, to).unwrap();
            }
            w.finish().unwrap();
        }
        (a, b)
    }

    /// Everything a reader sees of `g`, libhdf5 reading: its members by name, and for each
    /// attribute and dataset its type, shape, chunking, filters and values, as text.
    fn seen(g: &hdf5::Group, at: &str, out: &mut Vec<String>) {
        let info = g.loc_info().unwrap();
        out.push(format!("{at}: {} attributes", info.num_attrs));
        for (name, value) in all_attrs(g) {
            out.push(format!("{at} @{name} = {value:?}"));
        }
        let mut names = g.member_names().unwrap();
        names.sort();
        for name in names {
            let path = format!("{at}/{name}");
            if let Ok(sub) = g.group(&name) {
                seen(&sub, &path, out);
                continue;
            }
            let d = g.dataset(&name).unwrap();
            let values = match d.dtype().unwrap().size() {
                1 => format!("{:?}", d.read_raw::<u8>().unwrap()),
                _ => format!("{:?}", d.read_raw::<f64>().unwrap()),
            };
            out.push(format!(
                "{path}: {:?} {:?} chunk {:?} filters {:?} {} attributes\n{values}",
                d.dtype().unwrap().to_descriptor().unwrap(),
                d.shape(),
                d.chunk(),
                d.filters(),
                d.loc_info().unwrap().num_attrs,
            ));
            for (name, value) in all_attrs(&d) {
                out.push(format!("{path} @{name} = {value:?}"));
            }
        }
    }

    fn read(file: &Path) -> Vec<String> {
        let f = hdf5::File::open(file).unwrap();
        let mut out = Vec::new();
        seen(&f.group("/").unwrap(), "", &mut out);
        out
    }

    fn assert_same(a: &Path, b: &Path) {
        let (x, y) = (read(a), read(b));
        assert_eq!(x.len(), y.len());
        for (p, q) in x.iter().zip(&y) {
            assert!(p == q, "direct: {:.300}\nlibhdf5: {:.300}", p, q);
        }
    }

    /// The reference is libhdf5's own writer: the same runs read back through libhdf5
    /// from the two files give the same groups, attributes, types, layouts and values.
    #[test]
    fn libhdf5_reads_the_same_file_from_both_writers() {
        let dir = tempfile::tempdir().unwrap();
        let runs: Vec<EncodedRun> = (0..12)
            .map(|i| run(&format!("/runs/run_{i:03}"), i as f64))
            .chain([run("/other/ünï", 20.0)])
            .collect();
        let (a, b) = both(dir.path(), &runs, &[]);
        assert_same(&a, &b);
        let seen = read(&a);
        assert!(seen
            .iter()
            .any(|s| s.contains("@format = Text(\"skelid-results/1\")")));
        assert!(seen.iter().any(|s| s.starts_with("/runs: 0 attributes")));
        assert!(seen
            .iter()
            .any(|s| s.starts_with("/runs/run_011: 4 attributes")));
    }

    /// Runs whose data workers put into the file themselves, from several threads at once
    /// while the writer lays out other runs (as a batch does), read back as libhdf5's own
    /// writer writes them; data placed for another file are written again by that file's
    /// writer, and a placement that does not fit the run is not used.
    #[test]
    fn runs_placed_by_workers_read_back_as_libhdf5_writes_them() {
        let dir = tempfile::tempdir().unwrap();
        let runs: Vec<EncodedRun> = (0..24)
            .map(|i| run(&format!("/runs/run_{i:03}"), i as f64))
            .collect();
        let (a, b) = (dir.path().join("direct.h5"), dir.path().join("libhdf5.h5"));
        let direct = DirectWriter::create_at(&a).unwrap();
        let other = DirectWriter::create_at(&dir.path().join("other.h5")).unwrap();
        let (placer, elsewhere) = (direct.placer(), other.placer());
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::scope(|scope| {
            for t in 0..3 {
                let (tx, placer, runs) = (tx.clone(), placer.clone(), &runs);
                scope.spawn(move || {
                    for (i, r) in runs.iter().enumerate().filter(|(i, _)| i % 4 == t) {
                        tx.send((i, placer.place(r).unwrap().expect("placed")))
                            .unwrap();
                    }
                });
            }
            drop(tx);
            // The fourth share is written whole by the writer, between the placed ones.
            let mut whole = runs.iter().skip(3).step_by(4);
            for (i, placed) in rx {
                direct
                    .write_placed_as(&runs[i], Some(&placed), &runs[i].path)
                    .unwrap();
                if let Some(r) = whole.next() {
                    direct.write_encoded_as(r, &r.path).unwrap();
                }
            }
            for r in whole {
                direct.write_encoded_as(r, &r.path).unwrap();
            }
        });
        // Placed in another file: written here again. Placed for another run (fewer
        // datasets): not used.
        let extra = run("/more/elsewhere", 30.0);
        let placed = elsewhere.place(&extra).unwrap().unwrap();
        direct
            .write_placed_as(&extra, Some(&placed), &extra.path)
            .unwrap();
        let mut small = EncodedRun::new("/more/small");
        small.signal("", "x", &[1.0, 2.0, 3.0], false);
        let misfit = placer.place(&small).unwrap().unwrap();
        let last = run("/more/misfit", 40.0);
        direct
            .write_placed_as(&last, Some(&misfit), &last.path)
            .unwrap();
        // Placed from another run of the same shape: not used.
        let twin = placer.place(&run("/more/twin", 50.0)).unwrap().unwrap();
        let unused: u64 = twin.addrs.iter().flatten().map(|&(_, len)| len).sum();
        let alike = run("/more/alike", 51.0);
        direct
            .write_placed_as(&alike, Some(&twin), &alike.path)
            .unwrap();
        direct.finish().unwrap();
        other.abandon();
        let library = ResultsWriter::create_at(&b).unwrap();
        for r in runs.iter().chain([&extra, &last, &alike]) {
            library.write_encoded_as(r, &r.path).unwrap();
        }
        library.finish().unwrap();
        assert_same(&a, &b);
        // Nothing written twice: as long as the file the writer writes whole, but for the
        // misfit's and the twin's placed bytes, which no header points to.
        let c = dir.path().join("whole.h5");
        let whole = DirectWriter::create_at(&c).unwrap();
        for r in runs.iter().chain([&extra, &last, &alike]) {
            whole.write_encoded_as(r, &r.path).unwrap();
        }
        whole.finish().unwrap();
        let size = |f: &Path| std::fs::metadata(f).unwrap().len();
        assert!(unused > 0);
        assert_eq!(size(&a), size(&c) + 24 + unused);
    }

    /// A placement whose write fails (here a descriptor opened for reading) is an error,
    /// not data: the run is then written whole by the writer and reads back as libhdf5's,
    /// the range the failed write reserved left unused.
    #[test]
    fn a_failed_placement_is_an_error_and_the_writer_writes_the_run() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("direct.h5"), dir.path().join("libhdf5.h5"));
        let direct = DirectWriter::create_at(&a).unwrap();
        let mut placer = direct.placer();
        placer.file = Arc::new(File::open(&direct.tmp).unwrap());
        let r = run("/runs/run_000", 1.0);
        let failed = placer.place(&r);
        assert!(failed.is_err(), "a read-only descriptor placed the run");
        direct.write_placed_as(&r, None, &r.path).unwrap();
        direct.finish().unwrap();
        let library = ResultsWriter::create_at(&b).unwrap();
        library.write_encoded_as(&r, &r.path).unwrap();
        library.finish().unwrap();
        assert_same(&a, &b);
    }

    /// Runs moved (into the report's order, through a staging group), and a run whose
    /// path lies inside another run's group, written before or after it: the groups
    /// written already are read back and extended.
    #[test]
    fn moved_and_nested_runs_land_where_libhdf5_puts_them() {
        let dir = tempfile::tempdir().unwrap();
        let runs = [
            run("/a", 1.0),
            run("/a/b", 2.0),
            run("/x/y/z", 3.0),
            run("/x/y", 4.0),
            run("/s/pending0", 5.0),
        ];
        let moves = [
            ("/a/b", "/stage/0"),
            ("/s/pending0", "/stage/1"),
            ("/stage/0", "/a/b@two.h5"),
            ("/stage/1", "/a/wavelet/deep"),
        ];
        let (a, b) = both(dir.path(), &runs, &moves);
        assert_same(&a, &b);
        let seen = read(&a);
        assert!(seen
            .iter()
            .any(|s| s.starts_with("/a/wavelet/deep/wavelet/amplitude:")));
    }

    /// A dataset of more chunks than one B-tree node indexes (64) gets a tree of two
    /// levels, and a group of hundreds of links (past what a version 1 header counts on
    /// compact groups) reads whole.
    #[test]
    fn many_chunks_and_many_links_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let mut big = EncodedRun::new("/big");
        let mask: Vec<u8> = (0..65 * encoded::CHUNK + 5)
            .map(|i| (i % 7) as u8)
            .collect();
        big.bytes("", "mask", &mask, 1);
        let file = dir.path().join("r.h5");
        let w = DirectWriter::create_at(&file).unwrap();
        w.write_encoded(&big).unwrap();
        for i in 0..600 {
            let mut e = EncodedRun::new(&format!("/runs/r{i}"));
            e.f64_attr("", "i", i as f64);
            w.write_encoded(&e).unwrap();
        }
        w.write_settings(&serde_json::json!({"fingerprint": "abc", "n": 1}))
            .unwrap();
        w.finish().unwrap();
        let f = hdf5::File::open(&file).unwrap();
        let d = f.dataset("big/mask").unwrap();
        assert_eq!(d.read_raw::<u8>().unwrap(), mask);
        let runs = f.group("runs").unwrap();
        assert_eq!(runs.member_names().unwrap().len(), 600);
        let r = runs.group("r599").unwrap();
        assert_eq!(
            all_attrs(&r),
            [("i".to_string(), crate::h5util::AttrValue::Number(599.0))]
        );
        let root = all_attrs(&f.group("/").unwrap());
        let names: Vec<&str> = root.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(
            names,
            ["format", "settings", "settings_json", "skelid_version"]
        );
    }

    /// A writer that stops leaves nothing behind, and errors name what went wrong.
    #[test]
    fn an_abandoned_file_is_deleted_and_bad_moves_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("results.h5");
        let w = DirectWriter::create_at(&file).unwrap();
        w.write_encoded(&run("/r", 0.0)).unwrap();
        let e = w.move_run("/nowhere", "/x").unwrap_err();
        assert!(e.detail.contains("/nowhere does not exist"), "{e}");
        w.abandon();
        let w = DirectWriter::create_at(&file).unwrap();
        w.write_encoded(&run("/r", 0.0)).unwrap();
        let e = w
            .write_encoded(&run("/r/wavelet/amplitude/x", 0.0))
            .unwrap_err();
        assert!(e.detail.contains("is a dataset"), "{e}");
        w.abandon();
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    /// What libhdf5 makes of the file when it changes it: attributes added to a group kept
    /// in the header, to a symbol-table group and to a dataset, a group created in each
    /// kind, a run deleted, then everything read back.
    #[test]
    fn libhdf5_can_change_the_file_in_place() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("results.h5");
        let w = DirectWriter::create_at(&file).unwrap();
        for i in 0..20 {
            w.write_encoded(&run(&format!("/runs/run_{i:03}"), i as f64))
                .unwrap();
        }
        w.finish().unwrap();
        {
            let f = hdf5::File::open_rw(&file).unwrap();
            crate::h5util::write_str_attr(&f, "note", "checked").unwrap();
            let r = f.group("runs/run_003").unwrap();
            for k in 0..12 {
                crate::h5util::write_f64_attr(&r, &format!("extra{k}"), k as f64).unwrap();
            }
            r.group("wavelet").unwrap().create_group("added").unwrap();
            f.group("runs").unwrap().create_group("zz_added").unwrap();
            let d = f.dataset("runs/run_003/wavelet/amplitude").unwrap();
            crate::h5util::write_str_attr(&d, "comment", "a note").unwrap();
            f.unlink("runs/run_007").unwrap();
        }
        let f = hdf5::File::open(&file).unwrap();
        let runs = f.group("runs").unwrap();
        let mut names = runs.member_names().unwrap();
        names.sort();
        assert_eq!(names.len(), 20);
        assert!(names.contains(&"zz_added".to_string()));
        assert!(!names.contains(&"run_007".to_string()));
        let r = runs.group("run_003").unwrap();
        assert_eq!(r.loc_info().unwrap().num_attrs, 4 + 12);
        assert!(r.group("wavelet/added").is_ok());
        let d = f.dataset("runs/run_003/wavelet/amplitude").unwrap();
        let v: Vec<f64> = d.read_raw().unwrap();
        assert_eq!(v[1234], (1234.0f64 * 1e-3 + 3.0).sin());
        let attrs = all_attrs(&d);
        assert_eq!(attrs.len(), 2, "{attrs:?}");
        assert!(all_attrs(&f.group("/").unwrap())
            .iter()
            .any(|(n, v)| n == "note" && v.to_string() == "checked"));
    }

    /// After a failed call the writer refuses the next ones and will not finish: what it
    /// wrote may be half a run (every caller abandons the file on an error anyway).
    #[test]
    fn a_failed_call_stops_the_writer() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("results.h5");
        let w = DirectWriter::create_at(&file).unwrap();
        w.write_encoded(&run("/a", 0.0)).unwrap();
        w.remove("/a").unwrap();
        w.write_encoded(&run("/b", 0.0)).unwrap();
        let e = w.move_run("/b", "/b/inside").unwrap_err();
        assert!(e.detail.contains("lies inside"), "{e}");
        let e = w.write_encoded(&run("/c", 0.0)).unwrap_err();
        assert!(
            e.detail.contains("left unfinished by an earlier error"),
            "{e}"
        );
        assert!(w.finish().is_err());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        // A move onto a run, and a name with a NUL byte, are refused.
        let w = DirectWriter::create_at(&file).unwrap();
        w.write_encoded(&run("/a", 0.0)).unwrap();
        w.write_encoded(&run("/b", 1.0)).unwrap();
        let e = w.move_run("/a", "/b").unwrap_err();
        assert!(e.detail.contains("/b exists already"), "{e}");
        w.abandon();
        let w = DirectWriter::create_at(&file).unwrap();
        let e = w.write_encoded(&run("/x\0y", 0.0)).unwrap_err();
        assert!(e.detail.contains("NUL"), "{e}");
        w.abandon();
    }
}
