"""Exact empowerment: occupancies are distributions, MI vanishes exactly where the human's
action cannot matter, and matches a Monte-Carlo estimate from the real environment."""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esr_cli.analysis import exact, state_count
from esr_cli.model.envs.gridworld import GridState, Gridworld
from esr_cli.model.humans.gridworld import NoisyGreedyHuman

GAMMA = 0.7
GOAL = (2, 2)


@pytest.fixture(scope="module")
def tiny():
    env = Gridworld(size=3, num_blocks=1, start="random", episode_steps=50)
    human = NoisyGreedyHuman(env=env, noise=0.3)
    space = exact.enumerate_states(env, GOAL, exact.start_states(env, GOAL, 512))
    pi_h = exact.human_policy(space, human)
    pi_r = exact.uniform_robot(space)
    return env, human, space, pi_h, pi_r, exact.empowerment(space, pi_r, pi_h, GAMMA)


def index_of(space, human, block):
    hits = np.flatnonzero(np.all(space.human == human, axis=1) & np.all(space.blocks[:, 0] == block, axis=1))
    assert len(hits) == 1
    return int(hits[0])


@pytest.mark.slow
def test_enumeration_is_closed_and_complete(tiny):
    env, _, space, *_ = tiny
    # 9 human cells x 9 block cells (the block may sit on the human), except the human on the
    # goal under the block: nothing moves once the human is on its goal, and it cannot step
    # onto a block.
    assert space.size == 80
    assert space.next_state.shape == (80, 45, 5)
    assert space.next_state.max() < space.size
    assert abs(space.start.sum() - 1) < 1e-12


def test_rho_is_a_distribution(tiny):
    *_, emp = tiny
    m = emp.occupancy.rows(np.arange(len(emp.value)))
    np.testing.assert_allclose(m.sum(axis=1), 1.0, atol=1e-10)
    assert (m >= -1e-12).all()
    np.testing.assert_allclose(emp.visitation.sum(), 1.0, atol=1e-10)


def test_mi_is_zero_where_the_human_cannot_matter(tiny):
    env, _, space, _, _, emp = tiny
    dead = index_of(space, [1, 1], [1, 1])  # block on the human
    at_goal = index_of(space, list(GOAL), [0, 0])
    for s in (dead, at_goal):
        np.testing.assert_allclose(emp.mi[s], 0.0, atol=1e-12)
    assert emp.value[dead] == pytest.approx(0.0, abs=1e-12)


def test_mi_is_positive_for_a_free_human(tiny):
    _, _, space, _, _, emp = tiny
    free = index_of(space, [0, 0], [0, 2])
    assert (emp.mi[free] > 1e-3).all()
    assert emp.effective_empowerment > 0


@pytest.mark.slow
def test_mi_matches_monte_carlo_rollouts_of_the_environment(tiny):
    env, human, space, pi_h, _, emp = tiny
    s = index_of(space, [0, 0], [1, 1])
    a_r = 4 * 5 + 1  # push the centre block down
    n = 40_000
    goal = jnp.asarray(GOAL, jnp.int32)
    start = GridState(jnp.asarray(space.human[s]), jnp.asarray(space.blocks[s]), goal, jnp.zeros((), jnp.int32))
    keys = {tuple(h) + tuple(b.reshape(-1)): i for i, (h, b) in enumerate(zip(space.human, space.blocks))}

    def future(key, a_h):
        k_geo, k_steps = jax.random.split(key)
        steps = jax.random.geometric(k_geo, 1 - GAMMA)  # K on {1, 2, ...}
        first, _ = env.step(start, jnp.asarray(a_r), a_h)

        def body(i, st):
            k_r, k_h = jax.random.split(jax.random.fold_in(k_steps, i))
            nxt, _ = env.step(st, jax.random.randint(k_r, (), 0, env.num_robot_actions), human.act(k_h, st))
            return jax.tree.map(lambda a, b: jnp.where(i < steps - 1, a, b), nxt, st)

        return jax.lax.fori_loop(0, 40, body, first)

    rho_hat = []
    for a_h in range(5):
        ends = jax.jit(jax.vmap(lambda k: future(k, jnp.asarray(a_h))))(jax.random.split(jax.random.PRNGKey(a_h), n))
        h, b = exact._canonical(np.asarray(ends.human), np.asarray(ends.blocks))
        idx = [keys[tuple(x) + tuple(y.reshape(-1))] for x, y in zip(h, b)]
        rho_hat.append(np.bincount(idx, minlength=space.size) / n)
        # the geometric tail beyond 40 steps has mass 0.7^40 ~ 1e-6: negligible
        np.testing.assert_allclose(rho_hat[-1], emp.occupancy.rows([space.next_state[s, a_r, a_h]])[0], atol=0.01)
    rho_hat = np.array(rho_hat)
    mix = pi_h[s] @ rho_hat
    with np.errstate(divide="ignore", invalid="ignore"):
        kl = np.where(rho_hat > 0, rho_hat * np.log(rho_hat / mix), 0.0).sum(axis=1)
    mc = float(pi_h[s] @ kl)
    assert mc == pytest.approx(emp.mi[s, a_r], abs=0.02)
    assert emp.mi[s, a_r] > 0.05


