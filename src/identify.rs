//! One run through the identification: its channels conditioned ([`crate::condition`]: mode
//! band, displacement), the instantaneous characteristics of input and response, ForceVib,
//! skeleton, fits.

use std::f64::consts::PI;

use crate::backend::Backend;
use crate::condition::{self, Channels, ConditionError, Conditioned};
use crate::fit::{self, Bin, DeadZoneFit, Estimate, Sample};
use crate::forcevib::{self, Modal};
use crate::mode::{ModeBand, ModeChoice};
use crate::run::{Run, RunKind};
use crate::track::{track_hilbert, HilbertOptions, Method, Track, TrackError, WaveletOptions};

/// Why a run could not be identified.
#[derive(Debug, thiserror::Error)]
pub enum IdentifyError {
    /// The run lacks something the identification needs.
    #[error("{0}")]
    Unusable(String),
    /// A channel could not be tracked.
    #[error("{channel} channel: {source}")]
    Track {
        /// Which channel.
        channel: &'static str,
        /// Why.
        source: TrackError,
    },
    /// Too little valid data for a skeleton.
    #[error("{0}")]
    NoSkeleton(String),
}

impl From<ConditionError> for IdentifyError {
    /// The same words either way: conditioning is the identification's first stage.
    fn from(e: ConditionError) -> Self {
        match e {
            ConditionError::Unusable(s) => IdentifyError::Unusable(s),
            ConditionError::Band { channel, source } => IdentifyError::Track { channel, source },
        }
    }
}

/// Amplitudes below this fraction of the half-gap are free play: the orbit model first
/// touches at 8δ/π² ≈ 0.81δ.
const FREE_PLAY: f64 = 0.7;

/// Options of the identification.
#[derive(Debug, Clone, serde::Serialize)]
pub struct IdentifyOptions {
    /// Wavelet method options (band chosen per channel unless given).
    pub wavelet: WaveletOptions,
    /// Hilbert low-pass cut-off (fraction of Nyquist); the paper's 0.005 by default.
    pub hilbert_cutoff: Option<f64>,
    /// Amplitude bins of the skeleton.
    pub bins: usize,
    /// Resonance band for the backbone fit of a non-linear joint: samples with
    /// |ω/ω0 − 1| below this (README, "Identification").
    pub resonance: f64,
    /// Backbone curve of the dead-zone fit; `None` picks the periodic orbit for forced runs
    /// and the describing function for free decays (README, "Identification").
    pub backbone: Option<fit::BackboneModel>,
    /// Simulations per half of the simulation-refined identification of base-motion runs
    /// ([`crate::refine`]); `None`: the skeleton estimates only.
    pub refine: Option<usize>,
    /// Which mode to isolate before tracking ([`crate::mode`]).
    pub mode: ModeChoice,
}

impl Default for IdentifyOptions {
    fn default() -> Self {
        Self {
            wavelet: WaveletOptions::default(),
            hilbert_cutoff: Some(0.005),
            bins: 40,
            resonance: 0.1,
            backbone: None,
            refine: None,
            mode: ModeChoice::default(),
        }
    }
}

impl IdentifyOptions {
    /// Refuses impossible values before any run is touched: the wavelet options
    /// ([`WaveletOptions::validate`]), fewer than 2 skeleton bins, and a Hilbert cut-off or
    /// resonance band that is not a fraction in (0, 1).
    pub fn validate(&self) -> Result<(), String> {
        self.wavelet.validate()?;
        self.mode.validate()?;
        if let Some(n) = self.refine {
            if n < 10 {
                return Err(format!(
                    "{n} refinement simulations: a simplex over six parameters needs at least 10"
                ));
            }
        }
        if self.bins < 2 {
            return Err(format!(
                "{} amplitude bins: the skeleton needs at least 2",
                self.bins
            ));
        }
        if let Some(c) = self.hilbert_cutoff {
            if !(c > 0.0 && c < 1.0) {
                return Err(format!(
                    "Hilbert cut-off {c} must be a fraction of Nyquist in (0, 1), e.g. 0.005"
                ));
            }
        }
        if !(self.resonance > 0.0 && self.resonance < 1.0) {
            return Err(format!(
                "resonance band {} must be a fraction in (0, 1), e.g. 0.1 for ±10 % around ω0",
                self.resonance
            ));
        }
        Ok(())
    }
}

