"""esr diagnose: the human's situation read from observations, and the command on a real run."""

import json

import numpy as np
import pytest
from conftest import esr

from esr_cli.analysis.diagnose import SITUATIONS, free_trapped_contrast, situation, stored_effects


def test_situations_of_hand_made_states():
    obs = np.zeros((5, 5, 5, 2), np.uint8)
    obs[0, 0, 0, 0] = 1; obs[0, 0, 1, 1] = 1; obs[0, 1, 0, 1] = 1  # noqa: E702 - cornered by two blocks
    obs[1, 2, 2, 0] = 1; obs[1, 2, 3, 1] = 1  # noqa: E702 - a block beside, three ways open
    obs[2, 1, 1, 0] = 1; obs[2, 1, 1, 1] = 1  # noqa: E702 - a block on the human
    obs[3, 4, 4, 0] = 1  # on its goal (the reward says so)
    obs[4, 0, 2, 0] = 1; obs[4, 0, 1, 1] = 1; obs[4, 0, 3, 1] = 1; obs[4, 1, 2, 1] = 1  # noqa: E702 - wall and 3 blocks
    got = [SITUATIONS[i] for i in situation(obs, np.array([0, 0, 0, 1, 0]))]
    assert got == ["trapped", "free", "dead", "at_goal", "trapped"]


def test_free_trapped_contrast_is_cohens_d():
    free = np.array([1.0, 2.0, 3.0, 6.0])
    trapped = np.array([0.0, 1.0, -1.0])
    rewards = {name: {"n": len(v), "mean": float(v.mean()), "sd": float(v.std())}
               for name, v in (("free", free), ("trapped", trapped))}
    pooled = np.sqrt((free.var(ddof=1) * 3 + trapped.var(ddof=1) * 2) / 5)
    got = free_trapped_contrast(rewards)
    assert abs(got["difference"] - 3.0) < 1e-12
    assert abs(got["effect_size"] - 3.0 / pooled) < 1e-12
    rewards["trapped"] = {"n": 1, "mean": 0.0, "sd": 0.0}
    assert np.isnan(free_trapped_contrast(rewards)["effect_size"])  # one trapped transition: no spread


@pytest.mark.slow
def test_diagnose_reads_a_trained_run(smoke_run):
    store, path, _ = smoke_run
    proc = esr("diagnose", str(path), "--batches", "3", "--json", store=store)
    report = json.loads(proc.stdout)
    assert set(report["reward"]) == set(SITUATIONS)
    counted = sum(r["n"] for r in report["reward"].values())
    assert counted == 3 * 16  # three smoke batches of 16, every transition in one situation
    assert report["start"] == "corner" and len(report["start_states"]) == 4  # four distinct corner starts
    assert set(report["free_vs_trapped"]) == {"difference", "effect_size"}
    for row in report["start_states"]:
        # A cornered human (N = 2): 4 robot actions free it, 2 push a block onto it.
        assert (row["free"]["actions"], row["dead"]["actions"], row["trapped"]["actions"]) == (4, 2, 119)
        assert abs(sum(row[e]["p"] for e in ("trapped", "free", "dead")) - 1) < 1e-4
        assert all(row[e]["stored"] >= 0 for e in ("trapped", "free", "dead"))
    reprs = report["representations"]  # an ESR run: what its representations pick futures by
    assert set(reprs) == {"accuracy_phi", "accuracy_phi_prime", "chance", "layout_only", "within_layout_phi",
                          "within_layout_phi_prime", "mi_estimate"}
    assert all(0 <= reprs[k] <= 1 for k in reprs if k != "mi_estimate")
    assert reprs["layout_only"] >= reprs["chance"] - 1e-6  # knowing the layout never hurts
    assert report["finished"] is True and report["epoch"] == report["epochs"] == 2
    play = report["play"]  # the run's robot and a uniform one, scored by the run's own reward
    assert set(play) == {"robot", "uniform"}
    for side in play.values():
        assert side["episodes"] == 16 and 0 <= side["human_moves"] <= 1 and side["return"] >= 0
        # ESR's reward is the phi minus phi' logit before its 1/d: over equal batches its mean is
        # d times the mean MI estimate
        assert abs(side["reward"]["mean"] - 32 * side["reward"]["mi_estimate"]) < 1e-3 * (1 + abs(side["reward"]["mean"]))
    bad = esr("diagnose", str(path), "--seed-index", "3", store=store, check=False)
    assert bad.returncode == 2 and "seed" in bad.stderr


