"""The white-noise-on-jerk prior of the exact GP (rtsgt.interpolation.gp, ``prior="wnoj"``).

References, all independent of the code under test:

- a dense reference: the full information matrix of the Markov chain of the states
  ``[p; v; a]`` at the knots and at the query times (no measurement there), built from
  ``Phi`` and ``Q`` obtained by numerical quadrature of the SDE (not the closed forms of the
  code), solved by Gaussian elimination in extended precision (``np.longdouble``): the
  posterior of every state is the dense conditional Gaussian;
- the marginal likelihood with a proper prior as the density of the stacked measurements under
  their dense joint Gaussian (mean and covariance of the chain written out);
- the prediction-error decomposition of a Kalman filter, with the exact diffuse start: the
  first three measurements fix the state (``log p(y_0, y_1, y_2) = -log|det A|``, ``A`` the
  map from ``x(t_0)`` to the three noise-free positions), then innovations;
- simulation from the prior for coverage and for the estimation of Qc.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, stats

from rtsgt.errors import InputError
from rtsgt.interpolation import (
    as_qc,
    fit_qc,
    fit_track,
    log_marginal_likelihood,
    wnoj_phi,
    wnoj_q,
    wnoj_q_inv,
)
from rtsgt.interpolation.cross import gp_cross_covariance
from rtsgt.interpolation.loo import fit_qc_loo, loo_predictive
from test_gp import cov_err, diag, random_spd  # helpers of the WNOA tests

LD = np.longdouble
EXTENDED = np.finfo(LD).eps < 1e-18
TOL = 1e-8 if EXTENDED else 1e-6
#: At query times the reference is the dense chain with the query times as knots: a time
#: d = 0.05 x 50 ms from a knot makes its Q(d) conditioned as d^-4 (1e13), and the reference
#: loses digits that the closed forms of the code do not (they work on the unit interval).
TOL_Q = 1e-6


def _phi_ref(d):
    """``Phi(d)`` of ``x' = F x + L w`` by the matrix exponential series (F nilpotent)."""
    F = np.kron(np.array([[0, 1, 0], [0, 0, 1], [0, 0, 0]], float), np.eye(3))
    return np.eye(9) + F * d + F @ F * d * d / 2


def _q_ref(d, qc):
    """``Q(d) = int_0^d Phi(s) L Qc L^T Phi(s)^T ds`` by adaptive quadrature."""
    L = np.zeros((9, 3))
    L[6:] = np.eye(3)
    qc = as_qc(qc)
    return integrate.quad_vec(lambda s: _phi_ref(s) @ L @ qc @ L.T @ _phi_ref(s).T, 0.0, d,
                              epsabs=0, epsrel=1e-13)[0]


def _solve_spd(G, B):
    """``G^-1 B`` and ``log|G|`` by Gaussian elimination without pivoting (G is SPD)."""
    A, X = G.copy(), B.copy()
    n = A.shape[0]
    logdet = 0.0
    for j in range(n):
        logdet += np.log(A[j, j])
        f = A[j + 1:, j] / A[j, j]
        A[j + 1:, j:] -= f[:, None] * A[j, j:][None, :]
        X[j + 1:] -= f[:, None] * X[j][None, :]
    for i in range(n - 1, -1, -1):
        X[i] = (X[i] - A[i, i + 1:] @ X[i + 1:]) / A[i, i]
    return X, logdet


