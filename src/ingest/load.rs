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

/// What tells one file from another at the same path (device, inode, length, last
/// change), taken when an archive is opened: a reader of its placed samples checks that the
/// file it opened is still that one (an export that writes a new file and renames it over
/// the old one changes the inode; one that rewrites it in place, the length or the time).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileStamp {
    dev: u64,
    ino: u64,
    len: u64,
    modified_s: i64,
    modified_ns: i64,
}

impl FileStamp {
    /// The stamp of a file's metadata.
    pub fn of(md: &std::fs::Metadata) -> FileStamp {
        use std::os::unix::fs::MetadataExt;
        FileStamp {
            dev: md.dev(),
            ino: md.ino(),
            len: md.len(),
            modified_s: md.mtime(),
            modified_ns: md.mtime_nsec(),
        }
    }
}

/// A run's channels as placed ([`Archive::placed`]), and the file they lie in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PlacedRun {
    /// The input's samples (none for a free decay).
    pub input: Option<Placed>,
    /// The output's samples.
    pub output: Placed,
    /// The archive's file as it was opened.
    pub file: FileStamp,
}

/// Reads a placed run's samples from `file` (the archive named `file_name`, opened by
/// the reader) and checks them as [`Archive::load`] does, output first, with the same
/// words for samples that are not finite: the other half of [`Archive::placed`]. Refused
/// with the reason: a file that is no longer the one the child opened (replaced or
/// rewritten), and a place that runs past the file's end, before anything is allocated
/// for it. `options` names the datasets, as for `load`. Little-endian machines only, as
/// `placed` is.
pub fn read_placed(
    file: &std::fs::File,
    file_name: &str,
    meta: &RunMeta,
    options: &IngestOptions,
    placed: PlacedRun,
) -> Result<(Option<Vec<f64>>, Vec<f64>), IngestError> {
    let unreadable = |detail: String| IngestError::Unreadable {
        file: file_name.to_string(),
        detail,
    };
    let now = file.metadata().map_err(|e| unreadable(e.to_string()))?;
    if FileStamp::of(&now) != placed.file {
        return Err(unreadable(format!(
            "it changed while run {} was being read (replaced or rewritten); run the batch \
             again once it is complete",
            meta.path
        )));
    }
    let channel = |dataset: &str, p: Placed| {
        let corrupt = |detail: String| IngestError::Corrupt {
            file: file_name.to_string(),
            run: Some(meta.path.clone()),
            detail: format!("dataset `{dataset}`: {detail}"),
        };
        let end = (p.samples as u64)
            .checked_mul(8)
            .and_then(|b| b.checked_add(p.offset));
        if end.is_none_or(|end| end > now.len()) {
            return Err(corrupt(format!(
                "{} samples at byte {} run past the file's end ({} bytes)",
                p.samples,
                p.offset,
                now.len()
            )));
        }
        let mut v = vec![0f64; p.samples];
        file.read_exact_at(bytemuck::cast_slice_mut(&mut v), p.offset)
            .map_err(|e| corrupt(e.to_string()))?;
        check_finite(file_name, meta, dataset, &v)?;
        Ok(v)
    };
    // Output first, as `load` checks it first: the same error wins when both are bad.
    let output = channel(&options.output_name, placed.output)?;
    let input = placed
        .input
        .map(|p| channel(&options.input_name, p))
        .transpose()?;
    Ok((input, output))
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

    /// Reads every run listed, its metadata included, each to its own result.
    pub fn load_all(&self) -> Vec<(String, Result<Run, IngestError>)> {
        self.listed
            .iter()
            .map(|entry| {
                let run = self.read_meta(entry).and_then(|meta| self.load(&meta));
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
    /// them does: a whole one-dimensional dataset (not a `NAME[k]` channel) of native
    /// float64, as long as the run, stored in one contiguous block (not chunked, filtered,
    /// compact or in an external file) inside the file, on a little-endian machine; and its
    /// last sample, read through libhdf5, is the last 8 bytes of that block. `None`
    /// otherwise or on any error; then [`load`](Self::load) reads the run, and says what
    /// is wrong.
    pub fn placed(&self, meta: &RunMeta) -> Option<PlacedRun> {
        if cfg!(target_endian = "big") || meta.samples == 0 {
            return None;
        }
        let stamp = self.stamp;
        let group = self.file.group(&meta.path).ok()?;
        let raw = self.raw.as_ref()?;
        let place = |name: &str| -> Option<Placed> {
            let (base, channel) = channel_name(name);
            if channel.is_some() {
                return None;
            }
            let ds = group.dataset(base).ok()?;
            let plist = ds.dcpl().ok()?;
            // The storage's size is what keeps out a dataset never written: libhdf5 gives
            // it no block (its reads return the fill value), yet behind a user block its
            // offset is not "undefined" but the undefined address plus the block's size.
            let plain = ds.ndim() == 1
                && plist.layout() == Layout::Contiguous
                && plist.filters().is_empty()
                && plist.external().is_empty()
                && ds.dtype().ok()?.is::<f64>()
                && ds.size() == meta.samples
                && ds.storage_size() == 8 * meta.samples as u64;
            if !plain {
                return None;
            }
            let offset = ds.offset()?;
            let last = offset.checked_add(8 * (meta.samples as u64 - 1))?;
            if last.checked_add(8)? > stamp.len {
                return None;
            }
            // libhdf5 reads the last sample where the block ends, or refuses a block past
            // the end of what the file allocates; either way the plain read must agree.
            let through_hdf5 = ds.read_slice_1d::<f64, _>(meta.samples - 1..).ok()?;
            let mut bytes = [0u8; 8];
            raw.read_exact_at(&mut bytes, last).ok()?;
            let same = through_hdf5
                .as_slice()?
                .iter()
                .map(|x| x.to_bits())
                .eq([u64::from_le_bytes(bytes)]);
            same.then_some(Placed {
                offset,
                samples: meta.samples,
            })
        };
        let output = place(&self.options.output_name)?;
        let input = match meta.kind {
            RunKind::Free => None,
            _ => Some(place(&self.options.input_name)?),
        };
        Some(PlacedRun {
            input,
            output,
            file: stamp,
        })
    }
}
