"""The PPO human as a stored artifact (esr_cli/recipes/ppo_humans.py) and the calibration command
(esr_cli/report/human_calibration.py), on budgets of seconds: built once then found, resumed
bit-identically after a stop, refused when it fails its checks, used by a training run, and
calibrated with returns a plain evaluation of the same human reproduces."""

import json
import math
import os
import shlex
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest
from conftest import ROOT, esr, esr_env
from rich.console import Console

from esr_cli.common import specs
from esr_cli.model.envs.overcooked import Overcooked
from esr_cli.model.humans import conv_actor_critic as cac, human_eval
from esr_cli.recipes import human_runs, ppo_humans, stored_humans
from esr_cli.report import human_calibration as hc
from esr_cli.storage.store import Store, StoreError

# 4 environments x 32 steps: 128 environment steps an update.
TINY = "human={kind: ppo, total_steps: %d, num_envs: 4, rollout_steps: 32, min_selfplay_return: 0, eval_episodes: 4, chunk_updates: %d}"
SPEC = "experiments/cramped_room.yaml"


def tiny(updates=8, chunk=4):
    return TINY % (128 * updates, chunk)


def params_of(path):
    return jax.tree.leaves(human_runs.load_params(path))


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    store = tmp_path_factory.mktemp("ppo-store")
    proc = esr("human", "build", SPEC, "-b", "smoke", "--set", tiny(), store=store)
    return store, proc


@pytest.mark.slow
def test_a_built_human_records_its_returns_and_curve_and_is_found_again(built):
    store, proc = built
    path = proc.stdout.strip().splitlines()[-1]
    manifest = json.loads(open(f"{path}/manifest.json").read())
    summary = manifest["summary"]
    assert summary["updates"] == 8 and summary["environment_steps"] == 8 * 128
    assert set(summary["partner_returns"]) == {"random", "stay", "self"}
    assert all(v["episodes"] == 4 for v in summary["partner_returns"].values())
    rows = [json.loads(line) for line in open(f"{path}/metrics.jsonl")]
    assert [r["update"] for r in rows] == list(range(1, 9))
    assert not list(Store(store).root.glob("humans/*/*/ppo_state.npz"))  # a finished human is its parameters
    again = esr("human", "build", SPEC, "-b", "smoke", "--set", tiny(), store=store)
    assert again.stdout.strip() == proc.stdout.strip() and "cache hit" in again.stderr


def test_the_chunk_size_is_not_part_of_the_key():
    spec_a = specs.load(SPEC, "smoke", [tiny(8, 4)])
    spec_b = specs.load(SPEC, "smoke", [tiny(8, 2)])
    spec_c = specs.load(SPEC, "smoke", [tiny(16, 4)])
    key = lambda s: stored_humans.stored_key(s.human, "cramped_room")[0]  # noqa: E731
    assert key(spec_a) == key(spec_b) != key(spec_c)


