//! Campaign ingestion: finds the runs of a `skelid-campaign/1` HDF5 archive (FORMATS.md §1),
//! resolves their attributes and loads their signals, with one specific error per way an
//! archive can be wrong.
//!
//! File-level failures (not HDF5, empty, corrupt, no runs) are `Err` from [`Archive::open`];
//! a bad run never hides the others: it is listed with its own [`IngestError`].

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

use hdf5::types::TypeDescriptor;
use hdf5::{File, Group, Location};
use serde::Serialize;

use crate::h5util::{all_attrs, read_attr, AttrValue};
pub use crate::run::{Quantity, Run, RunKind, RunMeta};

/// Fewest samples a run may have: the wavelet ridge needs several periods plus its edge zones.
pub const MIN_SAMPLES: usize = 256;

/// Largest accepted relative jitter of a `time` dataset's steps (FORMATS.md §1).
pub const MAX_TIME_JITTER: f64 = 1e-6;

/// Everything that can be wrong with an archive or one of its runs.
///
/// Every message names the file, and the run where there is one, and says what to do next.
#[derive(Debug, Clone, thiserror::Error, Serialize)]
#[serde(tag = "error", rename_all = "snake_case")]
pub enum IngestError {
    /// The path cannot be read at all.
    #[error("{file}: cannot read the file: {detail}")]
    Unreadable { file: String, detail: String },
    /// Zero-byte file.
    #[error(
        "{file}: the file is empty (0 bytes); an interrupted copy or export leaves such files"
    )]
    EmptyFile { file: String },
    /// No HDF5 signature anywhere it may be.
    #[error("{file}: not an HDF5 file (no HDF5 signature at offset 0, 512, 1024, ...); skelid reads HDF5 campaign archives (MATLAB: save with -v7.3)")]
    NotHdf5 { file: String },
    /// libhdf5 refused the file or an object in it.
    #[error("{file}: truncated or corrupt HDF5 file{}: {detail}", run_part(run))]
    Corrupt {
        file: String,
        run: Option<String>,
        detail: String,
    },
    /// The walk found no group holding the signal datasets.
    #[error("{file}: no runs found: no group holds datasets named `{input}` and `{output}` (or `{output}` alone with kind = \"free\"){hint}; use --input-name/--output-name (NAME[k] picks channel k of a matrix), --kind and --run-glob for other layouts")]
    NoRuns {
        file: String,
        input: String,
        output: String,
        hint: String,
    },
    /// Neither a `sample_rate` attribute nor a `time` dataset, nor `--sample-rate`.
    #[error("{file}: run {run}: no sample rate: add a `sample_rate` attribute (Hz) to the run or a parent group, a `time` dataset, or pass --sample-rate")]
    MissingSampleRate { file: String, run: String },
    /// Sample rate present but not a positive finite number.
    #[error("{file}: run {run}: invalid sample rate {value} Hz (must be positive and finite)")]
    BadSampleRate {
        file: String,
        run: String,
        value: f64,
    },
    /// `input`, `output` (and `time`) differ in length.
    #[error(
        "{file}: run {run}: length mismatch: {a_name} has {a_len} samples but {b_name} has {b_len}"
    )]
    LengthMismatch {
        file: String,
        run: String,
        a_name: String,
        a_len: usize,
        b_name: String,
        b_len: usize,
    },
    /// A signal dataset is not a vector (N, 1×N or N×1).
    #[error("{file}: run {run}: dataset `{dataset}` has shape {shape:?}; a signal must be 1-D (N, 1xN or Nx1)")]
    NotOneD {
        file: String,
        run: String,
        dataset: String,
        shape: Vec<usize>,
    },
    /// A signal dataset of a type that is not a number.
    #[error("{file}: run {run}: dataset `{dataset}` has unsupported type {dtype}; signals must be float32/float64, or integer counts with a `scale` attribute")]
    UnsupportedType {
        file: String,
        run: String,
        dataset: String,
        dtype: String,
    },
    /// NaN or infinite samples.
    #[error("{file}: run {run}: dataset `{dataset}` has {count} non-finite value(s) (NaN/Inf), the first at sample {first} (t = {first_time:.6} s); remove or interpolate them")]
    NonFinite {
        file: String,
        run: String,
        dataset: String,
        count: usize,
        first: usize,
        first_time: f64,
    },
    /// Fewer samples than the analysis needs.
    #[error(
        "{file}: run {run}: too short to analyse: {samples} samples, at least {min} are needed"
    )]
    TooShort {
        file: String,
        run: String,
        samples: usize,
        min: usize,
    },
    /// `time` not strictly increasing or not uniform.
    #[error("{file}: run {run}: non-uniform time: {detail}; skelid needs uniformly sampled signals (resample first, or drop `time` and pass --sample-rate)")]
    NonUniformTime {
        file: String,
        run: String,
        detail: String,
    },
    /// An attribute with a value skelid cannot use.
    #[error("{file}: run {run}: attribute `{name}` = {value}: {detail}")]
    BadAttribute {
        file: String,
        run: String,
        name: String,
        value: String,
        detail: String,
    },
    /// A group with an `input` but no `output`.
    #[error("{file}: run {run}: has `{input}` but no `{output}` dataset; a run needs its response channel")]
    MissingOutput {
        file: String,
        run: String,
        input: String,
        output: String,
    },
    /// A group with an `output` but no `input` and no `kind = "free"`.
    #[error("{file}: run {run}: has `{output}` but no `{input}`; for a free decay set the attribute kind = \"free\", otherwise add the input channel")]
    MissingInput {
        file: String,
        run: String,
        input: String,
        output: String,
    },
}

