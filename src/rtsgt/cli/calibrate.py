"""``rtsgt calibrate``: extrinsic calibration of the stations from GCP shots.

A thin wrapper over :func:`rtsgt.io.gcp_csv.read_gcp_shots` and
:func:`rtsgt.calibration.calibrate`. ``GCP_FILE`` may be the word ``example`` for the small
synthetic example shipped in the package (three stations, eight markers). ``--out FILE``
writes the JSON object to a file, atomically (complete or not at all: a failed run leaves no
file and keeps a previous one), which a shell redirection of ``--json`` cannot promise.
"""

from __future__ import annotations

import json
import warnings
from contextlib import ExitStack
from importlib import resources
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from rtsgt.calibration import CalibrationResult, calibrate
from rtsgt.calibration.gcp import CALIBRATION_WEIGHTING_NAMES, DEFAULT_WEIGHTING
from rtsgt.errors import InputError
from rtsgt.io._parse import atomic_write_text
from rtsgt.io.gcp_csv import GCP_FORMATS, read_gcp_shots
from rtsgt.io.output_dir import check_output_file
from rtsgt.measurement.instruments import get_instrument

#: Name of the packaged example GCP file (in ``rtsgt/data``).
EXAMPLE_GCP = "example_gcp.txt"

_RAD_TO_MRAD = 1e3


def _station_id(s: str) -> int | str:
    return int(s) if s.isdigit() else s


def result_to_json(result: CalibrationResult, **extra) -> dict:
    """The JSON object printed by ``rtsgt calibrate --json``.

    ``stations`` holds every station except the reference (whose transform is the identity):
    ``matrix`` (4x4 ``T_world_station``), ``yaw_deg``, ``translation_m``, ``covariance`` (6x6,
    x, y, z, rx, ry, rz, m^2 / rad^2, left perturbation in the world frame; null without
    samples), the 1-sigma values in mm and mrad, and the markers used.
    """
    stations = {}
    for s, T in result.transforms.items():
        if s == result.reference_station:
            continue
        entry = {
            "matrix": T.as_matrix().tolist(),
            "yaw_deg": float(np.degrees(T.yaw)),
            "translation_m": T.translation.tolist(),
            "covariance": None if T.covariance is None else T.covariance.tolist(),
        }
        if T.covariance is not None:
            sig = np.sqrt(np.diag(T.covariance))
            entry["sigma_translation_mm"] = (sig[:3] * 1e3).tolist()
            entry["sigma_rotation_mrad"] = (sig[3:] * _RAD_TO_MRAD).tolist()
        entry["markers_used"] = list(result.markers_used[s])
        stations[s] = entry
    res = result.residuals
    return {
        "reference_station": _station_id(result.reference_station),
        "stations": stations,
        "residuals_mm": {
            "median": res.median_m * 1e3 if len(res) else None,
            "max": res.max_m * 1e3 if len(res) else None,
            "count": len(res),
        },
        "residuals": [
            {"marker": m, "station_a": a, "station_b": b, "distance_mm": float(x * 1e3)}
            for m, a, b, x in zip(res.marker, res.station_a, res.station_b, res.distance_m,
                                  strict=True)
        ],
        "markers_skipped": list(result.markers_skipped),
        "excluded_shots": result.excluded_shots,
        "samples": result.samples,
        "weighting": result.weighting,
        "model": result.model,
        **extra,
    }


def _print_table(result: CalibrationResult, source: str, console: Console) -> None:
    table = Table(title=f"T_world_station, world = station {result.reference_station} ({source})")
    for name, justify in (
        ("station", "left"), ("markers", "right"), ("yaw (deg)", "right"), ("axis", "center"),
        ("t (m)", "right"), ("1σ t (mm)", "right"), ("1σ rot (mrad)", "right"),
    ):
        table.add_column(name, justify=justify)
    for s, T in result.transforms.items():
        sig = None if T.covariance is None else np.sqrt(np.diag(T.covariance))
        for k, axis in enumerate("xyz"):
            first = k == 0
            table.add_row(
                s if first else "",
                str(len(result.markers_used[s])) if first else "",
                f"{np.degrees(T.yaw):.4f}" if first else "",
                axis,
                f"{T.translation[k]:.4f}",
                "-" if sig is None else f"{sig[k] * 1e3:.2f}",
                "-" if sig is None else f"{sig[3 + k] * _RAD_TO_MRAD:.3g}",
            )
        table.add_section()
    console.print(table)
    res = result.residuals
    if len(res):
        worst = int(np.argmax(res.distance_m))
        console.print(
            f"GCP residuals between stations: {len(res)}, median {res.median_m * 1e3:.2f} mm, "
            f"max {res.max_m * 1e3:.2f} mm (marker {res.marker[worst]}, stations "
            f"{res.station_a[worst]}-{res.station_b[worst]})"
        )
    sampled = f"{result.samples} Monte Carlo samples" if result.samples else "no Monte Carlo"
    console.print(f"{sampled}; {CALIBRATION_WEIGHTING_NAMES[result.weighting]} fits.")
    if result.excluded_shots:
        console.print(f"note: {result.excluded_shots} shot(s) with non-zero status excluded")
    if result.markers_skipped:
        console.print(
            f"note: marker(s) {', '.join(result.markers_skipped)} shot by fewer than 2 "
            "stations were skipped"
        )


