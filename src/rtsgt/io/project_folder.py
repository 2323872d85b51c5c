"""An RTS_project deployment folder as it is: what it holds, and a deployment TOML for it.

:func:`scan_folder` looks for each input of ``data/<date>/`` (the GCP shots, the prism files
or a raw bag, the survey, a weather file) at its RTS_project path, then by name anywhere
under the folder; :func:`deployment_toml_text` writes the ``deployment.toml`` that
``rtsgt run`` reads (``rtsgt init``), each choice commented in it. Paths, choices and
output: docs/file-formats.md#rtsgt-init.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rtsgt import __version__
from rtsgt.errors import InputError
from rtsgt.io._bag import open_bag, rosbags_modules
from rtsgt.io.config import options_toml_text, toml_value
from rtsgt.io.output_dir import MANIFEST
from rtsgt.io.rts_bag import OLD_TOPIC, TOPIC
from rtsgt.io.rts_project import read_gcp_rts_project, read_prism_file
from rtsgt.io.survey import (
    read_calibration_results,
    read_sensor_positions,
    read_survey_raw,
)
from rtsgt.io.weather import read_weather_csv, read_weather_eccc, weather_format
from rtsgt.measurement.instruments import instrument_from_config
from rtsgt.options import RunOptions
from rtsgt.record import MIN_POSE_PRISMS

#: The first characters of every TOML ``rtsgt init`` writes (what ``--force`` may replace).
INIT_MARK = "# Written by rtsgt init"
#: Where the RTS_project keeps each input, relative to ``data/<date>/``.
RTS_PROJECT_PATHS = {
    "gcp": "total_stations/GCP.txt",
    "prisms": "uncertainty/raw_data",
    "survey": "sensors_extrinsic_calibration/calibration_raw.csv",
    "sensor_positions": "sensors_extrinsic_calibration/sensor_positions.csv",
    "calibration_results": "sensors_extrinsic_calibration/calibration_results.csv",
}
#: Measurement sources ``rtsgt init`` may take.
MEASUREMENT_CHOICES = ("auto", "bag", "prisms")
#: The RTS_project's additive (prism) constant, m, and instrument.
RTS_PROJECT_CONSTANT_M = 0.01
RTS_PROJECT_INSTRUMENT = "trimble-s7"
#: Survey rows of the RTS_project layout (1-based): prisms 1-3, GNSS antennas 1-3.
PRISM_ROWS = (1, 2, 3)
GNSS_ROWS = (4, 5, 6)
#: Default offset of an ECCC file's local standard time from UTC, h (Quebec).
ECCC_UTC_OFFSET_H = -5.0
#: How deep under the folder inputs are looked for.
MAX_DEPTH = 6

_PRISM_FILE = re.compile(r"^prism(\d+)\.csv$", re.IGNORECASE)


@dataclass
class FolderScan:
    """What :func:`scan_folder` found in a deployment folder.

    ``found``, ``missing`` and ``notes`` are the lines to show: one per input found, one per
    input missing (``required`` among them: what prevents a TOML), one per choice made.
    """

    folder: Path
    gcp: Path | None = None
    gcp_stations: tuple[str, ...] = ()
    #: prism id -> tracked prism file (empty when the measurements come from a bag).
    prism_files: dict[str, Path] = field(default_factory=dict)
    bag: Path | None = None
    #: The stations (ids), each tracking the prism of the same id.
    stations: tuple[str, ...] = ()
    survey: Path | None = None
    survey_format: str | None = None
    survey_rows: int = 0
    calibration_results: Path | None = None
    weather: Path | None = None
    weather_format: str | None = None
    found: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    required_missing: int = 0
    notes: list[str] = field(default_factory=list)

    def lack(self, text: str, *, required: bool) -> None:
        self.missing.append(text if required else f"{text} (optional)")
        self.required_missing += int(required)


def _skipped(folder: Path, names: list[str]) -> bool:
    """Whether a folder under the scan is one to skip: one rtsgt wrote, other than a
    simulated deployment (module docstring)."""
    if MANIFEST not in names:
        return False
    try:
        kind = json.loads((folder / MANIFEST).read_text(encoding="utf-8")).get("kind")
    except (OSError, ValueError, AttributeError):
        return False
    return kind != "deployment"


def _walk(root: Path) -> list[tuple[Path, list[str], list[str]]]:
    """``(folder, subfolders, files)`` under ``root``, sorted, at most :data:`MAX_DEPTH`
    deep, skipping hidden and ``static*`` folders and rtsgt outputs (module docstring)."""
    out = []
    for here, dirs, files in os.walk(root):
        p = Path(here)
        depth = len(p.relative_to(root).parts)
        dirs[:] = sorted(d for d in dirs if not d.startswith(".")
                         and not d.lower().startswith("static") and depth < MAX_DEPTH)
        if p != root and _skipped(p, files):
            dirs[:] = []
            continue
        out.append((p, list(dirs), sorted(files)))
    return out


def _find_file(root: Path, tree, canonical: str, name: str) -> tuple[Path | None, list[Path]]:
    """The file at its RTS_project path, else the only file called ``name`` under the
    folder; ``(path or None, every candidate)``."""
    p = root / canonical
    if p.is_file():
        return p, [p]
    hits = [d / f for d, _, files in tree for f in files if f.lower() == name.lower()]
    return (hits[0] if len(hits) == 1 else None), hits


def _rel(p: Path, root: Path) -> str:
    return p.relative_to(root).as_posix()


def _bags(tree) -> list[Path]:
    """ROS 1 ``.bag`` files and ROS 2 bag directories (with ``metadata.yaml``) under the
    folder."""
    out = []
    for d, _, files in tree:
        if "metadata.yaml" in files and any(f.endswith((".db3", ".mcap")) for f in files):
            out.append(d)
        else:
            out += [d / f for f in files if f.endswith(".bag")]
    return sorted(set(out))


def _theodolite_bags(bags: list[Path]) -> tuple[list[Path], bool]:
    """The bags with a total-station topic (:data:`~rtsgt.io.rts_bag.TOPIC` or the older
    one), and whether that could be checked (it needs ``rosbags``; without it every bag is
    kept)."""
    try:
        rosbags_modules()
    except InputError:
        return bags, False
    kept = []
    for b in bags:
        try:
            with open_bag(b) as reader:
                if {TOPIC, OLD_TOPIC} & set(reader.topics):
                    kept.append(b)
        except InputError:
            continue
    return kept, True


def _prism_dirs(root: Path, tree) -> dict[Path, dict[str, Path]]:
    """Folders holding ``prism<i>.csv`` files: folder -> {prism id: file}."""
    out: dict[Path, dict[str, Path]] = {}
    for d, _, files in tree:
        found = {}
        for f in files:
            m = _PRISM_FILE.match(f)
            if m:
                found[str(int(m.group(1)))] = d / f
        if found:
            out[d] = dict(sorted(found.items(), key=lambda kv: int(kv[0])))
    canonical = root / RTS_PROJECT_PATHS["prisms"]
    if canonical in out:
        return {canonical: out[canonical]}
    return out


def scan_folder(folder: str | os.PathLike, *, weather: str | os.PathLike | None = None,
                measurements: str = "auto") -> FolderScan:
    """Look for a deployment's inputs in an RTS_project-like ``folder`` (``data/<date>/`` or a flat
    folder): ``weather`` a file anywhere (default: the one found), ``measurements`` ``"auto"``
    (the bag if any, else the prism files), ``"bag"`` or ``"prisms"``. Returns the
    :class:`FolderScan`, found and missing; an input that cannot be read raises
    :class:`~rtsgt.errors.InputError`."""
    if measurements not in MEASUREMENT_CHOICES:
        raise InputError(f"Expected measurements among {', '.join(MEASUREMENT_CHOICES)}, got "
                         f"{measurements!r}")
    root = Path(os.path.abspath(folder))
    if not root.is_dir():
        raise InputError("no such folder", folder)
    scan = FolderScan(root)
    tree = _walk(root)

    # GCP shots
    gcp, hits = _find_file(root, tree, RTS_PROJECT_PATHS["gcp"], "GCP.txt")
    if gcp is None:
        scan.lack(_several("GCP.txt", hits, root) if hits else
                  f"GCP shots: no {RTS_PROJECT_PATHS['gcp']} (the ground control points shot "
                  "by every station, RTS_project format; needed to calibrate the stations)",
                  required=True)
    else:
        shots = read_gcp_rts_project(gcp, additive_constant=RTS_PROJECT_CONSTANT_M)
        valid = sorted({str(s) for s, st in zip(shots.station, shots.status, strict=True)
                        if st == 0}, key=_natural)
        scan.gcp, scan.gcp_stations = gcp, tuple(valid)
        n_markers = len({m for m, st in zip(shots.marker, shots.status, strict=True) if st == 0})
        scan.found.append(f"GCP shots: {_rel(gcp, root)} ({int(np.sum(shots.status == 0))} "
                          f"valid shots of {n_markers} markers by stations {', '.join(valid)})")

    _scan_measurements(scan, root, tree, measurements)
    _scan_survey(scan, root, tree)
    _scan_weather(scan, root, tree, weather)
    return scan


def _natural(s: str) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", s) if p)


def _several(name: str, hits: list[Path], root: Path) -> str:
    return (f"{name}: {len(hits)} files of that name ({', '.join(_rel(h, root) for h in hits)})"
            "; keep the one of this deployment, or write the TOML by hand")


def _scan_measurements(scan: FolderScan, root: Path, tree, choice: str) -> None:
    """The stations' measurements: a raw bag, or the tracked prism files."""
    prism_dirs = _prism_dirs(root, tree) if choice != "bag" else {}
    bags: list[Path] = []
    checked = False
    if choice != "prisms":
        bags, checked = _theodolite_bags(_bags(tree))
    if len(bags) > 1:
        scan.lack(f"measurements: {len(bags)} raw bags ({', '.join(_rel(b, root) for b in bags)})"
                  "; one deployment is one bag: keep one in the folder, or use --measurements "
                  "prisms", required=True)
        return
    if bags:
        scan.bag = bags[0]
        scan.stations = scan.gcp_stations
        scan.found.append(
            f"measurements: raw bag {_rel(bags[0], root)}"
            + ("" if checked else " (its topics not checked: rosbags is not installed)")
            + (f"; stations {', '.join(scan.stations)} (those of the GCP shots), station i "
               "tracking prism i" if scan.stations else ""))
        if prism_dirs:
            scan.notes.append("the raw bag is used, not the prism files of "
                              f"{', '.join(_rel(d, root) for d in prism_dirs)} (those are the "
                              "reference code's output after its rate filter); "
                              "--measurements prisms takes them")
        if not scan.stations and scan.gcp is not None:
            scan.lack("stations: the GCP file has no valid shot, so no station to read from the "
                      "bag", required=True)
        return
    if len(prism_dirs) > 1:
        scan.lack("measurements: prism files in several folders ("
                  + ", ".join(_rel(d, root) or "." for d in prism_dirs)
                  + "); keep one set, or write the TOML by hand", required=True)
        return
    if not prism_dirs:
        what = {"auto": "no raw bag and no tracked prism files",
                "bag": "no raw bag of the total stations",
                "prisms": "no tracked prism files"}[choice]
        scan.lack(f"measurements: {what} ({RTS_PROJECT_PATHS['prisms']}/prism<i>.csv, `t d V "
                  "Hz`, or a ROS 1 .bag / ROS 2 bag folder with the theodolite topic)",
                  required=True)
        return
    (d, files), = prism_dirs.items()
    scan.prism_files = files
    scan.stations = tuple(files)
    where = _rel(d, root)
    scan.found.append(f"measurements: {len(files)} prism files in {where or '.'} ("
                      + ", ".join(f.name for f in files.values())
                      + "), station i tracking prism i")
    if scan.gcp is not None:
        lacking = [s for s in scan.stations if s not in scan.gcp_stations]
        for s in lacking:
            scan.lack(f"GCP shots of station {s} (it tracks prism{s}.csv; {_rel(scan.gcp, root)} "
                      f"has valid shots of stations {', '.join(scan.gcp_stations) or 'none'})",
                      required=True)


