"""A training run's final performance, read from its `metrics.jsonl` (figures, tables, sweeps).

"Final" means each seed's mean over the last 10% of its epochs (at least one), then the mean,
standard error and interquartile mean with its bootstrap interval across seeds (esr_cli.common.stats): training episodes with the robot's sampled policy, as the
paper's learning curves end. Reading only; nothing here trains.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from esr_cli.common.jsonl import read_jsonl

FINAL_FRACTION = 0.1


def read_rows(run_path: Path) -> list[dict]:
    """A run's metrics.jsonl, one dict per epoch (a line cut short by a kill ends it)."""
    return read_jsonl(Path(run_path) / "metrics.jsonl")


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
    epoch is logged or where the rows are not a run's (a damaged or foreign file: listing a
    store must not fail on it)."""
    try:
        rows = read_rows(run_path)
        if not rows:
            return 0, None
        epochs, per_seed = int(rows[-1]["epoch"]), final_per_seed(rows)
    except (KeyError, TypeError, ValueError, AttributeError, OSError):
        return 0, None
    return epochs, float(np.nanmean(per_seed)) if np.isfinite(per_seed).any() else None


def run_finals(run_path: Path, names: tuple[str, ...] = ("return", "success")) -> dict:
    """{name: stats.describe(per-seed finals)} for each metric (mean, SE, IQM and its interval,
    the per-seed values), plus the run's seed and epoch counts."""
    from esr_cli.common.stats import describe  # scipy: only where statistics are made

    rows = read_rows(run_path)
    out: dict = {"seeds": len(rows[-1]["return"]) if rows else 0, "epochs": rows[-1]["epoch"] if rows else 0}
    for name in names:
        out[name] = describe(final_per_seed(rows, name) if rows else [])
    return out
