"""ESR's losses, estimators and reward against plain numpy and hand-built cases."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esr_cli.common import specs
from esr_cli.model.envs.gridworld import Gridworld
from esr_cli.model.methods.esr import (
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


@pytest.mark.slow
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
    from esr_cli.model.networks import PatchConv

    x = jax.random.normal(jax.random.PRNGKey(0), (3, 5, 5, 4))
    layer = PatchConv(6)
    params = layer.init(jax.random.PRNGKey(1), x)
    got = layer.apply(params, x)
    k, b = params["params"]["kernel"], params["params"]["bias"]
    want = jax.lax.conv_general_dilated(x, k, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")) + b
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def _filled_buffer(env, episodes=6, seed=0):
    """A replay buffer holding `episodes` random-play episodes of `env`."""
    from esr_cli.model import replay
    from esr_cli.model.humans.gridworld import NoisyGreedyHuman

    human = NoisyGreedyHuman(env=env, noise=0.2)
    t_max = env.episode_steps

    def episode(key):
        k_reset, k_steps = jax.random.split(key)

        def step(s, k):
            k_r, k_h = jax.random.split(k)
            a_r = jax.random.randint(k_r, (), 0, env.num_robot_actions)
            a_h = human.act(k_h, s)
            s2, r = env.step(s, a_r, a_h)
            return s2, (env.observe(s), a_r, a_h, r)

        final, (obs, a_r, a_h, r) = jax.lax.scan(step, env.reset(k_reset), jax.random.split(k_steps, t_max))
        return replay.Episodes(jnp.concatenate([obs, env.observe(final)[None]]), a_r, a_h, r)

    eps = jax.vmap(episode)(jax.random.split(jax.random.PRNGKey(seed), episodes))
    obs = eps.obs[0, 0]
    return replay.add(replay.init(episodes, t_max, obs.shape, obs.dtype), eps)


@pytest.mark.slow
def test_reward_table_gives_the_rewards_of_direct_representation():
    from esr_cli.model import replay

    esr, env = _esr()
    buf = _filled_buffer(env)
    st = esr.init(jax.random.PRNGKey(1), buf.obs[0, 0])
    table = esr.reward_table(st, buf)
    idx = replay.sample_index(buf, jax.random.PRNGKey(2), 64, 0.9)
    direct = esr.reward(st, replay.gather(buf, idx), None)
    np.testing.assert_allclose(esr.reward_from_table(table, idx), direct, rtol=1e-4, atol=1e-5)
    assert float(jnp.std(direct)) > 0  # a real check: the rewards differ between transitions


def test_same_future_packed_bytes_match_elementwise_comparison():
    rng = np.random.default_rng(0)
    obs = rng.integers(0, 2, (40, 5, 5, 2)).astype(np.uint8)  # 50 bytes: not a multiple of 4
    obs[7], obs[30] = obs[3], obs[3]
    want = np.all(obs.reshape(40, -1)[:, None] == obs.reshape(40, -1)[None], axis=-1)
    np.testing.assert_array_equal(np.asarray(same_future(jnp.asarray(obs))), want)
    assert want[3, 7] and want[7, 30] and want.sum() == 40 + 6
    changed = obs.copy()
    changed[30, 4, 4, 1] ^= 1  # the last byte: the padded word
    assert not bool(same_future(jnp.asarray(changed))[3, 30])


def test_dense_layers_start_as_the_original_truncated_normals():
    """Haiku's Linear default: N(0, 1/fan_in) truncated at 2 deviations, not rescaled."""
    from esr_cli.model.networks import ConvNet

    params = ConvNet((16, 32), 100, 32).init(jax.random.PRNGKey(0), jnp.zeros((1, 5, 5, 12)))
    w = np.asarray(params["params"]["Dense_0"]["kernel"])  # fan_in 800
    assert np.abs(w).max() <= 2 / np.sqrt(800)
    assert w.std() * np.sqrt(800) == pytest.approx(0.8796, abs=0.01)


def test_tables_are_used_only_when_the_buffer_is_smaller_than_a_phase_samples():
    from esr_cli.model.train import make_trainer

    paper = make_trainer(specs.load("experiments/grid_2.yaml", "paper"))  # 15,000 stored, 25,600 sampled
    assert paper.stored_transitions == 15000 and paper.reward_table_pays and paper.q_table_pays
    big = make_trainer(specs.load("experiments/grid_2.yaml", "paper", ["learner.buffer_size=30000"]))
    assert not big.reward_table_pays and not big.q_table_pays
    ave = make_trainer(specs.load("experiments/grid_2_ave.yaml", "paper"))  # no representations to table
    assert not ave.reward_table_pays and ave.q_table_pays
