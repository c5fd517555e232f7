"""Environments behind one interface: reset, step, observe, action planes, render.

Every environment is a frozen NamedTuple of static facts with pure methods, so it can be
closed over by jitted code. See docs/environments.md.
"""

from __future__ import annotations

from esr_cli.model.envs import gridworld, overcooked  # jaxmarl itself loads only when an Overcooked env is made

# How each `env.kind` is made from its spec.
ENVS = {"gridworld": gridworld.make, "overcooked": overcooked.make}


def make_env(env_spec):
    if env_spec.kind not in ENVS:
        raise ValueError(f"unknown env kind {env_spec.kind!r}; known: {', '.join(ENVS)}")
    return ENVS[env_spec.kind](env_spec)
