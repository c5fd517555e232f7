"""Pictures: the learning curve marks the warm-up epochs; a suite's runs become panels by environment."""

import numpy as np
from PIL import Image

from esr_cli.common import plots


def test_learning_curve_shades_the_warm_up_epochs(tmp_path):
    rows = [{"epoch": e, "return": [float(e)], "success": [0.5], "mi_estimate": [0.01 * e]} for e in range(1, 31)]
    plain = plots.learning_curve(rows, tmp_path / "plain.png", "t", {"budget": "quick"})
    shaded = plots.learning_curve(rows, tmp_path / "shaded.png", "t", {"budget": "quick"}, warmup_epochs=10)
    a = np.asarray(Image.open(plain).convert("L"), dtype=int)
    b = np.asarray(Image.open(shaded).convert("L"), dtype=int)
    assert a.shape == b.shape
    changed = np.abs(a - b) > 10
    assert changed.mean() > 0.01  # a grey band over a third of each panel, and its legend
    cols = np.nonzero(changed.any(axis=0))[0]
    assert cols.min() < a.shape[1] // 3  # the band starts at the left of the first panel


def test_every_figure_format_offered_is_written_with_its_provenance_where_the_format_keeps_one(tmp_path):
    """`esr plot curve --out` offers PNG, PDF, SVG and JPEG: each is written (JPEG once failed on
    the PNG's metadata, a PDF warned and lost it), the provenance in the field each format has
    for it, and always in the sidecar JSON."""
    import warnings

    rows = [{"epoch": e, "return": [float(e)], "success": [0.5], "mi_estimate": [0.01]} for e in range(1, 6)]
    provenance = {"run": "abc123"}
    for suffix in (".png", ".pdf", ".svg", ".jpg", ".jpeg"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # matplotlib warns where a format lacks the field named
            out = plots.learning_curve(rows, tmp_path / f"curve{suffix}", "t", provenance)
        data = out.read_bytes()
        assert out.suffix == suffix and len(data) > 1000
        assert (b"abc123" in data) == (suffix in (".png", ".svg", ".pdf"))
        assert '"abc123"' in out.with_suffix(".json").read_text()
    with Image.open(tmp_path / "curve.png") as png:
        assert "abc123" in png.info["Description"]


def test_suite_panels_group_runs_by_environment_and_name_lines_by_method(tmp_path):
    from types import SimpleNamespace

    from esr_cli.common import specs
    from esr_cli.report import figures

    root = figures.PAPER_SUITE.parents[2]
    runs = []
    for i, (stem, sets) in enumerate([("grid_2", ()), ("grid_2_random", ()), ("grid_5", ()), ("grid_5", ("learner.gamma=0.0",)),
                                      ("cramped_room", ())]):
        run_dir = tmp_path / str(i)
        run_dir.mkdir()
        (run_dir / "metrics.jsonl").write_text('{"epoch": 1, "return": [1.0]}\n')
        spec = specs.load(root / "experiments" / f"{stem}.yaml", "smoke", list(sets))
        runs.append((SimpleNamespace(spec=spec, label=" ".join((spec.name, *sets))), run_dir))
    panels = figures.suite_panels(runs)
    assert [title for title, _ in panels] == ["gridworld N = 2", "gridworld N = 5", "cramped_room"]
    assert [label for label, _, _ in panels[0][1]] == ["ESR", "Random"]
    # Two ESR runs in one panel are told apart by their labels.
    assert [label for label, _, _ in panels[1][1]] == ["grid_5", "grid_5 learner.gamma=0.0"]
    assert [label for label, _, _ in panels[2][1]] == ["ESR"]


def test_frame_captions_name_the_step_its_actions_reward_and_return():
    from esr_cli.common.plots import frame_caption

    assert frame_caption(0, 50, None, None, 0.0).startswith("step 0/50: the start")
    text = frame_caption(3, 50, ("push (4,1) up", "right"), 1.0, 2.0)
    assert text == "step 3/50   reward 1   return 2\nrobot: push (4,1) up   human: right"


def test_gridworld_and_overcooked_name_their_actions():
    from esr_cli.model.envs.action_labels import action_labels
    from esr_cli.model.envs.gridworld import DIRECTIONS, Gridworld

    grid = Gridworld(size=5, num_blocks=2, start="corner", episode_steps=50)
    assert action_labels("gridworld", grid, 4 * 5 + 3, 0) == ("push (0,4) up", "left")
    assert action_labels("gridworld", grid, 7 * 5 + 4, 4) == ("no push", "stay")
    assert [tuple(d) for d in DIRECTIONS.tolist()] == [(0, -1), (1, 0), (0, 1), (-1, 0), (0, 0)]  # left, down, right, up, stay
    assert action_labels("overcooked", None, 5, 4) == ("interact", "stay")
    assert action_labels("other", None, 2, 3) == ("action 2", "action 3")
