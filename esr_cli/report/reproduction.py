"""The reproduction report (`esr paper --report`, docs/reproduction.md): every claim of the paper
next to what the store holds, with a verdict.

Evidence is found by *spec*, not by key: a stored run (finished or not) supports a claim when
its validated spec equals the claim's spec in every field outside `train` (length, seeds,
environments in parallel and chunking may differ). Runs made by another checkout are therefore
found too; the report names each run's key, its commit where known, its length and its seeds.
Among the runs that match, the one with the most epochs done (then the most seeds) is used.
Nothing here trains; the estimator check computes exact artifacts for a stored run.
"""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import dataclass, field, replace
from functools import cache
from pathlib import Path
from typing import NamedTuple, Optional

import numpy as np

from esr_cli.common import specs, yamlio
from esr_cli.common.markdown import plain_text
from esr_cli.common.printing import train_line
from esr_cli.common.stats import describe, format_summary, mean_difference_ci, probability_of_improvement, scored_seeds
from esr_cli.model import spec as spec_model
from esr_cli.recipes.exact_lookup import SeedCheck, Target, number_cell, read_checks, run_checks
from esr_cli.recipes.targets import exact_defaults, run_spec
from esr_cli.storage import provenance
from esr_cli.storage.artifacts import ensure
from esr_cli.storage.checkpoint_files import verified_steps
from esr_cli.storage.finals import FINAL_FRACTION, final_per_seed, read_rows, series
from esr_cli.storage.store import FIGURE_KIND, RUN_KIND, Store, StoreError, atomic_write_bytes, write_output_file

EXPERIMENTS = provenance.experiments_dir()
PAPER_EPOCHS = 10_000
# A run is at a length comparable with the paper's once it has this many epochs behind it: the
# gridworld at 30% of the paper's 10,000 epochs (beyond which ESR's return in the paper's
# figure changes little), Overcooked at its full length (cheap enough to run whole).
COMPARABLE_EPOCHS = {"gridworld": 3000, "overcooked": 10_000}
# "Similar" returns: the difference of the means within this share of the larger mean, by two
# one-sided tests (the 90% bootstrap interval of the difference inside the margin) where a side
# has several seeds, by the point difference where both have one.
EQUIVALENCE_MARGIN = 0.15
# A verdict needs this many seeds on every side; with fewer a row is only indicative.
MIN_SEEDS = 3
# "Positive" MI estimate: above this many nats at the end (a grid_2 run that learned ends near
# +0.17; an estimate stuck at +0.002 carries no signal however many epochs are above zero).
MI_POSITIVE = 0.01
REPRODUCED, NOT_REPRODUCED, INCONCLUSIVE, NOT_YET = (
    "reproduced", "not reproduced", "inconclusive", "not yet run at a comparable budget")
INDICATIVE = "indicative"
HEX_DIGEST = re.compile(r"[0-9a-f]{32}")  # a code digest as a key's components name it
# What an indicative row's numbers say, before enough seeds: holds, does not hold, open.
LEANINGS = {True: "holds", False: "does not hold", None: "open"}


# ---------------------------------------------------------------- evidence in the store
@dataclass
class Evidence:
    """One stored run: what it is, how far it got, its per-seed metric rows."""

    key: str
    path: Path
    status: str  # complete | partial
    budget: str
    spec: spec_model.Spec
    rows: list[dict]
    commit: Optional[str]  # the checkout it was started from
    device: Optional[str] = None  # where it ran, e.g. 'gpu:NVIDIA H200'; None: unknown
    # False for an unfinished run whose checkpoint is not in this store (a record of its
    # logged epochs, `esr import --without-checkpoint`): training it again starts from epoch 0.
    resumable: bool = True
    # True when the checkout it was started from had edits under esr_cli/ (its code digest,
    # part of the key, still says exactly which training code it ran).
    modified: bool = False
    # The training program that made it, as its key names it (the training code's digest and the
    # toolchain); None where its manifest does not say. Runs of one program pool their seeds.
    program: Optional[str] = None
    # A pooled run (`pooled`): the finished runs whose seeds it joins; () for a stored run.
    parts: tuple = ()
    _finals: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def epochs_done(self) -> int:
        return self.rows[-1]["epoch"] if self.rows else 0

    @property
    def seeds(self) -> int:
        return len(self.rows[-1]["return"]) if self.rows else len(self.spec.train.seeds)

    def finals(self, name: str = "return") -> dict:
        """stats.describe of the per-seed finals, computed once (it bootstraps)."""
        if name not in self._finals:
            self._finals[name] = describe(final_per_seed(self.rows, name))
        return self._finals[name]

    def comparable(self) -> bool:
        return self.epochs_done >= COMPARABLE_EPOCHS.get(self.spec.env.kind, PAPER_EPOCHS)

    @property
    def commit_label(self) -> str:
        if not self.commit:
            return "unknown"
        return self.commit[:7] + (" (esr_cli/ modified)" if self.modified else "")

    @property
    def accelerator(self) -> Optional[str]:
        """The device where it is not a CPU (the default, left unsaid), else None."""
        return self.device if self.device and not self.device.startswith("cpu") else None

    def describe_length(self) -> str:
        state = ""
        if self.status != "complete":
            lost = "" if self.resumable else "; its checkpoint is not in this store"
            state = f" of {self.spec.train.epochs:,} (unfinished{lost})"
        return f"{self.epochs_done:,} epochs{state}, {self.seeds} seed{'s' if self.seeds != 1 else ''}"


def _without_train(spec: spec_model.Spec) -> str:
    part = spec.training_part()
    part.pop("train")
    return json.dumps(part, sort_keys=True)


def index_store(store: Store) -> dict[str, list[Evidence]]:
    """Every training run of the store whose spec still validates, by spec outside `train`."""
    out: dict[str, list[Evidence]] = {}
    for entry in store.entries():
        if entry.kind != RUN_KIND or not (entry.path / "spec.yaml").is_file():
            continue
        try:
            spec = run_spec(entry.path)  # only the spec its key was computed from
        except StoreError:
            continue  # made by code whose spec fields this version no longer reads, or not its key's spec
        info = entry.manifest or {}
        made = provenance.origin(info)
        resumable = entry.status == "complete" or bool(verified_steps(entry.path))
        # The page is markdown: what the manifest says of the device is shown as the text it is.
        device = plain_text(made.device) if made.device else None
        budget = info.get("budget") if info.get("budget") in spec_model.BUDGETS else spec.budget
        ev = Evidence(entry.key, entry.path, entry.status, budget, spec, read_rows(entry.path), made.commit,
                      device, resumable, modified=made.modified, program=_program(info))
        if ev.rows:
            out.setdefault(_without_train(spec), []).append(ev)
    return out


