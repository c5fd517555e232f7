"""A run that answers: Ctrl-C and SIGTERM acknowledged and acted on within seconds at any point
of training, a second signal exits at once, and a run says up front how long it will take.
See docs/reliability.md."""

import io
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import ROOT, esr, esr_env
from rich.console import Console

# A smoke run whose second chunk (400 epochs, after the 1-epoch warm-up) takes 10-20 s here.
# 402 epochs: stopped after the first, it resumes with a warm-up epoch and a 400-epoch chunk,
# programs the uninterrupted run (1, 400, 1) compiled already.
LONG_SETS = ("--set", "train.epochs=402", "--set", "train.chunk_epochs=400")
LONG = ("train", "experiments/grid_2.yaml", "--budget", "smoke", *LONG_SETS)
# The same with a 4,000-epoch chunk: 100-200 s here, stopped a second into it.
VERY_LONG = ("train", "experiments/grid_2.yaml", "--budget", "smoke", "--set", "train.epochs=4002",
             "--set", "train.chunk_epochs=4000")


def final_arrays(run_dir):
    from esr_cli.common import specs
    from esr_cli.model.train import make_trainer
    from esr_cli.runner import loop

    trainer = make_trainer(specs.load("experiments/grid_2.yaml", "smoke", list(LONG_SETS[1::2])))
    return [np.asarray(x) for x in jax.tree.leaves(loop.final_state(trainer, run_dir))]


def stop_mid_chunk(store: Path, sig, args=LONG, as_timeout: bool = False) -> tuple[int, float, str]:
    """Start `args`, send `sig` a second into its long chunk; -> (exit code, seconds from the
    signal to the exit, stderr). as_timeout: as GNU `timeout` sends it, to the process and then
    to its process group, so that it arrives twice at once."""
    proc = subprocess.Popen([sys.executable, "-m", "esr_cli.cli.main", *args], cwd=ROOT, env=esr_env(store),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=as_timeout)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 300
        while sum("compiled in" in line for line in lines) < 2:  # the long chunk's program: it runs now
            assert proc.poll() is None and time.monotonic() < deadline, "".join(lines)
            time.sleep(0.05)
        time.sleep(1)
        sent = time.monotonic()
        proc.send_signal(sig)
        if as_timeout:
            os.killpg(proc.pid, sig)
        proc.wait(timeout=60)
        took = time.monotonic() - sent
    finally:
        proc.kill()
    reader.join(timeout=10)
    return proc.returncode, took, "".join(lines)


def partial_run(store: Path) -> Path:
    (part,) = Path(store).glob("runs/*/*.partial")
    return part


