//! One run's metadata from its group: kind, quantities, inertia, units, attributes (its own
//! and inherited), the channels' lengths and the sample rate (attribute, `time` dataset or
//! MATLAB's `Fs`), each wrong way named by its own error. In: a group of an [`Archive`];
//! out: a [`RunMeta`].

use hdf5::types::TypeDescriptor;
use hdf5::{Group, Location};

use crate::h5util::{all_attrs, read_attr, AttrValue};

use super::*;

impl Archive {
    pub(super) fn run_meta(
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
        let zero_tolerance = number("zero_tolerance")?.unwrap_or(0.0);
        if zero_tolerance < 0.0 {
            return Err(IngestError::BadAttribute {
                file: file.clone(),
                run,
                name: "zero_tolerance".into(),
                value: zero_tolerance.to_string(),
                detail: "the encoders' zero tolerance is a distance (rad, or m), 0 or more".into(),
            });
        }
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
            zero_tolerance,
        })
    }

    /// Length of a signal (`NAME` or `NAME[k]`, see [`channel_name`]) of `group`, checking
    /// shape and type.
    pub(super) fn signal_len(
        &self,
        group: &Group,
        run: &str,
        name: &str,
    ) -> Result<usize, IngestError> {
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

    pub(super) fn sample_rate(
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
                        "disagrees with the `time` dataset, which gives {fs_time:.6} Hz; fix one, or pass {}", crate::hint::Hint::SampleRate
                    ),
                });
            }
        }
        Ok(fs_time)
    }

    /// A sample rate saved as a scalar variable (`Fs`, …) in the run's group or, for a
    /// run at the root, at the root.
    pub(super) fn rate_variable(&self, group: &Group) -> Option<f64> {
        RATE_VARIABLES.iter().find_map(|name| {
            let ds = group.dataset(name).ok()?;
            let shape = ds.get_shape().ok()?;
            if shape.iter().product::<usize>() != 1 {
                return None;
            }
            ds.read_raw::<f64>().ok()?.first().copied()
        })
    }
}

/// For a 2-D shape: the axis that counts channels (the shorter one) and the length of the
/// other (samples).
pub(super) fn channel_axis(shape: &[usize]) -> Option<(usize, usize)> {
    match *shape {
        [a, b] if a <= b => Some((0, b)),
        [a, _] => Some((1, a)),
        _ => None,
    }
}

pub(super) fn check_rate(fs: f64, file: &str, run: &str) -> Result<f64, IngestError> {
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

pub(super) fn attr_number(loc: &Location, name: &str) -> Option<f64> {
    let a = loc.attr(name).ok()?;
    match read_attr(&a) {
        Ok(AttrValue::Number(x)) => Some(x),
        _ => None,
    }
}
