"""The `esr` command line: parse, call, render. Progress and messages go to stderr; stdout
carries results (artifact paths, tables). Exit codes: 0 success (a cache hit is success),
1 a failed run, 2 bad usage or a bad spec, 75 stopped at `--stop-after` or a sweep job's time budget (resumable), 130
interrupted (resumable)."""

from __future__ import annotations

import errno
import io
import json
import os
import shlex
import signal
import sys
from pathlib import Path
from typing import List, Optional

import typer
from rich.table import Table
from rich.text import Text

from esr_cli.common import specs
from esr_cli.common.failures import Failure
from esr_cli.common.printing import plain_console, print_table, printable, tagged
from esr_cli.model import spec as spec_model
from esr_cli.recipes import targets
from esr_cli.runner.stop_signals import StopSignals, Terminated, stop_signals_raise
from esr_cli.storage.artifacts import ensure
from esr_cli.storage.store import KINDS, PLAY_KIND, RUN_KIND, Store, atomic_write_bytes, nearest_existing, probe_writable


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
    """A command's own ending: `code` and the line to print (none: nothing to add)."""

    def __init__(self, code: int, message: str = ""):
        super().__init__(message)
        self.exit_code, self.message = code, message

    def one_line(self) -> str:
        return self.message


class Ctx:
    store: Store
    debug: bool


STATE = Ctx()

StoreOpt = typer.Option(None, "--store", help="artifact store root (default: $ESR_STORE or ./artifacts)")
BudgetOpt = typer.Option("paper", "--budget", "-b", help="paper | quick | smoke")
SetOpt = typer.Option(None, "--set", "-s", help="override a spec field: key.path=value (repeatable)")


@app.callback()
def main_options(
    store: Optional[str] = StoreOpt,  # text, not Path: Path("") would silently mean the current directory
    debug: bool = typer.Option(False, "--debug", help="show tracebacks"),
):
    from esr_cli.storage.provenance import compile_cache_dir, matmul_precision

    if store is not None and not store.strip():
        raise Exit(2, "--store: an empty path; give the store's directory (or leave --store out for $ESR_STORE or ./artifacts)")
    STATE.store = Store(store or os.environ.get("ESR_STORE") or "artifacts")
    STATE.debug = debug
    for left in STATE.store.remove_abandoned_imports():  # each command tidies what a killed import left
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


def _refuse_spec_options(target: str, budget: str, sets: Optional[List[str]]) -> None:
    """A trained run's spec and budget are fixed: --set and --budget beside its key or path
    would silently change nothing."""
    for given, option in ((sets, "--set"), (budget != "paper", "--budget")):
        if given:
            raise Exit(2, f"{option} applies to a spec file target only; {target} is not a spec file but a "
                          "run's key or path, whose spec and budget are fixed (name the spec file instead)")


def _load_spec(path: Path, budget: str, sets: Optional[List[str]]):
    """The spec, with any played-episode key prefix in it completed from the store."""
    return targets.complete_play_keys(specs.load(path, budget, list(sets or [])), STATE.store)


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


# ---------------------------------------------------------------- train
def _quick_spec(path: Path, sets: Optional[List[str]]):
    """The spec at --budget quick, whose time a run estimates beside its own; None where the
    --set values do not fit it."""
    try:
        return specs.load(path, "quick", list(sets or []))
    except specs.SpecError:
        return None


