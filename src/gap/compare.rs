//! The measured side of a comparison ([`Target`]: the part of the run compared, its
//! features and where it jumps) and the domains' errors against a model's features,
//! combined into one [`Gap`] with its regions. In: two sets of features; out: a gap.

use crate::identify::Identification;
use crate::run::Run;

use super::features::nearest_finite;
use super::{Errors, Features, Gap, Region, AMPLITUDE_RANGES, TIME_WINDOWS};

/// The measured side of a comparison on one part of a run, prepared once for all the
/// models compared with it: the part's samples, the measurement's features and its jumps.
pub struct Target {
    waveform: bool,
    zero_tolerance: f64,
    pub(super) mask: Option<Vec<bool>>,
    pub(super) features: Features,
    pub(super) jumps: Option<Jumps>,
}

/// Where a response jumps between the low and the resonant branch, on the measurement's
/// scales (its half-gap and decay time).
pub(super) struct Jumps {
    /// The settling windows after each jump-down (sample ranges).
    pub(super) downs: Vec<(usize, usize)>,
    /// The jump-ups onto the resonant branch (a record may sweep more than once), each as
    /// the climb's first sample and the first sample above the grazing band.
    pub(super) ups: Vec<(usize, usize)>,
}

impl Jumps {
    /// The jumps of the log envelope `ln` (NaN where not valid) at `fs` Hz, for a
    /// measurement of half-gap `half_gap` whose settling lasts `settle` seconds.
    fn of(ln: &[f64], fs: f64, half_gap: f64, settle: f64) -> Jumps {
        Jumps {
            downs: settling(ln, fs, half_gap, settle),
            ups: jump_ups(ln, half_gap),
        }
    }
}

impl Target {
    /// `measured` (identified from `run`) on the samples flagged in `mask` (the whole run
    /// when `None`).
    pub fn new(measured: &Identification, run: &Run, mask: Option<Vec<bool>>) -> Target {
        let features = Features::of(measured, run);
        // A free decay has no sweep and so no jumps between branches: from its first
        // sample it would read as one long jump-up and be compared nowhere.
        let swept = run.meta.kind != crate::run::RunKind::Free;
        let jumps = measured.dead_zone.filter(|_| swept).map(|dz| {
            let fs = measured.response.sample_rate;
            Jumps::of(
                &features.ln,
                fs,
                dz.half_gap.value,
                settle_seconds(measured),
            )
        });
        Target {
            waveform: false,
            zero_tolerance: run.meta.zero_tolerance,
            features,
            jumps,
            mask,
        }
    }

    /// The same target, scoring the waveform domain too when `on` (the third harmonic
    /// against the first at resonance, [`super::features::third_harmonic`]).
    pub fn with_waveform(mut self, on: bool) -> Target {
        self.set_waveform(on);
        self
    }

    /// Scores the waveform domain when `on` and the measurement has one (a run whose
    /// channels are not displacements has no relative motion to read it from: its gap stays
    /// the three domains', not a mean diluted by an empty fourth).
    pub(super) fn set_waveform(&mut self, on: bool) {
        self.waveform = on && self.features.waveform.iter().any(|v| v.is_finite());
    }

    /// Sets how far apart the encoders' zeros may be (rad): a constant difference between
    /// the centres of the measured and simulated relative motion up to it is not counted.
    pub(super) fn set_zero_tolerance(&mut self, tolerance: f64) {
        self.zero_tolerance = tolerance.max(0.0);
    }

    /// How far apart the encoders' zeros may be (rad), as this target scores.
    pub(super) fn zero_tolerance(&self) -> f64 {
        self.zero_tolerance
    }

    /// The same target with the measurement's resolution set (its RMS quantisation error,
    /// [`measured_resolution`] of the run as recorded).
    pub fn with_resolution(mut self, resolution: f64) -> Target {
        self.features.resolution = resolution;
        self
    }

