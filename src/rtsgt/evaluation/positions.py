r"""Evaluation against a position-only ground truth: one tracked point (a prism) on the robot.

Most public datasets with total-station ground truth track **one prism** (NTU VIRAL, EuRoC's
Leica sequences, GrandTour), and ``rtsgt run`` on a deployment with one or two tracked prisms
gives the prisms' tracks with covariance and no pose. A SLAM or odometry estimate gives the
pose of its own sensor; with the lever arm ``l`` of the prism in the sensor frame
(:mod:`rtsgt.evaluation.lever_arm`), the estimate's prism is ``p_P = p_S + R_S l`` and is
compared with the ground truth's ``y``. :func:`evaluate_positions` runs the chain in evo's
order, as :func:`rtsgt.evaluation.evaluate` does for poses::

    associate (time offset, max_dt)  ->  lever arm  ->  align (point sets: none | se3 | sim3
      | 4dof | scale)  ->  APE, RPE of positions  ->  NEES (3 dof), noise floor

Association
-----------
As for poses (:mod:`rtsgt.evaluation.associate`): a discrete :class:`~rtsgt.types.
PositionTrajectory` is interpolated linearly (its covariance too, flagged), a continuous one
(:class:`ValidatedPositionGroundTruth`, e.g. :class:`rtsgt.evaluation.groundtruth.
ContinuousPositionGroundTruth` from a run directory) answers at every offset time with a drop
reason. The association of poses serves both: the ground truth is handed to it as poses whose
orientation is a placeholder (identity, never read).

Alignment
---------
The estimate's points in its own frame, ``x_k = p_S,k + R_S,k l``, are aligned onto ``y_k``
by weighted least squares over the positions (rotation metrics need an orientation the ground
truth does not have):

``none``: identity. ``se3``: rotation and translation, Umeyama (Kabsch) on ``(x_k, y_k)``.
``4dof``: translation and yaw (:func:`rtsgt.geometry.kabsch.kabsch_yaw`).
``sim3``: with a scale ``s`` the estimate's positions are scaled and the lever arm is not (it
is metric): ``p_P = s R p_S + t + R R_S l``, so

.. math::

    \min_{s, R, t} \sum_k w_k \| y_k - t - R (s\, p_{S,k} + R_{S,k} l) \|^2 ,

solved by alternating the two closed forms from the Umeyama scale of the points ``x_k``: for
a given ``s`` the rigid fit of ``z_k(s) = s p_S,k + R_S,k l`` onto ``y_k``, for a given ``R``
``s = sum w (R p0_k) . (y0_k - R a0_k) / sum w |p0_k|^2`` (``0``: centred by the weighted
means, ``a_k = R_S,k l``). Each step lowers the cost; the coupling through the lever arm is
weak (a lever arm of decimetres against a trajectory of metres), so a few steps reach a
relative change of the scale below :data:`SIM3_TOL`.
``scale``: ``R = I``, ``t = 0``, ``s = sum w (y - R_S l) . p_S / sum w |p_S|^2``.
``origin`` maps the first pose onto the first ground-truth pose: it needs an orientation,
and is refused.

``--weighted`` (``weighted=True``) makes the fit generalised least squares
(:func:`gls_alignment`): each error weighted by the inverse of its full covariance (the
ground truth's, plus the estimate's point's as the unweighted fit maps it), by Gauss-Newton
from the unweighted fit. A total station's covariance is thin across the line of sight and
long along it (and along the velocity, the clock); an unweighted fit (evo's) moves the points
by as much in every direction and so inflates the NEES after it (on 40 simulated
single-prism deployments an exact estimate's NEES / dof is 1.09 without alignment, 4.1 after
an unweighted SE(3) fit, 0.97 after a weighted one, docs/evaluation.md): use the weighted fit
for the NEES; the split verdict projects the alignment out either way.

The alignment is then applied to the sensor poses (positions ``s R p + t``, rotations
``R R_S``, the 6x6 covariance mapped, :meth:`~rtsgt.evaluation.align.Alignment.apply`), and
the lever arm to the aligned poses.

Errors and their covariance
---------------------------
``e_k = p_P,k - y_k`` (world frame). **APE**: ``|e_k|``, evo's statistics. **RPE**: pairs
``(i, j)`` selected as evo (:func:`~rtsgt.evaluation.metrics.rpe_pairs`, from the aligned
estimate's points or the ground truth's), error ``|e_j - e_i|``: the difference of the two
displacements in the world frame. evo's RPE translation expresses it in the frame of pose
``i``; without the ground truth's orientation it cannot, and the two agree in norm when the
estimate's rotations are exact (the estimate's rotation error enters ``e`` through the lever
arm instead).

**NEES**: ``e_k^T S_k^-1 e_k`` with ``S_k = Sigma_y,k + J_k Sigma_S,k J_k^T`` (the estimate's
6x6 covariance, mapped into the world frame by the alignment, through the lever-arm Jacobian
``J_k = [I, -[R_S,k l]x]``), chi-square(3) under consistency, tested as the pose NEES
(:func:`~rtsgt.evaluation.metrics.nees_consistency`). **Relative NEES**: ``e_j - e_i`` against
``P_i + P_j - C_ij - C_ij^T``, the ground truth's covariance of its displacement (a ground
truth that gives its cross-covariances, :class:`PairCovariancePositionGroundTruth`; else the
two positions taken as independent). **Shared errors**: a ground truth that gives its error
split (:class:`SharedPositionGroundTruth`: the varying covariance and the shared factor of the
station's clock, atmosphere and calibration, :func:`rtsgt.shared.prism_shared_factor`) gets
the split verdict of the poses (:func:`~rtsgt.evaluation.metrics.shared_error_test`, position
rows; what the alignment absorbs projected out).

**An estimated lever arm** (``lever_arm_cov``, the estimator of the sensor mounting, issue 14
item 1) is one error for the whole trajectory: its covariance ``Sigma_l`` enters ``S_k`` as
``R_S,k Sigma_l R_S,k^T`` and the split verdict as a shared factor ``R_S,k A_l``
(:func:`~rtsgt.evaluation.lever_arm.lever_arm_factor`), beside the ground truth's.

Rotation metrics are not reported: the result's rotation statistics are ``null`` and its
``rotation`` entry says why.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import ConvergenceError, GeometryError, InputError
from rtsgt.evaluation.align import MIN_POSES, Alignment, align_yaw, aligned_count, umeyama
from rtsgt.evaluation.associate import Association, GroundTruthSample, associate
from rtsgt.evaluation.drift import (
    POSITION_DRIFT_DEFINITION,
    ROTATION_DRIFT_NOT_ESTIMABLE,
    Drift,
    drift_metrics,
)
from rtsgt.evaluation.evaluator import _check_trajectory, _nees, _no_pair_reason, _warn_gaps
from rtsgt.evaluation.lever_arm import (
    LeverArmPoints,
    lever_arm_factor,
    lever_arm_points,
    parse_lever_arm,
    point_covariance,
)
from rtsgt.evaluation.metrics import (
    NeesResult,
    alignment_sensitivity,
    noise_floor,
    remove_floor,
    rpe_pairs,
    shared_error_test,
)
from rtsgt.evaluation.options import EvaluationOptions
from rtsgt.evaluation.result import ErrorStatistics, NeesSection, NoiseFloor, error_sections
from rtsgt.geometry.so3 import exp_so3, hat
from rtsgt.types import PoseTrajectory, PositionTrajectory

__all__ = [
    "POSITION_ALIGN_METHODS",
    "ROTATION_NOT_REPORTED",
    "PairCovariancePositionGroundTruth",
    "PositionErrors",
    "PositionEvaluationResult",
    "PositionSample",
    "PositionSplit",
    "SharedPositionGroundTruth",
    "ValidatedPositionGroundTruth",
    "align_points",
    "evaluate_positions",
]

#: Alignments of a position-only evaluation (``origin`` needs an orientation).
POSITION_ALIGN_METHODS = ("none", "se3", "sim3", "4dof", "scale")

#: What the result says about rotations (``rotation`` of the JSON).
ROTATION_NOT_REPORTED = ("not reported: the ground truth has positions only; the estimate's "
                         "rotation enters the position errors through the lever arm")

_IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


@dataclass(frozen=True)
class PositionSample:
    """A continuous position ground truth at query times (one entry per time).

    Attributes
    ----------
    t : ndarray, shape (M,)
        Query times, s (ground-truth clock).
    position : ndarray, shape (M, 3)
        m, world frame; NaN where none was computed.
    cov : ndarray, shape (M, 3, 3) or None
    reason : ndarray of str, shape (M,)
        ``""`` where valid, else why not (the codes of :mod:`rtsgt.evaluation.groundtruth`).
    nearest_dt : ndarray, shape (M,)
        Distance to the nearest measurement, s (NaN where unknown).
    """

    t: np.ndarray
    position: np.ndarray
    cov: np.ndarray | None
    reason: np.ndarray
    nearest_dt: np.ndarray


@dataclass(frozen=True)
class PositionSplit:
    """A position ground truth's error split at some times: ``e_i = nu_i + F_i theta``.

    Attributes
    ----------
    varying_cov : ndarray, shape (N, 3, 3)
        ``Cov(nu_i)``, m^2 (the GP posterior).
    factor : ndarray, shape (N, 3, k)
        ``F_i``, m per unit of the whitened shared parameters ``theta ~ N(0, I_k)``.
    names : tuple of str
        The shared parameters.
    """

    varying_cov: np.ndarray
    factor: np.ndarray
    names: tuple[str, ...]


@runtime_checkable
class ValidatedPositionGroundTruth(Protocol):
    """A continuous-time position ground truth that says, per time, whether it can vouch for a
    position."""

    def query_positions(self, times: np.ndarray, *,
                        max_gap_s: float | None = None) -> PositionSample:
        """Positions at ``times`` with a drop reason per time."""
        ...


@runtime_checkable
class PairCovariancePositionGroundTruth(Protocol):
    """A position ground truth that computes the covariances of pairs of its positions."""

    def position_pair_covariances(
        self, tau_a: ArrayLike, tau_b: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``Cov(y(a))``, ``Cov(y(b))``, ``Cov(y(a), y(b))``, each (K, 3, 3)."""
        ...


