"""GCP extrinsic calibration: real excerpt, synthetic truth, Monte Carlo covariance, errors."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.stats import chi2

from _paths import EXCERPT
from rtsgt.calibration import calibrate, fit_stations, polar_point_covariance
from rtsgt.calibration.shots import EARTH_RADIUS_M, curvature_tilt
from rtsgt.choices import CALIBRATION_WEIGHTINGS
from rtsgt.errors import GeometryError, InputError
from rtsgt.geometry.so3 import exp_so3, log_so3
from rtsgt.geometry.transform import perturbation
from rtsgt.io.rts_project import read_gcp_rts_project
from rtsgt.measurement.instruments import TRIMBLE_S7
from rtsgt.measurement.polar import cartesian_to_polar, polar_to_cartesian
from rtsgt.types import GcpShots

GCP = EXCERPT / "GCP.txt"

#: Synthetic truth: T_world_station (rotation vector rad, translation m); world = station 1.
TRUTH = {
    "1": ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    "2": ((0.01, -0.02, 2.3), (14.0, -6.0, 0.8)),
    "3": ((0.0, 0.0, -0.9), (-9.0, 11.0, -0.5)),
}
MARKERS = np.array([
    [4.0, 3.0, -0.6], [-18.0, 7.0, 0.9], [25.0, 20.0, 1.8], [40.0, -15.0, 0.1],
    [-10.0, -30.0, -1.3], [6.0, 50.0, 2.6], [-45.0, -28.0, -0.2], [60.0, 25.0, 2.2],
    [-30.0, 35.0, 3.5], [15.0, -42.0, -2.0],
])


def truth(s):
    rv, t = TRUTH[s]
    return exp_so3(np.array(rv)), np.array(t, dtype=float)


def true_polar(markers=MARKERS, stations=("1", "2", "3"), transforms=None):
    """Noise-free (hz, v, d with constant) of every marker from every station, station order;
    ``transforms``: station -> (R, t), the synthetic ``TRUTH`` when None."""
    hz, v, d, st, mk = [], [], [], [], []
    for s in stations:
        R, t = truth(s) if transforms is None else transforms[s]
        h, z, r = cartesian_to_polar((markers - t) @ R)
        hz.append(h)
        v.append(z)
        d.append(r)
        st += [s] * len(markers)
        mk += [str(i + 1) for i in range(len(markers))]
    return np.concatenate(hz), np.concatenate(v), np.concatenate(d), st, mk


def shots_of(hz, v, d, st, mk, *, c=0.01, status=None):
    return GcpShots(st, mk, hz, v, np.asarray(d) - c, status=status, additive_constant=c)


def noisy_polar(hz, v, d, rng):
    """Independent implementation of the instrument + tilt noise (Vaidis et al. 2023, III)."""
    n = hz.shape
    sa = TRIMBLE_S7.angle_rad / TRIMBLE_S7.confidence_sigma
    st = TRIMBLE_S7.tilt_rad / TRIMBLE_S7.confidence_sigma
    sd = (TRIMBLE_S7.distance_constant_m + TRIMBLE_S7.distance_ppm * 1e-6 * d) / 2.0
    e_tilt = rng.normal(0.0, st, n)
    v2 = v + rng.normal(0.0, sa, n) + e_tilt
    hz2 = hz + rng.normal(0.0, sa, n) + e_tilt * np.cos(v2) / np.sin(v2)
    return hz2, v2, d + rng.normal(0.0, 1.0, n) * sd


# ---------------------------------------------------------------- real excerpt


@pytest.fixture(scope="module")
def real_result():
    return calibrate(read_gcp_rts_project(GCP), samples=500, rng=np.random.default_rng(0))


def test_real_gcp_fit_matches_source_md(real_result):
    # SOURCE.md "Facts for tests" (the reference code's unweighted fit), with the +0.01 m
    # additive constant
    unweighted = calibrate(read_gcp_rts_project(GCP), samples=0, weighting="none")
    T2 = unweighted.transforms["2"]
    T3 = unweighted.transforms["3"]
    assert np.degrees(T2.yaw) == pytest.approx(159.94, abs=0.05)
    np.testing.assert_allclose(T2.translation, [-0.659, -1.301, 0.286], atol=0.005)
    assert np.degrees(T3.yaw) == pytest.approx(1.99, abs=0.05)
    np.testing.assert_allclose(T3.translation, [0.873, -2.433, 0.000], atol=0.005)
    res = unweighted.residuals
    assert len(res) == 36  # 12 markers x 3 pairs
    assert res.median_m * 1e3 == pytest.approx(1.90, abs=0.1)
    assert res.max_m * 1e3 == pytest.approx(8.25, abs=0.1)
    assert sorted(set(zip(res.station_a, res.station_b, strict=True))) == [
        ("1", "2"), ("1", "3"), ("2", "3")
    ]
    # the generalised least-squares fit stays within a few millimetres of it
    assert real_result.weighting == "none"
    gls = calibrate(read_gcp_rts_project(GCP), samples=0, weighting="gls")
    for s in ("2", "3"):
        dt = gls.transforms[s].translation - unweighted.transforms[s].translation
        assert 1e-5 < np.abs(dt).max() < 3e-3
    assert real_result.markers_used["2"] == tuple(str(m) for m in range(1, 13))
    assert real_result.excluded_shots == 0 and real_result.markers_skipped == ()


def test_real_gcp_additive_constant_matters():
    a = fit_stations(read_gcp_rts_project(GCP))
    b = fit_stations(read_gcp_rts_project(GCP, additive_constant=0.0))
    # the constant shifts every point radially by 1 cm: the fit moves by mm, not by nothing
    assert 1e-4 < np.linalg.norm(a["2"].translation - b["2"].translation) < 0.02


def test_real_gcp_uncertainty_is_sub_millimetre_and_consistent(real_result):
    res = real_result.residuals
    for s in ("2", "3"):
        T = real_result.transforms[s]
        sig = np.sqrt(np.diag(T.covariance))
        assert np.all(sig[:2] > 2e-4) and np.all(sig[:3] < 2e-3)  # 0.2-2 mm
        assert np.all(sig[3:] < np.radians(0.01))
        assert T.samples_rotation.shape == (500, 3, 3) and T.samples_translation.shape == (500, 3)
    # the residuals are what the noise model predicts: a pair's residual has covariance
    # C_a + C_b (fit error is smaller); the median of |N(0, C)| over the 36 lies in its range
    assert 1e-3 < res.median_m < 3e-3


# ---------------------------------------------------------------- synthetic truth


def test_noise_free_shots_recover_the_truth_exactly():
    hz, v, d, st, mk = true_polar()
    for weighting in CALIBRATION_WEIGHTINGS:
        T = fit_stations(shots_of(hz, v, d, st, mk), weighting=weighting)
        for s in ("1", "2", "3"):
            R, t = truth(s)
            np.testing.assert_allclose(T[s].rotation, R, atol=1e-12)
            np.testing.assert_allclose(T[s].translation, t, atol=1e-10)
    r = calibrate(shots_of(hz, v, d, st, mk), samples=0)
    assert r.residuals.max_m < 1e-9 and len(r.residuals) == 30
    assert r.transforms["2"].covariance is None and r.transforms["2"].samples_rotation is None


def test_other_reference_station_is_the_inverse():
    hz, v, d, st, mk = true_polar()
    T = fit_stations(shots_of(hz, v, d, st, mk), reference_station="2")
    R1, t1 = truth("2")
    np.testing.assert_allclose(T["1"].rotation, R1.T, atol=1e-12)
    np.testing.assert_allclose(T["1"].translation, -R1.T @ t1, atol=1e-10)
    np.testing.assert_array_equal(T["2"].rotation, np.eye(3))


def test_reflection_is_guarded():
    # station 2 records counter-clockwise directions (a mirror image of its points): the best
    # *proper* rotation is returned, never a reflection, and the residuals expose the problem
    hz, v, d, st, mk = true_polar()
    mirrored = np.where(np.array(st) == "2", np.mod(-hz, 2 * np.pi), hz)
    r = calibrate(shots_of(mirrored, v, d, st, mk), samples=50, rng=np.random.default_rng(0))
    R = r.transforms["2"].rotation
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.all(np.linalg.det(r.transforms["2"].samples_rotation) > 0.999)
    assert r.residuals.max_m > 1.0


def shot_covariances(hz, v, d):
    """Each shot's first-order covariance, from a finite-difference Jacobian and the polar
    covariance written out here."""
    sa2 = (TRIMBLE_S7.angle_rad / 2) ** 2
    st2 = (TRIMBLE_S7.tilt_rad / 2) ** 2
    sd2 = ((0.004 + 2e-6 * d) / 2) ** 2
    cot = 1 / np.tan(v)
    C = np.zeros((len(hz), 3, 3))
    for k in range(len(hz)):
        J = np.empty((3, 3))
        for j, h in enumerate((1e-7, 1e-7, 1e-6)):
            e = np.zeros(3)
            e[j] = h
            a = np.array([hz[k], v[k], d[k]])
            J[:, j] = (polar_to_cartesian(*(a + e)) - polar_to_cartesian(*(a - e))) / (2 * h)
        S = np.array([[sa2 + st2 * cot[k] ** 2, st2 * cot[k], 0],
                      [st2 * cot[k], sa2 + st2, 0], [0, 0, sd2[k]]])
        C[k] = J @ S @ J.T
    return C


def test_weighted_fit_matches_an_independent_weighted_least_squares():
    rng = np.random.default_rng(5)
    hz, v, d, st, mk = true_polar()
    hz, v, d = noisy_polar(hz, v, d, rng)
    shots = shots_of(hz, v, d, st, mk)
    T = fit_stations(shots, weighting="trace")
    trace = np.trace(shot_covariances(hz, v, d), axis1=1, axis2=2)
    np.testing.assert_allclose(
        trace, np.trace(polar_point_covariance(hz, v, d, TRIMBLE_S7), axis1=1, axis2=2),
        rtol=1e-6,
    )
    p = polar_to_cartesian(hz, v, d)
    st = np.array(st)
    for s in ("2", "3"):
        ps, pr = p[st == s], p[st == "1"]
        w = 1 / (trace[st == s] + trace[st == "1"])

        def cost(x, ps=ps, pr=pr, w=w):
            return (np.sqrt(w)[:, None] * (pr - ps @ exp_so3(x[:3]).T - x[3:])).ravel()

        x0 = np.concatenate([np.array(TRUTH[s][0]) + 0.01, TRUTH[s][1]])
        sol = least_squares(cost, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
        np.testing.assert_allclose(T[s].rotation, exp_so3(sol.x[:3]), atol=1e-9)
        np.testing.assert_allclose(T[s].translation, sol.x[3:], atol=1e-8)
    # the weights change the answer (they are used), but only within the noise
    U = fit_stations(shots, weighting="none")
    assert 1e-7 < np.abs(U["2"].translation - T["2"].translation).max() < 2e-3


@pytest.mark.parametrize("model", ["6dof", "4dof"])
def test_gls_fit_matches_an_independent_generalised_least_squares(model):
    """The generalised least-squares fit (full covariance of each residual, evaluated at the
    trace-weighted fit's rotation) against scipy's least squares on the residuals whitened
    here, with the covariances of a finite-difference Jacobian; under 4 DOF with the tilt of
    the Earth's curvature inside the cost (on levelled stations: the model must hold)."""
    rng = np.random.default_rng(6)
    if model == "6dof":
        hz, v, d, st, mk = true_polar()
        hz, v, d = noisy_polar(hz, v, d, rng)
        shots = shots_of(hz, v, d, st, mk)
        truth_T = {s: truth(s) for s in TRUTH}
    else:
        shots, truth_T = levelled_deployment(rng)
        hz, v, d, st = shots.hz, shots.v, shots.d + shots.additive_constant, shots.station
    T = fit_stations(shots, weighting="gls", model=model)
    start = fit_stations(shots, weighting="trace", model=model)
    C = shot_covariances(hz, v, d)
    p = polar_to_cartesian(hz, v, d)
    st = np.array(st)
    for s in ("2", "3"):
        ps, pr = p[st == s], p[st == "1"]
        R0 = start[s].rotation
        L = np.linalg.cholesky(C[st == "1"] + R0 @ C[st == s] @ R0.T)

        def transform(x):
            if model == "6dof":
                return exp_so3(x[:3]), x[3:]
            tilt = np.array([-x[2], x[1], 0.0]) / EARTH_RADIUS_M
            return exp_so3(tilt) @ exp_so3(np.array([0.0, 0.0, x[0]])), x[1:]

        def cost(x, ps=ps, pr=pr, L=L):
            R, t = transform(x)
            return np.linalg.solve(L, (pr - ps @ R.T - t)[..., None]).ravel()

        R_true, t_true = truth_T[s]
        x0 = (np.concatenate([log_so3(R_true) + 0.01, t_true]) if model == "6dof"
              else np.r_[np.arctan2(R_true[1, 0], R_true[0, 0]) + 0.01, t_true])
        sol = least_squares(cost, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
        R, t = transform(sol.x)
        np.testing.assert_allclose(T[s].rotation, R, atol=1e-9)
        np.testing.assert_allclose(T[s].translation, t, atol=1e-8)
        # and it is not the trace-weighted fit
        assert np.abs(start[s].translation - t).max() > 1e-6


def test_monte_carlo_covariance_matches_independent_repeated_draws():
    """MC covariance (batched, one call) vs the spread of fit_stations over independent draws.

    Independent in code path (noise drawn by this test, nominal fits one by one) and in data.
    N = 300 trials: the whitened empirical covariance must be I within Wishart sampling error
    (the extreme eigenvalues of a 6x6 Wishart(300)/300 fall in about [0.65, 1.4]; its mean
    eigenvalue has a standard deviation of 3.3 %), and the 95 % chi-square(6)
    region centred on each trial's estimate must cover the truth 95 % of the time
    (binomial standard deviation 1.3 %).
    """
    rng = np.random.default_rng(2023)
    hz0, v0, d0, st, mk = true_polar()
    n_trials = 300
    xi = {s: np.empty((n_trials, 6)) for s in ("2", "3")}
    for k in range(n_trials):
        T = fit_stations(shots_of(*noisy_polar(hz0, v0, d0, rng), st, mk))
        for s in xi:
            R, t = truth(s)
            xi[s][k] = perturbation(T[s].rotation, T[s].translation, R, t)  # truth about estimate
    mc = calibrate(
        shots_of(*noisy_polar(hz0, v0, d0, rng), st, mk), samples=4000,
        rng=np.random.default_rng(1),
    )
    for s in xi:
        C = mc.transforms[s].covariance
        L = np.linalg.cholesky(C)
        z = np.linalg.solve(L, xi[s].T).T  # whitened errors, ~ N(0, I) if C is right
        W = z.T @ z / n_trials
        eig = np.linalg.eigvalsh(W)
        assert 0.6 < eig.min() and eig.max() < 1.45, (s, eig)
        assert np.trace(W) / 6 == pytest.approx(1.0, abs=0.1)
        m2 = np.einsum("ki,ki->k", z, z)
        coverage = np.mean(m2 <= chi2.ppf(0.95, 6))
        assert 0.91 <= coverage <= 0.99, (s, coverage)
        # the samples reproduce the stored covariance (convention of geometry.transform)
        T = mc.transforms[s]
        x = perturbation(T.rotation, T.translation, T.samples_rotation, T.samples_translation)
        np.testing.assert_allclose(np.cov(x, rowvar=False), C, rtol=1e-9, atol=1e-18)


def test_weighted_monte_carlo_is_not_worse():
    # markers from 4 to 80 m: weighting by 1/trace down-weights the far, noisier ones, the
    # full covariance also the directions each shot is known worse in
    rng = np.random.default_rng(7)
    hz, v, d, st, mk = true_polar()
    shots = shots_of(*noisy_polar(hz, v, d, rng), st, mk)
    res = {w: calibrate(shots, samples=3000, rng=np.random.default_rng(3), weighting=w)
           for w in CALIBRATION_WEIGHTINGS}
    assert {w: r.weighting for w, r in res.items()} == {w: w for w in CALIBRATION_WEIGHTINGS}
    for s in ("2", "3"):
        var = {w: np.trace(r.transforms[s].covariance[:3, :3]) for w, r in res.items()}
        assert var["trace"] < 1.05 * var["none"]
        assert var["gls"] < 1.05 * var["trace"]


def test_monte_carlo_is_seeded_and_shaped():
    hz, v, d, st, mk = true_polar()
    shots = shots_of(hz, v, d, st, mk)
    a = calibrate(shots, samples=200, rng=np.random.default_rng(11))
    b = calibrate(shots, samples=200, rng=np.random.default_rng(11))
    c = calibrate(shots, samples=200, rng=np.random.default_rng(12))
    np.testing.assert_array_equal(a.transforms["3"].covariance, b.transforms["3"].covariance)
    assert not np.array_equal(a.transforms["3"].covariance, c.transforms["3"].covariance)
    ref = a.transforms["1"]
    np.testing.assert_array_equal(ref.covariance, np.zeros((6, 6)))
    np.testing.assert_array_equal(ref.samples_rotation, np.broadcast_to(np.eye(3), (200, 3, 3)))
    np.testing.assert_array_equal(ref.samples_translation, np.zeros((200, 3)))
    assert a.samples == 200 and a.reference_station == "1"
    assert np.all(np.linalg.eigvalsh(a.transforms["2"].covariance) > 0)
    with pytest.raises(ValueError, match="samples"):
        calibrate(shots, samples=1)
    with pytest.raises(TypeError, match="InstrumentProfile"):
        calibrate(shots, instrument="trimble-s7")


# ---------------------------------------------------------------- bad input


def test_unknown_reference_station_lists_known_ones():
    hz, v, d, st, mk = true_polar()
    with pytest.raises(InputError, match=r"unknown reference station '7'; .*: 1, 2, 3"):
        calibrate(shots_of(hz, v, d, st, mk), reference_station="7", samples=0)


def test_single_station_is_refused():
    hz, v, d, st, mk = true_polar(stations=("1",))
    with pytest.raises(InputError, match="only one station"):
        fit_stations(shots_of(hz, v, d, st, mk))


def test_marker_seen_by_one_station_is_skipped_and_reported():
    hz, v, d, st, mk = true_polar()
    keep = ~((np.array(st) != "1") & (np.array(mk) == "4"))  # marker 4 only seen by station 1
    args = [np.asarray(a)[keep] for a in (hz, v, d, st, mk)]
    with pytest.warns(UserWarning, match=r"marker\(s\) 4 shot validly by fewer than 2"):
        r = calibrate(shots_of(*args), samples=0)
    assert r.markers_skipped == ("4",)
    assert "4" not in r.markers_used["2"] and "4" not in r.markers_used["1"]
    assert len(r.residuals) == 27 and "4" not in set(r.residuals.marker)


def test_status_nonzero_shots_are_excluded_and_counted():
    hz, v, d, st, mk = true_polar()
    status = np.zeros(len(hz), int)
    bad = [3, 15]  # station 1 marker 4, station 2 marker 6
    status[bad] = 4
    d = d.copy()
    d[bad] += 5.0  # garbage that would spoil the fit if it were used
    # marker 4 (invalid on station 1) is still seen by 2 and 3: not skipped, no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = calibrate(shots_of(hz, v, d, st, mk, status=status), samples=0)
    assert r.excluded_shots == 2
    assert "4" not in r.markers_used["2"] and "6" not in r.markers_used["2"]
    assert "6" in r.markers_used["3"]
    assert r.residuals.max_m < 1e-9  # garbage not used anywhere
    assert r.markers_skipped == ()
    # 30 residuals less the pairs of the two invalid shots: (1-2, 1-3) for 4, (1-2, 2-3) for 6
    assert len(r.residuals) == 30 - 4
    assert "4" in set(r.residuals.marker[(r.residuals.station_a == "2")])


def test_invalid_values_in_valid_shots_are_refused():
    hz, v, d, st, mk = true_polar()
    v = v.copy()
    v[12] = np.nan  # station 2, marker 3
    with pytest.raises(InputError, match=r"marker 3 by station 2 \(shot 12\).*v=nan"):
        fit_stations(shots_of(hz, v, d, st, mk))
    status = np.zeros(len(hz), int)
    status[12] = 2  # the same garbage with an error status is simply excluded
    assert calibrate(shots_of(hz, v, d, st, mk, status=status), samples=0).excluded_shots == 1


def test_fewer_than_three_common_markers():
    hz, v, d, st, mk = true_polar()
    st_, mk_ = np.array(st), np.array(mk)
    # station 3 shares only markers 1 and 2 with the reference (its others are invalid)
    status = np.where((st_ == "3") & ~np.isin(mk_, ["1", "2"]), 1, 0)
    with pytest.raises(GeometryError, match=r"station 3 shares 2 valid marker\(s\) .* \(1, 2\)"):
        fit_stations(shots_of(hz, v, d, st, mk, status=status))


def test_collinear_markers_are_refused():
    line = np.array([[x, 0.5 * x + 3.0, 0.02 * x] for x in (-30.0, -10.0, 5.0, 20.0, 45.0)])
    hz, v, d, st, mk = true_polar(markers=line)
    with pytest.raises(GeometryError, match=r"station 2: markers .* collinear"):
        fit_stations(shots_of(hz, v, d, st, mk))
    # still refused with measurement noise (spread off the line within the noise)
    hz, v, d = noisy_polar(hz, v, d, np.random.default_rng(0))
    with pytest.raises(GeometryError, match="collinear"):
        calibrate(shots_of(hz, v, d, st, mk), samples=10, rng=np.random.default_rng(0))
    # a marker 7 m off the line makes the geometry well posed again
    ok = np.vstack([line, [[2.0, -3.0, 0.5]]])
    hz, v, d, st, mk = true_polar(markers=ok)
    fit_stations(shots_of(hz, v, d, st, mk))


def test_duplicate_shot_names_both_lines(tmp_path):
    p = tmp_path / "GCP.txt"
    hz, v, d, st, mk = true_polar()
    shots = shots_of(hz, v, d, st, mk)
    from rtsgt.io.rts_project import write_gcp_rts_project

    dup = GcpShots(
        np.append(shots.station, "2"), np.append(shots.marker, "5"), np.append(shots.hz, 1.0),
        np.append(shots.v, 1.5), np.append(shots.d, 9.0), t=np.arange(31.0),
    )
    write_gcp_rts_project(p, dup)
    with pytest.raises(InputError, match=r"marker 5 twice .*line 16 and line 32") as e:
        fit_stations(read_gcp_rts_project(p))
    assert e.value.path == str(p) and e.value.line == 32


def test_calibration_does_not_read_files():
    import rtsgt.calibration.gcp as mod

    src = Path(mod.__file__).read_text()
    for bad in ("open(", "read_text", "import rtsgt.io", "from rtsgt.io", "print("):
        assert bad not in src
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        hz, v, d, st, mk = true_polar()
        calibrate(shots_of(hz, v, d, st, mk), samples=0)  # clean input: no warning at all


# ---------------------------------------------------------------- fit check (variance factor)


def test_fit_check_variance_factor_follows_its_chi_square_law():
    """Shots drawn with the instrument model (this file's independent noise): s0^2 has mean 1
    and its 95 % interval holds about 95 % of 300 deployments (binomial sd 1.3 %); with a
    1 mm vertical error per shot (pole heights) the z factor and the verdict see it."""
    rng = np.random.default_rng(31)
    hz0, v0, d0, st, mk = true_polar()
    factors, inside = [], []
    for _ in range(300):
        c = calibrate(shots_of(*noisy_polar(hz0, v0, d0, rng), st, mk), samples=0)
        for s in ("2", "3"):
            f = c.fit_checks[s]
            assert (f.markers, f.dof) == (10, 24)
            factors.append(f.variance_factor)
            inside.append(f.verdict == "consistent")
    # the dof is exact for generalised least squares; the unweighted fit is close to it
    assert np.mean(factors) == pytest.approx(1.0, abs=0.08)
    assert 0.90 <= np.mean(inside) <= 0.985
    # a vertical error of 1 mm on every shot, which the model does not have
    pts = polar_to_cartesian(*noisy_polar(hz0, v0, d0, rng))
    pts[:, 2] += rng.normal(0.0, 1e-3, pts.shape[0])
    c = calibrate(shots_of(*cartesian_to_polar(pts), st, mk), samples=0)
    for s in ("2", "3"):
        f = c.fit_checks[s]
        assert f.verdict == "optimistic" and f.axis_factors[2] > 5 * max(f.axis_factors[:2])
    assert c.fit_checks.keys() == {"2", "3"}  # not the reference


@pytest.mark.slow
def test_variance_components_make_the_calibration_covariance_honest_again():
    """Shots with a 1 mm vertical error the instrument model does not have (pole heights):
    without variance components the calibration covariance is far too small in z and tilt
    (whitened errors over 200 independent deployments: mean squared norm / 6 far above 1);
    with them, the added vertical sigma is found (about 1 mm; none horizontal) and the
    covariance covers the errors again. Shots that follow the model get nothing added in
    most deployments (the components need a significant excess)."""
    rng = np.random.default_rng(44)
    hz0, v0, d0, st, mk = true_polar(np.vstack([MARKERS, MARKERS[:4] * 0.7 + 3.0]))
    nees = {False: [], True: []}
    added_v, added_h = [], []
    for k in range(200):
        pts = polar_to_cartesian(*noisy_polar(hz0, v0, d0, rng))
        pts[:, 2] += rng.normal(0.0, 1e-3, pts.shape[0])  # vertical: station frames are level
        shots = shots_of(*cartesian_to_polar(pts), st, mk)
        for vc in (False, True):
            c = calibrate(shots, samples=300, rng=np.random.default_rng(k),
                          variance_components=vc)
            if vc:
                added_h.append(c.extra_shot_sigma_m[0])
                added_v.append(c.extra_shot_sigma_m[1])
            for s in ("2", "3"):
                T = c.transforms[s]
                R, t = truth(s)
                xi = perturbation(T.rotation, T.translation, R, t)
                nees[vc].append(float(xi @ np.linalg.solve(T.covariance, xi)) / 6)
    assert np.median(added_v) == pytest.approx(1e-3, rel=0.25)
    assert np.mean(np.asarray(added_h) == 0.0) >= 0.8
    assert np.mean(nees[False]) > 5.0
    assert 0.75 <= np.mean(nees[True]) <= 1.3
    honest = [calibrate(shots_of(*noisy_polar(hz0, v0, d0, rng), st, mk), samples=0)
              .extra_shot_sigma_m for _ in range(100)]
    assert np.mean([h == 0.0 and v == 0.0 for h, v in honest]) >= 0.85


# ---------------------------------------------------------------- levelled stations (4 DOF)
#: Levelled stations 90-100 m from the reference (yaw, translation m): their verticals differ
#: from the reference's by 14-15 microradians (the Earth's curvature), 3-4x the 6-DOF fit's tilt
#: sigma.
LEVELLED = {"1": (0.0, (0.0, 0.0, 0.0)), "2": (2.3, (84.0, -36.0, 0.8)),
            "3": (-0.9, (-59.0, 71.0, -0.5))}


def levelled_deployment(rng):
    """Shots of 2x the markers from levelled stations on a sphere, each compensator off by its
    own tilt error (drawn here, independently of rtsgt: sigma_tilt per axis and station)."""
    sigma_tilt = TRIMBLE_S7.tilt_rad / TRIMBLE_S7.confidence_sigma
    comp = rng.normal(0.0, sigma_tilt, (3, 2))
    markers = MARKERS * 2.0
    truth_T = {}
    for j, (s, (yaw, t)) in enumerate(LEVELLED.items()):
        t = np.array(t, dtype=float)
        up = np.array([t[0], t[1], EARTH_RADIUS_M]) / np.hypot(np.hypot(t[0], t[1]), EARTH_RADIUS_M)
        # the vertical of a sphere, and the compensator's tilt relative to the reference's
        tilt = np.array([-up[1], up[0], 0.0]) + np.r_[comp[j] - comp[0], 0.0]
        truth_T[s] = (exp_so3(tilt) @ exp_so3(np.array([0.0, 0.0, yaw])), t)
    hz, v, d, st, mk = true_polar(markers, tuple(LEVELLED), truth_T)
    return shots_of(*noisy_polar(hz, v, d, rng), st, mk), truth_T


def test_curvature_tilt_is_the_angle_between_verticals():
    t = np.array([[100.0, 0.0, 3.0], [0.0, -250.0, 0.0], [30.0, 40.0, 0.0]])
    w = curvature_tilt(t)
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), np.hypot(t[:, 0], t[:, 1]) / 6.371e6)
    # turns the reference's vertical towards the station
    up = exp_so3(w) @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(up[:, :2] * 6.371e6, t[:, :2], rtol=1e-6)


