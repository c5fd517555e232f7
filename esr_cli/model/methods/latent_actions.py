"""Inferring the human's action from observations alone (ESR's `human_action: inferred`).

A latent-action model in the manner of LAPO (Schmidt and Jiang 2024), trained online on the
robot's own transitions with observations as its only targets:

    encoder   q(z | s, s')            K logits from the observation before and after a step
    decoder   f(s, aR, z) -> s' - s   predicts the step's change of the observation from s, the
                                      robot's action and the code (a straight-through
                                      Gumbel-softmax sample)
    loss      squared error of the predicted change, summed over the observation

The code is a K-way bottleneck: what the decoder cannot get from s and aR (the robot's own
part of the step) must pass through z, and the human's move is the rest. No term reads the
human's true action, so the model needs no action labels. phi(s, aR, aH) then receives q(z | s,
s') in place of aH's one-hot (docs/estimators.md says what this changes in the MI).

The code's agreement with the true actions is measured for the researcher only (never in a
loss): the accuracy of the best many-to-one code -> action map, and the plug-in mutual
information between the most likely code and the action, on each batch.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from esr_cli.model.networks import conv_net


def straight_through_sample(key, logits: jax.Array) -> jax.Array:
    """A one-hot Gumbel-max sample whose gradient is the softmax's (straight-through)."""
    soft = jax.nn.softmax(logits)
    hard = jax.nn.one_hot(jnp.argmax(logits + jax.random.gumbel(key, logits.shape), axis=-1), logits.shape[-1])
    return soft + jax.lax.stop_gradient(hard - soft)


def code_action_agreement(code: jax.Array, action: jax.Array, codes: int, actions: int) -> dict:
    """How well integer codes [B] tell integer actions [B] apart: the accuracy of the best
    many-to-one map from codes to actions, and the plug-in MI (nats) of their joint counts."""
    joint = jnp.zeros((codes, actions)).at[code, action].add(1.0) / code.shape[0]
    accuracy = jnp.sum(jnp.max(joint, axis=1))
    outer = jnp.sum(joint, axis=1, keepdims=True) * jnp.sum(joint, axis=0, keepdims=True)
    mi = jnp.sum(jnp.where(joint > 0, joint * jnp.log(joint / jnp.where(outer > 0, outer, 1.0)), 0.0))
    return {"code_accuracy": accuracy, "code_action_mi": mi}


class LatentActions(NamedTuple):
    """The encoder and forward model; parameters live in ESR's state under "encoder"/"decoder"."""

    env: object
    network_spec: object
    codes: int

    @property
    def encoder(self):
        return conv_net(self.network_spec, self.codes)

    @property
    def decoder(self):
        return conv_net(self.network_spec, math.prod(self.env.obs_shape))

    def _pair(self, obs, next_obs):
        return jnp.concatenate([obs.astype(jnp.float32), next_obs.astype(jnp.float32)], axis=-1)

    def _decoder_input(self, obs, robot_planes, code):
        h, w = obs.shape[1:3]
        z = jnp.broadcast_to(code[:, None, None, :], (code.shape[0], h, w, self.codes))
        return jnp.concatenate([obs.astype(jnp.float32), robot_planes, z], axis=-1)

    def init(self, key, obs_example, robot_planes_example) -> dict:
        k_enc, k_dec = jax.random.split(key)
        obs = obs_example[None]
        code = jnp.zeros((1, self.codes))
        return {
            "encoder": self.encoder.init(k_enc, self._pair(obs, obs)),
            "decoder": self.decoder.init(k_dec, self._decoder_input(obs, robot_planes_example[None], code)),
        }

    def code_probs(self, params, obs, next_obs) -> jax.Array:
        """q(z | s, s'): float32[B, K]."""
        return jax.nn.softmax(self.encoder.apply(params["encoder"], self._pair(obs, next_obs)))

    def loss(self, params, obs, robot_planes, next_obs, key) -> tuple[jax.Array, jax.Array]:
        """-> (squared error of the predicted change s' - s, summed over cells, mean over the
        batch; the code logits)."""
        logits = self.encoder.apply(params["encoder"], self._pair(obs, next_obs))
        code = straight_through_sample(key, logits)
        predicted = self.decoder.apply(params["decoder"], self._decoder_input(obs, robot_planes, code))
        # The decoder predicts the change s' - s: "nothing moved" is then its zero output, and
        # its capacity goes to what moved, where the human's action shows.
        change = (next_obs.astype(jnp.float32) - obs.astype(jnp.float32)).reshape(next_obs.shape[0], -1)
        return jnp.mean(jnp.sum((predicted - change) ** 2, axis=-1)), logits
