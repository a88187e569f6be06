//! What the gap compares of one identification ([`Features`]: its log envelope with running
//! extremes, natural frequency and damping force at resonance, the centre of the relative
//! motion), and the measurement chain's resolution read off the samples (the lattice an
//! encoder's or ADC's steps leave). In: an identification and its run; out: features.

use crate::identify::Identification;
use crate::model::RigModel;
use crate::run::Run;

use super::compare::window_extremes;
use super::TIME_TOLERANCE;

/// What the gap compares of one identification, computed once per identification: its log
/// envelope (NaN where not valid) with the running extremes over ±[`TIME_TOLERANCE`], its
/// natural frequency and damping force at resonance, smoothed over ±[`SMOOTH`] (NaN off
/// resonance), and, where the run's channels are displacements, the centre of the relative
/// motion (its mean over one period).
pub struct Features {
    pub(super) ln: Vec<f64>,
    pub(super) lo: Vec<f64>,
    pub(super) hi: Vec<f64>,
    pub(super) f0: Vec<f64>,
    pub(super) force: Vec<f64>,
    pub(super) centre: Option<Vec<f64>>,
    pub(super) waveform: Vec<f64>,
    pub(super) resolution: f64,
}

/// Cycles of the fundamental each waveform estimate spans (a Hann taper in phase over them).
pub const WAVEFORM_CYCLES: f64 = 2.0;

/// Half-width (s) of the running mean the instantaneous natural frequency and damping force
/// are smoothed with before they are compared (the encoder noise's scatter, sample to
/// sample, would otherwise set the floor of both skeleton domains).
pub const SMOOTH: f64 = 0.1;

impl Features {
    /// The features of `id`, identified from `run`.
    pub fn of(id: &Identification, run: &Run) -> Features {
        let track = &id.response;
        let ln: Vec<f64> = (0..track.len())
            .map(|i| {
                if track.valid[i] && track.amplitude[i] > 0.0 {
                    track.amplitude[i].ln()
                } else {
                    f64::NAN
                }
            })
            .collect();
        let half = (TIME_TOLERANCE * track.sample_rate).round() as usize;
        let (lo, hi) = window_extremes(&ln, half);
        let resonant = |i: usize| id.resonant(i);
        let n = id.used.len().min(track.len());
        let (raw_f0, raw_force): (Vec<f64>, Vec<f64>) = (0..n)
            .map(|i| {
                if !resonant(i) {
                    return (f64::NAN, f64::NAN);
                }
                let w = 2.0 * std::f64::consts::PI * track.frequency[i];
                (
                    id.modal.stiffness[i].max(0.0).sqrt() / (2.0 * std::f64::consts::PI),
                    2.0 * id.modal.damping[i] * track.amplitude[i] * w,
                )
            })
            .unzip();
        let half = (SMOOTH * track.sample_rate).round() as usize;
        let z = relative_motion(run);
        Features {
            waveform: z.as_deref().map_or_else(
                || vec![f64::NAN; track.len()],
                |z| third_harmonic(z, &track.phase, &track.valid, &resonant),
            ),
            centre: z.map(|z| centre(&z, track)),
            ln,
            lo,
            hi,
            f0: mean_around(&raw_f0, |i| raw_f0[i].is_finite().then_some(half)),
            force: mean_around(&raw_force, |i| raw_force[i].is_finite().then_some(half)),
            resolution: 0.0,
        }
    }

    /// The same features with the measurement chain's resolution set: the RMS quantisation
    /// error of the response (see [`measured_resolution`] and [`model_resolution`]).
    pub fn with_resolution(mut self, resolution: f64) -> Features {
        self.resolution = resolution;
        self
    }
}

/// The relative motion z = y − x of a base-motion run whose channels are displacements
/// (`None` otherwise: an integrated velocity or acceleration has lost its mean).
pub(super) fn relative_motion(run: &Run) -> Option<Vec<f64>> {
    use crate::run::{Quantity, RunKind};
    let x = run.input.as_ref()?;
    let displacement = run.meta.output_quantity == Quantity::Displacement
        && run.meta.input_quantity.unwrap_or_default() == Quantity::Displacement;
    (run.meta.kind == RunKind::BaseMotion && displacement && x.len() == run.output.len())
        .then(|| run.output.iter().zip(x).map(|(y, x)| y - x).collect())
}

