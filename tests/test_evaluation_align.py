"""Alignment: Umeyama SE(3)/Sim(3), 4-DOF yaw, weighted variant, origin, n_align, errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from rtsgt.errors import GeometryError, InputError
from rtsgt.evaluation.align import align_trajectories, align_yaw, alignment_weights, umeyama
from rtsgt.geometry.so3 import exp_so3
from rtsgt.types import PoseTrajectory
from test_evaluation_synth import random_covariances, smooth_truth, trajectory, transform_trajectory


@pytest.fixture(scope="module")
def truth():
    return smooth_truth(800)


def test_umeyama_recovers_an_exact_similarity(truth):
    t, p, R = truth
    Ra = exp_so3([0.7, -0.2, 2.5])
    ta = np.array([4.0, -1.0, 2.0])
    x = p
    y = 1.7 * x @ Ra.T + ta
    R_, t_, s_ = umeyama(x, y, with_scale=True)
    np.testing.assert_allclose(R_, Ra, atol=1e-12)
    np.testing.assert_allclose(t_, ta, atol=1e-10)
    assert s_ == pytest.approx(1.7, rel=1e-12)
    R_, t_, s_ = umeyama(x, x @ Ra.T + ta)
    assert s_ == 1.0
    np.testing.assert_allclose(R_, Ra, atol=1e-12)


def test_weighted_umeyama_minimises_the_weighted_cost(truth):
    """The closed form equals a generic numerical minimiser of sum w |y - (sRx + t)|^2."""
    t, p, R = truth
    rng = np.random.default_rng(1)
    x = p[::20]
    y = x @ exp_so3([0.1, 0.2, 0.3]).T + 1.0 + rng.normal(0, 0.2, x.shape)
    w = rng.uniform(0.1, 5.0, x.shape[0])
    R_, t_, s_ = umeyama(x, y, w, with_scale=True)

    def cost(v):
        return np.sum(w * np.sum((y - (v[6] * x @ exp_so3(v[:3]).T + v[3:6])) ** 2, axis=1))

    from rtsgt.geometry.so3 import log_so3

    v0 = np.r_[log_so3(R_), t_, s_]
    best = minimize(cost, v0 + 0.01, method="BFGS", options={"gtol": 1e-10})
    assert cost(v0) <= best.fun + 1e-9
    # and the weights matter: the unweighted solution has a higher weighted cost
    Ru, tu, su = umeyama(x, y, with_scale=True)
    from rtsgt.geometry.so3 import log_so3 as lg

    assert cost(np.r_[lg(Ru), tu, su]) > cost(v0)


def test_4dof_alignment_recovers_yaw_only_and_keeps_roll_pitch(truth):
    t, p, R = truth
    yaw = exp_so3([0, 0, -2.2])
    ta = np.array([10.0, -5.0, 0.3])
    gt = trajectory(t, p, R)
    est = transform_trajectory(gt, yaw.T, -yaw.T @ ta)  # est = T^-1 gt
    al = align_trajectories(gt, est, method="4dof")
    np.testing.assert_allclose(al.rotation, yaw, atol=1e-12)
    np.testing.assert_allclose(al.translation, ta, atol=1e-10)
    # closed form agrees with a numerical minimiser on noisy data
    rng = np.random.default_rng(2)
    y = p + rng.normal(0, 0.3, p.shape)

    def cost(v):
        return np.sum((y - (p @ exp_so3([0, 0, v[0]]).T + v[1:])) ** 2)

    R4, t4 = align_yaw(p, y)
    v0 = np.r_[np.arctan2(R4[1, 0], R4[0, 0]), t4]
    assert cost(v0) <= minimize(cost, v0 + 0.01, method="BFGS").fun + 1e-9
    # a tilted estimate: 4dof cannot remove roll, se3 can
    tilt = exp_so3([0.1, 0, 0])
    est_t = transform_trajectory(gt, tilt, np.zeros(3))
    a4 = align_trajectories(gt, est_t, method="4dof")
    np.testing.assert_allclose(a4.rotation[2], [0, 0, 1], atol=1e-15)
    a6 = align_trajectories(gt, est_t, method="se3")
    np.testing.assert_allclose(a6.rotation, tilt.T, atol=1e-10)


def test_weighted_alignment_down_weights_uncertain_poses(truth):
    """Poses whose ground truth is 100x less certain carry large errors: the weighted fit
    ignores them, the unweighted fit is pulled."""
    t, p, R = truth
    rng = np.random.default_rng(3)
    n = len(t)
    cov = random_covariances(n, rng, 1e-3, 1e-4)
    bad = np.zeros(n, dtype=bool)
    bad[::5] = True
    cov[bad] *= 1e4
    gt_pos = p.copy()
    gt_pos[bad] += rng.normal(0, 0.5, (bad.sum(), 3))
    gt = trajectory(t, gt_pos, R, cov)
    est = trajectory(t, p, R)
    aw = align_trajectories(gt, est, method="se3", weighted=True)
    au = align_trajectories(gt, est, method="se3")
    err_w = np.linalg.norm(aw.translation) + np.linalg.norm(aw.rotation - np.eye(3))
    err_u = np.linalg.norm(au.translation) + np.linalg.norm(au.rotation - np.eye(3))
    assert err_w < 0.1 * err_u
    np.testing.assert_allclose(
        alignment_weights(cov[:3]), 1 / np.trace(cov[:3, :3, :3], axis1=1, axis2=2)
    )


def test_n_align_and_origin(truth):
    t, p, R = truth
    gt = trajectory(t, p, R)
    drift = np.c_[np.linspace(0, 5, len(t)), 0 * t, 0 * t]
    est = trajectory(t, p + drift, R)
    a = align_trajectories(gt, est, method="se3", n_align=20)
    assert a.n_used == 20
    full = align_trajectories(gt, est, method="se3")
    # aligned on the start only: the start matches better than with the full fit
    e20 = np.linalg.norm(a.apply(est).position[:20] - p[:20], axis=1).max()
    ef = np.linalg.norm(full.apply(est).position[:20] - p[:20], axis=1).max()
    assert e20 < 0.2 * ef
    o = align_trajectories(
        gt, transform_trajectory(gt, exp_so3([0, 0, 1]), np.ones(3)), method="origin"
    )
    np.testing.assert_allclose(o.rotation, exp_so3([0, 0, -1]), atol=1e-12)


def test_covariance_is_mapped_with_the_alignment(truth):
    """Sampling: a cloud of estimate poses mapped by the alignment has covariance J C J^T."""
    from rtsgt.evaluation.align import Alignment
    from rtsgt.geometry.transform import perturb, perturbation

    rng = np.random.default_rng(4)
    C = random_covariances(1, rng, 1e-2, 1e-2)[0]
    R0, t0 = exp_so3([0.3, 0.1, -0.4]), np.array([1.0, 2.0, 3.0])
    al = Alignment("sim3", exp_so3([0.5, -1.0, 2.0]), np.array([3.0, 0, 1]), 1.4)
    xi = rng.multivariate_normal(np.zeros(6), C, 50000)
    Rs, ts = perturb(R0, t0, xi)
    pa, Ra = al.apply_pose(ts, Rs)
    pm, Rm = al.apply_pose(t0[None], R0[None])
    emp = np.cov(perturbation(Rm[0], pm[0], Ra, pa).T)
    mapped = al.apply_covariance(C)
    assert np.linalg.norm(emp - mapped) / np.linalg.norm(mapped) < 0.03


def test_alignment_errors(truth):
    t, p, R = truth
    gt = trajectory(t[:2], p[:2], R[:2])
    with pytest.raises(InputError, match="at least 3"):
        align_trajectories(gt, gt, method="sim3")
    with pytest.raises(InputError, match="covariances"):
        align_trajectories(trajectory(t, p, R), trajectory(t, p, R), weighted=True)
    vertical = PoseTrajectory(
        t[:10], np.c_[0 * t[:10], 0 * t[:10], t[:10] - t[0]], np.tile([0, 0, 0, 1.0], (10, 1))
    )
    with pytest.raises(GeometryError, match="horizontal"):
        align_trajectories(vertical, vertical, method="4dof")
    with pytest.raises(GeometryError, match="collinear"):
        umeyama(vertical.position, vertical.position)
    with pytest.raises(InputError, match="alignment"):
        align_trajectories(gt, gt, method="affine")
