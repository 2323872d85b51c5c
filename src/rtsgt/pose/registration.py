r"""Batched least-squares rigid registration in closed form, and its first-order Jacobian.

``(R, t) = argmin sum_i |q_i - (R p_i + t)|^2`` for every batch element: Horn's quaternion
matrix, its largest eigenvalue by Newton on the characteristic polynomial (Theobald's QCP), the
rotation from the adjugate; elements the closed form cannot resolve to full precision are
re-solved by the SVD (:func:`rtsgt.geometry.kabsch`), so the result matches it to about 1e-10.
Method and Jacobian: docs/pose.md#registration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import GeometryError
from rtsgt.geometry.kabsch import kabsch, point_pairs
from rtsgt.geometry.so3 import hat, log_so3

#: Default threshold on the shape ratio (second / largest singular value of the centred points)
#: below which a point set is called (nearly) collinear. For a triangle of base b and height h
#: (apex above the middle of the base) the ratio is about 1.15 h / b, so 0.1 is a triangle
#: whose height is under ~9 % of its base (a smallest angle under ~10 degrees).
MIN_SHAPE = 0.1

#: Lower bound of the relative eigen-gap under which the closed form hands over to the SVD.
_MIN_RELGAP = 1e-3
#: Relative Newton step under which the largest eigenvalue is converged.
_NEWTON_TOL = 1e-12
_NEWTON_MAX_ITER = 50
#: Full-array Newton iterations before the iteration continues on the unconverged elements.
_NEWTON_FULL_ITER = 6
#: Default number of problems solved per chunk (keeps the working set in cache).
DEFAULT_CHUNK = 8192


@dataclass(frozen=True)
class RegistrationInfo:
    """Per-element diagnostics of :func:`register`: ``shape_body``, ``shape_world`` (...) the
    shape ratios (:func:`shape_ratio`); ``degenerate`` (...) their minimum below ``min_shape`` or
    non-finite input; ``rms`` (...) the root mean square residual, m; ``fallback`` (...) solved by
    the SVD."""

    shape_body: np.ndarray
    shape_world: np.ndarray
    degenerate: np.ndarray
    rms: np.ndarray
    fallback: np.ndarray


def shape_ratio(points: ArrayLike) -> np.ndarray:
    """``sigma_2 / sigma_1`` (...) of the two largest singular values of centred ``points``
    (..., N, 3): 0 for collinear points (the rotation about their line is undetermined), NaN where a
    point is not finite. For a triangle of base b and height h (apex above the middle of the base)
    it is ``2 h / (sqrt(3) b)`` while ``h <= b sqrt(3) / 2``."""
    x = np.asarray(points, dtype=float)
    if x.ndim < 2 or x.shape[-1] != 3:
        raise ValueError(f"Expected points of shape (..., N, 3), got {x.shape}")
    finite = np.all(np.isfinite(x), axis=(-1, -2))
    x = np.where(finite[..., None, None], x, 0.0)
    x0 = x - x.mean(axis=-2, keepdims=True)
    scatter = np.swapaxes(x0, -1, -2) @ x0
    lam = np.linalg.eigvalsh(scatter)  # ascending
    l1 = lam[..., 2]
    l2 = np.clip(lam[..., 1], 0.0, None)
    ratio = np.sqrt(l2 / np.where(l1 > 0, l1, 1.0))
    ratio = np.where(l1 > 0, ratio, 0.0)
    return np.where(finite, ratio, np.nan)


def _qcp_chunk(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form solve of a chunk: ``p, q`` (B, N, 3) -> R (B, 3, 3), t (B, 3), ok (B,)."""
    B, N, _ = p.shape
    # structure of arrays: row 3 i + k is component k of point i, the batch along the row;
    # copies, as they are centred in place (p may be a read-only broadcast view, and with
    # B = 1 the transpose is contiguous already, so ascontiguousarray would not copy)
    X = p.reshape(B, 3 * N).T.copy()
    Y = q.reshape(B, 3 * N).T.copy()
    inv_n = 1.0 / N
    pc = [X[k::3].sum(axis=0) * inv_n for k in range(3)]
    qc = [Y[k::3].sum(axis=0) * inv_n for k in range(3)]
    for k in range(3):
        X[k::3] -= pc[k]
        Y[k::3] -= qc[k]
    lam0 = 0.5 * (np.einsum("ij,ij->j", X, X) + np.einsum("ij,ij->j", Y, Y))
    k, c2, c1, c0 = _horn_matrix(X, Y)
    lam, converged = _largest_root(lam0, c2, c1, c0)
    out, relgap = _rotation_of_root(k, lam, lam0)
    for j in range(3):
        out[9 + j] = qc[j] - (out[3 * j] * pc[0] + out[3 * j + 1] * pc[1] + out[3 * j + 2] * pc[2])
    ok = converged & (relgap >= _MIN_RELGAP) & np.all(np.isfinite(out), axis=0)
    o = out.T
    return o[:, :9].reshape(B, 3, 3), o[:, 9:], ok


