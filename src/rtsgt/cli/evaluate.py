"""``rtsgt evaluate``: evaluate a SLAM / odometry trajectory against an rtsgt ground truth.

A thin wrapper over :func:`rtsgt.io.trajectory.read_trajectory`,
:func:`rtsgt.evaluation.evaluate` and :func:`rtsgt.report.eval_plots.plot_evaluation`.
``GT_DIR`` is an ``rtsgt run`` output directory or a trajectory file. A run directory with
``measurements/`` gives a continuous-time ground truth
(:class:`rtsgt.evaluation.groundtruth.ContinuousGroundTruth`: the pose and covariance at each
estimate time from the run's GP tracks, and the run's gates); otherwise (or with
``--gt-mode discrete``) its stored poses (``groundtruth_covariance.csv`` preferred, else
``groundtruth.tum``) are interpolated.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from rtsgt.errors import InputError
from rtsgt.evaluation import ALIGN_METHODS, DELTA_UNITS, EvaluationResult, evaluate
from rtsgt.evaluation.associate import GroundTruthQuery, ValidatedGroundTruth
from rtsgt.io.trajectory import (
    FORMATS,
    attach_covariance,
    read_covariance_csv,
    read_groundtruth_dir,
    read_trajectory,
)
from rtsgt.types import PoseTrajectory

#: Ground-truth modes of ``--gt-mode``.
GT_MODES = ("auto", "continuous", "discrete")
#: Pose engines of ``--gt-engine`` (``run``: the run's own).
GT_ENGINES = ("run", "mc", "ut", "linear")


def load_ground_truth(
    gt_dir: str | Path, *, mode: str = "auto", engine: str | None = None
) -> PoseTrajectory | ValidatedGroundTruth | GroundTruthQuery:
    """The ground truth of ``GT_DIR``: continuous from a run directory with ``measurements/``
    (``mode`` ``auto`` or ``continuous``), else the discrete stored poses or trajectory file.

    ``engine``: pose engine of the continuous ground truth (None: the run's).
    """
    if mode not in GT_MODES:
        raise InputError(f"unknown ground-truth mode {mode!r}; expected one of {', '.join(GT_MODES)}")
    gt_path = Path(gt_dir)
    run_dir = gt_path.is_dir() and not (gt_path / "metadata.yaml").exists()
    if run_dir and mode != "discrete" and (gt_path / "measurements").is_dir():
        from rtsgt.evaluation.groundtruth import ContinuousGroundTruth

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


def run_evaluate(
    gt_dir: str | Path,
    est_file: str | Path,
    *,
    fmt: str | None = None,
    topic: str | None = None,
    child_frame: str | None = None,
    timestamps: str | Path | None = None,
    est_cov: str | Path | None = None,
    align: str = "se3",
    n_align: int | None = None,
    weighted: bool = False,
    delta: float = 1.0,
    delta_unit: str = "m",
    all_pairs: bool = False,
    time_offset: float = 0.0,
    max_dt: float | None = 0.5,
    gt_mode: str = "auto",
    gt_engine: str | None = None,
) -> EvaluationResult:
    """Read the ground truth and the estimate, then :func:`rtsgt.evaluation.evaluate`.

    ``time_offset`` (s) is added to the estimate's times; ``max_dt`` (s) is the largest
    distance to the nearest ground-truth measurement (continuous: of every prism; discrete:
    the nearest stored pose); ``gt_mode`` and ``gt_engine``: :func:`load_ground_truth`
    (``gt_engine`` ``"run"`` or None: the run's engine).
    """
    if gt_engine is not None and gt_engine not in GT_ENGINES:
        raise InputError(
            f"unknown ground-truth engine {gt_engine!r}; expected one of {', '.join(GT_ENGINES)}"
        )
    gt = load_ground_truth(
        gt_dir, mode=gt_mode, engine=None if gt_engine in (None, "run") else gt_engine
    )
    if fmt is not None and fmt not in FORMATS:
        raise InputError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
    est = read_trajectory(
        est_file, fmt, topic=topic, timestamps=timestamps, child_frame=child_frame
    )
    if est_cov is not None:
        est = attach_covariance(est, read_covariance_csv(est_cov), source=str(est_cov))
    return evaluate(
        gt,
        est,
        align=align,
        n_align=n_align,
        weighted=weighted,
        delta=delta,
        delta_unit=delta_unit,
        all_pairs=all_pairs,
        time_offset=time_offset,
        max_dt=max_dt,
    )


def _stats_row(name: str, s, scale: float, digits: int) -> list[str]:
    return [name] + [
        f"{scale * getattr(s, k):.{digits}f}"
        for k in ("rmse", "mean", "median", "std", "min", "max")
    ]


def print_report(
    result: EvaluationResult, console: Console, *, gt_source: str, est_source: str
) -> None:
    """The readable report: association, alignment, APE/RPE, NEES, noise floor."""
    a = result.association
    if a.ground_truth == "continuous":
        d = a.ground_truth_detail
        kind = f"continuous ground truth (GP tracks, {d.get('engine', '?')} pose engine)"
        limit = "max gap"
    else:
        kind = f"{a.ground_truth} ground truth"
        limit = "max dt"
    dropped = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in a.dropped.items())
    console.print(
        f"[bold]{est_source}[/bold] against [bold]{gt_source}[/bold] ({kind}): {len(a)} of "
        f"{a.n_est} estimate poses associated"
        + (f"; dropped: {dropped}" if dropped else "")
        + f" (time offset {a.time_offset} s, {limit} {a.max_dt} s)"
    )
    al = result.alignment
    if al.method == "none":
        console.print("alignment: none")
    else:
        console.print(
            f"alignment: {al.method}{' (covariance-weighted)' if al.weighted else ''} on "
            f"{al.n_used} poses, yaw {al.yaw * 57.29577951308232:.4f} deg, scale {al.scale:.6f}, "
            f"t = [{', '.join(f'{v:.4f}' for v in al.translation)}] m"
        )
    table = Table(title="Pose errors (evo definitions)")
    for col in ("metric", "rmse", "mean", "median", "std", "min", "max"):
        table.add_column(col, justify="left" if col == "metric" else "right")
    table.add_row(*_stats_row("APE translation (mm)", result.ape.translation_m, 1e3, 3))
    table.add_row(*_stats_row("APE rotation (deg)", result.ape.rotation_deg, 1.0, 4))
    unit = {"m": "m", "s": "s", "f": "frames"}[result.rpe_delta_unit]
    pairs = f"{result.rpe.pairs.shape[0]} {'all' if result.rpe_all_pairs else 'consecutive'} pairs"
    table.add_section()
    table.add_row(
        *_stats_row(
            f"RPE translation (mm), {result.rpe_delta:g} {unit}", result.rpe.translation_m, 1e3, 3
        )
    )
    table.add_row(*_stats_row(f"RPE rotation (deg), {pairs}", result.rpe.rotation_deg, 1.0, 4))
    console.print(table)
    n = result.nees
    if n.position is None:
        console.print(f"NEES: {n.covariance}")
        return
    nt = Table(title=f"NEES (covariance: {n.covariance})")
    for col in ("", "mean", "dof", "accepted mean", "inside 95 %", "accepted", "N_eff", "verdict"):
        nt.add_column(col, justify="left" if col == "" else "right")
    for name, r in (
        ("position", n.position),
        ("pose", n.pose),
        ("relative position", n.relative_position),
        ("relative pose", n.relative_pose),
    ):
        verdict = "[green]consistent[/green]" if r.consistent else "[red]inconsistent[/red]"
        nt.add_row(
            name,
            f"{r.mean:.3f}",
            str(r.dof),
            f"[{r.mean_interval[0]:.2f}, {r.mean_interval[1]:.2f}]",
            f"{100 * r.fraction_inside_95:.1f} %",
            f"[{100 * r.fraction_interval[0]:.1f}, {100 * r.fraction_interval[1]:.1f}] %",
            f"{r.n_eff:.0f} / {r.n}",
            verdict,
        )
    console.print(nt)
    console.print(f"relative poses: ground-truth correlations {n.rpe_correlations}")
    f = result.noise_floor
    console.print(
        f"noise floor of the ground truth: APE {1e3 * f.ape_translation_m:.3f} mm, "
        f"{f.ape_rotation_deg:.4f} deg; APE rmse with the floor removed "
        f"{1e3 * f.ape_translation_rmse_floor_removed_m:.3f} mm, "
        f"{f.ape_rotation_rmse_floor_removed_deg:.4f} deg"
    )
    console.print(
        f"RPE floor {1e3 * f.rpe_translation_m:.3f} mm, {f.rpe_rotation_deg:.4f} deg; "
        f"RPE rmse with the floor removed {1e3 * f.rpe_translation_rmse_floor_removed_m:.3f} mm, "
        f"{f.rpe_rotation_rmse_floor_removed_deg:.4f} deg"
    )
    if a.cov_interpolated.any():
        console.print(
            f"note: {int(a.cov_interpolated.sum())} ground-truth covariances were interpolated "
            "linearly between samples"
        )


def register(app: typer.Typer) -> None:
    """Add ``rtsgt evaluate`` to the application."""

    @app.command("evaluate")
    def evaluate_command(
        gt_dir: Path = typer.Argument(
            ...,
            metavar="GT_DIR",
            help="rtsgt run directory (continuous ground truth from its measurements/, else "
            "groundtruth_covariance.csv or groundtruth.tum), or a ground-truth trajectory file.",
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
            0.0, "--t-offset", "--time-offset", help="Seconds added to the estimate's times."
        ),
        max_dt: float = typer.Option(
            0.5,
            "--max-gap",
            "--max-dt",
            help="Max distance (s) to the nearest ground-truth measurement (continuous: of "
            "every prism; discrete: the nearest stored pose); poses farther are dropped.",
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
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        plot: Path | None = typer.Option(None, "--plot", help="Write PNG and SVG figures here."),
    ) -> None:
        """Evaluate an estimated trajectory against the uncertain ground truth (APE, RPE, NEES)."""
        if align not in ALIGN_METHODS:
            raise typer.BadParameter(
                f"expected one of {', '.join(ALIGN_METHODS)}", param_hint="--align"
            )
        if delta_unit not in DELTA_UNITS:
            raise typer.BadParameter(
                f"expected one of {', '.join(DELTA_UNITS)}", param_hint="--delta-unit"
            )
        if fmt is not None and fmt not in FORMATS:
            raise typer.BadParameter(f"expected one of {', '.join(FORMATS)}", param_hint="--format")
        if gt_mode not in GT_MODES:
            raise typer.BadParameter(f"expected one of {', '.join(GT_MODES)}", param_hint="--gt-mode")
        if gt_engine not in GT_ENGINES:
            raise typer.BadParameter(
                f"expected one of {', '.join(GT_ENGINES)}", param_hint="--gt-engine"
            )
        if not max_dt > 0:
            raise typer.BadParameter("expected a positive number of seconds", param_hint="--max-gap")
        result = run_evaluate(
            gt_dir,
            est_file,
            fmt=fmt,
            topic=topic,
            child_frame=child_frame,
            timestamps=timestamps,
            est_cov=est_cov,
            align=align,
            n_align=n_align,
            weighted=weighted,
            delta=delta,
            delta_unit=delta_unit,
            all_pairs=all_pairs,
            time_offset=time_offset,
            max_dt=max_dt,
            gt_mode=gt_mode,
            gt_engine=gt_engine,
        )
        written = None
        if plot is not None:
            from rtsgt.report.eval_plots import plot_evaluation

            written = plot_evaluation(result, plot)
        if as_json:
            typer.echo(json.dumps(result.to_dict()))
            return
        console = Console()
        print_report(result, console, gt_source=str(gt_dir), est_source=str(est_file))
        if written is not None:
            console.print(f"figures: {', '.join(p.name for p in written.files)} in {plot}")
