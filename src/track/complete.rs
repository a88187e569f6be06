//! The wavelet track from its skeleton, whichever backend estimated it. In: a
//! [`WaveletPrep`], its [`CoarseRidge`], the grid and a [`GridEstimate`] per point; out: the
//! [`Track`] — white-noise floor, validity (cone of influence, band, SNR, failed
//! corrections), low-SNR smoothing, the unwrapped phase, σ′, and every sample interpolated
//! from the grid.

use std::f64::consts::PI;
use std::mem::MaybeUninit;

use rayon::prelude::*;

use crate::filter::{window_line, window_lines};
use crate::skeleton::{GridEstimate, GridPoint};
use crate::transform::Morlet;

use super::unwrap::unwrap_phase;
use super::{CoarseRidge, Device, Method, Scalogram, Track, WaveletPrep};

impl WaveletPrep {
    /// The track from the skeleton on the grid, on the CPU whichever backend estimated it:
    /// the white-noise floor (from the first pass's per-scale medians and the spectrum above
    /// the band), validity (cone of influence, band, SNR, failed corrections), low-SNR
    /// smoothing, the phase unwrapped, σ′, and every sample interpolated from the grid.
    pub fn complete(
        self,
        ridge: CoarseRidge,
        grid: &[GridPoint],
        est: &[GridEstimate],
        backend: Device,
    ) -> Track {
        let scalogram = ridge.power.as_ref().map(|p| Scalogram {
            frequency: self.freqs.clone(),
            time: (0..self.steps)
                .map(|j| (j * self.h) as f64 / self.fs)
                .collect(),
            magnitude: p.iter().map(|v| v.max(0.0).sqrt()).collect(),
        });
        let WaveletPrep {
            n,
            fs,
            opt,
            fmin,
            fmax,
            spec,
            noise_above_band,
            ..
        } = self;
        let opt = &opt;
        let wl = opt.wavelet;
        // White-noise floor: the lower of the quietest quarter of the scales (median over
        // time) and the spectrum above the analysis band, where only noise should be left.
        let gains = ridge.gains;
        let mut per_scale: Vec<f64> = ridge
            .median_power
            .iter()
            .zip(&gains)
            .filter_map(|(m, g)| m.map(|m| m / std::f64::consts::LN_2 / (n as f64 * g)))
            .collect();
        let from_scales = if per_scale.is_empty() {
            f64::INFINITY
        } else {
            let q = per_scale.len() / 4;
            *per_scale.select_nth_unstable_by(q, |a, b| a.total_cmp(b)).1
        };
        let g_count = grid.len();
        let from_spectrum = noise_above_band.unwrap_or(f64::INFINITY);
        let noise_var = from_scales.min(from_spectrum);
        let noise_var = if noise_var.is_finite() {
            noise_var
        } else {
            0.0
        };
        let noise_w: Vec<f64> = gains
            .iter()
            .map(|g| (noise_var * n as f64 * g).sqrt())
            .collect();
        let offset = spec.mean;
        drop(spec);
        let Columns {
            t,
            half,
            mut ln_amp,
            mut phase,
            decay,
            mut frequency,
            sweep,
            observed,
            noise,
            peaked,
            corrected,
        } = Columns::of(grid, est, fs, &wl, &noise_w);
        // The sweep rate as the frequency track's own slope over ±σ_t: where the window saw a
        // signal the local model cannot describe, it disagrees with the model's β.
        // σ′ too, now: σ is not smoothed, and both slopes share their windows.
        let [fslope, dsigma] = coarse_slopes(&t, [&frequency, &decay], &half);
        // A failed solve invalidates the grid points around it.
        let mut fix_ok = vec![true; g_count];
        for (g, _) in corrected.iter().enumerate().filter(|(_, &c)| !c) {
            let b = (g + 1).min(g_count - 1);
            fix_ok[g.saturating_sub(1)..=b].fill(false);
        }

        let mut valid: Vec<bool> = (0..g_count)
            .into_par_iter()
            .with_min_len(POINT_TASK)
            .map(|g| {
                let i = grid[g].sample;
                let st = half[g];
                let margin = st * (opt.coi + (decay[g] * st).abs()) * fs;
                let inside = i as f64 >= margin && (n - 1 - i) as f64 >= margin;
                // The window spans ±coi σ_t, over which a sweep moves the frequency by β coi σ_t:
                // the model needs all of that inside the analysed band (and clear of DC).
                let reach = sweep[g].abs().max(fslope[g].abs()) * opt.coi * st;
                let in_band = frequency[g] - reach >= fmin && frequency[g] + reach <= fmax;
                // A loose threshold first: the final one is applied after smoothing, so that
                // noise which happens to lift a point over it does not select that point.
                let audible = observed[g] >= 0.5 * opt.min_snr * noise[g];
                peaked[g] && fix_ok[g] && inside && in_band && audible && frequency[g] > 0.0
            })
            .collect();
        if opt.smooth_snr > 0.0 {
            let snr: Vec<f64> = observed
                .par_iter()
                .zip(&noise)
                .with_min_len(POINT_TASK)
                .map(|(o, w)| o / w)
                .collect();
            smooth_low_snr(
                &t,
                &half,
                &snr,
                &mut ln_amp,
                &mut frequency,
                &valid,
                opt.smooth_snr,
            );
        }
        // A at each point, once: the final threshold and every segment's first sample.
        let amp: Vec<f64> = ln_amp
            .par_iter()
            .with_min_len(POINT_TASK)
            .map(|v| v.exp())
            .collect();
        valid
            .par_iter_mut()
            .zip(&amp)
            .zip(&noise)
            .with_min_len(POINT_TASK)
            .for_each(|((v, a), w)| *v = *v && *a >= opt.min_snr * w);
        unwrap_phase(&mut phase, &frequency, |g| t[g]);
        // A'' = A (σ² − σ'), σ' (above) by a local least-squares slope over ±σ_t of the grid.
        let grid_series = GridSeries {
            grid,
            fs,
            ln_amp: &ln_amp,
            amp: &amp,
            phase: &phase,
            decay: &decay,
            frequency: &frequency,
            dsigma: &dsigma,
            sweep: &sweep,
            valid: &valid,
        };
        let mut out = Track {
            method: Method::Wavelet,
            sample_rate: fs,
            amplitude: Vec::new(),
            frequency: Vec::new(),
            phase: Vec::new(),
            d_amplitude: Vec::new(),
            d2_amplitude: Vec::new(),
            d_frequency: Vec::new(),
            valid: Vec::new(),
            offset,
            noise: noise_var.sqrt(),
            band: (fmin, fmax),
            backend,
            scalogram,
        };
        grid_series.per_sample(&mut out, n, FILL_CHUNK);
        out
    }
}

/// Samples filled by one task of the completion's per-sample loop (about; whole segments).
const FILL_CHUNK: usize = 65_536;

/// Grid points one task of the completion's per-point loops takes: a campaign signal's few
/// thousand points stay one task, a 2^20-sample record's 156 000 are spread over the
/// cores. Each point's values are its own, so the result is the same to the bit.
const POINT_TASK: usize = 16_384;

