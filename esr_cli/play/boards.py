"""What `esr play` needs of an environment to seat a person in it: the person's keys as human
actions, whether the game waits for a key or ticks, the picture, its legend and, where it has
one, a drawing in characters. One `Board` per `env.kind`, in `BOARDS`; the game loop and the
front ends ask the board, never the kind. These are presentation only (what a person sees and
presses), so they live here rather than in the keyed model.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from esr_cli.model.envs import gridworld, overcooked
from esr_cli.play import overcooked_board


class Board(Protocol):
    keymap: dict[str, int]  # the person's key (up, down, left, right, space) -> the human's action
    idle_action: int | None  # the human's action on a tick without a key; None: the game waits for a key
    space_does: str  # what the space key does, for the help line

    def frame(self, env, state) -> np.ndarray:
        """The state as an RGB picture."""

    def legend(self, as_text: bool) -> str:
        """What the person is looking at: the characters of `text`, or the picture's colours."""

    def text(self, env, state) -> list[str] | None:
        """The state as rows of characters, or None where the terminal draws the picture."""

    def finished_early(self, env, state) -> int | None:
        """The human's action that plays out the rest of an episode in which nothing can move
        any more (the person's keys would change nothing), or None while the game goes on."""


class GridworldBoard:
    keymap = {"up": gridworld.UP, "down": gridworld.DOWN, "left": gridworld.LEFT, "right": gridworld.RIGHT,
              "space": gridworld.STAY}
    idle_action = None  # one step per key
    space_does = "stays"

    def frame(self, env, state) -> np.ndarray:
        return np.asarray(env.render(state))

    def legend(self, as_text: bool) -> str:
        if as_text:
            return "@ you   G your goal (the robot does not know it)   # a block the robot can push   " \
                   "X you, trapped under a block   . floor"
        return "orange: you · green: your goal (the robot does not know it) · purple: blocks the robot can push"

    def text(self, env, state) -> list[str]:
        """@ you, G your goal, # a block, . floor, X you trapped under a block."""
        size = env.size
        rows = [["."] * size for _ in range(size)]
        goal, human = np.asarray(state.goal), np.asarray(state.human)
        rows[goal[0]][goal[1]] = "G"
        for r, c in np.asarray(state.blocks):
            rows[r][c] = "#"
        rows[human[0]][human[1]] = "X" if bool(env.is_dead(state)) else "@"
        return ["".join(r) for r in rows]

    def finished_early(self, env, state) -> int | None:
        # On the goal or trapped, nothing moves again: the return still counts every step.
        return gridworld.STAY if bool(env.frozen(state)) else None


class OvercookedBoard:
    keymap = {"up": overcooked.UP, "down": overcooked.DOWN, "left": overcooked.LEFT, "right": overcooked.RIGHT,
              "space": overcooked.INTERACT}
    idle_action = overcooked.STAY  # the kitchen runs at a fixed rate; a tick without a key stays
    space_does = "interacts"

    def frame(self, env, state) -> np.ndarray:
        return overcooked_board.draw_env(env, state)

    def legend(self, as_text: bool) -> str:
        return overcooked_board.LEGEND  # both front ends draw the picture

    def text(self, env, state) -> None:
        return None

    def finished_early(self, env, state) -> None:
        return None


BOARDS: dict[str, Board] = {"gridworld": GridworldBoard(), "overcooked": OvercookedBoard()}


def board_for(env_kind: str) -> Board:
    if env_kind not in BOARDS:
        raise ValueError(f"esr play has no board for env.kind {env_kind!r}; known: {', '.join(BOARDS)}")
    return BOARDS[env_kind]
