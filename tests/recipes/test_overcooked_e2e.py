"""Overcooked end to end on a small slice of the human data: the data and BC-human artifacts
(built once, then cache hits), a smoke training run that depends on the human by key, a
co-adapting human inside the runner, spec errors and the MLP network."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from play_script import Scripted
from rich.console import Console

from esr_cli.common import specs
from esr_cli.model import spec as spec_model
from esr_cli.model.humans import overcooked_data as od
from esr_cli.model.networks import MLP, conv_net, orthogonal
from esr_cli.recipes import human_runs, runs, stored_humans
from esr_cli.storage.artifacts import ensure
from esr_cli.storage.store import Store, StoreError

ROWS = 150  # rows per split: enough to exercise every step, small enough to be quick
SMALL_HUMAN = ["human.epochs=2", "human.selfplay_episodes=2"]


@pytest.fixture(scope="module")
def small_data():
    """Restrict the human data to its first ROWS rows per split for this module."""
    mp = pytest.MonkeyPatch()
    full = od.load_rows
    mp.setattr(od, "load_rows", lambda layout, split: full(layout, split).iloc[:ROWS].reset_index(drop=True))
    yield
    mp.undo()


def _evaluate(path, store, episodes, console, partner="training", seat=None):
    """(evaluation dir, its summary, cache hit) of `esr eval`'s recipe."""
    built = ensure(runs.eval_recipe(path, store, episodes, console, partner, seat), store)
    return built.path, built.summary(), built.cached


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return Store(tmp_path_factory.mktemp("oc-store"))


@pytest.fixture(scope="module")
def console():
    return Console(stderr=True)


@pytest.fixture(scope="module")
def random_smoke(small_data, store, console):
    """A smoke run of the Random robot with a co-adapting BC human (one compile for both)."""
    spec = specs.load("experiments/coord_ring_random.yaml", "smoke", SMALL_HUMAN + ["human.adapt=true", "human.adapt_lr=0.01"])
    path, cached = ensure(runs.run_recipe(spec, console), store)
    return spec, path, cached


@pytest.mark.slow
def test_human_and_data_artifacts(random_smoke, store, console):
    spec, _, _ = random_smoke
    key, components = human_runs.human_key(spec.human, "coord_ring")
    path = store.lookup(human_runs.HUMAN_KIND, key)
    assert path is not None
    m = json.loads((path / "manifest.json").read_text())
    s = m["summary"]
    for split in ("train", "test"):
        assert 0.0 <= s[split]["accuracy"] <= 1.0 and 0.0 <= s[split]["non_stay_accuracy"] <= 1.0
        assert s[split]["samples"] == 2 * ROWS  # both players' views
    assert s["selfplay_return"]["episodes"] == 2 and s["selfplay_return"]["mean"] >= 0
    data_key = components["dependencies"][human_runs.DATA_KIND]
    data_path = store.lookup(human_runs.DATA_KIND, data_key)
    dm = json.loads((data_path / "manifest.json").read_text())
    assert dm["summary"]["replay_check"]["rate"] == 1.0 and dm["summary"]["replay_check"]["checked"] == ROWS
    assert dm["key_components"]["data"]["sha256"] == od.checksums()
    data = human_runs.load_data(data_path)
    assert data["obs"].shape == (4 * ROWS, 5, 5, 26) and set(np.unique(data["player"])) == {0, 1}
    assert not store.verify(path) and not store.verify(data_path)
    # Built once: asking again is a cache hit for both.
    assert ensure(human_runs.human_recipe(spec.human, "coord_ring", console), store) == (path, True)
    assert ensure(human_runs.data_recipe("coord_ring", console), store) == (data_path, True)
    # The stored parameters load back into the policy the manifest describes.
    params = stored_humans.human_params(spec.human, "coord_ring", store)
    logits = MLP(hidden=(64, 64), out=6, out_scale=0.01).apply(params, jnp.zeros((1, 5, 5, 26)))
    assert logits.shape == (1, 6)


