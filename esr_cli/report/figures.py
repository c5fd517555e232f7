"""The paper's figures and tables, drawn from training runs in the store (docs/paper.md).

Each figure is one function `(inputs, out_dir) -> FigureResult` over `PaperInputs`, which maps
the runs of `experiments/suites/paper.yaml` (at one budget) to their committed artifacts.
Nothing here trains: a missing run raises `MissingRuns`, which names the commands that make it.
Every figure is saved as PNG and PDF with a sidecar JSON (and PNG metadata) holding the keys of
the artifacts it used, the budget and the seeds.
"""

from __future__ import annotations

import json
import textwrap
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from esr_cli.common import specs  # noqa: E402
from esr_cli.common.plots import smooth  # noqa: E402
from esr_cli.common.stats import describe, format_summary  # noqa: E402
from esr_cli.recipes import suite as suites  # noqa: E402
from esr_cli.storage.finals import final_per_seed, read_rows, series  # noqa: E402
from esr_cli.storage.provenance import experiments_dir  # noqa: E402
from esr_cli.storage.store import RUN_KIND, Store  # noqa: E402

PAPER_SUITE = experiments_dir() / "suites" / "paper.yaml"
GRID_NS = (2, 5, 7, 10)
GRID_METHODS = ("esr", "ave", "goal_inference", "iq_learn", "random", "oracle")
# One label and one colour per method, in every figure. A user's own runs are labelled by what
# their specs say; the paper's figures use the paper's names (PAPER_LABELS).
METHOD_LABELS = {
    "esr": "ESR",
    "ave": "AvE",
    "goal_inference": "Goal Inference",
    "iq_learn": "Reward Inference (iq_learn)",
    "random": "Random",
    "oracle": "Oracle (sees goal)",
}
PAPER_LABELS = {**METHOD_LABELS, "esr": "ESR (ours)", "iq_learn": "Reward Inference"}
METHOD_COLORS = {"esr": "C0", "ave": "C1", "goal_inference": "C2", "iq_learn": "C3", "random": "0.45", "oracle": "C4"}
# ESR's ablations, drawn beside ESR: colours no method uses.
ABLATION_COLORS = {"no_robot_action": "C5", "greedy": "C6"}
OVERCOOKED_LAYOUTS = ("cramped_room", "coord_ring", "asymm_advantages")
OVERCOOKED_METHODS = ("esr", "iq_learn", "ave", "random")
# The paper's published Overcooked table, mean +- SE (Random: mean only; docs/paper-facts.md).
PAPER_OVERCOOKED = {
    "asymm_advantages": {"esr": (72.00, 5.37), "iq_learn": (60.33, 0.26), "ave": (36.71, 1.71), "random": (59.36, None)},
    "coord_ring": {"esr": (8.40, 0.69), "iq_learn": (5.96, 0.20), "ave": (5.69, 0.93), "random": (6.02, None)},
    "cramped_room": {"esr": (91.33, 4.08), "iq_learn": (39.24, 0.35), "ave": (5.13, 1.31), "random": (69.26, None)},
}
ABLATION_SETS = {
    "no_robot_action": ("method.condition_on_robot_action=false",),
    "greedy": ("learner.gamma=0.0",),
}
# The baselines as the paper ran them (its figures' lines): the published AvE and Du et al.'s
# Goal Inference; the spec files' defaults are esr's versions, drawn beside them as esr's.
PUBLISHED_SETS = {"ave": ('method.variant="original"',), "goal_inference": ('method.variant="original"',)}
# esr's own lines in the paper's figures: dotted, in their method's colour, never in place of one.
ESRS_STYLE = ":"
ESRS_EXTRA_LINES = (
    ("esr", "grid_{n}", ('method.future="human"',), "ESR, human future (esr's)"),
    ("ave", "grid_{n}_ave", (), "AvE, sampling fixed (esr's)"),
    ("goal_inference", "grid_{n}_goal_inference", (), "Goal Inference, exact posterior (esr's)"),
)
REPRESENTATION_SETS = ("method.repr_dim=3",)


class MissingRuns(Exception):
    """Some runs a figure needs are not in the store; `commands` make them."""

    def __init__(self, figure: str, commands: list[str]):
        self.figure, self.commands = figure, commands
        super().__init__(f"{figure} needs {len(commands)} run(s) the store lacks; make them with:\n  " + "\n  ".join(commands))