/// Everything one method found on one run.
#[derive(Debug, Clone)]
pub struct Identification {
    /// Method used.
    pub method: Method,
    /// Input channel's track (none for a free decay).
    pub input: Option<Track>,
    /// The identified channel's track (z = y − x for base motion, y otherwise).
    pub response: Track,
    /// ω0²(t), h0(t).
    pub modal: Modal,
    /// Samples used for the skeleton.
    pub used: Vec<bool>,
    /// The skeleton.
    pub bins: Vec<Bin>,
    /// The skeleton of the samples at resonance (|ω/ω0 − 1| < `resonance`).
    pub resonant_bins: Vec<Bin>,
    /// Dead-zone fit (half-gap and k/J).
    pub dead_zone: Option<DeadZoneFit>,
    /// Whether the dead-zone fit used `resonant_bins` (a joint with free play) rather than
    /// `bins` (a linear one).
    pub fitted_at_resonance: bool,
    /// The paper's extrapolated half-gap and the amplitude range it used.
    pub extrapolated: Option<(Estimate, (f64, f64))>,
    /// Viscous c/J (1/s) and Coulomb F/J (units/s²).
    pub damping: Option<(Estimate, Estimate)>,
    /// Mass or inertia used by ForceVib (force runs), and whether it was estimated.
    pub mass: Option<(f64, bool)>,
    /// Warnings for the user (partial skeleton, estimated mass, …).
    pub warnings: Vec<String>,
    /// The band the mode was isolated in before tracking (`None`: the whole record).
    pub mode: Option<ModeBand>,
    /// The resonance band it was identified with ([`IdentifyOptions::resonance`]).
    pub resonance: f64,
}

impl Identification {
    /// Total clearance 2δ from the exact fit.
    pub fn clearance(&self) -> Option<Estimate> {
        self.dead_zone.map(|f| Estimate {
            value: 2.0 * f.half_gap.value,
            stderr: 2.0 * f.half_gap.stderr,
        })
    }
    /// Total clearance the paper's way (2 × the extrapolated intercept).
    pub fn clearance_extrapolated(&self) -> Option<Estimate> {
        self.extrapolated.map(|(e, _)| Estimate {
            value: 2.0 * e.value,
            stderr: 2.0 * e.stderr,
        })
    }
    /// Whether sample `i` is at resonance, |ω/ω0 − 1| below `tol`.
    pub fn at_resonance(&self, i: usize, tol: f64) -> bool {
        at_resonance(&self.response, &self.modal, i, tol)
    }
    /// Whether sample `i` was used and is at resonance within the band it was identified
    /// with: the samples its backbone fit saw.
    pub fn resonant(&self, i: usize) -> bool {
        self.used[i] && self.at_resonance(i, self.resonance)
    }
    /// The skeleton, in `bins` bins, of the samples `mask` keeps (every sample where
    /// `None`): those at resonance, as [`Identification::resonant_bins`] takes them, or
    /// every used one where fewer than 100 are. With no mask it is `resonant_bins` (or
    /// `bins` where that is empty); a fit that sees part of a run reads its start off
    /// that part alone.
    pub fn skeleton_within(&self, mask: Option<&[bool]>, bins: usize) -> Vec<Bin> {
        let n = self.used.len().min(self.response.len());
        let kept = |i: &usize| mask.is_none_or(|m| m.get(*i).copied().unwrap_or(false));
        let skeleton = |v: &[Sample]| fit::skeleton(v, bins, min_bin_count(v.len(), bins));
        let sample = |i: usize| sample_at(&self.response, &self.modal, i);
        let resonant: Vec<Sample> = (0..n)
            .filter(kept)
            .filter(|&i| self.resonant(i))
            .map(sample)
            .collect();
        if resonant.len() >= 100 {
            return skeleton(&resonant);
        }
        let used: Vec<Sample> = (0..n)
            .filter(kept)
            .filter(|&i| self.used[i])
            .map(sample)
            .collect();
        skeleton(&used)
    }

    /// Amplitude range covered by the skeleton.
    pub fn amplitude_range(&self) -> Option<(f64, f64)> {
        fit::amplitude_range(&self.bins)
    }