/// The step of the lattice a sampled channel lies on, when it lies on one: an encoder's or
/// an ADC's least count, with or without an offset, exact ([`exact_lattice_step`]) or
/// blurred by acquisition noise after the quantiser ([`noisy_lattice_step`]).
pub fn lattice_step(x: &[f64]) -> Option<f64> {
    exact_lattice_step(x).or_else(|| noisy_lattice_step(x))
}

/// The step of an exact lattice: the smallest change between consecutive samples, accepted
/// when at least [`LATTICE_SHARE`] of the samples sit within 0.1 % of a step from a whole
/// number of steps above the first. A continuous signal, noisy or not, puts about 0.2 % of
/// its samples there by chance.
pub fn exact_lattice_step(x: &[f64]) -> Option<f64> {
    let step = x
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .filter(|d| *d > 0.0 && d.is_finite())
        .fold(f64::INFINITY, f64::min);
    let (lo, hi) = finite_range(x)?;
    // A handful of levels is a lattice of anything: ask for a few of them at least.
    if !step.is_finite() || x.len() < 100 || (hi - lo) < 4.0 * step {
        return None;
    }
    let on = x
        .iter()
        .filter(|&&v| {
            let u = (v - x[0]) / step;
            (u - u.round()).abs() < 1e-3
        })
        .count();
    (on as f64 >= LATTICE_SHARE * x.len() as f64).then_some(step)
}

fn finite_range(x: &[f64]) -> Option<(f64, f64)> {
    let (lo, hi) = x
        .iter()
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    (hi > lo).then_some((lo, hi))
}

/// How well the samples sit on a lattice of step `q`, whatever its offset: |mean
/// e^{2πi·x/q}|. 1 on an exact lattice; exp(−2π²σ²/q²) when noise of deviation σ is added
/// after the quantiser (0.92 at σ = q/15, 0.995 at q/60); about 1/√n for a continuous
/// signal, and small for steps under a tenth of its range.
pub fn lattice_coherence(x: &[f64], q: f64) -> f64 {
    let w = 2.0 * std::f64::consts::PI / q;
    let (mut c, mut s, mut n) = (0.0, 0.0, 0usize);
    for &v in x.iter().filter(|v| v.is_finite()) {
        let (sin, cos) = (w * v).sin_cos();
        c += cos;
        s += sin;
        n += 1;
    }
    (c * c + s * s).sqrt() / n.max(1) as f64
}

/// Coherence a noisy lattice must reach ([`lattice_coherence`]): noise up to about a fifth
/// of a step (σ = q/5 gives 0.45 … q/4.5 gives 0.38; the 1/60–1/15 of a real acquisition
/// chain gives 0.92–1).
pub const NOISY_COHERENCE: f64 = 0.5;

/// Bins of the value histogram whose spectrum finds a noisy lattice: steps down to 1/100 000
/// of the record's range at 8 bins each.
const HISTOGRAM_BINS: usize = 1 << 20;