@pytest.mark.slow
def test_a_stopped_build_resumes_bit_identically(built, tmp_path):
    store, proc = built
    reference = params_of(proc.stdout.strip().splitlines()[-1])
    mine = tmp_path / "store"
    cmd = [sys.executable, "-m", "esr_cli.cli.main", "human", "build", SPEC, "-b", "smoke", "--set", tiny(8, 1)]
    run = subprocess.Popen(cmd, cwd=ROOT, env=esr_env(mine), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 300
        while not list(mine.glob("humans/*/*/ppo_state.npz")):
            assert run.poll() is None and time.time() < deadline, run.communicate()
            time.sleep(0.05)
        run.send_signal(signal.SIGINT)
        _, err = run.communicate(timeout=60)
    finally:
        run.kill()
    if run.returncode == 0:  # it finished before the signal: nothing was left to stop
        pytest.skip("the build ended before it could be stopped")
    assert run.returncode == 130 and "interrupted after update" in err and "checkpoint is saved" in err, err
    resumed = esr("human", "build", SPEC, "-b", "smoke", "--set", tiny(8, 1), store=mine)
    assert "resuming at update" in resumed.stderr
    again = params_of(resumed.stdout.strip().splitlines()[-1])
    assert all(np.array_equal(a, b) for a, b in zip(reference, again))


@pytest.mark.slow
def test_a_human_that_fails_its_checks_is_refused_with_one_line_and_leaves_nothing(tmp_path):
    demanding = tiny().replace("min_selfplay_return: 0", "min_selfplay_return: 1000")
    proc = esr("human", "build", SPEC, "-b", "smoke", "--set", demanding, store=tmp_path, check=False)
    assert proc.returncode != 0
    lines = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "refused" in lines[0] and "self-play return" in lines[0], proc.stderr
    assert not [p for p in tmp_path.glob("humans/*/*") if not p.name.endswith(".lock")]


def test_non_finite_parameters_are_a_problem():
    params = {"a": np.zeros(3), "b": np.array([1.0, np.nan])}
    assert "not all finite" in ppo_humans.params_problem(params)
    assert ppo_humans.params_problem({"a": np.zeros(3)}) is None


def test_a_random_partner_names_itself_in_the_key_and_reaches_the_trainer():
    plain = specs.load(SPEC, "smoke", [tiny()]).human
    beside = specs.load(SPEC, "smoke", [tiny(), "human.random_partner=1"]).human
    assert "random_partner" not in plain.training_part("cramped_room")  # humans from before the field keep their keys
    assert beside.training_part("cramped_room")["random_partner"] == 1.0
    assert ppo_humans.ppo_human_key(plain, "cramped_room")[0] != ppo_humans.ppo_human_key(beside, "cramped_room")[0]
    assert ppo_humans.ppo_config(beside).random_partner == 1.0 and ppo_humans.ppo_config(plain).random_partner == 0.0


@pytest.mark.slow
def test_a_checkpoint_of_another_shape_is_refused(tmp_path):
    trainer = ppo_humans.ppo.overcooked_ppo(Overcooked("cramped_room", 400), ppo_humans.ppo_config(specs.load(SPEC, "smoke", [tiny()]).human))
    runner = trainer.init(jax.random.PRNGKey(0))
    ppo_humans.save_checkpoint(tmp_path, runner, {"loss": [1.0]})
    restored, history = ppo_humans.load_checkpoint(tmp_path, runner)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(restored), jax.tree.leaves(runner)))
    assert history == {"loss": [1.0]}
    other = runner._replace(episode_return=np.zeros(7, np.float32))
    with pytest.raises(StoreError, match="does not hold this human's PPO state"):
        ppo_humans.load_checkpoint(tmp_path, other)


@pytest.mark.parametrize("put", ["link to /dev/zero", "fifo", "too large"])
def test_a_stored_humans_files_are_read_as_regular_files_of_bounded_size(tmp_path, monkeypatch, put):
    """A human's params.msgpack and human data's data.npz, replaced by hand with a link to
    /dev/zero (read until memory ran out), a FIFO (waited on for ever) or a file larger than esr
    writes, are refused in one line naming the file; a PPO checkpoint likewise."""
    monkeypatch.setattr(human_runs, "MAX_PARAMS_BYTES", 1000)
    monkeypatch.setattr(human_runs, "MAX_DATA_BYTES", 1000)
    for name, load in ((human_runs.PARAMS_FILE, human_runs.load_params), (human_runs.DATA_FILE, human_runs.load_data),
                       (ppo_humans.CHECKPOINT_FILE, lambda p: ppo_humans.load_checkpoint(p, {"w": np.zeros(3)}))):
        folder = tmp_path / name
        folder.mkdir()
        if put == "link to /dev/zero":
            (folder / name).symlink_to("/dev/zero")
        elif put == "fifo":
            os.mkfifo(folder / name)
        else:
            (folder / name).write_bytes(b"\0" * (64 << 20) + b"\0" * 2000 if name == ppo_humans.CHECKPOINT_FILE else b"\0" * 2000)
        signal.alarm(20)  # a regression would block on the FIFO: the alarm ends the test
        try:
            with pytest.raises(StoreError) as refused:
                load(folder)
        finally:
            signal.alarm(0)
        said = str(refused.value)
        assert str(folder / name) in said and "\n" not in said
        assert any(w in said for w in ("a link, not a regular file", "not a regular file", "more than the")), said


