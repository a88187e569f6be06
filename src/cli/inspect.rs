//! `skelid inspect`: the runs of campaign archives and every problem found.

use anyhow::Result;
use clap::Args;
use skelid::inspect;
use std::process::ExitCode;

use super::args::IngestArgs;

#[derive(Args)]
pub(crate) struct InspectArgs {
    /// Campaign archives: files, folders (searched for .h5/.hdf5/.mat) or glob patterns.
    #[arg(required = true, value_name = "ARCHIVE")]
    pub(crate) archives: Vec<String>,
    /// Print JSON instead of a table (one object per archive, runs and problems inside).
    #[arg(long)]
    pub(crate) json: bool,
    /// Seconds one step of reading may take, opening an archive or reading one of its
    /// runs, before that archive or run is reported as unreadable (libhdf5 loops on some
    /// corrupt files) and reading goes on after it.
    #[arg(long, default_value_t = 300, value_name = "S",
          value_parser = clap::value_parser!(u64).range(1..))]
    pub(crate) timeout: u64,
    #[command(flatten)]
    pub(crate) ingest: IngestArgs,
}

pub(crate) fn cmd_inspect(a: InspectArgs) -> Result<ExitCode> {
    let options = a.ingest.options()?;
    let files = super::args::archives(&a.archives)?;
    let reports = inspect::inspect_isolated(
        &super::internal::reader_command(&options, None)?,
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