fn run_part(run: &Option<String>) -> String {
    match run {
        Some(r) => format!(" (run {r})"),
        None => String::new(),
    }
}

impl IngestError {
    /// The run path this error concerns, if any.
    pub fn run(&self) -> Option<&str> {
        use IngestError::*;
        match self {
            Corrupt { run, .. } => run.as_deref(),
            MissingSampleRate { run, .. }
            | BadSampleRate { run, .. }
            | LengthMismatch { run, .. }
            | NotOneD { run, .. }
            | UnsupportedType { run, .. }
            | NonFinite { run, .. }
            | TooShort { run, .. }
            | NonUniformTime { run, .. }
            | BadAttribute { run, .. }
            | MissingInput { run, .. }
            | MissingOutput { run, .. } => Some(run),
            Unreadable { .. } | EmptyFile { .. } | NotHdf5 { .. } | NoRuns { .. } => None,
        }
    }

    /// Short machine-readable name of the error kind (as in JSON output).
    pub fn kind(&self) -> &'static str {
        use IngestError::*;
        match self {
            Unreadable { .. } => "unreadable",
            EmptyFile { .. } => "empty_file",
            NotHdf5 { .. } => "not_hdf5",
            Corrupt { .. } => "corrupt",
            NoRuns { .. } => "no_runs",
            MissingSampleRate { .. } => "missing_sample_rate",
            BadSampleRate { .. } => "bad_sample_rate",
            LengthMismatch { .. } => "length_mismatch",
            NotOneD { .. } => "not_one_d",
            UnsupportedType { .. } => "unsupported_type",
            NonFinite { .. } => "non_finite",
            TooShort { .. } => "too_short",
            NonUniformTime { .. } => "non_uniform_time",
            BadAttribute { .. } => "bad_attribute",
            MissingInput { .. } => "missing_input",
            MissingOutput { .. } => "missing_output",
        }
    }
}

/// Options for archives laid out differently from FORMATS.md §1.
#[derive(Debug, Clone)]
pub struct IngestOptions {
    /// Name of the input dataset in a run group.
    pub input_name: String,
    /// Name of the output dataset in a run group.
    pub output_name: String,
    /// Sample rate (Hz) that overrides attributes and `time` datasets.
    pub sample_rate: Option<f64>,
    /// Only runs whose path matches this glob (e.g. `/runs/run_0*`).
    pub run_glob: Option<glob::Pattern>,
    /// Kind of every run, overriding `kind` attributes.
    pub kind: Option<RunKind>,
    /// Inertia of every run (kg m² or kg), overriding `inertia` attributes.
    pub inertia: Option<f64>,
    /// What every run's input measures, overriding `input_quantity` attributes.
    pub input_quantity: Option<Quantity>,
    /// What every run's output measures, overriding `output_quantity` attributes.
    pub output_quantity: Option<Quantity>,
}

