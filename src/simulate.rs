//! Rig simulator: integrates the model of FORMATS.md §2 (every effect of the vocabulary)
//! under a chirp, a stepped sine, a free decay or a given measured input, and applies the
//! measurement chain (delay, noise, quantization).
//!
//! Integration is classical RK4 on a fixed sub-step, with **event location**: a step that
//! crosses a clearance corner (|z − offset| = δ) or a zero of the relative velocity is cut
//! at the event (Illinois root finding), so the non-smooth right-hand side is only ever
//! integrated where it is smooth. Coulomb friction is a two-mode machine: in *slip* the
//! friction torque is −F·sign(v) with the sign fixed for the whole mode; in *stick* the
//! link moves with the base and the torque needed to hold it is checked against F.

use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;

use crate::model::RigModel;

const TAU: f64 = std::f64::consts::TAU;

/// A value with its first two time derivatives: the excitations are written once as
/// functions and differentiate themselves exactly.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Jet {
    /// Value.
    pub v: f64,
    /// First derivative.
    pub d1: f64,
    /// Second derivative.
    pub d2: f64,
}

impl Jet {
    /// The independent variable t.
    pub fn time(t: f64) -> Jet {
        Jet {
            v: t,
            d1: 1.0,
            d2: 0.0,
        }
    }
    /// A constant.
    pub fn constant(c: f64) -> Jet {
        Jet {
            v: c,
            d1: 0.0,
            d2: 0.0,
        }
    }
    fn sin(self) -> Jet {
        let (s, c) = self.v.sin_cos();
        Jet {
            v: s,
            d1: c * self.d1,
            d2: c * self.d2 - s * self.d1 * self.d1,
        }
    }
    fn recip(self) -> Jet {
        let r = 1.0 / self.v;
        Jet {
            v: r,
            d1: -self.d1 * r * r,
            d2: (2.0 * self.d1 * self.d1 * r - self.d2) * r * r,
        }
    }
    fn sqrt(self) -> Jet {
        let s = self.v.sqrt();
        Jet {
            v: s,
            d1: 0.5 * self.d1 / s,
            d2: 0.5 * self.d2 / s - 0.25 * self.d1 * self.d1 / (s * s * s),
        }
    }
}

impl std::ops::Add for Jet {
    type Output = Jet;
    fn add(self, o: Jet) -> Jet {
        Jet {
            v: self.v + o.v,
            d1: self.d1 + o.d1,
            d2: self.d2 + o.d2,
        }
    }
}
impl std::ops::Mul for Jet {
    type Output = Jet;
    fn mul(self, o: Jet) -> Jet {
        Jet {
            v: self.v * o.v,
            d1: self.d1 * o.v + self.v * o.d1,
            d2: self.d2 * o.v + 2.0 * self.d1 * o.d1 + self.v * o.d2,
        }
    }
}
impl std::ops::Mul<f64> for Jet {
    type Output = Jet;
    fn mul(self, k: f64) -> Jet {
        Jet {
            v: self.v * k,
            d1: self.d1 * k,
            d2: self.d2 * k,
        }
    }
}

/// Servo roll-off: amplitude gain 1/sqrt(1 + (f/f_r)^(2·order)) of the drive at frequency f.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct Rolloff {
    /// Corner frequency, Hz.
    pub corner_hz: f64,
    /// Butterworth-like order (1 or 2 are typical).
    pub order: u32,
}

impl Rolloff {
    fn gain(&self, f: Jet) -> Jet {
        let u = f * (1.0 / self.corner_hz);
        let mut p = Jet::constant(1.0);
        for _ in 0..self.order {
            p = p * u * u;
        }
        (p + Jet::constant(1.0)).sqrt().recip()
    }
}

/// A drive signal (base angle, or force for the force variant) as a function of time.
#[derive(Debug, Clone)]
pub enum Excitation {
    /// a(f(t))·sin(2π(f0 t + ½ r t²)), r = (f1 − f0)/T; after T it holds f1.
    Chirp {
        /// Start frequency, Hz.
        f0: f64,
        /// End frequency, Hz.
        f1: f64,
        /// Sweep duration, s.
        duration: f64,
        /// Amplitude (rad, m or N).
        amplitude: f64,
        /// Optional servo roll-off of the amplitude with frequency.
        rolloff: Option<Rolloff>,
    },
    /// Phase-continuous sine held `dwell` seconds at each frequency in turn.
    SteppedSine {
        /// Frequencies, Hz.
        freqs: Vec<f64>,
        /// Dwell per step, s.
        dwell: f64,
        /// Amplitude.
        amplitude: f64,
    },
    /// A measured signal, interpolated by cubic Hermite on 4th-order derivative estimates.
    Sampled {
        /// Samples.
        samples: Vec<f64>,
        /// Sample rate, Hz.
        sample_rate: f64,
        /// Derivative estimates at the samples (filled by [`Excitation::sampled`]).
        slopes: Vec<f64>,
    },
    /// Zero for all time.
    Zero,
}

/// Default low-pass of a measured input before it drives a simulation, as a fraction of
/// the Nyquist frequency (`simulate --input-cutoff`, and `gap`).
pub const MEASURED_INPUT_CUTOFF: f64 = 0.1;

impl Excitation {
    /// A measured input signal, used as given; derivatives are estimated once here.
    /// Noisy measurements should go through [`Excitation::measured`] instead.
    pub fn sampled(samples: Vec<f64>, sample_rate: f64) -> Excitation {
        let slopes = derivative_4th(&samples, sample_rate);
        Excitation::Sampled {
            samples,
            sample_rate,
            slopes,
        }
    }

    /// A measured (noisy) input, band-limited to `cutoff_hz` by a zero-phase FFT low-pass
    /// first: encoder noise differentiated twice would otherwise swamp the base
    /// acceleration and make dry friction chatter between stick and slip at every step.
    pub fn measured(samples: &[f64], sample_rate: f64, cutoff_hz: f64) -> Excitation {
        Excitation::sampled(band_limit(samples, sample_rate, cutoff_hz), sample_rate)
    }

