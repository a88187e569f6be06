//! The GPU backend's device: one wgpu adapter and device (Vulkan; software adapters such as
//! Mesa's lavapipe included), its limits, and the errors that send a batch back to the CPU.
//!
//! Each compute stage is its own WGSL file in `shaders/` with a small typed host wrapper in
//! a submodule here ([`fft`]); the wrapper declares the stage's buffers and bind layout
//! next to the shader that uses them.

pub mod fft;
pub mod morlet;
pub mod refine;
pub mod ridge;
pub mod scales;
pub mod spectrum;

/// `shaders/select.wgsl`: a byte of a workgroup's radix selection, appended to the stages
/// that take medians (`ridge.wgsl`, `spectrum.wgsl`).
const SELECT_WGSL: &str = include_str!("../../shaders/select.wgsl");

use std::sync::{Arc, Mutex};

/// Why the GPU could not do (or finish) a piece of work. Every variant is a cue for the CPU
/// fallback; the text says what the user can do about it.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter at all (no Vulkan driver, or none that wgpu accepts).
    #[error(
        "no GPU adapter found ({0}); install a Vulkan driver (scripts/install-deps.sh installs \
         Mesa's lavapipe, a software one) or use {cpu}",
        cpu = crate::hint::Hint::CpuBackend
    )]
    NoAdapter(String),
    /// The adapter refused to open a device.
    #[error("the GPU adapter {adapter} refused a device: {detail}")]
    Device {
        /// Adapter name.
        adapter: String,
        /// wgpu's reason.
        detail: String,
    },
    /// The device was lost, or a submission failed validation, mid-work.
    #[error("the GPU device failed during the work: {0}")]
    Lost(String),
    /// One piece of work does not fit the adapter's limits even alone.
    #[error("{what} needs {need} bytes in one buffer; this adapter allows {limit}")]
    TooLarge {
        /// What was being placed.
        what: String,
        /// Bytes needed.
        need: u64,
        /// The adapter's limit.
        limit: u64,
    },
    /// A request the stage cannot serve (e.g. an FFT length with a prime factor above 5).
    #[error("{0}")]
    Unsupported(String),
}

/// Turns off Mesa's Vulkan device-selection layer for this process when no display
/// session could be asked; call at the start of `main`, before any thread exists.
///
/// The layer (`VK_LAYER_MESA_device_select`, installed with Mesa's Vulkan drivers) puts
/// the GPU that drives the display first by asking Wayland and X11. Without
/// `XDG_RUNTIME_DIR` (a cron job, an `ssh` session, a scheduler's batch slot) libwayland
/// prints "error: XDG_RUNTIME_DIR is invalid or not set in the environment." twice on
/// every `--backend gpu` command, a line that reads like a failure in an overnight log,
/// and the layer then falls back to the boot VGA device, an order that wgpu's own choice
/// (the most powerful adapter) overrides anyway. Left alone when the user steers the layer
/// (`MESA_VK_DEVICE_SELECT`, `DRI_PRIME`) or has set `NODEVICE_SELECT` either way.
pub fn quiet_headless_vulkan() {
    if cfg!(target_os = "linux") && headless(|k| std::env::var_os(k).is_some()) {
        std::env::set_var(NO_DEVICE_SELECT_ENV, "1");
    }
}

/// Mesa's switch for its device-selection layer (the layer's manifest names it).
const NO_DEVICE_SELECT_ENV: &str = "NODEVICE_SELECT";

/// Whether no display session can be asked and nobody steers the selection layer, given
/// which environment variables are set.
fn headless(is_set: impl Fn(&str) -> bool) -> bool {
    !is_set("XDG_RUNTIME_DIR")
        && ![NO_DEVICE_SELECT_ENV, "MESA_VK_DEVICE_SELECT", "DRI_PRIME"]
            .iter()
            .any(|k| is_set(k))
}

/// An adapter's name, kind and graphics backend, as the user reads it.
fn describe(info: &wgpu::AdapterInfo) -> String {
    format!("{} ({:?}, {:?})", info.name, info.device_type, info.backend)
}

/// The floating-point type a stage computes in. Shaders are written over
/// `alias real = f32;`; the f64 copy swaps that one line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Real {
    /// 32-bit.
    F32,
    /// 64-bit (wgpu's SHADER_F64).
    F64,
}

impl Real {
    /// `f32` or `f64`, as a user reads it.
    pub fn name(self) -> &'static str {
        match self {
            Real::F32 => "f32",
            Real::F64 => "f64",
        }
    }

    /// Bytes of one complex value.
    pub fn complex_bytes(self) -> usize {
        match self {
            Real::F32 => 8,
            Real::F64 => 16,
        }
    }

    /// The shader source in this precision: its `alias real = f32;` line set to the type.
    pub fn source(self, wgsl: &str) -> String {
        const LINE: &str = "alias real = f32;";
        assert!(wgsl.contains(LINE), "the shader declares {LINE}");
        match self {
            Real::F32 => wgsl.to_string(),
            Real::F64 => wgsl.replace(LINE, "alias real = f64;"),
        }
    }
}

/// Test hook: with this environment variable set, an adapter's SHADER_F64 is not used, so
/// that the f32 path is tested on adapters that have f64.
const NO_F64_ENV: &str = "SKELID_GPU_NO_F64";

/// How a stage's shader sees one of its buffers.
#[derive(Debug, Clone, Copy)]
pub enum Binding {
    /// `var<uniform>`.
    Uniform,
    /// `var<uniform>` bound with a dynamic offset: one buffer holds a record per dispatch.
    UniformDynamic,
    /// `var<storage, read>`.
    Read,
    /// `var<storage, read_write>`.
    Write,
}

/// An open GPU device and what is known about it.
pub struct Gpu {
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// The limits the device was opened with (the adapter's own).
    pub limits: wgpu::Limits,
    info: wgpu::AdapterInfo,
    /// A lower binding limit to pretend (`SKELID_GPU_MAX_BINDING`, bytes), so that tests can
    /// exercise batches and records larger than one binding on any adapter.
    binding_cap: Option<u64>,
    /// A lower workgroups-per-dimension limit to pretend (`SKELID_GPU_MAX_WORKGROUPS`), so
    /// that tests exercise dispatches split across dimensions on any adapter.
    workgroup_cap: Option<u32>,
    /// The first failure reported by the device-lost callback or a validation error.
    failure: Arc<Mutex<Option<String>>>,
    /// Work buffers given back by finished batches, by size, for [`Gpu::reusable`].
    pool: Arc<Pool>,
    /// Read-back staging buffers given back once read, by size, for
    /// [`Gpu::encode_readback`].
    staging_pool: Arc<Pool>,
    /// Staging buffers created so far (the others were taken from `staging_pool`).
    staging_made: std::sync::atomic::AtomicUsize,
    /// Upload staging memory kept mapped between batches, for [`Gpu::upload_segments`].
    uploads: Uploads,
    /// Device time of each compute pass, where `SKELID_GPU_TRACE` asks for it and the
    /// adapter has timestamp queries.
    timer: Option<Timer>,
    /// The FFT's root tables by length and precision, kept for the device's lifetime and
    /// shared by every [`fft::FftStage`] of that precision (the first pass's and the
    /// refinement's share most of a long record's lengths).
    roots: Mutex<std::collections::HashMap<(usize, Real), wgpu::Buffer>>,
}

