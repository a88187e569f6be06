//! A run's diagnosis finished for its outputs: the whole-run gaps and identifications of
//! the models it names (nominal, baseline, fitted), simulated here so that the output files
//! (`gap::export`) only render what they are given.

use super::search::{Reference, Role};
use super::{Diagnosis, Gap, GapError};
use crate::identify::Identification;

/// A model over the whole run: its gap and its simulation's identification.
pub struct Whole {
    /// The gap over the whole run (in a [`GapRun`], its regions in the record's own time;
    /// `identified`'s track starts at a free decay's release).
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
    /// How the run took part in the fit: alone on alternate blocks, or one of several
    /// runs fitted together or held out.
    pub role: Role,
    /// Of runs fitted together, the fit runs and the held-out ones (empty for a run alone).
    pub together: (Vec<String>, Vec<String>),
    /// Where the verdict is `none`: the best candidate over the whole run (how near the
    /// nearest explanation came, for the page and gap.json).
    pub best: Option<Whole>,
    /// The tracked displacement's unit as the run's archive states it (`rad`, `m`, … or
    /// `u`): the page names it as report.html does for the same run.
    pub amplitude_unit: String,
    /// Of a free decay: where it was cut from its record. Every time in this run's outputs
    /// (its gaps' regions, the envelope's plot) is the record's own, this much later than
    /// the cut record's.
    pub release: Option<super::search::Release>,
}

impl GapRun {
    /// Simulates the nominal, baseline and fitted models over the whole run.
    pub fn new(reference: &Reference, diagnosis: Diagnosis) -> Result<GapRun, GapError> {
        Self::of(reference, 0, diagnosis)
    }

    /// Every run of `reference` with the nominal, baseline and fitted models simulated over
    /// it, each carrying the diagnosis of them all (named after it).
    pub fn every(reference: &Reference, diagnosis: &Diagnosis) -> Vec<Result<GapRun, GapError>> {
        use rayon::prelude::*;
        (0..reference.len())
            .into_par_iter()
            .map(|i| {
                let mut d = diagnosis.clone();
                d.run = reference.measured(i).0.meta.path.clone();
                Self::of(reference, i, d)
            })
            .collect()
    }

    /// [`new`](Self::new) for run `i` of `reference`.
    pub fn of(reference: &Reference, i: usize, diagnosis: Diagnosis) -> Result<GapRun, GapError> {
        let d = &diagnosis;
        let with_effect = d.verdict.map(|_| d.fitted_model());
        let best_model = d
            .verdict
            .is_none()
            .then(|| d.candidates.first().map(|c| &c.model))
            .flatten();
        let (((nominal, baseline), fitted), best) = rayon::join(
            || {
                rayon::join(
                    || {
                        rayon::join(
                            || reference.whole_of(i, &d.nominal).ok(),
                            || reference.whole_of(i, &d.baseline.model),
                        )
                    },
                    || with_effect.map(|m| reference.whole_of(i, m)).transpose(),
                )
            },
            || best_model.and_then(|m| reference.whole_of(i, m).ok()),
        );
        let (run, measured, role) = reference.measured(i);
        let mut together = (Vec::new(), Vec::new());
        if reference.len() > 1 {
            for j in 0..reference.len() {
                let (run, _, role) = reference.measured(j);
                match role {
                    Role::Holdout => together.1.push(run.meta.path.clone()),
                    _ => together.0.push(run.meta.path.clone()),
                }
            }
        }
        let release = reference.release(i);
        let mut r = GapRun {
            role,
            together,
            measured: measured.clone(),
            nominal,
            baseline: baseline?,
            fitted: fitted?,
            best,
            zero_tolerance: reference.zero_tolerance(),
            amplitude_unit: crate::units::Units::of(&run.meta).displacement,
            diagnosis,
            release,
        };
        // The regions were found on the cut record; the user reads times off the whole one.
        let offset = r.record_offset();
        let wholes = [
            r.nominal.as_mut(),
            Some(&mut r.baseline),
            r.fitted.as_mut(),
            r.best.as_mut(),
        ];
        for w in wholes.into_iter().flatten() {
            for reg in &mut w.gap.regions {
                reg.t0 += offset;
                reg.t1 += offset;
            }
        }
        Ok(r)
    }

    /// How much later in its record this run's compared samples lie than in the record as
    /// compared (s): a free decay's release, 0 for every other run.
    pub fn record_offset(&self) -> f64 {
        self.release.map_or(0.0, |r| r.at_s)
    }

    /// The fitted model over the whole run.
    pub fn fitted(&self) -> &Whole {
        self.fitted.as_ref().unwrap_or(&self.baseline)
    }

    /// Where the verdict is `none`, the best candidate over the whole run with its name.
    pub fn best_candidate(&self) -> Option<(String, &Whole)> {
        let c = self.diagnosis.candidates.first()?;
        self.best.as_ref().map(|w| (c.name(), w))
    }

    /// This run's own gap under each model, named, as the terminal and gap.html show it:
    /// the nominal (when its response could be identified), the baseline only where a
    /// verdict makes the fitted model another, the fitted model, and the best candidate
    /// where there is no verdict.
    pub fn own_gaps(&self) -> Vec<(String, &Gap)> {
        let mut gaps = Vec::new();
        if let Some(w) = &self.nominal {
            gaps.push(("nominal".to_string(), &w.gap));
        }
        if self.fitted.is_some() {
            gaps.push(("baseline".to_string(), &self.baseline.gap));
        }
        gaps.push(("fitted".to_string(), &self.fitted().gap));
        if let Some((name, w)) = self.best_candidate() {
            gaps.push((name, &w.gap));
        }
        gaps
    }
}
