//! An archive opened: the file checked (HDF5 signature, not empty), its groups walked for
//! runs with the attributes they inherit from their parents, and the groups that hold
//! datasets but are not runs listed with the reason. In: a path and the ingest options; out:
//! an [`Archive`] with its runs' metadata ([`Archive::open`]), or its run groups listed,
//! each run's metadata read when asked ([`Archive::open_listed`]).

use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;

use hdf5::{File, Group};

use crate::h5util::{read_attr, AttrValue};

use super::*;

/// An open campaign archive and the runs found in it.
pub struct Archive {
    pub(super) file_name: String,
    /// The file as plain bytes (`None` where it cannot be opened so), and what it was when
    /// opened: for [`Archive::placed`].
    pub(super) raw: Option<std::fs::File>,
    pub(super) stamp: super::FileStamp,
    pub(super) file: File,
    pub(super) options: IngestOptions,
    /// Runs in path order, with their metadata (empty when opened by
    /// [`Archive::open_listed`]).
    pub runs: Vec<RunEntry>,
    /// The run groups found, in path order, their metadata not read.
    pub listed: Vec<Listed>,
    /// Groups with datasets that are not runs (other dataset names), in path order.
    pub not_runs: Vec<NotARun>,
}

impl fmt::Debug for Archive {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Archive")
            .field("file", &self.file_name)
            .field("runs", &self.runs.len())
            .field("listed", &self.listed.len())
            .finish()
    }
}

/// Where HDF5 looks for its signature (user blocks are powers of two from 512).
fn has_hdf5_signature(path: &Path, len: u64) -> std::io::Result<bool> {
    use std::io::{Read, Seek, SeekFrom};
    const SIG: [u8; 8] = [0x89, b'H', b'D', b'F', b'\r', b'\n', 0x1a, b'\n'];
    let mut f = std::fs::File::open(path)?;
    let mut offset = 0u64;
    while offset + 8 <= len {
        f.seek(SeekFrom::Start(offset))?;
        let mut buf = [0u8; 8];
        f.read_exact(&mut buf)?;
        if buf == SIG {
            return Ok(true);
        }
        offset = if offset == 0 { 512 } else { offset * 2 };
    }
    Ok(false)
}

/// A run group found in an archive, its metadata not read yet: the datasets it holds, or why
/// it could not be looked into.
#[derive(Debug, Clone)]
pub struct Listed {
    /// Group path.
    pub path: String,
    members: Result<RunMembers, IngestError>,
}

impl Archive {
    /// Opens an archive and finds its runs; per-run problems are kept in [`RunEntry::meta`].
    pub fn open(path: &Path, options: &IngestOptions) -> Result<Archive, IngestError> {
        let mut archive = Archive::open_listed(path, options)?;
        archive.runs = (archive.listed.iter())
            .map(|l| RunEntry {
                path: l.path.clone(),
                meta: archive.read_meta(l),
            })
            .collect();
        Ok(archive)
    }

