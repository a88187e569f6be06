//! Where the time goes: CPU seconds spent in each stage of the pipeline, summed over every
//! thread of the process (thread CPU time, so a thread waiting for a lock or for a core
//! counts nothing), and the host↔device traffic of the GPU backend. `skelid
//! bench` resets these, runs a batch and prints them; `skelid run` logs them at its end.
//!
//! Process-wide counters (relaxed atomics, a few per run) rather than values threaded
//! through every stage's signature: a stage adds what it spent and knows nothing else.
//!
//! A stage's CPU time is its calling thread's. Work it hands to rayon and that an idle
//! thread steals is counted by no stage, so the stages can sum to a little less than the
//! process's CPU time (1000-run batch: 86.7 of 90 s); a busy batch leaves little to steal.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use serde::Serialize;

/// A stage of the pipeline, as `skelid bench` reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Reading the input archives (the reader thread's waits on its child included).
    Read,
    /// The wavelet transform's first pass: the signal's spectrum (on the worker), then every
    /// scale, noise floors and the ridge programme (on the CPU, or one GPU submission's wall
    /// time on the dispatcher thread).
    FirstPass,
    /// The wavelet track after the ridge: W, W′, W″ at the ridge scales, bias correction
    /// (on the CPU, or the GPU refinement's wall time on the dispatcher thread), then
    /// envelope, frequency, phase and validity from the grid (CPU).
    Refine,
    /// The Hilbert track (CPU).
    Hilbert,
    /// ForceVib, the skeleton and the fits: identification minus its tracks.
    ForceVibFit,
    /// Encoding the results (compression included), on the workers.
    Encode,
    /// Writing the output folder (journal, results.h5, summaries, report).
    Write,
}

/// Every stage, in report order.
pub const STAGES: [Stage; 7] = [
    Stage::Read,
    Stage::FirstPass,
    Stage::Refine,
    Stage::Hilbert,
    Stage::ForceVibFit,
    Stage::Encode,
    Stage::Write,
];

impl Stage {
    /// Key in `skelid-bench.json`.
    pub fn name(self) -> &'static str {
        match self {
            Stage::Read => "read",
            Stage::FirstPass => "first_pass",
            Stage::Refine => "refine",
            Stage::Hilbert => "hilbert",
            Stage::ForceVibFit => "forcevib_fit",
            Stage::Encode => "encode",
            Stage::Write => "write",
        }
    }
}

static NANOS: [AtomicU64; 7] = [const { AtomicU64::new(0) }; 7];

/// GPU traffic counters.
static SUBMISSIONS: AtomicU64 = AtomicU64::new(0);
static SYNCS: AtomicU64 = AtomicU64::new(0);
static BYTES_UP: AtomicU64 = AtomicU64::new(0);
static BYTES_DOWN: AtomicU64 = AtomicU64::new(0);
static GPU_SIGNALS: AtomicU64 = AtomicU64::new(0);
static GPU_BATCHES: AtomicU64 = AtomicU64::new(0);
static OVERLAPPED: AtomicU64 = AtomicU64::new(0);
static DISPATCHER_NANOS: AtomicU64 = AtomicU64::new(0);
static DISPATCHER_WAIT_NANOS: AtomicU64 = AtomicU64::new(0);
static DISPATCHER_DEVICE_WAIT_CPU_NANOS: AtomicU64 = AtomicU64::new(0);
static HOST_PREPARE_NANOS: AtomicU64 = AtomicU64::new(0);
static HOST_COMPLETE_NANOS: AtomicU64 = AtomicU64::new(0);
static HOST_WAIT_NANOS: AtomicU64 = AtomicU64::new(0);
static GRID_POINTS: AtomicU64 = AtomicU64::new(0);
static HOST_SOLVED: AtomicU64 = AtomicU64::new(0);
static HOST_REFINED: AtomicU64 = AtomicU64::new(0);

/// Adds `d` to `stage`.
pub fn add(stage: Stage, d: Duration) {
    NANOS[stage as usize].fetch_add(d.as_nanos() as u64, Ordering::Relaxed);
}

