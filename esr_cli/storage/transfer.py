"""Moving artifacts between stores as one file: `esr export` and `esr import` (docs/store.md).

An archive is a gzipped tar of one artifact's directory, named as the store names it
(`<kind>/<key[:2]>/<key>` for a committed artifact, `<key>.partial` for an unfinished run), so
`tar -xzf ARCHIVE -C STORE` would also put it back. Long runs outlive the machine that started
them this way: an unfinished run travels with its newest verified checkpoint and continues
wherever it is imported (from a checkout of the commit its pending.json names).

Importing treats the archive as untrusted: esr_cli/common/tar_reader.py reads it, bounding its size,
members, names and headers on the raw stream before anything is unpacked; members must stay
inside that one directory and be plain files or folders, a committed artifact's manifest (an
unfinished run's pending.json) must name it (its kind, and a key that its listed key components
digest to), a run's spec.yaml must be the spec of those components, a manifest must match every
file, and the artifact appears in the store by one rename, or not at all (a refused import also
removes the folders it made; a killed one's staging folder is removed by the next command).
"""

from __future__ import annotations

import os
import re
import shutil
import tarfile
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO, Iterator

from esr_cli.common import bounded_files, faults, tar_reader, yamlio
from esr_cli.common.printing import printable
from esr_cli.common.jsonl import read_jsonl
from esr_cli.storage.checkpoint_files import CHECKPOINT_DIR, epochs_problem, state_epochs_problem, verified_steps, verify_artifact
from esr_cli.storage.finals import epoch_rows, run_length
from esr_cli.storage.labels import labels_problem
from esr_cli.storage.store import KINDS, LEFT_OUT, MANIFEST, RUN_KIND, Store, StoreError, components_problem, file_problem, fsync_dir, kept_without, load_manifest, parse_dirname, read_pending, shown_name

KEY_RE = re.compile(r"[0-9a-f]{32}")
SNAPSHOT_TRIES = 5


@dataclass(frozen=True)
class Moved:
    kind: str
    key: str
    status: str  # complete | partial
    files: int
    path: Path  # the archive written (export) or the artifact's directory (import)
    local_epoch: int | None = None  # import over a local unfinished run: that run's checkpoint epoch
    record: bool = False  # import: an unfinished run without an intact checkpoint (--without-checkpoint)
    restored: tuple[str, ...] = ()  # import: the parts a local copy was kept without, put back from the archive

    @property
    def replaced_partial(self) -> bool:
        """import: the archive took the place of a local unfinished run (kept when files == 0)."""
        return self.files > 0 and self.local_epoch is not None


# ---------------------------------------------------------------- export
def export(store: Store, ref: str, out: Path | None = None, without_checkpoint: bool = False) -> Moved:
    """Archive the artifact `ref` (key, unique key prefix or path; committed, or an unfinished
    run) into `out` (default: ./<key[:8]>.tar.gz). A running run may keep writing meanwhile.
    without_checkpoint: a finished run as metrics, spec, manifest and digests (it verifies,
    reports and plots, but cannot be evaluated or extended); an unfinished one as a record of its
    logged epochs (`esr import --without-checkpoint`); an exact check as its summary and manifest
    (tables read it; the estimator check needs its arrays); an evaluation without its rollout GIF
    (tables read its summary). Kinds: LEFT_OUT."""
    kind, key, src, status = _find(store, ref)
    if without_checkpoint and kind not in LEFT_OUT:
        raise StoreError(f"{kind} {key[:12]} is kept whole: only a run's checkpoint, an exact check's arrays and an evaluation's rollout GIF are left out")
    out = Path(out) if out is not None else Path(f"{key[:8]}.tar.gz")
    if out.is_dir():
        raise StoreError(f"{out} is a directory: give the archive's file name")
    if out.exists() and not out.is_file():  # a device or pipe would be renamed over, not written to
        raise StoreError(f"{out} exists and is not a regular file: give the archive's file name")
    if not out.parent.is_dir():
        raise StoreError(f"no directory {out.parent} to write {out.name} into")
    arcroot = PurePosixPath(kind, key[:2], src.name)
    # Staged beside the archive, never in the store: exporting only reads the store, so a store
    # the user cannot write to (another's, a read-only mount) exports all the same.
    with tempfile.TemporaryDirectory(prefix=".export-", dir=out.parent) as tmp:
        stage = Path(tmp) / arcroot  # laid out as in a store: verify checks the kind folder
        if status == "complete":
            copy_plain_tree(src, stage, ignore=_leaving_out(src, LEFT_OUT[kind]) if without_checkpoint else None)
            problems = verify_artifact(store, stage)
            if problems:
                raise StoreError(f"{kind} {key[:12]} fails its manifest ({problems[0]}); `{store.invocation()} verify {key[:12]}` lists every problem")
        elif without_checkpoint:
            copy_plain_tree(src, stage, ignore=_record_only(src))
        else:
            snapshot_partial(src, stage)
        files = sorted(p for p in stage.rglob("*") if p.is_file())
        part = out.with_name(f".{out.name}.part")
        try:
            with tarfile.open(part, "w:gz") as tar:
                for f in files:
                    tar.add(f, arcname=str(arcroot / f.relative_to(stage).as_posix()), recursive=False)
            part.replace(out)
        except BaseException:
            part.unlink(missing_ok=True)
            raise
    return Moved(kind, key, status, len(files), out)


