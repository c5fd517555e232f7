"""User studies (`esr play --study`, docs/play.md): the study file's validation, the checks of
what a page sends back, and the whole flow (participant id, consent, instructions, practice,
each robot's episodes and questionnaire, the completion code) driven as a person would, in a
pseudo-terminal and in headless Chromium, down to `esr plays --study`."""

import csv
import dataclasses
import io
import json
import os
import select
import subprocess
import sys
import threading
import time
import urllib.parse
from pathlib import Path

import pytest
from conftest import ROOT, esr, esr_env
from play_script import Scripted
from test_play import ARROW, Pty, browser, chromium, free_port, grid_keys, logged_steps, press_and_wait, refused, serve, wait_for  # noqa: F401

from esr_cli.cli.main import main
from esr_cli.play import pages, study_session as ss
from esr_cli.play.study import MAX_TEXT_FILE_BYTES, StudyError, blocks_of, load_study, participant_problem
from esr_cli.storage.store import PLAY_KIND, Store, StoreError

EXAMPLE = ROOT / "experiments" / "studies" / "grid_pilot.yaml"
CONSENT = "# Taking part\n\nYou play a grid game. <script>window.pwned = 1</script>\n\n- we keep your keys\n- and answers\n"
QUESTIONS = [{"id": "helpful", "kind": "likert", "text": "The robot helped me.", "scale": 7,
              "anchors": ["strongly disagree", "strongly agree"]},
             {"id": "comments", "kind": "text", "text": "Anything else?", "max_chars": 200}]


def study_dict(seed: int = 0, **changes) -> dict:
    """A small study on the open 5 x 5 grid (no blocks: the way to each goal is known), two
    random robots, one practice episode and one episode per robot."""
    study = {"name": "t_study", "environment": str(ROOT / "experiments" / "grid_2.yaml"),
             "set": {"env.blocks": 0, "env.start": "random"},
             "robots": [{"label": "first", "run": "random"}, {"label": "second", "run": "random"}],
             "episodes_per_robot": 1, "practice_episodes": 1, "consent": "consent.md",
             "instructions": "instructions.md", "questionnaire": QUESTIONS, "countdown": 0, "seed": seed,
             "completion": {"code": "TESTCODE1"}}
    return {**study, **changes}


def questionnaire_record(**changes) -> dict:
    """A questionnaire's record as a session writes it (study_session.record_recipe)."""
    items = [pages.item_dicts([ss.ITEM_MODELS[q["kind"]].model_validate(q)])[0] for q in QUESTIONS]
    return {"kind": "study", "record": "questionnaire", "study": "t_study", "session": "s", "participant": "p1",
            "study_digest": "d", "recorded_at": 1.5, "block": 0, "study_robot": "first", "robot": "random",
            "robot_label": "robot A", "items": items, "answers": {"helpful": 5, "comments": "fine"}, **changes}


@pytest.mark.parametrize("changes, problem", [
    ({"recorded_at": "x"}, "no recorded_at of the kind esr writes"),
    ({"recorded_at": float("inf")}, "no recorded_at of the kind esr writes"),
    ({"participant": None}, "no participant of the kind esr writes"),
    ({"study_robot": None}, "its robot or block is not of the kind esr writes"),
    ({"answers": [1, 2]}, "its items or answers are not of the kind esr writes"),
    ({"items": "xx"}, "its items or answers are not of the kind esr writes"),
    ({"items": [{"id": "helpful", "kind": "likert"}]}, "an item esr would not ask"),
    ({"answers": {"helpful": 1e308, "comments": None}}, "answers a page would not have accepted"),
    ({"answers": {"helpful": "lots", "comments": None}}, "answers a page would not have accepted"),
    ({"answers": {"helpful": 5, "comments": None, "extra": 1}}, "answers a page would not have accepted"),
])
def test_a_damaged_study_record_is_named_with_what_is_wrong(tmp_path, changes, problem):
    good = tmp_path / "good.json"
    good.write_text(json.dumps(questionnaire_record(answers={"helpful": 5, "comments": None})))
    assert ss.read_record(good)["answers"] == {"helpful": 5, "comments": None}
    bad = tmp_path / "record.json"
    bad.write_text(json.dumps(questionnaire_record(**changes)))
    with pytest.raises(StoreError) as e:
        ss.read_record(bad)
    assert str(e.value) == f"damaged study record: {bad}: {problem}"
    bad.write_text("[1, 2]")
    with pytest.raises(StoreError, match="not a JSON object"):
        ss.read_record(bad)


def write_study(folder: Path, study: dict | str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "consent.md").write_text(CONSENT)
    (folder / "instructions.md").write_text("# How to play\n\nWalk to the green goal with the arrow keys.\n")
    path = folder / "study.yaml"
    path.write_text(study if isinstance(study, str) else json.dumps(study, indent=1))  # JSON is YAML
    return path


def open_seed() -> int:
    """A study seed whose practice and robot episodes (seeds s, s + 1) start off their goal."""
    def walkable(seed):
        try:
            return bool(grid_keys(seed))
        except AssertionError:
            return False

    return next(s for s in range(50) if walkable(s) and walkable(s + 1))


# ---------------------------------------------------------------- the study file
def test_the_example_study_is_valid_and_reads_its_texts():
    study = load_study(EXAMPLE)
    assert study.name == "grid_pilot" and [r.run for r in study.model.robots] == ["random", "random"]
    assert study.spec.env.kind == "gridworld" and study.model.order == "counterbalanced"
    assert study.model.completion.generated and study.model.practice_episodes >= 1
    assert blocks_of(study.consent)[0] == ("h", "Taking part in this study") and "How to play" in study.instructions
    assert len(study.digest) == 32


