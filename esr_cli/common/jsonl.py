"""Reading the JSON esr writes into a store (manifests, pending.json, checkpoint digests) and the
JSON-lines files appended as work goes (metrics, played steps), with bounded work: a file or
line larger than esr ever writes is refused unread, and so is nesting deeper than MAX_DEPTH, so
one damaged or hostile artifact costs a listing one line, never its memory or its stack. Each
file is opened without blocking and without following a link, and read only once the open file
is known to be a regular one: a FIFO or a device put in a file's place is refused, never waited
on (nor is a name checked first and opened after, when something else may lie there)."""

from __future__ import annotations

import errno
import fcntl
import json
import os
import stat
from pathlib import Path
from typing import Any, BinaryIO

MAX_DEPTH = 64  # a manifest nests about 6 levels (key components, spec, section, list)
MAX_LINE_BYTES = 1 << 20  # a metrics line of 1,024 seeds is about 250 KiB
# A whole JSON-lines file: a 20-seed 10,000-epoch run's metrics are about 30 MiB. Reading one
# costs about 9 times its size in memory (a dict a row, a float object a value), so this bounds
# a command at a few GiB; training refuses a run whose metrics would pass it
# (runner/resources.py::check_metrics_readable).
MAX_JSONL_BYTES = 256 << 20


class JsonInputError(ValueError):
    """A JSON text esr refuses to read; `str()` is one line."""


def _depth(value: Any) -> int:
    """How deeply lists and objects nest in `value` (walked without recursion)."""
    deepest, todo = 0, [(value, 1)]
    while todo:
        item, level = todo.pop()
        children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else None
        if children is not None:
            deepest = max(deepest, level)
            todo.extend((child, level + 1) for child in children)
    return deepest


class _KeyTwice(Exception):
    pass


def _object(pairs: list) -> dict:
    """One JSON object, refusing a key named twice: esr never writes one, and readers disagree
    on which value counts (Python's keeps the last, others the first), so a manifest could show
    one reader one record and another reader another."""
    out = dict(pairs)
    if len(out) != len(pairs):
        seen: set = set()
        raise _KeyTwice(next(k for k, _ in pairs if k in seen or seen.add(k)))
    return out


def parse(data: bytes) -> Any:
    """The JSON value of `data`; JsonInputError where it is not UTF-8 JSON, names a key twice in
    one object or nests too deeply."""
    too_deep = JsonInputError(f"nested deeper than {MAX_DEPTH} levels")
    try:
        value = json.loads(data, object_pairs_hook=_object)
    except _KeyTwice as e:
        raise JsonInputError(f"JSON with an object naming the key {ascii(str(e.args[0])[:64])} twice") from None
    except RecursionError:  # far deeper than the limit: the parser gave up first
        raise too_deep from None
    except UnicodeDecodeError:
        raise JsonInputError("not UTF-8 JSON") from None
    except json.JSONDecodeError as e:
        raise JsonInputError(f"not UTF-8 JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except ValueError:  # what else json refuses: an integer of more digits than it converts
        raise JsonInputError("JSON with an integer too long to read") from None
    if _depth(value) > MAX_DEPTH:
        raise too_deep
    return value


def open_regular(path: Path) -> BinaryIO:
    """`path` open for reading, once the open file is known to be a regular one. Opened without
    blocking (a FIFO does not wait for a writer) and without following a link, then made blocking
    again. OSError where it cannot be opened (FileNotFoundError where nothing is there);
    JsonInputError where it is a link or not a regular file."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as e:
        if e.errno == errno.ELOOP:  # O_NOFOLLOW met a link
            raise JsonInputError("a link, not a regular file") from None
        raise
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # a FIFO would block the reader, a device never end
            raise JsonInputError("not a regular file")
        flags = fcntl.fcntl(fd, fcntl.F_GETFL)
        if flags & os.O_NONBLOCK:
            fcntl.fcntl(fd, fcntl.F_SETFL, flags & ~os.O_NONBLOCK)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def _too_large(f: BinaryIO, max_bytes: int) -> JsonInputError | None:
    size = os.fstat(f.fileno()).st_size
    return JsonInputError(f"{size:,} bytes, more than the {max_bytes:,} esr reads") if size > max_bytes else None


def read_json(path: Path, max_bytes: int) -> Any:
    """The JSON value of file `path`. OSError where it cannot be read; JsonInputError where it is
    a link, not a regular file, larger than `max_bytes`, not UTF-8 JSON or nested too deeply."""
    with open_regular(path) as f:
        too_large = _too_large(f, max_bytes)
        if too_large:
            raise too_large
        data = f.read(max_bytes + 1)  # a size the system misreports cannot make esr read more
    if len(data) > max_bytes:
        raise JsonInputError(f"more than the {max_bytes:,} bytes esr reads")
    return parse(data)


def read_jsonl(path: Path) -> list[dict]:
    """One dict per line; [] where the file does not exist yet. A line cut short by a kill ends
    the reading: everything after it is untrusted, as is everything after a line that is not a
    JSON object, is longer than MAX_LINE_BYTES or nests too deeply, and after the first
    MAX_JSONL_BYTES (a file that grew past them while it was read). JsonInputError where the file
    is a link, not a regular file or larger than MAX_JSONL_BYTES; OSError where it cannot be read."""
    try:
        f = open_regular(path)
    except FileNotFoundError:
        return []
    rows = []
    with f:
        too_large = _too_large(f, MAX_JSONL_BYTES)
        if too_large:
            raise too_large
        left = MAX_JSONL_BYTES
        while left and (line := f.readline(min(MAX_LINE_BYTES + 1, left))):
            left -= len(line)
            if len(line) > MAX_LINE_BYTES:
                break
            try:
                row = parse(line)
            except JsonInputError:
                break
            if not isinstance(row, dict):
                break
            rows.append(row)
    return rows


def dumps(value: Any, **options) -> str:
    """`value` as strict JSON, which every reader parses: a NaN or an infinity (which a manifest
    read from an archive may hold, and Python's json would write as the non-JSON `NaN`) is null."""

    def finite(v: Any) -> Any:
        if isinstance(v, float):
            return v if v == v and v not in (float("inf"), float("-inf")) else None
        if isinstance(v, dict):
            return {k: finite(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [finite(x) for x in v]
        return v

    return json.dumps(finite(value), allow_nan=False, **options)
