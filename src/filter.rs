//! Smoothing shared by the tracking stages: a zero-phase low-pass (the paper's filtering of
//! Hilbert envelopes and frequencies) and local polynomial differentiation.

use std::f64::consts::PI;

/// Zero-phase low-pass: a 2nd-order Butterworth run forwards and backwards (4th-order
/// magnitude, no delay), cut-off `fraction` of the Nyquist frequency (0 < fraction < 1).
/// The ends are extended by odd reflection so that a trend continues through them.
pub fn lowpass_zero_phase(x: &[f64], fraction: f64) -> Vec<f64> {
    let n = x.len();
    if n < 3 || !(fraction > 0.0 && fraction < 1.0) {
        return x.to_vec();
    }
    // Bilinear transform with pre-warping; fraction of Nyquist = ω_c / π.
    let k = (PI * fraction / 2.0).tan();
    let q = std::f64::consts::FRAC_1_SQRT_2;
    let norm = 1.0 / (1.0 + k / q + k * k);
    let b0 = k * k * norm;
    let b = [b0, 2.0 * b0, b0];
    let a = [2.0 * (k * k - 1.0) * norm, (1.0 - k / q + k * k) * norm];
    // The filter's memory is about 1/fraction samples; reflect that much (at most the record).
    let pad = ((3.0 / fraction).ceil() as usize).min(n - 1);
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
        // Transposed direct form II, started in the steady state of a constant input.
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

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn local_slope_is_exact_on_a_line() {
        let t: Vec<f64> = (0..50).map(|i| (i as f64).powf(1.3)).collect();
        let y: Vec<f64> = t.iter().map(|v| 3.0 - 0.25 * v).collect();
        let s = local_slope(&t, &y, 40.0, 10.0).unwrap();
        assert!((s + 0.25).abs() < 1e-12);
    }
}
