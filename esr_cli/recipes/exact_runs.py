"""Exact-empowerment artifacts (`esr exact`) and the estimator check (`esr plot estimator`).

An exact artifact holds, for one gridworld spec, goal, discount and robot policy (uniform or
a trained run's Boltzmann policy), the exact I(aH; s+ | s, aR) for every reachable state and
robot action, and the effective empowerment (esr_cli/analysis/exact.py).
"""

from __future__ import annotations

import functools
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from scipy.stats import spearmanr

from esr_cli.analysis import exact, geometry
from esr_cli.common import bounded_files, plots
from esr_cli.model.envs import make_env
from esr_cli.model.envs.gridworld import GridState
from esr_cli.model.humans.registry import make_human
from esr_cli.recipes.runs import load_run, seed_slice
from esr_cli.recipes.targets import exact_artifact, exact_target, geometry_options
from esr_cli.storage import provenance
from esr_cli.storage.artifacts import Recipe
from esr_cli.storage.store import EXACT_ARRAYS, EXACT_KIND, FIGURE_KIND, Store, StoreError, kept_without

# The code behind an exact analysis: the environment, human and evaluation path with the
# analysis package (their import closure), and this module's own steps, but not the store,
# checkpoint and figure plumbing it imports: those decide where numbers are read and written,
# never what they are, and an edit there should not discard hours of exact computation.
# (The robot's training code is pinned by its run's key, a component of its own.)
EXACT_CODE = (provenance.MODEL_SOURCES + ("analysis",), ("recipes/exact_runs.py",))
# What esr reads of an exact check's arrays: the 4 x 4 grid with 4 blocks writes about 20 MB; a
# space large enough to pass this is refused before it is enumerated.
MAX_EXACT_ARRAYS_BYTES = 2 << 30


def exact_recipe(spec, store: Store, goal, gamma: float | None, robot: str | None, seed_index: int,
                 console: Console, sample_pairs: int = 0) -> Recipe:
    """Exact empowerment of `spec`'s gridworld at `goal` and discount `gamma`, for a uniform
    robot or the Boltzmann policy of seed `seed_index` of the trained run `robot`. Where the
    space is too large for every pair (above exact.DENSE_STATES), `sample_pairs` more pairs drawn
    uniformly from all of them are computed beside the visited ones, for a rank correlation that
    stands for all pairs (`esr plot estimator`); they do not enter the effective empowerment."""
    # the cell named in an error: the user's --goal, or the default they did not choose
    goal_named = "--goal {}" if goal is not None else "the default goal {} (the centre; --goal names another)"
    goal, gamma, robot_manifest = exact_target(spec, store, goal, gamma, robot, seed_index)
    components = {
        "kind": "exact",
        "env": spec.training_part()["env"],
        "human": spec.training_part()["human"],
        "goal": list(goal),
        "gamma": gamma,
        "robot": {"run": robot_manifest["key"], "seed_index": seed_index} if robot_manifest else "uniform",
        "code": provenance.code_digest(*EXACT_CODE),
        "toolchain": provenance.toolchain(),
    }
    if sample_pairs:  # absent otherwise: the artifacts made before the option keep their keys
        components["sample_pairs"] = sample_pairs

    @functools.cache  # drawn once, for the check and the build (never on a cache hit)
    def start_states():
        return exact.start_states(make_env(spec.env), goal)

    def build(out: Path, store: Store) -> dict:
        env = make_env(spec.env)
        human = make_human(spec.human, env)
        with console.status("enumerating reachable states"):
            try:
                space = exact.enumerate_states(env, goal, start_states(), max_states=exact.MAX_STATES)
            except exact.TooManyStates as e:
                raise StoreError(f"{spec.name}: {e}") from None
        console.print(f"{space.size} reachable states, {env.num_robot_actions} robot actions")
        pi_h = exact.human_policy(space, human)
        if robot:
            _, _, trainer, state = load_run(store, robot_manifest["key"])
            lstate = seed_slice(state.learner, seed_index)
            pi_r = exact.boltzmann_robot(space, lambda obs: trainer.learner.log_probs(lstate, obs))
        else:
            pi_r = exact.uniform_robot(space)
        emp, sampled = _solve(space, pi_r, pi_h, gamma, console, sample_pairs)
        arrays = {} if sampled is None else {"sampled": sampled}
        np.savez_compressed(
            out / EXACT_ARRAYS, human=space.human, blocks=space.blocks, next_state=space.next_state, start=space.start,
            pi_human=pi_h, pi_robot=pi_r, mi=emp.mi, mi_merged=emp.mi_merged, state_mi=emp.state_mi, value=emp.value,
            **arrays,
        )
        # the summary's means are over the counted pairs: a sample's pairs stand for ranking only
        counted, merged = (np.where(emp.counted, m, np.nan) for m in (emp.mi, emp.mi_merged))
        pairs = "all" if emp.complete else f"visited ({exact.VISITED_MASS:.0%} of the robot's occupancy)"
        return {
            "name": spec.name, "goal": list(goal), "gamma": gamma, "states": space.size,
            "robot": components["robot"],
            "effective_empowerment": emp.effective_empowerment,
            # over every state alike: only where every pair was computed
            "mean_mi_uniform_states": float(emp.state_mi.mean()) if emp.complete else None,
            "mean_mi_visited": _visited_mean(emp, pi_r, counted),
            # what a robot that infers the human's action from (s, s') could at most see
            "mean_mi_visited_merged_actions": _visited_mean(emp, pi_r, merged),
            "max_mi": float(np.nanmax(counted)),
            "states_with_zero_mi": int((emp.state_mi < 1e-9).sum()) if emp.complete else None,
            # above exact.DENSE_STATES only the robot's visited pairs: the rest count 0 in
            # state_mi and value, so the effective empowerment is then a lower bound
            "pairs": pairs if sampled is None or emp.complete else f"{pairs} and a uniform sample of {int(sampled.sum()):,}",
            "pairs_computed": int(np.isfinite(emp.mi).sum()),
            **({} if sampled is None else {"sample_pairs": int(sampled.sum())}),
        }

    def check(store: Store) -> None:  # before anything is written: the goal must leave some start free
        if not len(start_states().t):
            raise StoreError(f"{goal_named.format(goal)}: no start state of {spec.name} leaves this cell free "
                             f"(the human starts there or a block always covers it): choose another cell")

    return Recipe(EXACT_KIND, spec.name, components, _discard_on_failure(build), budget=spec.budget, check=check)


