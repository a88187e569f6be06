//! Conditioning: a run's channels made ready for the tracks, one stage before them. In: a
//! run and the mode choice; out: the mode's band (when one is isolated) and, by the run's
//! kind, the channels to track: the response of a free decay; the input displacement and the
//! relative motion z = y − x of a base-motion run; the drive and the response displacement
//! of a force run. Every channel is band-passed to the mode's band first, velocities and
//! accelerations are integrated to displacement (spectrally, with a high-pass at half the
//! band's lower edge, or of the signal's own band), and nothing after this stage conditions a
//! signal again: ForceVib receives tracks.

use std::borrow::Cow;
use std::f64::consts::PI;

use num_complex::Complex64;

use crate::mode::{self, ModeBand, ModeChoice};
use crate::run::{Quantity, Run, RunKind};
use crate::track::{default_band, TrackError};
use crate::transform::{fast_len, real_inverse_plan, real_plan, Morlet};

/// A run's channels, conditioned.
pub struct Conditioned {
    /// The mode's band, when one was isolated ([`crate::mode`]).
    pub band: Option<ModeBand>,
    /// The channels to track.
    pub channels: Channels,
}

/// What is tracked, by the run's kind (displacements in the run's units, force as given).
pub enum Channels {
    /// A free decay: its response.
    Free {
        /// Response displacement.
        response: Vec<f64>,
    },
    /// A base-motion run: the base's displacement and the joint's relative motion.
    BaseMotion {
        /// Input (base) displacement x.
        input: Vec<f64>,
        /// Relative motion z = y − x.
        relative: Vec<f64>,
    },
    /// A force-input run: the drive and the response.
    Force {
        /// The measured force.
        force: Vec<f64>,
        /// Response displacement.
        response: Vec<f64>,
    },
}

/// Why a run's channels could not be conditioned.
#[derive(Debug, thiserror::Error)]
pub enum ConditionError {
    /// The run lacks something, or holds something contradictory.
    #[error("{0}")]
    Unusable(String),
    /// A channel's band could not be found (the integration's high-pass needs it).
    #[error("{channel} channel: {source}")]
    Band {
        /// Which channel.
        channel: &'static str,
        /// Why.
        source: TrackError,
    },
}

/// `run`'s channels conditioned for tracking, with the mode chosen by `choice`.
pub fn condition(run: &Run, choice: ModeChoice) -> Result<Conditioned, ConditionError> {
    let meta = &run.meta;
    let fs = meta.sample_rate;
    finite(&run.output, "output")?;
    if let Some(input) = &run.input {
        finite(input, "input")?;
    }
    let band = mode::choose(run, choice).map_err(|e| ConditionError::Unusable(e.to_string()))?;
    let band_ref = band.as_ref();
    let y = displacement(&run.output, fs, meta.output_quantity, "output", band_ref)?;
    let channels = match meta.kind {
        RunKind::Free => Channels::Free { response: y },
        RunKind::BaseMotion => {
            let raw = run.input.as_ref().ok_or_else(|| {
                ConditionError::Unusable("a base-motion run needs an input dataset".into())
            })?;
            let q = meta.input_quantity.unwrap_or(Quantity::Displacement);
            if q == Quantity::Force {
                return Err(ConditionError::Unusable(
                    "input_quantity is force but kind is base_motion: set kind = \"force\"".into(),
                ));
            }
            let x = displacement(raw, fs, q, "input", band_ref)?;
            let z: Vec<f64> = y.iter().zip(&x).map(|(a, b)| a - b).collect();
            Channels::BaseMotion {
                input: x,
                relative: z,
            }
        }
        RunKind::Force => {
            let f = run.input.as_ref().ok_or_else(|| {
                ConditionError::Unusable("a force run needs an input (force) dataset".into())
            })?;
            let force = match band_ref {
                Some(b) => mode::band_pass(f, fs, b.fmin, b.fmax),
                None => f.clone(),
            };
            Channels::Force { force, response: y }
        }
    };
    Ok(Conditioned { band, channels })
}

/// Refuses a channel with a sample that is not finite (a simulation that diverged: the
/// archive's reader refuses them in measured runs), which the spectral filters would
/// spread over the whole record and the inverse real FFT refuse.
fn finite(x: &[f64], channel: &'static str) -> Result<(), ConditionError> {
    crate::track::non_finite(x).map_or(Ok(()), |why| {
        Err(ConditionError::Unusable(format!(
            "{channel} channel: {why}"
        )))
    })
}

fn order(q: Quantity) -> u32 {
    match q {
        Quantity::Velocity => 1,
        Quantity::Acceleration => 2,
        _ => 0,
    }
}

