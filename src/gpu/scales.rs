//! Host side of `shaders/scales.wgsl`: the coarse |W|² grid of every scale of a batch of
//! runs in one submission — pass band scattered from each run's spectrum, batched inverse
//! FFTs (one group per decimated length), interpolation to the coarse time grid — read
//! back as f32 power per scale and step, computed in f64 where the adapter has SHADER_F64,
//! and each scale's noise gain (what turns its noise median into the white-noise floor).
//! This is the first pass of the wavelet track (`track::track_wavelet`), which the CPU
//! evaluates scale by scale.

use crate::profile::SpanGuard;
use std::collections::HashMap;

use rayon::prelude::*;

use super::fft::{offset_alignment_of, FftStage, Holder};
use super::morlet::{self, split, BinWeights, WaveletParams};
use super::{Gpu, GpuError, Pooled, Real};
use crate::transform::band::{self, ScalePlan};
use crate::transform::{Morlet, Spectrum};

/// Measurement hook: `SKELID_GPU_FIRST_PASS=f32` keeps the first pass in f32 on an adapter
/// with f64 (the refinement stays f64), so that a GPU machine can show what the first
/// pass's f64 costs it (`scripts/gpu-measure.sh`). Its agreement with the CPU is then the
/// f32 first pass's (the README's *Precision*).
pub const FIRST_PASS_ENV: &str = "SKELID_GPU_FIRST_PASS";

/// The shader's `Item`: one run × one scale.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Item {
    spec: u32,
    lo: u32,
    hi: u32,
    centre: u32,
    m: u32,
    data: u32,
    power: u32,
    positions: u32,
    steps: u32,
    gain: u32,
    weights: BinWeights,
}

/// One run's share of a batch: its spectrum, the plans of its scales, and its coarse grid
/// (every `h`-th sample, `steps` of them).
pub struct RunScales<'a> {
    /// The run's padded spectrum.
    pub spectrum: &'a Spectrum,
    /// One plan per scale.
    pub plans: &'a [ScalePlan],
    /// Samples between coarse steps.
    pub h: usize,
    /// Coarse steps.
    pub steps: usize,
    /// Where its bins are in the spectra already on the device ([`super::spectrum::Spectra`]),
    /// and the bin the first of them is; `None` to upload them from `spectrum`.
    pub resident: Option<(usize, usize)>,
}

impl RunScales<'_> {
    /// The bins of the spectrum that the scales' pass bands cover: the first, and how many.
    fn bins(&self) -> (usize, usize) {
        band::covered(self.plans, self.spectrum.bin_count())
    }
}

/// The compiled stage: scatter, power and noise-gain pipelines, their shared bind layout,
/// and the FFT.
pub struct ScaleStage {
    fft: FftStage,
    real: Real,
    /// A note that [`FIRST_PASS_ENV`] held a value it does not take.
    ignored: Option<String>,
    scatter: wgpu::ComputePipeline,
    power: wgpu::ComputePipeline,
    gain: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    positions: PositionCache,
}

/// A table's key: decimated length m, padded length l, samples between coarse steps h,
/// coarse steps.
type PositionKey = (usize, usize, usize, usize);

/// Where each coarse step falls in a decimated scale (index and fraction), by
/// [`PositionKey`]: the same for every record of a campaign's length, so computed once
/// and kept. Recomputing them every batch cost `skelid run` (a few signals a batch, 30-80
/// tables of 1 900 steps) more of the dispatcher's time than recording the batch's passes.
#[derive(Default)]
struct PositionCache(std::sync::Mutex<(HashMap<PositionKey, Positions>, usize)>);

/// One table of [`PositionCache`].
struct Positions {
    index: Vec<u32>,
    /// The fraction as an f32 pair (hi + lo): f32 alone moved |W| by 2e-6 in f64 where W
    /// changes fast against its size (70 dB below a scale's peak).
    frac: Vec<[f32; 2]>,
}

/// Entries kept at most (12 bytes each); past it the cache starts afresh.
const POSITION_CACHE_ENTRIES: usize = 1 << 22;

