"""Readers and writers of the file formats of the RTS_project repository (Vaidis et al. 2023):
the tracked prism file (``t d V Hz``, zenith before azimuth) and ``GCP.txt`` (``elevation`` is
the zenith angle, the time ``sec + nsec * 1e-9`` with ``nsec`` not zero-padded). Distances
are raw (the additive constant stored apart), so ``read(write(x)) == x`` exactly.
docs/file-formats.md#tracked-prism-files, docs/file-formats.md#gcp-files.
"""

from __future__ import annotations

from os import PathLike

import numpy as np

from rtsgt.errors import InputError
from rtsgt.io._parse import (
    atomic_write_text,
    check_distance,
    check_header,
    check_increasing,
    check_seconds,
    check_zenith,
    fmt_float,
    read_lines,
    split_rows,
    to_float,
    to_int,
)
from rtsgt.types import GcpShots, Observations

#: Columns of a tracked prism file, in file order.
PRISM_COLUMNS = ("t", "d", "V", "Hz")

#: Header of an RTS_project GCP file, in file order.
GCP_COLUMNS = (
    "theodolite_number", "marker_number", "status", "elevation", "azimuth", "distance",
    "sec", "nsec",
)
GCP_SEPARATOR = " , "


def _check_constant(additive_constant: float) -> float:
    c = float(additive_constant)
    if not np.isfinite(c):
        raise InputError(f"Expected a finite additive constant (m), got {additive_constant!r}")
    return c


def read_prism_file(
    path: str | PathLike,
    *,
    station: str | int,
    prism: str | int,
    additive_constant: float = 0.01,
) -> Observations:
    """Read a tracked prism file of RTS_project (``t d V Hz``, no header) of ``station`` tracking
    ``prism`` into :class:`~rtsgt.types.Observations` (s, rad, raw distances in m, status 0),
    ``additive_constant`` (m; 0.01 for RTS_project) stored apart. Bad lines (column count,
    non-finite, distance <= 0, zenith outside (0, pi), times not increasing) raise
    :class:`~rtsgt.errors.InputError` naming the file and line."""
    c = _check_constant(additive_constant)
    numbers, lines = read_lines(path, "tracked prism measurements `t d V Hz`")
    tokens = split_rows(lines, numbers, path, PRISM_COLUMNS, None)
    values = to_float(tokens, numbers, path, PRISM_COLUMNS)
    t, d, v, hz = values.T
    check_distance(d, numbers, path)
    check_zenith(v, numbers, path)
    check_increasing(t, numbers, path)
    return Observations(
        t=t, hz=hz, v=v, d=d, status=None, station=str(station), prism=str(prism),
        additive_constant=c, source=str(path),
    )


def write_prism_file(path: str | PathLike, obs: Observations) -> None:
    """Write observations as a tracked prism file (``t d V Hz``, raw distance), atomically.

    See :func:`prism_file_text` for the content and the errors.
    """
    atomic_write_text(path, prism_file_text(obs))


def prism_file_text(obs: Observations) -> str:
    """Text of a tracked prism file (``t d V Hz`` per line, raw distance).

    The format has no status column: observations with a non-zero status are refused (select
    the valid ones first). The additive constant is not written (the reader takes it as an
    argument). Floats are written with the shortest exact representation, so reading the file
    back gives the same arrays bit for bit.

    Raises
    ------
    ValueError
        Non-zero status, or non-finite values that the reader would refuse.
    """
    if np.any(obs.status != 0):
        raise ValueError(
            "Expected only valid observations (status 0): the prism format has no status "
            "column; write obs.select(obs.status == 0)"
        )
    cols = (obs.t, obs.d, obs.v, obs.hz)
    if not all(np.all(np.isfinite(a)) for a in cols):
        raise ValueError("Expected finite t, d, v, hz to write a prism file, got NaN or inf")
    return "".join(
        f"{fmt_float(t)} {fmt_float(d)} {fmt_float(v)} {fmt_float(hz)}\n"
        for t, d, v, hz in zip(*cols, strict=True)
    )


