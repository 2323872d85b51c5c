"""Batched SE(3): exponential, logarithm, adjoints and Jacobians, ``xi = (rho, phi)``.

Translation first, as the project's 6x6 covariances (docs/conventions.md). Formulas: Barfoot,
*State Estimation for Robotics*, 2nd ed., sections 8.1.5 to 8.1.9 (docs/joint.md#se3).
"""

from __future__ import annotations

import numpy as np

from rtsgt.geometry.so3 import exp_so3, hat, log_so3

#: Below this angle (rad) the SO(3) Jacobians use their Taylor series.
SMALL_ANGLE = 1e-3
#: Terms of the series of the SE(3) left Jacobian (exact to round-off for angles below pi).
JACOBIAN_TERMS = 24


def curly(xi: np.ndarray) -> np.ndarray:
    """``xi^curly = [[phi^, rho^], [0, phi^]]`` (..., 6, 6), the adjoint of the algebra."""
    xi = np.asarray(xi, dtype=float)
    out = np.zeros(xi.shape[:-1] + (6, 6))
    ph = hat(xi[..., 3:])
    out[..., :3, :3] = ph
    out[..., 3:, 3:] = ph
    out[..., :3, 3:] = hat(xi[..., :3])
    return out


def so3_left_jacobian(phi: np.ndarray, inverse: bool = False) -> np.ndarray:
    """SO(3) left Jacobian ``J(phi)`` (..., 3, 3) or its inverse (Barfoot eqs. 7.77, 7.79)."""
    phi = np.asarray(phi, dtype=float)
    th2 = np.einsum("...i,...i->...", phi, phi)
    th = np.sqrt(th2)
    small = th < SMALL_ANGLE
    s = np.where(small, 1.0, th)
    k = hat(phi)
    eye = np.broadcast_to(np.eye(3), k.shape)
    if inverse:
        # J^-1 = I - phi^/2 + (1/th^2 - (1 + cos th) / (2 th sin th)) phi^ phi^
        c = np.where(small, 1.0 / 12.0 + th2 / 720.0,
                     1.0 / (s * s) - (1.0 + np.cos(s)) / (2.0 * s * np.sin(s)))
        return eye - 0.5 * k + c[..., None, None] * (k @ k)
    # J = I + (1 - cos th)/th^2 phi^ + (th - sin th)/th^3 phi^ phi^
    b1 = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(s)) / (s * s))
    b2 = np.where(small, 1.0 / 6.0 - th2 / 120.0, (s - np.sin(s)) / s**3)
    return eye + b1[..., None, None] * k + b2[..., None, None] * (k @ k)


def exp_se3(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``exp(xi^)``: rotations (..., 3, 3) and translations ``J(phi) rho`` (..., 3)."""
    xi = np.asarray(xi, dtype=float)
    R = exp_so3(xi[..., 3:])
    t = np.einsum("...ij,...j->...i", so3_left_jacobian(xi[..., 3:]), xi[..., :3])
    return R, t


def log_se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``log(T)^v`` (..., 6) of ``T = (R, t)``: ``phi = log(R)``, ``rho = J(phi)^-1 t``."""
    phi = log_so3(R)
    rho = np.einsum("...ij,...j->...i", so3_left_jacobian(phi, inverse=True), t)
    return np.concatenate([rho, phi], axis=-1)


def adjoint(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``Ad(T) = [[R, t^ R], [0, R]]`` (..., 6, 6)."""
    R = np.asarray(R, dtype=float)
    out = np.zeros(R.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = hat(t) @ R
    return out


def left_jacobian(xi: np.ndarray) -> np.ndarray:
    """SE(3) left Jacobian ``J_l(xi) = sum_n (xi^curly)^n / (n + 1)!`` (..., 6, 6)
    (Barfoot eq. 7.95), summed by Horner's rule; ``J_r(xi) = J_l(-xi)``."""
    ad = curly(xi)
    eye = np.broadcast_to(np.eye(6), ad.shape)
    out = eye.copy()
    for n in range(JACOBIAN_TERMS, 0, -1):
        out = eye + (ad @ out) / (n + 1)
    return out


def jacobians_inv(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(J_l(xi)^-1, J_r(xi)^-1)`` (..., 6, 6)."""
    jl = left_jacobian(xi)
    jr = left_jacobian(-np.asarray(xi, dtype=float))
    return np.linalg.inv(jl), np.linalg.inv(jr)
