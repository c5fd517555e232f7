"""esr play (a person in the human's seat) and esr plays (what was played)."""

from __future__ import annotations

import io
import ipaddress
import re
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

import typer
from rich.table import Table

from esr_cli.cli.app import BudgetOpt, Exit, SetOpt, app, check_output_file, err, out, refuse_inside_store, refuse_spec_options
from esr_cli.common.printing import print_table, tagged
from esr_cli.model import spec as spec_model
from esr_cli.recipes import targets
from esr_cli.storage.store import PLAY_KIND, Store, write_output_file

MAX_PLAY_EPISODES = 10_000  # a person plays each one: far above any study's session


@app.command()
def play(
    ctx: typer.Context,
    target: Optional[str] = typer.Argument(None, help="a trained run (key or path) or a spec; with --robots, the spec only "
                                          "names the environment", show_default=False),
    budget: str = BudgetOpt,
    set_: Optional[List[str]] = SetOpt,
    robots: Optional[str] = typer.Option(None, "--robots", help="comma-separated robots to play with, in a counterbalanced "
                                         "order under neutral names: run keys, paths or specs, and `random`"),
    episodes: int = typer.Option(1, "--episodes", "-n", help="episodes in the session"),
    participant: Optional[str] = typer.Option(None, "--participant", help="the person's id (logged; decides the order and "
                                              "names of the robots); default: anonymous, or with --study asked first"),
    fps: float = typer.Option(6.0, "--fps", help="Overcooked: steps per second (a tick without a key is stay)"),
    web: bool = typer.Option(False, "--web", help="play in a browser: serve the game on localhost"),
    port: int = typer.Option(8765, "--port", help="--web: the port to serve on"),
    host: str = typer.Option("127.0.0.1", "--host", help="--web: the address to listen on; beyond localhost (a lab's "
                             "network, 0.0.0.0) the page's token guards it, and an online study belongs behind HTTPS"),
    public_url: Optional[str] = typer.Option(None, "--public-url", help="--web: the address participants reach the "
                                             "server at (an HTTPS proxy in front of it), the base of the links printed"),
    participants: Optional[int] = typer.Option(None, "--participants", help="--study --web: serve this many participants, "
                                               "several at once, each on a single-use link of their own"),
    links: Optional[Path] = typer.Option(None, "--links", help="--participants: write the links to this file (readable "
                                         "by you only) rather than the console"),
    seed: int = typer.Option(0, "--seed", help="the first episode's environment seed (episode i: seed + i)"),
    seed_index: int = typer.Option(0, "--seed-index", help="which seed of each trained run acts"),
    countdown: float = typer.Option(3.0, "--countdown", help="seconds counted down after the person presses space to "
                                    "start each episode (0: none)"),
    study: Optional[Path] = typer.Option(None, "--study", help="run a user study from its file (docs/play.md): consent, "
                                         "instructions, practice, each robot's episodes and questionnaire, a completion code"),
):
    """Play the human's part with trained robots; every episode is logged as a `play` artifact."""
    from esr_cli.play import session as ps

    if not 1024 <= port <= 65535:
        raise Exit(2, f"--port: between 1024 and 65535 (got {port})")
    serving = _serving(ctx, web, host, public_url, participants, links, study, participant)
    if study is not None:
        return _play_study(ctx, study, target, participant, web, port, serving)
    if target is None:
        raise Exit(2, "esr play: name a trained run or a spec (or give --study STUDY.yaml)")
    participant = "anonymous" if participant is None else participant
    if not 1 <= episodes <= MAX_PLAY_EPISODES:
        raise Exit(2, f"--episodes: between 1 and {MAX_PLAY_EPISODES:,} (got {episodes:,})")
    if not 0.5 <= fps <= 60:
        raise Exit(2, f"--fps: between 0.5 and 60 (got {fps})")
    if not 0 <= countdown <= 30:
        raise Exit(2, f"--countdown: between 0 and 30 seconds (got {countdown})")
    from esr_cli.play.study import participant_problem  # the same rule as a study's: ids name files and rows

    if problem := participant_problem(participant):
        raise Exit(2, f"--participant: {problem}")
    if not 0 <= seed <= spec_model.MAX_SEED - (episodes - 1):  # episode i plays seed + i, an int32 PRNG seed
        raise Exit(2, f"--seed: between 0 and {spec_model.MAX_SEED - (episodes - 1):,} for {episodes} episode(s) (got {seed})")
    refs = [r.strip() for r in robots.split(",") if r.strip()] if robots else []
    if robots is not None and not refs:
        raise Exit(2, "--robots: name at least one robot (a run key, path or spec, or `random`)")
    if not any(targets.is_spec_file(r) for r in [target, *refs]):
        refuse_spec_options(target, budget, set_)
    front, name = _front(web, port, serving)
    spec, opponents = ps.load_opponents(target, refs, budget, set_, seed_index, ctx.obj.store, participant)
    ps.recover_abandoned(ctx.obj.store, err)
    session = ps.new_session_id()
    with front:
        played = ps.run_session(spec, opponents, participant, episodes, seed, fps, front, name, ctx.obj.store, err,
                                countdown, session)
        rows = ps.summary_rows(played)
        front.finish([f"session over: {len(played)} episode(s) played. Thank you!"])
    # The terminal is the participant's screen: which robot is which stays with `esr plays`.
    shown = ("robot", "episodes (completed)", "return (mean)", "success", "steps (mean)")
    table = Table(title=f"esr play: participant {participant}, session {session}, {len(played)} of {episodes} episode(s)")
    for col in shown if not web else shown[:1] + ("key",) + shown[1:]:
        table.add_column(col)
    for r in rows:
        cells = [f"{r['episodes']} ({r['completed']})", f"{r['return_mean']:.2f}", f"{r['success_rate']:.2f}",
                 f"{r['steps_mean']:.1f}"]
        table.add_row(r["robot_label"], *([r["robot"][:12]] if web else []), *cells)
    err.print(table)
    if not web:
        err.print(f"the robots' keys: {ctx.obj.store.invocation()} plays --session {session}", highlight=False)
    for p in played:
        out.print(p["path"], highlight=False)
    if played and not played[-1]["completed"]:
        err.print("the session was ended early; its last episode is kept as incomplete", highlight=False)
        raise Exit(130)


