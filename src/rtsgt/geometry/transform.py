"""Rigid transforms with a 6x6 covariance, and their left perturbations.

The convention (``p_a = R_a_b p_b + t_a_b``; covariance of the left perturbation, world frame,
ordered x, y, z, rx, ry, rz) is docs/conventions.md#rigid-transforms-and-pose-covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.geometry.so3 import exp_so3, hat, log_so3


def perturbation(
    R_mean: ArrayLike, t_mean: ArrayLike, R: ArrayLike, t: ArrayLike
) -> np.ndarray:
    """Left perturbation ``xi = (t - t_mean, log(R R_mean^T))`` (..., 6), ordered (x, y, z, rx,
    ry, rz), of samples ``R`` (..., 3, 3), ``t`` (..., 3) about the mean (broadcast)."""
    R_mean = np.asarray(R_mean, dtype=float)
    R = np.asarray(R, dtype=float)
    dtheta = log_so3(R @ np.swapaxes(R_mean, -1, -2))
    dt = np.asarray(t, dtype=float) - np.asarray(t_mean, dtype=float)
    return np.concatenate([np.broadcast_to(dt, dtheta.shape), dtheta], axis=-1)


def perturb(
    R_mean: ArrayLike, t_mean: ArrayLike, xi: ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """Apply left perturbations ``xi`` (..., 6) to a mean transform; inverse of :func:`perturbation`."""
    xi = np.asarray(xi, dtype=float)
    R = exp_so3(xi[..., 3:]) @ np.asarray(R_mean, dtype=float)
    t = np.asarray(t_mean, dtype=float) + xi[..., :3]
    return R, t


def check_covariance(cov: ArrayLike, dim: int, name: str = "covariance", tol: float = 1e-9) -> np.ndarray:
    """``cov`` (..., dim, dim) as floats; raises ValueError ("Expected ..., got ...") unless of
    that shape, finite, symmetric and positive semi-definite to ``tol`` of its largest entry."""
    cov = np.asarray(cov, dtype=float)
    if cov.shape[-2:] != (dim, dim):
        raise ValueError(f"Expected {name} of shape (..., {dim}, {dim}), got {cov.shape}")
    if not np.all(np.isfinite(cov)):
        raise ValueError(f"Expected finite {name}, got NaN or inf")
    asym = np.abs(cov - np.swapaxes(cov, -1, -2))
    scale = np.maximum(np.abs(cov).max(axis=(-1, -2), keepdims=True), np.finfo(float).tiny)
    if np.any(asym > tol * scale + 1e-300):
        raise ValueError(f"Expected a symmetric {name}")
    eig = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    if np.any(eig < -tol * scale[..., 0]):
        raise ValueError(f"Expected a positive semi-definite {name}, got eigenvalue {eig.min():.3g}")
    return cov


@dataclass(frozen=True)
class RigidTransform:
    """A rigid transform ``T_a_b`` (maps frame b into frame a): ``rotation`` ``R_a_b`` (3, 3),
    ``translation`` ``t_a_b`` (3,), m; ``covariance`` (6, 6) of the left perturbation in frame
    a, (x, y, z, rx, ry, rz), m^2 / rad^2, or None; the frames' names ``frame_to`` (a) and
    ``frame_from`` (b); Monte Carlo samples (M, 3, 3) / (M, 3) when it was sampled (the prism
    Monte Carlo uses sample m for its sample m), docs/conventions.md#rigid-transforms-and-pose-covariance.
    """

    rotation: np.ndarray
    translation: np.ndarray
    covariance: np.ndarray | None = None
    frame_to: str = "a"
    frame_from: str = "b"
    samples_rotation: np.ndarray | None = None
    samples_translation: np.ndarray | None = None

    def __post_init__(self) -> None:
        R = np.asarray(self.rotation, dtype=float)
        t = np.asarray(self.translation, dtype=float)
        if R.shape != (3, 3):
            raise ValueError(f"Expected rotation of shape (3, 3), got {R.shape}")
        if t.shape != (3,):
            raise ValueError(f"Expected translation of shape (3,), got {t.shape}")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("Expected a proper rotation matrix (orthonormal, det +1)")
        object.__setattr__(self, "rotation", R)
        object.__setattr__(self, "translation", t)
        if self.covariance is not None:
            object.__setattr__(self, "covariance", check_covariance(self.covariance, 6))

    @classmethod
    def identity(cls, frame: str = "a") -> RigidTransform:
        """The identity transform of a frame onto itself, with zero covariance."""
        return cls(np.eye(3), np.zeros(3), np.zeros((6, 6)), frame, frame)

    @classmethod
    def from_matrix(cls, T: ArrayLike, covariance: ArrayLike | None = None, **kw) -> RigidTransform:
        """From a homogeneous 4x4 matrix."""
        T = np.asarray(T, dtype=float)
        if T.shape != (4, 4):
            raise ValueError(f"Expected a matrix of shape (4, 4), got {T.shape}")
        return cls(T[:3, :3], T[:3, 3], covariance, **kw)

    def as_matrix(self) -> np.ndarray:
        """Homogeneous 4x4 matrix."""
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = self.translation
        return T

    @property
    def yaw(self) -> float:
        """Rotation about z of frame a (rad), ``atan2(R[1,0], R[0,0])``."""
        return float(np.arctan2(self.rotation[1, 0], self.rotation[0, 0]))

    def apply(self, p_b: ArrayLike) -> np.ndarray:
        """Map points ``p_b`` (..., 3) into frame a."""
        return np.asarray(p_b, dtype=float) @ self.rotation.T + self.translation

    def inverse(self) -> RigidTransform:
        """``T_b_a``; the covariance is mapped to frame b by the adjoint (first order)."""
        Rt = self.rotation.T
        t_inv = -Rt @ self.translation
        cov = None
        if self.covariance is not None:
            # T_b_a' = (R^T exp(-dtheta), -R^T exp(-dtheta)(t + dt)); to first order
            # dtheta_b = -R^T dtheta_a and dt_b = -R^T dt_a - R^T [t]x dtheta_a
            J = np.zeros((6, 6))
            J[:3, :3] = -Rt
            J[:3, 3:] = -Rt @ hat(self.translation)
            J[3:, 3:] = -Rt
            cov = J @ self.covariance @ J.T
        return RigidTransform(Rt, t_inv, cov, self.frame_from, self.frame_to)
