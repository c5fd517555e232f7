"""A study session (`esr play --study`): participant id, consent, instructions, practice
episodes, then for each robot its episodes and its questionnaire, then the end page with the
completion code (docs/play.md).

Episodes are `play` artifacts as in any session, their headers marked with the study, the
robot's label in the study file, the block and whether they are practice. What the person
answers is stored the same way, through the artifact layer: one `play` artifact per record
(a questionnaire per robot block, a declined consent, the completion), holding `record.json`
and no episode, so that the store keeps a session's episodes and answers side by side.
"""

from __future__ import annotations

import json
import math
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from esr_cli.common.jsonl import JsonInputError, read_json
from esr_cli.model.envs import make_env
from esr_cli.play import pages
from esr_cli.play.game import RANDOM_ROBOT, Robot, SessionEnded
from esr_cli.play.session import Opponent, episode_recipe, latin_square, load_opponents, new_session_id, participant_number, played_episodes, robot_labels
from esr_cli.play.study import ITEM_MODELS, Study
from esr_cli.storage.artifacts import Recipe, ensure
from esr_cli.storage.play_log import MAX_RECORD_BYTES
from esr_cli.storage.store import PLAY_KIND, Store, StoreError, atomic_write_text

RECORD_FILE = "record.json"
STUDY_RECORD = "study"  # the `kind` in a record's key components (an episode's is "play")
PRACTICE_LABEL = "practice robot"


class RobotError(StoreError):
    """A study's robot that cannot be loaded, named by its place in the study file."""


# ---------------------------------------------------------------- the robots
@dataclass
class StudyRobot:
    label: str  # the study file's name for it, never shown to the participant
    opponent: Opponent  # its run and the neutral name the participant sees


def load_robots(study: Study, store: Store) -> list[StudyRobot]:
    """Every robot of the study, loaded before anyone plays; all must share the study's environment."""
    robots = []
    for i, entry in enumerate(study.model.robots):
        refs = [] if entry.run == RANDOM_ROBOT else [entry.run]
        try:
            _, opponents = load_opponents(str(study.environment), refs or [RANDOM_ROBOT], study.model.budget, study.sets,
                                          study.model.seed_index, store, "anyone")
        except StoreError as e:
            raise RobotError(f"{study.path}: robots[{i}].run: {e}") from None
        robots.append(StudyRobot(entry.label, opponents[0]))
    return robots


def block_order(study: Study, participant: str) -> list[int]:
    """The robots' order for this participant: a row of the balanced Latin square (the session
    code's counterbalancing), or the file's order."""
    n = len(study.model.robots)
    if study.model.order == "fixed":
        return list(range(n))
    rows = latin_square(n)
    return rows[participant_number(participant) % len(rows)]


# ---------------------------------------------------------------- the records
def record_recipe(study: Study, what: str, participant: str, session: str, body: dict,
                  block: int | None = None) -> Recipe:
    """A record of the session (a questionnaire, a declined consent, the completion) as an artifact."""
    components = {"kind": STUDY_RECORD, "record": what, "study": study.name, "session": session,
                  "participant": participant, **({"block": block} if block is not None else {})}

    def build(out: Path, store: Store) -> dict:
        record = {**components, "study_digest": study.digest, "recorded_at": time.time(), **body}
        atomic_write_text(out / RECORD_FILE, json.dumps(record, indent=2))
        return {"record": what, "study": study.name, "participant": participant}  # answers stay in record.json

    return Recipe(PLAY_KIND, f"{what} {participant}", components, build,
                  record={"study": study.name, "participant": participant})


def study_records(store: Store, study: str) -> list[dict]:
    """Every committed record of the study, in the order they were made."""
    found = []
    for entry in store.entries():
        components = (entry.manifest or {}).get("key_components") or {}
        if entry.kind != PLAY_KIND or entry.status != "complete" or components.get("kind") != STUDY_RECORD:
            continue
        if components.get("study") == study and (entry.path / RECORD_FILE).is_file():
            found.append(read_record(entry.path / RECORD_FILE) | {"key": entry.key})
    return sorted(found, key=lambda r: r["recorded_at"])


def read_record(file: Path) -> dict:
    """A study's record as esr writes it; StoreError naming the file where it is not: the fields
    every reader relies on, of their types, and a questionnaire's items and answers such as a
    page would have asked and accepted."""
    def damaged(what: str) -> StoreError:
        return StoreError(f"damaged study record: {file}: {what}")

    try:
        record = read_json(file, MAX_RECORD_BYTES)
    except (JsonInputError, OSError) as e:
        raise damaged(str(e)) from None
    if not isinstance(record, dict):
        raise damaged("not a JSON object")
    for name in ("record", "study", "session", "participant"):
        if not isinstance(record.get(name), str):
            raise damaged(f"no {name} of the kind esr writes")
    at = record.get("recorded_at")
    if isinstance(at, bool) or not isinstance(at, (int, float)) or not math.isfinite(at):
        raise damaged("no recorded_at of the kind esr writes")
    if record["record"] == "questionnaire":
        if not (isinstance(record.get("study_robot"), str) and isinstance(record.get("robot"), str)
                and type(record.get("block")) is int and isinstance(record.get("robot_label"), (str, type(None)))):
            raise damaged("its robot or block is not of the kind esr writes")
        items, answers = record.get("items"), record.get("answers")
        if not isinstance(items, list) or not isinstance(answers, dict):
            raise damaged("its items or answers are not of the kind esr writes")
        try:
            items = [ITEM_MODELS[item["kind"]].model_validate(item).model_dump(mode="json") for item in items]
        except (KeyError, TypeError, ValueError):  # a pydantic ValidationError is a ValueError
            raise damaged("an item esr would not ask") from None
        clean, problem = pages.check_answers(tuple(items), answers)
        if problem or set(answers) - {i["id"] for i in items} or clean != answers:
            raise damaged("answers a page would not have accepted")
    return record


