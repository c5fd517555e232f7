"""Overcooked (Carroll et al. 2019) through JaxMARL's pure-JAX port, behind esr's env interface.

- The robot is JaxMARL's agent_0, the human agent_1; 6 actions each (up, down, right, left,
  stay, interact); both act on the same state every step (JaxMARL resolves the joint move).
- The reward is the shared sparse reward: 20 per delivered soup. An episode is
  `episode_steps` (400) steps with no early end and no automatic reset.
- Observations are JaxMARL's lossless (H, W, 26) grid encoding; the robot sees agent_0's
  view (own layers first), the human agent_1's (`observe_human`).
- Action "planes" broadcast the action's one-hot over the H x W grid, so a method that
  concatenates observation and action planes (ESR) works unchanged; an MLP network
  flattens them.
"""

from __future__ import annotations

import contextlib
import os
import sys
from functools import cache
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

LAYOUTS = ("cramped_room", "coord_ring", "asymm_advantages", "forced_coord", "counter_circuit")
NUM_ACTIONS = 6
UP, DOWN, RIGHT, LEFT, STAY, INTERACT = range(NUM_ACTIONS)
ACTION_NAMES = ("up", "down", "right", "left", "stay", "interact")
URGENCY_CHANNEL = 25  # 1 everywhere in the last 40 steps of an episode


@contextlib.contextmanager
def stdout_to_stderr():
    """Send whatever is printed meanwhile to stderr, at the file-descriptor level: jaxmarl's
    package import prints to stdout (which carries esr's results) and one of its modules
    resets sys.stdout to sys.__stdout__, which defeats contextlib.redirect_stdout alone."""
    current = sys.stdout
    for stream in (sys.stdout, sys.__stdout__):
        if stream is not None:
            stream.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no file descriptor 1: nothing to protect
        with contextlib.redirect_stdout(sys.stderr):
            yield
        return
    os.dup2(2, 1)
    try:
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        if sys.__stdout__ is not None:
            sys.__stdout__.flush()
        os.dup2(saved, 1)
        os.close(saved)
        sys.stdout = current


@cache
def jaxmarl_env(layout: str, max_steps: int):
    """JaxMARL's Overcooked for `layout` (imported lazily: jaxmarl prints on import)."""
    import warnings

    # ensure_compile_time_eval: jaxmarl makes module-level arrays on import, and this may
    # first run inside a traced function; the result is cached, so it must hold no tracer.
    with stdout_to_stderr(), warnings.catch_warnings(), jax.ensure_compile_time_eval():
        warnings.simplefilter("ignore", DeprecationWarning)
        from flax.core.frozen_dict import FrozenDict
        from jaxmarl.environments.overcooked import Overcooked as JaxmarlOvercooked
        from jaxmarl.environments.overcooked import overcooked_layouts

        if layout not in overcooked_layouts:
            raise ValueError(f"unknown Overcooked layout {layout!r}; known: {', '.join(LAYOUTS)}")
        return JaxmarlOvercooked(layout=FrozenDict(overcooked_layouts[layout]), max_steps=max_steps)


class Overcooked(NamedTuple):
    layout: str
    episode_steps: int

    # ---------------------------------------------------------------- static facts
    @property
    def base(self):
        return jaxmarl_env(self.layout, self.episode_steps)

    @property
    def height(self) -> int:
        return int(self.base.height)

    @property
    def width(self) -> int:
        return int(self.base.width)

    @property
    def num_robot_actions(self) -> int:
        return NUM_ACTIONS

    @property
    def num_human_actions(self) -> int:
        return NUM_ACTIONS

    @property
    def obs_shape(self) -> tuple[int, int, int]:
        # JaxMARL's observation_space says (W, H, 26), but get_obs returns (H, W, 26).
        return (self.height, self.width, 26)

    # ---------------------------------------------------------------- dynamics
    def reset(self, key: jax.Array):
        _, state = self.base.reset(key)
        return state

    def step(self, state, robot_action: jax.Array, human_action: jax.Array):
        """-> (next_state, reward). step_env: no automatic reset at the episode's end."""
        actions = {"agent_0": robot_action, "agent_1": human_action}
        # The vanilla environment's step draws no randomness: any key does.
        _, next_state, rewards, _, _ = self.base.step_env(jax.random.PRNGKey(0), state, actions)
        return next_state, rewards["agent_0"].astype(jnp.float32)

    def step_joint(self, state, action_0: jax.Array, action_1: jax.Array):
        """Step with agent_0's and agent_1's actions (self-play and data replay)."""
        return self.step(state, action_0, action_1)

    # ---------------------------------------------------------------- encodings
    def observe(self, state) -> jax.Array:
        """The robot's (agent_0's) view: uint8[H, W, 26]."""
        return self.base.get_obs(state)["agent_0"].astype(jnp.uint8)

    def observe_human(self, state) -> jax.Array:
        """The human's (agent_1's) view: uint8[H, W, 26] with its own layers first."""
        return self.base.get_obs(state)["agent_1"].astype(jnp.uint8)

    def _action_planes(self, action: jax.Array) -> jax.Array:
        onehot = jax.nn.one_hot(action, NUM_ACTIONS, dtype=jnp.float32)
        return jnp.broadcast_to(onehot, (self.height, self.width, NUM_ACTIONS))

    def robot_action_planes(self, action: jax.Array) -> jax.Array:
        """float32[H, W, 6]: the robot action's one-hot, broadcast over the grid."""
        return self._action_planes(action)

    def human_action_planes(self, action: jax.Array) -> jax.Array:
        """float32[H, W, 6]: the human action's one-hot, broadcast over the grid."""
        return self._action_planes(action)

    # ---------------------------------------------------------------- pictures
    def render(self, state, cell_px: int = 32) -> np.ndarray:
        """uint8[H*cell_px, W*cell_px, 3] by JaxMARL's tile renderer (numpy, not jittable).

        The robot (agent_0) is drawn red, the human (agent_1) blue.
        """
        with stdout_to_stderr():
            from jaxmarl.viz.overcooked_visualizer import OvercookedVisualizer
        pad = (np.asarray(state.maze_map).shape[0] - self.height) // 2
        grid = np.asarray(state.maze_map)[pad : pad + self.height, pad : pad + self.width, :]
        img = OvercookedVisualizer._render_grid(
            grid,
            tile_size=cell_px,
            highlight_mask=None,
            agent_dir_idx=np.asarray(state.agent_dir_idx),
            agent_inv=np.asarray(state.agent_inv),
        )
        return np.asarray(img, dtype=np.uint8)


def make(env_spec) -> Overcooked:
    env = Overcooked(layout=env_spec.layout, episode_steps=env_spec.episode_steps)
    env.base  # fail early on an unknown layout or a missing jaxmarl
    return env