def test_simple_markdown_becomes_blocks_never_markup():
    assert blocks_of("# Title\nline one\nline two\n\n- an item\n  that goes on\n* another\n\n<b>x</b>") == [
        ("h", "Title"), ("p", "line one line two"), ("li", "an item that goes on"), ("li", "another"),
        ("p", "<b>x</b>")]


def _without(d: dict, key: str) -> dict:
    return {k: v for k, v in d.items() if k != key}


MISTAKES = [
    (lambda d: {**d, "episodes_per_robto": 2}, "episodes_per_robto: unknown key; did you mean `episodes_per_robot`?"),
    (lambda d: _without(d, "consent"), "consent: missing: this key is required"),
    (lambda d: {**d, "questionnaire": [{**QUESTIONS[0], "scal": 7}]}, "questionnaire[0].scal: unknown key; did you mean `scale`?"),
    (lambda d: {**d, "questionnaire": [{**QUESTIONS[0], "anchors": ["a", "b", "c"]}]},
     "questionnaire[0]: anchors: give 2 (the ends of the scale) or 7 (one per point), not 3"),
    (lambda d: {**d, "questionnaire": [{**QUESTIONS[0], "kind": "slider"}]}, "kind 'slider' is not one of likert, text"),
    (lambda d: {**d, "questionnaire": [QUESTIONS[0], QUESTIONS[0]]}, "questionnaire: the item id 'helpful' is used twice"),
    (lambda d: {**d, "questionnaire": [{**QUESTIONS[0], "scale": 40}]}, "questionnaire[0].scale: Input should be less than or equal to 11"),
    (lambda d: {**d, "questionnaire": [{**QUESTIONS[1], "max_chars": 5000}]}, "questionnaire[0].max_chars:"),
    (lambda d: {**d, "questionnaire": [{**QUESTIONS[1], "text": "two\nlines"}]}, "questionnaire[0].text: control characters"),
    (lambda d: {**d, "robots": [{"label": "a", "run": "not-a-key"}]},
     "robots[0].run: 'not-a-key': a run's key or key prefix (4 to 32 hex digits), or random"),
    (lambda d: {**d, "robots": [{"label": "a", "run": "random"}, {"label": "a", "run": "random"}]},
     "robots: the robot label 'a' is used twice"),
    (lambda d: {**d, "robots": []}, "robots: "),
    (lambda d: {**d, "completion": {"code": "X1", "generated": True}}, "completion: give either `code: ...`"),
    (lambda d: {**d, "completion": {"code": "no spaces"}}, "completion.code: 'no spaces': a completion code is"),
    (lambda d: {**d, "budget": "huge"}, "budget: unknown budget 'huge'"),
    (lambda d: {**d, "episodes_per_robot": True}, "episodes_per_robot:"),
    (lambda d: {**d, "name": "my study"}, "name: 'my study': a name here is"),
    (lambda d: {**d, "environment": "nowhere.yaml"}, "environment: no spec file 'nowhere.yaml'"),
    (lambda d: {**d, "set": {"env.nope": 1}}, "environment: "),
    (lambda d: {**d, "consent": "../outside.md"}, "consent: '../outside.md' is outside the study file's folder"),
    (lambda d: {**d, "instructions": "/etc/passwd"}, "instructions: '/etc/passwd' is outside the study file's folder"),
    (lambda d: {**d, "consent": "missing.md"}, "consent: no file 'missing.md' in the study file's folder"),
]


@pytest.mark.parametrize("mistake,expected", MISTAKES, ids=[m[1][:40] for m in MISTAKES])
def test_each_mistake_is_one_line_naming_the_file_key_and_problem(tmp_path, mistake, expected):
    path = write_study(tmp_path / "s", mistake(study_dict()))
    (tmp_path / "outside.md").write_text("a secret")
    with pytest.raises(StudyError) as e:
        load_study(path)
    line = e.value.one_line()
    assert line.startswith(f"bad study file: {path}: ") and expected in line and "\n" not in line, line
    assert "a secret" not in line and "root:" not in line  # never what a file outside the folder holds


def test_hostile_study_files_are_refused_in_one_line(tmp_path):
    folder = tmp_path / "s"
    path = write_study(folder, study_dict())
    for text, expected in [
        ("name: x\n" + "# padding\n" * 200_000, "larger than the 262,144 bytes"),  # refused unread
        ('a: &a ["x", "x"]\nb: [*a, *a]\n', "anchors (&name) are not allowed"),  # nested aliases, never expanded
        ("- a list\n- not a study\n", "the top level must be a mapping"),
        ("name: x\nname: y\n", "key 'name' appears twice"),
    ]:
        path.write_text(text)
        with pytest.raises(StudyError) as e:
            load_study(path)
        assert expected in str(e.value) and "\n" not in str(e.value), (expected, str(e.value))
    # texts: a link out of the folder, one too large, one with an escape sequence, one not UTF-8
    write_study(folder, study_dict())
    (tmp_path / "secret").write_text("do not show")
    (folder / "link.md").symlink_to(tmp_path / "secret")
    (folder / "big.md").write_text("x" * (MAX_TEXT_FILE_BYTES + 1))
    (folder / "escape.md").write_text("fine\nnot \x1b[31mfine\n")
    (folder / "latin1.md").write_bytes("caf\xe9".encode("latin-1"))
    for name, expected in (("link.md", "is outside the study file's folder"), ("big.md", "more than the 65,536 esr reads"),
                           ("escape.md", "line 2: a control character \\x1b"), ("latin1.md", "is not UTF-8")):
        write_study(folder, study_dict(consent=name))
        with pytest.raises(StudyError) as e:
            load_study(folder / "study.yaml")
        assert f"consent: {name}" in str(e.value) or f"consent: '{name}'" in str(e.value)
        assert expected in str(e.value) and "do not show" not in str(e.value), str(e.value)