/// The grid estimates' fields that the completion reads, as columns (one value a point).
struct Columns {
    /// Time (s).
    t: Vec<f64>,
    /// σ_t at the refined scale (s).
    half: Vec<f64>,
    /// ln A, bias corrected.
    ln_amp: Vec<f64>,
    /// Phase (rad).
    phase: Vec<f64>,
    /// Decay rate σ (1/s).
    decay: Vec<f64>,
    /// Frequency (Hz).
    frequency: Vec<f64>,
    /// Sweep rate (Hz/s).
    sweep: Vec<f64>,
    /// |W| observed at the ridge, before the bias correction: the SNR's numerator.
    observed: Vec<f64>,
    /// White noise's |W| at the point's scale: the SNR's denominator.
    noise: Vec<f64>,
    /// |W| peaked inside the point's triple of scales.
    peaked: Vec<bool>,
    /// The bias correction succeeded or was not needed.
    corrected: Vec<bool>,
}

impl Columns {
    /// The columns of `est` on `grid`, in one pass over the estimates, in parallel tasks of
    /// [`POINT_TASK`] points: field by field, a 2^20-sample record's 156 000 estimates
    /// (12 MB) were read from memory nine times, one core after the other, a quarter of its
    /// completion. `noise_w` is white noise's |W| at each scale.
    fn of(
        grid: &[GridPoint],
        est: &[GridEstimate],
        fs: f64,
        wl: &Morlet,
        noise_w: &[f64],
    ) -> Columns {
        assert_eq!(est.len(), grid.len(), "one estimate a grid point");
        let count = est.len();
        // Written once each, not zeroed first: a zeroing pass is saved, and on the GPU
        // backend's completion of the long record, zeroed (calloc) blocks were measured
        // with 4 000 more page faults a repetition.
        let mut reals: [Vec<f64>; 9] = std::array::from_fn(|_| Vec::with_capacity(count));
        let mut peaked: Vec<bool> = Vec::with_capacity(count);
        let mut corrected: Vec<bool> = Vec::with_capacity(count);
        {
            let mut chunks = reals
                .each_mut()
                .map(|v| v.spare_capacity_mut()[..count].chunks_mut(POINT_TASK));
            let tasks: Vec<_> = est
                .chunks(POINT_TASK)
                .zip(grid.chunks(POINT_TASK))
                .zip(peaked.spare_capacity_mut()[..count].chunks_mut(POINT_TASK))
                .zip(corrected.spare_capacity_mut()[..count].chunks_mut(POINT_TASK))
                .map(|(((e, g), p), c)| {
                    let columns = chunks
                        .each_mut()
                        .map(|it| it.next().expect("a chunk of every column"));
                    (e, g, p, c, columns)
                })
                .collect();
            tasks
                .into_par_iter()
                .for_each(|(est, grid, peaked, corrected, columns)| {
                    debug_assert!(columns.iter().all(|c| c.len() == est.len()));
                    debug_assert!(peaked.len() == est.len() && corrected.len() == est.len());
                    let [t, half, ln_amp, phase, decay, frequency, sweep, observed, noise] =
                        columns;
                    for (i, (e, p)) in est.iter().zip(grid).enumerate() {
                        t[i].write(p.sample as f64 / fs);
                        half[i].write(wl.time_sigma(e.scale));
                        ln_amp[i].write(e.ln_amp);
                        phase[i].write(e.phase);
                        decay[i].write(e.decay);
                        frequency[i].write(e.frequency);
                        sweep[i].write(e.sweep);
                        // One exp a point, used twice.
                        observed[i].write(e.observed_ln_amp.exp());
                        noise[i].write(noise_w[e.best]);
                        peaked[i].write(e.peaked);
                        corrected[i].write(e.corrected);
                    }
                });
        }
        // SAFETY: the estimates, the grid and every column were cut into the same chunks
        // of the same `count` elements, and each task wrote index i of each of its columns'
        // chunks for every i of its estimates' chunk: all `count` elements of every column.
        unsafe {
            for v in &mut reals {
                v.set_len(count);
            }
            peaked.set_len(count);
            corrected.set_len(count);
        }
        let [t, half, ln_amp, phase, decay, frequency, sweep, observed, noise] = reals;
        Columns {
            t,
            half,
            ln_amp,
            phase,
            decay,
            frequency,
            sweep,
            observed,
            noise,
            peaked,
            corrected,
        }
    }
}

/// A track's six per-sample series of reals (all but `valid`).
fn real_series(t: &mut Track) -> [&mut Vec<f64>; 6] {
    [
        &mut t.amplitude,
        &mut t.frequency,
        &mut t.phase,
        &mut t.d_amplitude,
        &mut t.d2_amplitude,
        &mut t.d_frequency,
    ]
}

/// The track's per-sample outputs over one stretch of samples, not yet written: the
/// completion writes each sample once instead of zeroing it first (a second pass over 49
/// bytes a sample; without it the completion, the GPU backend's largest host share, took
/// 18 % less on a 16-core H200).
struct Rows<'a> {
    amplitude: &'a mut [MaybeUninit<f64>],
    frequency: &'a mut [MaybeUninit<f64>],
    phase: &'a mut [MaybeUninit<f64>],
    d_amplitude: &'a mut [MaybeUninit<f64>],
    d2_amplitude: &'a mut [MaybeUninit<f64>],
    d_frequency: &'a mut [MaybeUninit<f64>],
    valid: &'a mut [MaybeUninit<bool>],
}

impl<'a> Rows<'a> {
    /// Sets every sample of these rows as a track outside its grid: zero, not valid.
    fn clear(self) {
        for o in [
            self.amplitude,
            self.frequency,
            self.phase,
            self.d_amplitude,
            self.d2_amplitude,
            self.d_frequency,
        ] {
            o.fill(MaybeUninit::new(0.0));
        }
        self.valid.fill(MaybeUninit::new(false));
    }

    /// The first `k` samples and the rest.
    fn split_at(self, k: usize) -> (Rows<'a>, Rows<'a>) {
        let (a0, a1) = self.amplitude.split_at_mut(k);
        let (f0, f1) = self.frequency.split_at_mut(k);
        let (p0, p1) = self.phase.split_at_mut(k);
        let (d0, d1) = self.d_amplitude.split_at_mut(k);
        let (e0, e1) = self.d2_amplitude.split_at_mut(k);
        let (g0, g1) = self.d_frequency.split_at_mut(k);
        let (v0, v1) = self.valid.split_at_mut(k);
        (
            Rows {
                amplitude: a0,
                frequency: f0,
                phase: p0,
                d_amplitude: d0,
                d2_amplitude: e0,
                d_frequency: g0,
                valid: v0,
            },
            Rows {
                amplitude: a1,
                frequency: f1,
                phase: p1,
                d_amplitude: d1,
                d2_amplitude: e1,
                d_frequency: g1,
                valid: v1,
            },
        )
    }
}

/// The skeleton's series on the grid, from which every sample is interpolated.
struct GridSeries<'a> {
    grid: &'a [GridPoint],
    fs: f64,
    ln_amp: &'a [f64],
    /// exp(ln A) at each point.
    amp: &'a [f64],
    phase: &'a [f64],
    decay: &'a [f64],
    frequency: &'a [f64],
    dsigma: &'a [f64],
    sweep: &'a [f64],
    valid: &'a [bool],
}

