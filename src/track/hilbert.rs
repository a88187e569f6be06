//! The Hilbert track: in, one signal and its sample rate; out, a [`Track`] from the analytic
//! signal by FFT (envelope, frequency and their spectral derivatives, optionally low-passed),
//! valid away from the record's ends.

use std::f64::consts::PI;

use crate::filter::lowpass_zero_phase_all;
use crate::transform::{hilbert, Spectrum};

use super::unwrap::unwrap_phase;
use super::{check_signal, Device, HilbertOptions, Method, Track, TrackError};

/// Envelope, frequency and derivatives by the Hilbert transform.
///
/// Derivatives are spectral (z', z'' by FFT); with a cut-off they, A and f are low-passed by
/// the same zero-phase filter. Valid: away from the ends by two periods of the median
/// frequency (where the FFT's periodic extension distorts z).
pub fn track_hilbert(x: &[f64], fs: f64, opt: &HilbertOptions) -> Result<Track, TrackError> {
    crate::profile::time(crate::profile::Stage::Hilbert, || hilbert_inner(x, fs, opt))
}

fn hilbert_inner(x: &[f64], fs: f64, opt: &HilbertOptions) -> Result<Track, TrackError> {
    check_signal(x, fs)?;
    if let Some(c) = opt.cutoff {
        if !(c > 0.0 && c < 1.0) {
            return Err(TrackError::BadOption(format!(
                "Hilbert cut-off {c} must be a fraction of Nyquist between 0 and 1 (e.g. 0.005)"
            )));
        }
    }
    let n = x.len();
    let an = hilbert::analytic(x, fs);
    let mut amplitude = Vec::with_capacity(n);
    let mut frequency = Vec::with_capacity(n);
    let mut d_amplitude = Vec::with_capacity(n);
    let mut d2_amplitude = Vec::with_capacity(n);
    let mut d_frequency = Vec::with_capacity(n);
    for i in 0..n {
        let z = an.z[i];
        let a = z.norm();
        if a == 0.0 {
            amplitude.push(0.0);
            frequency.push(0.0);
            d_amplitude.push(0.0);
            d2_amplitude.push(0.0);
            d_frequency.push(0.0);
            continue;
        }
        let r1 = an.dz[i] / z; // A'/A + jφ'
        let r2 = an.d2z[i] / z; // A''/A − φ'² + j(2A'φ'/A + φ'')
        let w = r1.im;
        amplitude.push(a);
        frequency.push(w / (2.0 * PI));
        d_amplitude.push(a * r1.re);
        d2_amplitude.push(a * (r2.re + w * w));
        d_frequency.push((r2.im - 2.0 * r1.re * w) / (2.0 * PI));
    }
    let mut phase: Vec<f64> = an.z.iter().map(|z| z.arg()).collect();
    unwrap_phase(&mut phase, &frequency, |i| i as f64 / fs);
    if let Some(c) = opt.cutoff {
        [amplitude, frequency, d_amplitude, d2_amplitude, d_frequency] = lowpass_zero_phase_all(
            [
                &amplitude,
                &frequency,
                &d_amplitude,
                &d2_amplitude,
                &d_frequency,
            ],
            c,
        );
    }
    let mut sorted: Vec<f64> = frequency.iter().map(|f| f.abs()).collect();
    let mid = sorted.len() / 2;
    let median_f = *sorted.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
    let edge = if median_f > 0.0 {
        ((2.0 * fs / median_f).ceil() as usize).min(n / 2)
    } else {
        n / 2
    };
    let valid = (0..n).map(|i| i >= edge && i + edge < n).collect();
    let noise = hilbert_noise(x, fs);
    Ok(Track {
        method: Method::Hilbert,
        sample_rate: fs,
        amplitude,
        frequency,
        phase,
        d_amplitude,
        d2_amplitude,
        d_frequency,
        valid,
        offset: an.mean,
        noise,
        band: (0.0, fs / 2.0),
        backend: Device::Cpu,
        scalogram: None,
    })
}

fn hilbert_noise(x: &[f64], fs: f64) -> f64 {
    Spectrum::new(x, fs, 0)
        .white_noise_variance(fs / 4.0, fs / 2.0)
        .unwrap_or(0.0)
        .sqrt()
}
