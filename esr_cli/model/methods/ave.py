"""AvE, Assistance via Empowerment (Du et al. 2020), as a reward for the shared soft-Q learner.

The robot's reward at a state s is a proxy for the human's empowerment there: the log
variance of where the human ends up after M rollouts of L uniformly random human actions from
s, the robot staying meanwhile (docs/baselines.md). Everything is batched: the B x M x L
rollouts of a critic batch are one vmapped scan (the environment's `random_human_futures`).

Variants (`method.variant`, docs/baselines.md):
- fixed (default): human actions uniform over the human's actions; features = the human's
  position; reward = log(mean over coordinates of the variance across rollouts + 1e-3).
- original: as the published code (docs/paper-facts.md) computed it. Gridworld: actions drawn from [0, robot action
  count) and clamped to the last human action ('stay'), so most rollout steps stay; features =
  all coordinates of the state vector [human, blocks] of all rollouts, one variance over them
  all. Overcooked: the published rollouts never advance the state, so each is one uniform human
  action from s (the robot staying); features = the human's whole observation; reward =
  log(one variance over every element of every rollout's observation), no floor.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from esr_cli.model.methods.base import no_update, stateless_init

VARIANCE_FLOOR = 1e-3


def log_variance_fixed(futures: jax.Array) -> jax.Array:
    """futures float[M, F] -> log(mean_f var_m futures + 1e-3)."""
    return jnp.log(jnp.var(futures, axis=0).mean() + VARIANCE_FLOOR)


def log_variance_original(futures: jax.Array, static_coords: jax.Array) -> jax.Array:
    """The published features: one variance over every coordinate of every rollout's state
    vector [human (2), blocks (2N)], the blocks being where they are (the robot stays)."""
    m = futures.shape[0]
    vectors = jnp.concatenate([futures, jnp.broadcast_to(static_coords, (m, static_coords.shape[0]))], axis=1)
    return jnp.log(jnp.var(vectors) + VARIANCE_FLOOR)


def log_variance_whole_observation(futures: jax.Array) -> jax.Array:
    """The published Overcooked features: futures float[M, F] (each rollout's human observation)
    -> log(variance over all M x F elements)."""
    return jnp.log(jnp.var(futures))


class AvE(NamedTuple):
    env: object
    spec: object  # AvEMethodSpec
    env_kind: str = "gridworld"  # which published AvE `variant: original` reproduces

    updates_per_epoch: int = 0
    learns_policy: bool = True
    metric_names: tuple = ()
    all_metric_names = ()  # not a field: the same for every spec
    acts_by_rule: bool = False
    has_reward_table: bool = False

    init = stateless_init
    update = no_update

    @classmethod
    def from_spec(cls, spec, env, human):
        return cls(env=env, spec=spec.method, env_kind=spec.env.kind)

    @property
    def published_overcooked(self) -> bool:
        return self.spec.variant == "original" and self.env_kind == "overcooked"

    def rollout_actions(self, key, batch_size: int) -> jax.Array:
        if self.published_overcooked:  # one step: the published rollouts never advance the state
            return jax.random.randint(key, (batch_size, self.spec.num_rollouts, 1), 0, self.env.num_human_actions, dtype=jnp.int32)
        shape = (batch_size, self.spec.num_rollouts, self.spec.rollout_length)
        if self.spec.variant == "original":
            raw = jax.random.randint(key, shape, 0, self.env.num_robot_actions)
            return jnp.minimum(raw, self.env.num_human_actions - 1).astype(jnp.int32)
        return jax.random.randint(key, shape, 0, self.env.num_human_actions, dtype=jnp.int32)

    def state_reward(self, obs: jax.Array, key) -> jax.Array:
        """float32[B]: the AvE proxy at each observed state."""
        actions = self.rollout_actions(key, obs.shape[0])
        futures = jax.vmap(self.env.random_human_futures)(obs, actions)  # [B, M, F]
        if self.published_overcooked:
            return jax.vmap(log_variance_whole_observation)(futures)
        if self.spec.variant == "original":
            coords = jax.vmap(self.env.block_coordinates)(obs).astype(jnp.float32)
            return jax.vmap(log_variance_original)(futures, coords.reshape(obs.shape[0], -1))
        return jax.vmap(log_variance_fixed)(futures)

    def reward(self, state, batch, key):
        # The reward of the transition from s is the proxy at s, as in the original code.
        return self.state_reward(batch.obs, key)