/// The step of a lattice blurred by noise: the value histogram's spectrum (the samples'
/// characteristic function) peaks at the lattice's frequency and its harmonics; the lowest
/// such peak with a [`lattice_coherence`] of at least [`NOISY_COHERENCE`] gives the step,
/// refined on the samples themselves. Needs at least 1000 samples, 8 levels and steps
/// larger than 8 histogram bins; a continuous signal's histogram has no such peak (its
/// coherence beyond 8 cycles over its range stays under 0.2 for a sine, a sweep or noise).
pub fn noisy_lattice_step(x: &[f64]) -> Option<f64> {
    let (lo, hi) = finite_range(x)?;
    let n = x.iter().filter(|v| v.is_finite()).count();
    if n < 1000 {
        return None;
    }
    let m = HISTOGRAM_BINS;
    let w = (hi - lo) / (m - 1) as f64;
    let mut h = vec![0.0f64; m];
    for &v in x.iter().filter(|v| v.is_finite()) {
        h[(((v - lo) / w).round() as usize).min(m - 1)] += 1.0;
    }
    let plan = crate::transform::real_plan(m);
    let mut spec = plan.make_output_vec();
    plan.process(&mut h, &mut spec).ok()?;
    // Frequency k (cycles over m bins) is a step of m·w/k; from 8 levels over the range to
    // 8 bins per step.
    let coherence: Vec<f64> = spec.iter().map(|c| c.norm() / n as f64).collect();
    let (k_lo, k_hi) = (8usize, m / 8);
    let best = coherence[k_lo..=k_hi]
        .iter()
        .copied()
        .fold(0.0f64, f64::max);
    if best < NOISY_COHERENCE {
        return None;
    }
    // The fundamental: the lowest local peak near the best (harmonics lose coherence) that
    // stands alone. A lattice's peak is a line, with little coherence a quarter of its
    // frequency below it; a smooth distribution's (many samples near one value, as in a
    // long free decay) falls off gradually from low frequencies and is refused.
    let floor = NOISY_COHERENCE.max(0.6 * best);
    let k0 = (k_lo..=k_hi).find(|&k| {
        let peak = coherence[k] >= floor
            && coherence[k] >= coherence[k - 1]
            && coherence[k] >= coherence[k + 1];
        peak && {
            let below = coherence[k * 7 / 10..=k * 85 / 100]
                .iter()
                .copied()
                .fold(0.0f64, f64::max);
            below < 0.5 * coherence[k]
        }
    })?;
    // Refine on the samples: the peak is about 1/k0 wide in relative step.
    let q_of = |k: f64| m as f64 * w / k;
    let (mut a, mut b) = (q_of(k0 as f64 + 1.0), q_of(k0 as f64 - 1.0));
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut c, mut d) = (b - g * (b - a), a + g * (b - a));
    let (mut fc, mut fd) = (lattice_coherence(x, c), lattice_coherence(x, d));
    for _ in 0..60 {
        if fc > fd {
            b = d;
            d = c;
            fd = fc;
            c = b - g * (b - a);
            fc = lattice_coherence(x, c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + g * (b - a);
            fd = lattice_coherence(x, d);
        }
    }
    let q = 0.5 * (a + b);
    (lattice_coherence(x, q) >= NOISY_COHERENCE).then_some(q)
}

/// Share of the samples that must lie on a lattice for [`lattice_step`] to accept it.
pub const LATTICE_SHARE: f64 = 0.99;

/// The channels the response track is made of: the output, and for a base-motion run the
/// input too (the joint's relative motion is their difference).
pub(super) fn response_channels(run: &Run) -> Vec<&[f64]> {
    let mut ch = vec![run.output.as_slice()];
    if run.meta.kind == crate::run::RunKind::BaseMotion {
        ch.extend(run.input.as_deref());
    }
    ch
}

/// The RMS quantisation error of a measured run's response, from the lattices its channels
/// lie on: `sqrt(Σ q²/12)` over the response's channels (0 where none is quantised). Read
/// from the samples as recorded: a filtered or decimated run has lost its lattice.
pub fn measured_resolution(run: &Run) -> f64 {
    response_channels(run)
        .into_iter()
        .filter_map(lattice_step)
        .map(|q| q * q / 12.0)
        .sum::<f64>()
        .sqrt()
}

/// The RMS quantisation error a model's measurement chain puts on `run`'s response: its
/// quantisation step q on every channel the simulator quantises (the output, and the
/// input of a base-motion run), `q·sqrt(channels/12)`.
pub fn model_resolution(model: &RigModel, run: &Run) -> f64 {
    let q = model
        .effects
        .get(crate::model::EffectKind::Quantization)
        .unwrap_or(0.0);
    q * resolution_per_step(run)
}

/// A resolution of `run`'s recorded response (in its own quantity) as the displacement
/// the identification tracks: divided by ω² for an accelerometer, by ω for a velocity
/// pickup, with ω the mode's peak in `identified` (unchanged for a displacement, or where
/// no mode was isolated).
pub fn as_displacement(resolution: f64, run: &Run, identified: Option<&Identification>) -> f64 {
    let order = match run.meta.output_quantity {
        crate::run::Quantity::Velocity => 1,
        crate::run::Quantity::Acceleration => 2,
        _ => 0,
    };
    match identified.and_then(|i| i.mode) {
        Some(m) if order > 0 && m.peak > 0.0 => {
            resolution / (std::f64::consts::TAU * m.peak).powi(order)
        }
        _ => resolution,
    }
}