impl Positions {
    fn new((m, l, h, steps): PositionKey) -> Positions {
        let (index, frac) = (0..steps)
            .map(|j| {
                let x = (j * h) as f64 * m as f64 / l as f64;
                let i = x.floor();
                ((i as usize % m) as u32, split(x - i))
            })
            .unzip();
        Positions { index, frac }
    }
}

/// The cache's lock and what it holds: the tables by key, and their entries in all.
type PositionGuard<'a> = std::sync::MutexGuard<'a, (HashMap<PositionKey, Positions>, usize)>;

impl PositionCache {
    /// The cache, locked, holding every table of `keys`: those not kept yet computed
    /// (each on its own core when there are many entries: a long record's, 16 384 steps at
    /// 2^20 samples for each of up to hundreds of decimated lengths).
    fn holding(&self, keys: &[PositionKey]) -> PositionGuard<'_> {
        let mut guard = self.0.lock().unwrap_or_else(|p| p.into_inner());
        let (kept, entries) = &mut *guard;
        let mut missing: Vec<PositionKey> = keys
            .iter()
            .filter(|k| !kept.contains_key(k))
            .copied()
            .collect();
        if *entries + missing.iter().map(|k| k.3).sum::<usize>() > POSITION_CACHE_ENTRIES {
            kept.clear();
            *entries = 0;
            missing = keys.to_vec();
        }
        let new_entries: usize = missing.iter().map(|k| k.3).sum();
        let made: Vec<(PositionKey, Positions)> = missing
            .into_par_iter()
            .with_min_len(super::min_len_for(new_entries, 1))
            .map(|k| (k, Positions::new(k)))
            .collect();
        for (k, p) in made {
            *entries += k.3;
            kept.insert(k, p);
        }
        guard
    }

    /// The tables of `keys`, back to back, uploaded (index, fraction). Each is copied from
    /// the cache straight into the upload's staging memory, on every core: gathered into
    /// one vector first and uploaded from it, a long record's 13 MB took the dispatcher's
    /// one thread 9 ms a batch here.
    fn upload(&self, gpu: &Gpu, keys: &[PositionKey]) -> Result<[Pooled; 2], GpuError> {
        let guard = self.holding(keys);
        let tables: Vec<&Positions> = keys.iter().map(|k| &guard.0[k]).collect();
        let lens: Vec<usize> = keys.iter().map(|k| k.3).collect();
        let index = gpu.upload_whole_segments("positions", &lens, |i, out: &mut [u32]| {
            out.copy_from_slice(&tables[i].index)
        })?;
        let frac = gpu.upload_whole_segments("fractions", &lens, |i, out: &mut [[f32; 2]]| {
            out.copy_from_slice(&tables[i].frac)
        })?;
        Ok([index, frac])
    }
}

impl ScaleStage {
    /// Compiles `scales.wgsl` (and the FFT) in f64 where the device allows it, else f32
    /// (and in f32 with [`FIRST_PASS_ENV`]` = f32`).
    pub fn new(gpu: &Gpu) -> ScaleStage {
        let (real, ignored) = match std::env::var(FIRST_PASS_ENV).ok().as_deref() {
            Some("f32") => (Real::F32, None),
            Some(v) => (
                gpu.real(),
                Some(format!(
                    "{FIRST_PASS_ENV}={v:?} is not \"f32\", the one value it takes: ignored"
                )),
            ),
            None => (gpu.real(), None),
        };
        ScaleStage {
            ignored,
            ..Self::with_real(gpu, real)
        }
    }

    /// Compiles `scales.wgsl` in `real` (f64 needs [`Gpu::has_f64`]) and declares its
    /// bindings: wavelet (uniform), items, spectrum, data, power, the interpolation
    /// positions (index, fraction), and the noise gains.
    pub fn with_real(gpu: &Gpu, real: Real) -> ScaleStage {
        use super::Binding::{Read, Uniform, Write};
        let (layout, pipelines) = gpu.stage(
            "scales.wgsl",
            &morlet::source(real, include_str!("../../shaders/scales.wgsl")),
            &[Uniform, Read, Read, Write, Write, Read, Read, Write],
            &["scatter", "power_grid", "noise_gain"],
        );
        let [scatter, power, gain]: [wgpu::ComputePipeline; 3] =
            pipelines.try_into().expect("three entry points");
        ScaleStage {
            fft: FftStage::with_real(gpu, real),
            real,
            ignored: None,
            scatter,
            power,
            gain,
            layout,
            positions: PositionCache::default(),
        }
    }

