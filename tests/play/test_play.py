"""`esr play` driven as a person would: the terminal through a pseudo-terminal (keys in,
screen text out) and the browser through a real headless Chromium. Each plays a gridworld
episode to the goal and an Overcooked episode, and the logged artifact must match the keys
sent."""

import io
import json
import math
import os
import pty
import re
import select
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import pytest
from conftest import ROOT, esr, esr_env
from hypothesis import HealthCheck, event, given, settings, strategies as st
from play_script import STALE, Scripted

from esr_cli.common import specs
from esr_cli.model.envs import make_env
from esr_cli.play import session as ps
from esr_cli.play.boards import BOARDS
from esr_cli.play.game import CLOSED, QUIT, Game, KeyPress, Robot
from esr_cli.storage.play_log import state_from_record
from esr_cli.storage.store import PLAY_KIND, Store, StoreError

# An open 5 x 5 grid (no blocks) with the random robot: the way to the goal is known in advance.
GRID = ["experiments/grid_2.yaml", "--set", "env.blocks=0", "--set", "env.start=random", "--robots", "random",
        "--countdown", "0"]
COOK = ["experiments/cramped_room_random.yaml", "--set", "env.episode_steps=12", "--robots", "random", "--fps", "8",
        "--countdown", "0"]
ARROW = {"up": b"\x1b[A", "down": b"\x1b[B", "right": b"\x1b[C", "left": b"\x1b[D", "space": b" "}


def grid_keys(seed: int) -> list[str]:
    """The keys that walk the human of episode `seed` straight to its goal."""
    spec = specs.load(ROOT / GRID[0], "paper", [GRID[2], GRID[4]])
    _, k_reset = jax.random.split(jax.random.PRNGKey(seed))
    state = make_env(spec.env).reset(k_reset)
    (hr, hc), (gr, gc) = state.human.tolist(), state.goal.tolist()
    keys = ["down" if gr > hr else "up"] * abs(gr - hr) + ["right" if gc > hc else "left"] * abs(gc - hc)
    assert keys, "the human starts on its goal: pick another seed"
    return keys


def played(store: Path) -> list[Path]:
    return sorted(e.path for e in Store(store).entries() if e.kind == PLAY_KIND and e.status == "complete")


def is_subsequence(part: list, whole: list) -> bool:
    it = iter(whole)
    return all(x in it for x in part)


def logged_steps(path: Path) -> list[dict]:
    return [json.loads(line) for line in (path / "steps.jsonl").read_text().splitlines()]


