//! The estimation grid and the CPU's refinement. In: a [`WaveletPrep`] and its ridge; out:
//! the grid (σ_t/8 apart at the ridge's scale, [`GridPoint`]s) and the skeleton at every
//! grid point ([`GridEstimate`]: W, W′, W″ of the scales near the ridge by the exact pass
//! band, the three-scale estimate, the bias correction) — on the CPU here, on a GPU in
//! `gpu::refine`.

use num_complex::Complex64;
use rayon::prelude::*;

use crate::skeleton::{self, GridEstimate, GridPoint, ScaleValue};
use crate::transform::band::{ScalePlan, Taps};
use crate::transform::{Morlet, Spectrum};

use super::{WaveletPrep, GRID_DIVISION, PASS2_OVERSAMPLE};

/// Scale values W, W', W'' kept around the ridge for one scale and one stretch of time.
struct Segment {
    /// First decimated index held (may be negative: periodic).
    first: isize,
    w: Vec<Complex64>,
    d1: Vec<Complex64>,
    d2: Vec<Complex64>,
    /// Samples (inclusive range) this segment serves.
    samples: (usize, usize),
}

/// Everything kept for one scale after the second pass.
struct ScaleData {
    plan: ScalePlan,
    step: f64,
    segments: Vec<Segment>,
}

impl ScaleData {
    fn segment(&self, n: usize) -> Option<&Segment> {
        let i = self.segments.partition_point(|s| s.samples.1 < n);
        self.segments.get(i).filter(|s| s.samples.0 <= n)
    }

    fn value(&self, spec: &Spectrum, n: usize) -> Option<ScaleValue> {
        let seg = self.segment(n)?;
        let x = n as f64 / self.step - seg.first as f64;
        let taps = Taps::new(seg.w.len(), x);
        let w = taps.apply(&seg.w);
        let w1 = taps.apply(&seg.d1);
        let w2 = taps.apply(&seg.d2);
        let d1 = w1 / w;
        Some(ScaleValue {
            scale: self.plan.scale,
            ln_amp: w.norm().max(1e-300).ln(),
            phase: w.arg() + self.plan.carrier(spec, n as f64),
            d1,
            d2: w2 / w - d1 * d1,
        })
    }
}

impl WaveletPrep {
    /// The ridge's scale index at sample `i`, linear between coarse steps.
    fn ridge_at(&self, path: &[usize], i: usize) -> usize {
        let (h, steps) = (self.h, self.steps);
        let j = i / h;
        let u = (i % h) as f64 / h as f64;
        let a = path[j] as f64;
        let b = path[(j + 1).min(steps - 1)] as f64;
        (a + u * (b - a)).round() as usize
    }

    /// The estimation grid: σ_t/`GRID_DIVISION` apart at the ridge's scale (each point the
    /// next multiple of that spacing), from the first sample to the last. Everything after
    /// it is computed on this grid; the per-sample track is interpolated at the end. Each
    /// point carries the ridge's scale there, kept one scale inside the range so that it
    /// has a neighbour on each side.
    pub fn grid(&self, path: &[usize]) -> Vec<GridPoint> {
        let (n, s_count) = (self.n, self.freqs.len());
        // Each scale's spacing once: per point it had been most of a long record's grid.
        let spacing = self.grid_spacings();
        let mut grid = Vec::with_capacity(n / spacing[s_count - 1] + 2);
        let mut i = 0usize;
        while i < n {
            let k = self.ridge_at(path, i);
            let centre = k.clamp(1, s_count - 2);
            grid.push(GridPoint { sample: i, centre });
            // The next multiple of the spacing, not i + spacing: two ridges that part for a
            // while (a near-tie of two paths, which the GPU's f32 programme and the CPU's f64
            // one can settle differently) then give the same grid again as soon as they
            // meet, instead of grids offset by a sample or two for the rest of the record,
            // whose validity would then switch a few samples apart.
            i = (i / spacing[k] + 1) * spacing[k];
            // Where the ridge holds scale k over the coarse step of the sample before the
            // next point (the next point's own step, unless it opens a step), as it does
            // over most steps, ridge_at is k up to the step's end, and the next point a
            // multiple of k's spacing: the step's points are one spacing apart. The same
            // points without the chain of divisions that was 5 ms of a 2^20-sample record's
            // grid, on the GPU dispatcher's serial path.
            let j = (i - 1) / self.h;
            if i < n && path[j] == k && path[(j + 1).min(self.steps - 1)] == k {
                let stop = ((j + 1) * self.h).min(n);
                while i < stop {
                    grid.push(GridPoint { sample: i, centre });
                    i += spacing[k];
                }
            }
        }
        if grid.last().expect("n ≥ 1").sample != n - 1 {
            let k = self.ridge_at(path, n - 1);
            grid.push(GridPoint {
                sample: n - 1,
                centre: k.clamp(1, s_count - 2),
            });
        }
        grid
    }

