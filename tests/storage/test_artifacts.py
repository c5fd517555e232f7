"""The artifact lifecycle (esr_cli/storage/artifacts.py): one `ensure` for every kind."""

import ast
import json
from pathlib import Path

import pytest

from esr_cli.runner.stop_signals import Terminated
from esr_cli.storage import artifacts
from esr_cli.storage.artifacts import Recipe, ensure
from esr_cli.storage.store import FIGURE_KIND, MANIFEST, PLAY_KIND, RUN_KIND, Store, StoreError

PACKAGE = Path(artifacts.__file__).parents[1]  # esr_cli/


def _writer(calls: list, name: str, fail: bool = False):
    def build(out: Path, store: Store) -> dict:
        calls.append(name)
        (out / f"{name}.txt").write_text(name)
        if fail:
            raise RuntimeError("killed mid-build")
        return {"made": name}

    return build


def test_made_once_then_a_cache_hit(tmp_path):
    store, calls = Store(tmp_path / "store"), []
    recipe = Recipe(FIGURE_KIND, "a", {"kind": "figure", "x": 1}, _writer(calls, "a"), record={"method": "esr"})
    first = ensure(recipe, store)
    assert not first.cached and calls == ["a"]
    assert first.path == store.final_path(FIGURE_KIND, recipe.key)
    assert ensure(recipe, store) == (first.path, True) and calls == ["a"]
    manifest = json.loads((first.path / MANIFEST).read_text())
    assert manifest["key"] == recipe.key and manifest["key_components"] == {"kind": "figure", "x": 1}
    assert manifest["method"] == "esr" and manifest["summary"] == {"made": "a"} == first.summary()
    assert set(manifest["files"]) == {"a.txt", "summary.json"} and not store.verify(first.path)


def test_a_summary_is_read_bounded(tmp_path):
    """A store's summary.json may come from an archive: a pipe in its place or one larger than
    the cap is refused, never waited on or read whole."""
    import os

    from esr_cli.common.jsonl import JsonInputError

    store = Store(tmp_path / "store")
    built = ensure(Recipe(FIGURE_KIND, "a", {"kind": "figure", "x": 2}, _writer([], "a")), store)
    summary = built.path / "summary.json"
    summary.unlink()
    os.mkfifo(summary)
    with pytest.raises(JsonInputError):
        built.summary()
    summary.unlink()
    summary.write_text(" " * (artifacts.MAX_SUMMARY_BYTES + 1) + "{}")
    with pytest.raises(JsonInputError, match="bytes"):
        built.summary()


def test_requires_come_first_and_a_failed_check_writes_nothing(tmp_path):
    store, calls = Store(tmp_path / "store"), []
    base = Recipe(FIGURE_KIND, "base", {"n": "base"}, _writer(calls, "base"))
    top = Recipe(FIGURE_KIND, "top", {"n": "top", "needs": base.key}, _writer(calls, "top"), requires=(base,))
    ensure(top, store)
    assert calls == ["base", "top"] and store.lookup(FIGURE_KIND, base.key)

    def refuse(store):
        raise StoreError("not enough memory")

    blocked = Recipe(FIGURE_KIND, "blocked", {"n": "blocked"}, _writer(calls, "blocked"), requires=(base,), check=refuse)
    fresh = Store(tmp_path / "fresh")
    with pytest.raises(StoreError, match="memory"):
        ensure(blocked, fresh)
    assert not fresh.root.exists() and calls == ["base", "top"]


def test_a_failed_build_commits_nothing_and_the_next_resumes_its_partial_directory(tmp_path):
    """A training run resumes from what it wrote; any other kind leaves nothing and starts again."""
    store, calls = Store(tmp_path / "store"), []
    components = {"n": "run"}
    with pytest.raises(RuntimeError):
        ensure(Recipe(RUN_KIND, "run", components, _writer(calls, "run", fail=True)), store)
    key = Recipe(RUN_KIND, "run", components, _writer(calls, "run")).key
    partial = store.partial_path(RUN_KIND, key)
    assert store.lookup(RUN_KIND, key) is None and (partial / "run.txt").exists()
    assert json.loads((partial / "pending.json").read_text())["key_components"] == components

    def resume(out: Path, store: Store) -> dict:
        return {"found": (out / "run.txt").read_text()}  # what the interrupted build left

    built = ensure(Recipe(RUN_KIND, "run", components, resume), store)
    assert built.summary() == {"found": "run"} and not partial.exists()
    with pytest.raises(RuntimeError):
        ensure(Recipe(FIGURE_KIND, "fig", components, _writer(calls, "fig", fail=True)), store)
    figure_key = Recipe(FIGURE_KIND, "fig", components, _writer(calls, "fig")).key
    assert not store.partial_path(FIGURE_KIND, figure_key).exists()


