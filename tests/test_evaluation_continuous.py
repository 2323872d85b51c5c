"""Continuous-time ground truth (GP tracks of a run) and its use by ``rtsgt evaluate``.

Simulated deployments with known truth (``sim.truth_at``), run through the pipeline and
written as run directories; the continuous ground truth is rebuilt from those files.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from rtsgt.app import read_ground_truth
from rtsgt.cli.main import app as main_app
from rtsgt.errors import InputError
from rtsgt.evaluation import evaluate
from rtsgt.evaluation.associate import ValidatedGroundTruth
from rtsgt.evaluation.groundtruth import DROP_REASONS, ContinuousGroundTruth
from rtsgt.evaluation.metrics import squared_mahalanobis
from rtsgt.filtering.gates import position_uncertainty
from rtsgt.geometry.so3 import quat_xyzw_to_matrix
from rtsgt.geometry.transform import perturbation
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import COV3_NAMES, columns_to_cov3, read_table, write_run
from rtsgt.io.trajectory import read_covariance_csv, write_covariance_csv, write_tum
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.types import PoseTrajectory
from test_evaluation_synth import perturbed, random_covariances

runner = CliRunner()


def _app() -> typer.Typer:
    """The application, with its rule for errors and exit statuses."""
    return main_app


def _simulate_run(tmp: Path, seed: int, **options):
    sim = simulate_deployment(SimulationConfig(duration_s=120.0), np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, tmp / f"dep{seed}"))
    result = run_pipeline(data, opts.updated(seed=seed, **options))
    out = write_run(result, tmp / f"run{seed}")
    return sim, result, out


@pytest.fixture(scope="module")
def linear_run(tmp_path_factory):
    return _simulate_run(tmp_path_factory.mktemp("cgt_linear"), 4, engine="linear")


@pytest.fixture(scope="module")
def mc_run(tmp_path_factory):
    return _simulate_run(tmp_path_factory.mktemp("cgt_mc"), 6, engine="mc", samples=400)


def _truth(sim, t) -> tuple[np.ndarray, np.ndarray]:
    p, q = sim.truth_at(t)
    return p, quat_xyzw_to_matrix(q)


def _errors(sim, t, position, quat_xyzw) -> np.ndarray:
    """Left perturbation from the truth to the given poses, (N, 6)."""
    p, R = _truth(sim, t)
    return perturbation(R, p, quat_xyzw_to_matrix(quat_xyzw), position)


def _corr_scaled(c: np.ndarray) -> np.ndarray:
    d = np.sqrt(np.einsum("kii->ki", c))
    return c / (d[:, :, None] * d[:, None, :])


# ----------------------------------------------------------------------------- (a) grid


def test_reproduces_the_run_at_its_grid_times_linear_engine(linear_run):
    sim, result, out = linear_run
    cgt = read_ground_truth(out)
    assert isinstance(cgt, ValidatedGroundTruth)
    assert cgt.options.pose.engine == "linear" and cgt.prism_ids == ("1", "2", "3")
    # the refitted GPs are the run's (same Qc, same measurements read back exactly)
    for pid, g in cgt.gps.items():
        np.testing.assert_array_equal(g.qc, result.computation.gps[pid].qc)
        np.testing.assert_allclose(g.mean, result.computation.gps[pid].mean, rtol=0, atol=1e-9)
    s = cgt.query_poses(result.computation.prisms.t)  # every queried grid time, kept or gated
    np.testing.assert_array_equal(s.valid, result.computation.keep)
    gated = ~result.computation.keep
    np.testing.assert_array_equal(
        s.reason[gated], np.char.add("gate_", result.computation.gate_report.reason[gated])
    )
    gt = read_covariance_csv(out / "groundtruth_covariance.csv")
    v = s.valid
    np.testing.assert_array_equal(s.t[v], gt.t)
    np.testing.assert_allclose(s.position[v], gt.position, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        quat_xyzw_to_matrix(s.quat_xyzw[v]), gt.rotation, rtol=0, atol=1e-9
    )
    # covariances: same numbers up to rounding (scaled by the standard deviations)
    scale = np.sqrt(np.einsum("kii,kjj->kij", gt.cov, gt.cov))
    assert np.max(np.abs(s.cov[v] - gt.cov) / scale) < 1e-9
    # the in-memory variant answers the same
    s2 = ContinuousGroundTruth.from_record(result).query_poses(result.computation.prisms.t)
    np.testing.assert_allclose(s2.position[v], s.position[v], rtol=0, atol=1e-9)
    assert np.max(np.abs(s2.cov[v] - gt.cov) / scale) < 1e-9


def test_gp_noise_all_refits_on_the_covariance_of_the_measurement_file(linear_run, tmp_path):
    """gp_noise = "all": the GP is given the cov_* columns of measurements/prism<i>.csv as
    written (read once, by rtsgt.io.run_dir.read_run), not the sum of the sources."""
    _, _, out = linear_run
    run = tmp_path / "all"
    shutil.copytree(out, run)
    summary = json.loads((run / "summary.json").read_text())
    summary["parameters"]["gp_noise"] = "all"
    (run / "summary.json").write_text(json.dumps(summary))
    cgt = read_ground_truth(run)
    assert cgt.options.interpolation.gp_noise == "all"
    for pid, tr in cgt.tracks.items():
        header, data = read_table(run / "measurements" / f"prism{pid}.csv")
        cols = [header.index(f"cov_{c}") for c in COV3_NAMES]
        np.testing.assert_array_equal(tr.cov, columns_to_cov3(data[:, cols]))


def test_reproduces_the_run_at_its_grid_times_monte_carlo(mc_run):
    """Monte Carlo: the run's own poses, covariances included, since the continuous ground
    truth draws from the run's pose stream (rtsgt.options.stage_rng)."""
    sim, result, out = mc_run
    cgt = read_ground_truth(out)
    assert (cgt.options.pose.engine, cgt.options.pose.samples, cgt.options.seed) == ("mc", 400, 6)
    s = cgt.query_poses(result.computation.prisms.t)
    np.testing.assert_array_equal(s.valid, result.computation.keep)
    gt = result.groundtruth
    v = s.valid
    np.testing.assert_allclose(s.position[v], gt.position, rtol=0, atol=1e-9)
    # the same draws: equal up to the rounding of the files read back (a 400-sample estimate
    # from independent draws would differ by ~10 %)
    scale = np.sqrt(np.einsum("kii,kjj->kij", gt.cov, gt.cov))
    assert np.max(np.abs(s.cov[v] - gt.cov) / scale) < 1e-6
    # a query is reproducible (its own generator from the run's seed)
    again = cgt.query_poses(result.computation.prisms.t)
    np.testing.assert_array_equal(again.cov, s.cov)
    # the linear engine agrees with the Monte Carlo one to its noise
    lin = read_ground_truth(out, engine="linear").query_poses(result.computation.prisms.t)
    r_lin = np.einsum("kii->ki", s.cov[v]) / np.einsum("kii->ki", lin.cov[v]) - 1.0
    assert np.all(np.abs(np.mean(r_lin, axis=0)) < 0.05)