def _horn_matrix(X: np.ndarray, Y: np.ndarray):
    """Horn's (1987, eq. 41) symmetric 4x4 matrix of centred points ``X, Y`` (3N, B): its 10
    entries (k00, k01, k02, k03, k11, k12, k13, k22, k23, k33), quaternion order (w, x, y, z),
    and its characteristic polynomial ``l^4 + c2 l^2 + c1 l + c0`` (Theobald 2005, eqs. 9-12)."""
    # S_ab = sum_i p0_ia q0_ib
    (sxx, sxy, sxz), (syx, syy, syz), (szx, szy, szz) = (
        [np.einsum("ij,ij->j", X[a::3], Y[b::3]) for b in range(3)] for a in range(3)
    )
    k = (sxx + syy + szz, syz - szy, szx - sxz, sxy - syx, sxx - syy - szz, sxy + syx,
         szx + sxz, syy - sxx - szz, syz + szy, szz - sxx - syy)
    c2 = -2.0 * (sxx * sxx + sxy * sxy + sxz * sxz + syx * syx + syy * syy + syz * syz
                 + szx * szx + szy * szy + szz * szz)
    c1 = -8.0 * (sxx * (syy * szz - syz * szy) - sxy * (syx * szz - syz * szx)
                 + sxz * (syx * szy - syy * szx))
    return k, c2, c1, _det4_sym(*k)


def _largest_root(lam0, c2, c1, c0) -> tuple[np.ndarray, np.ndarray]:
    """The largest root (B,) of ``l^4 + c2 l^2 + c1 l + c0`` by Newton from the upper bound
    ``lam0`` (Theobald 2005, eq. 14), and whether it converged (B,)."""
    B = lam0.shape[0]
    lam = lam0.copy()
    active = np.arange(B)
    converged = np.zeros(B, dtype=bool)
    for it in range(_NEWTON_MAX_ITER):
        if it < _NEWTON_FULL_ITER:
            la, a2, a1, a0 = lam, c2, c1, c0
        else:
            la, a2, a1, a0 = lam[active], c2[active], c1[active], c0[active]
        l2 = la * la
        f = ((l2 + a2) * la + a1) * la + a0
        fp = (4.0 * l2 + 2.0 * a2) * la + a1
        with np.errstate(divide="ignore", invalid="ignore"):
            step = f / fp
        la = la - step
        done = np.abs(step) <= _NEWTON_TOL * np.abs(la)
        if it < _NEWTON_FULL_ITER:
            lam = la
            converged = done
            if it == _NEWTON_FULL_ITER - 1 or done.all():
                active = np.flatnonzero(~converged)
        else:
            lam[active] = la
            converged[active[done]] = True
            active = active[~done]
        if active.size == 0 and (it >= _NEWTON_FULL_ITER - 1 or converged.all()):
            break
    return lam, converged


