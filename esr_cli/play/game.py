"""One game loop for every front end: a person in the human's seat, a robot in the other.

The person's keys are named `up`, `down`, `left`, `right` and `space`; `KEYMAP` turns them into
the environment's human actions (space: stay in the gridworld, interact in Overcooked). A
gridworld advances one step per key; Overcooked advances at a fixed rate, a tick without a
key being `stay`. Once the gridworld's human is on the goal (or trapped) nothing can move any
more, so the remaining steps are played out at once: the return counts every step on the goal,
as in training.

Timing (docs/play.md): every picture a front end shows is a numbered frame, and every key
arrives as a `KeyPress` naming the frame that was on screen when it was pressed, with the front
end's own stamps of the press and of that frame's display. A key acts only on the frame it was
pressed on: a key pressed before that frame was shown (typed ahead, or in flight while the
game moved on) is dropped and counted, never applied. Each episode opens with a ready gate (the
first state, "press space to start") and a countdown; Overcooked's clock starts after it. `q`
asks for confirmation (the game waits meanwhile); a closed tab or terminal ends at once.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from esr_cli.play.boards import board_for
from esr_cli.storage.play_log import state_record

KEYS = ("up", "down", "left", "right", "space")
QUIT = "quit"  # the person asks to end the session (confirmed before it ends)
# The tab or the terminal went away: the session ends at once. A control character no front
# end passes on in a key's name, so that no page can pose as a closed tab by naming this key.
CLOSED = "\x00closed"
START_KEY = "space"
RANDOM_ROBOT = "random"


class Robot:
    """The robot a person plays with: one seed of a trained run (its Boltzmann policy, or its
    rule for Goal Inference), or a uniformly random robot (`trainer=None`)."""

    def __init__(self, ref: str, env, trainer=None, lstate=None):
        self.ref, self.env = ref, env
        uniform = trainer is None or not trainer.method.learns_policy
        self.by_rule = trainer is not None and trainer.acts_by_rule

        if self.by_rule:
            method = trainer.method
            self._start = jax.jit(lambda state: method.memory_init(env.observe(state)))
            self._rule = jax.jit(lambda memory, state, prev, key: method.rule_step(memory, env.observe(state), prev, key))
        else:
            def act(state, key):
                if uniform:
                    return jax.random.randint(key, (), 0, env.num_robot_actions, dtype=jnp.int32)
                return trainer.robot_action(lstate, env.observe(state)[None], key, "sample")[1][0]

            self._act = jax.jit(act)

    def warm(self, state) -> None:
        """Compile the robot's step now, so that the first ticks of a game are not late."""
        if self.by_rule:
            self._rule(self._start(state), state, jnp.int32(0), jax.random.PRNGKey(0))
        else:
            self._act(state, jax.random.PRNGKey(0))

    # The robot holds no episode's state (a rule's memory goes back to the caller): one robot
    # serves every participant of a study server at once.
    def start(self, state):
        """-> the memory an episode starts with (None for a policy)."""
        return self._start(state) if self.by_rule else None

    def act(self, memory, state, key, prev_human_action: int) -> tuple[int, object]:
        """-> (the robot's action, the memory after it)."""
        if self.by_rule:
            action, memory = self._rule(memory, state, jnp.int32(prev_human_action), key)
            return int(action), memory
        return int(self._act(state, key)), memory


@dataclass(frozen=True)
class KeyPress:
    """A key as a front end saw it. Stamps in seconds on the front end's own clock (the browser's
    `performance.now()`, the terminal's monotonic clock at read time); None where unknown."""

    name: str  # a name in KEYS, QUIT, CLOSED, or an unknown key's text
    frame: int | None = None  # the frame on screen when it was pressed (None: before the first)
    pressed_at: float | None = None
    shown_at: float | None = None  # when that frame was shown, on the same clock
    received_at: float = 0.0  # esr's monotonic clock when the game loop got it

    @property
    def reaction_s(self) -> float | None:
        if self.pressed_at is None or self.shown_at is None:
            return None
        return round(self.pressed_at - self.shown_at, 6)  # the stamps' own precision (a microsecond)


# The front end's stamps' rounding: a browser coarsens performance.now() to protect its users,
# to 100 ms at most (Tor Browser; Firefox's fingerprinting protection to 16.7 ms).
CLOCK_SLACK_S = 0.1


def possible_reaction(press: KeyPress, frame_sent_at: float | None) -> float | None:
    """The key's reaction time where it can be one: never below zero, and never longer than esr
    waited between sending the frame and getting the key (the frame was shown after it was
    sent, the key pressed before it came). A front end's stamps are its own (a page's script
    sends them), so others are recorded as they came and the reaction as unknown."""
    reaction = press.reaction_s
    if reaction is None or reaction < 0:
        return None
    if frame_sent_at is not None and reaction > press.received_at - frame_sent_at + CLOCK_SLACK_S:
        return None
    return reaction