@pytest.mark.slow
def test_diagnose_reads_an_unfinished_run_without_touching_it(tmp_path):
    store = tmp_path / "store"
    stopped = esr("train", "experiments/grid_2.yaml", "--budget", "smoke", "--stop-after", "0s", store=store, check=False)
    assert stopped.returncode == 75, stopped.stderr
    (part,) = (store / "runs").glob("*/*.partial")
    before = sorted((p.relative_to(part), p.read_bytes()) for p in part.rglob("*") if p.is_file())
    proc = esr("diagnose", part.name.split(".")[0][:8], "--batches", "2", "--episodes", "4", "--refit", "3", "--json", store=store)
    report = json.loads(proc.stdout)
    assert report["finished"] is False and (report["epoch"], report["epochs"]) == (1, 2)
    assert report["play"]["robot"]["episodes"] == 4
    assert all(np.isfinite(side["refit"][k]) for side in report["play"].values() for k in ("fit", "held_out"))
    after = sorted((p.relative_to(part), p.read_bytes()) for p in part.rglob("*") if p.is_file())
    assert after == before  # read from a copy: the run resumes as if never read
    # the same sizes as above: its programs come from the session's compile cache
    text = esr("diagnose", str(part), "--batches", "2", "--episodes", "4", "--refit", "3", store=store).stdout
    assert "unfinished: checkpoint at epoch 1 of 2" in text


def test_human_moves_counts_steps_that_change_the_humans_own_part():
    from esr_cli.analysis.play_check import human_moves
    from esr_cli.common import specs
    from esr_cli.model.envs import gridworld

    env = gridworld.make(specs.load("experiments/grid_2.yaml", "smoke").env)
    obs = np.zeros((2, 4, 5, 5, 2), np.uint8)
    cells = [[(0, 0), (0, 1), (0, 1), (1, 1)], [(2, 2), (2, 2), (2, 2), (2, 2)]]
    for e, path in enumerate(cells):
        for t, (r, c) in enumerate(path):
            obs[e, t, r, c, 0] = 1
    obs[1, 2, 4, 4, 1] = 1  # a block moves: not the human's own part
    assert abs(human_moves(env, obs) - 2 / 6) < 1e-6


def test_play_check_needs_a_robot_that_learns_a_policy():
    import jax
    import pytest

    from esr_cli.analysis.play_check import play_check
    from esr_cli.common import specs
    from esr_cli.model.train import make_trainer

    trainer = make_trainer(specs.load("experiments/grid_2_random.yaml", "smoke"))
    with pytest.raises(ValueError, match="learns no robot policy"):
        play_check(trainer, None, jax.random.PRNGKey(0))


@pytest.mark.slow
def test_representation_scores_of_hand_made_representations():
    import jax.numpy as jnp

    from esr_cli.analysis.diagnose import representation_scores

    # Four distinct futures in two block layouts (0, 1 share one, 2, 3 the other).
    future = np.zeros((4, 5, 5, 2), np.uint8)
    for i, (human, block) in enumerate([((0, 0), (2, 2)), ((0, 1), (2, 2)), ((0, 0), (3, 3)), ((4, 4), (3, 3))]):
        future[i, human[0], human[1], 0] = 1
        future[i, block[0], block[1], 1] = 1
    psi = jnp.eye(4)
    phi_sa = jnp.eye(4)  # names its own future
    phi_s = 0.5 * jnp.array([[1, 1, 0, 0], [1, 1, 0, 0], [0, 0, 1, 1], [0, 0, 1, 1]], jnp.float32)  # the layout only
    got = {k: float(v) for k, v in representation_scores(phi_s, phi_sa, psi, jnp.asarray(future)).items()}
    assert got["accuracy_phi"] == 1.0 and got["within_layout_phi"] == 1.0
    assert got["accuracy_phi_prime"] == 0.5 and got["within_layout_phi_prime"] == 0.5  # ties go to the first
    assert got["chance"] == 0.25 and got["layout_only"] == 0.5
    assert abs(got["mi_estimate"] - (1 - 0.5) / 4) < 1e-6  # diagonal logits / d



