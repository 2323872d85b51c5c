r"""Fast batched least-squares rigid registration, and its analytic first-order Jacobian.

The problem, for every batch element (no scale, no weights)::

    (R, t) = argmin_{R in SO(3), t}  sum_i || q_i - (R p_i + t) ||^2

is solved in closed form by Horn's quaternion method (Horn 1987, "Closed-form solution of
absolute orientation using unit quaternions", JOSA A 4(4)): with the centred points
``p0_i = p_i - mean(p)``, ``q0_i = q_i - mean(q)`` and ``S = sum_i p0_i q0_i^T``, the optimal
rotation is the unit quaternion that is the eigenvector of the largest eigenvalue of the
symmetric, traceless 4x4 matrix ``K(S)`` (Horn eq. 41). Instead of a generic eigen-solver,
the largest eigenvalue is found as the largest root of the characteristic polynomial
``P(l) = l^4 + c2 l^2 + c1 l + c0`` by Newton's method started at its upper bound
``(sum |p0|^2 + sum |q0|^2) / 2`` (Theobald 2005, "Rapid calculation of RMSDs using a
quaternion-based characteristic polynomial", Acta Cryst. A61, eqs. 8-14: the QCP method).
Started above the largest root of a polynomial whose roots are all real, Newton converges
monotonically. The eigenvector then follows from the adjugate of ``A = K - l I``: for a simple
eigenvalue ``adj(A) = c v v^T`` (Theobald's appendix), so ``adj(A) / tr(adj(A)) = v v^T`` for
the unit eigenvector ``v``, and the rotation matrix, which is quadratic in the quaternion, is a
linear function of ``v v^T``: no square root, no sign choice, no column selection, and it
stays exact through 180 degree rotations.

Everything is computed on structure-of-arrays component vectors (one numpy array per scalar,
the batch along the array), about 300 elementwise operations per solve, in chunks that stay
in cache. Elements the closed form cannot resolve to full precision (the relative eigen-gap
bound ``|tr adj(A)| / (2 l0)^3`` below 1e-3, Newton not converged, non-finite values) are
re-solved with the SVD of :func:`rtsgt.geometry.kabsch`, so the result matches the SVD to
about 1e-10 everywhere; elements with non-finite input give NaN.

The Jacobian of the solution (:func:`registration_jacobian`) is derived with the implicit
function theorem from the optimality condition ``sum_i (R p0_i) x q0_i = 0``; see its
docstring.
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
    """Per-element diagnostics of :func:`register`.

    Attributes
    ----------
    shape_body, shape_world : ndarray, shape (...)
        Shape ratio ``sigma_2 / sigma_1`` of the centred points (see :func:`shape_ratio`):
        0 for collinear points, about 0.7 for the paper's prism triangle.
    degenerate : ndarray of bool, shape (...)
        ``min(shape_body, shape_world) < min_shape``, or non-finite input: the rotation is not
        (well) determined by the points.
    rms : ndarray, shape (...)
        Root mean square residual ``sqrt(mean_i |q_i - R p_i - t|^2)``, m.
    fallback : ndarray of bool, shape (...)
        The element was solved by the SVD because the closed form was ill-conditioned.
    """

    shape_body: np.ndarray
    shape_world: np.ndarray
    degenerate: np.ndarray
    rms: np.ndarray
    fallback: np.ndarray


def shape_ratio(points: ArrayLike) -> np.ndarray:
    """Ratio ``sigma_2 / sigma_1`` of the two largest singular values of centred points.

    It measures how far a point set is from a line: 0 for collinear points, 1 for a set that is
    as wide as it is long in its plane (for a triangle of base b and height h with the apex
    above the middle of the base, ``sigma_2 / sigma_1 = 2 h / (sqrt(3) b)`` while
    ``h <= b sqrt(3) / 2``).
    The rotation of a rigid fit about the set's long axis is determined to about
    ``sigma_noise / (sigma_2 sqrt(N))``, so a small ratio means an ill-determined pose.

    Parameters
    ----------
    points : array_like, shape (..., N, 3)

    Returns
    -------
    ndarray, shape (...)
        NaN where a point is not finite; 0 where all points coincide.
    """
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
    ga = np.einsum("ij,ij->j", X, X)
    gb = np.einsum("ij,ij->j", Y, Y)
    # S_ab = sum_i p0_ia q0_ib
    (sxx, sxy, sxz), (syx, syy, syz), (szx, szy, szz) = (
        [np.einsum("ij,ij->j", X[a::3], Y[b::3]) for b in range(3)] for a in range(3)
    )
    # Horn (1987) eq. 41: the symmetric traceless 4x4 matrix, quaternion order (w, x, y, z)
    k00 = sxx + syy + szz
    k01 = syz - szy
    k02 = szx - sxz
    k03 = sxy - syx
    k11 = sxx - syy - szz
    k12 = sxy + syx
    k13 = szx + sxz
    k22 = syy - sxx - szz
    k23 = syz + szy
    k33 = szz - sxx - syy
    # characteristic polynomial l^4 + c2 l^2 + c1 l + c0 (Theobald 2005, eqs. 9-12)
    c2 = -2.0 * (sxx * sxx + sxy * sxy + sxz * sxz + syx * syx + syy * syy + syz * syz
                 + szx * szx + szy * szy + szz * szz)
    c1 = -8.0 * (sxx * (syy * szz - syz * szy) - sxy * (syx * szz - syz * szx)
                 + sxz * (syx * szy - syy * szx))
    c0 = _det4_sym(k00, k01, k02, k03, k11, k12, k13, k22, k23, k33)
    # Newton from the upper bound (ga + gb) / 2 >= l_max (Theobald 2005, eq. 14)
    lam0 = 0.5 * (ga + gb)
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
    # adjugate of A = K - lam I: for a simple eigenvalue adj(A) = c v v^T (Theobald 2005)
    a00 = k00 - lam
    a11 = k11 - lam
    a22 = k22 - lam
    a33 = k33 - lam
    a01, a02, a03, a12, a13, a23 = k01, k02, k03, k12, k13, k23
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
    out = np.empty((12, B))
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
    for k in range(3):
        out[9 + k] = qc[k] - (out[3 * k] * pc[0] + out[3 * k + 1] * pc[1] + out[3 * k + 2] * pc[2])
    ok = converged & (relgap >= _MIN_RELGAP) & np.all(np.isfinite(out), axis=0)
    o = out.T
    return o[:, :9].reshape(B, 3, 3), o[:, 9:], ok


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

    Closed form (Horn's quaternion matrix, largest eigenvalue by QCP Newton iterations,
    eigenvector from the adjugate; see the module docstring), vectorised over the batch and
    processed in chunks; ill-conditioned elements are re-solved by the SVD. Identical to
    :func:`rtsgt.geometry.kabsch` (to ~1e-10) and over 10 times faster for 3 points.

    Parameters
    ----------
    p_body : array_like, shape (..., N, 3)
        Points in the body frame (m), N >= 3.
    q_world : array_like, shape (..., N, 3)
        The same points in the world frame (m).
    chunk_size : int, optional
        Problems solved at once (default :data:`DEFAULT_CHUNK`); bounds the memory.
    return_info : bool
        Also return a :class:`RegistrationInfo` (shape ratios, degenerate flags, residuals).
    min_shape : float
        Threshold of :attr:`RegistrationInfo.degenerate` on :func:`shape_ratio`.

    Returns
    -------
    R_world_body : ndarray, shape (..., 3, 3)
        Proper rotation. For degenerate (collinear) input it is *a* minimiser, not unique:
        check ``info.degenerate``. NaN where an input point is not finite.
    t_world_body : ndarray, shape (..., 3)
        With ``q_world ~= R_world_body @ p_body + t_world_body``.
    info : RegistrationInfo
        Only with ``return_info=True``.

    Raises
    ------
    ValueError
        Shapes differ or are not (..., N, 3).
    GeometryError
        Fewer than 3 points.
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
    r"""First-order sensitivity of the least-squares rigid fit to its input points.

    Derivation (implicit function theorem). With ``a_i = R p0_i`` and the centred points
    ``p0_i = p_i - mean(p)``, ``q0_i = q_i - mean(q)``, the rotation minimising
    ``sum_i |q0_i - R p0_i|^2`` makes the gradient with respect to a left rotation vanish:

    .. math:: g = \sum_i a_i \times q_{0,i} = 0 .

    Perturb the inputs (``dq_i``, ``dp_i``) and the rotation (``R -> exp([phi]x) R``, so
    ``da_i = phi x a_i + R dp0_i``). Using ``(phi x a) x q = (a q^T - (a.q) I) phi``:

    .. math::

        A\,\phi = -\sum_i \left([a_i]_\times\, dq_i - [q_{0,i}]_\times R\, dp_i\right),\qquad
        A = \sum_i a_i q_{0,i}^T - \Big(\sum_i a_i\cdot q_{0,i}\Big) I

    (the centring of ``dq`` and ``dp`` drops out because ``sum a_i = sum q0_i = 0``). ``A`` is
    symmetric at the optimum and invertible unless the points are collinear. The translation
    ``t = mean(q) - R mean(p)`` gives, with ``c = R mean(p)``,

    .. math:: dt = \frac1N \sum_i dq_i - \frac1N R \sum_i dp_i + [c]_\times \phi .

    ``(dt, phi)`` is the left perturbation of :mod:`rtsgt.geometry.transform` (world frame,
    ordered x, y, z, rx, ry, rz).

    Parameters
    ----------
    p_body, q_world : array_like, shape (..., N, 3)
        The points of the fit (m).
    R_world_body : array_like, shape (..., 3, 3), optional
        The optimal rotation, if already known (computed with :func:`register` otherwise).

    Returns
    -------
    J_q : ndarray, shape (..., 6, N, 3)
        ``d(dt, phi) / d q_i``.
    J_p : ndarray, shape (..., 6, N, 3)
        ``d(dt, phi) / d p_i``.

    Raises
    ------
    GeometryError
        If ``A`` is singular (collinear points) for some element.
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
    """Rotation vector of rotations (..., 3, 3) -> (..., 3), fast for angles below 90 deg.

    ``phi = theta / sin(theta) * vee((R - R^T) / 2)`` with ``theta = atan2(|vee|, (tr R - 1)/2)``
    (exact, well conditioned below 90 degrees); larger angles use
    :func:`rtsgt.geometry.so3.log_so3`.
    """
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
