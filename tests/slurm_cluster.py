"""A real single-node SLURM cluster on localhost, for tests: munged with a generated key, then
slurmctld and slurmd from a slurm.conf generated in a temporary folder (no cgroups, no
accounting), all as the current user. `start(folder)` returns a running Cluster or raises
Unavailable with the exact reason (binaries missing, a daemon that would not start); the
caller skips on it. Every command of the cluster reads the configuration through SLURM_CONF.

    cluster = start(Path(tempfile.mkdtemp()))
    subprocess.run(["sinfo"], env=cluster.env)
    cluster.stop()
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

PARTITION = "debug"
NODE = "localhost"
BINARIES = ("munged", "munge", "unmunge", "slurmctld", "slurmd", "sinfo", "squeue", "sbatch", "srun", "scancel", "scontrol")
# Where Debian puts the daemons; a non-root PATH often lacks the sbin folders.
SBIN = ("/usr/sbin", "/sbin", "/usr/local/sbin")


class Unavailable(Exception):
    """SLURM cannot run here; `str()` says exactly what failed."""


def _which(name: str) -> str | None:
    return shutil.which(name) or shutil.which(name, path=os.pathsep.join(SBIN))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _tail(path: Path, n: int = 15) -> str:
    try:
        lines = path.read_text(errors="replace").strip().splitlines()
    except OSError:
        return f"({path} not written)"
    return "\n".join(lines[-n:]) or f"({path} empty)"


def _mem_mb() -> int:
    with open("/proc/meminfo") as f:
        total_kb = next(int(line.split()[1]) for line in f if line.startswith("MemTotal:"))
    return int(total_kb / 1024 * 0.9)  # below what slurmd detects, or it drains the node


def slurm_conf(folder: Path, user: str, munge_socket: Path, ctld_port: int, slurmd_port: int,
               cpus: int, mem_mb: int) -> str:
    """The cluster's configuration: one node (this machine's CPUs and most of its memory), one
    partition, process tracking by /proc (no cgroups), no accounting, state under `folder`."""
    return f"""\
ClusterName=esrtest
SlurmctldHost={NODE}
SlurmctldPort={ctld_port}
SlurmdPort={slurmd_port}
SlurmUser={user}
SlurmdUser={user}
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={munge_socket}
StateSaveLocation={folder}/state
SlurmdSpoolDir={folder}/spool
SlurmctldPidFile={folder}/slurmctld.pid
SlurmdPidFile={folder}/slurmd.pid
SlurmctldLogFile={folder}/slurmctld.log
SlurmdLogFile={folder}/slurmd.log
PlugStackConfig={folder}/plugstack.conf
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
MpiDefault=none
ReturnToService=2
KillWait=5
MinJobAge=600
NodeName={NODE} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={mem_mb} State=UNKNOWN
PartitionName={PARTITION} Nodes={NODE} Default=YES MaxTime=INFINITE State=UP
"""


@dataclass
class Cluster:
    folder: Path
    conf: Path
    env: dict
    procs: dict = field(default_factory=dict)  # name -> Popen

    def run(self, *args: str, check: bool = True, timeout: float = 60) -> subprocess.CompletedProcess:
        proc = subprocess.run(list(args), env=self.env, capture_output=True, text=True, timeout=timeout)
        if check and proc.returncode != 0:
            raise AssertionError(f"{' '.join(args)} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
        return proc

    def node_state(self) -> str:
        proc = self.run("sinfo", "-h", "-n", NODE, "-o", "%T", check=False, timeout=20)
        return proc.stdout.strip() if proc.returncode == 0 else f"sinfo failed: {proc.stderr.strip()}"

    def jobs(self) -> dict[str, str]:
        """{job id (4242_0 for an array task): state} of every job slurmctld still knows,
        finished ones too (MinJobAge keeps them 10 minutes): squeue, not sacct (no accounting)."""
        out = self.run("squeue", "-h", "-t", "all", "-o", "%i %T").stdout
        return dict(line.split() for line in out.splitlines() if line.strip())

    def job_state(self, job_id: str) -> str:
        """One job's state (4242_1: a task of an array, pending ones too) from squeue."""
        return self.run("squeue", "-h", "-t", "all", "-j", job_id, "-o", "%T").stdout.strip()

    def logs(self) -> str:
        names = ("munged.out", "slurmctld.out", "slurmctld.log", "slurmd.out", "slurmd.log")
        return "\n".join(f"--- {name}\n{_tail(self.folder / name)}" for name in names if (self.folder / name).exists())

    def stop(self) -> None:
        """Cancel every job, then end the daemons (slurmd, slurmctld, munged), each by its pid."""
        if "slurmctld" in self.procs:
            self.run("scancel", "--full", "-p", PARTITION, check=False, timeout=20)
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                try:
                    if not self.run("squeue", "-h", "-o", "%i", check=False, timeout=10).stdout.strip():
                        break
                except subprocess.TimeoutExpired:
                    break
                time.sleep(0.5)
        for name in ("slurmd", "slurmctld", "munged"):
            proc = self.procs.pop(name, None)
            if proc is None or proc.poll() is not None:
                continue
            proc.terminate()
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)


