"""Poses at arbitrary times between the knots: the WNOA GP's interpolation on SE(3), mean and
covariance from the two neighbouring knots' joint posterior: docs/joint.md#queries-between-knots.
"""

from __future__ import annotations

import numpy as np

from rtsgt.errors import InputError
from rtsgt.joint.prior import TRAJECTORY_DIM, relative_log
from rtsgt.joint.se3 import adjoint, curly, exp_se3, jacobians_inv, left_jacobian


def _phi(a: np.ndarray) -> np.ndarray:
    """Transition ``[[1, a], [0, 1]]`` (N, 2, 2) of intervals ``a`` (N,)."""
    out = np.zeros(a.shape + (2, 2))
    out[:, 0, 0] = out[:, 1, 1] = 1.0
    out[:, 0, 1] = a
    return out


def _q(a: np.ndarray) -> np.ndarray:
    """Process covariance at unit ``Qc``, ``[[a^3/3, a^2/2], [a^2/2, a]]`` (N, 2, 2)."""
    return np.stack([np.stack([a**3 / 3, a**2 / 2], -1), np.stack([a**2 / 2, a], -1)], -2)


def gp_weights(h: np.ndarray, dt: np.ndarray):
    """Interpolation weights of the local state ``[xi; xi']`` at ``h`` (N,) s after the left
    knot of intervals of ``dt`` (N,) s: ``Lambda``, ``Psi`` (N, 2, 2) and the conditional
    variance at unit ``Qc`` ``P`` (N, 2, 2) (Barfoot, 2nd ed., section 11.1; ``Qc`` cancels)."""
    qh = _q(h)
    psi = qh @ np.swapaxes(_phi(dt - h), 1, 2) @ np.linalg.inv(_q(dt))
    lam = _phi(h) - psi @ _phi(dt)
    return lam, psi, qh - psi @ _phi(dt - h) @ qh


def _query(tq, t_knot, R, t, w):
    """Each query's interval ``k`` (Q,), pose ``Rq``, ``pq``, the Jacobian ``J`` (Q, 6, 24) of
    its right perturbation with respect to the two knots' ``(d, dw)``, ``jr`` (Q, 6, 6)
    ``J_r(xi(tau))`` and the conditional variance at unit ``Qc`` ``pc`` (Q,)."""
    if tq.size and (tq.min() < t_knot[0] or tq.max() > t_knot[-1]):
        bad = tq[(tq < t_knot[0]) | (tq > t_knot[-1])][0]
        raise InputError(f"Query time {bad:.6f} s outside the measurements' span "
                         f"[{t_knot[0]:.6f}, {t_knot[-1]:.6f}] s")
    k = np.clip(np.searchsorted(t_knot, tq, side="right") - 1, 0, t_knot.size - 2)
    dt = t_knot[k + 1] - t_knot[k]
    lam, psi, pc = gp_weights(tq - t_knot[k], dt)
    xi_k = relative_log(R, t)[k]
    jl_inv, jr_inv = jacobians_inv(xi_k)
    w0, w1 = w[k], w[k + 1]
    psi_next = np.einsum("nij,nj->ni", jr_inv, w1)
    xi = (lam[:, 0, 1, None] * w0 + psi[:, 0, 0, None] * xi_k
          + psi[:, 0, 1, None] * psi_next)
    dR, dp = exp_se3(xi)
    Rq = R[k] @ dR
    pq = t[k] + np.einsum("nij,nj->ni", R[k], dp)
    # d xi(tau) / d (d_k, dw_k, d_k+1, dw_k+1), first order as the prior's Jacobians
    eye = np.eye(6)
    g = psi[:, 0, 0, None, None] * eye - 0.5 * psi[:, 0, 1, None, None] * curly(w1)
    J = np.zeros((tq.size, 6, 24))
    J[:, :, :6] = -g @ jl_inv
    J[:, :, 6:12] = lam[:, 0, 1, None, None] * eye
    J[:, :, 12:18] = g @ jr_inv
    J[:, :, 18:] = psi[:, 0, 1, None, None] * jr_inv
    jr = left_jacobian(-xi)
    J = jr @ J
    J[:, :, :6] += adjoint(np.swapaxes(dR, 1, 2), -np.einsum("nji,nj->ni", dR, dp))
    return k, Rq, pq, J, jr, pc[:, 0, 0]


