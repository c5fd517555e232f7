"""A study served to several participants at once (`esr play --study S --web --participants N`):
one single-use link per participant, each admitted tab a StudySession in its own thread, with
its own participant id, robot order, episodes and records; the robots are loaded once and
shared (they hold no episode's state).

The server runs until every link's session has ended, or Ctrl-C or SIGTERM: sessions still
going are ended as a closed tab ends them, what they played and answered is kept.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

from esr_cli.common.printing import printable
from esr_cli.play.study import Study
from esr_cli.play.study_session import Outcome, StudyRobot, StudySession
from esr_cli.play.web import Links
from esr_cli.runner.stop_signals import Terminated
from esr_cli.storage.store import Store, StoreError, write_output_file

JOIN_S = 30  # how long a stopping server waits for each session to write what it played


@dataclass
class Served:
    link: int  # the link's number (1-based), as in the links file
    outcome: Outcome | None = None  # None: the session failed (`problem` says why)
    problem: str = ""


def outcome_line(study: str, served: Served) -> str:
    """One line on the researcher's console for a session that has ended."""
    o = served.outcome
    if o is None:
        return f"study {study}: link {served.link}: the session failed: {served.problem}"
    who = f"link {served.link}: participant {o.participant or '(no id given)'}, session {o.session}"
    if o.consent is False:
        return f"study {study}: {who}: consent declined"
    if o.ended_early:
        return f"study {study}: {who}: ended early after {len(o.episodes)} episode(s)"
    return f"study {study}: {who}: finished, {len(o.episodes)} episode(s), code {o.code}"


class StudyServer:
    """`StudyServer(...).serve()` -> (every session served, the stop that ended the server early:
    KeyboardInterrupt or Terminated, None when every link's session ended)."""

    def __init__(self, study: Study, robots: list[StudyRobot], store: Store, console, participants: int, port: int,
                 host: str, public_url: str | None):
        self.study, self.robots, self.store, self.console = study, robots, store, console
        self.served: list[Served] = []
        self.threads: list[threading.Thread] = []
        self.lock = threading.Lock()
        self.ids: dict[str, int] = {}  # participant id -> the link it was given on
        self.server = Links(port, console, participants, self._start, host, public_url)

    def _start(self, channel, link: int) -> None:
        thread = threading.Thread(target=self._run, args=(channel, link), name=f"esr-study-link-{link}", daemon=True)
        with self.lock:
            self.threads.append(thread)
        thread.start()

    def _run(self, channel, link: int) -> None:
        served = Served(link)
        try:
            served.outcome = StudySession(self.study, self.robots, channel, "web", self.store,
                                          lambda participant: self._claim(participant, link)).run()
        except (StoreError, OSError) as e:  # the store, not the person: this session ends, the others go on
            served.problem = printable(str(e))
        except Exception as e:  # noqa: BLE001 - a fault in one session must not hang the server
            served.problem = printable(f"{type(e).__name__}: {e}")[:300]
        finally:
            channel.finish(["the session has ended"] if served.outcome is None else [])
            with self.lock:
                self.served.append(served)
        self.console.print(outcome_line(self.study.name, served), highlight=False, markup=False)

    def _claim(self, participant: str, link: int) -> str:
        """Two links' sessions under one id would be counted as one person's: the second is asked again."""
        with self.lock:
            first = self.ids.setdefault(participant, link)
        return "" if first == link else f"the id {participant} is in use on another link: check your id with the researcher"

    def _all_ended(self) -> bool:
        with self.lock:
            return self.server.used == len(self.server.tokens) and len(self.served) == len(self.threads)

    def write_links(self, path: Path | None) -> None:
        links = self.server.links
        if path is None:
            self.console.print(f"one link per participant ({len(links)}); each lets one person in, once:", highlight=False)
            for link in links:
                self.console.print(f"  {link}", highlight=False, markup=False)
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        # The links are the study's keys: readable by their owner only. Written beside and
        # renamed, so whoever waits for the file (a script handing links out) reads all of them.
        write_output_file(path, "".join(f"{link}\n" for link in links).encode(), mode=0o600)
        self.console.print(f"{len(links)} link(s), one per participant, each usable once: {path}", highlight=False)

    def serve(self, links_file: Path | None) -> tuple[list[Served], bool]:
        with self.server:
            self.write_links(links_file)
            self.console.print("the server runs until every link's session has ended (Ctrl-C stops it sooner)",
                               highlight=False)
            try:
                while not self._all_ended():
                    time.sleep(0.2)
                stopped = None
            except (KeyboardInterrupt, Terminated) as e:  # Ctrl-C, or SIGTERM (kill, a service manager)
                stopped = e
                self.server.end_all()
                for thread in list(self.threads):
                    thread.join(timeout=JOIN_S)
        return sorted(self.served, key=lambda s: s.link), stopped
