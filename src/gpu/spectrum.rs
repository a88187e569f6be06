//! Host side of `shaders/spectrum.wgsl`: each run's padded spectrum computed on the device
//! from its samples, uploaded once, and kept there for both of its batch's passes. In: the
//! prepared signals of one part of a batch ([`WaveletPrep::new_deferred`]'s, whose spectrum
//! the CPU did not take; a signal prepared by `WaveletPrep::new` has its kept bins uploaded
//! instead); out: [`Spectra`], every run's kept bins back to back in device memory (what the
//! first pass and the refinement read), and each deferred run's white-noise median above
//! its band, read back with the first pass.
//!
//! The samples go up in f64, less their mean (taken on the host as the CPU takes it, when
//! the signal is prepared); the transform is the stage's FFT (`fft.wgsl`, f64), of the complex sequence with no
//! imaginary part, zero-padded to the padded length the CPU would use. Only with f64: an
//! f32 transform of the whole record would lose the quiet stretches' digits that the f64
//! first pass and refinement exist to keep.

use super::fft::{offset_alignment_of, FftStage, Holder};
use super::{Gpu, GpuError, Pooled, Real};
use crate::track::WaveletPrep;

/// Measurement hook: `SKELID_GPU_SPECTRA=host` keeps the padded spectra on the host (each
/// signal prepared with its spectrum, whose bins each pass uploads), so that a GPU machine
/// can show what computing them on the device buys; `device` (the default where the first
/// pass is f64) computes them there.
pub const SPECTRA_ENV: &str = "SKELID_GPU_SPECTRA";

/// Whether [`SPECTRA_ENV`] lets the spectra be computed on the device, and a note when it
/// held a value it does not take (then they are).
pub fn on_device_from_env() -> (bool, Option<String>) {
    match std::env::var(SPECTRA_ENV).ok().as_deref() {
        None | Some("device") => (true, None),
        Some("host") => (false, None),
        Some(v) => (
            true,
            Some(format!(
                "{SPECTRA_ENV}={v:?} is neither \"host\" nor \"device\": ignored, the spectra \
                 are computed on the device"
            )),
        ),
    }
}

/// The shader's `Run`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct RunEntry {
    flags: u32,
    samples: u32,
    n: u32,
    l: u32,
    work: u32,
    first: u32,
    count: u32,
    resident: u32,
    host: u32,
    noise_lo: u32,
    noise_hi: u32,
    scale: i32,
    slot: u32,
}

/// The shader's `HOST`: a run whose bins the host computed and uploaded.
const HOST: u32 = 1;

/// Samples in one segment of a chunk's upload ([`Gpu::upload_whole_segments`]): 512 kB.
const SAMPLE_PIECE: usize = 1 << 16;

/// The compiled stage: its three pipelines and their bind layout.
pub struct SpectrumStage {
    pack: wgpu::ComputePipeline,
    compact: wgpu::ComputePipeline,
    median: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
}

/// One part's spectra on the device: every run's kept bins (those its pass bands read, bin
/// 0 zeroed) back to back, in f64; and the deferred runs' white-noise medians, until the
/// batch's read-back.
pub struct Spectra {
    /// The bins.
    pub resident: Pooled,
    /// Per run: where its bins start in `resident`, and the bin the first of them is.
    pub at: Vec<(usize, usize)>,
    /// Per run, 16 bytes: its median's key and scaling (the shader's `medians`).
    medians: Pooled,
    /// Chunks the transforms took (each within one binding).
    chunks: usize,
    /// The samples, tables and work buffers, held until the submission has finished.
    keep: Vec<Pooled>,
}

impl Spectra {
    /// The medians' buffer and its length in bytes, for the batch's read-back.
    pub fn medians(&self) -> (&wgpu::Buffer, u64) {
        (&self.medians, self.at.len() as u64 * 16)
    }

