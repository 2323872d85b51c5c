"""Uncertainty-aware evaluation: NEES and its consistency test, noise floor, relative-pose
covariance, association with an uncertain ground truth, and the errors on bad input."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy import stats

from rtsgt.errors import GeometryError, InputError, RtsgtWarning
from rtsgt.evaluation import EvaluationOptions, associate, evaluate
from rtsgt.evaluation.associate import PairCovarianceGroundTruth, interpolate_trajectory
from rtsgt.evaluation.metrics import (
    chain_cross_covariance,
    error_statistics,
    integrated_autocorrelation_time,
    nees_consistency,
    noise_floor,
    relative_pose_covariance,
    relative_poses,
    remove_floor,
    rpe_pairs,
    squared_mahalanobis,
)
from rtsgt.geometry.so3 import exp_so3
from rtsgt.geometry.transform import perturb, perturbation
from rtsgt.types import PoseTrajectory
from test_evaluation_synth import (
    perturbed,
    random_covariances,
    sample_xi,
    smooth_truth,
    trajectory,
    transform_trajectory,
)

# ----------------------------------------------------------------------------- statistics


def test_error_statistics_closed_form():
    s = error_statistics([3.0, 4.0, 0.0, 5.0])
    assert s["rmse"] == pytest.approx(np.sqrt(50 / 4))
    assert s["mean"] == 3.0 and s["median"] == 3.5 and s["min"] == 0.0 and s["max"] == 5.0
    assert s["std"] == pytest.approx(np.sqrt((0 + 1 + 9 + 4) / 4))  # population std


def test_chi2_quantiles_are_the_documented_ones():
    r3 = nees_consistency(np.full(10, 3.0), 3)
    r6 = nees_consistency(np.full(10, 6.0), 6)
    assert r3.quantile_95 == pytest.approx(7.815, abs=5e-4)
    assert r6.quantile_95 == pytest.approx(12.592, abs=5e-4)


def test_squared_mahalanobis_closed_form_and_error():
    S = np.diag([4.0, 9.0, 1.0])[None]
    assert squared_mahalanobis(np.array([[2.0, 3.0, 1.0]]), S)[0] == pytest.approx(3.0)
    with pytest.raises(ValueError, match="positive definite"):
        squared_mahalanobis(np.zeros((2, 3)), np.stack([np.eye(3), np.diag([1.0, 0.0, -1.0])]))


# ----------------------------------------------------------------------------- consistency test


def test_consistency_test_false_alarm_rate_is_alpha_for_independent_nees():
    """200 seeded replications of 500 chi2(6) values: the verdict rejects ~5 % (+ the
    fraction test), well under the 30 % a too-strict test would give."""
    rng = np.random.default_rng(5)
    rejections = sum(not nees_consistency(rng.chisquare(6, 500), 6).consistent for _ in range(200))
    assert rejections / 200 < 0.13


def test_consistency_test_is_robust_to_correlated_poses():
    """AR(1) errors (rho = 0.95) with the right marginal covariance: the textbook test (which
    assumes independence) rejects most replications; the effective-sample-size test does not."""
    rng = np.random.default_rng(6)
    n, rho, reps = 1500, 0.95, 60
    naive = robust = 0
    for _ in range(reps):
        w = rng.normal(size=(n, 3))
        x = np.empty_like(w)
        x[0] = w[0]
        for k in range(1, n):  # test data generation only
            x[k] = rho * x[k - 1] + np.sqrt(1 - rho**2) * w[k]
        nees = np.sum(x**2, axis=1)
        naive += not nees_consistency(nees, 3, correlated=False).consistent
        robust += not nees_consistency(nees, 3).consistent
    assert naive / reps > 0.4
    assert robust / reps < 0.2


def test_integrated_autocorrelation_time_of_ar1():
    """tau = (1 + rho) / (1 - rho) for an AR(1) series."""
    rng = np.random.default_rng(7)
    rho, n = 0.8, 200_000
    w = rng.normal(size=n)
    x = np.empty(n)
    x[0] = w[0]
    # AR(1) via lfilter (vectorised)
    from scipy.signal import lfilter

    x = lfilter([1.0], [1.0, -rho], w)
    assert integrated_autocorrelation_time(x) == pytest.approx((1 + rho) / (1 - rho), rel=0.1)
    assert integrated_autocorrelation_time(rng.normal(size=5000)) == pytest.approx(1.0, abs=0.1)


# ----------------------------------------------------------------------------- NEES end to end


@pytest.fixture(scope="module")
def truth():
    return smooth_truth(3000)


def test_nees_consistent_for_an_estimate_perturbed_with_known_covariance(truth):
    """Ground truth = truth + N(0, Sigma_gt); estimate = truth + N(0, Sigma_est) in another
    frame, reporting Sigma_est in its own frame. S = Sigma_gt + Sigma_est (mapped by the
    alignment) makes both NEES chi-square: consistent, mean ~ dof, 95 % inside."""
    t, p, R = truth
    rng = np.random.default_rng(11)
    n = len(t)
    cov_gt = random_covariances(n, rng, 2e-3, 5e-4)
    cov_est = random_covariances(n, rng, 8e-3, 3e-3)
    gt = perturbed(t, p, R, cov_gt, rng)
    est_world = perturbed(t, p, R, cov_est, rng)
    Ra = exp_so3([0.4, -0.3, 2.0])
    est = transform_trajectory(est_world, Ra, np.array([3.0, 1.0, -2.0]))
    res = evaluate(gt, est, align="se3", delta=10, delta_unit="f")
    for r, dof in ((res.nees.position, 3), (res.nees.pose, 6)):
        assert r.consistent, r.to_dict()
        assert r.mean == pytest.approx(dof, rel=0.06)
        assert r.fraction_inside_95 == pytest.approx(0.95, abs=0.015)
    assert "estimate" in res.nees.covariance
    # the estimate's covariance really was mapped into the world frame: the same data with
    # the covariance left in the estimate's frame is far from chi-square
    unmapped = PoseTrajectory(est.t, est.position, est.quat_xyzw, est_world.cov)
    bad = evaluate(
        gt,
        transform_trajectory(unmapped, np.eye(3), np.zeros(3)),
        align="se3",
        delta=10,
        delta_unit="f",
    )
    assert bad.nees.position.mean > 1.2 * 3 or not bad.nees.position.consistent


def test_nees_inconsistent_for_biased_or_overconfident_estimates(truth):
    t, p, R = truth
    rng = np.random.default_rng(12)
    n = len(t)
    cov_gt = random_covariances(n, rng, 2e-3, 5e-4)
    gt = perturbed(t, p, R, cov_gt, rng)
    perfect = trajectory(t, p, R)
    ok = evaluate(gt, perfect, align="none", delta=10, delta_unit="f")
    assert ok.nees.position.consistent and ok.nees.pose.consistent
    # biased: a constant 6 mm offset with no alignment to absorb it
    biased = trajectory(t, p + [0.006, 0.0, 0.0], R)
    r = evaluate(gt, biased, align="none", delta=10, delta_unit="f")
    assert not r.nees.position.consistent and r.nees.position.mean > 3.5
    # biased but slowly varying, so that an SE(3) alignment cannot remove it
    wobble = 0.006 * np.c_[np.sin((t - t[0]) / 7), np.cos((t - t[0]) / 11), 0 * t]
    r = evaluate(gt, trajectory(t, p + wobble, R), align="se3", delta=10, delta_unit="f")
    assert not r.nees.position.consistent
    # over-confident: errors of 2x the stated standard deviations
    cov_est = random_covariances(n, rng, 5e-3, 1e-3)
    est = perturbed(t, p, R, 4 * cov_est, rng, report=cov_est)
    r = evaluate(gt, est, align="se3", delta=10, delta_unit="f")
    assert not r.nees.pose.consistent and r.nees.pose.mean > 12
    assert r.nees.pose.fraction_inside_95 < 0.8
    # under-confident: states 4x its variance
    est = perturbed(t, p, R, cov_est, rng, report=4 * cov_est)
    r = evaluate(gt, est, align="se3", delta=10, delta_unit="f")
    assert not r.nees.pose.consistent and r.nees.pose.mean < 4


def test_noise_floor_is_the_ape_of_a_perfect_estimate(truth):
    """A perfect estimate's APE rmse equals sqrt(mean tr Sigma_gt) (statistically), and the
    floor-removed rmse recovers the estimate's own error."""
    t, p, R = truth
    rng = np.random.default_rng(13)
    cov_gt = random_covariances(len(t), rng, 3e-3, 5e-4)
    gt = perturbed(t, p, R, cov_gt, rng)
    r = evaluate(gt, trajectory(t, p, R), align="none", delta=10, delta_unit="f")
    f = r.noise_floor
    assert f.ape_translation_m == pytest.approx(noise_floor(cov_gt[:, :3, :3]))
    assert r.ape.translation_m.rmse == pytest.approx(f.ape_translation_m, rel=0.03)
    assert f.ape_translation_rmse_floor_removed_m < 0.3 * f.ape_translation_m
    assert r.ape.rotation_deg.rmse == pytest.approx(f.ape_rotation_deg, rel=0.03)
    # an estimate with its own isotropic 10 mm error per axis: rms norm 17.3 mm
    est = trajectory(t, p + rng.normal(0, 0.01, p.shape), R)
    r = evaluate(gt, est, align="none", delta=10, delta_unit="f")
    assert r.noise_floor.ape_translation_rmse_floor_removed_m == pytest.approx(
        0.01 * np.sqrt(3), rel=0.03
    )
    assert remove_floor(1.0, 2.0) == 0.0


