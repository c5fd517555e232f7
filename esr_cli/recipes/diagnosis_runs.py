"""Diagnoses of trained runs (`esr diagnose`): why one seed's robot helps or not.

A diagnosis of a finished run is an artifact (kind `diagnoses`), keyed by the run, the seed and
the options, so that a table of results can read it back (`esr sweep --results --diagnose`) and
`esr diagnose` answers again from the store. An unfinished run changes with every chunk, so
its diagnosis is computed and shown but never stored, as figures of unfinished runs are.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from esr_cli.storage import provenance
from esr_cli.storage.artifacts import Recipe
from esr_cli.storage.store import DIAGNOSIS_KIND, Store, parse_dirname

# The code behind a diagnosis: the model and the analysis package (their import closure) and
# this module's own steps; not the store and checkpoint plumbing they import, which decides
# where numbers are read, never what they are. (The run's training code is pinned by its key.)
DIAGNOSIS_CODE = (provenance.MODEL_SOURCES + ("analysis",), ("recipes/diagnosis_runs.py",))


@dataclass(frozen=True)
class Options:
    """What a diagnosis computes over; `esr diagnose`'s defaults are the ones tables read."""

    batches: int = 40  # critic batches scored by situation, representation batches checked
    episodes: int = 16  # episodes each robot plays for the play check
    refit: int = 0  # ESR: updates of fresh representations fitted to each robot's play (0: off)


def components(run_key: str, seed_index: int, options: Options) -> dict:
    """The key components of a diagnosis of seed `seed_index` of the finished run `run_key`."""
    return {"kind": "diagnosis", "run": run_key, "seed_index": seed_index, **asdict(options),
            "code": provenance.code_digest(*DIAGNOSIS_CODE), "toolchain": provenance.toolchain()}


def compute(trainer, state, epoch: int, seed_index: int, options: Options, finished: bool, run_key: str) -> dict:
    """The diagnosis of one seed of a run's state at `epoch`: the play check (any environment,
    for a method that learns a policy), and on the gridworld the reward by the human's
    situation, the critic and policy at distinct start states and, for ESR, what its
    representations pick futures by (esr_cli/analysis/diagnose.py)."""
    import jax

    from esr_cli.analysis import diagnose as dg, play_check as pc
    from esr_cli.recipes.runs import seed_slice

    one = seed_slice(state, seed_index)
    learns = trainer.method.learns_policy and not trainer.acts_by_rule
    play = pc.play_check(trainer, one, jax.random.PRNGKey(3), options.episodes, options.batches, options.refit) if learns else None
    report = {"run": run_key, "finished": finished, "epoch": epoch, "epochs": trainer.spec.train.epochs,
              "seed_index": seed_index, "play": play}
    if trainer.spec.env.kind == "gridworld":
        rewards = dg.reward_by_situation(trainer, one, jax.random.PRNGKey(0), options.batches)
        report.update({
            "reward": rewards,
            "free_vs_trapped": dg.free_trapped_contrast(rewards),
            "start": trainer.spec.env.start,
            "start_states": dg.start_policy(trainer, one, jax.random.PRNGKey(1)) if learns else [],
            "representations": dg.representation_check(trainer, one, jax.random.PRNGKey(2), options.batches)
            if trainer.spec.method.kind == "esr" else None,
        })
    return report


def diagnosis_recipe(store: Store, run_path: Path, seed_index: int, options: Options) -> Recipe:
    """The stored diagnosis of seed `seed_index` of the finished run at `run_path` (its key is
    the name of its folder, as `esr diagnose` names an unfinished one's)."""
    manifest = store.read_manifest(run_path)
    run_key = parse_dirname(run_path.name)[0]
    comps = components(run_key, seed_index, options)

    def build(out: Path, store: Store) -> dict:
        from esr_cli.recipes.runs import load_run_so_far

        trainer, state, epoch = load_run_so_far(store, run_path, True)
        return compute(trainer, state, epoch, seed_index, options, True, run_key)

    seeds = manifest.get("seeds")
    seed = seeds[seed_index] if isinstance(seeds, list) and 0 <= seed_index < len(seeds) else seed_index
    return Recipe(DIAGNOSIS_KIND, str(manifest.get("name") or "diagnosis"), comps, build,
                  budget=manifest.get("budget"), seeds=(seed,))
