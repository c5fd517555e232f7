"""Episode-structured replay buffer (a pure pytree with `init`, `add`, `sample`).

Episodes have a fixed length T, so the buffer holds whole episodes: observations
[E, T + 1, ...] (the last one is the state after the final step) and per-step actions and
rewards [E, T]. This makes the two lookups that need episode boundaries exact and cheap:
- the next observation of step t is obs[e, t + 1], and `done` is true only at t = T - 1;
- the future state g is obs[e, min(t + K, T)] with K ~ Geometric(1 - future_gamma) on
  {1, 2, ...}: never in another episode (clipped to the episode's last state).
The original code (docs/paper-facts.md) kept a flat ring of transitions whose `done` was true only for the newest
row, so its Q-targets bootstrapped across episode ends; docs/choices.md says more.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class Buffer(NamedTuple):
    obs: jax.Array  # [E, T+1, *obs_shape]
    robot_action: jax.Array  # int32[E, T]
    human_action: jax.Array  # int32[E, T]
    reward: jax.Array  # float32[E, T]
    ptr: jax.Array  # int32[]: next episode slot
    count: jax.Array  # int32[]: episodes held


class Episodes(NamedTuple):
    """A batch of n complete episodes, as collected by the rollout."""

    obs: jax.Array  # [n, T+1, *obs_shape]
    robot_action: jax.Array  # [n, T]
    human_action: jax.Array  # [n, T]
    reward: jax.Array  # [n, T]


class Batch(NamedTuple):
    obs: jax.Array
    next_obs: jax.Array
    future_obs: jax.Array
    robot_action: jax.Array
    human_action: jax.Array
    reward: jax.Array  # the environment's reward (never shown to ESR; used by metrics and oracles)
    done: jax.Array  # float32: 1 on an episode's last step
    offset: jax.Array  # int32: future index - t (K after clipping)


def init(capacity_episodes: int, episode_steps: int, obs_shape, obs_dtype) -> Buffer:
    e, t = capacity_episodes, episode_steps
    return Buffer(
        obs=jnp.zeros((e, t + 1, *obs_shape), obs_dtype),
        robot_action=jnp.zeros((e, t), jnp.int32),
        human_action=jnp.zeros((e, t), jnp.int32),
        reward=jnp.zeros((e, t), jnp.float32),
        ptr=jnp.zeros((), jnp.int32),
        count=jnp.zeros((), jnp.int32),
    )


def add(buf: Buffer, episodes: Episodes) -> Buffer:
    capacity = buf.obs.shape[0]
    n = episodes.obs.shape[0]
    slots = (buf.ptr + jnp.arange(n)) % capacity
    return Buffer(
        obs=buf.obs.at[slots].set(episodes.obs.astype(buf.obs.dtype)),
        robot_action=buf.robot_action.at[slots].set(episodes.robot_action),
        human_action=buf.human_action.at[slots].set(episodes.human_action),
        reward=buf.reward.at[slots].set(episodes.reward),
        ptr=(buf.ptr + n) % capacity,
        count=jnp.minimum(buf.count + n, capacity),
    )


def post_step_view(buf: Buffer) -> Buffer:
    """The buffer as the published Overcooked code pairs it: row t holds the observation after
    step t, o_{t+1}, with the actions a_t that led to it (docs/choices.md). Every lookup then
    shifts by one step: next of row t is o_{t+2}, a future o_{t+1+K}. The episode's last row
    keeps o_T (the original stored the next episode's first observation there)."""
    return buf._replace(obs=jnp.concatenate([buf.obs[:, 1:], buf.obs[:, -1:]], axis=1))


def episodes_per_call(steps: int) -> int:
    """How many stored episodes `map_episodes` takes at once: about 256 transitions, the size
    of a training batch, so that intermediates stay in cache."""
    return max(1, 256 // steps)


def map_episodes(fn, episodes, steps: int):
    """fn over the stored episodes (leading axis of every leaf), a few at a time."""
    return jax.lax.map(fn, episodes, batch_size=episodes_per_call(steps))


def geometric_offsets(key: jax.Array, shape, gamma: float) -> jax.Array:
    """K ~ Geometric(1 - gamma) on {1, 2, ...}: P(K = k) = (1 - gamma) gamma^(k - 1)."""
    if gamma <= 0.0:
        return jnp.ones(shape, jnp.int32)
    u = jax.random.uniform(key, shape, minval=jnp.finfo(jnp.float32).tiny, maxval=1.0)
    k = 1 + jnp.floor(jnp.log(u) / jnp.log(gamma))
    return jnp.minimum(k, 2**30).astype(jnp.int32)


class Index(NamedTuple):
    """Where a batch comes from: episode slot e, step t and future index (t + K, clipped)."""

    episode: jax.Array  # int32[B]
    t: jax.Array  # int32[B]
    future: jax.Array  # int32[B]


def sample_index(buf: Buffer, key: jax.Array, batch_size: int, future_gamma: float, episode_group: int = 1) -> Index:
    """Uniform transitions with geometric futures. With episode_group = k > 1 the batch is
    ceil(B / k) uniform episodes, k uniform steps from each (the last group cut short), so
    that transitions of one episode sit next to each other in the batch."""
    k_ep, k_t, k_future = jax.random.split(key, 3)
    steps = buf.robot_action.shape[1]
    groups = -(-batch_size // episode_group)
    episode = jax.random.randint(k_ep, (groups,), 0, jnp.maximum(buf.count, 1))
    episode = jnp.repeat(episode, episode_group)[:batch_size]
    t = jax.random.randint(k_t, (batch_size,), 0, steps)
    future = jnp.minimum(t + geometric_offsets(k_future, (batch_size,), future_gamma), steps)
    return Index(episode=episode, t=t, future=future)


def gather(buf: Buffer, idx: Index) -> Batch:
    steps = buf.robot_action.shape[1]
    episode, t, future = idx
    return Batch(
        obs=buf.obs[episode, t],
        next_obs=buf.obs[episode, t + 1],
        future_obs=buf.obs[episode, future],
        robot_action=buf.robot_action[episode, t],
        human_action=buf.human_action[episode, t],
        reward=buf.reward[episode, t],
        done=(t == steps - 1).astype(jnp.float32),
        offset=future - t,
    )


class Sampler(NamedTuple):
    """How a run samples its buffer, bound once: the batch size, the discount of the future
    states drawn with each transition, and the transitions drawn from each sampled episode."""

    batch_size: int
    future_gamma: float
    episode_group: int = 1

    def index(self, buf: Buffer, key: jax.Array) -> Index:
        return sample_index(buf, key, self.batch_size, self.future_gamma, self.episode_group)

    def batch(self, buf: Buffer, key: jax.Array) -> Batch:
        return gather(buf, self.index(buf, key))


def sample(buf: Buffer, key: jax.Array, batch_size: int, future_gamma: float, episode_group: int = 1) -> Batch:
    return gather(buf, sample_index(buf, key, batch_size, future_gamma, episode_group))
