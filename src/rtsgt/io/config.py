"""Deployment configuration (TOML): what files a deployment has and how to process them.

:func:`load_config` reads and checks every key (paths relative to the file, units in the key
names, unknown keys an error) into a :class:`DeploymentConfig`; :func:`options_toml_text`
writes the processing tables back. Schema and an example of every section:
docs/file-formats.md#deployment-toml.
"""

from __future__ import annotations

import json
import math
import re
import sys
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from rtsgt.errors import ConfigError, InputError
from rtsgt.filtering import FilterParams
from rtsgt.io.rts_bag import TIME_SOURCES
from rtsgt.measurement.instruments import InstrumentProfile, instrument_from_config
from rtsgt.noise import NoiseModel
from rtsgt.noise.sources import NOISE_SOURCES
from rtsgt.options import (
    PROFILES,
    CalibrationOptions,
    InterpolationOptions,
    PoseOptions,
    RunOptions,
)
from rtsgt.record import MIN_POSE_PRISMS

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

STATION_FORMATS = ("rts-project",)
MEASUREMENT_FORMATS = ("ros-bag",)
GCP_FORMATS = ("rts-project", "csv")
WEATHER_FORMATS = ("csv", "eccc")
REFERENCE_FORMATS = ("survey-dms", "sensor-positions", "csv")
BODY_FRAMES = ("survey", "points", "transform")


@dataclass(frozen=True)
class StationConfig:
    """One station and the prism it tracks."""

    id: str
    prism: str
    #: The tracked prism file; None when the measurements come from ``[measurements]``.
    file: Path | None
    format: str = "rts-project"
    additive_constant_m: float = 0.0
    #: With ``[measurements]``: the ``theodolite_id`` of this station's messages.
    theodolite_id: int | None = None


@dataclass(frozen=True)
class FileConfig:
    """A file with its format (GCP, weather, reference survey)."""

    file: Path
    format: str
    additive_constant_m: float = 0.0
    utc_offset_hours: float = 0.0


@dataclass(frozen=True)
class MeasurementsConfig:
    """Every station's measurements from one bag (``[measurements]``, :mod:`rtsgt.io.rts_bag`)."""

    file: Path
    format: str = "ros-bag"
    #: The measurements' topic (None: the reader's default).
    topic: str | None = None
    #: ``"header"`` or ``"theodolite"`` (None: the reader's default, ``"header"``).
    time: str | None = None
    #: The clock corrections' topic (None: the reader's default, beside the measurements').
    correction_topic: str | None = None


@dataclass(frozen=True)
class ReferenceConfig:
    """Where the reference prism positions on the robot come from, and the body frame."""

    file: Path
    format: str
    prisms: dict[str, int]
    body_frame: str = "survey"
    body_points: tuple[int, ...] = ()
    T_survey_body: tuple[tuple[float, ...], ...] | None = None
    #: ``rocking_pivot``: the point the vehicle rocks about (m; the survey's frame, the body
    #: frame's for a ``csv`` reference); None: not given (docs/joint.md#the-rockings-pivot).
    rocking_pivot: tuple[float, float, float] | None = None
    #: ``prism_stability_mm``: how far (1 sigma per axis, mm) a prism may have moved since
    #: its survey where no station can see it; 0: the survey is trusted there
    #: (docs/joint.md#what-no-station-sees).
    prism_stability_mm: float = 0.0


@dataclass(frozen=True)
class DeploymentConfig:
    """A validated deployment configuration; every path is absolute."""

    path: Path
    name: str
    reference_station: str
    instrument: InstrumentProfile
    stations: tuple[StationConfig, ...]
    gcp: FileConfig
    #: ``[reference]``: None for a deployment with fewer than 3 tracked prisms that has none
    #: (its run gives positions only, :class:`rtsgt.record.PositionRunRecord`).
    reference: ReferenceConfig | None
    weather: FileConfig | None = None
    #: ``[noise]``, ``[filter]``, ``[interpolation]`` and ``[pose]``, mapped onto the option
    #: records (their defaults where a key is absent).
    options: RunOptions = field(default_factory=RunOptions)
    #: ``[interpolation] query_times``: a file of query times (None: the grid of ``rate_hz``).
    query_times: Path | None = None
    #: ``[measurements]``: the stations' measurements from one bag (None: per-station files).
    measurements: MeasurementsConfig | None = None


