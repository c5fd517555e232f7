"""Why a gridworld robot does or does not help: a trained run's reward by the human's situation,
and what its critic and policy make of the trapped corner start.

Situations of a stored transition (from the state the robot acted in, and its reward):
    trapped   the human cannot move: every neighbouring cell is a wall or a block
    free      the human can move and is not on its goal
    at_goal   the human is on its goal (the environment's reward is 1)
    dead      a block sits on the human
For ESR the reward estimates the human's empowerment, which is positive only while the human
is free; a working estimator ranks `free` far above the other three (docs/results.md).

Robot actions at a corner start are grouped by what they do with the human staying: keep the
human trapped (the no-ops and wall pushes), free it, or push a block onto it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from esr_cli.model import replay
from esr_cli.model.methods.esr import contrastive_accuracy, mutual_information_estimate, same_future

SITUATIONS = ("trapped", "free", "at_goal", "dead")
EFFECTS = ("trapped", "free", "dead")


def situation(obs: np.ndarray, reward: np.ndarray) -> np.ndarray:
    """obs uint8[..., S, S, 2] (human plane, block plane), reward [...] -> int[...] into SITUATIONS."""
    obs = np.asarray(obs)
    human, blocks = obs[..., 0].astype(bool), obs[..., 1].astype(bool)
    size = human.shape[-1]
    dead = np.any(human & blocks, axis=(-2, -1))
    padded = np.pad(blocks, [(0, 0)] * (blocks.ndim - 2) + [(1, 1), (1, 1)], constant_values=True)  # walls
    free_neighbours = np.zeros(human.shape[:-2], int)
    for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        open_cell = ~padded[..., 1 + dr : 1 + dr + size, 1 + dc : 1 + dc + size]
        free_neighbours += np.any(human & open_cell, axis=(-2, -1))
    out = np.where(free_neighbours > 0, SITUATIONS.index("free"), SITUATIONS.index("trapped"))
    out = np.where(np.asarray(reward) > 0, SITUATIONS.index("at_goal"), out)
    return np.where(dead, SITUATIONS.index("dead"), out)


def reward_by_situation(trainer, state, key, batches: int = 40) -> dict:
    """The method's reward on `batches` critic batches from the run's buffer, by situation:
    {situation: {"n", "mean", "sd"}}. `state` is one seed's TrainState."""
    sample = jax.jit(lambda k: trainer.critic_sampler.batch(state.buffer, k))
    reward = jax.jit(lambda b, k: trainer.method.reward(state.method, b, k))
    values = {name: [] for name in SITUATIONS}
    for i in range(batches):
        k_batch, k_reward = jax.random.split(jax.random.fold_in(key, i))
        batch = sample(k_batch)
        r = np.asarray(reward(batch, k_reward))
        where = situation(np.asarray(batch.obs), np.asarray(batch.reward))
        for j, name in enumerate(SITUATIONS):
            values[name].extend(r[where == j].tolist())
    return {
        name: {"n": len(v), "mean": float(np.mean(v)) if v else float("nan"), "sd": float(np.std(v)) if v else float("nan")}
        for name, v in values.items()
    }


def free_trapped_contrast(rewards: dict) -> dict:
    """How far the reward ranks a free human above a trapped one (from `reward_by_situation`):
    the difference of means and Cohen's d, that difference in pooled standard deviations."""
    free, trapped = rewards["free"], rewards["trapped"]
    diff = free["mean"] - trapped["mean"]
    n1, n2 = free["n"], trapped["n"]
    if n1 < 2 or n2 < 2:
        return {"difference": diff, "effect_size": float("nan")}
    # reward_by_situation reports population SDs (ddof 0): back to sums of squares.
    pooled = np.sqrt((n1 * free["sd"] ** 2 + n2 * trapped["sd"] ** 2) / (n1 + n2 - 2))
    return {"difference": diff, "effect_size": float(diff / pooled) if pooled > 0 else float("nan")}


def stored_effects(buffer: replay.Buffer, human_cell) -> dict:
    """{effect: n}: the buffer's transitions out of a state where the human is trapped at
    `human_cell` (row, col), whatever the other blocks, by the human's situation after them.
    What the critic can have learned about freeing the human there from the data it holds: an
    effect that never occurs has its Q values from generalisation alone."""
    held = int(buffer.count)
    obs = np.asarray(buffer.obs[:held])
    before, after = obs[:, :-1], obs[:, 1:]
    no_reward = np.zeros(before.shape[:2])
    here = (before[..., human_cell[0], human_cell[1], 0] == 1) & (situation(before, no_reward) == SITUATIONS.index("trapped"))
    effect = situation(after[here], np.zeros(int(here.sum())))
    return {name: int(np.sum(effect == SITUATIONS.index(name))) for name in EFFECTS}


