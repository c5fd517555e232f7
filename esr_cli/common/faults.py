"""Fault points: simulated pre-emption for the reliability tests (docs/reliability.md).

`ESR_FAULT=<point>@<n>` makes the process SIGKILL itself the n-th time (default 1st) it
reaches `<point>`, exactly as a cluster pre-empting the job would; `ESR_FAULT=<point>@<n>:hang`
makes it hang there instead (a stalled file system), after one line on stderr that says so.
Unset (always, outside tests), `reached` does nothing.

Points: compile (before the first chunk runs: the program is being compiled),
after_metrics (a chunk's metrics are appended, its checkpoint not yet saved),
during_save (a chunk's checkpoint is being saved, in the thread that writes it),
after_checkpoint (a chunk's checkpoint is saved), before_rename (the manifest is written
into the partial directory, which is not yet renamed into place), after_unpack (`esr import`
has unpacked an archive into its staging folder, not yet checked or renamed into place).
"""

from __future__ import annotations

import os
import signal
import time

POINTS = ("compile", "after_metrics", "during_save", "after_checkpoint", "before_rename", "after_unpack")
ACTIONS = ("kill", "hang")
HANG_S = 3600


class FaultSpecError(ValueError):
    """ESR_FAULT names no fault point, or a count that is not a positive integer."""


def parse(spec: str) -> tuple[str, int, str]:
    """'after_metrics@2' -> ('after_metrics', 2, 'kill'); 'during_save:hang' -> ('during_save',
    1, 'hang'). A misspelt point would silently never fire and a test would pass for the wrong
    reason, so it is an error."""
    where, _, action = spec.partition(":")
    name, _, nth = where.partition("@")
    if name not in POINTS:
        raise FaultSpecError(f"ESR_FAULT={spec!r}: unknown fault point {name!r}; points: {', '.join(POINTS)}")
    if nth and not (nth.isdigit() and int(nth) >= 1):
        raise FaultSpecError(f"ESR_FAULT={spec!r}: the count after '@' must be a positive integer")
    if action and action not in ACTIONS:
        raise FaultSpecError(f"ESR_FAULT={spec!r}: unknown action {action!r} after ':'; actions: {', '.join(ACTIONS)}")
    return name, int(nth or 1), action or "kill"


def reached(point: str, count: int = 1) -> None:
    if point not in POINTS:
        raise ValueError(f"reached({point!r}): not a fault point; points: {', '.join(POINTS)}")
    spec = os.environ.get("ESR_FAULT")
    if not spec:
        return
    name, nth, action = parse(spec)
    if name != point or count != nth:
        return
    if action == "hang":
        os.write(2, f"fault: hanging at {point}\n".encode())
        time.sleep(HANG_S)
    else:
        os.kill(os.getpid(), signal.SIGKILL)
