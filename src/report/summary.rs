//! `summary.json` and `summary.csv` (FORMATS.md §3): one row per run × method with every
//! parameter, its units and the quality verdict; columns only ever added at the end. In:
//! the runs' outcomes; out: the two files.

use std::path::Path;

use crate::units::Units;

use super::*;

/// One row of `summary.json` / `summary.csv`: a run × method.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct SummaryRow {
    /// Run path.
    pub run: String,
    /// Archive file name.
    pub source: String,
    /// Method (empty when the run could not be read).
    pub method: String,
    /// `ok` or `failed`.
    pub status: Status,
    /// Error text when failed.
    pub error: String,
    /// Fitted parameters and extras, FORMATS.md §3 names (null where not fitted).
    #[serde(flatten)]
    pub parameters: std::collections::BTreeMap<String, Option<f64>>,
    /// Warnings, joined by "; ".
    pub warnings: String,
    /// Seconds spent on this method.
    pub seconds: f64,
    /// `good`, `suspect` or `bad` ([`crate::quality`]); empty when the method failed.
    #[serde(default)]
    pub quality: String,
    /// Why, joined by "; ".
    #[serde(default)]
    pub quality_reasons: String,
    /// Whether this row is the run's recommended estimate (the first good result,
    /// wavelet first, else the first suspect one).
    #[serde(default)]
    pub recommended: bool,
    /// Unit of each parameter in `parameters` ([`crate::units`]).
    #[serde(default)]
    pub units: std::collections::BTreeMap<String, String>,
    /// Displacement, force and inertia units of the run, the three that every parameter's
    /// unit is made of (`summary.csv` has them as its last columns).
    #[serde(default)]
    pub base_units: Option<crate::units::Units>,
}

/// The summary rows of one run.
pub fn summary_rows(run: &RunOutcome) -> Vec<SummaryRow> {
    let base = |method: &str, status: Status, error: String, seconds: f64| SummaryRow {
        run: run.path.clone(),
        source: run.source.clone(),
        method: method.into(),
        status,
        error,
        parameters: Default::default(),
        warnings: String::new(),
        seconds,
        quality: String::new(),
        quality_reasons: String::new(),
        recommended: false,
        units: Default::default(),
        base_units: Some(run.units.clone()),
    };
    if let Some(e) = &run.error {
        return vec![base("", Status::Failed, e.clone(), 0.0)];
    }
    let (qualities, recommended) = run.qualities();
    run.methods
        .iter()
        .zip(qualities)
        .map(|((m, r, secs), quality)| match r {
            Err(e) => base(m.as_str(), Status::Failed, e.clone(), *secs),
            Ok(id) => {
                let mut row = base(m.as_str(), Status::Ok, String::new(), *secs);
                row.parameters = parameters(id, run.inertia)
                    .into_iter()
                    .map(|(k, v)| (k.to_string(), v.is_finite().then_some(v)))
                    .collect();
                if let Some(Ok(r)) = &run.refined {
                    for (name, v) in crate::refine::NAMES.into_iter().zip(r.values()) {
                        row.parameters
                            .insert(name.to_string(), v.is_finite().then_some(v));
                    }
                }
                row.units = row
                    .parameters
                    .keys()
                    .filter_map(|k| Some((k.clone(), run.units.parameter(k)?)))
                    .collect();
                row.warnings = id.warnings.join("; ");
                if let Some(q) = quality {
                    row.quality = q.verdict.as_str().into();
                    row.quality_reasons = q.reasons.join("; ");
                }
                row.recommended = recommended == Some(*m);
                row
            }
        })
        .collect()
}

/// Writes `<dir>/summary.json` and `<dir>/summary.csv` (each atomically).
pub fn write_summary(dir: &Path, rows: &[SummaryRow]) -> Result<(), ReportError> {
    let json = serde_json::json!({
        "format": "skelid-summary/1",
        "units": campaign_units(rows),
        "rows": rows,
    });
    let text = serde_json::to_string_pretty(&json).map_err(|e| ReportError {
        file: "summary.json".into(),
        detail: e.to_string(),
    })?;
    write_atomic(&dir.join("summary.json"), text.as_bytes())?;
    let names = PARAMETER_NAMES;
    let mut csv = String::from("run,source,method,status,");
    csv.push_str(&names.join(","));
    csv.push_str(",seconds,warnings,error,quality,quality_reasons,recommended,");
    // Added after the columns other programs already read, never between them.
    csv.push_str(&ABSOLUTE_NAMES.join(","));
    csv.push_str(",displacement_unit,force_unit,inertia_unit,");
    csv.push_str(&crate::refine::NAMES.join(","));
    csv.push(',');
    csv.push_str(&MODE_NAMES.join(","));
    csv.push('\n');
    let quote = |s: &str| format!("\"{}\"", s.replace('"', "\"\""));
    let value = |r: &SummaryRow, n: &str| match r.parameters.get(n) {
        Some(Some(v)) => format!("{v:.6e}"),
        _ => String::new(),
    };
    for r in rows {
        csv.push_str(&format!(
            "{},{},{},{},",
            quote(&r.run),
            quote(&r.source),
            r.method,
            r.status
        ));
        for n in names {
            csv.push_str(&value(r, n));
            csv.push(',');
        }
        csv.push_str(&format!(
            "{:.3},{},{},{},{},{},",
            r.seconds,
            quote(&r.warnings),
            quote(&r.error),
            r.quality,
            quote(&r.quality_reasons),
            u8::from(r.recommended)
        ));
        for n in ABSOLUTE_NAMES {
            csv.push_str(&value(r, n));
            csv.push(',');
        }
        let u = r.base_units.clone().unwrap_or_default();
        csv.push_str(&format!(
            "{},{},{}",
            quote(&u.displacement),
            quote(&u.force),
            quote(&u.inertia)
        ));
        for n in crate::refine::NAMES.into_iter().chain(MODE_NAMES) {
            csv.push(',');
            csv.push_str(&value(r, n));
        }
        csv.push('\n');
    }
    write_atomic(&dir.join("summary.csv"), csv.as_bytes())
}

/// summary.json's campaign-wide `units`: each parameter's unit where every row that has it
/// agrees, else its unit in symbols: "F s/D (D, F, J: each row's base_units)".
fn campaign_units(rows: &[SummaryRow]) -> std::collections::BTreeMap<String, String> {
    let symbols = Units {
        displacement: "D".into(),
        input: "I".into(),
        inertia: "J".into(),
        force: "F".into(),
    };
    let mut units: std::collections::BTreeMap<String, String> = Default::default();
    for r in rows {
        for (name, unit) in &r.units {
            let u = units.entry(name.clone()).or_insert_with(|| unit.clone());
            if u != unit {
                let symbolic = symbols.parameter(name).unwrap_or_default();
                *u = format!("{symbolic} (D, F, J: each row's base_units)");
            }
        }
    }
    units
}
