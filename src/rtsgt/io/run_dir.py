"""The run directory: the run record (:class:`rtsgt.record.RunRecord`) on disk, written by
:func:`write_run` and read back by :func:`read_run` (the only writer and reader of its files).

The directory is assembled under a temporary name and renamed at the end, replacing only an
rtsgt output (:mod:`rtsgt.io.output_dir`). A position-only run
(:class:`~rtsgt.record.PositionRunRecord`) writes its prisms, measurements and summary only
(:func:`read_position_run`; :func:`read_any_run` takes either). :func:`read_summary` is the
only reader of ``summary.json`` (its ``schema``, the fallbacks of older layouts, a typed
:class:`RunSummary`). Columns are found by name; a damaged run is an error naming the file.
Layout and rules: docs/file-formats.md#run-directory,
docs/file-formats.md#reading-a-run-directory-back,
docs/file-formats.md#position-only-run-directory.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import re
import signal
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path

import numpy as np

from rtsgt import __version__
from rtsgt.checks.verdict import record_verdict
from rtsgt.choices import CALIBRATION_METHODS, CALIBRATION_MODELS, WRITE_PROCESSES_ENV
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.filtering import FilterParams
from rtsgt.filtering.modules import RemovedMeasurements
from rtsgt.interpolation.gp import PRIORS
from rtsgt.io._parse import (
    TABLE_CHUNK_VALUES,
    atomic_write_bytes,
    csv_table,
    read_table,
    split_rows,
    table_chunks,
    to_float,
)
from rtsgt.io.output_dir import OutputDir
from rtsgt.io.trajectory import (
    TUM_COMMENT,
    read_covariance_csv,
    write_covariance_csv,
    write_tum,
)
from rtsgt.noise.coupling import StationCoupling
from rtsgt.options import (
    CORRELATED_NOISE,
    GP_NOISE,
    MOTION_PRIORS,
    OUTLIER_WINDOWS,
    PRIOR_CHOICES,
    InterpolationOptions,
    PoseOptions,
    RunOptions,
)
from rtsgt.pose.reference import ReferencePoints
from rtsgt.record import (
    MIN_POSE_PRISMS,
    RUN_SCHEMA_NAME,
    RUN_SCHEMA_VERSION,
    PositionRunRecord,
    RunComputation,
    RunRecord,
    no_removed_measurements,
    ordered_sources,
)
from rtsgt.shared import POSE_COMPONENTS, SharedFactor
from rtsgt.types import PrismTrack

__all__ = ["COV3_NAMES", "POSITIONS_KIND", "PrismSummary", "RunSummary", "columns_to_cov3",
           "cov3_to_columns", "read_any_run", "read_position_run", "read_run", "read_summary",
           "read_table", "relocate_summary", "run_summary", "station_positions_from_summary",
           "write_csv", "write_run"]

COV3_NAMES = ("xx", "xy", "xz", "yy", "yz", "zz")
#: ``ground_truth.kind`` of the summary of a position-only run (absent: a pose run).
POSITIONS_KIND = "positions"
#: The comment line of ``groundtruth.tum``.
GROUNDTRUTH_TUM_COMMENT = f"{TUM_COMMENT} (world frame = reference station)"
_IU = np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2])


def cov3_to_columns(cov: np.ndarray) -> np.ndarray:
    """(N, 3, 3) -> (N, 6) upper-triangle columns xx, xy, xz, yy, yz, zz."""
    return cov[:, _IU[0], _IU[1]]


def columns_to_cov3(cols: np.ndarray) -> np.ndarray:
    """(N, 6) upper-triangle columns -> (N, 3, 3) symmetric matrices."""
    cols = np.asarray(cols, dtype=float)
    out = np.empty((cols.shape[0], 3, 3))
    out[:, _IU[0], _IU[1]] = cols
    out[:, _IU[1], _IU[0]] = cols
    return out


def write_csv(path: Path, header: list[str], columns: list[np.ndarray], fmt: str = "%.17g") -> None:
    """Write columns of numbers with a one-line header (no comment character), atomically, a
    block of rows at a time (:func:`~rtsgt.io._parse.table_chunks`; neither the whole table
    nor its text is ever in memory at once)."""
    n = len(columns[0])
    cols = [np.asarray(c, dtype=float).reshape(n, -1) for c in columns]
    rows = max(1, TABLE_CHUNK_VALUES // max(sum(c.shape[1] for c in cols), 1))

    def pieces():
        yield (",".join(header) + "\n").encode("utf-8")
        for s in range(0, n, rows):
            block = np.column_stack([c[s:s + rows] for c in cols])
            yield from (p.encode("utf-8") for p in table_chunks(block, fmt=fmt, rows=rows))

    atomic_write_bytes(path, pieces())


def write_json(path: Path, obj: dict) -> None:
    path.write_text(json.dumps(obj, indent=2, default=_json_default) + "\n", encoding="utf-8")


def relocate_summary(run_dir: Path, old: Path, new: Path) -> None:
    """Rewrite the paths under ``old`` that ``run_dir/summary.json`` records as under ``new``
    (a run written, with its inputs, in a temporary directory that becomes ``new``)."""

    def moved(x):
        if isinstance(x, dict):
            return {k: moved(v) for k, v in x.items()}
        if isinstance(x, list):
            return [moved(v) for v in x]
        if isinstance(x, str) and x.startswith(str(old)):
            return str(new) + x[len(str(old)):]
        return x

    path = Path(run_dir) / "summary.json"
    write_json(path, moved(json.loads(path.read_text(encoding="utf-8"))))


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _report_dict(rep) -> dict:
    """A filter or gate report as plain JSON data (dataclass, mapping or object with counts)."""

    if rep is None:
        return {}
    if hasattr(rep, "as_dict"):
        return json.loads(json.dumps(rep.as_dict(), default=_json_default))
    if dataclasses.is_dataclass(rep):
        return json.loads(json.dumps(dataclasses.asdict(rep), default=_json_default))
    if isinstance(rep, dict):
        return json.loads(json.dumps(rep, default=_json_default))
    return {"counts": getattr(rep, "counts", str(rep))}


def _median_sigmas(traj) -> dict:
    if len(traj) == 0:
        return {"translation_mm": None, "rotation_mrad": None}
    tr = np.sqrt(np.trace(traj.cov[:, :3, :3], axis1=1, axis2=2)) * 1e3
    rot = np.sqrt(np.trace(traj.cov[:, 3:, 3:], axis1=1, axis2=2)) * 1e3
    return {"translation_mm": float(np.median(tr)), "rotation_mrad": float(np.median(rot))}


def run_summary(record: RunRecord | PositionRunRecord, inputs: dict | None = None) -> dict:
    """The ``summary.json`` content of a run just computed (docs/file-formats.md#summaryjson);
    a position-only run has ``ground_truth`` and ``positions`` in place of the poses, gates,
    inter-prism distances and reference. ValueError for a record read from files (no
    :attr:`~rtsgt.record.RunRecord.computation`)."""
    c = _computation(record)
    opt = record.options
    cal = c.calibration
    prisms = _summary_prisms(record, c)
    head = {
        "schema": {"name": RUN_SCHEMA_NAME, "version": RUN_SCHEMA_VERSION},
        "software": {"name": "rtsgt", "version": __version__},
        "deployment": record.name,
        "inputs": inputs or {},
    }
    parameters = _summary_parameters(opt, c)
    filters = {k: _report_dict(v) for k, v in c.filter_reports.items()}
    calibration = _summary_calibration(record, cal)
    tail = {
        "self_checks": record.self_checks,
        # the time-correlated noise the static-stretch check found, as the GPs carried it
        # (rtsgt.noise.correlated)
        "interpolation": {"correlated_noise": record.correlated_noise},
        "warnings": list(record.warnings),
        # the run's verdict from its self-checks (rtsgt.checks.verdict)
        "verdict": record_verdict(record).to_dict(),
        "timings_s": c.timings_s,
    }
    if isinstance(record, PositionRunRecord):
        t = record.prisms_t
        return {
            **head,
            "ground_truth": {
                "kind": POSITIONS_KIND, "prisms": list(record.prism_ids),
                "why": (f"{len(record.prism_ids)} tracked prism"
                        f"{'s' if len(record.prism_ids) > 1 else ''}: a pose needs "
                        f"{MIN_POSE_PRISMS}"),
                "files": [f"prisms/prism{pid}.csv" for pid in record.prism_ids],
            },
            "parameters": parameters, "filters": filters, "intervals_s": record.intervals,
            "positions": {"queried": int(t.shape[0]),
                          "first_t": float(t[0]) if t.size else None,
                          "last_t": float(t[-1]) if t.size else None},
            "prisms": prisms, "calibration": calibration, "weather": record.weather_coverage,
            **tail,
        }
    gt = record.groundtruth
    reasons, counts = np.unique(record.rejected_reason, return_counts=True)
    ref = record.reference
    return {
        **head,
        "parameters": parameters,
        "filters": filters,
        "gates": _report_dict(c.gate_report),
        "intervals_s": record.intervals,
        "poses": {
            "queried": int(record.prisms_t.shape[0]),
            "kept": int(len(gt)),
            "rejected_by_reason": {str(r): int(n) for r, n in zip(reasons, counts, strict=True)},
            "first_t": float(gt.t[0]) if len(gt) else None,
            "last_t": float(gt.t[-1]) if len(gt) else None,
        },
        "median_uncertainty": _median_sigmas(gt),
        "prisms": prisms,
        "calibration": calibration,
        "weather": record.weather_coverage,
        "inter_prism_distances": record.distance_check,
        # the joint engine's estimates besides the poses (rtsgt.stages.joint.joint_summary)
        **({"joint": record.joint} if record.joint else {}),
        "self_checks": tail.pop("self_checks"),
        "interpolation": tail.pop("interpolation"),
        "warnings": tail.pop("warnings"),
        "verdict": tail.pop("verdict"),
        "timings_s": tail.pop("timings_s"),
        "reference": {"names": list(ref.names), "xyz_m": ref.xyz, "cov_m2": ref.cov,
                      "frame": ref.frame},
    }


def _summary_prisms(record: RunRecord | PositionRunRecord, c: RunComputation) -> dict:
    """``prisms`` of ``summary.json``: per prism its station, measurements, ``Qc``, prior,
    ``Qc`` fit and median sigma (mm)."""
    prisms = {}
    for i, (pid, tr) in enumerate(record.measurements.items()):
        sig = np.sqrt(np.trace(record.prisms_cov[:, i], axis1=1, axis2=2))
        prisms[pid] = {
            "station": tr.station,
            "measurements_used": len(tr),
            "qc_m2_s3": record.qc[pid],
            "prior": record.prior.get(pid, "wnoa"),
            "qc_fit": c.qc_info.get(pid, {}),
            "median_sigma_mm": float(np.median(sig) * 1e3),
        }
    return prisms


def _summary_parameters(opt: RunOptions, c: RunComputation) -> dict:
    """``parameters`` of ``summary.json``: the options the run was made with."""
    return {
        "engine": opt.pose.engine,
        "registration": opt.pose.registration,
        "samples": opt.pose.samples,
        "seed": opt.seed,
        "calibration_model": opt.calibration.model,
        "calibration_weighting": opt.calibration.weighting,
        "calibration_method": opt.calibration.method,
        "rate_hz": opt.interpolation.rate_hz,
        "qc": opt.interpolation.qc,
        "max_gap_s": opt.interpolation.max_gap_s,
        "gp_noise": opt.interpolation.gp_noise,
        "motion_prior": opt.interpolation.motion_prior,
        "outlier_windows": opt.interpolation.outlier_windows,
        "prior": opt.interpolation.prior,
        "correlated_noise": opt.interpolation.correlated_noise,
        "noise_sources": list(c.noise_model.sources),
        "instrument": c.data.instrument.name,
        "filter": _report_dict(opt.filter),
        "distance_gate_m": opt.pose.distance_gate_m,
        "uncertainty_gate_m": opt.pose.uncertainty_gate_m,
        # the joint engine's switch, only where it has a meaning
        **({"clocks": opt.pose.clocks} if opt.joint else {}),
    }


def _summary_calibration(record: RunRecord | PositionRunRecord, cal) -> dict:
    """``calibration`` of ``summary.json``: each station's transform and sigmas, the GCP
    residuals, the GCPs' world positions and the stations' coupling."""
    stations = {}
    for sid, T in cal.transforms.items():
        stations[sid] = {
            "matrix": T.as_matrix(),
            "yaw_deg": float(np.degrees(T.yaw)),
            "translation_m": T.translation,
            "sigma_translation_mm": np.sqrt(np.diag(T.covariance)[:3]) * 1e3,
            "sigma_rotation_mrad": np.sqrt(np.diag(T.covariance)[3:]) * 1e3,
        }
    res = cal.residuals
    return {
        "reference_station": cal.reference_station,
        "method": cal.method,
        "model": cal.model,
        "stations": stations,
        "residuals_mm": {
            "median": float(np.median(res.distance_m) * 1e3) if len(res) else None,
            "max": float(np.max(res.distance_m) * 1e3) if len(res) else None,
            "count": int(len(res)),
        },
        # world position of each GCP (m), for the figures and the report
        "gcp_world": {n: [float(v) for v in p]
                      for n, p in zip(record.gcp_names, _gcp_rows(record), strict=True)},
        # correlation of the station calibrations (noise.coupling.StationCoupling):
        # origins m, cross-covariances of the left perturbations (x, y, z, rx, ry, rz)
        "coupling": record.coupling.to_dict() if record.coupling is not None else None,
    }

def _computation(record: RunRecord) -> RunComputation:
    if record.computation is None:
        raise ValueError("This run record was read from files: only a run just computed "
                         "(rtsgt.pipeline.run_pipeline) is written")
    return record.computation


def _gcp_rows(record: RunRecord) -> np.ndarray:
    return np.empty((0, 3)) if record.gcp_xyz is None else record.gcp_xyz


def _write_removed(path: Path, removed: RemovedMeasurements) -> None:
    """``measurements/removed.csv`` from the run's
    :class:`~rtsgt.filtering.modules.RemovedMeasurements`."""
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("t,prism,station,x,y,z,stage,reason\n")
        for t, p, st, xyz, stage, why in zip(removed.t, removed.prism, removed.station,
                                             removed.xyz, removed.stage, removed.reason,
                                             strict=True):
            fh.write(f"{t:.9f},{p},{st},{xyz[0]:.6f},{xyz[1]:.6f},{xyz[2]:.6f},{stage},{why}\n")


#: The file of the ground truth's error split (:mod:`rtsgt.shared`).
SPLIT_FILE = "groundtruth_shared.csv"
_VARYING = tuple(f"varying_{i}{j}" for i in range(6) for j in range(6))


def _write_split(path: Path, split: SharedFactor) -> None:
    """``groundtruth_shared.csv``: t, the varying covariance, the shared factor's columns."""
    shared = [f"shared.{name}.{c}" for name in split.names for c in POSE_COMPONENTS]
    # column (name, component) of the file is L[:, component, name]
    factor = np.swapaxes(split.factor, 1, 2).reshape(len(split), -1)
    write_csv(path, ["t", *_VARYING, *shared],
              [split.t, split.varying_cov.reshape(-1, 36), factor])


def _read_split(path: Path, t_gt: np.ndarray) -> SharedFactor | None:
    """The split written by :func:`_write_split`, None when the file is absent (older run)."""
    if not path.is_file():
        return None
    header, data = read_table(path, ("t", *_VARYING))
    t = _col(header, data, "t")
    if t.shape != t_gt.shape or np.max(np.abs(t - t_gt), initial=0.0) > 1e-6:
        raise InputError("times differ from those of groundtruth_covariance.csv", path)
    V = data[:, [header.index(c) for c in _VARYING]].reshape(-1, 6, 6)
    names: list[str] = []
    for col in header:
        if col.startswith("shared."):
            name = col[len("shared."):].rsplit(".", 1)[0]
            if name not in names:
                names.append(name)
    cols = [f"shared.{n}.{c}" for n in names for c in POSE_COMPONENTS]
    missing = [c for c in cols if c not in header]
    if missing:
        raise InputError(f"missing column {missing[0]}", path)
    L = data[:, [header.index(c) for c in cols]].reshape(-1, len(names), 6)
    return SharedFactor(t, np.ascontiguousarray(np.swapaxes(L, 1, 2)), tuple(names), V)


def _write_prisms(tmp: Path, record: RunRecord | PositionRunRecord) -> None:
    """``prisms/`` and ``measurements/`` of a run (either kind), in ``tmp``."""
    (tmp / "prisms").mkdir()
    (tmp / "measurements").mkdir()
    cov_cols = [f"cov_{c}" for c in COV3_NAMES]
    t = record.prisms_t
    for i, pid in enumerate(record.prism_ids):
        write_csv(tmp / "prisms" / f"prism{pid}.csv", ["t", "x", "y", "z", *cov_cols],
                  [t, record.prisms_xyz[:, i], cov3_to_columns(record.prisms_cov[:, i])])
        srcs = list(record.prisms_cov_by_source)
        write_csv(tmp / "prisms" / f"prism{pid}_sources.csv",
                  ["t", "gp_xx", "gp_xy", "gp_xz", "gp_yy", "gp_yz", "gp_zz"]
                  + [f"{s}_{c}" for s in srcs for c in COV3_NAMES],
                  [t, cov3_to_columns(record.prisms_cov_gp[:, i])]
                  + [cov3_to_columns(record.prisms_cov_by_source[s][:, i]) for s in srcs])
        tr = record.measurements[pid]
        srcs = list(tr.cov_by_source)
        # the scale of Qc on the interval that starts at each measurement (none after
        # the last one)
        scale = ([] if pid not in record.qc_scale
                 else [np.append(record.qc_scale[pid], np.nan)])
        write_csv(tmp / "measurements" / f"prism{pid}.csv",
                  ["t", "x", "y", "z", *cov_cols, "range_m"]
                  + [f"{s}_{c}" for s in srcs for c in COV3_NAMES]
                  + ["qc_scale"] * len(scale),
                  [tr.t, tr.xyz, cov3_to_columns(record.measurements_gp_cov[pid]),
                   tr.range_m if tr.range_m is not None else np.full(len(tr), np.nan)]
                  + [cov3_to_columns(tr.cov_by_source[s]) for s in srcs] + scale)


def write_run(record: RunRecord | PositionRunRecord, out: str | Path, *, force: bool = False,
              inputs: dict | None = None, protect: Iterable[str | Path] = (),
              finish: Callable[[Path, Path], None] | None = None) -> Path:
    """Write every file of a run directory atomically; returns the final directory.

    ``record`` is a run just computed (:func:`rtsgt.pipeline.run_pipeline`). ``force``
    replaces an earlier rtsgt output at ``out`` (never anything else, nor a directory holding
    one of the paths in ``protect``, the run's inputs); ``inputs`` is recorded in
    ``summary.json``. ``finish(tmp, final)``, if given, is called once every file of the run is
    in the temporary directory ``tmp``, to add more (the HTML report) before the directory is
    put in place as ``final``: if it fails, nothing is left.
    """
    summary = run_summary(record, inputs)
    output = OutputDir(out, "run", force=force, inputs=protect)
    with output as tmp:
        if isinstance(record, PositionRunRecord):  # prisms/ is the ground truth: no pose
            _write_prisms(tmp, record)
            _write_removed(tmp / "measurements" / "removed.csv", record.removed)
            write_json(tmp / "summary.json", summary)
            if finish is not None:
                finish(tmp, output.final)
            return output.final
        gt = record.groundtruth

        def ground_truth_files() -> None:  # about half of the text, written beside the rest
            write_covariance_csv(tmp / "groundtruth_covariance.csv", gt, digits=17)
            if record.groundtruth_split is not None:
                _write_split(tmp / SPLIT_FILE, record.groundtruth_split)

        beside = _beside(ground_truth_files)
        try:
            _write_pose_run_rest(tmp, record, summary)
        except BaseException:
            beside(check=False)  # never leave the child writing into a directory removed
            raise
        beside()
        if finish is not None:
            finish(tmp, output.final)
    return output.final


def _write_pose_run_rest(tmp: Path, record: RunRecord, summary: dict) -> None:
    """The files of a pose run besides the ground truth's covariances (:func:`write_run`)."""
    gt = record.groundtruth
    write_tum(tmp / "groundtruth.tum", gt, decimals=(9, 12), comment=GROUNDTRUTH_TUM_COMMENT)
    with open(tmp / "rejected_poses.csv", "w", encoding="utf-8") as fh:
        fh.write("t,reason\n")
        for t, r in zip(record.rejected_t, record.rejected_reason, strict=True):
            fh.write(f"{t:.9f},{r}\n")
    _write_prisms(tmp, record)
    _write_removed(tmp / "measurements" / "removed.csv", record.removed)
    ref = record.reference
    cov_cols = [f"cov_{c}" for c in COV3_NAMES]
    with open(tmp / "reference.csv", "w", encoding="utf-8") as fh:
        fh.write("name,x,y,z," + ",".join(cov_cols) + "\n")
        blocks = cov3_to_columns(ref.cov_blocks())
        for name, p, c in zip(ref.names, ref.xyz, blocks, strict=True):
            fh.write(",".join([name] + [f"{v:.17g}" for v in (*p, *c)]) + "\n")
    write_json(tmp / "summary.json", summary)


#: Processes that write a run directory's files: 1 (this one) unless the environment variable
#: :data:`~rtsgt.choices.WRITE_PROCESSES_ENV` says more, as the command line sets it (2): the
#: ground truth's covariances are then written by a forked child (:func:`_beside`) while this
#: process writes the rest. The text of an hour's run (about 170 MB, formatted by Python under
#: its interpreter lock) then takes about half as long.
_WRITE_PROCESSES_SET = os.environ.get(WRITE_PROCESSES_ENV, "").strip()
WRITE_PROCESSES = max(1, int(_WRITE_PROCESSES_SET)) if _WRITE_PROCESSES_SET.isdigit() else 1


def _beside(job: Callable[[], None]) -> Callable[..., None]:
    """Start ``job`` (it writes files) in a forked child when :data:`WRITE_PROCESSES` > 1
    and the platform forks, else run it now; returns the function that waits for it and
    (unless called with ``check=False``) raises, in this process, an ``OSError`` with the
    child's message if it failed."""
    if WRITE_PROCESSES < 2 or not hasattr(os, "fork"):
        job()
        return lambda check=True: None
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: write, report a failure through the pipe, never return
        os.close(read)
        code = 1
        try:
            signal.signal(signal.SIGINT, signal.SIG_DFL)  # an interrupt ends it at once
            job()
            code = 0
        except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises
            os.write(write, str(exc).encode("utf-8", "replace")[:4000])
        finally:
            os._exit(code)
    os.close(write)

    def wait(check: bool = True) -> None:
        with os.fdopen(read, "rb") as fh:
            message = fh.read().decode("utf-8", "replace")
        _, status = os.waitpid(pid, 0)
        if check and status != 0:
            raise OSError(message or f"the process writing the ground truth files ended with "
                                     f"status {status}")

    return wait


# ------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------

_PRISM_FILE = re.compile(r"^prism(?P<id>.+?)\.csv$")
_SOURCES_FILE = re.compile(r"^prism(?P<id>.+?)_sources\.csv$")


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
    return ordered_sources(found)


def _prism_files(folder: Path, pattern: re.Pattern) -> dict[str, Path]:
    if not folder.is_dir():
        raise InputError("folder not found (is this an rtsgt run directory?)", folder)
    out = {}
    for p in folder.iterdir():
        m = pattern.match(p.name)
        if m and not (pattern is _PRISM_FILE and p.name.endswith("_sources.csv")):
            out[m.group("id")] = p
    return dict(sorted(out.items(), key=lambda kv: _natural_key(kv[0])))


def _read_measurements(path: Path, pid: str,
                       ) -> tuple[PrismTrack, np.ndarray | None, np.ndarray | None]:
    """The measured track, the file's ``cov_*`` columns (the covariance given to the GP;
    None without them) and its ``qc_scale`` per interval (None without the column)."""
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
    scale = None
    if "qc_scale" in header:
        scale = _col(header, data, "qc_scale")[:-1]
        bad = np.flatnonzero(~(np.isfinite(scale) & (scale > 0)))
        if bad.size:
            raise InputError(f"qc_scale: expected a finite number > 0, got {scale[bad[0]]!r}",
                             path, int(bad[0]) + 2)
    try:
        return PrismTrack(_col(header, data, "t"), data[:, [header.index(c) for c in "xyz"]],
                          cov, by_source, pid, "world", None, rng), file_cov, scale
    except ValueError as exc:
        raise InputError(str(exc), path) from exc


def _read_reference(path: Path, summary: RunSummary) -> ReferencePoints:
    """Every reference prism of ``reference.csv`` (names as ``"2"`` for ``"prism2"``), with the
    joint covariance of ``summary.json`` (``reference.cov_m2``, correlated between prisms when
    the body frame is defined by surveyed points) when it matches the file's blocks, else the
    block-diagonal one of the file."""
    need = ("name", "x", "y", "z") + tuple(f"cov_{c}" for c in COV3_NAMES)
    header, numbers, lines = csv_table(path, need)
    tokens = split_rows(lines, numbers, path, header, ",")
    values = to_float(tokens[:, [header.index(c) for c in need[1:]]], numbers, path, need[1:],
                      finite=False)
    names = tuple(_strip_prism(x) for x in tokens[:, header.index("name")].tolist())
    blocks = columns_to_cov3(values[:, 3:])
    n = len(names)
    cov = np.zeros((3 * n, 3 * n))
    for i in range(n):
        cov[3 * i:3 * i + 3, 3 * i:3 * i + 3] = blocks[i]
    full = summary.reference_cov
    listed = (None if summary.reference_names is None
              else tuple(_strip_prism(x) for x in summary.reference_names))
    # the joint covariance must be of these names, with the blocks of reference.csv on its
    # diagonal; else the files disagree and the file's blocks are what is known
    if (full is not None and listed == names and full.shape == (3 * n, 3 * n)
            and np.allclose(np.diagonal(full.reshape(n, 3, n, 3), axis1=0, axis2=2),
                            np.diagonal(cov.reshape(n, 3, n, 3), axis1=0, axis2=2),
                            rtol=1e-9, atol=1e-15)):
        cov = full
    try:
        return ReferencePoints(names, values[:, :3], cov, summary.reference_frame)
    except ValueError as exc:
        raise InputError(str(exc), path) from None


def _strip_prism(name: str) -> str:
    """``"prism2"`` and ``"2"`` both name prism ``"2"``."""
    return name[5:] if name.lower().startswith("prism") and len(name) > 5 else name


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


def _read_removed(path: Path) -> RemovedMeasurements:
    """``measurements/removed.csv`` (optional; older runs lack the ``reason`` column)."""
    if not path.is_file():
        return no_removed_measurements()
    with path.open(encoding="utf-8", newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        return no_removed_measurements()
    header = [h.strip() for h in rows[0]]
    missing = [c for c in _REMOVED_COLUMNS if c not in header]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}; header is "
                         f"{','.join(header)}", path, 1)
    idx = {c: header.index(c) for c in (*_REMOVED_COLUMNS, "reason") if c in header}
    t, xyz, text = [], [], {c: [] for c in ("prism", "station", "stage", "reason")}
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
        for c, values in text.items():
            values.append(row[idx[c]].strip() if c in idx else "")
    strings = {c: np.asarray(v, dtype=str) for c, v in text.items()}
    return RemovedMeasurements(np.asarray(t, dtype=float), strings["prism"], strings["station"],
                               np.asarray(xyz, dtype=float).reshape(-1, 3), strings["stage"],
                               strings["reason"])


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
    #: The GP's power spectral density Qc, m^2/s^3 (m^2/s^5 for the WNOJ prior; None when
    #: not recorded).
    qc_m2_s3: np.ndarray | None = None
    #: The GP's motion prior, "wnoa" or "wnoj" ("wnoa" when not recorded: an older run).
    prior: str = "wnoa"


