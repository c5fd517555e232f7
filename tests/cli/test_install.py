"""An installed esr, not a checkout: the package as pip installs it (no editable link back to
the source) finds the paper's specs it carries and trains from any directory."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT, esr_env

pytestmark = pytest.mark.slow  # a package build and a training run

# What a source distribution holds; the build runs in a copy so that it leaves nothing here.
SOURCE = ("pyproject.toml", "README.md", "esr_cli", "experiments")


def test_a_non_editable_install_trains_a_readme_spec_from_another_directory(tmp_path):
    src, site, elsewhere = tmp_path / "src", tmp_path / "site", tmp_path / "elsewhere"
    src.mkdir()
    for name in SOURCE:
        if (ROOT / name).is_dir():  # symlinks kept: esr_cli/experiments stays a link to ../experiments
            shutil.copytree(ROOT / name, src / name, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(ROOT / name, src / name)
    # The package alone (the test environment has its dependencies), as pip installs it.
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-compile", "--quiet", "--target", str(site),
                    str(src)], check=True, timeout=900, capture_output=True)
    carried = site / "esr_cli" / "experiments"
    assert not carried.is_symlink() and (carried / "grid_2.yaml").is_file() and (carried / "suites" / "paper.yaml").is_file()

    elsewhere.mkdir()
    env = esr_env(tmp_path / "store", PYTHONPATH=str(site))
    where = subprocess.run([sys.executable, "-c", "import esr_cli; print(esr_cli.__file__)"], cwd=elsewhere, env=env,
                           capture_output=True, text=True, check=True)
    assert Path(where.stdout.strip()).is_relative_to(site)  # the installed copy, not this checkout
    proc = subprocess.run([sys.executable, "-m", "esr_cli.cli.main", "train", "experiments/grid_2.yaml", "--budget", "smoke"],
                          cwd=elsewhere, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    run = Path(proc.stdout.strip().splitlines()[-1])
    assert run.is_relative_to(tmp_path / "store") and json.loads((run / "manifest.json").read_text())["name"] == "grid_2"
    # a spec of the user's own, in this directory, is read from here, not from the installed copy
    (elsewhere / "experiments").mkdir()
    (elsewhere / "experiments" / "grid_2.yaml").write_text("extends: " + str(carried / "grid_2.yaml") + "\nname: mine\n")
    mine = subprocess.run([sys.executable, "-m", "esr_cli.cli.main", "train", "experiments/grid_2.yaml", "--budget", "smoke",
                           "--set", "train.epochs=1"], cwd=elsewhere, env=env, capture_output=True, text=True, timeout=600)
    assert mine.returncode == 0, mine.stderr
    assert json.loads((Path(mine.stdout.strip().splitlines()[-1]) / "manifest.json").read_text())["name"] == "mine"