/// Runs `f`, adding the CPU time this thread spent in it to `stage`.
pub fn time<T>(stage: Stage, f: impl FnOnce() -> T) -> T {
    let t0 = thread_cpu();
    let out = f();
    add(stage, thread_cpu().saturating_sub(t0));
    out
}

/// Runs `f`, adding its wall time to `stage`: for work done elsewhere (the device) while
/// this thread waits.
pub fn time_wall<T>(stage: Stage, f: impl FnOnce() -> T) -> T {
    let t0 = Instant::now();
    let out = f();
    add(stage, t0.elapsed());
    out
}

/// CPU time of the calling thread.
pub fn thread_cpu() -> Duration {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec, which lives on this stack frame.
    let ok = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) } == 0;
    if ok {
        Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32)
    } else {
        Duration::ZERO
    }
}

/// What the kernel did for the whole process so far: page faults that mapped memory
/// without reading a file (minor faults: mostly fresh pages zeroed), and system CPU
/// seconds over every thread. Zeros where `getrusage` fails.
pub fn kernel_share() -> (u64, f64) {
    // SAFETY: all-zero bytes are a valid rusage, and getrusage writes the one on this
    // stack frame.
    let (u, ok) = unsafe {
        let mut u: libc::rusage = std::mem::zeroed();
        let ok = libc::getrusage(libc::RUSAGE_SELF, &mut u) == 0;
        (u, ok)
    };
    if !ok {
        return (0, 0.0);
    }
    let system = u.ru_stime.tv_sec as f64 + 1e-6 * u.ru_stime.tv_usec as f64;
    (u.ru_minflt as u64, system)
}

/// The CPU's own share of a GPU batch of tracks: wall time spent preparing the signals
/// (`complete` false) or completing the tracks (`complete` true), every core at once.
pub fn host_share(complete: bool, d: Duration) {
    let counter = if complete {
        &HOST_COMPLETE_NANOS
    } else {
        &HOST_PREPARE_NANOS
    };
    counter.fetch_add(d.as_nanos() as u64, Ordering::Relaxed);
}

/// The caller of a GPU batch of tracks waited `d` (wall time) for the device's answers to
/// a group it had handed over: the part of that group's path through the dispatcher and the
/// device that its own preparing and completing of other groups did not cover.
pub fn host_waited(d: Duration) {
    HOST_WAIT_NANOS.fetch_add(d.as_nanos() as u64, Ordering::Relaxed);
}

/// Counts one queue submission to the GPU.
pub fn submitted() {
    SUBMISSIONS.fetch_add(1, Ordering::Relaxed);
}

/// Counts one blocking wait of the host for the device.
pub fn synced() {
    SYNCS.fetch_add(1, Ordering::Relaxed);
}

/// Counts bytes copied host → device.
pub fn uploaded(bytes: u64) {
    BYTES_UP.fetch_add(bytes, Ordering::Relaxed);
}

/// Counts bytes copied device → host.
pub fn downloaded(bytes: u64) {
    BYTES_DOWN.fetch_add(bytes, Ordering::Relaxed);
}

/// Counts one submission made while an earlier one was still on the device.
pub fn overlapped() {
    OVERLAPPED.fetch_add(1, Ordering::Relaxed);
}

/// Runs `f` on the GPU dispatcher's thread, adding the CPU time it spent there (not work it
/// hands to rayon) to the dispatcher's serial host time. Its waits for the device count only
/// for the CPU the driver spends in them, which is also added up apart ([`device_wait`]).
/// Also adds the time the thread was ready to run but waited for a core (the kernel's
/// run delay), where the kernel reports it.
pub fn dispatcher<T>(f: impl FnOnce() -> T) -> T {
    let w0 = run_delay();
    let (out, cpu, waited) = cpu_and_waits(f);
    DISPATCHER_NANOS.fetch_add(cpu, Ordering::Relaxed);
    DISPATCHER_DEVICE_WAIT_CPU_NANOS.fetch_add(waited, Ordering::Relaxed);
    if let (Some(w0), Some(w1)) = (w0, run_delay()) {
        DISPATCHER_WAIT_NANOS.fetch_add(w1.saturating_sub(w0), Ordering::Relaxed);
    }
    out
}