    /// Value and derivatives at time t.
    pub fn eval(&self, t: f64) -> Jet {
        match self {
            Excitation::Chirp {
                f0,
                f1,
                duration,
                amplitude,
                rolloff,
            } => {
                let rate = (f1 - f0) / duration;
                let (phase, freq) = if t <= *duration {
                    let tj = Jet::time(t);
                    (
                        (tj * *f0 + tj * tj * (0.5 * rate)) * TAU,
                        tj * rate + Jet::constant(*f0),
                    )
                } else {
                    let p_end = f0 * duration + 0.5 * rate * duration * duration;
                    let dt = Jet::time(t - duration);
                    ((Jet::constant(p_end) + dt * *f1) * TAU, Jet::constant(*f1))
                };
                let gain = match rolloff {
                    Some(r) => r.gain(freq),
                    None => Jet::constant(1.0),
                };
                gain * phase.sin() * *amplitude
            }
            Excitation::SteppedSine {
                freqs,
                dwell,
                amplitude,
            } => {
                if freqs.is_empty() || t < 0.0 {
                    return Jet::constant(0.0);
                }
                let k = ((t / dwell) as usize).min(freqs.len() - 1);
                let base_phase: f64 = freqs[..k].iter().map(|f| f * dwell).sum();
                let tau = Jet::time(t - k as f64 * dwell);
                ((Jet::constant(base_phase) + tau * freqs[k]) * TAU).sin() * *amplitude
            }
            Excitation::Sampled {
                samples,
                sample_rate,
                slopes,
            } => hermite(samples, slopes, *sample_rate, t),
            Excitation::Zero => Jet::constant(0.0),
        }
    }

    /// Value at time t alone, bit for bit [`Excitation::eval`]'s: a force drive needs no
    /// derivatives, and a measured one spent half its interpolation on them.
    pub fn value(&self, t: f64) -> f64 {
        match self {
            Excitation::Sampled {
                samples,
                sample_rate,
                slopes,
            } => hermite_value(samples, slopes, *sample_rate, t),
            _ => self.eval(t).v,
        }
    }
}

/// The interval of a Hermite interpolation at t: its fraction s, 1/fs, and
/// [p0, p1, m0, m1] (the values at its ends and the slopes scaled by 1/fs); `Err` carries
/// the constant a signal of fewer than two samples is taken as.
#[inline(always)]
fn hermite_interval(y: &[f64], dy: &[f64], fs: f64, t: f64) -> Result<(f64, f64, [f64; 4]), f64> {
    let n = y.len();
    match n {
        0 => return Err(0.0),
        1 => return Err(y[0]),
        _ => {}
    }
    let x = (t * fs).clamp(0.0, (n - 1) as f64);
    // x ≥ 0 (or NaN, which both give 0): truncation is floor, without libm's call.
    let i = (x as usize).min(n - 2);
    let s = x - i as f64;
    let h = 1.0 / fs;
    Ok((s, h, [y[i], y[i + 1], dy[i] * h, dy[i + 1] * h]))
}

/// Cubic Hermite value on one interval (fraction s; values p0, p1; scaled slopes m0, m1).
#[inline(always)]
fn hermite_on(s: f64, [p0, p1, m0, m1]: [f64; 4]) -> f64 {
    let s2 = s * s;
    let s3 = s2 * s;
    (2.0 * s3 - 3.0 * s2 + 1.0) * p0
        + (s3 - 2.0 * s2 + s) * m0
        + (-2.0 * s3 + 3.0 * s2) * p1
        + (s3 - s2) * m1
}

/// [`hermite`]'s value alone.
fn hermite_value(y: &[f64], dy: &[f64], fs: f64, t: f64) -> f64 {
    match hermite_interval(y, dy, fs, t) {
        Ok((s, _, p)) => hermite_on(s, p),
        Err(c) => c,
    }
}

/// Cubic Hermite interpolation with its exact first and second derivative.
fn hermite(y: &[f64], dy: &[f64], fs: f64, t: f64) -> Jet {
    let (s, h, p) = match hermite_interval(y, dy, fs, t) {
        Ok(i) => i,
        Err(c) => return Jet::constant(c),
    };
    let v = hermite_on(s, p);
    let [p0, p1, m0, m1] = p;
    let s2 = s * s;
    let d1 = (6.0 * s2 - 6.0 * s) * p0
        + (3.0 * s2 - 4.0 * s + 1.0) * m0
        + (-6.0 * s2 + 6.0 * s) * p1
        + (3.0 * s2 - 2.0 * s) * m1;
    let d2 = (12.0 * s - 6.0) * p0
        + (6.0 * s - 4.0) * m0
        + (-12.0 * s + 6.0) * p1
        + (6.0 * s - 2.0) * m1;
    Jet {
        v,
        d1: d1 / h,
        d2: d2 / (h * h),
    }
}

/// Zero-phase low-pass by FFT with a raised-cosine roll-off from 0.8·fc to fc; the signal
/// is mirrored (even extension) first so that its ends do not ring. (Unlike
/// [`crate::filter::lowpass_zero_phase`], a Butterworth, this one has a finite stop band:
/// nothing above `cutoff_hz` reaches the integrator.)
pub fn band_limit(x: &[f64], fs: f64, cutoff_hz: f64) -> Vec<f64> {
    use crate::transform::complex_plan;
    use rustfft::num_complex::Complex;
    let n = x.len();
    if n < 4 || cutoff_hz <= 0.0 || cutoff_hz >= 0.5 * fs {
        return x.to_vec();
    }
    let m = 2 * n;
    let mut buf: Vec<Complex<f64>> = x
        .iter()
        .chain(x.iter().rev())
        .map(|&v| Complex::new(v, 0.0))
        .collect();
    complex_plan(m, false).process(&mut buf);
    let f_lo = 0.8 * cutoff_hz;
    for (k, c) in buf.iter_mut().enumerate() {
        let f = k.min(m - k) as f64 * fs / m as f64;
        let g = if f <= f_lo {
            1.0
        } else if f >= cutoff_hz {
            0.0
        } else {
            0.5 * (1.0 + (std::f64::consts::PI * (f - f_lo) / (cutoff_hz - f_lo)).cos())
        };
        *c *= g / m as f64;
    }
    complex_plan(m, true).process(&mut buf);
    buf[..n].iter().map(|c| c.re).collect()
}

