"""The Gauss-Markov noise's chains (rtsgt.joint.gm): their prior against the process's dense
covariance, and the estimate of sigma and tau against the truth of simulated chains."""

from __future__ import annotations

import numpy as np
import pytest

from rtsgt.joint import gm


def _ou(rng, t, sigma, tau):
    """Stationary first-order Gauss-Markov paths (len(t), n) drawn exactly at times ``t``."""
    sigma, tau = np.asarray(sigma, float), np.asarray(tau, float)
    g = np.empty((t.size, sigma.size))
    g[0] = sigma * rng.standard_normal(sigma.size)
    phi, c = gm.transition(np.diff(t), tau)
    w = rng.standard_normal((t.size - 1, sigma.size)) * sigma * np.sqrt(c)
    for k in range(1, t.size):  # the process's recursion, in the test's own code
        g[k] = phi[k - 1] * g[k - 1] + w[k - 1]
    return g


def _model(sigma, tau):
    sigma = np.asarray(sigma, float).reshape(-1, 3)
    return gm.GaussMarkov(sigma, np.asarray(tau, float).reshape(-1, 3), sigma.copy(),
                          np.ones(sigma.shape, bool))


def test_chain_prior_is_the_inverse_of_the_process_covariance():
    """The chains' normal equations (tridiagonal) equal the inverse of their dense covariance
    ``sigma^2 exp(-|t_i - t_j| / tau)`` at irregular knots, and the cost is ``g^T Sigma^-1
    g``."""
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.01, 2.0, 25))
    sigma, tau = np.array([1e-5, 3e-5, 4e-4]), np.array([0.5, 3.0, 12.0])
    model = _model(sigma, tau)
    col, d = 2, 5
    D, U, a = np.zeros((t.size, d, d)), np.zeros((t.size - 1, d, d)), np.zeros((t.size, d))
    g = _ou(rng, t, sigma, tau)
    cost = gm.add_prior(D, U, a, g, np.diff(t), model, col)
    for j in range(3):
        cov = sigma[j] ** 2 * np.exp(-np.abs(t[:, None] - t[None, :]) / tau[j])
        info = np.linalg.inv(cov)
        c = col + j
        dense = np.diag(D[:, c, c]) + np.diag(U[:, c, c], 1) + np.diag(U[:, c, c], -1)
        np.testing.assert_allclose(dense, info, rtol=1e-8, atol=1e-8 * np.abs(info).max())
        np.testing.assert_allclose(a[:, c], -info @ g[:, j], rtol=1e-7,
                                   atol=1e-7 * np.abs(info @ g[:, j]).max())
    expected = sum(g[:, j] @ np.linalg.solve(
        sigma[j] ** 2 * np.exp(-np.abs(t[:, None] - t[None, :]) / tau[j]), g[:, j])
        for j in range(3))
    assert cost == pytest.approx(expected, rel=1e-8)
    assert np.all(D[:, :col] == 0) and np.all(U[:, :, :col] == 0)


def test_sigma_and_tau_of_known_chains_are_their_maximum_likelihood_with_honest_sigmas():
    """Chains known exactly (no posterior variance): the update is the maximum likelihood of
    sigma and tau; over 40 drawn deployments of three chains (tau 1-12 s, 0.1 s spacing,
    10 min) each estimate's error over its sigma has mean square in [0.7, 1.4] (a sigma 25 %
    too small would read 1.56) and the estimates are unbiased within their spread."""
    rng = np.random.default_rng(7)
    t = np.arange(6000) * 0.1
    z = []
    for _ in range(40):
        sigma = rng.uniform(0.5, 2.0, 3)
        tau = np.exp(rng.uniform(np.log(1.0), np.log(12.0), 3))
        g = _ou(rng, t, sigma, tau)
        fit = gm.GaussMarkov(np.ones((1, 3)), np.full((1, 3), gm.START_TAU_S), np.ones((1, 3)),
                             np.ones((1, 3), bool))
        zero = np.zeros_like(g)
        for _ in range(4):  # Newton's steps on the exact likelihood
            fit = gm.update(fit, [(g, zero, zero[1:], np.diff(t))], fit.determined)
        assert fit.determined.all() and np.all(fit.redundancy > 5000)
        z.append(np.stack([np.log(fit.sigma[0] / sigma), np.log(fit.tau_s[0] / tau)])
                 / np.moveaxis(fit.sd_log[0], 1, 0))
    z = np.concatenate(z, axis=1)  # (2, 120)
    ms = np.mean(z**2, axis=1)
    assert np.all((ms > 0.7) & (ms < 1.4)), ms
    assert np.all(np.abs(z.mean(axis=1)) < 3.0 / np.sqrt(z.shape[1]) * np.sqrt(ms)), z.mean(1)


