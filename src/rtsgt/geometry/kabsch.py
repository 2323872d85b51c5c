"""Least-squares rigid fit of point sets (Kabsch / Umeyama without scale), batched.

:func:`kabsch` fits a proper rotation and a translation (reflection guarded, Umeyama 1991,
eq. 39); :func:`kabsch_yaw` the rotation about z only (4 DOF), in closed form.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import GeometryError


def point_pairs(p_b: ArrayLike, q_a: ArrayLike, min_points: int = 0,
                what: str = "A rigid fit") -> tuple[np.ndarray, np.ndarray]:
    """The two point clouds of a fit as float arrays of the same shape (..., N, 3); raises
    ValueError for other shapes, :class:`GeometryError` (starting ``what``) under
    ``min_points`` points."""
    p = np.asarray(p_b, dtype=float)
    q = np.asarray(q_a, dtype=float)
    if p.shape != q.shape or p.shape[-1] != 3 or p.ndim < 2:
        raise ValueError(f"Expected two arrays of shape (..., N, 3), got {p.shape} and {q.shape}")
    n = p.shape[-2]
    if n < min_points:
        raise GeometryError(f"{what} needs at least {min_points} points, got {n}")
    return p, q


def _centred(p_b: ArrayLike, q_a: ArrayLike, weights: ArrayLike | None, min_points: int,
             what: str):
    """Validated inputs of a fit: normalised weights (..., N), the weighted centroids
    (..., 3) of both clouds and the centred clouds (..., N, 3)."""
    p, q = point_pairs(p_b, q_a, min_points, what)
    n = p.shape[-2]
    if weights is None:
        w = np.full(p.shape[:-1], 1.0 / n)
    else:
        w = np.broadcast_to(np.asarray(weights, dtype=float), p.shape[:-1])
        if np.any(w < 0) or not np.all(np.isfinite(w)):
            raise ValueError("Expected finite non-negative weights")
        w = w / w.sum(axis=-1, keepdims=True)
    pc = np.einsum("...i,...ij->...j", w, p)
    qc = np.einsum("...i,...ij->...j", w, q)
    return w, pc, qc, p - pc[..., None, :], q - qc[..., None, :]


def kabsch(
    p_b: ArrayLike, q_a: ArrayLike, weights: ArrayLike | None = None, *, check: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """``R_a_b`` (..., 3, 3), ``t_a_b`` (..., 3) with ``q_a ~= R_a_b p_b + t_a_b`` in least
    squares, for the same points ``p_b`` in frame b and ``q_a`` in frame a (..., N, 3),
    ``weights`` (..., N) non-negative (None: uniform); ``check``: raise :class:`GeometryError`
    for fewer than 3 points or (nearly) collinear ones."""
    w, pc, qc, p0, q0 = _centred(p_b, q_a, weights, 3, "A rigid fit")
    H = np.einsum("...i,...ij,...ik->...jk", w, p0, q0)  # cross-covariance, sum w p q^T
    U, S, Vt = np.linalg.svd(H)
    if check:
        # rank of the centred source cloud: the second singular value must not vanish
        scale = np.maximum(S[..., 0], np.finfo(float).tiny)
        if np.any(S[..., 1] / scale < 1e-10):
            raise GeometryError("Degenerate rigid fit: the points are (nearly) collinear")
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    t = qc - np.einsum("...ij,...j->...i", R, pc)
    return R, t


def kabsch_yaw(
    p_b: ArrayLike, q_a: ArrayLike, weights: ArrayLike | None = None, *, check: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`kabsch` with the rotation about z only (4 DOF; both frames share the
    vertical), in closed form; ``check``: raise :class:`GeometryError` for points without
    horizontal spread (the yaw undetermined)."""
    w, pc, qc, p0, q0 = _centred(p_b, q_a, weights, 2, "A 4-DOF fit")
    if check:
        spread = np.einsum("...i,...i->...", w, np.sum(p0[..., :2] ** 2, axis=-1))
        total = (np.einsum("...i,...i->...", w, np.sum(p0 ** 2, axis=-1))
                 + np.einsum("...i,...i->...", w, np.sum(q0 ** 2, axis=-1)))
        if np.any((spread <= 1e-20) | (spread <= 1e-12 * total)):
            raise GeometryError("Degenerate 4-DOF fit: the points have no horizontal spread, "
                                "so the yaw is not determined")
    num = np.einsum("...i,...i->...", w, p0[..., 0] * q0[..., 1] - p0[..., 1] * q0[..., 0])
    den = np.einsum("...i,...i->...", w, p0[..., 0] * q0[..., 0] + p0[..., 1] * q0[..., 1])
    psi = np.arctan2(num, den)
    c, s = np.cos(psi), np.sin(psi)
    R = np.zeros(psi.shape + (3, 3))
    R[..., 0, 0] = R[..., 1, 1] = c
    R[..., 0, 1] = -s
    R[..., 1, 0] = s
    R[..., 2, 2] = 1.0
    t = qc - np.einsum("...ij,...j->...i", R, pc)
    return R, t