class TomlSection:
    """Reads typed keys of one TOML table and rejects unknown keys with a clear message."""

    def __init__(self, path: Path, name: str, table: Any):
        if not isinstance(table, dict):
            raise ConfigError(f"[{name}] must be a table, got {type(table).__name__}", path)
        self.path, self.name, self.table, self.used = path, name, table, set()

    def get(self, key: str, kind: type | tuple, default: Any = ..., choices: tuple = ()) -> Any:
        self.used.add(key)
        if key not in self.table:
            if default is ...:
                raise ConfigError(f"[{self.name}] is missing the key {key!r}", self.path)
            return default
        val = self.table[key]
        if kind is float and isinstance(val, int) and not isinstance(val, bool):
            val = float(val)
        if kind is str and isinstance(val, int) and not isinstance(val, bool):
            val = str(val)
        if not isinstance(val, kind) or isinstance(val, bool) and kind is not bool:
            want = kind.__name__ if isinstance(kind, type) else " or ".join(k.__name__ for k in kind)
            raise ConfigError(f"[{self.name}] {key} must be {want}, got {val!r}", self.path)
        if choices and val not in choices:
            raise ConfigError(
                f"[{self.name}] {key} = {val!r} is not one of {', '.join(map(repr, choices))}",
                self.path,
            )
        return val

    def record(self, cls: type, spec: dict[str, tuple], **fixed) -> Any:
        """The record ``cls`` built from the keys of this table: ``spec`` maps each key to
        (field, type, conversion or None, ...); an absent key takes the record's default, and a
        value the record refuses is a :class:`ConfigError` naming the section."""
        values, given = dict(fixed), {}
        for key, (name, kind, convert, *_) in spec.items():
            value = self.get(key, kind, None)
            if value is not None:
                given[name] = (key, value)
                values[name] = convert(value) if convert is not None else value
        try:
            return cls(**values)
        except InputError as exc:
            msg = exc.bare_message
            msg = msg[0].lower() + msg[1:] if msg[:1].isupper() and msg[1:2].islower() else msg
            # name the key and the value as the file has them (units and all)
            culprit = [kv for name, kv in given.items() if re.search(rf"\b{name}\b", msg)]
            where = f"{culprit[0][0]} = {culprit[0][1]!r}: " if culprit else ""
            raise ConfigError(f"[{self.name}] {where}{msg}", self.path) from None

    def positive(self, key: str, default: Any = ...) -> float:
        val = self.get(key, float, default)
        if val is not None and not val > 0:
            raise ConfigError(f"[{self.name}] {key} must be > 0, got {val}", self.path)
        return val

    def file(self, key: str = "file", *, directory: bool = False) -> Path:
        """The path of ``key``, relative to the configuration; it must be a file (or, with
        ``directory``, a file or a directory)."""
        rel = self.get(key, str)
        p = (self.path.parent / rel).resolve()
        if not (p.is_file() or directory and p.is_dir()):
            raise ConfigError(f"[{self.name}] {key} = {rel!r}: no such file ({p})", self.path)
        return p

    def done(self) -> None:
        unknown = sorted(set(self.table) - self.used)
        if unknown:
            raise ConfigError(
                f"[{self.name}] has unknown key(s) {', '.join(unknown)}; "
                f"known: {', '.join(sorted(self.used))}",
                self.path,
            )


