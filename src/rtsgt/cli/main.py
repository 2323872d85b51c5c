"""The ``rtsgt`` command line: a thin layer over the library.

Each command lives in its own module of :mod:`rtsgt.cli` and registers itself on :data:`app`
through a ``register(app)`` function. Errors derived from :class:`rtsgt.errors.RtsgtError` are
printed as one line on stderr with exit code 1 (no traceback).
"""

from __future__ import annotations

import sys

import typer

from rtsgt import __version__
from rtsgt.errors import RtsgtError

app = typer.Typer(
    name="rtsgt",
    help="Robotic total station ground truth: 6-DOF trajectories with honest covariances.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"rtsgt {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
) -> None:
    """Robotic total station ground truth."""


def fail(message: str) -> None:
    """Print ``error: message`` on stderr and exit with code 1."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(1)


def _register_all() -> None:
    from rtsgt.cli import analyze, calibrate, demo, evaluate, interpolate, run, simulate

    for module in (calibrate, interpolate, simulate, run, demo, evaluate, analyze):
        module.register(app)


_register_all()


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings of the library as one ``warning: ...`` line, without a source excerpt."""
    typer.echo(f"warning: {message}", err=True)


def main() -> None:  # pragma: no cover - console entry point
    import warnings

    warnings.showwarning = _show_warning
    try:
        app()
    except RtsgtError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(1)
