"""Pose engines (Monte Carlo, unscented, linear): agreement, honesty, convention, degeneracy."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rtsgt.errors import GeometryError
from rtsgt.geometry import kabsch
from rtsgt.geometry.transform import perturbation
from rtsgt.pose import (
    ENGINES,
    POSE_ENGINES,
    REASON_COLLINEAR,
    REASON_MISSING,
    Linear,
    MonteCarlo,
    Unscented,
    estimate_poses,
    psd_factor,
)
from rtsgt.pose.estimate import pose_weights
from rtsgt.pose.weighted import register_weighted

CHI2_95 = {3: 7.815, 6: 12.592}


def warthog_reference():
    """Prism triangle with the paper's Warthog distances d12, d13, d23 (m), body frame."""
    d12, d13, d23 = 0.73555, 0.90303, 1.03046
    x = (d12**2 + d13**2 - d23**2) / (2 * d12)
    y = np.sqrt(d13**2 - x**2)
    r = np.array([[0.0, 0.0, 0.6], [d12, 0.0, 0.6], [x, y, 0.6]])
    return r - np.array([0.4, 0.3, 0.0])


def simulate(rng, T, r_true, sigma_prism=0.002, far=200.0, floor=0.5e-6):
    """True poses, prism covariances (anisotropic, a few mm) and noisy world prisms."""
    R = Rotation.random(T, random_state=rng).as_matrix()
    t = rng.uniform(-far, far, size=(T, 3)) * [1, 1, 0.05]
    A = rng.normal(size=(T, 3, 3, 3)) * sigma_prism
    cov_q = A @ np.swapaxes(A, -1, -2) + np.eye(3) * floor
    q_true = np.einsum("tij,nj->tni", R, r_true) + t[:, None, :]
    z = rng.standard_normal((T, 3, 3))
    q = q_true + np.einsum("tnij,tnj->tni", np.linalg.cholesky(cov_q), z)
    return R, t, q, cov_q


def correlated_reference_cov(rng, sigma=0.7e-3):
    B = rng.normal(size=(9, 9)) * sigma / 3.0
    return B @ B.T + np.eye(9) * (0.2e-3) ** 2


def rel_frobenius(a, b):
    return np.linalg.norm(a - b, axis=(-2, -1)) / np.linalg.norm(b, axis=(-2, -1))


def test_three_engines_agree_at_the_papers_noise_levels():
    rng = np.random.default_rng(10)
    r = warthog_reference()
    cov_r = correlated_reference_cov(rng)
    _, _, q, cov_q = simulate(rng, 20, r)
    est = {
        e: estimate_poses(q, cov_q, r, cov_r, engine=e, samples=5000,
                          rng=np.random.default_rng(11))
        for e in ("mc", "ut", "linear")
    }
    for e in est.values():
        assert not e.degenerate.any()
        np.testing.assert_allclose(e.R, est["linear"].R, atol=1e-12)
    assert rel_frobenius(est["ut"].cov, est["linear"].cov).max() < 0.02
    assert rel_frobenius(est["mc"].cov, est["linear"].cov).max() < 0.10
    assert rel_frobenius(est["mc"].cov, est["ut"].cov).max() < 0.10
    assert est["mc"].samples == 5000 and est["ut"].samples == 36 and est["linear"].samples is None
    # the sample mean sits on the reported pose, far inside the noise
    std = np.sqrt(np.diagonal(est["mc"].cov, axis1=1, axis2=2))
    assert np.all(np.abs(est["mc"].mean_offset) < 0.1 * std)


