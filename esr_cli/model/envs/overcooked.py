"""Overcooked (Carroll et al. 2019) through JaxMARL's pure-JAX port, behind esr's env interface.

- The robot is JaxMARL's agent_0, the human agent_1 (`robot_seat: 1` swaps them: the
  "flipped" evaluation); 6 actions each (up, down, right, left, stay, interact); both act on
  the same state every step (JaxMARL resolves the joint move).
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
import io
import os
import sys
import tempfile
from functools import cache
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

LAYOUTS = ("cramped_room", "coord_ring", "asymm_advantages", "forced_coord", "counter_circuit")
NUM_ACTIONS = 6
UP, DOWN, RIGHT, LEFT, STAY, INTERACT = range(NUM_ACTIONS)
ACTION_NAMES = ("up", "down", "right", "left", "stay", "interact")
HUMAN_LAYERS = (1, 6, 7, 8, 9)  # in agent_0's view: the other agent's position and orientation
HUMAN_POSITION = 1
# What an agent holds shows in the item layers at its own cell (loose items and agents never
# share a cell): 18 onions in a soup (3 for a plated soup), 21 soup done, 22 plate, 23 onion.
HELD_ITEM_LAYERS = (18, 21, 22, 23)
URGENCY_CHANNEL = 25  # 1 everywhere in the last 40 steps of an episode
# JaxMARL's OBJECT_TO_INDEX values used when decoding an observation.
_EMPTY, _ONION, _PLATE, _DISH, _AGENT = 1, 3, 5, 9, 10


# What jaxmarl's package import prints about its optional environments: noise to esr's users.
JAXMARL_BANNER = frozenset({
    "Importing submoduled environments...",
    "Submoduled environments imported successfully.",
    "Submoduled environments not found. Skipping import.",
})


@contextlib.contextmanager
def quiet_jaxmarl():
    """Run jaxmarl code with what it prints caught at the file-descriptor level (one of its
    modules resets sys.stdout to sys.__stdout__, which defeats contextlib.redirect_stdout
    alone): its import banner is dropped and anything else goes to stderr, never to stdout,
    which carries esr's results."""
    current = sys.stdout
    for stream in (sys.stdout, sys.__stdout__):
        if stream is not None:
            stream.flush()
    caught = io.StringIO()
    try:
        saved = os.dup(1)
    except OSError:  # no file descriptor 1: only Python-level printing to catch
        try:
            with contextlib.redirect_stdout(caught):
                yield
        finally:
            _forward_to_stderr(caught.getvalue())
        return
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 1)
        try:
            with contextlib.redirect_stdout(caught):
                yield
        finally:
            if sys.__stdout__ is not None:
                sys.__stdout__.flush()
            os.dup2(saved, 1)
            os.close(saved)
            sys.stdout = current
            sink.seek(0)
            _forward_to_stderr(sink.read().decode(errors="replace") + caught.getvalue())


def _forward_to_stderr(text: str) -> None:
    kept = [line for line in text.splitlines() if line.strip() not in JAXMARL_BANNER]
    if kept:
        sys.stderr.write("\n".join(kept) + "\n")


@cache
def jaxmarl_env(layout: str, max_steps: int):
    """JaxMARL's Overcooked for `layout` (imported lazily: jaxmarl prints on import)."""
    import warnings

    # ensure_compile_time_eval: jaxmarl makes module-level arrays on import, and this may
    # first run inside a traced function; the result is cached, so it must hold no tracer.
    with quiet_jaxmarl(), warnings.catch_warnings(), jax.ensure_compile_time_eval():
        warnings.simplefilter("ignore", DeprecationWarning)
        from flax.core.frozen_dict import FrozenDict
        from jaxmarl.environments.overcooked import Overcooked as JaxmarlOvercooked, overcooked_layouts

        if layout not in overcooked_layouts:
            raise ValueError(f"unknown Overcooked layout {layout!r}; known: {', '.join(LAYOUTS)}")
        return JaxmarlOvercooked(layout=FrozenDict(overcooked_layouts[layout]), max_steps=max_steps)


