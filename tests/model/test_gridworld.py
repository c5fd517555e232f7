"""The gridworld's rules, pinned on hand-made states (docs/environments.md)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esr_cli.model.envs.gridworld import DOWN, LEFT, RIGHT, STAY, UP, GridState, Gridworld


def env(blocks=2, size=5, start="corner"):
    return Gridworld(size=size, num_blocks=blocks, start=start, episode_steps=50)


def state(human, blocks, goal, t=0):
    return GridState(
        human=jnp.array(human, jnp.int32),
        blocks=jnp.array(blocks, jnp.int32).reshape(-1, 2),
        goal=jnp.array(goal, jnp.int32),
        t=jnp.array(t, jnp.int32),
    )


def robot(cell_rc, direction, size=5):
    return jnp.array((cell_rc[0] * size + cell_rc[1]) * 5 + direction, jnp.int32)


NOOP = robot((4, 4), STAY)  # no block on (4, 4) in these states


def test_walls_stop_the_human():
    e = env()
    s = state([0, 0], [[3, 3], [4, 3]], [2, 2])
    for a in (LEFT, UP):
        nxt, r = e.step(s, NOOP, jnp.array(a))
        assert nxt.human.tolist() == [0, 0]
        assert float(r) == 0.0


def test_blocks_stop_the_human():
    e = env()
    s = state([0, 0], [[0, 1], [1, 0]], [4, 4])
    for a in (RIGHT, DOWN):
        nxt, _ = e.step(s, NOOP, jnp.array(a))
        assert nxt.human.tolist() == [0, 0]


def test_human_moves_in_each_direction():
    e = env()
    s = state([2, 2], [[0, 0], [4, 4]], [0, 4])
    expect = {LEFT: [2, 1], DOWN: [3, 2], RIGHT: [2, 3], UP: [1, 2], STAY: [2, 2]}
    for a, pos in expect.items():
        nxt, _ = e.step(s, NOOP, jnp.array(a))
        assert nxt.human.tolist() == pos
        assert int(nxt.t) == 1


def test_robot_pushes_a_block_one_step():
    e = env()
    s = state([0, 0], [[2, 2], [4, 4]], [0, 4])
    nxt, _ = e.step(s, robot((2, 2), UP), jnp.array(STAY))
    assert nxt.blocks.tolist() == [[1, 2], [4, 4]]


def test_robot_noop_on_an_empty_cell():
    e = env()
    s = state([0, 0], [[2, 2], [4, 4]], [0, 4])
    for d in range(5):
        nxt, _ = e.step(s, robot((3, 3), d), jnp.array(STAY))
        assert nxt.blocks.tolist() == [[2, 2], [4, 4]]


def test_blocks_stop_at_walls_and_other_blocks():
    e = env()
    s = state([0, 0], [[2, 4], [2, 3]], [0, 4])
    nxt, _ = e.step(s, robot((2, 4), RIGHT), jnp.array(STAY))  # wall
    assert nxt.blocks.tolist() == [[2, 4], [2, 3]]
    nxt, _ = e.step(s, robot((2, 4), LEFT), jnp.array(STAY))  # the other block
    assert nxt.blocks.tolist() == [[2, 4], [2, 3]]


def test_block_pushed_onto_the_human_freezes_the_episode():
    e = env()
    s = state([2, 2], [[2, 3], [4, 4]], [0, 0])
    nxt, _ = e.step(s, robot((2, 3), LEFT), jnp.array(STAY))
    assert nxt.blocks.tolist()[0] == [2, 2]
    assert bool(e.is_dead(nxt))
    # The human cannot move any more, and the robot cannot move blocks either.
    later, r = e.step(nxt, robot((4, 4), UP), jnp.array(UP))
    assert later.human.tolist() == [2, 2]
    assert later.blocks.tolist() == [[2, 2], [4, 4]]
    assert float(r) == 0.0


def test_human_moves_before_the_robot():
    e = env()
    # The human steps right onto (2, 3) first; the robot's push of (2, 4) left then lands the
    # block on the human. Had the robot moved first, the human would have been stopped instead.
    s = state([2, 2], [[2, 4], [0, 0]], [4, 4])
    nxt, _ = e.step(s, robot((2, 4), LEFT), jnp.array(RIGHT))
    assert nxt.human.tolist() == [2, 3]
    assert nxt.blocks.tolist()[0] == [2, 3]
    assert bool(e.is_dead(nxt))


def test_reward_counts_steps_on_the_goal():
    e = env()
    s = state([1, 2], [[4, 4], [4, 3]], [0, 2])
    s1, r1 = e.step(s, NOOP, jnp.array(UP))
    assert s1.human.tolist() == [0, 2] and float(r1) == 1.0
    # On the goal the human stays whatever it chooses, and keeps earning.
    s2, r2 = e.step(s1, NOOP, jnp.array(DOWN))
    assert s2.human.tolist() == [0, 2] and float(r2) == 1.0
    # And the robot can no longer move blocks.
    s3, _ = e.step(s2, robot((4, 4), UP), jnp.array(STAY))
    assert s3.blocks.tolist() == [[4, 4], [4, 3]]


@pytest.mark.slow
@pytest.mark.parametrize("start,blocks,size", [("corner", 2, 5), ("corner", 10, 5), ("corner_hard", 5, 5), ("center", 7, 5), ("random", 10, 5), ("random", 0, 3), ("corner", 7, 4)])
def test_reset_never_overlaps(start, blocks, size):
    e = env(blocks=blocks, size=size, start=start)
    states = jax.jit(jax.vmap(e.reset))(jax.random.split(jax.random.PRNGKey(0), 500))
    human, blk, goal = np.asarray(states.human), np.asarray(states.blocks), np.asarray(states.goal)
    for i in range(500):
        cells = [tuple(human[i])] + [tuple(b) for b in blk[i]]
        assert len(set(cells)) == len(cells), f"overlap in reset {i}: {cells}"
        assert tuple(goal[i]) not in cells, "goal under a block or on the human"
        assert (np.asarray(cells) >= 0).all() and (np.asarray(cells) < size).all()
    if start == "corner":
        corners = {(0, 0), (0, size - 1), (size - 1, 0), (size - 1, size - 1)}
        assert {tuple(h) for h in human} == corners  # every corner is used
        for i in range(20):  # the two blocks trap the human
            h = human[i]
            nbrs = {(h[0] + dr, h[1] + dc) for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0))}
            assert {tuple(b) for b in blk[i][:2]} == {n for n in nbrs if 0 <= n[0] < size and 0 <= n[1] < size}


def test_goal_is_uniform_over_free_cells():
    e = env(blocks=2, start="corner")
    states = jax.jit(jax.vmap(e.reset))(jax.random.split(jax.random.PRNGKey(1), 4000))
    goals = np.asarray(states.goal)
    corner00 = np.all(np.asarray(states.human) == [0, 0], axis=1)
    cells, counts = np.unique(goals[corner00], axis=0, return_counts=True)
    assert len(cells) == 22  # 25 cells minus the human and its two blocks
    expected = corner00.sum() / 22
    assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected))


def test_observation_planes():
    e = env()
    s = state([1, 1], [[3, 3], [0, 4]], [4, 0])
    obs = np.asarray(e.observe(s))
    assert obs.shape == (5, 5, 2) and obs.dtype == np.uint8
    assert obs[..., 0].sum() == 1 and obs[1, 1, 0] == 1
    assert obs[..., 1].sum() == 2 and obs[3, 3, 1] == 1 and obs[0, 4, 1] == 1


def test_action_planes():
    e = env()
    ar = np.asarray(e.robot_action_planes(robot((2, 3), DOWN)))
    assert ar.shape == (5, 5, 5) and ar.sum() == 1 and ar[2, 3, DOWN] == 1
    ah = np.asarray(e.human_action_planes(jnp.array(UP)))
    assert ah.shape == (5, 5, 5) and (ah[..., UP] == 1).all() and ah.sum() == 25


def test_render_is_an_rgb_picture():
    e = env()
    img = np.asarray(e.render(state([1, 1], [[3, 3], [1, 1]], [4, 0]), cell_px=8))
    assert img.shape == (40, 40, 3) and img.dtype == np.uint8
    assert len(np.unique(img.reshape(-1, 3), axis=0)) >= 4  # floor, lines, goal, block-on-human
