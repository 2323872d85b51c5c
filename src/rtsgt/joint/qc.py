"""The motion prior's ``Qc`` from the data: one diagonal ``Qc`` per motion class (standing and
half-decades of acceleration, the classes of :mod:`rtsgt.interpolation.motion`), each by
iterated variance components with redundancy numbers (Förstner): docs/joint.md#qc-from-the-data.
"""

from __future__ import annotations

import numpy as np

from rtsgt.interpolation.motion import ACCELERATION_EDGES_M_S2, CLASS_NAMES, STANDING_SPEED_M_S
from rtsgt.joint.prior import wnoa_coef

#: Window over which a knot's acceleration is measured (velocity difference across it), s.
ACC_WINDOW_S = 1.0
#: Least redundancy of a (class, axis) group to get its own ``Qc``; below it, the axis' pooled.
MIN_REDUNDANCY = 10.0
#: Most variance-component iterations, and the relative change of every ``Qc`` below which
#: they stop.
VCE_MAX_ITER = 8
VCE_TOL = 0.05
#: Gauss-Newton iterations between two variance-component updates (the last solve runs to
#: convergence).
VCE_GN_ITER = 1
#: Smallest ``Qc`` of a group (m^2/s^3 and rad^2/s^3): a direction the robot does not move in
#: (a wheeled robot's lateral velocity) has a maximum-likelihood ``Qc`` of 0; held here, its
#: prior is as stiff as the solver's conditioning allows (docs/joint.md#qc-from-the-data).
QC_FLOOR = 1e-10
#: Number of motion classes (index 0 standing).
N_CLASSES = len(CLASS_NAMES)


def motion_classes(t: np.ndarray, R: np.ndarray, w: np.ndarray,
                   points: np.ndarray | None = None) -> np.ndarray:
    """Class (K-1,) of each interval between knots at ``t`` (K,) s with poses ``R`` (K, 3, 3)
    and body velocities ``w`` (K, 6): the faster class of its two ends. A knot stands where
    every one of ``points`` (P, 3) m (body frame: the prisms; None: the origin alone) moves
    slower than :data:`STANDING_SPEED_M_S` (a turn in place about one of them is not
    standing); else its class is that of the largest norm of a point's world velocity change
    across :data:`ACC_WINDOW_S`, divided by the window (m/s^2)."""
    pts = np.zeros((1, 3)) if points is None else np.asarray(points, dtype=float)
    vb = w[:, None, :3] + np.cross(w[:, None, 3:], pts[None])  # (K, P, 3)
    v = np.einsum("kij,kpj->kpi", R, vb)
    h = 0.5 * ACC_WINDOW_S
    tp = np.minimum(t + h, t[-1])
    tm = np.maximum(t - h, t[0])
    dv = np.stack([[np.interp(tp, t, v[:, p, i]) - np.interp(tm, t, v[:, p, i])
                    for i in range(3)] for p in range(pts.shape[0])])  # (P, 3, K): a handful
    acc = np.linalg.norm(dv, axis=1).max(axis=0) / np.maximum(tp - tm, 1e-9)
    moving = 1 + np.searchsorted(np.asarray(ACCELERATION_EDGES_M_S2), acc, side="right")
    speed = np.linalg.norm(v, axis=2).max(axis=1)
    cls = np.where(speed < STANDING_SPEED_M_S, 0, moving)
    return np.maximum(cls[:-1], cls[1:])


