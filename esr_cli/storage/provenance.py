"""What produced an artifact: the components of its content key, and provenance facts.

Key components (they decide whether two runs are the same):
  spec        the validated spec's training sections (never the raw YAML)
  budget      the budget the spec was resolved at
  code        a digest of the source files that define training behaviour
  toolchain   jax / jaxlib versions and the backend (cpu, gpu, ...)
  dependencies  keys of artifacts this one is built from
Provenance facts (recorded, not part of the key): git commit and dirty flag, package
versions, device, host, wall time.
"""

from __future__ import annotations

import ast
import hashlib
import os
import platform
import re
import subprocess
import time
from datetime import datetime
from functools import cache
from importlib import metadata
from pathlib import Path
from typing import NamedTuple

from esr_cli.common.numbers import as_number
from esr_cli.common.printing import printable

PACKAGE_DIR = Path(__file__).resolve().parents[1]  # esr_cli/


def experiments_dir() -> Path:
    """The experiments/ folder commands read the paper's specs and suites from: the current
    directory's, where it has the paper suite (a researcher's own copy, edited or not), else
    the one installed with esr (the checkout's, through esr_cli/experiments, or a wheel's copy)."""
    here = Path.cwd() / "experiments"
    return here if (here / "suites" / "paper.yaml").is_file() else PACKAGE_DIR / "experiments"