/// Upload staging buffers (`MAP_WRITE | COPY_SRC`) reused from batch to batch.
///
/// wgpu's own `write_buffer_with` stages every write in a fresh allocation that it frees
/// once the copy is done, so every batch's uploads (45 MB for 400 campaign signals)
/// faulted in fresh pages on the dispatcher's serial path: on lavapipe 6757 of its page
/// faults in two such batches, 417 with these. They are mapped once, written, copied from
/// at the start of the next submission, then mapped again for a later batch.
#[derive(Default)]
struct Uploads {
    /// Mapped for writing and free, by size class.
    free: Pool,
    /// Written and unmapped: copied into their targets at the start of the next submission.
    copies: Mutex<Vec<StagedCopy>>,
    /// Work that must run before anything submitted after it was recorded (the FFT's long
    /// root tables expanded on the device), submitted right after the copies.
    preludes: Mutex<Vec<wgpu::CommandBuffer>>,
    /// Copied (or on their way to be): a map for writing asked for, which completes once
    /// that submission has finished; 0 while pending, 1 mapped, 2 failed.
    returning: Mutex<Vec<(wgpu::Buffer, u64, Arc<std::sync::atomic::AtomicU8>)>>,
    /// Upload staging buffers created so far.
    made: std::sync::atomic::AtomicUsize,
}

/// The most upload staging memory kept idle between batches (bytes): two batches in flight
/// of 1000 throughput-campaign signals upload about 220 MB. Host memory, or a GPU's own
/// where its driver maps that for the host (resizable BAR).
const UPLOAD_IDLE_MAX: u64 = 256 << 20;

/// One upload waiting for the next submission: its staging buffer (of size class
/// `class`), the buffer it fills and the bytes copied from the start of both.
struct StagedCopy {
    staging: wgpu::Buffer,
    class: u64,
    target: wgpu::Buffer,
    bytes: u64,
}

impl Uploads {
    /// A staging buffer of at least `bytes` (a multiple of 4), mapped for writing: a free
    /// one of its size class when an earlier batch's has come back, else a new one.
    fn take(&self, device: &wgpu::Device, bytes: u64, cap: u64) -> (wgpu::Buffer, u64) {
        use std::sync::atomic::Ordering;
        let class = pooled_size(bytes, cap);
        {
            let mut free = self.free.lock().unwrap_or_else(|p| p.into_inner());
            let mut returning = self.returning.lock().unwrap_or_else(|p| p.into_inner());
            // Those whose map has completed are free again, up to UPLOAD_IDLE_MAX bytes
            // idle (batches of changing sizes leave buffers in classes no longer asked
            // for); a failed map's is dropped.
            let mut idle: u64 = free.iter().map(|(c, b)| c * b.len() as u64).sum();
            returning.retain(
                |(buffer, class, state)| match state.load(Ordering::Acquire) {
                    0 => true,
                    1 => {
                        if idle + class <= UPLOAD_IDLE_MAX {
                            idle += class;
                            free.entry(*class).or_default().push(buffer.clone());
                        }
                        false
                    }
                    _ => false,
                },
            );
            if let Some(b) = free.get_mut(&class).and_then(Vec::pop) {
                return (b, class);
            }
        }
        self.made.fetch_add(1, Ordering::Relaxed);
        let buffer = crate::profile::span("staging", || {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("upload staging"),
                size: class,
                usage: wgpu::BufferUsages::MAP_WRITE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: true,
            })
        });
        (buffer, class)
    }

    /// Submits `buffer` after the copies written since the last submission and then the
    /// preludes ([`Gpu::prelude`]), in one
    /// submission, then asks for their staging buffers back. The list stays locked until
    /// the submission is made: another thread's submission could otherwise take these
    /// copies and go in after this one, whose work would then read its uploads before they
    /// had landed.
    fn submit_after(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        buffer: wgpu::CommandBuffer,
    ) -> wgpu::SubmissionIndex {
        // Copies before preludes, always in this order: a prelude reads what a copy
        // before it uploaded.
        let mut pending = self.copies.lock().unwrap_or_else(|p| p.into_inner());
        let mut preludes = self.preludes.lock().unwrap_or_else(|p| p.into_inner());
        let copies = std::mem::take(&mut *pending);
        let recorded = Self::record(device, &copies);
        let index = crate::profile::span("queue.submit", || {
            queue.submit(
                recorded
                    .into_iter()
                    .chain(preludes.drain(..))
                    .chain([buffer]),
            )
        });
        drop(preludes);
        drop(pending);
        self.give_back(copies);
        index
    }

    /// `copies` recorded into one command buffer (none when there are none).
    fn record(device: &wgpu::Device, copies: &[StagedCopy]) -> Option<wgpu::CommandBuffer> {
        if copies.is_empty() {
            return None;
        }
        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("uploads"),
        });
        for c in copies {
            enc.copy_buffer_to_buffer(&c.staging, 0, &c.target, 0, c.bytes);
        }
        Some(enc.finish())
    }

    /// Asks for the staging buffers of submitted copies to be mapped again; each is free
    /// for a later upload once its submission has finished and a poll has seen it.
    fn give_back(&self, copies: Vec<StagedCopy>) {
        let mut returning = self.returning.lock().unwrap_or_else(|p| p.into_inner());
        for c in copies {
            let state = Arc::new(std::sync::atomic::AtomicU8::new(0));
            let flag = state.clone();
            c.staging.map_async(wgpu::MapMode::Write, .., move |r| {
                flag.store(
                    if r.is_ok() { 1 } else { 2 },
                    std::sync::atomic::Ordering::Release,
                );
            });
            returning.push((c.staging, c.class, state));
        }
    }
}

/// Timestamps around every compute pass of a submission ([`Gpu::pass`]), resolved at its
/// submission and read once it has finished: the device's time by pass, which host
/// clocks cannot split.
struct Timer {
    set: wgpu::QuerySet,
    /// Nanoseconds per timestamp tick.
    period: f64,
    /// The passes recorded since the last submission, in order (two queries each).
    labels: Mutex<Vec<&'static str>>,
    /// Submitted, not yet read.
    pending: Mutex<Vec<TimedSubmission>>,
}

/// A submission's timestamps on their way back: the read-back buffer, whether it is
/// mapped, and its passes in order.
type TimedSubmission = (
    wgpu::Buffer,
    Arc<std::sync::atomic::AtomicBool>,
    Vec<&'static str>,
);

/// Fewest signals the dispatcher hands to rayon at once. A parallel iterator called from
/// the dispatcher (not a pool thread) queues behind whatever the pool is doing; in `skelid
/// run`, whose workers keep the pool busy and whose batches hold a few signals, that wait
/// was 2 of the dispatcher's 5 busy seconds on an H200. Below this many, the work runs on
/// the dispatcher itself.
pub(crate) const PAR_MIN: usize = 32;

/// `f` of each part of a batch (`parts`, holding `signals` signals in all), in order. The
/// parts run side by side on every core when there is more than one and the batch (not
/// one part) is as large as one part's own loop over [`PAR_MIN`]-signal pieces splits at
/// (2 × `PAR_MIN`); else one after another on the calling thread. `f` keeps its own loop
/// over a part's signals, so that a batch of one large part still splits. A small storage
/// binding makes many small parts (lavapipe's 128 MiB: 20 campaign signals a part at 512
/// scales), whose loops, each below the threshold, had all stayed on the dispatcher's one
/// thread.
pub(crate) fn map_parts<T: Send, R: Send>(
    parts: Vec<T>,
    signals: usize,
    f: impl Fn(T) -> R + Sync + Send,
) -> Vec<R> {
    use rayon::prelude::*;
    if parts.len() > 1 && signals >= 2 * PAR_MIN {
        parts.into_par_iter().with_max_len(1).map(f).collect()
    } else {
        parts.into_iter().map(f).collect()
    }
}

