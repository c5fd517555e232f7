"""Overcooked: the JaxMARL adapter, the human-data conversion (replayed through JaxMARL), the
BC loss and the co-adapting human's update."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esr_cli.common import specs
from esr_cli.model import spec as spec_model
from esr_cli.model.envs.overcooked import INTERACT, LAYOUTS, NUM_ACTIONS, STAY, Overcooked
from esr_cli.model.humans import bc, overcooked_data as od
from esr_cli.model.humans.policy_human import PolicyHuman


@pytest.fixture(scope="module")
def cramped():
    return Overcooked("cramped_room", 400)


@pytest.mark.slow
def test_env_interface(cramped):
    env = cramped
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    obs, h = jax.jit(lambda s: (env.observe(s), env.observe_human(s)))(s)
    assert obs.shape == env.obs_shape == (4, 5, 26) and obs.dtype == jnp.uint8
    # agent_0 (the robot) sees itself in channel 0, the human in channel 1; the human's view swaps them.
    assert (obs[..., 0] == h[..., 1]).all() and (obs[..., 1] == h[..., 0]).all()
    assert env.num_robot_actions == env.num_human_actions == NUM_ACTIONS == 6
    planes = env.robot_action_planes(jnp.int32(INTERACT))
    assert planes.shape == (4, 5, 6) and (planes[..., INTERACT] == 1).all() and planes.sum() == 20
    s2, r = jax.jit(env.step)(s, jnp.int32(STAY), jnp.int32(STAY))
    assert float(r) == 0.0 and int(s2.step) == 1
    assert (np.asarray(s2.agent_pos) == np.asarray(s.agent_pos)).all()
    img = env.render(s2)
    assert img.shape == (4 * 32, 5 * 32, 3) and img.dtype == np.uint8 and img.std() > 0


@pytest.mark.slow
def test_human_view_is_the_humans_position_and_orientation(cramped):
    """In the robot's view the human is layer 1 (position) and 6-9 (orientation, one-hot at its
    cell); the human's own view has them as 0 and 2-5. At the start it holds nothing, so
    everything else is zeroed."""
    env = cramped
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    obs, h = np.asarray(env.observe(s)), np.asarray(env.observe_human(s))
    view = np.asarray(env.human_view(jnp.asarray(obs)))
    assert view.shape == obs.shape and view.dtype == obs.dtype
    np.testing.assert_array_equal(view[..., 1], h[..., 0])
    np.testing.assert_array_equal(view[..., 6:10], h[..., 2:6])
    assert view[..., 6:10].sum() == 1  # one orientation at the human's cell
    others = [c for c in range(obs.shape[-1]) if c not in (1, 6, 7, 8, 9)]
    assert view[..., others].sum() == 0 and obs[..., others].sum() > 0


def test_human_view_keeps_what_the_human_holds_and_nothing_else_of_the_items(cramped):
    """A hand-built robot observation: the human at (1, 2) holding a plated soup, the robot at
    (2, 3) holding an onion, an onion and a plate on counters. The human's part keeps its soup
    (layers 18 and 21 at its cell) and drops every other item."""
    obs = np.zeros((4, 5, 26), np.uint8)
    obs[2, 3, 0] = obs[1, 2, 1] = 1  # robot, human positions
    obs[2, 3, 2] = obs[1, 2, 7] = 1  # orientations
    obs[1, 2, 18], obs[1, 2, 21] = 3, 1  # the human's plated soup
    obs[2, 3, 23] = 1  # the robot's onion
    obs[0, 1, 23] = obs[0, 4, 22] = 1  # an onion and a plate on counters
    obs[0, :, 11] = 1  # counters
    obs[3, 0, 18], obs[3, 0, 21] = 3, 1  # a soup done in a pot
    obs[..., 25] = 1  # urgency
    view = np.asarray(cramped.human_view(jnp.asarray(obs)))
    expected = np.zeros_like(obs)
    expected[1, 2, 1] = expected[1, 2, 7] = expected[1, 2, 21] = 1
    expected[1, 2, 18] = 3
    np.testing.assert_array_equal(view, expected)
    # an empty-handed human: position and orientation only
    obs[1, 2, 18] = obs[1, 2, 21] = 0
    obs[1, 2, 22] = 1  # now an empty plate
    view = np.asarray(cramped.human_view(jnp.asarray(obs)))
    assert view[1, 2, 22] == 1 and view.sum() == 3


def test_an_episode_runs_400_steps_without_reset(cramped):
    env = cramped

    def step(s, k):
        a = jax.random.randint(k, (2,), 0, 6)
        s, r = env.step(s, a[0], a[1])
        return s, r

    @jax.jit
    def episode(k0, k1):
        final, rewards = jax.lax.scan(step, env.reset(k0), jax.random.split(k1, 400))
        return final, rewards, env.observe(final)

    final, rewards, obs = episode(jax.random.PRNGKey(2), jax.random.PRNGKey(3))
    assert rewards.shape == (400,) and int(final.step) == 400
    assert obs[0, 0, 25] == 1  # the urgency channel is on at the end


@pytest.mark.slow
def test_conversion_details(cramped):
    # players[0] at (1, 2) facing west holding a plated soup ('soup'); players[1] at (3, 1)
    # facing north holding an empty plate ('dish'); 2 onions in the pot at (2, 0); a loose
    # onion on the counter at (4, 2).
    state = {
        "players": [
            {"position": [1, 2], "orientation": [-1, 0], "held_object": {"name": "soup", "position": [1, 2], "state": ["onion", 3, 20]}},
            {"position": [3, 1], "orientation": [0, -1], "held_object": {"name": "dish", "position": [3, 1]}},
        ],
        "objects": {
            "2,0": {"name": "soup", "position": [2, 0], "state": ["onion", 2, 0]},
            "4,2": {"name": "onion", "position": [4, 2]},
        },
    }
    s = jax.tree.map(lambda a: a[0], od.to_jaxmarl(cramped, [state]))
    obs = jax.jit(cramped.observe)(s)
    assert np.asarray(s.agent_pos).tolist() == [[1, 2], [3, 1]]
    assert np.asarray(s.agent_dir_idx).tolist() == [3, 0]
    assert np.asarray(s.agent_inv).tolist() == [od.DISH, od.PLATE]
    pad = (s.maze_map.shape[0] - 4) // 2
    assert int(s.maze_map[pad + 0, pad + 2, 2]) == 21  # 2 onions: status 23 - 2
    assert int(s.maze_map[pad + 2, pad + 4, 0]) == od.ONION
    assert int(obs[0, 2, 16]) == 2  # onions-in-pot channel
    # Cooking: 3 onions at tick t -> status 20 - t, clamped at 0 (the data's tick runs past 20).
    assert od._pot_status(["onion", 3, 5]) == 15 and od._pot_status(["onion", 3, 27]) == 0
    assert od.parse_joint_action("[[0, -1], 'INTERACT']") == (0, INTERACT)
    assert od.parse_joint_action("[[0, 0], [-1, 0]]") == (STAY, 3)
    # The observation decodes back to this state (AvE's rollouts start from observations),
    # and so do recorded states with cooking and ready pots, plated soups, plates and onions.
    rows = od.load_rows("cramped_room", "train")
    rows = rows[rows["state"].str.contains("soup")].iloc[::40][:100]
    states = od.to_jaxmarl(cramped, [state] + list(rows["state"]))
    decoded = jax.jit(jax.vmap(lambda s: cramped.state_from_obs(cramped.observe(s))))(states)
    for field in ("agent_pos", "agent_dir_idx", "agent_inv", "maze_map"):
        assert (np.asarray(getattr(decoded, field)) == np.asarray(getattr(states, field))).all(), field
    statuses = np.asarray(states.maze_map)[:, pad + 0, pad + 2, 2]
    assert (statuses == 0).any() and ((statuses > 0) & (statuses < 20)).any()  # ready and cooking pots seen


@pytest.mark.slow
@pytest.mark.parametrize("layout,split", list(zip(LAYOUTS, ("train", "test", "train", "test", "train"))))
def test_recorded_joint_actions_replay_in_jaxmarl(layout, split):
    """Stepping JaxMARL from a converted state with the recorded joint action gives the
    converted recorded next state, for a random sample of rows of each layout (every layout
    loads; the data artifact checks 1,000 rows of its layout when it is built)."""
    check = od.replay_match(layout, split, sample=50, seed=1)
    assert check["checked"] == 50
    assert check["matched"] == 50, check


def test_checksum_mismatch_is_refused(tmp_path, monkeypatch):
    for name, _ in od.FILES.values():
        (tmp_path / name).write_bytes(b"not the trials")
    monkeypatch.setattr(od, "data_dir", lambda: tmp_path)
    with pytest.raises(od.HumanDataError, match="sha256"):
        od.verified_files()


def test_missing_package_says_how_to_install(monkeypatch):
    monkeypatch.setattr(od.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(od.HumanDataError, match="make install"):
        od.data_dir()


# ---------------------------------------------------------------- BC
def test_weighted_ce_downweights_stay():
    logits = jnp.zeros((4, NUM_ACTIONS)).at[:, STAY].set(3.0)  # a policy that loves staying
    actions = jnp.array([STAY, STAY, STAY, INTERACT])
    full, light = bc.weighted_ce(logits, actions, 1.0), bc.weighted_ce(logits, actions, 0.1)
    assert float(light) > float(full)  # the mistaken non-stay sample counts for more
    nll_interact = -jax.nn.log_softmax(logits[3])[INTERACT]
    nll_stay = -jax.nn.log_softmax(logits[0])[STAY]
    np.testing.assert_allclose(float(light), float((3 * 0.1 * nll_stay + nll_interact) / 1.3), rtol=1e-6)


def cell_rule(n: int, moving_fraction: float, seed: int):
    """Synthetic pairs: the action is which of 3 cells holds a 1, else stay. -> (obs, action, moving)."""
    rng = np.random.default_rng(seed)
    obs = np.zeros((n, 4, 5, 26), np.uint8)
    action = np.full(n, STAY, np.int8)
    moving = rng.random(n) < moving_fraction
    which = rng.integers(0, 3, n)
    obs[moving, 0, which[moving], 3] = 1
    action[moving] = which[moving]
    return obs, action, moving


@pytest.mark.slow
def test_bc_learns_a_state_dependent_rule_and_reports_non_stay_accuracy():
    obs, action, moving = cell_rule(1000, 0.3, seed=0)  # stays dominate
    spec = spec_model.BCHumanSpec(kind="bc", epochs=10, lr=5e-3, batch_size=100)
    params, losses = bc.train_bc(obs, action, spec)
    assert losses[-1] < losses[0]
    acc = bc.accuracies(params, bc.cloned_policy(spec).logits, obs, action)
    assert acc["non_stay_accuracy"] > 0.95 and acc["accuracy"] > 0.9
    assert abs(acc["stay_fraction"] - (1 - moving.mean())) < 1e-3


@pytest.mark.slow
def test_bc_with_the_papers_network_learns_the_rule_and_has_the_ppo_humans_parameters():
    from esr_cli.model.humans import conv_actor_critic as cac

    obs, action, _ = cell_rule(600, 0.4, seed=1)
    spec = spec_model.BCHumanSpec(kind="bc", network="conv", epochs=15, lr=3e-3, batch_size=50)
    params, losses = bc.train_bc(obs, action, spec)
    assert losses[-1] < 0.5 * losses[0]
    acc = bc.accuracies(params, bc.cloned_policy(spec).logits, obs, action)
    assert acc["non_stay_accuracy"] > 0.9 and acc["accuracy"] > 0.9
    # The same tree as the PPO human's (value tower untouched by cloning), so either loads as the other.
    like = cac.init_params(jax.random.PRNGKey(0), 4, 5)
    assert jax.tree.structure(params) == jax.tree.structure(like)
    assert [x.shape for x in jax.tree.leaves(params)] == [x.shape for x in jax.tree.leaves(like)]
    fresh = bc.cloned_policy(spec).init(jax.random.split(jax.random.PRNGKey(0))[0], jnp.asarray(obs[0]))
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(fresh["params"]["value_tower"]),
                                                      jax.tree.leaves(params["params"]["value_tower"])))
    # The urgency channel is zeroed for this network too (the data's games are not 400 steps long).
    urgent = jnp.asarray(obs[:4]).at[..., 25].set(1)
    logits = bc.cloned_policy(spec).logits
    assert np.array_equal(np.asarray(logits(params, urgent)), np.asarray(logits(params, jnp.asarray(obs[:4]))))


def test_a_bc_human_names_its_network_in_its_key_and_refuses_mlp_settings_with_the_conv():
    mlp, conv = spec_model.BCHumanSpec(kind="bc"), spec_model.BCHumanSpec(kind="bc", network="conv")
    assert "network" not in mlp.cloning_part("cramped_room") and mlp.cloning_part("cramped_room")["hidden"] == [64, 64]
    assert conv.cloning_part("cramped_room")["network"] == "conv" and "hidden" not in conv.cloning_part("cramped_room")
    with pytest.raises(ValueError, match="hidden sizes the MLP"):
        spec_model.BCHumanSpec(kind="bc", network="conv", hidden=(32,))
    with pytest.raises(specs.SpecError, match="names MLP settings"):
        specs.load("experiments/cramped_room.yaml", "smoke", ["human={kind: bc, network: conv, preset: paper_random}"])


def test_urgency_channel_is_ignored():
    x = jnp.ones((2, 4, 5, 26), jnp.uint8)
    assert float(bc.prepare(x)[..., 25].sum()) == 0 and float(bc.prepare(x)[..., 24].sum()) == 40


# ---------------------------------------------------------------- co-adaptation
def _human(env, **kw):
    policy = bc.NETWORKS["mlp"]((16,))
    params = policy.init(jax.random.PRNGKey(0), jnp.zeros(env.obs_shape))
    return PolicyHuman(env=env, params=params, logits_fn=policy.logits, adapt=True, **kw)


@pytest.fixture(scope="module")
def played(cramped):
    """States [T, n] and human actions [n, T] of short episodes (robot stays, human samples)."""
    human = _human(cramped)

    @jax.jit
    def play(key):
        def one(key):
            def step(s, k):
                a_h = human.act(k, s)
                return cramped.step(s, jnp.int32(STAY), a_h)[0], (s, a_h)

            return jax.lax.scan(step, cramped.reset(key), jax.random.split(key, 24))[1]

        states, actions = jax.vmap(one)(jax.random.split(key, 6))
        return jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), states), actions

    return play(jax.random.PRNGKey(0))


@pytest.mark.slow
def test_adapting_human_follows_the_reward_and_the_kl_holds_it_back(cramped, played):
    """Reward every step on which the human interacted: policy gradient raises the
    probability of interacting; a strong KL weight keeps the policy nearer the clone.
    Without reward the clone is a fixed point: zero policy gradient, zero KL gradient."""
    import optax

    states, actions = played
    interact = (actions == INTERACT).astype(jnp.float32).T
    obs = jax.vmap(jax.vmap(cramped.observe_human))(states)
    human = _human(cramped, adapt_gamma=0.0)
    opt = optax.adam(3e-2)

    @jax.jit
    def learn(kl_weight, rewards):
        def step(carry, _):
            params, opt_state = carry
            grads, (pg, kl, _) = jax.grad(human.loss, has_aux=True)(params, obs, actions.T, rewards, kl_weight)
            updates, opt_state = opt.update(grads, opt_state, params)
            biggest = jnp.max(jnp.stack([jnp.abs(g).max() for g in jax.tree.leaves(grads)]))
            return (optax.apply_updates(params, updates), opt_state), (kl, biggest)

        (params, _), (kls, grads) = jax.lax.scan(step, (human.params, opt.init(human.params)), None, length=20)
        p = jax.nn.softmax(bc.NETWORKS["mlp"]((16,)).logits(params, obs))[..., INTERACT].mean()
        return p, kls[-1], kls[0] + grads[0]  # kls[0], grads[0]: at the clone

    _, _, at_clone = learn(jnp.float32(1.0), jnp.zeros_like(interact))
    assert float(at_clone) < 1e-6
    p_clone = float(jax.nn.softmax(bc.NETWORKS["mlp"]((16,)).logits(human.params, obs))[..., INTERACT].mean())
    (p_free, kl_free, _), (p_held, kl_held, _) = [tuple(map(float, learn(jnp.float32(w), interact))) for w in (0.0, 10.0)]
    assert p_free > p_clone + 0.1
    assert p_clone < p_held < p_free
    assert kl_held < kl_free


@pytest.mark.slow
def test_flipped_seat_puts_the_robot_in_agent_1(cramped):
    flipped = Overcooked("cramped_room", 400, robot_seat=1)
    s = jax.jit(cramped.reset)(jax.random.PRNGKey(0))
    base = cramped.base.get_obs(s)
    np.testing.assert_array_equal(flipped.observe(s), base["agent_1"])
    np.testing.assert_array_equal(flipped.observe_human(s), base["agent_0"])
    # The robot's action moves agent_1: robot 'right', human 'stay' from both seats.
    s0, _ = cramped.step(s, jnp.int32(2), jnp.int32(STAY))
    s1, _ = flipped.step(s, jnp.int32(2), jnp.int32(STAY))
    direct, _ = cramped.step_joint(s, jnp.int32(STAY), jnp.int32(2))  # agent_0 stays, agent_1 right
    np.testing.assert_array_equal(s1.agent_pos, direct.agent_pos)
    np.testing.assert_array_equal(s1.agent_dir_idx, direct.agent_dir_idx)
    assert not (np.asarray(s0.agent_dir_idx) == np.asarray(s1.agent_dir_idx)).all()


@pytest.mark.slow
@pytest.mark.parametrize("seat", [0, 1])
def test_observation_decodes_back_to_the_state(seat):
    """state_from_obs inverts observe (agents, orientations, inventories, map) along random
    play, which AvE's rollouts from observations rely on; from either seat."""
    env = Overcooked("cramped_room", 400, robot_seat=seat)

    @jax.jit
    def play(key):
        def step(s, k):
            a = jax.random.randint(k, (2,), 0, 6)
            s2 = env.step(s, a[0], a[1])[0]
            d = env.state_from_obs(env.observe(s2))
            same = jnp.stack([
                (d.agent_pos == s2.agent_pos).all(), (d.agent_dir_idx == s2.agent_dir_idx).all(),
                (d.agent_inv == s2.agent_inv).all(), (d.maze_map == s2.maze_map).all(),
                (env.observe(d) == env.observe(s2)).all()])
            return s2, (same, (s2.agent_inv != 1).any())

        return jax.lax.scan(step, env.reset(key), jax.random.split(key, 150))[1]

    same, holding = play(jax.random.PRNGKey(4))
    assert np.asarray(same).all(axis=0).tolist() == [True] * 5
    assert np.asarray(holding).any()  # the random play did pick things up
    futures = jax.jit(env.random_human_futures)(env.observe(env.reset(jax.random.PRNGKey(5))), jnp.zeros((3, 2), jnp.int32))
    assert futures.shape == (3, 4 * 5 * 26)


