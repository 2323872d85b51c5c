r"""Prism track CSV: positions over time with a 3x3 covariance per position.

Format
------
A header line, then one comma-separated row per measurement, in strictly increasing time::

    t,x,y,z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz

=========================================  ==================================================
``t``                                      time, s (Unix epoch where known; values
                                           that look like ms, us or ns are refused)
``x``, ``y``, ``z``                        position, m, in the frame of the track
``cov_xx`` ... ``cov_zz``                  upper triangle of the symmetric positive definite
                                           covariance of the position, m^2
=========================================  ==================================================

These ten columns come first, in this order (names case-insensitive). Extra columns after
them are allowed on read:

- ``range_m``: slope distance from the measuring station, m (parsed into
  :attr:`PrismTrack.range_m`);
- per-source covariances ``<source>_cov_xx, <source>_cov_xy, ..., <source>_cov_zz`` for a
  source of :data:`rtsgt.types.NOISE_SOURCES` (``instrument``, ``tilt``, ...): parsed into
  :attr:`PrismTrack.cov_by_source` when all six columns of the source are present (each
  must be symmetric positive semi-definite);
- any other column is ignored.

Blank lines and lines starting with ``#`` are skipped (line numbers still count them).
:func:`write_track_csv` writes the same layout (the extra columns only when asked), with the
shortest decimal text that reads back as the same float64, atomically (temporary file, then
:func:`os.replace`).
"""

from __future__ import annotations

from os import PathLike
from pathlib import Path

import numpy as np

from rtsgt.errors import InputError
from rtsgt.io._parse import (
    atomic_write_text,
    check_increasing,
    check_seconds,
    fmt_float,
    read_lines,
    split_rows,
    to_float,
)
from rtsgt.noise.sources import NOISE_SOURCES
from rtsgt.types import PrismTrack

__all__ = [
    "TRACK_COLUMNS",
    "read_query_times",
    "read_track_csv",
    "track_csv_text",
    "write_track_csv",
]

#: The ten mandatory columns, in file order.
TRACK_COLUMNS = ("t", "x", "y", "z", "cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz")

_UPPER = ("xx", "xy", "xz", "yy", "yz", "zz")
_IU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def _full_cov(upper: np.ndarray) -> np.ndarray:
    """(N, 6) upper triangles (xx, xy, xz, yy, yz, zz) to (N, 3, 3) symmetric matrices."""
    n = upper.shape[0]
    cov = np.empty((n, 3, 3))
    cov[:, _IU[0], _IU[1]] = upper
    cov[:, _IU[1], _IU[0]] = upper
    return cov


def read_track_csv(
    path: str | PathLike, *, prism: str | None = None, frame: str = "world"
) -> PrismTrack:
    """Read a prism track CSV into a :class:`~rtsgt.types.PrismTrack` (``prism`` default the file
    stem, positions in ``frame``). Bad input (header, column count, non-finite values, times not
    strictly increasing, a covariance not positive definite) raises
    :class:`~rtsgt.errors.InputError` naming the file and line."""
    numbers, lines = read_lines(path, "a header line and prism positions")
    header = [h.strip().lower() for h in lines[0].split(",")]
    if header[: len(TRACK_COLUMNS)] != list(TRACK_COLUMNS):
        raise InputError(
            f"expected the header to start with {','.join(TRACK_COLUMNS)!r}, "
            f"got {lines[0]!r}",
            path, numbers[0],
        )
    numbers, lines = numbers[1:], lines[1:]
    if not lines:
        raise InputError("no data line after the header", path)
    tokens = split_rows(lines, numbers, path, header, ",")
    values = to_float(tokens[:, : len(TRACK_COLUMNS)], numbers, path, TRACK_COLUMNS)
    t = values[:, 0]
    check_increasing(t, numbers, path)
    cov = _full_cov(values[:, 4:10])
    _check_cov(cov, numbers, path, "covariance", definite=True)
    by_source = {}
    for src in NOISE_SOURCES:
        names = [f"{src}_cov_{c}" for c in _UPPER]
        if all(nm in header for nm in names):
            cols = [header.index(nm) for nm in names]
            c = _full_cov(to_float(tokens[:, cols], numbers, path, names))
            _check_cov(c, numbers, path, f"{src} covariance", definite=False)
            by_source[src] = c
    range_m = None
    if "range_m" in header:
        j = header.index("range_m")
        range_m = to_float(tokens[:, [j]], numbers, path, ("range_m",))[:, 0]
    name = prism if prism is not None else _stem(path)
    return PrismTrack(
        t=t, xyz=values[:, 1:4], cov=cov, cov_by_source=by_source, prism=name, frame=frame,
        range_m=range_m,
    )


