"""Fault points: simulated pre-emption for the reliability tests (docs/reliability.md).

`ESR_FAULT=<point>@<n>` makes the process SIGKILL itself the n-th time (default 1st) it
reaches `<point>`, exactly as a cluster pre-empting the job would. Unset (always, outside
tests), `reached` does nothing.

Points: compile (before the first chunk runs: the program is being compiled),
after_metrics (a chunk's metrics are appended, its checkpoint not yet saved),
after_checkpoint (a chunk's checkpoint is saved), before_rename (the manifest is written
into the partial directory, which is not yet renamed into place), after_unpack (`esr import`
has unpacked an archive into its staging folder, not yet checked or renamed into place).
"""

from __future__ import annotations

import os
import signal

POINTS = ("compile", "after_metrics", "after_checkpoint", "before_rename", "after_unpack")


class FaultSpecError(ValueError):
    """ESR_FAULT names no fault point, or a count that is not a positive integer."""


def parse(spec: str) -> tuple[str, int]:
    """'after_metrics@2' -> ('after_metrics', 2). A misspelt point would silently never fire
    and a test would pass for the wrong reason, so it is an error."""
    name, _, nth = spec.partition("@")
    if name not in POINTS:
        raise FaultSpecError(f"ESR_FAULT={spec!r}: unknown fault point {name!r}; points: {', '.join(POINTS)}")
    if nth and not (nth.isdigit() and int(nth) >= 1):
        raise FaultSpecError(f"ESR_FAULT={spec!r}: the count after '@' must be a positive integer")
    return name, int(nth or 1)


def reached(point: str, count: int = 1) -> None:
    if point not in POINTS:
        raise ValueError(f"reached({point!r}): not a fault point; points: {', '.join(POINTS)}")
    spec = os.environ.get("ESR_FAULT")
    if not spec:
        return
    name, nth = parse(spec)
    if name == point and count == nth:
        os.kill(os.getpid(), signal.SIGKILL)
