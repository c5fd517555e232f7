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

from esr_cli.recipes.diagnosis_runs import Options
from esr_cli.storage.artifacts import summary_or_empty
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
NOTE = ("Diagnoses (`esr diagnose RUN --seed-index I`, its default options), seed by seed: the reward on critic "
        "batches of the run's final buffer by the human's situation, Cohen's d of free against trapped, how often "
        "phi(s, aR, aH) and phi'(s, aR) pick a transition's future among a batch's and how often its block layout "
        "alone would, the start states at which the policy puts over half its probability on freeing the human, "
        "and the return of 16 episodes of its robot against a uniform robot with the same human.")


def _at(tree, *path):
    for name in path:
        if not isinstance(tree, dict):
            return None
        tree = tree.get(name)
    return tree


def number(tree, *path) -> Optional[float]:
    """The number at `path` in a summary (never a bool or text), or None."""
    v = _at(tree, *path)
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def count(tree, *path) -> Optional[int]:
    v = _at(tree, *path)
    return v if isinstance(v, int) and not isinstance(v, bool) else None


def fmt(v: Optional[float], spec: str) -> str:
    return "—" if v is None or math.isnan(v) else format(v, spec)


def read_diagnoses(store: Store) -> dict[tuple[str, int], object]:
    """(run key, seed index) -> the path of the newest committed diagnosis made with `esr
    diagnose`'s default options; entries whose manifests or key components are damaged are
    passed over."""
    defaults, newest, found = asdict(Options()), {}, {}
    for entry in store.entries():
        if entry.status != "complete" or entry.kind != DIAGNOSIS_KIND or entry.manifest is None:
            continue
        comps = entry.manifest.get("key_components")
        if not isinstance(comps, dict) or any(comps.get(k) != v for k, v in defaults.items()):
            continue
        run, seed = comps.get("run"), count(comps, "seed_index")
        if not isinstance(run, str) or seed is None:
            continue
        created = str(entry.manifest.get("created_at") or "")
        if created >= newest.get((run, seed), ""):
            newest[(run, seed)], found[(run, seed)] = created, entry.path
    return found


def seed_cells(report: dict) -> dict[str, str]:
    """One seed's cells of COLUMNS from its diagnosis ('' where the run has no such part: a
    method without representations, an environment without situations)."""
    gridworld = isinstance(report.get("reward"), dict)
    reprs = report.get("representations")
    starts = report.get("start_states")
    cells = dict.fromkeys(COLUMNS, "")
    if gridworld:
        cells["reward_by_situation"] = ", ".join(fmt(number(report, "reward", s, "mean"), "+.2f") for s in SHOWN_SITUATIONS)
        cells["effect_size"] = fmt(number(report, "free_vs_trapped", "effect_size"), ".2f")
    if isinstance(reprs, dict):
        cells["future_picked"] = f"{fmt(number(reprs, 'accuracy_phi'), '.3f')}, {fmt(number(reprs, 'accuracy_phi_prime'), '.3f')}"
        cells["layout_only"] = fmt(number(reprs, "layout_only"), ".3f")
    if gridworld and isinstance(starts, list) and starts:
        freed = sum(1 for row in starts if (number(row, "free", "p") or 0.0) > 0.5)
        cells["starts_freed"] = f"{freed} of {len(starts)}"
    if isinstance(report.get("play"), dict):
        cells["play"] = f"{fmt(number(report, 'play', 'robot', 'return'), '.2f')} vs {fmt(number(report, 'play', 'uniform', 'return'), '.2f')}"
    return cells


def run_cells(found: dict, run_key: str, seeds: int) -> tuple[dict[str, str], list[int]]:
    """The cells of a run's seeds joined seed by seed ('a / b'), and the seed indices the store
    has no diagnosis of ('—' in their place)."""
    per_seed, missing = [], []
    for i in range(seeds):
        path = found.get((run_key, i))
        if path is None:
            missing.append(i)
        per_seed.append(None if path is None else seed_cells(summary_or_empty(path)))
    present = [c for c in per_seed if c is not None]
    cells = {}
    for col in COLUMNS:
        if present and all(c[col] == "" for c in present):  # no such part in this run
            cells[col] = ""
        else:
            cells[col] = " / ".join("—" if c is None else c[col] or "—" for c in per_seed)
    return cells, missing
