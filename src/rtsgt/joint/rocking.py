"""The vehicle's rocking: a first-order Gauss-Markov process per axis of the knots' pose,
added to the pose every measurement sees, carried as states of the knots.

A vehicle rocks on its suspension faster than one prism at a time can follow; with the
rocking taken for the stations' white noise, the model's cost prefers a wrong body frame
(docs/joint.md#the-vehicles-rocking). Axes as the pose's right perturbation (shifts along
x, y, z, then rotations about them: rtsgt.joint.se3's order), each its own chain with the
:mod:`rtsgt.joint.gm` process, its sigma and correlation time estimated as the noise
chains' are (:func:`rtsgt.joint.gm.update`: the model's rows are the shifts and the
rotations).
"""

from __future__ import annotations

import numpy as np

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


def rocking_moments(rock: np.ndarray, cov: np.ndarray, cross: np.ndarray,
                    dt: np.ndarray) -> list:
    """The chains' posterior moments for :func:`rtsgt.joint.gm.update`, one per row of the
    model (shifts, rotations): from the chains' means ``rock`` (K, 6), marginal variances
    ``cov`` (K, 6) and consecutive covariances ``cross`` (K-1, 6) at every knot, intervals
    ``dt`` (K-1,) s (every knot holds a measurement: the complete data)."""
    return [(rock[:, 3 * i:3 * i + 3], cov[:, 3 * i:3 * i + 3], cross[:, 3 * i:3 * i + 3], dt)
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


__all__ = ["ROCKING_DIM", "START_SIGMA_M", "START_SIGMA_RAD", "START_TAU_S", "bridge_variance",
           "rocked_knots", "rocking_moments", "start_rocking"]
