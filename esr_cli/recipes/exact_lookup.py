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

from esr_cli.storage.artifacts import read_summary
from esr_cli.storage.store import EXACT_KIND, FIGURE_KIND, Store, StoreError


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


def _default_view(components: dict, goal: tuple[int, int], gamma: float) -> bool:
    return tuple(components.get("goal", ())) == goal and math.isclose(float(components.get("gamma", -1.0)), gamma)


def run_checks(store: Store, run_key: str, seeds: int, goal: tuple[int, int], gamma: float) -> list[SeedCheck]:
    """Per seed index of run `run_key`: its exact check at `goal` and discount `gamma` (the
    defaults of `esr exact`), preferring one with a uniform sample of pairs, then the newest."""
    exacts: dict[int, list[tuple[dict, dict]]] = {}
    checks: dict[str, dict] = {}
    for entry in store.entries():
        if entry.status != "complete" or entry.manifest is None or entry.kind not in (EXACT_KIND, FIGURE_KIND):
            continue
        comps = entry.manifest.get("key_components") or {}
        if entry.kind == FIGURE_KIND:
            if comps.get("figure") == "estimator" and isinstance(comps.get("exact"), str):
                checks[comps["exact"]] = {"path": entry.path, "created": entry.manifest.get("created_at", "")}
            continue
        robot = comps.get("robot")
        if isinstance(robot, dict) and robot.get("run") == run_key and _default_view(comps, goal, gamma):
            exacts.setdefault(int(robot.get("seed_index", -1)), []).append((entry.manifest, {"path": entry.path}))
    out = []
    for i in range(seeds):
        found = sorted(exacts.get(i, []), key=lambda m: ("sample_pairs" in m[0]["key_components"], m[0].get("created_at", "")))
        if not found:
            out.append(SeedCheck())
            continue
        manifest, where = found[-1]
        try:
            summary = read_summary(where["path"])
        except StoreError:
            out.append(SeedCheck(exact=manifest["key"]))
            continue
        fields = {"exact": manifest["key"], "effective_empowerment": summary.get("effective_empowerment"),
                  "complete": summary.get("pairs") == "all", "sampled": "sample_pairs" in manifest["key_components"]}
        check = checks.get(manifest["key"])
        if check is not None:
            try:
                result = read_summary(check["path"])
            except StoreError:
                result = {}
            if result:
                fields.update(spearman_visited=result.get("spearman_visited"), visited_pairs=result.get("visited_pairs"))
                if result.get("complete", fields["complete"]):
                    fields["spearman_all"] = result.get("spearman")
                if "spearman_sample" in result:
                    low, high = result["spearman_sample_ci"]
                    fields.update(spearman_sample=(result["spearman_sample"], low, high), sample_pairs=result.get("sample_pairs"))
        out.append(SeedCheck(**fields))
    return out


def _num(v: Optional[float], digits: int = 3) -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def cells(checks: list[SeedCheck]) -> dict[str, str]:
    """The three table cells of a run's seeds, seed by seed ('a / b'): the human's exact
    effective empowerment ('≥' where a lower bound), the rank correlation over all pairs (exact,
    or a uniform sample's estimate with its interval), and over the visited pairs."""
    def ee(c: SeedCheck) -> str:
        return _num(c.effective_empowerment) if c.complete or c.effective_empowerment is None else f"≥ {_num(c.effective_empowerment)}"

    def every(c: SeedCheck) -> str:
        if c.spearman_all is not None:
            return _num(c.spearman_all)
        if c.spearman_sample is not None:
            rho, low, high = c.spearman_sample
            return f"{_num(rho)} [{_num(low)}, {_num(high)}] (sample of {c.sample_pairs:,})"
        return "—"

    def visited(c: SeedCheck) -> str:
        return "—" if c.spearman_visited is None else f"{_num(c.spearman_visited)} ({c.visited_pairs:,})"

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