/// Runs `f`: its result, the CPU nanoseconds the calling thread spent in it, and of those
/// the nanoseconds inside [`device_wait`]s.
fn cpu_and_waits<T>(f: impl FnOnce() -> T) -> (T, u64, u64) {
    let t0 = thread_cpu();
    let waited0 = DEVICE_WAIT_CPU.with(std::cell::Cell::get);
    let out = f();
    let cpu = thread_cpu().saturating_sub(t0).as_nanos() as u64;
    let waited = DEVICE_WAIT_CPU.with(std::cell::Cell::get) - waited0;
    (out, cpu, waited)
}

thread_local! {
    /// CPU nanoseconds this thread has spent inside the driver's waits for the device.
    static DEVICE_WAIT_CPU: std::cell::Cell<u64> = const { std::cell::Cell::new(0) };
}

/// Runs `f`, a blocking wait for the device, counting the CPU time the calling thread spent
/// in it: a driver that polls while it waits (lavapipe does work there; some drivers spin)
/// shows up in the dispatcher's CPU time, and this tells how much of it was that.
pub fn device_wait<T>(f: impl FnOnce() -> T) -> T {
    let t0 = thread_cpu();
    let out = f();
    let spent = thread_cpu().saturating_sub(t0).as_nanos() as u64;
    DEVICE_WAIT_CPU.with(|c| c.set(c.get() + spent));
    out
}

/// Nanoseconds this thread has spent runnable but not running (waiting for a core), from
/// Linux's `/proc/thread-self/schedstat`; `None` where that is not available.
pub fn run_delay() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    text.split_whitespace().nth(1)?.parse().ok()
}

/// Counts the grid points a GPU refinement decoded (`points`), those whose f32 estimate it
/// did not trust and the host solved again in f64 from the GPU's W, W′, W″ (`solved`), and
/// those the host refined whole on the CPU, for want of a slot (`refined`).
pub fn refined_points(points: u64, solved: u64, refined: u64) {
    GRID_POINTS.fetch_add(points, Ordering::Relaxed);
    HOST_SOLVED.fetch_add(solved, Ordering::Relaxed);
    HOST_REFINED.fetch_add(refined, Ordering::Relaxed);
}

/// Counts one GPU batch (first pass and refinement of many signals) of `n` signals.
pub fn gpu_batch(n: usize) {
    GPU_BATCHES.fetch_add(1, Ordering::Relaxed);
    GPU_SIGNALS.fetch_add(n as u64, Ordering::Relaxed);
}

/// CPU seconds per stage and the GPU traffic since the last [`reset`].
#[derive(Debug, Clone, Default, Serialize)]
pub struct Profile {
    /// (stage name, CPU seconds; wall seconds for the GPU's submissions), in [`STAGES`]
    /// order.
    pub stages: Vec<(String, f64)>,
    /// GPU traffic.
    pub gpu: Traffic,
}

