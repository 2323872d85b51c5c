"""Weighted (generalised least squares) registration: the fit, its Jacobian, the engines.

Layers: the fit against a dense solver of the same objective (scipy's least squares) on random
problems, and the closed form where the weights are isotropic and equal; the Jacobian against
finite differences and the unweighted one; the engines' covariances against each other and
against an independent Monte Carlo of the fit; Gauss-Markov (the weighted fit's first-order
covariance is never larger than the unweighted one's); honesty (NEES and coverage) pooled over
simulated deployments of poses with known truth.
"""

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from rtsgt.geometry.so3 import exp_so3, hat
from rtsgt.geometry.transform import perturbation
from rtsgt.pose import estimate_poses, register, registration_jacobian
from rtsgt.pose.estimate import pose_jacobians, pose_weights
from rtsgt.pose.weighted import (
    gls_weights,
    newton_inverse_at,
    refine_samples,
    register_weighted,
    weighted_registration_jacobian,
)

CHI2_95 = {3: 7.815, 6: 12.592}


def warthog_reference():
    """Prism triangle with the paper's Warthog distances d12, d13, d23 (m), body frame."""
    d12, d13, d23 = 0.73555, 0.90303, 1.03046
    x = (d12**2 + d13**2 - d23**2) / (2 * d12)
    r = np.array([[0.0, 0.0, 0.6], [d12, 0.0, 0.6], [x, np.sqrt(d13**2 - x**2), 0.6]])
    return r - np.array([0.4, 0.3, 0.0])


