"""Files of an rtsgt run directory, written atomically.

Layout of ``OUT/`` (every number in SI units, stated in the headers)::

    groundtruth.tum                  t x y z qx qy qz qw (s, m, unit quaternion scalar last)
    groundtruth_covariance.csv       t,x,y,z,qx,qy,qz,qw,cov_00,...,cov_55
                                     6x6 row-major, order (x, y, z, rx, ry, rz), m^2 / rad^2,
                                     left perturbation in the world frame
    rejected_poses.csv               t,reason for every pose removed by a gate
    prisms/prism<i>.csv              interpolated track: t,x,y,z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz
    prisms/prism<i>_sources.csv      per-source covariance at the same times: t,<source>_xx,...
    measurements/prism<i>.csv        measured track (world frame) after filtering, with the
                                     covariance given to the GP, the range and every source's
                                     covariance: t,x,y,z,cov_xx..cov_zz,range_m,<source>_xx..
    measurements/removed.csv         the measurements the filters removed, in the world frame:
                                     t,prism,station,x,y,z,stage,reason (stage: module1 = rates
                                     of change or status, module2 = outside the intervals where
                                     every prism is tracked; reason: the filter's reason, e.g.
                                     rate_hz, status, not_all_tracked, short_interval)
    reference.csv                    reference prisms in the body frame: name,x,y,z,cov_xx..cov_zz
    summary.json                     schema (name, version), inputs, parameters, version,
                                     seed, counts removed per filter and gate, Qc, calibration,
                                     medians, timings, the weather file and its coverage, the
                                     tracked inter-prism distances against the surveyed ones,
                                     warnings (read back only by rtsgt.io.run_reader.read_summary)
    .rtsgt-output.json               manifest of the files rtsgt wrote (rtsgt.io.output_dir)

The directory is assembled under a temporary name beside ``OUT`` and renamed at the end, and
an existing ``OUT`` is replaced only if rtsgt wrote it (:mod:`rtsgt.io.output_dir`): a crash
never leaves a half-written run, and ``--force`` never deletes a user's files.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from rtsgt import __version__
from rtsgt.interpolation.prisms import gp_covariance
from rtsgt.io._parse import atomic_write_text, table_text
from rtsgt.io.output_dir import OutputDir
from rtsgt.io.trajectory import TUM_COMMENT, write_covariance_csv, write_tum

COV3_NAMES = ("xx", "xy", "xz", "yy", "yz", "zz")
#: Name and version of the layout of ``summary.json`` (its ``schema`` key); read back by
#: :func:`rtsgt.io.run_reader.read_summary`, which refuses a newer version. A summary without
#: the key is of the layout before it (version 0).
SUMMARY_SCHEMA_NAME = "rtsgt-run"
SUMMARY_SCHEMA_VERSION = 1
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
    """Write columns of numbers with a one-line header (no comment character), atomically."""
    data = np.column_stack([np.asarray(c, dtype=float).reshape(len(columns[0]), -1) for c in columns])
    atomic_write_text(path, table_text(data, header=",".join(header), fmt=fmt))


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


def run_summary(result, inputs: dict | None = None) -> dict:
    """The ``summary.json`` content of a run (see the module docstring).

    Besides the inputs, parameters and results: ``weather``, the weather record used (file,
    span, sampling interval) and how it covers the measurements
    (:func:`rtsgt.measurement.weather.weather_coverage`; null without weather);
    ``inter_prism_distances``, per prism pair the median deviation of the tracked distance from
    the surveyed one, its predicted sigma and their ratio
    (:func:`rtsgt.filtering.gates.surveyed_distance_check`); ``warnings``, every warning of the
    run, once each, as printed on the terminal.
    """

    opt = result.options
    cal = result.calibration
    gt = result.groundtruth
    est = result.estimate
    rejected = {}
    for reason in np.unique(result.rejection_reasons[~result.keep]):
        rejected[str(reason)] = int(np.sum(result.rejection_reasons[~result.keep] == reason))
    stations = {}
    for sid, T in cal.transforms.items():
        stations[sid] = {
            "matrix": T.as_matrix(),
            "yaw_deg": float(np.degrees(T.yaw)),
            "translation_m": T.translation,
            "sigma_translation_mm": np.sqrt(np.diag(T.covariance)[:3]) * 1e3,
            "sigma_rotation_mrad": np.sqrt(np.diag(T.covariance)[3:]) * 1e3,
        }
    prisms = {}
    for pid, tr in result.tracks.items():
        gp = result.gps[pid]
        sig = np.sqrt(np.trace(result.prisms.cov[:, result.prism_ids.index(pid)], axis1=1, axis2=2))
        prisms[pid] = {
            "station": tr.station,
            "measurements_used": len(tr),
            "qc_m2_s3": gp.qc,
            "qc_fit": result.qc_info.get(pid, {}),
            "median_sigma_mm": float(np.median(sig) * 1e3),
        }
    res = cal.residuals
    return {
        "schema": {"name": SUMMARY_SCHEMA_NAME, "version": SUMMARY_SCHEMA_VERSION},
        "software": {"name": "rtsgt", "version": __version__},
        "deployment": result.data.name,
        "inputs": inputs or {},
        "parameters": {
            "engine": opt.pose.engine,
            "samples": opt.pose.samples,
            "seed": opt.seed,
            "rate_hz": opt.interpolation.rate_hz,
            "qc": opt.interpolation.qc,
            "max_gap_s": opt.interpolation.max_gap_s,
            "gp_noise": opt.interpolation.gp_noise,
            "noise_sources": list(result.noise_model.sources),
            "instrument": result.data.instrument.name,
            "filter": _report_dict(opt.filter),
            "distance_gate_m": opt.pose.distance_gate_m,
            "uncertainty_gate_m": opt.pose.uncertainty_gate_m,
        },
        "filters": {k: _report_dict(v) for k, v in result.filter_reports.items()},
        "gates": _report_dict(result.gate_report),
        "intervals_s": result.intervals,
        "poses": {
            "queried": int(len(est)),
            "kept": int(len(gt)),
            "rejected_by_reason": rejected,
            "first_t": float(gt.t[0]) if len(gt) else None,
            "last_t": float(gt.t[-1]) if len(gt) else None,
        },
        "median_uncertainty": _median_sigmas(gt),
        "prisms": prisms,
        "calibration": {
            "reference_station": cal.reference_station,
            "stations": stations,
            "residuals_mm": {
                "median": float(np.median(res.distance_m) * 1e3) if len(res) else None,
                "max": float(np.max(res.distance_m) * 1e3) if len(res) else None,
                "count": int(len(res)),
            },
            # world position of each GCP (m), for the figures and the report
            "gcp_world": _gcp_world_dict(result),
            # correlation of the station calibrations (pipeline.StationCoupling): origins m,
            # cross-covariances of the left perturbations (x, y, z, rx, ry, rz)
            "coupling": result.coupling.to_dict() if result.coupling is not None else None,
        },
        "weather": getattr(result, "weather_coverage", None),
        "inter_prism_distances": getattr(result, "distance_check", {}),
        "warnings": list(getattr(result, "warnings", [])),
        "timings_s": result.timings_s,
    }


def _write_removed(path: Path, removed) -> None:
    """``measurements/removed.csv`` from the run's
    :class:`~rtsgt.filtering.modules.RemovedMeasurements`."""
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("t,prism,station,x,y,z,stage,reason\n")
        for t, p, st, xyz, stage, why in zip(removed.t, removed.prism, removed.station,
                                             removed.xyz, removed.stage, removed.reason,
                                             strict=True):
            fh.write(f"{t:.9f},{p},{st},{xyz[0]:.6f},{xyz[1]:.6f},{xyz[2]:.6f},{stage},{why}\n")


def _gcp_world_dict(result) -> dict[str, list[float]]:
    return {n: [float(v) for v in p] for n, p in result.gcp_world.items()}


def write_run(result, out: str | Path, *, force: bool = False, inputs: dict | None = None,
              protect: Iterable[str | Path] = (),
              finish: Callable[[Path, Path], None] | None = None) -> Path:
    """Write every file of a run directory atomically; returns the final directory.

    ``force`` replaces an earlier rtsgt output at ``out`` (never anything else, nor a
    directory holding one of the paths in ``protect``, the run's inputs); ``inputs`` is
    recorded in ``summary.json``. ``finish(tmp, final)``, if given, is called once every file
    of the run is in the temporary directory ``tmp``, to add more (the HTML report) before the
    directory is put in place as ``final``: if it fails, nothing is left.
    """
    output = OutputDir(out, "run", force=force, inputs=protect)
    with output as tmp:
        gt = result.groundtruth
        write_tum(tmp / "groundtruth.tum", gt, decimals=(9, 12), comment=GROUNDTRUTH_TUM_COMMENT)
        write_covariance_csv(tmp / "groundtruth_covariance.csv", gt, digits=17)
        rej = ~result.keep
        with open(tmp / "rejected_poses.csv", "w", encoding="utf-8") as fh:
            fh.write("t,reason\n")
            for t, r in zip(result.prisms.t[rej], result.rejection_reasons[rej], strict=True):
                fh.write(f"{t:.9f},{r}\n")
        (tmp / "prisms").mkdir()
        (tmp / "measurements").mkdir()
        cov_cols = [f"cov_{c}" for c in COV3_NAMES]
        P = result.prisms
        for i, pid in enumerate(result.prism_ids):
            write_csv(tmp / "prisms" / f"prism{pid}.csv", ["t", "x", "y", "z", *cov_cols],
                      [P.t, P.xyz[:, i], cov3_to_columns(P.cov[:, i])])
            srcs = list(P.cov_by_source)
            write_csv(tmp / "prisms" / f"prism{pid}_sources.csv",
                      ["t", "gp_xx", "gp_xy", "gp_xz", "gp_yy", "gp_yz", "gp_zz"]
                      + [f"{s}_{c}" for s in srcs for c in COV3_NAMES],
                      [P.t, cov3_to_columns(P.cov_gp[:, i])]
                      + [cov3_to_columns(P.cov_by_source[s][:, i]) for s in srcs])
            tr = result.tracks[pid]
            srcs = list(tr.cov_by_source)
            write_csv(tmp / "measurements" / f"prism{pid}.csv",
                      ["t", "x", "y", "z", *cov_cols, "range_m"]
                      + [f"{s}_{c}" for s in srcs for c in COV3_NAMES],
                      [tr.t, tr.xyz, cov3_to_columns(gp_covariance(tr, result.options.interpolation.gp_noise)),
                       tr.range_m if tr.range_m is not None else np.full(len(tr), np.nan)]
                      + [cov3_to_columns(tr.cov_by_source[s]) for s in srcs])
        _write_removed(tmp / "measurements" / "removed.csv", result.removed)
        ref = result.data.reference
        with open(tmp / "reference.csv", "w", encoding="utf-8") as fh:
            fh.write("name,x,y,z," + ",".join(cov_cols) + "\n")
            blocks = cov3_to_columns(ref.cov_blocks())
            for name, p, c in zip(ref.names, ref.xyz, blocks, strict=True):
                fh.write(",".join([name] + [f"{v:.17g}" for v in (*p, *c)]) + "\n")
        summary = run_summary(result, inputs)
        summary["reference"] = {"names": list(ref.names), "xyz_m": ref.xyz, "cov_m2": ref.cov,
                                "frame": ref.frame}
        write_json(tmp / "summary.json", summary)
        if finish is not None:
            finish(tmp, output.final)
    return output.final
