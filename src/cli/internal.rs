//! The hidden commands skelid runs in its own child processes, so that a crash in libhdf5
//! or a measurement's allocations stay there: one benchmark measurement, and the isolated
//! reader of `skelid run` and `skelid inspect`. Each prints JSON (or the reader's
//! stream) on stdout for the parent.

use std::ffi::OsString;
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

/// The archives named on stdin, their runs streamed to stdout.
pub(crate) fn read_archives(a: ReadArchivesArgs) -> Result<ExitCode> {
    die_with_parent();
    let o = a.ingest.options()?;
    skelid::batch::reader::serve_stdio(&o, a.shard)?;
    Ok(ExitCode::SUCCESS)
}

/// Asks the kernel to kill this reader child when the batch that started it ends, however it
/// ends. A batch killed from outside (SIGKILL, or SIGTERM sent to it alone, not its process
/// group) otherwise left its reader running: one that hung in libhdf5 on an archive whose
/// file system stopped answering (the batch's `--timeout` watchdog went with the batch)
/// stayed there for good. The thread that starts the child waits for it (the batch's reader
/// thread, or the `inspect` worker of one archive), so the thread the signal follows lives
/// as long as the child is wanted.
fn die_with_parent() {
    #[cfg(target_os = "linux")]
    {
        // The batch's pid as it gave it, else the parent now (a reader started by hand).
        let batch = std::env::var(skelid::batch::reader::BATCH_PID)
            .ok()
            .and_then(|v| v.parse::<u32>().ok())
            .unwrap_or_else(std::os::unix::process::parent_id);
        // SAFETY: prctl(PR_SET_PDEATHSIG, signal) sets a process attribute and touches no
        // memory of ours.
        unsafe { libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) };
        // The batch gone before the request was made, this child adopted: nobody reads
        // what it would send.
        if std::os::unix::process::parent_id() != batch {
            std::process::exit(1);
        }
    }
}

/// The subcommand of `skelid run`'s reader child (`__read-archives`).
const READ: &str = "__read-archives";

/// The command of the reader child of `skelid run` and `skelid inspect` with `options` and `shard` (the archives go
/// on its stdin).
pub(crate) fn reader_command(
    options: &skelid::ingest::IngestOptions,
    shard: Option<skelid::batch::Shard>,
) -> Result<skelid::child::ChildCommand> {
    let mut args = vec![OsString::from(READ)];
    args.extend(option_args(options).into_iter().map(OsString::from));
    if let Some(s) = shard {
        args.extend(["--shard".into(), s.to_string().into()]);
    }
    Ok(skelid::child::ChildCommand {
        exe: super::args::self_exe()?,
        args,
    })
}

/// The flags that reproduce `options` in a child process (the ingest flags of
/// [`IngestArgs`]).
fn option_args(options: &skelid::ingest::IngestOptions) -> Vec<String> {
    let mut args = vec![
        "--input-name".to_string(),
        options.input_name.clone(),
        "--output-name".to_string(),
        options.output_name.clone(),
    ];
    if let Some(fs) = options.sample_rate {
        args.extend(["--sample-rate".to_string(), format!("{fs:e}")]);
    }
    if let Some(g) = &options.run_glob {
        args.extend(["--run-glob".to_string(), g.as_str().to_string()]);
    }
    if let Some(k) = options.kind {
        args.extend(["--kind".to_string(), k.as_str().to_string()]);
    }
    if let Some(j) = options.inertia {
        args.extend(["--inertia".to_string(), format!("{j:e}")]);
    }
    if let Some(q) = options.input_quantity {
        args.extend(["--input-quantity".to_string(), q.as_str().to_string()]);
    }
    if let Some(q) = options.output_quantity {
        args.extend(["--output-quantity".to_string(), q.as_str().to_string()]);
    }
    args
}

/// `__bench-one --variant`: the measurement a child process is asked for.
fn parse_variant(s: &str) -> Result<skelid::bench::Variant, String> {
    skelid::bench::Variant::from_name(s).ok_or_else(|| format!("{s:?}: use fast or naive"))
}
