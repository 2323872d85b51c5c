r"""Alignment of an estimated trajectory onto the ground truth before computing errors.

``p_world = s R p_est + t`` by (weighted) least squares on the associated positions, methods
:data:`ALIGN_METHODS` (none, se3, sim3, 4dof, scale, origin; Umeyama 1991 and its yaw-only
form); docs/evaluation.md#alignment.
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
    """A similarity ``p_world = s R p_est + t`` (``method``, ``rotation`` (3, 3), ``translation``
    (3,) m, ``scale``) fitted on ``n_used`` poses, ``weighted`` or not.
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
    r"""Weighted least-squares ``p_gt ~= s R p_est + t`` (Umeyama 1991) of points (N, 3) m with
    ``weights`` (N,) (None: uniform, evo's); returns R (3, 3), t (3,), s (1 unless ``with_scale``).
    GeometryError for fewer than 3 or collinear points (docs/evaluation.md#alignment).
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
    r"""Weighted least-squares ``p_gt ~= R_z(psi) p_est + t`` (x, y, z, yaw) of positions (N, 3) m,
    z along gravity in both frames: R (3, 3), t (3,) (:func:`rtsgt.geometry.kabsch.kabsch_yaw`).
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
    """Weights (N,) 1/m^2 ``1 / tr(Sigma_gt,pos + Sigma_est,pos)`` from the position blocks of
    ``cov_gt`` and ``cov_est`` ((N, 6, 6) or (N, 3, 3)).
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
    """Fit the :class:`Alignment` of ``est`` onto the associated ``gt`` (pose k with pose k).

    ``method`` in :data:`ALIGN_METHODS`; ``n_align``: the first poses only (evo); ``weighted``:
    :func:`alignment_weights` (needs ``gt.cov``). InputError on an unknown method, too few poses,
    weights without covariance; GeometryError on degenerate geometry.
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
