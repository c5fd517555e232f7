"""TensorBoard event files of a run (esr_cli/core/event_log.py), read back with TensorBoard's
own reader: the same values as metrics.jsonl, per seed and as the seeds' mean, and written
afresh from the metrics kept when a run resumes."""

import json
import math

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from conftest import esr
from esr_cli.core.event_log import EVENTS_DIR, EventLog


def scalars(path):
    acc = EventAccumulator(str(path), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: {e.step: e.value for e in acc.Scalars(tag)} for tag in acc.Tags()["scalars"]}


def test_a_trained_run_has_event_files_with_the_values_of_its_metrics(tmp_path):
    proc = esr("train", "experiments/grid_2.yaml", "-b", "smoke", "--set", "train.seeds=2", store=tmp_path)
    run = proc.stdout.strip().splitlines()[-1]
    rows = [json.loads(line) for line in open(f"{run}/metrics.jsonl")]
    per_seed = {s: scalars(f"{run}/{EVENTS_DIR}/seed_{s}") for s in (0, 1)}
    mean = scalars(f"{run}/{EVENTS_DIR}/mean")
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
    assert scalars(tmp_path / EVENTS_DIR / "seed_3")["return"] == {1: 1.0, 2: 2.0, 3: 3.0}
    assert scalars(tmp_path / EVENTS_DIR / "seed_7")["return"] == {1: -1.0, 3: -1.0}  # a NaN is left out
    assert scalars(tmp_path / EVENTS_DIR / "mean")["return"] == {1: 0.0, 2: 2.0, 3: 1.0}
    EventLog(tmp_path, [3, 7], [row(1)]).close()  # resumed at epoch 1: epochs 2 and 3 were not kept
    assert scalars(tmp_path / EVENTS_DIR / "seed_3")["return"] == {1: 1.0}