def _rotation_of_root(k, lam, lam0) -> tuple[np.ndarray, np.ndarray]:
    """Rows 0-8 (of 12, (12, B)) the rotation matrix from the adjugate of ``K - lam I`` (for a
    simple eigenvalue ``adj = c v v^T``, Theobald 2005), and the relative eigen-gap's lower
    bound (B,)."""
    k00, a01, a02, a03, k11, a12, a13, k22, a23, k33 = k
    a00 = k00 - lam
    a11 = k11 - lam
    a22 = k22 - lam
    a33 = k33 - lam
    # 2x2 minors of rows (2, 3) and of rows (0, 1), columns (i, j)
    m01 = a02 * a13 - a12 * a03
    m02 = a02 * a23 - a22 * a03
    m03 = a02 * a33 - a23 * a03
    m12 = a12 * a23 - a22 * a13
    m13 = a12 * a33 - a23 * a13
    m23 = a22 * a33 - a23 * a23
    n01 = a00 * a11 - a01 * a01
    n02 = a00 * a12 - a01 * a02
    n03 = a00 * a13 - a01 * a03
    n12 = a01 * a12 - a11 * a02
    n13 = a01 * a13 - a11 * a03
    # cofactors (the adjugate of a symmetric matrix is symmetric)
    c_00 = a11 * m23 - a12 * m13 + a13 * m12
    c_01 = a12 * m03 - a01 * m23 - a13 * m02
    c_02 = a01 * m13 - a11 * m03 + a13 * m01
    c_03 = a11 * m02 - a01 * m12 - a12 * m01
    c_11 = a00 * m23 - a02 * m03 + a03 * m02
    c_12 = a01 * m03 - a00 * m13 - a03 * m01
    c_13 = a00 * m12 - a01 * m02 + a02 * m01
    c_22 = a33 * n01 - a13 * n03 + a03 * n13
    c_23 = a13 * n02 - a23 * n01 - a03 * n12
    c_33 = a22 * n01 - a12 * n02 + a02 * n12
    tr = c_00 + c_11 + c_22 + c_33
    # |tr adj(A)| = |prod_{j>1} (l_j - l_1)| <= gap (2 l0)^2: a lower bound of the relative gap
    with np.errstate(divide="ignore", invalid="ignore"):
        relgap = np.abs(tr) / (2.0 * lam0) ** 3
        inv = 1.0 / tr
    ww, xx, yy, zz = c_00 * inv, c_11 * inv, c_22 * inv, c_33 * inv
    wx, wy, wz = c_01 * inv, c_02 * inv, c_03 * inv
    xy, xz, yz = c_12 * inv, c_13 * inv, c_23 * inv
    out = np.empty((12, lam.shape[0]))
    # rotation matrix of the unit quaternion (w, x, y, z), written with v v^T
    out[0] = ww + xx - yy - zz
    out[1] = 2.0 * (xy - wz)
    out[2] = 2.0 * (xz + wy)
    out[3] = 2.0 * (xy + wz)
    out[4] = ww - xx + yy - zz
    out[5] = 2.0 * (yz - wx)
    out[6] = 2.0 * (xz - wy)
    out[7] = 2.0 * (yz + wx)
    out[8] = ww - xx - yy + zz
    return out, relgap


def _det4_sym(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33):
    """Determinant of symmetric 4x4 matrices from their 10 entries (Laplace by 2x2 minors)."""
    t01 = a00 * a11 - a01 * a01
    t02 = a00 * a12 - a02 * a01
    t03 = a00 * a13 - a03 * a01
    t12 = a01 * a12 - a02 * a11
    t13 = a01 * a13 - a03 * a11
    t23 = a02 * a13 - a03 * a12
    b01 = a02 * a13 - a12 * a03
    b02 = a02 * a23 - a22 * a03
    b03 = a02 * a33 - a23 * a03
    b12 = a12 * a23 - a22 * a13
    b13 = a12 * a33 - a23 * a13
    b23 = a22 * a33 - a23 * a23
    return t01 * b23 - t02 * b13 + t03 * b12 + t12 * b03 - t13 * b02 + t23 * b01


