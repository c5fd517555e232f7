"""What a command's target names, and whether its options fit it, without importing JAX.

`eval`, `diagnose` and the play commands take a spec file or a stored training run, plus options
(the evaluation's human, its seat) that must fit that run's spec. Checking them needs only the
spec and the store's small files, so a mistake is refused in well under a second; the training
code (esr_cli/recipes/runs.py) is imported after the checks pass.
"""

from __future__ import annotations

import shlex
from pathlib import Path

from pydantic import ValidationError

from esr_cli.analysis.state_count import TooManyStates, check_size
from esr_cli.common import specs
from esr_cli.common.printing import printable
from esr_cli.common.stops import SAME_AGAIN, diverged_at
from esr_cli.model import spec as spec_model
from esr_cli.storage.store import EXACT_KIND, PLAY_KIND, RUN_KIND, Store, StoreError, load_manifest, parse_dirname, read_pending, require_networks

EVAL_PARTNERS = ("training", "proxy")
PLAY_PARTNER = "play:"  # --human play:KEY,KEY,...: a BC human cloned from played episodes


def is_spec_file(target: str) -> bool:
    """Whether a command's target names a spec file rather than an artifact (a key or a path)."""
    p = Path(target)
    return p.suffix in (".yaml", ".yml") or p.is_file()


def check_partner_name(partner: str) -> None:
    if partner not in EVAL_PARTNERS and not partner.startswith(PLAY_PARTNER):
        raise StoreError(f"--human: unknown partner {partner!r}; known: {', '.join(EVAL_PARTNERS)}, {PLAY_PARTNER}KEY,...")


def partner_spec(spec, partner: str):
    """The spec with the evaluation's human in place of the training one (the same spec for
    `training`). Raises StoreError naming why the partner cannot play this spec's run."""
    if partner == "training":
        return spec
    check_partner_name(partner)
    if spec.human.kind != "bc":
        raise StoreError(f"--human {partner.split(':')[0]} is a BC human (Overcooked): this run's human is {spec.human.kind!r}")
    if spec.human.adapt:
        raise StoreError(f"--human {partner.split(':')[0]}: this run's human adapted during training, and its state is "
                         "part of the run's; evaluate it with its training human")
    if partner == "proxy":
        other = spec.human.proxy()
    else:
        episodes = tuple(k.strip() for k in partner[len(PLAY_PARTNER):].split(",") if k.strip())
        try:  # the same cloning as the training human's (per seed if it was), from the played episodes
            other = type(spec.human).model_validate({**spec.human.model_dump(), "data": episodes, "split": "train",
                                                     "adapt": False})
        except ValidationError as e:
            raise StoreError(f"--human {partner[:60]}: {specs.first_problem(e)[1]}") from None
    return spec.model_copy(update={"human": other})


def seat_spec(spec, seat: int | None):
    """(spec with the robot in `seat`, the seat if it differs from training's, else None)."""
    if seat is None:
        return spec, None
    if spec.env.kind != "overcooked":
        raise StoreError("--seat: seats are JaxMARL's Overcooked agents; a gridworld has one robot seat")
    if seat not in (0, 1):
        raise StoreError(f"--seat: 0 or 1, got {seat}")
    if seat == spec.env.robot_seat:
        return spec, None
    return spec.model_copy(update={"env": spec.env.model_copy(update={"robot_seat": seat})}), seat


def stored_run(store: Store, ref: str) -> Path:
    """A committed training run named by its key, a key prefix or its path (an unfinished one
    is named as such, with how to finish it)."""
    try:
        path = store.resolve(ref)
    except StoreError:
        try:
            entry = store.find(ref, include_partial=True)
        except StoreError:
            entry = None
        if entry is not None and entry.status == "partial" and (diverged := diverged_at(entry.manifest)):
            raise StoreError(f"{ref} is a training run that diverged ({diverged}; {entry.path}), with no robot to read: "
                             f"{SAME_AGAIN}") from None
        if entry is not None and entry.status == "partial":
            what = "training run" if entry.kind == RUN_KIND else f"{entry.kind} artifact"
            raise StoreError(f"{ref} is an unfinished {what} ({entry.path}): run the command that started it "
                             "again to finish it") from None
        raise
    if store.read_manifest(path).get("kind") != RUN_KIND:
        raise StoreError(f"{ref} is not a training run")
    return path


