//! A run's samples: its input and output channels read (a channel of a 2-D dataset with
//! `NAME[k]`, integers and float32 converted) and checked (length, finite values). In: a
//! run's metadata; out: a [`Run`].

use hdf5::types::TypeDescriptor;
use hdf5::Group;

use super::*;

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
