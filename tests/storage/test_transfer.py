"""`esr export` / `esr import`: an artifact, finished or not, moves between stores as one file,
and a hostile archive changes nothing (esr_cli/storage/transfer.py)."""

import bz2
import copy
import gzip
import io
import json
import lzma
import os
import shutil
import signal
import subprocess
import tarfile
import tempfile
import time
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, esr
from hypothesis import HealthCheck, event, given, settings, strategies as st
from run_helpers import SMOKE, final_arrays, partials, rename_checkpoint

from esr_cli.common import specs, tar_reader
from esr_cli.storage import signing
from esr_cli.storage.checkpoint_files import verify_artifact
from esr_cli.storage.store import STAGING_PREFIX, STAGING_RE, Store, StoreError, _host, content_key, digest_bytes, digest_file
from esr_cli.storage.transfer import import_archive

SPEC = specs.load(ROOT / "experiments/grid_2.yaml", "smoke")
SPEC_YAML = specs.to_yaml(SPEC).encode()  # a run's spec.yaml, as training writes it
COMPONENTS = {"kind": "runs", "spec": SPEC.training_part(), "budget": "smoke"}
KEY = content_key(COMPONENTS)


@pytest.mark.slow
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


@pytest.mark.slow
def test_a_finished_run_travels_as_metrics_only_and_says_what_it_cannot_do(smoke_run, tmp_path):
    """`export --without-checkpoint`: the manifest, spec and metrics, no checkpoint folder and
    no TensorBoard event files (a second copy of the metrics). It imports and verifies as a
    finished run and reports read it, as does one archived before the event files were left out;
    evaluating it asks for the full archive, whose import puts the rest back; a damaged metrics
    file is still found."""
    store, path, _ = smoke_run
    assert (path / "tensorboard").is_dir()
    full, slim = tmp_path / "full.tar.gz", tmp_path / "slim.tar.gz"
    esr("export", path.name[:8], "--out", str(full), store=store)
    esr("export", path.name[:8], "--out", str(slim), "--without-checkpoint", store=store)
    with tarfile.open(slim) as tar:
        names = tar.getnames()
    assert not any("/checkpoints/" in n or "/tensorboard/" in n for n in names) and any(n.endswith("/metrics.jsonl") for n in names)
    assert slim.stat().st_size < full.stat().st_size / 2
    older = tmp_path / "older"  # metrics only with its event files, as runs were archived before
    shutil.copytree(path, older / "runs" / path.name[:2] / path.name, ignore=lambda d, names: ["checkpoints"] if d == str(path) else [])
    assert esr("verify", store=older).returncode == 0
    other = tmp_path / "other"
    copy = Path(esr("import", str(slim), store=other).stdout.strip())
    assert esr("verify", store=other).returncode == 0
    assert (copy / "metrics.jsonl").read_bytes() == (path / "metrics.jsonl").read_bytes()
    listed = esr("ls", store=other)
    assert path.name[:12] in listed.stdout
    for command in (["eval", path.name[:8]], ["diagnose", path.name[:8]]):
        refused = esr(*command, store=other, check=False)
        assert refused.returncode == 2 and "kept as metrics only" in " ".join(refused.stderr.split()), command
        assert "`esr import` of its full archive puts them back" in " ".join(refused.stderr.split())
    assert not (copy / "checkpoints").exists()  # reading it gave the committed copy no folder
    # A full archive of the same key whose checkpoint files are not the ones this copy's manifest
    # lists (its own manifest rewritten to match them) is refused before anything moves.
    forger = tmp_path / "forger"
    forged = forger / "runs" / path.name[:2] / path.name
    shutil.copytree(path, forged)
    victim = next(p for p in sorted((forged / "checkpoints").rglob("*")) if p.is_file())
    victim.write_bytes(victim.read_bytes() + b"x")
    manifest = json.loads((forged / "manifest.json").read_text())
    manifest["files"][victim.relative_to(forged).as_posix()] = digest_file(victim)
    (forged / "manifest.json").write_text(json.dumps(manifest))
    esr("export", path.name[:8], "--out", str(tmp_path / "forged.tar.gz"), store=forger)
    refused = esr("import", str(tmp_path / "forged.tar.gz"), store=other, check=False)
    said = " ".join(refused.stderr.split())
    assert refused.returncode == 2 and "are not the files the store's copy of runs" in said and "changed file checkpoints/" in said
    assert not (copy / "checkpoints").exists() and not (copy / "tensorboard").exists()
    # The full archive of the same run puts back what the metrics-only copy lacks, as the refusal
    # says; importing it again then has nothing to add.
    restored = esr("import", str(full), store=other)
    assert "kept without checkpoints and tensorboard" in " ".join(restored.stderr.split()) and (copy / "checkpoints").is_dir()
    assert esr("verify", store=other).returncode == 0
    assert "nothing to import" in esr("import", str(full), store=other).stderr
    (copy / "metrics.jsonl").write_bytes(b"{}\n")
    broken = esr("verify", store=other, check=False)
    assert broken.returncode == 1 and "metrics.jsonl" in broken.stderr


