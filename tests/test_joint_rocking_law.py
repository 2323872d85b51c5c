"""The rocking's speed law (rtsgt.joint.rocking.SpeedLaw; docs/joint.md#the-rockings-speed-law):
the scaled chains' prior against a dense Gauss-Markov covariance, the law's exponent found from
chains drawn with a known one, the bridge variance scaled between the knots."""

from __future__ import annotations

import numpy as np
import pytest

from rtsgt.interpolation.motion import STANDING_SPEED_M_S
from rtsgt.joint import gm as gmn
from rtsgt.joint.rocking import (
    SpeedLaw,
    bridge_variance,
    reference_speed,
    speed_law_step,
    start_rocking,
)


def _dense(D, U):
    K, d, _ = D.shape
    M = np.zeros((K * d, K * d))
    for k in range(K):
        M[k * d:(k + 1) * d, k * d:(k + 1) * d] = D[k]
    for k in range(K - 1):
        M[k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d] = U[k]
        M[(k + 1) * d:(k + 2) * d, k * d:(k + 1) * d] = U[k].T
    return M


def test_the_scaled_chains_prior_is_the_gauss_markov_density_of_the_unscaled_chain():
    """``add_prior`` with a scale per knot: its cost is ``z^T Sigma^-1 z`` of ``z = g / scale``
    with ``Sigma_ij = sigma^2 exp(-|t_i - t_j| / tau)`` (the test's own dense covariance),
    its information ``diag(1/scale) Sigma^-1 diag(1/scale)`` and its right-hand side minus
    that times ``g`` (the prior is linear in the chains), per chain."""
    rng = np.random.default_rng(3)
    K, col, d = 9, 2, 5
    t = np.cumsum(rng.uniform(0.05, 0.4, K))
    model = gmn.GaussMarkov(np.array([[2e-3, 1e-3, 3e-3]]), np.array([[0.3, 1.0, 0.1]]),
                            np.full((1, 3), 1e-3), np.ones((1, 3), bool))
    scale = rng.uniform(0.05, 2.0, K)
    g = rng.normal(0.0, 1e-3, (K, 3))
    D, U, a = np.zeros((K, d, d)), np.zeros((K - 1, d, d)), np.zeros((K, d))
    cost = gmn.add_prior(D, U, a, g, np.diff(t), model, col, scale)
    M = _dense(D, U)
    want = 0.0
    for c in range(3):
        sig, tau = model.sigma[0, c], model.tau_s[0, c]
        info = np.linalg.inv(sig**2 * np.exp(-np.abs(t[:, None] - t[None, :]) / tau))
        z = g[:, c] / scale
        want += z @ info @ z
        rows = np.arange(K) * d + col + c
        np.testing.assert_allclose(M[np.ix_(rows, rows)], info / np.outer(scale, scale),
                                   rtol=1e-9, atol=1e-9 * np.abs(info).max())
        np.testing.assert_allclose(a[:, col + c], -(info / np.outer(scale, scale)) @ g[:, c],
                                   rtol=1e-9, atol=1e-12 * np.abs(info).max())
    assert cost == pytest.approx(want, rel=1e-10)
    others = np.setdiff1d(np.arange(K * d), (np.arange(K) * d)[:, None] + col + np.arange(3))
    assert np.all(M[others] == 0.0)


