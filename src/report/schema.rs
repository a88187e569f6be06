//! What a run's results hold, and under which names: a [`RunOutcome`] encoded into an
//! [`EncodedRun`] (datasets compressed, attributes, units) — the layout the writer puts in
//! results.h5, the journal keeps and the page reads back — and the parameter names shared by
//! the encoding, the summaries and the page. In: a run's outcome; out: its encoded results.

use crate::fit::{Bin, Estimate};
use crate::identify::Identification;
use crate::units::Units;

use super::encoded::EncodedRun;
use super::*;

/// One column of a skeleton, read off a bin.
pub(super) type BinColumn = fn(&Bin) -> f64;

/// A run's results laid out for [`ResultsWriter::write_encoded`]: pure CPU work (the
/// compression included), so the batch's workers do it in parallel, outside libhdf5's lock.
pub fn encode_run(run: &RunOutcome) -> EncodedRun {
    let mut e = EncodedRun::new(&run.path);
    e.str_attr("", name::STATUS, run.status().as_str());
    // `error` goes with `failed` only (FORMATS.md §3): a run that one method identified is
    // `ok`, and names its failed methods instead (each method's group holds its error).
    if run.status() == Status::Failed {
        if let Some(err) = run.error_text() {
            e.str_attr("", name::ERROR, &err);
        }
    } else {
        let failed: Vec<&str> = run
            .methods
            .iter()
            .filter(|m| m.1.is_err())
            .map(|m| m.0.as_str())
            .collect();
        if !failed.is_empty() {
            e.str_attr("", "failed_methods", &failed.join(","));
        }
    }
    e.str_attr("", "backend", run.backend());
    e.str_attr("", name::SOURCE, &run.source);
    let (qualities, recommended) = run.qualities();
    if let Some(m) = recommended {
        e.str_attr("", "recommended", m.as_str());
    }
    match &run.refined {
        Some(Ok(r)) => {
            for (name, value) in crate::refine::NAMES.into_iter().zip(r.values()) {
                e.f64_attr("", name, value);
                if let Some(u) = run.units.parameter(name) {
                    e.str_attr("", &format!("{name}{}", name::UNITS_SUFFIX), &u);
                }
            }
        }
        Some(Err(err)) => e.str_attr("", "refined_error", err),
        None => {}
    }
    if let Some(fs) = run.sample_rate {
        e.f64_attr("", "sample_rate", fs);
        let t: Vec<f64> = (0..run.samples).map(|i| i as f64 / fs).collect();
        e.signal("", name::TIME, &t, true);
        e.dataset_attr("", name::TIME, "units", "s");
    }
    for ((method, result, seconds), quality) in run.methods.iter().zip(&qualities) {
        let m = method.as_str();
        e.group(m);
        e.f64_attr(m, "seconds", *seconds);
        if let Some(q) = quality {
            e.str_attr(m, "quality", q.verdict.as_str());
            e.str_attr(m, "quality_reasons", &q.reasons.join("; "));
        }
        match result {
            Err(err) => {
                e.str_attr(m, name::STATUS, Status::Failed.as_str());
                e.str_attr(m, name::ERROR, err);
            }
            Ok(id) => {
                e.str_attr(m, name::STATUS, Status::Ok.as_str());
                encode_identification(&mut e, m, id, run.inertia, &run.units);
            }
        }
    }
    e
}