/// The RMS quantisation error of `run`'s response per unit of quantisation step,
/// `sqrt(channels/12)`.
pub fn resolution_per_step(run: &Run) -> f64 {
    (response_channels(run).len() as f64 / 12.0).sqrt()
}

/// The mean of `z` over one period of `track`'s frequency around each sample (NaN where
/// the track is not valid): the centre the motion oscillates about.
pub(super) fn centre(z: &[f64], track: &crate::track::Track) -> Vec<f64> {
    mean_around(z, |i| {
        let f = *track.frequency.get(i)?;
        (track.valid[i] && f > 0.0).then(|| (0.5 * track.sample_rate / f).round() as usize)
    })
}

/// The waveform within a cycle: at each valid sample where `at` holds, the third harmonic
/// of `z` against its first, |Z3|/|Z1|, with Zk = Σ w·z·e^(−ikφ) over the valid samples
/// within ±[`WAVEFORM_CYCLES`]/2 cycles of the unwrapped `phase` φ of its fundamental, each weighted by its phase step
/// and a Hann taper in phase (so that a window whose ends fall between samples leaks
/// nothing of the first harmonic into the third). NaN elsewhere.
///
/// Why: every other feature is of the first harmonic, and there a hardening contact on one
/// sweep is a stiffer, wider contact; the fraction of each cycle spent in contact, which
/// the third harmonic measures, is not (`tests/hardening.rs`).
pub(super) fn third_harmonic(
    z: &[f64],
    phase: &[f64],
    valid: &[bool],
    at: &dyn Fn(usize) -> bool,
) -> Vec<f64> {
    use std::f64::consts::PI;
    let n = z.len().min(phase.len()).min(valid.len());
    let span = WAVEFORM_CYCLES * 2.0 * PI;
    let mut out = vec![f64::NAN; phase.len()];
    // e^(−iφ) and e^(−3iφ) once per sample, not once per window a sample falls in (a
    // sample lies in the windows of every sample within two cycles of it, and this runs
    // for every simulation of a search).
    let (mut c1, mut s1, mut c3, mut s3) = (vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    for j in (0..n).filter(|&j| valid[j]) {
        (c1[j], s1[j]) = (phase[j].cos(), phase[j].sin());
        (c3[j], s3[j]) = ((3.0 * phase[j]).cos(), (3.0 * phase[j]).sin());
    }
    for (i, o) in out.iter_mut().enumerate().take(n) {
        if !at(i) || !valid[i] {
            continue;
        }
        let (lo, hi) = (phase[i] - 0.5 * span, phase[i] + 0.5 * span);
        let (mut a, mut b) = (i, i);
        while a > 0 && phase[a - 1] >= lo && valid[a - 1] {
            a -= 1;
        }
        while b + 1 < n && phase[b + 1] <= hi && valid[b + 1] {
            b += 1;
        }
        // A window cut short by the end of the record or of the valid track does not span
        // its cycles, and would leak the first harmonic into the third.
        let whole = a > 0 && phase[a - 1] < lo && b + 1 < n && phase[b + 1] > hi;
        if !whole || b <= a + 2 {
            continue;
        }
        let (mut z1, mut z3) = ((0.0, 0.0), (0.0, 0.0));
        for j in a..=b {
            let step = 0.5 * (phase[(j + 1).min(b)] - phase[j.saturating_sub(1).max(a)]);
            let u = (phase[j] - lo) / span;
            let w = step * (PI * u).sin().powi(2) * z[j];
            z1.0 += w * c1[j];
            z1.1 -= w * s1[j];
            z3.0 += w * c3[j];
            z3.1 -= w * s3[j];
        }
        let h1 = z1.0.hypot(z1.1);
        if h1 > 0.0 {
            *o = z3.0.hypot(z3.1) / h1;
        }
    }
    out
}

/// For each index, the index of the nearest finite value of `x` (the earlier one on a tie),
/// `None` when `x` has none.
pub(super) fn nearest_finite(x: &[f64]) -> Vec<Option<usize>> {
    let mut before = vec![None; x.len()];
    let mut last = None;
    for (i, v) in x.iter().enumerate() {
        if v.is_finite() {
            last = Some(i);
        }
        before[i] = last;
    }
    let mut next = None;
    let mut out = vec![None; x.len()];
    for i in (0..x.len()).rev() {
        if x[i].is_finite() {
            next = Some(i);
        }
        out[i] = match (before[i], next) {
            (Some(b), Some(a)) => Some(if i - b <= a - i { b } else { a }),
            (b, a) => b.or(a),
        };
    }
    out
}

/// At each sample where `half` gives a half-width, the mean of the finite values of `x`
/// over `[i − half, i + half]` (NaN elsewhere, and where the window holds none).
pub(super) fn mean_around(x: &[f64], half: impl Fn(usize) -> Option<usize>) -> Vec<f64> {
    let mut sum = vec![0.0; x.len() + 1];
    let mut count = vec![0usize; x.len() + 1];
    for (i, &v) in x.iter().enumerate() {
        let ok = v.is_finite();
        sum[i + 1] = sum[i] + if ok { v } else { 0.0 };
        count[i + 1] = count[i] + ok as usize;
    }
    (0..x.len())
        .map(|i| {
            let Some(h) = half(i) else {
                return f64::NAN;
            };
            let (a, b) = (i.saturating_sub(h), (i + h + 1).min(x.len()));
            match count[b] - count[a] {
                0 => f64::NAN,
                k => (sum[b] - sum[a]) / k as f64,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A chirp's phase (0.5 to 12 Hz in 30 s at `fs`) and a waveform on it.
    fn chirp(fs: f64, wave: impl Fn(f64) -> f64) -> (Vec<f64>, Vec<f64>) {
        let n = (30.0 * fs) as usize;
        let phase: Vec<f64> = (0..n)
            .map(|i| {
                let t = i as f64 / fs;
                std::f64::consts::TAU * (0.5 * t + 0.5 * (11.5 / 30.0) * t * t)
            })
            .collect();
        let z = phase.iter().map(|&p| wave(p)).collect();
        (phase, z)
    }

    #[test]
    fn the_third_harmonic_is_read_against_the_first_along_a_chirp() {
        // 20 samples per cycle at 12 Hz, as the gap decimates; an offset and a second
        // harmonic beside the third leak nothing into it.
        let fs = 240.0;
        let (phase, z) = chirp(fs, |p| {
            0.003 + 0.02 * p.cos() + 0.004 * (2.0 * p).sin() + 0.0014 * (3.0 * p + 0.3).cos()
        });
        let valid = vec![true; z.len()];
        let r = third_harmonic(&z, &phase, &valid, &|i| i % 7 == 0);
        let got: Vec<f64> = r.iter().copied().filter(|v| v.is_finite()).collect();
        assert!(got.len() > 800, "{}", got.len());
        for (i, v) in r.iter().enumerate().filter(|(_, v)| v.is_finite()) {
            assert!((v / 0.07 - 1.0).abs() < 5e-3, "{i} {v}");
        }
        // Only where asked, and never over a window the valid track does not span.
        assert!(r.iter().enumerate().all(|(i, v)| i % 7 == 0 || v.is_nan()));
        assert!(r[0].is_nan() && r[r.len() - 1].is_nan());
        let mut gap = valid.clone();
        gap[3000..3010].iter_mut().for_each(|v| *v = false);
        let r = third_harmonic(&z, &phase, &gap, &|_| true);
        assert!(r[3005].is_nan() && r[2995].is_nan() && r[3200].is_finite());

        // A pure sine has none, to the quadrature's error at 20 samples a cycle (which the
        // measurement and a simulation, sampled alike, share).
        let (phase, z) = chirp(fs, |p| 0.02 * p.sin());
        let r = third_harmonic(&z, &phase, &valid, &|_| true);
        let worst = r
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max);
        assert!(worst < 1e-3, "{worst}");
    }
}