def _find(store: Store, ref: str) -> tuple[str, str, Path, str]:
    """(kind, key, directory, status) of a committed artifact or an unfinished run."""
    e = store.find(ref, include_partial=True)
    if e.kind not in KINDS or not KEY_RE.fullmatch(e.key):
        raise StoreError(f"{ref} is not an artifact's directory in a store (<kind>/<kk>/<key>)")
    if e.status == "partial" and e.kind != RUN_KIND:
        raise StoreError(f"{e.kind} {e.key[:12]} is unfinished, and only a run resumes: finish it or remove {e.path}")
    return e.kind, e.key, e.path, e.status


def snapshot_partial(src: Path, stage: Path) -> None:
    """Copy an unfinished run with only its newest verified checkpoint. The run may be saving a
    newer one meanwhile (and deleting the oldest), so a copy that changed under it is retried."""
    for _ in range(SNAPSHOT_TRIES):
        _remove_copy(stage)
        steps = verified_steps(src)
        if not steps:
            raise StoreError(f"{src} has no verified checkpoint yet: nothing that could resume")
        step = steps[0]
        try:
            copy_plain_tree(src, stage, ignore=_keep_checkpoint(src / CHECKPOINT_DIR, step))
        except FileNotFoundError:
            continue  # a checkpoint was removed while it was copied
        if verified_steps(stage) == [step]:
            return
    raise StoreError(f"{src} kept changing while it was copied ({SNAPSHOT_TRIES} tries); try again")


def copy_plain_tree(src: Path, dst: Path, ignore=None) -> None:
    """Copy the folder `src` to `dst` (new), as shutil.copytree with `ignore` would, where an
    artifact holds folders and regular files only: a link, a FIFO or a device inside it is refused
    by name (StoreError), never followed or read, and each file is copied to the size it had when
    listed (a file that grows meanwhile cannot fill the disk). Before a byte is written, those
    sizes together must fit the free space of `dst`'s disk. FileNotFoundError where a file goes
    away meanwhile (a run deleting an old checkpoint)."""
    plan: list[tuple[Path, int | None]] = []  # (relative path, its size; None for a folder)
    total, todo = 0, [Path()]
    while todo:
        rel = todo.pop()
        plan.append((rel, None))
        with os.scandir(src / rel) as entries:
            listed = {e.name: e for e in entries}
        skipped = set(ignore(str(src / rel), list(listed)) if ignore else ())
        for name in sorted(set(listed) - skipped):
            entry = listed[name]
            if entry.is_dir(follow_symlinks=False):
                todo.append(rel / name)
            elif entry.is_file(follow_symlinks=False):
                size = entry.stat(follow_symlinks=False).st_size
                plan.append((rel / name, size))
                total += size
            else:
                what = "a link" if entry.is_symlink() else "a FIFO, a socket or a device"
                raise StoreError(f"{printable(str(src / rel / name))} is {what}: an artifact holds plain files and folders "
                                 f"only; `esr verify` checks it, remove what is not the artifact's")
    free = shutil.disk_usage(_existing_parent(dst)).free
    if total > free:
        raise StoreError(f"not enough free space: {printable(str(src))} holds {total:,} bytes but the disk of "
                         f"{printable(str(_existing_parent(dst)))} has {free:,} free")
    for rel, size in plan:
        if size is None:
            (dst / rel).mkdir(parents=True, exist_ok=rel != Path())
        else:
            _copy_regular(src / rel, dst / rel, size)


