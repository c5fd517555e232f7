"""`esr sweep --executor slurm` against a real SLURM: slurmctld and slurmd on localhost
(tests/slurm_cluster.py; docs/cluster.md), no accounting, so sacct refuses and job states come
from squeue. Smoke-budget runs of grid_2, one job at a time (one CPU each). Skipped, with what
failed, where SLURM is not installed or will not start."""

import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import slurm_cluster
from conftest import ROOT, esr, esr_env

pytestmark = pytest.mark.slow

GRID_2 = ROOT / "experiments" / "grid_2.yaml"
WIDE = {"COLUMNS": "400"}
# One job at a time, one CPU each, no GPU: the node is this machine.
SLURM = "slurm: {cpus: 1, mem_gb: 2, gpus: 0, time_min: 10, array_parallelism: 1}\n"


@pytest.fixture(scope="module")
def cluster():
    folder = Path(tempfile.mkdtemp(prefix="esr-slurm-"))  # short: the munge socket's path must fit
    try:
        c = slurm_cluster.start(folder)
    except slurm_cluster.Unavailable as e:
        shutil.rmtree(folder, ignore_errors=True)
        pytest.skip(f"no SLURM cluster here: {e}")
    yield c
    c.stop()
    shutil.rmtree(folder, ignore_errors=True)


def seeds_suite(tmp_path: Path, name: str, extra: str = "") -> Path:
    path = tmp_path / f"{name}.yaml"
    path.write_text(f"name: {name}\nspecs: [{GRID_2}]\ngrid: {{train.seeds: [[0], [1]]}}\n{extra}{SLURM}")
    return path


def sweep(cluster, *args, store, check=True):
    return esr("sweep", *args, "--budget", "smoke", store=store, check=check, SLURM_CONF=str(cluster.conf), **WIDE)


def status(cluster, suite, store) -> list[dict]:
    return json.loads(sweep(cluster, str(suite), "--status", "--json", store=store).stdout)


def job_ids(store: Path, name: str) -> list[str]:
    """The job of each run, in the suite's order, from the sweep's state file."""
    (state_file,) = (store / "sweeps").glob(f"{name}-smoke-*.json")
    return json.loads(state_file.read_text())["jobs"]


def test_a_suite_runs_as_a_job_array_and_its_runs_are_committed(cluster, tmp_path):
    store = tmp_path / "store"
    suite = seeds_suite(tmp_path, "slurmseeds")
    proc = sweep(cluster, str(suite), "--executor", "slurm", "--wait", store=store)
    assert "0 done, 0 running or queued, 2 to submit" in proc.stderr
    assert "2 of 2 run(s) done; 2 submitted this time" in proc.stderr
    paths = [Path(p) for p in proc.stdout.split()]
    assert sorted(json.loads((p / "manifest.json").read_text())["seeds"] for p in paths) == [[0], [1]]

    # One job array of two tasks; each job recorded, and each wrote its own outcome record.
    rows = status(cluster, suite, store)
    jobs = job_ids(store, "slurmseeds")
    ids = [jobs[r["key"]]["job_id"] for r in rows]
    array = ids[0].split("_")[0]
    assert sorted(ids) == [f"{array}_0", f"{array}_1"] and {j["executor"] for j in jobs.values()} == {"slurm"}
    logs = Path(next(iter(jobs.values()))["folder"]).parent
    for job in ids:
        assert json.loads((logs / job / f"{job}_esr_outcome.json").read_text())["outcome"] == "success"

    # --status agrees with SLURM: every run done, every job COMPLETED in squeue (sacct has no
    # accounting to read here: it refuses).
    assert [r["state"] for r in rows] == ["done", "done"] and sorted(Path(r["path"]) for r in rows) == sorted(paths)
    assert [cluster.job_state(job) for job in ids] == ["COMPLETED", "COMPLETED"]
    sacct = cluster.run("sacct", "-j", array, check=False)
    assert sacct.returncode != 0 and "accounting storage is disabled" in sacct.stderr
    table = sweep(cluster, str(suite), "--status", store=store).stdout
    assert "suite slurmseeds (smoke): 2 done" in table

    # Again: all committed, nothing submitted, no new job in SLURM.
    before = set(cluster.jobs())
    again = sweep(cluster, str(suite), "--executor", "slurm", "--wait", store=store)
    assert "2 done, 0 running or queued, 0 to submit" in again.stderr and "0 submitted this time" in again.stderr
    assert set(cluster.jobs()) == before


