"""TensorBoard event files of a run (esr_cli/runner/event_log.py), read back with TensorBoard's
own reader: the same values as metrics.jsonl, per seed and as the seeds' mean, and written
afresh from the metrics kept when a run resumes."""

import json
import math

import pytest
from conftest import esr
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from esr_cli.runner.event_log import EventLog
from esr_cli.storage.store import EVENTS_FOLDER


def scalars(path):
    acc = EventAccumulator(str(path), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: {e.step: e.value for e in acc.Scalars(tag)} for tag in acc.Tags()["scalars"]}


@pytest.mark.slow
def test_a_trained_run_has_event_files_with_the_values_of_its_metrics(tmp_path):
    proc = esr("train", "experiments/grid_2.yaml", "-b", "smoke", "--set", "train.seeds=2", store=tmp_path)
    run = proc.stdout.strip().splitlines()[-1]
    rows = [json.loads(line) for line in open(f"{run}/metrics.jsonl")]
    per_seed = {s: scalars(f"{run}/{EVENTS_FOLDER}/seed_{s}") for s in (0, 1)}
    mean = scalars(f"{run}/{EVENTS_FOLDER}/mean")
    names = [k for k, v in rows[0].items() if isinstance(v, list)]
    assert "return" in names and "return" in mean
    checked = 0
    for row in rows:
        for name in names:
            for i, value in enumerate(row[name]):
                if value is None:
                    assert row["epoch"] not in per_seed[i].get(name, {})
                    continue
                assert per_seed[i][name][row["epoch"]] == pytest.approx(value, rel=1e-6, abs=1e-6)
                checked += 1
            finite = [v for v in row[name] if v is not None]
            if finite:
                assert mean[name][row["epoch"]] == pytest.approx(sum(finite) / len(finite), rel=1e-6, abs=1e-6)
        assert mean["env_steps"][row["epoch"]] == row["env_steps"]
    assert checked > 0


def test_events_are_written_afresh_from_the_metrics_kept(tmp_path):
    def row(epoch):
        return {"epoch": epoch, "env_steps": 10 * epoch, "return": [float(epoch), math.nan if epoch == 2 else -1.0]}

    log = EventLog(tmp_path, [3, 7], [row(1), row(2)])
    log.append([row(3)])
    log.close()
    assert scalars(tmp_path / EVENTS_FOLDER / "seed_3")["return"] == {1: 1.0, 2: 2.0, 3: 3.0}
    assert scalars(tmp_path / EVENTS_FOLDER / "seed_7")["return"] == {1: -1.0, 3: -1.0}  # a NaN is left out
    assert scalars(tmp_path / EVENTS_FOLDER / "mean")["return"] == {1: 0.0, 2: 2.0, 3: 1.0}
    EventLog(tmp_path, [3, 7], [row(1)]).close()  # resumed at epoch 1: epochs 2 and 3 were not kept
    assert scalars(tmp_path / EVENTS_FOLDER / "seed_3")["return"] == {1: 1.0}


# ---------------------------------------------------------------- the wandb record (`esr train --wandb`)
def wandb_records(path):
    """The records of wandb's offline run file, read with wandb's own protobuf schema: the file
    is a 7-byte header (":W&B", a 2-byte magic, a version byte) and then LevelDB-log records in
    32 KiB blocks, each with a CRC, a length and a type (1 whole, 2 first, 3 middle, 4 last)."""
    import struct

    from wandb.proto import wandb_internal_pb2

    data, block = path.read_bytes(), 32768
    assert data[:4] == b":W&B"
    pos, pending = 7, b""
    while pos + 7 <= len(data):
        if block - pos % block < 7:  # a block's tail too short for a header is padding
            pos += block - pos % block
            continue
        _, length, kind = struct.unpack("<IHB", data[pos:pos + 7])
        if kind == 0:
            break
        pending += data[pos + 7:pos + 7 + length]
        pos += 7 + length
        if kind in (1, 4):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pending)
            pending = b""
            yield record


def wandb_history(folder):
    """(the offline run's record, {step: {name: value}}) of the one offline run in `folder`."""
    (path,) = folder.glob("wandb/offline-run-*/run-*.wandb")
    records = list(wandb_records(path))
    history = {}
    for r in records:
        if r.WhichOneof("record_type") == "history":
            items = {i.key or "/".join(i.nested_key): json.loads(i.value_json) for i in r.history.item}
            history[items.pop("_step")] = {k: v for k, v in items.items() if not k.startswith("_")}
    (run,) = [r.run for r in records if r.WhichOneof("record_type") == "run"]
    return run, history


@pytest.mark.slow
def test_a_run_trained_with_wandb_has_an_offline_record_of_its_metrics(tmp_path):
    proc = esr("train", "experiments/grid_2.yaml", "-b", "smoke", "--set", "train.seeds=2", "--wandb", store=tmp_path)
    run_dir = proc.stdout.strip().splitlines()[-1]
    key = run_dir.rstrip("/").split("/")[-1]
    assert not [line for line in proc.stderr.splitlines() if line.startswith("wandb:")]  # wandb's own lines are silenced
    run, history = wandb_history(tmp_path / "wandb" / key)
    assert run.run_id == key and run.display_name == "grid_2 (smoke)"
    assert json.loads(run.config.update[0].value_json) is not None
    rows = [json.loads(line) for line in open(f"{run_dir}/metrics.jsonl")]
    assert sorted(history) == [row["epoch"] for row in rows]
    for row in rows:
        logged = history[row["epoch"]]
        assert logged["env_steps/mean"] == row["env_steps"]
        for name, values in row.items():
            if not isinstance(values, list):
                continue
            for seed, value in enumerate(values):
                assert logged.get(f"{name}/seed_{seed}") == (None if value is None else pytest.approx(value, rel=1e-6))
            finite = [v for v in values if v is not None]
            if finite:
                assert logged[f"{name}/mean"] == pytest.approx(sum(finite) / len(finite), rel=1e-6)


@pytest.mark.slow
def test_the_wandb_record_is_written_afresh_from_the_metrics_kept(tmp_path):
    from esr_cli.runner.wandb_log import WandbLog

    def row(epoch):
        return {"epoch": epoch, "env_steps": 10 * epoch, "return": [float(epoch), -1.0]}

    log = WandbLog(tmp_path / "k", "k" * 32, "t", {"a": 1}, [3, 7], [row(1), row(2)])
    log.append([row(3)])
    log.close()
    _, history = wandb_history(tmp_path / "k")
    assert {step: h["return/seed_3"] for step, h in history.items()} == {1: 1.0, 2: 2.0, 3: 3.0}
    assert history[2]["return/mean"] == 0.5
    WandbLog(tmp_path / "k", "k" * 32, "t", {"a": 1}, [3, 7], [row(1)]).close()  # resumed at epoch 1
    _, history = wandb_history(tmp_path / "k")
    assert sorted(history) == [1]


def test_wandb_without_the_package_is_one_line_before_any_work(tmp_path, monkeypatch, capsys):
    import importlib.util

    from esr_cli.cli.main import main

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "wandb" else real(name, *a))
    assert main(["--store", str(tmp_path), "train", "experiments/grid_2.yaml", "-b", "smoke", "--wandb"]) == 2
    assert "--wandb needs the wandb package: pip install 'esr-cli[wandb]'" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
