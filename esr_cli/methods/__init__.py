"""Methods: what the robot is rewarded for, and any representation it learns.

Every method has the same small interface, so the one runner (esr_cli.core.train) drives
them all with the shared soft-Q learner:

    init(key, obs_example) -> state            (a pytree; () for methods that learn nothing)
    update(state, batch, key) -> (state, metrics)   one representation/model step
    reward(state, batch, key) -> float32[B]    the robot's reward for a critic batch
    updates_per_epoch: int                     how many `update` steps per epoch
    learns_policy: bool                        False: the robot acts uniformly at random
    metric_names: tuple[str, ...]              keys of `update`'s metrics
"""

from __future__ import annotations


def make_method(spec, env):
    kind = spec.method.kind
    if kind == "esr":
        from esr_cli.methods.esr import ESR

        return ESR(env=env, spec=spec.method, network_spec=spec.network)
    if kind == "random":
        from esr_cli.methods.random import RandomRobot

        return RandomRobot()
    raise ValueError(f"unknown method kind {kind!r}")