def test_a_recipe_that_keeps_its_partial_loses_nothing_to_a_failed_or_stopped_build(tmp_path):
    """What a person played cannot be made again: neither an error nor a stop signal during the
    build, nor the next build, removes it."""
    store = Store(tmp_path / "store")
    components = {"n": "episode"}
    for stop in (RuntimeError("the front end failed"), Terminated()):
        def build(out: Path, store: Store, stop=stop) -> dict:
            with open(out / "steps.txt", "a") as f:
                f.write("step\n")
            raise stop

        with pytest.raises(type(stop)):
            ensure(Recipe(PLAY_KIND, "episode", components, build, keeps_partial=True), store)
    key = Recipe(PLAY_KIND, "episode", components, build, keeps_partial=True).key
    assert (store.partial_path(PLAY_KIND, key) / "steps.txt").read_text() == "step\nstep\n"
    built = ensure(Recipe(PLAY_KIND, "episode", components, lambda out, store: {"steps": len(
        (out / "steps.txt").read_text().split())}, keeps_partial=True), store)
    assert built.summary() == {"steps": 2}


def test_what_a_killed_build_left_is_cleared_before_the_next_one_unless_it_is_a_run(tmp_path):
    """SIGKILL leaves a partial directory behind; only a training run resumes from one."""
    store, calls = Store(tmp_path / "store"), []
    recipe = Recipe(FIGURE_KIND, "fig", {"n": "fig"}, _writer(calls, "fig"))
    left = store.begin(FIGURE_KIND, recipe.key, {"kind": FIGURE_KIND, "commit": "d" * 40, "device": "cpu"})
    (left / "half_written.png").write_text("cut short")
    built = ensure(recipe, store)
    assert sorted(p.name for p in built.path.iterdir()) == sorted([MANIFEST, "fig.txt", "summary.json"])
    assert len(json.loads((built.path / MANIFEST).read_text())["sessions"]) == 1  # nor the killed one's session


def test_unknown_kind_is_refused():
    with pytest.raises(ValueError, match="unknown artifact kind"):
        Recipe("models", "x", {}, lambda out, store: {})


def test_the_lifecycle_is_written_once():
    """Only the artifact layer begins and commits artifacts: every kind goes through `ensure`."""
    writers = set()
    for f in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                    node.func.attr in ("begin", "commit", "get_or_make"):
                writers.add(f.name)
    assert writers == {"artifacts.py"}


def test_every_start_and_resume_is_a_session_and_the_first_names_the_artifact(tmp_path, monkeypatch):
    """A run resumed from another checkout (same training code: the key holds its digest) or on
    another device keeps where it was made and adds where it went on, in order."""
    from esr_cli.storage import provenance

    store, calls = Store(tmp_path / "store"), []
    components = {"n": "long run"}
    places = iter([({"commit": "a" * 40, "dirty": False}, "gpu:NVIDIA H100", 16),
                   ({"commit": "b" * 40, "dirty": True}, "gpu:NVIDIA H200", 2)])

    def next_place():
        place = next(places)
        monkeypatch.setattr(provenance, "git_state", lambda: place[0])
        monkeypatch.setattr(provenance, "device", lambda: place[1])
        monkeypatch.setattr(provenance, "cpu_cores", lambda: place[2])

    next_place()
    with pytest.raises(RuntimeError):
        ensure(Recipe(RUN_KIND, "run", components, _writer(calls, "run", fail=True)), store)
    key = Recipe(RUN_KIND, "run", components, _writer(calls, "run")).key
    pending = json.loads((store.partial_path(RUN_KIND, key) / "pending.json").read_text())
    assert (pending["commit"], pending["device"]) == ("a" * 40, "gpu:NVIDIA H100")
    assert [s["device"] for s in pending["sessions"]] == ["gpu:NVIDIA H100"]
    next_place()
    built = ensure(Recipe(RUN_KIND, "run", components, _writer(calls, "run")), store)
    manifest = json.loads((built.path / MANIFEST).read_text())
    assert (manifest["commit"], manifest["device"]) == ("a" * 40, "gpu:NVIDIA H100")  # where it was made
    assert [(s["commit"][0], s["dirty"], s["device"]) for s in manifest["sessions"]] == \
        [("a", False, "gpu:NVIDIA H100"), ("b", True, "gpu:NVIDIA H200")]
    assert all(s["started_at"] for s in manifest["sessions"]) and manifest["provenance"]["device"] == "gpu:NVIDIA H200"
    # the cores each session's process could use: the float order of XLA's CPU work depends on them
    assert [s["cpu_cores"] for s in manifest["sessions"]] == [16, 2]


