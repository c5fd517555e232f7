"""Why a training run ends short of its length. The CLI maps each to an exit code; they live
apart from the training loop so that a usage error or `--help` is answered without importing
JAX and orbax (seconds of start-up, paid by every command that only refuses its input)."""

from __future__ import annotations

import signal


class Interrupted(Exception):
    """Ctrl-C (SIGINT) or SIGTERM arrived; the run stopped, keeping its checkpoint of `epoch`
    (the chunk in flight, if any, is dropped). The command exits with `exit_code`. `unit`:
    what `epoch` counts (a trained human counts PPO updates)."""

    def __init__(self, epoch: int, signum: int = signal.SIGINT, unit: str = "epoch"):
        self.epoch, self.signum, self.unit = epoch, signum, unit
        super().__init__(f"interrupted after {unit} {epoch}")

    @property
    def exit_code(self) -> int:
        return exit_code(self.signum)


def exit_code(signum: int) -> int:
    """A shell's code for a process a signal ended: 130 for SIGINT, 143 for SIGTERM."""
    return 128 + int(signum)


class TimeLimitReached(Exception):
    """The next chunk would end past the run's time limit; the run stopped after saving."""

    def __init__(self, epoch: int, total: int):
        self.epoch, self.total = epoch, total
        super().__init__(f"stopped at the time limit after epoch {epoch} of {total}")


class CorruptCheckpoint(Exception):
    """A checkpoint exists but cannot be restored."""


class Diverged(Exception):
    """A non-finite value appeared; the run stops and is not committed."""
