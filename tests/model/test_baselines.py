"""The baselines (docs/baselines.md) on small cases whose answer is known by hand or by numpy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esr_cli.common import specs
from esr_cli.model import replay, spec as spec_model
from esr_cli.model.envs.gridworld import DOWN, RIGHT, STAY, GridState, Gridworld
from esr_cli.model.humans.gridworld import NoisyGreedyHuman
from esr_cli.model.methods.ave import AvE
from esr_cli.model.methods.goal_inference import GoalInference
from esr_cli.model.methods.iq_learn import IQLearn
from esr_cli.model.train import make_trainer

STEPS = 800  # IQ-Learn updates in the fitted toy case
KEY = jax.random.PRNGKey(0)
MOVES = np.array([[0, -1], [1, 0], [0, 1], [-1, 0], [0, 0]])


def grid_state(human, blocks, goal):
    return GridState(
        human=jnp.array(human, jnp.int32),
        blocks=jnp.array(blocks, jnp.int32).reshape(-1, 2),
        goal=jnp.array(goal, jnp.int32),
        t=jnp.zeros((), jnp.int32),
    )


def np_walk(human, blocks, actions, size=5):
    """The human's cell after `actions`, the robot staying: plain numpy."""
    pos = np.array(human)
    block_set = {tuple(b) for b in blocks}
    dead = tuple(pos) in block_set
    for a in actions:
        target = np.clip(pos + MOVES[a], 0, size - 1)
        if not dead and tuple(target) not in block_set:
            pos = target
    return pos


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["fixed", "original"])
def test_ave_proxy_matches_numpy(variant):
    env = Gridworld(size=5, num_blocks=3, start="corner", episode_steps=50)
    human, blocks = [1, 1], [[1, 2], [0, 1], [3, 3]]
    obs = env.observe(grid_state(human, blocks, [4, 4]))
    spec = spec_model.AvEMethodSpec(kind="ave", num_rollouts=20, rollout_length=5, variant=variant)
    ave = AvE(env=env, spec=spec)
    key = jax.random.PRNGKey(3)
    actions = np.asarray(ave.rollout_actions(key, 1))[0]  # the same draws as state_reward's
    if variant == "original":
        assert np.mean(actions == STAY) > 0.9  # the published sampling makes most steps 'stay'
    ends = np.array([np_walk(human, blocks, seq) for seq in actions], dtype=np.float64)
    if variant == "fixed":
        want = np.log(ends.var(axis=0).mean() + 1e-3)
    else:
        block_coords = np.array(sorted(blocks)).reshape(-1)  # any order: one variance over all
        vectors = np.concatenate([ends, np.tile(block_coords, (len(ends), 1))], axis=1)
        want = np.log(vectors.var() + 1e-3)
    got = float(ave.state_reward(obs[None], key)[0])
    assert got == pytest.approx(want, rel=1e-5, abs=1e-5)


@pytest.mark.slow
def test_published_overcooked_ave_is_one_step_and_one_variance_over_the_human_observation():
    """variant: original on Overcooked, against JaxMARL stepped directly from the true state:
    each rollout is one uniform human action (the robot staying), the reward the log of one
    variance over every element of the rollouts' human observations."""
    from esr_cli.model.envs.overcooked import STAY as OC_STAY, Overcooked

    env = Overcooked("cramped_room", 400)
    spec = specs.load("experiments/cramped_room_ave.yaml", "smoke", ["method.variant=original"])
    ave = AvE.from_spec(spec, env, None)
    state = jax.jit(env.reset)(jax.random.PRNGKey(4))
    state, _ = jax.jit(env.step)(state, jnp.int32(OC_STAY), jnp.int32(1))  # not the start state
    key = jax.random.PRNGKey(5)
    actions = np.asarray(ave.rollout_actions(key, 1))[0]
    assert actions.shape == (spec.method.num_rollouts, 1) and set(actions[:, 0]) <= set(range(6))
    assert len(set(actions[:, 0])) > 1  # uniform over the six actions, not mostly 'stay'
    step = jax.jit(lambda a: env.observe_human(env.step(state, jnp.int32(OC_STAY), a)[0]))
    ends = np.stack([np.asarray(step(jnp.int32(a)), np.float64).reshape(-1) for a in actions[:, 0]])
    want = np.log(ends.var())
    got = float(jax.jit(ave.state_reward)(env.observe(state)[None], key)[0])
    assert got == pytest.approx(want, rel=1e-5)


