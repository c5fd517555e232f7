"""Draws docs/img/play_terminal.svg (one gridworld and one Overcooked frame of `esr play` as its
terminal front end shows them), docs/img/play_web.png and docs/img/play_web_overcooked.png (the
browser front end).

    .venv/bin/python docs/img/play_screenshots.py        # needs chromium and chromedriver
"""

import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rich.console import Console

from esr_cli.common import specs
from esr_cli.model.envs import make_env
from esr_cli.play.game import Game, KeyPress, Robot, View
from esr_cli.play.terminal import Terminal

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "img"


def terminal_svg() -> None:
    console = Console(record=True, width=72, force_terminal=True, color_system="truecolor", file=open("/dev/null", "w"))
    front = Terminal.__new__(Terminal)  # drawing only: no keys are read
    front.console = console
    front._read = lambda timeout: False  # no keys to read before a frame
    for path, kind, seed in (("experiments/grid_5.yaml", "gridworld", 3), ("experiments/cramped_room_random.yaml", "overcooked", 0)):
        spec = specs.load(ROOT / path, "paper")
        game = Game(kind, Robot("random", make_env(spec.env)), seed)
        for key in ("up", "right") if kind == "gridworld" else ("left", "up", "space"):
            game.act(KeyPress(key))
        front.show(View("episode 2 of 6 · robot B", game.score, game.steps_left, game.frame(), game.text(), game.legend(True),
                        "arrow keys move; space " + ("stays" if kind == "gridworld" else "interacts") + "; q ends"))
    console.save_svg(str(OUT / "play_terminal.svg"), title="esr play")


def web_png(spec_path: str, name: str, keys: list[str], wait_s: float) -> None:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.keys import Keys

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    store = tempfile.mkdtemp()
    proc = subprocess.Popen([sys.executable, "-m", "esr_cli.cli.main", "--store", store, "play", spec_path, "--robots", "random",
                             "--web", "--port", str(port), "--seed", "3", "--countdown", "0"], cwd=ROOT,
                            stderr=subprocess.PIPE, text=True)
    # The address esr prints once it serves, with the session's token.
    url = next(line.strip() for line in proc.stderr if "?token=" in line)
    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=640,900"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
    named = {"up": Keys.ARROW_UP, "down": Keys.ARROW_DOWN, "left": Keys.ARROW_LEFT, "right": Keys.ARROW_RIGHT, "space": " "}
    try:
        driver.get(url)
        while not (driver.execute_script("return document.body.dataset.stepsLeft") or "").isdigit():
            time.sleep(0.1)  # the first frame (the robot's program compiles first)
        body = driver.find_element("tag name", "body")
        time.sleep(1.0)
        body.send_keys(" ")  # the ready gate
        time.sleep(1.0)
        for key in keys:
            body.send_keys(named[key])
            time.sleep(0.5)
        time.sleep(wait_s)
        driver.save_screenshot(str(OUT / name))
    finally:
        driver.quit()
        proc.terminate()
        proc.wait()


if __name__ == "__main__":
    terminal_svg()
    web_png("experiments/grid_5.yaml", "play_web.png", ["up", "right"], 0.0)
    web_png("experiments/cramped_room_random.yaml", "play_web_overcooked.png", ["left", "up", "space"], 1.0)