def load_config(path: str | Path) -> DeploymentConfig:
    """Read and validate a deployment configuration.

    Raises
    ------
    ConfigError
        Naming the file, the section and the key of any problem: a missing file, an unknown
        key, a wrong type, an unknown format, engine or noise source, duplicated stations, ...
    """
    path = Path(path).resolve()
    if not path.is_file():
        raise ConfigError("no such configuration file", path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"invalid TOML: {exc}", path) from None
    known = {"deployment", "instrument", "stations", "measurements", "gcp", "weather",
             "reference", "noise", "calibration", "filter", "interpolation", "pose"}
    unknown = sorted(set(doc) - known - {"profile"})
    if unknown:
        raise ConfigError(f"unknown section(s) {', '.join(unknown)}", path)
    _misplaced_profile(path, doc)

    dep = TomlSection(path, "deployment", doc.get("deployment", {}))
    name = dep.get("name", str, path.stem)
    reference_station = dep.get("reference_station", str, "1")
    dep.done()

    instrument = read_instrument(path, doc)

    measurements = None
    if "measurements" in doc:
        m = TomlSection(path, "measurements", doc["measurements"])
        measurements = MeasurementsConfig(
            m.file(directory=True), m.get("format", str, "ros-bag", MEASUREMENT_FORMATS),
            m.get("topic", str, None), m.get("time", str, None, TIME_SOURCES),
            m.get("correction_topic", str, None))
        m.done()

    raw_stations = doc.get("stations")
    if not isinstance(raw_stations, list) or not raw_stations:
        raise ConfigError("expected at least one [[stations]] table", path)
    stations = [_station(path, i, tab, measurements) for i, tab in enumerate(raw_stations)]
    ids = [s.id for s in stations]
    if len(set(ids)) != len(ids):
        raise ConfigError(f"duplicated station ids in [[stations]]: {ids}", path)
    tids = [s.theodolite_id for s in stations if s.theodolite_id is not None]
    if len(set(tids)) != len(tids):
        raise ConfigError(f"duplicated theodolite_id in [[stations]]: {tids}", path)
    if reference_station not in ids:
        raise ConfigError(
            f"[deployment] reference_station = {reference_station!r} is not a station; "
            f"known: {', '.join(ids)}",
            path,
        )
    prisms = [s.prism for s in stations]
    if len(set(prisms)) != len(prisms):
        raise ConfigError(f"each station must track a different prism, got {prisms}", path)

    g = TomlSection(path, "gcp", doc.get("gcp", None) if "gcp" in doc else _missing(path, "gcp"))
    gcp = FileConfig(g.file(), g.get("format", str, "rts-project", GCP_FORMATS),
                     g.get("additive_constant_m", float, 0.0))
    g.done()

    weather = None
    if "weather" in doc:
        w = TomlSection(path, "weather", doc["weather"])
        fmt = w.get("format", str, "csv", WEATHER_FORMATS)
        weather = FileConfig(w.file(), fmt, 0.0, w.get("utc_offset_hours", float, 0.0))
        w.done()

    # a pose needs three tracked prisms; with fewer the run gives positions only and the
    # survey of the robot (a pose's reference) is optional and not read
    positions_only = len(stations) < MIN_POSE_PRISMS
    reference = None
    if "reference" in doc or not positions_only:
        reference = _reference(path, doc, prisms, positions_only)
    options, query_times = read_options(path, doc, instrument)
    return DeploymentConfig(path, name, reference_station, instrument, tuple(stations), gcp,
                            reference, weather, options, query_times, measurements)


def read_instrument(path: Path, doc: dict) -> InstrumentProfile:
    """The ``[instrument]`` table of a configuration (default: the Trimble S7)."""
    table = doc.get("instrument", {"profile": "trimble-s7"})
    if not isinstance(table, dict):
        raise ConfigError("[instrument] must be a table", path)
    try:
        return instrument_from_config(table)
    except InputError as exc:
        raise ConfigError(f"[instrument] {exc.bare_message}", path) from None


#: The keys of the processing tables, one spec per table: TOML key -> (field of the option
#: record, type in the file, conversion of the file's value into the field's or None, and
#: back or None). :func:`read_options` reads the tables with them and
#: :func:`options_toml_text` writes them.
NOISE_KEYS = {"sources": ("sources", list, tuple, list)} | {
    k: (k, float, None, None) for k in ("time_sync_mean_s", "time_sync_std_s",
                                        "temperature_halfwidth_c", "pressure_halfwidth_hpa",
                                        "humidity_halfwidth_pct")}
#: The file's angular rates in deg/s, :class:`FilterParams`' in rad/s.
FILTER_KEYS = {
    "tau_r_m_s": ("tau_r", float, None, None),
    "tau_a_deg_s": ("tau_a", float, math.radians, math.degrees),
    "tau_e_deg_s": ("tau_e", float, math.radians, math.degrees),
    "tau_s_s": ("tau_s", float, None, None), "tau_l_s": ("tau_l", float, None, None),
    "max_distance_m": ("max_distance", float, None, None)}
CALIBRATION_KEYS = {"model": ("model", str, None, None),
                    "weighting": ("weighting", str, None, None),
                    "method": ("method", str, None, None)}
INTERPOLATION_KEYS = {
    "rate_hz": ("rate_hz", float, None, None),
    "qc": ("qc", (str, float, int), lambda v: v if isinstance(v, str) else float(v), None),
    "max_gap_s": ("max_gap_s", float, None, None), "gp_noise": ("gp_noise", str, None, None),
    "motion_prior": ("motion_prior", str, None, None),
    "outlier_windows": ("outlier_windows", str, None, None),
    "prior": ("prior", str, None, None),
    "correlated_noise": ("correlated_noise", str, None, None)}
POSE_KEYS = {k: (k, kind, None, None) for k, kind in (
    ("engine", str), ("registration", str), ("samples", int), ("distance_gate_m", float),
    ("uncertainty_gate_m", float), ("clocks", bool))}


