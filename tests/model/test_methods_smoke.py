"""Every method trains end to end at the smoke budget on the paper's smallest and largest
gridworld (N = 2 and 10; in-process, through the same run recipe as `esr train`), and its
metrics are finite where defined. N only changes array shapes, so the two ends cover the code;
every spec file at every N is validated by tests/model/test_spec.py, and the CI's smoke paper suite
(`make paper-figures BUDGET=smoke`) trains all 24."""

import json
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from esr_cli.common import specs
from esr_cli.recipes import runs
from esr_cli.storage.artifacts import ensure
from esr_cli.storage.store import Store

METHODS = ("esr", "random", "ave", "goal_inference", "iq_learn", "oracle")
SPECS = [
    f"experiments/grid_{n}.yaml" if m == "esr" else f"experiments/grid_{n}_{m}.yaml" for n in (2, 10) for m in METHODS
]


# ESR's estimator variants (docs/estimators.md) together, on the crowded grid of the estimator check.
VARIANTS = [("experiments/grid_4x4_3.yaml", ("method.episode_group=4", "method.future=human", "method.infonce=separate",
                                              "method.human_action=inferred", "method.reward=simplified"))]


@pytest.mark.slow
@pytest.mark.parametrize("path,sets", VARIANTS, ids=["esr_variants"])
def test_esr_variants_train_at_smoke(path, sets, smoke_store):
    spec = specs.load(path, "smoke", list(sets))
    assert (spec.method.episode_group, spec.method.future, spec.method.infonce) == (4, "human", "separate")
    run_path, _ = ensure(runs.run_recipe(spec, Console(quiet=True)), Store(smoke_store))
    rows = [json.loads(line) for line in (run_path / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == spec.train.epochs
    assert all(np.isfinite(row["repr_loss"]).all() and np.isfinite(row["mi_estimate"]).all() for row in rows)
    assert all(0 <= row["code_accuracy"][0] <= 1 and row["latent_loss"][0] >= 0 for row in rows)


@pytest.mark.slow
@pytest.mark.parametrize("path", SPECS, ids=lambda p: Path(p).stem)
def test_spec_trains_at_smoke(path, smoke_store):
    spec = specs.load(path, "smoke")
    run_path, _ = ensure(runs.run_recipe(spec, Console(quiet=True)), Store(smoke_store))
    manifest = json.loads((run_path / "manifest.json").read_text())
    assert manifest["method"] == spec.method.kind
    rows = [json.loads(line) for line in (run_path / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == spec.train.epochs
    for row in rows:
        assert 0.0 <= np.mean(row["return"]) <= spec.env.episode_steps
        if spec.method.kind not in ("random", "goal_inference"):
            assert np.isfinite(row["critic_loss"]).all() and np.isfinite(row["beta"]).all()
    if spec.method.kind == "goal_inference":
        assert all(0.0 <= v <= 1.0 for row in rows for v in row["goal_belief_true"])
