"""The use case "evaluate an estimated trajectory against an rtsgt ground truth": read the
ground truth and the estimate, evaluate (:mod:`rtsgt.evaluation`), write evo's result files.
Ground truths and gap limits: docs/evaluating.md.
"""

from __future__ import annotations

import dataclasses
import warnings
from os import PathLike
from pathlib import Path

from rtsgt.choices import DEFAULT_MAX_DT_S
from rtsgt.choices import TRAJECTORY_FORMATS as FORMATS
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.evaluation import (
    EvaluationOptions,
    EvaluationResult,
    PositionEvaluationResult,
    evaluate,
    evaluate_positions,
)
from rtsgt.evaluation.associate import GroundTruthQuery, ValidatedGroundTruth
from rtsgt.evaluation.groundtruth import ContinuousGroundTruth, ContinuousPositionGroundTruth
from rtsgt.evaluation.lever_arm import parse_lever_arm
from rtsgt.io.evo_results import evo_result, write_evo_result
from rtsgt.io.positions import position_csv_form, read_position_csv, read_positions
from rtsgt.io.run_dir import POSITIONS_KIND, read_any_run, read_run, read_summary
from rtsgt.io.trajectory import (
    attach_covariance,
    read_covariance_csv,
    read_groundtruth_dir,
    read_trajectory,
)
from rtsgt.pose import POSE_ENGINES
from rtsgt.types import PoseTrajectory, PositionTrajectory

__all__ = ["DEFAULT_MAX_GAP_FILE_S", "GT_MODES", "gt_engines", "load_ground_truth",
           "load_position_ground_truth", "read_ground_truth", "read_position_ground_truth",
           "run_evaluation", "run_gap_limit", "save_evo_results", "wants_positions"]

#: Ground-truth modes of ``--gt-mode``.
GT_MODES = ("auto", "continuous", "discrete")


def gt_engines() -> tuple[str, ...]:
    """The pose engines of ``--gt-engine``: ``run`` (the run's own) and the engines."""
    return ("run", *POSE_ENGINES)


#: Default ``--max-gap`` (s) for a ground-truth trajectory file.
DEFAULT_MAX_GAP_FILE_S = DEFAULT_MAX_DT_S


def run_gap_limit(gt: object, gt_dir: str | Path) -> float | None:
    """The run's own gap limit, s (a continuous ground truth's, else ``summary.json``'s);
    None for a trajectory file or a directory without a summary."""
    options = getattr(gt, "options", None)
    if options is not None:  # a continuous ground truth: its run's options
        return float(options.interpolation.max_gap_s)
    if not Path(gt_dir).is_dir():
        return None
    summary = read_summary(gt_dir)
    return float(summary.options.interpolation.max_gap_s) if summary.exists else None


def read_ground_truth(run_dir: str | PathLike, *, engine: str | None = None,
                      samples: int | None = None, seed: int | None = None
                      ) -> ContinuousGroundTruth:
    """The continuous ground truth of a run directory (its ``measurements/`` and
    ``summary.json``); ``engine``, ``samples``, ``seed`` override the run's."""
    root = _run_with_measurements(run_dir)
    record = read_run(root)
    _check_summary(record, root)
    return ContinuousGroundTruth.from_record(record, engine=engine, samples=samples, seed=seed)


def read_position_ground_truth(run_dir: str | PathLike, prism: str | None = None
                               ) -> ContinuousPositionGroundTruth:
    """The continuous position ground truth of one prism of a run directory of either kind
    (``prism`` may be left out when the run tracked one)."""
    root = _run_with_measurements(run_dir)
    record = read_any_run(root)
    _check_summary(record, root)
    return ContinuousPositionGroundTruth.from_record(record, prism)


def _run_with_measurements(run_dir: str | PathLike) -> Path:
    root = Path(run_dir)
    if not (root / "measurements").is_dir():
        raise InputError(
            "no measurements/ folder: not an rtsgt run directory with measured tracks", root)
    return root


