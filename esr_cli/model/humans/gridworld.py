"""The gridworld's noisy-greedy human (Du et al. 2020; docs/environments.md).

With probability 1 - noise the human takes the action whose resulting cell (walls and blocks
taken into account) is closest to its goal in Euclidean distance, with stay's distance counted
0.1 smaller so that a blocked human waits; otherwise a uniformly random action. The two
choices use independent random keys (the original drew both from one key: see docs/choices.md).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from esr_cli.model.envs.gridworld import NUM_HUMAN_ACTIONS, STAY, GridState, Gridworld

STAY_BONUS = 0.1


class NoisyGreedyHuman(NamedTuple):
    env: Gridworld
    noise: float
    learns: bool = False
    has_state: bool = False
    metric_names: tuple = ()

    def greedy_action(self, state: GridState) -> jax.Array:
        targets = jax.vmap(lambda a: self.env.human_target(state, a))(jnp.arange(NUM_HUMAN_ACTIONS))
        dist = jnp.linalg.norm((targets - state.goal[None, :]).astype(jnp.float32), axis=-1)
        dist = dist.at[STAY].add(-STAY_BONUS)
        return jnp.argmin(dist).astype(jnp.int32)

    def action_probs(self, state: GridState) -> jax.Array:
        """float32[5]: the policy's exact action distribution (for exact analyses and tests)."""
        greedy = jax.nn.one_hot(self.greedy_action(state), NUM_HUMAN_ACTIONS)
        return (1.0 - self.noise) * greedy + self.noise / NUM_HUMAN_ACTIONS

    def act(self, key: jax.Array, state: GridState) -> jax.Array:
        k_explore, k_random = jax.random.split(key)
        explore = jax.random.uniform(k_explore) < self.noise
        random_action = jax.random.randint(k_random, (), 0, NUM_HUMAN_ACTIONS, dtype=jnp.int32)
        return jnp.where(explore, random_action, self.greedy_action(state))
