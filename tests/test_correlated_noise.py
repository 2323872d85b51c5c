"""Time-correlated measurement noise carried by inflating the white covariance the GP is given
(rtsgt.noise.correlated; rtsgt.pipeline, section on time-correlated noise).

Closed forms first: the factor against the variance of averages of simulated white plus
Gauss-Markov noise, the inflation in each measurement's own frame, which components the plan
inflates. Then simulated deployments with the reality effect ``correlated_noise`` (Gauss-Markov
angle and distance noise beside the white noise), where the inflated runs' position NEES
against the truth is lower than that of the runs that take the measurements as independent,
and deployments where the static-stretch check finds nothing, whose runs are bit-identical
under both settings. Last, the option through the TOML, the command line and the run
directory.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter
from typer.testing import CliRunner

from rtsgt.app import read_ground_truth
from rtsgt.checks.static import COMPONENTS
from rtsgt.cli.main import app
from rtsgt.errors import InputError
from rtsgt.interpolation.prisms import gp_covariance
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import read_run, write_run
from rtsgt.measurement.polar import sight_frames
from rtsgt.noise.correlated import correlated_noise_plan, independence_factor, inflate_tracks
from rtsgt.noise.sources import CORRELATED_NOISE_SOURCE
from rtsgt.options import InterpolationOptions, RunOptions
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth
from rtsgt.simulation.reality import RealityEffects
from rtsgt.types import PrismTrack

DT = 0.4


def _white_plus_gauss_markov(rng, size: int, f: float, tau: float) -> np.ndarray:
    """Unit-variance noise at DT: white plus a stationary Gauss-Markov share ``f``."""
    rho = np.exp(-DT / tau)
    gm = lfilter([np.sqrt(1.0 - rho ** 2)], [1.0, -rho], rng.standard_normal(size),
                 zi=[rho * rng.standard_normal()])[0]  # stationary from the first sample
    return np.sqrt(1.0 - f) * rng.standard_normal(size) + np.sqrt(f) * gm


def _g(n: int, rho: float) -> float:
    """Variance of the mean of n unit Gauss-Markov samples, times n (module docstring)."""
    return (1 + rho) / (1 - rho) - 2 * rho * (1 - rho ** n) / (n * (1 - rho) ** 2)


# --- closed forms ---------------------------------------------------------------------------

@pytest.mark.parametrize("f, tau", [(0.5, 1.0), (0.9, 3.0), (0.99, 0.5)])
def test_the_factor_is_the_variance_of_a_long_average(f, tau):
    rng = np.random.default_rng(20240611)
    n, blocks = 1000, 3000
    z = _white_plus_gauss_markov(rng, n * blocks, f, tau)
    ratio = n * np.var(z.reshape(blocks, n).mean(axis=1), ddof=1)  # var(mean_n) * n / v
    k = float(independence_factor(f, tau, DT))
    rho = np.exp(-DT / tau)
    assert k == pytest.approx((1 - f) + f * (1 + rho) / (1 - rho), rel=1e-12)
    # the sample variance of 3000 block means is within 3 sigma (sqrt(2 / 3000) = 2.6 %)
    assert ratio == pytest.approx(k, rel=0.08)
    # what a GP taking the samples as independent would say (1), or the share f alone
    # (1 / (1 - f): the correlated part taken as fully dependent), is not it
    assert abs(ratio - 1.0) > 0.5 * (k - 1.0) and abs(ratio - 1 / (1 - f)) > 0.1 * ratio


def test_the_factor_is_conservative_for_a_short_average():
    rng = np.random.default_rng(7)
    f, tau, n, blocks = 0.8, 2.0, 5, 100_000
    z = _white_plus_gauss_markov(rng, n * blocks, f, tau)
    ratio = n * np.var(z.reshape(blocks, n).mean(axis=1), ddof=1)
    exact = (1 - f) + f * _g(n, np.exp(-DT / tau))
    assert ratio == pytest.approx(exact, rel=0.03)  # 3 sigma: 3 sqrt(2 / 1e5) = 1.3 %
    assert ratio < 0.5 * float(independence_factor(f, tau, DT))


def test_the_factor_is_one_without_correlation():
    assert independence_factor(0.0, 1.0, DT) == 1.0
    assert independence_factor(0.7, 1e-3, DT) == pytest.approx(1.0, abs=1e-12)  # rho -> 0
    k = independence_factor([0.2, 0.5], [1.0, 10.0], [0.4, 0.2])
    assert k.shape == (2,) and np.all(k > 1.0)


def _check_entry(verdict: str, f: float | None, tau: float | None) -> dict:
    return {"correlation": {"verdict": verdict, "correlated_fraction": f,
                            "correlation_time_s": tau}}


def _tracks(rng, n: int = 50) -> tuple[dict[str, PrismTrack], dict[str, np.ndarray]]:
    """Two prisms, each seen by its own station: an instrument covariance diagonal in each
    measurement's frame, a tilt covariance that is not, a calibration source."""
    tracks, stations = {}, {}
    for pid in ("1", "2"):
        station = rng.uniform(-30, 30, 3)
        xyz = station + rng.uniform(5, 80, (n, 1)) * np.column_stack(
            [np.cos(a := rng.uniform(0, 2 * np.pi, n)), np.sin(a), rng.uniform(-0.1, 0.1, n)])
        E = sight_frames(xyz, station)
        inst = np.einsum("nci,c,ncj->nij", E, np.array([2e-3, 0.4e-3, 0.3e-3]) ** 2, E)
        B = rng.normal(0, 2e-4, (n, 3, 3))
        tilt = B @ np.swapaxes(B, 1, 2) + 1e-9 * np.eye(3)
        calib = np.tile(np.diag([1e-6, 2e-6, 3e-6]), (n, 1, 1))
        by = {"instrument": inst, "tilt": tilt, "calibration": calib}
        tracks[pid] = PrismTrack(DT * np.arange(n), xyz, inst + tilt + calib, by, pid,
                                 "world", pid)
        stations[pid] = station
    return tracks, stations