MAX_PARTICIPANTS = 1000  # links of one server
HOST_NAME = re.compile(r"[A-Za-z0-9]([A-Za-z0-9.-]{0,251}[A-Za-z0-9])?")
PUBLIC_URL = re.compile(r"https?://[A-Za-z0-9.\-\[\]:]{1,260}(/[A-Za-z0-9._~\-/]{0,200})?")


@dataclass(frozen=True)
class Serving:
    """Where and for how many the browser's server listens (`--host`, `--public-url`, `--participants`)."""

    host: str = "127.0.0.1"
    public_url: str | None = None
    participants: int | None = None  # None: one participant at a time on one token
    links: Path | None = None


def _serving(ctx: typer.Context, web: bool, host: str, public_url: Optional[str], participants: Optional[int],
             links: Optional[Path], study: Optional[Path], participant: Optional[str]) -> Serving:
    """The web server's options, checked before any work."""
    for name, given in (("host", host != "127.0.0.1"), ("public_url", public_url is not None),
                        ("participants", participants is not None)):
        if given and not web:
            raise Exit(2, f"--{name.replace('_', '-')}: only with --web")
    if participants is not None:
        if study is None:
            raise Exit(2, "--participants: only with --study (each participant's session is the study's)")
        if not 1 <= participants <= MAX_PARTICIPANTS:
            raise Exit(2, f"--participants: between 1 and {MAX_PARTICIPANTS:,} (got {participants:,})")
        if participant is not None:
            raise Exit(2, "--participant: with --participants each person gives their own id (the link's "
                          "&participant=ID, or the page's form)")
    if links is not None:
        if participants is None:
            raise Exit(2, "--links: only with --participants N")
        refuse_inside_store(links, "--links", ctx.obj.store)
        check_output_file(links, "--links")
    try:
        ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        if not HOST_NAME.fullmatch(host):
            raise Exit(2, f"--host: an IP address or a host name (got {host[:80]!r})") from None
    if public_url is not None and not PUBLIC_URL.fullmatch(public_url):
        raise Exit(2, f"--public-url: an http:// or https:// address with no query (got {public_url[:80]!r})")
    base = None if public_url is None else public_url.rstrip("/") + "/"
    return Serving(host, base, participants, links)


def _warn_if_plain(serving: Serving) -> None:
    from esr_cli.play.web import is_loopback

    if not is_loopback(serving.host) and not (serving.public_url or "").startswith("https://"):
        err.print(f"esr play: listening on {serving.host}: the page and its token travel unencrypted; "
                  "an online study belongs behind an HTTPS proxy (--public-url https://...)", highlight=False)


