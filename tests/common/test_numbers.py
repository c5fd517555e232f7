"""What counts as a number when esr reads its own JSON back (metrics, summaries, manifests)."""

import math

from esr_cli.common.numbers import as_count, as_number


def test_only_json_numbers_a_float_holds_are_numbers():
    assert as_number(3) == 3.0 and isinstance(as_number(3), float)
    assert as_number(-2.5) == -2.5
    assert math.isnan(as_number(float("nan"))) and as_number(float("inf")) == math.inf  # kept: callers decide
    for not_a_number in (True, False, "1", None, [1], {"v": 1}, 10**400, -(10**400)):
        assert as_number(not_a_number) is None, not_a_number


def test_counts_are_integers_and_never_bools():
    assert as_count(7) == 7 and as_count(10**400) == 10**400
    for not_a_count in (True, 1.0, "3", None):
        assert as_count(not_a_count) is None, not_a_count