def read_options(path: Path, doc: dict, instrument: InstrumentProfile,
                 *, query_times: bool = True) -> tuple[RunOptions, Path | None]:
    """The processing tables of a configuration (``[noise]``, ``[filter]``,
    ``[calibration]``, ``[interpolation]``, ``[pose]``) as options, each key checked, and the
    query-times file of ``[interpolation]`` (None without it; refused unless
    ``query_times``)."""
    n = TomlSection(path, "noise", doc.get("noise", {}))
    sources = n.get("sources", list, None)
    bad = [x for x in sources or () if x not in NOISE_SOURCES]
    if bad:
        raise ConfigError(
            f"[noise] unknown source(s) {', '.join(map(repr, bad))}; known: {', '.join(NOISE_SOURCES)}",
            path,
        )
    profile = _profile(path, doc)
    noise = n.record(NoiseModel, NOISE_KEYS, instrument=instrument)
    n.done()

    f = TomlSection(path, "filter", doc.get("filter", {}))
    filt = f.record(FilterParams, FILTER_KEYS, **_preset(profile, FilterParams))
    f.done()

    c = TomlSection(path, "calibration", doc.get("calibration", {}))
    calibration = c.record(CalibrationOptions, CALIBRATION_KEYS,
                           **_preset(profile, CalibrationOptions))
    c.done()

    it = TomlSection(path, "interpolation", doc.get("interpolation", {}))
    if "query_times" in it.table and not query_times:
        raise ConfigError("[interpolation] query_times has no meaning here", path)
    times = it.file("query_times") if "query_times" in it.table else None
    if times is not None and "rate_hz" in it.table:
        raise ConfigError("[interpolation] give rate_hz or query_times, not both", path)
    interp = it.record(InterpolationOptions, INTERPOLATION_KEYS,
                       **_preset(profile, InterpolationOptions))
    it.done()

    p = TomlSection(path, "pose", doc.get("pose", {}))
    pose = p.record(PoseOptions, POSE_KEYS, **_preset(profile, PoseOptions))
    p.done()

    return RunOptions(filter=filt, noise=noise, calibration=calibration, interpolation=interp,
                      pose=pose), times


def _profile(path: Path, doc: dict) -> str | None:
    """The file's top-level ``profile`` key (None without it): a name of
    :data:`rtsgt.options.PROFILES`."""
    value = doc.get("profile")
    if value is not None and (not isinstance(value, str) or value not in PROFILES):
        raise ConfigError(f"profile = {value!r} is not one of "
                          f"{', '.join(map(repr, PROFILES))}", path)
    return value


def _preset(profile: str | None, record: type) -> dict[str, Any]:
    """The switches of ``profile`` that are fields of the option ``record``: its values where
    the file's table does not give the key."""
    names = {f.name for f in fields(record)}
    return {k: v for k, v in PROFILES.get(profile, {}).items() if k in names}


def _misplaced_profile(path: Path, doc: dict) -> None:
    """Refuse the run's ``profile`` key inside a table (TOML puts a key written below a
    table's header in that table)."""
    tables = [(name, t) for name, t in doc.items() if isinstance(t, dict)]
    tables += [(f"{name} #{i + 1}", t) for name, ts in doc.items() if isinstance(ts, list)
               for i, t in enumerate(ts) if isinstance(t, dict)]
    for name, table in tables:
        # [instrument] profile names the instrument: misplaced only when it names a preset
        if "profile" in table and (name != "instrument" or table["profile"] in PROFILES):
            raise ConfigError(f"[{name}] profile = {table['profile']!r}: the run's profile is "
                              "a key of the file's top, written before its first table", path)


def toml_value(value: Any) -> str:
    """A TOML literal of a string, number or list of them (strings as basic strings, floats
    in their shortest exact form)."""
    if isinstance(value, str):
        return json.dumps(value)  # JSON's escapes are TOML's (\uXXXX, \", \\)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ("nan" if value != value
                                                         else ("inf" if value > 0 else "-inf"))
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML literal for {type(value).__name__}")


def options_toml_text(options: RunOptions, instrument: InstrumentProfile) -> str:
    """The processing tables ``[noise]``, ``[filter]``, ``[calibration]``,
    ``[interpolation]`` and ``[pose]`` with every key, as :func:`read_options` reads them back
    into ``options`` (the seed is not a key of the file: the command line gives it; a
    ``noise`` of None is written as the instrument's default model)."""
    records = {
        "noise": options.noise if options.noise is not None else NoiseModel(instrument=instrument),
        "filter": options.filter, "calibration": options.calibration,
        "interpolation": options.interpolation, "pose": options.pose,
    }
    specs = {"noise": NOISE_KEYS, "filter": FILTER_KEYS, "calibration": CALIBRATION_KEYS,
             "interpolation": INTERPOLATION_KEYS, "pose": POSE_KEYS}
    out = []
    for table, spec in specs.items():
        out.append(f"[{table}]")
        for key, (name, _kind, _read, back) in spec.items():
            value = getattr(records[table], name)
            out.append(f"{key} = {toml_value(back(value) if back is not None else value)}")
        out.append("")
    return "\n".join(out)


