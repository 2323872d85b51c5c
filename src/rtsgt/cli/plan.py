"""``rtsgt plan``: the ground truth's uncertainty, predicted from a layout before going out."""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from rtsgt.errors import RtsgtWarning
from rtsgt.io.output_dir import OutputDir

if TYPE_CHECKING:
    from rtsgt.io.plan import PlanInputs
    from rtsgt.planning import PlanResult, RobotMotion

#: Points of an area's grid when the plan gives no step (about; the step is a round number).
DEFAULT_GRID_POINTS = 2500
#: Spacing of the points along waypoints when the plan gives no step, m.
DEFAULT_WAYPOINT_STEP_M = 1.0


def _round_step(raw: float) -> float:
    """The smallest of 1, 2, 5 times a power of ten at or above ``raw`` (m)."""
    k = math.floor(math.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * 10.0 ** k >= raw * (1 - 1e-12):
            return m * 10.0 ** k
    return 10.0 ** (k + 1)  # pragma: no cover


def _motion(inputs: PlanInputs, qc_run: Path | None) -> RobotMotion:
    from rtsgt.io.plan import read_run_qc
    from rtsgt.planning import DEFAULT_QC_M2_S3, RobotMotion, qc_from_run
    from rtsgt.planning.predict import DEFAULT_SPEED_M_S

    speed = DEFAULT_SPEED_M_S if inputs.speed_m_s is None else inputs.speed_m_s
    run = qc_run if qc_run is not None else inputs.qc_from_run
    if run is not None:
        return qc_from_run(read_run_qc(run), speed, f"run {run}")
    if inputs.qc_m2_s3 is not None:
        return RobotMotion.given(*inputs.qc_m2_s3, speed_m_s=speed, source="the plan")
    warnings.warn(f"plan: no Qc for the GP ([robot] qc_m2_s3 or qc_from_run): assuming "
                  f"{DEFAULT_QC_M2_S3[0]:g} (horizontal), {DEFAULT_QC_M2_S3[1]:g} (vertical) "
                  "m^2/s^3, the simulator's smooth robot; a real robot over rough ground can "
                  "have a hundred times more (docs/planning.md#the-gp-and-qc)",
                  RtsgtWarning, stacklevel=2)
    return RobotMotion.given(*DEFAULT_QC_M2_S3, speed_m_s=speed,
                             source="default: the simulator's smooth robot")


def compute_plan(plan: Path, *, path: Path | None = None,
                 qc_run: Path | None = None) -> PlanResult:
    """Read a plan file (or a deployment's TOML or folder) and predict over its area or path
    (``path``: a path file instead; ``qc_run``: the GP's Qc from that run directory)."""
    import numpy as np

    from rtsgt.geometry.so3 import quat_xyzw_to_matrix
    from rtsgt.io.deployment import resolve_config
    from rtsgt.io.plan import load_plan, read_path
    from rtsgt.planning import (
        DEFAULT_HEADINGS,
        layout_from_deployment,
        layout_from_positions,
        plan_area,
        plan_path,
        waypoint_path,
    )

    inputs = load_plan(resolve_config(plan))  # a deployment's folder: its deployment.toml
    if inputs.deployment is not None:
        data, options = inputs.deployment
        layout = layout_from_deployment(data, options, source=f"deployment {data.name}")
    else:
        layout = layout_from_positions(
            inputs.name, inputs.stations, inputs.gcp_xyz, inputs.reference, inputs.options,
            reference_station=inputs.reference_station, instrument=inputs.instrument,
            gcp_names=inputs.gcp_names, source=f"planned positions ({plan.name})")
    motion = _motion(inputs, qc_run)
    z_default = float(np.median(layout.gcp_xyz[:, 2] + layout.origin[2])) \
        if layout.gcp_xyz.size else float(layout.origin[2])
    z = z_default if inputs.z_m is None else inputs.z_m
    track = read_path(path) if path is not None else inputs.path_data
    if track is not None:
        xyz, t = np.where(np.isfinite(track.xyz), track.xyz, z), track.t
        if path is None and track.source == "waypoints":
            xyz, t = waypoint_path(xyz, inputs.path_step_m or DEFAULT_WAYPOINT_STEP_M), None
        R = None if track.quat_xyzw is None else quat_xyzw_to_matrix(track.quat_xyzw)
        return plan_path(layout, motion, xyz, t=t, R=R, forward_deg=inputs.forward_deg,
                         name=inputs.name)
    polygon = inputs.polygon
    if polygon is None:  # the area of the stations and the markers
        pts = np.vstack([np.array(list(layout.station_xyz().values())),
                         layout.gcp_xyz + layout.origin])[:, :2]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        polygon = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    step = inputs.step_m
    if step is None:
        ext = np.ptp(polygon, axis=0)
        step = _round_step(math.sqrt(max(ext[0] * ext[1], 1e-6) / DEFAULT_GRID_POINTS))
    return plan_area(layout, motion, polygon, step, z,
                     headings=inputs.headings or DEFAULT_HEADINGS,
                     forward_deg=inputs.forward_deg, name=inputs.name)


def write_plan(results: list[PlanResult], out: Path, *, inputs: list[Path],
               force: bool = False) -> tuple[Path, list[str]]:
    """Write the plan's directory (checked before any work by the caller's
    :class:`~rtsgt.io.output_dir.OutputDir`); returns it and the file names."""
    from rtsgt.report.plan import (
        draw_plan_map,
        plan_json_text,
        plan_table_text,
        render_plan_page,
    )

    output = OutputDir(out, "plan", force=force, inputs=inputs)
    names = ["plan.json", "sigma.csv", "plan_map.png", "plan_map.svg", "plan.html"]
    with output as tmp:
        (tmp / "plan.json").write_text(plan_json_text(results, [str(p) for p in inputs[:2]]),
                                       encoding="utf-8")
        (tmp / "sigma.csv").write_text(plan_table_text(results[0]), encoding="utf-8")
        if len(results) > 1:
            (tmp / "sigma_compare.csv").write_text(plan_table_text(results[1]), encoding="utf-8")
            names.insert(2, "sigma_compare.csv")
        fig = draw_plan_map(results)
        fig.save(tmp, ("png", "svg"))
        (tmp / "plan.html").write_text(render_plan_page(results, fig), encoding="utf-8")
    return output.final, names


def print_plan_summary(results: list[PlanResult], out: Path) -> None:
    """A short table of the prediction and the advice, one column per plan."""
    from rich.console import Console

    from rtsgt.cli.tables import TextTable
    from rtsgt.planning.plan import RANGE_LIMIT_M

    table = TextTable("rtsgt plan", ("", *[res.name for res in results]),
                      header=len(results) > 1, right=(False,) * (len(results) + 1))
    sums = [r.summary() for r in results]

    def row(label, fn):
        table.add_row(label, *[fn(s, r) for s, r in zip(sums, results, strict=True)])

    def dist(key):
        return lambda s, r: ("-" if s[key]["median"] is None else
                             f"{s[key]['median']:.2f} / {s[key]['p90']:.2f} / "
                             f"{s[key]['max']:.2f}")

    row("points predicted", lambda s, r: f"{s['points_predicted']} / {s['points']}")
    row("pose sigma, median / 90 % / largest (mm)", dist("sigma_mm"))
    row("rotation sigma, median / 90 % / largest (mrad)", dist("rotation_sigma_mrad"))
    row("GP Qc (m^2/s^3)", lambda s, r: f"{r.motion.qc_m2_s3[0, 0]:.2g} / "
        f"{r.motion.qc_m2_s3[2, 2]:.2g} ({r.motion.qc_source})")
    row(f"prisms beyond {RANGE_LIMIT_M:g} m", lambda s, r:
        f"{100 * s['advice']['ranges']['fraction_beyond']:.0f} % of the points: "
        f"{s['advice']['ranges']['verdict']}")
    row("points outside the markers' hull", lambda s, r:
        f"{100 * s['advice']['gcp_hull']['fraction_outside']:.0f} %: "
        f"{s['advice']['gcp_hull']['verdict']}")
    row("markers per station", lambda s, r: ", ".join(
        f"{k}: {v}" for k, v in s["advice"]["gcp_markers"]["per_station"].items())
        + f": {s['advice']['gcp_markers']['verdict']}")
    table.add_row("output", str(out), *[""] * (len(results) - 1))
    table.print(Console())


def register(app: typer.Typer) -> None:
    """Add the command to the application."""

    @app.command("plan")
    def plan_command(
        plan: Path = typer.Argument(..., help="Plan file (TOML), or a deployment TOML as its "
                                              "own layout."),
        out: Path = typer.Option(Path("rtsgt-plan"), "--out", "-o", help="Output directory."),
        compare: Path = typer.Option(None, "--compare",
                                     help="A second plan, drawn beside the first with the "
                                          "same colour scale."),
        path: Path = typer.Option(None, "--path",
                                  help="Predict along this path instead of the plan's area "
                                       "or path: x,y[,z][,t] CSV with a header, or poses "
                                       "(TUM, a run's groundtruth_covariance.csv, ...)."),
        qc_from_run_dir: Path = typer.Option(None, "--qc-from-run", metavar="RUN_DIR",
                                             help="Take the GP's Qc from this earlier run "
                                                  "of the same robot."),
        force: bool = typer.Option(False, "--force",
                                   help="Replace an earlier output of rtsgt at --out (never a "
                                        "directory holding anything else)."),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="No table."),
    ) -> None:
        """Predict the ground truth's pose uncertainty over a planned layout (a map)."""
        inputs = [plan] + ([compare] if compare is not None else [])
        OutputDir(out, "plan", force=force, inputs=inputs)  # refuse now, before any work
        results = [compute_plan(plan, path=path, qc_run=qc_from_run_dir)]
        if compare is not None:
            results.append(compute_plan(compare, path=path, qc_run=qc_from_run_dir))
        final, _ = write_plan(results, out, inputs=inputs, force=force)
        if not quiet:
            print_plan_summary(results, final)
