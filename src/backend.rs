//! The one place where the CPU or GPU backend is chosen (`--backend auto|cpu|gpu`).
//!
//! The backend evaluates the wavelet transform of each signal: its first pass (the
//! band-limited Morlet transform at every scale and the ridge search,
//! [`WaveletPrep::coarse_ridge`]) and its refinement (W, W′, W″ at the scales around the
//! ridge, the three-scale estimate and the bias correction at every point of the
//! estimation grid, [`WaveletPrep::estimate_grid`]). What follows — the noise floor,
//! validity, the per-sample track ([`WaveletPrep::complete`]), ForceVib and the fits — is
//! the shared CPU stage. On a GPU, signals tracked at the same time by different worker
//! threads are gathered into batches by a dispatcher thread that owns the device: a worker
//! hands over its prepared signal and waits for its skeleton. A batch takes two
//! submissions: the first pass (its ridges are read back, the host lays out each signal's
//! estimation grid), then the refinement (its grid records are read back). When the GPU
//! cannot serve a signal (no adapter, a failed or lost device, a signal beyond the
//! adapter's limits), that signal's first pass, or only its refinement, runs on the CPU, a
//! warning is kept, and a track whose first pass ran on the CPU records `backend = "cpu"`.

use std::sync::mpsc::{self, Receiver, Sender};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::gpu::refine::{RefineFlight, RefineStage, Refined};
use crate::gpu::ridge::{batch_bytes, FirstPass, InFlight};
use crate::gpu::{Gpu, GpuError};
use crate::skeleton::{GridEstimate, GridPoint};
use crate::track::{CoarseRidge, Device, Track, TrackError, WaveletOptions, WaveletPrep};

/// Which backend the user asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendChoice {
    /// A hardware GPU when one opens, else the CPU. A software adapter (lavapipe) is
    /// slower than the CPU backend on the same cores, so `auto` passes it over.
    #[default]
    Auto,
    /// The CPU (rustfft + rayon).
    Cpu,
    /// The GPU, or an error when none opens.
    Gpu,
}

/// How long the dispatcher waits for more signals once one has arrived.
const LINGER: Duration = Duration::from_millis(4);

/// Most signals in one batch, whatever the adapter's memory (their prepared spectra are held
/// in host memory while they wait: about 0.3 MB each at 30 000 samples).
const MAX_BATCH: usize = 4096;

/// Signals in [`Backend::track_many`]'s first group (and every group on the CPU); later
/// groups on a GPU are sized to fill one submission's device memory.
const GROUP: usize = 256;

/// Most binding-sized parts in one submission: bounds the device memory one submission
/// takes to about this many times the adapter's largest binding.
const SUBMISSION_PARTS: u64 = 8;

/// Test hook: pretend the device is lost after this many batches (the value of the
/// environment variable `SKELID_GPU_FAIL_AFTER`), to exercise the mid-batch fallback.
const FAIL_AFTER_ENV: &str = "SKELID_GPU_FAIL_AFTER";

/// The chosen backend, shared by all worker threads.
pub struct Backend {
    gpu: Option<GpuService>,
    warnings: Mutex<Warnings>,
}

/// What the dispatcher has done, for the user's summary.
#[derive(Default)]
struct Stats {
    batches: std::sync::atomic::AtomicUsize,
    signals: std::sync::atomic::AtomicUsize,
}

#[derive(Default)]
struct Warnings {
    notes: Vec<String>,
    first: Vec<String>,
    count: usize,
}

/// One signal to track: samples, sample rate (Hz), and the guide's frequency per sample.
#[derive(Debug, Clone, Copy)]
pub struct Signal<'a> {
    /// The samples.
    pub samples: &'a [f64],
    /// Sample rate (Hz).
    pub sample_rate: f64,
    /// The guide's frequency (Hz) per sample, if the ridge is guided.
    pub guide: Option<&'a [f64]>,
}

/// What the GPU did for one signal: its ridge, and its skeleton on its estimation grid (or
/// why the GPU could not refine it, for the CPU to do from the ridge).
struct GpuPass {
    ridge: CoarseRidge,
    refined: Result<(Vec<GridPoint>, Vec<GridEstimate>), GpuError>,
}

/// A signal after the GPU.
struct Passed {
    prep: WaveletPrep,
    /// What the GPU did (or why not); `None` for the CPU to do everything.
    pass: Option<Result<GpuPass, GpuError>>,
}

