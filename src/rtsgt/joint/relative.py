"""Covariance between the joint engine's poses at two distant times (the relative pose).

The knots given the globals are a Gauss-Markov chain (block-tridiagonal precision), so
``Cov(x_i, x_j) = G_i ... G_j-1 Cov(x_j)`` for ``i < j``, ``G_k = Cov(x_k, x_k+1)
Cov(x_k+1)^-1``; the globals add ``L_i L_j^T``. A query pose is the GP's interpolation of its
interval's two knots: docs/joint.md#poses-at-two-times.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rtsgt.geometry.so3 import hat
from rtsgt.joint.interpolate import interpolate_poses_gp, query_jacobians
from rtsgt.joint.prior import TRAJECTORY_DIM
from rtsgt.joint.sparse import ArrowSolution

__all__ = ["JointPosterior", "body_to_world", "chain_gains", "chain_products",
           "knot_cross_covariance", "knots_to_body", "linear_covariance", "origin_adjoint",
           "query_cross_covariance", "world_covariance"]


def chain_gains(sol: ArrowSolution) -> np.ndarray:
    """``G_k = Cov(x_k, x_k+1) Cov(x_k+1)^-1`` (K-1, d, d) of the knots given the globals."""
    return np.linalg.solve(sol.cov_var[1:], np.swapaxes(sol.cov_var_next, 1, 2)).swapaxes(1, 2)


def chain_products(gains: np.ndarray, k_a: np.ndarray, k_b: np.ndarray) -> np.ndarray:
    """``G_ka ... G_kb-1`` (N, d, d) for ``k_a <= k_b`` (N,) (the identity where equal); a
    loop over the knots between, each step batched over the pairs still going."""
    d = gains.shape[1]
    T = np.broadcast_to(np.eye(d), (k_a.size, d, d)).copy()
    steps = np.asarray(k_b) - np.asarray(k_a)
    for j in range(int(steps.max(initial=0))):
        on = np.flatnonzero(steps > j)
        T[on] = T[on] @ gains[k_a[on] + j]
    return T


def knot_cross_covariance(sol: ArrowSolution, gains: np.ndarray, k_a: np.ndarray,
                          k_b: np.ndarray) -> np.ndarray:
    """``Cov(x_ka, x_kb)`` (N, d, d) of the knots' states, ``k_a <= k_b`` (N,): the chain's
    part and the globals' ``L_ka L_kb^T``."""
    k_a, k_b = np.asarray(k_a), np.asarray(k_b)
    C = chain_products(gains, k_a, k_b) @ sol.cov_var[k_b]
    return C + sol.factor[k_a] @ np.swapaxes(sol.factor[k_b], 1, 2)


def linear_covariance(sol: ArrowSolution, gains: np.ndarray, k: np.ndarray, Ax: np.ndarray,
                      Ag: np.ndarray) -> np.ndarray:
    """Covariance (N, N) of ``N`` linear functions ``y_i = Ax_i x_ki + Ag_i g`` of the knots'
    states and the globals: ``k`` (N,) each one's knot, ``Ax`` (N, d), ``Ag`` (N, G). The
    chain's part ``Ax_a G_ka ... G_kb-1 Cov(x_kb) Ax_b^T`` (``gains``: :func:`chain_gains`'s;
    one product
    of gains between each two consecutive knots of ``k``, then one matrix per pair of them:
    for a few hundred functions, not for every knot), the globals' ``Z Z^T``,
    ``Z_i = Ax_i L_ki + Ag_i chol_g``."""
    k = np.asarray(k)
    u, of = np.unique(k, return_inverse=True)
    P = chain_products(gains, u[:-1], u[1:])
    out = np.zeros((k.size, k.size))
    for b in range(u.size):  # the knots in ``k``: a few dozen
        rb = np.flatnonzero(of == b)
        M = sol.cov_var[u[b]] @ Ax[rb].T  # Cov(x_ua, x_ub) Ax_b^T, from a = b down
        for a in range(b, -1, -1):
            if a < b:
                M = P[a] @ M
            ra = np.flatnonzero(of == a)
            out[np.ix_(ra, rb)] = Ax[ra] @ M
            out[np.ix_(rb, ra)] = out[np.ix_(ra, rb)].T
    Z = np.einsum("nd,ndg->ng", Ax, sol.factor[k]) + Ag @ sol.chol_g
    out += Z @ Z.T
    return 0.5 * (out + out.T)


