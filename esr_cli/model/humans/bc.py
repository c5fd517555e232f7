"""The Overcooked human: behavioural cloning on the 2019 human-human trials.

Policy (`network`): an MLP (64-64 tanh, orthogonal init) on the flattened (H, W, 26)
observation, or the paper's convolutional actor-critic (humans/conv_actor_critic.py; its policy
tower is cloned, its value tower is kept untrained so that the parameters have the PPO human's
shape). Either reads the human's own view (agent_1 in play; both players' views in training)
with the urgency channel zeroed: the human games last about 1,200 steps, so the data cannot say
what 40 steps before the end of a 400-step episode looks like. The human samples its actions
(an argmax policy freezes).

About 72% of the recorded actions are 'stay'. Stay samples get weight `stay_weight` (0.1 by
default) in the cross-entropy: with weight 1 the clone mostly stays and BC+BC self-play
scores about half the humans' own rate.

The clone in play, and its co-adaptation (`adapt: true`), are humans/policy_human.py's.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from esr_cli.model.envs.overcooked import NUM_ACTIONS, STAY, URGENCY_CHANNEL
from esr_cli.model.gradient import gradient_step
from esr_cli.model.humans import conv_actor_critic
from esr_cli.model.networks import MLP


def prepare(obs: jax.Array) -> jax.Array:
    """float32[..., H, W, 26] with the urgency channel zeroed (see the module docstring)."""
    x = obs.astype(jnp.float32)
    return x.at[..., URGENCY_CHANNEL].set(0.0)


class ClonedPolicy(NamedTuple):
    init: Callable  # (key, one observation [H, W, 26]) -> params
    logits: Callable  # (params, obs [..., H, W, 26]) -> logits [..., 6]


def _mlp(hidden) -> ClonedPolicy:
    # A small output scale starts the policy near uniform (as PPO-style policy heads do).
    net = MLP(hidden=tuple(hidden), out=NUM_ACTIONS, out_scale=0.01)
    return ClonedPolicy(lambda key, obs: net.init(key, prepare(obs)), lambda params, obs: net.apply(params, prepare(obs)))


def _conv(hidden) -> ClonedPolicy:
    del hidden  # the paper's network has one shape (conv_actor_critic.py)
    return ClonedPolicy(
        lambda key, obs: conv_actor_critic.init_params(key, obs.shape[-3], obs.shape[-2]),
        lambda params, obs: conv_actor_critic.policy_logits(params, prepare(obs)),
    )


NETWORKS = {"mlp": _mlp, "conv": _conv}


def cloned_policy(human_spec) -> ClonedPolicy:
    """The BC human's network (`human.network`, `human.hidden`)."""
    return NETWORKS[human_spec.network](tuple(human_spec.hidden))


# ---------------------------------------------------------------- cloning
def weighted_ce(logits, actions, stay_weight: float):
    """Mean cross-entropy with stay samples weighted by `stay_weight` (normalised weights)."""
    w = jnp.where(actions == STAY, stay_weight, 1.0)
    nll = -jnp.take_along_axis(jax.nn.log_softmax(logits), actions[:, None].astype(jnp.int32), axis=1)[:, 0]
    return jnp.sum(w * nll) / jnp.sum(w)


def train_bc(obs: np.ndarray, actions: np.ndarray, spec, seed: int = 0):
    """Fit the cloned policy; -> (params, per-epoch mean training losses)."""
    policy = cloned_policy(spec)
    apply = policy.logits
    key = jax.random.PRNGKey(seed)
    k_init, key = jax.random.split(key)
    params = policy.init(k_init, jnp.asarray(obs[0]))
    opt = optax.adam(spec.lr)
    opt_state = opt.init(params)
    n, bs = len(actions), min(spec.batch_size, len(actions))
    steps = n // bs
    obs_j, act_j = jnp.asarray(obs), jnp.asarray(actions.astype(np.int32))

    @jax.jit
    def epoch(carry, key):
        def step(carry, idx):
            params, opt_state = carry
            (loss, _), params, opt_state = gradient_step(
                lambda p: (weighted_ce(apply(p, obs_j[idx]), act_j[idx], spec.stay_weight), ()), params, opt_state, opt)
            return (params, opt_state), loss

        order = jax.random.permutation(key, n)[: steps * bs].reshape(steps, bs)
        carry, losses = jax.lax.scan(step, carry, order)
        return carry, losses.mean()

    carry, losses = (params, opt_state), []
    for k in jax.random.split(key, spec.epochs):
        carry, loss = epoch(carry, k)
        losses.append(float(loss))
    return carry[0], losses


def accuracies(params, logits: Callable, obs: np.ndarray, actions: np.ndarray) -> dict:
    """Argmax accuracy on all samples and on the non-stay samples; mean log-likelihood."""
    apply = jax.jit(logits)
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
