#!/usr/bin/env bash
# Seeds on a CPU: one process using every core (seeds one after another) against one process
# pinned to each core (a seed each), on the gridworld paper configuration. Run it on an idle
# machine; docs/performance.md ("Seeds across cores") has the figures.
#     bash benchmarks/cores.sh OUTDIR
set -euo pipefail
out=${1:-benchmarks/cores}; mkdir -p "$out"
cd "$(dirname "$0")/.."
B=(.venv/bin/python benchmarks/bench.py --one experiments/grid_2.yaml)
"${B[@]}" 1 3 auto > "$out/both_1seed.json"
"${B[@]}" 2 3 auto > "$out/both_2seeds.json"
taskset -c 0 "${B[@]}" 1 3 auto > "$out/core0_1seed.json"
taskset -c 0 "${B[@]}" 1 3 auto > "$out/pair_core0.json" &
taskset -c 1 "${B[@]}" 1 3 auto > "$out/pair_core1.json" &
wait
for f in "$out"/*.json; do echo "$(basename "$f" .json): $(tail -1 "$f")"; done
