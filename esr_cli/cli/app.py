"""The `esr` application, its shared options (--store, --debug, --budget, --set) and the checks several commands share."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

import typer

from esr_cli.common import specs
from esr_cli.common.failures import Failure
from esr_cli.common.printing import plain_console, tagged
from esr_cli.model import spec as spec_model
from esr_cli.recipes import targets
from esr_cli.storage.store import KINDS, Store, nearest_existing, probe_writable


def _flag_type_hidden(display_type_rich):
    """Typer's help names a flag's type ("--json <bool>") as if it took a value; a flag takes
    none, so its row shows the flag alone."""

    def display(self, ctx):
        return None if getattr(self, "is_flag", False) else display_type_rich(self, ctx)

    return display


typer.core.TyperOption.display_type_rich = _flag_type_hidden(typer.core.TyperOption.display_type_rich)


app = typer.Typer(
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
    add_completion=False,
    help="Experiments on assistive agents: ESR and baselines, with a content-addressed artifact store.",
)


out = plain_console()
err = plain_console(stderr=True)


class Exit(Failure):
    """A command's own ending: `code` and the line to print (none: nothing to add); with
    own_lines, esr's own text over several lines, printed with its newlines."""

    def __init__(self, code: int, message: str = "", own_lines: bool = False):
        super().__init__(message)
        self.exit_code, self.message, self.own_lines = code, message, own_lines

    def one_line(self) -> str:
        return self.message


@dataclass(frozen=True)
class Options:
    """What every command shares (--store, --debug), kept in the CLI library's context for the
    command being run rather than in module state."""

    store: Store
    debug: bool


StoreOpt = typer.Option(None, "--store", help="artifact store root (default: $ESR_STORE or ./artifacts)")
BudgetOpt = typer.Option("paper", "--budget", "-b", help="paper | quick | smoke")
SetOpt = typer.Option(None, "--set", "-s", help="override a spec field: key.path=value (repeatable)")


def _print_version(asked: bool) -> None:
    """`esr --version`: the package's version, the training code's digest (part of every run's
    key: runs continue and pool only under the same one) and the checkout's commit, if any."""
    if not asked:
        return
    from importlib import metadata

    from esr_cli.storage import provenance

    git = provenance.git_state()
    line = f"esr-cli {metadata.version('esr-cli')}; training code {provenance.code_digest()[:8]}"
    if git["commit"]:
        line += f"; commit {git['commit'][:12]}" + (" (esr_cli/ modified)" if git["dirty"] else "")
    out.print(line, highlight=False)
    raise typer.Exit()


@app.callback()
def main_options(
    ctx: typer.Context,
    store: Optional[str] = StoreOpt,  # text, not Path: Path("") would silently mean the current directory
    debug: bool = typer.Option(False, "--debug", help="show tracebacks"),
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="print the version, the training code's digest and the commit, and exit"),
):
    from esr_cli.storage.provenance import compile_cache_dir, matmul_precision

    if store is not None and not store.strip():
        raise Exit(2, "--store: an empty path; give the store's directory (or leave --store out for $ESR_STORE or ./artifacts)")
    ctx.obj = Options(Store(store or os.environ.get("ESR_STORE") or "artifacts"), debug)
    for left in ctx.obj.store.remove_abandoned_imports():  # each command tidies what a killed import left
        err.print(f"removed the staging folder a killed `esr import` left: {left}")
    # Several esr processes may share one GPU (runs side by side, a sweep's local jobs, which
    # inherit this): by default JAX takes 75% of the device for the first and the next fails.
    # esr's programs need a few hundred MiB; setting the variable yourself overrides this.
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    try:
        matmul_precision()  # a bad setting stops every command before any work
        compile_cache_dir()
    except ValueError as e:
        raise Exit(2, str(e)) from None


def refuse_spec_options(target: str, budget: str, sets: Optional[List[str]]) -> None:
    """A trained run's spec and budget are fixed: --set and --budget beside its key or path
    would silently change nothing."""
    for given, option in ((sets, "--set"), (budget != "paper", "--budget")):
        if given:
            raise Exit(2, f"{option} applies to a spec file target only; {target} is not a spec file but a "
                          "run's key or path, whose spec and budget are fixed (name the spec file instead)")


