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

use std::sync::mpsc::Receiver;
use std::sync::Mutex;

use crate::gpu::ridge::batch_bytes;
use crate::gpu::{Gpu, GpuError};
use crate::track::{Device, Track, TrackError, WaveletOptions, WaveletPrep};

mod dispatcher;

pub(crate) use dispatcher::panic_message;
use dispatcher::{Answer, GpuPass, GpuService};

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

/// Why `auto` need not look for a GPU adapter: on Linux a GPU driver is reached through a
/// device node, and where `/dev` shows none of them ([`is_gpu_node`]) the only adapter
/// wgpu could find is a software one, which `auto` passes over anyway. Looking costs
/// loading the Vulkan loader and every installed driver (lavapipe brings LLVM): 45–85 ms
/// at the start of every command here and 20–30 ms more at its exit, 2 % of a 200-run
/// batch on two cores. `None` where a node is present, where `/dev` cannot be read, and
/// off Linux: then the adapters are asked.
fn no_gpu_device() -> Option<String> {
    if !cfg!(target_os = "linux") {
        return None;
    }
    let any_node = std::fs::read_dir("/dev")
        .ok()?
        .filter_map(Result::ok)
        .any(|e| is_gpu_node(&e.file_name().to_string_lossy()));
    (!any_node).then(|| {
        format!(
            "no GPU device on this machine (/dev has no {}): using the CPU backend; {} \
             looks for an adapter anyway, a software one included",
            GPU_NODES.join(", "),
            crate::hint::Hint::GpuBackend
        )
    })
}

/// The device nodes through which Linux GPU drivers are reached: the DRM directory (Mesa's
/// drivers, NVIDIA's open module, virtio-gpu), NVIDIA's own nodes, WSL2's D3D12 bridge and
/// the proprietary mobile drivers (Qualcomm, Arm Mali, Vivante, PowerVR).
const GPU_NODES: [&str; 7] = [
    "dri/", "nvidia*", "dxg", "kgsl*", "mali*", "galcore", "pvr*",
];

/// Whether `choice` may open a GPU that computes the spectra itself: `gpu`, or `auto` where
/// a GPU device node exists. A command that prepares its signal before the backend is open
/// prepares it for that GPU ([`WaveletPrep::new_deferred`]) only then.
pub fn may_compute_spectra(choice: BackendChoice) -> bool {
    match choice {
        BackendChoice::Cpu => false,
        BackendChoice::Gpu => true,
        BackendChoice::Auto => no_gpu_device().is_none(),
    }
}

/// Whether `name`, an entry of `/dev`, is one of [`GPU_NODES`].
fn is_gpu_node(name: &str) -> bool {
    GPU_NODES.iter().any(|pattern| {
        let pattern = pattern.trim_end_matches('/');
        match pattern.strip_suffix('*') {
            Some(prefix) => name.starts_with(prefix),
            None => name == pattern,
        }
    })
}

/// Most signals in one batch, whatever the adapter's memory (their prepared spectra are held
/// in host memory while they wait: about 0.3 MB each at 30 000 samples).
pub(crate) const MAX_BATCH: usize = 4096;

/// The group size of [`Backend::track_many`] on a GPU, for `count` signals of which `fit`
/// fill one submission: equal groups, as few as fit, but at least two where `count` holds
/// two [`GROUP`]s, so that one group's completion on the CPU overlaps the next one's device
/// work. On an H100, `bench` of 2000 signals took 0.75 s in groups of 256 and 1744 (the
/// second's whole chain — upload, device, read-back, completion — unoverlapped), 0.59 s in
/// 256, 872 and 872 (the third prepared only once the first was complete) and 0.505 s in
/// two of 1000.
fn groups_of(count: usize, fit: usize) -> usize {
    let fit = fit.clamp(GROUP, MAX_BATCH);
    let groups = count
        .div_ceil(fit)
        .max(if count >= 2 * GROUP { 2 } else { 1 });
    count.div_ceil(groups).clamp(GROUP.min(count.max(1)), fit)
}

