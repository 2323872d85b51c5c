"""Cross-covariance of a GP track's posterior between two query times (the relative pose of
the RPE), from the Gauss-Markov chain of the knots and the bridges of the intervals.

Owns :func:`gp_cross_covariance` and :func:`gp_joint_covariance`. Formulas:
docs/interpolation.md#cross-covariance-between-times.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError
from rtsgt.interpolation.gp import GPTrack

__all__ = ["gp_cross_covariance", "gp_joint_covariance"]


def _weights(gp: GPTrack, tau: np.ndarray):
    """Interval index k, weights W (K, d, 2d) on [x_k; x_{k+1}], and whether tau is interior."""
    dim = gp.state_dim
    eye = np.eye(dim)
    t = gp.t
    n = t.shape[0]
    k = np.clip(np.searchsorted(t, tau, side="right") - 1, 0, n - 2)
    on_k = t[k] == tau
    on_k1 = t[k + 1] == tau
    interior = ~on_k & ~on_k1
    d = t[k + 1] - t[k]
    s = np.clip((tau - t[k]) / d, 0.0, 1.0)
    W = np.zeros((tau.size, dim, 2 * dim))
    # Lambda = Phi(tau - t_k) - Psi Phi(d), Psi = Q(tau - t_k) Phi(t_{k+1} - tau)^T Q(d)^-1
    q1 = gp.process_noise(s * d)
    qd_inv = np.linalg.inv(gp.process_noise(d))
    psi = q1 @ np.swapaxes(gp.transition((1.0 - s) * d), 1, 2) @ qd_inv
    lam = gp.transition(s * d) - psi @ gp.transition(d)
    W[:, :, :dim] = np.where(interior[:, None, None], lam,
                             np.where(on_k[:, None, None], eye, 0))
    W[:, :, dim:] = np.where(interior[:, None, None], psi,
                             np.where(on_k1[:, None, None], eye, 0))
    return k, W, interior


def _knot_cov(gp: GPTrack, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``Cov(x_a, x_b)`` (K, d, d) for knot indices with ``a <= b`` elementwise."""
    S, C = gp.cov, gp.cross_cov
    out = S[a].copy()
    lag = b - a
    for step in range(int(lag.max(initial=0))):
        m = lag > step
        k = a[m] + step  # Cov(x_a, x_{k+1}) = Cov(x_a, x_k) S_k^-1 C_k
        out[m] = out[m] @ np.linalg.solve(S[k], C[k])
    return out


