"""Generated result tables in markdown (`esr tables`) and `esr sweep --results --any-code`."""

import json
import os
import shlex
from pathlib import Path

import pytest
from conftest import ROOT, esr

from esr_cli.recipes import sweep
from esr_cli.report import doc_tables
from esr_cli.storage import provenance
from esr_cli.storage.store import Store

GRID_2 = ROOT / "experiments" / "grid_2.yaml"
END = doc_tables.END


def one_run_suite(tmp_path: Path) -> Path:
    path = tmp_path / "one.yaml"
    path.write_text(f"name: one\nspecs: [{GRID_2}]\n")
    return path


def doc_with(tmp_path: Path, command: str, body: str = "") -> Path:
    path = tmp_path / "page.md"
    path.write_text(f"# A page\n\nSome text.\n<!-- {command} -->\n{body}{END}\n\nMore text.\n")
    return path


def test_a_tables_command_is_parsed_into_the_sweeps_own_options():
    cmd = doc_tables.parse_command("esr sweep experiments/suites/x.yaml --budget quick --results --markdown --any-code "
                                   "--metric return --metric mi_estimate --metric return --diagnose --exact", "page.md:4")
    # the checks in the table's own order, whatever the comment's
    assert cmd == doc_tables.SweepTable(Path("experiments/suites/x.yaml"), "quick", ("return", "mi_estimate"),
                                     ("exact", "diagnosis"), True)
    assert doc_tables.parse_command("esr sweep s.yaml --results --markdown --diagnose", "w").checks == ("diagnosis",)
    assert doc_tables.parse_command("esr sweep s.yaml --results --markdown", "w").budget == "paper"  # the CLI's default


@pytest.mark.parametrize("text,problem", [
    ("esr train experiments/grid_2.yaml", "a table's command is `esr sweep SUITE"),
    ("esr sweep --results --markdown", "a table's command is `esr sweep SUITE"),
    ("esr sweep s.yaml --results --markdown --store /elsewhere", "'--store' is not an option of a generated table"),
    ("esr sweep s.yaml --results --markdown ; rm -rf ~", "';' is not an option"),
    ("esr sweep s.yaml --results", "needs --markdown"),
    ("esr sweep s.yaml --markdown --metric", "--metric needs a value"),
    ("esr sweep s.yaml --results --markdown 'unclosed", "cannot split the command"),
])
def test_anything_but_a_sweep_table_in_a_block_is_refused_naming_file_and_line(text, problem):
    with pytest.raises(doc_tables.TableError) as e:
        doc_tables.parse_command(text, "docs/page.md:12")
    assert str(e.value).startswith("docs/page.md:12: ") and problem in str(e.value)


def test_blocks_are_found_between_their_comments_and_a_broken_one_is_named(tmp_path):
    path = doc_with(tmp_path, "esr sweep s.yaml --results --markdown", "| old |\n")
    (block,) = doc_tables.blocks(path, doc_tables.read_doc(path))
    assert (block.line, block.start, block.end) == (4, 4, 5)  # the table is line 5 (index 4), the end comment line 6
    unclosed = tmp_path / "unclosed.md"
    unclosed.write_text("<!-- esr sweep s.yaml --results --markdown -->\n| a |\n<!-- esr sweep t.yaml --results --markdown -->\n")
    with pytest.raises(doc_tables.TableError, match=r"unclosed.md:1: the table has no"):
        doc_tables.blocks(unclosed, doc_tables.read_doc(unclosed))
    stray = tmp_path / "stray.md"
    stray.write_text(f"text\n{END}\n")
    with pytest.raises(doc_tables.TableError, match=r"stray.md:2: .* without a table's opening comment"):
        doc_tables.blocks(stray, doc_tables.read_doc(stray))
    open_ended = tmp_path / "open.md"
    open_ended.write_text(f"text\n<!-- esr sweep s.yaml --results --markdown\n| old |\n{END}\n")
    with pytest.raises(doc_tables.TableError, match=r"open.md:2: a table's opening comment must end with ' -->'"):
        doc_tables.blocks(open_ended, doc_tables.read_doc(open_ended))


