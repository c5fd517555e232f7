"""The noisy-greedy human (docs/environments.md)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esr_cli.model.envs.gridworld import DOWN, LEFT, RIGHT, STAY, UP, GridState, Gridworld
from esr_cli.model.humans.gridworld import NoisyGreedyHuman


def setup(human, blocks, goal, noise=0.0):
    e = Gridworld(size=5, num_blocks=len(blocks), start="corner", episode_steps=50)
    s = GridState(jnp.array(human), jnp.array(blocks).reshape(-1, 2), jnp.array(goal), jnp.array(0))
    return NoisyGreedyHuman(env=e, noise=noise), s


def test_greedy_moves_toward_the_goal():
    h, s = setup([2, 2], [[0, 0], [4, 4]], [2, 4])
    assert int(h.greedy_action(s)) == RIGHT
    h, s = setup([2, 2], [[0, 0], [4, 4]], [0, 2])
    assert int(h.greedy_action(s)) == UP
    h, s = setup([2, 2], [[0, 0], [4, 4]], [2, 0])
    assert int(h.greedy_action(s)) == LEFT


def test_blocked_human_waits():
    # The only improving moves are blocked: stay (counted 0.1 closer) wins over sideways moves.
    h, s = setup([0, 0], [[0, 1], [1, 0]], [4, 4])
    assert int(h.greedy_action(s)) == STAY


def test_tie_breaks_to_the_first_action():
    # Goal diagonal: down and right are equally good; argmin takes the first (down = 1).
    h, s = setup([2, 2], [[0, 0], [4, 4]], [3, 3])
    assert int(h.greedy_action(s)) == DOWN


@pytest.mark.slow
def test_noise_frequencies():
    h, s = setup([2, 2], [[0, 0], [4, 4]], [2, 4], noise=0.2)
    actions = np.asarray(jax.vmap(lambda k: h.act(k, s))(jax.random.split(jax.random.PRNGKey(0), 20000)))
    freq = np.bincount(actions, minlength=5) / len(actions)
    expected = np.asarray(h.action_probs(s))
    np.testing.assert_allclose(expected, [0.04, 0.04, 0.84, 0.04, 0.04], atol=1e-6)
    np.testing.assert_allclose(freq, expected, atol=0.01)


@pytest.mark.slow
def test_noise_zero_is_deterministic_and_one_is_uniform():
    h, s = setup([2, 2], [[0, 0], [4, 4]], [2, 4], noise=0.0)
    keys = jax.random.split(jax.random.PRNGKey(3), 500)
    assert set(np.asarray(jax.vmap(lambda k: h.act(k, s))(keys)).tolist()) == {RIGHT}
    h, s = setup([2, 2], [[0, 0], [4, 4]], [2, 4], noise=1.0)
    freq = np.bincount(np.asarray(jax.vmap(lambda k: h.act(k, s))(jax.random.split(jax.random.PRNGKey(4), 20000))), minlength=5) / 20000
    np.testing.assert_allclose(freq, 0.2, atol=0.015)