def _existing_parent(path: Path) -> Path:
    while not path.exists():
        path = path.parent
    return path


def _copy_regular(src: Path, dst: Path, size: int) -> None:
    """Copy at most `size` bytes of one regular file, without following a link or waiting on a FIFO."""
    try:
        f = bounded_files.open_regular(src)
    except bounded_files.UnreadableInput as e:  # replaced by a link or a FIFO since it was listed
        raise StoreError(f"{printable(str(src))} is {e}: an artifact holds plain files only") from None
    with f, open(dst, "xb") as out:
        left = size
        while left > 0 and (block := f.read(min(left, 1 << 20))):
            out.write(block)
            left -= len(block)


def _remove_copy(tree: Path) -> None:
    """Remove a copy made by an earlier try, whose folders are read-only where the store's are."""
    if not tree.exists():
        return

    def writable_then_again(func, path, _):
        os.chmod(os.path.dirname(path), 0o700)
        func(path)

    shutil.rmtree(tree, onerror=writable_then_again)


def _leaving_out(src: Path, parts: tuple[str, ...]):
    def ignore(directory: str, names: list[str]) -> list[str]:
        return [n for n in names if n in parts] if Path(directory) == src else []

    return ignore


RECORD_FILES = ("pending.json", "spec.yaml", "metrics.jsonl")  # what a record of an unfinished run holds


def _record_only(src: Path):
    def ignore(directory: str, names: list[str]) -> list[str]:
        return [n for n in names if n not in RECORD_FILES] if Path(directory) == src else names

    return ignore


def _keep_checkpoint(ckpt: Path, step: int):
    def ignore(directory: str, names: list[str]) -> list[str]:
        if Path(directory) == ckpt:
            return [n for n in names if n != str(step)]
        return [n for n in names if n.startswith(".") or n.endswith(".tmp")]  # a write in progress

    return ignore


# ---------------------------------------------------------------- import
def import_archive(store: Store, archive: Path, without_checkpoint: bool = False) -> Moved:
    """Put the artifact in `archive` into the store: atomically, after checking every member.

    without_checkpoint: also accept an unfinished run that has no intact checkpoint (a record of
    its logged epochs, e.g. what came back from a machine that could not send its checkpoint),
    so that reports and figures read it; training it again starts from epoch 0."""
    archive = Path(archive)
    made = [] if store.root.is_dir() else [store.root]  # folders to remove again if it is refused
    try:
        with _open(archive) as f:
            return _import(store, f, archive, made, without_checkpoint)
    except BaseException:
        for d in reversed(made):  # innermost first; rmdir leaves a folder another process filled
            try:
                d.rmdir()
            except OSError:
                pass
        raise


@contextmanager
def _reading(archive: Path):
    """What tar_reader refuses, and a read or write that fails, as one line naming the archive."""
    try:
        yield
    except tar_reader.ArchiveError as e:
        raise StoreError(f"{archive}: {e}") from None
    except OSError as e:
        raise StoreError(f"{archive} could not be read and unpacked to the end ({_first_line(e)})") from None


@contextmanager
def _open(archive: Path) -> Iterator[BinaryIO]:
    with _reading(archive):
        f = tar_reader.open_archive(archive)
    with f:
        yield f


def check_archive(archive: Path) -> None:
    """Raise StoreError unless `archive` reads to the end as one artifact's folder: what can be
    known without unpacking it (`esr import` of several archives checks all before adding any)."""
    with _open(Path(archive)) as f:
        _checked_members(f, Path(archive))


