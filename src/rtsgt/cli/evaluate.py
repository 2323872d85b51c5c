"""``rtsgt evaluate``: evaluate a SLAM / odometry trajectory against an rtsgt ground truth.

A thin wrapper over :func:`rtsgt.io.trajectory.read_trajectory`,
:func:`rtsgt.evaluation.evaluate` and :func:`rtsgt.report.eval_plots.plot_evaluation`.
``GT_DIR`` is an ``rtsgt run`` output directory or a trajectory file. A run directory with
``measurements/`` gives a continuous-time ground truth
(:class:`rtsgt.evaluation.groundtruth.ContinuousGroundTruth`: the pose and covariance at each
estimate time from the run's GP tracks, and the run's gates); otherwise (or with
``--gt-mode discrete``) its stored poses (``groundtruth_covariance.csv`` preferred, else
``groundtruth.tum``) are interpolated.

``--max-gap`` (the largest distance, s, from an estimate time to the nearest ground-truth
measurement) defaults to the run's own gap limit when ``GT_DIR`` is a run directory
(``parameters.max_gap_s`` of its ``summary.json``, 3 s by default; the continuous ground truth
falls back to the run's default when the summary lacks it), so that every pose the run
produced is evaluated; for a trajectory file, or a directory without that limit, it defaults
to :data:`DEFAULT_MAX_GAP_FILE_S`. An explicit value always wins.

A position-only ground truth (:func:`wants_positions`: a run with one or two tracked prisms, a
position CSV, or ``--lever-arm``, ``--prism``, ``--gt-topic``) is evaluated by
:func:`rtsgt.evaluation.evaluate_positions`: the estimate's sensor pose moved by the lever arm
against the prism's positions (:func:`load_position_ground_truth`; docs/evaluation.md,
section Position-only ground truth).

``--save-results`` / ``--save-results-rpe`` write the APE / RPE as evo's result zips
(:mod:`rtsgt.io.evo_results`; docs/evaluation.md, section evo result files), checked before
any work and written whole after it.

Every :class:`~rtsgt.errors.RtsgtWarning` of the reading and the evaluation is shown as one
``warning: ...`` line on stderr and, with ``--json``, listed under ``warnings``.
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from rtsgt.choices import (
    ALIGN_METHODS,
    DEFAULT_MAX_DT_S,
    JOINT_ALIGNMENTS,
    POSE_RELATIONS,
)
from rtsgt.choices import TRAJECTORY_FORMATS as FORMATS
from rtsgt.cli.common import checked_options, usage_error
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.io.output_dir import check_target

if TYPE_CHECKING:
    from rich.console import Console

    from rtsgt.cli.tables import TextTable
    from rtsgt.evaluation import (
        EvaluationOptions,
        EvaluationResult,
        PositionEvaluationResult,
    )
    from rtsgt.evaluation.associate import GroundTruthQuery, ValidatedGroundTruth
    from rtsgt.evaluation.groundtruth import ContinuousPositionGroundTruth
    from rtsgt.evaluation.mounting import MountingFit
    from rtsgt.types import PoseTrajectory, PositionTrajectory

#: Ground-truth modes of ``--gt-mode``.
GT_MODES = ("auto", "continuous", "discrete")


def gt_engines() -> tuple[str, ...]:
    """The pose engines of ``--gt-engine``: ``run`` (the run's own), then
    :data:`rtsgt.pose.POSE_ENGINES`."""
    from rtsgt.pose import POSE_ENGINES

    return ("run", *POSE_ENGINES)


#: Default ``--max-gap`` (s) for a ground-truth trajectory file (distance to the nearest stored
#: pose): a few samples of a 5-10 Hz ground truth.
DEFAULT_MAX_GAP_FILE_S = DEFAULT_MAX_DT_S
#: The command-line options of the fields of :class:`~rtsgt.evaluation.EvaluationOptions`.
EVALUATION_OPTION_NAMES = {
    "align": "--align",
    "n_align": "--n-align",
    "weighted": "--weighted",
    "delta": "--delta",
    "delta_unit": "--delta-unit",
    "all_pairs": "--all-pairs",
    "time_offset": "--t-offset",
    "max_dt": "--max-gap",
    "estimate": "--estimate",
    "mounting": "--mounting",
}


def evaluation_options(**values) -> EvaluationOptions:
    """The :class:`~rtsgt.evaluation.EvaluationOptions` of the given (not None) command-line
    values, each checked by the record's own rule first; a bad one is a usage error naming its
    option (a bad combination names the first option it involves: ``--delta`` with
    ``--delta-unit f``, ``--estimate`` with an ``--align`` it cannot be estimated with)."""
    from rtsgt.evaluation import EvaluationOptions

    changes = checked_options(EvaluationOptions, EVALUATION_OPTION_NAMES, **values)
    try:
        return EvaluationOptions(**changes)
    except InputError as exc:
        option = "estimate" if changes.get("estimate") and "to estimate" in exc.bare_message \
            else "delta"
        raise usage_error(exc.bare_message, EVALUATION_OPTION_NAMES[option]) from None


def mounting_option(value: str | None) -> tuple[float, ...] | None:
    """``--mounting``: seven numbers or a file (:func:`rtsgt.io.transform.read_transform`); a
    bad one is a usage error naming the option."""
    if value is None:
        return None
    from rtsgt.io.transform import read_transform

    try:
        return read_transform(value)
    except InputError as exc:
        raise usage_error(str(exc), "--mounting") from None


def run_gap_limit(gt: object, gt_dir: str | Path) -> float | None:
    """The run's own gap limit, s: ``max_gap_s`` of a continuous ground truth, else that of
    ``GT_DIR/summary.json`` (:func:`rtsgt.io.run_dir.read_summary`); None for a trajectory
    file or a directory without a summary.

    Raises
    ------
    InputError
        ``summary.json`` cannot be read (naming it).
    """
    from rtsgt.io.run_dir import read_summary

    options = getattr(gt, "options", None)
    if options is not None:  # a continuous ground truth: its run's options
        return float(options.interpolation.max_gap_s)
    if not Path(gt_dir).is_dir():
        return None
    summary = read_summary(gt_dir)
    return float(summary.options.interpolation.max_gap_s) if summary.exists else None


def load_ground_truth(
    gt_dir: str | Path, *, mode: str = "auto", engine: str | None = None
) -> PoseTrajectory | ValidatedGroundTruth | GroundTruthQuery:
    """The ground truth of ``GT_DIR``: continuous from a run directory with ``measurements/``
    (``mode`` ``auto`` or ``continuous``), else the discrete stored poses or trajectory file.

    ``engine``: pose engine of the continuous ground truth (None: the run's).
    """
    from rtsgt.evaluation.groundtruth import ContinuousGroundTruth
    from rtsgt.io.trajectory import read_groundtruth_dir, read_trajectory

    if mode not in GT_MODES:
        raise InputError(f"unknown ground-truth mode {mode!r}; expected one of {', '.join(GT_MODES)}")
    gt_path = Path(gt_dir)
    run_dir = gt_path.is_dir() and not (gt_path / "metadata.yaml").exists()
    if run_dir and mode != "discrete" and (gt_path / "measurements").is_dir():
        return ContinuousGroundTruth.from_run_dir(gt_path, engine=engine)
    if mode == "continuous":
        raise InputError(
            "a continuous ground truth needs an rtsgt run directory with measurements/", gt_path
        )
    if run_dir:
        return read_groundtruth_dir(gt_path)
    if gt_path.exists():
        return read_trajectory(gt_path)
    raise InputError("ground truth not found", gt_path)


def _is_run_dir(path: Path) -> bool:
    return path.is_dir() and not (path / "metadata.yaml").exists()


def wants_positions(gt_dir: str | Path, *, lever_arm=None, prism: str | None = None,
                    gt_topic: str | None = None) -> bool:
    """Whether ``GT_DIR`` is evaluated as a position-only ground truth
    (:mod:`rtsgt.evaluation.positions`): it is one (a run with one or two tracked prisms, a
    position CSV, :func:`rtsgt.io.positions.position_csv_form`), or one of ``--lever-arm``,
    ``--prism``, ``--gt-topic`` asks for it."""
    from rtsgt.io.positions import position_csv_form
    from rtsgt.io.run_dir import POSITIONS_KIND, read_summary

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
    (continuous from its ``measurements/``, or with ``mode`` ``discrete`` its
    ``prisms/prism<i>.csv``), a topic of a bag (``topic``) or a position CSV
    (:mod:`rtsgt.io.positions`)."""
    from rtsgt.evaluation.groundtruth import ContinuousPositionGroundTruth
    from rtsgt.io.positions import read_position_csv, read_positions

    if mode not in GT_MODES:
        raise InputError(f"unknown ground-truth mode {mode!r}; expected one of {', '.join(GT_MODES)}")
    path = Path(gt_dir)
    if _is_run_dir(path):
        if mode != "discrete" and (path / "measurements").is_dir():
            return ContinuousPositionGroundTruth.from_run_dir(path, prism)
        if mode == "continuous":
            raise InputError("a continuous ground truth needs an rtsgt run directory with "
                             "measurements/", path)
        files = sorted(p.name[len("prism"):-len(".csv")] for p in (path / "prisms").glob(
            "prism*.csv") if not p.name.endswith("_sources.csv"))
        if prism is None and len(files) != 1:
            raise InputError(f"choose the prism (--prism): prisms/ has {', '.join(files) or 'none'}",
                             path)
        pid = files[0] if prism is None else str(prism)
        if pid not in files:
            raise InputError(f"no prisms/prism{pid}.csv; prisms: {', '.join(files)}", path)
        return read_position_csv(path / "prisms" / f"prism{pid}.csv", name=f"prism {pid}")
    if prism is not None:
        raise InputError("--prism selects a prism of an rtsgt run directory", path)
    if not path.exists():
        raise InputError("ground truth not found", path)
    return read_positions(path, topic=topic)


def run_evaluate(
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
    """Read the ground truth and the estimate, then :func:`rtsgt.evaluation.evaluate` with
    ``options`` (default: ``EvaluationOptions()``); for a position-only ground truth
    (:func:`wants_positions`), :func:`rtsgt.evaluation.evaluate_positions` with the
    ``lever_arm`` (``"x,y,z"`` m in the estimate's sensor frame; zero, with a warning, when
    not given).

    ``max_gap`` (s), the largest distance to the nearest ground-truth measurement
    (continuous: of every prism; discrete: the nearest stored pose), replaces
    ``options.max_dt``; its default depends on the ground truth: the run's own gap limit
    (:func:`run_gap_limit`) or :data:`DEFAULT_MAX_GAP_FILE_S` (module docstring).
    ``gt_mode`` and ``gt_engine``: :func:`load_ground_truth` (``gt_engine`` ``"run"`` or
    None: the run's engine; no meaning for positions). ``prism``: the prism of a run
    directory; ``gt_topic``: the ground truth's topic in a bag.
    """
    from rtsgt.evaluation import evaluate, evaluate_positions
    from rtsgt.evaluation.lever_arm import parse_lever_arm

    engines = gt_engines()
    if gt_engine is not None and gt_engine not in engines:
        raise InputError(
            f"unknown ground-truth engine {gt_engine!r}; expected one of {', '.join(engines)}"
        )
    if wants_positions(gt_dir, lever_arm=lever_arm, prism=prism, gt_topic=gt_topic):
        if options is not None and (options.estimate or options.mounting is not None):
            raise InputError(
                f"{gt_dir}: a position-only ground truth gives no rotation to fit a mounting or "
                "a clock to (--estimate, --mounting); give the prism's lever arm in the sensor "
                "frame with --lever-arm and the clock with --t-offset")
        lever = parse_lever_arm(lever_arm)
        gt_pos = load_position_ground_truth(gt_dir, prism=prism, topic=gt_topic, mode=gt_mode)
        if lever_arm is None:
            warnings.warn("position-only ground truth without --lever-arm: the estimate's "
                          "sensor origin is compared with the tracked point (lever arm 0; the "
                          "estimate's rotation does not enter)", RtsgtWarning, stacklevel=2)
        est = _read_estimate(est_file, fmt, topic, timestamps, child_frame, est_cov)
        options = _with_max_gap(gt_pos, gt_dir, options, max_gap)
        return evaluate_positions(gt_pos, est, lever, options)
    gt = load_ground_truth(
        gt_dir, mode=gt_mode, engine=None if gt_engine in (None, "run") else gt_engine
    )
    est = _read_estimate(est_file, fmt, topic, timestamps, child_frame, est_cov)
    return evaluate(gt, est, _with_max_gap(gt, gt_dir, options, max_gap))


def _read_estimate(est_file, fmt, topic, timestamps, child_frame, est_cov) -> PoseTrajectory:
    """The estimate's poses (and its covariance file)."""
    from rtsgt.io.trajectory import attach_covariance, read_covariance_csv, read_trajectory

    if fmt is not None and fmt not in FORMATS:
        raise InputError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
    est = read_trajectory(
        est_file, fmt, topic=topic, timestamps=timestamps, child_frame=child_frame
    )
    if est_cov is not None:
        est = attach_covariance(est, read_covariance_csv(est_cov), source=str(est_cov))
    return est


def _with_max_gap(gt, gt_dir, options: EvaluationOptions | None,
                  max_gap: float | None) -> EvaluationOptions:
    """``options`` with ``max_dt`` the given ``max_gap`` or its default (module docstring)."""
    from rtsgt.evaluation import EvaluationOptions

    if max_gap is None:
        limit = run_gap_limit(gt, gt_dir) if Path(gt_dir).is_dir() else None
        max_gap = DEFAULT_MAX_GAP_FILE_S if limit is None else limit
    options = EvaluationOptions() if options is None else options
    return dataclasses.replace(options, max_dt=max_gap)


def _stats_row(name: str, s, scale: float, digits: int) -> list[str]:
    return [name] + [
        f"{scale * getattr(s, k):.{digits}f}"
        for k in ("rmse", "mean", "median", "std", "min", "max")
    ]


def _vector(v, scale: float, digits: int) -> str:
    import numpy as np

    return "(" + ", ".join("given" if not np.isfinite(x) else f"{scale * x:.{digits}f}"
                           for x in v) + ")"


def print_mounting(m: MountingFit, console: Console) -> None:
    """The mounting ``T_body_sensor`` and the clock offset, with the sigma of what was
    estimated, and how the fit went."""
    import numpy as np

    from rtsgt.cli.tables import TextTable

    table = TextTable("Mounting T_body_sensor (sensor pose in the body frame) and clock",
                      ("", "value", "sigma", ""))
    rv = m.rotation_vector
    angle = float(np.linalg.norm(rv))
    axis = rv / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
    rs, ls, cs = (m.group_sigma(g) for g in ("rotation", "lever", "clock"))
    table.add_row(
        "rotation",
        f"{np.degrees(angle):.4f} deg about {_vector(axis, 1.0, 4)}",
        "-" if rs is None else f"{_vector(rs, 57.29577951308232, 4)} deg (body x, y, z)",
        "estimated" if rs is not None else "given",
    )
    table.add_row(
        "lever arm (m, body frame)",
        _vector(m.lever, 1.0, 4),
        "-" if ls is None else _vector(ls, 1.0, 4),
        "estimated" if ls is not None else "given",
    )
    table.add_row(
        "clock offset (s)",
        f"{m.clock_offset:.6f}",
        "-" if cs is None else f"{cs[0]:.6f}",
        "estimated" if cs is not None else "given",
    )
    table.print(console)
    if m.covariance is not None:
        console.print(
            f"estimated jointly with a {m.alignment.method} alignment weighted by the ground "
            f"truth's covariance on {m.n_used} poses (start: {m.start}, {m.iterations} "
            f"Gauss-Newton iterations): chi2 / dof {m.chi2 / max(m.dof, 1):.3f}; variances "
            f"x {m.time_correlation:.1f} at most for the ground truth's correlation between "
            f"poses, sigmas x {np.sqrt(m.scale_factor):.2f} for the residual's scale",
            highlight=False)
    if m.odometry is not None:
        lv = m.odometry
        console.print(
            f"with the odometry's own error estimated beside it: white noise "
            f"{100 * lv['white_position']:.2g} cm and {np.degrees(lv['white_rotation']):.2g} deg "
            f"per pose, drift {100 * lv['drift_position']:.2g} cm and "
            f"{np.degrees(lv['drift_yaw']):.2g} deg (yaw) per sqrt(m) (docs/evaluating.md)",
            highlight=False)


def _print_association(console: Console, a, continuous: str, what: str, *, gt_source: str,
                       est_source: str) -> None:
    """The association's line of a report: what was associated, dropped, and the limits
    (``continuous``: what a continuous ground truth is, in parentheses; ``what``: the kind of
    ground truth, in words)."""
    if a.ground_truth == "continuous":
        kind, limit = f"continuous {what} ({continuous})", "max gap"
    else:
        kind, limit = f"{a.ground_truth} {what}", "max dt"
    dropped = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in a.dropped.items())
    console.print(
        f"[bold]{est_source}[/bold] against [bold]{gt_source}[/bold] ({kind}): {len(a)} of "
        f"{a.n_est} estimate poses associated"
        + (f"; dropped: {dropped}" if dropped else "")
        + f" (time offset {a.time_offset:.6g} s, {limit} {a.max_dt} s)", highlight=False)


def _print_alignment(console: Console, al, what: str, items: str) -> None:
    """The alignment's line of a report (``what``: its name; ``items``: what it aligned)."""
    import numpy as np

    if al.method == "none":
        console.print("alignment: none")
        return
    console.print(
        f"{what}: {al.method}{' (covariance-weighted)' if al.weighted else ''} on {al.n_used} "
        f"{items}, yaw {np.degrees(al.yaw):.4f} deg, scale {al.scale:.6f}, "
        f"t = [{', '.join(f'{v:.4f}' for v in al.translation)}] m", highlight=False)


def _error_table(title: str) -> TextTable:
    """An empty table of error statistics (evo's columns)."""
    from rtsgt.cli.tables import TextTable

    return TextTable(title, ("metric", "rmse", "mean", "median", "std", "min", "max"))


def _print_nees_table(console: Console, title: str, rows) -> None:
    """The NEES table of a report: one row per ``(name, NeesResult or None)`` given."""
    from rtsgt.cli.tables import TextTable

    nt = TextTable(title, ("", "mean", "dof", "accepted mean", "inside 95 %", "accepted",
                           "N_eff", "verdict (test)"))
    for name, r in rows:
        if r is None:
            continue
        test = "split" if r.split is not None else "autocorrelation"
        verdict = (f"[green]consistent[/green] ({test})" if r.consistent else
                   f"[red]inconsistent[/red] ({test})")
        nt.add_row(name, f"{r.mean:.3f}", str(r.dof),
                   f"[{r.mean_interval[0]:.2f}, {r.mean_interval[1]:.2f}]",
                   f"{100 * r.fraction_inside_95:.1f} %",
                   f"[{100 * r.fraction_interval[0]:.1f}, {100 * r.fraction_interval[1]:.1f}] %",
                   f"{r.n_eff:.0f} / {r.n}", verdict)
    nt.print(console)
    if any(r is not None and r.split is not None for _, r in rows):
        console.print("verdict (split): the shared and varying parts of the errors tested "
                      "apart (the line below); the accepted mean and share hold for errors "
                      "independent from pose to pose (autocorrelation test)", highlight=False)


def _print_split_verdict(console: Console, what: str, sp) -> None:
    """The line of the verdict with the shared and varying parts apart (``what``: its name)."""
    sh, v = sp.shared, sp.varying
    console.print(
        f"{what}, shared and varying parts apart ({'one' if sh.upper else 'two'}-"
        f"sided): shared {sh.statistic:.1f} on {sh.dof} dof (accepted <= "
        f"{sh.interval[1]:.1f}{'' if sh.upper else f', >= {sh.interval[0]:.1f}'}), "
        f"varying NEES {v.mean:.2f} / {v.dof} (accepted <= {v.mean_interval[1]:.2f})",
        highlight=False)


def print_report(
    result: EvaluationResult, console: Console, *, gt_source: str, est_source: str
) -> None:
    """The readable report: association, alignment, APE/RPE, NEES, noise floor."""
    a = result.association
    engine = a.ground_truth_detail.get("engine", "?") if a.ground_truth == "continuous" else ""
    _print_association(console, a, f"GP tracks, {engine} pose engine", "ground truth",
                       gt_source=gt_source, est_source=est_source)
    _print_alignment(console, result.alignment, "alignment", "poses")
    if result.mounting is not None:
        print_mounting(result.mounting, console)
    table = _error_table("Pose errors (evo definitions)")
    table.add_row(*_stats_row("APE translation (mm)", result.ape.translation_m, 1e3, 3))
    table.add_row(*_stats_row("APE rotation (deg)", result.ape.rotation_deg, 1.0, 4))
    unit = {"m": "m", "s": "s", "f": "frames"}[result.rpe_delta_unit]
    table.add_section()
    if result.rpe is None:
        table.add_row(f"RPE, {result.rpe_delta:g} {unit}", *(["-"] * 6))
    else:
        kind = "all" if result.rpe_all_pairs else "consecutive"
        pairs = f"{result.rpe.pairs.shape[0]} {kind} pairs"
        table.add_row(
            *_stats_row(
                f"RPE translation (mm), {result.rpe_delta:g} {unit}",
                result.rpe.translation_m,
                1e3,
                3,
            )
        )
        table.add_row(*_stats_row(f"RPE rotation (deg), {pairs}", result.rpe.rotation_deg, 1.0, 4))
    table.print(console)
    u = result.mounting_effect
    if u is not None:
        rpe_u = ("" if u["rpe_translation_m"] is None else
                 f"; RPE rmse +- {1e3 * u['rpe_translation_m']:.3f} mm, "
                 f"+- {u['rpe_rotation_deg']:.4f} deg")
        console.print(
            f"within the uncertainty of the estimated {', '.join(result.mounting.estimated)}: "
            f"APE rmse +- {1e3 * u['ape_translation_m']:.3f} mm, "
            f"+- {u['ape_rotation_deg']:.4f} deg{rpe_u}", highlight=False)
    if result.rpe is None:
        console.print(f"no RPE: {result.rpe_absent_reason}", highlight=False)
    n = result.nees
    if n.position is None:
        console.print(f"NEES: {n.covariance}")
        return
    _print_nees_table(console, f"NEES (covariance: {n.covariance})", (
        ("position", n.position), ("pose", n.pose),
        ("relative position", n.relative_position), ("relative pose", n.relative_pose)))
    if n.pose.split is None:
        console.print("absolute verdict: autocorrelation of the NEES series (the ground truth "
                      "has no shared factor: errors constant over the run are not tested "
                      "apart)", highlight=False)
    else:
        _print_split_verdict(console, "absolute verdict", n.pose.split)
    console.print(f"relative poses: ground-truth correlations {n.rpe_correlations}")
    f = result.noise_floor
    console.print(
        f"noise floor of the ground truth: APE {1e3 * f.ape_translation_m:.3f} mm, "
        f"{f.ape_rotation_deg:.4f} deg; APE rmse with the floor removed "
        f"{1e3 * f.ape_translation_rmse_floor_removed_m:.3f} mm, "
        f"{f.ape_rotation_rmse_floor_removed_deg:.4f} deg"
    )
    if f.rpe_translation_m is not None:
        console.print(
            f"RPE floor {1e3 * f.rpe_translation_m:.3f} mm, {f.rpe_rotation_deg:.4f} deg; "
            f"RPE rmse with the floor removed "
            f"{1e3 * f.rpe_translation_rmse_floor_removed_m:.3f} mm, "
            f"{f.rpe_rotation_rmse_floor_removed_deg:.4f} deg"
        )
    if a.cov_interpolated.any():
        console.print(
            f"note: {int(a.cov_interpolated.sum())} ground-truth covariances were interpolated "
            "linearly between samples"
        )


def print_position_report(
    result: PositionEvaluationResult, console: Console, *, gt_source: str, est_source: str
) -> None:
    """The readable report of a position-only ground truth: association, alignment, lever
    arm, APE / RPE of positions, NEES (3 dof), noise floor; rotations not reported."""
    a = result.association
    prism = a.ground_truth_detail.get("prism", "?") if a.ground_truth == "continuous" else ""
    _print_association(console, a, f"GP track of prism {prism}", "position ground truth",
                       gt_source=gt_source, est_source=est_source)
    lever = ", ".join(f"{v:.4f}" for v in result.lever_arm)
    console.print(f"lever arm (sensor frame): [{lever}] m, {result.lever_arm_source}: the "
                  "estimate's point p + R l is compared", highlight=False)
    _print_alignment(console, result.alignment, "alignment of the points", "positions")
    table = _error_table("Position errors (rotations not reported: position-only ground truth)")
    table.add_row(*_stats_row("APE position (mm)", result.ape.translation_m, 1e3, 3))
    unit = {"m": "m", "s": "s", "f": "frames"}[result.rpe_delta_unit]
    if result.rpe is None:
        table.add_row(f"RPE position, {result.rpe_delta:g} {unit}", *(["-"] * 6))
    else:
        table.add_row(*_stats_row(
            f"RPE position (mm), {result.rpe_delta:g} {unit}, {result.rpe.pairs.shape[0]} pairs",
            result.rpe.translation_m, 1e3, 3))
    table.print(console)
    if result.rpe is None:
        console.print(f"no RPE: {result.rpe_absent_reason}", highlight=False)
    n = result.nees
    if n.position is None:
        console.print(f"NEES: {n.covariance}")
        return
    _print_nees_table(console, f"NEES, 3 dof (covariance: {n.covariance})", (
        ("position", n.position), ("relative position", n.relative_position)))
    if n.position.split is not None:
        _print_split_verdict(console, "position verdict", n.position.split)
    console.print(f"relative positions: ground-truth correlations {n.rpe_correlations}")
    f = result.noise_floor
    console.print(
        f"noise floor of the ground truth: APE {1e3 * f.ape_translation_m:.3f} mm; APE rmse "
        f"with the floor removed {1e3 * f.ape_translation_rmse_floor_removed_m:.3f} mm"
        + ("" if f.rpe_translation_m is None else
           f"; RPE floor {1e3 * f.rpe_translation_m:.3f} mm, rmse with it removed "
           f"{1e3 * f.rpe_translation_rmse_floor_removed_m:.3f} mm"), highlight=False)
    if a.cov_interpolated.any():
        console.print(
            f"note: {int(a.cov_interpolated.sum())} ground-truth covariances were interpolated "
            "linearly between samples"
        )


def save_targets(ape: Path | None, rpe: Path | None, relation: str, *, force: bool,
                 inputs) -> dict[str, Path]:
    """The result files asked for (``{"ape": path, "rpe": path}``), each checked before any
    work (:func:`rtsgt.io.evo_results.check_results_file`, which names the option)."""
    from rtsgt.io.evo_results import check_results_file

    if relation not in POSE_RELATIONS:
        raise typer.BadParameter(f"expected one of {', '.join(POSE_RELATIONS)}",
                                 param_hint="--pose-relation")
    targets = {}
    for metric, path, option in (("ape", ape, "--save-results"),
                                 ("rpe", rpe, "--save-results-rpe")):
        if path is None:
            continue
        check_results_file(path, option=option, force=force, inputs=inputs)
        targets[metric] = path
    if len(targets) == 2 and Path(ape).absolute() == Path(rpe).absolute():
        raise usage_error("--save-results and --save-results-rpe name the same file",
                          "--save-results-rpe")
    return targets


def save_evo_results(result, targets: dict[str, Path], *, gt_dir, est_file, relation: str,
                     force: bool) -> list[Path]:
    """Write the evo result files of ``targets`` (:func:`save_targets`); every result is
    built before the first file is written, so that a refused one (a rotation of a
    position-only ground truth, an RPE without pairs) leaves no file."""
    from rtsgt.io.evo_results import evo_result, write_evo_result

    results = {m: evo_result(result, metric=m, relation=relation, ref_name=str(gt_dir),
                             est_name=str(est_file)) for m in targets}
    option = {"ape": "--save-results", "rpe": "--save-results-rpe"}
    inputs = [gt_dir, est_file]
    return [write_evo_result(targets[m], res, option=option[m], force=force, inputs=inputs)
            for m, res in results.items()]


class _collect_warnings:
    """Record the warnings of a block, then show every one again (``warning: ...`` lines on
    stderr through the CLI's handler) also when the block raises; the messages of the
    :class:`~rtsgt.errors.RtsgtWarning` ones are the list the block gives (``--json``)."""

    def __enter__(self) -> list[str]:
        self._ctx = warnings.catch_warnings(record=True)
        self._caught = self._ctx.__enter__()
        warnings.simplefilter("always")
        self.notes: list[str] = []
        return self.notes

    def __exit__(self, *exc) -> bool:
        self._ctx.__exit__(*exc)
        for w in self._caught:
            if issubclass(w.category, RtsgtWarning):
                self.notes.append(str(w.message))
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
        return False


def register(app: typer.Typer) -> None:
    """Add ``rtsgt evaluate`` to the application."""

    @app.command("evaluate")
    def evaluate_command(
        gt_dir: Path = typer.Argument(
            ...,
            metavar="GT_DIR",
            help="rtsgt run directory (continuous ground truth from its measurements/, else "
            "groundtruth_covariance.csv or groundtruth.tum; a run of one or two prisms: their "
            "positions), a ground-truth trajectory file, a position CSV or a bag (--gt-topic).",
        ),
        est_file: Path = typer.Argument(
            ..., metavar="EST_FILE", help="Estimated trajectory (file, or ROS 2 bag directory)."
        ),
        fmt: str | None = typer.Option(
            None,
            "--format",
            help=f"Estimate format: {' | '.join(FORMATS)} (default: from the extension/content).",
        ),
        topic: str | None = typer.Option(None, "--topic", help="Bag topic of the estimate."),
        child_frame: str | None = typer.Option(
            None, "--child-frame", help="Child frame to take from a TF / TransformStamped topic."
        ),
        timestamps: Path | None = typer.Option(
            None, "--timestamps", help="Timestamps file of KITTI poses (one time in s per line)."
        ),
        est_cov: Path | None = typer.Option(
            None, "--est-cov", help="Covariances of the estimate (rtsgt covariance CSV)."
        ),
        align: str = typer.Option(
            "se3", "--align", help=f"Alignment: {' | '.join(ALIGN_METHODS)}."
        ),
        n_align: int | None = typer.Option(
            None, "--n-align", min=1, help="Align on the first N associated poses (default: all)."
        ),
        weighted: bool = typer.Option(
            False,
            "--weighted",
            help="Weight the alignment by 1 / trace of the GT position covariance.",
        ),
        delta: float = typer.Option(1.0, "--delta", help="RPE pair separation."),
        delta_unit: str = typer.Option(
            "m", "--delta-unit", help="RPE delta unit: m (path) | s | f (frames)."
        ),
        all_pairs: bool = typer.Option(
            False, "--all-pairs", help="RPE on all pairs (evo --all_pairs)."
        ),
        time_offset: float = typer.Option(
            0.0, "--t-offset", "--time-offset",
            help="Seconds added to the estimate's times (the start of --estimate clock).",
        ),
        estimate: str | None = typer.Option(
            None,
            "--estimate",
            help="Estimate jointly with the alignment (comma-separated): rotation, lever (the "
            "mounting T_body_sensor), lever-xy (its x, y in the body frame, z given: for a "
            "ground robot), clock (the time offset); mounting = rotation,lever; all = "
            "rotation,lever,clock. "
            f"Needs --align {' | '.join(JOINT_ALIGNMENTS)}; refused, with the reason, when the "
            "trajectory does not excite it.",
        ),
        mounting: str | None = typer.Option(
            None,
            "--mounting",
            help="Given T_body_sensor (the sensor's pose in the body frame, p_body = R "
            "p_sensor + t): x,y,z,qx,qy,qz,qw, or a file (evo's JSON transform, or a 4x4 "
            "matrix). The start of what --estimate asks, the value of the rest.",
        ),
        max_dt: float | None = typer.Option(
            None,
            "--max-gap",
            "--max-dt",
            help="Max distance (s) to the nearest ground-truth measurement (continuous: of "
            "every prism; discrete: the nearest stored pose); poses farther are dropped. "
            "Default: the run's own gap limit (summary.json parameters.max_gap_s) for a run "
            f"directory, {DEFAULT_MAX_GAP_FILE_S} s for a trajectory file.",
        ),
        gt_mode: str = typer.Option(
            "auto",
            "--gt-mode",
            help="Ground truth: auto (continuous when GT_DIR has measurements/) | continuous "
            "| discrete (interpolate the stored poses).",
        ),
        gt_engine: str = typer.Option(
            "run",
            "--gt-engine",
            help="Pose engine of the continuous ground truth: run (the run's) | mc | ut | "
            "linear (fastest).",
        ),
        lever_arm: str | None = typer.Option(
            None,
            "--lever-arm",
            help="x,y,z (m): the ground truth's tracked point (prism) in the estimate's sensor "
            "frame; evaluates against a position-only ground truth (p + R l).",
        ),
        prism: str | None = typer.Option(
            None,
            "--prism",
            help="The prism of a run directory that is the (position-only) ground truth "
            "(needed when the run tracked more than one).",
        ),
        gt_topic: str | None = typer.Option(
            None,
            "--gt-topic",
            help="Topic of a position ground truth in a bag GT_DIR (PointStamped, "
            "PoseStamped, ...).",
        ),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        plot: Path | None = typer.Option(None, "--plot",
                                         help="Write PNG and SVG figures into this directory."),
        save_results: Path | None = typer.Option(
            None, "--save-results",
            help="Write the APE as an evo result zip (evo_ape --save_results layout, with "
            "rtsgt's NEES and noise floor added), for evo_res.",
        ),
        save_results_rpe: Path | None = typer.Option(
            None, "--save-results-rpe",
            help="Write the RPE as an evo result zip (evo_rpe --save_results layout).",
        ),
        pose_relation: str = typer.Option(
            "trans_part", "--pose-relation",
            help="Pose relation of the saved results (evo's -r): "
            f"{' | '.join(POSE_RELATIONS)}.",
        ),
        force: bool = typer.Option(False, "--force",
                                   help="Replace an earlier output of rtsgt at --plot, "
                                        "--save-results, --save-results-rpe (never a file or "
                                        "directory rtsgt did not write)."),
    ) -> None:
        """Evaluate an estimated trajectory against the uncertain ground truth (APE, RPE, NEES)."""
        from rich.console import Console

        from rtsgt.evaluation import PositionEvaluationResult
        from rtsgt.evaluation.lever_arm import parse_lever_arm

        options = evaluation_options(
            align=align,
            n_align=n_align,
            weighted=weighted,
            delta=delta,
            delta_unit=delta_unit,
            all_pairs=all_pairs,
            time_offset=time_offset,
            max_dt=max_dt,  # None: the run's own limit (run_evaluate), checked here when given
            estimate=estimate,
            mounting=mounting_option(mounting),
        )
        if fmt is not None and fmt not in FORMATS:
            raise typer.BadParameter(f"expected one of {', '.join(FORMATS)}", param_hint="--format")
        if gt_mode not in GT_MODES:
            raise typer.BadParameter(f"expected one of {', '.join(GT_MODES)}", param_hint="--gt-mode")
        if gt_engine not in gt_engines():
            raise typer.BadParameter(
                f"expected one of {', '.join(gt_engines())}", param_hint="--gt-engine"
            )
        if lever_arm is not None:
            try:
                parse_lever_arm(lever_arm)
            except InputError as exc:
                raise usage_error(exc.bare_message, "--lever-arm") from None
        if plot is not None:
            check_target(plot, force=force)  # before any work
        saves = save_targets(save_results, save_results_rpe, pose_relation, force=force,
                             inputs=[p for p in (gt_dir, est_file, timestamps, est_cov) if p])
        with _collect_warnings() as notes:
            result = run_evaluate(
                gt_dir,
                est_file,
                fmt=fmt,
                topic=topic,
                child_frame=child_frame,
                timestamps=timestamps,
                est_cov=est_cov,
                options=options,
                max_gap=max_dt,
                gt_mode=gt_mode,
                gt_engine=gt_engine,
                lever_arm=lever_arm,
                prism=prism,
                gt_topic=gt_topic,
            )
        saved = save_evo_results(result, saves, gt_dir=gt_dir, est_file=est_file,
                                 relation=pose_relation, force=force)
        written = None
        if plot is not None:
            from rtsgt.report.eval_plots import plot_evaluation

            written = plot_evaluation(result, plot, force=force)
        if as_json:
            typer.echo(json.dumps({**result.to_dict(), "warnings": notes}))
            return
        console = Console()
        report = (print_position_report if isinstance(result, PositionEvaluationResult)
                  else print_report)
        report(result, console, gt_source=str(gt_dir), est_source=str(est_file))
        from rtsgt.cli.drift_table import print_drift

        print_drift(None if result.drift is None else result.drift.to_dict(), console)
        if written is not None:
            console.print(f"figures: {', '.join(p.name for p in written.files)} in {plot}")
        for path in saved:
            console.print(f"evo result: {path}", highlight=False)
