"""Environments behind one interface: reset, step, observe, action planes, render.

Every environment is a frozen NamedTuple of static facts with pure methods, so it can be
closed over by jitted code. See docs/environments.md.
"""

from __future__ import annotations

from esr_cli.model.envs import gridworld, overcooked  # jaxmarl itself loads only when an Overcooked env is made


def make_env(env_spec):
    if env_spec.kind == "gridworld":
        return gridworld.make(env_spec)
    if env_spec.kind == "overcooked":
        return overcooked.make(env_spec)
    raise ValueError(f"unknown env kind {env_spec.kind!r}")
