"""Reliability: kills at every stage, Ctrl-C, two writers, divergence, corruption, bad input.
See docs/reliability.md."""

import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, esr, esr_env
from run_helpers import SMOKE, committed, final_arrays, partials, rename_checkpoint


def assert_same_run(path: Path, reference) -> None:
    """The run at `path` ends bit for bit where the uninterrupted one does: metrics and state."""
    want_metrics, want_state = reference
    assert (path / "metrics.jsonl").read_text() == want_metrics
    for a, b in zip(final_arrays(path), want_state, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.fixture(scope="module")
def reference(smoke_run):
    """The uninterrupted smoke run: metrics text and final training state."""
    _, path, _ = smoke_run
    return (path / "metrics.jsonl").read_text(), final_arrays(path)


@pytest.mark.slow
@pytest.mark.parametrize("point", ["compile@1", "after_metrics@1", "after_checkpoint@1", "after_metrics@2", "before_rename"])
def test_killed_run_resumes_to_the_uninterrupted_result(tmp_path, reference, point):
    store = tmp_path / "store"
    killed = esr(*SMOKE, store=store, check=False, ESR_FAULT=point)
    assert killed.returncode == -signal.SIGKILL
    assert committed(store) == []  # nothing half-made is ever visible as an artifact
    assert len(partials(store)) == 1
    resumed = esr(*SMOKE, store=store)
    if point != "compile@1":
        assert "resuming" in resumed.stderr or point == "after_metrics@1"
    path = Path(resumed.stdout.strip())
    assert committed(store) == [path] and partials(store) == []
    assert esr("verify", store=store).returncode == 0
    assert_same_run(path, reference)


@pytest.mark.slow
def test_stop_after_ends_at_a_chunk_boundary_and_resumes_to_the_uninterrupted_result(tmp_path, reference):
    store = tmp_path / "store"
    # 0s: no second chunk fits, so the run stops after its first (one always runs)
    stopped = esr(*SMOKE, "--stop-after", "0s", store=store, check=False)
    assert stopped.returncode == 75, stopped.stderr
    assert "stopped after epoch 1 of 2" in stopped.stderr and "run the same command again" in stopped.stderr
    assert "error" not in stopped.stderr  # a stop asked for, said as such
    assert stopped.stdout == "" and committed(store) == []
    (part,) = partials(store)
    assert len((part / "metrics.jsonl").read_text().splitlines()) == 1
    # stopped on purpose, as listings say ("stopped", not "failed"); what uses the run says so
    assert json.loads((part / "pending.json").read_text())["stopped"]["epoch"] == 1
    assert "stopped" in esr("ls", store=store).stdout
    unfinished = esr("eval", *SMOKE[1:], store=store, check=False)
    assert unfinished.returncode == 2 and "is not finished" in unfinished.stderr and "to continue it" in unfinished.stderr
    resumed = esr(*SMOKE, "--stop-after", "1h", store=store)
    path = Path(resumed.stdout.strip())
    assert "resuming" in resumed.stderr and committed(store) == [path] and partials(store) == []
    assert_same_run(path, reference)


def test_next_chunk_fits_by_its_estimated_duration():
    from esr_cli.runner.loop import next_chunk_fits

    assert next_chunk_fits(100.0, None, 1e9)  # no limit
    assert next_chunk_fits(100.0, 130.0, 30.0)  # ends exactly at the limit
    assert not next_chunk_fits(100.0, 130.0, 30.5)
    assert not next_chunk_fits(140.0, 130.0, 0.0)  # already past it


def test_a_scheduled_job_stops_a_margin_before_its_time_limit():
    from esr_cli.recipes.sweep import job_time_budget_s

    assert job_time_budget_s(720) == 720 * 60 * 0.95  # 5% of 12 hours: 36 minutes
    assert job_time_budget_s(10) == 600 - 60  # at least a minute
    assert job_time_budget_s(1) == 0.0  # one chunk, then stop


@pytest.mark.slow
def test_two_trainers_of_one_spec_make_one_artifact(tmp_path):
    store = tmp_path / "store"
    args = [sys.executable, "-m", "esr_cli.cli.main", *SMOKE, "--set", "train.epochs=30"]
    first = subprocess.Popen(args, cwd=ROOT, env=esr_env(store), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while not partials(store) and time.time() < deadline:
        time.sleep(0.1)
    second = subprocess.Popen(args, cwd=ROOT, env=esr_env(store), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out1, err1 = first.communicate(timeout=600)
    out2, err2 = second.communicate(timeout=600)
    assert first.returncode == 0 and second.returncode == 0, err1 + err2
    assert out1.strip() == out2.strip()
    assert "trained" in err1 and "cache hit" in err2
    assert "in progress" in err2 and "pid" in err2
    assert len(committed(store)) == 1 and partials(store) == []


@pytest.mark.slow
def test_divergence_stops_with_the_quantity_seed_and_epoch(tmp_path):
    store = tmp_path / "store"
    proc = esr(*SMOKE, "--set", "method.repr_lr=1e30", "--set", "learner.lr=1e30", store=store, check=False)
    assert proc.returncode == 1
    assert "run diverged" in proc.stderr and "seed 0" in proc.stderr and "epoch" in proc.stderr
    assert "Traceback" not in proc.stderr
    (part,) = partials(store)  # kept for inspection, never committed
    assert committed(store) == []
    # It says that it diverged, and where, to every command that reads it; its epochs up to
    # the divergence are kept; nothing advises running it again as if it had only stopped.
    mark = json.loads((part / "pending.json").read_text())["diverged"]
    rows = [json.loads(line) for line in (part / "metrics.jsonl").read_text().splitlines()]
    assert mark["what"] in proc.stderr and rows and rows[-1]["epoch"] == mark["epoch"]
    assert "diverged" in esr("ls", store=store).stdout
    shown = esr("show", part.name[:8], store=store).stdout
    assert f"diverged:      {mark['what']}; training is deterministic" in shown
    ev = esr("eval", part.name[:8], store=store, check=False)
    assert ev.returncode == 2 and "diverged" in ev.stderr and "run the command" not in ev.stderr


@pytest.mark.slow  # trains the shared smoke run
def test_verify_reports_a_flipped_byte_and_a_deleted_file(tmp_path, smoke_run):
    _, path, _ = smoke_run
    store = tmp_path / "store"
    copy = store / path.relative_to(path.parents[2])
    shutil.copytree(path, copy)
    assert esr("verify", store=store).returncode == 0
    data = bytearray((copy / "metrics.jsonl").read_bytes())
    data[10] ^= 1
    (copy / "metrics.jsonl").write_bytes(bytes(data))
    victim = next(p for p in (copy / "checkpoints").rglob("*") if p.is_file())
    victim.unlink()
    proc = esr("verify", store=store, check=False)
    assert proc.returncode == 1
    assert "changed file metrics.jsonl" in proc.stderr and "missing file" in proc.stderr


@pytest.mark.slow
def test_corrupt_checkpoint_is_a_clear_error(tmp_path):
    store = tmp_path / "store"
    assert esr(*SMOKE, store=store, check=False, ESR_FAULT="after_checkpoint@1").returncode == -signal.SIGKILL
    (part,) = partials(store)
    for f in (part / "checkpoints").rglob("*"):
        if f.is_file() and "ocdbt" in str(f.relative_to(part)):
            f.write_bytes(b"garbage")
    proc = esr(*SMOKE, store=store, check=False)
    assert proc.returncode == 1
    assert "no intact checkpoint" in proc.stderr and "Traceback" not in proc.stderr
    assert committed(store) == []


@pytest.mark.slow
def test_a_checkpoint_folder_renamed_to_another_epoch_is_refused(tmp_path):
    """The folder's number must be the epoch the checkpoint's state holds, an epoch the metrics
    logged and one of the run's: an import and a resume refuse it, naming the epochs, and
    nothing is committed."""
    store = tmp_path / "store"
    assert esr(*SMOKE, store=store, check=False, ESR_FAULT="after_checkpoint@1").returncode == -signal.SIGKILL
    (part,) = partials(store)
    rename_checkpoint(part, 1, 999)
    archive = tmp_path / "renamed.tar.gz"
    esr("export", part.name[:8], "--out", str(archive), store=store)
    imported = esr("import", str(archive), store=tmp_path / "other", check=False)
    assert imported.returncode == 2 and not (tmp_path / "other").exists()
    assert "checkpoint folder says epoch 999 but metrics end at 1, in a run of 2 epochs; nothing imported" in imported.stderr

    resumed = esr(*SMOKE, store=store, check=False)
    assert resumed.returncode == 1 and "Traceback" not in resumed.stderr
    assert "checkpoint folder says epoch 999 but its state holds epoch 1 and metrics end at 1, in a run of 2 epochs" \
        in " ".join(resumed.stderr.split())
    # Within the run, and with a metrics line forged to match: the state still holds epoch 1.
    rename_checkpoint(part, 999, 2)
    row = json.loads((part / "metrics.jsonl").read_text().splitlines()[0])
    with open(part / "metrics.jsonl", "a") as f:
        f.write(json.dumps({**row, "epoch": 2}) + "\n")
    resumed = esr(*SMOKE, store=store, check=False)
    assert resumed.returncode == 1
    assert "checkpoint folder says epoch 2 but its state holds epoch 1;" in " ".join(resumed.stderr.split())
    assert committed(store) == []


@pytest.mark.slow  # trains the shared smoke run
def test_verify_finds_a_finished_run_whose_epochs_disagree(tmp_path, smoke_run):
    """A committed run's length, newest checkpoint folder, digests, metrics and summary must
    agree: a renamed checkpoint folder fails `esr verify` even with a manifest rewritten to match."""
    from esr_cli.storage.store import digest_file

    _, path, _ = smoke_run
    store = tmp_path / "store"
    copy = store / path.relative_to(path.parents[2])
    shutil.copytree(path, copy)
    rename_checkpoint(copy, 2, 999)
    manifest = json.loads((copy / "manifest.json").read_text())
    files = {rel.replace("checkpoints/2/", "checkpoints/999/"): d for rel, d in manifest["files"].items()}
    files["checkpoint_digests.json"] = digest_file(copy / "checkpoint_digests.json")
    (copy / "manifest.json").write_text(json.dumps({**manifest, "files": files}))
    proc = esr("verify", store=store, check=False)
    assert proc.returncode == 1
    assert ("the run has 2 epochs but its newest checkpoint folder says 999 and its checkpoint digests end at 999"
            in " ".join(proc.stderr.split())), proc.stderr


@pytest.mark.slow  # trains the shared smoke run
def test_a_finished_run_keeps_only_its_newest_checkpoint(smoke_run):
    from esr_cli.runner import loop

    _, path, _ = smoke_run
    epochs = max(r["epoch"] for r in loop.read_rows(path))
    assert [d.name for d in (path / "checkpoints").iterdir() if d.name.isdigit()] == [str(epochs)]
    assert loop.verified_steps(path) == [epochs]


@pytest.mark.slow
def test_a_damaged_newest_checkpoint_falls_back_to_the_one_before(tmp_path, reference):
    store = tmp_path / "store"
    # Killed after the last chunk's checkpoint: training keeps the one before it until the end.
    assert esr(*SMOKE, store=store, check=False, ESR_FAULT="after_checkpoint@2").returncode == -signal.SIGKILL
    (part,) = partials(store)
    assert len([d for d in (part / "checkpoints").iterdir() if d.name.isdigit()]) == 2
    newest = max((part / "checkpoints").iterdir(), key=lambda p: int(p.name) if p.name.isdigit() else -1)
    victim = next(f for f in newest.rglob("*") if f.is_file() and "ocdbt" in str(f))
    victim.write_bytes(b"garbage")
    proc = esr(*SMOKE, store=store)
    assert "resuming" in proc.stderr and "from epoch 1" in proc.stderr
    path = Path(proc.stdout.strip())
    assert_same_run(path, reference)


def test_not_enough_disk_fails_before_any_work(tmp_path, monkeypatch, capsys):
    from esr_cli.cli.main import main
    from esr_cli.recipes import runs

    monkeypatch.setattr(runs.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(10**9, 10**9, 1 << 20))
    store = tmp_path / "store"
    assert main(["--store", str(store), *SMOKE]) != 0
    err = capsys.readouterr().err
    assert "MiB free" in err and partials(store) == [] and committed(store) == []


def test_bad_store_and_bad_keys_are_one_line_errors(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    proc = esr(*SMOKE, store=blocker / "store", check=False)
    assert proc.returncode != 0 and "not writable" in proc.stderr and "Traceback" not in proc.stderr
    proc = esr("eval", "0123abcd", store=tmp_path / "empty", check=False)
    assert proc.returncode == 2 and "no artifact" in proc.stderr and "Traceback" not in proc.stderr
    proc = esr("--debug", "show", "0123abcd", store=tmp_path / "empty", check=False)
    assert proc.returncode != 0 and "Traceback" in proc.stderr


@pytest.mark.slow
def test_a_longer_run_continues_a_shorter_one_bit_for_bit(tmp_path, reference):
    """train.epochs grows: the longer run starts from the shorter run's last checkpoint and
    ends exactly where an uninterrupted run of the longer length ends."""
    store = tmp_path / "store"
    short = Path(esr(*SMOKE, "--set", "train.epochs=1", store=store).stdout.strip())
    longer = esr(*SMOKE, store=store)
    assert f"starting from run {short.name[:12]} at epoch 1: the same spec but for its length, finished" in longer.stderr
    path = Path(longer.stdout.strip())
    assert_same_run(path, reference)
    assert (short / "manifest.json").is_file()  # the shorter artifact is untouched
    assert esr("verify", store=store).returncode == 0
    # Kept as metrics only elsewhere, the shorter run has no networks to continue from: said.
    slim = tmp_path / "short.tar.gz"
    esr("export", short.name[:8], "--without-checkpoint", "--out", str(slim), store=store)
    esr("import", str(slim), store=tmp_path / "slim")
    again = esr(*SMOKE, store=tmp_path / "slim")
    said = " ".join(again.stderr.split())
    assert f"run {short.name[:12]} (the same spec but for its length) is kept as metrics only: training starts from epoch 1" in said
    assert_same_run(Path(again.stdout.strip()), reference)


@pytest.mark.slow
def test_an_unfinished_longer_run_gives_a_shorter_one_its_checkpoint(tmp_path, reference):
    store = tmp_path / "store"
    killed = esr(*SMOKE, "--set", "train.epochs=3", store=store, check=False, ESR_FAULT="after_checkpoint@2")
    assert killed.returncode == -signal.SIGKILL
    shorter = esr(*SMOKE, store=store)
    assert "at epoch 2: the same spec but for its length, unfinished (3 epochs long, checkpointed at epoch 2)" in shorter.stderr
    path = Path(shorter.stdout.strip())
    assert_same_run(path, reference)
    assert len(partials(store)) == 1  # the 3-epoch run is still there to be resumed


def test_a_human_cloned_from_episodes_the_store_lacks_is_refused_before_anything_is_written(tmp_path):
    """The played episodes are looked up before any artifact begins: nothing of the data, the
    human or the run is left half-made (no partial, no lock) by a mistyped key."""
    from rich.console import Console

    from esr_cli.common import specs
    from esr_cli.recipes.human_runs import human_recipe
    from esr_cli.storage.artifacts import ensure
    from esr_cli.storage.store import Store, StoreError

    spec = specs.load(ROOT / "experiments/cramped_room.yaml", "smoke", ["human.data=[0123456789abcdef0123456789abcdef]"])
    store = Store(tmp_path / "store")
    with pytest.raises(StoreError, match="played episode 0123456789ab is not in"):
        ensure(human_recipe(spec.human, spec.env.layout, Console(quiet=True)), store)
    assert [p for p in (tmp_path / "store").rglob("*") if p.is_file()] == []


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
@pytest.mark.parametrize("where", ["gc-callback", "finalizer"])
def test_a_stop_signal_where_python_ignores_exceptions_is_not_lost(sig, where):
    """Python ignores an exception raised in a gc callback (jax registers one), a weakref
    callback or a finalizer; Ctrl-C or a SIGTERM handled there must still end the command,
    a moment later."""
    import gc
    import os

    from esr_cli.runner.stop_signals import Terminated, stop_signals_raise

    sent = []

    def send_and_linger():
        if not sent:
            sent.append(True)
            os.kill(os.getpid(), sig)  # handled at the next bytecode, still in here
            sum(range(10_000))

    class Finalized:
        def __del__(self):
            send_and_linger()

    def callback(phase, info):
        if phase == "start":
            send_and_linger()

    gc.callbacks.append(callback)
    try:
        with pytest.raises(KeyboardInterrupt if sig == signal.SIGINT else Terminated), stop_signals_raise():
            if where == "gc-callback":
                gc.collect()
            else:
                Finalized()  # dropped at once: __del__ runs here
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                time.sleep(0.01)
    finally:
        gc.callbacks.remove(callback)
    assert sent


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_library_catching_exception_does_not_swallow_a_stop_signal(sig):
    """jax reads its compilation cache, and orbax restores, under `except Exception`: a stop
    raised in there must still end the command, not become a warning or a 'corrupt checkpoint'."""
    import os

    from esr_cli.runner.stop_signals import Terminated, stop_signals_raise

    swallowed = []
    with pytest.raises(KeyboardInterrupt if sig == signal.SIGINT else Terminated), stop_signals_raise():
        try:
            os.kill(os.getpid(), sig)
            time.sleep(10)
        except Exception as e:  # noqa: BLE001 - what such a library does
            swallowed.append(e)
    assert not swallowed


@pytest.mark.slow  # trains the shared smoke run
@pytest.mark.parametrize("sig, code, line", [(signal.SIGTERM, 143, "terminated (SIGTERM)"),
                                             (signal.SIGINT, 130, "interrupted")], ids=["sigterm", "ctrl-c"])
def test_an_evaluation_stopped_by_a_signal_says_so_and_leaves_nothing_half_made(smoke_run, tmp_path, sig, code, line):
    """Only a training run resumes from what it wrote: an evaluation ended by SIGTERM or
    Ctrl-C exits 143 or 130 with one line, and its partial directory is removed."""
    store, path, _ = smoke_run
    mine = tmp_path / "store"
    shutil.copytree(path, mine / "runs" / path.parent.name / path.name)
    proc = subprocess.Popen([sys.executable, "-m", "esr_cli.cli.main", "eval", path.name[:8], "--episodes", "1000000"],
                            cwd=ROOT, env=esr_env(mine), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:  # a failure must not leave a million-episode evaluation running
        deadline = time.time() + 300
        while not list((mine / "evals").rglob("pending.json")):
            assert proc.poll() is None and time.time() < deadline, proc.communicate()
            time.sleep(0.1)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == code and err.strip().endswith(line), err
    assert not list((mine / "evals").rglob("*.partial"))


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)], ids=["ctrl-c", "sigterm"])
def test_a_stop_signal_a_library_wraps_in_its_own_error_still_ends_the_command_as_stopped(sig, code, monkeypatch, capsys):
    """pybind11 turns an exception raised while a C++ module initialises into
    `ImportError: initialization failed`: the command still reports the signal and its code."""
    import os

    from esr_cli.cli import main as cli

    def importing(args, standalone_mode):
        try:
            os.kill(os.getpid(), sig)
            time.sleep(10)
        except BaseException as e:  # noqa: BLE001 - what pybind11 does around a module's init
            raise ImportError("initialization failed") from e

    monkeypatch.setattr(cli, "app", importing)
    assert cli.main(["eval", "abc"]) == code
    assert "ImportError" not in capsys.readouterr().err


def test_a_misspelt_fault_point_is_an_error_not_a_fault_that_never_fires(monkeypatch):
    from esr_cli.common import faults

    assert faults.parse("after_metrics@2") == ("after_metrics", 2, "kill") and faults.parse("compile") == ("compile", 1, "kill")
    assert faults.parse("during_save@3:hang") == ("during_save", 3, "hang")
    for bad, said in (("after_metric@2", "unknown fault point 'after_metric'"), ("compile@0", "positive integer"),
                      ("compile@x", "positive integer"), ("compile:stall", "unknown action 'stall'")):
        with pytest.raises(faults.FaultSpecError, match=said):
            faults.parse(bad)
    monkeypatch.setenv("ESR_FAULT", "after_metric@1")
    with pytest.raises(faults.FaultSpecError):
        faults.reached("after_metrics")
    with pytest.raises(ValueError, match="not a fault point"):
        faults.reached("nowhere")


def test_the_divergence_named_is_the_earliest_epoch_of_any_seed_and_metric(monkeypatch):
    """Metrics are checked in a fixed order and seeds first: the epoch recorded (and the metrics
    kept up to it) must still be the first at which any watched value went non-finite."""
    from esr_cli.runner import loop

    monkeypatch.setattr(loop, "_watched_metrics", lambda trainer: ["critic_loss", "q_mean"])
    metrics = {"critic_loss": np.array([[0.0, 0.0, 0.0, np.nan], [0.0, 0.0, 0.0, 0.0]]),
               "q_mean": np.array([[0.0, 0.0, 0.0, 0.0], [0.0, np.inf, np.nan, 0.0]])}
    diverged = loop._divergence(None, None, metrics, [7, 3], 10)
    assert diverged.epoch == 12 and str(diverged) == "q_mean became inf at seed 3, epoch 12"
