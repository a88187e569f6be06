//! Host side of `shaders/refine.wgsl`: the wavelet track after its ridge for a batch of
//! runs — W, W′, W″ of the scales each run's ridge comes near (the exact pass band,
//! batched inverse FFTs), then per point of each run's estimation grid the three-scale
//! estimate and its bias correction — read back as one 32-byte record per grid point.
//! Where the f32 estimate could decide otherwise than the CPU's f64 (a bias correction
//! that failed or needed more than three Newton steps, a threshold nearly met), the shader
//! also writes the triple's W, W′, W″ in `real` to a slot after the records, and the host
//! finishes that point in f64 exactly as the CPU backend does ([`Decoded::solve`], on the
//! worker that completes the track).
//!
//! The grid comes from the host (`WaveletPrep::grid`, after the first pass's ridge is read
//! back), so the scales evaluated, and the points estimated, are exactly the CPU's. Each
//! run's spectrum goes up once more, only the bins its pass bands use, in f64 where the
//! adapter has SHADER_F64 (else f32; the shader explains why f64), scaled by a power of
//! two. A run whose W, W′, W″ exceed one storage binding is split into pieces over
//! overlapping ranges of scales, each serving the grid points whose scales within
//! [`skeleton::REACH`] of the ridge's it holds.

use crate::profile::SpanGuard;
use rayon::prelude::*;

use super::fft::{offset_alignment_of, plannable, FftStage, Holder};
use super::morlet::{self, BinWeights, WaveletParams};
use super::spectrum::Spectra;
use super::{Gpu, GpuError, Pooled, Real};
use num_complex::Complex64;

use crate::skeleton::{self, GridEstimate, GridPoint, ScaleValue};
use crate::track::WaveletPrep;
use crate::transform::band::{self, ScalePlan};

/// The shader's `Item`: one run × one scale, its three derivative orders (W, W′, W″) back
/// to back from `data`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Item {
    spec: u32,
    lo: u32,
    hi: u32,
    centre: u32,
    m: u32,
    data: u32,
    _pad: u32,
    weights: BinWeights,
}

/// The shader's `Scale`: where one scale of one run sits in `data`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ScaleEntry {
    data: u32,
    m: u32,
    centre: u32,
    _pad: u32,
    scale: f32,
    freq: f32,
    omega_c: f32,
    _pad1: u32,
}

/// The shader's `Run`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct RunParams {
    scales: u32,
    count: u32,
    l: u32,
    correct: u32,
    slot_first: u32,
    slot_cap: u32,
    _pad: [u32; 2],
}

/// The shader's `Point`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct PointParams {
    sample: u32,
    centre: u32,
    run: u32,
    _pad: u32,
}

/// The shader's `NONE`: a scale not evaluated.
const NONE: u32 = u32::MAX;
/// Record flags (the shader's constants): the best scale in the low 16 bits, then these.
const PEAKED: u32 = 0x1_0000;
const CORRECTED: u32 = 0x2_0000;
const NO_TRIPLE: u32 = 0x4_0000;
/// The point's f32 estimate is not trusted: the host solves it again in f64, from the
/// triple's w, w′, w″ in the slot the record's first word names, or, with `OVERFLOW` (all
/// its run's slots taken), from its own values.
const UNSURE: u32 = 0x8_0000;
const OVERFLOW: u32 = 0x10_0000;
/// Slots for unsure points after the records, each run's (or piece's) own: one for every
/// `SLOT_SHARE` of its points and `SLOT_BASE` more, 9 bytes a point. The demo campaign's
/// tracks have 2.9 % of their points unsure, the F-16's 0.6 %; a run with more than its
/// slots has every unsure point refined whole on the host.
const SLOT_SHARE: usize = 16;
const SLOT_BASE: usize = 64;
/// Words of one slot: three scales × w, w′, w″ × re, im × hi, lo.
const SLOT_WORDS: usize = 36;
/// Bytes of one grid point's record.
pub const RECORD_BYTES: u64 = 32;

/// Slots for unsure points after the records of `points` grid points.
fn slot_count(points: usize) -> usize {
    points / SLOT_SHARE + SLOT_BASE
}

/// Bytes of the records of `points` grid points and of their slots.
pub fn records_bytes(points: usize) -> u64 {
    points as u64 * RECORD_BYTES + (slot_count(points) * SLOT_WORDS * 4) as u64
}

/// The compiled stage.
pub struct RefineStage {
    fft: FftStage,
    /// `refine.wgsl`'s pipelines, made at once or on a thread of their own
    /// ([`beside`](Self::beside)).
    made: Made,
    real: Real,
    /// At most this many slots for unsure points a run ([`RefineStage::with_slot_limit`]).
    slot_limit: Option<usize>,
}

/// `refine.wgsl`'s bind layout and its two pipelines.
struct Pipelines {
    scatter: wgpu::ComputePipeline,
    estimate: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
}

impl Pipelines {
    fn new(device: &wgpu::Device, real: Real) -> Pipelines {
        use super::Binding::{Read, Uniform, Write};
        let (layout, pipelines) = Gpu::stage_on(
            device,
            "refine.wgsl",
            &morlet::source(real, include_str!("../../shaders/refine.wgsl")),
            &[Uniform, Read, Read, Write, Read, Read, Read, Write, Write],
            &["scatter", "estimate"],
        );
        let [scatter, estimate]: [wgpu::ComputePipeline; 2] =
            pipelines.try_into().expect("two entry points");
        Pipelines {
            scatter,
            estimate,
            layout,
        }
    }
}

/// [`Pipelines`] made, or being made on another thread.
struct Made {
    ready: std::sync::OnceLock<Pipelines>,
    making: std::sync::Mutex<Option<std::thread::JoinHandle<Pipelines>>>,
}

impl Made {
    fn now(p: Pipelines) -> Made {
        Made {
            ready: std::sync::OnceLock::from(p),
            making: std::sync::Mutex::new(None),
        }
    }

    fn later(handle: std::thread::JoinHandle<Pipelines>) -> Made {
        Made {
            ready: std::sync::OnceLock::new(),
            making: std::sync::Mutex::new(Some(handle)),
        }
    }

