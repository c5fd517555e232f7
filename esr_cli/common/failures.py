"""The failures a command ends with: each says its own exit code and one line for the terminal,
so the CLI maps an exception to its ending by asking it, not by a list of kinds.

Exit codes (docs/reliability.md): 1 a failed run, 2 bad usage or input, 75 stopped at a time
limit, 130 / 143 stopped by Ctrl-C / SIGTERM.
"""

from __future__ import annotations


class Failure(Exception):
    """An expected way for a command to end. `exit_code`: the process's; `one_line()`: what the
    terminal is told after "error:" (an empty line: nothing more to say)."""

    exit_code: int = 1
    # True where `one_line()` is esr's own text over several lines (a hint below the error),
    # printed with its newlines; otherwise a newline in it (a name from a store) is an escape.
    own_lines: bool = False

    def one_line(self) -> str:
        return str(self)
