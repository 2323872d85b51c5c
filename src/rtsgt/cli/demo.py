"""``rtsgt demo``: simulate a deployment, compute its ground truth, compare with the truth."""

from __future__ import annotations

import contextlib
import warnings
from pathlib import Path

import typer

from rtsgt.cli.common import Stages, collected_warnings, print_warnings, usage_error
from rtsgt.cli.run import option_overrides, run_command
from rtsgt.errors import InputError
from rtsgt.io.output_dir import OutputDir, record_files

#: Simulations shorter than this (s) are too short for the demo to be meaningful.
_SHORT_S = 60.0


def run_demo(out: Path, *, seed: int, duration: float, engine: str, samples: int,
             force: bool, quiet: bool, report: bool = True, registration: str | None = None):
    """Simulate into ``out/deployment``, run into ``out/run`` (``out`` whole or not at all);
    returns (result, run directory, comparison with the truth)."""
    import numpy as np

    from rtsgt.io.run_dir import relocate_summary
    from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
    from rtsgt.simulation.compare import compare_to_truth

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
        done = run_command(toml, tmp / "run", engine=engine, samples=samples, seed=seed,
                           quiet=quiet, registration=registration,
                           inputs={"config": "../deployment/deployment.toml"})
        result, run_dir = done.record, done.path
        relocate_summary(run_dir, tmp, output.final)  # the paths the run will have
        if report:
            from rtsgt.report.html import write_report  # matplotlib: only for a report

            with Stages(quiet) as stages:
                stages("analysis, figures and HTML report")
                record_files(run_dir, [write_report(run_dir, shown_path=output.final / "run")])
        gt = result.groundtruth
        if len(gt) == 0:
            raise InputError("no pose passed the quality gates")
        p_true, q_true = sim.truth_at(gt.t)
        comparison = compare_to_truth(gt, p_true, q_true, split=result.groundtruth_split)
    return result, output.final / "run", comparison


@contextlib.contextmanager
def _as_final(tmp: Path, final: Path, duration: float):
    """Messages name the demo's files at ``final``, not ``tmp``; an error says when the
    simulation was too short."""
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


def _test(n) -> str:
    """The test that decided a NEES verdict, and its numbers, in words."""
    if n.split is None:
        lo, hi = (v / n.dof for v in n.mean_interval)
        return (f"autocorrelation test: NEES / dof {n.mean / n.dof:.2f}, accepted "
                f"{lo:.2f}-{hi:.2f}")
    sh, v = n.split.shared, n.split.varying
    return (f"split test: shared {sh.statistic:.1f} on {sh.dof} dof (accepted "
            f"{sh.interval[0]:.1f}-{sh.interval[1]:.1f}), varying NEES / dof "
            f"{v.mean / v.dof:.2f} (accepted {v.mean_interval[0] / v.dof:.2f}-"
            f"{v.mean_interval[1] / v.dof:.2f})")


def demo_verdict(comparison) -> str:
    """The demo's last line: the pose NEES's verdict (6 dof) against the truth, with the
    position's (3 dof) when it disagrees."""
    pose, position = comparison.nees_pose, comparison.nees_position
    word = "consistent" if pose.consistent else "inconsistent"
    line = (f"verdict: {word}: the ground truth's pose covariance "
            f"{'agrees' if pose.consistent else 'disagrees'} with the simulated truth "
            f"(6 dof, {_test(pose)})")
    if position.consistent != pose.consistent:
        line += (f"; the position alone (3 dof) is "
                 f"{'consistent' if position.consistent else 'inconsistent'}: {_test(position)}")
    return line


def print_demo_table(result, comparison, run_dir: Path) -> None:
    """The estimate against the truth in a few lines, the run's own verdict, and the demo's
    verdict as the last line."""
    import numpy as np
    from rich.console import Console

    from rtsgt.checks.verdict import record_verdict
    from rtsgt.cli.tables import TextTable

    d = comparison.to_dict()
    gt = result.groundtruth
    sig = np.sqrt(np.trace(gt.cov[:, :3, :3], axis1=1, axis2=2)) * 1e3
    t = TextTable("rtsgt demo: computed ground truth vs simulated truth",
                  ("quantity", "value", "accepted", "verdict"))
    t.add_row("poses kept / queried", f"{len(gt)} / {result.prisms_t.shape[0]}", "", "")
    t.add_row("position error RMSE", f"{d['position_error_mm']['rmse']:.2f} mm", "", "")
    t.add_row("median position sigma", f"{np.median(sig):.2f} mm", "~ RMSE", "")
    t.add_row("rotation error RMSE", f"{d['rotation_error_mrad']['rmse']:.3f} mrad", "", "")
    for n in (comparison.nees_position, comparison.nees_pose):
        test = "split test" if n.split is not None else "autocorrelation test"
        word = "consistent" if n.consistent else "inconsistent"
        lo, hi = (v / n.dof for v in n.mean_interval)
        t.add_row(f"NEES {n.dof} dof / dof", f"{n.mean / n.dof:.2f}",
                  f"({lo:.2f}-{hi:.2f})", f"{word} ({test})")
        if n.split is not None:
            sh, v = n.split.shared, n.split.varying
            t.add_row(f"  shared, chi2 {sh.dof} dof", f"{sh.statistic:.1f}",
                      f"{sh.interval[0]:.1f}-{sh.interval[1]:.1f}",
                      "consistent" if sh.consistent else "inconsistent")
            t.add_row("  varying, NEES / dof", f"{v.mean / v.dof:.2f}",
                      f"{v.mean_interval[0] / v.dof:.2f}-{v.mean_interval[1] / v.dof:.2f}",
                      "consistent" if v.consistent else "inconsistent")
    p = result.options.pose
    console = Console()
    t.print(console)
    console.print(f"pose engine {p.engine}, {p.registration} registration"
                  + (f", {p.samples} Monte Carlo samples" if p.engine == "mc" else ""),
                  highlight=False)
    console.print("The errors a deployment draws once (calibration, clocks, weather, survey) are "
                  "tested apart from those that vary from pose to pose (the split test, "
                  "docs/evaluation.md#errors-shared-by-the-deployment); the interval in "
                  "parentheses would hold for errors independent from pose to pose.",
                  highlight=False)
    out = run_dir.parent
    console.print(f"simulated inputs: {out / 'deployment'} (deployment.toml, the measurement "
                  "files, and the truth: truth.tum, truth.json)", highlight=False, soft_wrap=True)
    console.print(f"ground truth: {run_dir / 'groundtruth.tum'} (+ groundtruth_covariance.csv)",
                  highlight=False, soft_wrap=True)
    report = run_dir / "report.html"
    if report.exists():
        console.print(f"report: {report}", highlight=False, soft_wrap=True)
    console.print("self-checks of the run: " + record_verdict(result).line(
        str(run_dir / "summary.json")).removeprefix("verdict: "), highlight=False)


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
        quiet: bool = typer.Option(False, "--quiet", "-q",
                                   help="Only errors and the verdict line."),
        report: bool = typer.Option(True, "--report/--no-report", help="Write the HTML report."),
    ) -> None:
        """Simulate a deployment, compute its ground truth and compare it with the truth."""
        run_dir = None
        with collected_warnings() as caught:
            try:
                result, run_dir, comparison = run_demo(
                    out, seed=seed, duration=duration, engine=engine, samples=samples,
                    force=force, quiet=quiet, report=report, registration=registration)
            finally:
                if not quiet:
                    print_warnings(caught, None if run_dir is None else run_dir / "summary.json")
        if not quiet:
            print_demo_table(result, comparison, run_dir)
        typer.echo(demo_verdict(comparison))