TINY_SPEC = """
name: tiny
env: {kind: gridworld, size: 3, blocks: 2, start: corner}
human: {kind: noisy_greedy, noise: 0.2}
method: {kind: esr, future_gamma: 0.7}
"""


@pytest.mark.slow
def test_exact_and_estimator_cli(tmp_path):
    from conftest import esr

    spec = tmp_path / "tiny.yaml"
    spec.write_text(TINY_SPEC)
    store = tmp_path / "store"
    uniform = esr("exact", str(spec), "--goal", "1,1", store=store)
    path = Path(uniform.stdout.strip())
    summary = json.loads((path / "summary.json").read_text())
    assert summary["states"] > 50 and summary["effective_empowerment"] > 0 and summary["goal"] == [1, 1]
    data = np.load(path / "exact.npz")
    assert data["mi"].shape == (summary["states"], 45) and (data["mi"] >= 0).all()
    assert "cache hit" in esr("exact", str(spec), "--goal", "1,1", store=store).stderr
    run = Path(esr("train", str(spec), "--budget", "smoke", store=store).stdout.strip())
    with_robot = Path(esr("exact", str(spec), "--budget", "smoke", "--goal", "1,1", "--robot", run.name, store=store).stdout.strip())
    fig = esr("plot", "estimator", with_robot.name, store=store)
    png = Path(fig.stdout.strip())
    assert png.exists() and png.with_suffix(".json").exists()
    assert "Spearman" in fig.stderr
    result = json.loads((png.parent / "summary.json").read_text())
    assert -1 <= result["spearman"] <= 1
    assert 1 <= result["visited_pairs"] <= result["pairs"] and -1 <= result["spearman_visited"] <= 1 or \
        np.isnan(result["spearman_visited"])  # a constant estimate over few pairs has no rank correlation
    assert result["complete"] and "over all" in fig.stderr
    sampled = Path(esr("exact", str(spec), "--budget", "smoke", "--goal", "1,1", "--robot", run.name, "--sample-pairs", "30",
                       store=store).stdout.strip())
    assert sampled != with_robot
    check = json.loads((Path(esr("plot", "estimator", sampled.name, store=store).stdout.strip()).parent / "summary.json").read_text())
    assert check["sample_pairs"] == 30 and check["spearman"] == pytest.approx(result["spearman"])
    for args, why in ((("--sample-pairs", "40"), "give --robot"), (("--robot", run.name, "--sample-pairs", "5"), "at least 30 pairs")):
        refused = esr("exact", str(spec), "--budget", "smoke", "--goal", "1,1", *args, store=store, check=False)
        assert refused.returncode == 2 and why in refused.stderr, refused.stderr
    low, high = check["spearman_sample_ci"]
    assert low <= check["spearman_sample"] <= high or np.isnan(check["spearman_sample"])
    bad = esr("plot", "estimator", path.name, store=store, check=False)
    assert bad.returncode == 2 and "--robot" in bad.stderr
    # a robot without a learned policy has no Boltzmann policy to analyse: refused, not faked
    random_run = Path(esr("train", str(spec), "--budget", "smoke", "--set", "method.kind=random", store=store).stdout.strip())
    refused = esr("exact", str(spec), "--goal", "1,1", "--robot", random_run.name, store=store, check=False)
    assert refused.returncode == 2 and "leave out --robot for the uniform robot" in refused.stderr, refused.stderr


