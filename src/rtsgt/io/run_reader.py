"""Read an rtsgt run directory back into arrays (for ``rtsgt analyze`` and ``rtsgt report``).

The layout is the one written by :mod:`rtsgt.io.run_output` (see its module docstring)::

    groundtruth_covariance.csv   t,x,y,z,qx,qy,qz,qw,cov_00..cov_55 (kept poses)
    rejected_poses.csv           t,reason
    prisms/prism<i>.csv          t,x,y,z,cov_xx..cov_zz (prisms at the query times, total cov)
    prisms/prism<i>_sources.csv  t,<source>_xx..<source>_zz (each source at the query times)
    measurements/prism<i>.csv    t,x,y,z,cov_xx..cov_zz,range_m,<source>_xx..<source>_zz
    measurements/removed.csv     t,prism,station,x,y,z,stage[,reason] (optional: what the
                                 filters removed; older runs lack the reason column)
    reference.csv                name,x,y,z,cov_xx..cov_zz
    summary.json

Columns are located by their header names, so extra columns are ignored and the order of the
columns does not matter. Every problem is an :class:`~rtsgt.errors.InputError` naming the file
(and the line where it applies).

summary.json
------------
:func:`read_summary` is the only reader of ``summary.json``: it checks the layout's
``schema`` (``{"name": "rtsgt-run", "version": 1}``; a summary without it is of the layout
before, read as version 0; a newer version is refused), applies the fallbacks for older layouts
(``options`` for ``parameters``, engine, samples, seed and gp_noise at the top level, ``name``
for ``deployment``, ``gcp_world`` outside ``calibration``) and returns a typed
:class:`RunSummary`. :func:`read_run`, :meth:`rtsgt.evaluation.ContinuousGroundTruth.from_run_dir`
and the report take what they need from it.

Missing files
-------------
A run whose files are not all there is a damaged run (a file deleted, a copy cut short), and
reading what is left would analyse part of it as if it were the whole. So:

- a file that ``summary.json`` says was written is **required**: every prism listed under
  ``prisms`` has ``measurements/prism<i>.csv``, ``prisms/prism<i>.csv`` and
  ``prisms/prism<i>_sources.csv``; one missing is an :class:`~rtsgt.errors.InputError` naming
  it;
- ``rejected_poses.csv`` and ``measurements/removed.csv`` are **optional** (runs of older
  versions lack ``removed.csv``; the analysis works without them): one missing from a run
  written by rtsgt (its ``summary.json`` names the software) is a
  :class:`~rtsgt.errors.RtsgtWarning` naming it;
- without ``summary.json`` (a directory assembled by hand), nothing says which files were
  written: a prism of ``prisms/`` without its ``measurements/prism<i>.csv`` is read with a
  warning naming the file.
"""

from __future__ import annotations

import csv
import json
import re
import warnings
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path

import numpy as np

from rtsgt.calibration.coupling import StationCoupling
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.io._parse import csv_table, read_table, split_rows, to_float
from rtsgt.io.run_output import (
    COV3_NAMES,
    SUMMARY_SCHEMA_NAME,
    SUMMARY_SCHEMA_VERSION,
    columns_to_cov3,
)
from rtsgt.io.trajectory import read_covariance_csv
from rtsgt.options import GP_NOISE, InterpolationOptions, PoseOptions
from rtsgt.types import NOISE_SOURCES, PoseTrajectory, PrismTrack

__all__ = ["PrismSummary", "RunData", "RunSummary", "read_run", "read_summary", "read_table",
           "station_positions_from_summary"]

_PRISM_FILE = re.compile(r"^prism(?P<id>.+?)\.csv$")
_SOURCES_FILE = re.compile(r"^prism(?P<id>.+?)_sources\.csv$")


