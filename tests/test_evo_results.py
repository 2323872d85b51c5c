"""``rtsgt evaluate --save-results``: evo's result zips, read by evo itself.

evo (GPL) is a test-only dependency: ``evo_res`` runs here as a real client (a subprocess of
the venv's executable) on three zips written by rtsgt, and ``evo.tools.file_interface``
loads them; ``evo_ape`` / ``evo_rpe --save_results`` on the same TUM files give the reference
layout. rtsgt itself never imports evo.
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from rtsgt.app import run_evaluation
from rtsgt.cli.main import app
from rtsgt.evaluation import EvaluationOptions
from rtsgt.io.evo_results import EVO_STATISTICS, EXTRA_STATISTICS, RTSGT_ENTRY
from rtsgt.io.positions import write_position_csv
from rtsgt.io.trajectory import write_covariance_csv, write_tum
from rtsgt.types import PositionTrajectory
from test_evaluation_synth import (
    perturbed,
    random_covariances,
    smooth_truth,
    transform_trajectory,
    write_gt_dir,
)

file_interface = pytest.importorskip("evo.tools.file_interface")

runner = CliRunner()
STATS = ("rmse", "mean", "median", "std", "min", "max")
#: Estimate noise (m, rad) of the three evaluations.
NOISE = {"est_a": (4e-3, 1e-3), "est_b": (8e-3, 2e-3), "est_c": (16e-3, 4e-3)}


def _evo_exe(tool: str) -> str:
    exe = shutil.which(tool) or str(Path(sys.executable).parent / tool)
    if not Path(exe).exists():
        pytest.skip(f"{tool} is not installed (evo is a test-only dependency)")
    return exe


def _evo_env(tmp: Path) -> dict:
    """evo's settings in a fresh home (no user settings), a non-interactive backend."""
    home = tmp / "home"
    home.mkdir(exist_ok=True)
    return {**os.environ, "HOME": str(home), "MPLBACKEND": "Agg", "OPENBLAS_NUM_THREADS": "1"}


def _evaluate(args: list[str]) -> dict:
    r = runner.invoke(app, ["evaluate", *args, "--json"])
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """A ground-truth run directory (600 poses at 10 Hz, with covariances) and three
    estimates (5 Hz, their covariance files) in another frame, each evaluated with
    ``--save-results`` and ``--save-results-rpe``."""
    d = tmp_path_factory.mktemp("evores")
    rng = np.random.default_rng(11)
    t, p, R = smooth_truth(600)
    gt = perturbed(t, p, R, random_covariances(len(t), rng, 2e-3, 5e-4), rng)
    gt_dir = write_gt_dir(d / "run", gt)
    sub = slice(0, None, 2)
    Ra = Rotation.from_rotvec([0.0, 0.0, 0.8]).as_matrix()
    out = {"dir": d, "gt_dir": gt_dir, "json": {}}
    for name, (sp, sr) in NOISE.items():
        est_w = perturbed(t[sub], p[sub], R[sub],
                          random_covariances(len(t[sub]), rng, sp, sr), rng)
        est = transform_trajectory(est_w, Ra, np.array([1.0, -2.0, 0.3]))
        write_tum(d / f"{name}.tum", est)
        write_covariance_csv(d / f"{name}_cov.csv", est)
        out["json"][name] = _evaluate([
            str(gt_dir), str(d / f"{name}.tum"), "--est-cov", str(d / f"{name}_cov.csv"),
            "--save-results", str(d / f"{name}_ape.zip"),
            "--save-results-rpe", str(d / f"{name}_rpe.zip")])
    return out


def _close(a: float, b: float, tol: float = 1e-12) -> bool:
    return abs(a - b) <= tol * max(1.0, abs(b))


