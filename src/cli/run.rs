//! `skelid run`, `merge` and `demo`: the batch with its progress, the terminal tables and
//! the exit status.

use anyhow::{bail, Context, Result};
use clap::Args;
use rayon::prelude::*;
use skelid::campaign::{write_campaign, Attr, RunData};
use skelid::demo;
use skelid::ingest::IngestOptions;
use std::path::PathBuf;
use std::process::ExitCode;

use super::args::{
    report_fallbacks, BackendArgs, FiguresArgs, IdentifyArgs, IngestArgs, ReportArgs, RunMethod,
};

#[derive(Args)]
pub(crate) struct DemoArgs {
    /// Output folder; the campaign is written to DIR/demo_campaign.h5.
    #[arg(long, default_value = "demo-out", value_name = "DIR")]
    pub(crate) out: PathBuf,
    /// Also refine the base-motion runs by simulation (as `skelid run --refine`), and show
    /// the refined estimates against the truth.
    #[arg(long)]
    pub(crate) refine: bool,
    #[command(flatten)]
    pub(crate) figures: FiguresArgs,
}

#[derive(Args)]
pub(crate) struct MergeArgs {
    /// Output folders of `skelid run --shard K/N`, one per shard.
    #[arg(required = true, value_name = "DIR")]
    pub(crate) dirs: Vec<PathBuf>,
    /// Folder for the joined results.
    #[arg(long, value_name = "DIR")]
    pub(crate) out: PathBuf,
    #[command(flatten)]
    pub(crate) report: ReportArgs,
}

pub(crate) fn cmd_merge(a: MergeArgs) -> Result<ExitCode> {
    super::args::refuse_file_as_folder("--out", &a.out)?;
    for d in &a.dirs {
        super::args::refuse_overwriting("--out", &a.out, true, "one of the folders merged", d)?;
    }
    stop_cleanly_on_interrupt(
        &a.out,
        "the same `skelid merge` finishes it, keeping the runs linked so far",
    );
    let summary = skelid::batch::merge(&a.dirs, &a.out, a.report.report_runs)?;
    if let Some(why) = &summary.unguarded {
        eprintln!("note: {why}");
    }
    let strict = a.report.strict;
    report_damaged(&summary.damaged);
    report_unread(&summary.incomplete);
    println!(
        "merged {} folder(s): {} run(s), {} failed{}; wrote {}, summary.json, summary.csv, report.html, manifest.json, skelid.log",
        a.dirs.len(),
        summary.runs,
        summary.failed_runs,
        damaged_count(&summary.damaged) + &unread_count(&summary.incomplete),
        summary.results.display()
    );
    Ok(exit_status(&summary, strict))
}

/// Takes `out` for this command (see [`skelid::batch::FolderLock`]), saying on stderr where
/// its file system cannot lock it.
fn take_folder(out: &std::path::Path, what: &str) -> Result<skelid::batch::FolderLock> {
    let lock = skelid::batch::FolderLock::take(out, what)?;
    if let Some(why) = &lock.unguarded {
        eprintln!("note: {why}");
    }
    Ok(lock)
}

/// 1 when a run failed or a result is `bad` (impossible values), so that schedulers see
/// it, else 0; suspect results and damaged archives (every run read, the file likely
/// damaged) are counted in the last line, and with `strict` give 1 too.
pub(crate) fn exit_status(summary: &skelid::batch::BatchSummary, strict: bool) -> ExitCode {
    let doubtful = |q: &str| q == "bad" || (strict && q == "suspect");
    if summary.failed_runs > 0
        || summary.rows.iter().any(|r| doubtful(&r.quality))
        || (strict && !summary.damaged.is_empty())
    {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    }
}

