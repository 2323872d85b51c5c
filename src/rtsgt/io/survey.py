"""Readers of the static survey of the robot and of reference-point files: RTS_project's
``calibration_raw.csv`` (DMS angles with sigmas; the points computed by
:class:`rtsgt.types.SurveyShots`), ``calibration_results.csv`` (inter-prism and inter-GNSS
distances) and ``sensor_positions.csv`` (Cartesian with a covariance and a flag, kept unused:
:class:`SensorPositions`), and rtsgt's reference CSV (``name,x,y,z,cov_..``, body frame).
docs/file-formats.md#survey-and-reference-files.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np

from rtsgt.errors import GeometryError, InputError
from rtsgt.io._parse import (
    atomic_write_text,
    find_columns,
    fmt_float,
    read_lines,
    split_rows,
    to_float,
)
from rtsgt.measurement.units import dms_to_rad
from rtsgt.pose.reference import ReferencePoints
from rtsgt.types import SurveyShots

SURVEY_COLUMNS = (
    "hz_d", "hz_m", "hz_s", "sigma_hz_d", "sigma_hz_m", "sigma_hz_s",
    "v_d", "v_m", "v_s", "sigma_v_d", "sigma_v_m", "sigma_v_s",
    "distance", "sigma_distance", "flag",
)

REFERENCE_CSV_COLUMNS = (
    "name", "x", "y", "z", "cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz",
)


SENSOR_POSITIONS_COLUMNS = (
    "x", "y", "z", "flag", "cov_xx", "cov_xy", "cov_xz", "cov_yx", "cov_yy", "cov_yz",
    "cov_zx", "cov_zy", "cov_zz",
)


def default_survey_names(k: int) -> tuple[str, ...]:
    """Row names of the RTS_project layout: prism1-3, gnss1-3, then lidar1, lidar2, ..."""
    names = []
    for i in range(k):
        if i < 3:
            names.append(f"prism{i + 1}")
        elif i < 6:
            names.append(f"gnss{i - 2}")
        else:
            names.append(f"lidar{i - 5}")
    return tuple(names)


def _dms_to_rad(
    tokens: np.ndarray, numbers: Sequence[int], path: str | PathLike, what: str
) -> np.ndarray:
    """Angles from (N, 3) tokens ``degrees minutes seconds`` to radians.

    Checks each line (naming the file and line), then converts with
    :func:`rtsgt.measurement.units.dms_to_rad`: a leading ``-`` on the degrees makes the whole
    angle negative (``-0 30 00`` is -0.5 deg). Degrees and minutes must be whole numbers,
    minutes in [0, 60) and seconds in [0, 60).
    """
    names = (f"{what} degrees", f"{what} minutes", f"{what} seconds")
    values = to_float(tokens, numbers, path, names)
    deg, mins, secs = values[:, 0], values[:, 1], values[:, 2]
    for i in range(values.shape[0]):
        if not (mins[i] >= 0 and mins[i] < 60 and mins[i] == np.floor(mins[i])):
            raise InputError(
                f"expected whole minutes in [0, 60) for {what}, got {tokens[i, 1]!r}",
                path, numbers[i],
            )
        if not (secs[i] >= 0 and secs[i] < 60):
            raise InputError(
                f"expected seconds in [0, 60) for {what}, got {tokens[i, 2]!r}", path, numbers[i]
            )
        if deg[i] != np.floor(deg[i]):
            raise InputError(
                f"expected whole degrees for {what} (d m s), got {tokens[i, 0]!r}",
                path, numbers[i],
            )
    # the sign of the degrees (a "-0" included) applies to the whole angle
    return dms_to_rad(deg, mins, secs)


def read_survey_raw(
    path: str | PathLike,
    *,
    names: Sequence[str] | None = None,
    additive_constant: float = 0.0,
) -> SurveyShots:
    """Read a static survey in RTS_project's ``calibration_raw.csv`` format into
    :class:`~rtsgt.types.SurveyShots` (rows named by ``names``, default
    :func:`default_survey_names`; ``additive_constant`` m added to every distance). Bad lines
    raise :class:`~rtsgt.errors.InputError` naming the file and line."""
    numbers, lines = read_lines(path, "survey shots (15 space-separated fields per line)")
    tok = split_rows(lines, numbers, path, SURVEY_COLUMNS, None)
    hz = _dms_to_rad(tok[:, 0:3], numbers, path, "Hz")
    s_hz = _dms_to_rad(tok[:, 3:6], numbers, path, "sigma Hz")
    v = _dms_to_rad(tok[:, 6:9], numbers, path, "V")
    s_v = _dms_to_rad(tok[:, 9:12], numbers, path, "sigma V")
    rest = to_float(tok[:, 12:15], numbers, path, SURVEY_COLUMNS[12:15])
    d_raw, s_d = rest[:, 0], rest[:, 1]
    for i, number in enumerate(numbers):
        if not d_raw[i] > 0:
            raise InputError(f"expected a positive distance, got {tok[i, 12]!r} m", path, number)
        if not (v[i] > 0 and v[i] < np.pi):
            raise InputError(
                f"expected a zenith angle V in (0, 180) deg, got {' '.join(tok[i, 6:9])}",
                path, number,
            )
        for what, val in (("sigma Hz", s_hz[i]), ("sigma V", s_v[i]), ("sigma distance", s_d[i])):
            if not val >= 0:
                raise InputError(f"expected a non-negative {what}, got {val!r}", path, number)
    k = len(lines)
    if names is None:
        names = default_survey_names(k)
    names = tuple(str(s) for s in names)
    if len(names) != k:
        raise InputError(f"expected {len(names)} survey rows (one per name), got {k}", path)
    d = d_raw + float(additive_constant)
    return SurveyShots(names, hz, s_hz, v, s_v, d, s_d, str(path))


@dataclass(frozen=True)
class CalibrationResults:
    """Inter-point distances of the RTS_project ``calibration_results.csv``, m.

    Attributes
    ----------
    prism_distances : ndarray, shape (3,)
        d12, d13, d23.
    gnss_distances : ndarray, shape (3,) or None
        g12, g13, g23 (None when the file has only the three prism distances).
    """

    prism_distances: np.ndarray
    gnss_distances: np.ndarray | None = None


def read_calibration_results(path: str | PathLike) -> CalibrationResults:
    """Read ``calibration_results.csv``: one line ``d12 d13 d23 [g12 g13 g23]`` (m).

    Raises
    ------
    InputError
        Not exactly one data line of 3 or 6 positive numbers.
    """
    numbers, lines = read_lines(path, "inter-prism distances d12 d13 d23 [g12 g13 g23]")
    if len(lines) != 1:
        raise InputError(
            f"expected one line of distances, got {len(lines)} data lines", path, numbers[1]
        )
    fields = lines[0].replace(",", " ").split()
    if len(fields) not in (3, 6):
        raise InputError(
            f"expected 3 or 6 distances (d12 d13 d23 [g12 g13 g23]), got {len(fields)}",
            path, numbers[0],
        )
    cols = ("d12", "d13", "d23", "g12", "g13", "g23")[: len(fields)]
    vals = to_float(np.array([fields], dtype=object), numbers, path, cols)[0]
    for c, x in zip(cols, vals, strict=True):
        if not x > 0:
            raise InputError(f"expected a positive distance {c}, got {x!r} m", path, numbers[0])
    return CalibrationResults(vals[:3], vals[3:] if len(vals) == 6 else None)


def read_reference_csv(path: str | PathLike, *, frame: str = "body") -> ReferencePoints:
    """Read reference points ``name,x,y,z,cov_xx,...,cov_zz`` (body ``frame``, m, m^2; header first)
    into :class:`~rtsgt.pose.ReferencePoints` with a block-diagonal covariance. Bad numbers,
    duplicated names, a covariance not symmetric PSD, fewer than 3 or nearly collinear points
    raise :class:`~rtsgt.errors.InputError`."""
    numbers, lines = read_lines(path, "a header and reference points")
    header = [h.strip() for h in lines[0].split(",")]
    pos = find_columns(header, REFERENCE_CSV_COLUMNS, path, numbers[0])
    if len(lines) < 2:
        raise InputError("expected reference points after the header, got none", path)
    tok = split_rows(lines[1:], numbers[1:], path, header, ",")
    names = [str(s) for s in tok[:, pos["name"]]]
    for i, s in enumerate(names):
        if not s:
            raise InputError("expected a point name, got an empty field", path, numbers[1 + i])
        if s in names[:i]:
            raise InputError(f"duplicated point name {s!r}", path, numbers[1 + i])
    num_cols = REFERENCE_CSV_COLUMNS[1:]
    vals = to_float(tok[:, [pos[c] for c in num_cols]], numbers[1:], path, num_cols)
    xyz = vals[:, :3]
    cxx, cxy, cxz, cyy, cyz, czz = vals[:, 3:].T
    cov = np.stack([
        np.stack([cxx, cxy, cxz], -1), np.stack([cxy, cyy, cyz], -1), np.stack([cxz, cyz, czz], -1)
    ], axis=-2)
    for i in range(len(names)):
        w = np.linalg.eigvalsh(cov[i])
        if w[0] < -1e-9 * max(abs(w[-1]), 1e-300):
            raise InputError(
                f"expected a positive semi-definite covariance for {names[i]!r}, got "
                f"eigenvalue {w[0]:.3g} m^2", path, numbers[1 + i],
            )
    try:
        return ReferencePoints(tuple(names), xyz, cov, frame)
    except GeometryError as exc:
        raise InputError(str(exc), path) from exc


def write_reference_csv(path: str | PathLike, reference: ReferencePoints) -> None:
    """Write reference points in the rtsgt reference CSV format (atomically).

    Raises
    ------
    ValueError
        The covariance correlates different points (the format cannot hold that).
    """
    n = len(reference)
    cov = reference.cov
    off = cov.copy()
    for i in range(n):
        off[3 * i:3 * i + 3, 3 * i:3 * i + 3] = 0.0
    if np.any(off != 0.0):
        raise ValueError(
            "Expected a block-diagonal reference covariance: the CSV format has no "
            "correlation between points"
        )
    rows = [",".join(REFERENCE_CSV_COLUMNS)]
    blocks = reference.cov_blocks()
    for name, p, c in zip(reference.names, reference.xyz, blocks, strict=True):
        vals = [p[0], p[1], p[2], c[0, 0], c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2]]
        rows.append(",".join([name] + [fmt_float(x) for x in vals]))
    atomic_write_text(Path(path), "\n".join(rows) + "\n")


@dataclass(frozen=True)
class SensorPositions:
    """Surveyed points of an RTS_project ``sensor_positions.csv``: ``names`` (K,), ``xyz`` (K, 3;
    survey frame, m), ``cov`` (K, 3, 3; m^2, as written), the fourth field ``flag`` (K,), the
    1-based ``lines`` and the ``source`` file."""

    names: tuple[str, ...]
    xyz: np.ndarray
    cov: np.ndarray
    flag: np.ndarray
    lines: np.ndarray
    source: str = ""

    def __len__(self) -> int:
        return len(self.names)


def read_sensor_positions(
    path: str | PathLike, *, names: Sequence[str] | None = None
) -> SensorPositions:
    """Read an RTS_project ``sensor_positions.csv`` (``x y z flag`` and a row-major 3x3 covariance
    per row, named by ``names``, default :func:`default_survey_names`) into
    :class:`SensorPositions`. A bad row (13 fields, finite, symmetric PSD covariance) raises
    :class:`~rtsgt.errors.InputError` naming the file and line."""
    numbers, lines = read_lines(path, "sensor positions `x y z flag` and a 3x3 covariance")
    tok = split_rows(lines, numbers, path, SENSOR_POSITIONS_COLUMNS, None)
    vals = to_float(tok, numbers, path, SENSOR_POSITIONS_COLUMNS)
    cov = vals[:, 4:].reshape(-1, 3, 3)
    scale = np.max(np.abs(cov), axis=(1, 2))
    asym = np.max(np.abs(cov - np.swapaxes(cov, 1, 2)), axis=(1, 2))
    bad = np.flatnonzero(asym > 1e-9 * scale)
    if bad.size:
        i = bad[0]
        raise InputError(f"expected a symmetric covariance (row-major cov_xx .. cov_zz), got "
                         f"entries differing by {asym[i]:.3g} m^2 across the diagonal",
                         path, numbers[i])
    diag = np.diagonal(cov, axis1=1, axis2=2)
    bad = np.flatnonzero(np.any(diag < 0, axis=1))
    if bad.size:
        i = bad[0]
        raise InputError(f"expected non-negative variances, got {diag[i].min():.3g} m^2",
                         path, numbers[i])
    w = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, 1, 2)))
    bad = np.flatnonzero(w[:, 0] < -1e-9 * np.maximum(w[:, -1], 0.0))
    if bad.size:
        i = bad[0]
        raise InputError(f"expected a positive semi-definite covariance, got eigenvalue "
                         f"{w[i, 0]:.3g} m^2", path, numbers[i])
    k = len(lines)
    names = default_survey_names(k) if names is None else tuple(str(s) for s in names)
    if len(names) != k:
        raise InputError(f"expected {len(names)} rows (one per name), got {k}", path)
    return SensorPositions(names, vals[:, :3], cov, vals[:, 3], np.asarray(numbers), str(path))
