"""Monte Carlo versus first-order propagation of the per-measurement noise model.

The Monte Carlo engine is the paper's method; the linearised engine must agree with it
(relative Frobenius difference < 5 % at 1e4 samples) over ranges 2 m to 1000 m and all
directions (any Hz; zenith from 1e-3 rad, 0.06 degrees, to pi - 1e-3: the tilt enters Hz
through cot V, 1000 at the bound, and stays first order), source by source.
"""

from itertools import combinations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rtsgt.errors import InputError
from rtsgt.geometry.so3 import exp_so3
from rtsgt.geometry.transform import RigidTransform, perturbation
from rtsgt.measurement.atmosphere import instrument_correction_ppm
from rtsgt.measurement.instruments import ARCSEC, LEICA_MS60, TRIMBLE_S7, InstrumentProfile
from rtsgt.measurement.polar import polar_jacobian
from rtsgt.noise import NOISE_SOURCES, NoiseModel, propagate
from rtsgt.noise import montecarlo as mc
from rtsgt.noise.model import prepare_nominal
from rtsgt.types import Observations, WeatherSeries

M = 10_000


def rel_frob(a, b):
    return np.linalg.norm(a - b, axis=(-2, -1)) / np.linalg.norm(b, axis=(-2, -1))


def one_obs(hz, v, d, t0=0.0):
    return Observations(t=[t0], hz=[hz], v=[v], d=[d], additive_constant=0.0)


def weather_at(T, p, rh):
    return WeatherSeries(t=[-1.0, 1.0], temperature_c=[T, T], pressure_hpa=[p, p],
                         humidity_pct=[rh, rh])


geometry = dict(
    hz=st.floats(0.0, 2 * np.pi, exclude_max=True),
    v=st.floats(1e-3, np.pi - 1e-3),
    d=st.floats(2.0, 1000.0),
)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(**geometry, T=st.floats(-20, 35), p=st.floats(700, 1050), rh=st.floats(5, 95),
       profile=st.sampled_from([TRIMBLE_S7, LEICA_MS60]))
def test_mc_matches_linear_instrument_tilt_atmosphere(hz, v, d, T, p, rh, profile):
    obs = one_obs(hz, v, d)
    model = NoiseModel(profile, sources=("instrument", "tilt", "atmosphere"))
    w = weather_at(T, p, rh)
    lin = propagate(obs, model, weather=w)
    mcr = propagate(obs, model, weather=w, engine="mc", samples=M, rng=np.random.default_rng(7))
    for s in model.sources:
        r = rel_frob(mcr.cov_by_source[s], lin.cov_by_source[s])[0]
        assert r < 0.05, (s, r)
    assert rel_frob(mcr.cov, lin.cov)[0] < 0.05


@settings(max_examples=10, deadline=None, derandomize=True)
@given(**geometry)
def test_linear_instrument_is_the_polar_jacobian(hz, v, d):
    # independent check of the linear engine: J diag(sa^2, sa^2, sd^2) J^T with polar_jacobian
    obs = one_obs(hz, v, d)
    prof = TRIMBLE_S7
    lin = propagate(obs, NoiseModel(prof, sources=("instrument", "tilt")))
    J = polar_jacobian(hz, v, d)
    S = np.diag([prof.sigma_angle**2, prof.sigma_angle**2, float(prof.sigma_distance(d)) ** 2])
    np.testing.assert_allclose(lin.cov_by_source["instrument"][0], J @ S @ J.T, rtol=1e-10,
                               atol=1e-22)
    g = J @ np.array([np.cos(v) / np.sin(v), 1.0, 0.0])
    np.testing.assert_allclose(lin.cov_by_source["tilt"][0], prof.sigma_tilt**2 * np.outer(g, g),
                               rtol=1e-10, atol=1e-24)


