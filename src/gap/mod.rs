//! The sim-to-real gap between two identifications of one run — the measurement and the
//! model simulated under the measurement's own input — as one dimensionless number with its
//! breakdown into domains and regions (DESIGN.md, "Simulation and the sim-to-real gap").
//!
//! The domains compare what a model gets right or wrong, never the raw response:
//! after the jump-down of a chirp, which flank of the clearance the link settles on is a
//! coin-flip that moves z's mean, not its envelope, its backbone or its damping.
//! - **time**: the response envelope over time, e = how far ln A_meas(t) lies outside the
//!   range of ln A_sim over t ± 0.25 s (and the other way round), weighted by the measured
//!   amplitude (a relative error; 0.1 ≈ 10 %); where both touch both flanks, plus the error
//!   of the centre of the motion relative to the measured amplitude; where the measurement
//!   chains' resolutions differ, plus the quantisation error one has and the other lacks,
//!   relative to the measured amplitude (at most 1);
//! - **backbone**: the natural frequency at each sample where the measurement is at
//!   resonance (|ω/ω0 − 1| < 0.1), e = (f0_sim − f0_meas) / rms f0_meas, both smoothed over
//!   ±[`SMOOTH`], the model taken at the same instant or its nearest resonant one;
//! - **damping**: the damping force 2h0·Aω at the same samples, e = (D_sim − D_meas) /
//!   rms D_meas;
//! - **waveform** (on by default): H3/H1 of the relative motion at the same samples,
//!   e = (H_sim − H_meas) / rms H_meas, at most 1 a sample.
//!
//! Left out, as coin-flips of the rig's noise: the grazing band ([`GRAZING`], time domain),
//! and in every domain the settling after a jump-down ([`SETTLE_DECAY_TIMES`]) and the
//! climb between each measured jump-up and the model's nearest ([`JUMP_UP_SPAN`]).
//!
//! Each domain's gap is the RMS of its e; the gap is the RMS of the domains present,
//! `sqrt((g_time² + g_backbone² + g_damping²) / 3)`.
//!
//! A gap can be measured on part of a run only ([`Blocks`]): the search fits on alternate
//! time blocks and scores on the others ([`search`]); [`selfcheck`] measures how well the
//! whole diagnosis does on simulated rigs with a known missing effect.

mod compare;
pub mod detection;
pub mod export;
mod features;
mod finished;
pub mod runner;
pub mod search;
pub mod selfcheck;
mod simulated;

use crate::identify::Identification;
use crate::run::Run;

pub use compare::{
    Target, GRAZING, JOIN_DECAY_TIMES, JUMP_UP_SPAN, SETTLE_DECAY_TIMES, TIME_TOLERANCE,
};
pub use features::{
    as_displacement, exact_lattice_step, lattice_coherence, lattice_step, measured_resolution,
    model_resolution, noisy_lattice_step, resolution_per_step, Features, LATTICE_SHARE,
    NOISY_COHERENCE, SMOOTH,
};
pub use finished::{GapRun, Whole};
pub use search::{diagnose, Candidate, Diagnosis, SearchOptions};
pub use simulated::{
    decimate, decimation_for, simulate_given, simulate_like, simulate_released, Simulated,
    SAMPLES_PER_CYCLE,
};

/// Time windows the time domain is split into for the regions.
pub(super) const TIME_WINDOWS: usize = 8;
/// Amplitude ranges the skeleton domains are split into for the regions.
pub(super) const AMPLITUDE_RANGES: usize = 4;

/// Where part of the gap lies (FORMATS.md §5, `regions`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Region {
    /// Start of the time range (s).
    pub t0: f64,
    /// End of the time range (s).
    pub t1: f64,
    /// Lowest response amplitude in the region (signal units).
    pub amp_lo: f64,
    /// Highest response amplitude.
    pub amp_hi: f64,
    /// Lowest response frequency (Hz).
    pub f_lo: f64,
    /// Highest response frequency (Hz).
    pub f_hi: f64,
    /// `time`, `backbone`, `damping` or `waveform`.
    pub domain: &'static str,
    /// Fraction of the total squared gap in this region (all regions sum to 1).
    pub share: f64,
}

/// The gap and its breakdown.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Gap {
    /// The dimensionless gap.
    pub total: f64,
    /// Per domain (`None` where the two identifications share nothing to compare).
    pub time: Option<f64>,
    /// Backbone domain.
    pub backbone: Option<f64>,
    /// Damping domain.
    pub damping: Option<f64>,
    /// Waveform domain (the third harmonic against the first at resonance), when scored
    /// (the default; not with `skelid gap --no-waveform`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub waveform: Option<f64>,
    /// Regions, largest share first.
    pub regions: Vec<Region>,
}

