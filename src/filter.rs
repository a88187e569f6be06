//! Smoothing shared by the tracking stages: a zero-phase low-pass (the paper's filtering of
//! Hilbert envelopes and frequencies) and local polynomial differentiation.

use std::f64::consts::PI;

/// Zero-phase low-pass: a 2nd-order Butterworth run forwards and backwards (4th-order
/// magnitude, no delay), cut-off `fraction` of the Nyquist frequency (0 < fraction < 1).
/// The ends are extended by odd reflection so that a trend continues through them.
pub fn lowpass_zero_phase(x: &[f64], fraction: f64) -> Vec<f64> {
    let [y] = lowpass_zero_phase_all([x], fraction);
    y
}

/// [`lowpass_zero_phase`] of `K` series at once, each to the last bit as alone (series of
/// different lengths are filtered one by one). The filter is a recurrence whose every
/// sample waits on the one before (a few dependent multiply-adds); run side by side, the
/// series' chains overlap in the core. The Hilbert track filters five series: one at a
/// time, that was 3.9 % of a batch's CPU time (`perf`, 200 runs of the throughput campaign
/// on 2 cores); together, the Hilbert stage takes 1.18–1.19 s of CPU there instead of
/// 1.45–1.47 s.
pub fn lowpass_zero_phase_all<const K: usize>(xs: [&[f64]; K], fraction: f64) -> [Vec<f64>; K] {
    let n = xs.first().map_or(0, |x| x.len());
    if n < 3 || !(fraction > 0.0 && fraction < 1.0) {
        return xs.map(<[f64]>::to_vec);
    }
    if xs.iter().any(|x| x.len() != n) {
        return xs.map(|x| lowpass_zero_phase(x, fraction));
    }
    let (b, a) = butterworth(fraction);
    let pad = reflection(fraction, n);
    let len = n + 2 * pad;
    // Sample-major: the K series' values of one sample side by side.
    let mut ext = vec![[0.0; K]; len];
    for (j, x) in xs.iter().enumerate() {
        for (e, i) in ext.iter_mut().zip((1..=pad).rev()) {
            e[j] = 2.0 * x[0] - x[i];
        }
        for (e, &v) in ext[pad..pad + n].iter_mut().zip(x.iter()) {
            e[j] = v;
        }
        for (e, i) in ext[pad + n..].iter_mut().zip(1..=pad) {
            e[j] = 2.0 * x[n - 1] - x[n - 1 - i];
        }
    }
    // Transposed direct form II, forwards then backwards, each pass started in the steady
    // state of a constant input.
    let step = |e: &mut [f64; K], z1: &mut [f64; K], z2: &mut [f64; K]| {
        for j in 0..K {
            let xi = e[j];
            let y = b[0] * xi + z1[j];
            z1[j] = b[1] * xi - a[0] * y + z2[j];
            z2[j] = b[2] * xi - a[1] * y;
            e[j] = y;
        }
    };
    let start = |c: &[f64; K]| (c.map(|c| (1.0 - b[0]) * c), c.map(|c| (b[2] - a[1]) * c));
    let (mut z1, mut z2) = start(&ext[0]);
    for e in ext.iter_mut() {
        step(e, &mut z1, &mut z2);
    }
    let (mut z1, mut z2) = start(&ext[len - 1]);
    for e in ext.iter_mut().rev() {
        step(e, &mut z1, &mut z2);
    }
    std::array::from_fn(|j| ext[pad..pad + n].iter().map(|e| e[j]).collect())
}

/// The 2nd-order Butterworth low-pass at `fraction` of Nyquist: numerator b and
/// denominator a₁, a₂ (a₀ = 1), by the bilinear transform with pre-warping.
fn butterworth(fraction: f64) -> ([f64; 3], [f64; 2]) {
    let k = (PI * fraction / 2.0).tan();
    let q = std::f64::consts::FRAC_1_SQRT_2;
    let norm = 1.0 / (1.0 + k / q + k * k);
    let b0 = k * k * norm;
    (
        [b0, 2.0 * b0, b0],
        [2.0 * (k * k - 1.0) * norm, (1.0 - k / q + k * k) * norm],
    )
}

/// Samples reflected at each end of a record of `n`: the filter's memory is about
/// 1/fraction samples, so three times that, at most the record.
fn reflection(fraction: f64, n: usize) -> usize {
    ((3.0 / fraction).ceil() as usize).min(n - 1)
}