impl GridSeries<'_> {
    /// Sets `out`'s seven per-sample series to `n` samples: from the grid's first point to
    /// its last by [`Self::fill_all`] in tasks of about `chunk` samples, zero and not valid
    /// outside it.
    fn per_sample(&self, out: &mut Track, n: usize, chunk: usize) {
        for v in real_series(out) {
            *v = Vec::with_capacity(n);
        }
        out.valid = Vec::with_capacity(n);
        let rows = Rows {
            amplitude: &mut out.amplitude.spare_capacity_mut()[..n],
            frequency: &mut out.frequency.spare_capacity_mut()[..n],
            phase: &mut out.phase.spare_capacity_mut()[..n],
            d_amplitude: &mut out.d_amplitude.spare_capacity_mut()[..n],
            d2_amplitude: &mut out.d2_amplitude.spare_capacity_mut()[..n],
            d_frequency: &mut out.d_frequency.spare_capacity_mut()[..n],
            valid: &mut out.valid.spare_capacity_mut()[..n],
        };
        // fill_all writes every sample from the first point's to the last point's when the
        // points' samples rise strictly inside the record (each segment runs from its
        // point's sample to the next one's, the last segment its own sample alone). The
        // grid is laid out so; anything else is cleared whole instead, and never left
        // unwritten.
        let grid = self.grid;
        let rising = grid.windows(2).all(|w| w[0].sample < w[1].sample);
        match (grid.first(), grid.last()) {
            (Some(first), Some(last)) if rising && last.sample < n => {
                let (head, rest) = rows.split_at(first.sample);
                let (inside, tail) = rest.split_at(last.sample + 1 - first.sample);
                head.clear();
                tail.clear();
                self.fill_all(inside, chunk);
            }
            _ => rows.clear(),
        }
        // SAFETY: every one of the first n elements of each vector was written above: the
        // head and tail by `clear`, the samples between by `fill_all` (see above), or all of
        // them by `clear`.
        unsafe {
            for v in real_series(out) {
                v.set_len(n);
            }
            out.valid.set_len(n);
        }
    }

    /// Fills every sample from the first grid point's to the last one's (`rows` starts at
    /// the first's), in tasks of whole segments of about `chunk` samples run in parallel
    /// (a long record's loop was the completion's whole serial time). Each sample depends
    /// on its own segment alone, so the result is the same to the last bit whatever the
    /// chunk.
    fn fill_all(&self, mut rows: Rows<'_>, chunk: usize) {
        let grid = self.grid;
        let Some(first) = grid.first() else {
            return;
        };
        let mut tasks = Vec::new();
        let mut base = first.sample;
        let mut g0 = 0;
        while g0 < grid.len() {
            let mut g1 = g0 + 1;
            while g1 < grid.len() && grid[g1].sample - grid[g0].sample < chunk {
                g1 += 1;
            }
            // Segments g0..g1 hold the samples up to the next task's first point (the
            // last segment its own point only).
            let end = grid
                .get(g1)
                .map_or(grid[grid.len() - 1].sample + 1, |p| p.sample);
            let (head, tail) = rows.split_at(end - base);
            tasks.push((g0..g1, head));
            rows = tail;
            base = end;
            g0 = g1;
        }
        tasks
            .into_par_iter()
            .for_each(|(range, rows)| self.fill(range, rows));
    }

    /// Fills the samples of segments `range` (from each grid point to the next), `rows`
    /// starting at the first one's sample: ln A, f, σ, β, σ′ linear between grid points
    /// (they vary over σ_t, the grid is σ_t/8), the phase cubic (Hermite, with 2πf as its
    /// slope at both ends).
    fn fill(&self, range: std::ops::Range<usize>, rows: Rows<'_>) {
        let GridSeries {
            grid,
            fs,
            ln_amp,
            amp: amp_at,
            phase,
            decay,
            frequency,
            dsigma,
            sweep,
            valid,
        } = *self;
        let g_count = grid.len();
        let base = grid[range.start].sample;
        // The grid's spacing changes slowly along a record, so consecutive segments mostly
        // share their length, and with it the position and Hermite weights of every sample.
        let mut basis = Basis::default();
        for g in range {
            let a = grid[g].sample;
            let b = grid.get(g + 1).map_or(a, |p| p.sample);
            let gb = (g + 1).min(g_count - 1);
            let len = (b - a).max(1);
            let span = len as f64;
            let weights = basis.of(len);
            let dt = span / fs;
            let last = if g + 1 == g_count { a } else { b - 1 };
            // Each series' value at g and its rise to gb, for v[g] + u (v[gb] − v[g]).
            let ends = |v: &[f64]| (v[g], v[gb] - v[g]);
            let (sig0, sig_d) = ends(decay);
            let (f0, f_d) = ends(frequency);
            let (ds0, ds_d) = ends(dsigma);
            let (b0, b_d) = ends(sweep);
            let (p0, p1) = (phase[g], phase[gb]);
            let w0 = 2.0 * PI * frequency[g] * dt;
            let w1 = 2.0 * PI * frequency[gb] * dt;
            let both = valid[g] && valid[gb];
            // ln A is linear over the segment, so A is geometric: one exp per segment, not
            // per sample (the product drifts by ~1e-14 over a segment).
            let geometric = ln_amp[g].is_finite() && ln_amp[gb].is_finite();
            let ratio = segment_ratio((ln_amp[gb] - ln_amp[g]) / span);
            let mut next_amp = amp_at[g];
            // The segment's samples as slices: no bounds check per sample.
            let r = a - base..last + 1 - base;
            let samples = rows.amplitude[r.clone()]
                .iter_mut()
                .zip(&mut rows.frequency[r.clone()])
                .zip(&mut rows.phase[r.clone()])
                .zip(&mut rows.d_amplitude[r.clone()])
                .zip(&mut rows.d2_amplitude[r.clone()])
                .zip(&mut rows.d_frequency[r.clone()])
                .zip(&mut rows.valid[r])
                .zip(weights);
            for (((((((o_amp, o_f), o_ph), o_da), o_d2a), o_df), o_valid), w) in samples {
                let u = w.u;
                let amp = if geometric {
                    let amp = next_amp;
                    next_amp *= ratio;
                    amp
                } else if u < 0.5 {
                    amp_at[g]
                } else {
                    amp_at[gb]
                };
                let sig = sig0 + u * sig_d;
                let [h00, h10, h01, h11] = w.hermite;
                o_amp.write(amp);
                o_f.write(f0 + u * f_d);
                o_ph.write(h00 * p0 + h10 * w0 + h01 * p1 + h11 * w1);
                o_da.write(-sig * amp);
                o_d2a.write(amp * (sig * sig - (ds0 + u * ds_d)));
                o_df.write(b0 + u * b_d);
                o_valid.write(both);
            }
        }
    }
}

/// e^x, the amplitude's ratio from one sample to the next over a segment where ln A rises
/// by x a sample: by its Taylor series where |x| ≤ [`SMALL_STEP`] (a sample's step in ln A
/// is a few thousandths on a campaign's records: 94 % of its segments), `exp` elsewhere.
/// The call, one a segment, cost 5–10 µs of a campaign record's 240 µs completion; the
/// series is within an ulp of `exp` (the terms left out are under 4e-19 of the value).
#[inline]
fn segment_ratio(x: f64) -> f64 {
    if x.abs() <= SMALL_STEP {
        const C: [f64; 7] = [
            1.0,
            1.0,
            1.0 / 2.0,
            1.0 / 6.0,
            1.0 / 24.0,
            1.0 / 120.0,
            1.0 / 720.0,
        ];
        let tail = C[3] + x * (C[4] + x * (C[5] + x * C[6]));
        C[0] + x * (C[1] + x * (C[2] + x * tail))
    } else {
        x.exp()
    }
}

/// Largest |x| for which [`segment_ratio`] sums its series: x^7/7! is then below 4e-19.
const SMALL_STEP: f64 = 1.0 / 128.0;