def _polar_ld(hz, v, d):
    sv = np.sin(v)
    return np.stack(np.broadcast_arrays(d * sv * np.sin(hz), d * sv * np.cos(hz), d * np.cos(v)),
                    axis=-1)


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-12), (np.float32, 2e-6)])
def test_sampled_displacements_equal_the_exact_polar_model(dtype, tol):
    # the engine computes displacements with the addition theorem and truncated series; they
    # must equal polar_to_cartesian(perturbed) - polar_to_cartesian(nominal)
    rng = np.random.default_rng(0)
    n, m = 6, 400
    obs = Observations(t=np.arange(n), hz=rng.uniform(0, 6.28, n), v=rng.uniform(0.2, 2.9, n),
                       d=rng.uniform(2, 1000, n))
    model = NoiseModel(TRIMBLE_S7)
    nom = prepare_nominal(obs, model)
    ch = mc._Chunk(nom, model, slice(0, n), dtype)
    ws = mc._Workspace(n, m, dtype)
    for scale in (1e-5, 1e-3):  # Taylor branch and np.sin / np.cos fallback
        dd = (rng.standard_normal((n, m)) * 3e-3).astype(dtype)
        dV = (rng.standard_normal((n, m)) * scale).astype(dtype)
        et = (rng.standard_normal((n, m)) * scale / 4).astype(dtype)
        dH = (rng.standard_normal((n, m)) * scale).astype(dtype)
        dx, dy, dz = (a.astype(float) for a in mc._deltas(ws, ch, dd, dV, et, dH))
        # reference in extended precision (the difference of two 1000 m coordinates loses
        # 1e-13 m in float64)
        L = np.longdouble
        v0, hz0, d0 = (np.asarray(a, dtype=L)[:, None] for a in (obs.v, obs.hz, nom.d_corr))
        v_hat = v0 + dV.astype(L)  # dV is the total change of V (e_V + e_tilt)
        hz_hat = hz0 + dH.astype(L) + et.astype(L) * np.cos(v_hat) / np.sin(v_hat)
        ref = _polar_ld(hz_hat, v_hat, d0 + dd.astype(L)) - _polar_ld(hz0, v0, d0)
        ref = ref.astype(float)
        got = np.stack([dx, dy, dz], axis=-1)
        err = np.abs(got - ref).max() / np.abs(ref).max()
        assert err < tol, (scale, err)


# (T degC, p hPa, RH %): cold and thin, dry (RH clipped at 0), a reference atmosphere, the
# GeodePy example, hot and saturated (RH clipped at 100), hot at altitude
ALPHA_WEATHERS = np.array([(-25.0, 700.0, 2.0), (0.0, 950.0, 0.0), (12.0, 1013.25, 60.0),
                           (6.8, 960.8, 58.6), (35.0, 1050.0, 97.0), (45.0, 820.0, 100.0)])


@pytest.mark.parametrize("dtype, tol_ppm", [(np.float32, 3e-4), (np.float64, 1e-12)])
@pytest.mark.parametrize("formula", ["magnus", "buck"])
def test_alpha_samples_equal_the_atmosphere_module_at_the_perturbed_weather(formula, dtype,
                                                                            tol_ppm):
    """The engine evaluates [MAG] / [BUCK], [IAG99-2] and [R02-K] in place, in its working
    dtype (atmosphere.py's allocating float64 functions would cost 14-58 % of its speed):
    every sample's ``alpha`` must be ``1e-6 K`` of atmosphere.instrument_correction_ppm at the
    same perturbed (and clipped) weather, to the rounding of N_L ~ 300 in the working dtype
    (ulp 3e-5 in float32, 6e-14 in float64; the largest errors seen are 3 ulp). A wrong
    coefficient, reference atmosphere, wavelength or clipping moves K by 1e-2 ppm or more."""
    n, m = len(ALPHA_WEATHERS), 20_000
    t = np.arange(n, dtype=float)
    obs = Observations(t=t, hz=np.full(n, 1.0), v=np.full(n, 1.5), d=np.full(n, 100.0))
    w = WeatherSeries(t=t, temperature_c=ALPHA_WEATHERS[:, 0], pressure_hpa=ALPHA_WEATHERS[:, 1],
                      humidity_pct=ALPHA_WEATHERS[:, 2])
    h = np.array([5.0, 30.0, 10.0])  # half-widths of T, p, RH
    for lam, ref in ((0.532, (20.0, 1013.25, 50.0)), (0.658, (12.0, 1013.25, 60.0)),
                     (0.905, (20.0, 1013.25, 60.0)), (1.064, (15.0, 1000.0, 0.0))):
        prof = InstrumentProfile("p", distance_constant_m=1e-3, distance_ppm=1.0, angle_rad=1e-5,
                                 tilt_rad=1e-6, confidence_sigma=1.0, wavelength_um=lam,
                                 reference_temperature_c=ref[0], reference_pressure_hpa=ref[1],
                                 reference_humidity_pct=ref[2])
        model = NoiseModel(prof, vapour_formula=formula, temperature_halfwidth_c=h[0],
                           pressure_halfwidth_hpa=h[1], humidity_halfwidth_pct=h[2])
        ch = mc._Chunk(prepare_nominal(obs, model, weather=w), model, slice(0, n), dtype)
        ws = mc._Workspace(n, m, dtype)
        rng = np.random.default_rng(17)
        for buf in (ws.u0, ws.u1, ws.u2):
            rng.random(out=buf, dtype=dtype)
        u = np.stack([ws.u0, ws.u1, ws.u2]).astype(float)  # the engine overwrites them
        alpha = mc._alpha_samples(ws, ch, *mc._atmosphere_constants(model)).astype(float)
        # the model: x^ = x + h (2u - 1), RH^ clipped to [0, 100]
        T_hat, p_hat, rh_hat = ALPHA_WEATHERS.T[:, :, None] + h[:, None, None] * (2.0 * u - 1.0)
        assert rh_hat.min() < 0.0 and rh_hat.max() > 100.0  # the clipping is exercised
        K = instrument_correction_ppm(prof, T_hat, p_hat, np.clip(rh_hat, 0.0, 100.0), formula)
        assert np.ptp(K) > 50.0  # tens of ppm of spread
        err = np.abs(1e6 * alpha - K).max()
        assert err < tol_ppm, (lam, err)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("source", ["instrument", "tilt", "atmosphere", "time_sync", "calibration"])
