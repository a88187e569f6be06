//! A model simulated under a measured run's own input and identified like the measurement
//! ([`Simulated`]), with the decimation that keeps long records cheap to simulate. In: a
//! measured run, a rig model and the identifier; out: the simulated run and its
//! identification.

use crate::identify::{Identification, Identifier};
use crate::model::{ModelKind, RigModel};
use crate::run::Run;
use crate::simulate::{simulate, Drive, Excitation, SimSettings, MEASURED_INPUT_CUTOFF};
use crate::track::Method;

use super::{model_resolution, Features, GapError};

/// A model simulated under a measured run's own input: the simulated run and its
/// identification (made like the measurement's).
pub struct Simulated {
    /// The simulated run (the measured one with its channels replaced).
    pub run: Run,
    /// Its identification.
    pub identified: Identification,
    /// The RMS quantisation error the model's measurement chain puts on the response
    /// ([`model_resolution`]).
    pub resolution: f64,
}

impl Simulated {
    /// What the gap compares of it.
    pub fn features(&self) -> Features {
        Features::of(&self.identified, &self.run).with_resolution(self.resolution)
    }
}

/// A simulated displacement as the measured run's output channel records it: velocity and
/// acceleration by 4th-order differences (the simulation is noise-free and sampled at
/// the record's rate, tens of samples a cycle).
fn as_measured(displacement: Vec<f64>, measured: &Run) -> Vec<f64> {
    use crate::run::Quantity;
    use crate::simulate::derivative_4th;
    let fs = measured.meta.sample_rate;
    match measured.meta.output_quantity {
        Quantity::Velocity => derivative_4th(&displacement, fs),
        Quantity::Acceleration => derivative_4th(&derivative_4th(&displacement, fs), fs),
        _ => displacement,
    }
}

/// The model simulated under `measured`'s own input, identified like the measurement.
pub fn simulate_like(
    measured: &Run,
    model: &RigModel,
    identifier: Identifier<'_>,
) -> Result<Simulated, GapError> {
    simulate_given(measured, None, model, 1, identifier)
}

/// Samples per cycle of the highest tracked frequency that a run decimated for the search
/// keeps.
pub const SAMPLES_PER_CYCLE: f64 = 20.0;

/// The factor a run can be decimated by before it is identified for the search: its rate
/// over [`SAMPLES_PER_CYCLE`] samples of the highest frequency either of its tracks
/// reaches (1 to 8). The identification's cost falls with the samples, and the 1 kHz of a
/// sweep that ends at 12 Hz carries nothing the envelope, backbone or damping need.
pub fn decimation_for(id: &Identification) -> usize {
    let highest = |t: &crate::track::Track| {
        (0..t.len())
            .filter(|&i| t.valid[i])
            .map(|i| t.frequency[i])
            .fold(0f64, f64::max)
    };
    let f = highest(&id.response).max(id.input.as_ref().map_or(0.0, highest));
    if f <= 0.0 {
        return 1;
    }
    ((id.response.sample_rate / (SAMPLES_PER_CYCLE * f)).floor() as usize).clamp(1, 8)
}

/// `run` low-passed (zero-phase, at 40 % of the new Nyquist frequency) and kept one sample
/// in `factor`; itself when `factor` is 1. The measurement and every simulation compared
/// with it go through the same filter.
pub fn decimate(run: Run, factor: usize) -> Run {
    if factor <= 1 {
        return run;
    }
    let down = |x: &[f64]| -> Vec<f64> {
        crate::filter::lowpass_zero_phase(x, 0.4 / factor as f64)
            .into_iter()
            .step_by(factor)
            .collect()
    };
    let output = down(&run.output);
    let mut meta = run.meta.clone();
    meta.sample_rate = run.meta.sample_rate / factor as f64;
    meta.samples = output.len();
    Run {
        meta,
        input: run.input.as_deref().map(down),
        output,
    }
}

