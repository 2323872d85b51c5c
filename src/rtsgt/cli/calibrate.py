"""``rtsgt calibrate``: extrinsic calibration of the stations (docs/calibration.md).

From a GCP file (or ``example``, the packaged one) by :func:`rtsgt.calibration.calibrate`; from
a deployment's TOML or folder as its run calibrates (:func:`rtsgt.pipeline.calibrate_by_method`;
``--method`` or ``--dynamic``). ``--out`` writes the JSON atomically.
"""

from __future__ import annotations

import json
import warnings
from contextlib import ExitStack
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from rtsgt.choices import CALIBRATION_METHODS, DEFAULT_WEIGHTING, GCP_FORMATS
from rtsgt.errors import InputError
from rtsgt.io.output_dir import check_output_file

if TYPE_CHECKING:
    from rich.console import Console

    from rtsgt.calibration import CalibrationResult

#: Name of the packaged example GCP file (in ``rtsgt/data``).
EXAMPLE_GCP = "example_gcp.txt"

_RAD_TO_MRAD = 1e3


def _station_id(s: str) -> int | str:
    return int(s) if s.isdigit() else s


def result_to_json(result: CalibrationResult, **extra) -> dict:
    """The JSON object of ``rtsgt calibrate --json`` (docs/file-formats.md#other-outputs); ``extra``
    adds keys (``dynamic``, ``gcp_fit``: :mod:`rtsgt.checks.calibration`)."""
    import numpy as np

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
        "method": result.method,
        **extra,
    }


def _print_table(result: CalibrationResult, source: str, console: Console,
                 dynamic: dict | None = None, gcp_fit: dict | None = None) -> None:
    import numpy as np

    from rtsgt.calibration.result import CALIBRATION_METHOD_NAMES, CALIBRATION_WEIGHTING_NAMES
    from rtsgt.cli.tables import TextTable

    table = TextTable(f"T_world_station, world = station {result.reference_station} ({source})",
                      ("station", "markers", "yaw (deg)", "axis", "t (m)", "1σ t (mm)",
                       "1σ rot (mrad)"), right=(False, True, True, False, True, True, True))
    for s, T in result.transforms.items():
        sig = None if T.covariance is None else np.sqrt(np.diag(T.covariance))
        for k, axis in enumerate("xyz"):
            first = k == 0
            table.add_row(
                s if first else "",
                (str(len(result.markers_used[s])) if result.markers_used.get(s) else "-")
                if first else "",
                f"{np.degrees(T.yaw):.4f}" if first else "",
                axis,
                f"{T.translation[k]:.4f}",
                "-" if sig is None else f"{sig[k] * 1e3:.2f}",
                "-" if sig is None else f"{sig[3 + k] * _RAD_TO_MRAD:.3g}",
            )
        table.add_section()
    table.print(console)
    res = result.residuals
    if len(res):
        worst = int(np.argmax(res.distance_m))
        console.print(
            f"GCP residuals between stations: {len(res)}, median {res.median_m * 1e3:.2f} mm, "
            f"max {res.max_m * 1e3:.2f} mm (marker {res.marker[worst]}, stations "
            f"{res.station_a[worst]}-{res.station_b[worst]})")
    console.print(f"calibrated from {CALIBRATION_METHOD_NAMES[result.method]}, model "
                  f"{result.model}")
    if dynamic is not None:
        clocks = ", ".join(f"station {s} {v:+.2f} +- {dynamic['clock_sigma_ms'][s]:.2f} ms"
                           for s, v in dynamic["clock_offset_ms"].items())
        lo, hi = dynamic["interval_95"]
        console.print(f"clock offsets against station {result.reference_station}: {clocks}")
        console.print(f"inter-prism distances: {dynamic['samples']} samples, variance factor "
                      f"{dynamic['variance_factor']:.2f}, 95 % [{lo:.2f}, {hi:.2f}]: "
                      f"{dynamic['verdict']}")
        for s, v in dynamic.get("gcp_agreement", {}).items():
            console.print(f"station {s} against the GCP calibration: chi2 {v['chi2']:.1f} "
                          f"({v['dof']} dof, p = {v['p_value']:.2g}): {v['verdict']}")
    if gcp_fit is not None:
        _print_gcp_fit(gcp_fit, console)
    sampled = f"{result.samples} Monte Carlo samples" if result.samples else "no Monte Carlo"
    console.print(f"{sampled}; {CALIBRATION_WEIGHTING_NAMES[result.weighting]} fits.")
    if result.excluded_shots:
        console.print(f"note: {result.excluded_shots} shot(s) with non-zero status excluded")
    if result.markers_skipped:
        console.print(f"note: marker(s) {', '.join(result.markers_skipped)} shot by fewer than 2 "
                      "stations were skipped")


