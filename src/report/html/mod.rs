//! `report.html`: one self-contained page per output folder. It holds the campaign summary
//! (a sortable table of every run × method) and, per run, the paper's Figs. 10–13: the
//! envelope and frequency tracks of both methods, the backbone with the fitted dead-zone
//! curve, and the restoring and damping forces against amplitude.
//!
//! Plots are inline SVG drawn with plotters; their text is SVG `<text>`, laid out by the
//! browser. The page therefore reads offline and needs no fonts on the machine that writes
//! it. A small script on the page checks itself on load: it counts the plots and confirms
//! each one was drawn, records script errors, and writes the outcome to the `<body>`'s
//! `data-check` attribute, which the headless-browser test reads back.

mod figures;
mod stored;

use crate::report::Status;
pub(crate) use figures::plot;
pub use figures::run_figure_set;
pub(crate) use figures::{esc, reduce, svg_plot, Mark, Series, YAxis};
use figures::{fit_color, method_color, run_figures};
pub use stored::{encoded_plots, read_run, Fitted, MethodPlots, RunPlots, Skeleton};

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use plotters::prelude::*;

use super::{write_atomic, ReportError, SummaryRow};
use crate::units::eng;

/// Points a time track is reduced to: enough for a plot 560 pixels wide.
pub(super) const TRACK_POINTS: usize = 400;
/// Size of one plot (pixels).
pub(super) const PLOT_SIZE: (u32, u32) = (560, 300);
/// Points along a fitted curve.
pub(super) const CURVE_POINTS: usize = 160;

/// What goes on the page beyond the runs themselves.
pub struct ReportPage<'a> {
    /// Heading (the output folder).
    pub title: &'a str,
    /// The settings fingerprint of the batch.
    pub settings: &'a str,
    /// Every summary row (run × method), in the manifest's order.
    pub rows: &'a [SummaryRow],
    /// The runs drawn in full, in order; an `Err` is shown as the reason a run has no plots.
    pub runs: Vec<Result<DrawnRun, String>>,
    /// Runs in `rows` not drawn (beyond the `--report-runs` limit).
    pub omitted: usize,
    /// What in the inputs wants a look, one line each: archives given up part-way with runs
    /// left unread, damaged archives, groups that hold datasets but are not runs (the
    /// manifest's `incomplete_archives`, `damaged_archives` and `not_runs`).
    pub inputs_to_check: &'a [String],
}

/// One run as the page shows it: its plots' data and its figures, drawn beforehand. A batch
/// draws each run on the worker that finished it, so that its end, serial for a good part,
/// only assembles the page (drawing a hundred runs there was 60 ms of a 200-run batch's
/// 170 ms end on 2 cores).
#[derive(Debug, Clone)]
pub struct DrawnRun {
    /// What the run's text on the page is made from.
    pub run: RunPlots,
    /// The run's figures, SVG.
    pub figures: Vec<String>,
}

impl DrawnRun {
    /// Draws the figures of `run`, then lets go of its curves: the page's text needs the
    /// fitted values alone, and a batch holds up to `--report-runs` of these until its end.
    pub fn new(mut run: RunPlots) -> DrawnRun {
        let figures = run_figures(&run);
        for m in &mut run.methods {
            m.time = Vec::new();
            m.amplitude = Vec::new();
            m.frequency = Vec::new();
            m.input_amplitude = Vec::new();
            m.input_frequency = Vec::new();
            m.skeleton = Skeleton::default();
        }
        DrawnRun { run, figures }
    }
}

/// Table columns beyond run/source/method/status: (parameter, header). Each cell carries
/// its own unit, since runs of one campaign may differ (rad against m).
const TABLE_COLUMNS: [(&str, &str); 8] = [
    ("clearance", "clearance (total)"),
    ("stiffness", "k/J"),
    ("viscous_damping", "c/J"),
    ("coulomb_friction", "F/J"),
    ("contact_stiffness", "k (contact)"),
    ("viscous_damping_absolute", "c (viscous)"),
    ("coulomb_friction_absolute", "F (friction)"),
    (
        "natural_frequency_at_amplitude_max",
        "f at largest amplitude",
    ),
];