@pytest.mark.slow  # trains the shared smoke run
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


@pytest.mark.slow
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



@pytest.mark.slow
def test_an_archive_relabelled_to_a_later_epoch_never_replaces_the_local_unfinished_run(tmp_path):
    """Of two unfinished copies of a run, the one further along is kept: an archive whose
    checkpoint folder was renamed to a later epoch, its digests and metrics edited to agree,
    would pass for it. The epoch its training state holds is read before the two are compared,
    so it is refused, naming both epochs, and the store's own unfinished run is left as it was."""
    here = tmp_path / "here"
    assert esr(*SMOKE, store=here, check=False, ESR_FAULT="after_checkpoint@1").returncode == -signal.SIGKILL
    (part,) = partials(here)
    forged = tmp_path / "forger" / part.relative_to(here)
    shutil.copytree(part, forged)
    rename_checkpoint(forged, 1, 2)
    row = json.loads((forged / "metrics.jsonl").read_text().splitlines()[0])
    with open(forged / "metrics.jsonl", "a") as f:
        f.write(json.dumps({**row, "epoch": 2}) + "\n")
    archive = tmp_path / "relabelled.tar.gz"
    esr("export", part.name[:8], "--out", str(archive), store=tmp_path / "forger")
    before = {p.relative_to(part): p.read_bytes() for p in part.rglob("*") if p.is_file()}

    proc = esr("import", str(archive), store=here, check=False)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    said = " ".join(proc.stderr.split())
    assert "checkpoint folder says epoch 2 but its state holds epoch 1;" in said
    assert "nothing imported (this store's unfinished run, at epoch 1, is kept)" in said
    assert partials(here) == [part] and {p.relative_to(part): p.read_bytes() for p in part.rglob("*") if p.is_file()} == before
    assert not [p for p in part.parent.iterdir() if p.name.startswith(STAGING_PREFIX)]


@pytest.mark.slow
def test_a_store_that_cannot_be_written_to_exports_all_the_same(tmp_path):
    """Exporting only reads the store: it stages beside the archive, so a store the user cannot
    write to (another's, a read-only mount) exports, leaving nothing beside the archive."""
    components = {"kind": "runs", "spec": {"name": "x"}}
    key = content_key(components)
    root = tmp_path / "store"
    store = Store(root)
    (store.begin("runs", key, {"name": "x", "key": key, "key_components": components}) / "metrics.jsonl").write_text('{"epoch": 1}\n')
    store.commit("runs", key, {"kind": "runs", "name": "x", "key": key, "key_components": components})
    archive = tmp_path / "out" / "x.tar.gz"
    archive.parent.mkdir()
    subprocess.run(["chmod", "-R", "a-w", str(root)], check=True)
    try:
        if os.access(root, os.W_OK):
            pytest.skip("permissions do not stop this user's writes (root)")
        proc = esr("export", key[:8], "--out", str(archive), store=root)
        assert Path(proc.stdout.strip()) == archive
        assert [p.name for p in archive.parent.iterdir()] == ["x.tar.gz"]  # no staging folder or part left
    finally:
        subprocess.run(["chmod", "-R", "u+w", str(root)], check=True)
    esr("import", str(archive), store=tmp_path / "other")
    assert esr("verify", store=tmp_path / "other").returncode == 0

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
    return json.dumps({"kind": "runs", "key": KEY, "key_components": COMPONENTS, "name": SPEC.name, **fields}).encode()


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
        ([(f"{RUN_DIR}.partial/pending.json", _pending()), (f"{RUN_DIR}.partial/spec.yaml", SPEC_YAML)], "no checkpoint matching"),
        ([(f"{RUN_DIR}.partial/pending.json", _pending()), (f"{RUN_DIR}.partial/spec.yaml", b"[1, 2")], "spec.yaml cannot be read"),
        ([(f"{RUN_DIR}.partial/pending.json", _pending()),
          (f"{RUN_DIR}.partial/spec.yaml", SPEC_YAML.replace(b"  lr: 0.001", b"  lr: 0.002"))], "spec.yaml is not the spec its key"),
        # a key is the digest of its components: an archive whose components name another key is
        # relabelled or edited, finished or not
        ([(f"{RUN_DIR}/manifest.json", _manifest(key_components={"kind": "runs", "spec": {"name": "y"}}))], "key_components digest to"),
        ([(f"{RUN_DIR}/manifest.json", _manifest(key_components="x"))], "lists no key_components"),
        # labels shown and filtered on are the key's: a smoke run relabelled as another is found out
        ([(f"{RUN_DIR}/manifest.json", _manifest(budget="paper"))], "names its budget otherwise than its key components"),
        ([(f"{RUN_DIR}/manifest.json", _manifest(method="ave", env="overcooked"))], "names its method and env otherwise"),
        ([(f"{RUN_DIR}/manifest.json", _manifest(seeds=[7]))], "names its seeds otherwise"),
        ([(f"{RUN_DIR}/manifest.json", _manifest(seeds=10**400))], "names its seeds otherwise"),
        ([(f"{RUN_DIR}.partial/pending.json", _pending(budget="paper"))], "pending.json names its budget otherwise"),
        ([(f"{RUN_DIR}.partial/pending.json", _pending(name="grid_7")), (f"{RUN_DIR}.partial/spec.yaml", SPEC_YAML)],
         "spec.yaml names another spec than its record does"),
        ([(f"{RUN_DIR}.partial/pending.json", _pending(key_components={"kind": "runs"}))], "key_components digest to"),
        ([(f"{RUN_DIR}.partial/pending.json", _pending(key="ab" * 16))], "pending.json names key 'abab"),
        ([(f"{RUN_DIR}.partial/pending.json", b"[]")], "pending.json is not a JSON object"),
        ([(f"{RUN_DIR}.partial/pending.json", b"{}")], "pending.json names key 'None'"),
        ([], "holds no artifact"),
        ([(f"{RUN_DIR}/a", b"x"), (f"{RUN_DIR}/a/b", b"y")], "member .*a/b' repeats a file or lies inside one"),
        ([(f"{RUN_DIR}/a", b"x"), (f"{RUN_DIR}/a", b"y")], "member .*/a' repeats a file or lies inside one"),
        ([(f"{RUN_DIR}/a", None), (f"{RUN_DIR}/a", b"y")], "member .*/a' is a file where a folder of the archive is"),
        ([(f"{RUN_DIR}/a/b", b"x"), (f"{RUN_DIR}/a", b"y")], "member .*/a' is a file where a folder of the archive is"),
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
    pending = _pending(seeds=SPEC.train.seeds)
    rows = b"".join(json.dumps({"epoch": e, "return": [1.0, 2.0]}).encode() + b"\n" for e in (1, 2))
    record = [(f"{RUN_DIR}.partial/pending.json", pending), (f"{RUN_DIR}.partial/spec.yaml", SPEC_YAML),
              (f"{RUN_DIR}.partial/metrics.jsonl", rows)]
    store = Store(tmp_path / "store")
    with pytest.raises(StoreError, match="no checkpoint matching.*--without-checkpoint"):
        import_archive(store, _archive(tmp_path, record))
    with pytest.raises(StoreError, match="neither an intact checkpoint nor a logged epoch"):
        import_archive(store, _archive(tmp_path, record[:2], "empty.tar.gz"), without_checkpoint=True)
    bad = [*record[:2], (f"{RUN_DIR}.partial/metrics.jsonl", rows + b'{"epoch": "3", "return": [1.0]}\n')]
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