def test_posterior_draws_have_the_moments_they_are_drawn_from():
    """The chains' posterior draws (a Gauss-Markov sequence of the given means, variances and
    consecutive covariances): their sample moments match within 5 of their standard errors
    (4000 draws)."""
    rng = np.random.default_rng(3)
    N = 30
    var = rng.uniform(0.5, 2.0, (N, 2))
    rho = rng.uniform(-0.2, 0.9, (N - 1, 2))
    cross = rho * np.sqrt(var[1:] * var[:-1])
    g = rng.normal(size=(N, 2))
    R = 4000
    d = gm._posterior_draws(g, var, cross, np.random.default_rng(4), R)
    assert d.shape == (N, 2, R)
    se = np.sqrt(var / R)
    assert np.all(np.abs(d.mean(axis=2) - g) < 5 * se)
    v = d.var(axis=2, ddof=1)
    assert np.all(np.abs(v - var) < 5 * var * np.sqrt(2.0 / R))
    c = np.mean((d[1:] - g[1:, :, None]) * (d[:-1] - g[:-1, :, None]), axis=2)
    assert np.all(np.abs(c - cross) < 5 * np.sqrt((var[1:] * var[:-1] + cross**2) / R))


def test_with_known_chains_louis_information_is_the_complete_datas():
    """Chains known exactly: the posterior draws do not scatter, Louis' information is the
    complete data's and Newton's steps land where EM's do (the maximum likelihood)."""
    rng = np.random.default_rng(8)
    t = np.arange(3000) * 0.1
    g = _ou(rng, t, [1.0, 0.5, 2.0], [2.0, 5.0, 9.0])
    zero = np.zeros_like(g)
    start = gm.GaussMarkov(np.ones((1, 3)), np.full((1, 3), gm.START_TAU_S), np.ones((1, 3)),
                           np.ones((1, 3), bool))
    em, newton = start, start
    for _ in range(10):  # EM's first step reaches it; Newton's from far are bounded
        em = gm.update(em, [(g, zero, zero[1:], np.diff(t))], em.determined)
        newton = gm.update(newton, [(g, zero, zero[1:], np.diff(t))], newton.determined,
                           np.random.default_rng(9))
    # EM's tau is a grid's parabola and its sigma^2 Förstner's at that tau: the two agree to
    # a fifth of their sigmas
    assert np.all(np.abs(np.log(newton.sigma / em.sigma)) < 0.2 * em.sd_log[..., 0])
    assert np.all(np.abs(np.log(newton.tau_s / em.tau_s)) < 0.2 * em.sd_log[..., 1])
    np.testing.assert_allclose(newton.sd_log, em.sd_log, rtol=1e-2)


def test_chains_the_data_do_not_inform_keep_their_start():
    """A posterior as wide as the prior (the data say nothing): redundancy 0, the chain is not
    determined and keeps its start; its sigmas are 0 (flagged, not estimated)."""
    t = np.arange(200) * 0.5
    model = gm.GaussMarkov(np.ones((1, 3)), np.full((1, 3), 3.0), np.ones((1, 3)),
                           np.zeros((1, 3), bool))
    phi, _ = gm.transition(np.diff(t), model.tau_s[0])
    var = np.ones((t.size, 3))
    cross = phi  # the prior's own covariance of consecutive knots
    fit = gm.update(model, [(np.zeros((t.size, 3)), var, cross, np.diff(t))])
    assert not fit.determined.any()
    np.testing.assert_allclose(fit.redundancy, 0.0, atol=1e-9)
    np.testing.assert_array_equal(fit.sigma, model.sigma)
    np.testing.assert_array_equal(fit.tau_s, model.tau_s)
    assert np.all(fit.sd_log == 0)


def test_chain_jacobian_and_values_pick_the_measurements_station():
    station = np.array([0, 2, 1, 2])
    J = gm.chain_jacobian(station, 9)
    for i, s in enumerate(station):
        np.testing.assert_array_equal(J[i][:, 3 * s:3 * s + 3], np.eye(3))
        assert np.count_nonzero(J[i]) == 3
    g = np.arange(5 * 9, dtype=float).reshape(5, 9)
    knot = np.array([4, 0, 3, 1])
    vals = gm.chain_values(g, knot, station)
    np.testing.assert_array_equal(vals, np.einsum("mij,mj->mi", J, g[knot]))


