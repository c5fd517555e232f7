#!/usr/bin/env bash
# One short GPU job, prepared in advance: record the machine, optionally
# measure the benchmark, then train (or continue) one run until shortly before the job's
# time is up, and write what must come back into $OUT: the run's archive in parts small enough
# to travel (to continue it next time), and a record of its logged epochs (for the report even
# when the parts cannot be kept). Run from the repository root.
#
#   RUN="experiments/grid_10.yaml --budget paper --set train.seeds=10 --set train.epochs=3000" \
#   BUDGET_S=540 BENCH_SEEDS="1 20" bash evidence/gpu/lease.sh
#
# Environment:
#   RUN          `esr train` arguments (spec file, --budget, --set ...); empty: no run
#   BUDGET_S     seconds the whole script may take (default 540, inside a 600 s job)
#   BENCH_SEEDS  seed counts for benchmarks/bench.py (empty: no benchmark)
#   BENCH_CONFIG the benchmark's configuration (default: the gridworld paper configuration)
#   BENCH_S      seconds the benchmark may take (default 240)
#   OUT          where results go (the job's output folder; default ./out)
# Inputs it uses when present: .whl/*.whl (Python packages the machine lacks, installed into
# /tmp/site), .dev/*.part-* (an archive written by a previous job, joined and imported, so
# the run continues from its checkpoint). Needs jax with an accelerator plugin already there.
set -uo pipefail
OUT=${OUT:-out}
BUDGET_S=${BUDGET_S:-540}
BENCH_S=${BENCH_S:-240}
BENCH_CONFIG=${BENCH_CONFIG:-"gridworld grid_2 (paper)"}
PART_BYTES=${PART_BYTES:-15M}  # under the 16 MiB a returned file may have
started=$(date +%s)
left() { echo $((BUDGET_S - ($(date +%s) - started))); }
mkdir -p "$OUT"
log() { echo "[$(date -u +%T)] $*" | tee -a "$OUT/lease.log"; }

# A wheel whose package the image already has at the same major version is left out: /tmp/site
# comes first on the path, and the image's builds are the ones made for its jax and numpy.
missing_wheels() {
    python3 - .whl/*.whl <<'PY'
import sys
from importlib import metadata
for path in sys.argv[1:]:
    name, version = path.rsplit("/", 1)[-1].split("-")[:2]
    try:
        have = metadata.version(name)
    except metadata.PackageNotFoundError:
        have = None
    if have is None or have.split(".")[0] != version.split(".")[0]:
        print(path)
PY
}
if compgen -G ".whl/*.whl" >/dev/null; then
    mapfile -t wheels < <(missing_wheels)
    log "wheels installed: ${wheels[*]:-none}"
    if [ ${#wheels[@]} -gt 0 ]; then
        python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "${wheels[@]}" \
            || { log "installing .whl failed"; exit 1; }
    fi
    export PYTHONPATH="/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
else
    export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
fi
esr() { python3 -c 'import sys; from esr_cli.cli.main import main; sys.exit(main(sys.argv[1:]))' "$@"; }
STORE=${STORE:-/tmp/esr_store}

{
    date -u
    nvidia-smi 2>&1 || echo "no nvidia-smi"
    env | grep -E '^(XLA_|JAX_|CUDA_VISIBLE)' || true
    python3 -c 'import jax; print("jax", jax.__version__, jax.devices())'
} >"$OUT/machine.txt" 2>&1
log "machine: $(grep -m1 '^jax' "$OUT/machine.txt")"

if [ -n "${BENCH_SEEDS:-}" ]; then
    log "bench: $BENCH_CONFIG, seeds $BENCH_SEEDS"
    # shellcheck disable=SC2086 # seed counts are separate arguments
    # in the run's store, so an Overcooked benchmark's BC human is built once for both
    ESR_STORE="$STORE" timeout "$BENCH_S" python3 benchmarks/bench.py --configs "$BENCH_CONFIG" --seeds $BENCH_SEEDS \
        --out "$OUT/bench.json" >>"$OUT/lease.log" 2>&1
    log "bench: exit $?"
fi

[ -n "${RUN:-}" ] || { log "no RUN given"; exit 0; }
for first in .dev/*.part-aa; do
    [ -e "$first" ] || continue
    key8=$(basename "${first%.tar.gz.part-aa}")
    if compgen -G "$STORE/runs/*/$key8*" >/dev/null; then  # the machine kept it from an earlier job: that copy is newer
        log "import of $key8 skipped: the store already has it"
        continue
    fi
    cat "${first%aa}"* >/tmp/continue.tar.gz
    esr --store "$STORE" import /tmp/continue.tar.gz >>"$OUT/lease.log" 2>&1 || log "import of ${first%.part-aa} failed"
done

# Stop at a chunk boundary with time left to export and split (a 10-seed archive: ~30 s).
limit=$(($(left) - 60))
log "train $RUN (stop after ${limit}s)"
# shellcheck disable=SC2086 # RUN is a list of arguments
esr --store "$STORE" train $RUN --stop-after "${limit}s" >"$OUT/run_path.txt" 2>>"$OUT/lease.log"
rc=$?
log "train: exit $rc (0 finished, 75 stopped at the time limit: resumable)"

run_dir=$(tail -n 1 "$OUT/run_path.txt" 2>/dev/null)
if [ -z "$run_dir" ] || [ ! -d "$run_dir" ]; then  # stopped runs print no path: the newest run
    run_dir=$(ls -td "$STORE"/runs/*/*/ 2>/dev/null | head -n 1)
    run_dir=${run_dir%/}
fi
[ -n "$run_dir" ] && [ -d "$run_dir" ] || { log "no run directory"; exit 1; }
name=$(basename "$run_dir")
key=${name%.partial}
# An unfinished run's record: every logged epoch, small, laid out as in a store
# (`esr import --without-checkpoint`), for the report even if the parts below are not kept.
if [ "$name" != "$key" ]; then
    rel=${run_dir#"$STORE"/}
    tar -czf "$OUT/record_${key:0:8}.tar.gz" -C "$STORE" "$rel/metrics.jsonl" "$rel/spec.yaml" "$rel/pending.json"
fi
# The archive with its newest checkpoint, in parts (`cat PARTS > RUN.tar.gz`, then `esr import`).
if esr --store "$STORE" export "$key" --out "/tmp/${key:0:8}.tar.gz" >>"$OUT/lease.log" 2>&1; then
    split -b "$PART_BYTES" "/tmp/${key:0:8}.tar.gz" "$OUT/${key:0:8}.tar.gz.part-"
fi
log "returned: $(cd "$OUT" && ls | tr '\n' ' ')"
exit $((rc == 75 ? 0 : rc))
