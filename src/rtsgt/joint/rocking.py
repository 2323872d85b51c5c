"""The vehicle's rocking: a first-order Gauss-Markov process per axis of the knots' pose,
added to the pose every measurement sees, carried as states of the knots; its rotations
about the vehicle's pivot.

A vehicle rocks on its suspension faster than one prism at a time can follow; with the
rocking taken for the stations' white noise, the model's cost prefers a wrong body frame
(docs/joint.md#the-vehicles-rocking). Axes as the pose's right perturbation (shifts along
x, y, z, then rotations about them: rtsgt.joint.se3's order), each its own chain with the
:mod:`rtsgt.joint.gm` process, its sigma and correlation time estimated as the noise
chains' are (:func:`rtsgt.joint.gm.update`: the model's rows are the shifts and the
rotations). The rotations turn about the vehicle's pivot, below its prisms, and carry the
prisms sideways with them: the knots' states are the rocked pose's perturbation ``r``, the
chains the process's about the pivot, ``u = P^-1 r`` (:func:`pivot_map`;
docs/joint.md#the-rockings-pivot).
"""

from __future__ import annotations

import numpy as np

from rtsgt.geometry.so3 import hat
from rtsgt.joint import gm as gmn
from rtsgt.joint.se3 import exp_se3
from rtsgt.joint.sparse import ArrowSolution, chunks

#: The rocking's chains per knot: shifts along x, y, z (m), rotations about them (rad).
ROCKING_DIM = 6
#: Starting sigma of the shifts' chains, m, and of the rotations', rad: a rocking vehicle's
#: size (docs/simulation.md#the-vehicles-rocking); the data decide from there.
START_SIGMA_M = 1e-3
START_SIGMA_RAD = 1e-3
#: Starting correlation time, s: a suspension's period, 0.3-2 s.
START_TAU_S = 0.3


def start_rocking() -> gmn.GaussMarkov:
    """The rocking's starting chains (:class:`rtsgt.joint.gm.GaussMarkov`, rows the shifts
    and the rotations, columns x, y, z), none determined."""
    sigma = np.array([[START_SIGMA_M] * 3, [START_SIGMA_RAD] * 3])
    return gmn.GaussMarkov(sigma, np.full((2, 3), START_TAU_S), sigma.copy(),
                           np.zeros((2, 3), bool))


def pivot_map(pivot: np.ndarray | None) -> np.ndarray:
    """The rocked pose's perturbation per unit of the rocking process's (shifts, rotations),
    (6, 6), its rotations about the point ``pivot`` (3,) m of the knots' frame (None: their
    origin): ``[[I, p^], [0, I]]`` (a rotation ``phi`` about ``p`` moves the origin by
    ``p x phi``, to first order). Its inverse is ``pivot_map(-pivot)``."""
    M = np.eye(6)
    if pivot is not None:
        M[:3, 3:] = hat(np.asarray(pivot, dtype=float))
    return M


def add_rocking_prior(D: np.ndarray, U: np.ndarray, a: np.ndarray, rock: np.ndarray,
                      dt: np.ndarray, model: gmn.GaussMarkov, col: int,
                      pivot: np.ndarray | None = None) -> float:
    """Adds the rocking's prior to the knots' normal equations ``D`` (K, d, d), ``U``
    (K-1, d, d), ``a`` (K, d) (in place; the rocked pose's perturbations ``rock`` (K, 6) at
    columns ``col:col+6``) and returns its cost: the chains of ``model``
    (:func:`rtsgt.joint.gm.add_prior`) on the process ``u_k = T r_k``, ``T`` the inverse of
    :func:`pivot_map` of ``pivot`` (3,) m, turned to the knots' columns (``T^T . T``,
    ``T^T a``)."""
    if pivot is None:
        return gmn.add_prior(D, U, a, rock, dt, model, col)
    T = pivot_map(-np.asarray(pivot, dtype=float))
    K = rock.shape[0]
    Du, Uu, au = np.zeros((K, 6, 6)), np.zeros((K - 1, 6, 6)), np.zeros((K, 6))
    cost = gmn.add_prior(Du, Uu, au, rock @ T.T, dt, model, 0)
    j = slice(col, col + ROCKING_DIM)
    D[:, j, j] += T.T @ Du @ T
    U[:, j, j] += T.T @ Uu @ T
    a[:, j] += au @ T
    return cost