    /// The skeleton at its largest amplitude: that bin's amplitude (signal units), natural
    /// frequency (Hz) and damping ratio ζ = h0/ω0 (NaN where its stiffness is not positive).
    pub fn at_largest_amplitude(&self) -> Option<AtLargest> {
        let b = self
            .bins
            .iter()
            .max_by(|a, b| a.amplitude.total_cmp(&b.amplitude))?;
        Some(AtLargest {
            amplitude: b.amplitude,
            frequency: b.natural_frequency(),
            damping_ratio: if b.stiffness > 0.0 {
                0.5 * b.damping / b.stiffness.sqrt()
            } else {
                f64::NAN
            },
        })
    }
}

/// The skeleton at its largest amplitude ([`Identification::at_largest_amplitude`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct AtLargest {
    /// The bin's amplitude (signal units).
    pub amplitude: f64,
    /// Natural frequency there (Hz).
    pub frequency: f64,
    /// Damping ratio there (1).
    pub damping_ratio: f64,
}

/// Whether sample `i` is at resonance: |ω/ω0 − 1| below `tol`.
fn at_resonance(response: &Track, modal: &Modal, i: usize, tol: f64) -> bool {
    let k = modal.stiffness[i];
    k > 0.0 && (2.0 * PI * response.frequency[i] / k.sqrt() - 1.0).abs() < tol
}

/// Sample `i` of the instantaneous characteristics, for a skeleton.
fn sample_at(response: &Track, modal: &Modal, i: usize) -> Sample {
    Sample {
        amplitude: response.amplitude[i],
        omega: 2.0 * PI * response.frequency[i],
        stiffness: modal.stiffness[i],
        damping: modal.damping[i],
    }
}

/// A bin needs 1/20 of its even share of the samples (at least 5) to be kept.
fn min_bin_count(samples: usize, bins: usize) -> usize {
    (samples / (20 * bins.max(1))).max(5)
}

/// A band-passed drive is nearly zero while a sweep is outside the band, where the ratio of
/// response to force is noise over noise: those samples are not valid (the Hilbert track
/// has no noise floor of its own to say so). The drive counts as outside the band below a
/// quarter of its 99th-percentile envelope.
fn drive_outside_band(tf: &mut Track) {
    let mut a: Vec<f64> = tf
        .amplitude
        .iter()
        .zip(&tf.valid)
        .filter(|(a, &v)| v && a.is_finite())
        .map(|(a, _)| *a)
        .collect();
    if a.is_empty() {
        return;
    }
    let k = ((a.len() - 1) as f64 * 0.99) as usize;
    let (_, &mut p99, _) = a.select_nth_unstable_by(k, |x, y| x.total_cmp(y));
    for (v, &amp) in tf.valid.iter_mut().zip(&tf.amplitude) {
        *v &= amp >= 0.25 * p99;
    }
}

fn track(
    x: &[f64],
    fs: f64,
    method: Method,
    ctx: &Identifier,
    guide: Option<&Track>,
    channel: &'static str,
) -> Result<Track, IdentifyError> {
    let t0 = crate::profile::thread_cpu();
    let opt = ctx.options;
    let r = match method {
        Method::Wavelet => {
            ctx.backend
                .track_wavelet(x, fs, &opt.wavelet, guide.map(|g| g.frequency.as_slice()))
        }
        Method::Hilbert => track_hilbert(
            x,
            fs,
            &HilbertOptions {
                cutoff: opt.hilbert_cutoff,
            },
        ),
    };
    TRACKED.with(|t| t.set(t.get() + crate::profile::thread_cpu().saturating_sub(t0)));
    r.map_err(|source| IdentifyError::Track { channel, source })
}

thread_local! {
    /// CPU time this thread spent in [`track`], so that the identification's own share
    /// (ForceVib and the fits) can be told apart for the profile.
    static TRACKED: std::cell::Cell<std::time::Duration> = const { std::cell::Cell::new(std::time::Duration::ZERO) };
}

/// Identifies one loaded run with one method, the wavelet transform's first pass on
/// `backend` (chosen once, by the caller: see [`crate::backend`]).
pub fn identify(
    run: &Run,
    method: Method,
    opt: &IdentifyOptions,
    backend: &Backend,
) -> Result<Identification, IdentifyError> {
    Identifier {
        options: opt,
        backend,
    }
    .identify(run, method)
}

