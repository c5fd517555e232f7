"""Result tables inside markdown files, generated from a store (`esr tables`).

A table is written between two HTML comments, the first naming the command that makes it:

    <!-- esr sweep experiments/suites/NAME.yaml --budget quick --results --markdown --any-code --metric return -->
    (the command's output)
    <!-- end of generated table -->

The commands a table can name (`COMMANDS`): `esr sweep SUITE --results --markdown ...`, a
suite's runs and what the store holds of them, and `esr human calibrate SPEC... --markdown`,
stored calibrations of Overcooked humans. Either is read from the store only: nothing is
trained or played. `esr tables FILE...` replaces each table with what the command gives on the
store now, and `--check` writes nothing and names every table that differs. The command is
parsed here, never run by a shell: anything but those commands with a table's own options stops
with the file and line that holds it. With `--any-code` a sweep table keeps reading archived
runs after the training code changes (their rows name the commit that made them); a
calibration table always does (report/stored_calibrations.py).
"""

from __future__ import annotations

import difflib
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

from esr_cli.common import bounded_files
from esr_cli.recipes import check_columns
from esr_cli.storage.store import Store

END = "<!-- end of generated table -->"
_START = re.compile(r"^<!-- (esr\s.*) -->$")  # any esr command: one that is not a sweep table is named
_OPENED = re.compile(r"^<!-- esr\s")  # the start of one, closed or not
MAX_DOC_BYTES = 4 << 20  # a markdown page of this project is tens of KiB
MAX_DIFF_LINES = 60
MAX_TABLES = 100  # generated tables in one page; this project's pages hold at most a handful
_CHECK_FLAGS = {c.option: c.name for c in check_columns.REGISTRY.values()}  # flag -> check_columns name
_FLAGS = {"--results", "--markdown", "--any-code", *_CHECK_FLAGS}
_VALUED = {"--budget": "budget", "-b": "budget", "--metric": "metric"}


class TableError(Exception):
    """A block that cannot be generated: `str()` is one line naming the file and line."""


@dataclass(frozen=True)
class SweepTable:
    """`esr sweep SUITE --results --markdown ...`: a suite's runs and their checks."""

    suite: Path
    budget: str
    metrics: tuple[str, ...]
    checks: tuple[str, ...]  # check_columns names ("exact", "diagnosis", "eval")
    any_code: bool

    def lines(self, store: Store, where: str) -> list[str]:
        """The lines `esr sweep SUITE --results --markdown ...` prints for this store."""
        from esr_cli.common import specs
        from esr_cli.recipes import sweep as sw

        try:
            suite = sw.load_suite(self.suite, self.budget)
            metrics = self.metrics or sw.DEFAULT_RESULT_METRICS
            # A page is read from any checkout and store: its commands say `esr` and name spec files
            # from the checkout's root, as the page's own command does.
            rows = sw.results(suite, store, metrics, self.checks, self.any_code, esr="esr", paths_from=Path.cwd())
        except (sw.SuiteError, specs.SpecError) as e:
            raise TableError(f"{where}: {e}") from None
        return sw.results_markdown(suite, rows, metrics, self.checks).split("\n")


