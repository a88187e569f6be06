//! The diagnosis of many runs of one archive, N at a time: the per-run loop of `skelid gap`
//! as a library, after hyperfine's exporters. In: the archive, the runs chosen, the rig
//! model, the search options and the identifier; out: each run handed to an [`Exporter`] as
//! it ends — with every run ended so far, in archive order, so that outputs rewritten then
//! keep a night's work stopped half-way — and all of them at the end ([`Diagnosed`]).
//!
//! A run's own search is a chain of simplex steps, each waiting for the last, with its
//! candidates' fits and each simulation's identification in parallel; runs are diagnosed
//! up to `jobs` at a time, each on a thread pool of its own (see [`pool_sizes`]).

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;

use super::search::Reference;
use super::{diagnose, GapRun, SearchOptions};
use crate::identify::Identifier;
use crate::ingest::Archive;
use crate::model::RigModel;
use crate::run::RunMeta;

/// An error an exporter returns: it stops the runner (a report that cannot be written).
pub type ExportError = Box<dyn std::error::Error + Send + Sync>;

/// Where the runner's work goes as it happens: progress, and each run as it ends.
pub trait Exporter: Sync {
    /// `run`'s diagnosis starts.
    fn started(&self, _run: &RunMeta) {}
    /// `run` has run `simulations` simulations so far.
    fn simulations(&self, _run: &RunMeta, _simulations: usize) {}
    /// `run` ended, diagnosed (`Ok`) or not (`Err`, the reason). `done` and `failed` hold
    /// every run ended so far, in archive order (the runs that failed before the runner
    /// started first among the failed).
    fn finished(
        &self,
        run: &RunMeta,
        result: Result<&GapRun, &str>,
        done: &[&GapRun],
        failed: &[(String, String)],
    ) -> Result<(), ExportError>;
}

/// Every run's outcome, in archive order.
pub struct Diagnosed {
    /// The diagnosed runs.
    pub runs: Vec<GapRun>,
    /// The runs that could not be diagnosed, with the reason (those failed before first).
    pub failed: Vec<(String, String)>,
}

/// Why the runner stopped.
#[derive(Debug, thiserror::Error)]
pub enum RunnerError {
    /// The worker threads could not start.
    #[error("cannot start {jobs} worker thread(s): {detail}")]
    Threads {
        /// Threads asked for.
        jobs: usize,
        /// Why not.
        detail: String,
    },
    /// The exporter failed.
    #[error(transparent)]
    Export(ExportError),
}

/// Runs ended so far: (index in `runs`, report) and (index, run, reason).
type Ended = (Vec<(usize, GapRun)>, Vec<(usize, String, String)>);

/// Diagnoses `runs` of `archive` against `model`, `jobs` at a time, each identified by
/// `identifier`; `failed_before` are runs that could not even be listed (they lead the
/// failed ones). Each run ends in `exporter`.
#[allow(clippy::too_many_arguments)]
pub fn diagnose_runs(
    archive: &Archive,
    runs: &[RunMeta],
    model: &RigModel,
    opt: &SearchOptions,
    identifier: Identifier,
    jobs: usize,
    failed_before: Vec<(String, String)>,
    exporter: &dyn Exporter,
) -> Result<Diagnosed, RunnerError> {
    let jobs = jobs.max(1);
    let pools = pool_sizes(jobs, runs.len())
        .into_iter()
        .map(|n| rayon::ThreadPoolBuilder::new().num_threads(n).build())
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| RunnerError::Threads {
            jobs,
            detail: e.to_string(),
        })?;
    let ended: Mutex<Ended> = Mutex::default();
    let one = |(i, meta): (usize, &RunMeta)| -> Result<(), RunnerError> {
        exporter.started(meta);
        let diagnosed = || -> Result<GapRun, String> {
            let run = archive.load(meta).map_err(|e| chain(&e))?;
            let reference = Reference::new(&run, opt.blocks, identifier)
                .map_err(|e| chain(&e))?
                .scored_as(opt)
                .on_score(|n| exporter.simulations(meta, n));
            let d = diagnose(&reference, model, opt).map_err(|e| chain(&e))?;
            GapRun::new(&reference, d).map_err(|e| chain(&e))
        };
        let result = caught(diagnosed);
        // The outputs are written under the lock: one writer at a time, in archive order.
        let mut guard = ended.lock().unwrap_or_else(|p| p.into_inner());
        match result {
            Ok(r) => guard.0.push((i, r)),
            Err(e) => guard.1.push((i, meta.path.clone(), e)),
        }
        guard.0.sort_by_key(|r| r.0);
        guard.1.sort_by_key(|r| r.0);
        let done: Vec<&GapRun> = guard.0.iter().map(|r| &r.1).collect();
        let failed: Vec<(String, String)> = failed_before
            .iter()
            .cloned()
            .chain(guard.1.iter().map(|f| (f.1.clone(), f.2.clone())))
            .collect();
        let this = match guard.0.iter().find(|r| r.0 == i) {
            Some(r) => Ok(&r.1),
            None => Err(guard
                .1
                .iter()
                .find(|f| f.0 == i)
                .map_or("", |f| f.2.as_str())),
        };
        exporter
            .finished(meta, this, &done, &failed)
            .map_err(RunnerError::Export)
    };
    // Each pool takes the next run in archive order when its last one ends; the first error
    // (an exporter's) stops every pool from taking another.
    let next = AtomicUsize::new(0);
    let stop = AtomicBool::new(false);
    let first_error: Mutex<Option<RunnerError>> = Mutex::default();
    std::thread::scope(|scope| {
        for pool in &pools {
            let (next, stop, first_error, one) = (&next, &stop, &first_error, &one);
            scope.spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(meta) = runs.get(i) else { break };
                    if let Err(e) = pool.install(|| one((i, meta))) {
                        stop.store(true, Ordering::Relaxed);
                        first_error
                            .lock()
                            .unwrap_or_else(|p| p.into_inner())
                            .get_or_insert(e);
                    }
                }
            });
        }
    });
    if let Some(e) = first_error.into_inner().unwrap_or_else(|p| p.into_inner()) {
        return Err(e);
    }
    let (done, errors) = ended.into_inner().unwrap_or_else(|p| p.into_inner());
    let mut failed = failed_before;
    failed.extend(errors.into_iter().map(|f| (f.1, f.2)));
    Ok(Diagnosed {
        runs: done.into_iter().map(|r| r.1).collect(),
        failed,
    })
}