/// Columns of the simulation-refined estimates (`--refine`), shown when a row has them.
const REFINED_COLUMNS: [(&str, &str); 4] = [
    ("refined_clearance", "clearance (refined)"),
    ("refined_stiffness", "k/J (refined)"),
    ("refined_viscous_damping", "c/J (refined)"),
    ("refined_coulomb_friction", "F/J (refined)"),
];

/// Columns of the isolated mode (force and free runs, `--band`, `--mode-near`), shown when
/// a row has them.
const MODE_COLUMNS: [(&str, &str); 4] = [
    ("mode_frequency", "mode peak"),
    ("mode_fmin", "band from"),
    ("mode_fmax", "band to"),
    ("damping_ratio_at_amplitude_max", "ζ at largest amplitude"),
];

/// Writes `<out>/report.html` (atomically) and returns its path.
pub fn write_report(out: &Path, page: &ReportPage) -> Result<PathBuf, ReportError> {
    let path = out.join("report.html");
    let mut html = render(page);
    // A diagnosis `skelid gap` wrote into this folder stays linked when the batch writes
    // its page again (a rerun, even one that skips every run, dropped the link).
    if out.join("gap.html").is_file() {
        html = with_gap_link(&html).unwrap_or(html);
    }
    write_atomic(&path, html.as_bytes())?;
    Ok(path)
}

/// The link to the folder's `gap.html` (`skelid gap`'s page), under the report's title.
const GAP_LINK: &str =
    "<p class=\"meta\"><a href=\"gap.html\">sim-to-real gap (skelid gap)</a></p>\n";

/// A report page with the link to `gap.html` under its title; `None` when it has the link
/// already or no title to put it under.
pub fn with_gap_link(html: &str) -> Option<String> {
    if html.contains("href=\"gap.html\"") {
        return None;
    }
    let at = html.find("</h1>")? + "</h1>".len();
    let mut out = String::with_capacity(html.len() + GAP_LINK.len() + 1);
    out.push_str(&html[..at]);
    out.push('\n');
    out.push_str(GAP_LINK);
    out.push_str(&html[at..]);
    Some(out)
}

