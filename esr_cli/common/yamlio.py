"""Reading the YAML files esr is given (specs, suites, `extends:` targets, `--set` values) with
bounded work, before anything walks the tree (docs/reliability.md):

- files over MAX_FILE_BYTES (or a caller's own bound) are refused unread; a store's files are
  read without following a symbolic link;
- anchors and aliases are refused where the parser meets them, so a nested-alias "billion
  laughs" file is never expanded;
- a key given twice in one mapping is refused, naming the key and both lines (PyYAML would
  silently keep the last one);
- scalars are read as YAML 1.2 reads them, not as PyYAML's YAML 1.1: only `true`/`false` are
  booleans (`yes`, `on`, `off` stay text, which a boolean field then refuses), integers are
  decimal (`010` is 10, not octal 8; `1:30` is text, not 90; unlike YAML 1.2, `0x1f` and `0o17`
  are text too), `1e-4` without a dot and `+.5`
  are numbers, and `2020-01-01` is text, not a date; an explicit `!!float` or `!!bool` on
  something else is refused, and so is `!!null` on anything but YAML's spellings of null;
- every key is text: `1:`, `true:` or `null:` as a key is refused (it would read as a list
  index or nothing), and so is YAML 1.1's merge key `<<:` (YAML 1.2 has none);
- integers longer than MAX_INT_DIGITS digits are refused (Python refuses to read them);
- tags that build other Python types (`!!binary`, `!!set`, `!!timestamp`, `!!omap`, `!!pairs`)
  are refused: a spec holds numbers, text, booleans, lists and mappings only.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Callable

import yaml

from esr_cli.common import bounded_files

# The largest spec or suite shipped is under 4 KiB; pure-Python parsing of a worst-case file
# (a flow list of 0s) costs about 4 s a 256 KiB.
MAX_FILE_BYTES = 256 << 10


class YamlInputError(Exception):
    """A file or value esr refuses to read; `str()` is one line."""


_NAME = re.compile(r"[\w.\-\[\]]{1,64}")  # a field, section or anchor name as a spec writes one


def reads_as_name(text: object) -> bool:
    """Whether `text` is a field, section or anchor name as a spec writes one."""
    return _NAME.fullmatch(str(text)) is not None


def shown_name(text: object) -> str:
    """`text` as a message may quote it: a key or anchor that reads as a name is shown as
    written; anything else (a line of a file that is not a spec, a value, something long) only
    by its length, so that a page or suite naming another file never prints that file's text."""
    text = str(text)
    return text if reads_as_name(text) else f"(a key of {len(text):,} character{'s' * (len(text) != 1)} that is not a name)"


def key_path(loc: tuple, tag: Callable[[int, object], bool] = lambda i, part: False, last_is_key: bool = False) -> str:
    """A validator's error location as the key path the user wrote (`questionnaire[1].scale`):
    list indices in brackets, keys as `shown_name` shows them, and the parts for which
    `tag(i, part)` holds (a discriminated union's or a validator's tags) left out.
    `last_is_key`: the last part is a key of the input (an unknown key), shown whatever it is."""
    out = ""
    for i, part in enumerate(loc):
        key = last_is_key and i == len(loc) - 1
        if isinstance(part, int) and not key:
            out += f"[{part}]"
        elif key or not tag(i, part):
            out += ("." if out else "") + shown_name(part)
    return out


_SCALAR_KINDS = {type(None): "null", bool: "a boolean", int: "a number", float: "a number"}


def _not_text(node, key) -> str:
    """What a key that is not text is, as a message says it: a null, boolean or number key as
    written (those read as such only when short and plain), anything else by its kind."""
    if not isinstance(node, yaml.ScalarNode):
        return "is a list or mapping"
    kind = _SCALAR_KINDS.get(type(key), "not text")
    written = node.value or "(empty)"
    return f"{written if len(written) <= 40 else shown_name(written)} is {kind}"


class _BoundedLoader(yaml.SafeLoader):
    def compose_node(self, parent, index):
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent):
            raise YamlInputError(f"line {event.start_mark.line + 1}: aliases (*name) are not allowed; "
                                 "write the value out")
        anchor = getattr(event, "anchor", None)
        if anchor is not None:
            raise YamlInputError(f"line {event.start_mark.line + 1}: anchors (&name) are not allowed; "
                                 "write each value out")
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            line = key_node.start_mark.line + 1
            if key_node.tag == "tag:yaml.org,2002:merge":  # YAML 1.1's `<<:`, which YAML 1.2 does not have
                raise YamlInputError(f"line {line}: merge keys (<<) are not allowed; write each value out")
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.get(key)
            except TypeError:  # an unhashable key: PyYAML's own error follows
                first = None
            if first is not None:
                where = f"line {line}" if first == line else f"lines {first} and {line}"
                raise YamlInputError(f"key {shown_name(key)!r} appears twice in one mapping ({where}); keep one")
            if not isinstance(key, str):  # `1:`, `true:` or `null:` would read as a list index or None
                raise YamlInputError(f"line {line}: the key {_not_text(key_node, key)}, not a name: keys are text "
                                     "(write it in quotes to make it one)")
            seen[key] = line
        return super().construct_mapping(node, deep=deep)


