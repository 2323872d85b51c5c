"""Noise model: parameters, prism velocity, input validation, reproducibility."""

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.measurement.atmosphere import correction_ppm
from rtsgt.measurement.instruments import TRIMBLE_S7
from rtsgt.measurement.polar import polar_to_cartesian
from rtsgt.noise import NOISE_SOURCES, NoiseModel, prism_velocity, propagate
from rtsgt.types import Observations, WeatherSeries


def _obs(n=20, **kw):
    rng = np.random.default_rng(1)
    base = dict(
        t=np.arange(n) * 0.4 + 1000.0,
        hz=rng.uniform(0, 2 * np.pi, n),
        v=rng.uniform(1.2, 1.9, n),
        d=rng.uniform(5, 80, n),
        additive_constant=0.01,
        station="2",
        prism="2",
    )
    base.update(kw)
    return Observations(**base)


def test_noise_model_defaults_and_validation():
    m = NoiseModel(TRIMBLE_S7)
    assert m.sources == NOISE_SOURCES
    assert (m.time_sync_mean_s, m.time_sync_std_s) == (1.157e-3, 0.815e-3)
    assert m.time_sync_second_moment_s2 == pytest.approx(1.157e-3**2 + 0.815e-3**2)
    assert m.weather_variances == pytest.approx((1 / 3, 100 / 3, 4 / 3))
    # sources are kept in the canonical order, whatever order they are given in
    assert m.with_sources(["tilt", "instrument"]).sources == ("instrument", "tilt")
    assert m.with_sources("atmosphere").sources == ("atmosphere",)
    with pytest.raises(InputError, match="Unknown noise source.*'wind'"):
        m.with_sources(["instrument", "wind"])
    with pytest.raises(InputError, match="temperature_halfwidth_c >= 0"):
        NoiseModel(TRIMBLE_S7, temperature_halfwidth_c=-1.0)
    with pytest.raises(InputError, match="vapour_formula"):
        NoiseModel(TRIMBLE_S7, vapour_formula="goff-gratch")
    assert NoiseModel(TRIMBLE_S7, vapour_formula="Buck").vapour_formula == "buck"


def test_prism_velocity_central_one_sided_and_gaps():
    t = np.array([0.0, 0.5, 1.0, 1.4, 5.0, 5.3, 20.0])
    v_true = np.array([1.0, -2.0, 0.5])
    p = t[:, None] * v_true + np.array([3.0, 4.0, 5.0])
    v, valid = prism_velocity(t, p, max_gap_s=1.0)
    # constant velocity: every valid difference is exact
    np.testing.assert_allclose(v[valid], np.broadcast_to(v_true, v[valid].shape), atol=1e-12)
    # the 3.6 s gap is not crossed; the last point is isolated
    assert valid.tolist() == [True, True, True, True, True, True, False]
    np.testing.assert_array_equal(v[~valid], 0.0)
    # quadratic motion: central differences at interior points, one-sided at block ends
    p2 = np.stack([t**2, np.zeros_like(t), np.zeros_like(t)], axis=1)
    v2, _ = prism_velocity(t, p2, max_gap_s=1.0)
    assert v2[1, 0] == pytest.approx((1.0 - 0.0) / 1.0)  # (p2 - p0) / (t2 - t0)
    assert v2[3, 0] == pytest.approx((1.4**2 - 1.0) / 0.4)  # one-sided: next gap is too long
    assert v2[4, 0] == pytest.approx((5.3**2 - 25.0) / 0.3)


def test_prism_velocity_rejects_bad_times():
    p = np.zeros((3, 3))
    with pytest.raises(InputError, match=r"duplicated t\[2\] = 1.0 after t\[1\] = 1.0"):
        prism_velocity([0.0, 1.0, 1.0], p, 1.0)
    with pytest.raises(InputError, match="decreasing"):
        prism_velocity([0.0, 2.0, 1.0], p, 1.0)
    with pytest.raises(InputError, match="shape"):
        prism_velocity([0.0, 1.0], p, 1.0)


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("d", np.nan, r"finite distances, got d\[7\] = nan"),
        ("d", -3.0, r"non-negative distances, got d\[7\] = -3.0"),
        ("v", 0.0, r"zenith angles in \(0, pi\) rad, got v\[7\] = 0.0"),
        ("v", np.pi, r"got v\[7\] = 3.14159"),
        ("v", -0.2, r"got v\[7\] = -0.2"),
        ("hz", np.inf, r"hz\[7\] = inf"),
        ("t", 1000.0, r"strictly increasing times"),
    ],
)
@pytest.mark.parametrize("engine", ["linear", "mc"])
def test_bad_input_names_value_and_index(field, value, message, engine):
    obs = _obs()
    arr = getattr(obs, field).copy()
    arr[7] = value
    bad = Observations(**{**_obs_kwargs(obs), field: arr})
    with pytest.raises(InputError, match=message):
        propagate(bad, NoiseModel(TRIMBLE_S7), engine=engine, samples=10,
                  rng=np.random.default_rng(0))