@pytest.mark.parametrize("engine", ["mc", "ut", "linear"])
def test_honest_uncertainty_nees_and_coverage(engine):
    """Known truth: NEES / dof averages 1 +- 15 %, the 95 % regions hold the truth 95 +- 3 %.

    Each of 100 simulated deployments has its own reference survey error (shared by its 40
    poses, as in reality); 4000 poses in all. The paper's unweighted fit; the weighted one:
    tests/test_pose_weighted.py.
    """
    rng = np.random.default_rng(20)
    r_true = warthog_reference()
    cov_r = correlated_reference_cov(rng)
    L_r = np.linalg.cholesky(cov_r)
    nees6, nees3 = [], []
    for _ in range(100):
        r_meas = r_true + (L_r @ rng.standard_normal(9)).reshape(3, 3)
        R, t, q, cov_q = simulate(rng, 40, r_true)
        est = estimate_poses(q, cov_q, r_meas, cov_r, engine=engine, samples=600, rng=rng,
                             registration="unweighted")
        xi = perturbation(est.R, est.t, R, t)
        nees6.append(np.einsum("ti,tij,tj->t", xi, np.linalg.inv(est.cov), xi))
        nees3.append(np.einsum("ti,tij,tj->t", xi[:, :3], np.linalg.inv(est.cov[:, :3, :3]),
                               xi[:, :3]))
    for dof, nees in ((6, np.concatenate(nees6)), (3, np.concatenate(nees3))):
        assert nees.size == 4000
        assert abs(nees.mean() / dof - 1.0) < 0.15, (dof, nees.mean() / dof)
        assert abs(np.mean(nees < CHI2_95[dof]) - 0.95) < 0.03, (dof, np.mean(nees < CHI2_95[dof]))


@pytest.mark.parametrize("registration", ["unweighted", "weighted"])
def test_sampled_cloud_reproduces_reported_covariance(registration):
    """Convention pin: solve independently sampled inputs (with the SVD Kabsch, or the weighted
    fit with the pose's weights), take the left perturbations with
    geometry.transform.perturbation: their covariance is the reported one."""
    rng = np.random.default_rng(30)
    r = warthog_reference()
    cov_r = correlated_reference_cov(rng)
    _, _, q, cov_q = simulate(rng, 3, r)
    est = estimate_poses(q, cov_q, r, cov_r, engine="linear", registration=registration)
    W = pose_weights(q, cov_q, r, cov_r)
    M = 40_000
    z_r = rng.standard_normal((M, 9)) @ np.linalg.cholesky(cov_r).T
    r_s = r + z_r.reshape(M, 3, 3)
    for k in range(3):
        L = np.linalg.cholesky(cov_q[k])
        q_s = q[k] + np.einsum("nij,mnj->mni", L, rng.standard_normal((M, 3, 3)))
        R_s, t_s = (kabsch(r_s, q_s) if registration == "unweighted"
                    else register_weighted(r_s, q_s, W[k]))
        xi = perturbation(est.R[k], est.t[k], R_s, t_s)
        cloud = xi.T @ xi / M
        assert rel_frobenius(cloud, est.cov[k]) < 0.04
        # rotation block on the left (world frame): a right perturbation would differ
        xi_right = np.concatenate(
            [t_s - est.t[k], Rotation.from_matrix(est.R[k].T @ R_s).as_rotvec()], axis=1
        )
        assert rel_frobenius(xi_right.T @ xi_right / M, est.cov[k]) > 0.2


def test_reference_is_sampled_with_its_full_covariance():
    """A reference error common to all prisms (fully correlated) is a pure translation of the
    body frame: translation variance s^2 per axis and no rotation; independent errors of the
    same size rotate the pose (the reference code sampled every prism from one covariance)."""
    rng = np.random.default_rng(40)
    r = warthog_reference()
    s = 2e-3
    cov_full = np.kron(np.ones((3, 3)), np.eye(3) * s**2)
    cov_indep = np.kron(np.eye(3), np.eye(3) * s**2)
    _, _, q, cov_q = simulate(rng, 5, r, sigma_prism=1e-5, floor=1e-14)
    mc = estimate_poses(q, cov_q, r, cov_full, engine="mc", samples=20_000, rng=rng)
    mc_indep = estimate_poses(q, cov_q, r, cov_indep, engine="mc", samples=20_000, rng=rng)
    lin = estimate_poses(q, cov_q, r, cov_full, engine="linear")
    var_mc = np.diagonal(mc.cov, axis1=1, axis2=2)
    np.testing.assert_allclose(var_mc[:, :3], np.diagonal(lin.cov, axis1=1, axis2=2)[:, :3],
                               rtol=0.1)
    np.testing.assert_allclose(var_mc[:, :3].sum(axis=1), 3 * s**2, rtol=0.05)
    rot_full = var_mc[:, 3:].sum(axis=1)
    rot_indep = np.diagonal(mc_indep.cov, axis1=1, axis2=2)[:, 3:].sum(axis=1)
    assert np.all(rot_full < 0.01 * rot_indep)
    assert np.all(rot_indep > (s / 1.0) ** 2)  # ~ s^2 / extent^2 with a ~1 m triangle