# ---------------------------------------------------------------- the pieces
def test_latin_square_is_balanced():
    for n in (2, 3, 4, 5):
        rows = ps.latin_square(n)
        assert all(sorted(r) == list(range(n)) for r in rows)
        assert all(sorted(col) == sorted(list(range(n)) * (len(rows) // n)) for col in zip(*rows))
        pairs = [(r[i], r[i + 1]) for r in rows for i in range(n - 1)]
        counts = {p: pairs.count(p) for p in set(pairs)}
        assert len(counts) == n * (n - 1) and len(set(counts.values())) == 1  # every ordered pair equally often
    order = ps.episode_order(3, 6, "p7")
    assert sorted(order) == [0, 0, 1, 1, 2, 2] and order == ps.episode_order(3, 6, "p7")
    assert len({tuple(ps.episode_order(3, 3, f"p{i}")) for i in range(40)}) == 6  # all rows are used
    assert sorted(ps.robot_labels(3, "p7")) == ["robot A", "robot B", "robot C"]


def test_front_ends_meet_the_interface():
    from esr_cli.play.game import FrontEnd
    from esr_cli.play.terminal import Terminal
    from esr_cli.play.web import Web

    for cls in (Terminal, Web, Scripted):
        assert all(callable(getattr(cls, m, None)) for m in ("ready", "show", "key", "shown_at", "finish")), cls
        assert isinstance(cls.draws_text, bool)
    assert isinstance(Scripted([]), FrontEnd)


@pytest.mark.slow
def test_the_game_loop_logs_every_key_and_plays_out_a_finished_gridworld():
    spec = specs.load(ROOT / GRID[0], "paper", [GRID[2], GRID[4]])
    env = make_env(spec.env)
    keys = grid_keys(3)
    front, steps = Scripted(["x"] + keys), []
    game = Game("gridworld", Robot("random", env), 3)
    from esr_cli.play.game import play_episode

    assert play_episode(game, front, 6.0, "t", steps.append, countdown_s=0)
    assert [s.key for s in steps[: len(keys)]] == keys and all(s.key is None for s in steps[len(keys):])
    assert [s.human_action for s in steps[: len(keys)]] == [BOARDS["gridworld"].keymap[k] for k in keys]
    assert len(steps) == env.episode_steps and game.score == env.episode_steps - len(keys) + 1
    assert front.views[0].message == "press space to start" and "unknown key 'x'" in front.views[2].message
    assert front.views[-1].over and all(s.reaction_s == 0.25 for s in steps[: len(keys)])
    assert [v.seq for v in front.views] == list(range(1, len(front.views) + 1))


def test_keys_pressed_before_their_frame_are_dropped_and_counted_and_q_asks_first():
    from esr_cli.play.game import play_episode

    spec = specs.load(ROOT / GRID[0], "paper", [GRID[2], GRID[4]])
    env = make_env(spec.env)
    keys = grid_keys(3)
    # Before the gate's frame, during the countdown and on a stale frame: never applied.
    script = [STALE + "space", "up", "space"] + [STALE + keys[0], STALE + keys[0]] + keys[:1] + [QUIT, "left"] + keys[1:]
    front, steps = Scripted(script, start=False), []
    game = Game("gridworld", Robot("random", env), 3)
    assert play_episode(game, front, 6.0, "t", steps.append, countdown_s=0)
    assert [s.key for s in steps if s.key] == keys  # 'left' only answered the question
    assert steps[0].dropped_keys == 4 and sum(s.dropped_keys for s in steps) == 4  # stale space, up; two stale
    assert "end the session?" in front.views[len(keys[:1]) + 2].message
    front, steps = Scripted(keys[:1] + [QUIT, QUIT]), []
    assert not play_episode(Game("gridworld", Robot("random", env), 3), front, 6.0, "t", steps.append, countdown_s=0)
    assert len(steps) == 1
    # A countdown shows each (part of a) second and drops what is typed meanwhile.
    front, steps = Scripted(["up", None] + keys), []
    assert play_episode(Game("gridworld", Robot("random", env), 3), front, 6.0, "t", steps.append, countdown_s=0.3)
    assert [v.message for v in front.views[:2]] == ["press space to start", "starting in 1"]
    assert steps[0].dropped_keys == 1 and [s.key for s in steps if s.key] == keys


# ---------------------------------------------------------------- the Overcooked board
# cramped_room (x, y): the pot at (2, 0), onion piles at (0, 1) and (4, 1), the plate pile at
# (1, 3), the serving window at (3, 3); the robot (agent_0) starts at (1, 1), the human at (3, 1).
POT, HUMAN_START, ROBOT_START = (2, 0), (3, 1), (1, 1)


@pytest.fixture(scope="module")
def cramped_board():
    """(env, a start state) of cramped_room, the robot in agent_0's seat."""
    env = make_env(specs.load(ROOT / COOK[0], "paper").env)
    return env, jax.jit(env.reset)(jax.random.PRNGKey(0))  # compiled: a second, where op by op takes ten


def board_cell(picture, x: int, y: int):
    from esr_cli.play.overcooked_board import CELL_PX

    return picture[y * CELL_PX:(y + 1) * CELL_PX, x * CELL_PX:(x + 1) * CELL_PX]


def pixels_of(cell, colour) -> int:
    """How many pixels of `cell` are exactly `colour` (the insides of a tile's shapes are)."""
    import numpy as np

    return int((cell == np.array(colour, np.uint8)).all(-1).sum())


def all_different(pictures) -> bool:
    pictures = list(pictures)
    return all((a != b).any() for i, a in enumerate(pictures) for b in pictures[i + 1:])


def with_cell(state, x: int, y: int, obj: int, status: int = 0):
    """`state` with maze-map cell (x, y) set to `obj` (a JaxMARL object index) with `status`."""
    pad = (state.maze_map.shape[0] - 4) // 2
    cell = jax.numpy.array([obj, 0, status], "uint8")
    return state.replace(maze_map=state.maze_map.at[pad + y, pad + x].set(cell))


def test_overcooked_board_has_readable_cells_drawn_once_each(cramped_board):
    import numpy as np

    from esr_cli.play import overcooked_board as ob

    env, state = cramped_board
    picture = ob.draw_env(env, state)
    assert ob.CELL_PX >= 48 and picture.shape == (4 * ob.CELL_PX, 5 * ob.CELL_PX, 3) and picture.dtype == np.uint8
    # Every kind of cell is its own tile.
    cells = {POT: ob.tile("pot", ob.POT_EMPTY), (0, 1): ob.tile("onion_pile"), (1, 3): ob.tile("plate_pile"),
             (3, 3): ob.tile("serve"), (0, 0): ob.tile("counter"), (2, 2): ob.tile("floor")}
    assert all((board_cell(picture, *at) == tile).all() for at, tile in cells.items()) and all_different(cells.values())
    # Tiles are drawn once and reused (a frame is drawn every tick): drawing again draws none.
    drawn = ob.tile.cache_info().misses
    ob.draw_env(env, state)
    assert ob.tile.cache_info().misses == drawn and ob.tile.cache_info().hits > 0


def test_overcooked_board_shows_a_pots_onions_its_cooking_and_ready_soup(cramped_board):
    from esr_cli.play import overcooked_board as ob

    env, state = cramped_board
    # JaxMARL's pot status: 23 empty, 22-20 one to three onions (20 starts cooking), 19-1
    # cooking, 0 ready.
    pots = {status: board_cell(ob.draw_env(env, with_cell(state, *POT, ob.POT, status)), *POT)
            for status in (23, 22, 21, 20, 15, 5, 0)}
    assert all_different(pots.values())
    onions = [pixels_of(pots[s], ob.ONION_FILL) for s in (23, 22, 21)]
    assert onions[0] == 0 < onions[1] < onions[2]  # a dot per onion
    bar = [pixels_of(pots[s], ob.COOKING_BAR) for s in (20, 15, 5)]
    assert 0 < bar[0] < bar[1] < bar[2] and pixels_of(pots[21], ob.COOKING_BAR) == 0  # fills while it cooks
    assert pixels_of(pots[0], ob.READY) > 0 and pixels_of(pots[0], ob.COOKING_BAR) == 0  # a green bar and tick
    assert pixels_of(pots[5], ob.READY) == 0
    assert pixels_of(pots[15], ob.SOUP) > 0 and pixels_of(pots[21], ob.SOUP) == 0


def test_overcooked_board_shows_loose_items_on_counters(cramped_board):
    from esr_cli.play import overcooked_board as ob

    env, state = cramped_board
    for obj, item in ((ob.ONION, "onion"), (ob.PLATE, "plate"), (ob.DISH, "soup")):
        cell = board_cell(ob.draw_env(env, with_cell(state, 0, 2, obj)), 0, 2)
        assert (cell == ob.tile("counter", item)).all() and (cell != ob.tile("counter")).any()
    onion, plate, soup = (ob.tile("counter", item) for item in ("onion", "plate", "soup"))
    assert pixels_of(onion, ob.ONION_FILL) > 0 and pixels_of(plate, ob.ONION_FILL) == 0
    assert pixels_of(plate, ob.PLATE_FILL) > 0 and pixels_of(plate, ob.SOUP) == 0 and pixels_of(soup, ob.SOUP) > 0


def test_overcooked_board_shows_who_is_who_where_they_face_and_what_they_hold(cramped_board):
    from esr_cli.model.envs.overcooked import Overcooked
    from esr_cli.play import overcooked_board as ob

    env, state = cramped_board
    east = state.replace(agent_dir_idx=jax.numpy.array([3, 2], "int32"))  # the robot faces west, the human east
    for held, colour in ((ob.EMPTY, None), (ob.ONION, ob.ONION_FILL), (ob.PLATE, ob.PLATE_FILL), (ob.DISH, ob.SOUP)):
        picture = ob.draw_env(env, east.replace(agent_inv=jax.numpy.array([ob.EMPTY, held], "int32")))
        human, robot = board_cell(picture, *HUMAN_START), board_cell(picture, *ROBOT_START)
        assert pixels_of(human, ob.YOU) > 100 and pixels_of(human, ob.ROBOT) == 0
        assert pixels_of(robot, ob.ROBOT) > 100 and pixels_of(robot, ob.YOU) == 0
        if colour is not None:
            assert pixels_of(human, colour) > 0 and pixels_of(robot, colour) == 0
    assert pixels_of(board_cell(ob.draw_env(env, east), *HUMAN_START), ob.ONION_FILL) == 0  # empty hands
    # An arrow in the agent's colour reaches the edge of its cell it faces, and only that edge.
    edge = ob.CELL_PX // 6
    human, robot = board_cell(ob.draw_env(env, east), *HUMAN_START), board_cell(ob.draw_env(env, east), *ROBOT_START)
    assert pixels_of(human[:, -edge:], ob.YOU) > 0 and pixels_of(human[:, :edge], ob.YOU) == 0
    assert pixels_of(robot[:, :edge], ob.ROBOT) > 0 and pixels_of(robot[:, -edge:], ob.ROBOT) == 0
    assert pixels_of(human[:edge], ob.YOU) == pixels_of(human[-edge:], ob.YOU) == 0
    facing = [state.replace(agent_dir_idx=jax.numpy.array([0, d], "int32")) for d in range(4)]
    assert all_different(board_cell(ob.draw_env(env, s), *HUMAN_START) for s in facing)
    # In the flipped seat the person plays agent_0: agent_0 is drawn as "you".
    flipped = ob.draw_env(Overcooked(env.layout, env.episode_steps, robot_seat=1), state)
    assert pixels_of(board_cell(flipped, *ROBOT_START), ob.YOU) > 100
    assert pixels_of(board_cell(flipped, *HUMAN_START), ob.ROBOT) > 100


def test_overcooked_legend_names_every_symbol_and_colour():
    from esr_cli.play import overcooked_board as ob

    for as_text in (True, False):  # both front ends draw Overcooked's picture
        legend = BOARDS["overcooked"].legend(as_text)
        assert legend == ob.LEGEND
        for words in ("blue: you", "red: the robot", "faces", "holds", "onion", "plate", "soup", "pot", "onions in it",
                      "cooks", "ready", "onion pile", "plate pile", "serving window", "counter"):
            assert words in legend, words
    blue, red = ob.YOU, ob.ROBOT  # the colours the legend names
    assert blue[2] > max(blue[:2]) and red[0] > max(red[1:])


@pytest.mark.slow
def test_one_rule_robot_plays_two_games_at_once_as_it_plays_each_alone():
    """A study server shares each robot between its participants' sessions: a Goal Inference
    robot's belief travels with the game, so interleaved games play as each would alone."""
    from esr_cli.model.train import make_trainer

    spec = specs.load(ROOT / "experiments" / "grid_2_goal_inference.yaml", "smoke")
    trainer = make_trainer(spec)
    assert trainer.acts_by_rule
    robot = Robot("gi", trainer.env, trainer)
    moves = {0: ["up", "up", "left", "space", "up"], 1: ["left", "left", "down", "up", "right"]}

    def play(games):
        actions = {seed: [] for seed in games}
        for t in range(5):
            for seed, game in games.items():
                if not game.done:
                    actions[seed] += [s.robot_action for s in game.act(KeyPress(moves[seed][t]))]
        return actions

    alone = {seed: play({seed: Game("gridworld", robot, seed)})[seed] for seed in moves}
    together = play({seed: Game("gridworld", robot, seed) for seed in moves})
    assert together == alone and all(alone.values())


def test_overcooked_frames_are_the_board_as_the_human_plays(cramped_board):
    """Played through the game: the human turns to the onion pile, takes an onion and puts it
    in the pot; each frame is the board of the game's state."""
    import numpy as np

    from esr_cli.model.envs.overcooked import STAY
    from esr_cli.play import overcooked_board as ob
    from esr_cli.play.game import KeyPress

    env, _ = cramped_board

    class StayingRobot(Robot):  # stays put: the human's way to the pot is free
        def act(self, memory, state, key, prev_human_action):
            return STAY, memory

    game = Game("overcooked", StayingRobot("stay", env), 0)
    assert np.array_equal(game.frame(), ob.draw_env(env, game.state))
    for key in ("right", "space"):
        game.act(KeyPress(key))
    human = board_cell(game.frame(), *HUMAN_START)
    assert (human == ob.tile("you", (2, "onion"))).all() and pixels_of(human, ob.ONION_FILL) > 0
    for key in ("left", "up", "space"):
        game.act(KeyPress(key))
    picture = game.frame()
    assert (board_cell(picture, *POT) == ob.tile("pot", 22)).all()  # one onion in it
    assert (board_cell(picture, 2, 1) == ob.tile("you", (0, None))).all()  # facing the pot, hands empty


# ---------------------------------------------------------------- the terminal
class Pty:
    def __init__(self, args, store):
        self.fd, child = pty.openpty()  # the real CLI with a pseudo-terminal as its terminal
        self.proc = subprocess.Popen([sys.executable, "-m", "esr_cli.cli.main", *args], cwd=ROOT, stdin=child, stdout=child,
                                     stderr=child, env=esr_env(store, COLUMNS="100", LINES="40"), start_new_session=True)
        os.close(child)
        self.pid, self.screen = self.proc.pid, b""

    def read_until(self, pattern: bytes, timeout=120) -> bytes:
        deadline = time.time() + timeout
        while pattern not in self.screen:
            if time.time() > deadline:
                raise AssertionError(f"no {pattern!r} on the screen after {timeout} s:\n{self.screen[-2000:]!r}")
            ready, _, _ = select.select([self.fd], [], [], 0.5)
            if ready:
                try:
                    self.screen += os.read(self.fd, 65536)
                except OSError:
                    break
        return self.screen

    def send(self, data: bytes) -> None:
        os.write(self.fd, data)

    def frames(self) -> int:
        return self.screen.count(b"steps left")

    def next_frame(self, timeout=120) -> None:
        """Wait until the next frame has begun."""
        before, deadline = self.frames(), time.time() + timeout
        while self.frames() == before:
            assert time.time() < deadline, f"no new frame:\n{self.screen[-2000:]!r}"
            if select.select([self.fd], [], [], 0.05)[0]:
                self.screen += os.read(self.fd, 65536)

    def press(self, data: bytes, timeout=120) -> None:
        """Send a key and wait for the frame it brings (a key typed before its frame is dropped)."""
        before = self.frames()
        self.send(data)
        deadline = time.time() + timeout
        while self.frames() == before:
            assert time.time() < deadline, f"no new frame after {data!r}:\n{self.screen[-2000:]!r}"
            self.read_until(b"steps left", timeout=timeout)
            if select.select([self.fd], [], [], 0.1)[0]:
                self.screen += os.read(self.fd, 65536)
        # The frame's header has come; the rest of it (the message at the bottom) may be a read
        # behind on a loaded machine: read until the terminal has been quiet for a moment or the
        # next frame begins (a ticking game never goes quiet).
        after = self.frames()
        while self.frames() == after and select.select([self.fd], [], [], 0.3)[0]:
            try:
                self.screen += os.read(self.fd, 65536)
            except OSError:
                break

    def start(self) -> None:
        """Pass the ready gate."""
        self.read_until(b"press space to start", timeout=240)
        self.press(b" ")

    def wait(self, timeout=120) -> int:
        deadline = time.time() + timeout
        while time.time() < deadline:
            try:
                self.screen += os.read(self.fd, 65536) if select.select([self.fd], [], [], 0.2)[0] else b""
            except OSError:
                pass
            if self.proc.poll() is not None:
                return self.proc.returncode
        self.proc.kill()
        raise AssertionError(f"esr play did not end:\n{self.screen[-2000:]!r}")


def test_a_terminal_that_goes_away_ends_the_session_at_once():
    """Its input stays readable at end of input (or raises EIO): drawing a frame must not spin
    on it, and every key from then on is CLOSED."""
    from rich.console import Console

    from esr_cli.play.game import View
    from esr_cli.play.terminal import Terminal

    master, child = pty.openpty()
    with os.fdopen(child, "rb", buffering=0) as stdin:
        term = Terminal(Console(file=io.StringIO(), width=80), stdin=stdin)
        os.close(master)
        view = View("t", 0.0, 5, jax.numpy.zeros((8, 8, 3), "uint8"), ["..", ".."], seq=1)
        term.show(view)  # returns, having read the end of input
        assert term.key(None).name == CLOSED and term.key(0.01).name == CLOSED


def test_the_terminal_draws_overcooked_as_large_as_its_width_allows():
    import numpy as np

    from esr_cli.play.terminal import picture_text

    def columns(height, width, terminal):
        return {len(line) for line in picture_text(np.zeros((height, width, 3), "uint8"), terminal).plain.split("\n")}

    # 48-pixel cells: 12 characters a cell where that fits (cramped_room, 5 cells), 8 where it
    # would not (asymm_advantages, 9 cells, on 80 columns).
    assert columns(4 * 48, 5 * 48, 80) == {60} and columns(5 * 48, 9 * 48, 80) == {72}
    assert columns(5 * 48, 9 * 48, 120) == {108} and columns(5 * 48, 9 * 48, None) == {108}


@pytest.mark.slow
def test_terminal_gridworld_to_the_goal(tmp_path):
    keys = grid_keys(0)
    term = Pty(["play", *GRID, "--participant", "p1"], tmp_path)
    term.read_until(b"steps left")
    term.read_until(b"@")
    assert b"your goal" in term.screen
    term.start()
    for k in keys[:-1]:
        term.press(ARROW[k])
    term.send(ARROW[keys[-1]])
    assert term.wait() == 0
    assert b"session over" in term.screen
    (path,) = played(tmp_path)
    steps = logged_steps(path)
    assert [s["key"] for s in steps if s["key"] is not None] == keys
    assert [s["human_action"] for s in steps[: len(keys)]] == [BOARDS["gridworld"].keymap[k] for k in keys]
    summary = json.loads((path / "summary.json").read_text())
    assert summary["completed"] and summary["success"] and summary["participant"] == "p1"
    assert summary["score"] == 50 - len(keys) + 1 and all(s["reaction_s"] > 0 for s in steps[: len(keys)])
    # the participant's screen names the robots by their neutral labels only ("random" is this one's key)
    after = term.screen.split(b"session over")[-1]
    assert b"robot A" in after and b"random" not in after and b"esr plays --session" in after


@pytest.mark.slow
def test_terminal_overcooked_ticks_and_logs_the_keys(tmp_path):
    # 2 ticks a second: a key sent as soon as a frame shows lands on that frame even on a loaded
    # machine (a key still in the terminal when the next frame is drawn is stale, and dropped).
    term = Pty(["play", *COOK, "--participant", "p2", "--fps", "2"], tmp_path)
    term.start()
    term.next_frame()  # the first tick (and its compile) is past
    sent = ["up", "space", "left"]
    for k in sent:
        term.send(ARROW[k])
        term.next_frame()
    assert term.wait(timeout=240) == 0
    (path,) = played(tmp_path)
    steps = logged_steps(path)
    assert len(steps) == 12
    logged = [s["key"] for s in steps if s["key"] is not None]
    # A key acts on the next tick; of keys pressed within one tick the latest counts.
    assert len(logged) >= 2 and is_subsequence(logged, sent)
    assert all(s["human_action"] == BOARDS["overcooked"].keymap[s["key"]] for s in steps if s["key"])
    assert all(s["human_action"] == 4 for s in steps if s["key"] is None)  # stay


@pytest.mark.slow
def test_terminal_quit_keeps_the_episode_as_incomplete(tmp_path):
    term = Pty(["play", *GRID, "--participant", "p3", "--episodes", "2"], tmp_path)
    term.start()
    term.press(b"z")
    assert b"unknown key 'z'" in term.screen
    term.press(ARROW["up"] if grid_keys(0)[0] != "up" else ARROW["down"])
    term.press(b"q")
    assert b"end the session?" in term.screen
    term.send(b"q")
    assert term.wait() == 130
    assert b"error" not in term.screen.split(b"session over")[-1] and b"ended early" in term.screen
    (path,) = played(tmp_path)
    summary = json.loads((path / "summary.json").read_text())
    assert not summary["completed"] and summary["steps"] == 1


def test_a_robot_named_twice_is_refused_however_it_is_named():
    """Two names of one run (a key prefix and a longer prefix) are one robot: the session would
    show it under two blind labels and count it as two."""
    run = Path("/store/runs/grid_2/13abd656" + "0" * 24)
    ps._named_once(["random", "13ab"], [None, run])
    with pytest.raises(StoreError, match=r"robot 13abd6560000 is named twice \(as 13ab and 13abd656\): name each robot once"):
        ps._named_once(["13ab", "random", "13abd656"], [run, None, run])
    with pytest.raises(StoreError, match="robot random is named twice: name each robot once"):
        ps._named_once(["random", "random"], [None, None])


@pytest.mark.slow
def test_bad_input_is_one_line_and_writes_nothing(tmp_path):
    for args, message in [
        (["play", "deadbeef", "--web"], "no artifact with key 'deadbeef'"),
        (["play", "experiments/grid_2.yaml", "--set", "train.seeds=7", "--web"], "is not trained"),
        (["play", "experiments/grid_2.yaml", "--robots", ",", "--web"], "--robots: name at least one robot"),
        (["play", "experiments/grid_2.yaml", "--robots", "random,random", "--web"], "--robots: robot random is named twice"),
        (["play", "experiments/grid_2.yaml", "--robots", "random"], "needs a terminal"),
        (["play", "deadbeef", "--episodes", "99999999999"], "--episodes: between 1 and 10,000"),
        (["play", "deadbeef", "--budget", "smoke", "--web"], "--budget applies to a spec file target only"),
    ]:
        proc = esr(*args, store=tmp_path / "store", check=False, timeout=120)
        assert proc.returncode == 2 and message in proc.stderr, (args, proc.stderr)
        assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "store" / PLAY_KIND).exists()
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        proc = esr("play", *GRID, "--web", "--port", str(port), store=tmp_path / "store", check=False, timeout=120)
    assert proc.returncode == 2 and f"port {port}" in proc.stderr and "not free" in proc.stderr


@pytest.mark.slow
@pytest.mark.parametrize("stop", [signal.SIGKILL, signal.SIGTERM])
def test_an_episode_left_by_a_killed_process_is_kept_as_incomplete(tmp_path, stop):
    """SIGKILL leaves the partial episode behind; SIGTERM (a closed terminal, a shutdown) ends the
    command, but the person's steps must not go with it: both are recovered by the next play."""
    keys = grid_keys(0)
    term = Pty(["play", *GRID, "--participant", "p4"], tmp_path)
    term.start()
    term.send(ARROW[keys[0]])
    deadline = time.time() + 60
    while not list((tmp_path / PLAY_KIND).rglob("steps.jsonl")) or \
            not next((tmp_path / PLAY_KIND).rglob("steps.jsonl")).read_text():
        assert time.time() < deadline
        time.sleep(0.1)
    os.kill(term.pid, stop)
    assert term.wait() == (-signal.SIGKILL if stop == signal.SIGKILL else 143)
    assert not played(tmp_path)
    again = Pty(["play", *GRID, "--participant", "p4"], tmp_path)
    again.read_until(b"kept as incomplete")
    again.read_until(b"steps left")
    again.press(b"q")
    again.send(b"q")
    assert again.wait() == 130
    recovered = [p for p in played(tmp_path) if json.loads((p / "manifest.json").read_text()).get("recovered")]
    (path,) = recovered
    summary = json.loads((path / "summary.json").read_text())
    assert not summary["completed"] and summary["steps"] == 1 and logged_steps(path)[0]["key"] == keys[0]


# ---------------------------------------------------------------- the browser
CHROMIUM, DRIVER = shutil.which("chromium"), shutil.which("chromedriver")


def chromium():
    """A headless Chromium under Selenium (the caller quits it)."""
    assert CHROMIUM and DRIVER, "the browser tests need Chromium and its driver (Debian: chromium chromium-driver; .ci/run installs them)"
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=900,700"):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(DRIVER), options=options)


@pytest.fixture(scope="module")
def browser():
    driver = chromium()
    yield driver
    driver.quit()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve(args, store, port):
    """`esr play --web` started -> (the process, the address it printed for the participant)."""
    proc = subprocess.Popen([sys.executable, "-m", "esr_cli.cli.main", "play", *args, "--web", "--port", str(port)], cwd=ROOT,
                            env=esr_env(store), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline, printed = time.time() + 240, b""
    # Read the raw pipe (no buffer of its own) so that communicate() later reads the rest.
    while not (url := re.search(rb"(http://127\.0\.0\.1:\d+/\?token=[\w-]+)\s", printed)):
        assert proc.poll() is None, printed.decode() + proc.communicate()[1]
        assert time.time() < deadline, "the play server did not start"
        if select.select([proc.stderr], [], [], 0.2)[0]:
            printed += os.read(proc.stderr.fileno(), 65536)
    return proc, url.group(1).decode()


def wait_for(driver, script, timeout=120):
    deadline = time.time() + timeout
    while not driver.execute_script(script):
        assert time.time() < deadline, f"timed out waiting for {script}"
        time.sleep(0.1)


def press(driver, key):
    from selenium.webdriver.common.keys import Keys

    names = {"up": Keys.ARROW_UP, "down": Keys.ARROW_DOWN, "left": Keys.ARROW_LEFT, "right": Keys.ARROW_RIGHT, "space": Keys.SPACE}
    driver.find_element("tag name", "body").send_keys(names.get(key, key))


def frame_on_screen(driver) -> int:
    return int(driver.execute_script("return document.body.dataset.frame || '0'"))


def press_and_wait(driver, key) -> None:
    """Press a key and wait until the frame it brings is on screen."""
    before = frame_on_screen(driver)
    press(driver, key)
    wait_for(driver, f"return Number(document.body.dataset.frame || 0) > {before}")


@pytest.mark.slow
def test_browser_gridworld_to_the_goal(browser, tmp_path):
    from selenium.webdriver.common.keys import Keys

    keys, port = grid_keys(0), free_port()
    proc, url = serve([*GRID, "--participant", "w1"], tmp_path, port)
    browser.get(url)
    wait_for(browser, "return document.body.dataset.frame === '1'")  # the ready gate
    assert browser.execute_script("return document.getElementById('message').textContent") == "press space to start"
    assert browser.execute_script("return document.getElementById('frame').naturalWidth") > 0
    press(browser, "x")  # before the game's first frame: dropped and counted
    press_and_wait(browser, "space")
    assert browser.execute_script("return document.body.dataset.stepsLeft") == "50"
    # Three stays at once, all pressed on one frame: the first acts, the others are dropped
    # unless the next frame was already painted when they were pressed.
    browser.find_element("tag name", "body").send_keys(Keys.SPACE * 3)
    wait_for(browser, "return document.body.dataset.stepsLeft !== '50'")
    time.sleep(1)
    for k in keys:
        press_and_wait(browser, k)
    wait_for(browser, "return document.body.dataset.finished === 'true'")
    out, errs = proc.communicate(timeout=60)
    assert proc.returncode == 0, errs
    (path,) = played(tmp_path)
    steps = logged_steps(path)
    pressed = [s["key"] for s in steps if s["key"] is not None]
    stays = len(pressed) - len(keys)
    assert 1 <= stays <= 3 and pressed == ["space"] * stays + keys
    summary = json.loads((path / "summary.json").read_text())
    assert summary["completed"] and summary["score"] == 50 - len(pressed) + 1
    assert summary["dropped_keys"] == 1 + (3 - stays) and steps[0]["dropped_keys"] == 1  # the gate's 'x' on the first
    # The browser's own stamps: presses in order, each after its frame was painted.
    stamped = [s for s in steps if s["key"] is not None]
    assert all(s["reaction_s"] > 0 and s["key_pressed_at"] > s["frame_shown_at"] for s in stamped)
    assert all(a["key_pressed_at"] < b["key_pressed_at"] for a, b in zip(stamped, stamped[1:]))
    assert all(a["frame"] < b["frame"] for a, b in zip(stamped, stamped[1:]))
    header = json.loads((path / "episode.json").read_text())
    assert header["front_end"] == "web" and "performance.now()" in header["clocks"]["key_pressed_at"]


@pytest.mark.slow
def test_browser_overcooked_and_a_closed_tab(browser, tmp_path):
    port = free_port()
    # 40 ticks at 8 fps: the second episode lasts 5 s, time enough for the tab to leave it
    # even on a loaded machine (with 12 ticks it could end first).
    cook = [a.replace("episode_steps=12", "episode_steps=40") for a in COOK]
    proc, url = serve([*cook, "--participant", "w2", "--episodes", "2"], tmp_path, port)
    browser.get(url)
    wait_for(browser, "return document.body.dataset.frame === '1'", timeout=240)
    press_and_wait(browser, "space")
    for k in ("up", "space"):
        press(browser, k)
        time.sleep(0.3)
    wait_for(browser, "return document.body.dataset.over === 'true'", timeout=120)  # the first episode ends
    # The second episode numbers its frames from 1 again: wait until its gate frame is painted
    # (its message arrives before its picture), or the space would answer the first's last frame.
    wait_for(browser, "return document.body.dataset.frame === '1' && "
                      "document.getElementById('message').textContent === 'press space to start'", timeout=120)
    press_and_wait(browser, "space")  # the second begins
    browser.get("about:blank")  # the tab leaves (the page may stay in the back-forward cache)
    proc.communicate(timeout=120)
    assert proc.returncode == 130
    first, second = sorted(played(tmp_path), key=lambda p: json.loads((p / "summary.json").read_text())["episode"])
    steps = logged_steps(first)
    assert len(steps) == 40 and is_subsequence([s["key"] for s in steps if s["key"]], ["up", "space"])
    assert json.loads((first / "summary.json").read_text())["completed"]
    assert not json.loads((second / "summary.json").read_text())["completed"]


# ---------------------------------------------------------------- who may play
def refused(url: str, **headers) -> int:
    """The HTTP status of a websocket handshake (ws://) or page request (http://) with these headers."""
    import urllib.error
    import urllib.request

    import websocket

    try:
        if url.startswith("ws:"):
            websocket.create_connection(url, timeout=10, **headers).close()
        else:
            urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=10).close()
        return 200
    except websocket.WebSocketBadStatusException as e:
        return e.status_code
    except urllib.error.HTTPError as e:
        return e.code


@pytest.mark.slow
def test_only_the_printed_address_plays(tmp_path):
    """Any web page on the participant's machine can reach 127.0.0.1: the server answers only
    requests with the printed token, for its own host name, and (a websocket) from its own page.
    The refused ones play nothing and log nothing; the one with the token plays."""
    import websocket

    port = free_port()
    proc, url = serve([*GRID, "--participant", "w3"], tmp_path, port)
    token = url.split("token=")[1]
    page, ws = f"http://127.0.0.1:{port}/", f"ws://127.0.0.1:{port}/ws"
    origin = f"http://127.0.0.1:{port}"
    attempts = [(page, {}), (page + "?token=wrong", {}), (url, {"Host": f"attacker.example:{port}"}),
                (ws, {"origin": origin}), (f"{ws}?token={token[:-1]}", {"origin": origin}),
                (f"{ws}?token={token}", {"origin": "http://attacker.example"}),
                (f"{ws}?token={token}", {"origin": origin, "host": f"attacker.example:{port}"}),
                (f"{ws}?token={token}", {"suppress_origin": True})]
    assert [refused(u, **h) for u, h in attempts] == [403] * len(attempts)
    assert refused(url) == 200 and refused(url.replace("127.0.0.1", "localhost")) == 200
    assert not (tmp_path / PLAY_KIND).exists()  # nothing has begun

    # The page's own websocket plays: a key, then a binary frame, which ends the connection
    # (and the session, as a closed tab would) with one line.
    keys = grid_keys(0)
    conn = websocket.create_connection(f"{ws}?token={token}", timeout=60, origin=origin)
    gate = json.loads(conn.recv())
    assert "frame" in gate and gate["message"] == "press space to start"
    conn.send(json.dumps({"key": "space", "frame": gate["seq"]}))
    first = json.loads(conn.recv())
    conn.send(json.dumps({"key": keys[0], "frame": first["seq"]}))
    assert json.loads(conn.recv())["steps_left"] == 49
    conn.send_binary(b"\x00\x01")
    _, errs = proc.communicate(timeout=60)
    assert proc.returncode == 130, errs
    lines = errs.splitlines()
    assert sum("esr play: refused a" in line for line in lines) == len(attempts)
    assert sum("the browser sent binary data; its connection is closed" in line for line in lines) == 1
    assert "Traceback" not in errs
    (path,) = played(tmp_path)
    assert [s["key"] for s in logged_steps(path)] == keys[:1]
    assert not json.loads((path / "summary.json").read_text())["completed"]


def test_off_localhost_any_host_name_reaches_the_server_but_only_with_the_token_and_from_its_page():
    """`--host`: a lab machine's name or a proxy's stands in the Host header; the token and the
    websocket's Origin (the page's own, http or https behind a proxy) still decide."""
    from rich.console import Console

    from esr_cli.play.web import Web

    port = free_port()
    with Web(port, Console(file=io.StringIO()), host="0.0.0.0", public_url="https://lab.example/study/") as web:
        assert web.url == f"https://lab.example/study/?token={web.token}"
        page, ws, lab = f"http://127.0.0.1:{port}/", f"ws://127.0.0.1:{port}/ws", f"lab-pc.example:{port}"
        assert refused(f"{page}?token={web.token}", Host=lab) == 200
        assert refused(page, Host=lab) == 403 and refused(f"{page}?token=wrong", Host=lab) == 403
        assert refused(f"{ws}?token={web.token}", host=lab, origin="http://attacker.example") == 403
        for scheme in ("http", "https"):
            assert refused(f"{ws}?token={web.token}", host=lab, origin=f"{scheme}://{lab}") == 200
            assert web.key(timeout=10).name == CLOSED  # that tab has gone


def test_a_study_link_lets_one_tab_in_once():
    from rich.console import Console

    from esr_cli.play.web import Links

    said, started = io.StringIO(), []
    port = free_port()
    links = Links(port, Console(file=said, width=300), 2, lambda channel, link: started.append(link))
    origin = f"http://127.0.0.1:{port}"
    with links:
        first, second = (u.replace("http://", "ws://").replace("/?token=", "/ws?token=") for u in links.links)
        assert refused(first, origin=origin) == 200 and started == [1]
        assert refused(first, origin=origin) == 403 and started == [1]  # used: its session has begun
        assert refused(second, origin=origin) == 200 and started == [1, 2]
        assert refused(first.split("?")[0] + "?token=made-up", origin=origin) == 403
    assert "link 1 has been used" in said.getvalue()


def test_bad_frames_end_the_connection_with_one_line_each():
    import websocket
    from rich.console import Console

    from esr_cli.play.web import MAX_MESSAGE_BYTES, Web

    said = io.StringIO()
    port = free_port()
    web = Web(port, Console(file=said, markup=False, soft_wrap=True, width=200))
    sent = [(b"\x00\x01", websocket.ABNF.OPCODE_BINARY, "binary data"),
            ("not json", websocket.ABNF.OPCODE_TEXT, "text that is not a key"),
            ('["up"]', websocket.ABNF.OPCODE_TEXT, "text that is not a key"),
            ('{"form": 1, "button": "agree"}', websocket.ABNF.OPCODE_TEXT, "text that is not a key"),  # no study page shown
            (b"\xff\xfe", websocket.ABNF.OPCODE_TEXT, "text that is not UTF-8"),
            ("x" * (MAX_MESSAGE_BYTES + 1), websocket.ABNF.OPCODE_TEXT, f"a message over {MAX_MESSAGE_BYTES:,} bytes")]
    with web:
        for data, opcode, what in sent:
            conn = websocket.create_connection(f"ws://127.0.0.1:{port}/ws?token={web.token}", timeout=10,
                                               origin=f"http://127.0.0.1:{port}")
            conn.send(data, opcode=opcode)
            assert web.key(timeout=10).name == CLOSED  # the episode ends as with a closed tab
            conn.close()
            assert said.getvalue().splitlines()[-1] == f"esr play: the browser sent {what}; its connection is closed"
    assert len(said.getvalue().splitlines()) == len(sent) and "Traceback" not in said.getvalue()


def test_a_flood_of_keys_the_game_has_not_taken_ends_the_connection_with_one_line():
    """No person types a thousand keys ahead of the game: a page that does is a script, and the
    queue stays bounded (MAX_WAITING) rather than growing with whatever it sends."""
    import websocket
    from rich.console import Console

    from esr_cli.play.web import MAX_WAITING, Web

    said, port = io.StringIO(), free_port()
    with Web(port, Console(file=said, markup=False, soft_wrap=True, width=200)) as web:
        conn = websocket.create_connection(f"ws://127.0.0.1:{port}/ws?token={web.token}", timeout=10,
                                           origin=f"http://127.0.0.1:{port}")
        try:
            for _ in range(MAX_WAITING + 50):
                conn.send(json.dumps({"key": "up", "frame": 1}))
        except (OSError, websocket.WebSocketException):
            pass  # the server closed it mid-flood
        try:  # nothing is taken before the server has closed it: taking keys would make room
            while conn.recv():
                pass
        except (OSError, websocket.WebSocketException):
            pass
        got = []
        while (press := web.key(timeout=20)) is not None and press.name != CLOSED:
            got.append(press)
        assert press is not None and len(got) == MAX_WAITING
        conn.close()
    assert said.getvalue().splitlines() == [f"esr play: the browser sent more than {MAX_WAITING:,} messages the game "
                                            "has not taken yet; its connection is closed"]


# ---------------------------------------------------------------- fuzzed websocket messages
WEBSOCKET_FUZZ_CASES = int(os.environ.get("ESR_WEBSOCKET_FUZZ_CASES", 200))
FIELDS = ("key", "frame", "t", "shown")
_scalars = st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70), st.floats(), st.text(max_size=50))
_json = st.recursive(_scalars, lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=6), kids, max_size=4),
                     max_leaves=12)
