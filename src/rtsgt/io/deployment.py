"""Read every file a deployment configuration names into a :class:`DeploymentData`."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from rtsgt.deployment import DeploymentData
from rtsgt.errors import ConfigError, InputError, RtsgtWarning
from rtsgt.geometry import RigidTransform
from rtsgt.io._parse import check_seconds
from rtsgt.io.config import DeploymentConfig, load_config
from rtsgt.io.gcp_csv import read_gcp_shots
from rtsgt.io.rts_bag import InputReport, read_theodolite_bag
from rtsgt.io.rts_project import read_prism_file
from rtsgt.io.survey import (
    SensorPositions,
    read_reference_csv,
    read_sensor_positions,
    read_survey_raw,
)
from rtsgt.io.weather import read_weather_csv, read_weather_eccc
from rtsgt.options import RunOptions
from rtsgt.pose.reference import ReferencePoints, reference_from_survey
from rtsgt.record import MIN_POSE_PRISMS
from rtsgt.types import Observations

#: The file name of a deployment's configuration in its folder (``rtsgt init`` and
#: ``rtsgt simulate`` write it there; a command given the folder reads it).
DEPLOYMENT_TOML = "deployment.toml"


def resolve_config(path: str | Path) -> Path:
    """The deployment configuration a command was given: ``path`` itself, or, for a folder,
    its :data:`DEPLOYMENT_TOML`.

    Raises
    ------
    InputError
        ``path`` is a folder without a :data:`DEPLOYMENT_TOML` (one line naming the folder and
        what to do). A missing file is left to :func:`rtsgt.io.config.load_config`, which
        names it.
    """
    path = Path(path)
    if not path.is_dir():
        return path
    toml = path / DEPLOYMENT_TOML
    if toml.is_file():
        return toml
    raise InputError(f"a folder without {DEPLOYMENT_TOML}: give the deployment's TOML, or "
                     "write one with `rtsgt init FOLDER` (an RTS_project-like folder)", path)


def check_gcp_covers_stations(cfg: DeploymentConfig, gcp) -> None:
    """Every tracked station needs valid GCP shots for its calibration: refuse early.

    Raises
    ------
    ConfigError
        Naming the station, the GCP file and the stations it has.
    """
    valid = {str(s) for s, st in zip(gcp.station, gcp.status, strict=True) if st == 0}
    missing = [s.id for s in cfg.stations if s.id not in valid]
    if missing:
        raise ConfigError(
            f"[[stations]] {', '.join(repr(m) for m in missing)}: no valid shot in the GCP "
            f"file {cfg.gcp.file} (stations there: {', '.join(sorted(valid)) or 'none'}); "
            "every tracked station needs GCP shots for its calibration: check the station "
            "ids or the GCP file",
            cfg.path,
        )


def read_reference(cfg: DeploymentConfig) -> ReferencePoints:
    """Reference prisms in the body frame, from the survey file named by the configuration."""

    rc = cfg.reference
    names = list(rc.prisms)
    if rc.format == "csv":
        ref = read_reference_csv(rc.file)
        missing = [n for n in names if n not in ref.names]
        if missing:
            raise InputError(f"no reference point named {', '.join(missing)}", rc.file)
        return replace(ref.select(names), pivot=rc.rocking_pivot,
                       stability=1e-3 * rc.prism_stability_mm)
    survey = (read_sensor_positions(rc.file) if rc.format == "sensor-positions"
              else read_survey_raw(rc.file))
    n_rows = survey.xyz.shape[0]
    rows = [rc.prisms[n] - 1 for n in names]
    for n, r in zip(names, rows, strict=True):
        if r >= n_rows:
            raise ConfigError(
                f"[reference] prisms.{n} = {r + 1}: the survey {rc.file.name} has {n_rows} rows",
                cfg.path,
            )
    if isinstance(survey, SensorPositions):
        used = rows + ([r - 1 for r in rc.body_points] if rc.body_frame == "points" else [])
        _warn_sensor_position_defects(survey, sorted(set(used)))
    if rc.body_frame == "survey":
        body = "survey"
    elif rc.body_frame == "points":
        body = [r - 1 for r in rc.body_points]
    else:
        body = RigidTransform.from_matrix(np.array(rc.T_survey_body), frame_to="survey",
                                          frame_from="body")
    return replace(reference_from_survey(survey.xyz, survey.cov, rows, body_frame=body,
                                         names=names, pivot=rc.rocking_pivot),
                   stability=1e-3 * rc.prism_stability_mm)


def _warn_sensor_position_defects(points: SensorPositions, rows: list[int]) -> None:
    """Warn, naming the file and line, for each row the reference uses (0-based ``rows``) whose
    covariance is zero (the survey's uncertainty is then missing from the poses) or whose flag
    is not 1 (its ``x y z`` are used as written)."""
    for r in rows:
        where = f"{points.source}:{int(points.lines[r])}"
        if not np.any(points.cov[r]):
            warnings.warn(f"{where}: zero covariance for {points.names[r]}, which the "
                          "reference uses: the survey's uncertainty of this point is missing "
                          "from the poses' covariance", RtsgtWarning, stacklevel=3)
        if points.flag[r] != 1.0:
            warnings.warn(f"{where}: flag {points.flag[r]:g} for {points.names[r]}, where the "
                          "file has 1 (the homogeneous coordinate); its x y z are used as "
                          "written", RtsgtWarning, stacklevel=3)


def load_deployment(config: str | Path | DeploymentConfig) -> tuple[DeploymentData, RunOptions]:
    """Read a deployment: its configuration (a TOML, or a folder holding
    :data:`DEPLOYMENT_TOML`: :func:`resolve_config`), then every file it names.

    Returns
    -------
    data : DeploymentData
    options : RunOptions
        The processing parameters of the configuration (the CLI may override some).
    """
    cfg = config if isinstance(config, DeploymentConfig) else load_config(resolve_config(config))
    observations, input_report = read_observations(cfg)
    gcp = read_gcp_shots(cfg.gcp.file, format=cfg.gcp.format,
                         additive_constant=cfg.gcp.additive_constant_m)
    check_gcp_covers_stations(cfg, gcp)
    weather = None
    if cfg.weather is not None:
        if cfg.weather.format == "eccc":
            weather = read_weather_eccc(cfg.weather.file, utc_offset_hours=cfg.weather.utc_offset_hours)
        else:
            weather = read_weather_csv(cfg.weather.file)
    # a run with fewer than 3 tracked prisms gives positions only: no pose, no reference
    reference = read_reference(cfg) if len(cfg.stations) >= MIN_POSE_PRISMS else None
    query_times = None
    if cfg.query_times is not None:
        query_times = _read_times(cfg.query_times)
    data = DeploymentData(cfg.name, cfg.instrument, observations, gcp, reference,
                          cfg.reference_station, weather, query_times, input_report)
    return data, cfg.options


def read_observations(cfg: DeploymentConfig) -> tuple[tuple[Observations, ...],
                                                      InputReport | None]:
    """Every station's observations: from its prism file, or from the bag of
    ``[measurements]`` (:mod:`rtsgt.io.rts_bag`) with the reader's report of what it removed
    (None for prism files, which hold valid measurements only)."""
    m = cfg.measurements
    if m is None:
        return tuple(
            read_prism_file(s.file, station=s.id, prism=s.prism,
                            additive_constant=s.additive_constant_m)
            for s in cfg.stations), None
    bag = read_theodolite_bag(m.file, topic=m.topic, time=m.time,
                              correction_topic=m.correction_topic)
    observations = tuple(
        bag.station(s.theodolite_id, station=s.id, prism=s.prism,
                    additive_constant=s.additive_constant_m)
        for s in cfg.stations)
    return observations, bag.report({s.id: s.theodolite_id for s in cfg.stations})


def _read_times(path: Path) -> np.ndarray:
    """One time (s) per line; ``#`` comments and blank lines allowed."""
    values, numbers = [], []
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        try:
            v = float(s.split()[0].split(",")[0])
        except ValueError:
            raise InputError(f"expected a time in seconds, got {s!r}", path, i) from None
        if not np.isfinite(v):
            raise InputError(f"expected a finite time, got {s!r}", path, i)
        values.append(v)
        numbers.append(i)
    if not values:
        raise InputError("no query time in the file", path)
    check_seconds(np.array(values), numbers, path)
    return np.sort(np.array(values))
