"""The information-geometry picture's quantities, computed exactly."""

import json

import numpy as np
import pytest

from esr_cli.analysis import geometry as g


def test_future_distributions_are_distributions():
    t = g.example_mdp()
    rho = g.future_distributions(t, np.full((3, 3), 1 / 3), 0.8)
    np.testing.assert_allclose(rho.sum(axis=-1), 1.0, atol=1e-12)


def test_gamma_zero_future_is_the_next_state():
    t = g.example_mdp()
    rho = g.future_distributions(t, np.full((3, 3), 1 / 3), 0.0)
    np.testing.assert_allclose(rho, t, atol=1e-12)


def test_capacity_equals_the_largest_kl_to_the_centre():
    geo = g.geometry(g.example_mdp(), state=0, gamma=0.5)
    support = geo.policy > 1e-6
    # At capacity every action used is equally far from the centre, and none is farther.
    np.testing.assert_allclose(geo.kl[support], geo.mutual_information, rtol=1e-6)
    assert geo.kl.max() == pytest.approx(geo.mutual_information, rel=1e-6)
    assert geo.mutual_information >= geo.uniform_mi - 1e-12
    assert not np.allclose(geo.policy, 1 / 3)  # the asymmetric MDP moves the centre
    np.testing.assert_allclose(geo.centre, geo.policy @ geo.vertices)


def test_identical_actions_give_no_information():
    t = np.tile(np.array([0.2, 0.3, 0.5]), (3, 3, 1))
    geo = g.geometry(t, state=1, gamma=0.7)
    assert geo.mutual_information == pytest.approx(0.0, abs=1e-12)


def test_plot_geometry_cli(tmp_path, capsys):
    from pathlib import Path

    from esr_cli.cli.main import main

    store = tmp_path / "store"
    assert main(["--store", str(store), "plot", "geometry", "--gamma", "0.5"]) == 0
    png = Path(capsys.readouterr().out.strip())
    assert png.exists() and png.stat().st_size > 5000 and png.with_suffix(".pdf").exists()
    assert json.loads(png.with_suffix(".json").read_text())["gamma"] == 0.5  # each discount's figure says which
    assert main(["--store", str(store), "plot", "geometry", "--gamma", "1.5"]) == 2
    assert main(["--store", str(store), "plot", "nope"]) == 2
