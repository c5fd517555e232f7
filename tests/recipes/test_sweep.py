"""`esr sweep`: suites expand into runs, go through submitit's local executor, are skipped once
committed, and report their state. Four smoke runs of one spec share one compiled program
(the session's compile cache, warmed by `smoke_run`), which keeps this file fast."""

import json
import os
import pickle
import shlex
from pathlib import Path

import pytest
from conftest import ROOT, esr
from rich.console import Console

from esr_cli.common import specs
from esr_cli.recipes import sweep
from esr_cli.recipes.suite import SuiteError
from esr_cli.storage import provenance
from esr_cli.storage.store import Store

GRID_2 = ROOT / "experiments" / "grid_2.yaml"
WIDE = {"COLUMNS": "400"}  # rich wraps at 80 columns when not on a terminal


def write_suite(tmp_path: Path, text: str, name: str = "suite.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def seeds_suite(tmp_path: Path, n: int, name: str = "suite.yaml") -> Path:
    seeds = ", ".join(f"[{i}]" for i in range(n))
    return write_suite(tmp_path, f"name: seeds\nspecs: [{GRID_2}]\ngrid: {{train.seeds: [{seeds}]}}\n", name)


def test_suite_expands_list_and_grid(tmp_path):
    # Paths are relative to the suite file; an entry's grid multiplies the suite's grid.
    (tmp_path / "sub").mkdir()
    rel = os.path.relpath(GRID_2, tmp_path / "sub")
    path = write_suite(tmp_path / "sub", f"""
specs:
  - {rel}
  - {{spec: {rel}, set: {{learner.gamma: 0.0}}, grid: {{learner.lr: [1.0e-3, 3.0e-4]}}}}
  - {rel}
set: {{train.epochs: 3}}
grid: {{train.seeds: [[0], [1]]}}
""")
    suite = sweep.load_suite(path, "smoke")
    assert suite.name == "suite" and suite.budget == "smoke"
    # 2 (first entry) + 2 x 2 (second) runs; the third entry repeats the first and is dropped.
    assert len(suite.runs) == 6 and suite.duplicates == 2
    assert len({r.key for r in suite.runs}) == 6
    assert all(r.spec.train.epochs == 3 for r in suite.runs)
    second = [r for r in suite.runs if r.spec.learner.gamma == 0.0]
    assert sorted((r.spec.learner.lr, r.spec.train.seeds) for r in second) == [
        (3e-4, (0,)), (3e-4, (1,)), (1e-3, (0,)), (1e-3, (1,))]
    assert second[0].sets[0] == "train.epochs=3" and "learner.gamma=0.0" in second[0].sets
    # A top-level list is short for `specs:`.
    short = sweep.load_suite(write_suite(tmp_path, f"- {GRID_2}\n", "short.yaml"), "smoke")
    assert [r.spec.name for r in short.runs] == ["grid_2"] and short.runs[0].sets == ()


def test_a_spec_file_named_by_many_entries_is_read_once(tmp_path, monkeypatch):
    """Expanding a suite reads each spec file (and its chain of `extends`) once, however many
    entries name it: 40 entries of one file that extends another cost one read of each."""
    (tmp_path / "base.yaml").write_text(GRID_2.read_text())
    (tmp_path / "child.yaml").write_text("extends: base.yaml\nname: child\n")
    read = []
    for name in ("_read_yaml", "_read_extended"):
        real = getattr(specs, name)
        monkeypatch.setattr(specs, name, lambda path, real=real: read.append(Path(path).name) or real(path))
    entries = "".join(f"  - {{spec: child.yaml, set: {{train.seeds: [{i}]}}}}\n" for i in range(40))
    suite = sweep.load_suite(write_suite(tmp_path, f"specs:\n{entries}"), "smoke")
    assert len(suite.runs) == 40 and {r.spec.name for r in suite.runs} == {"child"}
    assert sorted(read) == ["base.yaml", "child.yaml"]


def test_paper_gridworld_suite_lists_every_method_on_the_four_settings():
    suite = sweep.load_suite(ROOT / "experiments" / "suites" / "gridworld.yaml", "paper")
    pairs = {(r.spec.method.kind, r.spec.env.blocks) for r in suite.runs}
    kinds = {"esr", "random", "ave", "goal_inference", "iq_learn", "oracle"}
    assert len(suite.runs) == 24 and pairs == {(k, n) for k in kinds for n in (2, 5, 7, 10)}
    assert all(len(r.spec.train.seeds) == 20 for r in suite.runs)
    assert suite.slurm.gpus == 1


@pytest.mark.parametrize("path", sorted((ROOT / "experiments" / "suites").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_suite_in_experiments_loads_at_the_quick_budget(path):
    assert sweep.load_suite(path, "quick").runs


def test_the_calibrated_human_suite_puts_the_preset_human_behind_every_robot():
    suite = sweep.load_suite(ROOT / "experiments" / "suites" / "overcooked_calibrated.yaml", "quick")
    kinds = {(r.spec.env.layout, r.spec.method.kind) for r in suite.runs}
    assert kinds == {(layout, k) for layout in ("cramped_room", "coord_ring", "asymm_advantages")
                     for k in ("random", "esr", "ave", "iq_learn")}
    humans = {r.spec.env.layout: r.spec.human for r in suite.runs}
    assert humans["cramped_room"].kind == "ppo" and humans["cramped_room"].random_partner == 0.5
    assert humans["coord_ring"].kind == "bc" and humans["coord_ring"].stay_weight == 1
    assert all(r.spec.method.variant == "original" for r in suite.runs if r.spec.method.kind == "ave")
    assert all(len(r.spec.train.seeds) == 3 for r in suite.runs)


def test_baselines_quick_suite_is_every_method_on_grid_2_and_grid_5_with_five_seeds():
    suite = sweep.load_suite(ROOT / "experiments" / "suites" / "baselines_quick.yaml", "quick")
    kinds = {"esr", "random", "ave", "goal_inference", "iq_learn", "oracle"}
    assert {(r.spec.method.kind, r.spec.env.blocks) for r in suite.runs} == {(k, n) for k in kinds for n in (2, 5)}
    assert all(len(r.spec.train.seeds) == 5 and r.spec.train.epochs == 150 for r in suite.runs)


@pytest.mark.parametrize("text, where, problem", [
    ("specs: []\n", "specs", "at least 1"),
    (f"specs: [{GRID_2}]\nexecutor: slurm\n", "executor", "unknown key"),
    (f"specs: [{GRID_2}]\ngrid: {{train.seeds: 3}}\n", "grid", "train.seeds: a grid needs a non-empty list"),
    (f"specs: [{GRID_2}]\nset: {{'train..seeds': 3}}\n", "set", "not a key path"),
    # written into `--set KEY=VALUE` text, an '=' or a '#' in a key would set another field
    (f"specs: [{GRID_2}]\nset: {{'train.seeds=3 #': 1}}\n", "set", "not a key path"),
    (f"specs: [{{spec: {GRID_2}, grid: {{'train.seeds=[5] #': [1]}}}}]\n", "specs[0].grid", "not a key path"),
    (f"specs: [{GRID_2}]\nset: {{'train.ep[ochs': 3}}\n", "set", "not a key path"),
    ('specs: ["a\\0b.yaml"]\n', "specs[0].spec", "cannot hold a NUL"),
    ("specs: [no_such_spec.yaml]\n", "specs[0].spec", "file not found (a suite's spec paths are read from the suite file's folder"),
    (f"specs: [{GRID_2}]\ngrid: {{learner.gamma: [0.5, 2.0]}}\n", "specs[0]", "learner.gamma: Input should be less than 1"),
    (f"specs: [{GRID_2}]\nset: {{method.no_such_field: 1}}\n", "specs[0]", "method.no_such_field: unknown key"),
    (f"specs: [{GRID_2}]\nslurm: {{gpus: -1}}\n", "slurm.gpus", "greater than or equal to 0"),
    ("just a string\n", "", "a suite is a mapping"),
    ("specs: [unclosed\n", "", "unreadable YAML"),
    (f"specs: [{GRID_2}]\nslrum: {{gpus: 1}}\n", "slrum", "unknown key; did you mean `slurm`?"),
    (f"specs: [{GRID_2}]\nslurm: {{gpu: 1}}\n", "slurm.gpu", "unknown key; did you mean `gpus`?"),
    (f"specs: [{{spce: {GRID_2}}}]\n", "specs[0].spce", "unknown key; did you mean `spec`?"),
    ("name: t\nenv: {kind: gridworld}\nmethod: {kind: esr}\n", "", "this is a spec file, not a suite"),
    (f"specs: [{ROOT / 'experiments/suites/gridworld.yaml'}]\n", "specs[0].spec", "is a suite, not a spec file"),
    (f"specs: [{GRID_2}]\nslurm: {{setup: 'module load x'}}\n", "slurm.setup", "expected a list"),
    (f"specs: [{GRID_2}]\nset: {{1: 2}}\n", "", "the key 1 is a number, not a name"),
    # one field set twice at one level: which would win depends only on the order of the keys
    (f"specs: [{GRID_2}]\nset: {{train: {{epochs: 2}}, train.epochs: 9}}\n", "",
     "train (in set) and train.epochs (in set) both set train.epochs: keep one"),
    (f"specs: [{{spec: {GRID_2}, set: {{train.epochs: 2}}, grid: {{train: [{{epochs: 3}}]}}}}]\n", "specs[0]",
     "train (in grid) replaces what train.epochs (in set) sets (train.epochs), which then never counts: keep one"),
    # the suite's grid applies after an entry's set: the entry's value would be lost
    (f"specs: [{{spec: {GRID_2}, set: {{train.seeds: 3}}}}]\ngrid: {{train.seeds: [1, 2]}}\n", "specs[0]",
     "train.seeds (in the suite's grid) replaces what train.seeds (in this entry's set) sets (train.seeds)"),
    # a kind set first, then fields of that kind crossed: each point refines the section
    (f"specs: [{GRID_2}]\nset: {{train.seeds: 3, method: {{kind: ave}}}}\ngrid: {{method.repr_dim: [1, 2]}}\n", "specs[0]",
     "method.repr_dim: unknown key"),
])
def test_bad_suites_name_the_key(tmp_path, text, where, problem):
    path = write_suite(tmp_path, text)
    with pytest.raises(SuiteError) as e:
        sweep.load_suite(path, "smoke")
    assert e.value.path == where and problem in str(e.value), str(e.value)
    assert str(path) in str(e.value)


def test_a_bad_value_from_a_file_a_spec_extends_is_named_with_that_file_and_budget(tmp_path):
    """As `esr train` names it: the suite entry, then the file (and budget entry) that wrote the value."""
    (tmp_path / "base.yaml").write_text(GRID_2.read_text() + "budgets: {smoke: {method.repr_dimm: 3}}\n")
    (tmp_path / "child.yaml").write_text("name: child\nextends: base.yaml\n")
    (tmp_path / "grand.yaml").write_text("name: grand\nextends: broken.yaml\n")
    (tmp_path / "broken.yaml").write_text("env: [unclosed\n")
    with pytest.raises(SuiteError) as e:
        sweep.load_suite(write_suite(tmp_path, "specs: [child.yaml]\n"), "smoke")
    assert e.value.path == "specs[0]"
    assert f"child.yaml: {tmp_path / 'base.yaml'} (extended by {tmp_path / 'child.yaml'}), budgets.smoke: " \
           "method.repr_dimm: unknown key" in str(e.value), str(e.value)
    with pytest.raises(specs.SpecError, match=r"base.yaml \(extended by .*child.yaml\), budgets.smoke: method.repr_dimm"):
        specs.load(tmp_path / "child.yaml", "smoke")  # the same words
    with pytest.raises(SuiteError) as e:
        sweep.load_suite(write_suite(tmp_path, "specs: [grand.yaml]\n"), "smoke")
    assert e.value.path == "specs[0].spec" and f"grand.yaml: {tmp_path / 'broken.yaml'}: not a spec file" in str(e.value)
    # the spec's own budget entry by the entry alone; a value of the suite's own --set once
    (tmp_path / "own.yaml").write_text(GRID_2.read_text() + "budgets: {smoke: {train.epochz: 1}}\n")
    with pytest.raises(SuiteError) as e:
        sweep.load_suite(write_suite(tmp_path, "specs: [own.yaml]\n"), "smoke")
    assert str(e.value).endswith("specs[0]: own.yaml: budgets.smoke: train.epochz: unknown key; did you mean `epochs`?")
    with pytest.raises(SuiteError) as e:
        sweep.load_suite(write_suite(tmp_path, f"specs: [{GRID_2}]\ngrid: {{learner.gamma: [2.0]}}\n"), "smoke")
    assert str(e.value).endswith(f"specs[0]: {GRID_2} with learner.gamma=2.0: learner.gamma: Input should be less than 1")


def test_a_grid_over_the_method_kind_starts_the_section_again(tmp_path):
    """As `--set method.kind=random` does: ESR's fields do not follow into the Random robot."""
    path = write_suite(tmp_path, f"specs: [{GRID_2}]\ngrid: {{method.kind: [esr, random]}}\n")
    runs = sweep.load_suite(path, "smoke").runs
    assert [r.spec.method.kind for r in runs] == ["esr", "random"]
    assert runs[1].spec.training_part() == specs.load(ROOT / "experiments/grid_2_random.yaml", "smoke").training_part()


@pytest.mark.slow
def test_bad_suite_exits_2_before_any_work(tmp_path):
    store = tmp_path / "store"
    path = write_suite(tmp_path, f"specs: [{GRID_2}]\ngrid: {{learner.gamma: [0.5, 2.0]}}\n")
    proc = esr("sweep", str(path), "--budget", "smoke", "--executor", "submitit-local", store=store, check=False, **WIDE)
    assert proc.returncode == 2
    assert "bad suite" in proc.stderr and "specs[0]" in proc.stderr and "learner.gamma" in proc.stderr
    assert not store.exists()
    proc = esr("sweep", str(seeds_suite(tmp_path, 1)), "--executor", "nope", store=store, check=False, **WIDE)
    assert proc.returncode == 2 and "unknown executor 'nope'" in proc.stderr and not store.exists()


@pytest.mark.slow
def test_a_local_sweep_checks_every_runs_memory_before_the_first_trains(tmp_path):
    """The second run would not fit: the sweep stops before the first one trains."""
    store = tmp_path / "store"
    path = write_suite(tmp_path, f"specs: [{GRID_2}]\ngrid: {{learner.buffer_size: [1000, 50000000000]}}\n")
    proc = esr("sweep", str(path), "--budget", "smoke", store=store, check=False, **WIDE)
    assert proc.returncode == 2, proc.stderr
    assert "too large for this machine" in proc.stderr and "learner.buffer_size=50000000000" in proc.stderr
    assert "nothing of the suite has run" in proc.stderr
    assert not list(store.rglob("*.partial")) and not list(store.rglob("manifest.json"))


@pytest.mark.slow
def test_sweep_through_submitit_local(smoke_run, tmp_path):
    # smoke_run compiled grid_2's smoke program into the session cache; the two jobs reuse it.
    store = tmp_path / "store"
    path = seeds_suite(tmp_path, 2)
    proc = esr("sweep", str(path), "--budget", "smoke", "--executor", "submitit-local", store=store, **WIDE)
    assert "0 done, 0 running or queued, 2 to submit" in proc.stderr
    assert "2 of 2 run(s) done; 2 submitted this time" in proc.stderr
    paths = [Path(p) for p in proc.stdout.split()]
    assert len(set(paths)) == 2
    seeds = sorted(json.loads((p / "manifest.json").read_text())["seeds"] for p in paths)
    assert seeds == [[0], [1]]

    # Each run went through its own submitit job, recorded in the sweep's state file.
    (state_file,) = (store / "sweeps").glob("seeds-smoke-*.json")
    state = json.loads(state_file.read_text())
    assert len(state["jobs"]) == 2 and {j["executor"] for j in state["jobs"].values()} == {"submitit-local"}
    logs = state_file.parent / "logs" / state_file.stem
    job_dirs = sorted(d.name for d in logs.iterdir() if d.name != "%j")  # submitit's own template dir
    assert job_dirs == sorted(j["job_id"] for j in state["jobs"].values())
    for d in job_dirs:  # submitit's result, and the job's own outcome record that status reads
        assert (logs / d / f"{d}_0_result.pkl").exists()
        assert json.loads(sweep.outcome_path(logs / d, d).read_text())["outcome"] == "success"

    # Again: everything is committed, so nothing is submitted and the state file is untouched.
    before = state_file.read_text()
    again = esr("sweep", str(path), "--budget", "smoke", "--executor", "submitit-local", store=store, **WIDE)
    assert "2 done, 0 running or queued, 0 to submit" in again.stderr
    assert "0 submitted this time" in again.stderr
    assert [Path(p) for p in again.stdout.split()] == paths
    assert state_file.read_text() == before
    assert sorted(d.name for d in logs.iterdir() if d.name != "%j") == job_dirs

    # --status: all done, as JSON and as a table.
    rows = json.loads(esr("sweep", str(path), "--budget", "smoke", "--status", "--json", store=store).stdout)
    assert [r["state"] for r in rows] == ["done"] * 2
    assert [Path(r["path"]) for r in rows] == paths
    table = esr("sweep", str(path), "--budget", "smoke", "--status", store=store, **WIDE).stdout
    assert "suite seeds (smoke): 2 done" in table
    assert sum(" done " in line for line in table.splitlines() if "│" in line) == 2

    # The importable API (for paper figures), local executor, one seed more: the two
    # committed runs are skipped and only the third trains, here in this process. Keys are
    # computed afresh, as a new `esr` process would (this one cached its code digest earlier).
    provenance.code_digest.cache_clear()
    three = seeds_suite(tmp_path, 3, "three.yaml")
    result = sweep.run_suite(three, "smoke", "local", Store(store), Console(stderr=True, quiet=True))
    assert result.paths[:2] == paths and result.complete and len(result.skipped) == 2
    assert [run.spec.train.seeds for run, _ in result.submitted] == [(2,)] and result.failed == []
    assert json.loads((result.paths[2] / "manifest.json").read_text())["seeds"] == [2]

    # --results: each run's final return and success, read from its metrics. A smoke run has 2
    # epochs, so "the last 10% of epochs" is the last one; one seed has no spread.
    rows = json.loads(esr("sweep", str(three), "--budget", "smoke", "--results", "--json", store=store).stdout)
    assert [r["state"] for r in rows] == ["done"] * 3 and [r["seeds"] for r in rows] == [1] * 3
    for r, p in zip(rows, result.paths):
        last = json.loads((p / "metrics.jsonl").read_text().splitlines()[-1])
        assert r["return"] == {"mean": pytest.approx(last["return"][0]), "se": 0.0, "seeds": 1,
                               "per_seed": [pytest.approx(last["return"][0])]}  # one seed: no IQM interval
        assert r["success"]["mean"] == pytest.approx(last["success"][0]) and r["path"] == str(p)
    md = esr("sweep", str(three), "--budget", "smoke", "--results", "--markdown", store=store).stdout
    assert "| run | method | seeds | return | success | wall |" in md
    assert sum(line.startswith("| grid_2 train.seeds=") for line in md.splitlines()) == 3
    assert "(1 seed)" in md and "±" not in md.split("|---|")[-1]  # one seed: no standard error shown
    # --metric: any logged metric; one the run does not log (ESR's with inferred human actions)
    # is shown as a dash, not invented; one no run can log is refused.
    md = esr("sweep", str(three), "--budget", "smoke", "--results", "--markdown", "--metric", "mi_estimate",
             "--metric", "code_accuracy", store=store).stdout
    assert "| run | method | seeds | mi_estimate | code_accuracy | wall |" in md
    bad = esr("sweep", str(three), "--budget", "smoke", "--results", "--metric", "no_such_metric", store=store, check=False)
    assert bad.returncode == 2 and "unknown metric 'no_such_metric'; known: return, success" in bad.stderr
    last = json.loads((result.paths[0] / "metrics.jsonl").read_text().splitlines()[-1])
    first_row = next(line for line in md.splitlines() if line.startswith("| grid_2 train.seeds="))
    assert f"| {last['mi_estimate'][0]:.3f} (1 seed) | — |" in first_row
    # --eval: each run's stored evaluation beside its finals, the command for each missing one
    evaluated = Path(esr("eval", result.paths[0].name[:8], store=store).stdout.strip().splitlines()[-1])
    mode = next(iter(json.loads((evaluated / "summary.json").read_text())["results"].values()))
    md = esr("sweep", str(three), "--budget", "smoke", "--results", "--markdown", "--eval", store=store).stdout
    assert "| wall | eval return, training human (first policy mode) | eval return, held-out proxy human" in md
    rows_md = [line for line in md.splitlines() if line.startswith("| grid_2 train.seeds=")]
    assert f"| {mode['return_per_seed'][0]:.2f} (1 seed) |  |" in rows_md[0]  # a gridworld human has no proxy
    assert rows_md[1].endswith("| — |  |") and f"esr eval {result.paths[1].name[:8]} --episodes " in md
    assert f"esr eval {result.paths[0].name[:8]}" not in md

    # --plot: their learning curves and table as a figures artifact naming every run it read.
    proc = esr("sweep", str(three), "--budget", "smoke", "--results", "--plot", store=store, **WIDE)
    fig_dir = Path(proc.stderr.split("drawn: ")[1].split()[0]).parent
    side = json.loads((fig_dir / "suite.json").read_text())
    assert side["artifacts"]["runs"] == [p.name for p in result.paths] and side["budget"] == "smoke"
    assert (fig_dir / "suite.png").stat().st_size > 0 and (fig_dir / "suite.pdf").exists()
    assert sum(line.startswith("| grid_2 train.seeds=") for line in (fig_dir / "table.md").read_text().splitlines()) == 3
    again = esr("sweep", str(three), "--budget", "smoke", "--results", "--plot", store=store, **WIDE)
    assert f"cache hit: {fig_dir / 'suite.png'}" in again.stderr


def test_status_says_a_diverged_run_diverged_and_not_to_resume_it(tmp_path):
    store = Store(tmp_path / "store")
    suite = sweep.load_suite(seeds_suite(tmp_path, 1), "smoke")
    what = "critic_loss became nan at seed 0, epoch 3"
    store.begin("runs", suite.runs[0].key, {"diverged": {"epoch": 3, "what": what, "at": "2026-12-07T00:00:00+0000"}})
    (row,) = sweep.status(suite, store)
    assert row.state == "failed" and row.note.startswith(f"diverged: {what}; training is deterministic")
    assert "resume" not in row.note
    # a sweep names it and leaves it: it would only diverge again (nothing is trained here)
    result = sweep.run_suite(suite, "smoke", "local", store)
    assert result.submitted == [] and [(r.key, m.split(";")[0]) for r, m in result.failed] == [(suite.runs[0].key, f"diverged: {what}")]


def test_status_tells_running_failed_queued_missing(tmp_path):
    store = Store(tmp_path / "store")
    suite = sweep.load_suite(seeds_suite(tmp_path, 6), "smoke")
    r = suite.runs
    # 0: a partial run that nobody holds (a killed writer) -> failed.
    store.partial_path("runs", r[0].key).mkdir(parents=True)
    # 2: a job that raised; 3: a job whose process is alive but has not taken the lock yet;
    # 5: a job that reached its time budget and saved its run at a chunk boundary. Each job's
    # outcome record is what the job itself writes (train_job) in its folder under the store.
    folder = store.root / "sweeps" / "logs" / "x" / "%j"
    sweep._record_jobs(store, suite, "submitit-local",
                       [(r[2], "999999", folder), (r[3], str(os.getpid()), folder), (r[5], "999998", folder)])
    for job, outcome in (("999999", {"outcome": "error", "error": "ValueError: boom"}),
                         ("999998", {"outcome": "stopped", "epoch": 1, "total": 2})):
        record = sweep.outcome_path(folder.parent / job, job)
        record.parent.mkdir(parents=True)
        record.write_text(json.dumps({"job_id": job, **outcome}))
    store.partial_path("runs", r[5].key).mkdir(parents=True)
    # 1: its lock is held (flock conflicts between two open files, even in one process).
    with store.lock("runs", r[1].key):
        rows = sweep.status(suite, store)
    assert [row.state for row in rows] == ["failed", "running", "failed", "running", "missing", "stopped"]
    assert "no live writer" in rows[0].note
    assert f"pid {os.getpid()}" in rows[1].note
    assert "job 999999" in rows[2].note and "ValueError: boom" in rows[2].note
    assert rows[5].note == "job 999998: stopped at its time budget after epoch 1 of 2; sweep again to continue"
    # Once the lock is free again, run 1 (no partial, no job) is missing.
    assert sweep.status(suite, store)[1].state == "missing"
    table = sweep.status_table(suite, rows)
    assert table.row_count == 6 and "2 failed" in str(table.title) and "1 stopped" in str(table.title)
    # --results names what is not done, with the command that makes it, and reads nothing else.
    res = sweep.results(suite, store)
    assert [row["state"] for row in res] == ["failed", "missing", "failed", "running", "missing", "stopped"]
    # the command reaches this store, which is not the default one
    assert res[4]["command"] == f"esr --store {store.root} train {GRID_2} --budget smoke --set 'train.seeds=[4]'"
    assert "return" not in res[4]


class Planted:
    """A pickle that, once loaded, runs a shell command: what anyone who can write into a
    shared store could leave there for the next `esr sweep --status` to load."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_status_never_unpickles_what_it_finds_in_the_store(tmp_path):
    store = Store(tmp_path / "store")
    suite = sweep.load_suite(seeds_suite(tmp_path, 3), "smoke")
    r = suite.runs
    outside, inside = tmp_path / "elsewhere" / "%j", store.root / "sweeps" / "logs" / "x" / "%j"
    markers = [tmp_path / f"ran-{i}" for i in range(2)]
    # 0: the state file points at a planted result pickle outside the store; 1: one inside the
    # store's sweeps/ folder, with no outcome record beside it; 2: a job folder reached through
    # a link that leaves the store.
    (store.root / "sweeps" / "logs").mkdir(parents=True)
    (store.root / "sweeps" / "logs" / "link").symlink_to(tmp_path / "elsewhere")
    for folder, marker in zip((outside, inside), markers):
        pkl = folder.parent / "4242" / "4242_0_result.pkl"
        pkl.parent.mkdir(parents=True, exist_ok=True)
        pkl.write_bytes(pickle.dumps(("success", Planted(marker))))
    sweep._record_jobs(store, suite, "submitit-local", [(r[0], "4242", outside), (r[1], "4242", inside),
                                                         (r[2], "4242", store.root / "sweeps" / "logs" / "link" / "%j")])
    rows = sweep.status(suite, store)
    assert not any(m.exists() for m in markers)
    assert [row.state for row in rows] == ["missing"] * 3
    area = os.path.realpath(store.root / "sweeps")
    assert rows[0].note == f"job record refused: its job folder {outside} is outside {area}; not read"
    assert rows[1].note == "job 4242 ENDED: finished without esr's outcome record (its submitit result is not read)"
    assert rows[2].note.startswith("job record refused: its job folder") and "is outside" in rows[2].note
    # Through the command: one line per run, and still nothing ran.
    table = esr("sweep", str(suite.path), "--budget", "smoke", "--status", store=store.root, **WIDE).stdout
    assert "suite seeds (smoke): 3 missing" in table and table.count("job record refused") == 2
    assert not any(m.exists() for m in markers)


def test_a_damaged_job_record_is_named_not_followed(tmp_path):
    store = Store(tmp_path / "store")
    suite = sweep.load_suite(seeds_suite(tmp_path, 2), "smoke")
    state = {"jobs": {suite.runs[0].key: {"job_id": "../../x", "folder": str(store.root / "sweeps" / "%j"), "executor": "slurm"},
                      suite.runs[1].key: ["not", "a", "record"]}}
    sweep.state_path(store, suite).parent.mkdir(parents=True)
    sweep.state_path(store, suite).write_text(json.dumps(state))
    rows = sweep.status(suite, store)
    assert [(row.state, row.note) for row in rows] == [("missing", "job record refused: its job record is damaged; not read")] * 2


def test_a_job_that_raises_records_its_error_for_status(tmp_path, monkeypatch):
    # The environment submitit-local gives a job: its id and its folder under the store.
    store = Store(tmp_path / "store")
    suite = sweep.load_suite(seeds_suite(tmp_path, 1), "smoke")
    folder = store.root / "sweeps" / "logs" / "x" / "%j"
    for var, value in {"SUBMITIT_EXECUTOR": "local", "SUBMITIT_LOCAL_JOB_ID": "4242", "SUBMITIT_FOLDER": str(folder),
                       "SUBMITIT_LOCAL_GLOBALID": "0", "SUBMITIT_LOCAL_LOCALID": "0", "SUBMITIT_LOCAL_NTASKS": "1"}.items():
        monkeypatch.setenv(var, value)
    (folder.parent / "4242").mkdir(parents=True)  # submitit makes it, for the job's logs
    with pytest.raises(specs.SpecError):
        sweep.train_job(str(tmp_path / "gone.yaml"), "smoke", [], str(store.root))
    record = json.loads(sweep.outcome_path(folder.parent / "4242", "4242").read_text())
    assert record == {"job_id": "4242", "outcome": "error", "error": f"SpecError: {tmp_path / 'gone.yaml'}: file not found"}
    sweep._record_jobs(store, suite, "submitit-local", [(suite.runs[0], "4242", folder)])
    (row,) = sweep.status(suite, store)
    assert row.state == "failed" and row.note == f"job 4242 ERROR: SpecError: {tmp_path / 'gone.yaml'}: file not found"


@pytest.mark.slow
def test_a_job_that_reaches_its_time_budget_returns_stopped_and_the_next_finishes(smoke_run, tmp_path):
    # In-process, as submitit runs it; grid_2's smoke program is in the session's compile cache.
    store = tmp_path / "store"
    stopped = sweep.train_job(GRID_2, "smoke", [], str(store), stop_after_s=0.0)  # one chunk always runs
    assert stopped == sweep.JobStopped(1, 2)
    assert len(list(store.glob("runs/*/*.partial"))) == 1
    path = Path(sweep.train_job(GRID_2, "smoke", [], str(store), stop_after_s=None))
    assert (path / "manifest.json").is_file() and not list(store.glob("runs/*/*.partial"))


FAKE_SBATCH = """#!/bin/sh
# Stands in for SLURM's sbatch: keeps the job script and answers as sbatch does.
cp "$1" "$(dirname "$0")/script.sh"
echo "Submitted batch job 4242"
"""


def test_slurm_submission_builds_one_job_array(tmp_path, monkeypatch):
    # No cluster here: stand-ins for sbatch and srun (submitit looks for srun), and no sacct.
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "sbatch").write_text(FAKE_SBATCH)
    (bin_dir / "srun").write_text("#!/bin/sh\nexit 0\n")
    for f in bin_dir.iterdir():
        f.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}:{os.environ['PATH']}")
    path = write_suite(tmp_path, f"specs: [{GRID_2}]\ngrid: {{train.seeds: [[0], [1], [2]]}}\n"
                                 "slurm: {partition: gpu, gpus: 1, time_min: 600, mem_gb: 16, setup: [module load cuda]}\n")
    store = Store(tmp_path / "store")
    quiet = Console(stderr=True, quiet=True)
    result = sweep.run_suite(path, "smoke", "slurm", store, quiet, slurm={"time_min": 90})
    assert [job for _, job in result.submitted] == ["4242_0", "4242_1", "4242_2"]
    # Each job trains until a margin before its 90-minute limit, then stops at a chunk boundary.
    pickles = sorted((tmp_path / "store").rglob("*_submitted.pkl"))
    assert len(pickles) == 3
    for pkl in pickles:
        call = pickle.loads(pkl.read_bytes())
        assert call.function is sweep.train_job and call.args[-1] == sweep.job_time_budget_s(90) == 90 * 60 * 0.95
    assert result.paths == [None] * 3 and not result.complete  # submitted, not waited for
    script = (bin_dir / "script.sh").read_text()
    for line in ("#SBATCH --array=0-2", "#SBATCH --partition=gpu", "#SBATCH --gpus-per-node=1",
                 "#SBATCH --time=90", "#SBATCH --mem=16GB", "module load cuda"):
        assert line in script, line
    # The jobs are recorded: status says queued (no sacct here), and a second sweep submits nothing.
    rows = sweep.status(sweep.load_suite(path, "smoke"), store)
    assert [r.state for r in rows] == ["queued"] * 3 and "job 4242_0" in rows[0].note
    again = sweep.run_suite(path, "smoke", "slurm", store, quiet)
    assert again.submitted == [] and len(again.skipped) == 3


def test_a_refused_submission_is_one_line_and_leaves_no_job_files(tmp_path, monkeypatch, capsys):
    """sbatch's refusal (a bad partition): the sweep ends with its one line, printed once, and the
    job script and pickled calls submitit wrote for jobs that do not exist are removed."""
    from esr_cli.cli.main import main

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "sbatch").write_text("#!/bin/sh\necho 'sbatch: error: invalid partition specified: nope' >&2\nexit 1\n")
    (bin_dir / "srun").write_text("#!/bin/sh\nexit 0\n")
    for f in bin_dir.iterdir():
        f.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}:{os.environ['PATH']}")
    path = write_suite(tmp_path, f"specs: [{GRID_2}]\ngrid: {{train.seeds: [[0], [1]]}}\nslurm: {{partition: nope}}\n")
    store = tmp_path / "store"
    assert main(["--store", str(store), "sweep", str(path), "--budget", "smoke", "--executor", "slurm"]) == 1
    err = capsys.readouterr().err
    assert err.count("invalid partition specified: nope") == 1
    assert "error: submission failed: sbatch: error: invalid partition specified: nope" in " ".join(err.split())
    assert not [p for p in (store / "sweeps" / "logs").rglob("*") if p.is_file()]


def test_a_sweep_whose_jobs_stopped_at_their_time_budget_exits_75(tmp_path, monkeypatch, capsys):
    from esr_cli.cli.main import main

    path = seeds_suite(tmp_path, 2)
    suite = sweep.load_suite(path, "smoke")

    def stopped_sweep(*args, **kwargs):
        r = suite.runs
        return sweep.SweepResult(suite, [None, None], submitted=[(r[0], "1"), (r[1], "2")],
                                 stopped=[(run, str(sweep.JobStopped(1, 2))) for run in r])

    monkeypatch.setattr(sweep, "run_suite", stopped_sweep)
    assert main(["--store", str(tmp_path / "store"), "sweep", str(path), "--budget", "smoke",
                 "--executor", "submitit-local"]) == 75
    err = " ".join(capsys.readouterr().err.split())
    assert "0 of 2 run(s) done" in err and "2 run(s) stopped and saved (" in err and "stopped at its time budget" in err and "run the same sweep again to continue them" in err


def test_a_run_stopped_on_purpose_is_stopped_not_failed(tmp_path):
    """A run saved at a chunk boundary by Ctrl-C or --stop-after marks its pending.json; a
    partial run without the mark (a killed writer) stays failed."""
    store = Store(tmp_path / "store")
    suite = sweep.load_suite(seeds_suite(tmp_path, 2), "smoke")
    stopped, killed = suite.runs
    store.begin("runs", stopped.key, {"key": stopped.key, "stopped": {"epoch": 3, "why": "interrupted"}})
    store.begin("runs", killed.key, {"key": killed.key})
    rows = sweep.status(suite, store)
    assert [row.state for row in rows] == ["stopped", "failed"]
    assert rows[0].note == "stopped (interrupted) after epoch 3; sweep again (or esr train) to continue it"


@pytest.mark.slow
def test_curves_of_unfinished_runs_are_a_preview_marked_unfinished_outside_the_store(tmp_path):
    store, preview = tmp_path / "store", tmp_path / "preview"
    path = seeds_suite(tmp_path, 2)
    suite = sweep.load_suite(path, "smoke")
    esr(*shlex.split(suite.runs[0].command("smoke"))[1:], store=store)
    # The second run is killed once its first epoch is saved: a partial run with one of 2 epochs.
    killed = esr(*shlex.split(suite.runs[1].command("smoke"))[1:], store=store, check=False, ESR_FAULT="after_checkpoint@1")
    assert killed.returncode == -9

    refused = esr("sweep", str(path), "--budget", "smoke", "--results", "--plot", store=store, check=False)
    assert refused.returncode == 2 and "needs 1 run(s) the store lacks" in refused.stderr
    # A store named by --store (not the one ESR_STORE names) is named in every hint, the last one too.
    named = esr("--store", str(store), "sweep", str(path), "--budget", "smoke", "--results", "--plot",
                store=tmp_path / "elsewhere", check=False)
    assert named.stderr.strip().splitlines()[-1] == f"or all at once: esr --store {store} sweep {path} --budget smoke"
    assert esr("sweep", str(path), "--budget", "smoke", "--results", "--unfinished", store=store,
               check=False).returncode == 2  # --unfinished without --plot: named, not ignored

    proc = esr("sweep", str(path), "--budget", "smoke", "--results", "--plot", "--unfinished", "--out", str(preview),
               store=store, **WIDE)
    assert f"drawn: {preview / 'suite.png'}" in proc.stderr and (preview / "suite.png").stat().st_size > 0
    note = f"{suite.runs[1].label}: epoch 1 of 2"
    assert f"a preview of unfinished runs: {note}" in proc.stderr
    assert json.loads((preview / "suite.json").read_text())["unfinished"] == [note]
    table = (preview / "table.md").read_text()
    assert table.startswith(f"UNFINISHED, as far as these runs have got: {note}")
    assert not (store / "figures").exists() or not any((store / "figures").rglob("manifest.json"))


def test_a_paper_figure_of_unfinished_runs_is_drawn_as_a_preview_and_never_stored(tmp_path):
    from esr_cli.report import figures as figs, paper
    from esr_cli.storage.artifacts import ensure, preview

    store = Store(tmp_path / "store")
    inputs = figs.PaperInputs(store, "smoke", unfinished=True)
    wanted = figs.WANTS["fig1_gridworld"]()
    for i, (stem, sets) in enumerate(wanted):  # each run has logged 3 epochs of its 2 seeds
        part = store.partial_path("runs", inputs.run(stem, sets).key)
        part.mkdir(parents=True)
        rows = [{"epoch": e, "return": [float(i + e), float(i)], "success": [0.0, 1.0]} for e in (1, 2, 3)]
        (part / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    with pytest.raises(figs.MissingRuns):  # without unfinished, every one of them is missing
        paper.figure_recipe(store, "smoke", "gridworld")
    recipe = paper.figure_recipe(store, "smoke", "gridworld", inputs)
    assert len(recipe.unfinished) == len(wanted) and all(n.endswith(": epoch 3 of 2") for n in recipe.unfinished)
    with pytest.raises(ValueError, match="reads unfinished runs"):
        ensure(recipe, store)
    summary = preview(recipe, tmp_path / "out", store)
    side = json.loads((tmp_path / "out" / "fig1_gridworld.json").read_text())
    assert side["unfinished"] == list(recipe.unfinished)
    assert side["artifacts"]["runs"] == [inputs.run(stem, sets).key for stem, sets in wanted]
    # the final return of the first line at N = 2: the last 10% of 3 epochs is the last one
    first = summary["final_return"]["N = 2 blocks"][figs.PAPER_LABELS["esr"]]
    assert first["per_seed"] == [3.0, 0.0]
    # the figures that restore a run's final state still need it finished, partial or not
    for stem, sets in figs.WANTS["fig6_representations"]():
        part = store.partial_path("runs", inputs.run(stem, sets).key)
        part.mkdir(parents=True)
        (part / "metrics.jsonl").write_text(json.dumps({"epoch": 1, "return": [1.0]}) + "\n")
    with pytest.raises(figs.MissingRuns):
        paper.figure_recipe(store, "smoke", "representations", inputs)
