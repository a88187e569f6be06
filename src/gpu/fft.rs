//! Host side of `shaders/fft.wgsl` and `shaders/fft_local.wgsl`: batched complex FFTs of
//! any length 2^a·3^b·5^c (the lengths [`plan_len`](crate::transform::plan_len) chooses),
//! in f32 or (where the adapter has SHADER_F64) f64, by one of two [`Algorithm`]s that
//! [`FftStage::algorithm`] picks per length: every transform that fits one workgroup's
//! memory in one dispatch ([`Algorithm::Local`]), longer ones one dispatch per radix pass
//! through global memory, ping-ponging between two buffers ([`Algorithm::Passes`]).

use num_complex::Complex;

use super::{Gpu, GpuError, Real};

/// The shader's `Pass` uniform, declared once here for the host.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct PassParams {
    n: u32,
    radix: u32,
    ns: u32,
    batch: u32,
    inverse: u32,
    _pad: [u32; 3],
}

/// Invocations per workgroup (the shader's `@workgroup_size`).
const WORKGROUP: u32 = 64;

/// Invocations per workgroup of `fft_local.wgsl` (its `WG` and `@workgroup_size`).
const LOCAL_WORKGROUP: usize = 256;

/// The longest transform [`Algorithm::Local`] takes, whatever the adapter's workgroup
/// memory: it bounds the values an invocation holds in registers in a pass.
const LOCAL_MAX: usize = 8192;

/// Roots a task of [`FftStage::roots`] computes: about 100 µs of cosines and sines, so
/// that a table of 64 k roots is 8 tasks and one of a few thousand stays one.
const ROOTS_PIECE: usize = 8192;

/// The longest root table the host computes whole; longer ones are expanded on the
/// device (`FftStage::roots`). Every length of a campaign of 30 000-sample runs (46 080
/// at most) stays on the host, its tables as they were to the bit.
pub const ROOTS_ON_HOST_MAX: usize = 1 << 16;

/// Test and measurement hook: `1` sends every length that fits a workgroup to
/// [`Algorithm::Local`] whatever the adapter, `0` sends every length to
/// [`Algorithm::Passes`]; unset, [`FftStage::algorithm`] chooses. One binary can so
/// measure both algorithms side by side, and lavapipe test the local one end to end.
pub const LOCAL_ENV: &str = "SKELID_GPU_FFT_LOCAL";

/// What [`LOCAL_ENV`] asks for: `Some(true)` for `1`, `Some(false)` for `0`, `None`
/// (the planner's choice) when unset or anything else.
pub fn local_hook() -> Option<bool> {
    match std::env::var(LOCAL_ENV).ok()?.trim() {
        "1" => Some(true),
        "0" => Some(false),
        _ => None,
    }
}

/// How a length is transformed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Algorithm {
    /// One dispatch per radix pass (`fft.wgsl`), each reading and writing every sequence
    /// in global memory: any length.
    Passes,
    /// One dispatch for all the passes (`fft_local.wgsl`), each sequence held in one
    /// workgroup's memory: lengths up to [`FftStage::local_cap`]. On an adapter with 48 kB of
    /// it, every one of the refinement's transforms (40 to 3072 points, f64).
    Local,
}

/// Most radix passes `fft_local.wgsl`'s uniform holds (its `radix`, four `vec4<u32>`):
/// the longest local length, [`LOCAL_MAX`] = 2^13, takes 7.
const LOCAL_PASSES: usize = 16;

/// The shader `fft_local.wgsl`'s `Local` uniform, declared once here for the host.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct LocalParams {
    n: u32,
    batch: u32,
    inverse: u32,
    passes: u32,
    radix: [u32; LOCAL_PASSES],
}

/// One compiled `fft_local.wgsl` and the longest length it takes.
struct LocalStage {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    cap: usize,
}

/// The capacities `fft_local.wgsl` is compiled with on this adapter, smallest first: short
/// sequences get a workgroup that reserves (and holds in registers) no more than they need,
/// so that more workgroups share a multiprocessor. Empty where the adapter's workgroup
/// memory holds too few values to be worth a dispatch of its own, or the hook says `0`.
fn local_caps(gpu: &Gpu, real: Real) -> Vec<usize> {
    let limits = &gpu.limits;
    let most =
        (limits.max_compute_workgroup_storage_size as usize / real.complex_bytes()).min(LOCAL_MAX);
    let fits = limits.max_compute_invocations_per_workgroup as usize >= LOCAL_WORKGROUP
        && limits.max_compute_workgroup_size_x as usize >= LOCAL_WORKGROUP;
    if most < 64 || !fits || local_hook() == Some(false) {
        return Vec::new();
    }
    let mut caps: Vec<usize> = [256, 1024].into_iter().filter(|&c| c < most).collect();
    caps.push(most);
    caps
}

