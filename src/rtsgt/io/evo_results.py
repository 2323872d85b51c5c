"""evo-compatible result files: ``rtsgt evaluate --save-results FILE.zip``.

evo's ``evo_ape`` / ``evo_rpe --save_results`` write one metric (the APE or the RPE of one pose
relation) into a zip archive that ``evo_res`` tables and plots many of together. rtsgt writes
the same layout, with its own numbers (it never imports evo, which is GPL):

``info.json``
    ``title`` (evo's, e.g. ``"APE w.r.t. translation part (m)\\n(with SE(3) Umeyama
    alignment)"``: ``evo_res`` compares the titles of the results it aggregates), ``ref_name``,
    ``est_name`` (its base name labels the result in ``evo_res``), ``label``
    (``"APE (m)"``), and rtsgt's additions: ``written_by`` (``"rtsgt"``), ``rtsgt_version``,
    ``metric``, ``pose_relation``, ``alignment``, ``ground_truth`` (its kind),
    ``nees_covariance`` (which covariances entered the NEES), ``drift_lengths`` (the segments
    of the drift, in words).
``stats.json``
    evo's statistics of the error array (``rmse``, ``mean``, ``median``, ``std``, ``min``,
    ``max``, ``sse``: the sum of squares) and rtsgt's extra entries, in the same table of
    ``evo_res``: ``noise_floor`` (the error a perfect estimate would show against this ground
    truth, in the metric's unit), ``rmse_floor_removed`` (``sqrt(max(rmse^2 - floor^2, 0))``),
    ``nees_mean``, ``nees_dof``, ``nees_fraction_inside_95`` and ``nees_consistent`` (1 or 0)
    of the NEES that goes with the metric (APE translation: positions, 3 dof; APE angle or
    full: poses, 6 dof; RPE: the relative ones); the evaluation's drift by segment length
    pooled over all segments (the KITTI leaderboard's averages) with the ground truth's
    floors, in every result whatever its metric (:data:`DRIFT_STATISTICS`: ``drift_*_pct``,
    ``*_deg_per_m`` over segments of path, ``*_m_per_s``, ``*_deg_per_s`` over segments of
    time). A value that does not exist (no covariance, no floor for the full transformation,
    no rotational drift of a position-only ground truth) is ``NaN``, so that every result has
    the same keys (``evo_res --merge`` needs them).
``<name>.npy``
    numpy arrays (``numpy.save``): ``error_array``; ``timestamps`` (estimate clock, s) and
    ``seconds_from_start`` of each error; ``distances_from_start`` (path length of the ground
    truth) and ``distances`` (of the aligned estimate), m, at each error;
    ``alignment_transformation_sim3`` (4x4, when an alignment was made); rtsgt's ``nees``
    (the NEES of each error, NaN without covariances); the drift per segment length
    (:data:`DRIFT_ARRAYS`: ``drift_lengths_m`` and the values of each, as the statistics;
    ``drift_lengths_s`` for time; empty without segments).
``<ref>.tum``, ``<est>.tum``
    The associated ground truth and the aligned estimate (TUM: ``t x y z qx qy qz qw``, named
    after the base names of the inputs, as evo names them after its arguments). For a
    position-only ground truth the reference is the prism's positions with the identity
    rotation (a position has none), the estimate the compared points ``p + R l`` with the
    sensor's rotation.
``rtsgt_evaluation.json``
    The whole ``rtsgt evaluate --json`` object (evo does not read it).

For the RPE, the arrays belong to the second pose ``j`` of each pair ``(i, j)``; rtsgt's path
lengths are along all associated poses (evo's run along the poses of the pairs only); the
trajectories hold all associated poses.

The archive is written whole through a temporary file (:func:`write_evo_result`); an existing
file is replaced only with ``force`` and only when rtsgt wrote it
(:func:`check_results_file`).
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rtsgt import __version__
from rtsgt.choices import POSE_RELATIONS  # evo's --pose_relation -> (title words, unit)
from rtsgt.errors import InputError
from rtsgt.io._parse import atomic_write_bytes
from rtsgt.io.output_dir import check_output_file
from rtsgt.io.trajectory import tum_text
from rtsgt.types import PoseTrajectory

__all__ = ["METRICS", "POSE_RELATIONS", "EvoResult", "check_results_file", "evo_result",
           "is_evo_result_head", "write_evo_result"]

#: Metrics a result file holds (one each, as evo's).
METRICS = ("ape", "rpe")
#: evo's statistics, in its order.
EVO_STATISTICS = ("rmse", "mean", "median", "std", "min", "max", "sse")
#: rtsgt's drift entries of ``stats.json`` (pooled over all segments) and their keys in the
#: ``drift`` section of the JSON: (section kind, key).
DRIFT_STATISTICS = {
    "drift_translation_pct": ("distance", "translation_pct"),
    "drift_translation_floor_pct": ("distance", "translation_floor_pct"),
    "drift_rotation_deg_per_m": ("distance", "rotation_deg_per_m"),
    "drift_rotation_floor_deg_per_m": ("distance", "rotation_floor_deg_per_m"),
    "drift_translation_m_per_s": ("time", "translation_m_per_s"),
    "drift_translation_floor_m_per_s": ("time", "translation_floor_m_per_s"),
    "drift_rotation_deg_per_s": ("time", "rotation_deg_per_s"),
    "drift_rotation_floor_deg_per_s": ("time", "rotation_floor_deg_per_s"),
}
#: rtsgt's extra entries of ``stats.json``.
EXTRA_STATISTICS = ("noise_floor", "rmse_floor_removed", "nees_mean", "nees_dof",
                    "nees_fraction_inside_95", "nees_consistent", *DRIFT_STATISTICS)
#: rtsgt's drift arrays (one value per segment length): the lengths, then the values of
#: :data:`DRIFT_STATISTICS` per length.
DRIFT_ARRAYS = ("drift_lengths_m", "drift_lengths_s", *DRIFT_STATISTICS)
#: Entry holding the complete ``rtsgt evaluate --json`` object.
RTSGT_ENTRY = "rtsgt_evaluation.json"

_ALIGN_TITLES = {
    "none": "\n(not aligned)",
    "se3": "\n(with SE(3) Umeyama alignment)",
    "sim3": "\n(with Sim(3) Umeyama alignment)",
    "scale": "\n(scale corrected)",
    "origin": "\n(with origin alignment)",
    "4dof": "\n(with 4-DOF (yaw) alignment)",
}
_DELTA_UNITS = {"m": "m", "s": "s", "f": "frames"}
_MARKER = '"written_by": "rtsgt"'


@dataclass
class EvoResult:
    """The content of one result file (what evo's ``Result`` holds).

    Attributes
    ----------
    info : dict
    stats : dict of str to float
    np_arrays : dict of str to ndarray
    trajectories : dict of str to PoseTrajectory
        Written as ``<name>.tum``.
    rtsgt : dict
        The ``rtsgt evaluate --json`` object.
    """

    info: dict
    stats: dict
    np_arrays: dict = field(default_factory=dict)
    trajectories: dict = field(default_factory=dict)
    rtsgt: dict = field(default_factory=dict)


def _num(value) -> float:
    return math.nan if value is None else float(value)


def _path_length(position: np.ndarray) -> np.ndarray:
    """Path length from the first position, m (evo's ``distances``)."""
    steps = np.linalg.norm(np.diff(position, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def _drift_entries(drift: dict | None) -> tuple[dict, dict, str]:
    """The drift's pooled statistics, per-length arrays and description in words from the
    ``drift`` section of the JSON (None: no drift; NaN values, empty arrays)."""
    stats, arrays, words = {}, {}, []
    for kind, unit in (("distance", "m"), ("time", "s")):
        sec = None if drift is None else drift.get(kind)
        rows = [] if sec is None else sec["by_length"]
        arrays[f"drift_lengths_{unit}"] = np.array([r[f"length_{unit}"] for r in rows], float)
        if sec is not None:
            lengths = ", ".join(f"{v:g}" for v in sec[f"lengths_{unit}"])
            words.append(f"{lengths} {unit} ({sec['lengths_from']}, "
                         f"{sec['n_segments']} segments)")
        for name, (k, key) in DRIFT_STATISTICS.items():
            if k != kind:
                continue
            stats[name] = math.nan if sec is None else _num(sec[key])
            arrays[name] = np.array([_num(r[key]) for r in rows], float)
    return stats, arrays, "; ".join(words) or "none"


def _title(metric: str, relation: str, result) -> str:
    words, unit = POSE_RELATIONS[relation]
    if metric == "ape":
        title = f"APE w.r.t. {words} ({unit})"
    else:
        pairs = "all pairs" if result.rpe_all_pairs else "consecutive pairs"
        delta = float(result.rpe_delta)
        if result.rpe_delta_unit == "f" and delta.is_integer():
            delta = int(delta)  # frames: evo writes an integer
        title = (f"RPE w.r.t. {words} ({unit})\nfor delta = {delta} "
                 f"({_DELTA_UNITS[result.rpe_delta_unit]}) using {pairs}")
    al = result.alignment
    title += _ALIGN_TITLES.get(al.method, f"\n(with {al.method} alignment)")
    if al.method not in ("none", "origin") and 0 < al.n_used < np.shape(result.t)[0]:
        title += f" (aligned poses: {al.n_used})"
    if al.weighted:
        title += " (covariance-weighted)"
    return title


def _positions_only(result) -> bool:
    return hasattr(result, "est_poses")


def evo_result(result, *, metric: str = "ape", relation: str = "trans_part",
               ref_name: str = "reference", est_name: str = "estimate") -> EvoResult:
    """The evo result of one metric of an rtsgt evaluation.

    Parameters
    ----------
    result : EvaluationResult or PositionEvaluationResult
    metric : {"ape", "rpe"}
    relation : {"trans_part", "angle_deg", "full"}
        evo's pose relation; a position-only ground truth has ``trans_part`` only.
    ref_name, est_name : str
        The ground truth and the estimate as the user named them (evo: its arguments).

    Raises
    ------
    InputError
        Unknown metric or relation, a rotation relation of a position-only ground truth, or
        the RPE of an evaluation without RPE pairs.
    """
    if metric not in METRICS:
        raise InputError(f"unknown metric {metric!r}; expected one of {', '.join(METRICS)}")
    if relation not in POSE_RELATIONS:
        raise InputError(f"unknown pose relation {relation!r}; expected one of "
                         f"{', '.join(POSE_RELATIONS)}")
    positions = _positions_only(result)
    if positions and relation != "trans_part":
        raise InputError(f"a position-only ground truth has no {relation} (no rotation): use "
                         "trans_part")
    errors = result.ape if metric == "ape" else result.rpe
    if errors is None:
        raise InputError(f"no RPE to save: {result.rpe_absent_reason}")
    rel = relation if not positions else "trans_part"
    err = {"trans_part": lambda: errors.translation_error,
           "angle_deg": lambda: errors.rotation_error_deg,
           "full": lambda: errors.full_error}[rel]()
    stats_obj = {"trans_part": errors.translation_m,
                 "angle_deg": getattr(errors, "rotation_deg", None),
                 "full": getattr(errors, "full", None)}[rel]
    err = np.asarray(err, dtype=float)
    stats = {k: float(v) for k, v in stats_obj.to_dict().items()}
    stats["sse"] = float(np.sum(err**2))

    floor = result.noise_floor
    prefix = "ape" if metric == "ape" else "rpe"
    floors = {"trans_part": ("translation_m", "translation_rmse_floor_removed_m"),
              "angle_deg": ("rotation_deg", "rotation_rmse_floor_removed_deg")}.get(rel)
    if floors is None:
        stats["noise_floor"] = stats["rmse_floor_removed"] = math.nan
    else:
        stats["noise_floor"] = _num(getattr(floor, f"{prefix}_{floors[0]}"))
        stats["rmse_floor_removed"] = _num(getattr(floor, f"{prefix}_{floors[1]}"))
    nees_name = {("ape", True): "position", ("ape", False): "pose",
                 ("rpe", True): "relative_position", ("rpe", False): "relative_pose"}[
        (metric, rel == "trans_part")]
    nees = getattr(result.nees, nees_name)
    stats["nees_mean"] = math.nan if nees is None else float(nees.mean)
    stats["nees_dof"] = math.nan if nees is None else float(nees.dof)
    stats["nees_fraction_inside_95"] = (math.nan if nees is None
                                        else float(nees.fraction_inside_95))
    stats["nees_consistent"] = math.nan if nees is None else float(bool(nees.consistent))
    everything = result.to_dict()
    drift_stats, drift_arrays, drift_words = _drift_entries(everything.get("drift"))
    stats.update(drift_stats)

    t = np.asarray(result.t, dtype=float)
    gt_pos = np.asarray(result.gt.position, dtype=float)
    est_pos = np.asarray(result.est.position, dtype=float)
    idx = np.arange(t.size) if metric == "ape" else np.asarray(errors.pairs)[:, 1]
    nees_values = np.full(err.shape, math.nan)
    if nees is not None and np.shape(nees.values) == err.shape:
        nees_values = np.asarray(nees.values, dtype=float)
    arrays = {
        "error_array": err,
        "seconds_from_start": t[idx] - t[0],
        "timestamps": t[idx],
        "distances_from_start": _path_length(gt_pos)[idx],
        "distances": _path_length(est_pos)[idx],
    }
    if result.alignment.method != "none":
        arrays["alignment_transformation_sim3"] = result.alignment.as_matrix()
    arrays["nees"] = nees_values
    arrays.update({k: drift_arrays[k] for k in DRIFT_ARRAYS})

    if positions:
        identity = np.tile([0.0, 0.0, 0.0, 1.0], (t.size, 1))
        ref_traj = PoseTrajectory(np.asarray(result.gt.t, dtype=float), gt_pos, identity)
        est_traj = PoseTrajectory(t, est_pos, result.est_poses.quat_xyzw)
    else:
        ref_traj = PoseTrajectory(result.gt.t, result.gt.position, result.gt.quat_xyzw)
        est_traj = PoseTrajectory(result.est.t, result.est.position, result.est.quat_xyzw)
    ref_key, est_key = Path(ref_name).name or "reference", Path(est_name).name or "estimate"
    if ref_key == est_key:
        ref_key, est_key = f"reference_{ref_key}", f"estimate_{est_key}"
    words, unit = POSE_RELATIONS[rel]
    info = {
        "title": _title(metric, rel, result),
        "ref_name": str(ref_name),
        "est_name": str(est_name),
        "label": f"{metric.upper()} ({unit})",
        "written_by": "rtsgt",
        "rtsgt_version": __version__,
        "metric": metric.upper(),
        "pose_relation": words,
        "alignment": result.alignment.method,
        "ground_truth": ("positions " if positions else "") + str(result.association.ground_truth),
        "nees_covariance": str(result.nees.covariance),
        "drift_lengths": drift_words,
    }
    return EvoResult(info, stats, arrays, {ref_key: ref_traj, est_key: est_traj}, everything)


def evo_result_bytes(res: EvoResult) -> bytes:
    """The zip archive of ``res`` (module docstring); ``info.json`` first and stored, so that
    :func:`is_evo_result_head` recognises it."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as archive:
        archive.writestr("info.json", json.dumps(res.info, indent=1))
        archive.writestr("stats.json", json.dumps(res.stats))
        for name, array in res.np_arrays.items():
            npy = io.BytesIO()
            np.save(npy, np.asarray(array), allow_pickle=False)
            archive.writestr(f"{name}.npy", npy.getvalue())
        for name, traj in res.trajectories.items():
            archive.writestr(f"{name}.tum", tum_text(traj, comment=f"rtsgt evaluate: {name}"))
        archive.writestr(RTSGT_ENTRY, json.dumps(res.rtsgt, indent=1,
                                                 default=_json_default))
    return buf.getvalue()


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def is_evo_result_head(head: str) -> bool:
    """Whether the first bytes of a file (as text) are those of a result file rtsgt wrote:
    a zip archive whose first entry is ``info.json`` naming rtsgt as its writer."""
    return head.startswith("PK\x03\x04") and "info.json" in head[:200] and _MARKER in head


def check_results_file(path: str | os.PathLike, *, option: str = "--save-results",
                       force: bool = False,
                       inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Check, before any work, that a result file may be written at ``path``; returns it.

    A new file is written; an existing one is replaced only with ``force`` and only if rtsgt
    wrote it (:func:`rtsgt.io.output_dir.check_output_file`, :func:`is_evo_result_head`).

    Raises
    ------
    InputError
        ``path`` is a directory, its directory is missing, it is an input, or it exists and
        ``force`` is not given or rtsgt did not write it.
    """
    out = check_output_file(path, option=option, written_by_rtsgt=is_evo_result_head,
                            inputs=inputs)
    if (out.exists() or out.is_symlink()) and not force:
        raise InputError(f"exists; use --force to replace a result file that rtsgt wrote, or "
                         f"give another file name ({option})", out)
    return out


def write_evo_result(path: str | os.PathLike, res: EvoResult, *, option: str = "--save-results",
                     force: bool = False, inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Write ``res`` to ``path`` whole (a temporary file renamed into place), after
    :func:`check_results_file` (again, just before the rename); returns the path."""
    inputs = tuple(inputs)
    out = check_results_file(path, option=option, force=force, inputs=inputs)
    atomic_write_bytes(out, evo_result_bytes(res), before_replace=lambda: check_results_file(
        path, option=option, force=force, inputs=inputs))
    return out
