//! Skeleton curves and their fits: the backbone ω0(A), the restoring force A·ω0²(A) and the
//! damping force 2h0·Aω binned over amplitude, then the dead-zone describing function
//! (clearance, contact stiffness), the paper's linear extrapolation, and viscous + Coulomb
//! damping (DESIGN.md, "Fitting the skeleton").

use std::f64::consts::PI;

/// One amplitude bin of the skeleton (medians over the samples that fell in it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bin {
    /// Response amplitude A (signal units).
    pub amplitude: f64,
    /// ω0² (1/s²).
    pub stiffness: f64,
    /// Interquartile half-range of ω0² in the bin (1/s²).
    pub stiffness_spread: f64,
    /// 2 h0 (1/s).
    pub damping: f64,
    /// Interquartile half-range of 2 h0 (1/s).
    pub damping_spread: f64,
    /// Velocity amplitude A ω (units/s).
    pub velocity: f64,
    /// Samples in the bin.
    pub count: usize,
}

impl Bin {
    /// Natural frequency ω0/2π (Hz), 0 where ω0² ≤ 0.
    pub fn natural_frequency(&self) -> f64 {
        self.stiffness.max(0.0).sqrt() / (2.0 * PI)
    }
    /// Restoring force per unit inertia, A ω0².
    pub fn restoring_force(&self) -> f64 {
        self.amplitude * self.stiffness
    }
    /// Damping force per unit inertia, 2 h0 A ω.
    pub fn damping_force(&self) -> f64 {
        self.damping * self.velocity
    }
}

/// Samples of the instantaneous characteristics that a skeleton is built from.
#[derive(Debug, Clone, Copy)]
pub struct Sample {
    /// Response amplitude.
    pub amplitude: f64,
    /// Response angular frequency ω (rad/s).
    pub omega: f64,
    /// ω0² (1/s²).
    pub stiffness: f64,
    /// h0 (1/s).
    pub damping: f64,
}

/// The rank of quantile `p` among `n` sorted values (the nearest, as the skeleton has
/// always taken it).
fn rank(n: usize, p: f64) -> usize {
    ((n - 1) as f64 * p).round() as usize
}

/// The value sorting `v` by `total_cmp` puts at `rank`, found by selection (linear time;
/// sorting every bin's four series was 6 % of a batch's CPU). `v` is left reordered.
fn nth(v: &mut [f64], rank: usize) -> f64 {
    *v.select_nth_unstable_by(rank, f64::total_cmp).1
}

/// The lower quartile, median and upper quartile of `v` (non-empty), the values sorting
/// by `total_cmp` puts at those ranks; `v` is left reordered.
fn quartiles(v: &mut [f64]) -> (f64, f64, f64) {
    let n = v.len();
    let (r1, r2, r3) = (rank(n, 0.25), rank(n, 0.5), rank(n, 0.75));
    let (below, &mut median, above) = v.select_nth_unstable_by(r2, f64::total_cmp);
    // The median's selection leaves every value ranked below it before it, every one
    // above after it: each quartile is selected within its side alone.
    let q1 = if r1 < r2 { nth(below, r1) } else { median };
    let q3 = if r3 > r2 {
        nth(above, r3 - r2 - 1)
    } else {
        median
    };
    (q1, median, q3)
}

/// The values of `v` (non-empty) at quantiles `p_lo` ≤ `p_hi`, as [`quartiles`] takes
/// them; `v` is left reordered.
fn quantiles(v: &mut [f64], p_lo: f64, p_hi: f64) -> (f64, f64) {
    let n = v.len();
    let (r_lo, r_hi) = (rank(n, p_lo), rank(n, p_hi));
    let hi = nth(v, r_hi);
    // The selection left every value ranked below `r_hi` before it.
    let lo = if r_lo < r_hi {
        nth(&mut v[..r_hi], r_lo)
    } else {
        hi
    };
    (lo, hi)
}

/// The median of `v` (non-empty), as [`quartiles`] takes it.
fn median(v: &mut [f64]) -> f64 {
    let n = v.len();
    nth(v, rank(n, 0.5))
}