@pytest.mark.slow
def test_ctrl_c_mid_chunk_stops_within_seconds_and_the_run_resumes_bit_identical(tmp_path):
    store = tmp_path / "store"
    code, took, err = stop_mid_chunk(store, signal.SIGINT)
    assert code == 130 and took < 5, (took, err)
    assert "stopping (Ctrl-C): the run stops now, keeping its checkpoint of epoch 1" in err
    assert "Ctrl-C again exits at once" in err and "Traceback" not in err
    assert "interrupted after epoch 1; the checkpoint is saved: run the same command again to resume" in err
    assert len((partial_run(store) / "metrics.jsonl").read_text().splitlines()) == 1  # the chunk in flight: dropped

    resumed = Path(esr(*LONG, store=store).stdout.strip())
    whole = Path(esr(*LONG, store=tmp_path / "whole").stdout.strip())
    assert (resumed / "metrics.jsonl").read_bytes() == (whole / "metrics.jsonl").read_bytes()
    for a, b in zip(final_arrays(resumed), final_arrays(whole)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow
def test_sigterm_in_a_chunk_of_minutes_stops_within_seconds_with_143(tmp_path):
    """Sent as `timeout` sends it (to the process, then to its group): one request, not two."""
    code, took, err = stop_mid_chunk(tmp_path / "store", signal.SIGTERM, VERY_LONG, as_timeout=True)
    assert code == 143 and took < 5, (took, err)
    assert "second stop signal" not in err
    assert "stopping (SIGTERM)" in err and "a second signal exits at once" in err
    assert "terminated (SIGTERM) after epoch 1; the checkpoint is saved" in err and "Traceback" not in err
    assert len((partial_run(tmp_path / "store") / "metrics.jsonl").read_text().splitlines()) == 1


@pytest.mark.slow
def test_a_second_ctrl_c_exits_at_once_even_while_a_checkpoint_is_written(tmp_path):
    # The first checkpoint's save hangs (a stalled file system): the first Ctrl-C is acknowledged
    # and waits for it, as the checkpoint is what the run keeps; the second leaves at once.
    proc = subprocess.Popen([sys.executable, "-m", "esr_cli.cli.main", *LONG], cwd=ROOT,
                            env=esr_env(tmp_path / "store", ESR_FAULT="during_save@1:hang"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()

    def wait_for(text: str) -> None:
        deadline = time.monotonic() + 300
        while not any(text in line for line in lines):
            assert proc.poll() is None and time.monotonic() < deadline, "".join(lines)
            time.sleep(0.05)

    try:
        wait_for("fault: hanging at during_save")
        proc.send_signal(signal.SIGINT)
        wait_for("stopping (Ctrl-C)")
        time.sleep(0.5)
        assert proc.poll() is None  # the first waits for the checkpoint
        sent = time.monotonic()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=5) == 130 and time.monotonic() - sent < 1
    finally:
        proc.kill()
    reader.join(timeout=10)
    assert "second stop signal: exiting at once" in "".join(lines)


def test_the_same_signal_twice_at_once_is_one_request_and_a_later_one_a_second(monkeypatch):
    """`timeout` sends its signal to the process and then to its group: the same signal again
    within SAME_REQUEST_S is the first request; later, or another signal, is a second one, which
    leaves at once."""
    from types import SimpleNamespace

    from esr_cli.runner import stop_requests as sr

    class Left(Exception):
        pass

    def leave(code):
        raise Left(code)

    monkeypatch.setattr(sr, "os", SimpleNamespace(_exit=leave, write=lambda fd, data: len(data)))
    for first, then, after_s, leaves in ((signal.SIGTERM, signal.SIGTERM, 0.01, None),
                                         (signal.SIGTERM, signal.SIGTERM, 0.5, 143),
                                         (signal.SIGTERM, signal.SIGINT, 0.01, 130)):
        clock = iter([100.0, 100.0 + after_s])
        monkeypatch.setattr(sr, "time", SimpleNamespace(monotonic=lambda: next(clock)))
        requests = sr.StopRequests()
        requests(first, None)
        if leaves is None:
            requests(then, None)
            assert requests.signum == first
        else:
            with pytest.raises(Left) as left:
                requests(then, None)
            assert left.value.args == (leaves,)


def test_chunks_are_timed_by_a_one_epoch_warm_up_then_bounded_by_the_checkpoint_interval():
    from esr_cli.runner.loop import CHECKPOINT_EVERY_S, chunk_length

    assert chunk_length(50, None, 10_000) == 1  # not timed yet: the warm-up
    assert chunk_length(50, 1.0, 10_000) == 50
    assert chunk_length(50, CHECKPOINT_EVERY_S / 13, 10_000) == 8  # 50 would run past the interval: a power of two
    assert chunk_length(50, CHECKPOINT_EVERY_S / 16, 10_000) == 16
    assert chunk_length(50, CHECKPOINT_EVERY_S / 49, 10_000) == 32
    # an epoch's time drifting under load (12 to 15 s at a 600 s interval) gives one length, not four
    assert {chunk_length(50, CHECKPOINT_EVERY_S / fits, 10_000) for fits in (40, 42, 45, 48)} == {32}
    assert chunk_length(50, 2 * CHECKPOINT_EVERY_S, 10_000) == 1  # never fewer than one epoch
    assert chunk_length(50, 1.0, 7) == 7  # never past the end


def test_the_estimate_names_the_epoch_time_the_run_the_quick_budget_and_a_run_over_a_day():
    from esr_cli.common import specs
    from esr_cli.model.train import make_trainer
    from esr_cli.runner.run_progress import TrainingReport, progress_bar, quick_estimate

    spec, quick = (specs.load("experiments/grid_2.yaml", b) for b in ("paper", "quick"))
    console = Console(file=io.StringIO(), width=400)
    report = TrainingReport(spec, make_trainer(spec), console, progress_bar(console), "k" * 64, quick)
    report.on_start(0, 10_000)
    report.on_chunk(1, 10_000, {"return": [1.0] * 20}, 45.0)
    text = console.file.getvalue()
    assert "grid_2 [paper]: 45 s an epoch (20 seeds); 10,000 epochs: about 5.2 days here; " \
           "--budget quick: about 5.6 min" in text  # 45 s / 20 seeds x 1 seed x 150 epochs
    assert "note: this run needs more than a day on this machine (5.2 days); it goes on" in text
    assert "epoch 1/10,000  last-epoch return 1.00" in text and "ETA 5.2 days" in text  # a log file's line per chunk

    resumed = Console(file=io.StringIO(), width=400)  # the run's epoch 4 of 4 is its one chunk
    report = TrainingReport(spec, make_trainer(spec), resumed, progress_bar(resumed), "k" * 64, None)
    report.on_start(3, 4)
    report.on_chunk(4, 4, {"return": [1.0] * 20}, 45.0)
    assert "resuming kkkkkkkkkkkk from epoch 3 of 4\ngrid_2 [paper]: 45 s an epoch (20 seeds); 1 epoch left: about 45 s here" \
           in resumed.file.getvalue()

    coop = specs.load("experiments/cramped_room.yaml", "paper")
    assert quick_estimate(coop, specs.load("experiments/cramped_room.yaml", "quick"), 1.0)[0] is None


@pytest.mark.slow  # trains the shared smoke run
def test_a_run_logged_to_a_file_says_when_it_compiled_and_how_long_it_takes(smoke_run):
    _, _, proc = smoke_run  # stderr was a pipe
    err = proc.stderr
    assert "grid_2 [smoke]: compiling..." in err and "grid_2 [smoke]: compiled in " in err
    assert "an epoch (1 seed); 2 epochs: about " in err
    assert err.index("compiled in") < err.index("an epoch") < err.index("epoch 2/2")