impl Default for IngestOptions {
    fn default() -> Self {
        Self {
            input_name: "input".into(),
            output_name: "output".into(),
            sample_rate: None,
            run_glob: None,
            kind: None,
            inertia: None,
            input_quantity: None,
            output_quantity: None,
        }
    }
}

/// A dataset name as given, `NAME` or `NAME[k]`: the dataset and the channel picked from
/// a 2-D one (k counts from 0 along its shorter axis, so a MATLAB 3×N matrix, stored N×3,
/// and an N×3 one read alike).
pub fn channel_name(name: &str) -> (&str, Option<usize>) {
    if let Some(base) = name.strip_suffix(']') {
        if let Some((base, k)) = base.rsplit_once('[') {
            if let Ok(k) = k.trim().parse() {
                return (base, Some(k));
            }
        }
    }
    (name, None)
}

/// Scalar datasets that give a run's sample rate (Hz) when no attribute or `time` does, as
/// MATLAB saves a variable `Fs`.
const RATE_VARIABLES: [&str; 7] = [
    "Fs",
    "fs",
    "FS",
    "sample_rate",
    "SampleRate",
    "sampling_rate",
    "samplerate",
];

/// A group that holds datasets but is not a run: none of them has the input's or the
/// output's name. Listed so that a run laid out with other names is never dropped unseen.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NotARun {
    /// Group path.
    pub path: String,
    /// Its datasets' names (the first 16).
    pub datasets: Vec<String>,
}

impl fmt::Display for NotARun {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} (datasets: {}) is not a run: no dataset has the input's or the output's \
             name; --input-name/--output-name read other names",
            self.path,
            self.datasets.join(", ")
        )
    }
}

/// Groups listed as [`NotARun`] at most per archive.
const MAX_NOT_RUNS: usize = 256;

/// One run found in an archive: its metadata, or why it cannot be used.
#[derive(Debug, Clone)]
pub struct RunEntry {
    /// Group path.
    pub path: String,
    /// Metadata if the structure is sound.
    pub meta: Result<RunMeta, IngestError>,
}

/// An open campaign archive and the runs found in it.
pub struct Archive {
    file_name: String,
    file: File,
    options: IngestOptions,
    /// Runs in path order.
    pub runs: Vec<RunEntry>,
    /// Groups with datasets that are not runs (other dataset names), in path order.
    pub not_runs: Vec<NotARun>,
}

impl fmt::Debug for Archive {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Archive")
            .field("file", &self.file_name)
            .field("runs", &self.runs.len())
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

impl Archive {
    /// Opens an archive and finds its runs; per-run problems are kept in [`RunEntry::meta`].
    pub fn open(path: &Path, options: &IngestOptions) -> Result<Archive, IngestError> {
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
            file,
            options: options.clone(),
            runs: Vec::new(),
            not_runs: Vec::new(),
        };
        let mut found = Vec::new();
        let mut stats = WalkStats::default();
        archive.walk(&root, "/", 0, &mut found, &mut stats)?;
        found.sort_by(|a: &RunEntry, b| a.path.cmp(&b.path));
        if let Some(pat) = &options.run_glob {
            found.retain(|r| pat.matches(&r.path));
        }
        if found.is_empty() {
            let mut hint = String::new();
            if let Some(pat) = &options.run_glob {
                hint = format!(" matching --run-glob {pat}");
            } else if !stats.dataset_names.is_empty() {
                let names: Vec<_> = stats.dataset_names.iter().take(8).cloned().collect();
                hint = format!(" (datasets seen: {})", names.join(", "));
            }
            return Err(IngestError::NoRuns {
                file: archive.file_name.clone(),
                input: options.input_name.clone(),
                output: options.output_name.clone(),
                hint,
            });
        }
        archive.runs = found;
        stats.not_runs.sort_by(|a, b| a.path.cmp(&b.path));
        if let Some(pat) = &options.run_glob {
            stats.not_runs.retain(|g| pat.matches(&g.path));
        }
        archive.not_runs = stats.not_runs;
        Ok(archive)
    }

    /// The archive's file name as given.
    pub fn file_name(&self) -> &str {
        &self.file_name
    }