class Overcooked(NamedTuple):
    layout: str
    episode_steps: int
    robot_seat: int = 0  # JaxMARL's agent index the robot plays; the human plays the other

    @property
    def robot_agent(self) -> str:
        return f"agent_{self.robot_seat}"

    @property
    def human_agent(self) -> str:
        return f"agent_{1 - self.robot_seat}"

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
        return self.step_joint(state, *((robot_action, human_action) if self.robot_seat == 0 else (human_action, robot_action)))

    def step_joint(self, state, action_0: jax.Array, action_1: jax.Array):
        """Step with agent_0's and agent_1's actions (self-play and data replay) -> (next_state, reward)."""
        # The vanilla environment's step draws no randomness: any key does.
        _, next_state, rewards, _, _ = self.base.step_env(jax.random.PRNGKey(0), state, {"agent_0": action_0, "agent_1": action_1})
        return next_state, rewards["agent_0"].astype(jnp.float32)  # shared: both agents get it

    # ---------------------------------------------------------------- encodings
    def observe(self, state) -> jax.Array:
        """The robot's view (its own layers first): uint8[H, W, 26]."""
        return self.base.get_obs(state)[self.robot_agent].astype(jnp.uint8)

    def observe_human(self, state) -> jax.Array:
        """The human's view (its own layers first): uint8[H, W, 26]."""
        return self.base.get_obs(state)[self.human_agent].astype(jnp.uint8)

    def human_view(self, obs: jax.Array) -> jax.Array:
        """A robot observation with all but the human's own part zeroed (same shape): its
        position (layer 1), orientation (layers 6-9) and what it holds (the item layers at its
        own cell only; items on counters, pots and the robot's hands are the world's part)."""
        keep = jnp.zeros((obs.shape[-1],), obs.dtype).at[jnp.array(HUMAN_LAYERS)].set(1)
        held = jnp.zeros((obs.shape[-1],), obs.dtype).at[jnp.array(HELD_ITEM_LAYERS)].set(1)
        at_human = obs[..., HUMAN_POSITION:HUMAN_POSITION + 1]
        return obs * keep + obs * held * at_human

    def _action_planes(self, action: jax.Array) -> jax.Array:
        onehot = jax.nn.one_hot(action, NUM_ACTIONS, dtype=jnp.float32)
        return jnp.broadcast_to(onehot, (self.height, self.width, NUM_ACTIONS))

    def robot_action_planes(self, action: jax.Array) -> jax.Array:
        """float32[H, W, 6]: the robot action's one-hot, broadcast over the grid."""
        return self._action_planes(action)

    def human_action_planes(self, action: jax.Array) -> jax.Array:
        """float32[H, W, 6]: the human action's one-hot, broadcast over the grid."""
        return self._action_planes(action)

    # ---------------------------------------------------------------- decoding
    def state_from_obs(self, obs: jax.Array):
        """The JaxMARL state a robot observation encodes (the encoding is lossless but for
        the step count: the result has step 0, or step episode_steps - 39 when the urgency
        channel is on, so that it stays on). Layout parts come from the layout itself."""
        from jaxmarl.environments.overcooked.common import OBJECT_INDEX_TO_VEC

        template = self.reset(jax.random.PRNGKey(0))
        h, w = self.height, self.width
        pad = (template.maze_map.shape[0] - h) // 2
        obs = obs.astype(jnp.int32)

        def where_is(plane):
            i = jnp.argmax(plane.reshape(-1))
            return jnp.stack([i % w, i // w]).astype(jnp.uint32)

        # The view is the robot's: its own layers (0, 2-5) first, the human's (1, 6-9) second.
        pos = jnp.stack([where_is(obs[..., 0]), where_is(obs[..., 1])])
        dir_idx = jnp.stack([jnp.argmax(obs[pos[0, 1], pos[0, 0], 2:6]), jnp.argmax(obs[pos[1, 1], pos[1, 0], 6:10])]).astype(jnp.int32)
        if self.robot_seat == 1:  # -> JaxMARL's agent order
            pos, dir_idx = pos[::-1], dir_idx[::-1]
        # Loose objects and held ones share the plate (22), onion (23) and soup-ready (21) layers.
        item = jnp.where(obs[..., 22] > 0, _PLATE, jnp.where(obs[..., 23] > 0, _ONION, jnp.where(obs[..., 21] > 0, _DISH, _EMPTY)))
        is_pot = obs[..., 10] > 0
        inv = jnp.stack([item[pos[0, 1], pos[0, 0]], item[pos[1, 1], pos[1, 0]]]).astype(jnp.int32)
        inner = template.maze_map[pad : pad + h, pad : pad + w]
        for a in range(2):  # the template's agents leave empty floor
            inner = inner.at[template.agent_pos[a, 1], template.agent_pos[a, 0]].set(OBJECT_INDEX_TO_VEC[_EMPTY])
        loose = (item != _EMPTY) & ~is_pot
        inner = jnp.where(loose[..., None], OBJECT_INDEX_TO_VEC[item], inner)
        status = jnp.where(obs[..., 21] > 0, 0, jnp.where(obs[..., 20] > 0, obs[..., 20], 23 - obs[..., 16]))
        inner = jnp.where(is_pot[..., None], inner.at[..., 2].set(status.astype(jnp.uint8)), inner)
        for a in range(2):
            inner = inner.at[pos[a, 1], pos[a, 0]].set(jnp.array([_AGENT, 2 * a, 0], jnp.uint8).at[2].set(dir_idx[a].astype(jnp.uint8)))
        maze = template.maze_map.at[pad : pad + h, pad : pad + w].set(inner)
        from jaxmarl.environments.overcooked.common import DIR_TO_VEC

        urgent = obs[0, 0, URGENCY_CHANNEL] > 0
        return template.replace(
            agent_pos=pos,
            agent_dir_idx=dir_idx,
            agent_dir=DIR_TO_VEC[dir_idx],
            agent_inv=inv,
            maze_map=maze,
            step=jnp.where(urgent, self.episode_steps - 39, 0).astype(template.step.dtype),
        )

    def random_human_futures(self, obs: jax.Array, human_actions: jax.Array) -> jax.Array:
        """float32[M, H*W*26]: the human's observation after each of M sequences of L human
        actions (int[M, L]) from the observed state, the robot staying (AvE's rollouts; the
        features are the human's observation, as in the original code)."""
        start = self.state_from_obs(obs)

        def walk(actions):
            def step(s, a):
                return self.step(s, jnp.int32(STAY), a)[0], None

            end, _ = jax.lax.scan(step, start, actions)
            return self.observe_human(end).reshape(-1).astype(jnp.float32)

        return jax.vmap(walk)(human_actions)

    # ---------------------------------------------------------------- pictures
    def render(self, state, cell_px: int = 32) -> np.ndarray:
        """uint8[H*cell_px, W*cell_px, 3] by JaxMARL's tile renderer (numpy, not jittable).

        The robot (agent_0) is drawn red, the human (agent_1) blue.
        """
        with quiet_jaxmarl():
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
    env = Overcooked(layout=env_spec.layout, episode_steps=env_spec.episode_steps, robot_seat=env_spec.robot_seat)
    env.base  # fail early on an unknown layout or a missing jaxmarl
    return env
