//! Mode isolation: which band of a record one mode lives in.
//!
//! In: a run's channels (force and response, or the response alone of a free decay) and
//! what the user asked for ([`ModeChoice`]). Out: a [`ModeBand`] — the band's edges and the
//! mode's peak frequency — that the identification band-passes both channels to before any
//! track is taken, so that a sweep through several modes, or a hammer decay that rings in
//! all of them, is identified one mode at a time.
//!
//! The automatic choice reads the frequency response |H(f)| = √(S_yy/S_xx) of the record
//! as measured (accelerance for an accelerometer), smoothed over 0.5 % of frequency; a free
//! decay has no input and uses the response's own spectrum. The mode is the largest peak
//! (or the prominent peak nearest a frequency the user names); its band runs to the lowest
//! point of |H| towards each neighbouring prominent peak (or to the end of the resolvable
//! range where there is none). No fixed width: a joint with free play sweeps its frequency
//! over an octave or more as its amplitude changes, and a record with one mode keeps all
//! of it, less the harmonics beyond the valley above the mode.

use std::f64::consts::PI;

use crate::run::{Run, RunKind};
use crate::transform::{fast_len, real_inverse_plan, real_plan};

/// What the user asked for.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, Default)]
pub enum ModeChoice {
    /// For force-input runs the largest mode when the record shows more than one, else the
    /// whole record; the whole record for base-motion runs (whose joint sweeps its
    /// frequency over a wide range) and free decays.
    #[default]
    ByKind,
    /// No isolation for any run.
    Whole,
    /// The largest mode of every run.
    Largest,
    /// The prominent mode nearest this frequency (Hz).
    Near(f64),
    /// This band (Hz), as given.
    Band(f64, f64),
}

impl ModeChoice {
    /// Refuses a band or frequency that no record can have.
    pub fn validate(&self) -> Result<(), String> {
        match *self {
            ModeChoice::Near(f) if !(f > 0.0 && f.is_finite()) => {
                Err(format!("mode frequency {f} Hz must be positive"))
            }
            ModeChoice::Band(lo, hi) if !(lo > 0.0 && hi > lo && hi.is_finite()) => Err(format!(
                "mode band {lo}:{hi} Hz must have 0 < fmin < fmax, e.g. 6:9"
            )),
            _ => Ok(()),
        }
    }
}

/// How a band was chosen (results.h5 `mode_choice`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum Chosen {
    /// The largest peak of the response.
    Largest,
    /// The prominent peak nearest a named frequency.
    Near,
    /// Given by the user (option or run attribute).
    Given,
}

impl Chosen {
    /// The name written to results.h5 and the summaries.
    pub fn as_str(self) -> &'static str {
        match self {
            Chosen::Largest => "largest",
            Chosen::Near => "near",
            Chosen::Given => "given",
        }
    }
}

/// The band one mode was isolated in.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ModeBand {
    /// Lower edge, Hz.
    pub fmin: f64,
    /// Upper edge, Hz.
    pub fmax: f64,
    /// The mode's peak in the record's frequency response (Hz); the band's geometric centre
    /// when the band was given.
    pub peak: f64,
    /// How it was chosen.
    pub chosen: Chosen,
}

impl ModeBand {
    /// How long [`band_pass`] spreads an impulse on this band (s): the reciprocal of its
    /// narrower edge's raised-cosine ramp (the lower's, fmin·(1 − 1/[`EDGE`])). A hammer's
    /// impact leaves the band-passed record this long after it.
    pub fn spread(&self) -> f64 {
        1.0 / (self.fmin * (1.0 - 1.0 / EDGE)).min(self.fmax * (EDGE - 1.0))
    }
}

/// Why no band could be chosen.
#[derive(Debug, thiserror::Error)]
pub enum ModeError {
    /// The record has no resolvable peak.
    #[error("no mode found: {0}")]
    NoPeak(String),
}

/// A peak counts as a mode when it stands this factor above the valleys on both sides.
const PROMINENCE: f64 = 1.5;
/// Relative spacing of the log-frequency grid the response is smoothed on.
const GRID: f64 = 0.005;

/// One point of the smoothed frequency response.
#[derive(Debug, Clone, Copy)]
struct Point {
    f: f64,
    h: f64,
}

