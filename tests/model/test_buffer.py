"""The episode buffer: wrap-around, episode boundaries, and the geometric future offsets."""

import jax
import jax.numpy as jnp
import numpy as np

from esr_cli.model import replay

T = 10


def episodes(first_id, n):
    """n episodes whose observation at step t encodes (episode id, t) as [id, t]."""
    ids = jnp.arange(first_id, first_id + n)
    obs = jnp.stack(jnp.broadcast_arrays(ids[:, None], jnp.arange(T + 1)[None, :]), axis=-1).astype(jnp.int32)
    steps = jnp.broadcast_to(jnp.arange(T), (n, T))
    return replay.Episodes(obs=obs, robot_action=steps + 100 * ids[:, None], human_action=steps, reward=steps.astype(jnp.float32))


def test_add_wraps_around_by_episode():
    buf = replay.init(5, T, (2,), jnp.int32)
    buf = replay.add(buf, episodes(0, 3))
    assert int(buf.count) == 3 and int(buf.ptr) == 3
    buf = replay.add(buf, episodes(3, 3))  # slots 3, 4, then 0
    assert int(buf.count) == 5 and int(buf.ptr) == 1
    assert np.asarray(buf.obs[:, 0, 0]).tolist() == [5, 1, 2, 3, 4]


def test_samples_stay_inside_their_episode():
    buf = replay.add(replay.add(replay.init(8, T, (2,), jnp.int32), episodes(0, 8)), episodes(8, 3))
    b = jax.jit(lambda k: replay.sample(buf, k, 4096, 0.9))(jax.random.PRNGKey(0))
    ep, t = np.asarray(b.obs[:, 0]), np.asarray(b.obs[:, 1])
    assert set(np.unique(ep)) <= set(range(3, 11))  # episodes 0..2 were overwritten
    np.testing.assert_array_equal(np.asarray(b.next_obs[:, 0]), ep)
    np.testing.assert_array_equal(np.asarray(b.next_obs[:, 1]), t + 1)
    np.testing.assert_array_equal(np.asarray(b.future_obs[:, 0]), ep)
    ft = np.asarray(b.future_obs[:, 1])
    assert (ft > t).all() and (ft <= T).all()
    np.testing.assert_array_equal(ft - t, np.asarray(b.offset))
    np.testing.assert_array_equal(np.asarray(b.done), (t == T - 1).astype(np.float32))
    # actions and rewards belong to the sampled step of the sampled episode
    np.testing.assert_array_equal(np.asarray(b.robot_action), t + 100 * ep)
    np.testing.assert_array_equal(np.asarray(b.reward), t)


def test_geometric_offsets_follow_the_law():
    gamma = 0.9
    k = np.asarray(replay.geometric_offsets(jax.random.PRNGKey(1), (200_000,), gamma))
    assert k.min() == 1
    for j in range(1, 8):
        expected = (1 - gamma) * gamma ** (j - 1)
        assert abs((k == j).mean() - expected) < 4 * np.sqrt(expected / 200_000) + 1e-3
    assert abs(k.mean() - 1 / (1 - gamma)) < 0.1


def test_future_offsets_are_clipped_geometric():
    """P(offset = k | t) = (1 - g) g^(k-1) for k < T - t, and the tail mass sits on T - t."""
    gamma = 0.8
    buf = replay.add(replay.init(4, T, (2,), jnp.int32), episodes(0, 4))
    b = jax.jit(lambda k: replay.sample(buf, k, 200_000, gamma))(jax.random.PRNGKey(2))
    t, off = np.asarray(b.obs[:, 1]), np.asarray(b.offset)
    sel = off[t == 6]  # at most 4 steps to the end
    for j in range(1, 4):
        assert abs((sel == j).mean() - (1 - gamma) * gamma ** (j - 1)) < 0.01
    assert abs((sel == 4).mean() - gamma**3) < 0.01


def test_zero_gamma_means_the_next_state():
    buf = replay.add(replay.init(4, T, (2,), jnp.int32), episodes(0, 4))
    b = replay.sample(buf, jax.random.PRNGKey(3), 512, 0.0)
    assert (np.asarray(b.offset) == 1).all()
