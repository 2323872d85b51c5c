"""Slowly varying states as chains at the joint engine's knots: a level and its rate, the sum
of a random walk of the level and an integrated random walk of the rate (the stations' clock
offsets, the tripods' settling). ``(level, rate)`` is Markov, so the states sit at every knot
beside the trajectory and the normal equations stay block tridiagonal whatever the
deployment's length: docs/joint.md#slowly-varying-states.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.clocks import level_rate_noise
from rtsgt.joint.sparse import add_transitions

#: A process's two states at a knot, in this order (columns ``2 i``, ``2 i + 1`` of process
#: ``i`` in :meth:`LevelRate.add_prior`'s ``z``).
STATES = ("level", "rate")


def _inv2(Q: np.ndarray) -> np.ndarray:
    """Inverses (..., 2, 2) of SPD 2x2 blocks in closed form (the rate's and the level's
    variances differ by many orders: no pivoting to lose them in)."""
    det = Q[..., 0, 0] * Q[..., 1, 1] - Q[..., 0, 1] * Q[..., 1, 0]
    W = np.empty_like(Q)
    W[..., 0, 0] = Q[..., 1, 1] / det
    W[..., 1, 1] = Q[..., 0, 0] / det
    W[..., 0, 1] = W[..., 1, 0] = -Q[..., 0, 1] / det
    return W


@dataclass(frozen=True)
class LevelRate:
    """``n`` independent processes, each a level and its rate at every knot: ``q`` (n,) the
    level's random-walk intensity (unit^2/s), ``q_rate`` (n,) the rate's (unit^2/s^3, > 0),
    ``start`` (n, 2, 2) the covariance of ``(level, rate)`` at the first knot (zero mean)."""

    q: np.ndarray
    q_rate: np.ndarray
    start: np.ndarray

    @property
    def n(self) -> int:
        return self.q.size

    @property
    def size(self) -> int:
        """States per knot: a level and a rate per process."""
        return 2 * self.n

    def add_prior(self, D: np.ndarray, U: np.ndarray, a: np.ndarray, z: np.ndarray,
                  dt: np.ndarray, col: int) -> float:
        """Adds the processes' prior to the knots' normal equations ``D`` (K, d, d), ``U``
        (K-1, d, d), ``a`` (K, d) (in place; process ``i`` at columns ``col + 2 i`` and
        ``col + 2 i + 1``) at the knots' states ``z`` (K, 2 n) over the intervals ``dt``
        (K-1,) s, and returns its cost: ``z_0 ~ N(0, start)``, ``z_k+1 - F_k z_k ~ N(0,
        Q_k)`` (:func:`level_rate_noise`)."""
        F = np.zeros((dt.size, 2, 2))
        F[:, 0, 0] = F[:, 1, 1] = 1.0
        F[:, 0, 1] = dt
        eye = np.broadcast_to(np.eye(2), F.shape)
        cost = 0.0
        for i in range(self.n):  # a handful of processes, each vectorised over the knots
            c = slice(col + 2 * i, col + 2 * i + 2)
            zi = z[:, 2 * i:2 * i + 2]
            W = _inv2(level_rate_noise(dt, self.q[i], self.q_rate[i]))
            e = zi[1:] - np.einsum("kij,kj->ki", F, zi[:-1])
            cost += add_transitions(D, U, a, c, e, -F, eye, W)
            W0 = _inv2(self.start[i])
            D[0, c, c] += W0
            a[0, c] -= W0 @ zi[0]
            cost += float(zi[0] @ W0 @ zi[0])
        return cost


def at_times(z: np.ndarray, t_knot: np.ndarray, t: np.ndarray, knot: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each process's level at times ``t`` (T,) s from the knots ``t_knot`` (K,) and their
    states ``z`` (K, 2 n): ``level_k + (t - t_k) rate_k`` of the knot ``k`` at or before
    ``t`` (the first for earlier times; ``knot`` (T,) where given). Returns the levels
    (T, n), the knots ``k`` (T,) and the weights ``(1, t - t_k)`` (T, 2) of the knot's
    ``(level, rate)``."""
    t = np.asarray(t, dtype=float)
    if knot is None:
        knot = np.clip(np.searchsorted(t_knot, t, side="right") - 1, 0, t_knot.size - 1)
    w = np.stack([np.ones_like(t), t - t_knot[knot]], axis=1)
    lv = z[knot, 0::2] + w[:, 1:] * z[knot, 1::2]
    return lv, knot, w


__all__ = ["STATES", "LevelRate", "at_times"]