def _import(store: Store, f: BinaryIO, archive: Path, made: list[Path], without_checkpoint: bool) -> Moved:
    store.ensure_writable()
    kind, dirname, members = _checked_members(f, archive)
    key, status = parse_dirname(dirname)
    final, partial = store.final_path(kind, key), store.partial_path(kind, key)
    if _nothing_to_add(store, kind, key, status):  # already here: like a cache hit, nothing to do
        return Moved(kind, key, "complete", 0, final)
    unpacked = sum(m.size for m in members)
    free = shutil.disk_usage(store.root).free
    if unpacked > free:  # the headers' sizes, known before a byte is written
        raise StoreError(f"{archive} unpacks to {unpacked / (1 << 20):,.1f} MiB but the store's disk has "
                         f"{free / (1 << 20):,.1f} MiB free")
    made += [d for d in (final.parent.parent, final.parent) if not d.exists()]
    final.parent.mkdir(parents=True, exist_ok=True)
    with store.staging(final.parent) as tmp:
        with _reading(archive):
            tar_reader.unpack(f, Path(tmp), members)
        faults.reached("after_unpack")
        stage = Path(tmp) / kind / key[:2] / dirname
        record, stage_epoch = _check_contents(store, stage, kind, key, status, archive, without_checkpoint)
        with store.lock(kind, key, wait=False):
            if _nothing_to_add(store, kind, key, status):
                return Moved(kind, key, "complete", 0, final)
            if store.lookup(kind, key):  # kept without parts the archive holds
                return _restore_left_out(store, final, stage, kind, key, archive)
            # One key is one computation, so of two copies the one further along supersedes the
            # other (the local run is not training now: this process holds its lock).
            local_epoch = _checkpoint_epoch(partial) if partial.exists() else None
            if status != "complete" and local_epoch is not None:
                # How far the archive's run got decides whether the local one stays: its folder's
                # number is only a name (folder, digests and metrics can be edited to agree), so
                # the epoch its training state holds must be that number too.
                problem = stage_epoch and state_epochs_problem(stage, stage_epoch, run_length(read_pending(stage) or {}))
                if problem:
                    raise StoreError(f"{archive}: unfinished run {key[:12]}: {problem}; nothing imported (this store's "
                                     f"unfinished run, at epoch {local_epoch}, is kept)")
                if local_epoch >= stage_epoch:
                    return Moved(kind, key, status, 0, partial, local_epoch=local_epoch)
                # Moved aside into the staging folder (removed with it) only now, just before the
                # archive's copy takes its place; a kill in between leaves it to be put back
                # (Store.remove_abandoned_imports).
                partial.rename(Path(tmp) / partial.name)
            target = final if status == "complete" else partial
            stage.rename(target)
            fsync_dir(target.parent)
            # A finished artifact is in place before the unfinished one goes: a kill between
            # leaves both, never neither.
            if status == "complete" and partial.exists():
                shutil.rmtree(partial)
    files = sum(1 for p in target.rglob("*") if p.is_file())
    return Moved(kind, key, status, files, target, local_epoch=local_epoch, record=record)


def _nothing_to_add(store: Store, kind: str, key: str, status: str) -> bool:
    """Whether the store's committed copy of `key` leaves nothing for an archive of it to add:
    it is whole, or the archive is an unfinished run's (a committed copy supersedes it)."""
    local = store.lookup(kind, key)
    return local is not None and (status != "complete" or not kept_without(kind, local))


def _restore_left_out(store: Store, final: Path, stage: Path, kind: str, key: str, archive: Path) -> Moved:
    """Put back into the committed copy `final` the parts it was kept without (`esr export
    --without-checkpoint`) from the archive's copy `stage` of the same key. Every file of those
    parts is checked against `final`'s own manifest before anything moves (the archive's
    manifest could list other files under the same key), so what goes in is what the manifest
    lists. The first part (a run's checkpoints, by which a copy is known as kept without) goes
    in last: a kill between leaves checked files in place and the copy still known as kept
    without, and importing the archive again finishes the job."""
    missing = kept_without(kind, final)
    present = tuple(part for part in missing if (stage / part).exists())
    if kept_without(kind, stage) or not present:
        return Moved(kind, key, "complete", 0, final)  # the archive lacks them too
    want = _listed_under(final, present)
    problem = _parts_problem(stage, present, want)
    if problem:
        raise StoreError(f"{archive}: its {' and '.join(present)} are not the files the store's copy of {kind} "
                         f"{key[:12]} lists ({problem}); nothing imported")
    moved = []
    try:
        for part in reversed(present):
            (stage / part).rename(final / part)
            moved.append(part)
        fsync_dir(final)
    except BaseException:  # Ctrl-C or a failed rename: the copy is left as it was
        for part in moved:
            (final / part).rename(stage / part)
        raise
    return Moved(kind, key, "complete", len(want), final, restored=present)  # checked: exactly the listed files


def _listed_under(final: Path, parts: tuple[str, ...]) -> dict[str, str]:
    """{file: digest} of what `final`'s manifest lists under `parts` (a folder or one file each)."""
    return {rel: digest for rel, digest in load_manifest(final)["files"].items()
            if any(rel == part or rel.startswith(f"{part}/") for part in parts)}