    /// Per scale, the grid's spacing (samples) where the ridge is at that scale:
    /// σ_t/`GRID_DIVISION`, at least one sample.
    fn grid_spacings(&self) -> Vec<usize> {
        let wl = self.opt.wavelet;
        self.freqs
            .iter()
            .map(|&f| {
                let st = wl.time_sigma(wl.scale_for(f)) * self.fs;
                ((st / GRID_DIVISION).floor() as usize).max(1)
            })
            .collect()
    }

    /// Per scale, the stretches of samples (inclusive) where `grid` needs its W, W′, W″:
    /// within [`skeleton::REACH`] of the ridge (the scales [`skeleton::estimate_point`] may
    /// read). Empty for a scale the ridge never comes near.
    pub fn wanted(&self, grid: &[GridPoint]) -> Vec<Vec<(usize, usize)>> {
        let s_count = self.freqs.len();
        let mut wanted: Vec<Vec<(usize, usize)>> = vec![Vec::new(); s_count];
        let reach = skeleton::REACH;
        for (g, p) in grid.iter().enumerate() {
            let c = p.centre;
            let (lo, hi) = (c.saturating_sub(reach), (c + reach).min(s_count - 1));
            let prev = g.checked_sub(1).map(|q| grid[q].sample);
            for runs in &mut wanted[lo..=hi] {
                match runs.last_mut() {
                    Some(r) if Some(r.1) == prev => r.1 = p.sample,
                    _ => runs.push((p.sample, p.sample)),
                }
            }
        }
        wanted
    }

    /// The pass-2 plan of scale `k`: the exact pass band (the first pass cut it at 1e-3),
    /// for the W, W′, W″ the skeleton is estimated from.
    pub fn exact_plan(&self, k: usize) -> ScalePlan {
        exact_plan(&self.spec, &self.opt.wavelet, self.plans[k].scale)
    }

    /// The analysis scales (s), one per frequency of [`freqs`](Self::freqs).
    pub fn scales(&self) -> Vec<f64> {
        let wl = self.opt.wavelet;
        self.freqs.iter().map(|&f| wl.scale_for(f)).collect()
    }

    /// Whether the window's bias is removed ([`WaveletOptions::correct`]).
    pub fn corrects(&self) -> bool {
        self.opt.correct
    }

    /// The skeleton at every grid point on the CPU: W, W′, W″ of the scales the ridge comes
    /// near (pass 2), then per point the three-scale estimate and its bias correction
    /// ([`skeleton::estimate_point`]).
    pub fn estimate_grid(&self, grid: &[GridPoint]) -> Vec<GridEstimate> {
        let wl = self.opt.wavelet;
        let s_count = self.freqs.len();
        let spec = &self.spec;
        let data: Vec<ScaleData> = self
            .wanted(grid)
            .into_par_iter()
            .enumerate()
            .map(|(k, runs)| {
                let plan = self.exact_plan(k);
                let step = plan.step(spec);
                if runs.is_empty() {
                    return ScaleData {
                        plan,
                        step,
                        segments: Vec::new(),
                    };
                }
                let [w, d1, d2] = plan.evaluate_with_derivatives(spec, &wl).map(|d| d.values);
                let m = w.len() as isize;
                let take = |v: &[Complex64], a: isize, b: isize| -> Vec<Complex64> {
                    (a..=b).map(|i| v[i.rem_euclid(m) as usize]).collect()
                };
                let segments = runs
                    .iter()
                    .map(|&(s0, s1)| {
                        let a = (s0 as f64 / step).floor() as isize - 2;
                        let b = (s1 as f64 / step).floor() as isize + 3;
                        Segment {
                            first: a,
                            w: take(&w, a, b),
                            d1: take(&d1, a, b),
                            d2: take(&d2, a, b),
                            samples: (s0, s1),
                        }
                    })
                    .collect();
                ScaleData {
                    plan,
                    step,
                    segments,
                }
            })
            .collect();
        let scales = self.scales();
        grid.par_iter()
            .map(|p| {
                skeleton::estimate_point(
                    &wl,
                    &scales,
                    &self.freqs,
                    p.centre,
                    self.opt.correct,
                    |k| {
                        (k < s_count)
                            .then(|| data[k].value(spec, p.sample))
                            .flatten()
                    },
                )
            })
            .collect()
    }
}

