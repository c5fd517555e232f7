"""Evaluation in bounded chunks: any number of episodes, at most EVAL_STEPS environment steps
(episodes x seeds x episode length) per program."""

import numpy as np
import pytest

from esr_cli.common import specs
from esr_cli.model import evaluate as ev
from esr_cli.model.train import make_trainer
from esr_cli.runner import loop


@pytest.mark.slow
def test_many_episodes_run_in_chunks_whose_first_is_the_one_program_evaluation(monkeypatch):
    trainer = make_trainer(specs.load("experiments/grid_2_random.yaml", "smoke", ["env.episode_steps=8"]))
    seeds = (0, 1)
    state = loop.initial_state(trainer, seeds)
    (mode,) = ev.policy_modes(trainer)
    alone = ev.evaluate(trainer, state, 2, seeds)[mode]
    monkeypatch.setattr(ev, "EVAL_STEPS", 2 * 2 * 8)  # 2 seeds of 8-step episodes: 2 episodes per seed per program
    seen = []
    chunked = ev.evaluate(trainer, state, 6, seeds, progress=lambda done, total: seen.append((done, total)))[mode]
    assert seen == [(2, 6), (4, 6), (6, 6)]  # one report per program
    assert chunked["return"].shape == chunked["success"].shape == (2, 6)
    # chunk 0 is what a 2-episode evaluation plays: same keys, same program
    np.testing.assert_array_equal(chunked["return"][:, :2], alone["return"])
    for a, b in zip(jax_leaves(chunked["states"]), jax_leaves(alone["states"])):
        np.testing.assert_array_equal(a, b)  # the GIF's trajectories come from chunk 0 alone


def jax_leaves(tree):
    import jax

    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def test_a_program_holds_fewer_episodes_the_longer_they_are():
    assert ev.episodes_per_program(50, 1) == 2048  # the gridworld's episodes: as many as ever
    assert ev.episodes_per_program(400, 1) == 256  # Overcooked's: the same number of steps
    assert ev.episodes_per_program(50, 4) == 512
    assert ev.episodes_per_program(10_000, 20) == 1  # never none