# ----------------------------------------------------------------------------- (b) off grid


def test_off_grid_times_closer_to_the_truth_than_the_nearest_pose(linear_run):
    sim, result, out = linear_run
    cgt = read_ground_truth(out)
    gt = result.groundtruth
    rng = np.random.default_rng(40)
    t = np.arange(gt.t[0], gt.t[-1], 0.1) + rng.uniform(0.0, 0.1)  # a 10 Hz estimate's clock
    s = cgt.query_poses(t, max_gap_s=0.5)
    v = s.valid
    assert v.sum() > 800
    e = _errors(sim, t[v], s.position[v], s.quat_xyzw[v])
    rms_cont = np.sqrt(np.mean(np.sum(e[:, :3] ** 2, axis=1)))
    # nearest stored pose (what a naive association does)
    k = np.clip(np.searchsorted(gt.t, t[v]), 1, len(gt) - 1)
    k = np.where(np.abs(gt.t[k - 1] - t[v]) < np.abs(gt.t[k] - t[v]), k - 1, k)
    p_true, _ = _truth(sim, t[v])
    rms_near = np.sqrt(np.mean(np.sum((gt.position[k] - p_true) ** 2, axis=1)))
    assert rms_cont < 5e-3  # millimetres
    assert rms_cont < 0.1 * rms_near  # the nearest pose is centimetres off at 1-2 m/s
    # NEES against the exact truth: the continuous ground truth is as consistent between the
    # grid times as the run is on them, and within a factor 3 of the nominal 1 (over one
    # 2-minute run the systematic errors -- calibration, clocks, atmosphere -- are one draw
    # shared by every pose, so NEES / dof of the run itself spreads over ~0.4 - 2.2 by seed)
    n3 = squared_mahalanobis(e[:, :3], s.cov[v][:, :3, :3]).mean() / 3
    n6 = squared_mahalanobis(e, s.cov[v]).mean() / 6
    eg = _errors(sim, gt.t, gt.position, gt.quat_xyzw)
    g3 = squared_mahalanobis(eg[:, :3], gt.cov[:, :3, :3]).mean() / 3
    g6 = squared_mahalanobis(eg, gt.cov).mean() / 6
    assert 1 / 3 < n3 < 3 and 1 / 3 < n6 < 3
    assert abs(n3 / g3 - 1) < 0.15 and abs(n6 / g6 - 1) < 0.15


