"""The PPO human as a stored artifact of kind humans: the paper's convolutional actor-critic
(model/humans/conv_actor_critic.py) trained by PPO in Overcooked self-play (model/humans/ppo.py).

Training is long on a CPU (5e6 steps: hours), so the build resumes: every `chunk_updates`
updates, the whole PPO state (parameters, optimiser, environments, key) and the metrics so far
are written atomically to one file in the artifact's partial directory, and the next build of
the same key continues from it, bit-identically. Ctrl-C or SIGTERM stops within a fraction of
a second (runner/stop_requests.py), keeping the last checkpoint.

When training ends the human is checked before it is stored: its parameters must be finite,
and its self-play return at least `min_selfplay_return`; a human that fails is refused with
one line and its partial directory removed. The manifest records its returns over
`eval_episodes` episodes beside a uniform random partner, a partner that only stays, and
itself, and the training curve is in metrics.jsonl.
"""

from __future__ import annotations

import io
import json
import shutil
import time
from pathlib import Path

import jax
import numpy as np
from flax import serialization
from rich.console import Console

from esr_cli.common import bounded_files
from esr_cli.model.envs.overcooked import Overcooked
from esr_cli.model.humans import bc, conv_actor_critic as cac, human_eval, ppo
from esr_cli.recipes import human_runs
from esr_cli.runner.stop_requests import StopRequests
from esr_cli.storage import provenance
from esr_cli.storage.artifacts import Recipe
from esr_cli.storage.store import HUMAN_KIND, Store, StoreError, atomic_write_bytes, atomic_write_text, content_key

PPO_SOURCES = ("model/envs/overcooked.py", "model/humans/ppo.py", "model/humans/conv_actor_critic.py", "model/humans/human_eval.py")
CHECKPOINT_FILE = "ppo_state.npz"
CHECKPOINT_METRICS_BYTES = 64 << 20  # beside the state: each update's metrics (a few KiB per thousand updates)
METRICS_FILE = "metrics.jsonl"
EPISODE_STEPS = 400  # the paper's Overcooked horizon, in training and in the recorded returns


def ppo_config(human_spec) -> ppo.PPOConfig:
    fields = {k: getattr(human_spec, k) for k in ("total_steps", "num_envs", "rollout_steps", "lr", "ent_coef",
                                                  "random_partner")}
    if human_spec.mode == "bc_kl":
        fields["kl_coef"] = human_spec.kl_coef
    return ppo.mode_config(human_spec.mode, **fields)


def ppo_human_key(human_spec, layout: str) -> tuple[str, dict]:
    part = human_spec.training_part(layout)
    clone = human_spec.bc_clone()
    dependencies = {HUMAN_KIND: human_runs.human_key(clone, part["layout"])[0]} if clone else {}
    components = {
        "kind": "human",
        "trainer": "ppo",
        "spec": part,
        "code": provenance.code_digest(PPO_SOURCES),
        "packages": {"jaxmarl": human_runs._version("jaxmarl")},
        "toolchain": provenance.toolchain(),
        "dependencies": dependencies,
    }
    return content_key(components), components


# ---------------------------------------------------------------- checkpoints
def save_checkpoint(out: Path, runner: ppo.RunnerState, history: dict[str, list]) -> None:
    """The PPO state and the metrics so far, in one file replaced atomically."""
    arrays = {f"state_{i}": np.asarray(leaf) for i, leaf in enumerate(jax.tree.leaves(runner))}
    arrays.update({f"metric_{name}": np.asarray(values, np.float64) for name, values in history.items()})
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    atomic_write_bytes(out / CHECKPOINT_FILE, buffer.getvalue())


def load_checkpoint(out: Path, like: ppo.RunnerState) -> tuple[ppo.RunnerState, dict[str, list]] | None:
    """The state and metrics saved in `out`, shaped as `like`; None where there is none. A file
    that does not fit `like` is an error: the partial directory belongs to this key."""
    path = out / CHECKPOINT_FILE
    if not path.exists() and not path.is_symlink():  # anything else there is read, or refused by name
        return None
    leaves, treedef = jax.tree.flatten(like)
    # The state's own size, and room for the metrics of every update: a file that unpacks to more is not this human's.
    most = sum(getattr(leaf, "nbytes", None) or np.asarray(leaf).nbytes for leaf in leaves) + CHECKPOINT_METRICS_BYTES
    try:
        f = bounded_files.load_npz(path, most)
    except (bounded_files.UnreadableInput, OSError) as e:
        raise StoreError(f"{path} cannot be read ({e}): remove it to start the human afresh") from None
    saved = [f[f"state_{i}"] for i in range(len(leaves)) if f"state_{i}" in f]
    history = {k[len("metric_"):]: f[k].tolist() for k in f if k.startswith("metric_")}
    bad = len(saved) != len(leaves) or any(a.shape != np.shape(b) or a.dtype != np.asarray(b).dtype for a, b in zip(saved, leaves))
    if bad:
        raise StoreError(f"{path} does not hold this human's PPO state: remove it to start the human afresh")
    return jax.tree.unflatten(treedef, [jax.numpy.asarray(a) for a in saved]), history


# ---------------------------------------------------------------- checks and returns
def params_problem(params) -> str | None:
    if not all(bool(np.isfinite(np.asarray(leaf)).all()) for leaf in jax.tree.leaves(params)):
        return "its parameters are not all finite (NaN or inf)"
    return None


