"""Played episodes summed up for a study's analysis: per robot over participants (`esr plays
--by-robot`), and one row per episode for analysis elsewhere (`esr plays --csv`).

A participant is the unit: each participant's completed episodes with a robot are averaged
first, then the table gives the mean ± SE and the interquartile mean with its bootstrap
interval across participants (esr_cli.common.stats), as a study's analysis would. Episodes a person
ended early are counted but never scored.
"""

from __future__ import annotations

import csv
import io
from collections import defaultdict

from esr_cli.common.stats import describe

# One row per played episode (`--csv`), in this order.
EPISODE_FIELDS = ("key", "participant", "session", "episode", "robot", "robot_label", "env", "completed", "steps",
                  "return", "success", "keys", "dropped_keys", "reaction_s_mean", "front_end")


def env_name(header: dict) -> str:
    env = header.get("env") or {}
    return str(env.get("layout") or env.get("kind") or "")


def episode_rows(found: list[tuple[str, dict, dict]]) -> list[dict]:
    """(key, header, summary) of played episodes (play.session.played_episodes) -> one flat row each."""
    rows = []
    for key, header, summary in found:
        rows.append({"key": key, "participant": header.get("participant"), "session": header.get("session"),
                     "episode": header.get("episode"), "robot": header.get("robot"), "robot_label": header.get("robot_label"),
                     "env": env_name(header), "completed": bool(summary.get("completed")), "steps": summary.get("steps"),
                     "return": summary.get("score"), "success": summary.get("success"), "keys": summary.get("keys"),
                     "dropped_keys": summary.get("dropped_keys"), "reaction_s_mean": summary.get("reaction_s_mean"),
                     "front_end": header.get("front_end")})
    return rows


def episodes_csv(rows: list[dict]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=EPISODE_FIELDS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()


def by_robot(rows: list[dict]) -> list[dict]:
    """One entry per (robot, environment): participants, episodes played and completed, and the
    return and success rate of completed episodes, per participant first, then described across
    participants."""
    groups: dict[tuple, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        groups[(row["robot"], row["env"])][row["participant"]].append(row)
    out = []
    for (robot, env), people in sorted(groups.items(), key=lambda g: (str(g[0][1]), str(g[0][0]))):
        done = {p: [r for r in eps if r["completed"]] for p, eps in people.items()}
        scored = {p: eps for p, eps in done.items() if eps}
        out.append({
            "robot": robot, "env": env, "participants": len(people), "scored_participants": len(scored),
            "episodes": sum(len(eps) for eps in people.values()), "completed": sum(len(eps) for eps in done.values()),
            "return": describe([sum(r["return"] for r in eps) / len(eps) for eps in scored.values()]),
            "success": describe([sum(bool(r["success"]) for r in eps) / len(eps) for eps in scored.values()]),
        })
    return out