#: The options of a run whose summary does not say them (the engine was the linear one, the
#: registration unweighted).
_OLDEST_OPTIONS = RunOptions().updated(engine="linear", registration="unweighted")


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
    #: ``parameters`` (``options`` in older layouts) as options; a summary without them is of a
    #: run before rtsgt recorded the engine, which was the linear one.
    options: RunOptions = field(default_factory=lambda: _OLDEST_OPTIONS)
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
    #: ``warnings``, ``weather`` and ``inter_prism_distances`` (empty when absent).
    warnings: tuple[str, ...] = ()
    weather_coverage: dict | None = None
    distance_check: dict = field(default_factory=dict)
    #: ``self_checks`` (empty for a run written before rtsgt made them).
    self_checks: dict = field(default_factory=dict)
    #: ``interpolation.correlated_noise`` (empty for a run written before rtsgt carried it).
    correlated_noise: dict = field(default_factory=dict)
    #: ``ground_truth.kind``: ``"poses"`` (absent: a run with poses) or
    #: :data:`POSITIONS_KIND` (a run with one or two tracked prisms).
    ground_truth: str = "poses"


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
    if (not isinstance(schema, dict) or schema.get("name") != RUN_SCHEMA_NAME
            or not isinstance(version, int) or isinstance(version, bool) or version < 0):
        raise InputError(f"'schema': expected {{\"name\": \"{RUN_SCHEMA_NAME}\", "
                         f"\"version\": <integer>}}, got {schema!r}"[:300], path)
    if version > RUN_SCHEMA_VERSION:
        raise InputError(f"summary schema version {version} is newer than this rtsgt reads "
                         f"(version {RUN_SCHEMA_VERSION}): the run was written by a later "
                         "rtsgt; upgrade rtsgt to read it", path)
    return version


