"""The ground truth's error split into a varying and a shared part, and the verdict built on it.

Layers: the shared factor against the per-source prism covariances the pipeline already has
and the split against the engines' total covariance (simulated deployment, stated
tolerances); the round trip through the run directory (exact); the split test's statistics on
a synthetic case with a known covariance (chi-square means, pooled over seeded draws); a
constant bias; the alignment's projection (invariance to a rigid offset, exact).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from rtsgt.app import read_ground_truth
from rtsgt.evaluation import ContinuousGroundTruth, evaluate
from rtsgt.evaluation.metrics import alignment_sensitivity, shared_error_test
from rtsgt.geometry.so3 import exp_so3, matrix_to_quat_xyzw, quat_xyzw_to_matrix
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import SPLIT_FILE, read_run, write_run
from rtsgt.pipeline import run_pipeline
from rtsgt.pose import estimate_poses
from rtsgt.pose.estimate import pose_jacobians
from rtsgt.pose.reference import block_diagonal
from rtsgt.shared import prism_shared_factor, select_prisms
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.types import PoseTrajectory


@pytest.fixture(scope="module")
def deployment(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("shared")
    sim = simulate_deployment(SimulationConfig(duration_s=90.0), np.random.default_rng(21))
    data, opts = load_deployment(write_deployment(sim, tmp / "dep"))
    return sim, data, opts, tmp


def _run(deployment, engine):
    _, data, opts, _ = deployment
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return run_pipeline(data, opts.updated(engine=engine, samples=300, seed=8))


@pytest.fixture(scope="module")
def runs(deployment):
    """The run of each engine, computed once for the module."""
    cache = {}

    def get(engine):
        if engine not in cache:
            cache[engine] = _run(deployment, engine)
        return cache[engine]
    return get


@pytest.fixture(scope="module")
def linear(runs):
    return runs("linear")


def _prism_factor(rec):
    c = rec.computation
    pr = c.prisms
    ids = list(c.tracks)
    vel = np.stack([c.gps[p].query(pr.t, with_velocity=True, allow_gaps=True).velocity
                    for p in ids], axis=1)
    origins = {s: T.translation for s, T in c.calibration.transforms.items()}
    F, names = prism_shared_factor(pr, vel, [c.tracks[p].station for p in ids], origins,
                                   rec.coupling)
    return pr, F, names


def test_the_factor_reproduces_each_sources_prism_covariance(linear):
    pr, F, names = _prism_factor(linear)
    n = pr.xyz.shape[1]
    assert {nm.split("_")[0] for nm in names} >= {"calibration", "time", "atmosphere"}
    for src in ("calibration", "time_sync", "atmosphere"):
        cols = [j for j, nm in enumerate(names) if nm.startswith(src)]
        for i in range(n):
            Fi = F[:, 3 * i:3 * i + 3][:, :, cols]
            diff = np.linalg.norm(Fi @ np.swapaxes(Fi, 1, 2) - pr.cov_by_source[src][:, i],
                                  axis=(1, 2))
            ref = np.linalg.norm(pr.cov_by_source[src][:, i], axis=(1, 2))
            total = np.linalg.norm(pr.cov[:, i], axis=(1, 2))
            if src == "time_sync":
                # rank one along the GP velocity, not the differenced measurements': they
                # disagree in direction only where the prism (nearly) stops
                assert np.median(diff / ref) < 1e-2, (src, i)
                assert np.all(diff <= 3e-2 * total), (src, i)
            else:
                # the calibration and the scale at the query position instead of the
                # measurement covariances interpolated between neighbours
                assert np.all(diff <= 2e-3 * ref), (src, i)


def test_the_shared_factor_is_zero_for_the_reference_stations_calibration(linear):
    # station 1 defines the world frame: no calibration parameter of its own
    assert not any(nm.startswith("calibration_station1") for nm in linear.groundtruth_split.names)
    assert "time_sync_station1" in linear.groundtruth_split.names


def varying_pose_covariance(prisms, reference, engine="linear", samples=1000, rng=None,
                            registration="weighted"):
    """The reference computation of ``V_i`` (T, 6, 6): the pose engine run again on the prisms'
    GP covariance alone, the reference exact, the weights those of the total (the run's fit)."""
    n = prisms.xyz.shape[1]
    est = estimate_poses(prisms.xyz, prisms.cov_gp, reference.xyz, np.zeros((3 * n, 3 * n)),
                         engine=engine, registration=registration,
                         weight_cov_q=prisms.pose_covariance, weight_cov_r=reference.cov,
                         samples=samples, rng=rng)
    return est.cov


@pytest.mark.parametrize("engine, tol_max, tol_median", [("linear", 2e-2, 2e-3),
                                                           ("ut", 2e-2, 2e-3),
                                                           ("mc", 0.35, 0.15)])
def test_varying_plus_shared_is_the_total_covariance(runs, engine, tol_max, tol_median):
    rec = runs(engine)
    sp = rec.groundtruth_split
    tot = rec.groundtruth.cov
    rel = np.linalg.norm(tot - sp.total_cov, axis=(1, 2)) / np.linalg.norm(tot, axis=(1, 2))
    # linear: the rank-one time-sync terms (above) are the only difference; mc: 300 samples
    assert rel.max() < tol_max and np.median(rel) < tol_median, (rel.max(), np.median(rel))
    assert np.all(np.linalg.eigvalsh(sp.varying_cov) > -1e-15)


@pytest.mark.parametrize("engine", ["linear", "ut", "mc"])
def test_the_varying_part_is_the_engine_free_first_order_propagation(runs, engine):
    # the split's fast path (the Jacobian of the shared factor, once) against the pose engine
    # run again on the GP part (the reference computation); the Monte Carlo engine's own run
    # used to be its sampling error (sqrt(2 / M)) away from it
    rec = runs(engine)
    c = rec.computation
    kept = select_prisms(c.prisms, np.flatnonzero(c.keep))
    ref = varying_pose_covariance(kept, rec.tracked_reference, "linear",
                                  registration=rec.options.pose.registration)
    V = rec.groundtruth_split.varying_cov
    s = np.sqrt(np.einsum("tii->ti", ref))
    assert np.max(np.abs(V - ref) / (s[:, :, None] * s[:, None, :])) < 1e-9


def test_a_monte_carlo_of_the_varying_part_agrees_with_its_first_order(linear):
    # what the split leaves out: the fit's nonlinearity over the GP part, far inside the
    # sampling error of a Monte Carlo of it (M = 4000 on 20 poses)
    c = linear.computation
    idx = np.flatnonzero(c.keep)[:: max(1, int(c.keep.sum()) // 20)][:20]
    kept = select_prisms(c.prisms, idx)
    args = (kept, linear.tracked_reference)
    reg = linear.options.pose.registration
    lin = varying_pose_covariance(*args, "linear", registration=reg)
    M = 4000
    mc = varying_pose_covariance(*args, "mc", samples=M, rng=np.random.default_rng(5),
                                 registration=reg)
    d = np.einsum("tii->ti", lin)
    z = (np.einsum("tii->ti", mc) - d) / (d * np.sqrt(2.0 / M))  # ~ N(0, 1) each
    assert np.max(np.abs(z)) < 5 and abs(np.mean(z)) < 0.6, (np.abs(z).max(), np.mean(z))


def test_selecting_every_pose_keeps_the_prisms_without_a_copy(linear):
    pr = linear.computation.prisms
    T = pr.t.shape[0]
    assert select_prisms(pr, np.ones(T, dtype=bool)) is pr
    assert select_prisms(pr, np.arange(T)) is pr
    back = select_prisms(pr, np.arange(T)[::-1])
    np.testing.assert_array_equal(back.xyz, pr.xyz[::-1])
    np.testing.assert_array_equal(back.cov_gp, pr.cov_gp[::-1])
    assert select_prisms(pr, np.arange(1, T)).t.shape == (T - 1,)


def test_the_linear_split_is_exact_given_the_factors_prism_covariance(linear):
    # linear engine: total - V - L L^T = J_q (C_systematic - F F^T) J_q^T exactly, the only
    # gap being the factor's rank-one time-sync terms checked above
    keep = linear.computation.keep
    pr, F, _ = _prism_factor(linear)
    sp = linear.groundtruth_split
    ref = linear.tracked_reference
    # the run's fit (weighted by default: its weights from the total covariance)
    J_q, _ = pose_jacobians(pr.xyz[keep], ref.xyz, linear.groundtruth.rotation,
                            registration=linear.options.pose.registration,
                            cov_q=pr.pose_covariance[keep], cov_r=ref.cov)
    gap = (pr.pose_covariance - block_diagonal(pr.cov_gp))[keep] - F[keep] @ np.swapaxes(
        F[keep], 1, 2)
    expected = J_q @ gap @ np.swapaxes(J_q, 1, 2)
    resid = linear.groundtruth.cov - sp.varying_cov - sp.shared_cov
    scale = np.linalg.norm(linear.groundtruth.cov, axis=(1, 2))
    assert np.all(np.linalg.norm(resid - expected, axis=(1, 2)) < 1e-9 * scale)


def test_the_split_round_trips_through_the_run_directory(deployment, linear):
    *_, tmp = deployment
    disk = read_run(write_run(linear, tmp / "run"))
    a, b = linear.groundtruth_split, disk.groundtruth_split
    assert (disk.path / SPLIT_FILE).is_file()
    assert b.names == a.names and len(b.names) == b.factor.shape[2]
    np.testing.assert_array_equal(b.t, a.t)
    np.testing.assert_allclose(b.factor, a.factor, rtol=1e-15, atol=0)
    np.testing.assert_allclose(b.varying_cov, a.varying_cov, rtol=1e-15, atol=0)
    # the continuous ground truth gives the same split at the run's own times
    gt = read_ground_truth(disk.path)
    again = gt.shared_split(a.t)
    assert again.names == a.names
    scale = np.abs(a.factor).max()
    np.testing.assert_allclose(again.factor, a.factor, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(again.varying_cov, a.varying_cov, rtol=1e-9,
                               atol=1e-9 * np.abs(a.varying_cov).max())


def test_an_older_run_without_the_file_has_no_split_and_the_old_verdict(deployment, linear):
    sim, *_, tmp = deployment
    run = write_run(linear, tmp / "old")
    (run / SPLIT_FILE).unlink()
    (run / ".rtsgt-output.json").unlink()  # the manifest lists the file
    assert read_run(run).groundtruth_split is None
    gt = read_ground_truth(run)
    assert gt.shared_split(linear.groundtruth.t) is None
    t = linear.groundtruth.t
    p, q = sim.truth_at(t)
    nees = evaluate(gt, PoseTrajectory(t, p, q), align="none").nees.pose
    assert nees.split is None
    d = nees.to_dict()
    assert "no shared factor" in d["verdict"] and "split" not in d


# ---------------------------------------------------------------------------------------------
# the split test on a synthetic case with a known covariance
# ---------------------------------------------------------------------------------------------


def _synthetic(seed=3, N=300, k=8):
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 60.0, N)
    pos = np.c_[10 * np.cos(t / 10), 8 * np.sin(t / 10), 0.1 * t]
    L = 1e-3 * (rng.standard_normal((N, 6, k)) * (1 + 0.5 * np.sin(t / 7))[:, None, None]
                + rng.standard_normal((1, 6, k)))
    B = 1e-3 * rng.standard_normal((N, 6, 6))
    D = B @ np.swapaxes(B, 1, 2) + 1e-7 * np.eye(6)
    return rng, pos, L, D


def _draws(rng, D, L, rho, n_draws, K=None):
    N = D.shape[0]
    Lc = np.linalg.cholesky(D)
    for _ in range(n_draws):
        w = rng.standard_normal((N, 6))
        if rho > 0:  # AR(1) correlation of the varying part between consecutive poses
            for i in range(1, N):
                w[i] = rho * w[i - 1] + np.sqrt(1 - rho * rho) * w[i]
        e = np.einsum("nij,nj->ni", Lc, w) + L @ rng.standard_normal(L.shape[2])
        if K is not None:
            e = e + K @ (0.01 * rng.standard_normal(K.shape[2]))
        yield e


@pytest.mark.parametrize("rho, align", [(0.0, "none"), (0.0, "se3"), (0.8, "none"),
                                        (0.8, "sim3"), (0.8, "4dof")])
def test_the_split_statistics_have_their_chi_square_means(rho, align):
    rng, pos, L, D = _synthetic()
    K = alignment_sensitivity(pos, align)
    shared, var3, var6, ok = [], [], [], []
    for e in _draws(rng, D, L, rho, 150, K):
        p3, p6 = shared_error_test(e, D, L, K)
        shared.append(p6.shared.statistic / p6.shared.dof)
        var3.append(p3.varying.mean / 3)
        var6.append(p6.varying.mean / 6)
        ok.append(p6.consistent)
    # 150 draws of chi2(8) / 8: sd of the mean 0.04; a ratio of 1.25 is 6 sd away
    assert abs(np.mean(shared) - 1) < 0.1, np.mean(shared)
    # the varying NEES, scaled by its exact expectation: sd of the mean below 0.01
    assert abs(np.mean(var3) - 1) < 0.03 and abs(np.mean(var6) - 1) < 0.03
    # each part at half the significance (5 %); the varying part's effective-sample-size test
    # is approximate under strong correlation (rho = 0.8: 10 poses per independent sample)
    assert np.mean(ok) >= (0.88 if rho == 0 else 0.8), np.mean(ok)


def test_a_shared_covariance_too_small_by_a_quarter_is_caught_by_the_pooled_statistic():
    rng, pos, L, D = _synthetic(seed=4)
    stat = [shared_error_test(e, D, L / np.sqrt(1.25))[1].shared
            for e in _draws(rng, D, L, 0.0, 150)]
    ratio = np.mean([s.statistic / s.dof for s in stat])
    assert ratio > 1.15, ratio


def test_a_constant_bias_is_detected():
    rng, pos, L, D = _synthetic(seed=5)
    bias = np.r_[0.01, 0.0, 0.0, 0.0, 0.0, 0.0]  # 1 cm, against ~1 mm shared and varying
    assert not any(shared_error_test(e + bias, D, L)[1].consistent
                   for e in _draws(rng, D, L, 0.5, 20))
    # a shared parameter 6 sigma off: the shared test catches it, the varying part is clean
    off = np.r_[6.0, np.zeros(L.shape[2] - 1)]
    res = [shared_error_test(e + L @ off, D, L)[1] for e in _draws(rng, D, L, 0.5, 20)]
    assert not any(r.shared.consistent for r in res)
    assert np.mean([r.varying.consistent for r in res]) >= 0.8


def test_the_alignment_projection_removes_exactly_a_rigid_offset():
    rng, pos, L, D = _synthetic(seed=6)
    e = next(_draws(rng, D, L, 0.5, 1))
    for align, m in (("se3", 6), ("sim3", 7), ("4dof", 4), ("scale", 1)):
        K = alignment_sensitivity(pos, align)
        assert K.shape == (len(pos), 6, m)
        a0 = shared_error_test(e, D, L, K)[1]
        a1 = shared_error_test(e + K @ (0.05 * rng.standard_normal(m)), D, L, K)[1]
        np.testing.assert_allclose(a1.shared.theta, a0.shared.theta, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(a1.varying.values, a0.varying.values, rtol=1e-6, atol=1e-9)
        assert a0.shared.absorbed == m
    # without the projection, the same offset is a shared error
    off = shared_error_test(e + alignment_sensitivity(pos, "se3") @ np.r_[0.02, 0, 0, 0, 0, 0],
                            D, L)[1]
    assert not off.consistent


def test_evaluate_a_rigidly_moved_truth_with_se3_alignment(deployment, linear):
    sim, *_ = deployment
    gt = ContinuousGroundTruth.from_record(linear)
    t = linear.groundtruth.t
    p, q = sim.truth_at(t)
    R = exp_so3(np.array([0.1, -0.2, 0.7]))
    tt = np.array([5.0, -3.0, 0.5])
    Rq = quat_xyzw_to_matrix(q)
    moved = PoseTrajectory(t, p @ R.T + tt, matrix_to_quat_xyzw(R @ Rq))
    a = evaluate(gt, PoseTrajectory(t, p, q), align="se3").nees.pose
    b = evaluate(gt, moved, align="se3").nees.pose
    assert a.split is not None and a.split.shared.absorbed == 6
    np.testing.assert_allclose(b.split.shared.statistic, a.split.shared.statistic, rtol=1e-5)
    assert b.consistent == a.consistent
    # the biased truth, unaligned, is inconsistent; its shared test says so
    biased = evaluate(gt, PoseTrajectory(t, p + np.r_[0.0, 0.01, 0.0], q), align="none")
    assert not biased.nees.pose.consistent and not biased.nees.pose.split.shared.consistent
    d = biased.to_dict()["nees"]["pose"]
    assert {"mean", "dof", "fraction_inside_95", "consistent", "split", "verdict"} <= set(d)
