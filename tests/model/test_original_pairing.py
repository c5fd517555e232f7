"""The published Overcooked code's two input conventions as ESR options (docs/choices.md):
`pairing: original` (o_{t+1} with a_t) and `action_input: append` (each action's one-hot once)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esr_cli.common import specs
from esr_cli.model import replay
from esr_cli.model.train import make_trainer


def _buffer(episodes=3, steps=4):
    """obs[e, t] = 10 e + t, so every lookup says which (episode, step) it read."""
    obs = (10 * jnp.arange(episodes)[:, None] + jnp.arange(steps + 1)[None, :]).astype(jnp.int32)[..., None]
    actions = (100 * jnp.arange(episodes)[:, None] + jnp.arange(steps)[None, :]).astype(jnp.int32)
    buf = replay.init(episodes, steps, (1,), jnp.int32)
    return replay.add(buf, replay.Episodes(obs=obs, robot_action=actions, human_action=actions + 1000,
                                           reward=jnp.zeros((episodes, steps))))


def test_original_pairing_reads_the_post_step_observation_with_the_actions_before_it():
    buf = _buffer()
    idx = replay.Index(episode=jnp.array([0, 1, 2, 2]), t=jnp.array([0, 2, 3, 1]), future=jnp.array([2, 4, 4, 3]))
    aligned, original = replay.gather(buf, idx), replay.gather(replay.post_step_view(buf), idx)
    # Aligned: o_t, o_{t+1}, o_future with a_t.
    assert np.asarray(aligned.obs)[:, 0].tolist() == [0, 12, 23, 21]
    # Original: o_{t+1} with the same a_t; next o_{t+2}; future one step later; o_T repeats at the end.
    assert np.asarray(original.obs)[:, 0].tolist() == [1, 13, 24, 22]
    assert np.asarray(original.next_obs)[:, 0].tolist() == [2, 14, 24, 23]
    assert np.asarray(original.future_obs)[:, 0].tolist() == [3, 14, 24, 24]
    np.testing.assert_array_equal(original.robot_action, aligned.robot_action)
    np.testing.assert_array_equal(original.human_action, aligned.human_action)
    np.testing.assert_array_equal(original.done, aligned.done)  # episode ends are where they were


@pytest.mark.slow
def test_original_pairing_trains_and_leaves_the_stored_buffer_as_played():
    """One epoch of the real runner under `pairing: original` (validation allows it only on
    Overcooked; the runner itself is environment-agnostic, so a gridworld smoke spec is
    switched to it here to keep the test's compile small)."""
    spec = specs.load("experiments/grid_2.yaml", "smoke")
    spec = spec.model_copy(update={"method": spec.method.model_copy(update={"pairing": "original"})})
    trainer = make_trainer(spec)
    assert trainer.post_step_pairing
    state = trainer.init(0)
    new_state, metrics = jax.jit(trainer.epoch)(state)
    assert all(np.isfinite(float(v)) for k, v in metrics.items() if k in ("repr_loss", "critic_loss", "mi_estimate"))
    buf = new_state.buffer
    first = np.asarray(buf.obs[0])
    # The stored episode is the one played: it starts at a reset observation (a corner start:
    # the human in a corner), not one step later.
    human_cell = np.argwhere(first[0, ..., 0] == 1)[0]
    assert tuple(human_cell) in {(0, 0), (0, 4), (4, 0), (4, 4)}


@pytest.mark.slow
def test_append_puts_each_action_once_and_broadcast_everywhere():
    from esr_cli.model.envs.overcooked import Overcooked
    from esr_cli.model.methods.esr import ESR

    env = Overcooked("cramped_room", 400)
    obs = jax.jit(env.observe)(jax.jit(env.reset)(jax.random.PRNGKey(0)))
    obs2 = jnp.stack([obs, obs])
    ar, ah = jnp.array([1, 5], jnp.int32), jnp.array([4, 0], jnp.int32)
    inputs = {}
    for mode in ("append", "broadcast"):
        spec = specs.load("experiments/cramped_room.yaml", "smoke", [f"method.action_input={mode}"])
        inputs[mode] = np.asarray(ESR(env=env, spec=spec.method, network_spec=spec.network)._phi_inputs(obs2, ar, ah))
    c = obs.shape[-1]
    app, bc = inputs["append"], inputs["broadcast"]
    assert app.shape == bc.shape == (4, 4, 5, c + 12)
    np.testing.assert_array_equal(app[..., :c], bc[..., :c])  # the observation is untouched
    # Rows 0-1 are phi'(s, aR) (no human action), rows 2-3 phi(s, aR, aH).
    for row, (r, h, with_human) in enumerate([(1, 4, False), (5, 0, False), (1, 4, True), (5, 0, True)]):
        robot, human = app[row, ..., c : c + 6], app[row, ..., c + 6 :]
        assert robot.sum() == 1 and robot[0, 0, r] == 1
        assert human.sum() == (1 if with_human else 0) and (not with_human or human[0, 0, h] == 1)
        assert bc[row, ..., c + r].sum() == 20  # broadcast: once per cell of the 4 x 5 grid


@pytest.mark.parametrize("field,value,message", [
    ("method.pairing", "original", "pairing=original is the published Overcooked code's pairing"),
    ("method.action_input", "append", "action_input=append feeds the one-hot once"),
])
def test_original_options_are_refused_where_they_do_not_apply(field, value, message):
    with pytest.raises(specs.SpecError, match=message):
        specs.load("experiments/grid_2.yaml", "smoke", [f"{field}={value}"])
    spec = specs.load("experiments/cramped_room.yaml", "smoke", [f"{field}={value}"])  # Overcooked, MLP: fine
    assert getattr(spec.method, field.split(".")[1]) == value