def read_gcp_rts_project(path: str | PathLike, *, additive_constant: float = 0.01) -> GcpShots:
    """Read an RTS_project ``GCP.txt`` into :class:`~rtsgt.types.GcpShots` in file order (``t = sec
    + nsec * 1e-9``, identifiers as written, ``lines`` 1-based), ``additive_constant`` (m) stored
    apart. Shots with a non-zero status are kept (the calibration excludes them); bad lines
    raise :class:`~rtsgt.errors.InputError` naming the file and line."""
    c = _check_constant(additive_constant)
    numbers, lines = read_lines(path, "a header line and ground control point shots")
    check_header(lines[0].split(","), GCP_COLUMNS, path, numbers[0])
    numbers, lines = numbers[1:], lines[1:]
    if not lines:
        raise InputError("no GCP shot after the header", path)
    tokens = split_rows(lines, numbers, path, GCP_COLUMNS, ",")
    for j in (0, 1):
        empty = np.flatnonzero(tokens[:, j] == "")
        if empty.size:
            raise InputError(f"empty {GCP_COLUMNS[j]}", path, numbers[empty[0]])
    ints = to_int(tokens[:, [2, 6, 7]], numbers, path, ("status", "sec", "nsec"))
    status, sec, nsec = ints.T
    valid = status == 0
    v, hz, d = to_float(
        tokens[:, 3:6], numbers, path, GCP_COLUMNS[3:6], finite=valid
    ).T
    bad = np.flatnonzero((nsec < 0) | (nsec >= 1_000_000_000))
    if bad.size:
        i = bad[0]
        raise InputError(f"expected nsec in [0, 999999999], got {nsec[i]}", path, numbers[i])
    check_distance(d, numbers, path, where=valid)
    check_zenith(v, numbers, path, where=valid)
    t = sec.astype(float) + nsec.astype(float) * 1e-9
    check_seconds(t, numbers, path, "sec")
    return GcpShots(
        station=tokens[:, 0], marker=tokens[:, 1], hz=hz, v=v, d=d, t=t, status=status,
        additive_constant=c, source=str(path), lines=np.asarray(numbers),
    )


def _sec_nsec(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split float seconds into integer ``sec`` and ``nsec`` such that they read back to ``t``."""
    sec = np.floor(t)
    nsec = np.rint((t - sec) * 1e9)
    carry = nsec >= 1e9
    sec = sec + carry
    nsec = np.where(carry, nsec - 1e9, nsec)
    return sec.astype(np.int64), nsec.astype(np.int64)


def write_gcp_rts_project(path: str | PathLike, shots: GcpShots) -> None:
    """Write GCP shots in the RTS_project ``GCP.txt`` format, atomically.

    See :func:`gcp_rts_project_text` for the content and the errors.
    """
    atomic_write_text(path, gcp_rts_project_text(shots))


def gcp_rts_project_text(shots: GcpShots) -> str:
    """Text of an RTS_project ``GCP.txt`` file (header and one line per shot).

    Distances are written raw (without the additive constant); times as ``sec`` and
    non-padded ``nsec``. Reading the file back with the same additive constant gives the same
    arrays (times to float64 precision, bit for bit for times that came from such a file).

    Raises
    ------
    ValueError
        Non-finite times, or identifiers that contain a comma, whitespace or are empty.
    """
    t = np.asarray(shots.t, dtype=float)
    if not np.all(np.isfinite(t)):
        raise ValueError("Expected finite shot times to write GCP.txt (columns sec, nsec)")
    for name in ("station", "marker"):
        ids = getattr(shots, name)
        bad = [s for s in ids if s == "" or "," in s or any(ch.isspace() for ch in s)]
        if bad:
            raise ValueError(
                f"Expected {name} identifiers without commas or spaces, got {bad[0]!r}"
            )
    sec, nsec = _sec_nsec(t)
    rows = [GCP_SEPARATOR.join(GCP_COLUMNS)]
    for k in range(len(shots)):
        rows.append(GCP_SEPARATOR.join((
            shots.station[k], shots.marker[k], str(int(shots.status[k])),
            fmt_float(shots.v[k]), fmt_float(shots.hz[k]), fmt_float(shots.d[k]),
            str(sec[k]), str(nsec[k]),
        )))
    return "\n".join(rows) + "\n"
