"""Reading the JSON esr writes into a store (manifests, pending.json, checkpoint digests) and the
JSON-lines files appended as work goes (metrics, played steps), with bounded work: a file or
line larger than esr ever writes is refused unread, and so is nesting deeper than MAX_DEPTH and a
line or file of more lists and objects than esr ever writes (each costs the parser a Python object,
far more than its two bytes of text), so one damaged or hostile artifact costs a listing one line,
never its memory, its time or its stack. Files are opened as common/bounded_files.py opens them:
regular files only, never a link, a FIFO or a device."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, BinaryIO

from esr_cli.common import bounded_files

MAX_DEPTH = 64  # a manifest nests about 6 levels (key components, spec, section, list)
MAX_LINE_BYTES = 1 << 20  # a metrics line of 1,024 seeds is about 250 KiB
# A whole JSON-lines file: a 20-seed 10,000-epoch run's metrics are about 30 MiB. Reading one
# costs about 9 times its size in memory (a dict a row, a float object a value), so this bounds
# a command at a few GiB; training refuses a run whose metrics would pass it
# (runner/resources.py::check_metrics_readable).
MAX_JSONL_BYTES = 256 << 20
# Lists and objects: a manifest holds about 50, a metrics line about 15 (one list a metric), a
# played step's state a few hundred (its grids as nested lists), a metrics file of 10,000 epochs
# about 150,000. A line of 1 MiB could hold 350,000, and a file of such lines take the parser
# minutes and many GiB.
MAX_CONTAINERS = 1 << 16  # in one JSON text (a file, or a line of a JSON-lines file)
MAX_JSONL_CONTAINERS = 1 << 22


class JsonInputError(bounded_files.UnreadableInput):
    """A JSON text esr refuses to read; `str()` is one line."""


def _containers(data: bytes) -> int:
    """How many lists and objects `data` can hold at most (a bracket in a string counts too)."""
    return data.count(b"{") + data.count(b"[")


def _open(path: Path) -> BinaryIO:
    """bounded_files.open_regular, its refusals as JsonInputError."""
    try:
        return bounded_files.open_regular(path)
    except bounded_files.UnreadableInput as e:
        raise JsonInputError(str(e)) from None


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
    one object, holds more than MAX_CONTAINERS lists and objects or nests too deeply."""
    if _containers(data) > MAX_CONTAINERS:
        raise JsonInputError(f"JSON of more than {MAX_CONTAINERS:,} lists and objects (esr writes a few hundred at most)")
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
        # json's messages that name a place end in " at", its position following in str(e) only
        raise JsonInputError(f"not UTF-8 JSON (line {e.lineno}, column {e.colno}: {e.msg.removesuffix(' at')})") from None
    except ValueError:  # what else json refuses: an integer of more digits than it converts
        raise JsonInputError("JSON with an integer too long to read") from None
    if _depth(value) > MAX_DEPTH:
        raise too_deep
    return value


def read_json(path: Path, max_bytes: int) -> Any:
    """The JSON value of file `path`. OSError where it cannot be read; JsonInputError where it is
    a link, not a regular file, larger than `max_bytes`, not UTF-8 JSON or nested too deeply."""
    try:
        data = bounded_files.read_bytes(path, max_bytes)
    except bounded_files.UnreadableInput as e:
        raise JsonInputError(str(e)) from None
    return parse(data)


def read_jsonl(path: Path) -> list[dict]:
    """One dict per line; [] where the file does not exist yet. A line cut short by a kill ends
    the reading: everything after it is untrusted, as is everything after a line that is not a
    JSON object, is longer than MAX_LINE_BYTES, holds more than MAX_CONTAINERS lists and objects
    or nests too deeply, and after the first MAX_JSONL_BYTES or MAX_JSONL_CONTAINERS (a
    file that grew past them while it was read, or one no esr command wrote). JsonInputError where
    the file is a link, not a regular file or larger than MAX_JSONL_BYTES; OSError where it cannot
    be read."""
    try:
        f = _open(path)
    except FileNotFoundError:
        return []
    rows = []
    with f:
        too_large = bounded_files.size_problem(f, MAX_JSONL_BYTES)
        if too_large:
            raise JsonInputError(str(too_large))
        left, containers_left = MAX_JSONL_BYTES, MAX_JSONL_CONTAINERS
        while left and (line := f.readline(min(MAX_LINE_BYTES + 1, left))):
            left -= len(line)
            containers_left -= _containers(line)
            if len(line) > MAX_LINE_BYTES or containers_left < 0:
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
