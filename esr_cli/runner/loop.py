"""The host side of training: chunks, progress, metrics, checkpoints, resume.

The Brax pattern: a short Python loop over jitted chunks of `chunk_epochs` epochs (all seeds
in one program: vmapped on an accelerator, one after another on the CPU). Between chunks the
host appends the chunk's metrics to `metrics.jsonl` (and to TensorBoard's event files,
runner/event_log.py), saves an orbax checkpoint of the *whole* training state (parameters,
optimiser states, replay buffer, RNG keys), and updates the progress bar. A run started again
in the same directory restores the newest complete checkpoint and continues exactly where it
stopped; metrics lines past that checkpoint are dropped first.

The first chunk is one epoch (the warm-up, which times an epoch); later ones are shorter than
`chunk_epochs` where that many would run past CHECKPOINT_EVERY_S (a power of two then, so that
few lengths are compiled). Chunking changes no number:
an epoch is a pure function of the state, its RNG key included. Compiling, running and saving
run in a worker thread, so Ctrl-C and SIGTERM are answered at once (runner/stop_requests.py).
"""

from __future__ import annotations

import json
import math
import shutil
import time
from functools import partial
from pathlib import Path
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from esr_cli.common import faults
from esr_cli.common.stops import CorruptCheckpoint, Diverged, TimeLimitReached
from esr_cli.model.train import Trainer, TrainState, compiled_chunk, compiled_init
from esr_cli.runner.event_log import EventLog
from esr_cli.runner.stop_requests import StopRequests
from esr_cli.storage.checkpoint_files import (
    CHECKPOINT_DIGESTS,
    CHECKPOINT_DIR,
    epochs_of,
    epochs_problem,
    read_digests,
    record_digests,
    step_intact,
    verified_steps,
)
from esr_cli.storage.finals import read_rows
from esr_cli.storage.store import atomic_write_text, require_networks

METRICS_FILE = "metrics.jsonl"


# A checkpoint at least this often, whatever `chunk_epochs` says (unless one epoch takes
# longer): a paper chunk of 50 epochs takes over half an hour on a 2-core CPU, and a kill or a
# power cut loses the chunk in flight.
CHECKPOINT_EVERY_S = 600.0


def chunk_length(chunk_epochs: int, epoch_seconds: float | None, left: int) -> int:
    """Epochs in the next chunk: one until an epoch is timed (epoch_seconds None), then
    `chunk_epochs`, fewer where those would take longer than CHECKPOINT_EVERY_S; at most `left`.
    Fewer is the largest power of two that fits: a chunk of a new length is a new program to
    compile (most of a minute at the paper's settings), and an epoch's time drifts with the
    machine's load, so lengths taken from a short ladder are compiled once, not every chunk."""
    if epoch_seconds is None:
        return min(1, left)
    fits = int(CHECKPOINT_EVERY_S / max(epoch_seconds, 1e-9))
    n = chunk_epochs if fits >= chunk_epochs else 1 << (max(fits, 1).bit_length() - 1)
    return min(n, left)


def next_chunk_fits(now: float, stop_at: float | None, next_chunk_seconds: float) -> bool:
    """Whether the next chunk, estimated to take `next_chunk_seconds`, would end by `stop_at`
    (time.monotonic() values; None: no limit)."""
    return stop_at is None or now + next_chunk_seconds <= stop_at


def checkpoint_manager(run_dir: Path) -> ocp.CheckpointManager:
    return ocp.CheckpointManager(
        (Path(run_dir) / CHECKPOINT_DIR).absolute(),
        # cleanup_tmp_directories: a save cut short by a kill leaves a temporary directory;
        # it is removed when the run resumes (orbax commits a step by renaming it into place).
        options=ocp.CheckpointManagerOptions(
            max_to_keep=2, create=True, enable_async_checkpointing=False, cleanup_tmp_directories=True
        ),
    )