def test_run_depends_on_the_human_by_key_and_repeats_as_a_cache_hit(random_smoke, store, console):
    spec, path, cached = random_smoke
    assert not cached
    m = json.loads((path / "manifest.json").read_text())
    human_key, _ = human_runs.human_key(spec.human, "coord_ring")
    assert m["key_components"]["dependencies"] == {"humans": human_key}
    assert m["env"] == "overcooked" and m["summary"]["epochs"] == 2
    assert ensure(runs.run_recipe(spec, console), store) == (path, True)
    # Another human (different cloning settings) is another dependency, hence another run.
    other = specs.load("experiments/coord_ring_random.yaml", "smoke", SMALL_HUMAN + ["human.stay_weight=0.2"])
    assert runs.run_key(other)[0] != runs.run_key(spec)[0]


def test_a_missing_human_is_a_clear_error(small_data, tmp_path):
    spec = specs.load("experiments/coord_ring_random.yaml", "smoke", SMALL_HUMAN)
    with pytest.raises(StoreError, match="not built"):
        stored_humans.human_params(spec.human, "coord_ring", Store(tmp_path))
    with pytest.raises(StoreError, match="needs the store"):
        stored_humans.human_params(spec.human, "coord_ring", None)


def test_co_adapting_human_learns_inside_the_runner(random_smoke, store):
    from esr_cli.recipes.runs import build_trainer
    from esr_cli.runner import loop

    spec, path, _ = random_smoke
    trainer = build_trainer(spec, store)
    assert trainer.human_learns and "human_kl_to_bc" in trainer.metric_names
    state = loop.final_state(trainer, path)  # the human's state is checkpointed with the rest
    clone = stored_humans.human_params(spec.human, "coord_ring", store)
    moved = max(float(np.abs(np.asarray(a)[0] - b).max()) for a, b in zip(jax.tree.leaves(state.human.params), jax.tree.leaves(clone)))
    assert moved > 0
    rows = loop.read_rows(path)
    assert rows[0]["human_kl_to_bc"][0] == pytest.approx(0.0, abs=1e-6)  # the first update starts at the clone
    # (whether it moves further depends on soups delivered in two smoke epochs; the unit tests
    # in test_overcooked.py check the direction of learning)
    assert rows[-1]["human_kl_to_bc"][0] >= 0 and rows[-1]["human_entropy"][0] > 0


@pytest.mark.slow
def test_esr_takes_overcooked_batches():
    """ESR's input construction (observation + broadcast action planes) on Overcooked, MLP nets."""
    from esr_cli.model.envs.overcooked import Overcooked
    from esr_cli.model.methods.esr import ESR
    from esr_cli.model.replay import Batch

    spec = specs.load("experiments/cramped_room.yaml", "smoke")
    env = Overcooked("cramped_room", 400)
    esr = ESR(env=env, spec=spec.method, network_spec=spec.network)
    obs = jax.jit(env.observe)(jax.jit(env.reset)(jax.random.PRNGKey(0)))
    b = 8
    grid = jnp.broadcast_to(obs, (b,) + obs.shape)
    a = jnp.arange(b, dtype=jnp.int32) % 6
    batch = Batch(obs=grid, next_obs=grid, future_obs=grid, robot_action=a, human_action=a[::-1],
                  reward=jnp.zeros(b), done=jnp.zeros(b), offset=jnp.ones(b, jnp.int32))
    state = esr.init(jax.random.PRNGKey(1), obs)
    assert state.params["phi"]["params"]["Dense_0"]["kernel"].shape == (4 * 5 * (26 + 6 + 6), 64)
    state, metrics = jax.jit(esr.update)(state, batch, jax.random.PRNGKey(2))
    reward = jax.jit(esr.reward)(state, batch, jax.random.PRNGKey(3))
    assert reward.shape == (b,) and np.isfinite(np.asarray(reward)).all() and np.isfinite(float(metrics["repr_loss"]))


