"""``rtsgt evaluate``: its options, their checks and its tables (docs/evaluating.md).

The work is :func:`rtsgt.app.evaluate.run_evaluation` and
:func:`rtsgt.app.evaluate.save_evo_results`; every :class:`~rtsgt.errors.RtsgtWarning` is a
``warning: ...`` line and, with ``--json``, listed under ``warnings``.
"""

from __future__ import annotations

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
    from rtsgt.evaluation.mounting import MountingFit

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
    """The :class:`~rtsgt.evaluation.EvaluationOptions` of the given (not None) values; a bad
    value or combination is a usage error naming its (first) option."""
    from rtsgt.evaluation import EvaluationOptions

    changes = checked_options(EvaluationOptions, EVALUATION_OPTION_NAMES, **values)
    try:
        return EvaluationOptions(**changes)
    except InputError as exc:
        option = "estimate" if changes.get("estimate") and "to estimate" in exc.bare_message \
            else "delta"
        raise usage_error(exc.bare_message, EVALUATION_OPTION_NAMES[option]) from None


def mounting_option(value: str | None) -> tuple[float, ...] | None:
    """``--mounting``: seven numbers or a file (:func:`rtsgt.io.transform.read_transform`)."""
    if value is None:
        return None
    from rtsgt.io.transform import read_transform

    try:
        return read_transform(value)
    except InputError as exc:
        raise usage_error(str(exc), "--mounting") from None


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
    """The mounting ``T_body_sensor``, the clock offset, their sigmas and the fit."""
    import numpy as np

    from rtsgt.cli.tables import TextTable

    table = TextTable("Mounting T_body_sensor (sensor pose in the body frame) and clock",
                      ("", "value", "sigma", ""))
    rv = m.rotation_vector
    angle = float(np.linalg.norm(rv))
    axis = rv / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
    rs, ls, cs = (m.group_sigma(g) for g in ("rotation", "lever", "clock"))
    table.add_row("rotation", f"{np.degrees(angle):.4f} deg about {_vector(axis, 1.0, 4)}",
                  "-" if rs is None else f"{_vector(rs, 57.29577951308232, 4)} deg (body x, y, z)",
                  "estimated" if rs is not None else "given")
    table.add_row("lever arm (m, body frame)", _vector(m.lever, 1.0, 4),
                  "-" if ls is None else _vector(ls, 1.0, 4),
                  "estimated" if ls is not None else "given")
    table.add_row("clock offset (s)", f"{m.clock_offset:.6f}",
                  "-" if cs is None else f"{cs[0]:.6f}", "estimated" if cs is not None else "given")
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
    """The association's line of a report (``continuous``, ``what``: the ground truth, in
    words)."""
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
    console.print(f"{what}, shared and varying parts apart ({'one' if sh.upper else 'two'}-"
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
    unit = "frames" if result.rpe_delta_unit == "f" else result.rpe_delta_unit
    table.add_section()
    if result.rpe is None:
        table.add_row(f"RPE, {result.rpe_delta:g} {unit}", *(["-"] * 6))
    else:
        kind = "all" if result.rpe_all_pairs else "consecutive"
        pairs = f"{result.rpe.pairs.shape[0]} {kind} pairs"
        table.add_row(
            *_stats_row(f"RPE translation (mm), {result.rpe_delta:g} {unit}",
                        result.rpe.translation_m, 1e3, 3)
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
    n = result.nees
    if not _print_rpe_absence_and_nees(console, result):
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
    console.print(f"noise floor of the ground truth: APE {1e3 * f.ape_translation_m:.3f} mm, "
                  f"{f.ape_rotation_deg:.4f} deg; APE rmse with the floor removed "
                  f"{1e3 * f.ape_translation_rmse_floor_removed_m:.3f} mm, "
                  f"{f.ape_rotation_rmse_floor_removed_deg:.4f} deg")
    if f.rpe_translation_m is not None:
        console.print(
            f"RPE floor {1e3 * f.rpe_translation_m:.3f} mm, {f.rpe_rotation_deg:.4f} deg; "
            f"RPE rmse with the floor removed "
            f"{1e3 * f.rpe_translation_rmse_floor_removed_m:.3f} mm, "
            f"{f.rpe_rotation_rmse_floor_removed_deg:.4f} deg")
    _print_interpolated(console, a)


def print_position_report(
    result: PositionEvaluationResult, console: Console, *, gt_source: str, est_source: str
) -> None:
    """The readable report against a position-only ground truth (no rotations)."""
    a = result.association
    prism = a.ground_truth_detail.get("prism", "?") if a.ground_truth == "continuous" else ""
    _print_association(console, a, f"GP track of prism {prism}", "position ground truth",
                       gt_source=gt_source, est_source=est_source)
    lever = ", ".join(f"{v:.4f}" for v in result.lever_arm)
    console.print(f"lever arm (sensor frame): [{lever}] m, {result.lever_arm_source}: the "
                  "estimate's point p + R l is compared", highlight=False)
    m = result.mounting
    if m is not None:  # the lever arm and the clock estimated (docs/evaluating.md)
        d = m.to_prism_dict()
        sig = ", ".join("given" if v is None else f"{1e3 * v:.2f}"
                        for v in d["lever_arm_sigma_m"])
        clock = ("given" if d["clock_sigma_s"] is None else
                 f"{m.clock_offset:.4f} s +- {1e3 * d['clock_sigma_s']:.2f} ms")
        console.print(f"estimated ({m.model} model): lever arm sigma [{sig}] mm; clock offset "
                      f"{clock}", highlight=False)
    _print_alignment(console, result.alignment, "alignment of the points", "positions")
    table = _error_table("Position errors (rotations not reported: position-only ground truth)")
    table.add_row(*_stats_row("APE position (mm)", result.ape.translation_m, 1e3, 3))
    unit = "frames" if result.rpe_delta_unit == "f" else result.rpe_delta_unit
    if result.rpe is None:
        table.add_row(f"RPE position, {result.rpe_delta:g} {unit}", *(["-"] * 6))
    else:
        table.add_row(*_stats_row(
            f"RPE position (mm), {result.rpe_delta:g} {unit}, {result.rpe.pairs.shape[0]} pairs",
            result.rpe.translation_m, 1e3, 3))
    table.print(console)
    n = result.nees
    if not _print_rpe_absence_and_nees(console, result):
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
    _print_interpolated(console, a)


def _print_rpe_absence_and_nees(console: Console, result) -> bool:
    """Say why there is no RPE, if so, and the NEES's absence; False when it is absent."""
    if result.rpe is None:
        console.print(f"no RPE: {result.rpe_absent_reason}", highlight=False)
    if result.nees.position is None:
        console.print(f"NEES: {result.nees.covariance}")
        return False
    return True


def _print_interpolated(console: Console, a) -> None:
    """The note on the ground-truth covariances interpolated between samples, if any."""
    if a.cov_interpolated.any():
        console.print(f"note: {int(a.cov_interpolated.sum())} ground-truth covariances were "
                      "interpolated linearly between samples")


#: (kind, unit of the lengths, translation key and unit shown, its scale from the JSON,
#: rotation key and unit shown).
_DRIFT_KINDS = (
    ("distance", "m", "pct", "%", 1.0, "deg_per_m", "deg/m"),
    ("time", "s", "m_per_s", "mm/s", 1e3, "deg_per_s", "deg/s"),
)


def _drift_cell(value: float | None, floor: float | None, unit: str, scale: float = 1.) -> str:
    if value is None:
        return "-"
    text = f"{scale * value:.3g} {unit}"
    return text + (" (<= floor)" if floor is not None and value <= floor else "")


def _drift_rows(table: TextTable, sec: dict, kind: tuple) -> None:
    """The rows of one kind of segment: each length, then all pooled."""
    _, lu, tk, tu, ts, rk, ru = kind
    entries = [(f"{r[f'length_{lu}']:g} {lu}", r) for r in sec["by_length"]]
    lengths = sec[f"lengths_{lu}"]
    entries.append((f"all, {lengths[0]:g}-{lengths[-1]:g} {lu}", {**sec, "n": sec["n_segments"]}))
    for name, r in entries:
        t, tf = r[f"translation_{tk}"], r[f"translation_floor_{tk}"]
        rot, rf = r[f"rotation_{rk}"], r[f"rotation_floor_{rk}"]
        table.add_row(name, str(r["n"]), _drift_cell(t, tf, tu, ts),
                      "-" if tf is None else f"{ts * tf:.3g} {tu}",
                      _drift_cell(rot, rf, ru), "-" if rf is None else f"{rf:.3g} {ru}")


def print_drift(drift: dict | None, console: Console) -> None:
    """The drift table of the JSON's ``drift`` section (None: nothing printed;
    docs/evaluating.md#drift-by-segment-length)."""
    from rtsgt.cli.tables import TextTable

    if drift is None or (drift["distance"] is None and drift["time"] is None):
        return
    table = TextTable("Drift by segment length (KITTI devkit definition: mean over segments "
                      "every 10 poses; floor: the ground truth's own, rms)",
                      ("segment", "n", "translation", "floor", "rotation", "floor"))
    first = True
    for kind in _DRIFT_KINDS:
        sec = drift[kind[0]]
        if sec is None:
            continue
        if not first:
            table.add_section()
        first = False
        _drift_rows(table, sec, kind)
    table.print(console)
    d = drift["distance"]
    notes = [] if d is None else [f"lengths of path: {d['lengths_from']}"]
    notes.append("rotation per metre as the devkit (KITTI's leaderboard shows deg/100 m); "
                 "'<= floor': not resolved by this ground truth")
    if drift["rotation"]:
        notes.append(f"rotational drift {drift['rotation']}")
    console.print("; ".join(notes), highlight=False)


def save_targets(ape: Path | None, rpe: Path | None, relation: str, *, force: bool,
                 inputs) -> dict[str, Path]:
    """The result files asked for (``{"ape": path, "rpe": path}``), checked before any work."""
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


class _collect_warnings:
    """Record a block's warnings, then show each again, also when it raises; the block gets
    the list of the RtsgtWarning messages (``--json``)."""

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
            ..., metavar="GT_DIR",
            help="rtsgt run directory (continuous ground truth from its measurements/, else "
            "groundtruth_covariance.csv or groundtruth.tum; a run of one or two prisms: their "
            "positions), a ground-truth trajectory file, a position CSV or a bag (--gt-topic)."),
        est_file: Path = typer.Argument(
            ..., metavar="EST_FILE", help="Estimated trajectory (file, or ROS 2 bag directory)."),
        fmt: str | None = typer.Option(
            None, "--format",
            help=f"Estimate format: {' | '.join(FORMATS)} (default: from the extension/content)."),
        topic: str | None = typer.Option(None, "--topic", help="Bag topic of the estimate."),
        child_frame: str | None = typer.Option(
            None, "--child-frame", help="Child frame to take from a TF / TransformStamped topic."),
        timestamps: Path | None = typer.Option(
            None, "--timestamps", help="Timestamps file of KITTI poses (one time in s per line)."),
        est_cov: Path | None = typer.Option(
            None, "--est-cov", help="Covariances of the estimate (rtsgt covariance CSV)."),
        align: str = typer.Option(
            "se3", "--align", help=f"Alignment: {' | '.join(ALIGN_METHODS)}."),
        n_align: int | None = typer.Option(
            None, "--n-align", min=1, help="Align on the first N associated poses (default: all)."),
        weighted: bool = typer.Option(
            False, "--weighted",
            help="Weight the alignment by 1 / trace of the GT position covariance."),
        delta: float = typer.Option(1.0, "--delta", help="RPE pair separation."),
        delta_unit: str = typer.Option("m", "--delta-unit",
                                       help="RPE delta unit: m (path) | s | f (frames)."),
        all_pairs: bool = typer.Option(False, "--all-pairs",
                                       help="RPE on all pairs (evo --all_pairs)."),
        time_offset: float = typer.Option(
            0.0, "--t-offset", "--time-offset",
            help="Seconds added to the estimate's times (the start of --estimate clock)."),
        estimate: str | None = typer.Option(
            None, "--estimate",
            help="Estimate jointly with the alignment (comma-separated): rotation, lever (the "
            "mounting T_body_sensor), lever-xy (its x, y in the body frame, z given: for a "
            "ground robot), clock (the time offset); mounting = rotation,lever; all = "
            "rotation,lever,clock. "
            f"Needs --align {' | '.join(JOINT_ALIGNMENTS)}; refused, with the reason, when the "
            "trajectory does not excite it."),
        mounting: str | None = typer.Option(
            None, "--mounting",
            help="Given T_body_sensor (the sensor's pose in the body frame, p_body = R "
            "p_sensor + t): x,y,z,qx,qy,qz,qw, or a file (evo's JSON transform, or a 4x4 "
            "matrix). The start of what --estimate asks, the value of the rest."),
        max_dt: float | None = typer.Option(
            None, "--max-gap", "--max-dt",
            help="Max distance (s) to the nearest ground-truth measurement (continuous: of "
            "every prism; discrete: the nearest stored pose); poses farther are dropped. "
            "Default: the run's own gap limit (summary.json parameters.max_gap_s) for a run "
            f"directory, {DEFAULT_MAX_DT_S} s for a trajectory file."),
        gt_mode: str = typer.Option(
            "auto", "--gt-mode",
            help="Ground truth: auto (continuous when GT_DIR has measurements/) | continuous "
            "| discrete (interpolate the stored poses)."),
        gt_engine: str = typer.Option(
            "run", "--gt-engine",
            help="Pose engine of the continuous ground truth: run (the run's) | mc | ut | "
            "linear (fastest)."),
        lever_arm: str | None = typer.Option(
            None, "--lever-arm",
            help="x,y,z (m): the ground truth's tracked point (prism) in the estimate's sensor "
            "frame; evaluates against a position-only ground truth (p + R l)."),
        prism: str | None = typer.Option(
            None, "--prism",
            help="The prism of a run directory that is the (position-only) ground truth "
            "(needed when the run tracked more than one)."),
        gt_topic: str | None = typer.Option(
            None, "--gt-topic",
            help="Topic of a position ground truth in a bag GT_DIR (PointStamped, "
            "PoseStamped, ...)."),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        plot: Path | None = typer.Option(None, "--plot",
                                         help="Write PNG and SVG figures into this directory."),
        save_results: Path | None = typer.Option(
            None, "--save-results",
            help="Write the APE as an evo result zip (evo_ape --save_results layout, with "
            "rtsgt's NEES and noise floor added), for evo_res."),
        save_results_rpe: Path | None = typer.Option(
            None, "--save-results-rpe",
            help="Write the RPE as an evo result zip (evo_rpe --save_results layout)."),
        pose_relation: str = typer.Option("trans_part", "--pose-relation",
                                          help="Pose relation of the saved results (evo's -r): "
                                          f"{' | '.join(POSE_RELATIONS)}."),
        force: bool = typer.Option(False, "--force",
                                   help="Replace an earlier output of rtsgt at --plot, "
                                        "--save-results, --save-results-rpe (never a file or "
                                        "directory rtsgt did not write)."),
    ) -> None:
        """Evaluate an estimated trajectory against the uncertain ground truth (APE, RPE, NEES)."""
        from rtsgt.app.evaluate import run_evaluation, save_evo_results

        # max_dt None: the run's own limit (run_evaluation), checked here when given
        options = evaluation_options(
            align=align, n_align=n_align, weighted=weighted, delta=delta, delta_unit=delta_unit,
            all_pairs=all_pairs, time_offset=time_offset, max_dt=max_dt, estimate=estimate,
            mounting=mounting_option(mounting))
        _check_choices(fmt, gt_mode, gt_engine, lever_arm)
        if plot is not None:
            check_target(plot, force=force)  # before any work
        saves = save_targets(save_results, save_results_rpe, pose_relation, force=force,
                             inputs=[p for p in (gt_dir, est_file, timestamps, est_cov) if p])
        with _collect_warnings() as notes:
            result = run_evaluation(gt_dir, est_file, fmt=fmt, topic=topic,
                                    child_frame=child_frame, timestamps=timestamps,
                                    est_cov=est_cov, options=options, max_gap=max_dt,
                                    gt_mode=gt_mode, gt_engine=gt_engine, lever_arm=lever_arm,
                                    prism=prism, gt_topic=gt_topic)
        saved = save_evo_results(result, saves, gt_dir=gt_dir, est_file=est_file,
                                 relation=pose_relation, force=force)
        written = None
        if plot is not None:
            from rtsgt.report.eval_plots import plot_evaluation

            written = plot_evaluation(result, plot, force=force)
        if as_json:
            typer.echo(json.dumps({**result.to_dict(), "warnings": notes}))
        else:
            _print_result(result, str(gt_dir), str(est_file), written, plot, saved)


