"""Memory a training run needs, checked against what the machine has before any work
(docs/reliability.md). The estimate is deliberately simple and on the safe side:

  replay buffers  seeds x (buffer episodes x (steps + 1) x observation bytes + 12 bytes a step)
  rollouts        environments x (steps + 1) x (observation bytes x 5 + 64) per seed in flight
  working copies  x2 on both (a chunk's input and output state, XLA's temporaries)
  runtime         1.5 GiB (JAX, compiled programs, the human model)

On the CPU every seed's state lives in host memory and seeds run one after another; on an
accelerator the state lives there and all seeds run at once. Measured peaks (docs/performance.md)
sit below this estimate: cramped room with 20 seeds peaked at 5.3 GiB against 5.7 estimated,
the 20-seed gridworld at 1.35 GiB against 1.5.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

GIB = 1 << 30
RUNTIME_BYTES = 3 * GIB // 2


class ResourceError(Exception):
    """A run that cannot fit this machine; `str()` says the estimate and the field to lower."""


@dataclass(frozen=True)
class Estimate:
    buffers: int
    rollouts: int

    @property
    def total(self) -> int:
        return 2 * (self.buffers + self.rollouts) + RUNTIME_BYTES

    @property
    def field_to_lower(self) -> str:
        return "learner.buffer_size or train.seeds" if self.buffers >= self.rollouts else "train.num_envs"


def observation_bytes(spec) -> int:
    """Bytes of one observation, from the environment's shapes alone (nothing runs)."""
    import jax
    import numpy as np

    from esr_cli.envs import make_env

    env = make_env(spec.env)
    shape = jax.eval_shape(lambda k: env.observe(env.reset(k)), jax.random.PRNGKey(0))
    return int(np.prod(shape.shape)) * shape.dtype.itemsize


def estimate(spec, obs_bytes: int, seeds_at_once: int) -> Estimate:
    steps = spec.env.episode_steps
    seeds = len(spec.train.seeds)
    episodes = max(1, spec.learner.buffer_size // steps)
    buffers = seeds * episodes * ((steps + 1) * obs_bytes + 12 * steps)
    rollouts = seeds_at_once * spec.train.num_envs * (steps + 1) * (5 * obs_bytes + 64)
    return Estimate(buffers, rollouts)


def available_host_bytes() -> int | None:
    """MemAvailable from /proc/meminfo (Linux), else physical pages; None if unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def available_device_bytes() -> int | None:
    """The accelerator allocator's limit (None on the CPU)."""
    import jax

    if jax.default_backend() == "cpu":
        return None
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("bytes_limit")


def check_run_fits(spec) -> Estimate:
    """Raise ResourceError when the run's estimate exceeds the memory that will hold it."""
    import jax

    from esr_cli.core.train import default_seed_batch

    on_cpu = jax.default_backend() == "cpu"
    seeds_at_once = default_seed_batch() or len(spec.train.seeds)
    est = estimate(spec, observation_bytes(spec), seeds_at_once)
    have = available_host_bytes() if on_cpu else available_device_bytes()
    where = "host memory" if on_cpu else "accelerator memory"
    if have is not None and est.total > have:
        raise ResourceError(
            f"{spec.name} needs about {est.total / GIB:,.1f} GiB of {where} (replay buffers {est.buffers / GIB:,.2f} GiB, "
            f"rollouts {est.rollouts / GIB:,.2f} GiB, doubled for working copies, plus 1.5 GiB) but {have / GIB:,.1f} GiB "
            f"are available: lower {est.field_to_lower}"
        )
    return est