def test_the_cli_refuses_a_bad_study_in_one_line_before_any_work(tmp_path, capsys):
    store = tmp_path / "store"
    bad = write_study(tmp_path / "s", {**study_dict(), "robots": [{"label": "a", "rn": "random"}]})
    good = write_study(tmp_path / "g", study_dict())
    for args, expected in [
        (["play", "--study", str(bad)], f"bad study file: {bad}: robots[0].rn: unknown key; did you mean `run`?"),
        (["play", "--study", str(good), "--robots", "random"], "--robots: the study file sets this"),
        (["play", "--study", str(good), "--episodes", "3"], "--episodes: the study file sets this"),
        (["play", "--study", str(good), "experiments/grid_2.yaml"], "--study: the study file names the environment"),
        (["play", "--study", str(good), "--participant", "bad id!"], "--participant: a participant id is 1 to 64"),
        (["play", "experiments/grid_2.yaml", "--participant", "bad id!"], "--participant: a participant id is 1 to 64"),
        (["play"], "name a trained run or a spec (or give --study STUDY.yaml)"),
        (["plays", "--study", "no such/study"], "--study: a study's name"),
        (["plays", "--answers", str(tmp_path / "a.csv")], "--answers: only with --study NAME"),
        (["plays", "--study", "t_study", "--csv", str(tmp_path / "same.csv"), "--answers", str(tmp_path / "same.csv")],
         "--csv and --answers name the same file"),
        (["play", "--study", str(good), "--participants", "2"], "--participants: only with --web"),
        (["play", "experiments/grid_2.yaml", "--web", "--participants", "2"], "--participants: only with --study"),
        (["play", "--study", str(good), "--web", "--participants", "0"], "--participants: between 1 and 1,000"),
        (["play", "--study", str(good), "--web", "--participants", "2", "--participant", "a1"],
         "--participant: with --participants each person gives their own id"),
        (["play", "--study", str(good), "--web", "--links", str(tmp_path / "l.txt")], "--links: only with --participants N"),
        (["play", "--study", str(good), "--web", "--participants", "2", "--links", str(store / PLAY_KIND / "l.txt")],
         "lies inside the store's play/ folder"),
        (["play", "--study", str(good), "--host", "10.0.0.1"], "--host: only with --web"),
        (["play", "--study", str(good), "--web", "--host", "bad host!"], "--host: an IP address or a host name"),
        (["play", "--study", str(good), "--web", "--public-url", "ftp://lab.example/"], "--public-url: an http:// or https://"),
        (["play", "--study", str(good), "--web", "--public-url", "https://lab.example/?x=1"], "--public-url: an http:// or https://"),
    ]:
        capsys.readouterr()
        assert main(["--store", str(store), *args]) == 2, args
        said = capsys.readouterr().err.strip()
        assert expected in said and len(said.splitlines()) == 1, (args, said)
    assert not (store / PLAY_KIND).exists()
    # nothing played yet: an empty listing, and no file written where one is asked for
    assert main(["--store", str(store), "plays", "--study", "t_study"]) == 0
    assert "no sessions of study 't_study'" in capsys.readouterr().err
    assert main(["--store", str(store), "plays", "--study", "t_study", "--csv", str(tmp_path / "t.csv")]) == 1
    assert not (tmp_path / "t.csv").exists()


@pytest.mark.slow
def test_a_robot_the_store_lacks_is_named_by_its_place_in_the_study(tmp_path, capsys):
    path = write_study(tmp_path / "s", study_dict(robots=[{"label": "a", "run": "random"}, {"label": "b", "run": "abcd12"}]))
    assert main(["--store", str(tmp_path / "store"), "play", "--study", str(path), "--web", "--port", str(free_port())]) == 2
    said = capsys.readouterr().err.strip()
    assert f"{path}: robots[1].run: no artifact with key 'abcd12'" in said and len(said.splitlines()) == 1


def test_participant_ids_are_short_and_plain():
    assert not participant_problem("p07") and not participant_problem("5f3c2a9b8e1d4c6a7b0e9f12")
    for bad in ("", "a b", "x" * 65, "../x", "-lead", "p\n1", "ünï", "<script>"):
        assert participant_problem(bad), bad


# ---------------------------------------------------------------- replies
def test_replies_are_checked_never_trusted():
    likert, text = ({**QUESTIONS[0], "required": True}, {**QUESTIONS[1], "required": False})
    assert pages.check_answers((likert, text), {"helpful": 3, "comments": "  fine  "}) == ({"helpful": 3, "comments": "fine"}, "")
    assert pages.check_answers((likert, text), {"helpful": 7}) == ({"helpful": 7, "comments": None}, "")
    for bad in (0, 8, True, "3", 2.5, None, [1]):
        assert pages.check_answers((likert, text), {"helpful": bad})[1], bad
    assert "at most 200 characters" in pages.check_answers((likert, text), {"helpful": 1, "comments": "x" * 201})[1]
    assert pages.check_item(pages.PARTICIPANT_ITEM, "bad id")[1] and pages.check_item(pages.PARTICIPANT_ITEM, "p1") == ("p1", "")


