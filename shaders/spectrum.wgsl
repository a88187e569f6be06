// The padded spectrum of each run of a batch on the device (host: src/gpu/spectrum.rs; the
// CPU reference is transform::Spectrum::with_mean and Spectrum::white_noise_variance).
//
// `pack`: a run's samples, less their mean (taken off on the host, in f64, as the CPU
// takes it), zero-padded to the padded length L as complex values with no imaginary part:
// the input of its forward FFT (fft.wgsl), whose bins 0..=L/2 are the one-sided spectrum.
//
// `compact`: the bins a run's pass bands read (`first`, `count`), bin 0 (the mean) zeroed,
// into `resident`, where the first pass and the refinement read them; or, for a run whose
// spectrum the host computed (`HOST`), its bins as uploaded.
//
// `noise_median`: the median |X|² over the bins above the band (`noise_lo..=noise_hi`):
// the white-noise floor the completion compares the track with. Selected a byte at a time
// (as ridge.wgsl's column_stats) on a key of two f32 words: the value's f32 rounding, then
// the f32 rounding of what that leaves, so that the order of the keys is the order of the
// f64 values to 48 bits. Values are scaled by powers of two first (exactly) so that the
// largest of the band is near 1 and f32 holds them.
//
// `real` is f64: the host compiles this stage only where the adapter has SHADER_F64.

alias real = f32;

struct Run {
    flags: u32,     // HOST: the bins come from `host`, not from an FFT of `samples`
    samples: u32,   // offset of its samples in `samples`
    n: u32,         // samples
    l: u32,         // padded length L
    work: u32,      // offset of its L values in `work` (its chunk's)
    first: u32,     // first bin kept
    count: u32,     // bins kept
    resident: u32,  // offset of its kept bins in `resident`
    host: u32,      // offset of its uploaded bins in `host` (HOST only)
    noise_lo: u32,  // the white-noise median's bins (noise_hi < noise_lo: none)
    noise_hi: u32,
    scale: i32,     // 2^scale brings every |X|² to at most 1 (the host's bound)
    slot: u32,      // its entry in `medians`
};

const HOST: u32 = 1u;

@group(0) @binding(0) var<storage, read> runs: array<Run>;
@group(0) @binding(1) var<storage, read> samples: array<real>;
@group(0) @binding(2) var<storage, read_write> work: array<vec2<real>>;
@group(0) @binding(3) var<storage, read_write> resident: array<vec2<real>>;
@group(0) @binding(4) var<storage, read> host: array<vec2<real>>;
// Per run: the median's key (two f32 words) and the power of two it was scaled by; the
// fourth word is 1 where there is one.
@group(0) @binding(5) var<storage, read_write> medians: array<vec4<u32>>;

// One workgroup row per run (y, then z), values along x (strided).
fn run_index(wg: vec3<u32>, groups: vec3<u32>) -> u32 {
    return wg.z * groups.y + wg.y;
}

@compute @workgroup_size(64)
fn pack(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let r = run_index(wg, groups);
    if (r >= arrayLength(&runs)) {
        return;
    }
    let run = runs[r];
    if ((run.flags & HOST) != 0u) {
        return;
    }
    for (var j = wg.x * 64u + local; j < run.l; j += groups.x * 64u) {
        var v = real(0.0);
        if (j < run.n) {
            v = samples[run.samples + j];
        }
        work[run.work + j] = vec2<real>(v, real(0.0));
    }
}

@compute @workgroup_size(64)
fn compact(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let r = run_index(wg, groups);
    if (r >= arrayLength(&runs)) {
        return;
    }
    let run = runs[r];
    let from_host = (run.flags & HOST) != 0u;
    for (var b = wg.x * 64u + local; b < run.count; b += groups.x * 64u) {
        var v = vec2<real>(real(0.0), real(0.0));
        if (from_host) {
            v = host[run.host + b];
        } else if (run.first + b != 0u) {
            v = work[run.work + run.first + b];
        }
        resident[run.resident + b] = v;
    }
}