/// The names of what a run's results hold (FORMATS.md §3), for the writer (this file) and
/// the page's reader (`html::stored`) alike: a name changed here changes both.
pub mod name {
    /// A run's archive (attribute of the run's group).
    pub const SOURCE: &str = "source";
    /// `ok` or `failed` (attribute of a run's and of a method's group).
    pub const STATUS: &str = "status";
    /// Why it failed (attribute beside `status`).
    pub const ERROR: &str = "error";
    /// The samples' times, s (dataset of the run's group).
    pub const TIME: &str = "time";
    /// Trusted samples (dataset of a method's group).
    pub const VALID: &str = "valid";
    /// The response's envelope (dataset of a method's group).
    pub const RESPONSE_AMPLITUDE: &str = "response_amplitude";
    /// The response's instantaneous frequency, Hz (dataset of a method's group).
    pub const RESPONSE_FREQUENCY: &str = "response_frequency";
    /// The input's envelope.
    pub const INPUT_AMPLITUDE: &str = "input_amplitude";
    /// The input's frequency (Hz).
    pub const INPUT_FREQUENCY: &str = "input_frequency";
    /// The skeleton's group inside a method's group.
    pub const SKELETON: &str = "skeleton";
    /// Skeleton columns the page draws.
    pub const AMPLITUDE: &str = "amplitude";
    /// The natural frequency per bin, Hz.
    pub const NATURAL_FREQUENCY: &str = "natural_frequency";
    /// The restoring force per bin.
    pub const RESTORING_FORCE: &str = "restoring_force";
    /// The velocity amplitude per bin.
    pub const VELOCITY_AMPLITUDE: &str = "velocity_amplitude";
    /// The damping force per bin.
    pub const DAMPING_FORCE: &str = "damping_force";
    /// Which backbone model the dead zone was fitted with (attribute of a method's group).
    pub const BACKBONE_MODEL: &str = "backbone_model";
    /// A parameter's unit is the attribute `<parameter>` followed by this.
    pub const UNITS_SUFFIX: &str = "_units";
}

/// One skeleton's columns (FORMATS.md §3 names plus stiffness, spreads and counts).
pub(super) fn encode_bins(e: &mut EncodedRun, g: &str, bins: &[Bin], units: &Units) {
    let columns: [(&str, BinColumn); 9] = [
        (name::AMPLITUDE, |b| b.amplitude),
        (name::NATURAL_FREQUENCY, |b| b.natural_frequency()),
        ("stiffness", |b| b.stiffness),
        ("stiffness_spread", |b| b.stiffness_spread),
        (name::RESTORING_FORCE, |b| b.restoring_force()),
        (name::VELOCITY_AMPLITUDE, |b| b.velocity),
        (name::DAMPING_FORCE, |b| b.damping_force()),
        ("damping_spread", |b| b.damping_spread),
        ("count", |b| b.count as f64),
    ];
    e.group(g);
    for (name, f) in columns {
        let v: Vec<f64> = bins.iter().map(f).collect();
        e.signal(g, name, &v, false);
        unit(e, g, name, units.dataset(name));
    }
}

/// Sets the `units` attribute of a dataset just written.
pub(super) fn unit(e: &mut EncodedRun, group: &str, name: &str, unit: Option<String>) {
    if let Some(u) = unit {
        e.dataset_attr(group, name, "units", &u);
    }
}

pub(super) fn encode_identification(
    e: &mut EncodedRun,
    m: &str,
    id: &Identification,
    inertia: Option<f64>,
    units: &Units,
) {
    let signal = |e: &mut EncodedRun, name: &str, v: &[f64]| {
        e.signal(m, name, v, true);
        unit(e, m, name, units.dataset(name));
    };
    if let Some(inp) = &id.input {
        signal(e, name::INPUT_AMPLITUDE, &inp.amplitude);
        signal(e, name::INPUT_FREQUENCY, &inp.frequency);
    }
    signal(e, name::RESPONSE_AMPLITUDE, &id.response.amplitude);
    signal(e, name::RESPONSE_FREQUENCY, &id.response.frequency);
    signal(e, "stiffness", &id.modal.stiffness);
    signal(e, "damping", &id.modal.damping);
    let valid: Vec<u8> = id.used.iter().map(|&b| u8::from(b)).collect();
    e.bytes(m, name::VALID, &valid, 4);
    unit(e, m, name::VALID, units.dataset(name::VALID));
    encode_bins(e, &format!("{m}/{}", name::SKELETON), &id.bins, units);
    // The bins the backbone was fitted on, when not the whole skeleton.
    if id.fitted_at_resonance {
        encode_bins(
            e,
            &format!("{m}/{}_resonant", name::SKELETON),
            &id.resonant_bins,
            units,
        );
    }
    if let Some(dz) = &id.dead_zone {
        e.str_attr(m, name::BACKBONE_MODEL, dz.model.name());
    }
    e.str_attr(
        m,
        "mode_choice",
        id.mode.map_or("whole_record", |b| b.chosen.as_str()),
    );
    e.str_attr(
        m,
        "backbone_bins",
        if id.fitted_at_resonance {
            "resonant"
        } else {
            "all"
        },
    );
    // An attribute cannot carry attributes: each parameter's unit is `<name>_units`.
    for (name, value) in parameters(id, inertia) {
        e.f64_attr(m, name, value);
        if let Some(u) = units.parameter(name) {
            e.str_attr(m, &format!("{name}{}", name::UNITS_SUFFIX), &u);
        }
    }
    e.str_attr(m, "warnings", &id.warnings.join("\n"));
}