def test_an_npz_is_read_only_to_the_size_its_arrays_may_unpack_to(tmp_path):
    """A compressed .npz of a few KiB may unpack to gigabytes: its members' declared sizes are
    summed before anything is unpacked; pickled objects are never read."""
    from esr_cli.common import bounded_files

    np.savez_compressed(tmp_path / "small.npz", a=np.zeros(10_000, np.uint8))
    assert (tmp_path / "small.npz").stat().st_size < 1000
    assert bounded_files.load_npz(tmp_path / "small.npz", 20_000)["a"].shape == (10_000,)
    with pytest.raises(bounded_files.UnreadableInput, match=r"^unpacks to 10,\d{3} bytes, more than the 5,000 esr reads$"):
        bounded_files.load_npz(tmp_path / "small.npz", 5000)
    np.savez(tmp_path / "objects.npz", a=np.array([{"x": 1}], dtype=object))
    with pytest.raises(bounded_files.UnreadableInput, match="'a.npy' holds Python objects, not a plain array"):
        bounded_files.load_npz(tmp_path / "objects.npz", 1 << 20)
    # A header declaring 800 GB over 16 bytes: numpy would allocate it before reading a byte.
    import io
    import zipfile

    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (10**11,)})
    with zipfile.ZipFile(tmp_path / "claims.npz", "w") as z:
        z.writestr("a.npy", header.getvalue() + b"\0" * 16)
    with pytest.raises(bounded_files.UnreadableInput, match=r"'a.npy' declares 800,000,000,000 bytes of array in a member of \d+"):
        bounded_files.load_npz(tmp_path / "claims.npz", 1 << 20)


@pytest.mark.slow
def test_a_robot_trains_with_the_ppo_human_and_its_key_names_the_human(built):
    store, proc = built
    run = esr("train", "experiments/cramped_room_random.yaml", "-b", "smoke", "--set", tiny(), store=store)
    run_path = run.stdout.strip().splitlines()[-1]
    manifest = json.loads(open(f"{run_path}/manifest.json").read())
    human_key = proc.stdout.strip().splitlines()[-1].rsplit("/", 1)[-1]
    assert manifest["key_components"]["dependencies"]["humans"] == human_key


@pytest.mark.slow
def test_calibration_rows_are_plain_evaluations_of_the_stored_humans(built):
    store, _ = built
    proc = esr("human", "calibrate", SPEC, "-b", "smoke", "--set", tiny(), "--human-seeds", "2", "--episodes", "3", "--json",
               store=store)
    report = json.loads(proc.stdout)
    (row,) = report["rows"]
    assert row["layout"] == "cramped_room" and row["paper_random"] == pytest.approx(69.26) and len(row["keys"]) == 2
    assert report["score"] is None  # one layout of three
    env = Overcooked("cramped_room", 400)
    for i, key in enumerate(row["keys"]):
        params = human_runs.load_params(next(Store(store).root.glob(f"humans/*/{key}")))
        for partner in hc.PARTNERS:
            r = human_eval.episode_returns(env, cac.policy_logits, params, partner, 3, jax.random.PRNGKey(i))
            assert row["returns"][partner]["per_human"][i] == pytest.approx(float(r.mean()))
    for partner in hc.PARTNERS:
        per = row["returns"][partner]["per_human"]
        assert row["returns"][partner]["mean"] == pytest.approx(np.mean(per))
        assert row["returns"][partner]["se"] == pytest.approx(np.std(per, ddof=1) / math.sqrt(2))


@pytest.mark.slow
def test_a_calibration_is_stored_answered_again_from_the_store_and_drawn_in_a_page(built, tmp_path):
    store, _ = built
    args = ("human", "calibrate", SPEC, "-b", "smoke", "--set", tiny(), "--human-seeds", "2", "--episodes", "3", "--markdown")
    first = esr(*args, store=store)
    again = esr(*args, store=store)
    assert again.stdout == first.stdout and "cache hit: cramped_room's calibration" in again.stderr
    assert len(list(Store(store).root.glob("calibrations/*/*/manifest.json"))) == 1
    page = tmp_path / "page.md"
    command = f"esr human calibrate {SPEC} -b smoke --set {shlex.quote(tiny())} --human-seeds 2 --episodes 3 --markdown"
    page.write_text(f"# Humans\n<!-- {command} -->\n<!-- end of generated table -->\n")
    esr("tables", str(page), store=store)
    assert page.read_text() == f"# Humans\n<!-- {command} -->\n{first.stdout.strip()}\n<!-- end of generated table -->\n"
    assert esr("tables", str(page), "--check", store=store).returncode == 0


