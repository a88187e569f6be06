//! Whether a result can be believed: a verdict per run and method — `good`, `suspect` or
//! `bad` — with its reasons, and the estimate to read when both methods ran.
//!
//! Why: an identification always produces numbers, also where its own statistics say they
//! are impossible (negative damping well beyond its standard error) or that the fit does not
//! describe the skeleton it was fitted to. The verdict is written beside every result so
//! that nobody has to judge the numbers by eye.

use crate::identify::Identification;
use crate::track::Method;
use crate::units::eng;

/// How far a result can be trusted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Verdict {
    /// Nothing found against it.
    Good,
    /// Usable with care: the reasons say why.
    Suspect,
    /// Physically impossible or unusable.
    Bad,
}

impl Verdict {
    /// `good`, `suspect` or `bad`.
    pub fn as_str(self) -> &'static str {
        match self {
            Verdict::Good => "good",
            Verdict::Suspect => "suspect",
            Verdict::Bad => "bad",
        }
    }
}

/// A verdict and the reasons for it (notes that do not lower it included).
#[derive(Debug, Clone, PartialEq)]
pub struct Quality {
    /// The verdict.
    pub verdict: Verdict,
    /// Why, one sentence each.
    pub reasons: Vec<String>,
}

impl Quality {
    fn lower(&mut self, to: Verdict, reason: String) {
        self.verdict = self.verdict.max(to);
        self.reasons.push(reason);
    }
}

/// How many standard errors two estimates of the same quantity may differ by.
const AGREEMENT_SIGMAS: f64 = 3.0;

/// A negative damping or friction below this share of its scale is zero within resolution.
const NEGLIGIBLE: f64 = 1e-3;

/// A negative damping or friction above this share of its scale (and beyond 3 standard
/// errors) is impossible, not merely doubtful.
const IMPOSSIBLE: f64 = 0.01;

/// Median interquartile half-range of ω0² within the skeleton's bins, relative to ω0²,
/// above which the skeleton is suspect (clean single-mode runs stay below 10 %).
const SCATTERED: f64 = 0.25;

/// How many times the skeleton's own spread the backbone fit's residual may be.
const RESIDUAL_SPREADS: f64 = 3.0;

/// The verdict on one method's result by itself: impossible values (k/J ≤ 0; viscous or
/// Coulomb damping negative beyond 3 standard errors and above 1 % of its scale: ω0 for
/// c/J, the peak restoring force for F/J) are `bad`; a smaller significant negative
/// damping, a backbone fit whose residual is several times the spread of the skeleton it
/// was fitted to, or a partial skeleton, is `suspect`; a clearance within its standard
/// error of zero, and a negative damping below 0.1 % of its scale, are noted as zero.
/// `unit` is the response's displacement unit ([`crate::units`]), for the reasons' text.
pub fn assess(id: &Identification, unit: &str) -> Quality {
    let mut q = Quality {
        verdict: Verdict::Good,
        reasons: Vec::new(),
    };
    if let Some(fit) = &id.dead_zone {
        let k = fit.stiffness;
        // NaN counts as not positive.
        if k.value.is_nan() || k.value <= 0.0 {
            q.lower(
                Verdict::Bad,
                format!("k/J = {:.4e} 1/s² is not positive", k.value),
            );
        }
        let spread = median_relative_spread(if id.fitted_at_resonance {
            &id.resonant_bins
        } else {
            &id.bins
        });
        if let Some(spread) = spread {
            if fit.residual > RESIDUAL_SPREADS * spread && fit.residual > 0.01 {
                q.lower(
                    Verdict::Suspect,
                    format!(
                        "the backbone fit misses its skeleton: RMS residual {:.1} % of ω0² \
                         against a spread of {:.1} % within the bins",
                        100.0 * fit.residual,
                        100.0 * spread
                    ),
                );
            }
        }
    }
    // A skeleton whose bins scatter this much is not one mode's backbone: a sweep through
    // several modes (the F-16), or a track too noisy to bin.
    if let Some(spread) = median_relative_spread(&id.bins) {
        if spread > SCATTERED {
            q.lower(
                Verdict::Suspect,
                format!(
                    "the skeleton scatters: ω0² spreads by a median {:.0} % within its \
                     amplitude bins, so no one backbone describes it (several modes in the \
                     band? narrow it with {})",
                    100.0 * spread,
                    crate::hint::Hint::FrequencyRange
                ),
            );
        }
    }
    if let Some(c) = id.clearance() {
        if c.value.abs() <= c.stderr || c.value.abs() < 1e-12 {
            q.reasons.push(format!(
                "no clearance resolved: 2δ = 0 within ± {} (fitted {:.2e} {unit}, zero within its error)",
                eng(c.stderr, unit),
                c.value
            ));
        }
    }
    if let Some((c, f)) = id.damping {
        // What "large" means for each: the natural angular frequency for c/J, the peak
        // restoring force per inertia of the skeleton for F/J.
        let omega0 = id
            .dead_zone
            .map(|d| d.stiffness.value)
            .or_else(|| id.bins.iter().map(|b| b.stiffness).reduce(f64::max))
            .filter(|k| *k > 0.0)
            .map(f64::sqrt);
        let peak_force = id
            .bins
            .iter()
            .map(|b| b.restoring_force())
            .filter(|v| v.is_finite())
            .reduce(f64::max);
        let friction_unit = format!("{unit}/s²");
        for (what, e, unit, scale, scale_name) in [
            ("viscous damping c/J", c, "1/s", omega0, "ω0"),
            (
                "Coulomb friction F/J",
                f,
                friction_unit.as_str(),
                peak_force,
                "the peak restoring force",
            ),
        ] {
            if !(e.value < 0.0 && -e.value > e.stderr.max(0.0)) {
                continue;
            }
            let size = scale.map(|s| -e.value / s);
            let said = format!(
                "negative {what} = {:.3} ± {:.3} {unit}, beyond its standard error",
                e.value, e.stderr
            );
            match size {
                // Too small to matter: zero within what the skeleton resolves.
                Some(r) if r < NEGLIGIBLE => q.reasons.push(format!(
                    "{said}, but {:.2} % of {scale_name}: zero within resolution",
                    100.0 * r
                )),
                Some(r) if r > IMPOSSIBLE && -e.value > AGREEMENT_SIGMAS * e.stderr => q.lower(
                    Verdict::Bad,
                    format!("{said} ({:.1} % of {scale_name}): impossible", 100.0 * r),
                ),
                _ => q.lower(Verdict::Suspect, said),
            }
        }
    }
    for w in &id.warnings {
        if w.starts_with("partial skeleton") {
            q.lower(Verdict::Suspect, w.clone());
        }
    }
    q
}

