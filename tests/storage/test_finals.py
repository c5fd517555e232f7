"""A run's metrics read back (esr_cli/storage/finals.py): only rows as training writes them, so a
damaged or forged metrics.jsonl shortens what tables and figures read instead of failing them."""

import json

import numpy as np
import pytest

from esr_cli.storage import finals


def _write(tmp_path, rows):
    (tmp_path / "metrics.jsonl").write_text("".join((r if isinstance(r, str) else json.dumps(r)) + "\n" for r in rows))
    return tmp_path


def _row(epoch, ret=(1.0, 2.0), **more):
    return {"epoch": epoch, "env_steps": 100 * epoch, "return": list(ret), **more}


def test_sound_rows_are_read_whole_and_their_finals_computed_by_hand(tmp_path):
    rows = [_row(e, (float(e), 2.0 * e), mi_estimate=[None, 0.5]) for e in range(1, 21)]
    run = _write(tmp_path, rows)
    assert finals.read_rows(run) == rows
    # the last 10% of 20 epochs is epochs 19 and 20: seed 0 (19 + 20) / 2, seed 1 (38 + 40) / 2
    assert finals.final_per_seed(rows).tolist() == [19.5, 39.0]
    out = finals.run_finals(run, ("return",))
    assert (out["seeds"], out["epochs"]) == (2, 20) and out["return"]["mean"] == pytest.approx(29.25)
    assert np.isnan(finals.final_per_seed(rows, "mi_estimate")[0])
    assert finals.run_progress(run) == (20, pytest.approx(29.25))


@pytest.mark.parametrize("bad", [
    {"epoch": 3, "env_steps": 300, "return": [10 ** 400, 1.0]},  # too large for a float
    {"epoch": 3, "env_steps": 300, "return": [1.7e308, 1.0]},  # beyond float32: training never logs it
    {"epoch": 3, "env_steps": 300, "return": [1.0, 2.0], "mi_estimate": [-1e39, 0.5]},
    {"epoch": 3, "env_steps": 300},  # no return
    {"epoch": 3, "env_steps": 300, "return": 5.0},  # a number where a list over seeds goes
    {"epoch": 3, "env_steps": 300, "return": [1.0]},  # another seed count
    {"epoch": 3, "env_steps": 300, "return": ["7", 1.0]},
    {"epoch": 3, "env_steps": 300, "return": [[1.0], 1.0]},
    {"epoch": 3, "env_steps": 300, "return": [True, 1.0]},
    {"epoch": 3, "env_steps": 300, "return": [1.0, 2.0], "mi_estimate": {"a": 1}},
    {"epoch": 3, "env_steps": "300", "return": [1.0, 2.0]},
    {"epoch": 2, "env_steps": 300, "return": [1.0, 2.0]},  # not after the epoch before
    {"epoch": 3000, "env_steps": 300, "return": [50.0, 50.0]},  # a gap: one row would stand for a run's last 10%
    {"epoch": None, "env_steps": 300, "return": [1.0, 2.0]},
    {"epoch": 3.0, "env_steps": 300, "return": [1.0, 2.0]},
    {"epoch": 10 ** 30, "env_steps": 300, "return": [1.0, 2.0]},
    {"env_steps": 300, "return": [1.0, 2.0]},
])
def test_reading_ends_at_the_first_row_that_is_not_an_epochs(tmp_path, bad):
    run = _write(tmp_path, [_row(1), _row(2), bad, _row(4)])
    assert finals.read_rows(run) == [_row(1), _row(2)]  # what follows is not trusted either
    assert finals.run_finals(run, ("return",))["epochs"] == 2
    assert finals.run_progress(run) == (2, 1.5)


def test_a_metrics_file_with_no_sound_row_reads_as_no_epoch(tmp_path):
    run = _write(tmp_path, ['{"epoch": "one"}', _row(2)])
    assert finals.read_rows(run) == [] and finals.run_progress(run) == (0, None)
    assert finals.read_rows(_write(tmp_path, [_row(2), _row(3)])) == []  # training's first epoch is 1
    out = finals.run_finals(run, ("return",))
    assert (out["seeds"], out["epochs"]) == (0, 0)


