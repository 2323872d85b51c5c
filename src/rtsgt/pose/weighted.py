r"""Weighted (generalised least squares) rigid registration, batched, and its Jacobian.

Problem
-------
The prisms ``q_i`` (world) and their reference positions ``r_i`` (body) of one pose have
errors; the residual of a rigid transform ``(R, t)`` is the stacked ``3n``-vector
``e = q - (R r + t)``. Its covariance, to first order, is

.. math:: C = \Sigma_q + (I_n \otimes R)\, \Sigma_r\, (I_n \otimes R)^T ,

``Sigma_q`` the prisms' joint ``(3n, 3n)`` covariance at that time, ``Sigma_r`` the
reference's (body frame, rotated into the world frame). The weighted fit minimises

.. math:: (R, t) = \operatorname{argmin}\; e^T W e, \qquad W = C^{-1}

(:func:`gls_weights`): the Gauss-Markov best linear unbiased fit of one pose, the one of least
variance. The reference error is one draw shared by every pose of a deployment, but each pose
is fitted alone and at one pose it is noise on the residual like the prisms': it belongs in
``C``. The unweighted fit (``W = I``, the paper's point-to-point registration,
:func:`rtsgt.pose.registration.register`) is the special case of isotropic, equal, independent
errors; it ignores that a prism tracked from far away is known worse along the line of sight,
and that the calibrations correlate the prisms.

``W`` is evaluated once per pose, at the rotation of the closed-form fit of the mean inputs,
and then held fixed: the estimator is a fixed function of the inputs (``W`` does not move with
a Monte Carlo sample or a sigma point, the standard choice), and the propagation engines
differentiate or sample the fit only.

Solution
--------
For a fixed ``R`` the best ``t`` is linear: with ``1`` the ``(3n, 3)`` stack of identities,
``S = 1^T W 1`` and ``P = S^{-1} 1^T W``, ``t(R) = P (q - (I \otimes R) r)``. Eliminating it
leaves a problem in the rotation alone (variable projection),

.. math::

    f(R) = (q - a)^T \tilde W (q - a), \qquad a = (I_n \otimes R)\, r, \qquad
    \tilde W = W - W 1 S^{-1} 1^T W ,

where ``tilde W`` annihilates translations (``tilde W 1 = 0``), so ``q`` may be shifted by any
translation first (by the closed-form ``t``, for round-off: the residual is then millimetres,
not the station's hundreds of metres). Starting from the closed-form (unweighted) rotation,
Newton's method on SO(3) with the left update ``R <- exp([theta]x) R``: expanding
``exp([theta]x) a_i = a_i + theta x a_i + theta x (theta x a_i) / 2`` to second order gives,
with ``u = tilde W (q - a)``,

.. math::

    g = \sum_i a_i \times u_i, \qquad
    N = \sum_{ij} [a_i]_\times^T \tilde W_{ij} [a_j]_\times
        - \operatorname{sym}\Big(\sum_i u_i a_i^T\Big) + \Big(\sum_i u_i \cdot a_i\Big) I,
    \qquad \theta = N^{-1} g .

The first term of ``N`` is the Gauss-Newton matrix; the other two are the residual's
curvature, which makes the convergence quadratic (they are of the order of the residual over
the prisms' spread, a few 1e-3, and vanish for exact data). From the closed-form start (about
the pose's own uncertainty away, milliradians) the steps are typically 1e-3, 1e-6, 1e-12 rad.
Once the largest step of a batch is below 1e-3 rad, the next steps keep the last ``N``
(chord steps: its error is then of the order of that step, so each step still shrinks the
error by that factor) and skip its computation, the largest part of a step. The iteration
stops when every step of a batch is below :data:`GLS_TOL` = 1e-6 rad: what is left is below
1e-10 rad (tests/test_pose_weighted.py); at most :data:`GLS_MAX_ITER` steps, the elements that
did not get there are reported. Far from a minimum the steps are safeguarded: at most
0.25 rad (a trust region), and the Gauss-Newton matrix alone where the Newton matrix is not
positive definite (a descent direction; undamped steps can settle on a saddle). Samples of a
pose (Monte Carlo draws, sigma points) start from their first-order prediction about the
pose's fit instead (``xi0`` of :func:`refine_batches`), within about the square of their
perturbation: two steps. The Monte Carlo engine's samples take chord steps with the pose's
Newton matrix instead (:func:`refine_samples`), which skip the per-sample matrix.

Vectorised over poses and over the samples of a pose (the Monte Carlo draws, the sigma
points), sharing the pose's weights: the samples of a pose are the columns of matrix products
with the pose's ``(3n, 3n)`` matrices (``tilde W`` and, for ``N``, one matrix per entry of
``N``: ``N_ab = a^T G^{ab} a`` with
``G^{ab}_{(ie),(jf)} = sum_cd eps_cea eps_dfb tilde W_{(ic),(jd)}``), and everything else is
elementwise arithmetic on arrays over (poses, samples). No Python loop over poses or samples.

Jacobian
--------
First order, by the implicit function theorem on the optimality condition of the full
problem, ``g(xi; q, r) = H^T W e = 0`` with ``H_i = [I, -[a_i]x]`` (``a_i = R r_i``, the
derivative of ``R r_i + t`` along the left perturbation ``xi = (dt, dtheta)`` of
:mod:`rtsgt.geometry.transform`) and ``w = W e`` at the optimum:

.. math::

    K \xi = H^T W\, dq - H^T W (I_n \otimes R)\, dr - \begin{pmatrix} 0 \\
        \sum_i [w_i]_\times R\, dr_i \end{pmatrix}, \qquad
    K = H^T W H - \begin{pmatrix} 0 & 0 \\ 0 & \sum_i [w_i]_\times [a_i]_\times
        \end{pmatrix}

(:func:`weighted_registration_jacobian`). For exact data (``w = 0``) it is the classic
``(H^T W H)^{-1} H^T W``, and the first-order covariance of the weighted fit is
``(H^T W H)^{-1}``; with ``W = I`` it is the Jacobian of the unweighted fit
(:func:`rtsgt.pose.registration.registration_jacobian`).
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
           "refine_samples", "register_weighted", "weighted_registration_jacobian"]

#: Rotation step (rad) under which the Newton iteration of a batch has converged (the error
#: left is then below 1e-10 rad, module docstring).
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
    """Diagnostics of :func:`register_weighted`.

    Attributes
    ----------
    converged : ndarray of bool, shape (...)
        The last Newton step of the element was below :data:`GLS_TOL`.
    iterations : int
        Newton steps taken (the same for the whole batch).
    """

    converged: np.ndarray
    iterations: int


def gls_weights(cov_q: ArrayLike, cov_r: ArrayLike, R: ArrayLike) -> np.ndarray:
    """``W = (Sigma_q + (I (x) R) Sigma_r (I (x) R)^T)^{-1}``: the weights of the fit.

    Parameters
    ----------
    cov_q : array_like, shape (..., 3n, 3n)
        Joint covariance of the stacked world prisms at each pose, m^2.
    cov_r : array_like, shape (3n, 3n) or (..., 3n, 3n)
        Covariance of the stacked reference prisms, body frame, m^2.
    R : array_like, shape (..., 3, 3)
        ``R_world_body`` of each pose (the closed-form fit's).

    Returns
    -------
    ndarray, shape (..., 3n, 3n)
        Symmetric positive definite, scaled to a unit mean eigenvalue (the fit does not depend
        on the scale). Eigenvalues of the covariance below 1e-12 of its largest are raised to
        that floor (a residual covariance known exactly in some direction); a covariance that
        is zero altogether gives the identity (the unweighted fit).
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
    ``[tilde W; G^{ab}]`` (K, 7 (3n), 3n) of the Newton products (module docstring)."""
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

    Parameters
    ----------
    p, q : ndarray, shape (K, S, n, 3)
        Body and world points (``p`` may be a broadcast view).
    W : ndarray, shape (K, 3n, 3n)
        The weights of each pose.
    R, t : ndarray, shapes (K, S or 1, 3, 3) and (K, S or 1, 3)
        The start, or with ``xi0`` the pose it is a left perturbation of.
    xi0 : ndarray, shape (K, S, 6), optional
        Start at ``exp(xi0) (R, t)`` (:mod:`rtsgt.geometry.transform`).
    tol, max_iter, chunk
        Convergence, most Newton steps, problems refined at once.

    Returns
    -------
    R : ndarray, shape (K, S, 3, 3)
    t : ndarray, shape (K, S, 3)
    converged : ndarray of bool, shape (K, S)
    iterations : int
        The most Newton steps a chunk took.
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
    """Rigid transform ``T_world_body`` minimising ``e^T W e``, ``e = q - (R p + t)`` stacked.

    Newton's method on SO(3) from the closed-form (unweighted) fit, the translation eliminated
    in closed form (module docstring), vectorised over the batch.

    Parameters
    ----------
    p_body : array_like, shape (..., n, 3)
        Points in the body frame, m, n >= 3.
    q_world : array_like, shape (..., n, 3)
        The same points in the world frame, m.
    weights : array_like, shape (..., 3n, 3n)
        Symmetric positive definite ``W`` of the stacked residual ``(e_1x, e_1y, e_1z, e_2x,
        ...)`` (e.g. :func:`gls_weights`), broadcast against the batch.
    tol : float
        Rotation step (rad) under which the iteration has converged.
    max_iter : int
        Newton steps at most.
    return_info : bool
        Also return a :class:`WeightedInfo`.

    Returns
    -------
    R_world_body : ndarray, shape (..., 3, 3)
    t_world_body : ndarray, shape (..., 3)
    info : WeightedInfo
        Only with ``return_info=True``.
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
    r"""First-order sensitivity of the weighted fit to its input points (module docstring).

    Parameters
    ----------
    p_body, q_world : array_like, shape (..., n, 3)
        The points of the fit, m.
    weights : array_like, shape (..., 3n, 3n)
        The fit's ``W`` (held fixed).
    R_world_body, t_world_body : array_like, shape (..., 3, 3) and (..., 3)
        The weighted fit (:func:`register_weighted`); without ``t_world_body``, the best
        translation for ``R_world_body``, ``t = P (q - (I (x) R) p)`` (module docstring).

    Returns
    -------
    J_q : ndarray, shape (..., 6, n, 3)
        ``d(dt, dtheta) / d q_i``.
    J_p : ndarray, shape (..., 6, n, 3)
        ``d(dt, dtheta) / d p_i``.

    Raises
    ------
    GeometryError
        If ``K`` is singular (collinear points) for some element.
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
    """The projected weights, translation projector and inverse Newton matrix of K fits.

    ``p, q`` (K, n, 3) the body and world points, ``W`` (K, 3n, 3n) the weights, ``R``
    (K, 3, 3), ``t`` (K, 3) the fits (module docstring). Returns ``tilde W`` (K, 3n, 3n),
    ``P`` (K, 3, 3n) and ``N^-1`` (K, 3, 3) at the fits: what :func:`refine_samples` needs.
    """
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
    """The weighted fits of S samples of each of K poses, by chord steps from their
    first-order prediction: the Monte Carlo engine's fits.

    A sample of a pose is its prisms and reference perturbed by about the pose's
    uncertainty; its fit ``R = exp([phi]x) R0`` is within about the square of that
    perturbation of the first-order prediction ``phi = xi0``. Each step
    ``phi <- phi + N^-1 g`` takes the sample's own gradient ``g`` at ``exp([phi]x) R0``
    (module docstring) and the pose's Newton matrix ``N`` at its fit in place of the
    sample's: the two differ by the relative size of the perturbation (and of ``phi``), so
    each step shrinks the error by about that factor ``rho`` (typically 1e-3: steps 1e-6,
    1e-9 rad), and the fixed point is the sample's fit (``g = 0``). The error left after a
    step ``d_k`` is about ``rho d_k``, ``rho = d_k / d_(k-1)``: the iteration stops when that
    estimate is below ``tol`` for every sample of the batch (contracting, ``rho < 1/2``), or
    after ``max_iter`` steps; samples that did not get there are flagged
    (:func:`refine_batches` can finish them).

    Parameters
    ----------
    Y : ndarray, shape (K, 3n, S)
        World points of the samples minus the pose's fitted translation ``t0``, m, stacked
        ``(x1, y1, z1, x2, ...)``, samples last.
    X : ndarray, shape (n, 3, S)
        Body points of the samples (shared by the poses), m.
    Wt, P, N_inv : ndarray, shapes (K, 3n, 3n), (K, 3, 3n), (K, 3, 3)
        Each pose's projected weights, translation projector and inverse Newton matrix
        (:func:`newton_inverse_at`).
    R0 : ndarray, shape (K, 3, 3)
        The poses' fitted rotations.
    xi0 : ndarray, shape (K, 6, S)
        First-order prediction of each sample's left perturbation ``(dt, dtheta)``.

    Returns
    -------
    xi : ndarray, shape (K, 6, S)
        The left perturbation of each sample's fit about ``(R0, t0)``: ``(t - t0, phi)``.
    converged : ndarray of bool, shape (K, S)
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