impl LocalStage {
    /// Compiled to hold `cap` values; `Err` with the driver's reason where it refused the
    /// shader (caught, so that the passes serve and the device stays usable).
    fn new(gpu: &Gpu, real: Real, cap: usize) -> Result<LocalStage, String> {
        use super::Binding::{Read, Uniform, Write};
        let maxv = cap.div_ceil(LOCAL_WORKGROUP) + 4;
        let source = real.source(include_str!("../../shaders/fft_local.wgsl"));
        for line in ["const CAP: u32 = 1024u;", "const MAXV: u32 = 8u;"] {
            assert!(source.contains(line), "fft_local.wgsl declares {line}");
        }
        let wgsl = source
            .replace(
                "const CAP: u32 = 1024u;",
                &format!("const CAP: u32 = {cap}u;"),
            )
            .replace(
                "const MAXV: u32 = 8u;",
                &format!("const MAXV: u32 = {maxv}u;"),
            );
        let layout = gpu.layout("fft_local.wgsl", &[Uniform, Write, Read]);
        // Every value of the workgroup array is written before it is read: wgpu's zeroing
        // of it would be one more pass over it for each sequence.
        let mut pipelines =
            gpu.try_stage_variant("fft_local.wgsl", &wgsl, &layout, &["local_fft"], false)?;
        Ok(LocalStage {
            pipeline: pipelines.pop().expect("one entry point"),
            layout,
            cap,
        })
    }
}

/// Whether the GPU FFT plans length `n` (no prime factor above 5), without allocating: the
/// dispatcher asks it of every scale of every signal.
pub fn plannable(n: usize) -> bool {
    if n == 0 {
        return false;
    }
    let mut rest = n;
    for r in [2, 3, 5] {
        while rest.is_multiple_of(r) {
            rest /= r;
        }
    }
    rest == 1
}

/// The radices of a length, largest passes first (4 before 2: fewer passes); `None` when
/// the length has a prime factor above 5.
pub fn radices(n: usize) -> Option<Vec<u32>> {
    if n < 2 {
        return (n == 1).then(Vec::new);
    }
    let mut rest = n;
    let mut out = Vec::new();
    for r in [5, 3, 4, 2] {
        while rest.is_multiple_of(r) {
            out.push(r as u32);
            rest /= r;
        }
    }
    (rest == 1).then_some(out)
}

/// Which of the two buffers given to [`FftStage::encode`] holds the result.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Holder {
    /// The first (`data`).
    Data,
    /// The second (`scratch`).
    Scratch,
}

/// The compiled FFT passes, the workgroup-memory transform where the adapter has room for
/// it, and the expansion of long root tables (the tables themselves are the device's,
/// `Gpu::root_tables`, shared by every stage of a precision).
pub struct FftStage {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    /// The workgroup-memory transform by capacity, smallest first (empty: not compiled).
    local: Vec<LocalStage>,
    /// Whether [`algorithm`](FftStage::algorithm) picks the local transform where it fits.
    prefer_local: bool,
    /// Why the driver refused the local transform, if it did.
    refused: Option<String>,
    /// `expand_roots`: a long root table from two short ones.
    expand: wgpu::ComputePipeline,
    real: Real,
}

impl FftStage {
    /// Compiles the shader in f32 and declares its bindings: the pass's parameters
    /// (uniform), the source and destination of the pass, and the root table.
    pub fn new(gpu: &Gpu) -> FftStage {
        Self::with_real(gpu, Real::F32)
    }

    /// [`new`](Self::new) in the given precision (f64 needs [`Gpu::has_f64`]). The
    /// workgroup-memory transform is compiled where [`algorithm`](Self::algorithm) would
    /// take it (on a hardware GPU, or as [`LOCAL_ENV`] says).
    pub fn with_real(gpu: &Gpu, real: Real) -> FftStage {
        Self::build(gpu, real, false)
    }

