"""The odometry's levels started from a previous fit's (the clock's next association): the same
optimum as from the default start (issue 24 item 4: the estimate's speed without changing it)."""

from __future__ import annotations

import numpy as np
import pytest

from rtsgt.evaluation.mounting import fit_mounting
from test_evaluation_mounting import LEVER, T0, drifting, truth


def test_levels_from_a_previous_fit_give_the_same_estimate():
    t = T0 + 1.0 + 0.1 * np.arange(300)
    est, gt = drifting(t, np.random.default_rng(43), clock=0.0, white_m=0.03)
    g = gt(t)
    v = (truth(t + 1e-4)[0] - truth(t - 1e-4)[0]) / 2e-4
    R = truth(t + 1e-4)[1] @ np.swapaxes(truth(t - 1e-4)[1], 1, 2)
    w = np.stack([np.array([r[2, 1], r[0, 2], r[1, 0]]) for r in R]) / 2e-4
    kw = {"estimate": "rotation,clock", "lever": LEVER, "gt_velocity": v,
          "gt_angular_velocity": w}
    cold = fit_mounting(g.position, g.rotation, g.cov, est.position, est.rotation, **kw)
    assert cold.model == "odometry"
    start = [cold.odometry[c] * 1.2 for c in cold.odometry]  # 20 % off: the next association
    warm = fit_mounting(g.position, g.rotation, g.cov, est.position, est.rotation, **kw,
                        odometry_levels=start)
    for c in cold.odometry:
        assert warm.odometry[c] == pytest.approx(cold.odometry[c], rel=0.01)
    s = np.sqrt(np.diagonal(cold.covariance))
    assert abs(warm.clock_offset - cold.clock_offset) < 0.01 * s[-1]
    np.testing.assert_allclose(np.sqrt(np.diagonal(warm.covariance)), s, rtol=0.01)
