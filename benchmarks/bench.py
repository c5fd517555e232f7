"""Speed and memory of the training core (`make bench`). Not a test: it prints figures.

For each configuration and each number of seeds vmapped in one program, in a fresh
subprocess (so peak memory is that program's alone):
  compile time (ahead-of-time lowering + compile of one chunk), seconds per epoch,
  environment steps per second, gradient updates per second, achieved GFLOP/s (XLA's own
  count of one epoch's floating-point work), and peak resident memory.
It also measures this machine's float32 matmul peak, for scale.

Output: a table on stdout, a JSON file (--out), and a last line with the headline figure
(gridworld paper configuration, seconds per epoch, 1 seed).

    python benchmarks/bench.py                 # grid_2 paper config; seeds 1, 5, 20
    python benchmarks/bench.py --seeds 1 --epochs 2
    python benchmarks/bench.py --phases        # where one epoch's time goes, phase by phase

--phases times the configuration's epoch whole and with each phase's updates set to none (the
representation updates; the critic's, with the reward table they read; the dual's, with the Q
table they read), each in a fresh process, so that every phase is timed inside the real epoch
program: a phase's cost is the whole epoch's time less the time without it, and the rollout's
(with the buffer and the metrics) the time with no updates at all.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAPER_EPOCHS = 10_000  # the paper's run length: the "10k ep h" column is one run's hours
CONFIGS = {"gridworld grid_2 (paper)": "experiments/grid_2.yaml", "overcooked cramped_room (paper)": "experiments/cramped_room.yaml"}


def matmul_peak_gflops(n: int = 2048, reps: int = 10) -> float:
    import jax
    import jax.numpy as jnp

    from esr_cli.storage.provenance import apply_matmul_precision

    # At the precision the measured programs use: JAX's own default would let a GPU use TF32,
    # a peak several times the float32 one the programs are held to.
    apply_matmul_precision()
    a = jax.random.normal(jax.random.PRNGKey(0), (n, n), jnp.float32)
    f = jax.jit(lambda x: x @ x)
    f(a).block_until_ready()
    t = time.perf_counter()
    for _ in range(reps):
        out = f(a)
    out.block_until_ready()
    return 2 * n**3 * reps / (time.perf_counter() - t) / 1e9


def epoch_flops(trainer) -> float:
    """XLA's flop count of one epoch, phase by phase as `Trainer.epoch` runs them (XLA counts a
    loop's body once, so each body is counted alone and multiplied by its trip count)."""
    import jax

    from esr_cli.model import replay

    spec = trainer.spec
    state = trainer.init(0)
    buf = state.buffer
    b, fg = spec.learner.batch_size, trainer.future_gamma
    idx = replay.sample_index(buf, jax.random.PRNGKey(0), b, fg)
    batch = replay.gather(buf, idx)
    episodes, steps = buf.robot_action.shape

    def flops(fn, *args):
        cost = jax.jit(fn).lower(*args).compile().cost_analysis()
        cost = cost[0] if isinstance(cost, (list, tuple)) else cost
        return float(cost.get("flops", 0.0))

    def per_episode_table(fn, *arrays):
        """Flops of a table built a few episodes per call, scaled to the whole buffer."""
        per_call = replay.episodes_per_call(steps)
        part = flops(fn, *[a[:per_call] for a in arrays])
        return part * episodes / per_call

    # The rollout's scan body is counted once: scale by the episode length.
    total = steps * flops(lambda l, k: trainer.rollout(l, k, spec.train.num_envs), state.learner, jax.random.PRNGKey(1))
    m, learner = trainer.method, trainer.learner
    if m.updates_per_epoch:
        total += m.updates_per_epoch * flops(lambda s, bt: m.update(s, bt, jax.random.PRNGKey(2)), state.method, batch)
    if not m.learns_policy:
        return total
    step = lambda l, r, bt: learner.critic_step(l, bt.obs, bt.robot_action, r, bt.next_obs, bt.done)  # noqa: E731
    if trainer.reward_table_pays:
        total += per_episode_table(
            lambda o, ra, ha, r: m.reward_table(state.method, buf._replace(obs=o, robot_action=ra, human_action=ha, reward=r)),
            buf.obs, buf.robot_action, buf.human_action, buf.reward,
        )
        critic = lambda l, bt: step(l, bt.reward, bt)  # noqa: E731 - the lookup itself is no flops
    else:
        critic = lambda l, bt: step(l, m.reward(state.method, bt, jax.random.PRNGKey(3)), bt)  # noqa: E731
    total += spec.learner.updates_per_epoch * flops(critic, state.learner, batch)
    q = learner.q_values(state.learner.params, batch.obs)
    if trainer.q_table_pays:
        total += per_episode_table(lambda o: learner.q_table(state.learner, o), buf.obs[:, :-1])
        total += spec.learner.dual_updates_per_epoch * flops(learner.dual_step_q, state.learner, q)
    else:
        total += spec.learner.dual_updates_per_epoch * flops(learner.dual_step, state.learner, batch.obs)
    return total