def dense_chain(t, y, R, qc, extra=(), scale=None, weight=None, P0=None, m0=None):
    """Dense posterior of the chain of states at ``t`` and ``extra`` (module docstring).

    ``scale``: multiplier of Qc per knot interval (the intervals that ``extra`` splits keep
    theirs); ``weight``: 0 for a measurement given no weight. Returns times, mean (M, 9),
    covariance of the whole chain (9M, 9M), and ``log|J|``.
    """
    t = np.asarray(t, float)
    times = np.unique(np.concatenate([t, np.asarray(extra, float)]))
    n = times.size
    scale = np.ones(t.size - 1) if scale is None else np.asarray(scale, float)
    weight = np.ones(t.size) if weight is None else np.asarray(weight, float)
    J = np.zeros((9 * n, 9 * n), LD)
    h = np.zeros(9 * n, LD)
    for j in range(n - 1):
        d = times[j + 1] - times[j]
        k = int(np.clip(np.searchsorted(t, times[j], side="right") - 1, 0, t.size - 2))
        A = np.zeros((9, 9 * n), LD)
        A[:, 9 * j:9 * j + 9] = -_phi_ref(d)
        A[:, 9 * j + 9:9 * j + 18] = np.eye(9)
        Qi, _ = _solve_spd(_q_ref(d, scale[k] * as_qc(qc)).astype(LD), np.eye(9, dtype=LD))
        J += A.T @ Qi @ A
    for i, tk in enumerate(t):
        j = int(np.searchsorted(times, tk))
        ri, _ = _solve_spd(R[i].astype(LD), np.eye(3, dtype=LD))
        J[9 * j:9 * j + 3, 9 * j:9 * j + 3] += weight[i] * ri
        h[9 * j:9 * j + 3] += weight[i] * (ri @ y[i].astype(LD))
    if P0 is not None:
        p0i, _ = _solve_spd(np.asarray(P0, LD), np.eye(9, dtype=LD))
        J[:9, :9] += p0i
        h[:9] += p0i @ np.asarray(m0, LD)
    sol, logdet = _solve_spd(J, np.concatenate([h[:, None], np.eye(9 * n, dtype=LD)], axis=1))
    mean = sol[:, 0].reshape(n, 9)
    return times, mean.astype(float), sol[:, 1:].astype(float), float(logdet)


def _block(cov, i, j):
    return cov[9 * i:9 * i + 9, 9 * j:9 * j + 9]


def proper_loglik(t, y, R, qc, P0, m0):
    """log N(y; E[y], Cov(y)) of the stacked measurements, the chain's joint Gaussian written
    out: ``Cov(x_i, x_j) = Cov(x_i, x_i) Phi(t_j - t_i)^T`` for ``i <= j``."""
    n = t.size
    P = [np.asarray(P0, float)]
    m = [np.asarray(m0, float)]
    for k in range(1, n):
        F = _phi_ref(t[k] - t[k - 1])
        P.append(F @ P[-1] @ F.T + _q_ref(t[k] - t[k - 1], qc))
        m.append(F @ m[-1])
    C = np.zeros((3 * n, 3 * n))
    for i in range(n):
        for j in range(i, n):
            c = (P[i] @ _phi_ref(t[j] - t[i]).T)[:3, :3]
            C[3 * i:3 * i + 3, 3 * j:3 * j + 3] = c
            C[3 * j:3 * j + 3, 3 * i:3 * i + 3] = c.T
        C[3 * i:3 * i + 3, 3 * i:3 * i + 3] += R[i]
    mu = np.concatenate([mk[:3] for mk in m])
    return stats.multivariate_normal(mu, C).logpdf(np.ravel(y))


def kalman_loglik(t, y, R, qc, scale=None):
    """Prediction-error decomposition with the exact diffuse start (module docstring)."""
    n = t.size
    scale = np.ones(n - 1) if scale is None else np.asarray(scale, float)
    d1, d2 = t[1] - t[0], t[2] - t[0]
    ll = -3.0 * math.log(d1 * d2 * (d2 - d1) / 2.0)
    # the state at t_2 given the first three measurements: dense, three knots
    _, mean, cov, _ = dense_chain(t[:3], y[:3], R[:3], qc, scale=scale[:2])
    m, P = mean[2], _block(cov, 2, 2)
    H = np.hstack([np.eye(3), np.zeros((3, 6))])
    for k in range(3, n):
        d = t[k] - t[k - 1]
        F = _phi_ref(d)
        m = F @ m
        P = F @ P @ F.T + _q_ref(d, scale[k - 1] * as_qc(qc))
        e = y[k] - m[:3]
        S = P[:3, :3] + R[k]
        ll += stats.multivariate_normal(np.zeros(3), S).logpdf(e)
        K = np.linalg.solve(S, H @ P).T
        m = m + K @ e
        A = np.eye(9) - K @ H  # Joseph form: keeps P symmetric positive definite
        P = A @ P @ A.T + K @ R[k] @ K.T
    return ll


def simulate_wnoj(rng, times, qc, x0):
    """States (len(times), 9) of the WNOJ process through ``x0``, exact steps."""
    out = [np.asarray(x0, float)]
    for d in np.diff(times):
        L = np.linalg.cholesky(wnoj_q(d, qc))
        out.append(wnoj_phi(d) @ out[-1] + L @ rng.normal(size=9))
    return np.array(out)


