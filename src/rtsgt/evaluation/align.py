r"""Alignment of an estimated trajectory onto the ground truth before computing errors.

An odometry or SLAM estimate lives in its own frame (and, for monocular methods, its own
scale). Before comparing it with the ground truth, its positions ``p_est`` are mapped into the
ground-truth (world) frame by a similarity transform::

    p_world = s R p_est + t          R_world_body = R R_est_body

estimated by least squares on the associated positions ``p_gt``:

.. math::

    (s, R, t) = \arg\min \sum_k w_k \| p_{gt,k} - (s R p_{est,k} + t) \|^2

Methods
-------
``none``
    Identity.
``se3``
    Rotation and translation (Umeyama 1991 without scale: Kabsch), as ``evo -a``.
``sim3``
    Rotation, translation and scale (Umeyama 1991), as ``evo -a -s``.
``4dof``
    Translation and a rotation about the world z axis only (yaw), for gravity-aligned
    odometry (VIO, wheel-inertial), where roll and pitch are observable and must not be
    "aligned away". Closed form below.
``scale``
    Scale only (``s`` of the Sim(3) fit, ``R = I``, ``t = 0``), as ``evo -s`` without ``-a``.
``origin``
    The first estimated pose is mapped onto the first ground-truth pose
    (``T = T_gt,0 T_est,0^-1``), as ``evo --align_origin``.

Weighted variant
----------------
With ``weighted=True`` each pose gets the scalar weight ``w_k = 1 / tr(Sigma_k)`` where
``Sigma_k`` is the 3x3 ground-truth position covariance (plus the estimate's own position
covariance when it has one; the trace is invariant under the rotation of the alignment). A
scalar weight keeps Umeyama's closed form exact (weighted means, weighted cross-covariance);
the fully anisotropic weighting ``sum e^T Sigma^-1 e`` has no closed form and is not used.
Poses whose ground truth is less certain then pull less on the alignment.

References
----------
S. Umeyama, "Least-squares estimation of transformation parameters between two point
patterns", IEEE TPAMI 13(4), 1991, eqs. 34-43 (weights enter through the means and the
cross-covariance). The ``4dof`` closed form is the 2-D Procrustes (Kabsch) solution in the
horizontal plane after removing the weighted centroids.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.choices import ALIGN_METHODS  # understood by align_trajectories
from rtsgt.errors import GeometryError, InputError
from rtsgt.geometry.kabsch import kabsch_yaw
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.types import PoseTrajectory

#: Minimum number of associated poses each method needs.
MIN_POSES = {"none": 0, "se3": 3, "sim3": 3, "4dof": 2, "scale": 3, "origin": 1}


@dataclass(frozen=True)
class Alignment:
    """A similarity transform ``p_world = s R p_est + t`` applied to the estimate.

    Attributes
    ----------
    method : str
        One of :data:`ALIGN_METHODS`.
    rotation : ndarray, shape (3, 3)
        ``R_world_est``.
    translation : ndarray, shape (3,)
        ``t_world_est``, m.
    scale : float
        ``s`` (1 unless the method is ``sim3`` or ``scale``).
    n_used : int
        Number of poses the transform was fitted on.
    weighted : bool
        Whether the covariance weights were used.
    """

    method: str
    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0
    n_used: int = 0
    weighted: bool = False

    def as_matrix(self) -> np.ndarray:
        """4x4 Sim(3) matrix ``[[s R, t], [0, 1]]`` (evo: ``alignment_transformation_sim3``)."""
        T = np.eye(4)
        T[:3, :3] = self.scale * self.rotation
        T[:3, 3] = self.translation
        return T

    @property
    def yaw(self) -> float:
        """Rotation about z, rad, ``atan2(R[1, 0], R[0, 0])``."""
        return float(np.arctan2(self.rotation[1, 0], self.rotation[0, 0]))

    def apply_pose(self, position: ArrayLike, rotation: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Map poses ``(t_est_body (N, 3), R_est_body (N, 3, 3))`` into the world frame."""
        p = np.asarray(position, dtype=float)
        R = np.asarray(rotation, dtype=float)
        return self.scale * p @ self.rotation.T + self.translation, self.rotation @ R

    def apply_covariance(self, cov: ArrayLike) -> np.ndarray:
        r"""Map 6x6 left-perturbation covariances (..., 6, 6) of the estimate into the world frame.

        With ``t' = s R t + t_a`` and ``R' = R R_est``, a perturbation ``(dt, dtheta)`` of the
        estimate becomes ``(s R dt, R dtheta)``, so ``cov' = J cov J^T`` with
        ``J = blockdiag(s R, R)``.
        """
        J = np.zeros((6, 6))
        J[:3, :3] = self.scale * self.rotation
        J[3:, 3:] = self.rotation
        return J @ np.asarray(cov, dtype=float) @ J.T

    def apply(self, traj: PoseTrajectory) -> PoseTrajectory:
        """A new trajectory: ``traj`` (estimate frame) mapped into the world frame."""
        p, R = self.apply_pose(traj.position, traj.rotation)
        cov = None if traj.cov is None else self.apply_covariance(traj.cov)
        return PoseTrajectory(traj.t, p, matrix_to_quat_xyzw(R), cov)

    def to_dict(self) -> dict:
        """JSON-ready summary."""
        return {
            "method": self.method,
            "weighted": self.weighted,
            "n_used": self.n_used,
            "scale": float(self.scale),
            "yaw_deg": float(np.degrees(self.yaw)),
            "matrix_sim3": self.as_matrix().tolist(),
        }