# Objects near the page's own ({"key": ..., "frame": ..., "t": ..., "shown": ...}), with every field
# of any JSON type, the page's well-formed paint reports, and whatever else text and bytes can be.
_page_like = st.dictionaries(st.sampled_from(FIELDS) | st.text(max_size=6), _json, max_size=5).map(json.dumps)
_painted = st.builds(lambda f, t: json.dumps({"shown": f, "t": t}), st.integers(0, 2**53 - 1),
                     st.floats(0, 1e13, exclude_max=True))
_pressed = st.builds(lambda k, f, t, at: json.dumps({"key": k, "frame": f, "t": t, "shown": at}),
                     st.sampled_from(["up", "down", "left", "right", "space", "q", "y", "n"]) | st.text(max_size=60),
                     st.none() | st.integers(0, 2**53), st.floats(0, 1e13), st.none() | st.floats(0, 1e13))
_nested = st.builds(lambda n, open_: open_ * n, st.integers(1, 4000), st.sampled_from(["[", '{"key":', '{"shown":[']))
WS_TEXT = st.one_of(_page_like, _painted, _json.map(json.dumps), st.text(max_size=80), _nested)
WS_MESSAGES = st.one_of(st.tuples(st.just("text"), _pressed), st.tuples(st.just("text"), _pressed | _painted),
                        st.tuples(st.just("text"), WS_TEXT),
                        st.tuples(st.just("binary"), st.binary(max_size=60)),
                        st.tuples(st.just("raw text"), st.binary(max_size=60)),  # a text frame of any bytes
                        st.tuples(st.just("oversize"), st.integers(1, 3000)),
                        st.tuples(st.just("reserved opcode"), st.integers(3, 7)))


