//! `skelid simulate`: a rig model under a chosen drive, written as a campaign archive.

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use skelid::campaign::{write_campaign, Attr};
use skelid::ingest::{Archive, IngestOptions};
use skelid::model::RigModel;
use skelid::simulate::{simulate, Drive, Excitation, Rolloff, SimSettings};
use std::path::PathBuf;

use super::gap::warn_model;

#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum ExcitationKind {
    /// Linear chirp from --f0 to --f1 over --duration, with optional servo roll-off.
    Chirp,
    /// Phase-continuous stepped sine over --steps, --dwell seconds each.
    Stepped,
    /// Free decay from --initial-offset (no input channel).
    Free,
    /// The input channel of a measured run (--measured ARCHIVE --measured-run PATH).
    Measured,
}

#[derive(Args)]
pub(crate) struct SimulateArgs {
    /// Rig model (TOML, FORMATS.md §2).
    #[arg(long, value_name = "RIG.toml")]
    pub(crate) model: PathBuf,
    /// Campaign archive to write (HDF5).
    #[arg(long, value_name = "FILE.h5")]
    pub(crate) out: PathBuf,
    /// Group path of the run in the archive.
    #[arg(long, default_value = "/runs/run_001", value_name = "PATH")]
    pub(crate) run_path: String,
    /// What drives the rig.
    #[arg(long, value_enum, default_value = "chirp")]
    pub(crate) excitation: ExcitationKind,
    /// Drive the mass with a force (m y'' + c y' + k D(y) = f) instead of the base.
    #[arg(long)]
    pub(crate) force_input: bool,
    /// Chirp start frequency, Hz.
    #[arg(allow_negative_numbers = true, long, default_value_t = 0.0)]
    pub(crate) f0: f64,
    /// Chirp end frequency, Hz.
    #[arg(allow_negative_numbers = true, long, default_value_t = 12.0)]
    pub(crate) f1: f64,
    /// Duration of the run (and of the chirp), s.
    #[arg(allow_negative_numbers = true, long, default_value_t = 30.0)]
    pub(crate) duration: f64,
    /// Drive amplitude (rad for base motion, N for force input).
    #[arg(allow_negative_numbers = true, long, default_value_t = 0.03)]
    pub(crate) amplitude: f64,
    /// Servo roll-off corner, Hz: the amplitude falls as 1/sqrt(1+(f/fc)^(2n)) (0 = none).
    #[arg(
        allow_negative_numbers = true,
        long,
        default_value_t = 0.0,
        value_name = "HZ"
    )]
    pub(crate) rolloff_hz: f64,
    /// Servo roll-off order n.
    #[arg(long, default_value_t = 1)]
    pub(crate) rolloff_order: u32,
    /// Stepped-sine frequencies, Hz, comma-separated.
    #[arg(
        allow_negative_numbers = true,
        long,
        value_delimiter = ',',
        default_value = "2,4,6,8,10"
    )]
    pub(crate) steps: Vec<f64>,
    /// Stepped-sine dwell per frequency, s.
    #[arg(allow_negative_numbers = true, long, default_value_t = 5.0)]
    pub(crate) dwell: f64,
    /// Free decay: initial link offset, rad.
    #[arg(allow_negative_numbers = true, long, default_value_t = 0.05)]
    pub(crate) initial_offset: f64,
    /// Measured input: the archive holding it.
    #[arg(long, value_name = "ARCHIVE")]
    pub(crate) measured: Option<PathBuf>,
    /// Measured input: the run whose input channel drives the simulation.
    #[arg(long, value_name = "PATH")]
    pub(crate) measured_run: Option<String>,
    /// Measured input: zero-phase low-pass cut-off as a fraction of Nyquist (1 = none),
    /// so that encoder noise is not differentiated into the base acceleration.
    #[arg(allow_negative_numbers = true, long, default_value_t = skelid::simulate::MEASURED_INPUT_CUTOFF, value_name = "FRACTION")]
    pub(crate) input_cutoff: f64,
    /// Output sample rate, Hz (a measured input keeps its own).
    #[arg(allow_negative_numbers = true, long, default_value_t = 1000.0)]
    pub(crate) sample_rate: f64,
    /// RK4 sub-steps per sample (events are located exactly in any case).
    #[arg(long, default_value_t = 4)]
    pub(crate) substeps: usize,
    /// Std of white measurement noise on both channels (rad, or N for a force input).
    #[arg(allow_negative_numbers = true, long, default_value_t = 0.0)]
    pub(crate) noise: f64,
    /// Noise seed.
    #[arg(long, default_value_t = 1)]
    pub(crate) seed: u64,
    /// Write gzip-compressed, chunked datasets.
    #[arg(long)]
    pub(crate) compress: bool,
}

