"""The content-addressed artifact store (docs/store.md).

Layout: <root>/<kind>/<key[:2]>/<key>/ for a committed artifact, <key>.partial/ beside it
while it is being made, <key>.lock for the lock, and an import's staging folder
(.import-<pid>-<random>@<host>/) while `esr import` unpacks into it. Kinds: `KINDS` below.

- A key is blake2b over the canonical JSON of its components (validated spec, budget,
  dependency keys, code hash, toolchain); the manifest lists each component, so `esr show`
  can say why something would run again.
- Writers hold an exclusive `flock` on the lock file: the kernel releases it when the process
  dies, so a lock is never stale.
- Committing writes manifest.json (with a digest of every file) into the partial directory,
  then renames the directory into place: one atomic step. A committed artifact is never
  modified afterwards.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import re
import secrets
import shlex
import shutil
import stat
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Callable, Iterator

from esr_cli.common import faults
from esr_cli.common.failures import Failure
from esr_cli.common.jsonl import JsonInputError, read_json
from esr_cli.common.printing import printable

MANIFEST = "manifest.json"
PENDING = "pending.json"  # an unfinished artifact's record: what it is and who has worked on it
MAX_PENDING_BYTES = 1 << 20
MAX_MANIFEST_BYTES = 16 << 20  # a run's manifest is a few KiB; a figure's lists its inputs
# The artifact kinds, each a top-level folder of the store; every module names them from here.
RUN_KIND, EVAL_KIND, EXACT_KIND, FIGURE_KIND, DATA_KIND, HUMAN_KIND = "runs", "evals", "exact", "figures", "humandata", "humans"
CHECKPOINT_FOLDER = "checkpoints"  # a run's checkpoints, one folder per epoch (checkpoint_files.py)
EVENTS_FOLDER = "tensorboard"  # a run's TensorBoard event files (runner/event_log.py)
PLAY_KIND = "play"  # an episode a person played with a robot (esr play)
DIAGNOSIS_KIND = "diagnoses"  # why a finished run's robot helps or not, one seed (esr diagnose)
CALIBRATION_KIND = "calibrations"  # an Overcooked human with each partner, no robot trained (esr human calibrate)
KINDS = (RUN_KIND, EVAL_KIND, EXACT_KIND, FIGURE_KIND, DATA_KIND, HUMAN_KIND, PLAY_KIND, DIAGNOSIS_KIND, CALIBRATION_KIND)


class StoreError(Failure):
    """A problem with the store or an artifact; `str()` is a one-line explanation."""

    exit_code = 2


class LockBusy(StoreError):
    """Another process holds an artifact's lock (Store.lock with wait=False)."""


def digest_bytes(data: bytes, size: int = 16) -> str:
    return hashlib.blake2b(data, digest_size=size).hexdigest()


def digest_file(path: Path) -> str:
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def content_key(components: dict) -> str:
    return digest_bytes(json.dumps(components, sort_keys=True, separators=(",", ":")).encode())


def atomic_write_bytes(path: Path, data: bytes, mode: int | None = None) -> None:
    """Write via a temporary file, fsync, rename: readers see the old file or the new one. The
    temporary file is made new under an unguessable name, never opened through a link planted
    where it would be; `path` itself, a link or not, is replaced. `mode`: its permission bits
    (default: 0o666 less the umask, as any new file)."""
    path = Path(path)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
    while True:
        # not named after `path`: a name near the file system's limit would be too long with it
        tmp = path.with_name(f".esr-{secrets.token_hex(8)}.tmp")
        try:
            fd = os.open(tmp, flags, 0o666 if mode is None else 0o600)  # never readable beyond `mode` meanwhile
            break
        except FileExistsError:
            continue
    try:
        with os.fdopen(fd, "wb") as f:
            if mode is not None:
                os.fchmod(f.fileno(), mode)
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a failed write (full disk, `path` a directory) leaves nothing behind
        raise


class NotAFile(Failure):
    """An output path that names something other than a regular file (a device, a pipe, a socket)."""

    exit_code = 2