def _solve(space, pi_r: np.ndarray, pi_h: np.ndarray, gamma: float, console: Console,
           sample_pairs: int = 0) -> tuple[exact.Empowerment, np.ndarray | None]:
    """exact.empowerment over every pair, or over the robot's visited pairs (and a uniform sample
    of `sample_pairs` pairs, computed but not counted) where the space is too large for the dense
    solve (the sparse series costs per row of M wanted), with progress; and the sample (None
    without one)."""
    p = exact.transition_matrix(space, pi_r, pi_h)
    shape = space.next_state.shape[:2]
    sampled = exact.sampled_pairs(shape, sample_pairs) if sample_pairs else None
    if space.size <= exact.DENSE_STATES:
        with console.status(f"solving for occupancies and mutual information ({space.size:,} states)"):
            return exact.empowerment(space, pi_r, pi_h, gamma, occupancy=exact.solve_occupancy(p, gamma)), sampled
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  console=console, transient=True) as bar:
        task = bar.add_task("visitation", total=1)
        occ = exact.solve_occupancy(p, gamma, progress=lambda n: bar.advance(task, n))
        visited = exact.visited_pairs(occ, space.start, pi_r)
        pairs = visited if sampled is None else visited | sampled
        rows = exact.rows_needed(space, pairs)
        extra = "" if sampled is None else f" and {int(sampled.sum()):,} sampled"
        console.print(f"{int(visited.sum()):,} visited{extra} (state, robot action) pairs need {rows:,} rows of the occupancy")
        bar.reset(task, total=rows + 2, description="occupancy rows")  # + value and visitation
        return exact.empowerment(space, pi_r, pi_h, gamma, pairs=pairs, occupancy=occ, counted=visited), sampled


def estimator_recipe(exact_ref: str, store: Store, console: Console) -> Recipe:
    """`esr plot estimator`: a figure artifact (kind `figures`) from an exact artifact."""
    exact_path = exact_artifact(store, exact_ref)
    manifest = store.read_manifest(exact_path)
    components = {"kind": "figure", "figure": "estimator", "exact": manifest["key"],
                  "code": provenance.code_digest(EXACT_CODE[0], EXACT_CODE[1] + ("common/plots.py",))}

    def build(out: Path, store: Store) -> dict:
        return estimator_check(exact_path, store, out / "estimator.png", console)

    return Recipe(FIGURE_KIND, f"estimator-{manifest['name']}", components, _discard_on_failure(build),
                  budget=manifest.get("budget"))


