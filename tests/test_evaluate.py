"""Evaluation in bounded chunks: any number of episodes, memory of at most EVAL_BATCH
trajectories per program."""

import numpy as np

from esr_cli import spec as specs
from esr_cli.core import evaluate as ev, loop
from esr_cli.core.train import make_trainer


def test_many_episodes_run_in_chunks_whose_first_is_the_one_program_evaluation(monkeypatch):
    trainer = make_trainer(specs.load("experiments/grid_2_random.yaml", "smoke", ["env.episode_steps=8"]))
    seeds = (0, 1)
    state = loop.initial_state(trainer, seeds)
    (mode,) = ev.policy_modes(trainer)
    alone = ev.evaluate(trainer, state, 2, seeds)[mode]
    monkeypatch.setattr(ev, "EVAL_BATCH", 4)  # 2 seeds: 2 episodes per seed per program
    chunked = ev.evaluate(trainer, state, 6, seeds)[mode]
    assert chunked["return"].shape == chunked["success"].shape == (2, 6)
    # chunk 0 is what a 2-episode evaluation plays: same keys, same program
    np.testing.assert_array_equal(chunked["return"][:, :2], alone["return"])
    for a, b in zip(jax_leaves(chunked["states"]), jax_leaves(alone["states"])):
        np.testing.assert_array_equal(a, b)  # the GIF's trajectories come from chunk 0 alone


def jax_leaves(tree):
    import jax

    return [np.asarray(x) for x in jax.tree.leaves(tree)]