def write_output_file(path: Path, data: bytes, mode: int | None = None) -> None:
    """Write a file a user named (a report, a table's page, an export), atomically. A link there
    is written through, to its target, as a shell's `>` would; an existing file keeps its
    permission bits (unless `mode` is given); a device, pipe or socket is refused (NotAFile),
    never replaced."""
    target = Path(os.path.realpath(path))
    try:
        st = os.stat(target)
    except FileNotFoundError:
        st = None
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise NotAFile(f"{path} exists and is not a regular file (a device, pipe or socket): name a file")
    atomic_write_bytes(target, data, mode if mode is not None or st is None else stat.S_IMODE(st.st_mode))


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


PARTIAL_SUFFIX = ".partial"  # an unfinished artifact's directory: <key>.partial


def parse_dirname(name: str) -> tuple[str, str]:
    """(key, status) of an artifact directory's name: `<key>` is committed, `<key>.partial` unfinished."""
    if name.endswith(PARTIAL_SUFFIX):
        return name[: -len(PARTIAL_SUFFIX)], "partial"
    return name, "complete"


@dataclass(frozen=True)
class Entry:
    kind: str
    key: str
    path: Path
    status: str  # complete | partial
    manifest: dict | None
    problem: str | None = None  # why a committed artifact's manifest could not be read (manifest None)


def nearest_existing(path: Path) -> Path:
    """`path` made absolute, or the nearest of its parents that exists: where a file or
    folder meant for `path` is really made (or refused)."""
    absolute = Path(path).absolute()
    return next(p for p in (absolute, *absolute.parents) if os.path.exists(p))


def probe_writable(path: Path) -> None:
    """Raise OSError unless a file can be made in the nearest existing folder of `path`: the
    only sure test (permissions, /proc, a read-only mount). Leaves nothing behind."""
    with tempfile.TemporaryFile(dir=nearest_existing(path)):
        pass