/// Host↔device traffic.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Traffic {
    /// Signals whose first pass ran on the GPU.
    pub signals: u64,
    /// GPU batches (first pass and refinement of many signals at once).
    pub batches: u64,
    /// Queue submissions (two per batch, first pass and refinement, each with the copies
    /// of its read-back).
    pub submissions: u64,
    /// Blocking waits of the host for the device.
    pub syncs: u64,
    /// Bytes host → device.
    pub bytes_up: u64,
    /// Bytes device → host.
    pub bytes_down: u64,
    /// Submissions made while an earlier one was still on the device (upload and compute
    /// of one batch overlapping the other's compute and read-back).
    pub overlapped: u64,
    /// CPU seconds of the dispatcher thread itself (encoding, uploads, laying out grids,
    /// reading back): the serial host work every GPU batch goes through. Its waits for the
    /// device count only for the CPU the driver spends in them (`dispatcher_wait_cpu_s`).
    pub dispatcher_cpu_s: f64,
    /// Of `dispatcher_cpu_s`, CPU seconds spent inside the driver's blocking waits for the
    /// device: zero for a driver that sleeps while the device works, the device's time for
    /// one that spins (added 2026-12-05).
    pub dispatcher_wait_cpu_s: f64,
    /// Seconds the dispatcher thread was ready to run but waited for a core (the CPU
    /// stages of other signals had every core), during its serial host work.
    pub dispatcher_core_wait_s: f64,
    /// Wall seconds the caller of a GPU batch of tracks spent preparing its signals on
    /// every core (checks, band, spectrum, plans) before handing them over.
    pub host_prepare_s: f64,
    /// Wall seconds it spent completing the tracks on every core (noise floor, validity,
    /// smoothing, every sample from the skeleton) once the device had answered.
    pub host_complete_s: f64,
    /// Wall seconds it waited for the device's answers between the two (the dispatcher's
    /// and the device's path that its own host work did not cover; added 2026-12-06).
    pub host_wait_s: f64,
    /// Grid points the GPU refined.
    pub grid_points: u64,
    /// Of those, points whose f32 bias correction or thresholds the host did not trust and
    /// solved again in f64 from the W, W′, W″ the GPU computed.
    pub host_solved: u64,
    /// Of those, points that found no slot for their W, W′, W″ and that the host refined
    /// whole on the CPU.
    pub host_refined: u64,
}

impl Traffic {
    /// Per signal: (signals per batch, syncs, bytes up, bytes down); `None` without GPU
    /// work.
    pub fn per_signal(&self) -> Option<(f64, f64, f64, f64)> {
        (self.signals > 0).then(|| {
            let n = self.signals as f64;
            (
                n / self.batches.max(1) as f64,
                self.syncs as f64 / n,
                self.bytes_up as f64 / n,
                self.bytes_down as f64 / n,
            )
        })
    }
}

/// The counters now.
pub fn snapshot() -> Profile {
    Profile {
        stages: STAGES
            .iter()
            .map(|&s| {
                let ns = NANOS[s as usize].load(Ordering::Relaxed);
                (s.name().to_string(), ns as f64 * 1e-9)
            })
            .collect(),
        gpu: Traffic {
            signals: GPU_SIGNALS.load(Ordering::Relaxed),
            batches: GPU_BATCHES.load(Ordering::Relaxed),
            submissions: SUBMISSIONS.load(Ordering::Relaxed),
            syncs: SYNCS.load(Ordering::Relaxed),
            bytes_up: BYTES_UP.load(Ordering::Relaxed),
            bytes_down: BYTES_DOWN.load(Ordering::Relaxed),
            overlapped: OVERLAPPED.load(Ordering::Relaxed),
            dispatcher_cpu_s: DISPATCHER_NANOS.load(Ordering::Relaxed) as f64 * 1e-9,
            dispatcher_core_wait_s: DISPATCHER_WAIT_NANOS.load(Ordering::Relaxed) as f64 * 1e-9,
            dispatcher_wait_cpu_s: DISPATCHER_DEVICE_WAIT_CPU_NANOS.load(Ordering::Relaxed) as f64
                * 1e-9,
            host_prepare_s: HOST_PREPARE_NANOS.load(Ordering::Relaxed) as f64 * 1e-9,
            host_complete_s: HOST_COMPLETE_NANOS.load(Ordering::Relaxed) as f64 * 1e-9,
            host_wait_s: HOST_WAIT_NANOS.load(Ordering::Relaxed) as f64 * 1e-9,
            grid_points: GRID_POINTS.load(Ordering::Relaxed),
            host_solved: HOST_SOLVED.load(Ordering::Relaxed),
            host_refined: HOST_REFINED.load(Ordering::Relaxed),
        },
    }
}