def test_a_pending_record_from_before_sessions_counts_as_the_last_session(tmp_path, monkeypatch):
    from esr_cli.storage import provenance

    monkeypatch.setattr(provenance, "git_state", lambda: {"commit": "c" * 40, "dirty": False})
    store = Store(tmp_path / "store")
    recipe = Recipe(RUN_KIND, "run", {"n": "run"}, _writer([], "run"))  # a run resumes what an older esr began
    partial = store.partial_path(RUN_KIND, recipe.key)
    partial.mkdir(parents=True)
    (partial / "pending.json").write_text(json.dumps({"key": recipe.key, "commit": "d" * 40, "device": "gpu:X"}))
    manifest = json.loads((ensure(recipe, store).path / MANIFEST).read_text())
    assert [s["commit"][0] for s in manifest["sessions"]] == ["d", "c"] and manifest["commit"] == "d" * 40
    assert provenance.earlier_sessions({"sessions": [{"commit": "e"}, "junk", 3]}) == [{"commit": "e"}]
    assert provenance.earlier_sessions(None) == [] == provenance.earlier_sessions({"commit": 5})


def test_a_resumed_pending_record_carries_only_session_fields_into_the_manifest(tmp_path, monkeypatch):
    """A pending.json may come from an archive: the run it resumes is finished with its sessions'
    own fields only, a commit only if it names one, texts bounded and escaped as they are shown."""
    from esr_cli.storage import provenance

    monkeypatch.setattr(provenance, "git_state", lambda: {"commit": "c" * 40, "dirty": False})
    store = Store(tmp_path / "store")
    recipe = Recipe(RUN_KIND, "run", {"n": "forged"}, _writer([], "run"))
    partial = store.partial_path(RUN_KIND, recipe.key)
    partial.mkdir(parents=True)
    forged = {"commit": "not\x1b[2J a commit", "dirty": "yes", "device": "gpu\n| 999 |" + "x" * 500,
              "started_at": "2026-12-01T20:12:38+0000", "cpu_cores": True, "wall_s": 12.5, "payload": {"a": [1] * 9}}
    (partial / "pending.json").write_text(json.dumps({"key": recipe.key, "sessions": [forged, {"omitted": 3}]}))
    manifest = json.loads((ensure(recipe, store).path / MANIFEST).read_text())
    first, omitted, latest = manifest["sessions"]
    assert first == {"device": ("gpu\\n| 999 |" + "x" * 500)[:provenance.MAX_DEVICE_CHARS + 1],
                     "started_at": "2026-12-01T20:12:38+0000", "wall_s": 12.5}
    assert omitted == {"omitted": 3} and latest["commit"] == "c" * 40
    assert "commit" not in manifest and manifest["device"] == first["device"]
    # a session made outside a git checkout says so (commit and dirty null) and keeps saying it
    assert provenance.carried_sessions({"sessions": [{"commit": None, "dirty": None, "cpu_cores": 2}]}) == [
        {"commit": None, "dirty": None, "cpu_cores": 2}]


def test_a_resumed_run_counts_the_working_time_of_every_session(tmp_path, monkeypatch):
    """A run stopped at a chunk boundary records its session's seconds; the one that finishes it
    adds its own, and the manifest's wall time is the sum (not the last session's alone)."""
    from esr_cli.common.stops import Interrupted
    from esr_cli.recipes.sweep import _wall
    from esr_cli.storage import provenance

    clock = iter([1000.0, 1600.0, 5000.0, 5090.0])  # each session: its start, then its end
    monkeypatch.setattr(artifacts.time, "time", lambda: next(clock))
    store = Store(tmp_path / "store")

    def stops(out, store):
        raise Interrupted(26)

    with pytest.raises(Interrupted):
        ensure(Recipe(RUN_KIND, "run", {"n": "timed"}, stops), store)
    recipe = Recipe(RUN_KIND, "run", {"n": "timed"}, _writer([], "run"))
    pending = json.loads((store.partial_path(RUN_KIND, recipe.key) / "pending.json").read_text())
    assert [s["wall_s"] for s in pending["sessions"]] == [600.0] and pending["stopped"]["epoch"] == 26
    manifest = json.loads((ensure(recipe, store).path / MANIFEST).read_text())
    assert [s["wall_s"] for s in manifest["sessions"]] == [600.0, 90.0]
    assert manifest["wall_time_s"] == 690.0 and provenance.wall_time(manifest) == (690.0, True)
    assert _wall({"wall_s": 690.0, "wall_whole": True}) == "690 s"


