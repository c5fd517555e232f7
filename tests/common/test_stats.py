"""The statistics behind every multi-seed table: IQM, its stratified bootstrap interval, the
probability of improvement. Each against a value worked out by hand or by scipy's reference."""

import numpy as np
import pytest
from scipy.stats import mannwhitneyu

from esr_cli.common import stats


def test_iqm_is_the_mean_of_the_middle_half():
    assert stats.iqm(range(8)) == pytest.approx(3.5)  # drops 0, 1 and 6, 7
    assert stats.iqm([1, 2, 3, 4, 100, -100, 2.5, 2.5]) == pytest.approx(np.mean([2, 2.5, 2.5, 3]))


def test_two_seed_interval_is_the_hand_computed_percentile_interval():
    # Resamples of (0, 1): (0,0) p=1/4 -> 0, mixed p=1/2 -> 0.5, (1,1) p=1/4 -> 1. The 2.5% and
    # 97.5% quantiles of that distribution are 0 and 1.
    point, low, high = stats.iqm_ci([[0.0, 1.0]])
    assert (point, low, high) == (0.5, 0.0, 1.0)


def test_bootstrap_is_stratified_by_task():
    """Constant within each task: a stratified resample always keeps three runs of each, so the
    interval has no width. Pooling the runs first would mix them (IQM anywhere in [0, 10])."""
    point, low, high = stats.iqm_ci([[0.0, 0.0, 0.0], [10.0, 10.0, 10.0]])
    assert point == low == high == 5.0
    _, low_pooled, high_pooled = stats.iqm_ci([[0.0, 0.0, 0.0, 10.0, 10.0, 10.0]])
    assert high_pooled - low_pooled > 4


def test_interval_covers_the_point_and_is_reproducible():
    rng = np.random.default_rng(3)
    scores = [rng.normal(5, 2, 10), rng.normal(-1, 1, 7)]
    a, b = stats.iqm_ci(scores, seed=11), stats.iqm_ci(scores, seed=11)
    assert a == b and a[1] < a[0] < a[2]


def test_one_seed_has_no_interval():
    assert stats.iqm_ci([[3.0]]) is None
    d = stats.describe([3.0])
    assert "iqm" not in d and d["se"] == 0.0
    assert stats.format_summary(d) == "3.00 (1 seed)"


def test_probability_of_improvement_matches_mann_whitney_and_hand_count():
    # pairs (3,1) (3,3) (4,1) (4,3): 1 + 0.5 + 1 + 1 = 3.5 of 4
    point, low, high = stats.probability_of_improvement([3, 4], [1, 3])
    assert point == 0.875
    assert point == mannwhitneyu([3, 4], [1, 3]).statistic / 4
    # (3,3) against (3,3) happens with probability 1/16 > 2.5% and gives 0.5, the lowest value
    assert (low, high) == (0.5, 1.0)
    rng = np.random.default_rng(0)
    x, y = rng.normal(1, 1, 9), rng.normal(0, 1, 6)
    assert stats.probability_of_improvement(x, y)[0] == pytest.approx(mannwhitneyu(x, y).statistic / 54)
    assert stats.probability_of_improvement([1.0], [2.0]) == (0.0, None, None)


def test_describe_keeps_per_seed_values_and_formats_several_seeds():
    d = stats.describe([1, 2, 3, 4, 10])
    assert d["per_seed"] == [1, 2, 3, 4, 10] and d["mean"] == 4.0
    assert d["iqm"] == 3.0 and d["iqm_low"] <= 3.0 <= d["iqm_high"]
    assert stats.format_summary(d).startswith("4.00 ± 1.58; IQM 3.00 [")


def test_a_one_seed_method_is_held_fixed_against_several_seeds():
    """A 10-seed run against a 1-seed baseline: resampling one value returns it, so only the
    other method's seeds vary. Hand count: resamples of x = (3, 1) against y = (2) give
    P = 1 for (3,3) (p 1/4), 0 for (1,1) (p 1/4), 0.5 otherwise: the interval is [0, 1]."""
    assert stats.probability_of_improvement([3.0, 1.0], [2.0]) == (0.5, 0.0, 1.0)
    assert stats.probability_of_improvement([2.0], [3.0, 1.0]) == (0.5, 0.0, 1.0)
    # every resample of x = (5, 6, 7) lies above y = (4): the interval has no width
    assert stats.probability_of_improvement([5.0, 6.0, 7.0], [4.0]) == (1.0, 1.0, 1.0)
    # a fixed task in a stratified IQM: the pooled runs are always (0, 0, 9), IQM 3
    assert stats.iqm_ci([[0.0, 0.0], [9.0]]) == (3.0, 3.0, 3.0)
    # the two-seed task still varies: (0, 1) with a fixed 0.5 pools to IQMs 0.5 - ... as by hand:
    # (0,0,.5) -> mean 1/6, (0,1,.5) -> 0.5, (1,1,.5) -> 5/6 with probabilities 1/4, 1/2, 1/4
    point, low, high = stats.iqm_ci([[0.0, 1.0], [0.5]])
    assert point == 0.5 and low == pytest.approx(1 / 6) and high == pytest.approx(5 / 6)


def test_a_seed_without_a_final_score_is_left_out_and_counted():
    """NaN (a seed whose final epochs never logged the metric) is not a score: compared as a
    number it would lose every pair. Here x beats every scored y, so P = 1 by hand."""
    assert stats.probability_of_improvement([1.0, 1.0], [0.0, np.nan]) == (1.0, 1.0, 1.0)
    assert stats.probability_of_improvement([1.0], [0.0, np.nan]) == (1.0, None, None)
    point, low, high = stats.probability_of_improvement([10, 11, 12, 13, 14], [1, 2, 3, 4, np.nan])
    assert (point, low, high) == (1.0, 1.0, 1.0)
    assert np.isnan(stats.probability_of_improvement([10.0, 11.0], [np.nan, np.nan])[0])
    d = stats.describe([1.0, 2.0, 3.0, np.nan])
    assert d["seeds"] == 4 and d["missing"] == 1 and d["mean"] == 2.0 and d["iqm"] == 2.0
    assert np.isnan(d["per_seed"][3])  # stored as computed
    text = stats.format_summary(d)
    assert text.startswith("2.00 ± 0.58; IQM 2.00 [") and text.endswith("(1 of 4 seeds without a final score)")
    assert stats.format_summary(stats.describe([5.0, np.nan])) == "5.00 (1 seed) (1 of 2 seeds without a final score)"


def test_a_run_without_scores_says_so_rather_than_one_seed():
    assert stats.format_summary(stats.describe([])) == "no value"
    assert stats.format_summary(stats.describe([np.nan] * 3)) == "no value (3 seeds without a final score)"


def test_per_seed_values_are_kept_unrounded_for_later_statistics():
    """Rounding to 6 decimals would tie 1.0000001 with 1.0000004: by hand, x = (1.0000001, 2)
    against y = (1.0000004, 0) wins 3 of 4 pairs; with the tie it would be 3.5 of 4."""
    x, y = stats.describe([1.0000001, 2.0]), stats.describe([1.0000004, 0.0])
    assert stats.probability_of_improvement(x["per_seed"], y["per_seed"])[0] == 0.75