    /// The pipelines, once made. A panic of the thread that made them is raised here, in
    /// the refinement's recording, which the dispatcher catches like any other: the
    /// batch is then refined on the CPU.
    fn get(&self) -> &Pipelines {
        self.ready.get_or_init(|| {
            let handle = self.making.lock().unwrap_or_else(|p| p.into_inner()).take();
            match handle.map(|h| crate::profile::span("refine.pipelines_wait", || h.join())) {
                Some(Ok(p)) => p,
                Some(Err(why)) => panic!(
                    "the refinement's pipelines could not be made: {}",
                    crate::backend::panic_message(why.as_ref())
                ),
                None => panic!("the refinement's pipelines could not be made (see above)"),
            }
        })
    }
}

impl Drop for Made {
    /// Waits for pipelines still being made (a command that ends before its first
    /// refinement): the device is released only after, never while its driver compiles
    /// on another thread (see [`crate::backend`]'s dispatcher, which joins likewise).
    fn drop(&mut self) {
        let handle = self
            .making
            .get_mut()
            .unwrap_or_else(|p| p.into_inner())
            .take();
        if let Some(h) = handle {
            let _ = h.join();
        }
    }
}

/// One run's pass-2 plan: the scales it needs, with their exact plans.
struct Planned {
    /// (scale index, plan) of every wanted scale, in scale order.
    scales: Vec<(usize, ScalePlan)>,
    /// The spectrum bins they read, the first and how many ([`band::covered`]): all of
    /// the spectrum that is uploaded.
    first: usize,
    bins: usize,
}

impl Planned {
    /// The uploaded bins.
    fn range(&self) -> std::ops::Range<usize> {
        self.first..self.first + self.bins
    }
}

/// [`plan`] of each run of a part, in parallel from [`PAR_MIN`](super::PAR_MIN) runs.
fn plan_part(preps: &[&WaveletPrep], grids: &[Vec<GridPoint>]) -> Vec<Planned> {
    preps
        .par_iter()
        .zip(grids)
        .with_min_len(super::PAR_MIN)
        .map(|(p, g)| plan(p, g))
        .collect()
}

/// One run's plan: the scales its grid points read and the spectrum bins those cover.
fn plan(prep: &WaveletPrep, grid: &[GridPoint]) -> Planned {
    let scales: Vec<(usize, ScalePlan)> = prep
        .wanted(grid)
        .iter()
        .enumerate()
        .filter(|(_, w)| !w.is_empty())
        .map(|(k, _)| (k, prep.exact_plan(k)))
        .collect();
    let (first, bins) = band::covered(scales.iter().map(|(_, p)| p), prep.spec.bin_count());
    Planned {
        scales,
        first,
        bins,
    }
}

/// A run's share of one sub-part: the scales it evaluates there (indices into its
/// [`Planned::scales`]) and the grid points they serve.
struct Piece {
    run: usize,
    scales: std::ops::Range<usize>,
    points: Points,
}

/// The grid points a piece serves, in record order. A run that fits whole serves all of
/// its points (the usual case): kept as a count, since listing them for a batch of 1000
/// runs was tens of MB written and read on the dispatcher's one thread.
#[derive(Clone)]
enum Points {
    /// Points 0..n.
    All(usize),
    /// These points, ascending (decoding in tasks relies on it).
    Listed(Vec<usize>),
}

impl Points {
    fn len(&self) -> usize {
        match self {
            Points::All(n) => *n,
            Points::Listed(v) => v.len(),
        }
    }

    /// The `k`-th point served.
    fn at(&self, k: usize) -> usize {
        match self {
            Points::All(_) => k,
            Points::Listed(v) => v[k],
        }
    }
}

/// Where a run's grid points are read back: per piece its sub-part, the index of its first
/// record there, and the points in record order.
type Spans = Vec<(usize, usize, Points)>;

/// A refinement recorded into a submission: the sub-parts' record buffers, and per run
/// where its records are (or why the GPU cannot serve it) and the log of the factor its
/// spectrum was scaled by.
pub struct Encoded {
    records: Vec<(Pooled, u64)>,
    /// Grid points of each sub-part: its slots follow their records.
    part_points: Vec<usize>,
    at: Vec<Result<Spans, GpuError>>,
    ln_scale: Vec<f64>,
    /// The work buffers of its submission, held until it has finished.
    _keep: Vec<Pooled>,
}

impl Encoded {
    /// The record buffers and their lengths (bytes), for the batch's read-back.
    pub fn buffers(&self) -> impl Iterator<Item = (&wgpu::Buffer, u64)> {
        self.records.iter().map(|(b, n)| (&**b, *n))
    }

    /// The device's buffers, taken out once their read-back is in, so that decoding (on
    /// any core) does not hand them back to the pool.
    fn release_buffers(&mut self) -> (Vec<(Pooled, u64)>, Vec<Pooled>) {
        (
            std::mem::take(&mut self.records),
            std::mem::take(&mut self._keep),
        )
    }

    /// Each run's grid estimates from the read-back bytes of [`buffers`](Self::buffers), in
    /// order, its unsure points left for [`Decoded::solve`]; `preps` and `grids` are its
    /// part's, as given to [`RefineStage::submit`].
    pub fn decode(
        self,
        words: &[&[u32]],
        preps: &[&WaveletPrep],
        grids: &[Vec<GridPoint>],
    ) -> Vec<Refined> {
        let part_points = &self.part_points;
        self.at
            .into_par_iter()
            .zip(preps.par_iter().zip(grids))
            .zip(&self.ln_scale)
            .with_min_len(super::PAR_MIN)
            .map(|((spans, (prep, grid)), &ln_scale)| {
                let mut out = Decoded {
                    estimates: nones(grid.len()),
                    unsure: Vec::new(),
                    overflow: Vec::new(),
                    ln_scale,
                };
                let mut centres: Vec<Option<u64>> = vec![None; prep.freqs.len()];
                for (part, first, points) in spans? {
                    let all = words[part];
                    let w = &all[first * 8..(first + points.len()) * 8];
                    let reader = Reader {
                        prep,
                        grid,
                        ln_scale,
                        slots: &all[part_points[part] * 8..],
                    };
                    if points.len() > DECODE_TASK {
                        // A long run's records in tasks on every core: each task's points
                        // ascend, so they lie in a stretch of the estimates of their own.
                        let pieces = reader.read_in_tasks(w, &points, &mut out.estimates);
                        for (unsure, overflow) in pieces {
                            out.unsure.extend(unsure);
                            out.overflow.extend(overflow);
                        }
                    } else {
                        for (k, rec) in w.chunks_exact(8).enumerate() {
                            let g = points.at(k);
                            reader.read(
                                rec,
                                g,
                                &mut out.estimates[g],
                                &mut centres,
                                &mut out.unsure,
                                &mut out.overflow,
                            );
                        }
                    }
                }
                // A run that ran out of slots has all its unsure points refined on the host,
                // those with a slot too: which of them found one was the device's timing.
                // In grid order, as `estimate_grid` takes points (it joins neighbours' spans).
                if !out.overflow.is_empty() {
                    out.overflow.extend(out.unsure.drain(..).map(|p| p.g));
                    out.overflow.sort_unstable();
                }
                Ok(out)
            })
            .collect()
    }
}