/// Derivative of uniformly sampled data: 4th-order central differences, one-sided at the ends.
pub fn derivative_4th(y: &[f64], fs: f64) -> Vec<f64> {
    let n = y.len();
    let mut d = vec![0.0; n];
    if n < 5 {
        for (i, di) in d.iter_mut().enumerate() {
            let (a, b) = (i.saturating_sub(1), (i + 1).min(n - 1));
            if b > a {
                *di = (y[b] - y[a]) * fs / (b - a) as f64;
            }
        }
        return d;
    }
    for i in 2..n - 2 {
        d[i] = (y[i - 2] - 8.0 * y[i - 1] + 8.0 * y[i + 1] - y[i + 2]) * fs / 12.0;
    }
    // 4th-order one-sided stencils at the two first and last samples.
    let fwd = |y: &[f64], i: usize| {
        (-25.0 * y[i] + 48.0 * y[i + 1] - 36.0 * y[i + 2] + 16.0 * y[i + 3] - 3.0 * y[i + 4]) / 12.0
    };
    d[0] = fwd(y, 0) * fs;
    d[1] = fwd(y, 1) * fs;
    let rev: Vec<f64> = y[n - 5..].iter().rev().copied().collect();
    d[n - 1] = -fwd(&rev, 0) * fs;
    d[n - 2] = -(-3.0 * rev[0] - 10.0 * rev[1] + 18.0 * rev[2] - 6.0 * rev[3] + rev[4]) / 12.0 * fs;
    d
}

/// How the rig is driven.
#[derive(Debug, Clone)]
pub enum Drive {
    /// Base-motion rig: the excitation is the base angle φ(t) (FORMATS.md §2).
    Base(Excitation),
    /// Force variant m y'' + c y' + k·D(y) = f: the excitation is the force.
    Force(Excitation),
    /// Free decay from an initial offset of the link (base at rest).
    Free {
        /// Initial angle (displacement) of the link, released at rest.
        initial_offset: f64,
    },
    /// Free decay from a state (base at rest): a record's own state after an impact.
    Released {
        /// Initial angle (displacement).
        displacement: f64,
        /// Initial angular velocity (velocity).
        velocity: f64,
    },
}

/// Sampling and integration settings.
#[derive(Debug, Clone)]
pub struct SimSettings {
    /// Output sample rate, Hz.
    pub sample_rate: f64,
    /// Duration, s.
    pub duration: f64,
    /// RK4 sub-steps per output sample.
    pub substeps: usize,
    /// Std of white noise added to the output channel (its units).
    pub output_noise: f64,
    /// Std of white noise added to the input channel.
    pub input_noise: f64,
    /// Noise seed.
    pub seed: u64,
}

impl Default for SimSettings {
    fn default() -> Self {
        SimSettings {
            sample_rate: 1000.0,
            duration: 30.0,
            substeps: 4,
            output_noise: 0.0,
            input_noise: 0.0,
            seed: 1,
        }
    }
}

/// Result of a simulation, sampled at the output rate.
///
/// A simulation that diverges (its state no longer finite) has NaN in `output`,
/// `relative` and `relative_velocity` from the first sample where it is not finite; from
/// there `stuck` repeats its last mode and `events` stops counting.
#[derive(Debug, Clone)]
pub struct SimOutput {
    /// Sample times, s.
    pub time: Vec<f64>,
    /// Measured input channel (base angle or force; zeros for free decay).
    pub input: Vec<f64>,
    /// Measured output channel (absolute link angle / displacement).
    pub output: Vec<f64>,
    /// True (noise-free, undelayed) relative motion z = θ − φ.
    pub relative: Vec<f64>,
    /// True relative velocity.
    pub relative_velocity: Vec<f64>,
    /// 1 where the link is stuck to the base (Coulomb friction), else 0.
    pub stuck: Vec<u8>,
    /// Number of events located (corners, velocity zeros, stick breaks).
    pub events: usize,
}

/// Integration state: link angle and velocity.
#[derive(Debug, Clone, Copy)]
struct State {
    th: f64,
    om: f64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Mode {
    /// Friction torque −F·dir; dir is +1/−1 for the whole mode (0 when F = 0).
    Slip { dir: f64 },
    /// Link stuck to the base at relative offset z.
    Stick { z: f64 },
}

/// The right-hand side of the rig equation, with every effect.
struct Rig<'a> {
    j: f64,
    k: f64,
    c: f64,
    delta: f64,
    gc: f64,
    friction: f64,
    preload: f64,
    offset: f64,
    /// The cubic term (k3 = 0 without one).
    cubic: crate::model::CubicParam,
    c_contact: f64,
    /// The microslip's Jenkins elements: the stiffness of each of the joint's
    /// [`crate::model::IWAN_ELEMENTS`] and of each of its fine population's (which follow
    /// them in `slip`), and every element's slip displacement (empty without microslip).
    jenkins: [f64; 2],
    slip: Vec<f64>,
    /// Each element's slider position on z, moved only after a step is taken: within one
    /// step the element is elastic-perfectly-plastic on its frozen slider, which its force
    /// clamped to ± stiffness × slip is exactly.
    sliders: std::cell::RefCell<Vec<f64>>,
    drive: &'a Drive,
    /// The last two (time, base jet, force) [`Rig::inputs`] computed, newest first.
    inputs_cache: std::cell::Cell<[(f64, Jet, f64); 2]>,
}

