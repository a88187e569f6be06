//! The physical unit of every number skelid writes, worked out from what the archive says
//! of its channels (`units`, `kind`, `input_quantity`, `output_quantity`), and engineering
//! notation for people.
//!
//! skelid never converts units: a clearance comes out in the unit the response was measured
//! in (integrated to a displacement), so this module only *names* units. Where the archive
//! states none, the displacement unit is written `u` and everything else is expressed in it.

use crate::run::{Quantity, RunKind, RunMeta};

/// Placeholder for a displacement unit that the archive does not state.
pub const UNKNOWN: &str = "u";

/// The units of one run's results.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Units {
    /// Displacement of the identified channel (`rad`, `m`, ... or [`UNKNOWN`]).
    pub displacement: String,
    /// What the input channel's envelope is measured in (a force for force runs, else a
    /// displacement).
    pub input: String,
    /// Inertia J or mass m (`kg m^2`, `kg`, ...).
    pub inertia: String,
    /// Force or torque (`N m`, `N`, ...), for the absolute parameters.
    pub force: String,
}

impl Default for Units {
    fn default() -> Self {
        Units::from_parts(
            None,
            None,
            RunKind::BaseMotion,
            None,
            Quantity::Displacement,
        )
    }
}

impl Units {
    /// The units of a run, from its metadata.
    pub fn of(meta: &RunMeta) -> Units {
        let (input, output) = split_units(meta.units.as_deref());
        Units::from_parts(
            input.as_deref(),
            output.as_deref(),
            meta.kind,
            meta.input_quantity,
            meta.output_quantity,
        )
    }

    /// The units from the `units` text already split into input and output parts.
    pub fn from_parts(
        input_unit: Option<&str>,
        output_unit: Option<&str>,
        kind: RunKind,
        input_quantity: Option<Quantity>,
        output_quantity: Quantity,
    ) -> Units {
        let displacement = output_unit
            .and_then(|u| integrate(u, output_quantity))
            .unwrap_or_else(|| UNKNOWN.to_string());
        let d = displacement.as_str();
        let force_input = kind == RunKind::Force || input_quantity == Some(Quantity::Force);
        let (inertia, force) = match (force_input, input_unit) {
            (true, Some(f)) => {
                let inertia = match (f, d) {
                    ("N", "m") => "kg".to_string(),
                    ("N m" | "Nm", "rad") => "kg m^2".to_string(),
                    _ => format!("{f} s^2/{d}"),
                };
                (inertia, f.to_string())
            }
            _ => match d {
                "rad" => ("kg m^2".to_string(), "N m".to_string()),
                "m" => ("kg".to_string(), "N".to_string()),
                _ => ("J".to_string(), format!("J {d}/s^2")),
            },
        };
        let input = if force_input {
            input_unit.unwrap_or("F").to_string()
        } else {
            input_unit
                .and_then(|u| integrate(u, input_quantity.unwrap_or(Quantity::Displacement)))
                .unwrap_or_else(|| displacement.clone())
        };
        Units {
            displacement,
            input,
            inertia,
            force,
        }
    }

    /// Unit of a fitted parameter or extra, by its results.h5 / summary name; `None` for a
    /// name this module does not know (a test keeps every name known).
    pub fn parameter(&self, name: &str) -> Option<String> {
        let d = &self.displacement;
        let base = name.strip_suffix("_stderr").unwrap_or(name);
        let base = base.strip_prefix("refined_").unwrap_or(base);
        Some(match base {
            "gravity_stiffness" => "1/s^2".into(),
            "gap" | "simulations" => "1".into(),
            "clearance" | "clearance_extrapolated" | "amplitude_min" | "amplitude_max" => d.clone(),
            "stiffness" => "1/s^2".into(),
            "viscous_damping" => "1/s".into(),
            "coulomb_friction" => format!("{d}/s^2"),
            "inertia" => self.inertia.clone(),
            "contact_stiffness" => self.per_displacement(""),
            "viscous_damping_absolute" => self.per_displacement(" s"),
            "coulomb_friction_absolute" => self.force.clone(),
            "inertia_estimated" => "1".into(),
            "natural_frequency_at_amplitude_max" | "mode_frequency" | "mode_fmin" | "mode_fmax" => {
                "Hz".into()
            }
            "damping_ratio_at_amplitude_max" => "1".into(),
            _ => return None,
        })
    }

    /// The force unit times `times` per displacement unit: "N m s/rad"; a force written in
    /// the displacement unit ("J u/s^2", where the archive gave no units) cancels it
    /// ("J s/s^2" is said "J/s").
    fn per_displacement(&self, times: &str) -> String {
        let d = &self.displacement;
        match self.force.strip_suffix(&format!(" {d}/s^2")) {
            Some(mass) if times.is_empty() => format!("{mass}/s^2"),
            Some(mass) => format!("{mass}/s"),
            None => format!("{}{times}/{d}", self.force),
        }
    }

