"""Reward inference with IQ-Learn (Garg et al. 2021), then the shared robot learner.

A soft Q-function of the human, Q_H(s, aH), is fitted online (on the replay buffer, alongside
the robot, from the human's transitions (s, aH, s') only) with the inverse soft-Q objective
for discrete actions and the chi-squared regulariser:

    V(s)  = alpha logsumexp(Q_H(s, .) / alpha)
    r     = Q_H(s, aH) - gamma (1 - done) V(s')                 (the recovered reward)
    loss  = -E[r] + E[V(s) - gamma (1 - done) V(s')] + chi2 E[r^2]

(the "offline" form: expert data only, the initial-state term estimated on all expert
states). The robot's reward for a transition is the recovered human reward r(s, aH, s').
The human's Q sees what the robot sees (no goal), which is the baseline's handicap.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from esr_cli.model.gradient import gradient_step
from esr_cli.model.networks import conv_net
from esr_cli.model.replay import map_episodes


class IQState(NamedTuple):
    params: dict
    opt_state: tuple


def soft_value(q: jax.Array, alpha: float) -> jax.Array:
    return alpha * jax.nn.logsumexp(q / alpha, axis=-1)


def recovered_reward(q_s: jax.Array, action: jax.Array, q_next: jax.Array, done: jax.Array, gamma: float, alpha: float):
    """r = Q(s, a) - gamma (1 - done) V(s'), per example."""
    q_sa = jnp.take_along_axis(q_s, action[:, None], axis=-1)[:, 0]
    return q_sa - gamma * (1.0 - done) * soft_value(q_next, alpha)


def iq_loss(q_s, action, q_next, done, gamma: float, alpha: float, chi2: float):
    r = recovered_reward(q_s, action, q_next, done, gamma, alpha)
    value_term = soft_value(q_s, alpha) - gamma * (1.0 - done) * soft_value(q_next, alpha)
    return -jnp.mean(r) + jnp.mean(value_term) + chi2 * jnp.mean(r**2), r


class IQLearn(NamedTuple):
    env: object
    spec: object  # IQLearnMethodSpec
    network_spec: object

    learns_policy: bool = True
    metric_names: tuple = ("iq_loss", "iq_reward_taken", "iq_reward_random")
    all_metric_names = metric_names  # not a field (a class attribute): the same for every spec
    acts_by_rule: bool = False
    has_reward_table: bool = True  # reward_table / reward_from_table (model/train.reward_table_pays)

    @classmethod
    def from_spec(cls, spec, env, human):
        return cls(env=env, spec=spec.method, network_spec=spec.network)

    @property
    def updates_per_epoch(self) -> int:
        return self.spec.updates_per_epoch

    @property
    def net(self):
        return conv_net(self.network_spec, self.env.num_human_actions)

    @property
    def optimizer(self):
        return optax.adam(self.spec.lr)

    def init(self, key, obs_example) -> IQState:
        params = self.net.init(key, obs_example[None])
        return IQState(params=params, opt_state=self.optimizer.init(params))

    def _q_pair(self, params, batch):
        both = self.net.apply(params, jnp.concatenate([batch.obs, batch.next_obs], axis=0))
        return jnp.split(both, 2, axis=0)

    def update(self, state: IQState, batch, key):
        s = self.spec

        def loss_fn(params):
            q_s, q_next = self._q_pair(params, batch)
            loss, r = iq_loss(q_s, batch.human_action, q_next, batch.done, s.gamma, s.alpha, s.chi2)
            return loss, (q_s, q_next, r)

        (loss, (q_s, q_next, r)), params, opt_state = gradient_step(loss_fn, state.params, state.opt_state, self.optimizer)
        # How the recovered reward ranks the human's actual actions against random ones.
        random_action = jax.random.randint(key, batch.human_action.shape, 0, self.env.num_human_actions)
        r_random = recovered_reward(q_s, random_action, q_next, batch.done, s.gamma, s.alpha)
        metrics = {"iq_loss": loss, "iq_reward_taken": jnp.mean(r), "iq_reward_random": jnp.mean(r_random)}
        return IQState(params=params, opt_state=opt_state), metrics

    def reward(self, state: IQState, batch, key):
        q_s, q_next = self._q_pair(state.params, batch)
        r = recovered_reward(q_s, batch.human_action, q_next, batch.done, self.spec.gamma, self.spec.alpha)
        return jax.lax.stop_gradient(r)

    # Within the critic phase Q_H is fixed: where it pays (a buffer smaller than the phase's
    # batches, the gridworld's), every stored state is run through Q_H once and the critic's
    # batches look their rewards up, instead of two forward passes per batch.
    def reward_table(self, state: IQState, buf) -> jax.Array:
        steps = buf.robot_action.shape[1]
        done = (jnp.arange(steps) == steps - 1).astype(jnp.float32)  # as replay.gather marks it

        def episode(args):
            obs, human_action = args
            q = self.net.apply(state.params, obs)  # every state of the episode, the last included
            return recovered_reward(q[:steps], human_action, q[1 : steps + 1], done, self.spec.gamma, self.spec.alpha)

        return jax.lax.stop_gradient(map_episodes(episode, (buf.obs, buf.human_action), steps))

    def reward_from_table(self, table: jax.Array, idx) -> jax.Array:
        """The reward of the batch at buffer index `idx` (replay.Index)."""
        return table[idx.episode, idx.t]