#[derive(Args)]
pub(crate) struct RunArgs {
    /// Campaign archives: files, folders (searched for .h5/.hdf5/.mat) or glob patterns.
    #[arg(required = true, value_name = "ARCHIVE")]
    pub(crate) archives: Vec<String>,
    /// Output folder for results.h5, summary.json and summary.csv.
    #[arg(long, value_name = "DIR")]
    pub(crate) out: PathBuf,
    /// Instantaneous characteristics by the wavelet ridge, the Hilbert transform, or both.
    #[arg(long, value_enum, default_value = "both")]
    pub(crate) method: RunMethod,
    #[command(flatten)]
    pub(crate) identify: IdentifyArgs,
    /// Also refine each base-motion run's clearance, k/J, c/J, gravity stiffness and
    /// Coulomb F/J by matching simulations to the record (README, "Simulation-refined
    /// identification"): written beside the skeleton estimates as `refined_*`, with
    /// standard errors from two independent fits (even and odd time blocks). About 5–10 s
    /// per run on 2 cores.
    #[arg(long)]
    pub(crate) refine: bool,
    /// Simulations per half of the refinement (two halves per run).
    #[arg(long, default_value_t = skelid::refine::EVALUATIONS, value_name = "N")]
    pub(crate) refine_evaluations: usize,
    /// Take only the K-th of N shares of the runs (e.g. 3/8), for N copies of skelid on a
    /// scheduler (a Slurm array). The share depends on each run's archive name and path,
    /// not on the order of the inputs; join the N output folders with `skelid merge`.
    #[arg(long, value_name = "K/N")]
    pub(crate) shard: Option<String>,
    /// Redo every run, even those already committed in DIR by an earlier invocation with
    /// the same data and settings (which are otherwise skipped).
    #[arg(long)]
    pub(crate) force: bool,
    /// No progress bar and no result table (the log is still written to DIR/skelid.log).
    #[arg(long, short)]
    pub(crate) quiet: bool,
    /// Progress as one JSON object per finished run on stderr (done, total, skipped,
    /// failed, suspect, bad, elapsed_s, and disk: the output disk's free bytes against
    /// what the runs left need), for schedulers and dashboards.
    #[arg(long)]
    pub(crate) json_progress: bool,
    /// Seconds the reading child (a process of its own, since libhdf5 hangs on some corrupt
    /// files) may spend on one step, opening an archive or reading one of its runs: a run
    /// past it fails and a new child reads on from the next (after three in a row, or ten
    /// in one archive, the rest of the archive is reported failed); an archive's opening
    /// past it fails the archive.
    #[arg(long, default_value_t = 300, value_name = "S",
          value_parser = clap::value_parser!(u64).range(1..))]
    pub(crate) timeout: u64,
    /// Runs identified at once (default: one per core; 32 on a GPU backend, whose batches
    /// gather the signals of the runs in flight). Memory grows with N, not with the number
    /// of runs: each run in flight adds its working set (about 0.5 kB a sample with both
    /// methods: 12 MB for 30,000 samples, 2 GB for 4,000,000, on about 70 MB of base),
    /// within --memory.
    #[arg(long, short, value_name = "N")]
    pub(crate) jobs: Option<usize>,
    /// Memory the runs in flight may take together, in GB (10^9 bytes; default: three
    /// quarters of what the system, or the cgroup the batch runs in, has available when it
    /// starts). A run waits for room rather than start beside runs that would run the
    /// machine out of memory; one larger than the whole budget runs alone.
    #[arg(allow_negative_numbers = true, long, value_name = "GB", value_parser = positive_gb)]
    pub(crate) memory: Option<f64>,
    #[command(flatten)]
    pub(crate) backend: BackendArgs,
    #[command(flatten)]
    pub(crate) report: ReportArgs,
    #[command(flatten)]
    pub(crate) figures: FiguresArgs,
    #[command(flatten)]
    pub(crate) ingest: IngestArgs,
}

