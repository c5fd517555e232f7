"""The convolutional actor-critic human and its PPO training (docs/overcooked.md)."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esr_cli.model.envs.overcooked import STAY, Overcooked
from esr_cli.model.humans import conv_actor_critic as cac, human_eval
from esr_cli.model.humans.ppo import PPO, Agent, PPOConfig, SelfPlayEnv, mode_config, overcooked_ppo


# ---------------------------------------------------------------- the network
def test_overcooked_ai_view_transposes_height_and_width():
    obs = np.zeros((4, 5, 26), np.uint8)
    obs[1, 3, 7] = 1  # (h, w, c)
    obs[:, :, 25] = 1  # urgency: kept
    view = np.asarray(cac.overcooked_ai_view(jnp.asarray(obs)))
    assert view.shape == (5, 4, 26) and view.dtype == np.uint8
    assert view[3, 1, 7] == 1 and view[..., :25].sum() == 1  # lands at (w, h, c)
    assert view[..., 25].all()
    batch = np.stack([obs, np.zeros_like(obs)])
    assert np.array_equal(np.asarray(cac.overcooked_ai_view(jnp.asarray(batch)))[0], view)


@pytest.mark.slow
def test_output_shapes_for_a_batch():
    params = cac.init_params(jax.random.PRNGKey(0), height=4, width=5)
    apply = jax.jit(cac.apply_jaxmarl)
    logits, value = apply(params, jnp.zeros((7, 2, 4, 5, 26), jnp.uint8))
    assert logits.shape == (7, 2, 6) and value.shape == (7, 2)
    logits, value = apply(params, jnp.zeros((4, 5, 26), jnp.uint8))
    assert logits.shape == (6,) and value.shape == ()


def test_parameter_count_for_cramped_room():
    # cramped_room: JaxMARL (H, W) = (4, 5); the network reads (W, H) = (5, 4).
    conv1 = 5 * 5 * 26 * 25 + 25  # 16,275 (5x5, padded: 5 x 4 stays)
    conv2 = 3 * 3 * 25 * 25 + 25  # 5,650 (padded)
    conv3 = 3 * 3 * 25 * 25 + 25  # 5,650 (unpadded: 5 x 4 -> 3 x 2)
    flat = (5 - 2) * (4 - 2) * 25  # 150
    dense = (flat * 64 + 64) + 2 * (64 * 64 + 64)  # 9,664 + 2 x 4,160
    tower = conv1 + conv2 + conv3 + dense  # 45,559
    expected = (tower + 64 * 6 + 6) + (tower + 64 * 1 + 1)  # policy tower + head, value tower + head
    assert expected == 91_573
    params = cac.init_params(jax.random.PRNGKey(0), height=4, width=5)
    assert cac.parameter_count(params) == expected
    # The value tower is its own: no parameter is shared with the policy.
    assert set(params["params"]) == {"policy_tower", "policy_head", "value_tower", "value_head"}


@pytest.mark.parametrize("size,pad", cac.CONV_LAYERS)
def test_matmul_convolution_equals_nn_conv(size, pad):
    x = jax.random.normal(jax.random.PRNGKey(1), (3, 5, 4, 7))
    conv = cac.Conv(6, size, pad)
    p = conv.init(jax.random.PRNGKey(2), x)
    ref = nn.Conv(6, (size, size), padding=((pad, pad), (pad, pad))).apply(p, x)
    np.testing.assert_allclose(np.asarray(conv.apply(p, x)), np.asarray(ref), atol=1e-5)


def test_initialisation_is_pytorch_default_uniform():
    params = cac.init_params(jax.random.PRNGKey(3), height=4, width=5)["params"]["policy_tower"]
    kernel = np.asarray(params["Conv_0"]["kernel"])
    bound = 1 / np.sqrt(5 * 5 * 26)
    assert np.abs(kernel).max() <= bound and np.abs(kernel).max() > 0.95 * bound


def test_leaky_relu_keeps_negative_units_alive():
    # A leaky ReLU network has a nonzero gradient for every input cell of the first layer.
    params = cac.init_params(jax.random.PRNGKey(4), height=4, width=5)
    obs = jax.random.bernoulli(jax.random.PRNGKey(5), 0.3, (4, 5, 26)).astype(jnp.float32)
    g = jax.jit(jax.grad(lambda o: cac.apply_jaxmarl(params, o)[0].sum()))(obs)
    assert np.isfinite(np.asarray(g)).all() and np.abs(np.asarray(g)).sum() > 0


# ---------------------------------------------------------------- PPO on toy environments
def bandit(payoff, players=1):
    """A one-step game: every step ends an episode. players=1: reward payoff[a]; players=2:
    reward payoff[a0] if both players chose the same action, else 0 (a coordination game)."""
    payoff = jnp.asarray(payoff, jnp.float32)

    def step(key, state, actions):
        r = payoff[actions[0]] if players == 1 else jnp.where(actions[0] == actions[1], payoff[actions[0]], 0.0)
        return state, r, jnp.zeros((players,), jnp.float32), jnp.bool_(True)

    return SelfPlayEnv(
        reset=lambda key: jnp.int32(0),
        step=step,
        observe=lambda state: jnp.zeros((players, 1), jnp.float32),
        players=players,
        num_actions=len(payoff),
    )


def tabular_agent(num_actions):
    """Logits and value as free parameters, the same in every state."""
    return Agent(
        init=lambda key: {"logits": jnp.zeros((num_actions,)), "value": jnp.zeros(())},
        apply=lambda p, obs: (jnp.broadcast_to(p["logits"], obs.shape[:-1] + (num_actions,)), jnp.broadcast_to(p["value"], obs.shape[:-1])),
    )


TOY = dict(total_steps=60 * 128, num_envs=16, rollout_steps=8, lr=0.05, anneal_lr=False)


def final_probs(ppo, updates=60, seed=0):
    runner, metrics = ppo.train(jax.random.PRNGKey(seed), updates)
    return np.asarray(jax.nn.softmax(runner.params["logits"])), metrics


@pytest.mark.slow
def test_ppo_solves_a_bandit():
    probs, metrics = final_probs(PPO(bandit([0.0, 1.0, 0.3]), tabular_agent(3), PPOConfig(**TOY)))
    assert probs[1] > 0.95, probs
    ret = np.asarray(metrics["episode_return"])
    assert ret[-5:].mean() > 0.9 and ret[:3].mean() < 0.7  # every step ends an episode: returns are rewards


@pytest.mark.slow
def test_self_play_coordinates_on_the_better_convention():
    # Both seats are the one network: it must put both on the same action, the paying one.
    probs, _ = final_probs(PPO(bandit([0.0, 1.0, 0.0], players=2), tabular_agent(3), PPOConfig(**TOY)))
    assert probs[1] > 0.9, probs


@pytest.mark.slow
def test_beside_a_random_partner_the_human_learns_its_best_response_to_it():
    # Seat 1 (the human's) alone earns 0.6 with action 2 whatever the partner does; matching the
    # partner on action 0 earns 1.0. In self-play the one network coordinates on (0, 0); beside
    # a uniform random partner matching pays 1/3 on average, so the best response is action 2.
    payoff = jnp.array([[1.0, 0.0, 0.6], [0.0, 0.9, 0.6], [0.0, 0.0, 0.6]], jnp.float32)  # [a0, a1]

    def step(key, state, actions):
        return state, payoff[actions[0], actions[1]], jnp.zeros((2,), jnp.float32), jnp.bool_(True)

    env = bandit([0.0, 0.0, 0.0], players=2)._replace(step=step)
    config = {**TOY, "total_steps": 120 * 128}
    selfplay, _ = final_probs(PPO(env, tabular_agent(3), PPOConfig(**config)), updates=120)
    assert selfplay[0] > 0.9, selfplay
    beside, metrics = final_probs(PPO(env, tabular_agent(3), PPOConfig(**config, random_partner=1.0)), updates=120)
    assert beside[2] > 0.9, beside
    assert abs(float(np.mean(metrics["episode_return"][-10:])) - 0.6) < 0.05  # the partner stays random
    # Only the partner's seat is ever random, with the probability asked for.
    ppo = PPO(env, tabular_agent(3), PPOConfig(**config, random_partner=0.5))
    fixed = jnp.log(jnp.array([1e-6, 1e-6, 1.0]))[None, None].repeat(4000, 0).repeat(2, 1)  # the network: action 2
    action, learnt = ppo.act(jax.random.PRNGKey(1), fixed)
    assert (np.asarray(action[:, 1]) == 2).all() and np.asarray(learnt[:, 1]).all()
    random_steps = ~np.asarray(learnt[:, 0], bool)
    assert abs(random_steps.mean() - 0.5) < 0.03 and (np.asarray(action[:, 0])[~random_steps] == 2).all()
    with pytest.raises(ValueError, match="random_partner"):
        PPOConfig(**TOY, random_partner=1.5)


@pytest.mark.slow
def test_a_large_kl_coefficient_holds_the_policy_at_the_clone():
    clone = np.array([0.6, 0.1, 0.3], np.float32)
    clone_logits = lambda obs: jnp.broadcast_to(jnp.log(clone), obs.shape[:-1] + (3,))  # noqa: E731
    env, agent = bandit([0.0, 1.0, 0.0]), tabular_agent(3)
    held, metrics = final_probs(PPO(env, agent, PPOConfig(**TOY, kl_coef=1000.0), clone_logits))
    np.testing.assert_allclose(held, clone, atol=0.02)
    assert float(metrics["kl_to_clone"][-1]) < 1e-3
    # Without the KL the same setting goes for the paying action.
    free, _ = final_probs(PPO(env, agent, PPOConfig(**TOY, kl_coef=0.0), clone_logits))
    assert free[1] > 0.95


def test_kl_without_a_clone_is_refused():
    with pytest.raises(ValueError, match="clone"):
        PPO(bandit([0.0, 1.0]), tabular_agent(2), PPOConfig(**TOY, kl_coef=1.0)).init(jax.random.PRNGKey(0))


def test_modes_and_schedules():
    assert mode_config("selfplay").mode == "selfplay"
    shaped = mode_config("shaped")
    assert shaped.mode == "shaped" and shaped.shaping_fraction == 0.5
    assert mode_config("bc_kl", kl_coef=3.0).kl_coef == 3.0 and mode_config("bc_kl").mode == "bc_kl"
    with pytest.raises(ValueError):
        mode_config("nope")
    d = PPOConfig()
    assert (d.num_envs, d.rollout_steps, d.update_epochs, d.num_minibatches) == (16, 128, 4, 4)
    assert d.num_updates == 5_000_000 // (16 * 128) == 2441
    ppo = PPO(bandit([0.0, 1.0]), tabular_agent(2), shaped)
    coefs = [float(ppo.shaping_coef(u)) for u in (0, d.num_updates // 4, d.num_updates // 2, d.num_updates)]
    np.testing.assert_allclose(coefs, [1.0, 0.5, 0.0, 0.0], atol=2e-3)
    assert float(PPO(bandit([0.0, 1.0]), tabular_agent(2), d).shaping_coef(0)) == 0.0


@pytest.mark.slow
def test_shaped_reward_is_annealed_into_the_training_reward():
    # A bandit whose sparse reward favours arm 0 and whose shaped reward favours arm 1 much more:
    # while shaping is on, arm 1 wins.
    def step(key, state, actions):
        return state, jnp.where(actions[0] == 0, 1.0, 0.0), jnp.where(actions[0] == 1, 5.0, 0.0)[None], jnp.bool_(True)

    env = bandit([1.0, 0.0])._replace(step=step)
    shaped = PPO(env, tabular_agent(2), PPOConfig(**{**TOY, "total_steps": 10_000 * 128}, shaping_fraction=1.0))
    probs, metrics = final_probs(shaped, updates=30)
    assert probs[1] > 0.9 and float(metrics["shaping_coef"][-1]) > 0.99
    sparse, _ = final_probs(PPO(env, tabular_agent(2), PPOConfig(**TOY)), updates=30)
    assert sparse[0] > 0.9


# ---------------------------------------------------------------- Overcooked
@pytest.mark.slow
def test_a_few_updates_on_cramped_room_run_and_are_deterministic():
    # Both optional terms at once (one compiled program): shaped reward and KL to a clone that
    # mostly stays. 20-step episodes so that resets happen within 3 updates of 16 steps.
    env = Overcooked("cramped_room", 20)
    clone = lambda obs: jnp.zeros(obs.shape[:-3] + (6,)).at[..., STAY].set(2.0)  # noqa: E731
    config = mode_config("shaped", total_steps=3 * 4 * 16, num_envs=4, rollout_steps=16, update_epochs=2, num_minibatches=2, kl_coef=0.5)
    assert config.mode == "bc_kl+shaped"
    ppo = overcooked_ppo(env, config, clone_logits=clone)
    a, ma = ppo.train(jax.random.PRNGKey(7))
    b, mb = ppo.train(jax.random.PRNGKey(7))
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(a.params))
    assert int(a.update) == 3 and ma["loss"].shape == (3,)
    for x, y in zip(jax.tree.leaves((a.params, ma)), jax.tree.leaves((b.params, mb))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    start = cac.init_params(jax.random.split(jax.random.PRNGKey(7), 3)[0], 4, 5)
    assert max(float(jnp.abs(x - y).max()) for x, y in zip(jax.tree.leaves(a.params), jax.tree.leaves(start))) > 0
    # 1 -> 0 over half of the 3 updates' 192 steps.
    np.testing.assert_allclose(np.asarray(ma["shaping_coef"]), [1.0, 1 / 3, 0.0], atol=1e-6)
    kl = np.asarray(ma["kl_to_clone"])
    assert np.isfinite(kl).all() and (kl > 0).all()
    # Steps 1-16, 17-32, 33-48 of 20-step episodes: episodes end at steps 20 and 40 in each of 4 envs.
    assert np.asarray(ma["episodes_finished"]).tolist() == [0.0, 4.0, 4.0]
    assert np.isnan(ma["episode_return"][0]) and np.isfinite(np.asarray(ma["episode_return"][1:])).all()
    # The trained human plays in the evaluation (self-play, 2 episodes of 20 steps).
    r = human_eval.episode_returns(env, cac.policy_logits, a.params, "self", 2, jax.random.PRNGKey(0))
    assert r.shape == (2,) and all(x >= 0 and x % 20 == 0 for x in r)


# ---------------------------------------------------------------- evaluation
def python_rollout(env, logits_fn, params, partner, key):
    """The evaluation's episode, step by step in Python (not jitted), with the same keys."""
    k_reset, k_steps = jax.random.split(key)
    state, total = env.reset(k_reset), 0.0
    for k in jax.random.split(k_steps, env.episode_steps):
        k_human, k_partner = jax.random.split(k)
        human = jax.random.categorical(k_human, logits_fn(params, env.observe_human(state)))
        if partner == "random":
            other = jax.random.randint(k_partner, (), 0, 6)
        elif partner == "stay":
            other = jnp.int32(STAY)
        else:
            other = jax.random.categorical(k_partner, logits_fn(params, env.observe(state)))
        state, reward = env.step(state, jnp.int32(other), jnp.int32(human))
        total += float(reward)
    return total, state