/// The user's identification options and the backend, handed together to the stages that
/// identify runs of their own (the gap's simulations, the refinement).
#[derive(Clone, Copy)]
pub struct Identifier<'a> {
    /// Options, as the user gave them.
    pub options: &'a IdentifyOptions,
    /// Where the wavelet transform's first pass runs.
    pub backend: &'a Backend,
}

impl Identifier<'_> {
    /// Identifies one loaded run with one method.
    pub fn identify(&self, run: &Run, method: Method) -> Result<Identification, IdentifyError> {
        identify_profiled(run, method, self, None)
    }

    /// [`identify`](Self::identify) for a base-motion run whose input channel was already
    /// tracked (`input`): a simulation driven by a measured input needs only its response
    /// tracked, which halves the cost of each gap evaluation.
    pub fn identify_with_input_track(
        &self,
        run: &Run,
        method: Method,
        input: &Track,
    ) -> Result<Identification, IdentifyError> {
        identify_profiled(run, method, self, Some(input))
    }
}

/// The identification, its CPU time split between the tracks and the rest for the profile.
fn identify_profiled(
    run: &Run,
    method: Method,
    ctx: &Identifier,
    known_input: Option<&Track>,
) -> Result<Identification, IdentifyError> {
    let before = TRACKED.with(|t| t.get());
    let t0 = crate::profile::thread_cpu();
    let r = identify_run(run, method, ctx, known_input);
    let tracks = TRACKED.with(|t| t.get()) - before;
    crate::profile::add(
        crate::profile::Stage::ForceVibFit,
        crate::profile::thread_cpu()
            .saturating_sub(t0)
            .saturating_sub(tracks),
    );
    r
}