def _program(info: dict) -> Optional[str]:
    """The training code digest and toolchain a run's key was computed from, as one comparable text."""
    components = info.get("key_components")
    components = components if isinstance(components, dict) else {}
    code, toolchain = components.get("code"), components.get("toolchain")
    if not (isinstance(code, str) and HEX_DIGEST.fullmatch(code) and isinstance(toolchain, dict)):
        return None
    return json.dumps({"code": code, "toolchain": toolchain}, sort_keys=True)


def _rank(e: Evidence) -> tuple:
    return (e.epochs_done, e.seeds, e.status == "complete")


def best(index: dict[str, list[Evidence]], spec: spec_model.Spec) -> Optional[Evidence]:
    return max(index.get(_without_train(spec), []), key=_rank, default=None)


def _train_but_seeds(e: Evidence) -> str:
    train = e.spec.training_part()["train"]
    train.pop("seeds")
    return json.dumps(train, sort_keys=True)


def _join_rows(runs: list[Evidence]) -> list[dict]:
    """Epoch rows of runs of equal length, each per-seed list joined in run order."""
    return [{k: sum((r[k] for r in rows), []) if isinstance(v, list) else v for k, v in rows[0].items()}
            for rows in zip(*(e.rows for e in runs))]


def pooled(index: dict[str, list[Evidence]], spec: spec_model.Spec) -> Optional[Evidence]:
    """The evidence for `spec`: its longest run, or, where several finished runs share that
    length and differ only in their seeds (same training program: code digest and toolchain, as
    their keys name them, whichever commit they were started from; same device and every other
    training field; no seed twice), all of them as one run of their joined seeds: the group with
    the most seeds, whichever run happens to be listed first. Which of two single-seed runs of one
    length to believe is otherwise an arbitrary choice."""
    top = best(index, spec)
    if top is None or top.status != "complete":
        return top
    groups: dict[tuple, list[Evidence]] = {}
    for e in index[_without_train(spec)]:
        if e.status == "complete" and e.epochs_done == top.epochs_done and e.program:
            groups.setdefault((e.program, e.device, _train_but_seeds(e)), []).append(e)
    pools = [_pool(mates) for mates in groups.values() if _poolable(mates)]
    return max([top, *pools], key=lambda e: e.seeds)  # a tie keeps the longest stored run


def _poolable(mates: list[Evidence]) -> bool:
    seeds = [s for e in mates for s in e.spec.train.seeds]
    return len(mates) > 1 and len(set(seeds)) == len(seeds)


def _pool(mates: list[Evidence]) -> Evidence:
    mates = sorted(mates, key=lambda e: min(e.spec.train.seeds))
    first = mates[0]
    train = first.spec.train.model_copy(update={"seeds": [s for e in mates for s in e.spec.train.seeds]})
    return replace(first, key="+".join(e.key[:8] for e in mates), spec=first.spec.model_copy(update={"train": train}),
                   rows=_join_rows(mates), parts=tuple(mates), _finals={})


def others(index: dict[str, list[Evidence]], spec: spec_model.Spec, chosen: Evidence) -> list[Evidence]:
    """The runs of `spec` besides `chosen` (or the runs it pools), longest first."""
    used = {p.key for p in chosen.parts} | {chosen.key}
    return sorted((e for e in index.get(_without_train(spec), []) if e.key not in used), key=_rank, reverse=True)


# ---------------------------------------------------------------- claims
@dataclass
class Claim:
    """One statement of the paper, checked on runs of the specs it names."""

    figure: str
    text: str
    paper: str  # what the paper reports
    kind: str  # above | similar | mi_positive
    a: tuple[str, tuple[str, ...]]  # (spec stem in experiments/, --set values)
    b: Optional[tuple[str, tuple[str, ...]]] = None
    variants: list[tuple[str, tuple[str, ...]]] = field(default_factory=list)  # esr's variants of `a`, shown too
    # esr's stronger versions of the baseline `b` (the paper ran the published one): extra rows
    baseline_variants: list[tuple[str, tuple[str, ...]]] = field(default_factory=list)
    # The statement under other conditions than the paper's, both sides changed alike (label,
    # --set values added to `a` and to `b`): extra rows, each judged on its own runs
    conditions: list[tuple[str, tuple[str, ...]]] = field(default_factory=list)


QUICK_CHANGES = ("learner.warmup_epochs=20", "method.repr_lr=0.001")
PUBLISHED_AVE = ("method.variant=original",)
PUBLISHED_GOAL_INFERENCE = ("method.variant=original",)
NO_ROBOT_ACTION = ("method.condition_on_robot_action=false",)
GREEDY = ("learner.gamma=0.0",)
FUTURE_HUMAN = ("method.future=human",)  # esr's estimator: psi sees only the human's part of the future
# Overcooked's human before the layout specs named the paper's (`human.preset: paper`): esr's MLP
# clone of the 2019 trials, whose Random-robot returns are far from the paper's Random column.
CLONE_HUMAN = ("human={kind: bc}",)


def _paper_cell(mean: float, se) -> str:
    return f"{mean:.2f}" if se is None else f"{mean:.2f} ± {se:.2f}"