def test_stored_effects_counts_the_transitions_out_of_a_trapped_corner():
    from esr_cli.model import replay

    start = np.zeros((3, 3, 2), np.uint8)
    start[0, 0, 0] = 1; start[0, 1, 1] = 1; start[1, 0, 1] = 1  # noqa: E702 - cornered at (0, 0)
    elsewhere = start.copy(); elsewhere[2, 2, 1] = 1  # noqa: E702 - cornered too, another layout
    freed = start.copy(); freed[0, 1, 1] = 0; freed[0, 2, 1] = 1  # noqa: E702 - a block pushed away
    dead = start.copy(); dead[0, 0, 1] = 1; dead[0, 1, 1] = 0  # noqa: E702 - a block pushed onto the human
    free = np.zeros((3, 3, 2), np.uint8); free[0, 0, 0] = 1  # noqa: E702 - at the corner but free
    episodes = np.stack([
        [start, start, freed],  # trapped, then freed
        [elsewhere, dead, dead],  # dead (then a dead human: not trapped, not counted)
        [free, start, freed],  # a free human first: not counted; then freed
        [start, start, start],  # the slot past `count`: not held, never counted
    ])
    buf = replay.Buffer(obs=episodes, robot_action=np.zeros((4, 2), np.int32), human_action=np.zeros((4, 2), np.int32),
                        reward=np.zeros((4, 2), np.float32), ptr=np.int32(3), count=np.int32(3))
    assert stored_effects(buf, (0, 0)) == {"trapped": 1, "free": 2, "dead": 1}
    assert stored_effects(buf, (2, 2)) == {"trapped": 0, "free": 0, "dead": 0}


@pytest.mark.slow
def test_refit_recovers_log_4_when_the_next_state_names_one_of_4_human_actions():
    """Next observations place the human in the row its action names (4 rows, uniform) and a
    random column; with the future the next state, I(aH; s' | s, aR) = log 4 exactly. Labels
    drawn independently of the observations carry nothing: 0."""
    import jax
    import jax.numpy as jnp

    from esr_cli.analysis.play_check import refit_mi_estimate
    from esr_cli.common import specs
    from esr_cli.model import replay
    from esr_cli.model.train import make_trainer

    trainer = make_trainer(specs.load("experiments/grid_2.yaml", "smoke", ["method.future_gamma=0.01", "learner.batch_size=64"]))
    rng = np.random.default_rng(0)
    n, steps = 32, 20
    actions = rng.integers(0, 4, (n, steps))
    obs = np.zeros((n, steps + 1, 5, 5, 2), np.uint8)
    obs[:, 0, 2, 2, 0] = 1
    for e in range(n):
        for t in range(steps):
            obs[e, t + 1, actions[e, t], rng.integers(0, 5), 0] = 1

    def episodes(human_action):
        return replay.Episodes(obs=jnp.asarray(obs), robot_action=jnp.zeros((n, steps), jnp.int32),
                               human_action=jnp.asarray(human_action, jnp.int32), reward=jnp.zeros((n, steps)))

    told = refit_mi_estimate(trainer, episodes(actions), jax.random.PRNGKey(0), 300)
    assert abs(told["held_out"] - np.log(4)) < 0.15 and abs(told["fit"] - np.log(4)) < 0.15
    unrelated = refit_mi_estimate(trainer, episodes(rng.integers(0, 4, (n, steps))), jax.random.PRNGKey(0), 300)
    assert abs(unrelated["held_out"]) < 0.15 and abs(unrelated["fit"]) < 0.15