def _scan_survey(scan: FolderScan, root: Path, tree) -> None:
    """The static survey of the robot (``calibration_raw.csv`` or ``sensor_positions.csv``)
    and the inter-prism distances of ``calibration_results.csv``."""
    raw, raw_hits = _find_file(root, tree, RTS_PROJECT_PATHS["survey"], "calibration_raw.csv")
    pos, pos_hits = _find_file(root, tree, RTS_PROJECT_PATHS["sensor_positions"],
                               "sensor_positions.csv")
    xyz = None
    if raw is not None:
        survey = read_survey_raw(raw)
        scan.survey, scan.survey_format, xyz = raw, "survey-dms", survey.xyz
        scan.found.append(f"survey: {_rel(raw, root)} ({len(survey)} points, DMS with sigmas)")
        if pos is not None:
            scan.notes.append(f"survey: {_rel(raw, root)} is used, not {_rel(pos, root)} (the "
                              "same points; its covariances are not those of the survey's "
                              "sigmas)")
    elif pos is not None:
        points = read_sensor_positions(pos)
        scan.survey, scan.survey_format, xyz = pos, "sensor-positions", points.xyz
        scan.found.append(f"survey: {_rel(pos, root)} ({len(points)} points, x y z and a "
                          "covariance)")
    else:
        hits = raw_hits or pos_hits
        # a run of fewer than MIN_POSE_PRISMS tracked prisms gives their positions only and
        # reads no survey (rtsgt.io.config): then the survey is not required
        poses = not scan.stations or len(scan.stations) >= MIN_POSE_PRISMS
        n = len(scan.stations)
        scan.lack(_several(hits[0].name, hits, root) if hits else
                  f"survey of the robot: no {RTS_PROJECT_PATHS['survey']} nor "
                  f"{Path(RTS_PROJECT_PATHS['sensor_positions']).name} (the prisms' positions on "
                  "the robot; needed for the poses"
                  + ("" if poses else f", not for the positions of {n} tracked prism"
                     f"{'s' * (n > 1)}, all a run of fewer than {MIN_POSE_PRISMS} gives") + ")",
                  required=poses or bool(hits))
    if xyz is not None:
        scan.survey_rows = xyz.shape[0]
        beyond = [s for s in scan.stations
                  if not (s.isdigit() and int(s) in PRISM_ROWS)]
        for s in beyond:
            scan.lack(f"survey row of prism {s}: the RTS_project survey has the prisms in rows "
                      f"{PRISM_ROWS[0]}-{PRISM_ROWS[-1]}; write [reference] prisms by hand",
                      required=True)
        if scan.survey_rows < max(GNSS_ROWS):
            scan.notes.append(f"the survey has {scan.survey_rows} rows, not the GNSS antennas "
                              f"of rows {GNSS_ROWS[0]}-{GNSS_ROWS[-1]}: the ground truth is in "
                              "the survey frame")

    res, hits = _find_file(root, tree, RTS_PROJECT_PATHS["calibration_results"],
                           "calibration_results.csv")
    if res is None:
        scan.lack(_several("calibration_results.csv", hits, root) if hits else
                  "calibration_results.csv (the surveyed inter-prism distances: only checked "
                  "against the survey, rtsgt run takes them from the survey)", required=False)
        return
    scan.calibration_results = res
    d = read_calibration_results(res).prism_distances
    text = f"inter-prism distances: {_rel(res, root)}"
    if xyz is not None and scan.survey_rows >= 3:
        p = xyz[np.array(PRISM_ROWS) - 1]
        survey_d = np.linalg.norm(p[[0, 0, 1]] - p[[1, 2, 2]], axis=1)
        text += (f" (d12 d13 d23 differ from the survey's by at most "
                 f"{np.max(np.abs(survey_d - d)) * 1e3:.2f} mm; not needed by the run)")
    scan.found.append(text)