def test_the_browser_page_replies_only_in_shape_and_a_bad_answer_is_asked_again():
    """A page's reply arrives as one message per answer, then the button; the server queues only
    well-formed ones (anything else closes the connection, as for keys), ignores replies to an
    earlier page and keys pressed on a page, and the flow asks again until the answers pass."""
    import websocket
    from rich.console import Console

    from esr_cli.play.web import Web, form_of

    assert form_of({"form": 1, "button": "submit"}).button == "submit"
    assert form_of({"form": 1, "item": "q", "value": 5}).value == 5
    for bad in ({"form": -1, "button": "x"}, {"form": 1, "item": "q", "value": True}, {"form": 1, "item": "q", "value": [1]},
                {"form": 1, "item": "q", "value": "x" * 501}, {"form": 1}, {"form": "1", "button": "x"},
                {"form": 1, "button": "x", "item": "q"}, {"form": 1, "key": "up"}):
        assert form_of(bad) is None, bad
    said = io.StringIO()
    page = pages.questionnaire_page("robot A", tuple(QUESTIONS))
    items = page.items
    with Web(free_port(), Console(file=said, width=200)) as web:
        got = {}
        flow = threading.Thread(target=lambda: got.update(answers=ss.ask(
            web, page, lambda reply: pages.check_answers(items, reply.get("answers", {})))))
        conn = websocket.create_connection(f"ws://127.0.0.1:{web.port}/ws?token={web.token}", timeout=20,
                                           origin=f"http://127.0.0.1:{web.port}")
        flow.start()
        first = json.loads(conn.recv())
        assert first["page"]["kind"] == "questionnaire" and first["page"]["error"] == ""
        form = first["form"]
        for message in ({"form": form, "item": "helpful", "value": 99}, {"key": "up", "frame": 1},
                        {"form": form - 1, "button": "submit"}, {"form": form, "item": "nope", "value": 1},
                        {"form": form, "button": "submit"}):
            conn.send(json.dumps(message))
        again = json.loads(conn.recv())
        assert again["form"] == form + 1 and "choose a number from 1 to 7" in again["page"]["error"]
        for message in ({"form": form + 1, "item": "helpful", "value": 4}, {"form": form + 1, "item": "comments", "value": "ok"},
                        {"form": form + 1, "button": "submit"}):
            conn.send(json.dumps(message))
        flow.join(timeout=20)
        assert got["answers"] == {"helpful": 4, "comments": "ok"}
        conn.send(json.dumps({"form": form + 1, "answer": "not a reply"}))  # any other object ends the connection
        from esr_cli.play.game import CLOSED

        assert web.key(timeout=10).name == CLOSED
        conn.close()
    assert "the browser sent text that is not a key; its connection is closed" in said.getvalue()


# ---------------------------------------------------------------- the flow, scripted
class Person(Scripted):
    """A scripted participant: keys for the episodes, replies for the pages in turn."""

    def __init__(self, keys, replies):
        super().__init__(keys, start=False)
        self.replies, self.pages = list(replies), []

    def ask(self, page):
        self.pages.append(page)
        return self.replies.pop(0) if page.buttons else {}


def test_declining_consent_ends_the_session_and_records_only_that(tmp_path, capsys):
    study = load_study(write_study(tmp_path / "s", study_dict()))
    store = Store(tmp_path / "store")
    person = Person([], [{"answers": {"participant": "bad id"}}, {"answers": {"participant": "d1"}}, {"button": "decline"}])
    outcome = ss.StudySession(study, ss.load_robots(study, store), person, "test", store).run()
    assert outcome.participant == "d1" and outcome.consent is False and not outcome.ended_early
    assert [p.kind for p in person.pages] == ["participant", "participant", "consent", "end"]
    assert "a participant id is" in person.pages[1].error and "only that consent was declined" in person.pages[-1].blocks[0][1]
    entries = [e for e in store.entries() if e.kind == PLAY_KIND]
    assert len(entries) == 1 and not ss.played_episodes_of(store, "t_study")
    (record,) = ss.study_records(store, "t_study")
    assert record["record"] == "consent declined" and record["participant"] == "d1" and "answers" not in record
    assert main(["--store", str(store.root), "plays", "--study", "t_study"]) == 0
    assert "declined" in capsys.readouterr().out


@pytest.mark.slow
def test_a_person_who_leaves_mid_study_keeps_what_was_played(tmp_path):
    seed = open_seed()
    study = load_study(write_study(tmp_path / "s", study_dict(seed=seed)))
    store = Store(tmp_path / "store")
    keys = ["space", *grid_keys(seed), "space", *grid_keys(seed + 1)]
    person = Person(keys, [{"button": "agree"}, {"button": "continue"}, None])  # the tab closes at the questionnaire
    outcome = ss.StudySession(study, ss.load_robots(study, store), person, "test", store).run("m1")
    assert outcome.ended_early and outcome.consent and len(outcome.episodes) == 2 and outcome.code is None
    assert [e["completed"] for e in outcome.episodes] == [True, True]
    assert not [r for r in ss.study_records(store, "t_study") if r["record"] != "consent declined"]