def _print_gcp_fit(check: dict, console: Console) -> None:
    """The GCP fit's self-check (:func:`rtsgt.checks.calibration.gcp_fit_check`)."""
    for s, v in check.get("stations", {}).items():
        if not v.get("dof"):
            continue
        lo, hi = v["interval_95"]
        x, y, z = v["axis_factors_xyz"]
        console.print(f"self-check GCP fit, station {s}: variance factor "
                      f"{v['variance_factor']:.2f}, 95 % [{lo:.2f}, {hi:.2f}]: {v['verdict']} "
                      f"({v['dof']} dof; per axis x {x:.2f}, y {y:.2f}, z {z:.2f})",
                      highlight=False)
    h, v = (check["added_shot_sigma_mm"][k] for k in ("horizontal", "vertical"))
    console.print(f"calibration: added per shot {h:.2f} mm horizontal, {v:.2f} mm vertical "
                  "(variance components of the GCP residuals)" if h or v else
                  "calibration: no variance component added per shot", highlight=False)


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
    import numpy as np

    from rtsgt.calibration import calibrate
    from rtsgt.io.gcp_csv import read_gcp_shots
    from rtsgt.measurement.instruments import get_instrument

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
            result = calibrate(shots, reference_station=reference_station, instrument=profile,
                               samples=samples, rng=np.random.default_rng(seed),
                               weighting=weighting, model=model)
    return result, source


def run_calibrate_deployment(
    config: Path, *, method: str | None = None, model: str | None = None,
    weighting: str | None = None, samples: int = 1000, seed: int = 0,
) -> tuple[CalibrationResult, dict | None, CalibrationResult | None]:
    """Calibrate a deployment's stations as its run would (``method``, ``model``,
    ``weighting`` over its ``[calibration]``); returns the result, the dynamic self-check
    (None for ``gcp``) and the GCP calibration (None when the GCPs cannot calibrate)."""
    from rtsgt.checks.calibration import dynamic_calibration_check
    from rtsgt.filtering import module1
    from rtsgt.io.deployment import load_deployment
    from rtsgt.pipeline import calibrate_by_method

    data, options = load_deployment(config)
    changes = {k: v for k, v in (("method", method), ("model", model),
                                 ("weighting", weighting)) if v is not None}
    options = options.updated(seed=seed, samples=samples, **changes)
    filtered = []
    for obs in data.observations:
        kept = module1(obs, options.filter)[0]
        if len(kept) < 2:
            raise InputError(f"station {obs.station}: fewer than 2 measurements left after "
                             "module 1", obs.source)
        filtered.append(kept)
    result, gcp = calibrate_by_method(data, options, filtered)
    check = None if result.dynamic is None else dynamic_calibration_check(result, gcp, warn=False)
    return result, check, result if result.dynamic is None else gcp


def is_calibration_json(head: str) -> bool:
    """Whether a file's first characters are those of ``rtsgt calibrate``'s JSON object."""
    return head.lstrip().startswith("{") and all(
        f'"{k}"' in head for k in ("reference_station", "stations", "residuals_mm"))


def _checked_method(gcp_file: str, method: str | None, dynamic: bool,
                    samples: int) -> tuple[str | None, bool]:
    """``--method`` (``--dynamic``: ``dynamic``) and whether ``GCP_FILE`` is a deployment's,
    checked as usage errors with ``--samples``."""
    if samples == 1:
        raise typer.BadParameter("use 0 (fit only) or at least 2", param_hint="--samples")
    if dynamic:
        if method not in (None, "dynamic"):
            raise typer.BadParameter(f"--dynamic with --method {method}: give one",
                                     param_hint="--dynamic")
        method = "dynamic"
    if method is not None and method not in CALIBRATION_METHODS:
        raise typer.BadParameter(f"expected {' or '.join(CALIBRATION_METHODS)}, got "
                                 f"{method!r}", param_hint="--method")
    deployment = gcp_file.lower().endswith(".toml") or Path(gcp_file).is_dir()
    if not deployment and method not in (None, "gcp"):
        raise typer.BadParameter(
            f"method {method} fits the stations to the tracked prisms: give a deployment's "
            "TOML (its tracks and the survey of the prisms), not a GCP file",
            param_hint="GCP_FILE")
    return method, deployment