def test_an_older_manifests_wall_time_is_a_lower_bound_and_a_damaged_one_is_none():
    from esr_cli.recipes.sweep import _wall
    from esr_cli.storage import provenance

    # an older esr: wall_time_s is the last session's, the sessions say nothing of their own
    older = {"wall_time_s": 79.3, "sessions": [{"started_at": "2026-12-01T20:12:38+0000"}, {"started_at": "2026-12-01T20:29:20+0000"}]}
    assert provenance.wall_time(older) == (79.3, False)
    assert _wall({"wall_s": 79.3, "wall_whole": False}) == "≥ 79 s"
    assert provenance.wall_time({"wall_time_s": 12.0, "sessions": [{"commit": "a"}]}) == (12.0, True)
    for damaged in ({"wall_time_s": "79"}, {"wall_time_s": True}, {"wall_time_s": None}, {"wall_time_s": 10 ** 400},
                    {"wall_time_s": float("nan")}, {"wall_time_s": float("inf")}, {"wall_time_s": -5}, [], None, {}):
        assert provenance.wall_time(damaged)[0] is None
    assert provenance.session_wall({"wall_s": -1}) is None and provenance.session_wall({"wall_s": "5"}) is None
    # an older esr's stopped record: the session's time is when it stopped less when it started
    stopped = {"sessions": [{"started_at": "2026-12-01T20:16:38+0000"}],
               "stopped": {"epoch": 26, "at": "2026-12-01T20:28:49+0000"}}
    assert provenance.earlier_sessions(stopped)[0]["wall_s"] == 731.0
    for bad in ("yesterday", 5, None, "2026-12-01T20:00:00+0000"):  # unreadable, or before it started
        assert "wall_s" not in provenance.earlier_sessions({**stopped, "stopped": {"at": bad}})[0]


def test_a_run_resumed_by_many_jobs_keeps_its_first_and_latest_sessions():
    from esr_cli.storage import provenance

    sessions = []
    for i in range(250):
        sessions = provenance.with_session(sessions, {"commit": str(i)})
    assert len(sessions) == provenance.MAX_SESSIONS
    assert sessions[0] == {"commit": "0"} and sessions[-1] == {"commit": "249"}
    assert sessions[1]["omitted"] + len(sessions) - 1 == 250  # every session is counted once
    assert [s["commit"] for s in sessions[2:]] == [str(i) for i in range(152, 250)]
    assert "wall_s" not in sessions[1]  # the sessions left out did not record their seconds
    timed = []
    for i in range(250):
        timed = provenance.with_session(timed, {"commit": str(i), "wall_s": 2.0})
    assert timed[1]["wall_s"] == 2.0 * timed[1]["omitted"]  # their seconds are kept in the count
    assert provenance.wall_time({"wall_time_s": 500.0, "sessions": timed}) == (500.0, True)


def test_where_an_artifact_was_made_is_never_text_that_breaks_a_page():
    """A manifest may come from an archive: its device is shown with control characters as
    escapes (a table row stays one line), and a commit that is no git object name is none."""
    from esr_cli.recipes.sweep import _markdown_cell
    from esr_cli.storage.provenance import origin

    forged = {"sessions": [{"commit": "deadbee\n<!-- end of generated table -->", "device": "cpu\n\nINJECTED | 999"}],
              "provenance": {"git": {"commit": "not a commit"}}}
    made = origin(forged)
    assert made.commit is None and made.device == "cpu\\n\\nINJECTED | 999" and "\n" not in made.device
    assert _markdown_cell(made.device) == "cpu\\n\\nINJECTED \\| 999"  # one cell of one row
    assert _markdown_cell("a\x1b[2Jb") == "a\\x1b[2Jb"
    assert origin({"sessions": [{"commit": "ab12cd3" + "0" * 33, "device": "x" * 10_000}]}).device == "x" * 200


def test_where_an_artifact_was_made_is_read_from_its_sessions_and_a_damaged_manifest_says_nothing():
    from esr_cli.storage.provenance import Origin, origin

    sessions = [{"commit": "a" * 40, "dirty": True, "device": "gpu:NVIDIA H100"},
                {"commit": "b" * 40, "dirty": False, "device": "cpu:cpu"}]
    assert origin({"sessions": sessions}) == Origin("a" * 40, "gpu:NVIDIA H100, then cpu:cpu", True)
    # a manifest from before sessions were recorded: its provenance names the commit and device
    assert origin({"provenance": {"git": {"commit": "c" * 40}, "device": "cpu:cpu"}}) == Origin("c" * 40, "cpu:cpu", False)
    assert origin({"key_components": {"toolchain": {"backend": "gpu"}}}) == Origin(None, "gpu", False)
    for damaged in (None, {}, {"provenance": "x", "key_components": 3}, {"provenance": {"git": ["c"], "device": 7}}):
        assert origin(damaged) == Origin(None, None, False)