def estimator_check(exact_path: Path, store: Store, out_png: Path | None = None, console: Console | None = None) -> dict:
    """ESR's reward, averaged over g from the exact future distribution, against the exact MI.

    For every (s, aR): est(s, aR) = sum_aH pi_H(aH | s) (phi(s, aR, aH) - phi'(s, aR)) . psibar,
    psibar = sum_g rho(g | s, aR, aH) psi(g). The exact artifact must have been computed for
    the run's own robot (`esr exact SPEC --robot RUN`), so that rho is the future the
    representations were trained on. -> Spearman rank correlation and a scatter plot.
    """
    manifest = store.read_manifest(exact_path)
    if kept_without(EXACT_KIND, exact_path):
        raise StoreError(f"exact {exact_path.name[:12]} was kept without its arrays (esr export --without-checkpoint): "
                         "tables read its summary, but this check needs its state space: compute it again with "
                         "`esr exact` in a store that does not hold it")
    robot = manifest["key_components"]["robot"]
    if robot == "uniform":
        raise StoreError("this exact artifact is for a uniform robot: run `esr exact SPEC --robot RUN` for an ESR run first")
    run_path, run_manifest, trainer, state = load_run(store, robot["run"])
    if trainer.spec.method.kind != "esr":
        raise StoreError("the estimator check needs an ESR run")
    if trainer.spec.method.human_action == "inferred":
        raise StoreError("the estimator check evaluates phi at each true human action; this run infers them "
                         "(method.human_action: inferred), so its phi takes latent codes instead")
    try:
        data = bounded_files.load_npz(exact_path / EXACT_ARRAYS, MAX_EXACT_ARRAYS_BYTES)
    except (bounded_files.UnreadableInput, OSError) as e:
        raise StoreError(f"damaged exact check: {exact_path / EXACT_ARRAYS}: {e}") from None
    mstate = seed_slice(state.method, robot["seed_index"])
    goal = jnp.asarray(manifest["key_components"]["goal"], jnp.int32)
    n = len(data["human"])
    states = GridState(jnp.asarray(data["human"]), jnp.asarray(data["blocks"]), jnp.broadcast_to(goal, (n, 2)), jnp.zeros((n,), jnp.int32))
    env = trainer.env
    obs = jax.vmap(env.observe)(states)
    esr = trainer.method
    psi_all = np.asarray(esr.represent_future(mstate.params, obs), dtype=np.float64)  # [S, d]
    gamma = manifest["key_components"]["gamma"]
    space = exact.StateSpace(env=env, goal=tuple(manifest["key_components"]["goal"]), human=data["human"], blocks=data["blocks"], next_state=data["next_state"], start=data["start"])
    occ = exact.solve_occupancy(exact.transition_matrix(space, data["pi_robot"], data["pi_human"]), gamma)
    psibar = occ.times(psi_all)  # [S, d]: expected psi(g) from each next state
    a_h = env.num_human_actions
    mi = data["mi"]
    computed = np.isfinite(mi)  # every pair, or on large spaces the visited ones (and a sample, if drawn)
    pair_state, pair_action = np.nonzero(computed)

    @jax.jit
    def phis(obs_b, ar_b, ah_b):
        phi_s, phi_sa, _ = esr.represent(mstate.params, obs_b, ar_b, ah_b, obs_b)
        return phi_s, phi_sa

    est = np.full(mi.shape, np.nan)
    chunk = 4096
    # Minutes on a CPU (about 10 for the N = 2 grid's 934,500 pairs): a bar says how far it is.
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  console=console, transient=True, disable=console is None) as bar:
        task = bar.add_task("ESR's reward over the exact future of each (state, robot action) pair", total=len(pair_state))
        for i in range(0, len(pair_state), chunk):
            st, ar = pair_state[i : i + chunk], pair_action[i : i + chunk]
            total = np.zeros(len(st))
            for h in range(a_h):
                phi_s, phi_sa = phis(obs[st], jnp.asarray(ar), jnp.full((len(st),), h))
                diff = np.asarray(phi_sa, np.float64) - np.asarray(phi_s, np.float64)
                total += data["pi_human"][st, h] * np.einsum("bd,bd->b", diff, psibar[data["next_state"][st, ar, h]])
            est[st, ar] = total
            bar.advance(task, len(st))
    rho, _ = spearmanr(est[computed], mi[computed])
    visited = exact.visited_pairs(occ, space.start, data["pi_robot"]) & computed
    rho_visited, _ = spearmanr(est[visited], mi[visited])
    result = {"spearman": float(rho), "pairs": int(computed.sum()), "complete": bool(computed.all()),
              "spearman_visited": float(rho_visited), "visited_pairs": int(visited.sum()), "visited_mass": exact.VISITED_MASS,
              "run": run_manifest["key"], "exact": manifest["key"]}
    if "sampled" in data:  # a uniform sample of all pairs: its rank correlation, with an interval
        sampled = data["sampled"] & computed
        rho_sample, low, high = spearman_interval(est[sampled], mi[sampled])
        result.update({"spearman_sample": rho_sample, "spearman_sample_ci": [low, high], "sample_pairs": int(sampled.sum())})
    if out_png is not None:
        plots.estimator_scatter(mi[computed], est[computed], float(rho), out_png,
                                {"artifacts": {"runs": run_manifest["key"], "exact": manifest["key"]},
                                 "budget": run_manifest.get("budget"), "seeds": run_manifest.get("seeds")})
    return result