/// `diagnosed`, with a panic in it (here or in a rayon task of its pool, which rayon
/// raises again here) turned into its runs' failure: a bug met in one diagnosis fails its
/// runs alone, and the others of an overnight diagnosis still end and are written.
fn caught<T>(diagnosed: impl FnOnce() -> Result<T, String>) -> Result<T, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(diagnosed)).unwrap_or_else(|payload| {
        let message = payload
            .downcast_ref::<&str>()
            .copied()
            .or_else(|| payload.downcast_ref::<String>().map(String::as_str))
            .unwrap_or("no message");
        Err(format!(
            "skelid failed inside the diagnosis ({message}): a bug, not the run's fault; \
             please report it with the run and the model"
        ))
    })
}

/// The thread pools `jobs` threads make for `runs` runs: one per run in flight, as many as
/// runs up to `jobs`, the threads shared out evenly (the first pools one more).
///
/// A pool per run, not one for all: a thread of a shared pool that waits for its run's
/// parallel work (the candidates' fits, a simulation's identification) takes on any other
/// queued work meanwhile, another run's fit of several seconds included, and its own run,
/// whose simplex chain only that thread carries on, waits until that fit ends. On a 16-core
/// H200, nine demo runs sharing one pool of 16 threads kept 5.6 cores busy and took 76 s,
/// each run 66–76 s against 9.8 s alone.
pub fn pool_sizes(jobs: usize, runs: usize) -> Vec<usize> {
    let jobs = jobs.max(1);
    let at_once = jobs.min(runs).max(1);
    (0..at_once)
        .map(|p| jobs / at_once + usize::from(p < jobs % at_once))
        .collect()
}

/// Diagnoses the runs of one structure together: the model's parameters and each effect's
/// are fitted on the `fit` runs at once and scored on the `holdout` runs (each whole,
/// driven by its own measured input). Every run then ends in `exporter` with the one
/// diagnosis, in the order given (fit runs first), its progress reported on the first fit
/// run. The runs are simulated in parallel within each evaluation.
#[allow(clippy::too_many_arguments)]
pub fn diagnose_together(
    archive: &Archive,
    fit: &[RunMeta],
    holdout: &[RunMeta],
    model: &RigModel,
    opt: &SearchOptions,
    identifier: Identifier,
    failed_before: Vec<(String, String)>,
    exporter: &dyn Exporter,
) -> Result<Diagnosed, RunnerError> {
    let first = &fit[0];
    exporter.started(first);
    let all: Vec<&RunMeta> = fit.iter().chain(holdout).collect();
    let diagnosed = || -> Result<Vec<Result<GapRun, String>>, String> {
        let runs = all
            .iter()
            .map(|m| archive.load(m).map_err(|e| chain(&e)))
            .collect::<Result<Vec<_>, _>>()?;
        let (f, h) = runs.split_at(fit.len());
        let f: Vec<&crate::run::Run> = f.iter().collect();
        let h: Vec<&crate::run::Run> = h.iter().collect();
        let reference = Reference::together(&f, &h, identifier)
            .map_err(|e| chain(&e))?
            .scored_as(opt)
            .on_score(|n| exporter.simulations(first, n));
        let d = diagnose(&reference, model, opt).map_err(|e| chain(&e))?;
        Ok(GapRun::every(&reference, &d)
            .into_iter()
            .map(|r| r.map_err(|e| chain(&e)))
            .collect())
    };
    let result = caught(diagnosed);
    let per_run: Vec<Result<GapRun, String>> = match result {
        Ok(r) => r,
        Err(e) => all.iter().map(|_| Err(e.clone())).collect(),
    };
    let mut done: Vec<GapRun> = Vec::new();
    let mut failed = failed_before;
    for (meta, r) in all.iter().zip(per_run) {
        match r {
            Ok(g) => done.push(g),
            Err(e) => failed.push((meta.path.clone(), e)),
        }
    }
    let refs: Vec<&GapRun> = done.iter().collect();
    for meta in &all {
        let this = match done.iter().find(|g| g.diagnosis.run == meta.path) {
            Some(g) => Ok(g),
            None => Err(failed
                .iter()
                .find(|f| f.0 == meta.path)
                .map_or("", |f| f.1.as_str())),
        };
        exporter
            .finished(meta, this, &refs, &failed)
            .map_err(RunnerError::Export)?;
    }
    Ok(Diagnosed { runs: done, failed })
}