def _propagate(k, J, jr, pc, qc, cov, cov_next):
    """``J Sigma_k,k+1 J^T`` plus the GP's conditional variance (Q, 6, 6), symmetrised (of
    the knots' states only their trajectory's first :data:`TRAJECTORY_DIM`)."""
    n = TRAJECTORY_DIM
    Ja, Jb = J[:, :, :n], J[:, :, n:]
    cross = Ja @ cov_next[k, :n, :n] @ np.swapaxes(Jb, 1, 2)
    out = (Ja @ cov[k, :n, :n] @ np.swapaxes(Ja, 1, 2)
           + Jb @ cov[k + 1, :n, :n] @ np.swapaxes(Jb, 1, 2) + cross + np.swapaxes(cross, 1, 2))
    q = qc[k] if qc.ndim == 3 else qc[k][:, :, None] * np.eye(6)
    out += jr @ (pc[:, None, None] * q) @ np.swapaxes(jr, 1, 2)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def interpolate_poses_gp(t_query, t_knot, R, t, w, qc, cov, cov_next):
    """Poses ``T(t_query)`` (Q,) s of the GP through the knots and their covariance.

    Knots at ``t_knot`` (K,) s, poses ``R`` (K, 3, 3), ``t`` (K, 3), body velocities ``w``
    (K, 6), the prior's ``qc`` (K-1, 6) per interval (or (K-1, 6, 6), the motion axes' turned
    into the knots' frame), the knots' posterior covariance ``cov``
    (K, d, d) and that of consecutive knots ``cov_next`` (K-1, d, d) (right perturbations; their
    first :data:`TRAJECTORY_DIM` rows and columns the trajectory's).
    Returns ``R`` (Q, 3, 3), ``t`` (Q, 3) and the covariance (Q, 6, 6) of the query poses'
    right perturbation. A query time outside the knots' span is an InputError.
    """
    tq = np.asarray(t_query, dtype=float)
    k, Rq, pq, J, jr, pc = _query(tq, t_knot, R, t, w)
    return Rq, pq, _propagate(k, J, jr, pc, qc, cov, cov_next)


def interpolate_split_gp(t_query, t_knot, R, t, w, qc, cov_var, cov_var_next, factor):
    """As :func:`interpolate_poses_gp`, the covariance split (docs/joint.md#the-shared-error):
    from the knots' covariance given the globals ``cov_var`` (K, d, d), ``cov_var_next``
    (K-1, d, d) and their shared factor ``factor`` (K, d, G), returns ``R`` (Q, 3, 3),
    ``t`` (Q, 3), the varying covariance (Q, 6, 6) (with the GP's conditional variance) and
    the shared factor (Q, 6, G) of the query poses' right perturbation."""
    tq = np.asarray(t_query, dtype=float)
    k, Rq, pq, J, jr, pc = _query(tq, t_knot, R, t, w)
    n = TRAJECTORY_DIM
    L = J[:, :, :n] @ factor[k, :n] + J[:, :, n:] @ factor[k + 1, :n]
    return Rq, pq, _propagate(k, J, jr, pc, qc, cov_var, cov_var_next), L


__all__ = ["gp_weights", "interpolate_poses_gp", "interpolate_split_gp", "query_jacobians"]


def query_jacobians(t_query, t_knot, R, t, w):
    """Each query's interval ``k`` (Q,), its pose ``R`` (Q, 3, 3), ``t`` (Q, 3) and the
    Jacobian (Q, 6, 24) of its right perturbation on the interval's two knots' ``(d, dw)``
    (the interpolation of :func:`interpolate_poses_gp`)."""
    k, Rq, pq, J, _, _ = _query(np.asarray(t_query, dtype=float), t_knot, R, t, w)
    return k, Rq, pq, J