def test_json_esr_prints_is_strict_whatever_a_manifest_held():
    """A manifest from an archive may hold NaN or an infinity, which Python writes as non-JSON
    `NaN`: what `--json` prints is null there, so every JSON reader parses it."""
    from esr_cli.common.jsonl import dumps

    text = dumps({"summary": {"return": {"mean": float("nan"), "per_seed": [1.5, float("inf"), float("-inf")]}}, "k": (1, "a")})
    assert text == '{"summary": {"return": {"mean": null, "per_seed": [1.5, null, null]}}, "k": [1, "a"]}'
    json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))


def test_values_as_training_logs_them_are_read_and_summarised_without_a_warning(tmp_path):
    """float32's largest value, NaN and infinities (a diverged seed) are what training can log:
    read as logged, and a table's statistics over them neither overflow nor warn."""
    import warnings

    from esr_cli.common.stats import describe, format_summary

    big = float(np.finfo(np.float32).max)
    rows = [_row(e, (big, -big), success=[float("nan"), 0.5], mi_estimate=[float("inf"), 0.5]) for e in (1, 2)]
    run = _write(tmp_path, rows)
    read = finals.read_rows(run)
    assert len(read) == 2 and read[1]["return"] == [big, -big] and np.isnan(read[1]["success"][0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        summary = describe(finals.final_per_seed(read))
        assert np.isfinite(summary["mean"]) and np.isfinite(summary["se"]) and summary["se"] == pytest.approx(big)
        assert describe(finals.final_per_seed(read, "mi_estimate"))["missing"] == 1
        assert format_summary(summary) == "0.00 ± 3.40e+38; IQM 0.00 [-3.40e+38, 3.40e+38]"  # never 39 digits in a cell


def test_rows_beyond_a_runs_length_are_not_read_as_its_epochs(tmp_path):
    """A finished 2-epoch run whose metrics.jsonl goes on: tables read its 2 epochs; the check
    that names the file's disagreement (`esr verify`) still sees every row."""
    from esr_cli.storage.checkpoint_files import logged_epochs

    run = _write(tmp_path, [_row(e) for e in range(1, 6)])
    (run / "manifest.json").write_text(json.dumps({"kind": "runs", "key": "0" * 32, "files": {},
                                                   "key_components": {"spec": {"train": {"epochs": 2}}}}))
    assert [r["epoch"] for r in finals.read_rows(run)] == [1, 2] and finals.run_progress(run)[0] == 2
    assert logged_epochs(run) == [1, 2, 3, 4, 5]
    (run / "manifest.json").unlink()
    (run / "pending.json").write_text(json.dumps({"key_components": {"spec": {"train": {"epochs": 3}}}}))
    assert [r["epoch"] for r in finals.read_rows(run)] == [1, 2, 3]
    (run / "pending.json").write_text("[]")  # no record of its length: every sound row
    assert len(finals.read_rows(run)) == 5




@pytest.mark.parametrize("intruder", ["fifo", "link"])
def test_a_metrics_file_that_cannot_be_read_is_one_failure_naming_it(tmp_path, intruder):
    """A FIFO or a link where metrics.jsonl belongs: every reader of a run's rows (figures,
    evaluation, the checkpoint checks) ends with the line `esr ls` prints for it, exit 2, and a
    listing's progress is left blank instead."""
    import os

    from esr_cli.storage.checkpoint_files import logged_epochs

    path = tmp_path / "metrics.jsonl"
    os.mkfifo(path) if intruder == "fifo" else path.symlink_to("/dev/zero")
    for read in (finals.read_rows, finals.logged_rows, logged_epochs):
        with pytest.raises(finals.UnreadableMetrics) as e:
            read(tmp_path)
        assert e.value.exit_code == 2 and e.value.one_line().startswith(f"unreadable metrics: {path} is ")
        assert ("not a regular file" if intruder == "fifo" else "link") in e.value.problem
    assert finals.run_progress(tmp_path) == (0, None)
