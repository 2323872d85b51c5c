"""The white noise's variance components (rtsgt.joint.noise, issue 23 item 2) on a linear
model whose residuals' weight is known exactly: the REML fixed point recovers the truth
within its sigma, the range part enters only where the data show one, and a component
the data do not determine keeps its prior."""

from __future__ import annotations

import numpy as np

from rtsgt.joint.noise import (
    FACTOR_FLOOR,
    PRIOR,
    component_sums,
    measurement_cov,
    noise_basis,
    update_components,
)


def _fit(theta_true, n=3000, seed=0, iters=10, stations=1):
    """Measurements ``y = A x + e`` of (Hz, V, d), one channel-wise linear model each (a
    constant and a slope in time), ranges 10-500 m, noise of components ``theta_true``
    (S, 3, 2) over a datasheet of (3e-6 rad, 3e-6 rad, 1e-3 m); returns the fit after
    ``iters`` REML steps from the prior."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(10.0, 500.0, n)
    st = np.arange(n) % stations
    Q = noise_basis(np.broadcast_to([9e-12, 9e-12, 1e-6], (n, 3)).copy(), d)
    rest = np.zeros((n, 3, 3))
    corr = np.broadcast_to(np.eye(3), (n, 3, 3))
    cov_true = measurement_cov(corr, Q, st, theta_true)
    e = rng.standard_normal((n, 3)) * np.sqrt(np.einsum("mii->mi", cov_true))
    t = np.linspace(0.0, 1.0, n)
    A = np.zeros((n, 3, 6))  # channel c: columns 2c, 2c+1
    for c in range(3):
        A[:, c, 2 * c] = 1.0
        A[:, c, 2 * c + 1] = t
    y = e  # x = 0: the residuals are y - A x_hat
    theta = np.tile(PRIOR, (stations, 3, 1))
    det = None
    for _ in range(iters):
        W = np.linalg.inv(measurement_cov(corr, Q, st, theta))
        N = np.einsum("mia,mij,mjb->ab", A, W, A)
        x = np.linalg.solve(N, np.einsum("mia,mij,mj->a", A, W, y))
        res = y - A @ x
        HSH = A @ np.linalg.inv(N) @ np.swapaxes(A, 1, 2)
        q, r, F = component_sums(res, W, HSH, Q, rest, st, stations)
        theta, sigma, det, share, _ = update_components(theta, q, r, F, det)
    return theta, sigma, det, share


def test_reml_recovers_the_white_and_range_parts_within_their_sigma():
    truth = np.array([[[0.5, (2e-6) ** 2], [1.5, 0.0], [0.4, 1.0]]])
    theta, sigma, det, _ = _fit(truth)
    assert det[0, :, 0].all() and det[0, 0, 1] and det[0, 2, 1], det
    assert not det[0, 1, 1], det  # no range part on V: it stays at its prior 0
    assert theta[0, 1, 1] == 0.0
    z = (theta - truth)[det] / sigma[det]
    assert np.all(np.abs(z) < 3), z
    # a single component's sigma is sqrt(2 / r) relative
    assert sigma[0, 1, 0] / theta[0, 1, 0] < 1.2 * np.sqrt(2.0 / 1000.0)


def test_a_component_with_too_little_redundancy_keeps_its_prior():
    """Three stations of 8 measurements each: a factor's redundancy share below 10."""
    truth = np.tile(np.array([[0.5, 0.0], [1.0, 0.0], [2.0, 0.0]]), (3, 1, 1))
    theta, sigma, det, share = _fit(truth, n=24, stations=3, iters=5)
    assert not det.any(), det
    np.testing.assert_array_equal(theta, np.tile(PRIOR, (3, 3, 1)))
    assert np.all(sigma == 0) and np.all(share[..., 0] < 10)
    assert FACTOR_FLOOR > 0
