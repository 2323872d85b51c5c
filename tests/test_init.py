"""``rtsgt init``: an RTS_project deployment folder as it is, and ``sensor_positions.csv``.

The folder is built by each test from the repository's excerpt, copied into the nested layout
of the RTS_project's ``data/<date>/`` (with the static stretches, the reference code's sorted
weather file and the excerpt's other files beside the inputs, as the real folder has them).
Then:

- ``rtsgt init`` writes a TOML whose ``rtsgt run`` gives the hand-written example's ground
  truth file for file (same seed); its processing tables read back as rtsgt's defaults;
- each missing input is one ``missing:`` line, and nothing is written while a required one
  is missing; an existing TOML is replaced only with ``--force`` and only if init wrote it;
- ``sensor_positions.csv``: read as written (its rows 1-6 are the survey's points), selectable
  as ``format = "sensor-positions"`` (init takes it without ``calibration_raw.csv``), its
  defects warned about where the reference uses them, and a bad line is one error line
  naming the file and the line.
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from _paths import EXAMPLE_TOML, EXCERPT
from rtsgt.cli.main import app
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.filtering import FilterParams
from rtsgt.io.config import load_config, options_toml_text, read_options, tomllib
from rtsgt.io.deployment import load_deployment, read_reference
from rtsgt.io.project_folder import INIT_MARK, scan_folder
from rtsgt.io.survey import read_sensor_positions, read_survey_raw
from rtsgt.measurement.instruments import instrument_from_config
from rtsgt.noise import NoiseModel
from rtsgt.options import RunOptions

runner = CliRunner()

#: Where each excerpt file goes in an RTS_project ``data/<date>/`` folder.
LAYOUT = {
    "GCP.txt": "total_stations/GCP.txt",
    "prism1.csv": "uncertainty/raw_data/prism1.csv",
    "prism2.csv": "uncertainty/raw_data/prism2.csv",
    "prism3.csv": "uncertainty/raw_data/prism3.csv",
    "static/prism1.csv": "uncertainty/static_raw_data/prism1.csv",
    "static/prism2.csv": "uncertainty/static_raw_data/prism2.csv",
    "calibration_raw.csv": "sensors_extrinsic_calibration/calibration_raw.csv",
    "calibration_results.csv": "sensors_extrinsic_calibration/calibration_results.csv",
    "sensor_positions.csv": "sensors_extrinsic_calibration/sensor_positions.csv",
    "weather_ECCC_raw_excerpt.csv": "weather/fr_climat_horaires_QC_7042395_11-2022_P1H.csv",
    "weather_sorted_excerpt.txt": "weather/data_sorted_2022.txt",
}


def rts_folder(tmp_path: Path, leave_out: tuple[str, ...] = ()) -> Path:
    """An RTS_project-like ``20221110/`` folder of the excerpt's files, less ``leave_out``."""
    root = tmp_path / "20221110"
    for src, dst in LAYOUT.items():
        if src in leave_out:
            continue
        p = root / dst
        p.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(EXCERPT / src, p)
    return root


def init(*args: str):
    return runner.invoke(app, ["init", *map(str, args)])


def lines(result, kind: str) -> list[str]:
    return [s for s in result.output.splitlines() if s.startswith(f"{kind}: ")]


def test_init_gives_the_run_of_the_hand_written_example(tmp_path):
    folder = rts_folder(tmp_path)
    r = init(folder)
    assert r.exit_code == 0, r.output
    toml = folder / "deployment.toml"
    assert toml.read_text().startswith(INIT_MARK)
    assert f"wrote: {toml}" in r.output
    assert not lines(r, "missing") and len(lines(r, "found")) == 5
    # the raw survey, not the Cartesian one, and say so; the sorted weather file is no input
    assert any("sensor_positions.csv" in s for s in lines(r, "note"))
    cfg, ex = load_config(toml), load_config(EXAMPLE_TOML)
    assert cfg.weather.file.name.startswith("fr_climat_horaires")
    assert [s.file.name for s in cfg.stations] == [s.file.name for s in ex.stations]
    assert cfg.options == ex.options

    out_init, out_ex = tmp_path / "run-init", tmp_path / "run-example"
    for cfg_path, out in ((toml, out_init), (EXAMPLE_TOML, out_ex)):
        r = runner.invoke(app, ["run", str(cfg_path), "-o", str(out), "--engine", "linear",
                                "-q"])
        assert r.exit_code == 0, r.output
    for name in ("groundtruth.tum", "groundtruth_covariance.csv", "groundtruth_shared.csv",
                 "rejected_poses.csv", "reference.csv", "prisms/prism1.csv",
                 "measurements/prism3.csv", "measurements/removed.csv"):
        assert (out_init / name).read_bytes() == (out_ex / name).read_bytes(), name