/// Bins the samples over log-amplitude: `bins` equal steps between the 0.5 % and 99.5 %
/// amplitude quantiles; bins with fewer than `min_count` samples are dropped.
pub fn skeleton(samples: &[Sample], bins: usize, min_count: usize) -> Vec<Bin> {
    if samples.len() < min_count.max(2) || bins == 0 {
        return Vec::new();
    }
    let mut amps: Vec<f64> = samples.iter().map(|s| s.amplitude).collect();
    let (lo, hi) = quantiles(&mut amps, 0.005, 0.995);
    let lo = lo.max(f64::MIN_POSITIVE);
    if hi <= lo {
        return Vec::new();
    }
    let step = (hi / lo).ln() / bins as f64;
    let mut members: Vec<Vec<Sample>> = vec![Vec::new(); bins];
    for s in samples {
        if s.amplitude < lo || s.amplitude > hi {
            continue;
        }
        let b = (((s.amplitude / lo).ln() / step) as usize).min(bins - 1);
        members[b].push(*s);
    }
    members
        .into_iter()
        .filter(|m| m.len() >= min_count)
        .map(|m| {
            let mut a: Vec<f64> = m.iter().map(|s| s.amplitude).collect();
            let mut k: Vec<f64> = m.iter().map(|s| s.stiffness).collect();
            let mut d: Vec<f64> = m.iter().map(|s| 2.0 * s.damping).collect();
            let mut v: Vec<f64> = m.iter().map(|s| s.amplitude * s.omega).collect();
            let am = median(&mut a);
            let (k1, km, k3) = quartiles(&mut k);
            let (d1, dm, d3) = quartiles(&mut d);
            let vm = median(&mut v);
            Bin {
                amplitude: am,
                stiffness: km,
                stiffness_spread: 0.5 * (k3 - k1),
                damping: dm,
                damping_spread: 0.5 * (d3 - d1),
                velocity: vm,
                count: m.len(),
            }
        })
        .collect()
}

/// First-harmonic stiffness ratio of a dead zone of half-width δ at amplitude A:
/// k_eq/k = 1 − (2/π)(asin r + r√(1 − r²)), r = δ/A (0 below the gap).
pub fn dead_zone_ratio(delta: f64, amplitude: f64) -> f64 {
    if amplitude <= delta {
        return 0.0;
    }
    let r = delta / amplitude;
    1.0 - (2.0 / PI) * (r.asin() + r * (1.0 - r * r).sqrt())
}

/// ω0²/K along the exact free periodic orbit of a dead-zone oscillator (half-gap δ), as a
/// function of the orbit's *first-harmonic* amplitude A1 — what the wavelet and Hilbert
/// envelopes measure. Near the gap the orbit is far from a sinusoid (a triangle wave at
/// the limit), so the describing function, which assumes x = A sin ωt, overstates the
/// softening there: +4 % in ω0 at A1 = 1.5δ, +37 % at 1.13δ. Closed form (README,
/// "Identification"): with u = 1 − ω/ωn, A1/δ = 8 sin(πu/2) / (π² u² (2 − u)), and
/// ω0²/K = (1 − u)². Below A1 = 8δ/π² the link never touches: 0.
pub fn dead_zone_orbit_ratio(delta: f64, amplitude: f64) -> f64 {
    if delta <= 0.0 {
        return 1.0;
    }
    let s = delta / amplitude;
    // NaN (an amplitude of 0 over a gap of 0 is excluded above) counts as no contact too.
    if s.is_nan() || s >= ORBIT_S_MAX {
        return 0.0;
    }
    // The fit evaluates this for every bin at hundreds of trial gaps (a fifth of a batch's
    // time when solved by Newton each time), so u(δ/A) is interpolated from a table of
    // exact solutions: a cubic Hermite with exact slopes, within 1e-13 of the solve (test
    // `the_orbit_table_matches_the_exact_solve`).
    let t = orbit_table();
    let x = s / ORBIT_STEP;
    let i = (x as usize).min(ORBIT_NODES - 2);
    let f = x - i as f64;
    let (u0, d0) = t[i];
    let (u1, d1) = t[i + 1];
    let (f2, f3) = (f * f, f * f * f);
    let u = (2.0 * f3 - 3.0 * f2 + 1.0) * u0
        + (f3 - 2.0 * f2 + f) * ORBIT_STEP * d0
        + (-2.0 * f3 + 3.0 * f2) * u1
        + (f3 - f2) * ORBIT_STEP * d1;
    (1.0 - u) * (1.0 - u)
}

