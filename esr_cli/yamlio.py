"""Reading the YAML files esr is given (specs, suites, `extends:` targets, `--set` values) with
bounded work, before anything walks the tree (docs/reliability.md):

- files over MAX_FILE_BYTES are refused unread;
- anchors and aliases are refused where the parser meets them, so a nested-alias "billion
  laughs" file is never expanded;
- a key given twice in one mapping is refused, naming the key and both lines (PyYAML would
  silently keep the last one);
- `1e-4` without a dot is read as a number (YAML 1.1 reads it as a string).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

MAX_FILE_BYTES = 1 << 20  # 1 MiB: the largest spec or suite shipped is under 4 KiB


class YamlInputError(Exception):
    """A file or value esr refuses to read; `str()` is one line."""


class _BoundedLoader(yaml.SafeLoader):
    def compose_node(self, parent, index):
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent):
            raise YamlInputError(f"line {event.start_mark.line + 1}: aliases (*{event.anchor}) are not allowed; "
                                 "write the value out")
        anchor = getattr(event, "anchor", None)
        if anchor is not None:
            raise YamlInputError(f"line {event.start_mark.line + 1}: anchors (&{anchor}) are not allowed; "
                                 "write each value out")
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            try:
                first = seen.get(key)
            except TypeError:  # an unhashable key: PyYAML's own error follows
                first = None
            if first is not None:
                raise YamlInputError(f"key {key!r} appears twice in one mapping (lines {first} and {line}); keep one")
            if isinstance(key, (str, int, float, bool)) or key is None:
                seen[key] = line
        return super().construct_mapping(node, deep=deep)


_FLOAT = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9_]+(?:[eE][-+][0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""", re.X)
_BoundedLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list("-+0123456789."))


def parse(text: str) -> Any:
    """The YAML value of `text` (bounded: see the module doc). Raises YamlInputError."""
    try:
        return yaml.load(text, Loader=_BoundedLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        raise YamlInputError(f"unreadable YAML: {where}{getattr(e, 'problem', None) or e}") from None
    except RecursionError:
        raise YamlInputError("unreadable YAML: nested too deeply") from None


def read(path: str | Path) -> Any:
    """Parse a file after checking its size. Raises YamlInputError (missing, too large, bad)."""
    p = Path(path)
    if not p.exists():
        raise YamlInputError("file not found")
    if not p.is_file():
        raise YamlInputError("not a file")
    size = p.stat().st_size
    if size > MAX_FILE_BYTES:
        raise YamlInputError(f"{size:,} bytes: larger than the {MAX_FILE_BYTES:,} bytes esr reads from a spec or suite file")
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise YamlInputError(f"cannot read file: {e}") from None
    return parse(text)
