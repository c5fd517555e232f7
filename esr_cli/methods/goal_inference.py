"""Goal Inference (after Du et al. 2020): infer the human's goal, then clear its way there.

The robot keeps, in each environment, a belief over the human's goal: every cell free of
blocks and of the human at the episode's start, uniform at first. After each step it sees the
human's action aH taken from state s and updates the belief by Bayes' rule under the known
noisy-greedy human model (the world model is the gridworld's own rules):

    b(g) <- b(g) P(aH | s, g),   P(aH | s, g) = (1 - noise) [aH = greedy(s, g)] + noise / 5

Du et al. used a uniform prior moved by fixed +-alpha steps for consistent / inconsistent
moves; the exact posterior is the same idea without the step size to tune (docs/baselines.md).

Acting rule, toward the most probable goal g*: the human's next cell on its straight-line
way to g*, ignoring blocks, is c. If a block sits on c, the robot pushes it sideways
(perpendicular to the human's move, first choice that lands on a free in-grid cell), else
straight ahead away from the human; never onto the human. Otherwise it does nothing. It
learns nothing, so there is no critic; training only records its returns.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from esr_cli.envs.gridworld import DIRECTIONS, NUM_HUMAN_ACTIONS, STAY, GridState
from esr_cli.methods.base import no_update, stateless_init

MOVES = 4  # left, down, right, up: the human's moves toward a goal
# For a move d (index into DIRECTIONS), the push directions tried in order: the two
# perpendicular ones, then d itself (away from the human).
PUSH_ORDER = jnp.array([[1, 3, 0], [0, 2, 1], [1, 3, 2], [0, 2, 3]], dtype=jnp.int32)


class Memory(NamedTuple):
    belief: jax.Array  # float32[S*S]: over goal cells
    prev_obs: jax.Array  # the observation the human last acted on
    started: jax.Array  # bool: false before the first step of an episode


class GoalInference(NamedTuple):
    env: object  # Gridworld
    human: object  # NoisyGreedyHuman (the known human model)

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
        return cls(env=env, human=human)

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
        post = belief * self.likelihood(obs, human_action)
        total = post.sum()
        # A move no goal explains (cannot happen under the model) leaves the belief unchanged.
        return jnp.where(total > 0, post / jnp.where(total > 0, total, 1.0), belief)

    # ------------------------------------------------------------ acting
    def clearing_action(self, obs, goal) -> jax.Array:
        env = self.env
        human = env.human_position(obs)
        dist = jnp.linalg.norm((human[None, :] + DIRECTIONS[:MOVES] - goal[None, :]).astype(jnp.float32), axis=-1)
        move = jnp.argmin(dist)
        cell = human + DIRECTIONS[move]
        inside = jnp.all((cell >= 0) & (cell < env.size))
        cell = jnp.clip(cell, 0, env.size - 1)
        blocked = obs[..., 1] > 0
        in_the_way = inside & blocked[cell[0], cell[1]] & ~jnp.all(human == goal)
        dests = cell[None, :] + DIRECTIONS[PUSH_ORDER[move]]
        ok = jnp.all((dests >= 0) & (dests < env.size), axis=-1)
        dests = jnp.clip(dests, 0, env.size - 1)
        ok = ok & ~blocked[dests[:, 0], dests[:, 1]] & ~jnp.all(dests == human[None, :], axis=-1)
        direction = PUSH_ORDER[move][jnp.argmax(ok)]
        push = (cell[0] * env.size + cell[1]) * NUM_HUMAN_ACTIONS + direction
        nothing = (human[0] * env.size + human[1]) * NUM_HUMAN_ACTIONS + STAY  # always a no-op
        return jnp.where(in_the_way & jnp.any(ok), push, nothing).astype(jnp.int32)

    def memory_init(self, obs) -> Memory:
        return Memory(belief=self.prior(obs), prev_obs=obs, started=jnp.zeros((), bool))

    def rule_step(self, memory: Memory, obs, prev_human_action):
        """One robot decision: fold in the human's last action, then act. -> (action, memory)."""
        updated = self.update_belief(memory.belief, memory.prev_obs, prev_human_action)
        belief = jnp.where(memory.started, updated, memory.belief)
        goal = self.cells()[jnp.argmax(belief)]
        action = self.clearing_action(obs, goal)
        return action, Memory(belief=belief, prev_obs=obs, started=jnp.ones((), bool))

    def rule_metrics(self, memory: Memory, env_state: GridState) -> dict:
        """At an episode's end: the belief's mass on the true goal."""
        index = env_state.goal[0] * self.env.size + env_state.goal[1]
        return {"goal_belief_true": memory.belief[index]}