@dataclass
class FigureResult:
    name: str
    files: list[Path]
    provenance: dict
    summary: dict = field(default_factory=dict)


# Figures that restore a run's final state (its networks), not only its metrics: an unfinished
# run has none, so they read finished runs only, with or without `unfinished`.
NEEDS_FINAL_STATE = frozenset({"fig6_representations", "fig8_filmstrip"})


def find_run(store: Store, run, unfinished: bool = False) -> tuple[Path | None, int | None]:
    """A suite run's committed artifact -> (path, None); with `unfinished`, else its partial
    directory once it has logged an epoch -> (path, epochs logged); (None, None): neither."""
    path = store.lookup(RUN_KIND, run.key)
    if path is not None or not unfinished:
        return path, None
    part = store.partial_path(RUN_KIND, run.key)
    rows = read_rows(part) if part.is_dir() else []
    return (part, int(rows[-1]["epoch"])) if rows else (None, None)


def unfinished_note(run, epochs: int) -> str:
    return f"{run.label}: epoch {epochs:,} of {run.spec.train.epochs:,}"


class PaperInputs:
    """The paper suite at one budget, resolved against a store. unfinished: runs still training
    are read as far as they have got (a preview, never a stored figure: see `progress`)."""

    def __init__(self, store: Store, budget: str, suite_path: Path = PAPER_SUITE, unfinished: bool = False):
        self.store, self.budget, self.unfinished = store, budget, unfinished
        self.suite = suites.load(suite_path, budget)
        self._by_name = {(run.spec_path.stem, tuple(run.sets)): run for run in self.suite.runs}
        self.progress: dict[Path, tuple[object, int]] = {}  # unfinished runs read: path -> (run, epochs logged)

    def run(self, stem: str, sets: tuple[str, ...] = ()):
        return self._by_name[(stem, tuple(sets))]

    def paths(self, figure: str, wanted: list[tuple[str, tuple[str, ...]]]) -> list[Path]:
        """The artifacts of `wanted` runs (committed, or with `unfinished` partial, unless the
        figure NEEDS_FINAL_STATE), or MissingRuns naming the commands."""
        runs = [self.run(stem, sets) for stem, sets in wanted]
        partial_ok = self.unfinished and figure not in NEEDS_FINAL_STATE
        found = [find_run(self.store, r, partial_ok) for r in runs]
        missing = [r.command(self.budget, self.store.invocation()) for r, (p, _) in zip(runs, found) if p is None]
        if missing:
            raise MissingRuns(figure, missing)
        for r, (p, epochs) in zip(runs, found):
            if epochs is not None:
                self.progress[p] = (r, epochs)
        return [p for p, _ in found]

    def key(self, path: Path) -> str:
        return self.progress[path][0].key if path in self.progress else self.store.read_manifest(path)["key"]

    def seeds(self, path: Path) -> list[int]:
        if path in self.progress:
            return [int(s) for s in self.progress[path][0].spec.train.seeds]
        return list(self.store.read_manifest(path).get("seeds", []))

    def provenance(self, figure: str, paths: list[Path], **extra) -> dict:
        seeds = sorted({s for p in paths for s in self.seeds(p)})
        unfinished = [unfinished_note(*self.progress[p]) for p in paths if p in self.progress]
        return {"figure": figure, "artifacts": {"runs": [self.key(p) for p in paths]}, "budget": self.budget,
                "seeds": seeds, "suite": str(self.suite.path.name), **extra, **({"unfinished": unfinished} if unfinished else {})}


def _smooth(y: np.ndarray, window: int) -> np.ndarray:
    return smooth(y, window)