@pytest.mark.slow
def test_an_overcooked_study_in_a_fixed_order_exports_as_human_data(tmp_path):
    """`order: fixed` plays the robots as written for every participant (p1 and p2 stand in
    different rows of the counterbalancing); Overcooked ticks at the study's rate; the study's
    episodes, practice included, export as overcooked-ai's human data."""
    import pandas as pd

    study = load_study(write_study(tmp_path / "s", study_dict(
        environment=str(ROOT / "experiments" / "cramped_room_random.yaml"), set={"env.episode_steps": 6},
        order="fixed", fps=60, questionnaire=QUESTIONS[:1])))
    store = Store(tmp_path / "store")
    robots = ss.load_robots(study, store)
    episode = ["space", "up", *[None] * 6]  # up, taken at the first tick, then five ticks of staying
    for who in ("p1", "p2"):
        replies = [{"button": "agree"}, {"button": "continue"}, *({"answers": {"helpful": v}, "button": "submit"} for v in (4, 5))]
        person = Person(episode * 3, replies)
        outcome = ss.StudySession(study, robots, person, "test", store).run(who)
        assert outcome.code == "TESTCODE1" and [e["steps"] for e in outcome.episodes] == [6, 6, 6]
    episodes, records = stored(store.root, "t_study")
    assert [ss.block_order(study, who) for who in ("p1", "p2")] == [[0, 1], [0, 1]]
    balanced = dataclasses.replace(study, model=study.model.model_copy(update={"order": "counterbalanced"}))
    assert ss.block_order(balanced, "p1") != ss.block_order(balanced, "p2")
    for who in ("p1", "p2"):
        mine = [h for _, h, _ in episodes if h["participant"] == who]
        assert [h["study_robot"] for h in mine] == [None, "first", "second"] and mine[0]["env"]["kind"] == "overcooked"
    assert [r["study_robot"] for r in records if r["record"] == "questionnaire"] == ["first", "second"] * 2
    out = tmp_path / "trials.pickle"
    assert main(["--store", str(store.root), "plays", "--study", "t_study", "--export", str(out)]) == 0
    frame = pd.read_pickle(out)
    assert len(frame) == 2 * 3 * 6 and frame["workerid_num"].nunique() == 2
    assert frame.groupby(["workerid_num", "round_num"]).size().tolist() == [6] * 6  # an episode per round


# ---------------------------------------------------------------- the flow, as a person plays it
def wait_text(term: Pty, text: bytes, since: int, timeout: float = 240) -> int:
    """Wait until `text` is on the terminal after byte `since`; -> the byte after it."""
    deadline = time.time() + timeout
    while (at := term.screen.find(text, since)) < 0:
        assert time.time() < deadline, f"no {text!r} on the screen after {timeout} s:\n{term.screen[since:][-2000:]!r}"
        if select.select([term.fd], [], [], 0.2)[0]:
            try:
                term.screen += os.read(term.fd, 65536)
            except OSError:
                break
    return at + len(text)


def play_in_terminal(term: Pty, keys: list[str], since: int) -> int:
    """Pass the ready gate and walk to the goal (the rest of the episode plays out)."""
    wait_text(term, b"press space to start", since)
    term.press(b" ")
    for k in keys[:-1]:
        term.press(ARROW[k])
    term.send(ARROW[keys[-1]])
    return wait_text(term, b"episode over", since)


def stored(store: Path, study: str):
    """(the study's episodes as (key, header, summary), its records)."""
    return ss.played_episodes_of(Store(store), study), ss.study_records(Store(store), study)


def check_plays_study(store: Path, answers_by_block: dict, free_text: str) -> None:
    """`esr plays --study`: one row per robot with its one completed episode (the practice one
    left out), the Likert answers as means, the free text only in the --answers file."""
    proc = esr("plays", "--study", "t_study", "--csv", str(store.parent / "t.csv"), "--answers",
               str(store.parent / "a.csv"), store=store, COLUMNS="400")
    _, records = stored(store, "t_study")
    for r in (r for r in records if r["record"] == "questionnaire"):
        line = next(line for line in proc.stdout.splitlines() if line.startswith(f"│ {r['study_robot']} "))
        assert "1 of 1 completed" in line and f"{answers_by_block[r['block']]:.2f} (1 participant)" in line, line
    assert free_text not in proc.stdout and free_text not in proc.stderr
    with open(store.parent / "t.csv") as f:
        table = list(csv.DictReader(f))
    assert sorted(r["robot"] for r in table) == ["first", "second"] and all(r["episodes"] == "1" for r in table)
    with open(store.parent / "a.csv") as f:
        answers = list(csv.DictReader(f))
    assert free_text in [a["value"] for a in answers if a["item"] == "comments"]
    by_robot = esr("plays", "--by-robot", store=store, COLUMNS="400").stdout
    assert "2 of 2 completed" in by_robot  # the practice episode is kept out here too


def check_stored(store: Path, participant: str, answers_by_block: dict, free_text: str) -> dict:
    """The session as the store holds it: one practice and two robot episodes, a questionnaire
    per robot block with the answers given, and the completion; -> the completion record."""
    episodes, records = stored(store, "t_study")
    headers = [h for _, h, _ in episodes]
    assert [h["practice"] for h in headers] == [True, False, False] and all(s["completed"] for _, _, s in episodes)
    assert {h["study_robot"] for h in headers[1:]} == {"first", "second"} and headers[0]["robot_label"] == "practice robot"
    assert all(h["participant"] == participant and h["study"] == "t_study" for h in headers)
    asked = sorted((r for r in records if r["record"] == "questionnaire"), key=lambda r: r["block"])
    assert [r["answers"]["helpful"] for r in asked] == [answers_by_block[0], answers_by_block[1]]
    assert [r["answers"]["comments"] for r in asked] == [free_text, None]
    assert [r["study_robot"] for r in asked] == [h["study_robot"] for h in headers[1:]]  # each after its robot's block
    (completion,) = [r for r in records if r["record"] == "completion"]
    return completion