def run_spec(run_path: Path):
    """The validated spec a run was trained from (its spec.yaml), once it is the spec the run's
    key was computed from: a spec.yaml swapped under a genuine key (an archive's, a damaged
    store's) would make an evaluation or diagnosis of another spec stored as this run's."""
    from esr_cli.storage.transfer import read_spec_yaml, spec_mismatch

    source = run_path / "spec.yaml"
    unfinished = parse_dirname(run_path.name)[1] == "partial"
    record = read_pending(run_path) if unfinished else load_manifest(run_path)
    raw, problem = read_spec_yaml(run_path) if source.exists() else (None, "it has no spec.yaml")
    problem = problem or spec_mismatch(raw, record or {})  # None: a mapping with a human section
    if problem:
        # (`esr verify` checks a finished artifact's files; an unfinished one has no manifest to check them by)
        what = f"remove {run_path} to start it over" if unfinished else f"`esr verify {shlex.quote(str(run_path))}`"
        raise StoreError(f"{run_path}: {problem}; the run cannot be read ({what})")
    # The stored fields are the preset's values when the run trained: read again, a named preset
    # would lay today's table over them (the key is of the values, not the name).
    raw["human"] = {k: v for k, v in raw["human"].items() if k != "preset"}
    try:
        return specs.validate(raw, str(source))
    except specs.SpecError as e:
        raise StoreError(f"{source}: not a spec this esr reads ({printable(str(e))})") from None


def run_record(store: Store, ref: str) -> tuple[Path, dict, bool]:
    """(path, manifest or pending record, finished) of a training run, finished or not; reads
    two small files, so a caller can check its options against the run before loading it."""
    entry = store.find(ref, include_partial=True)
    if entry.kind != RUN_KIND:
        raise StoreError(f"{ref} is not a training run")
    finished = entry.status == "complete"
    record = store.read_manifest(entry.path) if finished else entry.manifest
    if not isinstance(record, dict) or not isinstance(record.get("seeds"), list):
        made = "manifest.json" if finished else "pending.json"
        raise StoreError(f"{entry.path}: its {made} names no list of seeds; the run cannot be inspected")
    return entry.path, record, finished


def exact_artifact(store: Store, ref: str) -> Path:
    """A committed exact-empowerment artifact (`esr exact`) named by its key, prefix or path."""
    path = store.resolve(ref)
    if store.read_manifest(path).get("kind") != EXACT_KIND:
        raise StoreError(f"{ref} is not an exact-empowerment artifact (make one with `esr exact SPEC --robot RUN`)")
    return path


# `esr exact --sample-pairs`: each sampled pair needs up to one row of the occupancy per human
# action, S floats each; beyond this many the sample costs what computing every pair costs.
MAX_SAMPLE_PAIRS = 10_000
MIN_SAMPLE_PAIRS = 30  # below this a bootstrap interval of a rank correlation says little