def paper_claims() -> list[Claim]:
    claims = []
    for n in (2, 5, 7, 10):
        esr = (f"grid_{n}", ())
        var = [(f"grid_{n}", QUICK_CHANGES), (f"grid_{n}", FUTURE_HUMAN)]
        claims.append(Claim("Figure 1", f"N = {n}: ESR ends above Random", "ESR's final return is above Random's at every N",
                            "above", esr, (f"grid_{n}_random", ()), var))
        if n == 2:
            claims.append(Claim("Figure 1", "N = 2: ESR and AvE end level",
                                "at N = 2 ESR and AvE reach a similar final return (AvE sooner)",
                                "similar", esr, (f"grid_{n}_ave", PUBLISHED_AVE), var, [(f"grid_{n}_ave", ())]))
        else:
            fixed_ave = [(f"grid_{n}_ave", ())]
            claims.append(Claim("Figure 1", f"N = {n}: ESR ends above AvE", "from N = 5 on ESR is clearly the best method",
                                "above", esr, (f"grid_{n}_ave", PUBLISHED_AVE), var, fixed_ave))
            claims.append(Claim("Figure 1", f"N = {n}: AvE ends below Random", "from N = 5 on AvE falls below Random",
                                "above", (f"grid_{n}_random", ()), (f"grid_{n}_ave", PUBLISHED_AVE), [], fixed_ave))
            claims.append(Claim("Figure 1", f"N = {n}: ESR ends above Goal Inference", "Goal Inference fails except at N = 2",
                                "above", esr, (f"grid_{n}_goal_inference", PUBLISHED_GOAL_INFERENCE), var,
                                [(f"grid_{n}_goal_inference", ())]))
            claims.append(Claim("Figure 1", f"N = {n}: ESR ends above Reward Inference",
                                "Reward Inference fails except at N = 2", "above", esr, (f"grid_{n}_iq_learn", ()), var))
    from esr_cli.report.figures import PAPER_OVERCOOKED  # the paper's table: mean, SE (Random: mean only)

    for layout in ("cramped_room", "coord_ring", "asymm_advantages"):
        paper = {m: _paper_cell(*v) for m, v in PAPER_OVERCOOKED[layout].items()}
        earlier = [("with esr's MLP clone as the human, not the paper's", CLONE_HUMAN)]
        for base, label in (("random", "Random"), ("iq_learn", "Reward Inference")):
            claims.append(Claim("Figure 2", f"{layout}: ESR ends above {label}", f"ESR {paper['esr']} against {label} {paper[base]}",
                                "above", (layout, ()), (f"{layout}_{base}", ()), conditions=earlier))
        claims.append(Claim("Figure 2", f"{layout}: ESR ends above AvE", f"ESR {paper['esr']} against AvE {paper['ave']}",
                            "above", (layout, ()), (f"{layout}_ave", PUBLISHED_AVE), [], [(f"{layout}_ave", ())], earlier))
    for n in (2, 5, 7, 10):
        claims.append(Claim("Figure 3", f"N = {n}: ESR ends above ESR without the robot action",
                            "without aR in phi and phi' learning is worse, most at high N", "above",
                            (f"grid_{n}", ()), (f"grid_{n}", NO_ROBOT_ACTION)))
    for n in (2, 5, 7, 10):
        claims.append(Claim("Figure 4", f"N = {n}: ESR ends above the greedy ESR (critic gamma 0)",
                            "a greedy critic does far worse than gamma = 0.9", "above",
                            (f"grid_{n}", ()), (f"grid_{n}", GREEDY)))
    for n in (2, 5, 7, 10):
        claims.append(Claim("Figure 5", f"N = {n}: the MI estimate turns positive and stays positive",
                            "the estimate turns positive early in training and stays positive", "mi_positive",
                            (f"grid_{n}", ()), None, [(f"grid_{n}", QUICK_CHANGES), (f"grid_{n}", FUTURE_HUMAN)]))
    return claims


def claim_spec(ref: tuple[str, tuple[str, ...]]) -> spec_model.Spec:
    stem, sets = ref
    return specs.load(EXPERIMENTS / f"{stem}.yaml", "paper", list(sets))


# ---------------------------------------------------------------- verdicts
@dataclass
class Finding:
    claim: Claim
    a: Optional[Evidence]
    b: Optional[Evidence]
    verdict: str
    measured: str
    variants: list[tuple[str, Optional[Evidence], str]] = field(default_factory=list)
    # esr's stronger baselines, each judged in place of the published one
    baselines: list["BaselineRow"] = field(default_factory=list)
    # The other stored runs of the first spec (fewer epochs, another seed set or device), with
    # their own comparison: a one-seed verdict is read beside the several-seed runs that exist.
    others: list[tuple[Evidence, str]] = field(default_factory=list)
    conditions: list["ConditionRow"] = field(default_factory=list)  # the claim's other conditions, judged

    def evidence(self) -> list[Evidence]:
        """Every run shown for this claim (pooled ones as themselves)."""
        runs = [self.a, self.b] + [v[1] for v in self.variants] + [o[0] for o in self.others]
        runs += [r.evidence for r in self.baselines]
        runs += [e for c in self.conditions for e in [c.a, c.b] + [o[0] for o in c.others]]
        return [e for e in runs if e is not None]