@pytest.mark.slow
def test_per_seed_humans_are_one_clone_per_training_seed(cramped):
    """human.per_seed: the clones' specs (cloning seed = human.seed + training seed), and each
    seed's training state holding its own clone's parameters."""
    from esr_cli.model.humans.registry import make_human

    spec = specs.load("experiments/cramped_room.yaml", "smoke", ["human.per_seed=true", "human.seed=10", "train.seeds=[3,7]"])
    clones = spec.human.clones(spec.train.seeds)
    assert [c.seed for c in clones] == [13, 17] and not any(c.per_seed for c in clones)
    assert spec.human.model_copy(update={"per_seed": False}).clones((3, 7)) == [spec.human.model_copy(update={"per_seed": False})]
    policy = bc.cloned_policy(spec.human)
    params = [policy.init(jax.random.PRNGKey(i), jnp.zeros(cramped.obs_shape)) for i in (13, 17)]
    human = make_human(spec.human, cramped, params, spec.train.seeds)
    assert human.has_state and not human.learns
    states = jax.vmap(human.init)(jax.random.split(jax.random.PRNGKey(0), 2), jnp.array([3, 7]))
    for i in range(2):
        for got, want in zip(jax.tree.leaves(jax.tree.map(lambda x: x[i], states.params)), jax.tree.leaves(params[i])):
            np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="2 humans for 3 seeds"):
        make_human(spec.human, cramped, params, (3, 7, 9))
    with pytest.raises(specs.SpecError, match="per_seed with human.adapt is not supported"):
        specs.load("experiments/cramped_room.yaml", "smoke", ["human.per_seed=true", "human.adapt=true"])


@pytest.mark.slow
def test_jaxmarl_import_banner_is_dropped_and_nothing_reaches_stdout():
    """jaxmarl announces its optional environments when imported; esr's stdout carries results,
    so that banner is dropped, and anything else printed from jaxmarl code goes to stderr."""
    import subprocess
    import sys

    code = ("from esr_cli.model.envs.overcooked import jaxmarl_env, quiet_jaxmarl\n"
            "jaxmarl_env('cramped_room', 400)\n"
            "with quiet_jaxmarl():\n"
            "    print('from jaxmarl')\n"
            "print('result')\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    assert proc.stdout == "result\n"
    assert "from jaxmarl" in proc.stderr.splitlines() and "ubmoduled" not in proc.stderr
