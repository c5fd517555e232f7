"""Calibrating the Overcooked human against the paper's Random column, without any robot.

The paper's Random robot is uniform over the six actions, so its score measures the human it
is paired with. For each spec given (one per layout), each of `human_seeds` humans of the
spec's kind (human.seed, human.seed + 1, ...; each made, or found, in the store) plays
`episodes` 400-step episodes with three partners in the robot's seat: a uniform random one,
one that only stays, and itself. A row gives each partner's mean return over the humans, with
the SE over the humans (over episodes where there is one human), beside the paper's Random
score on that layout.

The selection rule, fixed before any candidate was measured (docs/overcooked.md): a
candidate's score is the mean over the paper's three layouts of |ln(random / paper)|, the
absolute log-ratio of its Random-partner return to the paper's; the least score is the
calibrated human. A return of 0 scores infinity.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import numpy as np
from rich.console import Console

from esr_cli.model.envs.overcooked import Overcooked
from esr_cli.model.humans import human_eval
from esr_cli.model.humans.registry import policy_logits
from esr_cli.recipes import stored_humans
from esr_cli.recipes.ppo_humans import EPISODE_STEPS
from esr_cli.report.figures import PAPER_OVERCOOKED
from esr_cli.storage.artifacts import ensure
from esr_cli.storage.store import Store

PARTNERS = human_eval.PARTNERS  # random, stay, self


class Row(NamedTuple):
    name: str  # the spec's name
    layout: str
    human: str  # the human's kind and key fields, for the table
    keys: list[str]  # the humans' artifact keys, in seed order
    returns: dict  # {partner: {"mean", "se", "per_human": [...]}}
    paper_random: float | None

    @property
    def log_ratio(self) -> float | None:
        """|ln(random / paper)|; None off the paper's layouts; inf for a return of 0."""
        if self.paper_random is None:
            return None
        mean = self.returns["random"]["mean"]
        return math.inf if mean <= 0 else abs(math.log(mean / self.paper_random))

    def as_json(self) -> dict:
        return {**self._asdict(), "log_ratio": self.log_ratio}


def describe(human_spec) -> str:
    d = human_spec.model_dump()
    if human_spec.kind == "bc":
        network = "conv" if d["network"] == "conv" else "x".join(map(str, d["hidden"]))
        return f"bc {network} stay_weight={d['stay_weight']:g} epochs={d['epochs']}"
    if human_spec.kind == "ppo":
        extra = f" kl_coef={d['kl_coef']:g}" if d["mode"] == "bc_kl" else ""
        extra += f" random_partner={d['random_partner']:g}" if d["random_partner"] else ""
        return f"ppo {d['mode']} steps={d['total_steps']:.3g}{extra}"
    return human_spec.kind


def calibrate_spec(spec, human_seeds: int, episodes: int, store: Store, console: Console) -> Row:
    """One row: `human_seeds` humans of `spec`'s kind on its layout, each with every partner."""
    layout = spec.env.layout
    env = Overcooked(layout, EPISODE_STEPS)
    logits = policy_logits(spec.human)
    per_human, keys = [], []
    for i, human in enumerate(stored_humans.seeded(spec.human, human_seeds)):
        recipe = stored_humans.stored_recipe(human, layout, console)
        ensure(recipe, store)
        keys.append(recipe.key)
        params = stored_humans.human_params(human, layout, store)
        per_human.append(human_eval.evaluate(env, logits, params, episodes, jax.random.PRNGKey(i)))
    returns = {}
    for partner in PARTNERS:
        means = [h[partner]["mean"] for h in per_human]
        # SE over the humans; with one human, over its episodes (human_eval's)
        se = float(np.std(means, ddof=1) / math.sqrt(len(means))) if len(means) > 1 else per_human[0][partner]["se"]
        returns[partner] = {"mean": float(np.mean(means)), "se": se, "per_human": means}
    return Row(spec.name, layout, describe(spec.human), keys, returns, paper_random(layout))


def paper_random(layout: str) -> float | None:
    """The paper's Random score on `layout`; None off the paper's layouts."""
    return PAPER_OVERCOOKED.get(layout, {}).get("random", (None,))[0]


def score(rows: list[Row]) -> float | None:
    """The selection rule's score: mean |ln(random / paper)| over the paper's three layouts;
    None unless the rows cover each of them once."""
    on_paper = [r for r in rows if r.paper_random is not None]
    if sorted(r.layout for r in on_paper) != sorted(PAPER_OVERCOOKED):
        return None
    return float(np.mean([r.log_ratio for r in on_paper]))


def within_target(row: Row) -> bool | None:
    """The target: within 15% of the paper on cramped_room and asymm_advantages, within a
    factor 1.5 on coord_ring (where the paper's 6.02 is a few soups)."""
    if row.paper_random is None:
        return None
    ratio = row.returns["random"]["mean"] / row.paper_random
    return (1 / 1.5 <= ratio <= 1.5) if row.layout == "coord_ring" else (0.85 <= ratio <= 1.15)


def cells(row: Row) -> list[str]:
    """A row as a table shows it: spec, layout, human, each partner's mean ± SE, paper, ratio."""
    returns = [f"{row.returns[p]['mean']:.2f} ± {row.returns[p]['se']:.2f}" for p in PARTNERS]
    paper = "-" if row.paper_random is None else f"{row.paper_random:.2f}"
    ratio = "-" if row.paper_random is None else f"{row.returns['random']['mean'] / row.paper_random:.2f}"
    return [row.name, row.layout, row.human, *returns, paper, ratio]


COLUMNS = ("spec", "layout", "human", *PARTNERS, "paper Random", "ratio")


def markdown(rows: list[Row], human_seeds: int, episodes: int) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|---|---|---|---:|---:|---:|---:|---:|"]
    lines += ["| " + " | ".join(cells(r)) + " |" for r in rows]
    s = score(rows)
    tail = f"score (mean |ln(random / paper)|): {s:.3f}" if s is not None else "score: needs the three paper layouts"
    return "\n".join(lines) + f"\n\n{human_seeds} human(s) per layout, {episodes} episodes each; {tail}\n"