@dataclass(frozen=True)
class RunData:
    """The arrays of one run that the analysis, the figures and the report use.

    Built by :func:`read_run` from a run directory, or by
    :func:`rtsgt.report.analysis.run_data_from_result` from an in-memory
    :class:`~rtsgt.pipeline.RunResult`. Every position and covariance is in the world frame
    (m, m^2); times in s.

    Attributes
    ----------
    name : str
        Deployment name (or the directory name).
    prism_ids : tuple of str, length n
        Prisms in the order of the ``n`` axis of the ``prisms_*`` arrays.
    measurements : dict str -> PrismTrack
        The measured (filtered) track of each prism: ``xyz``, ``range_m`` and
        ``cov_by_source``. ``cov`` is the sum of the per-source covariances when they are
        known (the total of independent sources), else the covariance of the file.
    prisms_t : ndarray, shape (T,)
        Query times (every pose time, kept or rejected).
    prisms_xyz : ndarray, shape (T, n, 3)
        Interpolated prism positions.
    prisms_cov : ndarray, shape (T, n, 3, 3)
        Their total covariance (what the pose engine used).
    prisms_cov_by_source : dict str -> ndarray (T, n, 3, 3)
        Each source's covariance at the query times.
    prisms_cov_gp : ndarray, shape (T, n, 3, 3), optional
        The GP posterior covariance alone (``gp_*`` columns of ``prism<i>_sources.csv``).
    groundtruth : PoseTrajectory
        The kept poses with their 6x6 covariance.
    rejected_t : ndarray, shape (R,)
    rejected_reason : ndarray of str, shape (R,)
    reference_xyz : ndarray, shape (n, 3)
        Reference prisms in the body frame, same order as ``prism_ids``.
    reference_cov : ndarray, shape (3n, 3n)
        Their covariance (block diagonal when read from ``reference.csv``).
    stations : dict str -> ndarray (3,)
        Station positions (translations of ``T_world_station``), m.
    gcp_xyz : ndarray, shape (G, 3), optional
        Ground control points in the world frame, m.
    gcp_names : tuple of str
    engine : str
        Pose engine of the run (``"mc"``, ``"ut"`` or ``"linear"``).
    samples : int
        Monte Carlo samples of the run.
    seed : int
    gp_noise : str
        ``"white"`` (systematic sources added after the GP) or ``"all"``.
    summary : dict
        The run's ``summary.json`` (empty when the run was not written).
    path : Path, optional
        The run directory.
    removed_t : ndarray, shape (M,)
        Times of the measurements removed by the filters (``measurements/removed.csv``;
        empty when the run does not have it), s.
    removed_xyz : ndarray, shape (M, 3)
        Their world positions, m.
    removed_prism : ndarray of str, shape (M,)
    removed_stage : ndarray of str, shape (M,)
        ``"module1"`` or ``"module2"``: the filter that removed each.
    summary_record : RunSummary, optional
        ``summary`` parsed by :func:`read_summary` (None for an in-memory run).
    measurements_gp_cov : dict str -> ndarray (N, 3, 3)
        Per prism, the covariance the GP was given (the ``cov_*`` columns of
        ``measurements/prism<i>.csv``), when the file has them.
    """

    name: str
    prism_ids: tuple[str, ...]
    measurements: dict[str, PrismTrack]
    prisms_t: np.ndarray
    prisms_xyz: np.ndarray
    prisms_cov: np.ndarray
    prisms_cov_by_source: dict[str, np.ndarray]
    groundtruth: PoseTrajectory
    rejected_t: np.ndarray
    rejected_reason: np.ndarray
    reference_xyz: np.ndarray
    reference_cov: np.ndarray
    stations: dict[str, np.ndarray] = field(default_factory=dict)
    prisms_cov_gp: np.ndarray | None = None
    gcp_xyz: np.ndarray | None = None
    gcp_names: tuple[str, ...] = ()
    engine: str = "linear"
    samples: int = 1000
    seed: int = 0
    gp_noise: str = "white"
    summary: dict = field(default_factory=dict)
    path: Path | None = None
    removed_t: np.ndarray = field(default_factory=lambda: np.empty(0))
    removed_xyz: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    removed_prism: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=str))
    removed_stage: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=str))
    summary_record: RunSummary | None = None
    measurements_gp_cov: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.prism_ids)
        T = self.prisms_t.shape[0]
        if self.prisms_xyz.shape != (T, n, 3):
            raise ValueError(f"Expected prisms_xyz of shape ({T}, {n}, 3), got "
                             f"{self.prisms_xyz.shape}")
        if self.prisms_cov.shape != (T, n, 3, 3):
            raise ValueError(f"Expected prisms_cov of shape ({T}, {n}, 3, 3), got "
                             f"{self.prisms_cov.shape}")
        for s, c in self.prisms_cov_by_source.items():
            if c.shape != (T, n, 3, 3):
                raise ValueError(f"Expected prisms_cov_by_source[{s!r}] of shape "
                                 f"({T}, {n}, 3, 3), got {c.shape}")
        if self.prisms_cov_gp is not None and self.prisms_cov_gp.shape != (T, n, 3, 3):
            raise ValueError(f"Expected prisms_cov_gp of shape ({T}, {n}, 3, 3), got "
                             f"{self.prisms_cov_gp.shape}")
        if self.reference_xyz.shape != (n, 3):
            raise ValueError(f"Expected reference_xyz of shape ({n}, 3), got "
                             f"{self.reference_xyz.shape}")
        if self.reference_cov.shape != (3 * n, 3 * n):
            raise ValueError(f"Expected reference_cov of shape ({3 * n}, {3 * n}), got "
                             f"{self.reference_cov.shape}")
        if self.rejected_t.shape != self.rejected_reason.shape:
            raise ValueError("Expected one rejection reason per rejected time")

    @property
    def sources(self) -> tuple[str, ...]:
        """Noise sources present in the measurements, in :data:`NOISE_SOURCES` order."""
        present = set()
        for tr in self.measurements.values():
            present |= set(tr.cov_by_source)
        return _ordered_sources(present)