def measure(spec_path: str, seeds: int, epochs: int, seed_batch: int | None, sets: tuple[str, ...] = ()) -> dict:
    """One configuration in this process (with `sets`, --set overrides): -> figures."""
    import resource

    import jax
    import jax.numpy as jnp

    from esr_cli.common import specs
    from esr_cli.model.train import compiled_chunk, compiled_init
    from esr_cli.recipes.runs import build_trainer
    from esr_cli.storage.provenance import apply_matmul_precision
    from esr_cli.storage.store import Store

    apply_matmul_precision()  # as training does (ESR_MATMUL_PRECISION)
    spec = specs.load(ROOT / spec_path, "paper", [f"train.seeds={seeds}", f"train.chunk_epochs={epochs}", *sets])
    store = Store(os.environ.get("ESR_STORE") or ROOT / "artifacts")
    if spec.human.kind == "bc":  # the BC human of an Overcooked spec: built once, then stored
        from esr_cli.common.printing import plain_console
        from esr_cli.recipes.human_runs import human_recipe
        from esr_cli.storage.artifacts import ensure

        ensure(human_recipe(spec.human, spec.env.layout, plain_console(stderr=True)), store)
    trainer = build_trainer(spec, store)
    state = compiled_init(trainer)(jnp.asarray(spec.train.seeds, jnp.int32))
    chunk = compiled_chunk(trainer, epochs, seed_batch)
    t = time.perf_counter()
    compiled = chunk.lower(state).compile()
    compile_s = time.perf_counter() - t
    state, m = compiled(state)  # warm-up: first call touches all buffers
    jax.block_until_ready(m)
    t = time.perf_counter()
    state, m = compiled(state)
    jax.block_until_ready(m)
    per_epoch = (time.perf_counter() - t) / epochs
    steps = spec.train.num_envs * trainer.env.episode_steps * seeds
    updates = (
        trainer.method.updates_per_epoch
        + (spec.learner.updates_per_epoch + spec.learner.dual_updates_per_epoch) * trainer.method.learns_policy
    ) * seeds
    flops = epoch_flops(trainer) * seeds
    return {
        "config": spec_path,
        "sets": list(sets),
        "seeds": seeds,
        "seed_batch": "all" if seed_batch is None else seed_batch,
        "num_envs": spec.train.num_envs,
        "compile_s": round(compile_s, 2),
        "s_per_epoch": round(per_epoch, 3),
        "env_steps_per_s": round(steps / per_epoch),
        "updates_per_s": round(updates / per_epoch, 1),
        "gflop_per_epoch": round(flops / 1e9, 1),
        "gflops": round(flops / per_epoch / 1e9, 1),
        "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "device_peak_mib": _device_peak_mib(),
        "device": device_name(),
        "paper_run_hours": round(per_epoch * PAPER_EPOCHS / 3600, 2),
    }


