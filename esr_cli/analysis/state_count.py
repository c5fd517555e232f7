"""How many states an exact analysis of a gridworld would enumerate, from the spec alone.

Kept apart from esr_cli/analysis/exact.py (JAX) so that `esr exact` refuses a grid too large
to enumerate before importing JAX.
"""

from __future__ import annotations

import math

MAX_STATES = 30_000


class TooManyStates(ValueError):
    pass


def state_bound(size: int, blocks: int) -> int:
    """An upper bound on the states `enumerate_states` can reach on a size x size grid with
    `blocks` blocks, from the spec alone. Blocks sit on distinct cells. A live human stands on a
    cell without a block; a dead one is under the block just pushed onto it, so one of its
    neighbours is free. The smaller of that count and "human anywhere, any layout" is close to
    the reachable count: 8,960 for 8,851 on a 4x4 grid with 3 blocks, 5,340 for 5,031 on a 6x6
    grid with 34."""
    cells = size * size
    anywhere = cells * math.comb(cells, blocks)
    if blocks == 0:
        return anywhere
    neighbour_pairs = 4 * size * (size - 1)  # (cell, adjacent cell), both orders
    live_or_dead = cells * math.comb(cells - 1, blocks) + neighbour_pairs * math.comb(cells - 2, blocks - 1)
    return min(anywhere, live_or_dead)


def _count(n: int) -> str:
    return f"{n:,}" if n < 10**12 else f"{float(n):.1e}"


def check_size(size: int, blocks: int, max_states: int = MAX_STATES) -> int:
    """`state_bound`, or TooManyStates naming the spec fields to lower when it exceeds `max_states`."""
    n = state_bound(size, blocks)
    if n > max_states:
        raise TooManyStates(f"env.size={size}, env.blocks={blocks}: up to {_count(n)} states, more than the "
                            f"{max_states:,} exact analysis handles: lower env.size or env.blocks "
                            "(a 4x4 grid with 4 blocks has 28,604)")
    return n