def register(app: typer.Typer) -> None:
    """Add ``rtsgt calibrate`` to the application."""

    @app.command("calibrate")
    def calibrate_command(
        gcp_file: str = typer.Argument(
            ..., metavar="GCP_FILE",
            help="GCP shots file, `example` for the small example shipped with rtsgt, or a "
            "deployment's TOML (the calibration of its run: its [calibration], or --method)."),
        format: str = typer.Option(
            "auto", "--format",
            help=f"File format: {' | '.join(GCP_FORMATS)} (auto: RTS_project if its header "
            "line is there, else the native CSV)."),
        reference_station: str = typer.Option("1", "--reference-station",
                                              help="Station whose frame is the world frame."),
        additive_constant: float | None = typer.Option(
            None, "--additive-constant",
            help="Additive (prism) constant in m added to every distance "
            "(default: 0.01 for rts-project files, 0 for csv)."),
        samples: int = typer.Option(1000, "--samples", min=0,
                                    help="Monte Carlo samples (0: fit only)."),
        seed: int = typer.Option(0, "--seed", min=0, help="Seed of the random generator (>= 0)."),
        weighting: str | None = typer.Option(
            None, "--weighting",
            help="Markers' weights: gls (the full covariance of each shot), trace (its "
            f"trace) or none (the paper). Default: {DEFAULT_WEIGHTING}, or the TOML's."),
        instrument: str = typer.Option("trimble-s7", "--instrument",
                                       help="Instrument profile for the noise model."),
        model: str | None = typer.Option(
            None, "--model",
            help="Each station's transform: 6dof (free rotation) or 4dof (levelled stations: "
            "yaw only, the tilt that of the Earth's curvature). Default: 6dof, or the TOML's."),
        method: str | None = typer.Option(
            None, "--method",
            help=f"What to fit the stations to: {' | '.join(CALIBRATION_METHODS)} (the GCPs, "
            "the robot's motion through the inter-prism distances, or both; dynamic and "
            "joint need a deployment's TOML). Default: gcp, or the TOML's."),
        dynamic: bool = typer.Option(False, "--dynamic",
                                     help="The same as --method dynamic (a deployment's TOML)."),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        out: Path | None = typer.Option(
            None, "--out", "-o",
            help="Also write the JSON object to this file (atomically: complete or absent)."),
    ) -> None:
        """Calibrate every station into the reference station's frame from GCP shots."""
        from rich.console import Console

        from rtsgt.checks.calibration import gcp_fit_check
        from rtsgt.io._parse import atomic_write_text
        from rtsgt.io.deployment import resolve_config

        method, deployment = _checked_method(gcp_file, method, dynamic, samples)
        if out is not None:
            check_output_file(out, option="--out", written_by_rtsgt=is_calibration_json)
        check = None
        if deployment:
            config = resolve_config(gcp_file)
            result, check, gcp_result = run_calibrate_deployment(
                config, method=method, model=model, weighting=weighting, samples=samples,
                seed=seed)
            source = str(config)
        else:
            result, source = run_calibrate(gcp_file, format=format,
                                           reference_station=reference_station,
                                           additive_constant=additive_constant, samples=samples,
                                           seed=seed, weighting=weighting or DEFAULT_WEIGHTING,
                                           instrument=instrument, model=model or "6dof")
            gcp_result = result
        extra = {} if check is None else {"dynamic": check}
        gcp_fit = None if gcp_result is None else gcp_fit_check(gcp_result, warn=False)
        if gcp_fit is not None:
            extra["gcp_fit"] = gcp_fit
        obj = result_to_json(result, source=source, seed=seed, **extra)
        if out is not None:
            try:
                atomic_write_text(out, json.dumps(obj) + "\n")
            except OSError as exc:
                raise InputError(f"cannot write: {exc.strerror or exc}", out) from exc
        if as_json:
            typer.echo(json.dumps(obj))
        else:
            _print_table(result, source, Console(), check, gcp_fit)
            if out is not None:
                Console().print(f"written: {out}")