def load_spec(path: Path, budget: str, sets: Optional[List[str]], store: Store):
    """The spec, with any played-episode key prefix in it completed from the store. An unknown
    budget is the option's mistake, named as such (not the spec file's)."""
    check_budget(budget)
    return targets.complete_play_keys(specs.load(path, budget, list(sets or [])), store)


_DURATION_UNITS = {"": 1.0, "s": 1.0, "m": 60.0, "h": 3600.0}
MAX_DURATION_S = 366 * 24 * 3600.0


def parse_duration(text: str, option: str) -> float:
    """'90', '90s', '9m', '1.5h' -> seconds; anything else (negative, not finite, over a year)
    is a usage error naming the option."""
    t = text.strip().lower()
    unit = t[-1:] if t[-1:] in ("s", "m", "h") else ""
    try:
        seconds = float(t[: len(t) - len(unit)]) * _DURATION_UNITS[unit]
    except ValueError:
        seconds = float("nan")
    if not 0.0 <= seconds <= MAX_DURATION_S:  # also false for nan
        raise Exit(2, f"{option}: expected a duration such as 90s, 9m or 1.5h (at most a year), got {text!r}")
    return seconds


def quick_spec(path: Path, sets: Optional[List[str]]):
    """The spec at --budget quick, whose time a run estimates beside its own; None where the
    --set values do not fit it."""
    try:
        return specs.load(path, "quick", list(sets or []))
    except specs.SpecError:
        return None


def check_budget(budget: str) -> None:
    if budget not in spec_model.BUDGETS:
        raise Exit(2, f"--budget: unknown budget {budget!r}; known: {', '.join(spec_model.BUDGETS)}")


def check_executor(executor: str, known: tuple[str, ...]) -> None:
    if executor not in known:
        raise Exit(2, f"--executor: unknown executor {executor!r}; known: {', '.join(known)}")


def refuse_inside_store(path: Path, option: str, store: Store) -> None:
    """An output file must not land in the store's artifact folders: inside an artifact it would be
    a file its manifest does not list (`esr verify` fails it), and a committed artifact never changes."""
    # Where the file really lands: links followed, and a `..` after folders yet to be made taken
    # as the kernel will take it once they are made (`new/../runs` is `runs`).
    here = Path(os.path.realpath(path)).parent
    for kind in KINDS:
        folder = (store.root / kind).resolve()
        if here == folder or folder in here.parents:
            raise Exit(2, f"{option}: {path} lies inside the store's {kind}/ folder; write it outside the store's artifacts")


def check_output_file(path: Path, option: str) -> None:
    """Refuse, before any work, an output path that cannot become a file: a directory, or one
    below an existing file."""
    if path.is_dir():
        raise Exit(2, f"{option}: {path} is a directory; name a file")
    if path.exists() and not path.is_file():  # written through a link as a shell's `>` would; never replaced
        raise Exit(2, f"{option}: {path} exists and is not a regular file (a device, pipe or socket); name a file")
    # The folder the file is really written in: a link's target's (write_output_file follows it).
    parent = nearest_existing(Path(os.path.realpath(path)).parent)
    if not parent.is_dir():
        raise Exit(2, f"{option}: {parent} is a file, not a directory")
    try:
        probe_writable(parent)
    except OSError as e:
        raise Exit(2, f"{option}: cannot write in {parent}: {e.strerror or e}") from None


def draw_preview(recipe, out_dir: Path, store: Store, print_path: bool = True) -> None:
    """A figure that reads unfinished runs, drawn into `out_dir` outside the store (it would
    change as they train, so it is never an artifact); its PNG is named on stderr (and printed
    on stdout with `print_path`)."""
    from esr_cli.storage.artifacts import preview

    if out_dir.exists() and not out_dir.is_dir():
        raise Exit(2, f"--out: {out_dir} is a file; name a folder")
    refuse_inside_store(out_dir / "x", "--out", store)
    check_output_file(out_dir / "x", "--out")
    summary = preview(recipe, out_dir, store)
    png = next((out_dir / f for f in summary.get("files", []) if f.endswith(".png")), None) or next(out_dir.glob("*.png"))
    err.print(tagged("drawn", "green", f": {png}", f"  (a preview of unfinished runs: {'; '.join(recipe.unfinished)})"))
    if print_path:
        out.print(str(png), highlight=False)
