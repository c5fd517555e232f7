"""Draws docs/img/play_terminal.svg (one gridworld and one Overcooked frame of `esr play` as its
terminal front end shows them), docs/img/play_web.png and docs/img/play_web_overcooked.png (the
browser front end), and docs/img/study_*.png (each stage of the example study in the browser).

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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def chromium(size: str):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", f"--window-size={size}"):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)


def wait_for(driver, script: str, timeout: float = 300) -> None:
    deadline = time.time() + timeout
    while not driver.execute_script(script):
        if time.time() > deadline:
            raise TimeoutError(script)
        time.sleep(0.1)


def web_png(spec_path: str, name: str, keys: list[str], wait_s: float) -> None:
    from selenium.webdriver.common.keys import Keys

    port, store = free_port(), tempfile.mkdtemp()
    proc = subprocess.Popen([sys.executable, "-m", "esr_cli.cli.main", "--store", store, "play", spec_path, "--robots", "random",
                             "--web", "--port", str(port), "--seed", "3", "--countdown", "0"], cwd=ROOT,
                            stderr=subprocess.PIPE, text=True)
    # The address esr prints once it serves, with the session's token.
    url = next(line.strip() for line in proc.stderr if "?token=" in line)
    driver = chromium("640,900")
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


def study_pngs() -> None:
    """The example study (experiments/studies/grid_pilot.yaml) as a participant sees it, stage by
    stage: study_1_participant.png ... study_6_end.png. Episodes are played by staying put."""
    port, store, links = free_port(), tempfile.mkdtemp(), Path(tempfile.mkdtemp()) / "links.txt"
    proc = subprocess.Popen([sys.executable, "-m", "esr_cli.cli.main", "--store", store, "play", "--study",
                             "experiments/studies/grid_pilot.yaml", "--web", "--port", str(port), "--participants", "1",
                             "--links", str(links)], cwd=ROOT, stderr=subprocess.DEVNULL)
    while not links.is_file() or not links.read_text().endswith("\n"):
        time.sleep(0.2)
    driver = chromium("760,760")
    shot = lambda n, stage: driver.save_screenshot(str(OUT / f"study_{n}_{stage}.png"))  # noqa: E731
    page_is = lambda kind: wait_for(driver, f"return document.body.dataset.page === '{kind}'")  # noqa: E731
    try:
        driver.get(links.read_text().split()[0])
        page_is("participant")
        driver.find_element("css selector", "[name=participant]").send_keys("p07")
        shot(1, "participant")
        driver.find_element("id", "button-continue").click()
        page_is("consent")
        shot(2, "consent")
        driver.find_element("id", "button-agree").click()
        page_is("instructions")
        shot(3, "instructions")
        driver.find_element("id", "button-continue").click()
        for episode in range(5):  # the practice episode, then each robot's two
            wait_for(driver, "return !document.body.dataset.page && "
                             "document.getElementById('message').textContent === 'press space to start'")
            if episode == 1:
                shot(4, "ready")
            driver.find_element("tag name", "body").send_keys(" ")
            while driver.execute_script("return document.body.dataset.over") != "true":
                driver.find_element("tag name", "body").send_keys(" ")
                time.sleep(0.15)
            if episode == 2:
                page_is("questionnaire")
                driver.find_element("css selector", "input[name=helpful][value='5']").click()
                driver.find_element("css selector", "input[name=predictable][value='3']").click()
                driver.find_element("css selector", "[name=comments]").send_keys("It kept to its side.")
                shot(5, "questionnaire")
            if episode in (2, 4):
                page_is("questionnaire")
                for name in ("helpful", "predictable"):
                    driver.find_element("css selector", f"input[name={name}][value='4']").click()
                driver.find_element("id", "button-submit").click()
        page_is("end")
        wait_for(driver, "return document.getElementById('page-code').textContent.length === 8")
        shot(6, "end")
    finally:
        driver.quit()
        proc.wait(timeout=120)


if __name__ == "__main__":
    terminal_svg()
    web_png("experiments/grid_5.yaml", "play_web.png", ["up", "right"], 0.0)
    web_png("experiments/cramped_room_random.yaml", "play_web_overcooked.png", ["left", "up", "space"], 1.0)
    study_pngs()
