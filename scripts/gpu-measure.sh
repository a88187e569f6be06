#!/usr/bin/env bash
# Both backends side by side on a GPU machine, with the GPU trace: what issue 18's figures
# in the README were measured with. On the lent device machine, after
# `bash ../shared/tools/device-bundle.sh` here, run it from the repository root with
# `.device` carried (it unpacks the Vulkan loader there and uses .device/skelid):
#
#   bash scripts/gpu-measure.sh            # N=1000 runs; N=200 for a shorter campaign
#
# Elsewhere, with skelid and a Vulkan driver installed: SKELID=$(command -v skelid) bash
# scripts/gpu-measure.sh. Prints, and writes under $OUT (default /tmp/skelid-measure):
#   - `bench` on N simulated runs (30 000 samples) at 128 scales, traced
#     (SKELID_GPU_TRACE=1: the dispatcher's host spans and each compute pass's device
#     time), with the end-to-end run per backend;
#   - an experiment: the FFTs that fit one workgroup held in its memory (the default on a
#     GPU) against the passes through global memory (SKELID_GPU_FFT_LOCAL=0), alternating,
#     traced, on the campaign and on the 2^20-sample signal;
#   - an experiment: the first pass in f64 (the default where the adapter has it) against
#     f32 (SKELID_GPU_FIRST_PASS=f32), alternating, traced, on the campaign;
#   - an experiment: the padded spectra computed on the device from the samples (the
#     default where the first pass is f64) against on the host (SKELID_GPU_SPECTRA=host),
#     alternating, with the host share and the bytes uploaded;
#   - `bench` at 512 scales (untraced, then an experiment with the GPU traced: where its
#     dispatcher's time goes); one 2^20-sample log sweep at 256 scales (traced: where its
#     host and device time goes);
#   - an experiment: the ridge programme narrow (256 invocations a run) and wide (1024),
#     on the 2^20-sample signal and on the campaign (SKELID_GPU_RIDGE);
#   - an experiment: the 2^20-sample signal's ridge programme and backtrack in lanes side by
#     side (the default) against one workgroup through every step (SKELID_GPU_RIDGE_LANES=1);
#   - an experiment: the long record's two spectra on every core (the four-step, the
#     default) against realfft's serial plan (SKELID_SPECTRUM_FFT=realfft), both backends;
#   - an experiment: a smaller first group (SKELID_GPU_FIRST_GROUP 250 and 500) against
#     equal groups at 128 scales: whether the pipeline's start (the CPU's wait for the
#     first group's two passes) shrinks by more than one batch more costs;
#   - an experiment: the GPU backend's host share (preparing, completing) on 2 to 16
#     threads, to see whether the completion stops scaling;
#   - an experiment: the GPU `bench` with glibc's malloc keeping freed memory (no trims, no
#     unmaps: do they cost a 16-core machine its shared address space's locks and TLB
#     flushes?) against the default, back to back, with each backend's page faults and
#     system time a repetition (the kernel share), and with MALLOC_ARENA_MAX=1 (one arena:
#     no faults, one lock);
#   - an experiment: `bench` with every track of a repetition held (--hold-tracks, as before
#     2026-12-03) against each let go as it is complete (the default), both backends;
#   - `skelid run` end to end, both methods, on each backend (traced on the GPU), with
#     its log's timeline and how busy its one writer thread was;
#   - an experiment: `run` on the CPU backend with written data released from the page
#     cache (the default) against SKELID_PAGECACHE=keep, alternating;
#   - `skelid track` of the 2^20-sample signal end to end on each backend, as issue 18's 5×
#     target names it (start-up, read and write included), HDF5 and CSV out;
#   - determinism: the GPU track of one campaign run and of the 2^20-sample signal, twice.
#
# The headline figures (bench at 128 and 512 scales, the long record, run, track end to
# end, determinism) come first, then the experiments, most decisive first. A lent machine
# gives a session 15 minutes in all, its start included, and one call 10: the script keeps
# to BUDGET seconds (default 520) by skipping any step whose guessed time on an H200 is
# more than what is left, and says which it skipped. Every section prints when it began, so
# that the next call's estimates can be set from this one's. BUDGET=3600 runs everything.
set -u
N=${N:-1000}; OUT=${OUT:-/tmp/skelid-measure}; BUDGET=${BUDGET:-520}; mkdir -p "$OUT"
exec > >(tee "$OUT/log.txt") 2>&1
if [ -d .device ] && [ -z "${SKELID:-}" ]; then
  for f in .device/gl/*.deb; do dpkg -x "$f" /; done; ldconfig
  export LD_LIBRARY_PATH=$PWD/.device/lib
  for icd in /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json /usr/share/vulkan/icd.d/nvidia_icd.json; do
    [ -f "$icd" ] && { export VK_DRIVER_FILES=$icd; break; }
  done
fi
B=${SKELID:-$PWD/.device/skelid}; W=${W:-/tmp/skelid-measure-work}
now() { date +%s.%N; }
since() { awk "BEGIN{printf \"%.2f\", $(now) - $1}"; }
T0=$(now)
# Whole seconds of the budget left.
left() { awk "BEGIN{l = $BUDGET - ($(now) - $T0); printf \"%d\", (l > 0 ? l : 0)}"; }
# A command's own limit, cut to what is left of the budget (at least 1 s).
tmo() { local l; l=$(left); [ "$l" -lt 1 ] && l=1; [ "$1" -lt "$l" ] && echo "$1" || echo "$l"; }
SKIPPED=""
# step COST FUNCTION: runs FUNCTION when at least COST seconds (a guess at its time on an
# H200 with N=1000, scaled to N from 200 runs up) are left of the budget; otherwise says it
# skipped it.
step() {
  local cost=$1 l n=$N; shift; l=$(left)
  [ "$n" -lt 200 ] && n=200
  cost=$(( cost * n / 1000 ))
  if [ "$l" -ge "$cost" ]; then
    echo "-- $1 at $(since "$T0") s"; "$@"
  else
    echo "== skipped for time: $1 (about $cost s; $l s left of BUDGET=$BUDGET)"; SKIPPED="$SKIPPED $1"
  fi
}
quiet() { grep -vE "^  (cpu|gpu): (repetition|warm-up|end)"; }
# with VAR VALUE COMMAND...: COMMAND with VAR=VALUE, or with VAR unset for "default" (the
# experiments' pairs: a switch set one way, then left to skelid's own choice).
with() { local var=$1 val=$2; shift 2; if [ "$val" = default ]; then env -u "$var" "$@"; else env "$var=$val" "$@"; fi; }
# campaign_pair VAR VALUE TAG PATTERN LINES: a traced GPU bench of the campaign at 128
# scales with VAR=VALUE, then with skelid's own choice, twice over; of each, the last LINES
# lines matching PATTERN. Its JSON goes to $OUT/bench-128-TAG-VALUE.json (…-default.json).
campaign_pair() {
  local var=$1 val=$2 tag=$3 pattern=$4 lines=$5 f
  for f in "$val" default "$val" default; do
    echo "$var=$f, the campaign at 128 scales"
    SKELID_GPU_TRACE=1 with "$var" "$f" timeout "$(tmo 40)" "$B" bench "$W/campaign" --backend gpu --repeat 3 --scales 128 --no-end-to-end \
      --out "$OUT/bench-128-$tag-$f.json" 2>&1 | grep -E "$pattern" | tail -"$lines"
  done
}

echo "== $(nproc) cores; $(nvidia-smi -L 2>/dev/null | head -1); budget $BUDGET s"
bash "$(dirname "$0")/campaign.sh" "$N" "$W" "$B"
python3 - "$W/long.h5" 2>/dev/null <<'PY' || echo "(the 2^20-sample signal needs python3 with numpy and h5py: skipped)"
import sys, numpy as np, h5py
n = 2**20; fs = 1000.0; t = np.arange(n)/fs; f0, f1 = 0.5, 50.0; k = np.log(f1/f0)/t[-1]
x = np.sin(2*np.pi*f0*(np.exp(k*t)-1)/k) + 0.01*np.random.default_rng(1).standard_normal(n)
with h5py.File(sys.argv[1], 'w') as h:
    g = h.create_group('sig'); g.attrs['sample_rate'] = fs; g.attrs['kind'] = 'free'; g['output'] = x
PY
echo "campaign and long record ready at $(since "$T0") s"
LONG=0; [ -f "$W/long.h5" ] && LONG=1

# ---------------------------------------------------------------- the headline figures
bench_128() {
  echo "== bench, 128 scales (traced), with the end-to-end run"
  SKELID_GPU_TRACE=1 timeout "$(tmo 150)" "$B" bench "$W/campaign" --backend cpu,gpu --repeat 3 --scales 128 --out "$OUT/bench-128.json" 2>&1 | quiet
}
bench_512() {
  echo "== bench, 512 scales"
  timeout "$(tmo 100)" "$B" bench "$W/campaign" --backend cpu,gpu --repeat 3 --scales 512 --no-end-to-end --out "$OUT/bench-512.json" 2>&1 | quiet
}
bench_long() {
  echo "== one 2^20-sample signal, 256 scales"
  SKELID_GPU_TRACE=1 timeout "$(tmo 60)" "$B" bench "$W/long.h5" --backend cpu,gpu --repeat 5 --scales 256 --no-end-to-end --out "$OUT/bench-long.json" 2>&1 | quiet
}
run_both() {
  echo "== skelid run, both methods"
  local cfg s
  for cfg in cpu gpu; do
    s=$(now)
    SKELID_GPU_TRACE=1 timeout "$(tmo 90)" /usr/bin/time -f "maxrss %M kB, user %U s, sys %S s" "$B" run "$W/campaign" \
      --out "$W/out" --force --method both --backend $cfg --quiet > "$OUT/run-$cfg.log" 2>&1
    echo "run --backend $cfg: rc=$? wall $(since "$s") s"; grep -v "^note" "$OUT/run-$cfg.log" | tail -40
    # Where the batch's wall time went: first and last run done, the end, the one writer's load.
    awk '/ start: /{t0=$1; n=0} / done /{if(!n)f=$1; l=$1; n++} / end: /{printf "log: first run done %.2f s, last %.2f s, end %.2f s\n", f-t0, l-t0, $1-t0}' "$W/out/skelid.log" | tail -1
    grep "the writer" "$W/out/skelid.log" | tail -1 | cut -d' ' -f2-
  done
}
# Issue 18's 5× target names `skelid track` itself, as a user runs it: the device opened
# and its pipelines made, the record read, the track written (60 MB of HDF5 at 2^20
# samples), none of which `bench` times. Both backends alternating, each a fresh process,
# to a fresh file name; the CSV (117 MB of text, its rows formatted on every core) once each.
track_once() {  # backend, output file, label[, "traced": with the GPU's opening spans]
  rm -f "$2"; local s t=0; [ -n "${4:-}" ] && t=1; s=$(now)
  SKELID_GPU_TRACE=$t timeout "$(tmo 60)" "$B" track "$W/long.h5" --dataset /sig/output --scales 256 \
    --backend "$1" --out "$2" > "$OUT/track.log" 2>&1
  echo "track --backend $1 ($3): rc=$? wall $(since "$s") s"
  # Opening the device, and the dispatcher's recording before the device can start (the
  # root tables expanded on the device since 2026-12-05: fft.encode was 109-120 ms here).
  grep -E "^  (open\.|first\.submit|fft\.encode|refine\.submit|refine\.pipelines_wait|staging) " "$OUT/track.log"
}
track_end_to_end() {
  echo "== skelid track, the 2^20-sample signal at 256 scales, end to end (fresh process, HDF5 out)"
  local k b
  for k in 1 2 3; do
    for b in cpu gpu; do track_once $b "$W/track-$b-$k.h5" "$k"; done
  done
  for b in cpu gpu; do track_once $b "$W/track-$b.csv" "CSV out"; done
  track_once gpu "$W/track-traced.h5" "traced: what opening the device costs" traced
  rm -f "$W"/track-*
}
# A run's GPU track once depended on the order in which the device reached its points (the
# slots for unsure points were shared by a batch's runs; lavapipe: six invocations, six
# files). Each run has its own slots since: on a real GPU, the same file twice?
determinism() {
  echo "== determinism: the GPU track of one campaign run and of the 2^20-sample signal, twice each"
  local spec k
  for spec in "$W/campaign/run_1.h5 /runs/run_001/output" "$W/long.h5 /sig/output"; do
    set -- $spec
    [ -f "$1" ] || continue
    rm -f "$OUT"/det-*.csv
    for k in 1 2; do
      timeout "$(tmo 60)" "$B" track "$1" --dataset "$2" --backend gpu --out "$OUT/det-$k.csv" > /dev/null 2>&1
    done
    if cmp -s "$OUT/det-1.csv" "$OUT/det-2.csv"; then echo "$1 $2: the same file"; else echo "$1 $2: DIFFERENT files"; fi
  done
}

# ---------------------------------------------------------------- the experiments
# The long record's programme cut into lanes that run side by side (the default on a GPU:
# up to 256 lanes in all, here 32 of 512 steps) against one workgroup through every step
# (SKELID_GPU_RIDGE_LANES=1), alternating; the same paths either way. The H200 spent 103
# of the record's 240 ms in one workgroup's steps.
exp_lanes() {
  echo "== experiment: the ridge programme in lanes, SKELID_GPU_RIDGE_LANES=1 and the default (traced)"
  local l
  for l in 1 default 1 default; do
    echo "SKELID_GPU_RIDGE_LANES=$l, the 2^20-sample signal"
    SKELID_GPU_TRACE=1 with SKELID_GPU_RIDGE_LANES "$l" timeout "$(tmo 40)" "$B" bench "$W/long.h5" --backend cpu,gpu --repeat 5 --scales 256 \
      --no-end-to-end --out "$OUT/bench-long-lanes-$l.json" 2>&1 | grep -E "^ +(cpu|gpu) |ridge\.(steps|repair|backtrack)" | tail -7
  done
}
# 512 scales is the target furthest off (3.3× on the H200), and its dispatcher took 0.2 ms
# a signal there, 0.4 s of a 0.82 s repetition: which of its spans.
exp_trace_512() {
  echo "== experiment: bench, 512 scales, the GPU traced"
  SKELID_GPU_TRACE=1 timeout "$(tmo 60)" "$B" bench "$W/campaign" --backend gpu --repeat 3 --scales 512 --no-end-to-end \
    --out "$OUT/bench-512-traced.json" 2>&1 | quiet
}
# The refinement's f64 FFTs were the device's largest share (69 of 143 ms on an H100), one
# dispatch a radix pass, each reading and writing every sequence in global memory.
exp_fft_local() {
  echo "== experiment: the FFTs in workgroup memory (the default) and SKELID_GPU_FFT_LOCAL=0 (the passes), traced"
  local f
  campaign_pair SKELID_GPU_FFT_LOCAL 0 fft "^ +gpu |^  fft f" 5
  [ "$LONG" = 1 ] || return 0
  for f in 0 default 0 default; do
    echo "SKELID_GPU_FFT_LOCAL=$f, the 2^20-sample signal at 256 scales"
    SKELID_GPU_TRACE=1 with SKELID_GPU_FFT_LOCAL "$f" timeout "$(tmo 40)" "$B" bench "$W/long.h5" --backend gpu --repeat 5 --scales 256 --no-end-to-end \
      --out "$OUT/bench-long-fft-$f.json" 2>&1 | grep -E "^ +gpu |^  fft f" | tail -5
  done
}
# Since 2026-12-05 the workers no longer take each signal's padded spectrum (its FFT, the
# white-noise median above the band, the variance): the device does, from the samples
# uploaded once for both passes (2 cores: the GPU backend's preparation 0.015 -> 0.010 s
# a repetition of 80 signals). What the host share and the upload are on a GPU.
exp_spectra() {
  echo "== experiment: the padded spectra on the device (the default) and SKELID_GPU_SPECTRA=host, traced"
  campaign_pair SKELID_GPU_SPECTRA host spectra "^ +gpu |^  (fft f|spectrum\.|scales\.scatter)|bytes up|CPU share|wait for the device" 10
}
# A batch of few runs leaves most of a GPU idle, one workgroup a run, and each step of the
# ridge programme lasts as long as its longest scan: the wide programme (1024 invocations,
# four a scale at 256 scales) is what `auto` takes for up to 128 runs. Both, side by side.
exp_ridge_width() {
  echo "== experiment: the ridge programme's width, SKELID_GPU_RIDGE=narrow and wide (traced)"
  local w
  for w in narrow wide narrow wide; do
    echo "SKELID_GPU_RIDGE=$w, the 2^20-sample signal"
    SKELID_GPU_RIDGE=$w SKELID_GPU_TRACE=1 timeout "$(tmo 40)" "$B" bench "$W/long.h5" --backend gpu --repeat 5 --scales 256 \
      --no-end-to-end --out "$OUT/bench-long-$w.json" 2>&1 | grep -E "^ +gpu |ridge.steps" | tail -2
  done
  for w in narrow wide; do
    echo "SKELID_GPU_RIDGE=$w, the campaign at 128 scales"
    SKELID_GPU_RIDGE=$w SKELID_GPU_TRACE=1 timeout "$(tmo 40)" "$B" bench "$W/campaign" --backend gpu --repeat 3 --scales 128 \
      --no-end-to-end --out "$OUT/bench-128-$w.json" 2>&1 | grep -E "^ +gpu |ridge.steps" | tail -2
  done
}
# The first pass went to f64 on 2026-11-29 for agreement with the CPU (lavapipe: within
# bench's noise); what it costs a GPU, against the f32 first pass it replaced.
exp_first_pass() {
  echo "== experiment: the first pass in f64 (the default) and SKELID_GPU_FIRST_PASS=f32, traced"
  campaign_pair SKELID_GPU_FIRST_PASS f32 first "^ +gpu |^  (fft f|scales\.)|bytes up" 7
}
# The pipeline's start: with equal groups the CPU prepares the second group and then waits
# for the first one's two passes (the "wait for the device" line), about a quarter of the
# H200's repetition at 128 scales (2026-11-27). A smaller first group (SKELID_GPU_FIRST_GROUP)
# starts the device sooner and comes back sooner, for one batch more.
# A first group of the campaign's size or more is no first group (skelid ignores it): with
# N=200 (400 signals) the 500s are left out rather than run as equal groups again.
exp_first_group() {
  echo "== experiment: bench, 128 scales, GPU, a first group of 250 and of 500 signals against equal groups (SKELID_GPU_FIRST_GROUP)"
  local f
  for f in 250 default 500 250 default 500; do
    [ "$f" != default ] && [ "$f" -ge $((2 * N)) ] && continue
    echo -n "SKELID_GPU_FIRST_GROUP=$f: "
    with SKELID_GPU_FIRST_GROUP "$f" timeout "$(tmo 40)" "$B" bench "$W/campaign" --backend gpu --repeat 3 --scales 128 --no-end-to-end \
      --out "$OUT/bench-128-first-$f.json" 2>&1 | grep -E "^ +gpu |CPU share|wait for the device|in [0-9]+ batch" | tail -4 \
      | sed -E 's/^ +gpu +([0-9.]+) .*/median \1 s;/; s/.*every core\): /CPU share: /; s/.*between preparing and completing\): /wait: /; s/^GPU backend: //' | tr '\n' ' '
    echo
  done
}
# The completion took 0.18–0.22 s for 2000 tracks on the H200's 16 cores, about three
# times a track's one-thread cost on a slower 2-core machine: does it stop scaling (memory
# traffic, 1.5 MB of series written a track)? The GPU backend's host share by thread count.
exp_threads() {
  echo "== experiment: the GPU backend's host share (preparing, completing) by RAYON_NUM_THREADS"
  local t
  for t in 2 4 8 16; do
    echo -n "RAYON_NUM_THREADS=$t: "
    RAYON_NUM_THREADS=$t timeout "$(tmo 40)" "$B" bench "$W/campaign" --backend gpu --repeat 2 --scales 128 --no-end-to-end \
      --out "$OUT/bench-128-threads-$t.json" 2>&1 | grep -E "CPU share|wait for the device" | tail -2
  done
}
exp_malloc() {
  echo "== experiment: bench, 128 scales, glibc's malloc at its defaults (SKELID_MALLOC=default), as skelid sets it, and so with one arena (MALLOC_ARENA_MAX=1)"
  # Last, skelid's setting with every thread in glibc's main arena (MALLOC_ARENA_MAX=1), which
  # keeps what is freed: the completion's page faults (the threads' arenas growing and
  # unmapped) gone, against one lock for every allocation of 16 threads (2 cores,
  # 2026-12-03: 16 rayon threads 3.68 s against 2.64 s).
  local m setting
  for m in default skelid arena1; do
    case $m in
      arena1) setting=(MALLOC_ARENA_MAX=1) ;;
      *) setting=("SKELID_MALLOC=$m") ;;
    esac
    echo "${setting[*]}"
    env "${setting[@]}" timeout "$(tmo 80)" "$B" bench "$W/campaign" --backend cpu,gpu --repeat 3 --scales 128 --no-end-to-end \
      --out "$OUT/bench-128-malloc-$m.json" 2>&1 | grep -E "^ +(cpu|gpu) |CPU share|wait for the device|kernel share|floor"
  done
}
# Held, 2000 tracks are 3.4 GB a repetition of fresh memory for the kernel to map and zero
# (120 000-165 000 page faults a repetition on the H200, 2026-11-27); let go, the next
# track reuses the same thread's arrays (2 cores, 2026-12-03: 26 000-81 000 faults a
# repetition down to 56-166; the times within this machine's noise).
exp_hold() {
  echo "== experiment: bench, 128 scales, every track of a repetition held (--hold-tracks, as before 2026-12-03) and let go as it is complete (the default)"
  local h flag
  for h in hold default; do
    flag=(); [ "$h" = hold ] && flag=(--hold-tracks)
    # ${flag[@]+...}: an empty array under `set -u` is an error before bash 4.4.
    echo "tracks: $h"
    timeout "$(tmo 80)" "$B" bench "$W/campaign" --backend cpu,gpu --repeat 3 --scales 128 --no-end-to-end ${flag[@]+"${flag[@]}"} \
      --out "$OUT/bench-128-tracks-$h.json" 2>&1 | grep -E "^ +(cpu|gpu) |speed-up|CPU share|wait for the device|kernel share"
  done
}
# The long record's two spectra (2^20 and 1.6 M points) on every core by the four-step
# (the default from 2^18 points) against realfft's serial plan
# (SKELID_SPECTRUM_FFT=realfft), alternating: both backends wait for them.
exp_long_spectra() {
  echo "== experiment: the long record's spectra, SKELID_SPECTRUM_FFT=realfft and the default"
  local f
  for f in realfft default realfft default; do
    echo "SKELID_SPECTRUM_FFT=$f, the 2^20-sample signal"
    with SKELID_SPECTRUM_FFT "$f" timeout "$(tmo 40)" "$B" bench "$W/long.h5" --backend cpu,gpu --repeat 5 --scales 256 \
      --no-end-to-end --out "$OUT/bench-long-spectrum-$f.json" 2>&1 | grep -E "^ +(cpu|gpu) |preparing" | tail -4
  done
}
# The writer bounds `run` on 16 cores, and a fresh machine's untouched memory made its copies
# into the page cache cost a host fault a page (2-core machine: 1.05 s of system time for
# 400 MB). The release of written data (src/pagecache.rs) against SKELID_PAGECACHE=keep,
# alternating, on the CPU backend: wall time, the writer's busy time and the system time.
exp_pagecache() {
  echo "== experiment: the page-cache release, SKELID_PAGECACHE=keep and the default, CPU backend" \
    "($W on $(df -T "$W" | awk 'NR==2{print $2}'): on tmpfs there is nothing to release)"
  local pc s
  for pc in keep default keep default; do
    s=$(now)
    SKELID_PAGECACHE=$pc timeout "$(tmo 60)" /usr/bin/time -f "user %U s, sys %S s" "$B" run "$W/campaign" \
      --out "$W/out-pc" --force --method both --backend cpu --quiet > "$OUT/run-pagecache-$pc.log" 2>&1
    echo "SKELID_PAGECACHE=$pc: rc=$? wall $(since "$s") s; $(tail -1 "$OUT/run-pagecache-$pc.log");" \
      "$(grep -o 'busy [0-9.]* s of the [0-9.]* s' "$W/out-pc/skelid.log" | tail -1)"
  done
}

# Guesses at each step's time on an H200 with N=1000, with some to spare: the benches and
# `run` from its calls of 2026-11-26/27, the steps added since (most of them) never run on
# a GPU yet; reset them from the start times this call prints. A step that starts is not
# skipped halfway:
# only its commands that would run past the budget's end are cut there (each `timeout` is
# at most what is left), so that the call ends inside the device's limit with its log.
step 45 bench_128
step 30 bench_512
[ "$LONG" = 1 ] && step 15 bench_long
step 30 run_both
[ "$LONG" = 1 ] && step 30 track_end_to_end
step 10 determinism
step 40 exp_first_group
[ "$LONG" = 1 ] && step 30 exp_lanes
step 15 exp_trace_512
step 45 exp_fft_local
step 25 exp_spectra
[ "$LONG" = 1 ] && step 35 exp_ridge_width
step 25 exp_first_pass
step 25 exp_threads
step 50 exp_malloc
step 35 exp_hold
[ "$LONG" = 1 ] && step 30 exp_long_spectra
step 35 exp_pagecache
echo "== total $(since "$T0") s; skipped for time:${SKIPPED:- none}"
