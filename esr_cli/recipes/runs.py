"""Training runs and evaluations as artifact recipes (esr_cli/storage/artifacts.py).

A run's recipe trains (or resumes from its checkpoint) and requires its BC humans; an
evaluation's reads a trained run only and never trains silently. Here too: finding a run from
a spec or key, and loading a trained run's state.
"""

from __future__ import annotations

import shutil
import tempfile
from functools import partial
from pathlib import Path

import jax
import numpy as np
from rich.console import Console

from esr_cli.common import specs
from esr_cli.common.printing import train_line
from esr_cli.common.stats import describe
from esr_cli.model import evaluate as ev
from esr_cli.model.train import make_trainer
from esr_cli.recipes import stored_humans
from esr_cli.recipes.targets import is_spec_file, partner_spec, run_spec, seat_spec, stored_run
from esr_cli.runner import loop
from esr_cli.runner.resources import check_run_fits
from esr_cli.runner.run_progress import TrainingReport, progress_bar
from esr_cli.runner.wandb_log import WandbLog, wandb_folder
from esr_cli.storage import provenance
from esr_cli.storage.artifacts import Recipe
from esr_cli.storage.finals import run_length
from esr_cli.storage.finals import read_rows
from esr_cli.storage.store import EVAL_KIND, EVAL_ROLLOUT, HUMAN_KIND, RUN_KIND, LockBusy, Store, StoreError, atomic_write_text, content_key, nearest_existing, probe_writable, require_networks, without_checkpoint

# Rough upper bound of a checkpoint per seed plus metrics, checked before a run starts.
MIN_FREE_BYTES_PER_SEED = 32 << 20


def enable_compile_cache() -> None:
    """Keep compiled XLA programs on disk ($ESR_COMPILE_CACHE, default ~/.cache/esr/jax;
    `off` disables): resuming, evaluating or re-running a spec then skips most compile time.
    Also fixes the matmul precision (provenance.matmul_precision) before anything compiles."""
    provenance.apply_matmul_precision()
    where = provenance.compile_cache_dir()
    if where is None:
        return
    jax.config.update("jax_compilation_cache_dir", where)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def run_key(spec) -> tuple[str, dict]:
    # A stored human (BC) is a dependency: its key is part of the run's key.
    components = provenance.key_components("run", spec.training_part(), spec.budget, stored_humans.dependencies(spec))
    return content_key(components), components


def lineage_key(components: dict) -> str:
    """The key a run has at every length: its key components without `train.epochs`. Runs of
    one lineage compute the same epochs (training is a pure function of the state, epoch by
    epoch), so a longer run can start where a shorter one ended (docs/store.md)."""
    spec = components["spec"]
    train = {k: v for k, v in spec["train"].items() if k != "epochs"}
    return content_key({**components, "spec": {**spec, "train": train}})


def _lineage_of(record: dict | None) -> str | None:
    """The lineage key a stored run's manifest or pending.json names; None where its components
    are not a run's (a damaged or foreign record must not stop another run from training)."""
    try:
        return lineage_key(record["key_components"])
    except (KeyError, TypeError, AttributeError, ValueError):
        return None


def adopt_shorter_run(store: Store, key: str, components: dict, run_dir: Path, epochs: int, console: Console) -> None:
    """Start an empty run directory from the longest run of its lineage that got no further than
    `epochs`: a committed run, or an unfinished one that no process is writing."""
    if loop.verified_steps(run_dir):
        return  # this run has started already: it resumes from its own checkpoint
    lineage = lineage_key(components)
    donors = []
    for entry in store.entries():
        if entry.kind != RUN_KIND or entry.key == key or _lineage_of(entry.manifest) != lineage:
            continue
        done = (run_length(entry.manifest) or 0) if entry.status == "complete" else \
            next((s for s in loop.verified_steps(entry.path) if s <= epochs), 0)
        if 0 < done <= epochs:
            donors.append((done, entry))
    donors.sort(key=lambda d: (-d[0], d[1].status != "complete"))  # the longest first, a finished one before
    for done, entry in donors:
        if entry.status == "complete":
            adopted = loop.adopt_checkpoint(entry.path, run_dir, epochs)
        else:
            try:  # an unfinished run is only read while its lock shows no process is writing it
                with store.lock(RUN_KIND, entry.key, wait=False):
                    adopted = loop.adopt_checkpoint(entry.path, run_dir, epochs)
            except LockBusy:
                continue
        if adopted:
            total = run_length(entry.manifest)
            state = "finished" if entry.status == "complete" else \
                f"unfinished ({'' if total is None else f'{total:,} epochs long, '}checkpointed at epoch {done:,})"
            console.print(f"starting from run {entry.key[:12]} at epoch {adopted}: the same spec but for its length, {state}")
            return
    kept = [entry for _, entry in donors if entry.status == "complete" and without_checkpoint(entry.path)]
    if kept:  # it would have continued from one of these, had its networks been kept
        console.print(f"run {kept[0].key[:12]} (the same spec but for its length) is kept as metrics only: training starts "
                      "from epoch 1 (`esr import` of its full archive first would continue from it)")