# ----------------------------------------------------------------------------- (c) consistency


def _estimate_from_truth(sim, t, cov, rng, report=None) -> PoseTrajectory:
    p, R = _truth(sim, t)
    return perturbed(t, p, R, cov, rng, report=report)


def test_estimate_with_known_covariance_is_consistent_biased_or_overconfident_is_not(linear_run):
    sim, result, out = linear_run
    cgt = read_ground_truth(out)
    gt = result.groundtruth
    rng = np.random.default_rng(41)
    t = np.arange(gt.t[0] - 2.0, gt.t[-1] + 2.0, 0.1) + rng.uniform(0.0, 0.1)
    # SLAM-like accuracy (2 cm, 0.5 deg), well above the ground truth's (~2 mm, ~1 mrad): the
    # NEES then judges the estimate, not the ground truth's own calibration (test above)
    cov = random_covariances(t.size, rng, 2e-2, 8e-3)
    est = _estimate_from_truth(sim, t, cov, rng)
    r = evaluate(cgt, est, align="none", max_dt=0.5)
    a = r.association
    assert a.ground_truth == "continuous" and a.n_outside > 0
    assert len(a) + sum(a.dropped.values()) == t.size
    for n in (r.nees.position, r.nees.pose):
        assert n.consistent, n.to_dict()
        assert 0.85 < n.mean / n.dof < 1.15
    assert "estimate" in r.nees.covariance
    # biased by 4 cm along x: inconsistent (and visible in the APE)
    biased = PoseTrajectory(est.t, est.position + [0.04, 0.0, 0.0], est.quat_xyzw, est.cov)
    rb = evaluate(cgt, biased, align="none", max_dt=0.5)
    assert not rb.nees.position.consistent and not rb.nees.pose.consistent
    # over-confident: claims a covariance 9 times too small
    over = PoseTrajectory(est.t, est.position, est.quat_xyzw, est.cov / 9.0)
    ro = evaluate(cgt, over, align="none", max_dt=0.5)
    assert not ro.nees.position.consistent and not ro.nees.pose.consistent
    assert ro.nees.pose.mean / 6 > 4


# ----------------------------------------------------------------------------- (d) CLI, offset


@pytest.fixture(scope="module")
def offset_estimate(linear_run, tmp_path_factory):
    """A 10 Hz estimate whose clock is 0.3 s behind the ground truth's, with covariances."""
    sim, result, out = linear_run
    d = tmp_path_factory.mktemp("cgt_offset")
    gt = result.groundtruth
    rng = np.random.default_rng(42)
    t_true = np.arange(gt.t[0] + 1.0, gt.t[-1] - 1.0, 0.1) + rng.uniform(0.0, 0.1)
    cov = random_covariances(t_true.size, rng, 1e-2, 8e-3)
    est = _estimate_from_truth(sim, t_true, cov, rng)
    est = PoseTrajectory(t_true - 0.3, est.position, est.quat_xyzw, est.cov)
    write_tum(d / "est.tum", est)
    write_covariance_csv(d / "est_cov.csv", est)
    return d, est


