"""Goal Inference (Du et al. 2020): infer the human's goal, then clear its way there.

The robot keeps, in each environment, a belief over the human's goal: every cell free of
blocks and of the human at the episode's start, uniform at first. Two variants
(`method.variant`, docs/baselines.md):

exact (esr's): after each step it sees the human's action aH taken from state s and updates
the belief by Bayes' rule under the known noisy-greedy human model,

    b(g) <- b(g) P(aH | s, g),   P(aH | s, g) = (1 - noise) [aH = greedy(s, g)] + noise / 5

and clears the way to the most probable goal.

original (Du et al.'s published rule): after each step, every candidate goal's weight moves by
a fixed step alpha / |G|, up when the human came closer to it (straight-line distance), down
(floored at 0) when it went away, to 0 when the human stands on it without moving; then the
weights are renormalised. The robot takes the action that helps the most goal mass: each goal
votes with its weight for its own clearing action, and ties are broken at random.

Clearing action for a goal g: the human's next cell on its straight-line way to g, ignoring
blocks, is c. If a block sits on c, the robot pushes it (exact: sideways first, perpendicular to
the human's move, then straight ahead; original: the first of left, down, right, up that lands
on a free in-grid cell), never onto the human. Otherwise it does nothing. It learns nothing, so
there is no critic; training only records its returns.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from esr_cli.model.envs.gridworld import DIRECTIONS, NUM_HUMAN_ACTIONS, STAY, GridState
from esr_cli.model.methods.base import no_update, stateless_init

MOVES = 4  # left, down, right, up: the human's moves toward a goal
# For a move d (index into DIRECTIONS), the push directions tried in order. exact: the two
# perpendicular ones, then d itself (away from the human). original: left, down, right, up,
# whatever the move (a push back toward the human is refused as landing on it).
PUSH_ORDER = {
    "exact": jnp.array([[1, 3, 0], [0, 2, 1], [1, 3, 2], [0, 2, 3]], dtype=jnp.int32),
    "original": jnp.tile(jnp.arange(MOVES, dtype=jnp.int32), (MOVES, 1)),
}


class Memory(NamedTuple):
    belief: jax.Array  # float32[S*S]: over goal cells
    prev_obs: jax.Array  # the observation the human last acted on
    started: jax.Array  # bool: false before the first step of an episode
    candidates: jax.Array  # bool[S*S]: the goal set G (cells free at the episode's start)


class GoalInference(NamedTuple):
    env: object  # Gridworld
    human: object  # NoisyGreedyHuman (the known human model)
    variant: str = "exact"  # exact | original (module docstring)
    step: float = 0.5  # original: alpha, the belief's step per move is alpha / |G|

    updates_per_epoch: int = 0
    learns_policy: bool = False
    acts_by_rule: bool = True
    metric_names: tuple = ("goal_belief_true",)
    all_metric_names = metric_names  # not a field (a class attribute): the same for every spec
    has_reward_table: bool = False

    init = stateless_init
    update = no_update

    @classmethod
    def from_spec(cls, spec, env, human):
        return cls(env=env, human=human, variant=spec.method.variant, step=spec.method.step)

    def reward(self, state, batch, key):
        return jnp.zeros(batch.robot_action.shape, jnp.float32)

    # ------------------------------------------------------------ belief
    def cells(self) -> jax.Array:
        n = self.env.size
        return jnp.stack(jnp.divmod(jnp.arange(n * n), n), axis=-1).astype(jnp.int32)

    def state_for_goal(self, obs, goal) -> GridState:
        """The world as the robot sees it, with a hypothesised goal."""
        return GridState(
            human=self.env.human_position(obs),
            blocks=self.env.block_coordinates(obs),
            goal=goal,
            t=jnp.zeros((), jnp.int32),
        )

    def prior(self, obs) -> jax.Array:
        free = (obs[..., 0] == 0) & (obs[..., 1] == 0)
        p = free.reshape(-1).astype(jnp.float32)
        return p / jnp.maximum(p.sum(), 1.0)

    def likelihood(self, obs, human_action) -> jax.Array:
        """float32[S*S]: P(aH | s, g) for every goal cell g."""
        probs = jax.vmap(lambda g: self.human.action_probs(self.state_for_goal(obs, g)))(self.cells())
        return probs[:, human_action]

    def update_belief(self, belief, obs, human_action) -> jax.Array:
        return _normalised_or(belief * self.likelihood(obs, human_action), belief)

    def step_belief(self, belief, candidates, prev_obs, obs) -> jax.Array:
        """Du et al.'s update: each candidate goal's weight moves by step / |G| toward or away
        from the goals the human's last move approached or left (squared distances compare
        exactly in integers)."""
        cells = self.cells()
        d2 = lambda o: jnp.sum((self.env.human_position(o)[None, :] - cells) ** 2, axis=-1)  # noqa: E731
        before, after = d2(prev_obs), d2(obs)
        adj = self.step / jnp.maximum(candidates.sum(), 1.0)
        moved = jnp.where(after < before, belief + adj, jnp.maximum(belief - adj, 0.0))
        stays_on = (after == before) & (after == 0)
        weights = jnp.where(after == before, jnp.where(stays_on, 0.0, belief), moved)
        return _normalised_or(jnp.where(candidates > 0, weights, 0.0), belief)

    # ------------------------------------------------------------ acting
    def clearing_action(self, obs, goal) -> jax.Array:
        env, push_order = self.env, PUSH_ORDER[self.variant]
        human = env.human_position(obs)
        dist = jnp.linalg.norm((human[None, :] + DIRECTIONS[:MOVES] - goal[None, :]).astype(jnp.float32), axis=-1)
        move = jnp.argmin(dist)
        cell = human + DIRECTIONS[move]
        inside = jnp.all((cell >= 0) & (cell < env.size))
        cell = jnp.clip(cell, 0, env.size - 1)
        blocked = obs[..., 1] > 0
        in_the_way = inside & blocked[cell[0], cell[1]] & ~jnp.all(human == goal)
        dests = cell[None, :] + DIRECTIONS[push_order[move]]
        ok = jnp.all((dests >= 0) & (dests < env.size), axis=-1)
        dests = jnp.clip(dests, 0, env.size - 1)
        ok = ok & ~blocked[dests[:, 0], dests[:, 1]] & ~jnp.all(dests == human[None, :], axis=-1)
        direction = push_order[move][jnp.argmax(ok)]
        push = (cell[0] * env.size + cell[1]) * NUM_HUMAN_ACTIONS + direction
        nothing = (human[0] * env.size + human[1]) * NUM_HUMAN_ACTIONS + STAY  # always a no-op
        return jnp.where(in_the_way & jnp.any(ok), push, nothing).astype(jnp.int32)

    def memory_init(self, obs) -> Memory:
        prior = self.prior(obs)
        return Memory(belief=prior, prev_obs=obs, started=jnp.zeros((), bool), candidates=prior > 0)

    def expected_help(self, obs, belief, key) -> jax.Array:
        """Du et al.'s choice: the robot action with the most goal mass voting for it."""
        votes = jax.vmap(lambda g: self.clearing_action(obs, g))(self.cells())
        mass = jax.ops.segment_sum(belief, votes, num_segments=self.env.num_robot_actions)
        top = mass == mass.max()
        return jnp.argmax(jnp.where(top, jax.random.uniform(key, mass.shape), -1.0)).astype(jnp.int32)

    def rule_step(self, memory: Memory, obs, prev_human_action, key):
        """One robot decision: fold in the human's last move, then act. -> (action, memory)."""
        if self.variant == "original":
            updated = self.step_belief(memory.belief, memory.candidates, memory.prev_obs, obs)
        else:
            updated = self.update_belief(memory.belief, memory.prev_obs, prev_human_action)
        belief = jnp.where(memory.started, updated, memory.belief)
        if self.variant == "original":
            action = self.expected_help(obs, belief, key)
        else:
            action = self.clearing_action(obs, self.cells()[jnp.argmax(belief)])
        return action, memory._replace(belief=belief, prev_obs=obs, started=jnp.ones((), bool))

    def rule_metrics(self, memory: Memory, env_state: GridState) -> dict:
        """At an episode's end: the belief's mass on the true goal."""
        index = env_state.goal[0] * self.env.size + env_state.goal[1]
        return {"goal_belief_true": memory.belief[index]}


def _normalised_or(weights: jax.Array, fallback: jax.Array) -> jax.Array:
    """weights / their sum; where nothing is left (a move no goal explains under the exact
    model, or every weight floored at 0 by the original rule), the belief stays as it was."""
    total = weights.sum()
    return jnp.where(total > 0, weights / jnp.where(total > 0, total, 1.0), fallback)