def test_single_source_total_equals_its_own_entry(source, dtype):
    # the total runs every sample through the full model; the per-source entries use exact
    # shortcuts (line of sight, velocity, linearity in (R_m, t_m)): same draws, same numbers
    rng = np.random.default_rng(2)
    n = 30
    obs = Observations(t=np.arange(n) * 0.4, hz=rng.uniform(0, 6.28, n), v=rng.uniform(0.4, 2.7, n),
                       d=np.linspace(3, 400, n) + rng.uniform(0, 1, n) * np.arange(n))
    Rs = exp_so3(rng.standard_normal((500, 3)) * 1e-3) @ exp_so3([0, 0, 1.0])
    ts = np.array([1.0, -2.0, 0.5]) + rng.standard_normal((500, 3)) * 2e-3
    T = RigidTransform(exp_so3([0, 0, 1.0]), np.array([1.0, -2.0, 0.5]), frame_to="world",
                       frame_from="station_1", samples_rotation=Rs, samples_translation=ts)
    tr = propagate(obs, NoiseModel(TRIMBLE_S7, sources=(source,)), T_world_station=T,
                   weather=weather_at(5.0, 940.0, 70.0), engine="mc", samples=500,
                   rng=np.random.default_rng(3), mc_dtype=dtype, chunk_size=8)
    tol = 1e-9 if dtype == np.float64 else 2e-4
    np.testing.assert_allclose(tr.cov, tr.cov_by_source[source], rtol=tol,
                               atol=tol * np.abs(tr.cov).max())


def test_time_sync_is_rank_one_along_the_velocity():
    # a prism moving at (1.0, 0.5, 0.02) m/s seen every 0.4 s from ~50 m
    n = 40
    t = np.arange(n) * 0.4
    vel = np.array([1.0, 0.5, 0.02])
    p = np.array([30.0, 40.0, -1.0]) + t[:, None] * vel
    from rtsgt.measurement.polar import cartesian_to_polar

    hz, v, d = cartesian_to_polar(p)
    obs = Observations(t=t, hz=hz, v=v, d=d)
    model = NoiseModel(TRIMBLE_S7, sources=("instrument", "time_sync"))
    lin = propagate(obs, model)
    mcr = propagate(obs, model, engine="mc", samples=M, rng=np.random.default_rng(5))
    m2 = model.time_sync_second_moment_s2
    for tr in (lin, mcr):
        C = tr.cov_by_source["time_sync"]
        w, V = np.linalg.eigh(C)
        assert np.all(w[:, 1] / w[:, 2] < 1e-9)  # second eigenvalue / first
        u = vel / np.linalg.norm(vel)
        np.testing.assert_allclose(np.abs(V[:, :, 2] @ u), 1.0, atol=1e-9)
        np.testing.assert_allclose(w[:, 2], m2 * vel @ vel, rtol=0.05)
    assert np.all(rel_frob(mcr.cov_by_source["time_sync"], lin.cov_by_source["time_sync"]) < 0.05)
    # the linear total also carries the (tiny) interaction with the velocity noise
    extra = lin.cov - lin.cov_by_source["instrument"] - lin.cov_by_source["time_sync"]
    assert np.all(np.linalg.eigvalsh(extra) > -1e-20)
    assert 0 < np.abs(extra).max() < 1e-9  # < (30 um)^2
    assert np.all(rel_frob(mcr.cov, lin.cov) < 0.05)
    # about 1.4 mm along a 1.1 m/s velocity: the paper's order of magnitude
    assert np.sqrt(m2) * np.linalg.norm(vel) == pytest.approx(1.57e-3, rel=0.02)