/// The items of `keyed` (each with its length, in their given order) ordered by length, and
/// within a length in their given order: what a stable sort by length gives, found by
/// bucketing. A batch's work items (a run × scale each: 512 000 for 1000 runs at 512
/// scales) have a few dozen distinct FFT lengths, and a sort with the length looked up
/// through each item's run was the largest serial step of a recording. `keyed` is walked
/// twice: once for the lengths, once to place the items.
pub(crate) fn stable_by_length<T: Copy>(keyed: impl Iterator<Item = (usize, T)> + Clone) -> Vec<T> {
    // The distinct lengths, ascending; consecutive items mostly share theirs.
    let mut lengths: Vec<usize> = Vec::new();
    let mut last = None;
    for (len, _) in keyed.clone() {
        if last != Some(len) {
            if let Err(at) = lengths.binary_search(&len) {
                lengths.insert(at, len);
            }
            last = Some(len);
        }
    }
    // Each length's items, in their given order.
    let mut buckets: Vec<Vec<T>> = vec![Vec::new(); lengths.len()];
    let mut last: Option<(usize, usize)> = None;
    for (len, item) in keyed {
        let slot = match last {
            Some((l, slot)) if l == len => slot,
            _ => lengths
                .binary_search(&len)
                .expect("every length was listed"),
        };
        last = Some((len, slot));
        buckets[slot].push(item);
    }
    buckets.concat()
}

/// Fewest entries of one batch's work over steps (the positions tables) that the
/// dispatcher hands to rayon. Below it the loop stays on the dispatcher: on an H100,
/// `run`'s 273 batches of a few short records waited 3.4 s for the busy pool in loops
/// whose work took 0.1 s.
pub(crate) const PAR_MIN_ENTRIES: usize = 1 << 16;

/// `with_min_len` for a dispatcher's loop over `entries` entries in all: `per_piece` pieces
/// a job when the loop is large enough to pay for rayon's queue, otherwise all of them (no
/// split, so the calling thread runs the loop itself).
pub(crate) fn min_len_for(entries: usize, per_piece: usize) -> usize {
    if entries >= PAR_MIN_ENTRIES {
        per_piece
    } else {
        usize::MAX
    }
}

/// Bytes of an upload from which its tasks are cut by size ([`upload_tasks`]): a long
/// record's 8 MB of samples, one segment or a few, had been one task on the dispatcher's
/// thread, while a `run` batch of fewer than [`PAR_MIN`] campaign signals (7 MB) stays one.
const UPLOAD_SPLIT_BYTES: usize = 8 << 20;

/// Bytes a task of a large upload holds at least ([`UPLOAD_SPLIT_BYTES`]).
const UPLOAD_TASK_BYTES: usize = 1 << 20;

/// Whether [`Gpu::stage_segments`] zeroes a segment before its `fill` writes it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fill {
    /// `fill` sees zeros, as in a fresh vector.
    Zeroed,
    /// `fill` writes every value.
    Whole,
}

/// The segments of an upload of segments of `lens` values of `elem` bytes, grouped into
/// consecutive tasks: a task ends at `min_len` segments or, in an upload of
/// [`UPLOAD_SPLIT_BYTES`] or more, once it holds [`UPLOAD_TASK_BYTES`].
fn upload_tasks(lens: &[usize], elem: usize, min_len: usize) -> Vec<std::ops::Range<usize>> {
    let by_size = lens.iter().sum::<usize>() * elem >= UPLOAD_SPLIT_BYTES;
    let mut tasks = Vec::new();
    let (mut first, mut bytes) = (0, 0);
    for (i, &len) in lens.iter().enumerate() {
        bytes += len * elem;
        if i + 1 - first >= min_len || (by_size && bytes >= UPLOAD_TASK_BYTES) {
            tasks.push(first..i + 1);
            (first, bytes) = (i + 1, 0);
        }
    }
    if first < lens.len() {
        tasks.push(first..lens.len());
    }
    tasks
}

impl Timer {
    /// Records the resolve of this submission's timestamps into `enc` and a copy to a
    /// mappable buffer; `None` when no pass was timed.
    fn resolve(
        &self,
        device: &wgpu::Device,
        enc: &mut wgpu::CommandEncoder,
    ) -> Option<(wgpu::Buffer, Vec<&'static str>)> {
        let labels = std::mem::take(&mut *self.labels.lock().unwrap_or_else(|p| p.into_inner()));
        if labels.is_empty() {
            return None;
        }
        let queries = labels.len() as u32 * 2;
        let bytes = u64::from(queries) * 8;
        let resolved = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("timestamps"),
            size: bytes,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let staging = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("timestamps read-back"),
            size: bytes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        enc.resolve_query_set(&self.set, 0..queries, &resolved, 0);
        enc.copy_buffer_to_buffer(&resolved, 0, &staging, 0, bytes);
        Some((staging, labels))
    }

    /// Asks for a submitted read-back to be mapped once its submission has finished.
    fn read_later(&self, staging: wgpu::Buffer, labels: Vec<&'static str>) {
        let done = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let flag = done.clone();
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            flag.store(r.is_ok(), std::sync::atomic::Ordering::Release);
        });
        let mut pending = self.pending.lock().unwrap_or_else(|p| p.into_inner());
        pending.push((staging, done, labels));
    }

    /// Adds the passes of every finished submission to the trace.
    fn harvest(&self) {
        let mut pending = self.pending.lock().unwrap_or_else(|p| p.into_inner());
        pending.retain(|(staging, done, labels)| {
            if !done.load(std::sync::atomic::Ordering::Acquire) {
                return true;
            }
            if let Ok(view) = staging.get_mapped_range(..) {
                let ticks: &[u64] = bytemuck::cast_slice(&view);
                for (k, label) in labels.iter().enumerate() {
                    let (a, b) = (ticks[2 * k], ticks[2 * k + 1]);
                    let ns = b.saturating_sub(a) as f64 * self.period;
                    crate::profile::device_pass(label, ns);
                }
            }
            staging.unmap();
            false
        });
    }
}

/// The size a pooled buffer of `bytes` is made with: eight classes an octave, so at most
/// 12.5 % more than asked, and batches of similar signals land in the same class.
fn size_class(bytes: u64) -> u64 {
    let bytes = bytes.max(4).next_multiple_of(4);
    let step = (bytes.next_power_of_two() / 16).max(4);
    bytes.next_multiple_of(step)
}

/// The size a pooled buffer for `bytes` (a multiple of 4) is made with: its size class,
/// at most `cap`, never less than `bytes`.
fn pooled_size(bytes: u64, cap: u64) -> u64 {
    size_class(bytes).min(cap).max(bytes)
}

/// The bytes an upload of segments of `lens` values of `T` takes on the device: a
/// multiple of [`wgpu::COPY_BUFFER_ALIGNMENT`], never 0.
fn upload_size<T>(lens: &[usize]) -> u64 {
    ((lens.iter().sum::<usize>() * std::mem::size_of::<T>()) as u64)
        .next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT)
        .max(wgpu::COPY_BUFFER_ALIGNMENT)
}

/// Free work buffers by size class.
type Pool = Mutex<std::collections::HashMap<u64, Vec<wgpu::Buffer>>>;

/// A buffer of at least `bytes` from `pool`, its size class's (at most `cap`, at least
/// `bytes`): a free one given back earlier, else one `make` creates at that size.
fn take(pool: &Arc<Pool>, bytes: u64, cap: u64, make: impl FnOnce(u64) -> wgpu::Buffer) -> Pooled {
    let requested = bytes.max(4).next_multiple_of(4);
    let class = pooled_size(requested, cap);
    let free = {
        let mut free = pool.lock().unwrap_or_else(|p| p.into_inner());
        free.get_mut(&class).and_then(Vec::pop)
    };
    Pooled {
        buffer: Some(free.unwrap_or_else(|| make(class))),
        class,
        requested,
        mapped: false,
        pool: pool.clone(),
    }
}

/// A work buffer of [`Gpu::reusable`]: goes back to the device's pool when dropped. Keep it
/// until the submission that uses it has finished, or a later batch could get it while
/// this one still reads it.
pub struct Pooled {
    buffer: Option<wgpu::Buffer>,
    class: u64,
    /// The bytes asked for (a multiple of 4); the buffer may be up to its class's size.
    requested: u64,
    /// Mapped, or a map asked for: not to be given back (a read-back's copy that
    /// panicked, or a map that failed, would fail the next user's submission).
    mapped: bool,
    pool: Arc<Pool>,
}

