"""Posterior cross-covariance of a GP track between two times (rtsgt.interpolation.cross)."""

from __future__ import annotations

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.interpolation.cross import gp_cross_covariance
from rtsgt.interpolation.gp import fit_track
from test_gp import measure, random_spd, simulate_prior  # helpers of the GP tests


def _track(rng, n=30, qc=0.05):
    t = np.cumsum(rng.uniform(0.3, 0.6, n))
    R = random_spd(rng, n, 4e-6, cond=5)
    x = simulate_prior(rng, t, qc, np.array([1.0, 2.0, 0.0, 0.5, -0.2, 0.0]))
    return t, measure(rng, x[:, :3], R), R


def _augmented(t, y, R, qc, taus, scale=None):
    """Exact reference: the query times as knots with an uninformative measurement (each new
    interval with the scale of Qc of the interval it splits); the posterior is Markov along
    the knots, so Cov between knots is the chained lag-one one."""
    ta = np.concatenate([t, taus])
    order = np.argsort(ta, kind="stable")
    ya = np.concatenate([y, np.zeros((taus.size, 3))])[order]
    Ra = np.concatenate([R, np.tile(np.eye(3) * 1e8, (taus.size, 1, 1))])[order]
    sa = None
    if scale is not None:
        k = np.clip(np.searchsorted(t, ta[order][:-1], side="right") - 1, 0, t.size - 2)
        sa = scale[k]
    return fit_track((ta[order], ya, Ra), qc=qc, max_gap_s=1e9, qc_scale=sa), np.argsort(order)


@pytest.mark.parametrize("scaled", [False, True])
def test_cross_covariance_equals_the_augmented_posterior(scaled):
    """Also with a Qc scaled per interval (a motion prior): the bridge scales with it."""
    rng = np.random.default_rng(3)
    t, y, R = _track(rng)
    qc = 0.05
    scale = np.exp(rng.uniform(-3.0, 2.0, t.size - 1)) if scaled else None
    gp = fit_track((t, y, R), qc=qc, max_gap_s=1e9, qc_scale=scale)
    # pairs: same interval (both orders), adjacent intervals, far apart, on knots, equal times
    k = 10
    pairs = [(t[k] + 0.1, t[k] + 0.2), (t[k] + 0.2, t[k] + 0.1), (t[k] + 0.1, t[k + 1] + 0.1),
             (t[3] + 0.05, t[20] + 0.05), (t[5], t[9]), (t[5], t[5] + 0.1), (t[7] + 0.1,) * 2]
    for a, b in pairs:
        taus = np.unique([a, b])
        taus = taus[~np.isin(taus, t)]
        aug, pos = _augmented(t, y, R, qc, taus, scale)
        ia = int(np.flatnonzero(np.isclose(aug.t, a, rtol=0, atol=0))[0])
        ib = int(np.flatnonzero(np.isclose(aug.t, b, rtol=0, atol=0))[0])
        lo, hi = min(ia, ib), max(ia, ib)
        ref = aug.cov[lo].copy()
        for m in range(lo, hi):
            ref = ref @ np.linalg.solve(aug.cov[m], aug.cross_cov[m])
        if ia > ib:
            ref = ref.T
        got = gp_cross_covariance(gp, [a], [b])[0]
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_equal_times_give_the_query_covariance_and_outside_times_are_refused():
    rng = np.random.default_rng(4)
    t, y, R = _track(rng)
    gp = fit_track((t, y, R), qc=0.05, max_gap_s=1e9)
    tau = np.sort(rng.uniform(t[0], t[-1], 50))
    c = gp_cross_covariance(gp, tau, tau)
    q = gp.query(tau, with_velocity=True)
    np.testing.assert_allclose(c, q.state_cov, rtol=1e-7, atol=1e-7 * np.abs(q.state_cov).max())
    with pytest.raises(InputError, match="inside the track"):
        gp_cross_covariance(gp, [t[0] - 1.0], [t[3]])