/// The fitted parameters under their FORMATS.md §3 names (NaN where not fitted), then the
/// extras: amplitude range, mass used, contact stiffness in physical units.
pub fn parameters(id: &Identification, inertia: Option<f64>) -> Vec<(&'static str, f64)> {
    let nan = f64::NAN;
    let split = |e: Option<Estimate>| e.map_or([nan, nan], |e| [e.value, e.stderr]);
    let [c, c_se] = split(id.clearance());
    let [ce, ce_se] = split(id.clearance_extrapolated());
    let [k, k_se] = split(id.dead_zone.map(|d| d.stiffness));
    let [v, v_se] = split(id.damping.map(|d| d.0));
    let [f, f_se] = split(id.damping.map(|d| d.1));
    let (a_lo, a_hi) = id.amplitude_range().unwrap_or((nan, nan));
    let mass = id.mass.map(|m| m.0).or(inertia);
    let largest = id.at_largest_amplitude();
    let at_max = largest.map_or(nan, |b| b.frequency);
    // In the order of PARAMETER_NAMES, which names them once for every output.
    let values = [
        c,
        c_se,
        ce,
        ce_se,
        k,
        k_se,
        v,
        v_se,
        f,
        f_se,
        a_lo,
        a_hi,
        mass.unwrap_or(nan),
        mass.map_or(nan, |m| m * k),
        id.mass.map_or(0.0, |m| f64::from(u8::from(m.1))),
        at_max,
    ];
    // The absolute values: the per-inertia ones times the inertia (given or estimated).
    let abs = |x: f64| mass.map_or(nan, |m| m * x);
    let absolute = [abs(k_se), abs(v), abs(v_se), abs(f), abs(f_se)];
    let zeta = largest.map_or(nan, |b| b.damping_ratio);
    let mode = [
        id.mode.map_or(nan, |m| m.peak),
        id.mode.map_or(nan, |m| m.fmin),
        id.mode.map_or(nan, |m| m.fmax),
        zeta,
    ];
    PARAMETER_NAMES
        .into_iter()
        .zip(values)
        .chain(ABSOLUTE_NAMES.into_iter().zip(absolute))
        .chain(MODE_NAMES.into_iter().zip(mode))
        .collect()
}

/// The fitted parameters (FORMATS.md §3 names) and extras, in the order of `summary.csv`'s
/// columns; [`parameters`] gives their values.
pub const PARAMETER_NAMES: [&str; 16] = [
    "clearance",
    "clearance_stderr",
    "clearance_extrapolated",
    "clearance_extrapolated_stderr",
    "stiffness",
    "stiffness_stderr",
    "viscous_damping",
    "viscous_damping_stderr",
    "coulomb_friction",
    "coulomb_friction_stderr",
    "amplitude_min",
    "amplitude_max",
    "inertia",
    "contact_stiffness",
    "inertia_estimated",
    "natural_frequency_at_amplitude_max",
];

/// The absolute parameters (inertia times the per-inertia ones, added after
/// [`PARAMETER_NAMES`]): NaN where no inertia is given or estimated. `contact_stiffness`
/// itself is among [`PARAMETER_NAMES`].
pub const ABSOLUTE_NAMES: [&str; 5] = [
    "contact_stiffness_stderr",
    "viscous_damping_absolute",
    "viscous_damping_absolute_stderr",
    "coulomb_friction_absolute",
    "coulomb_friction_absolute_stderr",
];

/// The isolated mode ([`crate::mode`]: its peak and band, Hz; NaN for the whole record)
/// and the damping ratio at the largest amplitude, added after [`ABSOLUTE_NAMES`] and the
/// refined names.
pub const MODE_NAMES: [&str; 4] = [
    "mode_frequency",
    "mode_fmin",
    "mode_fmax",
    "damping_ratio_at_amplitude_max",
];
