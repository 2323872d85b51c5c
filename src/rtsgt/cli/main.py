"""The ``rtsgt`` command line: the application, its exit statuses and its style of help.

Each command module registers itself through ``register(app)``; its top level holds only the
typer declaration and imports light modules (start-up, exit statuses and help style:
docs/cli.md#rules-every-command-keeps).
"""

from __future__ import annotations

import os
import sys
import warnings
from collections.abc import Sequence
from typing import Any, get_args, get_origin

import typer
from typer.core import TyperCommand, TyperGroup

from rtsgt import __version__
from rtsgt.choices import EXIT_INTERRUPTED, INTERRUPTED_LINE
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
from rtsgt.errors import RtsgtError

#: Exit statuses (docs/cli.md#errors-warnings-and-exit-statuses).
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


#: The word for the value of an option or argument whose declaration names none, by type.
TYPE_WORDS = {"Path": "PATH", "int": "INTEGER", "float": "NUMBER", "str": "TEXT"}


def _type_word(param) -> str:
    """The upper-case word for the values of a typer parameter, from its annotation."""
    annotation = param.type_descriptor.annotation
    if get_origin(annotation) in (list, tuple) and get_args(annotation):
        annotation = get_args(annotation)[0]
    return TYPE_WORDS.get(getattr(annotation, "__name__", ""), "VALUE")


class _Command(TyperCommand):
    """typer's command with rtsgt's style of help (``CONFIG``, ``--engine TEXT``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        for param in self.params:
            if param.metavar is not None:
                continue
            if param.param_type_name == "argument":
                param.metavar = param.name.upper()
            elif not (getattr(param, "is_flag", False) or getattr(param, "count", False)):
                param.metavar = _type_word(param)

    @staticmethod
    def _argument_name(param) -> str:
        name = param.metavar
        return name + "..." if param.nargs != 1 and not name.endswith("...") else name

    def collect_usage_pieces(self, ctx) -> list[str]:
        pieces = [self.options_metavar] if self.options_metavar else []
        for param in self.get_params(ctx):
            if param.param_type_name == "argument":
                name = self._argument_name(param)
                pieces.append(name if param.required else f"[{name}]")
            else:
                pieces.extend(param.get_usage_pieces(ctx))
        return pieces

    def format_options(self, ctx, formatter) -> None:
        arguments, options = [], []
        for param in self.get_params(ctx):
            record = param.get_help_record(ctx)
            if record is None:
                continue
            if param.param_type_name == "argument":
                arguments.append((self._argument_name(param), record[1]))
            else:
                options.append(record)
        for title, rows in (("Arguments", arguments), ("Options", options)):
            if rows:
                with formatter.section(title):
                    formatter.write_dl(rows)


app = typer.Typer(
    name="rtsgt", cls=_Group,
    help="Robotic total station ground truth: 6-DOF trajectories with honest covariances.",
    no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
    rich_markup_mode=None)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"rtsgt {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="Print the version."),
) -> None:
    """Robotic total station ground truth."""


for _command in (init, calibrate, interpolate, simulate, run, batch, demo, evaluate, analyze,
                 plan):
    _command.register(app)
for _info in app.registered_commands:  # every command in rtsgt's style of help
    if _info.cls in (None, TyperCommand):
        _info.cls = _Command