@pytest.mark.slow
def test_sweep_results_exact_puts_each_seeds_checks_beside_the_returns(tmp_path):
    """`esr sweep --results --exact` reads each seed's exact check and rank correlation from the
    store, names the command of each one missing, and those commands fill the cells in."""
    import shlex

    from conftest import ROOT, esr

    (tmp_path / "tiny.yaml").write_text(TINY_SPEC)
    suite = tmp_path / "suite.yaml"
    suite.write_text("name: tinyx\nset: {train.seeds: 2}\nspecs: [tiny.yaml, {spec: tiny.yaml, set: {method.kind: random}}]\n")
    store = tmp_path / "store"
    esr("sweep", str(suite), "--budget", "smoke", store=store)

    def results():
        rows = json.loads(esr("sweep", str(suite), "--budget", "smoke", "--results", "--exact", "--json", store=store).stdout)
        return rows[0], rows[1]

    def run(line):  # a printed line, run as printed: `esr` reaches the store it names by default (ESR_STORE)
        words = shlex.split(line)
        assert words[0] == "esr" and words[1] != "--store"
        return esr(*words[1:], store=store)

    esr_row, random_row = results()
    assert "exact" not in random_row  # a uniformly random robot has no policy of its own to analyse
    assert esr_row["exact"] == {"exact_ee": "— / —", "spearman_all": "— / —", "spearman_visited": "— / —"}
    first, second = esr_row["exact_todo"]
    assert f"--robot {esr_row['key'][:8]} --seed-index 0 --sample-pairs 500" in first and "--seed-index 1" in second
    exact_path = Path(run(first).stdout.strip())
    summary = json.loads((exact_path / "summary.json").read_text())
    esr_row, _ = results()
    assert esr_row["exact"]["exact_ee"] == f"{summary['effective_empowerment']:.3f} / —"  # every pair: exact, no '≥'
    assert esr_row["exact_todo"][0] == f"esr plot estimator {exact_path.name[:8]}"
    check = json.loads((Path(run(esr_row["exact_todo"][0]).stdout.strip()).parent / "summary.json").read_text())
    esr_row, _ = results()
    assert esr_row["exact"]["spearman_all"] == f"{check['spearman']:.3f} / —"
    assert esr_row["exact"]["spearman_visited"] == f"{check['spearman_visited']:.3f} ({check['visited_pairs']:,}) / —"
    assert esr_row["exact_todo"] == [second]
    table = esr("sweep", str(suite), "--budget", "smoke", "--results", "--exact", "--markdown", store=store).stdout
    assert "exact effective empowerment, per seed (nats)" in table and "Missing from the store, made by:" in table
    assert second in table
    plain = esr("sweep", str(suite), "--budget", "smoke", "--results", "--exact", store=store).stdout
    assert second in plain.splitlines()  # whole, on a line of its own: to copy and paste
    refused = esr("sweep", str(suite), "--budget", "smoke", "--exact", store=store, check=False)
    assert refused.returncode == 2 and "--exact applies with --results only" in refused.stderr
    overcooked = tmp_path / "oc.yaml"
    overcooked.write_text(f"name: oc\nspecs: [{ROOT / 'experiments' / 'cramped_room_random.yaml'}]\n")
    refused = esr("sweep", str(overcooked), "--budget", "smoke", "--results", "--exact", store=store, check=False)
    assert refused.returncode == 2 and "exact checks are made on gridworld runs; this suite has none" in refused.stderr


@pytest.mark.slow
def test_a_goal_that_no_start_leaves_free_is_refused_naming_the_goal(tmp_path):
    """A center start puts the human on the default goal (the centre): no start state is left."""
    from conftest import esr

    spec = tmp_path / "center.yaml"
    spec.write_text(TINY_SPEC.replace("start: corner", "start: center"))
    store = tmp_path / "store"
    refused = esr("exact", str(spec), store=store, check=False)
    said = " ".join(refused.stderr.split())
    assert refused.returncode == 2 and "the default goal (1, 1) (the centre; --goal names another): no start state of tiny" in said
    refused = esr("exact", str(spec), "--goal", "1,1", store=store, check=False)
    assert refused.returncode == 2 and "--goal (1, 1): no start state of tiny leaves this cell free" in refused.stderr
    assert not list(store.rglob("*.partial"))


@pytest.mark.slow
def test_mi_is_zero_for_a_human_trapped_by_blocks():
    """Human in a corner, both neighbours blocked: whatever the robot does this step, the
    human's action cannot change the next state, so I(aH; s+ | s, aR) = 0 for every aR."""
    env = Gridworld(size=3, num_blocks=2, start="corner", episode_steps=50)
    human = NoisyGreedyHuman(env=env, noise=0.2)
    goal = (2, 2)
    space = exact.enumerate_states(env, goal, exact.start_states(env, goal, 256))
    emp = exact.empowerment(space, exact.uniform_robot(space), exact.human_policy(space, human), 0.9)
    trapped = np.flatnonzero(
        np.all(space.human == [0, 0], axis=1) & np.all(space.blocks == np.array([[0, 1], [1, 0]]), axis=(1, 2))
    )
    assert len(trapped) == 1
    np.testing.assert_allclose(emp.mi[trapped[0]], 0.0, atol=1e-12)
    assert emp.value[trapped[0]] > 0  # later steps, once freed, do carry information


