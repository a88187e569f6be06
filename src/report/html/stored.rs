//! What the page reads of a run's stored results — its reduced tracks, skeletons and fitted
//! curves per method ([`RunPlots`]) — from a group of results.h5 or from a run encoded in
//! memory, through one reader ([`StoredRun`]) so that both are read alike. In: a stored run;
//! out: its plots' data.

use crate::report::schema::name;
use crate::report::schema::name as schema_name;
use crate::report::Status;
use std::path::Path;

use super::super::encoded::{Decoded, EncodedRun, Scalar};
use super::*;
use crate::fit::BackboneModel;
use crate::h5util::{read_attr, AttrValue};

/// One skeleton (backbone and force curves binned over amplitude), as stored in results.h5.
#[derive(Debug, Clone, Default)]
pub struct Skeleton {
    /// Response amplitude of each bin.
    pub amplitude: Vec<f64>,
    /// Natural frequency (Hz).
    pub natural_frequency: Vec<f64>,
    /// Restoring force per unit inertia, A·ω0².
    pub restoring_force: Vec<f64>,
    /// Velocity amplitude A·ω.
    pub velocity_amplitude: Vec<f64>,
    /// Damping force per unit inertia, 2h0·A·ω.
    pub damping_force: Vec<f64>,
}

/// Fitted parameters of one method, enough to draw the model's curves.
#[derive(Debug, Clone, Copy)]
pub struct Fitted {
    /// Backbone curve the fit used.
    pub model: BackboneModel,
    /// Half the total clearance.
    pub half_gap: f64,
    /// k/J (1/s²).
    pub stiffness: f64,
    /// c/J (1/s); NaN when not fitted.
    pub viscous: f64,
    /// F/J (units/s²); NaN when not fitted.
    pub coulomb: f64,
}

/// One method's curves of one run, read back from a results file.
#[derive(Debug, Clone)]
pub struct MethodPlots {
    /// `wavelet` or `hilbert`.
    pub method: String,
    /// The method's error, when it failed.
    pub error: Option<String>,
    /// Time (s) of the reduced track.
    pub time: Vec<f64>,
    /// Response envelope, reduced; NaN where no sample was valid.
    pub amplitude: Vec<f64>,
    /// Response frequency (Hz), reduced; NaN where no sample was valid.
    pub frequency: Vec<f64>,
    /// Input envelope on the same reduced time (empty without an input track).
    pub input_amplitude: Vec<f64>,
    /// Input frequency (Hz) on the same reduced time (empty without an input track).
    pub input_frequency: Vec<f64>,
    /// The skeleton over all bins.
    pub skeleton: Skeleton,
    /// The fitted model, when the dead-zone fit succeeded.
    pub fitted: Option<Fitted>,
    /// Unit of the response's displacement (`rad`, `m`, or `u` when the archive says none).
    pub unit: String,
    /// Unit of the input's envelope.
    pub input_unit: String,
    /// Absolute contact stiffness, viscous damping and friction with their units, where
    /// the inertia is known or estimated.
    pub absolute: Vec<(&'static str, f64, String)>,
}

/// Everything the page shows of one run.
#[derive(Debug, Clone)]
pub struct RunPlots {
    /// Run path (as in results.h5).
    pub path: String,
    /// Archive file name.
    pub source: String,
    /// `ok` or `failed`.
    pub status: Status,
    /// The run's error, when it failed.
    pub error: Option<String>,
    /// One entry per method present.
    pub methods: Vec<MethodPlots>,
}

/// Where a run's stored results are read from: a group of an HDF5 file, or a run encoded
/// in memory (the same layout before it reaches the file). Groups are relative to the run's
/// group ("" for the run's own).
pub(crate) trait StoredRun {
    /// A string attribute.
    fn text(&self, group: &str, name: &str) -> Option<String>;
    /// A number attribute (NaN when absent).
    fn number(&self, group: &str, name: &str) -> f64;
    /// A float dataset (empty when absent).
    fn floats(&self, group: &str, name: &str) -> Vec<f64>;
    /// A byte dataset (empty when absent).
    fn bytes(&self, group: &str, name: &str) -> Vec<u8>;
    /// Whether the group exists.
    fn has(&self, group: &str) -> bool;
    /// A string attribute of a dataset.
    fn dataset_text(&self, group: &str, dataset: &str, name: &str) -> Option<String>;
}

/// A run's group in an open HDF5 file.
pub(super) struct FileRun(hdf5::Group);

impl FileRun {
    fn at(&self, group: &str) -> Option<hdf5::Group> {
        if group.is_empty() {
            Some(self.0.clone())
        } else {
            self.0.group(group).ok()
        }
    }
}

impl StoredRun for FileRun {
    fn text(&self, group: &str, name: &str) -> Option<String> {
        match read_attr(&self.at(group)?.attr(name).ok()?).ok()? {
            AttrValue::Text(s) => Some(s),
            _ => None,
        }
    }