/// Records in one task of the decoding of a long run, or of a piece of one (the last task
/// fewer): a campaign run's few thousand stay one task, a 2^20-sample record's 156 000 (9
/// ms on the dispatcher's one thread, between its read-back and its completion, on 2 cores)
/// are spread over the cores.
const DECODE_TASK: usize = 16_384;

/// `n` estimates not yet decoded. A long run's 156 000 (17 MB, each page faulted in as it
/// is first written) are written in tasks on every core, not on the dispatcher's one thread,
/// where they were most of its decoding.
fn nones(n: usize) -> Vec<Option<GridEstimate>> {
    if n <= DECODE_TASK {
        return vec![None; n];
    }
    let mut v = Vec::with_capacity(n);
    v.par_extend(rayon::iter::repeat_n(None, n).with_min_len(DECODE_TASK));
    v
}

/// What reading one record back needs besides the record: its run's preparation and grid,
/// the log of the factor its spectrum was scaled by, and its sub-part's slots.
struct Reader<'a> {
    prep: &'a WaveletPrep,
    grid: &'a [GridPoint],
    ln_scale: f64,
    slots: &'a [u32],
}

impl Reader<'_> {
    /// [`read`](Self::read) of every record of `w` (point `points.at(k)` for record k), in
    /// tasks of [`DECODE_TASK`] records on every core; each task's unsure and overflowing
    /// points, in order. The points must ascend (each task then writes a stretch of
    /// `estimates` that no other task touches).
    fn read_in_tasks(
        &self,
        w: &[u32],
        points: &Points,
        estimates: &mut [Option<GridEstimate>],
    ) -> Vec<(Vec<Pending>, Vec<usize>)> {
        let count = points.len();
        debug_assert!((1..count).all(|k| points.at(k - 1) < points.at(k)));
        // Each task's stretch runs from its first point to the next task's first point.
        let mut stretches = Vec::with_capacity(count.div_ceil(DECODE_TASK));
        let mut rest = estimates;
        let mut base = 0;
        for first in (0..count).step_by(DECODE_TASK) {
            let end = if first + DECODE_TASK < count {
                points.at(first + DECODE_TASK)
            } else {
                points.at(count - 1) + 1
            };
            let (mine, tail) = std::mem::take(&mut rest).split_at_mut(end - base);
            stretches.push((first, base, mine));
            rest = tail;
            base = end;
        }
        stretches
            .into_par_iter()
            .map(|(first, base, stretch)| {
                let mut centres = vec![None; self.prep.freqs.len()];
                let (mut unsure, mut overflow) = (Vec::new(), Vec::new());
                let records = &w[first * 8..(first + DECODE_TASK).min(count) * 8];
                for (k, rec) in records.chunks_exact(8).enumerate() {
                    let g = points.at(first + k);
                    self.read(
                        rec,
                        g,
                        &mut stretch[g - base],
                        &mut centres,
                        &mut unsure,
                        &mut overflow,
                    );
                }
                (unsure, overflow)
            })
            .collect()
    }

    /// Grid point `g`'s record `rec`: its estimate into `estimate` where the device trusted
    /// it, else the point into `unsure` (with its slot) or `overflow` (no slot left).
    /// `centres` caches each scale's centre bin.
    fn read(
        &self,
        rec: &[u32],
        g: usize,
        estimate: &mut Option<GridEstimate>,
        centres: &mut [Option<u64>],
        unsure: &mut Vec<Pending>,
        overflow: &mut Vec<usize>,
    ) {
        let flags = rec[7];
        if flags & UNSURE == 0 {
            *estimate = Some(decode(self.prep, self.grid[g], rec, self.ln_scale, centres));
        } else if flags & OVERFLOW != 0 {
            overflow.push(g);
        } else {
            let slot = rec[0] as usize;
            let mut words = [0; SLOT_WORDS];
            words.copy_from_slice(&self.slots[slot * SLOT_WORDS..(slot + 1) * SLOT_WORDS]);
            unsure.push(Pending { g, flags, words });
        }
    }
}

/// One run's skeleton as read back, before the host's share of it: every trusted grid
/// point decoded, the unsure ones (the shader's `UNSURE`) still to be solved in f64 by
/// [`solve`](Self::solve). The dispatcher decodes; the worker that completes the track
/// solves, so that the solves (1–3 % of the points, each the CPU backend's Newton solve:
/// 0.26 ms of CPU a campaign signal when they moved) run on every core instead of on the
/// dispatcher's path between one batch and the next.
pub struct Decoded {
    estimates: Vec<Option<GridEstimate>>,
    unsure: Vec<Pending>,
    /// Unsure points to refine whole on the host: all of them where the run ran out of slots.
    overflow: Vec<usize>,
    /// The log of the factor the run's spectrum was scaled by on the device.
    ln_scale: f64,
}

/// An unsure point's flags and its slot: the triple's w, w′, w″ as the GPU computed them.
struct Pending {
    g: usize,
    flags: u32,
    words: [u32; SLOT_WORDS],
}

impl Decoded {
    /// Whether some points are refined whole on the host (their run ran out of slots),
    /// which reads the spectrum there.
    pub fn refines_on_host(&self) -> bool {
        !self.overflow.is_empty()
    }