    /// [`with_real`](Self::with_real) with the workgroup-memory transform compiled on any
    /// adapter whose workgroup memory holds it, for [`encode_with`](Self::encode_with) to
    /// be asked for it (tests, benchmarks); [`algorithm`](Self::algorithm) chooses as
    /// before.
    pub fn with_local(gpu: &Gpu, real: Real) -> FftStage {
        Self::build(gpu, real, true)
    }

    fn build(gpu: &Gpu, real: Real, always_local: bool) -> FftStage {
        use super::Binding::{Read, UniformDynamic, Write};
        let (layout, mut pipelines) = gpu.stage(
            "fft.wgsl",
            &real.source(include_str!("../../shaders/fft.wgsl")),
            &[UniformDynamic, Read, Write, Read],
            &["stockham_pass", "expand_roots"],
        );
        // A software adapter (lavapipe) runs a workgroup's invocations one after another
        // on a CPU core and pays for every barrier and register-held value: there the
        // passes were faster (20 runs at 128 scales, device time: f32 0.61 s against
        // 0.82 s, f64 3.7 s against 4.2 s). A GPU's workgroup memory is the reason to hold
        // a sequence there.
        let prefer_local = local_hook().unwrap_or(!gpu.is_software());
        let caps = if prefer_local || always_local {
            local_caps(gpu, real)
        } else {
            Vec::new()
        };
        let (local, refused) = match caps
            .into_iter()
            .map(|cap| LocalStage::new(gpu, real, cap))
            .collect::<Result<Vec<_>, _>>()
        {
            Ok(local) => (local, None),
            Err(why) => (Vec::new(), Some(why)),
        };
        let expand = pipelines.pop().expect("two entry points");
        FftStage {
            pipeline: pipelines.pop().expect("two entry points"),
            expand,
            layout,
            local,
            prefer_local,
            refused,
            real,
        }
    }

    /// What a user should know of how the stage was compiled: the driver's refusal of the
    /// workgroup-memory transform.
    pub fn notes(&self) -> Vec<String> {
        self.refused
            .iter()
            .map(|why| {
                format!(
                    "the GPU driver refused the workgroup-memory FFT ({:?}), so every length \
                     takes the passes through global memory; results are the same: {why}",
                    self.real
                )
            })
            .collect()
    }

    /// The longest length [`Algorithm::Local`] takes on this adapter (0: none).
    pub fn local_cap(&self) -> usize {
        self.local.last().map_or(0, |l| l.cap)
    }

    /// The algorithm [`encode`](Self::encode) uses for length `n`: on a hardware GPU the
    /// workgroup-memory transform where the sequence fits, else the passes through global
    /// memory (see [`LOCAL_ENV`]).
    pub fn algorithm(&self, n: usize) -> Algorithm {
        if self.prefer_local && n <= self.local_cap() {
            Algorithm::Local
        } else {
            Algorithm::Passes
        }
    }

    /// The precision it computes in.
    pub fn real(&self) -> Real {
        self.real
    }

    /// e^{-j2πm/n}, m < n, computed in f64 (or expanded from such roots) and stored in the
    /// stage's precision, one table per length and precision, kept on the device
    /// ([`Gpu::root_tables`]). Up to [`ROOTS_ON_HOST_MAX`] roots the host computes every
    /// one; a longer table is expanded on the device from about 2·√n of them
    /// (`expand_roots`), which a one-shot `skelid track` of a long record needs: its tables
    /// (its padded spectrum's 1.6 M points, its scales', the refinement's) were 5.4 M
    /// roots, 87 MB computed, staged and uploaded on the dispatcher's one thread, 113 ms
    /// here before the device could start.
    fn roots(&self, gpu: &Gpu, n: usize) -> Result<wgpu::Buffer, GpuError> {
        let mut cache = gpu.root_tables().lock().unwrap_or_else(|p| p.into_inner());
        if let Some(b) = cache.get(&(n, self.real)) {
            return Ok(b.clone());
        }
        // The expansion's fine roots (r < fine) then its coarse ones (q·fine, q < n/fine),
        // or the whole table; each computed as the whole table's entry of that index.
        let fine = if n > ROOTS_ON_HOST_MAX {
            n.isqrt().next_power_of_two()
        } else {
            n
        };
        let index = |i: usize| if i < fine { i } else { (i - fine) * fine };
        let count = fine + n.div_ceil(fine) * usize::from(fine < n);
        let lens: Vec<usize> = (0..count)
            .step_by(ROOTS_PIECE)
            .map(|at| ROOTS_PIECE.min(count - at))
            .collect();
        let root = |i: usize| {
            let a = -2.0 * std::f64::consts::PI * index(i) as f64 / n as f64;
            (a.cos(), a.sin())
        };
        let label = "fft roots";
        let staged = match self.real {
            Real::F32 => gpu.upload_kept(label, &lens, |p, out: &mut [[f32; 2]]| {
                for (k, o) in out.iter_mut().enumerate() {
                    let (c, s) = root(p * ROOTS_PIECE + k);
                    *o = [c as f32, s as f32];
                }
            }),
            Real::F64 => gpu.upload_kept(label, &lens, |p, out: &mut [[f64; 2]]| {
                for (k, o) in out.iter_mut().enumerate() {
                    let (c, s) = root(p * ROOTS_PIECE + k);
                    *o = [c, s];
                }
            }),
        }?;
        let table = if fine < n {
            let table = gpu.storage(label, (n * self.real.complex_bytes()) as u64);
            self.expand_on_device(gpu, n, fine, &staged, &table)?;
            table
        } else {
            staged
        };
        cache.insert((n, self.real), table.clone());
        Ok(table)
    }