class Store:
    def __init__(self, root: str | Path):
        self.root = Path(root)
        # A file where the store (or a folder above it) should be would read as an empty store.
        here = nearest_existing(self.root)
        if here == self.root.absolute() and not here.is_dir():
            raise StoreError(f"store {self.root} is not a directory")
        if not here.is_dir():
            raise StoreError(f"store {self.root} is not writable: {here} is not a directory")
        # A file where a kind's folder belongs would hide that kind's artifacts and fail the first write.
        for kind in KINDS:
            if here == self.root.absolute() and (self.root / kind).exists() and not (self.root / kind).is_dir():
                raise StoreError(f"store {self.root} is damaged: {self.root / kind} is a file where its {kind} "
                                 "folder belongs (move it away)")

    # ---------------------------------------------------------------- paths
    def final_path(self, kind: str, key: str) -> Path:
        return self.root / kind / key[:2] / key

    def partial_path(self, kind: str, key: str) -> Path:
        return self.root / kind / key[:2] / f"{key}{PARTIAL_SUFFIX}"

    def lock_path(self, kind: str, key: str) -> Path:
        return self.root / kind / key[:2] / f"{key}.lock"

    def invocation(self, always_named: bool = False) -> str:
        """`esr`, with `--store PATH` unless this is the store esr opens by default (or always,
        for a record read elsewhere): a command printed as a hint must reach the store the user named."""
        default = Path(os.environ.get("ESR_STORE") or "artifacts")
        if not always_named and self.root.absolute() == default.absolute():
            return "esr"
        return f"esr --store {shlex.quote(str(self.root))}"

    def ensure_writable(self) -> None:
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            probe = self.root / f".write-probe-{os.getpid()}"
            probe.write_text("")
            probe.unlink()
        except OSError as e:
            raise StoreError(f"store {self.root} is not writable: {e.strerror or e}") from None

    # ---------------------------------------------------------------- queries
    def lookup(self, kind: str, key: str) -> Path | None:
        path = self.final_path(kind, key)
        return path if (path / MANIFEST).is_file() else None

    def read_manifest(self, path: Path) -> dict:
        """A committed artifact's manifest: a JSON object with at least MANIFEST_FIELDS."""
        try:
            return load_manifest(Path(path))
        except StoreError as e:
            raise StoreError(f"{path}: {e}") from None

    def entries(self, kinds: tuple[str, ...] = KINDS) -> Iterator[Entry]:
        """Every artifact of `kinds` (default: all), committed or partial, in key order."""
        for kind in kinds:
            base = self.root / kind
            if not base.is_dir():
                continue
            for shard in sorted(base.iterdir()):
                if not shard.is_dir():
                    continue
                for d in sorted(shard.iterdir()):
                    if not d.is_dir():
                        continue
                    key, status = parse_dirname(d.name)
                    if status == "partial":
                        yield Entry(kind, key, d, "partial", read_pending(d))
                    elif (d / MANIFEST).is_file():
                        yield self._complete_entry(kind, key, d)

    def _complete_entry(self, kind: str, key: str, path: Path) -> Entry:
        """A committed artifact, listed even where its manifest is damaged (manifest None)."""
        try:
            return Entry(kind, key, path, "complete", self.read_manifest(path))
        except StoreError as e:
            return Entry(kind, key, path, "complete", None, problem=str(e))

    def resolve(self, ref: str) -> Path:
        """A committed artifact from a key, a unique key prefix (>= 4 chars) or a path."""
        return self.find(ref).path

    def find(self, ref: str, include_partial: bool = False) -> Entry:
        """The artifact a key, a unique key prefix (>= 4 hex digits) or a directory names; with
        include_partial, an unfinished one too (where a key is both, the committed one)."""
        if not ref.strip():
            raise StoreError("an empty key: give an artifact's key (at least 4 hex digits), a unique prefix or its directory")
        p = Path(ref)
        key, status = parse_dirname(p.name)
        if (p / MANIFEST).is_file() or (include_partial and status == "partial" and p.is_dir()):
            return Entry(p.parent.parent.name, key, p, status, read_pending(p) if status == "partial" else None)
        if status == "partial" and p.is_dir():
            raise StoreError(f"{p} is unfinished (no manifest yet): `esr ls` shows how far it got")
        inside = next((q for q in p.parents if (q / MANIFEST).is_file() or parse_dirname(q.name)[1] == "partial"), None)
        if p.is_file() and inside is not None:
            raise StoreError(f"{ref} is a file inside the artifact {inside}: give that directory or its key")
        if re.fullmatch(r"[0-9a-fA-F]{33,}", ref):
            raise StoreError(f"{ref[:40]!r} has {len(ref)} hex digits: a key has 32")
        ref = ref.lower() if re.fullmatch(r"[0-9a-fA-F]{4,32}", ref) else ref  # keys are written in lower case
        if not re.fullmatch(r"[0-9a-f]{4,32}", ref):
            spec = next((q for q in (p.with_name(p.name + ".yaml"), p.with_name(p.name + ".yml")) if q.is_file()), None)
            hint = f" (the spec file is {spec})" if spec else ""
            raise StoreError(f"no artifact {ref!r}: give a path to an artifact directory or a key (at least 4 hex digits)" + hint)
        hits = [e for e in self.entries() if e.key.startswith(ref) and (include_partial or e.status == "complete")]
        hits = [e for e in hits if e.status == "complete"] or hits
        if not hits:
            unfinished = [] if include_partial else [e for e in self.entries() if e.key.startswith(ref)]
            if unfinished:
                e = unfinished[0]
                raise StoreError(f"{e.kind} {e.key[:12]} in store {self.root} is unfinished (no manifest yet): "
                                 "`esr ls` shows how far it got")
            raise StoreError(f"no artifact with key {ref!r} in store {self.root}")
        if len(hits) > 1:
            raise StoreError(f"key prefix {ref!r} is ambiguous: {', '.join(f'{e.kind}/{e.key[:12]}' for e in hits)}")
        return hits[0]

    # ---------------------------------------------------------------- writing
    @contextmanager
    def lock(self, kind: str, key: str, on_wait: Callable[[str], None] | None = None, poll_s: float = 1.0,
             wait: bool = True):
        """Hold the artifact's exclusive lock; wait (calling on_wait once) while another holds it,
        or with wait=False raise LockBusy at once."""
        path = self.lock_path(kind, key)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = open_lock(path, create=True)
        try:
            told = False
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError as e:
                    if e.errno not in (errno.EAGAIN, errno.EACCES):
                        raise
                    if not wait:
                        raise LockBusy(f"{kind} {key[:12]} is being written by another process") from None
                    if on_wait and not told:
                        on_wait(lock_holder(fd))
                        told = True
                    time.sleep(poll_s)
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"pid {os.getpid()} on {os.uname().nodename}".encode(), 0)
            yield
        finally:
            os.close(fd)  # closing releases the flock

    def get_or_make(self, kind: str, key: str, make: Callable[[], Path], on_wait=None) -> tuple[Path, bool]:
        """The committed artifact `key`, or `make()` under its lock. -> (path, cache_hit).

        The lookup is repeated after the lock is taken: another writer may have finished it
        while this one waited.
        """
        hit = self.lookup(kind, key)
        if hit:
            return hit, True
        self.ensure_writable()
        with self.lock(kind, key, on_wait=on_wait):
            hit = self.lookup(kind, key)
            if hit:
                return hit, True
            return make(), False

    def begin(self, kind: str, key: str, pending: dict) -> Path:
        """The partial directory for `key` (kept if it exists: a resumed run)."""
        path = self.partial_path(kind, key)
        path.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path / PENDING, json.dumps(pending, indent=2, sort_keys=True))
        return path

    def commit(self, kind: str, key: str, manifest: dict) -> Path:
        """Digest every file, write the manifest, rename partial -> final (atomic)."""
        partial, final = self.partial_path(kind, key), self.final_path(kind, key)
        for stale in (partial / PENDING, partial / MANIFEST):  # MANIFEST: a commit cut short
            if stale.exists():
                stale.unlink()
        files = {}
        for f in sorted(partial.rglob("*")):
            if f.is_file():
                files[f.relative_to(partial).as_posix()] = digest_file(f)
        manifest = {**manifest, "files": files}
        atomic_write_text(partial / MANIFEST, json.dumps(manifest, indent=2, sort_keys=True))
        fsync_dir(partial)
        faults.reached("before_rename")
        if final.exists():  # a committed copy already exists (should not happen under the lock)
            shutil.rmtree(partial)
            return final
        os.rename(partial, final)
        fsync_dir(final.parent)
        return final

    def staging(self, parent: Path) -> tempfile.TemporaryDirectory:
        """A folder in `parent` (an artifact's shard) that an import unpacks into before one
        rename puts the artifact in place; removed on the way out. Its name says whose it is
        (STAGING_RE), so what a killed import leaves is found later (remove_abandoned_imports)."""
        return tempfile.TemporaryDirectory(prefix=f"{STAGING_PREFIX}{os.getpid()}-", suffix=f"@{_host()}", dir=parent)

    def remove_abandoned_imports(self) -> list[Path]:
        """Remove the staging folders of imports that were killed on this machine (their process
        is gone); -> those removed. A run the import had moved aside to take its place is put
        back first. A running import's folder, or another machine's, is left alone."""
        removed = []
        for shard in (s for kind in KINDS for s in _folders(self.root / kind)):
            for d in _folders(shard):
                owner = STAGING_RE.fullmatch(d.name)
                if not owner or owner["host"] != _host() or _alive(int(owner["pid"])):
                    continue
                try:
                    for aside in _folders(d):
                        if aside.name.endswith(PARTIAL_SUFFIX) and not (shard / aside.name).exists():
                            aside.rename(shard / aside.name)
                except OSError:
                    continue  # it cannot be put back: all is kept, for a person to look at
                shutil.rmtree(d, ignore_errors=True)
                removed += [d] if not d.exists() else []
        return removed

    # ---------------------------------------------------------------- checking
    def verify(self, path: Path) -> list[str]:
        """Check that the manifest names this artifact and re-hash every file against it; -> list
        of problems (empty: intact). checkpoint_files.verify_artifact adds a run's epoch check."""
        path = Path(path)
        try:
            manifest = load_manifest(path)
        except StoreError as e:
            return [str(e)]
        problems = []
        kind, folder = manifest["kind"], path.parent.parent.name
        if manifest["key"] != path.name:
            problems.append(f"{MANIFEST} names key {manifest['key'][:40]!r}, not the directory's {path.name}")
        key_problem = components_problem(manifest, MANIFEST)
        if key_problem:
            problems.append(key_problem)
        if kind not in KINDS:
            problems.append(f"{MANIFEST} names kind {kind[:40]!r}, not one of {', '.join(KINDS)}")
        elif folder in KINDS and kind != folder:  # a directory outside a store has no kind folder
            problems.append(f"{MANIFEST} names kind {kind!r}, but the artifact is under {folder}/")
        listed = manifest["files"]
        for part in kept_without(kind, path):  # kept without its networks or arrays, on purpose (`esr export --without-checkpoint`)
            listed = {rel: want for rel, want in listed.items() if rel != part and not rel.startswith(f"{part}/")}
        problems += [p for rel, want in sorted(listed.items()) if (p := file_problem(path, rel, want))]
        for f in sorted(Path(path).rglob("*")):
            rel = f.relative_to(path).as_posix()
            if f.is_file() and rel != MANIFEST and rel not in listed:
                problems.append(f"unexpected file {shown_name(rel)}")
        return problems


