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


def reached(point: str, count: int = 1) -> None:
    spec = os.environ.get("ESR_FAULT")
    if not spec:
        return
    name, _, nth = spec.partition("@")
    if name == point and count == int(nth or 1):
        os.kill(os.getpid(), signal.SIGKILL)