def estimator_lines(result: dict) -> list[str]:
    """What `esr plot estimator` prints of a check: its rank correlations, each over its pairs."""
    head = "Spearman rank correlation of ESR's reward with the exact MI"
    if result.get("complete", True):  # checks made before `complete` was recorded were over every pair they had
        lines = [f"{head}: {result['spearman']:.3f} over all {result['pairs']:,} (state, robot action) pairs"]
    elif "spearman_sample" in result:
        low, high = result["spearman_sample_ci"]
        lines = [f"{head}: {result['spearman_sample']:.3f} [95% CI {low:.3f}, {high:.3f}] over a uniform sample of "
                 f"{result['sample_pairs']:,} of all (state, robot action) pairs"]
    else:
        lines = [f"{head}: not over all pairs (the space is solved over the robot's visited pairs; "
                 "`esr exact --sample-pairs N` adds a uniform sample of all pairs)"]
    lines.append(f"  over the {result['visited_pairs']:,} pairs holding {result['visited_mass']:.0%} of the robot's "
                 f"discounted occupancy: {result['spearman_visited']:.3f}")
    return lines


SPEARMAN_RESAMPLES = 2000


def spearman_interval(x: np.ndarray, y: np.ndarray, resamples: int = SPEARMAN_RESAMPLES, seed: int = 0) -> tuple[float, float, float]:
    """Spearman's rho of (x, y) and its 95% percentile bootstrap interval over the pairs (each
    resample draws as many pairs, with replacement, from a fixed generator)."""
    rho = float(spearmanr(x, y)[0])
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(x), size=(resamples, len(x)))
    boot = np.array([spearmanr(x[d], y[d])[0] for d in draws])
    low, high = np.nanpercentile(boot, [2.5, 97.5])
    return rho, float(low), float(high)


def _visited_mean(emp, pi_robot: np.ndarray, mi: np.ndarray | None = None) -> float:
    """Mean MI (emp.mi unless given) under the robot's discounted occupancy, over the pairs computed."""
    mi = emp.mi if mi is None else mi
    weight = emp.visitation[:, None] * pi_robot
    ok = np.isfinite(mi)
    return float(np.sum(weight[ok] * mi[ok]) / np.sum(weight[ok]))


def geometry_recipe(gamma: float, state: int) -> Recipe:
    """`esr plot geometry`: the information-geometry picture of a 3-state MDP (exact)."""
    geometry_options(gamma, state)
    components = {"kind": "figure", "figure": "geometry", "gamma": gamma, "state": state,
                  "code": provenance.code_digest(("analysis", "common/plots.py"))}

    def build(out: Path, store: Store) -> dict:
        geo = geometry.geometry(geometry.example_mdp(), state, gamma)
        plots.information_geometry(geo, gamma, out / "geometry.png", {"artifacts": {}, "budget": None, "seeds": [],
                                                                     "mdp": "analysis.geometry.example_mdp", "state": state,
                                                                     "gamma": gamma}, pdf=True)
        return {"gamma": gamma, "state": state, "mutual_information": geo.mutual_information,
                "uniform_policy_mi": geo.uniform_mi, "capacity_policy": geo.policy.round(6).tolist(),
                "kl_to_centre": geo.kl.round(6).tolist()}

    return Recipe(FIGURE_KIND, "information-geometry", components, _discard_on_failure(build))


def _discard_on_failure(build):
    """A build that removes its partial directory when it fails: unlike a training run these
    artifacts are computed in one go, so a partial one has nothing to resume. The store's lock
    is released by `ensure` either way."""

    def wrapped(out: Path, store: Store) -> dict:
        try:
            return build(out, store)
        except BaseException:
            shutil.rmtree(out, ignore_errors=True)
            raise

    return wrapped