def test_visited_pairs_hold_99_percent_of_the_robots_occupancy_by_hand():
    """Two states; from state 0 robot action 0 stays (prob 0.999), action 1 leads to the
    absorbing state 1. At gamma 0.5: d = (0.999, 0.001), so the pair weights d(s) pi(a|s) are
    0.998, 0.000999, 0.0005, 0.0005: the pair (0, 0) alone holds over 99%."""
    from types import SimpleNamespace

    space = SimpleNamespace(next_state=np.array([[[0], [1]], [[1], [1]]]), start=np.array([1.0, 0.0]))

    def visited(pi_robot, dense_states):
        occ = exact.solve_occupancy(exact.transition_matrix(space, pi_robot, np.ones((2, 1))), 0.5, dense_states)
        return exact.visited_pairs(occ, space.start, pi_robot)

    for dense_states in (2, 0):  # the LU and the series agree
        assert visited(np.array([[0.999, 0.001], [0.5, 0.5]]), dense_states).tolist() == [[True, False], [False, False]]
        assert visited(np.full((2, 2), 0.5), dense_states).sum() == 4  # d = (2/3, 1/3): every pair is needed


def test_the_series_stops_where_the_rest_weighs_the_tolerance_by_hand():
    """Two states that swap every step: the row of M from state 0 is (1 - g) (1, g, g^2, ...)
    alternating, i.e. (1, g) / (1 + g). Summed to K terms the row misses mass exactly g^K, and
    K is the fewest terms with g^K <= tolerance."""
    g = 0.9
    p = np.array([[0.0, 1.0], [1.0, 0.0]])
    exact_row = np.array([1.0, g]) / (1.0 + g)
    for tol in (1e-2, 1e-6, exact.SERIES_TOLERANCE):
        occ = exact.SeriesOccupancy(p, g, tolerance=tol)
        k = occ.terms
        assert g**k <= tol < g ** (k - 1)
        row = occ.rows(np.array([0]))[0]
        assert (row <= exact_row + 1e-15).all()
        assert exact_row.sum() - row.sum() == pytest.approx(g**k, rel=1e-6, abs=1e-15)
    assert exact.SeriesOccupancy(p, 0.0).terms == 1  # gamma 0: the next state itself


def test_the_series_occupancy_equals_the_lu_one(tiny):
    """Above DENSE_STATES the sparse series replaces the LU: rows, products, values and
    visitation agree to the series' tolerance, and so does the MI computed from them."""
    env, _, space, pi_h, pi_r, emp = tiny
    p = exact.transition_matrix(space, pi_r, pi_h)
    chunks = []
    series = exact.solve_occupancy(p, GAMMA, dense_states=0, progress=chunks.append)
    assert isinstance(series, exact.SeriesOccupancy) and isinstance(emp.occupancy, exact.LUOccupancy)
    lu = emp.occupancy
    states = np.arange(space.size)
    np.testing.assert_allclose(series.rows(states), lu.rows(states), atol=1e-10)
    assert sum(chunks) == space.size and max(chunks) <= 256  # reported chunk by chunk
    v = np.arange(space.size * 2, dtype=float).reshape(space.size, 2) / space.size
    np.testing.assert_allclose(series.times(v), lu.times(v), atol=1e-9)
    np.testing.assert_allclose(series.discounted_sum(emp.state_mi), lu.discounted_sum(emp.state_mi), atol=1e-9)
    np.testing.assert_allclose(series.visitation(space.start), emp.visitation, atol=1e-10)
    pairs = exact.visited_pairs(series, space.start, pi_r)
    assert 0 < pairs.sum() < pairs.size
    part = exact.empowerment(space, pi_r, pi_h, GAMMA, pairs=pairs, occupancy=series)
    np.testing.assert_allclose(part.mi[pairs], emp.mi[pairs], atol=1e-8)
    assert np.isnan(part.mi[~pairs]).all()
    assert exact.rows_needed(space, pairs) == len(np.unique(space.next_state[pairs]))
    # the pairs left out count 0, so the effective empowerment is a lower bound, and close
    assert emp.effective_empowerment * 0.95 <= part.effective_empowerment <= emp.effective_empowerment + 1e-12


def test_factorised_occupancy_equals_the_dense_inverse(tiny):
    """Rows, products, visitation and values from the LU equal the dense formulas."""
    env, _, space, pi_h, pi_r, emp = tiny
    p = exact.transition_matrix(space, pi_r, pi_h).toarray()
    np.testing.assert_allclose(p.sum(axis=1), 1.0, atol=1e-12)
    inv = np.linalg.inv(np.eye(space.size) - GAMMA * p)
    m = (1 - GAMMA) * inv
    occ = emp.occupancy
    np.testing.assert_allclose(occ.rows([3, 0, 3]), m[[3, 0, 3]], atol=1e-12)
    v = np.arange(space.size * 2, dtype=float).reshape(space.size, 2)
    np.testing.assert_allclose(occ.times(v), m @ v, atol=1e-10)
    np.testing.assert_allclose(emp.visitation, (1 - GAMMA) * space.start @ inv, atol=1e-12)
    np.testing.assert_allclose(emp.value, inv @ emp.state_mi, atol=1e-10)