def _cli_json(*args: str) -> dict:
    r = runner.invoke(_app(), ["evaluate", *args, "--json"])
    assert r.exit_code == 0, (r.output, r.exception)
    return json.loads(r.stdout)


def test_cli_t_offset_fixes_a_clock_offset(linear_run, offset_estimate):
    sim, result, out = linear_run
    d, est = offset_estimate
    base = [str(out), str(d / "est.tum"), "--est-cov", str(d / "est_cov.csv"), "--align", "none"]
    wrong = _cli_json(*base)
    fixed = _cli_json(*base, "--t-offset", "0.3")
    alias = _cli_json(*base, "--time-offset", "0.3")
    assert fixed["association"]["ground_truth"] == "continuous"
    assert fixed["association"]["ground_truth_detail"]["engine"] == "linear"
    assert fixed["association"]["time_offset_s"] == 0.3
    assert alias["ape"] == fixed["ape"]
    # 0.3 s at up to 2 m/s: decimetres of error and an inconsistent NEES without the offset
    assert wrong["ape"]["translation_m"]["rmse"] > 0.1
    assert wrong["nees"]["pose"]["consistent"] is False
    # with the offset, the APE is the estimate's own noise: rms sqrt(mean tr Sigma_pos)
    expected = np.sqrt(np.mean(np.trace(est.cov[:, :3, :3], axis1=1, axis2=2)))
    assert fixed["ape"]["translation_m"]["rmse"] == pytest.approx(expected, rel=0.1)
    assert fixed["nees"]["position"]["consistent"] is True
    assert fixed["nees"]["pose"]["consistent"] is True
    assert 0.8 < fixed["nees"]["pose"]["mean"] / 6 < 1.2
    a = fixed["association"]
    assert a["n_associated"] + a["n_dropped"] == a["n_estimate"] == len(est)
    assert sum(a["dropped_by_reason"].values()) == a["n_dropped"]
    # the readable table says what was dropped and why
    r = runner.invoke(_app(), ["evaluate", *base, "--t-offset", "0.3", "--max-gap", "0.25"])
    assert r.exit_code == 0, r.output
    text = " ".join(r.output.split())
    assert "continuous ground truth" in text and "far from measurement" in text


def test_cli_discrete_fallback_and_modes(linear_run, offset_estimate, tmp_path):
    sim, result, out = linear_run
    d, _ = offset_estimate
    est = [str(d / "est.tum"), "--align", "none", "--t-offset", "0.3"]
    disc = _cli_json(str(out), *est, "--gt-mode", "discrete")
    assert disc["association"]["ground_truth"] == "discrete"
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(out / "groundtruth_covariance.csv", bare)
    assert _cli_json(str(bare), *est)["association"]["ground_truth"] == "discrete"
    r = runner.invoke(_app(), ["evaluate", str(bare), *est, "--gt-mode", "continuous"])
    assert r.stderr.startswith("error: ") and "measurements/" in r.stderr
    r = runner.invoke(_app(), ["evaluate", str(out), *est, "--gt-engine", "exact"])
    assert r.exit_code == 2 and "--gt-engine" in r.output
    mc = _cli_json(str(out), *est, "--gt-engine", "mc")
    assert mc["association"]["ground_truth_detail"]["engine"] == "mc"
    assert mc["ape"]["translation_m"]["rmse"] == pytest.approx(
        _cli_json(str(out), *est)["ape"]["translation_m"]["rmse"], rel=1e-9
    )


# ----------------------------------------------------------------------------- (e) gaps