@runtime_checkable
class SharedPositionGroundTruth(Protocol):
    """A position ground truth that splits its error into varying and shared parts."""

    def position_split(self, times: ArrayLike) -> PositionSplit | None:
        """The split at valid times (None when it has none)."""
        ...


PositionGroundTruth = PositionTrajectory | ValidatedPositionGroundTruth


def _embed(cov3: np.ndarray | None) -> np.ndarray | None:
    """(N, 3, 3) position covariances as (N, 6, 6) with a zero rotation block (never read)."""
    if cov3 is None:
        return None
    out = np.zeros(cov3.shape[:-2] + (6, 6))
    out[..., :3, :3] = cov3
    return out


class _AsPoses:
    """A continuous position ground truth seen by the association of poses: a placeholder
    orientation (identity, never read), the covariance in the position block."""

    def __init__(self, gt: ValidatedPositionGroundTruth):
        self._gt = gt
        self.span = getattr(gt, "span", None)
        self.info = getattr(gt, "info", None) or {}

    def query_poses(self, times: np.ndarray, *,
                    max_gap_s: float | None = None) -> GroundTruthSample:
        s = self._gt.query_positions(times, max_gap_s=max_gap_s)
        if not isinstance(s, PositionSample) or s.t.shape != np.shape(times):
            raise ValueError("Expected query_positions to return a PositionSample per time")
        quat = np.broadcast_to(_IDENTITY, (s.t.size, 4)).copy()
        return GroundTruthSample(s.t, s.position, quat, _embed(s.cov), s.reason, s.nearest_dt)


