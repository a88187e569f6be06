//! Ridge search over a scalogram: a penalised dynamic-programming path through the scales,
//! and the three-point parabola that refines a ridge between grid scales.

/// Most-likely ridge through `scores` (time-major, `scales` values per time step, e.g.
/// log|W|): maximises Σ score(k_j, j) − `penalty` Σ (k_j − k_{j−1})². Returns one scale
/// index per step.
///
/// The maximisation over the previous step is a quadratic-cost distance transform, done in
/// O(scales) per step with Felzenszwalb and Huttenlocher's lower envelope of parabolas.
pub fn dp_ridge(scores: &[f32], scales: usize, penalty: f32) -> Vec<usize> {
    assert!(
        scales > 0 && scales <= 1 << 16 && scores.len().is_multiple_of(scales) && penalty > 0.0
    );
    let steps = scores.len() / scales;
    if steps == 0 {
        return Vec::new();
    }
    let lam = f64::from(penalty);
    let mut acc: Vec<f64> = scores[..scales].iter().map(|&v| f64::from(v)).collect();
    let mut next = vec![0f64; scales];
    let mut back = vec![0u16; steps * scales];
    // v: parabola vertices of the lower envelope of −acc(q) + λ(k − q)²; z: their bounds.
    let (mut v, mut z) = (vec![0usize; scales], vec![0f64; scales + 1]);
    // The serial hot loop: reciprocals and f(q) tabulated once rather than per comparison.
    let recip: Vec<f64> = (0..scales)
        .map(|d| 1.0 / (2.0 * lam * d.max(1) as f64))
        .collect();
    let mut f = vec![0f64; scales];
    for j in 1..steps {
        for (q, fq) in f.iter_mut().enumerate() {
            *fq = -acc[q] + lam * (q * q) as f64;
        }
        let mut top = 0usize;
        v[0] = 0;
        z[0] = f64::NEG_INFINITY;
        z[1] = f64::INFINITY;
        for q in 1..scales {
            let mut s;
            loop {
                let p = v[top];
                s = (f[q] - f[p]) * recip[q - p];
                // z[0] = −∞, so the loop ends at the latest with top = 0.
                if s > z[top] {
                    break;
                }
                top -= 1;
            }
            top += 1;
            v[top] = q;
            z[top] = s;
            z[top + 1] = f64::INFINITY;
        }
        let row = &scores[j * scales..(j + 1) * scales];
        let bp = &mut back[j * scales..(j + 1) * scales];
        let mut t = 0usize;
        for k in 0..scales {
            while z[t + 1] < k as f64 {
                t += 1;
            }
            let q = v[t];
            let d = k as f64 - q as f64;
            next[k] = f64::from(row[k]) + acc[q] - lam * d * d;
            bp[k] = q as u16;
        }
        std::mem::swap(&mut acc, &mut next);
    }
    backtrack(&acc, &back, scales)
}

/// Follows the back-pointers from the best final score.
fn backtrack<T: PartialOrd + Copy>(last: &[T], back: &[u16], scales: usize) -> Vec<usize> {
    let steps = back.len() / scales;
    let mut k = (0..last.len())
        .reduce(|a, b| if last[b] > last[a] { b } else { a })
        .unwrap_or(0);
    let mut path = vec![0usize; steps];
    for j in (0..steps).rev() {
        path[j] = k;
        k = back[j * scales + k] as usize;
    }
    path
}

/// The per-step argmax over scales (the usual "ridge" of other tools).
pub fn argmax_ridge(scores: &[f32], scales: usize) -> Vec<usize> {
    scores
        .chunks(scales)
        .map(|row| {
            row.iter()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(b.1))
                .map(|(i, _)| i)
                .unwrap_or(0)
        })
        .collect()
}

/// Vertex of the parabola through three points with distinct abscissae; `None` unless the
/// parabola opens downwards. Returns (x*, y*).
pub fn parabola_peak(x: [f64; 3], y: [f64; 3]) -> Option<(f64, f64)> {
    let (d0, d1) = (x[1] - x[0], x[2] - x[1]);
    let s0 = (y[1] - y[0]) / d0;
    let s1 = (y[2] - y[1]) / d1;
    let curv = (s1 - s0) / (x[2] - x[0]); // the x² coefficient
    if curv.partial_cmp(&0.0) != Some(std::cmp::Ordering::Less) {
        return None;
    }
    // y = y1 + b (x − x1) + curv (x − x1)², with b the slope at x1.
    let b = s0 + curv * d0;
    let dx = -b / (2.0 * curv);
    Some((x[1] + dx, y[1] + b * dx / 2.0))
}