def _parts_problem(stage: Path, parts: tuple[str, ...], want: dict[str, str]) -> str | None:
    """Why the files under `parts` of `stage` are not exactly `want`, with their digests; None
    where they are."""
    have = {p.relative_to(stage).as_posix() for part in parts
            for p in ([stage / part] if (stage / part).is_file() else (stage / part).rglob("*")) if not p.is_dir()}
    extra = sorted(have - set(want))
    if extra:
        return f"unexpected file {shown_name(extra[0])}"
    return next((p for rel, digest in sorted(want.items()) if (p := file_problem(stage, rel, digest))), None)


def _checkpoint_epoch(run_dir: Path) -> int:
    """The epoch of an unfinished run's newest intact checkpoint; 0 without one."""
    return next(iter(verified_steps(run_dir)), 0)


def _first_line(e: Exception) -> str:
    return (str(e).splitlines() or [type(e).__name__])[0][:200]


def _checked_members(f: BinaryIO, archive: Path) -> tuple[str, str, list[tar_reader.Member]]:
    """The archive's members (tar_reader bounds their number, sizes and names), all plain files
    or folders inside one `<kind>/<kk>/<key>[.partial]`."""
    members, top = [], None
    files: set[tuple[str, ...]] = set()
    folders: set[tuple[str, ...]] = set()  # inside the artifact: named, or above a member
    with _reading(archive):
        for m in tar_reader.members(f):
            path = PurePosixPath(m.name)
            if path.is_absolute() or ".." in path.parts:
                raise StoreError(f"{archive}: member {m.name!r} points outside the artifact")
            parts = [p for p in path.parts if p != "."]
            if len(parts) < 3 or (len(parts) == 3 and not m.is_dir):
                if m.is_dir and len(parts) < 3:
                    members.append(m)
                    continue  # the folders above the artifact (kind/, kind/kk/)
                raise StoreError(f"{archive}: member {m.name!r} is not inside an artifact directory <kind>/<kk>/<key>")
            head = tuple(parts[:3])
            if top is None:
                top = head
            elif head != top:
                raise StoreError(f"{archive} holds more than one artifact ({'/'.join(top)!r} and {'/'.join(head)!r}): export one per archive")
            here = tuple(parts)
            if here in files or any(here[:i] in files for i in range(4, len(here))):
                raise StoreError(f"{archive}: member {m.name!r} repeats a file or lies inside one: not an esr artifact")
            if not m.is_dir and here in folders:
                raise StoreError(f"{archive}: member {m.name!r} is a file where a folder of the archive is: not an esr artifact")
            folders.update(here[:i] for i in range(4, len(here)))
            if m.is_dir:
                folders.add(here)
            else:
                files.add(here)
            members.append(m)
    if top is None:
        raise StoreError(f"{archive} holds no artifact")
    kind, shard, dirname = top
    key, status = parse_dirname(dirname)
    if kind not in KINDS or not KEY_RE.fullmatch(key) or shard != key[:2]:
        raise StoreError(f"{archive}: {'/'.join(top)!r} is not an esr artifact directory (<kind>/<key[:2]>/<key>, kind one of {', '.join(KINDS)})")
    if status == "partial" and kind != RUN_KIND:
        raise StoreError(f"{archive}: an unfinished {kind} artifact cannot resume; only unfinished runs can be imported")
    return kind, dirname, members


