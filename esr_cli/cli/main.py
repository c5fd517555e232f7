"""The `esr` command line: parse, call, render. Progress and messages go to stderr; stdout
carries results (artifact paths, tables). Exit codes: 0 success (a cache hit is success),
1 a failed run, 2 bad usage or a bad spec, 75 stopped at `--stop-after` or a sweep job's time budget (resumable), 130
interrupted (resumable)."""

from __future__ import annotations

import errno
import inspect
import os
import signal
import sys
import threading

from esr_cli.cli import figures, humans, play, runs, store, sweeps  # noqa: F401 (each registers its commands on the app)
from esr_cli.cli.app import app, err
from esr_cli.common.failures import Failure
from esr_cli.common.printing import own, tagged
from esr_cli.runner.stop_signals import StopSignals, Terminated, stop_signals_raise

# `esr --help` lists the commands in the order of a study: train and examine, run suites, draw,
# look into the store, play.
HELP_ORDER = ("train", "eval", "exact", "diagnose", "ablate", "sweep", "paper", "plot", "ls", "show", "verify", "export",
              "import", "play", "plays")


def _help_place(command) -> int:
    name = command.name or command.callback.__name__
    return HELP_ORDER.index(name) if name in HELP_ORDER else len(HELP_ORDER)  # a new command: last


app.registered_commands.sort(key=_help_place)


def _one_line(command) -> None:
    """The command list shows a docstring's first paragraph as one line, wrapped to the
    terminal, not with the line breaks of its source."""
    doc = inspect.getdoc(command.callback) or ""
    if command.short_help is None and "\n" in doc.split("\n\n")[0]:
        command.short_help = " ".join(doc.split("\n\n")[0].split())


for _command in [*app.registered_commands, *(c for g in app.registered_groups for c in g.typer_instance.registered_commands)]:
    _one_line(_command)

GLOBAL_FLAGS, GLOBAL_VALUED = ("--debug",), ("--store",)


def global_options_first(argv: list[str]) -> list[str]:
    """Options shared by every command (--store DIR, --debug) may come before or after the
    command (`esr exact SPEC --store DIR`): they are moved in front of it. Nothing after `--`
    is touched."""
    head, rest, i = [], [], 0
    while i < len(argv):
        a = argv[i]
        if a == "--":
            rest += argv[i:]
            break
        if a in GLOBAL_FLAGS or any(a.startswith(o + "=") for o in GLOBAL_VALUED):
            head.append(a)
        elif a in GLOBAL_VALUED and i + 1 < len(argv):
            head += [a, argv[i + 1]]
            i += 1
        else:
            rest.append(a)
        i += 1
    return head + rest


def main(argv: list[str] | None = None) -> int:
    argv = global_options_first(sys.argv[1:] if argv is None else list(argv))
    debug = "--debug" in argv
    with stop_signals_raise() as stops:  # any command ends with its cleanup and one line (esr_cli/runner/stop_signals.py)
        return _run(argv, debug, stops)


def _run(argv: list[str], debug: bool, stops: StopSignals) -> int:
    from esr_cli.common.stops import Interrupted

    try:
        code = app(args=argv, standalone_mode=False)
        if code == 130:  # the CLI library hands back Ctrl-C inside a command (cleanup done) as this code
            raise KeyboardInterrupt
        return code if isinstance(code, int) else 0
    except KeyboardInterrupt:  # Ctrl-C, handed back as above or outside the CLI library (while importing, say)
        return _stopped(signal.SIGINT)
    except Terminated:  # a BaseException, so not among the failures below
        return _stopped(signal.SIGTERM)
    except SystemExit as e:  # typer/click's own exits (e.g. --help)
        return int(e.code or 0)
    except Exception as e:  # noqa: BLE001 - every failure becomes one line unless --debug
        if stops.received is not None and not isinstance(e, Interrupted):  # the stop, wrapped by a library
            return _stopped(stops.received)
        if debug:
            raise
        if type(e).__name__ == "Abort":  # the CLI library's Ctrl-C at a prompt
            err.print("aborted")
            return 130
        if hasattr(e, "format_message") and hasattr(e, "exit_code"):  # the CLI library's usage errors: one line too
            where = getattr(getattr(e, "ctx", None), "command_path", None) or "esr"
            err.print(tagged("error:", "red", " ", f"{' '.join(e.format_message().split())} (`{where} --help`)"), highlight=False)
            return int(e.exit_code) if e.exit_code else 2
        if isinstance(e, Failure):  # each says its exit code and its line (esr_cli/common/failures.py)
            code, msg = e.exit_code, e.one_line()
        elif isinstance(e, OSError) and e.errno == errno.ENAMETOOLONG:  # a path given on the command line
            name = str(e.filename or "")
            code, msg = 2, f"file name too long: {name[:60]}{'...' if len(name) > 60 else ''} (at most 255 bytes per component)"
        else:
            code, msg = 1, f"{type(e).__name__}: {e} (run with --debug for a traceback)"
        if msg and getattr(e, "on_purpose", False):  # a stop asked for (exit 75): no error
            err.print(msg, highlight=False)
        elif msg:
            own_lines = isinstance(e, Failure) and e.own_lines  # esr's hint below the error, not a name from a store
            err.print(tagged("error:", "red", " ", own(msg) if own_lines else msg), highlight=False)
        return code


def _stopped(signum: int) -> int:
    """The one line and exit code of a command stopped by Ctrl-C or SIGTERM outside training."""
    if signum == signal.SIGINT:
        err.print("interrupted")
        return 130
    err.print(tagged("error:", "red", " terminated (SIGTERM)"), highlight=False)
    return 143


STOPPED_BY_SIGNAL = (130, 143)


def _quiet_at_shutdown(args) -> None:
    """threading.excepthook: a library's background thread (orbax's checkpoint signalling) that
    finds the interpreter's executors already shut down, once the command has said its last
    line, ends without a traceback; any other thread's failure is reported as always."""
    if isinstance(args.exc_value, RuntimeError) and "cannot schedule new futures after" in str(args.exc_value):
        return
    threading.__excepthook__(args)


def entry() -> None:
    threading.excepthook = _quiet_at_shutdown
    code = main()
    if code in STOPPED_BY_SIGNAL:
        # Everything esr does on the way out (removing an unfinished artifact, saving a run) is
        # done. Tearing the interpreter down while an XLA program the signal cut short is still
        # running can crash it (SIGSEGV), so a stopped command leaves at once.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    entry()