def exact_defaults(spec) -> tuple[tuple[int, int], float]:
    """The goal cell and discount `esr exact` takes for a gridworld spec unless told: the centre,
    and the future discount ESR's representations were trained with (the critic's otherwise)."""
    return (spec.env.size // 2, spec.env.size // 2), float(getattr(spec.method, "future_gamma", spec.learner.gamma))


def exact_target(spec, store: Store, goal, gamma: float | None, robot: str | None,
                 seed_index: int) -> tuple[tuple[int, int], float, dict | None]:
    """(goal cell, discount, the robot run's manifest or None for a uniform robot) of an exact
    analysis of `spec`, or StoreError naming the option that does not fit: a spec that is not a
    small gridworld, a goal off the grid, a discount outside [0, 1), a robot that is not a run
    on the same environment or a seed it lacks. From the spec and two small files of the run."""
    if spec.env.kind != "gridworld":
        raise StoreError("exact empowerment is defined for gridworld specs only")
    try:  # from the spec alone: enumerating a large space exhausts memory before it can count
        check_size(spec.env.size, spec.env.blocks)
    except TooManyStates as e:
        raise StoreError(f"{spec.name}: {e}") from None
    size = spec.env.size
    default_goal, default_gamma = exact_defaults(spec)
    goal = tuple(goal) if goal else default_goal
    if not all(0 <= g < size for g in goal):
        raise StoreError(f"--goal {goal} is outside the {size}x{size} grid")
    gamma = float(gamma if gamma is not None else default_gamma)
    if not 0.0 <= gamma < 1.0:
        raise StoreError(f"--gamma must be in [0, 1), got {gamma}")
    if not robot:
        return goal, gamma, None
    run_path = stored_run(store, robot)
    robot_spec = run_spec(run_path)
    if robot_spec.env != spec.env:
        raise StoreError(f"robot {robot} was trained on another environment than {spec.name}")
    if robot_spec.method.kind in spec_model.POLICY_FREE_METHODS:  # no Q-values behind its actions
        why = ("which acts uniformly at random: leave out --robot for the uniform robot" if robot_spec.method.kind == "random"
               else "which acts by a rule, not by a policy over Q-values")
        raise StoreError(f"robot {robot} is a {robot_spec.method.kind} run, {why}")
    if not 0 <= seed_index < len(robot_spec.train.seeds):
        raise StoreError(f"--seed-index {seed_index} out of range for a run with {len(robot_spec.train.seeds)} seeds")
    require_networks(run_path)  # before the state space is built
    return goal, gamma, store.read_manifest(run_path)


def geometry_options(gamma: float, state: int) -> None:
    """`esr plot geometry`: a discount in [0, 1) and one of the example MDP's three states."""
    if not 0.0 <= gamma < 1.0:
        raise StoreError(f"--gamma must be in [0, 1), got {gamma}")
    if state not in (0, 1, 2):
        raise StoreError(f"--state must be 0, 1 or 2, got {state}")


def complete_play_key(store: Store, ref: str) -> str:
    """The whole key of the one played episode (`play` artifact) whose key starts with `ref`."""
    if not spec_model.is_play_key_ref(ref):
        raise StoreError(spec_model.not_a_play_key(ref))
    if len(ref) == 32:
        return ref
    hits = [e.key for e in store.entries() if e.kind == PLAY_KIND and e.status == "complete" and e.key.startswith(ref)]
    if len(hits) != 1:
        raise StoreError(f"{ref!r} is the start of {'no' if not hits else len(hits)} played episodes' keys in {store.root}"
                         " (`esr plays` lists them): give a longer prefix or the whole key")
    return hits[0]


def complete_play_keys(spec, store: Store):
    """The spec with any key prefix in `human.data` (or a PPO human's `clone.data`) completed
    from the store's played episodes."""
    human = spec.human
    for owner, field in ((human, "data"), (getattr(human, "clone", None), "data")):
        keys = getattr(owner, field, None) if owner is not None else None
        if keys and any(len(k) != 32 for k in keys):
            full = tuple(complete_play_key(store, k) for k in keys)
            if owner is human:
                human = human.model_copy(update={"data": full})
            else:
                human = human.model_copy(update={"clone": owner.model_copy(update={"data": full})})
    return spec if human is spec.human else spec.model_copy(update={"human": human})


def _lower_if_hex(text: str) -> str:
    return text.lower() if spec_model.is_play_key_ref(text.lower()) else text


def complete_play_partner(store: Store, partner: str) -> str:
    """`play:PREFIX,...` with each prefix completed; any other partner as given."""
    if not partner.startswith(PLAY_PARTNER):
        return partner
    # a key in capitals is the same key; anything else is named as it was typed
    refs = [_lower_if_hex(k.strip()) for k in partner[len(PLAY_PARTNER):].split(",") if k.strip()]
    return PLAY_PARTNER + ",".join(complete_play_key(store, k) for k in refs)

