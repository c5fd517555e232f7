"""Memory a training run needs, checked against what the machine has before any work
(docs/reliability.md). The estimate is deliberately simple and on the safe side:

  replay buffers  seeds x (buffer episodes x (steps + 1) x observation bytes + 12 bytes a step)
  rollouts        environments x (steps + 1) x (observation bytes x 5 + 64) per seed in flight
  networks        seeds x 20 copies of the largest network's parameters (the critic, its target,
                  ESR's encoders, optimiser moments and gradients), and per seed in flight
                  batch x 8 copies of one input's activations
  updates         what a method's update holds besides, per seed in flight: ESR's batch x batch
                  logits x 4, AvE's batch x rollouts x (length + 1) observations x 2; ESR's
                  representation table (buffer x 3 x repr_dim floats per seed in flight)
                  counts with the replay buffers, since learner.buffer_size sets it
  working copies  x2 on all (a chunk's input and output state, XLA's temporaries)
  runtime         1.5 GiB (JAX, compiled programs, the human model)

On the CPU every seed's state lives in host memory and seeds run one after another; on an
accelerator the state lives there and all seeds run at once. Measured peaks (docs/performance.md)
sit below this estimate: cramped room with 20 seeds peaked at 5.3 GiB against 5.95 estimated,
the 20-seed gridworld at 1.35 GiB against 1.94.
"""

from __future__ import annotations

import os
import resource
from dataclasses import dataclass
from pathlib import Path

from esr_cli.common.failures import Failure

GIB = 1 << 30
RUNTIME_BYTES = 3 * GIB // 2


class ResourceError(Failure):
    """A run that cannot fit this machine; `str()` says the estimate and the field to lower."""

    exit_code = 2

    def one_line(self) -> str:
        return f"too large for this machine: {self}"


PARAMETER_COPIES, ACTIVATION_COPIES = 20, 8

# What, beside learner.batch_size, sizes a method's updates (its `update_bytes`), by method kind.
UPDATE_FIELDS = {"ave": "method.num_rollouts or method.rollout_length"}


@dataclass(frozen=True)
class Estimate:
    buffers: int
    rollouts: int
    networks: int = 0
    updates: int = 0
    update_fields: str = ""  # what else sizes the method's updates (UPDATE_FIELDS)

    @property
    def total(self) -> int:
        return 2 * (self.buffers + self.rollouts + self.networks + self.updates) + RUNTIME_BYTES

    @property
    def field_to_lower(self) -> str:
        largest = max(self.buffers, self.rollouts, self.networks, self.updates)
        if largest == self.buffers:
            return "learner.buffer_size or train.seeds"
        if largest == self.rollouts:
            return "train.num_envs"
        if largest == self.networks:
            return "the network's widths (network.*, method.repr_dim) or learner.batch_size"
        return "learner.batch_size" + (f", or {self.update_fields}" if self.update_fields else "")

    def parts(self) -> str:
        return (f"replay buffers {self.buffers / GIB:,.2f} GiB, environment rollouts {self.rollouts / GIB:,.2f} GiB, "
                f"networks {self.networks / GIB:,.2f} GiB, the method's updates {self.updates / GIB:,.2f} GiB")


def _network_floats(network_spec, obs_shape: tuple, out: int) -> tuple[int, int]:
    """(parameters, activations of one input) of the network `networks.conv_net` builds."""
    cells = obs_shape[0] * obs_shape[1]
    if network_spec.kind == "mlp":
        widths = (cells * obs_shape[2], *network_spec.mlp_layers, out)
        return sum((a + 1) * b for a, b in zip(widths, widths[1:])), sum(widths)
    params, acts, channels = 0, 0, obs_shape[2]
    for c in network_spec.conv_channels:  # im2col patches (9 x inputs) and the outputs, per cell
        params += 9 * channels * c + c
        acts += cells * (9 * channels + c)
        channels = c
    flat = cells * channels
    params += (flat + 1) * network_spec.hidden + (network_spec.hidden + 1) * out
    return params, acts + flat + network_spec.hidden + out


