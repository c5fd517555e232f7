"""esr plot: the paper's figures, the estimator and geometry figures, a run's curves."""

from __future__ import annotations

import re

from pathlib import Path
from typing import Optional

import typer

from esr_cli.cli.app import Exit, app, check_budget, check_output_file, draw_preview, err, out, refuse_inside_store
from esr_cli.common.printing import printable, tagged
from esr_cli.recipes import targets
from esr_cli.storage.artifacts import ensure
from esr_cli.storage.store import RUN_KIND, Store, parse_dirname

FIGURE_SUFFIXES = {".png", ".pdf", ".svg", ".jpg", ".jpeg"}  # what matplotlib writes that a reader opens
PAPER_FIGURES = ("gridworld", "overcooked", "no-robot-action", "greedy", "mi", "representations", "filmstrip")


@app.command()
def plot(
    ctx: typer.Context,
    figure: str = typer.Argument(..., help="curve | estimator | geometry | " + " | ".join(PAPER_FIGURES), show_default=False),
    ref: Optional[str] = typer.Argument(None, help="curve: a training run, finished or not; estimator: an exact artifact made with --robot"),
    budget: Optional[str] = typer.Option(None, "--budget", "-b", help="paper figures: paper | quick | smoke (default paper)"),
    gamma: Optional[float] = typer.Option(None, "--gamma", help="geometry: the future-state horizon (default 0.2)"),
    state: Optional[int] = typer.Option(None, "--state", help="geometry: which of the 3 states (default 0)"),
    unfinished: bool = typer.Option(False, "--unfinished", help="paper figures: draw runs still training as far as they "
                                    "have got, marked unfinished (a preview outside the store)"),
    out_file: Optional[Path] = typer.Option(None, "--out", help="curve: the figure to write, its provenance beside it as "
                                            "the same name .json (default: NAME-KEY8-curve.png here); a paper figure with --unfinished: the folder for the preview"),
):
    """Draw a figure from artifacts (never trains; a missing run is named with its command).
    `esr plot curve RUN` draws a run's learning curves as far as it has got, unfinished or not."""
    if figure not in ("curve", "estimator", "geometry", *PAPER_FIGURES):
        raise Exit(2, f"unknown figure {figure!r}; known: curve, estimator, geometry, {', '.join(PAPER_FIGURES)}")
    # Each figure reads some of the options; one it would ignore is a mistake worth naming.
    if ref is not None and figure not in ("estimator", "curve"):
        raise Exit(2, f"esr plot {figure} takes no artifact (got {ref!r}); only `esr plot curve` and `esr plot estimator` read one")
    if unfinished and figure not in PAPER_FIGURES:
        raise Exit(2, f"--unfinished applies to the paper figures ({', '.join(PAPER_FIGURES)}); "
                      "`esr plot curve` draws an unfinished run without it")
    if out_file is not None and figure != "curve" and not unfinished:
        raise Exit(2, f"--out applies to `esr plot curve`, or to a paper figure with --unfinished; not to {figure}")
    if figure == "curve":
        if ref is None:
            raise Exit(2, "esr plot curve needs a training run: its key, a key prefix or its directory (`esr ls`)")
        for value, option in ((budget, "--budget"), (gamma, "--gamma"), (state, "--state")):
            if value is not None:
                raise Exit(2, f"{option} does not apply to `esr plot curve`")
        _plot_curve(ref, out_file, ctx.obj.store)
        return
    if budget is not None and figure not in PAPER_FIGURES:
        raise Exit(2, f"--budget applies to the paper figures ({', '.join(PAPER_FIGURES)}), not to {figure}")
    for value, option in ((gamma, "--gamma"), (state, "--state")):
        if value is not None and figure != "geometry":
            raise Exit(2, f"{option} applies to `esr plot geometry` only, not to {figure}")
    if figure == "estimator":
        if ref is None:
            raise Exit(2, "esr plot estimator needs an exact artifact: make one with `esr exact SPEC --robot RUN`")
        targets.exact_artifact(ctx.obj.store, ref)
    budget = budget or "paper"
    check_budget(budget)
    gamma = 0.2 if gamma is None else gamma
    state = 0 if state is None else state
    if figure == "geometry":
        targets.geometry_options(gamma, state)
    from esr_cli.recipes import exact_runs  # JAX, scipy, matplotlib: after the options are checked

    if figure == "estimator":
        built = ensure(exact_runs.estimator_recipe(ref, ctx.obj.store, err), ctx.obj.store)
        result = built.summary()
        for line in exact_runs.estimator_lines(result):
            err.print(line, highlight=False)
        png = built.path / "estimator.png"
    elif figure == "geometry":
        built = ensure(exact_runs.geometry_recipe(gamma, state), ctx.obj.store)
        result = built.summary()
        err.print(f"3-state MDP, state {state}, gamma {gamma}: capacity I = {result['mutual_information']:.4f} nats "
                  f"(uniform policy: {result['uniform_policy_mi']:.4f})")
        png = built.path / "geometry.png"
    else:  # a paper figure
        from esr_cli.report import figures as figs, paper

        try:
            recipe = paper.figure_recipe(ctx.obj.store, budget, figure, figs.PaperInputs(ctx.obj.store, budget, unfinished=unfinished))
        except figs.MissingRuns as e:
            # (what `make paper-figures` runs, which works outside a checkout too)
            raise Exit(2, f"{e}\nor all at once: {ctx.obj.store.invocation()} paper --budget {budget}", own_lines=True) from None
        if recipe.unfinished:
            draw_preview(recipe, out_file or Path(f"{figure}-{budget}-unfinished"), ctx.obj.store)
            return
        built = ensure(recipe, ctx.obj.store)
        png = built.path / f"{figs.FIGURES[figure][0]}.png"
    err.print(tagged("cache hit" if built.cached else "drawn", "green", f": {png}"))
    out.print(str(png), highlight=False)