@pytest.mark.slow  # trains the shared smoke run
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


@pytest.mark.slow  # trains the shared smoke run
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


def _hand_made_run(root: Path, name: str = "x") -> tuple[Path, str]:
    """A committed run of one metrics line, made through the store as training makes one."""
    components = {"kind": "runs", "spec": {"name": name}}
    key = content_key(components)
    store = Store(root)
    (store.begin("runs", key, {"name": name, "key": key, "key_components": components}) / "metrics.jsonl").write_text('{"epoch": 1}\n')
    return store.commit("runs", key, {"kind": "runs", "name": name, "key": key, "key_components": components}), key


@pytest.mark.parametrize("intruder", ["link to a device", "link to a file", "fifo", "link to a folder"])
def test_export_refuses_what_is_not_a_plain_file_in_an_artifact_and_reads_none_of_it(tmp_path, intruder):
    """A link (to /dev/zero, to a file outside, to a folder) or a FIFO put into a committed
    artifact by hand is named, never followed or waited on: exporting a link to /dev/zero once
    wrote until the disk was full. Nothing is left beside the archive."""
    from esr_cli.storage.transfer import export

    path, key = _hand_made_run(tmp_path / "store")
    (tmp_path / "outside.txt").write_text("secret")
    place = path / "figures"
    place.mkdir(mode=0o755, exist_ok=True)
    target = {"link to a device": "/dev/zero", "link to a file": str(tmp_path / "outside.txt"), "link to a folder": str(tmp_path)}
    if intruder == "fifo":
        os.mkfifo(place / "zz")
    else:
        (place / "zz").symlink_to(target[intruder])
    out = tmp_path / "out"
    out.mkdir()
    signal.alarm(20)  # a regression would block on the FIFO or copy /dev/zero: the alarm ends the test
    try:
        with pytest.raises(StoreError, match=r"figures/zz is (a link|a FIFO, a socket or a device): an artifact holds plain files and folders only"):
            export(Store(tmp_path / "store"), key[:8], out / "x.tar.gz")
    finally:
        signal.alarm(0)
    assert list(out.iterdir()) == []
    (place / "zz").unlink()
    assert export(Store(tmp_path / "store"), key[:8], out / "x.tar.gz").path == out / "x.tar.gz"  # intact again: exports


