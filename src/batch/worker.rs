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

/// What every run of a batch is prepared with.
pub(super) struct Work<'a> {
    /// The output folder's journal.
    pub(super) journal: &'a Journal,
    /// The settings' fingerprint, part of every run's key.
    pub(super) settings: &'a str,
    /// The batch's options.
    pub(super) opt: &'a BatchOptions<'a>,
    /// The report's runs, drawn by the worker that has them.
    pub(super) drawn: &'a Drawn,
    /// Where the workers put runs' data into results.h5 (where the file's writer has one).
    pub(super) placer: Option<&'a Placer>,
}

/// A worker's part: the key, the skip test, the identification and the encoding, and the
/// run's data put into results.h5 (through the placer, where the file's writer has one).
fn prepare(d: reader::Delivery, w: &Work<'_>) -> Finished {
    let (opt, settings) = (w.opt, w.settings);
    #[cfg(test)]
    if let reader::Delivery::Run { path, .. } = &d {
        assert_ne!(path, tests::PANICS, "a bug met in this run");
    }
    let (key, outcome) = match d {
        reader::Delivery::Unreadable { file, error, .. } => {
            let o = unreadable(&file, &error);
            let key = failed_key(
                &o.source,
                &o.path,
                &o.error_text().unwrap_or_default(),
                settings,
            );
            (key, Err(o))
        }
        reader::Delivery::Run {
            source, path, run, ..
        } => {
            let key = match &*run {
                Ok(run) => run_key(run, &source, settings),
                Err(e) => failed_key(&source, &path, e, settings),
            };
            (key, Ok((source, path, *run)))
        }
    };
    if !opt.force {
        if let Some((e, stored)) = w.journal.load(&key) {
            let (plots, placed) = match &stored {
                Stored::Encoded(run) => {
                    let plots = w.drawn.wants(&e).then(|| run_plots(run));
                    if let Err(err) = figures(run, &e.source, plots.as_ref(), opt) {
                        return Finished::Failed(err);
                    }
                    (plots.map(draw), place(w.placer, run))
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
    commit(&key, &outcome, w)
}

/// [`prepare`], with a panic anywhere in it (identifying, encoding, committing, drawing)
/// turned into the run's failure, recorded and committed like any other: a bug met in one
/// run fails that run alone, at once, and the batch goes on. (A panic left to the pool
/// surfaced only when every run of the batch was done, and the run was in no file.)
pub(super) fn prepare_caught(d: reader::Delivery, w: &Work<'_>) -> Finished {
    // The names it is recorded under, taken before `prepare` consumes the delivery.
    let (source, path) = match &d {
        reader::Delivery::Run { source, path, .. } => (source.clone(), path.clone()),
        reader::Delivery::Unreadable { file, .. } => {
            let o = unreadable(file, &"");
            (o.source, o.path)
        }
    };
    let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| prepare(d, w)));
    caught.unwrap_or_else(|p| {
        let error = format!(
            "internal error (panic) while preparing the run: {}; a bug, not the run's \
             fault: please report it",
            crate::backend::panic_message(p.as_ref())
        );
        let key = failed_key(&source, &path, &error, w.settings);
        let outcome = RunOutcome {
            error: Some(error),
            ..RunOutcome::new(path, source)
        };
        commit(&key, &outcome, w)
    })
}

/// Encodes `outcome`, commits it to the journal under `key`, draws its figures where they
/// are shown and puts its data into results.h5.
fn commit(key: &str, outcome: &RunOutcome, w: &Work<'_>) -> Finished {
    let prepared = profile::time(Stage::Encode, || Prepared::new(outcome));
    match profile::time(Stage::Write, || w.journal.commit(key, prepared)) {
        Ok((entry, mut prepared)) => {
            let plots = w.drawn.wants(&entry).then(|| run_plots(prepared.encoded()));
            match figures(prepared.encoded(), &entry.source, plots.as_ref(), w.opt) {
                Ok(()) => {
                    // On to the writer's queue: the chunks alone from here, already in
                    // results.h5 where the writer has a placer.
                    prepared.forget_kept();
                    let placed = place(w.placer, prepared.encoded());
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The run path at which [`prepare`] panics, in these tests only.
    pub(super) const PANICS: &str = "/runs/panics";

    /// A panic met while preparing a run (outside the identification, which has its own
    /// guard) becomes that run's failure, committed to the journal with the reason, and
    /// the batch's thread goes on.
    #[test]
    fn a_panic_while_preparing_fails_the_run_alone() {
        let dir = tempfile::tempdir().unwrap();
        let journal = Journal::open(dir.path()).unwrap();
        let backend = Backend::cpu();
        let opt = BatchOptions {
            methods: vec![Method::Hilbert],
            identify: IdentifyOptions::default(),
            isolation: Isolation::None,
            shard: None,
            force: false,
            jobs: Some(1),
            report_runs: 0,
            backend: &backend,
            figures: None,
            memory: None,
        };
        let d = reader::Delivery::Run {
            source: "a.h5".into(),
            path: PANICS.into(),
            run: Box::new(Err("never read".into())),
            error_kind: Some("corrupt".into()),
        };
        let work = Work {
            journal: &journal,
            settings: "settings",
            opt: &opt,
            drawn: &Drawn::new(0),
            placer: None,
        };
        let finished = prepare_caught(d, &work);
        let Finished::Committed(entry, ..) = finished else {
            panic!("committed as a failed run");
        };
        println!("{:?}", entry.rows.first().map(|r| &r.error));
        assert!(entry.failed);
        assert_eq!(
            (entry.path.as_str(), entry.source.as_str()),
            (PANICS, "a.h5")
        );
        let error = &entry.rows[0].error;
        assert!(
            error.contains("internal error (panic) while preparing the run"),
            "{error}"
        );
        assert!(error.contains("a bug met in this run"), "{error}");
        assert!(journal.lookup(&entry.key).is_some(), "in the journal");
    }
}