# ---------------------------------------------------------------- stored diagnoses, read back

def _stored_diagnosis(store, run_key: str, seed_index: int, summary: dict, **options):
    """A committed diagnosis with a hand-made summary, made the one way every artifact is."""
    from dataclasses import replace

    from esr_cli.recipes.diagnosis_runs import Options, components
    from esr_cli.storage.artifacts import Recipe, ensure
    from esr_cli.storage.store import DIAGNOSIS_KIND

    comps = components(run_key, seed_index, replace(Options(), **options))
    return ensure(Recipe(DIAGNOSIS_KIND, "hand-made", comps, lambda out, store: summary), store).path


HAND_MADE = {
    "play": {"robot": {"return": 26.125}, "uniform": {"return": 11.0}},
    "reward": {"free": {"n": 5, "mean": 5.319}, "trapped": {"n": 3, "mean": 0.241}, "dead": {"n": 1, "mean": -3.57},
               "at_goal": {"n": 2, "mean": 0.3}},
    "free_vs_trapped": {"difference": 5.08, "effect_size": 0.306},
    "start_states": [{"free": {"p": 1.0}}, {"free": {"p": 0.9}}, {"free": {"p": 2.7e-6}}, {"free": {"p": 0.5}}],
    "representations": {"accuracy_phi": 0.1456, "accuracy_phi_prime": 0.1433, "layout_only": 0.9553},
}


def test_a_runs_stored_diagnoses_become_its_cells_seed_by_seed(tmp_path):
    from esr_cli.recipes import diagnosis_lookup as dl
    from esr_cli.storage.store import Store

    store = Store(tmp_path / "store")
    run = "ab" * 16
    _stored_diagnosis(store, run, 0, HAND_MADE)
    _stored_diagnosis(store, run, 1, {**HAND_MADE, "representations": None}, batches=3)  # not the defaults: not read
    _stored_diagnosis(store, "cd" * 16, 1, HAND_MADE)  # another run's
    found = dl.read_diagnoses(store)
    cells, missing = dl.run_cells(found, run, 2)
    assert missing == [1]
    assert cells == {
        "reward_by_situation": "+5.32, +0.24, -3.57 / —",  # free, trapped, dead
        "effect_size": "0.31 / —",
        "future_picked": "0.146, 0.143 / —",  # phi, phi'
        "layout_only": "0.955 / —",
        "starts_freed": "2 of 4 / —",  # over half the policy's probability on freeing: 1.0 and 0.9, not 0.5
        "play": "26.12 vs 11.00 / —",
    }
    _stored_diagnosis(store, run, 1, {"play": HAND_MADE["play"]})  # an Overcooked run: a play check alone
    cells, missing = dl.run_cells(dl.read_diagnoses(store), run, 2)
    assert missing == [] and cells["play"] == "26.12 vs 11.00 / 26.12 vs 11.00"
    assert cells["layout_only"] == "0.955 / —"
    only_play, _ = dl.run_cells(dl.read_diagnoses(store), run, 3)  # seed 2 missing alike
    assert only_play["play"].endswith(" / —")
    one_seed, _ = dl.run_cells({(run, 0): found[(run, 0)]}, run, 1)
    assert all(one_seed[c] and " / " not in one_seed[c] for c in dl.COLUMNS)
    overcooked, _ = dl.run_cells(dl.read_diagnoses(store), run, 2, dl.applicable("overcooked", "esr"))
    assert overcooked["play"] == "26.12 vs 11.00 / 26.12 vs 11.00" and overcooked["layout_only"] == ""
    unreadable = _stored_diagnosis(store, "ef" * 16, 0, {})
    (unreadable / "summary.json").write_text("[1, 2]")  # not a diagnosis: made again by its command
    cells, missing = dl.run_cells(dl.read_diagnoses(store), "ef" * 16, 1)
    assert missing == [0] and set(cells.values()) == {"—"}


