"""``rtsgt run``: compute the ground truth of a deployment."""

from __future__ import annotations

import warnings
from pathlib import Path

import typer

from rtsgt.cli.common import (
    Stages,
    checked_options,
    collected_warnings,
    echo_err,
    print_run_summary,
    print_warnings,
)
from rtsgt.errors import RtsgtWarning
from rtsgt.io.output_dir import check_target

#: The command-line options that override keys of the deployment's configuration.
RUN_OPTION_NAMES = {"engine": "--engine", "registration": "--registration",
                    "samples": "--samples", "rate_hz": "--rate", "prior": "--prior",
                    "correlated_noise": "--correlated-noise"}


def option_overrides(**values) -> dict:
    """The given (not None) option values, each checked by :class:`RunOptions`'s own rule
    (the rule the configuration file's values meet); a bad one is a usage error."""
    from rtsgt.options import RunOptions

    return checked_options(RunOptions().updated, RUN_OPTION_NAMES, **values)


def run_deployment(
    config: Path,
    out: Path,
    *,
    engine: str | None = None,
    samples: int | None = None,
    seed: int = 0,
    registration: str | None = None,
    rate: float | None = None,
    correlated_noise: str | None = None,
    force: bool = False,
    quiet: bool = False,
    report: bool = False,
    inputs: dict | None = None,
    prior: str | None = None,
):
    """Load, process and write one deployment; returns (RunRecord, output directory).

    The options and the output directory are checked before any work; ``report`` adds the
    HTML report to the run directory before it is put in place; ``inputs`` (default: the
    configuration's absolute path) is what ``summary.json`` records as the run's inputs.
    """
    from rtsgt.io.deployment import load_deployment, resolve_config
    from rtsgt.io.run_dir import write_run
    from rtsgt.pipeline import run_pipeline
    from rtsgt.record import PositionRunRecord

    config = resolve_config(config)
    changes = option_overrides(engine=engine, registration=registration, samples=samples,
                               rate_hz=rate, prior=prior, correlated_noise=correlated_noise)
    check_target(out, force=force, inputs=[config])
    with Stages(quiet) as stages:
        stages("reading inputs")
        data, options = load_deployment(config)
        options = options.updated(seed=seed, **changes)
        result = run_pipeline(data, options, progress=stages)
        stages("writing outputs")

        def add_report(tmp: Path, final: Path) -> None:
            from rtsgt.report.html import write_report  # matplotlib: only for a report

            stages("analysis, figures and HTML report")
            write_report(tmp, shown_path=final)

        if report and isinstance(result, PositionRunRecord):
            warnings.warn("--report: the HTML report is of runs with poses; this run gives "
                          "positions only (prisms/prism<i>.csv), and no report is written",
                          RtsgtWarning, stacklevel=2)
            report = False

        if inputs is None:
            inputs = {"config": str(Path(config).resolve())}
        final = write_run(result, out, force=force, inputs=inputs, protect=[config],
                          finish=add_report if report else None)
    return result, final


def register(app: typer.Typer) -> None:
    """Add the command to the application."""

    @app.command("run")
    def run(
        config: Path = typer.Argument(..., help="Deployment configuration (TOML)."),
        out: Path = typer.Option(Path("rtsgt-out"), "--out", "-o", help="Output directory."),
        engine: str = typer.Option(None, help="Pose engine: mc, ut or linear (default: config)."),
        registration: str = typer.Option(
            None, help="Fit of the prisms: weighted (by their covariance) or unweighted (the "
                       "paper's) (default: config)."),
        samples: int = typer.Option(None, help="Monte Carlo samples M (default: config)."),
        seed: int = typer.Option(0, min=0, help="Seed of every random draw (>= 0)."),
        rate: float = typer.Option(None, help="Query rate, Hz (default: config)."),
        prior: str = typer.Option(None, help="GP motion prior: wnoa (the paper's), wnoj, or "
                                             "select (per track, by held-out windows) "
                                             "(default: config)."),
        correlated_noise: str = typer.Option(
            None, "--correlated-noise",
            help="Noise the static stretches find time-correlated: inflate the white "
                 "covariance (inflate) or take the measurements as independent (ignore, the "
                 "paper) (default: config, else ignore)."),
        force: bool = typer.Option(False, "--force",
                                   help="Replace an earlier output of rtsgt at --out (never a "
                                        "directory holding anything else)."),
        quiet: bool = typer.Option(False, "--quiet", "-q",
                                   help="Only errors and the verdict line (no progress, "
                                        "warnings or table; all are in summary.json)."),
        report: bool = typer.Option(False, "--report", help="Also write the HTML report."),
    ) -> None:
        """Compute the ground truth of a deployment: poses with 6x6 covariance (with one or two
        tracked prisms: their positions with 3x3 covariance)."""
        from rtsgt.checks.verdict import record_verdict

        final = None
        with collected_warnings() as caught:
            try:
                result, final = run_deployment(
                    config, out, engine=engine, samples=samples, seed=seed, rate=rate,
                    force=force, quiet=quiet, report=report, registration=registration,
                    prior=prior, correlated_noise=correlated_noise)
            finally:
                if not quiet:
                    print_warnings(caught, None if final is None else final / "summary.json")
        shown = final / "report.html"
        if not quiet:
            print_run_summary(result, final)
            if shown.exists():
                echo_err(f"report: {shown}")
        typer.echo(record_verdict(result).line(
            str(shown if shown.exists() else final / "summary.json")))