def _final_mi(ev: Evidence) -> tuple[float, float]:
    """(the MI estimate's mean over the last FINAL_FRACTION of epochs, the share of the second
    half's epochs where it is above zero); NaN where the run logs no estimate."""
    _, vals = series(ev.rows, "mi_estimate")
    with warnings.catch_warnings():  # a run without the metric is all NaN: its mean is NaN, said so
        warnings.simplefilter("ignore", RuntimeWarning)
        mi = np.nanmean(vals, axis=1)
        second = mi[len(mi) // 2:]
        k = max(1, int(round(len(mi) * FINAL_FRACTION)))
        final = float(np.nanmean(mi[-k:]))
    share = float(np.mean(second > 0)) if len(second) else float("nan")
    return final, share


def _mi_summary(ev: Evidence) -> tuple[bool, str]:
    final, share = _final_mi(ev)
    holds = final > MI_POSITIVE and share >= 0.9
    return holds, f"final MI {final:+.3f} nats; positive in {share:.0%} of the second half's epochs"


@cache  # every label of a report asks again for the same few spec files
def _paper_repr_lr(name: str) -> Optional[float]:
    """The representation rate of experiments/<name>.yaml at the paper's budget (it differs
    between environments), or None where there is no such ESR spec file."""
    try:
        base = specs.load(EXPERIMENTS / f"{name}.yaml", "paper")
    except (OSError, specs.SpecError, yamlio.YamlInputError):
        return None
    return base.method.repr_lr if isinstance(base.method, spec_model.ESRMethodSpec) else None


def run_label(spec: spec_model.Spec) -> str:
    """The method of a run as a reader knows it, with what sets it apart from the paper's
    settings in brackets: 'ESR (warm-up 20, representation rate 0.001)', 'AvE (published)'."""
    from esr_cli.report.figures import PAPER_LABELS

    method, notes = spec.method, []
    if isinstance(method, spec_model.AvEMethodSpec) and method.variant == "original":
        notes.append("published")
    if isinstance(method, spec_model.GoalInferenceMethodSpec):
        notes.append("published" if method.variant == "original" else "exact posterior")
    if isinstance(method, spec_model.ESRMethodSpec):
        if not method.condition_on_robot_action:
            notes.append("without aR")
        if method.future == "human":
            notes.append("human future")
        paper_rate = _paper_repr_lr(spec.name)
        if paper_rate is not None and method.repr_lr != paper_rate:
            notes.append(f"representation rate {method.repr_lr:g}")
    if not specs.plays_with_paper_human(spec):
        notes.append(f"{spec.human.kind} human")
    if spec.learner.gamma == 0.0:
        notes.append("critic gamma 0")
    if spec.learner.warmup_epochs:
        notes.append(f"warm-up {spec.learner.warmup_epochs}")
    name = PAPER_LABELS.get(method.kind, method.kind).removesuffix(" (ours)")
    return name + (f" ({', '.join(notes)})" if notes else "")


def _compare(kind: str, a: Evidence, b: Evidence) -> tuple[bool | None, str]:
    """(holds, text): True / False, or None where several seeds leave it open."""
    fa, fb = a.finals(), b.finals()
    text = f"{run_label(a.spec)} {format_summary(fa)} against {run_label(b.spec)} {format_summary(fb)}"
    if not scored_seeds(fa) or not scored_seeds(fb):  # a side without a finite final score decides nothing
        return None, text
    if kind == "similar":
        return _equivalent(fa, fb, text)
    if scored_seeds(fa) >= 2 or scored_seeds(fb) >= 2:
        p, low, high = probability_of_improvement(fa["per_seed"], fb["per_seed"])
        text += f"; P(improvement) {p:.2f} [{low:.2f}, {high:.2f}]"
        return (True if low > 0.5 else False if high < 0.5 else None), text
    if kind == "above":
        return fa["mean"] > fb["mean"], text
    return _equivalent(fa, fb, text)


def _equivalent(fa: dict, fb: dict, text: str) -> tuple[bool | None, str]:
    """Two one-sided tests: similar when the 90% interval of the difference of the means lies
    inside +- EQUIVALENCE_MARGIN of the larger mean, different when it lies wholly outside it."""
    margin = EQUIVALENCE_MARGIN * max(abs(fa["mean"]), abs(fb["mean"]), 1e-9)
    diff, low, high = mean_difference_ci(fa["per_seed"], fb["per_seed"])
    if low is None:
        return abs(diff) <= margin, text + f"; difference {diff:+.2f}, margin ±{margin:.2f}"
    text += f"; difference {diff:+.2f} [{low:+.2f}, {high:+.2f}], margin ±{margin:.2f}"
    if -margin <= low and high <= margin:
        return True, text
    return (False if low > margin or high < -margin else None), text


def judge(claim: Claim, index: dict[str, list[Evidence]]) -> Finding:
    a = pooled(index, claim_spec(claim.a))
    b = pooled(index, claim_spec(claim.b)) if claim.b else None
    variants = []
    for ref in claim.variants:
        ev = pooled(index, claim_spec(ref))
        label = " ".join(ref[1])
        if ev is None:
            variants.append((label, None, "not run"))
        elif claim.kind == "mi_positive":
            variants.append((label, ev, _mi_summary(ev)[1]))
        else:
            other = b and _compare(claim.kind, ev, b)[1]
            variants.append((label, ev, other or f"{run_label(ev.spec)} {format_summary(ev.finals())}"))
    baselines = _baseline_rows(claim, a, index)
    conditions = [_condition_row(claim, label, sets, index) for label, sets in claim.conditions]
    needed = [a] + ([b] if claim.b else [])
    if any(e is None for e in needed):
        return Finding(claim, a, b, NOT_YET, "not run", variants, baselines, conditions=conditions)
    more = [(ev, _mi_summary(ev)[1] if claim.kind == "mi_positive" else _compare(claim.kind, ev, b)[1])
            for ev in others(index, claim_spec(claim.a), a)]
    if claim.kind == "mi_positive":
        holds, measured = _mi_summary(a)
    else:
        holds, measured = _compare(claim.kind, a, b)
    if not all(e.comparable() for e in needed):
        return Finding(claim, a, b, NOT_YET, measured, variants, baselines, more, conditions)
    verdict = tiered_verdict(holds, [_scored(e) for e in needed])
    differs = [row.label for row in baselines if row.judged and row.holds != holds]
    if differs:
        measured += f"; the verdict depends on the baseline: against {', '.join(differs)} it is different (below)"
    return Finding(claim, a, b, verdict, measured, variants, baselines, more, conditions)


class ConditionRow(NamedTuple):
    """A claim judged on runs made under other conditions than the paper's (both sides alike)."""

    label: str
    a: Optional[Evidence]
    b: Optional[Evidence]
    measured: str
    verdict: str
    others: list[tuple[Evidence, str]] = []  # the other runs of the first spec, each compared as `a` is


def _condition_row(claim: Claim, label: str, sets: tuple[str, ...], index) -> ConditionRow:
    spec_a, spec_b = (claim_spec((stem, own + sets)) for stem, own in (claim.a, claim.b))
    a, b = pooled(index, spec_a), pooled(index, spec_b)
    if a is None or b is None:
        return ConditionRow(label, a, b, "not run", NOT_YET)
    holds, measured = _compare(claim.kind, a, b)
    more = [(ev, _compare(claim.kind, ev, b)[1]) for ev in others(index, spec_a, a)]
    return ConditionRow(label, a, b, measured, _pair_verdict(holds, a, b), more)


def _pair_verdict(holds: bool | None, a: Evidence, b: Evidence, tiers=None) -> str:
    """The tiered verdict of a comparison of two runs (by `tiers`, tiered_verdict unless named),
    once both are at a comparable length."""
    if not (a.comparable() and b.comparable()):
        return NOT_YET
    return (tiers or tiered_verdict)(holds, [_scored(a), _scored(b)])


class BaselineRow(NamedTuple):
    """A claim judged against one of esr's stronger baselines instead of the published one."""

    label: str
    evidence: Optional[Evidence]
    measured: str
    verdict: str
    holds: bool | None = None  # which way the comparison leans (when judged)
    judged: bool = False  # both runs at a comparable length


def _baseline_rows(claim: Claim, a: Optional[Evidence], index) -> list[BaselineRow]:
    rows = []
    for ref in claim.baseline_variants:
        ev = pooled(index, claim_spec(ref))
        label = f"esr's {run_label(claim_spec(ref))}"
        if ev is None or a is None:
            rows.append(BaselineRow(label, ev, "not run" if ev is None else format_summary(ev.finals()), NOT_YET))
            continue
        holds, measured = _compare(claim.kind, a, ev)
        judged = a.comparable() and ev.comparable()
        rows.append(BaselineRow(label, ev, measured, _pair_verdict(holds, a, ev), holds if judged else None, judged))
    return rows


def _scored(ev: Evidence) -> int:
    """Seeds with a final score: a seed without one counts towards no tier."""
    return scored_seeds(ev.finals())


def tiered_verdict(holds: bool | None, seeds: list[int]) -> str:
    """reproduced / not reproduced / inconclusive with MIN_SEEDS seeds on every side; below that
    only indicative, with which way the numbers lean; always with the seeds it rests on."""
    note = _seed_note(seeds)
    if min(seeds) >= MIN_SEEDS:
        return (INCONCLUSIVE if holds is None else REPRODUCED if holds else NOT_REPRODUCED) + note
    return f"{INDICATIVE}: {LEANINGS[holds]}{note}"


def _seed_note(seeds: list[int]) -> str:
    """The seeds a verdict rests on: ' (3 seeds each)', ' (1 seed)', ' (5 seeds against 1 seed)'."""
    count = lambda n: f"{n:,} seed{'' if n == 1 else 's'}"  # noqa: E731
    if len(set(seeds)) == 1:
        return f" ({count(seeds[0])}{' each' if len(seeds) > 1 and seeds[0] > 1 else ''})"
    return " (" + " against ".join(count(n) for n in seeds) + ")"


# ---------------------------------------------------------------- esr's variants, set against the paper's setting
# Which way a variant's final return goes against the paper's setting of its spec (the same rule
# as 'above': the probability-of-improvement interval, or one seed's sign). Not a paper statement.
VARIANT_LEANINGS = {True: "higher", False: "lower", None: "not distinguishable"}


class VariantRow(NamedTuple):
    """One of esr's variants against the run of the paper's setting its statements are judged on."""

    label: str
    variant: Evidence
    paper: Evidence
    measured: str
    mi: str
    reading: str


def variant_rows(findings: list[Finding]) -> list[VariantRow]:
    """Each (paper run, variant run) pair shown under the findings, once."""
    rows, seen = [], set()
    for f in findings:
        for label, ev, _ in f.variants:
            if ev is None or f.a is None or (f.a.key, ev.key) in seen:
                continue
            seen.add((f.a.key, ev.key))
            holds, measured = _compare("above", ev, f.a)
            rows.append(VariantRow(label, ev, f.a, measured, _mi_against(ev, f.a),
                                    _pair_verdict(holds, ev, f.a, _variant_tiers)))
    return rows


def _mi_against(variant: Evidence, paper: Evidence) -> str:
    (mv, _), (mp, _) = _final_mi(variant), _final_mi(paper)
    return "—" if np.isnan(mv) or np.isnan(mp) else f"{mv:+.3f} against {mp:+.3f}"


def _variant_tiers(holds: bool | None, seeds: list[int]) -> str:
    """Which way, with the seeds it rests on; only indicative below MIN_SEEDS a side."""
    word = VARIANT_LEANINGS[holds] + _seed_note(seeds)
    return word if min(seeds) >= MIN_SEEDS else f"{INDICATIVE}: {word}"


def variant_section(findings: list[Finding]) -> list[str]:
    rows = variant_rows(findings)
    if not rows:
        return []
    lines = ["## esr's variants against the paper's setting", "",
             "Not statements of the paper: each of esr's variants shown above, set against the statements' own ESR run "
             "(the paper's setting of the variant's spec). Final return as above, and the final MI estimate (its mean "
             f"over the last {FINAL_FRACTION:.0%} of epochs, seeds averaged). Which way: *higher* when the lower end of "
             "the probability-of-improvement interval is above 0.5, *lower* when its upper end is below 0.5, *not "
             "distinguishable* otherwise; one seed against one, the sign of the difference. With fewer than "
             f"{MIN_SEEDS} seeds on a side it is only *{INDICATIVE}*; where either run is shorter than "
             f"{COMPARABLE_EPOCHS['gridworld']:,} epochs (gridworld) or {COMPARABLE_EPOCHS['overcooked']:,} (Overcooked) it "
             f"is *{NOT_YET}*. The two runs may come from different devices and commits (the runs column).", "",
             "| variant | measured | final MI | runs | which way |", "|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row.paper.spec.name}: `{row.label}` | {row.measured} | {row.mi} | "
                     f"{_run_cell(row.variant)}<br>vs {_run_cell(row.paper)} | {row.reading} |")
    return lines + [""]


# ---------------------------------------------------------------- the report
def _run_cell(ev: Optional[Evidence]) -> str:
    if ev is None:
        return "—"
    if ev.parts:
        return "seeds pooled from " + " + ".join(_run_cell(p) for p in ev.parts)
    commit = f", commit {ev.commit_label}" if ev.commit else ""
    # The CPU is the default and goes unsaid; an accelerator's figures are marked as such.
    device = f", on {ev.accelerator}" if ev.accelerator else ""
    return f"`{ev.key[:8]}` ({ev.budget}; {ev.describe_length()}{commit}{device})"


def _leaves(tree: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in tree.items():
        if isinstance(v, dict):
            out.update(_leaves(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _override_text(path: str, value) -> str:
    if path == "train.seeds" and value == list(range(len(value))):
        value = len(value)  # seeds 0..n-1, as a spec file writes them
    text = value if isinstance(value, str) else json.dumps(value)
    return f"{path}={text}"


def train_overrides(spec: spec_model.Spec, budget: str, experiments: Path = EXPERIMENTS) -> Optional[tuple[Path, list[str]]]:
    """The spec file in `experiments` and the `--set` values that, at `budget`, resolve to this
    spec's training part (the run's key), or None when no such file does. The result is checked
    by resolving it, so a command printed from it makes this very run."""
    file = experiments / f"{spec.name}.yaml"
    if not file.is_file():
        return None
    target = spec.training_part()
    # First the fields that differ from the file's; where that does not resolve (a section the
    # file names by a preset, whose fields a value beside it may not change), each section that
    # differs starts again from its kind's defaults.
    for restart in (False, True):
        try:
            sets = _overrides(file, budget, target, restart)
            if specs.load(file, budget, sets).training_part() == target:
                return file, sets
        except (specs.SpecError, yamlio.YamlInputError):
            continue
    return None


def _overrides(file: Path, budget: str, target: dict, restart: bool) -> list[str]:
    base_part, sets = specs.load(file, budget).training_part(), []
    for section, value in target.items():
        base, want = _leaves(base_part.get(section, {}), f"{section}."), _leaves(value, f"{section}.")
        if base != want and isinstance(value, dict) and "kind" in value and (restart or base.keys() != want.keys()):
            kind = f"{section}={json.dumps({'kind': value['kind']})}"
            base = _leaves(specs.load(file, budget, [kind]).training_part().get(section, {}), f"{section}.")
            sets.append(kind)
        if base.keys() != want.keys():  # another kind of method, human or network: the section whole
            sets = [t for t in sets if not t.startswith(f"{section}=")] + [f"{section}={json.dumps(value)}"]
        else:
            sets += [_override_text(k, want[k]) for k in want if want[k] != base[k]]
    return sets


def train_command(ev: Evidence, store: Store) -> str:
    """The command that made this run and, run again from a checkout of its commit, continues it."""
    found = train_overrides(ev.spec, ev.budget)
    if found is None:
        return f"no spec file in experiments/ resolves to this run; its spec is {ev.path / 'spec.yaml'}"
    file, sets = found
    try:
        shown = file.relative_to(EXPERIMENTS.parent)
    except ValueError:
        shown = file
    return train_line(store.invocation(always_named=True), shown, ev.budget, sets)


MIN_CURVE_EPOCHS = 500


def learning_curves(findings: list[Finding], out_png: Path, title: str) -> list[Evidence]:
    """The curves of every run behind the report with at least MIN_CURVE_EPOCHS epochs: a row per
    figure of the paper (its MI estimate for figure 5, returns otherwise), a panel per
    environment, a line per run (esr_cli/report/reproduction_figure.py). Returns the runs drawn
    (none: no figure)."""
    from esr_cli.report import figures as figs, reproduction_figure

    def panel_order(e: Evidence):
        return (e.spec.env.kind, getattr(e.spec.env, "blocks", 0), figs.env_title(e.spec))

    rows, drawn = [], {}
    for figure in dict.fromkeys(f.claim.figure for f in findings):
        runs: dict[str, Evidence] = {}
        for f in (x for x in findings if x.claim.figure == figure):
            others = {o[0].key for o in f.others} | {o[0].key for c in f.conditions for o in c.others}
            for ev in f.evidence():
                if ev.key not in others and ev.epochs_done >= MIN_CURVE_EPOCHS:
                    runs[ev.key] = ev
        drawn.update(runs)
        panels: dict[str, list] = {}
        for ev in sorted(runs.values(), key=lambda e: (panel_order(e), run_label(e.spec), e.key)):
            panels.setdefault(figs.env_title(ev.spec), []).append((run_label(ev.spec), ev.spec, ev.rows))
        if panels:
            metric = "mi_estimate" if any(f.claim.kind == "mi_positive" for f in findings if f.claim.figure == figure) else "return"
            rows.append((figure, metric, list(panels.items())))
    if not rows:
        return []
    reproduction_figure.draw(rows, out_png, title)
    return list(drawn.values())


def devices_line(runs: list[Evidence]) -> str:
    """Which devices made the runs of a figure, with how many runs each (a run resumed elsewhere
    names both, in order)."""
    made: dict[str, list[str]] = {}
    for ev in sorted(runs, key=lambda e: e.key):
        made.setdefault(ev.device or "unknown", []).append(ev.key[:8])
    parts = [f"{device} ({len(keys)} run{'s' if len(keys) != 1 else ''}"
             + (f": {', '.join(f'`{k}`' for k in keys)})" if not device.startswith("cpu") else ")")
             for device, keys in sorted(made.items(), key=lambda kv: (kv[0].startswith("cpu"), kv[0]))]
    return "Made on: " + "; ".join(parts) + " (each run's device as its manifest records it)."


def _world(e: Evidence) -> str:
    """A run's environment and human: runs that share them are compared with each other."""
    part = e.spec.training_part()
    return json.dumps({"env": part["env"], "human": part["human"]}, sort_keys=True)


def estimator_run(index: dict[str, list[Evidence]]) -> Optional[Evidence]:
    """The finished ESR gridworld run with the most epochs (then seeds) that learned (its final
    return above the Random run's on its own gridworld with its own human), among the gridworlds
    small enough for exact empowerment (N <= 2 blocks); ties go to the paper's own settings, then
    to the key, so the choice never depends on the order of the store."""
    runs = [ev for evs in index.values() for ev in evs]
    learned = []
    for ev in runs:
        if ev.spec.method.kind != "esr" or ev.spec.env.kind != "gridworld" or ev.spec.env.blocks > 2 or ev.status != "complete":
            continue
        rnd = max((r for r in runs if r.spec.method.kind == "random" and _world(r) == _world(ev)), key=_rank, default=None)
        if rnd is not None and ev.finals()["mean"] > rnd.finals()["mean"]:
            learned.append(ev)

    def paper_settings(e: Evidence) -> bool:
        stem = f"grid_{e.spec.env.blocks}"
        return (EXPERIMENTS / f"{stem}.yaml").is_file() and _without_train(e.spec) == _without_train(claim_spec((stem, ())))

    return max(learned, key=lambda e: (e.epochs_done, e.seeds, paper_settings(e), e.key), default=None)


def estimator_section(index: dict[str, list[Evidence]], store: Store, console, compute: bool,
                      img_dir: Path) -> list[str]:
    """The estimator check (exact empowerment against ESR's reward) on `estimator_run`, read from
    the store's exact and estimator checks (`compute`: made first where the store lacks them),
    its scatter copied into `img_dir` beside the report."""
    lines = ["## The estimator against exact empowerment", ""]
    ev = estimator_run(index)
    if ev is None:
        return lines + ["No finished ESR run on a gridworld small enough for exact empowerment (N = 2) has "
                        "learned yet (above Random at its N); this section fills in once one has.", ""]
    head = (f"On ESR run `{ev.key[:8]}` (N = {ev.spec.env.blocks}, {ev.describe_length()}), goal at the centre, "
            "seed 0's robot:")
    trained, uniform = _stored_estimator_check(ev, store)
    # Checks stored by other code count: they are read, never made again (a check kept without
    # its arrays, as evidence/ keeps them, could not be).
    if compute and not (_measured(trained, uniform) and trained.estimator):
        _make_estimator_check(ev, store, console)
        trained, uniform = _stored_estimator_check(ev, store)
    if not _measured(trained, uniform):
        return lines + [head, "", "not computed (run `esr paper --report` without `--no-exact`).", ""]
    from esr_cli.common.plots import SCATTER_POINTS

    rows = []
    if trained.spearman_all is not None and trained.pairs:
        rows.append(f"| Spearman (ESR's reward, exact MI), all {trained.pairs:,} (state, robot action) pairs | "
                    f"{number_cell(trained.spearman_all)} |")
    rows += [f"| the same over the {trained.visited_pairs or 0:,} pairs holding 99% of the trained robot's discounted "
             f"occupancy | {number_cell(trained.spearman_visited)} |",
             f"| the human's exact effective empowerment under the trained robot | {number_cell(trained.effective_empowerment)} nats |",
             f"| the same under a uniform robot | {number_cell(uniform.effective_empowerment)} nats |"]
    figure = []
    scatter = store.lookup(FIGURE_KIND, trained.estimator) if trained.estimator else None
    if scatter is not None and (scatter / "estimator.png").is_file():
        from esr_cli.report.paper import read_figure_file  # the figures' own bounded reader

        img_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(img_dir / "reproduction_estimator.png", read_figure_file(scatter / "estimator.png"))
        shown = f", {min(trained.pairs, SCATTER_POINTS):,} of the {trained.pairs:,} drawn at random" if trained.pairs else ""
        figure = ["![ESR's reward against the exact MI](img/reproduction_estimator.png)", "",
                  f"The scatter (`esr plot estimator {trained.exact[:8]}`): one point per (state, robot action) pair{shown}.", ""]
    return lines + [head, "", "| quantity | value |", "|---|---|", *rows, "",
                    f"Artifacts: exact `{trained.exact[:8]}` (trained), `{uniform.exact[:8]}` (uniform), "
                    f"estimator check `{trained.estimator[:8]}`.", ""] + figure


def _measured(trained: SeedCheck, uniform: SeedCheck) -> bool:
    """Whether the stored checks hold the numbers the section shows."""
    return (trained.spearman_visited is not None and trained.effective_empowerment is not None
            and uniform.effective_empowerment is not None)


def _stored_estimator_check(ev: Evidence, store: Store) -> tuple[SeedCheck, SeedCheck]:
    """Seed 0's exact and estimator checks of `ev`'s run and the exact check of a uniform robot on
    its environment, at `esr exact`'s default goal and discount, as the store holds them."""
    goal, gamma = exact_defaults(ev.spec)
    part = ev.spec.training_part()
    checks = read_checks(store)
    trained, uniform = (run_checks(checks, Target(run, part["env"], part["human"], goal, gamma), 1)[0]
                        for run in (ev.key, None))
    return trained, uniform


def _make_estimator_check(ev: Evidence, store: Store, console) -> None:
    """The exact checks of seed 0's robot and of a uniform one, and the estimator check, made
    where the store lacks them (minutes each)."""
    from esr_cli.recipes import exact_runs  # jax: only when the report computes exact empowerment

    trained = ensure(exact_runs.exact_recipe(ev.spec, store, None, None, ev.key, 0, console), store)
    ensure(exact_runs.exact_recipe(ev.spec, store, None, None, None, 0, console), store)
    ensure(exact_runs.estimator_recipe(trained.path.name, store, console), store)


def verdict_counts(findings: list[Finding]) -> dict[str, int]:
    """How many statements have each verdict, whatever their seed note; indicative rows by how
    their numbers lean."""
    tiers = [REPRODUCED, NOT_REPRODUCED, INCONCLUSIVE] + [f"{INDICATIVE}: {v}" for v in LEANINGS.values()] + [NOT_YET]
    return {v: sum(f.verdict.startswith(v) for f in findings) for v in tiers}


def summary_line(findings: list[Finding]) -> str:
    c = verdict_counts(findings)
    lean = [c[f"{INDICATIVE}: {v}"] for v in LEANINGS.values()]
    return (f"{len(findings)} statements: {c[REPRODUCED]} {REPRODUCED}, {c[NOT_REPRODUCED]} {NOT_REPRODUCED} and "
            f"{c[INCONCLUSIVE]} {INCONCLUSIVE} with at least {MIN_SEEDS} seeds on every side; {sum(lean)} {INDICATIVE} "
            f"on fewer seeds ({lean[0]} holding, {lean[1]} not holding, {lean[2]} open); {c[NOT_YET]} {NOT_YET}.")


def report(store: Store, out: Path, console, exact: bool = True, now: Optional[str] = None) -> list[Finding]:
    """Write the reproduction report to `out` (markdown, with its curves beside it in img/)."""
    import time

    index = index_store(store)
    findings = [judge(c, index) for c in paper_claims()]
    lines = [
        "# Reproduction report", "",
        f"Generated by `esr --store {store.root} paper --report{'' if exact else ' --no-exact'} --out {out}` on "
        f"{now or time.strftime('%Y-%m-%d %H:%M %Z')} from the runs in that store; nothing is copied by hand. "
        "Run the same command again to bring it up to date.", "",
        "How to read it:",
        "- Each row is one statement of the paper, checked on the stored run with the most epochs whose spec matches "
        "(in every field outside `train`, so runs of any length, seed count or checkout count). A run made on an "
        "accelerator says so ('on gpu:...'); the others ran on a CPU. Finished runs of that length that differ only in "
        "their seeds (same training code and toolchain, as their keys name them, and same device) are pooled into one run of all their seeds; every other run of the spec "
        "is listed beside the verdict.",
        f"- Final return: each seed's mean over its last {FINAL_FRACTION:.0%} of epochs. Several seeds: mean ± SE, "
        "the interquartile mean (IQM) with its 95% stratified bootstrap interval, and the probability that the first run "
        "improves on the second with its interval. One seed: its value, marked as one seed.",
        f"- Verdict: a row is judged once every run behind it has {COMPARABLE_EPOCHS['gridworld']:,} epochs (gridworld) "
        f"or {COMPARABLE_EPOCHS['overcooked']:,} (Overcooked); before that it is *{NOT_YET}*, with the numbers so far. "
        f"With at least {MIN_SEEDS} seeds on every side it is *{REPRODUCED}*, *{NOT_REPRODUCED}* or *{INCONCLUSIVE}*; "
        f"with fewer it is only *{INDICATIVE}*, saying which way its numbers lean (holds, does not hold, open). "
        "'Above': with several seeds on a side, holds when the lower end of the probability-of-improvement interval is "
        "above 0.5, does not when its upper end is below 0.5, open otherwise; one seed against one: the sign of the "
        f"difference. 'Similar' (an equivalence test): the margin is {EQUIVALENCE_MARGIN:.0%} of the larger mean; holds "
        "when the 90% bootstrap interval of the difference of the means lies inside it (two one-sided tests at 5%), does "
        "not when the interval lies wholly outside it, open otherwise; one seed against one: the difference itself. "
        f"The MI estimate 'stays positive' when its mean over the last {FINAL_FRACTION:.0%} of epochs is above "
        f"{MI_POSITIVE} nats and it is above 0 in at least 90% of the second half's epochs.",
        "- Baselines: each claim is judged against the baseline the paper ran (the published AvE, Du et al.'s Goal "
        "Inference); esr's stronger versions (AvE with its sampling fixed, Goal Inference by the exact posterior) are "
        "extra rows marked as esr's, and a verdict that would change with them says so.",
        "- Overcooked's human: the statements are judged on runs with the paper's human (the layout specs' "
        "`human: {preset: paper}`); runs with esr's MLP clone of the 2019 trials (`human={kind: bc}`) are rows of their "
        "own under each statement, judged on their own pair of runs, never in its place.",
        "- The paper ran 20 seeds (gridworld) and 5 to 15 (Overcooked) for 10,000 epochs.", "",
        f"**Summary:** {summary_line(findings)}", "",
    ]
    for figure in dict.fromkeys(f.claim.figure for f in findings):
        lines += [f"## {figure}", "", "| statement | the paper | measured | runs | verdict |", "|---|---|---|---|---|"]
        for f in (x for x in findings if x.claim.figure == figure):
            runs = _run_cell(f.a) + ("<br>vs " + _run_cell(f.b) if f.claim.b else "")
            lines.append(f"| {f.claim.text} | {f.claim.paper} | {f.measured} | {runs} | **{f.verdict}** |")
            for ev, measured in f.others:
                lines.append(f"| ↳ another run of this spec | | {measured} | {_run_cell(ev)} | |")
            for label, ev, measured in f.variants:
                if ev is not None:
                    lines.append(f"| ↳ esr's variant `{label}` | | {measured} | {_run_cell(ev)} | |")
            for row in f.baselines:
                if row.evidence is not None:
                    lines.append(f"| ↳ against {row.label} | | {row.measured} | {_run_cell(row.evidence)} | {row.verdict} |")
            for row in f.conditions:
                if row.a is not None or row.b is not None:
                    runs = _run_cell(row.a) + "<br>vs " + _run_cell(row.b)
                    lines.append(f"| ↳ {row.label} | | {row.measured} | {runs} | {row.verdict} |")
                for ev, measured in row.others:
                    lines.append(f"| ↳ another run of this spec, {row.label} | | {measured} | {_run_cell(ev)} | |")
        lines.append("")
    lines += variant_section(findings)
    behind = {part.key: part for f in findings for ev in f.evidence() for part in (ev.parts or (ev,))}
    if behind:
        lines += ["## The runs behind this report", "",
                  "Each was made by the command beside it, run from a checkout of its commit (the training code is part of a "
                  "run's key: docs/store.md). An unfinished run continues from its last checkpoint with the same command; a "
                  "finished one grows with a larger `train.epochs`, starting from its last epoch (docs/store.md). A run "
                  "made on an accelerator continues on one with the same jax (the backend and jax version are part of its "
                  "key); one whose checkpoint is not in this store (its logged epochs only, `esr import "
                  "--without-checkpoint`) starts again from epoch 0.", "",
                  "| run | spec | status | commit | command |", "|---|---|---|---|---|"]
        for ev in sorted(behind.values(), key=lambda e: (e.status == "complete", e.spec.name, e.key)):
            state = f"finished: {ev.describe_length()}" if ev.status == "complete" else f"**{ev.describe_length()}**"
            if ev.accelerator:
                state += f", on {ev.accelerator}"
            lines.append(f"| `{ev.key[:8]}` | {ev.spec.name} | {state} | "
                         f"{ev.commit_label} | `{train_command(ev, store)}` |")
        lines.append("")
    img = out.parent / "img" / "reproduction_curves.png"
    drawn = learning_curves(findings, img, f"Runs of at least {MIN_CURVE_EPOCHS:,} epochs behind the report: the interquartile "
                                           "mean over seeds with its 95% bootstrap band (seeds per run: the tables above)\n"
                                           "dashed: esr's variants; dotted: esr's MLP clone as the human")
    if drawn:
        lines += ["## Learning curves", "", f"![learning curves](img/{img.name})", "", devices_line(drawn), ""]
    lines += estimator_section(index, store, console, exact, out.parent / "img")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_output_file(out, "\n".join(lines).encode())
    return findings


GENERATED_PREFIX = "Generated by `esr"  # the line that names the store and the time: left out of --check


def _comparable_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if not line.startswith(GENERATED_PREFIX)]


def check(store: Store, committed: Path, console, exact: bool = True) -> list[str]:
    """The differences (a unified diff, at most 60 lines) between `committed` and the report the
    store's runs give now; [] when they agree. Writes nothing beside `committed`."""
    import difflib
    import tempfile

    from esr_cli.report.doc_tables import TableError, read_doc

    # Read first, bounded and only a regular file: what cannot be the report costs no work.
    if not committed.is_file():
        return [f"cannot read {committed}: {'not a regular file' if committed.exists() else 'no such file'}"]
    try:
        before = _comparable_lines("\n".join(read_doc(committed)))
    except (OSError, TableError) as e:
        return [f"cannot read {committed}: {getattr(e, 'strerror', None) or e}"]
    with tempfile.TemporaryDirectory() as tmp:
        fresh = Path(tmp) / committed.name
        report(store, fresh, console, exact=exact)
        now = _comparable_lines(fresh.read_text(encoding="utf-8"))
    diff = list(difflib.unified_diff(before, now, str(committed), "now", lineterm="", n=0))
    return diff[:60] + ([f"... {len(diff) - 60} more lines"] if len(diff) > 60 else [])


def findings_json(findings: list[Finding]) -> list[dict]:
    """Per-claim verdicts with the per-seed finals behind them (for scripts)."""
    def ev(e: Optional[Evidence]):
        return None if e is None else {"key": e.key, "status": e.status, "epochs": e.epochs_done, "seeds": e.seeds,
                                       "commit": e.commit, "final_return": e.finals()}

    return [{"figure": f.claim.figure, "statement": f.claim.text, "paper": f.claim.paper, "verdict": f.verdict,
             "measured": f.measured, "a": ev(f.a), "b": ev(f.b),
             "baselines": [{"baseline": r.label, "verdict": r.verdict, "measured": r.measured, "run": ev(r.evidence)}
                           for r in f.baselines],
             "conditions": [{"condition": c.label, "verdict": c.verdict, "measured": c.measured, "a": ev(c.a), "b": ev(c.b)}
                            for c in f.conditions],
             # esr's variants of `a`, each against `a` itself (not a verdict on the paper)
             "variants": [{"variant": r.label, "which_way": r.reading, "measured": r.measured, "final_mi": r.mi,
                           "run": ev(r.variant)} for r in variant_rows([f])]} for f in findings]