def _front(web: bool, port: int, serving: Serving):
    """(the front end, its name): the browser's server on `port`, or this terminal."""
    if web:
        from esr_cli.play.web import PortInUse, Web

        try:
            front = Web(port, err, serving.host, serving.public_url)
        except PortInUse as e:
            raise Exit(2, str(e)) from None
        _warn_if_plain(serving)
        return front, "web"
    from esr_cli.play.terminal import NotATerminal, Terminal

    try:
        return Terminal(out), "terminal"
    except NotATerminal as e:
        raise Exit(2, str(e)) from None


# Options a study file sets itself: beside --study they would change nothing.
STUDY_SETS = ("budget", "set_", "robots", "episodes", "fps", "seed", "seed_index", "countdown")


def _play_study(ctx: typer.Context, path: Path, target: Optional[str], participant: Optional[str], web: bool,
                port: int, serving: Serving) -> None:
    from esr_cli.play import session as ps, study_session as ss
    from esr_cli.play.study import load_study, participant_problem

    if target is not None:
        raise Exit(2, f"--study: the study file names the environment and robots; leave out {target!r}")
    for name in STUDY_SETS:
        source = ctx.get_parameter_source(name)  # (the CLI library's own enum: compared by name)
        if source is not None and source.name in ("COMMANDLINE", "ENVIRONMENT"):
            option = next(p.opts[0] for p in ctx.command.params if p.name == name)
            raise Exit(2, f"{option}: the study file sets this; change it there")
    if participant is not None and participant_problem(participant):
        raise Exit(2, f"--participant: {participant_problem(participant)}")
    the_study = load_study(path)
    if serving.participants is not None:
        return _serve_study(ctx, the_study, port, serving)
    front, name = _front(web, port, serving)
    robots = ss.load_robots(the_study, ctx.obj.store)
    ps.recover_abandoned(ctx.obj.store, err)
    if web and participant is None:
        err.print("the participant's id: add &participant=ID to the address below, or the page asks for it", highlight=False)
    with front:
        outcome = ss.StudySession(the_study, robots, front, name, ctx.obj.store).run(participant)
    _print_paths(outcome)
    who = f"participant {outcome.participant or '(no id given)'}, session {outcome.session}"
    if outcome.consent is False:
        err.print(f"study {the_study.name}: {who}: consent declined; only that is recorded", highlight=False)
    elif outcome.ended_early:
        err.print(f"study {the_study.name}: {who}: ended early after {len(outcome.episodes)} episode(s); "
                  "what was played and answered is kept", highlight=False)
        raise Exit(130)
    else:
        err.print(f"study {the_study.name}: {who}: finished, {len(outcome.episodes)} episode(s); "
                  f"{ctx.obj.store.invocation()} plays --study {the_study.name}", highlight=False)


def _print_paths(outcome) -> None:
    """A study session's stored episodes and records, one path a line (stdout, for scripts)."""
    for p in [*(e["path"] for e in outcome.episodes), *map(str, outcome.records)]:
        out.print(p, highlight=False)


def _serve_study(ctx: typer.Context, the_study, port: int, serving: Serving) -> None:
    """`--participants N`: several participants at once, one single-use link each."""
    from esr_cli.play import session as ps, study_session as ss
    from esr_cli.play.study_server import StudyServer
    from esr_cli.play.web import PortInUse

    try:
        server = StudyServer(the_study, [], ctx.obj.store, err, serving.participants, port, serving.host, serving.public_url)
    except PortInUse as e:
        raise Exit(2, str(e)) from None
    _warn_if_plain(serving)
    server.robots = ss.load_robots(the_study, ctx.obj.store)
    ps.recover_abandoned(ctx.obj.store, err)
    err.print("a participant's id: add &participant=ID to their link, or the page asks for it", highlight=False)
    served, stopped = server.serve(serving.links)
    for s in served:
        if s.outcome is not None:
            _print_paths(s.outcome)
    finished = sum(1 for s in served if s.outcome is not None and s.outcome.code is not None)
    err.print(f"study {the_study.name}: {len(served)} of {serving.participants} link(s) used, {finished} session(s) "
              f"finished; {ctx.obj.store.invocation()} plays --study {the_study.name}", highlight=False)
    if stopped is not None and not isinstance(stopped, KeyboardInterrupt):
        raise stopped  # SIGTERM: its own line and exit code, once every session has written what it played
    if stopped is not None and any(s.outcome is None or s.outcome.ended_early for s in served):
        raise Exit(130)
    if any(s.outcome is None for s in served):
        raise Exit(1)