/// A run through conditioning, tracks, ForceVib, skeleton and fits.
fn identify_run(
    run: &Run,
    method: Method,
    ctx: &Identifier,
    known_input: Option<&Track>,
) -> Result<Identification, IdentifyError> {
    let meta = &run.meta;
    let fs = meta.sample_rate;
    let Conditioned { band, channels } = condition::condition(run, ctx.options.mode)?;
    // Within a mode's band the wavelet's scales span the band alone, unless given.
    let banded;
    let within;
    let ctx = match &band {
        Some(b) => {
            let mut o = ctx.options.clone();
            o.wavelet.fmin = o.wavelet.fmin.or(Some(b.fmin));
            o.wavelet.fmax = o.wavelet.fmax.or(Some(b.fmax));
            banded = o;
            within = Identifier {
                options: &banded,
                backend: ctx.backend,
            };
            &within
        }
        None => ctx,
    };
    let opt = ctx.options;
    let mut warnings = Vec::new();
    let (input, response, modal, mass) = match channels {
        Channels::Free { response: y } => {
            let resp = track(&y, fs, method, ctx, None, "output")?;
            let modal = forcevib::free_decay(&resp);
            (None, resp, modal, None)
        }
        Channels::BaseMotion {
            input: x,
            relative: z,
        } => {
            let tx = match known_input {
                Some(t) if t.amplitude.len() == x.len() => t.clone(),
                _ => track(&x, fs, method, ctx, None, "input")?,
            };
            let tz = track(&z, fs, method, ctx, Some(&tx), "relative motion")?;
            let modal = forcevib::base_motion(&tx, &tz, meta.gravity_stiffness);
            (Some(tx), tz, modal, None)
        }
        Channels::Force {
            force: f,
            response: y,
        } => {
            let mut tf = track(&f, fs, method, ctx, None, "input")?;
            if band.is_some() {
                drive_outside_band(&mut tf);
            }
            let ty = track(&y, fs, method, ctx, Some(&tf), "output")?;
            let (m, estimated) = match meta.inertia {
                Some(m) => (m, false),
                None => {
                    let m = forcevib::estimate_mass(&tf, &ty).ok_or_else(|| {
                        IdentifyError::Unusable(
                            "no inertia attribute and the modal mass cannot be estimated from the data: set `inertia`".into(),
                        )
                    })?;
                    warnings.push(format!(
                        "no inertia attribute: modal mass estimated from the data as {m:.4e}"
                    ));
                    (m, true)
                }
            };
            let modal = forcevib::force_input(&tf, &ty, m);
            (Some(tf), ty, modal, Some((m, estimated)))
        }
    };
    let n = response.amplitude.len();
    let used: Vec<bool> = (0..n)
        .map(|i| modal.valid[i] && modal.stiffness[i].is_finite())
        .collect();
    let resonant: Vec<bool> = (0..n)
        .map(|i| used[i] && at_resonance(&response, &modal, i, opt.resonance))
        .collect();
    let sample = |i: usize| sample_at(&response, &modal, i);
    let samples: Vec<Sample> = (0..n).filter(|&i| used[i]).map(sample).collect();
    if samples.len() < 100 {
        // On the whole record of a structure, several modes share the ridge: the beam's
        // acc2 gave 0 valid samples whole, and is identified with `--mode-near 80`.
        return Err(IdentifyError::NoSkeleton(format!(
            "only {} valid samples of {n}: the response is too weak or too short to identify{}",
            samples.len(),
            if band.is_none() {
                ", or the record holds several modes: isolate one (--mode-near HZ, or --band \
                 FMIN:FMAX)"
            } else {
                ""
            }
        )));
    }
    let skeleton = |v: &[Sample]| fit::skeleton(v, opt.bins, min_bin_count(v.len(), opt.bins));
    let bins = skeleton(&samples);
    // Forcing at resonance makes up each cycle's loss, so the motion is close to the free
    // undamped orbit; a free decay loses speed over every flight through the gap, which
    // moves its first harmonic towards the describing function (README).
    let model = opt.backbone.unwrap_or(match meta.kind {
        RunKind::Free => fit::BackboneModel::DescribingFunction,
        _ => fit::BackboneModel::PeriodicOrbit,
    });
    let resonant_samples: Vec<Sample> = (0..n).filter(|&i| resonant[i]).map(sample).collect();
    let resonant_bins = if resonant_samples.len() >= 100 {
        skeleton(&resonant_samples)
    } else {
        Vec::new()
    };
    let mut dead_zone = fit::fit_dead_zone(&bins, model);
    let mut at_resonance = false;
    // A joint with free play has a backbone only at resonance: off resonance (after a
    // jump-down, say) the first-harmonic stiffness depends on the forcing. A linear joint
    // has one ω0 everywhere, and the whole sweep estimates it better.
    if let (Some(dz), Some((lo, _))) = (dead_zone, fit::amplitude_range(&bins)) {
        if dz.half_gap.value > 0.01 * lo && resonant_bins.len() >= 3 {
            if let Some(r) = fit::fit_dead_zone(&resonant_bins, model) {
                dead_zone = Some(r);
                at_resonance = true;
            }
        }
    }
    let fit_bins = if at_resonance { &resonant_bins } else { &bins };
    let extrapolated = fit::extrapolated_half_gap(fit_bins);
    // Damping from the free play (no restoring force, so ForceVib's h0 is exact whatever
    // the forcing) and from the bins the backbone was fitted on; the off-resonance contact
    // bins carry a quadrature part of the non-sinusoidal contact force.
    let damping_bins: Vec<Bin> = match dead_zone {
        Some(dz) if at_resonance => {
            let d = dz.half_gap.value;
            bins.iter()
                .filter(|b| b.amplitude < FREE_PLAY * d)
                .chain(fit_bins.iter().filter(|b| b.amplitude > d))
                .copied()
                .collect()
        }
        _ => bins.clone(),
    };
    let damping = fit::fit_damping(&damping_bins);
    if let (Some(dz), Some((lo, hi))) = (dead_zone, fit::amplitude_range(&bins)) {
        let d = dz.half_gap.value;
        if d > 0.0 && hi < 2.0 * d {
            warnings.push(format!(
                "partial skeleton: amplitudes reach {:.2}× the half-gap only (the backbone bends most below 2×, so clearance and stiffness trade off)",
                hi / d
            ));
        }
        if hi / lo < 1.3 {
            warnings.push(format!(
                "partial skeleton: the amplitude range covered is narrow ({lo:.3e} to {hi:.3e})"
            ));
        }
    }
    Ok(Identification {
        method,
        input,
        response,
        modal,
        used,
        bins,
        fitted_at_resonance: at_resonance,
        resonant_bins,
        dead_zone,
        extrapolated,
        damping,
        mass,
        warnings,
        resonance: opt.resonance,
        mode: band,
    })
}
