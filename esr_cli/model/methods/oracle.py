"""Oracle: an upper bound the paper lacks. The robot sees the human's goal (the environment's
`goal_visible` observation) and is trained with the shared soft-Q learner on the human's true
reward, so the gap between it and ESR is the room left for any goal-agnostic assistant."""

from __future__ import annotations

from typing import NamedTuple

from esr_cli.model.methods.base import no_update, stateless_init


class Oracle(NamedTuple):
    updates_per_epoch: int = 0
    learns_policy: bool = True
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
        return batch.reward  # the environment's reward for this transition
