"""Figures, ablations and the report: numbers by hand, missing inputs named, provenance kept.
(The whole paper pipeline at the smoke budget runs in CI: `make paper-figures BUDGET=smoke`.)"""

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import esr

from esr_cli.common.stats import describe
from esr_cli.report import figures as figs


def rows_of(returns_by_epoch):
    return [{"epoch": i + 1, "return": list(r)} for i, r in enumerate(returns_by_epoch)]


def test_final_return_is_the_last_tenth_per_seed_then_mean_and_se():
    # 20 epochs, 2 seeds: the last 10% = epochs 19 and 20.
    rows = rows_of([[0.0, 0.0]] * 18 + [[10.0, 2.0], [20.0, 4.0]])
    per_seed = figs.final_per_seed(rows)
    assert per_seed.tolist() == [15.0, 3.0]
    d = describe(per_seed)
    assert d["mean"] == 9.0 and d["se"] == pytest.approx(np.std([15.0, 3.0], ddof=1) / np.sqrt(2))


def test_an_epoch_without_the_metric_counts_as_undefined_not_as_damage():
    """A metric some epochs do not log (success before the first episode ends, a metric added
    on resume) is NaN there; a seed with no value in its final tenth has no final score."""
    rows = rows_of([[1.0, 2.0]] * 20)
    for r in rows[:19]:
        r["success"] = [0.0, 1.0]
    rows[19]["success"] = [None, 1.0]
    epochs, vals = figs.series(rows, "success")
    assert vals.shape == (20, 2) and epochs.tolist() == list(range(1, 21))
    rows[18].pop("success")  # epochs 19 and 20 are the final tenth: seed 0 never logged there
    per_seed = figs.final_per_seed(rows, "success")
    assert np.isnan(per_seed[0]) and per_seed[1] == 1.0
    assert figs.final_per_seed(rows_of([[1.0]] * 5), "success").shape == (1,)


def test_panels_figure_tables_every_line(tmp_path):
    a = rows_of([[1.0, 3.0]] * 10)
    b = rows_of([[5.0, 5.0]] * 10)
    fig, table = figs.panels_figure([("p1", [("A", "C0", a), ("B", "C1", b)])], "t", "return")
    files = figs.save(fig, tmp_path, "f", {"artifacts": {"runs": ["k1", "k2"]}, "budget": "smoke", "seeds": [0, 1]})
    # per seed: A ends at 1 and 3, B at 5 and 5; with two seeds the IQM is the mean and the
    # bootstrap resamples (1,1), (1,3), (3,1), (3,3) put its 95% interval at [1, 3]
    assert table == {"p1": {"A": {"mean": 2.0, "se": 1.0, "seeds": 2, "per_seed": [1.0, 3.0], "iqm": 2.0, "iqm_low": 1.0, "iqm_high": 3.0},
                            "B": {"mean": 5.0, "se": 0.0, "seeds": 2, "per_seed": [5.0, 5.0], "iqm": 5.0, "iqm_low": 5.0, "iqm_high": 5.0}}}
    assert [f.suffix for f in files] == [".png", ".pdf", ".json"]
    assert json.loads(files[2].read_text())["artifacts"]["runs"] == ["k1", "k2"]
    from PIL import Image

    assert "k1" in Image.open(files[0]).info["Description"]  # provenance inside the PNG too


def test_one_seed_figures_say_so_instead_of_showing_a_zero_standard_error():
    from esr_cli.report.paper import _final_table

    assert figs.seeds_phrase([1, 1]) == "1 seed, no SE"
    assert figs.seeds_phrase([5, 5]) == "mean ± 1 SE over 5 seeds"
    assert figs.seeds_phrase([3, 1]) == "mean ± 1 SE over 1 to 3 seeds"
    fig, table = figs.panels_figure([("p1", [("A", "C0", rows_of([[2.0]] * 10))])], "t", "return", budget="quick")
    assert fig._suptitle.get_text() == "t  [quick budget, 1 seed, no SE]"
    table["p1"]["B"] = {"mean": 4.0, "se": 0.5, "seeds": 3}
    assert _final_table(table)[-2:] == ["| A | 2.00 (1 seed) |", "| B | 4.00 ± 0.50 |"]


