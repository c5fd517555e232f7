"""The information geometry of empowerment on a small tabular MDP (the paper's section 3).

For a state s, each action a gives a discounted future-state distribution rho(. | s, a); the
policy's average rho(. | s) = sum_a pi(a|s) rho(. | s, a) lies inside their convex hull (the
state-marginal polytope). The mutual information is I(a; s+ | s) = sum_a pi(a|s) KL(rho_a || rho);
for the capacity-achieving policy (Blahut-Arimoto) it equals max_a KL(rho_a || rho): the
distance from the centre to the furthest vertices. Occupancies use the same solve as
`exact.py`; everything is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from esr_cli.analysis.exact import occupancy


def kl_rows(rho: np.ndarray, mix: np.ndarray) -> np.ndarray:
    """KL(rho_a || mix) for each row a, in nats (0 log 0 = 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(rho > 0, rho * np.log(rho / np.where(mix > 0, mix, 1.0)), 0.0).sum(axis=-1)


def future_distributions(transitions: np.ndarray, policy: np.ndarray, gamma: float) -> np.ndarray:
    """rho[s, a, s+] for a tabular MDP T[s, a, s'] under policy pi[s, a]: s+ = s_{t+K},
    K ~ Geometric(1 - gamma) on {1, 2, ...}, after taking a in s."""
    p = np.einsum("sa,sat->st", policy, transitions)
    return np.einsum("sat,tu->sau", transitions, occupancy(p, gamma))


def capacity_policy(rho: np.ndarray, iters: int = 2000, tol: float = 1e-12) -> np.ndarray:
    """Blahut-Arimoto: the action distribution maximising sum_a pi_a KL(rho_a || sum pi rho)."""
    pi = np.full(len(rho), 1.0 / len(rho))
    for _ in range(iters):
        new = pi * np.exp(kl_rows(rho, pi @ rho))
        new /= new.sum()
        if np.abs(new - pi).max() < tol:
            return new
        pi = new
    return pi


@dataclass(frozen=True)
class Geometry:
    vertices: np.ndarray  # rho(. | s, a) for each action, [A, S]
    centre: np.ndarray  # rho(. | s) under the capacity-achieving action distribution
    policy: np.ndarray  # that distribution
    kl: np.ndarray  # KL(vertex_a || centre)
    mutual_information: float  # sum_a policy_a kl_a = max_a kl_a at capacity
    uniform_centre: np.ndarray  # rho(. | s) under the uniform action distribution
    uniform_mi: float


def example_mdp() -> np.ndarray:
    """A 3-state, 3-action MDP: action a moves to state a with probability 0.6 (0.3 for a = 2),
    otherwise to a uniformly random state. Asymmetric, so the capacity policy is not uniform."""
    t = np.zeros((3, 3, 3))
    success = [0.6, 0.6, 0.3]
    for s in range(3):
        for a in range(3):
            t[s, a] = (1 - success[a]) / 3
            t[s, a, a] += success[a]
    return t


def geometry(transitions: np.ndarray, state: int, gamma: float) -> Geometry:
    """The polytope of one state's future distributions, with the other states' policy uniform."""
    a = transitions.shape[1]
    uniform = np.full((transitions.shape[0], a), 1.0 / a)
    rho = future_distributions(transitions, uniform, gamma)[state]
    pi = capacity_policy(rho)
    centre = pi @ rho
    kl = kl_rows(rho, centre)
    u_centre = rho.mean(axis=0)
    return Geometry(
        vertices=rho, centre=centre, policy=pi, kl=kl, mutual_information=float(pi @ kl),
        uniform_centre=u_centre, uniform_mi=float(np.mean(kl_rows(rho, u_centre))),
    )
