"""Human models. Each has `act(key, env_state) -> action`."""

from __future__ import annotations


def make_human(human_spec, env):
    if human_spec.kind == "noisy_greedy":
        from esr_cli.humans.gridworld import NoisyGreedyHuman

        return NoisyGreedyHuman(env=env, noise=float(human_spec.noise))
    raise ValueError(f"unknown human kind {human_spec.kind!r}")
