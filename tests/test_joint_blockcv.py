"""Block cross-validation of the raw measurements (rtsgt.joint.blockcv): the deletion NEES
from the banded posterior against a dense inverse and against deleting the block and solving
again, and its verdict on honest and on too-small measurement covariances; the covariance of
distant knots and query poses (rtsgt.joint.relative) against a dense inverse."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from rtsgt.evaluation.joint_truth import JointGroundTruth
from rtsgt.joint import engine
from rtsgt.joint.blockcv import RawBlocks, raw_block_cv, raw_block_summary
from rtsgt.joint.engine import assemble, gauss_newton
from rtsgt.joint.relative import (
    JointPosterior,
    chain_gains,
    knot_cross_covariance,
    linear_covariance,
    query_cross_covariance,
    world_covariance,
)
from rtsgt.joint.sparse import mix_solutions
from rtsgt.stats import ratio_interval
from test_joint import _synthetic  # the joint tests' synthetic problem

#: The synthetic robot moves at constant velocity: a prior of (almost) no process noise is
#: its truth, so the held-out blocks' predictions are honest and informed by the prior.
QC_TRUE = np.full(6, 1e-8)
#: Blocks of 1 s and 2 s: these problems last 12-24 s (the algebra does not depend on it).
SHORT_BLOCKS_S = (1.0, 2.0)


def _dense_rows(prob, Hk, Hg):
    K, G, d = prob.t_knot.size, prob.n_globals, prob.knot_dim
    H = np.zeros((Hk.shape[0], 3, d * K + G))
    for m, k in enumerate(prob.of_meas):  # a small test problem
        H[m, :, d * k:d * k + d] = Hk[m]
        H[m, :, d * K:] = Hg[m]
    return H


@pytest.mark.parametrize("extra", [{}, {"clock_s": [0.0, 0.008, -0.005],
                                      "moved": [0.01, -0.02, 0.0]}])
def test_deletion_nees_equals_a_dense_inverse_and_a_solve_without_the_block(extra):
    """Without globals beyond the stations and the atmosphere, and with clock states at the
    knots and the prisms' positions among the globals."""
    rng = np.random.default_rng(31)
    prob, truth = _synthetic(rng, K=30, noise=1.0, **extra)
    prob = replace(prob, qc=QC_TRUE)
    s, sol, info = gauss_newton(prob, truth, max_iter=20, tol=1e-14)
    r, Hk, Hg = engine.measurement_terms(prob, s)
    m = prob.meas
    out = raw_block_cv(prob, s, sol, max_gap_s=5.0, lengths=SHORT_BLOCKS_S)
    assert out.n.sum() == m.t.size and out.nees.size >= 15
    system, _ = assemble(prob, s)
    N, _ = system.dense()
    cov = np.linalg.inv(N)
    H = _dense_rows(prob, Hk, Hg)
    R = np.linalg.inv(m.info)
    for b in range(out.nees.size):
        sel = np.flatnonzero((m.station == out.station[b]) & (m.t >= out.t0[b])
                             & (m.t <= out.t1[b]))
        assert sel.size == out.n[b]
        Hb = H[sel].reshape(-1, H.shape[2])
        Rb = np.zeros((3 * sel.size, 3 * sel.size))
        for i, j in enumerate(sel):
            Rb[3 * i:3 * i + 3, 3 * i:3 * i + 3] = R[j]
        e = r[sel].ravel()
        Q = Rb - Hb @ cov @ Hb.T
        ref = e @ np.linalg.solve(Q, e)
        assert out.nees[b] == pytest.approx(ref, rel=1e-7)
        for c in range(3):  # each channel's rows alone: their marginal covariance
            rows = np.arange(c, 3 * sel.size, 3)
            ref_c = e[rows] @ np.linalg.solve(Q[np.ix_(rows, rows)], e[rows])
            assert out.nees_channel[b, c] == pytest.approx(ref_c, rel=1e-6)
        if b % 4 == 0:  # deleted, solved again (one step: the problem is linear at s)
            Wb = np.linalg.inv(Rb)
            N_minus = N - Hb.T @ Wb @ Hb
            delta = np.linalg.solve(N_minus, -Hb.T @ Wb @ e)
            pred = e - Hb @ delta
            C = Rb + Hb @ np.linalg.solve(N_minus, Hb.T)
            assert out.nees[b] == pytest.approx(pred @ np.linalg.solve(C, pred), rel=1e-5)


