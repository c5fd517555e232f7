"""The artifact store: keys, atomic commit, locking, verification."""

import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest
from conftest import esr

from esr_cli.storage.store import Store, StoreError, content_key


def test_content_key_is_canonical():
    assert content_key({"a": 1, "b": [1, 2]}) == content_key({"b": [1, 2], "a": 1})
    assert content_key({"a": 1}) != content_key({"a": 2})


COMPONENTS = {"kind": "runs", "spec": {"name": "x"}}


def make_artifact(store, key=None, components=COMPONENTS):
    """A committed run; by default under the key its components digest to, as training makes it
    (an explicit key, for tests of key prefixes, does not pass `verify`)."""
    key = key or content_key(components)
    name = components["spec"]["name"]
    d = store.begin("runs", key, {"name": name, "key": key, "key_components": components})
    (d / "metrics.jsonl").write_text('{"epoch": 1}\n')
    (d / "sub").mkdir()
    (d / "sub" / "data.bin").write_bytes(b"\x00\x01\x02")
    assert store.lookup("runs", key) is None  # not visible before commit
    return store.commit("runs", key, {"kind": "runs", "name": name, "key": key, "key_components": components})


def make_artifacts(store, names):
    """{name: committed run}, in the order `esr ls` and `esr verify` list them."""
    paths = {n: make_artifact(store, components={"kind": "runs", "spec": {"name": n}}) for n in names}
    return dict(sorted(paths.items(), key=lambda item: item[1].name))


def test_commit_is_a_rename_with_digests(tmp_path):
    store = Store(tmp_path)
    key = content_key(COMPONENTS)
    path = make_artifact(store)
    assert path == store.lookup("runs", key)
    assert not store.partial_path("runs", key).exists()
    m = store.read_manifest(path)
    assert set(m["files"]) == {"metrics.jsonl", "sub/data.bin"}
    assert store.verify(path) == []
    assert store.resolve(key[:6]) == path and store.resolve(str(path)) == path


def test_verify_finds_a_flipped_byte_and_a_deleted_file(tmp_path):
    store = Store(tmp_path)
    path = make_artifact(store)
    data = path / "sub" / "data.bin"
    data.write_bytes(b"\x00\x01\x03")
    (path / "metrics.jsonl").unlink()
    problems = store.verify(path)
    assert any("changed file sub/data.bin" in p for p in problems)
    assert any("missing file metrics.jsonl" in p for p in problems)


def test_resolve_errors(tmp_path):
    store = Store(tmp_path)
    first = make_artifact(store, "abcd" + "0" * 28)
    make_artifact(store, "abcd" + "1" * 28)
    with pytest.raises(StoreError, match="ambiguous"):
        store.resolve("abcd")
    assert store.resolve("abcd0") == first
    with pytest.raises(StoreError, match="no artifact"):
        store.resolve("ffff")
    with pytest.raises(StoreError, match="no artifact"):
        store.resolve("not-a-key")


def test_find_names_unfinished_artifacts_only_when_asked(tmp_path):
    store = Store(tmp_path)
    unfinished = "cd" * 16
    partial = store.begin("runs", unfinished, {"name": "x", "key": unfinished})
    with pytest.raises(StoreError, match="runs cdcdcdcdcdcd in store .* is unfinished"):
        store.resolve(unfinished[:6])
    e = store.find(unfinished[:6], include_partial=True)
    assert (e.kind, e.key, e.path, e.status) == ("runs", unfinished, partial, "partial")
    assert store.find(str(partial), include_partial=True).status == "partial"
    with pytest.raises(StoreError, match="is unfinished"):
        store.find(str(partial))
    # a key both committed and begun again: the committed artifact is the one meant
    done = make_artifact(store, unfinished)
    store.begin("runs", unfinished, {"name": "x", "key": unfinished})
    assert store.find(unfinished[:6], include_partial=True).path == done


