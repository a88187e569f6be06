//! A worker's share of the batch: a delivered run prepared (its journal key, skipped when
//! committed by an earlier invocation), identified by every method, encoded and committed to
//! the journal, with its report figures drawn while the run can still be shown. In: a
//! delivery; out: what the writer receives. Panics in one run fail that run alone.

use std::time::Instant;

use crate::backend::Backend;
use crate::identify::{identify, IdentifyOptions};
use crate::journal::{failed_key, run_key, Journal, Prepared, Stored};
use crate::profile::{self, Stage};
use crate::report::html::{self, DrawnRun, RunPlots};
use crate::report::{Placer, RunOutcome};
use crate::track::Method;

use super::*;

/// A worker's part: the key, the skip test, the identification and the encoding, and the
/// run's data put into results.h5 (through `placer`, where the file's writer has one).
pub(super) fn prepare(
    d: reader::Delivery,
    journal: &Journal,
    settings: &str,
    opt: &BatchOptions<'_>,
    drawn: &Drawn,
    placer: Option<&Placer>,
) -> Finished {
    let (key, outcome) = match d {
        reader::Delivery::Unreadable { file, error } => {
            let o = unreadable(&file, &error);
            let key = failed_key(
                &o.source,
                &o.path,
                &o.error_text().unwrap_or_default(),
                settings,
            );
            (key, Err(o))
        }
        reader::Delivery::Run { source, path, run } => {
            let key = match &*run {
                Ok(run) => run_key(run, &source, settings),
                Err(e) => failed_key(&source, &path, e, settings),
            };
            (key, Ok((source, path, *run)))
        }
    };
    if !opt.force {
        if let Some((e, stored)) = journal.load(&key) {
            let (plots, placed) = match &stored {
                Stored::Encoded(run) => {
                    let plots = drawn.wants(&e).then(|| run_plots(run));
                    if let Err(err) = figures(run, &e.source, plots.as_ref(), opt) {
                        return Finished::Failed(err);
                    }
                    (plots.map(draw), place(placer, run))
                }
                Stored::Legacy(_) => (None, Ok(None)),
            };
            return Finished::Skipped(e, stored, plots, placed);
        }
    }
    let outcome = match outcome {
        Err(recorded) => recorded,
        Ok((source, path, run)) => identify_run(source, path, run, opt),
    };
    let prepared = profile::time(Stage::Encode, || Prepared::new(&outcome));
    match profile::time(Stage::Write, || journal.commit(&key, prepared)) {
        Ok((entry, mut prepared)) => {
            let plots = drawn.wants(&entry).then(|| run_plots(prepared.encoded()));
            match figures(prepared.encoded(), &entry.source, plots.as_ref(), opt) {
                Ok(()) => {
                    // On to the writer's queue: the chunks alone from here, already in
                    // results.h5 where the writer has a placer.
                    prepared.forget_kept();
                    let placed = place(placer, prepared.encoded());
                    Finished::Committed(entry, prepared, plots.map(draw), placed)
                }
                Err(e) => Finished::Failed(e),
            }
        }
        Err(e) => Finished::Failed(e),
    }
}

/// Puts `run`'s data into results.h5 through `placer`, timed as writing (`Ok(None)`: the
/// writer will write them itself; an error: so will it, and it logs why).
fn place(placer: Option<&Placer>, run: &crate::report::encoded::EncodedRun) -> Placement {
    let Some(placer) = placer else {
        return Ok(None);
    };
    profile::time(Stage::Write, || placer.place(run))
}

/// The report's plots of an encoded run (its group in results.h5 is set when drawn).
pub(super) fn run_plots(run: &crate::report::encoded::EncodedRun) -> RunPlots {
    profile::time(Stage::Encode, || html::encoded_plots(run))
}

/// The run's figures for report.html, drawn here on the worker rather than at the batch's
/// end.
fn draw(plots: RunPlots) -> DrawnRun {
    profile::time(Stage::Write, || DrawnRun::new(plots))
}

/// Writes the run's figures as files when the batch asks for them (`plots`: the run's
/// plots when already decoded for the report).
fn figures(
    run: &crate::report::encoded::EncodedRun,
    source: &str,
    plots: Option<&RunPlots>,
    opt: &BatchOptions<'_>,
) -> Result<(), crate::report::ReportError> {
    use crate::report::figure_files::{folder_name, write_figures};
    let Some(f) = &opt.figures else {
        return Ok(());
    };
    profile::time(Stage::Write, || {
        let decoded;
        let plots = match plots {
            Some(p) => p,
            None => {
                decoded = html::encoded_plots(run);
                &decoded
            }
        };
        // The archive's file name: runs of different archives may share a path.
        let archive = std::path::Path::new(source)
            .file_name()
            .map_or_else(|| source.to_string(), |n| n.to_string_lossy().into_owned());
        let dir = f
            .dir
            .join(folder_name(&archive))
            .join(folder_name(&run.path));
        write_figures(&dir, &html::run_figure_set(plots, true), f.format).map(|_| ())
    })
}

/// Every method of `opt` on one run as read (or its read error), timed.
pub(super) fn identify_run(
    source: String,
    path: String,
    run: Result<crate::run::Run, String>,
    opt: &BatchOptions<'_>,
) -> RunOutcome {
    let mut outcome = RunOutcome::new(path, source);
    match run {
        Err(e) => outcome.error = Some(e),
        Ok(run) => {
            outcome.sample_rate = Some(run.meta.sample_rate);
            outcome.samples = run.output.len();
            outcome.inertia = run.meta.inertia;
            outcome.units = crate::units::Units::of(&run.meta);
            for &m in &opt.methods {
                let t0 = Instant::now();
                outcome.methods.push((
                    m,
                    identify_guarded(&run, m, &opt.identify, opt.backend),
                    t0.elapsed().as_secs_f64(),
                ));
            }
            // Base-motion runs only: the others have no model to simulate yet.
            if let Some(n) = opt.identify.refine {
                if run.meta.kind == crate::run::RunKind::BaseMotion {
                    // The refinement's simulations are identified one after another, each
                    // waiting on the last: a GPU's batching gains nothing there, and its
                    // gathering window would be added to each, so they run on the CPU.
                    let cpu = Backend::cpu();
                    let identifier = crate::identify::Identifier {
                        options: &opt.identify,
                        backend: &cpu,
                    };
                    outcome.refined =
                        Some(crate::refine::refine(&run, n, identifier).map_err(|e| e.to_string()));
                }
            }
        }
    }
    outcome
}

/// One method on one run, with a panic inside any stage turned into that run's error.
pub(super) fn identify_guarded(
    run: &crate::run::Run,
    method: Method,
    options: &IdentifyOptions,
    backend: &Backend,
) -> Result<crate::identify::Identification, String> {
    guarded(|| identify(run, method, options, backend).map_err(|e| e.to_string()))
}

/// Runs `f`, turning a panic into an error that names it.
pub fn guarded<T>(f: impl FnOnce() -> Result<T, String>) -> Result<T, String> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => Err(format!(
            "internal error (panic) in the identification: {}",
            crate::backend::panic_message(p.as_ref())
        )),
    }
}
