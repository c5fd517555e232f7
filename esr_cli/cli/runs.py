"""Commands that train and examine runs: esr train, eval, exact, diagnose, ablate."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer
from rich.table import Table

from esr_cli.cli.app import BudgetOpt, Exit, SetOpt, app, check_budget, err, load_spec, out, parse_duration, quick_spec, refuse_spec_options
from esr_cli.common import jsonl, specs
from esr_cli.common.printing import tagged
from esr_cli.model import spec as spec_model
from esr_cli.recipes import targets
from esr_cli.recipes.diagnosis_runs import Options as DiagnosisOptions
from esr_cli.recipes.targets import MAX_SAMPLE_PAIRS, MIN_SAMPLE_PAIRS
from esr_cli.storage.artifacts import ensure, summary_or_empty
from esr_cli.storage.store import parse_dirname


@app.command()
def train(
    ctx: typer.Context,
    spec_file: Path = typer.Argument(..., help="experiment spec (YAML)", show_default=False),
    budget: str = BudgetOpt,
    set_: Optional[List[str]] = SetOpt,
    stop_after: Optional[str] = typer.Option(
        None, "--stop-after", help="stop at the last chunk boundary before this much time has passed "
        "(90s, 9m, 1.5h), saved and resumable, exit 75; for a job or machine with a time limit"),
    wandb: bool = typer.Option(
        False, "--wandb", help="also log to Weights & Biases in offline mode, in STORE/wandb/KEY (`wandb sync` "
        "uploads it; needs the wandb extra)"),
):
    """Train a spec (all its seeds in one program); a finished spec is a cache hit."""
    import importlib.util
    import time

    if wandb and importlib.util.find_spec("wandb") is None:
        raise Exit(2, "--wandb needs the wandb package: pip install 'esr-cli[wandb]' (or pip install wandb)")

    # the limit counts from the command's start, as a scheduler's or a lent machine's does
    stop_at = None if stop_after is None else time.monotonic() + parse_duration(stop_after, "--stop-after")
    spec = load_spec(spec_file, budget, set_, ctx.obj.store)
    quick = quick_spec(spec_file, set_) if budget != "quick" else None
    from esr_cli.recipes import runs  # JAX and the training code: after the spec is known to be good

    recipe = runs.run_recipe(spec, err, stop_at=stop_at, quick=quick, wandb=wandb)
    if ctx.obj.store.lookup(recipe.kind, recipe.key) is None:
        _note_run_made_elsewhere(spec, ctx.obj.store)
    built = ensure(recipe, ctx.obj.store)
    path, cached = built.path, built.cached
    err.print(tagged("cache hit" if cached else "trained", "green", f": {spec.name} ({spec.budget}) -> {path}"))
    out.print(str(path), highlight=False)


def _note_run_made_elsewhere(spec, store) -> None:
    """Keys name the training code: after the checkout's code changes, the store's run of this
    very spec is not this one. Say so before training it again, perhaps for hours."""
    from esr_cli.recipes.sweep import finished_elsewhere

    found = finished_elsewhere(spec, store)
    if found:
        key, _, where = found
        err.print(f"note: {key[:12]} in this store is a finished run of this spec, budget and seeds made by other "
                  f"code ({where}); this code trains it again (`esr sweep --results --any-code` reads that one)")


@app.command("eval")
def eval_(
    ctx: typer.Context,
    target: str = typer.Argument(..., help="a spec file or a training-run artifact (key or path)", show_default=False),
    budget: str = typer.Option("paper", "--budget", "-b", help="paper | quick | smoke (a spec file target only)"),
    set_: Optional[List[str]] = typer.Option(None, "--set", "-s", help="override a spec field: key.path=value "
                                             "(repeatable; a spec file target only)"),
    episodes: Optional[int] = typer.Option(None, "--episodes", "-n", help="episodes per seed and policy (default: spec eval.episodes)"),
    human: str = typer.Option("training", "--human", help="training: the human the robot trained with | proxy: a BC "
                              "human cloned from the held-out test split of the human data | play:KEY,KEY,...: a BC "
                              "human cloned from played episodes (`esr plays`) (Overcooked)"),
    seat: Optional[int] = typer.Option(None, "--seat", help="Overcooked: the JaxMARL agent the robot plays (default: "
                                       "its training seat; 1 flips the seats)"),
):
    """Evaluate a trained robot with its human; writes an evaluation artifact, a GIF and a curve."""
    targets.check_partner_name(human)
    most = spec_model.MAX_EVAL_EPISODES
    if episodes is not None and not 1 <= episodes <= most:
        raise Exit(2, f"--episodes: between 1 and {most:,} (got {episodes:,})")
    spec_file = targets.is_spec_file(target)
    if spec_file:  # options that cannot fit the spec are named before "not trained yet"
        spec = load_spec(Path(target), budget, set_, ctx.obj.store)
    else:
        refuse_spec_options(target, budget, set_)
        run_path = targets.stored_run(ctx.obj.store, target)
        spec = targets.run_spec(run_path)
    targets.partner_spec(targets.seat_spec(spec, seat)[0], human)  # a play human fits this run: then its keys
    human = targets.complete_play_partner(ctx.obj.store, human)
    from esr_cli.common.stats import format_summary  # scipy: +0.9 s, only where a table needs it
    from esr_cli.recipes import runs  # JAX and the training code: after the options are checked

    if spec_file:
        run_path = runs.committed_run(spec, runs.train_command(target, budget, set_, ctx.obj.store), ctx.obj.store)
    built = ensure(runs.eval_recipe(run_path, ctx.obj.store, episodes, err, human, seat), ctx.obj.store)
    path, summary, cached = built.path, built.summary(), built.cached
    partner = "" if human == "training" else f", with the {human.split(':')[0]} human {summary['human_key'][:8]}"
    if seat is not None and summary.get("robot_seat") is not None:
        partner += f", robot as agent_{summary['robot_seat']}"
    table = Table(title=f"{summary['name']} ({summary['budget']}, {len(summary['seeds'])} seed(s), {summary['episodes']} episodes each{partner})")
    for col in ("policy", "return (mean ± SE; IQM [95% CI] across seeds)", "success"):
        table.add_column(col)
    for mode, r in summary["results"].items():
        table.add_row(mode, format_summary(r["return"]), format_summary(r["success"], 3))
    err.print(table)
    err.print(tagged("cache hit" if cached else "evaluated", "green", f": {path}"))
    for name in ("rollout.gif", "learning_curve.png"):
        if (path / name).exists():
            err.print(f"  {name}: {path / name}")
    out.print(str(path), highlight=False)


@app.command()
def exact(
    ctx: typer.Context,
    spec_file: Path = typer.Argument(..., help="a gridworld spec (YAML)", show_default=False),
    budget: str = BudgetOpt,
    set_: Optional[List[str]] = SetOpt,
    robot: Optional[str] = typer.Option(None, "--robot", help="a training run (key or path) whose Boltzmann policy the robot follows; default uniform"),
    goal: Optional[str] = typer.Option(None, "--goal", help="the human's goal cell 'row,col' (default: the centre)"),
    gamma: Optional[float] = typer.Option(None, "--gamma", help="future-state horizon (default: the spec's method.future_gamma)"),
    seed_index: Optional[int] = typer.Option(None, "--seed-index", help="which seed of --robot's run (default 0)"),
    sample_pairs: int = typer.Option(0, "--sample-pairs", min=0, max=MAX_SAMPLE_PAIRS, help="where the space is too "
                                     "large for every pair: also compute this many pairs drawn uniformly from all, for "
                                     "`esr plot estimator`'s rank correlation over all pairs (not counted in the "
                                     "effective empowerment)"),
):
    """Exact effective empowerment of a small gridworld: I(aH; s+ | s, aR) for every state."""
    if seed_index is not None and robot is None:
        raise Exit(2, "--seed-index applies to --robot's run only (a uniform robot has no seeds)")
    if sample_pairs and robot is None:
        raise Exit(2, "--sample-pairs serves `esr plot estimator`, which needs a trained ESR robot: give --robot")
    if 0 < sample_pairs < MIN_SAMPLE_PAIRS:
        raise Exit(2, f"--sample-pairs {sample_pairs}: a rank correlation with an interval needs at least "
                      f"{MIN_SAMPLE_PAIRS} pairs (or 0 for none)")
    spec = load_spec(spec_file, budget, set_, ctx.obj.store)
    cell = None
    if goal is not None:
        try:
            cell = tuple(int(v) for v in goal.split(","))
            assert len(cell) == 2
        except (ValueError, AssertionError):
            raise Exit(2, f"--goal: expected 'row,col', got {goal!r}") from None
    targets.exact_target(spec, ctx.obj.store, cell, gamma, robot, seed_index or 0)
    from esr_cli.recipes import exact_runs  # JAX and the analysis: after the options are checked

    built = ensure(exact_runs.exact_recipe(spec, ctx.obj.store, cell, gamma, robot, seed_index or 0, err, sample_pairs),
                   ctx.obj.store)
    path, summary, cached = built.path, built.summary(), built.cached
    table = Table(title=f"exact empowerment: {spec.name}, goal {tuple(summary['goal'])}, gamma {summary['gamma']}")
    table.add_column("quantity")
    table.add_column("value")
    for k in ("states", "effective_empowerment", "mean_mi_visited", "mean_mi_visited_merged_actions", "mean_mi_uniform_states",
              "max_mi", "states_with_zero_mi", "pairs", "pairs_computed", "sample_pairs"):
        if k not in summary:  # made by an earlier version
            continue
        v = summary[k]
        table.add_row(k, f"{v:.4f}" if isinstance(v, float) else "— (not every pair computed)" if v is None else str(v))
    err.print(table)
    err.print(tagged("cache hit" if cached else "computed", "green", f": {path}"))
    out.print(str(path), highlight=False)


@app.command()
def diagnose(
    ctx: typer.Context,
    run: str = typer.Argument(..., help="a training run (key, key prefix or path), finished or not", show_default=False),
    seed_index: int = typer.Option(0, "--seed-index", help="which seed of the run"),
    batches: int = typer.Option(DiagnosisOptions().batches, "--batches", min=1, max=10_000, help="critic batches to score"),
    episodes: int = typer.Option(DiagnosisOptions().episodes, "--episodes", min=1, max=1024,
                                 help="episodes each robot plays for the play check"),
    refit: int = typer.Option(DiagnosisOptions().refit, "--refit", min=0, max=100_000, help="ESR: also fit fresh representations to each robot's "
                              "play for this many updates and compare their MI estimates (0: off)"),
    as_json: bool = typer.Option(False, "--json", help="print JSON instead of tables"),
):
    """Why a robot helps or not: its own reward on its play against a uniform robot's, and on
    the gridworld its reward by the human's situation and its critic and policy at a few
    distinct start states. An unfinished run is read at its newest checkpoint. A finished run's
    diagnosis is stored (`esr sweep --results --diagnose` reads it back); an unfinished run's is not."""
    path, record, finished = targets.run_record(ctx.obj.store, run)
    if not 0 <= seed_index < len(record["seeds"]):
        raise Exit(2, f"--seed-index: the run has {len(record['seeds'])} seed(s)")
    method = targets.run_spec(path).method.kind
    if refit and method != "esr":
        raise Exit(2, f"--refit fits ESR's representations; this run's method is {method}")
    if refit and episodes < 2:
        raise Exit(2, "--refit holds one episode in four out of the fit: give --episodes 2 or more")
    from esr_cli.recipes import diagnosis_runs as dr  # JAX and the training code: after the options are checked

    options = dr.Options(batches=batches, episodes=episodes, refit=refit)
    run_key = parse_dirname(path.name)[0]
    if finished:  # stored: a table reads it back, and the same diagnosis again is a cache hit
        built = ensure(dr.diagnosis_recipe(ctx.obj.store, path, seed_index, options), ctx.obj.store)
        report = summary_or_empty(built.path)
        if not report:
            raise Exit(1, f"{built.path}: its summary.json cannot be read as a diagnosis; `{ctx.obj.store.invocation()} verify {built.path.name[:12]}` "
                          "says why (remove the folder to compute it again)")
        err.print(tagged("cache hit" if built.cached else "computed", "green", f": {built.path}"))
    else:  # an unfinished run changes with every chunk: shown, never stored
        from esr_cli.recipes.runs import load_run_so_far

        trainer, state, epoch = load_run_so_far(ctx.obj.store, path, finished)
        report = dr.compute(trainer, state, epoch, seed_index, options, False, run_key)
    if as_json:
        out.print_json(jsonl.dumps(report))
        return
    when = "" if finished else f", unfinished: checkpoint at epoch {report['epoch']:,} of {report['epochs']:,}"
    out.print(f"{record['name']} ({record['budget']} budget, {method}), seed index {seed_index}{when}")
    if isinstance(report.get("play"), dict):
        _print_play_check(report["play"])
    elif method in spec_model.POLICY_FREE_METHODS:
        out.print(f"{method} learns no robot policy: no play check")
    else:
        out.print("the stored diagnosis holds no play check")
    if isinstance(report.get("reward"), dict):  # a gridworld run
        _print_gridworld_diagnosis(report)


