"""A training run's final performance, read from its `metrics.jsonl` (figures, tables, sweeps).

"Final" means each seed's mean over the last 10% of its epochs (at least one), then the mean,
standard error and interquartile mean with its bootstrap interval across seeds (esr_cli.common.stats): training episodes with the robot's sampled policy, as the
paper's learning curves end. Reading only; nothing here trains.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from esr_cli.common.failures import Failure
from esr_cli.common.jsonl import JsonInputError, read_jsonl
from esr_cli.common.numbers import as_number
from esr_cli.storage.store import MANIFEST, StoreError, load_manifest, read_pending

FINAL_FRACTION = 0.1


MAX_EPOCH = 10**9


class UnreadableMetrics(Failure):
    """A run's metrics.jsonl that cannot be read at all (a FIFO, a device or a link in its place,
    a file larger than esr reads, a disk error). `problem`: what is wrong, naming the file, for
    a listing's line; `one_line()`: a command's ending."""

    exit_code = 2  # bad input, as a damaged artifact is (storage/store.py::StoreError)

    def __init__(self, problem: str):
        super().__init__(problem)
        self.problem = problem

    def one_line(self) -> str:
        return f"unreadable metrics: {self.problem}"


def logged_rows(run_path: Path) -> list[dict]:
    """A run's metrics.jsonl, one dict per epoch, as training writes them: a line cut short by a
    kill ends it, as does the first row that is not an epoch's (see `epoch_rows`).
    UnreadableMetrics where the file cannot be read at all."""
    path = Path(run_path) / "metrics.jsonl"
    try:
        return epoch_rows(read_jsonl(path))
    except JsonInputError as e:
        raise UnreadableMetrics(f"{path} is {e}") from None
    except OSError as e:
        raise UnreadableMetrics(f"{path} cannot be read ({e.strerror or e})") from None


def read_rows(run_path: Path) -> list[dict]:
    """`logged_rows` without the rows beyond the run's length (its manifest's or pending.json's):
    no table reads epochs a run was never asked for (`checkpoint_files.logged_epochs` reads them
    all, for `esr verify` to name)."""
    rows = logged_rows(run_path)
    length = run_length(_record(Path(run_path)))
    return rows if length is None else [r for r in rows if r["epoch"] <= length]


def _record(run_path: Path) -> dict:
    """A run directory's manifest or else its pending.json; {} where neither can be read."""
    if (run_path / MANIFEST).exists():
        try:
            return load_manifest(run_path)
        except StoreError:
            return {}
    return read_pending(run_path) or {}


def run_length(record: dict) -> int | None:
    """The epochs a run's manifest or pending.json asks for (its key components' train.epochs);
    None where they name none."""
    value = record.get("key_components")
    for name in ("spec", "train", "epochs"):
        value = value.get(name) if isinstance(value, dict) else None
    return value if type(value) is int else None


def epoch_rows(rows: list[dict]) -> list[dict]:
    """`rows` up to the first that is not an epoch's metrics as training writes them: an integer
    epoch one above the row before's (the first 1), a number of environment steps, and every metric (the return
    always) a list of numbers over the seeds (None where undefined; a finite one within float32's
    range, as training writes them), as long in every row. What follows such a row is not
    trusted (a file from an archive or an older esr), so tables and figures read the run as far
    as it is sound instead of failing on it, and never turn a value too large for a float into
    an error."""
    out, widths, last = [], {}, 0
    for row in rows:
        epoch = row.get("epoch")
        # Training logs every epoch, from 1 on: a gap would let a forged last row stand for the
        # last 10% of a run's epochs, and its number for the run's length.
        if type(epoch) is not int or epoch != last + 1 or epoch > MAX_EPOCH or not isinstance(row.get("return"), list):
            break
        if not all(_sound(name, value, widths) for name, value in row.items() if name != "epoch"):
            break
        out.append(row)
        last = epoch
    return out


SCALARS = ("env_steps",)  # a row's values for the whole epoch; every other metric is a list over seeds


# Training logs float32 values: a finite number beyond float32's range was not written by it, and
# (squared in a standard error, summed in a mean) would overflow the statistics of a table.
MAX_LOGGED = float(np.finfo(np.float32).max)


def _loggable(x) -> bool:
    number = as_number(x)
    return number is not None and (abs(number) <= MAX_LOGGED or not math.isfinite(number))  # NaN, inf: as logged


def _sound(name: str, value, widths: dict) -> bool:
    if name in SCALARS:
        return _loggable(value)
    if not isinstance(value, list) or widths.setdefault(name, len(value)) != len(value):
        return False
    return all(x is None or _loggable(x) for x in value)


def series(rows: list[dict], name: str) -> tuple[np.ndarray, np.ndarray]:
    """(epochs [E], values [E, seeds]) with NaN where a metric is undefined, including an epoch
    whose row lacks the metric altogether (the seed count is the widest row's)."""
    epochs = np.array([r["epoch"] for r in rows])
    per_row = [r.get(name) or [] for r in rows]
    width = max((len(v) for v in per_row), default=0) or 1
    vals = np.full((len(rows), width), np.nan)
    for i, v in enumerate(per_row):
        if v and len(v) != width:
            raise ValueError(f"epoch {rows[i]['epoch']} logs {name} for {len(v)} seeds, other epochs for {width}")
        vals[i, :len(v)] = [np.nan if x is None else x for x in v]
    return epochs, vals


def final_per_seed(rows: list[dict], name: str = "return") -> np.ndarray:
    """Each seed's mean over the last 10% of epochs (at least one); NaN for a seed whose final
    epochs never logged the metric."""
    _, vals = series(rows, name)
    k = max(1, int(round(len(rows) * FINAL_FRACTION)))
    with warnings.catch_warnings():  # "mean of empty slice": exactly the seeds that get NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(vals[-k:], axis=0)


def run_progress(run_path: Path) -> tuple[int, float | None]:
    """(epochs logged, the mean across seeds of each seed's final return); (0, None) while no
    epoch is logged or where the file cannot be read (a link, too large, unreadable: listing a
    store must not fail on it). `read_rows` keeps only rows as training writes them, so what
    follows cannot fail on their contents."""
    try:
        rows = read_rows(run_path)
    except UnreadableMetrics:
        return 0, None
    if not rows:
        return 0, None
    per_seed = final_per_seed(rows)
    return rows[-1]["epoch"], float(np.nanmean(per_seed)) if np.isfinite(per_seed).any() else None


def run_finals(run_path: Path, names: tuple[str, ...] = ("return", "success")) -> dict:
    """{name: stats.describe(per-seed finals)} for each metric (mean, SE, IQM and its interval,
    the per-seed values), plus the run's seed and epoch counts."""
    from esr_cli.common.stats import describe  # scipy: only where statistics are made

    rows = read_rows(run_path)
    seeds = max((len(r["return"]) for r in rows), default=0)  # every sound row has its return list
    out: dict = {"seeds": seeds, "epochs": rows[-1]["epoch"] if rows else 0}
    for name in names:
        out[name] = describe(final_per_seed(rows, name) if rows else [])
    return out
