"""The static-stretch noise self-check (rtsgt.checks.static) on synthetic static prisms whose
noise is known: white noise of the stated covariance, the same scaled, and white plus a
first-order Gauss-Markov process of known correlation time."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.signal import lfilter

from rtsgt.checks.static import (
    COMPONENTS,
    EDGE_MARGIN_S,
    MIN_STATIC_S,
    MOVING_Z2,
    gauss_markov_fit,
    lag_one_test,
    static_noise_check,
    static_stretches,
)
from rtsgt.errors import RtsgtWarning
from rtsgt.interpolation.gp import fit_track
from rtsgt.interpolation.prisms import gp_velocity_z2
from rtsgt.types import PrismTrack

DT = 0.4
#: One-sigma white noise along the line of sight and across it (horizontal, vertical), m.
SIGMA = np.array([2e-3, 0.5e-3, 0.3e-3])
#: Three stretches (start, samples), s: the robot stands at a different place in each.
STRETCHES = ((0.0, 40), (100.0, 30), (200.0, 50))


def _frame(u):
    h = np.cross([0.0, 0.0, 1.0], u)
    h /= np.linalg.norm(h)
    return np.stack([u, h, np.cross(u, h)])


def _run(rng, scale=1.0, fraction=0.0, tau=1.0, prisms=3):
    """Tracks of ``prisms`` static prisms, each seen by its own station, over STRETCHES; noise
    ``scale`` times the stated white sigma, of which ``fraction`` of the variance is a
    Gauss-Markov process of correlation time ``tau``; an offset per stretch (a systematic
    error, not noise) and a "calibration" source the check must leave out."""
    tracks, stations = {}, {}
    phi = np.exp(-DT / tau)
    for p in range(prisms):
        station = rng.uniform(-50, 50, 3)
        t, xyz, cov = [], [], []
        for t0, n in STRETCHES:
            at = station + rng.uniform(5, 60) * np.r_[np.cos(a := rng.uniform(0, 2 * np.pi)),
                                                      np.sin(a), rng.uniform(-0.05, 0.05)]
            E = _frame((at - station) / np.linalg.norm(at - station))
            white = rng.standard_normal((n, 3))
            gm = lfilter([np.sqrt(1 - phi ** 2)], [1, -phi], rng.standard_normal((n, 3)),
                         axis=0)
            gm[0] = rng.standard_normal(3)  # stationary from the first sample
            e = scale * (np.sqrt(1 - fraction) * white + np.sqrt(fraction) * gm) * SIGMA
            keep = rng.random(n) > 0.05  # single losses inside a stretch
            t.append(t0 + DT * np.arange(n)[keep])
            xyz.append((at + rng.normal(0, 2e-3, 3) + e @ E)[keep])
            cov.append(np.tile(E.T @ np.diag(SIGMA ** 2) @ E, (keep.sum(), 1, 1)))
        t, xyz, cov = np.concatenate(t), np.concatenate(xyz), np.concatenate(cov)
        by_source = {"instrument": 0.7 * cov, "tilt": 0.3 * cov, "calibration": 10.0 * cov}
        sid = str(p + 1)
        tracks[sid] = PrismTrack(t, xyz, 11.0 * cov, by_source, sid, "world", sid)
        stations[sid] = station
    iv = np.array([[t0 - 0.1, t0 + DT * n] for t0, n in STRETCHES])
    return tracks, stations, iv


def _flags(out):
    return [(p, c, test, e[c][test]["verdict"]) for p, e in out["prisms"].items()
            for c in COMPONENTS for test in ("level", "correlation")
            if e[c][test]["verdict"] != "consistent"]


def test_static_stretches_cut_the_margins_and_end_at_motion_gaps_and_turns():
    t = np.round(np.arange(0.0, 80.0, 0.2), 6)
    t = t[(t <= 41.0) | (t >= 43.0)]  # no pose between 41 and 43 s
    x = np.clip(0.5 * (t - 20.0), 0.0, 5.0)  # standing, 10 s at 0.5 m/s, standing
    yaw = 0.5 * np.clip(t - 55.0, 0.0, 10.0)  # from 55 to 65 s it turns on the spot
    arm = np.stack([np.cos(yaw), np.sin(yaw), 0 * yaw], axis=1)
    xyz = np.stack([np.column_stack([x, 0 * x, 0 * x]) + r * arm for r in (0.0, 0.5)], axis=1)
    iv = static_stretches(t, xyz)
    # standing poses: 0-19.8 s (the pose at 20 s has a moving neighbour), 30.2-41 s, 43-54.8
    # s, 65.2-79.8 s; each shortened by the margin at both ends
    runs = [(0.0, 19.8), (30.2, 41.0), (43.0, 54.8), (65.2, 79.8)]
    expected = [(a + EDGE_MARGIN_S, b - EDGE_MARGIN_S) for a, b in runs]
    np.testing.assert_allclose(iv, expected, atol=1e-9)
    # a run shorter than the margins plus the minimum is no stretch
    short = t < 2 * EDGE_MARGIN_S + MIN_STATIC_S - 0.1
    assert static_stretches(t[short], xyz[short]).shape == (0, 2)
    assert static_stretches(t[:1], xyz[:1]).shape == (0, 2)


def _stops(rng, smooth_s, dt=0.2, stop_s=(7.0, 30.0), noise_m=0.3e-3):
    """Poses every ``dt`` of two prisms of a robot standing ``stop_s[0]`` s, starting along a
    quintic ramp to 1 m/s over 3.75 s (the simulator's peak acceleration of 0.5 m/s^2),
    driving, braking the same way, standing ``stop_s[1]`` s and starting again; the poses'
    noise ``noise_m`` (m, each axis) smoothed over ``smooth_s`` as a GP's between measurements
    that far apart. Returns the times,
    the prisms (T, 2, 3) and the true stops (2, 2), s."""
    ramp = 3.75
    edges = np.cumsum([0.0, stop_s[0], ramp, 10.0, ramp, stop_s[1], ramp, 5.0])
    t = np.arange(0.0, edges[-1], dt)
    s = np.clip((t - edges[1]) / ramp, 0, 1)
    v = s ** 3 * (10 - 15 * s + 6 * s * s)
    s = np.clip((t - edges[3]) / ramp, 0, 1)
    v -= s ** 3 * (10 - 15 * s + 6 * s * s)
    s = np.clip((t - edges[5]) / ramp, 0, 1)
    v += s ** 3 * (10 - 15 * s + 6 * s * s)
    x = np.r_[0.0, np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)]
    k = int(round(smooth_s / dt))
    noise = np.stack([np.convolve(rng.standard_normal(t.size + k - 1), np.ones(k) / np.sqrt(k),
                                  "valid") for _ in range(6)], axis=1).reshape(-1, 2, 3)
    xyz = np.stack([np.column_stack([x, 0 * x, 0 * x]) + [0.0, 0.5 * p, 0.0]
                    for p in range(2)], axis=1) + noise_m * noise
    return t, xyz, np.array([[0.0, edges[1]], [edges[4], edges[5]]])


@pytest.mark.parametrize("smooth_s", [0.4, 1.2])
def test_a_short_stop_is_found_and_every_stretch_ends_before_the_robot_moves(smooth_s):
    """A 7 s stop (the real deployment of 2022-11-09 has 5-8 s ones) was no stretch when the
    stretch ended where the speed passed 0.05 m/s less 2 s margins: the robot has moved 8 mm
    when its speed reaches 0.05 m/s. The speed's noise floor ends the run within 0.5 s of
    the truth, at the rate of the real pose noise (2.5 Hz) and of sparse data."""
    for seed in range(5):
        t, xyz, stops = _stops(np.random.default_rng(seed), smooth_s)
        iv = static_stretches(t, xyz)
        assert iv.shape == (2, 2), (seed, iv)
        # inside the true stops, and covering them but for at most the margins
        assert np.all(iv[:, 0] >= stops[:, 0]) and np.all(iv[:, 1] <= stops[:, 1]), (seed, iv)
        lost = (stops[:, 1] - stops[:, 0]) - (iv[:, 1] - iv[:, 0])
        assert np.all(lost <= 2 * EDGE_MARGIN_S), (seed, lost)


def _creeping(rng, creep_m_s, noise_m=0.3e-3, dt=0.2):
    """Two prisms measured every ``dt`` s with white noise ``noise_m`` (m, each axis): a robot
    standing 20 s, driving 10 s at 0.5 m/s, moving ``creep_m_s`` for 15 s (under the standing
    speed), driving 10 s and standing 20 s, each change of speed a quintic ramp over 2 s.
    Returns the times, the measured prisms (T, 2, 3), the GP of each (its ``Qc`` fitted) and
    the intervals (3, 2) s of the slow parts at their own speed."""
    levels = np.array([0.0, 0.5, creep_m_s, 0.5, 0.0])
    starts = np.cumsum([0.0, 20.0, 10.0, 15.0, 10.0])
    ramp = 2.0
    t = np.arange(0.0, starts[-1] + 20.0, dt)
    speed = np.full(t.size, levels[0])
    for a, lo, hi in zip(starts[1:], levels[:-1], levels[1:], strict=True):
        s = np.clip((t - a) / ramp, 0.0, 1.0)
        speed += (hi - lo) * s**3 * (10 - 15 * s + 6 * s * s)
    x = np.r_[0.0, np.cumsum(0.5 * (speed[1:] + speed[:-1]) * dt)]
    truth = np.stack([np.column_stack([x, 0 * x + 0.5 * p, 0 * x]) for p in range(2)], axis=1)
    xyz = truth + noise_m * rng.standard_normal(truth.shape)
    cov = np.broadcast_to(noise_m**2 * np.eye(3), (t.size, 3, 3))
    gps = {str(p): fit_track((t, xyz[:, p], cov)) for p in range(2)}
    slow = np.array([[0.0, starts[1]], [starts[2] + ramp, starts[3]], [starts[4] + ramp, t[-1]]])
    return t, xyz, gps, slow


@pytest.mark.parametrize("seed", range(3))
def test_a_robot_creeping_through_a_whole_run_does_not_stand(seed):
    """A robot moving at 30 mm/s for 15 s between two drives: every pose is under the standing
    speed and the run's own noise floor is its steady speed, so the speed alone takes it for
    standing (the real static stretches of 2022-11-10 hold such a run: 12-15 mm/s at 71 m,
    docs/self-checks.md#stretches). Its GP's velocity, tested against the GP's covariance,
    is not noise; the stops' is, and they stand."""
    t, xyz, gps, slow = _creeping(np.random.default_rng(seed), 0.03)
    z2 = gp_velocity_z2(gps, t)
    assert z2.shape == (t.size, 2) and np.all(np.isfinite(z2))
    alone = static_stretches(t, xyz)
    assert alone.shape == (3, 2), alone  # the creep taken for a stop by the speed alone
    iv = static_stretches(t, xyz, z2)
    assert iv.shape == (2, 2), iv
    assert np.all(iv[:, 0] >= slow[[0, 2], 0]) and np.all(iv[:, 1] <= slow[[0, 2], 1]), iv
    np.testing.assert_allclose(iv, alone[[0, 2]])  # the stops as the speed finds them
    inside = (t > slow[1, 0] + 1.0) & (t < slow[1, 1] - 1.0)
    assert np.median(z2[inside]) > MOVING_Z2, np.median(z2[inside])
    still = (t > 2.0) & (t < slow[0, 1] - 2.0) | (t > slow[2, 0] + 2.0) & (t < slow[2, 1] - 2.0)
    assert np.median(z2[still]) < 0.25 * MOVING_Z2, np.median(z2[still])


@pytest.mark.parametrize("confidence", [0.95, 0.99])
def test_the_lag_one_test_holds_its_level_on_white_series(confidence):
    rng = np.random.default_rng(1)
    group = np.repeat([0, 1, 2], [12, 40, 60])
    reps = 4000
    out = 0
    for _ in range(reps):  # the von Neumann ratio's beta approximation, at its tails
        z = rng.standard_normal(group.size)
        z -= (np.bincount(group, z) / np.bincount(group))[group]
        r1, (lo, hi) = lag_one_test(z, group, confidence)
        out += not lo <= r1 <= hi
    alpha = 1.0 - confidence
    assert abs(out / reps - alpha) < 3.0 * np.sqrt(alpha * (1 - alpha) / reps) + 1e-3


def test_white_noise_of_the_stated_covariance_passes_at_the_family_level():
    rng = np.random.default_rng(2)
    runs, flagged = 300, 0
    sums = np.zeros(3)
    dof = 0
    for _ in range(runs):
        out = static_noise_check(*_run(rng), warn=False)
        flagged += bool(_flags(out))
        for e in out["prisms"].values():
            sums += [e[c]["level"]["variance_ratio"] * (e["samples"] - 3) for c in COMPONENTS]
            dof += e["samples"] - 3
    assert out["tests"] == 18 and out["confidence"] == pytest.approx(1 - 0.05 / 18)
    e = out["prisms"]["1"]
    for c, sigma in zip(COMPONENTS, SIGMA, strict=True):
        # the line of sight from the measured position: off by the noise over the range
        assert e[c]["predicted_sigma_mm"] == pytest.approx(sigma * 1e3, rel=1e-5)
    # the pooled variance ratio per component (about 100 000 dof: +-0.005) and the share of
    # runs with any verdict but consistent: 5 % by Bonferroni, a little less as the tests
    # are not all independent (300 runs: +-1.3 %)
    np.testing.assert_allclose(sums / dof, 1.0, atol=0.02)
    assert 0.015 <= flagged / runs <= 0.08, flagged / runs


def test_noise_larger_or_smaller_than_stated_is_caught():
    rng = np.random.default_rng(3)
    with pytest.warns(RtsgtWarning, match=r"static stretches: prism 1 .*range level optimistic"):
        out = static_noise_check(*_run(rng, scale=1.6, prisms=1))
    e = out["prisms"]["1"]
    assert e["samples"] == pytest.approx(120 * 0.95, abs=10) and e["stretches"] == 3
    for c in COMPONENTS:
        assert e[c]["level"]["variance_ratio"] == pytest.approx(1.6 ** 2, rel=0.25)
        assert e[c]["level"]["verdict"] == "optimistic"
        assert e[c]["correlation"]["verdict"] == "consistent"
        assert e[c]["correlation"]["correlation_time_s"] is None
        assert e[c]["observed_sigma_mm"] / e[c]["predicted_sigma_mm"] == pytest.approx(
            np.sqrt(e[c]["level"]["variance_ratio"]), rel=1e-9)
    out = static_noise_check(*_run(rng, scale=0.6, prisms=1), warn=False)
    assert {out["prisms"]["1"][c]["level"]["verdict"] for c in COMPONENTS} == {"pessimistic"}


def test_correlated_noise_is_flagged_with_its_correlation_time():
    rng = np.random.default_rng(4)
    found, taus, fractions = 0, [], []
    for _ in range(20):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = static_noise_check(*_run(rng, fraction=0.5, tau=1.0))
        found += any(test == "correlation" and v == "optimistic" for *_, test, v in _flags(out))
        for e in out["prisms"].values():
            for c in COMPONENTS:
                co = e[c]["correlation"]
                if co["verdict"] == "optimistic":
                    taus.append(co["correlation_time_s"])
                    fractions.append(co["correlated_fraction"])
    # half the variance correlated over 1 s (2.5 samples): every run flagged (half of its
    # components), and the fit's correlation time close to the truth, pooled over the flagged
    # components (their median 0.98 s, quartiles 0.6 and 1.4 s); the correlated share is
    # overstated on such short stretches and where the test picked the strongest (0.64)
    assert found == 20
    assert np.median(taus) == pytest.approx(1.0, rel=0.2)
    assert np.median(fractions) == pytest.approx(0.5, abs=0.2)


def test_gauss_markov_fit_on_a_long_series():
    rng = np.random.default_rng(5)
    t = DT * np.arange(2000)
    gm = lfilter([np.sqrt(1 - np.exp(-2 * DT / 2.0))], [1, -np.exp(-DT / 2.0)],
                 rng.standard_normal(t.size))
    z = 3.0 * (np.sqrt(0.7) * gm + np.sqrt(0.3) * rng.standard_normal(t.size))
    group = np.repeat(np.arange(4), 500)  # four series of 200 s, each fitted in blocks
    v, f, tau, (lo, hi) = gauss_markov_fit(z, t, group)
    assert v == pytest.approx(9.0, rel=0.15)
    assert f == pytest.approx(0.7, abs=0.07)
    assert tau == pytest.approx(2.0, rel=0.2) and lo < 2.0 < hi


def test_without_a_static_stretch_the_check_says_so():
    tracks, stations, _ = _run(np.random.default_rng(6), prisms=1)
    out = static_noise_check(tracks, stations, np.zeros((0, 2)))
    assert out["prisms"] == {} and out["note"] == "no static stretch" and out["tests"] == 0
    out = static_noise_check(tracks, stations, [[500.0, 520.0]])
    assert out["note"] == "no measurement inside the static stretches"
    # a prism with few samples is reported without a verdict
    out = static_noise_check(tracks, stations, [[0.0, 6.0]])
    assert out["prisms"]["1"]["range"]["level"]["verdict"] == "too few samples"


@pytest.mark.slow
def test_simulated_correlated_noise_is_flagged_by_the_pipeline(tmp_path):
    """The pipeline's check on simulated deployments with time-correlated noise
    (``RealityEffects.only("correlated_noise")``: Gauss-Markov angle and distance noise of
    1 s, 1" and 1 mm beside the white 1" and 2 mm), pooled over 24 short deployments."""
    from rtsgt.io.deployment import load_deployment
    from rtsgt.pipeline import run_pipeline
    from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
    from rtsgt.simulation.reality import RealityEffects

    fx = RealityEffects.only("correlated_noise")
    checked, flagged, taus = 0, 0, []
    for seed in range(7000, 7024):
        sim = simulate_deployment(SimulationConfig(duration_s=60.0, reality=fx),
                                  np.random.default_rng(seed))
        data, opts = load_deployment(write_deployment(sim, tmp_path / f"d{seed}"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            record = run_pipeline(data, opts.updated(seed=seed, engine="linear", samples=20))
        out = record.self_checks["static_noise"]
        if not out["prisms"]:
            continue  # line-of-sight losses cut the initial stop short
        checked += 1
        flagged += bool(_flags(out))
        taus += [e[c]["correlation"]["correlation_time_s"] for e in out["prisms"].values()
                 for c in COMPONENTS if e[c]["correlation"]["correlation_time_s"] is not None]
    assert checked >= 18
    assert flagged / checked >= 0.5, (flagged, checked)
    assert np.median(taus) == pytest.approx(1.0, rel=0.35), taus