impl Gap {
    /// `total (time / backbone / damping[ / waveform])` to three decimals, `–` for a domain
    /// with nothing compared: one run's gap on the terminal and the page, after
    /// [`Gap::domains_label`].
    pub fn by_domain(&self) -> String {
        let part = |v: Option<f64>| v.map_or("–".into(), |v| format!("{v:.3}"));
        let mut parts = vec![part(self.time), part(self.backbone), part(self.damping)];
        if self.waveform.is_some() {
            parts.push(part(self.waveform));
        }
        format!("{:.3} ({})", self.total, parts.join(" / "))
    }

    /// What [`Gap::by_domain`] lists: the total, then its domains by name.
    pub fn domains_label(&self) -> &'static str {
        if self.waveform.is_some() {
            "total (time / backbone / damping / waveform)"
        } else {
            "total (time / backbone / damping)"
        }
    }
}

/// One domain's squared errors with their weights and where they lie.
pub(super) struct Errors {
    /// (weight, squared error, region index)
    pub(super) terms: Vec<(f64, f64, usize)>,
    pub(super) regions: Vec<Region>,
}

impl Errors {
    /// Weighted mean square.
    pub(super) fn mean_square(&self) -> Option<f64> {
        let w: f64 = self.terms.iter().map(|t| t.0).sum();
        (w > 0.0).then(|| self.terms.iter().map(|t| t.0 * t.1).sum::<f64>() / w)
    }
}

/// Alternate time blocks of a run: the even ones (from t = 0) to fit on, the odd ones
/// withheld to score on. With a sine sweep every part covers the whole band, a block at a
/// time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Blocks {
    /// Block length (s).
    pub seconds: f64,
}

/// Which samples of a run a gap is measured on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    /// The even blocks, which fits see.
    Fit,
    /// The odd blocks, withheld from every fit.
    Holdout,
}

impl Blocks {
    /// One flag per sample of an `n`-sample record at `fs` Hz: true inside `part`.
    pub fn mask(&self, n: usize, fs: f64, part: Part) -> Vec<bool> {
        let per = (self.seconds * fs).round().max(1.0) as usize;
        (0..n)
            .map(|i| (i / per).is_multiple_of(2) == (part == Part::Fit))
            .collect()
    }
}

/// The gap between `measured` (identified from `measured_run`) and `simulated`, the model
/// simulated under the same run's input.
pub fn gap(measured: &Identification, measured_run: &Run, simulated: &Simulated) -> Gap {
    let features = simulated.features();
    Target::new(measured, measured_run, None)
        .with_resolution(measured_resolution(measured_run))
        .gap(measured, &features)
}

/// Why a gap could not be computed.
#[derive(Debug, thiserror::Error)]
pub enum GapError {
    /// The run cannot drive a base-motion simulation.
    #[error("{0}")]
    Unusable(String),
    /// The model gives no response that can be identified (no refit of it does either).
    #[error("the model's simulated response could not be identified: {0}")]
    Simulated(String),
    /// The simulated response could not be identified, and why. The identification's error
    /// is kept whole, typed; it is part of the message rather than a `source()` because
    /// every place that shows a gap error prints the whole chain.
    #[error("the model's simulated response could not be identified: {reason}")]
    Unidentified {
        /// Why the identification failed.
        reason: crate::identify::IdentifyError,
    },
}

#[cfg(test)]
mod tests {
    use super::compare::{jump_ups, paired_settling, settling, window_extremes};
    use super::features::mean_around;
    use super::*;
    use crate::model::RigModel;