/// δ/A1 at which the orbit stops touching (A1 = 8δ/π²).
const ORBIT_S_MAX: f64 = PI * PI / 8.0;
/// Nodes of the orbit table over δ/A1 ∈ [0, π²/8].
const ORBIT_NODES: usize = 4097;
/// Spacing of the orbit table.
const ORBIT_STEP: f64 = ORBIT_S_MAX / (ORBIT_NODES - 1) as f64;

/// (u, du/ds) at the nodes s = δ/A1 = i·step.
fn orbit_table() -> &'static [(f64, f64)] {
    static TABLE: std::sync::OnceLock<Vec<(f64, f64)>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        (0..ORBIT_NODES)
            .map(|i| {
                let s = i as f64 * ORBIT_STEP;
                if i == 0 {
                    // Large amplitudes: u ≈ 2δ/(π A1).
                    (0.0, 2.0 / PI)
                } else if i == ORBIT_NODES - 1 {
                    // ln(A1/δ) falls with slope −1 in u at u = 1.
                    (1.0, 1.0 / s)
                } else {
                    let u = orbit_u_exact(1.0 / s);
                    // ln(1/s) = ln h(u), so du/ds = −1/(s · d ln h/du).
                    (u, -1.0 / (s * orbit_d_ln_h(u)))
                }
            })
            .collect()
    })
}

/// ln(A1/δ) of the orbit with u = 1 − ω/ωn.
fn orbit_ln_h(u: f64) -> f64 {
    (8.0 / (PI * PI)).ln() + (0.5 * PI * u).sin().ln() - 2.0 * u.ln() - (2.0 - u).ln()
}

/// d ln(A1/δ)/du.
fn orbit_d_ln_h(u: f64) -> f64 {
    0.5 * PI / (0.5 * PI * u).tan() - 2.0 / u + 1.0 / (2.0 - u)
}

/// u solving A1/δ = `target` (> 8/π²) to machine precision: Newton on ln(A1/δ), which is
/// smooth and convex enough to converge in a few steps, kept inside a shrinking bisection
/// bracket.
fn orbit_u_exact(target: f64) -> f64 {
    let ln_target = target.ln();
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    // Large amplitudes: u ≈ 2/(π A1/δ), which is also the starting point.
    let mut u = (2.0 / (PI * target)).min(0.5);
    for _ in 0..100 {
        let f = orbit_ln_h(u) - ln_target;
        if f > 0.0 {
            lo = u;
        } else {
            hi = u;
        }
        let mut next = u - f / orbit_d_ln_h(u);
        if !(next > lo && next < hi) {
            next = 0.5 * (lo + hi);
        }
        if (next - u).abs() <= 1e-15 * u || hi - lo <= 1e-15 {
            u = next;
            break;
        }
        u = next;
    }
    u
}

/// Weights of binned medians (value, interquartile spread, count): inverse variance, as the
/// median's variance goes as spread²/count, so bins where the estimate scatters (noise at
/// low amplitude, a transient) count for little. The spread is floored at 1 % of the
/// largest |value|, so that bins of near-identical samples (the near-zero free play of a
/// clearance in a noise-free record) cannot outweigh the rest.
fn inverse_variance_weights(bins: impl Iterator<Item = (f64, f64, usize)> + Clone) -> Vec<f64> {
    let floor = 1e-2
        * bins
            .clone()
            .map(|b| b.0.abs())
            .fold(f64::MIN_POSITIVE, f64::max);
    bins.map(|(_, spread, n)| n as f64 / (spread * spread + floor * floor))
        .collect()
}

