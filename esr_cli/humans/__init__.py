"""Human models. Each has `act(key, env_state) -> action`.

A human that keeps learning during training (humans/bc.py with `adapt`) also has
`learns = True`, `metric_names`, `init(key) -> hstate`, `act_with(hstate, key, env_state)`
and `update(hstate, states, human_actions, rewards, key) -> (hstate, metrics)`; the runner
keeps `hstate` in its training state.
"""

from __future__ import annotations

import jax
import numpy as np

from esr_cli.humans.bc import BCHuman
from esr_cli.humans.gridworld import NoisyGreedyHuman


def make_human(human_spec, env, params=None, seeds: tuple = ()):
    """`params`: a cloned human's parameters (kind bc), loaded from the store by the caller
    (runs.build_trainer): the models never reach into the store themselves. With
    `human.per_seed`, a list of parameters, one per training seed in `seeds` order."""
    if human_spec.kind == "noisy_greedy":
        return NoisyGreedyHuman(env=env, noise=float(human_spec.noise))
    if human_spec.kind == "bc":
        if params is None:
            raise ValueError("a BC human needs its cloned parameters (runs.build_trainer loads them from the store)")
        per_seed = None
        if human_spec.per_seed:
            if len(params) != len(seeds):
                raise ValueError(f"human.per_seed: {len(params)} clones for {len(seeds)} seeds")
            per_seed = jax.tree.map(lambda *leaves: np.stack(leaves), *params)
            params = params[0]
        return BCHuman(
            env=env,
            params=params,
            per_seed_params=per_seed,
            seeds=tuple(int(s) for s in seeds) if per_seed is not None else (),
            hidden=tuple(human_spec.hidden),
            adapt=bool(human_spec.adapt),
            adapt_lr=float(human_spec.adapt_lr),
            adapt_kl=float(human_spec.adapt_kl),
            adapt_gamma=float(human_spec.adapt_gamma),
        )
    raise ValueError(f"unknown human kind {human_spec.kind!r}")
