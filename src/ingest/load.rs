//! A run's samples: its input and output channels read (a channel of a 2-D dataset with
//! `NAME[k]`, integers and float32 converted) and checked (length, finite values). In: a
//! run's metadata; out: a [`Run`]. Or, for channels stored as plain float64 bytes, only
//! where they lie ([`Placed`]), so that another process can read them without libhdf5.

use std::os::unix::fs::FileExt;

use hdf5::dataset::Layout;
use hdf5::types::TypeDescriptor;
use hdf5::Group;
use serde::Deserialize;

use super::*;

/// Where one channel's samples lie in its archive as native little-endian IEEE float64,
/// one after another: what a plain read of the file at `offset` returns, without libhdf5.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Placed {
    /// Bytes from the start of the file (a user block included).
    pub offset: u64,
    /// Samples, 8 bytes each.
    pub samples: usize,
}

/// A run's channels as placed: the input's (when the run has one), the output's.
pub type PlacedRun = (Option<Placed>, Placed);

/// Reads `placed`'s samples from `file` (the archive named `file_name`) and checks them as
/// [`Archive::load`] does, with the same errors: the other half of [`Archive::placed`].
pub fn read_placed(
    file: &std::fs::File,
    file_name: &str,
    meta: &RunMeta,
    dataset: &str,
    placed: Placed,
) -> Result<Vec<f64>, IngestError> {
    let mut v = vec![0f64; placed.samples];
    file.read_exact_at(bytemuck::cast_slice_mut(&mut v), placed.offset)
        .map_err(|e| IngestError::Corrupt {
            file: file_name.to_string(),
            run: Some(meta.path.clone()),
            detail: format!("dataset `{dataset}`: {e}"),
        })?;
    check_finite(file_name, meta, dataset, &v)?;
    Ok(v)
}

/// Refuses samples that are not all finite, naming how many and the first.
fn check_finite(
    file_name: &str,
    meta: &RunMeta,
    dataset: &str,
    v: &[f64],
) -> Result<(), IngestError> {
    let mut count = 0;
    let mut first = None;
    for (i, x) in v.iter().enumerate() {
        if !x.is_finite() {
            count += 1;
            first.get_or_insert(i);
        }
    }
    match first {
        Some(first) => Err(IngestError::NonFinite {
            file: file_name.to_string(),
            run: meta.path.clone(),
            dataset: dataset.to_string(),
            count,
            first,
            first_time: first as f64 / meta.sample_rate,
        }),
        None => Ok(()),
    }
}

impl Archive {
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

    pub(super) fn read_signal(
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
        check_finite(&self.file_name, meta, name, &v)?;
        Ok(v)
    }

    /// Where the run's channels lie as plain float64 bytes in the file, when every one of
    /// them does: a whole dataset (not a `NAME[k]` channel) of native float64, as long as
    /// the run, stored in one contiguous block (not chunked, filtered, compact or in an
    /// external file) on a little-endian machine. `None` otherwise or on any error; then
    /// [`load`](Self::load) reads the run, and says what is wrong.
    pub fn placed(&self, meta: &RunMeta) -> Option<PlacedRun> {
        if cfg!(target_endian = "big") {
            return None;
        }
        let group = self.file.group(&meta.path).ok()?;
        let place = |name: &str| -> Option<Placed> {
            let (base, channel) = channel_name(name);
            if channel.is_some() {
                return None;
            }
            let ds = group.dataset(base).ok()?;
            let plist = ds.dcpl().ok()?;
            let plain = plist.layout() == Layout::Contiguous
                && plist.filters().is_empty()
                && plist.external().is_empty()
                && ds.dtype().ok()?.is::<f64>()
                && ds.size() == meta.samples
                && ds.storage_size() == 8 * meta.samples as u64;
            plain.then_some(())?;
            Some(Placed {
                offset: ds.offset()?,
                samples: meta.samples,
            })
        };
        let output = place(&self.options.output_name)?;
        let input = match meta.kind {
            RunKind::Free => None,
            _ => Some(place(&self.options.input_name)?),
        };
        Some((input, output))
    }
}