/// A fitted value with its standard error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    /// Value.
    pub value: f64,
    /// Standard error (NaN when it cannot be estimated).
    pub stderr: f64,
}

/// Which curve ω0²(A)/K a dead zone is fitted with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum BackboneModel {
    /// The describing function (first harmonic of a sinusoidal motion).
    DescribingFunction,
    /// The exact free periodic orbit, in its first-harmonic amplitude.
    PeriodicOrbit,
}

impl BackboneModel {
    /// ω0²/K at amplitude A for half-gap δ.
    pub fn ratio(self, delta: f64, amplitude: f64) -> f64 {
        match self {
            BackboneModel::DescribingFunction => dead_zone_ratio(delta, amplitude),
            BackboneModel::PeriodicOrbit => dead_zone_orbit_ratio(delta, amplitude),
        }
    }
    /// The largest half-gap that still gives contact at amplitude A.
    pub fn max_half_gap(self, amplitude: f64) -> f64 {
        match self {
            BackboneModel::DescribingFunction => amplitude,
            BackboneModel::PeriodicOrbit => amplitude * PI * PI / 8.0,
        }
    }
    /// The model a `backbone_model` name stands for.
    pub fn from_name(name: &str) -> Option<BackboneModel> {
        [
            BackboneModel::DescribingFunction,
            BackboneModel::PeriodicOrbit,
        ]
        .into_iter()
        .find(|m| m.name() == name)
    }
    /// Name written to the results (`backbone_model`).
    pub fn name(self) -> &'static str {
        match self {
            BackboneModel::DescribingFunction => "describing_function",
            BackboneModel::PeriodicOrbit => "periodic_orbit",
        }
    }
}

/// The dead-zone fit: ω0²(A) = K·k_eq/k(δ, A).
#[derive(Debug, Clone, Copy)]
pub struct DeadZoneFit {
    /// Curve fitted.
    pub model: BackboneModel,
    /// Half-gap δ (signal units).
    pub half_gap: Estimate,
    /// K = k/J (1/s²).
    pub stiffness: Estimate,
    /// RMS residual relative to the mean ω0².
    pub residual: f64,
}

