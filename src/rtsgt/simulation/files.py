r"""Write a simulated deployment as the files of a real one, plus its truth.

:func:`write_deployment` writes ``prism<k>.csv``, ``GCP.txt``, ``calibration_raw.csv``,
``weather.csv``, ``truth.tum``, ``truth_prisms.csv``, ``truth.json`` and ``deployment.toml``
(docs/file-formats.md), at full precision (shortest round-trip ``repr``), through a temporary
directory renamed at the end (:mod:`rtsgt.io.output_dir`): never half-written.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path

import numpy as np

from rtsgt import __version__
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.io._parse import table_text
from rtsgt.io.output_dir import OutputDir
from rtsgt.io.trajectory import tum_text
from rtsgt.simulation.deployment import SimulatedDeployment
from rtsgt.types import PoseTrajectory

__all__ = ["write_deployment", "DEPLOYMENT_FILES", "format_dms"]

#: Files :func:`write_deployment` always writes (plus one ``prism<k>.csv`` per station).
DEPLOYMENT_FILES = ("GCP.txt", "calibration_raw.csv", "weather.csv", "truth.tum",
                    "truth_prisms.csv", "truth.json", "deployment.toml")

GCP_HEADER = ("theodolite_number , marker_number , status , elevation , azimuth , distance , "
              "sec , nsec")

_UNITS_PER_ARCSEC = 10**10  # DMS seconds written with 10 decimals


def format_dms(angle_rad: float, pad_degrees: bool = True) -> str:
    """Angle (rad, >= 0) as ``"d m s.ssssssssss"`` (degrees, minutes, seconds).

    Computed in integer units of 1e-10 arcsec, so that no ``60`` seconds or minutes can appear.
    ``pad_degrees`` writes the degrees on at least two digits (``00 00 16.0...``), as the real
    ``calibration_raw.csv`` does for the angles (its sigmas have unpadded degrees).
    """
    angle = float(angle_rad)
    if not np.isfinite(angle) or angle < 0:
        raise ValueError(f"Expected a finite angle >= 0, got {angle!r}")
    units = round(np.degrees(angle) * 3600.0 * _UNITS_PER_ARCSEC)
    deg, rem = divmod(units, 3600 * _UNITS_PER_ARCSEC)
    minutes, rem = divmod(rem, 60 * _UNITS_PER_ARCSEC)
    sec, frac = divmod(rem, _UNITS_PER_ARCSEC)
    d = f"{deg:02d}" if pad_degrees else f"{deg:d}"
    return f"{d} {minutes:02d} {sec:02d}.{frac:010d}"


def _rows(columns, sep: str = " ") -> str:
    """Rows of floats at full precision (shortest round-trip repr), newline-terminated."""
    return table_text(np.column_stack([np.asarray(c, dtype=float) for c in columns]), sep=sep)


def _prism_text(obs) -> str:
    return _rows([obs.t, obs.d, obs.v, obs.hz])


def _gcp_text(gcp) -> str:
    t = np.asarray(gcp.t, dtype=float)
    sec = np.floor(t).astype(np.int64)
    nsec = np.rint((t - sec) * 1e9).astype(np.int64)
    carry = nsec >= 1_000_000_000
    sec, nsec = sec + carry, np.where(carry, nsec - 1_000_000_000, nsec)
    lines = [GCP_HEADER]
    for st, mk, status, v, hz, d, s, ns in zip(
        gcp.station.tolist(), gcp.marker.tolist(), gcp.status.tolist(), gcp.v.tolist(),
        gcp.hz.tolist(), gcp.d.tolist(), sec.tolist(), nsec.tolist(), strict=True,
    ):
        lines.append(" , ".join([st, mk, str(status), repr(v), repr(hz), repr(d), str(s),
                                 str(ns)]))
    return "\n".join(lines) + "\n"


def _survey_text(survey) -> str:
    lines = []
    for hz, shz, v, sv, d, sd in zip(survey.hz.tolist(), survey.sigma_hz.tolist(),
                                     survey.v.tolist(), survey.sigma_v.tolist(),
                                     survey.d.tolist(), survey.sigma_d.tolist(), strict=True):
        lines.append(" ".join([format_dms(hz), format_dms(shz, False), format_dms(v),
                               format_dms(sv, False), repr(d), repr(sd), "0"]))
    return "\n".join(lines) + "\n"


def _weather_text(weather) -> str:
    return "t_s,temperature_c,pressure_hpa,humidity_pct\n" + _rows(
        [weather.t, weather.temperature_c, weather.pressure_hpa, weather.humidity_pct], ",")


def _tum_text(truth) -> str:
    R, p = truth.model.robot_at(truth.t)
    return tum_text(PoseTrajectory(truth.t, p, matrix_to_quat_xyzw(R)))


def _truth_prisms_text(truth) -> str:
    n, p, _ = truth.prisms_world.shape
    t = np.repeat(truth.t, p).tolist()
    pid = list(truth.prism_ids) * n
    xyz = truth.prisms_world.reshape(-1, 3).tolist()
    return "t_s,prism,x_m,y_m,z_m\n" + "".join([
        f"{ti!r},{k},{x!r},{y!r},{z!r}\n" for ti, k, (x, y, z) in zip(t, pid, xyz, strict=True)
    ])


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    return x


def _truth_json(sim: SimulatedDeployment, name: str) -> str:
    tr = sim.truth
    stations = {}
    for sid, T in tr.T_world_station.items():
        o = tr.observations[sid]
        stations[sid] = {
            "prism": tr.station_prism[sid],
            "file": f"prism{tr.station_prism[sid]}.csv",
            "T_world_station": T.as_matrix().tolist(),
            "yaw_deg": float(np.degrees(np.arctan2(T.rotation[1, 0], T.rotation[0, 0]))),
            "translation_m": T.translation.tolist(),
            "clock_offset_s": tr.clock_offset_s[sid],
            "measurements": len(o.t_true),
            "outliers": int(np.count_nonzero(o.outlier)),
            "range_m": [float(o.d.min() + tr.additive_constant),
                        float(o.d.max() + tr.additive_constant)] if len(o.d) else None,
        }
    ref = tr.reference_body
    pairs = {f"d{i + 1}{j + 1}": float(np.linalg.norm(ref[i] - ref[j]))
             for i in range(len(ref)) for j in range(i + 1, len(ref))}
    doc = {
        "name": name,
        "generator": f"rtsgt {__version__} rtsgt.simulation.simulate_deployment",
        "seed": sim.seed,
        "conventions": {
            "time": "Unix s; truth in true time; a station stamps t_recorded = t_true - "
                    "clock_error, clock_error = clock_offset_s + jitter",
            "world": "frame of station 1 (levelled, tracking convention x = d sinV sinHz, "
                     "y = d sinV cosHz, z = d cosV)",
            "body": "manual-shot frame of the survey station at the static survey "
                    "(x = d cosHz sinV, y = -d sinHz sinV, z = d cosV), attached to the robot; "
                    "truth.body is T_world_body",
            "robot": "x forward, y left, z terrain normal, origin on the ground under the "
                     "robot centre; truth.tum is T_world_robot, the frame of the deployment's "
                     "ground truth (T_survey_body = T_body_robot in deployment.toml)",
            "distances": "files hold raw distances at the reference atmosphere (0 ppm) without "
                         "the additive constant: true = (d + additive_constant_m)(1 + ppm 1e-6)",
            "matrices": "4x4 homogeneous, row-major, T_a_b maps frame b into frame a",
        },
        "t_start_s": float(sim.config.start_time_s),
        "t_end_s": float(sim.config.start_time_s + sim.config.duration_s),
        "additive_constant_m": tr.additive_constant,
        "instrument": sim.config.instrument.name,
        "stations": stations,
        "reference_prisms_body_m": {pid: ref[i].tolist() for i, pid in enumerate(tr.prism_ids)},
        "reference_distances_m": pairs,
        "gnss_body_m": {str(i + 1): p.tolist() for i, p in enumerate(tr.gnss_body)},
        "survey_rows": list(sim.survey.names),
        "T_body_robot": tr.T_body_robot.as_matrix().tolist(),
        "prisms_robot_m": {pid: tr.model.prisms_robot[i].tolist()
                           for i, pid in enumerate(tr.prism_ids)},
        "gcp_world_m": {m: tr.gcp_world[i].tolist() for i, m in enumerate(tr.gcp_markers)},
        "noise_sources": list(sim.config.noise_sources),
        "config": asdict(sim.config),
    }
    # the reality effects (rtsgt.simulation.reality) appear only when one is on, so that a
    # deployment without them is written as before, byte for byte
    del doc["config"]["reality"]
    if tr.reality is not None:
        doc["reality_effects"] = tr.reality.to_dict()
    # the same for the far stations and the field effects (rtsgt.simulation.field)
    del doc["config"]["field"]
    if not sim.config.far_stations:
        del doc["config"]["far_stations"], doc["config"]["far_distance_m"]
    if tr.field is not None:
        doc["field"] = tr.field.to_dict()
        doc["field"]["displaced_prism"]["prism"] = tr.prism_ids[tr.field.displaced_prism]
        doc["field"]["displaced_prism"]["surveyed_body_m"] = (
            tr.reference_body[tr.field.displaced_prism] - tr.field.displacement_body_m).tolist()
    return json.dumps(_jsonable(doc), indent=2) + "\n"


def _toml_str(s: str) -> str:
    return json.dumps(str(s))  # a TOML basic string for the plain names used here


def _toml_text(sim: SimulatedDeployment, name: str) -> str:
    cfg = sim.config
    c = repr(float(sim.truth.additive_constant))
    out = [
        "# rtsgt deployment configuration (paths relative to this file)",
        f"# simulated by rtsgt {__version__}; truth in truth.tum, truth_prisms.csv, truth.json",
        "[deployment]",
        f"name = {_toml_str(name)}",
        'reference_station = "1"',
        "",
        "[instrument]",
        f"profile = {_toml_str(cfg.instrument.name)}",
        "",
    ]
    for obs in sim.observations:
        out += [
            "[[stations]]",
            f"id = {_toml_str(obs.station)}",
            f"prism = {_toml_str(obs.prism)}",
            f'file = "prism{obs.prism}.csv"',
            'format = "rts-project"',
            f"additive_constant_m = {c}",
            "",
        ]
    prisms = ", ".join(f"{_toml_str(p)} = {i + 1}" for i, p in enumerate(sim.truth.prism_ids))
    sources = ", ".join(_toml_str(s) for s in cfg.noise_sources)
    # the fastest a prism can move (body speed, plus the lever arm turning at the tightest
    # radius) seen from the closest a station stands to the path, with a factor 2 of margin
    lever = max(float(np.linalg.norm(r)) for r in cfg.prism_positions_robot_m)
    v_max = cfg.speed_max_m_s * (1.0 + lever / cfg.min_turn_radius_m)
    tau_r = round(max(2.0, 2.0 * v_max), 3)
    tau_ang = round(max(1.0, float(np.degrees(2.0 * v_max / cfg.station_clearance_m))), 3)
    out += [
        "[gcp]",
        'file = "GCP.txt"',
        'format = "rts-project"',
        f"additive_constant_m = {c}",
        "",
        "[weather]",
        'file = "weather.csv"',
        'format = "csv"',
        "",
        "[reference]",
        'file = "calibration_raw.csv"',
        'format = "survey-dms"',
        f"prisms = {{ {prisms} }}   # prism id -> 1-based row in the survey file",
        "# ground truth in the robot frame, placed in the survey frame by T_body_robot",
        'body_frame = "transform"',
        "T_survey_body = [" + ", ".join(
            "[" + ", ".join(repr(float(x)) for x in row) + "]"
            for row in sim.truth.T_body_robot.as_matrix()) + "]",
        "# the point the vehicle rocks about: the robot's origin, on the ground (survey frame)",
        "rocking_pivot = [" + ", ".join(
            repr(float(x)) for x in sim.truth.T_body_robot.translation) + "]",
        "",
        "[noise]",
        f"sources = [{sources}]",
        f"time_sync_mean_s = {float(cfg.time_sync_mean_s)!r}",
        f"time_sync_std_s = {float(cfg.time_sync_std_s)!r}",
        "",
        "[filter]",
        "# rate gates from the simulated robot's limits: the paper's 1 deg/s (a slow robot, far",
        "# stations) would reject true motion here; see rtsgt's docs/filtering.md, Module 1",
        f"tau_r_m_s = {tau_r!r}",
        f"tau_a_deg_s = {tau_ang!r}",
        f"tau_e_deg_s = {tau_ang!r}",
        "tau_s_s = 3.0",
        "tau_l_s = 2.0",
        "",
        "[interpolation]",
        "rate_hz = 5.0",
        'qc = "loo"',
        "max_gap_s = 3.0",
        "",
        "[pose]",
        'engine = "mc"',
        "samples = 1000",
        "distance_gate_m = 0.10",
        "uncertainty_gate_m = 0.20",
    ]
    return "\n".join(out) + "\n"


def write_deployment(
    sim: SimulatedDeployment, out_dir: str | os.PathLike, *, overwrite: bool = False,
    name: str | None = None,
) -> Path:
    """Write ``sim`` into ``out_dir``; returns ``out_dir / "deployment.toml"``.

    ``name`` defaults to ``"sim-seed-<seed>"``. InputError when ``out_dir`` is a file, a non-empty
    directory (without ``overwrite``) or holds files rtsgt did not write.
    """
    if not isinstance(sim, SimulatedDeployment):
        raise ValueError(f"Expected a SimulatedDeployment, got {type(sim).__name__}")
    out_dir = Path(out_dir)
    output = OutputDir(out_dir, "deployment", force=overwrite)  # checks out_dir before any work
    if name is None:
        name = "sim" if sim.seed is None else f"sim-seed-{sim.seed}"

    texts = {f"prism{obs.prism}.csv": _prism_text(obs) for obs in sim.observations}
    texts["GCP.txt"] = _gcp_text(sim.gcp)
    texts["calibration_raw.csv"] = _survey_text(sim.survey)
    texts["weather.csv"] = _weather_text(sim.weather_reported)
    texts["truth.tum"] = _tum_text(sim.truth)
    texts["truth_prisms.csv"] = _truth_prisms_text(sim.truth)
    texts["truth.json"] = _truth_json(sim, name)
    texts["deployment.toml"] = _toml_text(sim, name)

    with output as tmp:
        for fname, text in texts.items():
            with open(tmp / fname, "w", encoding="utf-8", newline="\n") as fh:
                fh.write(text)
    return out_dir / "deployment.toml"
