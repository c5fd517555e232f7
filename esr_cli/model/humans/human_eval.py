"""A human policy's sparse return with a fixed partner, over whole episodes (vmapped, jitted).

The human plays `env.human_agent` from its own view (`observe_human`), sampling from
`logits_fn(params, obs)`; the partner plays the robot's seat:

- `random`: uniform over the 6 actions;
- `stay`: always 'stay' (what the human scores alone, with a partner in the way);
- `self`: the same policy from the robot seat's view (self-play).

Keys (a plain step-by-step rollout with the same keys gives the same episode; the tests
check it): episode i uses `jax.random.split(key, episodes)[i]`, split into (reset key, steps
key); step t uses `jax.random.split(steps key, episode_steps)[t]`, split into (human key,
partner key).
"""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from esr_cli.model.envs.overcooked import NUM_ACTIONS, STAY, Overcooked

PARTNERS = ("random", "stay", "self")


def partner_action(partner: str, logits_fn: Callable, params, key, obs) -> jax.Array:
    """The partner's action from its own observation."""
    if partner == "random":
        return jax.random.randint(key, (), 0, NUM_ACTIONS)
    if partner == "stay":
        return jnp.int32(STAY)
    if partner == "self":
        return jax.random.categorical(key, logits_fn(params, obs))
    raise ValueError(f"unknown partner {partner!r}; known: {', '.join(PARTNERS)}")


def episode_fn(env: Overcooked, logits_fn: Callable, partner: str) -> Callable:
    """-> episode(params, key) -> (sparse return, final env state)."""
    if partner not in PARTNERS:
        raise ValueError(f"unknown partner {partner!r}; known: {', '.join(PARTNERS)}")

    def episode(params, key):
        k_reset, k_steps = jax.random.split(key)

        def step(state, key):
            k_human, k_partner = jax.random.split(key)
            human = jax.random.categorical(k_human, logits_fn(params, env.observe_human(state)))
            other = partner_action(partner, logits_fn, params, k_partner, env.observe(state))
            state, reward = env.step(state, other.astype(jnp.int32), human.astype(jnp.int32))
            return state, reward

        state, rewards = jax.lax.scan(step, env.reset(k_reset), jax.random.split(k_steps, env.episode_steps))
        return rewards.sum(), state

    return episode


@functools.cache
def _evaluator(env: Overcooked, logits_fn: Callable, partner: str):
    return jax.jit(jax.vmap(episode_fn(env, logits_fn, partner), in_axes=(None, 0)))


def episodes(env: Overcooked, logits_fn: Callable, params, partner: str, n: int, key):
    """n episodes in one jitted, vmapped program -> (sparse returns [n], final env states [n, ...])."""
    return _evaluator(env, logits_fn, partner)(params, jax.random.split(key, n))


def episode_returns(env: Overcooked, logits_fn: Callable, params, partner: str, n: int, key) -> np.ndarray:
    """Sparse returns [n] of the human (`logits_fn`, `params`) with `partner`, over
    env.episode_steps-step episodes (400 in the paper's setting)."""
    return np.asarray(episodes(env, logits_fn, params, partner, n, key)[0])


def evaluate(env: Overcooked, logits_fn: Callable, params, n: int, key, partners=PARTNERS) -> dict:
    """{partner: {"mean", "se", "returns"}} over n episodes with each partner (the same
    episode keys for every partner)."""
    out = {}
    for partner in partners:
        r = episode_returns(env, logits_fn, params, partner, n, key)
        se = float(r.std(ddof=1) / np.sqrt(len(r))) if len(r) > 1 else 0.0
        out[partner] = {"mean": float(r.mean()), "se": se, "returns": r.tolist()}
    return out


def partner_returns(env: Overcooked, logits_fn: Callable, params, episodes: int, seed: int) -> dict:
    """{partner: {mean, se, episodes}} (rounded, as artifacts record them) for every partner."""
    table = evaluate(env, logits_fn, params, episodes, jax.random.PRNGKey(seed))
    return {p: {"mean": round(v["mean"], 3), "se": round(v["se"], 3), "episodes": episodes} for p, v in table.items()}
