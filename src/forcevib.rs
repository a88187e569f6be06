//! Feldman's ForceVib (and FreeVib): instantaneous natural frequency ω0²(t) and damping
//! h0(t) of the identified channel from the instantaneous characteristics of the input and
//! the response (DESIGN.md, "ForceVib formulas").
//!
//! Every formula works on analytic signals rebuilt from tracks, U = A e^{jφ}, so the Hilbert
//! and the wavelet tracks feed it alike. With F/Y = α + jβ (force input, mass m) or
//! R/Z = α + jβ, R = −Ẍ + C·Y (base motion, z = y − x, m = 1):
//!   ω0² = ω² + α/m − β A'/(A ω m) − A''/A + 2A'²/A² + A'ω'/(A ω)
//!   h0  = β/(2 ω m) − A'/A − ω'/(2 ω)
//! where A, ω are the response's envelope and angular frequency. A free decay is the case
//! F = 0 (FreeVib).

use std::f64::consts::PI;

use num_complex::Complex64;

use crate::track::Track;

/// Instantaneous modal characteristics of the identified channel.
#[derive(Debug, Clone)]
pub struct Modal {
    /// ω0²(t), 1/s² (per unit mass/inertia: k_eq/m).
    pub stiffness: Vec<f64>,
    /// h0(t), 1/s (2 h0 = c_eq/m).
    pub damping: Vec<f64>,
    /// Where both tracks are valid and the result is finite.
    pub valid: Vec<bool>,
}

/// The analytic signal of a track at sample `i` and its first two time derivatives.
fn analytic(t: &Track, i: usize) -> [Complex64; 3] {
    let a = t.amplitude[i];
    let w = 2.0 * PI * t.frequency[i];
    let dw = 2.0 * PI * t.d_frequency[i];
    let (da, d2a) = (t.d_amplitude[i], t.d2_amplitude[i]);
    let u = Complex64::from_polar(a, t.phase[i]);
    // U = A e^{jφ}: U' = (A' + jAω) e^{jφ}, U'' = (A'' − Aω² + j(2A'ω + Aω')) e^{jφ}.
    let e = Complex64::from_polar(1.0, t.phase[i]);
    [
        u,
        Complex64::new(da, a * w) * e,
        Complex64::new(d2a - a * w * w, 2.0 * da * w + a * dw) * e,
    ]
}

/// ω0² and h0 from the complex ratio q = α + jβ (already divided by the mass) and the
/// response track at sample `i`.
fn formulas(q: Complex64, resp: &Track, i: usize) -> (f64, f64) {
    let a = resp.amplitude[i];
    let w = 2.0 * PI * resp.frequency[i];
    let dw = 2.0 * PI * resp.d_frequency[i];
    let r1 = resp.d_amplitude[i] / a;
    let r2 = resp.d2_amplitude[i] / a;
    let w0 = w * w + q.re - q.im * r1 / w - r2 + 2.0 * r1 * r1 + r1 * dw / w;
    let h0 = q.im / (2.0 * w) - r1 - dw / (2.0 * w);
    (w0, h0)
}

fn assemble(n: usize, f: impl Fn(usize) -> Option<(f64, f64)>) -> Modal {
    let mut out = Modal {
        stiffness: vec![f64::NAN; n],
        damping: vec![f64::NAN; n],
        valid: vec![false; n],
    };
    for i in 0..n {
        if let Some((w0, h0)) = f(i) {
            if w0.is_finite() && h0.is_finite() {
                out.stiffness[i] = w0;
                out.damping[i] = h0;
                out.valid[i] = true;
            }
        }
    }
    out
}

fn usable(t: &Track, i: usize) -> bool {
    t.valid[i] && t.amplitude[i] > 0.0 && t.frequency[i] > 0.0
}

/// Force input: `force` and the response displacement `resp`, mass (or inertia) `mass`.
pub fn force_input(force: &Track, resp: &Track, mass: f64) -> Modal {
    assemble(resp.amplitude.len(), |i| {
        (usable(force, i) && usable(resp, i)).then(|| {
            let q = analytic(force, i)[0] / analytic(resp, i)[0] / mass;
            formulas(q, resp, i)
        })
    })
}

/// Base motion: `input` the base displacement x, `rel` the relative motion z = y − x,
/// `gravity_stiffness` C (1/s²).
pub fn base_motion(input: &Track, rel: &Track, gravity_stiffness: f64) -> Modal {
    assemble(rel.amplitude.len(), |i| {
        (usable(input, i) && usable(rel, i)).then(|| {
            let [x, _, x2] = analytic(input, i);
            let z = analytic(rel, i)[0];
            let r = -x2 + gravity_stiffness * (x + z);
            formulas(r / z, rel, i)
        })
    })
}

/// Free decay (FreeVib): no input.
pub fn free_decay(resp: &Track) -> Modal {
    assemble(resp.amplitude.len(), |i| {
        usable(resp, i).then(|| formulas(Complex64::new(0.0, 0.0), resp, i))
    })
}

