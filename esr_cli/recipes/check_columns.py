"""Columns a table of results (`esr sweep --results`) can carry beside each done run's finals,
read from the store's other artifacts of that run: its exact checks (`--exact`), its
diagnoses (`--diagnose`), their play checks in full (`--play`) and its evaluations (`--eval`). Nothing here computes: a check the store lacks shows as '—' and is
named by the command that makes it, printed below the table.

Each kind of check is a `CheckColumns` in `REGISTRY`; a table's columns are those of the checks
it is asked for, always in the registry's order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

from esr_cli.common.printing import printable, train_line
from esr_cli.model import spec as spec_model
from esr_cli.recipes import diagnosis_lookup, eval_lookup, exact_lookup
from esr_cli.recipes.suite import Run, Suite
from esr_cli.recipes.targets import exact_defaults
from esr_cli.storage.store import Store


@dataclass(frozen=True)
class CheckColumns:
    name: str  # the row's field (JSON) and the name a table's checks are asked for by
    option: str  # the command-line flag
    columns: dict[str, str]  # cell -> heading
    note: str  # printed below a table that has these columns
    applies: Callable[[object], bool]  # to a run of this spec
    read: Callable[[Store], object]  # the store's artifacts of this kind, read once per table
    cells: Callable[[Run, str, str, object], tuple[dict[str, str], list[str]]]  # -> (cells, commands for what is missing)
    refusal: Callable[[Suite], Optional[str]]  # why a suite cannot have these columns, or None


# What `esr sweep --results --exact` asks `esr exact` to sample where a space is too large for
# every pair: enough for a rank correlation to within about +-0.08 (95% interval, rho near 0.4).
SUGGESTED_SAMPLE_PAIRS = 500


def _learns_a_policy(spec) -> bool:
    return spec.method.kind not in spec_model.POLICY_FREE_METHODS


def _has_exact_checks(spec) -> bool:
    """A gridworld run whose robot has a policy of its own, on a space small enough for `esr exact`."""
    from esr_cli.analysis.state_count import MAX_STATES, state_bound

    return spec.env.kind == "gridworld" and _learns_a_policy(spec) and state_bound(spec.env.size, spec.env.blocks) <= MAX_STATES


def _ranks_its_reward(spec) -> bool:
    """`esr plot estimator` ranks ESR's own reward, at each true human action."""
    return spec.method.kind == "esr" and spec.method.human_action != "inferred"


def _exact_cells(run: Run, budget: str, esr: str, stored_checks) -> tuple[dict[str, str], list[str]]:
    """A run's exact-check cells (exact_lookup.cells) and the commands for what the store lacks
    (`esr`: how they call esr)."""
    spec = run.spec
    part = spec.training_part()
    target = exact_lookup.Target(run.key, part["env"], part["human"], *exact_defaults(spec))
    checks = exact_lookup.run_checks(stored_checks, target, len(spec.train.seeds))
    todo = []
    for i, what in exact_lookup.missing(checks):
        if what == "exact":
            extra = ("--robot", run.key[:8], "--seed-index", str(i), "--sample-pairs", str(SUGGESTED_SAMPLE_PAIRS))
            todo.append(train_line(esr, run.spec_path, budget, run.sets, command="exact", extra=extra))
        elif _ranks_its_reward(spec):
            todo.append(f"{esr} plot estimator {checks[i].exact[:8]}")
    cells = exact_lookup.cells(checks)
    if not _ranks_its_reward(spec):  # no reward of its own to rank
        cells.update(spearman_all="", spearman_visited="")
    return cells, [printable(line) for line in todo]


def _no_gridworld(suite: Suite) -> Optional[str]:
    if any(r.spec.env.kind == "gridworld" for r in suite.runs):
        return None
    return "exact checks are made on gridworld runs; this suite has none"