def test_export_copies_no_more_than_a_file_held_when_it_was_listed(tmp_path, monkeypatch):
    """A file that grows while it is copied is copied to the size it had when listed, and the
    whole copy must fit the free disk before a byte is written."""
    import esr_cli.storage.transfer as transfer

    src = tmp_path / "src"
    (src / "d").mkdir(parents=True)
    (src / "a.bin").write_bytes(b"a" * 1000)
    (src / "d" / "b.bin").write_bytes(b"b" * 10)
    real_open = transfer.bounded_files.open_regular

    def growing(path, follow_links=False):
        f = real_open(path, follow_links)
        with open(path, "ab") as more:
            more.write(b"+" * 5000)  # after the open: not copied
        return f

    monkeypatch.setattr(transfer.bounded_files, "open_regular", growing)
    transfer.copy_plain_tree(src, tmp_path / "dst")
    assert (tmp_path / "dst" / "a.bin").read_bytes() == b"a" * 1000 and (tmp_path / "dst" / "d" / "b.bin").read_bytes() == b"b" * 10
    monkeypatch.setattr(transfer.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(10**9, 10**9 - 100, 100))
    with pytest.raises(StoreError, match=r"^not enough free space: .* holds [\d,]+ bytes but the disk of .* has 100 free$"):
        transfer.copy_plain_tree(src, tmp_path / "dst2")
    assert not (tmp_path / "dst2").exists()


def test_export_names_a_missing_artifact(tmp_path):
    proc = esr("export", "beef", store=tmp_path / "empty", check=False)
    assert proc.returncode == 2 and "no artifact with key 'beef'" in proc.stderr
    proc = esr("import", str(tmp_path / "nowhere.tar.gz"), store=tmp_path / "empty", check=False)
    assert proc.returncode == 2 and "no archive" in proc.stderr


@pytest.mark.slow  # trains the shared smoke run
def test_export_refuses_a_target_that_is_not_a_file_before_any_work(smoke_run, tmp_path):
    store, path, _ = smoke_run
    pipe = tmp_path / "pipe.tar.gz"
    os.mkfifo(pipe)
    for target, message in ((pipe, "not a regular file"), (tmp_path / "no" / "x.tar.gz", "no directory")):
        proc = esr("export", path.name[:8], "--out", str(target), store=store, check=False)
        assert proc.returncode == 2 and message in proc.stderr and "Traceback" not in proc.stderr
    assert pipe.exists() and not pipe.is_file() and not (tmp_path / "no").exists()


@pytest.mark.slow  # trains the shared smoke run
def test_an_archive_larger_than_the_free_disk_is_refused_before_it_is_unpacked(smoke_run, tmp_path, monkeypatch):
    """The members' sizes in the tar headers are summed first: a small archive of zeros that
    would unpack past the free space writes nothing."""
    import esr_cli.storage.transfer as transfer

    store, path, _ = smoke_run
    archive = tmp_path / "run.tar.gz"
    esr("export", path.name[:8], "--out", str(archive), store=store)
    monkeypatch.setattr(transfer.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(10**9, 10**9, 1000))
    other = tmp_path / "other"
    with pytest.raises(StoreError, match=r"unpacks to [\d.,]+ MiB but the store's disk has 0.0 MiB free"):
        import_archive(Store(other), archive)
    assert not [p for p in other.rglob("*") if p.is_file()]


@pytest.mark.slow  # trains the shared smoke run
def test_several_archives_are_all_checked_before_any_is_added(smoke_run, tmp_path):
    store, path, _ = smoke_run
    good, bad = tmp_path / "good.tar.gz", tmp_path / "bad.tar.gz"
    esr("export", path.name[:8], "--out", str(good), store=store)
    bad.write_bytes(b"not an archive at all")
    proc = esr("import", str(good), str(bad), store=tmp_path / "other", check=False)
    assert proc.returncode == 2 and "bad.tar.gz: not a tar archive, or a damaged one" in proc.stderr
    assert not list((tmp_path / "other").glob("runs/*/*"))  # the good one waits for the bad one to be mended


# ---------------------------------------------------------------- archives bounded before they are read
def _block(name: bytes, kind: bytes = b"0", size: int = 0) -> bytes:
    """A ustar header, checksum included: what tarfile would not write for a hostile archive."""
    block = bytearray(512)
    block[:len(name)] = name[:100]
    block[100:108] = b"0000644\0"
    block[124:136] = b"%011o\0" % size if size < 8 ** 11 else b"\x80" + size.to_bytes(11, "big")
    block[156:157] = kind
    block[257:265] = b"ustar\x0000"
    block[148:156] = b" " * 8
    block[148:156] = b"%06o\0 " % sum(block)
    return bytes(block)


def _pax(path: str) -> bytes:
    """A pax header naming the next member `path`, with its body."""
    text = f"path={path}\n".encode()
    n = len(text) + 1
    record = b"%d %s" % (n + len(str(n)), text)
    return _block(b"././@PaxHeader", b"x", len(record)) + record + bytes(-len(record) % 512)


END = bytes(1024)


def _gz(tmp_path, raw: bytes, name="hostile.tar.gz") -> Path:
    path = tmp_path / name
    path.write_bytes(gzip.compress(raw, compresslevel=1))
    return path


