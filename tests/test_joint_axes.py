"""The motion prior's axes (rtsgt.joint.axes, docs/joint.md#the-motion-axes): the
measurements' Jacobian of the axes against finite differences, the body-frame solution
against a dense inverse, and a noise-free problem whose vehicle axes differ from the survey's.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from rtsgt.evaluation.joint_truth import JointGroundTruth
from rtsgt.geometry.so3 import exp_so3, hat
from rtsgt.joint import sparse
from rtsgt.joint.axes import body_qc, body_rotation, body_solution, velocities_in_body
from rtsgt.joint.deviation import n_coefficients
from rtsgt.joint.engine import assemble, gauss_newton, measurement_terms, retract
from rtsgt.joint.estimate import _body_knots
from rtsgt.joint.measurements import residual
from rtsgt.joint.relative import JointPosterior, world_covariance
from rtsgt.joint.sparse import solve_arrow
from test_joint import _synthetic

EPS = 1e-6
TILT = np.array([0.03, -0.02, 0.05])  # R_mb of these tests, rad
#: Relative tolerance against the dense inverse: the axes' broad prior beside millimetre
#: knots leaves the dense matrix ill-conditioned (its inverse good to a few 1e-6 here); a
#: wrong term of the map is off by its whole size.
TOL = 1e-4


def _problem(rng, deviation=False, noise=0.0):
    """The synthetic problem with the prisms as parameters (and their deviation), the
    motion axes estimated, and the truth's knots in axes turned by ``TILT`` from the body's."""
    coef = 1e-3 * rng.normal(size=(3, n_coefficients())) if deviation else None
    prob, truth = _synthetic(rng, noise=noise, moved=np.zeros(3), deviation=coef)
    prob = replace(prob, motion_axes=True)
    R_mb = exp_so3(TILT)
    truth = replace(truth, R=truth.R @ R_mb.T, R_mb=R_mb,
                    w=truth.w @ body_rotation(R_mb.T).T)
    return prob, truth


def test_measurement_jacobian_of_the_motion_axes_and_the_prisms_against_finite_differences():
    rng = np.random.default_rng(31)
    prob, s = _problem(rng, deviation=True)
    _, _, Hg = measurement_terms(prob, s)
    a = prob.axes_col
    for j in range(3):
        d = np.zeros(3)
        d[j] = EPS
        r = [measurement_terms(prob, replace(s, R_mb=s.R_mb @ exp_so3(sg * d)))[0]
             for sg in (1.0, -1.0)]
        np.testing.assert_allclose(-residual(r[0], r[1]) / (2 * EPS), Hg[:, :, a + j],
                                   atol=1e-7)
    c = prob.kappa_col + 1
    for j in range(9):  # the prisms' columns with the axes turned
        d = np.zeros(9)
        d[j] = EPS
        r = [measurement_terms(prob, replace(s, p_body=s.p_body + sg * d.reshape(3, 3)))[0]
             for sg in (1.0, -1.0)]
        np.testing.assert_allclose(-residual(r[0], r[1]) / (2 * EPS), Hg[:, :, c + j],
                                   atol=1e-7)


@pytest.mark.parametrize("chunk", [7, 2048])
def test_the_body_frame_solution_is_the_dense_inverse_mapped_to_the_body_frame(chunk,
                                                                                monkeypatch):
    """``M x_k + N_k a`` of every knot, mapped through the dense inverse of the normal
    equations: the covariances, consecutive cross covariances, the split's part given the
    globals and ``Cov(y_k, g)`` = factor chol_g^T (the factor turned a few knots at a time)."""
    monkeypatch.setattr(sparse, "CHUNK", chunk)  # the blocks of rtsgt.joint.sparse.chunks
    rng = np.random.default_rng(32)
    prob, truth = _problem(rng, noise=1.0)
    K = prob.t_knot.size
    start = retract(prob, truth, 1e-3 * rng.normal(size=(K, 12)),
                    1e-4 * rng.normal(size=prob.n_globals))
    system, _ = assemble(prob, start)
    sol = solve_arrow(system, want_cov=True)
    w_b = velocities_in_body(start.w, start.R_mb)
    out = body_solution(sol, start.R_mb, w_b, prob.axes_col)
    Mat, _ = system.dense()
    inv = np.linalg.inv(Mat)
    n, G = 12 * K, prob.n_globals
    T = np.zeros((n + G, n + G))  # the map to the body frame's perturbations, globals kept
    T[n:, n:] = np.eye(G)
    A = body_rotation(start.R_mb)
    for k in range(K):
        sl = slice(12 * k, 12 * k + 12)
        T[12 * k:12 * k + 6, 12 * k:12 * k + 6] = A
        T[12 * k + 6:12 * k + 12, 12 * k + 6:12 * k + 12] = A
        a = n + prob.axes_col
        T[12 * k + 3:12 * k + 6, a:a + 3] = np.eye(3)
        T[12 * k + 6:12 * k + 9, a:a + 3] = hat(w_b[k, :3])
        T[12 * k + 9:12 * k + 12, a:a + 3] = hat(w_b[k, 3:])
    ref = T @ inv @ T.T
    inv_a = np.linalg.inv(Mat[:n, :n])
    for k in range(K):
        sl = slice(12 * k, 12 * k + 12)
        blk = ref[sl, sl]
        np.testing.assert_allclose(out.cov[k], blk, atol=TOL * np.abs(blk).max())
        cross = out.factor[k] @ out.chol_g.T
        np.testing.assert_allclose(cross, ref[sl, n:], atol=TOL * np.abs(ref[sl, n:]).max())
        Mk = T[sl, sl]
        var = Mk @ inv_a[sl, sl] @ Mk.T
        np.testing.assert_allclose(out.cov_var[k], var, atol=TOL * np.abs(var).max())
        if k < K - 1:
            nxt = slice(12 * k + 12, 12 * k + 24)
            blk = ref[sl, nxt]
            np.testing.assert_allclose(out.cov_next[k], blk, atol=TOL * np.abs(blk).max())
    q = body_qc(np.tile([1.0, 2.0, 3.0, 4.0, 5.0, 6.0], (2, 1)), start.R_mb)
    np.testing.assert_allclose(q[0], A @ np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) @ A.T)


def test_a_noise_free_problem_in_turned_axes_gives_the_body_poses_back():
    """The vehicle's constant twist is one in any axes, so only the axes' prior decides
    them: from knots in axes turned by ``TILT`` (and a perturbed start), Gauss-Newton ends on
    the truth's body poses at no cost, the axes back at the survey's."""
    rng = np.random.default_rng(33)
    prob, truth = _problem(rng)
    K = prob.t_knot.size
    start = retract(prob, truth, 1e-4 * rng.normal(size=(K, 12)),
                    1e-5 * rng.normal(size=prob.n_globals))
    est, _, info = gauss_newton(prob, start, max_iter=20, tol=1e-14)
    assert info.converged and info.costs[0] > 0.1 and info.costs[-1] < 1e-8, info
    np.testing.assert_allclose(est.R @ est.R_mb, truth.R @ truth.R_mb, atol=1e-7)
    np.testing.assert_allclose(est.t, truth.t, atol=1e-7)
    np.testing.assert_allclose(est.R_mb, np.eye(3), atol=1e-6)


def _body_map(prob, s):
    """The dense map (n + G, n + G) of the knots' motion-frame perturbations and the globals
    to the body frame's (globals kept), as in :func:`rtsgt.joint.axes.body_solution`."""
    K, G = prob.t_knot.size, prob.n_globals
    n = 12 * K
    w_b = velocities_in_body(s.w, s.R_mb)
    A = body_rotation(s.R_mb)
    T = np.eye(n + G)
    a = n + prob.axes_col
    for k in range(K):
        T[12 * k:12 * k + 6, 12 * k:12 * k + 6] = A
        T[12 * k + 6:12 * k + 12, 12 * k + 6:12 * k + 12] = A
        T[12 * k + 3:12 * k + 6, a:a + 3] = np.eye(3)
        T[12 * k + 6:12 * k + 9, a:a + 3] = hat(w_b[k, :3])
        T[12 * k + 9:12 * k + 12, a:a + 3] = hat(w_b[k, 3:])
    return T