    /// What a user should know of how the stage was compiled ([`FftStage::notes`], and a
    /// [`FIRST_PASS_ENV`] ignored).
    pub fn notes(&self) -> Vec<String> {
        let mut notes = self.fft.notes();
        notes.extend(self.ignored.clone());
        notes
    }

    /// The precision of the spectrum, the FFTs and the interpolation.
    pub fn real(&self) -> Real {
        self.real
    }

    /// The stage's FFT (in [`real`](Self::real)), which the spectra on the device share.
    pub fn fft(&self) -> &FftStage {
        &self.fft
    }

    /// |W|² on each run's coarse grid: per run, scale-major (`[k · steps + j]`), the
    /// values `track`'s first pass interpolates from the band-limited baseband. All runs
    /// go in one submission; split a campaign into batches that fit the adapter first.
    pub fn coarse_power(
        &self,
        gpu: &Gpu,
        wavelet: &Morlet,
        runs: &[RunScales],
    ) -> Result<Vec<Vec<f32>>, GpuError> {
        let mut enc = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("scales"),
            });
        let grid = self.encode(gpu, &mut enc, wavelet, runs, None)?;
        gpu.submit(enc);
        let all: Vec<f32> = gpu.download(&grid.power, grid.len)?;
        Ok(runs
            .iter()
            .zip(&grid.offsets)
            .map(|(r, &o)| all[o..o + r.plans.len() * r.steps].to_vec())
            .collect())
    }

    /// Records the work of [`coarse_power`](Self::coarse_power) into `enc`, leaving the
    /// power grid on the GPU for the next stage (the ridge). The run × scale items are
    /// split into parts whose decimated scales fit one storage binding, so a batch — or a
    /// single record — larger than the adapter's binding limit still runs; only one scale
    /// alone must fit. With `resident` (the part's [`super::spectrum::Spectra`], f64, whose
    /// place each run names in [`RunScales::resident`]) nothing is uploaded: the spectra
    /// are read where they are.
    pub fn encode(
        &self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        wavelet: &Morlet,
        runs: &[RunScales],
        resident: Option<&wgpu::Buffer>,
    ) -> Result<PowerGrid, GpuError> {
        if resident.is_some() && self.real != Real::F64 {
            return Err(GpuError::Unsupported(
                "spectra on the device are f64; this first pass is f32".into(),
            ));
        }
        let align = offset_alignment_of(gpu, self.real);
        let value = self.real.complex_bytes() as u64;
        let limit = gpu.max_binding();
        // Of each spectrum only the bins its scales' pass bands cover, back to back: the
        // band of a record's scales is a small part of its spectrum (the throughput
        // campaign's chirp to 12 Hz at 1 kHz: about 1 700 of 23 000 bins), and the upload
        // of the whole was the largest host cost of the dispatcher's first pass.
        let bands: Vec<(usize, usize)> = match resident {
            Some(_) => runs
                .iter()
                .map(|r| (r.resident.expect("a resident run's place").1, 0))
                .collect(),
            None => runs.iter().map(RunScales::bins).collect(),
        };
        let mut spec_offset = Vec::with_capacity(runs.len());
        let mut spectrum_len = 0usize;
        for (r, &(_, len)) in runs.iter().zip(&bands) {
            match (resident, r.resident) {
                (Some(_), Some((at, _))) => spec_offset.push(at),
                _ => {
                    spec_offset.push(spectrum_len);
                    spectrum_len += len;
                }
            }
        }
        let mut power_offset = Vec::with_capacity(runs.len());
        let mut power_len = 0usize;
        let mut gain_offset = Vec::with_capacity(runs.len());
        let mut gains_len = 0usize;
        for r in runs {
            power_offset.push(power_len);
            power_len += r.plans.len() * r.steps;
            gain_offset.push(gains_len);
            gains_len += r.plans.len();
        }
        for (what, bytes) in [
            ("the spectra", spectrum_len as u64 * value),
            ("the coarse power grid", power_len as u64 * 4),
            ("the noise gains", gains_len as u64 * 8),
        ] {
            if bytes > limit {
                return Err(GpuError::TooLarge {
                    what: format!("{what} of {} run(s)", runs.len()),
                    need: bytes,
                    limit,
                });
            }
        }
        // Items by FFT length; consecutive items form a part while their scales fit.
        let order = by_length(runs);
        // A part's interpolation positions, one table of 12 bytes a step for each of its
        // distinct position keys (index and fraction bound apart, the fractions 8 bytes a
        // step), must fit a binding too.
        let mut parts: Vec<Vec<(usize, usize)>> = Vec::new();
        let (mut used, mut table) = (0u64, 0u64);
        let mut keys: std::collections::HashSet<PositionKey> = std::collections::HashSet::new();
        // This loop runs once per run × scale on the dispatcher's one thread (512 000 items
        // a batch of 1000 runs at 512 scales): it formats no message unless it fails, and
        // hashes no key that the item before had (items come sorted by length, and a
        // batch's runs mostly share the rest of the key).
        let mut last: Option<PositionKey> = None;
        for &(r, k) in &order {
            let run = &runs[r];
            let m = run.plans[k].len;
            let bytes = (m.div_ceil(align) * align) as u64 * value;
            let key = (m, run.spectrum.padded_len, run.h, run.steps);
            let steps = run.steps as u64 * 8;
            if bytes > limit {
                return Err(GpuError::TooLarge {
                    what: format!("one scale of {m} decimated values"),
                    need: bytes,
                    limit,
                });
            }
            if steps > limit {
                return Err(GpuError::TooLarge {
                    what: format!("the positions of {} coarse steps", run.steps),
                    need: steps,
                    limit,
                });
            }
            // Whether the part lists the key already: the item before's it always does.
            let listed = last == Some(key) || keys.contains(&key);
            let more = if listed { 0 } else { steps };
            match parts.last_mut() {
                Some(p) if used + bytes <= limit && table + more <= limit => p.push((r, k)),
                _ => {
                    parts.push(vec![(r, k)]);
                    (used, table) = (0, 0);
                    keys.clear();
                }
            }
            used += bytes;
            // A part just opened lists nothing yet.
            if !listed || keys.is_empty() {
                keys.insert(key);
                table += steps;
            }
            last = Some(key);
        }
        let uniform = gpu.uniform("wavelet", &WaveletParams::new(wavelet));
        let lens: Vec<usize> = bands.iter().map(|b| b.1).collect();
        let bins = |r: usize| {
            let (first, len) = bands[r];
            runs[r].spectrum.bins(first..first + len)
        };
        let uploaded = match resident {
            Some(_) => None,
            None => {
                Some(gpu.upload_complex("spectra", self.real, &lens, |r| bins(r).iter().copied())?)
            }
        };
        let spectrum_buf: &wgpu::Buffer = uploaded.as_deref().or(resident).expect("one of them");
        // Every run × scale item writes all its steps, and its gain: reused buffers serve.
        let power = gpu.reusable("power", (power_len * 4) as u64);
        let gains = gpu.reusable("noise gains", (gains_len * 8) as u64);
        let shared = Shared {
            uniform: &uniform,
            spectrum: spectrum_buf,
            power: &power,
            gains: &gains,
            spec_offset: &spec_offset,
            bands: &bands,
            power_offset: &power_offset,
            gain_offset: &gain_offset,
        };
        let mut keep = Vec::with_capacity(5 * parts.len() + 1);
        for part in &parts {
            keep.extend(crate::profile::span("scales.part", || {
                self.encode_part(gpu, enc, runs, part, &shared)
            })?);
        }
        keep.extend(uploaded);
        Ok(PowerGrid {
            power,
            offsets: power_offset,
            len: power_len,
            gains,
            gain_offsets: gain_offset,
            gains_len,
            keep,
        })
    }

    /// One part's items: scatter, inverse FFTs grouped by length, interpolation.
    fn encode_part(
        &self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        runs: &[RunScales],
        part: &[(usize, usize)],
        shared: &Shared,
    ) -> Result<[Pooled; 5], GpuError> {
        let align = offset_alignment_of(gpu, self.real);
        let value = self.real.complex_bytes();
        let mut table_len = 0usize;
        let mut keys: Vec<PositionKey> = Vec::new();
        let mut tables: HashMap<PositionKey, u32> = HashMap::new();
        let mut items = Vec::with_capacity(part.len());
        let mut groups: Vec<(usize, usize, usize)> = Vec::new(); // (length, offset, count)
        let mut data_len = 0usize;
        let mut last: Option<(PositionKey, u32)> = None;
        let items_span = SpanGuard::new("scales.items");
        for &(r, k) in part {
            let run = &runs[r];
            let plan = &run.plans[k];
            let m = plan.len;
            match groups.last_mut() {
                Some(g) if g.0 == m => g.2 += 1,
                _ => {
                    data_len = data_len.div_ceil(align) * align;
                    groups.push((m, data_len, 1));
                }
            }
            let l = run.spectrum.padded_len;
            let key = (m, l, run.h, run.steps);
            // Items come sorted by length, and a batch's runs mostly share the rest: the
            // last item's table is usually this one's, without hashing the key again.
            let positions = match last {
                Some((k, at)) if k == key => at,
                _ => {
                    let at = *tables.entry(key).or_insert_with(|| {
                        let at = table_len;
                        table_len += run.steps;
                        keys.push(key);
                        at as u32
                    });
                    last = Some((key, at));
                    at
                }
            };
            let (lo, hi, centre) = plan.band();
            let spec = run.spectrum;
            items.push(Item {
                // Where bin `lo` lies in the uploaded segment (never read when the band
                // lies past the spectrum's end: then hi < lo).
                spec: (shared.spec_offset[r] + lo - shared.bands[r].0) as u32,
                lo: lo as u32,
                hi: hi.min(spec.bin_count() - 1) as u32,
                centre: centre as u32,
                m: m as u32,
                data: data_len as u32,
                power: (shared.power_offset[r] + k * run.steps) as u32,
                positions,
                steps: run.steps as u32,
                gain: (shared.gain_offset[r] + k) as u32,
                weights: BinWeights::new(plan.scale, spec.sample_rate, l),
            });
            data_len += m;
        }
        drop(items_span);
        let data_bytes = (data_len * value) as u64;
        // Items along y (and z past one dimension's limit), slots along x.
        let [rows, layers, deeper] = gpu.grid(items.len() as u64)?;
        if deeper > 1 {
            return Err(GpuError::TooLarge {
                what: format!("{} run × scale items in one dispatch", items.len()),
                need: items.len() as u64,
                limit: u64::from(gpu.max_workgroups()).pow(2),
            });
        }
        let max_x = gpu.max_workgroups() as usize;
        let items_buf = gpu.upload_pooled("items", &items)?;
        let data = gpu.reusable("scales", data_bytes);
        let scratch = gpu.reusable("scales scratch", data_bytes);
        let [index_buf, frac_buf] = self.positions.upload(gpu, &keys)?;
        // The items exactly: the shaders count them with `arrayLength`.
        let bind = gpu.bind_resources(
            "scales",
            &self.layout,
            vec![
                shared.uniform.as_entire_binding(),
                items_buf.exact(),
                shared.spectrum.as_entire_binding(),
                data.as_entire_binding(),
                shared.power.as_entire_binding(),
                index_buf.as_entire_binding(),
                frac_buf.as_entire_binding(),
                shared.gains.as_entire_binding(),
            ],
        );
        let longest = groups.iter().map(|g| g.0).max().unwrap_or(1);
        let dispatch = |enc: &mut wgpu::CommandEncoder, label, pipeline, width: usize| {
            let mut pass = gpu.pass(enc, label);
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(width.div_ceil(64).min(max_x) as u32, rows, layers);
        };
        dispatch(enc, "scales.scatter", &self.scatter, longest);
        for &(m, offset, count) in &groups {
            let holder = crate::profile::span("fft.encode", || {
                self.fft
                    .encode(gpu, enc, m, count, true, &data, &scratch, offset)
            })?;
            if holder == Holder::Scratch {
                let bytes = (offset * value) as u64;
                enc.copy_buffer_to_buffer(
                    &scratch,
                    bytes,
                    &data,
                    bytes,
                    (m * count * value) as u64,
                );
            }
        }
        let steps = part.iter().map(|&(r, _)| runs[r].steps).max().unwrap_or(1);
        dispatch(enc, "scales.power", &self.power, steps);
        // One workgroup an item: `width` 1 gives one along x.
        dispatch(enc, "scales.noise_gain", &self.gain, 1);
        Ok([data, scratch, items_buf, index_buf, frac_buf])
    }
}