def test_degenerate_poses_are_reported_not_solved():
    rng = np.random.default_rng(50)
    r = warthog_reference()
    cov_r = np.eye(9) * (0.5e-3) ** 2
    _, _, q, cov_q = simulate(rng, 12, r)
    q[3, 1] = np.nan  # a missing prism
    cov_q[8, 2] = np.nan  # a missing covariance
    q[5] = q[5, 0] + np.array([0.0, 0.5, 1.0])[:, None] * np.array([0.3, 0.6, 0.01])  # collinear
    good = np.setdiff1d(np.arange(12), [3, 5, 8])
    for engine in ("mc", "ut", "linear"):
        est = estimate_poses(q, cov_q, r, cov_r, engine=engine, samples=200,
                             rng=np.random.default_rng(51))
        assert list(np.flatnonzero(est.degenerate)) == [3, 5, 8]
        assert est.reason[3] == REASON_MISSING and est.reason[8] == REASON_MISSING
        assert est.reason[5] == REASON_COLLINEAR
        assert np.all(est.reason[good] == "")
        for k in (3, 5, 8):
            assert np.all(np.isnan(est.R[k])) and np.all(np.isnan(est.t[k]))
            assert np.all(np.isnan(est.cov[k]))
        assert np.all(np.isfinite(est.cov[good]))
        assert est.counts == {"valid": 9, REASON_MISSING: 2, REASON_COLLINEAR: 1}
        assert np.isnan(est.inter_prism_distance[3, [0, 2]]).all()
        # the valid poses are exactly what a run on them alone gives (same draws)
        alone = estimate_poses(q[good], cov_q[good], r, cov_r, engine=engine, samples=200,
                               rng=np.random.default_rng(51))
        np.testing.assert_allclose(est.cov[good], alone.cov, rtol=1e-9, atol=1e-20)


def test_mc_is_reproducible_and_independent_of_chunking():
    rng = np.random.default_rng(60)
    r = warthog_reference()
    _, _, q, cov_q = simulate(rng, 9, r)
    cov_r = np.eye(9) * (0.5e-3) ** 2
    a = estimate_poses(q, cov_q, r, cov_r, samples=300, rng=np.random.default_rng(1))
    b = estimate_poses(q, cov_q, r, cov_r, samples=300, rng=np.random.default_rng(1),
                       chunk_size=700)
    c = estimate_poses(q, cov_q, r, cov_r, samples=300, rng=np.random.default_rng(2))
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-8)
    assert rel_frobenius(a.cov, c.cov).max() > 1e-3  # a different seed, different samples
    # the chunks on a pool of threads: the same draws, bit for bit the same result
    for registration in ("weighted", "unweighted"):
        runs = [estimate_poses(q, cov_q, r, cov_r, samples=300, rng=np.random.default_rng(1),
                               chunk_size=700, threads=k, registration=registration)
                for k in (1, 3)]
        for x in ("cov", "mean_offset", "R", "t"):
            assert np.array_equal(getattr(runs[0], x), getattr(runs[1], x)), (registration, x)
        ref = b if registration == "weighted" else estimate_poses(
            q, cov_q, r, cov_r, samples=300, rng=np.random.default_rng(1),
            registration=registration)
        np.testing.assert_allclose(runs[1].cov, ref.cov, rtol=1e-8)
        if registration == "weighted":  # b: the same chunks on the default threads
            assert np.array_equal(runs[0].cov, b.cov)
    with pytest.raises(ValueError, match="threads"):
        estimate_poses(q, cov_q, r, cov_r, samples=300, rng=np.random.default_rng(1), threads=0)


