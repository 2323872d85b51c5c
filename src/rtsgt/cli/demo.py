"""``rtsgt demo``: simulate a deployment, compute its ground truth, compare with the truth."""

from __future__ import annotations

import contextlib
import warnings
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from rtsgt.cli.common import Stages, usage_error
from rtsgt.cli.run import option_overrides, run_deployment
from rtsgt.errors import InputError
from rtsgt.io.output_dir import OutputDir, record_files
from rtsgt.io.run_dir import relocate_summary
from rtsgt.report.html import write_report
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth

#: Simulations shorter than this (s) are too short for the demo to be meaningful.
_SHORT_S = 60.0


def run_demo(out: Path, *, seed: int, duration: float, engine: str, samples: int,
             force: bool, quiet: bool, report: bool = True, registration: str | None = None):
    """Simulate into ``out/deployment``, run into ``out/run``; returns (result, run directory,
    comparison with the truth).

    ``out`` appears whole when everything succeeded (report included), and not at all
    otherwise; the options are checked before any work.
    """

    option_overrides(engine=engine, registration=registration, samples=samples)
    try:
        config = SimulationConfig(duration_s=duration)
    except ValueError as exc:
        raise usage_error(str(exc), "--duration") from None
    output = OutputDir(out, "demo", force=force)
    with output as tmp, _as_final(tmp, output.final, duration):
        with Stages(quiet) as stages:
            stages("simulating a deployment")
            sim = simulate_deployment(config, np.random.default_rng(seed))
            toml = write_deployment(sim, tmp / "deployment", name=f"demo-seed-{seed}")
        result, run_dir = run_deployment(toml, tmp / "run", engine=engine, samples=samples,
                                         seed=seed, quiet=quiet, registration=registration,
                                         inputs={"config": "../deployment/deployment.toml"})
        relocate_summary(run_dir, tmp, output.final)  # the paths the run will have
        if report:
            with Stages(quiet) as stages:
                stages("analysis, figures and HTML report")
                record_files(run_dir, [write_report(run_dir, shown_path=output.final / "run")])
        gt = result.groundtruth
        if len(gt) == 0:
            raise InputError("no pose passed the quality gates")
        p_true, q_true = sim.truth_at(gt.t)
        comparison = compare_to_truth(gt, p_true, q_true)
    return result, output.final / "run", comparison


@contextlib.contextmanager
def _as_final(tmp: Path, final: Path, duration: float):
    """Messages about the demo's files name them where they will be (``final``), not in the
    temporary directory they are written to; an error says that the simulation was too
    short when it was."""
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield
    except InputError as exc:
        hint = "; simulate a longer deployment (--duration)" if duration < _SHORT_S else ""
        raise InputError(f"the simulated deployment of {duration:g} s could not be processed: "
                         f"{str(exc).replace(str(tmp), str(final))}{hint}") from None
    finally:
        for w in caught:
            warnings.warn_explicit(str(w.message).replace(str(tmp), str(final)),
                                   w.category, w.filename, w.lineno)


def _verdict(n) -> str:
    """In words: are the mean NEES / dof and the share inside the 95 % region as expected?"""
    lo, hi = (v / n.dof for v in n.mean_interval)
    flo, fhi = n.fraction_interval
    parts = [f"NEES / dof {n.mean / n.dof:.2f} "
             + ("inside" if n.mean_ok else "OUTSIDE") + f" its expected range {lo:.2f}-{hi:.2f}",
             f"{100 * n.fraction_inside_95:.1f} % inside the 95 % region, "
             + ("inside" if n.fraction_ok else "OUTSIDE")
             + f" its expected range {100 * flo:.1f}-{100 * fhi:.1f} %"]
    return "; ".join(parts)


def print_demo_table(result, comparison, run_dir: Path) -> None:
    """The estimate against the truth, in a few lines, with a verdict in words."""
    d = comparison.to_dict()
    gt = result.groundtruth
    sig = np.sqrt(np.trace(gt.cov[:, :3, :3], axis1=1, axis2=2)) * 1e3
    t = Table(title="rtsgt demo: computed ground truth vs simulated truth")
    t.add_column("quantity")
    t.add_column("value", justify="right")
    t.add_column("expected", justify="right")
    t.add_row("poses kept / queried", f"{len(gt)} / {result.prisms_t.shape[0]}", "")
    t.add_row("position error RMSE", f"{d['position_error_mm']['rmse']:.2f} mm", "")
    t.add_row("median position sigma (sqrt trace)", f"{np.median(sig):.2f} mm", "~ RMSE")
    t.add_row("rotation error RMSE", f"{d['rotation_error_mrad']['rmse']:.3f} mrad", "")
    for n in (comparison.nees_position, comparison.nees_pose):
        lo, hi = (v / n.dof for v in n.mean_interval)
        flo, fhi = n.fraction_interval
        t.add_row(f"NEES {n.dof} dof: mean / dof", f"{n.mean / n.dof:.2f}", f"{lo:.2f}-{hi:.2f}")
        t.add_row(f"NEES {n.dof} dof: inside 95 % region", f"{100 * n.fraction_inside_95:.1f} %",
                  f"{100 * flo:.1f}-{100 * fhi:.1f} %")
    p = result.options.pose
    t.add_row("engine / registration / samples",
              f"{p.engine} / {p.registration} / {p.samples}", "")
    console = Console()
    console.print(t)
    console.print("Expected ranges: two-sided 95 % acceptance intervals of a chi-square test that "
                  "accounts for the correlation between consecutive poses "
                  "(rtsgt.evaluation.metrics.nees_consistency).", highlight=False)
    for name, n in (("position", comparison.nees_position), ("pose", comparison.nees_pose)):
        word = "honest" if n.consistent else "NOT consistent with the truth"
        console.print(f"verdict, {name} ({n.dof} dof): covariance {word}: {_verdict(n)}.",
                      highlight=False)
    out = run_dir.parent
    typer.echo(f"simulated inputs: {out / 'deployment'} (deployment.toml, the measurement "
               "files, and the truth: truth.tum, truth.json)")
    typer.echo(f"ground truth: {run_dir / 'groundtruth.tum'} (+ groundtruth_covariance.csv)")
    report = run_dir / "report.html"
    if report.exists():
        typer.echo(f"report: {report}")


def register(app: typer.Typer) -> None:
    """Add the command to the application."""

    @app.command("demo")
    def demo(
        out: Path = typer.Option(Path("rtsgt-demo"), "--out", "-o", help="Output directory."),
        seed: int = typer.Option(0, min=0, help="Seed of the simulation and of the run (>= 0)."),
        duration: float = typer.Option(600.0, help="Simulated tracking time, s."),
        engine: str = typer.Option("mc", help="Pose engine: mc, ut or linear."),
        registration: str = typer.Option(
            None, help="Fit of the prisms: weighted (by their covariance) or unweighted (the "
                       "paper's) (default: weighted)."),
        samples: int = typer.Option(1000, help="Monte Carlo samples M."),
        force: bool = typer.Option(False, "--force",
                                   help="Replace an earlier output of rtsgt at --out (never a "
                                        "directory holding anything else)."),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="Only the final table."),
        report: bool = typer.Option(True, "--report/--no-report", help="Write the HTML report."),
    ) -> None:
        """Simulate a deployment, compute its ground truth and compare it with the truth."""
        result, run_dir, comparison = run_demo(out, seed=seed, duration=duration, engine=engine,
                                               samples=samples, force=force, quiet=quiet,
                                               report=report, registration=registration)
        print_demo_table(result, comparison, run_dir)
