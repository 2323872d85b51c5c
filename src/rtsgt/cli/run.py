"""``rtsgt run``: compute the ground truth of a deployment."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import typer

from rtsgt.cli.common import Stages, echo_err


def run_deployment(
    config: Path,
    out: Path,
    *,
    engine: str | None = None,
    samples: int | None = None,
    seed: int = 0,
    rate: float | None = None,
    force: bool = False,
    quiet: bool = False,
):
    """Load, process and write one deployment; returns (RunResult, output directory)."""
    from rtsgt.io.deployment import load_deployment
    from rtsgt.io.run_output import prepare_output_dir, write_run
    from rtsgt.pipeline import run_pipeline

    # refuse an existing output before any work
    _, tmp = prepare_output_dir(out, force)
    tmp.rmdir()
    with Stages(quiet) as stages:
        stages("reading inputs")
        data, options = load_deployment(config)
        changes = {"seed": seed}
        if engine is not None:
            changes["engine"] = engine
        if samples is not None:
            changes["samples"] = samples
        if rate is not None:
            changes["rate_hz"] = rate
        options = dataclasses.replace(options, **changes)
        result = run_pipeline(data, options, progress=stages)
        stages("writing outputs")
        inputs = {"config": str(Path(config).resolve())}
        final = write_run(result, out, force=force, inputs=inputs)
    return result, final


def register(app: typer.Typer) -> None:
    """Add the command to the application."""

    @app.command("run")
    def run(
        config: Path = typer.Argument(..., help="Deployment configuration (TOML)."),
        out: Path = typer.Option(Path("rtsgt-out"), "--out", "-o", help="Output directory."),
        engine: str = typer.Option(None, help="Pose engine: mc, ut or linear (default: config)."),
        samples: int = typer.Option(None, help="Monte Carlo samples M (default: config)."),
        seed: int = typer.Option(0, help="Seed of every random draw."),
        rate: float = typer.Option(None, help="Query rate, Hz (default: config)."),
        force: bool = typer.Option(False, "--force", help="Replace an existing output directory."),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress, no table."),
        report: bool = typer.Option(False, "--report", help="Also write the HTML report."),
    ) -> None:
        """Compute the ground truth of a deployment: poses with 6x6 covariance."""
        result, final = run_deployment(config, out, engine=engine, samples=samples, seed=seed,
                                       rate=rate, force=force, quiet=quiet)
        if report:
            from rtsgt.report.html import write_report

            path = write_report(final)
            if not quiet:
                echo_err(f"report: {path}")
        if not quiet:
            from rtsgt.cli.common import print_run_summary

            print_run_summary(result, final)