    /// Opens an archive and lists its run groups without reading their attributes:
    /// [`Archive::read_meta`] reads one run's. libhdf5 crashes on some corrupt attributes;
    /// `skelid run`'s reading child reads them one run at a time, so that such a crash costs
    /// that run, not its whole archive.
    pub fn open_listed(path: &Path, options: &IngestOptions) -> Result<Archive, IngestError> {
        let file_name = path.display().to_string();
        let md = std::fs::metadata(path).map_err(|e| IngestError::Unreadable {
            file: file_name.clone(),
            detail: e.to_string(),
        })?;
        if md.is_dir() {
            return Err(IngestError::Unreadable {
                file: file_name,
                detail: "is a directory (pass the .h5 files in it, or a glob)".into(),
            });
        }
        if md.len() == 0 {
            return Err(IngestError::EmptyFile { file: file_name });
        }
        match has_hdf5_signature(path, md.len()) {
            Ok(true) => {}
            Ok(false) => return Err(IngestError::NotHdf5 { file: file_name }),
            Err(e) => {
                return Err(IngestError::Unreadable {
                    file: file_name,
                    detail: e.to_string(),
                })
            }
        }
        let file = File::open(path).map_err(|e| IngestError::Corrupt {
            file: file_name.clone(),
            run: None,
            detail: e.to_string(),
        })?;
        let root = file.as_group().map_err(|e| IngestError::Corrupt {
            file: file_name.clone(),
            run: None,
            detail: e.to_string(),
        })?;
        let mut archive = Archive {
            file_name,
            raw: std::fs::File::open(path).ok(),
            stamp: super::FileStamp::of(&md),
            file,
            options: options.clone(),
            runs: Vec::new(),
            listed: Vec::new(),
            not_runs: Vec::new(),
        };
        let mut found = Vec::new();
        let mut stats = WalkStats::default();
        archive.walk(&root, "/", 0, &mut found, &mut stats)?;
        found.sort_by(|a: &Listed, b| a.path.cmp(&b.path));
        // Groups that could not be listed, named if no run is left to report them.
        let unlisted: Vec<String> = (found.iter())
            .filter_map(|l| l.members.as_ref().err().map(|_| l.path.clone()))
            .collect();
        if let Some(pat) = &options.run_glob {
            found.retain(|r| pat.matches(&r.path));
        }
        if found.is_empty() {
            let mut hint = String::new();
            if let Some(format) = skelid_output(&root) {
                hint = format!(
                    " (this is skelid's own output, format {format}, not a campaign archive: \
                     pass the archives it was made from)"
                );
            } else if let Some(pat) = &options.run_glob {
                hint = format!(" matching {} {pat}", crate::hint::Hint::RunGlob);
            } else if !stats.dataset_names.is_empty() {
                let names: Vec<_> = stats.dataset_names.iter().take(8).cloned().collect();
                hint = format!(" (datasets seen: {})", names.join(", "));
            }
            if !unlisted.is_empty() {
                let names: Vec<_> = unlisted.iter().take(8).cloned().collect();
                hint.push_str(&format!(
                    " (libhdf5 could not list {}: corrupt, their runs not found)",
                    names.join(", ")
                ));
            }
            return Err(IngestError::NoRuns {
                file: archive.file_name.clone(),
                input: options.input_name.clone(),
                output: options.output_name.clone(),
                hint,
            });
        }
        archive.listed = found;
        stats.not_runs.sort_by(|a, b| a.path.cmp(&b.path));
        if let Some(pat) = &options.run_glob {
            stats.not_runs.retain(|g| pat.matches(&g.path));
        }
        archive.not_runs = stats.not_runs;
        Ok(archive)
    }

    /// A listed run's metadata ([`Archive::open_listed`]), or why it cannot be used.
    pub fn read_meta(&self, run: &Listed) -> Result<RunMeta, IngestError> {
        let members = run.members.clone()?;
        let group = (self.file.group(&run.path)).map_err(|e| self.corrupt(Some(&run.path), e))?;
        self.run_meta(&group, &run.path, members)
    }

    /// The archive's file name as given.
    pub fn file_name(&self) -> &str {
        &self.file_name
    }

    pub(super) fn corrupt(&self, run: Option<&str>, e: impl fmt::Display) -> IngestError {
        IngestError::Corrupt {
            file: self.file_name.clone(),
            run: run.map(str::to_string),
            detail: e.to_string(),
        }
    }