def _calibrated_transform(cov6, n_samples, rng, with_cov=True):
    R = exp_so3([0.01, -0.02, 2.79])
    t = np.array([-0.659, -1.301, 0.286])
    xi = mc.sample_gaussian(cov6, n_samples, rng)
    Rs = exp_so3(xi[:, 3:]) @ R
    ts = t + xi[:, :3]
    cov = None
    if with_cov:
        e = perturbation(R, t, Rs, ts)
        e -= e.mean(axis=0)
        cov = e.T @ e / (n_samples - 1)
    return RigidTransform(R, t, cov, "world", "station_2", samples_rotation=Rs,
                          samples_translation=ts)


COV6 = np.diag([2e-6, 1e-6, 3e-6, 4e-9, 6e-9, 2.5e-7])
COV6[0, 5] = COV6[5, 0] = 3e-7


def test_calibration_mc_with_samples_matches_linear_with_their_covariance():
    rng = np.random.default_rng(11)
    T = _calibrated_transform(COV6, M, rng)
    obs = Observations(t=np.arange(12.0), hz=np.linspace(0, 6, 12), v=np.linspace(0.3, 2.8, 12),
                       d=np.geomspace(2, 1000, 12))
    model = NoiseModel(TRIMBLE_S7, sources=("instrument", "calibration"))
    lin = propagate(obs, model, T_world_station=T)
    mcr = propagate(obs, model, T_world_station=T, engine="mc", samples=M,
                    rng=np.random.default_rng(1))
    # same samples on both sides: only the linearisation of exp differs
    assert np.all(rel_frob(mcr.cov_by_source["calibration"], lin.cov_by_source["calibration"]) < 0.01)
    assert np.all(rel_frob(mcr.cov, lin.cov) < 0.05)
    assert lin.frame == mcr.frame == "world"
    # linear from the samples alone gives the same
    T_samples_only = RigidTransform(T.rotation, T.translation, None, "world", "station_2",
                                    T.samples_rotation, T.samples_translation)
    lin2 = propagate(obs, model, T_world_station=T_samples_only)
    np.testing.assert_allclose(lin2.cov_by_source["calibration"], lin.cov_by_source["calibration"],
                               rtol=1e-9)
    # sample m of every measurement uses transform m: more samples than the transform has fail
    with pytest.raises(InputError, match="carries 10000 Monte Carlo samples, fewer than the 10001"):
        propagate(obs, model, T_world_station=T, engine="mc", samples=M + 1,
                  rng=np.random.default_rng(1))


def test_calibration_from_a_covariance_only():
    T = RigidTransform(exp_so3([0, 0, 0.3]), np.array([2.0, 1.0, 0.0]), COV6, "world", "s3")
    obs = Observations(t=np.arange(5.0), hz=np.linspace(0, 6, 5), v=np.linspace(0.5, 2.5, 5),
                       d=np.geomspace(5, 500, 5))
    model = NoiseModel(TRIMBLE_S7, sources=("calibration",))
    lin = propagate(obs, model, T_world_station=T)
    mcr = propagate(obs, model, T_world_station=T, engine="mc", samples=M,
                    rng=np.random.default_rng(4))
    assert np.all(rel_frob(mcr.cov, lin.cov) < 0.05)
    # a transform with neither covariance nor samples carries no calibration uncertainty
    T0 = RigidTransform(T.rotation, T.translation, None, "world", "s3")
    assert np.all(propagate(obs, model, T_world_station=T0).cov == 0)