/// Where a sample lies in its segment, u = k / span, and the cubic Hermite weights of the
/// phase's two ends and two slopes there.
#[derive(Clone, Copy)]
struct SampleWeights {
    u: f64,
    hermite: [f64; 4],
}

impl SampleWeights {
    /// The weights of sample `k` of a segment of `span` samples.
    fn at(k: usize, span: usize) -> SampleWeights {
        let u = k as f64 / span as f64;
        let (u2, u3) = (u * u, u * u * u);
        SampleWeights {
            u,
            hermite: [
                2.0 * u3 - 3.0 * u2 + 1.0,
                u3 - 2.0 * u2 + u,
                3.0 * u2 - 2.0 * u3,
                u3 - u2,
            ],
        }
    }
}

/// Every sample's [`SampleWeights`] for the last segment length asked: a sample's division
/// and cubic were a third of the per-sample fill, and a record's segments mostly share their
/// length (the same values, so the same bits).
#[derive(Default)]
struct Basis {
    span: usize,
    weights: Vec<SampleWeights>,
}

impl Basis {
    /// The weights of the samples 0..`span` of a segment `span` samples long.
    fn of(&mut self, span: usize) -> &[SampleWeights] {
        if span != self.span {
            self.span = span;
            self.weights.clear();
            self.weights
                .extend((0..span).map(|k| SampleWeights::at(k, span)));
        }
        &self.weights
    }
}

/// Slopes of both `ys` at every coarse time `t` (sorted) by least-squares lines over ±`half` (0 where
/// too few points fall in the window): `filter::local_slope` of each within 1e-10 of the
/// slope (4e-11 in the test), with each window's sums slid from the previous point's.
fn coarse_slopes(t: &[f64], ys: [&[f64]; 2], half: &[f64]) -> [Vec<f64>; 2] {
    let mut pairs = vec![(0.0, 0.0); t.len()];
    // Whether every value is finite, asked once: each chunk asked it of its windows' whole
    // reach, which for wide windows (a low frequency's σ_t spans thousands of points) is
    // most of the record, a tenth of the completion of the bench's log sweep.
    let all_finite = [t, ys[0], ys[1]].iter().all(|v| every_finite(v));
    // Chunks in parallel; within one, each window's bounds are walked from the previous
    // point's (windows move little between neighbours) and its sums slid with them: a
    // window of some twenty points summed afresh at every point was a fifth of the
    // completion, its additions waiting on each other.
    pairs
        .par_chunks_mut(SLOPE_CHUNK)
        .enumerate()
        .for_each(|(chunk, out)| slide_chunk(t, ys, half, chunk * SLOPE_CHUNK, all_finite, out));
    [
        pairs.iter().map(|p| p.0).collect(),
        pairs.iter().map(|p| p.1).collect(),
    ]
}

/// Grid points whose slopes one task of [`coarse_slopes`] finds.
const SLOPE_CHUNK: usize = 512;

/// Whether every value of `v` is finite (neither infinite nor NaN), without stopping at the
/// first that is not (so that the loop is vectorised).
fn every_finite(v: &[f64]) -> bool {
    v.iter().fold(true, |ok, x| ok & x.is_finite())
}

/// [`coarse_slopes`] at the points `first..first + out.len()`; `all_finite` says that every
/// value of `t` and `ys` is finite (else the chunk looks at its windows' reach).
fn slide_chunk(
    t: &[f64],
    ys: [&[f64]; 2],
    half: &[f64],
    first: usize,
    all_finite: bool,
    out: &mut [(f64, f64)],
) {
    // The windows' bounds, walked (t is sorted): the same partition points as two binary
    // searches would give.
    let mut bounds = Vec::with_capacity(out.len());
    let (mut lo, mut hi) = (0usize, 0usize);
    for j in 0..out.len() {
        let c = first + j;
        let (below, above) = (t[c] - half[c], t[c] + half[c]);
        if j == 0 {
            lo = t.partition_point(|&v| v < below);
            hi = t.partition_point(|&v| v <= above);
        } else {
            while lo > 0 && t[lo - 1] >= below {
                lo -= 1;
            }
            while lo < t.len() && t[lo] < below {
                lo += 1;
            }
            while hi > 0 && t[hi - 1] > above {
                hi -= 1;
            }
            while hi < t.len() && t[hi] <= above {
                hi += 1;
            }
        }
        bounds.push((lo, hi));
    }
    let finite = || {
        let reach_lo = bounds.iter().map(|b| b.0).min().unwrap_or(0);
        let reach_hi = bounds.iter().map(|b| b.1.max(b.0)).max().unwrap_or(0);
        let reach = |v: &[f64]| every_finite(&v[reach_lo..reach_hi]);
        reach(t) && reach(ys[0]) && reach(ys[1])
    };
    if !(all_finite || finite()) {
        // A value that is not finite would spoil every sum slid past it: each window alone.
        for ((lo, hi), (o, c)) in bounds.into_iter().zip(out.iter_mut().zip(first..)) {
            let [a, b] = window_lines(t, ys, lo, hi, t[c]).map(|l| l.map_or(0.0, |l| l.1));
            *o = (a, b);
        }
        return;
    }
    // Sums about an anchor, whose values are subtracted from each term so that the centred
    // moments lose few digits to cancellation; it moves to the window's first point, and the
    // sums start afresh there, every `REANCHOR` points, before the rounding of terms added
    // and taken away has piled up (0.5 s from the anchor and 500 slides, the slopes were
    // 1e-9 off).
    let term = |i: usize, (to, ao, bo): (f64, f64, f64)| (t[i] - to, ys[0][i] - ao, ys[1][i] - bo);
    let (mut lo, mut hi) = (0usize, 0usize);
    let mut sums = SlideSums::default();
    let mut origin = (0.0, 0.0, 0.0);
    for (j, ((wlo, whi), o)) in bounds.into_iter().zip(out.iter_mut()).enumerate() {
        let whi = whi.max(wlo);
        if j % REANCHOR == 0 {
            let at = wlo.min(t.len() - 1);
            origin = (t[at], ys[0][at], ys[1][at]);
            sums = SlideSums::default();
            (lo, hi) = (wlo, wlo);
        }
        // Move the window's ends to wlo..whi, adding or removing one term at a time.
        while hi < whi {
            sums.add(term(hi, origin), 1.0);
            hi += 1;
        }
        while lo > wlo {
            lo -= 1;
            sums.add(term(lo, origin), 1.0);
        }
        while lo < wlo {
            sums.add(term(lo, origin), -1.0);
            lo += 1;
        }
        while hi > whi {
            hi -= 1;
            sums.add(term(hi, origin), -1.0);
        }
        *o = if whi < wlo + 3 {
            (0.0, 0.0)
        } else {
            sums.slopes((whi - wlo) as f64)
        };
    }
}

/// Points between fresh starts of [`slide_chunk`]'s sums.
const REANCHOR: usize = 32;

/// Running sums of a window's terms (t, a, b), their squares and cross products with t.
#[derive(Default)]
struct SlideSums {
    t: f64,
    a: f64,
    b: f64,
    tt: f64,
    ta: f64,
    tb: f64,
}

impl SlideSums {
    /// Adds one term (`sign` 1) or takes it away (`sign` −1).
    fn add(&mut self, (t, a, b): (f64, f64, f64), sign: f64) {
        self.t += sign * t;
        self.a += sign * a;
        self.b += sign * b;
        self.tt += sign * t * t;
        self.ta += sign * t * a;
        self.tb += sign * t * b;
    }