def _need_binaries() -> dict[str, str]:
    found = {name: _which(name) for name in BINARIES}
    missing = [name for name, path in found.items() if path is None]
    if missing:
        raise Unavailable(f"SLURM or munge not installed: {', '.join(missing)} not found "
                          "(make slurm; or apt-get install slurm-wlm munge)")
    return found


def _daemon(cluster: Cluster, name: str, argv: list[str]) -> None:
    log = open(cluster.folder / f"{name}.out", "wb")
    cluster.procs[name] = subprocess.Popen(argv, env=cluster.env, stdout=log, stderr=subprocess.STDOUT,
                                           stdin=subprocess.DEVNULL, start_new_session=True)
    log.close()


def _wait(cluster: Cluster, what: str, ready, timeout: float, daemons: tuple[str, ...]) -> None:
    deadline = time.monotonic() + timeout
    while True:
        for name in daemons:
            rc = cluster.procs[name].poll()
            if rc is not None:
                raise Unavailable(f"{name} exited {rc} while starting: {_tail(cluster.folder / f'{name}.out', 5)}\n"
                                  + cluster.logs())
        if ready():
            return
        if time.monotonic() > deadline:
            raise Unavailable(f"{what} not within {timeout:.0f} s\n{cluster.logs()}")
        time.sleep(0.5)


def start(folder: Path, timeout: float = 60) -> Cluster:
    """munged, slurmctld and slurmd on localhost, configured under `folder`, the node idle.
    Raises Unavailable (after stopping what it started) if any of it fails."""
    bins = _need_binaries()
    folder = Path(folder).absolute()
    for sub in ("state", "spool", "munge"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    (folder / "munge").chmod(0o700)
    key = folder / "munge" / "munge.key"
    key.write_bytes(os.urandom(1024))
    key.chmod(0o400)
    sock = folder / "munge" / "munge.socket"
    if len(str(sock)) > 100:
        raise Unavailable(f"the munge socket path is too long for a Unix socket: {sock}")
    (folder / "plugstack.conf").write_text("")
    user = pwd.getpwuid(os.getuid()).pw_name
    conf = folder / "slurm.conf"
    conf.write_text(slurm_conf(folder, user, sock, _free_port(), _free_port(), os.cpu_count() or 1, _mem_mb()))
    path = os.pathsep.join([os.environ.get("PATH", ""), *SBIN])
    cluster = Cluster(folder, conf, {**os.environ, "SLURM_CONF": str(conf), "PATH": path})
    try:
        # munged refuses to run as root unless forced (-f); its socket and key stay under folder.
        _daemon(cluster, "munged", [bins["munged"], "-F", "-f", f"--socket={sock}", f"--key-file={key}",
                                    f"--pid-file={folder}/munged.pid", f"--log-file={folder}/munged.log",
                                    f"--seed-file={folder}/munge/munged.seed"])

        def munge_works() -> bool:
            if not sock.exists():
                return False
            cred = subprocess.run([bins["munge"], "-n", f"--socket={sock}"], capture_output=True, timeout=10)
            return cred.returncode == 0 and subprocess.run(
                [bins["unmunge"], f"--socket={sock}"], input=cred.stdout, capture_output=True, timeout=10).returncode == 0

        _wait(cluster, "munged answering", munge_works, timeout, ("munged",))
        _daemon(cluster, "slurmctld", [bins["slurmctld"], "-D", "-i", "-f", str(conf)])
        _wait(cluster, "slurmctld answering", lambda: cluster.run("scontrol", "ping", check=False, timeout=10).returncode == 0
              and "UP" in cluster.run("scontrol", "ping", check=False, timeout=10).stdout, timeout, ("munged", "slurmctld"))
        _daemon(cluster, "slurmd", [bins["slurmd"], "-D", "-N", NODE, "-f", str(conf)])
        _wait(cluster, f"node {NODE} idle in sinfo", lambda: cluster.node_state() == "idle", timeout,
              ("munged", "slurmctld", "slurmd"))
    except BaseException:
        cluster.stop()
        raise
    return cluster