def _refused_within(store: Store, archive: Path, match: str, mib: int = 200, seconds: float = 60.0) -> None:
    """`esr import`'s refusal of `archive`: matching `match`, under `mib` MiB of Python memory at
    its peak, with nothing written where the store would be. `seconds` catches a refusal that
    never comes (a reader that loops), not speed: tracemalloc slows the reader several-fold, and
    a loaded machine more."""
    tracemalloc.start()
    start = time.monotonic()
    try:
        with pytest.raises(StoreError, match=match):
            import_archive(store, archive)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < mib << 20, f"{peak / (1 << 20):.0f} MiB"
    assert time.monotonic() - start < seconds
    assert not store.root.exists()


DEEP = f"{RUN_DIR}/" + "d/" * (tar_reader.MAX_DEPTH - 3) + "f"  # one folder past the limit
LONG = f"{RUN_DIR}/" + "/".join(["n" * 200] * 6)  # parts within 255 bytes, the whole past 1,024


@pytest.mark.parametrize("limit, raw, match", [
    ("members", b"".join(_block(f"{RUN_DIR}/d{i}".encode(), b"5") for i in range(tar_reader.MAX_MEMBERS + 1)) + END,
     "more than 10,000 members"),
    ("unpacked size", _block(f"{RUN_DIR}/metrics.jsonl".encode(), size=tar_reader.MAX_UNPACKED_BYTES + 1),
     "unpacks to more than 4,294,967,296 bytes"),
    ("depth", _pax(DEEP) + _block(b"f") + END, "33 folders deep; at most 32"),
    ("name length", _pax(LONG) + _block(b"f") + END, "a name of 1,246 bytes; at most 1,024"),
    ("name part", _pax(f"{RUN_DIR}/{'n' * 256}") + _block(b"f") + END, "a part longer than 255 bytes"),
    ("pax header", _block(b"././@PaxHeader", b"x", tar_reader.MAX_HEADER_BYTES + 1),
     "an extended header of 65,537 bytes, more than the 65,536"),
    ("GNU long name", _block(b"././@LongLink", b"L", 1 << 40), "an extended header of 1,099,511,627,776 bytes"),
    ("chained headers", _pax(f"{RUN_DIR}/a") + _pax(f"{RUN_DIR}/b") + _block(b"f") + END,
     "two extended headers of one kind"),
])
def test_an_archive_past_each_limit_is_refused_before_anything_is_unpacked(tmp_path, limit, raw, match):
    """Each bound of tar_reader is met on the raw stream: the header that passes it is the last
    thing read (a body of 1 TiB that a header announces is never read, nor needs to exist)."""
    _refused_within(Store(tmp_path / "store"), _gz(tmp_path, raw), match)


def test_an_archive_file_past_the_compressed_limit_is_refused_unread(tmp_path):
    archive = tmp_path / "huge.tar.gz"
    with open(archive, "wb") as f:  # sparse: no disk is used
        f.truncate(tar_reader.MAX_ARCHIVE_BYTES + 1)
    _refused_within(Store(tmp_path / "store"), archive, "4,294,967,297 bytes, more than the 4,294,967,296 esr imports")


def _zeros_gz(head: bytes, zeros: int) -> bytes:
    """`head` then `zeros` zero bytes, gzip-compressed a MiB at a time (about 1,000 to 1)."""
    z = zlib.compressobj(9, zlib.DEFLATED, 31)
    parts = [z.compress(head)] + [z.compress(bytes(1 << 20)) for _ in range(zeros >> 20)]
    return b"".join(parts + [z.flush()])


@pytest.mark.slow
@pytest.mark.parametrize("head, match", [
    (_block(f"{RUN_DIR}/metrics.jsonl".encode(), size=1 << 40), "unpacks to more than"),  # says 1 TiB
    (_block(f"{RUN_DIR}/metrics.jsonl".encode(), size=3) + b"{}\n".ljust(512, b"\0") + END, "data after the end"),
])
def test_a_gzip_bomb_is_refused_in_a_moment(tmp_path, head, match):
    """A few hundred KiB that inflate to 512 MiB of zeros: what a header announces is refused
    before it is read, and zeros past the end of the archive after 64 KiB of them."""
    archive = tmp_path / "bomb.tar.gz"
    archive.write_bytes(_zeros_gz(head, 512 << 20))
    assert archive.stat().st_size < 1 << 20
    _refused_within(Store(tmp_path / "store"), archive, match, seconds=2.0)


def _plain_tar() -> bytes:
    return _block(f"{RUN_DIR}/metrics.jsonl".encode(), size=3) + b"{}\n".ljust(512, b"\0") + END


def _gzip_bytes(data: bytes) -> bytes:
    return gzip.compress(data, mtime=0)  # the same bytes on every collection (xdist workers compare them)


