//! The analytic signal z = y + j H[y] by FFT, with its time derivatives taken spectrally.
//!
//! The record's mean is removed first (a DC offset has no phase and would bias the envelope
//! by the offset itself); it is returned so that callers can report it.

use std::f64::consts::PI;

use num_complex::Complex64;

use super::complex_plan;

/// The analytic signal of a record and its first two time derivatives.
#[derive(Debug, Clone)]
pub struct Analytic {
    /// z(t) = A e^{jφ}.
    pub z: Vec<Complex64>,
    /// dz/dt (1/s).
    pub dz: Vec<Complex64>,
    /// d²z/dt² (1/s²).
    pub d2z: Vec<Complex64>,
    /// Mean removed from the record.
    pub mean: f64,
}

/// Analytic signal of `x` sampled at `fs` Hz (negative frequencies zeroed, positive doubled,
/// DC removed, the Nyquist bin of an even-length record kept once).
pub fn analytic(x: &[f64], fs: f64) -> Analytic {
    let n = x.len();
    let mean = x.iter().sum::<f64>() / n.max(1) as f64;
    let mut spec: Vec<Complex64> = x.iter().map(|v| Complex64::new(v - mean, 0.0)).collect();
    complex_plan(n, false).process(&mut spec);
    let half = n / 2;
    let mut weights = vec![0.0; n];
    for (k, w) in weights.iter_mut().enumerate().take(half + 1).skip(1) {
        *w = if n.is_multiple_of(2) && k == half {
            1.0
        } else {
            2.0
        };
    }
    let inverse = complex_plan(n, true);
    let norm = 1.0 / n as f64;
    let make = |order: i32| {
        let mut buf: Vec<Complex64> = spec
            .iter()
            .zip(&weights)
            .enumerate()
            .map(|(k, (s, &w))| {
                let jw = Complex64::new(0.0, 2.0 * PI * k as f64 * fs / n as f64);
                s * w * norm * jw.powi(order)
            })
            .collect();
        inverse.process(&mut buf);
        buf
    };
    // The three inverse transforms are independent: side by side, a long record's do not
    // wait for one another (each is the same computation as alone, so the same bits).
    let (z, (dz, d2z)) = rayon::join(|| make(0), || rayon::join(|| make(1), || make(2)));
    Analytic { z, dz, d2z, mean }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn periodic_cosine_gives_exact_envelope_and_frequency() {
        let fs = 100.0;
        let n = 1000;
        let f = 7.0; // integer number of periods in the record
        let x: Vec<f64> = (0..n)
            .map(|i| 0.5 + 2.0 * (2.0 * PI * f * i as f64 / fs + 0.3).cos())
            .collect();
        let a = analytic(&x, fs);
        assert!((a.mean - 0.5).abs() < 1e-12);
        for i in 0..n {
            assert!((a.z[i].norm() - 2.0).abs() < 1e-9);
            let w = (a.dz[i] / a.z[i]).im;
            assert!((w - 2.0 * PI * f).abs() < 1e-8);
        }
    }
}
