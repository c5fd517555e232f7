"""`esr export` / `esr import`: an artifact, finished or not, moves between stores as one file,
and a hostile archive changes nothing (esr_cli/transfer.py)."""

import io
import json
import os
import shutil
import signal
import tarfile
from pathlib import Path

import numpy as np
import pytest

from conftest import esr
from esr_cli.store import Store, StoreError, content_key
from esr_cli.transfer import import_archive
from test_reliability import SMOKE, final_arrays, partials

COMPONENTS = {"kind": "runs", "spec": {"name": "x"}}
KEY = content_key(COMPONENTS)


def test_a_finished_run_moves_to_another_store(smoke_run, tmp_path):
    store, path, _ = smoke_run
    archive = tmp_path / "run.tar.gz"
    exported = esr("export", path.name[:8], "--out", str(archive), store=store)
    assert Path(exported.stdout.strip()) == archive and archive.is_file()

    other = tmp_path / "other"
    imported = esr("import", str(archive), store=other)
    copy = Path(imported.stdout.strip())
    assert copy == other / "runs" / path.name[:2] / path.name
    assert esr("verify", store=other).returncode == 0
    assert (copy / "metrics.jsonl").read_bytes() == (path / "metrics.jsonl").read_bytes()
    again = esr("import", str(archive), store=other)  # already there: success, nothing changes
    assert "already in the store" in again.stderr and Path(again.stdout.strip()) == copy


def test_a_finished_run_travels_as_metrics_only_and_says_what_it_cannot_do(smoke_run, tmp_path):
    """`export --without-checkpoint`: the manifest, spec and metrics, no checkpoint folder. It
    imports and verifies as a finished run and reports read it; evaluating it asks for the full
    archive; a damaged metrics file is still found."""
    store, path, _ = smoke_run
    full, slim = tmp_path / "full.tar.gz", tmp_path / "slim.tar.gz"
    esr("export", path.name[:8], "--out", str(full), store=store)
    esr("export", path.name[:8], "--out", str(slim), "--without-checkpoint", store=store)
    with tarfile.open(slim) as tar:
        names = tar.getnames()
    assert not any("/checkpoints/" in n for n in names) and any(n.endswith("/metrics.jsonl") for n in names)
    assert slim.stat().st_size < full.stat().st_size / 2
    other = tmp_path / "other"
    copy = Path(esr("import", str(slim), store=other).stdout.strip())
    assert esr("verify", store=other).returncode == 0
    assert (copy / "metrics.jsonl").read_bytes() == (path / "metrics.jsonl").read_bytes()
    listed = esr("ls", store=other)
    assert path.name[:12] in listed.stdout
    refused = esr("eval", path.name[:8], store=other, check=False)
    assert refused.returncode != 0 and "kept as metrics only" in " ".join(refused.stderr.split())
    (copy / "metrics.jsonl").write_bytes(b"{}\n")
    broken = esr("verify", store=other, check=False)
    assert broken.returncode == 1 and "metrics.jsonl" in broken.stderr


def test_a_finished_archive_replaces_an_idle_unfinished_run_of_the_same_key(smoke_run, tmp_path):
    """The same key is the same computation: the run finished elsewhere takes the place of the
    local copy that stopped part-way (an unfinished archive over it is still refused)."""
    store, path, _ = smoke_run
    archive = tmp_path / "run.tar.gz"
    esr("export", path.name[:8], "--out", str(archive), store=store)
    other = Store(tmp_path / "other")
    local = other.begin("runs", path.name, {"kind": "runs", "name": "grid_2", "key": path.name})
    (local / "metrics.jsonl").write_text('{"epoch": 1, "return": [0.0]}\n')
    proc = esr("import", str(archive), store=tmp_path / "other")
    assert "replaces this store's unfinished run" in " ".join(proc.stderr.split())
    assert Path(proc.stdout.strip()) == other.lookup("runs", path.name) and not local.exists()
    assert esr("verify", store=tmp_path / "other").returncode == 0


