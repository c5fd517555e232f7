"""The package's layout is its architecture: the keyed code is one package, and imports run one
way, from the command line down to the model (docs/architecture.md)."""

from __future__ import annotations

from pathlib import Path

from esr_cli.storage import provenance

PACKAGE = provenance.PACKAGE_DIR
# Packages from the bottom up: a file may import its own package and those below it, never one
# above.
LAYERS = [
    ("model",),  # the keyed code: imports nothing of esr's from outside itself
    ("common", "analysis"),
    ("storage",),
    ("runner",),
    ("recipes",),
    ("report",),
    ("play",),
    ("cli",),
]


def _files() -> list[Path]:
    return sorted(f for f in PACKAGE.rglob("*.py") if "experiments" not in f.relative_to(PACKAGE).parts)


def _package(f: Path) -> str:
    parts = f.relative_to(PACKAGE).parts
    return parts[0] if len(parts) > 1 else ""


def test_a_runs_code_digest_covers_exactly_the_model_package():
    """What re-keys a run is what a newcomer sees: every file under esr_cli/model, and nothing
    else (model imports nothing of esr's from outside itself)."""
    closure = set(provenance.module_closure(provenance.MODEL_SOURCES))
    model_files = {f for f in _files() if _package(f) == "model"}
    assert closure == model_files, (
        "outside model/: " + ", ".join(sorted(str(f.relative_to(PACKAGE)) for f in closure - model_files)))


def test_the_model_package_is_read_without_jax():
    """Validating a spec (model/spec.py) must not import JAX: a bad spec is refused before it."""
    import subprocess
    import sys

    code = "import sys; import esr_cli.model.spec, esr_cli.common.specs; print('jax' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "False"


def test_no_import_cycle_between_files():
    """Every esr_cli import (module level or inside functions, with the __init__.py of the
    packages it passes through) forms no cycle: the dependency graph reads top to bottom."""
    files = _files()
    graph = {f: provenance._imports(f) - {f} for f in files}
    state: dict = {}

    def visit(f, path):
        if state.get(f) == "done":
            return
        assert state.get(f) != "open", "import cycle: " + " -> ".join(p.name for p in path + [f])
        state[f] = "open"
        for g in sorted(graph[f]):
            visit(g, path + [f])
        state[f] = "done"

    for f in files:
        visit(f, [])


def test_imports_run_down_the_layers():
    """A package imports only its own layer and those below it."""
    layer = {name: i for i, names in enumerate(LAYERS) for name in names}
    upward = []
    for f in _files():
        own = layer.get(_package(f))
        if own is None:
            continue
        for g in provenance._imports(f):
            other = layer.get(_package(g))
            if other is None and _package(g) != _package(f):
                upward.append(f"{f.relative_to(PACKAGE)} imports {g.relative_to(PACKAGE)} (not a layer below)")
            elif other is not None and other > own:
                upward.append(f"{f.relative_to(PACKAGE)} imports {g.relative_to(PACKAGE)} (a layer above)")
    assert not upward, "\n".join(upward)


def test_every_module_is_in_a_package_of_the_layers():
    """No module at the top of esr_cli beside the packages, and no package the layers miss."""
    layered = {name for names in LAYERS for name in names}
    assert {_package(f) for f in _files()} == layered | {""}
    assert [f.name for f in _files() if _package(f) == ""] == ["__init__.py"]


def test_the_tests_mirror_the_packages():
    """Each package's tests are in tests/<package>/ (this file, about the whole, at the top)."""
    tests = Path(__file__).resolve().parent
    layered = {name for names in LAYERS for name in names}
    for f in tests.rglob("test_*.py"):
        parts = f.relative_to(tests).parts
        assert parts == ("test_layout.py",) or (len(parts) == 2 and parts[0] in layered), f"{f.relative_to(tests)}: not in a package's folder"
    assert {d.name for d in tests.iterdir() if d.is_dir() and d.name != "__pycache__"} <= layered
