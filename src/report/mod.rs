//! Output files for people and other programs: tracks (FORMATS.md §4), identification
//! results and summaries (FORMATS.md §3).

mod direct;
pub mod encoded;
pub mod figure_files;
mod hdf5_format;
pub mod html;
mod results;
pub mod schema;
mod sink;
mod summary;
mod track_file;

pub use direct::{DirectWriter, PlacedData, Placer};
pub use results::ResultsWriter;
pub use schema::{encode_run, parameters, ABSOLUTE_NAMES, MODE_NAMES, PARAMETER_NAMES};
pub use sink::ResultsFile;
pub use summary::{summary_rows, write_summary, SummaryRow};
pub use track_file::write_track;

use std::path::Path;

use crate::campaign::tmp_path;
use crate::identify::Identification;
use crate::track::Method;

/// How a run (or one method of it) ended: results.h5's `status`, the summaries' and the
/// manifest's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Identified (a run: by at least one method).
    Ok,
    /// Not identified; the error says why.
    Failed,
}

impl Status {
    /// The name written to the files.
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Ok => "ok",
            Status::Failed => "failed",
        }
    }

    /// A status as stored: `ok`, else failed (a run without one never finished).
    pub fn parse(text: Option<&str>) -> Status {
        match text {
            Some("ok") => Status::Ok,
            _ => Status::Failed,
        }
    }
}

impl std::fmt::Display for Status {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Why an output file could not be written.
#[derive(Debug, thiserror::Error)]
#[error("{file}: cannot write: {detail}")]
pub struct ReportError {
    /// Output path.
    pub file: String,
    /// What went wrong.
    pub detail: String,
}

/// What `run` did with one run of an archive: per method the identification or its error.
#[derive(Debug)]
pub struct RunOutcome {
    /// Run path in the archive.
    pub path: String,
    /// Archive file name.
    pub source: String,
    /// Sample rate (Hz), when the run could be read.
    pub sample_rate: Option<f64>,
    /// Samples, when the run could be read.
    pub samples: usize,
    /// Inertia attribute (J or m), when given.
    pub inertia: Option<f64>,
    /// The units of the run's results (from its `units`, `kind` and quantities).
    pub units: crate::units::Units,
    /// The simulation-refined estimates, when asked for (`--refine`), or why there are none.
    pub refined: Option<Result<crate::refine::Refined, String>>,
    /// Why the run could not be read at all.
    pub error: Option<String>,
    /// Per method: the result (or its error) and the seconds it took.
    pub methods: Vec<(Method, Result<Identification, String>, f64)>,
}

impl RunOutcome {
    /// The verdict on each method's result, in `methods` order (`None` where it failed),
    /// and the method whose estimate to read ([`crate::quality`]).
    pub fn qualities(&self) -> (Vec<Option<crate::quality::Quality>>, Option<Method>) {
        let results: Vec<(Method, Option<&Identification>)> = self
            .methods
            .iter()
            .map(|(m, r, _)| (*m, r.as_ref().ok()))
            .collect();
        let judged = crate::quality::judge(&results, &self.units.displacement);
        let pairs: Vec<(Method, Option<crate::quality::Quality>)> = self
            .methods
            .iter()
            .map(|m| m.0)
            .zip(judged.iter().cloned())
            .collect();
        (judged, crate::quality::recommend(&pairs))
    }

    /// `gpu` when the GPU did the transform's first pass of every wavelet track of this
    /// run, else `cpu` (the Hilbert method, the CPU backend, or a fallback).
    pub fn backend(&self) -> &'static str {
        let mut tracks = self
            .methods
            .iter()
            .filter_map(|(m, r, _)| (*m == Method::Wavelet).then_some(r.as_ref().ok()?))
            .flat_map(|id| id.input.iter().chain(std::iter::once(&id.response)))
            .peekable();
        if tracks.peek().is_some() && tracks.all(|t| t.backend == crate::track::Device::Gpu) {
            "gpu"
        } else {
            "cpu"
        }
    }

    /// A run not yet read: no data, no error, no method results.
    pub fn new(path: String, source: String) -> RunOutcome {
        RunOutcome {
            path,
            source,
            sample_rate: None,
            samples: 0,
            inertia: None,
            units: Default::default(),
            refined: None,
            error: None,
            methods: Vec::new(),
        }
    }

    /// `Ok` when at least one method identified the run.
    pub fn status(&self) -> Status {
        if self.error.is_none() && self.methods.iter().any(|m| m.1.is_ok()) {
            Status::Ok
        } else {
            Status::Failed
        }
    }

    /// The run's error text: the read error, or every method's error.
    pub fn error_text(&self) -> Option<String> {
        if let Some(e) = &self.error {
            return Some(e.clone());
        }
        let errs: Vec<String> = self
            .methods
            .iter()
            .filter_map(|(m, r, _)| r.as_ref().err().map(|e| format!("{}: {e}", m.as_str())))
            .collect();
        (!errs.is_empty()).then(|| errs.join("; "))
    }
}

/// Writes a file through a temporary file renamed into place.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ReportError> {
    write_atomic_inner(path, bytes, false)
}

