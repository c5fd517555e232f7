"""The stored humans (kinds bc and ppo of `human`), whichever way they are made: their keys,
recipes and parameters for a training run. A run with a stored human lists the human's key
among its key's dependencies, and its recipe requires the human's.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

from rich.console import Console

from esr_cli.recipes import human_runs, ppo_humans
from esr_cli.storage.artifacts import Recipe
from esr_cli.storage.store import HUMAN_KIND, Store, StoreError


class StoredKind(NamedTuple):
    key: Callable  # (human_spec, layout) -> (key, components)
    recipe: Callable  # (human_spec, layout, console) -> Recipe


STORED = {
    "bc": StoredKind(human_runs.human_key, human_runs.human_recipe),
    "ppo": StoredKind(ppo_humans.ppo_human_key, ppo_humans.ppo_human_recipe),
}


def stored_key(human_spec, layout: str) -> tuple[str, dict]:
    """The key (and components) of a stored human of either kind."""
    return STORED[human_spec.kind].key(human_spec, layout)


def stored_recipe(human_spec, layout: str, console: Console) -> Recipe:
    return STORED[human_spec.kind].recipe(human_spec, layout, console)


def seeded(human_spec, count: int) -> list:
    """`count` humans of `human_spec`'s recipe, seeds human.seed, +1, ..., one human each (never
    one per training seed): the humans a calibration plays."""
    base = human_spec.model_copy(update={"per_seed": False})
    return [base.model_copy(update={"seed": base.seed + i}) for i in range(count)]


def is_stored(human_spec) -> bool:
    return human_spec.kind in STORED


def dependencies(spec) -> dict:
    """Artifact keys a training run of `spec` is built from ({} when it needs none): its stored
    human's, or the list of its per-seed humans' (in seed order)."""
    if not is_stored(spec.human):
        return {}
    keys = [stored_key(h, spec.env.layout)[0] for h in spec.human.clones(spec.train.seeds)]
    return {HUMAN_KIND: keys if spec.human.per_seed else keys[0]}


def human_recipes(spec, console: Console) -> tuple[Recipe, ...]:
    """Every stored human a run of `spec` plays with (one, or one per seed); () for the others."""
    if not is_stored(spec.human):
        return ()
    return tuple(stored_recipe(h, spec.env.layout, console) for h in spec.human.clones(spec.train.seeds))


def humans_params(spec, store: Store | None):
    """The parameters `make_trainer` takes for `spec`'s stored human: one tree, or a list of one
    per seed (human.per_seed)."""
    params = [human_params(h, spec.env.layout, store) for h in spec.human.clones(spec.train.seeds)]
    return params if spec.human.per_seed else params[0]


def human_params(human_spec, layout: str, store: Store | None):
    """A committed stored human's parameters (it must have been made: see stored_recipe)."""
    key, _ = stored_key(human_spec, layout)
    what = f"{human_spec.kind.upper()} human {key[:12]} ({human_spec.layout or layout})"
    if store is None:
        raise StoreError(f"{what} is a stored artifact: this command needs the store to load it")
    path = store.lookup(HUMAN_KIND, key)
    if path is None:
        raise StoreError(f"{what} is not built in {store.root}: `esr train` or `esr human build` builds it")
    return human_runs.load_params(path)