impl<'a> Rig<'a> {
    fn new(model: &RigModel, drive: &'a Drive) -> Self {
        let e = &model.effects;
        let get = |k| e.get(k).unwrap_or(0.0);
        use crate::model::EffectKind::*;
        // The Iwan element: slip displacements spread evenly over ((1 − w)u, (1 + w)u] about
        // u = F/kj, so that the elements' slip forces sum to F; its stiffness is part of k.
        // A fine population adds elements whose slips spread evenly over (0, fine_slip].
        let (kj, jenkins, slip) = match e.microslip {
            Some(p) if p.slip_force > 0.0 && p.joint_stiffness > 0.0 => {
                let n = crate::model::IWAN_ELEMENTS;
                let u = p.slip_force / p.joint_stiffness;
                let kj = p.joint_stiffness.min(model.stiffness);
                let mut jenkins = [kj / n as f64, 0.0];
                let mut slip: Vec<f64> = crate::model::iwan_slips(u, p.spread).collect();
                let kf = if p.has_fine() {
                    p.fine_stiffness.min(model.stiffness - kj)
                } else {
                    0.0
                };
                if kf > 0.0 {
                    let m = crate::model::FINE_ELEMENTS;
                    jenkins[1] = kf / m as f64;
                    slip.extend((0..m).map(|i| p.fine_slip * (i + 1) as f64 / m as f64));
                }
                (kj + kf, jenkins, slip)
            }
            _ => (0.0, [0.0; 2], Vec::new()),
        };
        Rig {
            j: model.inertia,
            k: model.stiffness - kj,
            c: model.damping,
            delta: model.half_gap(),
            gc: model.gravity_stiffness,
            friction: get(CoulombFriction),
            preload: get(GravityPreload),
            offset: get(AsymmetricClearance),
            cubic: e.cubic_stiffness.unwrap_or(crate::model::CubicParam {
                k3: 0.0,
                limit: 0.0,
            }),
            c_contact: get(ContactDamping),
            jenkins,
            sliders: std::cell::RefCell::new(vec![0.0; slip.len()]),
            slip,
            drive,
            // NaN never equals a time, so both entries start empty.
            inputs_cache: std::cell::Cell::new([(f64::NAN, Jet::constant(0.0), 0.0); 2]),
        }
    }

    /// The microslip's force on relative displacement z (its sliders as last committed).
    #[inline(always)]
    fn joint(&self, z: f64) -> f64 {
        if self.slip.is_empty() {
            0.0
        } else {
            self.iwan(z)
        }
    }

    /// [`Rig::joint`]'s work, kept out of line so that a rig without microslip (every
    /// base-motion candidate but one) keeps the torque inlined into the integrator.
    #[inline(never)]
    fn iwan(&self, z: f64) -> f64 {
        let sliders = self.sliders.borrow();
        // Each population's stretches summed before its one element stiffness multiplies
        // them: a joint without a fine population gives the same bits as before it existed.
        let stretch = |sliders: &[f64], slip: &[f64]| -> f64 {
            sliders
                .iter()
                .zip(slip)
                .map(|(x, p)| (z - x).clamp(-p, *p))
                .sum()
        };
        let [kj, kf] = self.jenkins;
        // The joint alone over whole vectors, as before the fine population (split at
        // IWAN_ELEMENTS every time, a microslip diagnosis took 2 % longer).
        if self.slip.len() == crate::model::IWAN_ELEMENTS {
            return kj * stretch(&sliders, &self.slip);
        }
        let (joint, fine) = sliders.split_at(crate::model::IWAN_ELEMENTS);
        let (joint_slip, fine_slip) = self.slip.split_at(crate::model::IWAN_ELEMENTS);
        kj * stretch(joint, joint_slip) + kf * stretch(fine, fine_slip)
    }

    /// Moves the microslip's sliders to where relative displacement z has dragged them.
    fn commit(&self, z: f64) {
        // A state that diverged (NaN) would make the clamp's bounds NaN, which panics: the
        // sliders stay where they were, and the record carries the NaN.
        if self.slip.is_empty() || z.is_nan() {
            return;
        }
        for (x, p) in self.sliders.borrow_mut().iter_mut().zip(&self.slip) {
            *x = x.clamp(z - p, z + p);
        }
    }

    /// Base angle and force at t, from the last two times asked when t is one of them.
    /// A slip step asks for the same two or three times six or seven times over (RK4's
    /// midpoint twice, both ends again for the relative motion and the next step), and the
    /// Hermite drive was a third of a diagnosis: the cache keeps results bit-identical.
    #[inline(always)]
    fn inputs(&self, t: f64) -> (Jet, f64) {
        let cache = self.inputs_cache.get();
        for (tc, phi, f) in cache {
            if tc == t {
                return (phi, f);
            }
        }
        let (phi, f) = self.evaluate_inputs(t);
        self.inputs_cache.set([(t, phi, f), cache[0]]);
        (phi, f)
    }

    /// [`Rig::inputs`] without the cache.
    fn evaluate_inputs(&self, t: f64) -> (Jet, f64) {
        match self.drive {
            Drive::Base(e) => (e.eval(t), 0.0),
            Drive::Force(e) => (Jet::constant(0.0), e.value(t)),
            Drive::Free { .. } | Drive::Released { .. } => (Jet::constant(0.0), 0.0),
        }
    }

    /// Signed distance past the clearance flank: > 0 in contact.
    fn corner(&self, z: f64) -> f64 {
        (z - self.offset).abs() - self.delta
    }

    /// All torques on the link except Coulomb friction. Inlined: it is the integrator's
    /// inner loop, and out of line it cost a one-run diagnosis 15 %.
    #[inline(always)]
    fn torque_no_friction(&self, t: f64, s: State) -> f64 {
        let (phi, f_ext) = self.inputs(t);
        let z = s.th - phi.v;
        let v = s.om - phi.d1;
        let zc = z - self.offset;
        let pen = zc.abs() - self.delta;
        let (spring, contact) = if pen > 0.0 {
            let d = pen.copysign(zc);
            (self.k * d + self.cubic.force(d), true)
        } else {
            (0.0, false)
        };
        let mut c = self.c;
        if contact {
            c += self.c_contact;
        }
        -c * v - spring - self.joint(z) + self.j * self.gc * s.th + self.preload + f_ext
    }

    #[inline(always)]
    fn deriv(&self, t: f64, s: State, dir: f64) -> State {
        let torque = self.torque_no_friction(t, s) - self.friction * dir;
        State {
            th: s.om,
            om: torque / self.j,
        }
    }