/// The page's HTML.
pub fn render(page: &ReportPage) -> String {
    let mut body = String::new();
    let mut plots = 0usize;
    let runs_total = {
        let mut seen: Vec<(&str, &str)> = page
            .rows
            .iter()
            .map(|r| (r.source.as_str(), r.run.as_str()))
            .collect();
        seen.dedup();
        seen.len()
    };
    let failed_rows = page.rows.iter().filter(|r| r.status != Status::Ok).count();
    // A run failed when every one of its rows did (the terminal and results.h5 count so).
    let failed_runs = {
        let mut runs: std::collections::BTreeMap<(&str, &str), bool> = Default::default();
        for r in page.rows {
            *runs
                .entry((r.source.as_str(), r.run.as_str()))
                .or_insert(true) &= r.status != Status::Ok;
        }
        runs.values().filter(|&&f| f).count()
    };
    let _ = write!(
        body,
        "<h1>skelid report</h1>\n<p class=\"meta\">{} · {} run(s), {} failed · {} row(s) \
         (run × method), {} failed; {} suspect, {} bad · settings <code>{}</code> · skelid {}</p>\n",
        esc(page.title),
        runs_total,
        failed_runs,
        page.rows.len(),
        failed_rows,
        page.rows.iter().filter(|r| r.quality == "suspect").count(),
        page.rows.iter().filter(|r| r.quality == "bad").count(),
        esc(page.settings),
        env!("CARGO_PKG_VERSION")
    );
    // Above the results: the morning's reader sees first what the night could not use.
    if !page.inputs_to_check.is_empty() {
        body.push_str("<h2>Inputs to check</h2>\n<ul class=\"warn\">\n");
        for line in page.inputs_to_check {
            let _ = writeln!(body, "<li>{}</li>", esc(line));
        }
        body.push_str("</ul>\n");
    }
    body.push_str(&legend());
    // Campaign overview: the identified clearance and stiffness of every row.
    body.push_str("<h2>Campaign</h2>\n<div class=\"plots\">\n");
    for (param, label) in [("clearance", "clearance (total)"), ("stiffness", "k/J")] {
        // The axis names the unit when every row agrees on it.
        let units: std::collections::BTreeSet<&String> = page
            .rows
            .iter()
            .filter_map(|r| r.units.get(param))
            .collect();
        let label = match units.iter().next() {
            Some(u) if units.len() == 1 => format!("{label} ({u})"),
            _ => label.to_string(),
        };
        let label = label.as_str();
        let per_method = |method: &str| -> (Vec<f64>, Vec<f64>) {
            page.rows
                .iter()
                .enumerate()
                .filter(|(_, r)| r.method == method)
                .map(|(i, r)| {
                    let v = r.parameters.get(param).copied().flatten();
                    (i as f64, v.unwrap_or(f64::NAN))
                })
                .unzip()
        };
        let (w, h) = (per_method("wavelet"), per_method("hilbert"));
        let series = [
            Series {
                color: method_color("wavelet"),
                width: 1,
                mark: Mark::Points,
                x: &w.0,
                y: &w.1,
                label: "",
            },
            Series {
                color: method_color("hilbert"),
                width: 1,
                mark: Mark::Points,
                x: &h.0,
                y: &h.1,
                label: "",
            },
        ];
        if let Some(svg) = svg_plot(
            &format!("Identified {label} per row of the table"),
            "row",
            label,
            YAxis::Fenced,
            &series,
        ) {
            plots += 1;
            let _ = writeln!(body, "<figure class=\"plot\">{svg}</figure>");
        }
    }
    body.push_str("</div>\n");
    body.push_str(&table(page));
    body.push_str("<h2>Runs</h2>\n");
    if page.omitted > 0 {
        let _ = writeln!(
            body,
            "<p class=\"note\">{} more run(s) are in the table but not drawn; raise \
             <code>{}</code> to draw them.</p>",
            page.omitted,
            crate::hint::Hint::ReportRuns
        );
    }
    for (i, drawn) in page.runs.iter().enumerate() {
        let _ = writeln!(body, "<section id=\"run-{i}\">");
        match drawn {
            Err(e) => {
                let _ = writeln!(
                    body,
                    "<h3>run {i}</h3><p class=\"error\">could not read its results: {}</p>",
                    esc(e)
                );
            }
            Ok(DrawnRun { run, figures }) => {
                let _ = writeln!(
                    body,
                    "<h3>{} <small>{} · {}</small></h3>",
                    esc(&run.path),
                    esc(&run.source),
                    esc(run.status.as_str())
                );
                if let Some(e) = &run.error {
                    let _ = writeln!(body, "<p class=\"error\">{}</p>", esc(e));
                }
                for m in &run.methods {
                    let _ = writeln!(body, "<p>{}</p>", fitted_line(m));
                }
                if !figures.is_empty() {
                    body.push_str("<div class=\"plots\">\n");
                    for svg in figures {
                        plots += 1;
                        let _ = writeln!(body, "<figure class=\"plot\">{svg}</figure>");
                    }
                    body.push_str("</div>\n");
                }
            }
        }
        body.push_str("</section>\n");
    }
    format!(
        "<!doctype html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <title>skelid report — {title}</title>\n<script>{ERRORS_JS}</script>\n\
         <style>{CSS}</style>\n</head>\n<body data-plots=\"{plots}\">\n{body}\
         <script>{PAGE_JS}</script>\n</body>\n</html>\n",
        title = esc(page.title)
    )
}

/// The method colours, explained once for every plot.
fn legend() -> String {
    let swatch = |m: &str| {
        let RGBColor(r, g, b) = method_color(m);
        let RGBColor(fr, fg, fb) = fit_color(m);
        format!(
            "<span class=\"key\"><span style=\"background:rgb({r},{g},{b})\"></span>{m} \
             <span style=\"background:rgb({fr},{fg},{fb})\"></span>{m} fit</span>"
        )
    };
    format!(
        "<p class=\"legend\">{} {} — tracks are lines, skeleton bins are circles, fitted \
         models are dark lines. Amplitudes are in the run's displacement unit (from its \
         <code>units</code> attribute; <code>u</code> where it has none), forces per unit \
         inertia. Frequency and force axes leave out outliers (beyond three \
         interquartile ranges), which are then not drawn.</p>\n",
        swatch("wavelet"),
        swatch("hilbert")
    )
}

