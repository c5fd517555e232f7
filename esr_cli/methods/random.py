"""Random: the robot acts uniformly at random and learns nothing (the paper's naive baseline)."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp


class RandomRobot(NamedTuple):
    updates_per_epoch: int = 0
    learns_policy: bool = False
    metric_names: tuple = ()

    def init(self, key, obs_example):
        return ()

    def update(self, state, batch, key):
        return state, {}

    def reward(self, state, batch, key):
        return jnp.zeros(batch.robot_action.shape, jnp.float32)