def restore_latest(trainer: Trainer, run_dir: Path, seeds, repair: bool = True) -> tuple[TrainState, int]:
    """The newest checkpoint in `run_dir` whose files verify (or a fresh state) and its epoch.

    repair=True (a run being resumed): newer checkpoints that fail verification are deleted so
    training can save those steps again. repair=False (reading a committed artifact): nothing
    is touched, and only the newest checkpoint is acceptable.
    """
    template = initial_state(trainer, seeds)
    if not repair and not (Path(run_dir) / CHECKPOINT_DIR).is_dir():
        return template, 0  # reading only: a committed artifact is never given a folder it lacks
    mngr = checkpoint_manager(run_dir)
    try:
        steps = sorted(mngr.all_steps(), reverse=True)
        if not steps:
            return template, 0
        if (Path(run_dir) / CHECKPOINT_DIGESTS).exists():
            digests = read_digests(run_dir)
            good = [s for s in steps if step_intact(run_dir, s, digests)]
        else:  # a run written before checkpoint digests were recorded: trust orbax alone
            good = steps
        if not good:
            raise CorruptCheckpoint(
                f"no intact checkpoint in {Path(run_dir) / CHECKPOINT_DIR} (steps {steps} fail their digests); "
                f"remove {run_dir} to start this run over"
            )
        step = good[0]
        if step != steps[0] and not repair:
            raise CorruptCheckpoint(f"the newest checkpoint in {Path(run_dir) / CHECKPOINT_DIR} fails its digests (see `esr verify`)")
        for newer in (s for s in steps if s > step):  # unverified: a save cut short, or damaged
            shutil.rmtree(Path(run_dir) / CHECKPOINT_DIR / str(newer))
        try:
            state = mngr.restore(step, args=ocp.args.StandardRestore(template))
        except Exception as e:  # noqa: BLE001 - orbax raises many kinds; all mean the same here
            first = (str(e).splitlines() or [""])[0][:160]
            raise CorruptCheckpoint(
                f"checkpoint {Path(run_dir) / CHECKPOINT_DIR / str(step)} cannot be read ({type(e).__name__}: {first}); "
                f"remove {run_dir} to start this run over"
            ) from None
    finally:
        mngr.close()
    _check_epochs(trainer, run_dir, step, state, repair)
    return state, int(step)


def _check_epochs(trainer: Trainer, run_dir: Path, step: int, state: TrainState, repair: bool) -> None:
    """Refuse a checkpoint whose folder's number (only a name: an archive's folder can be
    renamed) is not the epoch its state holds, an epoch its metrics logged, or within the run:
    resuming from it would skip or repeat epochs and commit a run that never trained them."""
    problem = epochs_problem(run_dir, step, trainer.spec.train.epochs, epochs_of(jax.device_get(state.epoch)))
    if problem:
        what = f"remove {run_dir} to start this run over" if repair else "see `esr verify`"
        raise CorruptCheckpoint(f"{Path(run_dir) / CHECKPOINT_DIR / str(step)}: {problem}; {what}")


def adopt_checkpoint(source_dir: Path, run_dir: Path, at_most: int) -> int:
    """Start `run_dir` (empty) from the newest verified checkpoint of `source_dir` at epoch <=
    `at_most`: its checkpoint, its digests and its metrics up to that epoch are copied, so
    `train` then resumes there. -> the adopted epoch (0: nothing suitable, nothing copied).

    Training is a pure function of the state, epoch by epoch, so a run of the same spec that
    is longer continues from a shorter one's checkpoint exactly as if it had never stopped."""
    step = next((s for s in verified_steps(source_dir) if s <= at_most), 0)
    if not step:
        return 0
    target = Path(run_dir) / CHECKPOINT_DIR / str(step)
    shutil.copytree(Path(source_dir) / CHECKPOINT_DIR / str(step), target)
    rows = [r for r in read_rows(source_dir) if r["epoch"] <= step]
    atomic_write_text(Path(run_dir) / METRICS_FILE, "".join(json.dumps(r) + "\n" for r in rows))
    record_digests(run_dir, [step], step)
    return step