# What a run computes is the keyed package, esr_cli/model: the spec's models, the training core,
# learner, replay, networks, environments, methods and human models. A run's code digest covers
# every file in it, so editing any of them re-keys runs, and model imports nothing outside
# itself (tests/test_layout.py), so nothing else can change a run's numbers unseen. The host
# loop (chunking, checkpoints, progress), the store, the CLI, plotting and docs live outside it:
# they do not change the numbers (resuming is bit-identical). Evaluations use the same digest.
# Artifacts of other kinds digest their own roots' import closures (`module_closure`): a human
# its trainer's files, a figure its drawing code.
MODEL_SOURCES = ("model",)
PACKAGES = ("jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "numpy", "esr-cli")


ISO_FORMAT = "%Y-%m-%dT%H:%M:%S%z"


def now_iso() -> str:
    """Local time with its UTC offset, as every record of the store writes it."""
    return time.strftime(ISO_FORMAT)


def created_order(manifest: object) -> float:
    """When a record was made, in seconds since the epoch, for choosing the newest of several:
    its `created_at` read with its UTC offset (text comparison would misorder records written in
    different time zones); -inf for a record that lacks one or whose timestamp is damaged, so it
    ranks below every dated record."""
    created = manifest.get("created_at") if isinstance(manifest, dict) else None
    if not isinstance(created, str) or len(created) > 64:
        return float("-inf")
    try:
        return datetime.strptime(created, ISO_FORMAT).timestamp()
    except ValueError:
        return float("-inf")


def _module_file(dotted: str) -> Path | None:
    """The file of an `esr_cli...` module (a package's __init__.py), or None."""
    parts = dotted.split(".")
    if parts[0] != PACKAGE_DIR.name:
        return None
    base = PACKAGE_DIR.joinpath(*parts[1:])
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imports(path: Path) -> set[Path]:
    """esr_cli files that `path` imports anywhere (module level or inside functions), with the
    __init__.py of every package on the way."""
    tree = ast.parse(path.read_text(), str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)  # `from pkg import module`
    found = set()
    for name in names:
        parts = name.split(".")
        for i in range(2, len(parts) + 1):  # from esr_cli.X on: the root __init__ is only a version
            f = _module_file(".".join(parts[:i]))
            if f is not None:
                found.add(f)
    return found


def module_closure(roots: tuple[str, ...]) -> list[Path]:
    """Every esr_cli source file reachable by imports from `roots` (files or directories,
    relative to the package), sorted."""
    todo = []
    for name in roots:
        p = PACKAGE_DIR / name
        todo += sorted(p.rglob("*.py")) if p.is_dir() else [p]
    seen: set[Path] = set()
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        todo += [g for g in _imports(f) if g not in seen]
    return sorted(seen)


@cache
def code_digest(roots: tuple[str, ...] = MODEL_SOURCES, alone: tuple[str, ...] = ()) -> str:
    """blake2b over the path and bytes of every file in the import closure of `roots`, and of
    the files `alone` without what they import (host code such as an analysis's store and
    checkpoint plumbing, which decides where numbers are read from, never what they are)."""
    h = hashlib.blake2b(digest_size=16)
    for f in sorted(set(module_closure(roots)) | {PACKAGE_DIR / name for name in alone}):
        h.update(f.relative_to(PACKAGE_DIR).as_posix().encode() + b"\0")
        h.update(f.read_bytes() + b"\0")
    return h.hexdigest()


# float32 matrix products and convolutions: "highest" is exact float32 on every backend (on the
# CPU it is what XLA does anyway, bit for bit). On NVIDIA GPUs JAX's own default lets cuBLAS
# use TF32 (10-bit mantissa); ESR_MATMUL_PRECISION=tensorfloat32 or bfloat16 opts into that
# speed, and the choice then becomes part of every run's key (docs/performance.md).
PRECISION_ENV = "ESR_MATMUL_PRECISION"
PRECISIONS = ("highest", "tensorfloat32", "bfloat16")


def matmul_precision() -> str:
    value = os.environ.get(PRECISION_ENV, "").strip().lower() or "highest"
    if value not in PRECISIONS:
        raise ValueError(f"{PRECISION_ENV}={value!r}: choose one of {', '.join(PRECISIONS)}")
    return value


def compile_cache_dir() -> str | None:
    """Where compiled XLA programs are kept ($ESR_COMPILE_CACHE, default ~/.cache/esr/jax), or
    None when it is `off`; ValueError when it names something that is not a folder."""
    where = os.environ.get("ESR_COMPILE_CACHE", str(Path.home() / ".cache" / "esr" / "jax"))
    if where.strip().lower() in ("", "0", "off", "none"):
        return None
    if os.path.exists(where) and not os.path.isdir(where):
        raise ValueError(f"ESR_COMPILE_CACHE={where!r} is not a folder: name a folder, or `off` to keep no compiled programs")
    return where


def apply_matmul_precision() -> str:
    """Set JAX's default matmul precision for this process (before anything compiles)."""
    import jax

    value = matmul_precision()
    jax.config.update("jax_default_matmul_precision", value)
    return value


def toolchain() -> dict:
    import jax
    import jaxlib

    tools = {"jax": jax.__version__, "jaxlib": jaxlib.__version__, "backend": jax.default_backend()}
    if matmul_precision() != "highest":  # the default adds nothing, so keys made before it stay valid
        tools["matmul_precision"] = matmul_precision()
    return tools


def key_components(kind: str, spec_part: dict, budget: str, dependencies: dict | None = None) -> dict:
    return {
        "kind": kind,
        "spec": spec_part,
        "budget": budget,
        "code": code_digest(),
        "toolchain": toolchain(),
        "dependencies": dict(sorted((dependencies or {}).items())),
    }


def git_state() -> dict:
    root = PACKAGE_DIR.parent

    def run(*args):
        try:
            out = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return out.stdout.strip() if out.returncode == 0 else None

    commit = run("rev-parse", "HEAD")
    if commit is None:
        return {"commit": None, "dirty": None}
    status = run("status", "--porcelain", "--untracked-files=no", "--", "esr_cli")
    return {"commit": commit, "dirty": bool(status)}


def session(with_device: bool) -> dict:
    """This process's part in making an artifact: the checkout it ran from (and whether its
    esr_cli/ differed from that commit), when it started, and for a run the device."""
    git = git_state()
    record = {"commit": git["commit"], "dirty": git["dirty"], "started_at": now_iso()}
    if with_device:
        record["device"] = device()
        # XLA's CPU backend splits work over the cores a process may use, and the split orders
        # float additions: a run's numbers are reproduced bit for bit only on as many cores.
        record["cpu_cores"] = cpu_cores()
    return record


def cpu_cores() -> int:
    """The cores this process may run on (its affinity; `taskset` and cgroups narrow it)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # no affinity call on this platform
        return os.cpu_count() or 1


MAX_SESSIONS = 100  # a run resumed by many short jobs keeps its first and its latest sessions


def with_session(earlier: list[dict], new: dict) -> list[dict]:
    """`earlier` and then `new`, at most MAX_SESSIONS records: past that the first (where the
    artifact was made) is kept, then one record counting those left out (and their seconds,
    when every one of them recorded its own), then the latest."""
    sessions = earlier + [new]
    if len(sessions) <= MAX_SESSIONS:
        return sessions
    left_out = sessions[1:len(sessions) - MAX_SESSIONS + 2]
    merged = {"omitted": sum(s.get("omitted", 1) for s in left_out)}
    walls = [session_wall(s) for s in left_out]
    if all(w is not None for w in walls):
        merged["wall_s"] = round(sum(walls), 2)
    return [sessions[0], merged] + sessions[len(sessions) - MAX_SESSIONS + 2:]


def session_wall(session: dict) -> float | None:
    """The seconds a session recorded that it worked (None: it was killed before it could say,
    or an older esr made it)."""
    wall = as_number(session.get("wall_s"))
    return wall if wall is not None and 0 <= wall < 1e12 else None  # NaN fails the range too


def with_wall(sessions: list[dict], seconds: float) -> list[dict]:
    """`sessions` with the latest one's working time recorded."""
    return sessions[:-1] + [{**sessions[-1], "wall_s": round(seconds, 2)}]


def wall_time(info: dict | None) -> tuple[float | None, bool]:
    """(seconds, whether that is every session's) of a manifest: the sum over its sessions when
    they recorded their own (a resumed run's sessions add up), else its `wall_time_s`, which an
    older esr wrote for the last session only; a lower bound when some session did not say."""
    total = session_wall({"wall_s": info.get("wall_time_s")}) if isinstance(info, dict) else None
    sessions = earlier_sessions(info) if isinstance(info, dict) and isinstance(info.get("sessions"), list) else []
    return total, len(sessions) <= 1 or all(session_wall(s) is not None for s in sessions)


def earlier_sessions(pending: dict | None) -> list[dict]:
    """The sessions that a resumed artifact's pending.json records, oldest first. One written
    before sessions were recorded names only the session that last resumed it. A session that
    stopped at a chunk boundary without its own working time (an older esr) gets it from when it
    started and when it stopped."""
    if not pending:
        return []
    sessions = pending.get("sessions")
    if isinstance(sessions, list):
        sessions = [s for s in sessions if isinstance(s, dict)]
        stopped = pending.get("stopped")
        if sessions and session_wall(sessions[-1]) is None and isinstance(stopped, dict):
            seconds = _seconds_between(sessions[-1].get("started_at"), stopped.get("at"))
            if seconds is not None:
                sessions = with_wall(sessions, seconds)
        return sessions
    last = {k: pending[k] for k in ("commit", "device") if isinstance(pending.get(k), str)}
    return [last] if last else []


def carried_sessions(pending: dict | None) -> list[dict]:
    """`earlier_sessions`, as the manifest of the run they resumed keeps them: each record only
    the fields `session` and `with_session` write, each of its type, its texts bounded and
    escaped as `origin` shows them (a pending.json may come from an archive)."""
    return [_as_recorded(s) for s in earlier_sessions(pending)]


def _as_recorded(record: dict) -> dict:
    kept = {}
    for name, value in record.items():
        if name == "commit" and (value is None or isinstance(value, str) and COMMIT.fullmatch(value)):
            kept[name] = value  # None: made outside a git checkout, as `session` records it
        elif name == "dirty" and (value is None or isinstance(value, bool)):
            kept[name] = value
        elif name in ("device", "started_at") and isinstance(value, str) and value:
            kept[name] = printable(value[:MAX_DEVICE_CHARS])  # as `origin` shows it
        elif name in ("cpu_cores", "omitted") and type(value) is int and 0 < value < 1 << 31:
            kept[name] = value
        elif name == "wall_s" and session_wall(record) is not None:
            kept[name] = value
    return kept


def _seconds_between(start: object, end: object) -> float | None:
    try:
        seconds = (datetime.strptime(end, ISO_FORMAT) - datetime.strptime(start, ISO_FORMAT)).total_seconds()
    except (TypeError, ValueError):
        return None
    return seconds if seconds >= 0 else None


COMMIT = re.compile(r"[0-9a-f]{7,64}")  # a git object name: anything else a manifest says is no commit
MAX_DEVICE_CHARS = 200  # a session's device name (or start time), kept and shown


class Origin(NamedTuple):
    """Where a stored artifact was made, from its manifest (or an unfinished one's pending.json)."""

    commit: str | None  # the checkout it was started from; the same at every resume (the code is in the key)
    device: str | None  # every device it ran on, in order ('cpu:cpu', 'gpu:NVIDIA H200, then ...'); None: unknown
    modified: bool  # that checkout had edits under esr_cli/ (its code digest still says which code ran)


MAX_DEVICES_SHOWN = 4  # a run resumed on more devices than this names the first few and a count


def origin(info: dict | None) -> Origin:
    def part(record: object, name: str) -> dict:  # a damaged manifest's field is read as empty, never trusted
        value = record.get(name) if isinstance(record, dict) else None
        return value if isinstance(value, dict) else {}

    def text(value: object) -> str | None:  # shown in tables and pages: never a control character
        return printable(value[:MAX_DEVICE_CHARS]) if isinstance(value, str) and value else None

    def commit_of(value: object) -> str | None:
        return value if isinstance(value, str) and COMMIT.fullmatch(value) else None

    sessions = earlier_sessions(info)
    made = part(info, "provenance")
    # A manifest from before sessions were recorded names only the last one.
    commit = next((s["commit"] for s in sessions if commit_of(s.get("commit"))), None) or commit_of(part(made, "git").get("commit"))
    devices = list(dict.fromkeys(text(s["device"]) for s in sessions if text(s.get("device"))))
    if len(devices) > MAX_DEVICES_SHOWN:  # each name is bounded, their number only by the file
        devices = [*devices[:MAX_DEVICES_SHOWN - 1], f"{len(devices) - MAX_DEVICES_SHOWN + 1} more"]
    # An unfinished run made by an esr whose pending.json named only its backend (part of its key) says just that.
    backend = part(part(info, "key_components"), "toolchain").get("backend")
    device = ", then ".join(devices) or text(made.get("device")) or text(backend)
    return Origin(commit, device, sessions[0].get("dirty") is True if sessions else False)


def package_versions() -> dict:
    out = {}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def device() -> str:
    import jax

    d = jax.devices()[0]
    return f"{d.platform}:{getattr(d, 'device_kind', d.platform)}"


def provenance() -> dict:
    return {
        "git": git_state(),
        "packages": package_versions(),
        "device": device(),
        "host": platform.node(),
        "python": platform.python_version(),
    }


def complete_manifest(pending: dict, components: dict, summary: dict, **extra) -> dict:
    """The manifest every artifact commits with: what `begin` recorded, its key components,
    when it was made (and, with `sessions` in `extra`, how long all of them worked), the
    toolchain and its summary."""
    manifest = {**pending, "format": 1, "status": "complete", **extra, "key_components": components,
                "created_at": now_iso()}
    walls = [session_wall(s) for s in manifest.get("sessions", ())]
    if walls:
        manifest["wall_time_s"] = round(sum(w for w in walls if w is not None), 2)
    return {**manifest, "provenance": provenance(), "summary": summary}