STAGING_PREFIX = ".import-"  # an import's staging folder: .import-<pid>-<random>@<host>
STAGING_RE = re.compile(re.escape(STAGING_PREFIX) + r"(?P<pid>[0-9]{1,10})-[a-z0-9_]+@(?P<host>[A-Za-z0-9._-]+)")


def open_lock(path: Path, create: bool = False) -> int:
    """A descriptor of the lock file `path` (to take the lock: created, open for writing; else
    open for reading, to see who holds it), once it is known to be a regular file: a link is never followed (locking truncates the file, so a link could empty
    another), a FIFO or device put in its place is never waited on. FileNotFoundError where there
    is none and `create` is False; StoreError naming the file where it is not a lock file."""
    flags = os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC | (os.O_RDWR | os.O_CREAT if create else os.O_RDONLY)
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise StoreError(f"{printable(str(path))} is a link, not a lock file: remove it") from None
        if isinstance(e, FileNotFoundError):
            raise
        raise StoreError(f"lock file {printable(str(path))} cannot be opened ({e.strerror or e})") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise StoreError(f"{printable(str(path))} is not a regular file, so not a lock file: remove it")
    return fd


def lock_holder(fd: int) -> str:
    """Who a held lock file says holds it (its first 200 bytes, escaped), or 'another process'."""
    return printable(os.pread(fd, 200, 0).decode(errors="replace").strip()) or "another process"


