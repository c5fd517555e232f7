"""Environments behind one interface: reset, step, observe, action planes, render.

Every environment is a frozen NamedTuple of static facts with pure methods, so it can be
closed over by jitted code. See docs/environments.md.
"""

from __future__ import annotations


def make_env(env_spec):
    if env_spec.kind == "gridworld":
        from esr_cli.envs import gridworld

        return gridworld.make(env_spec)
    if env_spec.kind == "overcooked":
        from esr_cli.envs import overcooked

        return overcooked.make(env_spec)
    raise ValueError(f"unknown env kind {env_spec.kind!r}")