def test_poses_at_two_times_in_the_body_frame_equal_a_dense_inverse():
    """The run's continuous ground truth from the body-frame knots: at knot times its
    poses are the knots' times ``R_mb`` and its covariances and cross covariances the dense
    inverse's, mapped to the body frame and then to the world's."""
    rng = np.random.default_rng(34)
    prob, truth = _problem(rng, noise=1.0)
    s, sol, _ = gauss_newton(prob, truth, max_iter=20, tol=1e-14)
    system, _ = assemble(prob, s)
    Mat, _ = system.dense()
    T = _body_map(prob, s)
    cov = T @ np.linalg.inv(Mat) @ T.T
    prob = replace(prob, qc=np.broadcast_to(prob.qc, (prob.t_knot.size - 1, 6)))
    R_b, t_b, w_b, qc_b, sol_b = _body_knots(prob, s, sol)
    gt = JointGroundTruth(JointPosterior(prob.t_knot, R_b, t_b, w_b, qc_b, sol_b))
    a, b = np.array([2, 5, 11]), np.array([9, 6, 27])
    sample = gt.query_poses(prob.t_knot[a])
    np.testing.assert_allclose(sample.position, s.t[a], atol=1e-12)
    Caa, _, Cab = gt.pair_covariances(prob.t_knot[a], prob.t_knot[b])
    for i in range(3):
        for C, (x, y) in ((Caa[i], (a[i], a[i])), (Cab[i], (a[i], b[i]))):
            body = cov[12 * x:12 * x + 6, 12 * y:12 * y + 6]
            ref = world_covariance(R_b[x][None], body[None], R_b[y][None])[0]
            np.testing.assert_allclose(C, ref, atol=TOL * np.abs(ref).max())