def _truncate_metrics(run_dir: Path, epoch: int) -> None:
    """Keep only metrics of epochs <= epoch (those covered by the restored checkpoint)."""
    rows = [r for r in read_rows(run_dir) if r["epoch"] <= epoch]
    atomic_write_text(Path(run_dir) / METRICS_FILE, "".join(json.dumps(r) + "\n" for r in rows))


def _append_rows(run_dir: Path, rows: list[dict]) -> None:
    with open(run_dir / METRICS_FILE, "a") as f:
        f.write("".join(json.dumps(r) + "\n" for r in rows))


def _metric_rows(metrics: dict, first_epoch: int, steps_per_epoch: int) -> list[dict]:
    names = sorted(metrics)
    n = next(iter(metrics.values())).shape[1]
    rows = []
    for i in range(n):
        epoch = first_epoch + i + 1
        row = {"epoch": epoch, "env_steps": epoch * steps_per_epoch}
        for name in names:
            vals = metrics[name][:, i]
            row[name] = [None if not math.isfinite(v) else round(float(v), 6) for v in vals]
        rows.append(row)
    return rows


def _watched_metrics(trainer: Trainer) -> list[str]:
    """Metrics that must be finite for this method (others are NaN by design)."""
    watched = []
    if trainer.method.learns_policy and trainer.spec.learner.updates_per_epoch > 0:
        watched += ["critic_loss", "q_mean", "reward_mean"]
    if trainer.method.updates_per_epoch > 0:
        watched += list(trainer.method.metric_names)
    return watched


def _divergence(trainer: Trainer, state: TrainState, metrics: dict, seeds, first_epoch: int) -> Diverged | None:
    """The first NaN/inf in losses, Q-values or parameters, naming quantity, seed and epoch (the
    earliest epoch of any seed and metric); None if none."""
    first = None  # (epoch index, metric, seed index)
    for name in _watched_metrics(trainer):
        bad = ~np.isfinite(metrics[name])  # seeds x epochs
        if bad.any():
            e = int(np.argmax(bad.any(axis=0)))
            if first is None or e < first[0]:
                first = (e, name, int(np.argmax(bad[:, e])))
    if first is not None:
        e, name, s = first
        epoch = first_epoch + e + 1
        return Diverged(f"{name} became {metrics[name][s, e]} at seed {seeds[s]}, epoch {epoch}", epoch)
    last_epoch = first_epoch + next(iter(metrics.values())).shape[1]
    params = {"critic": state.learner.params, "method": state.method}
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        arr = np.asarray(leaf)
        if arr.dtype.kind != "f":
            continue
        bad_seed = ~np.isfinite(arr.reshape(arr.shape[0], -1)).all(axis=1)
        if bad_seed.any():
            s = int(np.argmax(bad_seed))
            where = jax.tree_util.keystr(path)
            return Diverged(f"parameter {where} became non-finite at seed {seeds[s]}, by epoch {last_epoch}", last_epoch)
    return None


