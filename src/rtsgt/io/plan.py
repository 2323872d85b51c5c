"""Plan files (TOML) of ``rtsgt plan``, and the paths they name: :func:`load_plan` reads one
(or a deployment TOML, its own layout) into a layout, a motion and an area or a path, every
key checked. Schema and example: docs/file-formats.md#plan-toml.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rtsgt.deployment import DeploymentData
from rtsgt.errors import ConfigError, InputError
from rtsgt.io._parse import find_columns, read_lines, split_rows, to_float
from rtsgt.io.config import TomlSection, read_instrument, read_options
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import read_summary
from rtsgt.io.survey import read_reference_csv
from rtsgt.io.trajectory import read_trajectory
from rtsgt.measurement.instruments import InstrumentProfile
from rtsgt.options import RunOptions
from rtsgt.planning.layout import DEFAULT_RATE_HZ, PlannedStation
from rtsgt.pose import ReferencePoints

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["PathData", "PlanInputs", "is_deployment_toml", "load_plan", "read_path",
           "read_run_qc"]

#: Sections of a plan file.
PLAN_SECTIONS = ("plan", "instrument", "stations", "gcp", "rig", "robot", "area", "path",
                 "noise", "filter", "calibration", "interpolation", "pose")
#: Those a plan with ``layout`` (an existing deployment) may not have.
LAYOUT_SECTIONS = ("instrument", "stations", "gcp", "rig", "noise", "filter", "calibration",
                   "interpolation", "pose")
#: Default survey sigma of a planned rig's prisms, m.
DEFAULT_RIG_SIGMA_M = 1e-3


@dataclass(frozen=True)
class PathData:
    """A path read from a file or given as waypoints.

    ``xyz`` (P, 3) plan coordinates, m (z NaN where the file has none); ``t`` (P,) s or None;
    ``quat_xyzw`` (P, 4) or None: a trajectory of poses (``xyz`` the body frame's origin).
    """

    xyz: np.ndarray
    t: np.ndarray | None = None
    quat_xyzw: np.ndarray | None = None
    source: str = ""


@dataclass(frozen=True)
class PlanInputs:
    """Everything a plan file says, read and checked (the CLI builds the plan from it).

    Either ``deployment`` (an existing deployment's data and options) or the planned layout
    (``stations``, ``gcp_xyz``, ``gcp_names``, ``reference``, ``instrument``, ``options``).
    """

    path: Path
    name: str
    reference_station: str
    seed: int
    deployment: tuple[DeploymentData, RunOptions] | None
    stations: dict[str, PlannedStation]
    gcp_xyz: np.ndarray
    gcp_names: tuple[str, ...]
    reference: ReferencePoints | None
    instrument: InstrumentProfile | None
    options: RunOptions
    speed_m_s: float | None
    qc_m2_s3: tuple[float, float] | None
    qc_from_run: Path | None
    forward_deg: float
    polygon: np.ndarray | None
    step_m: float | None
    z_m: float | None
    headings: int | None
    path_data: PathData | None
    path_step_m: float | None = None


def _doc(path: Path) -> dict:
    if not path.is_file():
        raise ConfigError("no such file", path)
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"invalid TOML: {exc}", path) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"cannot read the file: {exc}", path) from None


def is_deployment_toml(doc: dict) -> bool:
    """A deployment configuration (its stations name files), not a plan."""
    st = doc.get("stations")
    return "plan" not in doc and isinstance(st, list) and bool(st) and \
        all(isinstance(s, dict) and "file" in s for s in st)


def _xyz(value, path: Path, where: str, n: int | None = None) -> np.ndarray:
    """A list of numbers (or of lists of them) as a float array, checked."""
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"{where} must be numbers, got {value!r}"[:200], path) from None
    if (n is not None and a.shape != (n,)) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{where} must be {n} finite numbers, got {value!r}"[:200], path)
    return a


def _points(value, path: Path, where: str, dims: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"{where} must be a list of points, got {value!r}"[:200], path) \
            from None
    if a.ndim != 2 or a.shape[1] not in dims or not np.all(np.isfinite(a)):
        raise ConfigError(f"{where} must be a list of [{', '.join('xyz'[:d] for d in dims)}] "
                          "points of finite numbers"[:200], path)
    return a


def load_plan(path: str | Path) -> PlanInputs:
    """Read a plan file, or a deployment TOML as its own layout; any problem is a
    :class:`~rtsgt.errors.ConfigError` naming the file, the section and the key."""
    path = Path(path).resolve()
    doc = _doc(path)
    if is_deployment_toml(doc):
        doc = {"plan": {"layout": str(path)}}
    unknown = sorted(set(doc) - set(PLAN_SECTIONS))
    if unknown:
        raise ConfigError(f"unknown section(s) {', '.join(unknown)}; a plan has "
                          f"{', '.join(PLAN_SECTIONS)}", path)
    if "plan" not in doc:
        raise ConfigError("missing the [plan] section", path)
    pl = TomlSection(path, "plan", doc["plan"])
    name = pl.get("name", str, path.stem)
    seed = pl.get("seed", int, 0)
    if seed < 0:
        raise ConfigError(f"[plan] seed must be >= 0, got {seed}", path)
    rate = pl.positive("rate_hz", DEFAULT_RATE_HZ)
    layout_file = pl.file("layout") if "layout" in pl.table else None
    reference_station = pl.get("reference_station", str, "1")
    pl.done()

    deployment = None
    stations: dict[str, PlannedStation] = {}
    gcp = np.zeros((0, 3))
    gcp_names: tuple[str, ...] = ()
    reference = instrument = None
    if layout_file is not None:
        extra = [s for s in LAYOUT_SECTIONS if s in doc]
        if extra:
            raise ConfigError(f"[plan] layout = {layout_file.name!r} gives the layout and its "
                              f"options: remove the section(s) {', '.join(extra)}", path)
        data, options = load_deployment(layout_file)
        deployment = (data, options.updated(seed=seed))
        options = deployment[1]
        name = name if "name" in doc["plan"] else data.name
    else:
        instrument = read_instrument(path, doc)
        options = read_options(path, doc, instrument, query_times=False)[0].updated(seed=seed)
        stations = _stations(path, doc, rate)
        if reference_station not in stations:
            raise ConfigError(f"[plan] reference_station = {reference_station!r} is not a "
                              f"station; known: {', '.join(stations)}", path)
        gcp, gcp_names = _gcp(path, doc)
        reference = _rig(path, doc, [s.prism for s in stations.values() if s.prism])

    speed, qc_pair, run_dir, forward = _robot(path, doc)
    if "area" in doc and "path" in doc:
        raise ConfigError("give [area] or [path], not both", path)
    polygon, step, z, headings = _area(path, doc) if "area" in doc else (None,) * 4
    path_data, path_step, z = _path(path, doc) if "path" in doc else (None, None, z)
    return PlanInputs(path, name, reference_station, seed, deployment, stations, gcp,
                      gcp_names, reference, instrument, options, speed, qc_pair, run_dir,
                      forward, polygon, step, z, headings, path_data, path_step)


def _robot(path: Path, doc: dict) -> tuple:
    """``[robot]``: speed (m/s or None), ``Qc`` (horizontal, vertical) or None, the run
    directory of ``qc_from_run`` or None, and the forward axis (deg)."""
    rb = TomlSection(path, "robot", doc.get("robot", {}))
    speed = rb.get("speed_m_s", float, None)
    if speed is not None and not (speed >= 0 and math.isfinite(speed)):
        raise ConfigError(f"[robot] speed_m_s must be >= 0, got {speed}", path)
    qc = rb.get("qc_m2_s3", (float, int, list), None)
    qc_run = rb.get("qc_from_run", str, None)
    forward = rb.get("forward_deg", float, 0.0)
    rb.done()
    if qc is not None and qc_run is not None:
        raise ConfigError("[robot] give qc_m2_s3 or qc_from_run, not both", path)
    qc_pair = None
    if qc is not None:
        q = np.atleast_1d(_xyz(qc, path, "[robot] qc_m2_s3"))
        if q.shape not in ((1,), (2,)) or np.any(q <= 0):
            raise ConfigError(f"[robot] qc_m2_s3 must be a number > 0 or [horizontal, "
                              f"vertical], got {qc!r}", path)
        qc_pair = (float(q[0]), float(q[-1]))
    run_dir = None
    if qc_run is not None:
        run_dir = (path.parent / qc_run).resolve()
        if not run_dir.is_dir():
            raise ConfigError(f"[robot] qc_from_run = {qc_run!r}: no such directory", path)
    return speed, qc_pair, run_dir, forward


def _area(path: Path, doc: dict) -> tuple:
    """``[area]``: the polygon (V, 2), the grid step, the height and the headings (None where
    not given)."""
    ar = TomlSection(path, "area", doc["area"])
    bbox = ar.get("bbox_m", list, None)
    poly = ar.get("polygon_m", list, None)
    if (bbox is None) == (poly is None):
        raise ConfigError("[area] needs bbox_m = [xmin, ymin, xmax, ymax] or polygon_m, "
                          "one of them", path)
    if bbox is not None:
        x0, y0, x1, y1 = _xyz(bbox, path, "[area] bbox_m", 4)
        if not (x1 > x0 and y1 > y0):
            raise ConfigError(f"[area] bbox_m must be [xmin, ymin, xmax, ymax] with "
                              f"xmax > xmin and ymax > ymin, got {bbox}", path)
        polygon = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    else:
        polygon = _points(poly, path, "[area] polygon_m", (2,))
        if polygon.shape[0] < 3:
            raise ConfigError("[area] polygon_m needs at least 3 corners", path)
    step = ar.positive("step_m", None)
    z = ar.get("z_m", float, None)
    headings = ar.get("headings", int, None)
    if headings is not None and headings < 1:
        raise ConfigError(f"[area] headings must be >= 1, got {headings}", path)
    ar.done()
    return polygon, step, z, headings


def _path(path: Path, doc: dict) -> tuple:
    """``[path]``: the path's points (:class:`PathData`), the waypoints' step and the height
    (None where not given)."""
    pa = TomlSection(path, "path", doc["path"])
    has_file, way = "file" in pa.table, pa.get("waypoints_m", list, None)
    if has_file == (way is not None):
        raise ConfigError("[path] needs file or waypoints_m, one of them", path)
    if has_file:
        path_data = read_path(pa.file())
    else:
        w = _points(way, path, "[path] waypoints_m", (2, 3))
        if w.shape[0] < 2:
            raise ConfigError("[path] waypoints_m needs at least 2 points", path)
        if w.shape[1] == 2:
            w = np.column_stack([w, np.full(w.shape[0], np.nan)])
        path_data = PathData(w, source="waypoints")
    path_step = pa.positive("step_m", None)
    if "step_m" in pa.table and has_file:
        raise ConfigError("[path] step_m is for waypoints_m", path)
    z = pa.get("z_m", float, None)
    pa.done()
    return path_data, path_step, z


def _stations(path: Path, doc: dict, rate: float) -> dict[str, PlannedStation]:
    raw = doc.get("stations")
    if not isinstance(raw, list) or not raw:
        raise ConfigError("expected [[stations]] tables (or [plan] layout = a deployment "
                          "TOML)", path)
    out: dict[str, PlannedStation] = {}
    for i, tab in enumerate(raw):
        s = TomlSection(path, f"stations #{i + 1}", tab)
        sid = s.get("id", str)
        xyz = _xyz(s.get("xyz_m", list), path, f"[stations #{i + 1}] xyz_m", 3)
        prism = s.get("prism", str, None)
        r = s.positive("rate_hz", rate)
        s.done()
        if sid in out:
            raise ConfigError(f"duplicated station id {sid!r} in [[stations]]", path)
        out[sid] = PlannedStation(tuple(float(x) for x in xyz), prism, float(r))
    prisms = [s.prism for s in out.values() if s.prism is not None]
    if len(prisms) < 3:
        raise ConfigError(f"a pose needs three stations that track a prism, got "
                          f"{len(prisms)}", path)
    if len(set(prisms)) != len(prisms):
        raise ConfigError(f"each station must track a different prism, got {prisms}", path)
    return out


def _gcp(path: Path, doc: dict) -> tuple[np.ndarray, tuple[str, ...]]:
    if "gcp" not in doc:
        raise ConfigError("missing the [gcp] section (the markers' positions)", path)
    g = TomlSection(path, "gcp", doc["gcp"])
    xyz = _points(g.get("xyz_m", list), path, "[gcp] xyz_m", (3,))
    names = g.get("names", list, None)
    g.done()
    if names is None:
        names = [str(i + 1) for i in range(xyz.shape[0])]
    names = [str(n) for n in names]
    if len(names) != xyz.shape[0] or len(set(names)) != len(names):
        raise ConfigError(f"[gcp] names must be {xyz.shape[0]} distinct names", path)
    if xyz.shape[0] < 3:
        raise ConfigError(f"[gcp] a calibration needs at least 3 markers, got {xyz.shape[0]}",
                          path)
    return xyz, tuple(names)


def _rig(path: Path, doc: dict, prisms: list[str]) -> ReferencePoints:
    if "rig" not in doc:
        raise ConfigError("missing the [rig] section (the prisms on the robot)", path)
    r = TomlSection(path, "rig", doc["rig"])
    if "file" in r.table:
        if "prisms" in r.table or "sigma_m" in r.table:
            raise ConfigError("[rig] give file or prisms (with sigma_m), not both", path)
        ref = read_reference_csv(r.file())
        r.done()
    else:
        table = r.get("prisms", dict)
        sigma = r.positive("sigma_m", DEFAULT_RIG_SIGMA_M)
        r.done()
        names = [str(k) for k in table]
        xyz = np.stack([_xyz(v, path, f"[rig] prisms.{k}", 3) for k, v in table.items()]) \
            if table else np.zeros((0, 3))
        try:
            ref = ReferencePoints(tuple(names), xyz,
                                  np.eye(3 * len(names)) * sigma ** 2, "body")
        except (ValueError, InputError) as exc:
            raise ConfigError(f"[rig] {exc}", path) from None
    missing = [p for p in prisms if p not in ref.names]
    if missing:
        raise ConfigError(f"[rig] has no position for the tracked prism(s) "
                          f"{', '.join(missing)}", path)
    return ref


def read_path(path: str | Path) -> PathData:
    """A path file: ``x,y[,z][,t]`` with a header (any order, other columns ignored), or a
    trajectory of poses in a format :func:`rtsgt.io.trajectory.read_trajectory` recognises
    (TUM, KITTI, EuRoC, a run's ``groundtruth_covariance.csv``).

    Raises
    ------
    InputError
        Naming the file and line.
    """
    p = Path(path)
    numbers, lines = read_lines(p, "a path (x,y[,z][,t] with a header, or poses)")
    header = [h.strip().lower() for h in lines[0].replace(",", " ").split()]
    if "x" in header and "y" in header and "qx" not in header:
        cols = [h.strip() for h in lines[0].split(",")]
        pos = find_columns(cols, ("x", "y"), p, numbers[0], optional=("z", "t"))
        if len(lines) < 2:
            raise InputError("expected points after the header, got none", p)
        tok = split_rows(lines[1:], numbers[1:], p, cols, ",")
        names = [c for c in ("x", "y", "z", "t") if c in pos]
        a = to_float(tok[:, [pos[c] for c in names]], numbers[1:], p, names)
        col = dict(zip(names, a.T, strict=True))
        z = col.get("z", np.full(a.shape[0], np.nan))
        t = col.get("t")
        if t is not None and np.any(np.diff(t) <= 0):
            i = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
            raise InputError("expected increasing times t", p, numbers[1 + i])
        return PathData(np.column_stack([col["x"], col["y"], z]), t, None, str(p))
    traj = read_trajectory(p)
    return PathData(np.asarray(traj.position, dtype=float), np.asarray(traj.t, dtype=float),
                    np.asarray(traj.quat_xyzw, dtype=float), str(p))


def read_run_qc(run_dir: str | Path) -> dict[str, dict]:
    """Per prism, ``qc_m2_s3`` and ``qc_fit`` of a run directory's ``summary.json`` (for
    :func:`rtsgt.planning.qc_from_run`).

    Raises
    ------
    InputError
        No summary, or no prism with a Qc in it.
    """
    summary = read_summary(run_dir)
    if not summary.exists:
        raise InputError("no summary.json: expected an rtsgt run directory", run_dir)
    listed = summary.document.get("prisms")
    out = {}
    for pid, info in summary.prisms.items():
        if info.qc_m2_s3 is None:
            continue
        raw = listed.get(pid, {}) if isinstance(listed, dict) else {}
        fit = raw.get("qc_fit") if isinstance(raw, dict) else None
        q = np.asarray(info.qc_m2_s3, dtype=float)
        q = q * np.eye(3) if q.ndim == 0 else np.diag(q) if q.shape == (3,) else q
        out[pid] = {"qc_m2_s3": q, "qc_fit": fit if isinstance(fit, dict) else {}}
    if not out:
        raise InputError("summary.json has no prism with a Qc (qc_m2_s3)", summary.path)
    return out