def test_ave_proxy_is_lowest_for_a_trapped_human():
    env = Gridworld(size=5, num_blocks=2, start="corner", episode_steps=50)
    ave = AvE(env=env, spec=spec_model.AvEMethodSpec(kind="ave"))
    trapped = env.observe(grid_state([0, 0], [[0, 1], [1, 0]], [4, 4]))
    free = env.observe(grid_state([2, 2], [[0, 1], [1, 0]], [4, 4]))
    r = ave.state_reward(jnp.stack([trapped, free]), jax.random.PRNGKey(0))
    assert float(r[0]) == pytest.approx(np.log(1e-3), rel=1e-5)  # no variance at all
    assert float(r[1]) > 0.0


@pytest.mark.slow
def test_goal_belief_moves_toward_the_true_goal():
    env = Gridworld(size=5, num_blocks=2, start="corner", episode_steps=50)
    human_model = NoisyGreedyHuman(env=env, noise=0.2)
    gi = GoalInference(env=env, human=human_model)
    goal = [4, 4]
    s = grid_state([0, 0], [[0, 4], [4, 0]], goal)
    memory = gi.memory_init(env.observe(s))
    true_index = 4 * 5 + 4
    beliefs = [float(memory.belief[true_index])]
    prev_action = jnp.zeros((), jnp.int32)
    # A scripted human walking greedily to (4, 4): down, right, down, right, down, right.
    for action in [DOWN, RIGHT, DOWN, RIGHT, DOWN, RIGHT]:
        _, memory = gi.rule_step(memory, env.observe(s), prev_action, KEY)
        s = s._replace(human=jnp.clip(s.human + jnp.array(MOVES[action]), 0, 4))
        prev_action = jnp.array(action, jnp.int32)
        beliefs.append(float(memory.belief[true_index]))
    _, memory = gi.rule_step(memory, env.observe(s), prev_action, KEY)
    beliefs.append(float(memory.belief[true_index]))
    assert beliefs[-1] > 5 * beliefs[0]
    assert all(b1 >= b0 for b0, b1 in zip(beliefs, beliefs[1:]))
    # The path so far fits (3, 3), where the human now stands, as well as (4, 4): they tie.
    assert beliefs[-1] == pytest.approx(float(memory.belief.max()))
    assert beliefs[-1] == pytest.approx(float(memory.belief[3 * 5 + 3]))
    assert float(memory.belief.sum()) == pytest.approx(1.0, rel=1e-5)


def test_goal_inference_clears_the_way_sideways():
    env = Gridworld(size=5, num_blocks=2, start="corner", episode_steps=50)
    gi = GoalInference(env=env, human=NoisyGreedyHuman(env=env, noise=0.2))
    s = grid_state([0, 0], [[0, 1], [1, 0]], [4, 4])
    action = int(gi.clearing_action(env.observe(s), jnp.array([4, 4])))
    # Toward (4, 4) 'down' and 'right' tie; 'down' comes first, so the block on (1, 0) is in
    # the way. Pushed left it would leave the grid, so it is pushed right, onto (1, 1).
    assert action == (1 * 5 + 0) * 5 + RIGHT
    after, _ = env.step(s, jnp.array(action), jnp.array(STAY))
    moved, _ = env.step(after, jnp.array((0 * 5 + 0) * 5 + STAY), jnp.array(DOWN))
    assert moved.human.tolist() == [1, 0]