def prior_components(e, E, F, dt, qc, cov, cov_next):
    """Per interval and axis (K-1, 6): the prior error's quadratic form at unit ``Qc``,
    ``e_i^T Q0^-1 e_i`` (rows i and 6+i of ``e``), and its redundancy number
    ``2 - tr(Q_i^-1 (J Sigma J^T)_i)``.

    ``e`` (K-1, 12), ``E``, ``F`` (K-1, 12, 12) the prior's errors and Jacobians
    (:func:`rtsgt.joint.prior.prior_terms`), ``dt`` (K-1,) s, ``qc`` (K-1, 6) the ``Qc`` used,
    ``cov`` (K, 12, 12), ``cov_next`` (K-1, 12, 12) the knots' posterior covariances.
    """
    n = e.shape[0]
    coef = wnoa_coef(dt)
    e5 = e.reshape(n, 2, 6)
    quad = np.einsum("kai,abk,kbi->ki", e5, coef, e5)
    Et, Ft = np.swapaxes(E, 1, 2), np.swapaxes(F, 1, 2)
    EC = E @ cov_next @ Ft
    M = E @ cov[:-1] @ Et + F @ cov[1:] @ Ft + EC + np.swapaxes(EC, 1, 2)
    Md = np.einsum("kaibi->kabi", M.reshape(n, 2, 6, 2, 6))
    red = 2.0 - np.einsum("abk,kbai->ki", coef, Md) / qc
    return quad, red


def with_gaps(qc: np.ndarray, gap: np.ndarray, trusted: np.ndarray | None = None,
              moving: np.ndarray | None = None) -> np.ndarray:
    """``Qc`` (K-1, 6) per interval with the gaps' (``gap`` (K-1,): intervals no measurement
    is near) set, per axis, to the loosest of the moving intervals' (``moving`` (K-1,), None:
    every other interval) whose ``Qc`` the data determine (``trusted`` (K-1, 6), None: all),
    or, on an axis where none is, of every moving interval's (their pooled estimate): while
    no station tracked it the robot may have moved as it does anywhere else in the run, no
    more tightly (docs/joint.md#gaps). Unchanged without a gap, or without other intervals."""
    qc = np.array(qc, dtype=float)
    cand = ~gap if moving is None else ~gap & np.asarray(moving, bool)
    if not gap.any() or not cand.any():
        return qc
    ok = cand[:, None] & (np.ones(qc.shape, bool) if trusted is None
                          else np.asarray(trusted, bool))
    ok[:, ~ok.any(axis=0)] = cand[:, None]
    qc[gap] = np.where(ok, qc, 0.0).max(axis=0)
    return qc


def class_members(classes: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """Which intervals (K-1,) enter their motion class's variance components, of classes
    ``classes`` (K-1,) (0 standing) and gaps ``gap`` (K-1,): all but a gap between two
    stops. A gap between moving ends is its class's motion over a longer interval, and the
    only measure the run has of how that motion drifts from the prior's white acceleration
    over seconds; a standing class's gap is the robot driven between two stops, not its
    standing (docs/joint.md#gaps)."""
    return ~np.asarray(gap, bool) | (np.asarray(classes) > 0)


def qc_per_class(quad: np.ndarray, red: np.ndarray, classes: np.ndarray,
                 own: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The variance-component estimate of ``Qc`` (N_CLASSES, 6): each (class, axis) group the
    sum of its quadratic forms over the sum of its redundancy numbers, and ``own``
    (N_CLASSES, 6) which groups have their own. A group not ``own`` takes its axis' pooled
    estimate over the classes not own; ``own`` None: those with redundancy at least
    :data:`MIN_REDUNDANCY`."""
    sq = np.zeros((N_CLASSES, 6))
    sr = np.zeros((N_CLASSES, 6))
    np.add.at(sq, classes, quad)
    np.add.at(sr, classes, red)
    if own is None:
        own = sr >= MIN_REDUNDANCY
    rest_q = np.where(own, 0.0, sq).sum(axis=0)
    rest_r = np.where(own, 0.0, sr).sum(axis=0)
    pooled = np.where(rest_r > 0, rest_q / np.where(rest_r > 0, rest_r, 1.0),
                      sq.sum(axis=0) / np.maximum(sr.sum(axis=0), 1e-12))
    out = np.where(own, sq / np.where(own, sr, 1.0), pooled[None, :])
    return np.maximum(out, QC_FLOOR), own


__all__ = ["ACC_WINDOW_S", "MIN_REDUNDANCY", "N_CLASSES", "QC_FLOOR", "VCE_GN_ITER",
           "VCE_MAX_ITER", "VCE_TOL", "class_members", "motion_classes", "prior_components",
           "qc_per_class", "with_gaps"]
