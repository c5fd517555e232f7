"""What the store holds of a training run's exact checks: for each seed, the human's exact
effective empowerment under that seed's robot (`esr exact SPEC --robot RUN --seed-index I`)
and the rank correlation of its reward with the exact MI (`esr plot estimator EXACT`).

Read-only and light (no JAX): `esr sweep --results --exact` puts these beside a suite's
returns, so its tables come from the store, and names the command for anything missing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

from esr_cli.common.numbers import as_count, as_number
from esr_cli.storage.artifacts import summary_or_empty as _summary
from esr_cli.storage.provenance import created_order
from esr_cli.storage.store import EXACT_KIND, FIGURE_KIND, Store


@dataclass(frozen=True)
class SeedCheck:
    """One seed's exact check as stored; None where the store lacks that part."""

    exact: Optional[str] = None  # the exact artifact's key
    effective_empowerment: Optional[float] = None  # nats; a lower bound where not every pair was computed
    complete: Optional[bool] = None  # every pair computed and counted
    sampled: bool = False  # made with a uniform sample of all pairs (`esr exact --sample-pairs`)
    spearman_all: Optional[float] = None  # over every pair, where the space was solved whole
    spearman_sample: Optional[tuple[float, float, float]] = None  # (rho, low, high) over a uniform sample of all pairs
    sample_pairs: Optional[int] = None
    spearman_visited: Optional[float] = None  # over the pairs holding 99% of the robot's occupancy
    visited_pairs: Optional[int] = None
    pairs: Optional[int] = None  # the pairs spearman_all is over
    estimator: Optional[str] = None  # the estimator check's key (its scatter, `esr plot estimator`)


@dataclass(frozen=True)
class Target:
    """What an exact check of a run is of: the run's environment and human (its spec's training
    part), and the goal and discount `esr exact` takes by default for its spec. `run_key` None:
    the check of a uniform robot on that environment (seed index 0)."""

    run_key: Optional[str]
    env: dict
    human: dict
    goal: tuple[int, int]
    gamma: float

    def matches(self, comps: dict) -> Optional[int]:
        """The seed index of an exact artifact's key components when they are of this target."""
        robot, goal, gamma = comps.get("robot"), comps.get("goal"), as_number(comps.get("gamma"))
        if self.run_key is None:
            seed = 0 if robot == "uniform" else None
        elif isinstance(robot, dict) and robot.get("run") == self.run_key:
            seed = as_count(robot.get("seed_index"))
        else:
            seed = None
        if seed is None:
            return None
        if not isinstance(goal, list) or tuple(goal) != self.goal or gamma is None or not math.isclose(gamma, self.gamma):
            return None
        if comps.get("env") != self.env or comps.get("human") != self.human:
            return None
        return seed


@dataclass(frozen=True)
class StoreChecks:
    """The store's committed exact artifacts and estimator checks, read once for a whole table."""

    exacts: list[tuple[dict, bool, float, str, object]]  # (key components, sampled, created, key, path)
    estimators: dict[str, object]  # exact key -> the newest estimator check's path


def read_checks(store: Store) -> StoreChecks:
    """Every committed exact artifact and estimator check of `store`; entries whose manifests or
    key components are damaged are passed over, never trusted."""
    exacts, estimators = [], {}
    newest: dict[str, float] = {}
    for entry in store.entries():
        if entry.status != "complete" or entry.manifest is None or entry.kind not in (EXACT_KIND, FIGURE_KIND):
            continue
        comps = entry.manifest.get("key_components")
        if not isinstance(comps, dict):
            continue
        created = created_order(entry.manifest)
        if entry.kind == EXACT_KIND:
            exacts.append((comps, "sample_pairs" in comps, created, entry.key, entry.path))
            continue
        made_from = comps.get("exact")
        if comps.get("figure") == "estimator" and isinstance(made_from, str) and created >= newest.get(made_from, float("-inf")):
            newest[made_from], estimators[made_from] = created, entry.path
    return StoreChecks(exacts, estimators)