    /// Every grid point's estimate: the unsure ones solved in f64 exactly as the CPU
    /// backend solves them. `prep` and `grid` are the run's, as given to the refinement.
    pub fn solve(self, prep: &WaveletPrep, grid: &[GridPoint]) -> Vec<GridEstimate> {
        let Decoded {
            mut estimates,
            unsure,
            overflow,
            ln_scale,
        } = self;
        let mut host = Unsure::new(prep, ln_scale);
        for p in &unsure {
            estimates[p.g] = Some(host.solve(grid[p.g], p.flags, &p.words));
        }
        host.finish(grid, &overflow, &mut estimates);
        estimates
            .into_iter()
            .map(|e| e.expect("every grid point has a piece"))
            .collect()
    }
}

/// The host's f64 solve of one run's unsure points (the shader's `UNSURE`): the exact
/// sequel of the CPU backend's [`skeleton::estimate_point`], from the triple's w, w′, w″ the
/// GPU computed in `real`, or, for the points of a run that ran out of slots, from the
/// CPU's own values.
struct Unsure<'a> {
    prep: &'a WaveletPrep,
    ln_scale: f64,
    /// The analysis scales (s), as the CPU's estimate has them; made at the first use.
    scales: Vec<f64>,
    /// Each scale's exact plan, made at its first use.
    plans: Vec<Option<ScalePlan>>,
    /// Points solved from their slot.
    solved: u64,
}

impl<'a> Unsure<'a> {
    fn new(prep: &'a WaveletPrep, ln_scale: f64) -> Self {
        Unsure {
            prep,
            ln_scale,
            scales: Vec::new(),
            plans: Vec::new(),
            solved: 0,
        }
    }

    /// The point at `p` from its record's `flags` and its slot's `words`.
    fn solve(&mut self, p: GridPoint, flags: u32, words: &[u32; SLOT_WORDS]) -> GridEstimate {
        let prep = self.prep;
        let wl = prep.wavelet();
        if self.scales.is_empty() {
            self.scales = prep.scales();
            self.plans = vec![None; prep.freqs.len()];
        }
        self.solved += 1;
        let best = (flags & 0xffff) as usize;
        let half = |i: usize| f64::from(f32::from_bits(words[i]));
        let triple: [ScaleValue; 3] = std::array::from_fn(|q| {
            let k = best - 1 + q;
            let plan = self.plans[k].get_or_insert_with(|| prep.exact_plan(k));
            let c = |o: usize| {
                let i = 12 * q + 4 * o;
                Complex64::new(half(i) + half(i + 1), half(i + 2) + half(i + 3))
            };
            let (w, w1, w2) = (c(0), c(1), c(2));
            let r1 = w1 / w;
            ScaleValue {
                scale: plan.scale,
                ln_amp: w.norm().max(1e-300).ln() - self.ln_scale,
                phase: w.arg() + plan.carrier(&prep.spec, p.sample as f64),
                d1: r1 + Complex64::new(0.0, plan.carrier_rate()),
                d2: w2 / w - r1 * r1,
            }
        });
        skeleton::estimate_triple(&wl, &self.scales, best, triple, prep.corrects())
    }

    /// The points `overflow` (refined whole), by the CPU backend's own refinement of them.
    fn finish(self, grid: &[GridPoint], overflow: &[usize], out: &mut [Option<GridEstimate>]) {
        crate::profile::refined_points(
            grid.len() as u64,
            self.solved + overflow.len() as u64,
            overflow.len() as u64,
        );
        if overflow.is_empty() {
            return;
        }
        let points: Vec<GridPoint> = overflow.iter().map(|&g| grid[g]).collect();
        for (&g, e) in overflow.iter().zip(self.prep.estimate_grid(&points)) {
            out[g] = Some(e);
        }
    }
}

/// One record as a [`GridEstimate`] in f64: the spectrum's scaling taken off the logs, the
/// carrier's whole turns added to the phase (the shader's is arg W + 2π·frac(c·i/L); the
/// CPU's is arg W + 2π·c·i/L). `centres` caches each scale's demodulation bin.
fn decode(
    prep: &WaveletPrep,
    p: GridPoint,
    w: &[u32],
    ln_scale: f64,
    centres: &mut [Option<u64>],
) -> GridEstimate {
    let f = |i: usize| f64::from(f32::from_bits(w[i]));
    let flags = w[7];
    let best = (flags & 0xffff) as usize;
    let corrected = flags & CORRECTED != 0;
    let wl = prep.wavelet();
    if flags & NO_TRIPLE != 0 {
        let freq = prep.freqs[best];
        return GridEstimate::unobserved(wl.scale_for(freq), freq, best, corrected);
    }
    let c = *centres[best].get_or_insert_with(|| prep.exact_plan(best).band().2 as u64);
    let turns = (c * p.sample as u64 / prep.spec.padded_len as u64) as f64;
    GridEstimate {
        observed_ln_amp: f(0) - ln_scale,
        ln_amp: f(1) - ln_scale,
        phase: f(2) + 2.0 * std::f64::consts::PI * turns,
        decay: f(3),
        frequency: f(4),
        sweep: f(5),
        scale: f(6),
        best,
        peaked: flags & PEAKED != 0,
        corrected,
    }
}

impl RefineStage {
    /// Compiles `refine.wgsl` (and the FFT) in f64 where the device allows it, else f32,
    /// and declares its bindings: wavelet (uniform), items, spectra, data, the scale table,
    /// runs, grid points and records.
    pub fn new(gpu: &Gpu) -> RefineStage {
        Self::with_real(gpu, gpu.real())
    }

    /// [`new`](Self::new) in the given precision (f64 needs [`Gpu::has_f64`]).
    pub fn with_real(gpu: &Gpu, real: Real) -> RefineStage {
        RefineStage {
            fft: FftStage::with_real(gpu, real),
            made: Made::now(Pipelines::new(&gpu.device, real)),
            real,
            slot_limit: None,
        }
    }

    /// [`new`](Self::new), its `refine.wgsl` pipelines made on a thread of their own and
    /// waited for when the first refinement is recorded, so that a command's first pass
    /// (its preparation, upload and device work) runs meanwhile. They are most of what
    /// opening the GPU backend costs: on lavapipe 330–450 ms of a one-shot `track`, before
    /// any work (its two f64 entry points); the FFT stage, whose notes are reported when
    /// the backend opens, is still made at once.
    pub fn beside(gpu: &Gpu) -> RefineStage {
        let (device, real) = (gpu.device.clone(), gpu.real());
        let making = std::thread::Builder::new()
            .name("skelid-gpu-pipelines".into())
            .spawn(move || {
                crate::profile::span("open.refine_pipelines", || Pipelines::new(&device, real))
            });
        let made = match making {
            Ok(handle) => Made::later(handle),
            // No thread to be had: made here, as `new` makes them.
            Err(_) => Made::now(Pipelines::new(&gpu.device, real)),
        };
        RefineStage {
            fft: FftStage::with_real(gpu, real),
            made,
            real,
            slot_limit: None,
        }
    }