def train(
    trainer: Trainer,
    run_dir: Path,
    on_chunk: Callable[[int, int, dict, float], None] | None = None,
    on_start: Callable[[int, int], None] | None = None,
    stop_at: float | None = None,
    on_phase: Callable[[str], None] | None = None,
    on_stop: Callable[[int, int], None] | None = None,
    logs: Sequence[Callable[[Path, list[int], list[dict]], Any]] = (),
) -> dict:
    """Train (or resume) in `run_dir` until `spec.train.epochs`; -> summary of the last epoch.

    on_start(start_epoch, total_epochs); on_phase(phase) as each step begins: "compiling" (a
    program), "warm-up" (the first chunk, which times an epoch), "training";
    on_chunk(epoch, total, last_row, seconds_per_epoch) after each saved chunk;
    on_stop(signum, kept_epoch) once, as soon as SIGINT or SIGTERM asks the run to stop
    (Interrupted follows, keeping the checkpoint of kept_epoch).
    stop_at: a time.monotonic() value; after each saved chunk the run stops (TimeLimitReached)
    when the next chunk would end past it. At least one chunk always runs.
    logs: live records beside the TensorBoard files, each made as log(run_dir, seeds, rows kept)
    and then given each chunk's rows (`append`) until `close`.
    """
    spec = trainer.spec
    run_dir = Path(run_dir)
    seeds = list(spec.train.seeds)
    total = spec.train.epochs
    steps_per_epoch = spec.train.num_envs * trainer.env.episode_steps
    state, epoch = restore_latest(trainer, run_dir, seeds)
    _truncate_metrics(run_dir, epoch)
    if on_start:
        on_start(epoch, total)
    mngr = checkpoint_manager(run_dir)
    kept = read_rows(run_dir)
    records = []  # the live records made so far: closed on the way out, whatever fails
    chunks_done = 0
    try:
        for make in (EventLog, *logs):
            records.append(make(run_dir, seeds, kept))
        with StopRequests(on_stop).installed() as stop:
            chunks = _Chunks(trainer, stop, on_phase)
            while epoch < total:
                n = chunks.length(total - epoch)
                faults.reached("compile", chunks_done + 1)
                state, metrics = chunks.run(n, state, epoch)
                t0 = time.perf_counter()
                rows = _metric_rows(metrics, epoch, steps_per_epoch)
                diverged = _divergence(trainer, state, metrics, seeds, epoch)
                if diverged:
                    # The epochs up to it are kept for inspection (`esr plot curve`); a resume
                    # drops them again, back to its checkpoint's.
                    _append_rows(run_dir, [r for r in rows if r["epoch"] <= diverged.epoch])
                    raise diverged
                _append_rows(run_dir, rows)
                for record in records:
                    record.append(rows)
                epoch += n
                chunks_done += 1
                faults.reached("after_metrics", chunks_done)
                stop.wait(partial(_save, mngr, run_dir, epoch, state, chunks_done), epoch, abandon=False)
                faults.reached("after_checkpoint", chunks_done)
                if on_chunk:
                    on_chunk(epoch, total, rows[-1], chunks.epoch_seconds)
                stop.check(epoch)
                after = time.perf_counter() - t0  # saving and reporting, again after the next chunk
                if epoch < total and not next_chunk_fits(time.monotonic(), stop_at, chunks.seconds(total - epoch) + after):
                    raise TimeLimitReached(epoch, total)
    finally:
        mngr.close()
        for record in records:
            record.close()
    keep_newest_checkpoint(run_dir)
    return summarize(read_rows(run_dir))


class _Chunks:
    """The chunks of one call of `train`: their compiled programs, by length, and how long an
    epoch and a compile took. Each long step runs in `stop.wait`, so a stop ends it at once."""

    def __init__(self, trainer: Trainer, stop: StopRequests, on_phase: Callable[[str], None] | None):
        self.trainer, self.stop = trainer, stop
        self.phase = on_phase or (lambda name: None)
        self.programs: dict[int, Callable] = {}  # jitted, compiled for this run's states
        self.epoch_seconds: float | None = None  # the last chunk's, per epoch
        self.compile_seconds = 0.0  # the last program's

    def length(self, left: int) -> int:
        return chunk_length(self.trainer.spec.train.chunk_epochs, self.epoch_seconds, left)

    def run(self, n: int, state: TrainState, epoch: int) -> tuple[TrainState, dict]:
        """n more epochs from `state` (at `epoch`, the checkpoint a stop keeps); -> (state, metrics)."""
        if n not in self.programs:
            self.phase("compiling")
            t0 = time.perf_counter()
            program = compiled_chunk(self.trainer, n)
            self.stop.wait(partial(_compile, program, state), epoch)
            self.programs[n] = program
            self.compile_seconds = time.perf_counter() - t0
        self.phase("warm-up" if self.epoch_seconds is None else "training")
        t0 = time.perf_counter()
        out = self.stop.wait(partial(_run_chunk, self.programs[n], state), epoch)
        self.epoch_seconds = max(time.perf_counter() - t0, 1e-9) / n
        return out

    def seconds(self, left: int) -> float:
        """How long the next chunk would run, its compile included if its program is new."""
        n = self.length(left)
        return n * self.epoch_seconds + (0.0 if n in self.programs else self.compile_seconds)