/// One method's fitted parameters or error, as one line of text.
fn fitted_line(m: &MethodPlots) -> String {
    let name = format!(
        "<b style=\"color:{}\">{}</b>",
        css(method_color(&m.method)),
        m.method
    );
    if let Some(e) = &m.error {
        return format!("{name}: <span class=\"error\">failed: {}</span>", esc(e));
    }
    let u = m.unit.as_str();
    let absolute: String = m
        .absolute
        .iter()
        .map(|(label, v, unit)| format!(" · {label} {}", eng(*v, unit)))
        .collect();
    match &m.fitted {
        None => format!("{name}: no dead-zone fit"),
        Some(f) => format!(
            "{name}: clearance {} · k/J {} · c/J {} · F/J {}{absolute} · backbone {}",
            eng(2.0 * f.half_gap, u),
            eng(f.stiffness, "1/s²"),
            eng(f.viscous, "1/s"),
            eng(f.coulomb, &format!("{u}/s²")),
            f.model.name()
        ),
    }
}

/// A colour as CSS `rgb(…)`.
pub(crate) fn css(c: RGBColor) -> String {
    format!("rgb({},{},{})", c.0, c.1, c.2)
}

/// The sortable summary table: one row per run × method.
fn table(page: &ReportPage) -> String {
    let mut t = String::from(
        "<h2>Summary</h2>\n<p class=\"note\">Click a column header to sort. ★ marks each \
         run's recommended estimate (its first good result, wavelet first, else the first \
         suspect one); hover a quality for its reasons.</p>\n\
         <table class=\"sortable\" id=\"summary\">\n<thead><tr><th>run</th><th>archive</th>\
         <th>method</th><th>status</th><th>quality</th>",
    );
    let refined = page.rows.iter().any(|r| {
        r.parameters
            .get("refined_clearance")
            .is_some_and(|v| v.is_some())
    });
    let isolated = page.rows.iter().any(|r| {
        r.parameters
            .get("mode_frequency")
            .is_some_and(|v| v.is_some())
    });
    let columns: Vec<(&str, &str)> = TABLE_COLUMNS
        .into_iter()
        .chain(MODE_COLUMNS.into_iter().filter(|_| isolated))
        .chain(REFINED_COLUMNS.into_iter().filter(|_| refined))
        .collect();
    for (_, header) in &columns {
        let _ = write!(t, "<th>{}</th>", esc(header));
    }
    t.push_str("<th>seconds</th><th>error / warnings</th></tr></thead>\n<tbody>\n");
    // Section index of each drawn run, by (archive, run path) as the rows name them.
    let drawn: std::collections::HashMap<(&str, &str), usize> = page
        .runs
        .iter()
        .enumerate()
        .filter_map(|(i, r)| {
            r.as_ref()
                .ok()
                .map(|d| ((d.run.source.as_str(), d.run.path.as_str()), i))
        })
        .collect();
    for r in page.rows {
        let run = match drawn.get(&(r.source.as_str(), r.run.as_str())) {
            Some(i) => format!("<a href=\"#run-{i}\">{}</a>", esc(&r.run)),
            None => esc(&r.run),
        };
        // The recommended estimate is marked; a verdict other than good carries its reasons.
        let method = if r.recommended {
            format!("<b>{}</b> ★", esc(&r.method))
        } else {
            esc(&r.method)
        };
        let _ = write!(
            t,
            "<tr class=\"{}\"><td>{run}</td><td>{}</td><td>{method}</td><td>{}</td>\
             <td class=\"q-{}\" title=\"{}\">{}</td>",
            esc(r.status.as_str()),
            esc(&r.source),
            esc(r.status.as_str()),
            esc(&r.quality),
            esc(&r.quality_reasons),
            esc(&r.quality)
        );
        for &(name, _) in &columns {
            match r.parameters.get(name).copied().flatten() {
                Some(v) => {
                    let unit = r.units.get(name).map_or("", String::as_str);
                    let se = r
                        .parameters
                        .get(&format!("{name}_stderr"))
                        .copied()
                        .flatten();
                    // A value within its standard error of zero is shown as zero, with
                    // the resolution, not as noise (2.5e-18 rad).
                    let text = match se {
                        Some(se) if name == "clearance" && v.abs() < se => {
                            format!("0 (± {})", eng(se, unit))
                        }
                        // The refined estimates carry their two-fit error.
                        Some(se) if name.starts_with("refined_") => {
                            format!("{} ± {}", eng(v, unit), eng(se, unit))
                        }
                        _ => eng(v, unit),
                    };
                    let _ = write!(t, "<td data-v=\"{v:e}\">{}</td>", esc(&text));
                }
                None => t.push_str("<td></td>"),
            }
        }
        let reasons;
        let note = if !r.error.is_empty() {
            &r.error
        } else if r.quality == "suspect" || r.quality == "bad" {
            reasons = format!("{}: {}", r.quality, r.quality_reasons);
            &reasons
        } else {
            &r.warnings
        };
        // Long notes are cut in the cell; the whole text is the cell's tooltip.
        let cut: String = note.chars().take(80).collect();
        let more = if cut.len() < note.len() { "…" } else { "" };
        let _ = writeln!(
            t,
            "<td data-v=\"{s:e}\">{s:.2}</td><td class=\"text\" title=\"{}\">{}{more}</td></tr>",
            esc(note),
            esc(&cut),
            s = r.seconds
        );
    }
    t.push_str("</tbody>\n</table>\n");
    t
}