def test_times_outside_in_gaps_and_gated_are_dropped_with_their_reason(linear_run, tmp_path):
    sim, result, out = linear_run
    summary = json.loads((out / "summary.json").read_text())
    iv = np.asarray(summary["intervals_s"])
    assert iv.shape[0] >= 2  # the simulation has common dropouts: gaps between intervals
    rng = np.random.default_rng(43)
    t = np.arange(iv[0, 0] - 5.0, iv[-1, 1] + 5.0, 0.1) + rng.uniform(0.0, 0.1)
    est = _estimate_from_truth(sim, t, random_covariances(t.size, rng, 5e-3, 2e-3), rng)
    write_tum(tmp_path / "est.tum", est)
    # independent bookkeeping from the files
    outside = (t < iv[0, 0]) | (t > iv[-1, 1])
    in_iv = np.any((t[:, None] >= iv[:, 0]) & (t[:, None] <= iv[:, 1]), axis=1)
    between = ~outside & ~in_iv
    meas = [
        np.loadtxt(out / "measurements" / f"prism{p}.csv", delimiter=",", skiprows=1)[:, 0]
        for p in ("1", "2", "3")
    ]
    nearest = np.max([np.min(np.abs(t[:, None] - m[None, :]), axis=1) for m in meas], axis=0)
    far = ~outside & in_iv & (nearest > 0.25)
    assert outside.sum() > 0 and between.sum() > 0 and far.sum() > 0
    j = _cli_json(str(out), str(tmp_path / "est.tum"), "--align", "none", "--max-gap", "0.25")
    a = j["association"]
    assert a["dropped_by_reason"].get("outside_ground_truth") == int(outside.sum())
    assert a["dropped_by_reason"].get("between_intervals") == int(between.sum())
    assert a["dropped_by_reason"].get("far_from_measurement") == int(far.sum())
    assert a["n_outside_ground_truth"] == int(outside.sum())
    assert a["n_in_gaps"] == int(between.sum() + far.sum())
    assert a["n_associated"] == int(t.size - outside.sum() - between.sum() - far.sum())
    assert set(a["dropped_by_reason"]) <= set(DROP_REASONS)
    # the run's gates apply: a run whose uncertainty gate is the median pose uncertainty
    gated = tmp_path / "gated"
    shutil.copytree(out, gated)
    cgt = read_ground_truth(out)
    s = cgt.query_poses(t, max_gap_s=0.25)
    unc = position_uncertainty(s.cov[s.valid])
    gate = float(np.median(unc))
    summary["parameters"]["uncertainty_gate_m"] = gate
    (gated / "summary.json").write_text(json.dumps(summary))
    jg = _cli_json(str(gated), str(tmp_path / "est.tum"), "--align", "none", "--max-gap", "0.25")
    ag = jg["association"]
    assert ag["dropped_by_reason"]["gate_uncertainty"] == int(np.sum(unc > gate)) > 0
    assert ag["n_associated"] == a["n_associated"] - int(np.sum(unc > gate))
    assert ag["ground_truth_detail"]["uncertainty_gate_m"] == gate


def test_errors_name_the_problem(linear_run, tmp_path):
    sim, result, out = linear_run
    cgt = read_ground_truth(out)
    gt = result.groundtruth
    late = PoseTrajectory(gt.t + 1e5, gt.position, gt.quat_xyzw)
    with pytest.raises(InputError, match="No time overlap"):
        evaluate(cgt, late)
    # every time in the gaps between the intervals
    iv = np.asarray(cgt.intervals)
    t_gap = np.linspace(iv[0, 1] + 0.1, iv[1, 0] - 0.1, 5)
    p, q = sim.truth_at(t_gap)
    with pytest.raises(InputError, match="between intervals"):
        evaluate(cgt, PoseTrajectory(t_gap, p, q))
    with pytest.raises(InputError, match="engine"):
        read_ground_truth(out, engine="exact")
    broken = tmp_path / "broken"
    shutil.copytree(out, broken)
    summary = json.loads((broken / "summary.json").read_text())
    del summary["prisms"]["2"]["qc_m2_s3"]
    (broken / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(InputError, match=r"qc_m2_s3 for prism 2.*summary\.json|summary\.json.*2"):
        read_ground_truth(broken)
    with pytest.raises(InputError, match="measurements/"):
        read_ground_truth(tmp_path)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda s: [1, 2], "expected a JSON object"),
        (lambda s: {**s, "parameters": [1]}, "'parameters': expected a JSON object"),
        (lambda s: {**s, "parameters": {**s["parameters"], "max_gap_s": "abc"}},
         "parameters.max_gap_s: expected a positive number"),
        (lambda s: {**s, "parameters": {**s["parameters"], "max_gap_s": -1}},
         "parameters.max_gap_s: expected a positive number"),
        (lambda s: {**s, "reference": [1]}, "'reference': expected a JSON object"),
        (lambda s: {**s, "gates": "x"}, "'gates': expected a JSON object"),
        (lambda s: {**s, "calibration": [1]}, "'calibration': expected a JSON object"),
    ],
)
def test_malformed_summary_is_an_input_error_naming_it(linear_run, tmp_path, change, match):
    """A summary.json edited by hand: one InputError naming the file (CLI exit status 1), never
    an AttributeError or ValueError from deep inside."""
    _, _, out = linear_run
    broken = tmp_path / "broken"
    shutil.copytree(out, broken)
    summary = json.loads((broken / "summary.json").read_text())
    (broken / "summary.json").write_text(json.dumps(change(summary)))
    with pytest.raises(InputError, match=match) as exc:
        read_ground_truth(broken)
    assert exc.value.path == str(broken / "summary.json")
    r = runner.invoke(_app(), ["evaluate", str(broken), str(out / "groundtruth.tum")])
    assert r.stderr.startswith("error: ")


