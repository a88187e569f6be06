//! Host side of `shaders/ridge.wgsl`, and the wavelet track's whole first pass on the GPU
//! for a batch of runs: the scales of [`super::scales`], then per scale the floor score and
//! the median power, then the penalised ridge — one submission and one read-back (a single
//! blocking wait) per batch, and only the paths and the per-scale medians read back (a few
//! kB per run, never the scalogram).

use crate::profile::SpanGuard;
use rayon::prelude::*;

use super::fft::plannable;
use super::scales::{PowerGrid, RunScales, ScaleStage};
use super::spectrum::{Spectra, SpectrumStage};
use super::{Gpu, GpuError, Pooled, Readback, Real};
use crate::track::{CoarseRidge, WaveletPrep};

/// Most scales the ridge programme holds in workgroup memory (the shader's `MAX_SCALES`).
pub const MAX_SCALES: usize = 1024;

/// The shader's `Run`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct RunParams {
    power: u32,
    steps: u32,
    scales: u32,
    back: u32,
    path: u32,
    guide: u32,
    info: u32,
    flags: u32,
    unit: f32,
    penalty: f32,
    guide_weight: f32,
    resolution: f32,
    /// `ridge_steps`' lane: its first step, its first back-pointer, one past its last step.
    origin: u32,
    own: u32,
    end: u32,
    /// Its carried scores (and, after them, the scores at the end of its warm-up).
    slot: u32,
    /// A repair lane's seed: the slot of the lane before.
    seed: u32,
    /// The lane's number within its run.
    lane: u32,
    /// `backtrack_lanes`: the word of the paths buffer where the lane keeps its probe.
    probe: u32,
    /// `backtrack_lanes`: steps past its end where a lane but the last starts.
    reach: u32,
}

/// `RunParams::flags`: the run's ridge is guided.
const GUIDED: u32 = 1;
/// `RunParams::flags`: the penalised programme (else the per-step argmax).
const DYNAMIC: u32 = 2;
/// `RunParams::flags`: a repair lane, seeded with the lane before's final scores.
const REPAIR: u32 = 4;
/// `RunParams::flags`: a run cut into lanes, traced by `backtrack_lanes`.
const SPLIT: u32 = 8;

/// Most steps a lane owns: `backtrack_lanes` walks a lane's steps in one dispatch, within
/// lavapipe's loop limit with its warm-up and the scan of a step's scales.
const MAX_LANE: usize = 32_768;

/// How `ridge_steps` cuts long runs into lanes that run side by side, each after the first
/// warming up on steps of the one before, then checked and, where needed, repaired in
/// order: the same back-pointers, bit for bit, as one workgroup going through every step
/// (`ridge.wgsl`, "Lanes").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Lanes {
    /// Lanes a dispatch aims at, all runs together (a run gets its share); 1 never cuts.
    pub target: usize,
    /// Steps a lane after the first runs before its own (at least 2).
    pub warm: usize,
    /// Fewest steps of a lane's own.
    pub min_len: usize,
}

/// The environment variable that fixes [`Lanes::target`] (for measuring; 1 never cuts).
const LANES_ENV: &str = "SKELID_GPU_RIDGE_LANES";

impl Lanes {
    /// The default for `gpu`: on a hardware GPU up to 256 lanes in all (a GPU has of the
    /// order of a hundred multiprocessors, and a run's workgroup fills one); on a software
    /// adapter, which runs a workgroup on one thread, one lane a thread. A lane warms up on
    /// 128 steps: at 256 scales, lanes started 30–84 steps early on a 2^20-sample log
    /// sweep, and 51–68 on white noise, ended their warm-up on the sequential scores, bit
    /// for bit (with the scores shifted by scale 0's; shifted by each step's largest, since
    /// 2026-11-29, a lane on a clear ridge gets there within a few steps).
    /// `SKELID_GPU_RIDGE_LANES=N` fixes the target (a value that is not a positive number is
    /// an error).
    pub fn for_gpu(gpu: &Gpu) -> Result<Lanes, GpuError> {
        let target = match std::env::var(LANES_ENV).ok() {
            Some(v) => v.parse::<usize>().ok().filter(|&n| n > 0).ok_or_else(|| {
                GpuError::Unsupported(format!(
                    "{LANES_ENV}={v:?}: give the ridge programme's lanes as a positive number (1 \
                     never cuts a run)"
                ))
            })?,
            None if gpu.is_software() => {
                std::thread::available_parallelism().map_or(1, |n| n.get())
            }
            None => 256,
        };
        Ok(Lanes {
            target,
            warm: 128,
            min_len: 512,
        })
    }

    /// Steps of a lane's warm-up: [`Lanes::warm`], at least 2 (the warm-up's last step,
    /// whose scores are kept, comes after its first).
    fn warm_up(&self) -> usize {
        self.warm.max(2)
    }

    /// The lanes of a run of `steps` steps in a dispatch of `runs` runs, as the steps each
    /// owns (`[b_c, b_{c+1})`, the first from step 0): as equal as steps allow, so each
    /// owns at least `min_len` (and its warm-up) and at most [`MAX_LANE`].
    fn bounds(&self, steps: usize, runs: usize) -> Vec<usize> {
        let share = (self.target / runs.max(1)).max(1);
        let most = steps / self.min_len.max(self.warm_up());
        let mut n = share.min(most).max(1);
        if n > 1 {
            n = n.max(steps.div_ceil(MAX_LANE));
        }
        (0..=n).map(|c| c * steps / n).collect()
    }
}

/// The shader's `NO_MEDIAN`: a scale whose noise floor is not estimated.
const NO_MEDIAN: u32 = u32::MAX;

