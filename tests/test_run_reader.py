"""The tables of a run directory, read with rtsgt.io._parse (one parsing stack): what
:func:`rtsgt.io.run_dir.read_table` and :func:`~rtsgt.io.run_dir.read_run` accept and
refuse, each error naming the file and the line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.io.run_dir import read_run, read_summary, read_table
from rtsgt.io.trajectory import write_covariance_csv
from rtsgt.record import RUN_SCHEMA_NAME, RUN_SCHEMA_VERSION
from test_analysis import make_run_data, write_run_dir


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_read_table_locates_columns_by_name_and_keeps_nan(tmp_path):
    p = _write(tmp_path, "a.csv", " t , x,range_m\n1.5,2,nan\n2.5, -1e-3 ,inf\n")
    header, data = read_table(p, ("x", "t"))
    assert header == ["t", "x", "range_m"]
    assert data[:, :2].tolist() == [[1.5, 2.0], [2.5, -1e-3]]
    assert np.isnan(data[0, 2]) and data[1, 2] == np.inf
    header, data = read_table(_write(tmp_path, "h.csv", "t,x\n"))
    assert header == ["t", "x"] and data.shape == (0, 2)


@pytest.mark.parametrize(
    ("text", "line", "match"),
    [
        ("t,x\n1,2\n3,x4\n", 3, r"b\.csv:3: not a number: expected a number in column 'x', "
                               r"got 'x4'"),
        ("t,x\n1,2\n3\n", 3, r"b\.csv:3: expected 2 ,-separated columns \(t x\), got 1"),
        ("t,x\n1,2\n\n3,4\n", 3, r"b\.csv:3: expected 2 ,-separated columns"),  # blank line
        ("t,x\n# note\n1,2\n", 2, r"b\.csv:2: expected 2 ,-separated columns"),  # no comments
        ("x,y\n1,2\n", 1, r"b\.csv:1: missing column\(s\) t; header is x,y"),
        ("\ufefft,x\n1,2\n", 1, r"missing column\(s\) t"),  # UTF-8 without BOM, as before
    ],
)
def test_read_table_errors_name_file_and_line(tmp_path, text, line, match):
    p = _write(tmp_path, "b.csv", text)
    with pytest.raises(InputError, match=match) as exc:
        read_table(p, ("t",))
    assert exc.value.path == str(p) and exc.value.line == line


def test_read_table_missing_and_empty_files(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        read_table(tmp_path / "none.csv")
    with pytest.raises(InputError, match="empty file, expected a header line"):
        read_table(_write(tmp_path, "e.csv", ""))
    (tmp_path / "bad.csv").write_bytes(b"t\n\xff\n")
    with pytest.raises(InputError, match="cannot decode the file as utf-8 text"):
        read_table(tmp_path / "bad.csv")


@pytest.fixture(scope="module")
def run_data():
    return make_run_data()


def test_run_files_read_back_and_their_errors(run_data, tmp_path):
    run = write_run_dir(run_data, tmp_path / "run")
    # rejected_poses.csv: blank lines skipped, a reason may be missing
    (run / "rejected_poses.csv").write_text("t,reason\n1.5,distance\n\n2.5\n")
    # groundtruth_covariance.csv through rtsgt.io.trajectory (shortest floats, same numbers)
    write_covariance_csv(run / "groundtruth_covariance.csv", run_data.groundtruth)
    data = read_run(run)
    assert data.rejected_t.tolist() == [1.5, 2.5]
    assert data.rejected_reason.tolist() == ["distance", ""]
    np.testing.assert_array_equal(data.groundtruth.cov, run_data.groundtruth.cov)
    np.testing.assert_array_equal(data.groundtruth.quat_xyzw, run_data.groundtruth.quat_xyzw)
    np.testing.assert_array_equal(data.reference_xyz, run_data.reference_xyz)

    (run / "rejected_poses.csv").write_text("t,reason\n1.5,distance\nabc,uncertainty\n")
    with pytest.raises(InputError, match=r"rejected_poses\.csv:3: .*column 't', got 'abc'"):
        read_run(run)
    (run / "rejected_poses.csv").write_text("")  # an empty file: no rejected pose
    assert read_run(run).rejected_t.size == 0

    ref = run / "reference.csv"
    lines = ref.read_text().splitlines()
    ref.write_text("\n".join([lines[0], lines[1].replace(",", ",y", 1), *lines[2:]]) + "\n")
    with pytest.raises(InputError, match=r"reference\.csv:2: expected a number in column 'x'"):
        read_run(run)


def _summary(folder: Path, doc) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "summary.json").write_text(json.dumps(doc), encoding="utf-8")
    return folder


def test_summary_without_schema_and_with_version_1_are_both_read(tmp_path):
    """read_summary is the one reader of summary.json: the layout before the schema key
    (version 0, with its older names) and version 1 give the same record."""
    current = {"deployment": "d", "software": {"name": "rtsgt", "version": "x"},
               "parameters": {"engine": "mc", "samples": 50, "seed": 7, "max_gap_s": 2.5,
                              "gp_noise": "all", "distance_gate_m": 0.2,
                              "uncertainty_gate_m": 0.3, "registration": "weighted"},
               "gates": {"uncertainty_measure": "trace"},
               "intervals_s": [[1.0, 2.0], [3.0, 4.0]],
               "prisms": {"1": {"station": 2, "qc_m2_s3": 0.5}, "2": {"qc_m2_s3": 0.25}},
               "reference": {"names": ["prism1", "prism2"], "frame": "world"},
               "calibration": {"reference_station": "1",
                               "stations": {"2": {"translation_m": [1, 2, 3]}},
                               "gcp_world": {"A": [1, 1, 1]}}}
    v1 = read_summary(_summary(tmp_path / "v1", {
        "schema": {"name": RUN_SCHEMA_NAME, "version": RUN_SCHEMA_VERSION}, **current}))
    v0 = read_summary(_summary(tmp_path / "v0", current))
    older = {k: v for k, v in current.items() if k not in ("deployment", "parameters")}
    older.update(name="d", options={"max_gap_s": 2.5, "distance_gate_m": 0.2,
                                    "uncertainty_gate_m": 0.3},
                 engine="mc", samples=50, seed=7, gp_noise="all", registration="weighted")
    old = read_summary(_summary(tmp_path / "old", older))
    assert (v1.schema_version, v0.schema_version, old.schema_version) == (1, 0, 0)
    for s in (v1, v0, old):
        assert s.exists and s.written_by_rtsgt and s.name == "d"
        o = s.options
        assert (o.pose.engine, o.pose.samples, o.seed, o.interpolation.gp_noise) == \
            ("mc", 50, 7, "all")
        assert o.pose.registration == "weighted"
        assert (o.interpolation.max_gap_s, o.pose.distance_gate_m, o.pose.uncertainty_gate_m) \
            == (2.5, 0.2, 0.3)
        assert s.uncertainty_measure == "trace"
        assert s.intervals_s.tolist() == [[1.0, 2.0], [3.0, 4.0]]
        assert s.prisms["1"].station == "2" and s.prisms["2"].station is None
        assert float(s.prisms["1"].qc_m2_s3) == 0.5
        assert s.reference_names == ("prism1", "prism2") and s.reference_frame == "world"
        assert s.stations["2"].tolist() == [1, 2, 3] and s.gcp_names == ("A",)
    # no file: the defaults
    none = read_summary(tmp_path / "empty")
    assert not none.exists and none.document == {} and none.options.pose.engine == "linear"
    # a run from before the weighted registration: the paper's unweighted fit
    assert none.options.pose.registration == "unweighted"
    del current["parameters"]["registration"]
    assert read_summary(_summary(tmp_path / "pre", current)).options.pose.registration == \
        "unweighted"
    assert none.options.interpolation.max_gap_s == 3.0 and none.intervals_s is None


@pytest.mark.parametrize(
    ("schema", "match"),
    [
        ({"name": RUN_SCHEMA_NAME, "version": RUN_SCHEMA_VERSION + 1},
         rf"summary schema version {RUN_SCHEMA_VERSION + 1} is newer than this rtsgt reads"),
        ({"name": "other", "version": 1}, r"'schema': expected"),
        ({"name": RUN_SCHEMA_NAME, "version": "1"}, r"'schema': expected"),
        ([1], r"'schema': expected"),
    ],
)
def test_summary_of_an_unknown_schema_is_refused_naming_the_file(run_data, tmp_path, schema,
                                                                   match):
    run = write_run_dir(run_data, tmp_path / "run")
    doc = json.loads((run / "summary.json").read_text())
    read_run(run)  # the older layout of the fixture reads
    (run / "summary.json").write_text(json.dumps({"schema": schema, **doc}))
    for read in (read_summary, read_run):
        with pytest.raises(InputError, match=match) as exc:
            read(run)
        assert exc.value.path == str(run / "summary.json")
    (run / "summary.json").write_text(json.dumps(
        {"schema": {"name": RUN_SCHEMA_NAME, "version": 1}, **doc}))
    data = read_run(run)
    assert data.schema_version == 1 and data.options.pose.engine == run_data.options.pose.engine
