"""Speed of the PPO human's training (`make bench-human`). Not a test: it prints figures.

For each layout, in a fresh subprocess: the compile time of a scan of updates, then seconds per
PPO update (one 2,048-step rollout of 16 environments and 16 minibatch gradient steps of both
towers, the `shaped` recipe of docs/overcooked.md), and the hours a 1e6-step and a 5e6-step
human take at that rate. It also measures this machine's float32 matmul peak, for scale: the
machines this runs on vary, and a human's cost is read against it.

    python benchmarks/bench_human.py                          # the paper's three layouts
    python benchmarks/bench_human.py --layouts cramped_room --updates 4
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

from bench import matmul_peak_gflops

ROOT = Path(__file__).resolve().parents[1]
LAYOUTS = ("cramped_room", "coord_ring", "asymm_advantages")


def one(layout: str, updates: int, random_partner: float) -> dict:
    import jax

    from esr_cli.model.envs.overcooked import Overcooked
    from esr_cli.model.humans import ppo

    config = ppo.mode_config("shaped", random_partner=random_partner)
    trainer = ppo.overcooked_ppo(Overcooked(layout, 400), config)
    runner = trainer.init(jax.random.PRNGKey(0))
    t = time.perf_counter()
    compiled = type(trainer).run.lower(trainer, runner, updates).compile()  # static: the trainer and the count
    compile_s = time.perf_counter() - t
    jax.block_until_ready(compiled(runner))  # a warm-up call
    t = time.perf_counter()
    jax.block_until_ready(compiled(runner))
    per_update = (time.perf_counter() - t) / updates
    return {"layout": layout, "updates": updates, "random_partner": random_partner, "compile_s": round(compile_s, 1),
            "s_per_update": round(per_update, 3), "steps_per_update": config.steps_per_update,
            "hours_1e6": round(per_update * 1_000_000 / config.steps_per_update / 3600, 2),
            "hours_5e6": round(per_update * 5_000_000 / config.steps_per_update / 3600, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--layouts", nargs="+", choices=LAYOUTS, default=list(LAYOUTS))
    ap.add_argument("--updates", type=int, default=2, help="updates per timed scan")
    ap.add_argument("--random-partner", type=float, default=0.5)
    ap.add_argument("--out", default="benchmarks/results_human.json")
    ap.add_argument("--one", nargs=3, help=argparse.SUPPRESS)  # internal: layout updates random_partner
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one[0], int(args.one[1]), float(args.one[2]))))
        return
    import jax

    peak = matmul_peak_gflops()
    rows = []
    for layout in args.layouts:
        proc = subprocess.run([sys.executable, __file__, "--one", layout, str(args.updates), str(args.random_partner)],
                              cwd=ROOT, capture_output=True, text=True, check=True)
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        print(f"{layout:18s} compile {r['compile_s']:6.1f} s  {r['s_per_update']:7.3f} s/update  "
              f"1e6 steps {r['hours_1e6']:5.2f} h  5e6 steps {r['hours_5e6']:6.2f} h", flush=True)
    device = jax.devices()[0]
    result = {"device": f"{device.platform}: {device.device_kind}", "cpu_count": os.cpu_count(),
              "affinity": len(os.sched_getaffinity(0)), "machine": platform.machine(), "jax": jax.__version__,
              "matmul_peak_gflops": round(peak, 1), "rows": rows, "measured_at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"matmul peak {peak:.0f} GFLOP/s on {result['device']} ({result['affinity']} of {result['cpu_count']} cores); "
          f"written {args.out}")


if __name__ == "__main__":
    main()