    /// How many chunks the runs were transformed in (each chunk's sequences within one
    /// binding).
    pub fn chunks(&self) -> usize {
        self.chunks
    }

    /// Lets the work buffers go (the submission that used them has finished), keeping the
    /// bins for the refinement.
    pub fn release_work(&mut self) {
        self.keep.clear();
    }
}

/// Each run's white-noise median |X|² from the read-back words of [`Spectra::medians`]:
/// `None` where the run has none (too few bins above its band). Only a deferred run's is
/// written: the host found its own for the others, whose words are whatever the buffer
/// held.
pub fn decode_medians(words: &[u32]) -> Vec<Option<f64>> {
    words
        .chunks_exact(4)
        .map(|w| {
            (w[3] == 1).then(|| {
                let hi = f32::from_bits(w[0]);
                // The second word orders as unsigned: its sign bit set for values ≥ 0.
                let lo_bits = if w[1] & 0x8000_0000 != 0 {
                    w[1] & 0x7fff_ffff
                } else {
                    !w[1]
                };
                let lo = f32::from_bits(lo_bits);
                let shift = w[2] as i32;
                (f64::from(hi) + f64::from(lo)) * 2f64.powi(-shift)
            })
        })
        .collect()
}

impl SpectrumStage {
    /// Compiles `spectrum.wgsl` in f64 (the adapter must have SHADER_F64) and declares its
    /// bindings: runs, samples, the FFT's work buffer, the kept bins, the host's bins and
    /// the medians.
    pub fn new(gpu: &Gpu) -> SpectrumStage {
        use super::Binding::{Read, Write};
        let (layout, pipelines) = gpu.stage(
            "spectrum.wgsl",
            &Real::F64.source(&format!(
                "{}\n{}",
                include_str!("../../shaders/spectrum.wgsl"),
                super::SELECT_WGSL
            )),
            &[Read, Read, Write, Write, Read, Write],
            &["pack", "compact", "noise_median"],
        );
        let [pack, compact, median]: [wgpu::ComputePipeline; 3] =
            pipelines.try_into().expect("three entry points");
        SpectrumStage {
            pack,
            compact,
            median,
            layout,
        }
    }