def test_processing_tables_read_back_as_written():
    ins = instrument_from_config({"profile": "leica-ms60"})
    for opts in (RunOptions(), RunOptions().updated(
            engine="linear", samples=77, qc=0.25, prior="select", rate_hz=10.0,
            correlated_noise="inflate", registration="unweighted",
            filter=FilterParams(tau_a=np.radians(2.5)))):
        text = options_toml_text(opts, ins)
        back, _ = read_options(Path("x.toml"), tomllib.loads(text), ins)
        want = opts if opts.noise is not None else opts.updated(noise=NoiseModel(instrument=ins))
        assert back == want


def test_a_flat_folder_and_a_toml_written_elsewhere(tmp_path):
    """The excerpt's own flat data/ folder: init finds the same inputs (the static
    stretches in static/ are not the tracked prisms) and the paths are relative to --out."""
    out = tmp_path / "cfg" / "flat.toml"
    out.parent.mkdir()
    r = init(EXCERPT, "--out", out, "--name", "flat")
    assert r.exit_code == 0, r.output
    cfg, ex = load_config(out), load_config(EXAMPLE_TOML)
    assert cfg.name == "flat"
    assert [s.file for s in cfg.stations] == [s.file for s in ex.stations]
    assert (cfg.gcp, cfg.weather, cfg.reference) == (ex.gcp, ex.weather, ex.reference)
    assert '"../' in out.read_text()


def test_each_missing_input_is_one_line_and_nothing_is_written(tmp_path):
    folder = rts_folder(tmp_path, leave_out=("GCP.txt", "calibration_raw.csv",
                                             "sensor_positions.csv"))
    r = init(folder)
    assert r.exit_code == 1
    missing = lines(r, "missing")
    assert len(missing) == 2, missing
    assert "total_stations/GCP.txt" in missing[0] and "calibration_raw.csv" in missing[1]
    assert r.output.strip().splitlines()[-1] == (
        f"error: {folder / 'deployment.toml'}: not written: 2 required input(s) missing "
        "(the 'missing:' lines above)")
    assert not (folder / "deployment.toml").exists()

    empty = tmp_path / "empty"
    empty.mkdir()
    r = init(empty)
    assert r.exit_code == 1
    missing = lines(r, "missing")
    for m, start in zip(missing, ("GCP shots", "measurements", "survey of the robot",
                                  "calibration_results.csv", "weather"), strict=True):
        assert m.startswith(f"missing: {start}"), m
    assert missing[-1].endswith("(optional)") and "--weather FILE" in missing[-1]
    assert "Traceback" not in r.output


def test_optional_inputs_missing_still_give_a_toml(tmp_path):
    folder = rts_folder(tmp_path, leave_out=("weather_ECCC_raw_excerpt.csv",
                                             "calibration_results.csv"))
    r = init(folder)
    assert r.exit_code == 0, r.output
    assert len(lines(r, "missing")) == 2
    assert load_config(folder / "deployment.toml").weather is None
    # the weather given on the command line, and its UTC offset
    r = init(folder, "--force", "--weather", EXCERPT / "weather_ECCC_raw_excerpt.csv",
             "--utc-offset", "-4")
    assert r.exit_code == 0, r.output
    cfg = load_config(folder / "deployment.toml")
    assert cfg.weather.format == "eccc" and cfg.weather.utc_offset_hours == -4.0
    r = init(folder, "--force", "--weather", EXCERPT / "weather_sorted_excerpt.txt")
    assert r.exit_code == 1 and "not a weather file" in r.output