def _check_contents(store: Store, stage: Path, kind: str, key: str, status: str, archive: Path,
                    without_checkpoint: bool = False) -> tuple[bool, int]:
    """Refuse what cannot be imported; -> (whether it is a record (no intact checkpoint), the epoch
    of its newest intact checkpoint, 0 without one or for a finished artifact)."""
    if not stage.is_dir():
        raise StoreError(f"{archive} holds no files for {kind} {key[:12]}")
    if status == "complete":
        if not (stage / MANIFEST).is_file():
            raise StoreError(f"{archive}: {kind} {key[:12]} has no {MANIFEST}, so it is not a finished artifact "
                             "(an unfinished run's directory ends in .partial); nothing imported")
        problems = verify_artifact(store, stage)  # what `esr verify` checks: the manifest names it, every digest
        if problems:
            more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
            raise StoreError(f"{archive}: {kind}/{key[:2]}/{key}: {problems[0]}{more}; nothing imported")
        problem = spec_problem(stage, load_manifest(stage)) if kind == RUN_KIND else None
        if problem:
            raise StoreError(f"{archive}: {kind}/{key[:2]}/{key}: {problem}; nothing imported")
        return False, 0
    if not (stage / "pending.json").is_file():
        raise StoreError(f"{archive}: unfinished run {key[:12]} has no pending.json; nothing imported")
    pending = read_pending(stage)
    if pending is None:
        raise StoreError(f"{archive}: unfinished run {key[:12]}: its pending.json is not a JSON object of at most 1 MiB; nothing imported")
    if pending.get("key") != key:
        raise StoreError(f"{archive}: unfinished run {key[:12]}: its pending.json names key "
                         f"{str(pending.get('key'))[:40]!r}, not the directory's; nothing imported")
    problem = components_problem(pending, "pending.json") or labels_problem(pending, "pending.json") or spec_problem(stage, pending)
    if problem:
        raise StoreError(f"{archive}: unfinished run {key[:12]}: {problem}; nothing imported")
    steps = verified_steps(stage)  # newest first
    if steps:
        # Cheap, without JAX: the folder's number against the metrics and the run's length (a
        # resume also checks the epoch the state holds).
        problem = epochs_problem(stage, steps[0], run_length(pending))
        if problem:
            raise StoreError(f"{archive}: unfinished run {key[:12]}: {problem}; nothing imported")
        return False, steps[0]
    if not without_checkpoint:
        raise StoreError(f"{archive}: unfinished run {key[:12]} has no checkpoint matching its recorded digests; "
                         "nothing imported (`esr import --without-checkpoint` keeps its logged epochs for reports; "
                         "training it again would start from epoch 0)")
    logged = read_jsonl(stage / "metrics.jsonl")
    if not logged:
        raise StoreError(f"{archive}: unfinished run {key[:12]} has neither an intact checkpoint nor a logged epoch; nothing imported")
    # A record is read only for its rows: each must be an epoch's, as training writes them.
    sound = len(epoch_rows(logged))
    if sound < len(logged):
        raise StoreError(f"{archive}: unfinished run {key[:12]}: line {sound + 1} of metrics.jsonl is not an epoch's "
                         "metrics (an integer 'epoch' after the line before's, and each metric a list of numbers "
                         "over the seeds); nothing imported")
    return True, 0


TRAINING_SECTIONS = ("env", "human", "method", "network", "learner", "train")  # spec.Spec.training_part's


def spec_problem(run_dir: Path, record: dict) -> str | None:
    """Why a run's spec.yaml is not the spec its key components hold (`record`: its manifest or
    pending.json, whose components digest to its key), or None (also where it has none: then
    nothing reads one). Evaluating, extending and reporting a run read that file, so one swapped
    under a genuine key would pass another spec's numbers off as this key's. Compared as written,
    as `training_part` keys it, not validated again: a run made by older code holds the fields
    that code had."""
    if not (run_dir / "spec.yaml").exists():
        return None
    spec, problem = read_spec_yaml(run_dir)
    return problem or spec_mismatch(spec, record)


MAX_SPEC_YAML_BYTES = 64 << 10  # a run's spec.yaml, written by esr, is about 3 KiB


def read_spec_yaml(run_dir: Path) -> tuple[object, str | None]:
    """(a run's spec.yaml as read, None), or (None, why it cannot be read)."""
    try:
        return yamlio.read(run_dir / "spec.yaml", MAX_SPEC_YAML_BYTES, follow_links=False, what="a run's spec.yaml"), None
    except yamlio.YamlInputError as e:
        return None, f"its spec.yaml cannot be read ({e})"


def spec_mismatch(spec, record: dict) -> str | None:
    """Why `spec`, a run's spec.yaml as read, is not the spec its key components hold, or None
    (`spec_problem` for a spec already read)."""
    if not isinstance(spec, dict) or not isinstance(spec.get("human"), dict):
        return "its spec.yaml is not a spec"
    trained = {section: spec.get(section) for section in TRAINING_SECTIONS}
    trained["human"] = {k: v for k, v in spec["human"].items() if k != "preset"}  # keyed by its values
    components = record.get("key_components")
    if not isinstance(components, dict):
        return "its record holds no key components to check its spec.yaml against"
    if trained != components.get("spec") or spec.get("budget") != components.get("budget"):
        return "its spec.yaml is not the spec its key was computed from (the key components' spec and budget)"
    if "name" in record and record["name"] != spec.get("name"):  # the name is not keyed: both files say it
        return "its spec.yaml names another spec than its record does"
    return None
