"""Evaluation of a trained robot with its human: N episodes per seed and policy mode.

Modes: `sample` (the Boltzmann policy the robot trains with) and `greedy` (argmax Q); a
method that learns no policy is evaluated as `random`. All seeds run in one vmapped program.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from esr_cli.model.train import Trainer, TrainState

EVAL_KEY_SALT = 2**20  # evaluation keys never coincide with training keys


def policy_modes(trainer: Trainer) -> tuple[str, ...]:
    if trainer.acts_by_rule:
        return ("rule",)
    return ("sample", "greedy") if trainer.method.learns_policy else ("random",)


# Environment steps (episodes x seeds x episode length) in one program: 2,048 gridworld
# episodes of 50 steps. Memory stays bounded whatever `--episodes` (up to a million) and the
# episode length ask for, and so does the time between two programs, the only moments at
# which Python can act on Ctrl-C or SIGTERM. Fewer steps run as one program.
EVAL_STEPS = 2048 * 50


def episodes_per_program(episode_steps: int, n_seeds: int) -> int:
    return max(1, EVAL_STEPS // (episode_steps * n_seeds))


def evaluate(trainer: Trainer, state: TrainState, episodes: int, seeds,
             progress: Callable[[int, int], None] | None = None) -> dict:
    """-> {mode: {"return": float[seeds, episodes], "success": bool[seeds, episodes],
    "states": the first chunk's env-state trajectories, "steps": its (robot actions, human
    actions, rewards), each [seeds, episodes, T]}}. Episodes run in chunks of at most
    `episodes_per_program` per seed; chunk c > 0 draws from the seed's key folded with c.
    `progress(done, total)` is called after each chunk, in episodes per seed over all modes."""
    out = {}
    keys = jax.vmap(lambda s: jax.random.PRNGKey(s + EVAL_KEY_SALT))(jnp.asarray(seeds, jnp.int32))
    chunk = episodes_per_program(trainer.env.episode_steps, len(seeds))
    sizes = [min(chunk, episodes - start) for start in range(0, episodes, chunk)]
    modes = policy_modes(trainer)
    for m, mode in enumerate(modes):

        def run(lstate, hstate, key, n, mode=mode):
            roll = trainer.rollout(lstate, key, n, mode, hstate=hstate)
            steps = (roll.episodes.robot_action, roll.episodes.human_action, roll.episodes.reward)
            return roll.episodes.reward.sum(axis=1), (roll.states, steps)

        program = jax.jit(jax.vmap(run, in_axes=(0, 0, 0, None)), static_argnums=3)  # one compile per chunk size
        parts, states, done = [], None, m * episodes
        for c, n in enumerate(sizes):
            chunk_keys = keys if c == 0 else jax.vmap(lambda k, c=c: jax.random.fold_in(k, c))(keys)
            returns, (chunk_states, chunk_steps) = program(state.learner, state.human, chunk_keys, n)
            parts.append(np.asarray(returns))
            if c == 0:  # for the GIF; later chunks' trajectories are dropped
                states, steps = chunk_states, chunk_steps
            done += n
            if progress is not None:
                progress(done, len(modes) * episodes)
        returns = np.concatenate(parts, axis=1)
        out[mode] = {"return": returns, "success": returns > 0, "states": states, "steps": steps}
    return out


def episode_states(states, seed_index: int, episode: int):
    """The env-state trajectory [T+1] of one evaluation episode."""
    return jax.tree.map(lambda x: np.asarray(x[seed_index, :, episode]), states)


def episode_steps(steps, seed_index: int, episode: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(robot actions [T], human actions [T], rewards [T]) of one evaluation episode."""
    return tuple(np.asarray(x[seed_index, episode]) for x in steps)