def _ordered_sources(names) -> tuple[str, ...]:
    names = set(names)
    known = [s for s in NOISE_SOURCES if s in names]
    return tuple(known + sorted(names - set(known)))


def _natural_key(s: str) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", s) if p)


def _col(header: list[str], data: np.ndarray, name: str) -> np.ndarray:
    return data[:, header.index(name)]


def _cov_from(header: list[str], data: np.ndarray, prefix: str) -> np.ndarray:
    cols = np.column_stack([_col(header, data, f"{prefix}_{c}") for c in COV3_NAMES])
    return columns_to_cov3(cols)


#: Covariance column prefixes that are not noise sources: the total, the GP posterior.
_NOT_SOURCES = ("cov", "gp")


def _source_prefixes(header: list[str]) -> tuple[str, ...]:
    """Sources with all six ``<source>_xx .. <source>_zz`` columns (not ``cov`` or ``gp``)."""
    found = []
    for h in header:
        if h.endswith("_xx"):
            s = h[:-3]
            if s not in _NOT_SOURCES and all(f"{s}_{c}" in header for c in COV3_NAMES):
                found.append(s)
    return _ordered_sources(found)


def _prism_files(folder: Path, pattern: re.Pattern) -> dict[str, Path]:
    if not folder.is_dir():
        raise InputError("folder not found (is this an rtsgt run directory?)", folder)
    out = {}
    for p in folder.iterdir():
        m = pattern.match(p.name)
        if m and not (pattern is _PRISM_FILE and p.name.endswith("_sources.csv")):
            out[m.group("id")] = p
    return dict(sorted(out.items(), key=lambda kv: _natural_key(kv[0])))


def _read_measurements(path: Path, pid: str) -> tuple[PrismTrack, np.ndarray | None]:
    """The measured track, and the file's ``cov_*`` columns (the covariance given to the GP;
    None without them)."""
    header, data = read_table(path, ("t", "x", "y", "z"))
    sources = _source_prefixes(header)
    by_source = {s: _cov_from(header, data, s) for s in sources}
    file_cov = (_cov_from(header, data, "cov") if all(f"cov_{c}" in header for c in COV3_NAMES)
                else None)
    if by_source:
        cov = np.sum(list(by_source.values()), axis=0)
    elif "cov_xx" in header:
        cov = _cov_from(header, data, "cov")
    else:
        raise InputError("no covariance columns (cov_xx.. or <source>_xx..)", path, 1)
    rng = _col(header, data, "range_m") if "range_m" in header else None
    try:
        return PrismTrack(_col(header, data, "t"), data[:, [header.index(c) for c in "xyz"]],
                          cov, by_source, pid, "world", None, rng), file_cov
    except ValueError as exc:
        raise InputError(str(exc), path) from exc


