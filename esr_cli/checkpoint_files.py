"""A run's checkpoint files and their digests, without JAX: which checkpoints are intact.

Digests of every checkpoint's files are written after the checkpoint is saved; a resume, an
export and a report use only checkpoints that verify, so a damaged newest checkpoint falls
back to the one before and a run without an intact one is known to start again.
"""

from __future__ import annotations

import json
from pathlib import Path

from esr_cli.store import atomic_write_text, digest_file

CHECKPOINT_DIR = "checkpoints"
CHECKPOINT_DIGESTS = "checkpoint_digests.json"


def step_digests(run_dir: Path, step: int) -> dict[str, str]:
    root = Path(run_dir) / CHECKPOINT_DIR / str(step)
    return {f.relative_to(root).as_posix(): digest_file(f) for f in sorted(root.rglob("*")) if f.is_file()}


def read_digests(run_dir: Path) -> dict:
    """{step: {file: digest}}; {} where the file is missing, unreadable or not an object."""
    try:
        digests = json.loads((Path(run_dir) / CHECKPOINT_DIGESTS).read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    return digests if isinstance(digests, dict) else {}


def step_intact(run_dir: Path, step: int, digests: dict) -> bool:
    """Whether checkpoint `step`'s files match the digests recorded for it."""
    return bool(digests.get(str(step))) and step_digests(run_dir, step) == digests[str(step)]


def record_digests(run_dir: Path, steps, saved: int) -> None:
    """Record the just-saved step's digests; keep those of older steps still present."""
    known = read_digests(run_dir)
    digests = {str(s): known.get(str(s)) for s in steps if s != saved and known.get(str(s))}
    digests[str(saved)] = step_digests(run_dir, saved)
    atomic_write_text(Path(run_dir) / CHECKPOINT_DIGESTS, json.dumps(digests, sort_keys=True))


def verified_steps(run_dir: Path) -> list[int]:
    """The checkpoint steps of `run_dir` whose files match their recorded digests, newest first."""
    root = Path(run_dir) / CHECKPOINT_DIR
    if not root.is_dir():
        return []
    digests = read_digests(run_dir)
    steps = sorted((int(d.name) for d in root.iterdir() if d.is_dir() and d.name.isdigit()), reverse=True)
    return [s for s in steps if step_intact(run_dir, s, digests)]
