"""The motion prior's axes: the frame the WNOA prior is written in (diagonal ``Qc`` per
class), rotated from the survey's body frame by ``R_mb`` (``p_motion = R_mb p_body``), a
global parameter with a prior of a quarter of a degree; the knots are motion-frame poses,
turned back into the body frame here for the output: docs/joint.md#the-motion-axes.
"""

from __future__ import annotations

import numpy as np

from rtsgt.geometry.so3 import hat, log_so3
from rtsgt.joint.prior import TRAJECTORY_DIM
from rtsgt.joint.se3 import so3_left_jacobian
from rtsgt.joint.sparse import ArrowSolution, chunks

#: Prior sigma of each axis of ``R_mb`` about the identity, rad (a quarter of a degree): the
#: survey's axes are the vehicle's to its survey, and a vehicle rolls in turns and pitches
#: under acceleration, which a diagonal ``Qc`` does not model; chosen among 2, 5, 20 and
#: 100 mrad on development seeds (docs/joint.md#the-motion-axes).
AXES_SIGMA = 5e-3
#: The axes' prior sigma while a moved prism is searched for (rad): held at the body frame's,
#: the motion prior's frame lends the prisms' tests its power (solve_with_qc).
AXES_HELD_SIGMA = 1e-7


def axes_prior(R_mb: np.ndarray, sigma: float = AXES_SIGMA
               ) -> tuple[np.ndarray, np.ndarray, float]:
    """The prior's information (3, 3), gradient term (3,) (``J^T W e``) and cost for a right
    perturbation of ``R_mb`` (3, 3) about the identity with ``sigma`` rad per axis (rad^-2,
    rad^-1, chi^2)."""
    phi = log_so3(R_mb)
    J = so3_left_jacobian(-phi, inverse=True)  # d log(R exp(d)) / d d = J_r^-1(phi)
    w = 1.0 / sigma**2
    return w * J.T @ J, w * J.T @ phi, float(w * phi @ phi)


def body_rotation(R_mb: np.ndarray) -> np.ndarray:
    """``A = diag(R_mb^T, R_mb^T)`` (6, 6): a motion-frame right perturbation or velocity
    ``(rho, phi)`` as the body frame's (``T_body = T_motion (R_mb, 0)``)."""
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = R_mb.T
    return A


def velocities_in_body(w: np.ndarray, R_mb: np.ndarray) -> np.ndarray:
    """Body-frame velocities (K, 6) of motion-frame velocities ``w`` (K, 6) ``(v, omega)``."""
    return w @ body_rotation(R_mb).T


def body_qc(qc: np.ndarray, R_mb: np.ndarray) -> np.ndarray:
    """The prior's ``Qc`` (K-1, 6) per interval (motion axes, diagonal) as the body frame's
    (K-1, 6, 6) ``A diag(qc) A^T``."""
    A = body_rotation(R_mb)
    return np.einsum("ij,...j,lj->...il", A, qc, A)


def body_solution(sol: ArrowSolution, R_mb: np.ndarray, w_body: np.ndarray,
                  col: int) -> ArrowSolution:
    """``sol`` with its knots' trajectory states as the body frame's perturbations; its
    ``factor`` (K, d, G') is turned in place, a few thousand knots at a time (the hour's is
    the largest array of a run: the motion-frame solution is not read after this).

    A knot's body-frame perturbation is ``M x_k + N_k a``: ``M = diag(A, A, I)``
    (:func:`body_rotation`; the Gauss-Markov chains as they are), ``a`` the right
    perturbation of ``R_mb`` (globals ``col:col+3``), ``N_k`` (d, 3) its effect: the pose's
    rotation ``I`` and the velocities' ``(v_b^, omega_b^)`` (``w_body`` (K, 6) the body-frame
    velocities). The split follows: ``cov_var`` ``M . M^T`` (given the globals), ``factor``
    ``M L_k + N_k chol_g[a]``; ``cov``, ``cov_next`` from ``Cov(x_k, a) = L_k chol_g[a]^T``.
    The globals' ``g``, ``cov_g``, ``chol_g`` are kept."""
    K, d, _ = sol.cov.shape
    n = TRAJECTORY_DIM
    M = np.eye(d)
    A = body_rotation(R_mb)
    M[:6, :6] = M[6:n, 6:n] = A
    N = np.zeros((K, d, 3))
    N[:, 3:6, :] = np.eye(3)
    N[:, 6:9, :] = hat(w_body[:, :3])
    N[:, 9:n, :] = hat(w_body[:, 3:])
    c = sol.chol_g[col:col + 3]  # (3, G')
    X = np.empty((K, d, 3))  # Cov(x_k, a)
    factor = sol.factor
    for sl in chunks(K):
        f = factor[sl]
        X[sl] = f @ c.T
        f[:] = M @ f + N[sl] @ c

    def cross(cov_ab, X_a, X_b, N_a, N_b):  # Cov(M x_a + N_a a, M x_b + N_b a)
        out = M @ cov_ab @ M.T + M @ X_a @ _t(N_b) + N_a @ _t(X_b) @ M.T
        return out + N_a @ (c @ c.T) @ _t(N_b)

    cov = cross(sol.cov, X, X, N, N)
    return ArrowSolution(sol.x, sol.g, 0.5 * (cov + _t(cov)),
                         cross(sol.cov_next, X[:-1], X[1:], N[:-1], N[1:]), sol.cov_g,
                         M @ sol.cov_var @ M.T, M @ sol.cov_var_next @ M.T, factor, sol.chol_g)


def _t(a: np.ndarray) -> np.ndarray:
    return np.swapaxes(a, -1, -2)


__all__ = ["AXES_HELD_SIGMA", "AXES_SIGMA", "axes_prior", "body_qc", "body_rotation",
           "body_solution", "velocities_in_body"]
