"""Obstacle gridworld (after Du et al. 2020), pure JAX.

Rules (docs/environments.md):
- an S x S grid indexed (row, col); a human, N movable blocks and a goal the robot never sees;
- human actions: left, down, right, up, stay (0..4); moves stop at walls and at blocks;
- robot actions: cell * 5 + direction, "push the block on `cell` one step in `direction`";
  no block on the cell is a no-op; a block stops at walls and at other blocks but *can* be
  pushed onto the human, who is then stuck ("dead") for the rest of the episode;
- once the human is on the goal or dead, nothing moves any more;
- each step the human moves first, then the robot acts on the resulting state;
- reward 1 for every step after whose human move the human is on the goal.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

# (d_row, d_col) for left, down, right, up, stay.
DIRECTIONS = jnp.array([[0, -1], [1, 0], [0, 1], [-1, 0], [0, 0]], dtype=jnp.int32)
NUM_HUMAN_ACTIONS = 5
LEFT, DOWN, RIGHT, UP, STAY = range(5)


class GridState(NamedTuple):
    human: jax.Array  # int32[2]
    blocks: jax.Array  # int32[N, 2]
    goal: jax.Array  # int32[2]
    t: jax.Array  # int32[]


class Gridworld(NamedTuple):
    size: int
    num_blocks: int
    start: str
    episode_steps: int
    goal_visible: bool = False  # a third observation plane with the goal (the Oracle's view)

    # ---------------------------------------------------------------- static facts
    @property
    def num_robot_actions(self) -> int:
        return self.size * self.size * NUM_HUMAN_ACTIONS

    @property
    def num_human_actions(self) -> int:
        return NUM_HUMAN_ACTIONS

    @property
    def obs_shape(self) -> tuple[int, int, int]:
        return (self.size, self.size, 3 if self.goal_visible else 2)

    # ---------------------------------------------------------------- predicates
    def block_at(self, blocks: jax.Array, pos: jax.Array) -> jax.Array:
        """bool[N]: which blocks sit on `pos`."""
        return jnp.all(blocks == pos[None, :], axis=-1)

    def is_dead(self, state: GridState) -> jax.Array:
        return jnp.any(self.block_at(state.blocks, state.human))

    def at_goal(self, state: GridState) -> jax.Array:
        return jnp.all(state.human == state.goal)

    def frozen(self, state: GridState) -> jax.Array:
        return self.is_dead(state) | self.at_goal(state)

    # ---------------------------------------------------------------- dynamics
    def human_target(self, state: GridState, action: jax.Array) -> jax.Array:
        """Where `action` would take the human (walls and blocks stop it)."""
        target = jnp.clip(state.human + DIRECTIONS[action], 0, self.size - 1)
        blocked = jnp.any(self.block_at(state.blocks, target))
        return jnp.where(blocked, state.human, target)

    def move_human(self, state: GridState, action: jax.Array) -> GridState:
        new = jnp.where(self.frozen(state), state.human, self.human_target(state, action))
        return state._replace(human=new)

    def move_block(self, state: GridState, action: jax.Array) -> GridState:
        if self.num_blocks == 0:
            return state
        cell, direction = action // NUM_HUMAN_ACTIONS, action % NUM_HUMAN_ACTIONS
        pos = jnp.stack([cell // self.size, cell % self.size]).astype(jnp.int32)
        on_cell = self.block_at(state.blocks, pos)
        which = jnp.argmax(on_cell)
        target = jnp.clip(pos + DIRECTIONS[direction], 0, self.size - 1)
        others = self.block_at(state.blocks, target) & (jnp.arange(self.num_blocks) != which)
        moves = jnp.any(on_cell) & ~jnp.any(others) & ~self.frozen(state)
        blocks = state.blocks.at[which].set(jnp.where(moves, target, state.blocks[which]))
        return state._replace(blocks=blocks)

    def step(self, state: GridState, robot_action: jax.Array, human_action: jax.Array):
        """-> (next_state, reward). Human first, then robot, from the same observed state."""
        after_human = self.move_human(state, human_action)
        reward = self.at_goal(after_human).astype(jnp.float32)
        after_robot = self.move_block(after_human, robot_action)
        return after_robot._replace(t=state.t + 1), reward

    # ---------------------------------------------------------------- reset
    def _corner_layout(self, corner: jax.Array, gap: int):
        s = self.size - 1
        corners = jnp.array([[0, 0], [0, s], [s, 0], [s, s]], dtype=jnp.int32)
        # Unit vectors from each corner along its row and its column, into the grid.
        along = jnp.array([[[0, 1], [1, 0]], [[0, -1], [1, 0]], [[0, 1], [-1, 0]], [[0, -1], [-1, 0]]], dtype=jnp.int32)
        human = corners[corner]
        fixed = human[None, :] + gap * along[corner]
        return human, fixed

    def reset(self, key: jax.Array) -> GridState:
        k_corner, k_human, k_blocks, k_goal = jax.random.split(key, 4)
        n, cells = self.num_blocks, self.size * self.size
        if self.start in ("corner", "corner_hard"):
            corner = jax.random.randint(k_corner, (), 0, 4)
            human, fixed = self._corner_layout(corner, 1 if self.start == "corner" else 2)
        elif self.start == "center":
            c = self.size // 2
            human = jnp.array([c, c], dtype=jnp.int32)
            ring = jnp.array([[c, c + 1], [c + 1, c], [c, c - 1], [c - 1, c]], dtype=jnp.int32)
            fixed = ring[: min(n, 4)]
        elif self.start == "random":
            flat = jax.random.randint(k_human, (), 0, cells)
            human = jnp.stack([flat // self.size, flat % self.size]).astype(jnp.int32)
            fixed = jnp.zeros((0, 2), dtype=jnp.int32)
        else:
            raise ValueError(f"unknown start {self.start!r}")
        blocks = fixed
        n_random = n - fixed.shape[0]
        coords = jnp.stack(jnp.divmod(jnp.arange(cells), self.size), axis=-1).astype(jnp.int32)
        occupied = jnp.all(coords == human, axis=-1)
        for b in fixed:
            occupied = occupied | jnp.all(coords == b, axis=-1)
        if n_random > 0:
            free = (~occupied).astype(jnp.float32)
            idx = jax.random.choice(k_blocks, cells, (n_random,), replace=False, p=free / free.sum())
            blocks = jnp.concatenate([fixed, coords[idx]], axis=0)
            occupied = occupied.at[idx].set(True)
        free = (~occupied).astype(jnp.float32)
        goal = coords[jax.random.choice(k_goal, cells, (), p=free / free.sum())]
        return GridState(human=human, blocks=blocks.reshape(n, 2), goal=goal, t=jnp.zeros((), jnp.int32))

    # ---------------------------------------------------------------- encodings
    def observe(self, state: GridState) -> jax.Array:
        """The robot's view: uint8[S, S, 2] (human plane, block plane); no goal unless
        `goal_visible` (then a third plane marks it)."""
        grid = jnp.zeros(self.obs_shape, jnp.uint8)
        grid = grid.at[state.human[0], state.human[1], 0].set(1)
        grid = grid.at[state.blocks[:, 0], state.blocks[:, 1], 1].set(1)
        if self.goal_visible:
            grid = grid.at[state.goal[0], state.goal[1], 2].set(1)
        return grid

    def human_position(self, obs: jax.Array) -> jax.Array:
        """int32[2]: the human's cell, read from an observation."""
        flat = jnp.argmax(obs[..., 0].reshape(-1))
        return jnp.stack([flat // self.size, flat % self.size]).astype(jnp.int32)

    def block_coordinates(self, obs: jax.Array) -> jax.Array:
        """int32[N, 2]: the blocks' cells read from an observation, in row-major order."""
        flat = jnp.nonzero(obs[..., 1].reshape(-1) > 0, size=self.num_blocks, fill_value=0)[0]
        return jnp.stack([flat // self.size, flat % self.size], axis=-1).astype(jnp.int32)

    def random_human_futures(self, obs: jax.Array, human_actions: jax.Array) -> jax.Array:
        """float32[M, 2]: the human's cell after each of M sequences of L human actions
        (int[M, L]) from the observed state, the robot staying (AvE's rollouts).

        Read from the observation alone, as the robot sees it: blocks stop the human, a human
        under a block cannot move; the goal is unknown, so reaching it freezes nothing.
        """
        start = self.human_position(obs)
        blocked = obs[..., 1] > 0
        dead = blocked[start[0], start[1]]

        def walk(actions):
            def move(pos, a):
                target = jnp.clip(pos + DIRECTIONS[a], 0, self.size - 1)
                stays = dead | blocked[target[0], target[1]]
                return jnp.where(stays, pos, target), None

            end, _ = jax.lax.scan(move, start, actions)
            return end.astype(jnp.float32)

        return jax.vmap(walk)(human_actions)

    def human_view(self, obs: jax.Array) -> jax.Array:
        """The observation with everything but the human's plane zeroed (same shape)."""
        return obs.at[..., 1:].set(0)

    def robot_action_planes(self, action: jax.Array) -> jax.Array:
        """float32[S, S, 5]: one-hot at (cell row, cell col, direction)."""
        onehot = jax.nn.one_hot(action, self.num_robot_actions, dtype=jnp.float32)
        return onehot.reshape(self.size, self.size, NUM_HUMAN_ACTIONS)

    def human_action_planes(self, action: jax.Array) -> jax.Array:
        """float32[S, S, 5]: the human action one-hot, broadcast over the grid."""
        onehot = jax.nn.one_hot(action, NUM_HUMAN_ACTIONS, dtype=jnp.float32)
        return jnp.broadcast_to(onehot, (self.size, self.size, NUM_HUMAN_ACTIONS))

    # ---------------------------------------------------------------- pictures
    def render(self, state: GridState, cell_px: int = 24) -> jax.Array:
        """uint8[S*cell_px, S*cell_px, 3]: grey floor, green goal, orange human, purple blocks."""
        floor = jnp.array([50, 50, 50], jnp.uint8)
        goal_c, human_c, block_c = (
            jnp.array([120, 215, 10], jnp.float32),
            jnp.array([230, 150, 0], jnp.float32),
            jnp.array([100, 0, 215], jnp.float32),
        )
        img = jnp.broadcast_to(floor.astype(jnp.float32), (self.size, self.size, 3))
        img = img.at[state.goal[0], state.goal[1]].set(goal_c)
        img = img.at[state.human[0], state.human[1]].set(human_c)
        for i in range(self.num_blocks):
            r, c = state.blocks[i, 0], state.blocks[i, 1]
            tint = block_c
            tint = jnp.where(jnp.all(state.blocks[i] == state.goal), (2 * block_c + goal_c) / 3, tint)
            tint = jnp.where(jnp.all(state.blocks[i] == state.human), (block_c + 2 * human_c) / 3, tint)
            img = img.at[r, c].set(tint)
        big = jnp.repeat(jnp.repeat(img, cell_px, axis=0), cell_px, axis=1)
        # Thin grid lines so cells read as cells.
        lines = (jnp.arange(self.size * cell_px) % cell_px) == 0
        big = jnp.where(lines[:, None, None] | lines[None, :, None], 30.0, big)
        return big.astype(jnp.uint8)


def make(env_spec) -> Gridworld:
    return Gridworld(
        size=env_spec.size,
        num_blocks=env_spec.blocks,
        start=env_spec.start,
        episode_steps=env_spec.episode_steps,
        goal_visible=env_spec.goal_visible,
    )
