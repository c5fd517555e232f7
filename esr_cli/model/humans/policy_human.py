"""A policy network in the human's seat of Overcooked, fixed or co-adapting.

Co-adaptation (`adapt: true`): the human keeps learning alongside the robot, by policy
gradient (REINFORCE with reward-to-go, discount `adapt_gamma`, a per-step mean baseline) on
the shared reward of each epoch's episodes, regularised towards its starting policy by
`adapt_kl` x KL(pi_start || pi) on the states it visited.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax

from esr_cli.model.envs.overcooked import Overcooked
from esr_cli.model.gradient import gradient_step


class AdaptState(NamedTuple):
    params: Any
    opt_state: Any


class PolicyHuman(NamedTuple):
    """A policy network in the human's seat, sampling from `logits(params, obs)` on its own
    view: a BC clone (humans/bc.py) or a PPO-trained human (humans/ppo.py). With `adapt`, it
    also learns (see the module docstring).

    Fixed: `act(key, env_state)`. Learning: `learns` is True, `init(key) -> AdaptState`,
    `act_with(hstate, key, env_state)` and `update(hstate, states, human_actions, rewards,
    key) -> (hstate, metrics)` over a batch of whole episodes.
    """

    env: Overcooked
    params: Any  # the policy's parameters (constants)
    logits_fn: Callable  # (params, obs [..., H, W, 26]) -> logits [..., 6]
    adapt: bool = False
    adapt_lr: float = 1e-4
    adapt_kl: float = 1.0
    adapt_gamma: float = 0.99
    # One clone per training seed (human.per_seed): their parameters stacked in `seeds` order;
    # each seed's training state then holds its own (`init`), and `params` is the first.
    per_seed_params: Any = None
    seeds: tuple = ()

    @property
    def learns(self) -> bool:
        return self.adapt

    @property
    def has_state(self) -> bool:
        return self.adapt or self.per_seed_params is not None

    @property
    def metric_names(self) -> tuple[str, ...]:
        return ("human_pg_loss", "human_kl_to_bc", "human_entropy") if self.adapt else ()

    def logits(self, params, env_state) -> jax.Array:
        return self.logits_fn(params, self.env.observe_human(env_state))

    def act(self, key, env_state) -> jax.Array:
        return jax.random.categorical(key, self.logits(self.params, env_state)).astype(jnp.int32)

    def action_probs(self, env_state) -> jax.Array:
        return jax.nn.softmax(self.logits(self.params, env_state))

    # ---- co-adaptation
    @property
    def optimizer(self):
        return optax.adam(self.adapt_lr)

    def init(self, key, seed) -> AdaptState:
        """This seed's human: its own clone (per seed) or the one clone, and, if it adapts, its
        optimiser state. `seed` may be traced (the runner vmaps init over the seeds)."""
        if self.per_seed_params is None:
            params = jax.tree.map(jnp.asarray, self.params)
        else:
            index = jnp.argmax(jnp.asarray(self.seeds) == seed)
            params = jax.tree.map(lambda stacked: jnp.asarray(stacked)[index], self.per_seed_params)
        return AdaptState(params=params, opt_state=self.optimizer.init(params) if self.adapt else ())

    def act_with(self, hstate: AdaptState, key, env_state) -> jax.Array:
        return jax.random.categorical(key, self.logits(hstate.params, env_state)).astype(jnp.int32)

    def loss(self, params, obs, actions, rewards, kl_weight=None):
        """obs [T, n, H, W, 26], actions [T, n], rewards [T, n] -> (loss, (pg, kl, entropy)).
        kl_weight: the KL's weight (default adapt_kl)."""
        apply = self.logits_fn

        def to_go(carry, r):
            carry = r + self.adapt_gamma * carry
            return carry, carry

        _, returns = jax.lax.scan(to_go, jnp.zeros(rewards.shape[1:]), rewards[::-1])
        returns = returns[::-1]
        advantage = returns - returns.mean(axis=1, keepdims=True)  # per-step mean baseline
        logp = jax.nn.log_softmax(apply(params, obs))
        logp_bc = jax.nn.log_softmax(apply(self.params, obs))
        taken = jnp.take_along_axis(logp, actions[..., None].astype(jnp.int32), axis=-1)[..., 0]
        pg = -jnp.mean(taken * jax.lax.stop_gradient(advantage))
        kl = jnp.mean(jnp.sum(jnp.exp(logp_bc) * (logp_bc - logp), axis=-1))
        entropy = -jnp.mean(jnp.sum(jnp.exp(logp) * logp, axis=-1))
        kl_weight = self.adapt_kl if kl_weight is None else kl_weight
        return pg + kl_weight * kl, (pg, kl, entropy)

    def update(self, hstate: AdaptState, states, human_actions, rewards, key):
        """One gradient step on one epoch's episodes. states: env states [T(+1), n, ...]
        (the first T are used), human_actions and rewards [n, T]."""
        steps = human_actions.shape[1]
        obs = jax.vmap(jax.vmap(self.env.observe_human))(jax.tree.map(lambda a: a[:steps], states))
        (_, (pg, kl, ent)), params, opt_state = gradient_step(
            lambda p: self.loss(p, obs, human_actions.T, rewards.T), hstate.params, hstate.opt_state, self.optimizer)
        return AdaptState(params=params, opt_state=opt_state), {"human_pg_loss": pg, "human_kl_to_bc": kl, "human_entropy": ent}