def start_policy(trainer, state, key, starts: int = 4, draws: int = 64) -> list[dict]:
    """For up to `starts` distinct start states (of `draws` resets: a center start has one):
    per effect of the robot's action (the human staying), how many actions have it, their
    largest and mean Q, the policy's probability of choosing one, and how many of the buffer's
    transitions out of a trapped human at that start cell had it (`stored_effects`)."""
    env, learner = trainer.env, trainer.learner
    actions = jnp.arange(env.num_robot_actions, dtype=jnp.int32)
    rows, seen = [], set()
    for i in range(draws):
        if len(rows) == starts:
            break
        s = env.reset(jax.random.fold_in(key, i))
        layout = (tuple(np.asarray(s.human).tolist()), tuple(sorted(map(tuple, np.asarray(s.blocks).tolist()))))
        if layout in seen:
            continue
        seen.add(layout)
        nxt = jax.vmap(lambda a: env.step(s, a, jnp.int32(env.num_human_actions - 1))[0])(actions)  # human stays
        next_obs = np.asarray(jax.vmap(env.observe)(nxt))
        effect = np.array([SITUATIONS[k] for k in situation(next_obs, np.zeros(len(next_obs)))])
        obs = env.observe(s)[None]
        q = np.asarray(learner.q_values(state.learner.params, obs))[0]
        p = np.exp(np.asarray(learner.log_probs(state.learner, obs))[0])
        row = {"human": np.asarray(s.human).tolist()}
        stored = stored_effects(state.buffer, tuple(int(c) for c in np.asarray(s.human)))
        for name in EFFECTS:
            chosen = effect == name
            row[name] = {"actions": int(chosen.sum()), "q_max": float(q[chosen].max()) if chosen.any() else float("nan"),
                         "q_mean": float(q[chosen].mean()) if chosen.any() else float("nan"), "p": float(p[chosen].sum()),
                         "stored": stored[name]}
        rows.append(row)
    return rows


def representation_check(trainer, state, key, batches: int = 40) -> dict:
    """What ESR's contrastive representations use to pick a transition's future in a batch.

    Returns, averaged over `batches` representation batches of the run's buffer:
      accuracy_phi / accuracy_phi_prime   phi(s, aR, aH) / phi'(s, aR) pick the true future
                                          (an identical copy counts as right, as in training)
      chance                              guessing uniformly among the batch
      layout_only                         the best accuracy of a guesser that knows only the
                                          true future's block layout (uniform among the batch's
                                          futures with that layout)
      within_layout_phi / _phi_prime      accuracy when the candidates are only the futures with
                                          the true future's block layout: what the human's
                                          position adds beyond the layout
      mi_estimate                         mean diagonal logit of phi minus that of phi' (nats)
    When layout_only is near 1 the block layout alone names the episode, phi' solves the batch
    without the human's action, and the MI estimate has no reason to grow (docs/results.md)."""
    method = trainer.method
    params = state.method.params

    def one(k):
        b = trainer.critic_sampler.batch(state.buffer, k)
        phi_s, phi_sa, psi = method.represent_batch(params, b)
        return representation_scores(phi_s, phi_sa, psi, b.future_obs)

    out = jax.jit(jax.vmap(one))(jax.random.split(key, batches))
    return {name: float(np.mean(v)) for name, v in out.items()}


def representation_scores(phi_s, phi_sa, psi, future_obs) -> dict:
    """The scores of `representation_check` on one batch; future_obs [B, S, S, 2] (human plane,
    block plane)."""
    same = same_future(future_obs)
    layout = same_future(future_obs[..., 1])
    rows = jnp.arange(psi.shape[0])

    def within(phi):
        logits = jnp.where(layout, phi @ psi.T, -jnp.inf)
        return jnp.mean(same[rows, jnp.argmax(logits, axis=1)])

    return {
        "accuracy_phi": contrastive_accuracy(phi_sa, psi, same),
        "accuracy_phi_prime": contrastive_accuracy(phi_s, psi, same),
        "chance": jnp.mean(same),
        "layout_only": jnp.mean(jnp.sum(same, axis=1) / jnp.sum(layout, axis=1)),
        "within_layout_phi": within(phi_sa),
        "within_layout_phi_prime": within(phi_s),
        "mi_estimate": mutual_information_estimate(phi_s, phi_sa, psi),
    }
