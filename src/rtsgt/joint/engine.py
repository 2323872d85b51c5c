"""Gauss-Newton on the manifold for the joint trajectory, stations and atmosphere.

State, factors, update and covariance: docs/joint.md#the-solver.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.geometry.so3 import exp_so3, log_so3
from rtsgt.joint.measurements import PolarMeasurements, predict, residual
from rtsgt.joint.prior import prior_terms, wnoa_q_inv
from rtsgt.joint.se3 import exp_se3, so3_left_jacobian
from rtsgt.joint.sparse import ArrowSystem, solve_arrow

#: Prior standard deviation (m, rad) given to a station direction its calibration fixes
#: exactly (a zero variance, e.g. the reference station).
FIXED_SIGMA = 1e-7


@dataclass(frozen=True)
class JointState:
    """Knot poses ``R`` (K, 3, 3), ``t`` (K, 3) (``T_world_body``), body velocities ``w``
    (K, 6); stations ``R_s`` (S, 3, 3), ``t_s`` (S, 3) (``T_world_station``); ``kappa_ppm``."""

    R: np.ndarray
    t: np.ndarray
    w: np.ndarray
    R_s: np.ndarray
    t_s: np.ndarray
    kappa_ppm: float


@dataclass(frozen=True)
class JointProblem:
    """What is fixed during the solve: knot times ``t_knot`` (K,), each measurement's knot
    ``of_meas`` and offset ``tau`` (M,), the measurements, the prisms' body positions
    ``p_body`` (P, 3), the stations' prior means ``R_prior``, ``t_prior`` and information
    ``info_prior`` (S, 6, 6) of ``(dt, dtheta)``, the free stations ``free`` (F,) indices,
    and ``qc`` (6,)."""

    t_knot: np.ndarray
    of_meas: np.ndarray
    tau: np.ndarray
    meas: PolarMeasurements
    p_body: np.ndarray
    R_prior: np.ndarray
    t_prior: np.ndarray
    info_prior: np.ndarray
    free: np.ndarray
    qc: np.ndarray

    @property
    def n_globals(self) -> int:
        return 6 * self.free.size + 1


def station_prior_info(cov: np.ndarray) -> np.ndarray:
    """Information (6, 6) of a station's calibration covariance, directions of zero variance
    held at :data:`FIXED_SIGMA`."""
    return np.linalg.inv(cov + FIXED_SIGMA**2 * np.eye(6))


def _measurement_terms(prob: JointProblem, s: JointState):
    m = prob.meas
    k = prob.of_meas
    h, Hk, Hs, Hkap = predict(s.R[k], s.t[k], s.w[k], prob.tau, prob.p_body[m.prism],
                              s.R_s[m.station], s.t_s[m.station], s.kappa_ppm)
    r = residual(m.y, h)
    Hg = np.zeros(r.shape + (prob.n_globals,))
    col = np.full(len(s.R_s), -1)
    col[prob.free] = np.arange(prob.free.size)
    c = col[m.station]
    rows = np.nonzero(c >= 0)[0]
    for j in range(6):  # six columns of each free station
        Hg[rows, :, 6 * c[rows] + j] = Hs[rows, :, j]
    Hg[:, :, -1] = Hkap
    return r, Hk, Hg


def _station_terms(prob: JointProblem, s: JointState):
    """Residuals (F, 6) and Jacobians (F, 6, 6) of the free stations' priors."""
    f = prob.free
    phi = log_so3(s.R_s[f] @ np.swapaxes(prob.R_prior[f], 1, 2))
    e = np.concatenate([s.t_s[f] - prob.t_prior[f], phi], axis=1)
    J = np.zeros((f.size, 6, 6))
    J[:, :3, :3] = np.eye(3)
    J[:, 3:, 3:] = so3_left_jacobian(phi, inverse=True)
    return e, J


