#!/usr/bin/env bash
# Throughput benchmark (issue 6): the synthetic campaign of N paper-like runs
# (scripts/campaign.sh), then `skelid run` with both methods, end to end including the
# HDF5 read and write. Prints runs/s.
#
#   bash scripts/throughput.sh [N=1000] [DIR=/tmp/skelid-throughput]
set -euo pipefail
N=${1:-1000}
DIR=${2:-/tmp/skelid-throughput}
cd "$(dirname "$0")/.."
cargo build --release --quiet
BIN=$PWD/target/release/skelid
bash scripts/campaign.sh "$N" "$DIR" "$BIN"
rm -rf "$DIR/out"
start=$(date +%s.%N)
"$BIN" run "$DIR/campaign" --out "$DIR/out" --method both --quiet || true
end=$(date +%s.%N)
python3 - "$start" "$end" "$N" <<'PY'
import sys
t0, t1, n = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
print(f"{n} runs (both methods) in {t1 - t0:.1f} s: {n / (t1 - t0):.2f} runs/s")
PY