const WG: u32 = 256u;
var<workgroup> largest: array<real, WG>;
// The selection's histogram, running sums and chosen byte are select.wgsl's.

// |X|² of bin b of a run, scaled by 2^shift (exact: a power of two).
fn power_at(run: Run, b: u32, shift: i32) -> real {
    let x = work[run.work + b];
    return ldexp(x.x * x.x + x.y * x.y, shift);
}

// The two-word key of a scaled power v ≥ 0: f32(v)'s bits (which order as the values do),
// then the bits of f32(v − f32(v)) made to order as unsigned words.
fn key_of(v: real) -> vec2<u32> {
    let hi = f32(v);
    let lo = bitcast<u32>(f32(v - real(hi)));
    var lo_key = lo | 0x80000000u;
    if ((lo & 0x80000000u) != 0u) {
        lo_key = ~lo;
    }
    return vec2<u32>(bitcast<u32>(hi), lo_key);
}

// One workgroup per run (y, then z; one along x).
@compute @workgroup_size(256)
fn noise_median(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let r = run_index(wg, groups);
    // Uniform across the workgroup, so the barriers below stay in uniform control flow.
    if (r >= arrayLength(&runs)) {
        return;
    }
    let run = runs[r];
    if ((run.flags & HOST) != 0u || run.noise_hi < run.noise_lo) {
        if (lid == 0u) {
            medians[run.slot] = vec4<u32>(0u, 0u, 0u, 0u);
        }
        return;
    }
    // The largest power over the bins, after the host's bound (every |X|² ≤ 1 then).
    var top = real(0.0);
    for (var b = run.noise_lo + lid; b <= run.noise_hi; b += WG) {
        top = max(top, power_at(run, b, run.scale));
    }
    largest[lid] = top;
    workgroupBarrier();
    for (var w = WG / 2u; w > 0u; w = w >> 1u) {
        if (lid < w) {
            largest[lid] = max(largest[lid], largest[lid + w]);
        }
        workgroupBarrier();
    }
    // Doublings that bring the largest to [2^-32, 1]: the band's values then sit in f32's
    // range unless they span more than 2^90 below their largest.
    var shift = run.scale;
    var m = largest[0];
    if (m > real(0.0)) {
        // (At most to 2^1000: ldexp beyond f64's exponents is undefined.)
        for (var i = 0u; i < 40u && m < real(2.3283064365386963e-10) && shift < 968; i = i + 1u) {
            m = m * real(4294967296.0);
            shift = shift + 32;
        }
    }
    // The rank-th smallest key, a byte at a time: among the values whose key agrees with
    // `prefix` on the bytes above, the byte whose running count first passes the rank
    // left, which then counts from that byte's first value. Eight bytes: the first word's
    // four, then the second's.
    var rank = (run.noise_hi + 1u - run.noise_lo) / 2u;
    var prefix = vec2<u32>(0u, 0u);
    for (var pass_ = 0u; pass_ < 8u; pass_ = pass_ + 1u) {
        let word = pass_ / 4u;
        let shift_bits = 24u - 8u * (pass_ % 4u);
        // The bits of this word above the byte (none for its first byte).
        let above = select(0xffffffffu << (shift_bits + 8u), 0u, shift_bits == 24u);
        select_clear(lid);
        for (var b = run.noise_lo + lid; b <= run.noise_hi; b += WG) {
            let k = key_of(power_at(run, b, shift));
            var same = (k.x & select(above, 0xffffffffu, word == 1u)) == prefix.x;
            if (word == 1u) {
                same = same && (k.y & above) == prefix.y;
            }
            if (same) {
                let v = select(k.x, k.y, word == 1u);
                select_count(v >> shift_bits);
            }
        }
        let pick = select_byte(lid, rank);
        if (word == 0u) {
            prefix.x = prefix.x | (pick.x << shift_bits);
        } else {
            prefix.y = prefix.y | (pick.x << shift_bits);
        }
        rank = pick.y;
    }
    if (lid == 0u) {
        medians[run.slot] = vec4<u32>(prefix.x, prefix.y, bitcast<u32>(shift), 1u);
    }
}