/// Every run × scale item of a batch as (run, scale), by FFT length, and within a length in
/// (run, scale) order: the order a stable sort by length gives, found by bucketing. A batch
/// has runs × scales items (512 000 for 1000 runs at 512 scales) but a few dozen lengths,
/// and the sort, its key looked up through each item's run, was the largest serial step of
/// the dispatcher's first pass after the part-forming loop.
fn by_length(runs: &[RunScales]) -> Vec<(usize, usize)> {
    super::stable_by_length(runs.iter().enumerate().flat_map(|(r, run)| {
        run.plans
            .iter()
            .enumerate()
            .map(move |(k, p)| (p.len, (r, k)))
    }))
}

/// Buffers every part of a batch shares.
struct Shared<'a> {
    uniform: &'a wgpu::Buffer,
    spectrum: &'a wgpu::Buffer,
    power: &'a wgpu::Buffer,
    gains: &'a wgpu::Buffer,
    /// Where each run's segment starts in `spectrum`.
    spec_offset: &'a [usize],
    /// Each run's first bin uploaded and how many ([`RunScales::bins`]); for spectra
    /// already on the device, the first bin its segment holds, and 0 (nothing uploaded).
    bands: &'a [(usize, usize)],
    power_offset: &'a [usize],
    /// Where each run's noise gains (one a scale) start in `gains`.
    gain_offset: &'a [usize],
}