def _stem(path) -> str:
    return Path(path).stem


def _check_cov(cov, numbers, path, what: str, definite: bool) -> None:
    eig = np.linalg.eigvalsh(cov)
    scale = np.maximum(np.abs(eig).max(axis=1), np.finfo(float).tiny)
    bad = ~(eig[:, 0] > 0) if definite else eig[:, 0] < -1e-12 * scale
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        kind = "positive definite" if definite else "positive semi-definite"
        raise InputError(
            f"expected a symmetric {kind} {what} (m^2), got eigenvalues "
            f"{', '.join(f'{e:.3g}' for e in eig[i])}",
            path, numbers[i],
        )


def track_csv_text(track, *, extra_columns: bool = False) -> str:
    """Text of a prism track CSV of ``track`` (a PrismTrack, or ``(t (N,), xyz (N, 3), cov (N, 3,
    3))``), with ``extra_columns`` its ``range_m`` and per-source covariances. Bad shapes,
    non-finite values or times not increasing raise :class:`~rtsgt.errors.InputError`."""
    by_source, range_m = {}, None
    if isinstance(track, PrismTrack):
        t, xyz, cov = track.t, track.xyz, track.cov
        if extra_columns:
            by_source, range_m = dict(track.cov_by_source), track.range_m
    else:
        try:
            t, xyz, cov = (np.asarray(a, dtype=float) for a in track)
        except (TypeError, ValueError) as exc:
            raise InputError(f"Expected a PrismTrack or (t, xyz, cov), got {exc}") from None
    n = t.shape[0]
    if t.shape != (n,) or xyz.shape != (n, 3) or cov.shape != (n, 3, 3):
        raise InputError(
            f"Expected t (N,), xyz (N, 3), cov (N, 3, 3), got {t.shape}, {xyz.shape}, {cov.shape}"
        )
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(xyz)) and np.all(np.isfinite(cov))):
        raise InputError("Expected finite values to write a track, got NaN or inf")
    if np.any(np.diff(t) <= 0):
        raise InputError("Expected strictly increasing times to write a track")
    names = list(TRACK_COLUMNS)
    cols = [t[:, None], xyz, cov[:, _IU[0], _IU[1]]]
    if range_m is not None:
        names.append("range_m")
        cols.append(np.asarray(range_m)[:, None])
    for src in NOISE_SOURCES:
        if src in by_source:
            names += [f"{src}_cov_{c}" for c in _UPPER]
            cols.append(np.asarray(by_source[src])[:, _IU[0], _IU[1]])
    table = np.concatenate(cols, axis=1)
    body = "".join(",".join(map(fmt_float, row)) + "\n" for row in table.tolist())
    return ",".join(names) + "\n" + body


def write_track_csv(path: str | PathLike, track, *, extra_columns: bool = False) -> None:
    """Write a prism track CSV atomically (see :func:`track_csv_text`)."""
    atomic_write_text(path, track_csv_text(track, extra_columns=extra_columns))


def read_query_times(path: str | PathLike, *, with_lines: bool = False):
    """Query times (Q,), s, one per line in file order (blank and ``#`` lines skipped), and with
    ``with_lines`` their 1-based line numbers. Bad lines raise
    :class:`~rtsgt.errors.InputError` naming the file and line."""
    numbers, lines = read_lines(path, "query times, one per line")
    tokens = split_rows(lines, numbers, path, ("t",), None)
    times = to_float(tokens, numbers, path, ("t",))[:, 0]
    check_seconds(times, numbers, path)
    if with_lines:
        return times, np.asarray(numbers, dtype=int)
    return times