def test_the_comments_shown_in_a_code_block_are_an_example_not_a_table(tmp_path):
    page = tmp_path / "howto.md"
    page.write_text(f"Write a table so:\n```\n<!-- esr sweep experiments/suites/NAME.yaml --results --markdown -->\n"
                    f"(its output)\n{END}\n```\nand\n~~~md\n<!-- esr train x.yaml -->\n~~~\n")
    assert doc_tables.blocks(page, doc_tables.read_doc(page)) == []


def test_a_file_that_is_not_a_markdown_page_is_refused_before_any_work(tmp_path):
    binary = tmp_path / "b.md"
    binary.write_bytes(b"\xff\xfe\x00text")
    with pytest.raises(doc_tables.TableError, match="not UTF-8 text"):
        doc_tables.read_doc(binary)
    big = tmp_path / "big.md"
    with big.open("wb") as f:
        f.truncate(doc_tables.MAX_DOC_BYTES + 1)
    with pytest.raises(doc_tables.TableError, match="4,194,305 bytes, more than the 4,194,304 esr reads"):
        doc_tables.read_doc(big)
    fifo = tmp_path / "pipe.md"
    os.mkfifo(fifo)
    with pytest.raises(doc_tables.TableError, match="pipe.md: not a regular file"):
        doc_tables.read_doc(fifo)  # never waits for a writer


def test_a_page_with_crlf_line_ends_keeps_them_and_a_lone_cr_stays_in_its_line(tmp_path):
    page = tmp_path / "p.md"
    page.write_bytes(b"# t\r\na\rb\r\n")
    assert doc_tables.read_doc_and_newline(page) == (["# t", "a\rb", ""], "\r\n")
    page.write_bytes(b"# t\na\r\n")
    assert doc_tables.read_doc_and_newline(page) == (["# t", "a\r", ""], "\n")


def test_a_bad_table_in_one_page_leaves_every_page_as_it_was(tmp_path):
    suite = one_run_suite(tmp_path)
    good = doc_with(tmp_path, f"esr sweep {suite} --budget smoke --results --markdown", "| a stale table |\n")
    bad = tmp_path / "bad.md"
    bad.write_text(f"<!-- esr sweep {suite} --budget smoke --results --markdown --plot -->\n{END}\n")
    before = good.read_bytes()
    with pytest.raises(doc_tables.TableError, match="--plot"):
        doc_tables.update([good, bad], Store(tmp_path / "store"))
    assert good.read_bytes() == before


@pytest.mark.slow
def test_tables_writes_the_sweeps_own_table_and_check_fails_when_it_is_edited(smoke_run, tmp_path):
    store, run_path, _ = smoke_run
    suite = one_run_suite(tmp_path)
    command = f"esr sweep {suite} --budget smoke --results --markdown --metric return"
    page = doc_with(tmp_path, command, "| a stale table |\n")
    before = page.read_text()

    stale = esr("tables", "--check", str(page), store=store, check=False)
    assert stale.returncode == 1 and "| a stale table |" in stale.stderr and "generated tables are stale" in stale.stderr
    assert page.read_text() == before  # --check writes nothing

    esr("tables", str(page), store=store)
    table = esr("sweep", str(suite), "--budget", "smoke", "--results", "--markdown", "--metric", "return", store=store).stdout
    text = page.read_text()
    assert f"<!-- {command} -->\n{table.rstrip()}\n{END}\n" in text  # exactly what the sweep prints
    assert text.startswith("# A page\n\nSome text.\n") and text.endswith("\n\nMore text.\n")  # the rest untouched
    assert esr("tables", "--check", str(page), store=store).returncode == 0

    # A number changed by hand in the committed table makes the check fail, naming the line.
    last = json.loads((run_path / "metrics.jsonl").read_text().splitlines()[-1])
    shown = f"{last['return'][0]:.2f}"
    page.write_text(text.replace(shown, "99.99", 1))
    edited = esr("tables", "--check", str(page), store=store, check=False)
    assert edited.returncode == 1
    removed = [line for line in edited.stderr.splitlines() if line.startswith("-|")]
    added = [line for line in edited.stderr.splitlines() if line.startswith("+|")]
    assert len(removed) == len(added) == 1 and "99.99" in removed[0] and shown in added[0]

    # A block whose command is not a sweep table stops with exit 2 and its file and line.
    bad = doc_with(tmp_path, "esr train experiments/grid_2.yaml")
    proc = esr("tables", str(bad), store=store, check=False)
    assert proc.returncode == 2 and f"{bad}:4: a table's command is" in proc.stderr


