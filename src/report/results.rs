//! `results.h5` (FORMATS.md §3), written by one thread: each run's encoded results placed
//! with raw libhdf5 calls that share one type, space and creation list per layout, its
//! attributes and units, then the runs moved into the report's order. In: encoded runs;
//! out: the file.

use std::path::{Path, PathBuf};

use crate::campaign::tmp_path;
use crate::h5util::{write_str_attr, AttrMaker};

use super::encoded::{Elem, EncodedRun, Item, Scalar, Storage};
use super::*;

/// A results file being written (`results.h5`, or one run's journal file): written as
/// `<path>.tmp` and renamed into place by [`finish`](Self::finish), so a crash never leaves
/// a half-written one visible.
pub struct ResultsWriter {
    file: hdf5::File,
    path: PathBuf,
    tmp: PathBuf,
    attrs: AttrMaker,
    layouts: Layouts,
    /// The chunks written so far, released from the page cache in rounds (`None` where
    /// the file could not be opened a second time).
    extents: std::sync::Mutex<Option<crate::pagecache::Extents>>,
}

impl ResultsWriter {
    /// Starts `<dir>/results.h5`.
    pub fn create(dir: &Path) -> Result<ResultsWriter, ReportError> {
        Self::create_at(&dir.join("results.h5"))
    }