def test_goal_inference_does_nothing_when_the_way_is_clear():
    env = Gridworld(size=5, num_blocks=2, start="corner", episode_steps=50)
    gi = GoalInference(env=env, human=NoisyGreedyHuman(env=env, noise=0.2))
    s = grid_state([2, 2], [[0, 4], [4, 0]], [4, 4])
    action = int(gi.clearing_action(env.observe(s), jnp.array([4, 4])))
    after, _ = env.step(s, jnp.array(action), jnp.array(STAY))
    assert after.blocks.tolist() == s.blocks.tolist()


@pytest.mark.slow
def test_published_goal_inference_moves_weights_by_fixed_steps_as_computed_by_hand():
    """Du et al.'s rule on a 3 x 3 grid, one block at (0, 2), the human at (1, 1): the goal set is
    the 7 other cells, each starting at 1/7; alpha = 0.5, so a move shifts a weight by 1/14."""
    from fractions import Fraction as F

    env = Gridworld(size=3, num_blocks=1, start="corner", episode_steps=10)
    gi = GoalInference(env=env, human=NoisyGreedyHuman(env=env, noise=0.2), variant="original", step=0.5)
    blocks = [[0, 2]]
    path = [[1, 1], [1, 2], [1, 2], [2, 2]]  # right, stay (on (1, 2)), down
    memory = gi.memory_init(env.observe(grid_state(path[0], blocks, [2, 2])))
    assert int(memory.candidates.sum()) == 7
    for cell in path:
        _, memory = gi.rule_step(memory, env.observe(grid_state(cell, blocks, [2, 2])), jnp.int32(0), KEY)
    # Step 1, (1,1) -> (1,2): closer to (1,2) and (2,2): 1/7 + 1/14 = 3/14; the five others away:
    # 1/14; renormalised by 11/14: 3/11 and 1/11.
    # Step 2, staying on (1,2): its weight goes to 0; by 8/11: (2,2) 3/8, the five others 1/8.
    # Step 3, (1,2) -> (2,2): closer to (2,2), (2,0), (2,1): + 1/14; away from (0,0), (0,1), (1,0):
    # 1/8 - 1/14 = 3/56; (1,2) stays floored at 0.
    w = {(2, 2): F(3, 8) + F(1, 14), (2, 0): F(1, 8) + F(1, 14), (2, 1): F(1, 8) + F(1, 14),
         (0, 0): F(3, 56), (0, 1): F(3, 56), (1, 0): F(3, 56), (1, 2): F(0)}
    total = sum(w.values())
    expected = np.zeros(9)
    for (r, c), v in w.items():
        expected[r * 3 + c] = float(v / total)
    np.testing.assert_allclose(np.asarray(memory.belief), expected, atol=1e-6)


def test_published_goal_inference_floors_weights_at_zero_and_keeps_a_belief_nothing_explains():
    env = Gridworld(size=3, num_blocks=1, start="corner", episode_steps=10)
    gi = GoalInference(env=env, human=NoisyGreedyHuman(env=env, noise=0.2), variant="original", step=10.0)
    obs = lambda cell: env.observe(grid_state(cell, [[0, 2]], [2, 2]))  # noqa: E731
    memory = gi.memory_init(obs([1, 1]))
    _, memory = gi.rule_step(memory, obs([1, 1]), jnp.int32(0), KEY)
    _, memory = gi.rule_step(memory, obs([1, 2]), jnp.int32(0), KEY)
    # A step of 10/7 wipes every goal the move left: only (1,2) and (2,2) keep weight, equally.
    expected = np.zeros(9)
    expected[[5, 8]] = 0.5
    np.testing.assert_allclose(np.asarray(memory.belief), expected, atol=1e-6)
    # A goal at 0 comes back when approached (+ alpha / |G|): moving back to (1,1) approaches
    # (0,0), (0,1), (1,0), (2,0), (2,1) and leaves (1,2) and (2,2), floored at 0.
    _, memory = gi.rule_step(memory, obs([1, 1]), jnp.int32(0), KEY)
    expected = np.zeros(9)
    expected[[0, 1, 3, 6, 7]] = 0.2
    np.testing.assert_allclose(np.asarray(memory.belief), expected, atol=1e-6)
    # Standing still on the one goal with weight zeroes it: nothing is left, so the belief stays
    # as it was (the published code divides by zero there).
    only = jnp.zeros(9).at[8].set(1.0)
    after = gi.step_belief(only, memory.candidates, obs([2, 2]), obs([2, 2]))
    np.testing.assert_allclose(np.asarray(after), np.asarray(only))