    fn rk4(&self, t: f64, s: State, h: f64, dir: f64) -> State {
        let add = |a: State, b: State, k: f64| State {
            th: a.th + k * b.th,
            om: a.om + k * b.om,
        };
        let k1 = self.deriv(t, s, dir);
        let k2 = self.deriv(t + 0.5 * h, add(s, k1, 0.5 * h), dir);
        let k3 = self.deriv(t + 0.5 * h, add(s, k2, 0.5 * h), dir);
        let k4 = self.deriv(t + h, add(s, k3, h), dir);
        State {
            th: s.th + h / 6.0 * (k1.th + 2.0 * k2.th + 2.0 * k3.th + k4.th),
            om: s.om + h / 6.0 * (k1.om + 2.0 * k2.om + 2.0 * k3.om + k4.om),
        }
    }

    /// Relative position and velocity.
    fn relative(&self, t: f64, s: State) -> (f64, f64) {
        let (phi, _) = self.inputs(t);
        (s.th - phi.v, s.om - phi.d1)
    }

    /// Friction torque needed to keep the link stuck at relative offset z at time t.
    fn stick_torque(&self, t: f64, z: f64) -> f64 {
        let (phi, _) = self.inputs(t);
        let s = State {
            th: phi.v + z,
            om: phi.d1,
        };
        self.j * phi.d2 - self.torque_no_friction(t, s)
    }

    /// Whether the rig carries a microslip joint (whose sliders move after each step).
    fn has_microslip(&self) -> bool {
        !self.slip.is_empty()
    }

    fn has_friction(&self) -> bool {
        self.friction > 0.0
    }
}

/// Illinois (modified regula falsi) root of g on [0, 1] with g(0)·g(1) < 0.
fn locate(mut g: impl FnMut(f64) -> f64, g0: f64, g1: f64) -> f64 {
    let (mut a, mut b, mut ga, mut gb) = (0.0, 1.0, g0, g1);
    let mut side = 0;
    for _ in 0..60 {
        let x = (a * gb - b * ga) / (gb - ga);
        let gx = g(x);
        if gx == 0.0 || (b - a) < 1e-13 {
            return x;
        }
        if gx.signum() == gb.signum() {
            b = x;
            gb = gx;
            if side == 1 {
                ga *= 0.5;
            }
            side = 1;
        } else {
            a = x;
            ga = gx;
            if side == -1 {
                gb *= 0.5;
            }
            side = -1;
        }
    }
    0.5 * (a + b)
}

/// Integrates the model under a drive and returns the measured channels.
pub fn simulate(model: &RigModel, drive: &Drive, settings: &SimSettings) -> SimOutput {
    let rig = Rig::new(model, drive);
    let n = (settings.duration * settings.sample_rate).round() as usize;
    let dt = 1.0 / settings.sample_rate;
    let sub = settings.substeps.max(1);
    let h = dt / sub as f64;

    let mut s = match drive {
        Drive::Free { initial_offset } => State {
            th: *initial_offset,
            om: 0.0,
        },
        Drive::Released {
            displacement,
            velocity,
        } => State {
            th: *displacement,
            om: *velocity,
        },
        _ => {
            let (phi, _) = rig.inputs(0.0);
            State {
                th: phi.v,
                om: phi.d1,
            }
        }
    };
    let mut mode = initial_mode(&rig, 0.0, s);
    let mut events = 0usize;

    let mut time = Vec::with_capacity(n);
    let mut theta = Vec::with_capacity(n);
    let mut omega = Vec::with_capacity(n);
    let mut input = Vec::with_capacity(n);
    let mut relative = Vec::with_capacity(n);
    let mut relative_velocity = Vec::with_capacity(n);
    let mut stuck = Vec::with_capacity(n);

    let mut t = 0.0;
    // Once the state is not finite it stays so: the rest of the record is NaN without
    // integrating it (the identification refuses such a record, and the search scores the
    // model as unidentified).
    let mut diverged = false;
    for i in 0..n {
        let ti = i as f64 * dt;
        // Advance from t to ti in sub-steps of at most h, cutting at events. Past
        // MAX_EVENTS_PER_SAMPLE events in one sample interval (chattering of dry friction
        // on a rough input), the rest of the interval is integrated without cutting.
        let mut events_here = 0;
        while !diverged && t < ti - 1e-12 * dt {
            let h_now = (ti - t).min(h);
            let cut = events_here < MAX_EVENTS_PER_SAMPLE;
            let (t_new, s_new, mode_new, ev) = step(&rig, t, s, mode, h_now, cut);
            events_here += ev;
            events += ev;
            t = t_new;
            s = s_new;
            mode = mode_new;
            if rig.has_microslip() {
                rig.commit(rig.relative(t, s).0);
            }
        }
        diverged = diverged || !(s.th.is_finite() && s.om.is_finite());
        if diverged {
            s = State {
                th: f64::NAN,
                om: f64::NAN,
            };
        }
        let (phi, f_ext) = rig.inputs(ti);
        let (z, v) = (s.th - phi.v, s.om - phi.d1);
        time.push(ti);
        theta.push(s.th);
        omega.push(s.om);
        input.push(match drive {
            Drive::Base(_) => phi.v,
            Drive::Force(_) => f_ext,
            Drive::Free { .. } | Drive::Released { .. } => 0.0,
        });
        relative.push(z);
        relative_velocity.push(v);
        stuck.push(matches!(mode, Mode::Stick { .. }) as u8);
    }

    // Measurement chain: the output encoder lags, both channels are noisy and quantised.
    let delay = model
        .effects
        .get(crate::model::EffectKind::SensorDelay)
        .unwrap_or(0.0);
    let mut output = if delay > 0.0 {
        delayed(&theta, &omega, settings.sample_rate, delay)
    } else {
        theta.clone()
    };
    let mut input_meas = input;
    let mut rng = StdRng::seed_from_u64(settings.seed);
    add_noise(&mut output, settings.output_noise, &mut rng);
    add_noise(&mut input_meas, settings.input_noise, &mut rng);
    if let Some(q) = model.effects.get(crate::model::EffectKind::Quantization) {
        if !matches!(drive, Drive::Force(_)) {
            quantize(&mut input_meas, q);
        }
        quantize(&mut output, q);
    }

    SimOutput {
        time,
        input: input_meas,
        output,
        relative,
        relative_velocity,
        stuck,
        events,
    }
}