/// The band to isolate in `run`, or `None` for the whole record. The run's own attributes
/// (`mode_fmin`/`mode_fmax`, `mode_near`) are used where `choice` leaves it to the kind.
pub fn choose(run: &Run, choice: ModeChoice) -> Result<Option<ModeBand>, ModeError> {
    let meta = &run.meta;
    let by_kind = choice == ModeChoice::ByKind;
    let choice = match choice {
        ModeChoice::ByKind => match (meta.mode_band, meta.mode_near) {
            (Some((lo, hi)), _) => ModeChoice::Band(lo, hi),
            (None, Some(f)) => ModeChoice::Near(f),
            // A free decay of a joint with free play sweeps its frequency as it decays and
            // rings in its own harmonics, which an automatic choice would take for modes:
            // decays are isolated only when asked (--mode-near, --band, run attributes).
            _ if meta.kind != RunKind::Force => ModeChoice::Whole,
            _ => ModeChoice::Largest,
        },
        c => c,
    };
    let fs = meta.sample_rate;
    let input = match meta.kind {
        RunKind::Free => None,
        _ => run.input.as_deref(),
    };
    match choice {
        ModeChoice::Whole | ModeChoice::ByKind => Ok(None),
        ModeChoice::Band(lo, hi) => Ok(Some(ModeBand {
            fmin: lo,
            fmax: hi.min(0.49 * fs),
            peak: (lo * hi).sqrt(),
            chosen: Chosen::Given,
        })),
        // Left to the kind, a record with one prominent mode is kept whole: there is nothing
        // to isolate it from, and a joint with free play sweeps its frequency beyond any
        // band as its amplitude changes (the demo's free decay).
        ModeChoice::Largest if by_kind => {
            let h = response(input, &run.output, fs);
            if h.len() >= 5 && prominent_peaks(&h).len() <= 1 {
                return Ok(None);
            }
            isolate(input, &run.output, fs, None).map(Some)
        }
        ModeChoice::Largest => isolate(input, &run.output, fs, None).map(Some),
        ModeChoice::Near(f) => isolate(input, &run.output, fs, Some(f)).map(Some),
    }
}

/// The band of the largest mode (or of the prominent one nearest `near` Hz) of `output`,
/// driven by `input` when there is one.
pub fn isolate(
    input: Option<&[f64]>,
    output: &[f64],
    fs: f64,
    near: Option<f64>,
) -> Result<ModeBand, ModeError> {
    let h = response(input, output, fs);
    if h.len() < 5 {
        return Err(ModeError::NoPeak(
            "the record is too short or its excitation too narrow to show a frequency response"
                .into(),
        ));
    }
    let peaks = prominent_peaks(&h);
    let pick = match near {
        None => peaks
            .iter()
            .copied()
            .max_by(|&a, &b| h[a].h.total_cmp(&h[b].h)),
        Some(f) => peaks
            .iter()
            .copied()
            .min_by(|&a, &b| (h[a].f / f).ln().abs().total_cmp(&(h[b].f / f).ln().abs())),
    };
    let Some(p) = pick else {
        return Err(ModeError::NoPeak(format!(
            "the frequency response between {:.3} and {:.3} Hz has no peak standing {PROMINENCE}× above its surroundings; give the band ({} FMIN:FMAX)",
            h[0].f,
            h[h.len() - 1].f,
            crate::hint::Hint::Band
        )));
    };
    let f0 = h[p].f;
    // The band runs down to the valley towards the neighbouring mode, never past it.
    let below = peaks.iter().copied().filter(|&q| q < p).max().unwrap_or(0);
    let above = peaks
        .iter()
        .copied()
        .filter(|&q| q > p)
        .min()
        .unwrap_or(h.len() - 1);
    let valley = |r: std::ops::RangeInclusive<usize>| {
        r.min_by(|&a, &b| h[a].h.total_cmp(&h[b].h))
            .map_or(f0, |i| h[i].f)
    };
    let fmin = valley(below..=p);
    let fmax = valley(p..=above);
    Ok(ModeBand {
        fmin,
        fmax,
        peak: f0,
        chosen: if near.is_some() {
            Chosen::Near
        } else {
            Chosen::Largest
        },
    })
}