EXACT = CheckColumns(
    name="exact", option="--exact",
    columns={"exact_ee": "exact effective empowerment, per seed (nats)",
             "spearman_all": "Spearman (reward, exact MI), all pairs, per seed",
             "spearman_visited": "Spearman, visited pairs (count), per seed"},
    note=("Exact checks at the centre goal and the spec's future discount, seed by seed: '≥' marks a lower bound "
          "(the space is solved over the pairs holding 99% of the robot's discounted occupancy); an interval is a "
          "uniform sample of all pairs with its 95% bootstrap interval."),
    applies=_has_exact_checks, read=exact_lookup.read_checks, cells=_exact_cells, refusal=_no_gridworld,
)


def _diagnosis_cells(columns: dict, applicable: Callable[[object], tuple[str, ...]]):
    """The cells function of a group read from diagnoses: `columns` (diagnosis_lookup.COLUMNS or
    PLAY_COLUMNS) of each seed's, those `applicable` to the run's spec, and the `esr diagnose`
    command of each seed the store lacks."""
    def cells(run: Run, budget: str, esr: str, found) -> tuple[dict[str, str], list[str]]:
        shown, missing = diagnosis_lookup.run_cells(found, run.key, len(run.spec.train.seeds), applicable(run.spec), columns)
        return shown, [printable(f"{esr} diagnose {run.key[:8]} --seed-index {i}") for i in missing]

    return cells


def _no_policy(suite: Suite) -> Optional[str]:
    if any(_learns_a_policy(r.spec) for r in suite.runs):
        return None
    return "diagnoses are of robots that learn a policy; this suite has none"


DIAGNOSIS = CheckColumns(
    name="diagnosis", option="--diagnose", columns=diagnosis_lookup.COLUMNS, note=diagnosis_lookup.NOTE,
    applies=_learns_a_policy, read=diagnosis_lookup.read_diagnoses, refusal=_no_policy,
    cells=_diagnosis_cells(diagnosis_lookup.COLUMNS, lambda spec: diagnosis_lookup.applicable(spec.env.kind, spec.method.kind)),
)

PLAY = CheckColumns(
    name="play_check", option="--play", columns=diagnosis_lookup.PLAY_COLUMNS, note=diagnosis_lookup.PLAY_NOTE,
    applies=_learns_a_policy, read=diagnosis_lookup.read_diagnoses, refusal=_no_policy,
    cells=_diagnosis_cells(diagnosis_lookup.PLAY_COLUMNS, lambda spec: diagnosis_lookup.play_applicable(spec.method.kind)),
)


def _eval_cells(run: Run, budget: str, esr: str, found) -> tuple[dict[str, str], list[str]]:
    shown = eval_lookup.partners(run.spec)
    cells, missing = eval_lookup.run_cells(found, run.key, run.spec.eval.episodes, shown)
    # The episode count named: `esr eval KEY` takes its default from the stored run's spec, whose
    # eval section is not part of the run's key (another spec of the same run may differ there).
    episodes = run.spec.eval.episodes
    todo = [f"{esr} eval {run.key[:8]} --episodes {episodes}" + ("" if partner == "training" else f" --human {partner}")
            for partner in missing]
    return cells, [printable(line) for line in todo]


EVAL = CheckColumns(
    name="eval", option="--eval", columns=eval_lookup.COLUMNS, note=eval_lookup.NOTE,
    applies=lambda spec: True, read=eval_lookup.read_evals, cells=_eval_cells, refusal=lambda suite: None,
)

REGISTRY = {c.name: c for c in (EXACT, DIAGNOSIS, PLAY, EVAL)}


def chosen(names) -> tuple[CheckColumns, ...]:
    """The checks named (by `CheckColumns.name`), in the registry's order."""
    unknown = set(names) - set(REGISTRY)
    if unknown:
        raise ValueError(f"unknown checks {sorted(unknown)}; known: {', '.join(REGISTRY)}")
    return tuple(c for c in REGISTRY.values() if c.name in names)
