"""Played episodes of any environment as step records (`esr plays --export FILE.jsonl`): one
JSON object per line and step, with who played it and with which robot, so that a study's
steps load into any analysis tool without esr. The fields are documented in docs/play.md.
"""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import TypeAdapter

from esr_cli.model import spec as spec_model
from esr_cli.model.envs import make_env
from esr_cli.model.envs.action_labels import LABELS
from esr_cli.storage.play_log import read_header, read_steps, reading_episode

# Copied from the episode's header onto each of its steps.
EPISODE_FIELDS = ("participant", "session", "episode", "robot", "robot_label", "seed", "front_end")


def step_records(path: Path, envs: dict | None = None) -> list[dict]:
    """One played episode's steps, each with its episode's fields and both actions in words.
    envs: environments already made, by their spec (an export makes each one once)."""
    with reading_episode(path):
        return _step_records(path, {} if envs is None else envs)


def _step_records(path: Path, envs: dict) -> list[dict]:
    header = read_header(path)
    env_spec = TypeAdapter(spec_model.EnvSpec).validate_python(header["env"])  # the environment it was played on
    which = json.dumps(header["env"], sort_keys=True)
    if which not in envs:
        envs[which] = make_env(env_spec)
    env, label = envs[which], LABELS[env_spec.kind]
    common = {"play_key": Path(path).name, **{f: header.get(f) for f in EPISODE_FIELDS},
              "env": env_spec.kind, "layout": getattr(env_spec, "layout", None)}
    out = []
    for step in read_steps(path):
        robot_words, human_words = label(env, step["robot_action"], step["human_action"])
        # the step as logged (play.game.Step: actions, reward, timing, the state it was taken from)
        out.append({**common, **step, "robot_action_name": robot_words, "human_action_name": human_words})
    return out


def export_jsonl(paths: list[Path]) -> tuple[str, int]:
    """-> (the JSONL text, the number of steps)."""
    envs: dict = {}
    lines = [json.dumps(r, separators=(",", ":")) for p in paths for r in step_records(p, envs)]
    return "".join(line + "\n" for line in lines), len(lines)