/// A channel as displacement: velocity and acceleration are integrated spectrally, with the
/// high-pass at half the lowest frequency of the signal's own band. Within a mode's band
/// the channel is band-passed first and the band's lower edge sets the high-pass.
fn displacement(
    x: &[f64],
    fs: f64,
    q: Quantity,
    channel: &'static str,
    band: Option<&ModeBand>,
) -> Result<Vec<f64>, ConditionError> {
    let x = match band {
        Some(b) => Cow::Owned(mode::band_pass(x, fs, b.fmin, b.fmax)),
        None => Cow::Borrowed(x),
    };
    let k = order(q);
    if k == 0 {
        return Ok(x.into_owned());
    }
    let fmin = match band {
        Some(b) => b.fmin,
        None => {
            default_band(&x, fs, &Morlet::default())
                .map_err(|source| ConditionError::Band { channel, source })?
                .0
        }
    };
    Ok(integrate(&x, fs, k, 0.5 * fmin))
}

/// Displacement from a velocity (`order` 1) or acceleration (`order` 2) record by spectral
/// integration: X(f)/(j2πf)^order, with everything below `f_cut` Hz (drift, offsets, the
/// integration's 1/f blow-up) removed by a raised-cosine high-pass from f_cut/2 to f_cut.
/// The first and last 2/f_cut seconds are tapered and should be treated as edge zone.
pub fn integrate(x: &[f64], fs: f64, order: u32, f_cut: f64) -> Vec<f64> {
    if order == 0 {
        return x.to_vec();
    }
    let n = x.len();
    // Padding by a tenth keeps the ends from wrapping into each other.
    let len = fast_len(n + n / 10 + 16);
    let mean = x.iter().sum::<f64>() / n.max(1) as f64;
    let mut buf = vec![0.0; len];
    // A cosine taper over the first and last two periods of f_cut: the abrupt ends would
    // otherwise leak into the band just above f_cut, which integration amplifies as 1/f^k.
    let ramp = ((2.0 * fs / f_cut) as usize).min(n / 4).max(1);
    for (i, (b, v)) in buf.iter_mut().zip(x).enumerate() {
        let e = i.min(n - 1 - i);
        let w = if e >= ramp {
            1.0
        } else {
            0.5 - 0.5 * (PI * e as f64 / ramp as f64).cos()
        };
        *b = (v - mean) * w;
    }
    let fwd = real_plan(len);
    let mut spec = fwd.make_output_vec();
    fwd.process(&mut buf, &mut spec)
        .expect("buffer sizes come from the plan");
    for (m, c) in spec.iter_mut().enumerate() {
        let f = m as f64 * fs / len as f64;
        let gate = if f >= f_cut {
            1.0
        } else if f <= 0.5 * f_cut {
            0.0
        } else {
            0.5 - 0.5 * (PI * (f - 0.5 * f_cut) / (0.5 * f_cut)).cos()
        };
        if gate == 0.0 {
            *c = Complex64::new(0.0, 0.0);
            continue;
        }
        let jw = Complex64::new(0.0, 2.0 * PI * f).powi(order as i32);
        *c = *c * gate / jw;
    }
    let inv = real_inverse_plan(len);
    let mut out = inv.make_output_vec();
    inv.process(&mut spec, &mut out)
        .expect("buffer sizes come from the plan");
    out.truncate(n);
    out.iter_mut().for_each(|v| *v /= len as f64);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_channel_that_is_not_finite_is_refused_before_any_filter() {
        // An accelerometer's record: integrated, the path the inverse FFT panicked on.
        let run = crate::rig::plain_decay();
        assert_eq!(run.meta.output_quantity, Quantity::Acceleration);
        assert!(condition(&run, ModeChoice::Band(6.0, 9.0)).is_ok());
        for bad in [f64::NAN, f64::INFINITY] {
            let mut r = run.clone();
            r.output[100] = bad;
            for choice in [ModeChoice::Band(6.0, 9.0), ModeChoice::Whole] {
                let e = condition(&r, choice).err().expect("refused").to_string();
                assert!(e.contains("output channel: sample 100 is"), "{e}");
            }
            // A drive (force or base) alike.
            let mut r = run.clone();
            let mut drive = vec![0.0; r.output.len()];
            drive[7] = bad;
            r.input = Some(drive);
            let e = condition(&r, ModeChoice::Whole).err().expect("refused");
            assert!(e.to_string().contains("input channel: sample 7 is"), "{e}");
        }
    }

    #[test]
    fn spectral_integration_of_an_acceleration() {
        let fs = 500.0;
        let n = 5000;
        let w = 2.0 * PI * 7.0;
        let acc: Vec<f64> = (0..n)
            .map(|i| -w * w * (w * i as f64 / fs).sin() + 0.3)
            .collect();
        let x = integrate(&acc, fs, 2, 2.0);
        for (i, v) in x.iter().enumerate().take(n - 1000).skip(1000) {
            assert!((v - (w * i as f64 / fs).sin()).abs() < 2e-3, "{i}: {v}");
        }
    }
}
