"""The stations' clock offsets from the rigid body (rtsgt.clocks): a robot with three prisms
driving a known path, each prism seen by its station's clock, drifting against the first."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rtsgt.clocks import RATE_SIGMA, estimate_clock_offsets, walk_prior_info
from rtsgt.errors import InputError

BODY = np.array([[0.4, 0.0, 0.3], [-0.3, 0.35, 0.32], [-0.3, -0.35, 0.28]])
STATIONS = ["1", "2", "3"]


def _path(t):
    """A robot weaving and turning at about 0.7 m/s: positions (N, 3), rotations, and the
    world velocity of each body point (N, n, 3) (finite differences of 1 us)."""
    def pose(tt):
        yaw = 0.4 * np.sin(0.05 * tt) + 0.02 * tt
        p = np.stack([30 * np.cos(0.02 * tt), 20 * np.sin(0.035 * tt), 0.2 * np.sin(0.1 * tt)],
                     axis=-1)
        return p, Rotation.from_euler("z", yaw[:, None])

    def points(tt):
        p, R = pose(tt)
        return p[:, None] + np.stack([R.apply(b) for b in BODY], axis=1)

    h = 1e-6
    return points, (points(t + h) - points(t - h)) / (2 * h)


def _offsets(t, drift, level):
    """``t_recorded - t_true`` of stations 2 and 3 against station 1 (S=2, N)."""
    return np.stack([level + drift * (t - t[0]), -0.5 * level - 0.7 * drift * (t - t[0])])


def _observed(rng, t, drift, level, sigma, bias=0.0):
    """Each prism as its station saw it: where it was ``e`` before the time stamp, plus white
    noise; prism 3 displaced by ``bias`` along the body y axis."""
    points, vel = _path(t)
    e = _offsets(t, drift, level)
    xyz = points(t).copy()
    for k in (1, 2):
        xyz[:, k] = points(t - e[k - 1])[:, k]
    if bias:  # the prism sits elsewhere on the robot than the survey says
        xyz[:, 2] += _rotate_body(t, [0.0, bias, 0.0])
    xyz += rng.normal(0.0, sigma, xyz.shape)
    cov = np.broadcast_to(np.eye(3) * sigma**2, xyz.shape + (3,))
    return xyz, vel, cov, e


def _rotate_body(t, v):
    """``v`` (body frame) in the world frame at the times ``t``, (N, 3)."""
    yaw = 0.4 * np.sin(0.05 * t) + 0.02 * t
    return Rotation.from_euler("z", yaw[:, None]).apply(v)


@pytest.fixture(scope="module")
def pooled():
    """20 drives of 600 s at 5 Hz: the estimate's z against the truth at 1 Hz."""
    out = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        t = np.arange(0.0, 600.0, 0.2)
        drift = rng.uniform(10e-3, 20e-3) / 3600 * rng.choice([-1, 1])
        xyz, vel, cov, e = _observed(rng, t, drift, rng.uniform(-0.02, 0.02), 2e-3)
        est = estimate_clock_offsets(t, xyz, vel, cov, BODY, STATIONS, "1")
        tt = np.arange(0.0, 600.0, 1.0)
        m, s = est.at(tt)
        out.append((m - _offsets(tt, drift, e[0, 0])) / s)
    return np.concatenate([z.ravel() for z in out])


def test_the_offsets_are_recovered_within_their_sigma(pooled):
    """Pooled over 20 drives: the errors over their sigma have a mean square in [0.5, 1.25]
    (a sigma 12 % too small fails) and 90 % or more lie within 2 sigma."""
    assert 0.5 <= np.mean(pooled**2) <= 1.25, np.mean(pooled**2)
    assert np.mean(np.abs(pooled) < 2.0) >= 0.90


def test_a_prism_moved_on_the_robot_goes_to_the_pair_bias_not_the_clocks():
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 600.0, 0.2)
    xyz, vel, cov, e = _observed(rng, t, 15e-3 / 3600, 0.01, 2e-3, bias=0.02)
    est = estimate_clock_offsets(t, xyz, vel, cov, BODY, STATIONS, "1")
    m, s = est.at(t)
    assert np.all(np.abs(m - e) < 3 * s)
    moved = [p for p, (b, sb) in est.pair_bias_m.items() if abs(b) > 5 * sb]
    assert sorted(moved) == ["0-2", "1-2"]


def test_no_offset_in_the_data_gives_none():
    rng = np.random.default_rng(6)
    t = np.arange(0.0, 300.0, 0.2)
    xyz, vel, cov, _ = _observed(rng, t, 0.0, 0.0, 2e-3)
    est = estimate_clock_offsets(t, xyz, vel, cov, BODY, STATIONS, "1")
    m, s = est.at(t)
    assert np.all(np.abs(m) < 3 * s) and np.median(s) < 1e-3


def test_one_clock_can_only_be_measured_against_another():
    t = np.arange(0.0, 10.0, 0.2)
    xyz = np.zeros((t.size, 3, 3))
    with pytest.raises(InputError, match="reference station '9'"):
        estimate_clock_offsets(t, xyz, xyz, np.zeros((t.size, 3, 3, 3)), BODY, STATIONS, "9")


def test_the_clock_prior_is_the_sum_of_its_processes():
    """The prior's information inverts to the closed-form covariance of a level, a drift, a
    random walk and an integrated random walk of the rate (docs/clocks.md#the-prior), at
    uneven knots; with the defaults a constant drift of 20 ms an hour over 10 minutes costs
    the prior (drift / RATE_SIGMA)^2, not the 18.5 of a product of the two walks' priors."""
    knots = np.array([0.0, 40.0, 100.0, 160.0, 230.0, 300.0])
    q, qr, sl, sr = 1e-9, 2.8e-14, 1e-3, 1e-6
    a, b = np.meshgrid(knots, knots, indexing="ij")
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    cov = sl**2 + sr**2 * a * b + q * lo + qr * lo**2 * (3.0 * hi - lo) / 6.0
    np.testing.assert_allclose(np.linalg.inv(walk_prior_info(knots, q, qr, sl, sr)), cov,
                               rtol=1e-7)
    t = np.arange(11) * 60.0
    x = 20e-3 / 3600.0 * t
    cost = x @ walk_prior_info(t) @ x
    assert cost == pytest.approx((20e-3 / 3600.0 / RATE_SIGMA) ** 2, rel=0.05), cost