def _check_disk(store: Store, spec) -> None:
    need = MIN_FREE_BYTES_PER_SEED * len(spec.train.seeds)
    where = nearest_existing(store.root)  # the store itself may not be made yet
    try:
        probe_writable(where)
    except OSError as e:
        raise StoreError(f"store {store.root} is not writable: {e.strerror or e} (in {where})") from None
    free = shutil.disk_usage(where).free
    if free < need:
        raise StoreError(f"only {free >> 20} MiB free under {store.root}; this run needs about {need >> 20} MiB for checkpoints")


def _wandb_log(folder: Path, key: str, spec, run_dir: Path, seeds: list[int], rows: list[dict]) -> WandbLog:
    return WandbLog(folder, key, f"{spec.name} ({spec.budget})", spec.model_dump(mode="json"), seeds, rows)


def run_recipe(spec, console: Console, stop_at: float | None = None, quick=None, wandb: bool = False) -> Recipe:
    """The training run of `spec` as an artifact: trained, or resumed from its checkpoint, when
    the store lacks it; its BC humans (if any) are made first. stop_at (a time.monotonic()
    value): stop at the last chunk boundary before it, resumable (stops.TimeLimitReached).
    quick: the same spec at --budget quick, whose time the run estimates too. wandb: also log
    to an offline wandb run in the store (esr_cli/runner/wandb_log.py)."""
    key, components = run_key(spec)

    def check(store: Store):  # memory and disk, before anything is built or written
        check_run_fits(spec)
        _check_disk(store, spec)

    def build(run_dir: Path, store: Store) -> dict:
        enable_compile_cache()
        atomic_write_text(run_dir / "spec.yaml", specs.to_yaml(spec))
        adopt_shorter_run(store, key, components, run_dir, spec.train.epochs, console)
        trainer = build_trainer(spec, store)
        logs = [partial(_wandb_log, wandb_folder(store.root, key), key, spec)] if wandb else []
        with progress_bar(console) as bar:
            report = TrainingReport(spec, trainer, console, bar, key, quick)
            summary = loop.train(trainer, run_dir, on_chunk=report.on_chunk, on_start=report.on_start, stop_at=stop_at,
                                 on_phase=report.on_phase, on_stop=report.on_stop, logs=logs)
        from esr_cli.common import plots  # matplotlib: only once a run is trained

        plots.learning_curve(
            read_rows(run_dir),
            run_dir / "figures" / "learning_curve.png",
            f"{spec.name} [{spec.method.kind}]",
            {"artifacts": {RUN_KIND: key}, "budget": spec.budget, "seeds": list(spec.train.seeds)},
            warmup_epochs=spec.learner.warmup_epochs,
        )
        return summary

    def waiting(holder: str):
        console.print(f"run {key[:12]} is in progress ({holder}); waiting for it to finish")

    return Recipe(RUN_KIND, spec.name, components, build, budget=spec.budget, seeds=tuple(spec.train.seeds),
                  requires=stored_humans.human_recipes(spec, console), check=check,
                  record={"method": spec.method.kind, "env": spec.env.kind}, summary_file=False, on_wait=waiting)


def committed_run(spec, command: str, store: Store) -> Path:
    """The committed training run of a loaded spec; StoreError naming `command` (the
    `esr train ...` that makes it) where there is none."""
    key = run_key(spec)[0]
    hit = store.lookup(RUN_KIND, key)
    if not hit:
        if store.partial_path(RUN_KIND, key).is_dir():
            raise StoreError(f"{spec.name} ({spec.budget}) is not finished in {store.root}: run `{command}` to continue it")
        raise StoreError(f"{spec.name} ({spec.budget}) is not trained in {store.root}: run `{command}` first"
                         + other_budgets_hint(spec, store))
    return hit