def _register_flat(
    p: np.ndarray, q: np.ndarray, chunk_size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve (B, N, 3) problems chunk by chunk; returns R, t and the SVD-fallback mask."""
    B = p.shape[0]
    R = np.empty((B, 3, 3))
    t = np.empty((B, 3))
    fallback = np.zeros(B, dtype=bool)
    for s in range(0, B, chunk_size):
        e = min(B, s + chunk_size)
        Rc, tc, ok = _qcp_chunk(p[s:e], q[s:e])
        R[s:e] = Rc
        t[s:e] = tc
        fallback[s:e] = ~ok
    bad = np.flatnonzero(fallback)
    if bad.size:
        pb, qb = p[bad], q[bad]
        finite = np.all(np.isfinite(pb), axis=(1, 2)) & np.all(np.isfinite(qb), axis=(1, 2))
        Rb = np.full((bad.size, 3, 3), np.nan)
        tb = np.full((bad.size, 3), np.nan)
        if finite.any():
            Rb[finite], tb[finite] = kabsch(pb[finite], qb[finite], check=False)
        R[bad] = Rb
        t[bad] = tb
    return R, t, fallback


def register(
    p_body: ArrayLike,
    q_world: ArrayLike,
    *,
    chunk_size: int | None = None,
    return_info: bool = False,
    min_shape: float = MIN_SHAPE,
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, RegistrationInfo]:
    """Least-squares rigid transform ``T_world_body`` mapping ``p_body`` onto ``q_world``.

    ``p_body``, ``q_world`` (..., N, 3) m, N >= 3; ``chunk_size``: problems solved at once
    (default :data:`DEFAULT_CHUNK`). Returns ``R`` (..., 3, 3), ``t`` (..., 3) with
    ``q ~= R p + t`` (NaN where a point is not finite; *a* minimiser for collinear points), and
    with ``return_info`` a :class:`RegistrationInfo` (``min_shape`` its degenerate threshold).
    Raises ValueError (shapes) or GeometryError (fewer than 3 points).
    """
    p, q = point_pairs(p_body, q_world, 3)
    n = p.shape[-2]
    chunk = DEFAULT_CHUNK if chunk_size is None else int(chunk_size)
    if chunk < 1:
        raise ValueError(f"Expected a positive chunk_size, got {chunk_size}")
    batch = p.shape[:-2]
    pf = p.reshape(-1, n, 3)
    qf = q.reshape(-1, n, 3)
    R, t, fallback = _register_flat(pf, qf, chunk)
    R = R.reshape(batch + (3, 3))
    t = t.reshape(batch + (3,))
    if not return_info:
        return R, t
    shape_b = shape_ratio(p)
    shape_w = shape_ratio(q)
    with np.errstate(invalid="ignore"):
        degenerate = ~(np.minimum(shape_b, shape_w) >= min_shape)
    res = q - (np.einsum("...ij,...nj->...ni", R, p) + t[..., None, :])
    rms = np.sqrt(np.mean(np.sum(res * res, axis=-1), axis=-1))
    info = RegistrationInfo(shape_b, shape_w, degenerate, rms, fallback.reshape(batch))
    return R, t, info


def registration_jacobian(
    p_body: ArrayLike, q_world: ArrayLike, R_world_body: ArrayLike | None = None
) -> tuple[np.ndarray, np.ndarray]:
    r"""``J_q``, ``J_p`` (..., 6, N, 3): ``d(dt, phi) / d q_i`` and ``/ d p_i`` of the fit of
    ``p_body`` onto ``q_world`` (..., N, 3), the left perturbation of :mod:`rtsgt.geometry.transform`
    (implicit function theorem, docs/pose.md#pose-covariance-engines). ``R_world_body`` (..., 3, 3):
    the fit's rotation if known. Raises GeometryError for collinear points.
    """
    p, q = point_pairs(p_body, q_world)
    n = p.shape[-2]
    R = register(p, q)[0] if R_world_body is None else np.asarray(R_world_body, dtype=float)
    p_mean = p.mean(axis=-2)
    p0 = p - p_mean[..., None, :]
    q0 = q - q.mean(axis=-2)[..., None, :]
    a = np.einsum("...ij,...nj->...ni", R, p0)
    M = np.einsum("...ni,...nj->...ij", a, q0)
    A = M - np.trace(M, axis1=-2, axis2=-1)[..., None, None] * np.eye(3)
    det = np.linalg.det(A)
    scale = np.maximum(np.abs(M).max(axis=(-1, -2)), np.finfo(float).tiny) ** 3
    if np.any(~(np.abs(det) > 1e-12 * scale)):
        raise GeometryError("Degenerate rigid fit: the points are (nearly) collinear")
    A_inv = np.linalg.inv(A)
    # phi = -A^-1 [a_i]x dq_i + A^-1 [q0_i]x R dp_i
    Jphi_q = -np.einsum("...ij,...njk->...ink", A_inv, hat(a))
    Jphi_p = np.einsum("...ij,...njk,...kl->...inl", A_inv, hat(q0), R)
    c_hat = hat(np.einsum("...ij,...j->...i", R, p_mean))
    eye_n = np.broadcast_to(np.eye(3)[:, None, :] / n, Jphi_q.shape)
    Jt_q = eye_n + np.einsum("...ij,...jnk->...ink", c_hat, Jphi_q)
    Rn = np.broadcast_to((R / n)[..., :, None, :], Jphi_p.shape)
    Jt_p = -Rn + np.einsum("...ij,...jnk->...ink", c_hat, Jphi_p)
    J_q = np.concatenate([Jt_q, Jphi_q], axis=-3)
    J_p = np.concatenate([Jt_p, Jphi_p], axis=-3)
    return J_q, J_p


def small_rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotations ``R`` (..., 3, 3): ``theta / sin(theta)`` times
    ``vee((R - R^T) / 2)``, well conditioned below 90 degrees; larger angles by
    :func:`rtsgt.geometry.so3.log_so3`."""
    v0 = 0.5 * (R[..., 2, 1] - R[..., 1, 2])
    v1 = 0.5 * (R[..., 0, 2] - R[..., 2, 0])
    v2 = 0.5 * (R[..., 1, 0] - R[..., 0, 1])
    c = 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0)
    s = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    theta = np.arctan2(s, c)
    small = s < 1e-8
    f = np.where(small, 1.0 + s * s / 6.0, theta / np.where(small, 1.0, s))
    out = np.stack([f * v0, f * v1, f * v2], axis=-1)
    big = c <= 0.0  # NaN stays NaN
    if np.any(big):
        out[big] = log_so3(R[big])
    return out