def _host() -> str:
    """This machine's name as a staging folder's name holds it: a pid names a process on one machine only."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", os.uname().nodename)[:64] or "unknown"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):  # another user's process; a number no pid can be: left alone
        pass
    return True


def _folders(path: Path) -> list[Path]:
    """The folders (not links) directly in `path`; [] where it cannot be listed."""
    try:
        with os.scandir(path) as entries:
            return [Path(e.path) for e in entries if e.is_dir(follow_symlinks=False)]
    except OSError:
        return []


EXACT_ARRAYS = "exact.npz"  # an exact artifact's state space, occupancies and MI (recipes/exact_runs.py)
EVAL_ROLLOUT = "rollout.gif"  # an evaluation's first episode, drawn (recipes/runs.py): megabytes
# What `esr export --without-checkpoint` leaves out of a finished artifact, by kind: a run's
# networks and its TensorBoard event files (a second copy of metrics.jsonl, most of what else a
# run holds), an exact check's arrays, an evaluation's rollout GIF. What stays (manifest,
# summaries, metrics) is what reports and tables read; the manifest keeps the digests of what
# was left out. The first part's absence marks an artifact kept without them (runs archived
# before the event files were left out still hold theirs).
LEFT_OUT = {RUN_KIND: (CHECKPOINT_FOLDER, EVENTS_FOLDER), EXACT_KIND: (EXACT_ARRAYS,), EVAL_KIND: (EVAL_ROLLOUT,)}


def kept_without(kind: str, path: Path) -> tuple[str, ...]:
    """The parts (LEFT_OUT) a committed artifact was kept without; () where it is whole."""
    parts = LEFT_OUT.get(kind, ())
    if not parts or (Path(path) / parts[0]).exists():
        return ()
    return tuple(part for part in parts if not (Path(path) / part).exists())


def without_checkpoint(path: Path) -> bool:
    """Whether a committed run was kept as metrics only: `esr export --without-checkpoint` leaves
    out its whole checkpoint folder (a folder that is there is checked file by file, so a
    checkpoint damaged in part is still found). Its metrics, spec and manifest are checked as
    always; reading its final networks needs the full archive."""
    return bool(kept_without(RUN_KIND, path))


def require_networks(run_dir: Path) -> None:
    """Raise StoreError where a committed run was kept as metrics only: what reads its networks
    (evaluation, diagnosis, exact empowerment under its robot) says how to get them back."""
    if (Path(run_dir) / MANIFEST).is_file() and without_checkpoint(run_dir):  # committed: an unfinished one has none yet
        raise StoreError(f"{run_dir}: this run is kept as metrics only (exported with --without-checkpoint): its "
                         "networks are not in this store; `esr import` of its full archive puts them back")


def shown_name(rel: str) -> str:
    """A file name from an archive or a manifest as a message shows it: escaped, one line, at
    most 200 characters."""
    return printable(rel if len(rel) <= 200 else rel[:200] + "...")


def file_problem(path: Path, rel: str, want) -> str | None:
    """Why the file `rel` that a manifest lists does not match it, or None. Never reads outside
    the artifact (an absolute name, `..`, a link: committed artifacts hold plain files only) and
    never stops on a file it cannot read, so one bad file hides no other problem."""
    inside = PurePosixPath(rel)
    if inside.is_absolute() or ".." in inside.parts:
        return f"{MANIFEST} lists {rel[:80]!r}, which is not a file inside the artifact"
    shown = shown_name(rel)
    try:  # a name the file system cannot hold (too long) is a problem of this file, not a crash
        if any((path / PurePosixPath(*inside.parts[:i])).is_symlink() for i in range(1, len(inside.parts) + 1)):
            return f"{shown} is a link, not a plain file"
        f = path / rel
        if not f.is_file():
            return f"missing file {shown}" if not f.exists() else f"{shown} is not a plain file (a folder, a FIFO or a device)"
        same = digest_file(f) == want
    except OSError as e:
        return f"unreadable file {shown} ({e.strerror or e})"
    return None if same else f"changed file {shown} (digest differs from the manifest)"


def components_problem(record: dict, name: str) -> str | None:
    """Why `record` (a manifest or a pending.json) does not name its key's components, or None.
    A key is a digest of its components, so an artifact whose listed components digest to another
    key was relabelled or edited: its files may not be what its key says (`esr import` refuses it)."""
    components = record.get("key_components")
    if not isinstance(components, dict):
        return f"{name} lists no key_components (an object), so its key cannot be checked"
    try:
        recomputed = content_key(components)
    except (TypeError, ValueError, RecursionError):
        return f"{name}'s key_components cannot be digested"
    if recomputed != record.get("key"):
        return (f"{name}'s key_components digest to {recomputed}, not its key "
                f"{str(record.get('key'))[:40]!r}: the artifact was relabelled or its components edited")
    return None


# What every commit writes (artifacts.ensure and Store.commit); readers rely on these.
MANIFEST_FIELDS = {"kind": str, "key": str, "files": dict}


def load_manifest(path: Path) -> dict:
    """The manifest of the artifact directory `path`; StoreError if it is missing or damaged, whose
    text names the problem but not the path (callers say where). Read with bounded work
    (esr_cli/common/jsonl.py): listing a store reads every manifest in it."""
    try:
        manifest = read_json(path / MANIFEST, MAX_MANIFEST_BYTES)
    except FileNotFoundError:
        raise StoreError(f"no {MANIFEST}: not a committed artifact") from None
    except OSError as e:
        raise StoreError(f"{MANIFEST} cannot be read ({e.strerror})") from None
    except JsonInputError as e:
        raise StoreError(f"{MANIFEST} is {e}") from None
    if not isinstance(manifest, dict):
        raise StoreError(f"{MANIFEST} is not a JSON object")
    for field, kind in MANIFEST_FIELDS.items():
        if not isinstance(manifest.get(field), kind):
            raise StoreError(f"{MANIFEST} has no {field!r} ({'an object' if kind is dict else 'text'}), which every artifact's manifest has")
    return manifest


def read_pending(directory: Path) -> dict | None:
    """An unfinished artifact's pending.json, or None where it is missing, unreadable, not a
    JSON object, or larger or deeper than any esr writes (a few KiB: an archive's copy is read too)."""
    try:
        value = read_json(Path(directory) / PENDING, MAX_PENDING_BYTES)
    except (OSError, JsonInputError):
        return None
    return value if isinstance(value, dict) else None
