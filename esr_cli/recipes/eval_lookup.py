"""What the store holds of a training run's evaluations (`esr eval RUN`, and `esr eval RUN
--human proxy` with the held-out human of an Overcooked run's BC human), read back for a table
of results (`esr sweep --results --eval`).

Read-only and light (no JAX). An evaluation may come from an imported archive, so its per-seed
returns are read as numbers or not at all: anything missing, damaged or of the wrong type shows
as '—', never a crash or a number made up.
"""

from __future__ import annotations

from typing import Optional

from esr_cli.common.numbers import as_number
from esr_cli.common.stats import describe, format_summary
from esr_cli.storage.artifacts import summary_or_empty
from esr_cli.storage.provenance import created_order
from esr_cli.storage.store import EVAL_KIND, Store

# The partners a table shows, in its order, with their headings.
COLUMNS = {
    "training": "eval return, training human (first policy mode)",
    "proxy": "eval return, held-out proxy human (first policy mode)",
}
NOTE = ("Evaluations (`esr eval RUN`, `esr eval RUN --human proxy`, the spec's episode count, the robot in its "
        "training seat): each seed's mean return over its episodes with the robot's first policy mode (sampled for "
        "a learned policy), then mean ± SE and the IQM across seeds.")


def partners(spec) -> tuple[str, ...]:
    """The partners a run of `spec` is evaluated with: its training human, and the held-out proxy
    where that human is a BC clone that did not adapt during training."""
    human = spec.human
    held_out = getattr(human, "kind", None) == "bc" and not getattr(human, "adapt", False)
    return ("training", "proxy") if held_out else ("training",)


def read_evals(store: Store) -> dict[tuple[str, str, int], object]:
    """(run key, partner, episodes) -> the path of the newest committed evaluation of that run
    with that partner ('training' or 'proxy') in the robot's training seat; entries whose
    manifests or summaries are damaged are passed over."""
    newest, found = {}, {}
    for entry in store.entries((EVAL_KIND,)):
        if entry.status != "complete" or not isinstance(entry.manifest, dict):
            continue
        comps = entry.manifest.get("key_components")
        if not isinstance(comps, dict) or "robot_seat" in comps:
            continue
        run, episodes = comps.get("run"), comps.get("episodes")
        if not isinstance(run, str) or type(episodes) is not int:
            continue
        partner = "training" if "human" not in comps else summary_or_empty(entry.path).get("human")
        if not isinstance(partner, str) or partner not in COLUMNS:
            continue
        created = created_order(entry.manifest)
        if created >= newest.get((run, partner, episodes), float("-inf")):
            newest[(run, partner, episodes)], found[(run, partner, episodes)] = created, entry.path
    return found


def per_seed_returns(summary: dict) -> Optional[list[float]]:
    """The first policy mode's per-seed returns of a stored evaluation, or None."""
    results = summary.get("results")
    if not isinstance(results, dict) or not results:
        return None
    first = next(iter(results.values()))
    values = first.get("return_per_seed") if isinstance(first, dict) else None
    if not isinstance(values, list) or not values or len(values) > 10_000:
        return None
    numbers = [as_number(v) for v in values]
    if not all(v is not None and abs(v) < 1e300 for v in numbers):  # NaN too: a damaged record, never a statistic
        return None
    return numbers


def run_cells(found: dict, run_key: str, episodes: int, shown: tuple[str, ...]) -> tuple[dict[str, str], list[str]]:
    """The run's cells (of COLUMNS; '' for a partner it is not evaluated with) and the partners
    whose evaluation the store lacks or cannot read ('—' in their place)."""
    cells, missing = {}, []
    for partner in COLUMNS:
        if partner not in shown:
            cells[partner] = ""
            continue
        path = found.get((run_key, partner, episodes))
        values = per_seed_returns(summary_or_empty(path)) if path is not None else None
        if values is None:
            cells[partner] = "—"
            missing.append(partner)
        else:
            cells[partner] = format_summary(describe(values), 2)
    return cells, missing
