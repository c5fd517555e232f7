"""`esr plays --export FILE.pickle|.csv`: played Overcooked episodes as the 2019 human trials
that overcooked-ai 1.1.0 ships, read back by overcooked-ai's own code.

overcooked-ai 1.1.0 has no loader of the trials' DataFrame (its PyPI wheel ships no
human_aware_rl, and nothing in overcooked_ai_py reads pandas). What it has is the state path
that reads the trials' legacy state dicts: `OvercookedGridworld.from_grid` on the `layout`
column (which also configures the recipes a soup needs), then `OvercookedState.from_dict`,
whose `SoupState.from_dict` reads the legacy soup ({'state': [ingredient, n, tick]}). The one
step it needs besides `ast.literal_eval` is the objects as a list: the trials key them by
"x,y", from_dict iterates a list. `overcooked_state` below is exactly that; it reads the
bundled trials' states too (a sample of every layout is tested here)."""

import ast
import json

import numpy as np
import pandas as pd
import pytest
from conftest import ROOT, esr
from overcooked_ai_py.mdp.overcooked_mdp import OvercookedGridworld, OvercookedState  # gym: the test extra

from esr_cli.model.humans import overcooked_data as od

NAMES = {od.ONION: "onion", od.PLATE: "dish", od.DISH: "soup"}  # JaxMARL object -> overcooked-ai name
DIRECTION = {v: k for k, v in od.ORIENTATION.items()}  # JaxMARL direction index -> (dx, dy)


def overcooked_state(text: str) -> OvercookedState:
    """A trials' state cell -> overcooked-ai's OvercookedState, by overcooked-ai's own from_dict."""
    d = ast.literal_eval(text)
    return OvercookedState.from_dict(dict(d, objects=list(d["objects"].values())))


def overcooked_mdp(layout_cell: str) -> OvercookedGridworld:
    return OvercookedGridworld.from_grid(ast.literal_eval(layout_cell))


def overcooked_action(a):
    return tuple(a) if isinstance(a, list) else a.lower()  # 'INTERACT' -> Action.INTERACT


@pytest.fixture(scope="module")
def trials():
    return pd.read_pickle(od.verified_files()["train"])


# ---------------------------------------------------------------- the encoding
@pytest.mark.slow
def test_the_states_of_the_2019_trials_come_back_through_jaxmarl_in_their_own_encoding(trials):
    """Bundled states -> esr's reader (JaxMARL) -> the exporter give the bundled dicts back,
    soups included (a cooking tick past 20, which JaxMARL does not keep, as 20), and
    overcooked-ai's loader reads both to the same OvercookedState. random0 has every kind of
    object: onions, dishes and plated soups held and on counters, pots of 1, 2 and 3 onions."""
    import jax

    from esr_cli.model.envs.overcooked import Overcooked
    from esr_cli.play import export

    rows = trials[trials["layout_name"] == "random0"].iloc[::12]
    grid = ast.literal_eval(rows["layout"].iloc[0])
    texts = list(rows["state"])
    overcooked_mdp(rows["layout"].iloc[0])  # configures the recipes, as from any layout
    env = Overcooked("forced_coord", 400)
    batch = jax.tree.map(np.asarray, od.to_jaxmarl(env, texts))  # numpy: indexed per state below
    seen = set()
    for i, text in enumerate(texts):
        want = ast.literal_eval(text)
        for obj in [*want["objects"].values(), *(p["held_object"] for p in want["players"] if "held_object" in p)]:
            if obj["name"] == "soup":
                ingredient, n, tick = obj["state"]
                obj["state"] = [ingredient, n, min(tick, 20) if n == 3 else tick]
                seen.add(("soup", n, "pot" if grid[obj["position"][1]][obj["position"][0]] == "P" else "loose"))
            else:
                seen.add((obj["name"], 0, "loose"))
        got = export.state_from_jaxmarl(env, jax.tree.map(lambda a, i=i: a[i], batch))
        assert got == want, (i, text)
        assert overcooked_state(repr(got)) == overcooked_state(repr(want)), (i, text)
    assert {("soup", 1, "pot"), ("soup", 2, "pot"), ("soup", 3, "pot"), ("soup", 3, "loose"), ("onion", 0, "loose"),
            ("dish", 0, "loose")} <= seen, seen