@dataclass
class Step:
    t: int
    key: str | None  # the key pressed; None on a tick without one, or a step played out
    human_action: int
    robot_action: int
    reward: float
    score: float  # the return so far, this step's reward included
    wall_time: float  # unix time of the step
    reaction_s: float | None  # the key's press minus its frame's display (front end's clock); None without a key
    state: dict  # the environment state the step was taken from (state_record)
    frame: int | None = None  # the frame that showed `state`
    frame_sent_at: float | None = None  # esr's monotonic clock when that frame went to the front end
    frame_shown_at: float | None = None  # the front end's clock when it was on screen
    key_pressed_at: float | None = None  # the front end's clock
    key_received_at: float | None = None  # esr's monotonic clock
    dropped_keys: int = 0  # keys dropped since the previous step (pressed before the frame they would act on)


class Game:
    """One episode. `act(press, frame)` plays one step (press None: a tick without a key) from
    the state `frame` showed and returns its records, more than one when the rest of a finished
    gridworld episode is played out."""

    def __init__(self, env_kind: str, robot: Robot, seed: int):
        self.board, self.robot, self.env = board_for(env_kind), robot, robot.env
        self.key = jax.random.PRNGKey(seed)
        self.key, k_reset = jax.random.split(self.key)
        self.state = self.env.reset(k_reset)
        self.memory = self.robot.start(self.state)
        self.t, self.score, self.prev_human = 0, 0.0, 0
        self._step = jax.jit(self.env.step)
        self.robot.warm(self.state)  # compiled before the first frame is shown
        jax.block_until_ready(self._step(self.state, jnp.int32(0), jnp.int32(0)))

    @property
    def ticks(self) -> bool:
        return self.board.idle_action is not None

    @property
    def steps_left(self) -> int:
        return self.env.episode_steps - self.t

    @property
    def done(self) -> bool:
        return self.t >= self.env.episode_steps

    def act(self, press: KeyPress | None, frame: dict | None = None) -> list[Step]:
        """`frame`: the Step fields of the frame the step is taken from (frame, frame_sent_at,
        frame_shown_at, dropped_keys), recorded on the first step."""
        keymap = self.board.keymap
        if press is None:
            steps = [self._advance(self.board.idle_action, None, frame)]
        else:
            if press.name not in keymap:
                raise ValueError(f"unknown key {press.name!r}: {', '.join(KEYS)}")
            steps = [self._advance(keymap[press.name], press, frame)]
        rest = self.board.finished_early(self.env, self.state)
        if rest is not None:
            while not self.done:  # nothing can move any more: play the rest out
                steps.append(self._advance(rest, None, None))
        return steps

    def _advance(self, human_action: int, press: KeyPress | None, frame: dict | None) -> Step:
        if self.done:
            raise RuntimeError("the episode is over")
        before = state_record(self.state)
        self.key, k_robot = jax.random.split(self.key)
        robot_action, self.memory = self.robot.act(self.memory, self.state, k_robot, self.prev_human)
        self.state, reward = self._step(self.state, jnp.int32(robot_action), jnp.int32(human_action))
        self.t, self.score, self.prev_human = self.t + 1, self.score + float(reward), human_action
        timing = dict(frame or {})
        if press is not None:
            timing.update(key_pressed_at=press.pressed_at, key_received_at=round(press.received_at, 6))
            if press.shown_at is not None:
                timing["frame_shown_at"] = press.shown_at
        return Step(self.t - 1, None if press is None else press.name, human_action, robot_action, float(reward),
                    self.score, time.time(), None if press is None else possible_reaction(press, timing.get("frame_sent_at")),
                    before, **timing)

    def state_record(self) -> dict:
        return state_record(self.state)

    def frame(self) -> np.ndarray:
        """The current state as an RGB picture (the environment's board, esr_cli/play/boards.py)."""
        return self.board.frame(self.env, self.state)

    def legend(self, as_text: bool) -> str:
        """What the person is looking at: the characters of `text()`, or the picture's colours."""
        return self.board.legend(as_text)

    def text(self) -> list[str] | None:
        """The state in characters where the board has them (the terminal draws these), else None."""
        return self.board.text(self.env, self.state)


@dataclass
class View:
    """What a front end shows: the picture, the header and a one-line message."""

    title: str
    score: float
    steps_left: int
    frame: np.ndarray
    text: list[str] | None
    legend: str = ""
    message: str = ""
    over: bool = False
    seq: int = 0  # the frame's number: counted by the game loop within an episode


