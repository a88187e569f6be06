//! The outputs of `skelid gap`: `gap.json` (FORMATS.md §5), the fitted model
//! (`RIG.fitted.toml`, the rig file with the verdict's effect under `[effects]`) and
//! `gap.html`, a page of plots — measured against nominal against fitted: the
//! relative-motion envelope over time, the backbone and the damping force — linked from
//! `report.html` when the output folder has one.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use plotters::style::RGBColor;
use serde_json::{json, Value};

use super::search::{signature, Score};
use super::GapRun;
use crate::identify::Identification;
use crate::report::html::{css, esc, plot, reduce, Mark, Series, YAxis};
use crate::report::{write_atomic, ReportError};
use crate::units::eng;

/// Format string of gap.json.
pub const GAP_FORMAT: &str = "skelid-gap/1";

/// A finite number, or JSON null.
fn num(v: f64) -> Value {
    if v.is_finite() {
        json!(v)
    } else {
        Value::Null
    }
}

fn domains(d: [Option<f64>; 4]) -> Value {
    let mut v = json!({
        "time": d[0].map_or(Value::Null, num),
        "backbone": d[1].map_or(Value::Null, num),
        "damping": d[2].map_or(Value::Null, num),
    });
    // Only when scored (the default; not with `--no-waveform`).
    if let Some(w) = d[3] {
        v["waveform"] = num(w);
    }
    v
}

/// A whole-run gap's domains ([`domains`]).
fn gap_domains(g: &super::Gap) -> Value {
    domains([g.time, g.backbone, g.damping, g.waveform])
}

fn score_json(s: &Score) -> Value {
    json!({"gap_fit": num(s.fit), "gap_holdout": num(s.holdout), "domains": domains(s.domains)})
}

/// The JSON of one run (FORMATS.md §5, plus the extra keys the README lists).
pub fn run_json(r: &GapRun) -> Value {
    let d = &r.diagnosis;
    let candidates: Vec<Value> = d
        .candidates
        .iter()
        .map(|c| {
            let explains: Vec<&str> = c.effects.iter().map(|(k, _)| signature(*k)).collect();
            let mut v = json!({
                "effect": c.name(),
                "params": c.params(),
                "gap_fit": num(c.score.fit),
                "gap_holdout": num(c.score.holdout),
                "shrink": num(c.shrink),
                "shrink_domains": c.shrink_domains(),
                "refined": c.refined,
                "model": c.model,
                "domains": domains(c.score.domains),
                "signature": explains.join("; "),
            });
            // Only where its shrink is not taken against the baseline.
            if let Some(a) = &c.against {
                let mut against = score_json(&a.score);
                against["model"] = json!(a.model);
                v["against"] = against;
            }
            v
        })
        .collect();
    let baseline_whole = &r.baseline.gap;
    let largest = |id: &crate::identify::Identification| {
        id.at_largest_amplitude().map_or(Value::Null, |a| {
            json!({"amplitude": num(a.amplitude), "frequency": num(a.frequency), "damping_ratio": num(a.damping_ratio)})
        })
    };
    let mut entry = json!({
        "run": d.run,
        "zero_tolerance": num(r.zero_tolerance),
        "nominal_gap": num(d.nominal_score.holdout),
        "baseline_gap": num(d.baseline.score.holdout),
        "regions": baseline_whole.regions,
        "candidates": candidates,
        "verdict": d.verdict_name(),
        "nominal": score_json(&d.nominal_score),
        "baseline": score_json(&d.baseline.score),
        "whole_run_gap": {
            "nominal": r.nominal.as_ref().map_or(Value::Null, |w| num(w.gap.total)),
            "baseline": num(r.baseline.gap.total),
            "fitted": num(r.fitted().gap.total),
        },
        "baseline_model": d.baseline.model,
        "fitted_model": d.fitted_model(),
        "cost": {"simulations": d.evaluations, "seconds": d.seconds},
        "role": r.role.name(),
        "at_largest_amplitude": {
            "measured": largest(&r.measured),
            "nominal": r.nominal.as_ref().map_or(Value::Null, |w| largest(&w.identified)),
            "baseline": largest(&r.baseline.identified),
            "fitted": largest(&r.fitted().identified),
        },
    });
    // Each model's whole-run gap by domain: which run, and which domain of it, carries what
    // a diagnosis of runs fitted together leaves.
    entry["whole_run_domains"] = json!({
        "nominal": r.nominal.as_ref().map_or(Value::Null, |w| gap_domains(&w.gap)),
        "baseline": gap_domains(&r.baseline.gap),
        "fitted": gap_domains(&r.fitted().gap),
    });
    if let Some((name, best)) = r.best_candidate() {
        entry["at_largest_amplitude"]["best_candidate"] = largest(&best.identified);
        entry["at_largest_amplitude"]["best_candidate"]["effect"] = json!(name);
        entry["whole_run_gap"]["best_candidate"] = num(best.gap.total);
        entry["whole_run_domains"]["best_candidate"] = gap_domains(&best.gap);
    }
    if let Some(rel) = &r.release {
        entry["release"] = json!(rel);
    }
    if !r.together.0.is_empty() {
        entry["fit_runs"] = json!(r.together.0);
        entry["holdout_runs"] = json!(r.together.1);
    }
    entry
}

