"""The joint engine in a run (``[pose] engine = "joint"``, docs/pipeline.md#the-joint-engine):
the run completes and writes every output, its poses are the joint engine's and within their
covariance against the simulation's truth, ``summary.json`` has the ``joint`` section, the
checks that are not independent of the fit say so, ``rtsgt evaluate`` reads the run, and the
options refuse what they do not know in one line."""

from __future__ import annotations

import json
import warnings
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from rtsgt.app.evaluate import load_ground_truth
from rtsgt.cli.main import app
from rtsgt.errors import InputError
from rtsgt.geometry.so3 import quat_xyzw_to_matrix
from rtsgt.geometry.transform import perturbation
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import read_run, write_run
from rtsgt.joint.axes import AXES_SIGMA
from rtsgt.joint.gm import TAU_RANGE_S
from rtsgt.joint.qc import VCE_MAX_ITER, VCE_TOL
from rtsgt.measurement.units import MGON
from rtsgt.options import RUN_ENGINES, RunOptions
from rtsgt.pipeline import run_pipeline
from rtsgt.report.analysis import analyze
from rtsgt.report.html import render_report
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.stages.checks import JOINT_INTER_PRISM
from rtsgt.types import PoseTrajectory

runner = CliRunner()
SEEDS = (11, 12)


def _deployment(tmp, seed):
    """A 60 s simulated deployment of the default simulator (survey noise, the stations'
    clock offsets: the joint engine estimates the prisms and the offsets)."""
    sim = simulate_deployment(SimulationConfig(duration_s=60.0), np.random.default_rng(seed))
    return sim, write_deployment(sim, tmp / f"dep{seed}")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("joint_pipeline")
    out = []
    for seed in SEEDS:
        sim, folder = _deployment(tmp, seed)
        data, opts = load_deployment(folder)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the checks' warnings: tested elsewhere
            record = run_pipeline(data, opts.updated(seed=seed, engine="joint"))
        out.append((sim, folder, record, write_run(record, tmp / f"run{seed}")))
    return out


def _nees(sim, gt: PoseTrajectory) -> np.ndarray:
    p, q = sim.truth_at(gt.t)
    e = perturbation(quat_xyzw_to_matrix(q), p, quat_xyzw_to_matrix(gt.quat_xyzw), gt.position)
    return np.einsum("ki,kij,kj->k", e, np.linalg.inv(gt.cov), e)


def test_a_joint_run_keeps_the_joint_poses_within_their_covariance(runs):
    """Pooled over two 60 s runs the joint poses' NEES/dof against the truth is near 1
    (the default simulator: measured 1.04 and 1.83, the shared errors drawn once per
    deployment; 16 such deployments: 0.96 without the clock states, docs/pipeline.md)."""
    nees = []
    for sim, _, record, _ in runs:
        c = record.computation
        assert c.estimate.engine == "joint" and c.keep.all(), c.estimate.engine
        assert len(record.groundtruth) == record.prisms_t.size > 150
        nees.append(_nees(sim, record.groundtruth))
    nees = np.concatenate(nees)
    assert 0.7 < nees.mean() / 6 < 1.6, nees.mean() / 6
    assert 0.85 < np.mean(nees < 12.59) <= 1.0


