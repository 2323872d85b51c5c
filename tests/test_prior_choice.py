"""Held-out windows of a track (rtsgt.interpolation.windows) and the choice of the GP's motion
prior per track by them (rtsgt.interpolation.prisms.fit_gps with ``prior = "select"``).

The window scores are checked against a refit without the window (the GP's own ``held_out``
and the joint covariance of its queries, :mod:`rtsgt.interpolation.cross`); the choice on
tracks simulated from each prior, whose truth is known.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from rtsgt.app import read_ground_truth
from rtsgt.errors import InputError
from rtsgt.interpolation import fit_track, wnoj_phi, wnoj_q
from rtsgt.interpolation.cross import gp_joint_covariance
from rtsgt.interpolation.prisms import fit_gps
from rtsgt.interpolation.windows import cv_windows, window_score
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import read_run, write_run
from rtsgt.options import InterpolationOptions
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.types import PrismTrack
from test_gp import random_spd, simulate_prior


def _simulate(rng, prior, n, q, sigma=1e-3):
    """A track of ``n`` measurements at 2.5 Hz (with a few gaps of 1-2 s) from the ``prior``
    with PSD ``q``; returns (t, y, R)."""
    dt = rng.uniform(0.35, 0.45, n - 1)
    dt[rng.random(n - 1) < 0.03] += rng.uniform(1.0, 2.0)
    t = 100.0 + np.concatenate([[0.0], np.cumsum(dt)])
    if prior == "wnoa":
        x = simulate_prior(rng, t, q, np.r_[rng.normal(size=3), rng.normal(size=3) * 0.3])
    else:
        x = [np.r_[rng.normal(size=3), rng.normal(size=6) * 0.3]]
        for d in dt:
            x.append(wnoj_phi(d) @ x[-1] + np.linalg.cholesky(wnoj_q(d, q)) @ rng.normal(size=9))
        x = np.array(x)
    R = random_spd(rng, n, sigma**2, cond=4.0)
    y = x[:, :3] + np.einsum("nij,nj->ni", np.linalg.cholesky(R), rng.normal(size=(n, 3)))
    return t, y, R


@pytest.mark.parametrize("prior", ["wnoa", "wnoj"])
def test_window_scores_are_the_refit_without_the_window(prior):
    """NEES and log predictive density of each window, computed from the fit with every
    measurement, against the GP fitted without the window: its joint prediction at the
    window's times plus the measurement covariance."""
    rng = np.random.default_rng(5)
    t, y, R = _simulate(rng, prior, 60, 0.05)
    qc = np.diag([0.04, 0.06, 0.01])
    scale = np.exp(rng.uniform(-1.0, 1.0, t.size - 1))
    gp = fit_track((t, y, R), qc=qc, qc_scale=scale, prior=prior)
    w = cv_windows((t, y, R), gp, 3.0)
    assert w["nees"].size >= 10
    for i in (0, 3, 8):
        idx = np.arange(w["first"][i], w["last"][i] + 1)
        held = np.zeros(t.size, bool)
        held[idx] = True
        ref = fit_track((t, y, R), qc=qc, qc_scale=scale, prior=prior, held_out=held)
        joint = gp_joint_covariance(ref, t[idx])  # (m, m, 3, 3)
        m = idx.size
        S = joint.transpose(0, 2, 1, 3).reshape(3 * m, 3 * m)
        for a in range(m):
            S[3 * a:3 * a + 3, 3 * a:3 * a + 3] += R[idx[a]]
        e = (y[idx] - ref.mean[idx, :3]).ravel()
        nees = float(e @ np.linalg.solve(S, e))
        assert w["nees"][i] == pytest.approx(nees, rel=1e-6)
        logpdf = stats.multivariate_normal(np.zeros(3 * m), S).logpdf(e)
        assert w["log_density"][i] == pytest.approx(logpdf, rel=1e-8, abs=1e-6)
    score = window_score((t, y, R), gp, 3.0)
    assert score["log_density"] == pytest.approx(float(w["log_density"].sum()))
    assert score["windows"] == w["nees"].size
    assert score["nees_per_dof"] == pytest.approx(w["nees"].sum() / (3 * w["measurements"].sum()))


def _tracks(rng, prior, q):
    return {str(i + 1): PrismTrack(*_simulate(rng, prior, 200, q), prism=str(i + 1))
            for i in range(3)}