def test_overcooked_spec_errors():
    base = {"name": "x", "env": {"kind": "overcooked", "layout": "coord_ring"}, "human": {"kind": "bc"},
            "method": {"kind": "random"}, "learner": {"buffer_size": 40000}}
    cases = [
        ({"env": {"kind": "overcooked", "layout": "kitchen"}}, "env.layout"),
        ({"human": {"kind": "bc", "layout": "cramped_room"}}, "differs from env.layout"),
        ({"human": {"kind": "noisy_greedy"}}, "needs env.kind: gridworld"),
        ({"human": {"kind": "bc", "stay_weight": 0}}, "human.stay_weight"),
        ({"human": {"kind": "bc", "hidden": []}}, "human.hidden"),
        ({"network": {"kind": "transformer"}}, "network.kind"),
        ({"learner": {"buffer_size": 1000}}, "cannot hold one epoch"),
    ]
    for change, expected in cases:
        with pytest.raises(specs.SpecError) as e:
            specs.validate({**base, **change}, "f.yaml")
        assert expected in str(e.value) and "\n" not in str(e.value)
    grid = {"name": "g", "env": {"kind": "gridworld"}, "human": {"kind": "bc"}, "method": {"kind": "random"}}
    with pytest.raises(specs.SpecError, match="needs env.kind: overcooked"):
        specs.validate(grid, "g.yaml")


def test_all_overcooked_specs_load():
    for layout in ("cramped_room", "coord_ring", "asymm_advantages", "forced_coord", "counter_circuit"):
        for suffix in ("", "_random", "_ave"):
            for budget in ("paper", "quick", "smoke"):
                s = specs.load(f"experiments/{layout}{suffix}.yaml", budget)
                assert s.env.layout == layout and s.network.kind == "mlp"
                # the paper's layouts play with the paper's human (PPO on cramped room), the
                # others and every smoke budget with esr's MLP clone
                ppo = layout == "cramped_room" and budget != "smoke"
                assert s.human.kind == ("ppo" if ppo else "bc")
    paper = specs.load("experiments/cramped_room.yaml")
    assert (paper.learner.lr, paper.method.repr_lr, paper.learner.tau, paper.learner.gamma) == (1e-5, 3e-5, 1e-5, 0.8)
    assert (paper.learner.updates_per_epoch, paper.method.repr_updates_per_epoch, paper.learner.dual_updates_per_epoch) == (30, 100, 100)
    assert paper.learner.buffer_size == 200_000 and paper.learner.target_entropy == 0.9 and len(paper.train.seeds) == 15


@pytest.mark.slow
def test_mlp_network_flattens_the_grid():
    net_spec = spec_model.NetworkSpec(kind="mlp", mlp_layers=(8, 8))
    net = conv_net(net_spec, 3)
    x = jnp.ones((2, 4, 5, 7))
    params = net.init(jax.random.PRNGKey(0), x)
    assert net.apply(params, x).shape == (2, 3)
    assert params["params"]["Dense_0"]["kernel"].shape == (4 * 5 * 7, 8)
    w = np.asarray(params["params"]["Dense_1"]["kernel"])
    np.testing.assert_allclose(w.T @ w, 2.0 * np.eye(8), atol=1e-5)  # orthogonal, gain sqrt(2)
    wide = np.asarray(orthogonal(1.0)(jax.random.PRNGKey(1), (6, 40)))
    np.testing.assert_allclose(wide @ wide.T, np.eye(6), atol=1e-5)
    # No QR decomposition (a LAPACK call): several in one seed-vmapped program deadlock XLA on CPU.
    jaxpr = str(jax.make_jaxpr(lambda k: net.init(k, x))(jax.random.PRNGKey(0)))
    assert "qr[" not in jaxpr and "householder" not in jaxpr  # flax's orthogonal shows "qr["


