"""Exact effective empowerment on small gridworlds (ground truth for the ESR estimator).

For a gridworld with a fixed goal, every state reachable from the start states is enumerated
(human cell, set of block cells; blocks are interchangeable, as in the robot's observation).
The environment's own `step` gives the deterministic transitions next(s, aR, aH), and the
human model its exact policy pi_H(aH | s). For a robot policy pi_R:

    P[s, s']  = sum_{aR, aH} pi_R(aR | s) pi_H(aH | s) [next(s, aR, aH) = s']
    M         = (1 - gamma) (I - gamma P)^-1        rows: the discounted occupancy from a state
    rho(. | s, aR, aH) = M[next(s, aR, aH)]         the future state s+ = s_{t+K},
                                                    K ~ Geometric(1 - gamma) on {1, 2, ...}
    rho(. | s, aR)     = sum_aH pi_H(aH | s) rho(. | s, aR, aH)
    I(aH; s+ | s, aR)  = sum_aH pi_H(aH | s) KL(rho(. | s, aR, aH) || rho(. | s, aR))   (nats)

and the effective empowerment of the policy pair from start distribution mu0,
    E = sum_t gamma^t E[I(aH_t; s+ | s_t, aR_t)] = mu0 (I - gamma P)^-1 m,
    m(s) = sum_aR pi_R(aR | s) I(aH; s+ | s, aR).

The MDP is the infinite-horizon one (no 50-step cut-off), matching the geometric future of
ESR's buffer except near episode ends. Transitions come from `vmap` of the environment; P is
sparse, and M is never formed. Up to DENSE_STATES states one LU factorisation of I - gamma P
gives the rows of M that a set of (state, robot action) pairs needs (`LUOccupancy`); above it
(a 4 x 4 grid with 4 blocks: 28,604 states, where the dense LU needs 13 GB and 12 minutes) the
rows are sums of the Neumann series sum_k gamma^k P^k with sparse products, stopped where the
rest of the series weighs at most SERIES_TOLERANCE (`SeriesOccupancy`). MI can be restricted
to the pairs that matter (those a trained robot visits).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Protocol

import jax
import jax.numpy as jnp
import numpy as np
from scipy import sparse
from scipy.linalg import lu_factor, lu_solve

from esr_cli.analysis.state_count import MAX_STATES, TooManyStates
from esr_cli.model.envs.gridworld import GridState, Gridworld


@dataclass(frozen=True)
class StateSpace:
    env: Gridworld
    goal: tuple[int, int]
    human: np.ndarray  # int32[S, 2]
    blocks: np.ndarray  # int32[S, N, 2], sorted row-major
    next_state: np.ndarray  # int32[S, A_R, A_H]
    start: np.ndarray  # float64[S]: the start distribution given this goal

    @property
    def size(self) -> int:
        return len(self.human)

    def states(self) -> GridState:
        n = self.size
        return GridState(
            human=jnp.asarray(self.human),
            blocks=jnp.asarray(self.blocks),
            goal=jnp.broadcast_to(jnp.asarray(self.goal, jnp.int32), (n, 2)),
            t=jnp.zeros((n,), jnp.int32),
        )


def _canonical(human: np.ndarray, blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sort each state's blocks row-major so that equal observations are equal states."""
    order = np.argsort(blocks[..., 0] * 1000 + blocks[..., 1], axis=-1)
    return human, np.take_along_axis(blocks, order[..., None], axis=-2)


def _keys(human: np.ndarray, blocks: np.ndarray) -> list[bytes]:
    flat = np.concatenate([human.reshape(len(human), -1), blocks.reshape(len(blocks), -1)], axis=1)
    return [row.astype(np.int8).tobytes() for row in flat]