    /// Unit of a per-sample or skeleton dataset, by its results.h5 name.
    pub fn dataset(&self, name: &str) -> Option<String> {
        let d = &self.displacement;
        Some(match name {
            "time" => "s".into(),
            "input_amplitude" => self.input.clone(),
            "response_amplitude" | "amplitude" => d.clone(),
            "input_frequency" | "response_frequency" | "natural_frequency" => "Hz".into(),
            "stiffness" | "stiffness_spread" => "1/s^2".into(),
            "damping" => "1/s".into(),
            "damping_spread" => "1/s".into(),
            "restoring_force" | "damping_force" => format!("{d}/s^2"),
            "velocity_amplitude" => format!("{d}/s"),
            "valid" | "count" => "1".into(),
            _ => return None,
        })
    }
}

/// Splits an archive's `units` text into its input and output parts: "input N, output
/// m/s^2" names both; a single unit ("rad") applies to both channels.
pub fn split_units(text: Option<&str>) -> (Option<String>, Option<String>) {
    let Some(text) = text.map(str::trim).filter(|t| !t.is_empty()) else {
        return (None, None);
    };
    let mut input = None;
    let mut output = None;
    for part in text.split([',', ';']) {
        let part = part.trim();
        if let Some(u) = part.strip_prefix("input") {
            input = Some(u.trim_start_matches([':', '=', ' ']).trim().to_string());
        } else if let Some(u) = part.strip_prefix("output") {
            output = Some(u.trim_start_matches([':', '=', ' ']).trim().to_string());
        }
    }
    if input.is_none() && output.is_none() {
        return (Some(text.to_string()), Some(text.to_string()));
    }
    (
        input.filter(|u| !u.is_empty()),
        output.filter(|u| !u.is_empty()),
    )
}

/// The displacement unit of a channel measured in `unit` as `quantity`: `m/s^2` as an
/// acceleration is `m`. `None` when the unit does not end the way the quantity says.
fn integrate(unit: &str, quantity: Quantity) -> Option<String> {
    let unit = unit.trim();
    let stripped = match quantity {
        Quantity::Displacement => Some(unit),
        Quantity::Velocity => unit.strip_suffix("/s"),
        Quantity::Acceleration => ["/s^2", "/s²", "/s2", "/s/s"]
            .iter()
            .find_map(|s| unit.strip_suffix(s)),
        Quantity::Force => None,
    };
    stripped
        .map(str::trim)
        .filter(|u| !u.is_empty())
        .map(str::to_string)
}

/// A number in engineering notation with its unit: `0.0262 rad` → "26.2 mrad",
/// `15000 N m/rad` → "15.0 kN m/rad". SI prefixes go on simple leading units (`m`, `N`, `s`,
/// `Hz`, `rad`); other units, such as `1/s^2`, take the number as it is from 0.01 to 9999
/// and a power of ten in steps of three beyond ("26.0e3 1/s^2"). NaN prints as "—".
pub fn eng(value: f64, unit: &str) -> String {
    if !value.is_finite() {
        return "—".into();
    }
    if value == 0.0 {
        return join("0", unit);
    }
    let exp3 = (value.abs().log10() / 3.0).floor() as i32;
    let (head, tail) = match unit.split_once(' ') {
        Some((h, t)) => (h, Some(t)),
        None => (unit, None),
    };
    let head_base = head.split('/').next().unwrap_or("");
    let prefixable =
        matches!(head_base, "m" | "N" | "s" | "Hz" | "rad" | "g") && (-6..=4).contains(&exp3);
    // Numbers from 0.01 to 9999 read best as they are when no prefix applies.
    let plain = !prefixable && (1e-2..1e4).contains(&value.abs());
    let exp3 = if plain { 0 } else { exp3 };
    let mantissa = value / 10f64.powi(3 * exp3);
    let m = three_digits(mantissa);
    if exp3 == 0 {
        return join(&m, unit);
    }
    if prefixable {
        let prefix = ["a", "f", "p", "n", "µ", "m", "", "k", "M", "G", "T"][(exp3 + 6) as usize];
        let unit = match tail {
            Some(t) => format!("{prefix}{head} {t}"),
            None => format!("{prefix}{head}"),
        };
        join(&m, &unit)
    } else {
        join(&format!("{m}e{}", 3 * exp3), unit)
    }
}

/// A number with three significant digits (more before the point when it is ≥ 1000).
fn three_digits(x: f64) -> String {
    let a = x.abs();
    let digits = if a >= 100.0 {
        0
    } else if a >= 10.0 {
        1
    } else if a >= 1.0 {
        2
    } else if a >= 0.1 {
        3
    } else {
        4
    };
    format!("{x:.digits$}")
}