def test_a_station_without_gcp_shots_is_missing(tmp_path):
    folder = rts_folder(tmp_path)
    p = folder / "total_stations/GCP.txt"
    p.write_text("".join(x for x in p.read_text().splitlines(keepends=True)
                         if not x.startswith("3 ")))
    r = init(folder)
    assert r.exit_code == 1
    assert lines(r, "missing") == [
        "missing: GCP shots of station 3 (it tracks prism3.csv; total_stations/GCP.txt has "
        "valid shots of stations 1, 2)"]


def test_an_existing_toml_is_replaced_only_with_force_and_only_if_init_wrote_it(tmp_path):
    folder = rts_folder(tmp_path)
    toml = folder / "deployment.toml"
    toml.write_text("# my own\n")
    for args in ((), ("--force",)):
        r = init(folder, *args)
        assert r.exit_code == 1, r.output
        assert toml.read_text() == "# my own\n"
    assert "use --force" in init(folder).output
    toml.unlink()
    assert init(folder).exit_code == 0
    first = toml.read_text()
    r = init(folder)
    assert r.exit_code == 1 and toml.read_text() == first
    r = init(folder, "--force", "--name", "again")
    assert r.exit_code == 0 and load_config(toml).name == "again"
    assert not [p for p in folder.iterdir() if p.name.startswith(".")]  # no temporary left