# ----------------------------------------------------------------------------- relative poses


def test_relative_pose_covariance_matches_monte_carlo():
    """First-order covariance of T_i^-1 T_j (with a cross-covariance) against sampling."""
    rng = np.random.default_rng(21)
    Ri, Rj = exp_so3([0.3, -0.5, 1.2]), exp_so3([0.1, 0.2, 1.9])
    ti, tj = np.array([1.0, 2.0, 0.5]), np.array([3.0, -1.0, 0.8])
    A = rng.normal(size=(12, 12)) * np.r_[[3e-3] * 3, [1e-3] * 3, [3e-3] * 3, [1e-3] * 3][:, None]
    J = A @ A.T
    M = 100_000
    xi = rng.multivariate_normal(np.zeros(12), J, size=M)
    Rsi, tsi = perturb(Ri, ti, xi[:, :6])
    Rsj, tsj = perturb(Rj, tj, xi[:, 6:])
    R_rel = np.swapaxes(Rsi, -1, -2) @ Rsj
    t_rel = np.einsum("kba,kb->ka", Rsi, tsj - tsi)
    R0, t0 = relative_poses(np.stack([Ri, Rj]), np.stack([ti, tj]), np.array([[0, 1]]))
    emp = np.cov(perturbation(R0[0], t0[0], R_rel, t_rel).T)
    lin = relative_pose_covariance(
        Ri[None], ti[None], tj[None], J[None, :6, :6], J[None, 6:, 6:], J[None, :6, 6:]
    )[0]
    assert np.linalg.norm(emp - lin) / np.linalg.norm(lin) < 0.03
    indep = relative_pose_covariance(
        Ri[None], ti[None], tj[None], J[None, :6, :6], J[None, 6:, 6:]
    )[0]
    assert np.linalg.norm(indep - lin) / np.linalg.norm(lin) > 0.05  # the cross term matters


