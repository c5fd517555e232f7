"""A play session: a person plays episodes with one or more robots, each episode an artifact.

- The robots are presented in a counterbalanced order (a balanced Latin square, its row chosen
  by the participant's id) under neutral labels ("robot A", ...) whose assignment also depends
  on the participant, so neither the order nor the name tells the person which robot it is.
- Every episode is a `play` artifact made through the artifact layer. Its steps are appended
  to steps.jsonl (flushed and synced each step) while the person plays, so a crash loses at
  most the current step; a closed tab, Ctrl-C or q commits the episode as incomplete, and an
  episode left behind by a killed process is committed as incomplete by the next `esr play`.
"""

from __future__ import annotations

import json
import os
import time
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path

from rich.console import Console

from esr_cli.common import specs
from esr_cli.common.numbers import as_count, as_number
from esr_cli.model.envs import make_env
from esr_cli.play.boards import board_for
from esr_cli.play.game import RANDOM_ROBOT, Game, Robot, play_episode
from esr_cli.recipes.runs import find_run, load_run, seed_slice
from esr_cli.recipes.targets import run_spec
from esr_cli.storage.artifacts import Recipe, ensure
from esr_cli.storage.play_log import EPISODE_FILE, FINAL_STATE_FILE, STEPS_FILE, read_header, read_steps
from esr_cli.storage.store import PLAY_KIND, LockBusy, Store, StoreError, atomic_write_text, digest_bytes


# ---------------------------------------------------------------- the plan
def participant_number(participant: str) -> int:
    """A stable number from the participant's id (the same id: the same order and labels)."""
    return int(digest_bytes(participant.encode(), 8), 16)


