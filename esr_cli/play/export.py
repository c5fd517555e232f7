"""Played episodes back as data: JaxMARL states from the log, and Overcooked episodes in the
overcooked-ai trajectory schema.

The schema is that of overcooked-ai's human-data DataFrames (the 2019 trials that esr clones
its BC human from): one row per step with the state and next state as Python-literal strings
of overcooked-ai state dicts, the joint action as [[dx, dy] | 'INTERACT', ...], reward,
score, time_left / time_elapsed (seconds), cur_gameloop (the step), layout (the grid as
strings), layout_name, round_num, workerid_num, run, and which player is the person
(player_0_is_human / player_1_is_human, with their ids). `state_from_jaxmarl` inverts
`humans.overcooked_data.to_jaxmarl`, so the exported rows convert back to the same JaxMARL
states (tested), and esr's own BC cloning reads them like the 2019 trials.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from esr_cli.model import spec as spec_model
from esr_cli.model.envs import make_env
from esr_cli.model.envs.overcooked import INTERACT, Overcooked
from esr_cli.model.humans import overcooked_data as od
from esr_cli.storage.play_log import read_header, read_states, read_steps
from esr_cli.storage.store import PLAY_KIND

NAME = {od.ONION: "onion", od.PLATE: "dish", od.DISH: "soup"}  # JaxMARL object -> overcooked-ai name
ORIENTATION = {v: list(k) for k, v in od.ORIENTATION.items()}
ACTION = {v: list(k) for k, v in od.ACTION.items()}
COLUMNS = ("state", "joint_action", "next_state", "reward", "score", "time_left", "time_elapsed", "cur_gameloop",
           "layout", "layout_name", "round_num", "round_type", "workerid_num", "run", "is_wait", "completed",
           "player_0_id", "player_1_id", "player_0_is_human", "player_1_is_human", "datetime")


def state_from_jaxmarl(env: Overcooked, state) -> dict:
    """An overcooked-ai state dict (players, objects) from one JaxMARL state."""
    maze = np.asarray(state.maze_map)
    pad = (maze.shape[0] - env.height) // 2
    grid = maze[pad : pad + env.height, pad : pad + env.width]
    pots = {(int(x), int(y)) for x, y in np.asarray(state.pot_pos)}
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
                objects[f"{x},{y}"] = {"name": NAME[obj], "position": [x, y]}
    players = []
    for j in range(2):
        x, y = (int(v) for v in np.asarray(state.agent_pos)[j])
        player = {"position": [x, y], "orientation": ORIENTATION[int(np.asarray(state.agent_dir_idx)[j])]}
        held = int(np.asarray(state.agent_inv)[j])
        if held in NAME:
            player["held_object"] = {"name": NAME[held], "position": [x, y]}
        players.append(player)
    return {"players": players, "objects": objects, "order_list": None}


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


def trajectory_rows(path: Path, env: Overcooked) -> list[dict]:
    """The rows of one played Overcooked episode (a `play` artifact directory)."""
    header, steps, states = read_header(path), read_steps(path), read_states(path, env)
    human_seat = 1 - env.robot_seat
    fps = header.get("fps") or 1.0
    started = header.get("started_at", 0.0)
    rows = []
    for t, step in enumerate(steps[: len(states) - 1]):
        joint = [step["robot_action"], step["human_action"]] if human_seat == 1 else [step["human_action"], step["robot_action"]]
        ids = {human_seat: header["participant"], 1 - human_seat: f"robot:{header['robot']}"}
        rows.append({
            "state": repr(state_from_jaxmarl(env, states[t])),
            "joint_action": repr([action_text(a) for a in joint]),
            "next_state": repr(state_from_jaxmarl(env, states[t + 1])),
            "reward": step["reward"], "score": step["score"],
            "time_left": round((env.episode_steps - t - 1) / fps, 3), "time_elapsed": round(step["wall_time"] - started, 3),
            "cur_gameloop": t, "layout": repr(layout_rows(env)), "layout_name": od.DATA_LAYOUT[env.layout],
            "round_num": header["episode"], "round_type": "main", "workerid_num": header["participant"],
            "run": header["session"], "is_wait": False, "completed": len(steps) == env.episode_steps,
            "player_0_id": ids[0], "player_1_id": ids[1],
            "player_0_is_human": human_seat == 0, "player_1_is_human": human_seat == 1,
            "datetime": round(step["wall_time"] * 1000.0),
        })
    return rows


def export_overcooked(store, keys: list[str]):
    """(DataFrame of the Overcooked episodes among `keys`, how many there were); each episode
    is read with the environment it was played on."""
    import pandas as pd  # pandas: only where a DataFrame is made

    frames, count = [], 0
    for key in keys:
        path = store.lookup(PLAY_KIND, key)
        header = read_header(path)
        if header["env"]["kind"] != "overcooked":
            continue
        env = make_env(spec_model.OvercookedEnvSpec.model_validate(header["env"]))
        frames.append(trajectory_frame([path], env))
        count += 1
    return (pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=list(COLUMNS))), count


def trajectory_frame(paths: list[Path], env: Overcooked):
    """Played Overcooked episodes as one overcooked-ai human-data DataFrame."""
    import pandas as pd  # pandas: only where a DataFrame is made (docs/extending.md)

    rows = [row for p in paths for row in trajectory_rows(p, env)]
    return pd.DataFrame(rows, columns=list(COLUMNS))