/// Sets every counter to zero.
pub fn reset() {
    for n in &NANOS {
        n.store(0, Ordering::Relaxed);
    }
    for c in [
        &SUBMISSIONS,
        &SYNCS,
        &BYTES_UP,
        &BYTES_DOWN,
        &GPU_SIGNALS,
        &GPU_BATCHES,
        &OVERLAPPED,
        &DISPATCHER_NANOS,
        &DISPATCHER_WAIT_NANOS,
        &DISPATCHER_DEVICE_WAIT_CPU_NANOS,
        &HOST_PREPARE_NANOS,
        &HOST_COMPLETE_NANOS,
        &HOST_WAIT_NANOS,
        &GRID_POINTS,
        &HOST_SOLVED,
        &HOST_REFINED,
    ] {
        c.store(0, Ordering::Relaxed);
    }
}

impl Profile {
    /// One line: each stage's seconds and share.
    pub fn line(&self) -> String {
        let total: f64 = self.stages.iter().map(|s| s.1).sum::<f64>().max(1e-12);
        self.stages
            .iter()
            .map(|(n, s)| format!("{n} {s:.2} s ({:.0} %)", 100.0 * s / total))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// Whether `SKELID_GPU_TRACE` asks for the GPU dispatcher's host spans ([`span`]).
pub fn tracing() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var_os("SKELID_GPU_TRACE").is_some_and(|v| v != "0"))
}

/// Count, wall and thread-CPU nanoseconds of each named span, and its thread's events.
type Spans = std::collections::BTreeMap<&'static str, (u64, u64, u64, Events)>;

/// What the calling thread went through besides computing: page faults (minor: a fresh
/// page; major: one read from disk), voluntary context switches (it slept: a lock, an
/// I/O, a wait) and involuntary ones (preempted). A span whose wall time exceeds its CPU
/// time says which of these the difference is.
#[derive(Debug, Clone, Copy, Default)]
pub struct Events {
    /// Page faults, minor and major.
    pub faults: u64,
    /// Voluntary context switches.
    pub slept: u64,
    /// Involuntary context switches.
    pub preempted: u64,
}

impl Events {
    /// The calling thread's counts since it started (zero where `getrusage` fails).
    pub fn now() -> Events {
        // SAFETY: getrusage writes one rusage, which lives on this stack frame.
        let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
        if unsafe { libc::getrusage(libc::RUSAGE_THREAD, &mut ru) } != 0 {
            return Events::default();
        }
        Events {
            faults: (ru.ru_minflt + ru.ru_majflt) as u64,
            slept: ru.ru_nvcsw as u64,
            preempted: ru.ru_nivcsw as u64,
        }
    }

    fn since(self, before: Events) -> Events {
        Events {
            faults: self.faults.saturating_sub(before.faults),
            slept: self.slept.saturating_sub(before.slept),
            preempted: self.preempted.saturating_sub(before.preempted),
        }
    }

    fn add(&mut self, other: Events) {
        self.faults += other.faults;
        self.slept += other.slept;
        self.preempted += other.preempted;
    }
}

static SPANS: std::sync::Mutex<Spans> = std::sync::Mutex::new(std::collections::BTreeMap::new());

/// Runs `f`, adding its wall and calling-thread CPU time to the span `name` when
/// `SKELID_GPU_TRACE` is set (a developer's view of the dispatcher's serial host work,
/// printed by [`print_spans`]); otherwise only runs `f`.
pub fn span<T>(name: &'static str, f: impl FnOnce() -> T) -> T {
    let _span = SpanGuard::new(name);
    f()
}

/// Prints the spans gathered since the last call to stderr and clears them (nothing when
/// `SKELID_GPU_TRACE` is unset).
pub fn print_spans(title: &str) {
    if !tracing() {
        return;
    }
    let spans = std::mem::take(&mut *SPANS.lock().unwrap_or_else(|p| p.into_inner()));
    eprintln!(
        "GPU trace, {title}: span, calls, wall ms, thread CPU ms, page faults, \
         sleeps, preemptions"
    );
    for (name, (n, wall, cpu, ev)) in spans {
        eprintln!(
            "  {name:<24} {n:>6} {:>10.1} {:>10.1} {:>9} {:>7} {:>7}",
            wall as f64 / 1e6,
            cpu as f64 / 1e6,
            ev.faults,
            ev.slept,
            ev.preempted
        );
    }
    let passes = std::mem::take(&mut *PASSES.lock().unwrap_or_else(|p| p.into_inner()));
    if !passes.is_empty() {
        eprintln!("GPU trace, {title}: device time by compute pass (timestamps): pass, passes, ms");
        for (name, (n, ns)) in passes {
            eprintln!("  {name:<24} {n:>6} {:>10.1}", ns / 1e6);
        }
    }
}