def test_an_unfinished_run_moves_and_resumes_to_the_uninterrupted_result(smoke_run, tmp_path):
    _, reference, _ = smoke_run
    here = tmp_path / "here"
    assert esr(*SMOKE, store=here, check=False, ESR_FAULT="after_checkpoint@1").returncode == -signal.SIGKILL
    (part,) = partials(here)
    archive = tmp_path / "partial.tar.gz"
    esr("export", part.name[:8], "--out", str(archive), store=here)
    names = tarfile.open(archive).getnames()
    assert all(n.startswith(f"runs/{part.name[:2]}/{part.name}/") for n in names)

    there = tmp_path / "there"
    # A copy that never reached a checkpoint is superseded; importing the same archive again
    # keeps what is there (as far along), and the run resumes from it either way.
    key = part.name.removesuffix(".partial")
    stale = Store(there).begin("runs", key, {"kind": "runs", "name": "grid_2", "key": key})
    replaced = esr("import", str(archive), store=there)
    assert "replaces this store's unfinished run of the same key, which was at epoch 0" in " ".join(replaced.stderr.split())
    again = esr("import", str(archive), store=there)
    assert "already unfinished in the store, at epoch 1" in " ".join(again.stderr.split())
    assert Path(again.stdout.strip()) == stale and [p.name for p in partials(there)] == [part.name]
    assert not [p for p in stale.parent.iterdir() if p.name.startswith(".import-")]
    resumed = esr(*SMOKE, store=there)
    assert "resuming" in resumed.stderr
    path = Path(resumed.stdout.strip())
    assert path.name == reference.name
    assert (path / "metrics.jsonl").read_text() == (reference / "metrics.jsonl").read_text()
    for a, b in zip(final_arrays(path), final_arrays(reference)):
        np.testing.assert_array_equal(a, b)


def _archive(tmp_path, members, name="bad.tar.gz"):
    """A gzipped tar of (name, bytes | None for a folder | ('symlink', target))."""
    path = tmp_path / name
    with tarfile.open(path, "w:gz") as tar:
        for member, data in members:
            info = tarfile.TarInfo(member)
            if data is None:
                info.type = tarfile.DIRTYPE
                tar.addfile(info)
            elif isinstance(data, tuple):
                info.type, info.linkname = tarfile.SYMTYPE, data[1]
                tar.addfile(info)
            else:
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
    return path


RUN_DIR = f"runs/{KEY[:2]}/{KEY}"


def _manifest(**fields) -> bytes:
    """A committed run's manifest as JSON, with `fields` replaced."""
    return json.dumps({"kind": "runs", "key": KEY, "key_components": COMPONENTS, "name": "x", "files": {}, **fields}).encode()


def _pending(**fields) -> bytes:
    """An unfinished run's pending.json as JSON, with `fields` replaced."""
    return json.dumps({"kind": "runs", "key": KEY, "key_components": COMPONENTS, "name": "x", **fields}).encode()