def test_evo_res_tables_three_rtsgt_results(campaign, tmp_path):
    """``evo_res`` (a subprocess) tables the three APE zips: its CSV holds each estimate
    with rtsgt's statistics, noise floor and NEES mean; it plots them too."""
    exe = _evo_exe("evo_res")
    d = campaign["dir"]
    zips = [str(d / f"{n}_ape.zip") for n in NOISE]
    table = tmp_path / "table.csv"
    subprocess.run([exe, *zips, "--no_warnings", "--save_table", str(table),
                    "--save_plot", str(tmp_path / "plots.png")],
                   check=True, capture_output=True, timeout=300, env=_evo_env(tmp_path))
    with open(table, newline="") as fh:
        rows = {r[""]: r for r in csv.DictReader(fh)}
    assert set(rows) == {f"{n}.tum" for n in NOISE}
    for name in NOISE:
        row, js = rows[f"{name}.tum"], campaign["json"][name]
        for k in STATS:
            assert _close(float(row[k]), js["ape"]["translation_m"][k]), (name, k)
        assert _close(float(row["noise_floor"]), js["noise_floor"]["ape_translation_m"])
        assert _close(float(row["rmse_floor_removed"]),
                      js["noise_floor"]["ape_translation_rmse_floor_removed_m"])
        assert _close(float(row["nees_mean"]), js["nees"]["position"]["mean"])
        assert float(row["nees_dof"]) == 3.0
    # the noisier estimates rank as they should in evo's table
    rmse = [float(rows[f"{n}.tum"]["rmse"]) for n in NOISE]
    assert rmse == sorted(rmse)
    assert list(tmp_path.glob("plots*.png")), "evo_res wrote no figure"


def test_evo_res_reads_rpe_results(campaign, tmp_path):
    exe = _evo_exe("evo_res")
    d = campaign["dir"]
    table = tmp_path / "rpe.csv"
    subprocess.run([exe, *[str(d / f"{n}_rpe.zip") for n in NOISE], "--no_warnings",
                    "--save_table", str(table)],
                   check=True, capture_output=True, timeout=300, env=_evo_env(tmp_path))
    with open(table, newline="") as fh:
        rows = {r[""]: r for r in csv.DictReader(fh)}
    for name in NOISE:
        js = campaign["json"][name]
        for k in STATS:
            assert _close(float(rows[f"{name}.tum"][k]), js["rpe"]["translation_m"][k])
        assert _close(float(rows[f"{name}.tum"]["nees_mean"]),
                      js["nees"]["relative_position"]["mean"])


def test_load_res_file_arrays_equal_rtsgt(campaign):
    """Each zip through evo's reader: the arrays are rtsgt's, the extras are there."""
    d = campaign["dir"]
    for name in NOISE:
        res = run_evaluation(campaign["gt_dir"], d / f"{name}.tum", est_cov=d / f"{name}_cov.csv")
        ape = file_interface.load_res_file(str(d / f"{name}_ape.zip"), load_trajectories=True)
        assert ape.info["title"] == "APE w.r.t. translation part (m)\n(with SE(3) Umeyama alignment)"
        assert ape.info["label"] == "APE (m)" and ape.info["written_by"] == "rtsgt"
        assert set(ape.stats) == set(EVO_STATISTICS) | set(EXTRA_STATISTICS)
        np.testing.assert_array_equal(ape.np_arrays["error_array"], res.ape.translation_error)
        np.testing.assert_array_equal(ape.np_arrays["timestamps"], res.t)
        np.testing.assert_array_equal(ape.np_arrays["seconds_from_start"], res.t - res.t[0])
        np.testing.assert_array_equal(ape.np_arrays["nees"], res.nees.position.values)
        np.testing.assert_allclose(ape.np_arrays["alignment_transformation_sim3"],
                                   res.alignment.as_matrix(), rtol=0, atol=0)
        assert _close(ape.stats["sse"], float(np.sum(res.ape.translation_error**2)))
        assert ape.stats["nees_consistent"] == float(res.nees.position.consistent)
        # the trajectories: the associated ground truth and the aligned estimate
        est = ape.trajectories[f"{name}.tum"]
        np.testing.assert_allclose(est.positions_xyz, res.est.position, rtol=0, atol=1e-12)
        np.testing.assert_allclose(est.timestamps, res.est.t, rtol=0, atol=1e-9)
        ref = ape.trajectories["run"]
        np.testing.assert_allclose(ref.positions_xyz, res.gt.position, rtol=0, atol=1e-12)
        with zipfile.ZipFile(d / f"{name}_ape.zip") as z:
            full = json.loads(z.read(RTSGT_ENTRY))
        assert full["ape"] == campaign["json"][name]["ape"]
        rpe = file_interface.load_res_file(str(d / f"{name}_rpe.zip"))
        j = res.rpe.pairs[:, 1]
        np.testing.assert_array_equal(rpe.np_arrays["error_array"], res.rpe.translation_error)
        np.testing.assert_array_equal(rpe.np_arrays["timestamps"], res.t[j])
        np.testing.assert_array_equal(rpe.np_arrays["nees"], res.nees.relative_position.values)
        assert rpe.info["title"].startswith("RPE w.r.t. translation part (m)\nfor delta = 1.0 (m)")