def test_sensor_positions_as_written_with_its_defects():
    """The real file: 10 rows, rows 1-6 the survey's points, rows 7-10 zero covariances, row 9
    a flag of 11 (examples/rts_20221110/data/SOURCE.md)."""
    sp = read_sensor_positions(EXCERPT / "sensor_positions.csv")
    survey = read_survey_raw(EXCERPT / "calibration_raw.csv")
    assert len(sp) == 10 and sp.names[:4] == ("prism1", "prism2", "prism3", "gnss1")
    np.testing.assert_allclose(sp.xyz[:6], survey.xyz[:6], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(sp.flag, [1, 1, 1, 1, 1, 1, 1, 1, 11, 1])
    assert not np.any(sp.cov[6:]) and np.all(np.diagonal(sp.cov[:6], axis1=1, axis2=2) > 0)
    # the file's own covariance: about 2 mm on z, almost nothing across (not the survey's)
    sig = np.sqrt(np.diagonal(sp.cov[:6], axis1=1, axis2=2))
    assert np.all((sig[:, 2] > 1.9e-3) & (sig[:, 2] < 2.2e-3) & (sig[:, 0] < 1e-6))


def _sensor_positions_deployment(tmp_path: Path, extra: str = "") -> Path:
    folder = rts_folder(tmp_path, leave_out=("calibration_raw.csv",))
    r = init(folder)
    assert r.exit_code == 0, r.output
    toml = folder / "deployment.toml"
    text = toml.read_text()
    assert 'format = "sensor-positions"' in text
    if extra:
        text = text.replace("body_points = [4, 5, 6]", extra)
        toml.write_text(text)
    return toml


def test_sensor_positions_is_a_reference_format(tmp_path):
    toml = _sensor_positions_deployment(tmp_path)
    cfg = load_config(toml)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # rows 1-6 are fine: no warning
        ref = read_reference(cfg)
    # the same prisms as the survey's, in the frame of the same GNSS antennas
    ex = read_reference(load_config(EXAMPLE_TOML))
    np.testing.assert_allclose(ref.xyz, ex.xyz, rtol=0, atol=1e-12)
    assert not np.allclose(ref.cov, ex.cov)  # ... with the file's covariances


def test_sensor_position_defects_are_warned_where_the_reference_uses_them(tmp_path):
    toml = _sensor_positions_deployment(tmp_path, extra="body_points = [7, 9, 10]")
    cfg = load_config(toml)
    with pytest.warns(RtsgtWarning) as caught:
        read_reference(cfg)
    text = [str(w.message) for w in caught]
    path = cfg.reference.file
    assert sum("zero covariance" in t for t in text) == 3
    assert any(t.startswith(f"{path}:9: flag 11 for lidar3") for t in text), text


@pytest.mark.parametrize("line, message", [
    ("1 2 3 1 0 0 0 0 0 0 0 0", "expected 13 whitespace-separated columns"),
    ("1 2 3 1 1e-6 0 0 0 1e-6 0 x 0 1e-6", "expected a number in column 'cov_zx', got 'x'"),
    ("1 2 3 1 1e-6 0 0 0 1e-6 0 0 0 nan", "expected a finite number in column 'cov_zz'"),
    ("1 2 3 1 1e-6 5e-7 0 0 1e-6 0 0 0 1e-6", "expected a symmetric covariance"),
    ("1 2 3 1 1e-6 2e-6 0 2e-6 1e-6 0 0 0 1e-6", "expected a positive semi-definite"),
    ("1 2 3 1 -1e-6 0 0 0 1e-6 0 0 0 1e-6", "expected non-negative variances"),
])
def test_a_bad_sensor_positions_line_is_one_error_naming_file_and_line(tmp_path, line, message):
    toml = _sensor_positions_deployment(tmp_path)
    p = load_config(toml).reference.file
    rows = p.read_text().splitlines()
    rows[4] = line
    p.write_text("\n".join(rows) + "\n")
    with pytest.raises(InputError) as info:
        load_deployment(toml)
    assert str(info.value).startswith(f"{p}:5: ") and message in str(info.value)
    r = runner.invoke(app, ["run", str(toml), "-o", str(tmp_path / "run"), "-q"])
    assert r.exit_code == 1
    assert r.output.strip().splitlines() == [f"error: {p}:5: " + info.value.bare_message]


def test_a_raw_bag_is_taken_rather_than_the_prism_files(tmp_path):
    pytest.importorskip("rosbags")
    from test_io_rts_bag import excerpt, messages, write_bag

    folder = rts_folder(tmp_path)
    bag = write_bag(folder / "total_stations" / "2022-11-10-10-43-57.bag", True,
                    messages(excerpt(5.0)))
    r = init(folder)
    assert r.exit_code == 0, r.output
    assert any("uncertainty/raw_data" in s for s in lines(r, "note"))
    cfg = load_config(folder / "deployment.toml")
    assert cfg.measurements.file == bag
    assert [(s.id, s.prism, s.theodolite_id) for s in cfg.stations] == [
        ("1", "1", 1), ("2", "2", 2), ("3", "3", 3)]
    assert [s.additive_constant_m for s in cfg.stations] == [0.01] * 3
    # the prism files on request
    scan = scan_folder(folder, measurements="prisms")
    assert scan.bag is None and list(scan.prism_files) == ["1", "2", "3"]
    # two bags: which one is this deployment's? say so
    shutil.copyfile(bag, folder / "other.bag")
    r = init(folder, "--force")
    assert r.exit_code == 1
    assert any("2 raw bags" in s for s in lines(r, "missing"))


def test_a_one_prism_folder_without_a_survey_gives_a_toml_that_runs(tmp_path):
    """Issue 26: init refused a one-prism folder without a survey, which a one-prism run does
    not read (positions only): init accepts what run accepts."""
    folder = tmp_path / "20221110"
    for src in ("GCP.txt", "prism1.csv"):
        p = folder / LAYOUT[src]
        p.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(EXCERPT / src, p)
    r = init(folder)
    assert r.exit_code == 0, r.output
    survey = [s for s in lines(r, "missing") if "survey of the robot" in s]
    assert len(survey) == 1 and survey[0].endswith("(optional)"), survey
    toml = folder / "deployment.toml"
    assert "\n[reference]" not in toml.read_text()
    cfg = load_config(toml)
    assert cfg.reference is None and [s.id for s in cfg.stations] == ["1"]
    out = tmp_path / "run"
    r = runner.invoke(app, ["run", str(folder), "-o", str(out), "--engine", "linear", "-q"])
    assert r.exit_code == 0, r.output
    assert (out / "prisms" / "prism1.csv").is_file() and not (out / "groundtruth.tum").exists()
    # three prisms still need the survey
    r = init(rts_folder(tmp_path / "three", leave_out=("calibration_raw.csv",
                                                       "sensor_positions.csv")))
    assert r.exit_code == 1
    assert [s for s in lines(r, "missing") if "survey of the robot" in s][0].endswith(
        "needed for the poses)")
