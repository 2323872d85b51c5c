"""`rtsgt calibrate` on the real excerpt, the packaged example and bad input."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from _paths import EXCERPT
from rtsgt.cli.main import app
from rtsgt.geometry.transform import perturbation
from rtsgt.io.gcp_csv import write_gcp_csv
from rtsgt.io.rts_project import read_gcp_rts_project

GCP = EXCERPT / "GCP.txt"
runner = CliRunner()


def real_gcp() -> str:
    return str(GCP)


def invoke_json(*args) -> dict:
    result = runner.invoke(app, ["calibrate", *args, "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def test_json_on_real_gcp():
    out = invoke_json(real_gcp(), "--samples", "300")
    assert out["reference_station"] == 1
    assert set(out["stations"]) == {"2", "3"}
    s2, s3 = out["stations"]["2"], out["stations"]["3"]
    assert s2["yaw_deg"] == pytest.approx(159.94, abs=0.05)
    assert s3["yaw_deg"] == pytest.approx(1.99, abs=0.05)
    np.testing.assert_allclose(s2["translation_m"], [-0.659, -1.301, 0.286], atol=0.005)
    np.testing.assert_allclose(s3["translation_m"], [0.873, -2.433, 0.000], atol=0.005)
    T = np.array(s2["matrix"])
    assert T.shape == (4, 4)
    np.testing.assert_allclose(T[:3, 3], s2["translation_m"])
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    assert np.degrees(np.arctan2(T[1, 0], T[0, 0])) == pytest.approx(s2["yaw_deg"])
    C = np.array(s2["covariance"])
    assert C.shape == (6, 6) and np.all(np.linalg.eigvalsh(C) > 0)
    np.testing.assert_allclose(np.sqrt(np.diag(C))[:3] * 1e3, s2["sigma_translation_mm"])
    res = out["residuals_mm"]
    assert res["count"] == 36
    assert res["median"] == pytest.approx(1.90, abs=0.1)
    assert res["max"] == pytest.approx(8.25, abs=0.1)
    assert len(out["residuals"]) == 36 and out["samples"] == 300 and out["seed"] == 0
    assert out["weighting"] == "none"
    # the generalised least squares: the angles fix the stations across the lines of sight
    gls = invoke_json(real_gcp(), "--samples", "300", "--weighting", "gls")
    assert gls["weighting"] == "gls"
    for s in ("2", "3"):
        assert np.all(np.array(gls["stations"][s]["sigma_translation_mm"][:2])
                      < 0.5 * np.array(out["stations"][s]["sigma_translation_mm"][:2]))


def test_json_is_reproducible_from_the_seed():
    a = invoke_json(real_gcp(), "--samples", "100")
    b = invoke_json(real_gcp(), "--samples", "100", "--seed", "0")
    c = invoke_json(real_gcp(), "--samples", "100", "--seed", "1")
    assert a == b
    assert a["stations"]["2"]["covariance"] != c["stations"]["2"]["covariance"]
    assert a["stations"]["2"]["matrix"] == c["stations"]["2"]["matrix"]  # the fit is not random


def test_table_output():
    result = runner.invoke(app, ["calibrate", real_gcp(), "--samples", "100"])
    assert result.exit_code == 0, result.output
    assert "159.9362" in result.stdout and "1.9889" in result.stdout
    assert "median 1.90 mm" in result.stdout and "max 8.25 mm" in result.stdout
    assert "100 Monte Carlo samples" in result.stdout


def test_csv_format_and_additive_constant(tmp_path):
    csv_path = tmp_path / "gcp.csv"
    write_gcp_csv(csv_path, read_gcp_rts_project(real_gcp()))
    ref = invoke_json(real_gcp(), "--samples", "0")
    out = invoke_json(str(csv_path), "--format", "csv", "--additive-constant", "0.01",
                      "--samples", "0")
    assert out["stations"] == ref["stations"]
    assert ref["stations"]["2"]["covariance"] is None
    # the csv default constant is 0, so the fit moves by a few tenths of a mm
    raw = invoke_json(str(csv_path), "--samples", "0")
    d = np.subtract(raw["stations"]["2"]["translation_m"], ref["stations"]["2"]["translation_m"])
    assert 1e-5 < np.abs(d).max() < 0.02


def test_reference_station_option():
    out = invoke_json(real_gcp(), "--reference-station", "2", "--samples", "0")
    assert out["reference_station"] == 2 and set(out["stations"]) == {"1", "3"}
    assert out["stations"]["1"]["yaw_deg"] == pytest.approx(-159.94, abs=0.05)


def _example_module():
    spec = importlib.util.spec_from_file_location(
        "make_example_gcp", Path(__file__).with_name("make_example_gcp.py")
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_packaged_example_is_the_generator_output(tmp_path):
    gen = _example_module()
    out = tmp_path / "example.txt"
    gen.main(["make", str(out)])
    packaged = resources.files("rtsgt").joinpath("data").joinpath("example_gcp.txt").read_text()
    assert out.read_text() == packaged


def test_example_recovers_the_generator_truth():
    gen = _example_module()
    out = invoke_json("example", "--samples", "2000")
    assert set(out["stations"]) == {"2", "3"} and out["residuals_mm"]["count"] == 24
    for s, st in out["stations"].items():
        R, t = gen.truth_transform(s)
        C = np.array(st["covariance"])
        # error of the fit, left perturbation about the estimate, within chi-square(6) 99.9 %
        T = np.array(st["matrix"])
        xi = perturbation(T[:3, :3], T[:3, 3], R, t)
        assert xi @ np.linalg.solve(C, xi) < 22.46
        assert st["yaw_deg"] == pytest.approx(gen.TRUTH[s][0], abs=0.01)


def test_bad_input_errors():
    result = runner.invoke(app, ["calibrate", "/nonexistent/GCP.txt"])
    assert result.exit_code == 1
    assert result.stderr.startswith("error: ")
    assert "/nonexistent/GCP.txt: file not found" in result.stderr
    result = runner.invoke(app, ["calibrate", real_gcp(), "--reference-station", "9"])
    assert result.stderr.startswith("error: ")
    assert "unknown reference station '9'" in result.stderr
    assert "1, 2, 3" in result.stderr
    result = runner.invoke(app, ["calibrate", real_gcp(), "--format", "leica"])
    assert result.stderr.startswith("error: ")
    result = runner.invoke(app, ["calibrate", real_gcp(), "--samples", "1"])
    assert result.exit_code == 2 and "--samples" in result.output


def test_collinear_file_error(tmp_path):
    p = tmp_path / "GCP.txt"
    lines = ["theodolite_number , marker_number , status , elevation , azimuth , distance , "
             "sec , nsec"]
    for s, hz0 in (("1", 0.3), ("2", 1.3)):
        for m, d in enumerate((5.0, 10.0, 20.0, 40.0), start=1):
            lines.append(f"{s} , {m} , 0 , 1.5707963 , {hz0} , {d} , 1 , 0")
    p.write_text("\n".join(lines) + "\n")
    result = runner.invoke(app, ["calibrate", str(p)])
    assert result.exit_code == 1 and result.stderr.startswith("error: ")
    assert "collinear" in result.stderr


def _rtsgt_executable() -> str:
    exe = Path(sys.executable).with_name("rtsgt")
    found = str(exe) if exe.exists() else shutil.which("rtsgt")
    if found is None:
        pytest.skip("the rtsgt console script is not installed")
    return found


def test_console_script_json_and_error():
    exe = _rtsgt_executable()
    proc = subprocess.run(
        [exe, "calibrate", real_gcp(), "--samples", "200", "--json"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)  # exactly one JSON object on stdout
    assert out["stations"]["2"]["yaw_deg"] == pytest.approx(159.94, abs=0.05)
    assert out["residuals_mm"]["count"] == 36
    proc = subprocess.run(
        [exe, "calibrate", real_gcp(), "--reference-station", "9"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 1
    assert proc.stderr.startswith("error: ") and "unknown reference station '9'" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_the_gcp_fit_check_is_shown_and_written(tmp_path):
    """Issue 26: the variance factor per station and the variance components added were in the
    API only; now in the table (as `rtsgt run`'s summary has them) and in the JSON / --out."""
    out = tmp_path / "cal.json"
    r = runner.invoke(app, ["calibrate", real_gcp(), "--samples", "0", "-o", str(out)])
    assert r.exit_code == 0, r.output
    text = " ".join(r.stdout.split())
    fit = json.loads(out.read_text())["gcp_fit"]
    assert set(fit["stations"]) == {"2", "3"}
    for s, v in fit["stations"].items():
        lo, hi = v["interval_95"]
        assert lo < 1 < hi and v["dof"] == 30
        # the excerpt's GCP residuals are far above the instrument model (z above all)
        assert v["variance_factor"] > hi and v["verdict"] == "optimistic"
        assert (f"self-check GCP fit, station {s}: variance factor {v['variance_factor']:.2f}, "
                f"95 % [{lo:.2f}, {hi:.2f}]: optimistic") in text
    added = fit["added_shot_sigma_mm"]
    assert added["horizontal"] == 0 and 0.5 < added["vertical"] < 2
    assert (f"added per shot 0.00 mm horizontal, {added['vertical']:.2f} mm vertical"
            in text)


def test_a_deployment_folder_is_taken_for_its_toml(tmp_path):
    """`rtsgt calibrate FOLDER` (and --dynamic): the folder's deployment.toml; a folder without
    one is one error line naming it."""
    folder = EXCERPT.parent
    a = invoke_json(str(folder), "--samples", "10")
    b = invoke_json(str(folder / "deployment.toml"), "--samples", "10")
    assert a == b and a["source"].endswith("deployment.toml")
    assert set(a["gcp_fit"]["stations"]) == {"2", "3"}
    r = runner.invoke(app, ["calibrate", str(tmp_path), "--dynamic"])
    assert r.exit_code == 1 and "Traceback" not in r.output
    assert r.stderr.splitlines() == [
        f"error: {tmp_path}: a folder without deployment.toml: give the deployment's TOML, or "
        "write one with `rtsgt init FOLDER` (an RTS_project-like folder)"]