    /// The gap of a simulation (its `features`) against `measured`, the identification this
    /// target was prepared from, on the target's samples.
    pub fn gap(&self, measured: &Identification, sim: &Features) -> Gap {
        let mask = self.mask.as_deref();
        let ours = &self.features;
        let fs = measured.response.sample_rate;
        let (mut settling, mut jump_up) = (Vec::new(), Vec::new());
        if let (Some(mj), Some(dz)) = (&self.jumps, measured.dead_zone) {
            let settle = settle_seconds(measured);
            let sj = Jumps::of(&sim.ln, fs, dz.half_gap.value, settle);
            // The settling after a jump-down: the free flight that follows bounces between
            // the flanks for several decay times, and which flank it ends on is the
            // coin-flip again. It is left out where both have jumped within a second of
            // each other (from the first jump to the later end); a model that has not
            // jumped where the measurement has is still scored there.
            settling = paired_settling(&mj.downs, &sj.downs, fs.round() as usize);
            // Between the two jump-ups onto the resonant branch, and while the later one
            // joins the branch: where the branches coexist, the instant of the jump-up is as
            // much a coin-flip as the flank after a jump-down (the noise of the rig decides
            // it), while the jump-down's instant, which the damping sets, stays scored.
            let join = (JOIN_DECAY_TIMES / SETTLE_DECAY_TIMES * settle * fs).round() as usize;
            for &(climb, a) in &mj.ups {
                let partner = sj.ups.iter().min_by_key(|b| a.abs_diff(b.1));
                if let Some(&(climb_b, b)) =
                    partner.filter(|b| a.abs_diff(b.1) as f64 <= JUMP_UP_SPAN * fs)
                {
                    // From a tolerance before the earlier climb: a sample there is matched
                    // against the other's envelope over ±TIME_TOLERANCE, its climb included.
                    let lead = (TIME_TOLERANCE * fs).round() as usize;
                    jump_up.push(climb.min(climb_b).saturating_sub(lead)..a.max(b) + join);
                }
            }
        }
        let keep = |i: usize| {
            mask.is_none_or(|m| m.get(i).copied().unwrap_or(false))
                && !settling.get(i).copied().unwrap_or(false)
                && !jump_up.iter().any(|r| r.contains(&i))
        };
        let mut domains = vec![
            time_errors(measured, ours, sim, &keep, self.zero_tolerance),
            resonance_errors(measured, &ours.f0, &sim.f0, &keep, "backbone"),
            resonance_errors(measured, &ours.force, &sim.force, &keep, "damping"),
        ];
        if self.waveform {
            domains.push(capped(
                resonance_errors(measured, &ours.waveform, &sim.waveform, &keep, "waveform"),
                WAVEFORM_MISS,
            ));
        }
        combine(domains)
    }
}

/// The largest error one sample of the waveform domain counts (relative to the measured
/// third harmonic's RMS): a miss. H3/H1 is a small ratio, and where the measurement's is
/// smaller still (a preloaded link riding on one flank), a model's relative error there ran
/// to 4, outweighing every other domain's and hiding the right effect; a model that far
/// off misses the waveform, as one never at resonance does.
const WAVEFORM_MISS: f64 = 1.0;

/// `errors` with each sample's error limited to `miss` (a squared error to `miss²`).
fn capped(mut errors: Errors, miss: f64) -> Errors {
    for t in &mut errors.terms {
        t.1 = t.1.min(miss * miss);
    }
    errors
}

