"""``rtsgt plan``: the predicted pose uncertainty of a layout, against what a run reports.

The acceptance (issue 12, item 4): on a simulated deployment, the plan of its layout predicts at
the poses the robot took the pose sigma the run reports there (the linear engine, the same
noise model) within a factor 1.5, at the median and for 90 % of the poses; the GP's Qc comes
from an earlier deployment of the same (simulated) robot, as a user would have it. Then the
pieces in closed form: the GP's factor against a three-axis fit and its smooth limit, the
measurement covariances against the polar formulas of another module, the calibration of a
layout on paper against the run's, the advice's fractions for known geometries; and the
command: its files, its refusal to overwrite, the comparison of two plans.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from _paths import EXAMPLE_TOML
from rtsgt.calibration.shots import polar_point_covariance
from rtsgt.cli.main import app
from rtsgt.cli.plan import compute_plan
from rtsgt.errors import RtsgtWarning
from rtsgt.interpolation.gp import fit_track
from rtsgt.io.deployment import load_deployment
from rtsgt.io.output_dir import MANIFEST
from rtsgt.io.run_dir import write_run
from rtsgt.measurement.instruments import TRIMBLE_S7
from rtsgt.measurement.polar import cartesian_to_polar
from rtsgt.options import RunOptions
from rtsgt.pipeline import run_pipeline
from rtsgt.planning import (
    PlannedStation,
    RobotMotion,
    gp_factor,
    gp_posterior_covariance,
    layout_from_deployment,
    layout_from_positions,
    plan_area,
    qc_from_run,
    waypoint_path,
)
from rtsgt.planning.gp_factor import LOG10_KAPPA, PHASES, SMOOTH_LIMIT
from rtsgt.planning.plan import inside_polygon
from rtsgt.planning.predict import measurement_track
from rtsgt.pose import ReferencePoints
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment

runner = CliRunner()
FACTOR = 1.5  # the acceptance


def _run(tmp: Path, seed: int, duration: float):
    sim = simulate_deployment(SimulationConfig(duration_s=duration), np.random.default_rng(seed))
    cfg = write_deployment(sim, tmp / f"dep{seed}")
    data, opts = load_deployment(cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # markers seen by one station, by design
        rec = run_pipeline(data, opts.updated(seed=0, engine="linear"))
    return cfg, rec, write_run(rec, tmp / f"run{seed}")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """An earlier deployment of the robot (its Qc), and the deployment to predict."""
    tmp = tmp_path_factory.mktemp("plan")
    return _run(tmp, 7001, 150.0), _run(tmp, 7002, 300.0)


def _ratio(result, rec) -> np.ndarray:
    run_sigma = np.sqrt(np.trace(rec.groundtruth.cov[:, :3, :3], axis1=1, axis2=2))
    assert result.points.shape[0] == run_sigma.size
    return result.sigma_median_m / run_sigma


def test_plan_predicts_the_runs_pose_sigma_where_the_robot_drove(runs):
    """The acceptance, through the command's own path: the deployment TOML as the layout, the
    run's poses as the path (its groundtruth_covariance.csv), Qc from the earlier run."""
    (_, _, earlier), (cfg, rec, run_dir) = runs
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RtsgtWarning)  # the advice on the simulated layout
        res = compute_plan(cfg, path=run_dir / "groundtruth_covariance.csv", qc_run=earlier)
    ratio = _ratio(res, rec)
    assert np.all(np.isfinite(ratio))
    inside = np.mean(np.abs(np.log(ratio)) < np.log(FACTOR))
    assert 1 / FACTOR < np.median(ratio) < FACTOR and inside >= 0.9, (np.median(ratio), inside)
    # tighter than the acceptance: 1.00-1.02 measured; a forgotten source (calibration, time
    # synchronisation: 0.8) would fail it
    assert 1 / 1.2 < np.median(ratio) < 1.2, np.median(ratio)
    assert res.motion.qc_source.startswith("run ")


def test_the_default_qc_is_the_simulated_robots(runs):
    """Without an earlier run the plan assumes the simulator's robot, and says so."""
    _, (cfg, rec, run_dir) = runs
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always", RtsgtWarning)
        res = compute_plan(cfg, path=run_dir / "groundtruth_covariance.csv")
    assert any("no Qc for the GP" in str(w.message) for w in said)
    assert 1 / 1.2 < np.median(_ratio(res, rec)) < 1.2


