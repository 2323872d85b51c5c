"""The white-noise-on-acceleration prior on SE(3) between consecutive knots.

Right (body-frame) form of Anderson and Barfoot 2015: ``T = T_world_body``, ``T' = T exp(d^)``,
``w`` body-centric velocity (``dT/dt = T w^``). Error, Jacobians and weight:
docs/joint.md#the-motion-prior.
"""

from __future__ import annotations

import numpy as np

from rtsgt.joint.se3 import curly, jacobians_inv, log_se3

#: A knot's trajectory state ``(d, dw)``: the pose's right perturbation and the body
#: velocity's change; the first columns of every knot's state (others may follow it, e.g. the
#: Gauss-Markov noise's chains, :mod:`rtsgt.joint.gm`).
TRAJECTORY_DIM = 12


def wnoa_coef(dt: np.ndarray) -> np.ndarray:
    """``[[12/dt^3, -6/dt^2], [-6/dt^2, 4/dt]]`` (2, 2, K) of intervals ``dt`` (K,) s."""
    dt = np.asarray(dt, dtype=float)
    return np.stack([[12.0 / dt**3, -6.0 / dt**2], [-6.0 / dt**2, 4.0 / dt]])


def wnoa_q_inv(dt: np.ndarray, qc: np.ndarray) -> np.ndarray:
    """``Q(dt)^-1 = [[12/dt^3, -6/dt^2], [-6/dt^2, 4/dt]] (x) Qc^-1`` (K, 12, 12) for a diagonal
    ``Qc`` (6,) or one per interval (K, 6) (m^2/s^3, rad^2/s^3) and ``dt`` (K,) s (Barfoot
    eq. 11.25)."""
    dt = np.asarray(dt, dtype=float)
    qi = np.broadcast_to(1.0 / np.asarray(qc, dtype=float), (dt.shape[0], 6))
    out = np.einsum("abk,ki,ij->kaibj", wnoa_coef(dt), qi, np.eye(6))
    return out.reshape(dt.shape[0], 12, 12)


def relative_log(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``xi_k = log(T_k^-1 T_k+1)^v`` (K-1, 6) of poses ``R`` (K, 3, 3), ``t`` (K, 3)."""
    Rt = np.swapaxes(R[:-1], 1, 2)
    return log_se3(Rt @ R[1:], np.einsum("kij,kj->ki", Rt, t[1:] - t[:-1]))


def prior_terms(R: np.ndarray, t: np.ndarray, w: np.ndarray, dt: np.ndarray):
    """Error and Jacobians of the WNOA prior of every interval.

    ``e_k = [xi_k - dt w_k ; J_r(xi_k)^-1 w_k+1 - w_k]`` (K-1, 12); ``E`` (K-1, 12, 12) its
    Jacobian with respect to the state of knot k, ``(d_k, dw_k)``, ``F`` with respect to knot
    k+1. ``d J_r^-1(xi) w / d xi`` is taken as ``-w^curly / 2`` (first order in ``xi``).
    """
    xi = relative_log(R, t)
    jl_inv, jr_inv = jacobians_inv(xi)
    n = xi.shape[0]
    e = np.empty((n, 12))
    e[:, :6] = xi - dt[:, None] * w[:-1]
    e[:, 6:] = np.einsum("kij,kj->ki", jr_inv, w[1:]) - w[:-1]
    half_w = -0.5 * curly(w[1:])  # d (J_r^-1 w) / d xi
    eye = np.broadcast_to(np.eye(6), (n, 6, 6))
    E = np.zeros((n, 12, 12))
    F = np.zeros((n, 12, 12))
    E[:, :6, :6] = -jl_inv  # d xi / d d_k
    E[:, :6, 6:] = -dt[:, None, None] * eye
    E[:, 6:, :6] = -half_w @ jl_inv
    E[:, 6:, 6:] = -eye
    F[:, :6, :6] = jr_inv  # d xi / d d_k+1
    F[:, 6:, :6] = half_w @ jr_inv
    F[:, 6:, 6:] = jr_inv
    return e, E, F