/// The gap.json document (`skelid-gap/1`): `settings` says how the search was run,
/// `failed` lists the runs that could not be diagnosed, each with its error.
pub fn gap_document(runs: &[&GapRun], failed: &[(String, String)], settings: Value) -> Value {
    json!({
        "format": GAP_FORMAT,
        "skelid": env!("CARGO_PKG_VERSION"),
        "settings": settings,
        "runs": runs.iter().map(|r| run_json(r)).collect::<Vec<_>>(),
        "failed": failed
            .iter()
            .map(|(run, error)| json!({"run": run, "error": error}))
            .collect::<Vec<_>>(),
    })
}

/// Writes `<out>/gap.json` ([`gap_document`]) atomically.
pub fn write_gap_json(
    out: &Path,
    runs: &[&GapRun],
    failed: &[(String, String)],
    settings: Value,
) -> Result<PathBuf, ReportError> {
    let doc = gap_document(runs, failed, settings);
    let path = out.join("gap.json");
    let text = serde_json::to_string_pretty(&doc).expect("JSON values always serialise");
    write_atomic(&path, text.as_bytes())?;
    Ok(path)
}

/// Writes the fitted model to `path` (atomically), with a comment saying where it is from.
pub fn write_fitted_model(path: &Path, r: &GapRun) -> Result<(), ReportError> {
    let d = &r.diagnosis;
    let why = match d.verdict {
        Some(i) => format!(
            "verdict {} (held-out gap {:.4} against {:.4} for the refitted model alone, shrink {:.0} %)",
            d.candidates[i].name(),
            d.candidates[i].score.holdout,
            d.baseline.score.holdout,
            100.0 * d.candidates[i].shrink
        ),
        // Said of what moved, not of the option: `--refit-effects` moves the model's effects,
        // and so can a refit without it (a joint shrunk within a stiffness that fell).
        None if d.baseline.model.effects != d.nominal.effects => {
            "verdict none: the model's own parameters refitted, its effects moved with them, no effect added"
                .into()
        }
        None => "verdict none: the model's own parameters refitted, no effect added".into(),
    };
    let text = format!(
        "# Written by skelid gap {} from run {}: {why}.\n{}",
        env!("CARGO_PKG_VERSION"),
        d.run,
        d.fitted_model().to_toml()
    );
    write_atomic(path, text.as_bytes())
}

const MEASURED: RGBColor = RGBColor(20, 20, 20);
const NOMINAL: RGBColor = RGBColor(200, 60, 40);
const FITTED: RGBColor = RGBColor(31, 119, 180);

/// The envelope over time, reduced for a plot.
fn envelope(id: &Identification, offset: f64) -> (Vec<f64>, Vec<f64>) {
    let r = &id.response;
    let valid: Vec<u8> = r.valid.iter().map(|&v| v as u8).collect();
    let time: Vec<f64> = r.time().into_iter().map(|t| t + offset).collect();
    reduce(&time, &r.amplitude, &valid)
}

