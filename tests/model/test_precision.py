"""The matmul precision choice: exact float32 by default on every backend, a documented opt-in
that becomes part of the run key, and a bad value refused before any work."""

import jax
import numpy as np
from conftest import esr

from esr_cli.storage import provenance


def test_default_is_exact_float32_and_leaves_keys_as_they_were(monkeypatch):
    monkeypatch.delenv(provenance.PRECISION_ENV, raising=False)
    assert provenance.apply_matmul_precision() == "highest"
    assert jax.config.jax_default_matmul_precision == "highest"
    assert "matmul_precision" not in provenance.toolchain()


def test_an_opt_in_precision_changes_the_run_key(monkeypatch):
    from esr_cli.common import specs
    from esr_cli.recipes import runs

    spec = specs.load("experiments/grid_2.yaml", "smoke")
    monkeypatch.delenv(provenance.PRECISION_ENV, raising=False)
    exact_key, _ = runs.run_key(spec)
    monkeypatch.setenv(provenance.PRECISION_ENV, "tensorfloat32")
    tf32_key, components = runs.run_key(spec)
    assert tf32_key != exact_key and components["toolchain"]["matmul_precision"] == "tensorfloat32"


def test_highest_is_bit_identical_to_xla_default_on_the_cpu():
    """On the CPU the setting changes nothing: float32 products are float32 either way."""
    x = jax.random.normal(jax.random.PRNGKey(0), (64, 96))
    w = jax.random.normal(jax.random.PRNGKey(1), (96, 32))
    default = jax.jit(lambda a, b: jax.lax.dot(a, b, precision=jax.lax.Precision.DEFAULT))(x, w)
    highest = jax.jit(lambda a, b: jax.lax.dot(a, b, precision=jax.lax.Precision.HIGHEST))(x, w)
    np.testing.assert_array_equal(np.asarray(default), np.asarray(highest))


def test_a_bad_precision_is_refused_before_any_work(tmp_path):
    proc = esr("ls", store=tmp_path, check=False, ESR_MATMUL_PRECISION="fp8")
    assert proc.returncode == 2 and "ESR_MATMUL_PRECISION='fp8'" in proc.stderr