/// |H| on a log-frequency grid, smoothed over ±GRID/2 of each grid frequency, where the
/// excitation carries power (a thousandth of its peak, smoothed) and the record can resolve
/// a few cycles.
fn response(input: Option<&[f64]>, output: &[f64], fs: f64) -> Vec<Point> {
    let n = output.len();
    let power = |x: &[f64]| -> Vec<f64> {
        let len = fast_len(n);
        let mean = x.iter().sum::<f64>() / n.max(1) as f64;
        let mut buf = vec![0.0; len];
        for (b, v) in buf.iter_mut().zip(x) {
            *b = v - mean;
        }
        let fft = real_plan(len);
        let mut spec = fft.make_output_vec();
        fft.process(&mut buf, &mut spec)
            .expect("buffer sizes come from the plan");
        spec.iter().map(|c| c.norm_sqr()).collect()
    };
    let syy = power(output);
    let sxx = input.map(power);
    let df = fs / fast_len(n) as f64;
    let duration = n as f64 / fs;
    let f_lo = (4.0 / duration).max(2.0 * df);
    let f_hi = 0.45 * fs;
    let mut grid = Vec::new();
    let mut f = f_lo;
    while f < f_hi {
        let lo = ((f * (1.0 - GRID / 2.0) / df).floor() as usize).max(1);
        let hi = ((f * (1.0 + GRID / 2.0) / df).ceil() as usize).min(syy.len() - 1);
        let mean = |s: &[f64]| s[lo..=hi].iter().sum::<f64>() / (hi - lo + 1) as f64;
        grid.push((f, mean(&syy), sxx.as_deref().map(mean)));
        f *= 1.0 + GRID;
    }
    let drive_peak = grid.iter().filter_map(|g| g.2).fold(0.0f64, f64::max);
    grid.into_iter()
        .filter(|g| g.2.is_none_or(|x| x > 1e-3 * drive_peak && x > 0.0))
        .map(|(f, y, x)| Point {
            f,
            h: x.map_or(y.sqrt(), |x| (y / x).sqrt()),
        })
        .collect()
}

/// Indices of the local maxima of `h` that stand [`PROMINENCE`]× above the lowest point
/// between them and the next higher point on each side (or the record's end).
fn prominent_peaks(h: &[Point]) -> Vec<usize> {
    let n = h.len();
    (1..n - 1)
        .filter(|&i| h[i].h >= h[i - 1].h && h[i].h > h[i + 1].h)
        .filter(|&i| {
            let side = |r: &mut dyn Iterator<Item = usize>| {
                let mut low = h[i].h;
                for j in r {
                    if h[j].h > h[i].h {
                        break;
                    }
                    low = low.min(h[j].h);
                }
                low
            };
            let left = side(&mut (0..i).rev());
            let right = side(&mut (i + 1..n));
            // A peak at the edge of the excited range has no valley on that side: the
            // other side must show it.
            h[i].h >= PROMINENCE * left.max(right).min(h[i].h)
                && h[i].h >= PROMINENCE * left.min(right)
        })
        .collect()
}

/// The ratio of each edge frequency of a [`band_pass`] to where its ramp ends outside
/// the band.
pub const EDGE: f64 = 1.1;