/// The shader's `ScaleInfo`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ScaleInfo {
    first: u32,
    last: u32,
    mid: u32,
    ln_f: f32,
}

/// The shader's `Chunk` uniform: the steps of one dispatch.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Chunk {
    first: u32,
    last: u32,
    /// The most scales of any run: `column_stats` flattens run × scale with it.
    scales: u32,
    /// A repair dispatch's lane number ([`NO_LANE`] otherwise).
    lane: u32,
}

/// `Chunk::lane` of a dispatch that repairs nothing.
const NO_LANE: u32 = u32::MAX;

/// Loop iterations one invocation may run in a dispatch: lavapipe (gallivm) ends a loop
/// nest after 65 535, whatever the shader says; this leaves room for the bookkeeping.
const LOOP_BUDGET: usize = 60_000;

/// Workgroup memory `ridge_steps` takes with `width` invocations (the most of any entry
/// point): two score rows of `MAX_SCALES` f32, a partial maximum and its scale per
/// invocation, three rotating maxima and the repair's count.
const fn workgroup_bytes(width: u32) -> u32 {
    (2 * MAX_SCALES as u32 + 2 * width + 4) * 4
}

/// Invocations of `ridge_steps`' workgroup as `ridge.wgsl` is written (`STEPS_WG`).
const NARROW: u32 = 256;

/// Workgroup memory the ridge shader needs as written.
const WORKGROUP_BYTES: u32 = workgroup_bytes(NARROW);

/// Invocations of the wide programme's workgroup: `ridge_steps` compiled with `STEPS_WG`
/// this large, four invocations sharing each scale's scan at 256 scales, eight at 128.
const WIDE: u32 = 1024;

/// Runs in a dispatch up to which [`RidgeWidth::Auto`] takes the wide programme. One
/// workgroup a run: with fewer than a GPU has multiprocessors (132 on an H100), each
/// workgroup has one to itself and a step lasts as long as its longest scan (halving that
/// scan by sharing it between two invocations halved the H100's programme for batches of
/// 5 runs, 5.2 → 2.6 ms); with many runs the device is full either way, and the narrow
/// programme is the one measured there.
const WIDE_RUNS: usize = 128;

/// The environment variable that fixes the ridge programme's width (for measuring).
const WIDTH_ENV: &str = "SKELID_GPU_RIDGE";

/// Which ridge programme a dispatch runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RidgeWidth {
    /// Wide for dispatches of up to [`WIDE_RUNS`] runs where the adapter allows it and is
    /// a hardware GPU, narrow otherwise: on lavapipe, which runs the invocations one after
    /// another, the wide programme took 43 % longer (one 2^17-sample record, 256 scales).
    Auto,
    /// 256 invocations a run.
    Narrow,
    /// 1024 invocations a run where the adapter allows it (else narrow).
    Wide,
}

impl RidgeWidth {
    /// `SKELID_GPU_RIDGE` (`auto`, `narrow` or `wide`), or `Auto` when it is unset; any
    /// other value is an error that names the three.
    pub fn from_env() -> Result<RidgeWidth, GpuError> {
        match std::env::var(WIDTH_ENV).ok().as_deref() {
            None | Some("auto") => Ok(RidgeWidth::Auto),
            Some("narrow") => Ok(RidgeWidth::Narrow),
            Some("wide") => Ok(RidgeWidth::Wide),
            Some(v) => Err(GpuError::Unsupported(format!(
                "{WIDTH_ENV}={v:?}: use auto (the default), narrow (256 invocations a run) or \
                 wide (1024)"
            ))),
        }
    }
}

/// Most coarse steps per run: `stats` then loops 5 × steps/256 times over a column (its
/// minimum, then the median's four byte passes), far below lavapipe's 65 535.
pub const MAX_STEPS: usize = 1 << 18;

/// Loop iterations an invocation of `ridge_steps` runs per step, at most, for a run of
/// `scales` scales in a workgroup of `width`: `t` invocations share a scale where it is at
/// most half the workgroup (each scans its share of the scale's predecessors, and the first
/// then reads the others' maxima), else each holds ⌈S/width⌉ scales and scans up to S
/// predecessors for each; four for the bookkeeping. Lavapipe's loop limit counts these.
fn loops_per_step(scales: usize, width: usize) -> usize {
    let s = scales.max(1);
    if s <= width / 2 {
        let t = width / s;
        s.div_ceil(t) + 1 + t + 4
    } else {
        s.div_ceil(width) * (s + 2) + 4
    }
}

/// One compiled `ridge_steps`: its pipeline, its invocations a workgroup, and the name of
/// its pass in the trace (the two apart, to compare them on a device).
struct Programme {
    pipeline: wgpu::ComputePipeline,
    width: usize,
    label: &'static str,
}

/// `ridge.wgsl` with `select.wgsl` (its medians' radix selection) appended, compiled as
/// written and, for the wide programme, with `STEPS_WG` changed.
fn source() -> String {
    format!(
        "{}\n{}",
        include_str!("../../shaders/ridge.wgsl"),
        super::SELECT_WGSL
    )
}

/// The compiled ridge stage.
pub struct RidgeStage {
    stats: wgpu::ComputePipeline,
    narrow: Programme,
    /// `ridge_steps` with [`WIDE`] invocations, where the adapter allows that many.
    wide: Option<Programme>,
    width: RidgeWidth,
    backtrack: wgpu::ComputePipeline,
    backtrack_lanes: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    /// Why the driver refused the wide programme, when it did.
    refused: Option<String>,
    lanes: Lanes,
}