def test_select_keeps_the_prior_the_tracks_come_from():
    """Tracks from the WNOA prior keep WNOA, tracks from the WNOJ prior get WNOJ (each with
    its own leave-one-out Qc, without motion classes); every prism records both scores."""
    rng = np.random.default_rng(2024)
    opts = InterpolationOptions(prior="select", motion_prior="constant")
    chosen = {"wnoa": [], "wnoj": []}
    for truth, q in (("wnoa", 0.02), ("wnoj", 0.2)):
        for _ in range(2):
            info: dict = {}
            gps = fit_gps(_tracks(rng, truth, q), opts, info=info)
            for pid, g in gps.items():
                pc = info[pid]["prior_choice"]
                assert g.prior == pc["chosen"] == info[pid]["prior"]
                assert pc[g.prior]["log_density"] >= pc[{"wnoa": "wnoj", "wnoj": "wnoa"}[
                    g.prior]]["log_density"]
                assert len(pc["wnoa"]["qc"]) == 3 and pc["wnoj"]["windows"] > 40
                chosen[truth].append(g.prior)
    # by 57 to 874 units of log density on these tracks of 200 measurements
    assert chosen == {"wnoa": ["wnoa"] * 6, "wnoj": ["wnoj"] * 6}, chosen


def test_fixed_priors_and_given_qc():
    rng = np.random.default_rng(3)
    tracks = _tracks(rng, "wnoj", 0.2)
    info: dict = {}
    gps = fit_gps(tracks, InterpolationOptions(prior="wnoj", motion_prior="constant"), info=info)
    assert {g.prior for g in gps.values()} == {"wnoj"} and info["1"]["prior"] == "wnoj"
    assert "prior_choice" not in info["1"]
    # a Qc given as a number is a WNOA PSD: "select" keeps WNOA
    gps = fit_gps(tracks, InterpolationOptions(prior="select", qc=0.01), info=info)
    assert {g.prior for g in gps.values()} == {"wnoa"}
    # a written run's Qc and prior per prism rebuild the same GPs
    again = fit_gps(tracks, InterpolationOptions(prior="select"),
                    qc={p: g.qc for p, g in gps.items()}, prior={"1": "wnoj"})
    assert again["1"].prior == "wnoj" and again["2"].prior == "wnoa"
    with pytest.raises(InputError, match="Expected prior"):
        InterpolationOptions(prior="singer")


def test_a_run_records_each_prior_and_its_directory_rebuilds_the_same_gps(tmp_path, capsys,
                                                                         monkeypatch):
    """``prior = "select"`` through the pipeline: summary.json says per prism the prior it got,
    both window scores and both Qc; the run read back refits the same GPs (prior, Qc, scales)."""
    sim = simulate_deployment(SimulationConfig(duration_s=120.0), np.random.default_rng(11))
    data, opts = load_deployment(write_deployment(sim, tmp_path / "dep"))
    result = run_pipeline(data, opts.updated(seed=11, engine="linear", prior="select"))
    out = write_run(result, tmp_path / "run")
    gps = result.computation.gps
    assert result.prior == {p: g.prior for p, g in gps.items()}
    doc = read_run(out).summary
    assert doc["parameters"]["prior"] == "select"
    for pid, g in gps.items():
        entry = doc["prisms"][pid]
        assert entry["prior"] == g.prior == entry["qc_fit"]["prior_choice"]["chosen"]
        for p in ("wnoa", "wnoj"):
            assert np.isfinite(entry["qc_fit"]["prior_choice"][p]["log_density"])
            assert len(entry["qc_fit"]["prior_choice"][p]["qc"]) == 3
    back = read_run(out)
    assert back.prior == result.prior and back.options.interpolation.prior == "select"
    # the run's table says each prism's prior (and the unit of its Qc)
    from rtsgt.cli.common import print_run_summary

    monkeypatch.setenv("COLUMNS", "200")  # one table row per line
    print_run_summary(back, out)
    table = capsys.readouterr().out
    for pid, g in gps.items():
        row = next(ln for ln in table.splitlines() if f"Qc prism {pid}" in ln)
        assert g.prior.upper() in row
        assert ("m^2/s^5" if g.prior == "wnoj" else "m^2/s^3") in row
    cgt = read_ground_truth(out)
    for pid, g in cgt.gps.items():
        assert g.prior == gps[pid].prior
        np.testing.assert_array_equal(g.qc, gps[pid].qc)
        np.testing.assert_allclose(g.mean, gps[pid].mean, rtol=0, atol=1e-9)