const CSS: &str = "body{font-family:sans-serif;margin:1.5em;color:#222}\
h3 small{font-weight:normal;color:#666}\
table{border-collapse:collapse;font-size:0.85em}\
th,td{border:1px solid #ccc;padding:2px 6px;text-align:right}\
td.text,td:first-child,td:nth-child(2),td:nth-child(3){text-align:left}\
td.text{min-width:24em}\
th{cursor:pointer;background:#f2f2f2;position:sticky;top:0}\
tr.failed td{background:#fde8e8}td.q-suspect{background:#fff4d6}td.q-bad{background:#fde8e8;font-weight:bold}\
.error{color:#b00}.warn{color:#8a5300}.note,.meta{color:#555}\
.plots{display:flex;flex-wrap:wrap;gap:8px}\
figure.plot{margin:0}\
.legend .key span{display:inline-block;width:12px;height:12px;margin:0 4px 0 10px}\
section{border-top:1px solid #ddd;margin-top:1em}";

/// Runs first, in `<head>`: collects every script error on the page.
const ERRORS_JS: &str =
    "window.skelidErrors=[];window.addEventListener('error',function(e){skelidErrors.push(String(e.message));});";

/// Column sorting, and the self-check the headless-browser test reads from `data-check`.
const PAGE_JS: &str = r#"
document.querySelectorAll('table.sortable th').forEach(function(th, col) {
  th.addEventListener('click', function() {
    var body = th.closest('table').tBodies[0];
    var rows = Array.prototype.slice.call(body.rows);
    var asc = th.dataset.order !== 'asc';
    th.dataset.order = asc ? 'asc' : 'desc';
    var key = function(r) {
      var c = r.cells[col], t = c.dataset.v !== undefined ? c.dataset.v : c.textContent;
      var n = parseFloat(t);
      return isNaN(n) ? t : n;
    };
    rows.sort(function(a, b) {
      var x = key(a), y = key(b);
      var d = (typeof x === 'number' && typeof y === 'number') ? x - y
            : String(x).localeCompare(String(y));
      return asc ? d : -d;
    });
    rows.forEach(function(r) { body.appendChild(r); });
  });
});
window.addEventListener('load', function() {
  var svgs = document.querySelectorAll('figure.plot svg'), drawn = 0;
  svgs.forEach(function(s) {
    var b = s.getBBox();
    var marks = s.querySelectorAll('polyline, circle, path, line').length;
    if (b.width > 0 && b.height > 0 && marks > 0) drawn++;
  });
  document.body.setAttribute('data-check', 'expected=' + document.body.dataset.plots +
    ' found=' + svgs.length + ' drawn=' + drawn + ' errors=' + skelidErrors.length +
    (skelidErrors.length ? ' first-error=' + skelidErrors[0] : ''));
});
"#;

#[cfg(test)]
mod tests {
    use super::figures::short;
    use super::*;
    use crate::report::encoded::EncodedRun;

