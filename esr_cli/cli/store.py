"""Commands on the store's artifacts: esr ls, show, verify, export, import."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import List, Optional

import typer
from rich.table import Table
from rich.text import Text

from esr_cli.cli.app import Exit, app, check_budget, check_output_file, err, out, refuse_inside_store
from esr_cli.common import jsonl
from esr_cli.common.printing import print_table, printable, tagged
from esr_cli.common.stops import SAME_AGAIN, diverged_at
from esr_cli.storage.provenance import origin, wall_time
from esr_cli.storage.store import KINDS, RUN_KIND, Store


@app.command("ls")
def ls(
    ctx: typer.Context,
    kind: Optional[str] = typer.Option(None, "--kind", help=f"only this kind: {', '.join(KINDS)}"),
    name: Optional[str] = typer.Option(None, "--spec", help="only artifacts of this spec name (e.g. grid_2)"),
    method: Optional[str] = typer.Option(None, "--method", help="only runs of this method (esr, random, ave, ...)"),
    budget: Optional[str] = typer.Option(None, "--budget", "-b", help="only this budget: paper | quick | smoke"),
    as_json: bool = typer.Option(False, "--json", help="one JSON array of rows (fields: docs/store.md)"),
):
    """List the artifacts in the store (every column in full, on a terminal or piped)."""
    from esr_cli.report import listing

    if kind is not None and kind not in KINDS:
        raise Exit(2, f"--kind: unknown kind {kind!r}; kinds: {', '.join(KINDS)}")
    if budget is not None:
        check_budget(budget)
    found = list(listing.rows(ctx.obj.store, kind, name, method, budget))
    if as_json:
        out.print_json(jsonl.dumps([r for r, _ in found]))
        return
    if not found:
        filtered = any(v is not None for v in (kind, name, method, budget))
        err.print("no artifact matches those filters" if filtered and ctx.obj.store.root.is_dir() else
                  f"store {ctx.obj.store.root} is empty" if ctx.obj.store.root.is_dir() else
                  f"no store at {ctx.obj.store.root} (nothing has been made there yet)")
        return
    table = Table(caption=listing.FINAL_RETURN + "; another artifact's return is the one its summary names")
    for col in ("kind", "name", "key", "budget", "seeds", "status", "epochs", "final return", "created", "method",
                "overrides"):
        table.add_column(col, no_wrap=True)
    for r, entry in found:
        epochs = "" if r["epochs"] is None else (f"{r['epochs']:,}" if r["status"] == "complete" or r["epochs_total"] is None
                                                 else f"{r['epochs']:,} of {r['epochs_total']:,}")
        overrides = "" if entry.kind != RUN_KIND else ("(no spec file resolves to it)" if r["overrides"] is None
                                                      else " ".join(r["overrides"]) or "-")
        table.add_row(entry.kind, printable(r["name"] or "?"), r["key"][:12], printable(r["budget"] or "?"),
                      str(r["seeds"] or "?"), r["status"], epochs,
                      "" if r["final_return"] is None else f"{r['final_return']:.2f}", (r["created"] or "")[:16].replace("T", " "),
                      printable(r["method"] or ""), printable(overrides))
    print_table(out, table)  # piped, every cell in full
    for r, entry in found:  # one line each; the others are listed above all the same
        if listing.status_of(entry) == "damaged":
            err.print(f"damaged manifest: {entry.problem}")
        elif entry.kind == RUN_KIND and not r["epochs"] and (problem := listing.metrics_problem(entry.path)):
            err.print(f"unreadable metrics: {problem}")
        elif r["status"] == "complete" and r["epochs_total"] and (r["epochs"] or 0) < r["epochs_total"]:
            # a finished run logs every epoch: fewer is a file changed since (`esr verify` says which)
            err.print(f"metrics short of the run: {entry.path / 'metrics.jsonl'} logs {r['epochs'] or 0:,} of its "
                      f"{r['epochs_total']:,} epochs; `esr verify` checks its files")


@app.command()
def show(
    ctx: typer.Context,
    ref: str = typer.Argument(..., help="artifact key, key prefix or path (an unfinished run's too)", show_default=False),
    as_json: bool = typer.Option(False, "--json", help="the whole manifest (an unfinished run's pending.json), every component of the key included"),
):
    """Print what an artifact is (an unfinished run too): a readable summary, or its manifest
    (an unfinished run's pending.json) with --json."""
    from esr_cli.storage.store import Entry

    entry = ctx.obj.store.find(ref, include_partial=True)
    if entry.status == "complete":
        manifest = ctx.obj.store.read_manifest(entry.path)
        entry = Entry(entry.kind, entry.key, entry.path, "complete", manifest)
    else:  # what its pending.json says (read bounded); nothing is finished to check its files by
        manifest = entry.manifest if isinstance(entry.manifest, dict) else {}
    path = entry.path
    if as_json:  # stdout is the JSON alone, for a pipe (`| jq`); the path goes beside it
        unfinished = "" if entry.status == "complete" else "  (unfinished: its pending.json)"
        err.print(Text(printable(str(path)) + unfinished, style="bold"), highlight=False)
        out.print_json(jsonl.dumps(manifest))
        return
    from esr_cli.report import listing

    for label, value in _show_lines(listing.row(entry), manifest):
        out.print(f"{label + ':':<14} {printable(str(value))}", highlight=False, markup=False)


def _flat_scalars(tree, prefix: str = "", depth: int = 3) -> list[tuple[str, object]]:
    """The numbers and words of a summary as dotted names (lists of many values left out)."""
    if not isinstance(tree, dict) or depth == 0:
        return []
    out = []
    for k, v in tree.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out += _flat_scalars(v, name + ".", depth - 1)
        elif isinstance(v, float):
            out.append((name, f"{v:.4g}"))
        elif isinstance(v, (int, str, bool)) or (isinstance(v, list) and len(v) <= 8 and not any(isinstance(x, (dict, list)) for x in v)):
            out.append((name, v))
    return out


def _wall_time(manifest: dict) -> str | None:
    seconds, whole = wall_time(manifest)
    if seconds is None:
        return None
    return f"{seconds:,.0f} s" + ("" if whole else " at least (a session of this run did not record its own)")


def _show_lines(r: dict, manifest: dict) -> list[tuple[str, object]]:
    from esr_cli.report.listing import field

    lines = [("path", r["path"]), ("kind", r["kind"]), ("name", r["name"]), ("key", r["key"])]
    made = origin(manifest)  # a commit only when it is a git object name, every device it ran on
    for label, value in (("budget", r["budget"]), ("seeds", r["seeds"]), ("status", r["status"]),
                         ("method", r["method"]), ("env", r["env"]), ("created", r["created"]),
                         ("commit", made.commit), ("device", made.device),
                         ("wall time", _wall_time(manifest))):
        if value is not None:
            lines.append((label, value))
    if diverged := diverged_at(manifest):
        lines.append(("diverged", f"{diverged}; {SAME_AGAIN}"))
    if r["epochs"] is not None:
        lines.append(("epochs", f"{r['epochs']:,}" + (f" of {r['epochs_total']:,}" if r["epochs_total"] and r["epochs"] != r["epochs_total"] else "")))
    if r["kind"] == RUN_KIND:
        from esr_cli.report.listing import metrics_problem
        from esr_cli.storage.finals import run_finals

        problem = metrics_problem(r["path"])  # a FIFO, a link, a file too large: said, not waited on
        if problem:
            lines.append(("metrics", f"unreadable: {problem}"))
        try:
            finals = None if problem else run_finals(Path(r["path"]))["return"]
        except (OSError, KeyError, TypeError, ValueError):
            finals = None
        n = finals["seeds"] - finals.get("missing", 0) if finals else 0
        if n:
            text = f"{finals['mean']:.2f}" + (f" ± {finals['se']:.2f} (SE)" if n > 1 else "") + \
                (f", IQM {finals['iqm']:.2f}" if "iqm" in finals else "")
            lines.append(("final return", f"{text} over {n} seed{'s' if n != 1 else ''} (each seed's mean over its last 10% of epochs)"))
        lines.append(("overrides", "(no spec file in experiments/ resolves to it)" if r["overrides"] is None
                      else " ".join(f"--set {shlex.quote(o)}" for o in r["overrides"]) or "none: the spec file as it is"))
    else:
        if r["final_return"] is not None:
            lines.append(("return", f"{r['final_return']:.2f} ({r['return_of']})"))
        lines += [(f"  {name}", value) for name, value in _flat_scalars(manifest.get("summary"))]
    deps = field(manifest, "key_components", "dependencies")
    if isinstance(deps, dict) and deps:
        lines.append(("depends on", ", ".join(f"{k} {v if isinstance(v, str) else ', '.join(map(str, v))}" for k, v in deps.items())))
    files = manifest.get("files")
    if isinstance(files, dict):
        lines.append(("files", f"{len(files)} (esr verify checks them); --json: the whole manifest"))
    return lines


@app.command()
def verify(
    ctx: typer.Context,ref: Optional[str] = typer.Argument(None, help="artifact key or path (default: every artifact)")):
    """Re-hash every file of an artifact against its manifest."""
    if ref is None and not ctx.obj.store.root.is_dir():
        raise Exit(2, f"no store at {ctx.obj.store.root}: nothing to verify")
    paths = [ctx.obj.store.resolve(ref)] if ref is not None else [e.path for e in ctx.obj.store.entries() if e.status == "complete"]
    if not paths:
        err.print(f"store {ctx.obj.store.root} holds no finished artifact to verify")
    bad = 0
    for p in paths:
        problems = _verify_problems(p, ctx.obj.store)
        if problems:
            bad += 1
            err.print(tagged("CORRUPT", "red", f" {p}"))
            for prob in problems:
                err.print(f"  {prob}")
        else:
            err.print(tagged("ok", "green", f" {p}"))
    if bad:
        raise Exit(1, f"{bad} of {len(paths)} artifact(s) failed verification")


def _verify_problems(path: Path, store: Store) -> list[str]:
    """What `Store.verify` finds; an artifact it cannot read to the end (a disk error, say) is
    one more problem, never the end of checking the others."""
    from esr_cli.storage.checkpoint_files import verify_artifact
    from esr_cli.storage.finals import UnreadableMetrics

    try:
        return verify_artifact(store, path)
    except OSError as e:
        return [f"cannot be read to the end: {e.strerror or e}: {e.filename}"]
    except UnreadableMetrics as e:  # replaced by something unreadable after it was hashed
        return [e.one_line()]


@app.command("export")
def export_(
    ctx: typer.Context,
    ref: str = typer.Argument(..., help="artifact key, key prefix or directory; an unfinished run too", show_default=False),
    out_file: Optional[Path] = typer.Option(None, "--out", "-o", help="archive to write (default: ./KEY8.tar.gz)"),
    without_checkpoint: bool = typer.Option(False, "--without-checkpoint", help="a run without its networks (a finished "
                                            "one as metrics, spec and manifest: reports and figures, not eval; an "
                                            "unfinished one as a record of its logged epochs); an exact check without "
                                            "its arrays (its summary: tables, not the estimator check); an evaluation without its "
                                            "rollout GIF"),
    sign: bool = typer.Option(False, "--sign", help="also write ARCHIVE.sig, an HMAC-SHA256 of the archive under the "
                              "key in the file $ESR_ARCHIVE_KEY names (`esr import --require-signature` checks it)"),
):
    """Write one artifact to a single file, to carry to another store (`esr import`). An
    unfinished run travels with its newest verified checkpoint and continues where imported."""
    from esr_cli.storage import signing

    key = signing.archive_key() if sign else None  # a missing key is named before any work
    option = "--out"
    if out_file is None:  # ./KEY8.tar.gz, checked as --out is: the current folder may be an artifact's
        option = "--out (not given: the current folder)"
        out_file = Path(f"{ctx.obj.store.find(ref, include_partial=True).key[:8]}.tar.gz")
    elif not out_file.name.endswith((".tar.gz", ".tgz")):
        raise Exit(2, f"--out: {out_file} would hold a gzipped tar archive: name it with .tar.gz")
    check_output_file(out_file, option)
    refuse_inside_store(out_file, option, ctx.obj.store)
    from esr_cli.storage.transfer import export

    moved = export(ctx.obj.store, ref, out_file, without_checkpoint)
    signed = f", signed in {signing.sign(moved.path, key).name}" if key else ""
    err.print(tagged("exported", "green", f" {moved.kind} {moved.key[:12]} ({moved.status}, {moved.files} files{signed})"))
    out.print(str(moved.path), highlight=False)


@app.command("import")
def import_(
    ctx: typer.Context,
    archives: List[Path] = typer.Argument(..., help="archives written by `esr export`", show_default=False),
    without_checkpoint: bool = typer.Option(False, "--without-checkpoint", help="also accept an unfinished run "
                                            "whose checkpoint did not travel: its logged epochs, for reports and "
                                            "figures; training it again starts from epoch 0"),
    require_signature: bool = typer.Option(False, "--require-signature", help="refuse an archive unless ARCHIVE.sig "
                                           "beside it matches it under the key in the file $ESR_ARCHIVE_KEY names "
                                           "(`esr export --sign`)"),
):
    """Put artifacts exported from another store into this one, each checked and then added in
    one step; an unfinished run continues with the command that started it."""
    from esr_cli.storage import signing
    from esr_cli.storage.transfer import check_archive, import_archive

    key = signing.archive_key() if require_signature else None
    for archive in archives:  # every one readable (and signed, if asked) before any is added
        if key:
            signing.check_signature(archive, key)
        check_archive(archive)
    for archive in archives:
        moved = import_archive(ctx.obj.store, archive, without_checkpoint)
        if moved.files == 0 and moved.local_epoch is not None:
            err.print(f"{moved.kind} {moved.key[:12]} is already unfinished in the store, at epoch {moved.local_epoch}: "
                      "as far as the archive's or further, so it is kept and nothing is imported")
        elif moved.restored:
            err.print(tagged("imported", "green", f" {moved.kind} {moved.key[:12]}: the store's copy was kept without "
                                                  f"{' and '.join(moved.restored)}; {moved.files} files put back from the archive"))
        elif moved.files == 0:
            err.print(f"{moved.kind} {moved.key[:12]} is already in the store: nothing to import")
        else:
            note = ("; a record without a checkpoint: training it again starts from epoch 0" if moved.record else
                    f"; it replaces this store's unfinished run of the same key, which was at epoch {moved.local_epoch}"
                    if moved.replaced_partial else "")
            err.print(tagged("imported", "green", f" {moved.kind} {moved.key[:12]} ({moved.status}, {moved.files} files{note})"))
        out.print(str(moved.path), highlight=False)

