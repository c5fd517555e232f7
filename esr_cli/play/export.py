"""Played episodes back as data: JaxMARL states from the log, and Overcooked episodes as the
2019 human trials that overcooked-ai 1.1.0 ships (`clean_train_trials.pickle`).

The frame has the trials' 23 columns, in their order and with their dtypes (`COLUMNS`,
`DTYPES`): one row per step, its state and next state as Python-literal strings of
overcooked-ai's legacy state dicts ({'players': [...], 'objects': {'x,y': ...}, 'order_list':
['onion'], 'pot_explosion': False}, a soup as {'name': 'soup', 'position': [x, y], 'state':
['onion', n, tick]}), the joint action as [[dx, dy] | 'INTERACT', ...], and the game's
bookkeeping. overcooked-ai reads such a state with `OvercookedGridworld.from_grid` (the
`layout` column, which configures its recipes) and `OvercookedState.from_dict` once the
objects are given as a list (`SoupState.from_dict` reads the legacy soup); tested, like the
bundled trials. What esr cannot know (the 2019 game server's points, leader, run) is written
as docs/play.md says; who played which seat, the robot and the play keys, which the trials'
columns have no place for, travel in the pickled frame's `attrs["esr"]`.

`state_from_jaxmarl` inverts `humans.overcooked_data.to_jaxmarl`, so the exported rows convert
back to the same JaxMARL states (tested), and esr's own BC cloning reads them like the trials.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from esr_cli.model import spec as spec_model
from esr_cli.model.envs import make_env
from esr_cli.model.envs.overcooked import INTERACT, STAY, Overcooked
from esr_cli.model.humans import overcooked_data as od
from esr_cli.storage.play_log import read_header, read_states, read_steps, reading_episode
from esr_cli.storage.store import PLAY_KIND

NAME = {od.ONION: "onion", od.PLATE: "dish", od.DISH: "soup"}  # JaxMARL object -> overcooked-ai name
ORIENTATION = {v: list(k) for k, v in od.ORIENTATION.items()}
ACTION = {v: list(k) for k, v in od.ACTION.items()}
COOKED = ["onion", 3, 20]  # a plated soup's legacy state: JaxMARL's dish keeps no cooking tick
POINTS_PER_SOUP, REWARD_NORM_PER_SOUP = 5.0, 20.0  # the 2019 game's points; reward_norm's scale (JaxMARL's reward)
# The columns of the 2019 trials, in their order, with their dtypes (pandas names).
DTYPES = {
    "Unnamed: 0": "int64", "Unnamed: 0.1": "int64", "cur_gameloop": "float64", "datetime": "float64",
    "is_leader": "bool", "joint_action": "object", "layout": "object", "layout_name": "object",
    "next_state": "object", "reward": "float64", "round_num": "float64", "round_type": "object",
    "score": "float64", "state": "object", "time_elapsed": "float64", "time_left": "float64",
    "is_wait": "bool", "completed": "bool", "run": "object", "workerid_num": "int64",
    "reward_norm": "float64", "cur_gameloop_total": "int64", "reward_norm_total": "float64",
}
COLUMNS = tuple(DTYPES)


def state_from_jaxmarl(env: Overcooked, state) -> dict:
    """An overcooked-ai state dict in the 2019 trials' legacy schema from one JaxMARL state."""
    maze = np.asarray(state.maze_map)
    pad = (maze.shape[0] - env.height) // 2
    grid = maze[pad : pad + env.height, pad : pad + env.width]
    pots = {(int(x), int(y)) for x, y in np.asarray(state.pot_pos)}

    def thing(obj: int, x: int, y: int) -> dict:
        return {"name": NAME[obj], "position": [x, y], **({"state": list(COOKED)} if obj == od.DISH else {})}

    objects = {}
    for y in range(env.height):
        for x in range(env.width):
            obj, _, status = (int(v) for v in grid[y, x])
            if (x, y) in pots:
                if status >= 23 or status < 0:
                    continue  # an empty pot
                onions, tick = (23 - status, 0) if status > 20 else (3, 20 - status)
                objects[f"{x},{y}"] = {"name": "soup", "position": [x, y], "state": ["onion", onions, tick]}
            elif obj in NAME:
                objects[f"{x},{y}"] = thing(obj, x, y)
    players = []
    for j in range(2):
        x, y = (int(v) for v in np.asarray(state.agent_pos)[j])
        player = {"position": [x, y], "orientation": ORIENTATION[int(np.asarray(state.agent_dir_idx)[j])]}
        held = int(np.asarray(state.agent_inv)[j])
        if held in NAME:
            player["held_object"] = thing(held, x, y)
        players.append(player)
    return {"players": players, "objects": objects, "order_list": ["onion"], "pot_explosion": False}


def action_text(action: int):
    return "INTERACT" if action == INTERACT else ACTION[action]