/// Resonant skeleton: (A, f0 Hz) and (Aω, damping force).
fn skeleton(id: &Identification) -> [Vec<f64>; 4] {
    let b = if id.resonant_bins.is_empty() {
        &id.bins
    } else {
        &id.resonant_bins
    };
    [
        b.iter().map(|b| b.amplitude).collect(),
        b.iter().map(|b| b.natural_frequency()).collect(),
        b.iter().map(|b| b.velocity).collect(),
        b.iter().map(|b| b.damping_force()).collect(),
    ]
}

/// One run's three plots on the page.
fn run_figures(r: &GapRun) -> Vec<String> {
    gap_figure_set(r, false)
        .into_iter()
        .map(|(_, svg)| svg)
        .collect()
}

/// One run's three plots (measured, nominal and fitted), each with its title; with a
/// legend when they are drawn as files.
pub fn gap_figure_set(r: &GapRun, files: bool) -> Vec<(String, String)> {
    // A nominal model whose response could not be identified has no lines.
    let ids = [
        Some(&r.measured),
        r.nominal.as_ref().map(|w| &w.identified),
        Some(&r.fitted().identified),
    ];
    let offset = r.record_offset();
    let env: Vec<(Vec<f64>, Vec<f64>)> = ids
        .iter()
        .map(|i| i.map_or_else(Default::default, |id| envelope(id, offset)))
        .collect();
    let sk: Vec<[Vec<f64>; 4]> = ids
        .iter()
        .map(|i| i.map_or_else(Default::default, skeleton))
        .collect();
    let u = r.amplitude_unit.as_str();
    let (envelope_y, amplitude_x) = (
        format!("envelope A ({u})"),
        format!("response amplitude A ({u})"),
    );
    let (velocity_x, force_y) = (
        format!("velocity amplitude A·ω ({u}/s)"),
        format!("2h0·A·ω ({u}/s²)"),
    );
    let mut figs = Vec::new();
    let mut add = |title: &str, x: &str, y: &str, axis: YAxis, series: &[Series]| {
        if let Some(svg) = plot(title, x, y, axis, series, files) {
            figs.push((title.to_string(), svg));
        }
    };
    add(
        "Relative-motion envelope over time",
        "time (s)",
        &envelope_y,
        YAxis::Full,
        &three([0, 1, 2].map(|i| (env[i].0.as_slice(), env[i].1.as_slice()))),
    );
    add(
        "Backbone at resonance",
        &amplitude_x,
        "natural frequency f0 (Hz)",
        YAxis::Fenced,
        &three([0, 1, 2].map(|i| (sk[i][0].as_slice(), sk[i][1].as_slice()))),
    );
    add(
        if r.diagnosis.nominal.kind == crate::model::ModelKind::BaseMotion {
            "Damping force per unit inertia at resonance"
        } else {
            "Damping force per unit mass at resonance"
        },
        &velocity_x,
        &force_y,
        YAxis::Fenced,
        &three([0, 1, 2].map(|i| (sk[i][2].as_slice(), sk[i][3].as_slice()))),
    );
    figs
}

/// Writes a run's three plots as files in `out/figures/RUN/` (see
/// [`crate::report::figure_files`]); returns their paths.
pub fn write_gap_figures(
    out: &Path,
    r: &GapRun,
    format: crate::report::figure_files::FigureFormat,
) -> Result<Vec<PathBuf>, ReportError> {
    use crate::report::figure_files::{folder_name, write_figures};
    let dir = out.join("figures").join(folder_name(&r.diagnosis.run));
    write_figures(&dir, &gap_figure_set(r, true), format)
}

/// Measured, nominal and fitted as three lines.
fn three<'a>(xy: [(&'a [f64], &'a [f64]); 3]) -> Vec<Series<'a>> {
    let colors = [MEASURED, NOMINAL, FITTED];
    let labels = ["measured", "nominal", "fitted"];
    let widths = [2, 1, 1];
    xy.into_iter()
        .enumerate()
        .map(|(i, (x, y))| Series {
            color: colors[i],
            width: widths[i],
            mark: Mark::Line,
            x,
            y,
            label: labels[i],
        })
        .collect()
}