def linear_logits(params, obs):
    """A fixed state-dependent human: a random linear softmax policy on the channel counts."""
    feats = obs.astype(jnp.float32).reshape(obs.shape[:-3] + (-1, 26)).sum(-2)
    return feats @ params["w"]


@pytest.mark.slow
@pytest.mark.parametrize("partner", human_eval.PARTNERS)
def test_evaluation_matches_a_step_by_step_rollout(partner):
    env = Overcooked("cramped_room", 25)
    params = {"w": jax.random.normal(jax.random.PRNGKey(11), (26, 6))}
    key = jax.random.PRNGKey(5)
    returns, states = human_eval.episodes(env, linear_logits, params, partner, 2, key)
    for i, k in enumerate(jax.random.split(key, 2)):
        total, state = python_rollout(env, linear_logits, params, partner, k)
        assert float(returns[i]) == total
        # The whole final state agrees: the same trajectory, not only the same return.
        for x, y in zip(jax.tree.leaves(state), jax.tree.leaves(jax.tree.map(lambda a: a[i], states))):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    out = human_eval.evaluate(env, linear_logits, params, 2, key, partners=(partner,))
    assert out[partner]["returns"] == np.asarray(returns).tolist()


def test_unknown_partner_is_refused():
    with pytest.raises(ValueError, match="partner"):
        human_eval.episode_fn(Overcooked("cramped_room", 5), linear_logits, "robot")