MISNAMED = [
    ("bz.tar.gz", bz2.compress(_plain_tar()), "bzip2-compressed, though its name says gzip"),
    ("xz.tar.gz", lzma.compress(_plain_tar()), "xz-compressed, though its name says gzip"),
    ("zst.tar.gz", b"\x28\xb5\x2f\xfd" + bytes(600), "zstd-compressed, though its name says gzip"),
    ("plain.tar.gz", _plain_tar(), "an uncompressed tar, though its name says gzip"),
    ("gzip.tar.bz2", _gzip_bytes(_plain_tar()), "not named .tar.gz or .tgz"),
    ("gzip.tar", _gzip_bytes(_plain_tar()), "not named .tar.gz or .tgz"),
    ("tail.tar.gz", _gzip_bytes(_plain_tar()) + b"junk after the gzip stream", "damaged gzip data"),
    ("crc.tar.gz", _gzip_bytes(_plain_tar())[:-8] + bytes(8), "damaged gzip data"),
    ("cut.tar.gz", _gzip_bytes(_plain_tar())[:40], "cut short"),
]


@pytest.mark.parametrize("name, data, match", MISNAMED, ids=[case[0] for case in MISNAMED])
def test_an_archive_whose_compression_is_not_what_its_name_says_is_refused(tmp_path, name, data, match):
    (tmp_path / name).write_bytes(data)
    _refused_within(Store(tmp_path / "store"), tmp_path / name, match)


def test_a_fifo_given_as_an_archive_is_refused_without_waiting(tmp_path):
    fifo = tmp_path / "pipe.tar.gz"
    os.mkfifo(fifo)
    proc = esr("import", str(fifo), store=tmp_path / "store", check=False, timeout=60)
    assert proc.returncode == 2 and "pipe.tar.gz: not a regular file" in proc.stderr
    assert not (tmp_path / "store").exists()


# ---------------------------------------------------------------- staging folders of killed imports
@pytest.mark.slow
def test_what_a_killed_import_left_is_removed_by_the_next_command(smoke_run, tmp_path):
    store, path, _ = smoke_run
    archive = tmp_path / "run.tar.gz"
    esr("export", path.name[:8], "--out", str(archive), store=store)
    other = tmp_path / "other"
    shard = other / "runs" / path.name[:2]
    for command in ("ls", "verify"):
        killed = esr("import", str(archive), store=other, check=False, ESR_FAULT="after_unpack")
        assert killed.returncode == -signal.SIGKILL
        (left,) = [p for p in shard.iterdir() if p.name.startswith(STAGING_PREFIX)]
        assert STAGING_RE.fullmatch(left.name) and any(left.rglob("manifest.json"))
        after = esr(command, store=other, check=False)
        assert f"removed the staging folder a killed `esr import` left: {left}" in " ".join(after.stderr.split())
        assert not left.exists() and not (shard / path.name).exists()
    assert Path(esr("import", str(archive), store=other).stdout.strip()) == shard / path.name


def test_only_a_dead_import_s_staging_folder_is_removed_and_a_run_it_moved_aside_is_put_back(tmp_path):
    store = Store(tmp_path / "store")
    shard = tmp_path / "store" / "runs" / KEY[:2]
    gone = subprocess.Popen(["true"])
    gone.wait()  # a process that has ended: its pid names no process now
    here = _host()
    dead, aside = shard / f"{STAGING_PREFIX}{gone.pid}-abc_1234@{here}", f"{KEY}.partial"
    (dead / aside).mkdir(parents=True)
    (dead / aside / "pending.json").write_text("{}")
    kept = [shard / f"{STAGING_PREFIX}{os.getpid()}-abcd1234@{here}",  # an import running now
            shard / f"{STAGING_PREFIX}{gone.pid}-abcd1234@other-machine",  # a pid of another machine
            shard / f"{STAGING_PREFIX}abcd1234",  # no owner in its name
            shard / "a-folder-of-someone-else"]
    for d in kept:
        d.mkdir()
    assert store.remove_abandoned_imports() == [dead]
    assert not dead.exists() and all(d.is_dir() for d in kept)
    assert (shard / aside / "pending.json").read_text() == "{}"  # the local run, back where it was