_FILE_STEM = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]{0,127}")  # a spec's name as specs allow it, not '.' first


def _file_stem(text: str) -> str:
    """`text` (read from a store) as part of a file name in the current directory: as it is where
    a spec could have named it so, else 'run': a manifest's name never puts a file elsewhere."""
    return text if _FILE_STEM.fullmatch(text) else "run"


def _check_sidecar(sidecar: Path) -> None:
    """The figure's provenance is written beside it as NAME.json: refused before any work where
    that is a folder, or a file that is not an earlier figure's provenance (a user's own JSON is
    never overwritten)."""
    from esr_cli.common import jsonl

    check_output_file(sidecar, "--out")
    if not sidecar.exists() and not sidecar.is_symlink():
        return
    try:
        earlier = jsonl.read_json(sidecar, 1 << 20)  # a provenance is a few hundred bytes
    except (jsonl.JsonInputError, OSError):
        earlier = None
    if not (isinstance(earlier, dict) and isinstance(earlier.get("artifacts"), dict)):
        raise Exit(2, f"--out: {sidecar} exists and is not a figure's provenance, which esr writes there; "
                      "move it or name another --out")


def _plot_curve(ref: str, out_file: Optional[Path], store: Store) -> None:
    """A run's learning curves from its metrics so far; an unfinished run says so in the title."""
    if out_file is not None and out_file.suffix.lower() not in FIGURE_SUFFIXES:  # matplotlib would draw, then refuse it
        raise Exit(2, f"--out: {out_file}: a figure is written as {', '.join(sorted(FIGURE_SUFFIXES))}; name one of those")
    path, record, finished = targets.run_record(store, ref)
    from esr_cli.common import plots
    from esr_cli.report.listing import field
    from esr_cli.storage.finals import read_rows

    rows = read_rows(path)
    if not rows:
        raise Exit(2, f"{path} has no epoch logged yet: nothing to draw")
    total = field(record, "key_components", "spec", "train", "epochs")
    done = rows[-1]["epoch"]
    state = "" if finished else f" (unfinished: epoch {done:,}" + (f" of {total:,})" if total else ")")
    name, key = str(record.get("name", "run")), parse_dirname(path.name)[0]
    out_png = out_file or Path(f"{_file_stem(name)}-{_file_stem(key[:8])}-curve.png")
    refuse_inside_store(out_png, "--out", store)
    check_output_file(out_png, "--out")
    _check_sidecar(out_png.with_suffix(".json"))
    warmup = field(record, "key_components", "spec", "learner", "warmup_epochs") or 0
    method = field(record, "key_components", "spec", "method", "kind")
    title = printable(f"{name} [{method}]{state}" if method else f"{name}{state}")
    plots.learning_curve(rows, out_png, title, {"artifacts": {RUN_KIND: key}, "finished": finished, "epochs": done},
                         warmup_epochs=warmup)
    err.print(tagged("drawn", "green", f": {out_png}" + ("" if finished else f", at epoch {done:,}")))
    out.print(str(out_png), highlight=False)

