"""The deployment simulator against its own truth (rtsgt.simulation.deployment)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from rtsgt.errors import InputError
from rtsgt.io import survey as io_survey
from rtsgt.measurement.atmosphere import instrument_correction_ppm
from rtsgt.measurement.instruments import ARCSEC
from rtsgt.measurement.polar import polar_to_cartesian
from rtsgt.noise.sources import NOISE_SOURCES
from rtsgt.simulation import SimulationConfig, simulate_deployment
from rtsgt.simulation import deployment as sim_deployment
from rtsgt.types import SurveyShots


@pytest.fixture(scope="module")
def sim30():
    """A 30-minute deployment with every noise source (the statistics need its size)."""
    return simulate_deployment(SimulationConfig(duration_s=1800.0), np.random.default_rng(11))


@pytest.fixture(scope="module")
def clean():
    """A noise-free deployment (atmosphere and dropouts kept)."""
    return simulate_deployment(SimulationConfig(duration_s=300.0).without_noise(), 5)


def _to_world(sim, obs, t_true):
    """Independent inversion of a tracked observation: atmosphere, polar model, station pose."""
    ppm = instrument_correction_ppm(sim.config.instrument, *sim.truth.model.weather_at(t_true))
    d_true = (obs.d + obs.additive_constant) * (1.0 + 1e-6 * ppm)
    T = sim.truth.T_world_station[obs.station]
    return polar_to_cartesian(obs.hz, obs.v, d_true) @ T.rotation.T + T.translation


def test_noise_free_observations_convert_back_to_the_true_prisms(clean):
    assert all(o.additive_constant == 0.01 for o in clean.observations)
    for obs in clean.observations:
        # no clock error: the stamp is the true time
        p_world = _to_world(clean, obs, obs.t)
        k = clean.truth.prism_ids.index(obs.prism)
        expected = clean.truth.model.prisms_at(obs.t)[:, k]
        assert np.max(np.abs(p_world - expected)) < 1e-9
        # the atmosphere really is in the raw distances (about +0.8 ppm here, i.e. not zero)
        ppm = clean.truth.observations[obs.station].ppm
        assert np.all(np.abs(ppm) > 0.1)


def test_noise_free_with_clock_offsets_needs_the_offset():
    cfg = SimulationConfig(duration_s=300.0, noise_instrument=False, noise_tilt=False,
                           noise_weather=False, noise_survey=False)
    sim = simulate_deployment(cfg, 8)
    for obs in sim.observations:
        ot = sim.truth.observations[obs.station]
        offset = sim.truth.clock_offset_s[obs.station]
        # constant offset plus a small jitter
        assert np.std(ot.clock_error_s) < 3 * cfg.time_sync_jitter_s
        assert np.max(np.abs(ot.clock_error_s - offset)) < 6 * cfg.time_sync_jitter_s
        t_true = obs.t + ot.clock_error_s
        k = sim.truth.prism_ids.index(obs.prism)
        p_world = _to_world(sim, obs, t_true)
        assert np.max(np.abs(p_world - sim.truth.model.prisms_at(t_true)[:, k])) < 1e-9
        # at the stamped time the prism is displaced by e_ts * v (up to 2 m/s x ~3 ms)
        moved = np.linalg.norm(p_world - sim.truth.model.prisms_at(obs.t)[:, k], axis=-1)
        assert moved.max() > 1e-5 or abs(offset) < 1e-5


def test_noise_free_gcp_and_survey(clean):
    g = clean.gcp
    tr = clean.truth
    ppm = instrument_correction_ppm(clean.config.instrument, *tr.model.weather_at(g.t))
    p_st = polar_to_cartesian(g.hz, g.v, g.distance * (1.0 + 1e-6 * ppm))
    for s, T in tr.T_world_station.items():
        m = g.station == s
        idx = [tr.gcp_markers.index(k) for k in g.marker[m]]
        np.testing.assert_allclose(p_st[m] @ T.rotation.T + T.translation, tr.gcp_world[idx],
                                   rtol=0, atol=1e-9)
    # survey, manual-shot convention x = d cosHz sinV, y = -d sinHz sinV, z = d cosV
    sv = clean.survey
    xyz = np.stack([sv.d * np.cos(sv.hz) * np.sin(sv.v), -sv.d * np.sin(sv.hz) * np.sin(sv.v),
                    sv.d * np.cos(sv.v)], axis=-1)
    n = len(tr.prism_ids)
    np.testing.assert_allclose(xyz[:n], tr.reference_body, rtol=0, atol=1e-12)
    np.testing.assert_allclose(xyz[n:], tr.gnss_body, rtol=0, atol=1e-12)
    assert sv.names[:n] == ("prism1", "prism2", "prism3")
    # one survey record for files and simulations, its points in the survey (body) frame
    assert isinstance(sv, SurveyShots) and io_survey.SurveyShots is SurveyShots
    np.testing.assert_allclose(sv.xyz, xyz, rtol=0, atol=1e-12)


def test_station_frames(sim30):
    tr = sim30.truth
    T1 = tr.T_world_station["1"]
    np.testing.assert_array_equal(T1.rotation, np.eye(3))
    np.testing.assert_array_equal(T1.translation, np.zeros(3))
    for T in tr.T_world_station.values():
        # levelled: each z axis is the vertical of a sphere of the Earth's radius below
        # station 1 (a few microradians from station 1's), and the rest is a yaw
        up = np.r_[T.translation[:2], 6.371e6 + T.translation[2]]
        np.testing.assert_allclose(T.rotation[:, 2], up / np.linalg.norm(up), atol=1e-12)
        np.testing.assert_allclose(T.rotation[2], [0, 0, 1], atol=5e-5)
    # stations around a site: pairwise distances of tens of metres, ranges of up to ~100 m
    pos = np.stack([T.translation for T in tr.T_world_station.values()])
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=-1)[np.triu_indices(3, 1)]
    assert np.all(dist > 20.0) and np.all(dist < 250.0)
    ranges = np.concatenate([o.d for o in sim30.observations]) + 0.01
    assert ranges.min() > sim30.config.station_clearance_m * 0.9
    assert 50.0 < ranges.max() < 200.0


def test_noise_statistics_match_the_instrument_profile(sim30):
    prof = sim30.config.instrument
    assert prof.confidence_sigma == 2.0  # the S7 numbers are 2 sigma: 1 sigma is half
    zd, zv, zh = [], [], []
    for obs in sim30.observations:
        ot = sim30.truth.observations[obs.station]
        sig_d = (0.004 + 2e-6 * (ot.d + 0.01)) / 2.0
        sig_a = 2.0 * ARCSEC / 2.0
        sig_t = 0.5 * ARCSEC / 2.0
        zd.append((obs.d - ot.d) / sig_d)
        zv.append((obs.v - ot.v) / np.hypot(sig_a, sig_t))
        dhz = np.angle(np.exp(1j * (obs.hz - ot.hz)))
        zh.append(dhz / np.sqrt(sig_a**2 + (sig_t / np.tan(ot.v)) ** 2))
    for z in (np.concatenate(zd), np.concatenate(zv), np.concatenate(zh)):
        n = z.size
        assert n > 10000
        assert abs(z.mean()) < 4.0 / np.sqrt(n)
        assert abs(z.std() - 1.0) < 0.03
        # Gaussian tails
        assert abs(np.mean(np.abs(z) < 1.959964) - 0.95) < 0.01


def test_weather_reporting_errors_within_half_widths():
    cfg = SimulationConfig(duration_s=60.0, weather_interval_s=60.0, gcp_lead_time_s=20000.0)
    sim = simulate_deployment(cfg, 2)
    w = sim.weather_reported
    T, P, H = sim.truth.model.weather_at(w.t)
    for err, hw in ((w.temperature_c - T, 1.0), (w.pressure_hpa - P, 10.0),
                    (w.humidity_pct - H, 2.0)):
        assert err.size > 300
        assert np.all(np.abs(err) <= hw)
        # uniform on [-hw, hw]: zero mean, std hw / sqrt(3)
        assert abs(err.mean()) < 4 * hw / np.sqrt(3 * err.size)
        assert abs(err.std() / (hw / np.sqrt(3)) - 1.0) < 0.1
    # the true weather drifts over the hours
    Tt = sim.weather_true.temperature_c
    assert np.ptp(Tt) > 0.5
    clean = simulate_deployment(cfg.without_noise(), 2)
    np.testing.assert_allclose(clean.weather_reported.temperature_c,
                               clean.truth.model.weather_at(clean.weather_reported.t)[0])


def test_clock_offsets_follow_the_papers_distribution():
    cfg = SimulationConfig(duration_s=5.0, n_stations=5, n_gcp=5, gcp_min_common=3,
                           gcp_blocked_max=0, truth_rate_hz=10.0)
    rng = np.random.default_rng(123)
    off = np.array([list(simulate_deployment(cfg, rng).truth.clock_offset_s.values())
                    for _ in range(120)]).ravel()
    n = off.size
    # |e| ~ N(mu, sigma) (folded at 0, a 8 % effect on the moments here), random sign
    mag = np.abs(off)
    assert abs(mag.mean() - 1.157e-3) < 4 * 0.815e-3 / np.sqrt(n) + 0.1e-3
    assert abs(np.mean(np.sign(off) > 0) - 0.5) < 4 * 0.5 / np.sqrt(n)
    m2 = 1.157e-3**2 + 0.815e-3**2  # the second moment the noise model uses
    assert abs(np.mean(off**2) / m2 - 1.0) < 4 * np.sqrt(2.0 / n)


def test_truth_geometry(sim30):
    tr = sim30.truth
    ref = tr.reference_body
    d = {(i, j): np.linalg.norm(ref[i] - ref[j]) for i in range(3) for j in range(i + 1, 3)}
    assert all(0.7 <= v <= 1.1 for v in d.values())
    heights = np.asarray(sim30.config.prism_positions_robot_m)[:3, 2]
    assert np.ptp(heights) > 0.1  # prisms at different heights
    for (i, j), dij in d.items():
        dt = np.linalg.norm(tr.prisms_world[:, i] - tr.prisms_world[:, j], axis=-1)
        np.testing.assert_allclose(dt, dij, rtol=0, atol=1e-9)
    # T_world_body maps the reference (body frame) onto the true prisms
    R = tr.body.rotation
    mapped = np.einsum("nij,pj->npi", R, ref) + tr.body.position[:, None]
    assert np.max(np.abs(mapped - tr.prisms_world)) < 1e-9
    q = tr.body.quat_xyzw
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    # the body frame is the survey frame, ~10 m from the robot
    assert 9.0 < np.linalg.norm(tr.T_body_robot.translation) < 12.5


def test_robot_motion(sim30):
    cfg = sim30.config
    m = sim30.truth.model
    t = sim30.truth.t
    R, p = m.robot_at(t)
    v3 = np.linalg.norm(np.gradient(p, t, axis=0), axis=1)
    vh = m.speed_at(t)
    # the commanded horizontal speed is the speed of the path (arc-length parametrisation)
    np.testing.assert_allclose(np.linalg.norm(np.gradient(p[:, :2], t, axis=0), axis=1)[1:-1],
                               vh[1:-1], atol=2e-3)
    assert v3.max() <= cfg.speed_max_m_s * 1.01
    plateau = np.ones_like(t, bool)
    for t0, length in zip(m.ramp_t, m.ramp_len, strict=True):
        plateau &= ~((t - m.t0 >= t0) & (t - m.t0 <= t0 + length))
    moving = plateau & (vh > 0)
    assert np.all((v3[moving] >= 0.5 * 0.999) & (v3[moving] <= 2.0 * 1.01))
    # stops: the robot stands still at the start and at least once later
    stopped = vh == 0
    assert stopped[0]
    restarts = np.flatnonzero(np.diff(stopped.astype(int)) == 1)
    assert restarts.size >= 1
    # accelerations limited, roll and pitch of a few degrees
    acc = np.gradient(vh, t)
    assert np.abs(acc).max() <= cfg.accel_max_m_s2 * 1.01
    tilt = np.degrees(np.arccos(np.clip(R[:, 2, 2], -1, 1)))
    assert 0.5 < tilt.max() <= cfg.terrain_max_slope_deg
    # heading follows the direction of travel
    vel = np.gradient(p, t, axis=0)
    fwd = np.einsum("ni,ni->n", vel[moving], R[moving][:, :, 0])
    np.testing.assert_allclose(fwd, np.linalg.norm(vel[moving], axis=1), rtol=1e-3)
    # turns respect the curvature limit: yaw rate <= v / r_min
    yaw = np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    yaw_rate = np.abs(np.gradient(yaw, t))
    assert np.all(yaw_rate[moving] <= v3[moving] / cfg.min_turn_radius_m * 1.05)


def test_truth_at_100hz_interpolates_well_under_01_mm(sim30):
    tr = sim30.truth
    rng = np.random.default_rng(0)
    tq = np.sort(rng.uniform(tr.t[0], tr.t[-1], 20000))
    p_exact, q_exact = sim30.truth_at(tq, frame="body")
    p_lin = np.stack([np.interp(tq, tr.t, tr.body.position[:, i]) for i in range(3)], -1)
    slerp = Slerp(tr.t, Rotation.from_quat(tr.body.quat_xyzw))
    ang = (slerp(tq).inv() * Rotation.from_quat(q_exact)).magnitude()
    assert np.max(np.linalg.norm(p_lin - p_exact, axis=1)) < 2e-5
    lever = np.linalg.norm(tr.reference_body, axis=1).max()
    assert np.max(ang) * lever < 2e-5
    # truth_at agrees with the exported 100 Hz truth at its own times
    p, q = sim30.truth_at(tr.t[::97], frame="body")
    np.testing.assert_allclose(p, tr.body.position[::97], atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(q * tr.body.quat_xyzw[::97], 1)), 1.0, atol=1e-12)


def test_time_stamps_staggered_with_dropouts(sim30):
    obs = sim30.observations
    for o in obs:
        dt = np.diff(o.t)
        assert np.all(dt > 0)
        assert abs(np.median(dt) - 0.4) < 0.01
        assert np.std(dt[dt < 0.5]) > 1e-3  # jitter
        # line-of-sight losses of 1-15 s are present (two overlapping ones can merge)
        gaps = dt[dt > 1.0]
        assert gaps.size >= 3 and gaps.max() < 2 * 15.0 + 1.0
        assert 1.0 < np.median(gaps) < 15.0
        assert len(o) / (1800 * 2.5) > 0.7
    for a in range(3):
        for b in range(a + 1, 3):
            i = np.clip(np.searchsorted(obs[b].t, obs[a].t), 1, len(obs[b]) - 1)
            near = np.minimum(np.abs(obs[b].t[i] - obs[a].t), np.abs(obs[b].t[i - 1] - obs[a].t))
            assert np.median(near) > 0.04  # not simultaneous
    no_drop = simulate_deployment(SimulationConfig(duration_s=300.0, dropouts=False), 4)
    for o in no_drop.observations:
        assert np.diff(o.t).max() < 0.45
        assert len(o) >= 300 * 2.5 - 1


def test_gcp_shots(sim30):
    g = sim30.gcp
    cfg = sim30.config
    markers = set(sim30.truth.gcp_markers)
    assert len(markers) == cfg.n_gcp
    seen1 = set(g.marker[g.station == "1"])
    for s in ("1", "2", "3"):
        seen = set(g.marker[g.station == s])
        assert len(seen) >= cfg.n_gcp - cfg.gcp_blocked_max
        assert len(seen & seen1) >= cfg.gcp_min_common
        ts = g.t[g.station == s]
        assert np.all(np.diff(ts) >= 29.0)  # a shot every 30-60 s, before the tracking
        assert ts.max() < cfg.start_time_s
    assert g.additive_constant == 0.01
    assert np.all(g.status == 0)


def test_reproducible_from_the_seed():
    cfg = SimulationConfig(duration_s=120.0)
    a = simulate_deployment(cfg, 42)
    b = simulate_deployment(cfg, np.random.default_rng(42))
    c = simulate_deployment(cfg, 43)
    assert a.seed == 42 and b.seed is None
    for oa, ob, oc in zip(a.observations, b.observations, c.observations, strict=True):
        for name in ("t", "hz", "v", "d"):
            np.testing.assert_array_equal(getattr(oa, name), getattr(ob, name))
        assert len(oa) != len(oc) or not np.array_equal(oa.d, oc.d)
    np.testing.assert_array_equal(a.truth.body.position, b.truth.body.position)
    np.testing.assert_array_equal(a.gcp.d, b.gcp.d)
    np.testing.assert_array_equal(a.survey.hz, b.survey.hz)


def test_more_stations_and_validation():
    sim = simulate_deployment(SimulationConfig(duration_s=30.0, n_stations=4), 1)
    assert [o.prism for o in sim.observations] == ["1", "2", "3", "4"]
    assert sim.truth.prisms_world.shape[1:] == (4, 3)
    with pytest.raises(ValueError, match="n_stations >= 3"):
        SimulationConfig(n_stations=2)
    with pytest.raises(ValueError, match="at most 5 stations"):
        SimulationConfig(n_stations=6)
    with pytest.raises(ValueError, match="duration_s > 0"):
        SimulationConfig(duration_s=-1.0)
    with pytest.raises(ValueError, match="speed_min_m_s <= speed_max_m_s"):
        SimulationConfig(speed_min_m_s=3.0)
    with pytest.raises(ValueError, match="Generator"):
        simulate_deployment(SimulationConfig(), "seed")
    # errors about the configuration are InputErrors (still ValueErrors)
    for bad in ({"n_stations": 2}, {"outlier_probability": 1.0}, {"gcp_height_m": (1.0, 0.5)},
                {"gnss_positions_robot_m": ((0.0, 0.0),)}, {"additive_constant_m": np.nan}):
        with pytest.raises(InputError, match="Expected"):
            SimulationConfig(**bad)


def test_rejection_sampling_fails_loudly_instead_of_accepting_a_bad_draw():
    # a station at the site centre cannot be pushed out of a loop around it
    loop = 10.0 * np.stack([np.cos(np.linspace(0, 6.28, 100)), np.sin(np.linspace(0, 6.28, 100))],
                           axis=-1)
    st = np.array([[0.0, 0.0], [30.0, 0.0]])
    with pytest.raises(InputError, match=r"station\(s\) 1 .*station_clearance_m"):
        with np.errstate(divide="ignore", invalid="ignore"):
            sim_deployment._clear_of_path(st.copy(), loop, 15.0)
    with pytest.raises(InputError, match=r"station\(s\) 1 .*in 0 pushes"):
        sim_deployment._clear_of_path(np.array([[12.0, 0.0]]), loop, 5.0, max_pushes=0)
    pushed = sim_deployment._clear_of_path(np.array([[12.0, 0.0]]), loop, 5.0)
    assert np.linalg.norm(pushed[:, None] - loop, axis=-1).min() >= 5.0
    # no valid GCP visibility within the allowed draws: an error, never the last draw
    with pytest.raises(InputError, match="gcp_blocked_max"):
        sim_deployment._gcp_visibility(SimulationConfig(), np.random.default_rng(0), max_draws=0)
    vis = sim_deployment._gcp_visibility(SimulationConfig(gcp_blocked_max=5, n_gcp=10),
                                         np.random.default_rng(0))
    assert np.all((vis & vis[0]).sum(axis=1) >= 5)


def test_rotation_helper_matches_scipy():
    # the simulation's numpy rotations (kept for bit-identical deployments) are scipy's ones
    rng = np.random.default_rng(3)
    angle = rng.uniform(-np.pi, np.pi, 20)
    for axis, name in enumerate("xyz"):
        np.testing.assert_allclose(sim_deployment._rotation(axis, angle),
                                   Rotation.from_euler(name, angle[:, None]).as_matrix(),
                                   rtol=0, atol=1e-15)


def test_noise_sources_flags():
    assert SimulationConfig().noise_sources == NOISE_SOURCES
    assert SimulationConfig().without_noise().noise_sources == ()
    assert SimulationConfig(noise_instrument=False).noise_sources == (
        "tilt", "atmosphere", "time_sync", "calibration")


def test_outliers_optional():
    sim = simulate_deployment(SimulationConfig(duration_s=200.0, outlier_probability=0.05), 9)
    for o in sim.observations:
        ot = sim.truth.observations[o.station]
        assert ot.outlier.any()
        jump = np.abs(o.d - ot.d)
        assert np.all(jump[ot.outlier] > 0.9) and np.all(jump[~ot.outlier] < 0.05)