pub(crate) fn cmd_demo(a: DemoArgs) -> Result<ExitCode> {
    super::args::refuse_file_as_folder("--out", &a.out)?;
    // Before the archive is written: a second demo into the folder would replace it under
    // the first one's batch.
    let _lock = take_folder(&a.out, "demo")?;
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
            let r = skelid::rig::simulate_case(c);
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
        backend: crate::cli::args::BackendArg::Auto,
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
        figures: a.figures.batch(&a.out),
        memory: None,
    };
    let summary = identify_with_progress(
        std::slice::from_ref(&path),
        &IngestOptions::default(),
        &options,
        &a.out,
        ProgressMode::Bar,
        "`skelid demo` simulates and identifies everything afresh when run again",
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

pub(crate) fn cmd_run(a: RunArgs) -> Result<ExitCode> {
    super::args::refuse_file_as_folder("--out", &a.out)?;
    let ingest = a.ingest.options()?;
    let files = super::args::archives(&a.archives)?;
    let results = a.out.join("results.h5");
    if let Some(f) = files
        .iter()
        .find(|f| super::args::lands_on(&results, false, f))
    {
        bail!(
            "--out {}: its results.h5 would be written over {}, an archive this batch reads; \
             name another folder (nothing was done)",
            a.out.display(),
            f.display()
        );
    }
    let options = a
        .identify
        .options("run", a.refine.then_some(a.refine_evaluations))?;
    let shard = a
        .shard
        .as_deref()
        .map(skelid::batch::Shard::parse)
        .transpose()
        .map_err(anyhow::Error::msg)?;
    let reader = super::internal::reader_command(&ingest, shard)?;
    // After the arguments are checked (a mistyped option makes no folder), before the
    // backend is opened (up to 2 s for a GPU): a batch refused says so at once.
    let _lock = take_folder(&a.out, "batch")?;
    let backend = a.backend.open()?;
    let batch = skelid::batch::BatchOptions {
        methods: a.method.methods(),
        identify: options,
        isolation: skelid::batch::Isolation::Child {
            command: &reader,
            timeout: std::time::Duration::from_secs(a.timeout),
        },
        shard,
        force: a.force,
        jobs: a.jobs,
        report_runs: a.report.report_runs,
        backend: &backend,
        figures: a.figures.batch(&a.out),
        memory: a.memory.map(|gb| (gb * 1e9) as u64),
    };
    let mode = if a.json_progress {
        ProgressMode::Json
    } else if a.quiet {
        ProgressMode::Quiet
    } else {
        ProgressMode::Bar
    };
    let advice = if a.force {
        "the same command without --force resumes from them"
    } else {
        "the same command resumes without redoing them"
    };
    let summary = identify_with_progress(&files, &ingest, &batch, &a.out, mode, advice)?;
    report_fallbacks(&backend);
    if !a.quiet && !a.json_progress {
        print!("{}", render_summary(&summary.rows, None));
        print!("{}", render_refined(&summary.rows, None));
    }
    report_not_runs(&summary.not_runs);
    report_damaged(&summary.damaged);
    report_unread(&summary.incomplete);
    if let Some(u) = &summary.memory_held_back {
        eprintln!("note: {}", skelid::batch::memory::held_back(u));
    }
    println!(
        "\n{} run(s), {} failed{}, {} already done earlier (skipped){}{}; wrote {}, summary.json, summary.csv, report.html, manifest.json, skelid.log",
        summary.runs,
        summary.failed_runs,
        result_counts(&summary.rows),
        summary.skipped,
        match summary.not_runs.len() {
            0 => String::new(),
            n => format!(", {n} group(s) skipped as not runs"),
        },
        damaged_count(&summary.damaged) + &unread_count(&summary.incomplete),
        summary.results.display()
    );
    Ok(exit_status(&summary, a.report.strict))
}

/// `--memory`'s value: gigabytes, more than zero.
fn positive_gb(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(gb) if gb.is_finite() && gb > 0.0 => Ok(gb),
        _ => Err(format!(
            "--memory takes the gigabytes the runs in flight may take together, a number \
             above 0 (e.g. 6 or 0.5), not {s:?}"
        )),
    }
}