def _evo_cli_zip(tool: str, args: list[str], out: Path, tmp: Path) -> Path:
    subprocess.run([_evo_exe(tool), "tum", *args, "--save_results", str(out), "--no_warnings",
                    "--silent"], check=True, capture_output=True, timeout=120, env=_evo_env(tmp))
    return out


@pytest.mark.parametrize(("relation", "evo_r"), [("trans_part", "trans_part"),
                                                   ("angle_deg", "angle_deg"), ("full", "full")])
def test_same_layout_as_evo_ape_and_evo_rpe(tmp_path, relation, evo_r):
    """On the same TUM files, evo_ape / evo_rpe and rtsgt write the same entries: evo's keys
    all present with the same titles, labels, statistics and arrays (to 1e-9)."""
    rng = np.random.default_rng(3)
    t, p, R = smooth_truth(300)
    gt = perturbed(t, p, R, random_covariances(len(t), rng, 1e-3, 3e-4), rng)
    est = perturbed(t, p, R, random_covariances(len(t), rng, 5e-3, 2e-3), rng)
    est = transform_trajectory(est, Rotation.from_rotvec([0.1, 0.0, 0.5]).as_matrix(),
                               np.array([0.5, 1.0, 0.0]))
    write_tum(tmp_path / "gt.tum", gt)
    write_tum(tmp_path / "est.tum", est)
    files = [str(tmp_path / "gt.tum"), str(tmp_path / "est.tum")]
    for metric, tool, extra, mine in (
        ("ape", "evo_ape", [], []),
        ("rpe", "evo_rpe", ["-d", "1", "-u", "f"], ["--delta", "1", "--delta-unit", "f"]),
    ):
        ref = file_interface.load_res_file(str(_evo_cli_zip(
            tool, [*files, "-a", "-r", evo_r, *extra], tmp_path / f"evo_{metric}.zip", tmp_path)))
        ours = tmp_path / f"rtsgt_{metric}.zip"
        option = "--save-results" if metric == "ape" else "--save-results-rpe"
        _evaluate([*files, "--align", "se3", "--pose-relation", relation, *mine, option,
                   str(ours)])
        got = file_interface.load_res_file(str(ours))
        for k in ("title", "ref_name", "est_name", "label"):
            assert got.info[k] == ref.info[k], (metric, k)
        assert set(ref.stats) <= set(got.stats)
        for k, v in ref.stats.items():
            assert abs(got.stats[k] - v) <= 1e-9 * max(1.0, abs(v)), (metric, relation, k)
        assert set(ref.np_arrays) <= set(got.np_arrays)
        for k, v in ref.np_arrays.items():
            np.testing.assert_allclose(got.np_arrays[k], v, rtol=0, atol=1e-9,
                                       err_msg=f"{metric} {relation} {k}")
    if relation == "full":  # no floor for the full transformation: NaN, keys kept
        assert math.isnan(got.stats["noise_floor"])