def _normalised_weights(n: int, weights: ArrayLike | None) -> np.ndarray:
    if weights is None:
        return np.full(n, 1.0 / n)
    w = np.asarray(weights, dtype=float)
    if w.shape != (n,):
        raise ValueError(f"Expected weights of shape ({n},), got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("Expected finite, non-negative weights with a positive sum")
    return w / w.sum()


def _check_points(p_est: ArrayLike, p_gt: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(p_est, dtype=float)
    y = np.asarray(p_gt, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape != y.shape:
        raise ValueError(f"Expected two arrays of shape (N, 3), got {x.shape} and {y.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError("Expected finite positions, got NaN or inf")
    return x, y


def umeyama(
    p_est: ArrayLike,
    p_gt: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    with_scale: bool = False,
) -> tuple[np.ndarray, np.ndarray, float]:
    r"""Weighted least-squares similarity ``p_gt ~= s R p_est + t`` (Umeyama 1991).

    Parameters
    ----------
    p_est : array_like, shape (N, 3)
        Points in the estimate frame, m.
    p_gt : array_like, shape (N, 3)
        The same points in the world frame, m.
    weights : array_like, shape (N,), optional
        Non-negative weights (uniform when None, which is evo's ``umeyama_alignment``).
    with_scale : bool
        Estimate ``s`` as well (Sim(3)); otherwise ``s = 1`` (SE(3)).

    Returns
    -------
    R : ndarray, shape (3, 3)
    t : ndarray, shape (3,)
    s : float

    Notes
    -----
    With normalised weights ``w`` (Umeyama eqs. 34-38, weights inserted in the sums)::

        mu_x = sum w x,  mu_y = sum w y,  sigma_x^2 = sum w |x - mu_x|^2
        Sigma_xy = sum w (y - mu_y)(x - mu_x)^T = U D V^T
        S = diag(1, 1, sign(det U det V))                (eq. 39/43, no reflection)
        R = U S V^T,  s = tr(D S) / sigma_x^2,  t = mu_y - s R mu_x    (eqs. 40-42)

    Raises
    ------
    GeometryError
        Fewer than 3 points, or points that are (nearly) collinear so that the rotation is not
        determined.
    """
    x, y = _check_points(p_est, p_gt)
    n = x.shape[0]
    if n < 3:
        raise GeometryError(f"An SE(3)/Sim(3) alignment needs at least 3 poses, got {n}")
    w = _normalised_weights(n, weights)
    mu_x = w @ x
    mu_y = w @ y
    x0 = x - mu_x
    y0 = y - mu_y
    # Umeyama eq. 36 (weighted variance of the source points)
    sigma_x2 = float(w @ np.einsum("ij,ij->i", x0, x0))
    # Umeyama eq. 38 (weighted cross-covariance)
    cov_xy = (y0 * w[:, None]).T @ x0
    U, D, Vt = np.linalg.svd(cov_xy)
    if D[0] <= 0 or D[1] / D[0] < 1e-10:
        raise GeometryError(
            "Degenerate alignment: the associated positions are (nearly) collinear, so the "
            "rotation is not determined; use --align 4dof, origin or none"
        )
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2, 2] = -1.0
    R = U @ S @ Vt  # Umeyama eq. 40
    s = float(np.trace(np.diag(D) @ S) / sigma_x2) if with_scale else 1.0  # eq. 42
    t = mu_y - s * R @ mu_x  # eq. 41
    return R, t, s


def align_yaw(
    p_est: ArrayLike, p_gt: ArrayLike, weights: ArrayLike | None = None
) -> tuple[np.ndarray, np.ndarray]:
    r"""Weighted least-squares ``p_gt ~= R_z(psi) p_est + t`` (4 DOF: x, y, z, yaw).

    Parameters
    ----------
    p_est, p_gt : array_like, shape (N, 3)
        Positions in the estimate and world frames, m. Both frames must have z along gravity.
    weights : array_like, shape (N,), optional

    Returns
    -------
    R : ndarray, shape (3, 3)
        A rotation about z.
    t : ndarray, shape (3,)

    Notes
    -----
    The closed form of :func:`rtsgt.geometry.kabsch.kabsch_yaw`.
    """
    x, y = _check_points(p_est, p_gt)
    n = x.shape[0]
    if n < 2:
        raise GeometryError(f"A 4-DOF alignment needs at least 2 poses, got {n}")
    try:
        return kabsch_yaw(x, y, _normalised_weights(n, weights))
    except GeometryError:
        raise GeometryError(
            "Degenerate 4-DOF alignment: the estimate has no horizontal motion, so the yaw is "
            "not determined"
        ) from None


def alignment_weights(cov_gt: ArrayLike, cov_est: ArrayLike | None = None) -> np.ndarray:
    """Scalar weights ``1 / tr(Sigma_gt,pos + Sigma_est,pos)`` for a weighted alignment.

    Parameters
    ----------
    cov_gt : array_like, shape (N, 6, 6) or (N, 3, 3)
        Ground-truth covariance; its position block (top-left 3x3, m^2) is used.
    cov_est : array_like, shape (N, 6, 6) or (N, 3, 3), optional
        The estimate's own covariance (its trace is frame independent).

    Returns
    -------
    ndarray, shape (N,)
        Weights, 1/m^2 (unnormalised).
    """
    tr = np.trace(np.asarray(cov_gt, dtype=float)[:, :3, :3], axis1=1, axis2=2)
    if cov_est is not None:
        tr = tr + np.trace(np.asarray(cov_est, dtype=float)[:, :3, :3], axis1=1, axis2=2)
    if not np.all(np.isfinite(tr)) or np.any(tr <= 0):
        k = int(np.argmax(~np.isfinite(tr) | (tr <= 0)))
        raise ValueError(
            f"Expected positive finite position covariance traces for a weighted alignment, "
            f"got {tr[k]:.3g} at pose {k}"
        )
    return 1.0 / tr


def aligned_count(n: int, n_align: int | None) -> int:
    """How many of ``n`` associated poses an alignment uses: the first ``n_align`` (all when
    None)."""
    if n_align is None:
        return n
    if int(n_align) != n_align or n_align < 1:
        raise InputError(f"Expected a positive integer n_align, got {n_align}")
    return min(int(n_align), n)


def align_trajectories(
    gt: PoseTrajectory,
    est: PoseTrajectory,
    *,
    method: str = "se3",
    n_align: int | None = None,
    weighted: bool = False,
) -> Alignment:
    """Fit the alignment of ``est`` onto ``gt`` (already associated: pose k with pose k).

    Parameters
    ----------
    gt : PoseTrajectory
        Ground truth at the estimate's times (world frame); needs ``cov`` when ``weighted``.
    est : PoseTrajectory
        Estimate, same length as ``gt``.
    method : str
        One of :data:`ALIGN_METHODS`.
    n_align : int, optional
        Fit on the first ``n_align`` poses only (evo's ``--n_to_align``); all when None.
    weighted : bool
        Use the scalar covariance weights of :func:`alignment_weights`.

    Returns
    -------
    Alignment

    Raises
    ------
    InputError
        Unknown method, too few poses for the method, weights without a covariance.
    GeometryError
        Degenerate geometry (collinear positions, no horizontal motion for 4dof).
    """
    if method not in ALIGN_METHODS:
        raise InputError(f"Expected an alignment in {ALIGN_METHODS}, got {method!r}")
    if len(gt) != len(est):
        raise ValueError(
            f"Expected associated trajectories of equal length, got {len(gt)}, {len(est)}"
        )
    n = aligned_count(len(est), n_align)
    if method == "none":
        return Alignment("none", np.eye(3), np.zeros(3), 1.0, 0, False)
    if n < MIN_POSES[method]:
        raise InputError(
            f"Alignment {method!r} needs at least {MIN_POSES[method]} associated poses, got {n}"
            + (" (n_align)" if n_align is not None and n_align < len(est) else "")
            + "; check the time overlap, --max-dt and --time-offset"
        )
    if method == "origin":
        R0 = gt.rotation[0] @ est.rotation[0].T
        return Alignment("origin", R0, gt.position[0] - R0 @ est.position[0], 1.0, 1, False)
    w = None
    if weighted:
        if gt.cov is None:
            raise InputError("A weighted alignment needs a ground truth with covariances")
        w = alignment_weights(gt.cov[:n], None if est.cov is None else est.cov[:n])
    x, y = est.position[:n], gt.position[:n]
    if method == "4dof":
        R, t = align_yaw(x, y, w)
        return Alignment("4dof", R, t, 1.0, n, weighted)
    R, t, s = umeyama(x, y, w, with_scale=method in ("sim3", "scale"))
    if method == "scale":
        return Alignment("scale", np.eye(3), np.zeros(3), s, n, weighted)
    return Alignment(method, R, t, s, n, weighted)