/// The first pass of the wavelet track, scales and ridge, on one device.
pub struct FirstPass {
    scales: ScaleStage,
    ridge: RidgeStage,
    /// The padded spectra on the device, where the first pass is f64 (and
    /// [`SPECTRA_ENV`](super::spectrum::SPECTRA_ENV) does not keep them on the host).
    spectrum: Option<SpectrumStage>,
    /// A note that the spectra's setting held a value it does not take.
    spectra_note: Option<String>,
}

/// What a first pass found: per part, every run's ridge and noise statistics, the spectra
/// it left on the device for the refinement, and each run's white-noise median above its
/// band where the device took it (deferred runs).
pub struct FirstPassOut {
    /// Per part, per run.
    pub ridges: Vec<Vec<CoarseRidge>>,
    /// Per part, where the device computed the spectra.
    pub spectra: Vec<Option<Spectra>>,
    /// Per part, per run: the median |X|² above the band (deferred runs with one).
    pub noise_medians: Vec<Vec<Option<f64>>>,
}

impl FirstPass {
    /// Compiles both stages, once the device is known to hold the ridge shader's workgroup.
    pub fn new(gpu: &Gpu) -> Result<FirstPass, GpuError> {
        Self::with_width(gpu, RidgeWidth::from_env()?)
    }

    /// [`new`](Self::new) with the ridge programme's width fixed (tests compare them).
    pub fn with_width(gpu: &Gpu, width: RidgeWidth) -> Result<FirstPass, GpuError> {
        Self::with_lanes(gpu, width, Lanes::for_gpu(gpu)?)
    }

    /// [`with_width`](Self::with_width) with the ridge programme's lanes fixed too.
    pub fn with_lanes(gpu: &Gpu, width: RidgeWidth, lanes: Lanes) -> Result<FirstPass, GpuError> {
        let limits = &gpu.limits;
        if limits.max_compute_workgroup_storage_size < WORKGROUP_BYTES
            || limits.max_compute_invocations_per_workgroup < 256
        {
            return Err(GpuError::Unsupported(format!(
                "the adapter {} allows {} bytes of workgroup memory and {} invocations per \
                 workgroup; the ridge shader needs {WORKGROUP_BYTES} and 256 (use {})",
                gpu.adapter_name(),
                limits.max_compute_workgroup_storage_size,
                limits.max_compute_invocations_per_workgroup,
                crate::hint::Hint::CpuBackend
            )));
        }
        let scales = ScaleStage::new(gpu);
        let (on_device, spectra_note) = super::spectrum::on_device_from_env();
        let spectrum = (on_device && scales.real() == Real::F64).then(|| SpectrumStage::new(gpu));
        Ok(FirstPass {
            scales,
            ridge: RidgeStage::new(gpu, width, lanes),
            spectrum,
            spectra_note,
        })
    }

    /// Whether the padded spectra are computed on the device: signals for it are then
    /// prepared without them ([`WaveletPrep::new_deferred`]).
    pub fn spectra_on_device(&self) -> bool {
        self.spectrum.is_some()
    }

    /// Whether this device computes `prep`'s padded spectrum: its length is one the FFT
    /// plans, its values fit one binding, and its scaling (a power of two that brings its
    /// bins near 1, [`SCALE_EXPONENT_MAX`]) is one the refinement's f32 weights and the
    /// shader's `ldexp` hold. A deferred signal it does not is materialized on the CPU
    /// first, and its bins uploaded.
    pub fn transforms(&self, gpu: &Gpu, prep: &WaveletPrep) -> bool {
        let l = prep.spec.padded_len;
        let scaled = prep
            .deferred
            .as_ref()
            .is_none_or(|d| d.scale_exponent.abs() <= SCALE_EXPONENT_MAX);
        self.spectrum.is_some() && plannable(l) && l as u64 * 16 <= gpu.max_binding() && scaled
    }

    /// The precision of the first pass's transform ([`ScaleStage::real`]).
    pub fn real(&self) -> Real {
        self.scales.real()
    }

    /// What a user should know of how the first pass was compiled ([`ScaleStage::notes`],
    /// [`RidgeStage::notes`]).
    pub fn notes(&self) -> Vec<String> {
        let mut notes = self.scales.notes();
        notes.extend(self.ridge.notes());
        notes.extend(self.spectra_note.clone());
        notes
    }

    /// The coarse ridges, noise medians and noise gains of every run of every part, in one
    /// submission and one read-back (one blocking wait): [`submit`](Self::submit), then
    /// [`InFlight::finish`].
    pub fn coarse_ridges(
        &self,
        gpu: &Gpu,
        parts: &[Vec<&WaveletPrep>],
    ) -> Result<Vec<Vec<CoarseRidge>>, GpuError> {
        self.submit(gpu, parts)?.finish(gpu, parts)
    }