@pytest.mark.slow
def test_overcooked_ais_loader_reads_every_state_of_the_bundled_trials(trials):
    """What the export is held to: the same path reads the trials' states (every 40th row of
    the train split, its states and next states, all five layouts)."""
    for layout, rows in trials.iloc[::40].groupby("layout_name"):
        assert rows["layout"].nunique() == 1
        overcooked_mdp(rows["layout"].iloc[0])
        states = [overcooked_state(t) for t in [*rows["state"], *rows["next_state"]]]
        assert all(isinstance(s, OvercookedState) and len(s.players) == 2 for s in states), layout


# ---------------------------------------------------------------- a played episode
@pytest.fixture(scope="module")
def played(tmp_path_factory):
    """A 40-step cramped-room episode where the person (agent_1) carries onions from the pile
    to the pot until it cooks, beside the random robot; -> (store, artifact path, env)."""
    from play_script import Scripted

    from esr_cli.common import specs
    from esr_cli.model.envs import make_env
    from esr_cli.play import session as ps
    from esr_cli.play.game import Robot
    from esr_cli.storage.artifacts import ensure
    from esr_cli.storage.store import Store

    store = tmp_path_factory.mktemp("store")
    spec = specs.load(ROOT / "experiments/cramped_room_random.yaml", "paper", ["env.episode_steps=40"])
    env = make_env(spec.env)
    keys = (["right", "space", "left", "up", "space", "right"] * 7)[:40]
    opponent = ps.Opponent("random", "robot A", Robot("random", env))
    built = ensure(ps.episode_recipe(spec, opponent, "p9", "s1", 0, 5, Scripted([k for key in keys for k in (key, None)]),
                                     "test", 8.0, "t", 0), Store(store))
    assert built.summary()["completed"] and built.summary()["steps"] == 40
    return store, built.path, env


def expected(env, state) -> dict:
    """What the logged JaxMARL state says, read independently of the exporter: players
    (position, orientation, held), pots (onions, JaxMARL status) and loose objects."""
    maze = np.asarray(state.maze_map)
    pad = (maze.shape[0] - env.height) // 2
    pots = {(int(x), int(y)) for x, y in np.asarray(state.pot_pos)}
    players = [(tuple(int(v) for v in np.asarray(state.agent_pos)[j]), DIRECTION[int(np.asarray(state.agent_dir_idx)[j])],
                NAMES.get(int(np.asarray(state.agent_inv)[j]))) for j in range(2)]
    pot, loose = {}, {}
    for y in range(env.height):
        for x in range(env.width):
            obj, _, status = (int(v) for v in maze[pad + y, pad + x])
            if (x, y) in pots and status < 23:
                pot[(x, y)] = (23 - status if status > 20 else 3, status)
            elif (x, y) not in pots and obj in NAMES:
                loose[(x, y)] = NAMES[obj]
    return {"players": players, "pots": pot, "loose": loose}


def described(s: OvercookedState, pots) -> dict:
    """The same, read from overcooked-ai's OvercookedState."""
    players = [(p.position, p.orientation, p.held_object.name if p.held_object else None) for p in s.players]
    pot, loose = {}, {}
    for pos, obj in s.objects.items():
        if pos in pots:
            assert obj.name == "soup"
            tick, n = obj.to_dict()["cooking_tick"], len(obj.ingredients)
            status = 20 - tick if tick >= 0 else (23 - n if n < 3 else 20)  # JaxMARL's pot status
            pot[pos] = (n, status)
        else:
            loose[pos] = obj.name
    return {"players": players, "pots": pot, "loose": loose}