    /// The stage with at most `n` slots a run (or piece) for the W, W′, W″ of points whose f32
    /// estimate is not trusted, so that tests reach the host's refinement of those without
    /// one.
    pub fn with_slot_limit(mut self, n: usize) -> RefineStage {
        self.slot_limit = Some(n);
        self
    }

    /// What a user should know of how the stage was compiled ([`FftStage::notes`]).
    pub fn notes(&self) -> Vec<String> {
        self.fft.notes()
    }

    /// The precision of the spectrum, the FFTs and the ratios.
    pub fn real(&self) -> Real {
        self.real
    }

    /// A run's pieces within `limit` bytes each: one for the whole run when its W, W′, W″
    /// fit, else consecutive ranges of its scales overlapping by 2·[`skeleton::REACH`],
    /// each serving the points whose scales ridge ± `REACH` it holds.
    fn pieces(
        &self,
        run: usize,
        prep: &WaveletPrep,
        grid: &[GridPoint],
        planned: &Planned,
        limit: u64,
    ) -> Result<Vec<Piece>, GpuError> {
        let elem = self.real.complex_bytes() as u64;
        let bytes = |r: std::ops::Range<usize>| -> u64 {
            planned.scales[r]
                .iter()
                .map(|(_, p)| 3 * p.len as u64 * elem)
                .sum()
        };
        let spectrum = planned.bins as u64 * elem;
        let records = records_bytes(grid.len());
        let all = 0..planned.scales.len();
        if bytes(all.clone()) + spectrum <= limit && records <= limit {
            return Ok(vec![Piece {
                run,
                scales: all,
                points: Points::All(grid.len()),
            }]);
        }
        let reach = skeleton::REACH;
        let width = 2 * reach + 1;
        let too_large = |need: u64| GpuError::TooLarge {
            what: format!(
                "W, W′, W″ of {width} scales of a record of {} samples with its spectrum",
                prep.len()
            ),
            need,
            limit,
        };
        let s_count = prep.freqs.len();
        let k_of = |i: usize| planned.scales[i].0;
        // Scale ranges: as many scales as fit, the next overlapping the last by 2·REACH
        // scales, so that any point's 2·REACH + 1 scales lie within one range.
        let mut ranges: Vec<std::ops::Range<usize>> = Vec::new();
        let mut start = 0;
        loop {
            let mut end = start;
            while end < planned.scales.len() && bytes(start..end + 1) + spectrum <= limit {
                end += 1;
            }
            if end < planned.scales.len().min(start + width) {
                // The piece's binding holds the run's uploaded spectrum too.
                return Err(too_large(
                    bytes(start..(start + width).min(planned.scales.len())) + spectrum,
                ));
            }
            ranges.push(start..end);
            if end == planned.scales.len() {
                break;
            }
            let back = k_of(end - 1).saturating_sub(2 * reach - 1);
            let next = (start + 1..end).find(|&i| k_of(i) >= back).unwrap_or(end);
            start = next;
        }
        let mut lists: Vec<Vec<usize>> = vec![Vec::new(); ranges.len()];
        for (g, p) in grid.iter().enumerate() {
            let (lo, hi) = (
                p.centre.saturating_sub(reach),
                (p.centre + reach).min(s_count - 1),
            );
            let q = ranges
                .iter()
                .position(|q| k_of(q.start) <= lo && k_of(q.end - 1) >= hi)
                .ok_or_else(|| too_large(limit + 1))?;
            lists[q].push(g);
        }
        // Records of one piece are read back in one buffer.
        if let Some(q) = lists.iter().find(|q| records_bytes(q.len()) > limit) {
            return Err(too_large(records_bytes(q.len())));
        }
        let mut pieces: Vec<Piece> = ranges
            .into_iter()
            .zip(lists)
            .map(|(scales, points)| Piece {
                run,
                scales,
                points: Points::Listed(points),
            })
            .collect();
        pieces.retain(|q| q.points.len() > 0);
        Ok(pieces)
    }

