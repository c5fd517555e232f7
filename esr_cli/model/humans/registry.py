"""The humans a run plays with. Each has `act(key, env_state) -> action`.

A human that keeps learning during training (humans/policy_human.py with `adapt`) also has
`learns = True`, `metric_names`, `init(key) -> hstate`, `act_with(hstate, key, env_state)`
and `update(hstate, states, human_actions, rewards, key) -> (hstate, metrics)`; the runner
keeps `hstate` in its training state.
"""

from __future__ import annotations

import jax
import numpy as np

from esr_cli.model.humans import bc, conv_actor_critic
from esr_cli.model.humans.gridworld import NoisyGreedyHuman
from esr_cli.model.humans.policy_human import PolicyHuman

# The stored humans' policies by kind: human spec -> (params, obs [..., H, W, 26]) -> logits [..., 6].
STORED_POLICIES = {
    "bc": lambda human_spec: bc.cloned_policy(human_spec).logits,
    "ppo": lambda human_spec: conv_actor_critic.policy_logits,
}


def policy_logits(human_spec):
    """A stored human's policy: (params, obs [..., H, W, 26]) -> logits [..., 6]."""
    if human_spec.kind not in STORED_POLICIES:
        raise ValueError(f"human kind {human_spec.kind!r} is not a stored policy")
    return STORED_POLICIES[human_spec.kind](human_spec)

def _noisy_greedy(human_spec, env, params, seeds: tuple):
    return NoisyGreedyHuman(env=env, noise=float(human_spec.noise))


def _stored_policy(human_spec, env, params, seeds: tuple):
    logits = policy_logits(human_spec)
    if params is None:
        raise ValueError("a stored human needs its parameters (runs.build_trainer loads them from the store)")
    per_seed = None
    if human_spec.per_seed:
        if len(params) != len(seeds):
            raise ValueError(f"human.per_seed: {len(params)} humans for {len(seeds)} seeds")
        per_seed = jax.tree.map(lambda *leaves: np.stack(leaves), *params)
        params = params[0]
    adapt = {k: getattr(human_spec, k) for k in ("adapt", "adapt_lr", "adapt_kl", "adapt_gamma") if hasattr(human_spec, k)}
    return PolicyHuman(
        env=env,
        params=params,
        logits_fn=logits,
        per_seed_params=per_seed,
        seeds=tuple(int(s) for s in seeds) if per_seed is not None else (),
        **adapt,
    )


# How each `human.kind` is made: (human spec, environment, stored parameters or None, seeds).
HUMANS = {"noisy_greedy": _noisy_greedy, "bc": _stored_policy, "ppo": _stored_policy}


def make_human(human_spec, env, params=None, seeds: tuple = ()):
    """The human of `human_spec.kind`. `params`: a stored human's parameters (kinds bc and ppo),
    loaded from the store by the caller (runs.build_trainer): the models never reach into the
    store themselves. With `human.per_seed`, a list of parameters, one per training seed in
    `seeds` order."""
    if human_spec.kind not in HUMANS:
        raise ValueError(f"unknown human kind {human_spec.kind!r}; known: {', '.join(HUMANS)}")
    return HUMANS[human_spec.kind](human_spec, env, params, seeds)