def test_distances_residuals_and_quaternions():
    rng = np.random.default_rng(70)
    r = warthog_reference()
    R, t, q, cov_q = simulate(rng, 4, r, sigma_prism=1e-5, floor=1e-14)
    est = estimate_poses(q, cov_q, r, np.zeros((3, 3, 3)), engine="ut")
    assert est.pairs == ((0, 1), (0, 2), (1, 2))
    np.testing.assert_allclose(est.inter_prism_distance, [[0.73555, 0.90303, 1.03046]] * 4,
                               atol=1e-4)
    assert np.all(est.rms_residual < 1e-4)
    np.testing.assert_allclose(est.R, R, atol=1e-4)
    np.testing.assert_allclose(Rotation.from_quat(est.quat_xyzw).as_matrix(), est.R, atol=1e-12)
    assert np.all(est.shape > 0.5)


def test_bad_inputs():
    r = warthog_reference()
    q = r[None] + 1.0
    cq = np.broadcast_to(np.eye(3) * 1e-6, (1, 3, 3, 3))
    cr = np.eye(9) * 1e-6
    with pytest.raises(ValueError, match="Generator"):
        estimate_poses(q, cq, r, cr, engine="mc")
    with pytest.raises(ValueError, match="engine"):
        estimate_poses(q, cq, r, cr, engine="svd")
    with pytest.raises(ValueError, match="cov_q of shape"):
        estimate_poses(q, cq[:, :2], r, cr, engine="linear")
    with pytest.raises(ValueError, match="cov_r of shape"):
        estimate_poses(q, cq, r, np.eye(6), engine="linear")
    with pytest.raises(ValueError, match="positive semi-definite"):
        estimate_poses(q, cq, r, -cr, engine="linear")
    with pytest.raises(GeometryError, match="at least 3"):
        estimate_poses(q[:, :2], cq[:, :2], r[:2], cr[:6, :6], engine="linear")
    line = np.array([0.0, 0.5, 1.0])[:, None] * np.array([1.0, 0.2, 0.0])
    with pytest.raises(GeometryError, match="collinear"):
        estimate_poses(line[None] + 1.0, cq, line, cr, engine="linear")


def test_psd_factor_columns_reproduce_the_covariance():
    """Cholesky where possible; for a singular covariance the eigen-factor uses the COLUMNS of
    the eigenvector matrix (the reference code used the rows: pitfall 1 of
    docs/noise-model.md#reference-code-pitfalls)."""
    rng = np.random.default_rng(80)
    A = rng.normal(size=(6, 2))
    singular = A @ A.T  # rank 2
    L = psd_factor(singular)
    np.testing.assert_allclose(L @ L.T, singular, atol=1e-12)
    w, V = np.linalg.eigh(singular)
    rows = V.T * np.sqrt(np.clip(w, 0, None))  # the pitfall: rows scaled
    assert np.linalg.norm(rows @ rows.T - singular) > 1e-3
    B = rng.normal(size=(4, 3, 3))
    spd = B @ np.swapaxes(B, -1, -2) + np.eye(3)
    np.testing.assert_allclose(psd_factor(spd), np.linalg.cholesky(spd))


def test_joint_prism_covariance_block_diagonal_equals_per_prism():
    """A joint (3n x 3n) covariance with no cross terms gives what the per-prism blocks give."""
    from rtsgt.pose.estimate import block_diagonal

    rng = np.random.default_rng(41)
    r = warthog_reference()
    _, _, q, cov_q = simulate(rng, 20, r)
    cov_r = correlated_reference_cov(rng)
    joint = block_diagonal(cov_q)
    assert joint.shape == (20, 9, 9)
    for engine in ("linear", "ut"):
        a = estimate_poses(q, cov_q, r, cov_r, engine=engine)
        b = estimate_poses(q, joint, r, cov_r, engine=engine)
        np.testing.assert_allclose(b.cov, a.cov, rtol=1e-9, atol=1e-18)
    a = estimate_poses(q, cov_q, r, cov_r, engine="mc", samples=300, rng=np.random.default_rng(1))
    b = estimate_poses(q, joint, r, cov_r, engine="mc", samples=300, rng=np.random.default_rng(1))
    np.testing.assert_allclose(b.cov, a.cov, rtol=1e-9, atol=1e-18)


