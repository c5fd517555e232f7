"""docs/extending.md's example method, run through the real runner, its evaluation and a figure
of its curves: the page stays true."""

import re
from pathlib import Path

import jax
import numpy as np
import pytest

from esr_cli.common import specs
from esr_cli.model.interfaces import Method
from esr_cli.model.methods import registry
from esr_cli.model.train import make_trainer

PAGE = Path(__file__).resolve().parents[1] / "docs" / "extending.md"


@pytest.mark.slow
def test_the_example_method_trains_evaluates_and_is_drawn(monkeypatch, tmp_path):
    (code,) = re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S)
    namespace: dict = {}
    exec(compile(code, str(PAGE), "exec"), namespace)
    method_cls, spec_cls = namespace["RoomToMove"], namespace["RoomToMoveMethodSpec"]
    monkeypatch.setitem(registry.METHODS, "room_to_move", method_cls)

    base = specs.load("experiments/grid_5.yaml", "smoke")
    # The page's spec model would be in model/spec.py's METHOD_SPECS; here it is built directly.
    spec = base.model_copy(update={"method": spec_cls(kind="room_to_move")})
    trainer = make_trainer(spec)
    assert isinstance(trainer.method, method_cls) and isinstance(trainer.method, Method)
    state, metrics = jax.jit(trainer.epoch)(trainer.init(0))
    assert np.isfinite(float(metrics["critic_loss"])) and int(state.epoch) == 1
    # The reward is the human's free neighbours: 0 to 4, and the batch's mean is what the critic saw.
    assert 0.0 <= float(metrics["reward_mean"]) <= 4.0

    # Evaluated as `esr eval` does (all seeds in one program), and drawn as `esr plot curve` draws.
    from esr_cli.common.plots import learning_curve
    from esr_cli.model.evaluate import evaluate, policy_modes

    seeds = jax.tree.map(lambda x: x[None], state)
    result = evaluate(trainer, seeds, episodes=2, seeds=[0])
    assert set(result) == set(policy_modes(trainer))
    assert all(r["return"].shape == (1, 2) and np.isfinite(r["return"]).all() for r in result.values())
    rows = [{"epoch": 1, **{k: [float(v)] for k, v in metrics.items()}}]
    png = learning_curve(rows, tmp_path / "room_to_move.png", "room_to_move", {"method": "room_to_move"})
    assert png.is_file() and png.stat().st_size > 1000