/// A batch's coarse |W|² on the GPU: runs back to back, each scale-major.
pub struct PowerGrid {
    /// The values (f32).
    pub power: Pooled,
    /// Where each run's values start.
    pub offsets: Vec<usize>,
    /// Values in all.
    pub len: usize,
    /// Each scale's noise gain ([`ScalePlan::noise_gain`]), runs back to back, as f32
    /// pairs (hi + lo).
    pub gains: Pooled,
    /// Where each run's gains start.
    pub gain_offsets: Vec<usize>,
    /// Gains in all.
    pub gains_len: usize,
    /// The work buffers of its submission, held until it has finished.
    pub keep: Vec<Pooled>,
}

#[cfg(test)]
mod tests {
    use super::{PositionCache, PositionKey, RunScales, POSITION_CACHE_ENTRIES};
    use crate::transform::{band::ScalePlan, log_frequencies, Morlet, Spectrum};

    /// The items by length are a stable sort's by length, item for item: runs of two record
    /// lengths, bands and scale counts (one with none), so that lengths repeat within a
    /// run, across runs, and come in both orders.
    #[test]
    fn items_by_length_are_a_stable_sort_by_length() {
        let fs = 200.0;
        let w = Morlet::default();
        let specs: Vec<Spectrum> = [3001usize, 1200]
            .iter()
            .map(|&n| {
                let x: Vec<f64> = (0..n).map(|i| (0.3 * i as f64).sin()).collect();
                Spectrum::new(&x, fs, 400)
            })
            .collect();
        let bands = [
            (0.5, 15.0, 48, 0),
            (10.0, 40.0, 30, 1),
            (20.0, 99.9, 64, 0),
            (1.0, 5.0, 0, 1),
            (0.5, 15.0, 48, 1),
            (30.0, 2.0, 17, 0),
        ];
        let plans: Vec<(Vec<ScalePlan>, usize)> = bands
            .iter()
            .map(|&(a, b, count, s)| {
                let freqs = if count == 0 {
                    Vec::new()
                } else if a < b {
                    log_frequencies(a, b, count)
                } else {
                    // Descending frequencies: lengths that fall within a run.
                    let mut f = log_frequencies(b, a, count);
                    f.reverse();
                    f
                };
                let p = freqs
                    .iter()
                    .map(|&f| ScalePlan::new(&specs[s], &w, w.scale_for(f), 1.5))
                    .collect();
                (p, s)
            })
            .collect();
        let runs: Vec<RunScales> = plans
            .iter()
            .map(|(p, s)| RunScales {
                spectrum: &specs[*s],
                plans: p,
                h: 1,
                steps: 1,
                resident: None,
            })
            .collect();
        let mut reference: Vec<(usize, usize)> = runs
            .iter()
            .enumerate()
            .flat_map(|(r, run)| (0..run.plans.len()).map(move |k| (r, k)))
            .collect();
        reference.sort_by_key(|&(r, k)| runs[r].plans[k].len);
        let mut lengths: Vec<usize> = reference
            .iter()
            .map(|&(r, k)| runs[r].plans[k].len)
            .collect();
        lengths.dedup();
        assert!(lengths.len() >= 8, "lengths: {lengths:?}");
        assert!(lengths.len() < reference.len() / 4, "lengths repeat");
        assert_eq!(super::by_length(&runs), reference);
        assert!(super::by_length(&[]).is_empty());
    }

