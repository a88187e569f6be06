//! The figures of one run (the paper's Figs. 10–13) as inline SVG: envelope and frequency
//! tracks of both methods, the backbone with the fitted dead-zone curve, restoring and
//! damping forces against amplitude; axis ranges fenced against outliers. In: a run's
//! [`RunPlots`]; out: SVG strings.

use plotters::prelude::*;

use super::*;

/// Colour of each method, the same in every plot and in the legend.
pub(super) fn method_color(method: &str) -> RGBColor {
    match method {
        "wavelet" => RGBColor(31, 119, 180),
        "hilbert" => RGBColor(230, 110, 10),
        _ => RGBColor(90, 90, 90),
    }
}

/// Colour of a method's fitted model curve: darker than its points.
pub(super) fn fit_color(method: &str) -> RGBColor {
    let RGBColor(r, g, b) = method_color(method);
    RGBColor(r / 2, g / 2, b / 2)
}

/// A number in at most about four significant digits, for axis labels and table cells.
pub(super) fn short(v: f64) -> String {
    if !v.is_finite() {
        return String::new();
    }
    if v == 0.0 {
        return "0".into();
    }
    let mag = v.abs().log10().floor();
    if (-3.0..5.0).contains(&mag) {
        let decimals = (3.0 - mag).max(0.0) as usize;
        let s = format!("{v:.decimals$}");
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        }
    } else {
        format!("{v:.3e}")
    }
}

/// The finite range of some values, padded by 5 % (or ±1 around a single value).
pub(super) fn range<'a>(values: impl Iterator<Item = &'a f64>) -> Option<(f64, f64)> {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    if lo > hi {
        return None;
    }
    let pad = if hi > lo {
        0.05 * (hi - lo)
    } else {
        (0.1 * lo.abs()).max(1e-12)
    };
    Some((lo - pad, hi + pad))
}

/// The y range of a plot whose outliers would flatten what matters (the Hilbert method's
/// frequency at its edges, skeleton bins of a few samples): the values within three
/// interquartile ranges of the quartiles, then padded like [`range`].
pub(super) fn fenced_range<'a>(values: impl Iterator<Item = &'a f64>) -> Option<(f64, f64)> {
    let mut v: Vec<f64> = values.copied().filter(|v| v.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
    let (q1, q3) = (q(0.25), q(0.75));
    let (lo, hi) = (q1 - 3.0 * (q3 - q1), q3 + 3.0 * (q3 - q1));
    range(v.iter().filter(|&&x| x >= lo && x <= hi))
}

/// How a plot's y axis is scaled.
#[derive(Clone, Copy, PartialEq)]
pub(crate) enum YAxis {
    /// Every value shown.
    Full,
    /// Outliers left outside the axes ([`fenced_range`]) and not drawn.
    Fenced,
}

/// One plot as an SVG string; `None` when no series has a finite point.
pub(crate) fn svg_plot(
    title: &str,
    x_label: &str,
    y_label: &str,
    y_axis: YAxis,
    series: &[Series],
) -> Option<String> {
    plot(title, x_label, y_label, y_axis, series, false)
}

/// [`svg_plot`], with a legend of the series' labels when `legend` (a figure file stands
/// alone; a page's plots share the page's legend).
pub(crate) fn plot(
    title: &str,
    x_label: &str,
    y_label: &str,
    y_axis: YAxis,
    series: &[Series],
    legend: bool,
) -> Option<String> {
    let finite = |s: &&Series| {
        s.x.iter()
            .zip(s.y)
            .any(|(x, y)| x.is_finite() && y.is_finite())
    };
    let drawn: Vec<&Series> = series.iter().filter(finite).collect();
    if drawn.is_empty() {
        return None;
    }
    let xr = range(drawn.iter().flat_map(|s| s.x.iter()))?;
    let ys = drawn.iter().flat_map(|s| s.y.iter());
    let yr = match y_axis {
        YAxis::Full => range(ys)?,
        YAxis::Fenced => fenced_range(ys)?,
    };
    let inside = |p: &(f64, f64)| p.0.is_finite() && p.1 >= yr.0 && p.1 <= yr.1;
    let mut svg = String::new();
    let result = (|| -> Result<(), Box<dyn std::error::Error>> {
        let root = SVGBackend::with_string(&mut svg, PLOT_SIZE).into_drawing_area();
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(64)
            .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(y_label)
            .x_labels(6)
            .y_labels(6)
            .x_label_formatter(&|v| short(*v))
            .y_label_formatter(&|v| short(*v))
            .light_line_style(RGBColor(240, 240, 240))
            .draw()?;
        for s in &drawn {
            let mut labelled = false;
            let pts = s.x.iter().zip(s.y).map(|(&x, &y)| (x, y));
            match s.mark {
                Mark::Line => {
                    // One polyline per run of finite points: a gap breaks the line.
                    let mut segment: Vec<(f64, f64)> = Vec::new();
                    for p in pts.chain(std::iter::once((f64::NAN, f64::NAN))) {
                        if inside(&p) {
                            segment.push(p);
                        } else if !segment.is_empty() {
                            let drawn = chart.draw_series(LineSeries::new(
                                std::mem::take(&mut segment),
                                s.color.stroke_width(s.width),
                            ))?;
                            if legend && !labelled && !s.label.is_empty() {
                                labelled = true;
                                let style = s.color.stroke_width(s.width.max(2));
                                drawn.label(s.label).legend(move |(x, y)| {
                                    PathElement::new(vec![(x, y), (x + 16, y)], style)
                                });
                            }
                        }
                    }
                }
                Mark::Points => {
                    let drawn = chart.draw_series(
                        pts.filter(inside)
                            .map(|p| Circle::new(p, 3, s.color.stroke_width(1))),
                    )?;
                    if legend && !s.label.is_empty() {
                        let style = s.color.stroke_width(1);
                        drawn
                            .label(s.label)
                            .legend(move |(x, y)| Circle::new((x + 8, y), 3, style));
                    }
                }
            }
        }
        if legend && drawn.iter().any(|s| !s.label.is_empty()) {
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.85))
                .border_style(RGBColor(200, 200, 200))
                .label_font(("sans-serif", 11))
                .draw()?;
        }
        root.present()?;
        Ok(())
    })();
    result.ok().map(|_| svg)
}