def test_levelled_calibration_is_honest_and_sharper_than_six_dof():
    """150 deployments of levelled stations on the curved Earth, compensators off by their own
    tilt: the 4-DOF calibration's 6x6 covariance covers the truth (NEES / dof 1; a 1.25 is out of
    the bounds: 300 transforms of 6 dof give a standard error of about 0.05), with half the
    height sigma and a third of the tilt sigma of the 6-DOF fit of the same shots (unweighted).
    Without the curvature the levelled model would miss the truth by 14-15 microradians of
    tilt, several sigma. The same for the generalised least-squares fits, the default, which
    are as honest and sharper: two thirds of the horizontal sigma of the unweighted fits
    (a variance cut by half; measured 0.53 against 0.80 mm), and of the heights."""
    rng = np.random.default_rng(71)
    runs = [(m, w) for m in ("6dof", "4dof") for w in ("none", "gls")]
    nees = {r: [] for r in runs}
    sig = {r: [] for r in runs}
    p_values = []
    for k in range(150):
        shots, truth_T = levelled_deployment(rng)
        for model, weighting in runs:
            c = calibrate(shots, samples=300, rng=np.random.default_rng(k), model=model,
                          weighting=weighting, variance_components=False)
            assert c.model == model
            if weighting == "none":
                p_values += [lv.p_value for lv in c.levelling.values()]
            for s in ("2", "3"):
                T = c.transforms[s]
                xi = perturbation(T.rotation, T.translation, *truth_T[s])
                nees[model, weighting].append(float(xi @ np.linalg.solve(T.covariance, xi)) / 6)
                sig[model, weighting].append(np.sqrt(np.diag(T.covariance)))
    for run in runs:
        assert 0.85 <= np.mean(nees[run]) <= 1.15, (run, np.mean(nees[run]))
    # the levelling test: uniform p-values on levelled stations (600, both models)
    assert 0.02 <= np.mean(np.asarray(p_values) < 0.05) <= 0.09
    med = {r: np.median(v, axis=0) for r, v in sig.items()}
    s6, s4 = med["6dof", "none"], med["4dof", "none"]
    assert s4[2] < 0.65 * s6[2]  # height
    assert np.all(s4[3:5] < 0.4 * s6[3:5])  # tilt
    np.testing.assert_allclose(s4[[0, 1, 5]], s6[[0, 1, 5]], rtol=0.1)  # x, y, yaw: the same
    for model in ("6dof", "4dof"):
        g, u = med[model, "gls"], med[model, "none"]
        assert np.all(g[:3] < 0.8 * u[:3]), (model, g, u)  # x, y, z
        assert g[5] < 0.9 * u[5]  # yaw
    # the fitted tilt of a levelled station is the curvature's
    c = calibrate(shots, samples=0, model="4dof")
    for s in ("2", "3"):
        R = c.transforms[s].rotation
        yaw = np.arctan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1])
        tilt = log_so3(R @ exp_so3(np.array([0.0, 0.0, -yaw])))
        np.testing.assert_allclose(tilt, curvature_tilt(c.transforms[s].translation), atol=1e-9)