    fn number(&self, group: &str, name: &str) -> f64 {
        let v = self
            .at(group)
            .and_then(|g| g.attr(name).ok())
            .and_then(|a| read_attr(&a).ok());
        match v {
            Some(AttrValue::Number(x)) => x,
            _ => f64::NAN,
        }
    }

    fn floats(&self, group: &str, name: &str) -> Vec<f64> {
        self.at(group)
            .and_then(|g| g.dataset(name).and_then(|d| d.read_raw()).ok())
            .unwrap_or_default()
    }

    fn bytes(&self, group: &str, name: &str) -> Vec<u8> {
        self.at(group)
            .and_then(|g| g.dataset(name).and_then(|d| d.read_raw()).ok())
            .unwrap_or_default()
    }

    fn has(&self, group: &str) -> bool {
        self.at(group).is_some()
    }

    fn dataset_text(&self, group: &str, dataset: &str, name: &str) -> Option<String> {
        let attr = self.at(group)?.dataset(dataset).ok()?.attr(name).ok()?;
        match read_attr(&attr).ok()? {
            AttrValue::Text(s) => Some(s),
            _ => None,
        }
    }
}

impl StoredRun for EncodedRun {
    fn text(&self, group: &str, name: &str) -> Option<String> {
        match self.attr(group, name)? {
            Scalar::Str(s) => Some(s.clone()),
            Scalar::F64(_) => None,
        }
    }

    fn number(&self, group: &str, name: &str) -> f64 {
        match self.attr(group, name) {
            Some(Scalar::F64(x)) => *x,
            _ => f64::NAN,
        }
    }

    fn floats(&self, group: &str, name: &str) -> Vec<f64> {
        match self.read(group, name) {
            Some(Decoded::F64(v)) => v,
            _ => Vec::new(),
        }
    }

    fn bytes(&self, group: &str, name: &str) -> Vec<u8> {
        match self.read(group, name) {
            Some(Decoded::U8(v)) => v,
            _ => Vec::new(),
        }
    }

    fn has(&self, group: &str) -> bool {
        self.has_group(group)
    }