def test_mi_restricted_to_some_pairs_equals_the_full_computation(tiny):
    env, _, space, pi_h, pi_r, emp = tiny
    pairs = np.zeros(emp.mi.shape, bool)
    pairs[::7, ::3] = True
    part = exact.empowerment(space, pi_r, pi_h, GAMMA, pairs=pairs)
    np.testing.assert_allclose(part.mi[pairs], emp.mi[pairs], atol=1e-12)
    assert np.isnan(part.mi[~pairs]).all() and not part.complete and emp.complete


@pytest.mark.slow
def test_too_large_a_space_is_refused_by_name():
    env = Gridworld(size=5, num_blocks=2, start="corner", episode_steps=50)
    with pytest.raises(exact.TooManyStates, match="more than 100 reachable states"):
        exact.enumerate_states(env, (2, 2), exact.start_states(env, (2, 2), 64), max_states=100)


def test_actions_with_the_same_next_state_merge_into_one_class():
    nxt = np.array([[3, 3, 5], [1, 2, 1]])
    pi = np.array([[0.2, 0.3, 0.5], [0.1, 0.6, 0.3]])
    np.testing.assert_allclose(exact.merge_indistinguishable(nxt, pi), [[0.5, 0.0, 0.5], [0.4, 0.6, 0.0]])


def test_merged_mi_equals_the_true_mi_under_deterministic_dynamics(tiny):
    """The future depends on aH only through next(s, aR, aH), so merging the actions that
    observations cannot tell apart (a blocked move and 'stay') loses no information."""
    *_, emp = tiny
    np.testing.assert_allclose(emp.mi_merged, emp.mi, atol=1e-12)
    space = tiny[2]
    merges = (space.next_state[..., :, None] == space.next_state[..., None, :]).sum(axis=(-1, -2)) > space.next_state.shape[-1]
    assert merges.any()  # the tiny grid does have indistinguishable actions


