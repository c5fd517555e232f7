"""Draws docs/img/play_terminal.svg and docs/img/play_web.png: one gridworld and one Overcooked
frame of `esr play`, as its terminal and browser front ends show them.

    .venv/bin/python docs/img/play_screenshots.py        # needs chromium and chromedriver
"""

import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rich.console import Console

from esr_cli import spec as specs
from esr_cli.envs import make_env
from esr_cli.play.game import Game, Robot, View
from esr_cli.play.terminal import Terminal

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "img"


def terminal_svg() -> None:
    console = Console(record=True, width=72, force_terminal=True, color_system="truecolor", file=open("/dev/null", "w"))
    front = Terminal.__new__(Terminal)  # drawing only: no keys are read
    front.console = console
    for path, kind, seed in (("experiments/grid_5.yaml", "gridworld", 3), ("experiments/cramped_room_random.yaml", "overcooked", 0)):
        spec = specs.load(ROOT / path, "paper")
        game = Game(kind, Robot("random", make_env(spec.env)), seed)
        for key in ("up", "right") if kind == "gridworld" else ("left", "up", "space"):
            game.act(key, time.time())
        front.show(View("episode 2 of 6 · robot B", game.score, game.steps_left, game.frame(), game.text(), game.legend(True),
                        "arrow keys move; space " + ("stays" if kind == "gridworld" else "interacts") + "; q ends"))
    console.save_svg(str(OUT / "play_terminal.svg"), title="esr play")


def web_png() -> None:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    store = tempfile.mkdtemp()
    proc = subprocess.Popen([sys.executable, "-m", "esr_cli.cli", "--store", store, "play", "experiments/grid_5.yaml",
                             "--robots", "random", "--web", "--port", str(port), "--seed", "3"], cwd=ROOT,
                            stderr=subprocess.PIPE, text=True)
    # The address esr prints once it serves, with the session's token.
    url = next(line.strip() for line in proc.stderr if "?token=" in line)
    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=560,820"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
    try:
        driver.get(url)
        while driver.execute_script("return document.body.dataset.stepsLeft") != "50":
            time.sleep(0.1)
        body = driver.find_element("tag name", "body")
        from selenium.webdriver.common.keys import Keys

        for key in (Keys.ARROW_UP, Keys.ARROW_RIGHT):
            body.send_keys(key)
            time.sleep(0.5)
        driver.save_screenshot(str(OUT / "play_web.png"))
    finally:
        driver.quit()
        proc.terminate()
        proc.wait()


if __name__ == "__main__":
    terminal_svg()
    web_png()