def run_calibrate(
    gcp_file: str,
    *,
    format: str = "auto",
    reference_station: str = "1",
    additive_constant: float | None = None,
    samples: int = 1000,
    seed: int = 0,
    weighting: str = DEFAULT_WEIGHTING,
    instrument: str = "trimble-s7",
    model: str = "6dof",
) -> tuple[CalibrationResult, str]:
    """Read the GCP file (or the packaged example) and calibrate; returns the result and source."""
    profile = get_instrument(instrument)
    with ExitStack() as stack:
        if gcp_file == "example":
            ref = resources.files("rtsgt").joinpath("data").joinpath(EXAMPLE_GCP)
            path = stack.enter_context(resources.as_file(ref))
            source = f"packaged example {EXAMPLE_GCP}"
        else:
            path = Path(gcp_file)
            source = str(path)
        shots = read_gcp_shots(path, format=format, additive_constant=additive_constant)
        with warnings.catch_warnings():
            # skipped markers are reported from the result, not as a Python warning
            warnings.simplefilter("ignore", UserWarning)
            result = calibrate(
                shots, reference_station=reference_station, instrument=profile,
                samples=samples, rng=np.random.default_rng(seed), weighting=weighting,
                model=model,
            )
    return result, source


def is_calibration_json(head: str) -> bool:
    """Whether a file's first characters are those of ``rtsgt calibrate``'s JSON object."""
    return head.lstrip().startswith("{") and all(
        f'"{k}"' in head for k in ("reference_station", "stations", "residuals_mm"))


def register(app: typer.Typer) -> None:
    """Add ``rtsgt calibrate`` to the application."""

    @app.command("calibrate")
    def calibrate_command(
        gcp_file: str = typer.Argument(
            ..., metavar="GCP_FILE",
            help="GCP shots file, or `example` for the small example shipped with rtsgt.",
        ),
        format: str = typer.Option(
            "auto", "--format",
            help=f"File format: {' | '.join(GCP_FORMATS)} (auto: RTS_project if its header "
            "line is there, else the native CSV).",
        ),
        reference_station: str = typer.Option(
            "1", "--reference-station", help="Station whose frame is the world frame."
        ),
        additive_constant: float | None = typer.Option(
            None, "--additive-constant",
            help="Additive (prism) constant in m added to every distance "
            "(default: 0.01 for rts-project files, 0 for csv).",
        ),
        samples: int = typer.Option(
            1000, "--samples", min=0, help="Monte Carlo samples (0: fit only)."
        ),
        seed: int = typer.Option(0, "--seed", min=0, help="Seed of the random generator (>= 0)."),
        weighting: str = typer.Option(
            DEFAULT_WEIGHTING, "--weighting",
            help="Markers' weights: gls (the full covariance of each shot), trace (its "
            "trace) or none (the paper).",
        ),
        instrument: str = typer.Option(
            "trimble-s7", "--instrument", help="Instrument profile for the noise model."
        ),
        model: str = typer.Option(
            "6dof", "--model",
            help="Each station's transform: 6dof (free rotation) or 4dof (levelled stations: "
            "yaw only, the tilt that of the Earth's curvature).",
        ),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        out: Path | None = typer.Option(
            None, "--out", "-o",
            help="Also write the JSON object to this file (atomically: complete or absent).",
        ),
    ) -> None:
        """Calibrate every station into the reference station's frame from GCP shots."""
        if samples == 1:
            raise typer.BadParameter("use 0 (fit only) or at least 2", param_hint="--samples")
        if out is not None:
            check_output_file(out, option="--out", written_by_rtsgt=is_calibration_json)
        result, source = run_calibrate(
            gcp_file, format=format, reference_station=reference_station,
            additive_constant=additive_constant, samples=samples, seed=seed,
            weighting=weighting, instrument=instrument, model=model,
        )
        obj = result_to_json(result, source=source, seed=seed)
        if out is not None:
            try:
                atomic_write_text(out, json.dumps(obj) + "\n")
            except OSError as exc:
                raise InputError(f"cannot write: {exc.strerror or exc}", out) from exc
        if as_json:
            typer.echo(json.dumps(obj))
        else:
            _print_table(result, source, Console())
            if out is not None:
                Console().print(f"written: {out}")
