"""Sweeps: run every training run of a suite, here or on a SLURM cluster (docs/cluster.md).

Executors:
  local           in this process, one run after another (artifacts.ensure of runs.run_recipe): the default;
  slurm           one SLURM job per run, submitted as one job array through submitit;
  submitit-local  the same jobs as `slurm`, started as local processes by submitit (all at
                  once): checks a suite's job path without a cluster.

Every job is the equivalent of `esr train SPEC --budget B --set ...` with the same store root.
The store does the coordination: a committed key is skipped, a run whose lock is held is left
to its holder, and a re-submitted or duplicated job waits on the lock and then finds the
artifact committed. Job ids go to a small state file, <store>/sweeps/<suite>-<budget>-<key>.json,
so `--status` can tell a queued or crashed job from a run that was never submitted.

A store may be shared, so nothing read from it here is unpickled: each job writes how it ended
as a small JSON record beside submitit's files (`<job id>_esr_outcome.json`), and status reads
that, bounded, and only from a job folder inside the store's own sweeps/ folder. Submitit's
result pickles are left unread.
"""

from __future__ import annotations

import errno
import fcntl
import io
import json
import os
import re
import subprocess
import time
from contextlib import contextmanager, redirect_stderr
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Optional

from pydantic import ValidationError
from rich.console import Console
from rich.table import Table
from rich.text import Text

from esr_cli.common import bounded_files, specs
from esr_cli.common.printing import plain_console, printable, tagged
from esr_cli.common.stops import SAME_AGAIN, diverged_at
from esr_cli.recipes import check_columns
from esr_cli.recipes.suite import Run, SlurmOptions, Suite, SuiteError, load as load_suite
from esr_cli.storage import provenance
from esr_cli.storage.artifacts import ensure
from esr_cli.storage.store import RUN_KIND, Store, StoreError, atomic_write_text, lock_holder, open_lock, read_pending

EXECUTORS = ("local", "slurm", "submitit-local")
STATES = ("done", "running", "queued", "stopped", "failed", "missing")
SWEEPS_DIR = "sweeps"
OUTCOME_SUFFIX = "_esr_outcome.json"  # a job's own record of how it ended, beside submitit's files
MAX_RECORD_BYTES = 1 << 20  # far above any state file or outcome record esr writes
_JOB_ID = re.compile(r"\w[\w+-]*")  # a SLURM job (4242, 4242_0) or a local pid: never a path

# SLURM job states (sacct) grouped by what they mean for a run that is not committed.
# UNKNOWN (neither sacct nor squeue answers) counts as queued: a sweep then does not submit the run twice.
_QUEUED = {"PENDING", "REQUEUED", "REQUEUE_FED", "REQUEUE_HOLD", "CONFIGURING", "SUSPENDED", "RESIZING", "UNKNOWN"}
_ALIVE = {"RUNNING", "COMPLETING", "STAGE_OUT", "SIGNALING"}
WAIT_POLL_S = 2.0  # how often a waiting sweep looks at a job that has not ended


class SweepError(Exception):
    """A sweep that cannot proceed (e.g. no SLURM here); `str()` is one line."""


@dataclass(frozen=True)
class JobStopped:
    """What a job returns when it reached its time budget first: saved at a chunk boundary,
    resumable. A job that ends this way succeeded; its run is *stopped*, not failed."""

    epoch: int
    total: int

    def __str__(self) -> str:
        return f"stopped at its time budget after epoch {self.epoch:,} of {self.total:,}; sweep again to continue"


__all__ = ["EXECUTORS", "JobStopped", "RunStatus", "SlurmOptions", "SweepError", "SweepResult", "SuiteError", "check_metrics",
           "known_metrics", "load_suite", "run_suite", "slurm_options", "status", "status_table"]


# ---------------------------------------------------------------- the state file
def state_path(store: Store, suite: Suite) -> Path:
    return store.root / SWEEPS_DIR / f"{suite.name}-{suite.budget}-{suite.key[:16]}.json"


def read_record(path: Path) -> Optional[dict]:
    """A JSON object esr wrote, or None where `path` is missing, a link, not a regular file (a
    FIFO would block), larger than any esr writes, or not a JSON object."""
    try:
        data = bounded_files.read_bytes(path, MAX_RECORD_BYTES)
    except (OSError, bounded_files.UnreadableInput):
        return None
    try:
        value = json.loads(data) if data else None
    except (ValueError, RecursionError):
        return None
    return value if isinstance(value, dict) else None


def read_state(store: Store, suite: Suite) -> dict:
    return read_record(state_path(store, suite)) or {}


@contextmanager
def _state_lock(store: Store, suite: Suite):
    """Two sweeps of one suite at once must not lose each other's job records."""
    path = state_path(store, suite).with_suffix(".lock")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = open_lock(path, create=True)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _record_jobs(store: Store, suite: Suite, executor: str, submitted: Iterable[tuple[Run, str, Path]]) -> None:
    with _state_lock(store, suite):
        state = read_state(store, suite)
        state.update({"suite": str(suite.path), "name": suite.name, "budget": suite.budget})
        jobs = state.setdefault("jobs", {})
        now = provenance.now_iso()
        for run, job_id, folder in submitted:
            jobs[run.key] = {"label": run.label, "executor": executor, "job_id": job_id,
                             "folder": str(folder), "submitted_at": now}
        atomic_write_text(state_path(store, suite), json.dumps(state, indent=2, sort_keys=True))


