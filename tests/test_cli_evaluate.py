"""``rtsgt evaluate`` on files: the JSON layout, the table, the figures, formats and errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import typer
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from rtsgt.cli.main import app as main_app
from rtsgt.evaluation import evaluate
from rtsgt.io.trajectory import (
    read_groundtruth_dir,
    read_tum,
    write_covariance_csv,
    write_euroc,
    write_kitti,
    write_tum,
)
from rtsgt.types import PoseTrajectory
from test_evaluation_synth import (
    perturbed,
    random_covariances,
    smooth_truth,
    trajectory,
    transform_trajectory,
    write_gt_dir,
)

STATS = {"rmse", "mean", "median", "std", "min", "max"}


def _app() -> typer.Typer:
    """The application, with its rule for errors and exit statuses."""
    return main_app


runner = CliRunner()


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A ground-truth directory (1000 poses at 10 Hz with covariances) and an estimate:
    truth + N(0, Sigma_est) at 5 Hz, in another frame."""
    d = tmp_path_factory.mktemp("eval")
    rng = np.random.default_rng(7)
    t, p, R = smooth_truth(1000)
    gt = perturbed(t, p, R, random_covariances(len(t), rng, 2e-3, 5e-4), rng)
    gt_dir = write_gt_dir(d / "run", gt)
    sub = slice(0, None, 2)
    est_w = perturbed(t[sub], p[sub], R[sub], random_covariances(len(t[sub]), rng, 6e-3, 2e-3), rng)
    Ra = Rotation.from_rotvec([0.0, 0.0, 1.2]).as_matrix()
    est = transform_trajectory(est_w, Ra, np.array([2.0, -1.0, 0.5]))
    write_tum(d / "est.tum", est)
    write_covariance_csv(d / "est_cov.csv", est)
    return d, gt_dir, est