def _check_summary(record, root: Path) -> None:
    if not record.summary:
        raise InputError("missing or empty summary.json (the run's Qc and options)",
                         root / "summary.json")


def load_ground_truth(
    gt_dir: str | Path, *, mode: str = "auto", engine: str | None = None
) -> PoseTrajectory | ValidatedGroundTruth | GroundTruthQuery:
    """The ground truth of ``GT_DIR``: continuous from a run directory with ``measurements/``
    (``mode`` ``auto`` or ``continuous``; ``engine`` None: the run's), else the stored poses
    or the trajectory file."""
    gt_path = Path(gt_dir)
    if _continuous(gt_path, mode):
        return read_ground_truth(gt_path, engine=engine)
    if _is_run_dir(gt_path):
        return read_groundtruth_dir(gt_path)
    if gt_path.exists():
        return read_trajectory(gt_path)
    raise InputError("ground truth not found", gt_path)


def _is_run_dir(path: Path) -> bool:
    return path.is_dir() and not (path / "metadata.yaml").exists()


def _continuous(path: Path, mode: str) -> bool:
    """Whether ``mode`` (checked) takes the continuous ground truth of ``path``."""
    if mode not in GT_MODES:
        raise InputError(f"unknown ground-truth mode {mode!r}; expected one of "
                         f"{', '.join(GT_MODES)}")
    if _is_run_dir(path) and mode != "discrete" and (path / "measurements").is_dir():
        # a joint run's poses are not recomputed at other times: auto takes its stored poses
        # (docs/pipeline.md#the-joint-engine)
        return mode == "continuous" or not read_summary(path).options.joint
    if mode == "continuous":
        raise InputError("a continuous ground truth needs an rtsgt run directory with "
                         "measurements/", path)
    return False


def wants_positions(gt_dir: str | Path, *, lever_arm=None, prism: str | None = None,
                    gt_topic: str | None = None) -> bool:
    """Whether ``GT_DIR`` is evaluated as a position-only ground truth: it is one (a run of one
    or two prisms, a position CSV), or ``lever_arm``, ``prism`` or ``gt_topic`` asks for it."""
    if lever_arm is not None or prism is not None or gt_topic is not None:
        return True
    path = Path(gt_dir)
    if _is_run_dir(path):
        return read_summary(path).ground_truth == POSITIONS_KIND
    return position_csv_form(path) is not None


def load_position_ground_truth(
    gt_dir: str | Path, *, prism: str | None = None, topic: str | None = None,
    mode: str = "auto",
) -> PositionTrajectory | ContinuousPositionGroundTruth:
    """The position-only ground truth of ``GT_DIR``: one prism of a run directory
    (continuous, or with ``mode`` ``discrete`` its ``prisms/prism<i>.csv``), a bag's
    ``topic`` or a position CSV."""
    path = Path(gt_dir)
    if _continuous(path, mode):
        return read_position_ground_truth(path, prism)
    if _is_run_dir(path):
        files = sorted(p.name[len("prism"):-len(".csv")] for p in (path / "prisms").glob(
            "prism*.csv") if not p.name.endswith("_sources.csv"))
        if prism is None and len(files) != 1:
            raise InputError("choose the prism (--prism): prisms/ has "
                             f"{', '.join(files) or 'none'}", path)
        pid = files[0] if prism is None else str(prism)
        if pid not in files:
            raise InputError(f"no prisms/prism{pid}.csv; prisms: {', '.join(files)}", path)
        return read_position_csv(path / "prisms" / f"prism{pid}.csv", name=f"prism {pid}")
    if prism is not None:
        raise InputError("--prism selects a prism of an rtsgt run directory", path)
    if not path.exists():
        raise InputError("ground truth not found", path)
    return read_positions(path, topic=topic)


