//! `skelid inspect`: the runs of campaign archives and every problem found.

use anyhow::Result;
use clap::Args;
use skelid::inspect;
use std::process::ExitCode;
use std::sync::atomic::Ordering;

use super::args::IngestArgs;

#[derive(Args)]
pub(crate) struct InspectArgs {
    /// Campaign archives: files, folders (searched for .h5/.hdf5/.mat) or glob patterns.
    #[arg(required = true, value_name = "ARCHIVE")]
    pub(crate) archives: Vec<String>,
    /// Print JSON instead of a table (one object per archive, runs and problems inside).
    #[arg(long)]
    pub(crate) json: bool,
    /// Seconds one step of reading may take, opening an archive, reading one of its runs or
    /// closing it, before that step's archive or run is reported with the step that hung
    /// (libhdf5 loops on some corrupt files) and reading goes on after it.
    #[arg(long, default_value_t = 300, value_name = "S",
          value_parser = clap::value_parser!(u64).range(1..))]
    pub(crate) timeout: u64,
    #[command(flatten)]
    pub(crate) ingest: IngestArgs,
}

pub(crate) fn cmd_inspect(a: InspectArgs) -> Result<ExitCode> {
    let options = a.ingest.options()?;
    let files = super::args::archives(&a.archives)?;
    // On a terminal only (indicatif draws nothing elsewhere), and gone before the listing.
    let bar = indicatif::ProgressBar::new(files.len() as u64).with_style(
        indicatif::ProgressStyle::with_template(
            "inspecting {bar:30} {pos}/{len} archives, {elapsed} (eta {eta}) {msg}",
        )
        .expect("static template"),
    );
    let runs = std::sync::atomic::AtomicUsize::new(0);
    let reports = inspect::inspect_isolated(
        &super::internal::reader_command(&options, None)?,
        &files,
        &options,
        std::time::Duration::from_secs(a.timeout),
        &|report| {
            let n = report.runs.len() + runs.fetch_add(report.runs.len(), Ordering::Relaxed);
            bar.set_message(format!("{n} run(s)"));
            bar.inc(1);
        },
    );
    bar.finish_and_clear();
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