/// Nice steps below the process at which the compute pools' threads run. The GPU's
/// dispatcher is one serial thread that every batch goes through, the writer one that every
/// run goes through. With the pools below them, the H100's GPU `bench` took 0.51–0.54 s
/// instead of 0.63–0.65 s; the dispatcher's measured wait for a core was tiny either way,
/// so why is not known (README, "How a batch goes").
const COMPUTE_NICE: libc::c_int = 5;

/// Lowers the calling thread's scheduling priority by [`COMPUTE_NICE`] steps (Linux sets
/// it per thread): the start handler of the compute pools, so that the threads that feed
/// the GPU and write results (at the process's own priority) get a core when they need one.
/// Elsewhere, and where the kernel refuses, nothing changes.
pub fn lower_compute_priority() {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: plain system calls on the calling thread's own id.
        unsafe {
            let tid = libc::gettid() as libc::id_t;
            *libc::__errno_location() = 0;
            let now = libc::getpriority(libc::PRIO_PROCESS, tid);
            if *libc::__errno_location() == 0 {
                libc::setpriority(libc::PRIO_PROCESS, tid, (now + COMPUTE_NICE).min(19));
            }
        }
    }
}

/// Largest block that glibc's malloc still takes from its heaps rather than mapping on its
/// own (the most `mallopt` accepts on 64-bit, 32 MiB).
const HEAP_BLOCK_MAX: libc::c_int = 32 << 20;

/// Free memory at the top of the main heap kept for reuse rather than given back. A
/// one-signal group (one long record: `skelid track`, `bench` of a 2^20-sample record) is
/// completed on the calling thread, since rayon runs a parallel iterator of one item in
/// place, so on the main thread its arrays come from the main heap: at 64 MiB the 70 MB a
/// 2^20-sample track frees there were given back after each repetition and faulted in
/// again (about 17 700 page faults a repetition of `bench`, its completion 34–55 ms
/// instead of 22–41 on 2 cores). The threads' own heaps are at most 64 MiB, so any value
/// from there on changes the main heap alone; the peak is unchanged, only kept.
const KEEP_FREED: libc::c_int = 256 << 20;

/// Makes glibc's malloc keep freed blocks for reuse instead of giving them back to the
/// kernel at once. Every track allocates and frees arrays of a few hundred kilobytes; by
/// default glibc maps blocks above an adaptive threshold on their own and gives a heap's
/// free top back once it exceeds twice that threshold, so the kernel zeroed the same
/// pages again and again: on 2 cores 218 000 page faults and 0.54 s of system
/// time in a `bench` of 40 runs (7.4 s of CPU), 36 000 and 0.09 s with this, the peak
/// memory unchanged (159 MB). Called once at start-up; elsewhere than glibc, nothing.
/// `SKELID_MALLOC=default` leaves glibc as it is (to measure the difference); any other
/// value of it is answered with a note to print, and the setting applied.
pub fn keep_freed_memory() -> Option<String> {
    let asked = std::env::var(MALLOC_ENV).ok();
    if asked.as_deref() == Some("default") {
        return None;
    }
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets the allocator's parameters; any value is checked by glibc.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, HEAP_BLOCK_MAX);
        libc::mallopt(libc::M_TRIM_THRESHOLD, KEEP_FREED);
    }
    asked.filter(|v| v != "skelid").map(|v| {
        format!(
            "{MALLOC_ENV}={v:?} is not understood: `default` leaves glibc's malloc at its \
             defaults, `skelid` (or unset) keeps freed memory for reuse, as now"
        )
    })
}

/// Gives the pages of every freed block back to the kernel, in every thread's arena
/// (glibc's `malloc_trim`): after a run far larger than the next, whose memory the arenas
/// would otherwise keep. Elsewhere than glibc, nothing.
pub fn give_freed_memory_back() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free memory; it takes glibc's arena locks itself.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// The environment variable that leaves glibc's malloc at its defaults.
const MALLOC_ENV: &str = "SKELID_MALLOC";

/// Groups [`Backend::track_many`] hands to the GPU before it collects the oldest.
const AHEAD: usize = 2;

/// The environment variable that fixes [`Backend::track_many`]'s group size.
const GROUP_ENV: &str = "SKELID_GPU_GROUP";