def device_name() -> str:
    """The device the programs ran on, by kind (e.g. 'gpu:NVIDIA H100 80GB HBM3', 'cpu:cpu')."""
    from esr_cli.storage.provenance import device

    return device()


def _device_peak_mib():
    """Peak memory the accelerator allocator held (None on the CPU, which reports none)."""
    import jax

    stats = jax.devices()[0].memory_stats() or {}
    peak = stats.get("peak_bytes_in_use")
    return None if peak is None else round(peak / 2**20)


def _seed_batch(text: str):
    from esr_cli.model.train import default_seed_batch

    if text == "auto":
        return default_seed_batch()
    return None if text == "all" else int(text)


def _measure_in_child(path: str, seeds: int, epochs: int, seed_batch: str, sets: tuple[str, ...] = ()) -> dict:
    """`measure` in a fresh process: its memory and compiled programs are its own."""
    proc = subprocess.run([sys.executable, __file__, "--one", path, str(seeds), str(epochs), seed_batch, *sets],
                          capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        print(proc.stderr, file=sys.stderr)
        raise SystemExit(f"benchmark of {path} {' '.join(sets)} with {seeds} seeds failed")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# Each phase of an epoch, and the --set values that leave it out (its table goes with it: the
# reward table is built only for a critic phase, the Q table only for a dual phase).
PHASES = {
    "representation updates": ("method.repr_updates_per_epoch=0",),
    "critic updates, with the reward table": ("learner.updates_per_epoch=0",),
    "dual updates, with the Q table": ("learner.dual_updates_per_epoch=0",),
}


def phases(configs: list[str], seeds: int, epochs: int, seed_batch: str, out: str) -> None:
    """Each phase's seconds per epoch: the whole epoch less the epoch without that phase."""
    rows = []
    for name in configs:
        path = CONFIGS[name]
        print(f"measuring {name}, {seeds} seed(s): the whole epoch, then without each phase...", file=sys.stderr, flush=True)
        whole = _measure_in_child(path, seeds, epochs, seed_batch)
        print(f"device: {whole['device']}\n{name}, {seeds} seed(s): {whole['s_per_epoch']:.3f} s per epoch", flush=True)
        none = _measure_in_child(path, seeds, epochs, seed_batch, tuple(s for sets in PHASES.values() for s in sets))
        parts = {phase: whole["s_per_epoch"] - _measure_in_child(path, seeds, epochs, seed_batch, sets)["s_per_epoch"]
                 for phase, sets in PHASES.items()}
        parts["rollout, buffer and metrics (no updates)"] = none["s_per_epoch"]
        for phase, t in parts.items():
            print(f"  {phase:44} {t:7.3f} s  {100 * t / whole['s_per_epoch']:5.1f}%", flush=True)
        rest = whole["s_per_epoch"] - sum(parts.values())
        print(f"  {'left over (phases overlapping or noise)':44} {rest:7.3f} s  {100 * rest / whole['s_per_epoch']:5.1f}%", flush=True)
        rows.append({"name": name, "seeds": seeds, "epochs_timed": epochs, "device": whole["device"],
                     "s_per_epoch": whole["s_per_epoch"], "phases_s": {k: round(v, 3) for k, v in parts.items()},
                     "left_over_s": round(rest, 3)})
        _write(out, {"results": rows})
    print(f"wrote {out}")


def _write(path: str, results: dict) -> None:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(results, indent=2))
    tmp.replace(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 5, 20])
    ap.add_argument("--epochs", type=int, default=3, help="epochs per timed chunk")
    ap.add_argument("--configs", nargs="+", choices=sorted(CONFIGS), default=sorted(CONFIGS),
                    help="which configurations (default: all)")
    ap.add_argument("--seed-batch", default="auto",
                    help="seeds vmapped side by side, the rest one after another: auto (all on an "
                         "accelerator, 1 on the CPU), all, or a number")
    ap.add_argument("--out", help="the JSON file (default: benchmarks/results.json, or with --phases "
                    "benchmarks/results_phases.json)")
    ap.add_argument("--phases", action="store_true", help="time each phase of one epoch (the first of --seeds, each "
                    "of --configs) instead; writes benchmarks/results_phases.json unless --out is given")
    ap.add_argument("--one", nargs="+", help=argparse.SUPPRESS)  # internal: spec seeds epochs seed_batch [sets...]
    args = ap.parse_args()
    if args.one:
        path, n, epochs, batch, *sets = args.one
        print(json.dumps(measure(path, int(n), int(epochs), _seed_batch(batch), tuple(sets))))
        return
    if args.phases:
        phases(args.configs, args.seeds[0], args.epochs, args.seed_batch, args.out or "benchmarks/results_phases.json")
        return
    args.out = args.out or "benchmarks/results.json"

    # The parent touches no device until the children are done: on a GPU, jax would otherwise
    # take most of its memory for itself and the children would run out.
    rows = []
    header = (f"{'configuration':28} {'seeds':>5} {'compile s':>9} {'s/epoch':>8} {'10k ep h':>8} {'steps/s':>9} {'updates/s':>9} "
              f"{'GFLOP/ep':>8} {'GFLOP/s':>8} {'host MiB':>8} {'dev MiB':>8} device")
    for name in args.configs:
        path = CONFIGS[name]
        for n in args.seeds:
            print(f"measuring {name}, {n} seed(s)...", file=sys.stderr, flush=True)
            r = {"name": name, **_measure_in_child(path, n, args.epochs, args.seed_batch)}
            rows.append(r)
            if len(rows) == 1:  # the device as the first child saw it, before any figure
                print(f"device: {r['device']}\n{header}", flush=True)
            dev = "" if r.get("device_peak_mib") is None else f"{r['device_peak_mib']:,}"
            # Each row as soon as it is measured, on stdout and in --out: a run cut short keeps them.
            print(
                f"{r['name']:28} {r['seeds']:>5} {r['compile_s']:>9.1f} {r['s_per_epoch']:>8.3f} {r['paper_run_hours']:>8.2f} "
                f"{r['env_steps_per_s']:>9,} {r['updates_per_s']:>9.1f} {r['gflop_per_epoch']:>8.1f} {r['gflops']:>8.1f} "
                f"{r['peak_rss_mib']:>8} {dev:>8} {r['device']}", flush=True
            )
            _write(args.out, {"machine": None, "results": rows})

    import jax

    peak = matmul_peak_gflops()
    machine = {
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "device": device_name(),
        "matmul_precision": os.environ.get("ESR_MATMUL_PRECISION", "") or "highest",
        "jax": jax.__version__,
        "matmul_peak_gflops": round(peak, 1),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }
    print(f"machine: {machine}")
    for r in rows:
        print(f"{r['name']:28} {r['seeds']:>5}: {100 * r['gflops'] / peak:.1f}% of the matmul peak")
    one = next((r for r in rows if r["seeds"] == 1), None)
    for r in rows:
        if one is not None and r["seeds"] > 1 and r["name"] == one["name"]:  # no 1-seed row: no ratio
            print(f"{r['seeds']} seeds: {r['s_per_epoch'] / one['s_per_epoch']:.2f}x the 1-seed time per epoch ({r['seeds']}x would be no gain from vmap)")
    _write(args.out, {"machine": machine, "results": rows})
    print(f"wrote {args.out}")
    head = one or rows[0]
    print(f"headline on {machine['device']}: {head['name']}, {head['seeds']} seed(s): {head['s_per_epoch']:.3f} s per epoch "
          f"({head['gflops']:.0f} GFLOP/s, matmul peak {peak:.0f})")


if __name__ == "__main__":
    main()
