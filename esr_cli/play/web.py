"""The browser front end of `esr play --web`: a Starlette page and websocket served by uvicorn
in a thread beside the game loops, on localhost unless `--host` says otherwise.

The page draws each state as a PNG from esr's own renderer and sends the keys; the loops, the
robots and the logs stay in Python (esr_cli/play/game.py). Each tab plays on its own Channel:
`Web` is one participant at a time on one token (`esr play --web`), `Links` a study server
with one single-use link per participant, several playing at once (`--participants N`).
Closing a tab ends its episode (kept as incomplete), as does Ctrl-C in the terminal.

Timing is measured in the browser (`performance.now()`): the page reports when each numbered
frame was painted, and each key carries the event's time stamp, the frame on screen and that
frame's paint time. A key pressed before any frame was painted names no frame.

Any web page the participant has open can reach 127.0.0.1, so the server answers only its own
page: the address esr prints carries a random token that the page and its websocket must send,
on localhost the Host header must name this server (a DNS-rebound name reaches 127.0.0.1 under
another), and the websocket must come from this server's page (its Origin). Anything else is
refused with one line on the console and never plays.
"""
from __future__ import annotations

import abc
import asyncio
import base64
import hmac
import io
import ipaddress
import json
import logging
import math
import queue
import secrets
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np
import uvicorn
from PIL import Image
from starlette.applications import Starlette
from starlette.requests import HTTPConnection
from starlette.responses import HTMLResponse, PlainTextResponse
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from esr_cli.play.game import CLOSED, KeyPress, View
from esr_cli.play.study import MAX_TEXT_ANSWER

HOST = "127.0.0.1"  # never reachable from another machine
HOST_NAMES = (HOST, "localhost", "[::1]")  # the names a browser on this machine may give it
MAX_KEY_TEXT = 40
SHOWN_KEPT = 256  # paint times kept for the most recent frames
MAX_MESSAGE_BYTES = 4096  # a key message is a few bytes; the server's frames go the other way
MAX_WAITING = 1024  # messages queued and not yet taken by the game: no person types that far ahead
# Close codes with which the websocket layer ends a connection over a bad frame from the browser.
BAD_FRAMES = {1002: "a malformed frame", 1007: "text that is not UTF-8", 1009: f"a message over {MAX_MESSAGE_BYTES:,} bytes"}
SCALE = {True: 3, False: 2}  # a small picture (the gridworld's) drawn larger than a large one
# A plain HTTP connection (the page, and a browser's keep-alive after it) is closed this long
# after it was made; one upgraded to a websocket lives as long as its participant plays. A
# browser loads the page in well under a second and reconnects when it needs to, while a client
# trickling a header or a body byte every few seconds would otherwise hold its connection, and a
# file descriptor, for ever.
HTTP_CONNECTION_S = 30.0
# Connections open at once, websockets included: a participant holds one (and a page load or
# two); past the limit a new connection drops the oldest that is not a websocket (BoundedH11).
MIN_CONNECTIONS, CONNECTIONS_PER_PARTICIPANT = 256, 3
NOTICES_PER_MINUTE = 20  # lines on the console about clients (refusals, bad requests)
# At a stop, connections still busy this long after they were asked to close are dropped: a
# client that sends requests and never reads the answers would otherwise hold the stop.
GRACEFUL_SHUTDOWN_S = 1.0
STOP_TIMEOUT = "Cancel "  # uvicorn's record of those it dropped ("Cancel N running task(s), timeout ...")

PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>esr play</title>
<style>
 body { background: #1e1e1e; color: #eee; font-family: system-ui, sans-serif; margin: 2em; }
 #status span { margin-right: 1.5em; } #status b { color: #fff; }
 #frame { image-rendering: pixelated; display: block; margin: 1em 0; border: 1px solid #444; }
 #message { color: #e6c84f; min-height: 1.4em; } #legend { color: #aaa; }
 body[data-over="true"] #message { color: #7fdc4f; }
 #page { max-width: 46em; line-height: 1.45; } #page-error { color: #e6c84f; }
 #page-code { font: bold 2em monospace; color: #7fdc4f; } #page button { font-size: 1em; margin-right: 1em; padding: .4em 1em; }
 fieldset { border: 1px solid #444; margin: 1em 0; } .scale { display: flex; gap: .5em; }
 .scale label { flex: 1; text-align: center; } .scale small { display: block; min-height: 1.2em; color: #aaa; }
 textarea, input[type=text] { width: 100%; box-sizing: border-box; font-size: 1em; }
</style></head>
<body data-steps-left="" data-over="false" data-connected="false">
<div id="game">
<h2 id="title">connecting...</h2>
<div id="status"><span>score <b id="score">0</b></span><span>steps left <b id="steps">-</b></span></div>
<img id="frame" alt="the game">
<p id="legend"></p><p id="message"></p>
</div>
<div id="page" hidden><h2 id="page-title"></h2><div id="page-body"></div><div id="page-items"></div>
<p id="page-code"></p><p id="page-error"></p><div id="page-buttons"></div></div>
<script>
const KEYS = {ArrowUp: "up", ArrowDown: "down", ArrowLeft: "left", ArrowRight: "right", " ": "space", q: "quit", Q: "quit"};
const IGNORED = ["Shift", "Control", "Alt", "Meta", "CapsLock", "Tab"];
const $ = (id) => document.getElementById(id);
const token = new URLSearchParams(location.search).get("token") ?? "";
const wsUrl = new URL(`ws?token=${encodeURIComponent(token)}`, location.href);  // beside the page (a proxy's path too)
wsUrl.protocol = location.protocol === "https:" ? "wss:" : "ws:";
const ws = new WebSocket(wsUrl);
let everOpen = false;
let onScreen = null, paintedAt = null;  // the frame number on screen and when it was painted
let form = null, items = [];  // a study's page on screen (its number) and its questions
const fromUrl = new URLSearchParams(location.search).get("participant");
let triedUrl = false;
const make = (tag, text, attrs = {}) => {  // an element whose text is text, never markup
  const el = Object.assign(document.createElement(tag), attrs);
  if (text !== undefined) el.textContent = text;
  return el;
};
function itemBox(item) {
  const box = make("fieldset", undefined, {id: "item-" + item.id});
  box.append(make("legend", item.text));
  if (item.kind === "likert") {
    const scale = make("div", undefined, {className: "scale"});
    for (let v = 1; v <= item.scale; v++) {
      const label = make("label");
      label.append(make("input", undefined, {type: "radio", name: item.id, value: String(v)}), make("span", " " + v));
      const anchor = item.anchors.length === item.scale ? item.anchors[v - 1] :
        v === 1 ? item.anchors[0] : v === item.scale ? item.anchors[1] : "";
      label.append(make("small", anchor));
      scale.append(label);
    }
    box.append(scale);
  } else if (item.kind === "text") {
    box.append(make("textarea", undefined, {name: item.id, maxLength: item.max_chars, rows: 3}));
  } else {
    box.append(make("input", undefined, {type: "text", name: item.id, maxLength: item.max_chars}));
  }
  return box;
}
function valueOf(item) {
  if (item.kind === "likert") {
    const checked = document.querySelector(`input[name="${item.id}"]:checked`);
    return checked ? Number(checked.value) : null;
  }
  return document.querySelector(`[name="${item.id}"]`).value;
}
function submit(button) {
  if (form === null || ws.readyState !== WebSocket.OPEN) return;
  for (const item of items) ws.send(JSON.stringify({form: form, item: item.id, value: valueOf(item)}));
  ws.send(JSON.stringify({form: form, button: button}));
  form = null;  // one reply per page: the server sends the next page, or this one again with what was wrong
  for (const b of document.querySelectorAll("#page-buttons button")) b.disabled = true;
}
function showPage(m) {
  const p = m.page;
  form = m.form; items = p.items; document.body.dataset.page = p.kind;
  $("game").hidden = true; $("page").hidden = false;
  $("page-title").textContent = p.title;
  $("page-body").replaceChildren(...p.blocks.map(([kind, text]) => make(kind === "h" ? "h3" : kind === "li" ? "li" : "p", text)));
  $("page-items").replaceChildren(...p.items.map(itemBox));
  $("page-code").textContent = p.code; $("page-error").textContent = p.error;
  $("page-buttons").replaceChildren(...p.buttons.map((b) => {
    const el = make("button", b.text, {type: "button", id: "button-" + b.name});
    el.onclick = () => submit(b.name);
    return el;
  }));
  if (p.kind === "participant" && fromUrl !== null && !triedUrl) {  // as a recruitment platform passes it
    triedUrl = true;
    document.querySelector('[name="participant"]').value = fromUrl;
    submit("continue");
  }
}
ws.onopen = () => { everOpen = true; document.body.dataset.connected = "true"; $("title").textContent = "connected: waiting for the game"; };
ws.onmessage = (event) => {
  const m = JSON.parse(event.data);
  if (m.page) { showPage(m); return; }
  if (m.frame) {
    form = null; delete document.body.dataset.page; $("page").hidden = true; $("game").hidden = false;
    const img = new Image();
    img.onload = () => {
      $("frame").src = img.src; $("frame").style.width = m.width + "px";
      // after the next paint: the moment the person can see it
      requestAnimationFrame(() => setTimeout(() => {
        onScreen = m.seq; paintedAt = performance.now(); document.body.dataset.frame = m.seq;
        if (ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify({shown: m.seq, t: paintedAt}));
      }, 0));
    };
    img.src = "data:image/png;base64," + m.frame;
  }
  if (m.title !== undefined) $("title").textContent = m.title;
  if (m.score !== undefined) $("score").textContent = m.score;
  if (m.steps_left !== undefined) { $("steps").textContent = m.steps_left; document.body.dataset.stepsLeft = m.steps_left; }
  if (m.legend !== undefined) $("legend").textContent = m.legend;
  if (m.message !== undefined) $("message").textContent = m.message;
  document.body.dataset.over = m.over ? "true" : "false";
  if (m.finished) { document.body.dataset.finished = "true"; }
};
// Leaving the page must end the episode even where the browser keeps the page alive in its
// back-forward cache (which would keep the socket open): close the socket on the way out.
window.addEventListener("pagehide", () => ws.close());
ws.onclose = () => {
  document.body.dataset.connected = "closed";
  if (!everOpen) $("title").textContent = "this address cannot play now: its session has begun elsewhere, or the server has stopped";
  $("message").textContent += "  (the game has ended; you can close this tab)";
  if (document.body.dataset.page && document.body.dataset.page !== "end") $("page-error").textContent = "The session has ended; you can close this tab.";
};
document.addEventListener("keydown", (e) => {
  if (document.body.dataset.page || IGNORED.includes(e.key) || ws.readyState !== WebSocket.OPEN) return;
  e.preventDefault();
  ws.send(JSON.stringify({key: KEYS[e.key] ?? e.key, frame: onScreen, t: e.timeStamp, shown: paintedAt}));
});
</script></body></html>
"""


class PortInUse(Exception):
    pass


class Notices:
    """What a server says of its clients (refusals, the web server's records), one line each, at
    most NOTICES_PER_MINUTE a minute: a client sending bad requests as fast as it can must neither
    bury the addresses and outcomes esr prints nor grow a log without bound. Lines left out are
    counted, and the count is said when the next minute's first line is, or at the stop."""

    def __init__(self, console):
        self.console = console
        self.lock = threading.Lock()
        self.since, self.shown, self.hidden = -math.inf, 0, 0

    def say(self, text: str) -> None:
        with self.lock:
            if time.monotonic() - self.since >= 60:
                self._say_hidden()
                self.since, self.shown = time.monotonic(), 0
            if self.shown < NOTICES_PER_MINUTE:
                self.shown += 1
                self.console.print(text)
            else:
                self.hidden += 1

    def close(self) -> None:
        with self.lock:
            self._say_hidden()

    def _say_hidden(self) -> None:
        if self.hidden:
            self.console.print(f"esr play: {self.hidden:,} more line(s) like these were left out (more than "
                               f"{NOTICES_PER_MINUTE} a minute)")
            self.hidden = 0


class OneLine(logging.Handler):
    """uvicorn's log records as the server's notices, one line each, never a traceback. Its record
    of a text frame that is not UTF-8 is left out: the connection's close code (1007) reports that."""

    def __init__(self, notices: Notices):
        super().__init__(logging.WARNING)
        self.notices = notices

    def emit(self, record: logging.LogRecord) -> None:
        error = record.exc_info[1] if record.exc_info else None
        if isinstance(error, (UnicodeDecodeError, asyncio.CancelledError)) or record.getMessage().startswith(STOP_TIMEOUT):
            return  # a stop that drops busy connections (GRACEFUL_SHUTDOWN_S) is no error
        text = " ".join(record.getMessage().split())[:200]
        self.notices.say(f"esr play: web server: {text}" + (f" ({type(error).__name__}: {error})"[:200] if error else ""))


def _stamp(value) -> float | None:
    """A browser time stamp in ms -> seconds; None unless a finite, non-negative number."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < 1e13:
        return None
    return round(value / 1000.0, 6)


def _frame(value) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 2**53 else None


def key_of(message: dict) -> KeyPress | None:
    """The key a page's message names ({"key": "up", "frame": 3, "t": ms, "shown": ms}), its name
    cut to MAX_KEY_TEXT (a name with a control character as its escapes, as the terminal names
    such a key, so that none is game.CLOSED) and stamps that are not numbers left unknown; None
    for any other object."""
    if "key" not in message:
        return None
    name = str(message["key"])[:MAX_KEY_TEXT]
    return KeyPress(name if name.isprintable() else f"control key {name!r}", _frame(message.get("frame")),
                    _stamp(message.get("t")), _stamp(message.get("shown")), time.monotonic())


@dataclass(frozen=True)
class FormReply:
    """Part of the reply to a study's page: one question's answer, or the button (the last part)."""

    form: int  # the page's number
    item: str | None = None
    value: object = None  # an int, text of at most MAX_TEXT_ANSWER characters, or None
    button: str | None = None


def form_of(message: dict) -> FormReply | None:
    """The reply part a page's message names ({"form": 3, "item": "q1", "value": 5} or {"form": 3,
    "button": "submit"}); None for any other object. Values are checked again by the flow."""
    form = _frame(message.get("form"))
    if form is None or "key" in message:
        return None
    button, item, value = message.get("button"), message.get("item"), message.get("value")
    if isinstance(button, str) and len(button) <= MAX_KEY_TEXT and "item" not in message:
        return FormReply(form, button=button)
    is_number = isinstance(value, int) and not isinstance(value, bool) and abs(value) < 2**31
    is_text = isinstance(value, str) and len(value) <= MAX_TEXT_ANSWER
    if "button" not in message and isinstance(item, str) and len(item) <= MAX_KEY_TEXT and (value is None or is_number or is_text):
        return FormReply(form, item, value)
    return None


def shown_of(message: dict) -> tuple[int, float] | None:
    """(frame, paint time in seconds) of a page's {"shown": frame, "t": ms}; None otherwise."""
    if "key" in message:
        return None
    frame, at = _frame(message.get("shown")), _stamp(message.get("t"))
    return None if frame is None or at is None else (frame, at)


def _json_object(text: str | None) -> dict | None:
    try:
        message = json.loads(text) if text is not None else None
    except (ValueError, RecursionError):
        return None
    return message if isinstance(message, dict) else None


def png_base64(frame: np.ndarray) -> str:
    buf = io.BytesIO()
    Image.fromarray(np.asarray(frame, np.uint8)).save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode()


class Channel:
    """One browser tab's connection: the front end (FrontEnd) a game loop or a study session
    drives: ready(), show(View), key(timeout), ask(page), shown_at(frame), finish(lines)."""

    draws_text = False  # every environment as its picture

    def __init__(self, console):
        self.console = console
        self.keys: queue.Queue = queue.Queue()
        self.painted: dict[int, float] = {}  # frame -> the browser's paint time (the latest SHOWN_KEPT)
        self.latest: str | None = None
        self.socket: WebSocket | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self.connected = threading.Event()
        self.closed = threading.Event()  # the connection has gone (or never came: the server stopped)
        self.form = 0  # the number of the last study page sent
        self.asking = False  # page replies are taken only once a study has shown a page

    # ---------------------------------------------------------------- the server side
    async def attach(self, websocket: WebSocket) -> None:
        """Serve an accepted websocket until it closes; a closed tab ends the episode."""
        self.socket, self.loop = websocket, asyncio.get_running_loop()
        try:
            if self.latest is not None:
                await websocket.send_text(self.latest)
            self.connected.set()
            await self._receive_keys(websocket)
        except WebSocketDisconnect:
            pass  # the browser left while esr was sending
        finally:
            self.socket = None
            self.end()

    def end(self) -> None:
        """The connection has gone, or the server stops: whoever waits for a key gets CLOSED."""
        self.closed.set()
        self.keys.put(KeyPress(CLOSED, received_at=time.monotonic()))

    async def _receive_keys(self, websocket: WebSocket) -> None:
        """Queue each key the page sends until it closes; anything but a key message (a binary
        frame, text that is not {"key": ...}, a bad frame) ends the connection with one line, as a
        closed tab ends it."""
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                if why := BAD_FRAMES.get(message.get("code")):
                    self._bad_message(why)
                return
            parsed = _json_object(message.get("text"))  # None for a binary frame or text that is no object
            if parsed is not None and (shown := shown_of(parsed)) is not None:
                self.painted[shown[0]] = shown[1]
                while len(self.painted) > SHOWN_KEPT:
                    del self.painted[next(iter(self.painted))]
                continue
            if self.keys.qsize() >= MAX_WAITING:  # a script, not a person: the queue stays bounded
                self._bad_message(f"more than {MAX_WAITING:,} messages the game has not taken yet")
                await websocket.close(code=1008)
                return
            if parsed is not None and self.asking and (reply := form_of(parsed)) is not None:
                self.keys.put(reply)
                continue
            key = key_of(parsed) if parsed is not None else None
            if key is None:
                self._bad_message("binary data" if message.get("bytes") is not None else "text that is not a key")
                try:
                    await websocket.close(code=1003)
                except RuntimeError:  # the websocket layer closed first, over a bad frame right behind it
                    pass
                return
            self.keys.put(key)

    def _bad_message(self, what: str) -> None:
        self.console.print(f"esr play: the browser sent {what}; its connection is closed")

    def _send(self, message: dict) -> None:
        text = json.dumps(message)
        self.latest = text
        ws, loop = self.socket, self.loop
        if ws is not None and loop is not None:
            future = asyncio.run_coroutine_threadsafe(ws.send_text(text), loop)
            try:
                future.result(timeout=5)
            except Exception:  # noqa: BLE001 - a tab closing mid-send: its key queue says CLOSED
                pass

    # ---------------------------------------------------------------- the game side
    def ready(self) -> None:
        """Wait for the browser (Ctrl-C gives up; a connection that never came leaves CLOSED queued)."""
        while not self.connected.wait(timeout=0.2) and not self.closed.is_set():
            pass

    def show(self, view: View) -> None:
        frame = np.asarray(view.frame)
        self._send({"frame": png_base64(frame), "seq": view.seq, "width": frame.shape[1] * SCALE[frame.shape[1] < 200],
                    "title": view.title, "score": f"{view.score:g}", "steps_left": view.steps_left,
                    "legend": view.legend, "message": view.message, "over": view.over})

    def key(self, timeout: float | None) -> KeyPress | None:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                got = self.keys.get(timeout=max(0.0, deadline - time.monotonic())) if deadline is not None else self.keys.get()
            except queue.Empty:
                return None
            if isinstance(got, KeyPress):
                return got  # (a page's late reply, sent twice say, is no key)

    def ask(self, page) -> dict | None:
        """Show a study's page (pages.py) and wait for its reply; None when the tab has gone."""
        self.asking = True
        self.form += 1
        self._send({"page": page.message(), "form": self.form})
        if not page.buttons:
            return {}
        wanted, buttons, answers = {i["id"] for i in page.items}, {b.name for b in page.buttons}, {}
        while True:
            got = self.keys.get()
            if isinstance(got, KeyPress):
                if got.name == CLOSED:
                    return None
                continue  # keys do nothing on a page
            if got.form != self.form:
                continue  # a reply to an earlier page
            if got.button is None and got.item in wanted:
                answers[got.item] = got.value
            elif got.button in buttons:
                return {"button": got.button, "answers": answers}

    def shown_at(self, frame: int) -> float | None:
        return self.painted.get(frame)

    def finish(self, lines: list[str]) -> None:
        self._send({"message": "  ".join(lines), "over": True, "finished": True})


def is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return host == "localhost"


class Deadline:
    """A connection's timer, HTTP_CONNECTION_S after it was made (`lived_long_enough` says what
    then), cancelled when the connection goes so that it keeps nothing alive."""

    deadline: asyncio.TimerHandle | None = None

    def start_deadline(self) -> None:
        self.deadline = asyncio.get_running_loop().call_later(HTTP_CONNECTION_S, self._deadline_reached)

    def cancel_deadline(self) -> None:
        if self.deadline is not None:
            self.deadline.cancel()
            self.deadline = None

    def _deadline_reached(self) -> None:
        self.deadline = None
        self.lived_long_enough()

    def lived_long_enough(self) -> None:
        raise NotImplementedError

    def connection_lost(self, exc) -> None:
        self.cancel_deadline()
        super().connection_lost(exc)


BAD_UPGRADE = b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"


class AnsweringWebSocket(Deadline, WebSocketsSansIOProtocol):
    """uvicorn's websocket protocol, except that an upgrade request the websockets library
    refuses (one with a body, too many or too long headers) is answered and closed at once:
    uvicorn leaves it open and unanswered, so a few hundred such requests would hold every
    connection the server keeps, and its shutdown would stop on them with a traceback. Like a
    plain connection it is dropped HTTP_CONNECTION_S after it was made unless it is open by then."""

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self.start_deadline()

    def lived_long_enough(self) -> None:
        if not self.open:
            self.transport.abort()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self.conn.handshake_exc is not None and not self.handshake_initiated and not self.close_sent:
            answer = b"".join(self.conn.data_to_send())  # the library's 414 or 431, or nothing
            self.handshake_complete = self.close_sent = True  # nothing more to say: a shutdown only closes it
            self.transport.write(answer or BAD_UPGRADE)
            self.transport.close()

    @property
    def open(self) -> bool:
        """Whether the handshake has made this a websocket a page plays on."""
        return self.handshake_complete and not self.close_sent


class BoundedH11(Deadline, H11Protocol):
    """uvicorn's HTTP/1.1 protocol with the two bounds a server open to many clients needs: at
    most `max_connections` at once, and a connection dropped HTTP_CONNECTION_S after it was made,
    whatever it is doing (one upgraded to a websocket is AnsweringWebSocket's from then on).
    Dropped, not closed: a close waits for the client to read what is still to be sent, and a
    client that never reads would keep the connection, and its place, for ever."""

    max_connections = MIN_CONNECTIONS
    warned = False  # one server's protocol class (`limited`) says once that it turned connections away
    made = 0.0

    @classmethod
    def limited(cls, max_connections: int) -> type[BoundedH11]:
        return type(cls.__name__, (cls,), {"max_connections": max_connections, "warned": False})

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self.made = time.monotonic()
        if len(self.connections) > self.max_connections:
            if not type(self).warned:  # said once: a flood of connections must not flood the console
                type(self).warned = True
                self.logger.warning(f"{self.max_connections:,} connections are open, the most this server keeps: "
                                    "each new one drops the oldest that is not a websocket")
            # The oldest plain HTTP connection gives way: clients holding connections open (a
            # header a byte at a time, answers never read) cannot keep a participant's page load
            # out, and a page loads in well under a second, so it is not the oldest for long.
            oldest = min((c for c in self.connections if isinstance(c, BoundedH11) and c is not self),
                         key=lambda c: c.made, default=None)
            if oldest is None:  # every other connection is a websocket
                transport.abort()
                return
            oldest.transport.abort()
        self.start_deadline()

    def lived_long_enough(self) -> None:
        self.transport.abort()

    def handle_websocket_upgrade(self, event) -> None:
        # The connection is the websocket's now, with its own deadline; this timer would keep
        # this protocol, and its buffers, alive for the rest of the 30 s.
        self.cancel_deadline()
        super().handle_websocket_upgrade(event)


class Server(abc.ABC):
    """The page and its websocket served by uvicorn in a thread beside the game loops. Each
    admission token lets one participant in: `admit(token)` -> the Channel its tab plays on."""

    def __init__(self, port: int, console, host: str = HOST, public_url: str | None = None, participants: int = 1):
        self.port, self.console = port, console
        # Refusals of requests without a token are the ones anyone can make by the thousand: they
        # have their own budget of lines, so they never crowd out those about invited participants.
        self.notices, self.participant_notices = Notices(console), Notices(console)
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        probe = socket.socket(family, socket.SOCK_STREAM)
        # As the server's own socket does: a port whose last connections are in TIME_WAIT (a
        # session just ended) is free to listen on.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host.strip("[]"), port))
        except OSError as e:
            raise PortInUse(f"port {port} on {host} is not free ({e.strerror}): choose another with --port") from None
        finally:
            probe.close()
        self.local = is_loopback(host)
        self.base = public_url or f"http://{host if host not in ('0.0.0.0', '::') else socket.gethostname()}:{port}/"
        app = Starlette(routes=[Route("/", self._page), WebSocketRoute("/ws", self._play)])
        config = uvicorn.Config(app, host=host.strip("[]"), port=port, log_level="warning", lifespan="off",
                                http=BoundedH11.limited(max(MIN_CONNECTIONS, CONNECTIONS_PER_PARTICIPANT * participants)),
                                ws=AnsweringWebSocket, ws_max_size=MAX_MESSAGE_BYTES, log_config=None,  # logs: OneLine
                                timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="esr-play-web", daemon=True)

    def link(self, token: str) -> str:
        return f"{self.base}?token={token}"

    @abc.abstractmethod
    def admit(self, token: str) -> Channel | str:
        """The channel for this (known) token's tab, or why it may not play now."""

    @abc.abstractmethod
    def known(self, token: str) -> bool:
        """Whether the token is one this server gave out."""

    def __enter__(self):
        # uvicorn's records go to OneLine only: a handler on the root logger would print tracebacks.
        self.log, uvicorn_log = OneLine(self.notices), logging.getLogger("uvicorn")
        self.propagate, uvicorn_log.propagate = uvicorn_log.propagate, False
        uvicorn_log.addHandler(self.log)
        self.thread.start()
        deadline = time.monotonic() + 20
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise PortInUse(f"the web server did not start on {self.base}")
            time.sleep(0.05)
        return self

    def __exit__(self, *exc):
        self.server.should_exit = True
        self.thread.join(timeout=10)
        logging.getLogger("uvicorn").removeHandler(self.log)
        logging.getLogger("uvicorn").propagate = self.propagate
        self.notices.close()
        self.participant_notices.close()
        return False

    def _refusal(self, conn: HTTPConnection) -> str | None:
        """Why a request is not one of this server's pages or websockets, or None. Off localhost
        (`--host`) any Host may name the server (a proxy's, a lab machine's), the tokens guard it."""
        host = conn.headers.get("host", "")
        if self.local and host not in {f"{name}:{self.port}" for name in HOST_NAMES}:
            return f"its Host {host[:80]!r} is not this server"
        if not self.known(conn.query_params.get("token", "")):
            return "it has no token, or not one of this server's"
        origin = conn.headers.get("origin", "")
        if conn.scope["type"] == "websocket" and origin not in (f"http://{host}", f"https://{host}"):
            return f"its Origin {origin[:80]!r} is not this server's page"
        return None

    def _refuse(self, conn: HTTPConnection, why: str) -> None:
        self.notices.say(f"esr play: refused a {'websocket' if conn.scope['type'] == 'websocket' else 'page request'}: {why}")

    async def _page(self, request):
        if why := self._refusal(request):
            self._refuse(request, why)
            return PlainTextResponse("forbidden: open the address esr play printed", status_code=403)
        return HTMLResponse(PAGE)

    async def _play(self, websocket: WebSocket):
        if why := self._refusal(websocket):
            self._refuse(websocket, why)
            await websocket.close(code=1008)  # before the handshake: an HTTP 403
            return
        channel = self.admit(websocket.query_params.get("token", ""))
        if isinstance(channel, str):  # one tab per token at a time; a used link stays used
            self.participant_notices.say(f"esr play: refused a websocket: {channel}")
            await websocket.close(code=1013)
            return
        await websocket.accept()
        await channel.attach(websocket)


class Web(Server):
    """`with Web(port, console) as front:` one participant at a time on one token, the front end
    of `esr play --web`: ready(), show(View), key(timeout), ask(page), shown_at(frame), finish(lines)."""

    draws_text = False

    def __init__(self, port: int, console, host: str = HOST, public_url: str | None = None):
        super().__init__(port, console, host, public_url)
        self.token = secrets.token_urlsafe(32)  # only who reads esr's console can open the page
        self.channel = Channel(console)

    @property
    def url(self) -> str:
        return self.link(self.token)

    def known(self, token: str) -> bool:
        return hmac.compare_digest(token.encode(), self.token.encode())

    def admit(self, token: str) -> Channel | str:
        return "a tab is already playing on this address" if self.channel.socket is not None else self.channel

    @property
    def painted(self) -> dict[int, float]:
        return self.channel.painted

    def ready(self) -> None:
        self.console.print("open this address in a browser to play (Ctrl-C ends); its token lets only you in:")
        self.console.print(f"  {self.url}")
        self.channel.ready()

    def show(self, view: View) -> None:
        self.channel.show(view)

    def key(self, timeout: float | None) -> KeyPress | None:
        return self.channel.key(timeout)

    def ask(self, page) -> dict | None:
        return self.channel.ask(page)

    def shown_at(self, frame: int) -> float | None:
        return self.channel.shown_at(frame)

    def finish(self, lines: list[str]) -> None:
        self.channel.finish(lines)


class Links(Server):
    """A study server: one single-use link per participant (its own token), each admitted tab a
    new Channel handed to `start(channel)` (a study session in its own thread). A link whose
    session has begun lets nobody in again, the same person after closing the tab included."""

    def __init__(self, port: int, console, count: int, start, host: str = HOST, public_url: str | None = None):
        super().__init__(port, console, host, public_url, participants=count)
        self.tokens = [secrets.token_urlsafe(32) for _ in range(count)]
        self.channels: dict[str, Channel] = {}
        self.start = start
        self.lock = threading.Lock()

    @property
    def links(self) -> list[str]:
        return [self.link(t) for t in self.tokens]

    def known(self, token: str) -> bool:
        return any(hmac.compare_digest(token.encode(), t.encode()) for t in self.tokens)

    def admit(self, token: str) -> Channel | str:
        link = self.tokens.index(token) + 1
        with self.lock:
            if token in self.channels:
                return f"link {link} has been used (a session began on it)"
            channel = self.channels[token] = Channel(self.console)
        self.start(channel, link)
        return channel

    @property
    def used(self) -> int:
        return len(self.channels)

    def end_all(self) -> None:
        for channel in list(self.channels.values()):
            channel.end()
