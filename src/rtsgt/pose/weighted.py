r"""Weighted (generalised least squares) rigid registration, batched, and its Jacobian.

``(R, t) = argmin e^T W e``, ``e = q - (R r + t)`` stacked (3n), ``W`` the inverse of the
residual's covariance at the closed-form rotation, held fixed (:func:`gls_weights`). Newton's
method on SO(3) with the translation eliminated, safeguarded (:func:`refine_batches`); chord
steps for the Monte Carlo samples (:func:`refine_samples`); the Jacobian by the implicit function
theorem (:func:`weighted_registration_jacobian`). Vectorised over poses and the samples of a
pose. Derivations: docs/pose.md#weighted-registration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import GeometryError
from rtsgt.geometry.kabsch import point_pairs
from rtsgt.geometry.so3 import hat
from rtsgt.pose.registration import register

__all__ = ["GLS_MAX_ITER", "GLS_TOL", "WeightedInfo", "gls_weights", "newton_inverse_at",
           "refine_batches", "refine_samples", "register_weighted", "weighted_registration_jacobian"]

#: Rotation step (rad) under which the Newton iteration of a batch has converged (the error
#: left is then below 1e-10 rad, tests/test_pose_weighted.py).
GLS_TOL = 1e-6
#: Newton steps at most (typically 3 are taken from the closed form, 2 for samples; up to
#: about 15 from a closed form far from the weighted minimum, with the trust region).
GLS_MAX_ITER = 20
#: Estimated error (rad) under which a Monte Carlo sample's chord iteration has converged
#: (:func:`refine_samples`; the bound of the Newton fit's, :data:`GLS_TOL`).
SAMPLE_TOL = 1e-10
#: Chord steps at most of a Monte Carlo sample (:func:`refine_samples`; typically 3).
SAMPLE_MAX_ITER = 8
#: Registrations refined at once (poses times samples): the working set stays in cache.
GLS_CHUNK = 8192
#: Largest step (rad) after which the next step keeps the last Newton matrix (a chord step):
#: its error is then of the order of that step, far below one, so the convergence stays
#: superlinear while the next step skips the matrix's computation (its largest part).
_CHORD_BELOW = 1e-3
#: Longest Newton step (rad): a longer one is shortened to it (:func:`_capped`).
_MAX_STEP = 0.25
#: Relative floor of the eigenvalues of the residual covariance before it is inverted.
_EIG_FLOOR = 1e-12
#: Entries (a, b) of the symmetric 3x3 Newton matrix, in the order they are computed.
_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
_EPS = np.zeros((3, 3, 3))
_EPS[0, 1, 2] = _EPS[1, 2, 0] = _EPS[2, 0, 1] = 1.0
_EPS[0, 2, 1] = _EPS[2, 1, 0] = _EPS[1, 0, 2] = -1.0


@dataclass(frozen=True)
class WeightedInfo:
    """Diagnostics of :func:`register_weighted`: ``converged`` (...), the last step below
    :data:`GLS_TOL`; ``iterations``, the Newton steps taken by the batch."""

    converged: np.ndarray
    iterations: int


def gls_weights(cov_q: ArrayLike, cov_r: ArrayLike, R: ArrayLike) -> np.ndarray:
    """``W = (Sigma_q + (I (x) R) Sigma_r (I (x) R)^T)^-1`` (..., 3n, 3n), the weights of the fit.

    ``cov_q`` (..., 3n, 3n) the world prisms' joint covariance, m^2; ``cov_r`` (3n, 3n) or
    (..., 3n, 3n) the reference's, body frame; ``R`` (..., 3, 3) the closed-form rotations.
    Scaled to a unit mean eigenvalue (the fit does not depend on the scale); the covariance's
    eigenvalues floored at 1e-12 of its largest; a zero covariance gives the identity.
    """
    cq = np.asarray(cov_q, dtype=float)
    cr = np.asarray(cov_r, dtype=float)
    R = np.asarray(R, dtype=float)
    m = cq.shape[-1]
    n = m // 3
    blk = np.zeros(R.shape[:-2] + (n, 3, n, 3))
    for i in range(n):  # the block-diagonal I (x) R
        blk[..., i, :, i, :] = R
    B = blk.reshape(R.shape[:-2] + (m, m))
    C = cq + B @ cr @ np.swapaxes(B, -1, -2)
    w, V = np.linalg.eigh(0.5 * (C + np.swapaxes(C, -1, -2)))
    top = w[..., -1:]
    zero = ~(top > 0)
    w = np.maximum(w, _EIG_FLOOR * np.where(zero, 1.0, top))
    w = np.where(zero, 1.0, w)
    inv = 1.0 / w
    inv = inv / inv.mean(axis=-1, keepdims=True)
    W = (V * inv[..., None, :]) @ np.swapaxes(V, -1, -2)
    return 0.5 * (W + np.swapaxes(W, -1, -2))


def _projections(W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pose: ``P`` (K, 3, 3n) with ``t = P (q - a)``, ``tilde W`` (K, 3n, 3n) and the stack
    ``[tilde W; G^{ab}]`` (K, 7 (3n), 3n) of the Newton products (docs/pose.md)."""
    K, m, _ = W.shape
    n = m // 3
    ones = np.tile(np.eye(3), (n, 1))  # (3n, 3)
    WO = W @ ones
    S = ones.T @ WO  # (K, 3, 3)
    P = np.linalg.solve(S, np.swapaxes(WO, 1, 2))  # (K, 3, 3n)
    Wt = W - WO @ P
    Wt = 0.5 * (Wt + np.swapaxes(Wt, 1, 2))
    G = np.einsum("cea,dfb,kicjd->kabiejf", _EPS, _EPS, Wt.reshape(K, n, 3, n, 3))
    G = G.reshape(K, 3, 3, m, m)
    stack = np.concatenate([Wt[:, None]] + [G[:, a, b][:, None] for a, b in _PAIRS], axis=1)
    return P, Wt, stack.reshape(K, 7 * m, m)


