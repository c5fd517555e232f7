"""Calibrations of Overcooked humans (`esr human calibrate`), stored.

The calibration of one spec's human on its layout (`human_seeds` humans of the spec's recipe,
`episodes` episodes of each with each partner) is an artifact (kind `calibrations`), keyed by
the humans it played (their keys name the code that made them), the episode count and the code
that plays them. `esr human calibrate` answers again from the store, and a page's table reads
the stored calibration back (`esr tables`), never playing an episode.

A table asks for a calibration by what was calibrated (layout, human recipe, human seeds,
episodes): the one this checkout's code makes where the store has it, else the newest made by
other code (whose humans or player had other keys), which the table then names by commit, as
`esr sweep --results --any-code` names the commit of a run.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

from rich.console import Console

from esr_cli.common.numbers import as_number
from esr_cli.storage import provenance
from esr_cli.storage.artifacts import Recipe, summary_or_empty
from esr_cli.storage.store import CALIBRATION_KIND, Store, content_key

# The code that plays a stored human with each partner and sums the returns: the environment,
# the humans' policies and the evaluation loop (their import closure), and the module that
# makes the row; not this module, which decides where a calibration is read from, never what it is.
CALIBRATION_CODE = (("model/envs/overcooked.py", "model/humans/human_eval.py", "model/humans/registry.py"),
                    ("report/human_calibration.py",))
# The parts of the key that name what was calibrated, as a table asks for it; the rest ("humans",
# "code", "toolchain") names which code made it.
ASKED = ("kind", "layout", "human", "human_seeds", "episodes", "steps")
# A human's key components that say which code and data made it, not which recipe it is.
_MADE_BY = ("code", "toolchain", "packages", "dependencies")
# `esr human calibrate`'s counts, (least, most, default): the command's bounds and a table's.
COUNTS = {"human_seeds": (1, 64, 3), "episodes": (2, 100_000, 100)}
MAX_RETURN = 1e300  # a 400-step episode's return is a few hundred; anything near a float's end is damage


def human_keys(spec, human_seeds: int) -> list[str]:
    """The keys of the `human_seeds` humans a calibration of `spec` plays (data only)."""
    from esr_cli.recipes import stored_humans

    return [stored_humans.stored_key(human, spec.env.layout)[0] for human in stored_humans.seeded(spec.human, human_seeds)]


def asked(spec, human_seeds: int, episodes: int) -> dict:
    """What a calibration of `spec` is of, whichever code makes it: the first human's recipe as
    its own key reads it (a preset and its values written out are one recipe; the others differ
    in their seeds alone), the counts and the episodes' length."""
    from esr_cli.recipes import stored_humans
    from esr_cli.recipes.ppo_humans import EPISODE_STEPS

    _, made = stored_humans.stored_key(stored_humans.seeded(spec.human, 1)[0], spec.env.layout)
    recipe = {k: v for k, v in made.items() if k not in _MADE_BY}
    return {"kind": "calibration", "layout": spec.env.layout, "human": recipe, "human_seeds": human_seeds,
            "episodes": episodes, "steps": EPISODE_STEPS}


def components(spec, human_seeds: int, episodes: int) -> dict:
    return {**asked(spec, human_seeds, episodes), "humans": human_keys(spec, human_seeds),
            "code": provenance.code_digest(*CALIBRATION_CODE), "toolchain": provenance.toolchain()}


def check_specs(specs: list) -> str | None:
    """What is wrong with calibrating these specs together (one line), or None: each must be an
    Overcooked spec with a stored human, one per layout."""
    from esr_cli.recipes import stored_humans

    for spec in specs:
        if spec.env.kind != "overcooked" or not stored_humans.is_stored(spec.human):
            return (f"{spec.name}: a calibration needs an Overcooked spec whose human is stored (bc or ppo), "
                    f"not env.kind={spec.env.kind}, human.kind={spec.human.kind}")
    layouts = [s.env.layout for s in specs]
    if len(set(layouts)) != len(layouts):
        return f"two specs share a layout ({', '.join(layouts)}): give one spec per layout"
    return None