def _check_choices(fmt: str | None, gt_mode: str, gt_engine: str, lever_arm: str | None) -> None:
    """``--format``, ``--gt-mode``, ``--gt-engine`` and ``--lever-arm``, as usage errors."""
    from rtsgt.app.evaluate import GT_MODES, gt_engines
    from rtsgt.evaluation.lever_arm import parse_lever_arm

    for value, choices, option in ((fmt, FORMATS, "--format"), (gt_mode, GT_MODES, "--gt-mode"),
                                   (gt_engine, gt_engines(), "--gt-engine")):
        if value is not None and value not in choices:
            raise typer.BadParameter(f"expected one of {', '.join(choices)}", param_hint=option)
    if lever_arm is not None:
        try:
            parse_lever_arm(lever_arm)
        except InputError as exc:
            raise usage_error(exc.bare_message, "--lever-arm") from None


def _print_result(result, gt_source: str, est_source: str, written, plot, saved) -> None:
    """The readable report, the drift table and the files written."""
    from rich.console import Console

    from rtsgt.evaluation import PositionEvaluationResult

    console = Console()
    report = (print_position_report if isinstance(result, PositionEvaluationResult)
              else print_report)
    report(result, console, gt_source=gt_source, est_source=est_source)
    print_drift(None if result.drift is None else result.drift.to_dict(), console)
    if written is not None:
        console.print(f"figures: {', '.join(p.name for p in written.files)} in {plot}")
    for path in saved:
        console.print(f"evo result: {path}", highlight=False)