/// [`simulate_like`], decimated by `factor` before it is identified (see [`decimate`]),
/// reusing the measurement's input track when `identified` is given (the simulation is
/// driven by that very input, so tracking it again only costs time). A free-decay model
/// needs the record's state instead: [`simulate_released`].
pub fn simulate_given(
    measured: &Run,
    identified: Option<&Identification>,
    model: &RigModel,
    factor: usize,
    identifier: Identifier<'_>,
) -> Result<Simulated, GapError> {
    let input = measured.input.as_ref().ok_or_else(|| {
        GapError::Unusable("the run has no input channel to drive the model with".into())
    })?;
    let fs = measured.meta.sample_rate;
    let drive = match model.kind {
        ModelKind::BaseMotion => Drive::Base(Excitation::measured(
            input,
            fs,
            MEASURED_INPUT_CUTOFF * fs / 2.0,
        )),
        // One mode is driven by the force within its band: outside it the structure's other
        // modes answer, which a one-mode model does not have.
        ModelKind::Force => {
            let band = model
                .band
                .map(|[lo, hi]| (lo, hi))
                .or_else(|| identified.and_then(|i| i.mode).map(|b| (b.fmin, b.fmax)));
            let force = match band {
                Some((lo, hi)) => crate::mode::band_pass(input, fs, lo, hi),
                None => input.clone(),
            };
            Drive::Force(Excitation::sampled(force, fs))
        }
        ModelKind::Free => {
            return Err(GapError::Unusable(
                "a free-decay model starts from the record's own state, not from an input \
                 (skelid gap finds that state: the model's kind is \"free\")"
                    .into(),
            ))
        }
    };
    simulate_driven(measured, identified, model, drive, factor, identifier)
}

/// A free-decay model released from `state` (displacement, velocity of the mode at the
/// first sample of `measured`, the record as cut) over its length, recorded and identified
/// like it.
pub fn simulate_released(
    measured: &Run,
    identified: Option<&Identification>,
    model: &RigModel,
    state: (f64, f64),
    factor: usize,
    identifier: Identifier<'_>,
) -> Result<Simulated, GapError> {
    let drive = Drive::Released {
        displacement: state.0,
        velocity: state.1,
    };
    simulate_driven(measured, identified, model, drive, factor, identifier)
}

fn simulate_driven(
    measured: &Run,
    identified: Option<&Identification>,
    model: &RigModel,
    drive: Drive,
    factor: usize,
    identifier: Identifier<'_>,
) -> Result<Simulated, GapError> {
    let fs = measured.meta.sample_rate;
    let settings = SimSettings {
        sample_rate: fs,
        duration: measured.output.len() as f64 / fs,
        ..SimSettings::default()
    };
    // The encoder's quantisation enters the gap as the resolution it gives the response,
    // not by quantising this noise-free simulation: a real encoder quantises a noisy signal
    // whose noise dithers the steps away from the envelope, while a noise-free response
    // quantised turns into a staircase whose envelope and frequency jitter sample to sample
    // (the true model of a quantised rig then fitted worse than the same model without it).
    let resolution =
        super::as_displacement(model_resolution(model, measured), measured, identified);
    let mut unquantised = model.clone();
    unquantised
        .effects
        .set(crate::model::EffectKind::Quantization, None);
    let out = simulate(&unquantised, &drive, &settings);
    let run = Run {
        meta: measured.meta.clone(),
        input: measured.input.as_ref().map(|_| out.input),
        output: as_measured(out.output, measured),
    };
    let run = decimate(run, factor);
    let identified = match identified.and_then(|i| i.input.as_ref()) {
        Some(tx) => identifier.identify_with_input_track(&run, Method::Wavelet, tx),
        None => identifier.identify(&run, Method::Wavelet),
    }
    .map_err(|reason| GapError::Unidentified { reason })?;
    Ok(Simulated {
        run,
        identified,
        resolution,
    })
}
