"""Reading the JSON esr writes into a store (manifests, pending.json, checkpoint digests) and the
JSON-lines files appended as work goes (metrics, played steps), with bounded work: a file or
line larger than esr ever writes is refused unread, and so is nesting deeper than MAX_DEPTH, so
one damaged or hostile artifact costs a listing one line, never its memory or its stack."""

from __future__ import annotations

import json
import stat
from pathlib import Path
from typing import Any

MAX_DEPTH = 64  # a manifest nests about 6 levels (key components, spec, section, list)
MAX_LINE_BYTES = 1 << 20  # a metrics line of 1,024 seeds is about 250 KiB


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


def parse(data: bytes) -> Any:
    """The JSON value of `data`; JsonInputError where it is not UTF-8 JSON or nests too deeply."""
    too_deep = JsonInputError(f"nested deeper than {MAX_DEPTH} levels")
    try:
        value = json.loads(data)
    except RecursionError:  # far deeper than the limit: the parser gave up first
        raise too_deep from None
    except ValueError:  # bad UTF-8, bad JSON, an integer too long to read
        raise JsonInputError("not UTF-8 JSON") from None
    if _depth(value) > MAX_DEPTH:
        raise too_deep
    return value


def read_json(path: Path, max_bytes: int) -> Any:
    """The JSON value of file `path`. OSError where it cannot be read; JsonInputError where it is
    larger than `max_bytes`, not UTF-8 JSON or nested too deeply."""
    st = Path(path).stat()
    if not stat.S_ISREG(st.st_mode):  # a FIFO would block the reader, a device never end
        raise JsonInputError("not a regular file")
    size = st.st_size
    if size > max_bytes:
        raise JsonInputError(f"{size:,} bytes, more than the {max_bytes:,} esr reads")
    with open(path, "rb") as f:
        data = f.read(max_bytes + 1)  # a size the system misreports cannot make esr read more
    if len(data) > max_bytes:
        raise JsonInputError(f"more than the {max_bytes:,} bytes esr reads")
    return parse(data)


def read_jsonl(path: Path) -> list[dict]:
    """One dict per line; [] where the file does not exist yet. A line cut short by a kill ends
    the reading: everything after it is untrusted, as is everything after a line that is not a
    JSON object, is longer than MAX_LINE_BYTES or nests too deeply."""
    try:
        f = open(path, "rb")
    except FileNotFoundError:
        return []
    rows = []
    with f:
        while line := f.readline(MAX_LINE_BYTES + 1):
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
