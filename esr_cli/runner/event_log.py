"""TensorBoard event files of a training run, written as its chunks finish.

The run directory holds `tensorboard/`, one TensorBoard run per seed (`seed_<s>`) and one for
the mean over seeds (`mean`), each with one scalar per metric of metrics.jsonl at step =
epoch (and `env_steps`). `tensorboard --logdir <run path>/tensorboard` shows a run while it
trains; `--logdir <store>/runs` shows every run.

metrics.jsonl is the record; the event files follow it. When a run starts or resumes, its
events are written afresh from the metrics kept (a resumed run drops the metrics of a chunk
it did not checkpoint, and an adopted one starts from another run's), then appended chunk by
chunk. The writer is tensorboardX's, TensorBoard's own format.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

from esr_cli.storage.store import EVENTS_FOLDER

MEAN_RUN = "mean"


def _finite(values) -> list[float]:
    return [float(v) for v in values if v is not None and math.isfinite(v)]


def scalars(row: dict, seeds: list[int]) -> list[tuple[str, str, float]]:
    """(run, metric, value) of one metrics row: each seed's finite values under `seed_<s>`, their
    mean and `env_steps` under `mean`; what every live record of a run shows."""
    out = []
    for name, values in row.items():
        if name == "env_steps":
            out.append((MEAN_RUN, name, float(values)))
        if name == "epoch" or not isinstance(values, list):
            continue
        out += [(f"seed_{seed}", name, float(v)) for seed, v in zip(seeds, values) if v is not None and math.isfinite(v)]
        if finite := _finite(values):
            out.append((MEAN_RUN, name, sum(finite) / len(finite)))
    return out


class EventLog:
    """Scalars of metrics rows ({"epoch", "env_steps", name: [value per seed]}) as event files."""

    def __init__(self, run_dir: Path, seeds: list[int], rows: list[dict]):
        from tensorboardX import SummaryWriter  # only when a run trains

        root = Path(run_dir) / EVENTS_FOLDER
        shutil.rmtree(root, ignore_errors=True)  # written afresh from the metrics kept
        self.seeds = list(seeds)
        names = [f"seed_{s}" for s in self.seeds] + [MEAN_RUN]
        self.writers = {name: SummaryWriter(str(root / name), flush_secs=3600) for name in names}
        self.append(rows)

    def append(self, rows: list[dict]) -> None:
        for row in rows:
            for run, name, value in scalars(row, self.seeds):
                self.writers[run].add_scalar(name, value, int(row["epoch"]))
        self.flush()

    def flush(self) -> None:
        for writer in self.writers.values():
            writer.flush()

    def close(self) -> None:
        for writer in self.writers.values():
            writer.close()