# ---------------------------------------------------------------- what a key does and does not prove
def _reexported(tmp_path, src: Path, edit) -> Path:
    """The finished run `src` re-archived after `edit(copy)`, its manifest's digests recomputed
    (what a forger would do)."""
    base = Path(tempfile.mkdtemp(dir=tmp_path))
    copy = base / "runs" / src.name[:2] / src.name
    shutil.copytree(src, copy)
    edit(copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["files"] = {rel: digest_file(copy / rel) for rel in manifest["files"]}
    (copy / "manifest.json").write_text(json.dumps(manifest))
    archive = base / "forged.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        tar.add(copy, arcname=f"runs/{src.name[:2]}/{src.name}")
    return archive


@pytest.mark.slow  # trains the shared smoke run
def test_a_spec_swapped_under_a_key_is_refused_but_digests_do_not_stop_a_forger(smoke_run, tmp_path):
    """The key is the digest of the spec it names: a spec.yaml that is another spec is refused
    even with its digest recomputed. Metrics rewritten with their digest recomputed still import
    (docs/reliability.md, threat model): digests catch damage, not a forger."""
    _, path, _ = smoke_run
    swapped = _reexported(tmp_path, path, lambda d: (d / "spec.yaml").write_text(
        (d / "spec.yaml").read_text().replace("  lr: 0.001", "  lr: 0.002")))
    proc = esr("import", str(swapped), store=tmp_path / "a", check=False)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
    assert "spec.yaml is not the spec its key was computed from" in proc.stderr and not (tmp_path / "a").exists()

    forged = Path(esr("import", str(_reexported(tmp_path, path, _rewrite_metrics)), store=tmp_path / "b").stdout.strip())
    assert "99.0" in (forged / "metrics.jsonl").read_text()


def _rewrite_metrics(run: Path) -> None:
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    (run / "metrics.jsonl").write_text("".join(json.dumps({**r, "return": [99.0] * len(r["return"])}) + "\n" for r in rows))


@pytest.mark.slow
def test_a_signed_archive_imports_and_a_forged_or_unsigned_one_is_refused(smoke_run, tmp_path):
    """What digests cannot do, a signature does: `esr import --require-signature` takes only an
    archive whose ARCHIVE.sig matches it under the key in $ESR_ARCHIVE_KEY's file."""
    store, path, _ = smoke_run
    key, other_key = tmp_path / "archive.key", tmp_path / "other.key"
    key.write_bytes(os.urandom(32))
    other_key.write_bytes(os.urandom(32))
    archive = tmp_path / "run.tar.gz"
    unset = esr("export", path.name[:8], "--out", str(archive), "--sign", store=store, check=False)
    assert unset.returncode == 2 and "$ESR_ARCHIVE_KEY is not set" in unset.stderr and not archive.exists()
    (tmp_path / "short.key").write_bytes(b"x" * 8)
    short = esr("export", path.name[:8], "--out", str(archive), "--sign", store=store, check=False,
                ESR_ARCHIVE_KEY=str(tmp_path / "short.key"))
    assert short.returncode == 2 and "8 bytes; an archive key has at least 32" in short.stderr
    signed = esr("export", path.name[:8], "--out", str(archive), "--sign", store=store, ESR_ARCHIVE_KEY=str(key))
    assert "signed in run.tar.gz.sig" in signed.stderr and signing.signature_path(archive).is_file()
    imported = esr("import", "--require-signature", str(archive), store=tmp_path / "good", ESR_ARCHIVE_KEY=str(key))
    assert Path(imported.stdout.strip()).name == path.name

    forged = _reexported(tmp_path, path, _rewrite_metrics)
    refusals = [(lambda: None, "has no signature"),
                (lambda: shutil.copy(signing.signature_path(archive), signing.signature_path(forged)), "does not match its signature"),
                (lambda: signing.sign(forged, other_key.read_bytes()), "does not match its signature")]
    for make_signature, problem in refusals:
        make_signature()
        proc = esr("import", "--require-signature", str(forged), store=tmp_path / "bad", check=False, ESR_ARCHIVE_KEY=str(key))
        assert proc.returncode == 2 and problem in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
        assert not (tmp_path / "bad").exists()


# ---------------------------------------------------------------- fuzz, from a real export
ARCHIVE_FUZZ_CASES = 300
HOSTILE_PARTS = ["..", ".", "", "x", "n" * 300, "\x1b[2J", "\u202e", "checkpoints", "manifest.json", "runs", "ab", "0"]
NAME_TEXT = st.text(st.characters(blacklist_characters="\0"), max_size=8)  # a NUL cannot be written into a tar
JSON_VALUES = st.recursive(st.none() | st.booleans() | st.integers(-2, 2 ** 40) | st.text(max_size=12),
                           lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=6), c, max_size=3),
                           max_leaves=6)


class Export:
    """A real export's members as (TarInfo, data or None) pairs, and its key."""

    def __init__(self, archive: Path, key: str):
        with tarfile.open(archive) as tar:
            self.members = [(m, tar.extractfile(m).read() if m.isfile() else None) for m in tar.getmembers()]
        self.key = key

    def __repr__(self) -> str:  # what hypothesis prints of a failing case
        return f"Export({self.key[:12]})"


@pytest.fixture(scope="module")
def exported(smoke_run, tmp_path_factory) -> Export:
    store, path, _ = smoke_run
    archive = tmp_path_factory.mktemp("fuzz") / "run.tar.gz"
    esr("export", path.name[:8], "--out", str(archive), store=store)
    return Export(archive, path.name)