def _measurement_span(scan: FolderScan) -> tuple[float, float] | None:
    """First and last time of the tracked prism files (None with a bag)."""
    if not scan.prism_files:
        return None
    t = [read_prism_file(p, station=s, prism=s).t for s, p in scan.prism_files.items()]
    return min(x[0] for x in t), max(x[-1] for x in t)


def _read_weather(path: Path, fmt: str):
    if fmt == "eccc":
        return read_weather_eccc(path, utc_offset_hours=ECCC_UTC_OFFSET_H)
    return read_weather_csv(path)


def _scan_weather(scan: FolderScan, root: Path, tree, given: str | os.PathLike | None) -> None:
    """The weather file: given, or the one found under the folder (module docstring)."""
    if given is not None:
        p = Path(os.path.abspath(given))
        if not p.is_file():
            raise InputError("no such weather file", given)
        fmt = weather_format(p)
        if fmt is None:
            raise InputError("not a weather file: expected an ECCC hourly CSV (Date/Heure "
                             "(HNL) or Date/Time (LST), Temp (°C), ...) or rtsgt's weather CSV "
                             "(t_s,temperature_c,pressure_hpa,humidity_pct)", given)
        scan.weather, scan.weather_format = p, fmt
        scan.found.append(f"weather: {p} ({'ECCC hourly' if fmt == 'eccc' else 'rtsgt CSV'}, "
                          "given)")
        return
    candidates = [(d / f, fmt) for d, _, files in tree for f in files
                  if f.lower().endswith((".csv", ".txt"))
                  and (fmt := weather_format(d / f)) is not None]
    if len(candidates) > 1:
        span = _measurement_span(scan)
        if span is not None:
            covering = []
            for p, fmt in candidates:
                w = _read_weather(p, fmt)
                if w.t[0] <= span[0] and w.t[-1] >= span[1]:
                    covering.append((p, fmt))
            if len(covering) == 1:
                scan.notes.append(f"weather: {_rel(covering[0][0], root)} of "
                                  f"{len(candidates)} weather files, the one covering the "
                                  "measurements")
                candidates = covering
    if len(candidates) == 1:
        (p, fmt), = candidates
        scan.weather, scan.weather_format = p, fmt
        scan.found.append(f"weather: {_rel(p, root)} "
                          f"({'ECCC hourly' if fmt == 'eccc' else 'rtsgt CSV'})")
        return
    if candidates:
        scan.lack(f"weather: {len(candidates)} weather files ("
                  + ", ".join(_rel(p, root) for p, _ in candidates)
                  + "), none alone covering the measurements; give one with --weather FILE",
                  required=False)
        return
    scan.lack("weather: no ECCC hourly CSV nor rtsgt weather CSV under the folder (the "
              "RTS_project keeps them in data/weather_<year>/): without it the run makes no "
              "atmospheric correction; give one with --weather FILE", required=False)