def rocking_moments(rock: np.ndarray, cov: np.ndarray, cross: np.ndarray,
                    dt: np.ndarray, pivot: np.ndarray | None = None) -> list:
    """The chains' posterior moments for :func:`rtsgt.joint.gm.update`, one per row of the
    model (shifts, rotations) of the process ``u = T r`` (:func:`add_rocking_prior`): from
    the rocked pose's perturbations' means ``rock`` (K, 6), marginal covariances ``cov``
    (K, 6, 6) and consecutive covariances ``cross`` (K-1, 6, 6) at every knot, intervals
    ``dt`` (K-1,) s (every knot holds a measurement: the complete data), ``pivot`` (3,) m
    (None: the knots' origin)."""
    T = pivot_map(None if pivot is None else -np.asarray(pivot, dtype=float))
    u = rock @ T.T
    var = np.einsum("ij,kjl,il->ki", T, cov, T)
    cr = np.einsum("ij,kjl,il->ki", T, cross, T)
    return [(u[:, 3 * i:3 * i + 3], var[:, 3 * i:3 * i + 3], cr[:, 3 * i:3 * i + 3], dt)
            for i in range(2)]


def rocked_knots(R: np.ndarray, t: np.ndarray, rocking: np.ndarray, sol: ArrowSolution,
                 col: int) -> tuple[np.ndarray, np.ndarray, ArrowSolution]:
    """The knots' poses with their rocking, ``T_k exp(r_k^)`` (``R`` (K, 3, 3), ``t`` (K, 3),
    ``rocking`` (K, 6)), and ``sol`` with each knot's pose perturbation (its first 6 states)
    as the rocked pose's, ``xi_k + r_k`` (first order: ``r`` is millimetres and
    milliradians; the rocking's states at columns ``col:col+6``): ``M . M^T`` of the knots'
    covariances, ``M`` of the shared factor, all turned in place, a few thousand knots at a
    time (as :func:`rtsgt.joint.axes.body_solution`'s factor: the solution is not read
    unrocked after this, and the hour's arrays are not copied)."""
    dR, dp = exp_se3(rocking)
    j = slice(col, col + ROCKING_DIM)
    for a in (sol.cov, sol.cov_next, sol.cov_var, sol.cov_var_next):  # M a M^T
        for sl in chunks(a.shape[0]):
            a[sl, :6] += a[sl, j]
            a[sl, :, :6] += a[sl, :, j]
    for sl in chunks(sol.factor.shape[0]):  # M L
        sol.factor[sl, :6] += sol.factor[sl, j]
    return R @ dR, t + np.einsum("kij,kj->ki", R, dp), sol


def bridge_variance(t_query: np.ndarray, t_knot: np.ndarray, model: gmn.GaussMarkov
                    ) -> np.ndarray:
    """The rocking's variance (Q, 6) at ``t_query`` (Q,) s given its values at the two knots
    of the interval (``t_knot`` (K,) s) about each: per axis ``sigma^2 (1 - phi_a^2)
    (1 - phi_b^2) / (1 - phi_a^2 phi_b^2)``, ``phi = exp(-h / tau)`` over the times ``h`` to
    the interval's knots (the process is Markov: the knots beyond add nothing); zero at a
    knot. What the knots' poses with their rocking do not carry between them."""
    tq = np.asarray(t_query, dtype=float)
    k = np.clip(np.searchsorted(t_knot, tq, side="right") - 1, 0, t_knot.size - 2)
    sigma, tau = model.sigma.ravel(), model.tau_s.ravel()
    pa = np.exp(-2.0 * np.clip(tq - t_knot[k], 0.0, None)[:, None] / tau)
    pb = np.exp(-2.0 * np.clip(t_knot[k + 1] - tq, 0.0, None)[:, None] / tau)
    return sigma**2 * (1.0 - pa) * (1.0 - pb) / np.maximum(1.0 - pa * pb, 1e-300)


__all__ = ["ROCKING_DIM", "START_SIGMA_M", "START_SIGMA_RAD", "START_TAU_S", "add_rocking_prior",
           "bridge_variance", "pivot_map", "rocked_knots", "rocking_moments", "start_rocking"]