/// A fitted model's curves, drawn over a method's skeleton.
pub(super) struct Curves {
    pub(super) amplitude: Vec<f64>,
    /// Natural frequency (Hz) along `amplitude`.
    pub(super) frequency: Vec<f64>,
    /// Restoring force A·ω0² along `amplitude`.
    pub(super) restoring: Vec<f64>,
    /// Velocity amplitudes (empty when the damping was not fitted).
    pub(super) velocity: Vec<f64>,
    /// Damping force along `velocity`.
    pub(super) damping: Vec<f64>,
}

/// `n` points from `lo` to `hi`.
pub(super) fn grid(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| lo + (hi - lo) * i as f64 / (n - 1) as f64)
        .collect()
}

/// The curves of a method's fit over the range of its skeleton; `None` without a fit.
pub(super) fn model_curves(m: &MethodPlots) -> Option<Curves> {
    let fit = m.fitted?;
    let (lo, hi) = range(m.skeleton.amplitude.iter())?;
    let amplitude = grid(lo.max(0.0), hi, CURVE_POINTS);
    let w2: Vec<f64> = amplitude
        .iter()
        .map(|&a| fit.stiffness * fit.model.ratio(fit.half_gap, a))
        .collect();
    let frequency = w2
        .iter()
        .map(|w| w.max(0.0).sqrt() / (2.0 * std::f64::consts::PI))
        .collect();
    let restoring = amplitude.iter().zip(&w2).map(|(a, w)| a * w).collect();
    let (velocity, damping) = match range(m.skeleton.velocity_amplitude.iter()) {
        Some((lo, hi)) if fit.viscous.is_finite() && fit.coulomb.is_finite() => {
            let v = grid(lo.max(0.0), hi, CURVE_POINTS);
            let d = v
                .iter()
                .map(|v| fit.viscous * v + 4.0 / std::f64::consts::PI * fit.coulomb)
                .collect();
            (v, d)
        }
        _ => (Vec::new(), Vec::new()),
    };
    Some(Curves {
        amplitude,
        frequency,
        restoring,
        velocity,
        damping,
    })
}

/// The figures of one run on its page: response envelope and frequency, backbone,
/// restoring and damping forces.
pub(super) fn run_figures(run: &RunPlots) -> Vec<String> {
    run_figure_set(run, false)
        .into_iter()
        .map(|(_, svg)| svg)
        .collect()
}