@pytest.mark.parametrize("engine", ["mc", "ut", "linear"])
def test_errors_shared_between_prisms_need_the_joint_covariance(engine):
    """Prism errors with a common part (one shift for all prisms, as from a shared calibration
    or a common interpolation error): NEES is consistent with the joint covariance, and too
    large when only the per-prism blocks are given."""
    rng = np.random.default_rng(42)
    r = warthog_reference()
    T = 1500
    R, t, q0, cov_q = simulate(rng, T, r)
    q_true = np.einsum("tij,nj->tni", R, r) + t[:, None, :]
    common = np.diag([3e-3, 3e-3, 1.5e-3]) ** 2  # the shared part, m^2
    joint = np.tile(np.kron(np.ones((3, 3)), common), (T, 1, 1))
    for i in range(3):
        joint[:, 3 * i:3 * i + 3, 3 * i:3 * i + 3] += cov_q[:, i]
    L = np.linalg.cholesky(joint)
    q = q_true + np.einsum("tab,tb->ta", L, rng.standard_normal((T, 9))).reshape(T, 3, 3)
    zero_r = np.zeros((9, 9))
    res = {}
    for name, c in (("joint", joint), ("blocks", cov_q + common)):
        est = estimate_poses(q, c, r, zero_r, engine=engine, samples=400,
                             rng=np.random.default_rng(3))
        xi = perturbation(est.R, est.t, R, t)
        res[name] = np.mean(np.einsum("ti,tij,tj->t", xi, np.linalg.inv(est.cov), xi)) / 6
    assert abs(res["joint"] - 1.0) < 0.1, res
    assert res["blocks"] > 1.2, res


@pytest.mark.parametrize("engine", ["mc", "ut", "linear"])
def test_a_single_pose_is_the_same_as_in_a_batch(engine):
    """A batch of one pose (the broadcast reference view is read-only) gives what the same
    pose gives inside a larger batch."""
    rng = np.random.default_rng(12)
    r = warthog_reference()
    _, _, q, cov_q = simulate(rng, 4, r)
    cov_r = correlated_reference_cov(rng)
    kw = dict(engine=engine, samples=200)
    one = estimate_poses(q[2:3], cov_q[2:3], r, cov_r, rng=np.random.default_rng(3), **kw)
    batch = estimate_poses(q, cov_q, r, cov_r, rng=np.random.default_rng(3), **kw)
    np.testing.assert_allclose(one.t[0], batch.t[2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(one.R[0], batch.R[2], rtol=0, atol=1e-12)
    if engine != "mc":  # the Monte Carlo draws depend on the batch; its covariance is tested
        np.testing.assert_allclose(one.cov[0], batch.cov[2], rtol=1e-10, atol=0)
    else:
        assert np.all(np.linalg.eigvalsh(one.cov[0]) > 0)


def test_an_engine_object_is_the_engine_its_name_builds():
    assert tuple(ENGINES) == POSE_ENGINES == ("mc", "ut", "linear")
    rng = np.random.default_rng(90)
    r = warthog_reference()
    _, _, q, cov_q = simulate(rng, 5, r)
    cov_r = np.eye(9) * (0.5e-3) ** 2
    by_name = estimate_poses(q, cov_q, r, cov_r, samples=64, rng=np.random.default_rng(3))
    by_type = estimate_poses(q, cov_q, r, cov_r,
                             engine=MonteCarlo(np.random.default_rng(3), samples=64))
    assert np.array_equal(by_name.cov, by_type.cov) and by_type.engine == "mc"
    for engine in (Unscented(), Linear()):
        a = estimate_poses(q, cov_q, r, cov_r, engine=engine)
        b = estimate_poses(q, cov_q, r, cov_r, engine=engine.name)
        assert np.array_equal(a.cov, b.cov) and a.samples == b.samples
    with pytest.raises(ValueError, match="samples"):
        MonteCarlo(np.random.default_rng(3), samples=1)