def test_complete_score_is_the_gradient_of_the_expected_log_likelihood():
    """The closed-form score of known chains equals central differences of the expected
    complete-data log-likelihood at no posterior variance."""
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(0.05, 1.0, 400))
    g = _ou(rng, t, [1.0, 2.0, 0.5], [1.5, 4.0, 20.0])
    x = np.stack([np.log([0.7, 5.0, 0.2]), np.log([2.0, 3.0, 9.0])], axis=1)
    score = gm._complete_score(x, g, np.diff(t))
    zero = np.zeros_like(g)
    h = 1e-5
    for i in range(2):
        e = np.zeros(2)
        e[i] = h
        fd = (gm._q(*(x + e).T, g, zero, zero[1:], np.diff(t))
              - gm._q(*(x - e).T, g, zero, zero[1:], np.diff(t))) / (2 * h)
        np.testing.assert_allclose(score[:, i], fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


def _observed_chains(rng, t, sigma, tau, white):
    """Three chains (sigma, tau) at times ``t`` seen through white noise of sigma ``white``."""
    g = _ou(rng, t, np.full(3, sigma), np.full(3, tau)) if sigma > 0 else np.zeros((t.size, 3))
    return g + white * rng.standard_normal(g.shape)


def _posterior_moments(t, y, white, model):
    """The chains' exact posterior (dense) given ``y`` (N, 3) at ``model``'s sigma and tau:
    means (N, 3), variances (N, 3), consecutive covariances (N-1, 3)."""
    out = []
    for c in range(3):  # three chains
        K = model.sigma[0, c] ** 2 * np.exp(-np.abs(np.subtract.outer(t, t)) / model.tau_s[0, c])
        A = np.linalg.solve(K + white**2 * np.eye(t.size), np.column_stack([K, y[:, c]]))
        P = K - K @ A[:, :-1]
        out.append((K @ A[:, -1], np.diag(P).copy(), np.diag(P, 1).copy()))
    return tuple(np.stack([o[i] for o in out], axis=1) for i in range(3))


def _loop(t, y, white, start, follow, seed, updates=8):
    """The engine's loop for the chains alone: ``updates`` updates, each from the exact
    posterior at the last one's parameters."""
    model = gm.GaussMarkov(np.full((1, 3), start), np.full((1, 3), gm.START_TAU_S),
                           np.full((1, 3), start), np.zeros((1, 3), bool))
    for i in range(updates):
        g, var, cross = _posterior_moments(t, y, white, model)
        model = gm.update(model, [(g, var, cross, np.diff(t))],
                          model.determined if model.iterations else None,
                          np.random.default_rng(seed + i), follow=follow)
    return model


def test_a_chain_started_too_small_follows_the_data_and_enters():
    """Chains of sigma 1 (tau 5 s, every 0.5 s for 200 s) under white noise of 1, started at
    0.05: the data hardly inform them there (redundancy about 1, below 10), so without
    ``follow`` they keep their start and the last solve leaves them out; with it EM's steps
    take them up and they enter within the loop's 8 updates, their sigma within a factor 2
    of the truth. Chains of sigma 0 and 0.02 started at 0.05 stay out (not determined)."""
    t = np.arange(400) * 0.5
    rng = np.random.default_rng(21)
    y = _observed_chains(rng, t, 1.0, 5.0, 1.0)
    kept = _loop(t, y, 1.0, 0.05, follow=False, seed=31)
    assert not kept.determined.any()
    np.testing.assert_array_equal(kept.sigma, 0.05)
    fit = _loop(t, y, 1.0, 0.05, follow=True, seed=31)
    assert fit.determined.all()
    assert np.all((fit.sigma > 0.5) & (fit.sigma < 2.0)), fit.sigma
    for sigma in (0.0, 0.02):
        y0 = _observed_chains(rng, t, sigma, 5.0, 1.0)
        fit0 = _loop(t, y0, 1.0, 0.05, follow=True, seed=41)
        assert not fit0.determined.any(), fit0.redundancy
        assert np.all(fit0.redundancy < gm.MIN_REDUNDANCY)
