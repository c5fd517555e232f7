"""One game loop for every front end: a person in the human's seat, a robot in the other.

The person's keys are named `up`, `down`, `left`, `right` and `space`; `KEYMAP` turns them into
the environment's human actions (space: stay in the gridworld, interact in Overcooked). A
gridworld advances one step per key; Overcooked advances at a fixed rate, a tick without a
key being `stay`. Once the gridworld's human is on the goal (or trapped) nothing can move any
more, so the remaining steps are played out at once: the return counts every step on the goal,
as in training.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from esr_cli.envs import gridworld, overcooked
from esr_cli.play.log import state_record

KEYS = ("up", "down", "left", "right", "space")
QUIT = "quit"
KEYMAP = {
    "gridworld": {"up": gridworld.UP, "down": gridworld.DOWN, "left": gridworld.LEFT, "right": gridworld.RIGHT,
                  "space": gridworld.STAY},
    "overcooked": {"up": overcooked.UP, "down": overcooked.DOWN, "left": overcooked.LEFT, "right": overcooked.RIGHT,
                   "space": overcooked.INTERACT},
}
# The human's action on a tick without a key (Overcooked ticks; the gridworld waits for a key).
IDLE_ACTION = {"gridworld": gridworld.STAY, "overcooked": overcooked.STAY}
TICKS = {"gridworld": False, "overcooked": True}
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

    def start(self, state) -> None:
        self.memory = self._start(state) if self.by_rule else None

    def act(self, state, key, prev_human_action: int) -> int:
        if self.by_rule:
            action, self.memory = self._rule(self.memory, state, jnp.int32(prev_human_action), key)
            return int(action)
        return int(self._act(state, key))


@dataclass
class Step:
    t: int
    key: str | None  # the key pressed; None on a tick without one, or a step played out
    human_action: int
    robot_action: int
    reward: float
    score: float  # the return so far, this step's reward included
    wall_time: float  # unix time of the step
    reaction_s: float | None  # from the frame being shown to the key; None without a key
    state: dict  # the environment state the step was taken from (state_record)


class Game:
    """One episode. `shown()` marks when the person sees the current state (reaction times);
    `act(key, pressed_at)` plays one step (key None: a tick without a key) and returns its
    records, more than one when the rest of a finished gridworld episode is played out."""

    def __init__(self, env_kind: str, robot: Robot, seed: int):
        self.env_kind, self.robot, self.env = env_kind, robot, robot.env
        self.key = jax.random.PRNGKey(seed)
        self.key, k_reset = jax.random.split(self.key)
        self.state = self.env.reset(k_reset)
        self.robot.start(self.state)
        self.t, self.score, self.shown_at, self.prev_human = 0, 0.0, time.time(), 0
        self._step = jax.jit(self.env.step)
        self.robot.warm(self.state)  # compiled before the first frame is shown
        jax.block_until_ready(self._step(self.state, jnp.int32(0), jnp.int32(0)))

    @property
    def ticks(self) -> bool:
        return TICKS[self.env_kind]

    @property
    def steps_left(self) -> int:
        return self.env.episode_steps - self.t

    @property
    def done(self) -> bool:
        return self.t >= self.env.episode_steps

    def shown(self) -> None:
        self.shown_at = time.time()

    def act(self, key: str | None, pressed_at: float | None = None) -> list[Step]:
        if key is None:
            steps = [self._advance(IDLE_ACTION[self.env_kind], None, None)]
        else:
            if key not in KEYMAP[self.env_kind]:
                raise ValueError(f"unknown key {key!r}: {', '.join(KEYS)}")
            reaction = (pressed_at or time.time()) - self.shown_at
            steps = [self._advance(KEYMAP[self.env_kind][key], key, reaction)]
        if self.env_kind == "gridworld" and bool(self.env.frozen(self.state)):
            while not self.done:  # nothing can move any more: play the rest out
                steps.append(self._advance(gridworld.STAY, None, None))
        return steps

    def _advance(self, human_action: int, key: str | None, reaction: float | None) -> Step:
        if self.done:
            raise RuntimeError("the episode is over")
        before = state_record(self.state)
        self.key, k_robot = jax.random.split(self.key)
        robot_action = self.robot.act(self.state, k_robot, self.prev_human)
        self.state, reward = self._step(self.state, jnp.int32(robot_action), jnp.int32(human_action))
        self.t, self.score, self.prev_human = self.t + 1, self.score + float(reward), human_action
        return Step(self.t - 1, key, human_action, robot_action, float(reward), self.score, time.time(),
                    None if reaction is None else round(reaction, 4), before)

    def state_record(self) -> dict:
        return state_record(self.state)

    def frame(self) -> np.ndarray:
        """The current state as an RGB picture (the environment's own renderer)."""
        return np.asarray(self.env.render(self.state))

    def legend(self, as_text: bool) -> str:
        """What the person is looking at: the characters of `text()`, or the picture's colours."""
        if self.env_kind == "gridworld":
            if as_text:
                return "@ you   G your goal (the robot does not know it)   # block"
            return "orange: you · green: your goal (the robot does not know it) · purple: blocks the robot can push"
        return f"you play the {'blue' if self.env.robot_seat == 0 else 'red'} chef; the robot plays the other"

    def text(self) -> list[str] | None:
        """The gridworld as characters (the terminal draws these): @ you, G your goal, # a
        block, . floor; None for Overcooked (drawn from its picture)."""
        if self.env_kind != "gridworld":
            return None
        size = self.env.size
        rows = [["."] * size for _ in range(size)]
        goal, human = np.asarray(self.state.goal), np.asarray(self.state.human)
        rows[goal[0]][goal[1]] = "G"
        for r, c in np.asarray(self.state.blocks):
            rows[r][c] = "#"
        rows[human[0]][human[1]] = "X" if bool(self.env.is_dead(self.state)) else "@"
        return ["".join(r) for r in rows]


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


@runtime_checkable
class FrontEnd(Protocol):
    """What the game loop needs from a front end (the terminal, the browser, a test's script)."""

    draws_text: bool  # True: the gridworld as characters (View.text); False: pictures only

    def ready(self) -> None:
        """Block until a person can play (the browser has connected)."""
        ...

    def show(self, view: View) -> None: ...

    def key(self, timeout: float | None) -> str | None:
        """The next key within `timeout` seconds (None: wait): a name in KEYS, QUIT, any other
        string for an unknown key; None when the time ran out."""
        ...

    def finish(self, lines: list[str]) -> None:
        """The session is over: show these lines."""
        ...


def play_episode(game: Game, front: FrontEnd, fps: float, title: str, write: Callable[[Step], None]) -> bool:
    """Run one episode; every step is written as it happens. -> completed (False: the person
    ended it: q, Ctrl-C, a closed tab)."""
    interval = 1.0 / fps if game.ticks else None
    message, pending = "", None
    help_line = "arrow keys move; space " + ("interacts" if game.env_kind == "overcooked" else "stays") + "; q ends"

    def show(over=False):
        text = game.text() if front.draws_text else None
        front.show(View(title, game.score, game.steps_left, game.frame(), text, game.legend(text is not None),
                        message or help_line, over))
        game.shown()

    show()
    next_tick = time.monotonic() + (interval or 0)
    while not game.done:
        timeout = None if interval is None else max(0.0, next_tick - time.monotonic())
        key = front.key(timeout)
        if key == QUIT:
            return False
        if key is not None and key not in KEYS:
            message = f"unknown key {key!r}: {help_line}"
            show()
            continue
        if interval is not None:
            if key is not None:  # the latest key before the tick is the human's action
                pending = (key, time.time())
                continue
            steps = game.act(*(pending or (None, None)))
            # the next tick an interval from now: a stall (a slow first compile) is not caught up
            pending, next_tick = None, max(next_tick + interval, time.monotonic() + interval / 2)
        elif key is None:
            continue
        else:
            steps = game.act(key, time.time())
        for step in steps:
            write(step)
        message = ""
        show()
    message = f"episode over: return {game.score:g}"
    show(over=True)
    return True
