//! The sim-to-real gap between two identifications of one run — the measurement and the
//! model simulated under the measurement's own input — as one dimensionless number with its
//! breakdown into domains and regions (DESIGN.md, "Simulation and the sim-to-real gap").
//!
//! The three domains compare what a model gets right or wrong, never the raw response:
//! after the jump-down of a chirp, which flank of the clearance the link settles on is a
//! coin-flip that moves z's mean, not its envelope, its backbone or its damping.
//! - **time**: the response envelope over time, e = ln(A_sim / A_meas) at every sample
//!   valid in both tracks (a relative error; 0.1 ≈ 10 %);
//! - **backbone**: the natural frequency at each amplitude bin of the measured skeleton,
//!   e = f0_sim(A) / f0_meas(A) − 1, the simulated skeleton interpolated in ln A;
//! - **damping**: the damping force 2h0·Aω at each bin, e = (D_sim(A) − D_meas(A)) / rms D_meas.
//!
//! Each domain's gap is the RMS of its e (bins weighted by their sample counts); the gap is
//! the RMS of the domains present, `sqrt((g_time² + g_backbone² + g_damping²) / 3)`.

use crate::fit::Bin;
use crate::identify::{identify, Identification, IdentifyOptions};
use crate::ingest::Run;
use crate::model::{EffectKind, RigModel};
use crate::simulate::{simulate, Drive, Excitation, SimSettings, MEASURED_INPUT_CUTOFF};
use crate::track::Method;

/// Time windows the time domain is split into for the regions.
const TIME_WINDOWS: usize = 8;
/// Amplitude ranges the skeleton domains are split into for the regions.
const AMPLITUDE_RANGES: usize = 4;

/// Where part of the gap lies (FORMATS.md §5, `regions`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Region {
    /// Start of the time range (s).
    pub t0: f64,
    /// End of the time range (s).
    pub t1: f64,
    /// Lowest response amplitude in the region (signal units).
    pub amp_lo: f64,
    /// Highest response amplitude.
    pub amp_hi: f64,
    /// Lowest response frequency (Hz).
    pub f_lo: f64,
    /// Highest response frequency (Hz).
    pub f_hi: f64,
    /// `time`, `backbone` or `damping`.
    pub domain: &'static str,
    /// Fraction of the total squared gap in this region (all regions sum to 1).
    pub share: f64,
}

/// The gap and its breakdown.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Gap {
    /// The dimensionless gap.
    pub total: f64,
    /// Per domain (`None` where the two identifications share nothing to compare).
    pub time: Option<f64>,
    /// Backbone domain.
    pub backbone: Option<f64>,
    /// Damping domain.
    pub damping: Option<f64>,
    /// Regions, largest share first.
    pub regions: Vec<Region>,
}

/// One domain's squared errors with their weights and where they lie.
struct Errors {
    /// (weight, squared error, region index)
    terms: Vec<(f64, f64, usize)>,
    regions: Vec<Region>,
}

impl Errors {
    /// Weighted mean square.
    fn mean_square(&self) -> Option<f64> {
        let w: f64 = self.terms.iter().map(|t| t.0).sum();
        (w > 0.0).then(|| self.terms.iter().map(|t| t.0 * t.1).sum::<f64>() / w)
    }
}

/// The gap between `measured` and `simulated`, two identifications of the same run.
pub fn gap(measured: &Identification, simulated: &Identification) -> Gap {
    let domains = [
        time_errors(measured, simulated),
        backbone_errors(&measured.bins, &simulated.bins, measured, false),
        backbone_errors(&measured.bins, &simulated.bins, measured, true),
    ];
    let ms: Vec<Option<f64>> = domains.iter().map(Errors::mean_square).collect();
    let total_ms = ms.iter().flatten().sum::<f64>() / 3.0;
    let mut regions = Vec::new();
    for (d, m) in domains.into_iter().zip(&ms) {
        if m.is_none() {
            continue;
        }
        let w: f64 = d.terms.iter().map(|t| t.0).sum();
        let mut per = vec![0.0; d.regions.len()];
        for &(wt, e2, r) in &d.terms {
            per[r] += wt * e2 / w;
        }
        // A region's share of the total: its part of the domain's mean square, over 3.
        for (mut region, part) in d.regions.into_iter().zip(per) {
            region.share = if total_ms > 0.0 {
                part / 3.0 / total_ms
            } else {
                0.0
            };
            regions.push(region);
        }
    }
    regions.retain(|r| r.share > 0.0);
    regions.sort_by(|a, b| b.share.total_cmp(&a.share));
    Gap {
        total: total_ms.sqrt(),
        time: ms[0].map(f64::sqrt),
        backbone: ms[1].map(f64::sqrt),
        damping: ms[2].map(f64::sqrt),
        regions,
    }
}