    /// Records the refinement of the runs `preps` (one wavelet), with their estimation
    /// `grids` and their plans ([`plan_part`]), into `enc`. Pieces of runs are grouped into
    /// sub-parts whose buffers each fit one storage binding; a run the GPU cannot serve (an
    /// FFT length it cannot plan, one grid point's scales beyond a binding) gets its reason
    /// instead of a place.
    fn encode(
        &self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        preps: &[&WaveletPrep],
        grids: &[Vec<GridPoint>],
        planned: &[Planned],
        resident: Option<&Spectra>,
    ) -> Result<Encoded, GpuError> {
        if resident.is_some() && self.real != Real::F64 {
            return Err(GpuError::Unsupported(
                "spectra on the device are f64; this refinement is f32".into(),
            ));
        }
        let limit = gpu.max_binding();
        let elem = self.real.complex_bytes() as u64;
        let pieces_span = SpanGuard::new("refine.pieces");
        let mut at: Vec<Result<Spans, GpuError>> = Vec::with_capacity(preps.len());
        let mut parts: Vec<Vec<Piece>> = Vec::new();
        let mut used = (u64::MAX, u64::MAX);
        for (r, (prep, grid)) in preps.iter().zip(grids).enumerate() {
            let p = &planned[r];
            if let Some((_, bad)) = p.scales.iter().find(|(_, s)| !plannable(s.len)) {
                at.push(Err(GpuError::Unsupported(format!(
                    "FFT length {} has a prime factor above 5",
                    bad.len
                ))));
                continue;
            }
            let pieces = match self.pieces(r, prep, grid, p, limit) {
                Ok(q) => q,
                Err(e) => {
                    at.push(Err(e));
                    continue;
                }
            };
            at.push(Ok(Vec::new()));
            for piece in pieces {
                let data: u64 = p.scales[piece.scales.clone()]
                    .iter()
                    .map(|(_, s)| 3 * s.len as u64 * elem)
                    .sum::<u64>()
                    + p.bins as u64 * elem;
                let records = records_bytes(piece.points.len());
                if used.0.saturating_add(data) > limit || used.1.saturating_add(records) > limit {
                    parts.push(Vec::new());
                    used = (0, 0);
                }
                used = (used.0 + data, used.1 + records);
                parts.last_mut().expect("a part was opened").push(piece);
            }
        }
        drop(pieces_span);
        let wl = preps.first().map(|p| p.wavelet()).unwrap_or_default();
        let uniform = gpu.uniform("refine wavelet", &WaveletParams::new(&wl));
        // Each spectrum scaled by a power of two to a largest bin near 1: found from its bins
        // here, or from its samples' bound when the device computed it.
        let scale_span = SpanGuard::new("refine.ln_scale");
        let exponents: Vec<i32> = preps
            .par_iter()
            .zip(planned)
            .with_min_len(super::PAR_MIN)
            .map(|(p, q)| match &p.deferred {
                Some(d) => d.scale_exponent,
                None => crate::transform::bounding_exponent(
                    p.spec
                        .bins(q.range())
                        .iter()
                        .map(|c| c.re.abs().max(c.im.abs()))
                        .fold(0.0f64, f64::max),
                ),
            })
            .collect();
        let ln_scale: Vec<f64> = exponents
            .iter()
            .map(|&c| -f64::from(c) * std::f64::consts::LN_2)
            .collect();
        drop(scale_span);
        let mut records = Vec::with_capacity(parts.len());
        let mut part_points = Vec::with_capacity(parts.len());
        let mut keep = Vec::with_capacity(6 * parts.len());
        for (q, part) in parts.iter().enumerate() {
            let (buffer, bytes, firsts, work) = crate::profile::span("refine.encode_part", || {
                self.encode_part(
                    gpu, enc, &uniform, preps, grids, planned, &ln_scale, &exponents, part,
                    resident,
                )
            })?;
            let points: usize = part.iter().map(|p| p.points.len()).sum();
            for (piece, first) in part.iter().zip(firsts) {
                if let Ok(spans) = &mut at[piece.run] {
                    spans.push((q, first, piece.points.clone()));
                }
            }
            records.push((buffer, bytes));
            part_points.push(points);
            keep.extend(work);
        }
        Ok(Encoded {
            records,
            part_points,
            at,
            ln_scale,
            _keep: keep,
        })
    }