def run_checks(checks: StoreChecks, target: Target, seeds: int) -> list[SeedCheck]:
    """Per seed index of the target's run: its exact check among `checks`, preferring one with a
    uniform sample of pairs, then the newest; and the estimator check made from it. Damaged
    summaries leave their fields empty."""
    exacts: dict[int, list[tuple[bool, float, str, object]]] = {}  # seed -> (sampled, created, key, path)
    for comps, *found in checks.exacts:
        seed = target.matches(comps)
        if seed is not None:
            exacts.setdefault(seed, []).append(tuple(found))
    out = []
    for i in range(seeds):
        if not exacts.get(i):
            out.append(SeedCheck())
            continue
        sampled, _, key, path = max(exacts[i], key=lambda e: e[:2])
        summary = _summary(path)
        fields = {"exact": key, "effective_empowerment": as_number(summary.get("effective_empowerment")),
                  # summaries made before `pairs` was recorded were always of every pair
                  "complete": summary.get("pairs", "all") == "all" if summary else None, "sampled": sampled}
        result = _summary(checks.estimators[key]) if key in checks.estimators else {}
        if as_number(result.get("spearman_visited")) is not None:  # NaN too: a constant estimate has no rank correlation
            fields.update(spearman_visited=as_number(result.get("spearman_visited")),
                          visited_pairs=as_count(result.get("visited_pairs")), estimator=checks.estimators[key].name)
            if result.get("complete", fields["complete"]) is True:
                fields.update(spearman_all=as_number(result.get("spearman")), pairs=as_count(result.get("pairs")))
            ci = result.get("spearman_sample_ci")
            bounds = [as_number(c) for c in ci] if isinstance(ci, list) and len(ci) == 2 else [None]
            rho = as_number(result.get("spearman_sample"))
            if rho is not None and None not in bounds:
                fields.update(spearman_sample=(rho, *bounds), sample_pairs=as_count(result.get("sample_pairs")))
        out.append(SeedCheck(**fields))
    return out


def number_cell(v: Optional[float], digits: int = 3) -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def cells(checks: list[SeedCheck]) -> dict[str, str]:
    """The three table cells of a run's seeds, seed by seed ('a / b'): the human's exact
    effective empowerment ('≥' where a lower bound), the rank correlation over all pairs (exact,
    or a uniform sample's estimate with its interval), and over the visited pairs."""
    def ee(c: SeedCheck) -> str:
        return number_cell(c.effective_empowerment) if c.complete or c.effective_empowerment is None else f"≥ {number_cell(c.effective_empowerment)}"

    def pairs(n: Optional[int]) -> str:
        return "?" if n is None else f"{n:,}"

    def every(c: SeedCheck) -> str:
        if c.spearman_all is not None:
            return number_cell(c.spearman_all)
        if c.spearman_sample is not None:
            rho, low, high = c.spearman_sample
            return f"{number_cell(rho)} [{number_cell(low)}, {number_cell(high)}] (sample of {pairs(c.sample_pairs)})"
        return "—"

    def visited(c: SeedCheck) -> str:
        return "—" if c.spearman_visited is None else f"{number_cell(c.spearman_visited)} ({pairs(c.visited_pairs)})"

    return {"exact_ee": " / ".join(map(ee, checks)), "spearman_all": " / ".join(map(every, checks)),
            "spearman_visited": " / ".join(map(visited, checks))}


def missing(checks: list[SeedCheck]) -> list[tuple[int, str]]:
    """(seed index, what is missing): 'exact' (no exact check, or only one over the visited pairs
    without a sample, which leaves the correlation over all pairs unknown) or 'estimator' (no
    rank correlation made from it)."""
    out = []
    for i, c in enumerate(checks):
        if c.exact is None or (c.complete is False and not c.sampled):
            out.append((i, "exact"))
        elif c.spearman_visited is None:
            out.append((i, "estimator"))
    return out