def query_cross_covariance(sol: ArrowSolution, k_a: np.ndarray, J_a: np.ndarray,
                           k_b: np.ndarray, J_b: np.ndarray) -> np.ndarray:
    """``Cov(d_a, d_b)`` (N, 6, 6) of the right perturbations of query poses ``a`` and ``b``
    (``a`` in an earlier interval: ``k_a < k_b``), each the GP's interpolation of its
    interval ``k`` (N,) with Jacobian ``J`` (N, 6, 24) on the two knots' ``(d, dw)``
    (:func:`rtsgt.joint.interpolate.query_jacobians`). Within one interval the GP's own
    conditional variance would correlate them too: such pairs are an error here."""
    k_a, k_b = np.asarray(k_a), np.asarray(k_b)
    if np.any(k_a >= k_b):
        raise ValueError("Expected each pair's first pose in an earlier interval")
    gains = chain_gains(sol)  # the whole knot state's chain; the trajectory's part of it
    n = TRAJECTORY_DIM
    T1 = chain_products(gains, k_a + 1, k_b)  # knot k_a+1 to knot k_b
    C11 = T1 @ sol.cov_var[k_b]                            # (k_a+1, k_b)
    C12 = T1 @ gains[k_b] @ sol.cov_var[k_b + 1]           # (k_a+1, k_b+1)
    G0 = gains[k_a]
    C01, C02 = G0 @ C11, G0 @ C12                          # (k_a, k_b), (k_a, k_b+1)
    block = np.zeros((k_a.size, 2 * n, 2 * n))
    block[:, :n, :n], block[:, :n, n:] = C01[:, :n, :n], C02[:, :n, :n]
    block[:, n:, :n], block[:, n:, n:] = C11[:, :n, :n], C12[:, :n, :n]
    La = np.concatenate([sol.factor[k_a, :n], sol.factor[k_a + 1, :n]], axis=1)
    Lb = np.concatenate([sol.factor[k_b, :n], sol.factor[k_b + 1, :n]], axis=1)
    block += La @ np.swapaxes(Lb, 1, 2)
    return J_a @ block @ np.swapaxes(J_b, 1, 2)


def body_to_world(R: np.ndarray) -> np.ndarray:
    """``A = diag(R, R)`` (N, 6, 6) of poses ``R`` (N, 3, 3): a right (body) perturbation
    ``(rho, phi)`` as the world-frame ``(dt, dtheta)`` of :mod:`rtsgt.geometry.transform`
    (``dt = R rho``, ``dtheta = R phi`` to first order)."""
    A = np.zeros(R.shape[:1] + (6, 6))
    A[:, :3, :3] = A[:, 3:, 3:] = R
    return A


def world_covariance(R_a: np.ndarray, cov: np.ndarray, R_b: np.ndarray | None = None):
    """Covariance (N, 6, 6) of right perturbations of poses ``R_a`` (N, 3, 3) (and ``R_b``
    for a cross covariance) in the world frame: ``A_a cov A_b^T`` (:func:`body_to_world`)."""
    return body_to_world(R_a) @ cov @ np.swapaxes(body_to_world(R_a if R_b is None else R_b),
                                                  1, 2)


def origin_adjoint(origin: np.ndarray | None) -> np.ndarray:
    """``Ad(T_body_knot)`` (6, 6), ``T_body_knot = (I, origin)``: a right perturbation
    ``(rho, phi)`` of the knots' frame (the body's axes, its origin at ``origin`` (3,) m in
    the body frame; docs/joint.md#the-knots-origin) as the body frame's, ``rho + origin x
    phi``; the identity for None."""
    A = np.eye(6)
    if origin is not None:
        A[:3, 3:] = hat(origin)
    return A