/// Modal mass (kg, or inertia) of a force-input run from the data, for a record without
/// the `inertia` attribute: along a sweep, ω0² = ω² + c(t) + a(t)/m with a = α − β A'/(Aω)
/// and c the mass-free terms; m is the value that makes ω0² most nearly constant over the
/// valid samples (the least-squares slope of ω² + c against a). Exact for a linear
/// oscillator; for a non-linear one it is the mass of its best linear fit.
pub fn estimate_mass(force: &Track, resp: &Track) -> Option<f64> {
    // With m = 1 the formula gives (ω² + c) + a; a is the mass term, so ω² + c = ω0²|ₘ₌₁ − a.
    let pts: Vec<(f64, f64)> = (0..resp.amplitude.len())
        .filter(|&i| usable(force, i) && usable(resp, i))
        .filter_map(|i| {
            let q = analytic(force, i)[0] / analytic(resp, i)[0];
            let w = 2.0 * PI * resp.frequency[i];
            let r1 = resp.d_amplitude[i] / resp.amplitude[i];
            let a = q.re - q.im * r1 / w;
            let (w0, _) = formulas(q, resp, i);
            (w0.is_finite() && a.is_finite()).then_some((a, w0 - a))
        })
        .collect();
    if pts.len() < 10 {
        return None;
    }
    let n = pts.len() as f64;
    let (ma, mb) = pts
        .iter()
        .fold((0.0, 0.0), |(x, y), p| (x + p.0 / n, y + p.1 / n));
    let (mut sab, mut saa) = (0.0, 0.0);
    for (a, b) in &pts {
        sab += (a - ma) * (b - mb);
        saa += (a - ma) * (a - ma);
    }
    // ω² + c = K − a/m: the slope is −1/m.
    let slope = sab / saa;
    (slope < 0.0 && slope.is_finite()).then(|| -1.0 / slope)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::track::{Method, Track};

    /// An exact track of A e^{σt} cos(2π(f0 t + ½ b t²)).
    fn exact(n: usize, fs: f64, a0: f64, sigma: f64, f0: f64, b: f64, phase0: f64) -> Track {
        let t: Vec<f64> = (0..n).map(|i| i as f64 / fs).collect();
        let amp: Vec<f64> = t.iter().map(|t| a0 * (sigma * t).exp()).collect();
        Track {
            method: Method::Hilbert,
            sample_rate: fs,
            frequency: t.iter().map(|t| f0 + b * t).collect(),
            phase: t
                .iter()
                .map(|t| phase0 + 2.0 * PI * (f0 * t + 0.5 * b * t * t))
                .collect(),
            d_amplitude: amp.iter().map(|a| sigma * a).collect(),
            d2_amplitude: amp.iter().map(|a| sigma * sigma * a).collect(),
            d_frequency: vec![b; n],
            valid: vec![true; n],
            amplitude: amp,
            offset: 0.0,
            noise: 0.0,
            band: (0.0, fs / 2.0),
            backend: crate::track::Device::Cpu,
            scalogram: None,
        }
    }

    #[test]
    fn free_decay_of_a_linear_oscillator_is_exact() {
        // y = e^{−hω_n t} cos(ω_d t): ω0² = ω_d² + h²ω_n² = ω_n², h0 = hω_n.
        let (wn, zeta): (f64, f64) = (2.0 * PI * 5.0, 0.03);
        let wd = wn * (1.0 - zeta * zeta).sqrt();
        let tr = exact(500, 1000.0, 1.0, -zeta * wn, wd / (2.0 * PI), 0.0, 0.3);
        let m = free_decay(&tr);
        for i in 0..500 {
            assert!((m.stiffness[i] - wn * wn).abs() < 1e-9 * wn * wn);
            assert!((m.damping[i] - zeta * wn).abs() < 1e-12);
        }
    }

    #[test]
    fn forced_steady_state_gives_the_oscillator_back() {
        // m y'' + c y' + k y = F cos(ωt): Y = F/(k − mω² + jcω).
        let (m, c, k, w) = (2.0, 3.0, 5000.0, 40.0);
        let h = Complex64::new(1.0, 0.0) / Complex64::new(k - m * w * w, c * w);
        let f = exact(100, 1000.0, 10.0, 0.0, w / (2.0 * PI), 0.0, 0.0);
        let y = exact(
            100,
            1000.0,
            10.0 * h.norm(),
            0.0,
            w / (2.0 * PI),
            0.0,
            h.arg(),
        );
        let r = force_input(&f, &y, m);
        assert!((r.stiffness[50] - k / m).abs() < 1e-9 * k / m);
        assert!((r.damping[50] - c / (2.0 * m)).abs() < 1e-12);
    }

    #[test]
    fn base_motion_recovers_the_relative_oscillator() {
        // z'' + 2h z' + ω0² z = −x'' + C y, x = X cos ωt, z = Z cos(ωt + ψ).
        let (w0sq, h, cg, w) = (4000.0, 1.5, 3.0, 50.0);
        let x = Complex64::new(0.01, 0.0);
        // (ω0² − ω² + 2jhω) Z = ω² X + C (X + Z)
        let z = (w * w + cg) * x / Complex64::new(w0sq - w * w - cg, 2.0 * h * w);
        let f = w / (2.0 * PI);
        let xt = exact(100, 1000.0, x.norm(), 0.0, f, 0.0, 0.0);
        let zt = exact(100, 1000.0, z.norm(), 0.0, f, 0.0, z.arg());
        let r = base_motion(&xt, &zt, cg);
        assert!((r.stiffness[50] - w0sq).abs() < 1e-9 * w0sq);
        assert!((r.damping[50] - h).abs() < 1e-12);
    }
}
