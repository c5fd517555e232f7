"""Played episodes summed up for a study's analysis: per robot over participants (`esr plays
--by-robot`), one row per episode for analysis elsewhere (`esr plays --csv`), and a study
file's sessions per robot with their questionnaires (`esr plays --study`).

A participant is the unit: each participant's completed episodes with a robot are averaged
first, then the table gives the mean ± SE and the interquartile mean with its bootstrap
interval across participants (esr_cli.common.stats), as a study's analysis would. Episodes a person
ended early are counted but never scored, and practice episodes are left out.
"""

from __future__ import annotations

import csv
import io
import unicodedata
from collections import defaultdict

from esr_cli.common.stats import describe

# One row per played episode (`--csv`), in this order.
EPISODE_FIELDS = ("key", "participant", "session", "episode", "robot", "robot_label", "env", "completed", "steps",
                  "return", "success", "keys", "dropped_keys", "reaction_s_mean", "front_end", "study", "study_robot",
                  "practice")


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
                     "front_end": header.get("front_end"), "study": header.get("study"),
                     "study_robot": header.get("study_robot"), "practice": bool(header.get("practice"))})
    return rows


# A text cell that begins with one of these is read as a formula by spreadsheet programs; a
# participant's free text must open as the text it is, so such a cell gets a leading quote.
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


# Characters a terminal or a spreadsheet acts on rather than shows: controls (escape sequences,
# a bell, a carriage return that overwrites the line), format characters (bidirectional marks
# and overrides that reorder it, zero-width and tag characters that hide text) and line or
# paragraph separators. They are written as their \u escapes (\U for those past U+FFFF); a
# newline and a tab are text a free answer may hold.
UNSHOWN_CATEGORIES = ("Cc", "Cf", "Zl", "Zp")
KEPT = "\n\t"


def _escaped(ch: str) -> str:
    if ch in KEPT or unicodedata.category(ch) not in UNSHOWN_CATEGORIES:
        return ch
    return f"\\u{ord(ch):04x}" if ord(ch) <= 0xFFFF else f"\\U{ord(ch):08x}"


def as_text(value):
    """`value` as a spreadsheet shows it: characters that act rather than show as their escapes,
    and a text that would be read as a formula with a leading quote."""
    if not isinstance(value, str):
        return value
    if not value.isprintable():  # (every character UNSHOWN_CATEGORIES names is unprintable)
        value = "".join(map(_escaped, value))
    return "'" + value if value.startswith(FORMULA_STARTS) else value


def _as_text(row: dict) -> dict:
    return {k: as_text(v) for k, v in row.items()}


def frame_as_text(frame):
    """A table (pandas) whose every text cell is `as_text`'s, for a CSV a spreadsheet opens."""
    frame = frame.copy()
    for column in frame.columns:
        if frame[column].dtype == object or str(frame[column].dtype) in ("string", "str"):
            frame[column] = frame[column].map(as_text)
    return frame


