"""Evaluation against a position-only ground truth (rtsgt.evaluation.positions, lever_arm):
closed forms and synthetic trajectories with known truth.

The simulated single-prism deployments (the acceptance of issue 14, item 2) are in
``test_positions_pipeline.py``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from rtsgt.errors import GeometryError, InputError
from rtsgt.evaluation import evaluate_positions
from rtsgt.evaluation.lever_arm import (
    lever_arm_factor,
    lever_arm_points,
    parse_lever_arm,
    point_covariance,
)
from rtsgt.evaluation.positions import ROTATION_NOT_REPORTED, align_points
from rtsgt.geometry.transform import perturb
from rtsgt.types import PositionTrajectory
from test_evaluation_synth import (
    random_covariances,
    sample_xi,
    smooth_truth,
    trajectory,
    transform_trajectory,
)

#: NTU VIRAL's published body-to-prism lever arm (m).
LEVER = np.array([-0.2937, -0.0123, -0.2731])
#: A sensor frame turned half a turn about z (and slightly tilted) from the body frame.
R_MOUNT = Rotation.from_euler("zyx", [np.pi, 0.02, -0.01]).as_matrix()


def _truth(n=2000):
    t, p, R = smooth_truth(n)
    return t, p, R @ R_MOUNT  # the sensor's orientation


def _gt(t, p, R, rng, sig=(3e-3, 3e-3, 6e-3), lever=LEVER):
    """The prism with Gaussian errors of a known, rotated anisotropic covariance."""
    Q = Rotation.from_euler("z", 0.6).as_matrix()
    cov = np.broadcast_to(Q @ np.diag(np.square(sig)) @ Q.T, (t.size, 3, 3)).copy()
    y = p + R @ lever
    noise = np.einsum("ij,nj->ni", np.linalg.cholesky(cov[0]), rng.normal(size=(t.size, 3)))
    return PositionTrajectory(t, y + noise, cov, "prism 1"), y


def test_lever_arm_jacobian_is_the_derivative():
    """J_pose = [I, -[R l]x] and J_lever = R against central differences of p + R l."""
    rng = np.random.default_rng(0)
    R = Rotation.random(5, random_state=1).as_matrix()
    p = rng.normal(size=(5, 3))
    pts = lever_arm_points(p, R, LEVER)
    np.testing.assert_allclose(pts.position, p + np.einsum("nij,j->ni", R, LEVER))
    h = 1e-6
    for k in range(6):
        xi = np.zeros((5, 6))
        xi[:, k] = h
        Rp, pp = perturb(R, p, xi)
        Rm, pm = perturb(R, p, -xi)
        d = (lever_arm_points(pp, Rp, LEVER).position
             - lever_arm_points(pm, Rm, LEVER).position) / (2 * h)
        np.testing.assert_allclose(pts.jacobian_pose[:, :, k], d, atol=1e-8)
    for k in range(3):
        dl = np.zeros(3)
        dl[k] = h
        d = (lever_arm_points(p, R, LEVER + dl).position
             - lever_arm_points(p, R, LEVER - dl).position) / (2 * h)
        np.testing.assert_allclose(pts.jacobian_lever[:, :, k], d, atol=1e-8)


def test_point_covariance_and_lever_factor_match_sampling():
    """J Sigma J^T is the covariance of the point of perturbed poses (first order: 1e-3 rad
    perturbations), and R A_l A_l^T R^T that of a perturbed lever arm."""
    rng = np.random.default_rng(2)
    R = Rotation.random(1, random_state=3).as_matrix()
    p = rng.normal(size=(1, 3))
    cov = random_covariances(1, rng, sig_pos=2e-3, sig_rot=1e-3)
    pts = lever_arm_points(p, R, LEVER)
    M = 40000
    xi = sample_xi(np.broadcast_to(cov[0], (M, 6, 6)), rng)
    Rs, ps = perturb(np.broadcast_to(R[0], (M, 3, 3)), np.broadcast_to(p[0], (M, 3)), xi)
    emp = np.cov(lever_arm_points(ps, Rs, LEVER).position.T)
    C = point_covariance(pts, cov)[0]
    # standard error of a sample covariance entry: sqrt((C_ii C_jj + C_ij^2) / M); 5 of them
    se = np.sqrt((np.outer(np.diag(C), np.diag(C)) + C**2) / M)
    assert np.all(np.abs(emp - C) < 5 * se), (emp - C) / se
    C_l = np.diag([1e-4, 4e-4, 9e-4])
    F = lever_arm_factor(pts, C_l)[0]
    np.testing.assert_allclose(F @ F.T, R[0] @ C_l @ R[0].T, atol=1e-15)


def test_parse_lever_arm():
    np.testing.assert_allclose(parse_lever_arm("-0.2937, -0.0123,-0.2731"), LEVER)
    np.testing.assert_allclose(parse_lever_arm(None), 0.0)
    for bad in ("1,2", "a,b,c", "1,2,nan"):
        with pytest.raises(InputError, match="lever arm"):
            parse_lever_arm(bad)


@pytest.mark.parametrize("method, scale", [("se3", 1.0), ("4dof", 1.0), ("sim3", 0.8),
                                           ("scale", 1.25)])
def test_alignment_of_the_points_recovers_a_known_transform(method, scale):
    """Noise-free: the estimate in a frame moved by a known transform (and, for sim3 and
    scale, a scale that does not apply to the metric lever arm) is mapped back exactly."""
    t, p, R = _truth(600)
    y = p + R @ LEVER
    est = trajectory(t, p, R)
    if method == "4dof":
        Ra, ta = Rotation.from_euler("z", 2.4).as_matrix(), np.array([5.0, -3.0, 0.7])
    elif method == "scale":
        Ra, ta = np.eye(3), np.zeros(3)
    else:
        Ra, ta = Rotation.from_euler("zyx", [2.4, 0.3, -0.2]).as_matrix(), np.array([5., -3, .7])
    moved = transform_trajectory(est, Ra, ta, scale)
    al = align_points(y, moved.position, moved.rotation, LEVER, method=method)
    back = al.apply(moved)
    np.testing.assert_allclose(back.position + back.rotation @ LEVER, y, atol=1e-9)
    np.testing.assert_allclose(al.scale, 1.0 / scale, rtol=1e-10)


def test_alignment_refuses_what_needs_an_orientation():
    with pytest.raises(InputError, match="no orientation"):
        align_points(np.zeros((5, 3)), np.zeros((5, 3)), np.broadcast_to(np.eye(3), (5, 3, 3)),
                     LEVER, method="origin")
    t, p, R = _truth(50)
    line = np.c_[np.linspace(0, 10, 50), np.zeros(50), np.zeros(50)]
    Rs = np.broadcast_to(np.eye(3), (50, 3, 3))
    with pytest.raises(GeometryError):
        align_points(line, line, Rs, np.zeros(3), method="se3")


def test_exact_estimate_against_an_exact_ground_truth():
    """APE 0 with the right lever arm; with the lever arm left out, the APE is its length
    (the rotation of the sensor then hides in a wrong point)."""
    t, p, R = _truth(500)
    gt = PositionTrajectory(t, p + R @ LEVER)
    est = trajectory(t, p, R)
    r = evaluate_positions(gt, est, LEVER, align="none")
    assert r.ape.translation_m.max < 1e-12 and r.rpe.translation_m.max < 1e-12
    assert r.nees.position is None and r.noise_floor.ape_translation_m is None
    r0 = evaluate_positions(gt, est, None, align="none")
    np.testing.assert_allclose(r0.ape.translation_error, np.linalg.norm(LEVER), rtol=1e-12)


def test_nees_of_an_estimate_equal_to_the_truth_is_chi2_3():
    """Ground-truth errors drawn from its covariance: NEES / dof near 1 and 95 % inside,
    with the alignments a position-only ground truth allows."""
    t, p, R = _truth()
    est = trajectory(t, p, R)
    for seed, method in enumerate(("none", "se3", "sim3", "4dof")):
        gt, _ = _gt(t, p, R, np.random.default_rng(10 + seed))
        moved = est if method == "none" else transform_trajectory(
            est, Rotation.from_euler("z", 1.0).as_matrix(), np.array([1.0, 2.0, 0.0]))
        r = evaluate_positions(gt, moved, LEVER, align=method)
        n = r.nees.position
        # 2000 independent chi2(3) values: mean within +-0.055 (3 sigma), 95 % within +-1.5 %
        assert abs(n.mean / 3 - 1) < 0.055, (method, n.mean)
        assert abs(n.fraction_inside_95 - 0.95) < 0.015, (method, n.fraction_inside_95)
        assert n.consistent, method
        assert r.nees.pose is None and r.nees.relative_pose is None


def test_estimate_covariance_enters_through_the_lever_arm():
    """An estimate whose poses are off by xi ~ N(0, P) (rotation errors of 3 mrad, which
    move the prism by about 1.2 mm through a 0.4 m lever arm): with P in S the NEES is chi2(3);
    without its rotation block the errors are too large for S."""
    rng = np.random.default_rng(5)
    t, p, R = _truth()
    gt, _ = _gt(t, p, R, rng, sig=(1e-3, 1e-3, 1e-3))
    P = random_covariances(t.size, rng, sig_pos=1e-3, sig_rot=3e-3)
    Rn, pn = perturb(R, p, sample_xi(P, rng))
    r = evaluate_positions(gt, trajectory(t, pn, Rn, P), LEVER, align="none")
    assert abs(r.nees.position.mean / 3 - 1) < 0.06, r.nees.position.mean
    assert "lever arm" in r.nees.covariance
    P_pos = P.copy()
    P_pos[:, 3:, :] = 0.0
    P_pos[:, :, 3:] = 0.0
    P_pos[:, 3:, 3:] = np.eye(3) * 1e-18
    r2 = evaluate_positions(gt, trajectory(t, pn, Rn, P_pos), LEVER, align="none")
    assert r2.nees.position.mean > 1.3 * r.nees.position.mean
    assert not r2.nees.position.consistent


def test_relative_nees_with_independent_ground_truth_positions():
    """Pooled over draws, the RPE pairs' NEES against P_i + P_j is chi2(3)."""
    t, p, R = _truth()
    est = trajectory(t, p, R)
    vals = []
    for seed in range(8):
        gt, _ = _gt(t, p, R, np.random.default_rng(100 + seed))
        r = evaluate_positions(gt, est, LEVER, align="none")
        assert r.nees.rpe_correlations.startswith("assumed independent")
        vals.append(r.nees.relative_position.values)
    v = np.concatenate(vals)
    # 952 pairs (1 m apart), neighbours share a position (correlation 1/2): the mean's
    # standard error is about 0.04 of dof; within +-0.12 (3 of them)
    assert v.size > 900 and abs(v.mean() / 3 - 1) < 0.12, v.mean()
    assert abs(np.mean(v <= chi2.ppf(0.95, 3)) - 0.95) < 0.02