/// A span ([`span`]) that ends when dropped, for stretches of a function.
pub struct SpanGuard {
    name: &'static str,
    start: Option<(Instant, Duration, Events)>,
}

impl SpanGuard {
    /// Starts the span `name` (a no-op unless `SKELID_GPU_TRACE` is set).
    pub fn new(name: &'static str) -> SpanGuard {
        SpanGuard {
            name,
            start: tracing().then(|| (Instant::now(), thread_cpu(), Events::now())),
        }
    }
}

impl Drop for SpanGuard {
    fn drop(&mut self) {
        if let Some((w0, c0, e0)) = self.start {
            let (wall, cpu) = (w0.elapsed(), thread_cpu().saturating_sub(c0));
            let events = Events::now().since(e0);
            let mut spans = SPANS.lock().unwrap_or_else(|p| p.into_inner());
            let e = spans.entry(self.name).or_default();
            e.0 += 1;
            e.1 += wall.as_nanos() as u64;
            e.2 += cpu.as_nanos() as u64;
            e.3.add(events);
        }
    }
}

/// Count and device nanoseconds of each labelled compute pass ([`device_pass`]).
static PASSES: std::sync::Mutex<std::collections::BTreeMap<&'static str, (u64, f64)>> =
    std::sync::Mutex::new(std::collections::BTreeMap::new());

/// Adds one compute pass's device time (from GPU timestamps) under `label`, for
/// [`print_spans`].
pub fn device_pass(label: &'static str, ns: f64) {
    let mut passes = PASSES.lock().unwrap_or_else(|p| p.into_inner());
    let e = passes.entry(label).or_default();
    e.0 += 1;
    e.1 += ns;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(target_os = "linux")]
    #[test]
    fn the_wait_for_a_core_is_read_and_never_goes_back() {
        let first = run_delay().expect("Linux reports a thread's run delay");
        // Some work and a yield, so that the scheduler has had its chance to delay us.
        let mut x = 0u64;
        for i in 0..200_000u64 {
            x = x.wrapping_mul(31).wrapping_add(i);
        }
        std::hint::black_box(x);
        std::thread::yield_now();
        let second = run_delay().expect("still reported");
        assert!(second >= first, "{second} < {first}");
    }

    #[test]
    fn the_cpu_of_a_device_wait_is_counted_as_part_of_the_work_around_it() {
        // Thread-local and returned, not read from the counters that other tests reset.
        let spin = |ms| {
            let t0 = thread_cpu();
            while thread_cpu() - t0 < Duration::from_millis(ms) {}
        };
        let ((), cpu, waited) = cpu_and_waits(|| {
            spin(5);
            device_wait(|| spin(10));
        });
        assert!((10_000_000..15_000_000).contains(&waited), "{waited}");
        assert!(cpu >= waited + 5_000_000, "{cpu} {waited}");
        // Work without a wait for the device has none.
        let ((), cpu, waited) = cpu_and_waits(|| spin(5));
        assert_eq!(waited, 0);
        assert!(cpu >= 5_000_000);
    }

    #[test]
    fn reset_clears_the_dispatchers_core_wait() {
        DISPATCHER_WAIT_NANOS.fetch_add(1_000_000, Ordering::Relaxed);
        assert!(snapshot().gpu.dispatcher_core_wait_s >= 1e-3);
        reset();
        assert_eq!(snapshot().gpu.dispatcher_core_wait_s, 0.0);
    }
}