fn initial_mode(rig: &Rig, t: f64, s: State) -> Mode {
    if !rig.has_friction() {
        return Mode::Slip { dir: 0.0 };
    }
    let (z, v) = rig.relative(t, s);
    if v.abs() < 1e-12 {
        let need = rig.stick_torque(t, z);
        if need.abs() <= rig.friction {
            return Mode::Stick { z };
        }
        return Mode::Slip {
            dir: -need.signum(),
        };
    }
    Mode::Slip { dir: v.signum() }
}

/// Most events located within one output sample before the integrator stops cutting steps.
const MAX_EVENTS_PER_SAMPLE: usize = 16;

/// One sub-step from t of length at most h; returns the new time, state, mode and events.
/// With `cut` false, no event is located: the step is taken whole and friction follows the
/// sign of the relative velocity at its end (a regularised fallback against chattering).
fn step(rig: &Rig, t: f64, s: State, mode: Mode, h: f64, cut: bool) -> (f64, State, Mode, usize) {
    if !cut {
        let dir = match mode {
            Mode::Slip { dir } => dir,
            Mode::Stick { .. } => 0.0,
        };
        let s1 = rig.rk4(t, s, h, dir);
        let v1 = rig.relative(t + h, s1).1;
        let dir = if rig.has_friction() { v1.signum() } else { 0.0 };
        return (t + h, s1, Mode::Slip { dir }, 0);
    }
    match mode {
        Mode::Stick { z } => {
            let at = |tt: f64| {
                let (phi, _) = rig.inputs(tt);
                State {
                    th: phi.v + z,
                    om: phi.d1,
                }
            };
            let g = |tt: f64| rig.stick_torque(tt, z).abs() - rig.friction;
            let g0 = g(t);
            let g1 = g(t + h);
            if g1 <= 0.0 {
                return (t + h, at(t + h), mode, 0);
            }
            // The holding torque exceeds F inside the step: break away there.
            let x = if g0 >= 0.0 {
                0.0
            } else {
                locate(|x| g(t + x * h), g0, g1)
            };
            let te = t + x * h;
            let need = rig.stick_torque(te, z);
            (
                te,
                at(te),
                Mode::Slip {
                    dir: -need.signum(),
                },
                1,
            )
        }
        Mode::Slip { dir } => {
            let s1 = rig.rk4(t, s, h, dir);
            let (z0, v0) = rig.relative(t, s);
            let (z1, v1) = rig.relative(t + h, s1);
            let c0 = rig.corner(z0);
            let c1 = rig.corner(z1);
            let corner_hit = c0 != 0.0 && c0.signum() != c1.signum();
            // Velocity reversal against the friction direction ends the slip mode.
            let vel_hit = rig.has_friction() && dir != 0.0 && v1 * dir < 0.0;
            if !corner_hit && !vel_hit {
                return (t + h, s1, mode, 0);
            }
            let mut x_event = 1.0;
            let mut which = 0; // 1 corner, 2 velocity
            if corner_hit {
                let x = locate(
                    |x| {
                        let sx = rig.rk4(t, s, x * h, dir);
                        rig.corner(rig.relative(t + x * h, sx).0)
                    },
                    c0,
                    c1,
                );
                x_event = x;
                which = 1;
            }
            if vel_hit {
                let v0d = v0 * dir;
                let x = if v0d <= 0.0 {
                    0.0
                } else {
                    locate(
                        |x| {
                            let sx = rig.rk4(t, s, x * h, dir);
                            rig.relative(t + x * h, sx).1 * dir
                        },
                        v0d,
                        v1 * dir,
                    )
                };
                if x < x_event {
                    x_event = x;
                    which = 2;
                }
            }
            // Never stall on a zero-length step at a grazing corner.
            let x_event = x_event.max(1e-9);
            let te = t + x_event * h;
            let mut se = rig.rk4(t, s, x_event * h, dir);
            if which == 2 {
                let (phi, _) = rig.inputs(te);
                se.om = phi.d1; // exactly zero relative velocity at the event
                let z = se.th - phi.v;
                let need = rig.stick_torque(te, z);
                let mode = if need.abs() <= rig.friction {
                    Mode::Stick { z }
                } else {
                    Mode::Slip {
                        dir: -need.signum(),
                    }
                };
                return (te, se, mode, 1);
            }
            (te, se, mode, 1)
        }
    }
}

/// θ(t − d) at every sample from the samples of θ and θ' (cubic Hermite).
fn delayed(theta: &[f64], omega: &[f64], fs: f64, d: f64) -> Vec<f64> {
    (0..theta.len())
        .map(|i| {
            let t = i as f64 / fs - d;
            if t <= 0.0 {
                theta[0]
            } else {
                hermite(theta, omega, fs, t).v
            }
        })
        .collect()
}

fn add_noise(x: &mut [f64], std: f64, rng: &mut StdRng) {
    if std > 0.0 {
        let normal = Normal::new(0.0, std).expect("positive std");
        for v in x.iter_mut() {
            *v += normal.sample(rng);
        }
    }
}

fn quantize(x: &mut [f64], step: f64) {
    for v in x.iter_mut() {
        *v = (*v / step).round() * step;
    }
}

