// Ridge search for a batch of runs (host: src/gpu/ridge.rs), on the coarse |W|² grid that
// scales.wgsl leaves on the GPU (per run, scale-major: power[run.power + k·steps + j]).
//
// `stats`: one workgroup per run × scale: the column's lowest score (given to the steps
// outside the scale's cone of influence, as src/track.rs does) and the median power inside
// the cone (the noise floor), by a radix selection on the bits of non-negative f32 values,
// which sort as their u32 patterns: a byte a pass, most significant first, each pass
// counting the values that share the bytes chosen so far into 256 bins (four passes over
// the column, where one a bit took 32).
//
// `ridge_steps`: one workgroup per run: the penalised dynamic programme of src/ridge.rs,
// maximising Σ score(k_j, j) − λ Σ (k_j − k_{j−1})², the O(S²) maximum per step spread over
// the workgroup (several invocations a scale where S is at most half the workgroup: 256
// invocations, or 1024 in the host's wide programme), accumulated scores in
// workgroup memory (shifted by the step's largest every step, so that f32 keeps its
// precision over thousands of steps, and the most where paths compete for the ridge; two
// halves that swap, one barrier a step), back-pointers in global memory. `backtrack` then follows the back-pointers. Only the path and the
// statistics go back to the host.
//
// Both work on one chunk of steps per dispatch (the `chunk` uniform), carrying the scores
// (`accum`) or the path from one chunk to the next: Mesa's lavapipe ends any loop nest
// after 65 535 iterations in all (gallivm's loop limiter), and a real GPU's watchdog
// dislikes long dispatches. The host sizes chunks to stay under that limit.
//
// Lanes: one long record is a programme of thousands of steps, one after another, in one
// workgroup, while the rest of the GPU idles. The host may cut a run's steps into lanes that
// run side by side (Maleki, Musuvathi and Mytkowicz, PPoPP 2014: rank convergence). A lane
// after the first starts `warm` steps early from its own first scores, writing no
// back-pointers, and keeps its scores (less the shift) at the step before its own. Those
// started elsewhere forget their start within a few dozen steps: the scores become the
// same, bit for bit, as the lane before ends with; from that step on, each step computes
// exactly what one workgroup going through every step computes. A repair pass then takes
// lane 1, 2, … in order: a lane whose kept scores are not bit for bit the lane before's
// final ones runs its own steps again, seeded with those, so the back-pointers and the
// path are always the sequential programme's.
//
// The backtrack of a run cut into lanes goes the same way (`backtrack_lanes`): each lane
// but the last starts `warm` steps past its end, at the step's best score, and follows the
// back-pointers down through its own steps; paths that start apart meet within a few
// steps, and from there on are one. It keeps the scale it passed at the next lane's first
// step (`probe`); the repair, from the last lane down, redoes a lane whose probe is not
// where the next lane's path begins.

struct Run {
    power: u32,        // offset of the run's power grid
    steps: u32,        // coarse steps
    scales: u32,       // scales S (≤ MAX_SCALES)
    back: u32,         // offset of its steps × S back-pointers
    path: u32,         // offset of its path (one scale index per step)
    guide: u32,        // offset of its guide (one (ln f, usable) per step)
    info: u32,         // offset of its per-scale ScaleInfo and statistics
    flags: u32,        // bit 0: guided; 1: penalised path (else per-step argmax); 2: a
                       // repair lane; 3: a run cut into lanes (traced by backtrack_lanes)
    unit: f32,         // 1 / mean power of the record
    penalty: f32,      // λ per squared scale step
    guide_weight: f32, // weight of the guide's pull
    resolution: f32,   // wavelet's relative frequency resolution
    // ridge_steps' lane of the run (see "Lanes" above): the steps origin..end, its
    // back-pointers from step `own` on, its carried scores at `slot` (and, for a lane that
    // warms up, the scores of its step own − 1 at slot + scales).
    origin: u32,
    own: u32,
    end: u32,
    slot: u32,
    seed: u32,         // a repair lane: the slot of the lane before, whose scores it starts from
    lane: u32,         // the lane's number within its run
    probe: u32,        // backtrack_lanes: where in `path` the lane keeps its probe
    reach: u32,        // backtrack_lanes: steps past its end a lane's own start lies
};

struct ScaleInfo {
    first: u32,        // first coarse step inside the cone of influence
    last: u32,         // last one (first > last: none)
    mid: u32,          // rank of the median among the inner steps (NO_MEDIAN: none)
    ln_f: f32,         // ln of the scale's frequency (Hz)
};