def _obs_kwargs(obs):
    return dict(t=obs.t, hz=obs.hz, v=obs.v, d=obs.d, status=obs.status, station=obs.station,
                prism=obs.prism, additive_constant=obs.additive_constant, source="prism2.csv")


def test_bad_input_names_the_file_and_other_errors():
    obs = _obs()
    d = obs.d.copy()
    d[3] = np.nan
    with pytest.raises(InputError, match=r"^prism2.csv: Expected finite distances"):
        propagate(Observations(**{**_obs_kwargs(obs), "d": d}), NoiseModel(TRIMBLE_S7))
    status = np.zeros(len(obs), int)
    status[4] = 5
    with pytest.raises(InputError, match="Observation 4 has instrument status 5"):
        propagate(Observations(**{**_obs_kwargs(obs), "status": status}), NoiseModel(TRIMBLE_S7))
    with pytest.raises(InputError, match="Unknown noise engine 'ukf'"):
        propagate(obs, NoiseModel(TRIMBLE_S7), engine="ukf")
    with pytest.raises(InputError, match="needs rng"):
        propagate(obs, NoiseModel(TRIMBLE_S7), engine="mc")
    with pytest.raises(InputError, match="samples >= 2"):
        propagate(obs, NoiseModel(TRIMBLE_S7), engine="mc", samples=1, rng=np.random.default_rng(0))
    w = WeatherSeries(t=[0.0, 2000.0], temperature_c=[5.0, 5.0], pressure_hpa=[935.0, np.nan],
                      humidity_pct=[50.0, 50.0], source="weather.csv")
    with pytest.raises(InputError, match="weather.csv: Expected weather pressure_hpa"):
        propagate(obs, NoiseModel(TRIMBLE_S7), weather=w)


@pytest.mark.parametrize("mc_dtype", [np.float32, np.float64])
def test_reproducible_from_a_seed(mc_dtype):
    obs = _obs(60)
    model = NoiseModel(TRIMBLE_S7, sources=("instrument", "tilt", "atmosphere", "time_sync"))
    kw = dict(engine="mc", samples=500, chunk_size=7, mc_dtype=mc_dtype)
    a = propagate(obs, model, rng=np.random.default_rng(42), **kw)
    b = propagate(obs, model, rng=np.random.default_rng(42), **kw)
    c = propagate(obs, model, rng=np.random.default_rng(43), **kw)
    # threads do not change the result: every chunk draws from its own seeded generator
    d = propagate(obs, model, rng=np.random.default_rng(42), workers=2, **kw)
    np.testing.assert_array_equal(a.cov, b.cov)
    np.testing.assert_array_equal(a.cov, d.cov)
    for s in model.sources:
        np.testing.assert_array_equal(a.cov_by_source[s], b.cov_by_source[s])
        np.testing.assert_array_equal(a.cov_by_source[s], d.cov_by_source[s])
        assert not np.array_equal(a.cov_by_source[s], c.cov_by_source[s])
    assert not np.array_equal(a.cov, c.cov)
    np.testing.assert_array_equal(a.xyz, c.xyz)  # the nominal positions are not random


def test_nominal_positions_frame_and_atmospheric_correction():
    obs = _obs(10)
    model = NoiseModel(TRIMBLE_S7, sources=("instrument",))
    # no weather: the reference atmosphere, zero ppm
    tr = propagate(obs, model)
    np.testing.assert_allclose(tr.range_m, obs.d + 0.01)
    np.testing.assert_allclose(tr.xyz, polar_to_cartesian(obs.hz, obs.v, obs.d + 0.01))
    assert tr.frame == "station_2" and tr.station == "2" and tr.prism == "2"
    assert set(tr.cov_by_source) == {"instrument"}
    # cold, low-pressure forest air (Montmorency, ~640 m) against the S7's 20 degC / 1013 hPa:
    # -18 degC is about -17 ppm, -76 hPa about +21 ppm
    w = WeatherSeries(t=[900.0, 1100.0], temperature_c=[2.0, 2.0], pressure_hpa=[937.0, 937.0],
                      humidity_pct=[80.0, 80.0])
    tw = propagate(obs, model, weather=w)
    ppm = (tw.range_m / (obs.d + 0.01) - 1) * 1e6
    expected = correction_ppm(2.0, 937.0, 80.0, wavelength_um=0.905,
                              reference=(20.0, 1013.25, 60.0))
    np.testing.assert_allclose(ppm, expected, rtol=1e-6)
    assert 2.0 < float(expected) < 6.0
    np.testing.assert_allclose(np.linalg.norm(tw.xyz, axis=1), tw.range_m, rtol=1e-12)
