"""The terminal front end of `esr play`: keys from the terminal in cbreak mode, the game drawn
with rich (colours; works over ssh). The gridworld is drawn as characters, Overcooked as its
rendered picture in half-block cells (two pixels per character).

Timing: a frame is stamped with the monotonic clock once it is written and flushed, a key with
the same clock when it is read. Keys already waiting in the terminal when a frame is drawn were
typed before it: they are read then and keep the previous frame's number, so the game loop
drops them (esr_cli/play/game.py)."""

from __future__ import annotations

import os
import select
import sys
import termios
import time
import tty
from collections import deque

import numpy as np
from rich.console import Console, Group
from rich.text import Text

from esr_cli.common.printing import printable
from esr_cli.play import pages
from esr_cli.play.game import CLOSED, QUIT, KeyPress, View

ARROWS = {"A": "up", "B": "down", "C": "right", "D": "left"}
GRID_STYLE = {"@": "bold rgb(230,150,0)", "X": "bold red", "G": "bold rgb(120,215,10)", "#": "rgb(150,60,235)",
              ".": "rgb(110,110,110)"}
# Overcooked's 48-pixel cells drawn 12 pixels (characters) wide, or 8 where 12 would not fit the
# terminal's width (a wider layout on an 80-column terminal): one pixel in every 4 or 6.
PIXEL_STRIDES = (4, 6)


class NotATerminal(Exception):
    pass


class Terminal:
    """`with Terminal(console) as front:` -> ready(), show(View), key(timeout), finish(lines)."""

    draws_text = True  # the gridworld as characters

    def __init__(self, console: Console, stdin=None):
        self.console = console
        self.stdin = stdin or sys.stdin
        try:
            self.fd = self.stdin.fileno()
        except (AttributeError, ValueError, OSError):
            self.fd = -1
        if self.fd < 0 or not os.isatty(self.fd):
            raise NotATerminal("esr play needs a terminal for its keys (or --web for a browser)")
        self.buffer = b""
        self.waiting: deque[KeyPress] = deque()  # keys read ahead of the game loop
        self.frame, self.frame_shown_at = None, None
        self.gone = False  # the terminal went away: every key from now on is CLOSED

    def __enter__(self):
        self.saved = termios.tcgetattr(self.fd)
        tty.setcbreak(self.fd)
        self.console.show_cursor(False)
        return self

    def __exit__(self, *exc):
        termios.tcsetattr(self.fd, termios.TCSADRAIN, self.saved)
        self.console.show_cursor(True)
        return False

    def ready(self) -> None:
        pass

    def finish(self, lines: list[str]) -> None:
        self.console.print(Text("  ".join(lines), style="bold green"))

    # ---------------------------------------------------------------- keys
    def key(self, timeout: float | None) -> KeyPress | None:
        """The next key (its name a name in game.KEYS, QUIT, CLOSED or an unknown key's text), or
        None on timeout."""
        if not self.waiting and not self._read(timeout):
            return KeyPress(CLOSED) if self.gone else None
        return self.waiting.popleft()

    def shown_at(self, frame: int) -> float | None:
        return self.frame_shown_at if frame == self.frame else None

    def _read(self, timeout: float | None) -> bool:
        """Read what the terminal has (waiting up to `timeout`) into keys stamped now, on the
        frame on screen; -> whether any key came."""
        if self.gone:
            return False
        ready, _, _ = select.select([self.fd], [], [], timeout)
        if not ready:
            return False
        try:
            data = os.read(self.fd, 64)
        except OSError:  # EIO: the terminal's other side has closed
            data = b""
        now = time.monotonic()
        if not data:  # end of input: the terminal went away (and stays readable: read no more)
            self.gone = True
            self.waiting.append(KeyPress(CLOSED, self.frame, now, self.frame_shown_at, now))
            return True
        self.buffer += data
        while self.buffer:
            self.waiting.append(KeyPress(self._next_key(), self.frame, now, self.frame_shown_at, now))
        return True

    def _next_key(self):
        b = self.buffer
        if b[:1] == b"\x1b":
            if len(b) >= 3 and b[1:2] in (b"[", b"O"):
                self.buffer = b[3:]
                return ARROWS.get(b[2:3].decode(errors="replace"), f"escape sequence {b[:3]!r}")
            self.buffer = b""
            return "escape"
        self.buffer = b[1:]
        ch = b[:1].decode(errors="replace")
        if ch == " ":
            return "space"
        if ch in ("q", "Q", "\x03", "\x04"):
            return QUIT
        return ch if ch.isprintable() else f"control key {ch!r}"

    # ---------------------------------------------------------------- drawing
    def show(self, view: View) -> None:
        while self._read(0):  # typed before this frame: stamped with the frame before it
            pass
        header = Text.assemble((view.title, "bold"), "   score ", (f"{view.score:g}", "bold"),
                               "   steps left ", (str(view.steps_left), "bold"))
        body = grid_text(view.text) if view.text is not None else picture_text(view.frame, self.console.width)
        legend = Text(view.legend, style="dim")
        message = Text(view.message, style="bold green" if view.over else "yellow")
        self.console.file.write("\x1b[H\x1b[2J")
        self.console.print(Group(header, Text(""), body, Text(""), legend, message))
        self.console.file.flush()
        self.frame, self.frame_shown_at = view.seq, time.monotonic()


    # ---------------------------------------------------------------- a study's pages
    def ask(self, page: pages.Page) -> dict | None:
        """Show `page` and return the reply (pages.py); None when the terminal went away. Keys
        typed before the page was drawn are dropped. A button is a key (y, n, space), answers
        are typed lines (Enter ends one), and q twice ends the session."""
        if self.gone:
            return None
        self._drop_typed_ahead()
        if page.items:
            return self._fill(page)
        keys = " or ".join(f"{b.key} ({b.text})" for b in page.buttons)
        self._draw(page, [Text(f"press {keys}", style="bold yellow")] if page.buttons else [])
        return self._choose(page) if page.buttons else {}

    def _drop_typed_ahead(self) -> None:
        termios.tcflush(self.fd, termios.TCIFLUSH)
        self.waiting.clear()
        self.buffer = b""

    def _choose(self, page: pages.Page) -> dict | None:
        buttons, asked = {b.key: b.name for b in page.buttons}, False
        while True:
            press = self.key(None)
            if press.name == CLOSED or (press.name == QUIT and asked):
                return None
            asked = press.name == QUIT
            if asked:
                self.console.print(Text("end the session? press q again to end it, any other key to go on", style="yellow"))
            elif press.name in buttons:
                return {"button": buttons[press.name]}

    def _fill(self, page: pages.Page) -> dict | None:
        """Each question in turn, its answer a typed line (the terminal's own line editing)."""
        answers, problem = {}, page.error
        termios.tcsetattr(self.fd, termios.TCSADRAIN, self.saved)  # lines, echoed, before the question shows
        self.console.show_cursor(True)
        try:
            for item in page.items:
                while True:
                    self._draw(page, [*item_text(item), Text(problem, style="yellow"), Text(item_prompt(item), style="bold")])
                    line = self._line()
                    if line is None:
                        return None
                    value = int(line) if line.strip().isdigit() and item["kind"] == "likert" else line
                    answers[item["id"]], problem = pages.check_item(item, value)
                    if not problem:
                        break
        finally:
            tty.setcbreak(self.fd)
            self.console.show_cursor(False)
        return {"button": page.buttons[0].name if page.buttons else "", "answers": answers}

    def _line(self) -> str | None:
        """One typed line (without its newline); None at end of input."""
        data = b""
        while not data.endswith(b"\n") and len(data) < 65536:
            try:
                chunk = os.read(self.fd, 4096)
            except OSError:
                chunk = b""
            if not chunk:
                self.gone = True
                return None
            data += chunk
        return data.decode(errors="replace").rstrip("\r\n")

    def _draw(self, page: pages.Page, below: list) -> None:
        self.console.file.write("\x1b[H\x1b[2J")
        body = [Text(printable(page.title), style="bold"), Text("")]
        for kind, text in page.blocks:
            body.append(Text(("  • " if kind == "li" else "") + printable(text), style="bold" if kind == "h" else ""))
        if page.code:
            body.append(Text(printable(page.code), style="bold green"))
        if page.error and not page.items:
            body.append(Text(printable(page.error), style="yellow"))
        self.console.print(Group(*body, Text(""), *below))
        self.console.file.flush()