def problem(rng, n, t0=0.0):
    """A random track from the prior: steps 0.05-0.6 s, some gaps up to 3 s, 1 mm - 3 cm
    noise, a full Qc."""
    dt = rng.uniform(0.05, 0.6, n - 1)
    big = rng.random(n - 1) < 0.15
    dt[big] *= rng.uniform(2.0, 5.0, big.sum())
    t = t0 + np.concatenate([[0.0], np.cumsum(dt)])
    R = random_spd(rng, n, 10.0 ** rng.uniform(-6, -3), cond=30.0)
    qc = random_spd(rng, 1, 10.0 ** rng.uniform(-2, 0), cond=10.0)[0]
    x = simulate_wnoj(rng, t, qc, np.r_[rng.normal(size=3) * 5, rng.normal(size=6)])
    y = x[:, :3] + np.einsum("nij,nj->ni", np.linalg.cholesky(R), rng.normal(size=(n, 3)))
    return t, y, R, qc


def dense_queries(t, y, R, qc, tq, **kw):
    """The dense posterior (mean (Q, 9), covariance (Q, 9, 9)) at each query time, one chain
    per query (two query times close together would make the chain ill-conditioned)."""
    mean, cov = [], []
    for q in tq:
        times, m, c, _ = dense_chain(t, y, R, qc, extra=[q], **kw)
        a = int(np.searchsorted(times, q))
        mean.append(m[a])
        cov.append(_block(c, a, a))
    return np.array(mean), np.array(cov)


def rel_err(a, b):
    return float(np.abs(np.asarray(a) - b).max() / np.abs(b).max())


def test_wnoj_building_blocks_are_the_sde_integrated():
    qc = random_spd(np.random.default_rng(0), 1, 0.3)[0]
    for d in (1e-2, 0.4, 3.0):
        Q = wnoj_q(d, qc)
        np.testing.assert_allclose(Q, _q_ref(d, qc), rtol=1e-10, atol=0)
        np.testing.assert_allclose(wnoj_q_inv(d, qc) @ Q, np.eye(9), atol=1e-8)
        np.testing.assert_allclose(wnoj_phi(d), _phi_ref(d), rtol=1e-15)
        np.testing.assert_allclose(wnoj_phi(d) @ wnoj_phi(-d), np.eye(9), atol=1e-14)
    a, b = 0.7, 1.9  # Chapman-Kolmogorov
    np.testing.assert_allclose(
        wnoj_q(a + b, qc), wnoj_phi(b) @ wnoj_q(a, qc) @ wnoj_phi(b).T + wnoj_q(b, qc),
        rtol=1e-12)
    assert wnoj_q(np.array([0.1, 0.2]), 1.0).shape == (2, 9, 9)


@pytest.mark.parametrize("n", [3, 4, 5, 8, 17, 32, 33])
def test_knots_and_queries_are_the_dense_posterior(n):
    """Knot means and covariances, lag-one covariances and queries (both halves of an
    interval, near the knots, beyond both ends) against the dense conditional Gaussian."""
    rng = np.random.default_rng(100 + n)
    t, y, R, qc = problem(rng, n, t0=rng.uniform(-10, 10))
    k = int(rng.integers(0, n - 1))
    d = t[k + 1] - t[k]
    # near both knots of an interval, in both halves, beyond both ends
    tq = np.concatenate([rng.uniform(t[0], t[-1], 6), t[k] + d * np.array([0.05, 0.3, 0.7,
                                                                              0.95]),
                         [t[0] - 0.8, t[-1] + 1.3]])
    gp = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, prior="wnoj")
    assert gp.prior == "wnoj" and gp.state_dim == 9 and gp.mean.shape == (n, 9)
    _, mean, cov, _ = dense_chain(t, y, R, qc)
    S = np.array([_block(cov, i, i) for i in range(n)])
    C = np.array([_block(cov, i, i + 1) for i in range(n - 1)])
    assert rel_err(gp.mean[:, :3], mean[:, :3]) < TOL
    assert rel_err(gp.velocity, mean[:, 3:6]) < TOL
    # the acceleration sits next to the 720 / dt^5 entries of the information matrix and keeps
    # fewer digits (a dense float64 Cholesky solve loses about as many)
    assert rel_err(gp.mean[:, 6:], mean[:, 6:]) < 10 * TOL
    assert cov_err(gp.cov, S, diag(S), diag(S)) < TOL
    assert cov_err(gp.cross_cov, C, diag(S[:-1]), diag(S[1:])) < TOL
    mq, Sq = dense_queries(t, y, R, qc, tq)
    res = gp.query(tq, with_velocity=True, allow_gaps=True)
    assert rel_err(res.position, mq[:, :3]) < TOL_Q
    assert rel_err(res.velocity, mq[:, 3:6]) < TOL_Q
    assert res.state_cov.shape == (tq.size, 9, 9)
    assert cov_err(res.state_cov, Sq, diag(Sq), diag(Sq)) < TOL_Q
    # continuous at the knots: a query 1e-9 of an interval away is the knot
    near = gp.query(t[k] + d * np.array([1e-9, 1 - 1e-9]), with_velocity=True)
    np.testing.assert_allclose(near.state_cov, gp.cov[[k, k + 1]], rtol=0,
                               atol=1e-6 * np.abs(gp.cov[[k, k + 1]]).max())
    # the cross-covariance between two times (same interval, far apart)
    a, b = tq[[7, 6]], tq[[8, 2]]
    got = gp_cross_covariance(gp, a, b)
    for i in range(2):
        times, _, cov, _ = dense_chain(t, y, R, qc, extra=[a[i], b[i]])
        ia, ib = np.searchsorted(times, [a[i], b[i]])
        ref = _block(cov, ia, ib)
        assert cov_err(got[i], ref, np.diag(_block(cov, ia, ia)),
                       np.diag(_block(cov, ib, ib))) < TOL_Q