# ---------------------------------------------------------------- status
@dataclass(frozen=True)
class RunStatus:
    run: Run
    state: str  # one of STATES
    note: str = ""
    path: Optional[Path] = None  # the committed artifact (done) or the partial directory
    made_by: str = ""  # `--any-code`: the commit (and device) of the other code that made it


def _lock_holder(store: Store, key: str) -> Optional[str]:
    """Who holds the run's lock, or None. Probing takes a shared flock and drops it at once."""
    path = store.lock_path(RUN_KIND, key)
    try:
        fd = open_lock(path)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return None
    except OSError as e:
        if e.errno not in (errno.EAGAIN, errno.EACCES):
            raise
        return lock_holder(fd)
    finally:
        os.close(fd)  # also releases the probe's lock if it was taken


class _Refused(Exception):
    """A job record that status will not follow; `str()` says why, in one line."""


def _job_folder(store: Store, rec: object) -> Path:
    """The recorded job's folder, resolved, only where it lies inside the store's own sweeps/
    folder: the state file is a store file, and anyone who can write there could point it anywhere."""
    from submitit.core.utils import JobPaths

    if not (isinstance(rec, dict) and all(isinstance(rec.get(k), str) for k in ("job_id", "folder", "executor"))
            and _JOB_ID.fullmatch(rec["job_id"])):
        raise _Refused("its job record is damaged; not read")
    try:
        folder = Path(os.path.realpath(JobPaths(rec["folder"], job_id=rec["job_id"]).folder))
    except (ValueError, RuntimeError):  # a NUL byte in the path; ~user of no such user
        raise _Refused("its job record is damaged; not read") from None
    area = Path(os.path.realpath(store.root / SWEEPS_DIR))
    if not folder.is_relative_to(area):
        raise _Refused(f"its job folder {rec['folder']} is outside {area}; not read")
    return folder


def outcome_path(folder: Path, job_id: str) -> Path:
    return Path(folder) / f"{job_id}{OUTCOME_SUFFIX}"


def _last_line(text: str, default: str) -> str:
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    return (lines[-1] if lines else default)[:160]


def _from_outcome(outcome: dict) -> tuple[str, str]:
    """(state, detail) of a job from its own outcome record."""
    kind, epoch, total = outcome.get("outcome"), outcome.get("epoch"), outcome.get("total")
    if kind == "success":
        return "SUCCESS", ""
    if kind == "stopped" and isinstance(epoch, int) and isinstance(total, int):
        return "STOPPED", str(JobStopped(epoch, total))
    if kind == "interrupted" and isinstance(epoch, int):
        return "STOPPED", f"interrupted (SIGTERM: cancelled?) after epoch {epoch:,}; sweep again to continue"
    if kind == "error":
        return "ERROR", _last_line(str(outcome.get("error", "")), "job raised")
    return "ENDED", "its outcome record is unreadable"


def _job_outcome(store: Store, rec: object) -> tuple[str, str]:
    """(state, detail) of a recorded job: SUCCESS, STOPPED or ERROR from the job's own outcome
    record; else a SLURM state, RUNNING or GONE (a local job's process); ENDED (a result but no
    record: never unpickled); REFUSED (a record status does not follow)."""
    try:
        folder = _job_folder(store, rec)
    except _Refused as e:
        return "REFUSED", str(e)
    job_id = rec["job_id"]
    outcome = read_record(outcome_path(folder, job_id))
    if outcome is not None and outcome.get("job_id") == job_id:
        return _from_outcome(outcome)
    if (folder / f"{job_id}_0_result.pkl").exists():  # an older esr's job, or a planted pickle
        return "ENDED", "finished without esr's outcome record (its submitit result is not read)"
    if rec["executor"] == "slurm":
        return _slurm_state(rec["folder"], job_id)
    # submitit-local: the job id is the controller's pid.
    try:
        os.kill(int(job_id), 0)
        return "RUNNING", ""
    except (ProcessLookupError, ValueError):
        return "GONE", "the job's process ended without a result"
    except PermissionError:
        return "RUNNING", ""


def _quiet_submitit() -> None:
    """Off the cluster, or on one without accounting, submitit warns on every sacct call, on
    stdout (where a sweep prints its artifact paths); the states below say it once per run."""
    import logging

    logging.getLogger("submitit").setLevel(logging.ERROR)


def _slurm_state(folder: str, job_id: str) -> tuple[str, str]:
    import submitit

    _quiet_submitit()
    try:
        state = str(submitit.SlurmJob(folder=folder, job_id=job_id).state).upper()
    except Exception:  # noqa: BLE001 - sacct missing or refusing: the state is unknown
        state = "UNKNOWN"
    if state == "UNKNOWN":  # a cluster without accounting: sacct refuses, slurmctld still knows the job
        return _squeue_state(job_id)
    return state, ""