def _at_absent(tree: dict, outer: str, inner: str) -> bool:
    """No `inner` field under `outer`: a method whose reward has no MI estimate (not a damaged one)."""
    return not isinstance(tree.get(outer), dict) or inner not in tree[outer]


def _print_play_check(play: dict) -> None:
    """The play check of a diagnosis, computed or read from the store (every field read typed:
    a damaged one prints as '—')."""
    from esr_cli.recipes.diagnosis_lookup import count, fmt, number

    table = Table(title="the run's reward on its robot's play and on a uniform robot's (same human)")
    sides = [(player, play[player]) for player in ("robot", "uniform") if isinstance(play.get(player), dict)]
    refit = bool(sides) and all(isinstance(r.get("refit"), dict) for _, r in sides)
    columns = ["robot", "episodes", "return", "reward: mean", "sd", "MI estimate (nats)", "steps the human moves"]
    for col in columns + (["refit MI: fit", "held out"] if refit else []):
        table.add_column(col)
    for player, r in sides:
        episodes = count(r, "episodes")
        cells = [player, "—" if episodes is None else str(episodes), fmt(number(r, "return"), ".2f"),
                 fmt(number(r, "reward", "mean"), "+.3f"), fmt(number(r, "reward", "sd"), ".3f"),
                 "" if _at_absent(r, "reward", "mi_estimate") else fmt(number(r, "reward", "mi_estimate"), "+.4f"),
                 fmt(number(r, "human_moves"), ".3f")]
        if refit:
            cells += [fmt(number(r, "refit", "fit"), "+.4f"), fmt(number(r, "refit", "held_out"), "+.4f")]
        table.add_row(*cells)
    out.print(table)