def other_budgets_hint(spec, store: Store) -> str:
    """'; the store has NAME at --budget quick (complete), ...' for the runs of this spec's
    name at other budgets, or '' where there are none."""
    found: dict[str, set[str]] = {}
    for entry in store.entries():
        m = entry.manifest or {}
        if entry.kind != RUN_KIND or m.get("name") != spec.name or m.get("budget") in (None, spec.budget):
            continue
        found.setdefault(str(m["budget"]), set()).add("finished" if entry.status == "complete" else "unfinished")
    if not found:
        return ""
    listed = ", ".join(f"--budget {b} ({' and '.join(sorted(states))})" for b, states in sorted(found.items()))
    return f"; the store has {spec.name} at {listed}: add that option to use one"


def find_run(target: str, budget: str, sets, store: Store) -> Path:
    """A committed run from a spec file (at budget/sets) or an artifact key/path."""
    if is_spec_file(target):
        spec = specs.load(Path(target), budget, list(sets or []))
        return committed_run(spec, train_command(target, budget, sets, store), store)
    return stored_run(store, target)


def train_command(spec_file: str, budget: str, sets, store: Store) -> str:
    return train_line(store.invocation(), spec_file, budget, sets or [])


def eval_key(run_manifest: dict, episodes: int, partner_key: str | None = None, seat: int | None = None) -> tuple[str, dict]:
    components = {
        "kind": "eval",
        "run": run_manifest["key"],
        "episodes": episodes,
        "code": provenance.code_digest(provenance.MODEL_SOURCES),
        "toolchain": provenance.toolchain(),
    }
    if partner_key is not None:  # a human other than the one the robot trained with
        components["human"] = partner_key
    if seat is not None:  # seats other than the training ones
        components["robot_seat"] = seat
    return content_key(components), components


def eval_spec(spec, partner: str = "training", seat: int | None = None):
    """(the spec an evaluation plays, the seat if it differs from training's, the partner's key
    or None for the training human). Raises StoreError naming the option that does not fit."""
    spec, new_seat = seat_spec(spec, seat)
    other = partner_spec(spec, partner)
    if other is spec:
        return spec, new_seat, None
    keys = stored_humans.dependencies(other)[HUMAN_KIND]
    return other, new_seat, keys if isinstance(keys, str) else content_key({"per_seed_humans": keys})