/// The domains' errors (time, backbone, damping, and the waveform when scored) as one gap
/// with its regions: the root of the mean of the domains' mean squares.
pub(super) fn combine(domains: Vec<Errors>) -> Gap {
    let ms: Vec<Option<f64>> = domains.iter().map(Errors::mean_square).collect();
    let count = domains.len() as f64;
    let total_ms = ms.iter().flatten().sum::<f64>() / count;
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
        // A region's share of the total: its part of the domain's mean square, over the
        // number of domains.
        for (mut region, part) in d.regions.into_iter().zip(per) {
            region.share = if total_ms > 0.0 {
                part / count / total_ms
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
        waveform: ms.get(3).copied().flatten().map(f64::sqrt),
        regions,
    }
}

/// Half-width (s) of the time tolerance of the time domain: a sample's envelope is matched
/// against the other's envelope anywhere within ±this. The instant of a jump-down is as
/// sensitive as the flank the link settles on (a 0.2 % change in k moves it by tenths of a
/// second), and an exact-time comparison would score that instant, not the envelope; the
/// backbone domain holds the frequency errors a tolerance in time forgives.
pub const TIME_TOLERANCE: f64 = 0.25;

/// The grazing band of the time domain, in multiples of the measured half-gap δ: the
/// forced orbit first touches at 8δ/π² ≈ 0.81δ.
pub const GRAZING: (f64, f64) = (0.7, 1.05);

/// Running minimum and maximum of `x` over `[i − half, i + half]`, skipping NaN (an empty
/// window gives +∞, −∞). Monotone deques: O(n).
pub(super) fn window_extremes(x: &[f64], half: usize) -> (Vec<f64>, Vec<f64>) {
    use std::collections::VecDeque;
    let n = x.len();
    let (mut lo, mut hi) = (vec![f64::INFINITY; n], vec![f64::NEG_INFINITY; n]);
    let (mut qmin, mut qmax): (VecDeque<usize>, VecDeque<usize>) =
        (VecDeque::new(), VecDeque::new());
    let mut next = 0;
    for i in 0..n {
        while next < n && next <= i + half {
            if x[next].is_finite() {
                while qmin.back().is_some_and(|&j| x[j] >= x[next]) {
                    qmin.pop_back();
                }
                qmin.push_back(next);
                while qmax.back().is_some_and(|&j| x[j] <= x[next]) {
                    qmax.pop_back();
                }
                qmax.push_back(next);
            }
            next += 1;
        }
        while qmin.front().is_some_and(|&j| j + half < i) {
            qmin.pop_front();
        }
        while qmax.front().is_some_and(|&j| j + half < i) {
            qmax.pop_front();
        }
        if let (Some(&a), Some(&b)) = (qmin.front(), qmax.front()) {
            lo[i] = x[a];
            hi[i] = x[b];
        }
    }
    (lo, hi)
}

/// The longest time (s) between the measured and the simulated jump-up that is forgiven as
/// a coin-flip; a model that jumps up later than that is scored there.
pub const JUMP_UP_SPAN: f64 = 3.0;

/// Decay times the later of two jump-ups takes to join the resonant branch.
pub const JOIN_DECAY_TIMES: f64 = 3.0;

/// Decay times a jump-down's settling lasts in the time domain.
pub const SETTLE_DECAY_TIMES: f64 = 12.0;

/// How long (s) the settling after a jump-down lasts: [`SETTLE_DECAY_TIMES`] decay times
/// 1/h of the measured viscous damping (4 s where the damping was not identified).
pub(super) fn settle_seconds(m: &Identification) -> f64 {
    m.damping
        .map(|(c, _)| c.value)
        .filter(|c| c.is_finite() && *c > 0.0)
        .map_or(4.0, |c| SETTLE_DECAY_TIMES * 2.0 / c)
}

/// The jump-ups of a log envelope `ln` (NaN where not valid) onto the resonant branch of a
/// rig of half-gap `half_gap`: the first sample above the grazing band (1.05 `half_gap`),
/// and the first above it after each fall below it (0.7 `half_gap`), each with the start of
/// its climb, the sample after the last one below the band (the envelope of a climb is
/// often not valid: the ridge jumps with it).
pub(super) fn jump_ups(ln: &[f64], half_gap: f64) -> Vec<(usize, usize)> {
    let (high, low) = ((GRAZING.1 * half_gap).ln(), (GRAZING.0 * half_gap).ln());
    let mut ups = Vec::new();
    let mut below = true;
    let mut last_low = 0;
    for (i, &v) in ln.iter().enumerate() {
        if below && v > high {
            ups.push((last_low.min(i), i));
            below = false;
        } else if v < low {
            below = true;
            last_low = i + 1;
        }
    }
    ups
}

/// Flags the samples of a log envelope `ln` (NaN where not valid) that follow a jump-down
/// by less than `settle` seconds: a fall from above the grazing band (1.05 `half_gap`) to
/// below it (0.7 `half_gap`) within a second.
pub(super) fn settling(ln: &[f64], fs: f64, half_gap: f64, settle: f64) -> Vec<(usize, usize)> {
    let (high, low) = ((GRAZING.1 * half_gap).ln(), (GRAZING.0 * half_gap).ln());
    let within = fs.round() as usize;
    let span = (settle * fs).round() as usize;
    let mut windows = Vec::new();
    let mut last_high: Option<usize> = None;
    for (i, &v) in ln.iter().enumerate() {
        if v > high {
            last_high = Some(i);
        } else if v < low && last_high.is_some_and(|h| i - h <= within) {
            windows.push((i, (i + span).min(ln.len())));
            last_high = None;
        }
    }
    windows
}

/// The samples inside a settling window of `a` that has a partner in `b` starting within
/// `within` samples (or the other way round), from the earlier start to the later end.
pub(super) fn paired_settling(
    a: &[(usize, usize)],
    b: &[(usize, usize)],
    within: usize,
) -> Vec<bool> {
    let n = a.iter().chain(b).map(|w| w.1).max().unwrap_or(0);
    let mut out = vec![false; n];
    for &(s0, e0) in a {
        for &(s1, e1) in b {
            if s0.abs_diff(s1) <= within {
                out[s0.min(s1)..e0.max(e1)].fill(true);
            }
        }
    }
    out
}

/// How far `v` lies outside `[lo, hi]` (0 inside; NaN where the window was empty).
pub(super) fn outside(v: f64, lo: f64, hi: f64) -> f64 {
    if lo > hi {
        f64::NAN
    } else {
        (v - hi).max(lo - v).max(0.0)
    }
}

pub(super) fn time_errors(
    m: &Identification,
    ea: &Features,
    eb: &Features,
    keep: &dyn Fn(usize) -> bool,
    zero_tolerance: f64,
) -> Errors {
    let a = &m.response;
    let n = ea.ln.len().min(eb.ln.len());
    let fs = a.sample_rate;
    let window = n.div_ceil(TIME_WINDOWS).max(1);
    let (la, lb) = (&ea.ln, &eb.ln);
    // Each sample weighs by its amplitude: the free flight inside the clearance after a
    // jump-down is small and chaotic (which flank, how often it touches), and its relative
    // envelope error would otherwise weigh as much as the resonance's.
    let peak = (0..n)
        .filter(|&i| a.valid[i])
        .map(|i| a.amplitude[i])
        .fold(0f64, f64::max)
        .max(f64::MIN_POSITIVE);
    // The grazing band, from the measurement's own clearance: an orbit that just touches
    // the flanks is hypersensitive (a grazing bifurcation), in the rig and in any model of
    // it, so its envelope there is a coin-flip like the jump-down's flank.
    let grazing = |amp: f64| {
        m.dead_zone.is_some_and(|dz| {
            let d = dz.half_gap.value;
            amp > GRAZING.0 * d && amp < GRAZING.1 * d
        })
    };
    // Where both touch both flanks, the centre the motion oscillates about, relative to the
    // measured amplitude: an offset clearance or a preload moves it, and the envelope alone
    // cannot tell (a shifted dead zone shifts z, not its envelope). Off contact the centre
    // is wherever the free flight drifted, and is not compared.
    let centre_shift = |i: usize| -> Option<f64> {
        let (Some(dz), Some(cm), Some(cs)) = (m.dead_zone, &ea.centre, &eb.centre) else {
            return None;
        };
        let high = (GRAZING.1 * dz.half_gap.value).ln();
        let touching = la[i] > high && lb[i] > high;
        let shift = cs.get(i).copied().unwrap_or(f64::NAN) - cm[i];
        (touching && shift.is_finite()).then_some(shift)
    };
    // A difference between the two encoders' zeros shifts the measured relative motion
    // exactly as an offset clearance does (random rigs with zeros 1.6–3.1e-4 rad apart were
    // read as offset clearances). Up to the zero tolerance it is the sensors': the median
    // shift over the compared samples, limited to ±tolerance, is taken out before the
    // centres are compared, and only what an offset clearance adds beyond it is counted.
    // It is taken on each part's own samples (the held-out blocks' too): a constant of the
    // sensors, bounded by the tolerance, not a parameter of the model.
    let zero = if zero_tolerance > 0.0 {
        let mut shifts: Vec<f64> = (0..n)
            .filter(|&i| keep(i) && la[i].is_finite())
            .filter_map(centre_shift)
            .collect();
        shifts.sort_by(f64::total_cmp);
        shifts
            .get(shifts.len() / 2)
            .map_or(0.0, |s| s.clamp(-zero_tolerance, zero_tolerance))
    } else {
        0.0
    };
    let centre_error =
        |i: usize| -> f64 { centre_shift(i).map_or(0.0, |s| (s - zero) / a.amplitude[i]) };
    // The measurement chain's resolution: the quantisation error one of the two has and
    // the other lacks, relative to the measured amplitude. It is the noise floor a coarse
    // encoder leaves at small amplitude, and weighs most there; an error as large as the
    // amplitude counts as a miss (1), like an envelope the other lacks.
    let resolution_gap = (eb.resolution - ea.resolution).abs();
    let resolution_error = |i: usize| -> f64 {
        if resolution_gap == 0.0 {
            0.0
        } else {
            (resolution_gap / a.amplitude[i]).min(1.0).powi(2)
        }
    };
    let mut terms = Vec::new();
    let mut regions = Vec::new();
    for (w, start) in (0..n).step_by(window).enumerate() {
        let end = (start + window).min(n);
        let (mut alo, mut ahi, mut flo, mut fhi) = (f64::INFINITY, 0f64, f64::INFINITY, 0f64);
        for i in start..end {
            if !keep(i) || !la[i].is_finite() || grazing(a.amplitude[i]) {
                continue;
            }
            // Both ways: the measurement within the model's tolerance band and the model's
            // own envelope (where it has one) within the measurement's.
            // A model with no valid envelope within the tolerance misses the sample.
            let e1 = outside(la[i], eb.lo[i], eb.hi[i]);
            let e1 = if e1.is_finite() { e1 } else { 1.0 };
            let e2 = if lb[i].is_finite() {
                outside(lb[i], ea.lo[i], ea.hi[i])
            } else {
                e1
            };
            terms.push((
                a.amplitude[i] / peak,
                0.5 * (e1 * e1 + e2 * e2) + centre_error(i).powi(2) + resolution_error(i),
                w,
            ));
            alo = alo.min(a.amplitude[i]);
            ahi = ahi.max(a.amplitude[i]);
            flo = flo.min(a.frequency[i]);
            fhi = fhi.max(a.frequency[i]);
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

/// The backbone (natural frequency) or damping-force errors at the samples where both are
/// at resonance, e = (v_sim − v_meas) / rms v_meas, with regions by amplitude range (their
/// time and frequency spans taken from the measured track).
///
/// The comparison is made at the same instants, not over amplitude bins: a sweep passes
/// its resonance twice — riding up the backbone and falling off it before the jump — with
/// different damping estimates at the same amplitude, and a binned skeleton mixes the two
/// branches in proportions that jump with every small change of a model.
pub(super) fn resonance_errors(
    m: &Identification,
    meas: &[f64],
    sim: &[f64],
    keep: &dyn Fn(usize) -> bool,
    domain: &'static str,
) -> Errors {
    let r = &m.response;
    let ours: Vec<usize> = (0..meas.len())
        .filter(|&i| keep(i) && meas[i].is_finite())
        .collect();
    let scale =
        (ours.iter().map(|&i| meas[i].powi(2)).sum::<f64>() / ours.len().max(1) as f64).sqrt();
    let (lo, hi) = ours.iter().fold((f64::INFINITY, 0f64), |(l, h), &i| {
        (l.min(r.amplitude[i]), h.max(r.amplitude[i]))
    });
    let range_of = |a: f64| -> usize {
        if hi <= lo {
            return 0;
        }
        let u = (a / lo).ln() / (hi / lo).ln();
        ((u.max(0.0) * AMPLITUDE_RANGES as f64) as usize).min(AMPLITUDE_RANGES - 1)
    };
    // Where the model is not at resonance at that instant, its value at the nearest instant
    // it is: a model whose resonance comes early or late is then off by the frequency the
    // sweep had moved on by, a graded error, instead of being compared nowhere.
    let nearest = nearest_finite(sim);
    let mut terms: Vec<(f64, f64, usize)> = Vec::new();
    if scale > 0.0 {
        for &i in &ours {
            // A model never at resonance (too damped to reach the measured resonance, say)
            // misses all of it.
            let e = nearest
                .get(i)
                .copied()
                .flatten()
                .map_or(1.0, |j| (sim[j] - meas[i]) / scale);
            terms.push((1.0, e * e, range_of(r.amplitude[i])));
        }
    }
    // Each amplitude range's time and frequency span, from the measured track.
    let regions = (0..AMPLITUDE_RANGES)
        .map(|k| {
            let a_lo = lo * (hi / lo).powf(k as f64 / AMPLITUDE_RANGES as f64);
            let a_hi = lo * (hi / lo).powf((k + 1) as f64 / AMPLITUDE_RANGES as f64);
            let (mut t0, mut t1, mut f_lo, mut f_hi) = (f64::INFINITY, 0f64, f64::INFINITY, 0f64);
            for &i in &ours {
                if r.amplitude[i] >= a_lo && r.amplitude[i] <= a_hi {
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
