"""The log of a played episode (a `play` artifact's files) and the state records in it.

  episode.json      who played with which robot, on which environment and seed, and when
  steps.jsonl       one line per step, appended (flushed and synced) as it is played: the key,
                    both actions, reward, score, wall time, reaction time and the state the
                    step was taken from
  final_state.json  the state after the last step
  summary.json      return, success, steps, completed (also in the manifest)
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import jax
import numpy as np

from esr_cli.common.jsonl import JsonInputError, read_json, read_jsonl
from esr_cli.storage.store import StoreError

STEPS_FILE, EPISODE_FILE, FINAL_STATE_FILE = "steps.jsonl", "episode.json", "final_state.json"


def state_record(state) -> dict:
    """An environment state (any pytree) as {field path: plain Python value}."""
    leaves, _ = jax.tree_util.tree_flatten_with_path(state)
    return {jax.tree_util.keystr(path).lstrip("."): np.asarray(v).tolist() for path, v in leaves}


def state_from_record(env, record: dict):
    """The environment state a record holds (state_record's inverse), shaped like env.reset's."""
    template = env.reset(jax.random.PRNGKey(0))
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    values = [np.asarray(record[jax.tree_util.keystr(path).lstrip(".")], dtype=np.asarray(leaf).dtype).reshape(np.shape(leaf))
              for path, leaf in leaves]
    return jax.tree_util.tree_unflatten(treedef, values)


# A played episode's header, its final state and a study's record are a few KiB; a larger file is not esr's.
MAX_RECORD_BYTES = 1 << 20


# The header fields every reader of a played episode relies on, with the type esr writes each as.
HEADER_FIELDS = {"participant": str, "session": str, "episode": int, "robot": str, "env": dict, "started_at": (int, float)}


def read_header(path: Path) -> dict:
    """A played episode's header; StoreError naming the file where it is not the JSON object esr
    writes (a field of HEADER_FIELDS missing or of another type, the environment without its kind)."""
    file = Path(path) / EPISODE_FILE
    try:
        header = read_json(file, MAX_RECORD_BYTES)
    except JsonInputError as e:
        raise StoreError(f"damaged played episode: {file}: {e}") from None
    if not isinstance(header, dict):
        raise StoreError(f"damaged played episode: {file} is not a JSON object")
    for field, kind in HEADER_FIELDS.items():
        value = header.get(field)
        if isinstance(value, bool) or not isinstance(value, kind) or (
                isinstance(value, (int, float)) and not abs(value) < 2 ** 53):  # a count or a time, as float64 holds one
            raise StoreError(f"damaged played episode: {file} has no {field} of the kind esr writes")
    if not isinstance(header["env"].get("kind"), str):
        raise StoreError(f"damaged played episode: {file} names no environment kind")
    return header


# What reading a damaged log raises where it assumes what esr writes (a field missing or of another
# type, an action out of range); a pydantic ValidationError is a ValueError.
DAMAGE = (KeyError, IndexError, TypeError, ValueError, OverflowError, AttributeError)


@contextmanager
def reading_episode(path: Path) -> Iterator[None]:
    """Read a played episode's files inside: where they are not what esr writes, one StoreError
    names the episode, instead of whatever the reading code met first."""
    try:
        yield
    except StoreError:
        raise
    except (JsonInputError, OSError) as e:
        raise StoreError(f"damaged played episode: {path}: {e}") from None
    except DAMAGE as e:  # what was met, bounded (a pydantic error quotes whole values)
        said = " ".join(str(e).split())
        raise StoreError(f"damaged played episode: {path}: its steps or header are not what esr writes "
                         f"({type(e).__name__}: {said[:120] + ('...' if len(said) > 120 else '')})") from None


def read_steps(path: Path) -> list[dict]:
    """An episode's steps; a last line cut short by a crash is dropped."""
    return read_jsonl(Path(path) / STEPS_FILE)


def read_states(path: Path, env) -> list:
    """The states of an episode: each step's, then the final one (when it was written)."""
    states = [state_from_record(env, s["state"]) for s in read_steps(path)]
    final = Path(path) / FINAL_STATE_FILE
    if final.exists():
        states.append(state_from_record(env, read_json(final, MAX_RECORD_BYTES)))
    return states
