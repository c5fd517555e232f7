"""How esr prints to a terminal, and the command lines it prints for a person to paste.

Consoles print text as written: a store path, spec name, suite label, participant or error
message that looks like rich markup (`[bold]`, `[/x]`) is neither styled away nor a crash, and a
path printed for scripts to read is the path. The one exception is a control character (an
escape sequence, a bidirectional override, a newline, a tab): names, keys, messages and paths
read from a store, an archive or a played episode can hold any, so every text a console prints,
a table's cells and titles included, shows them as escapes (`printable`), and JSON is printed in
ASCII. A newline is escaped too: a file named `x\nok FORGED` would otherwise print a line esr
never wrote. esr's own text of several lines (a report in markdown, a hint below an error) is
printed with its newlines as `own(text)`. Style is added explicitly, as `Text` spans (`tagged`
escapes the text beside its tag), so a new print site is safe without escaping anything; a
`Text` made elsewhere is printed as it is made.
"""

from __future__ import annotations

import shlex
import unicodedata

from rich.console import Console
from rich.text import Text


class _EscapingConsole(Console):
    """Every str printed (directly, or as a table's cell, title or caption) goes through
    `render_str`: there its control characters become escapes, before its width is measured."""

    def render_str(self, text: str, **options) -> Text:
        return super().render_str(printable(text), **options)

    def print_json(self, json: str | None = None, **options) -> None:
        # rich writes JSON text as it is, \u202e included; in ASCII every such character is an escape
        super().print_json(json, **{**options, "ensure_ascii": True})


def plain_console(stderr: bool = False) -> Console:
    """A console that never reads markup in the text it prints, nor folds a long line (a path
    stays one piece to copy; the terminal wraps it), and shows control characters as escapes."""
    return _EscapingConsole(stderr=stderr, markup=False, soft_wrap=True)


def print_table(console: Console, table) -> None:
    """`table` on `console`; off a terminal (piped, redirected) as wide as its cells need, so
    that no cell is cut to the 80 columns a pipe reports."""
    if console.is_terminal:
        console.print(table)
        return
    width = console.width
    console.width = max(width, console.measure(table, options=console.options.update(width=100_000)).maximum)
    try:
        console.print(table)
    finally:
        console.width = width


def tagged(tag: str, style: str, *rest: str | Text) -> Text:
    """`tag` in `style`, then `rest` as written but for control characters (`printable`):
    tagged("ok", "green", " ", str(path)); a `Text` in `rest` (`own`) is kept as it is made."""
    return Text.assemble((tag, style), *(r if isinstance(r, Text) else printable(r) for r in rest))


def train_line(esr: str, spec_path, budget: str, sets, command: str = "train", extra=()) -> str:
    """`esr train` (or another command over a spec) as a shell line to paste: each word quoted
    where the shell would change it (`train.seeds=[1]` is a glob; a value may hold a quote or a
    space)."""
    words = [command, str(spec_path), "--budget", budget, *(w for s in sets for w in ("--set", s)), *extra]
    return " ".join([esr, *map(shlex.quote, words)])


def printable(text: str, keep: str = "") -> str:
    """`text` with every control character except those in `keep` shown as an escape (\\x1b,
    \\u202e, \\n, \\t): names, keys and messages read from a store or archive never drive the
    terminal, nor start a line of their own. Only esr's own text keeps its newlines (`own`)."""
    return "".join(c if c in keep or (c.isprintable() and not unicodedata.category(c).startswith("C"))
                   else c.encode("unicode_escape").decode("ascii") for c in text)


def own(text: str) -> Text:
    """esr's own text of several lines (a table in markdown, JSON it indents, a hint below an
    error), printed with its newlines and tabs; any other control character is still an escape.
    Nothing read from a store, an archive or a played episode belongs in it unescaped."""
    return Text(printable(text, keep="\n\t"))