def test_a_damaged_stored_diagnosis_shows_dashes_never_a_crash_or_a_number():
    from esr_cli.recipes import diagnosis_lookup as dl

    hostile = {
        "play": {"robot": {"return": "26"}, "uniform": {"return": True}},
        "reward": {"free": {"mean": [1]}, "trapped": "x", "dead": {"mean": float("nan")}},
        "free_vs_trapped": {"effect_size": 10**400},  # JSON allows it; float() of it overflows
        "start_states": ["not a row", {"free": {"p": "1"}}, {"free": {"p": 0.99}}],
        "representations": {"accuracy_phi": {"v": 1}, "layout_only": None},
    }
    assert dl.seed_cells(hostile) == {
        "reward_by_situation": "—, —, —", "effect_size": "—", "future_picked": "—, —", "layout_only": "—",
        "starts_freed": "1 of 2", "play": "— vs —",  # of the rows that are rows
    }
    assert set(dl.seed_cells(hostile, ("play",)).values()) == {"— vs —", ""}  # the cells asked for alone
    # which cells a run has comes from what it is, never from what a summary holds
    assert dl.applicable("overcooked", "esr") == ("play",)
    assert dl.applicable("gridworld", "ave") == ("reward_by_situation", "effect_size", "starts_freed", "play")
    assert dl.applicable("gridworld", "esr") == tuple(dl.COLUMNS)


def test_the_play_check_columns_read_both_players_and_dash_what_is_damaged():
    from esr_cli.recipes import diagnosis_lookup as dl

    report = {"play": {
        "robot": {"return": 0.0, "reward": {"mean": 1.812, "sd": 10.298, "mi_estimate": 0.0566}, "human_moves": 0.2188},
        "uniform": {"return": 18.75, "reward": {"mean": -4.491, "sd": 21.668, "mi_estimate": -0.1403}, "human_moves": 0.468},
    }}
    cells = dl.seed_cells(report, dl.play_applicable("esr"), dl.PLAY_COLUMNS)
    assert cells == {"play_return": "0.00 vs 18.75", "play_reward": "+1.81 (10.3) vs -4.49 (21.7)",
                     "play_mi": "+0.057 vs -0.140", "human_moves": "0.219 vs 0.468"}
    assert dl.play_applicable("ave") == ("play_return", "play_reward", "human_moves")  # no MI estimate of its own
    damaged = {"play": {"robot": {"return": True, "reward": "x", "human_moves": 10**400}, "uniform": [1]}}
    assert set(dl.seed_cells(damaged, tuple(dl.PLAY_COLUMNS), dl.PLAY_COLUMNS).values()) == {"— vs —", "— (—) vs — (—)"}
    assert set(dl.seed_cells({"play": None}, tuple(dl.PLAY_COLUMNS), dl.PLAY_COLUMNS).values()) == {"— vs —", "— (—) vs — (—)"}