def network_bytes(spec, obs_shape: tuple, seeds_at_once: int, num_actions: int) -> int:
    params, acts = _network_floats(spec.network, obs_shape, max(num_actions, spec.method.network_outputs()))
    in_flight = 4 * spec.learner.batch_size * acts * ACTIVATION_COPIES
    return 4 * len(spec.train.seeds) * PARAMETER_COPIES * params + seeds_at_once * in_flight


def representation_table_bytes(spec, seeds_at_once: int) -> int:
    """A method's tables over the whole buffer (ESR's representations: 3 x buffer x repr_dim
    floats per seed in flight): they grow with learner.buffer_size, so they count with the buffers."""
    return seeds_at_once * spec.method.table_bytes(spec.learner.buffer_size)


def observation(spec):
    """(shape, bytes) of one observation and the robot's action count, from the environment's
    shapes alone (nothing runs)."""
    import jax
    import numpy as np

    from esr_cli.model.envs import make_env

    env = make_env(spec.env)
    shape = jax.eval_shape(lambda k: env.observe(env.reset(k)), jax.random.PRNGKey(0))
    return tuple(shape.shape), int(np.prod(shape.shape)) * shape.dtype.itemsize, env.num_robot_actions


def observation_bytes(spec) -> int:
    return observation(spec)[1]