def test_a_mixture_of_hypotheses_is_cross_validated_with_the_estimates_own_posterior():
    """With prism hypotheses carried (rtsgt.joint.sparse.mix_solutions), the deletion
    residuals are the estimate's least squares': the same NEES as its own solution's, where
    the mixture's spread (here 5 sigmas) would change them (on the real static stretches
    it made a channel's NEES negative: the deletion covariance indefinite)."""
    rng = np.random.default_rng(32)
    prob, truth = _synthetic(rng, K=30, noise=1.0)
    prob = replace(prob, qc=QC_TRUE)
    s, sol, _ = gauss_newton(prob, truth, max_iter=20, tol=1e-14)
    dx = 5.0 * np.sqrt(np.einsum("kii->ki", sol.cov))[None] * rng.choice([-1.0, 1.0],
                                                                          size=sol.x.shape)
    dg = 5.0 * np.sqrt(np.diag(sol.cov_g))[None]
    mixed = mix_solutions([sol, sol], np.array([0.5, 0.5]), dx, dg)
    own = raw_block_cv(prob, s, sol, max_gap_s=5.0, lengths=SHORT_BLOCKS_S)
    out = raw_block_cv(prob, s, mixed, max_gap_s=5.0, lengths=SHORT_BLOCKS_S)
    np.testing.assert_array_equal(out.nees, own.nees)
    assert np.all(own.nees > 0), own.nees.min()
    spread = raw_block_cv(prob, s, replace(mixed, own=None), max_gap_s=5.0,
                          lengths=SHORT_BLOCKS_S)
    change = np.abs(spread.nees / own.nees - 1.0)
    assert change.max() > 0.5, change.max()


def test_verdict_consistent_for_the_model_and_optimistic_for_noise_larger_than_stated():
    """Pooled over synthetic problems: noise as stated gives NEES/dof about 1; noise 1.5
    times the stated sigma (2.25 in variance) is caught."""
    def pooled(scale, seeds):
        rows = []
        for seed in seeds:
            rng = np.random.default_rng(seed)
            prob, truth = _synthetic(rng, K=60, noise=scale)
            prob = replace(prob, qc=QC_TRUE)
            s, sol, _ = gauss_newton(prob, truth, max_iter=20, tol=1e-12)
            rows.append(raw_block_cv(prob, s, sol, max_gap_s=5.0, lengths=SHORT_BLOCKS_S))
        return RawBlocks(*(np.concatenate([getattr(x, f) for x in rows])
                           for f in ("station", "t0", "t1", "n", "nees", "nees_channel")))

    honest = raw_block_summary(pooled(1.0, range(40, 52)), ("1", "2", "3"), warn=False)
    v = honest["overall"]
    lo, hi = ratio_interval(3.0 * 60 * 12)
    assert lo < v["nees_per_dof"] < hi, v
    assert v["verdict"] == "consistent"
    assert {c: x["verdict"] for c, x in honest["channels"].items()} == {
        "hz": "consistent", "v": "consistent", "d": "consistent"}, honest["channels"]
    small = raw_block_summary(pooled(1.5, range(60, 72)), ("1", "2", "3"), warn=False)
    assert small["overall"]["verdict"] == "optimistic", small["overall"]
    assert small["overall"]["nees_per_dof"] > 1.8
    assert all(x["verdict"] == "optimistic" for x in small["channels"].values())