@pytest.mark.slow
def test_terminal_study_from_participant_id_to_completion_code(tmp_path):
    seed = open_seed()
    path = write_study(tmp_path / "s", study_dict(seed=seed))
    store = tmp_path / "store"
    term = Pty(["play", "--study", str(path)], store)
    at = wait_text(term, b"type your participant id", 0)
    term.send(b"bad id!\r")
    at = wait_text(term, b"a participant id is", at)
    term.send(b"t1\r")
    at = wait_text(term, b"press y (I agree) or n (I do not agree)", at)
    assert b"<script>window.pwned = 1</script>" in term.screen[:at]  # the consent text, as written
    term.send(b"y")
    at = wait_text(term, b"press space (Start)", at)
    term.send(b" ")
    at = play_in_terminal(term, grid_keys(seed), at)  # practice
    for block, (likert, text) in enumerate(((b"5", b"fine robot"), (b"2", b""))):
        at = play_in_terminal(term, grid_keys(seed + 1), at)
        at = wait_text(term, b"type a number from 1 to 7", at)
        term.send(b"9\r")
        at = wait_text(term, b"choose a number from 1 to 7", at)
        term.send(likert + b"\r")
        at = wait_text(term, b"type your answer", at)
        term.send(text + b"\r")
    wait_text(term, b"TESTCODE1", at)
    assert term.wait() == 0
    completion = check_stored(store, "t1", {0: 5, 1: 2}, "fine robot")
    assert completion["code"] == "TESTCODE1"
    check_plays_study(store, {0: 5, 1: 2}, "fine robot")


@pytest.mark.slow
def test_browser_study_from_participant_id_to_completion_code(browser, tmp_path):  # noqa: F811
    seed = open_seed()
    path = write_study(tmp_path / "s", study_dict(seed=seed, completion={"generated": True, "text": "Thanks!"}))
    store = tmp_path / "store"
    proc, url = serve(["--study", str(path)], store, free_port())
    by_id = lambda name: browser.find_element("id", name)  # noqa: E731
    page_is = lambda kind: wait_for(browser, f"return document.body.dataset.page === '{kind}'", timeout=240)  # noqa: E731
    # The id from the address, as a recruitment platform passes it: refused, then typed in.
    browser.get(url + "&participant=" + urllib.parse.quote("bad id!"))
    page_is("participant")
    wait_for(browser, "return document.getElementById('page-error').textContent.includes('a participant id is')")
    field = browser.find_element("css selector", "[name=participant]")
    field.clear()
    field.send_keys("w1")
    by_id("button-continue").click()
    page_is("consent")
    assert "<script>window.pwned = 1</script>" in by_id("page-body").text
    assert browser.execute_script("return window.pwned === undefined && document.querySelectorAll('#page-body li').length === 2")
    by_id("button-agree").click()
    page_is("instructions")
    by_id("button-continue").click()
    free_text = "fine <b>robot</b>"
    for keys, answers in ((grid_keys(seed), None), (grid_keys(seed + 1), ("5", free_text)), (grid_keys(seed + 1), ("2", ""))):
        wait_for(browser, "return !document.body.dataset.page && document.body.dataset.frame === '1' && "
                          "document.getElementById('message').textContent === 'press space to start'", timeout=240)
        press_and_wait(browser, "space")
        for k in keys:
            press_and_wait(browser, k)
        if answers is None:
            continue
        page_is("questionnaire")
        by_id("button-submit").click()  # nothing chosen: asked again, saying what is missing
        wait_for(browser, "return document.getElementById('page-error').textContent.includes('please answer')")
        browser.find_element("css selector", f"input[name=helpful][value='{answers[0]}']").click()
        browser.find_element("css selector", "[name=comments]").send_keys(answers[1])
        by_id("button-submit").click()
    page_is("end")
    wait_for(browser, "return document.getElementById('page-code').textContent.length === 8")
    code = by_id("page-code").text
    _, errs = proc.communicate(timeout=120)
    assert proc.returncode == 0, errs
    completion = check_stored(store, "w1", {0: 5, 1: 2}, free_text)
    assert completion["code"] == code and completion["participant"] == "w1"
    check_plays_study(store, {0: 5, 1: 2}, free_text)
    headers = [h for _, h, _ in stored(store, "t_study")[0]]
    assert all(h["front_end"] == "web" for h in headers)
    steps = logged_steps(Store(store).lookup(PLAY_KIND, stored(store, "t_study")[0][0][0]))
    assert [s["key"] for s in steps if s["key"]] == grid_keys(seed)  # the practice episode as played


