#!/usr/bin/env bash
# Queues a campaign on Slurm: a job array of N `skelid run --shard K/N` tasks, then a merge
# that waits for all of them. Prints the two job ids; the results land in OUT/merged.
#
#   scripts/slurm/submit.sh --tasks N --out OUT [--cpus C] ARCHIVE... [-- RUN OPTIONS...]
#
# --cpus C: CPUs (and skelid workers) per task (default 1). RUN OPTIONS go to every
# `skelid run` (e.g. --backend cpu --refine). SKELID names the binary the jobs run (default:
# skelid on PATH); it must be reachable from the compute nodes, as must OUT.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
tasks="" out="" cpus=1 archives=() run_opts=()
while [ $# -gt 0 ]; do
  case "$1" in
  --tasks) tasks=$2; shift 2 ;;
  --out) out=$2; shift 2 ;;
  --cpus) cpus=$2; shift 2 ;;
  --) shift; run_opts=("$@"); break ;;
  *) archives+=("$1"); shift ;;
  esac
done
[ -n "$tasks" ] && [ -n "$out" ] && [ ${#archives[@]} -gt 0 ] || {
  echo "usage: submit.sh --tasks N --out OUT [--cpus C] ARCHIVE... [-- RUN OPTIONS...]" >&2
  exit 2
}
mkdir -p "$out"
out=$(cd "$out" && pwd)
# sbatch passes this environment on: a SKELID_SHARDS left from running one task again
# alone must not set N for the whole array.
unset SKELID_SHARDS
abs=()
for a in "${archives[@]}"; do
  case "$a" in /*) abs+=("$a") ;; *) abs+=("$PWD/$a") ;; esac
done
array=$(sbatch --parsable --array="1-$tasks" --cpus-per-task="$cpus" \
  --output="$out/slurm-%A_%a.log" "$here/skelid-array.sbatch" "$out" "${abs[@]}" "${run_opts[@]}")
merge=$(sbatch --parsable --dependency="afterany:${array%%;*}" \
  --output="$out/slurm-merge-%j.log" "$here/skelid-merge.sbatch" "$out" "$tasks")
echo "array job ${array%%;*} ($tasks tasks), merge job ${merge%%;*}: results in $out/merged"
