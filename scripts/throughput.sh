#!/usr/bin/env bash
# Throughput benchmark (issue 6): a synthetic campaign of N paper-like runs (the paper's rig
# with Coulomb friction, chirp 0→12 Hz in 30 s at 1 kHz = 30 000 samples, simulate's
# default of no encoder noise, one archive per run), then `skelid run` with both
# methods, end to end including the HDF5 read and write. Prints runs/s.
#
#   bash scripts/throughput.sh [N=1000] [DIR=/tmp/skelid-throughput]
set -euo pipefail
N=${1:-1000}
DIR=${2:-/tmp/skelid-throughput}
cd "$(dirname "$0")/.."
cargo build --release --quiet
BIN=$PWD/target/release/skelid
mkdir -p "$DIR/campaign"
cat > "$DIR/paper.toml" <<'TOML'
inertia = 3.16
stiffness = 15000.0
damping = 13.0
clearance = 0.0262
gravity_stiffness = 0.0

[effects]
coulomb_friction = { torque = 2.5 }
TOML
have=$(find "$DIR/campaign" -name 'run_*.h5' | wc -l)
if [ "$have" -ne "$N" ]; then
  rm -f "$DIR"/campaign/run_*.h5
  echo "simulating $N runs into $DIR/campaign ..."
  seq 1 "$N" | xargs -P "$(nproc)" -I{} "$BIN" simulate --model "$DIR/paper.toml" \
    --out "$DIR/campaign/run_{}.h5" --seed {} --duration 30 --f0 0 --f1 12 \
    --amplitude 0.04 --rolloff-hz 1.8 --rolloff-order 2 >/dev/null
fi
rm -rf "$DIR/out"
start=$(date +%s.%N)
"$BIN" run "$DIR/campaign" --out "$DIR/out" --method both --quiet || true
end=$(date +%s.%N)
python3 - "$start" "$end" "$N" <<'PY'
import sys
t0, t1, n = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
print(f"{n} runs (both methods) in {t1 - t0:.1f} s: {n / (t1 - t0):.2f} runs/s")
PY
