"""The evaluation's steps that are specific to a ground truth of positions (3 dof: one
tracked point, a prism, on the robot): the alignment of the estimate's points ``p_S + R_S l``
onto the ground truth's positions (none | se3 | sim3 | 4dof | scale; ``origin`` needs an
orientation), its weighted form, an estimated lever arm's shared factor and the covariance of
the ground truth's displacements. The chain itself is :func:`rtsgt.evaluation.evaluate`'s, for
both kinds; the derivations are in docs/evaluation.md#position-only-ground-truth.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import ConvergenceError, GeometryError, InputError
from rtsgt.evaluation.align import MIN_POSES, Alignment, align_yaw, aligned_count, umeyama
from rtsgt.evaluation.associate import Association, PairCovarianceGroundTruth
from rtsgt.evaluation.lever_arm import (
    LeverArmPoints,
    lever_arm_factor,
    lever_arm_points,
    parse_lever_arm,
    point_covariance,
)
from rtsgt.evaluation.options import EvaluationOptions
from rtsgt.evaluation.result import ROTATION_NOT_REPORTED
from rtsgt.geometry.so3 import exp_so3, hat
from rtsgt.types import PoseTrajectory, PositionTrajectory

__all__ = ["POSITION_ALIGN_METHODS", "ROTATION_NOT_REPORTED", "align_points", "align_step",
           "check_position_alignment", "gls_alignment", "lever_arm_shared",
           "relative_position_covariance"]

#: Alignments of a position-only evaluation (``origin`` needs an orientation).
POSITION_ALIGN_METHODS = ("none", "se3", "sim3", "4dof", "scale")


def check_position_alignment(method: str) -> None:
    """An InputError unless ``method`` is one of :data:`POSITION_ALIGN_METHODS` (saying why
    ``origin`` is not)."""
    if method not in POSITION_ALIGN_METHODS:
        extra = (" (origin maps the first pose onto the first ground-truth pose: a "
                 "position-only ground truth has no orientation)" if method == "origin" else "")
        raise InputError(f"Expected an alignment in {POSITION_ALIGN_METHODS} for a "
                         f"position-only ground truth, got {method!r}{extra}")


#: Relative change of the scale that ends the Sim(3) alternation (:func:`align_points`).
SIM3_TOL = 1e-14
#: Most alternations of the Sim(3) alignment.
SIM3_MAX_ITER = 200


def align_points(
    gt_position: ArrayLike,
    est_position: ArrayLike,
    est_rotation: ArrayLike,
    lever_arm: ArrayLike,
    *,
    method: str = "se3",
    n_align: int | None = None,
    weights: ArrayLike | None = None,
) -> Alignment:
    """Fit the :class:`~rtsgt.evaluation.align.Alignment` (for the sensor poses) of the estimate's
    points ``p_S + R_S l`` onto ground-truth positions (N, 3) m
    (docs/evaluation.md#position-only-ground-truth).

    ``est_position`` (N, 3), ``est_rotation`` (N, 3, 3) in the estimate's frame, ``lever_arm``
    (3,) m; ``method`` of :data:`POSITION_ALIGN_METHODS`; ``n_align``; ``weights`` (N,) scalar or
    (N, 3, 3) information matrices (then :func:`gls_alignment`). InputError on an unknown method
    or too few positions; GeometryError on degenerate geometry.
    """
    check_position_alignment(method)
    y = np.asarray(gt_position, dtype=float)
    p = np.asarray(est_position, dtype=float)
    R = np.asarray(est_rotation, dtype=float)
    arm = R @ parse_lever_arm(lever_arm)
    n = aligned_count(y.shape[0], n_align)
    if method == "none":
        return Alignment("none", np.eye(3), np.zeros(3), 1.0, 0, False)
    if n < MIN_POSES[method]:
        raise InputError(
            f"Alignment {method!r} needs at least {MIN_POSES[method]} associated positions, "
            f"got {n}; check the time overlap, --max-gap and --t-offset")
    y, p, arm = y[:n], p[:n], arm[:n]
    weighted = weights is not None
    w = None if weights is None else np.asarray(weights, dtype=float)[:n]
    if w is not None and w.ndim == 3:  # information matrices: GLS from the unweighted fit
        start = align_points(y, p, R[:n], lever_arm, method=method)
        return gls_alignment(start, y, p, arm, w)
    x = p + arm
    if method == "4dof":
        Rz, t = align_yaw(x, y, w)
        return Alignment("4dof", Rz, t, 1.0, n, weighted)
    if method == "se3":
        Ra, t, _ = umeyama(x, y, w)
        return Alignment("se3", Ra, t, 1.0, n, weighted)
    wn = np.full(n, 1.0 / n) if w is None else w / w.sum()
    if method == "scale":
        den = float(wn @ np.einsum("ij,ij->i", p, p))
        if not den > 0:
            raise GeometryError("Degenerate scale alignment: every estimated position is at "
                                "the origin")
        s = float(wn @ np.einsum("ij,ij->i", y - arm, p)) / den
        return Alignment("scale", np.eye(3), np.zeros(3), s, n, weighted)
    # sim3: the rotation and the scale in turn (module docstring)
    _, _, s = umeyama(x, y, w, with_scale=True)
    p0 = p - wn @ p
    y0 = y - wn @ y
    a0 = arm - wn @ arm
    spread = float(wn @ np.einsum("ij,ij->i", p0, p0))
    for _ in range(SIM3_MAX_ITER):
        Ra, t, _ = umeyama(s * p + arm, y, w)
        Rp = p0 @ Ra.T
        s_new = float(wn @ np.einsum("ij,ij->i", Rp, y0 - a0 @ Ra.T)) / spread
        done = abs(s_new - s) <= SIM3_TOL * abs(s_new)
        s = s_new
        if done:
            break
    else:
        raise ConvergenceError(f"The Sim(3) alignment of the points did not converge in "
                               f"{SIM3_MAX_ITER} iterations (scale {s:.12g})")
    if not s > 0:
        raise GeometryError("Degenerate Sim(3) alignment: no positive scale fits the points")
    Ra, t, _ = umeyama(s * p + arm, y, w)
    return Alignment("sim3", Ra, t, s, n, weighted)


#: Largest Gauss-Newton steps of :func:`gls_alignment`, and the motion of the points a step
#: causes, relative to their spread, below which it stops (or 1000 units of the rounding of
#: their coordinates, if larger).
GLS_MAX_ITER = 50
GLS_TOL = 1e-12


def gls_alignment(start: Alignment, y: np.ndarray, p: np.ndarray, arm: np.ndarray,
                  W: np.ndarray) -> Alignment:
    r"""The alignment of ``start``'s method minimising ``sum_k r_k^T W_k r_k`` by Gauss-Newton about
    the aligned points' centroid (docs/evaluation.md#position-only-ground-truth). GeometryError
    when the normal equations are singular; ConvergenceError after :data:`GLS_MAX_ITER` steps.
    """
    method = start.method
    R, t, s = start.rotation.copy(), start.translation.copy(), float(start.scale)
    cols = {"se3": [0, 1, 2, 3, 4, 5], "4dof": [0, 1, 2, 5], "sim3": list(range(7)),
            "scale": [6]}[method]
    N = y.shape[0]
    for _ in range(GLS_MAX_ITER):
        x = (s * p + arm) @ R.T + t
        c = x.mean(axis=0) if method != "scale" else np.zeros(3)
        r = y - x
        J = np.zeros((N, 3, 7))
        J[:, :, :3] = np.eye(3)
        J[:, :, 3:6] = -hat(x - c)
        J[:, :, 6] = p @ R.T
        J = J[:, :, cols]
        JW = np.swapaxes(J, 1, 2) @ W
        H = np.einsum("nij,njk->ik", JW, J)
        g = np.einsum("nij,nj->i", JW, r)
        d = np.sqrt(np.diag(H))
        if not np.all(d > 0) or np.linalg.cond(H / np.outer(d, d)) > 1e12:
            raise GeometryError(f"Degenerate weighted {method} alignment: the positions do "
                                "not determine its parameters")
        step = np.zeros(7)
        step[cols] = np.linalg.solve(H, g)
        dR = exp_so3(step[3:6])
        R = dR @ R
        t = dR @ (t - c) + c + step[:3]
        s = s + step[6]
        # how far the step moves the points, against the spread of the points and the
        # rounding of their coordinates (far from the origin, e.g. UTM)
        spread = float(np.abs(x - c).max())
        move = (np.abs(step[:3]).max() + np.abs(step[3:6]).max() * spread
                + abs(step[6]) * float(np.abs(p).max()))
        if move <= max(GLS_TOL * spread, 1e3 * np.finfo(float).eps * float(np.abs(y).max())):
            break
    else:
        raise ConvergenceError(f"The weighted {method} alignment did not converge in "
                               f"{GLS_MAX_ITER} steps")
    if method == "scale":
        R, t = np.eye(3), np.zeros(3)
    return Alignment(method, R, t, s, N, True)


def align_step(g: PositionTrajectory, e_raw: PoseTrajectory, lever: np.ndarray,
               options: EvaluationOptions) -> Alignment:
    """The alignment of the estimate's points onto the ground truth (:func:`align_points`);
    with ``weighted``, generalised least squares, each error weighted by the inverse of its
    covariance (the estimate's point as the unweighted fit maps it)."""
    alignment = align_points(g.position, e_raw.position, e_raw.rotation, lever,
                             method=options.align, n_align=options.n_align)
    if not options.weighted or options.align == "none":
        return alignment
    if g.cov is None:
        raise InputError("A weighted alignment needs a ground truth with covariances")
    e0 = alignment.apply(e_raw)
    c0 = point_covariance(lever_arm_points(e0.position, e0.rotation, lever), e0.cov)
    try:
        W = np.linalg.inv(g.cov + (0.0 if c0 is None else c0))
    except np.linalg.LinAlgError:
        raise InputError("A weighted alignment needs positive definite covariances") from None
    return align_points(g.position, e_raw.position, e_raw.rotation, lever,
                        method=options.align, n_align=options.n_align, weights=W)


def lever_arm_shared(pts: LeverArmPoints,
                      lever_arm_cov: ArrayLike) -> tuple[np.ndarray, tuple[str, ...]]:
    """The points' factor of an estimated lever arm's error and its parameter names."""
    C_l = np.asarray(lever_arm_cov, dtype=float)
    if C_l.shape != (3, 3) or not np.all(np.isfinite(C_l)):
        raise InputError(f"Expected a finite 3x3 lever arm covariance, got shape {C_l.shape}")
    return lever_arm_factor(pts, C_l), ("lever_arm_x", "lever_arm_y", "lever_arm_z")


def relative_position_covariance(gt: object, g: PositionTrajectory, assoc: Association,
                         pairs: np.ndarray) -> tuple[np.ndarray, str]:
    """The ground truth's covariance of ``y_j - y_i`` for the RPE pairs, and where its
    correlations come from."""
    i, j = pairs[:, 0], pairs[:, 1]
    if isinstance(gt, PairCovarianceGroundTruth):
        P_i, P_j, C = gt.pair_covariances(g.t[i] + assoc.time_offset,
                                                   g.t[j] + assoc.time_offset)
        cov = P_i + P_j - C - np.swapaxes(C, 1, 2)
        why = "computed by the ground truth (shared systematic errors, GP correlation)"
    else:
        cov = g.cov[i] + g.cov[j]
        why = "assumed independent (no cross-covariance between ground-truth positions given)"
    return 0.5 * (cov + np.swapaxes(cov, 1, 2)), why
