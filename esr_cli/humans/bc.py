"""The Overcooked human: behavioural cloning on the 2019 human-human trials.

Policy: an MLP (64-64 tanh, orthogonal init) on the flattened (H, W, 26) observation from the
human's own view (agent_1 in play; both players' views in training), urgency channel zeroed:
the human games last about 1,200 steps, so the data cannot say what 40 steps before the end of
a 400-step episode looks like. The human samples its actions (an argmax policy freezes).

About 72% of the recorded actions are 'stay'. Stay samples get weight `stay_weight` (0.1 by
default) in the cross-entropy: with weight 1 the clone mostly stays and BC+BC self-play
scores about half the humans' own rate.

The clone in play, and its co-adaptation (`adapt: true`), are humans/policy_human.py's.
"""

from __future__ import annotations

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