def eval_recipe(run_path: Path, store: Store, episodes: int | None, console: Console,
                partner: str = "training", seat: int | None = None) -> Recipe:
    """The evaluation of a run's final robot with its training human, or with a held-out proxy
    human (`partner="proxy"`, a BC human cloned from the test split); in its training seat, or
    in `seat` (Overcooked: 1 plays the robot as agent_1, the flipped evaluation). Reads the
    run; never trains."""
    run_manifest = store.read_manifest(run_path)
    spec, new_seat, partner_key = eval_spec(run_spec(run_path), partner, seat)
    episodes = episodes or spec.eval.episodes
    key, components = eval_key(run_manifest, episodes, partner_key, new_seat)

    def build(eval_dir: Path, store: Store) -> dict:
        from esr_cli.common import plots  # matplotlib: only where an evaluation is made
        from esr_cli.model.envs.action_labels import action_labels

        enable_compile_cache()
        trainer = build_trainer(spec, store)
        what = f"evaluating {spec.name}: {episodes:,} episodes x {len(spec.train.seeds)} seed(s)"
        with console.status(what) as status:
            state = loop.final_state(trainer, run_path)
            if partner_key is not None and trainer.human.has_state:  # the checkpoint holds the training humans
                state = state._replace(human=loop.initial_state(trainer, spec.train.seeds).human)
            results = ev.evaluate(trainer, state, episodes, spec.train.seeds,
                                  progress=lambda done, total: status.update(f"{what}: {done:,} of {total:,} played"))
        summary = {"name": spec.name, "budget": spec.budget, "seeds": list(spec.train.seeds), "episodes": episodes,
                   "run": run_manifest["key"], "human": partner, "human_key": partner_key,
                   "robot_seat": spec.env.robot_seat if spec.env.kind == "overcooked" else None, "results": {}}
        for mode, r in results.items():  # per seed: the mean over its episodes
            ret, succ = describe(r["return"].mean(axis=1)), describe(r["success"].mean(axis=1))
            summary["results"][mode] = {
                "return_mean": ret["mean"], "return_se": ret["se"], "success_mean": succ["mean"], "success_se": succ["se"],
                "return_per_seed": [round(v, 4) for v in ret["per_seed"]],
                "success_per_seed": [round(v, 4) for v in succ["per_seed"]],
                "return": ret, "success": succ,
            }
        # One picture of the robot at work: the first seed's first episode, first policy mode.
        mode = ev.policy_modes(trainer)[0]
        traj = ev.episode_states(results[mode]["states"], 0, 0)
        robot, human, reward = ev.episode_steps(results[mode]["steps"], 0, 0)
        steps = trainer.env.episode_steps
        frames = [np.asarray(trainer.env.render(index(traj, t))) for t in range(steps + 1)]
        totals = np.concatenate([[0.0], np.cumsum(reward)])
        captions = [plots.frame_caption(t, steps, action_labels(spec.env.kind, trainer.env, robot[t - 1], human[t - 1]) if t else None,
                                        float(reward[t - 1]) if t else None, float(totals[t])) for t in range(steps + 1)]
        plots.rollout_gif(frames, eval_dir / EVAL_ROLLOUT, captions=captions)
        prov = {"artifacts": {RUN_KIND: run_manifest["key"], EVAL_KIND: key}, "budget": spec.budget, "seeds": list(spec.train.seeds)}
        plots.learning_curve(
            read_rows(run_path), eval_dir / "learning_curve.png", f"{spec.name} [{spec.method.kind}]", prov,
            warmup_epochs=spec.learner.warmup_epochs,
        )
        # what `esr ls` shows in its return column: the first policy mode's
        return {"return": {"mean": summary["results"][mode]["return_mean"]}, **summary}

    return Recipe(EVAL_KIND, spec.name, components, build, budget=spec.budget, seeds=tuple(spec.train.seeds),
                  requires=stored_humans.human_recipes(spec, console))


def build_trainer(spec, store: Store):
    """The spec's Trainer with its stored inputs (a BC human's parameters) loaded from `store`."""
    return make_trainer(spec, stored_humans.humans_params(spec, store) if stored_humans.is_stored(spec.human) else None)


def load_run(store: Store, ref: str):
    """(run path, its manifest, its trainer, its final TrainState) for a committed training run."""
    path = store.resolve(ref)
    manifest = store.read_manifest(path)
    if manifest.get("kind") != RUN_KIND:
        raise StoreError(f"{ref} is not a training run")
    enable_compile_cache()  # what reads a run (exact, estimator, diagnose) compiles programs on it
    trainer = build_trainer(run_spec(path), store)
    return path, manifest, trainer, loop.final_state(trainer, path)


def load_run_so_far(store: Store, path: Path, finished: bool):
    """(trainer, newest state, that state's epoch) of a run from `run_record`. An unfinished run
    is read at its newest verified checkpoint from a snapshot (`transfer.snapshot_partial`, as
    `esr export` takes one): a run being trained in another process is never touched (opening
    its checkpoint folder in place would clear a save in progress)."""
    from esr_cli.storage.transfer import snapshot_partial

    enable_compile_cache()
    trainer = build_trainer(run_spec(path), store)
    seeds = list(trainer.spec.train.seeds)
    if finished:
        return (trainer, *_restore_newest(trainer, path, seeds))
    with tempfile.TemporaryDirectory(prefix="esr-inspect-") as aside:
        snapshot = Path(aside) / path.name
        snapshot_partial(path, snapshot)
        return (trainer, *_restore_newest(trainer, snapshot, seeds))


def _restore_newest(trainer, run_dir: Path, seeds):
    require_networks(run_dir)
    state, epoch = loop.restore_latest(trainer, run_dir, seeds, repair=False)
    if not epoch:
        raise StoreError(f"{run_dir} has no checkpoint: nothing to inspect")
    return state, epoch


def seed_slice(tree, i: int):
    """One seed's part of a state whose leaves have a leading seed axis."""
    return jax.tree.map(lambda x: x[i], tree)


def index(tree, t: int):
    """Step t of a trajectory whose leaves have a leading time axis."""
    return jax.tree.map(lambda x: x[t], tree)