def run_evaluation(
    gt_dir: str | Path,
    est_file: str | Path,
    *,
    fmt: str | None = None,
    topic: str | None = None,
    child_frame: str | None = None,
    timestamps: str | Path | None = None,
    est_cov: str | Path | None = None,
    options: EvaluationOptions | None = None,
    max_gap: float | None = None,
    gt_mode: str = "auto",
    gt_engine: str | None = None,
    lever_arm=None,
    prism: str | None = None,
    gt_topic: str | None = None,
) -> EvaluationResult | PositionEvaluationResult:
    """Read the ground truth and the estimate and evaluate them with ``options`` (against a
    position-only ground truth, :func:`wants_positions`, with ``lever_arm``, ``"x,y,z"`` m in
    the sensor frame, zero with a warning when not given). ``max_gap`` (s) replaces
    ``options.max_dt`` (default: :func:`run_gap_limit`, else :data:`DEFAULT_MAX_GAP_FILE_S`);
    ``gt_mode``, ``gt_engine`` (``"run"``: the run's): :func:`load_ground_truth`."""
    engines = gt_engines()
    if gt_engine is not None and gt_engine not in engines:
        raise InputError(
            f"unknown ground-truth engine {gt_engine!r}; expected one of {', '.join(engines)}")
    if wants_positions(gt_dir, lever_arm=lever_arm, prism=prism, gt_topic=gt_topic):
        if options is not None and options.mounting is not None:
            raise InputError(
                f"{gt_dir}: a position-only ground truth gives no rotation to fit a mounting "
                "to (--mounting); give the prism's lever arm in the sensor frame with "
                "--lever-arm (--estimate lever, lever-xy, clock to estimate it and the clock)")
        lever = parse_lever_arm(lever_arm)
        gt_pos = load_position_ground_truth(gt_dir, prism=prism, topic=gt_topic, mode=gt_mode)
        if lever_arm is None and not (options is not None and options.estimate):
            warnings.warn("position-only ground truth without --lever-arm: the estimate's "
                          "sensor origin is compared with the tracked point (lever arm 0; the "
                          "estimate's rotation does not enter)", RtsgtWarning, stacklevel=2)
        est = _read_estimate(est_file, fmt, topic, timestamps, child_frame, est_cov)
        options = _with_max_gap(gt_pos, gt_dir, options, max_gap)
        return evaluate_positions(gt_pos, est, lever, options)
    gt = load_ground_truth(gt_dir, mode=gt_mode,
                           engine=None if gt_engine in (None, "run") else gt_engine)
    est = _read_estimate(est_file, fmt, topic, timestamps, child_frame, est_cov)
    return evaluate(gt, est, _with_max_gap(gt, gt_dir, options, max_gap))


def _read_estimate(est_file, fmt, topic, timestamps, child_frame, est_cov) -> PoseTrajectory:
    """The estimate's poses (and its covariance file)."""
    if fmt is not None and fmt not in FORMATS:
        raise InputError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
    est = read_trajectory(est_file, fmt, topic=topic, timestamps=timestamps,
                          child_frame=child_frame)
    if est_cov is not None:
        est = attach_covariance(est, read_covariance_csv(est_cov), source=str(est_cov))
    return est


def _with_max_gap(gt, gt_dir, options: EvaluationOptions | None,
                  max_gap: float | None) -> EvaluationOptions:
    """``options`` with ``max_dt`` the given ``max_gap`` or its default."""
    if max_gap is None:
        limit = run_gap_limit(gt, gt_dir) if Path(gt_dir).is_dir() else None
        max_gap = DEFAULT_MAX_GAP_FILE_S if limit is None else limit
    options = EvaluationOptions() if options is None else options
    return dataclasses.replace(options, max_dt=max_gap)


def save_evo_results(result, targets: dict[str, Path], *, gt_dir, est_file, relation: str,
                     force: bool) -> list[Path]:
    """Write the evo result files of ``targets``; all are built before the first is written
    (a refused one leaves no file)."""
    results = {m: evo_result(result, metric=m, relation=relation, ref_name=str(gt_dir),
                             est_name=str(est_file)) for m in targets}
    option = {"ape": "--save-results", "rpe": "--save-results-rpe"}
    inputs = [gt_dir, est_file]
    return [write_evo_result(targets[m], res, option=option[m], force=force, inputs=inputs)
            for m, res in results.items()]
