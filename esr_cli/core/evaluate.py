"""Evaluation of a trained robot with its human: N episodes per seed and policy mode.

Modes: `sample` (the Boltzmann policy the robot trains with) and `greedy` (argmax Q); a
method that learns no policy is evaluated as `random`. All seeds run in one vmapped program.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from esr_cli.core.train import TrainState, Trainer

EVAL_KEY_SALT = 2**20  # evaluation keys never coincide with training keys


def policy_modes(trainer: Trainer) -> tuple[str, ...]:
    if trainer.acts_by_rule:
        return ("rule",)
    return ("sample", "greedy") if trainer.method.learns_policy else ("random",)


def evaluate(trainer: Trainer, state: TrainState, episodes: int, seeds) -> dict:
    """-> {mode: {"return": float[seeds, episodes], "success": bool[seeds, episodes]}} and one rollout."""
    out = {}
    keys = jax.vmap(lambda s: jax.random.PRNGKey(s + EVAL_KEY_SALT))(jnp.asarray(seeds, jnp.int32))
    for mode in policy_modes(trainer):

        def run(lstate, hstate, key, mode=mode):
            roll = trainer.rollout(lstate, key, episodes, mode, hstate=hstate)
            return roll.episodes.reward.sum(axis=1), roll.states

        returns, states = jax.jit(jax.vmap(run))(state.learner, state.human, keys)
        returns = np.asarray(returns)
        out[mode] = {"return": returns, "success": returns > 0, "states": states}
    return out


def episode_states(states, seed_index: int, episode: int):
    """The env-state trajectory [T+1] of one evaluation episode."""
    return jax.tree.map(lambda x: np.asarray(x[seed_index, :, episode]), states)