def _squeue_state(job_id: str) -> tuple[str, str]:
    """(state, detail) of a job from squeue, which asks slurmctld: it knows a job until MinJobAge
    (5 minutes by default) after it ended, and one it no longer knows is GONE. UNKNOWN where squeue
    cannot be asked (no SLURM here)."""
    try:
        proc = subprocess.run(["squeue", "-h", "-t", "all", "-j", job_id, "-o", "%T"],
                              capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        proc = None
    if proc is not None and proc.returncode == 0 and proc.stdout.split():
        return proc.stdout.split()[0].upper(), ""
    if proc is not None and (proc.returncode == 0 or "Invalid job id" in proc.stderr):
        return "GONE", "SLURM no longer knows the job, which left no outcome record"
    return "UNKNOWN", "SLURM state unknown here (no sacct or squeue?)"


_OVER = {"SUCCESS", "STOPPED", "GONE", "ENDED"}  # ended, not in error: the run's own files say more


def status(suite: Suite, store: Store) -> list[RunStatus]:
    """done: committed; running: its lock is held; queued: a recorded job not started yet;
    failed: a partial run nobody holds, or a recorded job that ended in error; missing: none of those.
    A job record status does not follow counts as no record, and the row says why."""
    jobs = read_state(store, suite).get("jobs")
    jobs = jobs if isinstance(jobs, dict) else {}
    return [_run_status(store, run, jobs.get(run.key)) for run in suite.runs]


def _run_status(store: Store, run: Run, rec: object) -> RunStatus:
    hit = store.lookup(RUN_KIND, run.key)
    if hit:
        return RunStatus(run, "done", path=hit)
    partial = store.partial_path(RUN_KIND, run.key)
    try:
        holder = _lock_holder(store, run.key)
    except StoreError as e:  # something not a lock file in the lock's place: this run cannot start
        return RunStatus(run, "failed", str(e), partial if partial.is_dir() else None)
    if holder:
        return RunStatus(run, "running", holder, partial)
    job_state, detail = _job_outcome(store, rec) if rec is not None else ("", "")
    if job_state == "REFUSED":
        row = _job_status(run, partial, None, "", "")
        return replace(row, note="; ".join(filter(None, (f"job record refused: {detail}", row.note))))
    return _job_status(run, partial, rec, job_state, detail)


def _job_status(run: Run, partial: Path, rec: Optional[dict], job_state: str, detail: str) -> RunStatus:
    """A run neither committed nor held: what its job and its partial directory say."""
    job = f"job {rec['job_id']}" if rec else ""
    if job_state == "STOPPED" and partial.is_dir():
        return RunStatus(run, "stopped", f"{job}: {detail}", partial)
    if job_state == "ERROR" or (job_state and job_state not in _QUEUED | _ALIVE | _OVER):
        return RunStatus(run, "failed", f"{job} {job_state}: {detail}".rstrip(": "), partial if partial.is_dir() else None)
    if job_state in _QUEUED:
        return RunStatus(run, "queued", f"{job} {job_state}: {detail}".rstrip(": "))
    if job_state in _ALIVE:
        return RunStatus(run, "running", f"{job} started")
    if partial.is_dir() and isinstance(stop := (read_pending(partial) or {}).get("stopped"), dict):
        note = f"stopped ({stop.get('why')}) after epoch {stop.get('epoch')}; sweep again (or esr train) to continue it"
        return RunStatus(run, "stopped", f"{job}: {note}" if job else note, partial)
    if partial.is_dir() and (diverged := diverged_at(read_pending(partial))):
        note = f"diverged: {diverged}; {SAME_AGAIN}"
        return RunStatus(run, "failed", f"{job}: {note}" if job else note, partial)
    if partial.is_dir():
        note = "partial run with no live writer; sweep again (or esr train) to resume it"
        return RunStatus(run, "failed", f"{job} {job_state}: {note}" if job else note, partial)
    if job_state == "SUCCESS":
        # The job committed a different key: the code or toolchain changed since.
        return RunStatus(run, "missing", f"{job} finished, but under another key (code changed since?)")
    return RunStatus(run, "missing", f"{job} {job_state}: {detail}".strip(" :") if job else "")


_STYLE = {"done": "green", "running": "cyan", "queued": "blue", "stopped": "magenta", "failed": "red", "missing": "yellow"}


def status_table(suite: Suite, rows: list[RunStatus]) -> Table:
    counts = {s: sum(r.state == s for r in rows) for s in STATES}
    summary = ", ".join(f"{n} {s}" for s, n in counts.items() if n)
    table = Table(title=f"suite {suite.name} ({suite.budget}): {summary}")
    for col in ("run", "key", "state", "detail"):
        table.add_column(col, overflow="fold")
    for r in rows:
        detail = (f"{r.path} ({r.note})" if r.note else str(r.path)) if r.state == "done" else r.note
        table.add_row(r.run.label, r.run.key[:12], Text(r.state, style=_STYLE[r.state]), str(detail))
    return table


def status_json(rows: list[RunStatus]) -> list[dict]:
    return [{"run": r.run.label, "spec": str(r.run.spec_path), "sets": list(r.run.sets), "key": r.run.key,
             "state": r.state, "detail": r.note, "path": str(r.path) if r.path else None} for r in rows]


DEFAULT_RESULT_METRICS = ("return", "success")
_NOT_METRICS = ("epoch", "env_steps")  # bookkeeping columns of metrics.jsonl


def known_metrics(suite: Suite, store: Store, rows: Optional[list[RunStatus]] = None) -> tuple[str, ...]:
    """Every metric `--metric` may name for this suite: the trainer's own, those each registered
    method declares (ESR's with inferred human actions too), and whatever the suite's committed
    runs logged (a learning human's, for one)."""
    from esr_cli.model.methods.registry import METHODS
    from esr_cli.model.train import BASE_METRICS
    from esr_cli.storage.finals import read_rows

    names = dict.fromkeys(BASE_METRICS)
    for cls in METHODS.values():
        names.update(dict.fromkeys(cls.all_metric_names))
    for r in rows if rows is not None else status(suite, store):
        if r.state == "done":
            logged = read_rows(r.path)
            names.update(dict.fromkeys(k for k in (logged[-1] if logged else {}) if k not in _NOT_METRICS))
    return tuple(names)


def check_metrics(suite: Suite, store: Store, metrics: tuple[str, ...], rows: Optional[list[RunStatus]] = None) -> None:
    """Raise SuiteError naming the first of `metrics` that no run of this suite can log."""
    if set(metrics) <= set(DEFAULT_RESULT_METRICS):
        return
    known = known_metrics(suite, store, rows)
    for m in metrics:
        if m not in known:
            raise SuiteError("--metric", "", f"unknown metric {m!r}; known: {', '.join(known)}")


def _trained(spec_part: object, budget: object) -> str:
    """What a run trained, whatever code trained it: its spec's training part and budget."""
    return json.dumps({"spec": spec_part, "budget": budget}, sort_keys=True)


def _trained_as_read(comps: dict) -> Optional[str]:
    """What a run trained (`_trained`), read from its key components (what its key digests) as
    this code reads a spec: a field added since the run was made reads at its default, the
    behaviour the run had (new fields default to the behaviour before them; docs/specs.md), as
    the reproduction report reads runs. None where this code no longer reads them as a spec."""
    part, budget = comps.get("spec"), comps.get("budget")
    if not isinstance(part, dict):
        return None
    try:
        spec = specs.validate({**part, "name": "run", **({} if budget is None else {"budget": budget})}, "key components")
    except specs.SpecError:
        return None
    return _trained(spec.training_part(), spec.budget)


def finished_runs_by_training(store: Store) -> dict[str, tuple[str, Path, provenance.Origin]]:
    """The store's finished runs by what they trained (`_trained_as_read`): key, path and origin
    of the newest of each. Runs made by other training code (another commit, device or jax) have
    other keys; this is how `--any-code` finds them. A run whose key components this code no
    longer reads as a spec is passed over."""
    found: dict[str, tuple[float, str, Path, provenance.Origin]] = {}
    for entry in store.entries((RUN_KIND,)):
        info = entry.manifest
        if entry.status != "complete" or not isinstance(info, dict):
            continue
        comps = info.get("key_components")
        what = _trained_as_read(comps) if isinstance(comps, dict) else None
        if what is None:
            continue
        created = provenance.created_order(info)
        if what not in found or created > found[what][0]:
            found[what] = (created, entry.key, entry.path, provenance.origin(info))
    return {what: hit[1:] for what, hit in found.items()}


def _made_elsewhere(rows: list[RunStatus], store: Store) -> list[Optional[tuple[str, Path, str]]]:
    """For each row not done under this code, the finished run of exactly its spec and budget that
    other training code made, where the store has one: (key, path, "commit X, device"); else None."""
    if all(r.state == "done" for r in rows):
        return [None] * len(rows)
    index = finished_runs_by_training(store)
    return [None if r.state == "done" else _found_elsewhere(index, r.run.spec) for r in rows]


def finished_elsewhere(spec, store: Store) -> Optional[tuple[str, Path, str]]:
    """A finished run of exactly `spec` (its training part and budget) that other training code
    made: (key, path, "commit X, device"), or None. For a run this code is about to train."""
    return _found_elsewhere(finished_runs_by_training(store), spec)


def _found_elsewhere(index: dict, spec) -> Optional[tuple[str, Path, str]]:
    hit = index.get(_trained(spec.training_part(), spec.budget))
    if hit is None:
        return None
    key, path, made = hit
    return key, path, f"commit {made.commit[:7] if made.commit else 'unknown'}" + (f", {made.device}" if made.device else "")


def with_runs_made_elsewhere(rows: list[RunStatus], store: Store) -> list[RunStatus]:
    """Each row not done under this code taken from a finished run of exactly its spec and budget
    made by other training code, where the store has one; the row's note names that run's commit
    and device."""
    return [r if hit is None else
            RunStatus(replace(r.run, key=hit[0]), "done", f"made by other code: {hit[2]}", hit[1], made_by=hit[2])
            for r, hit in zip(rows, _made_elsewhere(rows, store))]


def noting_runs_made_elsewhere(rows: list[RunStatus], store: Store) -> list[RunStatus]:
    """Each missing row whose spec and budget other training code has finished, its note naming
    that run: after a checkout moves on every key changes, and a researcher should see that the
    run is there (`--any-code` reads it) before training it again for hours."""
    return [r if hit is None or r.state != "missing" else
            replace(r, note="; ".join(filter(None, (r.note, f"{hit[0][:12]} made by other code ({hit[2]}): "
                                                            "--any-code reads it; a sweep trains it again"))))
            for r, hit in zip(rows, _made_elsewhere(rows, store))]


def _shown_from(run: Run, base: Path) -> Run:
    """`run` with its spec path relative to `base` where it lies inside it (for commands printed
    in a page that any checkout reads, e.g. `esr tables`)."""
    try:
        return replace(run, spec_path=run.spec_path.relative_to(base))
    except ValueError:
        return run


def results(suite: Suite, store: Store, metrics: tuple[str, ...] = DEFAULT_RESULT_METRICS,
            checks: tuple[str, ...] = (), any_code: bool = False, esr: Optional[str] = None,
            paths_from: Optional[Path] = None) -> list[dict]:
    """Each run's final value of each metric (return and success unless told; mean +- SE across
    seeds, esr_cli.storage.finals) and wall time, read from the committed artifacts; a metric a run does
    not log is left out of its row; runs not done carry their state and the command. A metric
    no run of the suite can log is refused (SuiteError). With `checks` (names of
    check_columns.REGISTRY: "exact", "diagnosis", "play_check", "eval"), each done run a check applies to also carries
    its seeds' checks of that kind as the store holds them, under the check's name, and the
    commands that make what is missing, under NAME_todo. With `any_code`, a run this code
    has not made is read from a run of the same spec made by other code (`with_runs_made_elsewhere`),
    its row saying so in `made_by`. The commands of missing runs and checks call esr as `esr`
    says (default: as this store is reached, Store.invocation) with spec paths relative to
    `paths_from` when given."""
    from esr_cli.storage.finals import read_rows, run_finals

    esr = esr or store.invocation()

    groups = check_columns.chosen(checks)
    for group in groups:
        why = group.refusal(suite)
        if why:
            raise SuiteError(group.option, "", why)
    rows = status(suite, store)
    if any_code:
        rows = with_runs_made_elsewhere(rows, store)
    if paths_from is not None:
        rows = [replace(r, run=_shown_from(r.run, paths_from)) for r in rows]
    check_metrics(suite, store, metrics, rows)
    stored: dict = {}  # each kind of check's artifacts (by its reader), read once for the whole table
    out = []
    for r in rows:
        row = {"run": r.run.label, "method": r.run.spec.method.kind, "key": r.run.key, "state": r.state}
        if r.made_by:
            row["made_by"] = r.made_by
        if r.state == "done":
            last = read_rows(r.path)[-1:] if metrics != DEFAULT_RESULT_METRICS else [dict.fromkeys(metrics)]
            logged = set(last[0]) if last else set()  # no sound epoch logged: every metric shows no value
            wall_s, wall_whole = provenance.wall_time(store.read_manifest(r.path))
            row.update(run_finals(r.path, tuple(m for m in metrics if m in logged)),
                       wall_s=wall_s, wall_whole=wall_whole, path=str(r.path))
            for group in groups:
                if group.applies(r.run.spec):
                    if group.read not in stored:  # --diagnose and --play read the same artifacts
                        stored[group.read] = group.read(store)
                    row[group.name], row[f"{group.name}_todo"] = group.cells(r.run, suite.budget, esr, stored[group.read])
        else:
            row["command"] = r.run.command(suite.budget, esr)
        out.append(row)
    return out


def _pm(row: dict, name: str, digits: int) -> str:
    from esr_cli.common.stats import format_summary

    return format_summary(row[name], digits)


def _cell(row: dict, name: str) -> str:
    if name not in row:
        return "—"  # the run does not log this metric
    return _pm(row, name, 2 if name == "return" else 3)


def _what(metrics: tuple[str, ...]) -> str:
    return ", ".join(metrics[:-1]) + f" and {metrics[-1]}" if len(metrics) > 1 else metrics[0]


OTHER_CODE_NOTE = ("A run followed by (commit ...) was made by that commit's training code, not this checkout's "
                   "(--any-code: the same spec, budget and seeds).")


def _label(r: dict) -> str:
    """The run's cell: its label, and where it was made when that was other code (`--any-code`)."""
    return r["run"] + (f" ({r['made_by']})" if r.get("made_by") else "")


def _check_cells(r: dict, checks: tuple[str, ...]) -> list[str]:
    """A row's cells of the checks asked for ('' where a check does not apply to the run)."""
    return [r[g.name][c] if g.name in r else "" for g in check_columns.chosen(checks) for c in g.columns]


def _check_heads(checks: tuple[str, ...]) -> list[str]:
    return [head for g in check_columns.chosen(checks) for head in g.columns.values()]


def _check_todo(rows: list[dict], checks: tuple[str, ...]) -> list[str]:
    # once each: two checks read from the same artifacts (--diagnose, --play) name the same commands
    return list(dict.fromkeys(line for g in check_columns.chosen(checks) for r in rows for line in r.get(f"{g.name}_todo", ())))


def _wall(row: dict) -> str:
    """A run's working time; '≥' where some session of a resumed run did not record its own."""
    if row.get("wall_s") is None:
        return ""
    return f"{'' if row.get('wall_whole', True) else '≥ '}{row['wall_s']:.0f} s"


def _check_notes(checks: tuple[str, ...]) -> list[str]:
    return [g.note for g in check_columns.chosen(checks)]


def results_table(suite: Suite, rows: list[dict], metrics: tuple[str, ...] = DEFAULT_RESULT_METRICS,
                  checks: tuple[str, ...] = ()) -> Table:
    table = Table(title=f"suite {suite.name} ({suite.budget}): final {_what(metrics)}, mean ± SE and IQM "
                        "[95% bootstrap CI] across seeds (last 10% of epochs)")
    for col in ("run", "method", "seeds", *metrics, "wall", *_check_heads(checks)):
        table.add_column(col, overflow="fold")
    for r in rows:
        if r["state"] == "done":
            wall = _wall(r)
            table.add_row(_label(r), r["method"], str(r["seeds"]), *(_cell(r, m) for m in metrics), wall, *_check_cells(r, checks))
        else:
            table.add_row(r["run"], r["method"], "", Text(r["state"], style=_STYLE[r["state"]]), *[""] * len(metrics),
                          *_check_cells(r, checks))
    return table


def table_notes(rows: list[dict], checks: tuple[str, ...] = ()) -> list[str]:
    """What a plain table has below it: which runs other code made (`--any-code`), the note on
    each check's cells, and the commands of the missing checks."""
    notes = [OTHER_CODE_NOTE] if any("made_by" in r for r in rows) else []
    todo = _check_todo(rows, checks)
    return notes + _check_notes(checks) + (["Missing from the store, made by:", *todo] if todo else [])


def results_markdown(suite: Suite, rows: list[dict], metrics: tuple[str, ...] = DEFAULT_RESULT_METRICS,
                     checks: tuple[str, ...] = ()) -> str:
    heads = (*metrics, "wall", *_check_heads(checks))
    lines = [f"Suite `{suite.name}`, budget `{suite.budget}`: final {_what(metrics)}, mean ± SE and "
             "the interquartile mean [95% stratified bootstrap interval] across seeds (each seed's last 10% of epochs).", "",
             "| run | method | seeds | " + " | ".join(heads) + " |", "|---|---|---|" + "---|" * len(heads)]
    for r in rows:
        if r["state"] == "done":
            cells = [_label(r), r["method"], str(r["seeds"]), *(_cell(r, m) for m in metrics), _wall(r), *_check_cells(r, checks)]
        else:
            cells = [r["run"], r["method"], "", f"{r['state']}: `{r['command']}`", *[""] * (len(heads) - 1)]
        lines.append("| " + " | ".join(map(_markdown_cell, cells)) + " |")
    if any("made_by" in r for r in rows):
        lines += ["", OTHER_CODE_NOTE]
    for note in _check_notes(checks):
        lines += ["", note]
    todo = _check_todo(rows, checks)
    if todo:
        lines += ["", "Missing from the store, made by:", "", "```bash", *map(printable, todo), "```"]
    return "\n".join(lines)


def _markdown_cell(text: str) -> str:
    """A table cell that stays one cell of one row whatever a store or suite put in it: control
    characters (a newline too) as escapes, '|' escaped."""
    return printable(text).replace("|", "\\|")


# ---------------------------------------------------------------- running
@dataclass
class SweepResult:
    suite: Suite
    paths: list[Optional[Path]]  # per run, in suite order: the committed artifact, or None
    submitted: list[tuple[Run, str]] = field(default_factory=list)  # (run, job id); local: "local"
    skipped: list[RunStatus] = field(default_factory=list)  # done, running or queued before the sweep
    failed: list[tuple[Run, str]] = field(default_factory=list)
    stopped: list[tuple[Run, str]] = field(default_factory=list)  # (run, why): at its time budget, resumable

    @property
    def complete(self) -> bool:
        return all(p is not None for p in self.paths)


def job_time_budget_s(time_min: int) -> float:
    """Seconds a job trains before it stops at a chunk boundary: its wall-clock limit less a
    margin (5%, at least a minute) for start-up and exit, so the scheduler never kills a chunk
    half-done and the next sweep resumes from the job's last chunk."""
    limit = 60.0 * time_min
    return max(0.0, limit - max(60.0, 0.05 * limit))


def train_job(spec_path: str, budget: str, sets: list[str], store_root: str,
              stop_after_s: float | None = None) -> str | JobStopped:
    """One job: `esr train spec_path --budget budget --set ... --stop-after stop_after_s`
    in-process. -> the artifact path, or JobStopped if the time budget came first (the run is
    saved at a chunk boundary). Module-level so that submitit pickles it by reference. How it
    ended is also written as the job's outcome record, which is what status reads."""
    from esr_cli.common.stops import Interrupted

    try:
        result = _train(spec_path, budget, sets, store_root, stop_after_s)
    except Interrupted as e:  # SIGTERM (scancel, preemption): saved at a chunk boundary, resumable
        _record_outcome({"outcome": "interrupted", "epoch": e.epoch})
        raise
    except Exception as e:
        _record_outcome({"outcome": "error", "error": f"{type(e).__name__}: {e}"[-2000:]})
        raise
    if isinstance(result, JobStopped):
        _record_outcome({"outcome": "stopped", "epoch": result.epoch, "total": result.total})
    else:
        _record_outcome({"outcome": "success", "path": result})
    return result


def _record_outcome(record: dict) -> None:
    """Write `record` as <job folder>/<job id>_esr_outcome.json, atomically. Outside a submitit
    job (train_job called directly) there is no job to record."""
    import submitit

    try:
        env = submitit.JobEnvironment()
    except RuntimeError:
        return
    atomic_write_text(outcome_path(env.paths.folder, env.job_id), json.dumps({"job_id": env.job_id, **record}))


def _train(spec_path: str, budget: str, sets: list[str], store_root: str, stop_after_s: float | None) -> str | JobStopped:
    from esr_cli.common.stops import TimeLimitReached
    from esr_cli.recipes import runs  # jax and the training core load only where a run is made here

    stop_at = None if stop_after_s is None else time.monotonic() + stop_after_s
    spec = specs.load(spec_path, budget, sets)
    try:
        return str(ensure(runs.run_recipe(spec, plain_console(stderr=True), stop_at=stop_at), Store(store_root)).path)
    except TimeLimitReached as e:
        return JobStopped(e.epoch, e.total)


def _executor(kind: str, folder: Path, suite: Suite, opts: SlurmOptions):
    import submitit

    ex = submitit.AutoExecutor(folder=folder / "%j", cluster="slurm" if kind == "slurm" else "local")
    params = {"name": f"esr-{suite.name}", "timeout_min": opts.time_min, "cpus_per_task": opts.cpus, "mem_gb": opts.mem_gb}
    if kind == "slurm":
        params.update(gpus_per_node=opts.gpus, slurm_partition=opts.partition, slurm_account=opts.account,
                      slurm_qos=opts.qos, slurm_array_parallelism=opts.array_parallelism,
                      slurm_setup=list(opts.setup) or None, slurm_additional_parameters=dict(opts.additional) or None)
    ex.update_parameters(**params)
    return ex


_SLURM_FLAGS = {"time_min": "--time-min", "mem_gb": "--mem-gb"}  # the rest: --name


def slurm_options(base: SlurmOptions, overrides: Optional[dict], source: str) -> SlurmOptions:
    """`base` with the command line's `overrides` (None: not given), validated. A problem is a
    one-line SuiteError naming the option as it was given (--mem-gb, or slurm.mem_gb in the suite)."""
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    try:
        return SlurmOptions.model_validate({**base.model_dump(), **given})
    except ValidationError as e:
        err, msg = specs.first_problem(e)
        def where(loc: tuple) -> str:
            field = str(loc[0]) if loc else ""
            return _SLURM_FLAGS.get(field, f"--{field}") if field in given else ("slurm." + ".".join(map(str, loc))).rstrip(".")

        raise SuiteError(source, where(tuple(err["loc"])), msg + specs.other_problems(e, where)) from None


def run_suite(
    suite: Suite | str | Path,
    budget: str = "paper",
    executor: str = "local",
    store: Store | str | Path = "artifacts",
    console: Optional[Console] = None,
    wait: Optional[bool] = None,
    slurm: Optional[dict] = None,
) -> SweepResult:
    """Run or submit every run of `suite` that the store lacks. -> SweepResult (paths per run).

    `wait`: block until submitted jobs end (default: yes except for `slurm`). `slurm`: options
    that replace the suite file's `slurm:` values (partition, time_min, gpus, cpus, mem_gb, ...).
    Raises SuiteError (bad suite or spec; nothing has run) or SweepError.
    """
    console = console or plain_console(stderr=True)
    store = store if isinstance(store, Store) else Store(store)
    # The command line's own mistakes first: loading a suite builds every run.
    if executor not in EXECUTORS:
        raise SuiteError("--executor", "", f"unknown executor {executor!r}; known: {', '.join(EXECUTORS)}")
    if not isinstance(suite, Suite):
        slurm_options(SlurmOptions(), slurm, str(suite))  # before loading builds every run
        suite = load_suite(suite, budget)
    elif suite.budget != budget:
        raise SuiteError(str(suite.path), "--budget", f"the suite was loaded for budget {suite.budget!r}, not {budget!r}")
    opts = slurm_options(suite.slurm, slurm, str(suite.path))
    wait = executor != "slurm" if wait is None else wait
    store.ensure_writable()

    before = status(suite, store)
    result = SweepResult(suite, [None] * len(suite.runs))
    if executor == "local":
        # artifacts.ensure waits on a run another process holds, so nothing is skipped but the done.
        todo = [s for s in before if s.state != "done"]
    else:
        todo = [s for s in before if s.state in ("missing", "stopped", "failed")]
    # A run that diverged diverges again (training is deterministic): named, not run again
    # (`esr train` runs one again on purpose).
    diverged = [s for s in todo if s.path is not None and s.path.is_dir() and diverged_at(read_pending(s.path))]
    todo = [s for s in todo if s not in diverged]
    result.failed += [(s.run, f"{s.note} (not run again by a sweep; `esr train` runs it again)") for s in diverged]
    todo_keys = {s.run.key for s in todo} | {s.run.key for s in diverged}
    result.skipped = [s for s in before if s.run.key not in todo_keys]
    n_done = sum(s.state == "done" for s in before)
    console.print(f"suite {suite.name} ({suite.budget}): {len(suite.runs)} run(s); {n_done} done, "
                  f"{len(result.skipped) - n_done} running or queued, "
                  + (f"{len(diverged)} diverged (not run again), " if diverged else "")
                  + f"{len(todo)} to {'run' if executor == 'local' else 'submit'}"
                  + (f" ({suite.duplicates} duplicate(s) dropped)" if suite.duplicates else ""))
    elsewhere = sum(hit is not None for hit in _made_elsewhere(todo, store))
    if elsewhere:  # every key changed with the code: say so before hours of training again
        console.print(f"{elsewhere} of them finished under other training code (`sweep --status` names them, "
                      f"`sweep --results --any-code` reads them); this code trains them again")

    if executor == "local":
        _check_local_runs_fit(todo)  # all of them before the first trains for hours
        _run_local(todo, store, console, result)
    elif todo:
        _submit(todo, executor, opts, suite, store, console, result, wait)

    for i, run in enumerate(suite.runs):
        result.paths[i] = store.lookup(RUN_KIND, run.key)
    return result


def _check_local_runs_fit(todo: list[RunStatus]) -> None:
    """Raise ResourceError, naming the run, if any run here would not fit this machine's memory."""
    from esr_cli.runner.resources import ResourceError, check_run_fits

    for s in todo:
        try:
            check_run_fits(s.run.spec)
        except ResourceError as e:
            raise ResourceError(f"{s.run.label}: {e} (nothing of the suite has run)") from None


def _run_local(todo: list[RunStatus], store: Store, console: Console, result: SweepResult) -> None:
    from esr_cli.common.stops import Interrupted
    from esr_cli.model.train import release_compiled
    from esr_cli.recipes import runs  # jax and the training core load only where a run is made here

    for i, s in enumerate(todo, 1):
        console.print(tagged(f"({i}/{len(todo)})", "bold", f" {s.run.label}"))
        release_compiled()  # one spec's programs at a time
        try:
            ensure(runs.run_recipe(s.run.spec, console), store)
            result.submitted.append((s.run, "local"))
        except (Interrupted, KeyboardInterrupt):
            raise  # Ctrl-C ends the sweep; the same command resumes it
        except Exception as e:  # noqa: BLE001 - one failed run must not stop the others
            console.print(tagged("failed", "red", f": {s.run.label}: {type(e).__name__}: {e}"))
            result.failed.append((s.run, f"{type(e).__name__}: {e}"))


def _files_under(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*") if not p.is_dir()} if folder.is_dir() else set()


def _remove_new_files(folder: Path, earlier: set[Path]) -> None:
    """What a refused submission left in `folder` (submitit's job script and pickled calls, for
    jobs that do not exist), and the folder itself where it is then empty."""
    for p in _files_under(folder) - earlier:
        p.unlink(missing_ok=True)
    if folder.is_dir() and not any(folder.iterdir()):
        folder.rmdir()


def _submit(todo, executor, opts, suite, store, console, result, wait) -> None:
    logs = store.root.absolute() / SWEEPS_DIR / "logs" / state_path(store, suite).stem
    try:
        ex = _executor(executor, logs, suite, opts)
    except RuntimeError as e:  # submitit: no srun on this machine
        raise SweepError(f"{e} (submit from a SLURM login node, or use --executor local)") from None
    jobs = []
    earlier = _files_under(logs)
    try:
        # submitit prints sbatch's refusal itself before raising it; the error below names it once
        with redirect_stderr(io.StringIO()), ex.batch():  # one job array on SLURM
            for s in todo:
                jobs.append(ex.submit(train_job, str(s.run.spec_path), suite.budget, list(s.run.sets), str(store.root.absolute()),
                                         job_time_budget_s(opts.time_min)))
    except FileNotFoundError as e:
        _remove_new_files(logs, earlier)
        raise SweepError(f"cannot submit to SLURM from here ({e.filename or e} not found): run on a login node, "
                         "or use --executor local") from None
    except Exception as e:  # noqa: BLE001 - sbatch's own refusal (bad partition, limits): one line
        _remove_new_files(logs, earlier)
        raise SweepError(f"submission failed: {str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__}") from None
    _record_jobs(store, suite, executor, [(s.run, j.job_id, logs / "%j") for s, j in zip(todo, jobs)])
    result.submitted = [(s.run, j.job_id) for s, j in zip(todo, jobs)]
    console.print(f"submitted {len(jobs)} job(s) ({executor}): {', '.join(j.job_id for j in jobs)}; logs under {logs}")
    if not wait:
        return
    _quiet_submitit()
    for s, j in zip(todo, jobs):
        # Until it ends; its outcome comes from its own record, as for --status. submitit alone
        # would wait for ever on a job cancelled before it wrote a result where sacct is refused.
        rec = {"job_id": j.job_id, "folder": str(logs / "%j"), "executor": executor}
        while not j.done() and _job_outcome(store, rec)[0] in _QUEUED | _ALIVE:
            time.sleep(WAIT_POLL_S)
        state, detail = _job_outcome(store, rec)
        if state == "SUCCESS":
            console.print(tagged("done", "green", f": {s.run.label} (job {j.job_id})"))
        elif state == "STOPPED":
            console.print(tagged("stopped", "magenta", f": {s.run.label} (job {j.job_id}): {detail}"))
            result.stopped.append((s.run, detail))
        else:
            msg = detail if state == "ERROR" else f"{state}: {detail}".strip(" :") + f"; its log: {j.paths.stderr}"
            console.print(tagged("failed", "red", f": {s.run.label} (job {j.job_id}): {msg}"))
            result.failed.append((s.run, msg))