def calibration_recipe(spec, human_seeds: int, episodes: int, console: Console) -> Recipe:
    """The stored calibration of `spec`'s human: its humans are made first where the store lacks them."""
    from esr_cli.recipes import stored_humans
    from esr_cli.report import human_calibration as hc  # JAX, for the build alone

    humans = tuple(stored_humans.stored_recipe(human, spec.env.layout, console) for human in stored_humans.seeded(spec.human, human_seeds))

    def build(_path: Path, store: Store) -> dict:
        row = hc.calibrate_spec(spec, human_seeds, episodes, store, console)
        # Its log-ratio is derived (and infinite for a return of 0, which JSON cannot hold). `esr ls`
        # shows an artifact's summary "return": here the one the selection rule reads.
        return {**row._asdict(), "return": {"of": "with a uniform random partner", "mean": row.returns["random"]["mean"]}}

    return Recipe(CALIBRATION_KIND, spec.name, components(spec, human_seeds, episodes), build, requires=humans)


def find(store: Store, spec, human_seeds: int, episodes: int) -> Optional[tuple[Path, Optional[str], bool]]:
    """The stored calibration this checkout's code would make, else the newest one of what
    `asked` names: (its path, the commit that made it as a table names it, whether it is this
    code's); None when the store has neither."""
    want, key, found = asked(spec, human_seeds, episodes), content_key(components(spec, human_seeds, episodes)), None
    for entry in store.entries((CALIBRATION_KIND,)):
        comps = entry.manifest.get("key_components") if isinstance(entry.manifest, dict) else None
        if entry.status != "complete" or not isinstance(comps, dict) or any(comps.get(k) != want[k] for k in ASKED):
            continue
        rank = (entry.key == key, provenance.created_order(entry.manifest))
        if found is None or rank >= found[0]:
            found = (rank, entry)
    if found is None:
        return None
    (same_code, _), entry = found
    made = provenance.origin(entry.manifest)
    commit = made.commit[:7] + (" (esr_cli/ modified)" if made.modified else "") if made.commit else None
    return entry.path, commit, same_code


def damaged(path: Path) -> str:
    """The one line naming a stored calibration whose summary `read_row` cannot read."""
    return f"{path}: the stored calibration's summary is damaged: remove it and run `esr human calibrate` again"


def _finite(value) -> Optional[float]:
    """An episode return's mean or SE: a number of a return's size (NaN, infinity or 1e300 only
    from damage)."""
    number = as_number(value)
    return number if number is not None and math.isfinite(number) and abs(number) < MAX_RETURN else None


def read_row(path: Path, spec, human_seeds: int, keys: tuple[str, ...] = ()):
    """The stored calibration at `path` of `human_seeds` humans as the row of `spec` (its name,
    layout and human are the spec's, `keys` its humans' keys; only the returns are read from the
    store, as numbers); None when its summary is missing, damaged or not a calibration of as many
    humans (from an archive, perhaps)."""
    from esr_cli.report import human_calibration as hc

    returns = summary_or_empty(path).get("returns")
    if not isinstance(returns, dict):
        return None
    read = {}
    for partner in hc.PARTNERS:
        cell = returns.get(partner)
        if not isinstance(cell, dict) or not isinstance(cell.get("per_human"), list):
            return None
        mean, se = _finite(cell.get("mean")), _finite(cell.get("se"))
        per_human = [_finite(v) for v in cell["per_human"]]
        if mean is None or se is None or se < 0 or None in per_human or len(per_human) != human_seeds:
            return None
        read[partner] = {"mean": mean, "se": se, "per_human": per_human}
    return hc.Row(spec.name, spec.env.layout, hc.describe(spec.human), list(keys), read, hc.paper_random(spec.env.layout))