@pytest.mark.slow
@pytest.mark.parametrize("size, blocks, start", [(3, 1, "random"), (3, 2, "corner"), (3, 7, "random"), (4, 2, "corner")])
def test_the_state_bound_holds_the_reachable_states(size, blocks, start):
    """`state_bound` is read from the spec before any enumeration: it must never be below what
    enumeration finds, and stays close to it (8,960 for 8,851 on a 4x4 grid with 3 blocks)."""
    env = Gridworld(size=size, num_blocks=blocks, start=start, episode_steps=50)
    goal = (size // 2, size // 2)
    found = exact.enumerate_states(env, goal, exact.start_states(env, goal, 256)).size
    assert found <= state_count.state_bound(size, blocks) <= 1.3 * found
    assert state_count.state_bound(4, 3) == 8960 and state_count.state_bound(16, 0) == 256


def test_the_spec_alone_refuses_a_space_too_large():
    assert state_count.check_size(4, 3) == 8960  # the largest shipped spec for exact analysis
    assert state_count.check_size(4, 4) == 29120  # 28,604 reachable: the sparse series' range
    with pytest.raises(exact.TooManyStates, match=r"env.size=16, env.blocks=40: up to .* states, more than the 30,000 "
                                                  r"exact analysis handles: lower env.size or env.blocks"):
        state_count.check_size(16, 40)
    with pytest.raises(exact.TooManyStates, match="up to 57,500 states"):
        state_count.check_size(5, 3)


@pytest.mark.slow
def test_exact_above_the_dense_limit_covers_the_visited_pairs(tmp_path, monkeypatch):
    """A space larger than DENSE_STATES (here made small) is solved with the series, over the
    pairs holding 99% of the robot's occupancy, and the summary says so; those pairs' MI equals
    the complete computation's."""
    from rich.console import Console

    from esr_cli.common import specs
    from esr_cli.recipes import exact_runs
    from esr_cli.storage.artifacts import ensure
    from esr_cli.storage.store import Store

    spec_path = tmp_path / "tiny.yaml"
    spec_path.write_text(TINY_SPEC)
    spec = specs.load(spec_path)
    complete = ensure(exact_runs.exact_recipe(spec, Store(tmp_path / "a"), (1, 1), None, None, 0, Console(quiet=True)), Store(tmp_path / "a"))
    monkeypatch.setattr(exact, "DENSE_STATES", 10)
    part = ensure(exact_runs.exact_recipe(spec, Store(tmp_path / "b"), (1, 1), None, None, 0, Console(quiet=True)), Store(tmp_path / "b"))
    full, some = (json.loads((r.path / "summary.json").read_text()) for r in (complete, part))
    assert full["pairs"] == "all" and full["pairs_computed"] == full["states"] * 45
    assert some["pairs"] == "visited (99% of the robot's occupancy)" and 0 < some["pairs_computed"] < full["pairs_computed"]
    assert some["mean_mi_uniform_states"] is None and some["states_with_zero_mi"] is None  # not over every state
    assert full["mean_mi_uniform_states"] > 0 and full["states_with_zero_mi"] > 0
    mi_full, mi_some = np.load(complete.path / "exact.npz")["mi"], np.load(part.path / "exact.npz")["mi"]
    computed = np.isfinite(mi_some)
    np.testing.assert_allclose(mi_some[computed], mi_full[computed], atol=1e-8)
    assert some["effective_empowerment"] <= full["effective_empowerment"] + 1e-12
    # A uniform sample of all pairs, computed beside the visited ones: its MI is the complete
    # computation's, and it changes neither the effective empowerment nor the visited means.
    sampled = ensure(exact_runs.exact_recipe(spec, Store(tmp_path / "b"), (1, 1), None, None, 0, Console(quiet=True), 40),
                     Store(tmp_path / "b"))
    with_sample = json.loads((sampled.path / "summary.json").read_text())
    assert sampled.path.name != part.path.name and with_sample["sample_pairs"] == 40
    assert with_sample["pairs"] == "visited (99% of the robot's occupancy) and a uniform sample of 40"
    data = np.load(sampled.path / "exact.npz")
    assert data["sampled"].sum() == 40 and np.isfinite(data["mi"][data["sampled"]]).all()
    assert (data["sampled"] & ~np.isfinite(mi_some)).any()  # the sample reaches beyond the visited pairs
    np.testing.assert_allclose(data["mi"][data["sampled"]], mi_full[data["sampled"]], atol=1e-8)
    for k in ("effective_empowerment", "mean_mi_visited", "mean_mi_visited_merged_actions", "max_mi"):
        assert with_sample[k] == pytest.approx(some[k], abs=1e-12), k
    assert with_sample["pairs_computed"] == int((np.isfinite(mi_some) | data["sampled"]).sum())


def test_sampled_pairs_are_distinct_uniform_and_fixed():
    mask = exact.sampled_pairs((100, 5), 50)
    assert mask.shape == (100, 5) and mask.sum() == 50
    assert (exact.sampled_pairs((100, 5), 50) == mask).all()  # a function of its arguments
    assert exact.sampled_pairs((100, 5), 50, seed=1).sum() == 50 and (exact.sampled_pairs((100, 5), 50, seed=1) != mask).any()
    assert exact.sampled_pairs((3, 2), 10).all()  # more than there are: every pair
    # uniform: over many draws every row is picked about as often as n / S
    counts = sum(exact.sampled_pairs((20, 5), 10, seed=s).sum(axis=1) for s in range(400))
    assert counts.min() > 0.6 * counts.mean() and counts.max() < 1.4 * counts.mean()


def test_the_missing_checks_of_a_run_are_named_seed_by_seed():
    from esr_cli.recipes.exact_lookup import SeedCheck, cells, missing

    whole = SeedCheck(exact="a" * 32, effective_empowerment=0.25, complete=True, spearman_all=0.5, spearman_visited=0.4,
                      visited_pairs=120)
    visited_only = SeedCheck(exact="b" * 32, effective_empowerment=0.2, complete=False)
    sampled = SeedCheck(exact="c" * 32, effective_empowerment=0.2, complete=False, sampled=True)
    checked = SeedCheck(exact="c" * 32, effective_empowerment=0.2, complete=False, sampled=True,
                        spearman_sample=(0.52, 0.47, 0.58), sample_pairs=500, spearman_visited=0.61, visited_pairs=966)
    # no check; one over the visited pairs alone (the correlation over all pairs needs a sample);
    # a sampled one whose correlation is not yet made; complete ones
    assert missing([SeedCheck(), visited_only, sampled, whole, checked]) == [(0, "exact"), (1, "exact"), (2, "estimator")]
    assert cells([whole, checked]) == {"exact_ee": "0.250 / ≥ 0.200",
                                       "spearman_all": "0.500 / 0.520 [0.470, 0.580] (sample of 500)",
                                       "spearman_visited": "0.400 (120) / 0.610 (966)"}


def test_run_checks_read_only_the_runs_own_checks_and_pass_over_damaged_entries(tmp_path):
    """A hand-made store: the run's sampled check and its estimator are read; a check of another
    human, goal or run, and entries with damaged manifests, components or summaries, are passed
    over (never a traceback); between two checks of a seed the sampled one is read."""
    from esr_cli.recipes.exact_lookup import Target, read_checks, run_checks
    from esr_cli.storage.store import Store

    env, human = {"kind": "gridworld", "size": 4}, {"kind": "noisy_greedy", "noise": 0.2}
    run = "ab" * 16

    def artifact(kind, key, comps, summary, created="2026-11-29T10:00:00+0000"):
        d = tmp_path / kind / key[:2] / key
        d.mkdir(parents=True)
        (d / "manifest.json").write_text(json.dumps({"kind": kind, "key": key, "files": {}, "key_components": comps,
                                                     "created_at": created}))
        (d / "summary.json").write_text(summary if isinstance(summary, str) else json.dumps(summary))

    def exact_comps(seed, **over):
        return {"kind": "exact", "env": env, "human": human, "goal": [2, 2], "gamma": 0.9,
                "robot": {"run": run, "seed_index": seed}, **over}

    visited = {"effective_empowerment": 0.2, "pairs": "visited (99% of the robot's occupancy)"}
    artifact("exact", "10" * 16, exact_comps(0), visited, created="2026-11-29T12:00:00+0000")  # newer, no sample
    artifact("exact", "11" * 16, exact_comps(0, sample_pairs=500), {**visited, "sample_pairs": 500})
    artifact("figures", "12" * 16, {"figure": "estimator", "exact": "11" * 16},
             {"spearman": 0.5, "complete": False, "spearman_visited": 0.6, "visited_pairs": 900,
              "spearman_sample": 0.41, "spearman_sample_ci": [0.33, 0.49], "sample_pairs": 500})
    artifact("exact", "20" * 16, exact_comps(1, human={"kind": "noisy_greedy", "noise": 0.5}), visited)  # another human
    artifact("exact", "21" * 16, exact_comps(1, goal=[0, 0]), visited)  # another goal
    artifact("exact", "22" * 16, exact_comps(1, robot={"run": "cd" * 16, "seed_index": 1}), visited)  # another run
    artifact("exact", "23" * 16, exact_comps(1, gamma=None, robot={"run": run, "seed_index": "1"}), visited)
    artifact("exact", "24" * 16, "not a mapping", visited)
    artifact("exact", "30" * 16, exact_comps(2), "[1, 2]")  # a summary that is no mapping
    artifact("figures", "31" * 16, {"figure": "estimator", "exact": "30" * 16},
             {"spearman_sample": 0.4, "spearman_sample_ci": "x", "spearman_visited": 10**400})  # too large for a float
    (tmp_path / "exact" / "40").mkdir()
    (tmp_path / "exact" / "40" / ("40" * 16)).mkdir()  # no manifest at all
    checks = run_checks(read_checks(Store(tmp_path)), Target(run, env, human, (2, 2), 0.9), 3)
    first, second, third = checks
    assert first.exact == "11" * 16 and first.sampled and first.complete is False and first.effective_empowerment == 0.2
    assert first.spearman_sample == (0.41, 0.33, 0.49) and first.sample_pairs == 500
    assert first.spearman_visited == 0.6 and first.visited_pairs == 900 and first.spearman_all is None
    assert second.exact is None  # every candidate for seed 1 is of something else, or damaged
    assert third.exact == "30" * 16 and third.effective_empowerment is None and third.spearman_visited is None


def test_spearman_interval_by_hand():
    from esr_cli.recipes.exact_runs import spearman_interval

    x = np.arange(30.0)
    assert spearman_interval(x, x**3, resamples=200) == pytest.approx((1.0, 1.0, 1.0))  # monotone: every resample too
    assert spearman_interval(x, -x, resamples=200) == pytest.approx((-1.0, -1.0, -1.0))
    rng = np.random.default_rng(0)
    a = rng.normal(size=400)
    rho, low, high = spearman_interval(a, a + rng.normal(size=400), resamples=500)
    assert low < rho < high and 0.5 < rho < 0.8 and high - low < 0.2  # rho of a + noise (sd 1): about 0.68


@pytest.mark.slow
def test_a_failed_exact_build_leaves_no_lock_or_partial_artifact(tmp_path, monkeypatch):
    from rich.console import Console

    from esr_cli.common import specs
    from esr_cli.recipes import exact_runs
    from esr_cli.storage.artifacts import ensure
    from esr_cli.storage.store import EXACT_KIND, Store

    spec_path = tmp_path / "tiny.yaml"
    spec_path.write_text(TINY_SPEC)
    spec = specs.load(spec_path)
    store = Store(tmp_path / "store")
    recipe = exact_runs.exact_recipe(spec, store, (1, 1), None, None, 0, Console(quiet=True))

    def fail(*args, **kwargs):
        raise MemoryError("out of memory in the middle of the solve")

    monkeypatch.setattr(exact, "empowerment", fail)
    with pytest.raises(MemoryError):
        ensure(recipe, store)
    assert not store.partial_path(EXACT_KIND, recipe.key).exists()
    assert store.lookup(EXACT_KIND, recipe.key) is None
    with store.lock(EXACT_KIND, recipe.key, wait=False):  # free: LockBusy otherwise
        pass
    monkeypatch.undo()
    assert ensure(recipe, store).cached is False  # the same command then succeeds


def test_a_gridworld_without_blocks_enumerates_the_humans_cells():
    """No blocks: the robot's actions change nothing, the states are the human's cells, and
    the human's action alone decides the next state."""
    env = Gridworld(size=3, num_blocks=0, start="random", episode_steps=10)
    space = exact.enumerate_states(env, (2, 2), exact.start_states(env, (2, 2), 64))
    assert space.size == 9
    assert (space.next_state == space.next_state[:, :1, :]).all()  # whatever the robot does


@pytest.mark.slow
def test_a_check_kept_without_its_arrays_still_fills_the_table_in_another_store(tmp_path):
    """`esr export --without-checkpoint` of a finished run and of its exact check (no exact.npz)
    and the estimator figure: imported elsewhere, `--results --exact` shows the same cells; the
    estimator check itself, which needs the arrays, is refused by name."""
    from conftest import esr

    (tmp_path / "tiny.yaml").write_text(TINY_SPEC)
    suite = tmp_path / "suite.yaml"
    suite.write_text("name: tinyl\nspecs: [tiny.yaml]\n")
    store, other = tmp_path / "store", tmp_path / "other"
    run = Path(esr("sweep", str(suite), "--budget", "smoke", store=store).stdout.split()[0])
    exact_path = Path(esr("exact", str(tmp_path / "tiny.yaml"), "--budget", "smoke", "--robot", run.name[:8],
                          store=store).stdout.strip())
    figure = Path(esr("plot", "estimator", exact_path.name[:8], store=store).stdout.strip()).parent

    def table(s):
        return json.loads(esr("sweep", str(suite), "--budget", "smoke", "--results", "--exact", "--json", store=s).stdout)[0]["exact"]

    for key, light in ((run.name, True), (exact_path.name, True), (figure.name, False)):
        archive = tmp_path / f"{key[:8]}.tar.gz"
        esr("export", key, "--out", str(archive), *(["--without-checkpoint"] if light else []), store=store)
        esr("import", str(archive), store=other)
    (copy,) = (other / "exact").glob("*/" + exact_path.name)
    assert not (copy / "exact.npz").exists() and (copy / "summary.json").exists()
    assert esr("verify", store=other).returncode == 0  # the manifest keeps the left-out file's digest
    assert table(other) == table(store) and "—" not in table(other)["exact_ee"]
    # Where no estimator figure of it was imported, drawing one needs the arrays: refused by name.
    third = tmp_path / "third"
    esr("import", str(tmp_path / f"{exact_path.name[:8]}.tar.gz"), store=third)
    refused = esr("plot", "estimator", exact_path.name[:8], store=third, check=False)
    assert refused.returncode != 0 and "kept without its arrays" in refused.stderr
    whole = esr("export", figure.name, "--without-checkpoint", "--out", str(tmp_path / "f.tar.gz"), store=store, check=False)
    assert whole.returncode != 0 and "kept whole" in whole.stderr


def test_a_target_without_a_run_matches_the_uniform_robots_check_only():
    """Target(None, ...) is the check of a uniform robot on the environment (seed index 0), as the
    report's estimator section reads it beside the trained robot's; a run's target never matches it."""
    from esr_cli.recipes.exact_lookup import Target

    env, human = {"kind": "gridworld", "size": 5}, {"kind": "noisy_greedy"}
    comps = {"env": env, "human": human, "goal": [2, 2], "gamma": 0.9}
    uniform, trained = Target(None, env, human, (2, 2), 0.9), Target("ab" * 16, env, human, (2, 2), 0.9)
    assert uniform.matches({**comps, "robot": "uniform"}) == 0
    assert uniform.matches({**comps, "robot": {"run": "ab" * 16, "seed_index": 0}}) is None
    assert trained.matches({**comps, "robot": "uniform"}) is None
    assert trained.matches({**comps, "robot": {"run": "ab" * 16, "seed_index": 2}}) == 2
    assert uniform.matches({**comps, "robot": "uniform", "goal": [0, 0]}) is None