    #[test]
    fn window_extremes_match_a_naive_scan() {
        let x: Vec<f64> = (0..200)
            .map(|i| {
                if i % 17 == 3 {
                    f64::NAN
                } else {
                    ((i * 37) % 101) as f64
                }
            })
            .collect();
        for half in [0, 1, 5, 300] {
            let (lo, hi) = window_extremes(&x, half);
            for i in 0..x.len() {
                let w = &x[i.saturating_sub(half)..(i + half + 1).min(x.len())];
                let f = w.iter().filter(|v| v.is_finite());
                let (l, h) = f.fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                    (l.min(v), h.max(v))
                });
                assert_eq!((lo[i], hi[i]), (l, h), "i {i} half {half}");
            }
        }
    }

    #[test]
    fn mean_around_matches_a_naive_mean_of_the_finite_values() {
        let x: Vec<f64> = (0..300)
            .map(|i| {
                if i % 7 == 2 {
                    f64::NAN
                } else {
                    ((i * 13) % 29) as f64
                }
            })
            .collect();
        for half in [0, 3, 50, 400] {
            let y = mean_around(&x, |i| x[i].is_finite().then_some(half));
            for i in 0..x.len() {
                if !x[i].is_finite() {
                    assert!(y[i].is_nan());
                    continue;
                }
                let w: Vec<f64> = x[i.saturating_sub(half)..(i + half + 1).min(x.len())]
                    .iter()
                    .copied()
                    .filter(|v| v.is_finite())
                    .collect();
                let mean = w.iter().sum::<f64>() / w.len() as f64;
                assert!((y[i] - mean).abs() < 1e-9, "i {i} half {half}");
            }
        }
    }

    /// A 3 Hz sine of 0.02 amplitude sampled at 1 kHz, plus Gaussian noise of `noise` std
    /// (seeded: the same every run).
    fn noisy_sine(n: usize, noise: f64) -> Vec<f64> {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand::rngs::StdRng::seed_from_u64(12345);
        let normal = Normal::new(0.0, noise).expect("a positive deviation");
        (0..n)
            .map(|i| {
                0.02 * (2.0 * std::f64::consts::PI * 3.0 * i as f64 / 1000.0).sin()
                    + normal.sample(&mut rng)
            })
            .collect()
    }

    #[test]
    fn the_lattice_of_a_quantised_channel_is_found_and_a_continuous_one_has_none() {
        let x = noisy_sine(5000, 1e-4);
        assert_eq!(lattice_step(&x), None);
        for q in [1e-4, 3.7e-4, 2e-3] {
            let on: Vec<f64> = x.iter().map(|v| (v / q).round() * q).collect();
            let step = lattice_step(&on).unwrap();
            assert!((step / q - 1.0).abs() < 1e-9, "{q}: {step}");
            // A lattice need not pass through zero (an ADC's offset).
            let shifted: Vec<f64> = on.iter().map(|v| v + 0.3 * q).collect();
            let step = lattice_step(&shifted).unwrap();
            assert!((step / q - 1.0).abs() < 1e-9, "{q}: {step}");
            // Stored as f32, the lattice survives.
            let single: Vec<f64> = on.iter().map(|&v| v as f32 as f64).collect();
            assert!(lattice_step(&single).is_some(), "{q}");
        }
        // A constant or nearly constant channel says nothing.
        assert_eq!(lattice_step(&[0.5; 1000]), None);
        let two: Vec<f64> = (0..1000).map(|i| (i % 2) as f64 * 1e-3).collect();
        assert_eq!(lattice_step(&two), None);
    }

    /// A 30 s record at 1 kHz like a swept rig's: a chirp whose amplitude rises and falls.
    fn sweep(amplitude: f64) -> Vec<f64> {
        (0..30_000)
            .map(|i| {
                let t = i as f64 / 1000.0;
                let env = amplitude * (0.2 + 0.8 * (std::f64::consts::PI * t / 30.0).sin());
                env * (2.0 * std::f64::consts::PI * (0.5 * t + 0.2 * t * t)).sin()
            })
            .collect()
    }

    fn gaussian(n: usize, sigma: f64, seed: u64) -> Vec<f64> {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let normal = Normal::new(0.0, sigma).expect("a positive deviation");
        (0..n).map(|_| normal.sample(&mut rng)).collect()
    }

    #[test]
    fn a_lattice_blurred_by_acquisition_noise_and_offset_is_found() {
        let x = sweep(0.03);
        // Encoders of 20, 17 and 12 bit per revolution; noise of 1/60 to 1/15 of a step
        // after the quantiser, and an offset that is not a whole number of steps.
        for bits in [20, 17, 12] {
            let q = std::f64::consts::TAU / f64::from(1u32 << bits);
            for (k, fraction) in [60.0, 30.0, 15.0].into_iter().enumerate() {
                let noise = gaussian(x.len(), q / fraction, 7 + k as u64);
                let y: Vec<f64> = x
                    .iter()
                    .zip(&noise)
                    .map(|(v, e)| (v / q).round() * q + 1.7e-4 + 0.37 * q + e)
                    .collect();
                assert_eq!(exact_lattice_step(&y), None, "{bits} bit: not exact");
                let step = lattice_step(&y).unwrap_or_else(|| panic!("{bits} bit, q/{fraction}"));
                assert!(
                    (step / q - 1.0).abs() < 1e-3,
                    "{bits} bit, q/{fraction}: {step} against {q}"
                );
                let c = lattice_coherence(&y, step);
                let expected = (-2.0 * (std::f64::consts::PI / fraction).powi(2)).exp();
                assert!(
                    (c - expected).abs() < 0.02,
                    "coherence {c} against {expected}"
                );
            }
        }
    }

    #[test]
    fn continuous_records_have_no_noisy_lattice() {
        let decay: Vec<f64> = (0..30_000)
            .map(|i| {
                let t = i as f64 / 1000.0;
                0.02 * (-t / 3.0).exp() * (2.0 * std::f64::consts::PI * 8.0 * t).sin()
            })
            .collect();
        let cases: Vec<(&str, Vec<f64>)> = vec![
            ("sweep", sweep(0.03)),
            (
                "sweep with noise",
                sweep(0.03)
                    .iter()
                    .zip(gaussian(30_000, 1e-5, 3))
                    .map(|(a, b)| a + b)
                    .collect(),
            ),
            ("white noise", gaussian(30_000, 1e-3, 4)),
            (
                "long free decay with noise",
                decay
                    .iter()
                    .zip(gaussian(30_000, 1e-7, 5))
                    .map(|(a, b)| a + b)
                    .collect(),
            ),
            ("noisy sine", noisy_sine(30_000, 1e-4)),
        ];
        for (name, x) in cases {
            assert_eq!(noisy_lattice_step(&x), None, "{name}");
            assert_eq!(lattice_step(&x), None, "{name}");
        }
    }

    #[test]
    fn a_base_motion_run_counts_both_channels_and_a_model_matches_it() {
        use crate::run::{Quantity, RunKind, RunMeta};
        let q = 2e-4;
        let y: Vec<f64> = noisy_sine(3000, 1e-4)
            .iter()
            .map(|v| (v / q).round() * q)
            .collect();
        let x: Vec<f64> = y.iter().map(|v| (0.5 * v / q).round() * q).collect();
        let meta = RunMeta {
            path: "/q".into(),
            samples: y.len(),
            sample_rate: 1000.0,
            duration: 3.0,
            kind: RunKind::BaseMotion,
            input_quantity: Some(Quantity::Displacement),
            output_quantity: Quantity::Displacement,
            inertia: None,
            gravity_stiffness: 0.0,
            units: None,
            excitation: None,
            attributes: Default::default(),
            mode_band: None,
            mode_near: None,
            zero_tolerance: 0.0,
        };
        let run = Run {
            meta,
            input: Some(x),
            output: y,
        };
        let r = measured_resolution(&run);
        assert!((r - q * (2.0f64 / 12.0).sqrt()).abs() < 1e-12, "{r}");
        let mut model = RigModel::paper();
        assert_eq!(model_resolution(&model, &run), 0.0);
        model
            .effects
            .set(crate::model::EffectKind::Quantization, Some(q));
        assert!((model_resolution(&model, &run) - r).abs() < 1e-12);
        // Filtered, the lattice is gone: read the resolution before decimating.
        assert_eq!(measured_resolution(&decimate(run, 4)), 0.0);
    }

    #[test]
    fn settling_follows_each_jump_down_and_pairs_within_a_second() {
        let fs = 100.0;
        let d: f64 = 0.01;
        // High (2δ) for 1 s, a jump to 0.2δ, high again from 5 s, a second jump at 6 s.
        let ln: Vec<f64> = (0..1000)
            .map(|i| {
                if i < 100 || (500..600).contains(&i) {
                    (2.0 * d).ln()
                } else {
                    (0.2 * d).ln()
                }
            })
            .collect();
        let w = settling(&ln, fs, d, 2.0);
        assert_eq!(w, vec![(100, 300), (600, 800)]);
        // Both climbs onto the high branch are jump-ups.
        assert_eq!(jump_ups(&ln, d), vec![(0, 0), (500, 500)]);
        // A climb through invalid samples starts after the last sample below the band.
        let mut climb = ln.clone();
        climb[498] = f64::NAN;
        climb[499] = (0.9 * d).ln();
        climb[500] = f64::NAN;
        climb[501] = (2.0 * d).ln();
        assert_eq!(jump_ups(&climb[..600], d), vec![(0, 0), (498, 501)]);
        // A partner 0.5 s later widens the window; one 3 s later pairs with nothing.
        let flags = paired_settling(&w, &[(150, 350), (900, 1000)], 100);
        assert!(flags[100] && flags[349] && !flags[350]);
        assert!(!flags.get(600).copied().unwrap_or(false));
    }
}