/// The pass-2 plan of scale `s` for `spec` ([`WaveletPrep::exact_plan`]); the preparation
/// keeps the bins of every scale's.
pub(super) fn exact_plan(spec: &Spectrum, wavelet: &Morlet, s: f64) -> ScalePlan {
    ScalePlan::new(spec, wavelet, s, PASS2_OVERSAMPLE)
}

#[cfg(test)]
mod tests {
    use super::super::{WaveletOptions, WaveletPrep};

    /// Two ridges that part for a stretch (as the GPU's f32 programme and the CPU's f64 one
    /// can at a near-tie) lay the same grid again from the first point after they meet, and
    /// every grid point is a multiple of the spacing at its ridge's scale.
    #[test]
    fn grids_of_two_ridges_meet_again_where_the_ridges_do() {
        let fs = 1000.0;
        let x: Vec<f64> = (0..30_000)
            .map(|i| {
                let t = i as f64 / fs;
                (2.0 * std::f64::consts::PI * (t + 11.0 / 60.0 * t * t)).sin()
            })
            .collect();
        let prep = WaveletPrep::new(&x, fs, &WaveletOptions::default(), None).unwrap();
        let path = prep.coarse_ridge().path;
        // One scale lower over a fifth of the record, in its middle.
        let (a, b) = (2 * prep.steps / 5, 3 * prep.steps / 5);
        let mut other = path.clone();
        for k in &mut other[a..b] {
            *k = k.saturating_sub(1).max(1);
        }
        let (one, two) = (prep.grid(&path), prep.grid(&other));
        assert_ne!(one, two, "the stretch must change the grid");
        // Past the stretch (its last coarse step and one more, where the ridge is
        // interpolated between the two) and one spacing, the grids are the same points.
        let met = (b + 1) * prep.h;
        let after = |g: &[super::GridPoint]| -> Vec<usize> {
            g.iter()
                .map(|p| p.sample)
                .filter(|&s| s > met + 200)
                .collect()
        };
        assert!(after(&one).len() > 1000);
        assert_eq!(after(&one), after(&two));
        // Each point is the next multiple of the spacing at the ridge's scale of the point
        // before it (the last point is the last sample).
        let spacings = prep.grid_spacings();
        for w in one[..one.len() - 1].windows(2) {
            let spacing = spacings[prep.ridge_at(&path, w[0].sample)];
            assert_eq!(w[1].sample % spacing, 0, "grid point at {}", w[1].sample);
            assert!(w[1].sample - w[0].sample <= spacing);
        }
    }

    /// The grid, which crosses a coarse step where the ridge holds one scale a spacing at a
    /// time, is the point-by-point walk's to the point: on a long record's ridge, on a ridge
    /// that jumps between scales from one coarse step to the next, on one that never moves,
    /// and on one that holds the extreme scales in turn.
    #[test]
    fn the_grid_is_the_point_by_point_walk() {
        let fs = 1000.0;
        let n = 300_000;
        let x: Vec<f64> = (0..n)
            .map(|i| {
                let t = i as f64 / fs;
                (2.0 * std::f64::consts::PI * (20.0 * t + 0.2 * t * t)).sin()
            })
            .collect();
        let prep = WaveletPrep::new(&x, fs, &WaveletOptions::default(), None).unwrap();
        let s_count = prep.freqs.len();
        let spacings = prep.grid_spacings();
        let serial = |path: &[usize]| -> Vec<super::GridPoint> {
            let mut grid = Vec::new();
            let mut i = 0;
            while i < n {
                let k = prep.ridge_at(path, i);
                grid.push(super::GridPoint {
                    sample: i,
                    centre: k.clamp(1, s_count - 2),
                });
                i = (i / spacings[k] + 1) * spacings[k];
            }
            if grid.last().unwrap().sample != n - 1 {
                let k = prep.ridge_at(path, n - 1);
                grid.push(super::GridPoint {
                    sample: n - 1,
                    centre: k.clamp(1, s_count - 2),
                });
            }
            grid
        };
        let ridge = prep.coarse_ridge().path;
        let jumpy: Vec<usize> = (0..prep.steps)
            .map(|j| (j * 7919 + j * j * 31) % s_count)
            .collect();
        let high: Vec<usize> = vec![s_count - 1; prep.steps];
        // Two steps at the lowest scale, two at the highest, and so on: the last points of a
        // step that climbs are a scale or more below the flat step that follows.
        let blocks: Vec<usize> = (0..prep.steps)
            .map(|j| if (j / 2) % 2 == 0 { 0 } else { s_count - 1 })
            .collect();
        for path in [ridge, jumpy, high, blocks] {
            let grid = prep.grid(&path);
            assert!(grid.len() > 1000);
            assert_eq!(grid, serial(&path));
        }
    }
}