/// A fixed group size for [`Backend::track_many`] (`SKELID_GPU_GROUP`, signals), for tuning
/// the pipelining of benchmarks on a new machine.
fn fixed_group() -> Option<usize> {
    signals_from_env(GROUP_ENV)
}

/// A positive whole number of signals from the environment variable `name`, if it holds one.
fn signals_from_env(name: &str) -> Option<usize> {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&n| n > 0)
}

/// The environment variable that sets the size of [`Backend::track_many`]'s first group
/// on a GPU, the others sized for the signals after it as they would be for a campaign of
/// that many.
const FIRST_GROUP_ENV: &str = "SKELID_GPU_FIRST_GROUP";

/// The first group's size on a GPU (`SKELID_GPU_FIRST_GROUP`, signals), for measuring the
/// pipeline's start. The device starts on nothing until the first group is prepared, and
/// the CPU completes nothing until that group has been through both passes; in between it
/// prepares the second group and then waits. With equal groups that wait was about a
/// quarter of an H200's `bench` repetition at 128 scales (2026-11-27): a smaller first
/// group starts the device sooner and comes back sooner, at the cost of one more batch.
fn first_group() -> Option<usize> {
    signals_from_env(FIRST_GROUP_ENV)
}

/// The lengths of the groups of `count` signals: `first` (when given and fewer than
/// `count`) and then groups of `size`, the last one what is left.
fn group_lengths(count: usize, first: Option<usize>, size: usize) -> Vec<usize> {
    let size = size.max(1);
    let mut lengths = Vec::new();
    let mut left = count;
    if let Some(n) = first.filter(|&n| n > 0 && n < count) {
        lengths.push(n);
        left -= n;
    }
    while left > 0 {
        let n = size.min(left);
        lengths.push(n);
        left -= n;
    }
    lengths
}

/// Signals in each of [`Backend::track_many`]'s groups on the CPU, and the fewest in a
/// group on a GPU (unless there are fewer signals).
const GROUP: usize = 256;

/// The chosen backend, shared by all worker threads.
pub struct Backend {
    gpu: Option<GpuService>,
    warnings: Mutex<Warnings>,
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

/// A signal after the GPU.
struct Passed {
    prep: WaveletPrep,
    /// What the GPU did (or why not); `None` for the CPU to do everything.
    pass: Option<Result<GpuPass, GpuError>>,
}

/// Signals handed to the dispatcher: answered slots so far, and where the rest arrive
/// (`None` on the CPU backend, every slot already filled).
struct Sent {
    out: Vec<Option<Passed>>,
    answers: Option<Receiver<Answer>>,
}

/// A group of [`Backend::track_each`] in flight: the index of each signal prepared, and the
/// prepared signals handed over.
struct Group {
    indices: Vec<usize>,
    sent: Sent,
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
                if let Some(why) = no_gpu_device() {
                    let cpu = Backend::cpu();
                    cpu.note(why);
                    return Ok(cpu);
                }
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
        let mut service = GpuService::start()?;
        let notes = std::mem::take(&mut service.notes);
        let b = Backend {
            gpu: Some(service),
            warnings: Mutex::default(),
        };
        for n in notes {
            b.note(n);
        }
        for (name, instead) in [
            (GROUP_ENV, "groups are sized to the adapter"),
            (FIRST_GROUP_ENV, "the first group is sized as the others"),
        ] {
            if let (Ok(v), None) = (std::env::var(name), signals_from_env(name)) {
                b.note(format!(
                    "{name}={v:?} is not a positive whole number of signals: ignored, {instead}"
                ));
            }
        }
        Ok(b)
    }

    /// Whether a GPU device is open.
    pub fn is_gpu(&self) -> bool {
        self.gpu.is_some()
    }

    /// The GPU adapter's name and kind, when one is open.
    pub fn adapter(&self) -> Option<&str> {
        self.gpu.as_ref().map(|g| g.adapter.as_str())
    }

    /// The GPU's shader precision, e.g. `first pass f64, refinement f64` (f64 where the
    /// adapter has SHADER_F64); none on the CPU.
    pub fn gpu_precision(&self) -> Option<String> {
        self.gpu.as_ref().map(|g| {
            format!(
                "first pass {}, refinement {}",
                g.real.name(),
                g.refine_real.name()
            )
        })
    }