def assemble(prob: JointProblem, s: JointState) -> tuple[ArrowSystem, float]:
    """The normal equations at ``s`` and the cost (sum of squared whitened errors)."""
    K = prob.t_knot.size
    G = prob.n_globals
    D = np.zeros((K, 12, 12))
    U = np.zeros((K - 1, 12, 12))
    a = np.zeros((K, 12))
    e, E, F = prior_terms(s.R, s.t, s.w, np.diff(prob.t_knot))
    W = wnoa_q_inv(np.diff(prob.t_knot), prob.qc)
    EtW, FtW = np.swapaxes(E, 1, 2) @ W, np.swapaxes(F, 1, 2) @ W
    D[:-1] += EtW @ E
    D[1:] += FtW @ F
    U += EtW @ F
    a[:-1] -= np.einsum("kij,kj->ki", EtW, e)
    a[1:] -= np.einsum("kij,kj->ki", FtW, e)
    cost = float(np.einsum("ki,kij,kj->", e, W, e))
    r, Hk, Hg = _measurement_terms(prob, s)
    info = prob.meas.info
    HtW = np.swapaxes(Hk, 1, 2) @ info
    np.add.at(D, prob.of_meas, HtW @ Hk)
    B = np.zeros((K, 12, G))
    np.add.at(B, prob.of_meas, HtW @ Hg)
    np.add.at(a, prob.of_meas, np.einsum("mij,mj->mi", HtW, r))
    GtW = np.swapaxes(Hg, 1, 2) @ info
    C = np.einsum("mgi,mih->gh", GtW, Hg)
    c = np.einsum("mgi,mi->g", GtW, r)
    cost += float(np.einsum("mi,mij,mj->", r, info, r))
    es, Js = _station_terms(prob, s)
    Wp = prob.info_prior[prob.free]
    JtW = np.swapaxes(Js, 1, 2) @ Wp
    for i in range(prob.free.size):  # a handful of stations
        sl = slice(6 * i, 6 * i + 6)
        C[sl, sl] += JtW[i] @ Js[i]
        c[sl] -= JtW[i] @ es[i]
    cost += float(np.einsum("fi,fij,fj->", es, Wp, es))
    sk = prob.meas.kappa_sigma_ppm
    C[-1, -1] += 1.0 / sk**2 if sk > 0 else 1.0 / FIXED_SIGMA**2
    c[-1] -= s.kappa_ppm / sk**2 if sk > 0 else 0.0
    cost += (s.kappa_ppm / sk) ** 2 if sk > 0 else 0.0
    return ArrowSystem(D, U, B, C, a, c), cost


def retract(prob: JointProblem, s: JointState, x: np.ndarray, g: np.ndarray) -> JointState:
    """``T_k exp(d_k^)``, ``w_k + dw_k``, ``t_s + dt``, ``exp(dtheta) R_s``, ``kappa + dk``."""
    dR, dp = exp_se3(x[:, :6])
    R = s.R @ dR
    t = s.t + np.einsum("kij,kj->ki", s.R, dp)
    R_s, t_s = s.R_s.copy(), s.t_s.copy()
    gs = g[:-1].reshape(-1, 6)
    t_s[prob.free] += gs[:, :3]
    R_s[prob.free] = exp_so3(gs[:, 3:]) @ R_s[prob.free]
    return JointState(R, t, s.w + x[:, 6:], R_s, t_s, s.kappa_ppm + float(g[-1]))


@dataclass(frozen=True)
class SolveInfo:
    """``iterations``, ``converged``, ``costs`` (one per iteration, the first at the start)."""

    iterations: int
    converged: bool
    costs: tuple[float, ...]


def gauss_newton(prob: JointProblem, s: JointState, max_iter: int = 10, tol: float = 1e-6):
    """Gauss-Newton from ``s`` until the predicted decrease of the cost is below ``tol``
    (a step that raises the cost is halved, up to 8 times). Returns the state, the knots'
    covariance (K, 12, 12) and the globals' (G, G) at it, and a :class:`SolveInfo`."""
    system, cost = assemble(prob, s)
    costs = [cost]
    converged = False
    for _ in range(max_iter):
        x, g, _, _ = solve_arrow(system)
        decrease = float(np.sum(x * system.a) + g @ system.c)
        step = 1.0
        for _ in range(8):
            trial = retract(prob, s, step * x, step * g)
            trial_system, trial_cost = assemble(prob, trial)
            if trial_cost <= cost + 1e-9 * abs(cost):
                break
            step *= 0.5
        s, system, cost = trial, trial_system, trial_cost
        costs.append(cost)
        if decrease < tol:
            converged = True
            break
    _, _, cov, cov_g = solve_arrow(system, want_cov=True)
    return s, cov, cov_g, SolveInfo(len(costs) - 1, converged, tuple(costs))


__all__ = ["JointProblem", "JointState", "SolveInfo", "assemble", "gauss_newton"]
