"""Figures, the paper report and ablations as artifacts (docs/paper.md).

- `figure_recipe`: one figure of esr_cli.report.figures as a `figures` artifact, keyed by the figure,
  the budget, the keys of the runs it reads and the plotting code. Never trains.
- `ensure_report`: every figure, then a report artifact (report.md with the figures inline).
- `suite_figure_recipe`: the learning curves and final-return table of a suite's runs.
- `make_paper`: train what the paper suite lacks (esr sweep's executors), then the report.
- `ablate`: a base spec (or the gridworld suite) and its ablated variants -> one comparison
  artifact (figure + table, mean ± SE across seeds); runs already in the store are reused.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from rich.console import Console

from esr_cli.common import bounded_files, specs
from esr_cli.common.printing import tagged
from esr_cli.common.stats import format_summary
from esr_cli.model import spec as spec_model
from esr_cli.recipes import sweep
from esr_cli.report import figures as figs
from esr_cli.storage import provenance
from esr_cli.storage.artifacts import Recipe, ensure, read_summary
from esr_cli.storage.store import FIGURE_KIND, RUN_KIND, Store, StoreError, atomic_write_text, content_key

PLOT_SOURCES = ("report/figures.py", "common/plots.py", "report/paper.py", "analysis")


def figure_key(inputs: figs.PaperInputs, figure: str) -> tuple[str, dict, list[Path]]:
    paths = inputs.paths(figure, figs.WANTS[figure]())
    components = {"kind": "figure", "figure": figure, "budget": inputs.budget,
                  "inputs": [inputs.key(p) for p in paths],
                  "code": provenance.code_digest(PLOT_SOURCES)}
    return content_key(components), components, paths


def figure_recipe(store: Store, budget: str, name: str, inputs: Optional[figs.PaperInputs] = None) -> Recipe:
    """`esr plot NAME --budget B`. Raises figs.MissingRuns when a run it reads is not trained
    (with `inputs.unfinished`, not started). A recipe that reads an unfinished run is a preview:
    `preview(recipe, dir)` draws it outside the store."""
    figure, draw = figs.FIGURES[name]
    inputs = inputs or figs.PaperInputs(store, budget)
    _, components, paths = figure_key(inputs, figure)
    seeds = sorted({s for p in paths for s in inputs.seeds(p)})

    def build(out: Path, store: Store) -> dict:
        result = draw(inputs, out)
        return {"figure": figure, "files": [f.name for f in result.files], "provenance": result.provenance, **result.summary}

    return Recipe(FIGURE_KIND, figure, components, build, budget=budget, seeds=tuple(seeds),
                  unfinished=tuple(figs.unfinished_note(*inputs.progress[p]) for p in paths if p in inputs.progress))


MAX_FIGURE_FILE_BYTES = 64 << 20  # a figure's PNG, PDF or table: a few MiB at most


def _copy_figure_file(figure_dir: Path, name, into: Path) -> None:
    """One file a stored figure's summary lists, copied into the report: a plain name inside the
    figure's folder, a regular file of bounded size (a summary or a file edited by hand is refused)."""
    if not isinstance(name, str) or Path(name).name != name or name in ("", ".", ".."):
        raise StoreError(f"damaged figure: {figure_dir}: its summary lists {str(name)[:80]!r}, which is not a file in its folder")
    try:
        bounded_files.copy_file(figure_dir / name, into / name, MAX_FIGURE_FILE_BYTES)
    except (bounded_files.UnreadableInput, OSError) as e:
        raise StoreError(f"damaged figure: {figure_dir / name}: {e}") from None


def read_figure_file(path: Path) -> bytes:
    """One file of a stored figure, as a bounded regular file; StoreError naming it where it is not."""
    try:
        return bounded_files.read_bytes(path, MAX_FIGURE_FILE_BYTES)
    except (bounded_files.UnreadableInput, OSError) as e:
        raise StoreError(f"damaged figure: {path}: {e}") from None


def _figure_text(path: Path) -> str:
    try:
        return read_figure_file(path).decode()
    except UnicodeDecodeError as e:
        raise StoreError(f"damaged figure: {path}: {e}") from None