/// Zero-phase band-pass: the spectrum kept flat between `fmin` and `fmax` and rolled off
/// by a raised cosine over 10 % of each edge frequency outside the band; the record is
/// zero-padded by a tenth so that its ends do not wrap into each other.
pub fn band_pass(x: &[f64], fs: f64, fmin: f64, fmax: f64) -> Vec<f64> {
    let n = x.len();
    let len = fast_len(n + n / 10 + 16);
    let mean = x.iter().sum::<f64>() / n.max(1) as f64;
    let mut buf = vec![0.0; len];
    for (b, v) in buf.iter_mut().zip(x) {
        *b = v - mean;
    }
    let fwd = real_plan(len);
    let mut spec = fwd.make_output_vec();
    fwd.process(&mut buf, &mut spec)
        .expect("buffer sizes come from the plan");
    let (lo0, hi1) = (fmin / EDGE, fmax * EDGE);
    let ramp = |u: f64| 0.5 - 0.5 * (PI * u.clamp(0.0, 1.0)).cos();
    for (m, c) in spec.iter_mut().enumerate() {
        let f = m as f64 * fs / len as f64;
        let gate = if f <= lo0 || f >= hi1 {
            0.0
        } else if f < fmin {
            ramp((f - lo0) / (fmin - lo0))
        } else if f > fmax {
            ramp((hi1 - f) / (hi1 - fmax))
        } else {
            1.0
        };
        *c *= gate / len as f64;
    }
    let inv = real_inverse_plan(len);
    let mut out = inv.make_output_vec();
    inv.process(&mut spec, &mut out)
        .expect("buffer sizes come from the plan");
    out.truncate(n);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two modes (4 Hz and 11 Hz) of a linear structure swept by a force: the response is
    /// the sum of two resonances, the larger at 11 Hz.
    fn two_modes(fs: f64, n: usize) -> (Vec<f64>, Vec<f64>) {
        let mut f = vec![0.0; n];
        let mut y = vec![0.0; n];
        let modes = [(4.0, 0.02, 1.0), (11.0, 0.01, 3.0)];
        let mut state = [(0.0f64, 0.0f64); 2];
        let dt = 1.0 / fs;
        for i in 0..n {
            let t = i as f64 * dt;
            // A sweep 1 -> 20 Hz over the record.
            let rate = 19.0 / (n as f64 * dt);
            let force = (2.0 * PI * (1.0 * t + 0.5 * rate * t * t)).sin();
            f[i] = force;
            let mut out = 0.0;
            for (s, &(fn_, z, gain)) in state.iter_mut().zip(&modes) {
                let w = 2.0 * PI * fn_;
                // Semi-implicit Euler, fine at 100 samples per cycle of the upper mode.
                let acc = gain * force - 2.0 * z * w * s.1 - w * w * s.0;
                s.1 += acc * dt;
                s.0 += s.1 * dt;
                out += s.0 * w * w;
            }
            y[i] = out;
        }
        (f, y)
    }

    #[test]
    fn the_largest_mode_and_the_one_named_are_found_with_bands_between_them() {
        let fs = 1000.0;
        let (f, y) = two_modes(fs, 200_000);
        let b = isolate(Some(&f), &y, fs, None).unwrap();
        assert!((b.peak / 11.0 - 1.0).abs() < 0.01, "{b:?}");
        assert!(b.fmin > 4.0 && b.fmin < 11.0 / 1.05, "{b:?}");
        assert!(
            // The sweep ends at 20 Hz (its spectrum's edge leaks a little past it): the band
            // stops at the end of the excited range.
            b.fmax > 11.0 * 1.05 && b.fmax <= 22.0,
            "{b:?}"
        );
        let a = isolate(Some(&f), &y, fs, Some(3.5)).unwrap();
        assert!((a.peak / 4.0 - 1.0).abs() < 0.01, "{a:?}");
        assert!(a.fmax < 11.0 && a.fmax > 4.2, "{a:?}");
        assert_eq!(a.chosen, Chosen::Near);
    }

    #[test]
    fn an_impulse_band_passed_has_died_away_one_spread_after_it() {
        // The Brake–Reuss beam's band at its sample rate: an impact at the middle of 4 s.
        let (fs, n) = (12_800.0, 51_200);
        let band = ModeBand {
            fmin: 70.0,
            fmax: 92.0,
            peak: 80.0,
            chosen: Chosen::Given,
        };
        // The lower edge's ramp is 70·(1 − 1/1.1) = 6.36 Hz wide: 0.157 s.
        assert!(
            (band.spread() - 1.1 / 7.0).abs() < 1e-12,
            "{}",
            band.spread()
        );
        let mut x = vec![0.0; n];
        x[n / 2] = 1.0;
        let y = band_pass(&x, fs, band.fmin, band.fmax);
        let peak = y.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
        // The largest response this far after the impact or further, against the peak.
        let beyond = |seconds: f64| {
            let from = n / 2 + (seconds * fs) as usize;
            y[from..].iter().fold(0.0_f64, |m, v| m.max(v.abs())) / peak
        };
        let (half, whole) = (beyond(0.5 * band.spread()), beyond(band.spread()));
        println!("after half the spread {half:.2e}, after the spread {whole:.2e}");
        // 1.0 % of the peak left past one spread, 8.4 % past half of it.
        assert!(whole < 0.015 && half > 0.05);
    }

    #[test]
    fn band_pass_keeps_the_band_and_removes_the_rest() {
        let fs = 500.0;
        let n = 20_000;
        let t = |i: usize| i as f64 / fs;
        let inside: Vec<f64> = (0..n).map(|i| (2.0 * PI * 10.0 * t(i)).sin()).collect();
        let x: Vec<f64> = (0..n)
            .map(|i| {
                inside[i] + 2.0 * (2.0 * PI * 3.0 * t(i)).sin() + (2.0 * PI * 40.0 * t(i)).cos()
            })
            .collect();
        let y = band_pass(&x, fs, 8.0, 12.0);
        // Away from the ends (the padding's transient), the in-band sine alone is left.
        let err = (2000..n - 2000)
            .map(|i| (y[i] - inside[i]).abs())
            .fold(0.0f64, f64::max);
        assert!(err < 1e-3, "{err}");
    }

    #[test]
    fn a_free_decay_is_isolated_on_its_own_spectrum() {
        let fs = 2000.0;
        let n = 20_000;
        let y: Vec<f64> = (0..n)
            .map(|i| {
                let t = i as f64 / fs;
                (-2.0 * t).exp() * (2.0 * PI * 80.0 * t).sin()
                    + 0.3 * (-3.0 * t).exp() * (2.0 * PI * 230.0 * t).sin()
            })
            .collect();
        let b = isolate(None, &y, fs, None).unwrap();
        assert!((b.peak / 80.0 - 1.0).abs() < 0.01, "{b:?}");
        let c = isolate(None, &y, fs, Some(200.0)).unwrap();
        assert!((c.peak / 230.0 - 1.0).abs() < 0.01, "{c:?}");
        assert!(c.fmin > 80.0, "{c:?}");
    }
}
