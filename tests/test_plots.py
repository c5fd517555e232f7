"""Per-run pictures: the learning curve marks the warm-up epochs."""

import numpy as np
from PIL import Image

from esr_cli import plots


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
