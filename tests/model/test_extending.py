"""docs/extending.md's example method, run through the real runner, its evaluation and a figure
of its curves: the page stays true."""

import re
from pathlib import Path

import jax
import numpy as np
import pytest

from esr_cli.common import specs
from esr_cli.model.interfaces import Environment, Method
from esr_cli.model.methods import registry
from esr_cli.model.train import make_trainer

PAGE = Path(__file__).resolve().parents[2] / "docs" / "extending.md"


def _page_block(marker: str) -> dict:
    """The names the page's python block holding `marker` defines."""
    (code,) = [c for c in re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S) if marker in c]
    namespace: dict = {}
    exec(compile(code, str(PAGE), "exec"), namespace)
    return namespace


def _evaluated_and_drawn(trainer, state, metrics, out_png: Path) -> None:
    """Evaluated as `esr eval` does (all seeds in one program), and drawn as `esr plot curve` draws."""
    from esr_cli.common.plots import learning_curve
    from esr_cli.model.evaluate import evaluate, policy_modes

    result = evaluate(trainer, jax.tree.map(lambda x: x[None], state), episodes=2, seeds=[0])
    assert set(result) == set(policy_modes(trainer))
    assert all(r["return"].shape == (1, 2) and np.isfinite(r["return"]).all() for r in result.values())
    rows = [{"epoch": 1, **{k: [float(v)] for k, v in metrics.items()}}]
    png = learning_curve(rows, out_png, out_png.stem, {"example": out_png.stem})
    assert png.is_file() and png.stat().st_size > 1000


@pytest.mark.slow
def test_the_example_method_trains_evaluates_and_is_drawn(monkeypatch, tmp_path):
    namespace = _page_block("class RoomToMove(")
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

    _evaluated_and_drawn(trainer, state, metrics, tmp_path / "room_to_move.png")


@pytest.mark.slow
def test_the_example_environment_trains_evaluates_and_is_drawn(monkeypatch, tmp_path):
    from esr_cli.model import envs
    from esr_cli.model.humans import registry as humans

    page = _page_block("class Corridor(")
    monkeypatch.setitem(envs.ENVS, "corridor", page["Corridor"].make)
    monkeypatch.setitem(humans.HUMANS, "walking", lambda human_spec, env, params, seeds: page["WalkingHuman"]())

    base = specs.load("experiments/grid_5.yaml", "smoke")
    # The page's spec models would be in model/spec.py's unions; here they are built directly.
    spec = base.model_copy(update={"env": page["CorridorEnvSpec"](kind="corridor"),
                                   "human": page["WalkingHumanSpec"](kind="walking")})
    trainer = make_trainer(spec)
    assert isinstance(trainer.env, page["Corridor"]) and isinstance(trainer.env, Environment)
    state, metrics = jax.jit(trainer.epoch)(trainer.init(0))
    assert int(state.epoch) == 1 and np.isfinite(float(metrics["critic_loss"]))
    assert 0.0 <= float(metrics["return"]) <= spec.env.episode_steps
    # The walking human reaches the goal only through the door the robot holds open.
    env = trainer.env
    shut, held = env.reset(None), env.reset(None)
    for _ in range(env.length):
        shut, _ = env.step(shut, 0, 1)
        held, _ = env.step(held, 1, 1)
    assert int(shut.human) == env.length // 2 - 1 and int(held.human) == env.length - 1
    _evaluated_and_drawn(trainer, state, metrics, tmp_path / "corridor.png")