@pytest.mark.slow
def test_rpe_uses_the_correlation_between_ground_truth_poses(tmp_path):
    """The two ends of a relative pose share most of the ground truth's error (calibration,
    clock offsets, weather, reference, the GP's smoothing): with the cross-covariance the
    continuous ground truth computes, an exact estimate's RPE NEES is near its dof; treating the
    two poses as independent overstates the relative covariance (NEES well below the dof)."""
    import warnings

    from scipy.stats import chi2

    from rtsgt.evaluation import evaluate
    from rtsgt.io.deployment import load_deployment
    from rtsgt.io.run_dir import write_run
    from rtsgt.pipeline import run_pipeline
    from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
    from rtsgt.types import PoseTrajectory

    class Independent:  # the same ground truth, without its cross-covariances
        def __init__(self, g):
            self.g = g

        def query_poses(self, *args, **kwargs):
            return self.g.query_poses(*args, **kwargs)

    rel = {"with": [], "independent": []}
    for seed in range(1000, 1012):
        sim = simulate_deployment(SimulationConfig(duration_s=120.0), np.random.default_rng(seed))
        data, opts = load_deployment(write_deployment(sim, tmp_path / f"dep{seed}"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = run_pipeline(data, opts.updated(engine="linear", seed=seed))
        cgt = read_ground_truth(write_run(result, tmp_path / f"run{seed}"))
        t = np.arange(result.groundtruth.t[0], result.groundtruth.t[-1], 0.1)
        est = PoseTrajectory(t, *sim.truth_at(t))  # exact: the RPE error is the GT's own
        for name, g in (("with", cgt), ("independent", Independent(cgt))):
            res = evaluate(g, est, align="none", delta=1.0, delta_unit="m", max_dt=3.0)
            rel[name].append(res.nees.relative_position.values)
    with_ = np.concatenate(rel["with"])
    indep = np.concatenate(rel["independent"])
    assert with_.size > 1000
    assert abs(with_.mean() / 3.0 - 1.0) < 0.25, with_.mean() / 3.0
    assert abs(np.mean(with_ <= chi2.ppf(0.95, 3)) - 0.95) < 0.04
    assert indep.mean() < 0.85 * with_.mean()


def test_pose_cross_covariance_at_equal_times_is_the_runs_linear_covariance(linear_run):
    """The first-order cross-covariance model, at tau_a == tau_b, rebuilds the marginal pose
    covariance the run computed with the linear engine from the per-source covariances: every
    shared term (GP, clock, atmosphere, calibration coupling, reference) in its right place."""
    _, result, out = linear_run
    cgt = read_ground_truth(out)
    t = result.groundtruth.t[50:70]
    s = cgt.query_poses(t)
    C = cgt.cross_covariance(t, t)
    rel = np.linalg.norm(C - s.cov, axis=(1, 2)) / np.linalg.norm(s.cov, axis=(1, 2))
    assert np.max(rel) < 0.01, rel
    P_a, P_b, C_ab = cgt.pair_covariances(t[:-5], t[5:])
    np.testing.assert_allclose(P_a, C[:-5], rtol=1e-10, atol=0)
    np.testing.assert_allclose(C_ab, cgt.cross_covariance(t[:-5], t[5:]), rtol=1e-10, atol=0)
    np.testing.assert_allclose(C_ab, np.swapaxes(cgt.cross_covariance(t[5:], t[:-5]), 1, 2),
                               rtol=1e-10, atol=1e-30)