/// The figures of one run, each with its title. As files (`files`): each with its legend,
/// and the input's envelope and frequency first (the paper's Figs. 10–13); on the page,
/// the response's plots only.
pub fn run_figure_set(run: &RunPlots, files: bool) -> Vec<(String, String)> {
    // Hilbert first, so that the wavelet (the more accurate method) is drawn on top.
    let mut ms: Vec<&MethodPlots> = run.methods.iter().collect();
    ms.sort_by_key(|m| m.method == "wavelet");
    let mut figs = Vec::new();
    let mut add = |title: &str, x: &str, y: &str, axis: YAxis, series: &[Series]| {
        if let Some(svg) = plot(title, x, y, axis, series, files) {
            figs.push((title.to_string(), svg));
        }
    };
    let ok = ms.iter().find(|m| m.error.is_none());
    let unit = ok.map_or(crate::units::UNKNOWN, |m| m.unit.as_str());
    let input_unit = ok.map_or(crate::units::UNKNOWN, |m| m.input_unit.as_str());
    let tracks = |y: fn(&MethodPlots) -> &Vec<f64>| -> Vec<Series> {
        ms.iter()
            .map(|m| Series {
                color: method_color(&m.method),
                width: if m.method == "wavelet" { 2 } else { 1 },
                mark: Mark::Line,
                x: &m.time,
                y: y(m),
                label: &m.method,
            })
            .collect()
    };
    if files {
        add(
            "Input envelope",
            "time (s)",
            &format!("input amplitude ({input_unit})"),
            YAxis::Full,
            &tracks(|m| &m.input_amplitude),
        );
        add(
            "Input frequency",
            "time (s)",
            "frequency (Hz)",
            YAxis::Fenced,
            &tracks(|m| &m.input_frequency),
        );
    }
    add(
        "Response envelope",
        "time (s)",
        &format!("amplitude ({unit})"),
        YAxis::Full,
        &tracks(|m| &m.amplitude),
    );
    add(
        "Response frequency",
        "time (s)",
        "frequency (Hz)",
        YAxis::Fenced,
        &tracks(|m| &m.frequency),
    );
    // The fitted model over each method's skeleton amplitudes, and its damping line
    // 2h0·Aω = (c/J)·V + (4/π)·F/J over the velocity amplitudes V.
    let curves: Vec<Option<Curves>> = ms.iter().map(|m| model_curves(m)).collect();
    let fit_labels: Vec<String> = ms.iter().map(|m| format!("{} fit", m.method)).collect();
    let with_fit = |pick: fn(&Skeleton) -> (&Vec<f64>, &Vec<f64>),
                    curve: fn(&Curves) -> (&Vec<f64>, &Vec<f64>)| {
        let mut s = Vec::new();
        for ((m, c), fit_label) in ms.iter().zip(&curves).zip(&fit_labels) {
            let (x, y) = pick(&m.skeleton);
            s.push(Series {
                color: method_color(&m.method),
                width: 1,
                mark: Mark::Points,
                x,
                y,
                label: &m.method,
            });
            if let Some((x, y)) = c.as_ref().map(curve).filter(|(x, _)| !x.is_empty()) {
                s.push(Series {
                    color: fit_color(&m.method),
                    width: 2,
                    mark: Mark::Line,
                    x,
                    y,
                    label: fit_label,
                });
            }
        }
        s
    };
    add(
        "Backbone: skeleton (circles) and fitted dead zone (line)",
        &format!("response amplitude ({unit})"),
        "natural frequency (Hz)",
        YAxis::Fenced,
        &with_fit(
            |s| (&s.amplitude, &s.natural_frequency),
            |c| (&c.amplitude, &c.frequency),
        ),
    );
    add(
        "Restoring force per unit inertia",
        &format!("response amplitude ({unit})"),
        &format!("A·ω0² ({unit}/s²)"),
        YAxis::Fenced,
        &with_fit(
            |s| (&s.amplitude, &s.restoring_force),
            |c| (&c.amplitude, &c.restoring),
        ),
    );
    add(
        "Damping force per unit inertia: viscous + Coulomb fit",
        &format!("velocity amplitude A·ω ({unit}/s)"),
        &format!("2h0·A·ω ({unit}/s²)"),
        YAxis::Fenced,
        &with_fit(
            |s| (&s.velocity_amplitude, &s.damping_force),
            |c| (&c.velocity, &c.damping),
        ),
    );
    figs
}

/// Escapes text for HTML.
pub(crate) fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// Reduces a track to at most [`TRACK_POINTS`] points: the mean over each block of the
/// valid samples, NaN for a block with none (so the plotted line breaks there).
pub(crate) fn reduce(time: &[f64], y: &[f64], valid: &[u8]) -> (Vec<f64>, Vec<f64>) {
    let n = time.len().min(y.len());
    if n == 0 {
        return (Vec::new(), Vec::new());
    }
    let block = n.div_ceil(TRACK_POINTS);
    let ok = |i: usize| valid.get(i).is_none_or(|&v| v != 0) && y[i].is_finite();
    (0..n)
        .step_by(block)
        .map(|start| {
            let end = (start + block).min(n);
            let t = 0.5 * (time[start] + time[end - 1]);
            let (sum, count) = (start..end)
                .filter(|&i| ok(i))
                .fold((0.0, 0usize), |(s, c), i| (s + y[i], c + 1));
            (
                t,
                if count > 0 {
                    sum / count as f64
                } else {
                    f64::NAN
                },
            )
        })
        .unzip()
}

/// How a series is drawn.
#[derive(Clone, Copy)]
pub(crate) enum Mark {
    Line,
    Points,
}

/// One series of a plot.
pub(crate) struct Series<'a> {
    pub(crate) color: RGBColor,
    /// Line width (pixels).
    pub(crate) width: u32,
    pub(crate) mark: Mark,
    pub(crate) x: &'a [f64],
    pub(crate) y: &'a [f64],
    /// Its legend entry (figure files only; the pages have their own legend).
    pub(crate) label: &'a str,
}