def serve_links(args, store, port, links: Path):
    """`esr play --study ... --web --participants N --links FILE` started -> (the process, the links)."""
    proc = subprocess.Popen([sys.executable, "-m", "esr_cli.cli.main", "play", *args, "--web", "--port", str(port),
                             "--links", str(links)], cwd=ROOT, env=esr_env(store), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 240
    while not links.is_file() or not links.read_text().endswith("\n"):
        assert proc.poll() is None, proc.communicate()
        assert time.time() < deadline, "the study server did not start"
        time.sleep(0.2)
    return proc, links.read_text().split()


def participant_in_browser(driver, url: str, seed: int, likert: list[str]):
    """One person through the whole study in one browser, a stage per next(): the pages, the
    practice episode, each robot's episode and questionnaire, the end page."""
    page_is = lambda kind: wait_for(driver, f"return document.body.dataset.page === '{kind}'", timeout=240)  # noqa: E731
    driver.get(url)
    page_is("consent")  # the id came with the link
    yield
    driver.find_element("id", "button-agree").click()
    page_is("instructions")
    driver.find_element("id", "button-continue").click()
    for keys, answer in ((grid_keys(seed), None), (grid_keys(seed + 1), likert[0]), (grid_keys(seed + 1), likert[1])):
        wait_for(driver, "return !document.body.dataset.page && document.body.dataset.frame === '1' && "
                         "document.getElementById('message').textContent === 'press space to start'", timeout=240)
        press_and_wait(driver, "space")
        for k in keys:
            press_and_wait(driver, k)
        yield
        if answer is not None:
            page_is("questionnaire")
            driver.find_element("css selector", f"input[name=helpful][value='{answer}']").click()
            driver.find_element("id", "button-submit").click()
    page_is("end")
    wait_for(driver, "return document.getElementById('page-code').textContent.length === 8")
    yield driver.find_element("id", "page-code").text


@pytest.mark.slow
def test_two_browsers_at_once_are_two_participants_with_separate_sessions(browser, tmp_path):  # noqa: F811
    """One server, two single-use links: two people play the study side by side, each with their
    own id, robot order, episodes and answers; a used link lets nobody in again."""
    seed = open_seed()
    path = write_study(tmp_path / "s", study_dict(seed=seed, completion={"generated": True, "text": "Thanks!"}))
    store, port = tmp_path / "store", free_port()
    proc, links = serve_links(["--study", str(path), "--participants", "2"], store, port, tmp_path / "links.txt")
    assert len(links) == 2 and oct((tmp_path / "links.txt").stat().st_mode & 0o777) == "0o600"
    second = chromium()
    try:
        # p1 and p2 stand in the first and second row of the two robots' counterbalanced order.
        people = {"p1": participant_in_browser(browser, links[0] + "&participant=p1", seed, ["6", "3"]),
                  "p2": participant_in_browser(second, links[1] + "&participant=p2", seed, ["1", "7"])}
        codes = {}
        for stage in range(5):  # stage by stage, in turn: both sessions are open at once throughout
            for who, person in people.items():
                codes[who] = next(person)
            if stage == 0:
                # The first link again (another tab, or the same person back) while both sessions
                # are open: refused, its session is begun. (Checked here, not at the end: once
                # both sessions end the server stops by itself and nothing listens any more.)
                ws = links[0].replace("http://", "ws://").replace("/?token=", "/ws?token=")
                assert refused(ws, origin=f"http://127.0.0.1:{port}") == 403
    finally:
        second.quit()
    _, errs = proc.communicate(timeout=120)  # every link's session has ended: the server stops by itself
    assert proc.returncode == 0, errs
    assert "link 1 has been used" in errs and "2 of 2 link(s) used, 2 session(s) finished" in errs
    episodes, records = stored(store, "t_study")
    completions = {r["participant"]: r for r in records if r["record"] == "completion"}
    assert {who: c["code"] for who, c in completions.items()} == codes and codes["p1"] != codes["p2"]
    assert completions["p1"]["session"] != completions["p2"]["session"]
    for who, likert in (("p1", [6, 3]), ("p2", [1, 7])):
        mine = [h for _, h, _ in episodes if h["participant"] == who]
        assert [h["practice"] for h in mine] == [True, False, False]
        assert {h["session"] for h in mine} == {completions[who]["session"]}
        asked = sorted((r for r in records if r["record"] == "questionnaire" and r["participant"] == who), key=lambda r: r["block"])
        assert [r["answers"]["helpful"] for r in asked] == likert
        assert [r["study_robot"] for r in asked] == [h["study_robot"] for h in mine[1:]]
    orders = {who: [h["study_robot"] for _, h, _ in episodes if h["participant"] == who and not h["practice"]] for who in codes}
    assert sorted(orders.values()) == [["first", "second"], ["second", "first"]]  # counterbalanced per participant


def test_a_study_server_keeps_serving_when_one_session_fails_and_stops_when_every_link_has_ended(tmp_path, monkeypatch):
    """The server's bookkeeping, sessions stubbed: a session the store fails ends with one line
    and the others go on; serve() returns once every link's session has ended."""
    import websocket
    from rich.console import Console

    from esr_cli.play import study_server
    from esr_cli.storage.store import StoreError

    study = load_study(write_study(tmp_path / "s", study_dict()))

    def run(self, participant=None):  # the first link's session meets a full disk; the second finishes
        self.front.ready()
        if self.front.ask(pages.participant_page()) is None:
            raise StoreError("no space left on the device")
        return ss.Outcome("ok1", "session-2", consent=True, code="CODE")

    monkeypatch.setattr(ss.StudySession, "run", run)
    said = io.StringIO()
    server = study_server.StudyServer(study, [], Store(tmp_path / "store"), Console(file=said, width=300), 2, free_port(),
                                      "127.0.0.1", None)
    got = {}
    thread = threading.Thread(target=lambda: got.update(result=server.serve(tmp_path / "links.txt")))
    thread.start()
    while not (tmp_path / "links.txt").is_file():
        time.sleep(0.05)
    origin = f"http://127.0.0.1:{server.server.port}"
    first, second = (u.replace("http://", "ws://").replace("/?token=", "/ws?token=")
                     for u in (tmp_path / "links.txt").read_text().split())
    a = websocket.create_connection(first, timeout=10, origin=origin)
    assert json.loads(a.recv())["page"]["kind"] == "participant"
    a.close()  # the tab goes: the stubbed store fails this session
    b = websocket.create_connection(second, timeout=10, origin=origin)
    json.loads(b.recv())
    b.send(json.dumps({"form": 1, "button": "continue"}))
    thread.join(timeout=60)
    b.close()
    served, stopped = got["result"]
    assert not stopped and [s.link for s in served] == [1, 2]
    assert served[0].outcome is None and served[0].problem == "no space left on the device"
    assert served[1].outcome.code == "CODE"
    lines = said.getvalue().splitlines()
    assert "study t_study: link 1: the session failed: no space left on the device" in lines
    assert any(line.startswith("study t_study: link 2: participant ok1") and "finished" in line for line in lines)


def test_one_participant_id_on_two_links_of_a_server_is_asked_again(tmp_path):
    """Two people typing one id would be counted as one participant (and share one robot order):
    the second link's session asks for its id again; the same link may give it again."""
    from rich.console import Console

    from esr_cli.play import study_server

    study = load_study(write_study(tmp_path / "s", study_dict()))
    server = study_server.StudyServer(study, [], Store(tmp_path / "store"), Console(file=io.StringIO()), 3, free_port(),
                                      "127.0.0.1", None)
    assert server._claim("p1", 1) == "" and server._claim("p1", 1) == "" and server._claim("p2", 2) == ""
    assert server._claim("p1", 3) == "the id p1 is in use on another link: check your id with the researcher"
    session = ss.StudySession(study, [], None, "web", Store(tmp_path / "store"), lambda who: server._claim(who, 3))
    assert session._participant({"answers": {"participant": "p1"}})[1].startswith("the id p1 is in use")
    assert session._participant({"answers": {"participant": "p3"}}) == ("p3", "")
    assert session._participant({"answers": {"participant": "../x"}})[1] != ""  # the id's own rule first


@pytest.mark.slow
def test_sigterm_stops_a_study_server_within_seconds_keeping_the_episode_under_way(tmp_path):
    """A service manager's stop (SIGTERM) ends every session as a closed tab would: the episode
    being played is committed as incomplete, the server says so in one line each and exits 143."""
    import signal

    import websocket

    seed = open_seed()
    path = write_study(tmp_path / "s", study_dict(seed=seed))
    store, port, links = tmp_path / "store", free_port(), tmp_path / "links.txt"
    proc, urls = serve_links(["--study", str(path), "--participants", "2"], store, port, links)
    conn = websocket.create_connection(urls[0].replace("http://", "ws://").replace("/?token=", "/ws?token="), timeout=240,
                                       origin=f"http://127.0.0.1:{port}")
    for kind, answers, button in (("participant", {"participant": "s1"}, "continue"), ("consent", {}, "agree"),
                                  ("instructions", {}, "continue")):
        message = json.loads(conn.recv())
        assert message["page"]["kind"] == kind
        for item, value in answers.items():
            conn.send(json.dumps({"form": message["form"], "item": item, "value": value}))
        conn.send(json.dumps({"form": message["form"], "button": button}))
    message = json.loads(conn.recv())
    while "frame" not in message:  # the practice episode's ready gate
        message = json.loads(conn.recv())
    conn.send(json.dumps({"key": "space", "frame": message["seq"]}))
    message = json.loads(conn.recv())
    conn.send(json.dumps({"key": grid_keys(seed)[0], "frame": message["seq"]}))
    json.loads(conn.recv())  # the step is taken
    asked = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    _, errs = proc.communicate(timeout=60)
    assert proc.returncode == 143 and time.monotonic() - asked < 30, errs
    assert "link 1: participant s1" in errs and "ended early after 1 episode(s)" in errs and "terminated (SIGTERM)" in errs
    (episode,) = [e for e in Store(store).entries() if e.kind == PLAY_KIND]
    assert episode.status == "complete"  # committed, not left for the next start to recover
    assert not json.loads((episode.path / "summary.json").read_text())["completed"]
    assert [s["key"] for s in logged_steps(episode.path)] == grid_keys(seed)[:1]


def test_free_text_that_looks_like_a_formula_opens_as_text_in_a_spreadsheet():
    """A participant's answer `=HYPERLINK(...)` is written with a leading quote, so a spreadsheet
    shows the text rather than running it; numbers (a negative return) are untouched."""
    from esr_cli.play.results import answers_csv, episodes_csv

    record = {"record": "questionnaire", "study": "s", "participant": "p1", "session": "x", "block": 0,
              "study_robot": "A", "robot": "random", "robot_label": "A", "items": [{"id": "why", "kind": "text"}],
              "answers": {"why": '=HYPERLINK("http://example.com","x")'}}
    (row,) = csv.DictReader(io.StringIO(answers_csv([record])))
    assert row["value"] == "'" + record["answers"]["why"]
    (episode,) = csv.DictReader(io.StringIO(episodes_csv([{"participant": "@p", "return": -1.5}])))
    assert episode["participant"] == "'@p" and episode["return"] == "-1.5"
    record["answers"]["why"] = ("\x1b[2J\x1b]0;pwn\x07\r\nFORGED,row\u202e\tend\x9b\u061c\u2028\u200b\U000e0041"
                                "é 😀")  # acts on a terminal or viewer that shows the file, or hides text
    text = answers_csv([record])
    assert not any(c in text for c in "\x1b\x07\r\u202e\x9b\u061c\u2028\u200b\U000e0041")
    (row,) = csv.DictReader(io.StringIO(text))
    assert row["value"] == ("\\u001b[2J\\u001b]0;pwn\\u0007\\u000d\nFORGED,row\\u202e\tend\\u009b\\u061c\\u2028"
                            "\\u200b\\U000e0041é 😀")


def test_the_overcooked_export_csv_opens_its_text_as_text():
    """`esr plays --export FILE.csv` writes a table of every step: its text columns (a session,
    a run's name) get the same guard; numbers, negative ones too, are left as they are."""
    import pandas as pd

    from esr_cli.play.results import frame_as_text

    frame = pd.DataFrame({"run": ['=HYPERLINK("http://x","y")', "grid_2", "+1"], "reward": [1.0, -2.0, 0.0],
                          "session": ["-s", "@x", None]})
    rows = list(csv.DictReader(io.StringIO(frame_as_text(frame).to_csv(index=False))))
    assert [r["run"] for r in rows] == ['\'=HYPERLINK("http://x","y")', "grid_2", "'+1"]
    assert [r["reward"] for r in rows] == ["1.0", "-2.0", "0.0"] and [r["session"] for r in rows] == ["'-s", "'@x", ""]
    assert frame["run"][0].startswith("=")  # the caller's table is left as it was