def test_the_summary_has_the_joint_section_and_the_checks_say_what_they_judge(runs):
    sim, _, record, path = runs[0]
    doc = json.loads((path / "summary.json").read_text())
    assert doc["parameters"]["engine"] == "joint" and doc["parameters"]["clocks"] is True
    j = doc["joint"]
    assert j["converged"] and 0.5 < j["chi2_per_dof"] < 1.5, j
    # the variance components' loop: each part's last change, converged where all are small,
    # and a run whose loop stopped short says so in its warnings
    changes = j["qc_last_change"]
    assert {"qc", "white"} <= set(changes) <= {"qc", "white", "chains", "rocking"}, changes
    assert j["qc_converged"] == (max(changes.values()) < VCE_TOL), changes
    assert 1 <= j["qc_iterations"] <= VCE_MAX_ITER
    said = [w for w in record.warnings if "variance components did not converge" in w]
    assert len(said) == (not j["qc_converged"]), record.warnings
    assert j["poses"] == len(record.groundtruth) and j["knots"] <= j["measurements"]
    assert set(j["stations"]) == set(record.stations)
    held = [s for s, v in j["stations"].items() if v["held"]]
    assert held == [j["clock_reference"]]  # the reference station: held, no clock
    assert set(j["clocks"]) == set(record.stations) - set(held)
    # the white noise at each station's median range: that range is the median of the
    # station's tracked distances (within 2 %), its sigma the components' at it (mgon, mm),
    # with a sigma where the data determine a component
    nf = record.computation.joint.noise
    v, sd = nf.median_variance()
    for i, sid in enumerate(nf.stations):
        o = next(o for o in sim.observations if o.station == sid)
        d = np.median(o.d[np.isin(o.t, record.computation.tracks[o.prism].t)])
        for c, ch in enumerate(("hz", "v", "d")):
            w = j["noise"][sid][ch]
            assert abs(w["median_range_m"] / d - 1.0) < 0.02, (w, d)
            unit = 1e-3 if ch == "d" else MGON
            assert w["sigma_at_median"] == pytest.approx(np.sqrt(v[i, c]) / unit, rel=1e-12)
            assert (w["sigma_at_median_sigma"] > 0) == any(w["determined"]), w
    # each station's constant clock offset (the simulation's is t_true - t_recorded, the
    # engine's t_recorded - t_true) against the reference's within 3 sigma (the two
    # sigmas added: their errors share the common offset, so this bounds it); no drift
    # simulated: the clock states (the drift from their first knot) within 3 sigma of 0
    sync, ref = j["time_sync"], j["clock_reference"]
    assert set(sync) == set(record.stations)
    for sid, v in sync.items():
        truth_ms = -1e3 * (sim.truth.clock_offset_s[sid] - sim.truth.clock_offset_s[ref])
        est_ms = v["offset_ms"] - sync[ref]["offset_ms"]
        assert abs(est_ms - truth_ms) < 3 * (v["sigma_ms"] + sync[ref]["sigma_ms"]), (sid, v)
        assert 0.05 < v["sigma_ms"] < 1.5, v
    for sid, v in j["clocks"].items():  # no drift simulated: start and end alike
        truth_ms = -1e3 * (sim.truth.clock_offset_s[sid] - sim.truth.clock_offset_s[ref])
        assert abs(v["end_ms"] - truth_ms) < 3 * v["median_sigma_ms"] + 1e-3, (sid, v)
    assert set(j["prisms"]) == set(record.prism_ids)
    for v in j["prisms"].values():  # the default simulator moves no prism
        assert not v["moved"] and v["moved_weight"] == 0 and v["cost_above_found"] is None, v
        # the largest eigenvalue of a 3x3 covariance: between its largest diagonal and trace
        sd = np.array(v["sigma_mm"])
        assert sd.max() - 1e-9 <= v["largest_sigma_mm"] <= np.sqrt(sd @ sd) + 1e-9, v
    # three prisms: each one's blind move is across their plane (the same direction for
    # all), turning the poses by 1 / h, h its distance from the others' line (the closed
    # form on the survey the run used, in its body frame)
    body = record.computation.joint.prisms.survey
    n = np.cross(body[1] - body[0], body[2] - body[0])
    for i, v in enumerate(j["prisms"].values()):  # the survey's order, the simulator's
        (g,), (turn,) = v["blind_directions"], v["blind_turn_mrad_per_mm"]
        assert abs(abs(np.dot(g, n)) / np.linalg.norm(n) - 1.0) < 1e-9, g
        a, b = body[[k for k in range(3) if k != i]]
        u = (b - a) / np.linalg.norm(b - a)
        h = np.linalg.norm((body[i] - a) - ((body[i] - a) @ u) * u)
        assert turn == pytest.approx(1.0 / h, rel=1e-9), (turn, h)  # rad/m = mrad/mm
    assert not [f for f in doc["verdict"]["findings"] if f["check"] == "moved prism"]
    (blind,) = [f for f in doc["verdict"]["findings"] if f["check"] == "what no station sees"]
    assert blind["severity"] == 0 and "prisms 1, 2 and 3 across their plane" in blind["text"]
    # the prisms' deviation: per prism (order, term, component); a held order is 0 with its
    # prior's 0.1 um, an estimated one has a sigma under its prior's 2 mm / sqrt(6)
    dev = j["deviation"]
    assert dev["orders"] == [3, 6, 12] and set(dev["prisms"]) == set(record.prism_ids)
    for v in dev["prisms"].values():
        coef, sd = np.array(v["coefficients_mm"]), np.array(v["sigma_mm"])
        assert coef.shape == sd.shape == (3, 2, 3) and len(v["held"]) == 3
        held = np.array(v["held"])
        assert np.all(np.abs(coef[held]) < 1e-6) and np.all(sd[held] < 1e-3), v
        assert np.all(sd[~held] < 2.0 / np.sqrt(6) + 1e-9), v
        np.testing.assert_allclose(np.array(v["amplitude_mm"]),
                                   np.hypot(coef[:, 0], coef[:, 1]), rtol=1e-12)
    # the Gauss-Markov noise per station and channel: a determined chain has its sigmas, an
    # undetermined one its start and none; tau inside the searched range
    gmj = j["gauss_markov"]
    assert set(gmj) == set(record.stations)
    for per in gmj.values():
        assert set(per) == {"hz", "v", "d"}
        for v in per.values():
            assert TAU_RANGE_S[0] <= v["tau_s"] <= TAU_RANGE_S[1] and v["sigma"] > 0, v
            assert (v["sigma_sigma"] > 0 and v["tau_sigma_s"] > 0) == v["determined"], v
    # the motion prior's axes (docs/joint.md#the-motion-axes): informed by the data beyond
    # their prior, in its sigmas as stated
    ax = j["motion_axes"]
    assert ax["axes"] == ["rx", "ry", "rz"], ax
    assert all(0 < s < 1e3 * AXES_SIGMA for s in ax["sigma_mrad"]), ax
    np.testing.assert_allclose(np.array(ax["prior_sigmas"]) * 1e3 * AXES_SIGMA,
                               ax["rotation_mrad"], rtol=1e-12)
    for v in j["stations"].values():
        assert v["held"] or np.all(np.abs(v["shift_sigmas"]) < 4), v
    assert j["kappa_sigma_ppm"] > 0 and "standing" in j["qc"]
    checks = doc["self_checks"]
    assert checks["inter_prism_distances"] == {"skipped": JOINT_INTER_PRISM}
    assert "per-prism" in checks["inter_prism_structure"]["note"]
    assert "joint" in doc["timings_s"]
    # the checks the joint engine adds: the raw measurements in blocks, the static stretches'
    # relative poses from its own covariance between two times
    raw = checks["raw_block_cv"]
    assert set(raw["stations"]) == set(record.stations)
    assert raw["overall"]["blocks"] >= 15 and 0.5 < raw["overall"]["nees_per_dof"] < 2.0, raw
    assert set(raw["channels"]) == {"hz", "v", "d"}
    lags = checks["static_relative"]["lags"]
    assert lags["1"]["pairs"] > 0 and 0.1 < lags["1"]["nees_per_dof"] < 3.0, lags
    for name in ("groundtruth.tum", "groundtruth_covariance.csv", "reference.csv"):
        assert (path / name).is_file(), name