@pytest.mark.slow
def test_published_goal_inference_helps_the_goal_mass_and_breaks_ties_at_random():
    env = Gridworld(size=5, num_blocks=2, start="corner", episode_steps=50)
    gi = GoalInference(env=env, human=NoisyGreedyHuman(env=env, noise=0.2), variant="original")
    obs = env.observe(grid_state([0, 0], [[0, 1], [1, 0]], [4, 4]))
    # (0,4) is reached by moving right, through the block on (0,1); (4,0) by moving down, through
    # the block on (1,0). The published push order is left, down, right, up, never onto the human.
    push_right_block = (0 * 5 + 1) * 5 + DOWN  # left would land on the human
    push_down_block = (1 * 5 + 0) * 5 + DOWN  # left would leave the grid
    belief = jnp.zeros(25).at[4].set(0.6).at[20].set(0.4)
    assert int(gi.expected_help(obs, belief, KEY)) == push_right_block
    belief = jnp.zeros(25).at[4].set(0.5).at[20].set(0.5)
    chosen = {int(gi.expected_help(obs, belief, k)) for k in jax.random.split(KEY, 40)}
    assert chosen == {push_right_block, push_down_block}
    # esr's exact variant pushes sideways first: the block on (1,0) goes right, onto (1,1).
    exact = GoalInference(env=env, human=NoisyGreedyHuman(env=env, noise=0.2))
    assert int(exact.clearing_action(obs, jnp.array([4, 0]))) == (1 * 5 + 0) * 5 + RIGHT