@dataclass(frozen=True)
class CalibrationTable:
    """`esr human calibrate SPEC... --markdown`: the stored calibrations of the specs' humans."""

    specs: tuple[Path, ...]
    budget: str
    sets: tuple[str, ...]
    human_seeds: int
    episodes: int

    def command(self) -> str:
        """The `esr human calibrate` line that stores what this table reads (the table's own, as a table)."""
        words = ["human", "calibrate", *map(str, self.specs), "--budget", self.budget,
                 *(w for s in self.sets for w in ("--set", s)),
                 "--human-seeds", str(self.human_seeds), "--episodes", str(self.episodes)]
        return " ".join(["esr", *map(shlex.quote, words)])

    def lines(self, store: Store, where: str) -> list[str]:
        from esr_cli.common import specs
        from esr_cli.recipes import targets
        from esr_cli.report import human_calibration as hc, stored_calibrations
        from esr_cli.storage.store import StoreError

        try:  # as `esr human calibrate` reads them: a played episode's key prefix completed from the store
            loaded = [targets.complete_play_keys(specs.load(path, self.budget, list(self.sets)), store) for path in self.specs]
        except (specs.SpecError, StoreError) as e:
            raise TableError(f"{where}: {e}") from None
        problem = stored_calibrations.check_specs(loaded)
        if problem:
            raise TableError(f"{where}: {problem}")
        rows, other_code = [], []
        for spec in loaded:
            found = stored_calibrations.find(store, spec, self.human_seeds, self.episodes)
            if found is None:
                raise TableError(f"{where}: the store has no calibration of {spec.name}'s human ({hc.describe(spec.human)}, "
                                 f"{self.human_seeds} human(s), {self.episodes} episodes): `{self.command()}` makes it")
            at, commit, same_code = found
            row = stored_calibrations.read_row(at, spec, self.human_seeds)
            if row is None:
                raise TableError(f"{where}: {stored_calibrations.damaged(at)}")
            rows.append(row)
            if not same_code:
                other_code.append(f"{spec.name} (commit {commit or 'unknown'})")
        text = hc.markdown(rows, self.human_seeds, self.episodes).rstrip("\n")
        if other_code:
            text += ("\n\nCalibrated by code other than this checkout's (its humans or their player changed since): "
                     + ", ".join(other_code) + ".")
        return text.split("\n")


def _parse_sweep(argv: list[str], where: str) -> SweepTable:
    if not argv or argv[0].startswith("-"):
        raise TableError(f"{where}: a table's command is `esr sweep SUITE --results --markdown ...`")
    suite, options, flags = Path(argv[0]), {"budget": "paper", "metric": []}, set()
    rest = iter(argv[1:])
    for arg in rest:
        if arg in _FLAGS:
            flags.add(arg)
        elif arg in _VALUED:
            value = _value(arg, rest, where)
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
    return SweepTable(suite, options["budget"], tuple(dict.fromkeys(options["metric"])), checks, "--any-code" in flags)


# `esr human calibrate`'s options a table may give (the counts' bounds are the command's).
_CALIBRATION_VALUED = {"--budget": "budget", "-b": "budget", "--set": "set", "-s": "set",
                       "--human-seeds": "human_seeds", "--episodes": "episodes"}


def _parse_calibration(argv: list[str], where: str) -> CalibrationTable:
    from esr_cli.report.stored_calibrations import COUNTS  # `esr human calibrate`'s own bounds

    spec_files, options, markdown = [], {"budget": "paper", "set": []}, False
    rest = iter(argv)
    for arg in rest:
        if arg == "--markdown":
            markdown = True
        elif arg in _CALIBRATION_VALUED:
            name, value = _CALIBRATION_VALUED[arg], _value(arg, rest, where)
            if name == "set":
                options["set"].append(value)
            elif name in COUNTS:
                least, most, _ = COUNTS[name]
                if not (re.fullmatch(r"[0-9]{1,7}", value) and least <= int(value) <= most):
                    raise TableError(f"{where}: {arg} takes a whole number from {least} to {most:,}, not {value[:40]!r}")
                options[name] = int(value)
            else:
                options[name] = value
        elif arg.startswith("-"):
            raise TableError(f"{where}: {arg!r} is not an option of a calibration table "
                             f"(allowed: --markdown, {', '.join(sorted(_CALIBRATION_VALUED))})")
        else:
            spec_files.append(Path(arg))
    if not spec_files or not markdown:
        raise TableError(f"{where}: a calibration table's command is `esr human calibrate SPEC... --markdown ...`")
    counts = {name: options.get(name, default) for name, (_, _, default) in COUNTS.items()}
    return CalibrationTable(tuple(spec_files), options["budget"], tuple(options["set"]), **counts)


def _value(arg: str, rest, where: str) -> str:
    value = next(rest, None)
    if value is None or value.startswith("-"):
        raise TableError(f"{where}: {arg} needs a value")
    return value


# The commands a table can name: the words that start each, and how the rest is read.
COMMANDS = {("esr", "sweep"): _parse_sweep, ("esr", "human", "calibrate"): _parse_calibration}
Command = SweepTable | CalibrationTable


