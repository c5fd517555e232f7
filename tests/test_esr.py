"""ESR's losses, estimators and reward against plain numpy and hand-built cases."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esr_cli import spec as specs
from esr_cli.envs.gridworld import Gridworld
from esr_cli.methods.esr import (
    ESR,
    contrastive_accuracy,
    contrastive_chance,
    empowerment_reward,
    infonce_loss,
    mutual_information_estimate,
    same_future,
)


def np_log_softmax(x, axis):
    x = x - x.max(axis=axis, keepdims=True)
    return x - np.log(np.exp(x).sum(axis=axis, keepdims=True))


def np_sym_infonce(x, y, d):
    logits = x @ y.T / d
    n = logits.shape[0]
    rows = np_log_softmax(logits, 1)[np.arange(n), np.arange(n)]
    cols = np_log_softmax(logits, 0)[np.arange(n), np.arange(n)]
    return -rows.mean() - cols.mean()


@pytest.fixture
def reps():
    rng = np.random.default_rng(0)
    b, d = 7, 4
    return [rng.normal(size=(b, d)).astype(np.float32) * 2 for _ in range(3)]


def test_infonce_stacked_matches_numpy(reps):
    phi_s, phi_sa, psi = reps
    want = np_sym_infonce(np.concatenate([phi_s, phi_sa]), np.concatenate([psi, psi]), 4)
    got = float(infonce_loss(jnp.array(phi_s), jnp.array(phi_sa), jnp.array(psi), "stacked"))
    assert got == pytest.approx(want, rel=1e-5)


def test_infonce_separate_matches_numpy(reps):
    phi_s, phi_sa, psi = reps
    want = np_sym_infonce(phi_sa, psi, 4) + np_sym_infonce(phi_s, psi, 4)
    got = float(infonce_loss(jnp.array(phi_s), jnp.array(phi_sa), jnp.array(psi), "separate"))
    assert got == pytest.approx(want, rel=1e-5)


def test_infonce_separate_reaches_zero_and_stacked_cannot():
    big = 50.0 * np.eye(4, dtype=np.float32)
    sep = float(infonce_loss(jnp.array(big), jnp.array(big), jnp.array(big), "separate"))
    stk = float(infonce_loss(jnp.array(big), jnp.array(big), jnp.array(big), "stacked"))
    assert sep < 1e-3
    assert stk == pytest.approx(2 * np.log(2), rel=1e-3)  # each positive appears twice: log 2 per direction


def test_mi_estimate_and_accuracy_by_hand():
    psi = np.eye(3, dtype=np.float32)
    phi_sa = 2 * np.eye(3, dtype=np.float32)
    phi_s = np.zeros((3, 3), np.float32)
    assert float(mutual_information_estimate(phi_s, phi_sa, psi)) == pytest.approx(2 / 3)
    assert float(contrastive_accuracy(phi_sa, psi)) == 1.0
    assert float(contrastive_accuracy(phi_sa[::-1], psi)) == pytest.approx(1 / 3)


def test_accuracy_counts_identical_futures_as_right():
    futures = np.array([[0, 1], [0, 1], [2, 2]], np.uint8)  # the first two are the same state
    same = same_future(jnp.array(futures))
    assert np.asarray(same).tolist() == [[True, True, False], [True, True, False], [False, False, True]]
    assert float(contrastive_chance(same)) == pytest.approx(5 / 9)
    psi = np.eye(3, dtype=np.float32)
    phi_sa = np.array([[0, 1, 0], [1, 0, 0], [0, 1, 0]], np.float32)  # rows 0, 1 swap: still right
    assert float(contrastive_accuracy(phi_sa, psi)) == pytest.approx(0.0)
    assert float(contrastive_accuracy(phi_sa, psi, same)) == pytest.approx(2 / 3)


def test_reward_sign_by_hand():
    psi = np.array([[1.0, 0.0]], np.float32)
    toward = empowerment_reward(np.array([[0.0, 0.0]]), np.array([[2.0, 0.0]]), psi)
    away = empowerment_reward(np.array([[2.0, 0.0]]), np.array([[0.0, 0.0]]), psi)
    same = empowerment_reward(np.array([[1.0, 1.0]]), np.array([[1.0, 1.0]]), psi)
    # The human's action makes g more likely than without it: positive; less likely: negative.
    assert float(toward[0]) == 2.0 and float(away[0]) == -2.0 and float(same[0]) == 0.0


def _esr(condition=True):
    raw = specs.load_raw("experiments/grid_2.yaml")
    raw["method"]["condition_on_robot_action"] = condition
    spec = specs.resolve(raw, "smoke")
    env = Gridworld(size=5, num_blocks=2, start="corner", episode_steps=50)
    return ESR(env=env, spec=spec.method, network_spec=spec.network), env


def test_phi_prime_ignores_the_human_action():
    esr, env = _esr()
    obs = env.observe(env.reset(jax.random.PRNGKey(0)))
    st = esr.init(jax.random.PRNGKey(1), obs)
    obs2 = jnp.stack([obs, obs])
    phi_s, phi_sa, _ = esr.represent(st.params, obs2, jnp.array([7, 7]), jnp.array([0, 3]), obs2)
    np.testing.assert_allclose(phi_s[0], phi_s[1], rtol=1e-6)
    assert not np.allclose(phi_sa[0], phi_sa[1])


def test_no_robot_action_ablation_ignores_the_robot_action():
    esr, env = _esr(condition=False)
    obs = env.observe(env.reset(jax.random.PRNGKey(0)))
    st = esr.init(jax.random.PRNGKey(1), obs)
    obs2 = jnp.stack([obs, obs])
    phi_s, phi_sa, _ = esr.represent(st.params, obs2, jnp.array([7, 90]), jnp.array([2, 2]), obs2)
    np.testing.assert_allclose(phi_sa[0], phi_sa[1], rtol=1e-6)
    np.testing.assert_allclose(phi_s[0], phi_s[1], rtol=1e-6)
    esr_c, _ = _esr(condition=True)
    st = esr_c.init(jax.random.PRNGKey(1), obs)
    phi_s, _, _ = esr_c.represent(st.params, obs2, jnp.array([7, 90]), jnp.array([2, 2]), obs2)
    assert not np.allclose(phi_s[0], phi_s[1])


def test_patch_conv_equals_a_real_convolution():
    from esr_cli.networks import PatchConv

    x = jax.random.normal(jax.random.PRNGKey(0), (3, 5, 5, 4))
    layer = PatchConv(6)
    params = layer.init(jax.random.PRNGKey(1), x)
    got = layer.apply(params, x)
    k, b = params["params"]["kernel"], params["params"]["bias"]
    want = jax.lax.conv_general_dilated(x, k, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")) + b
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
