"""What `esr ls` and `esr show` say about the store's artifacts, as plain data.

One row per artifact (`ls --json` prints these, docs/store.md lists the fields): its kind,
name, key, path, budget, seed count, status (complete, partial, stopped, diverged or damaged), for a
run the epochs done and asked, its final return (the one definition used everywhere: each
seed's mean over its last 10% of epochs, averaged over seeds; an unfinished run's so far;
other kinds: the return their summary names), when it was made, its method and environment,
and the `--set` values that make it from its spec file in experiments/ (None where no spec
file there resolves to it).
"""

from __future__ import annotations

from typing import Iterator

from esr_cli.common.numbers import as_number
from esr_cli.common.stops import diverged_at
from esr_cli.storage.store import RUN_KIND, Entry, Store, StoreError

FINAL_RETURN = ("final return: a run's mean over each seed's last 10% of epochs (so far, if unfinished), averaged "
                "over seeds, as in figures and reports")


def field(info, *path):
    """info[path[0]][path[1]]...; None where a level is missing or not an object (an imported
    manifest is only checked for the fields the store itself reads)."""
    for name in path:
        info = info.get(name) if isinstance(info, dict) else None
    return info


def status_of(entry: Entry) -> str:
    if entry.status == "complete" and entry.manifest is None:
        return "damaged"  # an unreadable manifest
    if entry.status == "partial" and isinstance((entry.manifest or {}).get("stopped"), dict):
        return "stopped"  # saved at a chunk boundary on purpose; the same command continues it
    if entry.status == "partial" and diverged_at(entry.manifest):
        return "diverged"  # the same command reaches the same non-finite value again
    return entry.status


def created_of(manifest: dict) -> str | None:
    created = manifest.get("created_at")
    if isinstance(created, str):
        return created
    sessions = manifest.get("sessions")
    first = sessions[0] if isinstance(sessions, list) and sessions and isinstance(sessions[0], dict) else {}
    started = first.get("started_at")
    return started if isinstance(started, str) else None


def overrides_of(entry: Entry) -> list[str] | None:
    """The --set values that make this run from experiments/<name>.yaml at its budget."""
    from esr_cli.recipes.targets import run_spec
    from esr_cli.report.reproduction import train_overrides

    spec_file = entry.path / "spec.yaml"
    if entry.kind != RUN_KIND or not spec_file.is_file():
        return None
    try:
        spec = run_spec(entry.path)  # only the spec its key was computed from
    except StoreError:
        return None
    found = train_overrides(spec, spec.budget)
    return None if found is None else found[1]


def metrics_problem(run_path) -> str | None:
    """Why a run's metrics.jsonl cannot be read at all (a FIFO, a device or a link in its place,
    a file larger than esr reads, a disk error), or None: `ls` and `show` name it in one line,
    where the run's epochs and return are left blank."""
    from esr_cli.storage.finals import UnreadableMetrics, read_rows

    try:
        read_rows(run_path)
    except UnreadableMetrics as e:
        return e.problem
    return None


def row(entry: Entry, with_overrides: bool = True) -> dict:
    from esr_cli.storage.finals import run_progress

    m = entry.manifest or {}
    seeds = m.get("seeds")
    out = {
        "kind": entry.kind,
        "name": m.get("name") if isinstance(m.get("name"), str) else None,
        "key": entry.key,
        "path": str(entry.path),
        "budget": m.get("budget") if isinstance(m.get("budget"), str) else None,
        "seeds": len(seeds) if isinstance(seeds, list) and seeds else None,
        "status": status_of(entry),
        "epochs": None,
        "epochs_total": None,
        "final_return": None,
        "return_of": None,
        "created": created_of(m),
        "method": m.get("method") if isinstance(m.get("method"), str) else field(m, "key_components", "spec", "method", "kind"),
        "env": m.get("env") if isinstance(m.get("env"), str) else field(m, "key_components", "spec", "env", "kind"),
        "overrides": None,
    }
    if entry.kind == RUN_KIND:
        done, ret = run_progress(entry.path)
        total = field(m, "key_components", "spec", "train", "epochs")
        out.update(epochs=done, epochs_total=total if isinstance(total, int) else None, final_return=ret,
                   return_of="final return (last 10% of epochs)")
        if with_overrides:
            out["overrides"] = overrides_of(entry)
    else:
        ret = as_number(field(m, "summary", "return", "mean"))
        if ret is not None:
            out["final_return"] = ret
            of = field(m, "summary", "return", "of")
            out["return_of"] = of if isinstance(of, str) else "mean episode return"
    return out


def rows(store: Store, kind: str | None = None, name: str | None = None, method: str | None = None,
         budget: str | None = None) -> Iterator[tuple[dict, Entry]]:
    """The rows of the artifacts that pass every filter given (each an exact match)."""
    for entry in store.entries():
        if kind and entry.kind != kind:
            continue
        r = row(entry, with_overrides=False)
        if (name and r["name"] != name) or (method and r["method"] != method) or (budget and r["budget"] != budget):
            continue
        if entry.kind == RUN_KIND:
            r["overrides"] = overrides_of(entry)
        yield r, entry