/// The dispatcher's answer to one request.
struct Answer {
    /// The request's tag (its place among the signals handed over).
    tag: usize,
    /// The signal, back.
    prep: WaveletPrep,
    /// What the GPU did, or why not.
    result: Result<GpuPass, GpuError>,
}

/// Signals handed to the dispatcher: answered slots so far, and where the rest arrive
/// (`None` on the CPU backend, every slot already filled).
struct Sent {
    out: Vec<Option<Passed>>,
    answers: Option<Receiver<Answer>>,
}

/// A group of [`Backend::track_many`] in flight: per signal, its preparation error or
/// `None` for a track to come, and the prepared signals handed over.
struct Group {
    slots: Vec<Option<Result<Track, TrackError>>>,
    sent: Sent,
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

struct GpuService {
    adapter: String,
    /// Device memory (bytes, as [`batch_bytes`] counts it) one submission may take: half the
    /// adapter's largest binding times [`SUBMISSION_PARTS`]. Batches are sized to it.
    submission_budget: u64,
    /// Submissions made and signals they carried (successful ones).
    stats: Arc<Stats>,
    queue: Mutex<Option<Sender<Request>>>,
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

impl Backend {
    /// The CPU backend.
    pub fn cpu() -> Backend {
        Backend {
            gpu: None,
            warnings: Mutex::default(),
        }
    }

    /// Opens the backend asked for. `Auto` never fails: without a usable GPU it is the CPU,
    /// and [`warnings`](Self::warnings) says why. `Gpu` fails with the reason instead.
    pub fn open(choice: BackendChoice) -> Result<Backend, GpuError> {
        match choice {
            BackendChoice::Cpu => Ok(Backend::cpu()),
            BackendChoice::Gpu => Backend::start_gpu(),
            BackendChoice::Auto => {
                // Look at the adapter before opening a device on it.
                let opened = match Gpu::probe() {
                    Ok((name, true)) => Err(Ok(name)),
                    Ok((_, false)) => Backend::start_gpu().map_err(Err),
                    Err(e) => Err(Err(e)),
                };
                Ok(opened.unwrap_or_else(|why| {
                    let cpu = Backend::cpu();
                    match why {
                        Ok(software) => cpu.note(format!(
                            "only a software GPU adapter was found ({software}): using the \
                             CPU backend, which is faster; {} uses the adapter anyway",
                            crate::hint::Hint::GpuBackend
                        )),
                        Err(e) => cpu.warn(format!("GPU backend unavailable, using the CPU: {e}")),
                    }
                    cpu
                }))
            }
        }
    }