    /// Records and submits the first pass of every run of every part, with the copies of
    /// its results into one staging buffer, and returns without waiting, so that the
    /// caller can prepare and submit the next batch while this one runs. Each part holds
    /// one wavelet and fits the adapter's bindings (size parts with [`batch_bytes`]);
    /// parts let a submission carry more runs than one binding holds.
    pub fn submit(&self, gpu: &Gpu, parts: &[Vec<&WaveletPrep>]) -> Result<InFlight, GpuError> {
        let mut enc = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("first pass"),
            });
        let mut encoded = Vec::with_capacity(parts.len());
        // The ridge programme's per-run tables of every part at once, so that many small
        // parts (a small binding's) still go on every core.
        let signals = parts.iter().map(Vec::len).sum();
        let infos = crate::profile::span("ridge.info", || {
            super::map_parts(parts.iter().collect(), signals, |p| ridge_info(p))
        });
        for (preps, info) in parts.iter().zip(infos) {
            let Some(first) = preps.first() else {
                encoded.push(None);
                continue;
            };
            let wavelet = first.wavelet();
            if let Some(p) = preps.iter().find(|p| p.wavelet() != wavelet) {
                return Err(GpuError::Unsupported(format!(
                    "one part of a GPU batch holds one wavelet; got {:?} and {:?}",
                    wavelet,
                    p.wavelet()
                )));
            }
            for p in preps {
                self.check(gpu, p)?;
            }
            // A part with a deferred signal has every spectrum put on the device (the
            // others' uploaded), for both passes; else the passes upload their bins.
            let spectra = match &self.spectrum {
                Some(stage) if preps.iter().any(|p| p.is_deferred()) => {
                    Some(crate::profile::span("spectrum.encode", || {
                        stage.encode(gpu, &mut enc, self.scales.fft(), preps)
                    })?)
                }
                _ => None,
            };
            let runs: Vec<RunScales> = preps
                .iter()
                .enumerate()
                .map(|(i, p)| RunScales {
                    spectrum: &p.spec,
                    plans: &p.plans,
                    h: p.h,
                    steps: p.steps,
                    resident: spectra.as_ref().map(|s| s.at[i]),
                })
                .collect();
            let grid = crate::profile::span("scales.encode", || {
                let resident = spectra.as_ref().map(|s| &*s.resident);
                self.scales.encode(gpu, &mut enc, &wavelet, &runs, resident)
            })?;
            let out = crate::profile::span("ridge.encode", || {
                self.ridge
                    .encode(gpu, &mut enc, &grid.power, &grid.offsets, preps, info)
            })?;
            encoded.push(Some((grid, out, spectra)));
        }
        // Paths, statistics, noise gains, the white-noise medians (where the device took
        // the spectra) and (when a signal asks for it) the scalogram of every part.
        let mut wanted: Vec<(&wgpu::Buffer, u64)> = Vec::new();
        for (preps, e) in parts.iter().zip(&encoded) {
            let Some((grid, out, spectra)) = e else {
                continue;
            };
            wanted.push((&out.path, out.path_len as u64 * 4));
            wanted.push((&out.stats, out.stats_len as u64 * 8));
            wanted.push((&grid.gains, grid.gains_len as u64 * 8));
            let medians = spectra.as_ref().map(Spectra::medians);
            wanted.push(medians.unwrap_or((&grid.gains, 0)));
            let power = preps.iter().any(|p| p.keep_scalogram);
            wanted.push((&grid.power, if power { grid.len as u64 * 4 } else { 0 }));
        }
        let readback = gpu.encode_readback(&mut enc, &wanted);
        let readback = gpu.submit_reading(enc, readback);
        Ok(InFlight { encoded, readback })
    }

    /// Whether this device can take `prep` at all (alone in a batch): scales, steps, the
    /// FFT lengths and the largest buffer within what the shaders and adapter allow.
    pub fn check(&self, gpu: &Gpu, prep: &WaveletPrep) -> Result<(), GpuError> {
        if prep.freqs.len() > MAX_SCALES {
            return Err(GpuError::Unsupported(format!(
                "{} scales: the GPU ridge holds at most {MAX_SCALES}",
                prep.freqs.len()
            )));
        }
        if prep.steps > MAX_STEPS {
            return Err(GpuError::Unsupported(format!(
                "{} coarse steps: the GPU ridge takes at most {MAX_STEPS} (a record of about \
                 {} samples at this resolution)",
                prep.steps,
                MAX_STEPS * prep.h
            )));
        }
        if let Some(p) = prep.plans.iter().find(|p| !plannable(p.len)) {
            return Err(GpuError::Unsupported(format!(
                "FFT length {} has a prime factor above 5",
                p.len
            )));
        }
        if prep.is_deferred() && !self.transforms(gpu, prep) {
            return Err(GpuError::Unsupported(format!(
                "the padded spectrum of a record of {} samples ({} points) is not one this \
                 device computes: prepare it on the CPU (WaveletPrep::materialize)",
                prep.len(),
                prep.spec.padded_len
            )));
        }
        // The scales are split into parts that fit a binding, but one scale, the spectrum,
        // the power grid and the back-pointers each need one.
        let value = self.real().complex_bytes() as u64;
        let longest = prep.plans.iter().map(|p| p.len).max().unwrap_or(0) as u64 * value;
        for (what, need) in [
            ("one decimated scale", longest + value * 256),
            ("the spectrum", prep.spec.bin_count() as u64 * value),
            ("the ridge grid", (prep.steps * prep.freqs.len()) as u64 * 4),
        ] {
            if need > gpu.max_binding() {
                return Err(GpuError::TooLarge {
                    what: format!("{what} of a record of {} samples", prep.len()),
                    need,
                    limit: gpu.max_binding(),
                });
            }
        }
        Ok(())
    }
}

/// GPU memory one run's first pass in precision `real` takes in the largest of its
/// buffers — its decimated scales (a complex value each), its back-pointers (4 bytes per
/// step and scale) or its spectrum — for sizing batches.
pub fn batch_bytes(prep: &WaveletPrep, real: Real) -> u64 {
    let value = real.complex_bytes() as u64;
    let scales: u64 = prep.plans.iter().map(|p| p.len as u64 * value).sum();
    let back = (prep.steps * prep.freqs.len()) as u64 * 4;
    let spectrum = prep.spec.bin_count() as u64 * value;
    // A spectrum computed on the device takes L complex f64 values twice (the FFT's work
    // and scratch) while the first pass runs.
    let transform = if prep.is_deferred() {
        prep.spec.padded_len as u64 * 16
    } else {
        0
    };
    scales.max(back).max(spectrum).max(transform)
}

