"""Rotations: exponential and logarithm maps of SO(3), quaternions (scalar-last).

Conventions (active rotations, ``quat_xyzw``): docs/conventions.md#quaternions.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation


def hat(phi: ArrayLike) -> np.ndarray:
    """Skew-symmetric ``[phi]x`` (..., 3, 3) of ``phi`` (..., 3): ``[phi]x v = phi x v``."""
    phi = np.asarray(phi, dtype=float)
    out = np.zeros(phi.shape[:-1] + (3, 3))
    out[..., 0, 1] = -phi[..., 2]
    out[..., 0, 2] = phi[..., 1]
    out[..., 1, 0] = phi[..., 2]
    out[..., 1, 2] = -phi[..., 0]
    out[..., 2, 0] = -phi[..., 1]
    out[..., 2, 1] = phi[..., 0]
    return out


def exp_so3(phi: ArrayLike) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors ``phi`` (..., 3), rad (Rodrigues)."""
    phi = np.asarray(phi, dtype=float)
    theta2 = np.einsum("...i,...i->...", phi, phi)
    theta = np.sqrt(theta2)
    small = theta2 < 1e-12
    safe = np.where(small, 1.0, theta)
    # A = sin(t)/t, B = (1 - cos(t))/t^2, with Taylor series near zero
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    k = hat(phi)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def log_so3(R: ArrayLike) -> np.ndarray:
    """Rotation vectors (..., 3), rad, angle in [0, pi], of rotation matrices ``R`` (..., 3, 3).
    """
    R = np.asarray(R, dtype=float)
    shape = R.shape[:-2]
    rv = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec()
    return rv.reshape(shape + (3,))


def matrix_to_quat_xyzw(R: ArrayLike) -> np.ndarray:
    """Rotation matrix to unit quaternion ``(qx, qy, qz, qw)`` with ``qw >= 0``."""
    R = np.asarray(R, dtype=float)
    shape = R.shape[:-2]
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q = np.where(q[:, 3:4] < 0, -q, q)
    return q.reshape(shape + (4,))


def quat_xyzw_to_matrix(quat_xyzw: ArrayLike) -> np.ndarray:
    """Unit quaternion ``(qx, qy, qz, qw)`` to rotation matrix (the input must be unit norm)."""
    q = np.asarray(quat_xyzw, dtype=float)
    shape = q.shape[:-1]
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(shape + (3, 3))
