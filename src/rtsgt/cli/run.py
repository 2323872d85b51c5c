"""``rtsgt run``: compute the ground truth of a deployment."""

from __future__ import annotations

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

#: The command-line options that override keys of the deployment's configuration.
RUN_OPTION_NAMES = {"engine": "--engine", "registration": "--registration",
                    "samples": "--samples", "rate_hz": "--rate", "prior": "--prior",
                    "correlated_noise": "--correlated-noise", "profile": "--profile"}


def option_overrides(**values) -> dict:
    """The given (not None) option values, each checked by :class:`RunOptions`'s own rule
    (the rule the configuration file's values meet); a bad one is a usage error."""
    from rtsgt.options import RunOptions

    return checked_options(RunOptions().updated, RUN_OPTION_NAMES, **values)


def run_command(config: Path, out: Path, *, seed: int = 0, force: bool = False,
                quiet: bool = False, report: bool = False, inputs: dict | None = None,
                profile: str | None = None, **values):
    """The command-line ``values`` (None: the configuration's) and ``profile`` checked as
    usage errors, then :func:`rtsgt.app.run_deployment` with progress on stderr."""
    from rtsgt.app import run_deployment

    values = {("rate_hz" if k == "rate" else k): v for k, v in values.items()}
    changes = option_overrides(profile=profile, **values)
    profile = changes.pop("profile", None)
    with Stages(quiet) as stages:
        return run_deployment(config, out, options=changes, profile=profile, seed=seed,
                              force=force, report=report, inputs=inputs, progress=stages)


def register(app: typer.Typer) -> None:
    """Add the command to the application."""

    @app.command("run")
    def run(
        config: Path = typer.Argument(..., help="Deployment configuration (TOML)."),
        out: Path = typer.Option(Path("rtsgt-out"), "--out", "-o", help="Output directory."),
        engine: str = typer.Option(
            None, help="Pose engine: mc, ut or linear (per prism), or joint (every raw "
                       "measurement at once, after the per-prism poses) (default: config)."),
        registration: str = typer.Option(
            None, help="Fit of the prisms: weighted (by their covariance) or unweighted (the "
                       "paper's) (default: config)."),
        samples: int = typer.Option(None, help="Monte Carlo samples M (default: config)."),
        seed: int = typer.Option(0, min=0, help="Seed of every random draw (>= 0)."),
        rate: float = typer.Option(None, help="Query rate, Hz (default: config)."),
        prior: str = typer.Option(None, help="GP motion prior: wnoa (the paper's), wnoj, or "
                                  "select (per track, by held-out windows) " "(default: config)."),
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
        profile: str = typer.Option(
            None, help="Preset of the switches: paper (the published method, "
                       "docs/honesty.md#the-papers-switches); a switch given with it wins "
                       "(default: config)."),
    ) -> None:
        """Compute the ground truth of a deployment: poses with 6x6 covariance (with one or two
        tracked prisms: their positions with 3x3 covariance)."""
        from rtsgt.checks.verdict import record_verdict

        done = None
        with collected_warnings() as caught:
            try:
                done = run_command(
                    config, out, engine=engine, samples=samples, seed=seed, rate=rate,
                    force=force, quiet=quiet, report=report, registration=registration,
                    prior=prior, correlated_noise=correlated_noise, profile=profile)
            finally:
                if not quiet:
                    print_warnings(caught, None if done is None else done.summary)
        shown = done.path / "report.html"
        if not quiet:
            print_run_summary(done.record, done.path)
            if shown.exists():
                echo_err(f"report: {shown}")
        typer.echo(record_verdict(done.record).line(str(shown if shown.exists() else done.summary)))