/// `key = value unit` in engineering notation, for a parameter of a model of `kind`.
pub fn param_text(key: &str, value: f64, kind: crate::model::ModelKind) -> String {
    format!(
        "{key} = {}",
        eng(value, crate::model::key_unit_of(key, kind).unwrap_or(""))
    )
}

/// A gap for the page; "not identified" where the model's response could not be.
fn gap_text(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.4}")
    } else {
        "not identified".into()
    }
}

/// The page's HTML; `report` links back to report.html when there is one.
pub fn render(title: &str, runs: &[&GapRun], report: bool) -> String {
    let mut b = String::new();
    let _ = write!(
        b,
        "<h1>skelid sim-to-real gap</h1>\n<p class=\"meta\">{}{}</p>\n",
        esc(title),
        if report {
            " · <a href=\"report.html\">identification report</a>"
        } else {
            ""
        }
    );
    let _ = writeln!(
        b,
        "<p>Lines: <span style=\"color:{}\">measured</span>, <span style=\"color:{}\">nominal \
         model</span>, <span style=\"color:{}\">fitted model (the verdict's, or the refitted \
         baseline)</span>. Gaps are dimensionless (README, \"Sim-to-real gap\"); held-out gaps \
         are measured on the odd time blocks that no fit saw.</p>",
        css(MEASURED),
        css(NOMINAL),
        css(FITTED)
    );
    for r in runs {
        let d = &r.diagnosis;
        let _ = write!(
            b,
            "<h2>{}</h2>\n<p>verdict <b>{}</b> · held-out gap: nominal {}, baseline {} · \
             whole run: nominal {}, baseline {}, fitted {} · {} simulations, {:.1} s</p>\n",
            esc(&d.run),
            esc(&d.verdict_name()),
            gap_text(d.nominal_score.holdout),
            gap_text(d.baseline.score.holdout),
            gap_text(r.nominal.as_ref().map_or(f64::NAN, |w| w.gap.total)),
            gap_text(r.baseline.gap.total),
            gap_text(r.fitted().gap.total),
            d.evaluations,
            d.seconds
        );
        // The run's own gap under each model, domain by domain: which run of several, and
        // which domain of it, carries what the diagnosis leaves.
        let parts: Vec<String> = r
            .own_gaps()
            .into_iter()
            .map(|(name, g)| format!("{} {}", esc(&name), g.by_domain()))
            .collect();
        let _ = writeln!(
            b,
            "<p>this run's own gap, {}: {}</p>",
            r.baseline.gap.domains_label(),
            parts.join(" · ")
        );
        if let Some(rel) = &r.release {
            let _ = writeln!(
                b,
                "<p>A free decay: compared from t = {:.3} s of its record, {} (times here are \
                 the record's own).{}</p>",
                rel.at_s,
                esc(&rel.describe()),
                rel.warning()
                    .map_or(String::new(), |w| format!(" <b>Warning</b>: {}.", esc(&w)))
            );
        }
        let model_text = |m: &crate::model::RigModel| {
            [
                ("inertia", m.inertia),
                ("stiffness", m.stiffness),
                ("damping", m.damping),
                ("clearance", m.clearance),
                ("gravity_stiffness", m.gravity_stiffness),
            ]
            .iter()
            .map(|(k, v)| param_text(k, *v, m.kind))
            .collect::<Vec<_>>()
            .join(", ")
        };
        let _ = writeln!(
            b,
            "<p>nominal model: {}<br>refitted baseline: {}</p>",
            esc(&model_text(&d.nominal)),
            esc(&model_text(&d.baseline.model))
        );
        // The waveform domain has a column only where it was scored (not `--no-waveform`).
        let scored = if d.candidates.iter().any(|c| c.score.domains[3].is_some()) {
            4
        } else {
            3
        };
        let _ = writeln!(
            b,
            "<table><tr><th>candidate</th><th>parameters</th><th>gap (fit)</th>\
             <th>gap (held out)</th><th>shrink</th><th>held out: {}</th></tr>",
            ["time", "backbone", "damping", "waveform"][..scored].join(" / ")
        );
        for c in &d.candidates {
            let params: Vec<String> = c
                .params()
                .iter()
                .map(|(k, v)| param_text(k, *v, c.model.kind))
                .collect();
            let dom: Vec<String> = c.score.domains[..scored]
                .iter()
                .map(|x| x.map_or("–".into(), |v| format!("{v:.3}")))
                .collect();
            let _ = writeln!(
                b,
                "<tr><td>{}</td><td>{}</td><td>{:.4}</td><td>{:.4}</td><td>{:.0} %{}</td><td>{}</td></tr>",
                esc(&c.name()),
                esc(&params.join(", ")),
                c.score.fit,
                c.score.holdout,
                100.0 * c.shrink,
                if c.shrink_on_fewer_domains() {
                    format!(
                        " ({}{})",
                        c.shrink_domains().join("/"),
                        if c.against.is_some() {
                            ", against the model refitted there without it"
                        } else {
                            ""
                        }
                    )
                } else {
                    String::new()
                },
                dom.join(" / ")
            );
        }
        b.push_str("</table>\n<p>Where the refitted model's gap lies (largest shares):</p><ul>\n");
        for reg in r.baseline.gap.regions.iter().take(4) {
            let _ = writeln!(
                b,
                "<li>{}: {:.0} % — {:.1}–{:.1} s, A {}–{}, {:.2}–{:.2} Hz</li>",
                reg.domain,
                100.0 * reg.share,
                reg.t0,
                reg.t1,
                eng(reg.amp_lo, &r.amplitude_unit),
                eng(reg.amp_hi, &r.amplitude_unit),
                reg.f_lo,
                reg.f_hi
            );
        }
        b.push_str("</ul>\n<div class=\"plots\">\n");
        for f in run_figures(r) {
            let _ = writeln!(b, "<figure>{f}</figure>");
        }
        b.push_str("</div>\n");
    }
    format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>skelid gap</title><style>body{{font-family:sans-serif;margin:1.5em}}\
         table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:2px 6px;\
         text-align:left}}.plots{{display:flex;flex-wrap:wrap}}figure{{margin:4px}}\
         .meta{{color:#555}}</style></head><body>\n{b}</body></html>\n"
    )
}