/// Total mechanical energy ½Jθ'² + ½k·D² (+ ¼k3·D⁴, or its limited form) of an unforced
/// rig at rest base.
pub fn mechanical_energy(model: &RigModel, theta: f64, omega: f64) -> f64 {
    let offset = model
        .effects
        .get(crate::model::EffectKind::AsymmetricClearance)
        .unwrap_or(0.0);
    let zc = theta - offset;
    let d = (zc.abs() - model.half_gap()).max(0.0);
    let cubic = model.effects.cubic_stiffness.map_or(0.0, |p| p.energy(d));
    0.5 * model.inertia * omega * omega + 0.5 * model.stiffness * d * d + cubic
        - 0.5 * model.inertia * model.gravity_stiffness * theta * theta
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A force model of `stiffness` with only its microslip joint (slip force 2 N, joint
    /// stiffness 1000 N/m, so the last element slips at 2F/kj = 4 mm) and, where given,
    /// a fine population (stiffness, largest slip).
    fn iwan_model(stiffness: f64, fine: Option<(f64, f64)>) -> RigModel {
        let mut m = RigModel::paper();
        m.kind = crate::model::ModelKind::Force;
        m.clearance = 0.0;
        m.stiffness = stiffness;
        m.set_effect(crate::model::EffectKind::Microslip, Some(2.0));
        m.effects.set_joint_stiffness(1000.0);
        if let Some((k, slip)) = fine {
            m.effects.set_fine(k, slip);
        }
        m.validate().unwrap();
        m
    }

    #[test]
    fn a_diverging_joint_leaves_a_record_of_nan_instead_of_a_panic() {
        // Damping far below zero: the state grows past f64's range within the record. Its
        // sliders were clamped between NaN bounds, which panicked and took a whole
        // `skelid gap` down with it (a scan point of the Brake–Reuss beam, band 1.5–92 Hz).
        let mut m = iwan_model(1000.0, None);
        m.damping = -3.0e4 * m.inertia;
        let drive = Drive::Released {
            displacement: 1e-3,
            velocity: 0.0,
        };
        let settings = SimSettings {
            sample_rate: 400.0,
            duration: 2.0,
            substeps: 4,
            output_noise: 0.0,
            input_noise: 0.0,
            seed: 1,
        };
        let out = simulate(&m, &drive, &settings);
        assert_eq!(out.output.len(), 800);
        let first = out
            .output
            .iter()
            .position(|v| !v.is_finite())
            .expect("it diverges");
        println!("not finite from sample {first} of 800 on");
        assert!(first > 0 && first < 400, "{first}");
        // From there on the record says so, sample by sample.
        assert!(out.output[first..].iter().all(|v| v.is_nan()));
        assert!(out.output[..first].iter().all(|v| v.is_finite()));
    }

    /// [`iwan_model`]'s rig without a fine population, all of its stiffness in the joint.
    fn iwan_rig(drive: &Drive) -> Rig<'_> {
        Rig::new(&iwan_model(1000.0, None), drive)
    }

    /// 401 displacements from a to b.
    fn ramp(a: f64, b: f64) -> Vec<f64> {
        (0..=400).map(|i| a + (b - a) * i as f64 / 400.0).collect()
    }

    /// The joint's force at z after the displacement history `path` (each point committed).
    fn joint_after(rig: &Rig, path: &[f64]) -> f64 {
        for &z in path {
            rig.commit(z);
        }
        rig.joint(*path.last().unwrap())
    }

    #[test]
    fn the_iwan_element_is_a_spring_stuck_a_slider_at_macroslip_and_masing_between() {
        let drive = Drive::Free {
            initial_offset: 0.0,
        };
        // Stuck (below the first element's slip at 0.125 mm): the joint stiffness itself.
        let rig = iwan_rig(&drive);
        let f = joint_after(&rig, &ramp(0.0, 1e-4));
        assert!((f - 1000.0 * 1e-4).abs() < 1e-12, "{f}");
        // Past 2F/kj every element slides: the slip force, whatever the displacement.
        let rig = iwan_rig(&drive);
        for z in [5e-3, 1e-2, 0.1] {
            let f = joint_after(&rig, &ramp(0.0, z));
            assert!((f - 2.0).abs() < 1e-9, "{z}: {f}");
        }
        // Virgin loading to u with slip displacements spread evenly over (0, φ] (φ = 4 mm,
        // n elements): F(u) = kj·u − kj·u²/(2φ) up to the discretisation's O(φ/n²).
        let rig = iwan_rig(&drive);
        let u = 2e-3;
        let f = joint_after(&rig, &ramp(0.0, u));
        let phi = 4e-3;
        let exact = 1000.0 * (u - u * u / (2.0 * phi));
        assert!((f - exact).abs() < 0.01 * exact, "{f} vs {exact}");
        // Masing: unloading by Δ from the turning point follows twice the virgin curve
        // scaled by a half, F(u) − 2·F_virgin(Δ/2).
        let delta = 1e-3;
        let back = joint_after(&rig, &ramp(u, u - delta));
        let virgin = |x: f64| 1000.0 * (x - x * x / (2.0 * phi));
        let masing = f - 2.0 * virgin(0.5 * delta);
        assert!((back - masing).abs() < 0.01 * f, "{back} vs {masing}");
    }

    #[test]
    fn a_fine_population_adds_a_uniform_iwan_that_saturates_at_its_largest_slip() {
        let drive = Drive::Free {
            initial_offset: 0.0,
        };
        // The joint of `iwan_rig` with a fine population of 200 N/m slipping over (0, 0.5 mm].
        let (kf, phi_f) = (200.0, 5e-4);
        let model = iwan_model(1500.0, Some((kf, phi_f)));
        let fine_rig = |drive| Rig::new(&model, drive);
        // Its stiffness is part of the model's: the linear spring is what is left.
        let rig = fine_rig(&drive);
        assert!((rig.k - 300.0).abs() < 1e-12, "{}", rig.k);
        // Below the first fine element's slip (φ_f/8): both populations are springs.
        let f = joint_after(&rig, &ramp(0.0, 2e-5));
        assert!((f - 1200.0 * 2e-5).abs() < 1e-12, "{f}");
        // The fine population's force alone, the same joint without it taken away: its
        // elements slip at φ_f·i/m (i = 1..m), so on virgin loading to u its force is
        // kf/m·Σ min(u, φ_f·i/m), and past φ_f it slides as a whole at the sum of its
        // elements' slip forces, kf·φ_f·(m + 1)/(2m).
        let m = crate::model::FINE_ELEMENTS;
        let fine_exact = |u: f64| {
            (1..=m)
                .map(|i| kf / m as f64 * u.min(phi_f * i as f64 / m as f64))
                .sum::<f64>()
        };
        let without = iwan_model(1500.0, None);
        let fine_alone = |u: f64| {
            let path = ramp(0.0, u);
            joint_after(&fine_rig(&drive), &path) - joint_after(&Rig::new(&without, &drive), &path)
        };
        for u in [1e-4, 3e-4, 4.9e-4] {
            let (got, exact) = (fine_alone(u), fine_exact(u));
            assert!((got - exact).abs() < 1e-12, "{u}: {got} vs {exact}");
        }
        let slides = kf * phi_f * (m + 1) as f64 / (2 * m) as f64;
        for u in [6e-4, 2e-3] {
            assert!((fine_alone(u) - slides).abs() < 1e-12, "{u}");
        }
        // Without a fine population the joint is bit for bit the one before it existed:
        // one element stiffness times the sum of the 16 elements' stretches.
        let plain = iwan_rig(&drive);
        let path = ramp(0.0, 3e-3);
        let z = 2.5e-3;
        for &x in &path {
            plain.commit(x);
        }
        plain.commit(z);
        let before: f64 = 1000.0 / 16.0
            * plain
                .sliders
                .borrow()
                .iter()
                .zip(&plain.slip)
                .map(|(x, p)| (z - x).clamp(-p, *p))
                .sum::<f64>();
        assert_eq!(plain.joint(z).to_bits(), before.to_bits());
        let unset_model = iwan_model(1000.0, Some((0.0, 0.0)));
        let unset = Rig::new(&unset_model, &drive);
        assert_eq!(
            joint_after(&iwan_rig(&drive), &path).to_bits(),
            joint_after(&unset, &path).to_bits()
        );
    }

    #[test]
    fn a_microslip_joint_softens_and_damps_a_free_decay_more_at_larger_amplitude() {
        // The joint's stiffness is part of k: at small amplitude the mode rings at
        // sqrt(k/m), and decays the faster and the lower the larger it starts.
        let mut m = RigModel::paper();
        m.kind = crate::model::ModelKind::Force;
        m.clearance = 0.0;
        m.inertia = 1.0;
        m.stiffness = (TAU * 5.0_f64).powi(2);
        m.damping = 0.01;
        m.set_effect(
            crate::model::EffectKind::Microslip,
            Some(0.2 * m.stiffness * 1e-3),
        );
        let settings = SimSettings {
            sample_rate: 1000.0,
            duration: 4.0,
            ..SimSettings::default()
        };
        let ring = |a0: f64| {
            let out = simulate(&m, &Drive::Free { initial_offset: a0 }, &settings);
            // The frequency from the first ten zero crossings, the decay from the peaks.
            let y = &out.output;
            let crossings: Vec<usize> = (1..y.len())
                .filter(|&i| y[i - 1] > 0.0 && y[i] <= 0.0)
                .collect();
            let f = 1000.0 * 9.0 / (crossings[9] - crossings[0]) as f64;
            let peak_late = y[crossings[8]..crossings[9]]
                .iter()
                .fold(0f64, |a, v| a.max(v.abs()));
            (f, peak_late / a0)
        };
        let (f_small, keep_small) = ring(1e-5);
        let (f_large, keep_large) = ring(5e-3);
        assert!((f_small - 5.0).abs() < 0.02, "{f_small}");
        assert!(f_large < 0.99 * f_small, "{f_large} vs {f_small}");
        assert!(
            keep_large < 0.9 * keep_small,
            "{keep_large} vs {keep_small}"
        );
    }

    #[test]
    fn jet_derivatives_match_finite_differences() {
        let e = Excitation::Chirp {
            f0: 0.5,
            f1: 12.0,
            duration: 30.0,
            amplitude: 0.02,
            rolloff: Some(Rolloff {
                corner_hz: 5.0,
                order: 2,
            }),
        };
        for &t in &[0.3, 7.1, 15.0, 29.9, 31.0] {
            let h = 1e-5;
            let j = e.eval(t);
            let d1 = (e.eval(t + h).v - e.eval(t - h).v) / (2.0 * h);
            let d2 = (e.eval(t + h).d1 - e.eval(t - h).d1) / (2.0 * h);
            assert!(
                (j.d1 - d1).abs() < 1e-6 * (1.0 + d1.abs()),
                "t={t} {} {}",
                j.d1,
                d1
            );
            assert!(
                (j.d2 - d2).abs() < 1e-5 * (1.0 + d2.abs()),
                "t={t} {} {}",
                j.d2,
                d2
            );
        }
    }

    #[test]
    fn hermite_reproduces_a_sampled_sine_and_its_derivatives() {
        let fs = 1000.0;
        let f = 7.0;
        let y: Vec<f64> = (0..2000).map(|i| (TAU * f * i as f64 / fs).sin()).collect();
        let e = Excitation::sampled(y, fs);
        let w = TAU * f;
        let mut worst = [0.0f64; 3];
        for k in 0..500 {
            let t = 0.1 + k as f64 * 0.00237;
            let j = e.eval(t);
            worst[0] = worst[0].max((j.v - (w * t).sin()).abs());
            worst[1] = worst[1].max((j.d1 - w * (w * t).cos()).abs() / w);
            worst[2] = worst[2].max((j.d2 + w * w * (w * t).sin()).abs() / (w * w));
        }
        println!("hermite errors (value, d1/w, d2/w^2): {worst:?}");
        assert!(
            worst[0] < 1e-6 && worst[1] < 1e-4 && worst[2] < 0.02,
            "{worst:?}"
        );
    }

    #[test]
    fn a_value_alone_is_the_jets_value_to_the_bit() {
        // Force drives take `value`; their simulations must not change by a bit.
        let fs = 1000.0;
        let y: Vec<f64> = (0..3000).map(|i| (i as f64 * 0.0137).sin() * 3.7).collect();
        let drives = [
            Excitation::sampled(y, fs),
            Excitation::sampled(vec![2.5], fs),
            Excitation::sampled(Vec::new(), fs),
            Excitation::Chirp {
                f0: 1.0,
                f1: 9.0,
                duration: 2.0,
                amplitude: 0.3,
                rolloff: None,
            },
        ];
        for e in &drives {
            for k in 0..20_000 {
                let t = -0.5 + k as f64 * 2.0e-4 * std::f64::consts::E;
                assert_eq!(e.value(t).to_bits(), e.eval(t).v.to_bits(), "t = {t}");
            }
            assert_eq!(e.value(f64::NAN).to_bits(), e.eval(f64::NAN).v.to_bits());
        }
    }
}
