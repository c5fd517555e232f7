"""Shared fixtures. Compiled training programs dominate the suite's time, so the one smoke
run that several end-to-end tests inspect is made once per session."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Compiling, not running, dominates this suite (smoke budgets run in milliseconds), and XLA's
# CPU backend compiles about 2x faster without LLVM optimisation. Set before JAX starts, in
# this process and in every CLI subprocess the tests spawn. The benchmark never sets it.
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()


@pytest.fixture(scope="session", autouse=True)
def compile_cache(tmp_path_factory):
    """One persistent XLA compilation cache for the session: CLI subprocesses that run the
    same programs (train, resume, eval) compile them once. Under pytest-xdist the workers
    share it (the run's base directory, fresh for each run), so a program one worker compiled
    is not compiled again by another."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        path = tmp_path_factory.getbasetemp().parent / "xla-cache"
        path.mkdir(exist_ok=True)
    else:
        path = tmp_path_factory.mktemp("xla-cache")
    os.environ["ESR_COMPILE_CACHE"] = str(path)
    yield path


def esr_env(store, **extra):
    return {**os.environ, "ESR_STORE": str(store), "PYTHONUNBUFFERED": "1", **extra}


def esr(*args, store, check=True, timeout=600, **extra_env):
    """Run the real CLI in a subprocess; -> CompletedProcess."""
    env = esr_env(store, **extra_env)
    proc = subprocess.run(
        [sys.executable, "-m", "esr_cli.cli.main", *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"esr {' '.join(args)} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


@pytest.fixture(scope="session")
def smoke_store(tmp_path_factory):
    return tmp_path_factory.mktemp("store")


@pytest.fixture(scope="session")
def smoke_run(smoke_store):
    """`esr train experiments/grid_2.yaml --budget smoke` once: (store, artifact path, process)."""
    proc = esr("train", "experiments/grid_2.yaml", "--budget", "smoke", store=smoke_store)
    return smoke_store, Path(proc.stdout.strip().splitlines()[-1]), proc