def wait_for(what: str, ready, timeout: float = 300, proc=None):
    deadline = time.monotonic() + timeout
    while not ready():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"the sweep ended ({proc.returncode}) before {what}:\n{proc.stderr.read()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout:.0f} s: {what}")
        time.sleep(0.5)


LONG_EPOCHS = 200


def test_a_cancelled_job_stops_its_run_and_sweeping_again_resumes_it(cluster, tmp_path):
    store = tmp_path / "store"
    # One checkpoint per epoch, and long enough that run 0 is still training when --status looks
    # (40 epochs once ended first on a loaded machine).
    suite = seeds_suite(tmp_path, "slurmlong", f"set: {{train.epochs: {LONG_EPOCHS}}}\n")
    # A waiting sweep, in the background: run 0's job trains, run 1's waits for it (parallelism 1).
    waiting = subprocess.Popen([sys.executable, "-m", "esr_cli.cli.main", "sweep", str(suite), "--budget", "smoke",
                                "--executor", "slurm", "--wait"], cwd=ROOT, text=True, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, env=esr_env(store, SLURM_CONF=str(cluster.conf), **WIDE))
    try:
        wait_for("the sweep records its jobs", lambda: list((store / "sweeps").glob("slurmlong-smoke-*.json")), proc=waiting)
        rows = status(cluster, suite, store)
        key0, key1 = (r["key"] for r in rows)
        first, second = (job_ids(store, "slurmlong")[k]["job_id"] for k in (key0, key1))
        saved = lambda n: len(list(store.glob(f"runs/*/{key0}.partial/checkpoints/*"))) >= n  # noqa: E731
        wait_for("run 0 has saved an epoch", lambda: saved(1), proc=waiting)
        # While it trains: status says what squeue says (run 0's lock is held; run 1 is pending).
        rows = status(cluster, suite, store)
        assert [cluster.job_state(first), cluster.job_state(second)] == ["RUNNING", "PENDING"]
        assert [r["state"] for r in rows] == ["running", "queued"], rows
        assert rows[1]["detail"] == f"job {second} PENDING"
        wait_for("run 0 has saved two epochs", lambda: saved(2), proc=waiting)

        cluster.run("scancel", first.split("_")[0])  # the whole array: one running, one pending
        out, err = waiting.communicate(timeout=120)  # the waiting sweep returns, not waiting for ever
    finally:
        if waiting.poll() is None:
            waiting.kill()
    assert waiting.returncode == 1, err
    err = " ".join(err.split())
    assert f"stopped: {rows[0]['run']} (job {first}): interrupted (SIGTERM: cancelled?) after epoch" in err
    assert f"failed: {rows[1]['run']} (job {second}): CANCELLED" in err

    # --status: run 0 stopped (SIGTERM saved it at a chunk boundary), run 1 failed (cancelled
    # before it started); squeue says CANCELLED for both jobs.
    rows = status(cluster, suite, store)
    assert [r["state"] for r in rows] == ["stopped", "failed"], rows
    assert rows[0]["detail"].startswith(f"job {first}: interrupted (SIGTERM: cancelled?) after epoch ")
    assert rows[1]["detail"] == f"job {second} CANCELLED"
    assert [cluster.job_state(first), cluster.job_state(second)] == ["CANCELLED", "CANCELLED"]
    (partial,) = store.glob(f"runs/*/{key0}.partial")
    pending = json.loads((partial / "pending.json").read_text())
    kept = pending["stopped"]["epoch"]
    assert pending["stopped"]["why"] == "interrupted" and 2 <= kept < LONG_EPOCHS

    # The same sweep again: both runs are submitted; run 0 resumes from its checkpoint.
    proc = sweep(cluster, str(suite), "--executor", "slurm", "--wait", store=store)
    assert "0 done, 0 running or queued, 2 to submit" in proc.stderr and "2 of 2 run(s) done" in proc.stderr
    rows = status(cluster, suite, store)
    assert [r["state"] for r in rows] == ["done", "done"]
    new = job_ids(store, "slurmlong")[key0]["job_id"]
    assert new != first and cluster.job_state(new) == "COMPLETED"
    log = "".join(p.read_text() for p in (store / "sweeps" / "logs").rglob(f"{new}_0_log.err"))
    assert f"resuming {key0[:12]} from epoch {kept} of {LONG_EPOCHS}" in log
    manifest = json.loads((Path(rows[0]["path"]) / "manifest.json").read_text())
    assert len(manifest["sessions"]) == 2  # started by the cancelled job, finished by the next
    assert len((Path(rows[0]["path"]) / "metrics.jsonl").read_text().splitlines()) == LONG_EPOCHS
