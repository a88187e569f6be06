//! The batch's crash-safe record: every finished run is committed as its own small HDF5
//! file `<out>/runs/<key>.h5` (written beside, then renamed, so a run is either wholly
//! there or absent), keyed by a hash of the run's content and the settings. A rerun skips
//! the keys it finds; `results.h5` is assembled from these files and renamed into place, so
//! it is never seen half-written either.

use std::path::{Path, PathBuf};

use crate::identify::IdentifyOptions;
use crate::ingest::Run;
use crate::report::encoded::EncodedRun;
use crate::report::{encode_run, summary_rows, ReportError, ResultsWriter, RunOutcome, SummaryRow};
use crate::track::Method;

/// Folder of the committed runs inside the output folder.
pub const RUNS_DIR: &str = "runs";

/// Hash of everything that changes a run's result besides its data: the skelid version,
/// the methods and the identification options.
pub fn settings_fingerprint(methods: &[Method], options: &IdentifyOptions) -> String {
    let mut h = blake3::Hasher::new();
    h.update(env!("CARGO_PKG_VERSION").as_bytes());
    for m in methods {
        h.update(m.as_str().as_bytes());
        h.update(b"\0");
    }
    // Debug output names every field and value: a changed option changes the key.
    h.update(format!("{options:?}").as_bytes());
    h.finalize().to_hex()[..32].to_string()
}

/// The key of one run: its archive's file name, its path, metadata and samples, and the
/// settings.
pub fn run_key(run: &Run, source: &str, settings: &str) -> String {
    let mut h = blake3::Hasher::new();
    h.update(settings.as_bytes());
    h.update(base_name(source).as_bytes());
    h.update(b"\0");
    h.update(run.meta.path.as_bytes());
    h.update(b"\0");
    h.update(format!("{:?}", run.meta).as_bytes());
    if let Some(x) = &run.input {
        h.update(bytemuck::cast_slice(x));
    }
    h.update(b"\0output\0");
    h.update(bytemuck::cast_slice(&run.output));
    h.finalize().to_hex()[..32].to_string()
}

/// The key of a run that could not be read: its archive, path and error, and the settings.
pub fn failed_key(source: &str, path: &str, error: &str, settings: &str) -> String {
    let mut h = blake3::Hasher::new();
    for part in [settings, base_name(source), path, error] {
        h.update(part.as_bytes());
        h.update(b"\0");
    }
    h.finalize().to_hex()[..32].to_string()
}

/// The file name of an archive path (the folder it was given from does not matter).
pub fn base_name(source: &str) -> &str {
    source.rsplit('/').next().unwrap_or(source)
}

/// A committed run: its key and the summary rows stored with it.
#[derive(Debug, Clone)]
pub struct Entry {
    /// Content-and-settings key.
    pub key: String,
    /// Run path inside its archive.
    pub path: String,
    /// Archive file name.
    pub source: String,
    /// Whether the run failed.
    pub failed: bool,
    /// Its rows of summary.json.
    pub rows: Vec<SummaryRow>,
}

/// Where each of `entries` goes in results.h5: its own path, or `PATH@ARCHIVE` for the
/// second and later runs of the same path from different archives.
pub fn placements(entries: &[Entry]) -> Vec<String> {
    let mut seen = std::collections::HashSet::new();
    entries
        .iter()
        .map(|e| {
            if seen.insert(e.path.as_str()) {
                e.path.clone()
            } else {
                format!("{}@{}", e.path, e.source)
            }
        })
        .collect()
}

/// A finished run made ready for its commit: results encoded (compressed) and summary rows
/// computed, all CPU work, so a batch's workers do it and the writer only writes.
pub struct Prepared {
    encoded: EncodedRun,
    rows: Vec<SummaryRow>,
    path: String,
    source: String,
    failed: bool,
}

impl Prepared {
    /// The run's group path.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// The run's archive.
    pub fn source(&self) -> &str {
        &self.source
    }

    /// The run's results, encoded.
    pub fn encoded(&self) -> &EncodedRun {
        &self.encoded
    }

    /// Encodes `outcome` and computes its summary rows.
    pub fn new(outcome: &RunOutcome) -> Prepared {
        Prepared {
            encoded: encode_run(outcome),
            rows: summary_rows(outcome),
            path: outcome.path.clone(),
            source: outcome.source.clone(),
            failed: outcome.status() == "failed",
        }
    }
}

/// The committed runs of one output folder.
pub struct Journal {
    dir: PathBuf,
}

impl Journal {
    /// Opens (creating) `<out>/runs`.
    pub fn open(out: &Path) -> Result<Journal, ReportError> {
        let dir = out.join(RUNS_DIR);
        std::fs::create_dir_all(&dir).map_err(|e| ReportError {
            file: dir.display().to_string(),
            detail: e.to_string(),
        })?;
        Ok(Journal { dir })
    }

    /// The file of a key.
    pub fn file(&self, key: &str) -> PathBuf {
        self.dir.join(format!("{key}.h5"))
    }

    /// The committed entry of `key`, if any. A file that cannot be read (it cannot be
    /// half-written, but it can be damaged by hand) counts as absent and is redone.
    pub fn lookup(&self, key: &str) -> Option<Entry> {
        let f = self.file(key);
        if !f.exists() {
            return None;
        }
        let file = hdf5::File::open(&f).ok()?;
        let text = |name: &str| -> Option<String> {
            let a = file.attr(name).ok()?;
            let s: hdf5::types::VarLenUnicode = a.read_scalar().ok()?;
            Some(s.as_str().to_string())
        };
        let rows: Vec<SummaryRow> = serde_json::from_str(&text("summary")?).ok()?;
        Some(Entry {
            key: key.to_string(),
            path: text("run")?,
            source: text("run_source")?,
            failed: text("run_status")? == "failed",
            rows,
        })
    }

    /// Commits a run prepared by [`Prepared::new`] (on any thread) under `key`: written to
    /// a temporary file, then renamed. Only the HDF5 writing is left here, under libhdf5's
    /// lock.
    pub fn commit(&self, key: &str, run: Prepared) -> Result<Entry, ReportError> {
        let w = ResultsWriter::create_at(&self.file(key))?;
        w.write_encoded(&run.encoded)?;
        let summary = serde_json::to_string(&run.rows).map_err(|e| ReportError {
            file: self.file(key).display().to_string(),
            detail: e.to_string(),
        })?;
        for (name, value) in [
            ("run", run.path.as_str()),
            ("run_source", run.source.as_str()),
            ("run_status", if run.failed { "failed" } else { "ok" }),
            ("summary", summary.as_str()),
        ] {
            w.set_root_attr(name, value)?;
        }
        w.finish()?;
        Ok(Entry {
            key: key.to_string(),
            path: run.path,
            source: run.source,
            failed: run.failed,
            rows: run.rows,
        })
    }

    /// Writes `<out>/results.h5` holding the runs of `entries` (copied from their files),
    /// through a temporary file renamed into place. Two runs with the same path from
    /// different archives: the second goes to `PATH@ARCHIVE`.
    pub fn assemble(&self, out: &Path, entries: &[Entry]) -> Result<PathBuf, ReportError> {
        let w = ResultsWriter::create(out)?;
        for (e, dst) in entries.iter().zip(placements(entries)) {
            w.copy_run_from(&self.file(&e.key), &e.path, &dst)?;
        }
        w.finish()
    }
}
