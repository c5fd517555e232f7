"""Why a training run ends short of its length, each with its exit code and line; they live
apart from the training loop so that a usage error or `--help` is answered without importing
JAX and orbax (seconds of start-up, paid by every command that only refuses its input)."""

from __future__ import annotations

import signal

from esr_cli.common.failures import Failure
from esr_cli.common.printing import printable


class Interrupted(Failure):
    """Ctrl-C (SIGINT) or SIGTERM arrived; the run stopped, keeping its checkpoint of `epoch`
    (the chunk in flight, if any, is dropped). The command exits with `exit_code`. `unit`:
    what `epoch` counts (a trained human counts PPO updates)."""

    def __init__(self, epoch: int, signum: int = signal.SIGINT, unit: str = "epoch"):
        self.epoch, self.signum, self.unit = epoch, signum, unit
        super().__init__(f"interrupted after {unit} {epoch}")

    @property
    def exit_code(self) -> int:
        return exit_code(self.signum)

    def one_line(self) -> str:
        how = "interrupted" if self.exit_code == 130 else "terminated (SIGTERM)"
        if not self.epoch:
            return f"{how} before the first checkpoint: run the same command again to start over"
        return f"{how} after {self.unit} {self.epoch:,}; the checkpoint is saved: run the same command again to resume"


def exit_code(signum: int) -> int:
    """A shell's code for a process a signal ended: 130 for SIGINT, 143 for SIGTERM."""
    return 128 + int(signum)


class TimeLimitReached(Failure):
    """The next chunk would end past the run's time limit; the run stopped after saving."""

    exit_code = 75
    on_purpose = True  # the stop --stop-after asked for: said as it is, never as an error

    def __init__(self, epoch: int, total: int):
        self.epoch, self.total = epoch, total
        super().__init__(f"stopped at the time limit after epoch {epoch} of {total}")

    def one_line(self) -> str:
        return (f"stopped after epoch {self.epoch:,} of {self.total:,}: the next chunk would pass the time limit; "
                "the checkpoint is saved: run the same command again to continue")


class CorruptCheckpoint(Failure):
    """A checkpoint exists but cannot be restored."""


class Diverged(Failure):
    """A non-finite value appeared by `epoch`; the run stops and is not committed. Its partial
    directory keeps the epochs logged up to it and says that it diverged (pending.json)."""

    def __init__(self, what: str, epoch: int):
        self.epoch = epoch
        super().__init__(what)

    def one_line(self) -> str:
        return f"run diverged: {self} (the partial run is kept for inspection; {SAME_AGAIN})"


# Training is deterministic: the same spec resumed on the same machine reaches the same value.
SAME_AGAIN = "training is deterministic, so the same spec diverges again on this machine: change it (a lower learning rate, say)"


def diverged_at(pending: object) -> str | None:
    """What made an unfinished run stop as diverged ("critic_loss became nan at seed 0, epoch
    12"), as its pending.json records it (bounded, printable); None if it did not."""
    what = (pending or {}).get("diverged") if isinstance(pending, dict) else None
    what = what.get("what") if isinstance(what, dict) else None
    return printable(what[:300]) if isinstance(what, str) and what else None