/// The largest power of two (either way) a spectrum on the device is scaled by: 2/L
/// times it must stay an f32 pair (the refinement's weights, about 2^±100 at most) and the
/// white-noise median's `ldexp` within f64's exponents. Records whose Σ|x − mean| lies
/// beyond 2^±80 are transformed on the CPU instead.
pub const SCALE_EXPONENT_MAX: i32 = 80;

/// A submitted first pass: its outputs on the GPU and their read-back, not yet waited for.
pub struct InFlight {
    encoded: Vec<Option<(PowerGrid, RidgeOut, Option<Spectra>)>>,
    readback: Readback,
}

impl InFlight {
    /// Waits for the submission (one blocking wait) and reads back every run's ridge,
    /// noise medians and noise gains. `parts` are the ones given to [`FirstPass::submit`].
    /// A deferred signal's white-noise floor above its band is left out: take it from
    /// [`finish_all`](Self::finish_all), as the dispatcher does.
    pub fn finish(
        self,
        gpu: &Gpu,
        parts: &[Vec<&WaveletPrep>],
    ) -> Result<Vec<Vec<CoarseRidge>>, GpuError> {
        self.finish_all(gpu, parts).map(|o| o.ridges)
    }

    /// [`finish`](Self::finish), with the spectra the device keeps for the refinement
    /// (their work buffers let go) and the deferred runs' white-noise medians.
    pub fn finish_all(
        self,
        gpu: &Gpu,
        parts: &[Vec<&WaveletPrep>],
    ) -> Result<FirstPassOut, GpuError> {
        let InFlight { encoded, readback } = self;
        // Decoded where the driver mapped the words, before the staging buffer goes back.
        gpu.read_in_place(readback, |words| decode_first_pass(parts, encoded, words))
    }
}

/// Every part's ridges, noise medians and gains from the read-back `words` of its
/// [`InFlight`] (five a part that the device served, in order), and the spectra the device
/// keeps for the refinement, their work buffers let go.
fn decode_first_pass(
    parts: &[Vec<&WaveletPrep>],
    encoded: Vec<Option<(PowerGrid, RidgeOut, Option<Spectra>)>>,
    words: &[&[u32]],
) -> FirstPassOut {
    let mut by_part = words.iter().copied();
    let mut read = Vec::with_capacity(parts.len());
    let mut kept_spectra = Vec::with_capacity(parts.len());
    let mut noise_medians = Vec::with_capacity(parts.len());
    for (preps, e) in parts.iter().zip(encoded) {
        let Some((grid, out, spectra)) = e else {
            read.push(None);
            kept_spectra.push(None);
            noise_medians.push(Vec::new());
            continue;
        };
        let mut next = || by_part.next().expect("five read-backs per part");
        let (paths, stats, gains, medians, power) = (next(), next(), next(), next(), next());
        noise_medians.push(match &spectra {
            Some(_) => super::spectrum::decode_medians(medians),
            None => vec![None; preps.len()],
        });
        kept_spectra.push(spectra.map(|mut s| {
            s.release_work();
            s
        }));
        read.push(Some((grid, out, [paths, stats, gains, power])));
    }
    // Each part's ridges; the parts side by side where they are many and small.
    let signals = parts.iter().map(Vec::len).sum();
    let pairs: Vec<_> = parts.iter().zip(&read).collect();
    let answers = super::map_parts(pairs, signals, |(preps, read)| {
        let Some((grid, out, [paths, stats, gains, power])) = read else {
            return Vec::new();
        };
        let stats: &[[f32; 2]] = bytemuck::cast_slice(stats);
        let gains: &[[f32; 2]] = bytemuck::cast_slice(gains);
        let power: &[f32] = bytemuck::cast_slice(power);
        preps
            .par_iter()
            .enumerate()
            .with_min_len(super::PAR_MIN)
            .map(|(r, p)| {
                let (po, so) = (out.path_at[r], out.info_at[r]);
                CoarseRidge {
                    path: paths[po..po + p.steps]
                        .iter()
                        .map(|&k| k as usize)
                        .collect(),
                    median_power: (0..p.freqs.len())
                        .map(|k| p.noise_steps(k).map(|_| f64::from(stats[so + k][1])))
                        .collect(),
                    gains: {
                        let at = grid.gain_offsets[r];
                        gains[at..at + p.freqs.len()]
                            .iter()
                            .map(|&[hi, lo]| f64::from(hi) + f64::from(lo))
                            .collect()
                    },
                    power: p.keep_scalogram.then(|| {
                        let at = grid.offsets[r];
                        power[at..at + p.freqs.len() * p.steps].to_vec()
                    }),
                }
            })
            .collect()
    });
    // The device's buffers (`grid`, `out`) go back to the pool on this thread, after
    // the decoding, not on a core.
    drop(read);
    FirstPassOut {
        ridges: answers,
        spectra: kept_spectra,
        noise_medians,
    }
}

/// A run's guide for the ridge programme: each step's guiding log-frequency and weight,
/// where a guide is given.
type Guide = Option<Vec<[f32; 2]>>;

