"""Does a trained robot's reward rate its own play above a uniform robot's, and is the human
freer for it? Any environment, any method whose robot learns a policy.

A learned reward (ESR's is an estimate of the human's empowerment) is fitted to the data the
robot has produced lately: a replay buffer of its recent episodes. The robot's critic then
follows the reward wherever it is high, including where the estimate is wrong, and the
estimate is refitted to wherever the robot goes. This check plays the run's robot (its
sampling policy) and a uniformly acting robot with the same human, scores the transitions of
both with the run's own reward (futures drawn as in training), and sets beside that two things
the estimate does not decide: the environment's return, and how often the human's own part of
the state (its position, and on Overcooked its orientation) changes from one step to the next.
A robot whose reward climbs while the human moves less and the task fails is following the
estimate somewhere it no longer tracks the human's influence (docs/results.md, coordination
ring).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from esr_cli.model import replay
from esr_cli.model.methods.esr import mutual_information_estimate

PLAYERS = ("robot", "uniform")


def human_moves(env, obs: jax.Array) -> float:
    """obs [n, T+1, ...] -> the fraction of the n*T steps after which the human's own part of
    the observation (`env.human_view`) differs from before."""
    view = jax.vmap(jax.vmap(env.human_view))(obs)
    changed = jnp.any((view[:, 1:] != view[:, :-1]).reshape(view.shape[0], view.shape[1] - 1, -1), axis=-1)
    return float(jnp.mean(changed))


def _buffer(trainer, episodes: replay.Episodes) -> replay.Buffer:
    """`episodes` as a replay buffer, read as the run's updates read theirs (ESR's `pairing:
    original`: the post-step view)."""
    n, steps = episodes.robot_action.shape
    buf = replay.add(replay.init(n, steps, episodes.obs.shape[2:], episodes.obs.dtype), episodes)
    return replay.post_step_view(buf) if trainer.post_step_pairing else buf


def reward_on_episodes(trainer, method_state, episodes: replay.Episodes, key, batches: int) -> dict:
    """The method's reward on `batches` critic batches drawn from `episodes` as training draws
    them (geometric futures; ESR's `pairing: original` reads the post-step view):
    {"mean", "sd"} and, for ESR, "mi_estimate" (the phi minus phi' diagonal logit, nats)."""
    buf = _buffer(trainer, episodes)
    batch_size, gamma = trainer.spec.learner.batch_size, trainer.future_gamma
    method = trainer.method
    is_esr = trainer.spec.method.kind == "esr"

    @jax.jit
    def score(k):
        k_batch, k_reward = jax.random.split(k)
        batch = replay.sample(buf, k_batch, batch_size, gamma)
        reward = method.reward(method_state, batch, k_reward)
        if not is_esr:
            return reward, jnp.nan
        phi_s, phi_sa, psi = method.represent_batch(method_state.params, batch)
        return reward, mutual_information_estimate(phi_s, phi_sa, psi)

    rewards, mis = zip(*(score(jax.random.fold_in(key, i)) for i in range(batches)))
    r = np.concatenate([np.asarray(x) for x in rewards])
    out = {"mean": float(r.mean()), "sd": float(r.std())}
    if is_esr:
        out["mi_estimate"] = float(np.mean([float(m) for m in mis]))
    return out


# The refit's representation learning rate: fast enough to fit a few thousand updates (the
# paper's 3e-5 is tuned for 10,000 epochs of slowly changing data).
REFIT_LR = 1e-3
REFIT_HELD_OUT = 4  # one episode in REFIT_HELD_OUT is held out of the refit


def refit_mi_estimate(trainer, episodes: replay.Episodes, key, updates: int, batches: int = 40, lr: float = REFIT_LR) -> dict:
    """Fresh ESR representations (the run's architecture and loss, new parameters, rate `lr`)
    fitted for `updates` steps to these episodes alone, then their MI estimate on them and on
    held-out episodes: {"fit", "held_out"} (nats). Unlike the run's own representations, which
    were fitted to the robot's recent play, this estimate is fitted to the play it measures, so
    two robots' numbers compare like with like."""
    n = episodes.robot_action.shape[0]
    if n < 2:
        raise ValueError("the refit needs at least 2 episodes (one is held out)")
    method = trainer.method._replace(spec=trainer.method.spec.model_copy(update={"repr_lr": lr}))
    held = max(1, n // REFIT_HELD_OUT)
    fit_buf, held_buf = (_buffer(trainer, jax.tree.map(lambda x: x[part], episodes))
                         for part in (slice(0, n - held), slice(n - held, n)))
    batch_size, gamma, group = trainer.spec.learner.batch_size, trainer.future_gamma, trainer.repr_episode_group
    k_init, k_fit, k_eval = jax.random.split(key, 3)

    @jax.jit
    def fit(k_init, k_fit):
        def step(mstate, k):
            k_batch, k_update = jax.random.split(k)
            mstate, _ = method.update(mstate, replay.sample(fit_buf, k_batch, batch_size, gamma, group), k_update)
            return mstate, None

        mstate, _ = jax.lax.scan(step, method.init(k_init, episodes.obs[0, 0]), jax.random.split(k_fit, updates))
        return mstate

    mstate = fit(k_init, k_fit)

    @jax.jit
    def estimate(buf, k):
        batch = replay.sample(buf, k, batch_size, gamma, group)
        return mutual_information_estimate(*method.represent_batch(mstate.params, batch))

    keys = jax.random.split(k_eval, batches)
    return {name: float(np.mean([float(estimate(buf, k)) for k in keys])) for name, buf in (("fit", fit_buf), ("held_out", held_buf))}


def play_check(trainer, state, key, episodes: int = 16, batches: int = 40, refit: int = 0) -> dict:
    """{player: {"return", "reward": {...}, "human_moves"[, "refit"]}} for the run's robot and a
    uniform one, each `episodes` episodes with the run's human. `state` is one seed's
    TrainState. refit > 0 (ESR only): also `refit_mi_estimate` with that many updates."""
    if not trainer.method.learns_policy or trainer.acts_by_rule:
        raise ValueError(f"{trainer.spec.method.kind} learns no robot policy: there is no trained play to compare")
    if refit and trainer.spec.method.kind != "esr":
        raise ValueError(f"the refit fits ESR's representations; {trainer.spec.method.kind} has none")
    out = {}
    for i, player in enumerate(PLAYERS):
        k_roll, k_score = jax.random.split(jax.random.fold_in(key, i))
        uniform = player == "uniform"
        roll = jax.jit(lambda k, u=uniform: trainer.rollout(state.learner, k, episodes, "sample", u, state.human))(k_roll)
        ep = roll.episodes
        out[player] = {
            "episodes": episodes,
            "return": float(jnp.mean(ep.reward.sum(axis=1))),
            "reward": reward_on_episodes(trainer, state.method, ep, k_score, batches),
            "human_moves": human_moves(trainer.env, ep.obs),
        }
        if refit:
            out[player]["refit"] = refit_mi_estimate(trainer, ep, jax.random.fold_in(k_score, 1), refit, batches)
    return out