/// Slope of the least-squares line through the points (t_i, y_i) with |t_i − t0| ≤ `half`,
/// i.e. a Savitzky–Golay first derivative on a possibly non-uniform grid; `None` if fewer
/// than three points fall in the window.
pub fn local_slope(t: &[f64], y: &[f64], t0: f64, half: f64) -> Option<f64> {
    local_line(t, y, t0, half).map(|(_, slope)| slope)
}

/// The least-squares line through the points with |t_i − t0| ≤ `half`: (value at t0, slope).
pub fn local_line(t: &[f64], y: &[f64], t0: f64, half: f64) -> Option<(f64, f64)> {
    local_line_weighted(t, y, None, t0, half)
}

/// [`local_line`] with a weight per point (the inverse of its variance), if given.
pub fn local_line_weighted(
    t: &[f64],
    y: &[f64],
    w: Option<&[f64]>,
    t0: f64,
    half: f64,
) -> Option<(f64, f64)> {
    let lo = t.partition_point(|&v| v < t0 - half);
    let hi = t.partition_point(|&v| v <= t0 + half);
    window_line(t, y, w, lo, hi, t0)
}

/// The least-squares line through the points `lo..hi` (sorted `t`), weighted if `w` is
/// given: (value at t0, slope); `None` under three points or with no spread in time. For
/// callers that find the window themselves.
pub fn window_line(
    t: &[f64],
    y: &[f64],
    w: Option<&[f64]>,
    lo: usize,
    hi: usize,
    t0: f64,
) -> Option<(f64, f64)> {
    if hi < lo + 3 {
        return None;
    }
    let weight = |i: usize| w.map_or(1.0, |w| w[i]);
    let m: f64 = (lo..hi).map(weight).sum();
    let tm = (lo..hi).map(|i| weight(i) * t[i]).sum::<f64>() / m;
    let ym = (lo..hi).map(|i| weight(i) * y[i]).sum::<f64>() / m;
    let (mut sxy, mut sxx) = (0.0, 0.0);
    for i in lo..hi {
        let dt = t[i] - tm;
        sxy += weight(i) * dt * (y[i] - ym);
        sxx += weight(i) * dt * dt;
    }
    (sxx > 0.0).then(|| {
        let slope = sxy / sxx;
        (ym + slope * (t0 - tm), slope)
    })
}