@pytest.mark.parametrize(
    "members, message",
    [
        ([(f"{RUN_DIR}/../../../../evil", b"x")], "points outside the artifact"),
        ([("/etc/evil", b"x")], "points outside the artifact"),
        ([(f"{RUN_DIR}/manifest.json", ("symlink", "/etc/passwd"))], "not a plain file or folder"),
        ([(f"{RUN_DIR}/manifest.json", b"{}"), (f"runs/ab/{'ab' + KEY[2:]}/manifest.json", b"{}")], "more than one artifact"),
        ([("runs/evil.txt", b"x")], "not inside an artifact directory"),
        ([(f"models/{KEY[:2]}/{KEY}/manifest.json", b"{}")], "not an esr artifact directory"),
        ([(f"runs/zz/{KEY}/manifest.json", b"{}")], "not an esr artifact directory"),
        ([(f"evals/{KEY[:2]}/{KEY}.partial/pending.json", b"{}")], "only unfinished runs"),
        ([(f"{RUN_DIR}/metrics.jsonl", b"{}\n")], "has no manifest.json"),
        ([(f"{RUN_DIR}/manifest.json", b"[1, 2")], f"{RUN_DIR}: manifest.json is not UTF-8 JSON"),
        ([(f"{RUN_DIR}/manifest.json", b"\xff\xfe{}")], f"{RUN_DIR}: manifest.json is not UTF-8 JSON"),
        ([(f"{RUN_DIR}/manifest.json", b"[1, 2]")], f"{RUN_DIR}: manifest.json is not a JSON object"),
        ([(f"{RUN_DIR}/manifest.json", b"3")], f"{RUN_DIR}: manifest.json is not a JSON object"),
        ([(f"{RUN_DIR}/manifest.json", b"{}")], f"{RUN_DIR}: manifest.json has no 'kind'"),
        ([(f"{RUN_DIR}/manifest.json", _manifest(files=[]))], "has no 'files'"),
        ([(f"{RUN_DIR}/manifest.json", _manifest(key="ab" * 16))], "names key 'abab.*not the directory's"),
        ([(f"{RUN_DIR}/manifest.json", _manifest(kind="evals"))], "names kind 'evals', but the artifact is under runs/"),
        ([(f"{RUN_DIR}/manifest.json", _manifest(kind="models"))], "names kind 'models', not one of"),
        ([(f"{RUN_DIR}/manifest.json", _manifest(files={"metrics.jsonl": "00"}))], "missing file metrics.jsonl"),
        ([(f"{RUN_DIR}/manifest.json", _manifest(files={"/proc/self/status": "00"}))], "not a file inside the artifact"),
        ([(f"{RUN_DIR}/manifest.json", _manifest()), (f"{RUN_DIR}/extra", b"x")], "unexpected file extra"),
        ([(f"{RUN_DIR}.partial/metrics.jsonl", b"{}\n")], "no pending.json"),
        ([(f"{RUN_DIR}.partial/pending.json", _pending())], "no checkpoint matching"),
        # a key is the digest of its components: an archive whose components name another key is
        # relabelled or edited, finished or not
        ([(f"{RUN_DIR}/manifest.json", _manifest(key_components={"kind": "runs", "spec": {"name": "y"}}))], "key_components digest to"),
        ([(f"{RUN_DIR}/manifest.json", _manifest(key_components="x"))], "lists no key_components"),
        ([(f"{RUN_DIR}.partial/pending.json", _pending(key_components={"kind": "runs"}))], "key_components digest to"),
        ([(f"{RUN_DIR}.partial/pending.json", _pending(key="ab" * 16))], "pending.json names key 'abab"),
        ([(f"{RUN_DIR}.partial/pending.json", b"[]")], "pending.json is not a JSON object"),
        ([(f"{RUN_DIR}.partial/pending.json", b"{}")], "pending.json names key 'None'"),
        ([], "holds no artifact"),
        ([(f"{RUN_DIR}/a", b"x"), (f"{RUN_DIR}/a/b", b"y")], "member .*a/b' repeats a file or lies inside one"),
        ([(f"{RUN_DIR}/a", b"x"), (f"{RUN_DIR}/a", b"y")], "member .*/a' repeats a file or lies inside one"),
    ],
)
def test_a_bad_archive_is_refused_and_changes_nothing(tmp_path, members, message):
    store = Store(tmp_path / "store")
    with pytest.raises(StoreError, match=message):
        import_archive(store, _archive(tmp_path, members))
    assert not (tmp_path / "store").exists() and not (tmp_path / "evil").exists()  # not even empty folders


def test_a_run_without_its_checkpoint_is_imported_only_when_asked_as_a_record(tmp_path):
    """What came back from a machine that could not send a checkpoint: pending.json and the
    logged epochs. Refused by default (it cannot continue), kept with --without-checkpoint for
    reports; never without a logged epoch."""
    pending = _pending(name="grid_10", seeds=[0, 1])
    rows = b"".join(json.dumps({"epoch": e, "return": [1.0, 2.0]}).encode() + b"\n" for e in (1, 2))
    record = [(f"{RUN_DIR}.partial/pending.json", pending), (f"{RUN_DIR}.partial/metrics.jsonl", rows)]
    store = Store(tmp_path / "store")
    with pytest.raises(StoreError, match="no checkpoint matching.*--without-checkpoint"):
        import_archive(store, _archive(tmp_path, record))
    with pytest.raises(StoreError, match="neither an intact checkpoint nor a logged epoch"):
        import_archive(store, _archive(tmp_path, record[:1], "empty.tar.gz"), without_checkpoint=True)
    bad = [record[0], (f"{RUN_DIR}.partial/metrics.jsonl", rows + b'{"epoch": "3", "return": [1.0]}\n')]
    with pytest.raises(StoreError, match="line 3 of metrics.jsonl is not an epoch's metrics"):
        import_archive(store, _archive(tmp_path, bad, "bad.tar.gz"), without_checkpoint=True)
    assert not (tmp_path / "store").exists()
    proc = esr("import", "--without-checkpoint", str(_archive(tmp_path, record)), store=tmp_path / "store")
    assert "a record without a checkpoint: training it again starts from epoch 0" in " ".join(proc.stderr.split())
    path = Path(proc.stdout.strip())
    assert path == tmp_path / "store" / f"{RUN_DIR}.partial" and (path / "metrics.jsonl").read_bytes() == rows


def test_a_refused_import_removes_only_the_folders_it_made(tmp_path):
    store = Store(tmp_path / "store")
    other = tmp_path / "store" / "runs" / "ff" / "kept"
    other.mkdir(parents=True)
    with pytest.raises(StoreError, match="has no 'kind'"):
        import_archive(store, _archive(tmp_path, [(f"{RUN_DIR}/manifest.json", b"{}")]))
    assert sorted(p.relative_to(tmp_path / "store").as_posix() for p in (tmp_path / "store").rglob("*")) == \
        ["runs", "runs/ff", "runs/ff/kept"]