def layout_rows(env: Overcooked) -> list[str]:
    """The layout as overcooked-ai's grid strings (X wall, O onions, D dishes, P pot, S serving)."""
    base = env.base.layout  # JaxMARL's layout: flat cell indices by kind
    cells = [[" "] * env.width for _ in range(env.height)]
    for key, char in (("wall_idx", "X"), ("onion_pile_idx", "O"), ("plate_pile_idx", "D"), ("pot_idx", "P"),
                      ("goal_idx", "S")):
        for i in np.asarray(base[key]).tolist():
            cells[i // env.width][i % env.width] = char
    for n, i in enumerate(np.asarray(base["agent_idx"]).tolist(), 1):
        cells[i // env.width][i % env.width] = str(n)
    return ["".join(row) for row in cells]


def trajectory_rows(path: Path, env: Overcooked, worker: int) -> list[dict]:
    """The rows of one played Overcooked episode (a `play` artifact directory); `worker`: its
    participant's workerid_num. The frame-wide row numbers ("Unnamed: 0", "Unnamed: 0.1") are
    set by `frame_of`."""
    header, steps, states = read_header(path), read_steps(path), read_states(path, env)
    fps = header.get("fps") or 1.0
    started = header.get("started_at", 0.0)
    steps = steps[: len(states) - 1]
    completed = len(steps) == env.episode_steps
    reward_norm = [float(s["reward"]) for s in steps]  # JaxMARL's reward: 20 per soup, reward_norm's scale
    layout = repr(layout_rows(env))
    texts = [repr(state_from_jaxmarl(env, s)) for s in states[: len(steps) + 1]]  # the states, then the last next one
    rows = []
    for t, step in enumerate(steps):
        joint = [step["robot_action"], step["human_action"]][:: 1 if env.robot_seat == 0 else -1]
        rows.append({
            "cur_gameloop": t, "datetime": step["wall_time"] * 1000.0, "is_leader": True,
            "joint_action": repr([action_text(a) for a in joint]), "layout": layout,
            "layout_name": od.DATA_LAYOUT[env.layout], "next_state": texts[t + 1],
            "reward": reward_norm[t] * POINTS_PER_SOUP / REWARD_NORM_PER_SOUP, "round_num": header["episode"],
            "round_type": "practice" if header.get("practice") else "main",
            "score": float(step["score"]) * POINTS_PER_SOUP / REWARD_NORM_PER_SOUP,
            "state": texts[t], "time_elapsed": round(step["wall_time"] - started, 3),
            "time_left": round((env.episode_steps - t - 1) / fps, 3), "is_wait": joint == [STAY, STAY],
            "completed": completed, "run": header["session"], "workerid_num": worker, "reward_norm": reward_norm[t],
            "cur_gameloop_total": len(steps), "reward_norm_total": sum(reward_norm),
        })
    return rows


def frame_of(episodes: list[tuple[Path, Overcooked]], keys: list[str] | None = None):
    """Played Overcooked episodes ((artifact directory, the env it was played on), ...) as one
    DataFrame of the 2019 trials' columns and dtypes. The participants are numbered 1, 2, ...
    in the order of their ids (workerid_num); `attrs["esr"]` maps each episode back."""
    import pandas as pd  # pandas: only where a DataFrame is made (docs/extending.md)

    headers = [read_header(p) for p, _ in episodes]
    workers = {pid: n for n, pid in enumerate(sorted({h["participant"] for h in headers}), 1)}
    rows, attrs = [], []
    for i, ((path, env), header) in enumerate(zip(episodes, headers)):
        with reading_episode(path):
            part = trajectory_rows(path, env, workers[header["participant"]])
        attrs.append({"play_key": keys[i] if keys else Path(path).name, "first_row": len(rows), "rows": len(part),
                      "workerid_num": workers[header["participant"]], "participant": header["participant"],
                      "session": header["session"], "episode": header["episode"], "robot": header["robot"],
                      "robot_label": header.get("robot_label"), "human_player": 1 - env.robot_seat,
                      "layout": env.layout, "fps": header.get("fps"), "episode_steps": env.episode_steps})
        rows.extend(part)
    for n, row in enumerate(rows):
        row["Unnamed: 0"] = row["Unnamed: 0.1"] = n
    frame = pd.DataFrame(rows, columns=list(COLUMNS)).astype(DTYPES)
    frame.attrs["esr"] = {"episodes": attrs, "workers": {n: pid for pid, n in workers.items()}}
    return frame


def export_overcooked(store, keys: list[str]):
    """(DataFrame of the Overcooked episodes among `keys`, how many there were); each episode
    is read with the environment it was played on."""
    episodes, kept, envs = [], [], {}
    for key in keys:
        path = store.lookup(PLAY_KIND, key)
        header = read_header(path)
        if header["env"]["kind"] != "overcooked":
            continue
        with reading_episode(path):  # an environment esr would not have played is named, not dumped
            spec = spec_model.OvercookedEnvSpec.model_validate(header["env"])
        if (same := spec.model_dump_json()) not in envs:
            envs[same] = make_env(spec)  # one env per spec
        episodes.append((path, envs[same]))
        kept.append(key)
    return frame_of(episodes, kept), len(episodes)


def trajectory_frame(paths: list[Path], env: Overcooked):
    """Played Overcooked episodes, all on `env`, as one 2019-trials DataFrame."""
    return frame_of([(p, env) for p in paths])