def _print_gridworld_diagnosis(report: dict) -> None:
    from esr_cli.analysis import diagnose as dg
    from esr_cli.recipes.diagnosis_lookup import count, fmt, number

    def n(*path, tree=report) -> str:
        v = count(tree, *path)
        return "—" if v is None else str(v)

    table = Table(title="reward by the human's situation (the run's buffer)")
    for col in ("situation", "transitions", "mean reward", "sd"):
        table.add_column(col)
    for name in dg.SITUATIONS:
        table.add_row(name, n("reward", name, "n"), fmt(number(report, "reward", name, "mean"), ".3f"),
                      fmt(number(report, "reward", name, "sd"), ".3f"))
    out.print(table)
    n_free, n_trapped = count(report, "reward", "free", "n") or 0, count(report, "reward", "trapped", "n") or 0
    if n_free < 2 or n_trapped < 2:
        out.print(f"free vs trapped: too few transitions to compare ({n_free} free, {n_trapped} trapped)")
    else:
        out.print(f"free vs trapped: {fmt(number(report, 'free_vs_trapped', 'difference'), '+.3f')} in mean reward, "
                  f"effect size {fmt(number(report, 'free_vs_trapped', 'effect_size'), '.2f')} (pooled standard deviations)")
    listed = report.get("start_states")
    starts = [row for row in listed if isinstance(row, dict)] if isinstance(listed, list) else []
    if starts:
        table = Table(title=f"{report.get('start')} starts: robot actions by what they do (the human staying)")
        table.add_column("human at")
        for name in dg.EFFECTS:
            table.add_column(f"{name}: actions, max Q, P(policy), in buffer")
        for row in starts:
            table.add_row(str(row.get("human")), *[
                f"{n(e, 'actions', tree=row)}, {fmt(number(row, e, 'q_max'), '.2f')}, {fmt(number(row, e, 'p'), '.3f')}, "
                f"{n(e, 'stored', tree=row)}" for e in dg.EFFECTS])
        out.print(table)
    reprs = report.get("representations")
    if isinstance(reprs, dict):
        def r(name: str) -> str:
            return fmt(number(reprs, name), ".3f")

        table = Table(title="representations: how often each picks a transition's future in a batch")
        for col in ("candidates", "phi(s, aR, aH)", "phi'(s, aR)", "block layout alone", "uniform"):
            table.add_column(col)
        table.add_row("the whole batch", r("accuracy_phi"), r("accuracy_phi_prime"), r("layout_only"), r("chance"))
        table.add_row("futures with the true block layout", r("within_layout_phi"), r("within_layout_phi_prime"), "", "")
        out.print(table)
        out.print(f"MI estimate (phi minus phi' diagonal logit): {fmt(number(reprs, 'mi_estimate'), '+.3f')} nats")