/// Writes `<out>/gap.html` and, when `<out>/report.html` exists, links it from there.
pub fn write_gap_page(out: &Path, title: &str, runs: &[&GapRun]) -> Result<PathBuf, ReportError> {
    let report = out.join("report.html");
    let has_report = report.is_file();
    let path = out.join("gap.html");
    write_atomic(&path, render(title, runs, has_report).as_bytes())?;
    if has_report {
        link_from_report(&report)?;
    }
    Ok(path)
}

/// Links `gap.html` from the folder's report.html, once (the same link the batch puts
/// there when it writes the page again).
fn link_from_report(report: &Path) -> Result<(), ReportError> {
    let Ok(text) = std::fs::read_to_string(report) else {
        return Ok(());
    };
    match crate::report::html::with_gap_link(&text) {
        Some(linked) => write_atomic(report, linked.as_bytes()),
        None => Ok(()),
    }
}

/// Where the fitted model goes: `<out>/<stem>.fitted.toml` for one run, and
/// `<out>/<stem>.<run>.fitted.toml` (the run path's `/` as `_`) for each of several.
pub fn fitted_model_path(out: &Path, rig: &Path, run: &str, several: bool) -> PathBuf {
    let stem = rig
        .file_stem()
        .map_or_else(|| "rig".into(), |s| s.to_string_lossy().into_owned());
    if several {
        let tag = run.trim_matches('/').replace('/', "_");
        out.join(format!("{stem}.{tag}.fitted.toml"))
    } else {
        out.join(format!("{stem}.fitted.toml"))
    }
}