/// Weighted least squares of the dead-zone describing function to the backbone bins: δ by
/// a bracketing search (K is linear once δ is fixed), errors from the Jacobian.
pub fn fit_dead_zone(bins: &[Bin], model: BackboneModel) -> Option<DeadZoneFit> {
    let pts: Vec<&Bin> = bins.iter().filter(|b| b.stiffness.is_finite()).collect();
    if pts.len() < 3 {
        return None;
    }
    let w = inverse_variance_weights(
        pts.iter()
            .map(|b| (b.stiffness, b.stiffness_spread, b.count)),
    );
    // Cost and the optimal K for a given δ, with one model evaluation per bin.
    let solve = |delta: f64| -> (f64, f64) {
        let g: Vec<f64> = pts
            .iter()
            .map(|b| model.ratio(delta, b.amplitude))
            .collect();
        let (mut sgy, mut sgg) = (0.0, 0.0);
        for ((b, wi), gi) in pts.iter().zip(&w).zip(&g) {
            sgy += wi * gi * b.stiffness;
            sgg += wi * gi * gi;
        }
        // A contact stiffness is positive.
        let k = if sgg > 0.0 { (sgy / sgg).max(0.0) } else { 0.0 };
        let cost: f64 = pts
            .iter()
            .zip(&w)
            .zip(&g)
            .map(|((b, wi), gi)| wi * (b.stiffness - k * gi).powi(2))
            .sum();
        (cost, k)
    };
    // Below the contact threshold the model is 0: δ may lie anywhere up to the one of the
    // largest amplitude.
    let a_min = model.max_half_gap(pts.iter().map(|b| b.amplitude).fold(0.0, f64::max));
    // Coarse scan over δ ∈ [0, A_max), then golden-section refinement around the best.
    let grid = 400;
    let (mut best, mut best_cost) = (0.0, solve(0.0).0);
    for i in 1..grid {
        let d = a_min * i as f64 / grid as f64;
        let c = solve(d).0;
        if c < best_cost {
            best = d;
            best_cost = c;
        }
    }
    let h = a_min / grid as f64;
    let (mut lo, mut hi) = ((best - h).max(0.0), (best + h).min(a_min * (1.0 - 1e-9)));
    let g = 0.5 * (5f64.sqrt() - 1.0);
    for _ in 0..60 {
        let x1 = hi - g * (hi - lo);
        let x2 = lo + g * (hi - lo);
        if solve(x1).0 < solve(x2).0 {
            hi = x2;
        } else {
            lo = x1;
        }
    }
    let delta = 0.5 * (lo + hi);
    let (cost, k) = solve(delta);
    // Gauss–Newton covariance: J = [∂f/∂K, ∂f/∂δ], σ² = cost/(n − 2) per unit weight.
    let eps = 1e-6 * a_min.max(1e-12);
    let mut jtj = [[0.0; 2]; 2];
    for (b, wi) in pts.iter().zip(&w) {
        let g = model.ratio(delta, b.amplitude);
        let dg = (model.ratio(delta + eps, b.amplitude)
            - model.ratio((delta - eps).max(0.0), b.amplitude))
            / (delta + eps - (delta - eps).max(0.0));
        let j = [g, k * dg];
        for r in 0..2 {
            for c in 0..2 {
                jtj[r][c] += wi * j[r] * j[c];
            }
        }
    }
    let dof = (pts.len() as f64 - 2.0).max(1.0);
    let s2 = cost / dof;
    let det = jtj[0][0] * jtj[1][1] - jtj[0][1] * jtj[1][0];
    let (se_k, se_d) = if det > 0.0 {
        ((s2 * jtj[1][1] / det).sqrt(), (s2 * jtj[0][0] / det).sqrt())
    } else {
        (f64::NAN, f64::NAN)
    };
    let wsum: f64 = w.iter().sum();
    let mean = pts
        .iter()
        .zip(&w)
        .map(|(b, wi)| wi * b.stiffness)
        .sum::<f64>()
        / wsum;
    Some(DeadZoneFit {
        model,
        half_gap: Estimate {
            value: delta,
            stderr: se_d,
        },
        stiffness: Estimate {
            value: k,
            stderr: se_k,
        },
        residual: (cost / wsum).sqrt() / mean.abs().max(f64::MIN_POSITIVE),
    })
}

/// Weighted straight line y = a + b x; returns (a, b) with standard errors.
pub fn line(x: &[f64], y: &[f64], w: &[f64]) -> Option<(Estimate, Estimate)> {
    let n = x.len();
    if n < 3 {
        return None;
    }
    let sw: f64 = w.iter().sum();
    let xm = x.iter().zip(w).map(|(x, w)| x * w).sum::<f64>() / sw;
    let ym = y.iter().zip(w).map(|(y, w)| y * w).sum::<f64>() / sw;
    let (mut sxx, mut sxy) = (0.0, 0.0);
    for i in 0..n {
        sxx += w[i] * (x[i] - xm).powi(2);
        sxy += w[i] * (x[i] - xm) * (y[i] - ym);
    }
    if sxx <= 0.0 {
        return None;
    }
    let b = sxy / sxx;
    let a = ym - b * xm;
    let rss: f64 = (0..n).map(|i| w[i] * (y[i] - a - b * x[i]).powi(2)).sum();
    let s2 = rss / (n as f64 - 2.0).max(1.0);
    let se_b = (s2 / sxx).sqrt();
    let se_a = (s2 * (1.0 / sw + xm * xm / sxx)).sqrt();
    Some((
        Estimate {
            value: a,
            stderr: se_a,
        },
        Estimate {
            value: b,
            stderr: se_b,
        },
    ))
}