fn time_errors(m: &Identification, s: &Identification) -> Errors {
    let (a, b) = (&m.response, &s.response);
    let n = a.len().min(b.len());
    let fs = a.sample_rate;
    let window = n.div_ceil(TIME_WINDOWS).max(1);
    let mut terms = Vec::new();
    let mut regions = Vec::new();
    for (w, start) in (0..n).step_by(window).enumerate() {
        let end = (start + window).min(n);
        let (mut alo, mut ahi, mut flo, mut fhi) = (f64::INFINITY, 0f64, f64::INFINITY, 0f64);
        for i in start..end {
            if a.valid[i] && b.valid[i] && a.amplitude[i] > 0.0 && b.amplitude[i] > 0.0 {
                let e = (b.amplitude[i] / a.amplitude[i]).ln();
                terms.push((1.0, e * e, w));
                alo = alo.min(a.amplitude[i]);
                ahi = ahi.max(a.amplitude[i]);
                flo = flo.min(a.frequency[i]);
                fhi = fhi.max(a.frequency[i]);
            }
        }
        regions.push(Region {
            t0: start as f64 / fs,
            t1: end as f64 / fs,
            amp_lo: if alo.is_finite() { alo } else { 0.0 },
            amp_hi: ahi,
            f_lo: if flo.is_finite() { flo } else { 0.0 },
            f_hi: fhi,
            domain: "time",
            share: 0.0,
        });
    }
    Errors { terms, regions }
}

/// Linear interpolation of `value(bin)` over ln A at `amp` (None outside the bins' range).
fn at_amplitude(bins: &[Bin], amp: f64, value: impl Fn(&Bin) -> f64) -> Option<f64> {
    let i = bins.iter().position(|b| b.amplitude >= amp)?;
    if bins[i].amplitude == amp {
        return Some(value(&bins[i]));
    }
    let lo = bins.get(i.checked_sub(1)?)?;
    let hi = &bins[i];
    let u = (amp / lo.amplitude).ln() / (hi.amplitude / lo.amplitude).ln();
    Some(value(lo) + u * (value(hi) - value(lo)))
}

/// The backbone (`damping` false) or damping-force (`damping` true) errors at the measured
/// bins, with regions by amplitude range (their time and frequency spans taken from the
/// measured track).
fn backbone_errors(meas: &[Bin], sim: &[Bin], m: &Identification, damping: bool) -> Errors {
    let domain = if damping { "damping" } else { "backbone" };
    let mut sim: Vec<Bin> = sim
        .iter()
        .filter(|b| b.amplitude > 0.0 && b.stiffness.is_finite() && b.damping.is_finite())
        .copied()
        .collect();
    sim.sort_by(|a, b| a.amplitude.total_cmp(&b.amplitude));
    let meas: Vec<&Bin> = meas
        .iter()
        .filter(|b| b.amplitude > 0.0 && b.stiffness > 0.0 && b.damping.is_finite())
        .collect();
    let scale = if damping {
        let ms =
            meas.iter().map(|b| b.damping_force().powi(2)).sum::<f64>() / meas.len().max(1) as f64;
        ms.sqrt()
    } else {
        1.0
    };
    let (lo, hi) = meas.iter().fold((f64::INFINITY, 0f64), |(l, h), b| {
        (l.min(b.amplitude), h.max(b.amplitude))
    });
    let range_of = |a: f64| -> usize {
        if hi <= lo {
            return 0;
        }
        let u = (a / lo).ln() / (hi / lo).ln();
        ((u * AMPLITUDE_RANGES as f64) as usize).min(AMPLITUDE_RANGES - 1)
    };
    let mut terms = Vec::new();
    for b in &meas {
        let e = if damping {
            at_amplitude(&sim, b.amplitude, Bin::damping_force)
                .filter(|_| scale > 0.0)
                .map(|d| (d - b.damping_force()) / scale)
        } else {
            at_amplitude(&sim, b.amplitude, |x| x.stiffness)
                .map(|k| k.max(0.0).sqrt() / b.stiffness.sqrt() - 1.0)
        };
        if let Some(e) = e {
            terms.push((b.count as f64, e * e, range_of(b.amplitude)));
        }
    }
    // Each amplitude range's time and frequency span, from the measured track.
    let r = &m.response;
    let regions = (0..AMPLITUDE_RANGES)
        .map(|k| {
            let a_lo = lo * (hi / lo).powf(k as f64 / AMPLITUDE_RANGES as f64);
            let a_hi = lo * (hi / lo).powf((k + 1) as f64 / AMPLITUDE_RANGES as f64);
            let (mut t0, mut t1, mut f_lo, mut f_hi) = (f64::INFINITY, 0f64, f64::INFINITY, 0f64);
            for i in 0..r.len() {
                if r.valid[i] && r.amplitude[i] >= a_lo && r.amplitude[i] <= a_hi {
                    let t = i as f64 / r.sample_rate;
                    t0 = t0.min(t);
                    t1 = t1.max(t);
                    f_lo = f_lo.min(r.frequency[i]);
                    f_hi = f_hi.max(r.frequency[i]);
                }
            }
            Region {
                t0: if t0.is_finite() { t0 } else { 0.0 },
                t1,
                amp_lo: a_lo,
                amp_hi: a_hi,
                f_lo: if f_lo.is_finite() { f_lo } else { 0.0 },
                f_hi,
                domain,
                share: 0.0,
            }
        })
        .collect();
    Errors { terms, regions }
}