def _speeds(rng, K):
    """A run's speeds (K,) m/s: drives at 0.3-2 m/s between stands."""
    v = np.repeat(rng.uniform(0.3, 2.0, K // 100), 100)
    v[: K // 10] = 0.0  # a stand at the start
    v[K // 2: K // 2 + K // 20] = 0.0
    return np.convolve(v, np.ones(15) / 15, mode="same")


@pytest.mark.parametrize("beta", [0.0, 0.5, 1.0])
def test_the_speed_laws_exponent_is_found_from_chains_drawn_with_it(beta):
    """Six first-order Gauss-Markov chains (sigma 1-3 mm, tau 0.2-1 s, knots every 0.15 s),
    drawn with the test's own recursion and scaled by ``(max(v, 0.05) / v_ref) ** beta``
    along a run that drives and stands: from their values (the complete data: no posterior
    variance) Newton's steps from a law of exponent 0 end within 3 of their sigmas of
    ``beta``, the sigma below 0.05; the reference speed is the moving knots' median."""
    rng = np.random.default_rng(int(10 * beta) + 7)
    K = 4000
    dt = np.full(K - 1, 0.15)
    sigma = np.array([1e-3, 2e-3, 3e-3, 1e-3, 2e-3, 3e-3])
    tau = np.array([0.2, 0.5, 1.0, 0.3, 0.6, 0.9])
    z = np.zeros((K, 6))
    z[0] = rng.standard_normal(6)
    phi = np.exp(-0.15 / tau)
    for k in range(1, K):  # the process's recursion, in the test's own code
        z[k] = phi * z[k - 1] + np.sqrt(1.0 - phi**2) * rng.standard_normal(6)
    speed = _speeds(rng, K)
    v_ref = float(np.median(speed[speed >= STANDING_SPEED_M_S]))
    scale = (np.maximum(speed, STANDING_SPEED_M_S) / v_ref) ** beta
    rock = sigma * z * scale[:, None]
    model = gmn.GaussMarkov(sigma.reshape(2, 3), tau.reshape(2, 3), sigma.reshape(2, 3),
                            np.ones((2, 3), bool))
    law = SpeedLaw(0.0, 1.0)
    zero = np.zeros((K, 6))
    for _ in range(6):
        law = speed_law_step(law, model, rock, zero, zero[1:], dt, speed,
                             np.random.default_rng(1))
    assert 0.0 < law.exponent_sd < 0.05, law
    assert abs(law.exponent - beta) < 3.0 * law.exponent_sd, law
    assert law.reference_speed_m_s == pytest.approx(v_ref, rel=1e-12)
    assert reference_speed(np.zeros(5)) == 1.0
    # standing throughout, every knot's scale is the floor's: the law is not seen and stays
    still = speed_law_step(SpeedLaw(0.0, 1.0), model, rock, zero, zero[1:], dt,
                           np.zeros(K), np.random.default_rng(1))
    assert still.exponent == 0.0 and still.reference_speed_m_s == 1.0, still


def test_the_speed_laws_steps_climb_the_marginal_likelihood_of_noisy_data():
    """Chains drawn with exponent 1 and seen through white noise as large as they are (their
    posterior half their prior): each step's posterior the exact one under the law it
    starts from (the test's dense Gaussian conditioning, ``diag(a) Sigma diag(a)`` the
    prior), Newton's steps from exponent 0 end within 3 of their sigmas of 1."""
    rng = np.random.default_rng(12)
    K = 900
    t = 0.15 * np.arange(K)
    dt = np.diff(t)
    sigma, tau = np.full(6, 2e-3), np.full(6, 0.5)
    C = np.exp(-np.abs(t[:, None] - t[None, :]) / tau[0])  # unit process, every chain's
    z = np.linalg.cholesky(C + 1e-12 * np.eye(K)) @ rng.standard_normal((K, 6))
    speed = _speeds(rng, K)
    v_ref = float(np.median(speed[speed >= STANDING_SPEED_M_S]))
    true = (np.maximum(speed, STANDING_SPEED_M_S) / v_ref) ** 1.0
    y = sigma * z * true[:, None] + sigma * rng.standard_normal((K, 6))
    model = gmn.GaussMarkov(sigma.reshape(2, 3), tau.reshape(2, 3), sigma.reshape(2, 3),
                            np.ones((2, 3), bool))
    law = SpeedLaw(0.0, 1.0)
    for i in range(8):
        a = law.scale(speed) if i else np.ones(K)
        P = sigma[0] ** 2 * C * np.outer(a, a)  # the prior under the law
        G = P @ np.linalg.inv(P + sigma[0] ** 2 * np.eye(K))
        post = P - G @ P
        rock = G @ y
        var = np.repeat(np.diag(post)[:, None], 6, axis=1)
        cross = np.repeat(np.diag(post, 1)[:, None], 6, axis=1)
        law = speed_law_step(law, model, rock, var, cross, dt, speed, np.random.default_rng(i))
    assert 0.0 < law.exponent_sd < 0.2, law
    assert abs(law.exponent - 1.0) < 3.0 * law.exponent_sd, law


def test_the_bridge_variance_follows_the_speed_laws_scale():
    """Between two knots the rocking's variance given its values there is the unscaled
    process's times the law's scale at the query time squared (linear between the knots),
    zero at the knots; a law's scale is 1 at its reference speed and the floor's below."""
    model = start_rocking()
    t_knot = np.array([0.0, 0.2, 0.5, 1.5])
    scale = np.array([0.5, 1.0, 2.0, 0.1])
    tq = np.array([0.0, 0.05, 0.2, 0.31, 0.49, 1.0, 1.5])
    got = bridge_variance(tq, t_knot, model, scale)
    want = bridge_variance(tq, t_knot, model) * np.interp(tq, t_knot, scale)[:, None] ** 2
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0.0)
    assert np.all(got[[0, 2, 6]] < 1e-20)
    law = SpeedLaw(1.0, 1.2)
    np.testing.assert_allclose(law.scale(np.array([1.2, 0.0, 2.4])),
                               [1.0, STANDING_SPEED_M_S / 1.2, 2.0], rtol=1e-12)