/// The paper's clearance: the straight line through the restoring force A·ω0² over the upper
/// half of the amplitude range covered, extrapolated to zero force; returns the intercept
/// amplitude (a half-gap estimate; biased, see DESIGN.md) and the amplitudes fitted.
pub fn extrapolated_half_gap(bins: &[Bin]) -> Option<(Estimate, (f64, f64))> {
    let (lo, hi) = amplitude_range(bins)?;
    let mid = 0.5 * (lo + hi);
    let sel: Vec<&Bin> = bins.iter().filter(|b| b.amplitude >= mid).collect();
    let x: Vec<f64> = sel.iter().map(|b| b.amplitude).collect();
    let y: Vec<f64> = sel.iter().map(|b| b.restoring_force()).collect();
    let w: Vec<f64> = sel.iter().map(|b| b.count as f64).collect();
    let (a, b) = line(&x, &y, &w)?;
    if b.value <= 0.0 {
        return None;
    }
    // y = a + b A = 0 at A0 = −a/b; first-order error propagation.
    let a0 = -a.value / b.value;
    let se = ((a.stderr / b.value).powi(2) + (a0 * b.stderr / b.value).powi(2)).sqrt();
    Some((
        Estimate {
            value: a0,
            stderr: se,
        },
        (mid, hi),
    ))
}

/// Smallest and largest bin amplitude.
pub fn amplitude_range(bins: &[Bin]) -> Option<(f64, f64)> {
    let lo = bins
        .iter()
        .map(|b| b.amplitude)
        .fold(f64::INFINITY, f64::min);
    let hi = bins.iter().map(|b| b.amplitude).fold(0.0, f64::max);
    (lo.is_finite() && hi > lo).then_some((lo, hi))
}