def _refine(p, q, W, R, t, xi0, tol, max_iter):
    """Newton refinement of (K, S) problems sharing each pose's weights.

    ``p, q`` (K, S, n, 3) (``p`` may be a broadcast view), ``W`` (K, 3n, 3n), the start
    ``exp(xi0) (R, t)``: ``R`` (K, S or 1, 3, 3), ``t`` (K, S or 1, 3), ``xi0`` (K, S, 6) or
    None. Returns ``R, t, converged (K, S), iterations``.
    """
    K, S, n, _ = q.shape
    m = 3 * n
    P, _, stack = _projections(W)
    # component layout, the samples of a pose last: rotations (K, 3, 3, S), points (K, n, 3, S)
    if xi0 is not None and R.shape[1] == 1:  # one start per pose, perturbed per sample
        Rc = _left_update(R[:, 0, :, :, None],
                          np.ascontiguousarray(np.moveaxis(xi0[..., 3:], 1, -1)))
    else:
        Rc = np.ascontiguousarray(np.moveaxis(np.broadcast_to(R, (K, S, 3, 3)), 1, -1))
        if xi0 is not None:
            Rc = _left_update(Rc, np.ascontiguousarray(np.moveaxis(xi0[..., 3:], 1, -1)))
    t = np.broadcast_to(t, (K, S, 3))
    if xi0 is not None:
        t = t + xi0[..., :3]
    X = np.moveaxis(np.broadcast_to(p, (K, S, n, 3)), 1, -1)
    Y = np.ascontiguousarray(np.moveaxis(q - t[:, :, None, :], 1, -1)).reshape(K, m, S)
    WtY = stack[:, :m] @ Y
    A = np.einsum("kcds,kids->kics", Rc, X, order="C")
    converged = np.zeros((K, S), dtype=bool)
    it = 0
    last = np.inf
    while it < max_iter:
        full = last > _CHORD_BELOW  # else keep the last Newton matrix (chord step)
        prod = (stack if full else stack[:, :m]) @ A.reshape(K, m, S)  # (K, 7m or m, S)
        U = (WtY - prod[:, :m]).reshape(K, n, 3, S)  # tilde W (q - a)
        M = np.einsum("kias,kibs->kabs", U, A, order="C")  # sum_i u_i a_i^T
        g = np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0],
                      M[:, 1, 0] - M[:, 0, 1]], axis=1)  # sum_i a_i x u_i, (K, 3, S)
        if full:
            # Gauss-Newton entries in _PAIRS order (a^T G^ab a), then the residual's curvature
            gn = np.einsum("kjs,kajs->kas", A.reshape(K, m, S), prod[:, m:].reshape(K, 6, m, S))
            N_inv = _newton_inverse(gn, M)
        theta = np.einsum("kabs,kbs->kas", N_inv, g, order="C")
        theta = _capped(theta)
        Rc = _left_update(Rc, theta)
        A = np.einsum("kcds,kids->kics", Rc, X, order="C")
        it += 1
        with np.errstate(invalid="ignore"):
            step2 = np.einsum("kas,kas->ks", theta, theta)
            converged = step2 <= tol * tol
        if converged.all():
            break
        last = np.sqrt(np.max(step2, initial=0.0, where=np.isfinite(step2)))
    t_out = t + np.swapaxes(P @ (Y - A.reshape(K, m, S)), 1, 2)
    return np.moveaxis(Rc, -1, 1), t_out, converged, it


