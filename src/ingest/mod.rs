//! Campaign ingestion: finds the runs of a `skelid-campaign/1` HDF5 archive (FORMATS.md §1),
//! resolves their attributes and loads their signals, with one specific error per way an
//! archive can be wrong.
//!
//! File-level failures (not HDF5, empty, corrupt, no runs) are `Err` from [`Archive::open`];
//! a bad run never hides the others: it is listed with its own [`IngestError`].

use std::fmt;

use serde::Serialize;

use crate::hint::Hint;
pub use crate::run::{Quantity, Run, RunKind, RunMeta};

mod archive;
mod files;
mod load;
pub use load::{read_placed, FileStamp, Placed, PlacedRun};
mod meta;

pub use archive::{Archive, Listed};
use archive::{InheritedAttrs, RunMembers};
pub use files::{expand_inputs, find_archives, passed_over_note, FindError, Inputs, NothingFound};
pub use meta::time_sample_rate;
use meta::{attr_number, channel_axis};

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
    #[error("{file}: no runs found: no group holds datasets named `{input}` and `{output}` (or `{output}` alone with kind = \"free\"){hint}; use {} (NAME[k] picks channel k of a matrix), {} and {} for other layouts", Hint::ChannelNames, Hint::Kind, Hint::RunGlob)]
    NoRuns {
        file: String,
        input: String,
        output: String,
        hint: String,
    },
    /// Neither a `sample_rate` attribute nor a `time` dataset, nor `--sample-rate`.
    #[error("{file}: run {run}: no sample rate: add a `sample_rate` attribute (Hz) to the run or a parent group, a `time` dataset, or pass {}", Hint::SampleRate)]
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
    #[error("{file}: run {run}: non-uniform time: {detail}; skelid needs uniformly sampled signals (resample first, or drop `time` and pass {})", Hint::SampleRate)]
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

pub(super) fn run_part(run: &Option<String>) -> String {
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
pub(super) const RATE_VARIABLES: [&str; 7] = [
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
             name; {} read other names",
            self.path,
            self.datasets.join(", "),
            Hint::ChannelNames
        )
    }
}

/// Groups listed as [`NotARun`] at most per archive.
pub(super) const MAX_NOT_RUNS: usize = 256;

/// One run found in an archive: its metadata, or why it cannot be used.
#[derive(Debug, Clone)]
pub struct RunEntry {
    /// Group path.
    pub path: String,
    /// Metadata if the structure is sound.
    pub meta: Result<RunMeta, IngestError>,
}