/// [`window_line`] unweighted, of two series over the same window at once: the window's
/// own sums (count, mean time, spread) are taken once, each series' the same way as
/// there, so that both lines are [`window_line`]'s to the last bit.
pub fn window_lines(
    t: &[f64],
    ys: [&[f64]; 2],
    lo: usize,
    hi: usize,
    t0: f64,
) -> [Option<(f64, f64)>; 2] {
    if hi < lo + 3 {
        return [None, None];
    }
    // Unweighted, window_line multiplies by a weight of 1.0, which is exact, and a sum of
    // ones is the count. Each sum below is its own chain of additions in window_line's
    // order; the loops only run the independent chains side by side.
    let m = (hi - lo) as f64;
    let (t, ya, yb) = (&t[lo..hi], &ys[0][lo..hi], &ys[1][lo..hi]);
    let (mut st, mut sa, mut sb) = (-0.0, -0.0, -0.0);
    for ((&ti, &ai), &bi) in t.iter().zip(ya).zip(yb) {
        st += ti;
        sa += ai;
        sb += bi;
    }
    let (tm, am, bm) = (st / m, sa / m, sb / m);
    let (mut sxx, mut sxa, mut sxb) = (0.0, 0.0, 0.0);
    for ((&ti, &ai), &bi) in t.iter().zip(ya).zip(yb) {
        let dt = ti - tm;
        sxx += dt * dt;
        sxa += dt * (ai - am);
        sxb += dt * (bi - bm);
    }
    [(am, sxa), (bm, sxb)].map(|(ym, sxy)| {
        (sxx > 0.0).then(|| {
            let slope = sxy / sxx;
            (ym + slope * (t0 - tm), slope)
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_lines_at_once_are_window_lines_to_the_last_bit() {
        let t: Vec<f64> = (0..300)
            .map(|i| 0.37 * i as f64 + 0.01 * ((i * 7 % 5) as f64))
            .collect();
        let a: Vec<f64> = t.iter().map(|&x| (0.3 * x).sin() * 1e3 + x).collect();
        let b: Vec<f64> = t.iter().map(|&x| (-0.01 * x).exp() - 0.5).collect();
        for (lo, hi) in [(0, 0), (0, 2), (5, 8), (0, 300), (17, 61), (100, 299)] {
            let t0 = t[lo.min(299)] + 0.3;
            let both = window_lines(&t, [&a, &b], lo, hi, t0);
            let bits = |l: Option<(f64, f64)>| l.map(|(v, s)| (v.to_bits(), s.to_bits()));
            assert_eq!(bits(both[0]), bits(window_line(&t, &a, None, lo, hi, t0)));
            assert_eq!(bits(both[1]), bits(window_line(&t, &b, None, lo, hi, t0)));
        }
        // A window with no spread in time has no line.
        let flat = vec![2.0; 10];
        assert_eq!(window_lines(&flat, [&a, &b], 0, 10, 2.0), [None, None]);
    }

    #[test]
    fn lowpass_keeps_a_ramp_and_removes_a_fast_tone() {
        let n = 4000;
        let x: Vec<f64> = (0..n)
            .map(|i| 1.0 + 0.001 * i as f64 + 0.3 * (PI * 0.5 * i as f64).sin())
            .collect();
        let y = lowpass_zero_phase(&x, 0.01);
        for (i, v) in y.iter().enumerate().take(n - 300).skip(300) {
            assert!((v - (1.0 + 0.001 * i as f64)).abs() < 2e-3, "{i} {v}");
        }
    }

    /// The zero-phase Butterworth one series at a time, the plain way (the filter as it was
    /// before series were filtered side by side), to check [`lowpass_zero_phase_all`] against.
    fn naive_lowpass(x: &[f64], fraction: f64) -> Vec<f64> {
        let n = x.len();
        if n < 3 || !(fraction > 0.0 && fraction < 1.0) {
            return x.to_vec();
        }
        // The same design and reflection; the ends and the recurrence the plain way.
        let (b, a) = butterworth(fraction);
        let pad = reflection(fraction, n);
        let mut ext = Vec::with_capacity(n + 2 * pad);
        for i in (1..=pad).rev() {
            ext.push(2.0 * x[0] - x[i]);
        }
        ext.extend_from_slice(x);
        for i in 1..=pad {
            ext.push(2.0 * x[n - 1] - x[n - 1 - i]);
        }
        let run = |v: &mut [f64]| {
            let c = v[0];
            let (mut z1, mut z2) = ((1.0 - b[0]) * c, (b[2] - a[1]) * c);
            for s in v.iter_mut() {
                let xi = *s;
                let y = b[0] * xi + z1;
                z1 = b[1] * xi - a[0] * y + z2;
                z2 = b[2] * xi - a[1] * y;
                *s = y;
            }
        };
        run(&mut ext);
        ext.reverse();
        run(&mut ext);
        ext.reverse();
        ext[pad..pad + n].to_vec()
    }

    #[test]
    fn series_filtered_together_equal_each_filtered_alone_to_the_last_bit() {
        let series = |n: usize, k: f64| -> Vec<f64> {
            (0..n)
                .map(|i| (k * i as f64).sin() * (1.0 + 1e-3 * i as f64) + k)
                .collect()
        };
        // Lengths under the filter's memory (the pad is then the record), a long one, and
        // records too short to filter.
        for n in [0, 2, 3, 7, 150, 4001] {
            let xs = [series(n, 0.3), series(n, 0.05), series(n, 1.7)];
            for fraction in [0.004, 0.05, 0.6] {
                let together = lowpass_zero_phase_all([&xs[0], &xs[1], &xs[2]], fraction);
                for (x, t) in xs.iter().zip(&together) {
                    let alone = naive_lowpass(x, fraction);
                    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(t), bits(&alone), "n {n}, fraction {fraction}");
                    assert_eq!(bits(&lowpass_zero_phase(x, fraction)), bits(&alone));
                }
            }
        }
        // Series of different lengths are each filtered alone.
        let (a, b) = (series(50, 0.2), series(60, 0.2));
        let [fa, fb] = lowpass_zero_phase_all([&a, &b], 0.1);
        assert_eq!(fa, naive_lowpass(&a, 0.1));
        assert_eq!(fb, naive_lowpass(&b, 0.1));
    }

    #[test]
    fn local_slope_is_exact_on_a_line() {
        let t: Vec<f64> = (0..50).map(|i| (i as f64).powf(1.3)).collect();
        let y: Vec<f64> = t.iter().map(|v| 3.0 - 0.25 * v).collect();
        let s = local_slope(&t, &y, 40.0, 10.0).unwrap();
        assert!((s + 0.25).abs() < 1e-12);
    }
}
