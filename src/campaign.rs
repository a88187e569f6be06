//! Writing campaign archives in the `skelid-campaign/1` layout (FORMATS.md §1), used by the
//! simulator, the demo and the tests.
//!
//! Files are written under a temporary name and renamed into place when complete, so a
//! crash never leaves a half-written archive where a finished one is expected.

use std::path::{Path, PathBuf};

use crate::h5util::{write_f64_attr, write_str_attr};
use crate::run::{Quantity, RunKind};

/// Format string stored in the root attribute `format`.
pub const CAMPAIGN_FORMAT: &str = "skelid-campaign/1";

/// An attribute value to write.
#[derive(Debug, Clone, PartialEq)]
pub enum Attr {
    /// Float attribute.
    Num(f64),
    /// String attribute.
    Text(String),
}

/// One run to write.
#[derive(Debug, Clone)]
pub struct RunData {
    /// Group path, e.g. `/runs/run_001`.
    pub path: String,
    /// Input channel, absent for free decays.
    pub input: Option<Vec<f64>>,
    /// Output channel.
    pub output: Vec<f64>,
    /// Sample rate, Hz (written as the run's `sample_rate` attribute).
    pub sample_rate: f64,
    /// Run kind.
    pub kind: RunKind,
    /// Input quantity (`None`: the kind's default).
    pub input_quantity: Option<Quantity>,
    /// Output quantity.
    pub output_quantity: Quantity,
    /// Further attributes (inertia, units, true parameters, ...).
    pub attrs: Vec<(String, Attr)>,
}

impl RunData {
    /// The run as ingest would read it back from an archive, without the round trip
    /// through a file (the inertia and gravity stiffness taken from the attributes).
    pub fn into_run(self) -> crate::run::Run {
        let num = |name: &str| {
            self.attrs.iter().find_map(|(k, v)| match v {
                Attr::Num(x) if k == name => Some(*x),
                _ => None,
            })
        };
        let attributes = self
            .attrs
            .iter()
            .map(|(k, v)| {
                let text = match v {
                    Attr::Num(x) => x.to_string(),
                    Attr::Text(t) => t.clone(),
                };
                (k.clone(), text)
            })
            .collect();
        let n = self.output.len();
        crate::run::Run {
            meta: crate::run::RunMeta {
                path: self.path.clone(),
                samples: n,
                sample_rate: self.sample_rate,
                duration: n as f64 / self.sample_rate,
                kind: self.kind,
                input_quantity: self.input_quantity,
                output_quantity: self.output_quantity,
                inertia: num("inertia"),
                gravity_stiffness: num("gravity_stiffness").unwrap_or(0.0),
                units: None,
                excitation: None,
                attributes,
                mode_band: None,
                mode_near: None,
                zero_tolerance: num("zero_tolerance").unwrap_or(0.0),
            },
            input: self.input,
            output: self.output,
        }
    }
}

/// Error writing an archive.
#[derive(Debug, thiserror::Error)]
#[error("{file}: cannot write campaign archive: {detail}")]
pub struct WriteError {
    /// Target file.
    pub file: String,
    /// What failed.
    pub detail: String,
}

/// Writes a complete campaign archive atomically (temporary file, then rename).
pub fn write_campaign(
    path: &Path,
    root_attrs: &[(String, Attr)],
    runs: &[RunData],
    compress: bool,
) -> Result<(), WriteError> {
    let err = |detail: String| WriteError {
        file: path.display().to_string(),
        detail,
    };
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| err(e.to_string()))?;
    }
    let tmp = tmp_path(path);
    let result = (|| -> hdf5::Result<()> {
        let file = hdf5::File::create(&tmp)?;
        write_str_attr(&file, "format", CAMPAIGN_FORMAT)?;
        for (k, v) in root_attrs {
            write_attr(&file, k, v)?;
        }
        for run in runs {
            let g = file
                .create_group_builder()
                .create_intermediate_group(true)
                .create(run.path.trim_start_matches('/'))?;
            write_f64_attr(&g, "sample_rate", run.sample_rate)?;
            write_str_attr(&g, "kind", run.kind.as_str())?;
            if let Some(q) = run.input_quantity {
                write_str_attr(&g, "input_quantity", q.as_str())?;
            }
            write_str_attr(&g, "output_quantity", run.output_quantity.as_str())?;
            for (k, v) in &run.attrs {
                write_attr(&g, k, v)?;
            }
            if let Some(input) = &run.input {
                write_signal(&g, "input", input, compress)?;
            }
            write_signal(&g, "output", &run.output, compress)?;
        }
        file.flush()?;
        Ok(())
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(err(e.to_string()));
    }
    std::fs::rename(&tmp, path).map_err(|e| err(e.to_string()))
}

/// Where a file is written before it is renamed into place (nothing half-written is left).
pub fn tmp_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".tmp");
    path.with_file_name(name)
}

fn write_attr(loc: &hdf5::Location, name: &str, v: &Attr) -> hdf5::Result<()> {
    match v {
        Attr::Num(x) => write_f64_attr(loc, name, *x),
        Attr::Text(s) => write_str_attr(loc, name, s),
    }
}

/// Writes a float64 vector, chunked and gzip-compressed when asked (as real archives are).
pub fn write_signal(
    group: &hdf5::Group,
    name: &str,
    data: &[f64],
    compress: bool,
) -> hdf5::Result<()> {
    use crate::report::encoded::{chunk_len, MIN_COMPRESSED, SIGNAL_LEVEL};
    let builder = group.new_dataset_builder().with_data(data);
    // The same layout as the batch's pre-compressed results (report::encoded).
    if compress && data.len() >= MIN_COMPRESSED {
        builder
            .chunk(chunk_len(data.len()))
            .shuffle()
            .deflate(SIGNAL_LEVEL)
            .create(name)?;
    } else {
        builder.create(name)?;
    }
    Ok(())
}
