//! The `skelid` command line.

mod cli;

use cli::{
    args::IngestArgs,
    bench::{cmd_bench, BenchArgs},
    gap::{cmd_gap, GapArgs},
    inspect::{cmd_inspect, InspectArgs},
    run::{cmd_demo, cmd_merge, cmd_run, DemoArgs, MergeArgs, RunArgs},
    simulate::{cmd_simulate, SimulateArgs},
    track::{cmd_track, TrackArgs},
};

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

use skelid::ingest::FindError;
use skelid::inspect;

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
    /// summary.csv (FORMATS.md §3). Exit status 1 if any run failed or a result is bad
    /// (with --strict, also suspect).
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
        #[arg(long, value_parser = parse_variant)]
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

/// `__bench-one --variant`: the measurement a child process is asked for.
fn parse_variant(s: &str) -> Result<skelid::bench::Variant, String> {
    skelid::bench::Variant::from_name(s).ok_or_else(|| format!("{s:?}: use fast or naive"))
}