/// Quadratic (Lagrange) interpolation through three points, evaluated at `t`.
#[inline]
pub fn lagrange3<T>(x: [f64; 3], y: [T; 3], t: f64) -> T
where
    T: Copy + std::ops::Mul<f64, Output = T> + std::ops::Add<Output = T>,
{
    let l0 = (t - x[1]) * (t - x[2]) / ((x[0] - x[1]) * (x[0] - x[2]));
    let l1 = (t - x[0]) * (t - x[2]) / ((x[1] - x[0]) * (x[1] - x[2]));
    let l2 = (t - x[0]) * (t - x[1]) / ((x[2] - x[0]) * (x[2] - x[1]));
    y[0] * l0 + y[1] * l1 + y[2] * l2
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The direct O(scales²) programme, as the reference.
    fn direct_dp(scores: &[f32], scales: usize, penalty: f32) -> Vec<usize> {
        let steps = scores.len() / scales;
        let mut acc: Vec<f32> = scores[..scales].to_vec();
        let mut back = vec![0u16; steps * scales];
        for j in 1..steps {
            let prev = acc.clone();
            for k in 0..scales {
                let (arg, best) = (0..scales)
                    .map(|q| (q, prev[q] - penalty * (k.abs_diff(q).pow(2)) as f32))
                    .fold((0, f32::NEG_INFINITY), |a, b| if b.1 > a.1 { b } else { a });
                acc[k] = scores[j * scales + k] + best;
                back[j * scales + k] = arg as u16;
            }
        }
        backtrack(&acc, &back, scales)
    }

    #[test]
    fn parabola_is_exact_for_a_parabola() {
        let f = |x: f64| -3.0 * (x - 0.37).powi(2) + 2.0;
        let x = [0.1, 0.3, 0.8];
        let (xs, ys) = parabola_peak(x, [f(x[0]), f(x[1]), f(x[2])]).unwrap();
        assert!((xs - 0.37).abs() < 1e-12 && (ys - 2.0).abs() < 1e-12);
        assert!(parabola_peak([0.0, 1.0, 2.0], [0.0, 1.0, 2.0]).is_none());
        let g = |x: f64| x * x - x + 1.0;
        let v = lagrange3(x, [g(x[0]), g(x[1]), g(x[2])], 0.55);
        assert!((v - g(0.55)).abs() < 1e-12);
    }

    #[test]
    fn dp_ridge_ignores_a_brief_stronger_distraction() {
        // A ridge at scale 10 with a two-step spike at scale 40 that is stronger: argmax
        // jumps, the penalised path does not.
        let (scales, steps) = (50, 30);
        let mut s = vec![-10f32; scales * steps];
        for j in 0..steps {
            s[j * scales + 10] = 0.0;
            s[j * scales + 9] = -0.5;
            s[j * scales + 11] = -0.5;
        }
        for j in [14, 15] {
            s[j * scales + 40] = 2.0;
        }
        let path = dp_ridge(&s, scales, 0.05);
        assert!(path.iter().all(|&k| k == 10), "{path:?}");
        let naive = argmax_ridge(&s, scales);
        assert_eq!(naive[14], 40);
    }

    #[test]
    fn envelope_dp_equals_the_direct_one() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        for _ in 0..20 {
            let (scales, steps) = (37, 60);
            let s: Vec<f32> = (0..scales * steps)
                .map(|_| rng.random_range(-3.0..3.0))
                .collect();
            let a = direct_dp(&s, scales, 0.07);
            let b = dp_ridge(&s, scales, 0.07);
            let score = |p: &[usize]| {
                (0..steps)
                    .map(|j| {
                        s[j * scales + p[j]]
                            - if j > 0 {
                                0.07 * (p[j].abs_diff(p[j - 1]).pow(2)) as f32
                            } else {
                                0.0
                            }
                    })
                    .sum::<f32>()
            };
            assert!((score(&a) - score(&b)).abs() < 1e-3);
        }
    }

    #[test]
    fn dp_ridge_equals_brute_force_on_small_cases() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for _ in 0..50 {
            let (scales, steps) = (4, 5);
            let s: Vec<f32> = (0..scales * steps)
                .map(|_| rng.random_range(-3.0..3.0))
                .collect();
            let pen = 0.3f32;
            let path = dp_ridge(&s, scales, pen);
            let score = |p: &[usize]| {
                let mut v = 0f32;
                for j in 0..steps {
                    v += s[j * scales + p[j]];
                    if j > 0 {
                        v -= pen * (p[j].abs_diff(p[j - 1]).pow(2)) as f32;
                    }
                }
                v
            };
            let mut best = f32::NEG_INFINITY;
            for code in 0..scales.pow(steps as u32) {
                let mut c = code;
                let p: Vec<usize> = (0..steps)
                    .map(|_| {
                        let k = c % scales;
                        c /= scales;
                        k
                    })
                    .collect();
                best = best.max(score(&p));
            }
            assert!((score(&path) - best).abs() < 1e-4);
        }
    }
}