def test_chain_cross_covariance_equals_the_dense_gauss_markov_covariance():
    rng = np.random.default_rng(22)
    M = 8
    A = [np.eye(6) * 0.9 + 0.05 * rng.normal(size=(6, 6)) for _ in range(M - 1)]
    Q = [(lambda B: B @ B.T)(0.1 * rng.normal(size=(6, 6))) for _ in range(M - 1)]
    # dense joint covariance of x_{k+1} = A_k x_k + w_k
    G = np.zeros((6 * M, 6 * M))
    F = [np.eye(6)]
    for k in range(M - 1):
        F.append(A[k] @ F[-1])
    P0 = (lambda B: B @ B.T)(rng.normal(size=(6, 6)))

    # x_k = F_k x_0 + sum_m Phi(k, m+1) w_m
    def phi(k, m):
        out = np.eye(6)
        for s in range(m, k):
            out = A[s] @ out
        return out

    for a in range(M):
        for b in range(M):
            c = F[a] @ P0 @ F[b].T
            for m in range(min(a, b)):
                c = c + phi(a, m + 1) @ Q[m] @ phi(b, m + 1).T
            G[6 * a : 6 * a + 6, 6 * b : 6 * b + 6] = c
    P = np.stack([G[6 * k : 6 * k + 6, 6 * k : 6 * k + 6] for k in range(M)])
    C = np.stack([G[6 * k : 6 * k + 6, 6 * k + 6 : 6 * k + 12] for k in range(M - 1)])
    pairs = np.array([[0, 1], [0, 5], [2, 7], [3, 4], [1, 6]])
    got = chain_cross_covariance(P, C, pairs)
    for (i, j), g in zip(pairs, got, strict=True):
        ref = G[6 * i : 6 * i + 6, 6 * j : 6 * j + 6]
        np.testing.assert_allclose(g, ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())