def test_sample_gaussian_reproduces_a_singular_covariance():
    # pitfall 1 (docs/noise-model.md#reference-code-pitfalls): eigenvectors are the columns of V;
    # a cloud must reproduce the covariance
    A = np.random.default_rng(0).standard_normal((6, 4))
    cov = A @ A.T  # rank 4
    x = mc.sample_gaussian(cov, 200_000, np.random.default_rng(1))
    np.testing.assert_allclose(np.cov(x.T), cov, atol=0.03 * np.abs(cov).max())


def test_float32_box_muller_normals_are_standard():
    from scipy import stats

    ws = mc._Workspace(50, 20_000, np.float32)
    out = [ws.z0, ws.z1, ws.z2]
    mc._standard_normals(ws, np.random.default_rng(9), out)
    z = np.concatenate([o.ravel().astype(float) for o in out])
    assert abs(z.mean()) < 0.005 and abs(z.var() - 1) < 0.005
    assert abs(np.mean(z**4) - 3) < 0.03
    assert abs(np.corrcoef(out[0].ravel(), out[1].ravel())[0, 1]) < 0.005  # pair independence
    assert stats.kstest(z[:500_000], "norm").pvalue > 1e-3


def test_memory_is_bounded_by_chunks_and_results_do_not_depend_on_them_statistically():
    rng = np.random.default_rng(8)
    n = 101
    obs = Observations(t=np.arange(n) * 0.4, hz=rng.uniform(0, 6, n), v=rng.uniform(1, 2, n),
                       d=rng.uniform(2, 300, n))
    model = NoiseModel(TRIMBLE_S7, sources=("instrument", "tilt"))
    lin = propagate(obs, model)
    for chunk in (1, 13, None):
        tr = propagate(obs, model, engine="mc", samples=4000, chunk_size=chunk,
                       rng=np.random.default_rng(0))
        assert tr.cov.shape == (n, 3, 3)
        assert np.median(rel_frob(tr.cov, lin.cov)) < 0.04
    assert mc.CHUNK_ELEMENTS * len(mc._Workspace.NAMES) * 8 < 64e6  # workspace under 64 MB


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_all_five_sources_together_match_linear_source_by_source(dtype):
    """Every source at once, as the pipeline runs them: the draws of one source must not
    overwrite another's (a float32 Box-Muller scratch buffer once did, inflating the
    atmosphere to metres)."""
    n = 30
    t = np.arange(n) * 0.4
    vel = np.array([0.8, -0.6, 0.05])
    p = np.array([-20.0, 45.0, -2.0]) + t[:, None] * vel
    from rtsgt.measurement.polar import cartesian_to_polar

    hz, v, d = cartesian_to_polar(p)
    obs = Observations(t=t, hz=hz, v=v, d=d)
    w = WeatherSeries(t=[-10.0, 20.0], temperature_c=[3.0, 4.0], pressure_hpa=[935.0, 936.0],
                      humidity_pct=[70.0, 72.0])
    cov6 = np.diag([1e-6, 2e-6, 1e-6, 4e-9, 4e-9, 1e-8])
    T = RigidTransform(exp_so3([0.0, 0.0, 0.3]), [5.0, -3.0, 0.2], cov6, "world", "station")
    model = NoiseModel(TRIMBLE_S7)
    lin = propagate(obs, model, T_world_station=T, weather=w)
    mcr = propagate(obs, model, T_world_station=T, weather=w, engine="mc", samples=M,
                    rng=np.random.default_rng(11), mc_dtype=dtype)
    for s in model.sources:
        r = rel_frob(mcr.cov_by_source[s], lin.cov_by_source[s])
        assert np.median(r) < 0.05 and r.max() < 0.1, (s, np.median(r), r.max())
    assert np.all(rel_frob(mcr.cov, lin.cov) < 0.05)


