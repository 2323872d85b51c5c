"""The fast Monte Carlo engine against the plain reference Monte Carlo (tests/noise_reference_oracle.py).

Two independent implementations of the same model, with independent draws: their sample means
and covariances differ by Monte Carlo error alone, whose size follows from the sample size M.
Each comparison is a z-score: for a sample covariance of M samples the (Wishart) variance of an
element is ``(C_ij^2 + C_ii C_jj) / (M - 1)`` (relative standard error ``sqrt(2 / M)`` on a
variance), exact for Gaussian samples and an upper bound for the lighter-tailed ones here
(uniform weather errors, kurtosis 1.8; the signed clock error, kurtosis 2.1); for a sample
mean it is ``C_ii / M``. Every difference must stay below 5 standard errors (a chance of
6e-7 per comparison under the null hypothesis; a few thousand comparisons in all). With
M = 1e5 that is 3 % on a variance, and 50 um on a 100 m shot along the line of sight, so a
1 ppm bias of the atmospheric correction (0.1 mm at 100 m) fails the comparison of the means
(test_a_one_ppm_bias_of_alpha_fails_the_mean_comparison).

The engine's means are the means of its own displacement samples (``montecarlo._sample_chunk``),
read by wrapping ``montecarlo._run_chunk``. The comparisons hold 1e5 samples of 15 shots in
memory (a few hundred MB at most) and take tens of seconds: marked slow.
"""

import numpy as np
import pytest

from noise_reference_oracle import reference_propagate
from rtsgt.errors import InputError
from rtsgt.geometry.so3 import exp_so3
from rtsgt.geometry.transform import RigidTransform
from rtsgt.measurement.instruments import TRIMBLE_S7
from rtsgt.measurement.polar import cartesian_to_polar, polar_to_cartesian
from rtsgt.noise import NOISE_SOURCES, NoiseModel, propagate
from rtsgt.noise import montecarlo as mc
from rtsgt.types import Observations, WeatherSeries

M = 100_000
Z_MAX = 5.0

# one shot per range, 2 m to 1000 m, from near the zenith to near the nadir; each shot is
# followed 0.25 s later by a second one of the prism moving at about 1 m/s (10 s between the
# pairs: the velocity is differenced within a pair only), and one isolated shot (no velocity)
RANGES = np.array([2.0, 10.0, 30.0, 100.0, 300.0, 600.0, 1000.0])
ZENITHS = np.array([0.08, 0.7, 1.3, np.pi / 2, 1.9, 2.6, 3.06])
I_100M = 6  # the 100 m shot (first of pair 3)
AC = -0.0175  # additive constant, m


def make_obs():
    rng = np.random.default_rng(4)
    hz = np.linspace(0.3, 5.9, RANGES.size)
    p0 = polar_to_cartesian(hz, ZENITHS, RANGES)
    vel = rng.standard_normal((RANGES.size, 3))
    vel /= np.linalg.norm(vel, axis=1, keepdims=True)
    p = np.concatenate([np.stack([p0, p0 + 0.25 * vel], axis=1).reshape(-1, 3),
                        polar_to_cartesian(2.0, 1.0, 50.0)[None]])
    t = np.concatenate([(10.0 * np.arange(RANGES.size)[:, None] + [0.0, 0.25]).ravel(), [100.0]])
    hz_, v_, d_ = cartesian_to_polar(p)
    return Observations(t=t, hz=hz_, v=v_, d=d_ - AC, additive_constant=AC)


WEATHER = WeatherSeries(t=[-1.0, 101.0], temperature_c=[28.0, 30.0], pressure_hpa=[880.0, 885.0],
                        humidity_pct=[93.0, 95.0])  # humid: the perturbed RH is clipped at 100


def model_for(formula="magnus"):
    return NoiseModel(TRIMBLE_S7, temperature_halfwidth_c=2.0, pressure_halfwidth_hpa=10.0,
                      humidity_halfwidth_pct=8.0, vapour_formula=formula)


R_WS, T_WS = exp_so3([0.01, -0.02, 2.8]), np.array([-0.66, -1.30, 0.29])
COV6 = np.diag([1e-6, 2e-6, 1e-6, 1e-9, 1e-9, 4e-8])


def transform(kind):
    if kind == "covariance":
        return RigidTransform(R_WS, T_WS, COV6, "world", "station")
    Rs, ts = mc.transform_samples(RigidTransform(R_WS, T_WS, COV6, "world", "station"), M,
                                  np.random.default_rng(21))
    return RigidTransform(R_WS, T_WS, None, "world", "station", samples_rotation=Rs,
                          samples_translation=ts)


