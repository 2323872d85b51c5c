"""``rtsgt init FOLDER``: the deployment TOML of an RTS_project-like folder, as it is
(:mod:`rtsgt.io.project_folder`), written atomically when nothing required is missing.
"""

from __future__ import annotations

import os
from pathlib import Path

import typer

from rtsgt.errors import InputError
from rtsgt.io.output_dir import check_output_file


def run_init(folder: Path, *, out: Path | None = None, force: bool = False,
             weather: Path | None = None, utc_offset: float | None = None,
             measurements: str = "auto", name: str | None = None,
             echo=typer.echo) -> Path:
    """Scan ``folder``, say what is there and what is missing (``echo``), write its deployment
    TOML (replacing only one ``rtsgt init`` wrote, with ``force``); returns its path."""
    from rtsgt.io._parse import atomic_write_text
    from rtsgt.io.config import load_config
    from rtsgt.io.deployment import DEPLOYMENT_TOML
    from rtsgt.io.project_folder import deployment_toml_text, is_init_toml, scan_folder

    toml = Path(folder) / DEPLOYMENT_TOML if out is None else Path(out)
    if toml.exists() and not force:
        raise InputError("exists; use --force to replace a TOML that rtsgt init wrote, or give "
                         "another file with --out", toml)
    if toml.exists():
        check_output_file(toml, option="--out", written_by_rtsgt=is_init_toml)
    elif not toml.parent.is_dir() and Path(folder).is_dir():
        raise InputError(f"cannot write: the directory {toml.parent} does not exist", toml)
    scan = scan_folder(folder, weather=weather, measurements=measurements)
    for line in scan.found:
        echo(f"found: {line}")
    for line in scan.notes:
        echo(f"note: {line}")
    for line in scan.missing:
        echo(f"missing: {line}")
    if scan.required_missing:
        raise InputError(f"not written: {scan.required_missing} required input(s) missing "
                         "(the 'missing:' lines above)", toml)
    text = deployment_toml_text(scan, toml, name=name, utc_offset_hours=utc_offset)
    try:
        atomic_write_text(toml, text)
    except OSError as exc:
        raise InputError(f"cannot write: {exc.strerror or exc}", toml) from exc
    load_config(toml)  # what was written reads back (every file it names is there)
    echo(f"wrote: {toml}")
    echo(f"next: rtsgt run {_shell_path(toml)}")
    return toml


def _shell_path(p: Path) -> str:
    s = os.fspath(p)
    return s if all(c.isalnum() or c in "/._-+:@" for c in s) else "'" + s.replace("'", "'\\''") + "'"


def register(app: typer.Typer) -> None:
    """Add ``rtsgt init`` to the application."""

    @app.command("init")
    def init_command(
        folder: Path = typer.Argument(..., metavar="FOLDER",
                                      help="A deployment folder laid out like the RTS_project's "
                                           "data/<date>/ (or a flat folder of its files)."),
        out: Path = typer.Option(None, "--out", "-o",
                                 help="The TOML to write (default: FOLDER/deployment.toml)."),
        force: bool = typer.Option(False, "--force",
                                   help="Replace the TOML if rtsgt init wrote it (never another "
                                        "file)."),
        weather: Path = typer.Option(None, "--weather",
                                     help="The weather file (ECCC hourly CSV or rtsgt weather "
                                          "CSV; default: the one found under FOLDER)."),
        utc_offset: float = typer.Option(None, "--utc-offset", min=-14.0, max=14.0,
                                         help="Offset of an ECCC file's local standard time "
                                              "from UTC, h (default -5, Quebec's)."),
        measurements: str = typer.Option(
            "auto", "--measurements",
            help="The stations' measurements: auto (the raw bag if there is one, else the "
                 "prism files), bag, or prisms."),
        name: str = typer.Option(None, "--name", help="Deployment name (default: FOLDER's "
                                                       "name)."),
    ) -> None:
        """Write the deployment TOML of an RTS_project-like folder, saying what is missing."""
        from rtsgt.io.project_folder import MEASUREMENT_CHOICES

        if measurements not in MEASUREMENT_CHOICES:
            raise typer.BadParameter(f"expected one of {', '.join(MEASUREMENT_CHOICES)}, got "
                                     f"{measurements!r}", param_hint="--measurements")
        run_init(folder, out=out, force=force, weather=weather, utc_offset=utc_offset,
                 measurements=measurements, name=name)