def test_an_empty_manifest_is_not_imported_as_an_artifact(tmp_path):
    """A tar holding only runs/KK/KEY/manifest.json = {} was once taken as a finished run."""
    store = tmp_path / "store"
    proc = esr("import", str(_archive(tmp_path, [(f"{RUN_DIR}/manifest.json", b"{}")])), store=store, check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert f"{RUN_DIR}: manifest.json has no 'kind'" in proc.stderr and "nothing imported" in proc.stderr
    assert not store.exists()  # nothing committed, no folder left behind


def test_a_tampered_finished_run_is_refused(smoke_run, tmp_path):
    store, path, _ = smoke_run
    copy = tmp_path / "copy" / "runs" / path.name[:2] / path.name
    shutil.copytree(path, copy)
    (copy / "metrics.jsonl").write_text("{}\n")
    archive = tmp_path / "tampered.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        tar.add(copy, arcname=f"runs/{path.name[:2]}/{path.name}")
    proc = esr("import", str(archive), store=tmp_path / "other", check=False)
    assert proc.returncode == 2
    assert "changed file metrics.jsonl" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "other" / "runs" / path.name[:2] / path.name).exists()


@pytest.mark.parametrize("content", [b"not an archive at all", None])
def test_an_unreadable_archive_is_one_line(smoke_run, tmp_path, content):
    store, path, _ = smoke_run
    archive = tmp_path / "broken.tar.gz"
    if content is None:  # a real export cut short
        esr("export", path.name[:8], "--out", str(archive), store=store)
        archive.write_bytes(archive.read_bytes()[: archive.stat().st_size // 2])
    else:
        archive.write_bytes(content)
    proc = esr("import", str(archive), store=tmp_path / "other", check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and str(archive) in proc.stderr
    assert not list((tmp_path / "other").glob("runs/*/*"))


def test_export_names_a_missing_artifact(tmp_path):
    proc = esr("export", "beef", store=tmp_path / "empty", check=False)
    assert proc.returncode == 2 and "no artifact with key 'beef'" in proc.stderr
    proc = esr("import", str(tmp_path / "nowhere.tar.gz"), store=tmp_path / "empty", check=False)
    assert proc.returncode == 2 and "no archive" in proc.stderr


def test_export_refuses_a_target_that_is_not_a_file_before_any_work(smoke_run, tmp_path):
    store, path, _ = smoke_run
    pipe = tmp_path / "pipe.tar.gz"
    os.mkfifo(pipe)
    for target, message in ((pipe, "not a regular file"), (tmp_path / "no" / "x.tar.gz", "no directory")):
        proc = esr("export", path.name[:8], "--out", str(target), store=store, check=False)
        assert proc.returncode == 2 and message in proc.stderr and "Traceback" not in proc.stderr
    assert pipe.exists() and not pipe.is_file() and not (tmp_path / "no").exists()


def test_an_archive_larger_than_the_free_disk_is_refused_before_it_is_unpacked(smoke_run, tmp_path, monkeypatch):
    """The members' sizes in the tar headers are summed first: a small archive of zeros that
    would unpack past the free space writes nothing."""
    import esr_cli.transfer as transfer

    store, path, _ = smoke_run
    archive = tmp_path / "run.tar.gz"
    esr("export", path.name[:8], "--out", str(archive), store=store)
    monkeypatch.setattr(transfer.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(10**9, 10**9, 1000))
    other = tmp_path / "other"
    with pytest.raises(StoreError, match=r"unpacks to [\d.,]+ MiB but the store's disk has 0.0 MiB free"):
        import_archive(Store(other), archive)
    assert not [p for p in other.rglob("*") if p.is_file()]


def test_several_archives_are_all_checked_before_any_is_added(smoke_run, tmp_path):
    store, path, _ = smoke_run
    good, bad = tmp_path / "good.tar.gz", tmp_path / "bad.tar.gz"
    esr("export", path.name[:8], "--out", str(good), store=store)
    bad.write_bytes(b"not an archive at all")
    proc = esr("import", str(good), str(bad), store=tmp_path / "other", check=False)
    assert proc.returncode == 2 and "bad.tar.gz is not a tar archive, or a damaged one" in proc.stderr
    assert not list((tmp_path / "other").glob("runs/*/*"))  # the good one waits for the bad one to be mended
