//! The hidden commands skelid runs in its own child processes, so that a crash in libhdf5
//! or a measurement's allocations stay there: one benchmark measurement, one archive's
//! inspection, and the isolated reader of `skelid run`. Each prints JSON (or the reader's
//! stream) on stdout for the parent.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::Args;

use super::args::IngestArgs;

/// `__bench-one FILE --variant V --scales S`.
#[derive(Args)]
pub(crate) struct BenchOneArgs {
    file: PathBuf,
    #[arg(long, value_parser = parse_variant)]
    variant: skelid::bench::Variant,
    #[arg(long)]
    scales: usize,
}

/// `__inspect-one FILE [ingest options]`.
#[derive(Args)]
pub(crate) struct InspectOneArgs {
    file: PathBuf,
    #[command(flatten)]
    ingest: IngestArgs,
}

/// `__read-archives [ingest options] [--shard K/N]`, archives on stdin.
#[derive(Args)]
pub(crate) struct ReadArchivesArgs {
    #[command(flatten)]
    ingest: IngestArgs,
    /// Only this share of the runs.
    #[arg(long, value_parser = skelid::batch::Shard::parse)]
    shard: Option<skelid::batch::Shard>,
}

/// One benchmark measurement, printed as JSON.
pub(crate) fn bench_one(a: BenchOneArgs) -> Result<ExitCode> {
    let m = skelid::bench::measure(&a.file, a.variant, a.scales)?;
    println!("{}", serde_json::to_string(&m)?);
    Ok(ExitCode::SUCCESS)
}

/// One archive's inspection report, printed as JSON.
pub(crate) fn inspect_one(a: InspectOneArgs) -> Result<ExitCode> {
    let o = a.ingest.options()?;
    let report = skelid::inspect::inspect_archive(&a.file, &o);
    println!("{}", serde_json::to_string(&report)?);
    Ok(ExitCode::SUCCESS)
}

/// The archives named on stdin, their runs streamed to stdout.
pub(crate) fn read_archives(a: ReadArchivesArgs) -> Result<ExitCode> {
    let o = a.ingest.options()?;
    skelid::batch::reader::serve_stdio(&o, a.shard)?;
    Ok(ExitCode::SUCCESS)
}

/// `__bench-one --variant`: the measurement a child process is asked for.
fn parse_variant(s: &str) -> Result<skelid::bench::Variant, String> {
    skelid::bench::Variant::from_name(s).ok_or_else(|| format!("{s:?}: use fast or naive"))
}