    /// Records `expand_roots` (`parts`: the fine roots, then the coarse, into `table`) as
    /// a prelude of the next submission, so that whichever recording uses the table first,
    /// the table is there.
    fn expand_on_device(
        &self,
        gpu: &Gpu,
        n: usize,
        fine: usize,
        parts: &wgpu::Buffer,
        table: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let params = PassParams {
            n: n as u32,
            radix: 0,
            ns: fine as u32,
            batch: 1,
            inverse: 0,
            _pad: [0; 3],
        };
        let uniform = gpu.upload_uniform("fft roots", bytemuck::bytes_of(&params));
        let record = wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &uniform,
            offset: 0,
            size: wgpu::BufferSize::new(std::mem::size_of::<PassParams>() as u64),
        });
        // Binding 3 is unread by `expand_roots`: any buffer the pass does not write.
        let bind = gpu.bind_resources(
            "fft roots",
            &self.layout,
            vec![
                record,
                parts.as_entire_binding(),
                table.as_entire_binding(),
                parts.as_entire_binding(),
            ],
        );
        let [x, y, z] = gpu.grid((n as u64).div_ceil(u64::from(WORKGROUP)))?;
        let mut enc = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("fft roots"),
            });
        {
            // Untimed: the timer's queries are resolved in the recording it serves.
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("fft.expand_roots"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.expand);
            pass.set_bind_group(0, &bind, &[0]);
            pass.dispatch_workgroups(x, y, z);
        }
        gpu.prelude(enc.finish());
        Ok(())
    }

    /// Records the transforms of `batch` sequences of length `n`, held back to back in
    /// `data` from element `offset` on (a multiple of [`offset_alignment_of`] the stage's
    /// precision), by the length's [`algorithm`](Self::algorithm), using the same range of
    /// `scratch` for a ping-pong; returns which buffer holds the result.
    #[allow(clippy::too_many_arguments)]
    pub fn encode(
        &self,
        gpu: &Gpu,
        encoder: &mut wgpu::CommandEncoder,
        n: usize,
        batch: usize,
        inverse: bool,
        data: &wgpu::Buffer,
        scratch: &wgpu::Buffer,
        offset: usize,
    ) -> Result<Holder, GpuError> {
        let algorithm = self.algorithm(n);
        self.encode_with(
            algorithm, gpu, encoder, n, batch, inverse, data, scratch, offset,
        )
    }

    /// [`encode`](Self::encode) by the given algorithm; `Unsupported` when it cannot take
    /// the length on this adapter.
    #[allow(clippy::too_many_arguments)]
    pub fn encode_with(
        &self,
        algorithm: Algorithm,
        gpu: &Gpu,
        encoder: &mut wgpu::CommandEncoder,
        n: usize,
        batch: usize,
        inverse: bool,
        data: &wgpu::Buffer,
        scratch: &wgpu::Buffer,
        offset: usize,
    ) -> Result<Holder, GpuError> {
        let plan = radices(n).ok_or_else(|| {
            GpuError::Unsupported(format!(
                "FFT length {n} has a prime factor above 5; the GPU FFT takes 2^a·3^b·5^c"
            ))
        })?;
        let elem = self.real.complex_bytes();
        let bytes = (n * batch * elem) as u64;
        if bytes > gpu.max_binding() {
            return Err(GpuError::TooLarge {
                what: format!("{batch} FFT(s) of length {n}"),
                need: bytes,
                limit: gpu.max_binding(),
            });
        }
        let roots = self.roots(gpu, n)?;
        if algorithm == Algorithm::Local {
            return self.encode_local(gpu, encoder, n, &plan, batch, inverse, data, offset, &roots);
        }
        // Every pass's parameters in one uniform buffer, one record per pass at the
        // adapter's offset alignment, and two bind groups (data → scratch and back): a
        // buffer and a bind group per pass made the host's cost per batch grow with the
        // number of passes (hundreds per batch), which on a fast GPU set the pace.
        let size = std::mem::size_of::<PassParams>();
        let stride = (gpu.limits.min_uniform_buffer_offset_alignment as usize).max(size);
        let mut records = vec![0u8; stride * plan.len().max(1)];
        let mut ns = 1usize;
        for (i, &r) in plan.iter().enumerate() {
            let params = PassParams {
                n: n as u32,
                radix: r,
                ns: ns as u32,
                batch: batch as u32,
                inverse: u32::from(inverse),
                _pad: [0; 3],
            };
            records[i * stride..i * stride + size].copy_from_slice(bytemuck::bytes_of(&params));
            ns *= r as usize;
        }
        let uniform = gpu.upload_uniform("fft passes", &records);
        // This batch's range of either buffer.
        let range = |buffer| {
            wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                buffer,
                offset: (offset * elem) as u64,
                size: wgpu::BufferSize::new(bytes),
            })
        };
        let bind = |from, to| {
            let record = wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                buffer: &uniform,
                offset: 0,
                size: wgpu::BufferSize::new(size as u64),
            });
            gpu.bind_resources(
                "fft pass",
                &self.layout,
                vec![record, range(from), range(to), roots.as_entire_binding()],
            )
        };
        let forth = bind(data, scratch);
        let back = (plan.len() > 1).then(|| bind(scratch, data));
        let (mut from, mut to) = (data, scratch);
        // One compute pass: WebGPU orders its dispatches, each seeing the last one's writes.
        let mut pass = gpu.pass(
            encoder,
            match self.real {
                Real::F32 => "fft f32",
                Real::F64 => "fft f64",
            },
        );
        pass.set_pipeline(&self.pipeline);
        for (i, &r) in plan.iter().enumerate() {
            let group = if i % 2 == 0 {
                &forth
            } else {
                back.as_ref()
                    .expect("a second bind group for two passes or more")
            };
            pass.set_bind_group(0, group, &[(i * stride) as u32]);
            let invocations = (n / r as usize * batch) as u64;
            let [x, y, z] = gpu.grid(invocations.div_ceil(u64::from(WORKGROUP)))?;
            pass.dispatch_workgroups(x, y, z);
            std::mem::swap(&mut from, &mut to);
        }
        drop(pass);
        Ok(if std::ptr::eq(from, data) {
            Holder::Data
        } else {
            Holder::Scratch
        })
    }

    /// [`Algorithm::Local`]: one dispatch, a workgroup per sequence, in place.
    #[allow(clippy::too_many_arguments)]
    fn encode_local(
        &self,
        gpu: &Gpu,
        encoder: &mut wgpu::CommandEncoder,
        n: usize,
        plan: &[u32],
        batch: usize,
        inverse: bool,
        data: &wgpu::Buffer,
        offset: usize,
        roots: &wgpu::Buffer,
    ) -> Result<Holder, GpuError> {
        let local = match self.local.iter().find(|l| n <= l.cap) {
            Some(l) if plan.len() <= LOCAL_PASSES => l,
            _ => {
                return Err(GpuError::Unsupported(format!(
                    "FFT length {n} does not fit one workgroup's memory on this adapter \
                     (at most {} values)",
                    self.local_cap()
                )))
            }
        };
        let mut radix = [0u32; LOCAL_PASSES];
        radix[..plan.len()].copy_from_slice(plan);
        let params = LocalParams {
            n: n as u32,
            batch: batch as u32,
            inverse: u32::from(inverse),
            passes: plan.len() as u32,
            radix,
        };
        let uniform = gpu.uniform("fft local", &params);
        let elem = self.real.complex_bytes();
        let sequences = wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: data,
            offset: (offset * elem) as u64,
            size: wgpu::BufferSize::new((n * batch * elem) as u64),
        });
        let group = gpu.bind_resources(
            "fft local",
            &local.layout,
            vec![
                uniform.as_entire_binding(),
                sequences,
                roots.as_entire_binding(),
            ],
        );
        let [x, y, z] = gpu.grid(batch as u64)?;
        let mut pass = gpu.pass(
            encoder,
            match self.real {
                Real::F32 => "fft f32 local",
                Real::F64 => "fft f64 local",
            },
        );
        pass.set_pipeline(&local.pipeline);
        pass.set_bind_group(0, &group, &[]);
        pass.dispatch_workgroups(x, y, z);
        Ok(Holder::Data)
    }

    /// Transforms host data in place: `data` holds `data.len() / n` sequences of length
    /// `n` back to back, in the stage's precision (`Complex32` for [`Real::F32`],
    /// `Complex64` for [`Real::F64`]). Uploads, runs and reads back; for tests and
    /// benchmarks.
    pub fn transform<T: bytemuck::Pod>(
        &self,
        gpu: &Gpu,
        data: &mut [Complex<T>],
        n: usize,
        inverse: bool,
    ) -> Result<(), GpuError> {
        self.transform_with(self.algorithm(n), gpu, data, n, inverse)
    }

    /// [`transform`](Self::transform) by the given algorithm.
    pub fn transform_with<T: bytemuck::Pod>(
        &self,
        algorithm: Algorithm,
        gpu: &Gpu,
        data: &mut [Complex<T>],
        n: usize,
        inverse: bool,
    ) -> Result<(), GpuError> {
        if 2 * std::mem::size_of::<T>() != self.real.complex_bytes() {
            return Err(GpuError::Unsupported(format!(
                "values of {} bytes given to a stage made with {:?}",
                2 * std::mem::size_of::<T>(),
                self.real
            )));
        }
        let flat: Vec<[T; 2]> = data.iter().map(|c| [c.re, c.im]).collect();
        let out = self.round_trip(algorithm, gpu, flat, n, inverse)?;
        for (d, o) in data.iter_mut().zip(out) {
            *d = Complex::new(o[0], o[1]);
        }
        Ok(())
    }

    /// Uploads `flat` (complex values as pairs in the stage's precision), transforms it in
    /// sequences of length `n` and reads it back.
    fn round_trip<T: bytemuck::Pod>(
        &self,
        algorithm: Algorithm,
        gpu: &Gpu,
        flat: Vec<[T; 2]>,
        n: usize,
        inverse: bool,
    ) -> Result<Vec<[T; 2]>, GpuError> {
        if n == 0 || !flat.len().is_multiple_of(n) {
            return Err(GpuError::Unsupported(format!(
                "{} values are not a whole number of length-{n} transforms",
                flat.len()
            )));
        }
        let a = gpu.upload("fft data", &flat);
        let b = gpu.storage("fft scratch", std::mem::size_of_val(flat.as_slice()) as u64);
        let mut enc = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("fft") });
        let holder = self.encode_with(
            algorithm,
            gpu,
            &mut enc,
            n,
            flat.len() / n,
            inverse,
            &a,
            &b,
            0,
        )?;
        gpu.submit(enc);
        gpu.download(
            match holder {
                Holder::Data => &a,
                Holder::Scratch => &b,
            },
            flat.len(),
        )
    }
}

/// Complex elements of precision `real` that a bound sub-range must start on.
pub fn offset_alignment_of(gpu: &Gpu, real: Real) -> usize {
    (gpu.limits.min_storage_buffer_offset_alignment as usize)
        .div_ceil(real.complex_bytes())
        .max(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radices_cover_the_plan_lengths() {
        assert_eq!(radices(1), Some(vec![]));
        assert_eq!(radices(8), Some(vec![4, 2]));
        assert_eq!(radices(1152), Some(vec![3, 3, 4, 4, 4, 2]));
        assert_eq!(radices(7), None);
        for n in 1..5000 {
            assert_eq!(plannable(n), radices(n).is_some(), "{n}");
        }
        for n in 16..5000 {
            let m = crate::transform::plan_len(n);
            let r = radices(m).unwrap();
            assert_eq!(r.iter().map(|&x| x as usize).product::<usize>(), m);
        }
    }
}