/// Each run's scale table and guide for [`RidgeStage::encode`], in parallel (the dispatcher
/// is one thread for every worker); [`FirstPass::submit`] makes them for every part at once.
fn ridge_info(preps: &[&WaveletPrep]) -> Vec<(Vec<ScaleInfo>, Guide)> {
    preps
        .par_iter()
        .with_min_len(super::PAR_MIN)
        .map(|p| {
            let scales = (0..p.freqs.len())
                .map(|k| {
                    let (first, last) = p.inner_steps(k);
                    ScaleInfo {
                        first: first as u32,
                        last: last as u32,
                        mid: p
                            .noise_steps(k)
                            .map_or(NO_MEDIAN, |(a, b)| ((b + 1 - a) / 2) as u32),
                        ln_f: p.freqs[k].ln() as f32,
                    }
                })
                .collect();
            let guided = (0..p.steps).any(|j| p.guide_at(j).is_some());
            let guide = guided.then(|| {
                (0..p.steps)
                    .map(|j| match p.guide_at(j) {
                        Some(lg) => [lg as f32, 1.0],
                        None => [0.0, 0.0],
                    })
                    .collect()
            });
            (scales, guide)
        })
        .collect()
}

/// The ridge stage's outputs, on the GPU.
struct RidgeOut {
    path: Pooled,
    path_len: usize,
    path_at: Vec<usize>,
    stats: Pooled,
    stats_len: usize,
    info_at: Vec<usize>,
    /// The back-pointers and carried scores, held until the submission has finished.
    _keep: [Pooled; 2],
}

impl RidgeStage {
    /// Compiles `ridge.wgsl` and declares its bindings: runs, scale info, power, guide,
    /// statistics, back-pointers, paths, the chunk, and the scores carried between chunks.
    pub fn new(gpu: &Gpu, width: RidgeWidth, lanes: Lanes) -> RidgeStage {
        use super::Binding::{Read, Uniform, Write};
        let (layout, pipelines) = gpu.stage(
            "ridge.wgsl",
            &source(),
            &[Read, Read, Read, Read, Write, Write, Write, Uniform, Write],
            &[
                "column_stats",
                "ridge_steps",
                "backtrack",
                "backtrack_lanes",
            ],
        );
        let [stats, steps, backtrack, backtrack_lanes]: [wgpu::ComputePipeline; 4] =
            pipelines.try_into().expect("four entry points");
        let limits = &gpu.limits;
        let fits = limits.max_compute_invocations_per_workgroup >= WIDE
            && limits.max_compute_workgroup_size_x >= WIDE
            && limits.max_compute_workgroup_storage_size >= workgroup_bytes(WIDE);
        let width = match width {
            RidgeWidth::Auto if gpu.is_software() => RidgeWidth::Narrow,
            w => w,
        };
        let (wide, refused) = if fits && width != RidgeWidth::Narrow {
            match Self::compile_wide(gpu, &layout) {
                Ok(p) => (Some(p), None),
                Err(why) => (None, Some(why)),
            }
        } else {
            (None, None)
        };
        RidgeStage {
            stats,
            narrow: Programme {
                pipeline: steps,
                width: NARROW as usize,
                label: "ridge.steps",
            },
            wide,
            width,
            backtrack,
            backtrack_lanes,
            layout,
            refused,
            lanes,
        }
    }

    /// `ridge_steps` compiled with [`WIDE`] invocations, or why the driver refused it (the
    /// narrow programme then serves).
    fn compile_wide(gpu: &Gpu, layout: &wgpu::BindGroupLayout) -> Result<Programme, String> {
        let narrow = format!("const STEPS_WG: u32 = {NARROW}u;");
        let source = source();
        assert!(source.contains(&narrow), "ridge.wgsl declares {narrow}");
        let source = source.replace(&narrow, &format!("const STEPS_WG: u32 = {WIDE}u;"));
        let mut pipelines =
            gpu.try_stage_variant("ridge.wgsl (wide)", &source, layout, &["ridge_steps"], true)?;
        Ok(Programme {
            pipeline: pipelines.pop().expect("one entry point"),
            width: WIDE as usize,
            label: "ridge.steps wide",
        })
    }

    /// What a user should know of this stage: the driver's refusal of the wide programme.
    pub fn notes(&self) -> Vec<String> {
        self.refused
            .iter()
            .map(|why| {
                format!(
                    "the GPU driver refused the wide ridge programme ({WIDE} invocations), so \
                     the narrow one ({NARROW}) serves; results are the same: {why}"
                )
            })
            .collect()
    }

    /// The `ridge_steps` programme for a dispatch of `runs` runs (see [`RidgeWidth`]).
    fn programme_for(&self, runs: usize) -> &Programme {
        match (&self.wide, self.width) {
            (Some(w), RidgeWidth::Wide) => w,
            (Some(w), RidgeWidth::Auto) if runs <= WIDE_RUNS => w,
            _ => &self.narrow,
        }
    }

