"""Ctrl-C and SIGTERM while a run trains: acknowledged at once, acted on within a fraction of
a second, wherever training is.

Compiling a program and running a chunk hold a thread in XLA's C++ for as long as they take
(a paper chunk on a small CPU: over half an hour), and Python runs a signal handler only in
the main thread, between two bytecodes. So the long steps run in a worker thread while the
main thread waits in short slices and looks for a request between them. A chunk in flight is
then abandoned: its epochs are lost, the checkpoint before it is intact, and the process
leaves with `os._exit` (esr_cli/cli/main.py), which ends the worker too. A checkpoint being
written is waited for, as it is what the run keeps.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from typing import Callable, TypeVar

from esr_cli.common.stops import Interrupted, exit_code

# The signals that stop a run: Ctrl-C, and the SIGTERM of `kill`, `timeout` or a scheduler.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# How long the main thread waits on a worker before it looks for a stop request again.
POLL_S = 0.1
# The same signal again this soon is the same request: `timeout` (and some schedulers) send it to
# the process and then to its whole process group, so it arrives twice at once. No person presses
# Ctrl-C twice within this.
SAME_REQUEST_S = 0.25

T = TypeVar("T")


class StopRequests:
    """The training loop's handler of STOP_SIGNALS (`with requests.installed():`). The first
    signal asks the run to stop: `on_stop(signum, kept_epoch)` acknowledges it once, and the
    next `check` or `wait` raises Interrupted. A second one leaves the process at once, with
    that signal's exit code (the same signal within SAME_REQUEST_S is the first one again)."""

    def __init__(self, on_stop: Callable[[int, int], None] | None = None, unit: str = "epoch"):
        self.signum: int | None = None
        self.unit = unit  # what `kept` counts, for the Interrupted raised
        self._on_stop = on_stop
        self._acknowledged = False
        self._asked_at = 0.0

    def __call__(self, signum, frame) -> None:  # the handler: sets a flag, nothing that can block
        now = time.monotonic()
        if self.signum is not None:
            if signum == self.signum and now - self._asked_at < SAME_REQUEST_S:
                return  # one request delivered twice (to the process, then to its group)
            os.write(2, b"second stop signal: exiting at once\n")
            os._exit(exit_code(signum))
        self.signum, self._asked_at = signum, now

    @contextlib.contextmanager
    def installed(self):
        previous = {sig: signal.signal(sig, self) for sig in STOP_SIGNALS}
        try:
            yield self
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    def acknowledge(self, kept: int) -> None:
        """Tell the caller, once, that a stop was asked; `kept`: the epoch of the checkpoint the
        run keeps."""
        if self.signum is not None and not self._acknowledged:
            self._acknowledged = True
            if self._on_stop:
                self._on_stop(self.signum, kept)

    def check(self, kept: int) -> None:
        """Raise Interrupted (acknowledged first) if a stop was asked."""
        if self.signum is not None:
            self.acknowledge(kept)
            raise Interrupted(kept, self.signum, self.unit)

    def wait(self, work: Callable[[], T], kept: int, abandon: bool = True) -> T:
        """work() in a daemon thread while this one looks for a stop every POLL_S. abandon: a
        stop raises Interrupted at once, the worker left to the process's exit; otherwise (a
        checkpoint being written) it is acknowledged at once and acted on after work."""
        if abandon:
            self.check(kept)  # asked already: nothing to start
        result: list = []
        done = threading.Event()

        def run():
            try:
                result.append((True, work()))
            except BaseException as e:  # noqa: BLE001 - handed to the waiting thread
                result.append((False, e))
            finally:
                done.set()

        threading.Thread(target=run, name="esr-training", daemon=True).start()
        while not done.wait(POLL_S):
            if abandon:
                self.check(kept)
            else:
                self.acknowledge(kept)
        ok, value = result[0]
        if not ok:
            raise value
        return value
