"""The interfaces the one runner (model/train.py) drives: environments, human models, methods.

Each is a `typing.Protocol`; implementations are frozen NamedTuples of static facts with pure
methods (so jitted code can close over them) and declare every optional capability as an
explicit member rather than leaving the runner to probe for it. tests/model/test_interfaces.py
checks every implementation against these.
"""

from __future__ import annotations

from typing import Any, ClassVar, Protocol, runtime_checkable

import jax


@runtime_checkable
class Environment(Protocol):
    episode_steps: int

    @property
    def num_robot_actions(self) -> int: ...

    @property
    def num_human_actions(self) -> int: ...

    @property
    def obs_shape(self) -> tuple[int, ...]: ...

    def reset(self, key: jax.Array) -> Any: ...

    def step(self, state: Any, robot_action: jax.Array, human_action: jax.Array) -> tuple[Any, jax.Array]: ...

    def observe(self, state: Any) -> jax.Array: ...

    def human_view(self, obs: jax.Array) -> jax.Array:
        """An observation with all but the human's own part zeroed (ESR's `future: human`)."""
        ...

    def robot_action_planes(self, action: jax.Array) -> jax.Array: ...

    def human_action_planes(self, action: jax.Array) -> jax.Array: ...

    def random_human_futures(self, obs: jax.Array, human_actions: jax.Array) -> jax.Array:
        """AvE's rollouts: where the human ends up after each row of random actions."""
        ...

    def render(self, state: Any, cell_px: int = ...) -> Any: ...


@runtime_checkable
class Human(Protocol):
    learns: bool  # True: also update (a human that adapts during training); implies has_state
    has_state: bool  # True: init / act_with, a per-seed state in the training state (a per-seed or adapting human)
    metric_names: tuple  # keys of `update`'s metrics (empty for a fixed human)

    def act(self, key: jax.Array, env_state: Any) -> jax.Array: ...


@runtime_checkable
class StatefulHuman(Human, Protocol):
    def init(self, key: jax.Array, seed: jax.Array) -> Any: ...

    def act_with(self, hstate: Any, key: jax.Array, env_state: Any) -> jax.Array: ...


@runtime_checkable
class LearningHuman(StatefulHuman, Protocol):
    def update(self, hstate: Any, states: Any, human_actions: jax.Array, rewards: jax.Array, key: jax.Array) -> tuple[Any, dict]: ...


@runtime_checkable
class Method(Protocol):
    learns_policy: bool  # False: the robot acts uniformly at random
    acts_by_rule: bool  # True: the robot acts by memory_init / rule_step / rule_metrics instead
    has_reward_table: bool  # True: reward_table / reward_from_table over the whole buffer
    metric_names: tuple  # keys of `update`'s metrics
    # every key `metric_names` can hold under any spec of this method (a class attribute:
    # `esr sweep --metric` checks names before any method is built)
    all_metric_names: ClassVar[tuple[str, ...]]

    @property
    def updates_per_epoch(self) -> int: ...

    def init(self, key: jax.Array, obs_example: jax.Array) -> Any: ...

    def update(self, state: Any, batch: Any, key: jax.Array) -> tuple[Any, dict]: ...

    def reward(self, state: Any, batch: Any, key: jax.Array) -> jax.Array: ...


@runtime_checkable
class RuleMethod(Method, Protocol):
    def memory_init(self, obs: jax.Array) -> Any: ...

    def rule_step(self, memory: Any, obs: jax.Array, prev_human_action: jax.Array, key: jax.Array) -> tuple[jax.Array, Any]: ...

    def rule_metrics(self, memory: Any, env_state: Any) -> dict: ...


@runtime_checkable
class TableMethod(Method, Protocol):
    def reward_table(self, state: Any, buf: Any) -> Any: ...

    def reward_from_table(self, table: Any, idx: Any) -> jax.Array: ...
