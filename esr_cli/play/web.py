"""The browser front end of `esr play --web`: a Starlette page and websocket served by uvicorn
on localhost only, in a thread beside the game loop.

The page draws each state as a PNG from esr's own renderer and sends the keys; the loop, the
robot and the log stay in Python (esr_cli/play/game.py). One browser tab plays at a time.
Closing the tab ends the episode (kept as incomplete), as does Ctrl-C in the terminal.
"""

from __future__ import annotations

import asyncio
import base64
import io
import json
import queue
import socket
import threading
import time

import numpy as np
import uvicorn
from PIL import Image
from starlette.applications import Starlette
from starlette.responses import HTMLResponse
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect

from esr_cli.play.game import QUIT, View

HOST = "127.0.0.1"  # never reachable from another machine
MAX_KEY_TEXT = 40
SCALE = {True: 3, False: 2}  # a small picture (the gridworld's) drawn larger than a large one

PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>esr play</title>
<style>
 body { background: #1e1e1e; color: #eee; font-family: system-ui, sans-serif; margin: 2em; }
 #status span { margin-right: 1.5em; } #status b { color: #fff; }
 #frame { image-rendering: pixelated; display: block; margin: 1em 0; border: 1px solid #444; }
 #message { color: #e6c84f; min-height: 1.4em; } #legend { color: #aaa; }
 body[data-over="true"] #message { color: #7fdc4f; }
</style></head>
<body data-steps-left="" data-over="false" data-connected="false">
<h2 id="title">connecting...</h2>
<div id="status"><span>score <b id="score">0</b></span><span>steps left <b id="steps">-</b></span></div>
<img id="frame" alt="the game">
<p id="legend"></p><p id="message"></p>
<script>
const KEYS = {ArrowUp: "up", ArrowDown: "down", ArrowLeft: "left", ArrowRight: "right", " ": "space", q: "quit", Q: "quit"};
const IGNORED = ["Shift", "Control", "Alt", "Meta", "CapsLock", "Tab"];
const $ = (id) => document.getElementById(id);
const ws = new WebSocket(`ws://${location.host}/ws`);
ws.onopen = () => { document.body.dataset.connected = "true"; };
ws.onmessage = (event) => {
  const m = JSON.parse(event.data);
  if (m.frame) { $("frame").src = "data:image/png;base64," + m.frame; $("frame").style.width = m.width + "px"; }
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
ws.onclose = () => { document.body.dataset.connected = "closed"; $("message").textContent += "  (the game has ended; you can close this tab)"; };
document.addEventListener("keydown", (e) => {
  if (IGNORED.includes(e.key) || ws.readyState !== WebSocket.OPEN) return;
  e.preventDefault();
  ws.send(JSON.stringify({key: KEYS[e.key] ?? e.key}));
});
</script></body></html>
"""


class PortInUse(Exception):
    pass


def png_base64(frame: np.ndarray) -> str:
    buf = io.BytesIO()
    Image.fromarray(np.asarray(frame, np.uint8)).save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode()


class Web:
    """`with Web(port, console) as front:` -> ready(), show(View), key(timeout), finish(lines)."""

    draws_text = False  # every environment as its picture

    def __init__(self, port: int, console):
        self.port, self.console = port, console
        probe = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            probe.bind((HOST, port))
        except OSError as e:
            raise PortInUse(f"port {port} on {HOST} is not free ({e.strerror}): choose another with --port") from None
        finally:
            probe.close()
        self.keys: queue.Queue = queue.Queue()
        self.latest: str | None = None
        self.socket: WebSocket | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self.connected = threading.Event()
        app = Starlette(routes=[Route("/", self._page), WebSocketRoute("/ws", self._play)])
        config = uvicorn.Config(app, host=HOST, port=port, log_level="warning", lifespan="off", ws="websockets-sansio")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="esr-play-web", daemon=True)

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}/"

    def __enter__(self):
        self.thread.start()
        deadline = time.monotonic() + 20
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise PortInUse(f"the web server did not start on {self.url}")
            time.sleep(0.05)
        return self

    def __exit__(self, *exc):
        self.server.should_exit = True
        self.thread.join(timeout=10)
        return False

    # ---------------------------------------------------------------- the server side
    async def _page(self, request):
        return HTMLResponse(PAGE)

    async def _play(self, websocket: WebSocket):
        if self.socket is not None:  # one player at a time
            await websocket.close(code=1013)
            return
        await websocket.accept()
        self.socket, self.loop = websocket, asyncio.get_running_loop()
        if self.latest is not None:
            await websocket.send_text(self.latest)
        self.connected.set()
        try:
            while True:
                data = await websocket.receive_text()
                try:
                    key = json.loads(data).get("key")
                except (json.JSONDecodeError, AttributeError):
                    key = None
                self.keys.put(str(key)[:MAX_KEY_TEXT] if key is not None else "?")
        except WebSocketDisconnect:
            pass
        finally:
            self.socket = None
            self.keys.put(QUIT)  # a closed tab ends the episode

    def _send(self, message: dict) -> None:
        text = json.dumps(message)
        self.latest = text
        ws, loop = self.socket, self.loop
        if ws is not None and loop is not None:
            future = asyncio.run_coroutine_threadsafe(ws.send_text(text), loop)
            try:
                future.result(timeout=5)
            except Exception:  # noqa: BLE001 - a tab closing mid-send: its key queue says QUIT
                pass

    # ---------------------------------------------------------------- the game side
    def ready(self) -> None:
        """Wait for the browser (Ctrl-C gives up)."""
        self.console.print(f"open {self.url} in a browser to play (Ctrl-C ends)")
        while not self.connected.wait(timeout=0.2):
            pass

    def show(self, view: View) -> None:
        frame = np.asarray(view.frame)
        self._send({"frame": png_base64(frame), "width": frame.shape[1] * SCALE[frame.shape[1] < 200],
                    "title": view.title, "score": f"{view.score:g}", "steps_left": view.steps_left,
                    "legend": view.legend, "message": view.message, "over": view.over})

    def key(self, timeout: float | None):
        try:
            return self.keys.get(timeout=timeout) if timeout is not None else self.keys.get()
        except queue.Empty:
            return None

    def finish(self, lines: list[str]) -> None:
        self._send({"message": "  ".join(lines), "over": True, "finished": True})
