"""The tables of a run directory, read with rtsgt.io._parse (one parsing stack): what
:func:`rtsgt.io.run_reader.read_table` and :func:`~rtsgt.io.run_reader.read_run` accept and
refuse, each error naming the file and the line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.io.run_reader import read_run, read_table
from rtsgt.io.trajectory import write_covariance_csv
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
