//! The `skelid` command line.

mod cli;

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};
use rayon::prelude::*;

use skelid::campaign::{write_campaign, Attr, RunData};
use skelid::ingest::{find_archives, Archive, FindError, IngestOptions};
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
    /// Simulate the built-in demo campaign (the paper's rig plus one variant per effect) and
    /// identify it, printing true against identified parameters.
    Demo(DemoArgs),
    /// Identify every run of campaign archives: ForceVib, skeleton curves, clearance,
    /// stiffness, viscous and Coulomb damping; writes results.h5, summary.json and
    /// summary.csv (FORMATS.md §3). Exit status 1 if any run failed.
    Run(RunArgs),
    /// Join the output folders of the shards of one `skelid run --shard K/N` into one
    /// folder (results.h5, summaries, manifest), refusing missing or doubled shards, runs in
    /// two shards and folders made with other settings.
    Merge(MergeArgs),
    /// Instantaneous envelope, frequency and phase of one dataset, by the wavelet ridge or
    /// the Hilbert transform; writes time, amplitude, frequency (Hz), valid (FORMATS.md §4).
    Track(TrackArgs),
    /// Why a rig's simulation does not match its measurements: simulates the model under each
    /// run's measured input, refits its own parameters, tries every unmodelled effect of the
    /// vocabulary on alternate time blocks and scores it on the withheld ones; writes
    /// gap.json (FORMATS.md §5), RIG.fitted.toml and gap.html. `--self-check` measures how
    /// often it names the right effect on simulated rigs.
    Gap(GapArgs),
    /// How accurate the identification is: random paper-like rigs (issue 20's ranges,
    /// encoder steps, offsets and noise) simulated and identified blind by the skeleton and
    /// by simulation refinement; prints the error table and writes validate.json.
    Validate(cli::validate::ValidateArgs),
    /// Benchmarks, each measured side by side in one run.
    Bench(BenchArgs),
    /// Internal: one benchmark measurement in this (child) process, printed as JSON.
    #[command(name = "__bench-one", hide = true)]
    BenchOne {
        file: PathBuf,
        #[arg(long, value_enum)]
        variant: skelid::bench::Variant,
        #[arg(long)]
        scales: usize,
    },
    /// Internal: inspect one archive in this (child) process and print JSON.
    #[command(name = "__inspect-one", hide = true)]
    InspectOne {
        file: PathBuf,
        #[command(flatten)]
        ingest: IngestArgs,
    },
    /// Internal: read the archives named on stdin and stream their runs to stdout (the
    /// isolated reader of `skelid run`).
    #[command(name = "__read-archives", hide = true)]
    ReadArchives {
        #[command(flatten)]
        ingest: IngestArgs,
        /// Only this share of the runs.
        #[arg(long, value_parser = skelid::batch::Shard::parse)]
        shard: Option<skelid::batch::Shard>,
    },
}

/// Options of `skelid gap`.
#[derive(Args)]
struct GapArgs {
    /// Rig model to compare with the measurements (TOML, FORMATS.md §2). Its inertia is
    /// held (unless --fit-inertia); stiffness, damping, clearance and gravity stiffness are
    /// refitted before any effect is tried.
    #[arg(long, value_name = "RIG.toml", required_unless_present = "self_check")]
    model: Option<PathBuf>,
    /// Campaign archive with the measured base-motion runs (input = base angle, output =
    /// link angle).
    #[arg(value_name = "ARCHIVE", required_unless_present = "self_check")]
    archive: Option<PathBuf>,
    /// Run group to diagnose (repeatable); every base-motion run of the archive by default.
    #[arg(long = "run", value_name = "PATH")]
    runs: Vec<String>,
    /// Output folder: gap.json, gap.html, the fitted model(s); self-check.json with
    /// --self-check.
    #[arg(long, default_value = "skelid-gap", value_name = "DIR")]
    out: PathBuf,
    /// Length of the alternate time blocks (s): fits see the even ones, gaps are scored on
    /// the odd ones.
    #[arg(long, default_value_t = 1.0, value_name = "SECONDS")]
    holdout_block: f64,
    /// Runs diagnosed at once (default: one per core). A run's own search is a chain of
    /// simplex steps, each waiting for the last, so one run keeps about one core busy;
    /// an archive of several runs is diagnosed N at a time. Each run in flight holds its
    /// record and a few simulations of it.
    #[arg(long, short, value_name = "N")]
    jobs: Option<usize>,
    /// Simulations spent refitting the model's own parameters.
    #[arg(long, default_value_t = 150, value_name = "N")]
    baseline_evaluations: usize,
    /// Simulations per refined candidate (and per pair of effects).
    #[arg(long, default_value_t = 45, value_name = "N")]
    candidate_evaluations: usize,
    /// Scan points refined by the simplex: every effect is scanned on the baseline and on
    /// the nominal model, and the best N of those 2 × 6 starts are refined (fewer is
    /// faster, and may leave an effect the baseline absorbed undetected).
    #[arg(long, default_value_t = 12, value_name = "N")]
    refine: usize,
    /// Never try pairs of effects.
    #[arg(long)]
    no_pairs: bool,
    /// Refit the inertia too (held at the model's value otherwise).
    #[arg(long)]
    fit_inertia: bool,
    /// Effects to try, comma-separated (default: the whole vocabulary).
    #[arg(long, value_delimiter = ',', value_name = "EFFECT,...")]
    effects: Vec<String>,
    /// Instead of diagnosing an archive, measure the diagnosis on simulated rigs that hide
    /// one effect (or none) from their model; prints a confusion matrix.
    #[arg(long)]
    self_check: bool,
    /// Self-check cases (the seven effects and none in turn).
    #[arg(long, default_value_t = 40, value_name = "N", requires = "self_check")]
    cases: usize,
    /// Self-check seed.
    #[arg(long, default_value_t = 1, value_name = "S", requires = "self_check")]
    seed: u64,
    /// What drives the self-check's rigs: `paper`, the paper's chirp (0 to 12 Hz in 30 s),
    /// or `two-level`, 3 to 9 Hz at the paper's rate (0.4 Hz/s) at the paper's level and
    /// then at 1.75 times it, in one 30 s record (one level maps only part of the skeleton:
    /// a hardening contact hides behind a stiffer contact and a wider clearance).
    #[arg(long, value_enum, default_value = "paper", requires = "self_check")]
    sweep: SweepArg,
    #[command(flatten)]
    ingest: IngestArgs,
}

/// The drive of the self-check's rigs.
#[derive(Clone, Copy, ValueEnum)]
enum SweepArg {
    /// The paper's chirp.
    Paper,
    /// 3 to 9 Hz at the paper's rate, at the paper's level then 1.75 times it.
    TwoLevel,
}

/// Options for archives laid out differently from the skelid-campaign/1 format.
#[derive(Args, Clone)]
struct IngestArgs {
    /// Name of the input (drive or force) dataset inside each run group; `NAME[k]` takes
    /// channel k (from 0) of a 2-D dataset, along its shorter axis.
    #[arg(long, default_value = "input", value_name = "NAME")]
    input_name: String,
    /// Name of the output (response) dataset inside each run group; `NAME[k]` takes
    /// channel k (from 0) of a 2-D dataset such as MATLAB's 3×N `Acceleration`.
    #[arg(long, default_value = "output", value_name = "NAME")]
    output_name: String,
    /// Sample rate in Hz for every run, overriding `sample_rate` attributes and `time` datasets.
    #[arg(long, value_name = "HZ")]
    sample_rate: Option<f64>,
    /// Only runs whose group path matches this glob, e.g. '/sine_sweep/level_[1-3]'.
    #[arg(long, value_name = "GLOB")]
    run_glob: Option<String>,
    /// Kind of every run, overriding `kind` attributes: base-motion (input = base
    /// displacement), force (input = force on the mass) or free (decay, no input).
    #[arg(long, value_name = "KIND", value_parser = parse_kind)]
    kind: Option<skelid::ingest::RunKind>,
    /// Inertia of every run (kg m² for a rotary rig, kg for a linear one), overriding
    /// `inertia` attributes; gives the absolute stiffness, damping and friction.
    #[arg(long, value_name = "J")]
    inertia: Option<f64>,
    /// What every run's input measures (displacement, velocity, acceleration, force),
    /// overriding `input_quantity` attributes.
    #[arg(long, value_name = "QUANTITY", value_parser = parse_quantity)]
    input_quantity: Option<skelid::ingest::Quantity>,
    /// What every run's output measures (displacement, velocity, acceleration), overriding
    /// `output_quantity` attributes.
    #[arg(long, value_name = "QUANTITY", value_parser = parse_quantity)]
    output_quantity: Option<skelid::ingest::Quantity>,
}