def test_the_run_is_read_back_and_evaluated_on_its_own_poses(runs):
    """``rtsgt evaluate``'s ground truth of a joint run is the poses it stored (the joint
    engine is not recomputed at other times); the record reads back with its section."""
    sim, _, record, path = runs[0]
    back = read_run(path)
    assert back.options.joint and back.joint == json.loads(json.dumps(record.joint))
    gt = load_ground_truth(path)
    assert isinstance(gt, PoseTrajectory)
    np.testing.assert_allclose(gt.t, record.groundtruth.t, atol=1e-6)
    np.testing.assert_allclose(gt.cov, record.groundtruth.cov, rtol=1e-6, atol=1e-15)
    est = path.parent / "truth.tum"
    p, q = sim.truth_at(gt.t)
    est.write_text("".join(f"{t:.6f} {x[0]} {x[1]} {x[2]} {r[0]} {r[1]} {r[2]} {r[3]}\n"
                           for t, x, r in zip(gt.t, p, q, strict=True)))
    res = runner.invoke(app, ["evaluate", str(path), str(est), "--json", "--align", "none"])
    assert res.exit_code == 0, res.output
    nees = json.loads(res.stdout)["nees"]
    # the run's own poses and covariance against the truth (the honesty of a 60 s run: the
    # runs' test above)
    assert nees["pose"]["n"] == gt.t.size, nees
    assert nees["pose"]["mean"] == pytest.approx(_nees(sim, gt).mean(), rel=1e-3), nees


def test_the_shared_split_adds_up_to_the_pose_covariance(runs):
    """``groundtruth_shared.csv`` is the joint engine's split (its global parameters'
    columns); its total is the poses' covariance, written and read back."""
    _, _, record, path = runs[0]
    split = record.groundtruth_split
    assert split is not None and any(n.startswith("calibration_station") for n in split.names)
    np.testing.assert_array_equal(split.t, record.groundtruth.t)
    scale = np.max(np.abs(record.groundtruth.cov))
    np.testing.assert_allclose(split.total_cov, record.groundtruth.cov, rtol=0,
                               atol=1e-9 * scale)
    back = read_run(path).groundtruth_split
    assert back is not None and back.names == split.names
    np.testing.assert_allclose(back.total_cov, split.total_cov, rtol=1e-6, atol=1e-6 * scale)