def test_a_biased_estimate_is_judged_inconsistent():
    """1 cm off: constant in the world frame (no alignment), or in the sensor frame (a wrong
    lever arm, which an SE(3) alignment cannot absorb while the robot turns)."""
    rng = np.random.default_rng(7)
    t, p, R = _truth()
    gt, _ = _gt(t, p, R, rng)
    est = trajectory(t, p + np.array([0.006, -0.008, 0.0]), R)
    r = evaluate_positions(gt, est, LEVER, align="none")
    assert not r.nees.position.consistent and r.nees.position.mean > 2 * 3
    r = evaluate_positions(gt, trajectory(t, p, R), LEVER + np.array([0.0, 0.01, 0.0]),
                           align="se3")
    assert not r.nees.position.consistent, r.nees.position.mean


def test_the_json_says_rotations_are_not_reported():
    rng = np.random.default_rng(8)
    t, p, R = _truth(400)
    gt, _ = _gt(t, p, R, rng)
    d = evaluate_positions(gt, trajectory(t, p, R), "-0.2937,-0.0123,-0.2731").to_dict()
    json.dumps(d)
    assert d["ground_truth"] == "positions" and d["rotation"] == ROTATION_NOT_REPORTED
    assert d["ape"]["rotation_deg"] is None and d["rpe"]["rotation_deg"] is None
    assert d["nees"]["pose"]["mean"] is None and d["nees"]["position"]["dof"] == 3
    assert d["noise_floor"]["ape_rotation_deg"] is None
    assert d["lever_arm"]["m"] == pytest.approx(list(LEVER))
    assert d["alignment"]["method"] == "se3"