    /// Starts a results file at `path` (written as `path.tmp` until [`finish`](Self::finish)).
    pub fn create_at(path: &Path) -> Result<ResultsWriter, ReportError> {
        let path = path.to_path_buf();
        let err = |detail: String| ReportError {
            file: path.display().to_string(),
            detail,
        };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| err(e.to_string()))?;
        }
        let tmp = tmp_path(&path);
        let file = hdf5::File::create(&tmp).map_err(|e| err(e.to_string()))?;
        write_str_attr(&file, "format", "skelid-results/1").map_err(|e| err(e.to_string()))?;
        write_str_attr(&file, "skelid_version", env!("CARGO_PKG_VERSION"))
            .map_err(|e| err(e.to_string()))?;
        let attrs = AttrMaker::new().map_err(|e| err(e.to_string()))?;
        let layouts = Layouts::new().map_err(|e| err(e.to_string()))?;
        let extents = std::sync::Mutex::new(crate::pagecache::Extents::open(&tmp));
        Ok(ResultsWriter {
            file,
            path,
            tmp,
            attrs,
            layouts,
            extents,
        })
    }

    /// Sets a string attribute on the file's root.
    pub fn set_root_attr(&self, name: &str, value: &str) -> Result<(), ReportError> {
        write_str_attr(&self.file, name, value).map_err(|e| ReportError {
            file: self.path.display().to_string(),
            detail: e.to_string(),
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

    /// Copies the group `src_path` of the results file `src` to `dst_path` here, whole
    /// (datasets, attributes, sub-groups), with libhdf5's object copy.
    pub fn copy_run_from(
        &self,
        src: &Path,
        src_path: &str,
        dst_path: &str,
    ) -> Result<(), ReportError> {
        let err = |detail: String| ReportError {
            file: self.path.display().to_string(),
            detail: format!("copying {src_path} from {}: {detail}", src.display()),
        };
        let source = hdf5::File::open(src).map_err(|e| err(e.to_string()))?;
        let (parent, src_name, dst_name) = self.raw_target(src_path, dst_path).map_err(err)?;
        // The hdf5 crate serialises every libhdf5 call behind one lock; a raw call must
        // take the same lock.
        let status = hdf5::sync::sync(|| unsafe {
            hdf5_sys::h5o::H5Ocopy(
                source.id(),
                src_name.as_ptr(),
                parent.id(),
                dst_name.as_ptr(),
                hdf5_sys::h5p::H5P_DEFAULT,
                hdf5_sys::h5p::H5P_DEFAULT,
            )
        });
        if status < 0 {
            return Err(err("H5Ocopy failed".into()));
        }
        Ok(())
    }

    /// Adds one run (failed runs included, with their error) encoded by [`encode_run`]
    /// (possibly on another thread): groups and attributes through the hdf5 crate,
    /// compressed chunks straight into the file.
    pub fn write_encoded(&self, run: &EncodedRun) -> Result<(), ReportError> {
        self.write_encoded_as(run, &run.path)
    }

    /// [`write_encoded`](Self::write_encoded) under the group path `dst` instead of the
    /// run's own.
    pub fn write_encoded_as(&self, run: &EncodedRun, dst: &str) -> Result<(), ReportError> {
        self.write_encoded_inner(run, dst).map_err(|e| ReportError {
            file: self.path.display().to_string(),
            detail: format!("run {}: {e}", run.path),
        })
    }

    /// Moves the run at group path `from` to `to` (a link move: no data is copied),
    /// creating `to`'s parent groups.
    pub fn move_run(&self, from: &str, to: &str) -> Result<(), ReportError> {
        let err = |detail: String| ReportError {
            file: self.path.display().to_string(),
            detail: format!("moving {from} to {to}: {detail}"),
        };
        let (parent, src, dst) = self.raw_target(from, to).map_err(err)?;
        // A raw call takes the hdf5 crate's lock like every other libhdf5 call.
        let status = hdf5::sync::sync(|| unsafe {
            hdf5_sys::h5l::H5Lmove(
                self.file.id(),
                src.as_ptr(),
                parent.id(),
                dst.as_ptr(),
                hdf5_sys::h5p::H5P_DEFAULT,
                hdf5_sys::h5p::H5P_DEFAULT,
            )
        });
        if status < 0 {
            return Err(err("H5Lmove failed".into()));
        }
        Ok(())
    }

    /// For a raw libhdf5 call that puts `src` at the group path `dst`: `dst`'s parent group
    /// (created if need be), and `src` and `dst`'s last component as C strings.
    pub(super) fn raw_target(
        &self,
        src: &str,
        dst: &str,
    ) -> Result<(hdf5::Group, std::ffi::CString, std::ffi::CString), String> {
        let (parent, name) = match dst.trim_end_matches('/').rsplit_once('/') {
            Some((p, n)) if !n.is_empty() => (p, n),
            _ => return Err("a run path must name a group below the root".into()),
        };
        let parent = group_path(&self.file, parent).map_err(|e| e.to_string())?;
        let c = |s: &str| std::ffi::CString::new(s).map_err(|e| e.to_string());
        Ok((parent, c(src)?, c(name)?))
    }

    /// Removes the object at `path` (a group and everything under it).
    pub fn remove(&self, path: &str) -> Result<(), ReportError> {
        self.file.unlink(path).map_err(|e| ReportError {
            file: self.path.display().to_string(),
            detail: format!("removing {path}: {e}"),
        })
    }

    pub(super) fn write_encoded_inner(&self, run: &EncodedRun, dst: &str) -> hdf5::Result<()> {
        // Groups by relative path, opened once: a run has about a hundred items.
        let mut groups = std::collections::HashMap::new();
        groups.insert(String::new(), group_path(&self.file, dst)?);
        let at = |groups: &mut std::collections::HashMap<String, hdf5::Group>,
                  rel: &str|
         -> hdf5::Result<hdf5::Group> {
            if let Some(g) = groups.get(rel) {
                return Ok(g.clone());
            }
            let g = groups[""].group(rel)?;
            groups.insert(rel.to_string(), g.clone());
            Ok(g)
        };
        // A dataset's `units` follows it: the handle is kept, not reopened by name
        // (H5Dopen2 was an eighth of the writer's time).
        let mut last: Option<(&str, &str, hdf5::Dataset)> = None;
        for item in &run.items {
            match item {
                Item::Group(rel) => {
                    let (parent, name) = rel.rsplit_once('/').unwrap_or(("", rel));
                    let g = at(&mut groups, parent)?.create_group(name)?;
                    groups.insert(rel.clone(), g);
                }
                // The run's groups are new and an encoded run names each attribute once:
                // created without looking for an old one.
                Item::Attr { group, name, value } => {
                    let g = at(&mut groups, group)?;
                    match value {
                        Scalar::F64(x) => self.attrs.number(&g, name, *x)?,
                        Scalar::Str(s) => self.attrs.text(&g, name, s)?,
                    }
                }
                Item::Dataset(d) => {
                    let ds = write_dataset(
                        &at(&mut groups, &d.group)?,
                        d,
                        &self.layouts,
                        self.extents
                            .lock()
                            .unwrap_or_else(|e| e.into_inner())
                            .as_mut(),
                    )?;
                    last = Some((d.group.as_str(), d.name.as_str(), ds));
                }
                Item::DatasetAttr {
                    group,
                    dataset,
                    name,
                    value,
                } => match &last {
                    Some((g, n, ds)) if g == group && n == dataset => {
                        self.attrs.text(ds, name, value)?
                    }
                    _ => {
                        let ds = at(&mut groups, group)?.dataset(dataset)?;
                        self.attrs.text(&ds, name, value)?
                    }
                },
            }
        }
        // No flush here: `finish` flushes once, and a file not finished is discarded.
        Ok(())
    }

    /// Closes the file and renames it into place. A file it replaces (a rerun's earlier
    /// results) is moved aside first and deleted by a process of its own, which this one
    /// does not wait for ([`set_aside`], [`discard`]).
    pub fn finish(self) -> Result<PathBuf, ReportError> {
        let ResultsWriter {
            file, path, tmp, ..
        } = self;
        let err = |detail: String| ReportError {
            file: path.display().to_string(),
            detail,
        };
        let flushed = file.flush();
        drop(file);
        if let Err(e) = flushed {
            let _ = std::fs::remove_file(&tmp);
            return Err(err(e.to_string()));
        }
        put_in_place(&tmp, &path)
    }

    /// Closes and deletes the unfinished file: a batch that stops on an error leaves no
    /// `.tmp` behind (its runs are in the journal).
    pub fn abandon(self) {
        let ResultsWriter { file, tmp, .. } = self;
        drop(file);
        let _ = std::fs::remove_file(&tmp);
    }
}

/// Renames the finished `tmp` to `path`: a file it replaces (a rerun's earlier results) is
/// moved aside first and deleted by a process of its own, which this one does not wait
/// for ([`set_aside`], [`discard`]). On failure `tmp` is deleted and the old file put back.
pub(super) fn put_in_place(tmp: &Path, path: &Path) -> Result<PathBuf, ReportError> {
    let old = set_aside(path);
    match std::fs::rename(tmp, path) {
        Ok(()) => {
            discard(old);
            Ok(path.to_path_buf())
        }
        Err(e) => {
            let _ = std::fs::remove_file(tmp);
            if let Some(old) = old {
                let _ = std::fs::rename(old, path);
            }
            Err(ReportError {
                file: path.display().to_string(),
                detail: e.to_string(),
            })
        }
    }
}

/// Moves the file at `path`, if there is one, to a hidden name beside it, so that the new
/// file is renamed onto a free name. Renamed over an existing file, ext4 (`auto_da_alloc`)
/// allocates and starts writing the new file inside the rename: 0.26 s for 200 runs'
/// results.h5 here, 2 s for 1000 runs (2 GB) on a 16-core machine, a fifth of the batch.
/// A process killed between the two renames leaves the earlier results under the hidden
/// name; the next batch's [`discard`] deletes it. `None` where there was no file.
fn set_aside(path: &Path) -> Option<PathBuf> {
    let name = path.file_name()?.to_string_lossy().into_owned();
    let aside = path.with_file_name(format!(".{name}.replaced.{}", std::process::id()));
    std::fs::rename(path, &aside).ok().map(|()| aside)
}

/// Deletes `old` (from [`set_aside`]) and any set aside by earlier processes that stopped
/// before deleting theirs, in a child process that is not waited for: `rm`, its output
/// discarded, so that nobody waiting on this process's output waits for it too. Where no
/// child can be started, deletes them here.
fn discard(old: Option<PathBuf>) {
    let Some(old) = old else { return };
    let mut doomed = vec![old.clone()];
    if let (Some(dir), Some(name)) = (old.parent(), old.file_name()) {
        let name = name.to_string_lossy();
        let prefix = &name[..name.rfind('.').map_or(name.len(), |i| i + 1)];
        if let Ok(entries) = std::fs::read_dir(dir) {
            doomed.extend(
                entries
                    .filter_map(|e| e.ok())
                    .map(|e| e.path())
                    .filter(|p| {
                        p != &old
                            && p.file_name()
                                .is_some_and(|n| n.to_string_lossy().starts_with(prefix))
                    }),
            );
        }
    }
    let spawned = std::process::Command::new("rm")
        .arg("-f")
        .arg("--")
        .args(&doomed)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn();
    match spawned {
        // Reaped by a thread of its own, so that a long-lived caller (the tests) keeps no
        // zombies; the process may end first, which leaves `rm` to finish alone.
        Ok(mut child) => {
            let _ = std::thread::Builder::new()
                .name("discard".into())
                .spawn(move || child.wait());
        }
        Err(_) => {
            for p in doomed {
                let _ = std::fs::remove_file(p);
            }
        }
    }
}

/// Opens or creates the group at an absolute path, creating its parents.
fn group_path(file: &hdf5::File, path: &str) -> hdf5::Result<hdf5::Group> {
    let mut g = file.group("/")?;
    for part in path.split('/').filter(|p| !p.is_empty()) {
        g = match g.group(part) {
            Ok(x) => x,
            Err(_) => g.create_group(part)?,
        };
    }
    Ok(g)
}

/// The datasets' layouts written so far, each
/// with the datatype, dataspace and creation list of its first dataset, so that the next
/// ones are created with one libhdf5 call: a run has two dozen chunked datasets of three
/// or four layouts and as many small contiguous ones (skeleton columns) of a few lengths,
/// and building those lists anew for each was a fifth of what creating a dataset cost the
/// writer.
pub(super) struct Layouts {
    /// Link creation as the binding's dataset builder sets it.
    lcpl: hdf5::plist::LinkCreate,
    /// The memory type of float data.
    native_f64: hdf5::Datatype,
    seen: std::sync::Mutex<std::collections::HashMap<LayoutKey, Layout>>,
}

/// What makes two datasets alike for [`Layouts`].
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub(super) enum LayoutKey {
    /// Contiguous float64 values of this length.
    Plain(usize),
    /// Chunked: element, length, deflate level.
    Chunked(Elem, usize, u8),
}

/// Datatype, dataspace and creation list of one layout.
pub(super) type Layout = (hdf5::Datatype, hdf5::Dataspace, hdf5::plist::DatasetCreate);

impl Layouts {
    pub(super) fn new() -> hdf5::Result<Layouts> {
        Ok(Layouts {
            lcpl: hdf5::plist::LinkCreate::build()
                .create_intermediate_group(true)
                .finish()?,
            native_f64: hdf5::Datatype::from_type::<f64>()?,
            seen: std::sync::Mutex::new(std::collections::HashMap::new()),
        })
    }

    /// Creates the dataset `name` in `g` like the first of its layout, if one was made.
    pub(super) fn create_like(
        &self,
        g: &hdf5::Group,
        name: &str,
        key: LayoutKey,
    ) -> hdf5::Result<Option<hdf5::Dataset>> {
        let seen = self.seen.lock().unwrap_or_else(|p| p.into_inner());
        let Some((dtype, space, dcpl)) = seen.get(&key) else {
            return Ok(None);
        };
        let cname = std::ffi::CString::new(name)
            .map_err(|e| hdf5::Error::from(format!("dataset name {name:?}: {e}")))?;
        // The binding serialises every libhdf5 call behind one lock; a raw call takes it too.
        let id = hdf5::sync::sync(|| unsafe {
            hdf5_sys::h5d::H5Dcreate2(
                g.id(),
                cname.as_ptr(),
                dtype.id(),
                space.id(),
                self.lcpl.id(),
                dcpl.id(),
                hdf5_sys::h5p::H5P_DEFAULT,
            )
        });
        if id < 0 {
            return Err(hdf5::Error::from(format!("cannot create dataset {name}")));
        }
        // SAFETY: a fresh identifier from H5Dcreate2, owned by the handle from here on.
        unsafe { hdf5::from_id::<hdf5::Dataset>(id) }.map(Some)
    }

    /// Writes all of `v` into the float dataset `ds`.
    pub(super) fn write_all(&self, ds: &hdf5::Dataset, v: &[f64]) -> hdf5::Result<()> {
        use hdf5_sys::h5s::H5S_ALL;
        let status = hdf5::sync::sync(|| unsafe {
            hdf5_sys::h5d::H5Dwrite(
                ds.id(),
                self.native_f64.id(),
                H5S_ALL,
                H5S_ALL,
                hdf5_sys::h5p::H5P_DEFAULT,
                v.as_ptr().cast(),
            )
        });
        if status < 0 {
            return Err(hdf5::Error::from(format!("cannot write {}", ds.name())));
        }
        Ok(())
    }

    /// Remembers the layout of `ds`, the first dataset of `key`.
    pub(super) fn remember(&self, key: LayoutKey, ds: &hdf5::Dataset) -> hdf5::Result<()> {
        let layout = (ds.dtype()?, ds.space()?, ds.create_plist()?);
        self.seen
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(key, layout);
        Ok(())
    }
}

/// Creates one encoded dataset in `g`: contiguous values written as usual, or the dataset
/// created with the same chunking and filters the chunks were encoded for, then each chunk
/// handed to libhdf5 as it is (`H5Dwrite_chunk`, no filtering under the lock), and its place
/// in the file noted in `extents` for release from the page cache.
pub(super) fn write_dataset(
    g: &hdf5::Group,
    d: &encoded::Dataset,
    layouts: &Layouts,
    mut extents: Option<&mut crate::pagecache::Extents>,
) -> hdf5::Result<hdf5::Dataset> {
    let (level, chunks) = match &d.storage {
        Storage::Plain(v) => {
            let key = LayoutKey::Plain(v.len());
            if let Some(ds) = layouts.create_like(g, &d.name, key)? {
                layouts.write_all(&ds, v)?;
                return Ok(ds);
            }
            let ds = g
                .new_dataset_builder()
                .with_data(v)
                .create(d.name.as_str())?;
            layouts.remember(key, &ds)?;
            return Ok(ds);
        }
        Storage::Chunked { level, chunks } => (*level, chunks),
    };
    let key = LayoutKey::Chunked(d.elem, d.len, level);
    let ds = match layouts.create_like(g, &d.name, key)? {
        Some(ds) => ds,
        None => {
            let b = match d.elem {
                Elem::F64 => g.new_dataset::<f64>(),
                Elem::U8 => g.new_dataset::<u8>(),
            }
            .shape(d.len)
            .chunk(encoded::chunk_len(d.len));
            // The chunks were shuffled exactly when the element is wider than a byte.
            let b = if d.elem == Elem::U8 { b } else { b.shuffle() };
            let ds = b.deflate(level).create(d.name.as_str())?;
            layouts.remember(key, &ds)?;
            ds
        }
    };
    let step = encoded::chunk_len(d.len) as u64;
    for (i, c) in chunks.iter().enumerate() {
        let offset = [i as u64 * step];
        let (mut addr, mut size, mut mask) = (0, 0, 0);
        // The hdf5 crate serialises every libhdf5 call behind one lock; a raw call must
        // take the same lock.
        let status = hdf5::sync::sync(|| unsafe {
            let status = hdf5_sys::h5d::H5Dwrite_chunk(
                ds.id(),
                hdf5_sys::h5p::H5P_DEFAULT,
                0,
                offset.as_ptr(),
                c.len(),
                c.as_ptr().cast(),
            );
            if status >= 0 && extents.is_some() {
                // Where libhdf5 put the chunk: a lookup in the chunk index it just updated.
                let found = hdf5_sys::h5d::H5Dget_chunk_info_by_coord(
                    ds.id(),
                    offset.as_ptr(),
                    &mut mask,
                    &mut addr,
                    &mut size,
                );
                if found < 0 || addr == hdf5_sys::h5::HADDR_UNDEF {
                    size = 0;
                }
            }
            status
        });
        if let Some(e) = extents.as_deref_mut() {
            e.wrote(addr, size);
        }
        if status < 0 {
            return Err(hdf5::Error::from(format!(
                "H5Dwrite_chunk failed for {} chunk {i}",
                d.name
            )));
        }
    }
    Ok(ds)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The runs written into a fresh file at `file` under `/runs/<name>`.
    fn write(file: &Path, names: &[&str]) {
        let w = ResultsWriter::create_at(file).unwrap();
        for n in names {
            group_path(&w.file, &format!("/runs/{n}")).unwrap();
        }
        w.finish().unwrap();
    }

    fn names_in(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_replaced_file_is_set_aside_then_deleted_and_stale_ones_go_with_it() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("results.h5");
        write(&file, &["old"]);
        // What a process killed between its two renames leaves.
        let stale = dir.path().join(".results.h5.replaced.1");
        std::fs::copy(&file, &stale).unwrap();
        write(&file, &["new"]);
        let f = hdf5::File::open(&file).unwrap();
        assert!(f.group("/runs/new").is_ok() && f.group("/runs/old").is_err());
        // Deleted by a process not waited for: give it a few seconds.
        let t0 = std::time::Instant::now();
        while names_in(dir.path()) != ["results.h5"] && t0.elapsed().as_secs() < 10 {
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        assert_eq!(names_in(dir.path()), ["results.h5"]);
    }

    /// The extents noted for release from the page cache are where libhdf5 put the
    /// chunks: the finished file holds, over those extents in order, exactly the chunks
    /// written, byte for byte.
    #[test]
    fn the_extents_noted_for_release_hold_the_chunks_written() {
        let dir = tempfile::tempdir().unwrap();
        let (extents, written) = write_three_runs(&dir.path().join("results.h5"));
        // Consecutive chunks were merged, and the datasets' headers sit between runs.
        assert!(extents.len() > 1 && extents.len() < 27, "{extents:?}");
        let bytes = std::fs::read(dir.path().join("results.h5")).unwrap();
        let found: Vec<u8> = extents
            .iter()
            .flat_map(|&(o, l)| bytes[o as usize..(o + l) as usize].iter().copied())
            .collect();
        assert_eq!(found.len(), written.len());
        assert!(found == written);
    }

    /// Once a file is finished its chunks leave the page cache, though they are less than
    /// one round of [`crate::pagecache::Extents`] (before, such a last round was never
    /// handed over: every one of these pages stayed).
    #[cfg(target_os = "linux")]
    #[test]
    fn a_finished_files_chunks_leave_the_page_cache() {
        let Some(dir) = crate::pagecache::disk_tempdir() else {
            return;
        };
        let file = dir.path().join("results.h5");
        let (extents, _) = write_three_runs(&file);
        // Pages wholly inside the extents; those at their edges may hold metadata.
        let inside: Vec<usize> = extents
            .iter()
            .flat_map(|&(o, l)| (o.div_ceil(4096)..(o + l) / 4096).map(|p| p as usize))
            .collect();
        assert!(inside.len() > 100, "{} pages", inside.len());
        // A few may stay: the kernel caches long writes in folios of several pages, and
        // keeps one that reaches past the extent into metadata (7 of 625 pages here).
        let few = inside.len() / 10;
        let probe = std::fs::File::open(&file).unwrap();
        assert!(crate::pagecache::cached_after_release(&probe, &inside, few) <= few);
    }

    /// Writes three runs of three chunks per dataset (70 000 samples, distinct per run and
    /// dataset) into a new results file at `file`, finishes it, and returns the extents
    /// noted for release and the chunks' bytes in the order written.
    fn write_three_runs(file: &Path) -> (Vec<(u64, u64)>, Vec<u8>) {
        let w = ResultsWriter::create_at(file).unwrap();
        let mut written = Vec::new();
        for r in 0..3 {
            let mut e = encoded::EncodedRun::new(&format!("/runs/r{r}"));
            e.group("wavelet");
            let v: Vec<f64> = (0..70_000)
                .map(|i| (i as f64 * 1e-3 + r as f64).sin())
                .collect();
            e.signal("wavelet", "a", &v, true);
            e.signal(
                "",
                "b",
                &v.iter().map(|x| x * 3.0).collect::<Vec<_>>(),
                true,
            );
            e.bytes("wavelet", "valid", &vec![r as u8; 70_000], 4);
            for item in &e.items {
                if let Item::Dataset(d) = item {
                    if let Storage::Chunked { chunks, .. } = &d.storage {
                        written.extend(chunks.iter().flat_map(|c| c.iter().copied()));
                    }
                }
            }
            w.write_encoded(&e).unwrap();
        }
        let extents = {
            let held = w.extents.lock().unwrap();
            held.as_ref().unwrap().pending().to_vec()
        };
        w.finish().unwrap();
        (extents, written)
    }

    #[test]
    fn a_first_file_sets_nothing_aside() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("results.h5");
        assert_eq!(set_aside(&file), None);
        write(&file, &["a"]);
        assert_eq!(names_in(dir.path()), ["results.h5"]);
    }
}
