"""esr human: build a stored Overcooked human, or calibrate candidates against the paper's Random column."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer
from rich.table import Table

from esr_cli.cli.app import BudgetOpt, Exit, SetOpt, app, err, load_spec, out
from esr_cli.common import jsonl
from esr_cli.common.printing import own, printable, tagged
from esr_cli.report.stored_calibrations import COUNTS
from esr_cli.storage.artifacts import ensure
from esr_cli.storage.store import Store

human_app = typer.Typer(no_args_is_help=True, help="Stored Overcooked humans: build one, or calibrate candidates "
                        "against the paper's Random column (docs/overcooked.md).")


app.add_typer(human_app, name="human")


def _stored_human_spec(spec_file: Path, budget: str, sets: Optional[List[str]], store: Store):
    spec = load_spec(spec_file, budget, sets, store)
    from esr_cli.recipes import stored_humans

    if not stored_humans.is_stored(spec.human):
        raise Exit(2, f"{spec_file}: human.kind={spec.human.kind} is not a stored human (bc or ppo)")
    return spec


@human_app.command("build")
def human_build(
    ctx: typer.Context,
    spec_file: Path = typer.Argument(..., help="an Overcooked spec (YAML) whose human is stored (kind bc or ppo)", show_default=False),
    budget: str = BudgetOpt,
    set_: Optional[List[str]] = SetOpt,
):
    """Make (or resume, or find) the spec's human, one per training seed with human.per_seed,
    without training a robot; prints each human's artifact path."""
    spec = _stored_human_spec(spec_file, budget, set_, ctx.obj.store)
    from esr_cli.recipes import stored_humans

    for recipe in stored_humans.human_recipes(spec, err):
        built = ensure(recipe, ctx.obj.store)
        summary = ctx.obj.store.read_manifest(built.path).get("summary", {})
        ret = summary.get("return") or {}
        said = f" ({ret.get('of')}: {ret['mean']:.2f})" if "mean" in ret else ""
        err.print(tagged("cache hit" if built.cached else "built", "green", f": {recipe.name}{said}"), highlight=False)
        out.print(str(built.path), highlight=False)


@human_app.command("calibrate")
def human_calibrate(
    ctx: typer.Context,
    spec_files: List[Path] = typer.Argument(..., help="Overcooked specs (YAML), one per layout, whose human is the "
                                            "candidate (kind bc or ppo)", show_default=False),
    budget: str = BudgetOpt,
    set_: Optional[List[str]] = SetOpt,
    human_seeds: int = typer.Option(COUNTS["human_seeds"][2], "--human-seeds", min=COUNTS["human_seeds"][0],
                                    max=COUNTS["human_seeds"][1], help="humans per layout: seeds human.seed, +1, ..."),
    episodes: int = typer.Option(COUNTS["episodes"][2], "--episodes", min=COUNTS["episodes"][0], max=COUNTS["episodes"][1],
                                 help="episodes of each human with each partner"),
    as_json: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
    markdown: bool = typer.Option(False, "--markdown", help="print a markdown table"),
):
    """Each candidate human with a uniform random robot, a staying robot and itself, per layout
    and human seed, against the paper's Random column; no robot is trained. The humans are
    made first where the store lacks them, and each calibration is stored (kind calibrations): asked
    again, it is read back. The score is the selection rule's (docs/overcooked.md)."""
    if as_json and markdown:
        raise Exit(2, "--json and --markdown: choose one")
    loaded = [_stored_human_spec(f, budget, set_, ctx.obj.store) for f in spec_files]
    from esr_cli.report import human_calibration as hc, stored_calibrations

    problem = stored_calibrations.check_specs(loaded)
    if problem:
        raise Exit(2, problem)
    rows = []
    for s in loaded:
        recipe = stored_calibrations.calibration_recipe(s, human_seeds, episodes, err)
        built = ensure(recipe, ctx.obj.store)
        if built.cached:
            err.print(tagged("cache hit", "green", f": {own(s.name)}'s calibration, {built.path}"), highlight=False)
        row = stored_calibrations.read_row(built.path, s, human_seeds, tuple(recipe.components["humans"]))
        if row is None:
            raise Exit(1, stored_calibrations.damaged(built.path))
        rows.append(row)
    if as_json:
        out.print_json(jsonl.dumps({"rows": [r.as_json() for r in rows], "score": hc.score(rows),
                                   "human_seeds": human_seeds, "episodes": episodes}))
        return
    if markdown:
        out.print(own(hc.markdown(rows, human_seeds, episodes)), highlight=False, markup=False)
        return
    table = Table(title=f"the human with a uniform random, a staying and a self partner ({human_seeds} human(s), "
                        f"{episodes} episodes each; mean ± SE over humans)")
    for col in (*hc.COLUMNS, "in target"):
        table.add_column(col)
    for r in rows:
        inside = hc.within_target(r)
        table.add_row(*map(printable, hc.cells(r)), "-" if inside is None else ("yes" if inside else "no"))
    out.print(table)
    score = hc.score(rows)
    out.print(f"score (mean |ln(random / paper)| over the three paper layouts): {score:.3f}" if score is not None
              else "score: needs one spec on each of cramped_room, coord_ring and asymm_advantages", highlight=False)