def ensure_report(store: Store, budget: str, console: Console) -> Path:
    """Every figure (artifacts), then the report artifact with them inline."""
    from esr_cli.model.train import release_compiled  # some figures compile programs (jax)

    inputs = figs.PaperInputs(store, budget)
    made = {}
    for name, (figure, _) in figs.FIGURES.items():
        release_compiled()
        built = ensure(figure_recipe(store, budget, name, inputs), store)
        console.print(f"  {figure}: {'cache hit' if built.cached else 'drawn'} {built.path}")
        made[figure] = built.path
    components = {"kind": "report", "budget": budget, "figures": {f: p.name for f, p in made.items()},
                  "code": provenance.code_digest(PLOT_SOURCES)}

    def build(out: Path, store: Store) -> dict:
        lines = [f"# ESR paper figures ({budget} budget)", "",
                 f"Made by `make paper-figures BUDGET={budget}` from the runs of `experiments/suites/paper.yaml`. "
                 "Each figure's sidecar JSON lists the training-run keys it read; `esr show KEY` prints a run's spec.", ""]
        for figure, path in made.items():
            summary = read_summary(path)
            (out / figure).mkdir()
            for f in summary["files"]:
                _copy_figure_file(path, f, out / figure)
            doc = _FIGURE_DOCS[figure]
            lines += [f"## {doc[0]}", "", doc[1], "", f"![{figure}]({figure}/{figure}.png)", "",
                      f"Artifact: `{path.name}`; runs: {len(summary['provenance']['artifacts'].get('runs', []))}; "
                      f"seeds: {summary['provenance'].get('seeds')}", ""]
            if figure == "fig2_overcooked":
                lines += [_figure_text(path / "fig2_overcooked.md"), ""]
            if "final_return" in summary and figure != "fig2_overcooked":
                lines += _final_table(summary["final_return"]) + [""]
        atomic_write_text(out / "report.md", "\n".join(lines))
        return {"figures": {f: p.name for f, p in made.items()}, "report": "report.md"}

    return ensure(Recipe(FIGURE_KIND, f"paper-report-{budget}", components, build, budget=budget), store).path


def suite_figure_recipe(suite, store: Store, unfinished: bool = False) -> Recipe:
    """`esr sweep SUITE --results --plot`: learning curves of every run of a suite (one panel
    per environment) and their final-return table, keyed by the runs and the plotting code.
    unfinished: runs still training are drawn as far as they have got (the recipe is then a
    preview). Raises figs.MissingRuns; never trains."""
    found = [figs.find_run(store, run, unfinished) for run in suite.runs]
    missing = [run.command(suite.budget, store.invocation()) for run, (p, _) in zip(suite.runs, found) if p is None]
    if missing:
        raise figs.MissingRuns(f"suite {suite.name}", missing)
    keys = [run.key for run in suite.runs]
    components = {"kind": "suite_figure", "suite": suite.name, "budget": suite.budget, "runs": keys,
                  "code": provenance.code_digest(PLOT_SOURCES)}
    seeds = sorted({int(s) for run in suite.runs for s in run.spec.train.seeds})
    warmups = {getattr(run.spec.learner, "warmup_epochs", 0) for run in suite.runs}
    notes = [figs.unfinished_note(run, epochs) for run, (_, epochs) in zip(suite.runs, found) if epochs is not None]

    def build(out: Path, store: Store) -> dict:
        paths = [p for p, _ in found]
        fig, table = figs.panels_figure(figs.suite_panels(list(zip(suite.runs, paths))), f"suite {suite.name}", "return",
                                        warmups.pop() if len(warmups) == 1 else 0, suite.budget)
        prov = {"figure": "suite", "suite": suite.name, "artifacts": {"runs": keys}, "budget": suite.budget,
                "seeds": seeds, "runs": {run.label: k for run, k in zip(suite.runs, keys)},
                **({"unfinished": notes} if notes else {})}
        figs.save(fig, out, "suite", prov)
        head = [f"UNFINISHED, as far as these runs have got: {'; '.join(notes)}", ""] if notes else []
        atomic_write_text(out / "table.md", "\n".join(head + _final_table(table)) + "\n")
        return {"final_return": table, "provenance": prov}

    return Recipe(FIGURE_KIND, f"suite {suite.name}", components, build, budget=suite.budget, seeds=tuple(seeds),
                  unfinished=tuple(notes))