/// An error with its sources, "what: why: why", as the command line shows it.
fn chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        text += &format!(": {s}");
        source = s.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::pool_sizes;

    #[test]
    fn a_panic_inside_a_diagnosis_fails_its_runs_alone() {
        use super::{diagnose_runs, ExportError, Exporter, GapRun, RunMeta};
        use crate::model::ModelKind;
        use crate::rig::{structure_decay, structure_mode};
        // Two free decays of one mode; the progress callback of the first panics, as a
        // bug deep in its search would.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("hammer.h5");
        let mode = structure_mode();
        let decays = ["/hammer/acc1", "/hammer/acc2"]
            .map(|p| structure_decay(p, &mode, 0.02, 0.01, 3))
            .to_vec();
        crate::campaign::write_campaign(&path, &[], &decays, false).unwrap();
        let archive =
            crate::ingest::Archive::open(&path, &crate::ingest::IngestOptions::default()).unwrap();
        let runs: Vec<RunMeta> = archive
            .runs
            .iter()
            .map(|e| e.meta.as_ref().unwrap().clone())
            .collect();
        struct Panicky;
        impl Exporter for Panicky {
            fn simulations(&self, run: &RunMeta, _: usize) {
                assert!(run.path != "/hammer/acc1", "a bug met in acc1's search");
            }
            fn finished(
                &self,
                _: &RunMeta,
                _: Result<&GapRun, &str>,
                _: &[&GapRun],
                _: &[(String, String)],
            ) -> Result<(), ExportError> {
                Ok(())
            }
        }
        let mut model = mode.clone();
        model.kind = ModelKind::Free;
        let opt = crate::gap::SearchOptions {
            effects: vec![crate::model::EffectKind::SensorDelay],
            baseline_evaluations: 10,
            candidate_evaluations: 10,
            ..Default::default()
        };
        let (options, backend) = (
            crate::identify::IdentifyOptions::default(),
            crate::backend::Backend::cpu(),
        );
        let identifier = crate::identify::Identifier {
            options: &options,
            backend: &backend,
        };
        let diagnosed = diagnose_runs(
            &archive,
            &runs,
            &model,
            &opt,
            identifier,
            2,
            vec![],
            &Panicky,
        )
        .expect("the runner itself ends");
        assert_eq!(diagnosed.runs.len(), 1);
        assert_eq!(diagnosed.runs[0].diagnosis.run, "/hammer/acc2");
        assert_eq!(diagnosed.failed.len(), 1);
        let (run, why) = &diagnosed.failed[0];
        assert_eq!(run, "/hammer/acc1");
        assert!(why.contains("a bug met in acc1's search"), "{why}");
        assert!(why.contains("please report it"), "{why}");
        // Fitted together, the one diagnosis fails for every run it covers, and ends.
        let together = super::diagnose_together(
            &archive,
            &runs[..1],
            &runs[1..],
            &model,
            &opt,
            identifier,
            vec![],
            &Panicky,
        )
        .expect("the runner itself ends");
        assert!(together.runs.is_empty());
        let failed: Vec<&str> = together.failed.iter().map(|f| f.0.as_str()).collect();
        assert_eq!(failed, ["/hammer/acc1", "/hammer/acc2"]);
        assert!(together.failed[1].1.contains("a bug met in acc1's search"));
    }

    #[test]
    fn pools_share_every_thread_and_never_outnumber_the_runs() {
        for jobs in 1..=20 {
            for runs in 0..=25 {
                let sizes = pool_sizes(jobs, runs);
                assert_eq!(
                    sizes.len(),
                    jobs.min(runs).max(1),
                    "{jobs} jobs, {runs} runs"
                );
                assert_eq!(
                    sizes.iter().sum::<usize>(),
                    jobs,
                    "{jobs} jobs, {runs} runs"
                );
                let (lo, hi) = (sizes.iter().min().unwrap(), sizes.iter().max().unwrap());
                assert!(*lo >= 1 && hi - lo <= 1, "{sizes:?}");
            }
        }
        assert_eq!(pool_sizes(16, 9), [2, 2, 2, 2, 2, 2, 2, 1, 1]);
        assert_eq!(pool_sizes(16, 1), [16]);
        assert_eq!(pool_sizes(2, 4), [1, 1]);
    }
}
