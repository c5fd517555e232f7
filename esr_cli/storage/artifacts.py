"""The one artifact lifecycle: every kind in the store is made by a `Recipe` and `ensure`.

A recipe says what an artifact is (kind, name, the components its key is built from), what
must exist before it (`requires`: other recipes, such as a run's BC humans), what to check
before anything is written (`check`), and how to make its files (`build`). `ensure` does the
rest, the same way for runs, evaluations, human data, BC humans, exact analyses, figures,
reports and ablations:

  key = content_key(components) -> lookup (a hit is done) -> check -> requires -> lock ->
  lookup again (another process may have finished it) -> partial directory (kept: a resumed
  run) -> build -> summary.json -> manifest -> atomic rename.

Recipes are data: building one reads nothing and writes nothing, so a caller can compute a
key (or compare two) without touching the store.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, NamedTuple

from esr_cli.common.jsonl import read_json
from esr_cli.common.stops import Diverged, Interrupted, TimeLimitReached
from esr_cli.storage import provenance
from esr_cli.storage.store import KINDS, RUN_KIND, Store, StoreError, atomic_write_text, content_key, read_pending

SUMMARY_FILE = "summary.json"
MAX_SUMMARY_BYTES = 16 << 20  # a run's summary is a few KiB; a figure's lists the runs it read


@dataclass(frozen=True)
class Recipe:
    kind: str  # one of store.KINDS
    name: str  # what `esr ls` shows: a spec's name, a figure's
    components: dict  # everything that decides the artifact's content, and nothing else
    build: Callable[[Path, Store], dict]  # writes the files into the partial directory; -> summary
    budget: str | None = None
    seeds: tuple[int, ...] = ()
    requires: tuple["Recipe", ...] = ()  # made first (their keys belong in `components`)
    check: Callable[[Store], None] | None = None  # before anything is written; raises on a problem
    record: dict = field(default_factory=dict)  # facts for the manifest beside the summary
    summary_file: bool = True  # also write the summary as summary.json
    on_wait: Callable[[str], None] | None = None  # told once if another process holds the lock
    # The partial directory holds what cannot be made again (a person's played steps): like a
    # training run's, it is neither cleared before a build nor removed after a failed or stopped
    # one, so the next `esr play` can commit it as incomplete. Any other artifact starts afresh.
    keeps_partial: bool = False
    # Runs it reads that are still training ("LABEL: epoch E of T"): a preview, drawn by
    # `preview` outside the store and never committed, since those runs have not said their last.
    unfinished: tuple[str, ...] = ()

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"unknown artifact kind {self.kind!r}; kinds: {', '.join(KINDS)}")

    @property
    def key(self) -> str:
        return content_key(self.components)


def preview(recipe: Recipe, out_dir: Path, store: Store) -> dict:
    """Build `recipe` into `out_dir`, outside the store (a figure of unfinished runs). -> summary"""
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = recipe.build(out_dir, store)
    if recipe.summary_file:
        atomic_write_text(out_dir / SUMMARY_FILE, json.dumps(summary, indent=2, default=float))
    return summary


def read_summary(path: Path) -> dict:
    """An artifact's summary.json, read bounded (a store's files may come from an archive)."""
    return read_json(path / SUMMARY_FILE, MAX_SUMMARY_BYTES)


def summary_or_empty(path: Path) -> dict:
    """An artifact's summary as a mapping; {} where it is missing, damaged or not a mapping (for
    tables that read many artifacts and show what one lacks as a dash)."""
    try:
        summary = read_summary(path)
    except (StoreError, OSError, ValueError):
        return {}
    return summary if isinstance(summary, dict) else {}


class Built(NamedTuple):
    path: Path
    cached: bool  # True: it was in the store already

    def summary(self) -> dict:
        return read_summary(self.path)


def ensure(recipe: Recipe, store: Store) -> Built:
    """The committed artifact of `recipe`, made (or resumed) if the store lacks it."""
    if recipe.unfinished:
        raise ValueError(f"{recipe.name} reads unfinished runs ({'; '.join(recipe.unfinished)}): draw it with preview()")
    key = recipe.key
    hit = store.lookup(recipe.kind, key)
    if hit:
        return Built(hit, True)
    if recipe.check:
        recipe.check(store)
    for needed in recipe.requires:
        ensure(needed, store)

    def make() -> Path:
        starts_afresh = recipe.kind != RUN_KIND and not recipe.keeps_partial
        if starts_afresh:  # what a build killed outright (SIGKILL) left
            shutil.rmtree(store.partial_path(recipe.kind, key), ignore_errors=True)
        pending = {"kind": recipe.kind, "name": recipe.name, "key": key, "budget": recipe.budget,
                   "seeds": list(recipe.seeds)}
        # Every start and resume is a session (checkout, time, a run's device), kept in order:
        # a run resumed on another machine or from another checkout of the same training code
        # says so. "commit" and "device" name the first, where it was made.
        sessions = provenance.with_session(provenance.carried_sessions(read_pending(store.partial_path(recipe.kind, key))),
                                           provenance.session(with_device=recipe.kind == RUN_KIND))
        first = {k: sessions[0][k] for k in ("commit", "device") if k in sessions[0]}
        # The key components are in pending.json from the start: an unfinished run can then be
        # found by a longer run of the same lineage (runs.adopt_shorter_run).
        record = {**pending, "key_components": recipe.components, **first, "sessions": sessions}
        out = store.begin(recipe.kind, key, record)
        started = time.time()
        try:
            summary = recipe.build(out, store)
        except (Interrupted, TimeLimitReached) as e:
            # Saved at a chunk boundary on purpose: a listing says "stopped", not "failed" (a
            # partial run that nobody holds and that says nothing was killed). The next start
            # writes pending.json afresh, without this mark.
            why = "interrupted" if isinstance(e, Interrupted) else "its time limit"
            store.begin(recipe.kind, key, {**record, "sessions": provenance.with_wall(sessions, time.time() - started),
                                           "stopped": {"epoch": e.epoch, "why": why, "at": provenance.now_iso()}})
            raise
        except BaseException as e:
            # Only a training run resumes from what it wrote, and only a played episode is
            # recovered from it; any other artifact (an evaluation, a figure, a cloned human)
            # starts again, so an interrupted or failed one leaves nothing.
            if starts_afresh:
                shutil.rmtree(out, ignore_errors=True)
            elif isinstance(e, Diverged):
                # Kept for inspection, and marked: a listing says "diverged", and nothing advises
                # running it again as if it had only stopped. The next start writes pending.json
                # afresh, without this mark.
                store.begin(recipe.kind, key, {**record, "sessions": provenance.with_wall(sessions, time.time() - started),
                                               "diverged": {"epoch": e.epoch, "what": str(e), "at": provenance.now_iso()}})
            raise
        if recipe.summary_file:
            atomic_write_text(out / SUMMARY_FILE, json.dumps(summary, indent=2, default=float))
        manifest = provenance.complete_manifest(pending, recipe.components, summary, **first,
                                                sessions=provenance.with_wall(sessions, time.time() - started), **recipe.record)
        return store.commit(recipe.kind, key, manifest)

    path, cached = store.get_or_make(recipe.kind, key, make, on_wait=recipe.on_wait)
    return Built(path, cached)