def deployment_toml_text(scan: FolderScan, toml_path: str | os.PathLike, *,
                         name: str | None = None,
                         utc_offset_hours: float | None = None) -> str:
    """The ``deployment.toml`` of a ``scan`` without a required input missing (else ValueError),
    paths relative to ``toml_path``; ``name`` default the folder's, ``utc_offset_hours`` of an
    ECCC file default -5 (Quebec)."""
    if scan.required_missing:
        raise ValueError(f"{scan.required_missing} required input(s) missing: "
                         + "; ".join(scan.missing))
    base = Path(os.path.abspath(toml_path)).parent

    def rel(p: Path) -> str:
        return toml_value(Path(os.path.relpath(p, base)).as_posix())

    c = toml_value(RTS_PROJECT_CONSTANT_M)
    name = scan.folder.name if name is None else name
    out = [
        f"{INIT_MARK} {__version__} from the RTS_project-like folder {toml_value(scan.folder.name)};",
        "# rtsgt init --force replaces this file while this line heads it. Paths are relative to",
        "# this file; every key: docs/file-formats.md#deployment-toml. Choices below are those",
        "# of the RTS_project (docs/file-formats.md#rtsgt-init): check them for your deployment.",
        "",
        "[deployment]",
        f"name = {toml_value(name)}",
        f"reference_station = {toml_value(scan.stations[0])}",
        "",
        "[instrument]",
        "# the RTS_project's Trimble S7 stations",
        f"profile = {toml_value(RTS_PROJECT_INSTRUMENT)}",
        "",
    ]
    if scan.bag is not None:
        out += [
            "# every station's measurements from the raw bag of the acquisition system",
            "[measurements]",
            f"file = {rel(scan.bag)}",
            'format = "ros-bag"',
            "",
        ]
    for s in scan.stations:
        out += ["[[stations]]", f"id = {toml_value(s)}", f"prism = {toml_value(s)}"]
        if scan.bag is None:
            out += [f"file = {rel(scan.prism_files[s])}", 'format = "rts-project"']
        out += [f"additive_constant_m = {c}   # the RTS_project's prisms", ""]
    out += [
        "[gcp]",
        f"file = {rel(scan.gcp)}",
        'format = "rts-project"',
        f"additive_constant_m = {c}",
        "",
    ]
    if scan.weather is not None:
        out += ["[weather]", f"file = {rel(scan.weather)}",
                f"format = {toml_value(scan.weather_format)}"]
        if scan.weather_format == "eccc":
            off = ECCC_UTC_OFFSET_H if utc_offset_hours is None else float(utc_offset_hours)
            out.append(f"utc_offset_hours = {toml_value(off)}"
                       + ("   # ECCC local standard time: Quebec's (UTC-5); check for your site"
                          if utc_offset_hours is None else ""))
        out.append("")
    prisms = ", ".join(f"{toml_value(s)} = {int(s)}" for s in scan.stations)
    if scan.survey is None:  # fewer than MIN_POSE_PRISMS stations: positions only
        out += [f"# no [reference]: no survey of the robot, and with fewer than {MIN_POSE_PRISMS}",
                "# tracked prisms the run gives their positions only (no pose)"]
    else:
        out += [
            "[reference]",
            f"file = {rel(scan.survey)}",
            f"format = {toml_value(scan.survey_format)}",
            f"prisms = {{ {prisms} }}   # prism i is survey row i (RTS_project: rows 1-3)",
        ]
        if scan.survey_rows >= max(GNSS_ROWS):
            out += ["# the ground truth in the frame of the GNSS antennas (survey rows 4-6; "
                    "origin at", "# their centroid, x from antenna 1 to 2), not the survey "
                    "station's frame", 'body_frame = "points"',
                    f"body_points = {toml_value(list(GNSS_ROWS))}"]
        else:
            out += ['body_frame = "survey"']
    out += ["", "# processing: rtsgt's defaults (docs/file-formats.md#deployment-toml)"]
    instrument = instrument_from_config({"profile": RTS_PROJECT_INSTRUMENT})
    out.append(options_toml_text(RunOptions(), instrument))
    return "\n".join(out).rstrip("\n") + "\n"


def is_init_toml(head: str) -> bool:
    """Whether a file's first characters are those of a TOML written by ``rtsgt init``."""
    return head.startswith(INIT_MARK)