/// " (N of M run × method failed; S suspect, B bad)": the results that failed, and those
/// whose verdict is not good ([`skelid::quality`]), when there are any.
pub(crate) fn result_counts(rows: &[skelid::report::SummaryRow]) -> String {
    let failed = rows
        .iter()
        .filter(|r| r.status != skelid::report::Status::Ok)
        .count();
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
pub(crate) fn report_not_runs(groups: &[skelid::batch::GroupNotRun]) {
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

/// Warns of the archives read to the end that the reading child died closing: no run
/// lost, but each file wants checking ([`skelid::batch::DamagedArchive`]).
pub(crate) fn report_damaged(archives: &[skelid::batch::DamagedArchive]) {
    for d in archives {
        eprintln!("warning: {d}");
    }
}

/// A warning for each archive given up part-way: runs of it neither identified nor failed,
/// which the count of failed runs does not show.
pub(crate) fn report_unread(archives: &[skelid::batch::IncompleteArchive]) {
    for note in archives.iter().filter_map(|a| a.unread_note()) {
        eprintln!("warning: {note}");
    }
}

/// ", N run(s) left unread (see the warnings)" for the last line, when archives given up
/// part-way left any.
fn unread_count(archives: &[skelid::batch::IncompleteArchive]) -> String {
    match archives.iter().map(|a| a.runs_not_read).sum::<usize>() {
        0 => String::new(),
        n => format!(", {n} run(s) left unread (see the warnings)"),
    }
}

/// ", N archive(s) damaged (no run lost)" for the last line, when there are any.
fn damaged_count(archives: &[skelid::batch::DamagedArchive]) -> String {
    match archives.len() {
        0 => String::new(),
        n => format!(", {n} archive(s) damaged (no run lost; see the warnings)"),
    }
}

/// How a batch reports progress on the terminal.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum ProgressMode {
    /// An indicatif bar on stderr (hidden when stderr is not a terminal).
    Bar,
    /// Nothing.
    Quiet,
    /// One JSON object per finished run on stderr, for schedulers.
    Json,
}

pub(crate) fn identify_with_progress(
    files: &[PathBuf],
    ingest: &IngestOptions,
    options: &skelid::batch::BatchOptions<'_>,
    out: &std::path::Path,
    mode: ProgressMode,
    advice: &'static str,
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
        let disk_warning = p
            .disk
            .filter(|_| p.disk_short_now)
            .map(|room| room.warning(out));
        if let Some(w) = &disk_warning {
            // Above the bar, not through it; said in every mode, as other warnings are.
            bar.suspend(|| eprintln!("warning: {w}"));
        }
        if mode == ProgressMode::Json {
            let mut v = serde_json::to_value(p).unwrap_or_default();
            if let Some(w) = disk_warning {
                v["disk_warning"] = serde_json::json!(w);
            }
            v["elapsed_s"] = serde_json::json!(started.elapsed().as_secs_f64());
            eprintln!("{v}");
        }
    };
    stop_cleanly_on_interrupt(out, advice);
    let summary = skelid::batch::run_campaigns(files, ingest, options, out, &progress)
        .with_context(|| format!("batch into {}", out.display()))?;
    bar.finish_and_clear();
    Ok(summary)
}

/// On Ctrl-C, SIGTERM (a scheduler's time limit) or SIGHUP during a batch or a merge: say
/// on the terminal and in the log how far it got and how to go on (`advice`), take away
/// `results.h5.tmp`, and end with status 130. Before, the process died at once: nothing
/// said, a `.tmp` of up to the whole results left behind (a merge's until 2026-12-07).
fn stop_cleanly_on_interrupt(out: &std::path::Path, advice: &'static str) {
    let out = out.to_path_buf();
    // A second batch in one process keeps the first's handler (none does today).
    let _ = ctrlc::set_handler(move || {
        // The clean-up on a thread of its own, given 2 s: on a hung file system (an NFS
        // mount, a common reason to press Ctrl-C) the process still ends at once.
        let (tx, rx) = std::sync::mpsc::channel();
        let folder = out.clone();
        std::thread::spawn(move || {
            let why = "Ctrl-C, SIGTERM or SIGHUP";
            let _ = tx.send(skelid::batch::record_interruption(&folder, why, advice));
        });
        let line = rx
            .recv_timeout(std::time::Duration::from_secs(2))
            .unwrap_or_else(|_| {
                format!(
                    "interrupted; {} did not answer within 2 s, so its runs were not counted \
                     (every committed run is kept there; {advice})",
                    out.display()
                )
            });
        eprintln!("\n{line}");
        // _exit, not exit: libhdf5's exit handlers would wait for a lock another thread
        // may hold; nothing here needs flushing (stderr is unbuffered, commits are renames).
        unsafe { libc::_exit(130) };
    });
}

/// True clearance, f0 (Hz), c/J and F/J of a run, by its path.
pub(crate) type Truth<'a> = &'a dyn Fn(&str) -> Option<[f64; 4]>;

/// The simulation-refined estimates (`--refine`), one line per run that has them; empty
/// when none has. With `truth`, the true values beside them.
pub(crate) fn render_refined(
    rows: &[skelid::report::SummaryRow],
    truth: Option<Truth<'_>>,
) -> String {
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
pub(crate) fn render_summary(
    rows: &[skelid::report::SummaryRow],
    truth: Option<Truth<'_>>,
) -> String {
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
            _ if r.status != skelid::report::Status::Ok => r.error.clone(),
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