def played_episodes_of(store: Store, study: str, participant: str | None = None, session: str | None = None) -> list:
    """(key, header, summary) of the study's committed episodes, practice included, in order."""
    return [f for f in played_episodes(store, participant, session) if f[1].get("study") == study]


# ---------------------------------------------------------------- the session
@dataclass
class Outcome:
    participant: str | None
    session: str
    consent: bool | None = None  # None: the person left before answering
    episodes: list[dict] = field(default_factory=list)  # summaries, with their paths
    records: list[Path] = field(default_factory=list)
    code: str | None = None
    ended_early: bool = False


def ask(front, page: pages.Page, check) -> object:
    """Show `page` until its reply passes `check` (reply -> (value, problem)); -> the value."""
    while True:
        reply = front.ask(page)
        if reply is None:
            raise SessionEnded
        value, problem = check(reply)
        if not problem:
            return value
        page = pages.with_error(page, problem)


def _participant(reply: dict) -> tuple[str | None, str]:
    return pages.check_item(pages.PARTICIPANT_ITEM, reply.get("answers", {}).get("participant"))


def _button(reply: dict) -> tuple[str, str]:
    return reply.get("button"), ""


class StudySession:
    """One participant's way through a study on one front end."""

    def __init__(self, study: Study, robots: list[StudyRobot], front, front_name: str, store: Store,
                 claim: Callable[[str], str] = lambda participant: ""):
        """`claim(id)`: why this id may not play here ("" if it may), e.g. another link's participant."""
        self.study, self.robots, self.front, self.front_name, self.store = study, robots, front, front_name, store
        self.claim = claim
        self.practice = Opponent(RANDOM_ROBOT, PRACTICE_LABEL, Robot(RANDOM_ROBOT, make_env(study.spec.env)))
        self.outcome = Outcome(None, new_session_id())
        self.played = 0

    def _participant(self, reply: dict) -> tuple[str | None, str]:
        participant, problem = _participant(reply)
        return participant, problem or self.claim(participant)

    def run(self, participant: str | None = None) -> Outcome:
        out = self.outcome
        self.front.ready()
        try:
            out.participant = participant or ask(self.front, pages.participant_page(), self._participant)
            out.consent = ask(self.front, pages.consent_page(self.study.consent), _button) == "agree"
            if not out.consent:
                self._record("consent declined", {})
                self.front.ask(pages.declined_page())
                return out
            ask(self.front, pages.instructions_page(self.study.instructions), _button)
            self._play_practice()
            for block, which in enumerate(block_order(self.study, out.participant)):
                self._play_block(block, which)
            self._finish()
        except (SessionEnded, KeyboardInterrupt):
            out.ended_early = True
        return out

    def _play_practice(self) -> None:
        n = self.study.model.practice_episodes
        for k in range(n):
            self._episode(self.practice, self.study.model.seed + k, f"practice {k + 1} of {n}",
                          {"practice": True, "study_robot": None, "block": None})

    def _play_block(self, block: int, which: int) -> None:
        m, robot = self.study.model, self.robots[which]
        letters = robot_labels(len(self.robots), self.outcome.participant)
        opponent = Opponent(robot.opponent.ref, letters[which], robot.opponent.robot)
        for j in range(m.episodes_per_robot):
            self._episode(opponent, m.seed + m.practice_episodes + j,
                          f"{opponent.label} · episode {j + 1} of {m.episodes_per_robot}",
                          {"practice": False, "study_robot": robot.label, "block": block})
        if not m.questionnaire:
            return
        items = pages.item_dicts(m.questionnaire)
        answers = ask(self.front, pages.questionnaire_page(opponent.label, items),
                      lambda reply: pages.check_answers(items, reply.get("answers", {})))
        self._record("questionnaire", {"study_robot": robot.label, "robot": opponent.ref, "robot_label": opponent.label,
                                       "items": list(items), "answers": answers}, block)

    def _episode(self, opponent: Opponent, seed: int, title: str, marks: dict) -> None:
        """One episode, its header marked with the study; an episode ended early ends the session."""
        m, out = self.study.model, self.outcome
        recipe = episode_recipe(self.study.spec, opponent, out.participant, out.session, self.played, seed, self.front,
                                self.front_name, m.fps, title, m.countdown,
                                extra={"study": self.study.name, "study_digest": self.study.digest, **marks})
        built = ensure(recipe, self.store)
        self.played += 1
        summary = built.summary() | {"path": str(built.path)}
        out.episodes.append(summary)
        if not summary["completed"]:
            raise SessionEnded

    def _finish(self) -> None:
        completion = self.study.model.completion
        self.outcome.code = completion.code or secrets.token_hex(4).upper()
        self._record("completion", {"code": self.outcome.code, "episodes": self.played})
        self.front.ask(pages.end_page(completion.text, self.outcome.code))

    def _record(self, what: str, body: dict, block: int | None = None) -> None:
        out = self.outcome
        built = ensure(record_recipe(self.study, what, out.participant or "", out.session, body, block), self.store)
        out.records.append(built.path)