# The occupancy's dense LU needs 8 S^2 bytes and S^3 / 1.5 operations: about 1.2 GB and a
# minute on 2 cores at this size. Above it the occupancy is a sparse series (`SeriesOccupancy`),
# whose cost grows with the rows wanted rather than S^3.
DENSE_STATES = 12_000
# Enumeration keeps A_R x A_H successors per state (a 4 x 4 grid with 4 blocks: 28,604 states,
# 11 million transitions, a minute) and the series costs about 0.35 s per wanted row there on
# one core: beyond this the pairs a trained robot visits take hours.
def enumerate_states(env: Gridworld, goal, starts: GridState, max_states: int = MAX_STATES) -> StateSpace:
    """Breadth-first enumeration of every state reachable from `starts` (a batch of states
    with this goal) under all joint actions."""
    goal = tuple(int(g) for g in goal)
    a_r, a_h = env.num_robot_actions, env.num_human_actions
    goal_arr = jnp.asarray(goal, jnp.int32)

    @jax.jit
    def successors(human, blocks):
        def one(h, b):
            s = GridState(human=h, blocks=b, goal=goal_arr, t=jnp.zeros((), jnp.int32))
            def joint(ar, ah):
                nxt, _ = env.step(s, ar, ah)
                return nxt.human, nxt.blocks
            return jax.vmap(lambda ar: jax.vmap(lambda ah: joint(ar, ah))(jnp.arange(a_h)))(jnp.arange(a_r))
        return jax.vmap(one)(human, blocks)

    start_h, start_b = _canonical(np.asarray(starts.human), np.asarray(starts.blocks))
    index: dict[bytes, int] = {}
    humans, blockss, start_ids = [], [], []
    for k, h, b in zip(_keys(start_h, start_b), start_h, start_b):
        if k not in index:
            index[k] = len(humans)
            humans.append(h)
            blockss.append(b)
        start_ids.append(index[k])
    transitions = []  # per processed state, int[A_R, A_H]
    # Each state has A_R x A_H successors: on a large grid with many blocks, 512 states' worth
    # would be gigabytes, so a batch holds about 64 MiB of them.
    per_state = a_r * a_h * (2 * env.num_blocks + 2) * 4
    batch_states = max(1, min(512, (64 << 20) // per_state))
    done = 0
    while done < len(humans):
        batch = slice(done, min(len(humans), done + batch_states))
        nh, nb = successors(jnp.asarray(np.stack(humans[batch])), jnp.asarray(np.stack(blockss[batch])))
        nh, nb = np.asarray(nh), np.asarray(nb)
        shape = nh.shape[:3]
        n = int(np.prod(shape))  # explicit: with no blocks, -1 cannot be inferred from a 0-size array
        nh, nb = _canonical(nh.reshape(n, 2), nb.reshape(n, *nb.shape[3:]))
        ids = np.empty(len(nh), np.int64)
        for i, (k, h, b) in enumerate(zip(_keys(nh, nb), nh, nb)):
            j = index.get(k)
            if j is None:
                j = index[k] = len(humans)
                humans.append(h)
                blockss.append(b)
            ids[i] = j
        transitions.extend(ids.reshape(shape))
        done = batch.stop
        if len(humans) > max_states:
            raise TooManyStates(f"more than {max_states:,} reachable states: too large for exact analysis "
                                f"(a {env.size}x{env.size} grid with {env.num_blocks} blocks; a 4x4 grid with 4 blocks has 28,604)")
    start = np.bincount(start_ids, minlength=len(humans)).astype(np.float64)
    return StateSpace(
        env=env,
        goal=goal,
        human=np.stack(humans).astype(np.int32),
        blocks=np.stack(blockss).astype(np.int32),
        next_state=np.stack(transitions).astype(np.int32),
        start=start / start.sum(),
    )


def human_policy(space: StateSpace, human) -> np.ndarray:
    """float64[S, A_H]: the human model's exact action distribution in every state."""
    probs = np.asarray(jax.jit(jax.vmap(human.action_probs))(space.states()), dtype=np.float64)
    return probs / probs.sum(axis=1, keepdims=True)  # exact in float64 (float32 sums miss 1 by ~1e-8)


def uniform_robot(space: StateSpace) -> np.ndarray:
    a = space.env.num_robot_actions
    return np.full((space.size, a), 1.0 / a)


def boltzmann_robot(space: StateSpace, log_probs_fn: Callable) -> np.ndarray:
    """float64[S, A_R] from a function of a batch of observations -> log-probabilities."""
    obs = jax.vmap(space.env.observe)(space.states())
    probs = np.exp(np.asarray(log_probs_fn(obs), dtype=np.float64))
    return probs / probs.sum(axis=1, keepdims=True)


def transition_matrix(space: StateSpace, pi_robot: np.ndarray, pi_human: np.ndarray) -> sparse.csr_matrix:
    """P[s, s'] under the joint policy, sparse: each state has at most A_R x A_H successors and
    most robot actions share their effect, so a few dozen non-zeros per row."""
    s, a_r, a_h = space.next_state.shape
    weights = pi_robot[:, :, None] * pi_human[:, None, :]
    rows = np.repeat(np.arange(s), a_r * a_h)
    p = sparse.coo_matrix((weights.reshape(-1), (rows, space.next_state.reshape(-1))), shape=(s, s))
    return p.tocsr()  # duplicates summed


def occupancy(p, gamma: float) -> np.ndarray:
    """M = (1 - gamma) (I - gamma P)^-1, dense: row s is the distribution of s_{t+K}, K ~ Geom,
    from s_{t+1} = s. For small state spaces and tests; `Occupancy` never forms M."""
    p = p.toarray() if sparse.issparse(p) else np.asarray(p)
    n = len(p)
    return (1.0 - gamma) * np.linalg.solve(np.eye(n) - gamma * p, np.eye(n))


class Occupancy(Protocol):
    """M = (1 - gamma) (I - gamma P)^-1 without forming it: what exact analysis needs of it."""

    size: int
    gamma: float

    def rows(self, states: np.ndarray) -> np.ndarray:
        """float64[len(states), S]: M[states], the future-state distributions from those states."""

    def times(self, v: np.ndarray) -> np.ndarray:
        """M @ v."""

    def discounted_sum(self, v: np.ndarray) -> np.ndarray:
        """(I - gamma P)^-1 v: the discounted sum of v along the chain from each state."""

    def visitation(self, start: np.ndarray) -> np.ndarray:
        """(1 - gamma) mu0 (I - gamma P)^-1: the discounted state distribution from mu0."""


def solve_occupancy(p, gamma: float, dense_states: int | None = None,
                    progress: Callable[[int], None] | None = None) -> Occupancy:
    """The dense LU up to `dense_states` states (DENSE_STATES unless given; fastest there), the
    sparse series above (`progress` hears of each chunk of columns it finishes)."""
    limit = DENSE_STATES if dense_states is None else dense_states
    return LUOccupancy(p, gamma) if p.shape[0] <= limit else SeriesOccupancy(p, gamma, progress=progress)


class LUOccupancy:
    """M as one LU factorisation of I - gamma P: its rows, its products and the discounted
    visitation, each a triangular solve. The factorisation is dense: a sparse LU of a 4 x 4 grid
    with 4 blocks (28,604 states) fills in to 250 million entries and takes 14 minutes, the
    dense one 12 minutes and 13 GB, so above DENSE_STATES `SeriesOccupancy` serves instead."""

    def __init__(self, p, gamma: float):
        p = p.toarray() if sparse.issparse(p) else np.asarray(p, np.float64)
        self.size, self.gamma = p.shape[0], gamma
        self._lu = lu_factor(np.eye(self.size) - gamma * p, overwrite_a=True, check_finite=False)

    def rows(self, states: np.ndarray) -> np.ndarray:
        """float64[len(states), S]: M[states] (row s solves (I - gamma P)^T x = e_s)."""
        e = np.zeros((self.size, len(states)))
        e[np.asarray(states), np.arange(len(states))] = 1.0
        return (1.0 - self.gamma) * lu_solve(self._lu, e, trans=1, check_finite=False).T

    def times(self, v: np.ndarray) -> np.ndarray:
        """M @ v."""
        return (1.0 - self.gamma) * lu_solve(self._lu, np.asarray(v, np.float64), check_finite=False)

    def discounted_sum(self, v: np.ndarray) -> np.ndarray:
        """(I - gamma P)^-1 v: the discounted sum of v along the chain from each state."""
        return lu_solve(self._lu, np.asarray(v, np.float64), check_finite=False)

    def visitation(self, start: np.ndarray) -> np.ndarray:
        """(1 - gamma) mu0 (I - gamma P)^-1: the discounted state distribution from mu0."""
        return (1.0 - self.gamma) * lu_solve(self._lu, np.asarray(start, np.float64), trans=1, check_finite=False)


# Where the Neumann series stops: the terms left out weigh at most this much (in l1, per row of
# M), far below the float64 rounding that KL terms of size 1e-3 already carry.
SERIES_TOLERANCE = 1e-10


class SeriesOccupancy:
    """M = (1 - gamma) sum_k gamma^k P^k, summed with sparse products until the rest weighs at
    most `tolerance`. P is stochastic, so every term gamma^k x P^k of a row has l1 mass gamma^k
    and the rest of the series after K terms exactly gamma^K: K = log(tolerance) / log(gamma)
    terms (219 at gamma 0.9) bound the error of every row, product and visitation alike. Each
    term costs one product with P's few dozen non-zeros per row, so the cost grows with the
    columns wanted, not S^3: the rows a trained robot's visited pairs need on a 4 x 4 grid with
    4 blocks take minutes where the dense LU takes 12 and 13 GB. `chunk` columns at a time bound
    the memory (S x chunk floats, twice)."""

    def __init__(self, p, gamma: float, tolerance: float = SERIES_TOLERANCE, chunk: int = 256,
                 progress: Callable[[int], None] | None = None):
        p = sparse.csr_matrix(p, dtype=np.float64)
        self.size, self.gamma = p.shape[0], gamma
        self._p, self._pt = p, p.T.tocsr()
        self.terms = 1 if gamma == 0.0 else max(1, math.ceil(math.log(tolerance) / math.log(gamma)))
        self._chunk = chunk
        self._progress = progress  # called with the number of columns each finished chunk solved

    def _sum(self, matrix, term: np.ndarray) -> np.ndarray:
        """sum_{k < terms} gamma^k matrix^k term, term [S, C]."""
        total = term.copy()
        for _ in range(self.terms - 1):
            term = self.gamma * (matrix @ term)
            total += term
        if self._progress is not None:
            self._progress(total.shape[1])
        return total

    def _series(self, matrix, v: np.ndarray) -> np.ndarray:
        """sum_k gamma^k matrix^k v for v [S] or [S, C], `chunk` columns at a time."""
        v = np.asarray(v, np.float64)
        cols = v.reshape(self.size, -1)
        out = np.empty_like(cols)
        for c in range(0, cols.shape[1], self._chunk):
            out[:, c : c + self._chunk] = self._sum(matrix, np.array(cols[:, c : c + self._chunk]))
        return out.reshape(v.shape)

    def rows(self, states: np.ndarray) -> np.ndarray:
        states = np.asarray(states)
        out = np.empty((len(states), self.size))  # built a chunk at a time: no S x len(states) copies
        for c in range(0, len(states), self._chunk):
            part = states[c : c + self._chunk]
            e = np.zeros((self.size, len(part)))
            e[part, np.arange(len(part))] = 1.0
            out[c : c + len(part)] = (1.0 - self.gamma) * self._sum(self._pt, e).T  # row s: e_s^T sum gamma^k P^k
        return out

    def times(self, v: np.ndarray) -> np.ndarray:
        return (1.0 - self.gamma) * self._series(self._p, v)

    def discounted_sum(self, v: np.ndarray) -> np.ndarray:
        return self._series(self._p, v)

    def visitation(self, start: np.ndarray) -> np.ndarray:
        return (1.0 - self.gamma) * self._series(self._pt, start)


def _mutual_information(m_rows: np.ndarray, pi_h: np.ndarray) -> np.ndarray:
    """I(aH; s+ | s, aR) from rho = m_rows [U, A_H, S] (the rows of M at each next state) and the
    human policy pi_h [U, A_H]."""
    rho = m_rows
    mix = np.einsum("uh,uhs->us", pi_h, rho)[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(rho > 0, rho * np.log(rho / np.where(mix > 0, mix, 1.0)), 0.0)
    return np.einsum("uh,uh->u", pi_h, terms.sum(axis=-1))


def merge_indistinguishable(next_states: np.ndarray, pi_h: np.ndarray) -> np.ndarray:
    """[U, A_H] -> [U, A_H]: the human policy over the classes of actions that observations can
    tell apart. Actions with the same next state leave the same (s, s'), so each class's
    probability goes to its first action and the others get 0 (a model that sees only
    observations can infer at most the class)."""
    first = np.ones(next_states.shape, bool)
    for h in range(1, next_states.shape[1]):
        first[:, h] = ~np.any(next_states[:, :h] == next_states[:, h : h + 1], axis=1)
    same = next_states[:, :, None] == next_states[:, None, :]  # [U, h, h']
    return np.where(first, np.einsum("uhk,uk->uh", same, pi_h), 0.0)


@dataclass(frozen=True)
class Empowerment:
    mi: np.ndarray  # float64[S, A_R]: I(aH; s+ | s, aR), nats; NaN for pairs not computed
    mi_merged: np.ndarray  # float64[S, A_R]: the same with actions merged into observable classes
    state_mi: np.ndarray  # float64[S]: expected over the robot policy (pairs not computed count 0)
    value: np.ndarray  # float64[S]: discounted effective empowerment from each state
    effective_empowerment: float  # from the start distribution
    occupancy: Occupancy
    visitation: np.ndarray  # float64[S]: discounted state distribution from the start, sums to 1
    complete: bool  # MI computed and counted for every pair (else state_mi and value are lower bounds)
    counted: np.ndarray  # bool[S, A_R]: the pairs whose MI state_mi and value count


# "Visited" (state, robot action) pairs: the most likely pairs under the robot's own discounted
# occupancy from the start states that together hold this share of it.
VISITED_MASS = 0.99


def visited_pairs(occupancy: Occupancy, start: np.ndarray, pi_robot: np.ndarray) -> np.ndarray:
    """bool[S, A_R]: the smallest set of pairs holding VISITED_MASS of the discounted occupancy
    d(s) pi_R(aR | s), d the discounted state distribution from `start` under the chain whose
    `occupancy` this is (the robot's own)."""
    weight = (occupancy.visitation(start)[:, None] * pi_robot).reshape(-1)
    order = np.argsort(-weight)
    keep = np.cumsum(weight[order]) <= VISITED_MASS * weight.sum()
    keep[np.argmin(keep)] = True  # the pair that crosses the threshold belongs to the set
    mask = np.zeros(weight.shape, bool)
    mask[order[keep]] = True
    return mask.reshape(pi_robot.shape)


# The uniform sample of pairs that stands for all of them where the space is too large to
# compute every pair: drawn from a fixed generator, so an artifact's sample is a function of its
# components alone.
SAMPLE_SEED = 0


def sampled_pairs(shape: tuple[int, int], n: int, seed: int = SAMPLE_SEED) -> np.ndarray:
    """bool[S, A_R]: n distinct (state, robot action) pairs drawn uniformly from all of them
    (every pair where n covers them all)."""
    total = shape[0] * shape[1]
    mask = np.zeros(total, bool)
    mask[np.random.default_rng(seed).choice(total, size=min(n, total), replace=False)] = True
    return mask.reshape(shape)


def _distinct_pairs(space: StateSpace, wanted: np.ndarray):
    """The distinct (state, next states over aH) rows among the wanted pairs (most robot actions
    are no-ops or share their effect), the pairs' flat indices and their row in the distinct set."""
    s, a_r, a_h = space.next_state.shape
    rows = np.concatenate([np.repeat(np.arange(s), a_r)[:, None], space.next_state.reshape(s * a_r, a_h)], axis=1)
    picked = np.flatnonzero(np.asarray(wanted, bool).reshape(-1))
    unique, inverse = np.unique(rows[picked], axis=0, return_inverse=True)
    return unique, picked, inverse.reshape(-1)


def rows_needed(space: StateSpace, pairs: np.ndarray) -> int:
    """How many rows of M `empowerment` solves for these pairs: their distinct next states."""
    return len(np.unique(space.next_state[np.asarray(pairs, bool)]))


def empowerment(
    space: StateSpace, pi_robot: np.ndarray, pi_human: np.ndarray, gamma: float,
    pairs: np.ndarray | None = None, batch: int = 64, occupancy: Occupancy | None = None,
    counted: np.ndarray | None = None,
) -> Empowerment:
    """Exact MI for every (state, robot action), or only where `pairs` (bool[S, A_R]) is true:
    the rows of M are solved for just the next states those pairs need. `occupancy` is the
    chain's under these policies if the caller has it already (else solved here). `counted`
    (bool[S, A_R], within `pairs`; default all of them): the pairs whose MI enters state_mi and
    the value, so that pairs computed for another purpose (a uniform sample, to rank over) leave
    the effective empowerment's lower bound as it is."""
    occ = occupancy if occupancy is not None else solve_occupancy(transition_matrix(space, pi_robot, pi_human), gamma)
    s, a_r, a_h = space.next_state.shape
    wanted = np.ones((s, a_r), bool) if pairs is None else np.asarray(pairs, bool)
    unique, picked, inverse = _distinct_pairs(space, wanted)
    # Every row of M the pairs need, solved once: S x (rows needed) floats, at most 7 GB at MAX_STATES.
    needed = np.unique(unique[:, 1:])
    table = occ.rows(needed)
    where = np.zeros(s, np.int64)
    where[needed] = np.arange(len(needed))
    mi_unique, merged_unique = np.empty(len(unique)), np.empty(len(unique))
    for i in range(0, len(unique), batch):
        chunk = unique[i : i + batch]
        m_rows = table[where[chunk[:, 1:].reshape(-1)]].reshape(len(chunk), a_h, s)
        mi_unique[i : i + batch] = _mutual_information(m_rows, pi_human[chunk[:, 0]])
        merged_unique[i : i + batch] = _mutual_information(m_rows, merge_indistinguishable(chunk[:, 1:], pi_human[chunk[:, 0]]))

    def per_pair(values):
        out = np.full(s * a_r, np.nan)
        out[picked] = np.maximum(values[inverse], 0.0)  # KL >= 0; clip rounding
        return out.reshape(s, a_r)

    mi, mi_merged = per_pair(mi_unique), per_pair(merged_unique)
    counts = wanted if counted is None else np.asarray(counted, bool) & wanted
    state_mi = np.sum(pi_robot * np.where(counts, np.nan_to_num(mi, nan=0.0), 0.0), axis=1)
    value = occ.discounted_sum(state_mi)
    return Empowerment(
        mi=mi, mi_merged=mi_merged, state_mi=state_mi, value=value, effective_empowerment=float(space.start @ value),
        occupancy=occ, visitation=occ.visitation(space.start), complete=bool(counts.all()), counted=counts,
    )


def start_states(env: Gridworld, goal, samples: int = 4096, seed: int = 0) -> GridState:
    """Start states of `env` whose goal is `goal`: resets are sampled and given this goal, and
    those where the goal cell is occupied are dropped (the reset never puts the goal there)."""
    states = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(seed), samples))
    goal_arr = jnp.asarray(goal, jnp.int32)
    occupied = jnp.all(states.human == goal_arr, axis=-1) | jnp.any(jnp.all(states.blocks == goal_arr, axis=-1), axis=-1)
    keep = np.flatnonzero(~np.asarray(occupied))
    return GridState(
        human=states.human[keep], blocks=states.blocks[keep],
        goal=jnp.broadcast_to(goal_arr, (len(keep), 2)), t=states.t[keep],
    )