struct Chunk {
    first: u32,        // first step of this dispatch (ridge_steps: counted from each lane's origin)
    last: u32,         // one past its last step
    scales: u32,       // the most scales of any run (column_stats' items per run)
    lane: u32,         // ridge_steps' repair: the lanes of this number alone
};

@group(0) @binding(0) var<storage, read> runs: array<Run>;
@group(0) @binding(1) var<storage, read> info: array<ScaleInfo>;
@group(0) @binding(2) var<storage, read> power: array<f32>;
@group(0) @binding(3) var<storage, read> guide: array<vec2<f32>>;
@group(0) @binding(4) var<storage, read_write> stats: array<vec2<f32>>;
@group(0) @binding(5) var<storage, read_write> back: array<u32>;
@group(0) @binding(6) var<storage, read_write> path: array<u32>;
@group(0) @binding(7) var<uniform> chunk: Chunk;
@group(0) @binding(8) var<storage, read_write> accum: array<f32>;

const WG: u32 = 256u;
// ridge_steps' invocations. The host compiles this file a second time with 1024 here (the
// `wide` programme, src/gpu/ridge.rs): a step waits for its longest scan of predecessors,
// so four invocations a scale at 256 scales (t below) shorten each step for a batch of few
// runs, where one workgroup a run leaves most of a GPU idle.
const STEPS_WG: u32 = 256u;
const MAX_SCALES: u32 = 1024u;
const MIN_POSITIVE: f32 = 1.17549435e-38;
const BIG: f32 = 3.40282e38;
const NO_MEDIAN: u32 = 0xffffffffu;
// Chunk::lane of a dispatch that repairs nothing.
const NO_LANE: u32 = 0xffffffffu;
// Run::flags of lanes (src/gpu/ridge.rs): a repair lane; a run cut into lanes.
const REPAIR: u32 = 4u;
const SPLIT: u32 = 8u;

var<workgroup> lowest: array<f32, WG>;
// column_stats' selection (its histogram, running sums and chosen byte) is select.wgsl's.
var<workgroup> which: array<u32, WG>;
// ridge_steps' running scores, two halves: the step's own (read, less `shift`) and the
// next step's (written); they swap every step, so one barrier a step suffices.
var<workgroup> acc: array<f32, 2048>;
// ridge_steps' partial maxima, one per invocation, where several share a scale's scan.
var<workgroup> part_best: array<f32, STEPS_WG>;
var<workgroup> part_arg: array<u32, STEPS_WG>;
var<workgroup> top: array<atomic<u32>, 3>;
// ridge_steps' repair: the scales at which a lane's kept scores differ from its seed.
var<workgroup> differ: atomic<u32>;

// track.rs' score: half the log of the power relative to the record's, floored 380 dB down.
fn log_score(p: f32, unit: f32) -> f32 {
    return 0.5 * log(max(p * unit, MIN_POSITIVE));
}

@compute @workgroup_size(256)
fn column_stats(@builtin(workgroup_id) wid: vec3<u32>,
                @builtin(num_workgroups) groups: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    // One workgroup per run × scale, flattened over the dispatch's dimensions.
    let item = (wid.z * groups.y + wid.y) * groups.x + wid.x;
    let r = item / chunk.scales;
    if (r >= arrayLength(&runs)) {
        return;
    }
    let run = runs[r];
    let k = item % chunk.scales;
    if (k >= run.scales) {
        return;
    }
    let si = info[run.info + k];
    let base = run.power + k * run.steps;
    var lo = BIG;
    for (var j = lid; j < run.steps; j += WG) {
        lo = min(lo, power[base + j]);
    }
    lowest[lid] = lo;
    workgroupBarrier();
    for (var w = WG / 2u; w > 0u; w = w >> 1u) {
        if (lid < w) {
            lowest[lid] = min(lowest[lid], lowest[lid + w]);
        }
        workgroupBarrier();
    }
    let floor_score = log_score(lowest[0], run.unit);
    // The mid-th smallest bit pattern, a byte at a time: among the values whose higher
    // bytes are those chosen (`prefix`), the byte whose running count first passes the rank
    // left (`rank`), which then counts from that byte's first value.
    var prefix = 0u;
    if (si.mid != NO_MEDIAN) {
        var rank = si.mid;
        for (var shift = 24u; shift < 32u; shift = shift - 8u) {
            // The bytes above this one (none for the first).
            let above = select(0xffffffffu << (shift + 8u), 0u, shift == 24u);
            select_clear(lid);
            for (var j = si.first + lid; j <= si.last; j += WG) {
                let v = bitcast<u32>(power[base + j]);
                if ((v & above) == prefix) {
                    select_count(v >> shift);
                }
            }
            let pick = select_byte(lid, rank);
            prefix = prefix | (pick.x << shift);
            rank = pick.y;
        }
    }
    if (lid == 0u) {
        stats[run.info + k] = vec2<f32>(floor_score, bitcast<f32>(prefix));
    }
}

