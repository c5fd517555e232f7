"""What PPO asks of a PPO human's batch, checked from the spec's fields when the spec is read,
so that a human it cannot train is refused by key path before anything is built or written
(model/humans/ppo.py would stop with a bare ValueError once the build had begun)."""

from __future__ import annotations

# model/humans/ppo.py's values, kept here so that reading a spec does not load JAX (a test keeps
# them equal): both seats are the network's in self-play, and each update's batch is split into
# this many minibatches.
SEATS = 2  # ppo.overcooked_env(...).players
MINIBATCHES = 4  # ppo.PPOConfig.num_minibatches


def problem(human) -> tuple[str, str] | None:
    """(key path, problem) where PPO cannot train the PPO human spec `human`; None where it can."""
    envs, steps = human.num_envs, human.rollout_steps
    if human.total_steps < envs * steps:
        return ("human.total_steps", f"{human.total_steps:,} is less than one rollout: num_envs x rollout_steps = "
                                     f"{envs} x {steps} = {envs * steps:,} environment steps")
    batch = envs * steps * SEATS
    if batch % MINIBATCHES:
        return ("human", f"num_envs x rollout_steps x {SEATS} seats = {envs} x {steps} x {SEATS} = {batch:,} actor-steps "
                         f"an update, which PPO's {MINIBATCHES} minibatches cannot split evenly (make num_envs x "
                         f"rollout_steps a multiple of {MINIBATCHES // SEATS})")
    return None
