//! The GPU's dispatcher: the thread that owns the device, gathers the signals that worker
//! threads hand over into batches sized to the adapter's memory, takes each batch through
//! its two submissions (first pass, then refinement) with two batches in flight, and
//! answers each signal with its ridge and its skeleton on the estimation grid, or with why
//! the GPU could not serve it. What comes in: prepared signals ([`WaveletPrep`]); what goes
//! out: one [`Answer`] per signal, on the channel it came with.

use std::sync::atomic::AtomicBool;
use std::sync::mpsc::{self, Receiver, Sender};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::gpu::refine::{Decoded, RefineFlight, RefineStage, Refined};
use crate::gpu::ridge::{batch_bytes, FirstPass, FirstPassOut, InFlight};
use crate::gpu::spectrum::Spectra;
use crate::gpu::{Gpu, GpuError, Real};
use crate::skeleton::GridPoint;
use crate::track::{CoarseRidge, WaveletPrep};

use super::MAX_BATCH;

/// How long the dispatcher waits for more signals once one has arrived.
const LINGER: Duration = Duration::from_millis(4);

/// How often the dispatcher, while it gathers with work on the device, looks whether the
/// oldest submission has finished: the moment it has, the gathering stops and that
/// submission is moved on. It used to linger the whole `LINGER` for a first request and
/// `LINGER` more for others, and in `run`, where batches of a few signals take the device
/// a few milliseconds, the device then stood idle for most of each round trip.
const READY_POLL: Duration = Duration::from_micros(250);

/// Most binding-sized parts in one submission: bounds the device memory one submission
/// takes to about this many times the adapter's largest binding.
const SUBMISSION_PARTS: u64 = 8;

/// Test hook: pretend the device is lost after this many batches (the value of the
/// environment variable `SKELID_GPU_FAIL_AFTER`), to exercise the mid-batch fallback.
const FAIL_AFTER_ENV: &str = "SKELID_GPU_FAIL_AFTER";

/// What the dispatcher has done, for the user's summary.
#[derive(Default)]
struct Stats {
    batches: std::sync::atomic::AtomicUsize,
    signals: std::sync::atomic::AtomicUsize,
}

/// What the GPU did for one signal: its first pass, and its skeleton on the estimation grid
/// as read back, its unsure points still to solve (or why the GPU could not refine it, for
/// the CPU to do from the ridge).
pub(super) struct GpuPass {
    pub(super) ridge: CoarseRidge,
    pub(super) refined: Result<(Vec<GridPoint>, Decoded), GpuError>,
}

/// The dispatcher's answer to one request.
pub(super) struct Answer {
    /// The request's tag (its place among the signals handed over).
    pub(super) tag: usize,
    /// The signal, back.
    pub(super) prep: WaveletPrep,
    /// What the GPU did, or why not.
    pub(super) result: Result<GpuPass, GpuError>,
}

/// One signal handed to the dispatcher, and where its answer goes.
struct Request {
    tag: usize,
    prep: WaveletPrep,
    reply: Sender<Answer>,
}

impl Request {
    /// Sends the answer back to whoever waits for this signal (gone: nothing to do).
    fn answer(self, result: Result<GpuPass, GpuError>) {
        let _ = self.reply.send(Answer {
            tag: self.tag,
            prep: self.prep,
            result,
        });
    }
}