fn parse_kind(s: &str) -> Result<skelid::ingest::RunKind, String> {
    skelid::ingest::RunKind::parse(s)
        .ok_or_else(|| format!("{s:?}: use base-motion, force or free"))
}

fn parse_quantity(s: &str) -> Result<skelid::ingest::Quantity, String> {
    skelid::ingest::Quantity::parse(s)
        .ok_or_else(|| format!("{s:?}: use displacement, velocity, acceleration or force"))
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
        if let Some(j) = self.inertia {
            if !(j.is_finite() && j > 0.0) {
                bail!("--inertia {j}: must be a positive number (kg m² or kg)");
            }
        }
        Ok(IngestOptions {
            input_name: self.input_name.clone(),
            output_name: self.output_name.clone(),
            sample_rate: self.sample_rate,
            run_glob,
            kind: self.kind,
            inertia: self.inertia,
            input_quantity: self.input_quantity,
            output_quantity: self.output_quantity,
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
    #[arg(long, default_value_t = skelid::simulate::MEASURED_INPUT_CUTOFF, value_name = "FRACTION")]
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
    /// Also refine the base-motion runs by simulation (as `skelid run --refine`), and show
    /// the refined estimates against the truth.
    #[arg(long)]
    refine: bool,
}

#[derive(Args)]
struct MergeArgs {
    /// Output folders of `skelid run --shard K/N`, one per shard.
    #[arg(required = true, value_name = "DIR")]
    dirs: Vec<PathBuf>,
    /// Folder for the joined results.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    #[command(flatten)]
    report: ReportArgs,
}

/// Options of report.html.
#[derive(Args)]
struct ReportArgs {
    /// Runs drawn in full in report.html (tracks, backbone, forces: about 100 kB each);
    /// the summary table always lists every run.
    #[arg(long, default_value_t = 100, value_name = "N")]
    report_runs: usize,
    /// Exit with status 1 when any result is `suspect` too, not only when a run failed or
    /// a result is `bad` (for pipelines that must stop on anything doubtful).
    #[arg(long)]
    strict: bool,
}

fn cmd_merge(a: MergeArgs) -> Result<ExitCode> {
    let summary = skelid::batch::merge(&a.dirs, &a.out, a.report.report_runs)?;
    let strict = a.report.strict;
    println!(
        "merged {} folder(s): {} run(s), {} failed; wrote {}, summary.json, summary.csv, report.html, manifest.json",
        a.dirs.len(),
        summary.runs,
        summary.failed_runs,
        summary.results.display()
    );
    Ok(exit_status(&summary, strict))
}

/// 1 when a run failed or a result is `bad` (impossible values), so that schedulers see
/// it, else 0; suspect results are counted in the last line, and with `strict` give 1 too.
fn exit_status(summary: &skelid::batch::BatchSummary, strict: bool) -> ExitCode {
    let doubtful = |q: &str| q == "bad" || (strict && q == "suspect");
    if summary.failed_runs > 0 || summary.rows.iter().any(|r| doubtful(&r.quality)) {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    }
}

/// `--backbone` values.
#[derive(Clone, Copy, ValueEnum)]
enum BackboneArg {
    Auto,
    Orbit,
    DescribingFunction,
}

#[derive(Args)]
struct RunArgs {
    /// Campaign archives: files, folders (searched for .h5/.hdf5/.mat) or glob patterns.
    #[arg(required = true, value_name = "ARCHIVE")]
    archives: Vec<String>,
    /// Output folder for results.h5, summary.json and summary.csv.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Instantaneous characteristics by the wavelet ridge, the Hilbert transform, or both.
    #[arg(long, value_enum, default_value = "both")]
    method: RunMethod,
    #[command(flatten)]
    wavelet: WaveletArgs,
    /// Hilbert: zero-phase low-pass cut-off as a fraction of Nyquist (the paper's 0.005).
    #[arg(long, default_value_t = 0.005, value_name = "FRACTION")]
    cutoff: f64,
    /// Amplitude bins of the skeleton curves.
    #[arg(long, default_value_t = 40)]
    bins: usize,
    /// Resonance band of the backbone fit for a joint with free play: only samples with
    /// |ω/ω0 − 1| below this are fitted (off resonance, e.g. after a jump-down, the
    /// first-harmonic stiffness of a clearance depends on the forcing).
    #[arg(long, default_value_t = 0.1, value_name = "FRACTION")]
    resonance: f64,
    /// Backbone curve fitted to a joint with free play: `orbit` (the exact free periodic
    /// orbit, right for forced runs and lightly damped decays), `describing-function`
    /// (first harmonic of a sinusoid), or `auto` (orbit for forced runs, describing
    /// function for free decays).
    #[arg(long, value_enum, default_value = "auto")]
    backbone: BackboneArg,
    /// Also refine each base-motion run's clearance, k/J, c/J, gravity stiffness and
    /// Coulomb F/J by matching simulations to the record (README, "Simulation-refined
    /// identification"): written beside the skeleton estimates as `refined_*`, with
    /// standard errors from two independent fits (even and odd time blocks). About 5–10 s
    /// per run on 2 cores.
    #[arg(long)]
    refine: bool,
    /// Simulations per half of the refinement (two halves per run).
    #[arg(long, default_value_t = skelid::refine::EVALUATIONS, value_name = "N")]
    refine_evaluations: usize,
    /// Take only the K-th of N shares of the runs (e.g. 3/8), for N copies of skelid on a
    /// scheduler (a Slurm array). The share depends on each run's archive name and path,
    /// not on the order of the inputs; join the N output folders with `skelid merge`.
    #[arg(long, value_name = "K/N")]
    shard: Option<String>,
    /// Redo every run, even those already committed in DIR by an earlier invocation with
    /// the same data and settings (which are otherwise skipped).
    #[arg(long)]
    force: bool,
    /// No progress bar and no result table (the log is still written to DIR/skelid.log).
    #[arg(long, short)]
    quiet: bool,
    /// Progress as one JSON object per finished run on stderr (done, total, skipped,
    /// failed, suspect, bad, elapsed_s), for schedulers and dashboards.
    #[arg(long)]
    json_progress: bool,
    /// Seconds allowed to open one archive (in a child process) before it is reported failed.
    #[arg(long, default_value_t = 300, value_name = "S")]
    timeout: u64,
    /// Runs identified at once (default: one per core; 32 on a GPU backend, whose batches
    /// gather the signals of the runs in flight). Memory grows with N, not with the number
    /// of runs: each run in flight adds its working set (measured: about 12 MB for 30,000
    /// samples with both methods, on about 75 MB of base). Lower it for long records.
    #[arg(long, short, value_name = "N")]
    jobs: Option<usize>,
    #[command(flatten)]
    backend: BackendArgs,
    #[command(flatten)]
    report: ReportArgs,
    #[command(flatten)]
    ingest: IngestArgs,
}

/// The wavelet method's analysis band and mother wavelet (shared by `track` and `run`).
#[derive(Args, Clone)]
struct WaveletArgs {
    /// Wavelet: lowest analysis frequency, Hz (default: from the spectrum and the record length).
    #[arg(long, value_name = "HZ")]
    fmin: Option<f64>,
    /// Wavelet: highest analysis frequency, Hz (default: from the spectrum).
    #[arg(long, value_name = "HZ")]
    fmax: Option<f64>,
    /// Wavelet: number of log-spaced scales between --fmin and --fmax.
    #[arg(long, default_value_t = 64)]
    scales: usize,
    /// Wavelet: Morlet bandwidth f_b; larger is longer in time and finer in frequency.
    #[arg(long, default_value_t = 1.0, value_name = "FB")]
    bandwidth: f64,
    /// Wavelet: Morlet centre frequency f_c.
    #[arg(long, default_value_t = 1.0, value_name = "FC")]
    centre: f64,
}

impl WaveletArgs {
    /// These settings on top of `base`.
    fn apply(&self, base: skelid::track::WaveletOptions) -> skelid::track::WaveletOptions {
        skelid::track::WaveletOptions {
            wavelet: skelid::transform::Morlet {
                bandwidth: self.bandwidth,
                centre: self.centre,
            },
            fmin: self.fmin,
            fmax: self.fmax,
            scales: self.scales,
            ..base
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum RunMethod {
    /// Complex-Morlet ridge and bias-corrected skeleton.
    Wavelet,
    /// Analytic signal by FFT, low-passed with --cutoff.
    Hilbert,
    /// Both, side by side.
    Both,
}

impl RunMethod {
    fn methods(self) -> Vec<skelid::track::Method> {
        use skelid::track::Method;
        match self {
            RunMethod::Wavelet => vec![Method::Wavelet],
            RunMethod::Hilbert => vec![Method::Hilbert],
            RunMethod::Both => vec![Method::Wavelet, Method::Hilbert],
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum MethodArg {
    /// Complex-Morlet ridge and bias-corrected skeleton.
    Wavelet,
    /// Analytic signal by FFT (optionally low-passed with --cutoff).
    Hilbert,
}

#[derive(Args)]
struct TrackArgs {
    /// Campaign archive (HDF5).
    #[arg(value_name = "ARCHIVE")]
    archive: PathBuf,
    /// Dataset to track, e.g. /runs/run_001/output (a run group alone means its output).
    #[arg(long, value_name = "PATH")]
    dataset: String,
    /// Estimator.
    #[arg(long, value_enum, default_value = "wavelet")]
    method: MethodArg,
    /// Output file: HDF5, or CSV when the name ends in .csv.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    #[command(flatten)]
    wavelet: WaveletArgs,
    /// Samples whose ridge is below this multiple of the in-band noise are marked not valid.
    #[arg(long, default_value_t = 10.0, value_name = "X")]
    min_snr: f64,
    /// Ridge by per-sample argmax instead of the penalised dynamic programme.
    #[arg(long)]
    argmax: bool,
    /// Do not remove the window's decay/sweep bias (raw |W| and phase derivative).
    #[arg(long)]
    no_correction: bool,
    /// Hilbert only: zero-phase low-pass of A and f, cut-off as a fraction of Nyquist
    /// (the paper uses 0.0005-0.01).
    #[arg(long, value_name = "FRACTION")]
    cutoff: Option<f64>,
    /// Wavelet only: a dataset of the same run whose ridge guides this one (e.g. the input).
    #[arg(long, value_name = "PATH")]
    reference: Option<String>,
    /// Wavelet only: also write the first pass's |W| on its coarse grid (datasets
    /// `scalogram`, scales × steps, with `scalogram_frequency` in Hz and `scalogram_time` in
    /// s) to the HDF5 output; on a GPU this is the only time the scalogram is read back.
    #[arg(long)]
    keep_scalogram: bool,
    #[command(flatten)]
    backend: BackendArgs,
    #[command(flatten)]
    ingest: IngestArgs,
}

#[derive(Args, Clone, Copy)]
struct BackendArgs {
    /// Where the wavelet transform's first pass (the band-limited Morlet transform at every
    /// scale and the ridge search) runs. `auto`: a hardware GPU when wgpu opens one, else
    /// the CPU (a software adapter such as lavapipe is passed over: it is slower than the
    /// CPU backend). `gpu`: any adapter, lavapipe included, or an error when none opens.
    /// `cpu`: rustfft and rayon only. A signal the GPU cannot take (beyond the adapter's
    /// limits, or a device lost mid-batch) is done on the CPU with a warning; results.h5
    /// records per run which backend did the work.
    #[arg(long, value_enum, default_value = "auto", value_name = "BACKEND")]
    backend: skelid::backend::BackendChoice,
}

impl BackendArgs {
    /// Opens the backend, saying on stderr what `auto` chose and why.
    fn open(self) -> Result<skelid::backend::Backend> {
        let b = skelid::backend::Backend::open(self.backend).with_context(|| {
            "--backend gpu: no GPU could be opened (use --backend auto to fall back to the CPU)"
        })?;
        for w in b.notes().iter().chain(&b.warnings()) {
            eprintln!("note: {w}");
        }
        if let Some(a) = b.adapter() {
            eprintln!("GPU backend: {a}");
        }
        Ok(b)
    }
}

/// `skelid bench ARCHIVE...`: both backends on the same signals, with their agreement.
fn cmd_bench_backends(a: &BenchArgs) -> Result<()> {
    use skelid::backend::{Backend, BackendChoice};
    let scales = a
        .scales
        .as_ref()
        .and_then(|s| s.first().copied())
        .unwrap_or(128);
    let ingest = a.ingest.options()?;
    let files = find_archives(&a.archives)?;
    let mut signals = Vec::new();
    let mut runs = 0usize;
    for f in &files {
        let archive = Archive::open(f, &ingest)
            .with_context(|| format!("cannot read {} for the benchmark", f.display()))?;
        for (path, run) in archive.load_all() {
            let run = run.with_context(|| format!("{}: run {path}", f.display()))?;
            let fs = run.meta.sample_rate;
            runs += 1;
            if let Some(x) = run.input {
                signals.push((x, fs));
            }
            signals.push((run.output, fs));
        }
    }
    if signals.is_empty() {
        bail!("no runs in {}", a.archives.join(" "));
    }
    let mut opened: Vec<(&str, Backend)> = Vec::new();
    for b in &a.backend {
        match b {
            BenchBackend::Cpu if !opened.iter().any(|o| o.0 == "cpu") => {
                opened.push(("cpu", Backend::cpu()))
            }
            BenchBackend::Gpu if !opened.iter().any(|o| o.0 == "gpu") => opened.push((
                "gpu",
                Backend::open(BackendChoice::Gpu).context(
                    "--backend gpu: no GPU could be opened (bench only the CPU with --backend cpu)",
                )?,
            )),
            _ => {}
        }
    }
    let opt = skelid::track::WaveletOptions {
        scales,
        ..Default::default()
    };
    let samples: usize = signals.iter().map(|s| s.0.len()).sum();
    println!(
        "backend benchmark: {runs} run(s), {} signal(s), {samples} samples, {scales} scales, \
         wavelet track (first pass on the backend, the rest on {} CPU threads), median of {}",
        signals.len(),
        rayon::current_num_threads(),
        a.repeat.max(1)
    );
    let backends: Vec<(&str, &Backend)> = opened.iter().map(|(n, b)| (*n, b)).collect();
    let mut result =
        skelid::bench::backends::compare(&signals, runs, &opt, &backends, a.repeat, |stage| {
            eprintln!("  {stage}")
        });
    result.archives = files.iter().map(|f| f.display().to_string()).collect();
    println!(
        "\n{:>7} {:>10} {:>10} {:>16} {:>9}  adapter",
        "backend", "median s", "runs/s", "samples·scales/s", "fallback"
    );
    for t in &result.backends {
        println!(
            "{:>7} {:>10.3} {:>10.2} {:>16.3e} {:>9}  {}",
            t.backend,
            t.median_s,
            t.runs_per_s,
            t.samples_scales_per_s,
            t.fallbacks,
            t.adapter.as_deref().unwrap_or("-")
        );
    }
    if let Some(r) = result.gpu_speedup {
        println!("\nGPU speed-up over the CPU (median time ratio): {r:.2}x");
    }
    if let Some(g) = &result.agreement {
        println!(
            "agreement over {} track(s), {} samples valid in both: envelope within {:.1e} \
             (relative), frequency within {:.1e} Hz, valid in one only: {} samples",
            g.tracks, g.valid_samples, g.envelope_rel, g.frequency_hz, g.mask_samples
        );
    }
    for t in &result.backends {
        if let Some(p) = &t.per_signal {
            println!(
                "{} traffic per signal: {:.0} signals per batch, {:.3} blocking syncs, \
                 {:.0} bytes up, {:.0} bytes down ({:.2} bytes down per sample); \
                 {} of {} submissions made while another was on the device",
                t.backend,
                p.signals_per_batch,
                p.syncs,
                p.bytes_up,
                p.bytes_down,
                p.bytes_down * signals.len() as f64 / samples as f64,
                t.traffic.overlapped,
                t.traffic.submissions
            );
        }
    }
    for (_, b) in &opened {
        report_fallbacks(b);
    }
    if !a.no_end_to_end {
        let exe = std::env::current_exe().context("cannot find the skelid executable")?;
        let scratch = tempfile_dir()?;
        for (name, backend) in &opened {
            eprintln!("  {name}: end to end (skelid run, both methods)");
            let batch = skelid::batch::BatchOptions {
                methods: vec![
                    skelid::track::Method::Wavelet,
                    skelid::track::Method::Hilbert,
                ],
                identify: skelid::identify::IdentifyOptions {
                    wavelet: opt.clone(),
                    ..Default::default()
                },
                isolation: skelid::batch::Isolation::Child {
                    exe: &exe,
                    timeout: std::time::Duration::from_secs(300),
                },
                shard: None,
                force: true,
                jobs: None,
                report_runs: 100,
                backend,
            };
            let e = skelid::bench::backends::end_to_end(
                name,
                &files,
                &ingest,
                &batch,
                &scratch.join(format!("run-{name}")),
            )?;
            result.end_to_end.push(e);
        }
        let _ = std::fs::remove_dir_all(&scratch);
        print_stages(&result.end_to_end);
    }
    std::fs::write(&a.out, serde_json::to_string_pretty(&result)? + "\n")
        .with_context(|| format!("cannot write {}", a.out.display()))?;
    println!("wrote {}", a.out.display());
    Ok(())
}

/// The end-to-end table: wall time, then each stage's CPU seconds and share per backend.
fn print_stages(runs: &[skelid::bench::backends::EndToEnd]) {
    let Some(first) = runs.first() else { return };
    println!("\nend to end (skelid run, both methods, read and write included):");
    print!("{:>14}", "");
    for r in runs {
        print!(" {:>18}", r.backend);
    }
    println!();
    print!("{:>14}", "wall s");
    for r in runs {
        print!(
            " {:>18}",
            format!("{:.2} ({:.1} runs/s)", r.seconds, r.runs_per_s)
        );
    }
    println!();
    for (i, (stage, _)) in first.stages.iter().enumerate() {
        print!("{stage:>14}");
        for r in runs {
            let total: f64 = r.stages.iter().map(|s| s.1).sum::<f64>().max(1e-12);
            let s = r.stages[i].1;
            print!(" {:>18}", format!("{s:.2} s {:>3.0} %", 100.0 * s / total));
        }
        println!();
    }
    println!(
        "(CPU seconds summed over every thread; a GPU first pass in wall seconds of its \
         submissions)"
    );
    for r in runs {
        if let Some(p) = &r.per_signal {
            println!(
                "{} end to end: {:.0} signals per batch, {:.3} blocking syncs, {:.0} bytes \
                 up, {:.0} bytes down per signal",
                r.backend, p.signals_per_batch, p.syncs, p.bytes_up, p.bytes_down
            );
        }
    }
}

/// Prints the backend's fallback warnings gathered during the work, and how the GPU's work
/// was batched.
fn report_fallbacks(b: &skelid::backend::Backend) {
    if let Some((signals, submissions)) = b.gpu_work() {
        eprintln!(
            "GPU backend: {signals} signal(s) in {submissions} submission(s) ({:.1} per submission)",
            signals as f64 / submissions.max(1) as f64
        );
    }
    for w in b.warnings() {
        eprintln!("warning: {w}");
    }
}

#[derive(Args)]
struct BenchArgs {
    /// Campaign archives (files, folders or globs): time the wavelet track of every channel
    /// of every run on each backend of --backend, side by side in this process.
    #[arg(value_name = "ARCHIVE")]
    archives: Vec<String>,
    /// Backends to compare on the archives, comma-separated (`gpu` takes any adapter,
    /// lavapipe included).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "cpu,gpu")]
    backend: Vec<BenchBackend>,
    /// Timed repetitions per backend after one warm-up; the median is reported.
    #[arg(long, default_value_t = 3, value_name = "N")]
    repeat: usize,
    /// Where the archive benchmark's figures are written as JSON (`skelid-bench/1`).
    #[arg(long, default_value = "skelid-bench.json", value_name = "FILE")]
    out: PathBuf,
    /// Our transform + ridge + skeleton against the plain full-length CWT + argmax ridge
    /// (synthetic log sweeps, no archive needed).
    #[arg(long)]
    transform: bool,
    /// --transform: record lengths as powers of two.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "14,17,20",
        value_name = "LOG2N"
    )]
    log2_samples: Vec<u32>,
    /// Scale counts (default: 64,256 for --transform; 128 for archives, of which only
    /// the first count is used).
    #[arg(long, value_delimiter = ',', value_name = "S")]
    scales: Option<Vec<usize>>,
    /// --transform: print JSON rows instead of a table.
    #[arg(long)]
    json: bool,
    /// Archives: skip the end-to-end batch per backend (`skelid run`, both methods, read
    /// and write included) that shows where the time goes, stage by stage.
    #[arg(long)]
    no_end_to_end: bool,
    #[command(flatten)]
    ingest: IngestArgs,
}

/// A backend `skelid bench` can time.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum BenchBackend {
    Cpu,
    Gpu,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Inspect(a) => cmd_inspect(a),
        Command::Simulate(a) => cmd_simulate(a).map(|_| ExitCode::SUCCESS),
        Command::Demo(a) => cmd_demo(a),
        Command::Run(a) => cmd_run(a),
        Command::Merge(a) => cmd_merge(a),
        Command::Track(a) => cmd_track(a).map(|_| ExitCode::SUCCESS),
        Command::Gap(a) => cmd_gap(a),
        Command::Validate(a) => cli::validate::run(a),
        Command::Bench(a) => cmd_bench(a).map(|_| ExitCode::SUCCESS),
        Command::BenchOne {
            file,
            variant,
            scales,
        } => skelid::bench::measure(&file, variant, scales)
            .map_err(anyhow::Error::from)
            .and_then(|m| {
                println!("{}", serde_json::to_string(&m)?);
                Ok(ExitCode::SUCCESS)
            }),
        Command::InspectOne { file, ingest } => ingest.options().and_then(|o| {
            let report = inspect::inspect_archive(&file, &o);
            println!("{}", serde_json::to_string(&report)?);
            Ok(ExitCode::SUCCESS)
        }),
        Command::ReadArchives { ingest, shard } => ingest.options().and_then(|o| {
            skelid::batch::reader::serve_stdio(&o, shard)?;
            Ok(ExitCode::SUCCESS)
        }),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            // Inputs that hold nothing to do are a finding (1), not a usage error (2).
            let nothing = e
                .chain()
                .any(|c| matches!(c.downcast_ref::<FindError>(), Some(FindError::Nothing(_))));
            ExitCode::from(if nothing { 1 } else { 2 })
        }
    }
}

fn cmd_inspect(a: InspectArgs) -> Result<ExitCode> {
    let options = a.ingest.options()?;
    let files = find_archives(&a.archives)?;
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
    println!("wrote {}", path.display());
    // The demo archive is rewritten every time: identify it afresh, never from the journal.
    let backend = BackendArgs {
        backend: skelid::backend::BackendChoice::Auto,
    }
    .open()?;
    let options = skelid::batch::BatchOptions {
        methods: vec![
            skelid::track::Method::Wavelet,
            skelid::track::Method::Hilbert,
        ],
        identify: skelid::identify::IdentifyOptions {
            refine: a.refine.then_some(skelid::refine::EVALUATIONS),
            ..Default::default()
        },
        isolation: skelid::batch::Isolation::None,
        shard: None,
        force: true,
        jobs: None,
        report_runs: usize::MAX,
        backend: &backend,
    };
    let summary = identify_with_progress(
        std::slice::from_ref(&path),
        &IngestOptions::default(),
        &options,
        &a.out,
        ProgressMode::Bar,
    )?;
    let truth = |run: &str| -> Option<[f64; 4]> {
        let c = cases.iter().find(|c| c.path == run)?;
        let m = &c.model;
        let friction = m.effects.coulomb_friction.map_or(0.0, |f| f.torque);
        Some([
            m.clearance,
            (m.stiffness / m.inertia).sqrt() / std::f64::consts::TAU,
            m.damping / m.inertia,
            friction / m.inertia,
        ])
    };
    println!("\nidentified (true) per run, each with its unit:\n");
    print!("{}", render_summary(&summary.rows, Some(&truth)));
    print!("{}", render_refined(&summary.rows, Some(&truth)));
    println!(
        "\n{} run(s), {} failed{}; wrote {}, summary.json, summary.csv, report.html",
        summary.runs,
        summary.failed_runs,
        result_counts(&summary.rows),
        summary.results.display()
    );
    Ok(exit_status(&summary, false))
}

fn cmd_run(a: RunArgs) -> Result<ExitCode> {
    let ingest = a.ingest.options()?;
    let files = find_archives(&a.archives)?;
    let mut options = skelid::identify::IdentifyOptions::default();
    options.wavelet = a.wavelet.apply(options.wavelet);
    options.hilbert_cutoff = Some(a.cutoff);
    options.bins = a.bins;
    options.resonance = a.resonance;
    options.backbone = match a.backbone {
        BackboneArg::Auto => None,
        BackboneArg::Orbit => Some(skelid::fit::BackboneModel::PeriodicOrbit),
        BackboneArg::DescribingFunction => Some(skelid::fit::BackboneModel::DescribingFunction),
    };
    options.refine = a.refine.then_some(a.refine_evaluations);
    // Before any archive is opened: a value no run can use fails here, not in every run.
    options
        .validate()
        .map_err(|e| anyhow::anyhow!("{e} (see skelid run --help; nothing was done)"))?;
    let exe = self_exe()?;
    let shard = a
        .shard
        .as_deref()
        .map(skelid::batch::Shard::parse)
        .transpose()
        .map_err(anyhow::Error::msg)?;
    let backend = a.backend.open()?;
    let batch = skelid::batch::BatchOptions {
        methods: a.method.methods(),
        identify: options,
        isolation: skelid::batch::Isolation::Child {
            exe: &exe,
            timeout: std::time::Duration::from_secs(a.timeout),
        },
        shard,
        force: a.force,
        jobs: a.jobs,
        report_runs: a.report.report_runs,
        backend: &backend,
    };
    let mode = if a.json_progress {
        ProgressMode::Json
    } else if a.quiet {
        ProgressMode::Quiet
    } else {
        ProgressMode::Bar
    };
    let summary = identify_with_progress(&files, &ingest, &batch, &a.out, mode)?;
    report_fallbacks(&backend);
    if !a.quiet && !a.json_progress {
        print!("{}", render_summary(&summary.rows, None));
        print!("{}", render_refined(&summary.rows, None));
    }
    report_not_runs(&summary.not_runs);
    println!(
        "\n{} run(s), {} failed{}, {} already done earlier (skipped){}; wrote {}, summary.json, summary.csv, report.html, manifest.json, skelid.log",
        summary.runs,
        summary.failed_runs,
        result_counts(&summary.rows),
        summary.skipped,
        match summary.not_runs.len() {
            0 => String::new(),
            n => format!(", {n} group(s) skipped as not runs"),
        },
        summary.results.display()
    );
    Ok(exit_status(&summary, a.report.strict))
}

/// " (N of M run × method failed; S suspect, B bad)": the results that failed, and those
/// whose verdict is not good ([`skelid::quality`]), when there are any.
fn result_counts(rows: &[skelid::report::SummaryRow]) -> String {
    let failed = rows.iter().filter(|r| r.status != "ok").count();
    let count = |q: &str| rows.iter().filter(|r| r.quality == q).count();
    let mut parts = Vec::new();
    if failed > 0 {
        parts.push(format!("{failed} of {} run × method failed", rows.len()));
    }
    let (suspect, bad) = (count("suspect"), count("bad"));
    if suspect + bad > 0 {
        parts.push(format!("{suspect} suspect, {bad} bad"));
    }
    if parts.is_empty() {
        String::new()
    } else {
        format!(" ({})", parts.join("; "))
    }
}

/// Warns of the input groups that hold datasets but are not runs: the first few in full.
fn report_not_runs(groups: &[skelid::batch::GroupNotRun]) {
    for g in groups.iter().take(10) {
        eprintln!("warning: {}: {}", g.archive, g.group);
    }
    if groups.len() > 10 {
        eprintln!(
            "warning: … and {} more group(s) that are not runs (all in manifest.json and skelid.log)",
            groups.len() - 10
        );
    }
}

/// How a batch reports progress on the terminal.
#[derive(Clone, Copy, PartialEq, Eq)]
enum ProgressMode {
    /// An indicatif bar on stderr (hidden when stderr is not a terminal).
    Bar,
    /// Nothing.
    Quiet,
    /// One JSON object per finished run on stderr, for schedulers.
    Json,
}

fn identify_with_progress(
    files: &[PathBuf],
    ingest: &IngestOptions,
    options: &skelid::batch::BatchOptions<'_>,
    out: &std::path::Path,
    mode: ProgressMode,
) -> Result<skelid::batch::BatchSummary> {
    let bar = match mode {
        ProgressMode::Bar => indicatif::ProgressBar::new(0),
        _ => indicatif::ProgressBar::hidden(),
    }
    .with_style(
        indicatif::ProgressStyle::with_template(
            "identifying {bar:30} {pos}/{len} runs, {per_sec}, {elapsed} (eta {eta}) {msg}",
        )
        .expect("static template"),
    );
    let started = std::time::Instant::now();
    let progress = |p: skelid::batch::Progress| {
        bar.set_length(p.total as u64);
        bar.set_position(p.done as u64);
        bar.set_message(format!(
            "{} failed, {} bad, {} suspect{}",
            p.failed,
            p.bad,
            p.suspect,
            if p.skipped > 0 {
                format!(", {} already done", p.skipped)
            } else {
                String::new()
            }
        ));
        if mode == ProgressMode::Json {
            let mut v = serde_json::to_value(p).unwrap_or_default();
            v["elapsed_s"] = serde_json::json!(started.elapsed().as_secs_f64());
            eprintln!("{v}");
        }
    };
    let summary = skelid::batch::run_campaigns(files, ingest, options, out, &progress)
        .with_context(|| format!("batch into {}", out.display()))?;
    bar.finish_and_clear();
    Ok(summary)
}

/// True clearance, f0 (Hz), c/J and F/J of a run, by its path.
type Truth<'a> = &'a dyn Fn(&str) -> Option<[f64; 4]>;

/// The simulation-refined estimates (`--refine`), one line per run that has them; empty
/// when none has. With `truth`, the true values beside them.
fn render_refined(rows: &[skelid::report::SummaryRow], truth: Option<Truth<'_>>) -> String {
    let get = |r: &skelid::report::SummaryRow, k: &str| r.parameters.get(k).copied().flatten();
    let mut seen = std::collections::BTreeSet::new();
    let mut lines = String::new();
    for r in rows {
        let Some(c) = get(r, "refined_clearance") else {
            continue;
        };
        if !seen.insert((&r.source, &r.run)) {
            continue;
        }
        let t = truth.and_then(|f| f(&r.run));
        let unit = r.units.get("clearance").map_or("u", String::as_str);
        let se = |k: &str| get(r, &format!("{k}_stderr")).unwrap_or(f64::NAN);
        let with = |v: f64, e: f64, t: Option<f64>, prec: usize| match t {
            Some(t) => format!("{v:.prec$} ± {e:.prec$} ({t:.prec$})"),
            None => format!("{v:.prec$} ± {e:.prec$}"),
        };
        let k = get(r, "refined_stiffness").unwrap_or(f64::NAN);
        let f0 = k.max(0.0).sqrt() / std::f64::consts::TAU;
        let f0_se =
            0.5 * se("refined_stiffness") / k.max(f64::MIN_POSITIVE).sqrt() / std::f64::consts::TAU;
        lines.push_str(&format!(
            "{:<34} {:>28} {:>28} {:>26} {:>28} {:>8.4}\n",
            r.run,
            format!(
                "{} {unit}",
                with(c, se("refined_clearance"), t.map(|t| t[0]), 4)
            ),
            format!("{} Hz", with(f0, f0_se, t.map(|t| t[1]), 3)),
            format!(
                "{} 1/s",
                with(
                    get(r, "refined_viscous_damping").unwrap_or(f64::NAN),
                    se("refined_viscous_damping"),
                    t.map(|t| t[2]),
                    3
                )
            ),
            format!(
                "{} {unit}/s^2",
                with(
                    get(r, "refined_coulomb_friction").unwrap_or(f64::NAN),
                    se("refined_coulomb_friction"),
                    t.map(|t| t[3]),
                    3
                )
            ),
            get(r, "refined_gap").unwrap_or(f64::NAN),
        ));
    }
    if lines.is_empty() {
        return lines;
    }
    format!(
        "\nsimulation-refined (--refine; ± half the difference of the even- and odd-block fits{}):\n\n{:<34} {:>28} {:>28} {:>26} {:>28} {:>8}\n{lines}",
        if truth.is_some() { ", truth in brackets" } else { "" },
        "run",
        "clearance",
        "f0 = √(k/J)/2π",
        "viscous c/J",
        "Coulomb F/J",
        "gap"
    )
}

/// The summary as a table; with `truth`, the true values of each run beside them.
fn render_summary(rows: &[skelid::report::SummaryRow], truth: Option<Truth<'_>>) -> String {
    let mut out = format!(
        "{:<34} {:<8} {:<6} {:>24} {:>24} {:>21} {:>24}  {}\n",
        "run",
        "method",
        "status",
        "clearance",
        "f0 = √(k/J)/2π",
        "viscous c/J",
        "Coulomb F/J",
        "notes"
    );
    let get = |r: &skelid::report::SummaryRow, k: &str| r.parameters.get(k).copied().flatten();
    // Each value with its unit (runs of one campaign may differ), the truth in the same one.
    let fmt = |v: Option<f64>, t: Option<f64>, prec: usize, unit: &str| -> String {
        let text = match (v, t) {
            (Some(v), Some(t)) => format!("{v:.prec$} ({t:.prec$})"),
            (Some(v), None) => format!("{v:.prec$}"),
            (None, Some(t)) => format!("- ({t:.prec$})"),
            (None, None) => return "-".into(),
        };
        format!("{text} {unit}")
    };
    let unit = |r: &skelid::report::SummaryRow, k: &str| {
        r.units
            .get(k)
            .cloned()
            .unwrap_or_else(|| skelid::units::UNKNOWN.into())
    };
    for r in rows {
        let t = truth.and_then(|f| f(&r.run));
        let f0 = get(r, "stiffness").map(|k| k.max(0.0).sqrt() / std::f64::consts::TAU);
        let notes = match r.quality.as_str() {
            _ if r.status != "ok" => r.error.clone(),
            "suspect" | "bad" => format!("{}: {}", r.quality.to_uppercase(), r.quality_reasons),
            _ => r.warnings.clone(),
        };
        let method = if r.recommended {
            format!("{}*", r.method)
        } else {
            r.method.clone()
        };
        out.push_str(&format!(
            "{:<34} {:<8} {:<6} {:>24} {:>24} {:>21} {:>24}  {}\n",
            r.run,
            method,
            r.status,
            fmt(
                get(r, "clearance"),
                t.map(|t| t[0]),
                4,
                &unit(r, "clearance")
            ),
            fmt(f0, t.map(|t| t[1]), 3, "Hz"),
            fmt(get(r, "viscous_damping"), t.map(|t| t[2]), 3, "1/s"),
            fmt(
                get(r, "coulomb_friction"),
                t.map(|t| t[3]),
                3,
                &unit(r, "coulomb_friction")
            ),
            notes
        ));
    }
    if rows.iter().any(|r| r.recommended) {
        out.push_str(
            "* the run's recommended estimate: its first good result, wavelet first, else the \
             first suspect one (summary.csv: quality, quality_reasons, recommended)\n",
        );
    }
    out
}

fn self_exe() -> Result<PathBuf> {
    std::env::current_exe().context("cannot locate the skelid executable to isolate HDF5 reads")
}

/// Reads one dataset of an archive: the run is the dataset's parent group (or the path itself
/// when it names a run, meaning its output).
fn read_dataset(
    archive: &Archive,
    dataset: &str,
    options: &IngestOptions,
) -> Result<(Vec<f64>, f64)> {
    let file = archive.file_name().to_string();
    let dataset = format!("/{}", dataset.trim_start_matches('/'));
    let (run_path, name) = match archive.runs.iter().find(|r| r.path == dataset) {
        Some(_) => (dataset.clone(), options.output_name.clone()),
        None => {
            let (parent, name) = dataset.rsplit_once('/').unwrap_or(("", &dataset));
            let parent = if parent.is_empty() { "/" } else { parent };
            (parent.to_string(), name.to_string())
        }
    };
    let entry = archive
        .runs
        .iter()
        .find(|r| r.path == run_path)
        .with_context(|| {
            format!(
                "{file}: {dataset} is not in a run group; `skelid inspect {file}` lists the runs"
            )
        })?;
    let meta = entry.meta.clone()?;
    let run = archive.load(&meta)?;
    let x = if name == options.output_name {
        run.output
    } else if name == options.input_name {
        run.input
            .with_context(|| format!("{file}: {run_path} is a free decay without an input"))?
    } else {
        bail!(
            "{file}: {dataset}: tracks are taken of a run's `{}` or `{}` dataset",
            options.input_name,
            options.output_name
        );
    };
    Ok((x, meta.sample_rate))
}

fn cmd_track(a: TrackArgs) -> Result<()> {
    use skelid::track::{track_hilbert, HilbertOptions, RidgeSearch, WaveletOptions};
    match a.method {
        MethodArg::Wavelet if a.cutoff.is_some() => {
            bail!(
                "--cutoff low-passes the Hilbert method's tracks; add --method hilbert or drop it"
            )
        }
        MethodArg::Hilbert if a.reference.is_some() => {
            bail!("--reference guides a wavelet ridge; the Hilbert method has none (use --method wavelet)")
        }
        MethodArg::Hilbert if a.keep_scalogram => {
            bail!("--keep-scalogram keeps the wavelet transform; add --method wavelet")
        }
        _ if a.keep_scalogram
            && a.out
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("csv")) =>
        {
            bail!("--keep-scalogram needs an HDF5 output (a 2-D dataset); name --out FILE.h5")
        }
        _ => {}
    }
    let options = a.ingest.options()?;
    let backend = a.backend.open()?;
    let archive = Archive::open(&a.archive, &options)?;
    let (x, fs) = read_dataset(&archive, &a.dataset, &options)?;
    let track = match a.method {
        MethodArg::Hilbert => track_hilbert(&x, fs, &HilbertOptions { cutoff: a.cutoff })?,
        MethodArg::Wavelet => {
            let opt = a.wavelet.apply(WaveletOptions {
                ridge: if a.argmax {
                    RidgeSearch::Argmax
                } else {
                    RidgeSearch::Dynamic
                },
                min_snr: a.min_snr,
                correct: !a.no_correction,
                ..WaveletOptions::default()
            });
            let guide = match &a.reference {
                Some(r) => {
                    let (g, _) = read_dataset(&archive, r, &options)?;
                    let gt = backend
                        .track_wavelet(&g, fs, &opt, None)
                        .with_context(|| format!("tracking the reference {r}"))?;
                    Some(gt.frequency)
                }
                None => None,
            };
            backend.track_wavelet_keeping(&x, fs, &opt, guide.as_deref(), a.keep_scalogram)?
        }
    };
    report_fallbacks(&backend);
    skelid::report::write_track(
        &a.out,
        &track,
        &format!("{}:{}", a.archive.display(), a.dataset),
    )?;
    let n = track.len();
    let valid: Vec<usize> = (0..n).filter(|&i| track.valid[i]).collect();
    let (fmin_v, fmax_v, amin, amax) = valid.iter().fold(
        (f64::INFINITY, 0f64, f64::INFINITY, 0f64),
        |(a0, a1, b0, b1), &i| {
            (
                a0.min(track.frequency[i]),
                a1.max(track.frequency[i]),
                b0.min(track.amplitude[i]),
                b1.max(track.amplitude[i]),
            )
        },
    );
    println!(
        "{} {}: {n} samples at {fs} Hz, method {}, band {:.3}-{:.3} Hz, backend {}",
        a.archive.display(),
        a.dataset,
        track.method.as_str(),
        track.band.0,
        track.band.1,
        track.backend
    );
    println!(
        "valid {:.1} % of samples; over them frequency {:.4}-{:.4} Hz, amplitude {:.4e}-{:.4e}",
        100.0 * track.valid_fraction(),
        fmin_v,
        fmax_v,
        amin,
        amax
    );
    println!(
        "offset removed {:.4e}, white-noise estimate {:.3e} per sample; wrote {}",
        track.offset,
        track.noise,
        a.out.display()
    );
    Ok(())
}

fn cmd_bench(a: BenchArgs) -> Result<()> {
    use skelid::bench::{write_bench_archive, Measurement, Variant};
    if !a.archives.is_empty() {
        if a.transform {
            bail!("--transform uses its own synthetic signals: drop it, or the archives");
        }
        return cmd_bench_backends(&a);
    }
    if !a.transform {
        bail!(
            "choose a benchmark: campaign archives to compare the backends on (e.g. \
             `skelid bench demo-out/demo_campaign.h5`), or --transform"
        );
    }
    let scales = a.scales.clone().unwrap_or_else(|| vec![64, 256]);
    let exe = std::env::current_exe().context("cannot find the skelid executable")?;
    let dir = tempfile_dir()?;
    if !a.json {
        println!(
            "transform benchmark: log sweep {:.1}-{:.1} Hz at {} Hz, HDF5 in, {} threads",
            skelid::bench::BENCH_BAND.0,
            skelid::bench::BENCH_BAND.1,
            skelid::bench::BENCH_FS,
            rayon::current_num_threads()
        );
        println!(
            "{:>9} {:>7} | {:>10} {:>9} | {:>10} {:>9} | {:>7}",
            "samples", "scales", "skelid s", "peak MiB", "naive s", "peak MiB", "speed-up"
        );
    }
    for &p in &a.log2_samples {
        let n = 1usize << p;
        let file = dir.join(format!("bench_2e{p}.h5"));
        write_bench_archive(&file, n)?;
        for &s in &scales {
            let run = |v: Variant| -> Result<Measurement> {
                let name = match v {
                    Variant::Fast => "fast",
                    Variant::Naive => "naive",
                };
                let out = std::process::Command::new(&exe)
                    .arg("__bench-one")
                    .arg(&file)
                    .args(["--variant", name, "--scales", &s.to_string()])
                    .output()
                    .context("cannot run the benchmark child process")?;
                if !out.status.success() {
                    bail!("{name} failed: {}", String::from_utf8_lossy(&out.stderr));
                }
                Ok(serde_json::from_slice(&out.stdout)?)
            };
            let fast = run(Variant::Fast)?;
            let naive = run(Variant::Naive)?;
            let ratio = naive.seconds / fast.seconds;
            if a.json {
                println!(
                    "{}",
                    serde_json::json!({"samples": n, "scales": s, "skelid": fast, "naive": naive, "speedup": ratio})
                );
            } else {
                println!(
                    "{:>9} {:>7} | {:>10.3} {:>9.1} | {:>10.3} {:>9.1} | {:>6.1}x",
                    format!("2^{p}"),
                    s,
                    fast.seconds,
                    fast.peak_mib,
                    naive.seconds,
                    naive.peak_mib,
                    ratio
                );
            }
        }
        let _ = std::fs::remove_file(&file);
    }
    let _ = std::fs::remove_dir(&dir);
    Ok(())
}

fn tempfile_dir() -> Result<PathBuf> {
    let dir = std::env::temp_dir().join(format!("skelid-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)
        .with_context(|| format!("cannot create scratch folder {}", dir.display()))?;
    Ok(dir)
}

fn gap_search_options(a: &GapArgs) -> Result<skelid::gap::SearchOptions> {
    use skelid::model::EffectKind;
    if !a.holdout_block.is_finite() || a.holdout_block <= 0.0 {
        bail!("--holdout-block must be a positive number of seconds");
    }
    let effects = if a.effects.is_empty() {
        EffectKind::ALL.to_vec()
    } else {
        a.effects
            .iter()
            .map(|e| {
                EffectKind::parse(e).with_context(|| {
                    format!(
                        "--effects: unknown effect `{e}`; the vocabulary is {}",
                        EffectKind::ALL.map(|k| k.name()).join(", ")
                    )
                })
            })
            .collect::<Result<_>>()?
    };
    if a.baseline_evaluations < 10 || a.candidate_evaluations < 5 {
        bail!(
            "--baseline-evaluations must be at least 10 and --candidate-evaluations at least 5 (a simplex needs one simulation per parameter and a few steps); the defaults are 150 and 60"
        );
    }
    Ok(skelid::gap::SearchOptions {
        blocks: skelid::gap::Blocks {
            seconds: a.holdout_block,
        },
        baseline_evaluations: a.baseline_evaluations,
        refine: a.refine,
        candidate_evaluations: a.candidate_evaluations,
        pairs: !a.no_pairs,
        fit_inertia: a.fit_inertia,
        effects,
    })
}

fn cmd_gap(a: GapArgs) -> Result<ExitCode> {
    use skelid::gap::search::Reference;
    use skelid::ingest::RunKind;
    use skelid::report::gap as out;
    let opt = gap_search_options(&a)?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create the output folder {}", a.out.display()))?;
    if a.self_check {
        return gap_self_check(&a, &opt);
    }
    let (Some(model_path), Some(archive_path)) = (&a.model, &a.archive) else {
        bail!("give --model RIG.toml and an ARCHIVE (or --self-check)");
    };
    let model = RigModel::load(model_path)?;
    let model_warnings = warn_model(model_path, &model);
    let ingest = a.ingest.options()?;
    let archive = Archive::open(archive_path, &ingest)?;
    let mut chosen = Vec::new();
    let mut failed: Vec<(String, String)> = Vec::new();
    for entry in &archive.runs {
        let wanted = a.runs.is_empty() || a.runs.iter().any(|r| r == &entry.path);
        if !wanted {
            continue;
        }
        let meta = match &entry.meta {
            Ok(meta) => meta,
            Err(e) if a.runs.is_empty() => {
                eprintln!("error: {}: {e} (skipped; the other runs go on)", entry.path);
                failed.push((entry.path.clone(), e.to_string()));
                continue;
            }
            Err(e) => bail!("{}: {e}", entry.path),
        };
        if meta.kind != RunKind::BaseMotion {
            if a.runs.is_empty() {
                eprintln!(
                    "note: {} skipped: a {} run (the gap simulates base-motion runs)",
                    entry.path,
                    meta.kind.as_str()
                );
                continue;
            }
            bail!("{}: a {} run; skelid gap simulates the model under a measured base motion, so it needs kind = \"base_motion\"", entry.path, meta.kind.as_str());
        }
        chosen.push(meta.clone());
    }
    for r in &a.runs {
        if !archive.runs.iter().any(|e| &e.path == r) {
            bail!(
                "{}: no run {r} (list the runs with `skelid inspect {}`)",
                archive_path.display(),
                archive_path.display()
            );
        }
    }
    if chosen.is_empty() {
        bail!(
            "{}: no base-motion run to diagnose. skelid gap drives the rig model (a link on a moving base, FORMATS.md §2) with each run's measured base angle; force-input and free-decay runs are identified by `skelid run` only",
            archive_path.display()
        );
    }
    let settings = serde_json::json!({
        "model": model_path.display().to_string(),
        "archive": archive_path.display().to_string(),
        "holdout": format!("alternate {} s blocks: fits on the even ones (from t = 0), gaps scored on the odd ones", a.holdout_block),
        "baseline_evaluations": opt.baseline_evaluations,
        "candidate_evaluations": opt.candidate_evaluations,
        "refine": opt.refine,
        "pairs": opt.pairs,
        "fit_inertia": opt.fit_inertia,
        "min_shrink": skelid::gap::search::MIN_SHRINK,
        "min_drop": skelid::gap::search::MIN_DROP,
        "model_warnings": model_warnings,
    });
    let title = archive_path.display().to_string();
    // gap.json and gap.html are rewritten (atomically) after every run, so that a night's
    // work stopped half-way keeps every run finished so far.
    let write_outputs = |reports: &[&out::GapRun], failed: &[(String, String)]| -> Result<_> {
        let json = out::write_gap_json(&a.out, reports, failed, settings.clone())?;
        let page = out::write_gap_page(&a.out, &title, reports)?;
        Ok((json, page))
    };
    let several = chosen.len() > 1;
    let jobs = a
        .jobs
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
        .max(1);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(jobs)
        .build()
        .with_context(|| format!("cannot start {jobs} worker thread(s) (--jobs)"))?;
    // Finished runs (index in the archive, report) and failed ones (index, run, error),
    // kept in archive order whatever order they finish in.
    type Done = (Vec<(usize, out::GapRun)>, Vec<(usize, String, String)>);
    let done: std::sync::Mutex<Done> = Default::default();
    // Progress per run: runs done on the bar, each running run's simulations so far in its
    // message (a diagnosis runs a few hundred).
    let bar = indicatif::ProgressBar::new(chosen.len() as u64).with_style(
        indicatif::ProgressStyle::with_template(
            "{bar:25} {pos}/{len} runs, {elapsed} elapsed, ~{eta} left · {wide_msg}",
        )
        .expect("a valid template"),
    );
    let running: std::sync::Mutex<std::collections::BTreeMap<String, usize>> = Default::default();
    let show = |bar: &indicatif::ProgressBar,
                running: &std::collections::BTreeMap<String, usize>| {
        let parts: Vec<String> = running
            .iter()
            .map(|(run, n)| format!("{run}: {n} simulations"))
            .collect();
        bar.set_message(parts.join(", "));
    };
    let diagnose_one = |(i, meta): (usize, &skelid::ingest::RunMeta)| -> Result<()> {
        say(
            &bar,
            format!(
                "{}: refitting the model, then {} effects ...",
                meta.path,
                opt.effects.len()
            ),
        );
        let progress = |n: usize| {
            let mut r = running.lock().unwrap_or_else(|p| p.into_inner());
            r.insert(meta.path.clone(), n);
            show(&bar, &r);
            // Without a terminal (a log file), a line every 100 simulations.
            if bar.is_hidden() && n.is_multiple_of(100) {
                eprintln!("{}: {n} simulations", meta.path);
            }
        };
        let result = (|| -> Result<out::GapRun> {
            let run = archive.load(meta)?;
            let reference = Reference::new(&run, opt.blocks)?.on_score(progress);
            let d = skelid::gap::diagnose(&reference, &model, &opt)?;
            Ok(out::GapRun::new(&reference, d)?)
        })();
        {
            let mut r = running.lock().unwrap_or_else(|p| p.into_inner());
            r.remove(&meta.path);
            show(&bar, &r);
        }
        bar.inc(1);
        let mut guard = done.lock().unwrap_or_else(|p| p.into_inner());
        match result {
            Ok(r) => {
                let d = &r.diagnosis;
                let mut text = format!(
                    "{}: verdict {} · held-out gap nominal {:.4} → baseline {:.4}{} · {} simulations, {:.1} s",
                    d.run,
                    d.verdict_name(),
                    d.nominal_score.holdout,
                    d.baseline.score.holdout,
                    d.verdict.map_or(String::new(), |i| {
                        let c = &d.candidates[i];
                        format!(" → {:.4} with {} (shrink {:.0} %)", c.score.holdout, c.name(), 100.0 * c.shrink)
                    }),
                    d.evaluations,
                    d.seconds
                );
                for c in d.candidates.iter().take(3) {
                    let p: Vec<String> = c
                        .params()
                        .iter()
                        .map(|(k, v)| out::param_text(k, *v))
                        .collect();
                    text += &format!(
                        "\n    {:<40} held-out gap {:.4}  shrink {:>4.0} %  {}",
                        c.name(),
                        c.score.holdout,
                        100.0 * c.shrink,
                        p.join(", ")
                    );
                }
                bar.suspend(|| println!("{text}"));
                let path = out::fitted_model_path(&a.out, model_path, &d.run, several);
                out::write_fitted_model(&path, &r)?;
                let fitted =
                    RigModel::load(&path).context("the fitted model written does not read back")?;
                for w in fitted.warnings() {
                    say(&bar, format!("warning: {}: {w}", path.display()));
                }
                guard.0.push((i, r));
            }
            Err(e) => {
                say(&bar, format!("error: {}: {e:#}", meta.path));
                guard.1.push((i, meta.path.clone(), format!("{e:#}")));
            }
        }
        guard.0.sort_by_key(|r| r.0);
        guard.1.sort_by_key(|r| r.0);
        let reports: Vec<&out::GapRun> = guard.0.iter().map(|r| &r.1).collect();
        let errors: Vec<(String, String)> = failed
            .iter()
            .cloned()
            .chain(guard.1.iter().map(|f| (f.1.clone(), f.2.clone())))
            .collect();
        write_outputs(&reports, &errors)?;
        Ok(())
    };
    pool.install(|| {
        use rayon::prelude::*;
        chosen.par_iter().enumerate().try_for_each(diagnose_one)
    })?;
    bar.finish_and_clear();
    let (reports, errors) = done.into_inner().unwrap_or_else(|p| p.into_inner());
    let reports: Vec<&out::GapRun> = reports.iter().map(|r| &r.1).collect();
    failed.extend(errors.into_iter().map(|f| (f.1, f.2)));
    let (json, page) = write_outputs(&reports, &failed)?;
    println!(
        "wrote {}, {} and the fitted model(s) in {}",
        json.display(),
        page.display(),
        a.out.display()
    );
    Ok(if failed.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// Prints the rig model's implausible values on stderr ("warning: FILE: `clearance` = …")
/// and returns them.
fn warn_model(path: &std::path::Path, model: &RigModel) -> Vec<String> {
    let w = model.warnings();
    for line in &w {
        eprintln!("warning: {}: {line}", path.display());
    }
    w
}

/// A line above the progress bar, or on stderr when the bar is hidden (not a terminal: a
/// log file of an overnight self-check still gets every case).
fn say(bar: &indicatif::ProgressBar, line: String) {
    if bar.is_hidden() {
        eprintln!("{line}");
    } else {
        bar.println(line);
    }
}

fn gap_self_check(a: &GapArgs, opt: &skelid::gap::SearchOptions) -> Result<ExitCode> {
    use skelid::gap::selfcheck;
    let cases = selfcheck::cases(a.cases, a.seed);
    let sweep = match a.sweep {
        SweepArg::Paper => selfcheck::Sweep::Paper,
        SweepArg::TwoLevel => selfcheck::Sweep::TwoLevel,
    };
    eprintln!(
        "self-check: {} cases (seed {}), paper's rig under {} with encoder noise, one effect (or none) hidden from a model whose parameters are ~{:.0} % off",
        cases.len(),
        a.seed,
        sweep.describe(),
        100.0 * selfcheck::NOMINAL_ERROR
    );
    let bar = indicatif::ProgressBar::new(cases.len() as u64).with_style(
        indicatif::ProgressStyle::with_template(
            "{bar:30} {pos}/{len} cases, {elapsed} elapsed, ~{eta} left",
        )
        .expect("a valid template"),
    );
    let mut outcomes = Vec::new();
    let mut errors = Vec::new();
    let mut lines = Vec::new();
    for c in &cases {
        match selfcheck::run_case(c, opt, sweep) {
            Ok(o) => {
                let line = format!(
                    "case {:>3}: {:<22} {:>10.4e} → {:<22} {}",
                    c.index,
                    o.truth(),
                    c.value,
                    o.verdict,
                    if o.right() { "right" } else { "WRONG" }
                );
                say(&bar, line);
                lines.push(serde_json::json!({
                    "case": c.index, "effect": o.truth(), "value": c.value, "verdict": o.verdict,
                    "right": o.right(), "shrink": o.shrink, "param_error": o.param_error,
                    "baseline_gap": o.diagnosis.baseline.score.holdout,
                    "seconds": o.diagnosis.seconds, "simulations": o.diagnosis.evaluations,
                }));
                outcomes.push(o);
            }
            Err(e) => {
                say(&bar, format!("case {:>3}: error: {e}", c.index));
                errors.push(format!("case {}: {e}", c.index));
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let summary = selfcheck::summarize(&outcomes, errors);
    println!("\n{summary}");
    let path = a.out.join("self-check.json");
    let doc = serde_json::json!({"format": "skelid-gap-self-check/1", "seed": a.seed, "sweep": sweep.name(), "summary": summary, "cases": lines});
    skelid::report::write_atomic(&path, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    println!("wrote {}", path.display());
    Ok(ExitCode::SUCCESS)
}
