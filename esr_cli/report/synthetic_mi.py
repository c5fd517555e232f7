"""ESR's estimator variants on a synthetic problem whose mutual information is known
(docs/estimators.md, "A synthetic problem with a known answer").

Episodes are contexts (`CONTEXTS` of them, so that the context alone almost always tells a
batch's futures apart, as the block layout does on the gridworld); at each step the human picks
one of `ACTIONS` uniformly and the next state is (context, action). The future is the next
state (future_gamma = 0), so I(aH; g | s) = log ACTIONS exactly. Tiny MLPs for phi and psi are
trained with esr's own sampler and loss; the result is the final MI estimate in nats.

    python -m esr_cli.report.synthetic_mi      # the page's table: every variant, 3 seeds

It lives outside analysis/, whose files are digested into the keys of exact checks and
diagnoses: nothing stored depends on it.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import optax

from esr_cli.model import replay
from esr_cli.model.methods.esr import infonce_loss, mutual_information_estimate

CONTEXTS, ACTIONS, STEPS, DIM, HIDDEN, BATCH = 256, 4, 16, 16, 64, 64
UPDATES = 1500
TRUE_MI = float(np.log(ACTIONS))


@dataclass(frozen=True)
class Variant:
    """One row of the page's table: an estimator as `method` fields name it."""

    label: str
    infonce: str  # "stacked" | "separate"
    episode_group: int
    future: str  # "full" | "human"


VARIANTS = (
    Variant("`stacked`, batch negatives (the paper)", "stacked", 1, "full"),
    Variant("`stacked`, `episode_group: 8`", "stacked", 8, "full"),
    Variant("`stacked`, `future: human`", "stacked", 1, "human"),
    Variant("`separate`, batch negatives", "separate", 1, "full"),
    Variant("`separate`, `episode_group: 8`", "separate", 8, "full"),
)
SEEDS = (0, 1, 2)


def _buffer(key: jax.Array) -> replay.Buffer:
    actions = jax.random.randint(jax.random.fold_in(key, 1), (CONTEXTS, STEPS), 0, ACTIONS)
    previous = jnp.concatenate([jnp.zeros((CONTEXTS, 1), jnp.int32), actions], axis=1)
    context = jnp.broadcast_to(jnp.arange(CONTEXTS)[:, None], (CONTEXTS, STEPS + 1))
    zeros = jnp.zeros((CONTEXTS, STEPS), jnp.int32)
    return replay.add(
        replay.init(CONTEXTS, STEPS, (2,), jnp.int32),
        replay.Episodes(obs=jnp.stack([context, previous], -1), robot_action=zeros, human_action=actions,
                        reward=zeros.astype(jnp.float32)),
    )


def _mlp_init(key: jax.Array, n_in: int) -> dict:
    k1, k2 = jax.random.split(key)
    return {"w1": jax.random.normal(k1, (n_in, HIDDEN)) / np.sqrt(n_in), "b1": jnp.zeros(HIDDEN),
            "w2": jax.random.normal(k2, (HIDDEN, DIM)) / np.sqrt(HIDDEN), "b2": jnp.zeros(DIM)}


def _mlp(p: dict, x: jax.Array) -> jax.Array:
    return jax.nn.relu(x @ p["w1"] + p["b1"]) @ p["w2"] + p["b2"]


def _encode(ctx, action, keep_context=1.0, keep_action=1.0):
    return jnp.concatenate([keep_context * jax.nn.one_hot(ctx, CONTEXTS),
                            keep_action * jax.nn.one_hot(action, ACTIONS)], -1)


def estimate(infonce: str, episode_group: int, future: str, updates: int = UPDATES, seed: int = 0) -> float:
    """The MI estimate (nats, the mean of the last 100 updates) after `updates` updates."""
    key = jax.random.PRNGKey(seed)
    buf = _buffer(key)
    keep_context = 0.0 if future == "human" else 1.0  # `future: human`: psi sees only the action, the human's part of g

    def represent(params, b):
        ctx = b.obs[:, 0]
        phi_s = _mlp(params["phi"], _encode(ctx, b.human_action, keep_action=0.0))
        phi_sa = _mlp(params["phi"], _encode(ctx, b.human_action))
        psi = _mlp(params["psi"], _encode(b.future_obs[:, 0], b.future_obs[:, 1], keep_context=keep_context))
        return phi_s, phi_sa, psi

    params = {"phi": _mlp_init(jax.random.fold_in(key, 2), CONTEXTS + ACTIONS),
              "psi": _mlp_init(jax.random.fold_in(key, 3), CONTEXTS + ACTIONS)}
    opt = optax.adam(3e-3)

    def step(carry, k):
        params, opt_state = carry
        b = replay.sample(buf, k, BATCH, 0.0, episode_group)

        def loss(p):
            reps = represent(p, b)
            return infonce_loss(*reps, infonce), reps

        (_, reps), grads = jax.value_and_grad(loss, has_aux=True)(params)
        updates_, opt_state = opt.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates_), opt_state), mutual_information_estimate(*reps)

    scan = jax.jit(lambda c, ks: jax.lax.scan(step, c, ks))
    _, estimates = scan((params, opt.init(params)), jax.random.split(key, updates))
    return float(jnp.mean(estimates[-100:]))


def table(seeds: tuple[int, ...] = SEEDS) -> dict[str, list[float]]:
    """Each variant's estimate per seed, keyed by its label."""
    return {v.label: [estimate(v.infonce, v.episode_group, v.future, seed=s) for s in seeds] for v in VARIANTS}


def markdown(values: dict[str, list[float]], seeds: tuple[int, ...] = SEEDS) -> str:
    head = "| estimator | " + " | ".join(f"seed {s}" for s in seeds) + " | true |"
    rule = "|---|" + "---|" * (len(seeds) + 1)
    rows = [f"| {label} | " + " | ".join(f"{x:.3f}" for x in xs) + f" | {TRUE_MI:.3f} |" for label, xs in values.items()]
    return "\n".join([head, rule, *rows])


if __name__ == "__main__":
    sys.stdout.write(markdown(table()) + "\n")