/// The median over `bins` of the interquartile half-range of ω0² relative to ω0².
fn median_relative_spread(bins: &[crate::fit::Bin]) -> Option<f64> {
    let mut r: Vec<f64> = bins
        .iter()
        .filter(|b| b.stiffness > 0.0 && b.stiffness_spread.is_finite())
        .map(|b| b.stiffness_spread / b.stiffness)
        .collect();
    if r.is_empty() {
        return None;
    }
    let mid = r.len() / 2;
    Some(*r.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1)
}

/// Where two methods' results on one run disagree beyond their stated errors (clearance
/// and k/J), one sentence each.
pub fn disagreements(a: &Identification, b: &Identification, unit: &str) -> Vec<String> {
    let mut out = Vec::new();
    let pairs = [
        ("clearance 2δ", a.clearance(), b.clearance(), unit),
        (
            "k/J",
            a.dead_zone.map(|f| f.stiffness),
            b.dead_zone.map(|f| f.stiffness),
            "1/s²",
        ),
    ];
    for (what, x, y, unit) in pairs {
        let (Some(x), Some(y)) = (x, y) else { continue };
        let sigma = x.stderr.hypot(y.stderr);
        let gap = (x.value - y.value).abs();
        // Both errors known, and a difference that matters besides being significant.
        if sigma.is_finite()
            && gap > AGREEMENT_SIGMAS * sigma
            && gap > 0.05 * x.value.abs().max(y.value.abs())
        {
            out.push(format!(
                "{} and {} disagree on {what}: {} ± {} against {} ± {}",
                a.method.as_str(),
                b.method.as_str(),
                eng(x.value, unit),
                eng(x.stderr, unit),
                eng(y.value, unit),
                eng(y.stderr, unit)
            ));
        }
    }
    out
}

/// The verdicts of every method's result on one run (`None` where it failed), the methods
/// disagreeing counted as `suspect` in both; `unit` is the response's displacement unit.
pub fn judge(results: &[(Method, Option<&Identification>)], unit: &str) -> Vec<Option<Quality>> {
    let mut out: Vec<Option<Quality>> = results
        .iter()
        .map(|(_, id)| id.map(|id| assess(id, unit)))
        .collect();
    for i in 0..results.len() {
        for j in i + 1..results.len() {
            let (Some(a), Some(b)) = (results[i].1, results[j].1) else {
                continue;
            };
            for d in disagreements(a, b, unit) {
                for k in [i, j] {
                    if let Some(q) = &mut out[k] {
                        q.lower(Verdict::Suspect, d.clone());
                    }
                }
            }
        }
    }
    out
}

/// The method whose result to read: the first good one, wavelet first, else the first
/// suspect one; none when every result is bad or failed.
pub fn recommend(results: &[(Method, Option<Quality>)]) -> Option<Method> {
    let order = [Method::Wavelet, Method::Hilbert];
    [Verdict::Good, Verdict::Suspect]
        .into_iter()
        .find_map(|want| {
            order.into_iter().find(|m| {
                results
                    .iter()
                    .any(|(r, q)| r == m && q.as_ref().is_some_and(|q| q.verdict == want))
            })
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_recommendation_is_the_first_good_result_wavelet_first() {
        let q = |v| {
            Some(Quality {
                verdict: v,
                reasons: vec![],
            })
        };
        let pick = |w, h| recommend(&[(Method::Wavelet, w), (Method::Hilbert, h)]);
        assert_eq!(
            pick(q(Verdict::Good), q(Verdict::Good)),
            Some(Method::Wavelet)
        );
        assert_eq!(
            pick(q(Verdict::Suspect), q(Verdict::Good)),
            Some(Method::Hilbert)
        );
        assert_eq!(
            pick(q(Verdict::Bad), q(Verdict::Suspect)),
            Some(Method::Hilbert)
        );
        assert_eq!(pick(None, q(Verdict::Bad)), None);
        assert_eq!(pick(q(Verdict::Suspect), None), Some(Method::Wavelet));
    }
}