@pytest.mark.parametrize("n", [3, 4, 9, 25])
def test_likelihood_is_the_kalman_prediction_error_decomposition(n):
    rng = np.random.default_rng(200 + n)
    t, y, R, qc = problem(rng, n)
    ll = log_marginal_likelihood((t, y, R), qc, prior="wnoj")
    assert ll == pytest.approx(kalman_loglik(t, y, R, qc), rel=1e-8, abs=1e-8)
    scale = np.exp(rng.uniform(-3.0, 2.0, n - 1))
    gp = fit_track((t, y, R), qc=qc, qc_scale=scale, prior="wnoj")
    assert gp.log_likelihood == pytest.approx(kalman_loglik(t, y, R, qc, scale), rel=1e-8,
                                              abs=1e-8)
    # WNOA and WNOJ are different models of the same data
    assert ll != pytest.approx(log_marginal_likelihood((t, y, R), qc), rel=1e-3)


def test_proper_prior_posterior_and_likelihood_are_the_dense_gaussian():
    rng = np.random.default_rng(7)
    t, y, R, qc = problem(rng, 12)
    a = rng.normal(size=(9, 9)) * 0.3
    P0 = a @ a.T + 1e-4 * np.eye(9)
    P0 = 0.5 * (P0 + P0.T)
    m0 = np.concatenate([y[0], rng.normal(size=6) * 0.1])
    gp = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, prior="wnoj", initial_state_cov=P0,
                   initial_state_mean=m0)
    assert not gp.diffuse_prior
    assert gp.log_likelihood == pytest.approx(proper_loglik(t, y, R, qc, P0, m0), rel=1e-8)
    times, mean, cov, _ = dense_chain(t, y, R, qc, P0=P0, m0=m0)
    S = np.array([_block(cov, i, i) for i in range(t.size)])
    assert rel_err(gp.mean, mean) < TOL
    assert cov_err(gp.cov, S, diag(S), diag(S)) < TOL
    # a wide proper prior tends to the diffuse one
    wide = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, prior="wnoj",
                     initial_state_cov=1e8 * np.eye(9))
    plain = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, prior="wnoj")
    np.testing.assert_allclose(wide.mean[:, :3], plain.mean[:, :3], rtol=0, atol=1e-6)
    with pytest.raises(InputError, match=r"shape \(9, 9\)"):
        fit_track((t, y, R), qc=qc, prior="wnoj", initial_state_cov=np.eye(6))