    /// Least-squares slopes of a and b against t over the window's `m` terms (0 without a
    /// spread in time).
    fn slopes(&self, m: f64) -> (f64, f64) {
        let tm = self.t / m;
        let sxx = self.tt - self.t * tm;
        if sxx > 0.0 {
            ((self.ta - tm * self.a) / sxx, (self.tb - tm * self.b) / sxx)
        } else {
            (0.0, 0.0)
        }
    }
}

/// The low-SNR smoothing's window at `u` half-widths from its centre: flat to 0.8, then a
/// raised cosine to 0 at 1 (Tukey's), so that a point entering the window enters with no
/// weight.
fn taper(u: f64) -> f64 {
    const FLAT: f64 = 0.8;
    if u <= FLAT {
        1.0
    } else if u < 1.0 {
        0.5 * (1.0 + (std::f64::consts::PI * (u - FLAT) / (1.0 - FLAT)).cos())
    } else {
        0.0
    }
}

/// The smoothing window's half-width over σ_t (target/x)²: 10 % more than the box window the
/// taper replaced, whose noise it so keeps.
const WIDEN: f64 = 1.1;

/// Longest averaging window, in σ_t either side, that low-SNR smoothing may use.
const MAX_SMOOTH: f64 = 16.0;

/// Where the in-band SNR x is below `target`, replaces ln A and f by a weighted least-squares
/// line over the valid grid points within ±σ_t·min(16, 1.1 (target/x)²), within the point's
/// stretch of valid points (never across an invalid one): noise drops as the
/// window grows, and a decay or a linear sweep (ln A and f linear in time) is not biased by
/// it. The weights are SNR² (the variances of ln Â and f̂ go as 1/SNR²) times the window's
/// [`taper`]. Between target and √2 target the point moves to the line by the fraction
/// 2 − (x/target)². The track is so continuous in the data: a point whose SNR or window
/// changes by a rounding (the GPU's f32 against the CPU's f64) moves by as little, where a
/// box window and a sharp threshold moved it by the noise, 1e-3 on the F-16. On noisy decays
/// and chirps with known truth the noise is the box window's or slightly less.
fn smooth_low_snr(
    t: &[f64],
    sigma_t: &[f64],
    snr: &[f64],
    ln_amp: &mut [f64],
    frequency: &mut [f64],
    valid: &[bool],
    target: f64,
) {
    // A window never reaches past an invalid point, beyond which the ridge may follow
    // another mode: on the beam's acc2 a stretch at 297 Hz ended 1.3 σ_t before one at
    // 80.6 Hz began, and the line through both put the latter's first point at 96.4 Hz.
    // A stretch is a run of valid points with consecutive grid indices, so every window
    // is a slice of the grid's own columns: nothing is gathered, and a record with few
    // low-SNR points (a clean sweep's 156 000 points) costs a scan, on every core.
    let (ln_a, f): (&[f64], &[f64]) = (ln_amp, frequency);
    let smoothed: Vec<(usize, f64, f64)> = (0..t.len())
        .into_par_iter()
        .with_min_len(SMOOTH_TASK)
        // Each task's window weights in one buffer, not one allocation a point.
        .map_init(Vec::new, |wk: &mut Vec<f64>, g| {
            if !valid[g] || snr[g] >= target * std::f64::consts::SQRT_2 {
                return None;
            }
            let half = sigma_t[g] * (WIDEN * (target / snr[g]).powi(2)).min(MAX_SMOOTH);
            let t0 = t[g];
            // The window in time (the grid's times ascend), then cut at the nearest
            // invalid point either side: the same points as a search within the stretch.
            let reach_lo = t.partition_point(|&v| v < t0 - half);
            let reach_hi = t.partition_point(|&v| v <= t0 + half);
            let lo = (reach_lo..g)
                .rev()
                .find(|&i| !valid[i])
                .map_or(reach_lo, |i| i + 1);
            let hi = (g + 1..reach_hi).find(|&i| !valid[i]).unwrap_or(reach_hi);
            if hi < lo + 3 {
                return None;
            }
            // Weights that fall to 0 at the window's ends: a point entering the window as
            // its half-width changes by a rounding enters with no weight. With equal
            // weights one such point moved the line by 1e-3 on the F-16.
            // ln Â and f̂ have variances ∝ 1/SNR²: each point weighs SNR².
            wk.clear();
            wk.extend((lo..hi).map(|i| snr[i].powi(2) * taper((t[i] - t0).abs() / half)));
            let n = hi - lo;
            match (
                window_line(&t[lo..hi], &ln_a[lo..hi], Some(wk), 0, n, t0),
                window_line(&t[lo..hi], &f[lo..hi], Some(wk), 0, n, t0),
            ) {
                (Some((a, _)), Some((b, _))) => {
                    let mix = (2.0 - (snr[g] / target).powi(2)).clamp(0.0, 1.0);
                    Some((g, ln_a[g] + mix * (a - ln_a[g]), f[g] + mix * (b - f[g])))
                }
                _ => None,
            }
        })
        .flatten()
        .collect();
    for (g, a, b) in smoothed {
        ln_amp[g] = a;
        frequency[g] = b;
    }
}