@pytest.mark.slow
def test_iq_learn_reward_ranks_the_humans_actions_above_random_ones():
    """Fit on a toy gridworld whose goal the model sees and whose human is plainly greedy; the
    recovered reward must prefer the human's actual actions on held-out transitions."""
    raw = specs.load_raw("experiments/grid_2_iq_learn.yaml")
    spec = specs.resolve(
        raw,
        "smoke",
        [
            "env.goal_visible=true",
            "env.start=random",
            "human.noise=0.0",
            "train.num_envs=64",
            "network.conv_channels=[8]",
            "network.hidden=32",
            "method.lr=3e-3",
        ],
    )
    trainer = make_trainer(spec)
    method = trainer.method
    assert isinstance(method, IQLearn)
    key = jax.random.PRNGKey(0)
    lstate = trainer.learner.init(key, trainer.obs_example())
    roll = jax.jit(lambda k: trainer.rollout(lstate, k, 64, "random"))(key)
    steps = trainer.env.episode_steps
    buf = replay.add(replay.init(64, steps, trainer.env.obs_shape, jnp.uint8), roll.episodes)
    train_buf = buf._replace(count=jnp.array(48))  # episodes 0..47 train, 48..63 held out
    held = jax.tree.map(lambda x: x[48:], roll.episodes)
    state = method.init(key, trainer.obs_example())

    @jax.jit
    def fit(state, key):
        def body(state, key):
            batch = replay.sample(train_buf, key, 64, 0.9)
            return method.update(state, batch, key)[0], None

        return jax.lax.scan(body, state, jax.random.split(key, STEPS))[0]

    state = fit(state, key)
    n = held.robot_action.size
    batch = replay.Batch(
        obs=held.obs[:, :-1].reshape(n, *trainer.env.obs_shape),
        next_obs=held.obs[:, 1:].reshape(n, *trainer.env.obs_shape),
        future_obs=held.obs[:, 1:].reshape(n, *trainer.env.obs_shape),
        robot_action=held.robot_action.reshape(n),
        human_action=held.human_action.reshape(n),
        reward=held.reward.reshape(n),
        done=jnp.tile(jnp.arange(steps) == steps - 1, held.obs.shape[0]).astype(jnp.float32),
        offset=jnp.ones(n, jnp.int32),
    )
    # Only moving humans: a human on its goal or blocked is indifferent between actions.
    moving = np.asarray(jnp.any(batch.obs[..., 0] != batch.next_obs[..., 0], axis=(1, 2)))

    @jax.jit
    def rewards(state, batch):
        taken = method.reward(state, batch, key)
        every = [
            method.reward(state, batch._replace(human_action=jnp.full_like(batch.human_action, a)), key)
            for a in range(trainer.env.num_human_actions)
        ]
        return taken, jnp.stack(every)

    taken, every = (np.asarray(x) for x in rewards(state, batch))
    taken, every = taken[moving], every[:, moving]
    # The taken action beats the average action, on average and in most transitions.
    assert taken.mean() > every.mean() + 0.1
    assert np.mean(taken > every.mean(axis=0)) > 0.75, np.mean(taken > every.mean(axis=0))
    # The critic phase's table (Q_H of every stored state once) gives the per-batch values,
    # the episode's last step included (done: no value of the state after it).
    table = jax.jit(method.reward_table)(state, buf)
    idx = replay.Index(episode=jnp.array([0, 5, 63, 63]), t=jnp.array([0, 7, 3, steps - 1]), future=jnp.zeros(4, jnp.int32))
    direct = method.reward(state, replay.gather(buf, idx), key)
    np.testing.assert_allclose(method.reward_from_table(table, idx), direct, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_oracle_reward_is_the_environments():
    raw = specs.load_raw("experiments/grid_2_oracle.yaml")
    spec = specs.resolve(raw, "smoke", ["env.start=random", "train.num_envs=32"])
    trainer = make_trainer(spec)
    key = jax.random.PRNGKey(1)
    lstate = trainer.learner.init(key, trainer.obs_example())
    roll = jax.jit(lambda k: trainer.rollout(lstate, k, 32, "random"))(key)
    steps = trainer.env.episode_steps
    buf = replay.add(replay.init(32, steps, trainer.env.obs_shape, jnp.uint8), roll.episodes)
    batch = replay.sample(buf, key, 512, 0.9)
    got = np.asarray(trainer.method.reward((), batch, key))
    # The goal is in the observation (plane 2); the reward is 1 exactly when the human stands
    # on it after the step (a human on its goal is frozen, so the robot cannot move it off).
    on_goal = np.asarray(jnp.any((batch.next_obs[..., 0] == 1) & (batch.obs[..., 2] == 1), axis=(1, 2)))
    assert got.tolist() == on_goal.astype(np.float32).tolist()
    assert 0 < got.sum() < len(got)


def test_oracle_needs_the_goal_in_view():
    raw = specs.load_raw("experiments/grid_2_oracle.yaml")
    with pytest.raises(specs.SpecError, match="goal_visible"):
        specs.resolve(raw, "smoke", ["env.goal_visible=false"])


def test_gridworld_only_baselines_are_refused_elsewhere():
    for kind in ("oracle", "goal_inference"):
        raw = specs.load_raw("experiments/coord_ring_random.yaml")
        with pytest.raises(specs.SpecError, match="gridworld"):
            specs.resolve(raw, "smoke", [f"method.kind={kind}"])
