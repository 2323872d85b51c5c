"""The ``rtsgt`` command line: a thin layer over the library.

Each command lives in its own module of :mod:`rtsgt.cli` and registers itself on :data:`app`
through a ``register(app)`` function.

Exit status and messages (one rule for every command):

====  ======================================================================================
0     success (warnings, if any, are ``warning: ...`` lines on stderr)
1     the input is wrong or cannot be used: a file, a line, a value of the configuration, an
      output path that may not be written (:class:`rtsgt.errors.RtsgtError`)
2     the command line is wrong: an unknown command or option, a missing argument, a value
      an option does not accept
3     an unexpected error inside rtsgt (a bug: please report it); ``RTSGT_TRACEBACK=1``
      shows the traceback
130   interrupted (Ctrl-C), at any moment, start-up included (:mod:`rtsgt.cli.entry`, the
      console script); the one line is ``error: interrupted``; nothing half-written is left
====  ======================================================================================

Every error is one line on stderr, ``error: ...``, naming the file, line, option or value;
never a traceback.
"""

from __future__ import annotations

import os
import sys
import warnings
from collections.abc import Sequence
from typing import Any

import typer
from typer.core import TyperGroup

from rtsgt import __version__
from rtsgt.cli import (
    analyze,
    batch,
    calibrate,
    demo,
    evaluate,
    init,
    interpolate,
    plan,
    run,
    simulate,
)
from rtsgt.cli.entry import EXIT_INTERRUPTED, INTERRUPTED_LINE
from rtsgt.cli.entry import main as entry_main
from rtsgt.errors import RtsgtError

#: Exit statuses (see the module docstring; :data:`EXIT_INTERRUPTED` is the entry point's).
EXIT_INPUT, EXIT_USAGE, EXIT_BUG = 1, 2, 3

# click's exception classes, from typer's own public exception (typer vendors click)
_USAGE_ERROR = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")
_CLICK_EXCEPTION = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings of the library as one ``warning: ...`` line, without a source excerpt."""
    typer.echo(f"warning: {_one_line(message)}", err=True)


class _Group(TyperGroup):
    """typer's command group with rtsgt's rule for errors, exit statuses and warnings."""

    def main(self, args: Sequence[str] | None = None, prog_name: str | None = None,
             complete_var: str | None = None, standalone_mode: bool = True,
             **extra: Any) -> Any:
        shown = warnings.showwarning
        warnings.showwarning = _show_warning
        try:
            status = self._run(args, prog_name, complete_var, **extra)
        finally:
            warnings.showwarning = shown
        if standalone_mode:
            sys.exit(status)
        return status

    def _run(self, args, prog_name, complete_var, **extra) -> int:
        try:
            rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except _USAGE_ERROR as exc:
            if exc.ctx is not None and type(exc).__name__ == "NoArgsIsHelpError":
                typer.echo(exc.ctx.get_help(), err=True)
                return EXIT_USAGE
            where = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
            typer.echo(f"error: {_one_line(exc.format_message())}{where}", err=True)
            return EXIT_USAGE
        except RtsgtError as exc:
            typer.echo(f"error: {_one_line(exc)}", err=True)
            return EXIT_INPUT
        except _CLICK_EXCEPTION as exc:
            typer.echo(f"error: {_one_line(exc.format_message())}", err=True)
            return exc.exit_code
        except (KeyboardInterrupt, typer.Abort):
            typer.echo(INTERRUPTED_LINE, err=True)
            return EXIT_INTERRUPTED
        except Exception as exc:
            if os.environ.get("RTSGT_TRACEBACK"):
                raise
            typer.echo(f"error: unexpected {type(exc).__name__} inside rtsgt: "
                       f"{_one_line(exc)} (a bug: please report it; RTSGT_TRACEBACK=1 shows "
                       "the traceback)", err=True)
            return EXIT_BUG
        # typer returns the status of typer.Exit (and None, or a command's value, otherwise);
        # it turns an interrupt into Exit(130) and says nothing: say it
        if rv == EXIT_INTERRUPTED:
            typer.echo(INTERRUPTED_LINE, err=True)
        return rv if isinstance(rv, int) and not isinstance(rv, bool) else 0


app = typer.Typer(
    name="rtsgt",
    cls=_Group,
    help="Robotic total station ground truth: 6-DOF trajectories with honest covariances.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
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


for _command in (init, calibrate, interpolate, simulate, run, batch, demo, evaluate, analyze,
                 plan):
    _command.register(app)


def main() -> None:  # pragma: no cover - console entry point
    """The console entry point (:func:`rtsgt.cli.entry.main`, which imports this module inside
    its handling of interrupts)."""
    entry_main()
