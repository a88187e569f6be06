//! A run's diagnosis finished for its outputs: the whole-run gaps and identifications of
//! the models it names (nominal, baseline, fitted), simulated here so that the output files
//! (`gap::export`) only render what they are given.

use super::search::Reference;
use super::{Diagnosis, Gap, GapError};
use crate::identify::Identification;

/// A model over the whole run: its gap and its simulation's identification.
pub struct Whole {
    /// The gap over the whole run.
    pub gap: Gap,
    /// The simulation's identification.
    pub identified: Identification,
}

/// One run's diagnosis with the whole-run gaps and identifications of the models it names.
pub struct GapRun {
    /// The diagnosis.
    pub diagnosis: Diagnosis,
    /// The measurement's identification.
    pub measured: Identification,
    /// The nominal model (`None` when its response cannot even be identified).
    pub nominal: Option<Whole>,
    /// The baseline.
    pub baseline: Whole,
    /// The fitted model (the verdict's; the baseline's own when the verdict is `none`).
    pub fitted: Option<Whole>,
    /// The encoders' zero tolerance the run was scored with (rad).
    pub zero_tolerance: f64,
}

impl GapRun {
    /// Simulates the nominal, baseline and fitted models over the whole run.
    pub fn new(reference: &Reference, diagnosis: Diagnosis) -> Result<GapRun, GapError> {
        let d = &diagnosis;
        let with_effect = d.verdict.map(|_| d.fitted_model());
        let ((nominal, baseline), fitted) = rayon::join(
            || {
                rayon::join(
                    || reference.whole(&d.nominal).ok(),
                    || reference.whole(&d.baseline.model),
                )
            },
            || with_effect.map(|m| reference.whole(m)).transpose(),
        );
        Ok(GapRun {
            measured: reference.identified.clone(),
            nominal,
            baseline: baseline?,
            fitted: fitted?,
            zero_tolerance: reference.zero_tolerance(),
            diagnosis,
        })
    }

    /// The fitted model over the whole run.
    pub fn fitted(&self) -> &Whole {
        self.fitted.as_ref().unwrap_or(&self.baseline)
    }
}