    /// The batch draws its report from runs in memory; the page must be what reading the
    /// same runs back from results.h5 gives (a failed method and a failed run included).
    #[test]
    fn plots_of_an_encoded_run_equal_those_read_back_from_the_file() {
        use crate::identify::{identify, IdentifyOptions};
        use crate::report::{encode_run, ResultsWriter, RunOutcome};
        let case = crate::demo::cases().remove(0);
        let run = crate::rig::simulate_case(&case).into_run();
        let backend = crate::backend::Backend::cpu();
        let mut ok = RunOutcome::new("/runs/a".into(), "demo.h5".into());
        ok.sample_rate = Some(run.meta.sample_rate);
        ok.samples = run.output.len();
        ok.inertia = run.meta.inertia;
        ok.units = crate::units::Units::of(&run.meta);
        for m in [crate::track::Method::Wavelet, crate::track::Method::Hilbert] {
            let id = identify(&run, m, &IdentifyOptions::default(), &backend);
            assert!(id.is_ok(), "{m:?} identifies the demo rig");
            ok.methods.push((m, id.map_err(|e| e.to_string()), 1.0));
        }
        ok.methods[1].1 = Err("the Hilbert track failed".into());
        let mut failed = RunOutcome::new("/runs/b".into(), "demo.h5".into());
        failed.error = Some("no output channel".into());
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("results.h5");
        let w = ResultsWriter::create_at(&file).unwrap();
        let encoded: Vec<EncodedRun> = [&ok, &failed].map(encode_run).into();
        for e in &encoded {
            w.write_encoded(e).unwrap();
        }
        w.finish().unwrap();
        for e in &encoded {
            let from_file = read_run(&file, &e.path).unwrap();
            let from_memory = encoded_plots(e);
            // Debug text compares NaN (a break in a reduced track) as equal to itself.
            assert_eq!(format!("{from_memory:?}"), format!("{from_file:?}"));
        }
        let drawn = encoded_plots(&encoded[0]);
        assert_eq!(drawn.methods.len(), 2);
        assert!(
            drawn.methods[0].fitted.is_some() && !drawn.methods[0].skeleton.amplitude.is_empty()
        );
        assert!(drawn.methods[1].error.is_some());
    }

    #[test]
    fn reduce_averages_valid_samples_and_breaks_on_gaps() {
        let n = 4 * TRACK_POINTS;
        let t: Vec<f64> = (0..n).map(|i| i as f64).collect();
        let y: Vec<f64> = (0..n).map(|i| i as f64 * 2.0).collect();
        let mut valid = vec![1u8; n];
        valid[..8].iter_mut().for_each(|v| *v = 0);
        let (rt, ry) = reduce(&t, &y, &valid);
        assert_eq!(rt.len(), TRACK_POINTS);
        assert!(ry[0].is_nan() && ry[1].is_nan());
        // Block 2 holds samples 8..12: mean of 16, 18, 20, 22.
        assert_eq!(ry[2], 19.0);
        assert_eq!(rt[2], 9.5);
    }

    #[test]
    fn short_numbers() {
        assert_eq!(short(0.0262), "0.0262");
        assert_eq!(short(4746.8), "4747");
        assert_eq!(short(1.5e-6), "1.500e-6");
        assert_eq!(short(f64::NAN), "");
    }

    #[test]
    fn plot_skips_empty_and_draws_finite() {
        let x = [0.0, 1.0, 2.0, 3.0, 4.0];
        let nan = [f64::NAN; 5];
        let empty = Series {
            color: RED,
            width: 1,
            mark: Mark::Line,
            x: &x,
            y: &nan,
            label: "",
        };
        assert!(svg_plot("t", "x", "y", YAxis::Full, &[empty]).is_none());
        let y = [1.0, 2.0, f64::NAN, 3.0, 4.0];
        let line = Series {
            color: RED,
            width: 1,
            mark: Mark::Line,
            x: &x,
            y: &y,
            label: "",
        };
        let svg = svg_plot("t", "x", "y", YAxis::Full, &[line]).unwrap();
        assert!(svg.starts_with("<svg"));
        // A gap splits the line: two polylines, not one through the gap.
        assert!(svg.matches("<polyline").count() >= 2, "{svg}");
    }

    #[test]
    fn html_escapes_run_names() {
        assert_eq!(esc("<a&\"b\">"), "&lt;a&amp;&quot;b&quot;&gt;");
    }
}