def expected_of(kind: str, payload) -> tuple[str, object]:
    """What the server must make of one message, read from the protocol the page speaks rather
    than from the server's code: ("key", name), ("painted", (frame, seconds)), or ("bad", the
    reason it prints)."""
    from esr_cli.play.web import MAX_KEY_TEXT, MAX_MESSAGE_BYTES

    if kind == "binary":
        return "bad", "binary data"
    if kind == "reserved opcode":
        return "bad", "a malformed frame"
    if kind == "oversize":
        return "bad", f"a message over {MAX_MESSAGE_BYTES:,} bytes"
    if kind == "raw text":
        try:
            payload = payload.decode("utf-8")
        except UnicodeDecodeError:
            return "bad", "text that is not UTF-8"
    if len(payload.encode()) > MAX_MESSAGE_BYTES:
        return "bad", f"a message over {MAX_MESSAGE_BYTES:,} bytes"
    try:
        message = json.loads(payload)
    except (ValueError, RecursionError):
        return "bad", "text that is not a key"
    if not isinstance(message, dict):
        return "bad", "text that is not a key"
    if "key" in message:  # a name with a control character is named by its escapes, as the terminal names one
        name = str(message["key"])[:MAX_KEY_TEXT]
        return "key", name if name.isprintable() else f"control key {name!r}"
    frame, at = message.get("shown"), message.get("t")
    frame_ok = type(frame) is int and 0 <= frame < 2**53
    at_ok = type(at) in (int, float) and 0 <= at < 1e13
    return ("painted", (frame, round(at / 1000, 6))) if frame_ok and at_ok else ("bad", "text that is not a key")