def _final_table(table: dict) -> list[str]:
    """Markdown: rows = lines (methods), columns = panels; final return mean ± SE."""
    panels = list(table)
    labels = list(dict.fromkeys(label for p in panels for label in table[p]))
    out = ["Final return (mean over the last 10% of epochs per seed; mean ± SE across seeds and the "
           "interquartile mean with its 95% stratified bootstrap interval; no SE where a run has one seed):", "",
           "| | " + " | ".join(panels) + " |", "|---" * (len(panels) + 1) + "|"]

    for label in labels:
        cells = [format_summary(table[p][label]) if label in table[p] else "" for p in panels]
        out.append(f"| {label} | " + " | ".join(cells) + " |")
    return out


_FIGURE_DOCS = {
    "fig1_gridworld": ("Figure 1: the obstacle gridworld", "Return (steps the human spends on its goal, of 50) during training for every method, N = 2, 5, 7, 10 blocks; ±1 SE shading."),
    "fig2_overcooked": ("Figure 2: Overcooked", "Final training return per 400-step episode with the BC human, next to the paper's numbers."),
    "fig3_no_robot_action": ("Figure 3: ablation without the robot action", "ESR against ESR whose phi and phi' do not see the robot's action."),
    "fig4_greedy": ("Figure 4: greedy ablation", "ESR against ESR with critic discount 0 (the future-state horizon unchanged)."),
    "fig5_mutual_information": ("Figure 5: the MI estimate during training", "Mean diagonal logit of phi minus that of phi' (nats) and contrastive accuracy against chance, ESR runs of figure 1."),
    "fig6_representations": ("Figure 6: 3-dimensional representations", "psi(s) of an ESR run with repr_dim 3 on the N = 10 gridworld, coloured by how many cells the human can reach."),
    "fig7_geometry": ("Figure 7: information geometry", "The state-marginal polytope of a 3-state MDP, its capacity centre and the KL distance to each vertex, computed exactly."),
    "fig8_filmstrip": ("Figure 8: a coordination-ring rollout", "Frames of one episode with the trained ESR robot (agent 0) and the BC human."),
}


def make_paper(store: Store, budget: str, executor: str, console: Console) -> Path:
    """Train the paper suite's missing runs with `executor`, then the report. -> report dir."""
    result = sweep.run_suite(figs.PAPER_SUITE, budget, executor, store, console)
    if result.failed:
        raise sweep.SweepError(f"{len(result.failed)} run(s) failed: " + "; ".join(f"{r.label}: {m}" for r, m in result.failed))
    if not result.complete:
        raise sweep.SweepError("runs were submitted; when they finish, run the same command again to draw the report "
                               f"(`{store.invocation()} sweep --status {figs.PAPER_SUITE} --budget {budget}` shows them)")
    return ensure_report(store, budget, console)


# ---------------------------------------------------------------- ablations
NAMED_ABLATIONS = {
    "no_robot_action": ("no robot action", ("method.condition_on_robot_action=false",)),
    "greedy": ("greedy critic", ("learner.gamma=0.0",)),
}
# (the methods a named ablation changes, in words for the refusal)
ABLATION_APPLIES = {
    "no_robot_action": (lambda spec: spec.method.kind == "esr", "ESR's representations (method.kind: esr)"),
    "greedy": (lambda spec: spec.method.kind not in spec_model.POLICY_FREE_METHODS,
               "a method that learns a critic (the Random and Goal Inference robots learn none)"),
}
# The package's own spec files, wherever esr is run from.
DEFAULT_ABLATION_SPECS = tuple(str(figs.PAPER_SUITE.parents[1] / f"grid_{n}.yaml") for n in figs.GRID_NS)


@dataclass
class Variant:
    name: str
    sets: tuple[str, ...]