def estimate(spec, obs_bytes: int, seeds_at_once: int, obs_shape: tuple | None = None, num_actions: int = 0) -> Estimate:
    """`obs_shape` (and `num_actions`) add the networks' and updates' shares; without them they are left out."""
    steps = spec.env.episode_steps
    seeds = len(spec.train.seeds)
    episodes = max(1, spec.learner.buffer_size // steps)
    buffers = seeds * episodes * ((steps + 1) * obs_bytes + 12 * steps)
    rollouts = seeds_at_once * spec.train.num_envs * (steps + 1) * (5 * obs_bytes + 64)
    if not obs_shape:
        return Estimate(buffers, rollouts)
    networks = network_bytes(spec, obs_shape, seeds_at_once, num_actions)
    updates = seeds_at_once * spec.method.update_bytes(spec.learner.batch_size, obs_bytes)
    return Estimate(buffers + representation_table_bytes(spec, seeds_at_once), rollouts, networks, updates,
                    UPDATE_FIELDS.get(spec.method.kind, ""))


def available_host_bytes() -> int | None:
    """The memory this process can still take: the least of the machine's (`machine_bytes`), its
    control groups' (a container's or a job's limit, which the kernel enforces by killing it) and
    its address-space limit's (`ulimit -v`, which makes an allocation fail); None if none is known."""
    known = [b for b in (machine_bytes(), cgroup_bytes(), address_space_bytes()) if b is not None]
    return min(known, default=None)


def machine_bytes() -> int | None:
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


CGROUP_ROOT, PROC_CGROUP = Path("/sys/fs/cgroup"), Path("/proc/self/cgroup")


def cgroup_bytes() -> int | None:
    """The least, over this process's memory cgroup and each one above it, of its limit less its
    use (cgroup v2's memory.max and memory.current, v1's memory.limit_in_bytes and
    memory.usage_in_bytes); None where none sets a limit."""
    free = [_cgroup_free(d, *files) for base, own, files in _memory_cgroups()
            for d in (own, *own.parents) if d == base or base in d.parents]
    return min((b for b in free if b is not None), default=None)


def _memory_cgroups():
    """(hierarchy root, this process's folder in it, (limit file, usage file)) for each memory
    hierarchy /proc/self/cgroup names."""
    try:
        lines = PROC_CGROUP.read_text().splitlines()
    except OSError:
        return
    for line in lines:
        _, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if controllers == "":  # v2: one hierarchy for every controller
            base, files = CGROUP_ROOT, ("memory.max", "memory.current")
        elif "memory" in controllers.split(","):
            base, files = CGROUP_ROOT / "memory", ("memory.limit_in_bytes", "memory.usage_in_bytes")
        else:
            continue
        yield base, base / path.strip().lstrip("/"), files


def _cgroup_free(folder: Path, limit_file: str, usage_file: str) -> int | None:
    try:
        limit = (folder / limit_file).read_text().strip()
        used = int((folder / usage_file).read_text().strip() or 0)
    except (OSError, ValueError):
        return None
    return max(int(limit) - used, 0) if limit.isdigit() else None  # v2 writes "max" for no limit


def address_space_bytes() -> int | None:
    """RLIMIT_AS less the address space this process maps already; None without a limit."""
    limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    if limit == resource.RLIM_INFINITY:
        return None
    mapped = 0
    try:
        with open("/proc/self/status") as f:
            mapped = next((int(l.split()[1]) * 1024 for l in f if l.startswith("VmSize:")), 0)
    except (OSError, ValueError, IndexError):
        pass
    return max(limit - mapped, 0)


def available_device_bytes() -> int | None:
    """The accelerator allocator's limit (None on the CPU)."""
    import jax

    if jax.default_backend() == "cpu":
        return None
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("bytes_limit")


# A metrics row holds about 16 metrics: per seed some 12 bytes a value, per row some 300 bytes of
# names and counters. On the safe side, so that a run esr writes can always be read back.
METRICS_ROW_BYTES, METRICS_SEED_BYTES = 400, 240
METRICS_ROW_CONTAINERS = 32  # lists and objects in one logged epoch (about 15: a list a metric)


def metrics_bytes(spec) -> int:
    """About the most bytes the run's metrics.jsonl reaches (every epoch logged)."""
    return spec.train.epochs * (METRICS_ROW_BYTES + METRICS_SEED_BYTES * len(spec.train.seeds))


def check_metrics_readable(spec) -> None:
    """Raise ResourceError when the run's metrics would pass what esr reads back of a
    metrics.jsonl (`jsonl.MAX_JSONL_BYTES`, `jsonl.MAX_JSONL_CONTAINERS`): such a run could be
    trained but never reported."""
    from esr_cli.common.jsonl import MAX_JSONL_BYTES, MAX_JSONL_CONTAINERS

    if spec.train.epochs * METRICS_ROW_CONTAINERS > MAX_JSONL_CONTAINERS:
        raise ResourceError(
            f"{spec.name}: {spec.train.epochs:,} epochs would log more lines of metrics than esr reads back of a run "
            f"(at most {MAX_JSONL_CONTAINERS // METRICS_ROW_CONTAINERS:,} epochs): train fewer epochs")
    if metrics_bytes(spec) > MAX_JSONL_BYTES:
        raise ResourceError(
            f"{spec.name}: {spec.train.epochs:,} epochs of {len(spec.train.seeds):,} seeds would log about "
            f"{metrics_bytes(spec) / (1 << 20):,.0f} MiB of metrics, more than the {MAX_JSONL_BYTES >> 20:,} MiB esr "
            "reads back of a run: split the seeds over runs or train fewer epochs")


def check_run_fits(spec) -> Estimate:
    """Raise ResourceError when the run's estimate exceeds the memory that will hold it, or its
    metrics would exceed what esr reads back."""
    import jax

    check_metrics_readable(spec)

    from esr_cli.model.train import default_seed_batch

    on_cpu = jax.default_backend() == "cpu"
    seeds_at_once = default_seed_batch() or len(spec.train.seeds)
    shape, obs_bytes, num_actions = observation(spec)
    est = estimate(spec, obs_bytes, seeds_at_once, shape, num_actions)
    have = available_host_bytes() if on_cpu else available_device_bytes()
    where = "host memory" if on_cpu else "accelerator memory"
    if have is not None and est.total > have:
        raise ResourceError(
            f"{spec.name} needs about {est.total / GIB:,.1f} GiB of {where} ({est.parts()}, doubled for working "
            f"copies, plus 1.5 GiB) but {have / GIB:,.1f} GiB are available: lower {est.field_to_lower}"
        )
    return est
