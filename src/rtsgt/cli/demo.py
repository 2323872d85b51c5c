"""``rtsgt demo``: simulate a deployment, compute its ground truth, compare with the truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.table import Table


def run_demo(out: Path, *, seed: int, duration: float, engine: str, samples: int,
             force: bool, quiet: bool):
    """Simulate into ``out/deployment``, run into ``out/run``; returns (result, comparison)."""
    from rtsgt.cli.run import run_deployment
    from rtsgt.io.run_output import prepare_output_dir
    from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
    from rtsgt.simulation.compare import compare_to_truth

    final, tmp = prepare_output_dir(out, force)
    tmp.rmdir()
    final.mkdir(parents=True, exist_ok=True)
    sim = simulate_deployment(SimulationConfig(duration_s=duration), np.random.default_rng(seed))
    config = write_deployment(sim, final / "deployment", overwrite=force, name=f"demo-seed-{seed}")
    result, run_dir = run_deployment(config, final / "run", engine=engine, samples=samples,
                                     seed=seed, force=force, quiet=quiet)
    gt = result.groundtruth
    p_true, q_true = sim.truth_at(gt.t)
    return result, run_dir, compare_to_truth(gt, p_true, q_true)


def print_demo_table(result, comparison, run_dir: Path) -> None:
    """The estimate against the truth, in a few lines."""
    d = comparison.to_dict()
    gt = result.groundtruth
    sig = np.sqrt(np.trace(gt.cov[:, :3, :3], axis1=1, axis2=2)) * 1e3
    t = Table(title="rtsgt demo: computed ground truth vs simulated truth")
    t.add_column("quantity")
    t.add_column("value", justify="right")
    t.add_column("ideal", justify="right")
    t.add_row("poses kept / queried", f"{len(gt)} / {len(result.estimate)}", "")
    t.add_row("position error RMSE", f"{d['position_error_mm']['rmse']:.2f} mm", "")
    t.add_row("median position sigma (sqrt trace)", f"{np.median(sig):.2f} mm", "~ RMSE")
    t.add_row("rotation error RMSE", f"{d['rotation_error_mdeg']['rmse']:.1f} mdeg", "")
    for key, dof in (("nees_position", 3), ("nees_pose", 6)):
        n = d[key]
        t.add_row(f"NEES {dof} dof: mean / dof", f"{n['mean'] / dof:.2f}", "1.00")
        t.add_row(f"NEES {dof} dof: inside 95 % region", f"{100 * n['fraction_inside_95']:.1f} %",
                  "95 %")
    t.add_row("engine / samples", f"{result.options.engine} / {result.options.samples}", "")
    Console().print(t)
    typer.echo(f"ground truth: {run_dir}/groundtruth.tum (+ groundtruth_covariance.csv)")
    report = run_dir / "report.html"
    if report.exists():
        typer.echo(f"report: {report}")


def register(app: typer.Typer) -> None:
    """Add the command to the application."""

    @app.command("demo")
    def demo(
        out: Path = typer.Option(Path("rtsgt-demo"), "--out", "-o", help="Output directory."),
        seed: int = typer.Option(0, help="Seed of the simulation and of the run."),
        duration: float = typer.Option(600.0, help="Simulated tracking time, s."),
        engine: str = typer.Option("mc", help="Pose engine: mc, ut or linear."),
        samples: int = typer.Option(1000, help="Monte Carlo samples M."),
        force: bool = typer.Option(False, "--force", help="Replace an existing output."),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="Only the final table."),
        report: bool = typer.Option(True, "--report/--no-report", help="Write the HTML report."),
    ) -> None:
        """Simulate a deployment, compute its ground truth and compare it with the truth."""
        result, run_dir, comparison = run_demo(out, seed=seed, duration=duration, engine=engine,
                                               samples=samples, force=force, quiet=quiet)
        if report:
            try:
                from rtsgt.report.html import write_report
            except ImportError:  # the optional report extra is not installed
                pass
            else:
                write_report(run_dir)
        print_demo_table(result, comparison, run_dir)
