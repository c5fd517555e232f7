"""The shared soft-Q learner: TD targets, episode ends, the policy and the dual step."""

import jax.numpy as jnp
import numpy as np
import pytest

from esr_cli.model.learner import BETA_MAX, BETA_MIN, dual_loss, entropy, policy_log_probs, td_loss


def test_td_loss_by_hand():
    q = jnp.array([[1.0, 2.0], [0.0, 5.0]])
    q_next = jnp.array([[3.0, 1.0], [4.0, 0.0]])
    action = jnp.array([1, 0])
    reward = jnp.array([1.0, 0.5])
    done = jnp.array([0.0, 1.0])
    loss, q_taken = td_loss(q, action, reward, q_next, done, 0.9)
    # targets: 1 + 0.9 * 3 = 3.7 (bootstrap), 0.5 (episode end: no bootstrap)
    assert np.asarray(q_taken).tolist() == [2.0, 0.0]
    assert float(loss) == pytest.approx(((2.0 - 3.7) ** 2 + (0.0 - 0.5) ** 2) / 2)


def test_policy_is_a_distribution_and_beta_sharpens_it():
    q = jnp.array([[1.0, 2.0, 3.0]])
    for beta in (0.01, 1.0, 50.0):
        assert float(jnp.exp(policy_log_probs(q, beta)).sum()) == pytest.approx(1.0, rel=1e-6)
    h = [float(entropy(policy_log_probs(q, b))[0]) for b in (0.01, 1.0, 50.0)]
    assert h[0] > h[1] > h[2]
    assert h[0] == pytest.approx(np.log(3), rel=1e-3)


@pytest.mark.slow
def test_dual_step_moves_beta_toward_the_target_entropy():
    from esr_cli.common import specs
    from esr_cli.model.learner import LearnerState, SoftQLearner

    spec = specs.load("experiments/grid_2.yaml", "smoke")
    learner = SoftQLearner(num_actions=125, network_spec=spec.network, spec=spec.learner)
    obs = jnp.zeros((4, 5, 5, 2))
    st = learner.init(__import__("jax").random.PRNGKey(0), obs[0])
    # Near-uniform Q at init: entropy ~ log 125 >> 0.6, so beta must grow.
    st2, m = learner.dual_step(st, obs + jnp.arange(4)[:, None, None, None])
    assert float(st2.beta) >= float(st.beta)
    st_hi = LearnerState(st.params, st.target_params, st.opt_state, jnp.array(BETA_MAX))
    assert float(learner.dual_step(st_hi, obs)[0].beta) <= BETA_MAX
    st_lo = LearnerState(st.params, st.target_params, st.opt_state, jnp.array(BETA_MIN))
    assert float(learner.dual_step(st_lo, obs)[0].beta) >= BETA_MIN


def test_dual_loss_is_zero_at_the_target():
    q = jnp.array([[0.0, 0.0]])
    assert float(dual_loss(1.0, q, float(np.log(2)))) == pytest.approx(0.0, abs=1e-10)


def test_linear_dual_step_moves_log_beta_by_the_entropy_gap():
    import jax

    from esr_cli.common import specs
    from esr_cli.model.learner import LearnerState, SoftQLearner

    spec = specs.load("experiments/grid_2.yaml", "smoke", ["learner.dual=linear", "learner.dual_lr=0.1"])
    learner = SoftQLearner(num_actions=125, network_spec=spec.network, spec=spec.learner)
    obs = jnp.zeros((4, 5, 5, 2)) + jnp.arange(4)[:, None, None, None]
    st = learner.init(jax.random.PRNGKey(0), obs[0])
    # At beta = 50: log beta moves by dual_lr * (H - target), whatever dH/dbeta is.
    st_hi = LearnerState(st.params, st.target_params, st.opt_state, jnp.array(50.0))
    q = learner.q_values(st.params, obs)
    h = float(jnp.mean(entropy(policy_log_probs(q, 50.0))))
    got = float(learner.dual_step(st_hi, obs)[0].beta)
    assert got == pytest.approx(50.0 * np.exp(0.1 * (h - spec.learner.target_entropy)), rel=1e-4)
    # ... and stays inside [BETA_MIN, BETA_MAX].
    st_max = LearnerState(st.params, st.target_params, st.opt_state, jnp.array(BETA_MAX))
    assert float(learner.dual_step(st_max, obs)[0].beta) == BETA_MAX
    # Near-uniform policy (beta small): H > target, so log beta grows by dual_lr * (H - target).
    st_lo = LearnerState(st.params, st.target_params, st.opt_state, jnp.array(0.01))
    h_lo = float(jnp.mean(entropy(policy_log_probs(q, 0.01))))
    assert float(learner.dual_step(st_lo, obs)[0].beta) == pytest.approx(
        0.01 * np.exp(0.1 * (h_lo - spec.learner.target_entropy)), rel=1e-4
    )


@pytest.mark.slow
def test_warmup_epochs_act_uniformly():
    import jax

    from esr_cli.common import specs
    from esr_cli.model.train import make_trainer

    spec = specs.load("experiments/grid_2.yaml", "smoke", ["train.num_envs=64"])
    trainer = make_trainer(spec)
    lstate = trainer.learner.init(jax.random.PRNGKey(0), trainer.obs_example())
    # A policy sure of one action: Q is huge for action 7 (set through the output bias).
    params = jax.tree.map(lambda x: x, lstate.params)
    bias = params["params"]["Dense_1"]["bias"]
    params["params"]["Dense_1"]["bias"] = bias.at[7].set(1e4)
    lstate = lstate._replace(params=params, beta=jnp.array(100.0))
    roll = jax.jit(lambda u: trainer.rollout(lstate, jax.random.PRNGKey(1), 64, "sample", u))
    policy_actions = np.asarray(roll(False).episodes.robot_action)
    uniform_actions = np.asarray(roll(True).episodes.robot_action)
    assert (policy_actions == 7).all()
    assert len(np.unique(uniform_actions)) > 100  # 3,200 uniform draws over 125 actions


@pytest.mark.slow
def test_dual_step_on_a_q_table_equals_the_dual_step_on_states():
    import jax

    from esr_cli.common import specs
    from esr_cli.model.learner import SoftQLearner

    spec = specs.load("experiments/grid_2.yaml", "smoke")
    learner = SoftQLearner(num_actions=125, network_spec=spec.network, spec=spec.learner)
    obs = jax.random.bernoulli(jax.random.PRNGKey(3), 0.3, (3, 4, 5, 5, 2)).astype(jnp.uint8)  # [E, T, ...]
    st = learner.init(jax.random.PRNGKey(0), obs[0, 0])
    table = learner.q_table(st, obs)
    assert table.shape == (3, 4, 125)
    e, t = jnp.array([0, 2, 1]), jnp.array([3, 0, 1])
    a, _ = learner.dual_step(st, obs[e, t])
    b, _ = learner.dual_step_q(st, table[e, t])
    assert float(a.beta) == pytest.approx(float(b.beta), rel=1e-5)
    assert float(a.beta) != float(st.beta)