def _band(ax, rows: list[dict], name: str, color, label: str, style: str = "-") -> None:
    epochs, vals = series(rows, name)
    vals = _smooth(vals, max(1, len(rows) // 50))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # one seed: no spread, SE shown as 0
        mean = np.nanmean(vals, axis=1)
        n = np.isfinite(vals).sum(axis=1)
        se = np.where(n > 1, np.nanstd(vals, axis=1, ddof=1) / np.sqrt(np.maximum(n, 1)), 0.0)
    ax.plot(epochs, mean, style, color=color, label=label, lw=1.6, marker="o" if len(epochs) == 1 else None)  # one epoch: a point
    ax.fill_between(epochs, mean - se, mean + se, color=color, alpha=0.2, linewidth=0)


def _style():
    plt.rcParams.update({"font.size": 9, "axes.spines.top": False, "axes.spines.right": False, "figure.dpi": 110})


def save(fig, out_dir: Path, name: str, provenance: dict) -> list[Path]:
    """PNG (provenance in its metadata) + PDF (in its Subject) + sidecar JSON."""
    out_dir.mkdir(parents=True, exist_ok=True)
    if provenance.get("unfinished"):  # said on the figure itself, as well as in its metadata
        note = "UNFINISHED, drawn as far as these runs have got: " + "; ".join(provenance["unfinished"])
        title, width = fig.get_suptitle(), int(fig.get_figwidth() * 13)
        fig.suptitle("\n".join(filter(None, (title, textwrap.fill(note, width)))), fontsize=9, color="C3")
        fig.tight_layout()
    text = json.dumps(provenance, sort_keys=True)
    png, pdf, side = out_dir / f"{name}.png", out_dir / f"{name}.pdf", out_dir / f"{name}.json"
    fig.savefig(png, dpi=130, metadata={"Description": text})
    fig.savefig(pdf, metadata={"Subject": text})
    plt.close(fig)
    side.write_text(json.dumps(provenance, indent=2, sort_keys=True))
    return [png, pdf, side]


# ---------------------------------------------------------------- figures 1, 3, 4
def seeds_phrase(counts) -> str:
    """How a figure's lines aggregate seeds: one seed has no standard error to shade."""
    counts = sorted(set(counts))
    if counts == [1]:
        return "1 seed, no SE"
    span = str(counts[0]) if len(counts) == 1 else f"{counts[0]} to {counts[-1]}"
    return f"mean ± 1 SE over {span} seeds"


def panels_figure(panels: list[tuple[str, list[tuple[str, str, list[dict]]]]], title: str, ylabel: str,
                  warmup_epochs: int = 0, budget: str | None = None, legend_each: bool = False):
    """One panel per entry (title, [(label, colour, metric rows[, line style])]): return vs epoch, mean ± 1 SE
    over seeds; epochs 1..warmup_epochs (a uniform robot) shaded. The title gains
    "[budget, how seeds aggregate]". legend_each: a legend in every panel (when panels hold
    different lines), else one beside the last.
    -> (figure, {panel: {label: {mean, se, seeds}}}) with each line's final return."""
    _style()
    width = 3.25 * len(panels) + 0.5 + (1.7 if len(panels) < 3 else 0.0)  # room for the legend beside few panels
    fig, axes = plt.subplots(1, len(panels), figsize=(width, 3.2), sharey=True, squeeze=False)
    table: dict = {}
    for ax, (panel, lines) in zip(axes[0], panels):
        table[panel] = {}
        if warmup_epochs:
            ax.axvspan(0.5, warmup_epochs + 0.5, color="0.5", alpha=0.15, lw=0, label="warm-up (learners act uniformly)")
        for label, color, rows, *style in lines:  # (label, colour, rows[, line style])
            _band(ax, rows, "return", color, label, style[0] if style else "--" if label == "Random" else "-")
            table[panel][label] = describe(final_per_seed(rows) if rows else [])
        ax.set_title(panel)
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
        if legend_each:
            ax.legend(fontsize=7, loc="best")
    axes[0][0].set_ylabel(ylabel)
    if not legend_each:
        axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    counts = [row["seeds"] for lines in table.values() for row in lines.values()]
    title = f"{title}  [{budget + ' budget, ' if budget else ''}{seeds_phrase(counts)}]"
    fig.suptitle(textwrap.fill(title, int(width * 12)), fontsize=10)
    fig.tight_layout()
    return fig, table


def _grid_panels(inputs: PaperInputs, figure: str, title: str, lines: list[tuple[str, str, tuple[str, ...], str, str, str]],
                 out_dir: Path) -> FigureResult:
    """4 panels (N = 2, 5, 7, 10); `lines`: (key, spec stem pattern with {n}, sets, label, colour, style)."""
    wanted = WANTS[figure]()
    paths = inputs.paths(figure, wanted)
    it = iter(paths)
    panels = [(f"N = {n} blocks", [(label, color, read_rows(next(it)), style) for _, _, _, label, color, style in lines])
              for n in GRID_NS]
    warmups = {inputs.run(stem, sets).spec.learner.warmup_epochs for stem, sets in wanted}
    fig, table = panels_figure(panels, title, "return (steps on goal, of 50)", max(warmups) if len(warmups) == 1 else 0,
                               inputs.budget)
    prov = inputs.provenance(figure, paths)
    return FigureResult(figure, save(fig, out_dir, figure, prov), prov, {"final_return": table})


def env_title(spec) -> str:
    """A panel title naming a spec's environment."""
    env = spec.env
    if env.kind == "gridworld":
        size = "" if env.size == 5 else f", {env.size}x{env.size}"
        return f"gridworld N = {env.blocks}{size}" + ("" if env.start == "corner" else f", {env.start} start")
    return getattr(env, "layout", env.kind)


def suite_panels(runs: list[tuple[object, Path]]) -> list[tuple[str, list[tuple[str, str, list[dict]]]]]:
    """A suite's (run, artifact) pairs as panels: one per environment, one line per run, named
    and coloured by method (by the run's label where a panel has a method twice)."""
    groups: dict[str, list] = {}
    for run, path in runs:
        groups.setdefault(env_title(run.spec), []).append((run, path))
    panels = []
    for title, members in groups.items():
        kinds = [run.spec.method.kind for run, _ in members]
        lines = []
        for j, (run, path) in enumerate(members):
            kind = run.spec.method.kind
            unique = kinds.count(kind) == 1
            label = METHOD_LABELS.get(kind, kind) if unique else run.label
            color = METHOD_COLORS.get(kind, f"C{j % 10}") if unique else f"C{j % 10}"
            lines.append((label, color, read_rows(path)))
        panels.append((title, lines))
    return panels


GRID_LINES = [(m, "grid_{n}" if m == "esr" else "grid_{n}_" + m, PUBLISHED_SETS.get(m, ()), PAPER_LABELS[m], METHOD_COLORS[m],
               "--" if m == "random" else "-") for m in GRID_METHODS]
GRID_LINES += [(m, stem, sets, label, METHOD_COLORS[m], ESRS_STYLE) for m, stem, sets, label in ESRS_EXTRA_LINES]


def _ablation_lines(which: str, label: str):
    return [
        ("esr", "grid_{n}", (), "ESR", METHOD_COLORS["esr"], "-"),
        (which, "grid_{n}", ABLATION_SETS[which], label, ABLATION_COLORS[which], "-"),
        ("random", "grid_{n}_random", (), "Random", METHOD_COLORS["random"], "--"),
    ]


ABLATION_LABELS = {"no_robot_action": "ESR without aR in phi, phi'", "greedy": "ESR, greedy critic (gamma = 0)"}


def _grid_wants(lines) -> list[tuple[str, tuple[str, ...]]]:
    return [(stem.format(n=n), sets) for n in GRID_NS for _, stem, sets, _, _, _ in lines]


# Which runs of the paper suite each figure reads, in the order it reads them.
WANTS: dict[str, Callable[[], list[tuple[str, tuple[str, ...]]]]] = {
    "fig1_gridworld": lambda: _grid_wants(GRID_LINES),
    "fig2_overcooked": lambda: [(lay if m == "esr" else f"{lay}_{m}", PUBLISHED_SETS.get(m, ()))
                                for lay in OVERCOOKED_LAYOUTS for m in OVERCOOKED_METHODS],
    "fig3_no_robot_action": lambda: _grid_wants(_ablation_lines("no_robot_action", "")),
    "fig4_greedy": lambda: _grid_wants(_ablation_lines("greedy", "")),
    "fig5_mutual_information": lambda: [(f"grid_{n}", ()) for n in GRID_NS],
    "fig6_representations": lambda: [("grid_10", REPRESENTATION_SETS)],
    "fig7_geometry": lambda: [],
    "fig8_filmstrip": lambda: [("coord_ring", ())],
}


def gridworld_curves(inputs: PaperInputs, out_dir: Path) -> FigureResult:
    """Figure 1: every method's return on the four gridworlds."""
    return _grid_panels(inputs, "fig1_gridworld", "Obstacle gridworld: return during training", GRID_LINES, out_dir)


def no_robot_action_ablation(inputs: PaperInputs, out_dir: Path) -> FigureResult:
    """Figure 3: phi and phi' without the robot action."""
    label = ABLATION_LABELS["no_robot_action"]
    return _grid_panels(inputs, "fig3_no_robot_action", f"Ablation: {label}", _ablation_lines("no_robot_action", label), out_dir)


def greedy_ablation(inputs: PaperInputs, out_dir: Path) -> FigureResult:
    """Figure 4: critic discount 0 (future-state horizon unchanged)."""
    label = ABLATION_LABELS["greedy"]
    return _grid_panels(inputs, "fig4_greedy", f"Ablation: {label}", _ablation_lines("greedy", label), out_dir)


# ---------------------------------------------------------------- figure 2 (table)
def overcooked_table(inputs: PaperInputs, out_dir: Path) -> FigureResult:
    """Figure 2: the Overcooked table (final training return, mean ± SE), with the paper's."""
    _style()
    paths = inputs.paths("fig2_overcooked", WANTS["fig2_overcooked"]())
    it = iter(paths)
    ours: dict = {}
    seed_counts = []
    for layout in OVERCOOKED_LAYOUTS:
        ours[layout] = {}
        for m in OVERCOOKED_METHODS:
            ours[layout][m] = describe(final_per_seed(read_rows(next(it))))
            seed_counts.append(ours[layout][m]["seeds"])

    def cell(v):
        if isinstance(v, dict):  # ours: mean ± SE and IQM [CI], or one seed's value
            return format_summary(v)
        m, se = v
        return f"{m:.2f}" if se is None else f"{m:.2f} ± {se:.2f}"

    header = ["layout"] + [PAPER_LABELS[m] for m in OVERCOOKED_METHODS]
    body = []
    for layout in OVERCOOKED_LAYOUTS:
        body.append([layout] + [cell(ours[layout][m]) for m in OVERCOOKED_METHODS])
        body.append(["  paper"] + [cell(PAPER_OVERCOOKED[layout][m]) for m in OVERCOOKED_METHODS])
    md = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    md += ["| " + " | ".join(r) + " |" for r in body]
    tex = [r"\begin{tabular}{l" + "c" * len(OVERCOOKED_METHODS) + "}", r"\toprule", " & ".join(header) + r" \\", r"\midrule"]
    tex += [" & ".join(c.replace("±", r"$\pm$").replace("_", r"\_") for c in r) + r" \\" for r in body]
    tex += [r"\bottomrule", r"\end{tabular}"]
    prov = inputs.provenance("fig2_overcooked", paths, paper_numbers="the paper's published table")
    if prov.get("unfinished"):
        md = [f"UNFINISHED, as far as these runs have got: {'; '.join(prov['unfinished'])}", ""] + md
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "fig2_overcooked.md").write_text("\n".join(md) + "\n")
    (out_dir / "fig2_overcooked.tex").write_text("\n".join(tex) + "\n")
    fig, ax = plt.subplots(figsize=(9, 0.45 * (len(body) + 2)))
    ax.axis("off")
    t = ax.table(cellText=body, colLabels=header, loc="center", cellLoc="center")
    t.auto_set_font_size(False)
    t.set_fontsize(8)
    t.scale(1, 1.6)  # rows tall enough to fill the figure under its title
    for (r, _), c in t.get_celld().items():
        if r > 0 and body[r - 1][0].strip() == "paper":
            c.set_text_props(color="0.4", style="italic")
    paper_human = all(specs.plays_with_paper_human(inputs.run(stem, sets).spec) for stem, sets in WANTS["fig2_overcooked"]())
    human = "the paper's human" if paper_human else "esr's MLP clone as the human"
    ax.set_title(f"Overcooked with {human}: return per 400 steps (ours: {inputs.budget} budget, "
                 f"{seeds_phrase(seed_counts).replace('1 SE', 'SE')}; paper in grey)", fontsize=9)
    files = save(fig, out_dir, "fig2_overcooked", prov) + [out_dir / "fig2_overcooked.md", out_dir / "fig2_overcooked.tex"]
    return FigureResult("fig2_overcooked", files, prov, {"final_return": ours})


# ---------------------------------------------------------------- figure 5
def mutual_information(inputs: PaperInputs, out_dir: Path) -> FigureResult:
    """Figure 5: ESR's MI estimate and contrastive accuracy during training, N = 2..10."""
    _style()
    paths = inputs.paths("fig5_mutual_information", WANTS["fig5_mutual_information"]())
    fig, (ax_mi, ax_acc) = plt.subplots(1, 2, figsize=(10, 3.4))
    summary, seed_counts = {}, []
    for n, path, color in zip(GRID_NS, paths, ("C0", "C1", "C2", "C3")):
        rows = read_rows(path)
        seed_counts.append(len(rows[0]["mi_estimate"]))
        _band(ax_mi, rows, "mi_estimate", color, f"N = {n}")
        _band(ax_acc, rows, "contrastive_accuracy", color, f"N = {n}")
        _, chance = series(rows, "contrastive_chance")
        ax_acc.plot(series(rows, "contrastive_chance")[0], np.nanmean(_smooth(chance, max(1, len(rows) // 50)), axis=1),
                    ":", color=color, lw=1)
        half = len(rows) // 2
        summary[f"N={n}"] = {"mi_second_half": float(np.nanmean(series(rows, "mi_estimate")[1][half:])),
                             "accuracy_final": float(np.nanmean(final_per_seed(rows, "contrastive_accuracy")))}
    ax_mi.axhline(0.0, color="k", lw=0.8)
    ax_mi.set_title("MI estimate: mean diag. logit of phi minus phi' (nats)")
    ax_acc.set_title("contrastive accuracy (dotted: chance)")
    for ax in (ax_mi, ax_acc):
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"ESR's representation learning  [{inputs.budget} budget, {seeds_phrase(seed_counts)}]", fontsize=10)
    fig.tight_layout()
    prov = inputs.provenance("fig5_mutual_information", paths)
    return FigureResult("fig5_mutual_information", save(fig, out_dir, "fig5_mutual_information", prov), prov, summary)


# ---------------------------------------------------------------- figure 6
def _reachable_cells(obs: np.ndarray) -> int:
    """How many cells the human can walk to (blocks fixed): the appendix's colour."""
    size = obs.shape[0]
    blocked = obs[..., 1] > 0
    start = np.unravel_index(np.argmax(obs[..., 0]), obs.shape[:2])
    if blocked[start]:
        return 1
    seen, todo = {start}, [start]
    while todo:
        r, c = todo.pop()
        for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
            nr, nc = r + dr, c + dc
            if 0 <= nr < size and 0 <= nc < size and not blocked[nr, nc] and (nr, nc) not in seen:
                seen.add((nr, nc))
                todo.append((nr, nc))
    return len(seen)


def representations(inputs: PaperInputs, out_dir: Path) -> FigureResult:
    """Figure 6: ESR with 3-dimensional representations on the N = 10 gridworld. psi(s) of
    states from the robot's own rollouts, coloured by how many cells the human can reach."""
    import jax

    from esr_cli.recipes.runs import build_trainer
    from esr_cli.recipes.targets import run_spec
    from esr_cli.runner import loop

    _style()
    (path,) = inputs.paths("fig6_representations", WANTS["fig6_representations"]())
    spec = run_spec(path)
    trainer = build_trainer(spec, inputs.store)
    state = loop.final_state(trainer, path)
    first = jax.tree.map(lambda x: x[0], state)  # seed 0
    roll = jax.jit(lambda k: trainer.rollout(first.learner, k, 16, "sample"))(jax.random.PRNGKey(7))
    obs = np.asarray(roll.episodes.obs).reshape(-1, *trainer.env.obs_shape)
    obs = np.unique(obs, axis=0)
    psi = np.asarray(trainer.method.represent_future(first.method.params, obs))
    reach = np.array([_reachable_cells(o) for o in obs])
    fig = plt.figure(figsize=(6.2, 5))
    ax = fig.add_subplot(projection="3d")
    sc = ax.scatter(psi[:, 0], psi[:, 1], psi[:, 2], c=reach, cmap="viridis", s=12)
    fig.colorbar(sc, ax=ax, shrink=0.6, label="cells the human can reach")
    ax.set_title(f"psi(s) in 3 dimensions, N = 10  [{inputs.budget} budget, seed 0, {len(obs)} states]", fontsize=9)
    prov = inputs.provenance("fig6_representations", [path], seed_shown=int(spec.train.seeds[0]))
    corr = float(np.corrcoef(np.linalg.norm(psi, axis=1), reach)[0, 1]) if len(obs) > 2 and reach.std() > 0 else float("nan")
    return FigureResult("fig6_representations", save(fig, out_dir, "fig6_representations", prov), prov,
                        {"states": int(len(obs)), "corr_norm_psi_reachable": corr})


# ---------------------------------------------------------------- figure 7
def information_geometry(inputs: PaperInputs, out_dir: Path, gamma: float = 0.2, state: int = 0) -> FigureResult:
    """Figure 7: the state-marginal polytope of a 3-state MDP, exactly (no training)."""
    from esr_cli.analysis import geometry
    from esr_cli.common.plots import information_geometry as draw

    geo = geometry.geometry(geometry.example_mdp(), state, gamma)
    prov = {"figure": "fig7_geometry", "artifacts": {}, "budget": inputs.budget, "seeds": [],
            "mdp": "analysis.geometry.example_mdp", "state": state, "gamma": gamma}
    draw(geo, gamma, out_dir / "fig7_geometry.png", prov, pdf=True)
    return FigureResult("fig7_geometry", [out_dir / "fig7_geometry.png", out_dir / "fig7_geometry.pdf", out_dir / "fig7_geometry.json"],
                        prov, {"mutual_information": geo.mutual_information, "uniform_policy_mi": geo.uniform_mi})


# ---------------------------------------------------------------- figure 8
def overcooked_filmstrip(inputs: PaperInputs, out_dir: Path, frames: int = 8) -> FigureResult:
    """Figure 8: frames of one coordination-ring episode with the trained ESR robot."""
    import jax

    from esr_cli.recipes.runs import build_trainer
    from esr_cli.recipes.targets import run_spec
    from esr_cli.runner import loop

    _style()
    (path,) = inputs.paths("fig8_filmstrip", WANTS["fig8_filmstrip"]())
    spec = run_spec(path)
    trainer = build_trainer(spec, inputs.store)
    state = loop.final_state(trainer, path)
    first = jax.tree.map(lambda x: x[0], state)
    roll = jax.jit(lambda k: trainer.rollout(first.learner, k, 1, "sample"))(jax.random.PRNGKey(11))
    steps = trainer.env.episode_steps
    times = np.linspace(0, steps, frames).round().astype(int)
    rewards = np.cumsum(np.asarray(roll.episodes.reward)[0])
    fig, axes = plt.subplots(1, frames, figsize=(2.1 * frames, 2.3))
    for ax, t in zip(axes, times):
        s = jax.tree.map(lambda x: x[t, 0], roll.states)
        ax.imshow(np.asarray(trainer.env.render(s)))
        ax.set_title(f"t = {t}, return {rewards[t - 1] if t > 0 else 0:.0f}", fontsize=8)
        ax.axis("off")
    fig.suptitle(f"Coordination ring: ESR robot (agent 0) with the BC human  [{inputs.budget} budget, seed 0]", fontsize=9)
    fig.tight_layout()
    prov = inputs.provenance("fig8_filmstrip", [path], frames=times.tolist())
    return FigureResult("fig8_filmstrip", save(fig, out_dir, "fig8_filmstrip", prov), prov, {"episode_return": float(rewards[-1])})


# `esr plot NAME`: the short name -> (figure id, function).
FIGURES: dict[str, tuple[str, Callable[[PaperInputs, Path], FigureResult]]] = {
    "gridworld": ("fig1_gridworld", gridworld_curves),
    "overcooked": ("fig2_overcooked", overcooked_table),
    "no-robot-action": ("fig3_no_robot_action", no_robot_action_ablation),
    "greedy": ("fig4_greedy", greedy_ablation),
    "mi": ("fig5_mutual_information", mutual_information),
    "representations": ("fig6_representations", representations),
    "geometry": ("fig7_geometry", information_geometry),
    "filmstrip": ("fig8_filmstrip", overcooked_filmstrip),
}