def _pair_cov(gp: GPTrack, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``Cov(x_a, x_b)`` for any knot indices."""
    swap = a > b
    lo, hi = np.where(swap, b, a), np.where(swap, a, b)
    c = _knot_cov(gp, lo, hi)
    return np.where(swap[:, None, None], np.swapaxes(c, 1, 2), c)


def gp_cross_covariance(gp: GPTrack, tau_1: ArrayLike, tau_2: ArrayLike) -> np.ndarray:
    """``Cov(x(tau_1), x(tau_2))`` of the state for pairs of times (module docstring).

    Parameters
    ----------
    gp : GPTrack
    tau_1, tau_2 : array_like, shape (K,)
        Times, s, inside the track (from its first to its last knot), in any order.

    Returns
    -------
    ndarray, shape (K, d, d)
        The whole state (``d = gp.state_dim``: 6 for WNOA, 9 for WNOJ), m^2, m^2/s, ...;
        ``[:, :3, :3]`` is the position block.

    Raises
    ------
    InputError
        Times outside the track, or arrays of different shapes.
    """
    t1 = np.atleast_1d(np.asarray(tau_1, dtype=float))
    t2 = np.atleast_1d(np.asarray(tau_2, dtype=float))
    if t1.shape != t2.shape or t1.ndim != 1:
        raise InputError(f"Expected two time arrays of one shape (K,), got {t1.shape}, {t2.shape}")
    lo, hi = gp.t[0], gp.t[-1]
    bad = ~((t1 >= lo) & (t1 <= hi) & (t2 >= lo) & (t2 <= hi))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"Expected times inside the track [{lo!r}, {hi!r}] s, got "
                         f"{float(t1[i])!r}, {float(t2[i])!r} (pair {i})")
    swap = t1 > t2
    a_t, b_t = np.where(swap, t2, t1), np.where(swap, t1, t2)
    ka, Wa, ia = _weights(gp, a_t)
    kb, Wb, ib = _weights(gp, b_t)
    K, dim = t1.size, gp.state_dim
    big = np.empty((K, 2 * dim, 2 * dim))
    for u, du in ((0, 0), (dim, 1)):
        for v, dv in ((0, 0), (dim, 1)):
            big[:, u:u + dim, v:v + dim] = _pair_cov(gp, ka + du, kb + dv)
    out = Wa @ big @ np.swapaxes(Wb, 1, 2)
    same = ia & ib & (ka == kb)
    if same.any():
        k = ka[same]
        tk, d = gp.t[k], gp.t[k + 1] - gp.t[k]
        d1, d2 = a_t[same] - tk, b_t[same] - tk
        q1, q2, qd = gp.process_noise(d1), gp.process_noise(d2), gp.process_noise(d)
        phi = gp.transition
        bridge = (q1 @ np.swapaxes(phi(d2 - d1), 1, 2)
                  - q1 @ np.swapaxes(phi(d - d1), 1, 2) @ np.linalg.solve(
                      qd, phi(d - d2) @ q2))
        out[same] += gp.interval_scale(k)[:, None, None] * bridge
    return np.where(swap[:, None, None], np.swapaxes(out, 1, 2), out)


def gp_joint_covariance(gp: GPTrack, tau: ArrayLike) -> np.ndarray:
    """Joint posterior covariance of the positions at the times ``tau`` (module docstring).

    Parameters
    ----------
    gp : GPTrack
    tau : array_like, shape (m,)
        Times, s, inside the track, in any order.

    Returns
    -------
    ndarray, shape (m, m, 3, 3)
        ``Cov(p(tau_a), p(tau_b))``, m^2: the position blocks of
        :func:`gp_cross_covariance` for every pair, computed at the cost of the knots between
        the first and the last time (their number squared), not of the pairs times the lags.
    """
    tau = np.atleast_1d(np.asarray(tau, dtype=float))
    if tau.ndim != 1:
        raise InputError(f"Expected times of shape (m,), got {tau.shape}")
    m = tau.size
    if m == 0:
        return np.zeros((0, 0, 3, 3))
    lo_t, hi_t = gp.t[0], gp.t[-1]
    if np.any((tau < lo_t) | (tau > hi_t)):
        raise InputError(f"Expected times inside the track [{lo_t!r}, {hi_t!r}] s")
    k, W, interior = _weights(gp, tau)
    lo, hi = int(k.min()), int(k.max()) + 1  # the knots involved
    K, dim = hi - lo + 1, gp.state_dim
    S = gp.cov[lo:hi + 1]
    step = np.linalg.solve(S[:-1], gp.cross_cov[lo:hi])  # S_c^-1 C_c
    J = np.zeros((K, K, dim, dim))
    J[np.arange(K), np.arange(K)] = S
    for d in range(1, K):  # loop over the diagonals of the knot covariance
        a = np.arange(K - d)
        J[a, a + d] = J[a, a + d - 1] @ step[a + d - 1]
        J[a + d, a] = np.swapaxes(J[a, a + d], 1, 2)
    i = k - lo
    # the positions are A x (x: the knots involved; A: the rows of W on the knots k, k + 1),
    # so their covariance is A J A^T: two products of dense matrices
    A = np.zeros((m, 3, K, dim))
    A[np.arange(m), :, i] = W[:, :3, :dim]
    A[np.arange(m), :, i + 1] = W[:, :3, dim:]
    A = A.reshape(3 * m, K * dim)
    out = (A @ (J.transpose(0, 2, 1, 3).reshape(K * dim, K * dim) @ A.T)
           ).reshape(m, 3, m, 3).transpose(0, 2, 1, 3)
    same = interior[:, None] & interior[None, :] & (k[:, None] == k[None, :])
    a_idx, b_idx = np.nonzero(same)
    if a_idx.size:
        first = tau[a_idx] <= tau[b_idx]
        t1 = np.where(first, tau[a_idx], tau[b_idx])
        t2 = np.where(first, tau[b_idx], tau[a_idx])
        kk = k[a_idx]
        tk, dk = gp.t[kk], gp.t[kk + 1] - gp.t[kk]
        d1, d2 = t1 - tk, t2 - tk
        q1, q2, qd = gp.process_noise(d1), gp.process_noise(d2), gp.process_noise(dk)
        phi = gp.transition
        bridge = (q1 @ np.swapaxes(phi(d2 - d1), 1, 2)
                  - q1 @ np.swapaxes(phi(dk - d1), 1, 2) @ np.linalg.solve(
                      qd, phi(dk - d2) @ q2))[:, :3, :3]
        bridge = np.where(first[:, None, None], bridge, np.swapaxes(bridge, 1, 2))
        out[a_idx, b_idx] += gp.interval_scale(kk)[:, None, None] * bridge
    return out