/// Why a gap could not be computed.
#[derive(Debug, thiserror::Error)]
pub enum GapError {
    /// The run cannot drive a base-motion simulation.
    #[error("{0}")]
    Unusable(String),
    /// The simulated response could not be identified.
    #[error("the model's simulated response could not be identified: {0}")]
    Simulated(String),
}

/// The model simulated under `measured`'s own input, identified like the measurement.
pub fn simulate_like(measured: &Run, model: &RigModel) -> Result<Identification, GapError> {
    let input = measured.input.as_ref().ok_or_else(|| {
        GapError::Unusable("the run has no input channel to drive the model with".into())
    })?;
    let fs = measured.meta.sample_rate;
    let drive = Drive::Base(Excitation::measured(
        input,
        fs,
        MEASURED_INPUT_CUTOFF * fs / 2.0,
    ));
    let settings = SimSettings {
        sample_rate: fs,
        duration: input.len() as f64 / fs,
        ..SimSettings::default()
    };
    let out = simulate(model, &drive, &settings);
    let mut run = measured.clone();
    run.input = Some(out.input);
    run.output = out.output;
    identify(&run, Method::Wavelet, &IdentifyOptions::default())
        .map_err(|e| GapError::Simulated(e.to_string()))
}

/// The gap of `model` against the identified measurement (`f64::INFINITY` when the
/// simulated response cannot be identified: a model that far off is simply bad).
pub fn model_gap(measured: &Run, identified: &Identification, model: &RigModel) -> f64 {
    simulate_like(measured, model).map_or(f64::INFINITY, |s| gap(identified, &s).total)
}

/// The coordinates the simplex moves in: the model's own parameters relative to `base`
/// (stiffness, damping and clearance by their logarithms; the gravity stiffness, of either
/// sign, in units of 1 % of k/J) and, for a candidate, the effect's parameter in units of
/// its starting value (by its logarithm for those that cannot be negative).
struct Coordinates<'a> {
    base: &'a RigModel,
    effect: Option<(EffectKind, f64)>,
}

impl Coordinates<'_> {
    fn model(&self, x: &[f64]) -> RigModel {
        let b = self.base;
        let mut m = b.clone();
        m.stiffness = b.stiffness * x[0].exp();
        m.damping = b.damping.max(1e-9) * x[1].exp();
        m.clearance = b.clearance * x[2].exp();
        m.gravity_stiffness = b.gravity_stiffness + 0.01 * b.stiffness / b.inertia * x[3];
        if let Some((kind, start)) = self.effect {
            let v = if by_log(kind) {
                start * x[4].exp()
            } else {
                start * x[4]
            };
            m.effects.set(kind, Some(v));
        }
        m
    }

    /// The point of `base` itself (with the effect at its starting value).
    fn origin(&self) -> Vec<f64> {
        match self.effect {
            None => vec![0.0; 4],
            Some((kind, _)) => vec![0.0, 0.0, 0.0, 0.0, if by_log(kind) { 0.0 } else { 1.0 }],
        }
    }

    /// A simplex around `x`: a step of 0.1 in each log parameter, 0.5 in the effect's.
    /// Without a clearance its coordinate is left out.
    fn simplex(&self, x: &[f64]) -> Vec<Vec<f64>> {
        let mut simplex = vec![x.to_vec()];
        for d in 0..x.len() {
            if d == 2 && self.base.clearance <= 0.0 {
                continue;
            }
            let mut v = x.to_vec();
            v[d] += if d == 4 { 0.5 } else { 0.1 };
            simplex.push(v);
        }
        simplex
    }

    /// Minimises the gap from `start`; returns the model, its gap and the evaluations.
    fn fit(
        &self,
        measured: &Run,
        identified: &Identification,
        start: Vec<f64>,
        evaluations: usize,
        spent: usize,
    ) -> (RigModel, f64, usize) {
        let mut count = spent;
        let mut cost = |x: &[f64]| {
            count += 1;
            model_gap(measured, identified, &self.model(x))
        };
        let simplex = self.simplex(&start);
        let (best, g) = nelder_mead(&mut cost, simplex, evaluations, 1e-3);
        (self.model(&best), g, count)
    }
}

