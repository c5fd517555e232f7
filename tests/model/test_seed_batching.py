"""Seeds run side by side (vmap) or one after another (lax.map) compute the same training."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esr_cli.common import specs
from esr_cli.model.train import compiled_chunk, compiled_init, make_trainer


@pytest.mark.slow
def test_seeds_one_after_another_train_as_seeds_side_by_side():
    spec = specs.load("experiments/grid_2.yaml", "smoke", ["train.seeds=[3,4]"])
    trainer = make_trainer(spec)
    seeds = jnp.asarray(spec.train.seeds, jnp.int32)
    results = {}
    for seed_batch in (None, 1):
        state = compiled_init(trainer)(seeds)
        state, metrics = compiled_chunk(trainer, 2, seed_batch)(state)
        results[seed_batch] = (state, metrics)
    (s_vmap, m_vmap), (s_map, m_map) = results[None], results[1]
    np.testing.assert_array_equal(m_vmap["return"], m_map["return"])  # the same episodes
    for name in ("critic_loss", "repr_loss", "beta"):
        np.testing.assert_allclose(m_vmap[name], m_map[name], rtol=1e-4, atol=1e-6)
    first_bias = s_map.learner.params["params"]["Dense_1"]["bias"]
    assert not np.allclose(first_bias[0], first_bias[1])  # the two seeds are different runs
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-5), s_vmap.learner.params, s_map.learner.params)