# A custom profile and weather errors that make every source contribute about equally at
# ~50 m (each ~0.5 mm as sqrt of the Frobenius norm): a source whose draws another source
# overwrote, or whose workspace buffer the total reused, would move the total by ~20 %.
BALANCED = InstrumentProfile("balanced", distance_constant_m=0.5e-3, distance_ppm=0.0,
                             angle_rad=2.0 * ARCSEC, tilt_rad=2.0 * ARCSEC, confidence_sigma=1.0,
                             wavelength_um=0.658, reference_temperature_c=12.0,
                             reference_pressure_hpa=1013.25, reference_humidity_pct=60.0)
SOURCE_SETS = [s for k in (2, 3, 4, 5) for s in combinations(NOISE_SOURCES, k)]


@pytest.fixture(scope="module")
def balanced_inputs():
    from rtsgt.measurement.polar import cartesian_to_polar

    n = 12
    t = np.arange(n) * 0.4
    p = np.array([-25.0, 40.0, -8.0]) + t[:, None] * np.array([0.3, -0.2, 0.05])
    hz, v, d = cartesian_to_polar(p)
    obs = Observations(t=t, hz=hz, v=v, d=d)
    w = WeatherSeries(t=[-10.0, 20.0], temperature_c=[3.0, 4.0], pressure_hpa=[935.0, 936.0],
                      humidity_pct=[70.0, 72.0])
    cov6 = np.diag([0.3e-3**2] * 3 + [(5e-6) ** 2] * 2 + [(6e-6) ** 2])
    R, tr = exp_so3([0.01, 0.0, 0.3]), np.array([5.0, -3.0, 0.2])
    Rs, ts = mc.transform_samples(RigidTransform(R, tr, cov6, "world", "station"), M,
                                  np.random.default_rng(0))
    T = RigidTransform(R, tr, None, "world", "station", samples_rotation=Rs,
                       samples_translation=ts)
    return obs, w, T


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("sources", SOURCE_SETS, ids=["+".join(s) for s in SOURCE_SETS])
def test_no_source_disturbs_another_in_any_combination(balanced_inputs, sources, dtype):
    """Every subset of two or more sources, both precisions, several chunks (the last one
    shorter) on two threads: each source matches the linear engine, and the total (the full
    model, one pass) matches the sum of the sources alone, which share its draws (common random
    numbers: only cross terms of independent draws, ~1/sqrt(M), separate them)."""
    obs, w, T = balanced_inputs
    model = NoiseModel(BALANCED, sources=sources, temperature_halfwidth_c=15.0,
                       pressure_halfwidth_hpa=30.0)
    lin = propagate(obs, model, T_world_station=T, weather=w)
    mcr = propagate(obs, model, T_world_station=T, weather=w, engine="mc", samples=M,
                    rng=np.random.default_rng(3), mc_dtype=dtype, chunk_size=5, workers=2)
    for s in sources:
        r = rel_frob(mcr.cov_by_source[s], lin.cov_by_source[s])
        assert np.median(r) < 0.04 and r.max() < 0.08, (s, np.median(r), r.max())
    for ref in (lin.cov, sum(mcr.cov_by_source.values())):
        r = rel_frob(mcr.cov, ref)
        assert np.median(r) < 0.04 and r.max() < 0.08, (np.median(r), r.max())


@pytest.mark.parametrize("dtype, tol", [(np.float32, 1e-5), (np.float64, 1e-12)])
@pytest.mark.parametrize("offset", [0.0, 1e-5, 1.0])
def test_row_covariances_match_numpy_centred_or_not(dtype, tol, offset):
    # the engine's row covariances come from sums and dot products (no centring pass); rows
    # whose mean is not small against their spread are centred first: numpy's cov either way
    rng = np.random.default_rng(12)
    n, m = 7, 3000
    A = rng.standard_normal((3, 3))
    X = np.einsum("ij,jnm->inm", A, rng.standard_normal((3, n, m))) * 1e-3
    X += offset * rng.standard_normal((3, n, 1))  # offset 1.0: a mean 1000 times the spread
    X[:, 3] = 0.0  # a row without any spread
    ref = np.stack([np.cov(X[:, k]) for k in range(n)])
    got = mc._cov_rows(*(x.astype(dtype) for x in X))
    assert got.dtype == np.float64 and got.shape == (n, 3, 3)
    np.testing.assert_array_equal(got, np.swapaxes(got, 1, 2))
    np.testing.assert_allclose(got, ref, rtol=0, atol=tol * np.abs(ref).max())
