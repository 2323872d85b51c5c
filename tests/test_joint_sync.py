"""The stations' constant clock offsets against the robot's as parameters of the joint engine
(the noise model's time_sync source, carried once per deployment instead of as white noise):
recovered on a noise-free problem, and carried in a simulated run's covariance."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from rtsgt.joint.engine import COMMON_SYNC_HOLD_S, assemble, gauss_newton, retract
from rtsgt.joint.sparse import solve_arrow
from test_joint import _synthetic

OFFSETS_S = np.array([0.0, 0.008, -0.005])


def _problem(rng, with_sync):
    prob, truth = _synthetic(rng, K=45, clock_s=OFFSETS_S)
    prob = replace(prob, clock=None, sync_column=np.arange(3) if with_sync else None,
                   sync_var=1.0)  # a weak prior: the data decide (as the clock test's)
    truth = replace(truth, clock=None, sync=OFFSETS_S.copy() if with_sync else None)
    return prob, truth


def test_constant_clock_offsets_are_recovered_and_needed():
    """Stations 2 and 3 record 8 ms late and 5 ms early: with one offset per station the
    differences are recovered; the common one is the prior's (a time shift of a constant
    velocity is a translation): held at its zero while iterating, free to its whole prior in
    the covariance. Without them the fit cannot explain the measurements."""
    rng = np.random.default_rng(41)
    prob, truth = _problem(rng, True)
    start = retract(prob, replace(truth, sync=np.full(3, 0.004)),  # a common 4 ms to leave
                    1e-3 * rng.normal(size=(45, 12)), np.zeros(prob.n_globals))
    est, sol, info = gauss_newton(prob, start, max_iter=20, tol=1e-12)
    assert info.converged and info.costs[-1] < 1e-3, info.costs
    np.testing.assert_allclose(est.sync[1:] - est.sync[0], OFFSETS_S[1:], atol=5e-6)
    assert abs(np.mean(est.sync)) < 1e-8  # (this problem's data do not pull it either)
    sl = slice(prob.sync_col, prob.sync_col + 3)
    held_cov = solve_arrow(assemble(prob, est)[0], want_cov=True).cov_g[sl, sl]
    # while iterating the mean is held (COMMON_SYNC_HOLD_S, 1 us); the covariance releases it
    assert held_cov.sum() / 9 < (2 * COMMON_SYNC_HOLD_S) ** 2, held_cov.sum() / 9
    var_mean = sol.cov_g[sl, sl].sum() / 9  # the mean's variance: the prior's, 1/3 s^2
    assert abs(var_mean - 1.0 / 3.0) < 0.01 / 3.0, var_mean
    held, truth0 = _problem(rng, False)
    _, _, info0 = gauss_newton(held, truth0, max_iter=20, tol=1e-12)
    # without them the stations' positions take what they can (a time offset at constant
    # velocity is a shift along it), against their 1 mm prior: the cost stays
    assert info0.costs[-1] > 1e3 * info.costs[-1] and info0.costs[-1] > 1.0, info0.costs[-1]