/// Viscous + Coulomb damping: 2h0 = c/J + (4/π)(F/J)/(Aω), a line in 1/(Aω). Returns
/// (c/J in 1/s, F/J in units/s²).
pub fn fit_damping(bins: &[Bin]) -> Option<(Estimate, Estimate)> {
    let sel: Vec<&Bin> = bins
        .iter()
        .filter(|b| b.velocity > 0.0 && b.damping.is_finite())
        .collect();
    let x: Vec<f64> = sel.iter().map(|b| 1.0 / b.velocity).collect();
    let y: Vec<f64> = sel.iter().map(|b| b.damping).collect();
    let w = inverse_variance_weights(sel.iter().map(|b| (b.damping, b.damping_spread, b.count)));
    let (a, b) = line(&x, &y, &w)?;
    let f = PI / 4.0;
    Some((
        a,
        Estimate {
            value: b.value * f,
            stderr: b.stderr * f,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Quartiles, medians and the amplitude range by selection are, bit for bit, the
    /// values sorting by `total_cmp` puts at those ranks: every length to 300 and some
    /// long ones, with ties, signed zeros, infinities and NaNs of either sign.
    #[test]
    fn selected_quartiles_are_the_sorted_values() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let odd = [
            0.0,
            -0.0,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            -f64::NAN,
            1.0,
        ];
        let lengths = (1..=300).chain([1000, 4097, 30_000]);
        for (case, n) in lengths.enumerate() {
            let v: Vec<f64> = (0..n)
                .map(|i| match (case + i) % 9 {
                    0 => odd[rng.random_range(0..odd.len())],
                    1 | 2 => (rng.random_range(0..4) as f64) * 0.25,
                    _ => rng.random_range(-1.0..1.0) * 10f64.powf(rng.random_range(-8.0..8.0)),
                })
                .collect();
            let mut sorted = v.clone();
            sorted.sort_by(f64::total_cmp);
            let at = |p: f64| sorted[rank(n, p)].to_bits();
            let (q1, m, q3) = quartiles(&mut v.clone());
            assert_eq!(
                [q1.to_bits(), m.to_bits(), q3.to_bits()],
                [at(0.25), at(0.5), at(0.75)],
                "n = {n}"
            );
            assert_eq!(median(&mut v.clone()).to_bits(), at(0.5), "n = {n}");
            let (lo, hi) = quantiles(&mut v.clone(), 0.005, 0.995);
            assert_eq!(
                [lo.to_bits(), hi.to_bits()],
                [at(0.005), at(0.995)],
                "n = {n}"
            );
        }
    }

    #[test]
    fn the_orbit_table_matches_the_exact_solve() {
        let mut worst = 0.0f64;
        for i in 0..200_000 {
            // Dense near both ends, where the curve bends most.
            let x = (i as f64 + 0.5) / 200_000.0;
            let s = ORBIT_S_MAX * x.powf(if i % 2 == 0 { 1.0 } else { 3.0 });
            let u = orbit_u_exact(1.0 / s);
            let exact = (1.0 - u) * (1.0 - u);
            let fast = dead_zone_orbit_ratio(s, 1.0);
            worst = worst.max((fast - exact).abs());
        }
        println!("orbit table against the exact solve: largest difference {worst:.1e}");
        assert!(worst < 1e-13, "largest difference {worst:e}");
        assert_eq!(dead_zone_orbit_ratio(1.0, 8.0 / (PI * PI) * 0.999), 0.0);
    }

    fn bins_from(f: impl Fn(f64) -> (f64, f64, f64)) -> Vec<Bin> {
        (0..40)
            .map(|i| {
                let a = 0.015 * (1.0 + i as f64 / 20.0);
                let (k, d, v) = f(a);
                Bin {
                    amplitude: a,
                    stiffness: k,
                    stiffness_spread: 0.0,
                    damping: d,
                    damping_spread: 0.0,
                    velocity: v,
                    count: 10,
                }
            })
            .collect()
    }

    #[test]
    fn dead_zone_fit_recovers_an_exact_curve() {
        let (k, delta) = (4747.0, 0.0131);
        let bins = bins_from(|a| (k * dead_zone_ratio(delta, a), 0.0, 1.0));
        let f = fit_dead_zone(&bins, BackboneModel::DescribingFunction).unwrap();
        assert!((f.half_gap.value - delta).abs() < 1e-6 * delta, "{f:?}");
        assert!((f.stiffness.value - k).abs() < 1e-6 * k);
    }

    /// The closed form against the orbit itself: the piecewise motion (free flight at
    /// constant speed, half a sine in contact) integrated numerically for its first harmonic.
    #[test]
    fn orbit_ratio_matches_the_numerical_first_harmonic() {
        let (delta, wn) = (0.5, 3.0);
        for peak in [0.51, 0.55, 0.6, 0.75, 1.0, 2.0, 5.0] {
            let a = peak - delta;
            let tau = delta / (a * wn);
            let tq = tau + 0.5 * PI / wn;
            let w = 0.5 * PI / tq;
            let n = 200_000;
            let h = tq / n as f64;
            let x = |t: f64| {
                if t < tau {
                    a * wn * t
                } else {
                    delta + a * (wn * (t - tau)).sin()
                }
            };
            // Quarter-wave symmetry: b1 = (2/T_q) ∫₀^{T_q} x sin ωt dt (Simpson).
            let mut sum = x(0.0) * 0.0 + x(tq) * (w * tq).sin();
            for i in 1..n {
                let t = i as f64 * h;
                sum += if i % 2 == 1 { 4.0 } else { 2.0 } * x(t) * (w * t).sin();
            }
            let a1 = 2.0 / tq * sum * h / 3.0;
            let ratio = dead_zone_orbit_ratio(delta, a1);
            let truth = (w / wn).powi(2);
            assert!(
                (ratio - truth).abs() < 1e-6 * truth.max(1e-3),
                "peak {peak}: {ratio} vs {truth}"
            );
        }
        assert_eq!(dead_zone_orbit_ratio(0.0, 1.0), 1.0);
        assert_eq!(dead_zone_orbit_ratio(1.0, 0.8), 0.0);
        // Far from the gap the orbit and the describing function agree.
        let (o, d) = (dead_zone_orbit_ratio(1.0, 50.0), dead_zone_ratio(1.0, 50.0));
        assert!((o - d).abs() < 1e-5, "{o} {d}");
    }

    /// The bisection the Newton solve replaced, as its reference.
    fn orbit_ratio_by_bisection(delta: f64, amplitude: f64) -> f64 {
        let target = amplitude / delta;
        if target <= 8.0 / (PI * PI) {
            return 0.0;
        }
        let h = |u: f64| 8.0 * (0.5 * PI * u).sin() / (PI * PI * u * u * (2.0 - u));
        let (mut lo, mut hi) = (0.0f64, 1.0f64);
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if mid <= lo || mid >= hi {
                break;
            }
            if h(mid) > target {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        let u = 0.5 * (lo + hi);
        (1.0 - u) * (1.0 - u)
    }

    #[test]
    fn orbit_ratio_newton_equals_bisection() {
        let threshold = 8.0 / (PI * PI);
        let mut worst = 0f64;
        for i in 0..20_000 {
            // From just above the contact threshold to 10⁶ times the gap, log-spaced.
            let a = threshold * (1.0 + 1e-9) * (1e6f64 / threshold).powf(i as f64 / 19_999.0);
            let (x, y) = (
                dead_zone_orbit_ratio(1.0, a),
                orbit_ratio_by_bisection(1.0, a),
            );
            worst = worst.max((x - y).abs());
        }
        assert!(worst < 1e-12, "worst difference {worst:e}");
    }

    #[test]
    fn orbit_fit_recovers_an_exact_curve() {
        let (k, delta) = (4747.0, 0.0131);
        let bins = bins_from(|a| (k * dead_zone_orbit_ratio(delta, a), 0.0, 1.0));
        let f = fit_dead_zone(&bins, BackboneModel::PeriodicOrbit).unwrap();
        assert!((f.half_gap.value - delta).abs() < 1e-6 * delta, "{f:?}");
        assert!((f.stiffness.value - k).abs() < 1e-6 * k);
    }

    #[test]
    fn extrapolation_is_biased_as_design_says() {
        let (k, delta) = (4747.0, 0.01);
        // A ∈ [5δ, 20δ]: intercept ≈ 1.27δ.
        let bins: Vec<Bin> = (0..60)
            .map(|i| {
                let a = delta * (5.0 + 15.0 * i as f64 / 59.0);
                Bin {
                    amplitude: a,
                    stiffness: k * dead_zone_ratio(delta, a),
                    stiffness_spread: 0.0,
                    damping: 0.0,
                    damping_spread: 0.0,
                    velocity: 1.0,
                    count: 1,
                }
            })
            .collect();
        let (a0, _) = extrapolated_half_gap(&bins).unwrap();
        let ratio = a0.value / delta;
        assert!(ratio > 1.2 && ratio < 4.0 / PI + 1e-3, "{ratio}");
    }

    #[test]
    fn damping_fit_separates_viscous_and_dry() {
        let (c, fric) = (4.1, 0.8);
        let bins = bins_from(|a| {
            let v = a * 60.0;
            (1.0, c + 4.0 * fric / (PI * v), v)
        });
        let (cv, fr) = fit_damping(&bins).unwrap();
        assert!((cv.value - c).abs() < 1e-9 && (fr.value - fric).abs() < 1e-9);
    }

    #[test]
    fn skeleton_bins_medians() {
        let samples: Vec<Sample> = (0..1000)
            .map(|i| Sample {
                amplitude: 1.0 + i as f64 / 1000.0,
                omega: 10.0,
                stiffness: 100.0,
                damping: 0.5,
            })
            .collect();
        let b = skeleton(&samples, 10, 5);
        assert_eq!(b.len(), 10);
        for bin in &b {
            assert_eq!(bin.stiffness, 100.0);
            assert_eq!(bin.damping, 1.0);
            assert!(
                (bin.natural_frequency() - 10f64.sqrt() * 10f64.sqrt() / (2.0 * PI)).abs() < 1e-12
            );
        }
    }
}
