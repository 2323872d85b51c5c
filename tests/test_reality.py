"""Reality effects of the simulator (rtsgt.simulation.reality): each does what it says.

Every check is against a closed form or the simulation's own truth, with a fixed seed; the
deployments are noise-free where an effect has to be seen alone.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from typer.testing import CliRunner

from rtsgt.cli.main import app
from rtsgt.errors import InputError
from rtsgt.io.deployment import load_deployment
from rtsgt.measurement.atmosphere import instrument_correction_ppm
from rtsgt.measurement.polar import polar_to_cartesian
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth
from rtsgt.simulation.reality import (
    REALITY_EFFECTS,
    RealityEffects,
    clock_sawtooth,
    first_order_lag,
    gauss_markov,
    remote_weather,
    settling_fraction,
)


def _sim(duration: float, seed: int, noise: bool = True, **effects) -> object:
    cfg = SimulationConfig(duration_s=duration, reality=RealityEffects(**effects))
    return simulate_deployment(cfg.without_noise() if not noise else cfg, seed)


def _station_points(sim, obs, t_true):
    """Measured points in the frame the station had at set-up (atmosphere undone), m."""
    ppm = instrument_correction_ppm(sim.config.instrument, *sim.truth.model.weather_at(t_true))
    return polar_to_cartesian(obs.hz, obs.v, (obs.d + obs.additive_constant) * (1.0 + 1e-6 * ppm))


def _to_station(sim, sid, p_world):
    T = sim.truth.T_world_station[sid]
    return (p_world - T.translation) @ T.rotation


# -- all off: today's simulation --------------------------------------------------------------

#: Values of seed 3, 60 s, written by the simulator before the reality effects existed
#: (commit 038cdc0; the angles of stations 2 and 3 since their verticals follow the Earth's
#: curvature): station -> (t[5], hz[5], v[5], d[5], t[-1], d[-1]).
BEFORE = {
    "1": (1668092402.3799164, 4.669443142915062, 1.584622083974473, 81.27554165382702,
          1668092459.9799864, 39.55846340407477),
    "2": (1668092402.157649, 1.1028814118421963, 1.601793957923991, 64.72472055488433,
          1668092459.7590933, 74.28200408796073),
    "3": (1668092402.2487543, 2.4394837684924755, 1.6006528893081242, 17.53856902980022,
          1668092459.8511956, 59.1004383569768),
}


def test_all_effects_off_is_the_simulation_of_before(tmp_path):
    sim = simulate_deployment(SimulationConfig(duration_s=60.0), 3)
    for o in sim.observations:
        got = (o.t[5], o.hz[5], o.v[5], o.d[5], o.t[-1], o.d[-1])
        np.testing.assert_allclose(got, BEFORE[o.station], rtol=1e-12, atol=0)
    g, w = sim.gcp, sim.weather_reported
    np.testing.assert_allclose(
        [g.t[0], g.hz[0], g.v[0], g.d[0], g.d[-1], w.temperature_c[0], w.pressure_hpa[0],
         w.humidity_pct[-1], sim.survey.d[0], *sim.truth.body.position[3000]],
        [1668090599.9986398, 4.659883533884187, 1.593101576936819, 43.176685763029724,
         44.88217361922677, 4.304635823917755, 932.0366350555892, 66.22537167759728,
         11.032884816822914, -66.63975011037698, -18.908099022149887, -0.7883689035524102],
        rtol=1e-12, atol=0)
    assert sim.truth.reality is None
    # the explicit all-off record writes the same files, byte for byte, and no trace of itself
    off = simulate_deployment(SimulationConfig(duration_s=60.0, reality=RealityEffects()), 3)
    a = write_deployment(sim, tmp_path / "a").parent
    b = write_deployment(off, tmp_path / "b").parent
    for f in sorted(a.iterdir()):
        assert f.read_bytes() == (b / f.name).read_bytes(), f.name
    doc = json.loads((a / "truth.json").read_text())
    assert "reality" not in doc["config"] and "reality_effects" not in doc
    # nor of the field effects and the far stations (rtsgt.simulation.field), off by default
    assert "field" not in doc and "field" not in doc["config"]
    assert "far_stations" not in doc["config"] and sim.truth.field is None


@pytest.mark.parametrize("effect", [e for e in REALITY_EFFECTS if e != "jerky_ramps"])
def test_an_effect_leaves_the_rest_of_the_draws_alone(effect):
    base = simulate_deployment(SimulationConfig(duration_s=40.0), 9)
    sim = simulate_deployment(
        SimulationConfig(duration_s=40.0, reality=RealityEffects.only(effect)), 9)
    np.testing.assert_array_equal(sim.truth.body.position, base.truth.body.position)
    np.testing.assert_array_equal(sim.survey.d, base.survey.d)
    for o, b in zip(sim.observations, base.observations, strict=True):
        assert o.t.size == b.t.size
        np.testing.assert_array_equal(sim.truth.observations[o.station].d,
                                      base.truth.observations[b.station].d)
    assert sim.truth.reality.effects.enabled == (effect,)


def test_validation():
    with pytest.raises(InputError, match="correlated_time_s > 0"):
        RealityEffects(correlated_time_s=0.0)
    with pytest.raises(InputError, match="settling_sink_m >= 0"):
        RealityEffects(settling_sink_m=-1e-3)
    with pytest.raises(InputError, match="a bool"):
        RealityEffects(tracking_lag=1)
    with pytest.raises(InputError, match="one of"):
        RealityEffects.only("fog")
    with pytest.raises(InputError, match="RealityEffects"):
        SimulationConfig(reality={"tracking_lag": True})


# -- 1. time-correlated noise -----------------------------------------------------------------

def test_gauss_markov_variance_and_correlation():
    rng = np.random.default_rng(41)
    tau = 1.0
    # 2.5 Hz with jitter and a few long gaps; 300 tau blocks are crossed many times
    dt = 0.4 + rng.uniform(-0.01, 0.01, 200_000)
    dt[rng.choice(dt.size, 50, replace=False)] += 5.0
    t = 1.6e9 + np.cumsum(dt)
    sigma = np.array([2.0, 0.5, 1e-3])
    x = gauss_markov(t, tau, sigma, np.random.default_rng(42))
    assert x.shape == (t.size, 3)
    # variance: n_eff ~ N (1 - rho^2) / (1 + rho^2) ~ 76 000, so 2 % is over 3 sigma
    np.testing.assert_allclose(x.std(axis=0) / sigma, 1.0, atol=0.02)
    # lag-1 correlation against exp(-dt / tau), pair by pair
    rho = np.exp(-np.diff(t) / tau)
    normal = np.diff(t) < 1.0
    prod = (x[1:] * x[:-1])[normal] / sigma**2
    np.testing.assert_allclose(prod.mean(axis=0), rho[normal].mean(), atol=0.015)
    # across a 5 s gap the samples are (almost) independent: exp(-5) = 0.007
    gap = ~normal
    assert np.all(np.abs((x[1:] * x[:-1])[gap].mean(axis=0) / sigma**2) < 0.5)
    # lag 5 (about 2 s): exp(-2)
    prod5 = (x[5:] * x[:-5]) / sigma**2
    np.testing.assert_allclose(np.median(prod5.mean(axis=0)),
                               np.mean(np.exp(-(t[5:] - t[:-5]) / tau)), atol=0.03)


def test_correlated_noise_is_in_the_measurements():
    fx = dict(correlated_noise=True, correlated_sigma_distance_m=2e-3)
    sim = _sim(1800.0, 13, noise=False, **fx)
    eff = sim.config.reality
    r_hz, r_v, r_d, rho_ref, r1 = [], [], [], [], []
    for o in sim.observations:
        ot = sim.truth.observations[o.station]
        r_hz.append(np.angle(np.exp(1j * (o.hz - ot.hz))))
        r_v.append(o.v - ot.v)
        r_d.append(o.d - ot.d)
        dt = np.diff(ot.t_true)
        close = dt < 0.5
        r1.append((r_d[-1][1:] * r_d[-1][:-1])[close])
        rho_ref.append(np.exp(-dt[close] / eff.correlated_time_s))
    r_hz, r_v, r_d = (np.concatenate(r) for r in (r_hz, r_v, r_d))
    assert r_d.size > 10_000
    np.testing.assert_allclose(np.std(r_hz) / eff.correlated_sigma_angle_rad, 1.0, atol=0.1)
    np.testing.assert_allclose(np.std(r_v) / eff.correlated_sigma_angle_rad, 1.0, atol=0.1)
    np.testing.assert_allclose(np.std(r_d) / 2e-3, 1.0, atol=0.1)
    np.testing.assert_allclose(np.mean(np.concatenate(r1)) / 4e-6,
                               np.mean(np.concatenate(rho_ref)), atol=0.1)
    # white: the same seed without the effect has no residual at all
    clean = _sim(60.0, 13, noise=False)
    o = clean.observations[0]
    assert np.max(np.abs(o.d - clean.truth.observations[o.station].d)) < 1e-12


# -- 2. prism cyclic error --------------------------------------------------------------------

def test_prism_cyclic_error_against_its_closed_form():
    sim = _sim(600.0, 17, noise=False, prism_cyclic=True)
    eff, rt, model = sim.config.reality, sim.truth.reality, sim.truth.model
    seen = []
    for k, o in enumerate(sim.observations):
        ot = sim.truth.observations[o.station]
        R_wr, _ = model.robot_at(ot.t_true)
        st = sim.truth.T_world_station[o.station].translation
        los = st - ot.xyz_world
        # heading of the robot and direction of the station, both in the world's xy plane
        heading = np.arctan2(R_wr[:, 1, 0], R_wr[:, 0, 0])
        seen_az = np.arctan2(los[:, 1], los[:, 0]) - heading  # robot tilts < 4 deg: ~alpha
        e_range = (o.d - ot.d) * (1.0 + 1e-6 * ot.ppm)
        expected = eff.prism_cyclic_range_m * np.sin(6.0 * seen_az + rt.prism_phase_rad[k, 0])
        # the exact alpha is taken in the tilted robot frame: a few percent of 2 mm at most
        assert np.max(np.abs(e_range - expected)) < 0.15e-3
        assert np.max(np.abs(e_range)) <= eff.prism_cyclic_range_m * (1 + 1e-12)
        seen.append(e_range)
        # across: a horizontal offset a_c sin(...) of the point, seen as a change of Hz
        horiz = np.hypot(*_to_station(sim, o.station, ot.xyz_world)[:, :2].T)
        e_across = np.angle(np.exp(1j * (o.hz - ot.hz))) * horiz
        expected_c = eff.prism_cyclic_across_m * np.sin(6.0 * seen_az + rt.prism_phase_rad[k, 1])
        assert np.max(np.abs(e_across - expected_c)) < 0.1e-3
    seen = np.concatenate(seen)
    # the robot drives loops: the error takes the whole +-2 mm range
    assert seen.max() > 1.9e-3 and seen.min() < -1.9e-3


# -- 3. tracking lag --------------------------------------------------------------------------

def test_first_order_lag_closed_forms():
    t = np.linspace(0.0, 10.0, 7)
    v, a = np.array([1.5, -0.5, 0.1]), np.array([0.3, 0.2, -0.4])

    def line(tt):
        return tt[..., None] * v

    def parabola(tt):
        return tt[..., None] * v + 0.5 * tt[..., None] ** 2 * a

    lag = 0.08
    # constant velocity: exactly the position lag seconds earlier, an error |v| lag
    y = first_order_lag(line, t, lag)
    np.testing.assert_allclose(y, line(t - lag), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(y - line(t), axis=1), np.linalg.norm(v) * lag,
                               rtol=1e-10)
    # constant acceleration: p - lag v(t) + lag^2 a (int x^2 e^-x = 2)
    y = first_order_lag(parabola, t, lag)
    np.testing.assert_allclose(y, parabola(t) - lag * (v + t[:, None] * a) + lag**2 * a,
                               rtol=0, atol=1e-12)
    np.testing.assert_array_equal(first_order_lag(line, t, 0.0), line(t))


def test_tracking_lag_error_is_speed_times_lag_at_constant_speed():
    lag = 0.02
    sim = _sim(300.0, 19, noise=False, tracking_lag=True, tracking_lag_s=lag)
    model = sim.truth.model
    n_checked = 0
    for k, o in enumerate(sim.observations):
        ot = sim.truth.observations[o.station]
        t = ot.t_true
        measured = _station_points(sim, o, t)
        true = _to_station(sim, o.station, ot.xyz_world)
        err = np.linalg.norm(measured - true, axis=1)
        h = 1e-3
        v_prism = np.linalg.norm(model.prisms_at(t + h)[:, k] - model.prisms_at(t - h)[:, k],
                                 axis=1) / (2 * h)
        cruise = ((model.speed_at(t) > 0.3)  # a plateau: the same speed 0.6 s earlier
                  & (np.abs(model.speed_at(t) - model.speed_at(t - 30 * lag)) < 1e-9))
        assert cruise.sum() > 50
        # along a plateau the path still curves (radius >= 8 m): lag^2 |a| < 0.2 mm
        np.testing.assert_allclose(err[cruise], v_prism[cruise] * lag, rtol=0.02, atol=0.2e-3)
        # standing still there is no lag
        still = (model.speed_at(t + 1.0) < 1e-12) & (model.speed_at(t - 30 * lag) < 1e-12)
        if still.any():
            assert np.max(err[still]) < 1e-9
        n_checked += cruise.sum()
    assert n_checked > 300


# -- 4. clock drift ---------------------------------------------------------------------------

def test_clock_sawtooth_drifts_and_resets():
    fx = dict(clock_drift=True, clock_drift_rate=1e-4, clock_resync_interval_s=20.0)
    sim = _sim(300.0, 23, noise=False, **fx)
    rt = sim.truth.reality
    for k, o in enumerate(sim.observations):
        ot = sim.truth.observations[o.station]
        e = ot.clock_error_s
        np.testing.assert_allclose(e, ot.t_true - o.t, rtol=0, atol=1e-12)
        # the drawn sawtooth, to the resolution of a Unix time stamp (2.4e-7 s)
        np.testing.assert_allclose(e, rt.clock_error_s(k, ot.t_true), rtol=0, atol=3e-7)
        assert abs(rt.clock_rate[k]) == pytest.approx(1e-4)
        cycle = np.floor((ot.t_true - rt.clock_sync_phase_s[k]) / 20.0)
        same = np.diff(cycle) == 0
        # between re-synchronisations: linear at the drift rate (the stamps are Unix times,
        # resolved to 2.4e-7 s: 0.6 % of the drift over 0.4 s)
        slope = np.diff(e)[same] / np.diff(ot.t_true)[same]
        np.testing.assert_allclose(slope, rt.clock_rate[k], rtol=0.015)
        # across each re-synchronisation the error drops by rate * interval: it restarts at 0
        resets = np.diff(cycle) == 1
        assert resets.sum() >= 13
        np.testing.assert_allclose(np.diff(e)[resets],
                                   rt.clock_rate[k] * (np.diff(ot.t_true)[resets] - 20.0),
                                   rtol=0, atol=3e-7)
        assert np.max(np.abs(e)) > 0.9 * 1e-4 * 20.0
        assert np.max(np.abs(e)) <= 1e-4 * 20.0
    np.testing.assert_allclose(clock_sawtooth([0.0, 9.99, 10.0, 15.0], 2e-4, 10.0, 0.0),
                               [0.0, 1.998e-3, 0.0, 1e-3], rtol=0, atol=1e-15)


# -- 5. jerky starts and stops ----------------------------------------------------------------

def test_jerky_ramps_reach_the_requested_acceleration():
    base = _sim(400.0, 29)
    jerky = _sim(400.0, 29, jerky_ramps=True, jerky_accel_m_s2=4.0)
    t = base.config.start_time_s + np.arange(0.0, 400.0, 1e-3)
    acc = {n: np.diff(s.truth.model.speed_at(t)) / 1e-3 for n, s in
           (("base", base), ("jerky", jerky))}
    assert np.max(np.abs(acc["base"])) <= base.config.accel_max_m_s2 * 1.001
    assert 0.95 * 4.0 < np.max(np.abs(acc["jerky"])) <= 4.0 * 1.001
    # the same schedule: every ramp starts when it did, to the same speeds
    np.testing.assert_array_equal(jerky.truth.model.ramp_t, base.truth.model.ramp_t)
    np.testing.assert_array_equal(jerky.truth.model.level, base.truth.model.level)
    # nothing else drawn differently
    np.testing.assert_array_equal(jerky.observations[0].t, base.observations[0].t)


# -- 6. remote weather station ----------------------------------------------------------------

def test_remote_weather_matches_the_standard_atmosphere():
    # ISA: 1013.25 hPa, 15 degC at 0 m; 1001.29 hPa, 14.35 degC at 100 m (ISO 2533 table)
    T, P = remote_weather(15.0, 1013.25, -0.65, 100.0)
    assert T == pytest.approx(14.35)
    assert P == pytest.approx(1001.29, abs=0.05)


def test_remote_weather_biases_the_weather_file(tmp_path):
    base = _sim(60.0, 31)
    sim = _sim(60.0, 31, remote_weather=True)
    eff = sim.config.reality
    wb, w = base.weather_reported, sim.weather_reported
    np.testing.assert_allclose(w.temperature_c - wb.temperature_c,
                               eff.remote_temperature_bias_c, rtol=0, atol=1e-12)
    # 50 m higher at ~930 hPa: about 5.6 hPa less (1 hPa per ~8.5 m there)
    assert np.all((wb.pressure_hpa - w.pressure_hpa > 5.0)
                  & (wb.pressure_hpa - w.pressure_hpa < 6.5))
    np.testing.assert_array_equal(w.humidity_pct, wb.humidity_pct)
    # through the files
    data, _ = load_deployment(write_deployment(sim, tmp_path / "dep"))
    np.testing.assert_allclose(data.weather.temperature_c, w.temperature_c, rtol=1e-15)


# -- 7. tripod settling -----------------------------------------------------------------------

def test_settling_is_monotone_with_the_requested_size():
    f = settling_fraction(np.array([-10.0, 0.0, 100.0, 1000.0, 1e5]), 0.0, 600.0)
    assert f[0] == 0.0 and f[1] == 0.0
    assert np.all(np.diff(f[1:]) > 0) and f[-1] == pytest.approx(1.0, abs=1e-12)
    sim = _sim(600.0, 37, noise=False, tripod_settling=True)
    rt, eff = sim.truth.reality, sim.config.reality
    t = np.linspace(sim.truth.t[0] - 3000.0, sim.truth.t[-1] + 1e5, 500)
    for k in range(3):
        sink, twist = rt.settling_at(k, t)
        assert np.all(np.diff(sink) >= 0) and np.all(np.diff(np.abs(twist)) >= 0)
        assert sink[-1] == pytest.approx(eff.settling_sink_m, rel=1e-9)
        assert abs(twist[-1]) == pytest.approx(eff.settling_twist_rad, rel=1e-9)
        assert sink[0] == 0.0  # before the set-up


def test_settled_stations_measure_in_their_moved_frames():
    sim = _sim(300.0, 37, noise=False, tripod_settling=True)
    rt = sim.truth.reality

    def settled(k, p_station, t):
        # T_world_station(t) = T0 [Rz(psi), (0, 0, -z)]: the point in the moved frame
        sink, twist = rt.settling_at(k, t)
        c, s = np.cos(twist), np.sin(twist)
        q = p_station + np.stack([0 * sink, 0 * sink, sink], axis=-1)
        return np.stack([c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1], q[:, 2]], -1)

    moved = []
    for k, o in enumerate(sim.observations):
        ot = sim.truth.observations[o.station]
        measured = _station_points(sim, o, ot.t_true)
        true = _to_station(sim, o.station, ot.xyz_world)
        np.testing.assert_allclose(measured, settled(k, true, ot.t_true), rtol=0, atol=1e-9)
        moved.append(np.max(np.linalg.norm(measured - true, axis=1)))
    # tracking 30 min after set-up: most of the 1 mm sink and 0.1 mrad twist (at 10-60 m)
    assert max(moved) > 1.5e-3
    g = sim.gcp
    tr = sim.truth
    ppm = instrument_correction_ppm(sim.config.instrument, *tr.model.weather_at(g.t))
    p = polar_to_cartesian(g.hz, g.v, (g.d + g.additive_constant) * (1.0 + 1e-6 * ppm))
    for k, sid in enumerate(tr.prism_ids):
        m = g.station == sid
        marker = [tr.gcp_markers.index(x) for x in g.marker[m]]
        true = _to_station(sim, sid, tr.gcp_world[marker])
        np.testing.assert_allclose(p[m], settled(k, true, g.t[m]), rtol=0, atol=1e-9)
        assert rt.settling_start_s[k] == pytest.approx(g.t[m].min(), abs=1e-9)


# -- independent streams, and the route through the files and the pipeline -------------------

def test_effects_draw_from_their_own_streams():
    one = _sim(60.0, 43, noise=False, correlated_noise=True)
    two = _sim(60.0, 43, noise=False, correlated_noise=True, clock_drift=True)
    for a, b in zip(one.observations, two.observations, strict=True):
        np.testing.assert_array_equal(a.d, b.d)
        assert not np.array_equal(a.t, b.t)


def test_an_effect_goes_through_the_files_and_the_pipeline(tmp_path):
    runs = {}
    for name, fx in (("none", {}), ("lag", {"tracking_lag": True, "tracking_lag_s": 0.05})):
        sim = _sim(60.0, 47, **fx)
        toml = write_deployment(sim, tmp_path / name)
        doc = json.loads((toml.parent / "truth.json").read_text())
        assert ("reality_effects" in doc) == bool(fx)
        data, opts = load_deployment(toml)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = run_pipeline(data, opts.updated(seed=47, engine="linear"))
        p, q = sim.truth_at(result.groundtruth.t)
        runs[name] = compare_to_truth(result.groundtruth, p, q)
    # a 5 cm lag at up to 2 m/s: far outside the run's covariance
    assert runs["lag"].nees_position.mean > 5.0 * max(runs["none"].nees_position.mean, 1.0)


def test_rtsgt_simulate_switches_effects_on(tmp_path):
    runner = CliRunner()
    out = tmp_path / "dep"
    r = runner.invoke(app, ["simulate", str(out), "--duration", "30", "--seed", "3",
                            "--reality", "tracking_lag", "--reality", "clock_drift"])
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "truth.json").read_text())
    assert doc["reality_effects"]["enabled"] == ["tracking_lag", "clock_drift"]
    assert doc["reality_effects"]["effects"]["tracking_lag_s"] == 0.01
    r = runner.invoke(app, ["simulate", str(tmp_path / "bad"), "--reality", "fog"])
    assert r.exit_code == 2 and "fog" in r.output
    assert not (tmp_path / "bad").exists()
