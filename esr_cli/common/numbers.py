"""Numbers read back from stored JSON (metrics, summaries, manifests): a value counts as a number
only when it is a JSON number a float can hold. A bool is not one (True is an int to Python),
and an integer of hundreds of digits, which JSON allows, would overflow float() in a reader."""

from __future__ import annotations

from typing import Optional


def as_number(value) -> Optional[float]:
    """`value` as a float (NaN and infinities included), or None for anything else."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        return float(value)
    except OverflowError:
        return None


def as_count(value) -> Optional[int]:
    """`value` when it is an integer (not a bool), or None."""
    return value if isinstance(value, int) and not isinstance(value, bool) else None