fn score(run: Run, k: u32, j: u32) -> f32 {
    let si = info[run.info + k];
    var v: f32;
    if (j < si.first || j > si.last) {
        v = stats[run.info + k].x;
    } else {
        v = log_score(power[run.power + k * run.steps + j], run.unit);
    }
    if ((run.flags & 1u) != 0u) {
        let g = guide[run.guide + j];
        if (g.y > 0.5) {
            let d = (si.ln_f - g.x) / run.resolution;
            v = v - run.guide_weight * d * d;
        }
    }
    return v;
}

@compute @workgroup_size(STEPS_WG)
fn ridge_steps(@builtin(workgroup_id) wid: vec3<u32>,
               @builtin(num_workgroups) groups: vec3<u32>,
               @builtin(local_invocation_index) lid: u32) {
    let r = (wid.z * groups.y + wid.y) * groups.x + wid.x;
    if (r >= arrayLength(&runs)) {
        return;
    }
    let run = runs[r];
    let s = run.scales;
    // This dispatch's steps of the lane, counted from its origin.
    let begin = run.origin + chunk.first;
    let end = min(run.origin + chunk.last, run.end);
    if (begin >= end) {
        return;
    }
    if ((run.flags & REPAIR) != 0u) {
        // A repair lane: its number's turn only, and only where its warm-up did not end on
        // the seed's scores (both are final before this lane's turn).
        if (run.lane != chunk.lane) {
            return;
        }
        if (lid == 0u) {
            atomicStore(&differ, 0u);
        }
        workgroupBarrier();
        var d = 0u;
        for (var k = lid; k < s; k += STEPS_WG) {
            if (bitcast<u32>(accum[run.slot + s + k]) != bitcast<u32>(accum[run.seed + k])) {
                d += 1u;
            }
        }
        atomicAdd(&differ, d);
        if (workgroupUniformLoad(&differ) == 0u) {
            return;
        }
    }
    if ((run.flags & 2u) == 0u) {
        // Per-step argmax (the first maximum): one step per invocation, no programme.
        for (var j = begin + lid; j < end; j += STEPS_WG) {
            var best = -BIG;
            var arg = 0u;
            for (var k = 0u; k < s; k += 1u) {
                let v = score(run, k, j);
                if (v > best) {
                    best = v;
                    arg = k;
                }
            }
            path[run.path + j] = arg;
        }
        return;
    }
    // The largest score of each half, as an order-preserving u32 (`orderable`): three slots
    // that rotate, the step's own (read), the next step's (written with atomicMax) and the
    // one after (reset), so that no slot is reset while it is read or written.
    if (lid == 0u) {
        for (var i = 0u; i < 3u; i += 1u) {
            atomicStore(&top[i], 0u);
        }
    }
    workgroupBarrier();
    var start = begin;
    if (start == run.origin) {
        // The lane's first step: its own scores, or a repair lane's seed (scores less their
        // shift, as carried between chunks).
        let seeded = (run.flags & REPAIR) != 0u;
        for (var k = lid; k < s; k += STEPS_WG) {
            if (seeded) {
                acc[k] = accum[run.seed + k];
            } else {
                acc[k] = score(run, k, start);
            }
            atomicMax(&top[0], orderable(acc[k]));
        }
        start += 1u;
    } else {
        for (var k = lid; k < s; k += STEPS_WG) {
            acc[k] = accum[run.slot + k];
            atomicMax(&top[0], orderable(acc[k]));
        }
    }
    // Up to 128 scales, `t` invocations share each scale's scan of its predecessors, each
    // over its own contiguous range, and the first of them combines their maxima in order:
    // the first maximum over q, as one scan finds it, in a fraction of the time. A batch of a
    // few signals waits on this loop's latency (one workgroup a signal).
    var t = 1u;
    if (s <= STEPS_WG / 2u) {
        t = STEPS_WG / s;
    }
    // The step's scores are acc[src + q] − shift: the shift by the previous step's largest
    // keeps f32's precision over thousands of steps (the same rounding as shifting them in
    // place), and the scores that compete for the ridge near 0, where f32 is finest. Shifted
    // by the value at scale 0 instead (far below the ridge, tens of units away), they were
    // rounded to about 2e-6 a step, and two modes of the beam's hammer test whose paths
    // differ by 9.7e-6 in a total of 3 342 took the lower path.
    var src = 0u;
    var shift = 0.0;
    var slot = 0u;
    workgroupBarrier();
    for (var j = start; j < end; j += 1u) {
        let dst = MAX_SCALES - src;
        let next = (slot + 1u) % 3u;
        if (lid == 0u) {
            atomicStore(&top[(slot + 2u) % 3u], 0u);
        }
        // The step's largest score: no predecessor further from k than its `window` can beat
        // q = k itself (see `window`), so each scale scans only those within it.
        let most = from_orderable(atomicLoad(&top[slot])) - shift;
        if (t > 1u) {
            let k = lid / t;
            let part = lid % t;
            var best = -BIG;
            var arg = 0u;
            var own = 0.0;
            if (k < s) {
                if (part == 0u) {
                    // Loaded before the scan, so that its latency hides behind it.
                    own = score(run, k, j);
                }
                let w = window(k, s, most - (acc[src + k] - shift), run.penalty);
                let per = (w.y - w.x + t - 1u) / t;
                let found = scan(k, w.x + part * per, min(w.y, w.x + (part + 1u) * per), src,
                                 shift, run.penalty);
                best = found.value;
                arg = found.arg;
            }
            part_best[lid] = best;
            part_arg[lid] = arg;
            workgroupBarrier();
            if (k < s && part == 0u) {
                for (var i = 1u; i < t; i += 1u) {
                    if (part_best[lid + i] > best) {
                        best = part_best[lid + i];
                        arg = part_arg[lid + i];
                    }
                }
                settle(run, k, j, dst, next, own + best, arg);
            }
        } else {
            for (var k = lid; k < s; k += STEPS_WG) {
                let own = score(run, k, j);
                let w = window(k, s, most - (acc[src + k] - shift), run.penalty);
                let found = scan(k, w.x, w.y, src, shift, run.penalty);
                settle(run, k, j, dst, next, own + found.value, found.arg);
            }
        }
        workgroupBarrier();
        shift = from_orderable(atomicLoad(&top[next]));
        src = dst;
        slot = next;
        if (j + 1u == run.own) {
            // The end of a lane's warm-up: its scores, to compare with the lane before's.
            for (var k = lid; k < s; k += STEPS_WG) {
                accum[run.slot + s + k] = acc[src + k] - shift;
            }
        }
    }
    for (var k = lid; k < s; k += STEPS_WG) {
        accum[run.slot + k] = acc[src + k] - shift;
    }
}