def test_an_unknown_engine_or_clock_switch_is_one_clear_line(runs, tmp_path):
    _, folder, _, _ = runs[0]
    assert RUN_ENGINES[-1] == "joint"
    res = runner.invoke(app, ["run", str(folder), "--engine", "jont",
                              "--out", str(tmp_path / "out")])
    assert res.exit_code != 0 and not (tmp_path / "out").exists()
    lines = [x for x in res.output.splitlines() if "jont" in x]
    assert len(lines) == 1 and "joint" in lines[0], res.output
    text = folder.read_text().replace("[pose]\n", '[pose]\nclocks = "yes"\n')
    bad = folder.parent / "bad_clocks.toml"
    bad.write_text(text)
    res = runner.invoke(app, ["run", str(bad), "--out", str(tmp_path / "out2")])
    assert res.exit_code != 0 and not (tmp_path / "out2").exists()
    assert "[pose] clocks must be bool, got 'yes'" in res.output, res.output
    with pytest.raises(InputError, match="clocks true or false"):
        RunOptions().updated(clocks=1)


def test_the_papers_profile_and_the_default_engine_are_untouched():
    """The paper's profile keeps its engine; a per-prism run's ``summary.json`` parameters
    have no ``clocks`` (their outputs stay bit-identical, docs/pipeline.md)."""
    paper = RunOptions().updated(profile="paper")
    assert paper.pose.engine == "mc" and not paper.joint and paper.prism_engine == "mc"
    joint = RunOptions().updated(profile="paper", engine="joint")
    assert joint.prism_engine == "linear" and joint.interpolation == paper.interpolation
    assert replace(joint.pose, engine="mc") == paper.pose


def test_calibration_times_are_the_gcp_shots_within_the_hour_before_the_tracking():
    """A GCP calibration's station settles from the median time of its valid shots
    (docs/joint.md#settling-tripods) where that is at most an hour before the first
    measurement; a stamp 100 days old (another clock), a station without valid shots and a
    dynamic calibration give none."""
    from types import SimpleNamespace

    from rtsgt.stages.joint import MAX_CALIBRATION_AGE_S, calibration_times
    from rtsgt.types import GcpShots

    t0 = 1.668e9
    st = np.array(["1", "1", "1", "2", "2", "3"])
    t = np.array([t0 - 1800.0, t0 - 1700.0, t0 - 1200.0, t0 - 8.64e6, t0 - 8.64e6, t0 - 60.0])
    z = np.ones(6)
    shots = GcpShots(st, np.array(list("abcabc")), z, z, z, t, np.array([0, 0, 0, 0, 0, 1]))
    cal = SimpleNamespace(method="gcp", transforms={"1": None, "2": None, "3": None})
    assert calibration_times(shots, cal, t0) == {"1": pytest.approx(t0 - 1700.0)}
    late = replace(shots, t=t + 8.64e6 - 0.5 * MAX_CALIBRATION_AGE_S)
    assert set(calibration_times(late, cal, t0)) == {"1", "2"}
    assert calibration_times(shots, SimpleNamespace(method="dynamic", transforms={}), t0) == {}