/// The GPU's dispatcher thread, which owns the device, and the queue to it.
pub(super) struct GpuService {
    pub(super) adapter: String,
    /// Whether the adapter is a software one (lavapipe), running on the host's own cores.
    pub(super) software: bool,
    /// Device memory (bytes, as [`batch_bytes`] counts it) one submission may take: half the
    /// adapter's largest binding times [`SUBMISSION_PARTS`]. Batches are sized to it.
    pub(super) submission_budget: u64,
    /// The precision of the first pass ([`FirstPass::real`]), which [`batch_bytes`] weighs.
    pub(super) real: Real,
    /// The precision of the refinement ([`RefineStage::real`]).
    pub(super) refine_real: Real,
    /// Whether the padded spectra are computed on the device ([`FirstPass::spectra_on_device`]):
    /// signals are then prepared without them.
    pub(super) spectra_on_device: bool,
    /// What the user should know of how the stages were compiled (a programme refused);
    /// the backend takes them when it opens.
    pub(super) notes: Vec<String>,
    /// Submissions made and signals they carried (successful ones).
    stats: Arc<Stats>,
    /// Each message is one handover (a `send`'s signals), taken into a batch whole.
    queue: Mutex<Option<Sender<Handover>>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for GpuService {
    /// Closes the queue and waits for the dispatcher to release the device: a device torn
    /// down while the process exits can crash the driver.
    fn drop(&mut self) {
        self.queue.lock().unwrap_or_else(|p| p.into_inner()).take();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl GpuService {
    /// Opens the device on a new dispatcher thread; fails with the reason none opens.
    pub(super) fn start() -> Result<GpuService, GpuError> {
        let fail_after = std::env::var(FAIL_AFTER_ENV)
            .ok()
            .and_then(|v| v.parse::<usize>().ok());
        let (tx, rx) = mpsc::channel::<Handover>();
        let (ready_tx, ready_rx) = mpsc::channel();
        let stats = Arc::new(Stats::default());
        let counted = stats.clone();
        // The device lives on the dispatcher thread; it ends when the last sender is dropped.
        let thread = std::thread::Builder::new()
            .name("skelid-gpu".into())
            .spawn(move || {
                // Spans, so that a traced one-shot command (`track`) shows what opening
                // costs before any work, which `bench`'s warm-up hides. The refinement's
                // pipelines, the largest part on lavapipe, are made beside the first pass
                // (`open.refine_pipelines`; `refine.pipelines_wait`, what the first batch
                // waited of it).
                use crate::profile::span;
                let opened = span("open.device", Gpu::new).and_then(|gpu| {
                    let stages = Stages {
                        first: span("open.first_pass", || FirstPass::new(&gpu))?,
                        refine: span("open.refine", || RefineStage::beside(&gpu)),
                    };
                    Ok((gpu, stages))
                });
                match opened {
                    Ok((gpu, stages)) => {
                        let budget = gpu.max_binding() / 2 * SUBMISSION_PARTS;
                        let mut notes = stages.first.notes();
                        notes.extend(stages.refine.notes());
                        let _ = ready_tx.send(Ok((
                            gpu.adapter_name(),
                            gpu.is_software(),
                            budget,
                            (stages.first.real(), stages.refine.real()),
                            stages.first.spectra_on_device(),
                            notes,
                        )));
                        dispatch(&gpu, &stages, rx, fail_after, &counted);
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                    }
                }
            })
            .map_err(|e| GpuError::Device {
                adapter: "-".into(),
                detail: format!("cannot start the GPU thread: {e}"),
            })?;
        let ready = ready_rx
            .recv()
            .map_err(|_| GpuError::Lost("the GPU thread ended while opening the device".into()))
            .and_then(|r| r);
        let (adapter, software, submission_budget, (real, refine_real), spectra_on_device, notes) =
            match ready {
                Ok(a) => a,
                Err(e) => {
                    let _ = thread.join();
                    return Err(e);
                }
            };
        Ok(GpuService {
            adapter,
            software,
            submission_budget,
            real,
            refine_real,
            spectra_on_device,
            notes,
            stats,
            queue: Mutex::new(Some(tx)),
            thread: Some(thread),
        })
    }

    /// Signals done and batches they took.
    pub(super) fn work(&self) -> (usize, usize) {
        use std::sync::atomic::Ordering::Relaxed;
        (
            self.stats.signals.load(Relaxed),
            self.stats.batches.load(Relaxed),
        )
    }

    /// Hands `preps` to the dispatcher without waiting: their answers arrive on the
    /// receiver, tagged with their place in `preps`; those it could not take (the thread
    /// has ended) come back at once with the reason. With `linger`, a batch that starts
    /// with them waits [`LINGER`] for other senders' signals (`run`'s workers hand over one
    /// signal each); without, it takes only what is already queued: a whole group, or
    /// `skelid track`'s records, have nothing to wait for.
    pub(super) fn send(
        &self,
        preps: Vec<WaveletPrep>,
        linger: bool,
    ) -> (Vec<(usize, WaveletPrep, GpuError)>, Receiver<Answer>) {
        let (reply, answers) = mpsc::channel();
        let mut unsent = Vec::new();
        if preps.is_empty() {
            return (unsent, answers);
        }
        let requests: Vec<Request> = preps
            .into_iter()
            .enumerate()
            .map(|(tag, prep)| Request {
                tag,
                prep,
                reply: reply.clone(),
            })
            .collect();
        // One message: the dispatcher, which may close a batch at any moment (the device
        // has finished the one before), never takes part of a group and leaves the rest
        // for a batch of its own.
        let queue = self.queue.lock().unwrap_or_else(|p| p.into_inner());
        let handover = Handover { requests, linger };
        let sent = match queue.as_ref() {
            Some(q) => q.send(handover),
            None => Err(mpsc::SendError(handover)),
        };
        if let Err(mpsc::SendError(h)) = sent {
            for r in h.requests {
                let gone = GpuError::Lost("the GPU thread has ended".into());
                unsent.push((r.tag, r.prep, gone));
            }
        }
        (unsent, answers)
    }
}

/// One `send`'s signals, taken into a batch whole.
struct Handover {
    requests: Vec<Request>,
    /// Whether a batch that starts with these waits [`LINGER`] for more.
    linger: bool,
}

/// The compiled GPU stages the dispatcher runs.
struct Stages {
    first: FirstPass,
    refine: RefineStage,
}

/// The dispatcher: gathers requests (for up to `LINGER` after the first where that one
/// lingers, else those already queued: [`gather`]), splits them into parts that fit the
/// adapter's bindings, and takes each batch through its two submissions (first pass, then
/// refinement; one blocking read-back each) before answering its requests.
/// Up to [`IN_FLIGHT`] submissions are on the device at once: the next batch is gathered,
/// uploaded and submitted while the previous one computes, and only then is the previous
/// one waited for and moved on.
fn dispatch(
    gpu: &Gpu,
    stages: &Stages,
    rx: Receiver<Handover>,
    fail_after: Option<usize>,
    stats: &Stats,
) {
    let mut batches = 0usize;
    let mut dead: Option<String> = None;
    // A part's runs together within half the largest binding: their spectra, power grids
    // and back-pointers each share one binding, and the decimated scales (split further by
    // the scales stage) take two buffers of that size with their FFT scratch. A submission
    // holds parts up to a few bindings' worth, all in device memory at once.
    let budget = gpu.max_binding() / 2;
    let submission_budget = budget * SUBMISSION_PARTS;
    let real = stages.first.real();
    let mut flying: std::collections::VecDeque<Unit> = std::collections::VecDeque::new();
    let mut open = true;
    while open || !flying.is_empty() {
        let batch = if open {
            let oldest_done = || {
                flying.front().is_some_and(|u| {
                    gpu.poll_ready();
                    u.done.load(std::sync::atomic::Ordering::Acquire)
                })
            };
            let (batch, still_open) = gather(
                &rx,
                !flying.is_empty(),
                &oldest_done,
                submission_budget,
                real,
            );
            open = still_open;
            batch
        } else {
            Vec::new()
        };
        if batch.is_empty() {
            // Nothing new to overlap with: move the oldest submission on.
            if let Some(unit) = flying.pop_front() {
                step(gpu, stages, unit, &mut flying, &mut dead, stats);
            }
            continue;
        }
        // A signal beyond the adapter's limits goes back alone, not with its batch.
        let mut kept = Vec::with_capacity(batch.len());
        for mut r in batch {
            // A spectrum this device cannot take whole is the CPU's, its bins uploaded.
            if r.prep.is_deferred() && !stages.first.transforms(gpu, &r.prep) {
                r.prep.materialize();
            }
            match stages.first.check(gpu, &r.prep) {
                Ok(()) => kept.push(r),
                Err(e) => {
                    r.answer(Err(e));
                }
            }
        }
        for parts in split(kept, budget, submission_budget, real) {
            while flying.len() >= IN_FLIGHT {
                let unit = flying.pop_front().expect("in flight");
                step(gpu, stages, unit, &mut flying, &mut dead, stats);
            }
            let flight = if fail_after.is_some_and(|n| batches >= n) {
                Err(GpuError::Lost(format!(
                    "simulated device loss ({FAIL_AFTER_ENV})"
                )))
            } else {
                match gpu_dead(&dead) {
                    Some(e) => Err(e),
                    None => {
                        let preps = part_preps(&parts);
                        if !flying.is_empty() {
                            crate::profile::overlapped();
                        }
                        unpanicked(|| {
                            crate::profile::time_wall(crate::profile::Stage::FirstPass, || {
                                crate::profile::dispatcher(|| {
                                    crate::profile::span("first.submit", || {
                                        stages.first.submit(gpu, &preps)
                                    })
                                })
                            })
                        })
                    }
                }
            };
            batches += 1;
            flying.push_back(Unit {
                parts,
                flight: Flight::First(flight),
                done: gpu.work_done_flag(),
            });
        }
    }
}

/// Moves the oldest unit on ([`advance`]); one that goes on to its refinement is in flight
/// again, behind the others.
fn step(
    gpu: &Gpu,
    stages: &Stages,
    unit: Unit,
    flying: &mut std::collections::VecDeque<Unit>,
    dead: &mut Option<String>,
    stats: &Stats,
) {
    if let Some(next) = crate::profile::dispatcher(|| advance(gpu, stages, unit, dead, stats)) {
        if !flying.is_empty() {
            crate::profile::overlapped();
        }
        flying.push_back(next);
    }
}

/// Most submissions on the device at once.
const IN_FLIGHT: usize = 2;

/// One batch: its requests by part, and where its work on the device stands.
struct Unit {
    parts: Vec<Vec<Request>>,
    flight: Flight,
    /// Raised once its submission has finished on the device ([`Gpu::work_done_flag`]).
    done: Arc<AtomicBool>,
}

/// A batch's submission on the device (or why there is none).
enum Flight {
    /// The first pass.
    First(Result<InFlight, GpuError>),
    /// The refinement, with the first pass's ridges and each signal's estimation grid.
    Refine {
        ridges: Vec<Vec<CoarseRidge>>,
        grids: Vec<Vec<Vec<GridPoint>>>,
        flight: Result<RefineFlight, GpuError>,
        /// The spectra the refinement reads on the device, held until it has finished.
        _spectra: Vec<Option<Spectra>>,
    },
}

/// The error of a device already lost, if it was.
fn gpu_dead(dead: &Option<String>) -> Option<GpuError> {
    dead.as_ref().map(|why| GpuError::Lost(why.clone()))
}

/// Waits for a unit's submission and moves it on: after the first pass, lays out each
/// signal's estimation grid from its ridge and submits the refinement (the unit comes
/// back, in flight again); after the refinement, answers the requests. A lost device stays
/// lost (`dead`): later work goes straight to the CPU.
fn advance(
    gpu: &Gpu,
    stages: &Stages,
    unit: Unit,
    dead: &mut Option<String>,
    stats: &Stats,
) -> Option<Unit> {
    let Unit {
        mut parts, flight, ..
    } = unit;
    match flight {
        Flight::First(flight) => {
            let preps = part_preps(&parts);
            let done = flight.and_then(|f| {
                unpanicked(|| {
                    crate::profile::time_wall(crate::profile::Stage::FirstPass, || {
                        crate::profile::span("first.finish", || f.finish_all(gpu, &preps))
                    })
                })
            });
            drop(preps);
            let FirstPassOut {
                ridges,
                spectra,
                noise_medians,
            } = match done {
                Ok(d) => d,
                Err(e) => {
                    fail(parts, e, dead);
                    return None;
                }
            };
            // The white-noise floor above the band, where the device took the spectrum.
            for (part, medians) in parts.iter_mut().zip(&noise_medians) {
                for (r, m) in part.iter_mut().zip(medians) {
                    if r.prep.is_deferred() {
                        r.prep.set_noise_median(*m);
                    }
                }
            }
            let preps = part_preps(&parts);
            // In parallel (the global rayon pool idles while the workers wait on the GPU).
            let signals = preps.iter().map(Vec::len).sum();
            let grids: Vec<Vec<Vec<GridPoint>>> = crate::profile::span("grids", || {
                let pairs: Vec<_> = preps.iter().zip(&ridges).collect();
                crate::gpu::map_parts(pairs, signals, |(p, r)| {
                    use rayon::prelude::*;
                    p.par_iter()
                        .zip(r)
                        .with_min_len(crate::gpu::PAR_MIN)
                        .map(|(p, r)| p.grid(&r.path))
                        .collect()
                })
            });
            let flight = match gpu_dead(dead) {
                Some(e) => Err(e),
                None => unpanicked(|| {
                    crate::profile::time_wall(crate::profile::Stage::Refine, || {
                        crate::profile::span("refine.submit", || {
                            stages.refine.submit(gpu, &preps, &grids, &spectra)
                        })
                    })
                }),
            };
            drop(preps);
            Some(Unit {
                parts,
                flight: Flight::Refine {
                    ridges,
                    grids,
                    flight,
                    _spectra: spectra,
                },
                done: gpu.work_done_flag(),
            })
        }
        Flight::Refine {
            ridges,
            grids,
            flight,
            ..
        } => {
            let preps = part_preps(&parts);
            let refined = flight.and_then(|f| {
                unpanicked(|| {
                    crate::profile::time_wall(crate::profile::Stage::Refine, || {
                        crate::profile::span("refine.finish", || f.finish(gpu, &preps, &grids))
                    })
                })
            });
            drop(preps);
            use std::sync::atomic::Ordering::Relaxed;
            let count: usize = ridges.iter().map(Vec::len).sum();
            stats.batches.fetch_add(1, Relaxed);
            stats.signals.fetch_add(count, Relaxed);
            crate::profile::gpu_batch(count);
            // A whole failed refinement leaves every ridge good: the CPU refines from them.
            let refined: Vec<Vec<Refined>> = match refined {
                Ok(r) => r,
                Err(e) => {
                    if let GpuError::Lost(why) = &e {
                        dead.get_or_insert_with(|| why.clone());
                    }
                    ridges
                        .iter()
                        .map(|p| p.iter().map(|_| Err(copy_error(&e))).collect())
                        .collect()
                }
            };
            let all = parts.into_iter().flatten();
            let answers = ridges
                .into_iter()
                .flatten()
                .zip(grids.into_iter().flatten())
                .zip(refined.into_iter().flatten());
            crate::profile::span("answer", || {
                for (r, ((ridge, grid), est)) in all.zip(answers) {
                    let pass = GpuPass {
                        ridge,
                        refined: est.map(|e| (grid, e)),
                    };
                    r.answer(Ok(pass));
                }
            });
            None
        }
    }
}

/// The same error again, for each signal it applies to.
fn copy_error(e: &GpuError) -> GpuError {
    match e {
        GpuError::Lost(why) => GpuError::Lost(why.clone()),
        other => GpuError::Unsupported(other.to_string()),
    }
}

/// Answers every request of a batch whose first pass failed, for the CPU to do.
fn fail(parts: Vec<Vec<Request>>, e: GpuError, dead: &mut Option<String>) {
    if let GpuError::Lost(why) = &e {
        dead.get_or_insert_with(|| why.clone());
    }
    for r in parts.into_iter().flatten() {
        r.answer(Err(copy_error(&e)));
    }
}

/// The handovers that arrive within `LINGER` of the first, each taken whole, until they
/// fill `budget` bytes of device memory (one submission's, as [`batch_bytes`] counts it;
/// `split` divides what overshoots) or number [`MAX_BATCH`] requests (the last handover
/// taken may carry it past either: the sender already holds its signals in memory).
/// `oldest_done` says whether the oldest submission in flight has finished (false when
/// there is none). Blocks for the first request only when nothing is in flight; else
/// waits at most `LINGER` for it, and stops gathering, with what it has, as soon as
/// `oldest_done` (looked at every [`READY_POLL`]). A first handover sent without
/// `linger` takes only the handovers already queued: with nothing on the device the
/// gathering waited out the whole `LINGER` after a group or a lone record that nothing
/// would join, 4 ms at the head of every `bench` repetition and of `skelid track`. Also
/// says whether the queue is still open.
fn gather(
    rx: &Receiver<Handover>,
    busy: bool,
    oldest_done: &dyn Fn() -> bool,
    budget: u64,
    real: Real,
) -> (Vec<Request>, bool) {
    use std::sync::mpsc::RecvTimeoutError;
    // Waits for a request until `deadline`, in slices of READY_POLL while work is in
    // flight: None when the time is up or the oldest submission has finished.
    let next = |deadline: Instant| -> Result<Option<Handover>, ()> {
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() || oldest_done() {
                return Ok(None);
            }
            match rx.recv_timeout(left.min(READY_POLL)) {
                Ok(r) => return Ok(Some(r)),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => return Err(()),
            }
        }
    };
    let first = if busy {
        match next(Instant::now() + LINGER) {
            Ok(Some(r)) => r,
            Ok(None) => return (Vec::new(), true),
            Err(()) => return (Vec::new(), false),
        }
    } else {
        match rx.recv() {
            Ok(r) => r,
            Err(_) => return (Vec::new(), false),
        }
    };
    let weigh = |h: &[Request]| h.iter().map(|r| batch_bytes(&r.prep, real)).sum::<u64>();
    let mut bytes = weigh(&first.requests);
    let linger = first.linger;
    let mut batch = first.requests;
    let deadline = Instant::now() + LINGER;
    while batch.len() < MAX_BATCH && bytes < budget {
        let more = if linger {
            next(deadline)
        } else {
            match rx.try_recv() {
                Ok(h) => Ok(Some(h)),
                Err(mpsc::TryRecvError::Empty) => Ok(None),
                Err(mpsc::TryRecvError::Disconnected) => Err(()),
            }
        };
        match more {
            Ok(Some(h)) => {
                bytes += weigh(&h.requests);
                batch.extend(h.requests)
            }
            Ok(None) => break,
            Err(()) => return (batch, false),
        }
    }
    (batch, true)
}

/// Splits a batch into submissions of parts: each part one wavelet within `budget` bytes,
/// each submission within `submission_budget` (a request alone always fits one).
fn split(
    mut batch: Vec<Request>,
    budget: u64,
    submission_budget: u64,
    real: Real,
) -> Vec<Vec<Vec<Request>>> {
    let mut submissions = Vec::new();
    while !batch.is_empty() {
        let mut parts: Vec<(Vec<Request>, u64)> = Vec::new();
        let mut rest = Vec::new();
        let mut total = 0u64;
        for r in batch.drain(..) {
            let b = batch_bytes(&r.prep, real);
            if total > 0 && total + b > submission_budget {
                rest.push(r);
                continue;
            }
            total += b;
            let wavelet = r.prep.wavelet();
            let part = parts
                .iter_mut()
                .find(|(p, bytes)| p[0].prep.wavelet() == wavelet && bytes + b <= budget);
            match part {
                Some((p, bytes)) => {
                    *bytes += b;
                    p.push(r);
                }
                None => parts.push((vec![r], b)),
            }
        }
        batch = rest;
        submissions.push(parts.into_iter().map(|(p, _)| p).collect());
    }
    submissions
}

fn part_preps(parts: &[Vec<Request>]) -> Vec<Vec<&WaveletPrep>> {
    parts
        .iter()
        .map(|p| p.iter().map(|r| &r.prep).collect())
        .collect()
}

/// Runs GPU work, turning a panic into a lost device: a panic on the dispatcher would leave
/// every waiting worker without an answer.
fn unpanicked<T>(f: impl FnOnce() -> Result<T, GpuError>) -> Result<T, GpuError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).unwrap_or_else(|p| {
        Err(GpuError::Lost(format!(
            "internal error (panic) in the GPU first pass: {}",
            panic_message(p.as_ref())
        )))
    })
}