def send_one(conn, kind: str, payload) -> None:
    import struct

    import websocket

    if kind == "binary":
        conn.send_binary(payload)
    elif kind == "raw text":
        conn.send(payload, opcode=websocket.ABNF.OPCODE_TEXT)
    elif kind == "oversize":
        conn.send("k" * (4096 + payload))
    elif kind == "reserved opcode":  # a frame no websocket may send (opcodes 3-7 are reserved), masked as a client's
        conn.sock.sendall(struct.pack("!BB4s", 0x80 | payload, 0x80, b"\0\0\0\0"))
    else:
        conn.send(payload)


@pytest.fixture(scope="module")
def web_server():
    from rich.console import Console

    from esr_cli.play.web import Web

    said = io.StringIO()
    with Web(free_port(), Console(file=said, markup=False, soft_wrap=True, width=400)) as web:
        yield web, said


@settings(max_examples=WEBSOCKET_FUZZ_CASES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(messages=st.lists(WS_MESSAGES, min_size=1, max_size=6))
def test_fuzzed_websocket_messages_queue_only_keys_and_end_bad_ones_in_one_line(web_server, messages):
    """Whatever a page sends over an accepted websocket, the server queues exactly the key
    messages before the first message that is not a key or a paint report, records the paint
    reports, ends the connection there with one line naming what it got (a clean close prints
    nothing), and stays up for the next connection: never a traceback, never a stuck game."""
    import websocket

    from esr_cli.play.web import MAX_MESSAGE_BYTES

    web, said = web_server
    web.painted.clear()
    expected = [expected_of(kind, payload) for kind, payload in messages]
    upto = next((i for i, (what, _) in enumerate(expected) if what == "bad"), len(expected))
    lines_before = len(said.getvalue().splitlines())
    conn = websocket.create_connection(f"ws://127.0.0.1:{web.port}/ws?token={web.token}", timeout=10,
                                       origin=f"http://127.0.0.1:{web.port}")
    for kind, payload in messages:
        try:
            send_one(conn, kind, payload)
        except (OSError, websocket.WebSocketException):
            break  # the server has closed the connection over an earlier message
    if upto == len(expected):
        conn.close()
    got = []
    while (press := web.key(timeout=20)) is not None and press.name != CLOSED:
        got.append(press)
    conn.close()
    assert press is not None, "the game never heard that the connection ended"
    keys = [value for what, value in expected[:upto] if what == "key"]
    painted = dict(value for what, value in expected[:upto] if what == "painted")
    ended_by = expected[upto][1] if upto < len(expected) else None
    lines = said.getvalue().splitlines()[lines_before:]
    for p in got:
        assert p.frame is None or type(p.frame) is int and p.frame >= 0
        assert all(v is None or math.isfinite(v) and v >= 0 for v in (p.pressed_at, p.shown_at))
    # The websocket layer refuses a malformed or oversized frame as it parses the bytes of one
    # network read, before the messages that came in the same read reach the server: those may
    # be lost, and the connection ends over the refused frame.
    refused_unparsed = {what for what in ("a malformed frame", f"a message over {MAX_MESSAGE_BYTES:,} bytes")
                        if ("bad", what) in expected[upto:]}
    if unparsed := next((what for what in refused_unparsed if lines == [line_for(what)]), None):
        ended_by = unparsed + (" (with messages before it unread)" if lines != [line_for(ended_by)] else "")
        assert [p.name for p in got] == keys[:len(got)]
        # the paint reports read are a first part of those sent (a later report of one frame
        # replaces an earlier one, so compare with the reports of each first part)
        reports = [value for what, value in expected[:upto] if what == "painted"]
        assert any(web.painted == dict(reports[:n]) for n in range(len(reports) + 1)), (web.painted, reports)
    else:
        assert [p.name for p in got] == keys
        assert web.painted == painted
        assert lines == ([line_for(ended_by)] if ended_by else [])
    event(f"ended by {ended_by or 'a clean close'}")
    event(f"keys queued: {min(len(got), 3)}{'+' if len(got) >= 3 else ''}")


def line_for(what: str) -> str:
    return f"esr play: the browser sent {what}; its connection is closed"


def test_a_port_left_in_time_wait_is_free_to_serve_on():
    from rich.console import Console

    from esr_cli.play.web import Web

    # The side that closes a connection first keeps its port in TIME_WAIT, as the last
    # session's server (uvicorn, with SO_REUSEADDR) does; a new session on that port must start.
    with socket.socket() as server:
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        client = socket.create_connection(("127.0.0.1", port))
        accepted, _ = server.accept()
        accepted.close()
        time.sleep(0.1)
        client.close()
    with Web(port, Console(file=io.StringIO())) as web:
        assert web.url.startswith(f"http://127.0.0.1:{port}/?token=")


def test_a_plain_http_connection_is_closed_after_its_time_and_connections_are_bounded(monkeypatch):
    """A client trickling its request head, or a body after its answer, once held its connection
    for ever: a plain HTTP connection is closed HTTP_CONNECTION_S after it was made, whatever it
    is doing, while a websocket lives on. Past the connection limit a new connection closes the
    oldest plain one (said once on the console), so held connections keep no page load out; with
    only websockets playing it is closed at once."""
    import websocket
    from rich.console import Console

    from esr_cli.play import web as web_module

    monkeypatch.setattr(web_module, "HTTP_CONNECTION_S", 1.0)
    monkeypatch.setattr(web_module, "MIN_CONNECTIONS", 3)
    said = io.StringIO()
    port = free_port()
    with web_module.Web(port, Console(file=said, width=200)) as web:
        head = socket.create_connection(("127.0.0.1", port), timeout=10)
        head.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        body = socket.create_connection(("127.0.0.1", port), timeout=10)  # answered before its body is sent
        body.sendall(f"GET /?token={web.token} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Length: 100000\r\n\r\n".encode())
        play = websocket.create_connection(f"ws://127.0.0.1:{port}/ws?token={web.token}", timeout=10, origin=f"http://127.0.0.1:{port}")
        t0 = time.monotonic()
        for _ in range(6):  # a byte now and then: neither the head nor the body is ever whole
            time.sleep(0.3)
            for conn, byte in ((head, b"X-Slow: 1\r\n"), (body, b"x")):
                try:
                    conn.sendall(byte)
                except OSError:
                    pass
        for conn in (head, body):
            conn.settimeout(5)
            got = b""
            while chunk := conn.recv(65536):  # the page, for the second, then the close
                got += chunk
            assert time.monotonic() - t0 < 6
            conn.close()
        play.ping()  # the websocket is still open past HTTP_CONNECTION_S
        assert play.connected
        held = []
        for _ in range(2):  # with the websocket: 3, the oldest first
            held.append(socket.create_connection(("127.0.0.1", port), timeout=10))
            time.sleep(0.1)
        extra = socket.create_connection(("127.0.0.1", port), timeout=10)  # the fourth: the oldest page connection gives way
        held[0].settimeout(5)
        assert held[0].recv(1024) == b""
        extra.sendall(f"GET /?token={web.token} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
        extra.settimeout(5)
        assert extra.recv(64).startswith(b"HTTP/1.1 200")
        for conn in held + [extra]:
            conn.close()
        time.sleep(0.3)
        web.server.config.http.max_connections = 1  # the websocket alone: a new connection has nothing to take over
        late = socket.create_connection(("127.0.0.1", port), timeout=10)
        late.settimeout(5)
        assert late.recv(1024) == b"" and play.connected
        late.close()
        play.ping()
        play.close()
        web.server.config.http.max_connections = 3
        time.sleep(0.3)
        with socket.create_connection(("127.0.0.1", port), timeout=10) as ok:
            ok.sendall(f"GET /?token={web.token} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n".encode())
            assert ok.recv(64).startswith(b"HTTP/1.1 200")
    assert said.getvalue().count("connections are open, the most this server keeps") == 1


@pytest.mark.slow
def test_an_upgrade_request_the_websocket_layer_refuses_is_answered_and_closed_and_holds_no_stop():
    """An upgrade request with a body or an over-long header once stayed open unanswered (a few
    hundred kept every participant out) and made the stop print a traceback; a client that
    sends requests and never reads the answers once held the stop for 10 s."""
    from rich.console import Console

    from esr_cli.play.web import Web

    said = io.StringIO()
    port = free_port()
    web = Web(port, Console(file=said, width=200)).__enter__()
    upgrade = (f"GET /ws?token={web.token} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
               "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n")
    for extra, status in (("Content-Length: 1\r\n", b"HTTP/1.1 400"), ("X-Long: " + "a" * 9000 + "\r\n", b"HTTP/1.1 431")):
        with socket.create_connection(("127.0.0.1", port), timeout=5) as conn:
            conn.sendall((upgrade + extra + "\r\n").encode())
            got, t0 = b"", time.monotonic()
            while chunk := conn.recv(65536):
                got += chunk
            assert got.startswith(status) and time.monotonic() - t0 < 3, got[:80]
    stuck = socket.create_connection(("127.0.0.1", port), timeout=5)
    stuck.sendall((upgrade + "Content-Length: 1\r\n\r\n").encode())  # left open by the client
    greedy = socket.socket()
    greedy.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    greedy.connect(("127.0.0.1", port))
    greedy.setblocking(False)
    request = f"GET /nothing HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode()
    try:
        for _ in range(100_000):  # until the server stops reading: its answers are never read
            greedy.send(request)
    except BlockingIOError:
        pass
    time.sleep(0.5)
    t0 = time.monotonic()
    web.__exit__(None, None, None)
    assert time.monotonic() - t0 < 4 and not web.thread.is_alive()
    assert "Traceback" not in said.getvalue() and "Error" not in said.getvalue(), said.getvalue()
    stuck.close()
    greedy.close()


def test_clients_that_never_read_are_dropped_at_their_time_and_an_upgrade_keeps_no_timer(monkeypatch):
    """A connection closed at its time once waited for its client to read what was left to send:
    clients that never read kept their places past the limit, and every page load was refused.
    A websocket request once left its HTTP connection's timer, and the connection with it,
    alive for 30 s: a flood of them held memory."""
    import gc

    import websocket
    from rich.console import Console

    from esr_cli.play import web as web_module

    monkeypatch.setattr(web_module, "HTTP_CONNECTION_S", 1.0)
    monkeypatch.setattr(web_module, "MIN_CONNECTIONS", 3)
    port = free_port()
    with web_module.Web(port, Console(file=io.StringIO(), width=200)) as web:
        request = f"GET /?token={web.token} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode()
        greedy = []
        for _ in range(3):
            conn = socket.socket()
            conn.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
            conn.connect(("127.0.0.1", port))
            conn.setblocking(False)
            try:
                for _ in range(20_000):  # pages asked for and never read, until the server stops reading
                    conn.send(request)
            except BlockingIOError:
                pass
            greedy.append(conn)
        time.sleep(2.0)
        with socket.create_connection(("127.0.0.1", port), timeout=10) as ok:
            ok.sendall(request)
            assert ok.recv(64).startswith(b"HTTP/1.1 200")
        for _ in range(5):
            with pytest.raises(websocket.WebSocketBadStatusException):  # no token: a 403
                websocket.create_connection(f"ws://127.0.0.1:{port}/ws", timeout=10, origin=f"http://127.0.0.1:{port}")
        time.sleep(0.3)
        gc.collect()
        assert sum(isinstance(o, web_module.BoundedH11) for o in gc.get_objects()) <= 1  # (the page load's, closing)
        for conn in greedy:
            conn.close()


def test_what_a_server_says_of_its_clients_is_at_most_a_few_lines_a_minute(monkeypatch):
    from rich.console import Console

    from esr_cli.play import web as web_module

    clock = [1000.0]
    monkeypatch.setattr(web_module.time, "monotonic", lambda: clock[0])
    said = io.StringIO()
    notices = web_module.Notices(Console(file=said, width=200))
    for i in range(5000):
        notices.say(f"refused {i}")
    assert said.getvalue().splitlines() == [f"refused {i}" for i in range(web_module.NOTICES_PER_MINUTE)]
    clock[0] += 61
    notices.say("a minute later")
    assert said.getvalue().splitlines()[-2:] == [
        f"esr play: {5000 - web_module.NOTICES_PER_MINUTE:,} more line(s) like these were left out (more than "
        f"{web_module.NOTICES_PER_MINUTE} a minute)", "a minute later"]
    notices.say("x")
    for _ in range(web_module.NOTICES_PER_MINUTE):
        notices.say("y")
    notices.close()  # the stop says what the last minute left out
    assert said.getvalue().splitlines()[-1].startswith("esr play: 2 more line(s) like these were left out")  # 22 this minute


def test_no_page_can_pose_as_a_closed_tab_and_impossible_reaction_times_are_unknown():
    from esr_cli.play.game import CLOSED, possible_reaction
    from esr_cli.play.web import key_of

    assert key_of({"key": "closed"}).name == "closed"  # an unknown key, named back as such
    assert key_of({"key": CLOSED}).name == "control key '\\x00closed'" != CLOSED
    assert key_of({"key": "up"}).name == "up"
    sent, received = 100.0, 100.5  # esr's clock: the frame went out, the key came back half a second later
    assert possible_reaction(KeyPress("up", 1, 20.3, 20.0, received), sent) == pytest.approx(0.3)
    assert possible_reaction(KeyPress("up", 1, 20.0, 20.3, received), sent) is None  # pressed before it was shown
    assert possible_reaction(KeyPress("up", 1, 9e9, 0.0, received), sent) is None  # longer than esr waited
    assert possible_reaction(KeyPress("up", 1, 20.3, None, received), sent) is None
    assert possible_reaction(KeyPress("up", 1, 20.3, 20.0, received), None) == pytest.approx(0.3)


# ---------------------------------------------------------------- the data it leaves
@pytest.mark.slow
def test_overcooked_episodes_export_to_the_human_data_schema_and_replay(tmp_path):
    """A played Overcooked episode, exported as overcooked-ai rows, converts back to the logged
    JaxMARL states, and each row's joint action steps its state to its next state (the 2019
    trials' columns, dtypes and overcooked-ai's loader: tests/play/test_export.py)."""
    import numpy as np

    from esr_cli.model.humans import overcooked_data as od
    from esr_cli.play import export
    from esr_cli.storage.artifacts import ensure

    spec = specs.load(ROOT / COOK[0], "paper", ["env.episode_steps=40"])
    env = make_env(spec.env)
    rng = np.random.default_rng(0)
    script = [k for _ in range(40) for k in (str(rng.choice(["up", "down", "left", "right", "space"])), None)]
    opponent = ps.Opponent("random", "robot A", Robot("random", env))
    store = Store(tmp_path)
    built = ensure(ps.episode_recipe(spec, opponent, "p9", "s1", 0, 5, Scripted(script), "test", 8.0, "t", 0), store)
    summary = built.summary()
    assert summary["completed"] and summary["steps"] == 40 and summary["keys"] == 40
    frame = export.trajectory_frame([built.path], env)
    assert list(frame.columns) == list(export.COLUMNS) and len(frame) == 40
    assert frame.attrs["esr"]["episodes"][0]["human_player"] == 1 and frame["layout_name"].eq("cramped_room").all()
    logged = [state_from_record(env, s["state"]) for s in logged_steps(built.path)]
    back = od.to_jaxmarl(env, list(frame["state"]))
    for field in ("agent_pos", "agent_dir_idx", "agent_inv", "maze_map"):
        want = np.stack([np.asarray(getattr(s, field)) for s in logged])
        np.testing.assert_array_equal(np.asarray(getattr(back, field)), want, err_msg=field)
    nxt = od.to_jaxmarl(env, list(frame["next_state"]))
    actions = np.array([od.parse_joint_action(t) for t in frame["joint_action"]], np.int32)
    stepped, _ = jax.jit(jax.vmap(env.step_joint))(back, actions[:, 0], actions[:, 1])
    for field in ("agent_pos", "agent_dir_idx", "agent_inv", "maze_map"):
        np.testing.assert_array_equal(np.asarray(getattr(stepped, field)), np.asarray(getattr(nxt, field)), err_msg=field)
    # The CLI lists it and writes the same rows as a DataFrame that pandas reads back.
    proc = esr("plays", "--participant", "p9", "--export", str(tmp_path / "out" / "p9.pickle"), store=tmp_path, COLUMNS="300")
    assert built.path.name in proc.stdout and "exported 1 Overcooked episode(s), 40 rows" in proc.stderr
    import pandas as pd

    again = pd.read_pickle(tmp_path / "out" / "p9.pickle")
    assert list(again["joint_action"]) == list(frame["joint_action"])
    esr("plays", "--participant", "p9", "--export", str(tmp_path / "out" / "p9.csv"), store=tmp_path)
    assert list(pd.read_csv(tmp_path / "out" / "p9.csv")["joint_action"]) == list(frame["joint_action"])
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["p9.csv", "p9.pickle"]  # no temporary file left
    # As a human's data: the person's view of each logged state and their action, on this
    # layout only; one episode leaves no test split.
    from esr_cli.recipes import play_data

    data = play_data.convert([built.path], "cramped_room")
    np.testing.assert_array_equal(data["action"], [s["human_action"] for s in logged_steps(built.path)])
    states = jax.tree.map(lambda *xs: np.stack(xs), *logged)
    np.testing.assert_array_equal(data["obs"], np.asarray(jax.vmap(env.observe_human)(states), np.uint8))
    assert (data["player"] == 1).all() and not data["test"].any() and (data["game"] == 0).all()
    with pytest.raises(play_data.PlayDataError, match="is not an Overcooked episode on coord_ring"):
        play_data.convert([built.path], "coord_ring")
    # A selection of nothing lists nothing, as `esr ls` does; asked for a file, it writes none and fails.
    nobody = esr("plays", "--participant", "nobody", store=tmp_path, check=False)
    assert nobody.returncode == 0 and "no played episodes" in nobody.stderr and "for that selection" in nobody.stderr
    nothing = esr("plays", "--participant", "nobody", "--csv", str(tmp_path / "out" / "none.csv"), store=tmp_path, check=False)
    assert nothing.returncode == 1 and not (tmp_path / "out" / "none.csv").exists()


@pytest.mark.slow
def test_plays_by_robot_averages_each_participant_first_and_writes_one_csv_row_per_episode(tmp_path):
    import csv
    import statistics

    from esr_cli.storage.artifacts import ensure

    spec = specs.load(ROOT / GRID[0], "paper", [GRID[2], GRID[4]])
    env = make_env(spec.env)
    store = Store(tmp_path)
    trained = "0123456789abcdef0123456789abcdef"  # a run key as a robot's reference (it plays uniformly here)
    robots = [ps.Opponent("random", "robot A", Robot("random", env)), ps.Opponent(trained, "robot B", Robot(trained, env))]
    # p1 and p2 play both robots twice; p3 ends robot B's only episode early (q, confirmed).
    plan = [(p, robot, ep) for p in ("p1", "p2") for ep, robot in enumerate(robots * 2)] + [("p3", robots[1], 0)]
    for participant, robot, episode in plan:
        seed = episode + (5 if participant == "p2" else 0)  # p2 meets other start states
        keys = grid_keys(seed)
        script = keys[:1] + [QUIT, QUIT] if participant == "p3" else keys + ["space"] * 50
        ensure(ps.episode_recipe(spec, robot, participant, f"s-{participant}", episode, seed, Scripted(script), "test",
                                 6.0, "t", 0), store)

    proc = esr("plays", "--by-robot", "--csv", str(tmp_path / "out" / "plays.csv"), store=tmp_path, COLUMNS="400")
    with open(tmp_path / "out" / "plays.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(plan) and {r["participant"] for r in rows} == {"p1", "p2", "p3"}
    summaries = {e.key: e.manifest["summary"] for e in Store(tmp_path).entries() if e.kind == PLAY_KIND}
    for r in rows:
        assert float(r["return"]) == summaries[r["key"]]["score"] and (r["completed"] == "True") == summaries[r["key"]]["completed"]
    assert [r["completed"] for r in rows if r["participant"] == "p3"] == ["False"]
    # independently: completed episodes averaged per participant, then across participants
    for robot in ("random", trained):
        per_person = [statistics.mean(float(r["return"]) for r in rows if r["robot"] == robot and r["participant"] == p
                                      and r["completed"] == "True") for p in ("p1", "p2")]
        mean, se = statistics.mean(per_person), statistics.stdev(per_person) / math.sqrt(2)
        line = next(line for line in proc.stdout.splitlines() if robot in line)
        assert se > 0 and f"{mean:.2f} ± {se:.2f}" in line, line
    trained_line = next(line for line in proc.stdout.splitlines() if trained in line)
    assert "3 (2 with a completed episode)" in trained_line and "4 of 5 completed" in trained_line
    assert f"written {len(plan)} episode(s)" in proc.stderr
    # Every step of every episode (gridworld included) as JSON lines, with its episode's fields.
    proc = esr("plays", "--participant", "p3", "--export", str(tmp_path / "out" / "p3.jsonl"), store=tmp_path)
    (key,) = [r["key"] for r in rows if r["participant"] == "p3"]
    lines = [json.loads(line) for line in (tmp_path / "out" / "p3.jsonl").read_text().splitlines()]
    logged = logged_steps(Store(tmp_path).lookup(PLAY_KIND, key))
    assert len(lines) == len(logged) >= 1 and "exported 1 episode(s)" in proc.stderr
    for line, step in zip(lines, logged):
        assert line["play_key"] == key and line["participant"] == "p3" and line["robot"] == trained
        assert line["robot_label"] == "robot B" and line["env"] == "gridworld" and line["layout"] is None
        assert {k: line[k] for k in step} == step  # the logged step, state included, unchanged
        assert line["human_action_name"] == ("left", "down", "right", "up", "stay")[step["human_action"]]
    # An Overcooked export of gridworld episodes cannot be made: one line, nothing printed first.
    refused = esr("plays", "--participant", "p3", "--export", str(tmp_path / "out" / "p3.csv"), store=tmp_path, check=False)
    assert refused.returncode == 2 and refused.stdout == "" and not (tmp_path / "out" / "p3.csv").exists()
    assert refused.stderr.strip() == "error: --export: none of these episodes is an Overcooked episode"


def test_every_environment_kind_has_a_board_that_meets_its_protocol():
    """esr play asks the environment's board, never its kind: every env.kind a spec accepts has
    one, with a key for each of the person's keys and a picture of a reset state."""
    from esr_cli.model import spec as spec_model
    from esr_cli.model.envs import make_env
    from esr_cli.play.boards import board_for
    from esr_cli.play.game import KEYS

    assert set(BOARDS) == set(spec_model.KIND_MODELS["env"])
    for kind in BOARDS:
        board = board_for(kind)
        assert set(board.keymap) == set(KEYS) and isinstance(board.space_does, str)
        spec = specs.load(ROOT / "experiments" / ("grid_2.yaml" if kind == "gridworld" else "cramped_room.yaml"), "smoke")
        env = make_env(spec.env)
        state = env.reset(jax.random.PRNGKey(0))
        picture = board.frame(env, state)
        assert picture.ndim == 3 and picture.shape[2] == 3 and picture.size > 0
        assert board.legend(True) and board.legend(False)
    with pytest.raises(ValueError, match="no board for env.kind 'nope'"):
        board_for("nope")