def _ar1_ground_truth(truth, a, rng, n=None):
    """Ground-truth errors correlated in time: xi_{k+1} = a xi_k + w (stationary cov P)."""
    t, p, R = truth
    n = len(t) if n is None else n
    t, p, R = t[:n], p[:n], R[:n]
    L = np.diag(np.r_[[3e-3] * 3, [1e-3] * 3])
    P = L @ L.T
    w = sample_xi(np.broadcast_to((1 - a * a) * P, (n, 6, 6)), rng)
    from scipy.signal import lfilter

    xi = lfilter([1.0], [1.0, -a], w, axis=0)
    xi[0] = sample_xi(P[None], rng)[0]
    xi[1:] = lfilter([1.0], [1.0, -a], np.r_[[a * xi[0] + w[1]], w[2:]], axis=0)
    Rn, pn = perturb(R, p, xi)
    cov = np.broadcast_to(P, (n, 6, 6)).copy()
    cross = np.broadcast_to(a * P, (n - 1, 6, 6)).copy()
    return trajectory(t, pn, Rn, cov), cross, (t, p, R)


def test_rpe_nees_uses_the_ground_truth_correlations(truth):
    """Strongly correlated ground-truth errors: the relative pose is far more certain than
    two independent poses. With the cross-covariances (discrete or from a query) the relative
    NEES is chi-square; assuming independence it is far too small (inconsistent)."""
    rng = np.random.default_rng(23)
    gt, cross, (t, p, R) = _ar1_ground_truth(truth, 0.97, rng, 2000)
    perfect = trajectory(t, p, R)
    with_c = evaluate(gt, perfect, align="none", delta=1, delta_unit="f", gt_cross_next=cross)
    assert with_c.nees.rpe_correlations == "provided"
    assert with_c.nees.relative_pose.mean == pytest.approx(6, rel=0.08)
    assert with_c.nees.relative_pose.consistent
    without = evaluate(gt, perfect, align="none", delta=1, delta_unit="f")
    assert "independent" in without.nees.rpe_correlations
    assert without.nees.relative_pose.mean < 1.0 and not without.nees.relative_pose.consistent
    # delta of 3 frames: chained cross-covariances (exact for this Markov sequence)
    d3 = evaluate(gt, perfect, align="none", delta=3, delta_unit="f", gt_cross_next=cross)
    assert d3.nees.relative_position.mean == pytest.approx(3, rel=0.1)

    # the same through a continuous-time query returning its cross-covariances
    def query(times):
        idx = np.searchsorted(gt.t, times)
        sub = PoseTrajectory(gt.t[idx], gt.position[idx], gt.quat_xyzw[idx], gt.cov[idx])
        return sub, cross[idx[:-1]]

    q = evaluate(query, perfect, align="none", delta=1, delta_unit="f", gt_measurement_times=gt.t)
    assert q.nees.relative_pose.mean == pytest.approx(with_c.nees.relative_pose.mean, rel=1e-9)