    /// Collects the runs under `group` into `out`; `Err` only when `group` itself cannot be
    /// listed (a subgroup that cannot is an entry of its own, failed).
    pub(super) fn walk(
        &self,
        group: &Group,
        path: &str,
        depth: usize,
        out: &mut Vec<Listed>,
        stats: &mut WalkStats,
    ) -> Result<(), IngestError> {
        // Hard-link cycles are legal in HDF5; a depth cap ends them.
        if depth > 32 {
            return Ok(());
        }
        let names = group
            .member_names()
            .map_err(|e| self.corrupt((depth > 0).then_some(path), e))?;
        let has = |n: &str| names.iter().any(|m| m == n) && is_dataset(group, n);
        let members = RunMembers {
            input: has(channel_name(&self.options.input_name).0),
            output: has(channel_name(&self.options.output_name).0),
            time: has("time"),
        };
        if members.output || members.input {
            out.push(Listed {
                path: path.to_string(),
                members: Ok(members),
            });
            return Ok(());
        }
        let mut datasets = Vec::new();
        for name in &names {
            let child = join_path(path, name);
            match group.loc_type_by_name(name) {
                Ok(hdf5::LocationType::Group) => match group.group(name) {
                    // A group that cannot be listed (a corrupt symbol table or B-tree) is
                    // that group's failure, not the archive's: one run's damaged index lost
                    // all of an archive's runs until 2026-12-07.
                    Ok(g) => {
                        let listed = self.walk(&g, &child, depth + 1, out, stats);
                        // MATLAB's own groups (`#refs#`) hold no runs: not a failure either.
                        let matlab = name.starts_with('#') && name.ends_with('#');
                        if let (Err(e), false) = (listed, matlab) {
                            out.push(Listed {
                                path: child.clone(),
                                members: Err(e),
                            });
                        }
                    }
                    Err(e) => {
                        out.push(Listed {
                            path: child.clone(),
                            members: Err(self.corrupt(Some(&child), e)),
                        });
                    }
                },
                Ok(hdf5::LocationType::Dataset) => {
                    if stats.dataset_names.len() < 64 && !stats.dataset_names.contains(name) {
                        stats.dataset_names.push(name.clone());
                    }
                    if datasets.len() < 16 {
                        datasets.push(name.clone());
                    }
                }
                Ok(_) => {}
                // Dangling soft links and unreadable objects are skipped, not fatal.
                Err(_) => {}
            }
        }
        // A time base alone is no candidate for a run, nor are MATLAB's own groups.
        if datasets.iter().any(|d| d != "time")
            && !path.contains("/#")
            && stats.not_runs.len() < MAX_NOT_RUNS
        {
            stats.not_runs.push(NotARun {
                path: path.to_string(),
                datasets,
            });
        }
        Ok(())
    }
}

pub(super) fn is_dataset(group: &Group, name: &str) -> bool {
    matches!(
        group.loc_type_by_name(name),
        Ok(hdf5::LocationType::Dataset)
    )
}

pub(super) fn join_path(parent: &str, name: &str) -> String {
    if parent == "/" {
        format!("/{name}")
    } else {
        format!("{parent}/{name}")
    }
}

/// Which of a run group's datasets exist, found once while walking the file.
#[derive(Debug, Clone, Copy)]
pub(super) struct RunMembers {
    pub(super) input: bool,
    pub(super) output: bool,
    pub(super) time: bool,
}

#[derive(Default)]
pub(super) struct WalkStats {
    pub(super) dataset_names: Vec<String>,
    pub(super) not_runs: Vec<NotARun>,
}

/// The known attributes of a run, each taken from the run group or its nearest ancestor.
pub(super) struct InheritedAttrs {
    pub(super) values: BTreeMap<String, AttrValue>,
}

pub(super) const INHERITED: &[&str] = &[
    "sample_rate",
    "kind",
    "input_quantity",
    "output_quantity",
    "units",
    "inertia",
    "gravity_stiffness",
    "excitation",
    "mode_fmin",
    "mode_fmax",
    "mode_near",
    "zero_tolerance",
];

/// The root's `format` when it names one of skelid's own outputs (`skelid-results/1`,
/// `skelid-track/1`, …) rather than a campaign (`skelid-campaign/1`, or none).
fn skelid_output(root: &Group) -> Option<String> {
    match read_attr(&root.attr("format").ok()?).ok()? {
        AttrValue::Text(f) if f.starts_with("skelid-") && !f.starts_with("skelid-campaign/") => {
            Some(f)
        }
        _ => None,
    }
}

impl InheritedAttrs {
    pub(super) fn collect(file: &File, path: &str) -> Self {
        let mut values = BTreeMap::new();
        // Walk from the run up to the root; the first (nearest) value wins.
        let mut p = path.to_string();
        loop {
            if let Ok(g) = file.group(&p) {
                for &name in INHERITED {
                    if values.contains_key(name) {
                        continue;
                    }
                    if let Ok(a) = g.attr(name) {
                        let v = read_attr(&a).unwrap_or_else(AttrValue::Other);
                        values.insert(name.to_string(), v);
                    }
                }
            }
            if p == "/" {
                break;
            }
            p = match p.rfind('/') {
                Some(0) | None => "/".to_string(),
                Some(i) => p[..i].to_string(),
            };
        }
        InheritedAttrs { values }
    }

    pub(super) fn get(&self, name: &str) -> Option<&AttrValue> {
        self.values.get(name)
    }

    pub(super) fn text(&self, name: &str) -> Option<String> {
        self.values.get(name).map(|v| v.to_string())
    }
}