// The best predecessor of scale k among q0..q1: the first maximum of the step's scores
// (acc[src + q] − shift) less the penalty λ(k − q)²; −BIG and 0 when the range is empty.
struct Found {
    value: f32,
    arg: u32,
};

fn scan(k: u32, q0: u32, q1: u32, src: u32, shift: f32, penalty: f32) -> Found {
    var found = Found(-BIG, 0u);
    for (var q = q0; q < q1; q += 1u) {
        let d = f32(k) - f32(q);
        let v = (acc[src + q] - shift) - penalty * d * d;
        if (v > found.value) {
            found = Found(v, q);
        }
    }
    return found;
}

// Scale k's score at step j, `value`, and its predecessor `arg`: into the next half
// (`dst`), the step's largest score (slot `next`) and the back-pointers.
fn settle(run: Run, k: u32, j: u32, dst: u32, next: u32, value: f32, arg: u32) {
    acc[dst + k] = value;
    atomicMax(&top[next], orderable(value));
    if (j >= run.own) {
        back[run.back + j * run.scales + k] = arg;
    }
}

// The predecessors of scale k (of `s`) that can beat k itself, whose candidate is its own
// score a_k, as a range [x, y): a predecessor d scales away scores at most (the step's
// largest) − λd², below a_k once λd² > `gap` = largest − a_k. With 0.1 % of the gap and
// one scale to spare, far beyond f32's rounding of scores of order ten, so that the scan
// finds the same first maximum as a scan of every scale. All `s` scales where λ is not
// positive.
fn window(k: u32, s: u32, gap: f32, penalty: f32) -> vec2<u32> {
    var d = s;
    if (penalty > 0.0) {
        let r = min(sqrt(max(gap, 0.0) * 1.001 / penalty), f32(s));
        d = min(u32(ceil(r)) + 1u, s);
    }
    return vec2<u32>(k - min(k, d), min(s, k + d + 1u));
}