def test_position_only_ground_truth(tmp_path):
    """A prism's positions as ground truth: the APE of the compared points is saved; a
    rotation relation is refused and leaves no file."""
    rng = np.random.default_rng(5)
    t, p, R = smooth_truth(400)
    lever = np.array([0.1, -0.05, 0.3])
    prism = p + np.einsum("nij,j->ni", R, lever)
    cov = np.tile(np.diag([2e-3, 2e-3, 3e-3]) ** 2, (len(t), 1, 1))
    noisy = prism + rng.normal(0.0, 2e-3, prism.shape)
    write_position_csv(tmp_path / "prism.csv", PositionTrajectory(t, noisy, cov))
    est = perturbed(t[::2], p[::2], R[::2], random_covariances(len(t[::2]), rng, 5e-3, 1e-3),
                    rng)
    write_tum(tmp_path / "est.tum", est)
    args = [str(tmp_path / "prism.csv"), str(tmp_path / "est.tum"), "--lever-arm",
            ",".join(str(v) for v in lever)]
    js = _evaluate([*args, "--save-results", str(tmp_path / "pos.zip")])
    res = file_interface.load_res_file(str(tmp_path / "pos.zip"), load_trajectories=True)
    for k in STATS:
        assert _close(res.stats[k], js["ape"]["translation_m"][k])
    assert _close(res.stats["noise_floor"], js["noise_floor"]["ape_translation_m"])
    assert _close(res.stats["nees_mean"], js["nees"]["position"]["mean"])
    assert res.info["ground_truth"].startswith("positions")
    direct = run_evaluation(tmp_path / "prism.csv", tmp_path / "est.tum", lever_arm=lever,
                          options=EvaluationOptions())
    np.testing.assert_array_equal(res.np_arrays["error_array"], direct.ape.translation_error)
    np.testing.assert_allclose(res.trajectories["est.tum"].positions_xyz, direct.est.position,
                               rtol=0, atol=1e-12)
    r = runner.invoke(app, ["evaluate", *args, "--pose-relation", "angle_deg",
                            "--save-results", str(tmp_path / "angle.zip")])
    assert r.exit_code != 0 and "no angle_deg" in r.output
    assert not (tmp_path / "angle.zip").exists()


def test_never_overwrites_a_file_rtsgt_did_not_write(campaign, tmp_path):
    """A user's file (evo's own zip, a note) is refused with or without --force and left as
    it was; rtsgt's own zip is replaced only with --force; nothing temporary is left."""
    d = campaign["dir"]
    args = [str(campaign["gt_dir"]), str(d / "est_a.tum")]
    user_zip = tmp_path / "evo_made.zip"
    with zipfile.ZipFile(user_zip, "w") as z:  # what evo writes: not rtsgt's
        z.writestr("info.json", json.dumps({"title": "x", "est_name": "mine"}))
        z.writestr("stats.json", "{}")
    note = tmp_path / "notes.zip"
    note.write_text("my notes\n")
    for target in (user_zip, note):
        before = target.read_bytes()
        for force in ([], ["--force"]):
            r = runner.invoke(app, ["evaluate", *args, "--save-results", str(target), *force])
            assert r.exit_code != 0, r.output
            assert "not an output of rtsgt" in r.output
            assert target.read_bytes() == before
    # an input of the command is never the target
    r = runner.invoke(app, ["evaluate", *args, "--save-results", str(d / "est_a.tum"),
                            "--force"])
    assert r.exit_code != 0 and "input" in r.output
    ours = tmp_path / "ours.zip"
    _evaluate([*args, "--save-results", str(ours)])
    first = ours.read_bytes()
    r = runner.invoke(app, ["evaluate", *args, "--save-results", str(ours)])
    assert r.exit_code != 0 and "--force" in r.output
    assert ours.read_bytes() == first
    _evaluate([str(campaign["gt_dir"]), str(d / "est_c.tum"), "--save-results", str(ours),
               "--force"])
    assert ours.read_bytes() != first
    assert file_interface.load_res_file(str(ours)).info["est_name"].endswith("est_c.tum")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["evo_made.zip", "notes.zip",
                                                         "ours.zip"]
