//! The `skelid` command line.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};
use rayon::prelude::*;

use skelid::campaign::{write_campaign, Attr, RunData};
use skelid::ingest::{expand_inputs, Archive, IngestOptions};
use skelid::model::RigModel;
use skelid::simulate::{simulate, Drive, Excitation, Rolloff, SimSettings};
use skelid::{demo, inspect};

/// Identify non-linear joints (clearance, contact stiffness, viscous and dry friction) from
/// vibration test campaigns with skeleton methods, and explain why a rig's simulation does
/// not match its measurements.
#[derive(Parser)]
#[command(name = "skelid", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// List the runs of campaign archives (path, samples, rate, kind, quantities,
    /// attributes) and every problem found; exit status 1 if any.
    Inspect(InspectArgs),
    /// Simulate the rig model of a TOML file under a chosen drive and write a campaign archive.
    Simulate(SimulateArgs),
    /// Write the built-in demo campaign (the paper's rig plus one variant per effect) and list it.
    Demo(DemoArgs),
    /// Internal: inspect one archive in this (child) process and print JSON.
    #[command(name = "__inspect-one", hide = true)]
    InspectOne {
        file: PathBuf,
        #[command(flatten)]
        ingest: IngestArgs,
    },
}

/// Options for archives laid out differently from the skelid-campaign/1 format.
#[derive(Args, Clone)]
struct IngestArgs {
    /// Name of the input (drive or force) dataset inside each run group.
    #[arg(long, default_value = "input", value_name = "NAME")]
    input_name: String,
    /// Name of the output (response) dataset inside each run group.
    #[arg(long, default_value = "output", value_name = "NAME")]
    output_name: String,
    /// Sample rate in Hz for every run, overriding `sample_rate` attributes and `time` datasets.
    #[arg(long, value_name = "HZ")]
    sample_rate: Option<f64>,
    /// Only runs whose group path matches this glob, e.g. '/sine_sweep/level_[1-3]'.
    #[arg(long, value_name = "GLOB")]
    run_glob: Option<String>,
}

impl IngestArgs {
    fn options(&self) -> Result<IngestOptions> {
        let run_glob = match &self.run_glob {
            Some(g) => Some(
                glob::Pattern::new(g)
                    .with_context(|| format!("--run-glob {g}: not a valid glob"))?,
            ),
            None => None,
        };
        if let Some(fs) = self.sample_rate {
            if !(fs.is_finite() && fs > 0.0) {
                bail!("--sample-rate {fs}: must be a positive number of Hz");
            }
        }
        Ok(IngestOptions {
            input_name: self.input_name.clone(),
            output_name: self.output_name.clone(),
            sample_rate: self.sample_rate,
            run_glob,
        })
    }
}

#[derive(Args)]
struct InspectArgs {
    /// Campaign archives: files, folders (searched for .h5/.hdf5/.mat) or glob patterns.
    #[arg(required = true, value_name = "ARCHIVE")]
    archives: Vec<String>,
    /// Print JSON instead of a table (one object per archive, runs and problems inside).
    #[arg(long)]
    json: bool,
    /// Seconds allowed to read one archive before it is reported as unreadable.
    #[arg(long, default_value_t = 300, value_name = "S")]
    timeout: u64,
    #[command(flatten)]
    ingest: IngestArgs,
}