def _station(path: Path, i: int, table: Any,
             measurements: MeasurementsConfig | None) -> StationConfig:
    """One ``[[stations]]`` table: its file and format, or, with ``[measurements]``, its
    theodolite id (default: the station id read as an integer)."""
    s = TomlSection(path, f"stations #{i + 1}", table)
    sid, prism = s.get("id", str), s.get("prism", str)
    constant = s.get("additive_constant_m", float, 0.0)
    if measurements is None:
        if "theodolite_id" in s.table:
            raise ConfigError(f"[{s.name}] theodolite_id applies to measurements from a bag "
                              "([measurements]); this station reads file", path)
        st = StationConfig(sid, prism, s.file(), s.get("format", str, "rts-project",
                                                           STATION_FORMATS), constant)
    else:
        given = [k for k in ("file", "format") if k in s.table]
        if given:
            raise ConfigError(
                f"[{s.name}] {' and '.join(given)}: the measurements come from [measurements] "
                f"file {measurements.file.name}; give the stations' files or [measurements], "
                "not both", path)
        tid = s.get("theodolite_id", int, None)
        if tid is None:
            if not sid.isdigit():
                raise ConfigError(f"[{s.name}] id = {sid!r} is not a theodolite number: give "
                                  "theodolite_id (the station's id in the bag's messages)", path)
            tid = int(sid)
        if not 0 <= tid <= 255:
            raise ConfigError(f"[{s.name}] theodolite_id must be in [0, 255] (uint8), got {tid}",
                              path)
        st = StationConfig(sid, prism, None, "ros-bag", constant, tid)
    s.done()
    return st


def _reference(path: Path, doc: dict, prisms: list[str],
               positions_only: bool) -> ReferenceConfig:
    """The ``[reference]`` table (required for a pose run: at least 3 prisms)."""
    r = TomlSection(path, "reference", doc["reference"] if "reference" in doc
                 else _missing(path, "reference"))
    ref_file = r.file()
    ref_format = r.get("format", str, "survey-dms", REFERENCE_FORMATS)
    prism_rows = r.get("prisms", dict)
    rows: dict[str, int] = {}
    for k, v in prism_rows.items():
        if not isinstance(v, int) or v < 1:
            raise ConfigError(f"[reference] prisms.{k} must be a 1-based row number, got {v!r}", path)
        rows[str(k)] = v
    missing = sorted(set(prisms) - set(rows))
    if missing:
        raise ConfigError(
            f"[reference] prisms has no survey row for tracked prism(s) {', '.join(missing)}", path
        )
    if len(rows) < MIN_POSE_PRISMS and not positions_only:
        raise ConfigError(f"a pose needs at least 3 reference prisms, got {len(rows)}", path)
    body_frame = r.get("body_frame", str, "survey", BODY_FRAMES)
    body_points = tuple(r.get("body_points", list, []))
    T_sb = r.get("T_survey_body", list, None)
    if body_frame == "points" and len(body_points) < 3:
        raise ConfigError("[reference] body_frame = 'points' needs body_points = [3+ rows]", path)
    if body_frame == "transform":
        if T_sb is None or len(T_sb) != 4 or any(len(row) != 4 for row in T_sb):
            raise ConfigError("[reference] body_frame = 'transform' needs a 4x4 T_survey_body", path)
        T_sb = tuple(tuple(float(x) for x in row) for row in T_sb)
    pivot = r.get("rocking_pivot", list, None)
    if pivot is not None:
        if len(pivot) != 3 or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                      and math.isfinite(x) for x in pivot):
            raise ConfigError(f"[reference] rocking_pivot must be [x, y, z] in m, got {pivot!r}",
                              path)
        pivot = tuple(float(x) for x in pivot)
    stability = r.get("prism_stability_mm", float, 0.0)
    if not (math.isfinite(stability) and stability >= 0.0):
        raise ConfigError(f"[reference] prism_stability_mm must be a finite mm >= 0, got "
                          f"{stability!r}", path)
    reference = ReferenceConfig(ref_file, ref_format, rows, body_frame, body_points, T_sb, pivot,
                                stability)
    r.done()
    return reference


def _missing(path: Path, section: str):
    raise ConfigError(f"missing the [{section}] section", path)
