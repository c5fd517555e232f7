"""The content-addressed artifact store (docs/store.md).

Layout: <root>/<kind>/<key[:2]>/<key>/ for a committed artifact, <key>.partial/ beside it
while it is being made, and <key>.lock for the lock. Kinds: `KINDS` below.

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
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from esr_cli import faults

MANIFEST = "manifest.json"
# The artifact kinds, each a top-level folder of the store; every module names them from here.
RUN_KIND, EVAL_KIND, EXACT_KIND, FIGURE_KIND, DATA_KIND, HUMAN_KIND = "runs", "evals", "exact", "figures", "humandata", "humans"
PLAY_KIND = "play"  # an episode a person played with a robot (esr play)
KINDS = (RUN_KIND, EVAL_KIND, EXACT_KIND, FIGURE_KIND, DATA_KIND, HUMAN_KIND, PLAY_KIND)


class StoreError(Exception):
    """A problem with the store or an artifact; `str()` is a one-line explanation."""


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


def atomic_write_text(path: Path, text: str) -> None:
    """Write via a temporary file, fsync, rename: readers see the old file or the new one."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


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


class Store:
    def __init__(self, root: str | Path):
        self.root = Path(root)

    # ---------------------------------------------------------------- paths
    def final_path(self, kind: str, key: str) -> Path:
        return self.root / kind / key[:2] / key

    def partial_path(self, kind: str, key: str) -> Path:
        return self.root / kind / key[:2] / f"{key}{PARTIAL_SUFFIX}"

    def lock_path(self, kind: str, key: str) -> Path:
        return self.root / kind / key[:2] / f"{key}.lock"

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
        try:
            return json.loads((Path(path) / MANIFEST).read_text())
        except FileNotFoundError:
            raise StoreError(f"{path}: no {MANIFEST}: not a committed artifact") from None
        except json.JSONDecodeError as e:
            raise StoreError(f"{path}/{MANIFEST} is corrupt: {e}") from None

    def entries(self) -> Iterator[Entry]:
        for kind in KINDS:
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
                        yield Entry(kind, key, d, "partial", _try_json(d / "pending.json"))
                    elif (d / MANIFEST).is_file():
                        yield Entry(kind, key, d, "complete", _try_json(d / MANIFEST))

    def resolve(self, ref: str) -> Path:
        """A committed artifact from a key, a unique key prefix (>= 4 chars) or a path."""
        return self.find(ref).path

    def find(self, ref: str, include_partial: bool = False) -> Entry:
        """The artifact a key, a unique key prefix (>= 4 hex digits) or a directory names; with
        include_partial, an unfinished one too (where a key is both, the committed one)."""
        p = Path(ref)
        key, status = parse_dirname(p.name)
        if (p / MANIFEST).is_file() or (include_partial and status == "partial" and p.is_dir()):
            return Entry(p.parent.parent.name, key, p, status, None)
        if not re.fullmatch(r"[0-9a-f]{4,32}", ref):
            raise StoreError(f"no artifact {ref!r}: give a path to an artifact directory or a key (at least 4 hex digits)")
        hits = [e for e in self.entries() if e.key.startswith(ref) and (include_partial or e.status == "complete")]
        hits = [e for e in hits if e.status == "complete"] or hits
        if not hits:
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
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
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
                        holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
                        on_wait(holder)
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
        atomic_write_text(path / "pending.json", json.dumps(pending, indent=2, sort_keys=True))
        return path

    def commit(self, kind: str, key: str, manifest: dict) -> Path:
        """Digest every file, write the manifest, rename partial -> final (atomic)."""
        partial, final = self.partial_path(kind, key), self.final_path(kind, key)
        for stale in (partial / "pending.json", partial / MANIFEST):  # MANIFEST: a commit cut short
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

    # ---------------------------------------------------------------- checking
    def verify(self, path: Path) -> list[str]:
        """Re-hash every file against the manifest; -> list of problems (empty: intact)."""
        manifest = self.read_manifest(path)
        problems = []
        listed = manifest.get("files", {})
        for rel, want in sorted(listed.items()):
            f = Path(path) / rel
            if not f.is_file():
                problems.append(f"missing file {rel}")
            elif digest_file(f) != want:
                problems.append(f"changed file {rel} (digest differs from the manifest)")
        for f in sorted(Path(path).rglob("*")):
            rel = f.relative_to(path).as_posix()
            if f.is_file() and rel != MANIFEST and rel not in listed:
                problems.append(f"unexpected file {rel}")
        return problems


def _try_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