def test_the_plan_inflates_only_the_correlation_the_check_calls_optimistic():
    rng = np.random.default_rng(3)
    tracks, _ = _tracks(rng)
    check = {"prisms": {
        "1": {"range": _check_entry("optimistic", 0.6, 1.5),
              "horizontal": _check_entry("pessimistic", 0.3, 0.2),  # alternating: no
              "vertical": _check_entry("consistent", None, None)},
        "2": {c: _check_entry("too few samples", None, None) for c in COMPONENTS}}}
    plan = correlated_noise_plan(check, tracks, apply=True)
    assert plan["mode"] == "inflate" and plan["applied"]
    p1 = plan["prisms"]["1"]
    assert p1["median_interval_s"] == pytest.approx(DT)
    assert p1["range"]["applied"] and p1["range"]["rho"] == pytest.approx(np.exp(-DT / 1.5))
    assert p1["range"]["factor"] == pytest.approx(0.4 + 0.6 * (1 + np.exp(-DT / 1.5))
                                                  / (1 - np.exp(-DT / 1.5)))
    assert not p1["horizontal"]["applied"] and p1["horizontal"]["factor"] == 1.0
    assert not p1["vertical"]["applied"] and p1["vertical"]["factor"] == 1.0
    assert not any(plan["prisms"]["2"][c]["applied"] for c in COMPONENTS)
    json.dumps(plan)  # JSON-ready
    ignored = correlated_noise_plan(check, tracks, apply=False)
    assert ignored["mode"] == "ignore" and not ignored["applied"]
    assert ignored["prisms"]["1"]["range"]["factor"] == p1["range"]["factor"]
    assert not ignored["prisms"]["1"]["range"]["applied"]
    none = correlated_noise_plan({"prisms": {}, "note": "no static stretch"}, tracks, apply=True)
    assert not none["applied"] and none["note"] == "no static stretch"