def episodes_csv(rows: list[dict]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=EPISODE_FIELDS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(_as_text(r) for r in rows)
    return buffer.getvalue()


def by_robot(rows: list[dict]) -> list[dict]:
    """One entry per (robot, environment): participants, episodes played and completed, and the
    return and success rate of completed episodes, per participant first, then described across
    participants."""
    groups: dict[tuple, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        if not row["practice"]:
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


# ---------------------------------------------------------------- a study file's sessions
def _per_participant(values: dict[str, list[float]]) -> dict:
    """Each participant's values averaged, then described across participants."""
    return describe([sum(v) / len(v) for v in values.values() if v])


def study_items(records: list[dict]) -> list[dict]:
    """The questionnaire's items, as the latest questionnaire recorded them."""
    asked = [r for r in records if r.get("record") == "questionnaire"]
    return list(asked[-1]["items"]) if asked else []


def study_table(rows: list[dict], records: list[dict]) -> list[dict]:
    """One entry per robot of the study (its label in the study file): participants, episodes,
    return and success of completed episodes, and each questionnaire item (a Likert item
    described across participants, a text item's answers counted), practice left out."""
    rows = [r for r in rows if not r["practice"]]
    asked = [r for r in records if r.get("record") == "questionnaire"]
    out = []
    for label in sorted({r["study_robot"] for r in rows} | {a["study_robot"] for a in asked}):
        played = [r for r in rows if r["study_robot"] == label]
        done = defaultdict(list)
        for r in played:
            if r["completed"]:
                done[r["participant"]].append(r)
        entry = {"robot": label, "runs": sorted({str(r["robot"]) for r in played}),
                 "participants": len({r["participant"] for r in played}), "episodes": len(played),
                 "completed": sum(r["completed"] for r in played),
                 "return": _per_participant({p: [r["return"] for r in eps] for p, eps in done.items()}),
                 "success": _per_participant({p: [float(bool(r["success"])) for r in eps] for p, eps in done.items()})}
        mine = [a for a in asked if a["study_robot"] == label]
        for item in study_items(records):
            given = [(a["participant"], a["answers"].get(item["id"])) for a in mine if a["answers"].get(item["id"]) is not None]
            if item["kind"] == "likert":
                values = defaultdict(list)
                for participant, value in given:
                    values[participant].append(float(value))
                entry[item["id"]] = _per_participant(values)
            else:
                entry[item["id"]] = {"answers": len(given)}
        out.append(entry)
    return out


SUMMARY_COLUMNS = ("mean", "se", "iqm", "iqm_low", "iqm_high")


def study_csv(table: list[dict], items: list[dict]) -> str:
    """The study's table, one row per robot; a described measure as its mean, SE, IQM and
    interval and the participants it counts, a text item as its number of answers."""
    measures = ["return", "success", *(i["id"] for i in items if i["kind"] == "likert")]
    texts = [i["id"] for i in items if i["kind"] != "likert"]
    fields = ["robot", "runs", "participants", "episodes", "completed",
              *(f"{m}_{c}" for m in measures for c in (*SUMMARY_COLUMNS, "participants")), *(f"{t}_answers" for t in texts)]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for entry in table:
        row = {k: entry[k] for k in ("robot", "participants", "episodes", "completed")} | {"runs": " ".join(entry["runs"])}
        for m in measures:
            d = entry.get(m, {})
            row |= {f"{m}_{c}": d.get(c) for c in SUMMARY_COLUMNS} | {f"{m}_participants": d.get("seeds", 0) - d.get("missing", 0)}
        row |= {f"{t}_answers": entry.get(t, {}).get("answers", 0) for t in texts}
        writer.writerow(_as_text(row))
    return buffer.getvalue()


ANSWER_FIELDS = ("study", "participant", "session", "block", "robot", "run", "robot_label", "item", "kind", "value")


def answers_csv(records: list[dict]) -> str:
    """Every answer, free text included, one row each (the terminal never shows free text)."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=ANSWER_FIELDS, lineterminator="\n")
    writer.writeheader()
    for r in records:
        if r.get("record") != "questionnaire":
            continue
        kinds = {i["id"]: i["kind"] for i in r["items"]}
        for item, value in r["answers"].items():
            writer.writerow(_as_text({"study": r["study"], "participant": r["participant"], "session": r["session"],
                                      "block": r["block"], "robot": r["study_robot"], "run": r["robot"],
                                      "robot_label": r["robot_label"], "item": item, "kind": kinds.get(item), "value": value}))
    return buffer.getvalue()


def study_sessions(rows: list[dict], records: list[dict]) -> list[dict]:
    """One entry per session: its participant, consent, episodes played (practice apart),
    questionnaires answered, and its completion code once it finished."""
    sessions: dict[tuple, dict] = {}

    def entry(participant, session):
        return sessions.setdefault((participant, session), {"participant": participant, "session": session,
                                                            "consent": "given", "practice": 0, "episodes": 0,
                                                            "completed": 0, "questionnaires": 0, "code": None})

    for r in rows:
        e = entry(r["participant"], r["session"])
        e["practice" if r["practice"] else "episodes"] += 1
        e["completed"] += bool(r["completed"]) and not r["practice"]
    for r in records:
        e = entry(r["participant"], r["session"])
        if r["record"] == "consent declined":
            e["consent"] = "declined"
        elif r["record"] == "questionnaire":
            e["questionnaires"] += 1
        elif r["record"] == "completion":
            e["code"] = r["code"]
    return sorted(sessions.values(), key=lambda e: (str(e["session"]), str(e["participant"])))