// Non-negative and negative f32 to u32 in the same order (for atomicMax): the sign bit set
// on non-negatives, every bit flipped on negatives.
fn orderable(v: f32) -> u32 {
    let b = bitcast<u32>(v);
    if ((b & 0x80000000u) != 0u) {
        return ~b;
    }
    return b | 0x80000000u;
}

fn from_orderable(u: u32) -> f32 {
    if ((u & 0x80000000u) != 0u) {
        return bitcast<f32>(u & 0x7fffffffu);
    }
    return bitcast<f32>(~u);
}

@compute @workgroup_size(256)
fn backtrack(@builtin(workgroup_id) wid: vec3<u32>,
             @builtin(num_workgroups) groups: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let r = (wid.z * groups.y + wid.y) * groups.x + wid.x;
    if (r >= arrayLength(&runs)) {
        return;
    }
    let run = runs[r];
    let s = run.scales;
    let end = min(chunk.last, run.steps);
    // A run cut into lanes is traced by backtrack_lanes.
    if (chunk.first >= end || (run.flags & 2u) == 0u || (run.flags & SPLIT) != 0u) {
        return;
    }
    var k = 0u;
    if (end == run.steps) {
        // The chunk with the final step starts from the best final score (the first, on
        // ties, as src/ridge.rs), found by a tree reduction.
        var best = -BIG;
        var arg = 0u;
        for (var q = lid; q < s; q += WG) {
            let v = accum[run.slot + q];
            if (v > best) {
                best = v;
                arg = q;
            }
        }
        lowest[lid] = best;
        which[lid] = arg;
        workgroupBarrier();
        for (var w = WG / 2u; w > 0u; w = w >> 1u) {
            if (lid < w) {
                let v = lowest[lid + w];
                let i = which[lid + w];
                if (v > lowest[lid] || (v == lowest[lid] && i < which[lid])) {
                    lowest[lid] = v;
                    which[lid] = i;
                }
            }
            workgroupBarrier();
        }
        k = workgroupUniformLoad(&which[0]);
    } else {
        // The later chunk has written the path from `end` on.
        k = back[run.back + end * s + path[run.path + end]];
    }
    if (lid == 0u) {
        for (var j = end; j > chunk.first; j -= 1u) {
            path[run.path + j - 1u] = k;
            if (j > 1u) {
                k = back[run.back + (j - 1u) * s + k];
            }
        }
    }
}

// One lane of a run cut into lanes (`runs` holds the lanes): its path over own..end (the
// first lane's from step 0), from its own start (chunk.lane = NO_LANE), or in the repair
// (chunk.lane = the lane's number; the host goes from the last lanes down) from where the
// next lane's path begins, where its probe missed that.
@compute @workgroup_size(1)
fn backtrack_lanes(@builtin(workgroup_id) wid: vec3<u32>,
                   @builtin(num_workgroups) groups: vec3<u32>) {
    let r = (wid.z * groups.y + wid.y) * groups.x + wid.x;
    if (r >= arrayLength(&runs)) {
        return;
    }
    let run = runs[r];
    let s = run.scales;
    // The lane's first step on the path (the first lane's is step 0).
    var low = run.own;
    if (run.lane == 0u) {
        low = 0u;
    }
    let last = run.end == run.steps;
    var k = 0u;
    var top = run.end;
    if (chunk.lane == NO_LANE) {
        // The last lane from the best final score (the first, on ties, as src/ridge.rs);
        // the others from past their end, at that step's best score.
        if (!last) {
            top = min(run.end + run.reach, run.steps);
        }
        var best = -BIG;
        for (var q = 0u; q < s; q += 1u) {
            var v: f32;
            if (last) {
                v = accum[run.slot + q];
            } else {
                v = score(run, q, top - 1u);
            }
            if (v > best) {
                best = v;
                k = q;
            }
        }
    } else {
        if (run.lane != chunk.lane || last) {
            return;
        }
        let next = path[run.path + run.end];
        if (path[run.probe] == next) {
            return;
        }
        // The path at step end − 1, from the next lane's first step.
        k = back[run.back + run.end * s + next];
    }
    for (var j = top; j > low; j -= 1u) {
        let step = j - 1u;
        if (step < run.end) {
            path[run.path + step] = k;
        } else if (step == run.end) {
            path[run.probe] = k;
        }
        if (step > 0u) {
            k = back[run.back + step * s + k];
        }
    }
}