def test_every_figure_reads_runs_of_the_paper_suite():
    """Each figure's inputs exist in experiments/suites/paper.yaml (at any budget)."""
    from esr_cli.storage.store import Store

    inputs = figs.PaperInputs(Store("/nonexistent-store"), "smoke")
    for figure, wants in figs.WANTS.items():
        for stem, sets in wants():
            assert inputs.run(stem, sets).spec_path.stem == stem
    assert {f for f, _ in figs.FIGURES.values()} == set(figs.WANTS)


def test_the_paper_figures_draw_the_baselines_the_paper_ran_and_esrs_lines_dotted_beside_them():
    """Figure 1: AvE and Goal Inference as published, in solid lines; esr's estimator variant and
    its versions of the two baselines dotted in their method's colour. Figure 2: the published
    AvE, and its title names the human the runs played with."""
    from esr_cli.storage.store import Store

    inputs = figs.PaperInputs(Store("/nonexistent-store"), "paper")
    solid = {m: inputs.run(stem.format(n=5), sets).spec for m, stem, sets, _, _, style in figs.GRID_LINES if style == "-"}
    assert solid["ave"].method.variant == "original" and solid["goal_inference"].method.variant == "original"
    assert set(solid) == {"esr", "ave", "goal_inference", "iq_learn", "oracle"}
    dotted = [(m, inputs.run(stem.format(n=5), sets).spec, color) for m, stem, sets, _, color, style in figs.GRID_LINES
              if style == figs.ESRS_STYLE]
    assert [(m, c) for m, _, c in dotted] == [(m, figs.METHOD_COLORS[m]) for m in ("esr", "ave", "goal_inference")]
    assert dotted[0][1].method.future == "human" and dotted[1][1].method.variant == "fixed"
    assert dotted[2][1].method.variant != "original"
    fig2 = [inputs.run(stem, sets).spec for stem, sets in figs.WANTS["fig2_overcooked"]()]
    assert [s.method.variant for s in fig2 if s.method.kind == "ave"] == ["original"] * 3
    assert all(figs.specs.plays_with_paper_human(s) for s in fig2)
    assert not any(figs.specs.plays_with_paper_human(s) for s in
                   (figs.PaperInputs(Store("/nonexistent-store"), "smoke").run(stem, sets).spec
                    for stem, sets in figs.WANTS["fig2_overcooked"]() if stem.startswith("cramped")))


@pytest.mark.slow
def test_plot_with_missing_runs_names_the_commands(tmp_path):
    proc = esr("plot", "mi", "--budget", "smoke", store=tmp_path, check=False)
    assert proc.returncode == 2
    assert "esr train" in proc.stderr and "grid_2.yaml --budget smoke" in proc.stderr
    assert "or all at once: esr paper --budget smoke" in proc.stderr  # what make paper-figures runs
    assert not (tmp_path / "figures").exists()


def test_ablate_needs_an_ablation(tmp_path):
    proc = esr("ablate", "--budget", "smoke", store=tmp_path, check=False)
    assert proc.returncode == 2 and "--no-robot-action" in proc.stderr


@pytest.mark.slow
def test_ablate_reuses_trained_runs_and_writes_a_comparison(smoke_run):
    store, base_path, _ = smoke_run
    proc = esr("ablate", "experiments/grid_2.yaml", "--greedy", "--budget", "smoke", store=store)
    out = Path(proc.stdout.strip().splitlines()[-1])
    assert "cache hit" in proc.stderr  # the base run was not trained again
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["final_return"]["grid_2"]) == {"base", "greedy critic"}
    prov = json.loads((out / "ablation.json").read_text())
    assert base_path.name in prov["artifacts"]["runs"] and prov["budget"] == "smoke"
    assert (out / "ablation.pdf").exists() and "| base |" in (out / "table.md").read_text()
    again = esr("ablate", "experiments/grid_2.yaml", "--greedy", "--budget", "smoke", store=store)
    assert again.stdout.strip().splitlines()[-1] == str(out)


def test_the_paper_specs_are_read_from_the_current_directory_when_it_has_them(tmp_path, monkeypatch):
    from esr_cli.storage.provenance import PACKAGE_DIR, experiments_dir

    monkeypatch.chdir(tmp_path)
    # none here: the one installed with esr, in a checkout a link to the checkout's own
    assert experiments_dir() == PACKAGE_DIR / "experiments"
    assert experiments_dir().resolve() == PACKAGE_DIR.parent / "experiments"
    (tmp_path / "experiments" / "suites").mkdir(parents=True)
    (tmp_path / "experiments" / "suites" / "paper.yaml").write_text("name: paper\n")
    assert experiments_dir() == tmp_path / "experiments"