impl std::ops::Deref for Pooled {
    type Target = wgpu::Buffer;
    fn deref(&self) -> &wgpu::Buffer {
        self.buffer.as_ref().expect("held until dropped")
    }
}

impl Pooled {
    /// Unmaps it, so that it goes back to the pool when dropped.
    fn unmap_to_give_back(&mut self) {
        self.unmap();
        self.mapped = false;
    }

    /// Its first bytes, as many as were asked for, as a binding. A shader that counts an
    /// array with `arrayLength` (items, grid points) must be bound to this, not to the
    /// whole buffer, whose spare bytes past the request hold a previous user's values.
    pub fn exact(&self) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: self,
            offset: 0,
            size: wgpu::BufferSize::new(self.requested),
        })
    }
}

impl Drop for Pooled {
    fn drop(&mut self) {
        if let Some(b) = self.buffer.take() {
            if self.mapped {
                return;
            }
            let mut pool = self.pool.lock().unwrap_or_else(|p| p.into_inner());
            pool.entry(self.class).or_default().push(b);
        }
    }
}

impl Gpu {
    /// The adapter [`new`](Self::new) would open, without opening a device: its name and
    /// whether it is a software one.
    pub fn probe() -> Result<(String, bool), GpuError> {
        let info = Self::adapter()?.get_info();
        Ok((describe(&info), info.device_type == wgpu::DeviceType::Cpu))
    }

