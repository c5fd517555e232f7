"""Ctrl-C (SIGINT) and SIGTERM (kill, timeout, a scheduler) as exceptions, so any command ends
with its cleanup (an unfinished evaluation or figure is removed) and one line; the training
loop installs its own handlers, which save at the next chunk boundary first.

Python runs a signal handler between two bytecodes of whatever the main thread is doing. If
that is a garbage-collector callback (jax registers one), a weakref callback or a finalizer,
the exception is "ignored" (handed to sys.unraisablehook) and the program carries on: the
signal would be lost. Meanwhile esr's hook sends the same signal again a moment later.

A library can also wrap the exception in one of its own: pybind11 turns an exception raised
while a C++ module initialises into `ImportError: initialization failed`. So the handler
remembers what it received (`StopSignals.received`), and the command reports the signal
whatever exception reaches it.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

REDELIVER_AFTER_S = 0.05


class Terminated(BaseException):
    """SIGTERM arrived outside the training loop. A BaseException, as KeyboardInterrupt is:
    libraries catch Exception broadly (jax turns a failed compilation-cache read into a
    warning, orbax a failed restore into an error of its own), and a stop must pass through."""


RAISES = {signal.SIGINT: KeyboardInterrupt, signal.SIGTERM: Terminated}


class StopSignals:
    """What `stop_signals_raise` yields: `received`, the first stop signal delivered, or None."""

    def __init__(self):
        self.received: int | None = None

    def __call__(self, signum, frame):  # the handler
        if self.received is None:
            self.received = signum
        raise RAISES[signum]()


@contextlib.contextmanager
def stop_signals_raise():
    """Within: SIGINT raises KeyboardInterrupt and SIGTERM Terminated, in the main thread, and
    neither is lost where Python would ignore it. In another thread signals cannot be
    handled, and are left alone (and `received` stays None)."""
    stops = StopSignals()
    try:
        previous = {sig: signal.signal(sig, stops) for sig in RAISES}
    except ValueError:
        yield stops
        return
    previous_hook = sys.unraisablehook

    def redeliver(unraisable):
        sig = next((s for s, exc in RAISES.items() if unraisable.exc_type is exc), None)
        if sig is None:
            previous_hook(unraisable)
            return
        timer = threading.Timer(REDELIVER_AFTER_S, os.kill, (os.getpid(), sig))
        timer.daemon = True
        timer.start()

    sys.unraisablehook = redeliver
    try:
        yield stops
    finally:
        sys.unraisablehook = previous_hook
        for sig, handler in previous.items():
            signal.signal(sig, handler)