# ---------------------------------------------------------------- the recipe
def ppo_human_recipe(human_spec, layout: str, console: Console) -> Recipe:
    """The PPO human of `human_spec` on `layout` (its own layout if it names one)."""
    key, components = ppo_human_key(human_spec, layout)
    layout = human_spec.layout or layout
    clone_spec = human_spec.bc_clone()
    clone = human_runs.human_recipe(clone_spec, layout, console) if clone_spec else None
    config = ppo_config(human_spec)

    def build(out: Path, store: Store) -> dict:
        env = Overcooked(layout, EPISODE_STEPS)
        clone_logits = None
        if clone is not None:
            clone_params = human_runs.load_params(store.lookup(HUMAN_KIND, clone.key))
            apply = bc.cloned_policy(clone_spec).logits
            clone_logits = lambda obs: apply(clone_params, obs)  # noqa: E731
        trainer = ppo.overcooked_ppo(env, config, clone_logits)
        fresh = trainer.init(jax.random.PRNGKey(human_spec.seed))
        resumed = load_checkpoint(out, fresh)
        runner, history = resumed or (fresh, {name: [] for name in ppo.METRICS})
        done, total = int(runner.update), config.num_updates
        if resumed:
            console.print(f"PPO human {key[:12]} ({layout}): resuming at update {done:,} of {total:,}")

        def stopping(signum, kept):
            console.print(f"stopping: the human keeps its checkpoint of update {kept:,} (a second signal exits at once)")

        requests = StopRequests(on_stop=stopping, unit="update")
        started, first = time.monotonic(), done
        with requests.installed():
            while done < total:
                n = min(human_spec.chunk_updates, total - done)
                runner, metrics = requests.wait(lambda: jax.block_until_ready(trainer.run(runner, n)), kept=done)
                for name, values in metrics.items():
                    history[name].extend(np.asarray(values, np.float64).tolist())
                done = int(runner.update)
                requests.wait(lambda: save_checkpoint(out, runner, history), kept=done, abandon=False)
                requests.check(done)
                per_update = (time.monotonic() - started) / (done - first)
                console.print(progress_line(key, layout, done, total, history, per_update))
        return finish(out, runner, history, env)

    def finish(out: Path, runner, history: dict, env: Overcooked) -> dict:
        params = runner.params
        problem = params_problem(params)
        returns = None
        if problem is None:
            with console.status(f"PPO human {key[:12]}: {human_spec.eval_episodes} episodes with each partner"):
                returns = human_eval.partner_returns(env, cac.policy_logits, params, human_spec.eval_episodes, human_spec.seed)
            if returns["self"]["mean"] < human_spec.min_selfplay_return:
                problem = (f"its self-play return is {returns['self']['mean']:.2f} over {human_spec.eval_episodes} episodes, "
                           f"below human.min_selfplay_return={human_spec.min_selfplay_return:g}")
        if problem:
            shutil.rmtree(out, ignore_errors=True)  # nothing of it is kept: a new build starts afresh
            raise StoreError(f"PPO human {key[:12]} ({layout}) refused: {problem}; not stored")
        (out / human_runs.PARAMS_FILE).write_bytes(serialization.msgpack_serialize(serialization.to_state_dict(params)))
        atomic_write_text(out / human_runs.POLICY_FILE, json.dumps({
            "layout": layout, "network": "conv_actor_critic", "parameters": cac.parameter_count(params), "actions": 6,
            "input": "agent's own view, JaxMARL (H, W, 26) read transposed as overcooked-ai's (W, H, 26), urgency kept"}))
        write_metrics(out / METRICS_FILE, history, config.steps_per_update)
        (out / CHECKPOINT_FILE).unlink(missing_ok=True)  # the finished human is its parameters
        console.print(f"PPO human {key[:12]} ({layout}): self-play {returns['self']['mean']:.1f}, with a random partner "
                      f"{returns['random']['mean']:.1f}, with a staying one {returns['stay']['mean']:.1f}")
        last = {name: _last_mean(values) for name, values in history.items()}
        return {
            "layout": layout,
            "mode": human_spec.mode,
            "updates": int(runner.update),
            "environment_steps": int(runner.update) * config.steps_per_update,
            "partner_returns": returns,
            "training": {name: last[name] for name in ("episode_return", "entropy", "kl_to_clone", "approx_kl")},
            "return": {"mean": returns["random"]["mean"], "of": "with a uniform random partner"},
        }

    return Recipe(HUMAN_KIND, f"ppo_{layout}", components, build, requires=(clone,) if clone else (),
                  summary_file=False, keeps_partial=True)


def _last_mean(values: list, fraction: float = 0.1) -> float | None:
    """The mean of the finite values in the last `fraction` of training (None if none)."""
    tail = np.asarray(values[-max(1, int(len(values) * fraction)):], np.float64)
    tail = tail[np.isfinite(tail)]
    return round(float(tail.mean()), 4) if tail.size else None


def write_metrics(path: Path, history: dict[str, list], steps_per_update: int) -> None:
    rows = []
    for i in range(len(history["loss"])):
        row = {"update": i + 1, "environment_steps": (i + 1) * steps_per_update}
        row.update({name: (None if not np.isfinite(v[i]) else round(float(v[i]), 6)) for name, v in history.items()})
        rows.append(json.dumps(row))
    atomic_write_text(path, "\n".join(rows) + "\n")


def progress_line(key: str, layout: str, done: int, total: int, history: dict, per_update: float) -> str:
    recent = np.asarray(history["episode_return"][-50:], np.float64)
    recent = recent[np.isfinite(recent)]
    ret = f"{recent.mean():.1f}" if recent.size else "-"
    left = (total - done) * per_update
    return (f"PPO human {key[:12]} ({layout}): update {done:,}/{total:,}, self-play return (last 50 updates) {ret}; "
            f"{per_update:.2f} s per update, about {left / 60:,.0f} min left")
