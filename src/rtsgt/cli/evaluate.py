"""``rtsgt evaluate``: evaluate a SLAM / odometry trajectory against an rtsgt ground truth.

A thin wrapper over :func:`rtsgt.io.trajectory.read_trajectory`,
:func:`rtsgt.evaluation.evaluate` and :func:`rtsgt.report.eval_plots.plot_evaluation`.
``GT_DIR`` is an ``rtsgt run`` output directory (``groundtruth_covariance.csv`` preferred,
else ``groundtruth.tum``) or a trajectory file.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from rtsgt.errors import InputError
from rtsgt.evaluation import ALIGN_METHODS, DELTA_UNITS, EvaluationResult, evaluate
from rtsgt.io.trajectory import (
    FORMATS,
    attach_covariance,
    read_covariance_csv,
    read_groundtruth_dir,
    read_trajectory,
)


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
) -> EvaluationResult:
    """Read the ground truth and the estimate, then :func:`rtsgt.evaluation.evaluate`."""
    gt_path = Path(gt_dir)
    if gt_path.is_dir() and not (gt_path / "metadata.yaml").exists():
        gt = read_groundtruth_dir(gt_path)
    elif gt_path.exists():
        gt = read_trajectory(gt_path)
    else:
        raise InputError("ground truth not found", gt_path)
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
    console.print(
        f"[bold]{est_source}[/bold] against [bold]{gt_source}[/bold]: {len(a)} of {a.n_est} "
        f"estimate poses associated ({a.n_outside} outside the ground truth, {a.n_gap} in its "
        f"gaps; time offset {a.time_offset} s, max dt {a.max_dt} s)"
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
            help="rtsgt output directory (groundtruth_covariance.csv or groundtruth.tum), "
            "or a ground-truth trajectory file.",
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
            0.0, "--time-offset", help="Seconds added to the estimate's times."
        ),
        max_dt: float = typer.Option(
            0.5, "--max-dt", help="Max distance (s) to the nearest ground-truth time."
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