/// The text a panic was raised with (`panic!`'s message), or "unknown panic".
pub(crate) fn panic_message(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::track::WaveletOptions;

    /// `n` requests of one handover that lingers, answered on `reply`.
    fn handover(n: usize, reply: &Sender<Answer>) -> Handover {
        Handover {
            requests: requests(n, reply),
            linger: true,
        }
    }

    /// `n` requests, answered on `reply`.
    fn requests(n: usize, reply: &Sender<Answer>) -> Vec<Request> {
        let x: Vec<f64> = (0..2000).map(|i| (0.3 * i as f64).sin()).collect();
        let opt = WaveletOptions {
            scales: 8,
            ..Default::default()
        };
        (0..n)
            .map(|tag| Request {
                tag,
                prep: WaveletPrep::new(&x, 100.0, &opt, None).unwrap(),
                reply: reply.clone(),
            })
            .collect()
    }

    #[test]
    fn a_batch_takes_each_handover_whole() {
        let (tx, rx) = mpsc::channel();
        let (reply, _answers) = mpsc::channel();
        tx.send(handover(3, &reply)).unwrap();
        tx.send(handover(2, &reply)).unwrap();
        // The device finishes the previous batch just after the first handover is taken:
        // gathering stops there, with the whole of that handover and nothing of the next.
        let polls = std::cell::Cell::new(0);
        let done = || {
            polls.set(polls.get() + 1);
            polls.get() > 1
        };
        let (batch, open) = gather(&rx, true, &done, u64::MAX, Real::F32);
        assert!(open);
        assert_eq!(batch.iter().map(|r| r.tag).collect::<Vec<_>>(), [0, 1, 2]);
        // The next handover is the next batch's, whole; a closed queue ends the gathering.
        let (batch, open) = gather(&rx, false, &|| false, u64::MAX, Real::F32);
        assert_eq!(batch.iter().map(|r| r.tag).collect::<Vec<_>>(), [0, 1]);
        assert!(open);
        drop(tx);
        let (batch, open) = gather(&rx, false, &|| false, u64::MAX, Real::F32);
        assert!(batch.is_empty() && !open);
    }

    /// A handover sent without lingering takes what is already queued and waits for
    /// nothing more: the gathering never polls for the device or the queue after it. One
    /// that lingers does, with nothing in flight, until `LINGER` is out.
    #[test]
    fn a_handover_that_does_not_linger_takes_the_queue_as_it_is() {
        let (tx, rx) = mpsc::channel();
        let (reply, _answers) = mpsc::channel();
        let alone = |n| Handover {
            requests: requests(n, &reply),
            linger: false,
        };
        tx.send(alone(3)).unwrap();
        tx.send(handover(2, &reply)).unwrap();
        let polls = std::cell::Cell::new(0);
        let counted = || {
            polls.set(polls.get() + 1);
            false
        };
        // Nothing in flight: the first handover and the one queued behind it, no polls.
        let (batch, open) = gather(&rx, false, &counted, u64::MAX, Real::F32);
        assert!(open);
        assert_eq!(
            batch.iter().map(|r| r.tag).collect::<Vec<_>>(),
            [0, 1, 2, 0, 1]
        );
        assert_eq!(polls.get(), 0, "it waited for more");
        // Work in flight: waiting for a first handover polls, taking it does not.
        tx.send(alone(1)).unwrap();
        let (batch, _) = gather(&rx, true, &counted, u64::MAX, Real::F32);
        assert_eq!(batch.len(), 1);
        assert_eq!(
            polls.get(),
            1,
            "it polled once, before the handover was taken"
        );
        // A lingering handover alone waits until LINGER is out (whatever the scheduler does,
        // never less: a count of its polls depended on the thread running in between).
        tx.send(handover(1, &reply)).unwrap();
        let start = Instant::now();
        let (batch, _) = gather(&rx, false, &counted, u64::MAX, Real::F32);
        assert_eq!(batch.len(), 1);
        assert!(
            start.elapsed() >= LINGER,
            "a lingering handover waited for more"
        );
    }
}