def test_rpe_pairs_by_seconds():
    t = np.arange(0, 10.01, 0.1)
    p = np.zeros((t.size, 3))
    pairs = rpe_pairs(p, t, 1.0, "s")
    np.testing.assert_allclose(t[pairs[:, 1]] - t[pairs[:, 0]], 1.0, atol=1e-9)
    assert pairs.shape[0] == 10
    t = t + np.random.default_rng(0).uniform(0, 0.05, t.size)  # jittered times
    allp = rpe_pairs(p, t, 1.0, "s", all_pairs=True)
    # brute force: for every i the first j > i closest to 1 s, kept within 10 %
    ref = []
    for i in range(t.size - 1):
        d = np.abs((t[i + 1 :] - t[i]) - 1.0)
        j = int(np.argmin(d))
        if d[j] <= 0.1:
            ref.append((i, i + 1 + j))
    np.testing.assert_array_equal(allp, np.array(ref))
    with pytest.raises(ValueError, match="integer"):
        rpe_pairs(p, t, 1.5, "f")


def _path_of_steps(step: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Positions (N + 1, 3) whose consecutive distances are ``step`` (random directions)."""
    d = rng.normal(size=(step.size, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    return np.concatenate([[np.zeros(3)], np.cumsum(d * step[:, None], axis=0)])


@pytest.mark.parametrize("ulps", [0, 1, 3])
def test_rpe_pairs_resolve_ties_to_reaching_delta(ulps):
    """A path since the last selected pose equal to delta up to rounding reaches delta: 10 steps
    of 0.1 m against 1 m give a pair every 10 steps, however the step lengths round (here: each
    0.1 m step moved by up to ``ulps`` units in the last place, up or down, as different BLAS
    kernels or norms would), and the same for times at 10 Hz on an epoch clock. A path short
    of delta by far more than rounding (1e-7 relative) is not a tie."""
    rng = np.random.default_rng(3)
    for trial in range(20):
        step = np.full(300, 0.1)
        if ulps:
            step = step + rng.integers(-ulps, ulps + 1, step.size) * np.spacing(0.1)
        # stationary stretches (zero steps) must not change the pairs either
        step = np.insert(step, rng.integers(0, 300, 30), 0.0)
        p = _path_of_steps(step, rng)
        cum = np.concatenate([[0.0], np.cumsum(np.hypot.reduce(np.diff(p, axis=0), axis=1))])
        for delta, every in ((1.0, 10), (0.3, 3), (2.0, 20)):
            pairs = rpe_pairs(p, None, delta, "m")
            # the selected poses are the first at each multiple of delta (0.1 m units)
            units = np.round(cum[pairs.ravel()] / 0.1).astype(int).reshape(-1, 2)
            np.testing.assert_array_equal(units[:, 1] - units[:, 0], every, err_msg=str(trial))
            assert pairs.shape[0] == 300 // every
            moving = np.r_[True, np.diff(np.round(cum / 0.1)) > 0]
            assert np.all(moving[pairs[:, 1]])  # never a pose later on a stationary stretch
    short = _path_of_steps(np.full(300, 0.1 * (1 - 1e-7)), rng)
    pairs = rpe_pairs(short, None, 1.0, "m")
    np.testing.assert_array_equal(np.diff(pairs, axis=1), 11)
    t0 = 1_668_095_037.0
    for trial in range(20):
        k = np.arange(301)
        t = t0 + k * 0.1 + rng.integers(-ulps, ulps + 1, k.size) * np.spacing(t0)
        pairs = rpe_pairs(np.zeros((t.size, 3)), t, 1.0, "s")
        np.testing.assert_array_equal(pairs[:, 0], np.arange(0, 300, 10), err_msg=str(trial))
        np.testing.assert_array_equal(pairs[:, 1], np.arange(10, 301, 10))
    t = t0 + np.arange(301) * 0.1 * (1 - 1e-5)
    np.testing.assert_array_equal(np.diff(rpe_pairs(np.zeros((301, 3)), t, 1.0, "s")), 11)


# ----------------------------------------------------------------------------- association


def test_interpolation_is_linear_and_slerp_and_flags_covariances():
    t = np.array([0.0, 1.0, 2.0])
    p = np.array([[0.0, 0, 0], [1.0, 2, 0], [1.0, 2, 4]])
    R = exp_so3(np.array([[0, 0, 0.0], [0, 0, 1.0], [0, 0, 1.0]]))
    cov = np.stack([np.eye(6), 3 * np.eye(6), np.eye(6)])
    gt = trajectory(t, p, R, cov)
    pos, rot, c, exact, f = interpolate_trajectory(gt, np.array([0.25, 1.0, 1.5]))
    np.testing.assert_allclose(pos, [[0.25, 0.5, 0], [1, 2, 0], [1, 2, 2]], atol=1e-15)
    np.testing.assert_allclose(rot[0], exp_so3([0, 0, 0.25]), atol=1e-14)
    np.testing.assert_allclose(c[0], 1.5 * np.eye(6))
    np.testing.assert_array_equal(exact, [-1, 1, -1])
    est = trajectory(np.array([0.25, 1.0, 1.5]), pos, rot)
    a = associate(gt, est)
    np.testing.assert_array_equal(a.cov_interpolated, [True, False, True])


def test_association_drops_poses_outside_and_in_gaps():
    t = np.r_[np.arange(0, 5, 0.1), np.arange(8, 10, 0.1)]  # a 3 s gap in the ground truth
    n = t.size
    gt = trajectory(t, np.c_[t, 0 * t, 0 * t], np.broadcast_to(np.eye(3), (n, 3, 3)))
    te = np.arange(-1.0, 11.0, 0.25)
    est = trajectory(te, np.c_[te, 0 * te, 0 * te], np.broadcast_to(np.eye(3), (te.size, 3, 3)))
    a = associate(gt, est, max_dt=0.3)
    assert a.n_outside == np.count_nonzero((te < 0) | (te > t[-1] + 1e-9))
    assert np.all((a.est.t < 5.3) | (a.est.t > 7.7))
    assert a.n_gap > 0 and len(a) + a.n_gap + a.n_outside == te.size


def test_query_ground_truth_with_measurement_times(truth):
    t, p, R = truth
    cov = random_covariances(len(t), np.random.default_rng(3))
    calls = []

    def query(times):
        calls.append(times.copy())
        pos, rot, c, _, _ = interpolate_trajectory(trajectory(t, p, R, cov), times)
        return trajectory(times, pos, rot, c)

    est = trajectory(t[::7] + 0.02, p[::7], R[::7])
    r = evaluate(query, est, gt_measurement_times=t[100:2000], max_dt=0.2)
    assert calls and calls[0].min() >= t[100] and calls[0].max() <= t[1999]
    assert r.ape.translation_m.rmse < 0.05
    assert not r.association.cov_interpolated.any()


# ----------------------------------------------------------------------------- bad input


def test_bad_input_gives_clear_errors(truth):
    t, p, R = truth
    gt = trajectory(t[:200], p[:200], R[:200])
    late = trajectory(t[:200] + 1e4, p[:200], R[:200])
    with pytest.raises(InputError, match="No time overlap"):
        evaluate(gt, late)
    few = trajectory(t[:2], p[:2], R[:2])
    with pytest.raises(InputError, match="at least 3 associated poses"):
        evaluate(gt, few, align="se3", delta=1, delta_unit="f")
    q = trajectory(t[:200], p[:200], R[:200]).quat_xyzw * 1.1
    with pytest.raises(InputError, match="unit estimate quaternions"):
        evaluate(gt, PoseTrajectory(t[:200], p[:200], q))
    pn = p[:200].copy()
    pn[17, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        evaluate(gt, trajectory(t[:200], pn, R[:200]))
    with pytest.raises(InputError, match="strictly increasing"):
        evaluate(gt, trajectory(t[:200][::-1], p[:200], R[:200]))
    line = trajectory(t[:50], np.c_[t[:50] - t[0], 0 * t[:50], 0 * t[:50]], R[:50])
    with pytest.raises(GeometryError, match="collinear"):
        evaluate(line, line, align="se3", delta=1, delta_unit="f")
    with pytest.raises(InputError, match="alignment"):
        evaluate(gt, gt, align="7dof")
    with pytest.raises(InputError, match="max_dt"):
        evaluate(gt, trajectory(t[:200] + 0.05, p[:200], R[:200]), max_dt=0.01)


def test_nees_section_is_null_without_ground_truth_covariance(truth):
    t, p, R = truth
    r = evaluate(trajectory(t[:300], p[:300], R[:300]), trajectory(t[:300], p[:300], R[:300]))
    d = r.to_dict()
    assert d["nees"]["position"] == {
        "mean": None,
        "dof": 3,
        "fraction_inside_95": None,
        "consistent": None,
    }
    assert d["noise_floor"]["ape_translation_m"] is None
    assert r.ape.translation_m.max < 1e-9
    # consistent with the chi2 helper of scipy for dof checks
    assert stats.chi2.ppf(0.95, 3) == pytest.approx(7.8147, abs=1e-4)


def test_no_rpe_pair_still_gives_ape_and_nees_and_says_why(truth):
    """A robot that moved less than the RPE delta: APE and NEES, no RPE, and the reason."""
    t, p, R = truth
    cov = random_covariances(len(t), np.random.default_rng(5))
    gt = trajectory(t, p, R, cov)
    est = trajectory(t[:30], p[:30], R[:30])
    moved = float(np.sum(np.linalg.norm(np.diff(p[:30], axis=0), axis=1)))
    r = evaluate(gt, est, delta=100.0, delta_unit="m")
    assert r.rpe is None
    assert "100 m" in r.rpe_absent_reason and f"{moved:.3g} m" in r.rpe_absent_reason
    assert r.ape.translation_m.max < 1e-9 and r.nees.position.n == 30
    assert r.nees.relative_pose is None and r.noise_floor.rpe_translation_m is None
    d = r.to_dict()
    assert d["rpe"]["n_pairs"] == 0 and d["rpe"]["translation_m"] is None
    assert d["rpe"]["absent_reason"] == r.rpe_absent_reason
    assert d["nees"]["relative_position"]["mean"] is None and d["nees"]["pose"]["mean"] > 0
    for delta, unit, what in ((50, "f", "30 associated poses"), (10.0, "s", "2.9 s")):
        r = evaluate(gt, est, delta=delta, delta_unit=unit)
        assert r.rpe is None and what in r.rpe_absent_reason
    assert evaluate(gt, est, delta=1.0).to_dict()["rpe"]["absent_reason"] is None


def test_rpe_pairs_across_a_ground_truth_gap_are_counted_in_a_warning(truth):
    """A 10 s hole in a discrete ground truth: the RPE pairs reaching into it (an end pose
    interpolated across it, or the ends on both sides) are counted, with the longest gap; the
    pairs stay evo's (not excluded). Gaps within the limit are not."""
    t, p, R = truth
    s = t - t[0]
    hole = (s > 30.05) & (s < 40.05)  # ground-truth samples 30.0 and 40.1 s: a 10.1 s gap
    gt = trajectory(t[~hole], p[~hole], R[~hole])
    est = trajectory(t[:600], p[:600], R[:600])
    with pytest.warns(RtsgtWarning) as rec:
        r = evaluate(gt, est, align="none", delta=5.0, delta_unit="m", max_dt=0.5)
    msgs = [str(w.message) for w in rec if issubclass(w.category, RtsgtWarning)]
    assert len(msgs) == 1
    ti, tj = r.t[r.rpe.pairs[:, 0]] - t[0], r.t[r.rpe.pairs[:, 1]] - t[0]
    n_in = np.count_nonzero((tj > 30.05) & (ti < 40.05))  # the pairs overlapping the hole
    assert np.count_nonzero((ti < 30.6) & (tj > 39.5)) == 1  # one across the dropped poses
    n = r.rpe.pairs.shape[0]
    assert msgs[0].startswith(f"{n_in} of {n} RPE pairs span a gap of the ground truth (gap "
                              "limit 0.5 s; longest 10.1 s")
    # an estimate that has no pose in the hole either (nothing dropped): the samples' spacing
    cut = ~hole[:600]
    lost = trajectory(t[:600][cut], p[:600][cut], R[:600][cut])
    with pytest.warns(RtsgtWarning, match="longest 10.1 s"):
        r = evaluate(gt, lost, align="none", delta=5.0, delta_unit="m", max_dt=0.5)
    assert r.association.n_gap == 0
    # no gap; a hole within twice the limit (every pose within max_dt of a sample); a sparse
    # estimate (keyframes 0.7 s apart) on a dense ground truth; no limit: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error", RtsgtWarning)
        evaluate(trajectory(t, p, R), est, align="none", delta=5.0, delta_unit="m")
        evaluate(gt, est, align="none", delta=5.0, delta_unit="m", max_dt=5.1)
        sparse = trajectory(t[:600:7], p[:600:7], R[:600:7])
        evaluate(trajectory(t, p, R), sparse, delta=5.0, delta_unit="m", max_dt=0.06)
        evaluate(gt, est, align="none", delta=5.0, delta_unit="m", max_dt=None)


# ----------------------------------------------------------------------------- options record


@pytest.mark.parametrize("field, value, match", [
    ("align", "7dof", "alignment"),
    ("n_align", 0, "n_align"),
    ("delta", 0.0, "positive RPE delta"),
    ("delta", np.nan, "positive RPE delta"),
    ("delta_unit", "km", "delta unit"),
    ("rel_delta_tol", -0.1, "rel_delta_tol"),
    ("time_offset", np.inf, "finite time offset"),
    ("max_dt", -1.0, "positive max_dt"),
])
def test_evaluation_options_check_every_value(field, value, match):
    with pytest.raises(InputError, match=match):
        EvaluationOptions(**{field: value})


def test_evaluation_options_check_combinations_and_allow_no_limit():
    with pytest.raises(InputError, match="integer RPE delta in frames"):
        EvaluationOptions(delta=1.5, delta_unit="f")
    assert EvaluationOptions(max_dt=None).max_dt is None


def test_evaluate_takes_an_options_record_or_its_fields(truth):
    t, p, R = truth
    gt = trajectory(t[:300], p[:300], R[:300])
    est = trajectory(t[:300], p[:300] + 0.01 * np.sin(t[:300, None]), R[:300])
    by_fields = evaluate(gt, est, align="sim3", delta=5, delta_unit="f").to_dict()
    options = EvaluationOptions(align="sim3", delta=5, delta_unit="f")
    assert evaluate(gt, est, options).to_dict() == by_fields
    assert evaluate(gt, est, EvaluationOptions(align="none"), align="sim3", delta=5,
                    delta_unit="f").to_dict() == by_fields
    with pytest.raises(TypeError):
        evaluate(gt, est, no_such_option=1)


def test_pair_covariance_ground_truth_is_an_explicit_capability():
    class Pairs:
        def pair_covariances(self, tau_a, tau_b):
            return np.eye(6)[None], np.eye(6)[None], np.zeros((1, 6, 6))

    assert isinstance(Pairs(), PairCovarianceGroundTruth)
    assert not isinstance(trajectory(np.arange(3.0), np.zeros((3, 3)), np.stack([np.eye(3)] * 3)),
                          PairCovarianceGroundTruth)
