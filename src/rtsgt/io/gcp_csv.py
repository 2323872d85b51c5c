"""The native rtsgt CSV format of ground control point (GCP) shots, and the reader of every
GCP format (:func:`read_gcp_shots`): a header naming the columns ``station``, ``marker``,
``hz_rad``, ``v_rad`` (zenith), ``d_m`` (without the additive constant), optional ``t_s`` and
``status``, in any order, angles also in deg or gon. :func:`write_gcp_csv` writes floats in
their shortest exact form, so reading back gives the same arrays.
docs/file-formats.md#gcp-files.
"""

from __future__ import annotations

import csv
import io
from os import PathLike

import numpy as np

from rtsgt.choices import GCP_FORMATS  # understood by read_gcp_shots
from rtsgt.errors import InputError
from rtsgt.io._parse import (
    atomic_write_text,
    check_distance,
    check_seconds,
    check_zenith,
    find_columns,
    fmt_float,
    numbered_lines,
    read_text,
    to_float,
    to_int,
)
from rtsgt.io.rts_project import read_gcp_rts_project
from rtsgt.measurement.units import to_radians
from rtsgt.types import GcpShots

#: Columns written by :func:`write_gcp_csv`, in order.
GCP_CSV_COLUMNS = ("station", "marker", "hz_rad", "v_rad", "d_m", "t_s", "status")

#: Angle units accepted in the column names (``hz_deg``, ``v_gon``, ...).
_ANGLE_UNITS = ("rad", "deg", "gon")


def _angle_column(pos: dict[str, int], header: list[str], name: str, path, number) -> tuple:
    found = [(unit, f"{name}_{unit}") for unit in _ANGLE_UNITS if f"{name}_{unit}" in pos]
    if len(found) != 1:
        options = " or ".join(f"{name}_{u}" for u in _ANGLE_UNITS)
        got = "none" if not found else ", ".join(c for _, c in found)
        raise InputError(
            f"expected exactly one column {options}; found {got} in header {','.join(header)}",
            path, number,
        )
    unit, column = found[0]
    return column, unit


def read_gcp_csv(path: str | PathLike, *, additive_constant: float = 0.0) -> GcpShots:
    """Read GCP shots in the native CSV format into :class:`~rtsgt.types.GcpShots` (rad, raw m,
    ``lines`` 1-based), ``additive_constant`` (m) stored apart. Bad lines (columns, identifiers,
    numbers; for valid shots non-finite values, distance <= 0, zenith outside (0, pi)) raise
    :class:`~rtsgt.errors.InputError` naming the file and line."""
    c = float(additive_constant)
    if not np.isfinite(c):
        raise InputError(f"Expected a finite additive constant (m), got {additive_constant!r}")
    numbers, lines = numbered_lines(read_text(path))
    if not lines:
        raise InputError(
            f"empty file: expected a header ({','.join(GCP_CSV_COLUMNS)}) and GCP shots", path
        )
    rows = list(csv.reader(lines))
    header = [h.strip() for h in rows[0]]
    candidates = [f"{a}_{u}" for a in ("hz", "v") for u in _ANGLE_UNITS]
    pos = find_columns(
        header, ("station", "marker", "d_m"), path, numbers[0],
        optional=candidates + ["t_s", "status"],
    )
    hz_col, hz_unit = _angle_column(pos, header, "hz", path, numbers[0])
    v_col, v_unit = _angle_column(pos, header, "v", path, numbers[0])
    numbers, rows = numbers[1:], rows[1:]
    if not rows:
        raise InputError("no GCP shot after the header", path)
    for row, number in zip(rows, numbers, strict=True):
        if len(row) != len(header):
            raise InputError(
                f"expected {len(header)} comma-separated columns ({','.join(header)}), "
                f"got {len(row)}", path, number,
            )
    tokens = np.array([[s.strip() for s in row] for row in rows], dtype=object)

    def col(name):
        return tokens[:, [pos[name]]]

    for name in ("station", "marker"):
        empty = np.flatnonzero(col(name)[:, 0] == "")
        if empty.size:
            raise InputError(f"empty {name}", path, numbers[empty[0]])
    status = (
        to_int(col("status"), numbers, path, ("status",))[:, 0]
        if "status" in pos else np.zeros(len(rows), dtype=np.int64)
    )
    valid = status == 0
    values = to_float(
        np.hstack([col(hz_col), col(v_col), col("d_m")]), numbers, path,
        (hz_col, v_col, "d_m"), finite=valid,
    )
    hz = to_radians(values[:, 0], hz_unit)
    v = to_radians(values[:, 1], v_unit)
    d = values[:, 2]
    if "t_s" in pos:
        t_tok = col("t_s").copy()
        empty = t_tok == ""
        t_tok[empty] = "nan"
        t = to_float(t_tok, numbers, path, ("t_s",), finite=~empty[:, 0])[:, 0]
    else:
        t = np.full(len(rows), np.nan)
    check_seconds(t, numbers, path, "t_s")
    check_distance(d, numbers, path, where=valid)
    check_zenith(v, numbers, path, where=valid)
    return GcpShots(
        station=col("station")[:, 0], marker=col("marker")[:, 0], hz=hz, v=v, d=d, t=t,
        status=status, additive_constant=c, source=str(path), lines=np.asarray(numbers),
    )


def write_gcp_csv(path: str | PathLike, shots: GcpShots) -> None:
    """Write GCP shots in the native CSV format (radians, raw distances), atomically."""
    atomic_write_text(path, gcp_csv_text(shots))


def gcp_csv_text(shots: GcpShots) -> str:
    """Text of a native GCP CSV file (radians, raw distances).

    Times that are NaN are written as empty fields. The additive constant is not written.
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(GCP_CSV_COLUMNS)
    for k in range(len(shots)):
        t = shots.t[k]
        w.writerow((
            shots.station[k], shots.marker[k], fmt_float(shots.hz[k]), fmt_float(shots.v[k]),
            fmt_float(shots.d[k]), fmt_float(t) if np.isfinite(t) else "",
            int(shots.status[k]),
        ))
    return buf.getvalue()


def detect_gcp_format(path: str | PathLike) -> str:
    """``"rts-project"`` when the first data line is the RTS_project header, else ``"csv"``."""
    numbers, lines = numbered_lines(read_text(path))
    if lines and lines[0].split(",")[0].strip().lower() == "theodolite_number":
        return "rts-project"
    return "csv"


def read_gcp_shots(
    path: str | PathLike, *, format: str = "auto", additive_constant: float | None = None
) -> GcpShots:
    """Read GCP shots in either format.

    Parameters
    ----------
    path : str or PathLike
    format : {"auto", "rts-project", "csv"}
        ``auto`` recognises the RTS_project header line.
    additive_constant : float, optional
        m; when None, the reader's default: 0.01 m for ``rts-project`` (the RTS_project
        dataset's constant), 0 for ``csv``.
    """
    fmt = format.strip().lower()
    if fmt not in GCP_FORMATS:
        raise InputError(f"unknown GCP format {format!r}; expected one of {', '.join(GCP_FORMATS)}")
    if fmt == "auto":
        fmt = detect_gcp_format(path)
    kw = {} if additive_constant is None else {"additive_constant": additive_constant}
    if fmt == "rts-project":
        return read_gcp_rts_project(path, **kw)
    return read_gcp_csv(path, **kw)
