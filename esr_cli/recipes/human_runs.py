"""Human-model artifacts: the converted human data, the BC human and the PPO human.

Two kinds in the store, each a recipe (esr_cli/storage/artifacts.py) made the first time something
needs it, like training runs:

  humandata  the 2019 trials of one layout as (observation, action) pairs from both players'
             views (data.npz), with a replay check of the conversion in the manifest
  humans     a stored human policy (params.msgpack + policy.json):
             - bc: cloned from a humandata artifact, with its accuracies and BC+BC self-play
               return in the manifest;
             - ppo: the convolutional actor-critic trained by PPO (esr_cli/recipes/ppo_humans.py).

The PPO human is esr_cli/recipes/ppo_humans.py's; esr_cli/recipes/stored_humans.py finds either kind.
"""

from __future__ import annotations

import json
from importlib import metadata
from pathlib import Path

import numpy as np
from flax import serialization
from rich.console import Console

from esr_cli.common import bounded_files
from esr_cli.model.envs.overcooked import Overcooked
from esr_cli.model.humans import bc, human_eval, overcooked_data as od
from esr_cli.recipes import play_data
from esr_cli.storage import provenance
from esr_cli.storage.artifacts import Recipe
from esr_cli.storage.store import DATA_KIND, HUMAN_KIND, PLAY_KIND, Store, StoreError, atomic_write_text, content_key

DATA_SOURCES = ("model/envs/overcooked.py", "model/humans/overcooked_data.py")
BC_SOURCES = DATA_SOURCES + ("model/humans/bc.py", "model/humans/human_eval.py", "model/networks.py")
# Played episodes become data through the environments and the two readers below, taken without
# what they import (the store's and JSON's plumbing decides which files are read, never the pairs).
PLAY_DATA_SOURCES = ("model/envs", "model/spec.py")
PLAY_DATA_READERS = ("recipes/play_data.py", "storage/play_log.py")
# Rows checked by replaying the recorded joint action when the data artifact is built.
REPLAY_SAMPLE = 1000
PARAMS_FILE, POLICY_FILE, DATA_FILE = "params.msgpack", "policy.json", "data.npz"
# What esr reads of a stored human's parameters (a convolutional actor-critic is under 1 MiB) and
# of human data (the largest layout's trials, both players' views: about 100 MiB unpacked).
MAX_PARAMS_BYTES, MAX_DATA_BYTES = 64 << 20, 2 << 30


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def data_key(layout: str) -> tuple[str, dict]:
    components = {
        "kind": "humandata",
        "layout": layout,
        "data": {"package": f"{od.PACKAGE}=={od.PACKAGE_VERSION}", "sha256": od.checksums()},
        "code": provenance.code_digest(DATA_SOURCES),
        "packages": {"jaxmarl": _version("jaxmarl")},
        "toolchain": provenance.toolchain(),
    }
    return content_key(components), components


def play_data_key(episodes: tuple[str, ...], layout: str) -> tuple[str, dict]:
    short = [k for k in episodes if len(k) != 32]
    if short:  # the same episodes must make the same key, however they were named
        raise StoreError(f"human.data: {short[0]!r} is a key prefix; a command given the spec on its command line "
                         "completes prefixes from the store, elsewhere write the whole key (`esr plays` lists them)")
    components = {
        "kind": "humandata",
        "source": "play",
        "layout": layout,
        "episodes": list(episodes),
        "code": provenance.code_digest(PLAY_DATA_SOURCES, PLAY_DATA_READERS),
        "toolchain": provenance.toolchain(),
    }
    return content_key(components), components


def human_key(human_spec, layout: str) -> tuple[str, dict]:
    part = human_spec.cloning_part(layout)
    data = play_data_key(human_spec.data, part["layout"]) if human_spec.data else data_key(part["layout"])
    components = {
        "kind": "human",
        "spec": part,
        "code": provenance.code_digest(BC_SOURCES),
        "packages": {"jaxmarl": _version("jaxmarl")},
        "toolchain": provenance.toolchain(),
        "dependencies": {DATA_KIND: data[0]},
    }
    return content_key(components), components


# ---------------------------------------------------------------- building
def data_recipe(layout: str, console: Console) -> Recipe:
    """The human data of `layout` converted to JaxMARL observations, checked by replay."""
    key, components = data_key(layout)

    def build(out: Path, store: Store) -> dict:
        with console.status(f"converting the human data of {layout} to JaxMARL observations"):
            data = od.convert(layout)
            check = od.replay_match(layout, "train", sample=REPLAY_SAMPLE)
        if check["matched"] != check["checked"]:
            raise StoreError(
                f"the human data of {layout} does not replay in JaxMARL ({check['matched']}/{check['checked']} rows; "
                f"first mismatch at row {check['first_mismatch']}): not stored"
            )
        np.savez_compressed(out / DATA_FILE, **data)
        counts = np.bincount(data["action"], minlength=6)
        return {
            "pairs": {"train": int((~data["test"]).sum()), "test": int(data["test"].sum())},
            "action_fraction": [round(float(c) / len(data["action"]), 4) for c in counts],
            "replay_check": check,
        }

    return Recipe(DATA_KIND, layout, components, build, summary_file=False)