    fn corrupt(&self, run: Option<&str>, e: impl fmt::Display) -> IngestError {
        IngestError::Corrupt {
            file: self.file_name.clone(),
            run: run.map(str::to_string),
            detail: e.to_string(),
        }
    }

    fn walk(
        &self,
        group: &Group,
        path: &str,
        depth: usize,
        out: &mut Vec<RunEntry>,
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
            let meta = self.run_meta(group, path, members);
            out.push(RunEntry {
                path: path.to_string(),
                meta,
            });
            return Ok(());
        }
        let mut datasets = Vec::new();
        for name in &names {
            let child = join_path(path, name);
            match group.loc_type_by_name(name) {
                Ok(hdf5::LocationType::Group) => match group.group(name) {
                    Ok(g) => self.walk(&g, &child, depth + 1, out, stats)?,
                    Err(e) => {
                        out.push(RunEntry {
                            path: child.clone(),
                            meta: Err(self.corrupt(Some(&child), e)),
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

    fn run_meta(
        &self,
        group: &Group,
        path: &str,
        members: RunMembers,
    ) -> Result<RunMeta, IngestError> {
        let file = &self.file_name;
        let run = path.to_string();
        let attrs = InheritedAttrs::collect(&self.file, path);
        let kind = match (self.options.kind, attrs.text("kind")) {
            (Some(k), _) => k,
            (None, None) => RunKind::BaseMotion,
            (None, Some(k)) => match RunKind::parse(&k) {
                Some(k) => k,
                None => {
                    return Err(IngestError::BadAttribute {
                        file: file.clone(),
                        run,
                        name: "kind".into(),
                        value: k,
                        detail: "expected base_motion, force or free".into(),
                    })
                }
            },
        };
        if !members.output {
            return Err(IngestError::MissingOutput {
                file: file.clone(),
                run,
                input: self.options.input_name.clone(),
                output: self.options.output_name.clone(),
            });
        }
        if !members.input && kind != RunKind::Free {
            return Err(IngestError::MissingInput {
                file: file.clone(),
                run,
                input: self.options.input_name.clone(),
                output: self.options.output_name.clone(),
            });
        }
        // The option given overrides the attribute `name`.
        let quantity = |name: &str,
                        given: Option<Quantity>,
                        default: Quantity|
         -> Result<Quantity, IngestError> {
            if let Some(q) = given {
                return Ok(q);
            }
            match attrs.text(name) {
                None => Ok(default),
                Some(s) => Quantity::parse(&s).ok_or_else(|| IngestError::BadAttribute {
                    file: file.clone(),
                    run: run.clone(),
                    name: name.into(),
                    value: s.clone(),
                    detail: "expected displacement, velocity, acceleration or force".into(),
                }),
            }
        };
        let input_quantity = if kind == RunKind::Free {
            None
        } else {
            let default = if kind == RunKind::Force {
                Quantity::Force
            } else {
                Quantity::Displacement
            };
            Some(quantity(
                "input_quantity",
                self.options.input_quantity,
                default,
            )?)
        };
        let output_quantity = quantity(
            "output_quantity",
            self.options.output_quantity,
            Quantity::Displacement,
        )?;
        if output_quantity == Quantity::Force {
            return Err(IngestError::BadAttribute {
                file: file.clone(),
                run,
                name: "output_quantity".into(),
                value: "force".into(),
                detail: "the output must be a motion (displacement, velocity or acceleration)"
                    .into(),
            });
        }
        let number = |name: &str| -> Result<Option<f64>, IngestError> {
            match attrs.get(name) {
                None => Ok(None),
                Some(AttrValue::Number(x)) if x.is_finite() => Ok(Some(*x)),
                Some(v) => Err(IngestError::BadAttribute {
                    file: file.clone(),
                    run: run.clone(),
                    name: name.into(),
                    value: v.to_string(),
                    detail: "expected a finite number".into(),
                }),
            }
        };
        let inertia = match self.options.inertia {
            Some(j) => Some(j),
            None => number("inertia")?,
        };
        if let Some(j) = inertia {
            if j <= 0.0 {
                return Err(IngestError::BadAttribute {
                    file: file.clone(),
                    run,
                    name: "inertia".into(),
                    value: j.to_string(),
                    detail: "inertia must be positive (kg m^2 or kg)".into(),
                });
            }
        }
        let gravity_stiffness = number("gravity_stiffness")?.unwrap_or(0.0);
        let mode_near = number("mode_near")?;
        let mode_band = match (number("mode_fmin")?, number("mode_fmax")?) {
            (None, None) => None,
            (Some(lo), Some(hi)) if lo > 0.0 && hi > lo => Some((lo, hi)),
            (lo, hi) => return Err(IngestError::BadAttribute {
                file: file.clone(),
                run,
                name: "mode_fmin".into(),
                value: format!("{lo:?}, mode_fmax {hi:?}"),
                detail:
                    "a mode band needs both mode_fmin and mode_fmax (Hz), 0 < mode_fmin < mode_fmax"
                        .into(),
            }),
        };

        let samples = self.signal_len(group, path, &self.options.output_name)?;
        if members.input && kind != RunKind::Free {
            let n_in = self.signal_len(group, path, &self.options.input_name)?;
            if n_in != samples {
                return Err(IngestError::LengthMismatch {
                    file: file.clone(),
                    run,
                    a_name: self.options.input_name.clone(),
                    a_len: n_in,
                    b_name: self.options.output_name.clone(),
                    b_len: samples,
                });
            }
        }
        let sample_rate = self.sample_rate(group, path, &attrs, samples, members.time)?;
        if samples < MIN_SAMPLES {
            return Err(IngestError::TooShort {
                file: file.clone(),
                run,
                samples,
                min: MIN_SAMPLES,
            });
        }
        let attributes = all_attrs(group)
            .into_iter()
            .map(|(k, v)| (k, v.to_string()))
            .collect();
        Ok(RunMeta {
            path: run,
            samples,
            sample_rate,
            duration: samples as f64 / sample_rate,
            kind,
            input_quantity,
            output_quantity,
            inertia,
            gravity_stiffness,
            units: attrs.text("units"),
            excitation: attrs.text("excitation"),
            attributes,
            mode_band,
            mode_near,
        })
    }

    /// Length of a signal (`NAME` or `NAME[k]`, see [`channel_name`]) of `group`, checking
    /// shape and type.
    fn signal_len(&self, group: &Group, run: &str, name: &str) -> Result<usize, IngestError> {
        let (base, channel) = channel_name(name);
        let ds = group
            .dataset(base)
            .map_err(|e| self.corrupt(Some(run), e))?;
        let shape = ds.get_shape().map_err(|e| self.corrupt(Some(run), e))?;
        let not_1d = || IngestError::NotOneD {
            file: self.file_name.clone(),
            run: run.to_string(),
            dataset: name.to_string(),
            shape: shape.clone(),
        };
        let len = match channel {
            None if shape.is_empty() || shape.iter().filter(|&&d| d > 1).count() > 1 => {
                return Err(not_1d())
            }
            None => shape.iter().product(),
            Some(k) => match channel_axis(&shape) {
                Some((axis, n)) if k < shape[axis] => n,
                _ => return Err(not_1d()),
            },
        };
        let desc = ds
            .dtype()
            .and_then(|d| d.to_descriptor())
            .map_err(|e| self.corrupt(Some(run), e))?;
        match desc {
            TypeDescriptor::Float(_) | TypeDescriptor::Integer(_) | TypeDescriptor::Unsigned(_) => {
            }
            other => {
                return Err(IngestError::UnsupportedType {
                    file: self.file_name.clone(),
                    run: run.to_string(),
                    dataset: name.to_string(),
                    dtype: other.to_string(),
                })
            }
        }
        Ok(len)
    }

    fn sample_rate(
        &self,
        group: &Group,
        path: &str,
        attrs: &InheritedAttrs,
        samples: usize,
        has_time: bool,
    ) -> Result<f64, IngestError> {
        let file = self.file_name.clone();
        let run = path.to_string();
        if let Some(fs) = self.options.sample_rate {
            return check_rate(fs, &file, &run);
        }
        let from_attr = match attrs.get("sample_rate") {
            None => None,
            Some(AttrValue::Number(x)) => Some(check_rate(*x, &file, &run)?),
            Some(v) => {
                return Err(IngestError::BadAttribute {
                    file,
                    run,
                    name: "sample_rate".into(),
                    value: v.to_string(),
                    detail: "expected a number in Hz".into(),
                })
            }
        };
        if !has_time {
            if let Some(fs) = from_attr {
                return Ok(fs);
            }
            return match self.rate_variable(group) {
                Some(fs) => check_rate(fs, &file, &run),
                None => Err(IngestError::MissingSampleRate { file, run }),
            };
        }
        let n = self.signal_len(group, path, "time")?;
        let ds = group
            .dataset("time")
            .map_err(|e| self.corrupt(Some(path), e))?;
        if n != samples {
            return Err(IngestError::LengthMismatch {
                file,
                run,
                a_name: "time".into(),
                a_len: n,
                b_name: self.options.output_name.clone(),
                b_len: samples,
            });
        }
        let t: Vec<f64> = ds
            .read_raw::<f64>()
            .map_err(|e| self.corrupt(Some(path), e))?;
        let fs_time = time_sample_rate(&t).map_err(|detail| IngestError::NonUniformTime {
            file: file.clone(),
            run: run.clone(),
            detail,
        })?;
        if let Some(fs) = from_attr {
            if ((fs - fs_time) / fs).abs() > 1e-4 {
                return Err(IngestError::BadAttribute {
                    file,
                    run,
                    name: "sample_rate".into(),
                    value: fs.to_string(),
                    detail: format!(
                        "disagrees with the `time` dataset, which gives {fs_time:.6} Hz; fix one, or pass --sample-rate"
                    ),
                });
            }
        }
        Ok(fs_time)
    }

    /// A sample rate saved as a scalar variable (`Fs`, …) in the run's group or, for a
    /// run at the root, at the root.
    fn rate_variable(&self, group: &Group) -> Option<f64> {
        RATE_VARIABLES.iter().find_map(|name| {
            let ds = group.dataset(name).ok()?;
            let shape = ds.get_shape().ok()?;
            if shape.iter().product::<usize>() != 1 {
                return None;
            }
            ds.read_raw::<f64>().ok()?.first().copied()
        })
    }

    /// Reads a run's samples, applying `scale` and checking for NaN/Inf.
    pub fn load(&self, meta: &RunMeta) -> Result<Run, IngestError> {
        let group = self
            .file
            .group(&meta.path)
            .map_err(|e| self.corrupt(Some(&meta.path), e))?;
        let output = self.read_signal(&group, meta, &self.options.output_name)?;
        let input = match meta.kind {
            RunKind::Free => None,
            _ => Some(self.read_signal(&group, meta, &self.options.input_name)?),
        };
        Ok(Run {
            meta: meta.clone(),
            input,
            output,
        })
    }

    /// Reads every run, each to its own result.
    pub fn load_all(&self) -> Vec<(String, Result<Run, IngestError>)> {
        self.runs
            .iter()
            .map(|entry| {
                let run = match &entry.meta {
                    Ok(meta) => self.load(meta),
                    Err(e) => Err(e.clone()),
                };
                (entry.path.clone(), run)
            })
            .collect()
    }

    fn read_signal(
        &self,
        group: &Group,
        meta: &RunMeta,
        name: &str,
    ) -> Result<Vec<f64>, IngestError> {
        let (base, channel) = channel_name(name);
        let ds = group
            .dataset(base)
            .map_err(|e| self.corrupt(Some(&meta.path), e))?;
        let desc = ds
            .dtype()
            .and_then(|d| d.to_descriptor())
            .map_err(|e| self.corrupt(Some(&meta.path), e))?;
        let mut v: Vec<f64> = ds
            .read_raw::<f64>()
            .map_err(|e| self.corrupt(Some(&meta.path), e))?;
        if let Some(k) = channel {
            // One row or column of a 2-D dataset (row-major as read).
            let shape = ds
                .get_shape()
                .map_err(|e| self.corrupt(Some(&meta.path), e))?;
            v = match channel_axis(&shape) {
                Some((0, n)) => v[k * n..(k + 1) * n].to_vec(),
                Some((_, n)) => (0..n).map(|i| v[i * shape[1] + k]).collect(),
                None => return Err(self.corrupt(Some(&meta.path), "not a 2-D dataset")),
            };
        }
        if v.len() != meta.samples {
            return Err(self.corrupt(
                Some(&meta.path),
                format!(
                    "dataset `{name}` returned {} of {} samples",
                    v.len(),
                    meta.samples
                ),
            ));
        }
        let is_int = matches!(
            desc,
            TypeDescriptor::Integer(_) | TypeDescriptor::Unsigned(_)
        );
        if is_int {
            // Counts become physical values via `scale` on the dataset (or the run group).
            let scale = attr_number(&ds, "scale").or_else(|| attr_number(group, "scale"));
            match scale {
                Some(s) if s.is_finite() && s != 0.0 => v.iter_mut().for_each(|x| *x *= s),
                Some(s) => {
                    return Err(IngestError::BadAttribute {
                        file: self.file_name.clone(),
                        run: meta.path.clone(),
                        name: "scale".into(),
                        value: s.to_string(),
                        detail: "scale must be finite and non-zero".into(),
                    })
                }
                None => {
                    return Err(IngestError::UnsupportedType {
                        file: self.file_name.clone(),
                        run: meta.path.clone(),
                        dataset: name.to_string(),
                        dtype: format!(
                            "{desc} without a `scale` attribute (value = count x scale)"
                        ),
                    })
                }
            }
        }
        let mut count = 0;
        let mut first = None;
        for (i, x) in v.iter().enumerate() {
            if !x.is_finite() {
                count += 1;
                first.get_or_insert(i);
            }
        }
        if let Some(first) = first {
            return Err(IngestError::NonFinite {
                file: self.file_name.clone(),
                run: meta.path.clone(),
                dataset: name.to_string(),
                count,
                first,
                first_time: first as f64 / meta.sample_rate,
            });
        }
        Ok(v)
    }
}

/// For a 2-D shape: the axis that counts channels (the shorter one) and the length of the
/// other (samples).
fn channel_axis(shape: &[usize]) -> Option<(usize, usize)> {
    match *shape {
        [a, b] if a <= b => Some((0, b)),
        [a, _] => Some((1, a)),
        _ => None,
    }
}

fn check_rate(fs: f64, file: &str, run: &str) -> Result<f64, IngestError> {
    if fs.is_finite() && fs > 0.0 {
        Ok(fs)
    } else {
        Err(IngestError::BadSampleRate {
            file: file.to_string(),
            run: run.to_string(),
            value: fs,
        })
    }
}

/// Sample rate implied by a time vector, or why it is not uniform.
pub fn time_sample_rate(t: &[f64]) -> Result<f64, String> {
    if t.len() < 2 {
        return Err("fewer than two time stamps".into());
    }
    if let Some(i) = t.iter().position(|x| !x.is_finite()) {
        return Err(format!("time[{i}] is not finite"));
    }
    let span = t[t.len() - 1] - t[0];
    let dt = span / (t.len() - 1) as f64;
    if dt <= 0.0 {
        return Err("time does not increase".into());
    }
    for i in 1..t.len() {
        let step = t[i] - t[i - 1];
        if step <= 0.0 {
            return Err(format!(
                "not strictly increasing at sample {i} (t = {} s after {} s)",
                t[i],
                t[i - 1]
            ));
        }
        let jitter = (step - dt).abs() / dt;
        if jitter > MAX_TIME_JITTER {
            return Err(format!(
                "step {step:e} s at sample {i} differs from the mean step {dt:e} s by {:.2e} (relative; limit {MAX_TIME_JITTER:e})",
                jitter
            ));
        }
    }
    Ok(1.0 / dt)
}

fn attr_number(loc: &Location, name: &str) -> Option<f64> {
    let a = loc.attr(name).ok()?;
    match read_attr(&a) {
        Ok(AttrValue::Number(x)) => Some(x),
        _ => None,
    }
}

fn is_dataset(group: &Group, name: &str) -> bool {
    matches!(
        group.loc_type_by_name(name),
        Ok(hdf5::LocationType::Dataset)
    )
}

fn join_path(parent: &str, name: &str) -> String {
    if parent == "/" {
        format!("/{name}")
    } else {
        format!("{parent}/{name}")
    }
}

/// Which of a run group's datasets exist, found once while walking the file.
#[derive(Clone, Copy)]
struct RunMembers {
    input: bool,
    output: bool,
    time: bool,
}

#[derive(Default)]
struct WalkStats {
    dataset_names: Vec<String>,
    not_runs: Vec<NotARun>,
}

/// The known attributes of a run, each taken from the run group or its nearest ancestor.
struct InheritedAttrs {
    values: BTreeMap<String, AttrValue>,
}

const INHERITED: &[&str] = &[
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
];

impl InheritedAttrs {
    fn collect(file: &File, path: &str) -> Self {
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

    fn get(&self, name: &str) -> Option<&AttrValue> {
        self.values.get(name)
    }

    fn text(&self, name: &str) -> Option<String> {
        self.values.get(name).map(|v| v.to_string())
    }
}

/// Expands command-line arguments (files, folders searched recursively for `.h5`, `.hdf5`,
/// `.mat`, and glob patterns) to a sorted, de-duplicated list of files.
pub fn expand_inputs(args: &[String]) -> Result<Vec<PathBuf>, String> {
    let mut out = Vec::new();
    for a in args {
        let p = Path::new(a);
        if p.is_dir() {
            collect_dir(p, &mut out).map_err(|e| format!("{a}: cannot list folder: {e}"))?;
        } else if p.exists() {
            out.push(p.to_path_buf());
        } else if a.contains(['*', '?', '[']) {
            let paths = glob::glob(a).map_err(|e| format!("{a}: bad glob pattern: {e}"))?;
            let before = out.len();
            for entry in paths.flatten() {
                if entry.is_dir() {
                    collect_dir(&entry, &mut out)
                        .map_err(|e| format!("{}: {e}", entry.display()))?;
                } else {
                    out.push(entry);
                }
            }
            if out.len() == before {
                return Err(format!("{a}: the pattern matches no file"));
            }
        } else {
            return Err(format!("{a}: no such file or folder"));
        }
    }
    out.sort();
    out.dedup();
    Ok(out)
}

/// No archive among the inputs: what was looked at and what was there instead.
#[derive(Debug, thiserror::Error)]
#[error(
    "no campaign archive found: {0}; pass .h5, .hdf5, .he5 or .mat files, folders holding \
     them, or a glob (nothing was done)"
)]
pub struct NothingFound(pub String);

/// [`expand_inputs`], refusing an empty result with what each argument held instead.
pub fn find_archives(args: &[String]) -> Result<Vec<PathBuf>, FindError> {
    let files = expand_inputs(args).map_err(FindError::Bad)?;
    if !files.is_empty() {
        return Ok(files);
    }
    let seen: Vec<String> = args
        .iter()
        .map(|a| {
            let mut others = Vec::new();
            let _ = list_files(Path::new(a), &mut others);
            match others.len() {
                0 => format!("{a} is an empty folder"),
                n => {
                    let names: Vec<String> = others
                        .iter()
                        .take(3)
                        .map(|p| p.display().to_string())
                        .collect();
                    format!(
                        "{a} holds {n} other file(s) ({}{})",
                        names.join(", "),
                        if n > 3 { ", …" } else { "" }
                    )
                }
            }
        })
        .collect();
    Err(FindError::Nothing(NothingFound(seen.join("; "))))
}

/// Why [`find_archives`] found nothing to read.
#[derive(Debug, thiserror::Error)]
pub enum FindError {
    /// A missing path or a bad pattern.
    #[error("{0}")]
    Bad(String),
    /// Inputs that exist but hold no archive.
    #[error(transparent)]
    Nothing(#[from] NothingFound),
}

/// Every file below `dir`, whatever its extension (to say what a folder held instead).
fn list_files(dir: &Path, out: &mut Vec<PathBuf>) -> std::io::Result<()> {
    for e in std::fs::read_dir(dir)?.flatten() {
        let p = e.path();
        if p.is_dir() {
            list_files(&p, out)?;
        } else {
            out.push(p);
        }
    }
    Ok(())
}

fn collect_dir(dir: &Path, out: &mut Vec<PathBuf>) -> std::io::Result<()> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)?
        .flatten()
        .map(|e| e.path())
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            collect_dir(&p, out)?;
        } else if matches!(
            p.extension()
                .and_then(|e| e.to_str())
                .map(|e| e.to_ascii_lowercase())
                .as_deref(),
            Some("h5" | "hdf5" | "he5" | "mat")
        ) {
            out.push(p);
        }
    }
    Ok(())
}