def test_weighted_alignment_needs_covariances_and_time_offset_shifts():
    t, p, R = _truth(400)
    gt = PositionTrajectory(t, p + R @ LEVER)
    with pytest.raises(InputError, match="weighted"):
        evaluate_positions(gt, trajectory(t, p, R), LEVER, weighted=True)
    with pytest.raises(InputError, match="orientation"):
        evaluate_positions(gt, trajectory(t, p, R), LEVER, align="origin")
    # the estimate's clock 0.25 s behind: --t-offset 0.25 pairs it with the right positions
    late = trajectory(t - 0.25, p, R)
    r = evaluate_positions(gt, late, LEVER, align="none", time_offset=0.25)
    assert r.ape.translation_m.max < 1e-9


@pytest.mark.parametrize("method", ["se3", "4dof", "sim3"])
def test_weighted_alignment_is_generalised_least_squares(method):
    """Noise-free, the weighted (GLS) fit recovers the transform too; with errors thin
    across one direction and long along another, it keeps the NEES after the alignment near
    its degrees of freedom where the unweighted (evo's) fit inflates it, and it is the
    minimum of sum e^T S^-1 e (no small change of the alignment lowers it)."""
    t, p, R = _truth(1500)
    y = p + R @ LEVER
    Ra, ta = Rotation.from_euler("z", 0.9).as_matrix(), np.array([3.0, 1.0, -0.5])
    moved = transform_trajectory(trajectory(t, p, R), Ra, ta, 1.1 if method == "sim3" else 1.0)
    W = np.broadcast_to(np.eye(3), (t.size, 3, 3))
    al = align_points(y, moved.position, moved.rotation, LEVER, method=method, weights=W)
    back = al.apply(moved)
    np.testing.assert_allclose(back.position + back.rotation @ LEVER, y, atol=1e-8)
    assert al.weighted
    # a covariance 100 times thinner across than along a direction that turns along the path
    rng = np.random.default_rng(21)
    ang = np.arctan2(p[:, 1], p[:, 0])
    U = Rotation.from_euler("z", ang[:, None]).as_matrix()
    cov = U @ np.diag([4e-6, 4e-10, 1e-6]) @ np.swapaxes(U, 1, 2)
    noise = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(t.size, 3)))
    gt = PositionTrajectory(t, y + noise, cov)
    r_w = evaluate_positions(gt, moved, LEVER, align=method, weighted=True)
    r_u = evaluate_positions(gt, moved, LEVER, align=method)
    # 1500 chi2(3) values less the alignment's 4-7 parameters: mean 3 within +-0.07
    assert abs(r_w.nees.position.mean / 3 - 1) < 0.07, r_w.nees.position.mean
    assert r_w.nees.position.consistent and r_u.nees.position.mean > r_w.nees.position.mean
    # the GLS minimum: a small rotation or translation of the fit raises the weighted cost
    Sinv = np.linalg.inv(cov)

    def cost(res):
        e = res.position_error
        return float(np.einsum("ni,nij,nj->", e, Sinv, e))

    best = cost(r_w)
    for k in range(3):
        d = np.zeros(3)
        d[k] = 1e-4
        shifted = transform_trajectory(r_w.est_poses, np.eye(3), d)
        assert cost(evaluate_positions(gt, shifted, LEVER, align="none")) > best
    turned = transform_trajectory(r_w.est_poses, Rotation.from_euler("z", 1e-6).as_matrix(),
                                  np.zeros(3))
    assert cost(evaluate_positions(gt, turned, LEVER, align="none")) > best