def copy_run_under_key(run_path: Path, store: Path, key: str, edit=lambda manifest: None) -> tuple[Path, dict]:
    """A finished run copied into `store` under another key, as other training code would have
    keyed it, its manifest changed by `edit` -> (the copy, its manifest)."""
    import shutil

    copy = store / "runs" / key[:2] / key
    shutil.copytree(run_path, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["key"] = key
    edit(manifest)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    return copy, manifest


@pytest.mark.slow
def test_any_code_reads_a_run_of_the_same_spec_made_by_other_training_code(smoke_run, tmp_path, monkeypatch):
    store, run_path, _ = smoke_run
    suite_path = one_run_suite(tmp_path)
    own = sweep.results(sweep.load_suite(suite_path, "smoke"), Store(store), ("return",))
    assert own[0]["state"] == "done" and "made_by" not in own[0]  # this code made it: nothing to say

    # Other training code: every key changes, so the run is missing under it...
    monkeypatch.setattr(provenance, "code_digest", lambda *a, **k: "f" * 32)
    suite = sweep.load_suite(suite_path, "smoke")
    assert suite.runs[0].key != own[0]["key"]
    (missing,) = sweep.results(suite, Store(store), ("return",))
    assert missing["state"] == "missing"
    # ...and --any-code finds the run of the same spec, budget and seeds, and says which code made it.
    (found,) = sweep.results(suite, Store(store), ("return",), any_code=True)
    commit = provenance.origin(json.loads((run_path / "manifest.json").read_text())).commit
    assert found["state"] == "done" and found["key"] == own[0]["key"] and found["return"] == own[0]["return"]
    assert found["made_by"].startswith(f"commit {commit[:7] if commit else 'unknown'}")
    md = sweep.results_markdown(suite, [found], ("return",))
    assert f"| grid_2 ({found['made_by']}) | esr |" in md
    assert sweep.OTHER_CODE_NOTE in md

    # --status names the run while it stays missing under this code; --status --any-code counts it done.
    (noted,) = sweep.noting_runs_made_elsewhere(sweep.status(suite, Store(store)), Store(store))
    assert noted.state == "missing" and noted.note.startswith(f"{own[0]['key'][:12]} made by other code ({found['made_by']})")
    (taken,) = sweep.with_runs_made_elsewhere(sweep.status(suite, Store(store)), Store(store))
    assert taken.state == "done" and taken.made_by == found["made_by"] and taken.run.key == own[0]["key"]
    # A sweep says so before it trains the run again under this code.
    printed: list[str] = []
    console = type("Console", (), {"print": lambda self, *a, **k: printed.append(" ".join(map(str, a)))})()
    monkeypatch.setattr(sweep, "_run_local", lambda todo, *a: printed.append(f"trains {[s.run.key for s in todo]}"))
    sweep.run_suite(suite, "smoke", "local", Store(store), console)
    assert any(line.startswith("1 of them finished under other training code") for line in printed)
    assert f"trains {[suite.runs[0].key]}" in printed

    # A run of another spec (here other seeds) is never taken for it.
    seeds = tmp_path / "seeds.yaml"
    seeds.write_text(f"name: seeds\nspecs: [{GRID_2}]\nset: {{train.seeds: [7]}}\n")
    (other,) = sweep.results(sweep.load_suite(seeds, "smoke"), Store(store), ("return",), any_code=True)
    assert other["state"] == "missing" and "made_by" not in other


@pytest.mark.slow
def test_any_code_reads_a_run_made_before_a_field_with_a_default_existed(smoke_run, tmp_path, monkeypatch):
    """A run made by code that had no `method.future` yet (its spec.yaml and key components lack
    the field) trained what the field's default trains: --any-code reads it for a spec at the
    default, as the reproduction report does, and never for a spec that sets another value."""
    import yaml

    store, run_path, _ = smoke_run
    older = tmp_path / "store"
    key = "ab" * 16

    def without_future(manifest: dict) -> None:
        assert manifest["key_components"]["spec"]["method"].pop("future") == "full"

    copy, _ = copy_run_under_key(run_path, older, key, without_future)
    spec = yaml.safe_load((copy / "spec.yaml").read_text())
    del spec["method"]["future"]
    (copy / "spec.yaml").write_text(yaml.safe_dump(spec))
    monkeypatch.setattr(provenance, "code_digest", lambda *a, **k: "f" * 32)  # this checkout made nothing

    (found,) = sweep.results(sweep.load_suite(one_run_suite(tmp_path), "smoke"), Store(older), ("return",), any_code=True)
    assert found["state"] == "done" and found["key"] == key
    human = tmp_path / "human.yaml"
    human.write_text(f"name: human\nspecs: [{GRID_2}]\nset: {{method.future: human}}\n")
    (other,) = sweep.results(sweep.load_suite(human, "smoke"), Store(older), ("return",), any_code=True)
    assert other["state"] == "missing"


@pytest.mark.slow
def test_train_names_a_finished_run_of_its_spec_made_by_other_code(smoke_run, tmp_path):
    """A store whose run of the spec has another key (other training code made it): `esr train`
    says so before it trains again under this code; its own finished run is a cache hit, unremarked."""
    store, run_path, _ = smoke_run
    other = tmp_path / "store"
    key = "cd" * 16
    _, manifest = copy_run_under_key(run_path, other, key)

    proc = esr("train", str(GRID_2), "--budget", "smoke", "--stop-after", "1s", store=other, check=False)
    commit = provenance.origin(manifest).commit
    assert (f"note: {key[:12]} in this store is a finished run of this spec, budget and seeds made by other code "
            f"(commit {commit[:7] if commit else 'unknown'}") in proc.stderr
    again = esr("train", str(GRID_2), "--budget", "smoke", store=store)
    assert "cache hit" in again.stderr and "note:" not in again.stderr


def test_any_code_is_refused_where_it_would_change_nothing(tmp_path):
    suite = one_run_suite(tmp_path)
    for args, problem in ((["--any-code"], "--any-code applies with --status or --results only"),
                          (["--results", "--any-code", "--plot"], "--any-code applies to the table")):
        proc = esr("sweep", str(suite), "--budget", "smoke", *args, store=tmp_path / "store", check=False)
        assert proc.returncode == 2 and problem in proc.stderr


def test_a_missing_run_in_a_page_is_named_by_a_command_any_checkout_and_store_can_run(tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    monkeypatch.delenv("ESR_STORE", raising=False)
    suite = one_run_suite(tmp_path)
    command = doc_tables.parse_command(f"esr sweep {suite} --budget smoke --results --markdown", "page.md:1")
    lines = command.lines(Store(tmp_path / "somewhere" / "store"), "page.md:1")
    (row,) = [line for line in lines if line.startswith("| grid_2 |")]
    # Not `esr --store /tmp/...` nor the spec's absolute path: the page's reader has neither.
    assert "| missing: `esr train experiments/grid_2.yaml --budget smoke` |" in row


CRAMPED = ROOT / "experiments" / "cramped_room.yaml"
BC = "human={kind: bc}"


def test_a_calibration_table_command_is_parsed_into_the_calibrate_options():
    cmd = doc_tables.parse_command(f"esr human calibrate {CRAMPED} experiments/coord_ring.yaml --set '{BC}' "
                                   "--human-seeds 2 --episodes 50 --markdown", "page.md:4")
    assert cmd == doc_tables.CalibrationTable((CRAMPED, Path("experiments/coord_ring.yaml")), "paper", (BC,), 2, 50)
    assert doc_tables.parse_command(f"esr human calibrate {CRAMPED} --markdown", "w").human_seeds == 3  # the CLI's defaults
    for text, problem in (
            (f"esr human calibrate {CRAMPED}", "`esr human calibrate SPEC... --markdown"),
            ("esr human calibrate --markdown", "`esr human calibrate SPEC... --markdown"),
            (f"esr human calibrate {CRAMPED} --markdown --json", "'--json' is not an option of a calibration table"),
            (f"esr human calibrate {CRAMPED} --markdown --human-seeds 0", "--human-seeds takes a whole number from 1 to 64"),
            (f"esr human calibrate {CRAMPED} --markdown --episodes 1e9", "--episodes takes a whole number from 2 to 100,000"),
            (f"esr human calibrate {CRAMPED} --markdown --set", "--set needs a value"),
            ("esr human build experiments/cramped_room.yaml", "or `esr human calibrate SPEC... --markdown`")):
        with pytest.raises(doc_tables.TableError) as e:
            doc_tables.parse_command(text, "docs/page.md:9")
        assert str(e.value).startswith("docs/page.md:9: ") and problem in str(e.value), text


def _stored_calibration(store: Store, summary: dict, **changes):
    """A calibration artifact of cramped room's BC human (2 humans, 3 episodes) holding `summary`,
    its key components changed by `changes` (another code's, say)."""
    from esr_cli.common import specs
    from esr_cli.report import stored_calibrations
    from esr_cli.storage.artifacts import Recipe, ensure
    from esr_cli.storage.store import CALIBRATION_KIND

    spec = specs.load(CRAMPED, "paper", [BC])
    comps = {**stored_calibrations.components(spec, 2, 3), **changes}
    return ensure(Recipe(CALIBRATION_KIND, spec.name, comps, lambda _path, _store: summary), store)


def _summary(random_mean=30.0):
    per = {"random": [random_mean - 1, random_mean + 1], "stay": [10.0, 12.0], "self": [120.0, 130.0]}
    return {"returns": {p: {"mean": sum(v) / 2, "se": 1.0, "per_human": v} for p, v in per.items()}}


def test_a_calibration_table_reads_the_stored_calibration_and_plays_nothing(tmp_path):
    store = Store(tmp_path / "store")
    table = doc_tables.CalibrationTable((CRAMPED,), "paper", (BC,), 2, 3)
    with pytest.raises(doc_tables.TableError) as e:
        table.lines(store, "page.md:3")
    assert "page.md:3: the store has no calibration of cramped_room's human (bc 64x64 stay_weight=0.1 epochs=60, " \
           "2 human(s), 3 episodes)" in str(e.value)
    assert f"`esr human calibrate {CRAMPED} --budget paper --set {shlex.quote(BC)} --human-seeds 2 --episodes 3` makes it" in str(e.value)
    mine = _stored_calibration(store, _summary(34.63))
    lines = table.lines(store, "page.md:3")
    assert lines[2] == ("| cramped_room | cramped_room | bc 64x64 stay_weight=0.1 epochs=60 | 34.63 ± 1.00 | 11.00 ± 1.00 "
                        "| 125.00 ± 1.00 | 69.26 | 0.50 |")
    assert lines[-1].startswith("2 human(s) per layout, 3 episodes each; score: needs the three paper layouts")
    # another code's calibration of the same human: this code's is preferred; without it, the
    # other is read and its commit named
    _stored_calibration(store, _summary(50.0), code="0" * 32)
    assert table.lines(store, "page.md:3")[2] == lines[2]
    import shutil
    shutil.rmtree(mine.path)
    lines = table.lines(store, "page.md:3")
    assert "| 50.00 ± 1.00 |" in lines[2]
    assert lines[-1].startswith("Calibrated by code other than this checkout's") and "cramped_room (commit" in lines[-1]


@pytest.mark.parametrize("damage", [
    {"returns": "all good"},
    {"returns": {"random": {"mean": "9" * 500, "se": 1.0, "per_human": [1.0]}}},
    {"returns": {p: {"mean": 1.0, "se": 1.0, "per_human": ["\x1b[2J"]} for p in ("random", "stay", "self")}},
    {"returns": {p: {"mean": float("nan"), "se": 1.0, "per_human": [1.0, 1.0]} for p in ("random", "stay", "self")}},
    {"returns": {p: {"mean": 1e300, "se": 1.0, "per_human": [1.0, 1.0]} for p in ("random", "stay", "self")}},
    {"returns": {p: {"mean": 1.0, "se": -1.0, "per_human": [1.0, 1.0]} for p in ("random", "stay", "self")}},
    {"returns": {p: {"mean": 1.0, "se": 1.0, "per_human": [1.0]} for p in ("random", "stay", "self")}},  # 1 of 2 humans
])
def test_a_damaged_stored_calibration_is_named_in_one_line_never_shown(tmp_path, damage):
    store = Store(tmp_path / "store")
    built = _stored_calibration(store, damage)
    with pytest.raises(doc_tables.TableError) as e:
        doc_tables.CalibrationTable((CRAMPED,), "paper", (BC,), 2, 3).lines(store, "page.md:3")
    assert str(e.value) == (f"page.md:3: {built.path}: the stored calibration's summary is damaged: remove it and run "
                            "`esr human calibrate` again")


def test_a_calibration_is_asked_for_by_the_humans_recipe_not_by_how_the_spec_names_it():
    """A preset and its values written out are one calibration; the seeds and the episode count
    are part of what is asked, the code that made it is not."""
    from esr_cli.common import specs
    from esr_cli.recipes.ppo_humans import EPISODE_STEPS
    from esr_cli.report import stored_calibrations as sc

    preset = specs.load(CRAMPED, "paper", [BC, "human.preset=paper_random"])
    written = specs.load(CRAMPED, "paper", [BC, "human.stay_weight=0.05"])
    default = specs.load(CRAMPED, "paper", [BC])
    assert sc.asked(preset, 3, 100) == sc.asked(written, 3, 100) != sc.asked(default, 3, 100)
    assert sc.asked(preset, 3, 100) != sc.asked(preset, 2, 100) != sc.asked(preset, 2, 50)
    assert sc.asked(preset, 3, 100)["steps"] == EPISODE_STEPS
    assert sc.components(preset, 3, 100)["humans"] == sc.human_keys(written, 3)  # three humans, seeds 0 to 2
    assert len(set(sc.human_keys(written, 3))) == 3


def test_a_command_given_twice_is_read_once_and_a_page_holds_a_bounded_number_of_tables(tmp_path, monkeypatch):
    """200 copies of one block would read the store 200 times and write a page 70 times larger:
    a command is computed once per page, and more than MAX_TABLES tables is refused unread."""
    monkeypatch.chdir(ROOT)
    suite = one_run_suite(tmp_path)
    block = f"<!-- esr sweep {suite} --budget smoke --results --markdown -->\n{END}\n"
    page = tmp_path / "page.md"
    page.write_text(block * 3)
    calls = []
    real = doc_tables.SweepTable.lines
    monkeypatch.setattr(doc_tables.SweepTable, "lines", lambda self, store, where: calls.append(where) or real(self, store, where))
    lines, new, count = doc_tables.refresh(page, Store(tmp_path / "store"))
    assert count == 3 and len(calls) == 1 and sum(line.startswith("| grid_2 |") for line in new) == 3
    page.write_text(block * (doc_tables.MAX_TABLES + 1))
    with pytest.raises(doc_tables.TableError, match=f"{doc_tables.MAX_TABLES + 1} generated tables, more than the"):
        doc_tables.refresh(page, Store(tmp_path / "store"))
    assert len(calls) == 1  # refused before any table was read