    #[test]
    fn a_runs_uploaded_bins_are_exactly_what_its_pass_bands_read() {
        let fs = 200.0;
        let x: Vec<f64> = (0..3001)
            .map(|i| (2.0 * std::f64::consts::PI * 7.0 * i as f64 / fs).sin())
            .collect();
        let w = Morlet::default();
        let spec = Spectrum::new(&x, fs, 800);
        let last = spec.bin_count() - 1;
        // Bands inside the spectrum, and one whose top scales run past its end.
        for (fmin, fmax) in [(0.5, 15.0), (10.0, 40.0), (20.0, 99.9)] {
            let plans: Vec<ScalePlan> = log_frequencies(fmin, fmax, 48)
                .iter()
                .map(|&f| ScalePlan::with_tolerance(&spec, &w, w.scale_for(f), 1.0, 1e-3))
                .collect();
            let run = RunScales {
                spectrum: &spec,
                plans: &plans,
                h: 1,
                steps: 1,
                resident: None,
            };
            let (first, len) = run.bins();
            let lo = plans.iter().map(|p| p.band().0).min().unwrap();
            let hi = plans.iter().map(|p| p.band().1.min(last)).max().unwrap();
            assert_eq!((first, first + len - 1), (lo, hi), "{fmin}-{fmax} Hz");
            if fmin >= 10.0 {
                assert!(
                    first > 0,
                    "{fmin}-{fmax} Hz: the bins below the bands stay home"
                );
            }
        }
    }

