"""The real CLI end to end on smoke budgets: train, cache hit, ls, show, verify, eval, resume."""

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
from conftest import esr


@pytest.mark.slow  # trains the shared smoke run
def test_train_commits_a_complete_artifact(smoke_run):
    store, path, proc = smoke_run
    assert path.is_dir() and path.parent.parent.name == "runs"
    m = json.loads((path / "manifest.json").read_text())
    assert m["status"] == "complete" and m["name"] == "grid_2" and m["budget"] == "smoke"
    assert set(m["key_components"]) == {"kind", "spec", "budget", "code", "toolchain", "dependencies"}
    rows = [json.loads(line) for line in (path / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2]
    for name in ("return", "success", "mi_estimate", "contrastive_accuracy", "beta", "policy_entropy", "critic_loss", "repr_loss"):
        assert len(rows[-1][name]) == 1 and rows[-1][name][0] is not None, name
    assert (path / "figures" / "learning_curve.png").stat().st_size > 1000
    assert (path / "spec.yaml").exists() and list((path / "checkpoints").iterdir())
    assert not list(path.parent.glob("*.partial"))
    # stderr is not a terminal here: a plain line per chunk (1 epoch at smoke) for a log file
    assert "grid_2 [smoke] epoch 1/2  last-epoch return" in proc.stderr and "grid_2 [smoke] epoch 2/2  last-epoch return" in proc.stderr


@pytest.mark.slow
def test_repeat_is_a_cache_hit_that_trains_nothing(smoke_run):
    store, path, _ = smoke_run
    before = {f: f.stat().st_mtime_ns for f in path.rglob("*")}
    # The fault point kills the process if it ever reaches compiling a training program.
    proc = esr("train", "experiments/grid_2.yaml", "--budget", "smoke", store=store, ESR_FAULT="compile@1")
    assert proc.stdout.strip() == str(path)
    assert {f: f.stat().st_mtime_ns for f in path.rglob("*")} == before
    assert "cache hit" in proc.stderr


@pytest.mark.slow
def test_ls_show_verify(smoke_run):
    store, path, _ = smoke_run
    ls = esr("ls", store=store, COLUMNS="300").stdout  # rich wraps narrow columns off a terminal
    assert "grid_2" in ls and path.name[:12] in ls and "complete" in ls
    show = esr("show", path.name[:8], "--json", store=store).stdout
    assert '"key_components"' in show and '"toolchain"' in show and '"code"' in show
    readable = esr("show", path.name[:8], store=store).stdout
    assert "final return:" in readable and "last 10% of epochs" in readable and "overrides:" in readable
    assert f"key:           {path.name}" in readable and "{" not in readable
    assert esr("verify", path.name, store=store).returncode == 0


@pytest.mark.slow
def test_ls_names_a_finished_run_whose_metrics_were_cut_short(smoke_run, tmp_path):
    """A finished run logs every epoch: `ls` lists a copy whose metrics.jsonl was emptied as it
    is, with one line saying so (and `verify` finds the changed file)."""
    import shutil

    store = tmp_path / "store"
    shutil.copytree(smoke_run[0], store)
    run = store / smoke_run[1].relative_to(smoke_run[0])
    assert "metrics short" not in esr("ls", store=store).stderr
    (run / "metrics.jsonl").write_text("")
    listed = esr("ls", store=store)
    assert listed.returncode == 0 and run.name[:12] in listed.stdout
    assert " ".join(listed.stderr.split()) == (f"metrics short of the run: {run / 'metrics.jsonl'} logs 0 of its 2 epochs; "
                                               "`esr verify` checks its files")
    assert esr("verify", run.name, store=store, check=False).returncode == 1


@pytest.mark.slow
def test_ls_json_filters_and_piped_cells_in_full(smoke_run):
    store, path, _ = smoke_run
    rows = json.loads(esr("ls", "--json", store=store).stdout)
    run = next(r for r in rows if r["key"] == path.name)
    assert set(run) == {"kind", "name", "key", "path", "budget", "seeds", "status", "epochs", "epochs_total",
                        "final_return", "return_of", "created", "method", "env", "overrides"}
    assert (run["kind"], run["name"], run["budget"], run["status"], run["method"]) == ("runs", "grid_2", "smoke", "complete", "esr")
    assert run["overrides"] == [] and run["created"].startswith("20") and run["epochs"] == run["epochs_total"]
    assert json.loads(esr("ls", "--json", "--budget", "paper", store=store).stdout) == []
    assert json.loads(esr("ls", "--json", "--method", "random", "--kind", "runs", store=store).stdout) == []
    assert [r["key"] for r in json.loads(esr("ls", "--json", "--spec", "grid_2", "--kind", "runs", store=store).stdout)] \
        == [r["key"] for r in rows if r["kind"] == "runs" and r["name"] == "grid_2"]
    piped = esr("ls", store=store, COLUMNS="80").stdout  # a pipe: no terminal, 80 columns reported
    assert "…" not in piped and "..." not in piped and "complete" in piped and "budget" in piped
    assert esr("ls", "--kind", "bogus", store=store, check=False).returncode == 2


@pytest.mark.slow  # trains the shared smoke run
def test_unknown_key_is_a_one_line_error(smoke_run):
    store, _, _ = smoke_run
    proc = esr("show", "ffffffff", store=store, check=False)
    assert proc.returncode == 2 and "no artifact" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.slow
def test_eval_writes_summary_gif_and_curve(smoke_run):
    store, run_path, _ = smoke_run
    proc = esr("eval", "experiments/grid_2.yaml", "--budget", "smoke", store=store)
    path = Path(proc.stdout.strip().splitlines()[-1])
    summary = json.loads((path / "summary.json").read_text())
    assert set(summary["results"]) == {"sample", "greedy"}
    assert summary["run"] == run_path.name
    for r in summary["results"].values():
        assert 0 <= r["success_mean"] <= 1 and 0 <= r["return_mean"] <= 50
    assert (path / "rollout.gif").stat().st_size > 500 and (path / "learning_curve.png").exists()
    from PIL import Image

    gif = Image.open(path / "rollout.gif")
    durations = []
    for i in range(10_000):
        try:
            gif.seek(i)
        except EOFError:
            break
        durations.append(gif.info["duration"])
    assert len(durations) == 50 + 1 and min(durations) > 0  # one frame per state of the 50-step episode
    assert min(gif.size) >= 360
    assert "(1 seed)" in proc.stderr and "± 0.00" not in proc.stderr  # one seed claims no spread
    again = esr("eval", run_path.name, store=store)
    assert "cache hit" in again.stderr and again.stdout.strip() == str(path)


@pytest.mark.slow  # trains the shared smoke run
def test_eval_of_an_untrained_spec_says_how_to_train(smoke_run):
    store, _, _ = smoke_run
    proc = esr("eval", "experiments/grid_2.yaml", "--budget", "smoke", "--set", "learner.gamma=0.5", store=store, check=False)
    assert proc.returncode == 2 and "esr train experiments/grid_2.yaml" in proc.stderr


@pytest.mark.slow
def test_a_spec_trained_only_at_another_budget_says_which_and_the_option(smoke_run):
    store, _, _ = smoke_run
    proc = esr("eval", "experiments/grid_2.yaml", store=store, check=False)
    assert proc.returncode == 2 and "grid_2 (paper) is not trained" in proc.stderr
    assert "the store has grid_2 at --budget smoke (finished)" in proc.stderr


@pytest.mark.slow
def test_random_robot_runs_on_the_same_runner(smoke_store):
    proc = esr("train", "experiments/grid_2_random.yaml", "--budget", "smoke", store=smoke_store)
    path = Path(proc.stdout.strip().splitlines()[-1])
    row = json.loads((path / "metrics.jsonl").read_text().splitlines()[-1])
    assert row["return"][0] is not None and row["critic_loss"] == [None]  # learns nothing, by design


def test_interrupted_run_resumes_to_the_same_result(tmp_path):
    """SIGINT after the first chunk: saved, stopped; the second call resumes; the result equals
    an uninterrupted run's bit for bit."""
    from esr_cli.common import specs, stops
    from esr_cli.model.train import make_trainer
    from esr_cli.runner import loop

    spec = specs.load("experiments/grid_2.yaml", "smoke")
    trainer = make_trainer(spec)
    whole = tmp_path / "whole"
    whole.mkdir()
    loop.train(trainer, whole)

    cut = tmp_path / "cut"
    cut.mkdir()
    try:
        loop.train(trainer, cut, on_chunk=lambda *a: os.kill(os.getpid(), signal.SIGINT))
        raise AssertionError("the run did not stop")
    except stops.Interrupted as e:
        assert e.epoch == 1
    assert len(loop.read_rows(cut)) == 1
    loop.train(trainer, cut)
    assert loop.read_rows(cut) == loop.read_rows(whole)
    a, b = loop.final_state(trainer, whole), loop.final_state(trainer, cut)
    for x, y in zip(__import__("jax").tree.leaves(a), __import__("jax").tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_runs_can_share_a_gpu_unless_the_user_says_otherwise(tmp_path, monkeypatch):
    """JAX's default takes 75% of a GPU for the first process; esr's commands turn that off
    (so runs side by side fit), and leave a value the user set alone."""
    import os

    from esr_cli.cli.main import main

    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE", raising=False)
    assert main(["--store", str(tmp_path), "ls"]) == 0
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
    monkeypatch.setenv("XLA_PYTHON_CLIENT_PREALLOCATE", "true")
    assert main(["--store", str(tmp_path), "ls"]) == 0
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "true"


def test_the_command_list_gives_each_command_one_unbroken_summary():
    from esr_cli.cli.main import app

    commands = [*app.registered_commands, *(c for g in app.registered_groups for c in g.typer_instance.registered_commands)]
    for command in commands:  # wrapped to the terminal by the list, never at the source's line breaks
        summary = command.short_help or (command.callback.__doc__ or "").strip().split("\n\n")[0]
        assert summary and "\n" not in summary, command.callback.__name__


def test_version_names_the_package_and_the_training_code_digest(tmp_path):
    from importlib import metadata

    from esr_cli.storage import provenance

    proc = esr("--version", store=tmp_path / "store")
    assert proc.stdout.startswith(f"esr-cli {metadata.version('esr-cli')}; training code {provenance.code_digest()[:8]}")
    assert not (tmp_path / "store").exists()  # nothing else done


def test_help_shows_flags_as_flags_and_values_with_their_type(tmp_path):
    text = esr("play", "--help", store=tmp_path, COLUMNS="200").stdout
    web = next(line for line in text.splitlines() if "--web " in line)
    port = next(line for line in text.splitlines() if "--port" in line)
    assert "<bool>" not in text and "<int>" in port and "<" not in web


@pytest.mark.slow
def test_plot_curve_draws_an_unfinished_run_and_says_so(tmp_path):
    store = tmp_path / "store"
    stopped = esr("train", "experiments/grid_2.yaml", "-b", "smoke", "--stop-after", "0s", store=store, check=False)
    assert stopped.returncode == 75, stopped.stderr
    partial = next(store.glob("runs/*/*.partial"))
    out = tmp_path / "curve.png"
    proc = esr("plot", "curve", str(partial), "--out", str(out), store=store)
    assert proc.stdout.strip() == str(out) and out.stat().st_size > 1000
    assert "at epoch 1" in proc.stderr
    bad = esr("plot", "curve", str(partial), "--budget", "quick", store=store, check=False)
    assert bad.returncode == 2 and "--budget does not apply" in bad.stderr
    # Its provenance goes beside it as curve.json: drawn again, that is replaced; a user's own
    # JSON of that name, or a folder there, is refused before anything is drawn.
    assert json.loads(out.with_suffix(".json").read_text())["artifacts"]
    assert esr("plot", "curve", str(partial), "--out", str(out), store=store).returncode == 0
    mine = tmp_path / "mine.png"
    mine.with_suffix(".json").write_text('{"precious": 1}')
    refused = esr("plot", "curve", str(partial), "--out", str(mine), store=store, check=False)
    assert refused.returncode == 2 and "mine.json exists and is not a figure's provenance" in " ".join(refused.stderr.split())
    assert mine.with_suffix(".json").read_text() == '{"precious": 1}' and not mine.exists()
    (tmp_path / "box.json").mkdir()
    refused = esr("plot", "curve", str(partial), "--out", str(tmp_path / "box.png"), store=store, check=False)
    assert refused.returncode == 2 and "box.json is a directory" in refused.stderr and not (tmp_path / "box.png").exists()


def test_a_library_thread_that_outlives_the_executors_ends_without_a_traceback(capsys):
    """After a command's last line, orbax's background thread may find the interpreter's
    executors shut down: that ends quietly, while any other thread's failure is still shown."""
    import threading

    from esr_cli.cli.main import _quiet_at_shutdown

    def fail(error):
        def run():
            raise error

        before = threading.excepthook
        threading.excepthook = _quiet_at_shutdown
        try:
            t = threading.Thread(target=run)
            t.start()
            t.join()
        finally:
            threading.excepthook = before
        return capsys.readouterr().err

    assert fail(RuntimeError("cannot schedule new futures after interpreter shutdown")) == ""
    assert fail(RuntimeError("cannot schedule new futures after shutdown")) == ""
    shown = fail(ValueError("a real failure"))
    assert "Traceback" in shown and "ValueError: a real failure" in shown
