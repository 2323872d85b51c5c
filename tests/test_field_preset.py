"""The field-hour preset (rtsgt.simulation.field, .presets): its draws follow their truth.

Statistics are checked on long draws of the functions (closed forms of the variance and of
the lag-one correlation), the plumbing on one short simulated deployment against the truth it
records; every seed is fixed.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from rtsgt.cli.main import app
from rtsgt.errors import InputError
from rtsgt.io.deployment import load_deployment
from rtsgt.measurement.instruments import TRIMBLE_S7
from rtsgt.measurement.polar import survey_polar_to_cartesian
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.field import (
    MGON,
    FieldEffects,
    clock_walk,
    field_noise,
    white_sigma,
)
from rtsgt.simulation.presets import preset_config
from rtsgt.simulation.reality import RealityEffects


@pytest.fixture(scope="module")
def field_sim(tmp_path_factory):
    """300 s of the preset without the reality effects: measured minus noise-free is the
    field noise alone."""
    cfg = dataclasses.replace(preset_config("field-hour", duration_s=300.0),
                              reality=RealityEffects())
    sim = simulate_deployment(cfg, 5)
    toml = write_deployment(sim, tmp_path_factory.mktemp("field") / "dep")
    return sim, toml


def test_field_noise_variance_range_growth_and_correlation():
    rng = np.random.default_rng(12)
    n, dt, tau = 200_000, 0.4, 3.0
    t = dt * np.arange(n)
    white = np.array([0.2 * MGON, 0.1 * MGON, 0.6e-3])
    coef = np.array([0.1 * MGON, 0.3 * MGON, 1.0])  # rad at 100 m, rad at 100 m, ppm
    gm = np.array([0.15 * MGON, 0.2 * MGON, 0.3e-3])
    d = np.where(np.arange(n) % 2 == 0, 20.0, 400.0)  # two ranges, interleaved
    e = field_noise(t, d, white, coef, gm, np.full(3, tau), rng)
    for r in (20.0, 400.0):
        expect = white_sigma(np.array([r]), white, coef)[0] ** 2 + gm ** 2
        got = np.mean(e[d == r] ** 2, axis=0)
        # the GM part is correlated: n_eff about n / (1 + 2 tau / dt) for its share
        tol = 5.0 * np.sqrt(2.0 * (1.0 + 2.0 * tau / dt) / (n / 2))
        np.testing.assert_allclose(got / expect, 1.0, atol=tol)
    # closed forms: sigma_angle^2 = w^2 + s^2 d / 100 m, sigma_d = w_d + ppm 1e-6 d
    s = white_sigma(np.array([400.0]), white, coef)[0]
    np.testing.assert_allclose(s, [np.hypot(0.2, 0.2) * MGON, np.hypot(0.1, 0.6) * MGON,
                                   0.6e-3 + 0.4e-3], rtol=1e-12)
    # lag-one: cov(e_i, e_{i+1}) = gm^2 exp(-dt / tau) (the white part does not correlate)
    lag1 = np.mean(e[1:] * e[:-1], axis=0)
    np.testing.assert_allclose(lag1 / gm ** 2, np.exp(-dt / tau), atol=0.05)
    # unsorted times (the GCP shots and the tracking of a station) give the process of the
    # sorted ones, each value at its own time
    perm = np.random.default_rng(1).permutation(500)
    zero = np.zeros(3)
    a = field_noise(t[:500], d[:500], zero, zero, gm, np.full(3, tau), np.random.default_rng(3))
    b = field_noise(t[perm], d[perm], zero, zero, gm, np.full(3, tau), np.random.default_rng(3))
    c = np.empty_like(b)
    c[perm] = b
    np.testing.assert_array_equal(c, a)


def test_clock_walk_drift_and_diffusion():
    rng = np.random.default_rng(8)
    r, q, n = 15e-3 / 3600.0, (1e-3) ** 2 / 3600.0, 400_000
    x = clock_walk(n, 1.0, r, q, rng)
    assert x[0] == 0.0 and x.shape == (n + 1,)
    inc = np.diff(x)
    assert abs(inc.mean() - r) < 5.0 * np.sqrt(q / n)
    assert abs(inc.var() / q - 1.0) < 5.0 * np.sqrt(2.0 / n)


def test_preset_residuals_follow_the_recorded_noise(field_sim):
    sim, _ = field_sim
    ft = sim.truth.field
    z2 = {c: [] for c in range(3)}
    for k, obs in enumerate(sim.observations):
        ot = sim.truth.observations[obs.station]
        r = np.stack([np.angle(np.exp(1j * (obs.hz - ot.hz))), obs.v - ot.v, obs.d - ot.d], 1)
        var = white_sigma(ot.d + obs.additive_constant, ft.white[k], ft.range_coef[k]) ** 2 \
            + ft.gm_sigma[k] ** 2
        for c in range(3):
            z2[c].append(r[:, c] ** 2 / var[:, c])
    for c in range(3):
        # pooled over the stations; the datasheet's (2 mm, 1") would give 2-10 here
        assert 0.7 < np.mean(np.concatenate(z2[c])) < 1.3, c
    # the distances' white noise is the field's, about 0.6 mm, not the datasheet's 2 mm
    assert np.all((ft.white[:, 2] >= 0.5e-3) & (ft.white[:, 2] <= 0.7e-3))
    assert np.all((ft.gm_tau_s >= 1.0) & (ft.gm_tau_s <= 12.0))


def test_clocks_drift_against_the_reference(field_sim):
    sim, _ = field_sim
    ft = sim.truth.field
    rate_h = 3600.0 * ft.clock_drift_s_per_s
    assert rate_h[0] == 0.0 and ft.clock_walk_s2_per_s[0] == 0.0
    assert np.all((np.abs(rate_h[1:]) >= 10e-3) & (np.abs(rate_h[1:]) <= 20e-3))
    for k, obs in enumerate(sim.observations):
        ot = sim.truth.observations[obs.station]
        # the stamps hold the recorded clock error, up to the 0.05 ms jitter
        diff = ot.clock_error_s - ft.clock_error_s(k, ot.t_true)
        assert np.max(np.abs(diff)) < 6 * sim.config.time_sync_jitter_s
        if k:
            slope = np.polyfit(ot.t_true - ot.t_true[0], ot.clock_error_s, 1)[0]
            # a walk of 1 ms per sqrt(h) moves a 300 s slope by ~5 ms/h at most (4 sigma)
            assert abs(3600.0 * slope - rate_h[k]) < 5e-3


def test_a_prism_moved_after_its_survey(field_sim):
    sim, toml = field_sim
    ft, tr = sim.truth.field, sim.truth
    k = ft.displaced_prism
    assert 0.01 <= np.linalg.norm(ft.displacement_robot_m) <= 0.03
    surveyed = survey_polar_to_cartesian(sim.survey.hz, sim.survey.v, sim.survey.d)[:3]
    moved = np.linalg.norm(tr.reference_body - surveyed, axis=1)
    assert moved[k] > 0.009 and np.all(np.delete(moved, k) < 0.003)  # survey noise ~1 mm
    # the true prisms are where the truth says: T_world_body(t) applied to reference_body
    R, p = tr.model.body_at(tr.t[::500])
    np.testing.assert_allclose(tr.prisms_world[::500],
                               np.einsum("nij,pj->npi", R, tr.reference_body) + p[:, None],
                               atol=1e-9)
    doc = json.loads((toml.parent / "truth.json").read_text())["field"]
    np.testing.assert_allclose(doc["displaced_prism"]["surveyed_body_m"],
                               tr.reference_body[k] - ft.displacement_body_m, atol=1e-12)
    assert doc["displaced_prism"]["prism"] == tr.prism_ids[k]


def test_the_vehicle_rocks_as_it_drives(field_sim):
    """The truth's robot pose is its path's turned and shifted by the rocking (the pose with
    the rocking removed is the path's, 1e-12); the rocking's size follows the speed: none
    where the robot stands, and scaled to full speed each axis's RMS over the moving times
    is the drawn one (sinusoids of 0.5-3 Hz over minutes: within 15 %), drawn inside the
    preset's ranges and written to truth.json; with the speed exponent 0, of one size
    wherever the robot moves."""
    sim, toml = field_sim
    m, ft = sim.truth.model, sim.truth.field
    fx = ft.effects
    rms = ft.rocking_rms
    assert np.all((rms[:3] >= fx.rocking_angle_rad[0]) & (rms[:3] <= fx.rocking_angle_rad[1]))
    assert np.all((rms[3:5] >= fx.rocking_shift_m[0]) & (rms[3:5] <= fx.rocking_shift_m[1]))
    assert fx.rocking_heave_m[0] <= rms[5] <= fx.rocking_heave_m[1]
    t = m.t0 + np.arange(0.0, sim.config.duration_s, 0.01)
    R, p = m.robot_at(t)
    R0, p0 = dataclasses.replace(m, rocking=None).robot_at(t)
    x = m.rocking_at(t)
    # the rocking's rotation (z y x) and shift in the path's frame
    c, s_ = np.cos(x[:, :3]), np.sin(x[:, :3])
    Rx = np.zeros((t.size, 3, 3))
    Rx[:, 0, 0] = 1.0
    Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = c[:, 0], -s_[:, 0], s_[:, 0], c[:, 0]
    Ry = np.zeros((t.size, 3, 3))
    Ry[:, 1, 1] = 1.0
    Ry[:, 0, 0], Ry[:, 0, 2], Ry[:, 2, 0], Ry[:, 2, 2] = c[:, 1], s_[:, 1], -s_[:, 1], c[:, 1]
    Rz = np.zeros((t.size, 3, 3))
    Rz[:, 2, 2] = 1.0
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1] = c[:, 2], -s_[:, 2], s_[:, 2], c[:, 2]
    np.testing.assert_allclose(R, R0 @ Rz @ Ry @ Rx, atol=1e-12)
    np.testing.assert_allclose(p, p0 + np.einsum("nij,nj->ni", R0, x[:, 3:]), atol=1e-12)
    v = m.speed_at(t)
    assert np.all(x[v == 0.0] == 0.0) and np.any(v == 0.0)
    moving = v > 0.2 * m.rocking_speed_m_s
    assert moving.sum() > 5000
    unit = x[moving] / (v[moving] / m.rocking_speed_m_s)[:, None]  # as at full speed
    np.testing.assert_allclose(np.sqrt(np.mean(unit**2, axis=0)) / rms, 1.0, atol=0.15)
    doc = json.loads((toml.parent / "truth.json").read_text())["field"]
    np.testing.assert_allclose(list(doc["rocking_rms_at_top_speed"].values()), rms, rtol=1e-12)
    assert doc["effects"]["rocking_speed_exponent"] == fx.rocking_speed_exponent == 1.0
    # of one size while driving (exponent 0): the full speed's wherever it moves, none standing
    x0 = dataclasses.replace(m, rocking_speed_exponent=0.0).rocking_at(t)
    np.testing.assert_allclose(x0[moving], unit, rtol=1e-9, atol=1e-15)
    assert np.all(x0[v == 0.0] == 0.0) and np.all(np.any(x0[v > 0.0] != 0.0, axis=1))


def test_far_station_and_truth_json(field_sim):
    sim, toml = field_sim
    ranges = [sim.truth.observations[o.station].d for o in sim.observations]
    assert max(r.max() for r in ranges) > 250.0 and max(r.max() for r in ranges) < 500.0
    assert ranges[0].max() < 150.0  # the reference station stays near
    doc = json.loads((toml.parent / "truth.json").read_text())
    f = doc["field"]
    assert f["reference_station"] == "1"
    st = f["stations"]["2"]
    assert len(st["clock"]["error_s"]) == sim.truth.field.clock_drift_walk_s.shape[1]
    assert st["noise"]["d"]["ppm"] == sim.truth.field.range_coef[1, 2]
    assert doc["config"]["far_stations"] == 1 and "field" not in doc["config"]
    # the other stations stand where they would without a far one (same draws)
    base = simulate_deployment(dataclasses.replace(sim.config, far_stations=0), 5)
    np.testing.assert_array_equal(base.truth.T_world_station["2"].translation,
                                  sim.truth.T_world_station["2"].translation)


def test_the_toml_keeps_the_datasheet(field_sim):
    _, toml = field_sim
    data, _ = load_deployment(toml)
    assert data.instrument == TRIMBLE_S7
    assert 'profile = "trimble-s7"' in toml.read_text()
    assert "instrument" in toml.read_text().split("[noise]")[1].split("\n")[1]


def test_validation_and_cli(tmp_path):
    assert preset_config("field-hour").duration_s == 3600.0
    with pytest.raises(InputError, match="preset"):
        preset_config("field-day")
    with pytest.raises(InputError, match="low <= high"):
        FieldEffects(gm_time_s=(12.0, 1.0))
    with pytest.raises(InputError, match="far_stations"):
        SimulationConfig(far_stations=3)
    runner = CliRunner()
    out = tmp_path / "dep"
    r = runner.invoke(app, ["simulate", str(out), "--preset", "field-hour", "--duration", "20",
                            "--reality", "tracking_lag"])
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "truth.json").read_text())
    assert doc["t_end_s"] - doc["t_start_s"] == 20.0
    assert doc["reality_effects"]["enabled"] == ["prism_cyclic", "tracking_lag",
                                                 "tripod_settling"]
    assert "field" in doc and "drifting" in r.output
    r = runner.invoke(app, ["simulate", str(tmp_path / "bad"), "--preset", "field-day"])
    assert r.exit_code == 2 and "field-day" in r.output and not (tmp_path / "bad").exists()