def latin_square(n: int) -> list[list[int]]:
    """A balanced Latin square: every condition once per row and column, and (n even) every
    ordered pair adjacent once; for odd n its mirror rows are added, which restores that."""
    first = [0]
    for i in range(1, n):
        first.append((i + 1) // 2 if i % 2 else n - i // 2)
    rows = [[(c + r) % n for c in first] for r in range(n)]
    return rows if n % 2 == 0 else rows + [row[::-1] for row in rows]


def episode_order(robots: int, episodes: int, participant: str) -> list[int]:
    """Which robot (index) each episode is played with: the participant's row of the square,
    repeated until `episodes` are planned."""
    rows = latin_square(robots)
    row = rows[participant_number(participant) % len(rows)]
    return [row[i % robots] for i in range(episodes)]


def robot_labels(robots: int, participant: str) -> list[str]:
    """Neutral names for the robots, assigned in an order that depends on the participant."""
    letters = [f"robot {chr(ord('A') + i)}" for i in range(robots)]
    shift = (participant_number(participant) // 7) % robots
    return letters[shift:] + letters[:shift]


# ---------------------------------------------------------------- the robots
@dataclass
class Opponent:
    ref: str  # the run's key, or "random"
    label: str
    robot: Robot


def load_opponents(target: str, refs: list[str], budget: str, sets, seed_index: int, store: Store,
                   participant: str) -> tuple[object, list[Opponent]]:
    """(the spec whose environment is played, the robots). `target` is a trained run (key or
    path) or a spec; with `refs` (runs, specs or "random") those are played, else `target`'s
    run. Every robot must have been trained on the same environment."""
    spec = _spec_of(target, budget, sets, store, need_run=not refs)
    chosen = refs or [target]
    labels = robot_labels(len(chosen), participant)
    env = make_env(spec.env)
    paths = [None if ref == RANDOM_ROBOT else find_run(ref, budget, sets, store) for ref in chosen]
    _named_once(chosen, paths)
    opponents = []
    for ref, path, label in zip(chosen, paths, labels):
        if path is None:
            opponents.append(Opponent(RANDOM_ROBOT, label, Robot(RANDOM_ROBOT, env)))
            continue
        _, manifest, trainer, state = load_run(store, str(path))
        if trainer.spec.env != spec.env:
            raise StoreError(f"robot {ref} was trained on another environment than {spec.name}: all robots of a session share one")
        if not 0 <= seed_index < len(trainer.spec.train.seeds):
            raise StoreError(f"--seed-index {seed_index} out of range for run {ref} ({len(trainer.spec.train.seeds)} seeds)")
        lstate = seed_slice(state.learner, seed_index)
        opponents.append(Opponent(manifest["key"], label, Robot(manifest["key"], trainer.env, trainer, lstate)))
    return spec, opponents


def _named_once(refs: list[str], paths: list[Path | None]) -> None:
    """A session's robots are told apart by their labels: one robot under two would be counted as two."""
    first: dict[str, str] = {}
    for ref, path in zip(refs, paths):
        robot = path.name if path is not None else RANDOM_ROBOT
        if robot in first:
            same = "" if first[robot] == ref else f" (as {first[robot]} and {ref})"
            raise StoreError(f"--robots: robot {robot[:12]} is named twice{same}: name each robot once")
        first[robot] = ref


def _spec_of(target: str, budget: str, sets, store: Store, need_run: bool):
    p = Path(target)
    if p.suffix in (".yaml", ".yml") and not need_run:
        return specs.load(p, budget, list(sets or []))
    return run_spec(find_run(target, budget, sets, store))


# ---------------------------------------------------------------- the artifacts
# The clock of each front end's own stamps (frame_shown_at, key_pressed_at), in seconds.
FRONT_CLOCKS = {"web": "performance.now() of the page", "terminal": "monotonic, at read time"}

def episode_recipe(spec, opponent: Opponent, participant: str, session: str, episode: int, seed: int, front,
                   front_name: str, fps: float, title: str, countdown_s: float, extra: dict | None = None) -> Recipe:
    """`extra`: fields that mark the episode (a study's name, practice, block), in its key and header."""
    components = {"kind": "play", "session": session, "episode": episode, "participant": participant,
                  "robot": opponent.ref, "env": spec.training_part()["env"], "seed": seed, **(extra or {})}

    front_clock = f"{front_name}, {FRONT_CLOCKS.get(front_name, 'monotonic')}"

    def build(out: Path, store: Store) -> dict:
        header = {"participant": participant, "session": session, "episode": episode, "robot": opponent.ref,
                  "robot_label": opponent.label, "env": components["env"], "seed": seed, "front_end": front_name,
                  "episode_steps": spec.env.episode_steps,
                  "fps": fps if board_for(spec.env.kind).idle_action is not None else None, "countdown_s": countdown_s,
                  "started_at": time.time(), **(extra or {}),
                  # the clocks of the steps' stamps (docs/play.md)
                  "clocks": {"frame_sent_at": "esr, monotonic", "key_received_at": "esr, monotonic",
                             **dict.fromkeys(("frame_shown_at", "key_pressed_at"), front_clock)}}
        atomic_write_text(out / EPISODE_FILE, json.dumps(header, indent=2))
        game = Game(spec.env.kind, opponent.robot, seed)
        with open(out / STEPS_FILE, "a") as log:
            def write(step):
                log.write(json.dumps(asdict(step)) + "\n")
                log.flush()
                os.fsync(log.fileno())

            try:
                completed = play_episode(game, front, fps, title, write, countdown_s)
            except KeyboardInterrupt:
                completed = False
        atomic_write_text(out / FINAL_STATE_FILE, json.dumps(game.state_record()))  # the last step's next state
        return summarize(out, completed)

    return Recipe(PLAY_KIND, f"play {participant}", components, build, seeds=(seed,),
                  record={"env": spec.env.kind, "participant": participant}, keeps_partial=True)


def summarize(path: Path, completed: bool) -> dict:
    """The episode's summary, from its log (the same for a finished and a recovered episode)."""
    steps = read_steps(path)
    header = read_header(path) if (Path(path) / EPISODE_FILE).exists() else {}
    episode_steps = header.get("episode_steps")
    ret = float(sum(s["reward"] for s in steps))
    reactions = [s["reaction_s"] for s in steps if s["reaction_s"] is not None]
    dropped = sum(s.get("dropped_keys", 0) for s in steps)
    return {
        "participant": header.get("participant"), "robot": header.get("robot"), "robot_label": header.get("robot_label"),
        "episode": header.get("episode"), "completed": bool(completed and len(steps) == episode_steps),
        "steps": len(steps), "episode_steps": episode_steps, "score": ret, "success": ret > 0,
        "keys": sum(s["key"] is not None for s in steps),
        "reaction_s_mean": round(sum(reactions) / len(reactions), 4) if reactions else None,
        "dropped_keys": dropped,  # pressed before the frame they would have acted on
        "return": {"mean": ret, "of": "played episode"},
    }


def recover_abandoned(store: Store, console: Console) -> list[Path]:
    """Commit, as incomplete, every episode a killed process left unfinished (its lock free)."""
    recovered = []
    for entry in list(store.entries()):
        if entry.kind != PLAY_KIND or entry.status != "partial" or not entry.manifest:
            continue
        try:
            with store.lock(PLAY_KIND, entry.key, wait=False):
                pass
        except LockBusy:
            continue  # being played now, by another process
        components = entry.manifest.get("key_components")
        if not components or components.get("kind") != "play":  # a study's record (a questionnaire) is no episode
            continue
        def build(out: Path, store: Store) -> dict:
            return summarize(out, False)

        built = ensure(Recipe(PLAY_KIND, entry.manifest.get("name", "play"), components, build,
                              record={"recovered": True}, keeps_partial=True), store)
        console.print(f"an episode left unfinished was kept as incomplete: {built.path}")
        recovered.append(built.path)
    return recovered


def played_episodes(store: Store, participant: str | None = None, session: str | None = None) -> list[tuple[str, dict, dict]]:
    """(key, episode header, summary) of every committed played episode that matches, in the
    order they were played."""
    found = []
    for entry in store.entries():
        if entry.kind != PLAY_KIND or entry.status != "complete" or not (entry.path / EPISODE_FILE).exists():
            continue
        header = read_header(entry.path)
        if (participant and header.get("participant") != participant) or (session and header.get("session") != session):
            continue
        found.append((entry.key, header, _played_summary(entry)))
    return sorted(found, key=lambda f: (f[1]["started_at"], f[1]["episode"]))  # read_header checked their types


def _played_summary(entry) -> dict:
    """A played episode's summary from its manifest; StoreError naming the episode where it lacks
    what the listings read (completed, steps, score) in the types esr writes."""
    summary = (entry.manifest or {}).get("summary")
    fine = isinstance(summary, dict) and isinstance(summary.get("completed"), bool) and \
        as_count(summary.get("steps")) is not None and as_number(summary.get("score")) is not None
    if not fine:
        raise StoreError(f"damaged played episode: the manifest of {entry.path} has no summary esr wrote")
    return summary


# ---------------------------------------------------------------- the session
def new_session_id() -> str:
    return f"{time.strftime('%Y%m%dT%H%M%S')}-{uuid.uuid4().hex[:8]}"


def run_session(spec, opponents: list[Opponent], participant: str, episodes: int, seed: int, fps: float, front,
                front_name: str, store: Store, console: Console, countdown_s: float = 3.0,
                session: str | None = None) -> list[dict]:
    """Play the planned episodes in order; stop at the first one the person ends early.
    -> the summaries of the episodes played."""
    session = session or new_session_id()
    order = episode_order(len(opponents), episodes, participant)
    played = []
    front.ready()
    for i, which in enumerate(order):
        opponent = opponents[which]
        title = f"episode {i + 1} of {episodes} · {opponent.label}"
        built = ensure(episode_recipe(spec, opponent, participant, session, i, seed + i, front, front_name, fps, title,
                                      countdown_s), store)
        summary = built.summary() | {"path": str(built.path)}
        played.append(summary)
        if not summary["completed"]:
            break
    return played


def summary_rows(played: list[dict]) -> list[dict]:
    """One row per robot: its label, key, episodes (completed of played), mean return, success
    rate and mean steps."""
    rows = {}
    for p in played:
        row = rows.setdefault(p["robot_label"], {"robot_label": p["robot_label"], "robot": p["robot"], "episodes": 0,
                                                  "completed": 0, "returns": [], "successes": [], "steps": []})
        row["episodes"] += 1
        row["completed"] += p["completed"]
        row["returns"].append(p["score"])
        row["successes"].append(p["success"])
        row["steps"].append(p["steps"])
    out = []
    for row in sorted(rows.values(), key=lambda r: r["robot_label"]):
        n = len(row["returns"])
        out.append({"robot_label": row["robot_label"], "robot": row["robot"], "episodes": row["episodes"],
                    "completed": row["completed"], "return_mean": sum(row["returns"]) / n,
                    "success_rate": sum(row["successes"]) / n, "steps_mean": sum(row["steps"]) / n})
    return out
