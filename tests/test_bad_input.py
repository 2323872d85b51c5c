"""Bad input across the foundation (issue 2): clear errors naming the file and line or value,
and nothing half-written.

Reader-level cases (NaN or negative distances, zenith outside (0, pi), wrong column counts,
empty files, duplicated or decreasing timestamps) are tested with each reader
(tests/test_io_*.py) and the noise engines (tests/test_noise_model.py); the calibration's
geometry (fewer than 3 common markers, collinear markers, markers shot by one station) in
tests/test_calibration.py. This file covers what crosses module boundaries: the GCP file named
in geometry errors, a tracked station missing from the GCP file, and ``rtsgt calibrate --out``
(refused before any work, atomic, never a partial or stale file).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from typer.testing import CliRunner

from _paths import EXAMPLE_TOML as EXAMPLE
from _paths import EXCERPT
from rtsgt.calibration import calibrate
from rtsgt.cli import calibrate as calibrate_cli
from rtsgt.cli.main import app
from rtsgt.errors import ConfigError, GeometryError
from rtsgt.io.rts_project import read_gcp_rts_project

runner = CliRunner()
HEADER = "theodolite_number , marker_number , status , elevation , azimuth , distance , sec , nsec"


def gcp_file(path: Path, markers_of_station: dict[str, list[tuple[float, float, float]]]) -> Path:
    """An RTS_project GCP file: ``{station: [(zenith, hz, d) per marker 1, 2, ...]}``."""
    lines = [HEADER]
    for s, shots in markers_of_station.items():
        for m, (v, hz, d) in enumerate(shots, start=1):
            lines.append(f"{s} , {m} , 0 , {v} , {hz} , {d} , 1 , 0")
    path.write_text("\n".join(lines) + "\n")
    return path


def collinear_gcp(tmp_path: Path) -> Path:
    line = [(1.5707963, 0.3, d) for d in (5.0, 10.0, 20.0, 40.0)]
    return gcp_file(tmp_path / "GCP.txt", {"1": line, "2": [(v, h + 1.0, d) for v, h, d in line]})


# ---------------------------------------------------------------- geometry errors name the file

def test_geometry_errors_name_the_gcp_file(tmp_path):
    p = collinear_gcp(tmp_path)
    with pytest.raises(GeometryError, match="collinear") as info:
        calibrate(read_gcp_rts_project(p), samples=0)
    assert str(info.value).startswith(f"{p}: station 2: markers 1, 2, 3, 4")
    two = [(1.5, 0.3, 5.0), (1.6, 1.3, 9.0)]
    p = gcp_file(tmp_path / "two.txt", {"1": two, "2": two})
    with pytest.raises(GeometryError, match=r"shares 2 valid marker\(s\) .* \(1, 2\)") as info:
        calibrate(read_gcp_rts_project(p), samples=0)
    assert str(info.value).startswith(f"{p}: station 2 ")


# ---------------------------------------------------------------- a tracked station without GCP

def test_tracked_station_missing_from_the_gcp_file(tmp_path):
    from rtsgt.io.deployment import load_deployment

    # the copy lives elsewhere, so its data paths become absolute
    text = EXAMPLE.read_text().replace('"data/', f'"{EXCERPT}/')
    text = text.replace('id = "3"', 'id = "4"')  # GCP.txt has stations 1, 2, 3
    cfg = tmp_path / "deployment.toml"
    cfg.write_text(text)
    with pytest.raises(ConfigError, match=r"\[\[stations\]\] '4': no valid shot in the GCP file "
                       r".*GCP.txt \(stations there: 1, 2, 3\)") as info:
        load_deployment(cfg)
    assert info.value.path == str(cfg)


# ---------------------------------------------------------------- rtsgt calibrate --out

def test_calibrate_out_writes_the_json_object(tmp_path):
    out = tmp_path / "calibration.json"
    result = runner.invoke(app, ["calibrate", "example", "--samples", "50", "--json",
                                 "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert json.loads(out.read_text()) == json.loads(result.stdout)
    assert sorted(os.listdir(tmp_path)) == ["calibration.json"]  # no temporary left
    table = runner.invoke(app, ["calibrate", "example", "--samples", "50", "-o", str(out)])
    assert table.exit_code == 0 and f"written: {out}" in table.stdout.replace("\n", "")


def test_calibrate_out_is_refused_before_any_work(tmp_path, monkeypatch):
    def must_not_run(*args, **kwargs):
        raise AssertionError("calibrated before checking --out")

    monkeypatch.setattr(calibrate_cli, "run_calibrate", must_not_run)
    missing = tmp_path / "no" / "such" / "dir" / "calibration.json"
    result = runner.invoke(app, ["calibrate", "example", "--out", str(missing)])
    assert result.exit_code == 1 and result.stderr.startswith("error: ")
    assert result.stderr.startswith(f"error: {missing}: cannot write: the directory")
    result = runner.invoke(app, ["calibrate", "example", "--out", str(tmp_path)])
    assert result.stderr.startswith("error: ")
    assert "--out names a directory" in result.stderr
    assert not (tmp_path / "no").exists()


def test_failed_calibration_leaves_no_file_and_keeps_the_previous_one(tmp_path):
    out = tmp_path / "calibration.json"
    bad = collinear_gcp(tmp_path)
    result = runner.invoke(app, ["calibrate", str(bad), "--out", str(out)])
    assert result.exit_code == 1 and result.stderr.startswith("error: ")
    assert not out.exists()
    good = runner.invoke(app, ["calibrate", "example", "--samples", "0", "--out", str(out)])
    assert good.exit_code == 0, good.output
    previous = out.read_text()
    result = runner.invoke(app, ["calibrate", str(bad), "--json", "--out", str(out)])
    assert result.exit_code == 1 and result.stdout == ""  # no partial JSON on stdout either
    assert "collinear" in result.stderr
    assert out.read_text() == previous
    assert sorted(os.listdir(tmp_path)) == ["GCP.txt", "calibration.json"]


def test_failed_write_leaves_no_partial_file(tmp_path, monkeypatch):
    import rtsgt.io._parse as parse

    def disk_full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(parse.os, "fsync", disk_full)
    out = tmp_path / "calibration.json"
    result = runner.invoke(app, ["calibrate", "example", "--samples", "0", "--out", str(out)])
    assert result.exit_code == 1 and result.stderr.startswith("error: ")
    assert result.stderr == f"error: {out}: cannot write: No space left on device\n"
    assert os.listdir(tmp_path) == []