def _as_poses(gt: PositionGroundTruth):
    if isinstance(gt, PositionTrajectory):
        if not np.all(np.isfinite(gt.position)):
            k = int(np.argmax(~np.all(np.isfinite(gt.position), axis=1)))
            raise InputError(f"Expected finite ground-truth positions, got NaN or inf at "
                             f"position {k} (t = {gt.t[k]})")
        if gt.cov is not None and not np.all(np.isfinite(gt.cov)):
            raise InputError("Expected finite ground-truth covariances, got NaN or inf")
        quat = np.broadcast_to(_IDENTITY, (len(gt), 4))
        return PoseTrajectory(gt.t, gt.position, quat, _embed(gt.cov))
    if isinstance(gt, ValidatedPositionGroundTruth):
        return _AsPoses(gt)
    raise TypeError(f"Expected a PositionTrajectory or a ValidatedPositionGroundTruth, got "
                    f"{type(gt).__name__}")


# ------------------------------------------------------------------------------------------
# alignment
# ------------------------------------------------------------------------------------------


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
    """Fit the alignment of the estimate's points ``p_S + R_S l`` onto ground-truth positions
    (module docstring, section Alignment).

    Parameters
    ----------
    gt_position : array_like, shape (N, 3)
        Ground-truth positions at the estimate's times, world frame, m.
    est_position : array_like, shape (N, 3)
        Sensor positions in the estimate's frame.
    est_rotation : array_like, shape (N, 3, 3)
        Sensor orientations in the estimate's frame.
    lever_arm : array_like, shape (3,)
        The point in the sensor frame, m.
    method : str
        One of :data:`POSITION_ALIGN_METHODS`.
    n_align : int, optional
        Fit on the first ``n_align`` positions only.
    weights : array_like, shape (N,) or (N, 3, 3), optional
        Non-negative scalar weights (:func:`~rtsgt.evaluation.align.alignment_weights`), or
        information matrices ``W_k`` (the inverse covariances of the errors): generalised
        least squares, :func:`gls_alignment` from the unweighted fit.

    Returns
    -------
    Alignment
        To apply to the sensor poses (:meth:`~rtsgt.evaluation.align.Alignment.apply`).

    Raises
    ------
    InputError
        An unknown method (``origin`` among them), too few positions.
    GeometryError
        Degenerate geometry (collinear positions, no horizontal motion for ``4dof``).
    """
    if method not in POSITION_ALIGN_METHODS:
        extra = (" (origin maps the first pose onto the first ground-truth pose: a "
                 "position-only ground truth has no orientation)" if method == "origin" else "")
        raise InputError(f"Expected an alignment in {POSITION_ALIGN_METHODS} for a "
                         f"position-only ground truth, got {method!r}{extra}")
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
    r"""The alignment of ``start``'s method that minimises ``sum_k r_k^T W_k r_k``.

    ``r_k = y_k - (R u_k + t)``, ``u_k = s p_k + a_k`` (``a_k = R_S,k l``, estimate frame).
    Gauss-Newton from ``start`` (the unweighted fit), on a perturbation of the alignment about
    the aligned points' centroid ``c`` (so that coordinates far from the origin, e.g. UTM,
    keep the rotation and the translation apart): ``x -> exp([dphi]x) (x - c) + c + dt`` and
    ``s -> s + ds``, which moves the point ``x_k = R u_k + t`` by
    ``dt - [x_k - c]x dphi + ds R p_k``, restricted to the method's parameters (``se3``: ``dt,
    dphi``; ``4dof``: ``dt, dphi_z``; ``sim3``: and ``ds``; ``scale``: ``ds``, about the
    origin). With ``W_k``
    the inverse covariance of the errors the NEES after the alignment is what it leaves:
    the fit removes as much of it as its parameters can, not more in one direction than in
    another.

    Raises
    ------
    GeometryError
        The normal equations are singular (the method's parameters are not determined).
    ConvergenceError
        No convergence in :data:`GLS_MAX_ITER` steps.
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


# ------------------------------------------------------------------------------------------
# result
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PositionErrors:
    """APE or RPE of positions: per-position (per-pair) error norms and their statistics.

    Attributes
    ----------
    translation_m : ErrorStatistics
        evo's statistics, m.
    translation_error : ndarray, shape (K,)
        m.
    pairs : ndarray of int, shape (K, 2) or None
        RPE index pairs into the associated positions (None for the APE).
    """

    translation_m: ErrorStatistics
    translation_error: np.ndarray
    pairs: np.ndarray | None = None

    @classmethod
    def from_errors(cls, norms: np.ndarray, pairs: np.ndarray | None = None) -> PositionErrors:
        return cls(ErrorStatistics.from_errors(norms), norms, pairs)

    def to_dict(self) -> dict:
        return {"translation_m": self.translation_m.to_dict(), "rotation_deg": None,
                "full": None}


@dataclass(frozen=True)
class PositionEvaluationResult:
    """Everything :func:`evaluate_positions` computed.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Times of the associated estimate poses, s (estimate clock).
    gt : PositionTrajectory
        Ground truth at those times (world frame, with ``cov`` when available).
    est : PositionTrajectory
        The estimate's points ``p_S + R_S l`` after the alignment, with their covariance when
        the estimate has one (``J Sigma_S J^T``).
    est_poses : PoseTrajectory
        The associated sensor poses after the alignment (world frame, ``cov`` mapped).
    lever_arm : ndarray, shape (3,)
        ``l``, m, sensor frame.
    alignment : Alignment
    association : Association
    ape : PositionErrors
    rpe : PositionErrors or None
        None when no RPE pair exists (``rpe_absent_reason`` says why).
    nees : NeesSection
        ``position`` and ``relative_position``; ``pose`` and ``relative_pose`` are None.
    noise_floor : NoiseFloor
        Translation floors; the rotation ones are None.
    position_error : ndarray, shape (N, 3)
        ``p_P - y``, m, world frame.
    cov_error : ndarray, shape (N, 3, 3) or None
        ``S_k`` of the NEES.
    rpe_delta, rpe_delta_unit, rpe_all_pairs, rpe_absent_reason :
        As :class:`~rtsgt.evaluation.EvaluationResult`.
    lever_arm_source : str
        Where the lever arm comes from (``"given"``, ``"estimated"``).
    lever_arm_cov : ndarray, shape (3, 3) or None
        Its covariance, m^2, when known.
    drift : Drift or None
        Translational drift by segment length (:func:`drift_step`; rotational drift is not
        estimable).
    """

    t: np.ndarray
    gt: PositionTrajectory
    est: PositionTrajectory
    est_poses: PoseTrajectory
    lever_arm: np.ndarray
    alignment: Alignment
    association: Association
    ape: PositionErrors
    rpe: PositionErrors | None
    nees: NeesSection
    noise_floor: NoiseFloor
    position_error: np.ndarray
    cov_error: np.ndarray | None
    rpe_delta: float
    rpe_delta_unit: str
    rpe_all_pairs: bool
    rpe_absent_reason: str | None = None
    lever_arm_source: str = "given"
    lever_arm_cov: np.ndarray | None = None
    drift: Drift | None = None

    def to_dict(self) -> dict:
        """The JSON layout of ``rtsgt evaluate --json`` (that of
        :meth:`rtsgt.evaluation.EvaluationResult.to_dict`, rotations ``null``), with
        ``ground_truth`` ``"positions"``, ``lever_arm`` and ``rotation``."""
        ape, rpe = error_sections(self)
        rpe["definition"] = "|(p_est,j - p_est,i) - (p_gt,j - p_gt,i)|, world frame"
        return {
            "ground_truth": "positions",
            "rotation": ROTATION_NOT_REPORTED,
            "lever_arm": {"m": [float(v) for v in self.lever_arm], "frame": "sensor (estimate)",
                          "source": self.lever_arm_source,
                          "cov_m2": (None if self.lever_arm_cov is None
                                     else self.lever_arm_cov.tolist())},
            "ape": ape,
            "rpe": rpe,
            "nees": self.nees.to_dict(),
            "noise_floor": self.noise_floor.to_dict(),
            "alignment": self.alignment.to_dict(),
            "association": self.association.to_dict(),
            "drift": None if self.drift is None else self.drift.to_dict(),
        }


# ------------------------------------------------------------------------------------------
# the chain
# ------------------------------------------------------------------------------------------


def _relative_covariance(gt: PositionGroundTruth, g: PositionTrajectory, assoc: Association,
                         pairs: np.ndarray) -> tuple[np.ndarray, str]:
    """The ground truth's covariance of ``y_j - y_i`` for the RPE pairs, and where its
    correlations come from."""
    i, j = pairs[:, 0], pairs[:, 1]
    if isinstance(gt, PairCovariancePositionGroundTruth):
        P_i, P_j, C = gt.position_pair_covariances(g.t[i] + assoc.time_offset,
                                                   g.t[j] + assoc.time_offset)
        cov = P_i + P_j - C - np.swapaxes(C, 1, 2)
        why = "computed by the ground truth (shared systematic errors, GP correlation)"
    else:
        cov = g.cov[i] + g.cov[j]
        why = "assumed independent (no cross-covariance between ground-truth positions given)"
    return 0.5 * (cov + np.swapaxes(cov, 1, 2)), why


def _split_verdict(gt: PositionGroundTruth, g: PositionTrajectory, est_cov: np.ndarray | None,
                   assoc: Association, err: np.ndarray, absolute: NeesResult,
                   align: str, lever: tuple[np.ndarray, tuple[str, ...]] | None, *,
                   upper: bool) -> NeesResult:
    """The position NEES with the split verdict where the ground truth gives its split
    (:func:`~rtsgt.evaluation.metrics.shared_error_test` on the position rows); a lever arm
    known with a covariance adds its factor (``lever``: the factor and its names) to the
    shared ones. ``upper``: one-sided tests (an estimate without any covariance)."""
    if not isinstance(gt, SharedPositionGroundTruth):
        return absolute
    split = gt.position_split(g.t + assoc.time_offset)
    if split is None:
        return absolute
    D = split.varying_cov + (0.0 if est_cov is None else est_cov)
    K = alignment_sensitivity(g.position, align)
    factor, names = split.factor, split.names
    if lever is not None:
        factor = np.concatenate([factor, lever[0]], axis=2)
        names = (*names, *lever[1])
    try:
        verdict, _ = shared_error_test(err, D, factor, None if K is None else K[:, :3],
                                       names=names, upper=upper)
    except ValueError as exc:
        raise InputError(f"Cannot test the errors against the shared factor: {exc}") from None
    return dataclasses.replace(absolute, consistent=verdict.consistent, split=verdict)


def evaluate_positions(
    gt: PositionGroundTruth,
    est: PoseTrajectory,
    lever_arm: ArrayLike | str | None = None,
    options: EvaluationOptions | None = None,
    *,
    lever_arm_cov: ArrayLike | None = None,
    lever_arm_source: str = "given",
    gt_measurement_times: ArrayLike | None = None,
    **overrides,
) -> PositionEvaluationResult:
    """Evaluate an estimated sensor trajectory against a position-only ground truth.

    Parameters
    ----------
    gt : PositionTrajectory or ValidatedPositionGroundTruth
        The tracked point in the world frame: a discrete trajectory (interpolated at the
        estimate's times) or a continuous one (e.g.
        :class:`~rtsgt.evaluation.groundtruth.ContinuousPositionGroundTruth`). Covariances
        enable the NEES and the noise floor.
    est : PoseTrajectory
        Sensor poses in the estimate's frame, strictly increasing times; an optional 6x6
        ``cov`` enters the NEES through the lever arm.
    lever_arm : array_like or str, optional
        The tracked point in the sensor frame, m (``"x,y,z"`` accepted); zero when None.
    options : EvaluationOptions, optional
        Alignment (one of :data:`POSITION_ALIGN_METHODS`), RPE pairs, time offset, ``max_dt``.
    lever_arm_cov : array_like, shape (3, 3), optional
        The lever arm's covariance, m^2 (an estimated one): one error for the whole
        trajectory, in the NEES's covariance through ``J_lever`` and, with a ground truth that
        splits its error, a shared factor of the split verdict
        (:func:`~rtsgt.evaluation.lever_arm.lever_arm_factor`).
    lever_arm_source : str
        Where the lever arm comes from (``"given"``, ``"estimated"``), for the report.
    gt_measurement_times : array_like, optional
        Times supporting a discrete ground truth (default: its own times).
    **overrides
        Fields of :class:`EvaluationOptions` replacing those of ``options``.

    Returns
    -------
    PositionEvaluationResult

    Raises
    ------
    InputError
        No time overlap, too few associated positions, ``origin`` alignment, bad values.
    GeometryError
        Degenerate alignment geometry.
    """
    options = dataclasses.replace(EvaluationOptions() if options is None else options,
                                  **overrides)
    if options.align not in POSITION_ALIGN_METHODS:
        align_points(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(3),
                     method=options.align)  # raises, with the reason
    lever = parse_lever_arm(lever_arm)
    est = _check_trajectory(est, "estimate")
    as_poses = _as_poses(gt)
    assoc = associate(as_poses, est, time_offset=options.time_offset, max_dt=options.max_dt,
                      measurement_times=gt_measurement_times)
    a = assoc.gt
    name = gt.name if isinstance(gt, PositionTrajectory) else getattr(gt, "name", "")
    g = PositionTrajectory(a.t, a.position, None if a.cov is None else a.cov[:, :3, :3], name)
    e_raw = assoc.est
    alignment = align_step(g, e_raw, lever, options)
    e = alignment.apply(e_raw)
    pts: LeverArmPoints = lever_arm_points(e.position, e.rotation, lever)
    est_cov = point_covariance(pts, e.cov)
    lever_shared = None
    if lever_arm_cov is not None:
        lever_shared = _lever_arm_shared(pts, lever_arm_cov)
        marginal = lever_shared[0] @ np.swapaxes(lever_shared[0], 1, 2)
        est_cov = marginal if est_cov is None else est_cov + marginal
    err = pts.position - g.position
    ape = PositionErrors.from_errors(np.linalg.norm(err, axis=1))
    est_points = PositionTrajectory(e.t, pts.position, est_cov, "estimate")
    pairs, rpe, no_rpe = rpe_step(gt, g, est_points, err, assoc, options)
    S = None if g.cov is None else g.cov + (0.0 if est_cov is None else est_cov)
    if S is None:
        nees = NeesSection(None, None, None, None, "none: the ground truth has no covariance",
                           "not applicable")
        floor = NoiseFloor()
    else:
        absolute = _nees(err, S, 3, "position", g.t)
        absolute = _split_verdict(gt, g, point_covariance(pts, e.cov), assoc, err, absolute,
                                  options.align, lever_shared,
                                  upper=e.cov is None and lever_shared is None)
        nees, floor = nees_step(gt, g, est_cov, assoc, err, pairs, absolute, ape, rpe)
    return PositionEvaluationResult(
        t=assoc.est.t, gt=g, est=est_points, est_poses=e, lever_arm=lever, alignment=alignment,
        association=assoc, ape=ape, rpe=rpe, nees=nees, noise_floor=floor,
        position_error=err, cov_error=S, rpe_delta=float(options.delta),
        rpe_delta_unit=options.delta_unit, rpe_all_pairs=bool(options.all_pairs),
        rpe_absent_reason=no_rpe, lever_arm_source=lever_arm_source,
        lever_arm_cov=None if lever_arm_cov is None else np.asarray(lever_arm_cov, float),
        drift=drift_step(gt, g, err, assoc))


def drift_step(gt: PositionGroundTruth, g: PositionTrajectory, err: np.ndarray,
               assoc: Association) -> Drift:
    """Translational drift by segment length of the position errors ``err`` (N, 3)
    (:data:`~rtsgt.evaluation.drift.POSITION_DRIFT_DEFINITION`), with the ground truth's floor
    from the covariance of ``y_l - y_f`` over the segments when it has covariances."""

    def errors(first: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, None]:
        return np.linalg.norm(err[last] - err[first], axis=1), None

    def covariance(first: np.ndarray, last: np.ndarray) -> np.ndarray:
        return _relative_covariance(gt, g, assoc, np.column_stack([first, last]))[0]

    return drift_metrics(assoc.est.t, g.position, errors,
                         None if g.cov is None else covariance,
                         rotation=ROTATION_DRIFT_NOT_ESTIMABLE,
                         definition=POSITION_DRIFT_DEFINITION)


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


def _lever_arm_shared(pts: LeverArmPoints,
                      lever_arm_cov: ArrayLike) -> tuple[np.ndarray, tuple[str, ...]]:
    """The points' factor of an estimated lever arm's error and its parameter names."""
    C_l = np.asarray(lever_arm_cov, dtype=float)
    if C_l.shape != (3, 3) or not np.all(np.isfinite(C_l)):
        raise InputError(f"Expected a finite 3x3 lever arm covariance, got shape {C_l.shape}")
    return lever_arm_factor(pts, C_l), ("lever_arm_x", "lever_arm_y", "lever_arm_z")


def rpe_step(gt: PositionGroundTruth, g: PositionTrajectory, est_points: PositionTrajectory,
             err: np.ndarray, assoc: Association, options: EvaluationOptions
             ) -> tuple[np.ndarray, PositionErrors | None, str | None]:
    """evo's RPE pairs (from the aligned estimate's points, or the ground truth's), the
    errors ``|e_j - e_i|`` and, without a pair, why; pairs across a gap of a discrete ground
    truth are counted in a warning (:func:`rtsgt.evaluation.evaluator.evaluate`)."""
    source = g if options.pairs_from_reference else est_points
    pairs = rpe_pairs(source.position, source.t, options.delta, options.delta_unit,
                      all_pairs=options.all_pairs, rel_tol=options.rel_delta_tol)
    if pairs.shape[0] == 0:
        return pairs, None, _no_pair_reason(_pose_view(source), float(options.delta),
                                            options.delta_unit)
    d_err = err[pairs[:, 1]] - err[pairs[:, 0]]
    support = np.asarray(gt.t, float) if isinstance(gt, PositionTrajectory) else None
    _warn_gaps(assoc, pairs, support)
    return pairs, PositionErrors.from_errors(np.linalg.norm(d_err, axis=1), pairs), None


def nees_step(gt: PositionGroundTruth, g: PositionTrajectory, est_cov: np.ndarray | None,
              assoc: Association, err: np.ndarray, pairs: np.ndarray, absolute: NeesResult,
              ape: PositionErrors, rpe: PositionErrors | None) -> tuple[NeesSection, NoiseFloor]:
    """The NEES section (the absolute one given, the relative one of the RPE pairs) and the
    noise floor, for a ground truth with covariances."""
    what = "ground truth" + (" + estimate (through the lever arm)" if est_cov is not None
                             else "")
    f_t = noise_floor(g.cov)
    floor = NoiseFloor(f_t, remove_floor(ape.translation_m.rmse, f_t))
    if rpe is None:
        return NeesSection(absolute, None, None, None, what, "not applicable (no RPE pair)"), floor
    rel_cov, why = _relative_covariance(gt, g, assoc, pairs)
    rel = _nees(err[pairs[:, 1]] - err[pairs[:, 0]], rel_cov, 3, "relative position",
                g.t[pairs[:, 0]])
    nees = NeesSection(absolute, None, rel, None,
                       what + (" (relative: ground truth only)" if est_cov is not None else ""),
                       why)
    fr = noise_floor(rel_cov)
    floor = dataclasses.replace(
        floor, rpe_translation_m=fr,
        rpe_translation_rmse_floor_removed_m=remove_floor(rpe.translation_m.rmse, fr))
    return nees, floor


def _pose_view(traj: PositionTrajectory) -> PoseTrajectory:
    """Positions as poses with a placeholder orientation (for the messages of the RPE)."""
    return PoseTrajectory(traj.t, traj.position, np.broadcast_to(_IDENTITY, (len(traj), 4)))