def test_the_selection_rule_scores_the_mean_absolute_log_ratio():
    def row(layout, mean):
        returns = {p: {"mean": mean, "se": 0.0, "per_human": [mean]} for p in hc.PARTNERS}
        return hc.Row("x", layout, "h", [], returns, {"cramped_room": 69.26, "coord_ring": 6.02, "asymm_advantages": 59.36}[layout])

    rows = [row("cramped_room", 69.26 * 2), row("coord_ring", 6.02 / 2), row("asymm_advantages", 59.36)]
    assert hc.score(rows) == pytest.approx(2 * math.log(2) / 3)
    assert hc.score(rows[:2]) is None
    assert hc.score([row("cramped_room", 0.0), *rows[1:]]) == math.inf
    assert [hc.within_target(r) for r in rows] == [False, False, True]
    assert hc.within_target(row("coord_ring", 6.02 * 1.4)) and not hc.within_target(row("cramped_room", 69.26 * 1.2))


@pytest.mark.parametrize("sets, message", [
    (["human={kind: ppo, mode: shaped, clone: {kind: bc}}"], "human.clone is the policy of mode bc_kl"),
    (["human={kind: ppo, mode: bc_kl, clone: {kind: bc, preset: paper_random}}"], "written out field by field"),
    (["human={kind: ppo, mode: sparse}"], "human.mode"),
    (["human={kind: ppo, layout: coord_ring}"], "differs from env.layout"),
])
def test_bad_ppo_human_specs_are_refused(sets, message):
    with pytest.raises(specs.SpecError, match=message):
        specs.load(SPEC, "smoke", sets)


def test_a_ppo_human_needs_overcooked():
    with pytest.raises(specs.SpecError, match="needs env.kind: overcooked"):
        specs.load("experiments/grid_2.yaml", "smoke", ["human={kind: ppo}"])


def test_bc_kl_keys_on_its_clone_and_requires_it():
    spec = specs.load(SPEC, "smoke", ["human={kind: ppo, mode: bc_kl, clone: {kind: bc, epochs: 3}}"])
    other = specs.load(SPEC, "smoke", ["human={kind: ppo, mode: bc_kl, clone: {kind: bc, epochs: 4}}"])
    key, components = stored_humans.stored_key(spec.human, "cramped_room")
    clone_key = human_runs.human_key(spec.human.clone, "cramped_room")[0]
    assert components["dependencies"] == {"humans": clone_key}
    assert key != stored_humans.stored_key(other.human, "cramped_room")[0]
    recipe = stored_humans.stored_recipe(spec.human, "cramped_room", Console(stderr=True))
    assert [r.key for r in recipe.requires] == [clone_key]
    plain = specs.load(SPEC, "smoke", ["human={kind: ppo, mode: shaped}"])
    assert stored_humans.stored_key(plain.human, "cramped_room")[1]["dependencies"] == {}


@pytest.mark.slow
def test_the_calibration_command_refuses_a_human_that_is_not_stored(tmp_path):
    proc = esr("human", "calibrate", "experiments/grid_2.yaml", "-b", "smoke", store=tmp_path, check=False)
    assert proc.returncode == 2 and "not a stored human" in proc.stderr
    proc = esr("human", "calibrate", SPEC, SPEC, "-b", "smoke", store=tmp_path, check=False)
    assert proc.returncode == 2 and "share a layout" in proc.stderr
    proc = esr("human", "calibrate", SPEC, "--json", "--markdown", store=tmp_path, check=False)
    assert proc.returncode == 2 and proc.stderr.strip() == "error: --json and --markdown: choose one" and not tmp_path.joinpath("runs").exists()