def engine(obs, model, T, dtype, seed):
    """propagate(engine="mc") and the world-frame sample mean of its total."""
    rows = []

    def spy(ws, ch, rng, cal, n_gr, n_ref):
        x, y, z, bys = mc._sample_chunk(ws, ch, rng, cal, n_gr, n_ref)
        d = np.stack([a.mean(axis=1, dtype=np.float64) for a in (x, y, z)], axis=1)
        rows.append(d if cal is not None else d @ T.rotation.T)  # station -> world
        return mc._cov_rows(x, y, z), bys

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mc, "_run_chunk", spy)
        tr = propagate(obs, model, T_world_station=T, weather=WEATHER, engine="mc", samples=M,
                       rng=np.random.default_rng(seed), mc_dtype=dtype, workers=1)
    return tr, tr.xyz + np.concatenate(rows)  # workers=1: chunks in order


def cov_z(a, b, m_a, m_b):
    """|a - b| in standard errors of the difference of two independent sample covariances."""
    c = 0.5 * (a + b)
    dg = np.diagonal(c, axis1=-2, axis2=-1)
    var = (c**2 + dg[..., :, None] * dg[..., None, :]) * (1 / (m_a - 1) + 1 / (m_b - 1))
    return np.abs(a - b) / np.sqrt(var + 1e-40)  # floor (1e-20 m^2): rows without spread


def mean_z(ma, ca, mb, cb, m_a, m_b):
    """|ma - mb| in standard errors of the difference of two independent sample means."""
    var = np.diagonal(ca, axis1=-2, axis2=-1) / m_a + np.diagonal(cb, axis1=-2, axis2=-1) / m_b
    return np.abs(ma - mb) / np.sqrt(var + 1e-20)  # floor 1e-10 m: components without spread


@pytest.mark.slow
@pytest.mark.parametrize("dtype, formula, kind", [
    (np.float32, "magnus", "covariance"), (np.float64, "buck", "covariance"),
    (np.float32, "buck", "samples"), (np.float64, "magnus", "samples"),
])
def test_fast_engine_matches_the_reference_source_by_source(dtype, formula, kind):
    """Covariance and mean, every source alone and all five together, ranges 2 m to 1000 m,
    zenith angles 0.08 to 3.06 rad, both precisions and vapour formulas, calibration from a
    covariance (independent draws) and from the transform's samples (the same samples on both
    sides: the calibration source alone then agrees to rounding)."""
    obs, model, T = make_obs(), model_for(formula), transform(kind)
    ref = reference_propagate(obs, model, T_world_station=T, weather=WEATHER, samples=M,
                              rng=np.random.default_rng(1))
    fast, fast_mean = engine(obs, model, T, dtype, 2)
    assert np.max(cov_z(fast.cov, ref.cov, M, M)) < Z_MAX
    assert np.max(mean_z(fast_mean, fast.cov, ref.mean, ref.cov, M, M)) < Z_MAX
    for k, s in enumerate(NOISE_SOURCES):
        r_cov, r_mean = ref.cov_by_source[s], ref.mean_by_source[s]
        # the full run's per-source entry (closed-form shortcuts) and a run of s alone
        assert np.max(cov_z(fast.cov_by_source[s], r_cov, M, M)) < Z_MAX, s
        alone, alone_mean = engine(obs, model.with_sources((s,)), T, dtype, 10 + k)
        assert np.max(cov_z(alone.cov, r_cov, M, M)) < Z_MAX, s
        assert np.max(mean_z(alone_mean, alone.cov, r_mean, r_cov, M, M)) < Z_MAX, s
    # the isolated shot has no velocity: no clock-error term (the reference's points at 50 m
    # carry 1e-11 m of rounding)
    assert np.all(fast.cov_by_source["time_sync"][-1] == 0)
    assert np.abs(ref.cov_by_source["time_sync"][-1]).max() < 1e-20
    if kind == "samples":
        np.testing.assert_allclose(fast.cov_by_source["calibration"],
                                   ref.cov_by_source["calibration"], rtol=1e-8)
    # the bounds are tight enough to matter: 5 standard errors are 3.2 % of a variance, and
    # 0.06 mm of the total's mean along the line of sight of the 100 m shot (2.5 mm rms), so
    # a 1 ppm bias (0.1 mm, 9 standard errors) fails the comparison with every source on
    u = (ref.mean[I_100M] - T_WS) / np.linalg.norm(ref.mean[I_100M] - T_WS)
    se_los = np.sqrt(u @ (fast.cov[I_100M] + ref.cov[I_100M]) @ u / M)
    assert Z_MAX * np.sqrt(4 / (M - 1)) < 0.035 and Z_MAX * se_los < 0.07e-3


