"""A run's checkpoint files and their digests, without JAX: which checkpoints are intact, and
whether a checkpoint's epoch agrees with the run's metrics and length. Only reading the epoch a
checkpoint's training state holds (`held_epochs`) imports orbax, and JAX with it.

Digests of every checkpoint's files are written after the checkpoint is saved; a resume, an
export and a report use only checkpoints that verify, so a damaged newest checkpoint falls
back to the one before and a run without an intact one is known to start again.

A checkpoint's folder is named by its epoch, but a name is only a name (an archive's folder can
be renamed): the epoch the training state holds, the metrics logged and the run's length must
agree with it before a run resumes from it, is imported with it or is verified with it.
"""

from __future__ import annotations

import json
from pathlib import Path

from esr_cli.common.jsonl import JsonInputError, read_json
from esr_cli.storage.finals import logged_rows, run_length
from esr_cli.storage.labels import labels_problem
from esr_cli.storage.store import CHECKPOINT_FOLDER, MANIFEST, MAX_MANIFEST_BYTES, RUN_KIND, Store, atomic_write_text, digest_file, load_manifest, without_checkpoint

CHECKPOINT_DIR = CHECKPOINT_FOLDER
CHECKPOINT_DIGESTS = "checkpoint_digests.json"


def _is_step(name: str) -> bool:
    """Whether `name` is a checkpoint folder's: a few ASCII digits (an archive's folder or digests
    may name anything; str.isdigit also takes '²', and int() refuses both it and 5,000 digits)."""
    return name.isascii() and name.isdigit() and len(name) <= 12


def step_digests(run_dir: Path, step: int) -> dict[str, str]:
    root = Path(run_dir) / CHECKPOINT_DIR / str(step)
    return {f.relative_to(root).as_posix(): digest_file(f) for f in sorted(root.rglob("*")) if f.is_file()}


def read_digests(run_dir: Path) -> dict:
    """{step: {file: digest}}; {} where the file is missing, unreadable or not an object."""
    try:
        digests = read_json(Path(run_dir) / CHECKPOINT_DIGESTS, MAX_MANIFEST_BYTES)
    except (OSError, JsonInputError):
        return {}
    return digests if isinstance(digests, dict) else {}


# orbax reads a checkpoint's metadata files (all but the array data under its `d/` folders) whole,
# as JSON. esr's are tens of KiB; a larger one (an archive's, with digests to match) is not
# esr's, and is never handed to orbax to parse into memory.
MAX_METADATA_BYTES = 16 << 20


def _metadata_too_large(step_dir: Path) -> bool:
    return any(f.stat().st_size > MAX_METADATA_BYTES for f in step_dir.rglob("*")
               if f.is_file() and "d" not in f.relative_to(step_dir).parts[:-1])


def step_intact(run_dir: Path, step: int, digests: dict) -> bool:
    """Whether checkpoint `step`'s files match the digests recorded for it, none of its metadata
    files larger than esr writes."""
    return (bool(digests.get(str(step))) and not _metadata_too_large(Path(run_dir) / CHECKPOINT_DIR / str(step))
            and step_digests(run_dir, step) == digests[str(step)])


def record_digests(run_dir: Path, steps, saved: int) -> None:
    """Record the just-saved step's digests; keep those of older steps still present."""
    known = read_digests(run_dir)
    digests = {str(s): known.get(str(s)) for s in steps if s != saved and known.get(str(s))}
    digests[str(saved)] = step_digests(run_dir, saved)
    atomic_write_text(Path(run_dir) / CHECKPOINT_DIGESTS, json.dumps(digests, sort_keys=True))


def verified_steps(run_dir: Path) -> list[int]:
    """The checkpoint steps of `run_dir` whose files match their recorded digests, newest first."""
    root = Path(run_dir) / CHECKPOINT_DIR
    if not root.is_dir():
        return []
    digests = read_digests(run_dir)
    steps = sorted((int(d.name) for d in root.iterdir() if d.is_dir() and _is_step(d.name)), reverse=True)
    return [s for s in steps if step_intact(run_dir, s, digests)]


def logged_epochs(run_dir: Path) -> list[int]:
    """The epochs of a run's sound metrics lines, in order, beyond its length too (what a check
    compares with its length; tables read `read_rows`). UnreadableMetrics where the file cannot
    be read at all."""
    return [r["epoch"] for r in logged_rows(run_dir)]


def _epochs(values: list[int]) -> str:
    if not values:  # a forged state with an empty epoch array
        return "no epoch"
    return f"epoch {values[0]}" if len(values) == 1 else f"epochs {', '.join(map(str, values))}"


