"""docs/extending.md's example method, run through the real runner: the page stays true."""

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
def test_the_example_method_trains(monkeypatch):
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