    fn adapter() -> Result<wgpu::Adapter, GpuError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            // The real limits: batches are sized to them.
            apply_limit_buckets: false,
        }))
        .map_err(|e| GpuError::NoAdapter(e.to_string()))
    }

    /// Opens the best adapter wgpu finds (high performance preferred; a software adapter
    /// is accepted), with the adapter's own limits so that batches can be sized to them.
    pub fn new() -> Result<Gpu, GpuError> {
        let adapter = Self::adapter()?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let mut features = if std::env::var_os(NO_F64_ENV).is_some() {
            wgpu::Features::empty()
        } else {
            adapter.features() & wgpu::Features::SHADER_F64
        };
        let timed = crate::profile::tracing()
            && adapter.features().contains(wgpu::Features::TIMESTAMP_QUERY);
        if timed {
            features |= wgpu::Features::TIMESTAMP_QUERY;
        }
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("skelid"),
            required_features: features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device {
            adapter: info.name.clone(),
            detail: e.to_string(),
        })?;
        let failure: Arc<Mutex<Option<String>>> = Arc::default();
        let record = |failure: &Arc<Mutex<Option<String>>>| {
            let failure = failure.clone();
            move |text: String| {
                failure
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .get_or_insert(text);
            }
        };
        let lost = record(&failure);
        device.set_device_lost_callback(move |reason, message| {
            lost(format!("device lost ({reason:?}): {message}"))
        });
        let invalid = record(&failure);
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| invalid(e.to_string())));
        let timer = timed.then(|| Timer {
            set: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("pass timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: wgpu::QUERY_SET_MAX_QUERIES,
            }),
            period: f64::from(queue.get_timestamp_period()),
            labels: Mutex::new(Vec::new()),
            pending: Mutex::new(Vec::new()),
        });
        Ok(Gpu {
            device,
            queue,
            limits,
            info,
            binding_cap: std::env::var("SKELID_GPU_MAX_BINDING")
                .ok()
                .and_then(|v| v.parse().ok()),
            workgroup_cap: std::env::var("SKELID_GPU_MAX_WORKGROUPS")
                .ok()
                .and_then(|v| v.parse().ok()),
            failure,
            pool: Arc::new(Mutex::new(std::collections::HashMap::new())),
            staging_pool: Arc::new(Mutex::new(std::collections::HashMap::new())),
            staging_made: std::sync::atomic::AtomicUsize::new(0),
            uploads: Uploads::default(),
            roots: Mutex::new(std::collections::HashMap::new()),
            timer,
        })
    }

    /// Whether shaders may compute in f64 (the adapter has SHADER_F64 and `SKELID_GPU_NO_F64`
    /// is not set).
    pub fn has_f64(&self) -> bool {
        self.device.features().contains(wgpu::Features::SHADER_F64)
    }

    /// The precision the stages compute in: f64 where [`has_f64`](Self::has_f64), else f32.
    pub fn real(&self) -> Real {
        if self.has_f64() {
            Real::F64
        } else {
            Real::F32
        }
    }

    /// Whether the adapter is a software one (lavapipe): its invocations run one after
    /// another on the CPU, so a shader costs its total work, not its longest thread.
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// The adapter's name and kind, e.g. `llvmpipe (LLVM 15.0.6, 256 bits) (Cpu, Vulkan)`.
    pub fn adapter_name(&self) -> String {
        describe(&self.info)
    }

    /// Workgroups one dispatch may launch along each dimension.
    pub fn max_workgroups(&self) -> u32 {
        self.limits
            .max_compute_workgroups_per_dimension
            .min(self.workgroup_cap.unwrap_or(u32::MAX))
            .max(1)
    }

    /// The dispatch `[x, y, z]` that launches at least `groups` workgroups within the
    /// workgroups-per-dimension limit; a shader recovers the flat index as
    /// `(z·ny + y)·nx + x` and skips indices at or past its count.
    pub fn grid(&self, groups: u64) -> Result<[u32; 3], GpuError> {
        grid(groups, self.max_workgroups())
    }

    /// The largest buffer one storage binding may hold (bytes).
    pub fn max_binding(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
            .min(self.binding_cap.unwrap_or(u64::MAX))
    }

    /// Pretends the adapter binds at most `bytes` in one storage binding, as
    /// `SKELID_GPU_MAX_BINDING` does for a whole process: for tests that split work by it.
    pub fn cap_bindings(&mut self, bytes: u64) {
        self.binding_cap = Some(bytes);
    }

    /// `Err` when the device was lost or a submission failed since it was opened.
    pub fn check(&self) -> Result<(), GpuError> {
        match self
            .failure
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
        {
            Some(text) => Err(GpuError::Lost(text)),
            None => Ok(()),
        }
    }

    /// Submits one command buffer (counted for the profile).
    pub fn submit(&self, mut enc: wgpu::CommandEncoder) -> wgpu::SubmissionIndex {
        crate::profile::submitted();
        let timed = self
            .timer
            .as_ref()
            .and_then(|t| t.resolve(&self.device, &mut enc));
        let buffer = crate::profile::span("encoder.finish", || enc.finish());
        // The uploads made since the last submission are copied first, then the preludes
        // run, in the same
        // submission, as wgpu does with its own queue writes.
        let index = self.uploads.submit_after(&self.device, &self.queue, buffer);
        if let (Some(t), Some((staging, labels))) = (&self.timer, timed) {
            t.read_later(staging, labels);
        }
        index
    }

    /// Begins a compute pass labelled `label`; with `SKELID_GPU_TRACE` on an adapter with
    /// timestamp queries, its device time is added to the trace under that label.
    pub fn pass<'e>(
        &self,
        enc: &'e mut wgpu::CommandEncoder,
        label: &'static str,
    ) -> wgpu::ComputePass<'e> {
        let writes = self.timer.as_ref().and_then(|t| {
            let mut labels = t.labels.lock().unwrap_or_else(|p| p.into_inner());
            // Two queries a pass; passes beyond the set's size go untimed.
            let at = u32::try_from(labels.len() * 2).ok()?;
            (at + 1 < wgpu::QUERY_SET_MAX_QUERIES).then(|| {
                labels.push(label);
                wgpu::ComputePassTimestampWrites {
                    query_set: &t.set,
                    beginning_of_pass_write_index: Some(at),
                    end_of_pass_write_index: Some(at + 1),
                }
            })
        });
        enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: writes,
        })
    }

    /// Submits `enc`, which holds the copies of `rb`, so that [`read_in_place`]
    /// (Self::read_in_place) waits for this submission alone.
    pub fn submit_reading(&self, enc: wgpu::CommandEncoder, rb: Readback) -> Readback {
        Readback {
            submission: Some(self.submit(enc)),
            ..rb
        }
    }

    /// A flag that turns true once every submission made so far has finished on the
    /// device; it is raised by a [`poll_ready`](Self::poll_ready) (or any wait) after that.
    pub fn work_done_flag(&self) -> Arc<std::sync::atomic::AtomicBool> {
        let flag = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let raise = Arc::clone(&flag);
        self.queue.on_submitted_work_done(move || {
            raise.store(true, std::sync::atomic::Ordering::Release);
        });
        flag
    }

    /// Raises the flags of finished work ([`work_done_flag`](Self::work_done_flag))
    /// without blocking.
    pub fn poll_ready(&self) {
        // An error here is a lost device, which the next wait reports.
        let _ = self.device.poll(wgpu::PollType::Poll);
    }

    /// Waits for all submitted work.
    pub fn wait(&self) -> Result<(), GpuError> {
        self.wait_for(None)
    }

    /// Waits for `submission` and the work before it (all submitted work when `None`).
    /// A batch's read-back waits for its own submission: waiting for the newest one
    /// instead also waited for the batch submitted after it, which is what two batches in
    /// flight are meant to overlap.
    fn wait_for(&self, submission: Option<wgpu::SubmissionIndex>) -> Result<(), GpuError> {
        crate::profile::synced();
        crate::profile::span("wait", || {
            crate::profile::device_wait(|| {
                self.device.poll(wgpu::PollType::Wait {
                    submission_index: submission,
                    timeout: None,
                })
            })
        })
        .map_err(|e| GpuError::Lost(e.to_string()))?;
        if let Some(t) = &self.timer {
            t.harvest();
        }
        self.check()
    }

    /// A stage's shader, bind layout and compute pipelines: `bindings` in binding order
    /// (0, 1, …), one pipeline per entry point of `entries`, in that order.
    pub fn stage(
        &self,
        label: &str,
        wgsl: &str,
        bindings: &[Binding],
        entries: &[&str],
    ) -> (wgpu::BindGroupLayout, Vec<wgpu::ComputePipeline>) {
        Self::stage_on(&self.device, label, wgsl, bindings, entries)
    }

    /// [`stage`](Self::stage) on a device handle alone (a clone of [`Gpu::device`]), so that
    /// a stage can be made on a thread of its own while the device works
    /// ([`refine::RefineStage::beside`]).
    pub fn stage_on(
        device: &wgpu::Device,
        label: &str,
        wgsl: &str,
        bindings: &[Binding],
        entries: &[&str],
    ) -> (wgpu::BindGroupLayout, Vec<wgpu::ComputePipeline>) {
        let module = module_on(device, label, wgsl);
        let layout = layout_on(device, label, bindings);
        let pipelines = pipelines_on(device, label, &module, &layout, entries, true);
        (layout, pipelines)
    }

    /// A stage's bind layout: `bindings` in binding order (0, 1, …).
    pub fn layout(&self, label: &str, bindings: &[Binding]) -> wgpu::BindGroupLayout {
        layout_on(&self.device, label, bindings)
    }

    /// More pipelines for a stage's bind `layout`, from another version of its shader (the
    /// ridge's wide programme, the workgroup-memory FFT): one per entry point of `entries`,
    /// in that order, or why the device refused them. The refusal is caught in error
    /// scopes, so that an optional variant never fails the device for every later batch
    /// (see [`check`](Self::check)). `zero_workgroup_memory: false` leaves out wgpu's
    /// zeroing of workgroup memory at the start of every workgroup, for shaders that write
    /// every workgroup value before they read it (`fft_local.wgsl`, whose whole array would
    /// be zeroed for each sequence, however short).
    pub fn try_stage_variant(
        &self,
        label: &str,
        wgsl: &str,
        layout: &wgpu::BindGroupLayout,
        entries: &[&str],
        zero_workgroup_memory: bool,
    ) -> Result<Vec<wgpu::ComputePipeline>, String> {
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let internal = self.device.push_error_scope(wgpu::ErrorFilter::Internal);
        let module = module_on(&self.device, label, wgsl);
        let pipelines = pipelines_on(
            &self.device,
            label,
            &module,
            layout,
            entries,
            zero_workgroup_memory,
        );
        let refused =
            pollster::block_on(internal.pop()).or_else(|| pollster::block_on(validation.pop()));
        match refused {
            None => Ok(pipelines),
            // wgpu's report runs over several indented lines: one line for a note.
            Some(e) => Err(e
                .to_string()
                .split_whitespace()
                .collect::<Vec<_>>()
                .join(" ")),
        }
    }

    /// A bind group of `layout` with whole `buffers` at bindings 0, 1, … in order.
    pub fn bind(
        &self,
        label: &str,
        layout: &wgpu::BindGroupLayout,
        buffers: &[&wgpu::Buffer],
    ) -> wgpu::BindGroup {
        let whole: Vec<wgpu::BindingResource> =
            buffers.iter().map(|b| b.as_entire_binding()).collect();
        self.bind_resources(label, layout, whole)
    }

    /// [`bind`](Self::bind) with each binding given: a whole buffer
    /// (`as_entire_binding`) or a pooled one's requested bytes ([`Pooled::exact`]).
    pub fn bind_resources(
        &self,
        label: &str,
        layout: &wgpu::BindGroupLayout,
        resources: Vec<wgpu::BindingResource>,
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = resources
            .into_iter()
            .enumerate()
            .map(|(i, resource)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource,
            })
            .collect();
        crate::profile::span("bind", || {
            self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(label),
                layout,
                entries: &entries,
            })
        })
    }

    /// A uniform buffer holding `value`.
    pub fn uniform<T: bytemuck::Pod>(&self, label: &str, value: &T) -> wgpu::Buffer {
        self.init(
            label,
            bytemuck::bytes_of(value),
            wgpu::BufferUsages::UNIFORM,
        )
    }

    /// A uniform buffer initialised with `bytes` (records read at dynamic offsets).
    pub fn upload_uniform(&self, label: &str, bytes: &[u8]) -> wgpu::Buffer {
        self.init(label, bytes, wgpu::BufferUsages::UNIFORM)
    }

    /// A buffer of `usage` initialised with `bytes` (counted as uploaded).
    fn init(&self, label: &str, bytes: &[u8], usage: wgpu::BufferUsages) -> wgpu::Buffer {
        use wgpu::util::DeviceExt;
        crate::profile::uploaded(bytes.len() as u64);
        crate::profile::span("upload", || {
            self.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents: bytes,
                    usage,
                })
        })
    }

    /// A storage buffer of segments of `lens[i]` values each, back to back, segment `i`
    /// written by `fill(i, values)`. Every core fills segments and copies them straight
    /// into the upload's staging memory: a batch's spectra (hundreds of MB) built in one
    /// vector and copied by one thread set the pace of the whole GPU backend.
    ///
    /// The buffer is a reused one ([`reusable`](Self::reusable); keep it until the
    /// submission that reads it has finished), filled from reused staging memory
    /// ([`Uploads`]) by a copy at the start of the next submission: a buffer mapped at
    /// creation cost a fresh device buffer and a staging buffer that wgpu fills with zeros
    /// first, on the dispatcher's one thread (a batch of 1000 signals uploads about 200 MB).
    pub fn upload_segments<T: bytemuck::Pod + Send>(
        &self,
        label: &str,
        lens: &[usize],
        fill: impl Fn(usize, &mut [T]) + Sync,
    ) -> Result<Pooled, GpuError> {
        self.upload_pooled_segments(label, lens, Fill::Zeroed, fill)
    }

    /// [`upload_segments`](Self::upload_segments) for a `fill` that writes every value of
    /// its segment (a copy): the staging memory is not zeroed first, so values it leaves
    /// unwritten hold whatever an earlier upload put there. A long record's samples and
    /// position tables (21 MB) were written twice.
    pub fn upload_whole_segments<T: bytemuck::Pod + Send>(
        &self,
        label: &str,
        lens: &[usize],
        fill: impl Fn(usize, &mut [T]) + Sync,
    ) -> Result<Pooled, GpuError> {
        self.upload_pooled_segments(label, lens, Fill::Whole, fill)
    }

    /// A reused buffer of the segments, staged as `zeroing` says ([`stage_segments`]).
    ///
    /// [`stage_segments`]: Self::stage_segments
    fn upload_pooled_segments<T: bytemuck::Pod + Send>(
        &self,
        label: &str,
        lens: &[usize],
        zeroing: Fill,
        fill: impl Fn(usize, &mut [T]) + Sync,
    ) -> Result<Pooled, GpuError> {
        let buffer = self.reusable(label, upload_size::<T>(lens));
        self.stage_segments(label, &buffer, lens, PAR_MIN, zeroing, fill)?;
        Ok(buffer)
    }

    /// Has `commands` run at the start of the next submission, after the uploads staged
    /// before it and before that submission's own work: for work a later recording relies
    /// on whichever submission goes first.
    pub(crate) fn prelude(&self, commands: wgpu::CommandBuffer) {
        self.uploads
            .preludes
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push(commands);
    }

    /// The FFT's root tables kept on this device, by length and precision
    /// ([`fft::FftStage`]).
    pub(crate) fn root_tables(
        &self,
    ) -> &Mutex<std::collections::HashMap<(usize, Real), wgpu::Buffer>> {
        &self.roots
    }

    /// A storage buffer of its own (exactly the values' size, never given back to a pool)
    /// filled as [`upload_segments`](Self::upload_segments) fills one, every segment a task
    /// of its own: for tables kept for the device's lifetime, such as the FFT's roots. A
    /// long record's were 87 MB of cosines and sines computed on the dispatcher's one
    /// thread (`create_buffer_init`), 113 ms of a one-shot `skelid track` here.
    pub fn upload_kept<T: bytemuck::Pod + Send>(
        &self,
        label: &str,
        lens: &[usize],
        fill: impl Fn(usize, &mut [T]) + Sync,
    ) -> Result<wgpu::Buffer, GpuError> {
        let buffer = self.storage(label, upload_size::<T>(lens));
        self.stage_segments(label, &buffer, lens, 1, Fill::Zeroed, fill)?;
        Ok(buffer)
    }

    /// Fills reused staging memory with the segments (`fill(i, values)` for segment `i` of
    /// `lens[i]` values, on every core: a task holds `min_len` segments, or, in an upload of
    /// [`UPLOAD_SPLIT_BYTES`] or more, fewer that hold [`UPLOAD_TASK_BYTES`]) and records
    /// its copy into `buffer` for the start of the next submission
    /// ([`submit`](Self::submit)).
    fn stage_segments<T: bytemuck::Pod + Send>(
        &self,
        label: &str,
        buffer: &wgpu::Buffer,
        lens: &[usize],
        min_len: usize,
        zeroing: Fill,
        fill: impl Fn(usize, &mut [T]) + Sync,
    ) -> Result<(), GpuError> {
        use rayon::prelude::*;
        let elem = std::mem::size_of::<T>();
        let bytes = lens.iter().sum::<usize>() * elem;
        crate::profile::uploaded(bytes as u64);
        crate::profile::span("upload", || {
            let size = upload_size::<T>(lens);
            let (staging, class) =
                self.uploads
                    .take(&self.device, size, self.limits.max_buffer_size);
            let mut view = staging
                .get_mapped_range_mut(..size)
                .map_err(|e| GpuError::Lost(format!("cannot write {label} ({size} bytes): {e}")))?;
            {
                // wgpu's write-only view cannot be sent to other threads; its pointer can,
                // each thread writing only its own segment's bytes.
                struct Base(std::ptr::NonNull<u8>);
                // SAFETY: the threads write disjoint ranges, and the view outlives them.
                unsafe impl Send for Base {}
                unsafe impl Sync for Base {}
                impl Base {
                    fn at(&self, offset: usize) -> *mut u8 {
                        // SAFETY: callers pass offsets inside the mapping.
                        unsafe { self.0.as_ptr().add(offset) }
                    }
                }
                let mut whole = view.slice(..);
                let base = Base(whole.as_raw_element_ptr());
                let mut starts = Vec::with_capacity(lens.len());
                let mut at = 0usize;
                for &len in lens {
                    starts.push(at);
                    at += len * elem;
                }
                // Each segment filled where it lies when the mapping holds a T there (wgpu
                // maps at 8-byte alignment, every T here needs at most 8), else through a
                // vector of its own: a deferred signal's 240 kB of samples allocated,
                // zeroed and copied again per batch was most of the dispatcher's upload.
                let in_place = (base.at(0) as usize).is_multiple_of(std::mem::align_of::<T>());
                upload_tasks(lens, elem, min_len)
                    .into_par_iter()
                    .flat_map_iter(|task| task.map(|i| (i, starts[i])))
                    .for_each(|(i, start)| {
                        if in_place {
                            // SAFETY: [start, start + len·elem) lies inside the staging
                            // memory's `size` bytes (the starts are the running sums of the
                            // lengths), aligned for T (the base is, and every start is a
                            // multiple of T's size), and no other thread touches it; T is
                            // Pod, so any bytes there are a valid T; they are zeroed
                            // before `fill` sees them, as a fresh vector would be, unless
                            // `fill` writes them all.
                            let values = unsafe {
                                std::slice::from_raw_parts_mut(base.at(start).cast::<T>(), lens[i])
                            };
                            if zeroing == Fill::Zeroed {
                                values.fill(T::zeroed());
                            }
                            fill(i, values);
                            return;
                        }
                        let mut values = vec![T::zeroed(); lens[i]];
                        fill(i, &mut values);
                        let src: &[u8] = bytemuck::cast_slice(&values);
                        // SAFETY: as above, without the alignment, which bytes do not need.
                        unsafe {
                            std::ptr::copy_nonoverlapping(src.as_ptr(), base.at(start), src.len());
                        }
                    });
                if size as usize > bytes {
                    // The alignment's few bytes past the values: written, not left as
                    // whatever the staging memory held.
                    // SAFETY: [bytes, size) lies inside the staging memory.
                    unsafe { std::ptr::write_bytes(base.at(bytes), 0, size as usize - bytes) };
                }
            }
            drop(view);
            staging.unmap();
            self.uploads
                .copies
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .push(StagedCopy {
                    staging,
                    class,
                    target: buffer.clone(),
                    bytes: size,
                });
            Ok(())
        })
    }

    /// Segments of complex values (`values(i)` fills segment `i` of `lens[i]`) uploaded
    /// through [`upload_segments`](Self::upload_segments) as pairs in `real` (f64 as they
    /// are, f32 rounded): how the passes' spectra go up.
    pub fn upload_complex<I>(
        &self,
        label: &str,
        real: Real,
        lens: &[usize],
        values: impl Fn(usize) -> I + Sync,
    ) -> Result<Pooled, GpuError>
    where
        I: Iterator<Item = num_complex::Complex64>,
    {
        match real {
            Real::F64 => self.upload_segments(label, lens, |i, out: &mut [[f64; 2]]| {
                for (o, c) in out.iter_mut().zip(values(i)) {
                    *o = [c.re, c.im];
                }
            }),
            Real::F32 => self.upload_segments(label, lens, |i, out: &mut [[f32; 2]]| {
                for (o, c) in out.iter_mut().zip(values(i)) {
                    *o = [c.re as f32, c.im as f32];
                }
            }),
        }
    }

    /// [`upload`](Self::upload) into a reused buffer, through reused staging memory, as
    /// [`upload_segments`](Self::upload_segments) does: for a batch's large tables. Keep it
    /// until the submission that reads it has finished.
    pub fn upload_pooled<T: bytemuck::Pod + Send + Sync>(
        &self,
        label: &str,
        data: &[T],
    ) -> Result<Pooled, GpuError> {
        const PIECE: usize = 1 << 16;
        let lens: Vec<usize> = data.chunks(PIECE).map(<[T]>::len).collect();
        self.upload_whole_segments(label, &lens, |i, out: &mut [T]| {
            out.copy_from_slice(&data[i * PIECE..i * PIECE + out.len()]);
        })
    }

    /// A storage buffer initialised with `data`.
    pub fn upload<T: bytemuck::Pod>(&self, label: &str, data: &[T]) -> wgpu::Buffer {
        self.init(
            label,
            bytemuck::cast_slice(data),
            wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
        )
    }

    /// An uninitialised storage buffer of `bytes` bytes.
    pub fn storage(&self, label: &str, bytes: u64) -> wgpu::Buffer {
        crate::profile::span("storage", || {
            self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes.max(4),
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        })
    }

    /// A storage buffer of at least `bytes` for work the shaders write in full before they
    /// read it (decimated scales, FFT scratch): taken from the buffers earlier batches gave
    /// back when one of its size class is free. Its contents are whatever the last user
    /// left. On an H200 a fresh buffer of hundreds of MB cost ~16 ms of the dispatcher's
    /// time, 240 ms a batch of 1000 signals.
    pub fn reusable(&self, label: &str, bytes: u64) -> Pooled {
        // Never beyond one binding, which the buffer may be bound as whole.
        take(&self.pool, bytes, self.max_binding(), |class| {
            self.storage(label, class)
        })
    }

    /// A read-back staging buffer of at least `bytes`, unmapped, from those earlier
    /// read-backs gave back. On an H200 creating a fresh one of 74 MB for each batch of
    /// 1000 signals cost the dispatcher about 20 ms of its serial time a batch.
    fn staging(&self, bytes: u64) -> Pooled {
        take(
            &self.staging_pool,
            bytes,
            self.limits.max_buffer_size,
            |class| {
                self.staging_made
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                crate::profile::span("staging", || {
                    self.device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("read-back"),
                        size: class,
                        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                        mapped_at_creation: false,
                    })
                })
            },
        )
    }

    /// Records copies of `parts` (each a buffer and the bytes wanted from its start, a
    /// multiple of 4) into one staging buffer, so that a batch's results come back with one
    /// map and one wait ([`read_in_place`](Self::read_in_place)) after the submission
    /// that holds both its work and these copies.
    pub fn encode_readback(
        &self,
        enc: &mut wgpu::CommandEncoder,
        parts: &[(&wgpu::Buffer, u64)],
    ) -> Readback {
        let mut ranges = Vec::with_capacity(parts.len());
        let mut at = 0u64;
        for &(_, bytes) in parts {
            ranges.push((at, bytes));
            at += bytes.next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT);
        }
        let staging = self.staging(at.max(wgpu::COPY_BUFFER_ALIGNMENT));
        for (&(buffer, bytes), &(offset, _)) in parts.iter().zip(&ranges) {
            if bytes > 0 {
                enc.copy_buffer_to_buffer(buffer, 0, &staging, offset, bytes);
            }
        }
        Readback {
            staging,
            ranges,
            submission: None,
        }
    }

    /// Maps a read-back recorded by [`encode_readback`](Self::encode_readback) once its
    /// submission is made (one blocking wait) and hands `read` each part's contents in
    /// order, as 4-byte words read where the driver mapped them; the staging buffer goes
    /// back to the pool when `read` returns. Copying the words out first cost the
    /// dispatcher a write and a second read of every byte (106 kB a campaign signal), into
    /// memory freshly mapped for each batch: 6–10 ms of its thread and 1 000 page faults
    /// for a batch of 400 signals on lavapipe.
    pub fn read_in_place<R>(
        &self,
        rb: Readback,
        read: impl FnOnce(&[&[u32]]) -> R,
    ) -> Result<R, GpuError> {
        let Readback {
            mut staging,
            ranges,
            submission,
        } = rb;
        crate::profile::downloaded(ranges.iter().map(|r| r.1).sum());
        let (tx, rx) = std::sync::mpsc::channel();
        staging.mapped = true;
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        // On any failure from here `staging` stays marked mapped, and is dropped, not
        // given back: no later read-back may get a buffer left pending or mapped.
        self.wait_for(submission)?;
        rx.recv()
            .map_err(|e| GpuError::Lost(e.to_string()))?
            .map_err(|e| GpuError::Lost(e.to_string()))?;
        let view = staging
            .get_mapped_range(..)
            .map_err(|e| GpuError::Lost(e.to_string()))?;
        let bytes: &[u8] = &view;
        // wgpu maps at an alignment of 8 bytes and every part starts at a multiple of 4,
        // so the words are read in place; a driver that mapped otherwise gets a copy.
        let copied: Vec<u32>;
        let words: &[u32] = match bytemuck::try_cast_slice(bytes) {
            Ok(words) => words,
            Err(_) => {
                copied = bytemuck::pod_collect_to_vec(bytes);
                &copied
            }
        };
        let parts: Vec<&[u32]> = ranges
            .iter()
            .map(|&(at, bytes)| &words[(at / 4) as usize..((at + bytes) / 4) as usize])
            .collect();
        let out = read(&parts);
        drop(view);
        staging.unmap_to_give_back();
        Ok(out)
    }

    /// How many read-back staging buffers this device has created; read-backs of a size
    /// seen before reuse one that an earlier read-back gave back.
    pub fn staging_buffers_made(&self) -> usize {
        self.staging_made.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// How many upload staging buffers this device has created; uploads of a size seen
    /// before reuse one that an earlier batch's submission has finished with.
    pub fn upload_staging_made(&self) -> usize {
        self.uploads.made.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Copies `count` elements of `buffer` back to the host (waits for the GPU).
    pub fn download<T: bytemuck::Pod>(
        &self,
        buffer: &wgpu::Buffer,
        count: usize,
    ) -> Result<Vec<T>, GpuError> {
        let bytes = (count * std::mem::size_of::<T>()) as u64;
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        let readback = self.encode_readback(&mut enc, &[(buffer, bytes)]);
        let readback = self.submit_reading(enc, readback);
        self.read_in_place(readback, |parts| {
            crate::profile::span("readback.copy", || {
                use rayon::prelude::*;
                // Words are aligned to 4 bytes only: copied into a typed vector, every core
                // a share (mapped memory can be slow to read, uncached on some drivers).
                let src: &[u8] = bytemuck::cast_slice(parts[0]);
                let mut out = vec![T::zeroed(); count];
                bytemuck::cast_slice_mut::<T, u8>(&mut out)
                    .par_chunks_mut(1 << 20)
                    .zip(src.par_chunks(1 << 20))
                    .for_each(|(d, s)| d.copy_from_slice(s));
                out
            })
        })
    }
}

/// Copies recorded for one read-back: a staging buffer and each part's (offset, bytes).
pub struct Readback {
    /// Given back to the pool unmapped once read, or if never mapped.
    staging: Pooled,
    ranges: Vec<(u64, u64)>,
    /// The submission that holds the copies, once made ([`Gpu::submit_reading`]).
    submission: Option<wgpu::SubmissionIndex>,
}

/// [`Gpu::grid`] for a given per-dimension limit.
pub fn grid(groups: u64, max: u32) -> Result<[u32; 3], GpuError> {
    let max = u64::from(max.max(1));
    let groups = groups.max(1);
    let x = groups.min(max);
    let rest = groups.div_ceil(x);
    let y = rest.min(max);
    let z = rest.div_ceil(y);
    if z > max {
        return Err(GpuError::TooLarge {
            what: format!("{groups} workgroups in one dispatch"),
            need: groups,
            limit: max * max * max,
        });
    }
    Ok([x as u32, y as u32, z as u32])
}

/// The shader module of WGSL source `wgsl`.
fn module_on(device: &wgpu::Device, label: &str, wgsl: &str) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(wgsl.into()),
    })
}