    /// Whether the open GPU adapter is a software one (Mesa's lavapipe), which runs its
    /// invocations on the host's own cores: it shows the GPU code correct, never fast.
    pub fn is_software_gpu(&self) -> bool {
        self.gpu.as_ref().is_some_and(|g| g.software)
    }

    /// Signals the GPU has done and the batches they took (two submissions each: first
    /// pass, refinement), when a GPU is open.
    pub fn gpu_work(&self) -> Option<(usize, usize)> {
        self.gpu.as_ref().map(GpuService::work)
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
        self.track_wavelet_as(x, fs, opt, guide, keep_scalogram, true)
    }

    /// [`track_wavelet_keeping`](Self::track_wavelet_keeping) for a signal that no other is
    /// tracked beside ([`track_prepared_alone`](Self::track_prepared_alone)): `skelid track
    /// --reference`'s reference and then its guided record, one after the other.
    pub fn track_wavelet_alone(
        &self,
        x: &[f64],
        fs: f64,
        opt: &WaveletOptions,
        guide: Option<&[f64]>,
        keep_scalogram: bool,
    ) -> Result<Track, TrackError> {
        self.track_wavelet_as(x, fs, opt, guide, keep_scalogram, false)
    }

    /// A signal prepared here and tracked, its handover lingering for other signals or not
    /// ([`track_prepared_as`](Self::track_prepared_as)).
    fn track_wavelet_as(
        &self,
        x: &[f64],
        fs: f64,
        opt: &WaveletOptions,
        guide: Option<&[f64]>,
        keep_scalogram: bool,
        linger: bool,
    ) -> Result<Track, TrackError> {
        let mut prep = self.prepare(x, fs, opt, guide)?;
        prep.keep_scalogram = keep_scalogram;
        Ok(self.track_prepared_as(prep, linger))
    }

    /// A signal prepared for this backend: its padded spectrum left to the GPU where the
    /// GPU computes it ([`WaveletPrep::new_deferred`]; the device's stages in f64), else
    /// taken here ([`WaveletPrep::new`]).
    fn prepare(
        &self,
        x: &[f64],
        fs: f64,
        opt: &WaveletOptions,
        guide: Option<&[f64]>,
    ) -> Result<WaveletPrep, TrackError> {
        if self.spectra_on_device() {
            WaveletPrep::new_deferred(x, fs, opt, guide)
        } else {
            WaveletPrep::new(x, fs, opt, guide)
        }
    }