def _mutate(data, members: list) -> None:
    """One change of the kinds an attacker or a damaged copy makes, in place."""
    op = data.draw(st.sampled_from(["rename", "duplicate", "inflate", "nest", "retype", "drop", "manifest", "manifest, digests redone"]))
    event(op)
    i = data.draw(st.integers(0, len(members) - 1))
    info, body = members[i]
    info = copy.copy(info)
    parts = info.name.split("/")
    if op == "rename":
        parts[data.draw(st.integers(0, len(parts) - 1))] = data.draw(st.sampled_from(HOSTILE_PARTS) | NAME_TEXT)
        info.name = "/".join(parts)
    elif op == "nest":
        parts.insert(data.draw(st.integers(0, len(parts))), data.draw(st.sampled_from(HOSTILE_PARTS)))
        info.name = "/".join(parts)
    elif op == "duplicate":
        members.insert(data.draw(st.integers(0, len(members))), (copy.copy(info), body))
    elif op == "inflate" and body is not None:
        body = body * data.draw(st.integers(2, 64)) + data.draw(st.binary(max_size=64))
    elif op == "retype":
        info.type = data.draw(st.sampled_from([tarfile.SYMTYPE, tarfile.LNKTYPE, tarfile.FIFOTYPE, tarfile.CHRTYPE,
                                               tarfile.DIRTYPE, tarfile.REGTYPE]))
        info.linkname = data.draw(st.sampled_from(["/etc/passwd", "../../../x", "metrics.jsonl"]))
        # a folder or link made a regular file holds no bytes: an empty one
        body = (b"" if body is None else body) if info.type == tarfile.REGTYPE else None
    elif op == "drop":
        del members[i]
        return
    elif op.startswith("manifest"):
        i = next((j for j, (m, b) in enumerate(members) if m.name.endswith("/manifest.json") and b), None)
        try:
            manifest = json.loads(members[i][1]) if i is not None else None
        except ValueError:
            manifest = None
        if not isinstance(manifest, dict):
            return  # an earlier change took it away
        info, body = copy.copy(members[i][0]), members[i][1]
        where = data.draw(st.sampled_from([("kind",), ("key",), ("files",), ("files", "metrics.jsonl"), ("key_components",),
                                           ("key_components", "budget"), ("key_components", "spec", "train", "epochs"),
                                           ("name",), ("summary",)]))
        node = manifest
        for step in where[:-1]:
            if not isinstance(node.get(step), dict):
                node[step] = {}
            node = node[step]
        node[where[-1]] = data.draw(JSON_VALUES)
        if op.endswith("redone"):  # as a forger would: the files' digests made to match again
            by_rel = {m.name.split("/", 3)[3]: b for m, b in members if m.isfile() and m.name.count("/") >= 3}
            manifest["files"] = {rel: digest_bytes(b) for rel, b in by_rel.items() if rel != "manifest.json"}
        body = json.dumps(manifest).encode()
    members[i] = (info, body)


def _write(path: Path, members: list) -> None:
    with tarfile.open(path, "w:gz", compresslevel=1) as tar:
        for info, body in members:
            if body is None:
                tar.addfile(info)
            else:
                info.size = len(body)
                tar.addfile(info, io.BytesIO(body))


@pytest.mark.slow
@settings(max_examples=ARCHIVE_FUZZ_CASES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_fuzzed_archives_are_imported_whole_and_intact_or_refused_in_one_line_leaving_nothing(exported, data):
    """Cases made from a real export: members renamed, duplicated, inflated, nested, retyped or
    dropped, manifest fields replaced (with and without the digests made to match again). Each
    is the artifact exactly as exported, or one line and a store as it was."""
    members, key = list(exported.members), exported.key
    for _ in range(data.draw(st.integers(1, 3))):
        _mutate(data, members)
    with tempfile.TemporaryDirectory() as tmp:
        archive, store = Path(tmp) / "case.tar.gz", Store(Path(tmp) / "store")
        _write(archive, members)
        try:
            moved = import_archive(store, archive)
        except StoreError as e:
            event("refused")
            assert len(str(e).splitlines()) == 1
            assert not store.root.exists()
            return
        event("imported")
        assert moved.key == key and moved.status == "complete" and verify_artifact(store, moved.path) == []
        assert not [p for p in moved.path.parent.iterdir() if p.name.startswith(STAGING_PREFIX)]


def test_an_evaluation_kept_without_its_rollout_gets_it_back_from_the_full_archive(tmp_path):
    """A left-out part that is one file (an evaluation's rollout GIF): the full archive puts it
    back and says how many files it restored."""
    from esr_cli.storage.store import EVAL_ROLLOUT
    from esr_cli.storage.transfer import export

    here = Store(tmp_path / "here")
    components = {"kind": "evals", "run": "0" * 32, "episodes": 2}
    key = content_key(components)
    d = here.begin("evals", key, {"name": "ev", "key": key, "key_components": components})
    (d / "summary.json").write_text('{"return": {"mean": 1.0}}')
    (d / EVAL_ROLLOUT).write_bytes(b"GIF89a" + bytes(100))
    here.commit("evals", key, {"kind": "evals", "name": "ev", "key": key, "key_components": components})
    slim, full = tmp_path / "slim.tar.gz", tmp_path / "full.tar.gz"
    export(here, key, slim, without_checkpoint=True)
    export(here, key, full)
    there = Store(tmp_path / "there")
    copy = import_archive(there, slim).path
    assert not (copy / EVAL_ROLLOUT).exists() and verify_artifact(there, copy) == []
    moved = import_archive(there, full)
    assert (moved.restored, moved.files) == ((EVAL_ROLLOUT,), 1)
    assert (copy / EVAL_ROLLOUT).read_bytes() == (here.lookup("evals", key) / EVAL_ROLLOUT).read_bytes()
    assert verify_artifact(there, copy) == [] and import_archive(there, full).files == 0
