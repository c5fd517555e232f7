"""Commands over suites of runs: esr sweep and esr paper."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Optional

import typer

from esr_cli.cli.app import BudgetOpt, Exit, app, check_budget, check_executor, check_output_file, draw_preview, err, out, refuse_inside_store
from esr_cli.common import jsonl
from esr_cli.common.printing import own, print_table, tagged
from esr_cli.storage.artifacts import ensure


def _refuse_ignored_sweep_options(executor, show_status, show_results, as_json, markdown, plot, any_code, wait, job_opts,
                                  results_only: dict[str, bool], plot_only: dict[str, bool]):
    """An option that would change nothing is a mistake to name, not to ignore. `results_only`:
    every other --results option (flag -> given), `plot_only`: each --plot option."""
    for flag, given in plot_only.items():
        if given and not plot:
            raise Exit(2, f"{flag} applies with --results --plot only" + (" --unfinished" if flag == "--out" else ""))
    if plot_only.get("--out") and not plot_only.get("--unfinished"):
        raise Exit(2, "--out is the folder of a preview of unfinished runs: only with --plot --unfinished "
                      "(the figure of finished runs is an artifact in the store)")
    if show_status and show_results:
        raise Exit(2, "--status and --results: choose one")
    if as_json and markdown:
        raise Exit(2, "--json and --markdown: choose one")
    for flag, given in {"--markdown": markdown, **results_only, "--plot": plot}.items():
        if given and not show_results:
            raise Exit(2, f"{flag} applies with --results only")
    if any_code and not (show_status or show_results):
        raise Exit(2, "--any-code applies with --status or --results only (a sweep trains what this code has not made)")
    if any_code and plot:
        raise Exit(2, "--any-code applies to the table: --plot draws only the runs this code made")
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
    ctx: typer.Context,
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
    exact: bool = typer.Option(False, "--exact", help="--results: also each gridworld robot's exact checks as the store "
                               "holds them, seed by seed (esr exact --robot, esr plot estimator), and the commands "
                               "that make the missing ones; computes nothing"),
    diagnose: bool = typer.Option(False, "--diagnose", help="--results: also each robot's diagnoses as the store holds "
                                  "them, seed by seed (esr diagnose RUN --seed-index I), and the commands that make "
                                  "the missing ones; computes nothing"),
    play: bool = typer.Option(False, "--play", help="--results: also each robot's play check in full as its stored "
                              "diagnoses hold it (return, the run's reward, MI estimate and the human's moves, its "
                              "robot vs a uniform one), and the commands that make the missing ones; computes nothing"),
    evals: bool = typer.Option(False, "--eval", help="--results: also each run's evaluations as the store holds them "
                               "(esr eval RUN, and --human proxy for a BC human's run), and the commands that make "
                               "the missing ones; computes nothing"),
    any_code: bool = typer.Option(False, "--any-code", help="--status / --results: a run this code has not made is read "
                                  "from a finished run of the same spec, budget and seeds made by other training code "
                                  "(another commit, device or jax: an imported archive), its row naming that commit"),
    wait: Optional[bool] = typer.Option(None, "--wait/--no-wait", help="wait for submitted jobs (default: wait, except for slurm)"),
    partition: Optional[str] = typer.Option(None, "--partition", help="slurm: partition (default: the suite's slurm.partition)"),
    time_min: Optional[int] = typer.Option(None, "--time-min", help="slurm: wall-clock limit per job, minutes"),
    gpus: Optional[int] = typer.Option(None, "--gpus", help="slurm: GPUs per job"),
    cpus: Optional[int] = typer.Option(None, "--cpus", help="slurm: CPU cores per job"),
    mem_gb: Optional[float] = typer.Option(None, "--mem-gb", help="slurm: memory per job, GB"),
):
    """Train every run of a suite that the store lacks: here, or as SLURM jobs (docs/cluster.md)."""
    from esr_cli.recipes import check_columns, sweep as sw

    check_executor(executor, sw.EXECUTORS)
    # The check columns' flags, by check_columns.REGISTRY's option names.
    check_flags = {"--exact": exact, "--diagnose": diagnose, "--play": play, "--eval": evals}
    _refuse_ignored_sweep_options(
        executor, show_status, show_results, as_json, markdown, plot, any_code, wait,
        {"--partition": partition, "--time-min": time_min, "--gpus": gpus, "--cpus": cpus, "--mem-gb": mem_gb},
        results_only={"--metric": bool(metric), **check_flags},
        plot_only={"--unfinished": unfinished, "--out": out_dir is not None})
    overrides = {"partition": partition, "time_min": time_min, "gpus": gpus, "cpus": cpus, "mem_gb": mem_gb}
    try:
        sw.slurm_options(sw.SlurmOptions(), overrides, "")  # before the suite's runs are built
    except sw.SuiteError as e:
        raise Exit(2, str(e)) from None
    try:
        suite = sw.load_suite(suite_file, budget)
        if show_results:
            metrics = tuple(dict.fromkeys(metric)) if metric else sw.DEFAULT_RESULT_METRICS
            checks = tuple(c.name for c in check_columns.REGISTRY.values() if check_flags[c.option])
            try:
                rows = sw.results(suite, ctx.obj.store, metrics, checks, any_code)  # refuses a metric no run can log
            except sw.SuiteError as e:
                raise Exit(2, str(e)) from None
            if as_json:
                out.print_json(jsonl.dumps(rows))
            elif markdown:
                out.print(own(sw.results_markdown(suite, rows, metrics, checks)), highlight=False)
            else:
                print_table(out, sw.results_table(suite, rows, metrics, checks))  # piped: every cell in full
                for line in sw.table_notes(rows, checks):  # whole lines, to copy and paste
                    out.print(line, highlight=False, soft_wrap=True)
            if plot:
                from esr_cli.report import figures as figs, paper

                try:
                    recipe = paper.suite_figure_recipe(suite, ctx.obj.store, unfinished)
                except figs.MissingRuns as e:
                    raise Exit(2, f"{e}\nor all at once: {ctx.obj.store.invocation()} sweep {shlex.quote(str(suite_file))} "
                               f"--budget {budget}", own_lines=True) from None
                if recipe.unfinished:
                    draw_preview(recipe, out_dir or Path(f"suite-{suite.name}-{budget}-unfinished"), ctx.obj.store, print_path=False)
                else:
                    if out_dir is not None:  # --unfinished, and nothing is: the stored figure, not a preview
                        err.print(f"every run is finished: the figure is an artifact in the store, not a preview in {out_dir}")
                    built = ensure(recipe, ctx.obj.store)
                    path = built.path
                    err.print(tagged("cache hit" if built.cached else "drawn", "green", f": {path / 'suite.png'}  (table: {path / 'table.md'})"))
            return
        if show_status:
            rows = sw.status(suite, ctx.obj.store)
            rows = (sw.with_runs_made_elsewhere if any_code else sw.noting_runs_made_elsewhere)(rows, ctx.obj.store)
            if as_json:
                out.print_json(jsonl.dumps(sw.status_json(rows)))
            else:
                print_table(out, sw.status_table(suite, rows))
            return
        result = sw.run_suite(suite, budget, executor, ctx.obj.store, err, wait, overrides)
    except sw.SuiteError as e:
        raise Exit(2, f"bad suite: {e}") from None
    except sw.SweepError as e:
        raise Exit(1, str(e)) from None
    for p in result.paths:
        if p is not None:
            out.print(str(p), highlight=False)
    done = sum(p is not None for p in result.paths)
    err.print(tagged(f"{done} of {len(result.paths)} run(s) done", "green", f"; {len(result.submitted)} "
                     f"{'run' if executor == 'local' else 'submitted'} this time; `{ctx.obj.store.invocation()} sweep --status {suite_file} --budget {budget}` shows each"))
    if result.failed:
        raise Exit(1, f"{len(result.failed)} run(s) failed: " + "; ".join(f"{r.label}: {m}" for r, m in result.failed))
    if result.stopped:  # saved at a time budget or when cancelled: resumable, like `esr train --stop-after`
        raise Exit(75, f"{len(result.stopped)} run(s) stopped and saved (" + "; ".join(f"{r.label}: {why}" for r, why in result.stopped)
                   + "); run the same sweep again to continue them")


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
        check_budget(budget)
    from esr_cli.recipes import sweep as sw
    from esr_cli.report import figures as figs, paper

    if not report:
        check_executor(executor, sw.EXECUTORS)

    if report:
        from esr_cli.report import reproduction

        # Before any work: a report written into an artifact would be a file its manifest does not
        # list, and one drawn from a mistyped store would be every row "not yet run".
        if check and not report_out.is_file():  # a pipe or a device is never read
            raise Exit(2, f"--out: {report_out} is {'not a regular file' if report_out.exists() else 'not there'}: nothing to check")
        if not check:
            check_output_file(report_out, "--out")
        refuse_inside_store(report_out, "--out", ctx.obj.store)
        if not ctx.obj.store.root.is_dir():
            raise Exit(2, f"no store at {ctx.obj.store.root}: no runs to report on (--store names one)")
        if check:
            differences = reproduction.check(ctx.obj.store, report_out, err, exact=exact)
            if differences:
                err.print(f"{report_out} differs from what the store's runs give now "
                          f"(esr paper --report --out {report_out} brings it up to date):", highlight=False)
                for line in differences:  # each line escaped: the file on disk may hold anything
                    err.print(line, highlight=False)
                raise Exit(1, f"{report_out} is stale")
            err.print(tagged("reproduction report", "green", f": {report_out} is what the store's runs give"))
            return
        findings = reproduction.report(ctx.obj.store, report_out, err, exact=exact)
        err.print(reproduction.summary_line(findings))
        err.print(tagged("reproduction report", "green", f": {report_out}"))
        if as_json:
            out.print(own(jsonl.dumps(reproduction.findings_json(findings), indent=2)), highlight=False)
        else:
            out.print(str(report_out), highlight=False)
        return
    try:
        path = paper.make_paper(ctx.obj.store, budget, executor, err)
    except sw.SuiteError as e:
        raise Exit(2, f"bad suite: {e}") from None
    except (sw.SweepError, figs.MissingRuns) as e:
        raise Exit(1, str(e), own_lines=isinstance(e, figs.MissingRuns)) from None
    err.print(tagged("report", "green", f": {path / 'report.md'}"))
    out.print(str(path / "report.md"), highlight=False)


@app.command("tables")
def tables(
    ctx: typer.Context,
    files: list[Path] = typer.Argument(..., help="markdown files whose generated tables to bring up to date", show_default=False),
    check: bool = typer.Option(False, "--check", help="write nothing; exit 1 if a table differs from what the store gives now"),
):
    """Result tables inside markdown files, generated from the store: each table between
    `<!-- esr sweep SUITE ... --results --markdown -->` (or `<!-- esr human calibrate SPEC...
    --markdown -->`) and `<!-- end of generated table -->` is that command's output, read from
    the store (docs/cluster.md)."""
    from esr_cli.report import doc_tables

    for path in files:
        if not path.is_file():
            raise Exit(2, f"{path}: {'not a regular file' if path.exists() else 'no such file'}")
        if not check:  # an artifact's own page is never rewritten
            refuse_inside_store(path, "FILE", ctx.obj.store)
    if not ctx.obj.store.root.is_dir():
        raise Exit(2, f"no store at {ctx.obj.store.root}: no runs to draw tables from (--store names one)")
    try:
        if check:
            differences, counts = doc_tables.check(files, ctx.obj.store)
            if differences:
                for line in differences:  # each line escaped: the file on disk may hold anything
                    err.print(line, highlight=False)
                raise Exit(1, "generated tables are stale: `esr tables FILE...` brings them up to date")
            err.print(tagged("tables", "green", f": every generated table ({sum(counts):,} in {len(files)} file(s)) is what the store gives"))
            for path, count in zip(files, counts):
                if not count:
                    err.print(tagged("tables", "yellow", f": {path} holds no generated table"), highlight=False)
            return
        for path, count, changed in doc_tables.update(files, ctx.obj.store):
            err.print(tagged("tables", "green", f": {path}: {count} table(s), {'rewritten' if changed else 'unchanged'}"))
    except doc_tables.TableError as e:
        raise Exit(2, str(e)) from None