/// [`Gpu::layout`] on a device handle.
fn layout_on(device: &wgpu::Device, label: &str, bindings: &[Binding]) -> wgpu::BindGroupLayout {
    let layout_entries: Vec<wgpu::BindGroupLayoutEntry> = bindings
        .iter()
        .enumerate()
        .map(|(i, b)| wgpu::BindGroupLayoutEntry {
            binding: i as u32,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: match b {
                    Binding::Uniform | Binding::UniformDynamic => wgpu::BufferBindingType::Uniform,
                    Binding::Read => wgpu::BufferBindingType::Storage { read_only: true },
                    Binding::Write => wgpu::BufferBindingType::Storage { read_only: false },
                },
                has_dynamic_offset: matches!(b, Binding::UniformDynamic),
                min_binding_size: None,
            },
            count: None,
        })
        .collect();
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some(label),
        entries: &layout_entries,
    })
}

/// Compute pipelines of `module`, one per entry point of `entries`, on `layout`.
fn pipelines_on(
    device: &wgpu::Device,
    label: &str,
    module: &wgpu::ShaderModule,
    layout: &wgpu::BindGroupLayout,
    entries: &[&str],
    zero_workgroup_memory: bool,
) -> Vec<wgpu::ComputePipeline> {
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(label),
        bind_group_layouts: &[Some(layout)],
        immediate_size: 0,
    });
    entries
        .iter()
        .map(|entry| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&pipeline_layout),
                module,
                entry_point: Some(entry),
                compilation_options: wgpu::PipelineCompilationOptions {
                    zero_initialize_workgroup_memory: zero_workgroup_memory,
                    ..Default::default()
                },
                cache: None,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::{
        grid, headless, map_parts, stable_by_length, upload_tasks, PAR_MIN, UPLOAD_SPLIT_BYTES,
        UPLOAD_TASK_BYTES,
    };

    /// An upload's tasks cover its segments once, in order; a small upload is cut by count
    /// alone, a large one also by size, so that one long record's samples in pieces are
    /// several tasks and a few campaign signals stay one.
    #[test]
    fn an_upload_is_cut_into_tasks_by_count_and_by_size() {
        let covers = |tasks: &[std::ops::Range<usize>], n: usize| {
            tasks.first().is_none_or(|t| t.start == 0)
                && tasks
                    .windows(2)
                    .all(|w| w[0].end == w[1].start && w[0].start < w[0].end)
                && tasks.last().map_or(0, |t| t.end) == n
        };
        // 31 campaign signals of 30 000 f64 (7.1 MB): one task, as before.
        let few = upload_tasks(&[30_000; 31], 8, 32);
        assert_eq!(few, vec![0..31]);
        // 400 of them: tasks of at least a MB each, and at most 32 signals.
        let many = upload_tasks(&[30_000; 400], 8, 32);
        assert!(covers(&many, 400) && many.len() > 50);
        assert!(many[..many.len() - 1]
            .iter()
            .all(|t| t.len() * 240_000 >= UPLOAD_TASK_BYTES));
        // A 2^20-sample record in pieces of 2^16 values, and the one value after it.
        let mut lens = vec![1 << 16; 16];
        lens.push(1);
        let long = upload_tasks(&lens, 8, 32);
        assert!(long.len() >= 8 && covers(&long, 17), "{long:?}");
        assert!(lens.iter().sum::<usize>() * 8 >= UPLOAD_SPLIT_BYTES);
        // Each segment its own task where asked; none where there is none.
        assert_eq!(upload_tasks(&[5, 6, 7], 4, 1), vec![0..1, 1..2, 2..3]);
        assert!(upload_tasks(&[], 8, 32).is_empty());
    }

    /// Against the naive reference, a stable sort by length: runs of equal lengths, lengths
    /// in both orders, one length only, one item, none.
    #[test]
    fn items_by_length_are_a_stable_sorts_order() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(18);
        let sorted = |lens: &[usize]| {
            let mut want: Vec<usize> = (0..lens.len()).collect();
            want.sort_by_key(|&i| lens[i]);
            want
        };
        let mut cases: Vec<Vec<usize>> = vec![vec![], vec![7], vec![5; 9], vec![3, 2, 1, 2, 3]];
        for n in [2, 10, 100, 1000] {
            for distinct in [1, 3, 40] {
                // Lengths that come in runs, as a run's scales share their FFT length.
                let mut lens = Vec::with_capacity(n);
                while lens.len() < n {
                    let len = 100 + 7 * rng.random_range(0..distinct);
                    let run = rng.random_range(1..6);
                    lens.extend(std::iter::repeat_n(len, run));
                }
                lens.truncate(n);
                cases.push(lens);
            }
        }
        for lens in cases {
            let got = stable_by_length(lens.iter().copied().enumerate().map(|(i, l)| (l, i)));
            assert_eq!(got, sorted(&lens), "{lens:?}");
        }
    }

    #[test]
    fn a_batchs_parts_go_on_the_pool_only_when_the_batch_would_split() {
        let me = std::thread::current().id();
        // Each part's own index and the thread that ran it, in part order.
        let run = |parts: usize, signals: usize| {
            map_parts((0..parts).collect(), signals, |q| {
                (q, std::thread::current().id())
            })
        };
        // Four parts of 20 signals (lavapipe's at 512 scales): 80 signals, side by side.
        let small_parts = run(4, 80);
        assert_eq!(
            small_parts.iter().map(|r| r.0).collect::<Vec<_>>(),
            [0, 1, 2, 3]
        );
        assert!(small_parts.iter().all(|r| r.1 != me), "{small_parts:?}");
        // Fewer signals than one part's loop splits at, or one part (its loop splits
        // itself): on the calling thread.
        for (parts, signals) in [(4, 2 * PAR_MIN - 1), (1, 1000)] {
            let serial = run(parts, signals);
            assert_eq!(serial.len(), parts);
            assert!(
                serial.iter().all(|r| r.1 == me),
                "{parts} parts: {serial:?}"
            );
        }
    }

    #[test]
    fn the_selection_layer_is_turned_off_only_without_a_session_and_unsteered() {
        let with = |set: &[&str]| headless(|k| set.contains(&k));
        assert!(with(&[]));
        assert!(with(&["DISPLAY", "HOME"]));
        assert!(!with(&["XDG_RUNTIME_DIR"]));
        for steer in ["NODEVICE_SELECT", "MESA_VK_DEVICE_SELECT", "DRI_PRIME"] {
            assert!(!with(&[steer]), "{steer}");
        }
    }

    #[test]
    fn the_grid_covers_every_workgroup_within_the_limit() {
        for max in [1u32, 7, 100, 65_535] {
            for groups in [1u64, 2, 99, 100, 101, 10_007, 131_072, 1 << 20] {
                let Ok([x, y, z]) = grid(groups, max) else {
                    assert!(groups > u64::from(max).pow(3), "{groups} within {max}");
                    continue;
                };
                assert!(x <= max && y <= max && z <= max, "{groups} within {max}");
                let n = u64::from(x) * u64::from(y) * u64::from(z);
                // Enough, and less than one more row of waste.
                assert!(
                    n >= groups && n - groups < u64::from(x) * (u64::from(y) + 1),
                    "{groups}: {n}"
                );
            }
        }
    }
}