def ablation_variants(names: list[str], custom: list[str]) -> list[Variant]:
    """The base spec first, then each named ablation, then one variant of all --set values."""
    variants = [Variant("base", ())]
    for n in names:
        label, sets = NAMED_ABLATIONS[n]
        variants.append(Variant(label, sets))
    if custom:
        variants.append(Variant(" ".join(custom), tuple(custom)))
    return variants


def ablate(spec_paths: list[str], names: list[str], custom: list[str], budget: str, store: Store,
           console: Console) -> tuple[Path, dict]:
    """Train (or reuse) each spec and its variants; -> (comparison artifact, final-return table)."""
    variants = ablation_variants(names, custom)
    loaded = []  # (spec path, variant, spec)
    seen = {}
    for path in spec_paths or DEFAULT_ABLATION_SPECS:
        base = specs.load(path, budget)
        if base.training_part() in seen.values():
            raise specs.SpecError(path, "", f"the same training run as {next(p for p, t in seen.items() if t == base.training_part())}: "
                                  "name each base spec once")
        seen[path] = base.training_part()
        for n in names:
            applies, what = ABLATION_APPLIES[n]
            if not applies(base):
                raise specs.SpecError(path, "method", f"--{n.replace('_', '-')} ablates {what}; this spec's method is {base.method.kind!r}")
        for v in variants:  # all validated before any work
            spec = specs.load(path, budget, list(v.sets)) if v.sets else base
            if v.sets and spec.training_part() == base.training_part():
                raise specs.SpecError(path, "", f"the variant {v.name!r} ({' '.join(v.sets)}) is the base spec's own "
                                      "training run: it changes nothing to compare")
            twin = next((w for p, w, other in loaded if p == path and other.training_part() == spec.training_part()), None)
            if twin is not None:
                raise specs.SpecError(path, "", f"the variants {twin.name!r} and {v.name!r} are the same training run: "
                                      "name each ablation once")
            loaded.append((path, v, spec))

    from esr_cli.model.train import release_compiled
    from esr_cli.recipes import runs  # jax and the training core: after every spec is validated
    from esr_cli.runner.resources import check_run_fits

    for path, v, spec in loaded:  # every run still to train fits, before the first trains for hours
        if store.lookup(RUN_KIND, runs.run_key(spec)[0]) is None:
            check_run_fits(spec)

    run_paths = []
    for i, (path, v, spec) in enumerate(loaded, 1):
        console.print(tagged(f"({i}/{len(loaded)})", "bold", f" {spec.name} [{v.name}]"))
        release_compiled()
        built = ensure(runs.run_recipe(spec, console), store)
        if built.cached:
            console.print(f"  cache hit: {built.path}")
        run_paths.append(built.path)
    keys = [store.read_manifest(p)["key"] for p in run_paths]
    components = {"kind": "ablation", "budget": budget, "variants": [[v.name, list(v.sets)] for v in variants],
                  "runs": keys, "code": provenance.code_digest(PLOT_SOURCES)}
    seeds = sorted({s for p in run_paths for s in store.read_manifest(p).get("seeds", [])})
    colors = ["C0", "C3", "C2", "C1", "C4"]

    def build(out: Path, store: Store) -> dict:
        panels, it = [], iter(run_paths)
        for path in spec_paths or DEFAULT_ABLATION_SPECS:
            lines = [(v.name, colors[j % len(colors)], figs.read_rows(next(it))) for j, v in enumerate(variants)]
            panels.append((Path(path).stem, lines))
        title = f"Ablation: {', '.join(v.name for v in variants[1:])}"
        fig, table = figs.panels_figure(panels, title, "return", budget=budget)
        prov = {"figure": "ablation", "artifacts": {"runs": keys}, "budget": budget, "seeds": seeds,
                "variants": {v.name: list(v.sets) for v in variants}}
        figs.save(fig, out, "ablation", prov)
        atomic_write_text(out / "table.md", "\n".join(_final_table(table)) + "\n")
        return {"final_return": table, "provenance": prov}

    built = ensure(Recipe(FIGURE_KIND, "ablation", components, build, budget=budget, seeds=tuple(seeds)), store)
    return built.path, built.summary()["final_return"]
