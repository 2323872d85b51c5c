"""Self-checks (rtsgt.checks): the inter-prism distance check, its effective sample size and
its verdict, tested against series whose statistics are known in closed form."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.signal import lfilter

from rtsgt.checks.block_cv import block_cv_check, cv_blocks, cv_windows, nees_verdict
from rtsgt.checks.distances import (
    effective_sample_size,
    inter_prism_check,
    inter_prism_z,
    mean_z2_verdict,
    pose_speed,
)
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.interpolation.cross import gp_cross_covariance
from rtsgt.interpolation.gp import fit_track
from rtsgt.types import PrismTrack


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


# --------------------------------------------------------------------------------------------
# Block cross-validation of the tracks (rtsgt.checks.block_cv)
# --------------------------------------------------------------------------------------------

_QC = np.diag([3e-3, 2e-3, 1e-4])  # m^2/s^3
_R = np.diag([2.0e-3, 0.7e-3, 0.3e-3]) ** 2  # white measurement covariance, m^2


def _draw(rng, t, R, scale, qc=_QC):
    """Measurements at the times ``t`` of a track drawn from the WNOA prior (Qc times
    ``scale`` on each interval; at rest at the start) with white noise of covariance ``R``."""
    d = np.diff(t)
    la = np.zeros((d.size, 2, 2))  # Cholesky factor of Q(d) / Qc, times sqrt(scale)
    la[:, 0, 0] = np.sqrt(d**3 / 3)
    la[:, 1, 0] = (d**2 / 2) / la[:, 0, 0]
    la[:, 1, 1] = np.sqrt(d - la[:, 1, 0] ** 2)
    w = np.sqrt(scale)[:, None, None] * np.einsum(
        "nab,nbj->naj", la, rng.standard_normal((d.size, 2, 3))) @ np.linalg.cholesky(qc).T
    v = np.concatenate([np.zeros((1, 3)), np.cumsum(w[:, 1], axis=0)])
    p = np.concatenate([np.zeros((1, 3)), np.cumsum(d[:, None] * v[:-1] + w[:, 0], axis=0)])
    return p + np.einsum("nij,nj->ni", np.linalg.cholesky(R), rng.standard_normal(p.shape))


def _prior_track(rng, n=300, stand_s=0.0):
    """A track drawn from the WNOA prior itself at 2.5 Hz (jittered), standing (Qc scaled by
    1e-6, zero velocity) for the first ``stand_s`` seconds; white noise ``_R``. Returns
    (t, y, R, scale) with the true scale of Qc per interval."""
    t = np.cumsum(rng.uniform(0.3, 0.5, n))
    scale = np.where(t[1:] <= t[0] + stand_s, 1e-6, 1.0)
    R = np.tile(_R, (n, 1, 1))
    return t, _draw(rng, t, R, scale), R, scale


def _prior_run(rng, r_factor=1.0, qc_factor=1.0, tracks=3, n=300):
    """The tracks and GPs of a 'run' on prior-drawn tracks, the GP given ``r_factor`` times
    the true white covariance and ``qc_factor`` times the true Qc (1, 1: the model holds)."""
    trk, gps = {}, {}
    for i in range(tracks):
        t, y, R, scale = _prior_track(rng, n, stand_s=40.0)
        trk[str(i + 1)] = PrismTrack(t, y, r_factor * R, prism=str(i + 1))
        gps[str(i + 1)] = fit_track((t, y, r_factor * R), qc=qc_factor * _QC, qc_scale=scale)
    return trk, gps


def test_blocks_alternate_one_and_two_seconds_and_restart_after_a_long_gap():
    first = np.array([0, 0.4, 0.8, 1.1, 1.5, 1.9, 2.3, 2.7, 3.2, 3.6, 4.1, 4.5, 5.0, 5.4, 5.8,
                      6.2, 6.6])
    second = np.array([0, 0.4, 0.9, 1.3, 1.7, 2.2, 2.6, 3.1, 3.5])
    t = 100.0 + np.r_[first, 10.0 + second]  # a gap of 3.4 s > max_gap_s: a new segment
    block, fold = cv_blocks(t, max_gap_s=3.0)
    np.testing.assert_array_equal(fold, (np.r_[first, second] % 3.0 >= 1.0).astype(int))
    # [0, 1) [1, 3) [3, 4) [4, 6) [6, 7), then from the second segment's first measurement
    np.testing.assert_array_equal(
        block, [0, 0, 0, 1, 1, 1, 1, 1, 2, 2, 3, 3, 3, 3, 3, 4, 4, 5, 5, 5, 6, 6, 6, 6, 7, 7])


def test_a_window_is_judged_by_its_prediction_from_all_the_other_measurements():
    """Each window's NEES, computed from the run's GP alone, against the refit without its
    measurements (``fit_track(held_out=...)`` and, with one Qc, the fit without them): the
    prediction error against the joint covariance of the GP's prediction at the window's
    times (gp_cross_covariance) plus the white covariance. The variance of the sum of the
    windows' NEES (2 dof each, plus each neighbouring pair's share) against its sample
    variance over 1000 draws of tracks at the same times."""
    rng = np.random.default_rng(11)
    t, y, R, scale = _prior_track(rng, 60, stand_s=8.0)
    R = R * rng.uniform(0.5, 2.0, (t.size, 1, 1))
    gp = fit_track((t, y, R), qc=_QC, qc_scale=scale)
    w = cv_windows((t, y, R), gp, 3.0)
    block, _ = cv_blocks(t, 3.0)
    assert w["nees"].size > 10 and np.all(np.diff(w["centre"]) > 0)
    plain = fit_track((t, y, R), qc=_QC)
    w_plain = cv_windows((t, y, R), plain, 3.0)
    for i in range(w["nees"].size):
        inside = np.arange(w["first"][i], w["last"][i] + 1)
        assert np.all(block[inside] == block[inside[0]])
        assert w["t_before"][i] == t[inside[0] - 1] and w["t_after"][i] == t[inside[-1] + 1]
        held = np.isin(np.arange(t.size), inside)
        ti, m = t[inside], inside.size
        g = fit_track((t, y, R), qc=_QC, qc_scale=scale, held_out=held)
        ref = fit_track((t[~held], y[~held], R[~held]), qc=_QC)
        for fit, got, cross in ((g, w["nees"][i], False), (ref, w_plain["nees"][i], True)):
            a, b = (x.ravel() for x in np.meshgrid(np.arange(m), np.arange(m), indexing="ij"))
            if cross:  # the joint prediction between the kept measurements around the window
                c = gp_cross_covariance(fit, ti[a], ti[b])[:, :3, :3]
                e = (y[inside] - fit.query(ti).position).ravel()
            else:  # the held-out knots' posterior, jointly (lag-one chain, computed here)
                full = np.zeros((m, m, 6, 6))
                for j in range(m):
                    full[j, j] = fit.cov[inside[j]]
                    for q in range(j + 1, m):
                        k = inside[q] - 1
                        full[j, q] = full[j, q - 1] @ np.linalg.solve(fit.cov[k], fit.cross_cov[k])
                        full[q, j] = full[j, q].T
                c = full[a, b, :3, :3]
                e = (y[inside] - fit.mean[inside, :3]).ravel()
            sigma = c.reshape(m, m, 3, 3).transpose(0, 2, 1, 3).reshape(3 * m, 3 * m)
            for j in range(m):
                sigma[3 * j:3 * j + 3, 3 * j:3 * j + 3] += R[inside][j]
            assert got == pytest.approx(e @ np.linalg.solve(sigma, e), rel=1e-6)
        centre = 0.5 * (ti[0] + ti[-1])
        assert w["centre"][i] == centre
        assert w["into_gap"][i] == min(centre - w["t_before"][i], w["t_after"][i] - centre)
    # the covariance of neighbouring windows' NEES: the same times, new draws
    nees = []
    for _ in range(1000):
        y2 = _draw(rng, t, R, scale)
        nees.append(cv_windows((t, y2, R), fit_track((t, y2, R), qc=_QC, qc_scale=scale),
                               3.0)["nees"])
    nees = np.array(nees)
    dof = 3 * w["measurements"]
    np.testing.assert_allclose(nees.mean(axis=0) / dof, 1.0, atol=0.1)
    total = nees.sum(axis=1)
    model = 2.0 * dof.sum() + w["pair_var"].sum()
    assert total.var() == pytest.approx(model, rel=0.15)  # 1000 draws: 4.5 % standard error
    assert w["pair_var"].sum() > 0.2 * 2.0 * dof.sum()  # neighbours matter


def test_block_cv_is_calibrated_on_tracks_from_the_prior_and_catches_a_wrong_model():
    """Tracks drawn from the WNOA prior (standing 40 s, then moving), judged with the true Qc,
    scales and white covariance: NEES / dof within 3 % of 1 pooled over 60 tracks. A white
    covariance 1.25x too small or too large, or Qc 4x too small or too large, is flagged in
    the right direction (and never the other) in at least 9 runs of 10 (3 tracks of 120 s
    each), on the whole run in at least 6 (the white covariance: about 80 % of runs) or 9
    (Qc)."""
    rng = np.random.default_rng(5)
    windows = []
    for _ in range(20):
        trk, gps = _prior_run(rng)
        windows += [cv_windows((tr.t, tr.xyz, tr.cov), gps[p], 3.0) for p, tr in trk.items()]
    pooled = nees_verdict(windows, [np.ones(w["nees"].size, bool) for w in windows])
    assert pooled["blocks"] > 4000 and pooled["verdict"] == "consistent"
    assert pooled["nees_per_dof"] == pytest.approx(1.0, abs=0.03)
    for (r_factor, qc_factor), want in {(1 / 1.25, 1.0): "optimistic", (1.0, 0.25): "optimistic",
                                        (1.25, 1.0): "pessimistic", (1.0, 4.0): "pessimistic",
                                        }.items():
        runs = [block_cv_check(*_prior_run(rng, r_factor, qc_factor), max_gap_s=3.0,
                               warn=False) for _ in range(10)]
        overall = sum(r["overall"]["verdict"] == want for r in runs)
        anywhere = sum(want in {r["overall"]["verdict"]} | {v["verdict"] for v in
                                                             r["regimes"].values()}
                       for r in runs)
        # the white noise matters most standing, Qc while moving: a run sees both
        assert overall >= (9 if qc_factor != 1.0 else 6) and anywhere >= 9, \
            (r_factor, qc_factor, overall, anywhere)
        wrong = ({"optimistic", "pessimistic"} - {want}) & {
            v["verdict"] for r in runs for v in [r["overall"], *r["regimes"].values()]}
        assert not wrong


def test_block_cv_rarely_fails_a_run_whose_model_holds():
    """100 runs of 3 prior-drawn tracks judged with their true model: each verdict (the whole
    run and every regime given one) fails in 1-10 % of them (95 % intervals; the effective
    sample size is estimated from the data); a run whose model holds raises no warning."""
    rng = np.random.default_rng(6)
    runs = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for _ in range(100):
            runs.append(block_cv_check(*_prior_run(rng), max_gap_s=3.0, warn=False))
        trk, gps = _prior_run(np.random.default_rng(0))
        assert block_cv_check(trk, gps, max_gap_s=3.0)["overall"]["verdict"] == "consistent"
    rates = {}
    for name in ("overall", "standing", "accelerating", "near", "far"):
        v = [r["overall"] if name == "overall" else r["regimes"][name] for r in runs]
        assert all(x["blocks"] >= 30 for x in v), name
        rates[name] = np.mean([x["verdict"] in ("optimistic", "pessimistic") for x in v])
    assert all(0.01 <= r <= 0.10 for r in rates.values()), rates
    # the regimes: 40 s standing of 120 s; held-out windows of 1 s and 2 s
    r = runs[0]["regimes"]
    assert 0.2 < r["standing"]["blocks"] / runs[0]["overall"]["blocks"] < 0.45
    assert r["near"]["blocks"] + r["far"]["blocks"] == runs[0]["overall"]["blocks"]
    assert r["far"]["measurements"] > 1.5 * r["near"]["measurements"]


def test_block_cv_warns_when_a_regime_fails():
    trk, gps = _prior_run(np.random.default_rng(7), qc_factor=0.25)
    with pytest.warns(RtsgtWarning) as said:
        out = block_cv_check(trk, gps, max_gap_s=3.0)
    assert any(str(w.message).startswith("self-check, block cross-validation over the whole "
                                         "run") and "covariance is too small" in str(w.message)
               for w in said)
    assert out["overall"]["verdict"] == "optimistic"
    assert set(out["tracks"]) == {"1", "2", "3"} and "verdict" not in out["tracks"]["1"]
    assert out["block_lengths_s"] == [1.0, 2.0]


def test_block_cv_of_short_tracks_says_too_few_blocks():
    """A track too short to score a window, and one with a single window: no verdict, and
    the statistic where there is one."""
    rng = np.random.default_rng(8)
    t, y, R, _ = _prior_track(rng, 3)  # 3 measurements within 1.2 s: one window, no neighbour
    gp = fit_track((t, y, R), qc=_QC)
    out = block_cv_check({"1": PrismTrack(t, y, R)}, {"1": gp}, max_gap_s=3.0, warn=False)
    assert out["overall"] == {"blocks": 0, "measurements": 0, "nees_per_dof": None,
                              "n_eff": None, "interval_95": None, "verdict": "too few blocks"}
    t = 0.4 * np.arange(10)  # windows [0, 1), [1, 3), [3, 4): only the middle one is inside
    R = np.tile(_R, (10, 1, 1))
    y = _draw(rng, t, R, np.ones(9))
    w = cv_windows((t, y, R), fit_track((t, y, R), qc=_QC), 3.0)
    assert (w["first"].tolist(), w["last"].tolist()) == ([3], [7])
    assert w["into_gap"][0] == pytest.approx(1.2) and np.all(w["pair_var"] == 0.0)
    with pytest.raises(InputError, match="knots"):
        cv_windows((t[1:], y[1:], R[1:]), fit_track((t, y, R), qc=_QC), 3.0)