def test_the_white_covariance_is_inflated_in_each_measurements_frame():
    rng = np.random.default_rng(5)
    tracks, stations = _tracks(rng)
    check = {"prisms": {
        "1": {"range": _check_entry("optimistic", 0.5, 1.0),
              "horizontal": _check_entry("optimistic", 0.9, 4.0),
              "vertical": _check_entry("consistent", None, None)},
        "2": {c: _check_entry("consistent", None, None) for c in COMPONENTS}}}
    plan = correlated_noise_plan(check, tracks, apply=True)
    out = inflate_tracks(tracks, stations, plan)
    assert out["2"] is tracks["2"]  # nothing applied: the same track
    old, new = tracks["1"], out["1"]
    k = np.array([plan["prisms"]["1"][c]["factor"] for c in COMPONENTS])
    k[2] = 1.0
    E = sight_frames(old.xyz, stations["1"])
    # the model's sources stay as they are; the inflation is a source of its own
    for s in ("instrument", "tilt", "calibration"):
        np.testing.assert_array_equal(new.cov_by_source[s], old.cov_by_source[s])
    W = old.cov_by_source["instrument"] + old.cov_by_source["tilt"]
    given = gp_covariance(new, "white")
    np.testing.assert_allclose(given, W + new.cov_by_source[CORRELATED_NOISE_SOURCE],
                               rtol=1e-12, atol=1e-20)
    # what the GP is given: C' = A W A, symmetric positive definite
    A = np.einsum("nci,c,ncj->nij", E, np.sqrt(k), E)
    np.testing.assert_allclose(given, A @ W @ A, rtol=1e-10, atol=1e-24)
    np.testing.assert_allclose(given, np.swapaxes(given, 1, 2), rtol=0, atol=1e-20)
    assert np.all(np.linalg.eigvalsh(given) > 0)
    # the instrument, diagonal in the measurement's frame: its variances times k exactly,
    # and what the inflation adds to it is positive semi-definite
    inst = old.cov_by_source["instrument"]
    added = A @ inst @ A - inst
    in_frame = np.einsum("nci,nij,ndj->ncd", E, inst + added, E)
    was = np.einsum("nci,nij,ndj->ncd", E, inst, E)
    np.testing.assert_allclose(np.diagonal(in_frame, axis1=1, axis2=2),
                               k * np.diagonal(was, axis1=1, axis2=2), rtol=1e-10)
    off = in_frame - np.einsum("ncc->nc", in_frame)[:, :, None] * np.eye(3)
    assert np.max(np.abs(off)) < 1e-12 * np.max(in_frame)
    assert np.all(np.linalg.eigvalsh(added) > -1e-12 * np.max(in_frame))
    # the total moved by what the white part moved; under gp_noise = "all" only that part
    np.testing.assert_allclose(new.cov - old.cov, given - W, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(gp_covariance(new, "all") - gp_covariance(old, "all"),
                               given - W, rtol=1e-12, atol=1e-18)
    np.testing.assert_array_equal(new.xyz, old.xyz)
    assert (new.station, new.prism) == (old.station, old.prism)


# --- simulated deployments ------------------------------------------------------------------

#: Deployments whose robot stands 25-30 s at the start (the check's static stretch: 21-26 s
#: once its margins are cut) and has no line-of-sight losses, so that it finds the simulated
#: correlation; then 30-35 s of driving.
STANDING_START = {"duration_s": 60.0, "initial_stop_s": (25.0, 30.0), "dropouts": False}


def _run(tmp: Path, name: str, seed: int, reality: RealityEffects, **config):
    """The deployment of ``seed`` (STANDING_START, changed by ``config``) under both
    settings."""
    sim = simulate_deployment(SimulationConfig(reality=reality, **{**STANDING_START, **config}),
                              np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, tmp / name, overwrite=True))
    runs = {}
    for mode in ("inflate", "ignore"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            runs[mode] = run_pipeline(data, opts.updated(
                seed=seed, engine="linear", samples=20, rate_hz=2.0, correlated_noise=mode))
    return sim, runs


@pytest.mark.slow
def test_inflation_lowers_the_position_nees_where_correlation_is_found(tmp_path):
    nees: dict[str, list[np.ndarray]] = {"inflate": [], "ignore": []}
    applied = 0
    for seed in range(7000, 7006):
        sim, runs = _run(tmp_path, "d", seed, RealityEffects.only("correlated_noise"))
        plan = runs["inflate"].correlated_noise
        if not plan["applied"]:
            continue
        applied += 1
        # the static check is reported on the measurements as given, in both runs
        assert runs["inflate"].self_checks["static_noise"] == \
            runs["ignore"].self_checks["static_noise"]
        assert "correlated_noise" in runs["inflate"].computation.timings_s
        assert not runs["ignore"].correlated_noise["applied"]
        for mode, rec in runs.items():
            p, q = sim.truth_at(rec.groundtruth.t)
            nees[mode].append(compare_to_truth(rec.groundtruth, p, q).nees_position.values)
    assert applied >= 5
    pooled = {mode: np.concatenate(v).mean() / 3 for mode, v in nees.items()}
    per_run = [a.mean() < b.mean() for a, b in zip(nees["inflate"], nees["ignore"],
                                                     strict=True)]
    assert pooled["inflate"] < pooled["ignore"] - 0.05, pooled
    assert abs(pooled["inflate"] - 1.0) < abs(pooled["ignore"] - 1.0), pooled
    assert sum(per_run) >= applied - 1, per_run


def _same(a, b) -> None:
    ga, gb = a.groundtruth, b.groundtruth
    for x, y in ((ga.t, gb.t), (ga.position, gb.position), (ga.quat_xyzw, gb.quat_xyzw),
                 (ga.cov, gb.cov), (a.prisms_cov, b.prisms_cov), (a.prisms_xyz, b.prisms_xyz)):
        np.testing.assert_array_equal(x, y)
    assert a.self_checks == b.self_checks


@pytest.mark.parametrize("name, config", [
    ("white noise", {}),
    ("no static stretch", {"initial_stop_s": (1.0, 2.0), "stop_probability": 0.0}),
])
def test_where_nothing_is_found_the_run_is_bit_identical(tmp_path, name, config):
    _, runs = _run(tmp_path, "d", 7010, RealityEffects(), **config)
    plan = runs["inflate"].correlated_noise
    assert not plan["applied"] and plan["mode"] == "inflate"
    if name == "no static stretch":
        assert plan["note"] == "no static stretch" and not plan["prisms"]
    else:
        assert plan["prisms"]  # a stretch was checked, and nothing found
    assert "correlated_noise" not in runs["inflate"].computation.timings_s
    _same(runs["inflate"], runs["ignore"])


# --- the option -----------------------------------------------------------------------------

def test_the_option_is_checked_and_defaults_to_ignore():
    assert InterpolationOptions().correlated_noise == "ignore"
    assert RunOptions().updated(correlated_noise="inflate").interpolation.correlated_noise \
        == "inflate"
    with pytest.raises(InputError, match="correlated_noise 'inflate' or 'ignore'"):
        InterpolationOptions(correlated_noise="augment")


def test_the_option_round_trips_the_toml_the_command_line_and_the_run(tmp_path):
    sim = simulate_deployment(SimulationConfig(duration_s=40.0), np.random.default_rng(3))
    toml = write_deployment(sim, tmp_path / "dep")
    text = toml.read_text()
    assert 'qc = "loo"\n' in text
    toml.write_text(text.replace('qc = "loo"\n', 'qc = "loo"\ncorrelated_noise = "ignore"\n'))
    _, opts = load_deployment(toml)
    assert opts.interpolation.correlated_noise == "ignore"
    toml.write_text(text.replace('qc = "loo"\n', 'qc = "loo"\ncorrelated_noise = "no"\n'))
    with pytest.raises(InputError, match="correlated_noise"):
        load_deployment(toml)
    toml.write_text(text)

    runner = CliRunner()
    bad = runner.invoke(app, ["run", str(toml), "-o", str(tmp_path / "bad"),
                              "--correlated-noise", "augment"])
    assert bad.exit_code == 2 and "--correlated-noise" in bad.output
    out = tmp_path / "run"
    ok = runner.invoke(app, ["run", str(toml), "-o", str(out), "-q", "--engine", "linear",
                             "--samples", "20", "--correlated-noise", "ignore"])
    assert ok.exit_code == 0, ok.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["parameters"]["correlated_noise"] == "ignore"
    assert summary["interpolation"]["correlated_noise"]["mode"] == "ignore"
    back = read_run(out)
    assert back.options.interpolation.correlated_noise == "ignore"
    assert back.correlated_noise == summary["interpolation"]["correlated_noise"]
    # a run written before the option took the measurements as independent
    del summary["parameters"]["correlated_noise"], summary["interpolation"]
    (out / "summary.json").write_text(json.dumps(summary))
    old = read_run(out)
    assert old.options.interpolation.correlated_noise == "ignore" and not old.correlated_noise


def test_an_inflated_run_is_written_and_read_back_with_what_the_gps_were_given(tmp_path):
    sim = simulate_deployment(
        SimulationConfig(reality=RealityEffects.only("correlated_noise"), **STANDING_START),
        np.random.default_rng(7000))
    data, opts = load_deployment(write_deployment(sim, tmp_path / "dep"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = run_pipeline(data, opts.updated(seed=1, engine="linear", samples=20,
                                              rate_hz=2.0, correlated_noise="inflate"))
    assert rec.correlated_noise["applied"]
    out = write_run(rec, tmp_path / "run")
    back = read_run(out)
    assert back.correlated_noise == json.loads(json.dumps(rec.correlated_noise))
    assert any(CORRELATED_NOISE_SOURCE in tr.cov_by_source
               for tr in rec.computation.tracks.values())
    for pid, tr in rec.computation.tracks.items():
        # the instrument source as the model gives it, what the GP was given inflated
        np.testing.assert_allclose(back.measurements_gp_cov[pid], gp_covariance(tr, "white"),
                                   rtol=1e-12, atol=1e-30)
        np.testing.assert_allclose(gp_covariance(back.measurements[pid], "white"),
                                   gp_covariance(tr, "white"), rtol=1e-12, atol=1e-30)
        np.testing.assert_allclose(back.measurements[pid].cov_by_source["instrument"],
                                   tr.cov_by_source["instrument"], rtol=1e-12, atol=1e-30)
    # the continuous ground truth of the run read back fits the same GPs
    from rtsgt.evaluation import ContinuousGroundTruth
    t = rec.groundtruth.t[::7]
    mem = ContinuousGroundTruth.from_record(rec).query_poses(t)
    disk = read_ground_truth(out).query_poses(t)
    np.testing.assert_allclose(disk.position, mem.position, rtol=0, atol=1e-9)
    np.testing.assert_allclose(disk.cov, mem.cov, rtol=1e-6, atol=1e-14)