def epochs_problem(run_dir: Path, step: int, total: int | None, held: list[int] | None = None) -> str | None:
    """Why checkpoint `step` of `run_dir` is not where the run stands, or None: it must be an
    epoch of the run (at most `total`, where known) that the metrics logged, and the epoch the
    training state holds (`held`: each seed's, where it was read) must be `step` too."""
    logged = logged_epochs(run_dir)
    beyond = total is not None and step > total
    if not beyond and step in logged and held in (None, [step]):
        return None
    # Only what disagrees with the folder is named: a fact that agrees would read as the problem.
    facts = [f"its state holds {_epochs(held)}"] if held not in (None, [step]) else []
    if step not in logged:
        facts.append(f"metrics end at {logged[-1]}" if logged else "no epoch is logged")
    if not facts:  # beyond the run's length is all that is wrong
        return f"checkpoint folder says epoch {step} in a run of {total} epochs"
    return (f"checkpoint folder says epoch {step} but {' and '.join(facts)}"
            + (f", in a run of {total} epochs" if beyond else ""))


def epochs_of(epoch) -> list[int]:
    """The epochs a training state's `epoch` (one per seed, any array-like) holds, each once, in
    order: what `epochs_problem` compares with a checkpoint's folder."""
    import numpy as np

    return sorted({int(e) for e in np.asarray(epoch).ravel()})


STATE_ITEM = "default"  # the folder of a checkpoint's state, as the run's orbax CheckpointManager saves it


def held_epochs(run_dir: Path, step: int) -> list[int] | None:
    """The epochs the training state in checkpoint `step` of `run_dir` holds, read from its files
    alone (the `epoch` array, not the whole state, and no spec needed); None where that array
    cannot be read or is not one small array of integers (an edited or foreign checkpoint)."""
    import numpy as np
    import orbax.checkpoint as ocp
    from etils import epath

    from esr_cli.model.spec import MAX_SEEDS

    folder = epath.Path(Path(run_dir).absolute() / CHECKPOINT_DIR / str(step) / STATE_ITEM)
    handler = ocp.PyTreeCheckpointHandler()
    try:
        saved = handler.metadata(folder).tree.get("epoch")
        shape = getattr(saved, "shape", None)
        if not (isinstance(shape, tuple) and len(shape) <= 1 and int(np.prod(shape)) <= MAX_SEEDS
                and np.issubdtype(np.dtype(saved.dtype), np.integer)):
            return None  # checked before a byte of it is read: a declared size is only a claim
        restored = handler.restore(folder, args=ocp.args.PyTreeRestore(
            item={"epoch": np.zeros(shape, saved.dtype)}, restore_args={"epoch": ocp.RestoreArgs(restore_type=np.ndarray)},
            partial_restore=True))
        return epochs_of(restored["epoch"])
    except Exception:  # noqa: BLE001 - orbax and tensorstore raise many kinds; all mean it cannot be read
        return None
    finally:
        handler.close()


def state_epochs_problem(run_dir: Path, step: int, total: int | None) -> str | None:
    """`epochs_problem` with the epoch checkpoint `step`'s state holds, read from its files
    (`held_epochs`): why the checkpoint is not where its folder says, naming both, or None."""
    held = held_epochs(run_dir, step)
    if held is None:
        return f"the training state in checkpoint folder {step} cannot be read"
    return epochs_problem(run_dir, step, total, held)


def run_epochs_problem(run_dir: Path, manifest: dict) -> str | None:
    """Why a committed run's epochs disagree, or None: its newest checkpoint folder, the newest
    step its digests record, its last logged epoch and its manifest's summary must all be its
    length (checked where the manifest names one, as every run training commits does)."""
    total = run_length(manifest)
    if total is None:
        return None
    root = Path(run_dir) / CHECKPOINT_DIR
    folders = [int(d.name) for d in root.iterdir() if d.is_dir() and _is_step(d.name)] if root.is_dir() else []
    digested = [int(s) for s in read_digests(run_dir) if _is_step(s)]
    summary = manifest.get("summary")
    said = {"its newest checkpoint folder says": max(folders, default=None),
            "its checkpoint digests end at": max(digested, default=None),
            "its metrics end at": (logged_epochs(run_dir) or [None])[-1],
            f"its {MANIFEST} summary says": summary.get("epochs") if isinstance(summary, dict) else None}
    if without_checkpoint(run_dir):  # kept as metrics only: no folder to agree
        said.pop("its newest checkpoint folder says")
    wrong = [f"{what} {'none' if epoch is None else epoch}" for what, epoch in said.items() if epoch != total]
    return f"the run has {total} epochs but {' and '.join(wrong)}" if wrong else None


def verify_artifact(store: Store, path: Path) -> list[str]:
    """`Store.verify`, whether the manifest's labels are its key's (`labels_problem`) and, for a
    run whose files are as committed, whether its epochs agree (`run_epochs_problem`): what
    `esr verify` and `esr import` check."""
    problems = store.verify(path)
    if problems:
        return problems
    manifest = load_manifest(Path(path))
    epochs = run_epochs_problem(Path(path), manifest) if manifest["kind"] == RUN_KIND else None
    return [p for p in (labels_problem(manifest, MANIFEST), epochs) if p]