@pytest.mark.slow
def test_proxy_human_is_cloned_from_the_held_out_split(random_smoke, store, console):
    spec, path, _ = random_smoke
    proxy = spec.human.proxy()
    assert proxy.split == "test" and not proxy.adapt
    # The training human's key has no split component (keys made before the field stay valid).
    assert "split" not in spec.human.cloning_part("coord_ring") and proxy.cloning_part("coord_ring")["split"] == "test"
    proxy_path, _ = ensure(human_runs.human_recipe(proxy, "coord_ring", console), store)
    assert proxy_path != store.lookup(human_runs.HUMAN_KIND, human_runs.human_key(spec.human, "coord_ring")[0])
    s = json.loads((proxy_path / "manifest.json").read_text())["summary"]
    assert s["split"] == "test" and s["train"]["samples"] == s["test"]["samples"] == 2 * ROWS
    # A run whose human adapted carries that human in its state: no proxy evaluation.
    with pytest.raises(StoreError, match="adapted during training"):
        _evaluate(path, store, 2, console, "proxy")


@pytest.fixture(scope="module")
def per_seed_run(small_data, store, console):
    """A smoke Random run whose two seeds play with their own clones (one compile serves the
    per-seed, proxy and flipped-seat tests)."""
    spec = specs.load("experiments/coord_ring_random.yaml", "smoke", SMALL_HUMAN + ["human.per_seed=true", "train.seeds=2"])
    path, _ = ensure(runs.run_recipe(spec, console), store)
    return spec, path


@pytest.mark.slow
def test_a_run_with_per_seed_humans(per_seed_run, store):
    """Two seeds, two clones: both built as artifacts, both in the run's key, each seed playing
    with its own (the first clone is the module's usual human: cloning seed 0)."""
    from esr_cli.recipes.runs import build_trainer
    from esr_cli.runner import loop

    spec, path = per_seed_run
    keys = [human_runs.human_key(h, "coord_ring")[0] for h in spec.human.clones(spec.train.seeds)]
    assert len(set(keys)) == 2 and all(store.lookup(human_runs.HUMAN_KIND, k) for k in keys)
    m = json.loads((path / "manifest.json").read_text())
    assert m["key_components"]["dependencies"] == {"humans": keys}
    trainer = build_trainer(spec, store)
    state = loop.final_state(trainer, path)
    for i, clone in enumerate(spec.human.clones(spec.train.seeds)):
        want = stored_humans.human_params(clone, "coord_ring", store)
        for got, w in zip(jax.tree.leaves(jax.tree.map(lambda x: x[i], state.human.params)), jax.tree.leaves(want)):
            np.testing.assert_array_equal(got, w)


@pytest.mark.slow
def test_eval_with_the_proxy_human_and_in_the_flipped_seat(per_seed_run, store, console):
    spec, path = per_seed_run
    own, own_summary, _ = _evaluate(path, store, 2, console)
    proxy, summary, cached = _evaluate(path, store, 2, console, "proxy")
    assert not cached and proxy != own and own_summary["human"] == "training" and own_summary["human_key"] is None
    # Per-seed proxies: each seed's clone of the held-out split, all built and named in the key.
    proxies = [human_runs.human_key(h, "coord_ring")[0] for h in spec.human.proxy().clones(spec.train.seeds)]
    assert all(store.lookup(human_runs.HUMAN_KIND, k) for k in proxies)
    assert summary["human"] == "proxy" and summary["human_key"] == json.loads((proxy / "manifest.json").read_text())["key_components"]["human"]
    for r in summary["results"].values():
        assert 0 <= r["return_mean"] <= 400 * 20
    assert _evaluate(path, store, 2, console, "proxy")[2]  # a cache hit the second time
    # The flipped seats: the robot plays agent_1, a separate evaluation; its training seat is the same as none.
    flipped, fsummary, _ = _evaluate(path, store, 2, console, "training", 1)
    assert flipped not in (own, proxy) and fsummary["robot_seat"] == 1 and own_summary["robot_seat"] == 0
    assert json.loads((flipped / "manifest.json").read_text())["key_components"]["robot_seat"] == 1
    assert _evaluate(path, store, 2, console, "training", 0)[0] == own


