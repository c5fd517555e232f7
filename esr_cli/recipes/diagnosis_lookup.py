"""What the store holds of a training run's diagnoses (`esr diagnose RUN --seed-index I`), read
back for a table of results (`esr sweep --results --diagnose`) and for `esr diagnose`'s own
printout of a stored one.

Read-only and light (no JAX). A summary may come from an imported archive, so every field is
read through `number` / `count`: anything missing, damaged or of the wrong type is None and
shows as '—', never a crash or a number made up.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Optional

from esr_cli.common.numbers import as_count, as_number
from esr_cli.recipes.diagnosis_runs import Options
from esr_cli.storage.artifacts import summary_or_empty
from esr_cli.storage.provenance import created_order
from esr_cli.storage.store import DIAGNOSIS_KIND, Store

SHOWN_SITUATIONS = ("free", "trapped", "dead")  # of esr_cli.analysis.diagnose.SITUATIONS, in the table's order
# The table's cells, each per seed ('a / b'), with their headings.
COLUMNS = {
    "reward_by_situation": "reward: free / trapped / dead, per seed",
    "effect_size": "d (free vs trapped), per seed",
    "future_picked": "phi / phi' pick the future, per seed",
    "layout_only": "block layout alone picks it, per seed",
    "starts_freed": "start states the policy frees, per seed",
    "play": "play check: return, its robot vs a uniform robot, per seed",
}
# The play check in full (`--play`): what `esr diagnose` prints of it, per seed, its robot's play
# against a uniform robot's with the same human.
PLAY_COLUMNS = {
    "play_return": "return: its robot vs a uniform robot, per seed",
    "play_reward": "the run's reward on that play, mean (sd), per seed",
    "play_mi": "MI estimate on that play (nats), per seed",
    "human_moves": "share of steps the human moves, per seed",
}
PLAY_NOTE = (f"Play checks (`esr diagnose RUN --seed-index I`, its default options), seed by seed: {Options().episodes} "
             "episodes of the run's robot and of a uniform robot with the run's human, each cell 'its robot vs "
             "uniform': the return, the run's own reward on each play (its mean over the steps, and sd), the MI "
             "estimate of its representations on each play, and the share of steps on which the human's position "
             "or orientation changes.")
NOTE = ("Diagnoses (`esr diagnose RUN --seed-index I`, its default options), seed by seed: the reward on critic "
        "batches of the run's final buffer by the human's situation, Cohen's d of free against trapped, how often "
        "phi(s, aR, aH) and phi'(s, aR) pick a transition's future among a batch's and how often its block layout "
        "alone would, the start states at which the policy puts over half its probability on freeing the human, "
        f"and the return of {Options().episodes} episodes of its robot against a uniform robot with the same human.")
# Which cells a run has, by what it is (not by what a stored summary happens to hold: a damaged
# part then shows as '—', never as a part the run lacks).
GRIDWORLD_CELLS = ("reward_by_situation", "effect_size", "starts_freed")
REPRESENTATION_CELLS = ("future_picked", "layout_only")


def _at(tree, *path):
    for name in path:
        if not isinstance(tree, dict):
            return None
        tree = tree.get(name)
    return tree


def number(tree, *path) -> Optional[float]:
    """The number at `path` in a summary (never a bool or text), or None."""
    return as_number(_at(tree, *path))


def count(tree, *path) -> Optional[int]:
    return as_count(_at(tree, *path))


def fmt(v: Optional[float], spec: str) -> str:
    return "—" if v is None or math.isnan(v) else format(v, spec)


def read_diagnoses(store: Store) -> dict[tuple[str, int], object]:
    """(run key, seed index) -> the path of the newest committed diagnosis made with `esr
    diagnose`'s default options; entries whose manifests or key components are damaged are
    passed over."""
    defaults, newest, found = asdict(Options()), {}, {}
    for entry in store.entries((DIAGNOSIS_KIND,)):
        if entry.status != "complete" or entry.manifest is None:
            continue
        comps = entry.manifest.get("key_components")
        if not isinstance(comps, dict) or any(comps.get(k) != v for k, v in defaults.items()):
            continue
        run, seed = comps.get("run"), count(comps, "seed_index")
        if not isinstance(run, str) or seed is None:
            continue
        created = created_order(entry.manifest)
        if created >= newest.get((run, seed), float("-inf")):
            newest[(run, seed)], found[(run, seed)] = created, entry.path
    return found


def play_applicable(method_kind: str) -> tuple[str, ...]:
    """The cells of PLAY_COLUMNS a run's play check has: the MI estimate is ESR's alone."""
    return tuple(c for c in PLAY_COLUMNS if c != "play_mi" or method_kind == "esr")


def applicable(env_kind: str, method_kind: str) -> tuple[str, ...]:
    """The cells of COLUMNS a diagnosis of such a run has (every run it applies to learns a policy,
    so each has the play check)."""
    cells = {"play"}
    if env_kind == "gridworld":
        cells.update(GRIDWORLD_CELLS)
        if method_kind == "esr":
            cells.update(REPRESENTATION_CELLS)
    return tuple(c for c in COLUMNS if c in cells)


def _versus(report: dict, cell) -> str:
    """'its robot's vs the uniform robot's' of one play-check figure (`cell`: a player's record -> text)."""
    play = report.get("play")
    sides = [play.get(player) if isinstance(play, dict) else None for player in ("robot", "uniform")]
    return " vs ".join(cell(side if isinstance(side, dict) else {}) for side in sides)


def seed_cells(report: dict, cells: Optional[tuple[str, ...]] = None, columns: dict = COLUMNS) -> dict[str, str]:
    """One seed's `cells` (of `columns`, COLUMNS or PLAY_COLUMNS; default: all of them) from its
    diagnosis, '' for the others; '—' for a part missing or damaged."""
    cells = tuple(columns) if cells is None else cells
    reprs = report.get("representations")
    starts = report.get("start_states")
    out = {
        "play_return": _versus(report, lambda r: fmt(number(r, "return"), ".2f")),
        "play_reward": _versus(report, lambda r: f"{fmt(number(r, 'reward', 'mean'), '+.2f')} ({fmt(number(r, 'reward', 'sd'), '.1f')})"),
        "play_mi": _versus(report, lambda r: fmt(number(r, "reward", "mi_estimate"), "+.3f")),
        "human_moves": _versus(report, lambda r: fmt(number(r, "human_moves"), ".3f")),
        "reward_by_situation": ", ".join(fmt(number(report, "reward", s, "mean"), "+.2f") for s in SHOWN_SITUATIONS),
        "effect_size": fmt(number(report, "free_vs_trapped", "effect_size"), ".2f"),
        "future_picked": f"{fmt(number(reprs, 'accuracy_phi'), '.3f')}, {fmt(number(reprs, 'accuracy_phi_prime'), '.3f')}",
        "layout_only": fmt(number(reprs, "layout_only"), ".3f"),
        "starts_freed": "—",
        "play": f"{fmt(number(report, 'play', 'robot', 'return'), '.2f')} vs {fmt(number(report, 'play', 'uniform', 'return'), '.2f')}",
    }
    rows = [row for row in starts if isinstance(row, dict)] if isinstance(starts, list) else []
    if rows:
        freed = sum(1 for row in rows if (number(row, "free", "p") or 0.0) > 0.5)
        out["starts_freed"] = f"{freed} of {len(rows)}"
    return {c: (out[c] if c in cells else "") for c in columns}


def run_cells(found: dict, run_key: str, seeds: int, cells: Optional[tuple[str, ...]] = None,
              columns: dict = COLUMNS) -> tuple[dict[str, str], list[int]]:
    """The run's `cells` (of `columns`; default: all of them) joined seed by seed ('a / b'; ''
    for the others), and the seed indices whose diagnosis the store lacks or cannot read ('—'
    in their place)."""
    cells = tuple(columns) if cells is None else cells
    per_seed, missing = [], []
    for i in range(seeds):
        report = summary_or_empty(found[(run_key, i)]) if (run_key, i) in found else {}
        if not report:  # none, or unreadable: made again by the same command
            missing.append(i)
        per_seed.append(seed_cells(report, cells, columns) if report else None)
    return {col: " / ".join("—" if c is None else c[col] for c in per_seed) if col in cells else "" for col in columns}, missing