    fn dataset_text(&self, group: &str, dataset: &str, name: &str) -> Option<String> {
        self.dataset_attr_text(group, dataset, name)
            .map(str::to_string)
    }
}

/// Reads the plot data of the run at `group` of the results file `file` (a run's journal
/// file or results.h5).
pub fn read_run(file: &Path, group: &str) -> Result<RunPlots, String> {
    let f = hdf5::File::open(file).map_err(|e| format!("{}: {e}", file.display()))?;
    let g = f
        .group(group)
        .map_err(|e| format!("{}: {group}: {e}", file.display()))?;
    Ok(plots(&FileRun(g), group))
}

/// The plot data of a run encoded in memory, as [`read_run`] would read it back from the
/// file at the run's own path: the batch's workers draw the report's runs from this, so
/// that the end of a batch does not read every drawn run back from results.h5.
pub fn encoded_plots(run: &EncodedRun) -> RunPlots {
    plots(run, &run.path)
}

pub(super) fn plots(run: &dyn StoredRun, group: &str) -> RunPlots {
    let time = run.floats("", name::TIME);
    let methods = ["wavelet", "hilbert"]
        .into_iter()
        .filter(|m| run.has(m))
        .map(|m| read_method(run, m, &time))
        .collect();
    RunPlots {
        path: group.to_string(),
        source: run.text("", name::SOURCE).unwrap_or_default(),
        status: Status::parse(run.text("", name::STATUS).as_deref()),
        error: run.text("", name::ERROR),
        methods,
    }
}

pub(super) fn read_method(run: &dyn StoredRun, m: &str, time: &[f64]) -> MethodPlots {
    let valid = run.bytes(m, name::VALID);
    let (t, amplitude) = reduce(time, &run.floats(m, name::RESPONSE_AMPLITUDE), &valid);
    let (_, frequency) = reduce(time, &run.floats(m, name::RESPONSE_FREQUENCY), &valid);
    // The input's track is valid wherever it is finite: the mask is the response's.
    let input = |n: &str| {
        let v = run.floats(m, n);
        let all = vec![1u8; v.len()];
        reduce(time, &v, &all).1
    };
    let (input_amplitude, input_frequency) =
        (input(name::INPUT_AMPLITUDE), input(name::INPUT_FREQUENCY));
    let sk = format!("{m}/{}", name::SKELETON);
    let skeleton = if run.has(&sk) {
        let col = |n: &str| run.floats(&sk, n);
        Skeleton {
            amplitude: col(name::AMPLITUDE),
            natural_frequency: col(name::NATURAL_FREQUENCY),
            restoring_force: col(name::RESTORING_FORCE),
            velocity_amplitude: col(name::VELOCITY_AMPLITUDE),
            damping_force: col(name::DAMPING_FORCE),
        }
    } else {
        Skeleton::default()
    };
    let model = run
        .text(m, name::BACKBONE_MODEL)
        .and_then(|s| BackboneModel::from_name(&s));
    let (clearance, stiffness) = (run.number(m, "clearance"), run.number(m, "stiffness"));
    let fitted = model
        .filter(|_| clearance.is_finite() && stiffness.is_finite())
        .map(|model| Fitted {
            model,
            half_gap: 0.5 * clearance,
            stiffness,
            viscous: run.number(m, "viscous_damping"),
            coulomb: run.number(m, "coulomb_friction"),
        });
    let error = (run.text(m, name::STATUS).as_deref() == Some(Status::Failed.as_str()))
        .then(|| run.text(m, name::ERROR).unwrap_or_default());
    let unit = run
        .text(m, &format!("clearance{}", name::UNITS_SUFFIX))
        .unwrap_or_else(|| crate::units::UNKNOWN.into());
    let input_unit = run
        .dataset_text(m, name::INPUT_AMPLITUDE, "units")
        .unwrap_or_else(|| crate::units::UNKNOWN.into());
    let absolute = [
        ("k", "contact_stiffness"),
        ("c", "viscous_damping_absolute"),
        ("F", "coulomb_friction_absolute"),
    ]
    .into_iter()
    .filter_map(|(label, name)| {
        let v = run.number(m, name);
        v.is_finite().then(|| {
            let u = run
                .text(m, &format!("{name}{}", schema_name::UNITS_SUFFIX))
                .unwrap_or_default();
            (label, v, u)
        })
    })
    .collect();
    MethodPlots {
        method: m.to_string(),
        error,
        time: t,
        amplitude,
        frequency,
        input_amplitude,
        input_frequency,
        skeleton,
        fitted,
        unit,
        input_unit,
        absolute,
    }
}