    /// Records the spectra of `preps` (one part of a batch) into `enc` with `fft` (an f64
    /// stage): a deferred run's samples are transformed here, in chunks whose values fit
    /// one binding; another's kept bins are uploaded.
    pub fn encode(
        &self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        fft: &FftStage,
        preps: &[&WaveletPrep],
    ) -> Result<Spectra, GpuError> {
        const VALUE: usize = 16;
        let limit = gpu.max_binding();
        let kept: Vec<std::ops::Range<usize>> = preps.iter().map(|p| p.spec.kept()).collect();
        let mut at = Vec::with_capacity(preps.len());
        let mut resident_len = 0usize;
        for k in &kept {
            at.push((resident_len, k.start));
            resident_len += k.len();
        }
        let deferred = |p: &WaveletPrep| p.deferred.is_some();
        let bytes = (resident_len * VALUE) as u64;
        if bytes > limit {
            return Err(GpuError::TooLarge {
                what: format!("the kept spectra of {} run(s)", preps.len()),
                need: bytes,
                limit,
            });
        }
        for p in preps.iter().filter(|p| deferred(p)) {
            let need = (p.spec.padded_len * VALUE) as u64;
            if need > limit {
                return Err(GpuError::TooLarge {
                    what: format!("the padded spectrum of a record of {} samples", p.len()),
                    need,
                    limit,
                });
            }
        }
        // The host's kept bins (runs it prepared whole), with one value more, never read, so
        // that a buffer none of whose runs has a share still holds a whole value (a binding
        // must). The deferred runs' samples go up chunk by chunk, below.
        let host_lens: Vec<usize> = preps
            .iter()
            .zip(&kept)
            .map(|(p, k)| if deferred(p) { 0 } else { k.len() })
            .chain([1])
            .collect();
        let mut host_at = Vec::with_capacity(preps.len());
        let mut h = 0usize;
        for hl in &host_lens {
            host_at.push(h);
            h += hl;
        }
        let host = gpu.upload_complex("host spectra", Real::F64, &host_lens, |r| {
            let bins = match preps.get(r) {
                Some(p) if p.deferred.is_none() => p.spec.bins(p.spec.kept()),
                _ => &[],
            };
            bins.iter().copied()
        })?;
        let resident = gpu.reusable("kept spectra", bytes.max(VALUE as u64));
        let medians = gpu.reusable("noise medians", (preps.len() * 16).max(16) as u64);
        let entry = |r: usize, work: usize, sample: usize| -> RunEntry {
            let p = preps[r];
            let (noise_lo, noise_hi, scale) = match &p.deferred {
                Some(d) => {
                    let (lo, hi) = d.noise_bins.unwrap_or((1, 0));
                    // |X|² times 2^−2c, c the exponent that brings every bin to at most 1.
                    (lo as u32, hi as u32, -2 * d.scale_exponent)
                }
                None => (1, 0, 0),
            };
            RunEntry {
                flags: if deferred(p) { 0 } else { HOST },
                samples: sample as u32,
                n: p.len() as u32,
                l: p.spec.padded_len as u32,
                work: work as u32,
                first: kept[r].start as u32,
                count: kept[r].len() as u32,
                resident: at[r].0 as u32,
                host: host_at[r] as u32,
                noise_lo,
                noise_hi,
                scale,
                slot: r as u32,
            }
        };
        // Deferred runs by padded length, in chunks whose sequences fit one binding; the
        // host's runs in a chunk of their own that only copies.
        let align = offset_alignment_of(gpu, Real::F64);
        let mut order: Vec<usize> = (0..preps.len()).filter(|&r| deferred(preps[r])).collect();
        order.sort_by_key(|&r| preps[r].spec.padded_len);
        let cap = (limit as usize / VALUE).max(1);
        let mut chunks: Vec<Vec<(usize, usize)>> = Vec::new(); // (run, work offset)
        let mut used = 0usize;
        let mut last_len = 0usize;
        for &r in &order {
            let l = preps[r].spec.padded_len;
            // A new length starts a batched transform of its own, at an aligned offset.
            let mut start = if l == last_len {
                used
            } else {
                used.div_ceil(align) * align
            };
            if chunks.is_empty() || start + l > cap {
                chunks.push(Vec::new());
                start = 0;
            }
            chunks.last_mut().expect("a chunk").push((r, start));
            used = start + l;
            last_len = l;
        }
        let work_len = chunks
            .iter()
            .filter_map(|c| c.last().map(|&(r, at)| at + preps[r].spec.padded_len))
            .max()
            .unwrap_or(1);
        let work_bytes = (work_len * VALUE) as u64;
        let work = gpu.reusable("spectrum work", work_bytes);
        let scratch = gpu.reusable("spectrum scratch", work_bytes);
        let mut keep = vec![host, work, scratch];
        let host_runs: Vec<(usize, usize)> = (0..preps.len())
            .filter(|&r| !deferred(preps[r]))
            .map(|r| (r, 0))
            .collect();
        let max_x = gpu.max_workgroups() as usize;
        for chunk in chunks.iter().chain(std::iter::once(&host_runs)) {
            if chunk.is_empty() {
                continue;
            }
            // The chunk's samples less their mean, back to back (within a binding: each
            // run's n values of 8 bytes take half its L of 16), and one more never read.
            let sample_lens: Vec<usize> = chunk
                .iter()
                .map(|&(r, _)| {
                    if deferred(preps[r]) {
                        preps[r].len()
                    } else {
                        0
                    }
                })
                .chain([1])
                .collect();
            // In pieces, so that a long record's 8 MB are copied by every core.
            let pieces: Vec<(&[f64], usize)> = chunk
                .iter()
                .filter_map(|&(r, _)| preps[r].deferred.as_ref())
                .flat_map(|d| d.centred.chunks(SAMPLE_PIECE).map(|c| (c, c.len())))
                .collect();
            let lens: Vec<usize> = pieces.iter().map(|p| p.1).chain([1]).collect();
            // The run table's offsets below count by `sample_lens`.
            debug_assert_eq!(
                lens.iter().sum::<usize>(),
                sample_lens.iter().sum::<usize>()
            );
            let samples = gpu.upload_whole_segments("samples", &lens, |i, out: &mut [f64]| {
                match pieces.get(i) {
                    Some((values, _)) => out.copy_from_slice(values),
                    None => out.fill(0.0),
                }
            })?;
            let mut sample = 0usize;
            let table: Vec<RunEntry> = chunk
                .iter()
                .zip(&sample_lens)
                .map(|(&(r, w), &n)| {
                    let e = entry(r, w, sample);
                    sample += n;
                    e
                })
                .collect();
            let runs = gpu.upload_pooled("spectrum runs", &table)?;
            let [rows, layers, deeper] = gpu.grid(table.len() as u64)?;
            if deeper > 1 {
                return Err(GpuError::TooLarge {
                    what: format!("{} runs in one spectrum dispatch", table.len()),
                    need: table.len() as u64,
                    limit: u64::from(gpu.max_workgroups()).pow(2),
                });
            }
            let bind = gpu.bind_resources(
                "spectrum",
                &self.layout,
                vec![
                    runs.exact(),
                    samples.as_entire_binding(),
                    keep[1].as_entire_binding(),
                    resident.as_entire_binding(),
                    keep[0].as_entire_binding(),
                    medians.as_entire_binding(),
                ],
            );
            let dispatch = |enc: &mut wgpu::CommandEncoder, label, pipeline, width: usize| {
                let mut pass = gpu.pass(enc, label);
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, &bind, &[]);
                pass.dispatch_workgroups(width.div_ceil(64).clamp(1, max_x) as u32, rows, layers);
            };
            let longest = table.iter().map(|t| t.l as usize).max().unwrap_or(1);
            let widest = table.iter().map(|t| t.count as usize).max().unwrap_or(1);
            let transformed = table.iter().any(|t| t.flags & HOST == 0);
            if transformed {
                dispatch(enc, "spectrum.pack", &self.pack, longest);
                // The chunk's runs by length: one batched transform per length.
                let mut i = 0;
                while i < chunk.len() {
                    let l = preps[chunk[i].0].spec.padded_len;
                    let offset = chunk[i].1;
                    let mut j = i;
                    while j < chunk.len() && preps[chunk[j].0].spec.padded_len == l {
                        j += 1;
                    }
                    let count = j - i;
                    let holder = crate::profile::span("fft.encode", || {
                        fft.encode(gpu, enc, l, count, false, &keep[1], &keep[2], offset)
                    })?;
                    if holder == Holder::Scratch {
                        let bytes = (offset * VALUE) as u64;
                        enc.copy_buffer_to_buffer(
                            &keep[2],
                            bytes,
                            &keep[1],
                            bytes,
                            (l * count * VALUE) as u64,
                        );
                    }
                    i = j;
                }
            }
            dispatch(enc, "spectrum.compact", &self.compact, widest);
            if transformed {
                // One workgroup of 256 a run: `width` 1 gives one along x.
                dispatch(enc, "spectrum.noise_median", &self.median, 1);
            }
            keep.push(runs);
            keep.push(samples);
        }
        // The medians of runs the host transformed are never written: read only those of
        // deferred runs ([`decode_medians`] after the read-back).
        Ok(Spectra {
            resident,
            at,
            medians,
            chunks: chunks.len(),
            keep,
        })
    }
}
