"""Helpers the tests of runs share (tests/runner, tests/storage): the smoke training command,
the store's committed and unfinished runs, a run's final arrays, a relabelled checkpoint."""

import json
from pathlib import Path

import jax
import numpy as np

SMOKE = ("train", "experiments/grid_2.yaml", "--budget", "smoke")


def committed(store):
    return [p for p in Path(store).glob("runs/*/*") if p.is_dir() and not p.name.endswith(".partial")]


def partials(store):
    return list(Path(store).glob("runs/*/*.partial"))


def final_arrays(run_dir):
    from esr_cli.common import specs
    from esr_cli.model.train import make_trainer
    from esr_cli.runner import loop

    trainer = make_trainer(specs.load("experiments/grid_2.yaml", "smoke"))
    return [np.asarray(x) for x in jax.tree.leaves(loop.final_state(trainer, run_dir))]


def rename_checkpoint(run_dir: Path, old: int, new: int) -> None:
    """Rename checkpoint `old` to `new`, its recorded digests following: a folder whose number
    lies while every file still matches its digest."""
    (run_dir / "checkpoints" / str(old)).rename(run_dir / "checkpoints" / str(new))
    digests = json.loads((run_dir / "checkpoint_digests.json").read_text())
    (run_dir / "checkpoint_digests.json").write_text(json.dumps({str(new): digests[str(old)]}))
