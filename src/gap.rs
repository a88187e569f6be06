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
use crate::identify::Identification;

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