def test_plan_of_the_real_excerpt_with_the_runs_qc(tmp_path):
    """The acceptance on the real excerpt (docs/planning.md: median ratio 0.99, 85 % of the
    poses within 1.5, with the run's own Qc)."""
    data, opts = load_deployment(EXAMPLE_TOML)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = run_pipeline(data, opts.updated(seed=0, engine="linear"))
    run_dir = write_run(rec, tmp_path / "run")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RtsgtWarning)
        res = compute_plan(EXAMPLE_TOML, path=run_dir / "groundtruth_covariance.csv",
                           qc_run=run_dir)
    assert 1 / FACTOR < np.median(_ratio(res, rec)) < FACTOR


# --------------------------------------------------------------------------------------------
# The pieces in closed form
# --------------------------------------------------------------------------------------------


def test_gp_factor_is_the_three_axis_gp_on_a_uniform_track():
    """An anisotropic measurement covariance and an isotropic Qc: the eigen-decomposition is
    exact; the fit is gp.py's own on a long uniform track, queried at the same phases."""
    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    R = Q @ np.diag([4e-6, 2.5e-7, 1e-8]) @ Q.T  # range 2 mm, angles 0.5 and 0.1 mm
    h, qc, n = 0.4, 3e-3, 401
    t = np.arange(n) * h
    gp = fit_track((t, np.zeros((n, 3)), np.broadcast_to(R, (n, 3, 3)).copy()), qc=qc,
                   max_gap_s=1.0)
    tau = t[n // 2] + (np.arange(PHASES) + 0.5) / PHASES * h
    direct = gp.query(tau).position_cov.mean(axis=0)
    planned = gp_posterior_covariance(R[None], qc * np.eye(3), h)[0]
    np.testing.assert_allclose(planned, direct, rtol=2e-3, atol=2e-3 * np.abs(direct).max())


def test_gp_factor_limits():
    # smooth motion: the continuum limit, met by the table at its lower end
    k0 = 10.0 ** LOG10_KAPPA[0]
    assert gp_factor(k0) == pytest.approx(SMOOTH_LIMIT * k0 ** 0.25, rel=1e-5)
    assert gp_factor(k0 / 100) == pytest.approx(SMOOTH_LIMIT * (k0 / 100) ** 0.25, rel=1e-12)
    # rough motion: proportional to kappa beyond the table
    k1 = 10.0 ** LOG10_KAPPA[-1]
    assert gp_factor(100 * k1) == pytest.approx(100 * gp_factor(k1), rel=1e-9)
    g = gp_factor(np.logspace(-6, 12, 200))
    assert np.all(np.diff(g) > 0)
    # a known value between the nodes, from a direct fit (gp.py, one axis)
    kappa = 37.0
    t = np.arange(401.0)
    fit = fit_track((t, np.zeros((401, 3)), np.broadcast_to(np.eye(3), (401, 3, 3)).copy()),
                    qc=kappa, max_gap_s=2.0)
    direct = fit.query(200 + (np.arange(PHASES) + 0.5) / PHASES).position_cov[:, 0, 0].mean()
    assert gp_factor(kappa) == pytest.approx(direct, rel=1e-3)


def _paper_layout(options: RunOptions | None = None, markers=None, rate=2.5):
    """Three stations around a 60 m site, markers around it, the Warthog-like rig."""
    stations = {"1": PlannedStation((0.0, 0.0, 1.5), "1", rate),
                "2": PlannedStation((60.0, 0.0, 1.4), "2", rate),
                "3": PlannedStation((30.0, 50.0, 1.6), "3", rate)}
    if markers is None:
        a = np.linspace(0, 2 * np.pi, 8, endpoint=False)
        markers = np.column_stack([30 + 35 * np.cos(a), 18 + 35 * np.sin(a),
                                   0.2 + 0.1 * np.sin(3 * a)])
    rig = ReferencePoints(("1", "2", "3"), [[0.40, 0.30, 0.80], [0.40, -0.42, 0.64],
                                            [-0.45, 0.05, 0.95]], np.eye(9) * 1e-6)
    return layout_from_positions("paper", stations, markers, rig,
                                 options or RunOptions(), reference_station="1",
                                 instrument=TRIMBLE_S7)


def test_measurement_covariances_are_the_polar_ones():
    """The white sources of a planned measurement are the first-order polar covariance of
    the calibration module (another code path), and the time synchronisation is
    ``(mu^2 + sigma^2) v v^T`` with the planned velocity exactly."""
    layout = _paper_layout()
    q = np.array([[30.0, 20.0, 0.5], [10.0, 35.0, 0.2], [55.0, 5.0, 1.0]])
    v = np.array([[1.0, 0.0, 0.0], [0.3, -0.9, 0.05], [0.0, 0.0, 0.0]])
    for k, s in enumerate(layout.stations):
        tr = measurement_track(layout, k, q, v)
        T = layout.calibration.transforms[s]
        p_st = (q - T.translation) @ T.rotation
        C = polar_point_covariance(*cartesian_to_polar(p_st), TRIMBLE_S7)
        white = tr.cov_by_source["instrument"] + tr.cov_by_source["tilt"]
        np.testing.assert_allclose(white, T.rotation @ C @ T.rotation.T, rtol=1e-9,
                                   atol=1e-15)
        m2 = layout.model.time_sync_second_moment_s2
        np.testing.assert_allclose(tr.cov_by_source["time_sync"],
                                   m2 * v[:, :, None] * v[:, None, :], rtol=1e-9, atol=1e-18)
        np.testing.assert_allclose(tr.range_m, np.linalg.norm(q - T.translation, axis=1),
                                   rtol=1e-12)


def test_a_layout_on_paper_has_the_runs_calibration(tmp_path):
    """The stations and markers of a simulated deployment, given as positions: the synthetic
    shots fit to the true set-ups, and their Monte Carlo gives the covariance the run's own
    (noisy) shots give, within the Monte Carlo's noise and the shots' (M = 1000)."""
    sim = simulate_deployment(SimulationConfig(duration_s=60.0, gcp_blocked_max=0),
                              np.random.default_rng(11))
    data, opts = load_deployment(write_deployment(sim, tmp_path / "dep"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        real = layout_from_deployment(data, opts)
    assert real.calibration.extra_shot_sigma_m == (0.0, 0.0)  # the shots agree with the model
    truth = sim.truth
    stations = {s: PlannedStation(tuple(truth.T_world_station[s].translation),
                                  truth.station_prism[s]) for s in truth.T_world_station}
    paper = layout_from_positions("paper", stations, truth.gcp_world, data.reference, opts,
                                  reference_station="1", instrument=data.instrument)
    for s in ("2", "3"):
        Tp, Tr = paper.calibration.transforms[s], real.calibration.transforms[s]
        np.testing.assert_allclose(Tp.translation, truth.T_world_station[s].translation,
                                   atol=1e-9)
        ratio = np.sqrt(np.diag(Tp.covariance) / np.diag(Tr.covariance))
        assert np.all(np.abs(ratio - 1) < 0.15), ratio


def test_qc_from_a_run_weighs_the_moving_classes_by_their_intervals():
    fit = {"motion_prior": {"chosen": "classes",
                            "scales": {"standing": 0.01, "below 0.1 m/s^2": 0.5,
                                       "0.1-0.3 m/s^2": 2.0},
                            "intervals": {"standing": 50, "below 0.1 m/s^2": 300,
                                          "0.1-0.3 m/s^2": 100}}}
    qc = np.diag([1e-3, 3e-3, 1e-5])
    m = qc_from_run({"1": {"qc_m2_s3": qc, "qc_fit": fit},
                     "2": {"qc_m2_s3": 2 * qc, "qc_fit": {}}})
    scale = (300 * 0.5 + 100 * 2.0) / 400
    # prisms averaged: (qc * scale + 2 qc) / 2; horizontal: mean of x and y
    assert m.qc_m2_s3[0, 0] == pytest.approx(0.5 * (scale + 2) * 2e-3)
    assert m.qc_m2_s3[2, 2] == pytest.approx(0.5 * (scale + 2) * 1e-5)
    assert m.qc_standing_m2_s3[0, 0] == pytest.approx(0.5 * (0.01 + 2) * 2e-3)
    q = m.qc_at(np.array([0.0, 1.0]))
    np.testing.assert_allclose(q[0], m.qc_standing_m2_s3)
    np.testing.assert_allclose(q[1], m.qc_m2_s3)


def test_advice_fractions_for_known_geometries():
    """Stations within 2 m of the origin, markers on a 40 m square: over a 200 m square the
    share of points beyond 75 m is that outside the circle, and the share outside the
    markers' hull that outside the 40 m square; four markers are fewer than six."""
    stations = {"1": PlannedStation((0.0, 0.0, 1.5), "1"),
                "2": PlannedStation((1.0, 1.0, 1.5), "2"),
                "3": PlannedStation((-1.0, 1.0, 1.5), "3")}
    markers = np.array([[-20.0, -20.0, 0.0], [20.0, -20.0, 0.5], [20.0, 20.0, 0.0],
                        [-20.0, 20.0, 0.5]])
    rig = ReferencePoints(("1", "2", "3"), [[0.40, 0.30, 0.80], [0.40, -0.42, 0.64],
                                            [-0.45, 0.05, 0.95]], np.eye(9) * 1e-6)
    layout = layout_from_positions("square", stations, markers, rig, RunOptions(),
                                   reference_station="1", instrument=TRIMBLE_S7)
    box = [[-100, -100], [100, -100], [100, 100], [-100, 100]]
    with pytest.warns(RtsgtWarning) as rec:
        res = plan_area(layout, RobotMotion(), box, 4.0, 0.8, headings=1)
    said = " ".join(str(w.message) for w in rec)
    adv = res.advice
    assert adv["ranges"]["fraction_beyond"] == pytest.approx(1 - np.pi * 75**2 / 200**2,
                                                             abs=0.02)
    assert adv["ranges"]["verdict"] == "not met" and "75 m from its station" in said
    assert adv["gcp_hull"]["fraction_outside"] == pytest.approx(1 - 40**2 / 200**2, abs=0.01)
    assert adv["gcp_markers"]["per_station"] == {"2": 4, "3": 4}
    assert adv["gcp_markers"]["verdict"] == "not met" and "fewer than 6 markers" in said


def test_polygon_and_waypoints():
    tri = [[0, 0], [4, 0], [0, 4]]
    pts = np.array([[1, 1], [3, 3], [-1, 1], [0.5, 3.0], [2.1, 2.1]])
    np.testing.assert_array_equal(inside_polygon(pts, tri), [True, False, False, True, False])
    w = waypoint_path([[0, 0], [10, 0], [10, 5]], 2.0)
    np.testing.assert_allclose(w[:, 0], [0, 2, 4, 6, 8, 10, 10, 10, 10])
    np.testing.assert_allclose(w[-1], [10, 5])


def test_the_map_is_smaller_where_the_geometry_is_better():
    """Over a site, the predicted sigma grows towards the edges (farther from the stations,
    outside the markers); and a plan with a faster tracking rate predicts less everywhere."""
    box = [[-10, -20], [70, -20], [70, 60], [-10, 60]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RtsgtWarning)
        slow = plan_area(_paper_layout(rate=1.0), RobotMotion(), box, 5.0, 0.8, headings=4)
        fast = plan_area(_paper_layout(rate=5.0), RobotMotion(), box, 5.0, 0.8, headings=4)
    s, f = slow.sigma_median_m, fast.sigma_median_m
    ok = np.isfinite(s) & np.isfinite(f)
    assert ok.mean() > 0.95 and np.all(f[ok] < s[ok])
    centre = np.linalg.norm(slow.points[:, :2] - [30, 18], axis=1)
    assert np.median(s[ok & (centre < 15)]) < np.median(s[ok & (centre > 40)])
    assert np.all(slow.sigma_worst_m[ok] >= s[ok])


# --------------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------------


PLAN_TOML = """
[plan]
name = "{name}"
seed = 3

[[stations]]
id = "1"
xyz_m = [0.0, 0.0, 1.5]
prism = "1"

[[stations]]
id = "2"
xyz_m = [{x2}, 0.0, 1.4]
prism = "2"

[[stations]]
id = "3"
xyz_m = [30.0, 50.0, 1.6]
prism = "3"

[gcp]
xyz_m = [[5, -10, 0.1], [55, -10, 0.3], [65, 30, 0.2], [30, 60, 0.4], [-5, 40, 0.1],
         [30, 20, 0.6], [15, 5, 0.2]]

[rig]
prisms = {{ "1" = [0.40, 0.30, 0.80], "2" = [0.40, -0.42, 0.64], "3" = [-0.45, 0.05, 0.95] }}

[robot]
speed_m_s = 1.0
qc_m2_s3 = [1e-3, 1e-5]

[area]
bbox_m = [0.0, -5.0, 60.0, 50.0]
step_m = 5.0
headings = 4
"""


def _plan_file(tmp: Path, name: str, x2: float = 60.0) -> Path:
    p = tmp / f"{name}.toml"
    p.write_text(PLAN_TOML.format(name=name, x2=x2))
    return p


def test_plan_command_writes_its_files_and_refuses_foreign_ones(tmp_path):
    plan = _plan_file(tmp_path, "a")
    out = tmp_path / "out"
    r = runner.invoke(app, ["plan", str(plan), "-o", str(out)])
    assert r.exit_code == 0, r.output
    names = {p.name for p in out.iterdir()}
    assert names == {"plan.json", "sigma.csv", "plan_map.png", "plan_map.svg", "plan.html",
                     MANIFEST}
    doc = json.loads((out / "plan.json").read_text())
    assert doc["schema"] == {"name": "rtsgt-plan", "version": 1}
    pred = doc["plans"][0]["prediction"]
    table = np.loadtxt(out / "sigma.csv", delimiter=",", skiprows=1)
    assert table.shape == (pred["points"], 7)
    assert np.nanmedian(table[:, 3]) == pytest.approx(pred["sigma_mm"]["median"])
    assert doc["plans"][0]["robot"]["qc_moving_m2_s3"] == {"horizontal": 1e-3,
                                                          "vertical": 1e-5}
    assert set(pred["advice"]) == {"ranges", "gcp_hull", "gcp_markers"}
    assert (out / "plan.html").read_text().startswith("<!DOCTYPE html>")
    assert "median" in r.stdout and "markers per station" in r.stdout
    # never over a folder of the user's, --force or not; --force replaces its own
    before = (out / "sigma.csv").read_bytes()
    r = runner.invoke(app, ["plan", str(plan), "-o", str(out)])
    assert r.exit_code == 1 and "--force" in r.stderr
    (out / "notes.txt").write_text("mine\n")
    r = runner.invoke(app, ["plan", str(plan), "-o", str(out), "--force"])
    assert r.exit_code == 1 and "notes.txt, which rtsgt did not write" in r.stderr
    assert (out / "notes.txt").read_text() == "mine\n" and \
        (out / "sigma.csv").read_bytes() == before
    (out / "notes.txt").unlink()
    r = runner.invoke(app, ["plan", str(plan), "-o", str(out), "--force", "-q"])
    assert r.exit_code == 0 and r.stdout == ""


def test_plan_compare_draws_both_on_one_scale(tmp_path):
    a, b = _plan_file(tmp_path, "near"), _plan_file(tmp_path, "far", x2=110.0)
    out = tmp_path / "cmp"
    r = runner.invoke(app, ["plan", str(a), "--compare", str(b), "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert (out / "sigma_compare.csv").is_file()
    doc = json.loads((out / "plan.json").read_text())
    assert [p["name"] for p in doc["plans"]] == ["near", "far"]
    near, far = (p["prediction"] for p in doc["plans"])
    # station 2 50 m farther: the far layout is worse, and it says the range advice fails
    assert far["sigma_mm"]["median"] > near["sigma_mm"]["median"]
    assert far["advice"]["ranges"]["fraction_beyond"] > near["advice"]["ranges"]["fraction_beyond"]
    # one colour scale for both panels
    from rtsgt.cli.plan import compute_plan as cp
    from rtsgt.report.plan import draw_plan_map
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RtsgtWarning)
        fig = draw_plan_map([cp(a), cp(b)])
    meshes = [ax.collections[0] for ax in fig.figure.axes[:2]]
    assert meshes[0].norm is meshes[1].norm
    assert fig.points["grid_points 1"] > 0 and fig.points["grid_points 2"] > 0


def test_plan_file_errors_name_the_key(tmp_path):
    p = _plan_file(tmp_path, "bad")
    p.write_text(p.read_text().replace("speed_m_s = 1.0", "speed_m_s = 1.0\nsped = 2"))
    r = runner.invoke(app, ["plan", str(p), "-o", str(tmp_path / "o")])
    assert r.exit_code == 1 and "[robot] has unknown key(s) sped" in r.stderr
    assert not (tmp_path / "o").exists()


def test_paths_from_waypoints_and_from_a_csv_with_times(tmp_path):
    plan = _plan_file(tmp_path, "w")
    text = plan.read_text()
    text = text[:text.index("[area]")] + "[path]\nwaypoints_m = [[5, 5], [25, 5], [25, 20]]\n"
    plan.write_text(text)
    out = tmp_path / "w-out"
    r = runner.invoke(app, ["plan", str(plan), "-o", str(out), "-q"])
    assert r.exit_code == 0, r.output
    table = np.loadtxt(out / "sigma.csv", delimiter=",", skiprows=1)
    assert (out / "sigma.csv").read_text().startswith("x,y,z,sigma_mm")
    assert table.shape[0] == 36  # every metre along 35 m, both ends
    np.testing.assert_allclose(np.abs(np.diff(table[:, :2], axis=0)).sum(axis=1), 1.0)
    assert np.all(table[:, 3] == table[:, 4])  # one heading: the direction of travel
    csv = tmp_path / "p.csv"
    csv.write_text("t,x,y\n0,5,5\n1,7,5\n2,9,5\n3,11,5\n")
    r = runner.invoke(app, ["plan", str(plan), "--path", str(csv), "-o", str(tmp_path / "c"),
                            "-q"])
    assert r.exit_code == 0, r.output
    lines = (tmp_path / "c" / "sigma.csv").read_text().splitlines()
    assert lines[0].startswith("t,x,y,z,") and len(lines) == 5