/// Refuses drive values no simulation can use, before anything is read or written: a
/// campaign of 0 samples, or a chirp above the Nyquist frequency, would be written and only
/// found out by `inspect` or `run`.
fn check_drive(a: &SimulateArgs) -> Result<()> {
    let positive = |flag: &str, v: f64, unit: &str| {
        if v.is_finite() && v > 0.0 {
            Ok(())
        } else {
            bail!("--{flag} {v}: must be a positive number of {unit} (nothing was written)")
        }
    };
    let below_nyquist = |flag: &str, f: f64| {
        let nyquist = 0.5 * a.sample_rate;
        if f.is_finite() && f >= 0.0 && f < nyquist {
            Ok(())
        } else {
            bail!(
                "--{flag} {f} Hz: must be at least 0 and below the Nyquist frequency, {nyquist} Hz \
                 at --sample-rate {} (raise --sample-rate, or lower the frequency; nothing was \
                 written)",
                a.sample_rate
            )
        }
    };
    // 0 is a run of noise alone (with --noise), which a user may want.
    let non_negative_amplitude = || {
        if a.amplitude.is_finite() && a.amplitude >= 0.0 {
            Ok(())
        } else {
            bail!(
                "--amplitude {}: must be 0 or more, rad (N for a force input) (nothing was \
                 written)",
                a.amplitude
            )
        }
    };
    if a.substeps == 0 {
        bail!("--substeps 0: the integrator needs at least 1 step a sample (nothing was written)");
    }
    if !(a.noise.is_finite() && a.noise >= 0.0) {
        bail!(
            "--noise {}: a standard deviation is 0 or more (nothing was written)",
            a.noise
        );
    }
    if !matches!(a.excitation, ExcitationKind::Measured) {
        positive("sample-rate", a.sample_rate, "Hz")?;
    }
    match a.excitation {
        ExcitationKind::Chirp => {
            positive("duration", a.duration, "seconds")?;
            non_negative_amplitude()?;
            below_nyquist("f0", a.f0)?;
            below_nyquist("f1", a.f1)?;
            if !(a.rolloff_hz.is_finite() && a.rolloff_hz >= 0.0) {
                bail!(
                    "--rolloff-hz {}: a corner is 0 (none) or more Hz (nothing was written)",
                    a.rolloff_hz
                );
            }
        }
        ExcitationKind::Stepped => {
            positive("dwell", a.dwell, "seconds")?;
            non_negative_amplitude()?;
            for &f in &a.steps {
                below_nyquist("steps", f)?;
            }
        }
        ExcitationKind::Free => {
            positive("duration", a.duration, "seconds")?;
            if !a.initial_offset.is_finite() {
                bail!(
                    "--initial-offset {}: must be a finite number of rad (nothing was written)",
                    a.initial_offset
                );
            }
        }
        ExcitationKind::Measured => {
            if !(a.input_cutoff > 0.0 && a.input_cutoff <= 1.0) {
                bail!(
                    "--input-cutoff {}: a fraction of Nyquist in (0, 1] (1 = no low-pass; nothing \
                     was written)",
                    a.input_cutoff
                );
            }
        }
    }
    Ok(())
}