@pytest.mark.slow
def test_an_overcooked_export_has_the_2019_trials_columns_and_dtypes_and_loads_in_overcooked_ai(played, trials, tmp_path):
    from esr_cli.storage.play_log import read_states

    store, path, env = played
    esr("plays", "--participant", "p9", "--export", str(tmp_path / "p9.pickle"), store=store)
    frame = pd.read_pickle(tmp_path / "p9.pickle")
    # The trials' columns, in their order, with their dtypes.
    assert list(frame.columns) == list(trials.columns)
    assert frame.dtypes.equals(trials.dtypes), pd.concat({"export": frame.dtypes, "2019": trials.dtypes}, axis=1)
    assert len(frame) == 40 and list(frame["cur_gameloop"]) == list(range(40))
    assert list(frame["Unnamed: 0"]) == list(frame["Unnamed: 0.1"]) == list(range(40))
    assert (frame["workerid_num"] == 1).all() and (frame["run"] == "s1").all() and (frame["round_num"] == 0).all()
    assert (frame["cur_gameloop_total"] == 40).all() and frame["is_leader"].all() and frame["completed"].all()
    assert (frame["reward_norm"] == 4 * frame["reward"]).all() and (frame["score"] == frame["reward"].cumsum()).all()
    assert (frame["reward_norm_total"] == frame["reward_norm"].sum()).all()
    assert list(frame["is_wait"]) == [j == "[[0, 0], [0, 0]]" for j in frame["joint_action"]]
    # The state cells in the trials' own encoding: the same keys, objects keyed by "x,y".
    cell = ast.literal_eval(frame["state"].iloc[0])
    assert sorted(cell) == sorted(ast.literal_eval(trials["state"].iloc[0])) == ["objects", "order_list", "players", "pot_explosion"]
    assert all(k == "{},{}".format(*o["position"]) for t in frame["state"] for k, o in ast.literal_eval(t)["objects"].items())
    # What the schema has no place for travels in the pickle's attrs.
    (meta,) = frame.attrs["esr"]["episodes"]
    assert meta["participant"] == "p9" and meta["human_player"] == 1 and meta["robot"] == "random"
    assert meta["play_key"] == path.name and frame.attrs["esr"]["workers"] == {1: "p9"}

    # overcooked-ai's own loader: the layout cell -> its mdp, each state cell -> OvercookedState,
    # agreeing with the logged JaxMARL states at every step.
    mdp = overcooked_mdp(frame["layout"].iloc[0])
    logged = [expected(env, s) for s in read_states(path, env)]
    pots = {(int(x), int(y)) for x, y in np.asarray(read_states(path, env)[0].pot_pos)}
    states = [overcooked_state(t) for t in frame["state"]]
    nexts = [overcooked_state(t) for t in frame["next_state"]]
    for t in range(40):
        assert described(states[t], pots) == logged[t], t
        assert described(nexts[t], pots) == logged[t + 1], t
    held = {name for e in logged for _, _, name in e["players"]}
    onions = {n for e in logged for n, _ in e["pots"].values()}
    assert {"onion", "dish"} <= held and {1, 2, 3} <= onions, (held, onions)  # the episode shows what is checked

    # overcooked-ai's own dynamics step each state with its joint action to the next one, but
    # for one difference of game version that the 2019 trials share: overcooked-ai 1.1.0
    # waits for an INTERACT to cook a full pot, the 2019 game and JaxMARL start it at once.
    actions = [tuple(overcooked_action(a) for a in ast.literal_eval(j)) for j in frame["joint_action"]]
    differ = []
    for t in range(40):
        stepped, _ = mdp.get_state_transition(states[t], actions[t])
        assert stepped.players == nexts[t].players, t
        if stepped.objects != nexts[t].objects:
            differ.append(t)

    def full(e, pos):
        return e["pots"].get(pos, (0, 23))[0] == 3

    starts = [t for t in range(40) if any(full(logged[t + 1], p) and not full(logged[t], p) for p in pots)]
    assert differ == starts and starts, (differ, starts)

    # The CSV: the same columns, and what pandas reads back has the trials' numeric and bool dtypes.
    esr("plays", "--participant", "p9", "--export", str(tmp_path / "p9.csv"), store=store)
    again = pd.read_csv(tmp_path / "p9.csv")
    assert list(again.columns) == list(trials.columns)
    numeric = [c for c in trials.columns if trials[c].dtype != object]
    assert again[numeric].dtypes.equals(trials[numeric].dtypes)
    assert list(again["state"]) == list(frame["state"])
    json.dumps(frame.attrs)  # plain data