def knots_to_body(R: np.ndarray, t: np.ndarray, cov: np.ndarray,
                  origin: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``t`` (Q, 3) of the knots' frame (rotations ``R`` (Q, 3, 3)) and the
    covariance ``cov`` (Q, 6, 6) of its right perturbation as the body frame's (``origin``:
    :func:`origin_adjoint`): ``t - R origin`` and ``A cov A^T``."""
    if origin is None:
        return t, cov
    A = origin_adjoint(origin)
    return t - R @ origin, A @ cov @ A.T


@dataclass(frozen=True)
class JointPosterior:
    """What the joint engine's poses at any time inside the knots need: knot times ``t_knot``
    (K,) s, poses ``R`` (K, 3, 3), ``t`` (K, 3), body velocities ``w`` (K, 6), the prior's
    ``qc`` (K-1, 6) per interval and the solution ``sol`` with its covariances; with the
    vehicle's rocking (docs/joint.md#the-vehicles-rocking) ``bridge`` (Q,) -> (Q, 6, 6) its
    variance in the knots' frame at query times between the knots (each pose's own: two
    poses' apart are independent given the knots); ``origin`` (3,) m the knots' frame's
    origin in the body frame (the prisms' centroid, docs/joint.md#the-knots-origin; None: the
    body frame's own): the poses it returns are the body frame's."""

    t_knot: np.ndarray
    R: np.ndarray
    t: np.ndarray
    w: np.ndarray
    qc: np.ndarray
    sol: ArrowSolution
    bridge: Callable[[np.ndarray], np.ndarray] | None = None
    origin: np.ndarray | None = None

    @property
    def span(self) -> tuple[float, float]:
        return float(self.t_knot[0]), float(self.t_knot[-1])

    def poses(self, t_query) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``R`` (Q, 3, 3), ``t`` (Q, 3) and the world-frame covariance (Q, 6, 6) at
        ``t_query`` (Q,) s inside :attr:`span`."""
        R, p, cov = interpolate_poses_gp(t_query, self.t_knot, self.R, self.t, self.w,
                                         self.qc, self.sol.cov, self.sol.cov_next)
        if self.bridge is not None:
            cov = cov + self.bridge(t_query)
        p, cov = knots_to_body(R, p, cov, self.origin)
        out = world_covariance(R, cov)
        return R, p, 0.5 * (out + np.swapaxes(out, 1, 2))

    def cross_covariance(self, t_a, t_b) -> np.ndarray:
        """World-frame ``Cov(xi(t_a), xi(t_b))`` (N, 6, 6) of pairs of times (N,) inside
        :attr:`span`, ``t_a < t_b``; two times in one interval between knots share its two
        knots' joint covariance (the GP's conditional part between them left out)."""
        k_a, R_a, _, J_a = query_jacobians(t_a, self.t_knot, self.R, self.t, self.w)
        k_b, R_b, _, J_b = query_jacobians(t_b, self.t_knot, self.R, self.t, self.w)
        out = np.zeros((k_a.size, 6, 6))
        apart = k_a < k_b
        if apart.any():
            out[apart] = query_cross_covariance(self.sol, k_a[apart], J_a[apart], k_b[apart],
                                                J_b[apart])
        same = ~apart
        if same.any():
            k, sol, n = k_a[same], self.sol, TRAJECTORY_DIM
            block = np.zeros((k.size, 2 * n, 2 * n))
            block[:, :n, :n], block[:, n:, n:] = sol.cov[k, :n, :n], sol.cov[k + 1, :n, :n]
            block[:, :n, n:] = sol.cov_next[k, :n, :n]
            block[:, n:, :n] = np.swapaxes(sol.cov_next[k, :n, :n], 1, 2)
            out[same] = J_a[same] @ block @ np.swapaxes(J_b[same], 1, 2)
        A = origin_adjoint(self.origin)
        return world_covariance(R_a, A @ out @ A.T, R_b)