@app.command()
def train(
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
        raise Exit(2, "--wandb needs the wandb package: pip install 'esr[wandb]' (or pip install wandb)")

    # the limit counts from the command's start, as a scheduler's or a lent machine's does
    stop_at = None if stop_after is None else time.monotonic() + parse_duration(stop_after, "--stop-after")
    spec = _load_spec(spec_file, budget, set_)
    quick = _quick_spec(spec_file, set_) if budget != "quick" else None
    from esr_cli.recipes import runs  # JAX and the training code: after the spec is known to be good

    built = ensure(runs.run_recipe(spec, err, stop_at=stop_at, quick=quick, wandb=wandb), STATE.store)
    path, cached = built.path, built.cached
    err.print(tagged("cache hit" if cached else "trained", "green", f": {spec.name} ({spec.budget}) -> {path}"))
    out.print(str(path), highlight=False)


# ---------------------------------------------------------------- sweep
def _refuse_ignored_sweep_options(executor, show_status, show_results, as_json, markdown, metric, plot, wait, job_opts,
                                  unfinished=False, out_dir=None):
    """An option that would change nothing is a mistake to name, not to ignore."""
    for flag, given in (("--unfinished", unfinished), ("--out", out_dir is not None)):
        if given and not plot:
            raise Exit(2, f"{flag} applies with --results --plot only")
    if show_status and show_results:
        raise Exit(2, "--status and --results: choose one")
    if as_json and markdown:
        raise Exit(2, "--json and --markdown: choose one")
    for flag, given in (("--markdown", markdown), ("--metric", metric), ("--plot", plot)):
        if given and not show_results:
            raise Exit(2, f"{flag} applies with --results only")
    if as_json and not (show_status or show_results):
        raise Exit(2, "--json applies with --status or --results only")
    # submitit-local uses the time, CPU and memory limits; partition and GPUs are SLURM's alone.
    used = {"slurm": set(job_opts), "submitit-local": {"--time-min", "--cpus", "--mem-gb"}}.get(executor, set())
    submits = not (show_status or show_results)
    ignored = [f for f, v in job_opts.items() if v is not None and (f not in used or not submits)]
    if ignored:
        raise Exit(2, f"{', '.join(ignored)}: " + (f"not used by --executor {executor}" if submits else
                                                   "--status and --results submit nothing"))
    if wait is not None and (executor == "local" or not submits):
        raise Exit(2, "--wait/--no-wait: for submitted jobs (--executor slurm or submitit-local)")


@app.command()
def sweep(
    suite_file: Path = typer.Argument(..., help="a suite (YAML): spec files and/or a grid of --set values", show_default=False),
    budget: str = BudgetOpt,
    executor: str = typer.Option("local", "--executor", "-e", help="local (here, one after another) | slurm | submitit-local"),
    show_status: bool = typer.Option(False, "--status", help="only show each run's state: done / running / queued / stopped / failed / missing"),
    show_results: bool = typer.Option(False, "--results", help="only show each finished run's final return and success (mean ± SE across seeds); trains nothing"),
    as_json: bool = typer.Option(False, "--json", help="--status / --results: print JSON instead of a table"),
    markdown: bool = typer.Option(False, "--markdown", help="--results: print a markdown table"),
    metric: Optional[list[str]] = typer.Option(None, "--metric", help="--results: a logged metric to show (repeat for "
                                               "several; default: return and success), e.g. mi_estimate"),
    plot: bool = typer.Option(False, "--plot", help="--results: also draw the runs' learning curves (a figures artifact; every run must be done, unless --unfinished)"),
    unfinished: bool = typer.Option(False, "--unfinished", help="--plot: draw runs still training as far as they have got, "
                                    "marked unfinished (a preview outside the store)"),
    out_dir: Optional[Path] = typer.Option(None, "--out", help="--plot --unfinished: the folder for the preview "
                                           "(default: suite-NAME-BUDGET-unfinished here)"),
    wait: Optional[bool] = typer.Option(None, "--wait/--no-wait", help="wait for submitted jobs (default: wait, except for slurm)"),
    partition: Optional[str] = typer.Option(None, "--partition", help="slurm: partition (default: the suite's slurm.partition)"),
    time_min: Optional[int] = typer.Option(None, "--time-min", help="slurm: wall-clock limit per job, minutes"),
    gpus: Optional[int] = typer.Option(None, "--gpus", help="slurm: GPUs per job"),
    cpus: Optional[int] = typer.Option(None, "--cpus", help="slurm: CPU cores per job"),
    mem_gb: Optional[float] = typer.Option(None, "--mem-gb", help="slurm: memory per job, GB"),
):
    """Train every run of a suite that the store lacks: here, or as SLURM jobs (docs/cluster.md)."""
    from esr_cli.recipes import sweep as sw

    _check_executor(executor, sw.EXECUTORS)
    _refuse_ignored_sweep_options(executor, show_status, show_results, as_json, markdown, metric, plot, wait,
                                  {"--partition": partition, "--time-min": time_min, "--gpus": gpus,
                                   "--cpus": cpus, "--mem-gb": mem_gb}, unfinished, out_dir)
    overrides = {"partition": partition, "time_min": time_min, "gpus": gpus, "cpus": cpus, "mem_gb": mem_gb}
    try:
        sw.slurm_options(sw.SlurmOptions(), overrides, "")  # before the suite's runs are built
    except sw.SuiteError as e:
        raise Exit(2, str(e)) from None
    try:
        suite = sw.load_suite(suite_file, budget)
        if show_results:
            metrics = tuple(dict.fromkeys(metric)) if metric else sw.DEFAULT_RESULT_METRICS
            try:
                rows = sw.results(suite, STATE.store, metrics)  # refuses a metric no run can log
            except sw.SuiteError as e:
                raise Exit(2, str(e)) from None
            if as_json:
                out.print_json(json.dumps(rows))
            elif markdown:
                out.print(sw.results_markdown(suite, rows, metrics), highlight=False)
            else:
                out.print(sw.results_table(suite, rows, metrics))
            if plot:
                from esr_cli.report import figures as figs, paper

                try:
                    recipe = paper.suite_figure_recipe(suite, STATE.store, unfinished)
                except figs.MissingRuns as e:
                    raise Exit(2, f"{e}\nor all at once: esr sweep {suite_file} --budget {budget}") from None
                if recipe.unfinished:
                    _draw_preview(recipe, out_dir or Path(f"suite-{suite.name}-{budget}-unfinished"), print_path=False)
                else:
                    built = ensure(recipe, STATE.store)
                    path = built.path
                    err.print(tagged("cache hit" if built.cached else "drawn", "green", f": {path / 'suite.png'}  (table: {path / 'table.md'})"))
            return
        if show_status:
            rows = sw.status(suite, STATE.store)
            if as_json:
                out.print_json(json.dumps(sw.status_json(rows)))
            else:
                out.print(sw.status_table(suite, rows))
            return
        result = sw.run_suite(suite, budget, executor, STATE.store, err, wait, overrides)
    except sw.SuiteError as e:
        raise Exit(2, f"bad suite: {e}") from None
    except sw.SweepError as e:
        raise Exit(1, str(e)) from None
    for p in result.paths:
        if p is not None:
            out.print(str(p), highlight=False)
    done = sum(p is not None for p in result.paths)
    err.print(tagged(f"{done} of {len(result.paths)} run(s) done", "green", f"; {len(result.submitted)} "
                     f"{'run' if executor == 'local' else 'submitted'} this time; `{STATE.store.invocation()} sweep --status {suite_file} --budget {budget}` shows each"))
    if result.failed:
        raise Exit(1, f"{len(result.failed)} run(s) failed: " + "; ".join(f"{r.label}: {m}" for r, m in result.failed))
    if result.stopped:  # saved at their jobs' time budgets: resumable, like `esr train --stop-after`
        raise Exit(75, f"{len(result.stopped)} run(s) stopped at their jobs' time budget, saved; "
                       f"run the same sweep again to continue them")


def _check_budget(budget: str) -> None:
    if budget not in spec_model.BUDGETS:
        raise Exit(2, f"--budget: unknown budget {budget!r}; known: {', '.join(spec_model.BUDGETS)}")


def _check_executor(executor: str, known: tuple[str, ...]) -> None:
    if executor not in known:
        raise Exit(2, f"--executor: unknown executor {executor!r}; known: {', '.join(known)}")


# ---------------------------------------------------------------- eval
@app.command("eval")
def eval_(
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
    human = targets.complete_play_partner(STATE.store, human)
    most = spec_model.MAX_EVAL_EPISODES
    if episodes is not None and not 1 <= episodes <= most:
        raise Exit(2, f"--episodes: between 1 and {most:,} (got {episodes:,})")
    spec_file = targets.is_spec_file(target)
    if spec_file:  # options that cannot fit the spec are named before "not trained yet"
        spec = _load_spec(Path(target), budget, set_)
    else:
        _refuse_spec_options(target, budget, set_)
        run_path = targets.stored_run(STATE.store, target)
        spec = targets.run_spec(run_path)
    targets.partner_spec(targets.seat_spec(spec, seat)[0], human)
    from esr_cli.common.stats import format_summary  # scipy: +0.9 s, only where a table needs it
    from esr_cli.recipes import runs  # JAX and the training code: after the options are checked

    if spec_file:
        run_path = runs.committed_run(spec, runs.train_command(target, budget, set_, STATE.store), STATE.store)
    built = ensure(runs.eval_recipe(run_path, STATE.store, episodes, err, human, seat), STATE.store)
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


# ---------------------------------------------------------------- exact / plot
@app.command()
def exact(
    spec_file: Path = typer.Argument(..., help="a gridworld spec (YAML)", show_default=False),
    budget: str = BudgetOpt,
    set_: Optional[List[str]] = SetOpt,
    robot: Optional[str] = typer.Option(None, "--robot", help="a training run (key or path) whose Boltzmann policy the robot follows; default uniform"),
    goal: Optional[str] = typer.Option(None, "--goal", help="the human's goal cell 'row,col' (default: the centre)"),
    gamma: Optional[float] = typer.Option(None, "--gamma", help="future-state horizon (default: the spec's method.future_gamma)"),
    seed_index: Optional[int] = typer.Option(None, "--seed-index", help="which seed of --robot's run (default 0)"),
):
    """Exact effective empowerment of a small gridworld: I(aH; s+ | s, aR) for every state."""
    if seed_index is not None and robot is None:
        raise Exit(2, "--seed-index applies to --robot's run only (a uniform robot has no seeds)")
    spec = _load_spec(spec_file, budget, set_)
    cell = None
    if goal is not None:
        try:
            cell = tuple(int(v) for v in goal.split(","))
            assert len(cell) == 2
        except (ValueError, AssertionError):
            raise Exit(2, f"--goal: expected 'row,col', got {goal!r}") from None
    targets.exact_target(spec, STATE.store, cell, gamma, robot, seed_index or 0)
    from esr_cli.recipes import exact_runs  # JAX and the analysis: after the options are checked

    built = ensure(exact_runs.exact_recipe(spec, STATE.store, cell, gamma, robot, seed_index or 0, err), STATE.store)
    path, summary, cached = built.path, built.summary(), built.cached
    table = Table(title=f"exact empowerment: {spec.name}, goal {tuple(summary['goal'])}, gamma {summary['gamma']}")
    table.add_column("quantity")
    table.add_column("value")
    for k in ("states", "effective_empowerment", "mean_mi_visited", "mean_mi_visited_merged_actions", "mean_mi_uniform_states",
              "max_mi", "states_with_zero_mi", "pairs", "pairs_computed"):
        if k not in summary:  # made by an earlier version
            continue
        v = summary[k]
        table.add_row(k, f"{v:.4f}" if isinstance(v, float) else "— (not every pair computed)" if v is None else str(v))
    err.print(table)
    err.print(tagged("cache hit" if cached else "computed", "green", f": {path}"))
    out.print(str(path), highlight=False)


human_app = typer.Typer(no_args_is_help=True, help="Stored Overcooked humans: build one, or calibrate candidates "
                        "against the paper's Random column (docs/overcooked.md).")
app.add_typer(human_app, name="human")


def _stored_human_spec(spec_file: Path, budget: str, sets: Optional[List[str]]):
    spec = _load_spec(spec_file, budget, sets)
    from esr_cli.recipes import stored_humans

    if not stored_humans.is_stored(spec.human):
        raise Exit(2, f"{spec_file}: human.kind={spec.human.kind} is not a stored human (bc or ppo)")
    return spec


@human_app.command("build")
def human_build(
    spec_file: Path = typer.Argument(..., help="an Overcooked spec (YAML) whose human is stored (kind bc or ppo)", show_default=False),
    budget: str = BudgetOpt,
    set_: Optional[List[str]] = SetOpt,
):
    """Make (or resume, or find) the spec's human, one per training seed with human.per_seed,
    without training a robot; prints each human's artifact path."""
    spec = _stored_human_spec(spec_file, budget, set_)
    from esr_cli.recipes import stored_humans

    for recipe in stored_humans.human_recipes(spec, err):
        built = ensure(recipe, STATE.store)
        summary = STATE.store.read_manifest(built.path).get("summary", {})
        ret = summary.get("return") or {}
        said = f" ({ret.get('of')}: {ret['mean']:.2f})" if "mean" in ret else ""
        err.print(tagged("cache hit" if built.cached else "built", "green", f": {recipe.name}{said}"), highlight=False)
        out.print(str(built.path), highlight=False)


@human_app.command("calibrate")
def human_calibrate(
    spec_files: List[Path] = typer.Argument(..., help="Overcooked specs (YAML), one per layout, whose human is the "
                                            "candidate (kind bc or ppo)", show_default=False),
    budget: str = BudgetOpt,
    set_: Optional[List[str]] = SetOpt,
    human_seeds: int = typer.Option(3, "--human-seeds", min=1, max=64, help="humans per layout: seeds human.seed, +1, ..."),
    episodes: int = typer.Option(100, "--episodes", min=2, max=100_000, help="episodes of each human with each partner"),
    as_json: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
    markdown: bool = typer.Option(False, "--markdown", help="print a markdown table"),
):
    """Each candidate human with a uniform random robot, a staying robot and itself, per layout
    and human seed, against the paper's Random column; no robot is trained. The humans are
    made first where the store lacks them. The score is the selection rule's (docs/overcooked.md)."""
    loaded = [_stored_human_spec(f, budget, set_) for f in spec_files]
    layouts = [s.env.layout for s in loaded]
    if len(set(layouts)) != len(layouts):
        raise Exit(2, f"two specs share a layout ({', '.join(layouts)}): give one spec per layout")
    from esr_cli.report import human_calibration as hc

    rows = [hc.calibrate_spec(s, human_seeds, episodes, STATE.store, err) for s in loaded]
    if as_json:
        out.print_json(json.dumps({"rows": [r.as_json() for r in rows], "score": hc.score(rows),
                                   "human_seeds": human_seeds, "episodes": episodes}))
        return
    if markdown:
        out.print(hc.markdown(rows, human_seeds, episodes), highlight=False, markup=False)
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


@app.command()
def diagnose(
    run: str = typer.Argument(..., help="a training run (key, key prefix or path), finished or not", show_default=False),
    seed_index: int = typer.Option(0, "--seed-index", help="which seed of the run"),
    batches: int = typer.Option(40, "--batches", min=1, max=10_000, help="critic batches to score"),
    episodes: int = typer.Option(16, "--episodes", min=1, max=1024, help="episodes each robot plays for the play check"),
    refit: int = typer.Option(0, "--refit", min=0, max=100_000, help="ESR: also fit fresh representations to each robot's "
                              "play for this many updates and compare their MI estimates (0: off)"),
    as_json: bool = typer.Option(False, "--json", help="print JSON instead of tables"),
):
    """Why a robot helps or not: its own reward on its play against a uniform robot's, and on
    the gridworld its reward by the human's situation and its critic and policy at a few
    distinct start states. An unfinished run is read at its newest checkpoint."""
    path, record, finished = targets.run_record(STATE.store, run)
    if not 0 <= seed_index < len(record["seeds"]):
        raise Exit(2, f"--seed-index: the run has {len(record['seeds'])} seed(s)")
    method = targets.run_spec(path).method.kind
    if refit and method != "esr":
        raise Exit(2, f"--refit fits ESR's representations; this run's method is {method}")
    if refit and episodes < 2:
        raise Exit(2, "--refit holds one episode in four out of the fit: give --episodes 2 or more")
    import jax  # and the training code: after the options are checked against the run

    from esr_cli.analysis import diagnose as dg, play_check as pc
    from esr_cli.recipes.runs import load_run_so_far, seed_slice

    trainer, state, epoch = load_run_so_far(STATE.store, path, finished)
    one = seed_slice(state, seed_index)
    learns = trainer.method.learns_policy and not trainer.acts_by_rule
    play = pc.play_check(trainer, one, jax.random.PRNGKey(3), episodes, batches, refit) if learns else None
    report = {"run": str(path), "finished": finished, "epoch": epoch, "epochs": trainer.spec.train.epochs,
              "seed_index": seed_index, "play": play}
    if trainer.spec.env.kind == "gridworld":
        rewards = dg.reward_by_situation(trainer, one, jax.random.PRNGKey(0), batches)
        report.update({
            "reward": rewards,
            "free_vs_trapped": dg.free_trapped_contrast(rewards),
            "start": trainer.spec.env.start,
            "start_states": dg.start_policy(trainer, one, jax.random.PRNGKey(1)) if learns else [],
            "representations": dg.representation_check(trainer, one, jax.random.PRNGKey(2), batches)
            if trainer.spec.method.kind == "esr" else None,
        })
    if as_json:
        out.print_json(json.dumps(report))
        return
    when = "" if finished else f", unfinished: checkpoint at epoch {epoch:,} of {trainer.spec.train.epochs:,}"
    out.print(f"{record['name']} ({record['budget']} budget, {trainer.spec.method.kind}), seed index {seed_index}{when}")
    if play:
        _print_play_check(play)
    else:
        out.print(f"{trainer.spec.method.kind} learns no robot policy: no play check")
    if trainer.spec.env.kind == "gridworld":
        _print_gridworld_diagnosis(report)


def _print_play_check(play: dict) -> None:
    table = Table(title="the run's reward on its robot's play and on a uniform robot's (same human)")
    refit = all("refit" in r for r in play.values())
    columns = ["robot", "episodes", "return", "reward: mean", "sd", "MI estimate (nats)", "steps the human moves"]
    for col in columns + (["refit MI: fit", "held out"] if refit else []):
        table.add_column(col)
    for player, r in play.items():
        mi = r["reward"].get("mi_estimate")
        cells = [player, str(r["episodes"]), f"{r['return']:.2f}", f"{r['reward']['mean']:+.3f}", f"{r['reward']['sd']:.3f}",
                 "" if mi is None else f"{mi:+.4f}", f"{r['human_moves']:.3f}"]
        if refit:
            cells += [f"{r['refit']['fit']:+.4f}", f"{r['refit']['held_out']:+.4f}"]
        table.add_row(*cells)
    out.print(table)


def _print_gridworld_diagnosis(report: dict) -> None:
    from esr_cli.analysis import diagnose as dg

    rewards, contrast, starts, reprs = (report[k] for k in ("reward", "free_vs_trapped", "start_states", "representations"))
    table = Table(title="reward by the human's situation (the run's buffer)")
    for col in ("situation", "transitions", "mean reward", "sd"):
        table.add_column(col)
    for name, r in rewards.items():
        table.add_row(name, str(r["n"]), f"{r['mean']:.3f}", f"{r['sd']:.3f}")
    out.print(table)
    n_free, n_trapped = rewards["free"]["n"], rewards["trapped"]["n"]
    if n_free < 2 or n_trapped < 2:
        out.print(f"free vs trapped: too few transitions to compare ({n_free} free, {n_trapped} trapped)")
    else:
        out.print(f"free vs trapped: {contrast['difference']:+.3f} in mean reward, effect size {contrast['effect_size']:.2f} "
                  "(pooled standard deviations)")
    if starts:
        table = Table(title=f"{report['start']} starts: robot actions by what they do (the human staying)")
        table.add_column("human at")
        for name in dg.EFFECTS:
            table.add_column(f"{name}: actions, max Q, P(policy), in buffer")
        for row in starts:
            table.add_row(str(row["human"]), *[f"{row[e]['actions']}, {row[e]['q_max']:.2f}, {row[e]['p']:.3f}, "
                                               f"{row[e]['stored']}" for e in dg.EFFECTS])
        out.print(table)
    if reprs:
        table = Table(title="representations: how often each picks a transition's future in a batch")
        for col in ("candidates", "phi(s, aR, aH)", "phi'(s, aR)", "block layout alone", "uniform"):
            table.add_column(col)
        table.add_row("the whole batch", f"{reprs['accuracy_phi']:.3f}", f"{reprs['accuracy_phi_prime']:.3f}",
                      f"{reprs['layout_only']:.3f}", f"{reprs['chance']:.3f}")
        table.add_row("futures with the true block layout", f"{reprs['within_layout_phi']:.3f}",
                      f"{reprs['within_layout_phi_prime']:.3f}", "", "")
        out.print(table)
        out.print(f"MI estimate (phi minus phi' diagonal logit): {reprs['mi_estimate']:+.3f} nats")


PAPER_FIGURES = ("gridworld", "overcooked", "no-robot-action", "greedy", "mi", "representations", "filmstrip")


@app.command()
def plot(
    figure: str = typer.Argument(..., help="curve | estimator | geometry | " + " | ".join(PAPER_FIGURES), show_default=False),
    ref: Optional[str] = typer.Argument(None, help="curve: a training run, finished or not; estimator: an exact artifact made with --robot"),
    budget: Optional[str] = typer.Option(None, "--budget", "-b", help="paper figures: paper | quick | smoke (default paper)"),
    gamma: Optional[float] = typer.Option(None, "--gamma", help="geometry: the future-state horizon (default 0.2)"),
    state: Optional[int] = typer.Option(None, "--state", help="geometry: which of the 3 states (default 0)"),
    unfinished: bool = typer.Option(False, "--unfinished", help="paper figures: draw runs still training as far as they "
                                    "have got, marked unfinished (a preview outside the store)"),
    out_file: Optional[Path] = typer.Option(None, "--out", help="curve: the PNG to write (default: NAME-KEY8-curve.png "
                                            "here); a paper figure with --unfinished: the folder for the preview"),
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
        _plot_curve(ref, out_file)
        return
    if budget is not None and figure not in PAPER_FIGURES:
        raise Exit(2, f"--budget applies to the paper figures ({', '.join(PAPER_FIGURES)}), not to {figure}")
    for value, option in ((gamma, "--gamma"), (state, "--state")):
        if value is not None and figure != "geometry":
            raise Exit(2, f"{option} applies to `esr plot geometry` only, not to {figure}")
    if figure == "estimator":
        if ref is None:
            raise Exit(2, "esr plot estimator needs an exact artifact: make one with `esr exact SPEC --robot RUN`")
        targets.exact_artifact(STATE.store, ref)
    budget = budget or "paper"
    _check_budget(budget)
    gamma = 0.2 if gamma is None else gamma
    state = 0 if state is None else state
    if figure == "geometry":
        targets.geometry_options(gamma, state)
    from esr_cli.recipes import exact_runs  # JAX, scipy, matplotlib: after the options are checked

    if figure == "estimator":
        built = ensure(exact_runs.estimator_recipe(ref, STATE.store, err), STATE.store)
        result = built.summary()
        err.print(f"Spearman rank correlation of ESR's reward with the exact MI: {result['spearman']:.3f} over {result['pairs']} (state, robot action) pairs")
        png = built.path / "estimator.png"
    elif figure == "geometry":
        built = ensure(exact_runs.geometry_recipe(gamma, state), STATE.store)
        result = built.summary()
        err.print(f"3-state MDP, state {state}, gamma {gamma}: capacity I = {result['mutual_information']:.4f} nats "
                  f"(uniform policy: {result['uniform_policy_mi']:.4f})")
        png = built.path / "geometry.png"
    else:  # a paper figure
        from esr_cli.report import figures as figs, paper

        try:
            recipe = paper.figure_recipe(STATE.store, budget, figure, figs.PaperInputs(STATE.store, budget, unfinished=unfinished))
        except figs.MissingRuns as e:
            raise Exit(2, f"{e}\nor all at once: make paper-figures BUDGET={budget}") from None
        if recipe.unfinished:
            _draw_preview(recipe, out_file or Path(f"{figure}-{budget}-unfinished"))
            return
        built = ensure(recipe, STATE.store)
        png = built.path / f"{figs.FIGURES[figure][0]}.png"
    err.print(tagged("cache hit" if built.cached else "drawn", "green", f": {png}"))
    out.print(str(png), highlight=False)


def _draw_preview(recipe, out_dir: Path, print_path: bool = True) -> None:
    """A figure that reads unfinished runs, drawn into `out_dir` outside the store (it would
    change as they train, so it is never an artifact); its PNG is named on stderr (and printed
    on stdout with `print_path`)."""
    from esr_cli.storage.artifacts import preview

    if out_dir.exists() and not out_dir.is_dir():
        raise Exit(2, f"--out: {out_dir} is a file; name a folder")
    _refuse_inside_store(out_dir / "x", "--out")
    _check_output_file(out_dir / "x", "--out")
    summary = preview(recipe, out_dir, STATE.store)
    png = next((out_dir / f for f in summary.get("files", []) if f.endswith(".png")), None) or next(out_dir.glob("*.png"))
    err.print(tagged("drawn", "green", f": {png}", f"  (a preview of unfinished runs: {'; '.join(recipe.unfinished)})"))
    if print_path:
        out.print(str(png), highlight=False)


def _plot_curve(ref: str, out_file: Optional[Path]) -> None:
    """A run's learning curves from its metrics so far; an unfinished run says so in the title."""
    path, record, finished = targets.run_record(STATE.store, ref)
    from esr_cli.common import plots
    from esr_cli.report.listing import field
    from esr_cli.storage.finals import read_rows

    rows = read_rows(path)
    if not rows:
        raise Exit(2, f"{path} has no epoch logged yet: nothing to draw")
    total = field(record, "key_components", "spec", "train", "epochs")
    done = rows[-1]["epoch"]
    state = "" if finished else f" (unfinished: epoch {done:,}" + (f" of {total:,})" if total else ")")
    name, key = str(record.get("name", "run")), str(record.get("key", path.name.split(".")[0]))
    out_png = out_file or Path(f"{name}-{key[:8]}-curve.png")
    _refuse_inside_store(out_png, "--out")
    _check_output_file(out_png, "--out")
    warmup = field(record, "key_components", "spec", "learner", "warmup_epochs") or 0
    method = field(record, "key_components", "spec", "method", "kind")
    title = printable(f"{name} [{method}]{state}" if method else f"{name}{state}")
    plots.learning_curve(rows, out_png, title, {"artifacts": {RUN_KIND: key}, "finished": finished, "epochs": done},
                         warmup_epochs=warmup)
    err.print(tagged("drawn", "green", f": {out_png}" + ("" if finished else f", at epoch {done:,}")))
    out.print(str(out_png), highlight=False)


@app.command()
def ablate(
    spec_files: Optional[List[Path]] = typer.Argument(None, help="base spec(s); default: the paper's gridworld ESR specs (N = 2, 5, 7, 10)", show_default=False),
    no_robot_action: bool = typer.Option(False, "--no-robot-action", help="phi and phi' without the robot action"),
    greedy: bool = typer.Option(False, "--greedy", help="critic discount 0, future-state horizon unchanged"),
    budget: str = BudgetOpt,
    set_: Optional[List[str]] = SetOpt,
):
    """Train (or reuse) base specs and their ablated variants; write one comparison artifact."""
    names = [n for n, on in (("no_robot_action", no_robot_action), ("greedy", greedy)) if on]
    if not names and not set_:
        raise Exit(2, "name an ablation: --no-robot-action, --greedy and/or --set key.path=value")
    _check_budget(budget)
    from esr_cli.common.stats import format_summary
    from esr_cli.report import paper  # validates every spec before it imports the training code

    try:
        path, table = paper.ablate([str(p) for p in spec_files or []], names, list(set_ or []), budget, STATE.store, err)
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


def _refuse_inside_store(path: Path, option: str) -> None:
    """An output file must not land in the store's artifact folders: inside an artifact it would be
    a file its manifest does not list (`esr verify` fails it), and a committed artifact never changes."""
    here = nearest_existing(path.parent).resolve()
    for kind in KINDS:
        folder = (STATE.store.root / kind).resolve()
        if here == folder or folder in here.parents:
            raise Exit(2, f"{option}: {path} lies inside the store's {kind}/ folder; write it outside the store's artifacts")


def _check_output_file(path: Path, option: str) -> None:
    """Refuse, before any work, an output path that cannot become a file: a directory, or one
    below an existing file."""
    if path.is_dir():
        raise Exit(2, f"{option}: {path} is a directory; name a file")
    parent = nearest_existing(path.parent)
    if not parent.is_dir():
        raise Exit(2, f"{option}: {parent} is a file, not a directory")
    try:
        probe_writable(parent)
    except OSError as e:
        raise Exit(2, f"{option}: cannot write in {parent}: {e.strerror or e}") from None


@app.command("paper")
def paper_(
    ctx: typer.Context,
    budget: str = BudgetOpt,
    executor: str = typer.Option("local", "--executor", "-e", help="local | slurm | submitit-local (see esr sweep)"),
    report: bool = typer.Option(False, "--report", help="train nothing: write the reproduction report (every claim of "
                                "the paper against the store's runs, with a verdict) to --out"),
    report_out: Path = typer.Option(Path("docs/reproduction.md"), "--out", help="where --report writes (markdown; "
                                    "its curves go to img/ beside it)"),
    exact: bool = typer.Option(True, "--exact/--no-exact", help="with --report: compute the estimator check's exact "
                               "artifacts (a few minutes the first time)"),
    as_json: bool = typer.Option(False, "--json", help="with --report: also print every verdict as JSON on stdout"),
    check: bool = typer.Option(False, "--check", help="with --report: write nothing; exit 1 if --out differs from "
                               "what the store's runs give now (the generated-on line aside)"),
):
    """Train what the paper suite lacks, draw every figure and write the report (make paper-figures);
    with --report, the reproduction report instead (docs/reproduction.md)."""
    # The two modes take different options; one the chosen mode would ignore is a mistake to
    # name (a forgotten --report must not start hours of training).
    given = {name for name in ("budget", "executor", "report_out", "exact", "as_json", "check")
             if getattr(ctx.get_parameter_source(name), "name", "DEFAULT") not in ("DEFAULT", "DEFAULT_MAP")}
    options = {"budget": "--budget", "executor": "--executor", "report_out": "--out", "exact": "--exact/--no-exact",
               "as_json": "--json", "check": "--check"}
    wrong = given & ({"budget", "executor"} if report else {"report_out", "exact", "as_json", "check"})
    if wrong:
        names = ", ".join(options[n] for n in sorted(wrong))
        verb = "applies" if len(wrong) == 1 else "apply"
        raise Exit(2, f"{names}: {verb} to `esr paper --report` only; add --report to write the report (without "
                      "it, `esr paper` trains the paper suite)" if not report else
                      f"{names}: {verb} to training the paper suite; `esr paper --report` trains nothing and "
                      "reads every budget's runs")
    if not report:
        _check_budget(budget)
    from esr_cli.recipes import sweep as sw
    from esr_cli.report import figures as figs, paper

    if not report:
        _check_executor(executor, sw.EXECUTORS)

    if report:
        from esr_cli.report import reproduction

        if check:
            differences = reproduction.check(STATE.store, report_out, err, exact=exact)
            if differences:
                err.print(f"{report_out} differs from what the store's runs give now "
                          f"(esr paper --report --out {report_out} brings it up to date):", highlight=False)
                err.print("\n".join(differences), highlight=False)
                raise Exit(1, f"{report_out} is stale")
            err.print(tagged("reproduction report", "green", f": {report_out} is what the store's runs give"))
            return
        _check_output_file(report_out, "--out")
        findings = reproduction.report(STATE.store, report_out, err, exact=exact)
        err.print(reproduction.summary_line(findings))
        err.print(tagged("reproduction report", "green", f": {report_out}"))
        if as_json:
            out.print(json.dumps(reproduction.findings_json(findings), indent=2), highlight=False)
        else:
            out.print(str(report_out), highlight=False)
        return
    try:
        path = paper.make_paper(STATE.store, budget, executor, err)
    except sw.SuiteError as e:
        raise Exit(2, f"bad suite: {e}") from None
    except (sw.SweepError, figs.MissingRuns) as e:
        raise Exit(1, str(e)) from None
    err.print(tagged("report", "green", f": {path / 'report.md'}"))
    out.print(str(path / "report.md"), highlight=False)


# ---------------------------------------------------------------- ls / show / verify
@app.command("ls")
def ls(
    kind: Optional[str] = typer.Option(None, "--kind", help=f"only this kind: {', '.join(KINDS)}"),
    name: Optional[str] = typer.Option(None, "--spec", help="only artifacts of this spec name (e.g. grid_2)"),
    method: Optional[str] = typer.Option(None, "--method", help="only runs of this method (esr, random, ave, ...)"),
    budget: Optional[str] = typer.Option(None, "--budget", "-b", help="only this budget: paper | quick | smoke"),
    as_json: bool = typer.Option(False, "--json", help="one JSON array of rows (fields: docs/store.md)"),
):
    """List the artifacts in the store (every column in full, on a terminal or piped)."""
    from esr_cli.report import listing

    if kind is not None and kind not in KINDS:
        raise Exit(2, f"--kind: unknown kind {kind!r}; kinds: {', '.join(KINDS)}")
    if budget is not None:
        _check_budget(budget)
    found = list(listing.rows(STATE.store, kind, name, method, budget))
    if as_json:
        out.print_json(json.dumps([r for r, _ in found]))
        return
    if not found:
        filtered = any(v is not None for v in (kind, name, method, budget))
        err.print("no artifact matches those filters" if filtered and STATE.store.root.is_dir() else
                  f"store {STATE.store.root} is empty" if STATE.store.root.is_dir() else
                  f"no store at {STATE.store.root} (nothing has been made there yet)")
        return
    table = Table(caption=listing.FINAL_RETURN + "; another artifact's return is the one its summary names")
    for col in ("kind", "name", "key", "budget", "seeds", "status", "epochs", "final return", "created", "method",
                "overrides"):
        table.add_column(col, no_wrap=True)
    for r, entry in found:
        epochs = "" if r["epochs"] is None else (f"{r['epochs']:,}" if r["status"] == "complete" or r["epochs_total"] is None
                                                 else f"{r['epochs']:,} of {r['epochs_total']:,}")
        overrides = "" if entry.kind != RUN_KIND else ("(no spec file resolves to it)" if r["overrides"] is None
                                                      else " ".join(r["overrides"]) or "-")
        table.add_row(entry.kind, printable(r["name"] or "?"), r["key"][:12], printable(r["budget"] or "?"),
                      str(r["seeds"] or "?"), r["status"], epochs,
                      "" if r["final_return"] is None else f"{r['final_return']:.2f}", (r["created"] or "")[:16].replace("T", " "),
                      printable(r["method"] or ""), printable(overrides))
    print_table(out, table)  # piped, every cell in full
    for _, entry in found:  # one line each; the others are listed above all the same
        if listing.status_of(entry) == "damaged":
            err.print(f"damaged manifest: {entry.problem}")


# ---------------------------------------------------------------- play
MAX_PLAY_EPISODES = 10_000  # a person plays each one: far above any study's session


@app.command()
def play(
    target: str = typer.Argument(..., help="a trained run (key or path) or a spec; with --robots, the spec only names the environment", show_default=False),
    budget: str = BudgetOpt,
    set_: Optional[List[str]] = SetOpt,
    robots: Optional[str] = typer.Option(None, "--robots", help="comma-separated robots to play with, in a counterbalanced "
                                         "order under neutral names: run keys, paths or specs, and `random`"),
    episodes: int = typer.Option(1, "--episodes", "-n", help="episodes in the session"),
    participant: str = typer.Option("anonymous", "--participant", help="the person's id (logged; decides the order and names of the robots)"),
    fps: float = typer.Option(6.0, "--fps", help="Overcooked: steps per second (a tick without a key is stay)"),
    web: bool = typer.Option(False, "--web", help="play in a browser: serve the game on localhost"),
    port: int = typer.Option(8765, "--port", help="--web: the port on 127.0.0.1"),
    seed: int = typer.Option(0, "--seed", help="the first episode's environment seed (episode i: seed + i)"),
    seed_index: int = typer.Option(0, "--seed-index", help="which seed of each trained run acts"),
    countdown: float = typer.Option(3.0, "--countdown", help="seconds counted down after the person presses space to "
                                    "start each episode (0: none)"),
):
    """Play the human's part with trained robots; every episode is logged as a `play` artifact."""
    from esr_cli.play import session as ps

    if not 1 <= episodes <= MAX_PLAY_EPISODES:
        raise Exit(2, f"--episodes: between 1 and {MAX_PLAY_EPISODES:,} (got {episodes:,})")
    if not 0.5 <= fps <= 60:
        raise Exit(2, f"--fps: between 0.5 and 60 (got {fps})")
    if not 1024 <= port <= 65535:
        raise Exit(2, f"--port: between 1024 and 65535 (got {port})")
    if not 0 <= countdown <= 30:
        raise Exit(2, f"--countdown: between 0 and 30 seconds (got {countdown})")
    if not participant.strip() or len(participant) > 200:
        raise Exit(2, "--participant: a non-empty id of at most 200 characters")
    if not 0 <= seed <= spec_model.MAX_SEED - (episodes - 1):  # episode i plays seed + i, an int32 PRNG seed
        raise Exit(2, f"--seed: between 0 and {spec_model.MAX_SEED - (episodes - 1):,} for {episodes} episode(s) (got {seed})")
    refs = [r.strip() for r in robots.split(",") if r.strip()] if robots else []
    if robots is not None and not refs:
        raise Exit(2, "--robots: name at least one robot (a run key, path or spec, or `random`)")
    if not any(targets.is_spec_file(r) for r in [target, *refs]):
        _refuse_spec_options(target, budget, set_)
    if web:
        from esr_cli.play.web import PortInUse, Web

        try:
            front = Web(port, err)
        except PortInUse as e:
            raise Exit(2, str(e)) from None
        name = "web"
    else:
        from esr_cli.play.terminal import NotATerminal, Terminal

        try:
            front = Terminal(out)
        except NotATerminal as e:
            raise Exit(2, str(e)) from None
        name = "terminal"
    spec, opponents = ps.load_opponents(target, refs, budget, set_, seed_index, STATE.store, participant)
    ps.recover_abandoned(STATE.store, err)
    session = ps.new_session_id()
    with front:
        played = ps.run_session(spec, opponents, participant, episodes, seed, fps, front, name, STATE.store, err,
                                countdown, session)
        rows = ps.summary_rows(played)
        front.finish([f"session over: {len(played)} episode(s) played. Thank you!"])
    # The terminal is the participant's screen: which robot is which stays with `esr plays`.
    shown = ("robot", "episodes (completed)", "return (mean)", "success", "steps (mean)")
    table = Table(title=f"esr play: participant {participant}, session {session}, {len(played)} of {episodes} episode(s)")
    for col in shown if not web else shown[:1] + ("key",) + shown[1:]:
        table.add_column(col)
    for r in rows:
        cells = [f"{r['episodes']} ({r['completed']})", f"{r['return_mean']:.2f}", f"{r['success_rate']:.2f}",
                 f"{r['steps_mean']:.1f}"]
        table.add_row(r["robot_label"], *([r["robot"][:12]] if web else []), *cells)
    err.print(table)
    if not web:
        err.print(f"the robots' keys: esr plays --session {session}", highlight=False)
    for p in played:
        out.print(p["path"], highlight=False)
    if played and not played[-1]["completed"]:
        err.print("the session was ended early; its last episode is kept as incomplete", highlight=False)
        raise Exit(130)


@app.command()
def plays(
    participant: Optional[str] = typer.Option(None, "--participant", help="only this participant's episodes"),
    session: Optional[str] = typer.Option(None, "--session", help="only this session's episodes"),
    export: Optional[Path] = typer.Option(None, "--export", help="write the episodes shown: .jsonl, every step of any "
                                          "environment (docs/play.md); .pickle (a pandas DataFrame) or .csv, the "
                                          "Overcooked ones in overcooked-ai's human-data schema"),
    by_robot: bool = typer.Option(False, "--by-robot", help="a table per robot instead: participants, episodes, and the "
                                  "return and success of completed episodes (per participant, then mean ± SE and IQM across participants)"),
    csv_file: Optional[Path] = typer.Option(None, "--csv", help="also write one row per episode shown (participant, "
                                            "robot, return, success, keys, reaction time...) to this CSV file"),
):
    """List the played episodes (`esr play`), sum them up per robot, and export them."""
    from esr_cli.play import results, session as ps

    if export is not None and export.suffix not in (".jsonl", ".pickle", ".pkl", ".csv"):
        raise Exit(2, f"--export: {export} should end in .jsonl (steps), .pickle or .csv (Overcooked human data)")
    for path, option in ((export, "--export"), (csv_file, "--csv")):
        if path is not None:
            _refuse_inside_store(path, option)
            _check_output_file(path, option)
    if export is not None and csv_file is not None and export.resolve() == csv_file.resolve():
        raise Exit(2, "--export and --csv name the same file")
    found = ps.played_episodes(STATE.store, participant, session)
    if not found:
        raise Exit(1, f"no played episodes in {STATE.store.root}" + (" for that selection" if participant or session else ""))
    rows = results.episode_rows(found)
    if by_robot:
        _print_by_robot(results.by_robot(rows))
    else:
        _print_plays(found)
    if csv_file is not None:
        csv_file.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(csv_file, results.episodes_csv(rows).encode())
        err.print(tagged("written", "green", f" {len(rows)} episode(s): {csv_file}"))
    if export is not None and export.suffix == ".jsonl":
        from esr_cli.play.step_export import export_jsonl

        text, count = export_jsonl([STATE.store.lookup(PLAY_KIND, k) for k, _, _ in found])
        export.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(export, text.encode())
        err.print(tagged("exported", "green", f" {len(found)} episode(s), {count} steps: {export}"))
    elif export is not None:
        _export_overcooked(found, export)


def _print_by_robot(rows: list[dict]) -> None:
    from esr_cli.common.stats import format_summary

    table = Table(title="played episodes per robot: completed episodes averaged per participant, then mean ± SE and "
                        "IQM [95% bootstrap CI] across participants")
    for col in ("robot", "env", "participants", "episodes", "return", "success"):
        table.add_column(col, no_wrap=col == "robot")
    for r in rows:
        scored = "" if r["scored_participants"] == r["participants"] else f" ({r['scored_participants']} with a completed episode)"
        table.add_row(str(r["robot"]), r["env"], f"{r['participants']}{scored}", f"{r['completed']} of {r['episodes']} completed",
                      format_summary(r["return"], 2, "participant"), format_summary(r["success"], 2, "participant"))
    print_table(out, table)


def _print_plays(found) -> None:
    table = Table()
    for col in ("key", "participant", "session", "episode", "robot", "env", "completed", "steps", "return"):
        table.add_column(col, no_wrap=col == "key")  # the whole key, as human.data takes it
    for key, header, summary in found:
        env = header["env"]
        table.add_row(key, str(header["participant"]), str(header["session"]), str(header["episode"]),
                      str(header["robot"][:12]), str(env.get("layout", env["kind"])), "yes" if summary["completed"] else "no", str(summary["steps"]),
                      f"{summary['score']:g}")
    print_table(out, table)


def _export_overcooked(found, export: Path) -> None:
    from esr_cli.play import export as px

    frame, count = px.export_overcooked(STATE.store, [k for k, _, _ in found])
    if count == 0:
        raise Exit(2, "--export: none of these episodes is an Overcooked episode")
    export.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    frame.to_csv(buffer, index=False) if export.suffix == ".csv" else frame.to_pickle(buffer)
    atomic_write_bytes(export, buffer.getvalue())
    err.print(tagged("exported", "green", f" {count} Overcooked episode(s), {len(frame)} rows: {export}"))


@app.command()
def show(
    ref: str = typer.Argument(..., help="artifact key, key prefix or path", show_default=False),
    as_json: bool = typer.Option(False, "--json", help="the whole manifest, every component of the key included"),
):
    """Print what an artifact is: a readable summary, or its manifest with --json."""
    path = STATE.store.resolve(ref)
    manifest = STATE.store.read_manifest(path)
    if as_json:
        out.print(Text(printable(str(path)), style="bold"), highlight=False)
        out.print_json(json.dumps(manifest))
        return
    from esr_cli.report import listing
    from esr_cli.storage.store import Entry

    entry = Entry(path.parent.parent.name, path.name, path, "complete", manifest)
    for label, value in _show_lines(listing.row(entry), manifest):
        out.print(f"{label + ':':<14} {printable(str(value))}", highlight=False, markup=False)


def _flat_scalars(tree, prefix: str = "", depth: int = 3) -> list[tuple[str, object]]:
    """The numbers and words of a summary as dotted names (lists of many values left out)."""
    if not isinstance(tree, dict) or depth == 0:
        return []
    out = []
    for k, v in tree.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out += _flat_scalars(v, name + ".", depth - 1)
        elif isinstance(v, float):
            out.append((name, f"{v:.4g}"))
        elif isinstance(v, (int, str, bool)) or (isinstance(v, list) and len(v) <= 8 and not any(isinstance(x, (dict, list)) for x in v)):
            out.append((name, v))
    return out


def _show_lines(r: dict, manifest: dict) -> list[tuple[str, object]]:
    from esr_cli.report.listing import field

    lines = [("path", r["path"]), ("kind", r["kind"]), ("name", r["name"]), ("key", r["key"])]
    for label, value in (("budget", r["budget"]), ("seeds", r["seeds"]), ("status", r["status"]),
                         ("method", r["method"]), ("env", r["env"]), ("created", r["created"]),
                         ("commit", manifest.get("commit")), ("device", manifest.get("device")),
                         ("wall time", f"{manifest['wall_time_s']:,.0f} s" if isinstance(manifest.get("wall_time_s"), (int, float)) else None)):
        if value is not None:
            lines.append((label, value))
    if r["epochs"] is not None:
        lines.append(("epochs", f"{r['epochs']:,}" + (f" of {r['epochs_total']:,}" if r["epochs_total"] and r["epochs"] != r["epochs_total"] else "")))
    if r["kind"] == RUN_KIND:
        from esr_cli.storage.finals import run_finals

        try:
            finals = run_finals(Path(r["path"]))["return"]
        except (OSError, KeyError, TypeError, ValueError):
            finals = None
        n = finals["seeds"] - finals.get("missing", 0) if finals else 0
        if n:
            text = f"{finals['mean']:.2f}" + (f" ± {finals['se']:.2f} (SE)" if n > 1 else "") + \
                (f", IQM {finals['iqm']:.2f}" if "iqm" in finals else "")
            lines.append(("final return", f"{text} over {n} seed{'s' if n != 1 else ''} (each seed's mean over its last 10% of epochs)"))
        lines.append(("overrides", "(no spec file in experiments/ resolves to it)" if r["overrides"] is None
                      else " ".join(f"--set {shlex.quote(o)}" for o in r["overrides"]) or "none: the spec file as it is"))
    else:
        if r["final_return"] is not None:
            lines.append(("return", f"{r['final_return']:.2f} ({r['return_of']})"))
        lines += [(f"  {name}", value) for name, value in _flat_scalars(manifest.get("summary"))]
    deps = field(manifest, "key_components", "dependencies")
    if isinstance(deps, dict) and deps:
        lines.append(("depends on", ", ".join(f"{k} {v if isinstance(v, str) else ', '.join(map(str, v))}" for k, v in deps.items())))
    files = manifest.get("files")
    if isinstance(files, dict):
        lines.append(("files", f"{len(files)} (esr verify checks them); --json: the whole manifest"))
    return lines


@app.command()
def verify(ref: Optional[str] = typer.Argument(None, help="artifact key or path (default: every artifact)")):
    """Re-hash every file of an artifact against its manifest."""
    if ref is None and not STATE.store.root.is_dir():
        raise Exit(2, f"no store at {STATE.store.root}: nothing to verify")
    paths = [STATE.store.resolve(ref)] if ref is not None else [e.path for e in STATE.store.entries() if e.status == "complete"]
    if not paths:
        err.print(f"store {STATE.store.root} holds no finished artifact to verify")
    bad = 0
    for p in paths:
        problems = _verify_problems(p)
        if problems:
            bad += 1
            err.print(tagged("CORRUPT", "red", f" {p}"))
            for prob in problems:
                err.print(f"  {prob}")
        else:
            err.print(tagged("ok", "green", f" {p}"))
    if bad:
        raise Exit(1, f"{bad} of {len(paths)} artifact(s) failed verification")


def _verify_problems(path: Path) -> list[str]:
    """What `Store.verify` finds; an artifact it cannot read to the end (a disk error, say) is
    one more problem, never the end of checking the others."""
    try:
        from esr_cli.storage.checkpoint_files import verify_artifact

        return verify_artifact(STATE.store, path)
    except OSError as e:
        return [f"cannot be read to the end: {e.strerror or e}: {e.filename}"]


# ---------------------------------------------------------------- export / import
@app.command("export")
def export_(
    ref: str = typer.Argument(..., help="artifact key, key prefix or directory; an unfinished run too", show_default=False),
    out_file: Optional[Path] = typer.Option(None, "--out", "-o", help="archive to write (default: ./KEY8.tar.gz)"),
    without_checkpoint: bool = typer.Option(False, "--without-checkpoint", help="a run without its networks: a "
                                            "finished one as metrics, spec and manifest (reports and figures, not "
                                            "eval); an unfinished one as a record of its logged epochs"),
    sign: bool = typer.Option(False, "--sign", help="also write ARCHIVE.sig, an HMAC-SHA256 of the archive under the "
                              "key in the file $ESR_ARCHIVE_KEY names (`esr import --require-signature` checks it)"),
):
    """Write one artifact to a single file, to carry to another store (`esr import`). An
    unfinished run travels with its newest verified checkpoint and continues where imported."""
    from esr_cli.storage import signing

    key = signing.archive_key() if sign else None  # a missing key is named before any work
    if out_file is not None:
        if not out_file.name.endswith((".tar.gz", ".tgz")):
            raise Exit(2, f"--out: {out_file} would hold a gzipped tar archive: name it with .tar.gz")
        _check_output_file(out_file, "--out")
        _refuse_inside_store(out_file, "--out")
    from esr_cli.storage.transfer import export

    moved = export(STATE.store, ref, out_file, without_checkpoint)
    signed = f", signed in {signing.sign(moved.path, key).name}" if key else ""
    err.print(tagged("exported", "green", f" {moved.kind} {moved.key[:12]} ({moved.status}, {moved.files} files{signed})"))
    out.print(str(moved.path), highlight=False)


@app.command("import")
def import_(
    archives: List[Path] = typer.Argument(..., help="archives written by `esr export`", show_default=False),
    without_checkpoint: bool = typer.Option(False, "--without-checkpoint", help="also accept an unfinished run "
                                            "whose checkpoint did not travel: its logged epochs, for reports and "
                                            "figures; training it again starts from epoch 0"),
    require_signature: bool = typer.Option(False, "--require-signature", help="refuse an archive unless ARCHIVE.sig "
                                           "beside it matches it under the key in the file $ESR_ARCHIVE_KEY names "
                                           "(`esr export --sign`)"),
):
    """Put artifacts exported from another store into this one, each checked and then added in
    one step; an unfinished run continues with the command that started it."""
    from esr_cli.storage import signing
    from esr_cli.storage.transfer import check_archive, import_archive

    key = signing.archive_key() if require_signature else None
    for archive in archives:  # every one readable (and signed, if asked) before any is added
        if key:
            signing.check_signature(archive, key)
        check_archive(archive)
    for archive in archives:
        moved = import_archive(STATE.store, archive, without_checkpoint)
        if moved.files == 0 and moved.local_epoch is not None:
            err.print(f"{moved.kind} {moved.key[:12]} is already unfinished in the store, at epoch {moved.local_epoch}: "
                      "as far as the archive's or further, so it is kept and nothing is imported")
        elif moved.files == 0:
            err.print(f"{moved.kind} {moved.key[:12]} is already in the store: nothing to import")
        else:
            note = ("; a record without a checkpoint: training it again starts from epoch 0" if moved.record else
                    f"; it replaces this store's unfinished run of the same key, which was at epoch {moved.local_epoch}"
                    if moved.replaced_partial else "")
            err.print(tagged("imported", "green", f" {moved.kind} {moved.key[:12]} ({moved.status}, {moved.files} files{note})"))
        out.print(str(moved.path), highlight=False)


# ---------------------------------------------------------------- entry point
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
        if hasattr(e, "show") and hasattr(e, "exit_code"):  # the CLI library's usage errors
            e.show()
            return int(e.exit_code) if e.exit_code else 2
        if isinstance(e, Failure):  # each says its exit code and its line (esr_cli/common/failures.py)
            code, msg = e.exit_code, e.one_line()
        elif isinstance(e, OSError) and e.errno == errno.ENAMETOOLONG:  # a path given on the command line
            name = str(e.filename or "")
            code, msg = 2, f"file name too long: {name[:60]}{'...' if len(name) > 60 else ''} (at most 255 bytes per component)"
        else:
            code, msg = 1, f"{type(e).__name__}: {e} (run with --debug for a traceback)"
        if msg:
            err.print(tagged("error:", "red", f" {msg}"), highlight=False)
        return code


def _stopped(signum: int) -> int:
    """The one line and exit code of a command stopped by Ctrl-C or SIGTERM outside training."""
    if signum == signal.SIGINT:
        err.print("interrupted")
        return 130
    err.print(tagged("error:", "red", " terminated (SIGTERM)"), highlight=False)
    return 143


STOPPED_BY_SIGNAL = (130, 143)


def entry() -> None:
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
