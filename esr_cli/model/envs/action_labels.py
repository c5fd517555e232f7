"""Words for one step's actions, as the captions of an episode's pictures show them, by
environment kind (`env.kind` of the spec).

Kept apart from the environments: their files belong to the code that keys every run and
every trained human (a change there makes them again), and a caption changes no number.
"""

from __future__ import annotations

from typing import Callable

from esr_cli.model.envs.gridworld import NUM_HUMAN_ACTIONS, STAY
from esr_cli.model.envs.overcooked import ACTION_NAMES

# The gridworld's directions in the order of its DIRECTIONS table: left, down, right, up, stay.
GRID_DIRECTIONS = ("left", "down", "right", "up", "stay")


def gridworld_labels(env, robot_action: int, human_action: int) -> tuple[str, str]:
    """('push (row,col) up', 'left'): the robot's push of the block on a cell, the human's step."""
    cell, direction = divmod(int(robot_action), NUM_HUMAN_ACTIONS)
    robot = "no push" if direction == STAY else f"push ({cell // env.size},{cell % env.size}) {GRID_DIRECTIONS[direction]}"
    return robot, GRID_DIRECTIONS[int(human_action)]


def overcooked_labels(env, robot_action: int, human_action: int) -> tuple[str, str]:
    return ACTION_NAMES[int(robot_action)], ACTION_NAMES[int(human_action)]


LABELS: dict[str, Callable] = {"gridworld": gridworld_labels, "overcooked": overcooked_labels}


def action_labels(env_kind: str, env, robot_action: int, human_action: int) -> tuple[str, str]:
    """The two actions in words; an environment without labels here gives their numbers."""
    label = LABELS.get(env_kind)
    if label is None:
        return f"action {int(robot_action)}", f"action {int(human_action)}"
    return label(env, robot_action, human_action)