@app.command()
def ablate(
    ctx: typer.Context,
    spec_files: Optional[List[Path]] = typer.Argument(None, help="base spec(s); default: the paper's gridworld ESR specs (N = 2, 5, 7, 10)", show_default=False),
    no_robot_action: bool = typer.Option(False, "--no-robot-action", help="phi and phi' without the robot action"),
    greedy: bool = typer.Option(False, "--greedy", help="critic discount 0, future-state horizon unchanged"),
    budget: str = BudgetOpt,
    set_: Optional[List[str]] = typer.Option(None, "--set", "-s", help="one more variant: every --set together "
                                             "changes the base spec this way (key.path=value, repeatable); the base is unchanged"),
):
    """Train (or reuse) base specs and their ablated variants; write one comparison artifact."""
    names = [n for n, on in (("no_robot_action", no_robot_action), ("greedy", greedy)) if on]
    if not names and not set_:
        raise Exit(2, "name an ablation: --no-robot-action, --greedy and/or --set key.path=value")
    check_budget(budget)
    from esr_cli.common.stats import format_summary
    from esr_cli.report import paper  # validates every spec before it imports the training code

    try:
        path, table = paper.ablate([str(p) for p in spec_files or []], names, list(set_ or []), budget, ctx.obj.store, err)
    except specs.SpecError as e:
        raise Exit(2, str(e)) from None
    rich_table = Table(title=f"final return, mean ± SE and IQM [95% bootstrap CI] across seeds ({budget} budget)")
    panels = list(table)
    rich_table.add_column("variant")
    for p in panels:
        rich_table.add_column(p)
    for label in dict.fromkeys(lab for p in panels for lab in table[p]):
        rich_table.add_row(label, *[format_summary(table[p][label]) if label in table[p] else "" for p in panels])
    err.print(rich_table)
    err.print(tagged("comparison", "green", f": {path / 'ablation.png'}  (table: {path / 'table.md'})"))
    out.print(str(path), highlight=False)