def tracked_covariances(rng, T, n, correlated=True):
    """Joint prism covariances like a total station's: a few mm along the line of sight of a
    distant station, sub-mm across it, and (optionally) a calibration-like shared part."""
    cov = np.zeros((T, 3 * n, 3 * n))
    for i in range(n):
        u = rng.normal(size=(T, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        s_along = rng.uniform(1e-3, 4e-3, size=T)
        s_across = rng.uniform(0.3e-3, 1e-3, size=T)
        cov[:, 3 * i:3 * i + 3, 3 * i:3 * i + 3] = (
            s_across[:, None, None] ** 2 * np.eye(3)
            + (s_along**2 - s_across**2)[:, None, None] * u[:, :, None] * u[:, None, :])
    if correlated:
        B = rng.normal(size=(T, 3 * n, 2)) * 0.7e-3
        cov += B @ np.swapaxes(B, 1, 2)
    return cov


def simulate(rng, T, r_true, cov_q, far=200.0):
    n = r_true.shape[0]
    R = Rotation.random(T, random_state=rng).as_matrix()
    t = rng.uniform(-far, far, size=(T, 3)) * [1, 1, 0.05]
    q_true = np.einsum("tij,nj->tni", R, r_true) + t[:, None, :]
    z = rng.standard_normal((T, 3 * n, 1))
    q = q_true + (np.linalg.cholesky(cov_q) @ z).reshape(T, n, 3)
    return R, t, q


def reference_cov(rng, n, sigma=0.7e-3):
    B = rng.normal(size=(3 * n, 3 * n)) * sigma / 3.0
    return B @ B.T + np.eye(3 * n) * (0.2e-3) ** 2


def rel_frobenius(a, b):
    return np.linalg.norm(a - b, axis=(-2, -1)) / np.linalg.norm(b, axis=(-2, -1))


def _gradient(p, q, W, R, t):
    """``H^T W e`` at (R, t) (module docstring of rtsgt.pose.weighted) and the size of its
    terms."""
    a = p @ R.T
    w = (W @ (q - a - t).reshape(-1)).reshape(-1, 3)
    g = np.concatenate([w.sum(axis=0), np.cross(a, w).sum(axis=0)])
    return g, np.abs(w).max() * max(1.0, np.abs(a).max())


@pytest.mark.parametrize("n", [3, 4, 6])
def test_the_fit_minimises_the_weighted_objective_like_a_dense_solver(n):
    rng = np.random.default_rng(100 + n)
    r = rng.normal(size=(n, 3)) * 0.5
    cov_q = tracked_covariances(rng, 12, n)
    _, _, q = simulate(rng, 12, r, cov_q)
    cov_r = reference_cov(rng, n)
    R0 = register(np.broadcast_to(r, q.shape), q)[0]
    W = gls_weights(cov_q, cov_r, R0)
    R, t, info = register_weighted(np.broadcast_to(r, q.shape), q, W, return_info=True)
    assert info.converged.all() and info.iterations <= 4
    for k in range(q.shape[0]):
        Lw = np.linalg.cholesky(W[k])
        Rc, tc = register(r, q[k])

        def residual(x, k=k, Lw=Lw, Rc=Rc, tc=tc):
            e = q[k] - r @ (exp_so3(x[3:]) @ Rc).T - (tc + x[:3])
            return Lw.T @ e.reshape(-1)

        sol = least_squares(residual, np.zeros(6), method="lm", xtol=1e-15, ftol=1e-15,
                            gtol=1e-15)
        R_ref, t_ref = exp_so3(sol.x[3:]) @ Rc, tc + sol.x[:3]
        # the dense solver stops where the cost no longer changes in double precision, some
        # 1e-8 of the optimum (its relative cost tolerance is the square of that); ours is at
        # round-off: its gradient vanishes, and its cost is not above the solver's
        np.testing.assert_allclose(R[k], R_ref, atol=2e-7)
        np.testing.assert_allclose(t[k], t_ref, atol=2e-7)
        g, terms = _gradient(r, q[k], W[k], R[k], t[k])
        assert np.abs(g).max() < 1e-9 * terms
        e = (q[k] - r @ R[k].T - t[k]).reshape(-1)
        assert e @ W[k] @ e <= 2 * sol.cost * (1 + 1e-8)  # round-off of e: 1e-12 m in 1e-3
        # and it is not the unweighted fit (the weights matter here)
        assert np.abs(R[k] - Rc).max() > 1e-6


def test_isotropic_equal_weights_give_the_closed_form():
    rng = np.random.default_rng(7)
    r = warthog_reference()
    cov_q = tracked_covariances(rng, 20, 3)
    _, _, q = simulate(rng, 20, r, cov_q)
    p = np.broadcast_to(r, q.shape)
    R0, t0 = register(p, q)
    for W in (np.eye(9), 3.7e5 * np.eye(9)):
        R, t = register_weighted(p, q, W)
        np.testing.assert_allclose(R, R0, atol=1e-12)
        np.testing.assert_allclose(t, t0, atol=1e-10)
    # isotropic, equal and independent covariances: the weights are the identity
    iso = np.broadcast_to(np.eye(9) * 2e-6, (20, 9, 9))
    np.testing.assert_allclose(gls_weights(iso, np.eye(9) * 1e-6, R0),
                               np.broadcast_to(np.eye(9), (20, 9, 9)), atol=1e-12)
    est_w = estimate_poses(q, iso, r, np.eye(9) * 1e-6, engine="linear", registration="weighted")
    est_u = estimate_poses(q, iso, r, np.eye(9) * 1e-6, engine="linear",
                           registration="unweighted")
    np.testing.assert_allclose(est_w.R, est_u.R, atol=1e-12)
    np.testing.assert_allclose(est_w.cov, est_u.cov, rtol=1e-9, atol=1e-18)


def test_the_default_tolerance_reaches_round_off():
    """The iteration stops after a step below 1e-6 rad: what is left is below 1e-10 rad, for
    the fit from the closed form and for samples from their first-order prediction."""
    rng = np.random.default_rng(8)
    r = warthog_reference()
    cov_q = tracked_covariances(rng, 50, 3)
    _, _, q = simulate(rng, 50, r, cov_q)
    p = np.broadcast_to(r, q.shape)
    W = gls_weights(cov_q, reference_cov(rng, 3), register(p, q)[0])
    R, t = register_weighted(p, q, W)
    R_tight, t_tight = register_weighted(p, q, W, tol=1e-14, max_iter=30)
    assert np.abs(R - R_tight).max() < 1e-10
    assert np.abs(t - t_tight).max() < 1e-10
    # Monte Carlo: the engine's samples against the same samples solved tightly
    est = estimate_poses(q[:5], cov_q[:5], r, np.zeros((9, 9)), engine="mc", samples=2000,
                         registration="weighted", rng=np.random.default_rng(9))
    tight = _mc_reference(q[:5], cov_q[:5], r, est, rng=np.random.default_rng(9), M=2000)
    np.testing.assert_allclose(est.cov, tight, rtol=1e-6)


def _mc_reference(q, cov_q, r, est, rng, M):
    """The Monte Carlo engine's covariance redone sample by sample from the closed form with a
    tight tolerance (same draws: the reference's first, then the prisms')."""
    K, n, _ = q.shape
    rng.standard_normal((M, 3 * n))  # the reference's draws (exact reference here)
    z = rng.standard_normal((K, M, 3 * n))
    W = pose_weights(q, cov_q, r, np.zeros((3 * n, 3 * n)))
    out = np.empty((K, 6, 6))
    for k in range(K):
        qs = q[k] + (z[k] @ np.linalg.cholesky(cov_q[k]).T).reshape(M, n, 3)
        Rs, ts = register_weighted(np.broadcast_to(r, qs.shape), qs, W[k], tol=1e-14,
                                   max_iter=30)
        xi = perturbation(est.R[k], est.t[k], Rs, ts)
        out[k] = xi.T @ xi / M
    return out


def _xi(Ra, ta, Rb, tb):
    return perturbation(Rb, tb, Ra, ta)


@pytest.mark.parametrize("correlated", [False, True])
def test_the_jacobian_matches_finite_differences(correlated):
    rng = np.random.default_rng(11)
    n = 4
    r = rng.normal(size=(n, 3)) * 0.5
    cov_q = tracked_covariances(rng, 6, n, correlated)
    _, _, q = simulate(rng, 6, r, cov_q)
    p = np.broadcast_to(r, q.shape)
    W = gls_weights(cov_q, reference_cov(rng, n), register(p, q)[0])
    tight = {"tol": 1e-14, "max_iter": 30}
    R, t = register_weighted(p, q, W, **tight)
    J_q, J_p = weighted_registration_jacobian(p, q, W, R, t)
    h = 1e-6
    for i in range(n):
        for c in range(3):
            d = np.zeros((n, 3))
            d[i, c] = h
            fd_q = (_xi(*register_weighted(p, q + d, W, **tight), R, t)
                    - _xi(*register_weighted(p, q - d, W, **tight), R, t)) / (2 * h)
            fd_p = (_xi(*register_weighted(p + d, q, W, **tight), R, t)
                    - _xi(*register_weighted(p - d, q, W, **tight), R, t)) / (2 * h)
            np.testing.assert_allclose(J_q[:, :, i, c], fd_q, atol=1e-6 * np.abs(J_q).max())
            np.testing.assert_allclose(J_p[:, :, i, c], fd_p, atol=1e-6 * np.abs(J_p).max())
    # without t: the best translation for R, the same Jacobian
    J_q2, J_p2 = weighted_registration_jacobian(p, q, W, R)
    np.testing.assert_allclose(J_q2, J_q, atol=1e-10)
    np.testing.assert_allclose(J_p2, J_p, atol=1e-10)


def test_with_identity_weights_the_jacobian_is_the_unweighted_one():
    rng = np.random.default_rng(12)
    r = warthog_reference()
    cov_q = tracked_covariances(rng, 10, 3)
    _, _, q = simulate(rng, 10, r, cov_q)
    p = np.broadcast_to(r, q.shape)
    R, t = register(p, q)
    J_q, J_p = weighted_registration_jacobian(p, q, np.eye(9), R, t)
    J_q0, J_p0 = registration_jacobian(p, q, R)
    np.testing.assert_allclose(J_q, J_q0, atol=1e-10)
    np.testing.assert_allclose(J_p, J_p0, atol=1e-10)
    # pose_jacobians picks the right one
    Jq_u, _ = pose_jacobians(q, r, R, registration="unweighted")
    np.testing.assert_allclose(Jq_u, J_q0.reshape(10, 6, 9))
    with pytest.raises(ValueError, match="cov_q and cov_r"):
        pose_jacobians(q, r, R, registration="weighted")


def test_the_engines_agree_and_match_an_independent_monte_carlo():
    """Linear, unscented and Monte Carlo covariances of the weighted fit agree; sampling the
    inputs independently and fitting each sample with the pose's weights reproduces them."""
    rng = np.random.default_rng(13)
    r = warthog_reference()
    cov_q = tracked_covariances(rng, 6, 3)
    cov_r = reference_cov(rng, 3)
    _, _, q = simulate(rng, 6, r, cov_q)
    est = {e: estimate_poses(q, cov_q, r, cov_r, engine=e, registration="weighted",
                             samples=20_000, rng=np.random.default_rng(14))
           for e in ("mc", "ut", "linear")}
    assert est["linear"].registration == "weighted"
    for e in est.values():
        np.testing.assert_allclose(e.R, est["linear"].R, atol=1e-12)
    assert rel_frobenius(est["ut"].cov, est["linear"].cov).max() < 0.02
    assert rel_frobenius(est["mc"].cov, est["linear"].cov).max() < 0.04
    # independent Monte Carlo (reference and prisms drawn here, the fit with the pose's W)
    W = pose_weights(q, cov_q, r, cov_r)
    M = 20_000
    r_s = r + (rng.standard_normal((M, 9)) @ np.linalg.cholesky(cov_r).T).reshape(M, 3, 3)
    for k in range(3):
        q_s = q[k] + (rng.standard_normal((M, 9)) @ np.linalg.cholesky(cov_q[k]).T).reshape(
            M, 3, 3)
        R_s, t_s = register_weighted(r_s, q_s, W[k])
        xi = perturbation(est["linear"].R[k], est["linear"].t[k], R_s, t_s)
        assert rel_frobenius(xi.T @ xi / M, est["linear"].cov[k]) < 0.04


def test_the_weighted_fit_is_never_less_precise_to_first_order():
    """Gauss-Markov: with the weights the inverse of the residual's covariance, the first-order
    covariance of the fit, ``(H^T W H)^-1`` at a zero residual, is the smallest of any linear
    unbiased fit's, the unweighted one's included."""
    rng = np.random.default_rng(15)
    r = warthog_reference()
    cov_q = tracked_covariances(rng, 200, 3)
    cov_r = reference_cov(rng, 3)
    R, t, q = simulate(rng, 200, r, cov_q)
    q_exact = np.einsum("tij,nj->tni", R, r) + t[:, None, :]
    for data, tol in ((q_exact, 1e-9), (q, None)):
        w = estimate_poses(data, cov_q, r, cov_r, engine="linear", registration="weighted").cov
        u = estimate_poses(data, cov_q, r, cov_r, engine="linear",
                           registration="unweighted").cov
        if tol is not None:  # u - w is positive semi-definite, in the metric of w
            Li = np.linalg.inv(np.linalg.cholesky(w))
            ev = np.linalg.eigvalsh(Li @ (u - w) @ np.swapaxes(Li, 1, 2))
            assert ev.min() > -tol
            # and it is (H^T W H)^-1
            H = np.zeros((200, 3, 3, 6))
            H[..., :3] = np.eye(3)
            H[..., 3:] = -hat(np.einsum("tij,nj->tni", R, r))
            H = H.reshape(200, 9, 6)
            Wc = np.linalg.inv(_residual_cov(cov_q, cov_r, R))
            np.testing.assert_allclose(w, np.linalg.inv(np.swapaxes(H, 1, 2) @ Wc @ H),
                                       rtol=1e-7, atol=1e-16)
        # a real gain with these anisotropic prisms, noisy or not
        tr = np.trace(w[:, 3:, 3:], axis1=1, axis2=2) / np.trace(u[:, 3:, 3:], axis1=1, axis2=2)
        assert np.median(tr) < 0.9


def _residual_cov(cov_q, cov_r, R):
    B = np.zeros((R.shape[0], 9, 9))
    for i in range(3):
        B[:, 3 * i:3 * i + 3, 3 * i:3 * i + 3] = R
    return cov_q + B @ cov_r @ np.swapaxes(B, 1, 2)


@pytest.mark.parametrize("engine", ["mc", "ut", "linear"])
def test_weighted_poses_are_honest(engine):
    """Known truth, 60 simulated deployments of 30 poses, each with its own reference survey
    error: NEES / dof averages 1 +- 15 %, the 95 % regions hold the truth 95 +- 3 %."""
    rng = np.random.default_rng(16)
    r_true = warthog_reference()
    cov_r = reference_cov(rng, 3)
    L_r = np.linalg.cholesky(cov_r)
    nees6, nees3 = [], []
    for _ in range(60):
        r_meas = r_true + (L_r @ rng.standard_normal(9)).reshape(3, 3)
        cov_q = tracked_covariances(rng, 30, 3)
        R, t, q = simulate(rng, 30, r_true, cov_q)
        est = estimate_poses(q, cov_q, r_meas, cov_r, engine=engine, registration="weighted",
                             samples=400, rng=rng)
        xi = perturbation(est.R, est.t, R, t)
        nees6.append(np.einsum("ti,tij,tj->t", xi, np.linalg.inv(est.cov), xi))
        nees3.append(np.einsum("ti,tij,tj->t", xi[:, :3], np.linalg.inv(est.cov[:, :3, :3]),
                               xi[:, :3]))
    for dof, nees in ((6, np.concatenate(nees6)), (3, np.concatenate(nees3))):
        assert nees.size == 1800
        assert abs(nees.mean() / dof - 1.0) < 0.15, (dof, nees.mean() / dof)
        assert abs(np.mean(nees < CHI2_95[dof]) - 0.95) < 0.03, (dof, np.mean(nees < CHI2_95[dof]))


def test_weights_and_bad_inputs():
    rng = np.random.default_rng(17)
    r = warthog_reference()
    cov_q = tracked_covariances(rng, 4, 3)
    _, _, q = simulate(rng, 4, r, cov_q)
    R0 = register(np.broadcast_to(r, q.shape), q)[0]
    cov_r = reference_cov(rng, 3)
    W = gls_weights(cov_q, cov_r, R0)
    B = np.zeros((4, 9, 9))
    for i in range(3):
        B[:, 3 * i:3 * i + 3, 3 * i:3 * i + 3] = R0
    C = cov_q + B @ cov_r @ np.swapaxes(B, 1, 2)
    # the inverse of the residual's covariance, up to its scale
    WC = W @ C
    np.testing.assert_allclose(WC / WC[:, :1, :1], np.broadcast_to(np.eye(9), WC.shape),
                               atol=1e-9)
    # a residual covariance that is zero altogether: the identity (the unweighted fit)
    np.testing.assert_allclose(gls_weights(np.zeros((1, 9, 9)), np.zeros((9, 9)), R0[:1]),
                               np.eye(9)[None])
    with pytest.raises(ValueError, match="registration"):
        estimate_poses(q, cov_q, r, cov_r, engine="linear", registration="svd")
    with pytest.raises(ValueError, match="weight_cov_q"):
        estimate_poses(q, cov_q, r, cov_r, engine="linear", registration="weighted",
                       weight_cov_q=cov_q[:, :3, :3])
    # weights from the total, a part propagated: the fit is the total's
    fit = {"engine": "linear", "registration": "weighted"}
    part = estimate_poses(q, 0.5 * cov_q, r, cov_r, weight_cov_q=cov_q, weight_cov_r=cov_r,
                          **fit)
    whole = estimate_poses(q, cov_q, r, cov_r, **fit)
    np.testing.assert_allclose(part.R, whole.R, atol=1e-14)
    assert not np.allclose(estimate_poses(q, 0.5 * cov_q, r, cov_r, **fit).R, whole.R,
                           atol=1e-9, rtol=0)


def test_a_fit_far_from_the_closed_form_descends_to_a_minimum():
    """A pose of the 2022-11-09 deployment's first seconds (prisms known to 2-8 cm, the
    triangle distorted): the weighted minimum is about 1 rad from the closed form. Newton's
    undamped steps went to a stationary point of larger objective than the start (1.74
    against 0.84); with the trust region and the Gauss-Newton matrix where Newton's is not
    positive definite, the fit descends to a minimum (0.024)."""
    q = np.array([[0.332, -0.216, 0.262], [-0.152, 0.093, -0.175], [-0.179, 0.124, -0.087]])
    r = np.array([[0.064, -0.298, 0.615], [0.567, 0.045, 0.205], [-0.402, 0.389, 0.256]])
    sig = np.array([0.083, 0.063, 0.018, 0.006, 0.005, 0.002, 0.015, 0.032, 0.0035])
    R0, t0 = register(r, q)
    W = gls_weights(np.diag(sig**2), np.eye(9) * 0.5e-3**2, R0)
    R, t, info = register_weighted(r, q, W, return_info=True)

    def objective(R, t):
        e = (q - r @ R.T - t).reshape(-1)
        return e @ W @ e

    assert info.converged
    assert objective(R, t) < 0.1 * objective(R0, t0)
    R_tight, t_tight = register_weighted(r, q, W, tol=1e-15, max_iter=40)
    assert np.abs(R - R_tight).max() < 1e-8  # ill-conditioned: 3e-9 left (1e-10 typically)
    g, scale = _gradient(r, q, W, R_tight, t_tight)
    assert np.abs(g).max() < 1e-12 * scale
    # a minimum: the objective grows along every small rotation about the fit
    for axis in np.eye(3):
        for sign in (1.0, -1.0):
            R1 = exp_so3(sign * 1e-3 * axis) @ R
            t1 = t + (R @ r.mean(axis=0) - R1 @ r.mean(axis=0))
            assert objective(R1, t1) > objective(R, t)


def test_the_samples_chord_steps_reach_the_tight_fits():
    """refine_samples (the Monte Carlo engine's fits: chord steps with the pose's Newton matrix
    from the first-order prediction) against each sample solved by Newton to round-off; a
    sample perturbed by far more than the pose's uncertainty is flagged, not returned as
    converged when it is not."""
    rng = np.random.default_rng(12)
    r = warthog_reference()
    K, S, n = 4, 300, 3
    cov_q = tracked_covariances(rng, K, n)
    cov_r = reference_cov(rng, n)
    _, _, q = simulate(rng, K, r, cov_q)
    p = np.broadcast_to(r, q.shape)
    W = gls_weights(cov_q, cov_r, register(p, q)[0])
    R0, t0 = register_weighted(p, q, W, tol=1e-14, max_iter=30)
    J_q, J_r = weighted_registration_jacobian(p, q, W, R0, t0)
    dq = np.linalg.cholesky(cov_q) @ rng.standard_normal((K, 3 * n, S))
    dq[0, :, 0] *= 30.0  # centimetres: the first-order start is far off
    dr = np.linalg.cholesky(cov_r) @ rng.standard_normal((3 * n, S))
    xi0 = J_q.reshape(K, 6, 3 * n) @ dq + J_r.reshape(K, 6, 3 * n) @ dr
    Wt, P, N_inv = newton_inverse_at(p, q, W, R0, t0)
    X = np.moveaxis((r.reshape(-1, 1) + dr).reshape(n, 3, S), -1, -1)
    Y = (q - t0[:, None]).reshape(K, 3 * n, 1) + dq
    xi, conv = refine_samples(Y, X, Wt, P, N_inv, R0, xi0)
    qs = np.swapaxes((q.reshape(K, 3 * n, 1) + dq), 1, 2).reshape(K, S, n, 3)
    ps = np.broadcast_to((r.reshape(-1, 1) + dr).T.reshape(S, n, 3), qs.shape)
    Rs, ts = register_weighted(ps, qs, W[:, None], tol=1e-14, max_iter=30)
    tight = np.swapaxes(np.stack([perturbation(R0[k], t0[k], Rs[k], ts[k]) for k in range(K)]),
                        1, 2)
    ok = conv
    assert ok.mean() > 0.99
    assert np.abs(xi - tight).max(axis=1)[ok].max() < 1e-10
    # the far sample: either right or flagged
    assert not conv[0, 0] or np.abs(xi[0, :, 0] - tight[0, :, 0]).max() < 1e-10