    /// One sub-part: its pieces' spectra, the scatter of every scale's three orders, the
    /// inverse FFTs grouped by length, the estimate at every grid point. Returns its records
    /// buffer and the index of each piece's first record in it.
    #[allow(clippy::too_many_arguments)]
    fn encode_part(
        &self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        uniform: &wgpu::Buffer,
        preps: &[&WaveletPrep],
        grids: &[Vec<GridPoint>],
        planned: &[Planned],
        ln_scale: &[f64],
        exponents: &[i32],
        part: &[Piece],
        resident: Option<&Spectra>,
    ) -> Result<(Pooled, u64, Vec<usize>, Vec<Pooled>), GpuError> {
        let align = offset_alignment_of(gpu, self.real);
        let arrays_span = SpanGuard::new("refine.arrays");
        // Spectra: each piece's bins of its run's pass bands, scaled.
        let mut bins = 0usize;
        let mut spec_at = Vec::with_capacity(part.len());
        for piece in part {
            spec_at.push(bins);
            bins += planned[piece.run].bins;
        }
        // Blocks (piece, scale) by FFT length, in (piece, scale) order within a length (a
        // stable sort's order, by buckets: a piece has a block for each scale its ridge
        // crosses, hundreds at 512 scales); each block is w, w′, w″ back to back.
        let blocks: Vec<(usize, usize)> =
            super::stable_by_length(part.iter().enumerate().flat_map(|(q, piece)| {
                let scales = &planned[piece.run].scales;
                piece.scales.clone().map(move |j| (scales[j].1.len, (q, j)))
            }));
        let mut table_at: Vec<u32> = Vec::with_capacity(part.len());
        let mut table: Vec<ScaleEntry> = Vec::new();
        for piece in part {
            table_at.push(table.len() as u32);
            let prep = preps[piece.run];
            let wl = prep.wavelet();
            table.extend(prep.freqs.iter().map(|&f| ScaleEntry {
                data: NONE,
                m: 0,
                centre: 0,
                _pad: 0,
                scale: wl.scale_for(f) as f32,
                freq: f as f32,
                omega_c: 0.0,
                _pad1: 0,
            }));
        }
        let mut data_len = 0usize;
        let mut groups: Vec<(usize, usize, usize)> = Vec::new(); // (length, offset, sequences)
        let mut items = Vec::with_capacity(blocks.len());
        for &(q, j) in &blocks {
            let r = part[q].run;
            let (k, plan) = &planned[r].scales[j];
            let m = plan.len;
            match groups.last_mut() {
                Some(g) if g.0 == m => g.2 += 3,
                _ => {
                    data_len = data_len.div_ceil(align) * align;
                    groups.push((m, data_len, 3));
                }
            }
            let spec = &preps[r].spec;
            let l = spec.padded_len;
            let (lo, hi, centre) = plan.band();
            let e = &mut table[table_at[q] as usize + k];
            e.data = data_len as u32;
            e.m = m as u32;
            e.centre = centre as u32;
            e.omega_c = plan.carrier_rate() as f32;
            // Where bin `lo` lies: in the piece's uploaded segment, or in the spectra on
            // the device, whose scaling the weights then carry (a power of two: exact).
            let (at, weights) = match resident {
                Some(s) => {
                    let (offset, first) = s.at[r];
                    let factor = 2f64.powi(-exponents[r]);
                    (
                        offset + lo - first,
                        BinWeights::scaled(plan.scale, spec.sample_rate, l, factor),
                    )
                }
                None => (
                    spec_at[q] + lo - planned[r].first,
                    BinWeights::new(plan.scale, spec.sample_rate, l),
                ),
            };
            items.push(Item {
                spec: at as u32,
                lo: lo as u32,
                hi: hi.min(spec.bin_count() - 1) as u32,
                centre: centre as u32,
                m: m as u32,
                data: data_len as u32,
                _pad: 0,
                weights,
            });
            data_len += 3 * m;
        }
        let mut run_params = Vec::with_capacity(part.len());
        let mut firsts = Vec::with_capacity(part.len());
        let mut point_lens = Vec::with_capacity(part.len());
        let mut point_count = 0;
        let mut slot_count_all = 0;
        for (q, piece) in part.iter().enumerate() {
            let prep = preps[piece.run];
            let cap = slot_count(piece.points.len()).min(self.slot_limit.unwrap_or(usize::MAX));
            run_params.push(RunParams {
                scales: table_at[q],
                count: prep.freqs.len() as u32,
                l: prep.spec.padded_len as u32,
                correct: u32::from(prep.corrects()),
                slot_first: slot_count_all as u32,
                slot_cap: cap as u32,
                _pad: [0; 2],
            });
            firsts.push(point_count);
            point_lens.push(piece.points.len());
            point_count += piece.points.len();
            slot_count_all += cap;
        }
        drop(arrays_span);
        let elem = self.real.complex_bytes();
        // Written by every core straight into the upload's memory (none where the spectra
        // are on the device already).
        let lens: Vec<usize> = part.iter().map(|q| planned[q.run].bins).collect();
        let scaled = |q: usize| {
            let r = part[q].run;
            let k = ln_scale[r].exp();
            preps[r]
                .spec
                .bins(planned[r].range())
                .iter()
                .map(move |c| c * k)
        };
        let uploaded = match resident {
            Some(_) => None,
            None => Some(gpu.upload_complex("refine spectra", self.real, &lens, scaled)?),
        };
        let spectra: &wgpu::Buffer = uploaded
            .as_deref()
            .or(resident.map(|s| &*s.resident))
            .expect("one of them");
        let data_bytes = (data_len.max(1) * elem) as u64;
        let items_buf = gpu.upload_pooled("refine items", &items)?;
        let data = gpu.reusable("refine scales", data_bytes);
        let scratch = gpu.reusable("refine scratch", data_bytes);
        let table_buf = gpu.upload_pooled("refine table", &table)?;
        let runs_buf = gpu.upload("refine runs", &run_params);
        // Each piece's points written by every core straight into the upload's memory.
        let points_buf =
            gpu.upload_whole_segments("grid points", &point_lens, |q, out: &mut [PointParams]| {
                let piece = &part[q];
                let grid = &grids[piece.run];
                for (k, o) in out.iter_mut().enumerate() {
                    let g = &grid[piece.points.at(k)];
                    *o = PointParams {
                        sample: g.sample as u32,
                        centre: g.centre as u32,
                        run: q as u32,
                        _pad: 0,
                    };
                }
            })?;
        // The estimate writes every point's record; its unsure points fill their slots.
        let records_len =
            point_count as u64 * RECORD_BYTES + (slot_count_all * SLOT_WORDS * 4) as u64;
        let records = gpu.reusable("grid records", records_len);
        let slots_taken = gpu.upload("refine slots taken", &vec![0u32; part.len()]);
        // Items and points exactly: the shaders count them with `arrayLength`.
        // Waited for here, as late as can be (made on their own thread by `beside`).
        let made = self.made.get();
        let bind = gpu.bind_resources(
            "refine",
            &made.layout,
            vec![
                uniform.as_entire_binding(),
                items_buf.exact(),
                spectra.as_entire_binding(),
                data.as_entire_binding(),
                table_buf.as_entire_binding(),
                runs_buf.as_entire_binding(),
                points_buf.exact(),
                records.as_entire_binding(),
                slots_taken.as_entire_binding(),
            ],
        );
        // Items along y (and z past one dimension's limit), slots along x.
        let [rows, layers, deeper] = gpu.grid(items.len() as u64)?;
        if deeper > 1 {
            return Err(GpuError::TooLarge {
                what: format!("{} scale items in one dispatch", items.len()),
                need: items.len() as u64,
                limit: u64::from(gpu.max_workgroups()).pow(2),
            });
        }
        let longest = groups.iter().map(|g| g.0).max().unwrap_or(1);
        let max_x = gpu.max_workgroups() as usize;
        let _passes = SpanGuard::new("refine.passes");
        if !items.is_empty() {
            let mut pass = gpu.pass(enc, "refine.scatter");
            pass.set_pipeline(&made.scatter);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(longest.div_ceil(64).min(max_x) as u32, rows, layers);
        }
        for &(m, offset, count) in &groups {
            let holder = crate::profile::span("fft.encode", || {
                self.fft
                    .encode(gpu, enc, m, count, true, &data, &scratch, offset)
            })?;
            if holder == Holder::Scratch {
                let bytes = (offset * elem) as u64;
                enc.copy_buffer_to_buffer(&scratch, bytes, &data, bytes, (m * count * elem) as u64);
            }
        }
        if point_count > 0 {
            let [x, y, z] = gpu.grid(point_count.div_ceil(64) as u64)?;
            let mut pass = gpu.pass(enc, "refine.estimate");
            pass.set_pipeline(&made.estimate);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(x, y, z);
        }
        let mut work = vec![data, scratch, items_buf, table_buf, points_buf];
        work.extend(uploaded);
        Ok((records, records_len, firsts, work))
    }
}

/// One run's skeleton as read back, or why the GPU could not refine it.
pub type Refined = Result<Decoded, GpuError>;

/// A submitted refinement: each part's records and their read-back, not yet waited for.
pub struct RefineFlight {
    encoded: Vec<Option<Encoded>>,
    readback: super::Readback,
}

impl RefineStage {
    /// Records and submits the refinement of every run of every part, with the copies of
    /// all records into one staging buffer, and returns without waiting. `parts` hold one
    /// wavelet each (the first pass's), `grids` each run's estimation grid.
    pub fn submit(
        &self,
        gpu: &Gpu,
        parts: &[Vec<&WaveletPrep>],
        grids: &[Vec<Vec<GridPoint>>],
        spectra: &[Option<Spectra>],
    ) -> Result<RefineFlight, GpuError> {
        let mut enc = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("refinement"),
            });
        let mut encoded = Vec::with_capacity(parts.len());
        // Per-run host work in parallel (the dispatcher is one thread for every worker), for
        // every part at once, so that many small parts (a small binding's) still go on every
        // core.
        let signals = parts.iter().map(Vec::len).sum();
        let planned = crate::profile::span("refine.plan", || {
            let pairs: Vec<_> = parts.iter().zip(grids).collect();
            super::map_parts(pairs, signals, |(preps, grids)| plan_part(preps, grids))
        });
        for (q, ((preps, grids), planned)) in parts.iter().zip(grids).zip(&planned).enumerate() {
            let resident = spectra.get(q).and_then(Option::as_ref);
            encoded.push(if preps.is_empty() {
                None
            } else {
                Some(self.encode(gpu, &mut enc, preps, grids, planned, resident)?)
            });
        }
        let _span = SpanGuard::new("refine.readback");
        let wanted: Vec<(&wgpu::Buffer, u64)> =
            encoded.iter().flatten().flat_map(|e| e.buffers()).collect();
        let readback = gpu.encode_readback(&mut enc, &wanted);
        let readback = gpu.submit_reading(enc, readback);
        Ok(RefineFlight { encoded, readback })
    }
}

