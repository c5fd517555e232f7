"""The Overcooked human: behavioural cloning on the 2019 human-human trials.

Policy: an MLP (64-64 tanh, orthogonal init) on the flattened (H, W, 26) observation from the
human's own view (agent_1 in play; both players' views in training), urgency channel zeroed:
the human games last about 1,200 steps, so the data cannot say what 40 steps before the end of
a 400-step episode looks like. The human samples its actions (an argmax policy freezes).

About 72% of the recorded actions are 'stay'. Stay samples get weight `stay_weight` (0.1 by
default) in the cross-entropy: with weight 1 the clone mostly stays and BC+BC self-play
scores about half the humans' own rate.

Co-adaptation (`adapt: true`): the human keeps learning alongside the robot, by
policy gradient (REINFORCE with reward-to-go, discount `adapt_gamma`, a per-step mean
baseline) on the shared reward of each epoch's episodes, regularised towards the cloned
policy by `adapt_kl` x KL(pi_BC || pi) on the states it visited.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from esr_cli.envs.overcooked import NUM_ACTIONS, STAY, URGENCY_CHANNEL, Overcooked
from esr_cli.networks import MLP


def prepare(obs: jax.Array) -> jax.Array:
    """float32[..., H, W, 26] with the urgency channel zeroed (see the module docstring)."""
    x = obs.astype(jnp.float32)
    return x.at[..., URGENCY_CHANNEL].set(0.0)


def policy_net(hidden) -> MLP:
    # A small output scale starts the policy near uniform (as PPO-style policy heads do).
    return MLP(hidden=tuple(hidden), out=NUM_ACTIONS, out_scale=0.01)


def logits_fn(hidden):
    net = policy_net(hidden)
    return lambda params, obs: net.apply(params, prepare(obs))


# ---------------------------------------------------------------- cloning
def weighted_ce(logits, actions, stay_weight: float):
    """Mean cross-entropy with stay samples weighted by `stay_weight` (normalised weights)."""
    w = jnp.where(actions == STAY, stay_weight, 1.0)
    nll = -jnp.take_along_axis(jax.nn.log_softmax(logits), actions[:, None].astype(jnp.int32), axis=1)[:, 0]
    return jnp.sum(w * nll) / jnp.sum(w)


def train_bc(obs: np.ndarray, actions: np.ndarray, spec, seed: int = 0):
    """Fit the cloned policy; -> (params, per-epoch mean training losses)."""
    net, apply = policy_net(spec.hidden), logits_fn(spec.hidden)
    key = jax.random.PRNGKey(seed)
    k_init, key = jax.random.split(key)
    params = net.init(k_init, prepare(jnp.asarray(obs[:1])))
    opt = optax.adam(spec.lr)
    opt_state = opt.init(params)
    n, bs = len(actions), min(spec.batch_size, len(actions))
    steps = n // bs
    obs_j, act_j = jnp.asarray(obs), jnp.asarray(actions.astype(np.int32))

    @jax.jit
    def epoch(carry, key):
        def step(carry, idx):
            params, opt_state = carry
            loss, grads = jax.value_and_grad(lambda p: weighted_ce(apply(p, obs_j[idx]), act_j[idx], spec.stay_weight))(params)
            updates, opt_state = opt.update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), loss

        order = jax.random.permutation(key, n)[: steps * bs].reshape(steps, bs)
        carry, losses = jax.lax.scan(step, carry, order)
        return carry, losses.mean()

    carry, losses = (params, opt_state), []
    for k in jax.random.split(key, spec.epochs):
        carry, loss = epoch(carry, k)
        losses.append(float(loss))
    return carry[0], losses


def accuracies(params, hidden, obs: np.ndarray, actions: np.ndarray) -> dict:
    """Argmax accuracy on all samples and on the non-stay samples; mean log-likelihood."""
    apply = jax.jit(logits_fn(hidden))
    logits = np.concatenate([np.asarray(apply(params, jnp.asarray(obs[i : i + 8192]))) for i in range(0, len(obs), 8192)])
    pred = logits.argmax(-1)
    moving = actions != STAY
    logp = jax.nn.log_softmax(logits)[np.arange(len(actions)), actions.astype(int)]
    return {
        "accuracy": round(float((pred == actions).mean()), 4),
        "non_stay_accuracy": round(float((pred[moving] == actions[moving]).mean()), 4),
        "stay_fraction": round(float((~moving).mean()), 4),
        "predicted_stay_fraction": round(float((pred == STAY).mean()), 4),
        "log_likelihood": round(float(np.mean(logp)), 4),
        "samples": int(len(actions)),
    }


def selfplay_returns(env: Overcooked, params, hidden, episodes: int, seed: int = 0) -> np.ndarray:
    """BC+BC: both agents sample from the cloned policy for whole episodes; -> returns[episodes]."""
    apply = logits_fn(hidden)

    def episode(key):
        k_reset, k_steps = jax.random.split(key)
        state = env.reset(k_reset)

        def step(state, key):
            k0, k1 = jax.random.split(key)
            a0 = jax.random.categorical(k0, apply(params, env.observe(state)))
            a1 = jax.random.categorical(k1, apply(params, env.observe_human(state)))
            state, reward = env.step_joint(state, a0, a1)
            return state, reward

        _, rewards = jax.lax.scan(step, state, jax.random.split(k_steps, env.episode_steps))
        return rewards.sum()

    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    return np.asarray(jax.jit(jax.vmap(episode))(keys))


# ---------------------------------------------------------------- the human in play
class AdaptState(NamedTuple):
    params: Any
    opt_state: Any


class BCHuman(NamedTuple):
    """The cloned human; with `adapt`, it also learns (see the module docstring).

    Fixed: `act(key, env_state)`. Learning: `learns` is True, `init(key) -> AdaptState`,
    `act_with(hstate, key, env_state)` and `update(hstate, states, human_actions, rewards,
    key) -> (hstate, metrics)` over a batch of whole episodes.
    """

    env: Overcooked
    params: Any  # the cloned policy's parameters (constants)
    hidden: tuple
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
        return logits_fn(self.hidden)(params, self.env.observe_human(env_state))

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
        apply = logits_fn(self.hidden)

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
        grads, (pg, kl, ent) = jax.grad(self.loss, has_aux=True)(hstate.params, obs, human_actions.T, rewards.T)
        updates, opt_state = self.optimizer.update(grads, hstate.opt_state, hstate.params)
        params = optax.apply_updates(hstate.params, updates)
        return AdaptState(params=params, opt_state=opt_state), {"human_pg_loss": pg, "human_kl_to_bc": kl, "human_entropy": ent}