    /// The tables of `keys` as the cache holds them, back to back.
    fn tables(cache: &PositionCache, keys: &[PositionKey]) -> (Vec<u32>, Vec<[f32; 2]>) {
        let guard = cache.holding(keys);
        let mut out = (Vec::new(), Vec::new());
        for k in keys {
            out.0.extend_from_slice(&guard.0[k].index);
            out.1.extend_from_slice(&guard.0[k].frac);
        }
        out
    }

    #[test]
    fn kept_positions_are_the_formulas_also_after_the_cache_starts_afresh() {
        let direct = |keys: &[PositionKey]| {
            let mut out = (Vec::new(), Vec::new());
            for &(m, l, h, steps) in keys {
                for j in 0..steps {
                    let x = (j * h) as f64 * m as f64 / l as f64;
                    out.0.push((x.floor() as usize % m) as u32);
                    out.1.push(super::split(x - x.floor()));
                }
            }
            out
        };
        let cache = PositionCache::default();
        let small = [(1250, 32768, 16, 1875), (625, 32768, 16, 1875)];
        assert_eq!(tables(&cache, &small), direct(&small));
        assert_eq!(tables(&cache, &small[1..]), direct(&small[1..]));
        // Past the cap: the cache starts afresh, and the small ones come back computed.
        let big = (3 << 20, 1 << 22, 1, (POSITION_CACHE_ENTRIES / 2) + 1);
        let mixed = [small[0], big, small[1]];
        assert_eq!(tables(&cache, &mixed), direct(&mixed));
        assert_eq!(tables(&cache, &[big, small[0]]), direct(&[big, small[0]]));
    }
}