def test_cross_covariance_of_distant_knots_and_queries_equals_a_dense_inverse():
    rng = np.random.default_rng(33)
    prob, truth = _synthetic(rng, K=30, noise=1.0, clock_s=[0.0, 0.004, -0.002])
    s, sol, _ = gauss_newton(prob, truth, max_iter=20, tol=1e-14)
    system, _ = assemble(prob, s)
    N, _ = system.dense()
    cov = np.linalg.inv(N)
    d, K = prob.knot_dim, prob.t_knot.size  # the trajectory's 12 and the clocks' 4
    k_a, k_b = np.array([0, 3, 7, 12, 20]), np.array([1, 3, 19, 28, 28])
    C = knot_cross_covariance(sol, chain_gains(sol), k_a, k_b)
    for i, (a, b) in enumerate(zip(k_a, k_b, strict=True)):
        ref = cov[d * a:d * a + d, d * b:d * b + d]
        np.testing.assert_allclose(C[i], ref, rtol=1e-5, atol=1e-5 * np.abs(ref).max())
    # consecutive knots: the solution's own cov_next, which rocking_step reads directly
    k = np.arange(K - 1)
    np.testing.assert_allclose(knot_cross_covariance(sol, chain_gains(sol), k, k + 1),
                               sol.cov_next, rtol=1e-8, atol=1e-10 * np.abs(sol.cov).max())
    for a in (0, 13, K - 2):
        ref = cov[d * a:d * a + d, d * (a + 1):d * (a + 2)]
        np.testing.assert_allclose(sol.cov_next[a], ref, rtol=1e-5,
                                   atol=1e-5 * np.abs(ref).max())
    # query poses: any Jacobians on their intervals' two knots' trajectories
    q_a, q_b = np.array([0, 4, 10]), np.array([2, 26, 28])
    J_a, J_b = rng.normal(size=(3, 6, 24)), rng.normal(size=(3, 6, 24))
    out = query_cross_covariance(sol, q_a, J_a, q_b, J_b)
    for i, (a, b) in enumerate(zip(q_a, q_b, strict=True)):
        ia, ib = (np.r_[d * k:d * k + 12, d * (k + 1):d * (k + 1) + 12] for k in (a, b))
        ref = J_a[i] @ cov[np.ix_(ia, ib)] @ J_b[i].T
        np.testing.assert_allclose(out[i], ref, rtol=1e-5, atol=1e-5 * np.abs(ref).max())
    # linear functions of knots' states and globals (the clocks' and settling's reports)
    k = np.array([3, 25, 3, 0, 10, 25])
    Ax = rng.normal(size=(k.size, d))
    Ag = rng.normal(size=(k.size, prob.n_globals))
    A = np.zeros((k.size, N.shape[0]))
    for i, j in enumerate(k):
        A[i, d * j:d * j + d], A[i, d * K:] = Ax[i], Ag[i]
    ref = A @ cov @ A.T
    np.testing.assert_allclose(linear_covariance(sol, chain_gains(sol), k, Ax, Ag), ref, rtol=1e-5,
                               atol=1e-6 * np.abs(ref).max())
    with pytest.raises(ValueError):
        query_cross_covariance(sol, q_b, J_b, q_a, J_a)


def test_joint_ground_truth_between_two_knot_times_equals_a_dense_inverse():
    """At knot times a query is its knot: its covariance and the cross covariance of two of
    them are the dense inverse's blocks, in the world frame."""
    rng = np.random.default_rng(35)
    prob, truth = _synthetic(rng, K=30, noise=1.0)
    s, sol, _ = gauss_newton(prob, truth, max_iter=20, tol=1e-14)
    system, _ = assemble(prob, s)
    N, _ = system.dense()
    cov = np.linalg.inv(N)
    qc = np.broadcast_to(prob.qc, (prob.t_knot.size - 1, 6))
    gt = JointGroundTruth(JointPosterior(prob.t_knot, s.R, s.t, s.w, qc, sol))
    a, b = np.array([2, 5, 11]), np.array([9, 6, 27])
    t_a, t_b = prob.t_knot[a], prob.t_knot[b]
    sample = gt.query_poses(np.r_[t_a, prob.t_knot[-1] + 1.0])
    assert list(sample.reason[:3]) == ["", "", ""] and sample.reason[3] != ""
    np.testing.assert_allclose(sample.position[:3], s.t[a], atol=1e-12)
    Caa, Cbb, Cab = gt.pair_covariances(t_a, t_b)
    for i in range(3):
        for C, (x, y) in ((Caa[i], (a[i], a[i])), (Cab[i], (a[i], b[i]))):
            body = cov[12 * x:12 * x + 6, 12 * y:12 * y + 6]
            ref = world_covariance(s.R[x][None], body[None], s.R[y][None])[0]
            np.testing.assert_allclose(C, ref, rtol=1e-5, atol=1e-5 * np.abs(ref).max())