def test_json_layout_and_values(files):
    d, gt_dir, est = files
    r = runner.invoke(_app(), ["evaluate", str(gt_dir), str(d / "est.tum"), "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert {"ape", "rpe", "nees", "noise_floor"} <= set(out)
    for sec in ("ape", "rpe"):
        for part in ("translation_m", "rotation_deg"):
            assert set(out[sec][part]) == STATS
    for part, dof in (("position", 3), ("pose", 6)):
        assert {"mean", "dof", "fraction_inside_95", "consistent"} <= set(out["nees"][part])
        assert out["nees"][part]["dof"] == dof
    # same numbers as the library on the same files
    lib = evaluate(read_groundtruth_dir(gt_dir), read_tum(d / "est.tum"))
    assert out["ape"]["translation_m"]["rmse"] == pytest.approx(
        lib.ape.translation_m.rmse, rel=1e-12
    )
    assert out["rpe"]["rotation_deg"]["max"] == pytest.approx(lib.rpe.rotation_deg.max, rel=1e-12)
    assert out["noise_floor"]["ape_translation_m"] == pytest.approx(
        lib.noise_floor.ape_translation_m, rel=1e-12
    )
    # without the estimate's covariance, its own 6 mm noise makes the NEES too large
    assert out["nees"]["position"]["consistent"] is False
    # with it (--est-cov), consistent
    r = runner.invoke(
        _app(),
        [
            "evaluate",
            str(gt_dir),
            str(d / "est.tum"),
            "--json",
            "--est-cov",
            str(d / "est_cov.csv"),
        ],
    )
    assert r.exit_code == 0, r.output
    nees = json.loads(r.stdout)["nees"]
    assert nees["position"]["consistent"] is True and nees["pose"]["consistent"] is True
    assert abs(nees["pose"]["mean"] - 6) < 0.5


def test_json_ape_equals_evo_ape_on_the_same_files(files, tmp_path):
    pytest.importorskip("evo")
    import shutil
    import zipfile
    from pathlib import Path

    d, gt_dir, _ = files
    exe = shutil.which("evo_ape") or str(Path(sys.executable).parent / "evo_ape")
    out = tmp_path / "r.zip"
    subprocess.run(
        [
            exe,
            "tum",
            str(gt_dir / "groundtruth.tum"),
            str(d / "est.tum"),
            "-a",
            "--t_max_diff",
            "0.001",
            "--save_results",
            str(out),
            "--no_warnings",
            "--silent",
        ],
        check=True,
        capture_output=True,
        timeout=120,
    )
    with zipfile.ZipFile(out) as z:
        s = json.loads(z.read("stats.json"))
    r = runner.invoke(
        _app(), ["evaluate", str(gt_dir), str(d / "est.tum"), "--json", "--align", "se3"]
    )
    mine = json.loads(r.stdout)["ape"]["translation_m"]
    for k in STATS:
        # the TUM ground truth is written to 1e-9 m precision at most (shortest repr here)
        assert mine[k] == pytest.approx(s[k], abs=1e-9)


def test_table_output(files):
    d, gt_dir, _ = files
    r = runner.invoke(
        _app(),
        [
            "evaluate",
            str(gt_dir),
            str(d / "est.tum"),
            "--align",
            "4dof",
            "--delta",
            "10",
            "--delta-unit",
            "f",
        ],
        env={"COLUMNS": "200"},
    )
    assert r.exit_code == 0, r.output
    for text in (
        "APE translation",
        "RPE rotation",
        "NEES",
        "inconsistent",
        "noise floor",
        "alignment: 4dof",
        "500 of 500",
    ):
        assert text in r.stdout, text


def test_plots(files, tmp_path):
    from rtsgt.report.eval_plots import plot_evaluation

    d, gt_dir, _ = files
    r = runner.invoke(
        _app(),
        ["evaluate", str(gt_dir), str(d / "est.tum"), "--plot", str(tmp_path / "fig"), "--json"],
    )
    assert r.exit_code == 0, r.output
    for name in ("translation_error", "top_view", "nees_histogram"):
        for ext in ("png", "svg"):
            f = tmp_path / "fig" / f"{name}.{ext}"
            assert f.stat().st_size > 1000
    assert (tmp_path / "fig" / "top_view.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    res = evaluate(read_groundtruth_dir(gt_dir), read_tum(d / "est.tum"))
    pl = plot_evaluation(res, tmp_path / "fig2", max_ellipses=25)
    assert pl.n_ellipses == 25 and pl.ellipse_scale >= 1
    counts, edges = pl.hist["pose"]
    assert np.sum(counts * np.diff(edges)) == pytest.approx(1.0)
    np.testing.assert_allclose(pl.sigma_norm**2, np.trace(res.gt.cov[:, :3, :3], axis1=1, axis2=2))
    assert len(pl.files) == 8  # and the drift figure (tests/test_drift.py)


def test_other_estimate_formats(files, tmp_path):
    d, gt_dir, est = files
    ref = json.loads(
        runner.invoke(_app(), ["evaluate", str(gt_dir), str(d / "est.tum"), "--json"]).stdout
    )["ape"]["translation_m"]["rmse"]
    write_kitti(tmp_path / "est.kitti", est, tmp_path / "times.txt")
    write_euroc(tmp_path / "est_euroc.csv", est)
    for args in (
        [
            str(tmp_path / "est.kitti"),
            "--format",
            "kitti",
            "--timestamps",
            str(tmp_path / "times.txt"),
        ],
        [str(tmp_path / "est_euroc.csv")],
    ):
        r = runner.invoke(_app(), ["evaluate", str(gt_dir), *args, "--json"])
        assert r.exit_code == 0, r.output
        assert json.loads(r.stdout)["ape"]["translation_m"]["rmse"] == pytest.approx(ref, rel=1e-6)


def test_bag_estimate_and_unknown_topic(files, tmp_path):
    pytest.importorskip("rosbags")
    from test_io_trajectory import write_bag

    d, gt_dir, est = files
    write_bag(tmp_path / "est.bag", True, est, kinds=("posecov", "pose"))
    r = runner.invoke(
        _app(),
        ["evaluate", str(gt_dir), str(tmp_path / "est.bag"), "--topic", "/posecov", "--json"],
    )
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["nees"]["pose"]["consistent"] is True  # covariance from the bag
    r = runner.invoke(
        _app(), ["evaluate", str(gt_dir), str(tmp_path / "est.bag"), "--topic", "/odom"]
    )
    assert r.stderr.startswith("error: ")
    assert "/pose (geometry_msgs/msg/PoseStamped)" in r.stderr


def test_errors(files, tmp_path):
    d, gt_dir, est = files
    late = PoseTrajectory(est.t + 1e5, est.position, est.quat_xyzw)
    write_tum(tmp_path / "late.tum", late)
    r = runner.invoke(_app(), ["evaluate", str(gt_dir), str(tmp_path / "late.tum")])
    assert r.stderr.startswith("error: ") and "No time overlap" in r.stderr
    r = runner.invoke(
        _app(), ["evaluate", str(gt_dir), str(tmp_path / "late.tum"), "--time-offset", "-100000"]
    )
    assert r.exit_code == 0, r.output
    two = trajectory(est.t[:2], est.position[:2], est.rotation[:2])
    write_tum(tmp_path / "two.tum", two)
    r = runner.invoke(_app(), ["evaluate", str(gt_dir), str(tmp_path / "two.tum")])
    assert r.stderr.startswith("error: ") and "at least 3 associated poses" in r.stderr
    r = runner.invoke(_app(), ["evaluate", str(gt_dir), str(d / "est.tum"), "--align", "7dof"])
    assert r.exit_code == 2 and "--align" in r.output
    for args, option in ((["--delta", "1.5", "--delta-unit", "f"], "--delta"),
                         (["--delta", "-1"], "--delta"), (["--t-offset", "nan"], "--t-offset")):
        r = runner.invoke(_app(), ["evaluate", "no-such-gt", "no-such-est", *args])
        assert r.exit_code == 2 and option in r.output, (args, r.output)  # before any reading
    (tmp_path / "bad.tum").write_text("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 2\n")
    r = runner.invoke(_app(), ["evaluate", str(gt_dir), str(tmp_path / "bad.tum")])
    assert r.stderr.startswith("error: ") and ":2:" in r.stderr


def test_entry_point_prints_one_line_error_and_exit_code_1(files, tmp_path):
    """Through the real `rtsgt` entry point (rtsgt.cli.entry.main)."""
    d, gt_dir, _ = files
    (tmp_path / "nan.tum").write_text("1 0 0 0 0 0 0 1\n2 nan 0 0 0 0 0 1\n")
    p = subprocess.run(
        [
            sys.executable,
            "-c",
            "from rtsgt.cli.entry import main; main()",
            "evaluate",
            str(gt_dir),
            str(tmp_path / "nan.tum"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 1
    assert p.stderr.startswith("error: ") and "nan.tum:2" in p.stderr
    assert p.stderr.count("\n") == 1


# ----------------------------------------------------------------------------- a real run


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    """``rtsgt simulate`` (90 s, with line-of-sight losses) + ``rtsgt run --engine linear``."""
    from rtsgt.cli.main import app as main_app

    d = tmp_path_factory.mktemp("simrun")
    r = runner.invoke(main_app, ["simulate", "--seed", "1", "--duration", "90", str(d / "dep")])
    assert r.exit_code == 0, r.output
    r = runner.invoke(
        main_app,
        ["run", str(d / "dep" / "deployment.toml"), "-o", str(d / "run"), "--engine", "linear",
         "-q"],
    )
    assert r.exit_code == 0, r.output
    return d / "run"


def _json(*args: str) -> dict:
    r = runner.invoke(_app(), ["evaluate", *args, "--json"])
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)


def test_run_directory_keeps_every_pose_the_run_produced(sim_run):
    """The estimate = the run's own groundtruth.tum: every pose is associated by default (the
    run's own gap limit, summary.json parameters.max_gap_s), continuous and discrete; an
    explicit --max-gap still wins."""
    n = len(read_tum(sim_run / "groundtruth.tum"))
    limit = json.loads((sim_run / "summary.json").read_text())["parameters"]["max_gap_s"]
    est = str(sim_run / "groundtruth.tum")
    for mode in ("auto", "discrete"):
        out = _json(str(sim_run), est, "--gt-mode", mode)
        a = out["association"]
        assert a["n_associated"] == n and a["n_dropped"] == 0, (mode, a)
        assert a["max_dt_s"] == limit
        assert out["ape"]["translation_m"]["max"] < 1e-6
    assert out["warnings"] == []
    r = runner.invoke(_app(), ["evaluate", str(sim_run), est, "--max-gap", "0.5", "--json"])
    assert r.exit_code == 0, r.output
    shown = [ln for ln in r.stderr.splitlines() if ln.startswith("warning: ")]
    assert len(shown) == 1 and "RPE pairs span a gap of the ground truth" in shown[0]
    out = json.loads(r.stdout)
    a = out["association"]
    assert a["max_dt_s"] == 0.5
    assert a["dropped_by_reason"]["far_from_measurement"] > 0  # measurement gaps beyond 1 s
    # the RPE pairs across the poses so dropped are counted in a warning
    assert len(out["warnings"]) == 1 and "(gap limit 0.5 s;" in out["warnings"][0]
    # a trajectory file keeps the documented default for files (0.5 s)
    out = _json(est, est)
    assert out["association"]["max_dt_s"] == 0.5


def test_no_rpe_pair_reports_ape_nees_and_why(files, tmp_path):
    d, gt_dir, est = files
    short = PoseTrajectory(est.t[:30], est.position[:30], est.quat_xyzw[:30])
    write_tum(tmp_path / "short.tum", short)
    args = ["evaluate", str(gt_dir), str(tmp_path / "short.tum"), "--delta", "100"]
    r = runner.invoke(_app(), [*args, "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["rpe"]["n_pairs"] == 0 and out["rpe"]["translation_m"] is None
    assert "100 m" in out["rpe"]["absent_reason"]
    assert out["ape"]["n"] == 30 and out["nees"]["position"]["mean"] > 0
    assert out["nees"]["relative_pose"]["mean"] is None
    r = runner.invoke(_app(), args, env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert "APE translation" in r.stdout and "NEES" in r.stdout
    assert "no RPE: " in r.stdout and out["rpe"]["absent_reason"] in r.stdout


def test_warnings_are_shown_and_listed_in_json(files, tmp_path):
    """A comma-separated TUM estimate: read as TUM with one warning naming the file, in the
    terminal (one line through the entry point) and in --json's ``warnings``; the same
    numbers as the TUM file. Nanosecond stamps in it: one error line, exit status 1."""
    d, gt_dir, est = files
    rows = np.column_stack([est.t, est.position, est.quat_xyzw]).tolist()
    (tmp_path / "est.csv").write_text("".join(",".join(repr(v) for v in r) + "\n" for r in rows))
    ref = _json(str(gt_dir), str(d / "est.tum"))
    assert ref["warnings"] == []
    r = runner.invoke(_app(), ["evaluate", str(gt_dir), str(tmp_path / "est.csv"), "--json"])
    assert r.exit_code == 0, r.output
    assert r.stderr.startswith("warning: ") and "read as TUM" in r.stderr
    out = json.loads(r.stdout)
    assert len(out["warnings"]) == 1 and "est.csv" in out["warnings"][0]
    assert out["ape"] == ref["ape"] and out["rpe"] == ref["rpe"]

    def entry_point(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-c", "from rtsgt.cli.entry import main; main()", "evaluate", *args],
            capture_output=True, text=True, timeout=120,
        )

    p = entry_point(str(gt_dir), str(tmp_path / "est.csv"), "--json")
    assert p.returncode == 0, p.stderr
    assert p.stderr.startswith("warning: ") and p.stderr.count("\n") == 1
    assert "est.csv" in p.stderr
    assert json.loads(p.stdout)["warnings"] == out["warnings"]
    ns = (np.round(est.t * 1e6).astype(np.int64) * 1000).tolist()
    (tmp_path / "ns.tum").write_text(
        "".join(
            f"{t} " + " ".join(repr(v) for v in r[1:]) + "\n"
            for t, r in zip(ns, rows, strict=True)
        )
    )
    p = entry_point(str(gt_dir), str(tmp_path / "ns.tum"))
    assert p.returncode == 1
    assert p.stderr.startswith("error: ") and p.stderr.count("\n") == 1
    assert "ns.tum:1: " in p.stderr and "nanoseconds" in p.stderr


@pytest.fixture(scope="module")
def mounted(tmp_path_factory):
    """The ground truth of ``files`` and an estimate of a sensor rotated 180 deg about z from
    the body frame, 0.5 m from its origin, stamped 30 ms late, in another world frame."""
    d = tmp_path_factory.mktemp("mounted")
    rng = np.random.default_rng(17)
    t, p, R = smooth_truth(1000)
    gt = perturbed(t, p, R, random_covariances(len(t), rng, 2e-3, 5e-4), rng)
    gt_dir = write_gt_dir(d / "run", gt)
    R_bs = Rotation.from_rotvec([0.0, 0.0, np.pi]).as_matrix()
    lever = np.array([0.4, 0.0, 0.3])
    sub = slice(10, -10, 2)
    Rs, ps = R[sub] @ R_bs, p[sub] + R[sub] @ lever
    Ra = Rotation.from_rotvec([0.0, 0.0, 1.2]).as_matrix()
    est = transform_trajectory(trajectory(t[sub] - 0.03, ps, Rs), Ra, np.array([2.0, -1.0, 0.5]))
    write_tum(d / "sensor.tum", est)
    return d, gt_dir, R_bs, lever


def test_estimate_mounting_and_clock_json_table_and_plots(mounted, tmp_path):
    """``--estimate all``: the mounting (180 deg, 0.5 m) and the clock (30 ms) within a few
    sigma of the truth, in the JSON with their sigmas and covariance, in the table, and in
    the figures; without the estimate the same file gets an APE rotation near 180 deg."""
    d, gt_dir, R_bs, lever = mounted
    r = runner.invoke(_app(), ["evaluate", str(gt_dir), str(d / "sensor.tum"), "--json"])
    assert r.exit_code == 0, r.output
    plain = json.loads(r.stdout)
    assert plain["ape"]["rotation_deg"]["rmse"] > 170 and plain["mounting"] is None
    r = runner.invoke(_app(), ["evaluate", str(gt_dir), str(d / "sensor.tum"), "--json",
                               "--estimate", "all", "--plot", str(tmp_path / "fig")])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    m = out["mounting"]
    assert m["estimated"] == ["rotation", "lever", "clock"] and m["given"] == []
    assert abs(m["rotation_angle_deg"] - 180.0) < 4 * max(m["rotation_sigma_deg"])
    assert np.all(np.abs(np.array(m["lever_m"]) - lever) < 4 * np.array(m["lever_sigma_m"]))
    assert abs(m["clock_offset_s"] - 0.03) < 4 * m["clock_sigma_s"]
    assert out["association"]["time_offset_s"] == m["clock_offset_s"]
    assert np.array(m["covariance"]).shape == (7, 7) and len(m["names"]) == 7
    assert set(m["effect"]) == {"ape_translation_m", "ape_rotation_deg", "rpe_translation_m",
                                "rpe_rotation_deg"}
    lim = m["fit"]["max_sigma"]
    assert lim["rotation"] == pytest.approx(np.radians(1.0)) and lim["lever"] == 0.02
    assert m["clock_sigma_s"] < lim["clock"] <= 1.0  # 0.02 m at the rms speed, within 1 s
    assert out["ape"]["rotation_deg"]["rmse"] < 0.2
    assert out["rpe"]["translation_m"]["rmse"] < 0.02
    for f in ("top_view.png", "translation_error.svg"):
        assert (tmp_path / "fig" / f).stat().st_size > 1000
    assert "T_body_sensor estimated: rotation, lever, clock" in (
        tmp_path / "fig" / "top_view.svg").read_text()
    r = runner.invoke(_app(), ["evaluate", str(gt_dir), str(d / "sensor.tum"), "--estimate",
                               "mounting,clock"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    for text in ("Mounting T_body_sensor", "lever arm (m, body frame)", "clock offset (s)",
                 "estimated jointly with a se3 alignment", "within the uncertainty of the "
                 "estimated rotation, lever, clock: APE rmse +-"):
        assert text in r.stdout, text


def test_given_mounting_in_every_form(mounted, tmp_path):
    """``--mounting`` as seven numbers, evo's JSON transform or a 4x4 matrix file: the same
    result; bad values are usage errors naming the option."""
    d, gt_dir, R_bs, lever = mounted
    from rtsgt.geometry.so3 import matrix_to_quat_xyzw

    q = matrix_to_quat_xyzw(R_bs)
    seven = ",".join(f"{v:.17g}" for v in (*lever, *q))
    (tmp_path / "T.json").write_text(json.dumps(dict(zip(
        ("x", "y", "z", "qx", "qy", "qz", "qw"), (*lever, *q), strict=True))))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_bs, lever
    (tmp_path / "T.txt").write_text("# T_body_sensor\n" + "\n".join(
        " ".join(f"{v:.17g}" for v in row) for row in T))
    rmse = []
    for value in (seven, str(tmp_path / "T.json"), str(tmp_path / "T.txt")):
        r = runner.invoke(_app(), ["evaluate", str(gt_dir), str(d / "sensor.tum"), "--json",
                                   "--mounting", value, "--t-offset", "0.03"])
        assert r.exit_code == 0, r.output
        out = json.loads(r.stdout)
        assert out["mounting"]["estimated"] == [] and out["mounting"]["effect"] is None
        rmse.append(out["ape"]["translation_m"]["rmse"])
    assert rmse[0] < 0.01 and max(rmse) - min(rmse) < 1e-12
    for args, option in ((["--mounting", "1,2,3"], "--mounting"),
                         (["--mounting", "0,0,0,0,0,0,3"], "--mounting"),
                         (["--estimate", "levers"], "--estimate"),
                         (["--estimate", "lever", "--align", "origin"], "--estimate")):
        r = runner.invoke(_app(), ["evaluate", str(gt_dir), str(d / "sensor.tum"), *args])
        assert r.exit_code == 2 and option in r.output, (args, r.output)


def test_refusal_is_one_line_and_exit_code_1(tmp_path):
    """A straight drive asked for a lever arm: ``error: cannot estimate the lever arm: ...``
    on one line, exit status 1, no number."""
    rng = np.random.default_rng(3)
    n = 300
    t = 1_668_095_037.0 + 0.1 * np.arange(n)
    p = np.c_[t - t[0], np.zeros(n), np.zeros(n)]
    R = np.tile(np.eye(3), (n, 1, 1))
    gt = perturbed(t, p, R, random_covariances(n, rng, 2e-3, 5e-4), rng)
    gt_dir = write_gt_dir(tmp_path / "run", gt)
    write_tum(tmp_path / "est.tum", trajectory(t, p + [0.3, 0.4, 0.0], R))
    exe = [sys.executable, "-c", "from rtsgt.cli.entry import main; main()"]
    pr = subprocess.run([*exe, "evaluate", str(gt_dir), str(tmp_path / "est.tum"), "--estimate",
                         "lever", "--align", "4dof", "--json"], capture_output=True, text=True,
                        timeout=120)
    assert pr.returncode == 1, pr.stderr
    assert pr.stdout == ""
    assert pr.stderr.startswith("error: cannot estimate the lever arm: the trajectory does "
                                "not excite it")
    assert pr.stderr.count("\n") == 1
