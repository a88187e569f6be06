//! The `skelid` command line: parse, dispatch, and exit codes. Each subcommand lives in its
//! own file of `src/cli/`.

mod cli;

use std::process::ExitCode;

use clap::Parser;

use cli::{internal, Cli, Command};
use skelid::ingest::FindError;

fn main() -> ExitCode {
    skelid::hint::set_namer(cli::hints::flag);
    skelid::gpu::quiet_headless_vulkan();
    if let Some(note) = skelid::backend::keep_freed_memory() {
        eprintln!("note: {note}");
    }
    if let Some(note) = skelid::transform::parallel::hook_note() {
        eprintln!("note: {note}");
    }
    // The global pool (the parallel parts of every stage) below the process's priority:
    // see `lower_compute_priority`. Fails only if a pool was built already: then as it is.
    let _ = rayon::ThreadPoolBuilder::new()
        .start_handler(|_| skelid::backend::lower_compute_priority())
        .build_global();
    let ok = |r: anyhow::Result<()>| r.map(|()| ExitCode::SUCCESS);
    let result = match Cli::parse().command {
        Command::Inspect(a) => cli::inspect::cmd_inspect(a),
        Command::Simulate(a) => ok(cli::simulate::cmd_simulate(a)),
        Command::Demo(a) => cli::run::cmd_demo(a),
        Command::Run(a) => cli::run::cmd_run(a),
        Command::Merge(a) => cli::run::cmd_merge(a),
        Command::Track(a) => ok(cli::track::cmd_track(a)),
        Command::Gap(a) => cli::gap::cmd_gap(a),
        Command::Validate(a) => cli::validate::run(a),
        Command::Bench(a) => ok(cli::bench::cmd_bench(a)),
        Command::BenchOne(a) => internal::bench_one(a),
        Command::ReadArchives(a) => internal::read_archives(a),
    };
    result.unwrap_or_else(|e| {
        eprintln!("error: {e:#}");
        ExitCode::from(failure_code(&e))
    })
}

/// Exit status 2 for a command that could not run (bad arguments, unreadable inputs), but 1
/// for inputs that hold nothing to do: that is a finding, not a usage error.
fn failure_code(e: &anyhow::Error) -> u8 {
    let nothing = e
        .chain()
        .any(|c| matches!(c.downcast_ref::<FindError>(), Some(FindError::Nothing(_))));
    if nothing {
        1
    } else {
        2
    }
}