def parse_command(text: str, where: str) -> Command:
    """The table's command, from the opening comment's text."""
    try:
        argv = shlex.split(text)
    except ValueError as e:
        raise TableError(f"{where}: cannot split the command ({e})") from None
    for words, parse in COMMANDS.items():
        if tuple(argv[:len(words)]) == words:
            return parse(argv[len(words):], where)
    raise TableError(f"{where}: a table's command is `esr sweep SUITE --results --markdown ...` "
                     "or `esr human calibrate SPEC... --markdown`")


@dataclass(frozen=True)
class Block:
    path: Path
    line: int  # 1-based line of the opening comment
    command: Command
    start: int  # index of the first line of the table (after the opening comment)
    end: int  # index of the closing comment


def read_doc(path: Path) -> list[str]:
    """The lines of a markdown page, read bounded (a regular file of at most MAX_DOC_BYTES,
    whatever its size said), without the CR of a page written with CRLF line ends."""
    return read_doc_and_newline(path)[0]


def read_doc_and_newline(path: Path) -> tuple[list[str], str]:
    """(the lines, the line end to write them back with: "\r\n" where every line ends so)."""
    try:
        data = bounded_files.read_bytes(path, MAX_DOC_BYTES, follow_links=True)
    except bounded_files.UnreadableInput as e:
        raise TableError(f"{path}: {e}") from None
    except OSError as e:
        raise TableError(f"{path}: cannot read it: {e.strerror or e}") from None
    try:
        lines = data.decode("utf-8").split("\n")
    except UnicodeDecodeError as e:
        raise TableError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    if len(lines) > 1 and all(line.endswith("\r") for line in lines[:-1]):
        return [line[:-1] for line in lines[:-1]] + lines[-1:], "\r\n"
    return lines, "\n"


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
            if _OPENED.match(lines[i]):  # meant as a table: silently none would pass --check
                raise TableError(f"{path}:{i + 1}: a table's opening comment must end with ' -->' on its own line")
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


def refresh(path: Path, store: Store) -> tuple[list[str], list[str], int]:
    """(the file's lines, the same with every table generated anew, the number of tables)."""
    return _refreshed(path, store)[:3]


def _refreshed(path: Path, store: Store) -> tuple[list[str], list[str], int, str]:
    """refresh's, and the line end the file is written back with."""
    lines, newline = read_doc_and_newline(path)
    new = list(lines)
    found = blocks(path, lines)
    if len(found) > MAX_TABLES:
        raise TableError(f"{path}: {len(found):,} generated tables, more than the {MAX_TABLES} a page may hold")
    made: dict = {}  # a command given twice is read from the store once (commands are frozen values)
    for b in reversed(found):  # from the end, so earlier indices stay valid
        if b.command not in made:
            made[b.command] = b.command.lines(store, f"{path}:{b.line}")
        new[b.start:b.end] = made[b.command]
    return lines, new, len(found), newline


def check(paths: list[Path], store: Store) -> tuple[list[str], list[int]]:
    """The differences (unified diff lines) between each file's tables and what the store gives,
    and how many generated tables each file holds."""
    out, counts = [], []
    for path in paths:
        lines, new, count = refresh(path, store)
        counts.append(count)
        if new != lines:
            out += list(difflib.unified_diff(lines, new, str(path), f"{path} (from the store)", n=0, lineterm=""))
    return out[:MAX_DIFF_LINES] + ([f"... {len(out) - MAX_DIFF_LINES} more lines"] if len(out) > MAX_DIFF_LINES else []), counts


def update(paths: list[Path], store: Store) -> list[tuple[Path, int, bool]]:
    """Rewrite each file whose tables changed: (path, tables, changed) per file. Every file is
    read and its tables made before the first is written: a problem in one leaves all as they were."""
    from esr_cli.storage.store import write_output_file

    made = [(path, *_refreshed(path, store)) for path in paths]
    for path, lines, new, _, newline in made:
        if new != lines:
            write_output_file(path, newline.join(new).encode())
    return [(path, count, new != lines) for path, lines, new, count, _ in made]