/// [`write_atomic`] for a file that will not be read again soon (a journal's run file):
/// its pages are released from the page cache once on disk ([`crate::pagecache`]).
pub fn write_atomic_released(path: &Path, bytes: &[u8]) -> Result<(), ReportError> {
    write_atomic_inner(path, bytes, true)
}

fn write_atomic_inner(path: &Path, bytes: &[u8], release: bool) -> Result<(), ReportError> {
    let err = |detail: String| ReportError {
        file: path.display().to_string(),
        detail,
    };
    let tmp = tmp_path(path);
    let written = if release {
        crate::pagecache::write_new_file(&tmp, bytes)
    } else {
        std::fs::write(&tmp, bytes)
    };
    let done = written
        .and_then(|()| std::fs::rename(&tmp, path))
        .map_err(|e| err(e.to_string()));
    if done.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    done
}

#[cfg(test)]
mod tests {
    use super::encoded::EncodedRun;
    use super::*;
    use hdf5::types::VarLenUnicode;

    /// The writer creates attributes and the later datasets of a layout with raw libhdf5
    /// calls; what a reader finds must be what the binding's builders make: the same
    /// types, chunking, filters and values.
    #[test]
    fn raw_created_attributes_and_datasets_match_the_binding_s() {
        // A whole chunk and part of one, read back by libhdf5: each a zlib stream of byte
        // planes, the cosine's low ones (noise to deflate) stored, the others deflated.
        let x: Vec<f64> = (0..40_000).map(|i| (i as f64 * 0.003).cos()).collect();
        let mask: Vec<u8> = (0..40_000).map(|i| u8::from(i % 3 == 0)).collect();
        let run = |path: &str, scale: f64| {
            let mut e = EncodedRun::new(path);
            e.str_attr("", "status", Status::Ok.as_str());
            e.f64_attr("", "sample_rate", 1000.0);
            e.group("wavelet");
            e.group("wavelet/skeleton");
            let v: Vec<f64> = x.iter().map(|a| a * scale).collect();
            e.signal("wavelet", "response_amplitude", &v, true);
            e.dataset_attr("wavelet", "response_amplitude", "units", "rad");
            e.signal("wavelet", "response_frequency", &v, true);
            e.bytes("wavelet", "valid", &mask, 4);
            e.signal("wavelet/skeleton", "amplitude", &v[..12], false);
            e.str_attr("wavelet", "clearance_units", "rad · ü");
            e
        };
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("r.h5");
        let w = ResultsWriter::create_at(&file).unwrap();
        // The first run's datasets go through the builders, the second's are raw.
        for (path, scale) in [("/runs/a", 1.0), ("/runs/b", 2.0)] {
            w.write_encoded(&run(path, scale)).unwrap();
        }
        w.finish().unwrap();
        let f = hdf5::File::open(&file).unwrap();
        let layout = |p: &str| {
            let d = f.dataset(p).unwrap();
            let filters = d.filters();
            (d.chunk(), d.shape(), d.dtype().unwrap().size(), filters)
        };
        for name in ["response_amplitude", "response_frequency", "valid"] {
            let (a, b) = (
                format!("/runs/a/wavelet/{name}"),
                format!("/runs/b/wavelet/{name}"),
            );
            assert_eq!(
                format!("{:?}", layout(&a)),
                format!("{:?}", layout(&b)),
                "{name}"
            );
        }
        assert_eq!(
            format!("{:?}", layout("/runs/a/wavelet/skeleton/amplitude")),
            format!("{:?}", layout("/runs/b/wavelet/skeleton/amplitude"))
        );
        let plain: Vec<f64> = f
            .dataset("/runs/b/wavelet/skeleton/amplitude")
            .unwrap()
            .read_raw()
            .unwrap();
        assert_eq!(plain, x[..12].iter().map(|a| a * 2.0).collect::<Vec<_>>());
        let (chunk, _, _, filters) = layout("/runs/b/wavelet/response_amplitude");
        assert_eq!(chunk, Some(vec![encoded::CHUNK]));
        assert_eq!(filters.len(), 2, "shuffle and deflate: {filters:?}");
        let back: Vec<f64> = f
            .dataset("/runs/b/wavelet/response_amplitude")
            .unwrap()
            .read_raw()
            .unwrap();
        assert_eq!(back, x.iter().map(|a| a * 2.0).collect::<Vec<_>>());
        let valid: Vec<u8> = f
            .dataset("/runs/b/wavelet/valid")
            .unwrap()
            .read_raw()
            .unwrap();
        assert_eq!(valid, mask);
        let g = f.group("/runs/b/wavelet").unwrap();
        let text: VarLenUnicode = g.attr("clearance_units").unwrap().read_scalar().unwrap();
        assert_eq!(text.as_str(), "rad · ü");
        let units: VarLenUnicode = g
            .dataset("response_amplitude")
            .unwrap()
            .attr("units")
            .unwrap()
            .read_scalar()
            .unwrap();
        assert_eq!(units.as_str(), "rad");
        let fs: f64 = f
            .group("/runs/b")
            .unwrap()
            .attr("sample_rate")
            .unwrap()
            .read_scalar()
            .unwrap();
        assert_eq!(fs, 1000.0);
        assert_eq!(
            crate::h5util::read_attr(&g.attr("clearance_units").unwrap()).unwrap(),
            crate::h5util::AttrValue::Text("rad · ü".into())
        );
    }
}