# YAML 1.2 (core schema) plain scalars, replacing PyYAML's YAML 1.1 ones.
_BOOL = re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$")
_INT = re.compile(r"^[-+]?[0-9][0-9_]*$")  # underscores as in 10_000, like the floats
_FLOAT = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*\.[0-9_]*|\.[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)?
    |[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""", re.X)
_REPLACED = {"tag:yaml.org,2002:bool", "tag:yaml.org,2002:int", "tag:yaml.org,2002:float", "tag:yaml.org,2002:timestamp"}
_BoundedLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag not in _REPLACED]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_BoundedLoader.add_implicit_resolver("tag:yaml.org,2002:bool", _BOOL, list("tTfF"))
_BoundedLoader.add_implicit_resolver("tag:yaml.org,2002:int", _INT, list("-+0123456789"))
_BoundedLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list("-+0123456789."))

_NULL = frozenset({"", "~", "null", "Null", "NULL"})
MAX_INT_DIGITS = 4000  # below Python's own limit on reading an integer from text (4300)


def _construct_int(loader, node):
    text = loader.construct_scalar(node).replace("_", "")
    if not _INT.match(text):  # an explicit `!!int` on something else
        raise YamlInputError(f"line {node.start_mark.line + 1}: {text[:40]!r} is not a decimal integer")
    if len(text.lstrip("+-")) > MAX_INT_DIGITS:
        raise YamlInputError(f"line {node.start_mark.line + 1}: an integer of {len(text.lstrip('+-')):,} digits; "
                             f"at most {MAX_INT_DIGITS:,}")
    return int(text)


def _construct_float(loader, node):
    text = loader.construct_scalar(node)
    if not isinstance(text, str) or not (_FLOAT.match(text) or _INT.match(text)):  # an explicit `!!float` on a non-number
        raise YamlInputError(f"line {node.start_mark.line + 1}: {str(text)[:40]!r} is not a number")
    return yaml.SafeLoader.construct_yaml_float(loader, node)


def _construct_bool(loader, node):
    text = loader.construct_scalar(node)
    if not isinstance(text, str) or not _BOOL.match(text):  # `!!bool yes`: YAML 1.2 has only true and false
        raise YamlInputError(f"line {node.start_mark.line + 1}: {str(text)[:40]!r} is not true or false")
    return text.lower() == "true"


def _construct_null(loader, node):
    text = loader.construct_scalar(node)
    if text not in _NULL:  # `!!null x`: only YAML 1.2's spellings of null are null
        raise YamlInputError(f"line {node.start_mark.line + 1}: {str(text)[:40]!r} is not null")
    return None


def _refuse_tag(loader, node):
    raise YamlInputError(f"line {node.start_mark.line + 1}: the tag {node.tag.replace('tag:yaml.org,2002:', '!!')} "
                         "is not allowed: write a number, text, boolean, list or mapping")


_BoundedLoader.add_constructor("tag:yaml.org,2002:int", _construct_int)
_BoundedLoader.add_constructor("tag:yaml.org,2002:float", _construct_float)
_BoundedLoader.add_constructor("tag:yaml.org,2002:bool", _construct_bool)
_BoundedLoader.add_constructor("tag:yaml.org,2002:null", _construct_null)
for _tag in ("binary", "timestamp", "set", "omap", "pairs"):
    _BoundedLoader.add_constructor(f"tag:yaml.org,2002:{_tag}", _refuse_tag)


_LINE_BREAK = re.compile("\r\n|[\r\n\x85\u2028\u2029]")


def parse(text: str) -> Any:
    """The YAML value of `text` (bounded: see the module doc). Raises YamlInputError."""
    try:
        return yaml.load(text, Loader=_BoundedLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.reader.ReaderError as e:  # a character YAML does not allow: named where it is, on one line
        breaks = list(_LINE_BREAK.finditer(text, 0, e.position))  # the breaks YAML counts lines by
        column = e.position - (breaks[-1].end() if breaks else 0) + 1
        raise YamlInputError(f"unreadable YAML: line {len(breaks) + 1}, column {column}: the character "
                             f"U+{e.character:04X} is not allowed in YAML") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = str(getattr(e, "problem", None) or e)
        if "'\\t'" in problem:  # PyYAML takes a tab for neither indentation nor a separating space
            problem += " (a tab: write spaces instead)"
        raise YamlInputError(f"unreadable YAML: {where}{problem}") from None
    except RecursionError:
        raise YamlInputError("unreadable YAML: nested too deeply") from None
    except (ValueError, TypeError, KeyError) as e:  # a constructor's own refusal of an explicit tag
        raise YamlInputError(f"unreadable YAML: {e}") from None


DANGLING_LINK = "a symbolic link that leads to no file (its target is missing, or a loop)"


def leads_nowhere(path: Path) -> bool:
    """Whether `path` is a symbolic link to no file (`exists` follows it; a loop is not resolved)."""
    return path.is_symlink() and not path.exists()


def read(path: str | Path, max_bytes: int = MAX_FILE_BYTES, follow_links: bool = True,
         what: str = "a spec or suite file") -> Any:
    """Parse a file after checking its size. Raises YamlInputError (missing, too large, bad).
    `follow_links` False (a file in a store): a symbolic link is refused, not read."""
    p = Path(path)
    if not follow_links and p.is_symlink():
        raise YamlInputError("a symbolic link, not a file")
    if not p.exists():
        raise YamlInputError(DANGLING_LINK if p.is_symlink() else "file not found")
    if not p.is_file():
        raise YamlInputError("not a file")
    too_large = f"larger than the {max_bytes:,} bytes esr reads from {what}"
    size = p.stat().st_size
    if size > max_bytes:
        raise YamlInputError(f"{size:,} bytes: {too_large}")
    try:  # a FIFO or a link put in the file's place since the checks above is refused, not read
        text = bounded_files.read_bytes(p, max_bytes, follow_links).decode()
    except bounded_files.UnreadableInput as e:
        raise YamlInputError(f"{e} from {what}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise YamlInputError(f"cannot read file: {e}") from None
    return parse(text)