@pytest.mark.slow
def test_a_human_cloned_from_played_episodes_partners_a_robot(per_seed_run, store, console):
    """The loop closed: episodes played on coord_ring become a BC human's data (its last
    quarter held out), and `esr eval --human play:...` pairs the robot with that clone."""
    from esr_cli.model.envs import make_env
    from esr_cli.play import session as ps
    from esr_cli.play.game import Robot

    spec, path = per_seed_run
    play_spec = spec.model_copy(update={"env": spec.env.model_copy(update={"episode_steps": 30})})
    env = make_env(play_spec.env)
    rng = np.random.default_rng(1)
    keys = []
    for episode in range(4):
        presses = [str(k) for k in rng.choice(["up", "down", "left", "right", "space"], 30)]
        opponent = ps.Opponent("random", "robot A", Robot("random", env))
        recipe = ps.episode_recipe(play_spec, opponent, "p1", "s1", episode, episode,
                                   Scripted([k for key in presses for k in (key, None)]), "test", 6.0, "t", 0)
        keys.append(ensure(recipe, store).path.name)
    assert all(len(k) == 32 for k in keys)
    # A spec naming them clones from them: a data artifact of the person's pairs, then the human.
    clone = specs.load("experiments/coord_ring_random.yaml", "smoke", SMALL_HUMAN + [f"human.data={json.dumps(keys)}"])
    data_key, _ = human_runs.play_data_key(tuple(keys), "coord_ring")
    assert human_runs.human_key(clone.human, "coord_ring")[1]["dependencies"] == {human_runs.DATA_KIND: data_key}
    built = ensure(human_runs.human_recipe(clone.human, "coord_ring", console), store)
    summary = json.loads((built.path / "manifest.json").read_text())["summary"]
    assert summary["train"]["samples"] == 90 and summary["test"]["samples"] == 30  # 3 episodes cloned, 1 held out
    data = human_runs.load_data(store.lookup(human_runs.DATA_KIND, data_key))
    assert data["obs"].shape == (120, 5, 5, 26) and set(np.unique(data["player"])) == {1}
    # esr eval with that human: another evaluation, naming the clone's key.
    own, own_summary, _ = _evaluate(path, store, 2, console)
    other, summary, _ = _evaluate(path, store, 2, console, "play:" + ",".join(keys))
    assert other != own and summary["human_key"] != own_summary["human_key"]
    with pytest.raises(StoreError, match="is a key prefix"):  # only a command completes a prefix, from its store
        _evaluate(path, store, 2, console, "play:beef")
    # Any unique prefix names an episode, as `esr plays` prints the keys: completed from the store.
    from esr_cli.recipes import targets

    prefixes = [k[:8] for k in keys]
    short = specs.load("experiments/coord_ring_random.yaml", "smoke", SMALL_HUMAN + [f"human.data={json.dumps(prefixes)}"])
    assert targets.complete_play_keys(short, store).human.data == tuple(keys)
    assert targets.complete_play_partner(store, "play:" + ",".join(prefixes)) == "play:" + ",".join(keys)
    with pytest.raises(StoreError, match="start of no played episodes"):
        targets.complete_play_key(store, "ffff" if not any(k.startswith("ffff") for k in keys) else "0000")
    with pytest.raises(StoreError, match="is not in"):
        _evaluate(path, store, 2, console, "play:" + "0" * 32)


@pytest.mark.slow
def test_a_run_with_the_paper_network_as_its_bc_human_evaluates(small_data, store, console):
    """Its spec.yaml writes the MLP widths out at their default, which a conv human refuses when
    they are written by hand: read back from the store, the run is evaluated all the same."""
    spec = specs.load("experiments/coord_ring_random.yaml", "smoke", SMALL_HUMAN + ["human.network=conv"])
    path, _ = ensure(runs.run_recipe(spec, console), store)
    assert "hidden:" in (path / "spec.yaml").read_text()
    _, summary, _ = _evaluate(path, store, 2, console)
    assert summary["human"] == "training" and summary["results"]