def item_text(item: dict) -> list[Text]:
    """A question as the terminal shows it: its text, and a Likert scale's points and anchors."""
    lines = [Text(printable(item["text"]), style="bold")]
    if item["kind"] == "likert":
        anchors, scale = item["anchors"], item["scale"]
        named = {1: anchors[0], scale: anchors[-1]} if len(anchors) == 2 else dict(enumerate(anchors, 1))
        lines.append(Text("   ".join(f"{v} = {printable(named[v])}" if v in named else str(v) for v in range(1, scale + 1))))
    return lines


def item_prompt(item: dict) -> str:
    if item["kind"] == "likert":
        return f"type a number from 1 to {item['scale']} and press Enter" + ("" if item["required"] else " (Enter alone: skip)")
    what = "your participant id" if item["kind"] == "participant" else "your answer"
    return (f"type {what} (at most {item['max_chars']} characters) and press Enter"
            + ("" if item["required"] else " (Enter alone: skip)"))


def grid_text(rows: list[str]) -> Text:
    out = Text()
    for r, row in enumerate(rows):
        for c, ch in enumerate(row):
            out.append(ch + (" " if c < len(row) - 1 else ""), style=GRID_STYLE.get(ch, ""))
        if r < len(rows) - 1:
            out.append("\n")
    return out


def picture_text(frame: np.ndarray, columns: int | None = None) -> Text:
    """An RGB picture as rows of '▀' whose foreground is the upper pixel, background the lower,
    one pixel in every PIXEL_STRIDES[0], or in every next one where that is wider than `columns`."""
    width = np.asarray(frame).shape[1]
    stride = next((s for s in PIXEL_STRIDES if columns is None or -(-width // s) <= columns), PIXEL_STRIDES[-1])
    img = np.asarray(frame)[::stride, ::stride, :3]
    if img.shape[0] % 2:
        img = np.concatenate([img, np.zeros_like(img[:1])], axis=0)
    out = Text()
    for r in range(0, img.shape[0], 2):
        for c in range(img.shape[1]):
            top, bottom = img[r, c], img[r + 1, c]
            out.append("▀", style=f"rgb({top[0]},{top[1]},{top[2]}) on rgb({bottom[0]},{bottom[1]},{bottom[2]})")
        if r + 2 < img.shape[0]:
            out.append("\n")
    return out