@pytest.mark.slow
def test_a_one_ppm_bias_of_alpha_fails_the_mean_comparison():
    """The power of the comparison of the means: an engine whose alpha is 1e-6 (1 ppm) too
    large moves the 100 m shot by 0.1 mm along the line of sight, more than 5 standard errors
    (about 120 with the atmosphere alone, 10 with the instrument noise on top), in both
    precisions; the same comparison passes without the bias."""
    obs, T = make_obs(), transform("covariance")
    alpha = mc._alpha_samples

    def biased(ws, ch, n_gr, n_ref):
        out = alpha(ws, ch, n_gr, n_ref)
        out += ws.dtype(1e-6)
        return out

    for seed, sources in enumerate([("atmosphere",), ("instrument", "tilt", "atmosphere")]):
        model = model_for().with_sources(sources)
        ref = reference_propagate(obs, model, T_world_station=T, weather=WEATHER, samples=M,
                                  rng=np.random.default_rng(seed))
        for dtype in (np.float32, np.float64):
            fast, fast_mean = engine(obs, model, T, dtype, 30 + seed)
            assert np.max(mean_z(fast_mean, fast.cov, ref.mean, ref.cov, M, M)) < Z_MAX
            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(mc, "_alpha_samples", biased)
                bad, bad_mean = engine(obs, model, T, dtype, 30 + seed)
            # same draws: the shift is the bias alone, 1e-6 d along the line of sight
            u = (bad.xyz[I_100M] - T_WS) / np.linalg.norm(bad.xyz[I_100M] - T_WS)
            np.testing.assert_allclose(bad_mean[I_100M] - fast_mean[I_100M],
                                       1e-6 * (obs.d[I_100M] + AC) * u, rtol=1e-3, atol=1e-8)
            z_bad = mean_z(bad_mean, bad.cov, ref.mean, ref.cov, M, M)
            assert np.max(z_bad[I_100M]) > Z_MAX, (sources, dtype, z_bad[I_100M])


@pytest.mark.slow
def test_reference_matches_closed_forms_and_the_linear_engine():
    """The reference itself: the clock error alone is ``(mu^2 + sigma^2) v v^T`` about an
    unshifted mean, and every source is within Monte Carlo and linearisation error of the
    first-order engine (an independent third implementation)."""
    obs, model, T = make_obs(), model_for(), transform("covariance")
    ref = reference_propagate(obs, model, T_world_station=T, weather=WEATHER, samples=M,
                              rng=np.random.default_rng(5))
    lin = propagate(obs, model, T_world_station=T, weather=WEATHER)
    vel_w = np.zeros((len(obs), 3))
    vel_w[:-1] = (lin.xyz[1:-1:2] - lin.xyz[:-2:2]).repeat(2, axis=0) / 0.25  # within pairs
    C_ts = model.time_sync_second_moment_s2 * vel_w[:, :, None] * vel_w[:, None, :]
    assert np.max(cov_z(ref.cov_by_source["time_sync"], C_ts, M, np.inf)) < Z_MAX
    assert np.max(mean_z(ref.mean_by_source["time_sync"], ref.cov_by_source["time_sync"],
                         lin.xyz, 0 * C_ts, M, 1)) < Z_MAX
    for s in NOISE_SOURCES:
        a, b = ref.cov_by_source[s], lin.cov_by_source[s]
        r = np.linalg.norm(a - b, axis=(1, 2)) / np.maximum(np.linalg.norm(b, axis=(1, 2)), 1e-30)
        assert np.all(r[np.linalg.norm(b, axis=(1, 2)) > 0] < 0.03), (s, r)


def test_reference_refuses_too_few_samples():
    obs, model = make_obs(), model_for()
    with pytest.raises(InputError, match="samples >= 2"):
        reference_propagate(obs, model, samples=1, rng=np.random.default_rng(0))
    T = RigidTransform(R_WS, T_WS, None, "world", "station", samples_rotation=np.tile(R_WS, (9, 1, 1)),
                       samples_translation=np.tile(T_WS, (9, 1)))
    with pytest.raises(InputError, match="fewer than the 10 samples"):
        reference_propagate(obs, model, T_world_station=T, samples=10,
                            rng=np.random.default_rng(0))
