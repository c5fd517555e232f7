"""Random: the robot acts uniformly at random and learns nothing (the paper's naive baseline)."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from esr_cli.model.methods.base import no_update, stateless_init


class RandomRobot(NamedTuple):
    updates_per_epoch: int = 0
    learns_policy: bool = False
    metric_names: tuple = ()
    all_metric_names = ()  # not a field: the same for every spec
    acts_by_rule: bool = False
    has_reward_table: bool = False

    init = stateless_init
    update = no_update

    @classmethod
    def from_spec(cls, spec, env, human):
        return cls()

    def reward(self, state, batch, key):
        return jnp.zeros(batch.robot_action.shape, jnp.float32)