impl RefineFlight {
    /// Waits for the submission (one blocking wait) and decodes every run's grid estimates,
    /// or per run why the GPU could not serve it. `parts` and `grids` are the ones given to
    /// [`RefineStage::submit`].
    pub fn finish(
        self,
        gpu: &Gpu,
        parts: &[Vec<&WaveletPrep>],
        grids: &[Vec<Vec<GridPoint>>],
    ) -> Result<Vec<Vec<Refined>>, GpuError> {
        let RefineFlight { encoded, readback } = self;
        // Decoded where the driver mapped the words, before the staging buffer goes back.
        gpu.read_in_place(readback, |words| {
            decode_refinement(parts, grids, encoded, words)
        })
    }
}

/// Every part's runs' grid estimates from the read-back `words` of its [`RefineFlight`]
/// (one a records buffer of each part that the device served, in order), or per run why
/// the GPU could not serve it.
fn decode_refinement(
    parts: &[Vec<&WaveletPrep>],
    grids: &[Vec<Vec<GridPoint>>],
    encoded: Vec<Option<Encoded>>,
    words: &[&[u32]],
) -> Vec<Vec<Refined>> {
    let mut by_part = words.iter().copied();
    let mut read = Vec::with_capacity(parts.len());
    let mut held = Vec::with_capacity(parts.len());
    for e in encoded {
        read.push(e.map(|mut e| {
            let words: Vec<&[u32]> = (0..e.records.len())
                .map(|_| by_part.next().expect("one read-back per records buffer"))
                .collect();
            held.push(e.release_buffers());
            (e, words)
        }));
    }
    // Each part's runs; the parts side by side where they are many and small.
    let signals = parts.iter().map(Vec::len).sum();
    let work: Vec<_> = parts.iter().zip(grids).zip(read).collect();
    let decoded = crate::profile::span("refine.decode", || {
        super::map_parts(work, signals, |((preps, grids), read)| match read {
            Some((e, words)) => e.decode(&words, preps, grids),
            None => Vec::new(),
        })
    });
    // The device's buffers go back to the pool on this thread, after the decoding.
    drop(held);
    decoded
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Everything [`Reader::read`] leaves for one run: its estimates, its unsure points
    /// (point, flags, slot words) and its overflowing points, in order.
    type Read = (
        Vec<Option<GridEstimate>>,
        Vec<(usize, u32, Vec<u32>)>,
        Vec<usize>,
    );

    /// Records decoded in tasks on every core are those decoded one after the other: every
    /// point's estimate in its place, the unsure and overflowing ones in order, for a whole
    /// run and for a piece's ascending list of points.
    #[test]
    fn records_read_in_tasks_equal_records_read_in_order() {
        let fs = 1000.0;
        let x: Vec<f64> = (0..20_000)
            .map(|i| (2.0 * std::f64::consts::PI * 80.0 * i as f64 / fs).sin())
            .collect();
        let prep = WaveletPrep::new(&x, fs, &Default::default(), None).unwrap();
        let s_count = prep.freqs.len();
        let n = 3 * DECODE_TASK + 777;
        let grid: Vec<GridPoint> = (0..n)
            .map(|g| GridPoint {
                sample: g % 20_000,
                centre: 1 + g % (s_count - 2),
            })
            .collect();
        let slots: Vec<u32> = (0..50 * SLOT_WORDS as u32).collect();
        let record = |k: usize| -> [u32; 8] {
            let v = |i: usize| (0.25 + (k * 8 + i) as f32 * 1e-4).to_bits();
            let mut flags = (k % s_count) as u32 | PEAKED | CORRECTED;
            if k.is_multiple_of(97) {
                flags |= UNSURE;
            }
            if k.is_multiple_of(1013) {
                flags |= UNSURE | OVERFLOW;
            }
            let slot = if flags & UNSURE != 0 {
                (k % 50) as u32
            } else {
                v(0)
            };
            [slot, v(1), v(2), v(3), v(4), v(5), v(6), flags]
        };
        let reader = Reader {
            prep: &prep,
            grid: &grid,
            ln_scale: 0.5,
            slots: &slots,
        };
        let listed: Vec<usize> = (0..n).filter(|g| g % 3 != 1).collect();
        for points in [Points::All(n), Points::Listed(listed)] {
            let w: Vec<u32> = (0..points.len()).flat_map(record).collect();
            let mut serial: Read = (vec![None; n], Vec::new(), Vec::new());
            let (mut unsure, mut centres) = (Vec::new(), vec![None; s_count]);
            for (k, rec) in w.chunks_exact(8).enumerate() {
                let g = points.at(k);
                let e = &mut serial.0[g];
                reader.read(rec, g, e, &mut centres, &mut unsure, &mut serial.2);
            }
            serial.1 = unsure
                .iter()
                .map(|p: &Pending| (p.g, p.flags, p.words.to_vec()))
                .collect();
            let mut tasks: Read = (nones(n), Vec::new(), Vec::new());
            for (unsure, overflow) in reader.read_in_tasks(&w, &points, &mut tasks.0) {
                tasks
                    .1
                    .extend(unsure.iter().map(|p| (p.g, p.flags, p.words.to_vec())));
                tasks.2.extend(overflow);
            }
            assert!(serial.0.iter().filter(|e| e.is_some()).count() > 2 * DECODE_TASK);
            assert!(serial.1.len() > 100 && !serial.2.is_empty());
            assert_eq!(tasks, serial);
        }
    }
}