def test_a_store_that_is_a_file_is_refused(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")  # it would read as an empty store, and a store below it can never be made
    with pytest.raises(StoreError, match=f"store {blocker} is not a directory$"):
        Store(blocker)
    with pytest.raises(StoreError, match=f"store {blocker}/store is not writable: {blocker} is not a directory"):
        Store(blocker / "store")
    Store(tmp_path / "not" / "yet")  # a store that does not exist yet is made on the first write


def test_every_command_refuses_a_store_that_is_a_file(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    archive = tmp_path / "a.tar.gz"
    archive.write_bytes(b"")
    for args in (["ls"], ["verify"], ["show", "abcd"], ["import", str(archive)], ["export", "abcd"]):
        proc = esr(*args, "--store", str(blocker), store=tmp_path / "unused", check=False)
        assert proc.returncode == 2, args
        assert proc.stderr.strip() == f"error: store {blocker} is not a directory", args
    assert blocker.read_text() == ""


DAMAGED = {b"\xff\xfe{}": "is not UTF-8 JSON", b"{": "is not UTF-8 JSON (line 1, column 2: ",
           b'{"kind": "runs", "key": "e7da\n': "is not UTF-8 JSON (line 1, column 30: Invalid control character)", b"[]": "is not a JSON object",
           b'{"kind": ' + b"9" * 5000 + b"}": "is JSON with an integer too long to read",
           b'{"kind": "runs", "files": {"a": 1, "a": 2}}': "is JSON with an object naming the key 'a' twice",
           b"3": "is not a JSON object", b"{}": "has no 'kind'", b'{"kind": "runs", "key": 1}': "has no 'key'"}


@pytest.mark.parametrize("content", DAMAGED)
def test_a_damaged_manifest_is_a_store_error_and_a_verify_problem(tmp_path, content):
    store = Store(tmp_path)
    path = make_artifact(store)
    (path / "manifest.json").write_bytes(content)
    with pytest.raises(StoreError, match=re.escape(f"{path}: manifest.json {DAMAGED[content]}")):
        store.read_manifest(path)
    problems = store.verify(path)
    assert len(problems) == 1 and problems[0].startswith(f"manifest.json {DAMAGED[content]}")
    (entry,) = store.entries()
    assert (entry.status, entry.manifest) == ("complete", None)  # listed, marked unreadable


def test_verify_checks_that_the_manifest_names_its_artifact(tmp_path):
    import json

    store = Store(tmp_path)
    path = make_artifact(store)
    manifest = store.read_manifest(path)
    for change, problem in (({"key": "cd" * 16}, f"names key '{'cd' * 16}', not the directory's {path.name}"),
                            ({"kind": "evals"}, "names kind 'evals', but the artifact is under runs/"),
                            ({"kind": "models"}, "names kind 'models', not one of runs, evals"),
                            ({"files": {**manifest["files"], "../../x": "00"}}, "lists '../../x', which is not a file inside"),
                            # a key is the digest of its components: a relabelled artifact is found out
                            ({"key_components": {**COMPONENTS, "spec": {"name": "y"}}}, "key_components digest to"),
                            ({"key_components": None}, "lists no key_components")):
        (path / "manifest.json").write_text(json.dumps({**manifest, **change}))
        assert any(problem in p for p in store.verify(path)), (change, store.verify(path))


@pytest.mark.slow
def test_commands_report_a_damaged_manifest_in_one_line(tmp_path):
    store = Store(tmp_path)
    path = make_artifact(store)
    (path / "manifest.json").write_bytes(b"[]")
    listed = esr("ls", store=tmp_path)
    assert listed.returncode == 0 and "damaged" in listed.stdout and "damaged manifest" in listed.stderr
    verified = esr("verify", store=tmp_path, check=False)
    assert verified.returncode == 1 and "CORRUPT" in verified.stderr and "manifest.json is not a JSON object" in verified.stderr
    for args in (["show", path.name[:8]], ["eval", path.name[:8]]):
        proc = esr(*args, store=tmp_path, check=False)
        assert proc.returncode == 2, args
        assert proc.stderr.strip().splitlines() == [f"error: {path}: manifest.json is not a JSON object"], args


def hold_lock(root, key, seconds: int = 3) -> subprocess.Popen:
    """Another process holding `key`'s lock for `seconds`; returns once it holds it."""
    holder = subprocess.Popen(
        [sys.executable, "-c", (
            "import sys, time; from esr_cli.storage.store import Store; s = Store(sys.argv[1]);\n"
            f"with s.lock('runs', sys.argv[2]):\n    print('held', flush=True); time.sleep({seconds})"
        ), str(root), key],
        stdout=subprocess.PIPE, text=True,
    )
    assert holder.stdout.readline().strip() == "held"
    return holder


@pytest.mark.slow
def test_lock_excludes_a_second_process(tmp_path):
    store = Store(tmp_path)
    key = "cd" * 16
    holder = hold_lock(tmp_path, key)
    waited = []
    t0 = time.time()
    with store.lock("runs", key, on_wait=waited.append, poll_s=0.1):
        elapsed = time.time() - t0
    holder.wait()
    assert waited and "pid" in waited[0]
    assert elapsed > 1.0


@pytest.mark.slow
def test_lock_without_waiting_reports_a_busy_artifact_at_once(tmp_path):
    from esr_cli.storage.store import LockBusy

    store = Store(tmp_path)
    key = "ab" * 16
    holder = hold_lock(tmp_path, key)
    with pytest.raises(LockBusy, match="being written by another process"):
        with store.lock("runs", key, wait=False, on_wait=lambda h: pytest.fail("waited for the holder")):
            pass
    holder.wait()
    with store.lock("runs", key, wait=False):  # free again once the holder is gone
        pass


def test_lock_of_a_dead_process_is_free(tmp_path):
    store = Store(tmp_path)
    key = "ef" * 16
    p = subprocess.Popen([sys.executable, "-c", (
        "import os, sys; from esr_cli.storage.store import Store; s = Store(sys.argv[1]);\n"
        "with s.lock('runs', sys.argv[2]):\n    os.kill(os.getpid(), 9)"
    ), str(tmp_path), key])
    p.wait()
    assert store.lock_path("runs", key).exists()
    with store.lock("runs", key, on_wait=lambda h: pytest.fail("waited on a dead process")):
        pass


@pytest.mark.parametrize("intruder", ["link", "fifo"])
def test_a_lock_file_that_is_a_link_or_a_fifo_is_named_never_followed_or_waited_on(tmp_path, intruder):
    """Taking a lock empties its file, so a link in its place once emptied the file it led to; a
    FIFO hung `esr sweep --status`. Both are refused by name, and what the link leads to is kept."""
    from esr_cli.recipes.sweep import _lock_holder

    store = Store(tmp_path / "store")
    key = "ab" * 16
    lock = store.lock_path("runs", key)
    lock.parent.mkdir(parents=True)
    precious = tmp_path / "precious.txt"
    precious.write_text("keep me")
    lock.symlink_to(precious) if intruder == "link" else os.mkfifo(lock)
    said = "is a link, not a lock file" if intruder == "link" else "is not a regular file, so not a lock file"
    signal.alarm(20)  # a regression would block on the FIFO: the alarm ends the test
    try:
        with pytest.raises(StoreError, match=said):
            with store.lock("runs", key):
                pytest.fail("took a lock that is not a lock file")
        with pytest.raises(StoreError, match=said):
            _lock_holder(store, key)
    finally:
        signal.alarm(0)
    assert precious.read_text() == "keep me"


def test_a_runs_code_digest_is_the_model_package(tmp_path, monkeypatch):
    """A run's key digests every file under esr_cli/model, imported or not, and nothing else:
    host code (the store, the runner loop, the CLI, spec-file reading) can change without
    re-keying a run; an edit to a model file, or a new one, re-keys it."""
    import shutil

    from esr_cli.storage import provenance

    copy = tmp_path / "esr_cli"
    shutil.copytree(provenance.PACKAGE_DIR, copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(provenance, "PACKAGE_DIR", copy)
    digest = lambda: provenance.code_digest.__wrapped__(provenance.MODEL_SOURCES)  # noqa: E731 (uncached)
    before = digest()
    for host in ("storage/store.py", "recipes/runs.py", "runner/loop.py", "cli/main.py", "recipes/human_runs.py", "common/specs.py"):
        (copy / host).write_text((copy / host).read_text() + "\n# an edit\n")
    (copy / "unrelated.py").write_text("X = 1\n")
    assert digest() == before
    (copy / "model" / "extra.py").write_text("SCALE = 2.0\n")
    assert digest() != before  # in the keyed package, imported or not
    before = digest()
    for computing in ("model/methods/esr.py", "model/spec.py", "model/envs/gridworld.py"):
        (copy / computing).write_text((copy / computing).read_text() + "\n# an edit\n")
        assert digest() != before, computing
        before = digest()


def test_the_exact_analysis_digest_leaves_out_host_plumbing(tmp_path, monkeypatch):
    """An exact analysis is re-keyed by the environments, humans, analysis and its own module,
    not by the store or checkpoint code that its module imports (`alone`: not followed)."""
    import shutil

    from esr_cli.recipes import exact_runs
    from esr_cli.storage import provenance

    copy = tmp_path / "esr_cli"
    shutil.copytree(provenance.PACKAGE_DIR, copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(provenance, "PACKAGE_DIR", copy)
    digest = lambda: provenance.code_digest.__wrapped__(*exact_runs.EXACT_CODE)  # noqa: E731 (uncached)
    before = digest()
    for host in ("storage/store.py", "recipes/runs.py", "storage/transfer.py", "storage/artifacts.py", "cli/main.py"):
        (copy / host).write_text((copy / host).read_text() + "\n# an edit\n")
    assert digest() == before
    for computing in ("recipes/exact_runs.py", "analysis/exact.py", "model/envs/gridworld.py"):
        (copy / computing).write_text((copy / computing).read_text() + "\n# an edit\n")
        assert digest() != before, computing
        before = digest()

def test_ls_shows_a_runs_final_return_as_figures_and_reports_do(tmp_path):
    """`esr ls`'s "final return" is each seed's mean over its last 10% of epochs, averaged over
    seeds (not the manifest's 10-epoch summary), for unfinished runs too."""
    store = Store(tmp_path)
    rows = "".join(json.dumps({"epoch": e, "return": [float(e), float(2 * e)]}) + "\n" for e in range(1, 31))
    done = store.begin("runs", "cd" * 16, {"name": "finished", "key": "cd" * 16})
    (done / "metrics.jsonl").write_text(rows)
    store.commit("runs", "cd" * 16, {"kind": "runs", "name": "finished", "key": "cd" * 16, "seeds": [0, 1],
                                      "summary": {"return": {"mean": 99.0}}})
    going = store.begin("runs", "ef" * 16, {"name": "going", "key": "ef" * 16,
                                            "key_components": {"spec": {"train": {"epochs": 3000}}}})
    (going / "metrics.jsonl").write_text(rows + '{"epoch": 31, "ret')  # a line cut short by a kill
    listed = esr("ls", store=tmp_path).stdout
    # the last 3 of 30 epochs: seed 0 (28+29+30)/3 = 29, seed 1 58; their mean 43.5
    finished = next(line for line in listed.splitlines() if "cdcdcd" in line)
    assert "43.50" in finished and "99.00" not in finished
    assert "43.50" in next(line for line in listed.splitlines() if "efefef" in line)
    assert "30 of 3,000" in next(line for line in listed.splitlines() if "efefef" in line)


def test_ls_lists_an_evaluation_whose_return_no_float_holds_without_one(tmp_path):
    """JSON allows a 401-digit mean return; float() of it overflows. The listing shows the entry
    with no return instead of failing whole."""
    store = Store(tmp_path)
    for key, mean in (("ab" * 16, 10**400), ("cd" * 16, 12.5)):
        store.begin("evals", key, {"name": "an eval", "key": key})
        store.commit("evals", key, {"kind": "evals", "name": "an eval", "key": key, "summary": {"return": {"mean": mean}}})
    listed = esr("ls", store=tmp_path).stdout
    assert "ababab" in listed and "12.50" in next(line for line in listed.splitlines() if "cdcdcd" in line)


def test_a_printed_command_names_the_store_unless_it_is_the_default(tmp_path, monkeypatch):
    monkeypatch.delenv("ESR_STORE", raising=False)
    monkeypatch.chdir(tmp_path)
    assert Store("artifacts").invocation() == "esr"
    assert Store(tmp_path / "artifacts").invocation() == "esr"  # the same folder, written out
    assert Store("my store").invocation() == "esr --store 'my store'"
    monkeypatch.setenv("ESR_STORE", str(tmp_path / "elsewhere"))
    assert Store(tmp_path / "elsewhere").invocation() == "esr"
    assert Store("artifacts").invocation() == "esr --store artifacts"


def test_verify_checks_every_artifact_and_reports_every_problem(tmp_path, monkeypatch, capsys):
    """A file that cannot be read, or a link (here to an endless device), is a problem of its
    artifact: the artifacts after it are still checked, and the exit says some failed."""
    from esr_cli.cli.main import main
    from esr_cli.storage import store as store_module

    unreadable, linked, good = make_artifacts(Store(tmp_path), ["a", "b", "c"]).values()
    digest = store_module.digest_file

    def digest_or_refuse(path):
        if path == unreadable / "sub" / "data.bin":
            raise PermissionError(13, "Permission denied", str(path))
        return digest(path)

    monkeypatch.setattr(store_module, "digest_file", digest_or_refuse)
    (linked / "sub" / "data.bin").unlink()
    (linked / "sub" / "data.bin").symlink_to("/dev/zero")
    assert main(["--store", str(tmp_path), "verify"]) == 1
    err = " ".join(capsys.readouterr().err.split())
    assert f"CORRUPT {unreadable} unreadable file sub/data.bin (Permission denied)" in err
    assert f"CORRUPT {linked} sub/data.bin is a link, not a plain file" in err
    assert f"ok {good}" in err and "2 of 3 artifact(s) failed verification" in err


def test_one_bad_manifest_never_breaks_listing_the_others(tmp_path):
    """A manifest that is garbage, 100 MB or nested 10,000 deep is refused with bounded work
    (esr_cli/common/jsonl.py): `esr ls` lists every other artifact and names each bad one in one line."""
    made = make_artifacts(Store(tmp_path), ["good", "garbage", "huge", "deep"])
    good, garbage, huge, deep = (made[n] for n in ("good", "garbage", "huge", "deep"))
    (garbage / "manifest.json").write_bytes(b"\x00garbage{")
    with open(huge / "manifest.json", "wb") as f:
        f.truncate(100 << 20)
    (deep / "manifest.json").write_bytes(b"[" * 10_000 + b"]" * 10_000)
    listed = esr("ls", store=tmp_path, timeout=60)
    assert listed.returncode == 0
    assert any("good" in line and good.name[:12] in line for line in listed.stdout.splitlines())
    lines = listed.stderr.strip().splitlines()
    assert sorted(lines) == sorted([
        f"damaged manifest: {garbage}: manifest.json is not UTF-8 JSON",
        f"damaged manifest: {huge}: manifest.json is 104,857,600 bytes, more than the 16,777,216 esr reads",
        f"damaged manifest: {deep}: manifest.json is nested deeper than 64 levels",
    ]), listed.stderr
    assert esr("show", good.name[:8], store=tmp_path).returncode == 0


@pytest.mark.slow
def test_the_reproduction_report_is_written_from_a_store_holding_damaged_manifests(tmp_path):
    """A manifest that is garbage and one nested 10,000 levels deep cost `esr paper --report`
    those two artifacts only (tests/report/test_reproduction.py drives it with runs): it writes the
    report and exits 0."""
    made = make_artifacts(Store(tmp_path / "store"), ["garbage", "deep"])
    (made["garbage"] / "manifest.json").write_bytes(b"\x00garbage{")
    (made["deep"] / "manifest.json").write_bytes(b"[" * 10_000 + b"]" * 10_000)
    out = tmp_path / "docs" / "report.md"
    proc = esr("paper", "--report", "--out", str(out), "--no-exact", store=tmp_path / "store", timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip() == str(out) and "Traceback" not in proc.stderr
    assert "**Summary:** 38 statements" in out.read_text()


@pytest.mark.parametrize("bad", [b'{"epoch": 2, "x": "' + b"y" * (1 << 20) + b'"}', b'{"epoch": 2, "x": ' + b"[" * 100 + b"]" * 100 + b"}",
                                 b"[" * 10_000, b"3", b'{"epoch": 2',
                                 b'{"epoch": 2, "x": [' + b",".join([b"{}"] * 70_000) + b"]}"])
def test_a_metrics_line_too_long_too_deep_or_not_an_object_ends_the_reading(tmp_path, bad):
    """As a line cut short by a kill: it and everything after it are untrusted, never a crash."""
    from esr_cli.common.jsonl import read_jsonl

    (tmp_path / "metrics.jsonl").write_bytes(b'{"epoch": 1}\n' + bad + b'\n{"epoch": 3}\n')
    assert read_jsonl(tmp_path / "metrics.jsonl") == [{"epoch": 1}]


def test_json_of_more_lists_and_objects_than_esr_writes_is_refused_unparsed(tmp_path, monkeypatch):
    """Each list or object costs the parser a Python object (an empty one about 30 times its two
    bytes of text): a manifest, or a whole JSON-lines file, of more than esr writes is refused
    before the parser builds them, where the bytes alone would pass."""
    from esr_cli.common import jsonl

    many = b'{"x": [' + b",".join([b"{}"] * (jsonl.MAX_CONTAINERS + 1)) + b"]}"
    (tmp_path / "manifest.json").write_bytes(many)
    with pytest.raises(jsonl.JsonInputError, match=r"^JSON of more than 65,536 lists and objects"):
        jsonl.read_json(tmp_path / "manifest.json", 16 << 20)
    monkeypatch.setattr(jsonl, "MAX_JSONL_CONTAINERS", 10)
    (tmp_path / "metrics.jsonl").write_bytes(b'{"epoch": 1, "r": [1]}\n' * 5 + b'{"epoch": 6, "r": [1]}\n' * 5)
    assert [r["epoch"] for r in jsonl.read_jsonl(tmp_path / "metrics.jsonl")] == [1] * 5  # 2 a line: the 6th passes 10


@pytest.mark.slow
def test_a_fifo_in_place_of_a_runs_metrics_is_named_not_waited_on(tmp_path):
    """A FIFO where a committed run's metrics.jsonl belongs would block a reader until something
    wrote to it: `esr ls`, `esr show` and `esr verify` name it and go on, and `ls` lists the rest."""
    made = make_artifacts(Store(tmp_path), ["good", "piped"])
    good, piped = made["good"], made["piped"]
    (piped / "metrics.jsonl").unlink()
    os.mkfifo(piped / "metrics.jsonl")
    listed = esr("ls", store=tmp_path, timeout=60)
    assert listed.returncode == 0
    assert any("good" in line and good.name[:12] in line for line in listed.stdout.splitlines())
    assert listed.stderr.strip() == f"unreadable metrics: {piped / 'metrics.jsonl'} is not a regular file"
    shown = esr("show", piped.name[:8], store=tmp_path, timeout=60)
    assert shown.returncode == 0 and f"unreadable: {piped / 'metrics.jsonl'} is not a regular file" in shown.stdout
    verified = esr("verify", store=tmp_path, check=False, timeout=60)
    err = " ".join(verified.stderr.split())
    assert verified.returncode == 1 and f"CORRUPT {piped} metrics.jsonl is not a plain file" in err and f"ok {good}" in err


def test_json_readers_open_only_regular_files_and_read_a_bounded_amount(tmp_path, monkeypatch):
    """A FIFO (a played episode's steps.jsonl here) or a link is refused on the open file, at
    once; a JSON-lines file larger than MAX_JSONL_BYTES is refused unread, and one that grows past
    it while it is read is read up to it."""
    import signal

    from esr_cli.common import jsonl
    from esr_cli.storage.play_log import STEPS_FILE, read_steps

    os.mkfifo(tmp_path / STEPS_FILE)
    signal.alarm(20)  # a regression would block here; the alarm ends the test instead
    try:
        with pytest.raises(jsonl.JsonInputError, match="^not a regular file$"):
            read_steps(tmp_path)
        with pytest.raises(jsonl.JsonInputError, match="^not a regular file$"):
            jsonl.read_json(tmp_path / STEPS_FILE, 1 << 20)
    finally:
        signal.alarm(0)
    real = tmp_path / "metrics.jsonl"
    real.write_text('{"epoch": 1}\n' * 3)  # 39 bytes
    (tmp_path / "link.jsonl").symlink_to(real)
    for read in (jsonl.read_jsonl, lambda p: jsonl.read_json(p, 1 << 20)):
        with pytest.raises(jsonl.JsonInputError, match="^a link, not a regular file$"):
            read(tmp_path / "link.jsonl")
    assert jsonl.read_jsonl(real) == [{"epoch": 1}] * 3 and jsonl.read_jsonl(tmp_path / "none.jsonl") == []
    monkeypatch.setattr(jsonl, "MAX_JSONL_BYTES", 30)
    with pytest.raises(jsonl.JsonInputError, match="^39 bytes, more than the 30 esr reads$"):
        jsonl.read_jsonl(real)
    monkeypatch.setattr(jsonl.bounded_files, "size_problem", lambda f, limit: None)  # as if it grew after its size was read
    assert jsonl.read_jsonl(real) == [{"epoch": 1}] * 2  # 26 bytes, then 4 of a line: not an object


def test_a_manifest_listing_a_name_too_long_for_the_file_system_is_a_problem_not_a_crash(tmp_path):
    """A manifest (of an archive being imported, say) may list a name no file system holds: verify
    names it as that file's problem and goes on with the others."""
    from esr_cli.storage.store import file_problem

    (tmp_path / "metrics.jsonl").write_text("{}\n")
    problem = file_problem(tmp_path, "n" * 300, "0" * 64)
    assert problem.startswith("unreadable file " + "n" * 200 + "...") and "too long" in problem.lower()
    assert file_problem(tmp_path, "d/" + "n" * 300, "0" * 64).startswith("missing file d/")  # no such folder


def test_a_played_episodes_header_is_read_bounded(tmp_path):
    """episode.json of a played episode (and a study's record) is read up to MAX_RECORD_BYTES,
    never whole: a planted huge or non-regular file is refused in one line."""
    import os

    from esr_cli.storage.play_log import EPISODE_FILE, MAX_RECORD_BYTES, read_header

    (tmp_path / EPISODE_FILE).write_text('{"participant": "' + "p" * MAX_RECORD_BYTES + '"}')
    with pytest.raises(StoreError, match=f"damaged played episode: {tmp_path / EPISODE_FILE}: .*bytes"):
        read_header(tmp_path)
    fifo = tmp_path / "fifo"
    fifo.mkdir()
    os.mkfifo(fifo / EPISODE_FILE)
    with pytest.raises(StoreError, match="damaged played episode: .*not a regular file"):
        read_header(fifo)
    header = {"participant": "p1", "session": "s", "episode": 0, "robot": "random", "env": {"kind": "gridworld"}, "started_at": 1.5}
    (tmp_path / EPISODE_FILE).write_text(json.dumps(header))
    assert read_header(tmp_path) == header


@pytest.mark.parametrize("damage", [[1, 2], {"session": 3}, {"episode": True}, {"episode": "0"}, {"env": {}},
                                    {"env": "gridworld"}, {"started_at": "yesterday"}, {"robot": None},
                                    {"episode": 10 ** 4000}, {"started_at": float("inf")}])
def test_a_played_episodes_header_that_esr_did_not_write_is_one_line(tmp_path, damage):
    """A header that is no object, or whose fields the listings read are missing or of another
    type, is refused naming its file, before any reader trips over it."""
    from esr_cli.storage.play_log import EPISODE_FILE, read_header

    header = {"participant": "p1", "session": "s", "episode": 0, "robot": "random", "env": {"kind": "gridworld"}, "started_at": 1.5}
    bad = damage if isinstance(damage, list) else {**header, **damage}
    (tmp_path / EPISODE_FILE).write_text(json.dumps(bad))
    with pytest.raises(StoreError, match="damaged played episode: .*episode.json"):
        read_header(tmp_path)


def test_reading_a_damaged_played_episode_names_it_in_one_line(tmp_path):
    """What a reader meets in steps esr did not write (a missing field, an action out of range,
    text for a number, an environment esr would not play) is one StoreError naming the episode."""
    from esr_cli.storage.play_log import reading_episode

    for error in (KeyError("reward"), IndexError("tuple index out of range"), ValueError("could not convert"),
                  TypeError("can't multiply"), OverflowError("int too large")):
        with pytest.raises(StoreError) as e:
            with reading_episode(tmp_path):
                raise error
        assert str(e.value) == (f"damaged played episode: {tmp_path}: its steps or header are not what esr writes "
                                f"({type(error).__name__}: {str(error)})")
    with pytest.raises(StoreError, match="^already said$"):  # a StoreError of its own passes as it is
        with reading_episode(tmp_path):
            raise StoreError("already said")


def test_the_newest_record_is_chosen_by_its_instant_not_its_text():
    """created_at is local time with its UTC offset: 09:00+02:00 is earlier than 08:00+00:00 though
    its text sorts later; a record without a timestamp, or with a damaged one, ranks below all."""
    from esr_cli.storage.provenance import created_order

    east, utc = {"created_at": "2026-12-01T09:00:00+0200"}, {"created_at": "2026-12-01T08:00:00+0000"}
    assert created_order(east) < created_order(utc) and east["created_at"] > utc["created_at"]
    assert created_order(utc) - created_order(east) == 3600
    for damaged in ({}, {"created_at": 5}, {"created_at": "yesterday"}, {"created_at": "x" * 10_000}, None, [1]):
        assert created_order(damaged) == float("-inf") < created_order(east)


def test_verify_names_a_manifest_relabelled_in_place(tmp_path):
    """The labels listings show and filter on (budget, seeds, method, environment) are the ones
    the key was computed from: edited in the store after the key was made, `esr verify` says so."""
    from esr_cli.storage.checkpoint_files import verify_artifact

    components = {"kind": "runs", "budget": "smoke",
                  "spec": {"name": "r", "env": {"kind": "gridworld"}, "method": {"kind": "esr"}, "train": {"seeds": [0]}}}
    store = Store(tmp_path)
    path = make_artifact(store, components=components)
    manifest = store.read_manifest(path)
    agreeing = {"budget": "smoke", "seeds": [0], "method": "esr", "env": "gridworld"}
    (path / "manifest.json").write_text(json.dumps({**manifest, **agreeing}))
    assert verify_artifact(store, path) == []
    for change, named in (({"budget": "paper"}, "budget"), ({"seeds": [0, 1]}, "seeds"),
                          ({"method": "ave", "env": "overcooked"}, "method and env")):
        (path / "manifest.json").write_text(json.dumps({**manifest, **agreeing, **change}))
        assert verify_artifact(store, path) == [f"manifest.json names its {named} otherwise than its key components do: "
                                                "the artifact was relabelled after its key was made"]


def test_show_names_a_commit_only_when_it_is_a_git_object_name(tmp_path):
    """A manifest's commit text is shown only as a commit (hexadecimal, 7 to 40); anything else
    (an escape sequence, a sentence) is left out, as in the report."""
    store = Store(tmp_path)
    for key, commit in (("ab" * 16, "c\x1b[31mRED"), ("cd" * 16, "3a619620b454f78a08c1a6f3eb993e46c92295db")):
        store.begin("runs", key, {"name": "r", "key": key})
        store.commit("runs", key, {"kind": "runs", "name": "r", "key": key, "commit": commit,
                                   "provenance": {"git": {"commit": commit}}})
    bad, good = esr("show", "abab", store=tmp_path), esr("show", "cdcd", store=tmp_path)
    assert "\ncommit:" not in bad.stdout and "RED" not in bad.stdout and "\x1b" not in bad.stdout
    assert "3a619620b454f78a08c1a6f3eb993e46c92295db" in good.stdout


def test_show_reads_an_unfinished_run_from_its_pending_record(tmp_path, capsys):
    """`esr show` of a run still training (or stopped): what its pending.json says, its texts
    escaped; --json prints that record, saying it is one."""
    from esr_cli.cli.main import main

    key = "ab" * 16
    store = Store(tmp_path)
    components = {"kind": "runs", "spec": {"name": "g", "train": {"epochs": 40}, "method": {"kind": "esr"}}}
    store.begin("runs", key, {"name": "g\x1b[2J", "key": key, "budget": "quick", "seeds": [0],
                              "key_components": components,
                              "sessions": [{"commit": "a" * 40, "device": "cpu\x1b]0;x"}]})
    partial = store.partial_path("runs", key)
    rows = ({"epoch": e, "env_steps": 100 * e, "return": [float(e)]} for e in (1, 2))  # as training logs them
    (partial / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert main(["--store", str(tmp_path), "show", key[:6]]) == 0
    shown = capsys.readouterr().out
    assert "\x1b" not in shown and "g\\x1b[2J" in shown and "cpu\\x1b]0;x" in shown
    lines = dict(line.split(":", 1) for line in shown.splitlines())
    assert lines["status"].strip() == "partial" and lines["epochs"].strip() == "2 of 40"  # as esr ls says it
    assert lines["path"].strip() == str(partial) and lines["commit"].strip() == "a" * 40
    assert main(["--store", str(tmp_path), "show", key[:6], "--json"]) == 0
    printed = capsys.readouterr()
    assert json.loads(printed.out)["budget"] == "quick" and "(unfinished: its pending.json)" in printed.err
