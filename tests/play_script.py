"""A scripted person for `esr play`'s game loop (tests/play/test_play.py, tests/recipes/test_overcooked_e2e.py)."""

import time

from esr_cli.play.game import CLOSED, KeyPress

STALE = "stale:"  # a Scripted key pressed on the frame before the one on screen


class Scripted:
    """A front end that presses the given keys, after space at the ready gate (None: let a tick
    pass; "stale:up": up pressed on the previous frame; the script's end closes the tab)."""

    draws_text = True

    def ready(self):
        pass

    def finish(self, lines):
        pass

    def __init__(self, keys, start=True):
        self.keys, self.views = (["space"] if start else []) + list(keys), []

    def show(self, view):
        self.views.append(view)

    def shown_at(self, frame):
        return None

    def key(self, timeout):
        if not self.keys:
            return KeyPress(CLOSED)
        name, frame, now = self.keys.pop(0), self.views[-1].seq, time.monotonic()
        if name is None:
            time.sleep(timeout or 0)
            return None
        if name.startswith(STALE):
            name, frame = name[len(STALE):], frame - 1
        return KeyPress(name, frame, now, now - 0.25, now + 0.25)  # shown 0.25 s before the press, as esr's clock allows
