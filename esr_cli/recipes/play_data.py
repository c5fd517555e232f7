"""Played Overcooked episodes (`esr play`) as human data: the person's (observation, action)
pairs, in the arrays the 2019 trials convert to (model/humans/overcooked_data.convert), so that
esr's BC cloning reads either.

The person's observation is JaxMARL's view of the agent they played (env.observe_human), from
the state each step was taken from. Held out for the clone's test accuracy: the last quarter
of the episodes (at least one) when there are two or more; with one episode there is no test
split.
"""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from esr_cli.model import spec as spec_model
from esr_cli.model.envs import make_env
from esr_cli.storage.play_log import read_header, read_states, read_steps


class PlayDataError(Exception):
    """The played episodes cannot be used as this human's data; `str()` says why."""


def held_out(episodes: int) -> np.ndarray:
    """bool[episodes]: which episodes form the test split."""
    test = np.zeros(episodes, bool)
    if episodes >= 2:
        test[episodes - max(1, episodes // 4):] = True
    return test


def _played_on(path: Path, layout: str) -> dict:
    """The episode's header; PlayDataError unless it was played on Overcooked's `layout`."""
    header = read_header(path)
    if header["env"].get("kind") != "overcooked" or header["env"].get("layout") != layout:
        raise PlayDataError(f"played episode {Path(path).name[:12]} is not an Overcooked episode on {layout}")
    return header


def check(paths: list[Path], layout: str) -> None:
    """Raise PlayDataError unless every episode was played on Overcooked's `layout` and one at
    least has a step: cheap (headers and step logs), so it runs before anything is written."""
    for path in paths:
        _played_on(path, layout)
    if not any(read_steps(path) for path in paths):
        raise PlayDataError("the played episodes have no steps")


def convert(paths: list[Path], layout: str) -> dict[str, np.ndarray]:
    """-> obs uint8[M, H, W, 26], action int8[M], player int8[M] (the seat the person played),
    test bool[M], game int32[M] (the episode's index in `paths`)."""
    headers = [_played_on(path, layout) for path in paths]  # all, before any episode is converted
    out = {k: [] for k in ("obs", "action", "player", "test", "game")}
    test = held_out(len(paths))
    for i, (path, header) in enumerate(zip(paths, headers)):
        steps = read_steps(path)
        if not steps:
            continue
        env = make_env(spec_model.OvercookedEnvSpec.model_validate(header["env"]))
        states = read_states(path, env)[: len(steps)]
        stacked = jax.tree.map(lambda *xs: np.stack(xs), *states)
        out["obs"].append(np.asarray(jax.jit(jax.vmap(env.observe_human))(stacked), np.uint8))
        out["action"].append(np.array([s["human_action"] for s in steps], np.int8))
        out["player"].append(np.full(len(steps), 1 - env.robot_seat, np.int8))
        out["test"].append(np.full(len(steps), test[i]))
        out["game"].append(np.full(len(steps), i, np.int32))
    if not out["obs"]:
        raise PlayDataError("the played episodes have no steps")
    return {k: np.concatenate(v) for k, v in out.items()}