def _left_update(Rc: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``exp([theta]x) R`` for ``Rc`` (K, 3, 3, S or 1) and ``theta`` (K, 3, S)
    (:func:`_exp_left`)."""
    E = _exp_left(theta)
    # E @ R per element, as three broadcast products (einsum is several times slower here)
    if Rc.shape[-1] == 1:
        Rc = Rc[:, None, :, :, 0, None]  # (K, 1, 3, 3, 1)
    else:
        Rc = Rc[:, None]  # (K, 1, 3, 3, S)
    out = E[:, :, 0, None] * Rc[:, :, 0]
    out += E[:, :, 1, None] * Rc[:, :, 1]
    out += E[:, :, 2, None] * Rc[:, :, 2]
    return out


def _exp_left(theta: np.ndarray) -> np.ndarray:
    """``exp([theta]x)`` (K, 3, 3, S) of ``theta`` (K, 3, S) (Rodrigues; the Taylor series to
    ``theta^4`` below 1e-2 rad, exact to round-off there)."""
    th2 = np.einsum("kas,kas->ks", theta, theta)
    if np.all(th2 < 1e-4):
        s = 1.0 - th2 * (1.0 / 6.0 - th2 / 120.0)
        c = 0.5 - th2 * (1.0 / 24.0 - th2 / 720.0)
    else:
        small = th2 < 1e-4
        th = np.sqrt(np.where(small, 1.0, th2))
        s = np.where(small, 1.0 - th2 * (1.0 / 6.0 - th2 / 120.0), np.sin(th) / th)
        c = np.where(small, 0.5 - th2 * (1.0 / 24.0 - th2 / 720.0), (1.0 - np.cos(th)) / (th * th))
    # exp = (1 - c th^2) I + s [theta]x + c theta theta^T
    E = c[:, None, None] * theta[:, :, None] * theta[:, None, :]
    d = 1.0 - c * th2
    st = s[:, None] * theta
    for a in range(3):
        E[:, a, a] += d
    E[:, 0, 1] -= st[:, 2]
    E[:, 0, 2] += st[:, 1]
    E[:, 1, 0] += st[:, 2]
    E[:, 1, 2] -= st[:, 0]
    E[:, 2, 0] -= st[:, 1]
    E[:, 2, 1] += st[:, 0]
    return E


def _newton_inverse(gn: np.ndarray, M: np.ndarray) -> np.ndarray:
    """The inverse (K, 3, 3, S) of the Newton matrix from its Gauss-Newton entries ``gn``
    (K, 6, S) in :data:`_PAIRS` order and ``M = sum_i u_i a_i^T`` (K, 3, 3, S) (module
    docstring). Where the full matrix is not positive definite (far from a minimum, where
    Newton's step may climb to a saddle), the Gauss-Newton matrix alone (positive definite for
    non-collinear points): a descent direction."""
    dot = M[:, 0, 0] + M[:, 1, 1] + M[:, 2, 2]
    n00 = gn[:, 0] - M[:, 0, 0] + dot
    n11 = gn[:, 1] - M[:, 1, 1] + dot
    n22 = gn[:, 2] - M[:, 2, 2] + dot
    n01 = gn[:, 3] - 0.5 * (M[:, 0, 1] + M[:, 1, 0])
    n02 = gn[:, 4] - 0.5 * (M[:, 0, 2] + M[:, 2, 0])
    n12 = gn[:, 5] - 0.5 * (M[:, 1, 2] + M[:, 2, 1])
    c00 = n11 * n22 - n12 * n12
    c01 = n02 * n12 - n01 * n22
    c02 = n01 * n12 - n02 * n11
    det = n00 * c00 + n01 * c01 + n02 * c02
    indefinite = ~((n00 > 0) & (n00 * n11 - n01 * n01 > 0) & (det > 0))
    if np.any(indefinite):
        n00, n11, n22, n01, n02, n12 = (np.where(indefinite, gn[:, i], v) for i, v in
                                        enumerate((n00, n11, n22, n01, n02, n12)))
        c00 = n11 * n22 - n12 * n12
        c01 = n02 * n12 - n01 * n22
        c02 = n01 * n12 - n02 * n11
        det = n00 * c00 + n01 * c01 + n02 * c02
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
    N_inv = np.stack([c00, c01, c02, c01, n00 * n22 - n02 * n02, n01 * n02 - n00 * n12,
                      c02, n01 * n02 - n00 * n12, n00 * n11 - n01 * n01], axis=1)
    return (N_inv * inv[:, None]).reshape(gn.shape[:1] + (3, 3) + gn.shape[2:])


def _capped(theta: np.ndarray) -> np.ndarray:
    """Steps (K, 3, S) longer than :data:`_MAX_STEP` rad shortened to it (a trust region:
    far from the minimum the quadratic model of a step is not to be trusted)."""
    th2 = np.einsum("kas,kas->ks", theta, theta)
    with np.errstate(invalid="ignore"):
        long = th2 > _MAX_STEP * _MAX_STEP
    if not np.any(long):
        return theta
    scale = np.where(long, _MAX_STEP / np.sqrt(np.where(long, th2, 1.0)), 1.0)
    return theta * scale[:, None]


def refine_batches(p, q, W, R, t, xi0=None, *, tol=GLS_TOL, max_iter=GLS_MAX_ITER,
                   chunk=GLS_CHUNK):
    """The weighted fits of (K, S) problems, S per pose sharing the pose's weights.

    ``p``, ``q`` (K, S, n, 3) body and world points (``p`` may be broadcast); ``W`` (K, 3n, 3n);
    the start ``R`` (K, S or 1, 3, 3), ``t`` (K, S or 1, 3), or with ``xi0`` (K, S, 6)
    ``exp(xi0) (R, t)``; ``tol`` (rad), ``max_iter`` Newton steps, ``chunk`` problems at once.
    Returns ``R`` (K, S, 3, 3), ``t`` (K, S, 3), ``converged`` (K, S) and the most steps a chunk
    took.
    """
    K, S = q.shape[:2]
    per = max(1, chunk // max(S, 1))
    R_out = np.empty((K, S, 3, 3))
    t_out = np.empty((K, S, 3))
    conv = np.zeros((K, S), dtype=bool)
    its = 0
    p = np.broadcast_to(p, q.shape)
    for s in range(0, K, per):
        e = min(K, s + per)
        R_out[s:e], t_out[s:e], conv[s:e], it = _refine(
            p[s:e], q[s:e], W[s:e], R[s:e], t[s:e], None if xi0 is None else xi0[s:e], tol,
            max_iter)
        its = max(its, it)
    return R_out, t_out, conv, its


def register_weighted(
    p_body: ArrayLike,
    q_world: ArrayLike,
    weights: ArrayLike,
    *,
    tol: float = GLS_TOL,
    max_iter: int = GLS_MAX_ITER,
    return_info: bool = False,
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, WeightedInfo]:
    """Rigid transform ``T_world_body`` minimising ``e^T W e``, ``e = q - (R p + t)`` stacked:
    Newton from the closed-form fit, vectorised over the batch.

    ``p_body``, ``q_world`` (..., n, 3) m, n >= 3; ``weights`` (..., 3n, 3n) symmetric positive
    definite (e.g. :func:`gls_weights`), broadcast; ``tol`` (rad) and ``max_iter`` of the Newton
    steps. Returns ``R`` (..., 3, 3), ``t`` (..., 3) and with ``return_info`` a
    :class:`WeightedInfo`.
    """
    p, q = point_pairs(p_body, q_world, 3)
    n = p.shape[-2]
    batch = p.shape[:-2]
    W = np.broadcast_to(np.asarray(weights, dtype=float), batch + (3 * n, 3 * n))
    R0, t0 = register(p, q)
    B = int(np.prod(batch))
    R, t, conv, its = refine_batches(
        p.reshape(B, 1, n, 3), q.reshape(B, 1, n, 3), W.reshape(B, 3 * n, 3 * n),
        R0.reshape(B, 1, 3, 3), t0.reshape(B, 1, 3), tol=tol, max_iter=max_iter)
    R = R.reshape(batch + (3, 3))
    t = t.reshape(batch + (3,))
    if not return_info:
        return R, t
    return R, t, WeightedInfo(conv.reshape(batch), its)


def weighted_registration_jacobian(
    p_body: ArrayLike, q_world: ArrayLike, weights: ArrayLike, R_world_body: ArrayLike,
    t_world_body: ArrayLike | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    r"""``J_q``, ``J_p`` (..., 6, n, 3): ``d(dt, dtheta) / d q_i`` and ``/ d p_i`` of the weighted
    fit (docs/pose.md#weighted-registration).

    ``p_body``, ``q_world`` (..., n, 3) m; ``weights`` (..., 3n, 3n) the fit's ``W``, held fixed;
    ``R_world_body`` (..., 3, 3) and ``t_world_body`` (..., 3) the fit (without ``t``: the best
    translation for ``R``). Raises GeometryError where ``K`` is singular (collinear points).
    """
    p, q = point_pairs(p_body, q_world)
    n = p.shape[-2]
    m = 3 * n
    R = np.asarray(R_world_body, dtype=float)
    batch = np.broadcast_shapes(p.shape[:-2], R.shape[:-2])
    W = np.broadcast_to(np.asarray(weights, dtype=float), batch + (m, m))
    a = np.einsum("...ij,...nj->...ni", R, p)  # R p_i
    if t_world_body is None:
        ones = np.tile(np.eye(3), (n, 1))
        WO = W @ ones
        d = (q - a).reshape(batch + (m,))
        t = np.linalg.solve(ones.T @ WO, np.einsum("...ji,...j->...i", WO, d)[..., None])[..., 0]
    else:
        t = np.asarray(t_world_body, dtype=float)
    e = (q - a - t[..., None, :]).reshape(batch + (m,))
    w = np.einsum("...ij,...j->...i", W, e).reshape(batch + (n, 3))
    H = np.zeros(batch + (n, 3, 6))
    H[..., :3] = np.eye(3)
    H[..., 3:] = -hat(a)
    H = H.reshape(batch + (m, 6))
    HtW = np.swapaxes(H, -1, -2) @ W  # (..., 6, 3n)
    K = HtW @ H
    K[..., 3:, 3:] -= np.einsum("...nij,...njk->...ik", hat(w), hat(a))
    scale = np.maximum(np.abs(K).max(axis=(-1, -2)), np.finfo(float).tiny)
    cond = np.linalg.cond(K / scale[..., None, None])
    if np.any(~(cond < 1e12)):
        raise GeometryError("Degenerate weighted rigid fit: the points are (nearly) collinear")
    K_inv = np.linalg.inv(K)
    J_q = K_inv @ HtW
    # d/dr: -H^T W (I (x) R) dr - (0; sum_i [w_i]x R dr_i)
    blk = np.zeros(batch + (n, 3, n, 3))
    for i in range(n):
        blk[..., i, :, i, :] = R
    Rb = blk.reshape(batch + (m, m))
    extra = np.zeros(batch + (6, n, 3))
    extra[..., 3:, :, :] = np.swapaxes(hat(w) @ R[..., None, :, :], -3, -2)
    J_p = -(K_inv @ (HtW @ Rb + extra.reshape(batch + (6, m))))
    return J_q.reshape(batch + (6, n, 3)), J_p.reshape(batch + (6, n, 3))


def newton_inverse_at(p: np.ndarray, q: np.ndarray, W: np.ndarray, R: np.ndarray,
                      t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``W~`` (K, 3n, 3n), the translation projector ``P`` (K, 3, 3n) and ``N^-1`` (K, 3, 3) at
    K fits ``R`` (K, 3, 3), ``t`` (K, 3) of body and world points ``p``, ``q`` (K, n, 3) with the
    weights ``W`` (K, 3n, 3n): what :func:`refine_samples` needs."""
    K, n, _ = q.shape
    m = 3 * n
    ones = np.tile(np.eye(3), (n, 1))  # (3n, 3)
    WO = W @ ones
    P = np.linalg.solve(ones.T @ WO, np.swapaxes(WO, 1, 2))  # (K, 3, 3n)
    Wt = W - WO @ P
    Wt = 0.5 * (Wt + np.swapaxes(Wt, 1, 2))
    a = np.einsum("kcd,kid->kic", R, p)  # (K, n, 3)
    U = (Wt @ (q - t[:, None, :] - a).reshape(K, m, 1)).reshape(K, n, 3, 1)
    M = np.einsum("kias,kibs->kabs", U, a[..., None])
    H = hat(a).reshape(K, m, 3)  # [a_i]x stacked
    N = np.swapaxes(H, 1, 2) @ Wt @ H  # Gauss-Newton part, sum_ij [a_i]x^T Wt_ij [a_j]x
    gn = np.stack([N[:, a_, b_] for a_, b_ in _PAIRS], axis=1)[..., None]
    return Wt, P, _newton_inverse(gn, M)[..., 0]


def refine_samples(Y: np.ndarray, X: np.ndarray, Wt: np.ndarray, P: np.ndarray,
                   N_inv: np.ndarray, R0: np.ndarray, xi0: np.ndarray, *, tol: float = SAMPLE_TOL,
                   max_iter: int = SAMPLE_MAX_ITER) -> tuple[np.ndarray, np.ndarray]:
    """The weighted fits of S samples of each of K poses by chord steps ``phi <- phi + N^-1 g``
    from their first-order prediction, ``N`` the pose's (docs/pose.md#weighted-registration).

    ``Y`` (K, 3n, S) the samples' world points minus the pose's ``t0``, m, stacked ``(x1, y1, z1,
    x2, ...)``; ``X`` (n, 3, S) their body points (shared by the poses); ``Wt``, ``P``, ``N_inv``
    from :func:`newton_inverse_at`; ``R0`` (K, 3, 3) the poses' rotations; ``xi0`` (K, 6, S) the
    prediction. Stops when the error estimated from the last two steps, ``d_k^2 / d_(k-1)``, is
    below ``tol`` for every sample, or after ``max_iter`` steps. Returns ``xi`` (K, 6, S), each
    fit's ``(t - t0, phi)``, and ``converged`` (K, S) (:func:`refine_batches` finishes the rest).
    """
    K, m, S = Y.shape
    n = m // 3
    # the body points rotated by each pose's fit, b_i = R0 x_i: (K, n, 3, S)
    B = R0[:, None, :, 0, None] * X[:, 0, None]
    B += R0[:, None, :, 1, None] * X[:, 1, None]
    B += R0[:, None, :, 2, None] * X[:, 2, None]
    B0, B1, B2 = B[:, :, None, 0], B[:, :, None, 1], B[:, :, None, 2]  # (K, n, 1, S)

    def body(phi):  # a_i = exp([phi]x) b_i, (K, n, 3, S)
        E = _exp_left(phi)[:, None]  # (K, 1, 3, 3, S)
        A = E[:, :, :, 0] * B0
        A += E[:, :, :, 1] * B1
        A += E[:, :, :, 2] * B2
        return A

    phi = np.array(xi0[:, 3:])
    A = body(phi)
    converged = np.zeros((K, S), dtype=bool)
    g = np.empty((K, 3, S))
    last = None
    for _ in range(max_iter):
        U = (Wt @ (Y - A.reshape(K, m, S))).reshape(K, n, 3, S)
        for a, (b, c) in enumerate(((1, 2), (2, 0), (0, 1))):  # sum_i a_i x u_i
            g[:, a] = np.sum(A[:, :, b] * U[:, :, c] - A[:, :, c] * U[:, :, b], axis=1)
        theta = N_inv @ g
        phi += theta
        A = body(phi)
        step2 = np.einsum("kas,kas->ks", theta, theta)
        if last is not None:
            with np.errstate(invalid="ignore", divide="ignore"):
                # error left ~ rho d_k = d_k^2 / d_(k-1), with rho = d_k / d_(k-1) < 1/2
                converged = (step2 * step2 <= tol * tol * last) & (4.0 * step2 <= last)
                converged |= step2 <= (tol * tol) * 1e-4  # a step far below tol: done
            if converged.all():
                break
        last = step2
    xi = np.empty((K, 6, S))
    xi[:, :3] = P @ (Y - A.reshape(K, m, S))  # t - t0
    xi[:, 3:] = phi
    return xi, converged