def test_unknown_calibration_model_is_refused():
    shots = shots_of(*true_polar())
    with pytest.raises(InputError, match="calibration model"):
        calibrate(shots, samples=0, model="5dof")


def test_levelling_check_finds_a_tilted_station():
    """A station whose compensator is off by 100 microradians (20 arcsec) about x: the levelling
    test says so (and warns under the 4-DOF model); the others stay levelled."""
    from rtsgt.checks.calibration import gcp_fit_check
    rng = np.random.default_rng(72)
    shots, _ = levelled_deployment(rng)
    st = np.asarray(shots.station)
    p = polar_to_cartesian(shots.hz, shots.v, shots.distance)  # additive constant applied
    m = st == "2"
    p[m] = p[m] @ exp_so3(np.array([100e-6, 0.0, 0.0]))  # the station's frame turned
    tilted = shots_of(*cartesian_to_polar(p), list(st), list(shots.marker))
    c = calibrate(tilted, samples=50, rng=np.random.default_rng(0), model="4dof",
                  variance_components=False)
    assert c.levelling["2"].p_value < 1e-4 and c.levelling["3"].p_value > 0.01
    with pytest.warns(UserWarning, match="levelling of station 2"):
        out = gcp_fit_check(c)
    assert out["levelling"]["2"]["verdict"] == "tilted"
    assert out["levelling"]["3"]["verdict"] == "levelled"