def test_the_prisms_stability_turns_the_poses_as_the_closed_form_says(runs):
    """``[reference] prism_stability_mm``: a prism may have moved along its blind direction
    (docs/joint.md#what-no-station-sees), carried as a consider parameter. The poses are
    the same; their rotation covariance (body frame) grows by the closed form's: the tilts
    about the prisms' plane's in-plane axes of the rigid motion (tilt u1, u2, shift along n)
    that moves each prism by e_j along n, ``cov = sigma^2 (A^T A)^-1``, ``A_j = ((p_j x n)
    . u1, (p_j x n) . u2, 1)``, nothing about n; the growth is shared by every pose. The
    summary records it; a per-prism engine says it does not carry it."""
    sim, folder, base, _ = runs[0]
    data, opts = load_deployment(folder)
    data = replace(data, reference=replace(data.reference, stability=1e-3))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = run_pipeline(data, opts.updated(seed=SEEDS[0], engine="joint"))
        linear = run_pipeline(data, opts.updated(seed=SEEDS[0], engine="linear"))
    assert rec.joint["prism_stability_mm"] == pytest.approx(1.0)
    assert base.joint["prism_stability_mm"] == 0.0
    assert any("prism_stability_mm: only the joint engine" in w for w in linear.warnings)
    assert not any("prism_stability_mm" in w for w in rec.warnings)

    def body_rotation_cov(gt):
        R = quat_xyzw_to_matrix(gt.quat_xyzw)
        return np.swapaxes(R, 1, 2) @ gt.cov[:, 3:, 3:] @ R

    grown = np.mean(body_rotation_cov(rec.groundtruth) - body_rotation_cov(base.groundtruth),
                    axis=0)
    p = data.reference.xyz
    n = np.cross(p[1] - p[0], p[2] - p[0])
    n /= np.linalg.norm(n)
    U = np.linalg.svd(np.eye(3) - np.outer(n, n))[0][:, :2]
    A = np.column_stack([np.cross(p, n) @ U, np.ones(3)])
    closed = U @ (1e-6 * np.linalg.inv(A.T @ A))[:2, :2] @ U.T
    np.testing.assert_allclose(grown, closed, atol=1e-3 * np.trace(closed))
    np.testing.assert_allclose(rec.groundtruth.position, base.groundtruth.position, atol=1e-12)
    # the growth is shared: the split's shared part grows by it, the varying part not
    sb, sr = base.groundtruth_split, rec.groundtruth_split
    assert sr.names[-3:] == ("blind_1", "blind_2", "blind_3"), sr.names
    np.testing.assert_allclose(sr.varying_cov, sb.varying_cov, atol=1e-15)
    np.testing.assert_allclose(sr.shared_cov + sr.varying_cov, rec.groundtruth.cov, rtol=1e-6,
                               atol=1e-12)


def test_the_report_shows_the_joint_estimates_with_their_sigmas(runs):
    """The report's run section has the joint engine's estimates from summary.json, each with
    its sigma: the stations' shifts, the clocks, the prisms, the noise and the motion axes."""
    _, _, _, path = runs[0]
    data = read_run(path)
    page, _ = render_report(data, analyze(data), figures={})
    j = json.loads((path / "summary.json").read_text())["joint"]

    def table(name):
        part = page[page.index(f"<table id='{name}'"):]
        return part[:part.index("</table>")]

    loop = table("run-joint")
    assert (f"{j['qc_iterations']} updates, "
            + ("converged" if j["qc_converged"] else "not converged")) in loop, loop
    stations = table("run-joint-stations")
    for sid, v in j["stations"].items():
        row = stations[stations.index(f"<td class='s'>{sid}</td>"):]
        row = row[:row.index("</tr>")]
        assert ("held" in row) == v["held"], row
        if not v["held"]:
            assert ", ".join(f"{x:.2f}" for x in v["shift_mm"]) in row, (row, v)
    clocks = table("run-joint-clocks")
    for v in j["time_sync"].values():
        assert f"{v['offset_ms']:.3g} ± {v['sigma_ms']:.2g}" in clocks, (clocks, v)
    prisms = table("run-joint-prisms")
    for v in j["prisms"].values():
        assert f"{v['largest_sigma_mm']:.3g}" in prisms and ">kept<" in prisms
        blind = ", ".join(f"{x:.2f}" for x in v["blind_directions"][0])
        assert f"({blind}): {v['blind_turn_mrad_per_mm'][0]:.3g} mrad per mm" in prisms
    noise = table("run-joint-noise")
    rows = noise.split("<tr>")[1:]
    for sid, per in j["noise"].items():
        for ch, w in per.items():
            row = next(r for r in rows if f"<td class='s'>{sid}</td><td class='s'>{ch}</td>" in r)
            assert f"at {w['median_range_m']:.3g} m" in row and f"σ {w['sigma_at_median']:.3g}" in row, row
            # a factor pooled over the stations says so, one the data left says it is the prior
            assert ("pooled over the stations" in row) == w["pooled"], row
            assert ("(the prior, kept)" in row) == (not w["determined"][0]), row
            assert not w["pooled"] or w["determined"][0], w
    for sid, per in j["gauss_markov"].items():
        for ch, v in per.items():
            row = next(r for r in rows if f"<td class='s'>{sid}</td><td class='s'>{ch}</td>" in r)
            text = (f"τ {v['tau_s']:.3g} ± {v['tau_sigma_s']:.2g} s" if v["determined"]
                    else "not determined, not carried")
            assert text in row, (text, row)
    axes = table("run-joint-axes")
    for r, sd in zip(j["motion_axes"]["rotation_mrad"], j["motion_axes"]["sigma_mrad"],
                     strict=True):
        assert f"{r:.3g} ± {sd:.2g}" in axes, axes
