"""What a training run shows as it goes: the progress bar on a terminal, plain lines in a log
file, the time an epoch and the run take, and the acknowledgement of a stop (runner/loop.py calls
these as it trains)."""

from __future__ import annotations

import signal
import time

import jax
import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from esr_cli.common.printing import tagged


def progress_bar(console: Console) -> Progress:
    return Progress(
        TextColumn("{task.description}", style="bold", markup=False),  # a spec's name, as written
        TextColumn("{task.fields[phase]}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[stats]}"),
        TimeElapsedColumn(),
        TextColumn("{task.fields[eta]}"),
        console=console,
        transient=False,
        disable=not console.is_terminal,  # a log file gets plain lines instead (TrainingReport)
    )


def _fmt_stats(row: dict, steps_per_s: float) -> str:
    def mean(name):
        vals = [v for v in row.get(name, []) if v is not None]
        return float(np.mean(vals)) if vals else float("nan")

    # The last epoch's, as the label says: the final return (last 10%) is the listings' and reports'.
    parts = [f"last-epoch return {mean('return'):.2f}", f"succ {mean('success'):.2f}"]
    if "mi_estimate" in row:
        parts.append(f"MI {mean('mi_estimate'):+.3f}")
    parts.append(f"{steps_per_s:,.0f} steps/s")
    return "  ".join(parts)


def duration(seconds: float) -> str:
    """12 s, 7.5 min, 5.2 h, 3.1 days."""
    for unit, size, limit in (("s", 1, 90), ("min", 60, 90 * 60), ("h", 3600, 48 * 3600)):
        if seconds < limit:
            return f"{seconds / size:.{0 if unit == 's' and seconds >= 10 else 1}f} {unit}"
    return f"{seconds / 86400:.1f} days"


# Spec fields whose values leave the cost of an epoch per seed unchanged (besides rates and
# other real numbers): how long the run is, how it is chunked, how long the robot acts uniformly.
_FREE_OF_COST = {"train.epochs", "train.seeds", "train.chunk_epochs", "learner.warmup_epochs"}


def _flat(tree: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in tree.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def quick_estimate(spec, quick, epoch_seconds: float) -> tuple[float | None, list[str]]:
    """(seconds `quick`, the same spec at --budget quick, would take here by this run's epoch
    time, or None; the fields that prevent an estimate). An epoch costs the same per seed
    where the two differ only in _FREE_OF_COST and real-valued fields; seeds add up on the
    CPU, where they run one after another, and not on an accelerator."""
    mine, theirs = _flat(spec.training_part()), _flat(quick.training_part())
    differ = [k for k in sorted(set(mine) | set(theirs)) if mine.get(k) != theirs.get(k) and k not in _FREE_OF_COST
              and not (isinstance(mine.get(k), float) and isinstance(theirs.get(k), float))]
    seeds, quick_seeds = len(spec.train.seeds), len(quick.train.seeds)
    if seeds != quick_seeds and jax.default_backend() != "cpu":
        differ.append("train.seeds")
    if differ:
        return None, differ
    return epoch_seconds / seeds * quick_seeds * quick.train.epochs, []


class TrainingReport:
    """What a run shows as it trains: a progress bar on a terminal (phase, epoch, the latest
    return and MI, ETA) and, terminal or log file, a line after each compile, the time an
    epoch takes and the run's estimate after the warm-up chunk, a note where that passes a
    day, and the acknowledgement of a stop. In a log file also a line per chunk."""

    def __init__(self, spec, trainer, console: Console, bar: Progress, key: str, quick=None):
        """key: the run's; quick: the same spec at --budget quick, or None."""
        self.spec, self.console, self.bar, self.key, self.quick = spec, console, bar, key, quick
        self.label = f"{spec.name} [{spec.budget}]"
        self.steps_per_epoch = spec.train.num_envs * trainer.env.episode_steps * len(spec.train.seeds)
        self.task = bar.add_task(self.label, total=spec.train.epochs, phase="", stats="", eta="")
        self.started = 0  # the epoch this process started from
        self.compiling_since: float | None = None
        self.timed = False

    def say(self, text) -> None:
        self.console.print(text, markup=False, highlight=False)

    def on_start(self, epoch: int, total: int) -> None:
        self.started = epoch
        if epoch:
            self.say(f"resuming {self.key[:12]} from epoch {epoch} of {total}")
        self.bar.update(self.task, completed=epoch)

    def on_phase(self, phase: str) -> None:
        if self.compiling_since is not None:
            self.say(f"{self.label}: compiled in {duration(time.monotonic() - self.compiling_since)}")
        self.compiling_since = time.monotonic() if phase == "compiling" else None
        self.bar.update(self.task, phase=phase)
        if phase == "compiling" and not self.console.is_terminal:  # a log file: say why nothing moves
            self.say(f"{self.label}: compiling...")

    def on_chunk(self, epoch: int, total: int, row: dict, epoch_seconds: float) -> None:
        stats = _fmt_stats(row, self.steps_per_epoch / epoch_seconds)
        eta = f"ETA {duration((total - epoch) * epoch_seconds)}" if epoch < total else ""
        self.bar.update(self.task, completed=epoch, stats=stats, eta=eta)
        if not self.timed:
            self.timed = True
            self.estimate(epoch, total, epoch_seconds)
        if not self.console.is_terminal:  # a log file: no bar, a line per chunk
            self.say(f"{self.label} epoch {epoch:,}/{total:,}  {stats}  {eta}".rstrip())

    def estimate(self, epoch: int, total: int, epoch_seconds: float) -> None:
        """The lines after the warm-up chunk: an epoch's time, the run's, --budget quick's."""
        seeds, left = len(self.spec.train.seeds), (total - epoch) * epoch_seconds
        # Said once the first chunk has timed an epoch; the run is counted from where it (re)started,
        # that chunk included, so a resumed run's last epoch is not called "no epoch left" as it runs.
        todo = total - self.started
        run = f"{todo:,} epoch{'s' * (todo != 1)}{' left' if self.started else ''}: about {duration(todo * epoch_seconds)} here"
        line = f"{self.label}: {duration(epoch_seconds)} an epoch ({seeds} seed{'s' * (seeds != 1)}); {run}"
        if self.quick is not None:
            quick, differ = quick_estimate(self.spec, self.quick, epoch_seconds)
            more = f" and {len(differ) - 1} more" if len(differ) > 1 else ""
            line += (f"; --budget quick: about {duration(quick)}" if quick is not None else
                     f"; --budget quick: not estimated ({differ[0]}{more} differ from this run's)")
        self.say(line)
        if left > 86400:
            self.say(tagged("note:", "yellow", f" this run needs more than a day on this machine ({duration(left)}); "
                            "it goes on: Ctrl-C stops it, keeping the last checkpoint, and the same command resumes it"))

    def on_stop(self, signum: int, kept: int) -> None:
        name, again = ("Ctrl-C", "Ctrl-C again") if signum == signal.SIGINT else ("SIGTERM", "a second signal")
        keeps = (f"keeping its checkpoint of epoch {kept:,} (epochs since are dropped)" if kept else
                 "no epoch is saved yet, so it will start over")
        self.say(tagged("stopping", "yellow", f" ({name}): the run stops now, {keeps}; {again} exits at once"))
