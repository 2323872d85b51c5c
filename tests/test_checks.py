"""Self-checks (rtsgt.checks): the inter-prism distance check, its effective sample size and
its verdict, tested against series whose statistics are known in closed form."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.signal import lfilter

from rtsgt.checks.distances import (
    effective_sample_size,
    inter_prism_check,
    inter_prism_z,
    mean_z2_verdict,
    pose_speed,
)
from rtsgt.errors import RtsgtWarning


def _series(rng, T, P, shared, phi, common):
    """Unit-variance z: a constant ``sqrt(shared) a`` plus an AR(1) (``phi``) part whose
    ``P`` series share ``common`` of their innovations."""
    e = np.sqrt(common) * rng.standard_normal((T, 1)) + np.sqrt(1 - common) * \
        rng.standard_normal((T, P))
    x = lfilter([np.sqrt(1 - phi ** 2)], [1, -phi], e, axis=0)
    x[0] = e[0]
    return np.sqrt(shared) * rng.standard_normal(P) + np.sqrt(1 - shared) * x


def test_effective_sample_size_closed_forms():
    rng = np.random.default_rng(0)
    T = 4000
    assert effective_sample_size(rng.standard_normal((T, 3))) == pytest.approx(3 * T, rel=0.05)
    same = np.repeat(rng.standard_normal((T, 1)), 3, axis=1)
    assert effective_sample_size(same) == pytest.approx(T, rel=0.05)
    for phi in (0.5, 0.9):
        n = np.mean([effective_sample_size(_series(rng, T, 1, 0.0, phi, 0.0))
                     for _ in range(20)])
        assert n == pytest.approx(T * (1 - phi ** 2) / (1 + phi ** 2), rel=0.15), phi
    # a component shared by the whole series: few independent samples, whatever T
    n = np.median([effective_sample_size(_series(rng, T, 1, 0.6, 0.0, 0.0))
                   for _ in range(50)])
    assert n < 20


@pytest.mark.parametrize("shared, phi, common", [
    (0.0, 0.0, 0.0), (0.0, 0.9, 0.5), (0.3, 0.9, 0.3), (0.6, 0.95, 0.0), (0.1, 0.99, 0.5),
])
def test_the_verdict_rarely_fails_an_honest_covariance(shared, phi, common):
    """With z of unit variance (shared, correlated, correlated between pairs), 'consistent'
    in about 95 % of 400 runs (the chi-square interval is an approximation: 1-10 %)."""
    rng = np.random.default_rng(7)
    bad = [mean_z2_verdict(z, np.full(z.shape, shared))["verdict"] != "consistent"
           for z in (_series(rng, 500, 3, shared, phi, common) for _ in range(400))]
    assert np.mean(bad) <= 0.10


def test_the_verdict_catches_a_covariance_too_small_or_too_large():
    """Mostly varying errors (shared 10 %), 500 poses: a covariance 1.6x too small, or 2x too
    large, is flagged in most runs and in the right direction."""
    rng = np.random.default_rng(8)
    verdicts = {"optimistic": [], "pessimistic": []}
    for _ in range(200):
        z = _series(rng, 500, 3, 0.1, 0.5, 0.3)
        shared = np.full(z.shape, 0.1)
        verdicts["optimistic"].append(mean_z2_verdict(np.sqrt(1.6) * z, shared)["verdict"])
        verdicts["pessimistic"].append(mean_z2_verdict(z / np.sqrt(2.0), shared)["verdict"])
    for want, got in verdicts.items():
        assert np.mean(np.asarray(got) == want) >= 0.8, want


def test_a_shared_error_drawn_small_does_not_fail_the_run():
    """The data cannot see a shared error the run drew small: with 70 % of the variance
    shared, a run whose z are half their predicted size is still consistent."""
    rng = np.random.default_rng(9)
    z = 0.5 * rng.standard_normal((600, 3))
    assert mean_z2_verdict(z, np.full(z.shape, 0.7))["verdict"] == "consistent"
    assert mean_z2_verdict(z, np.full(z.shape, 0.0))["verdict"] == "pessimistic"


def test_pose_speed_by_central_differences_within_runs():
    t = np.r_[np.arange(0, 10, 0.2), np.arange(20, 25, 0.2)]
    p = np.column_stack([0.5 * t, np.zeros_like(t), np.zeros_like(t)])
    p[t >= 20, 0] = 3.0  # standing after the gap
    v = pose_speed(t, p)
    np.testing.assert_allclose(v[t < 10], 0.5, rtol=1e-12)
    np.testing.assert_allclose(v[t >= 20], 0.0, atol=1e-12)


def _robot(rng, sigma_scale):
    """Three prisms on a robot that stands 40 s, then drives at 1.2 m/s for 80 s; each prism
    position drawn with covariance sigma_scale^2 times the stated one, white."""
    t = np.arange(0, 120, 0.2)
    x = np.where(t < 40, 0.0, 1.2 * (t - 40))
    pos = np.column_stack([x, 0.1 * x, np.zeros_like(t)])
    ref = np.array([[0.0, 0.0, 0.5], [0.8, 0.0, 0.5], [0.3, 0.7, 0.5]])
    sig = np.array([1.0, 1.5, 2.0]) * 1e-3
    cov = np.zeros((t.size, 3, 3, 3))
    for i in range(3):
        cov[:, i] = sig[i] ** 2 * np.eye(3)
    xyz = pos[:, None, :] + ref[None] + sigma_scale * rng.standard_normal((t.size, 3, 3)) \
        * sig[None, :, None]
    ref_cov = (0.2e-3) ** 2 * np.eye(9)
    return t, pos, xyz, cov, ref, ref_cov


def test_inter_prism_check_on_a_robot_with_known_errors():
    rng = np.random.default_rng(3)
    t, pos, xyz, cov, ref, ref_cov = _robot(rng, 1.0)
    near = np.full((t.size, 3), 0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an honest covariance raises no warning
        out = inter_prism_check(t, pos, xyz, cov, near, ref, ref_cov, ["1", "2", "3"],
                                varying_cov=cov)
    assert out["overall"]["verdict"] == "consistent"
    assert out["overall"]["mean_z2"] == pytest.approx(1.0, abs=0.15)
    r = out["regimes"]
    assert (r["static"]["poses"], r["cruising"]["poses"], r["manoeuvring"]["poses"]) == \
        (200, 399, 1)  # the pose where the motion starts is between
    assert r["far"]["poses"] == 0 and r["manoeuvring"]["verdict"] == "too few poses"
    z, shared, pairs = inter_prism_z(xyz, cov, ref, ref_cov, varying_cov=cov)
    assert pairs == [(0, 1), (0, 2), (1, 2)] and np.all(shared < 0.05)
    # errors 1.5x the stated sigma: the check says the covariance is too small, and warns
    t, pos, xyz, cov, ref, ref_cov = _robot(rng, 1.5)
    with pytest.warns(RtsgtWarning, match="covariance is too small"):
        out = inter_prism_check(t, pos, xyz, cov, near, ref, ref_cov, ["1", "2", "3"],
                                varying_cov=cov)
    assert out["overall"]["verdict"] == "optimistic"
    assert out["overall"]["mean_z2"] == pytest.approx(2.25, rel=0.15)