/// Refuses a simulated response that left f64's range: an archive skelid's own reader
/// refuses (it wrote one, silently, before 2026-12-07). Where the model has a softening
/// cubic term (and no joint, whose slip would move the spring), says where its restoring
/// force vanishes and how far the motion got.
fn refuse_diverged(
    path: &std::path::Path,
    model: &RigModel,
    sim: &skelid::simulate::SimOutput,
    fs: f64,
    measured: bool,
) -> Result<()> {
    let Some(i) = sim.output.iter().position(|v| !v.is_finite()) else {
        return Ok(());
    };
    let e = &model.effects;
    let unit = skelid::model::key_unit_of("clearance", model.kind).unwrap_or("");
    let hint = match (e.cubic_stiffness, e.microslip) {
        (Some(c), None) => c.vanishes_at(model.stiffness).map(|d| {
            let offset = e
                .get(skelid::model::EffectKind::AsymmetricClearance)
                .unwrap_or(0.0);
            let edge = model.half_gap() + d;
            let passed = sim
                .relative
                .iter()
                .position(|z| (z - offset).abs() > edge)
                .map_or(String::new(), |j| {
                    format!("; the motion passed it at t = {:.3} s", j as f64 / fs)
                });
            format!(
                " (its softening cubic term: the restoring force stiffness·D + k3·D³ on the \
                 penetration D past the clearance's flank vanishes at D = {d:.4e} {unit}, \
                 |z − offset| = {edge:.4e} {unit}{passed})"
            )
        }),
        _ => None,
    };
    bail!(
        "{}: the simulated response diverged at t = {:.3} s (sample {i} and on are not finite): the model is unstable under this drive{}; nothing was written. {}",
        path.display(),
        i as f64 / fs,
        hint.unwrap_or_default(),
        if measured {
            "The measured input drives it: a model that stays stable under it is needed"
        } else {
            "A smaller --amplitude (or --initial-offset, for a free decay) keeps it in range"
        }
    )
}

pub(crate) fn cmd_simulate(a: SimulateArgs) -> Result<()> {
    check_drive(&a)?;
    let model = RigModel::load(&a.model)?;
    warn_model(&a.model, &model);
    let mut fs = a.sample_rate;
    let mut duration = a.duration;
    let rolloff = (a.rolloff_hz > 0.0).then_some(Rolloff {
        corner_hz: a.rolloff_hz,
        order: a.rolloff_order,
    });
    let excitation = match a.excitation {
        ExcitationKind::Chirp => Some(Excitation::Chirp {
            f0: a.f0,
            f1: a.f1,
            duration: a.duration,
            amplitude: a.amplitude,
            rolloff,
        }),
        ExcitationKind::Stepped => {
            duration = a.dwell * a.steps.len() as f64;
            Some(Excitation::SteppedSine {
                freqs: a.steps.clone(),
                dwell: a.dwell,
                amplitude: a.amplitude,
            })
        }
        ExcitationKind::Free => None,
        ExcitationKind::Measured => {
            let (Some(file), Some(run)) = (&a.measured, &a.measured_run) else {
                bail!("--excitation measured needs --measured ARCHIVE and --measured-run PATH");
            };
            super::args::refuse_overwriting(
                "--out",
                &a.out,
                false,
                "the archive of the measured input",
                file,
            )?;
            let archive = Archive::open(file, &IngestOptions::default())?;
            let entry = archive
                .runs
                .iter()
                .find(|r| &r.path == run)
                .with_context(|| {
                    format!("{}: no run {run} (see `skelid inspect`)", file.display())
                })?;
            let meta = entry.meta.clone()?;
            let loaded = archive.load(&meta)?;
            let input = loaded
                .input
                .with_context(|| format!("{run} is a free decay: it has no input channel"))?;
            fs = meta.sample_rate;
            duration = meta.duration;
            let cutoff = a.input_cutoff * 0.5 * fs;
            Some(Excitation::measured(&input, fs, cutoff))
        }
    };
    // A force model is driven by a force whether or not --force-input says so.
    let force_input = a.force_input || model.kind == skelid::model::ModelKind::Force;
    let drive = match (excitation, force_input) {
        (None, _) => Drive::Free {
            initial_offset: a.initial_offset,
        },
        (Some(e), false) => Drive::Base(e),
        (Some(e), true) => Drive::Force(e),
    };
    let settings = SimSettings {
        sample_rate: fs,
        duration,
        substeps: a.substeps,
        output_noise: a.noise,
        input_noise: a.noise,
        seed: a.seed,
    };
    let sim = simulate(&model, &drive, &settings);
    let measured = matches!(a.excitation, ExcitationKind::Measured);
    refuse_diverged(&a.model, &model, &sim, fs, measured)?;
    let events = sim.events;
    let samples = sim.time.len();
    let description = format!("skelid simulate of {}", a.model.display());
    let run = skelid::rig::run_data(&a.run_path, &model, &drive, sim, fs, &description);
    let root = vec![(
        "generator".to_string(),
        Attr::Text(format!("skelid {}", env!("CARGO_PKG_VERSION"))),
    )];
    write_campaign(&a.out, &root, &[run], a.compress)?;
    println!(
        "wrote {} run {} ({} samples at {} Hz, {} events located)",
        a.out.display(),
        a.run_path,
        samples,
        fs,
        events
    );
    Ok(())
}