    fn start_gpu() -> Result<Backend, GpuError> {
        let fail_after = std::env::var(FAIL_AFTER_ENV)
            .ok()
            .and_then(|v| v.parse::<usize>().ok());
        let (tx, rx) = mpsc::channel::<Request>();
        let (ready_tx, ready_rx) = mpsc::channel();
        let stats = Arc::new(Stats::default());
        let counted = stats.clone();
        // The device lives on the dispatcher thread; it ends when the last sender is dropped.
        let thread = std::thread::Builder::new()
            .name("skelid-gpu".into())
            .spawn(move || {
                let opened = Gpu::new().and_then(|gpu| {
                    let stages = Stages {
                        first: FirstPass::new(&gpu)?,
                        refine: RefineStage::new(&gpu),
                    };
                    Ok((gpu, stages))
                });
                match opened {
                    Ok((gpu, stages)) => {
                        let budget = gpu.max_binding() / 2 * SUBMISSION_PARTS;
                        let _ = ready_tx.send(Ok((gpu.adapter_name(), budget)));
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
        let (adapter, submission_budget) = match ready {
            Ok(a) => a,
            Err(e) => {
                let _ = thread.join();
                return Err(e);
            }
        };
        Ok(Backend {
            gpu: Some(GpuService {
                adapter,
                submission_budget,
                stats,
                queue: Mutex::new(Some(tx)),
                thread: Some(thread),
            }),
            warnings: Mutex::default(),
        })
    }

    /// Whether a GPU device is open.
    pub fn is_gpu(&self) -> bool {
        self.gpu.is_some()
    }

    /// The GPU adapter's name and kind, when one is open.
    pub fn adapter(&self) -> Option<&str> {
        self.gpu.as_ref().map(|g| g.adapter.as_str())
    }

    /// Signals the GPU has done and the batches they took (two submissions each: first
    /// pass, refinement), when a GPU is open.
    pub fn gpu_work(&self) -> Option<(usize, usize)> {
        use std::sync::atomic::Ordering::Relaxed;
        self.gpu
            .as_ref()
            .map(|g| (g.stats.signals.load(Relaxed), g.stats.batches.load(Relaxed)))
    }

    /// Why `auto` chose the CPU although an adapter exists (a software one), if it did.
    pub fn notes(&self) -> Vec<String> {
        self.warnings
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .notes
            .clone()
    }

    fn note(&self, text: String) {
        self.warnings
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .notes
            .push(text);
    }

    /// Warnings so far (the GPU unavailable, signals that fell back to the CPU): the first
    /// few in full, then how many more.
    pub fn warnings(&self) -> Vec<String> {
        let w = self.warnings.lock().unwrap_or_else(|p| p.into_inner());
        let mut out = w.first.clone();
        if w.count > w.first.len() {
            out.push(format!(
                "… and {} more GPU fallback warning(s)",
                w.count - w.first.len()
            ));
        }
        out
    }

    fn warn(&self, text: String) {
        let mut w = self.warnings.lock().unwrap_or_else(|p| p.into_inner());
        w.count += 1;
        if w.first.len() < 5 {
            w.first.push(text);
        }
    }

    /// The wavelet track of one signal (see [`crate::track::track_wavelet`]), its first
    /// pass on this backend. Blocks while the GPU batch it joins is computed.
    pub fn track_wavelet(
        &self,
        x: &[f64],
        fs: f64,
        opt: &WaveletOptions,
        guide: Option<&[f64]>,
    ) -> Result<Track, TrackError> {
        self.track_wavelet_keeping(x, fs, opt, guide, false)
    }

    /// [`track_wavelet`](Self::track_wavelet), keeping the first pass's |W| grid in the
    /// track when `keep_scalogram` (read back from the GPU only then).
    pub fn track_wavelet_keeping(
        &self,
        x: &[f64],
        fs: f64,
        opt: &WaveletOptions,
        guide: Option<&[f64]>,
        keep_scalogram: bool,
    ) -> Result<Track, TrackError> {
        let mut prep = WaveletPrep::new(x, fs, opt, guide)?;
        prep.keep_scalogram = keep_scalogram;
        let mut answers = self.first_passes(vec![prep]);
        let passed = answers.pop().expect("one answer per signal");
        Ok(self.finish(passed.prep, passed.pass))
    }

    /// The wavelet tracks of many signals, all with the same options, in order: prepared
    /// in parallel, handed to the GPU together (in batches sized to the adapter's memory),
    /// finished in parallel. Groups are pipelined: the next group is prepared and handed
    /// to the GPU before the previous one is collected, so that the CPU's preparation and
    /// finishing overlap the device's work. The first group holds [`GROUP`] signals; on a
    /// GPU the later ones as many as fill one submission's device memory by the first
    /// group's measure (up to [`MAX_BATCH`]: thousands on a large GPU). For benchmarks and
    /// commands that hold all their signals.
    pub fn track_many(
        &self,
        signals: &[Signal],
        opt: &WaveletOptions,
    ) -> Vec<Result<Track, TrackError>> {
        use rayon::prelude::*;
        let mut out = Vec::with_capacity(signals.len());
        // At most two groups of prepared spectra in memory at once.
        let mut pending: Option<Group> = None;
        let mut size = GROUP;
        let mut at = 0;
        while at < signals.len() {
            let group = &signals[at..(at + size).min(signals.len())];
            at += group.len();
            let preps: Vec<Result<WaveletPrep, TrackError>> = group
                .par_iter()
                .map(|s| WaveletPrep::new(s.samples, s.sample_rate, opt, s.guide))
                .collect();
            if let Some(budget) = self.gpu.as_ref().map(|g| g.submission_budget) {
                let (bytes, n) = preps
                    .iter()
                    .flatten()
                    .fold((0u64, 0u64), |(b, n), p| (b + batch_bytes(p), n + 1));
                if let Some(each) = bytes.checked_div(n) {
                    let fit = budget / each.max(1);
                    size = (fit as usize).clamp(GROUP, MAX_BATCH);
                }
            }
            let mut ok = Vec::new();
            let mut slots: Vec<Option<Result<Track, TrackError>>> = Vec::new();
            for p in preps {
                match p {
                    Ok(p) => {
                        ok.push(p);
                        slots.push(None);
                    }
                    Err(e) => slots.push(Some(Err(e))),
                }
            }
            let sent = self.send(ok);
            if let Some(previous) = pending.replace(Group { slots, sent }) {
                out.extend(self.finish_group(previous));
            }
        }
        if let Some(last) = pending {
            out.extend(self.finish_group(last));
        }
        out
    }

    /// A group's first passes, then its tracks finished in parallel, in order.
    fn finish_group(&self, group: Group) -> Vec<Result<Track, TrackError>> {
        use rayon::prelude::*;
        let mut tracks = self
            .receive(group.sent)
            .into_par_iter()
            .map(|p| self.finish(p.prep, p.pass))
            .collect::<Vec<Track>>()
            .into_iter();
        group
            .slots
            .into_iter()
            .map(|s| s.unwrap_or_else(|| Ok(tracks.next().expect("one track per prepared signal"))))
            .collect()
    }

    /// The first passes of `preps`, in order: on the GPU when one is open (a signal it
    /// cannot serve comes back with the reason), else `None` for the CPU to do.
    fn first_passes(&self, preps: Vec<WaveletPrep>) -> Vec<Passed> {
        self.receive(self.send(preps))
    }

    /// Hands `preps` to the GPU's dispatcher without waiting (see [`receive`](Self::receive)).
    fn send(&self, preps: Vec<WaveletPrep>) -> Sent {
        let count = preps.len();
        let mut out: Vec<Option<Passed>> = (0..count).map(|_| None).collect();
        let Some(service) = &self.gpu else {
            for (slot, p) in out.iter_mut().zip(preps) {
                *slot = Some(Passed {
                    prep: p,
                    pass: None,
                });
            }
            return Sent { out, answers: None };
        };
        let (reply, answers) = mpsc::channel();
        {
            let queue = service.queue.lock().unwrap_or_else(|p| p.into_inner());
            for (tag, prep) in preps.into_iter().enumerate() {
                let request = Request {
                    tag,
                    prep,
                    reply: reply.clone(),
                };
                let sent = match queue.as_ref() {
                    Some(q) => q.send(request),
                    None => Err(mpsc::SendError(request)),
                };
                if let Err(mpsc::SendError(r)) = sent {
                    let gone = GpuError::Lost("the GPU thread has ended".into());
                    out[r.tag] = Some(Passed {
                        prep: r.prep,
                        pass: Some(Err(gone)),
                    });
                }
            }
        }
        Sent {
            out,
            answers: Some(answers),
        }
    }

    /// Waits for every answer to what [`send`](Self::send) handed over, in order.
    fn receive(&self, sent: Sent) -> Vec<Passed> {
        let Sent { mut out, answers } = sent;
        if let Some(answers) = answers {
            for a in answers.iter() {
                out[a.tag] = Some(Passed {
                    prep: a.prep,
                    pass: Some(a.result),
                });
            }
        }
        out.into_iter()
            .map(|o| o.expect("the GPU thread answers every request it takes"))
            .collect()
    }

    /// The rest of a track after the GPU: its completion from the GPU's skeleton, or on the
    /// CPU whatever the GPU did not do (the refinement, or everything).
    fn finish(&self, prep: WaveletPrep, pass: Option<Result<GpuPass, GpuError>>) -> Track {
        match pass {
            Some(Ok(GpuPass {
                ridge,
                refined: Ok((grid, estimates)),
            })) => {
                return crate::profile::time(crate::profile::Stage::Refine, || {
                    prep.complete(ridge, &grid, &estimates, Device::Gpu)
                })
            }
            Some(Ok(GpuPass {
                ridge,
                refined: Err(e),
            })) => {
                self.warn(format!(
                    "GPU refinement failed, the skeleton done on the CPU: {e}"
                ));
                return prep.finish(ridge, Device::Gpu);
            }
            Some(Err(e)) => self.warn(format!(
                "GPU first pass failed, signal done on the CPU: {e}"
            )),
            None => {}
        }
        let ridge = prep.coarse_ridge();
        prep.finish(ridge, Device::Cpu)
    }
}

/// The compiled GPU stages the dispatcher runs.
struct Stages {
    first: FirstPass,
    refine: RefineStage,
}

/// The dispatcher: gathers requests for up to `LINGER` after the first, splits them into
/// parts that fit the adapter's bindings, and takes each batch through its two submissions
/// (first pass, then refinement; one blocking read-back each) before answering its requests.
/// Up to [`IN_FLIGHT`] submissions are on the device at once: the next batch is gathered,
/// uploaded and submitted while the previous one computes, and only then is the previous
/// one waited for and moved on.
fn dispatch(
    gpu: &Gpu,
    stages: &Stages,
    rx: Receiver<Request>,
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
    let mut flying: std::collections::VecDeque<Unit> = std::collections::VecDeque::new();
    let mut open = true;
    while open || !flying.is_empty() {
        let batch = if open {
            let (batch, still_open) = gather(&rx, !flying.is_empty(), submission_budget);
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
        for r in batch {
            match stages.first.check(gpu, &r.prep) {
                Ok(()) => kept.push(r),
                Err(e) => {
                    r.answer(Err(e));
                }
            }
        }
        for parts in split(kept, budget, submission_budget) {
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
                                crate::profile::dispatcher(|| stages.first.submit(gpu, &preps))
                            })
                        })
                    }
                }
            };
            batches += 1;
            flying.push_back(Unit {
                parts,
                flight: Flight::First(flight),
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
    let Unit { parts, flight } = unit;
    let preps = part_preps(&parts);
    match flight {
        Flight::First(flight) => {
            let done = flight.and_then(|f| {
                unpanicked(|| {
                    crate::profile::time_wall(crate::profile::Stage::FirstPass, || {
                        f.finish(gpu, &preps)
                    })
                })
            });
            let ridges = match done {
                Ok(d) => d,
                Err(e) => {
                    drop(preps);
                    fail(parts, e, dead);
                    return None;
                }
            };
            // In parallel (the global rayon pool idles while the workers wait on the GPU).
            let grids: Vec<Vec<Vec<GridPoint>>> = preps
                .iter()
                .zip(&ridges)
                .map(|(p, r)| {
                    use rayon::prelude::*;
                    p.par_iter().zip(r).map(|(p, r)| p.grid(&r.path)).collect()
                })
                .collect();
            let flight = match gpu_dead(dead) {
                Some(e) => Err(e),
                None => unpanicked(|| {
                    crate::profile::time_wall(crate::profile::Stage::Refine, || {
                        stages.refine.submit(gpu, &preps, &grids)
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
                },
            })
        }
        Flight::Refine {
            ridges,
            grids,
            flight,
        } => {
            let refined = flight.and_then(|f| {
                unpanicked(|| {
                    crate::profile::time_wall(crate::profile::Stage::Refine, || {
                        f.finish(gpu, &preps, &grids)
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
            for (r, ((ridge, grid), est)) in all.zip(answers) {
                let pass = GpuPass {
                    ridge,
                    refined: est.map(|e| (grid, e)),
                };
                r.answer(Ok(pass));
            }
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

/// The requests that arrive within `LINGER` of the first, until they fill `budget` bytes of
/// device memory (one submission's, as [`batch_bytes`] counts it) or number [`MAX_BATCH`].
/// Blocks for the first only when nothing is in flight (`busy` false); else waits at most
/// `LINGER`. Also says whether the queue is still open.
fn gather(rx: &Receiver<Request>, busy: bool, budget: u64) -> (Vec<Request>, bool) {
    use std::sync::mpsc::RecvTimeoutError;
    let first = if busy {
        match rx.recv_timeout(LINGER) {
            Ok(r) => r,
            Err(RecvTimeoutError::Timeout) => return (Vec::new(), true),
            Err(RecvTimeoutError::Disconnected) => return (Vec::new(), false),
        }
    } else {
        match rx.recv() {
            Ok(r) => r,
            Err(_) => return (Vec::new(), false),
        }
    };
    let mut bytes = batch_bytes(&first.prep);
    let mut batch = vec![first];
    let deadline = Instant::now() + LINGER;
    while batch.len() < MAX_BATCH && bytes < budget {
        let left = deadline.saturating_duration_since(Instant::now());
        match rx.recv_timeout(left) {
            Ok(r) => {
                bytes += batch_bytes(&r.prep);
                batch.push(r)
            }
            Err(RecvTimeoutError::Timeout) => break,
            Err(RecvTimeoutError::Disconnected) => return (batch, false),
        }
    }
    (batch, true)
}

/// Splits a batch into submissions of parts: each part one wavelet within `budget` bytes,
/// each submission within `submission_budget` (a request alone always fits one).
fn split(mut batch: Vec<Request>, budget: u64, submission_budget: u64) -> Vec<Vec<Vec<Request>>> {
    let mut submissions = Vec::new();
    while !batch.is_empty() {
        let mut parts: Vec<(Vec<Request>, u64)> = Vec::new();
        let mut rest = Vec::new();
        let mut total = 0u64;
        for r in batch.drain(..) {
            let b = batch_bytes(&r.prep);
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