/// Grid points one task of the low-SNR smoothing scans: most points need no window and
/// cost a comparison; the few that do cost up to a few hundred points each.
const SMOOTH_TASK: usize = 2048;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::local_slope;

    /// Every output of one fill of `n` samples by tasks of about `chunk` samples.
    fn filled(series: &GridSeries<'_>, n: usize, chunk: usize) -> Vec<Vec<u64>> {
        // Series left over from elsewhere are replaced whole.
        let stale = vec![9.0; 7];
        let mut o = Track {
            method: Method::Wavelet,
            sample_rate: series.fs,
            amplitude: stale.clone(),
            frequency: stale.clone(),
            phase: stale.clone(),
            d_amplitude: stale.clone(),
            d2_amplitude: stale.clone(),
            d_frequency: stale,
            valid: vec![true; 7],
            offset: 0.0,
            noise: 0.0,
            band: (0.0, 1.0),
            backend: Device::Cpu,
            scalogram: None,
        };
        series.per_sample(&mut o, n, chunk);
        let mut out: Vec<Vec<u64>> = [
            o.amplitude,
            o.frequency,
            o.phase,
            o.d_amplitude,
            o.d2_amplitude,
            o.d_frequency,
        ]
        .iter()
        .map(|s| s.iter().map(|x| x.to_bits()).collect())
        .collect();
        out.push(o.valid.iter().map(|&b| u64::from(b)).collect());
        out
    }

    /// Made-up skeleton series over a grid's points, each a sine about 2: ln A not finite
    /// at one point, and the points `invalid` picks not valid.
    struct MadeSeries {
        ln_amp: Vec<f64>,
        amp: Vec<f64>,
        phase: Vec<f64>,
        decay: Vec<f64>,
        frequency: Vec<f64>,
        dsigma: Vec<f64>,
        sweep: Vec<f64>,
        valid: Vec<bool>,
    }

    impl MadeSeries {
        /// The series of `g` points, ln A −∞ at point `no_amp`.
        fn new(g: usize, no_amp: usize, invalid: impl Fn(usize) -> bool) -> MadeSeries {
            let series =
                |k: f64| -> Vec<f64> { (0..g).map(|j| (k * j as f64).sin() + 2.0).collect() };
            let mut ln_amp = series(0.3);
            ln_amp[no_amp] = f64::NEG_INFINITY;
            MadeSeries {
                amp: ln_amp.iter().map(|v| v.exp()).collect(),
                ln_amp,
                phase: series(0.11),
                decay: series(0.7),
                frequency: series(0.05),
                dsigma: series(1.3),
                sweep: series(0.9),
                valid: (0..g).map(|j| !invalid(j)).collect(),
            }
        }

        /// The series on `grid`, sampled at `fs`.
        fn on<'a>(&'a self, grid: &'a [GridPoint], fs: f64) -> GridSeries<'a> {
            GridSeries {
                grid,
                fs,
                ln_amp: &self.ln_amp,
                amp: &self.amp,
                phase: &self.phase,
                decay: &self.decay,
                frequency: &self.frequency,
                dsigma: &self.dsigma,
                sweep: &self.sweep,
                valid: &self.valid,
            }
        }
    }

    #[test]
    fn samples_filled_in_parallel_tasks_equal_one_task_to_the_last_bit() {
        // An uneven grid starting past sample 0, some points invalid or without amplitude.
        let n = 5000;
        let mut grid = Vec::new();
        let mut i = 3;
        while i < n {
            grid.push(GridPoint {
                sample: i,
                centre: 0,
            });
            i += 1 + (i * 13 % 29);
        }
        let g = grid.len();
        let made = MadeSeries::new(g, 5, |j| j % 7 == 3);
        let (phase, frequency) = (&made.phase, &made.frequency);
        let grid_series = made.on(&grid, 100.0);
        let whole = filled(&grid_series, n, usize::MAX);
        // Samples before the grid and after its last point are zero and not valid, in every
        // series; the last point fills its own sample.
        let last = grid[g - 1].sample;
        for s in &whole {
            assert_eq!(s[..3], [0; 3]);
            assert!(s[last + 1..].iter().all(|&b| b == 0));
        }
        assert_ne!(whole[0][last], 0);
        // At each point's own sample, the frequency and the phase are the point's.
        for (j, p) in grid.iter().enumerate() {
            assert_eq!(whole[1][p.sample], frequency[j].to_bits(), "point {j}");
            assert_eq!(whole[2][p.sample], phase[j].to_bits(), "point {j}");
        }
        for chunk in [1, 2, 17, 100, 999] {
            assert_eq!(filled(&grid_series, n, chunk), whole, "chunks of {chunk}");
        }
        // A grid that does not rise, or reaches past the record, or is empty, leaves a track
        // of zeros, never an unwritten sample.
        let zeros = vec![vec![0u64; n]; 7];
        let mut flat = grid.clone();
        flat[4].sample = flat[3].sample;
        let past = [GridPoint {
            sample: n,
            centre: 0,
        }];
        for odd in [&flat[..], &past[..], &[]] {
            let s = GridSeries {
                grid: odd,
                ..grid_series
            };
            assert_eq!(filled(&s, n, 100), zeros);
        }
    }

    /// The amplitude's ratio a sample against `exp`, within two ulps where it sums its
    /// series (at the bound, inside it and at the smallest steps) and the same bits where
    /// it calls `exp` (beyond the bound, infinities, NaN).
    #[test]
    fn a_segments_ratio_is_exp_of_its_step() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let mut steps = vec![0.0, -0.0, 1e-300, -1e-300, 1e-17, 1e-9, -1e-9];
        for b in [SMALL_STEP, -SMALL_STEP] {
            steps.extend([b, b * (1.0 - f64::EPSILON), b * (1.0 + f64::EPSILON)]);
        }
        steps.extend((0..20_000).map(|_| rng.random_range(-SMALL_STEP..=SMALL_STEP)));
        steps.extend((0..2_000).map(|_| 10f64.powf(rng.random_range(-12.0..-2.1))));
        let ulps = |a: f64, b: f64| (a.to_bits() as i64 - b.to_bits() as i64).abs();
        let mut worst = 0;
        for x in steps {
            let (got, want) = (segment_ratio(x), x.exp());
            worst = worst.max(ulps(got, want));
            assert!(ulps(got, want) <= 2, "step {x:e}: {got:e} against {want:e}");
        }
        eprintln!("the series is at most {worst} ulp(s) from exp");
        for x in [
            0.0079,
            -0.0079,
            0.5,
            -3.0,
            700.0,
            -745.0,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ] {
            assert_eq!(segment_ratio(x).to_bits(), x.exp().to_bits(), "{x}");
        }
        assert!(segment_ratio(f64::NAN).is_nan());
    }

    /// Every output of sample `i` in segment `g` of `s`, evaluated on its own from the
    /// fill's formulas as they read before the weights were shared between segments: the
    /// naive reference of [`GridSeries::fill`].
    fn one_sample(s: &GridSeries<'_>, g: usize, i: usize) -> [u64; 7] {
        let (grid, n) = (s.grid, s.grid.len());
        let a = grid[g].sample;
        let b = grid.get(g + 1).map_or(a, |p| p.sample);
        let gb = (g + 1).min(n - 1);
        let span = (b - a).max(1) as f64;
        let dt = span / s.fs;
        let u = (i - a) as f64 / span;
        let geometric = s.ln_amp[g].is_finite() && s.ln_amp[gb].is_finite();
        let ratio = segment_ratio((s.ln_amp[gb] - s.ln_amp[g]) / span);
        let amp = if geometric {
            (0..i - a).fold(s.amp[g], |x, _| x * ratio)
        } else if u < 0.5 {
            s.amp[g]
        } else {
            s.amp[gb]
        };
        let lerp = |v: &[f64]| v[g] + u * (v[gb] - v[g]);
        let sig = lerp(s.decay);
        let (u2, u3) = (u * u, u * u * u);
        let w0 = 2.0 * PI * s.frequency[g] * dt;
        let w1 = 2.0 * PI * s.frequency[gb] * dt;
        let phase = (2.0 * u3 - 3.0 * u2 + 1.0) * s.phase[g]
            + (u3 - 2.0 * u2 + u) * w0
            + (3.0 * u2 - 2.0 * u3) * s.phase[gb]
            + (u3 - u2) * w1;
        [
            amp.to_bits(),
            lerp(s.frequency).to_bits(),
            phase.to_bits(),
            (-sig * amp).to_bits(),
            (amp * (sig * sig - lerp(s.dsigma))).to_bits(),
            lerp(s.sweep).to_bits(),
            u64::from(s.valid[g] && s.valid[gb]),
        ]
    }

    #[test]
    fn samples_filled_are_each_samples_own_formulas_to_the_last_bit() {
        // Stretches of equal spacing (whose samples share their weights), changes of
        // spacing back and forth, segments of one sample, and a point without amplitude.
        let spacings = [6, 6, 6, 7, 7, 6, 1, 1, 13, 13, 13, 2, 6, 6, 29, 1, 6];
        let mut grid = vec![GridPoint {
            sample: 2,
            centre: 0,
        }];
        for (j, d) in spacings.iter().cycle().take(120).enumerate() {
            let sample = grid[j].sample + d;
            grid.push(GridPoint { sample, centre: 0 });
        }
        let n = grid[grid.len() - 1].sample + 5;
        let g = grid.len();
        let made = MadeSeries::new(g, 40, |j| j % 5 == 2);
        let s = made.on(&grid, 250.0);
        let out = filled(&s, n, usize::MAX);
        let mut checked = 0;
        for j in 0..g {
            let end = grid.get(j + 1).map_or(grid[j].sample + 1, |p| p.sample);
            for i in grid[j].sample..end {
                let got: Vec<u64> = out.iter().map(|series| series[i]).collect();
                assert_eq!(got, one_sample(&s, j, i), "sample {i} of segment {j}");
                checked += 1;
            }
        }
        assert_eq!(checked, grid[g - 1].sample + 1 - grid[0].sample);
        println!("{checked} samples of {g} segments: every output the formulas' own, bit for bit");
    }

    #[test]
    fn coarse_slopes_are_local_slope_of_each_series() {
        // An uneven grid with varying windows, some too narrow for three points.
        // More than one chunk of 512, windows that jump back and forth between neighbours.
        let n = 1300;
        let t: Vec<f64> = (0..n)
            .map(|i| 0.01 * i as f64 + 0.0009 * ((i * 7 % 11) as f64))
            .collect();
        let half: Vec<f64> = (0..n)
            .map(|i| 0.005 + 0.04 * ((i * 5 % 13) as f64))
            .collect();
        let a: Vec<f64> = t.iter().map(|&x| (3.0 * x).sin() + 0.1 * x * x).collect();
        let b: Vec<f64> = t.iter().map(|&x| (x * 1.7).cos() * 5.0).collect();
        assert!(
            t.windows(2).all(|w| w[0] < w[1]),
            "the grid's times are sorted"
        );
        // Far from the origin, as a grid late in a long record is.
        let t: Vec<f64> = t.iter().map(|v| v + 500.0).collect();
        let [sa, sb] = coarse_slopes(&t, [&a, &b], &half);
        let mut zero = 0;
        let close = |s: f64, e: f64| (s - e).abs() <= 1e-10 * (1.0 + e.abs());
        let mut worst: f64 = 0.0;
        for c in 0..n {
            let ea = local_slope(&t, &a, t[c], half[c]).unwrap_or(0.0);
            let eb = local_slope(&t, &b, t[c], half[c]).unwrap_or(0.0);
            for (s, e) in [(sa[c], ea), (sb[c], eb)] {
                worst = worst.max((s - e).abs() / (1.0 + e.abs()));
            }
            assert!(close(sa[c], ea), "point {c}: {} against {ea}", sa[c]);
            assert!(close(sb[c], eb), "point {c}: {} against {eb}", sb[c]);
            assert_eq!(
                sa[c] == 0.0,
                ea == 0.0,
                "point {c}: a window too narrow in both"
            );
            zero += usize::from(ea == 0.0);
        }
        println!("slid slopes against each window's own line: within {worst:.1e} of the slope");
        // A value that is not finite spoils the windows that hold it, and no other.
        let mut bad = a.clone();
        bad[700] = f64::NAN;
        let [sa, _] = coarse_slopes(&t, [&bad, &b], &half);
        for c in 0..n {
            let e = local_slope(&t, &bad, t[c], half[c]).unwrap_or(0.0);
            assert_eq!(sa[c].is_nan(), e.is_nan(), "point {c}");
            assert!(e.is_nan() || close(sa[c], e), "point {c}");
        }
        // Both kinds of window occur.
        assert!(zero > 0 && zero < n / 2, "{zero}");
    }

    /// ln A and f of a smoothing of `n` grid points 1 s apart, σ_t 8 s, around two lines
    /// with deterministic noise of `noise`, all valid at SNR `snr` but point 100's.
    fn smoothed_at_100(n: usize, noise: f64, snr: f64, own: f64) -> (f64, f64) {
        let t: Vec<f64> = (0..n).map(|i| i as f64).collect();
        let wiggle =
            |i: usize, k: f64| noise * ((i as f64 * k).sin() + (i as f64 * 0.37 * k).cos());
        let mut ln_amp: Vec<f64> = (0..n).map(|i| -0.01 * i as f64 + wiggle(i, 1.3)).collect();
        let mut freq: Vec<f64> = (0..n)
            .map(|i| 5.0 + 0.02 * i as f64 + wiggle(i, 0.7))
            .collect();
        let mut x = vec![snr; n];
        x[100] = own;
        smooth_low_snr(
            &t,
            &vec![8.0; n],
            &x,
            &mut ln_amp,
            &mut freq,
            &vec![true; n],
            100.0,
        );
        (ln_amp[100], freq[100])
    }

    #[test]
    fn low_snr_smoothing_is_continuous_in_the_snr_and_the_window() {
        // A relative change of 1e-12 in a point's SNR, across the SNR where smoothing starts
        // (√2 × 100), across 100, and across the SNRs whose windows end exactly at a
        // neighbour (half-width 8 × 1.1 (100/x)² = 10 and 20 s) moves it by as little. A box
        // window or a sharp threshold moved it by the noise there (1e-3 and more).
        let mut worst: f64 = 0.0;
        for x in [
            100.0 * std::f64::consts::SQRT_2,
            100.0,
            100.0 * (1.1_f64 * 8.0 / 10.0).sqrt(),
            100.0 * (1.1_f64 * 8.0 / 20.0).sqrt(),
        ] {
            let (a0, f0) = smoothed_at_100(200, 1e-2, 60.0, x * (1.0 - 1e-12));
            let (a1, f1) = smoothed_at_100(200, 1e-2, 60.0, x * (1.0 + 1e-12));
            worst = worst.max((a1 - a0).abs()).max((f1 - f0).abs());
        }
        println!("largest move for a 1e-12 change in the SNR: {worst:.1e}");
        assert!(worst < 1e-9, "{worst:e}");
    }

    #[test]
    fn low_snr_smoothing_takes_the_noise_off_a_line_and_leaves_the_line() {
        // Against the lines the noise was added to: at SNR 30 the window is ±16 σ_t wide.
        let (a, f) = smoothed_at_100(400, 1e-2, 30.0, 30.0);
        let (a_true, f_true) = (-0.01 * 100.0, 5.0 + 0.02 * 100.0);
        let (a_raw, f_raw) = smoothed_at_100(400, 1e-2, 1e3, 1e3);
        println!(
            "ln A off by {:.1e} (raw {:.1e}), f by {:.1e} (raw {:.1e})",
            a - a_true,
            a_raw - a_true,
            f - f_true,
            f_raw - f_true
        );
        // Above √2 × 100 nothing is smoothed.
        assert_eq!(
            a_raw,
            a_true + 1e-2 * ((100.0f64 * 1.3).sin() + (100.0f64 * 0.37 * 1.3).cos())
        );
        assert!(
            (a - a_true).abs() < 0.2 * (a_raw - a_true).abs(),
            "{a} {a_raw}"
        );
        assert!(
            (f - f_true).abs() < 0.2 * (f_raw - f_true).abs(),
            "{f} {f_raw}"
        );
    }

    #[test]
    fn low_snr_smoothing_stays_within_a_stretch_of_valid_points() {
        // Two ridges on lines, at 297 and 80 Hz, with one invalid grid point between them
        // (as on the beam's acc2 at 2.97 s), all at SNR 30: each point's window (±16 σ_t)
        // reaches the other stretch, and must not take it in. A line fitted through both
        // put the second stretch's first point at 96 Hz.
        let n = 80;
        let t: Vec<f64> = (0..n).map(|i| i as f64).collect();
        let line = |i: usize| {
            if i < 40 {
                297.0 - 0.01 * i as f64
            } else {
                80.0 + 0.02 * i as f64
            }
        };
        let mut freq: Vec<f64> = (0..n).map(line).collect();
        let mut ln_amp: Vec<f64> = (0..n).map(|i| -0.01 * i as f64).collect();
        let mut valid = vec![true; n];
        valid[40] = false;
        smooth_low_snr(
            &t,
            &vec![1.0; n],
            &vec![30.0; n],
            &mut ln_amp,
            &mut freq,
            &valid,
            100.0,
        );
        for i in (0..n).filter(|&i| valid[i]) {
            assert!((freq[i] - line(i)).abs() < 1e-9, "point {i}: {}", freq[i]);
            assert!((ln_amp[i] + 0.01 * i as f64).abs() < 1e-12, "point {i}");
        }
    }

    /// The smoothing as it was written first: the valid points gathered into their own
    /// arrays, each point's stretch listed, each window searched within its stretch.
    fn smoothed_by_gathering(
        t: &[f64],
        sigma_t: &[f64],
        snr: &[f64],
        ln_amp: &mut [f64],
        frequency: &mut [f64],
        valid: &[bool],
        target: f64,
    ) {
        let pts: Vec<usize> = (0..t.len()).filter(|&g| valid[g]).collect();
        let tv: Vec<f64> = pts.iter().map(|&g| t[g]).collect();
        let ln_a: Vec<f64> = pts.iter().map(|&g| ln_amp[g]).collect();
        let f: Vec<f64> = pts.iter().map(|&g| frequency[g]).collect();
        let w: Vec<f64> = pts.iter().map(|&g| snr[g].powi(2)).collect();
        let mut stretch = vec![0..0; pts.len()];
        let mut at = 0;
        for run in pts.chunk_by(|a, b| *b == *a + 1) {
            let range = at..at + run.len();
            stretch[range.clone()].fill(range.clone());
            at = range.end;
        }
        for (c, &g) in pts.iter().enumerate() {
            if snr[g] >= target * std::f64::consts::SQRT_2 {
                continue;
            }
            let half = sigma_t[g] * (WIDEN * (target / snr[g]).powi(2)).min(MAX_SMOOTH);
            let t0 = tv[c];
            let own = stretch[c].clone();
            let lo = own.start + tv[own.clone()].partition_point(|&v| v < t0 - half);
            let hi = own.start + tv[own].partition_point(|&v| v <= t0 + half);
            let wk: Vec<f64> = (lo..hi)
                .map(|i| w[i] * taper((tv[i] - t0).abs() / half))
                .collect();
            let n = hi - lo;
            if let (Some((a, _)), Some((b, _))) = (
                window_line(&tv[lo..hi], &ln_a[lo..hi], Some(&wk), 0, n, t0),
                window_line(&tv[lo..hi], &f[lo..hi], Some(&wk), 0, n, t0),
            ) {
                let mix = (2.0 - (snr[g] / target).powi(2)).clamp(0.0, 1.0);
                ln_amp[g] = ln_a[c] + mix * (a - ln_a[c]);
                frequency[g] = f[c] + mix * (b - f[c]);
            }
        }
    }

    #[test]
    fn low_snr_smoothing_on_the_grid_is_the_gathered_smoothing_to_the_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(23);
        // Several tasks' worth of points, stretches from one point to hundreds, SNRs from
        // far below the target to far above, and windows reaching past the record's ends;
        // the last grid with times repeated in pairs, and NaN and zero SNRs and σ_t.
        for (n, invalid, odd) in [
            (0usize, 0.0, false),
            (2, 0.0, false),
            (5, 0.5, false),
            (3000, 0.002, false),
            (9000, 0.05, false),
            (4000, 0.01, true),
        ] {
            let t: Vec<f64> = (0..n)
                .map(|g| 0.01 * (if odd { g / 2 } else { g }) as f64 + 3.0)
                .collect();
            let mut sigma_t: Vec<f64> = (0..n).map(|g| 0.02 + 1e-5 * g as f64).collect();
            let mut snr: Vec<f64> = (0..n)
                .map(|_| 10f64.powf(rng.random_range(-0.5..2.5)))
                .collect();
            if odd {
                for g in (0..n - 400).step_by(397) {
                    snr[g] = f64::NAN;
                    snr[g + 101] = 0.0;
                    sigma_t[g + 203] = f64::NAN;
                    sigma_t[g + 307] = 0.0;
                }
            }
            let valid: Vec<bool> = (0..n).map(|_| !rng.random_bool(invalid)).collect();
            let ln_amp: Vec<f64> = (0..n)
                .map(|g| -0.3 * t[g] + rng.random_range(-0.1..0.1))
                .collect();
            let freq: Vec<f64> = (0..n)
                .map(|g| 12.0 + 0.5 * t[g] + rng.random_range(-0.2..0.2))
                .collect();
            let (mut a1, mut f1) = (ln_amp.clone(), freq.clone());
            let (mut a2, mut f2) = (ln_amp.clone(), freq.clone());
            smooth_low_snr(&t, &sigma_t, &snr, &mut a1, &mut f1, &valid, 100.0);
            smoothed_by_gathering(&t, &sigma_t, &snr, &mut a2, &mut f2, &valid, 100.0);
            let moved = (0..n).filter(|&g| a1[g] != ln_amp[g]).count();
            assert!(n < 3000 || moved > n / 4, "{moved} of {n} points smoothed");
            for g in 0..n {
                assert_eq!(a1[g].to_bits(), a2[g].to_bits(), "ln A at point {g} of {n}");
                assert_eq!(f1[g].to_bits(), f2[g].to_bits(), "f at point {g} of {n}");
            }
        }
    }

    #[test]
    fn columns_taken_in_parallel_tasks_are_each_estimates_own_fields() {
        // Three whole tasks and a short one; fields that differ from point to point.
        let count = 3 * POINT_TASK + 123;
        let (fs, wl) = (512.0, Morlet::default());
        let noise_w = [0.5, 1.0, 2.0, 4.0];
        let grid: Vec<GridPoint> = (0..count)
            .map(|g| GridPoint {
                sample: 5 * g + 7,
                centre: 1 + g % 5,
            })
            .collect();
        let est: Vec<GridEstimate> = (0..count)
            .map(|g| {
                let x = g as f64;
                GridEstimate {
                    observed_ln_amp: (x * 0.37).sin(),
                    ln_amp: (x * 0.11).cos(),
                    phase: x * 1e-3,
                    decay: -x * 1e-5,
                    frequency: 10.0 + (x * 0.05).sin(),
                    sweep: (x * 0.02).cos(),
                    scale: 0.1 + x * 1e-6,
                    best: g % 4,
                    peaked: g % 3 != 0,
                    corrected: g % 7 != 0,
                }
            })
            .collect();
        let c = Columns::of(&grid, &est, fs, &wl, &noise_w);
        let reals = [
            &c.t,
            &c.half,
            &c.ln_amp,
            &c.phase,
            &c.decay,
            &c.frequency,
            &c.sweep,
            &c.observed,
            &c.noise,
        ];
        for r in reals {
            assert_eq!(r.len(), count);
        }
        assert_eq!((c.peaked.len(), c.corrected.len()), (count, count));
        for (g, (e, p)) in est.iter().zip(&grid).enumerate() {
            let want = [
                p.sample as f64 / fs,
                wl.time_sigma(e.scale),
                e.ln_amp,
                e.phase,
                e.decay,
                e.frequency,
                e.sweep,
                e.observed_ln_amp.exp(),
                noise_w[e.best],
            ];
            for (k, (r, w)) in reals.iter().zip(want).enumerate() {
                assert_eq!(r[g].to_bits(), w.to_bits(), "column {k}, point {g}");
            }
            assert_eq!(
                (c.peaked[g], c.corrected[g]),
                (e.peaked, e.corrected),
                "point {g}"
            );
        }
    }
}
