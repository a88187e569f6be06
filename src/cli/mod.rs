//! The command line: its subcommands ([`Command`]), one file per subcommand (`main.rs`
//! parses and dispatches), the arguments several share (`args`), and the internal commands
//! skelid's own child processes run (`internal`).

pub mod args;
pub mod bench;
pub mod gap;
pub mod hints;
pub mod inspect;
pub mod internal;
pub mod run;
pub mod simulate;
pub mod track;
pub mod validate;

use clap::{Parser, Subcommand};

use bench::BenchArgs;
use gap::GapArgs;
use inspect::InspectArgs;
use run::{DemoArgs, MergeArgs, RunArgs};
use simulate::SimulateArgs;
use track::TrackArgs;

/// Identify non-linear joints (clearance, contact stiffness, viscous and dry friction) from
/// vibration test campaigns with skeleton methods, and explain why a rig's simulation does
/// not match its measurements.
#[derive(Parser)]
#[command(name = "skelid", version, about, long_about = None)]
pub(crate) struct Cli {
    /// The subcommand.
    #[command(subcommand)]
    pub(crate) command: Command,
}

/// The subcommands.
#[derive(Subcommand)]
pub(crate) enum Command {
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
    Validate(validate::ValidateArgs),
    /// Benchmarks, each measured side by side in one run.
    Bench(BenchArgs),
    /// Internal: one benchmark measurement in this (child) process, printed as JSON.
    #[command(name = "__bench-one", hide = true)]
    BenchOne(internal::BenchOneArgs),
    /// Internal: read the archives named on stdin and stream their runs to stdout (the
    /// isolated reader of `skelid run` and `skelid inspect`).
    #[command(name = "__read-archives", hide = true)]
    ReadArchives(internal::ReadArchivesArgs),
}

/// Identification options and the backend they run on, held together: what `gap` and
/// `validate` hand to the library's identifications.
pub(crate) struct Engine {
    options: skelid::identify::IdentifyOptions,
    backend: skelid::backend::Backend,
}

impl Engine {
    /// The options on the CPU backend.
    pub(crate) fn cpu(options: skelid::identify::IdentifyOptions) -> Engine {
        Engine::new(options, skelid::backend::Backend::cpu())
    }

    /// The options on a backend already opened.
    pub(crate) fn new(
        options: skelid::identify::IdentifyOptions,
        backend: skelid::backend::Backend,
    ) -> Engine {
        Engine { options, backend }
    }

    /// The backend, for its warnings and its work at the end.
    pub(crate) fn backend(&self) -> &skelid::backend::Backend {
        &self.backend
    }

    /// The options and backend, handed on together.
    pub(crate) fn get(&self) -> skelid::identify::Identifier<'_> {
        skelid::identify::Identifier {
            options: &self.options,
            backend: &self.backend,
        }
    }
}