def _compile(program, state: TrainState) -> None:
    """Compile the jitted `program` for states like `state` ahead of its first call, which then
    finds it compiled: the run is timed apart from the compile."""
    program.lower(state).compile()


def _run_chunk(program, state: TrainState) -> tuple[TrainState, dict]:
    """One chunk run to its end; its metrics on the host, as numpy arrays."""
    state, metrics = program(state)
    return state, {k: np.asarray(v) for k, v in jax.device_get(metrics).items()}


def _save(mngr: ocp.CheckpointManager, run_dir: Path, epoch: int, state: TrainState, chunk: int) -> None:
    faults.reached("during_save", chunk)
    mngr.save(epoch, args=ocp.args.StandardSave(state))
    mngr.wait_until_finished()
    record_digests(run_dir, mngr.all_steps(), epoch)


def keep_newest_checkpoint(run_dir: Path) -> None:
    """A finished run keeps only its newest verified checkpoint, the one evaluation and
    extension restore. The one before it is kept during training only in case the newest is
    cut short; dropping it halves what a finished run stores and what `esr export` moves."""
    steps = verified_steps(run_dir)
    if not steps:
        return
    newest = steps[0]
    # Digests first: a kill between the two steps leaves older directories that verify as
    # nothing, so they are never restored, and the next call removes them.
    atomic_write_text(Path(run_dir) / CHECKPOINT_DIGESTS, json.dumps({str(newest): read_digests(run_dir)[str(newest)]}))
    for d in (Path(run_dir) / CHECKPOINT_DIR).iterdir():
        if d.is_dir() and d.name.isdigit() and int(d.name) != newest:
            shutil.rmtree(d)


def summarize(rows: list[dict], last: int = 10) -> dict:
    """Mean over the last `last` epochs of each metric, per seed and across seeds."""
    if not rows:
        return {}
    tail = rows[-last:]
    out = {"epochs": rows[-1]["epoch"], "env_steps": rows[-1]["env_steps"]}
    for name in rows[-1]:
        if name in ("epoch", "env_steps"):
            continue
        per_seed = np.array([[np.nan if v is None else v for v in r[name]] for r in tail], dtype=float)
        seed_means = np.nanmean(per_seed, axis=0) if np.isfinite(per_seed).any() else per_seed[0]
        out[name] = {
            "per_seed": [None if not np.isfinite(v) else round(float(v), 6) for v in seed_means],
            "mean": None if not np.isfinite(seed_means).any() else round(float(np.nanmean(seed_means)), 6),
        }
    return out


def initial_state(trainer: Trainer, seeds) -> TrainState:
    """A fresh training state for these seeds (the one training starts from)."""
    return compiled_init(trainer)(jnp.asarray(seeds, jnp.int32))


def final_state(trainer: Trainer, run_dir: Path) -> TrainState:
    """The last checkpoint of a run (read-only)."""
    require_networks(run_dir)
    state, epoch = restore_latest(trainer, run_dir, list(trainer.spec.train.seeds), repair=False)
    if epoch == 0:
        raise FileNotFoundError(f"no checkpoint in {run_dir}")
    return state