@app.command()
def plays(
    ctx: typer.Context,
    participant: Optional[str] = typer.Option(None, "--participant", help="only this participant's episodes"),
    session: Optional[str] = typer.Option(None, "--session", help="only this session's episodes"),
    export: Optional[Path] = typer.Option(None, "--export", help="write the episodes shown: .jsonl, every step of any "
                                          "environment (docs/play.md); .pickle (a pandas DataFrame) or .csv, the "
                                          "Overcooked ones as overcooked-ai's 2019 human trials (their columns and dtypes)"),
    by_robot: bool = typer.Option(False, "--by-robot", help="a table per robot instead: participants, episodes, and the "
                                  "return and success of completed episodes (per participant, then mean ± SE and IQM across participants)"),
    csv_file: Optional[Path] = typer.Option(None, "--csv", help="also write one row per episode shown (participant, "
                                            "robot, return, success, keys, reaction time...) to this CSV file; with "
                                            "--study, the study's table"),
    study: Optional[str] = typer.Option(None, "--study", help="a study's sessions (its name): per robot, return, success "
                                        "and each questionnaire item across participants, practice left out"),
    answers: Optional[Path] = typer.Option(None, "--answers", help="with --study: write every answer, free text included, "
                                           "one row each, to this CSV file"),
):
    """List the played episodes (`esr play`), sum them up per robot or per study, and export them."""
    from esr_cli.play import results, session as ps

    if study is not None and by_robot:
        raise Exit(2, "--by-robot: --study prints its own table per robot")
    if answers is not None and study is None:
        raise Exit(2, "--answers: only with --study NAME")
    if export is not None and export.suffix not in (".jsonl", ".pickle", ".pkl", ".csv"):
        raise Exit(2, f"--export: {export} should end in .jsonl (steps), .pickle or .csv (Overcooked human data)")
    for path, option in ((export, "--export"), (csv_file, "--csv"), (answers, "--answers")):
        if path is not None:
            refuse_inside_store(path, option, ctx.obj.store)
            check_output_file(path, option)
    named = [(option, path) for path, option in ((export, "--export"), (csv_file, "--csv"), (answers, "--answers"))
             if path is not None]
    for i, (first, a) in enumerate(named):  # one would overwrite the other
        for second, b in named[i + 1:]:
            if a.resolve() == b.resolve():
                raise Exit(2, f"{first} and {second} name the same file")
    writes_a_file = any(path is not None for path in (export, csv_file, answers))  # none written: exit 1
    if study is not None:
        _plays_study(ctx.obj.store, study, participant, session, csv_file, answers, export, writes_a_file)
        return
    found = ps.played_episodes(ctx.obj.store, participant, session)
    if not found:
        what = f"no played episodes in {ctx.obj.store.root}" + (" for that selection" if participant or session else "")
        if writes_a_file:
            raise Exit(1, what)
        err.print(what, highlight=False)  # an empty listing, as `esr ls` says of an empty store
        return
    rows = results.episode_rows(found)
    exported = _prepare_export(found, export, ctx.obj.store) if export is not None else None
    if by_robot:
        _print_by_robot(results.by_robot(rows))
    else:
        _print_plays(found)
    if csv_file is not None:
        _write(csv_file, results.episodes_csv(rows), f"{len(rows)} episode(s)")
    if exported is not None:
        _write(export, *exported, tag="exported")


def _prepare_export(found, export: Path, store: Store) -> tuple[str | bytes, str]:
    """The file `--export` writes and what to say of it, made before anything is printed, so an
    export that cannot be made ends the command with its one line alone."""
    if export.suffix != ".jsonl":
        return _overcooked_export(found, export, store)
    from esr_cli.play.step_export import export_jsonl

    text, count = export_jsonl([store.lookup(PLAY_KIND, k) for k, _, _ in found])
    return text, f"{len(found)} episode(s), {count} steps"


def _write(path: Path, content: str | bytes, what: str, tag: str = "written") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_output_file(path, content.encode() if isinstance(content, str) else content)
    err.print(tagged(tag, "green", f" {what}: {path}"))