def _read_reference(path: Path, ids: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    need = ("name", "x", "y", "z") + tuple(f"cov_{c}" for c in COV3_NAMES)
    header, numbers, lines = csv_table(path, need)
    tokens = split_rows(lines, numbers, path, header, ",")
    values = to_float(tokens[:, [header.index(c) for c in need[1:]]], numbers, path, need[1:],
                      finite=False)
    names = tokens[:, header.index("name")].tolist()
    by_name = {_strip_prism(name): v for name, v in zip(names, values, strict=True)}
    n = len(ids)
    xyz = np.empty((n, 3))
    cov = np.zeros((3 * n, 3 * n))
    for i, pid in enumerate(ids):
        if pid not in by_name:
            raise InputError(f"no reference for prism {pid}; names: {', '.join(by_name)}", path)
        v = by_name[pid]
        xyz[i] = v[:3]
        cov[3 * i:3 * i + 3, 3 * i:3 * i + 3] = columns_to_cov3(v[None, 3:])[0]
    return xyz, cov


def _strip_prism(name: str) -> str:
    """``"prism2"`` and ``"2"`` both name prism ``"2"``."""
    return name[5:] if name.lower().startswith("prism") and len(name) > 5 else name


def _full_reference_cov(summary: RunSummary, ids: tuple[str, ...],
                        blocks: np.ndarray) -> np.ndarray:
    """The joint reference covariance of ``summary.json`` (``reference.cov_m2``, correlated
    between prisms when the body frame is defined by surveyed points), reordered to ``ids``;
    the block-diagonal one of ``reference.csv`` when it is absent or does not match."""
    if summary.reference_cov is None or summary.reference_names is None:
        return blocks
    names = [_strip_prism(x) for x in summary.reference_names]
    full = summary.reference_cov
    if full.shape != (3 * len(names), 3 * len(names)) or not set(ids) <= set(names):
        return blocks
    idx = np.concatenate([[3 * names.index(p) + j for j in range(3)] for p in ids])
    sub = full[np.ix_(idx, idx)]
    # the diagonal blocks must be those of reference.csv, else the files disagree
    if not np.allclose(np.diagonal(sub.reshape(len(ids), 3, len(ids), 3), axis1=0, axis2=2),
                       np.diagonal(blocks.reshape(len(ids), 3, len(ids), 3), axis1=0, axis2=2),
                       rtol=1e-9, atol=1e-15):
        return blocks
    return sub


def _read_rejected(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``rejected_poses.csv`` (optional, may be empty): times and reasons. Blank lines are
    skipped; a line may lack the reason (read as ``""``) or carry more fields."""
    if not path.is_file() or path.stat().st_size == 0:
        return np.empty(0), np.empty(0, dtype="<U32")
    header, numbers, lines = csv_table(path, ("t", "reason"))
    it, ir = header.index("t"), header.index("reason")
    rows = [(k, line.split(",")) for k, line in zip(numbers, lines, strict=True) if line]
    times = np.array([[r[it] if it < len(r) else ""] for _, r in rows], dtype=object)
    t = to_float(times.reshape(-1, 1), [k for k, _ in rows], path, ("t",), finite=False)[:, 0]
    reason = [r[ir].strip() if ir < len(r) else "" for _, r in rows]
    return t, np.asarray(reason, dtype=str)


_REMOVED_COLUMNS = ("t", "prism", "station", "x", "y", "z", "stage")


def _read_removed(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``measurements/removed.csv``: times, world positions, prisms and stages (optional)."""
    empty = (np.empty(0), np.empty((0, 3)), np.empty(0, dtype=str), np.empty(0, dtype=str))
    if not path.is_file():
        return empty
    with path.open(encoding="utf-8", newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        return empty
    header = [h.strip() for h in rows[0]]
    missing = [c for c in _REMOVED_COLUMNS if c not in header]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}; header is "
                         f"{','.join(header)}", path, 1)
    idx = {c: header.index(c) for c in _REMOVED_COLUMNS}
    t, xyz, prism, stage = [], [], [], []
    for k, row in enumerate(rows[1:]):
        if not row:
            continue
        if len(row) != len(header):
            raise InputError(f"expected {len(header)} fields, got {len(row)}", path, k + 2)
        try:
            t.append(float(row[idx["t"]]))
            xyz.append([float(row[idx[c]]) for c in "xyz"])
        except ValueError as exc:
            raise InputError(f"not a number: {exc}", path, k + 2) from exc
        prism.append(row[idx["prism"]].strip())
        stage.append(row[idx["stage"]].strip())
    return (np.asarray(t, dtype=float), np.asarray(xyz, dtype=float).reshape(-1, 3),
            np.asarray(prism, dtype=str), np.asarray(stage, dtype=str))


def _find(d: dict, *keys, default=None):
    """First value found among nested key paths (tuples) or keys of ``d``."""
    for key in keys:
        path = key if isinstance(key, tuple) else (key,)
        cur = d
        for k in path:
            if isinstance(cur, dict) and k in cur:
                cur = cur[k]
            else:
                break
        else:
            return cur
    return default


def station_positions_from_summary(summary: dict) -> dict[str, np.ndarray]:
    """Station positions (m, world frame) from the calibration block of ``summary.json``.

    Accepts the object of ``rtsgt calibrate --json`` (``stations`` with ``translation_m`` or a
    4x4 ``matrix``) under ``calibration``; the reference station is at the origin.
    """
    calib = _find(summary, "calibration", default=None)
    if not isinstance(calib, dict):
        return {}
    out: dict[str, np.ndarray] = {}
    ref = calib.get("reference_station")
    if ref is not None:
        out[str(ref)] = np.zeros(3)
    stations = calib.get("stations", {})
    if isinstance(stations, dict):
        for sid, entry in stations.items():
            if not isinstance(entry, dict):
                continue
            if entry.get("translation_m") is not None:
                out[str(sid)] = np.asarray(entry["translation_m"], dtype=float).reshape(3)
            elif entry.get("matrix") is not None:
                out[str(sid)] = np.asarray(entry["matrix"], dtype=float)[:3, 3]
    return dict(sorted(out.items(), key=lambda kv: _natural_key(kv[0])))


def _gcp_from_summary(summary: dict) -> tuple[np.ndarray | None, tuple[str, ...]]:
    g = _find(summary, ("calibration", "gcp_world"), "gcp_world", default=None)
    if not g:
        return None, ()
    if isinstance(g, dict):
        names = tuple(str(k) for k in g)
        return np.asarray(list(g.values()), dtype=float).reshape(-1, 3), names
    arr = np.asarray(g, dtype=float).reshape(-1, 3)
    return arr, tuple(str(i + 1) for i in range(arr.shape[0]))


@dataclass(frozen=True)
class PrismSummary:
    """What ``summary.json`` says of one prism (``prisms.<id>``)."""

    #: The station that tracked it (None when not recorded).
    station: str | None = None
    #: The GP's power spectral density Qc, m^2/s^3 (None when not recorded).
    qc_m2_s3: np.ndarray | None = None


@dataclass(frozen=True)
class RunSummary:
    """``summary.json`` of a run, parsed by :func:`read_summary` (the defaults are those of a
    run without the entry: an older layout, or a directory assembled by hand).

    ``document`` is the whole JSON object as read (``{}`` without the file), for display.
    """

    path: Path
    document: dict = field(default_factory=dict)
    #: Whether the file exists.
    exists: bool = False
    #: Layout version (``schema.version``; 0 for a summary written before it had one).
    schema_version: int = 0
    #: Whether ``software.name`` is ``"rtsgt"`` (a run written by rtsgt).
    written_by_rtsgt: bool = False
    #: Deployment name (``deployment``, or ``name`` of older layouts); None when absent.
    name: str | None = None
    engine: str = "linear"
    samples: int = PoseOptions.samples
    seed: int = 0
    rate_hz: object = None
    qc: object = None
    max_gap_s: float = InterpolationOptions.max_gap_s
    gp_noise: str = InterpolationOptions.gp_noise
    distance_gate_m: float = PoseOptions.distance_gate_m
    uncertainty_gate_m: float = PoseOptions.uncertainty_gate_m
    #: ``gates.uncertainty_measure``.
    uncertainty_measure: str = "max_std"
    #: Prisms listed under ``prisms``, in the file's order.
    prisms: dict[str, PrismSummary] = field(default_factory=dict)
    #: ``intervals_s`` (K, 2), s; None when absent (an older summary).
    intervals_s: np.ndarray | None = None
    #: ``reference``: names, body-frame positions (n, 3) m, joint covariance (3n, 3n) m^2,
    #: frame; None when absent.
    reference_names: tuple[str, ...] | None = None
    reference_xyz: np.ndarray | None = None
    reference_cov: np.ndarray | None = None
    reference_frame: str = "body"
    #: Station positions of ``calibration`` (:func:`station_positions_from_summary`), m.
    stations: dict[str, np.ndarray] = field(default_factory=dict)
    #: GCPs in the world frame (G, 3) m and their names (``calibration.gcp_world``).
    gcp_xyz: np.ndarray | None = None
    gcp_names: tuple[str, ...] = ()
    #: ``calibration.coupling`` (None for runs written before rtsgt carried it).
    coupling: StationCoupling | None = None


def _section(doc: dict, key: str, path: Path) -> dict:
    """``doc[key]``, a JSON object ({} when absent); an :class:`InputError` otherwise."""
    value = doc.get(key)
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise InputError(f"{key!r}: expected a JSON object, got {value!r}"[:200], path)
    return value


def _positive(params: dict, key: str, default: float, path: Path) -> float:
    """``params[key]`` (``default`` when absent) as a positive finite float."""
    value = params.get(key, default)
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = float("nan")
    if not (np.isfinite(x) and x > 0):
        raise InputError(f"parameters.{key}: expected a positive number, got {value!r}", path)
    return x


def _array(value, what: str, path: Path) -> np.ndarray:
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what}: expected numbers, got {value!r}: {exc}"[:300], path) from None