@pytest.mark.slow
def test_a_finished_runs_diagnosis_is_stored_and_read_back_by_its_suites_table(tmp_path):
    """`esr diagnose` of a finished run stores it (the same again is a cache hit), and `esr sweep
    --results --diagnose` reads it into the row, naming the command of each seed it lacks."""
    import shlex

    from conftest import ROOT

    suite = tmp_path / "suite.yaml"
    suite.write_text(f"name: diag\nset: {{train.seeds: 2}}\nspecs: [{ROOT / 'experiments' / 'grid_2.yaml'}, "
                     f"{{spec: {ROOT / 'experiments' / 'grid_2_random.yaml'}}}]\n")
    store = tmp_path / "store"
    esr("sweep", str(suite), "--budget", "smoke", store=store)

    def rows():
        return json.loads(esr("sweep", str(suite), "--budget", "smoke", "--results", "--diagnose", "--json", store=store).stdout)

    esr_row, random_row = rows()
    assert "diagnosis" not in random_row  # a uniformly random robot learns no policy to diagnose
    assert set(esr_row["diagnosis"].values()) == {"— / —"}
    first, second = esr_row["diagnosis_todo"]
    assert first == f"esr diagnose {esr_row['key'][:8]} --seed-index 0" and second.endswith("--seed-index 1")
    made = esr(*shlex.split(first)[1:], store=store)
    assert "computed" in made.stderr
    (stored,) = (store / "diagnoses").glob("*/*/summary.json")
    summary = json.loads(stored.read_text())
    assert summary["run"] == esr_row["key"] and summary["seed_index"] == 0 and summary["finished"] is True
    again = esr(*shlex.split(first)[1:], "--json", store=store)
    assert "cache hit" in again.stderr and json.loads(again.stdout) == summary
    assert made.stdout == esr(*shlex.split(first)[1:], store=store).stdout  # printed alike from the store
    esr_row, _ = rows()
    assert esr_row["diagnosis_todo"] == [second]
    free, trapped, dead = (summary["reward"][s]["mean"] for s in ("free", "trapped", "dead"))
    assert esr_row["diagnosis"]["reward_by_situation"].startswith(
        ", ".join("—" if v != v else f"{v:+.2f}" for v in (free, trapped, dead)) + " / ")
    assert esr_row["diagnosis"]["play"] == (f"{summary['play']['robot']['return']:.2f} vs "
                                            f"{summary['play']['uniform']['return']:.2f} / —")
    table = esr("sweep", str(suite), "--budget", "smoke", "--results", "--diagnose", "--markdown", store=store).stdout
    assert "reward: free / trapped / dead, per seed" in table and second in table
    # --play reads the same diagnoses' play checks in full; with --diagnose too, each missing
    # diagnosis is named once.
    both = esr("sweep", str(suite), "--budget", "smoke", "--results", "--diagnose", "--play", "--markdown", store=store).stdout
    robot = summary["play"]["robot"]
    assert "share of steps the human moves, per seed" in both and both.count(second) == 1
    assert f"| {robot['return']:.2f} vs {summary['play']['uniform']['return']:.2f} / — |" in both
    assert f"{robot['human_moves']:.3f} vs {summary['play']['uniform']['human_moves']:.3f} / —" in both
    refused = esr("sweep", str(suite), "--budget", "smoke", "--play", store=store, check=False)
    assert refused.returncode == 2 and "--play applies with --results only" in refused.stderr
    refused = esr("sweep", str(suite), "--budget", "smoke", "--diagnose", store=store, check=False)
    assert refused.returncode == 2 and "--diagnose applies with --results only" in refused.stderr
    only_random = tmp_path / "random.yaml"
    only_random.write_text(f"name: r\nspecs: [{ROOT / 'experiments' / 'grid_2_random.yaml'}]\n")
    refused = esr("sweep", str(only_random), "--budget", "smoke", "--results", "--diagnose", store=store, check=False)
    assert refused.returncode == 2 and "diagnoses are of robots that learn a policy" in refused.stderr


def test_a_damaged_stored_diagnosis_prints_dashes(capsys):
    """`esr diagnose` prints a stored diagnosis (a cache hit, perhaps from an archive) with every
    field read typed: wrong types and missing parts print as '—', text as text."""
    from esr_cli.cli.runs import _print_gridworld_diagnosis, _print_play_check

    _print_play_check({"robot": {"episodes": "16", "return": [1], "reward": "x"}, "uniform": None, "[bold]x": {}})
    _print_gridworld_diagnosis({
        "reward": {"free": {"n": True, "mean": "1"}, "trapped": [], "dead": {"mean": float("nan")}},
        "free_vs_trapped": None,
        "start": "[red]corner\x1b[2J",
        "start_states": [{"human": [0, 4], "free": {"p": "1", "actions": 4.5}}, "not a row"],
        "representations": {"accuracy_phi": "0.9"},
    })
    text = capsys.readouterr().out
    assert "robot" in text and "[bold]x" not in text  # only the two players a play check has
    assert "too few transitions to compare (0 free, 0 trapped)" in text
    assert "[red]corner\\x1b[2J starts" in text  # the store's text as text, its escape shown, not sent
    assert "MI estimate (phi minus phi' diagonal logit): — nats" in text
    assert "1.000" not in text and "0.900" not in text  # no number made from text