def _plays_study(store: Store, study: str, participant: Optional[str], session: Optional[str],
                 csv_file: Optional[Path], answers: Optional[Path], export: Optional[Path], writes_a_file: bool) -> None:
    """`esr plays --study NAME`: the study's table per robot and its sessions, and the files asked for."""
    from esr_cli.play import results, study_session as ss
    from esr_cli.play.study import NAME

    if not re.fullmatch(NAME, study):
        raise Exit(2, f"--study: a study's name (the `name:` of its file), not {study[:60]!r}")
    found = ss.played_episodes_of(store, study, participant, session)
    records = [r for r in ss.study_records(store, study)
               if participant in (None, r["participant"]) and session in (None, r["session"])]
    if not found and not records:
        narrowed = " for that selection" if participant or session else ""
        what = f"no sessions of study {study!r} in {store.root}{narrowed}"
        if writes_a_file:
            raise Exit(1, what)
        err.print(what, highlight=False)  # an empty listing, as `esr plays` and `esr ls` say of one
        return
    rows = results.episode_rows(found)
    exported = _prepare_export(found, export, store) if export is not None else None
    table, items = results.study_table(rows, records), results.study_items(records)
    _print_study(study, table, items)
    _print_study_sessions(results.study_sessions(rows, records))
    if csv_file is not None:
        _write(csv_file, results.study_csv(table, items), f"{len(table)} robot(s)")
    if answers is not None:
        text = results.answers_csv(records)
        _write(answers, text, f"{text.count(chr(10)) - 1} answer(s)")
    if exported is not None:
        _write(export, *exported, tag="exported")


def _print_study(study: str, table: list[dict], items: list[dict]) -> None:
    from esr_cli.common.stats import format_summary

    title = (f"study {study} per robot (practice left out): completed episodes and answers averaged per participant, "
             "then mean ± SE and IQM [95% bootstrap CI] across participants; free text: --answers FILE")
    t = Table(title=title)
    for col in ("robot", "run", "participants", "episodes", "return", "success", *(i["id"] for i in items)):
        t.add_column(col, no_wrap=col == "robot")
    for r in table:
        cells = [format_summary(r[i["id"]], 2, "participant") if i["kind"] == "likert" else f"{r[i['id']]['answers']} answer(s)"
                 for i in items]
        t.add_row(r["robot"], " ".join(k[:12] for k in r["runs"]), str(r["participants"]),
                  f"{r['completed']} of {r['episodes']} completed", format_summary(r["return"], 2, "participant"),
                  format_summary(r["success"], 2, "participant"), *cells)
    print_table(out, t)


def _print_study_sessions(sessions: list[dict]) -> None:
    t = Table(title="sessions")
    for col in ("participant", "session", "consent", "practice", "episodes", "questionnaires", "completion code"):
        t.add_column(col)
    for e in sessions:
        t.add_row(str(e["participant"]), str(e["session"]), e["consent"], str(e["practice"]),
                  f"{e['completed']} of {e['episodes']} completed", str(e["questionnaires"]), e["code"] or "not finished")
    print_table(out, t)


def _print_by_robot(rows: list[dict]) -> None:
    from esr_cli.common.stats import format_summary

    table = Table(title="played episodes per robot: completed episodes averaged per participant, then mean ± SE and "
                        "IQM [95% bootstrap CI] across participants")
    for col in ("robot", "env", "participants", "episodes", "return", "success"):
        table.add_column(col, no_wrap=col == "robot")
    for r in rows:
        scored = "" if r["scored_participants"] == r["participants"] else f" ({r['scored_participants']} with a completed episode)"
        table.add_row(str(r["robot"]), r["env"], f"{r['participants']}{scored}", f"{r['completed']} of {r['episodes']} completed",
                      format_summary(r["return"], 2, "participant"), format_summary(r["success"], 2, "participant"))
    print_table(out, table)


def _print_plays(found) -> None:
    table = Table()
    for col in ("key", "participant", "session", "episode", "robot", "env", "completed", "steps", "return"):
        table.add_column(col, no_wrap=col == "key")  # the whole key, as human.data takes it
    for key, header, summary in found:
        env = header["env"]
        table.add_row(key, str(header["participant"]), str(header["session"]), str(header["episode"]),
                      str(header["robot"][:12]), str(env.get("layout", env["kind"])), "yes" if summary["completed"] else "no", str(summary["steps"]),
                      f"{summary['score']:g}")
    print_table(out, table)


def _overcooked_export(found, export: Path, store: Store) -> tuple[bytes, str]:
    from esr_cli.play import export as px

    frame, count = px.export_overcooked(store, [k for k, _, _ in found])
    if count == 0:
        raise Exit(2, "--export: none of these episodes is an Overcooked episode")
    buffer = io.BytesIO()
    if export.suffix == ".csv":  # a participant's session or a run's name must open as text, never a formula
        from esr_cli.play.results import frame_as_text

        frame_as_text(frame).to_csv(buffer, index=False)
    else:
        frame.to_pickle(buffer)
    return buffer.getvalue(), f"{count} Overcooked episode(s), {len(frame)} rows"

