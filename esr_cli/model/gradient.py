"""The one gradient update every learner in the model takes (the critic, ESR's and IQ-Learn's
representations, the cloned, adapting and PPO humans)."""

from __future__ import annotations

import jax
import optax


def gradient_step(loss_fn, params, opt_state, optimizer: optax.GradientTransformation):
    """One optimiser step on `loss_fn(params) -> (loss, aux)`.
    Returns ((loss, aux), new params, new optimiser state)."""
    value, grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return value, optax.apply_updates(params, updates), opt_state