def read_summary(run_dir: str | PathLike) -> RunSummary:
    """Read ``run_dir/summary.json``, the only reader of that file, into a :class:`RunSummary`
    (the defaults, ``exists`` False, when absent). Invalid JSON, a newer schema or an entry of
    the wrong type raise :class:`~rtsgt.errors.InputError` naming the file."""
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

    name = _find(doc, "name", "deployment", default=None)
    if isinstance(name, dict):
        name = name.get("name")
    software = doc.get("software")

    prisms = _read_summary_prisms(doc, path)
    iv = doc.get("intervals_s")
    if iv is not None:
        try:
            iv = np.asarray(iv, dtype=float).reshape(-1, 2)
        except (TypeError, ValueError) as exc:
            raise InputError(f"bad intervals_s: {exc}", path) from None

    ref, ref_names, ref_xyz, ref_cov = _read_summary_reference(doc, path)
    calibration = _section(doc, "calibration", path)
    coupling = None
    if calibration.get("coupling") is not None:  # runs written before rtsgt carried it
        try:
            coupling = StationCoupling.from_dict(calibration["coupling"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"bad calibration.coupling: {exc}", path) from None
    gcp_xyz, gcp_names = _gcp_from_summary(doc)

    options = _summary_options(params, param, path)
    return RunSummary(
        path=path, document=doc, exists=True, schema_version=version,
        written_by_rtsgt=isinstance(software, dict) and software.get("name") == "rtsgt",
        name=None if name is None else str(name), options=options,
        uncertainty_measure=str(_section(doc, "gates", path).get("uncertainty_measure",
                                                                  "max_std")),
        prisms=prisms, intervals_s=iv, reference_names=ref_names, reference_xyz=ref_xyz,
        reference_cov=ref_cov, reference_frame=str(ref.get("frame", "body")),
        stations=station_positions_from_summary(doc), gcp_xyz=gcp_xyz, gcp_names=gcp_names,
        coupling=coupling, warnings=tuple(str(w) for w in doc.get("warnings") or ()),
        weather_coverage=doc.get("weather"),
        distance_check=doc.get("inter_prism_distances") or {},
        self_checks=_section(doc, "self_checks", path),
        correlated_noise=_section(_section(doc, "interpolation", path), "correlated_noise",
                                  path),
        ground_truth=_ground_truth_kind(doc, path),
    )


def _read_summary_prisms(doc: dict, path: Path) -> dict[str, PrismSummary]:
    """``prisms`` of a summary: each prism's station, ``Qc`` and prior."""
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
        prior = str(info.get("prior", "wnoa"))
        if prior not in PRIORS:
            raise InputError(f"prism {pid}: prior: expected {' or '.join(map(repr, PRIORS))}, "
                             f"got {prior!r}", path)
        prisms[str(pid)] = PrismSummary(None if station is None else str(station), q, prior)
    return prisms


def _read_summary_reference(doc: dict, path: Path) -> tuple:
    """``reference`` of a summary: the section, its names, points (n, 3) and covariance."""
    ref = _section(doc, "reference", path)
    ref_names = ref.get("names")
    if ref_names is not None:
        if not isinstance(ref_names, list):
            raise InputError(f"reference.names: expected a list, got {ref_names!r}"[:200], path)
        ref_names = tuple(str(x) for x in ref_names)
    ref_xyz = None if ref.get("xyz_m") is None else _array(ref["xyz_m"], "reference.xyz_m", path)
    ref_cov = (None if ref.get("cov_m2") is None
               else _array(ref["cov_m2"], "reference.cov_m2", path))
    return ref, ref_names, ref_xyz, ref_cov

def _ground_truth_kind(doc: dict, path: Path) -> str:
    """``ground_truth.kind`` of a summary (``"poses"`` when absent)."""
    kind = _section(doc, "ground_truth", path).get("kind", "poses")
    if kind not in ("poses", POSITIONS_KIND):
        raise InputError(f"ground_truth.kind: expected 'poses' or {POSITIONS_KIND!r}, got "
                         f"{kind!r}"[:200], path)
    return kind


def _summary_options(params: dict, param: Callable, path: Path) -> RunOptions:
    """The run's options from ``parameters`` (``param``: a parameter, or its older top-level
    key); each value meets the rule of :class:`~rtsgt.options.RunOptions`."""
    try:
        samples = int(param("samples", PoseOptions.samples))
        seed = param("seed", 0)
        seed = int(seed) if seed is not None else 0
    except (TypeError, ValueError) as exc:
        raise InputError(f"parameters: samples and seed must be integers: {exc}", path) from None

    def choice(name: str, default: str, choices: tuple[str, ...]) -> str:
        value = str(param(name, default))
        if value not in choices:
            raise InputError(f"{name}: expected {' or '.join(map(repr, choices))}, got "
                             f"{value!r}", path)
        return value

    gp_noise = choice("gp_noise", InterpolationOptions.gp_noise, GP_NOISE)
    # the defaults of a run written before each option: one Qc per track, the windows of
    # distance rejections kept, the paper's WNOA prior, the measurements taken as independent
    motion_prior = choice("motion_prior", "constant", MOTION_PRIORS)
    outlier_windows = choice("outlier_windows", "keep", OUTLIER_WINDOWS)
    prior = choice("prior", "wnoa", PRIOR_CHOICES)
    correlated_noise = choice("correlated_noise", "ignore", CORRELATED_NOISE)
    changes = {
        "engine": str(param("engine", _OLDEST_OPTIONS.pose.engine)), "samples": samples,
        "registration": str(param("registration", _OLDEST_OPTIONS.pose.registration)),
        "seed": seed, "gp_noise": gp_noise, "motion_prior": motion_prior,
        "outlier_windows": outlier_windows, "prior": prior, "correlated_noise": correlated_noise,
        # runs written before the 4-DOF and the dynamic calibrations: 6 DOF, from the GCPs
        "model": choice("calibration_model", "6dof", CALIBRATION_MODELS),
        "method": choice("calibration_method", "gcp", CALIBRATION_METHODS),
        "max_gap_s": _positive(params, "max_gap_s", InterpolationOptions.max_gap_s, path),
        "distance_gate_m": _positive(params, "distance_gate_m", PoseOptions.distance_gate_m,
                                     path),
        "uncertainty_gate_m": _positive(params, "uncertainty_gate_m",
                                        PoseOptions.uncertainty_gate_m, path),
    }
    if params.get("clocks") is not None:
        changes["clocks"] = params["clocks"]
    if params.get("rate_hz") is not None:
        changes["rate_hz"] = _positive(params, "rate_hz", InterpolationOptions.rate_hz, path)
    if params.get("qc") is not None:
        changes["qc"] = params["qc"]
    if isinstance(params.get("filter"), dict):
        try:
            changes["filter"] = FilterParams(**params["filter"])
        except (TypeError, InputError) as exc:
            raise InputError(f"parameters.filter: {exc}", path) from None
    try:
        return _OLDEST_OPTIONS.updated(**changes)
    except InputError as exc:
        raise InputError(f"parameters: {exc.bare_message}", path) from None


def _check_files(root: Path, summary: RunSummary) -> None:
    """Refuse a run missing a file its summary says was written; warn for an optional one
    (docs/file-formats.md#reading-a-run-directory-back)."""
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
        optional = (((root / "rejected_poses.csv", "the rejected poses"),)
                    if summary.ground_truth != POSITIONS_KIND else ())
        for path, lost in (*optional, (root / "measurements" / "removed.csv",
                                       "the measurements the filters removed")):
            if not path.is_file():
                warnings.warn(f"{path}: missing from this run of rtsgt; the analysis and the "
                              f"figures go on without {lost}", RtsgtWarning, stacklevel=3)


def read_run(run_dir: str | PathLike) -> RunRecord:
    """Read a run directory written by :func:`write_run` back into its
    :class:`~rtsgt.record.RunRecord` (without ``computation``; rejected poses, removed
    measurements, GCPs and stations optional). A missing or malformed file raises
    :class:`~rtsgt.errors.InputError` (docs/file-formats.md#reading-a-run-directory-back)."""
    root = Path(run_dir)
    if not root.is_dir():
        raise InputError("run directory not found", root)
    summary = read_summary(root)
    if summary.ground_truth == POSITIONS_KIND:
        raise InputError("a position-only run (no pose: fewer than 3 tracked prisms): its "
                         "ground truth is prisms/prism<i>.csv (rtsgt evaluate --lever-arm; "
                         "rtsgt.io.run_dir.read_position_run)", root)
    _check_files(root, summary)
    measurements, gp_cov, qc_scale = _read_measured(root)
    ids, t_ref, prisms_xyz, prisms_cov, prisms_by_source, cov_gp = _read_prisms(
        root, measurements)

    reference = _read_reference(root / "reference.csv", summary)
    missing = [p for p in ids if p not in reference.names]
    if missing:
        raise InputError(f"no reference for prism {missing[0]}; names: "
                         f"{', '.join(reference.names)}", root / "reference.csv")
    _stations_of_tracks(measurements, summary)
    rej_t, rej_r = _read_rejected(root / "rejected_poses.csv")
    groundtruth = read_covariance_csv(root / "groundtruth_covariance.csv", run_file=True)
    return RunRecord(
        name=summary.name if summary.name is not None else root.name, prism_ids=ids,
        measurements={pid: measurements[pid] for pid in ids if pid in measurements},
        prisms_t=t_ref, prisms_xyz=prisms_xyz, prisms_cov=prisms_cov,
        prisms_cov_by_source=prisms_by_source,
        groundtruth=groundtruth, rejected_t=rej_t, rejected_reason=rej_r, reference=reference,
        options=summary.options, schema_version=summary.schema_version,
        stations=summary.stations,
        prisms_cov_gp=cov_gp,
        gcp_xyz=summary.gcp_xyz, gcp_names=summary.gcp_names,
        qc={pid: info.qc_m2_s3 for pid, info in summary.prisms.items()
            if info.qc_m2_s3 is not None},
        qc_scale={pid: qc_scale[pid] for pid in ids if pid in qc_scale},
        prior={pid: info.prior for pid, info in summary.prisms.items()},
        intervals=summary.intervals_s, uncertainty_measure=summary.uncertainty_measure,
        coupling=summary.coupling, removed=_read_removed(root / "measurements" / "removed.csv"),
        measurements_gp_cov={pid: gp_cov[pid] for pid in ids if pid in gp_cov},
        warnings=summary.warnings, weather_coverage=summary.weather_coverage,
        distance_check=summary.distance_check, self_checks=summary.self_checks,
        correlated_noise=summary.correlated_noise,
        groundtruth_split=_read_split(root / SPLIT_FILE, groundtruth.t),
        joint=summary.document.get("joint") or {}, summary=summary.document, path=root,
    )


def read_position_run(run_dir: str | PathLike) -> PositionRunRecord:
    """Read a position-only run directory back into its record; a run with poses (read by
    :func:`read_run`) or a missing or malformed file raises :class:`~rtsgt.errors.InputError`."""
    root = Path(run_dir)
    if not root.is_dir():
        raise InputError("run directory not found", root)
    summary = read_summary(root)
    if summary.ground_truth != POSITIONS_KIND:
        raise InputError("not a position-only run (summary.json has no ground_truth.kind "
                         f"{POSITIONS_KIND!r}): read it with read_run", root)
    _check_files(root, summary)
    measurements, gp_cov, qc_scale = _read_measured(root)
    ids, t_ref, prisms_xyz, prisms_cov, prisms_by_source, cov_gp = _read_prisms(
        root, measurements)
    _stations_of_tracks(measurements, summary)
    try:
        return PositionRunRecord(
            name=summary.name if summary.name is not None else root.name, prism_ids=ids,
            measurements={pid: measurements[pid] for pid in ids if pid in measurements},
            prisms_t=t_ref, prisms_xyz=prisms_xyz, prisms_cov=prisms_cov,
            prisms_cov_by_source=prisms_by_source, prisms_cov_gp=cov_gp,
            options=summary.options, schema_version=summary.schema_version,
            stations=summary.stations, gcp_xyz=summary.gcp_xyz, gcp_names=summary.gcp_names,
            qc={pid: info.qc_m2_s3 for pid, info in summary.prisms.items()
                if info.qc_m2_s3 is not None},
            qc_scale={pid: qc_scale[pid] for pid in ids if pid in qc_scale},
            prior={pid: info.prior for pid, info in summary.prisms.items()},
            intervals=summary.intervals_s, coupling=summary.coupling,
            removed=_read_removed(root / "measurements" / "removed.csv"),
            measurements_gp_cov={pid: gp_cov[pid] for pid in ids if pid in gp_cov},
            warnings=summary.warnings, weather_coverage=summary.weather_coverage,
            self_checks=summary.self_checks, correlated_noise=summary.correlated_noise,
            summary=summary.document, path=root)
    except ValueError as exc:
        raise InputError(str(exc), root / "prisms") from None


def read_any_run(run_dir: str | PathLike) -> RunRecord | PositionRunRecord:
    """:func:`read_position_run` or :func:`read_run`, as ``summary.json`` says."""
    summary = read_summary(run_dir)
    if summary.ground_truth == POSITIONS_KIND:
        return read_position_run(run_dir)
    return read_run(run_dir)


def _read_measured(root: Path) -> tuple[dict[str, PrismTrack], dict[str, np.ndarray],
                                        dict[str, np.ndarray]]:
    """``measurements/prism<i>.csv``: the tracks, the covariance given to each GP and the
    scale of ``Qc`` per interval (where written)."""
    meas_files = _prism_files(root / "measurements", _PRISM_FILE)
    read = {pid: _read_measurements(p, pid) for pid, p in meas_files.items()}
    measurements = {pid: tr for pid, (tr, _, _) in read.items()}
    gp_cov = {pid: c for pid, (_, c, _) in read.items() if c is not None}
    qc_scale = {pid: s for pid, (_, _, s) in read.items() if s is not None}
    return measurements, gp_cov, qc_scale


def _stations_of_tracks(measurements: dict[str, PrismTrack], summary: RunSummary) -> None:
    """The station of each track, as ``summary.json`` says (in place)."""
    for pid, tr in measurements.items():
        info = summary.prisms.get(pid)
        if info is not None and info.station is not None:
            measurements[pid] = dataclasses.replace(tr, station=info.station)


def _read_prisms(root: Path, measurements: dict[str, PrismTrack]):
    """``prisms/prism<i>.csv`` and ``prisms/prism<i>_sources.csv``: the prism ids, the query
    times, positions (T, n, 3), total covariances (T, n, 3, 3), per-source covariances and
    the GP's (None unless every prism has it)."""
    prism_files = _prism_files(root / "prisms", _PRISM_FILE)
    if not prism_files:
        raise InputError("no prisms/prism<i>.csv files", root / "prisms")
    ids = tuple(prism_files)
    for pid in ids:
        if pid not in measurements:  # with a summary that lists it, _check_files refused
            warnings.warn(f"{root / 'measurements' / f'prism{pid}.csv'}: missing; prism {pid} "
                          "is read without its measured track (the analysis of the "
                          "measurements leaves it out)", RtsgtWarning, stacklevel=3)
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
    for s in ordered_sources(by_source):
        arr = np.zeros((T, n, 3, 3))
        for i, pid in enumerate(ids):
            if pid in by_source[s]:
                arr[:, i] = by_source[s][pid]
        prisms_by_source[s] = arr
    return (ids, t_ref, np.stack(xyz, axis=1), np.stack(cov, axis=1), prisms_by_source,
            np.stack(cov_gp, axis=1) if len(cov_gp) == n else None)