#[derive(Clone, Copy, ValueEnum)]
enum ExcitationKind {
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
struct SimulateArgs {
    /// Rig model (TOML, FORMATS.md §2).
    #[arg(long, value_name = "RIG.toml")]
    model: PathBuf,
    /// Campaign archive to write (HDF5).
    #[arg(long, value_name = "FILE.h5")]
    out: PathBuf,
    /// Group path of the run in the archive.
    #[arg(long, default_value = "/runs/run_001", value_name = "PATH")]
    run_path: String,
    /// What drives the rig.
    #[arg(long, value_enum, default_value = "chirp")]
    excitation: ExcitationKind,
    /// Drive the mass with a force (m y'' + c y' + k D(y) = f) instead of the base.
    #[arg(long)]
    force_input: bool,
    /// Chirp start frequency, Hz.
    #[arg(long, default_value_t = 0.0)]
    f0: f64,
    /// Chirp end frequency, Hz.
    #[arg(long, default_value_t = 12.0)]
    f1: f64,
    /// Duration of the run (and of the chirp), s.
    #[arg(long, default_value_t = 30.0)]
    duration: f64,
    /// Drive amplitude (rad for base motion, N for force input).
    #[arg(long, default_value_t = 0.03)]
    amplitude: f64,
    /// Servo roll-off corner, Hz: the amplitude falls as 1/sqrt(1+(f/fc)^(2n)) (0 = none).
    #[arg(long, default_value_t = 0.0, value_name = "HZ")]
    rolloff_hz: f64,
    /// Servo roll-off order n.
    #[arg(long, default_value_t = 1)]
    rolloff_order: u32,
    /// Stepped-sine frequencies, Hz, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "2,4,6,8,10")]
    steps: Vec<f64>,
    /// Stepped-sine dwell per frequency, s.
    #[arg(long, default_value_t = 5.0)]
    dwell: f64,
    /// Free decay: initial link offset, rad.
    #[arg(long, default_value_t = 0.05)]
    initial_offset: f64,
    /// Measured input: the archive holding it.
    #[arg(long, value_name = "ARCHIVE")]
    measured: Option<PathBuf>,
    /// Measured input: the run whose input channel drives the simulation.
    #[arg(long, value_name = "PATH")]
    measured_run: Option<String>,
    /// Measured input: zero-phase low-pass cut-off as a fraction of Nyquist (1 = none),
    /// so that encoder noise is not differentiated into the base acceleration.
    #[arg(long, default_value_t = 0.1, value_name = "FRACTION")]
    input_cutoff: f64,
    /// Output sample rate, Hz (a measured input keeps its own).
    #[arg(long, default_value_t = 1000.0)]
    sample_rate: f64,
    /// RK4 sub-steps per sample (events are located exactly in any case).
    #[arg(long, default_value_t = 4)]
    substeps: usize,
    /// Std of white measurement noise on both channels (rad, or N for a force input).
    #[arg(long, default_value_t = 0.0)]
    noise: f64,
    /// Noise seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Write gzip-compressed, chunked datasets.
    #[arg(long)]
    compress: bool,
}

#[derive(Args)]
struct DemoArgs {
    /// Output folder; the campaign is written to DIR/demo_campaign.h5.
    #[arg(long, default_value = "demo-out", value_name = "DIR")]
    out: PathBuf,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Inspect(a) => cmd_inspect(a),
        Command::Simulate(a) => cmd_simulate(a).map(|_| ExitCode::SUCCESS),
        Command::Demo(a) => cmd_demo(a),
        Command::InspectOne { file, ingest } => ingest.options().and_then(|o| {
            let report = inspect::inspect_archive(&file, &o);
            println!("{}", serde_json::to_string(&report)?);
            Ok(ExitCode::SUCCESS)
        }),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}

fn cmd_inspect(a: InspectArgs) -> Result<ExitCode> {
    let options = a.ingest.options()?;
    let files = expand_inputs(&a.archives).map_err(anyhow::Error::msg)?;
    let reports = inspect::inspect_isolated(
        &self_exe()?,
        &files,
        &options,
        std::time::Duration::from_secs(a.timeout),
    );
    if a.json {
        println!("{}", serde_json::to_string_pretty(&reports)?);
    } else {
        print!("{}", inspect::render_table(&reports));
    }
    let problems: usize = reports.iter().map(|r| r.problems()).sum();
    Ok(if problems > 0 {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    })
}

fn cmd_simulate(a: SimulateArgs) -> Result<()> {
    let model = RigModel::load(&a.model)?;
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
    let drive = match (excitation, a.force_input) {
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
    let events = sim.events;
    let samples = sim.time.len();
    let description = format!("skelid simulate of {}", a.model.display());
    let run = demo::run_data(&a.run_path, &model, &drive, sim, fs, &description);
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

fn cmd_demo(a: DemoArgs) -> Result<ExitCode> {
    let cases = demo::cases();
    let bar = indicatif::ProgressBar::new(cases.len() as u64).with_style(
        indicatif::ProgressStyle::with_template(
            "simulating demo campaign {bar:30} {pos}/{len} runs {elapsed}",
        )
        .expect("static template"),
    );
    let runs: Vec<RunData> = cases
        .par_iter()
        .map(|c| {
            let r = demo::simulate_case(c);
            bar.inc(1);
            r
        })
        .collect();
    bar.finish_and_clear();
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create output folder {}", a.out.display()))?;
    let path = a.out.join("demo_campaign.h5");
    let root = vec![(
        "campaign".to_string(),
        Attr::Text(
            "skelid demo: the paper's backlash rig and its effect variants (simulated)".into(),
        ),
    )];
    write_campaign(&path, &root, &runs, true)?;
    println!("wrote {}\n", path.display());
    let reports = inspect::inspect(&[path], &IngestOptions::default());
    print!("{}", inspect::render_table(&reports));
    Ok(ExitCode::SUCCESS)
}

fn self_exe() -> Result<PathBuf> {
    std::env::current_exe().context("cannot locate the skelid executable to isolate HDF5 reads")
}