/// Effect parameters that cannot be negative (a delay, a quantisation step) move by their
/// logarithm.
fn by_log(kind: EffectKind) -> bool {
    matches!(kind, EffectKind::SensorDelay | EffectKind::Quantization)
}

/// `ln(v / nominal)`, or 0 where either is not positive.
fn log_ratio(v: f64, nominal: f64) -> f64 {
    if v > 0.0 && nominal > 0.0 {
        (v / nominal).ln()
    } else {
        0.0
    }
}

/// The baseline: the model's own parameters — stiffness, damping, clearance, gravity
/// stiffness; the inertia stays — refitted to the measured run by minimising the gap, so
/// that a mis-set parameter is never taken for a missing effect. Returns the refitted
/// model, its gap, and the gap evaluations it took.
pub fn refit_baseline(
    measured: &Run,
    identified: &Identification,
    nominal: &RigModel,
    evaluations: usize,
) -> (RigModel, f64, usize) {
    let coords = Coordinates {
        base: nominal,
        effect: None,
    };
    let gap_of = |x: &[f64]| model_gap(measured, identified, &coords.model(x));
    // Start from the nominal model or from what the identification found, whichever is
    // closer: the skeleton fit is near the truth when the nominal values are far off.
    let mut start = coords.origin();
    let mut spent = 1;
    if let Some(dz) = identified.dead_zone {
        let j = nominal.inertia;
        let c = identified
            .damping
            .map_or(nominal.damping, |(c, _)| c.value * j);
        let found = vec![
            log_ratio(dz.stiffness.value * j, nominal.stiffness),
            log_ratio(c, nominal.damping),
            log_ratio(2.0 * dz.half_gap.value, nominal.clearance),
            0.0,
        ];
        spent += 1;
        if gap_of(&found) < gap_of(&start) {
            start = found;
        }
    }
    coords.fit(measured, identified, start, evaluations, spent)
}

/// A starting value for `kind`'s parameter on `model`, from the identification where it
/// says something (the Coulomb level of the damping fit) and otherwise a small fraction of
/// the model's own scales. The fit moves it; only its order of magnitude matters.
pub fn effect_start(kind: EffectKind, model: &RigModel, identified: &Identification) -> f64 {
    let half = (0.5 * model.clearance).max(1e-6);
    match kind {
        EffectKind::CoulombFriction => identified
            .damping
            .map(|(_, f)| f.value * model.inertia)
            .filter(|f| *f > 0.0)
            .unwrap_or(0.01 * model.stiffness * half),
        EffectKind::GravityPreload => 0.1 * model.stiffness * half,
        EffectKind::AsymmetricClearance => 0.1 * half,
        EffectKind::CubicStiffness => 0.1 * model.stiffness / (half * half),
        EffectKind::ContactDamping => model.damping.max(1e-6),
        EffectKind::SensorDelay => 0.002,
        EffectKind::Quantization => 0.02 * half,
    }
}

/// One candidate: `kind` added to `base` (the baseline model) and fitted together with the
/// model's own parameters by the same simplex on the gap. Returns the model with the
/// effect, its gap, and the evaluations taken.
pub fn fit_effect(
    measured: &Run,
    identified: &Identification,
    base: &RigModel,
    kind: EffectKind,
    evaluations: usize,
) -> (RigModel, f64, usize) {
    let coords = Coordinates {
        base,
        effect: Some((kind, effect_start(kind, base, identified))),
    };
    let mut start = coords.origin();
    // Dry friction trades off against viscous damping: the baseline, without friction, has
    // put all of it into c. Start c where the skeleton's damping fit separated the two.
    if let (EffectKind::CoulombFriction, Some((c, _))) = (kind, identified.damping) {
        start[1] = log_ratio(c.value * base.inertia, base.damping);
    }
    coords.fit(measured, identified, start, evaluations, 0)
}

