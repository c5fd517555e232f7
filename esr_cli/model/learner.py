"""The robot's soft Q-learner, shared by every method (docs/choices.md).

- Critic Q(s, .) over robot actions; target r + gamma (1 - done) max_a' Q_target(s', a');
  mean squared error; Adam; Polyak-averaged target (rate tau).
- Policy pi(a | s) = softmax(beta (Q(s, a) - logsumexp_a Q(s, a))).
- beta is tuned by a dual step, clipped to [1e-3, 100]. `learner.dual`:
  squared (the original code, docs/paper-facts.md): a gradient step on mean_s (target_entropy - H(pi(. | s)))^2.
    Its gradient vanishes once the policy saturates (dH/dbeta -> 0), so a beta that
    overshoots early stays high and the policy stays deterministic (docs/choices.md).
  linear (SAC's temperature rule, on log beta): log beta += dual_lr (H - target_entropy),
    a step of fixed size whatever the saturation.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from esr_cli.model.gradient import gradient_step
from esr_cli.model.networks import conv_net
from esr_cli.model.replay import map_episodes

BETA_MIN, BETA_MAX = 1e-3, 100.0


class LearnerState(NamedTuple):
    params: dict
    target_params: dict
    opt_state: tuple
    beta: jax.Array  # float32[]


def policy_log_probs(q: jax.Array, beta: jax.Array) -> jax.Array:
    adv = q - jax.nn.logsumexp(q, axis=-1, keepdims=True)
    return jax.nn.log_softmax(beta * adv, axis=-1)


def entropy(log_probs: jax.Array) -> jax.Array:
    return -jnp.sum(jnp.exp(log_probs) * log_probs, axis=-1)


def td_loss(q_all, action, reward, q_next_target_all, done, gamma):
    """Mean squared TD error of the taken actions (batched)."""
    q = jnp.take_along_axis(q_all, action[:, None], axis=-1)[:, 0]
    target = reward + gamma * (1.0 - done) * jnp.max(q_next_target_all, axis=-1)
    return jnp.mean((q - jax.lax.stop_gradient(target)) ** 2), q


def dual_loss(beta, q, target_entropy):
    return jnp.mean((target_entropy - entropy(policy_log_probs(q, beta))) ** 2)


class SoftQLearner(NamedTuple):
    num_actions: int
    network_spec: object
    spec: object  # LearnerSpec

    @property
    def net(self):
        return conv_net(self.network_spec, self.num_actions)

    @property
    def optimizer(self):
        return optax.adam(self.spec.lr)

    def init(self, key, obs_example) -> LearnerState:
        params = self.net.init(key, obs_example[None])
        return LearnerState(
            params=params,
            target_params=params,
            opt_state=self.optimizer.init(params),
            beta=jnp.asarray(self.spec.initial_beta, jnp.float32),
        )

    def q_values(self, params, obs):
        return self.net.apply(params, obs)

    def log_probs(self, state: LearnerState, obs):
        return policy_log_probs(self.q_values(state.params, obs), state.beta)

    def critic_step(self, state: LearnerState, obs, action, reward, next_obs, done):
        q_next = self.q_values(state.target_params, next_obs)

        def loss_fn(params):
            return td_loss(self.q_values(params, obs), action, reward, q_next, done, self.spec.gamma)

        (loss, q), params, opt_state = gradient_step(loss_fn, state.params, state.opt_state, self.optimizer)
        target = optax.incremental_update(params, state.target_params, self.spec.tau)
        metrics = {"critic_loss": loss, "q_mean": jnp.mean(q)}
        return state._replace(params=params, target_params=target, opt_state=opt_state), metrics

    def dual_step(self, state: LearnerState, obs):
        return self.dual_step_q(state, jax.lax.stop_gradient(self.q_values(state.params, obs)))

    def dual_step_q(self, state: LearnerState, q):
        """The dual step on Q-values of a batch of states (the dual phase does not change Q,
        so they may come from a table computed once; model/train.py)."""
        loss, grad = jax.value_and_grad(dual_loss)(state.beta, q, self.spec.target_entropy)
        if self.spec.dual == "linear":
            gap = jnp.mean(entropy(policy_log_probs(q, state.beta))) - self.spec.target_entropy
            beta = jnp.exp(jnp.log(state.beta) + self.spec.dual_lr * gap)
        else:
            beta = state.beta - self.spec.dual_lr * grad
        return state._replace(beta=jnp.clip(beta, BETA_MIN, BETA_MAX)), {"dual_loss": loss}

    def q_table(self, state: LearnerState, obs):
        """Q-values of every stored state obs [E, T, ...] -> [E, T, A]."""
        return map_episodes(lambda o: self.q_values(state.params, o), obs, obs.shape[1])
