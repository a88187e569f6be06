//! Instantaneous amplitude and frequency against analytic truth (issue 3's accuracy table).

use std::f64::consts::PI;

use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use skelid::track::{track_hilbert, track_wavelet, HilbertOptions, Track, WaveletOptions};

const FS: f64 = 1000.0;
const DURATION: f64 = 10.0;

/// A test signal with its true envelope and frequency.
struct Case {
    name: String,
    x: Vec<f64>,
    amp: Vec<f64>,
    freq: Vec<f64>,
    noise: f64,
}

fn times() -> Vec<f64> {
    (0..(DURATION * FS) as usize)
        .map(|i| i as f64 / FS)
        .collect()
}

fn impulse(zeta: f64) -> Case {
    let (fnat, t) = (10.0, times());
    let wn = 2.0 * PI * fnat;
    let wd = wn * (1.0 - zeta * zeta).sqrt();
    let amp: Vec<f64> = t.iter().map(|t| (-zeta * wn * t).exp()).collect();
    Case {
        name: format!("impulse ζ={zeta}"),
        x: t.iter()
            .zip(&amp)
            .map(|(t, a)| a * (wd * t).sin())
            .collect(),
        freq: vec![wd / (2.0 * PI); t.len()],
        amp,
        noise: 0.0,
    }
}

fn damped_chirp() -> Case {
    let t = times();
    let amp: Vec<f64> = t.iter().map(|t| (-0.2 * t).exp()).collect();
    Case {
        name: "damped chirp 0-10 Hz".into(),
        x: t.iter()
            .zip(&amp)
            .map(|(t, a)| a * (PI * t * t).cos())
            .collect(),
        freq: t.clone(),
        amp,
        noise: 0.0,
    }
}

fn offset_response() -> Case {
    let mut c = impulse(0.05);
    c.name = "impulse ζ=0.05 + offset 0.5".into();
    c.x.iter_mut().for_each(|v| *v += 0.5);
    c
}

fn harmonic_chirp() -> Case {
    let t = times();
    Case {
        name: "chirp + 15 % 3rd harmonic".into(),
        x: t.iter()
            .map(|t| (PI * t * t).cos() + 0.15 * (3.0 * PI * t * t).cos())
            .collect(),
        freq: t.clone(),
        amp: vec![1.0; t.len()],
        noise: 0.0,
    }
}

fn with_noise(mut c: Case, snr_db: f64, seed: u64) -> Case {
    let rms = (c.x.iter().map(|v| v * v).sum::<f64>() / c.x.len() as f64).sqrt();
    let sd = rms / 10f64.powf(snr_db / 20.0);
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let normal = Normal::new(0.0, sd).unwrap();
    c.x.iter_mut().for_each(|v| *v += normal.sample(&mut rng));
    c.noise = sd;
    c.name = format!("{} @ {snr_db} dB", c.name);
    c
}

/// Errors over the valid samples, and the coverage of the central 90 % above the noise.
struct Score {
    env_rms: f64,
    freq_rms: f64,
    coverage: f64,
    used: usize,
}

fn score(c: &Case, tr: &Track, mask: &[bool]) -> Score {
    let n = c.x.len();
    let peak = c.amp.iter().cloned().fold(0.0, f64::max);
    // Above the noise: the signal's RMS over a cycle (A/√2) exceeds the noise's; without
    // noise, above 1e-3 of the peak (60 dB, a good accelerometer channel's dynamic range).
    let floor = if c.noise > 0.0 {
        c.noise * 2f64.sqrt()
    } else {
        1e-3 * peak
    };
    let (lo, hi) = (n / 20, n - n / 20);
    let (mut e2, mut f2, mut used, mut region, mut covered) = (0.0, 0.0, 0, 0, 0);
    for (i, &trusted) in mask.iter().enumerate().take(hi).skip(lo) {
        let above = c.amp[i] > floor;
        if above {
            region += 1;
        }
        if !trusted {
            continue;
        }
        if above {
            covered += 1;
        }
        used += 1;
        e2 += ((tr.amplitude[i] - c.amp[i]) / c.amp[i]).powi(2);
        f2 += (tr.frequency[i] - c.freq[i]).powi(2);
    }
    Score {
        env_rms: (e2 / used.max(1) as f64).sqrt(),
        freq_rms: (f2 / used.max(1) as f64).sqrt(),
        coverage: covered as f64 / region.max(1) as f64,
        used,
    }
}

fn all_cases() -> Vec<(Case, bool)> {
    let mut v = Vec::new();
    let clean = || {
        vec![
            impulse(0.01),
            impulse(0.05),
            impulse(0.1),
            damped_chirp(),
            offset_response(),
            harmonic_chirp(),
        ]
    };
    for c in clean() {
        v.push((c, false));
    }
    for (i, c) in clean().into_iter().enumerate() {
        v.push((with_noise(c, 30.0, 10 + i as u64), true));
    }
    for (i, c) in clean().into_iter().enumerate() {
        v.push((with_noise(c, 20.0, 20 + i as u64), true));
    }
    v
}

#[test]
fn wavelet_meets_the_accuracy_table_and_beats_hilbert() {
    let mut failures = Vec::new();
    println!(
        "{:38} | {:>9} {:>9} {:>6} | {:>9} {:>9} (Hilbert on the same samples)",
        "case", "env RMS", "f RMS Hz", "cover", "env RMS", "f RMS Hz"
    );
    for (c, noisy) in all_cases() {
        let w = track_wavelet(&c.x, FS, &WaveletOptions::default(), None).unwrap();
        let h = track_hilbert(&c.x, FS, &HilbertOptions::default()).unwrap();
        let sw = score(&c, &w, &w.valid);
        let sh = score(&c, &h, &w.valid);
        println!(
            "{:38} | {:8.4}% {:9.5} {:5.1}% | {:8.3}% {:9.4}",
            c.name,
            100.0 * sw.env_rms,
            sw.freq_rms,
            100.0 * sw.coverage,
            100.0 * sh.env_rms,
            sh.freq_rms
        );
        let (env_tol, f_tol) = if noisy { (0.02, 0.05) } else { (0.005, 0.01) };
        if sw.env_rms > env_tol || sw.freq_rms > f_tol {
            failures.push(format!("{}: accuracy", c.name));
        }
        if sw.coverage < 0.8 || sw.used < 100 {
            failures.push(format!("{}: coverage {:.3}", c.name, sw.coverage));
        }
        let must_beat = noisy || c.name.contains("chirp");
        if must_beat && !(sw.env_rms < sh.env_rms && sw.freq_rms < sh.freq_rms) {
            failures.push(format!("{}: does not beat Hilbert", c.name));
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}
