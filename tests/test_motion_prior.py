"""A motion prior whose strength follows the robot's motion (rtsgt.interpolation.motion).

References: the truth of simulated tracks (a robot that stands, accelerates, cruises, brakes
and stands again; and tracks drawn from the WNOA prior itself, where one Qc is right), and
hand-made events for the classes of the intervals.
"""

from __future__ import annotations

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.interpolation.gp import fit_track, wnoa_phi, wnoa_q
from rtsgt.interpolation.motion import (
    CLASS_NAMES,
    MotionEvents,
    fit_motion_prior,
    interval_classes,
    motion_events,
)
from rtsgt.interpolation.prisms import fit_prism_gp
from rtsgt.options import InterpolationOptions

SIGMA = 1e-3  # measurement noise, m


def _nees(gp, t, truth):
    q = gp.query(t)
    e = q.position - truth
    return np.einsum("ni,nij,nj->n", e, np.linalg.inv(q.position_cov), e) / 3.0


def _fit(t, y, R):
    pilot, info = fit_prism_gp((t, y, R), "loo", 3.0, "test track")
    fit = fit_motion_prior((t, y, R), pilot.qc, motion_events({"p": pilot}), max_gap_s=3.0,
                           loo_constant=info["loo_log_predictive"])
    return pilot, fit, fit_track((t, y, R), qc=pilot.qc, max_gap_s=3.0, qc_scale=fit.qc_scale)


def test_each_interval_takes_the_fastest_motion_of_the_robot_inside_it():
    """The class of an interval is the fastest class of any event in it, its ends included:
    an interval of one prism that bridges a gap takes what another prism saw meanwhile."""
    ev = MotionEvents(np.array([0.0, 0.4, 0.8, 1.0, 1.2, 1.6, 2.0, 5.0]),
                      np.array([0, 0, 1, 4, 2, 1, 0, 3]))
    got = interval_classes([0.0, 0.4, 0.9, 1.1, 1.7, 2.5, 4.0, 6.0], ev)
    np.testing.assert_array_equal(got, [0, 1, 4, 2, 0, 0, 3])
    # an interval without any event (a track outside the events) counts as standing
    np.testing.assert_array_equal(interval_classes([7.0, 8.0], ev), [0])
    assert interval_classes([1.0], ev).shape == (0,)


def stop_and_go(rng):
    """Stand 20 s, accelerate at 0.5 m/s^2 for 2 s, cruise at 1 m/s for 20 s, brake at
    0.5 m/s^2 for 2 s, stand; 2.5 Hz measurements with white 1 mm noise."""
    t = np.cumsum(rng.uniform(0.3, 0.5, 160))

    def truth(tt):
        a = 0.5
        s = np.where(tt < 20, 0.0, np.where(tt < 22, 0.5 * a * (tt - 20) ** 2, 1.0 + (tt - 22)))
        s = np.where(tt < 42, s, 21.0 + (tt - 42) - 0.5 * a * (tt - 42) ** 2)
        s = np.where(tt < 44, s, 22.0)
        return np.column_stack([s, 0.2 * s, np.zeros_like(s)])

    y = truth(t) + rng.normal(0.0, SIGMA, (t.size, 3))
    return t, y, np.tile(SIGMA**2 * np.eye(3), (t.size, 1, 1)), truth


@pytest.mark.slow
def test_a_robot_that_stops_and_goes_gets_a_prior_per_class_and_stays_honest():
    """Standing, the prior is orders of magnitude tighter than while accelerating; the
    interpolated positions between measurements are honest in both (pooled over 20 tracks:
    with one Qc they are too, since this simulated noise is white; what changes is that each
    class gets the Qc its own motion calls for)."""
    standing, moving, ratio = [], [], []
    for seed in range(20):
        t, y, R, truth = stop_and_go(np.random.default_rng(seed))
        _, fit, gp = _fit(t, y, R)
        assert fit.chosen == "classes" and fit.loo_classes > fit.loo_constant
        assert fit.intervals["standing"] > 60
        ratio.append(fit.scales["standing"] / fit.scales["0.3-1 m/s^2"])
        tq = 0.5 * (t[1:] + t[:-1])
        n = _nees(gp, tq, truth(tq))
        still = (tq < 19.5) | (tq > 44.5)
        standing.append(n[still])
        moving.append(n[~still])
    assert np.max(ratio) < 1e-3
    assert 0.75 < np.mean(np.concatenate(standing)) < 1.35
    assert 0.75 < np.mean(np.concatenate(moving)) < 1.3


def test_on_tracks_from_the_prior_itself_the_classes_do_no_harm():
    """Where one Qc is the truth (tracks drawn from the WNOA prior), classes chosen from the
    data's own accelerations still give honest interpolation: pooled NEES/dof within 0.1
    of 1 over 30 tracks (the constant Qc gives 1.01 on the same tracks)."""
    nees = []
    for seed in range(30):
        rng = np.random.default_rng(100 + seed)
        t = np.cumsum(rng.uniform(0.3, 0.5, 161))
        grid = np.sort(np.concatenate([t, 0.5 * (t[1:] + t[:-1])]))
        x = np.array([0.0, 0.0, 0.0, 0.5, 0.0, 0.0])
        states = [x]
        for d in np.diff(grid):
            x = wnoa_phi(d) @ x + rng.multivariate_normal(np.zeros(6), wnoa_q(d, 0.01))
            states.append(x)
        states = np.array(states)
        knot = np.isin(grid, t)
        y = states[knot, :3] + rng.normal(0.0, SIGMA, (t.size, 3))
        _, _, gp = _fit(t, y, np.tile(SIGMA**2 * np.eye(3), (t.size, 1, 1)))
        nees.append(_nees(gp, grid[~knot], states[~knot, :3]))
    assert 0.9 < np.mean(np.concatenate(nees)) < 1.1


def test_the_option_is_checked_and_the_paper_setting_stays_reachable():
    assert InterpolationOptions().motion_prior == "classes"
    assert InterpolationOptions(motion_prior="constant").motion_prior == "constant"
    with pytest.raises(InputError, match="motion_prior"):
        InterpolationOptions(motion_prior="regimes")
    assert CLASS_NAMES[0] == "standing" and len(CLASS_NAMES) == 5