def _schema_version(doc: dict, path: Path) -> int:
    """``schema.version`` (0 without ``schema``); a newer version than this rtsgt's is
    refused."""
    schema = doc.get("schema")
    if schema is None:
        return 0
    version = schema.get("version") if isinstance(schema, dict) else None
    if (not isinstance(schema, dict) or schema.get("name") != SUMMARY_SCHEMA_NAME
            or not isinstance(version, int) or isinstance(version, bool) or version < 0):
        raise InputError(f"'schema': expected {{\"name\": \"{SUMMARY_SCHEMA_NAME}\", "
                         f"\"version\": <integer>}}, got {schema!r}"[:300], path)
    if version > SUMMARY_SCHEMA_VERSION:
        raise InputError(f"summary schema version {version} is newer than this rtsgt reads "
                         f"(version {SUMMARY_SCHEMA_VERSION}): the run was written by a later "
                         "rtsgt; upgrade rtsgt to read it", path)
    return version


def read_summary(run_dir: str | PathLike) -> RunSummary:
    """Read ``run_dir/summary.json``: the only reader of that file (module docstring).

    Returns
    -------
    RunSummary
        The defaults (and ``exists`` False) when the file is absent.

    Raises
    ------
    InputError
        Naming the file: not valid JSON, not a JSON object, a newer schema version, or an
        entry of the wrong type (a section that is not an object, a non-positive
        ``max_gap_s`` or gate, a ``gp_noise`` other than ``white`` or ``all``, a bad Qc,
        interval or coupling).
    """
    path = Path(run_dir) / "summary.json"
    if not path.is_file():
        return RunSummary(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(f"invalid JSON: {exc.msg}", path, exc.lineno) from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the file: {exc}", path) from None
    if not isinstance(doc, dict):
        raise InputError(f"expected a JSON object (the run's summary), got a "
                         f"{type(doc).__name__}", path)
    version = _schema_version(doc, path)
    # older layouts: "options" for "parameters"; engine, samples, seed, gp_noise at the top
    params = _section(doc, "parameters", path) or _section(doc, "options", path)

    def param(key, default):
        return params[key] if key in params else doc.get(key, default)

    try:
        samples = int(param("samples", PoseOptions.samples))
        seed = param("seed", 0)
        seed = int(seed) if seed is not None else 0
    except (TypeError, ValueError) as exc:
        raise InputError(f"parameters: samples and seed must be integers: {exc}", path) from None
    gp_noise = str(param("gp_noise", InterpolationOptions.gp_noise))
    if gp_noise not in GP_NOISE:
        raise InputError(f"gp_noise: expected {' or '.join(map(repr, GP_NOISE))}, got "
                         f"{gp_noise!r}", path)
    name = _find(doc, "name", "deployment", default=None)
    if isinstance(name, dict):
        name = name.get("name")
    software = doc.get("software")

    prisms: dict[str, PrismSummary] = {}
    listed = doc.get("prisms")
    for pid, info in (listed.items() if isinstance(listed, dict) else ()):
        info = info if isinstance(info, dict) else {}
        q = info.get("qc_m2_s3")
        if q is not None:
            try:
                q = np.asarray(q, dtype=float)
            except (TypeError, ValueError) as exc:
                raise InputError(f"prism {pid}: bad qc_m2_s3 {q!r}: {exc}", path) from None
        station = info.get("station")
        prisms[str(pid)] = PrismSummary(None if station is None else str(station), q)

    iv = doc.get("intervals_s")
    if iv is not None:
        try:
            iv = np.asarray(iv, dtype=float).reshape(-1, 2)
        except (TypeError, ValueError) as exc:
            raise InputError(f"bad intervals_s: {exc}", path) from None

    ref = _section(doc, "reference", path)
    ref_names = ref.get("names")
    if ref_names is not None:
        if not isinstance(ref_names, list):
            raise InputError(f"reference.names: expected a list, got {ref_names!r}"[:200], path)
        ref_names = tuple(str(x) for x in ref_names)
    ref_xyz = None if ref.get("xyz_m") is None else _array(ref["xyz_m"], "reference.xyz_m", path)
    ref_cov = (None if ref.get("cov_m2") is None
               else _array(ref["cov_m2"], "reference.cov_m2", path))

    calibration = _section(doc, "calibration", path)
    coupling = None
    if calibration.get("coupling") is not None:  # runs written before rtsgt carried it
        try:
            coupling = StationCoupling.from_dict(calibration["coupling"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"bad calibration.coupling: {exc}", path) from None
    gcp_xyz, gcp_names = _gcp_from_summary(doc)

    return RunSummary(
        path=path, document=doc, exists=True, schema_version=version,
        written_by_rtsgt=isinstance(software, dict) and software.get("name") == "rtsgt",
        name=None if name is None else str(name),
        engine=str(param("engine", "linear")), samples=samples, seed=seed,
        rate_hz=params.get("rate_hz"), qc=params.get("qc"),
        max_gap_s=_positive(params, "max_gap_s", InterpolationOptions.max_gap_s, path), gp_noise=gp_noise,
        distance_gate_m=_positive(params, "distance_gate_m", PoseOptions.distance_gate_m, path),
        uncertainty_gate_m=_positive(params, "uncertainty_gate_m",
                                     PoseOptions.uncertainty_gate_m, path),
        uncertainty_measure=str(_section(doc, "gates", path).get("uncertainty_measure",
                                                                  "max_std")),
        prisms=prisms, intervals_s=iv, reference_names=ref_names, reference_xyz=ref_xyz,
        reference_cov=ref_cov, reference_frame=str(ref.get("frame", "body")),
        stations=station_positions_from_summary(doc), gcp_xyz=gcp_xyz, gcp_names=gcp_names,
        coupling=coupling,
    )


def _check_files(root: Path, summary: RunSummary) -> None:
    """Refuse a run missing a file its summary says was written; warn for an optional one
    (module docstring, section Missing files)."""
    for pid in summary.prisms:
        for path, what in ((root / "measurements" / f"prism{pid}.csv", "measured track"),
                           (root / "prisms" / f"prism{pid}.csv", "interpolated positions"),
                           (root / "prisms" / f"prism{pid}_sources.csv",
                            "per-source covariances")):
            if not path.is_file():
                raise InputError(
                    f"missing: summary.json lists prism {pid}, whose {what} this file holds; "
                    "the run directory is damaged (a file deleted or not copied): copy the "
                    "whole directory again or rerun `rtsgt run`", path)
    if summary.written_by_rtsgt:
        for path, lost in ((root / "rejected_poses.csv", "the rejected poses"),
                           (root / "measurements" / "removed.csv",
                            "the measurements the filters removed")):
            if not path.is_file():
                warnings.warn(f"{path}: missing from this run of rtsgt; the analysis and the "
                              f"figures go on without {lost}", RtsgtWarning, stacklevel=3)


def read_run(run_dir: str | PathLike) -> RunData:
    """Read a run directory written by :mod:`rtsgt.io.run_output`.

    Parameters
    ----------
    run_dir : path
        The ``OUT`` directory of ``rtsgt run``.

    Returns
    -------
    RunData
        Rejected poses, GCPs and station positions are optional (empty when absent).

    Raises
    ------
    InputError
        A missing or malformed file, prisms whose query times disagree (module docstring,
        section Missing files; an optional file missing is a warning).
    """
    root = Path(run_dir)
    if not root.is_dir():
        raise InputError("run directory not found", root)
    summary = read_summary(root)
    _check_files(root, summary)

    # measurements
    meas_files = _prism_files(root / "measurements", _PRISM_FILE)
    read = {pid: _read_measurements(p, pid) for pid, p in meas_files.items()}
    measurements = {pid: tr for pid, (tr, _) in read.items()}
    gp_cov = {pid: c for pid, (_, c) in read.items() if c is not None}

    # prisms at the query times
    prism_files = _prism_files(root / "prisms", _PRISM_FILE)
    if not prism_files:
        raise InputError("no prisms/prism<i>.csv files", root / "prisms")
    ids = tuple(prism_files)
    for pid in ids:
        if pid not in measurements:  # with a summary that lists it, _check_files refused
            warnings.warn(f"{root / 'measurements' / f'prism{pid}.csv'}: missing; prism {pid} "
                          "is read without its measured track (the analysis of the "
                          "measurements leaves it out)", RtsgtWarning, stacklevel=2)
    source_files = _prism_files(root / "prisms", _SOURCES_FILE)
    t_ref = None
    xyz, cov, by_source, cov_gp = [], [], {}, []
    for pid, p in prism_files.items():
        header, data = read_table(p, ("t", "x", "y", "z") + tuple(f"cov_{c}" for c in COV3_NAMES))
        t = _col(header, data, "t")
        if t_ref is None:
            t_ref = t
        elif t.shape != t_ref.shape or np.max(np.abs(t - t_ref), initial=0.0) > 1e-6:
            raise InputError(f"query times differ from those of prism {ids[0]}", p)
        xyz.append(data[:, [header.index(c) for c in "xyz"]])
        cov.append(_cov_from(header, data, "cov"))
        sp = source_files.get(pid)
        if sp is not None:
            sh, sd = read_table(sp, ("t",))
            ts = _col(sh, sd, "t")
            if ts.shape != t_ref.shape or np.max(np.abs(ts - t_ref), initial=0.0) > 1e-6:
                raise InputError(f"times differ from those of {p.name}", sp)
            for s in _source_prefixes(sh):
                by_source.setdefault(s, {})[pid] = _cov_from(sh, sd, s)
            if all(f"gp_{c}" in sh for c in COV3_NAMES):
                cov_gp.append(_cov_from(sh, sd, "gp"))
    T, n = t_ref.shape[0], len(ids)
    prisms_by_source = {}
    for s, per in by_source.items():
        arr = np.zeros((T, n, 3, 3))
        for i, pid in enumerate(ids):
            if pid in per:
                arr[:, i] = per[pid]
        prisms_by_source[s] = arr

    # poses
    gt = read_covariance_csv(root / "groundtruth_covariance.csv", run_file=True)
    rej_t, rej_r = _read_rejected(root / "rejected_poses.csv")
    rm_t, rm_xyz, rm_prism, rm_stage = _read_removed(root / "measurements" / "removed.csv")
    ref_xyz, ref_cov = _read_reference(root / "reference.csv", ids)
    ref_cov = _full_reference_cov(summary, ids, ref_cov)
    return RunData(
        name=summary.name if summary.name is not None else root.name, prism_ids=ids,
        measurements={pid: measurements[pid] for pid in ids if pid in measurements},
        prisms_t=t_ref, prisms_xyz=np.stack(xyz, axis=1), prisms_cov=np.stack(cov, axis=1),
        prisms_cov_by_source=dict(zip(_ordered_sources(prisms_by_source),
                                      [prisms_by_source[s] for s in
                                       _ordered_sources(prisms_by_source)], strict=True)),
        groundtruth=gt, rejected_t=rej_t, rejected_reason=rej_r,
        reference_xyz=ref_xyz, reference_cov=ref_cov,
        stations=summary.stations,
        prisms_cov_gp=np.stack(cov_gp, axis=1) if len(cov_gp) == n else None,
        gcp_xyz=summary.gcp_xyz, gcp_names=summary.gcp_names, engine=summary.engine,
        samples=summary.samples, seed=summary.seed, gp_noise=summary.gp_noise,
        summary=summary.document, path=root, removed_t=rm_t, removed_xyz=rm_xyz,
        removed_prism=rm_prism, removed_stage=rm_stage, summary_record=summary,
        measurements_gp_cov={pid: gp_cov[pid] for pid in ids if pid in gp_cov},
    )