def play_data_recipe(episodes: tuple[str, ...], layout: str, console: Console) -> Recipe:
    """Played Overcooked episodes (`play` artifacts) as the person's (observation, action) pairs."""
    key, components = play_data_key(episodes, layout)

    def played(store: Store) -> list[Path]:
        paths = []
        for episode in episodes:
            path = store.lookup(PLAY_KIND, episode)
            if path is None:
                raise StoreError(f"played episode {episode[:12]} is not in {store.root} (`esr plays` lists them)")
            paths.append(path)
        return paths

    def check(store: Store) -> None:  # before the store holds anything of this artifact or those needing it
        try:
            play_data.check(played(store), layout)
        except play_data.PlayDataError as e:
            raise StoreError(str(e)) from None

    def build(out: Path, store: Store) -> dict:
        paths = played(store)
        try:
            data = play_data.convert(paths, layout)
        except play_data.PlayDataError as e:
            raise StoreError(str(e)) from None
        np.savez_compressed(out / DATA_FILE, **data)
        counts = np.bincount(data["action"], minlength=6)
        return {
            "source": "play",
            "episodes": len(paths),
            "pairs": {"train": int((~data["test"]).sum()), "test": int(data["test"].sum())},
            "action_fraction": [round(float(c) / len(data["action"]), 4) for c in counts],
        }

    return Recipe(DATA_KIND, f"play data {layout}", components, build, check=check, summary_file=False)


def load_data(path: Path) -> dict[str, np.ndarray]:
    file = Path(path) / DATA_FILE
    try:
        return bounded_files.load_npz(file, MAX_DATA_BYTES)
    except (bounded_files.UnreadableInput, OSError) as e:
        raise StoreError(f"damaged human data: {file}: {e}") from None


def human_recipe(human_spec, layout: str, console: Console) -> Recipe:
    """The BC human of `human_spec` on `layout` (its own layout if it names one)."""
    key, components = human_key(human_spec, layout)
    layout = human_spec.layout or layout
    data = play_data_recipe(human_spec.data, layout, console) if human_spec.data else data_recipe(layout, console)

    def build(out: Path, store: Store) -> dict:
        pairs = load_data(store.lookup(DATA_KIND, data.key))
        # The split cloned from, and the one held out for its accuracy (test for a proxy human).
        train, test = (pairs["test"], ~pairs["test"]) if human_spec.split == "test" else (~pairs["test"], pairs["test"])
        if not train.any():
            raise StoreError(f"the {human_spec.split} split of this human's data is empty: nothing to clone")
        with console.status(f"cloning the human of {layout} from its {human_spec.split} split "
                            f"({int(train.sum())} pairs, {human_spec.epochs} epochs)"):
            params, losses = bc.train_bc(pairs["obs"][train], pairs["action"][train], human_spec, seed=human_spec.seed)
        logits = bc.cloned_policy(human_spec).logits
        acc_train = bc.accuracies(params, logits, pairs["obs"][train], pairs["action"][train])
        # no test split: a clone of a single played episode
        acc_test = bc.accuracies(params, logits, pairs["obs"][test], pairs["action"][test]) if test.any() else None
        env = Overcooked(layout, 400)
        with console.status(f"BC+BC self-play on {layout}: {human_spec.selfplay_episodes} episodes"):
            partners = human_eval.partner_returns(env, logits, params, human_spec.selfplay_episodes, seed=0)
        selfplay = partners["self"]
        (out / PARAMS_FILE).write_bytes(serialization.msgpack_serialize(serialization.to_state_dict(params)))
        network = {"network": "conv"} if human_spec.network == "conv" else {"hidden": list(human_spec.hidden)}
        atomic_write_text(out / POLICY_FILE, json.dumps({"layout": layout, **network, "actions": 6,
                                                          "input": "agent's own view, (H, W, 26), urgency channel zeroed"}))
        held = "no test split" if acc_test is None else \
            f"test accuracy {acc_test['accuracy']:.3f}, non-stay {acc_test['non_stay_accuracy']:.3f}"
        console.print(f"BC human {key[:12]} ({layout}): {held}; BC+BC self-play {selfplay['mean']:.1f} "
                      f"+- {selfplay['se']:.1f}, with a uniform random partner {partners['random']['mean']:.1f}")
        return {
            "layout": layout,
            "split": human_spec.split,
            "train": acc_train,  # on the split it was cloned from
            "test": acc_test,  # on the other one
            "selfplay_return": {**selfplay, "episode_steps": 400},
            "partner_returns": partners,  # with a uniform random partner, one that only stays, and itself
            "final_train_loss": round(losses[-1], 5),
            # what `esr ls` shows in its return column for this artifact
            "return": {"mean": selfplay["mean"], "of": "BC+BC self-play"},
        }

    return Recipe(HUMAN_KIND, f"bc_{layout}", components, build, requires=(data,), summary_file=False)


def load_params(path: Path):
    file = Path(path) / PARAMS_FILE
    try:
        return serialization.msgpack_restore(bounded_files.read_bytes(file, MAX_PARAMS_BYTES))
    except (bounded_files.UnreadableInput, OSError) as e:
        raise StoreError(f"damaged human: {file}: {e}") from None