def test_figures_of_a_position_evaluation(tmp_path):
    """``--plot``: the error figure against the ground truth's sigmas, the top view of the
    points, the position NEES histogram; the pose panel says rotations are not reported."""
    from rtsgt.report.eval_plots import plot_evaluation

    rng = np.random.default_rng(31)
    t, p, R = _truth(400)
    gt, _ = _gt(t, p, R, rng)
    r = evaluate_positions(gt, trajectory(t, p, R), LEVER, align="se3")
    plots = plot_evaluation(r, tmp_path / "fig")
    assert {f.name for f in plots.files} == {f"{n}.{e}" for n in ("translation_error",
                                                                 "top_view", "nees_histogram",
                                                                 "drift")
                                             for e in ("png", "svg")}
    assert set(plots.hist) == {"position"} and plots.n_ellipses > 0
    np.testing.assert_allclose(plots.sigma_norm, np.sqrt(np.trace(gt.cov, axis1=1, axis2=2)))
    assert "rotations not reported" in (tmp_path / "fig" / "nees_histogram.svg").read_text()


def test_an_estimated_lever_arm_enters_with_its_covariance():
    """A lever arm known with covariance Sigma_l (as the mounting estimator gives it), off
    by one draw of N(0, Sigma_l) per trajectory: pooled over trajectories, the NEES with
    Sigma_l in S is chi2(3); without it, the lever arm's error is counted as the estimate's."""
    t, p, R = _truth(400)
    est = trajectory(t, p, R)
    C_l = np.diag([4e-5, 1e-5, 9e-5])  # 6, 3 and 9 mm
    with_cov, without = [], []
    for seed in range(60):
        rng = np.random.default_rng(300 + seed)
        gt, _ = _gt(t, p, R, rng, sig=(2e-3, 2e-3, 2e-3))
        wrong = LEVER + np.linalg.cholesky(C_l) @ rng.normal(size=3)
        r = evaluate_positions(gt, est, wrong, align="none", lever_arm_cov=C_l,
                               lever_arm_source="estimated")
        with_cov.append(r.nees.position.mean)
        without.append(evaluate_positions(gt, est, wrong, align="none").nees.position.mean)
    # 60 independent draws of the shared lever-arm error: the mean of the per-trajectory
    # NEES has a standard error of about 0.1 of dof; within 3 of them
    assert abs(np.mean(with_cov) / 3 - 1) < 0.3, np.mean(with_cov) / 3
    assert np.mean(without) > 2 * np.mean(with_cov)
    d = r.to_dict()["lever_arm"]
    assert d["source"] == "estimated" and np.allclose(d["cov_m2"], C_l)


@pytest.mark.parametrize("method, weighted", [("se3", True), ("sim3", True), ("sim3", False),
                                              ("4dof", True)])
def test_alignment_far_from_the_origin(method, weighted):
    """A ground truth in UTM-like coordinates (5e6 m from the origin): the fits, centred on
    the points, are as well determined as near the origin (to the rounding of coordinates
    of 5e6 m, 1e-9 m)."""
    rng = np.random.default_rng(41)
    t, p, R = _truth(800)
    far = np.array([4.5e5, 5.2e6, 300.0])
    gt, _ = _gt(t, p, R, rng)
    gt_far = PositionTrajectory(gt.t, gt.position + far, gt.cov)
    est = transform_trajectory(trajectory(t, p, R), Rotation.from_euler("z", 0.3).as_matrix(),
                               np.array([1.0, 2.0, 3.0]))
    near = evaluate_positions(gt, est, LEVER, align=method, weighted=weighted)
    r = evaluate_positions(gt_far, est, LEVER, align=method, weighted=weighted)
    np.testing.assert_allclose(r.position_error, near.position_error, atol=1e-7)