@runtime_checkable
class FrontEnd(Protocol):
    """What the game loop needs from a front end (the terminal, the browser, a test's script)."""

    draws_text: bool  # True: the gridworld as characters (View.text); False: pictures only

    def ready(self) -> None:
        """Block until a person can play (the browser has connected)."""
        ...

    def show(self, view: View) -> None: ...

    def key(self, timeout: float | None) -> KeyPress | None:
        """The next key within `timeout` seconds (None: wait), its name a name in KEYS, QUIT,
        CLOSED or any other string for an unknown key; None when the time ran out."""
        ...

    def shown_at(self, frame: int) -> float | None:
        """When the front end had `frame` on screen (its own clock), if it has said so."""
        ...

    def finish(self, lines: list[str]) -> None:
        """The session is over: show these lines."""
        ...


class Screen:
    """Numbers the frames a front end shows and remembers when each was sent."""

    def __init__(self, front: FrontEnd, game: Game, title: str):
        self.front, self.game, self.title = front, game, title
        self.frame, self.sent_at = 0, 0.0

    def show(self, message: str, over: bool = False) -> None:
        game = self.game
        text = game.text() if self.front.draws_text else None
        self.frame += 1
        view = View(self.title, game.score, game.steps_left, game.frame(), text, game.legend(text is not None),
                    message, over, self.frame)
        self.sent_at = time.monotonic()  # as it goes: the front end can show it no sooner
        self.front.show(view)

    def record(self, dropped: int) -> dict:
        """The current frame's Step fields."""
        return {"frame": self.frame, "frame_sent_at": round(self.sent_at, 6),
                "frame_shown_at": self.front.shown_at(self.frame), "dropped_keys": dropped}


class SessionEnded(Exception):
    """The person ended the session (q, confirmed) or left it (CLOSED)."""


def confirm_quit(screen: Screen, back: str) -> None:
    """`q` was pressed: ask before ending (the game waits); raise SessionEnded on a second `q`."""
    screen.show("end the session? press q again to end it, any other key to go on")
    while True:
        press = screen.front.key(None)
        if press.name in (QUIT, CLOSED):
            raise SessionEnded
        if press.frame == screen.frame:  # an answer to the question, not a key typed before it
            screen.show(back)
            return


def ready_gate(screen: Screen, countdown_s: float) -> int:
    """Show the first state until the person presses space on it, then count down; -> the keys
    dropped meanwhile (any other key, and every key during the countdown)."""
    dropped = 0
    screen.show("press space to start")
    while True:
        press = screen.front.key(None)
        if press.name == CLOSED:
            raise SessionEnded
        if press.name == QUIT:
            confirm_quit(screen, "press space to start")
        elif press.name == START_KEY and press.frame == screen.frame:
            break
        else:
            dropped += 1
    steps = math.ceil(countdown_s)  # "starting in 3", "2", "1": each a second (or an equal part of it)
    for left in range(steps, 0, -1):
        screen.show(f"starting in {left}")
        deadline = time.monotonic() + countdown_s / steps
        while (wait := deadline - time.monotonic()) > 0:
            press = screen.front.key(wait)
            if press is None:
                continue
            if press.name == CLOSED:
                raise SessionEnded
            dropped += 1
    return dropped


def play_episode(game: Game, front: FrontEnd, fps: float, title: str, write: Callable[[Step], None],
                 countdown_s: float = 3.0) -> bool:
    """Run one episode; every step is written as it happens. -> completed (False: the person
    ended it: q confirmed, Ctrl-C, a closed tab)."""
    interval = 1.0 / fps if game.ticks else None
    help_line = f"arrow keys move; space {game.board.space_does}; q ends"
    screen = Screen(front, game, title)
    try:
        dropped = ready_gate(screen, countdown_s)
        screen.show(help_line)
        pending, next_tick = None, time.monotonic() + (interval or 0)
        while not game.done:
            timeout = None if interval is None else max(0.0, next_tick - time.monotonic())
            press = front.key(timeout)
            if press is not None and press.name == CLOSED:
                return False
            if press is not None and press.name == QUIT:
                confirm_quit(screen, help_line)
                pending, next_tick = None, time.monotonic() + (interval or 0)
                continue
            if press is not None and press.frame != screen.frame:
                dropped += 1  # pressed before the frame it would act on was on screen
                continue
            if press is not None and press.name not in KEYS:
                screen.show(f"unknown key {press.name!r}: {help_line}")
                continue
            if interval is not None:
                if press is not None:  # the latest key on this frame is the human's action at the tick
                    pending = press
                    continue
                steps = game.act(pending, screen.record(dropped))
                # the next tick an interval from now: a stall (a slow first compile) is not caught up
                pending, next_tick = None, max(next_tick + interval, time.monotonic() + interval / 2)
            elif press is None:
                continue
            else:
                steps = game.act(press, screen.record(dropped))
            dropped = 0
            for step in steps:
                write(step)
            screen.show(help_line)
    except SessionEnded:
        return False
    screen.show(f"episode over: return {game.score:g}", over=True)
    return True