    /// Records the ridge programme of the runs `preps` over their coarse power (at
    /// `power_at` in `power`), with their scale tables and guides from [`ridge_info`].
    fn encode(
        &self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        power: &wgpu::Buffer,
        power_at: &[usize],
        preps: &[&WaveletPrep],
        per_run: Vec<(Vec<ScaleInfo>, Guide)>,
    ) -> Result<RidgeOut, GpuError> {
        let mut params: Vec<RunParams> = Vec::with_capacity(preps.len());
        let mut info = Vec::new();
        let mut guide: Vec<[f32; 2]> = Vec::new();
        let (mut back_len, mut path_len) = (0usize, 0usize);
        let (mut path_at, mut info_at) = (Vec::new(), Vec::new());
        let layout_span = SpanGuard::new("ridge.layout");
        // Each run's lanes (one, unless it is long and the dispatch has few runs), each with
        // a slot of 2 S carried scores; the run's own entry (statistics, backtrack) carries
        // its last lane's slot.
        let dynamic_runs = preps.iter().filter(|p| p.dynamic_ridge()).count();
        let mut lanes: Vec<RunParams> = Vec::with_capacity(preps.len());
        let mut repairs: Vec<RunParams> = Vec::new();
        // The lanes of runs cut in several, which `backtrack_lanes` traces.
        let mut traced: Vec<usize> = Vec::new();
        let mut slots = 0usize;
        for ((p, &at), (scales, run_guide)) in preps.iter().zip(power_at).zip(per_run) {
            let s = p.freqs.len();
            let guided = run_guide.is_some();
            let (weight, resolution) = p.guide_weight();
            let whole = RunParams {
                power: at as u32,
                steps: p.steps as u32,
                scales: s as u32,
                back: back_len as u32,
                path: path_len as u32,
                guide: guide.len() as u32,
                info: info.len() as u32,
                flags: if guided { GUIDED } else { 0 }
                    | if p.dynamic_ridge() { DYNAMIC } else { 0 },
                unit: p.unit as f32,
                penalty: p.penalty(),
                guide_weight: weight as f32,
                resolution: resolution as f32,
                origin: 0,
                own: 1,
                end: p.steps as u32,
                slot: slots as u32,
                seed: 0,
                lane: 0,
                probe: 0,
                reach: 0,
            };
            let bounds = if p.dynamic_ridge() {
                self.lanes.bounds(p.steps, dynamic_runs)
            } else {
                vec![0, p.steps]
            };
            let warm = self.lanes.warm_up();
            let split = bounds.len() > 2;
            for (c, b) in bounds.windows(2).enumerate() {
                let lane = RunParams {
                    origin: if c == 0 {
                        0
                    } else {
                        (b[0] - warm.min(b[0])) as u32
                    },
                    own: b[0].max(1) as u32,
                    end: b[1] as u32,
                    slot: (slots + 2 * s * c) as u32,
                    lane: c as u32,
                    reach: warm as u32,
                    ..whole
                };
                if split {
                    traced.push(lanes.len());
                }
                if c > 0 {
                    repairs.push(RunParams {
                        flags: lane.flags | REPAIR,
                        origin: lane.own - 1,
                        seed: lane.slot - 2 * s as u32,
                        ..lane
                    });
                }
                lanes.push(lane);
            }
            let last = (bounds.len() - 2) * 2 * s;
            params.push(RunParams {
                slot: (slots + last) as u32,
                flags: whole.flags | if split { SPLIT } else { 0 },
                ..whole
            });
            slots += 2 * s * (bounds.len() - 1);
            path_at.push(path_len);
            info_at.push(info.len());
            info.extend(scales);
            if let Some(g) = run_guide {
                guide.extend(g);
            }
            back_len += p.steps * s;
            path_len += p.steps;
        }
        // Each traced lane's probe, after the paths.
        let probes: Vec<RunParams> = traced
            .iter()
            .enumerate()
            .map(|(i, &l)| RunParams {
                probe: (path_len + i) as u32,
                ..lanes[l]
            })
            .collect();
        drop(layout_span);
        let back_bytes = back_len as u64 * 4;
        if back_bytes > gpu.max_binding() {
            return Err(GpuError::TooLarge {
                what: format!("the ridge back-pointers of {} run(s)", preps.len()),
                need: back_bytes,
                limit: gpu.max_binding(),
            });
        }
        if guide.is_empty() {
            guide.push([0.0, 0.0]);
        }
        let runs_buf = gpu.upload("ridge runs", &params);
        let lanes_buf = gpu.upload("ridge lanes", &lanes);
        let repairs_buf = (!repairs.is_empty()).then(|| gpu.upload("ridge repairs", &repairs));
        let probes_buf = (!probes.is_empty()).then(|| gpu.upload("ridge traced lanes", &probes));
        let info_buf = gpu.upload("scale info", &info);
        let guide_buf = gpu.upload("guide", &guide);
        // All four are written in full before they are read (statistics per scale, a
        // back-pointer per step after the first, the path per step, the scores at each
        // chunk's end and each warm-up's): reused buffers serve.
        let stats = gpu.reusable("column stats", (info.len() * 8) as u64);
        let back = gpu.reusable("back-pointers", back_bytes);
        let path = gpu.reusable("paths", ((path_len + probes.len()) * 4) as u64);
        let accum = gpu.reusable("carried scores", (slots.max(1) * 4) as u64);
        let max_scales = preps.iter().map(|p| p.freqs.len()).max().unwrap_or(1);
        let max_steps = preps.iter().map(|p| p.steps).max().unwrap_or(1);
        let programme = self.programme_for(lanes.len());
        let per_step = preps
            .iter()
            .map(|p| loops_per_step(p.freqs.len(), programme.width))
            .max()
            .unwrap_or(1);
        let per_chunk = (LOOP_BUDGET / per_step).max(1);
        let bind = |runs: &wgpu::Buffer, first: usize, last: usize, lane: u32| {
            let range = Chunk {
                first: first as u32,
                last: last as u32,
                scales: max_scales as u32,
                lane,
            };
            gpu.bind(
                "ridge",
                &self.layout,
                &[
                    runs,
                    &info_buf,
                    power,
                    &guide_buf,
                    &stats,
                    &back,
                    &path,
                    &gpu.uniform("chunk", &range),
                    &accum,
                ],
            )
        };
        // The statistics and the backtrack go over whole runs, in chunks of absolute steps;
        // the backtrack over the runs not cut into lanes (the others' are traced apart).
        let whole_steps = params
            .iter()
            .filter(|r| r.flags & SPLIT == 0)
            .map(|r| r.steps as usize)
            .max()
            .unwrap_or(0);
        let chunks: Vec<wgpu::BindGroup> = (0..whole_steps.div_ceil(per_chunk).max(1))
            .map(|c| {
                bind(
                    &runs_buf,
                    c * per_chunk,
                    ((c + 1) * per_chunk).min(max_steps),
                    NO_LANE,
                )
            })
            .collect();
        // The programme over lanes, in chunks of steps counted from each lane's origin.
        let longest = |ls: &mut dyn Iterator<Item = &RunParams>| {
            ls.map(|l| (l.end - l.origin) as usize).max().unwrap_or(0)
        };
        let lane_chunks: Vec<wgpu::BindGroup> = (0..longest(&mut lanes.iter()).div_ceil(per_chunk))
            .map(|c| bind(&lanes_buf, c * per_chunk, (c + 1) * per_chunk, NO_LANE))
            .collect();
        // The repair: lane 1 of every run, then lane 2, …, each in its chunks.
        let mut repair_chunks: Vec<wgpu::BindGroup> = Vec::new();
        if let Some(buf) = &repairs_buf {
            let most = repairs.iter().map(|l| l.lane).max().unwrap_or(0);
            for c in 1..=most {
                let these = longest(&mut repairs.iter().filter(|l| l.lane == c));
                for d in 0..these.div_ceil(per_chunk) {
                    repair_chunks.push(bind(buf, d * per_chunk, (d + 1) * per_chunk, c));
                }
            }
        }
        // Four passes, so that the trace times the statistics, the programme, its repair
        // and the backtrack apart. Each dispatch sees the previous one's writes (WebGPU
        // orders them).
        let [x, y, z] = gpu.grid((max_scales * preps.len()) as u64)?;
        {
            let mut pass = gpu.pass(enc, "ridge.stats");
            pass.set_pipeline(&self.stats);
            pass.set_bind_group(0, &chunks[0], &[]);
            pass.dispatch_workgroups(x, y, z);
        }
        let [x, y, z] = gpu.grid(lanes.len() as u64)?;
        {
            let mut pass = gpu.pass(enc, programme.label);
            pass.set_pipeline(&programme.pipeline);
            for b in &lane_chunks {
                pass.set_bind_group(0, b, &[]);
                pass.dispatch_workgroups(x, y, z);
            }
        }
        if !repair_chunks.is_empty() {
            let [x, y, z] = gpu.grid(repairs.len() as u64)?;
            let mut pass = gpu.pass(enc, "ridge.repair");
            pass.set_pipeline(&programme.pipeline);
            for b in &repair_chunks {
                pass.set_bind_group(0, b, &[]);
                pass.dispatch_workgroups(x, y, z);
            }
        }
        let [x, y, z] = gpu.grid(preps.len() as u64)?;
        {
            let mut pass = gpu.pass(enc, "ridge.backtrack");
            pass.set_pipeline(&self.backtrack);
            for b in chunks.iter().rev() {
                pass.set_bind_group(0, b, &[]);
                pass.dispatch_workgroups(x, y, z);
            }
        }
        if let Some(buf) = &probes_buf {
            // Every traced lane from its own start, then the repair from the last lanes
            // down: a lane's turn comes once the next lane's path is final.
            let [x, y, z] = gpu.grid(probes.len() as u64)?;
            let most = probes.iter().map(|l| l.lane).max().unwrap_or(0);
            let turns: Vec<wgpu::BindGroup> = std::iter::once(NO_LANE)
                .chain((0..most).rev())
                .map(|c| bind(buf, 0, 0, c))
                .collect();
            let mut pass = gpu.pass(enc, "ridge.backtrack lanes");
            pass.set_pipeline(&self.backtrack_lanes);
            for b in &turns {
                pass.set_bind_group(0, b, &[]);
                pass.dispatch_workgroups(x, y, z);
            }
        }
        Ok(RidgeOut {
            path,
            path_len,
            path_at,
            stats,
            stats_len: info.len(),
            info_at,
            _keep: [back, accum],
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lanes_cover_every_step_once_within_their_limits() {
        let lanes = Lanes {
            target: 256,
            warm: 128,
            min_len: 512,
        };
        // One long run: 32 lanes of 512 steps; a campaign's: never cut.
        assert_eq!(lanes.bounds(16_384, 1).len() - 1, 32);
        assert_eq!(lanes.bounds(938, 1), vec![0, 938]);
        assert_eq!(lanes.bounds(16_384, 1000), vec![0, 16_384]);
        let never = Lanes { target: 1, ..lanes };
        assert_eq!(never.bounds(1 << 18, 1), vec![0, 1 << 18]);
        for (lanes, steps, runs) in [
            (lanes, 16_384, 1),
            (lanes, 16_383, 3),
            (lanes, 1_025, 1),
            (Lanes { target: 2, ..lanes }, 1 << 18, 1),
            (
                Lanes {
                    target: 24,
                    warm: 2,
                    min_len: 16,
                },
                94,
                3,
            ),
            // Lanes of ⌈33/4⌉ = 9 steps would leave the last 6, under min_len.
            (
                Lanes {
                    target: 24,
                    warm: 2,
                    min_len: 8,
                },
                33,
                1,
            ),
        ] {
            let b = lanes.bounds(steps, runs);
            assert_eq!((b[0], *b.last().unwrap()), (0, steps));
            for w in b.windows(2) {
                let len = w[1] - w[0];
                assert!(len > 0 && len <= MAX_LANE, "{b:?}");
                if b.len() > 2 {
                    // Each lane's warm-up lies inside the lane before.
                    assert!(w[0] == 0 || w[0] >= lanes.warm_up(), "{b:?}");
                    assert!(len >= lanes.min_len.min(steps), "{b:?}");
                }
            }
            assert!(b.len() - 1 <= (lanes.target / runs).max(1).max(steps.div_ceil(MAX_LANE)));
        }
    }
}