    /// Where this backend's GPU computes the padded spectra: `device` or `host` (none on
    /// the CPU backend).
    pub fn spectra_where(&self) -> Option<&'static str> {
        self.gpu.as_ref().map(|g| {
            if g.spectra_on_device {
                "device"
            } else {
                "host"
            }
        })
    }

    /// Whether this backend's GPU computes the padded spectra itself, so that signals for
    /// it are best prepared by [`WaveletPrep::new_deferred`].
    pub fn spectra_on_device(&self) -> bool {
        self.gpu.as_ref().is_some_and(|g| g.spectra_on_device)
    }

    /// The wavelet track of a signal already prepared ([`WaveletPrep::new`], which needs
    /// no backend, or [`WaveletPrep::new_deferred`], whose spectrum the CPU computes here
    /// if this backend does not): lets a command prepare its signal while the backend
    /// opens.
    pub fn track_prepared(&self, prep: WaveletPrep) -> Track {
        self.track_prepared_as(prep, true)
    }

    /// [`track_prepared`](Self::track_prepared) for a signal that no other is tracked
    /// beside (`skelid track`'s records): the GPU's dispatcher starts on it at once
    /// instead of waiting a few milliseconds for other threads' signals to batch with.
    pub fn track_prepared_alone(&self, prep: WaveletPrep) -> Track {
        self.track_prepared_as(prep, false)
    }

    /// [`track_prepared`](Self::track_prepared), its handover lingering for other signals
    /// or not ([`GpuService::send`]).
    fn track_prepared_as(&self, mut prep: WaveletPrep, linger: bool) -> Track {
        if !self.spectra_on_device() {
            prep.materialize();
        }
        let mut answers = self.receive(self.send(vec![prep], linger));
        let passed = answers.pop().expect("one answer per signal");
        self.finish(passed.prep, passed.pass)
    }

    /// The wavelet tracks of many signals, all with the same options, in order: prepared
    /// in parallel, handed to the GPU together (in batches sized to the adapter's memory),
    /// finished in parallel. Groups are pipelined: the next group is prepared and handed
    /// to the GPU before the previous one is collected, so that the CPU's preparation and
    /// finishing overlap the device's work. Groups hold [`GROUP`] signals on the CPU; on a
    /// GPU they are equal, at most what fills one submission's device memory (up to
    /// [`MAX_BATCH`]: thousands on a large GPU), at least two ([`groups_of`]), unless
    /// `SKELID_GPU_FIRST_GROUP` gives the first group a size of its own. For
    /// commands that need every track at once; [`track_each`](Self::track_each) lets each
    /// go as it is made.
    pub fn track_many(
        &self,
        signals: &[Signal],
        opt: &WaveletOptions,
    ) -> Vec<Result<Track, TrackError>> {
        let slots: Vec<Mutex<Option<Result<Track, TrackError>>>> =
            (0..signals.len()).map(|_| Mutex::new(None)).collect();
        self.track_each(signals, opt, |i, t| {
            *slots[i].lock().expect("a slot's lock is never poisoned") = Some(t)
        });
        slots
            .into_iter()
            .map(|s| {
                s.into_inner()
                    .expect("a slot's lock is never poisoned")
                    .expect("track_each hands over every signal's track")
            })
            .collect()
    }

    /// [`track_many`](Self::track_many), handing each track (by its signal's index) to
    /// `consume` on the thread that completed it, the moment it is complete, in no set
    /// order. A consumer that lets the track go keeps memory to a group's spectra and the
    /// tracks being completed, and the next track reuses the same thread's freed arrays
    /// while they are still in its cache: holding 2000 tracks of 30 000 samples took
    /// 3.4 GB, and each repetition of `bench` had the kernel map and zero fresh pages.
    pub fn track_each<F>(&self, signals: &[Signal], opt: &WaveletOptions, consume: F)
    where
        F: Fn(usize, Result<Track, TrackError>) + Sync,
    {
        use rayon::prelude::*;
        // Groups handed over and not yet collected: while the oldest is completed on the
        // CPU, the next ones are on the device, so that it never waits for a preparation
        // queued behind a completion. At most AHEAD + 1 groups of prepared spectra at once.
        let mut pending: std::collections::VecDeque<Group> = std::collections::VecDeque::new();
        // A first group of its own size leaves the others sized for the signals after it.
        let first_len = first_group().filter(|&n| self.gpu.is_some() && n < signals.len());
        let rest = &signals[first_len.unwrap_or(0)..];
        let size = fixed_group().unwrap_or_else(|| self.group_size(rest, opt));
        let mut at = 0;
        for len in group_lengths(signals.len(), first_len, size) {
            let first = at;
            let group = &signals[at..at + len];
            at += len;
            let t0 = std::time::Instant::now();
            let preps: Vec<Result<WaveletPrep, TrackError>> =
                crate::profile::span("host.prepare", || {
                    group
                        .par_iter()
                        .map(|s| self.prepare(s.samples, s.sample_rate, opt, s.guide))
                        .collect()
                });
            if self.gpu.is_some() {
                crate::profile::host_share(false, t0.elapsed());
            }
            let mut ok = Vec::new();
            let mut indices = Vec::new();
            for (i, p) in preps.into_iter().enumerate() {
                match p {
                    Ok(p) => {
                        ok.push(p);
                        indices.push(first + i);
                    }
                    Err(e) => consume(first + i, Err(e)),
                }
            }
            // A group is whole: nothing else comes to share its batch.
            pending.push_back(Group {
                indices,
                sent: self.send(ok, false),
            });
            if pending.len() > AHEAD {
                let oldest = pending.pop_front().expect("a pending group");
                self.finish_group(oldest, &consume);
            }
        }
        for group in pending {
            self.finish_group(group, &consume);
        }
    }

    /// Signals per group in [`track_many`](Self::track_many): [`GROUP`] on the CPU; on a
    /// GPU [`groups_of`] by what one submission holds, measured, where there are more than
    /// [`GROUP`] signals, on the first one (which is prepared twice: one FFT).
    fn group_size(&self, signals: &[Signal], opt: &WaveletOptions) -> usize {
        // Up to GROUP signals are one group whatever a submission holds (`groups_of`), so
        // none is prepared to measure it: a GPU `bench` of one 2^20-sample record prepared
        // it twice a repetition (11.6 ms on 2 cores, on the main thread before any other
        // work).
        if signals.len() <= GROUP {
            return GROUP;
        }
        let (Some(service), Some(s)) = (&self.gpu, signals.first()) else {
            return GROUP;
        };
        match self.prepare(s.samples, s.sample_rate, opt, s.guide) {
            Ok(p) => {
                let fit = service.submission_budget / batch_bytes(&p, service.real).max(1);
                groups_of(signals.len(), usize::try_from(fit).unwrap_or(usize::MAX))
            }
            Err(_) => GROUP,
        }
    }

    /// A group's first passes, then its tracks finished in parallel, each handed to
    /// `consume` as it is done.
    fn finish_group<F>(&self, group: Group, consume: &F)
    where
        F: Fn(usize, Result<Track, TrackError>) + Sync,
    {
        use rayon::prelude::*;
        let waited = std::time::Instant::now();
        let passed = crate::profile::span("host.receive", || self.receive(group.sent));
        if self.gpu.is_some() {
            crate::profile::host_waited(waited.elapsed());
        }
        // `zip` would stop at the shorter side and lose tracks without a word.
        assert_eq!(
            passed.len(),
            group.indices.len(),
            "one answer per prepared signal"
        );
        let t0 = std::time::Instant::now();
        crate::profile::span("host.complete", || {
            passed
                .into_par_iter()
                .zip(group.indices)
                .for_each(|(p, i)| consume(i, Ok(self.finish(p.prep, p.pass))))
        });
        if self.gpu.is_some() {
            crate::profile::host_share(true, t0.elapsed());
        }
    }

    /// Hands `preps` to the GPU's dispatcher without waiting (see [`receive`](Self::receive)),
    /// their batch lingering for other senders' signals or not ([`GpuService::send`]).
    fn send(&self, preps: Vec<WaveletPrep>, linger: bool) -> Sent {
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
        let (unsent, answers) = service.send(preps, linger);
        for (tag, prep, gone) in unsent {
            out[tag] = Some(Passed {
                prep,
                pass: Some(Err(gone)),
            });
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
    fn finish(&self, mut prep: WaveletPrep, pass: Option<Result<GpuPass, GpuError>>) -> Track {
        // Whatever the CPU does from here on, other than the completion and the unsure
        // points' solves, reads the spectrum: it computes it where the GPU was to.
        let host_work = !matches!(
            &pass,
            Some(Ok(GpuPass {
                refined: Ok((_, decoded)),
                ..
            })) if !decoded.refines_on_host()
        );
        if host_work {
            prep.materialize();
        } else {
            // Nothing from here reads the samples (the completion and the unsure points'
            // solves read the grid's records): their buffer back for the next signal.
            prep.deferred = None;
        }
        match pass {
            Some(Ok(GpuPass {
                ridge,
                refined: Ok((grid, decoded)),
            })) => {
                return crate::profile::time(crate::profile::Stage::Refine, || {
                    let estimates = decoded.solve(&prep, &grid);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gpu_device_nodes_are_told_from_the_rest_of_dev() {
        for gpu in [
            "dri",
            "nvidia0",
            "nvidiactl",
            "nvidia-uvm",
            "dxg",
            "kgsl-3d0",
            "mali0",
            "galcore",
            "pvr_sync",
        ] {
            assert!(is_gpu_node(gpu), "{gpu}");
        }
        for other in [
            "null", "tty0", "vda", "nvme0n1", "drivers", "dx", "dxgkrnl", "kvm", "fuse", "shm",
        ] {
            assert!(!is_gpu_node(other), "{other}");
        }
    }

    /// `auto` skips the adapter search exactly where `/dev` has no GPU node, checked here
    /// against the paths themselves.
    #[cfg(target_os = "linux")]
    #[test]
    fn auto_looks_for_an_adapter_only_where_dev_has_a_gpu_node() {
        let present = ["/dev/dri", "/dev/nvidiactl", "/dev/nvidia0", "/dev/dxg"]
            .iter()
            .any(|p| std::path::Path::new(p).exists());
        match no_gpu_device() {
            Some(why) => {
                assert!(!present, "{why}");
                assert!(why.contains("/dev has no dri/, nvidia*, dxg"), "{why}");
            }
            None => {
                let listed = std::fs::read_dir("/dev")
                    .unwrap()
                    .any(|e| is_gpu_node(&e.unwrap().file_name().to_string_lossy()));
                assert!(present || listed);
            }
        }
    }

    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[test]
    fn freed_arrays_are_reused_without_the_kernel_zeroing_them_again() {
        // Minor page faults of this thread alone (the other tests run beside it).
        let faults = || {
            // SAFETY: getrusage fills the struct it is given.
            unsafe {
                let mut u: libc::rusage = std::mem::zeroed();
                libc::getrusage(libc::RUSAGE_THREAD, &mut u);
                u.ru_minflt
            }
        };
        keep_freed_memory();
        // A track's arrays: four of 30 000 × 8 f64, written, then all freed, again and again.
        let touch = || {
            let v: Vec<Vec<f64>> = (0..4).map(|_| vec![1.0f64; 30_000 * 8]).collect();
            drop(std::hint::black_box(v));
        };
        touch();
        // By default glibc raises its mapping threshold to the first block freed and trims
        // a heap whose free top exceeds twice that: 7.7 MB freed at once is given back and
        // faulted in again (1 880 pages) every round. The least of five rounds of 20, in
        // case another thread of this arena took the freed blocks in between.
        let again = (0..5)
            .map(|_| {
                let before = faults();
                for _ in 0..20 {
                    touch();
                }
                faults() - before
            })
            .min()
            .unwrap();
        println!("{again} page faults in the best round of 20 (without the setting: 36 860)");
        assert!(
            again < 100,
            "{again} page faults for 20 rounds of reused arrays"
        );
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn a_compute_thread_runs_below_the_process_and_no_other_thread_does() {
        // SAFETY: plain system calls on the calling thread's own id.
        let nice =
            || unsafe { libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t) };
        let here = nice();
        let (before, after) = std::thread::spawn(move || {
            let before = nice();
            lower_compute_priority();
            (before, nice())
        })
        .join()
        .unwrap();
        assert_eq!(after, (before + COMPUTE_NICE).min(19));
        assert_eq!(nice(), here, "the calling thread only");
    }

    /// Up to GROUP signals are one group whatever one submission holds: what lets
    /// `group_size` skip preparing a signal to measure it.
    #[test]
    fn up_to_a_group_of_signals_is_one_group_whatever_a_submission_holds() {
        for count in 1..=GROUP {
            for fit in [
                0,
                1,
                2,
                count / 2,
                count,
                GROUP,
                4096,
                MAX_BATCH,
                usize::MAX,
            ] {
                assert_eq!(groups_of(count, fit), count, "{count} signals, {fit} fit");
            }
        }
    }

    /// The groups cover the signals in order, each once: a first group as asked when it is
    /// fewer than all, then groups of the size, the last what is left.
    #[test]
    fn a_first_group_of_its_own_size_then_groups_of_the_size_cover_every_signal_once() {
        for count in 0..=40 {
            for size in [1, 2, 3, 7, 40, 100] {
                for first in [
                    None,
                    Some(0),
                    Some(1),
                    Some(5),
                    Some(count),
                    Some(count + 3),
                ] {
                    let lengths = group_lengths(count, first, size);
                    assert_eq!(
                        lengths.iter().sum::<usize>(),
                        count,
                        "{count} {first:?} {size}"
                    );
                    assert!(lengths.iter().all(|&n| n > 0), "{count} {first:?} {size}");
                    let own = first.filter(|&n| n > 0 && n < count);
                    let rest = match own {
                        Some(n) => {
                            assert_eq!(lengths[0], n, "{count} {first:?} {size}");
                            &lengths[1..]
                        }
                        None => &lengths[..],
                    };
                    let (last, full) = rest.split_last().unwrap_or((&0, &[]));
                    assert!(full.iter().all(|&n| n == size), "{count} {first:?} {size}");
                    assert!(*last <= size, "{count} {first:?} {size}");
                }
            }
        }
        // 2000 signals, a first group of 250: the other 1750 in two groups of 875.
        assert_eq!(
            group_lengths(2000, Some(250), groups_of(1750, 4096)),
            [250, 875, 875]
        );
    }

    #[test]
    fn groups_split_the_signals_evenly_within_a_submission() {
        // 2000 signals of which 4096 would fit: two groups of 1000.
        assert_eq!(groups_of(2000, 4096), 1000);
        assert_eq!(groups_of(2001, 4096), 1001);
        // More than fits: as few equal groups as fit.
        assert_eq!(groups_of(10_000, 3000), 2500);
        // Never beyond one submission, nor beyond MAX_BATCH, nor under GROUP.
        assert_eq!(groups_of(100_000, 1_000_000), 4000);
        assert_eq!(groups_of(5000, 1), GROUP);
        // Too few for two groups of GROUP: one.
        assert_eq!(groups_of(300, 4096), 300);
        assert_eq!(groups_of(7, 4096), 7);
    }

    #[test]
    fn track_each_hands_over_every_signals_track_once_and_as_track_many_makes_it() {
        // More than AHEAD + 1 CPU groups (GROUP = 256), so that groups are finished while
        // others are pending as well as at the end, with a signal too short to track and a
        // constant one among them: each error reaches the consumer at its own index.
        let signal = |k: usize| -> Vec<f64> {
            let f = 8.0 + (k % 13) as f64;
            (0..1500)
                .map(|i| {
                    let t = i as f64 / 500.0;
                    (-0.3 * t).exp() * (2.0 * std::f64::consts::PI * f * t).sin()
                })
                .collect()
        };
        let mut data: Vec<Vec<f64>> = (0..(AHEAD + 1) * GROUP + 20).map(signal).collect();
        let failing = [7, 2 * GROUP + 3];
        data[failing[0]] = vec![1.0; 10];
        data[failing[1]] = vec![0.5; 1500];
        let signals: Vec<Signal> = data
            .iter()
            .map(|x| Signal {
                samples: x,
                sample_rate: 500.0,
                guide: None,
            })
            .collect();
        let opt = WaveletOptions {
            scales: 32,
            ..Default::default()
        };
        let cpu = Backend::cpu();
        let seen: Vec<Mutex<Vec<Result<Track, TrackError>>>> =
            signals.iter().map(|_| Mutex::default()).collect();
        cpu.track_each(&signals, &opt, |i, t| seen[i].lock().unwrap().push(t));
        let many = cpu.track_many(&signals, &opt);
        for (i, got) in seen.into_iter().enumerate() {
            let got = got.into_inner().unwrap();
            assert_eq!(got.len(), 1, "signal {i} handed over {} times", got.len());
            let s = &signals[i];
            let alone = cpu.track_wavelet(s.samples, s.sample_rate, &opt, None);
            match (&got[0], &many[i], &alone) {
                (Ok(a), Ok(b), Ok(c)) => {
                    assert_eq!(a.amplitude, b.amplitude, "signal {i}");
                    assert_eq!(a.amplitude, c.amplitude, "signal {i}");
                    assert_eq!(a.frequency, c.frequency, "signal {i}");
                    assert_eq!(a.valid, c.valid, "signal {i}");
                    assert!(a.valid.iter().any(|&v| v), "signal {i} tracked nowhere");
                }
                (Err(a), Err(b), Err(c)) => {
                    assert!(failing.contains(&i), "signal {i} failed: {a}");
                    assert_eq!(
                        (a.to_string(), b.to_string()),
                        (c.to_string(), c.to_string())
                    );
                }
                _ => panic!("signal {i}: track_each, track_many and alone disagree on failing"),
            }
            assert_eq!(got[0].is_err(), failing.contains(&i), "signal {i}");
        }
    }
}