def test_scaled_qc_and_held_out_measurements_are_the_dense_chain():
    rng = np.random.default_rng(9)
    t, y, R, qc = problem(rng, 20)
    scale = np.exp(rng.uniform(-3.0, 2.0, t.size - 1))
    held = np.zeros(t.size, bool)
    held[[4, 5, 6, 13, 19]] = True
    gp = fit_track((t, y, R), qc=qc, max_gap_s=np.inf, prior="wnoj", qc_scale=scale,
                   held_out=held)
    tq = np.sort(rng.uniform(t[0] - 0.5, t[-1] + 0.5, 7))
    kw = {"scale": scale, "weight": (~held).astype(float)}
    _, mean, cov, _ = dense_chain(t, y, R, qc, **kw)
    S = np.array([_block(cov, i, i) for i in range(t.size)])
    assert rel_err(gp.mean, mean) < TOL
    assert cov_err(gp.cov, S, diag(S), diag(S)) < TOL
    res = gp.query(tq, with_velocity=True, allow_gaps=True)
    mq, Sq = dense_queries(t, y, R, qc, tq, **kw)
    assert rel_err(res.position, mq[:, :3]) < TOL_Q
    assert cov_err(res.state_cov, Sq, diag(Sq), diag(Sq)) < TOL_Q
    # without a scale, the held-out fit's likelihood is that of the others alone
    a = fit_track((t, y, R), qc=qc, prior="wnoj", held_out=held)
    b = fit_track((t[~held], y[~held], R[~held]), qc=qc, prior="wnoj")
    assert a.log_likelihood == pytest.approx(b.log_likelihood, rel=1e-9)
    with pytest.raises(InputError, match="at least 3 measurements left"):
        fit_track((t, y, R), qc=qc, prior="wnoj", held_out=np.arange(t.size) > 1)


def test_three_measurements_make_the_diffuse_posterior_proper():
    rng = np.random.default_rng(1)
    t, y, R, qc = problem(rng, 3)
    gp = fit_track((t, y, R), qc=qc, prior="wnoj")
    assert np.all(np.linalg.eigvalsh(gp.cov) > 0)
    with pytest.raises(InputError, match="at least 3 measurements"):
        fit_track((t[:2], y[:2], R[:2]), qc=qc, prior="wnoj")
    with pytest.raises(InputError, match="Expected prior"):
        fit_track((t, y, R), qc=qc, prior="singer")


def test_coverage_and_qc_recovery_on_tracks_from_the_prior():
    """Queries between measurements cover the truth at the 95 % level, and both Qc criteria
    (likelihood, leave-one-out) find the true Qc of a WNOJ track."""
    rng = np.random.default_rng(20250101)
    d2 = []
    for _ in range(60):
        n = int(rng.integers(20, 50))
        t = np.cumsum(rng.uniform(0.3, 0.5, n))
        q = 10.0 ** rng.uniform(-2, 0)
        R = random_spd(rng, n, 10.0 ** rng.uniform(-6, -4))
        tq = rng.uniform(t[0], t[-1], 30)
        allt, inv = np.unique(np.concatenate([t, tq]), return_inverse=True)
        x = simulate_wnoj(rng, allt, q, np.r_[rng.normal(size=3), rng.normal(size=6) * 0.3])
        y = x[inv[:n], :3] + np.einsum("nij,nj->ni", np.linalg.cholesky(R),
                                       rng.normal(size=(n, 3)))
        res = fit_track((t, y, R), qc=q, prior="wnoj").query(tq)
        e = x[inv[n:], :3] - res.position
        d2.append(np.einsum("qi,qi->q", e, np.linalg.solve(res.position_cov, e[..., None])[..., 0]))
    d2 = np.concatenate(d2)
    assert abs(np.mean(d2 <= stats.chi2.ppf(0.95, 3)) - 0.95) < 0.015
    assert abs(np.mean(d2) / 3.0 - 1.0) < 0.05
    # Qc of one long track, by both criteria
    n, q_true = 600, 0.2
    t = np.cumsum(rng.uniform(0.3, 0.5, n))
    R = np.tile(np.eye(3) * 1e-6, (n, 1, 1))
    x = simulate_wnoj(rng, t, q_true, np.zeros(9))
    y = x[:, :3] + rng.normal(size=(n, 3)) * 1e-3
    qc, _, info = fit_qc((t, y, R), prior="wnoj")
    assert info.converged and abs(qc[0, 0] / q_true - 1) < 0.2
    loo = fit_qc_loo((t, y, R), prior="wnoj")
    assert abs(loo.qc / q_true - 1) < 0.25
    # the leave-one-out predictive is that of a refit without the measurement
    used, r, _ = loo_predictive((t[:40], y[:40], R[:40]), q_true, prior="wnoj")
    k = int(np.flatnonzero(used)[5])
    keep = np.arange(40) != k
    ref = fit_track((t[:40][keep], y[:40][keep], R[:40][keep]), qc=q_true, prior="wnoj")
    np.testing.assert_allclose(r[5], y[k] - ref.query(t[k]).position[0], rtol=0, atol=1e-9)