/// Minimises `f` from the initial `simplex` (n + 1 points of any dimension ≥ n) by Nelder
/// and Mead's method (standard coefficients), for at most `budget` evaluations or until the
/// simplex's values agree within `tol`. Returns the best point and its value.
pub fn nelder_mead(
    f: &mut impl FnMut(&[f64]) -> f64,
    simplex: Vec<Vec<f64>>,
    budget: usize,
    tol: f64,
) -> (Vec<f64>, f64) {
    let mut pts: Vec<(Vec<f64>, f64)> = simplex
        .into_iter()
        .map(|x| {
            let v = f(&x);
            (x, v)
        })
        .collect();
    let mut used = pts.len();
    let dim = pts[0].0.len();
    let combine = |a: &[f64], b: &[f64], t: f64| -> Vec<f64> {
        a.iter().zip(b).map(|(a, b)| a + t * (b - a)).collect()
    };
    while used < budget {
        pts.sort_by(|a, b| a.1.total_cmp(&b.1));
        let (lo, hi) = (pts[0].1, pts[pts.len() - 1].1);
        if (hi - lo).abs() <= tol * lo.abs().max(1e-12) {
            break;
        }
        let n = pts.len() - 1;
        let centroid: Vec<f64> = (0..dim)
            .map(|d| pts[..n].iter().map(|p| p.0[d]).sum::<f64>() / n as f64)
            .collect();
        let worst = pts[n].clone();
        let reflected = combine(&centroid, &worst.0, -1.0);
        let fr = f(&reflected);
        used += 1;
        if fr < pts[0].1 {
            let expanded = combine(&centroid, &worst.0, -2.0);
            let fe = f(&expanded);
            used += 1;
            pts[n] = if fe < fr {
                (expanded, fe)
            } else {
                (reflected, fr)
            };
        } else if fr < pts[n - 1].1 {
            pts[n] = (reflected, fr);
        } else {
            let contracted = combine(&centroid, &worst.0, 0.5);
            let fc = f(&contracted);
            used += 1;
            if fc < worst.1 {
                pts[n] = (contracted, fc);
            } else {
                // Shrink towards the best point.
                let best = pts[0].0.clone();
                for p in pts.iter_mut().skip(1) {
                    p.0 = combine(&best, &p.0, 0.5);
                    p.1 = f(&p.0);
                    used += 1;
                }
            }
        }
    }
    pts.sort_by(|a, b| a.1.total_cmp(&b.1));
    pts.swap_remove(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::Bin;

    fn bin(a: f64, k: f64, d: f64) -> Bin {
        Bin {
            amplitude: a,
            stiffness: k,
            stiffness_spread: 0.0,
            damping: d,
            damping_spread: 0.0,
            velocity: a * k.sqrt(),
            count: 10,
        }
    }

    #[test]
    fn nelder_mead_finds_the_minimum_of_a_rosenbrock_valley() {
        let mut f = |x: &[f64]| (1.0 - x[0]).powi(2) + 100.0 * (x[1] - x[0] * x[0]).powi(2);
        let simplex = vec![vec![-1.2, 1.0], vec![-1.0, 1.0], vec![-1.2, 1.2]];
        let (x, v) = nelder_mead(&mut f, simplex, 2000, 1e-14);
        assert!(
            (x[0] - 1.0).abs() < 1e-3 && (x[1] - 1.0).abs() < 2e-3,
            "{x:?} {v}"
        );
    }

    #[test]
    fn interpolation_in_log_amplitude_is_exact_for_a_log_linear_curve() {
        let bins: Vec<Bin> = (0..10)
            .map(|i| {
                let a = 0.001 * 1.5f64.powi(i);
                bin(a, 100.0 + 7.0 * a.ln(), 1.0)
            })
            .collect();
        let a = 0.0042;
        let v = at_amplitude(&bins, a, |b| b.stiffness).unwrap();
        assert!((v - (100.0 + 7.0 * a.ln())).abs() < 1e-9, "{v}");
        assert!(at_amplitude(&bins, 1e-6, |b| b.stiffness).is_none());
        assert!(at_amplitude(&bins, 1.0, |b| b.stiffness).is_none());
    }
}
