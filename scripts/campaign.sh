#!/usr/bin/env bash
# The throughput campaign: N paper-like runs (the paper's rig with Coulomb friction, chirp
# 0→12 Hz in 30 s at 1 kHz = 30 000 samples, simulate's default of no encoder noise, one
# archive per run) in DIR/campaign, simulated with SKELID on every core. Kept when DIR
# already holds exactly N runs. Used by throughput.sh and gpu-measure.sh.
#
#   bash scripts/campaign.sh N DIR SKELID
set -euo pipefail
N=$1; DIR=$2; BIN=$3
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
