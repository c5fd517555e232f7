"""Result tables inside markdown files, generated from a store (`esr tables`).

A table is written between two HTML comments, the first naming the `esr sweep ... --results
--markdown` command that makes it:

    <!-- esr sweep experiments/suites/NAME.yaml --budget quick --results --markdown --any-code --metric return -->
    (the command's output)
    <!-- end of generated table -->

`esr tables FILE...` replaces each table with what the command gives on the store now, and
`--check` writes nothing and names every table that differs. The command is parsed here, never
run by a shell: only `esr sweep SUITE` with the table's own options is accepted, and anything
else in a block stops with the file and line that holds it. With `--any-code` a table keeps
reading archived runs after the training code changes (their rows name the commit that made
them).
"""

from __future__ import annotations

import difflib
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

from esr_cli.recipes import check_columns
from esr_cli.storage.store import Store

END = "<!-- end of generated table -->"
_START = re.compile(r"^<!-- (esr\s.*) -->$")  # any esr command: one that is not a sweep table is named
MAX_DOC_BYTES = 4 << 20  # a markdown page of this project is tens of KiB
MAX_DIFF_LINES = 60
_CHECK_FLAGS = {c.option: c.name for c in check_columns.REGISTRY.values()}  # flag -> check_columns name
_FLAGS = {"--results", "--markdown", "--any-code", *_CHECK_FLAGS}
_VALUED = {"--budget": "budget", "-b": "budget", "--metric": "metric"}


class TableError(Exception):
    """A block that cannot be generated: `str()` is one line naming the file and line."""


@dataclass(frozen=True)
class Command:
    suite: Path
    budget: str
    metrics: tuple[str, ...]
    checks: tuple[str, ...]  # check_columns names ("exact", "diagnosis", "eval")
    any_code: bool


@dataclass(frozen=True)
class Block:
    path: Path
    line: int  # 1-based line of the opening comment
    command: Command
    start: int  # index of the first line of the table (after the opening comment)
    end: int  # index of the closing comment


def parse_command(text: str, where: str) -> Command:
    """The table's `esr sweep` command, from the opening comment's text."""
    try:
        argv = shlex.split(text)
    except ValueError as e:
        raise TableError(f"{where}: cannot split the command ({e})") from None
    if argv[:2] != ["esr", "sweep"] or len(argv) < 3 or argv[2].startswith("-"):
        raise TableError(f"{where}: a table's command is `esr sweep SUITE --results --markdown ...`")
    suite, options, flags = Path(argv[2]), {"budget": "paper", "metric": []}, set()
    rest = iter(argv[3:])
    for arg in rest:
        if arg in _FLAGS:
            flags.add(arg)
        elif arg in _VALUED:
            value = next(rest, None)
            if value is None or value.startswith("-"):
                raise TableError(f"{where}: {arg} needs a value")
            if _VALUED[arg] == "metric":
                options["metric"].append(value)
            else:
                options["budget"] = value
        else:
            raise TableError(f"{where}: {arg!r} is not an option of a generated table "
                             f"(allowed: {', '.join(sorted(_FLAGS | set(_VALUED)))})")
    missing = {"--results", "--markdown"} - flags
    if missing:
        raise TableError(f"{where}: a generated table needs {' and '.join(sorted(missing))}")
    checks = tuple(name for flag, name in _CHECK_FLAGS.items() if flag in flags)
    return Command(suite, options["budget"], tuple(dict.fromkeys(options["metric"])), checks, "--any-code" in flags)


def read_doc(path: Path) -> list[str]:
    size = path.stat().st_size
    if size > MAX_DOC_BYTES:
        raise TableError(f"{path}: {size:,} bytes, more than a markdown page holds ({MAX_DOC_BYTES:,})")
    try:
        return path.read_text(encoding="utf-8").split("\n")
    except UnicodeDecodeError as e:
        raise TableError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None


def _fenced(lines: list[str]) -> list[bool]:
    """Per line, whether it lies inside a fenced code block (``` or ~~~): an example of the
    comments shown in a page is text, not a table."""
    inside, fence, out = False, "", []
    for line in lines:
        mark = line.lstrip()[:3]
        if mark in ("```", "~~~") and (not inside or mark == fence):
            inside, fence = not inside, mark
            out.append(True)
            continue
        out.append(inside)
    return out


def blocks(path: Path, lines: list[str]) -> list[Block]:
    found, i = [], 0
    fenced = _fenced(lines)
    while i < len(lines):
        m = None if fenced[i] else _START.match(lines[i].rstrip())
        if not m:
            if fenced[i]:
                i += 1
                continue
            if lines[i].strip() == END:
                raise TableError(f"{path}:{i + 1}: {END} without a table's opening comment above it")
            i += 1
            continue
        where = f"{path}:{i + 1}"
        end = next((j for j in range(i + 1, len(lines))
                    if not fenced[j] and (lines[j].strip() == END or _START.match(lines[j].rstrip()))), None)
        if end is None or lines[end].strip() != END:
            raise TableError(f"{where}: the table has no {END} after it")
        found.append(Block(path, i + 1, parse_command(m.group(1), where), i + 1, end))
        i = end + 1
    return found


def generate(command: Command, store: Store, where: str) -> list[str]:
    """The lines `esr sweep SUITE --results --markdown ...` prints for this store."""
    from esr_cli.common import specs
    from esr_cli.recipes import sweep as sw

    try:
        suite = sw.load_suite(command.suite, command.budget)
        metrics = command.metrics or sw.DEFAULT_RESULT_METRICS
        # A page is read from any checkout and store: its commands say `esr` and name spec files
        # from the checkout's root, as the page's own command does.
        rows = sw.results(suite, store, metrics, command.checks, command.any_code, esr="esr", paths_from=Path.cwd())
    except (sw.SuiteError, specs.SpecError) as e:
        raise TableError(f"{where}: {e}") from None
    return sw.results_markdown(suite, rows, metrics, command.checks).split("\n")


def refresh(path: Path, store: Store) -> tuple[list[str], list[str], int]:
    """(the file's lines, the same with every table generated anew, the number of tables)."""
    lines = read_doc(path)
    new = list(lines)
    found = blocks(path, lines)
    for b in reversed(found):  # from the end, so earlier indices stay valid
        new[b.start:b.end] = generate(b.command, store, f"{path}:{b.line}")
    return lines, new, len(found)


def check(paths: list[Path], store: Store) -> list[str]:
    """The differences (unified diff lines) between each file's tables and what the store gives."""
    out = []
    for path in paths:
        lines, new, _ = refresh(path, store)
        if new != lines:
            out += list(difflib.unified_diff(lines, new, str(path), f"{path} (from the store)", n=0, lineterm=""))
    return out[:MAX_DIFF_LINES] + ([f"... {len(out) - MAX_DIFF_LINES} more lines"] if len(out) > MAX_DIFF_LINES else [])


def update(paths: list[Path], store: Store) -> list[tuple[Path, int, bool]]:
    """Rewrite each file whose tables changed: (path, tables, changed) per file."""
    from esr_cli.storage.store import atomic_write_text

    done = []
    for path in paths:
        lines, new, count = refresh(path, store)
        if new != lines:
            atomic_write_text(path, "\n".join(new))
        done.append((path, count, new != lines))
    return done