/// `value unit`, or the value alone for a dimensionless unit.
fn join(value: &str, unit: &str) -> String {
    if unit.is_empty() || unit == "1" {
        value.to_string()
    } else {
        format!("{value} {unit}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn force_units() -> Units {
        let (i, o) = split_units(Some("input N, output m/s^2"));
        Units::from_parts(
            i.as_deref(),
            o.as_deref(),
            RunKind::Force,
            Some(Quantity::Force),
            Quantity::Acceleration,
        )
    }

    #[test]
    fn the_f16_archive_text_gives_metres_newtons_and_kilograms() {
        let u = force_units();
        assert_eq!(u.displacement, "m");
        assert_eq!(u.force, "N");
        assert_eq!(u.inertia, "kg");
        assert_eq!(u.input, "N");
        assert_eq!(u.parameter("coulomb_friction").unwrap(), "m/s^2");
        assert_eq!(u.parameter("contact_stiffness").unwrap(), "N/m");
        assert_eq!(u.parameter("viscous_damping_absolute").unwrap(), "N s/m");
        assert_eq!(u.dataset("input_amplitude").unwrap(), "N");
        assert_eq!(u.dataset("response_amplitude").unwrap(), "m");
    }

    #[test]
    fn a_rotational_base_motion_rig_gives_radians_and_newton_metres() {
        let u = Units::from_parts(
            Some("rad"),
            Some("rad"),
            RunKind::BaseMotion,
            Some(Quantity::Displacement),
            Quantity::Displacement,
        );
        assert_eq!(u.parameter("clearance_stderr").unwrap(), "rad");
        assert_eq!(u.parameter("inertia").unwrap(), "kg m^2");
        assert_eq!(u.parameter("contact_stiffness").unwrap(), "N m/rad");
        assert_eq!(
            u.parameter("viscous_damping_absolute").unwrap(),
            "N m s/rad"
        );
        assert_eq!(u.parameter("coulomb_friction_absolute").unwrap(), "N m");
        assert_eq!(u.parameter("stiffness").unwrap(), "1/s^2");
    }

    #[test]
    fn an_archive_without_units_says_u_and_an_acceleration_that_does_not_end_in_s2_too() {
        assert_eq!(Units::default().displacement, UNKNOWN);
        let u = Units::from_parts(None, Some("g"), RunKind::Free, None, Quantity::Acceleration);
        assert_eq!(u.displacement, UNKNOWN);
        assert_eq!(u.parameter("coulomb_friction").unwrap(), "u/s^2");
        assert_eq!(u.parameter("contact_stiffness").unwrap(), "J/s^2");
        assert_eq!(u.parameter("viscous_damping_absolute").unwrap(), "J/s");
        assert_eq!(u.parameter("coulomb_friction_absolute").unwrap(), "J u/s^2");
    }

    #[test]
    fn every_name_written_has_a_unit() {
        let u = force_units();
        for name in crate::report::PARAMETER_NAMES
            .iter()
            .chain(crate::report::ABSOLUTE_NAMES.iter())
            .chain(crate::refine::NAMES.iter())
            .chain(crate::report::MODE_NAMES.iter())
        {
            assert!(u.parameter(name).is_some(), "{name}");
        }
        for name in [
            "time",
            "input_amplitude",
            "input_frequency",
            "response_amplitude",
            "response_frequency",
            "stiffness",
            "damping",
            "valid",
            "amplitude",
            "natural_frequency",
            "stiffness_spread",
            "restoring_force",
            "velocity_amplitude",
            "damping_force",
            "damping_spread",
            "count",
        ] {
            assert!(u.dataset(name).is_some(), "{name}");
        }
    }

    #[test]
    fn engineering_notation_uses_si_prefixes_on_simple_units_and_powers_of_ten_otherwise() {
        assert_eq!(eng(0.0262, "rad"), "26.2 mrad");
        assert_eq!(eng(15000.0, "N m/rad"), "15.0 kN m/rad");
        assert_eq!(eng(1710.0, "1/s^2"), "1710 1/s^2");
        assert_eq!(eng(26000.0, "1/s^2"), "26.0e3 1/s^2");
        assert_eq!(eng(-1.44, "1/s"), "-1.44 1/s");
        assert_eq!(eng(2.5e-18, "rad"), "2.50 arad");
        assert_eq!(eng(-0.048, "m/s^2"), "-48.0 mm/s^2");
        assert_eq!(eng(7.25, "Hz"), "7.25 Hz");
        assert_eq!(eng(0.0, "m"), "0 m");
        assert_eq!(eng(f64::NAN, "m"), "—");
        assert_eq!(eng(0.5, "1"), "0.500");
        assert_eq!(eng(2.6e-5, "u"), "26.0e-6 u");
    }
}
