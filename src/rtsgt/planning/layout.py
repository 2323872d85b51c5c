"""A deployment's layout as ``rtsgt plan`` sees it: stations, GCPs, the rig, the calibration.

:func:`layout_from_deployment` takes an existing deployment (the run's own calibration of its
GCP shots, its survey as the rig, each station's median tracking rate);
:func:`layout_from_positions` a layout on paper (noise-free synthetic shots of every marker by
every station, :func:`synthetic_gcp_shots`, the same calibration; the world frame the
reference station's, :attr:`Layout.origin`). Reads no files. docs/planning.md#the-layout.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.calibration import CalibrationResult
from rtsgt.calibration.gcp import gcp_world_positions
from rtsgt.calibration.shots import curvature_tilt
from rtsgt.deployment import DeploymentData
from rtsgt.errors import InputError
from rtsgt.geometry.so3 import exp_so3
from rtsgt.measurement.instruments import InstrumentProfile
from rtsgt.measurement.polar import cartesian_to_polar
from rtsgt.noise import NoiseModel
from rtsgt.noise.coupling import StationCoupling
from rtsgt.options import RunOptions
from rtsgt.pipeline import calibrate_stations, noise_model
from rtsgt.pose import ReferencePoints
from rtsgt.types import GcpShots

__all__ = ["DEFAULT_RATE_HZ", "Layout", "PlannedStation", "layout_from_deployment",
           "layout_from_positions", "synthetic_gcp_shots"]

#: Measurement rate of a tracking station when the plan does not say, Hz (the Trimble S7's
#: tracking rate in the paper's deployments, and the simulator's default).
DEFAULT_RATE_HZ = 2.5


@dataclass(frozen=True)
class PlannedStation:
    """A station of a layout on paper: instrument position ``xyz`` (m, the plan's levelled
    frame), the ``prism`` it tracks (None: it only shoots the markers) and its ``rate_hz``."""

    xyz: tuple[float, float, float]
    prism: str | None = None
    rate_hz: float = DEFAULT_RATE_HZ


@dataclass(frozen=True)
class Layout:
    """Everything a plan needs of a deployment's layout: the tracking ``stations`` with their
    ``prisms`` and ``rate_hz``, the ``calibration`` (every station's ``T_world_station``, samples
    and covariance) and its ``coupling``, the markers ``gcp_xyz`` (K, 3; world, m) and
    ``gcp_names``, the rig ``reference`` (body frame, in the order of ``prisms``), the run
    ``options`` (noise model never None), the plan coordinates ``origin`` (3,) of the world
    origin (plan = world + origin) and the ``source`` in words."""

    name: str
    stations: tuple[str, ...]
    prisms: tuple[str, ...]
    rate_hz: tuple[float, ...]
    calibration: CalibrationResult
    coupling: StationCoupling
    gcp_xyz: np.ndarray
    gcp_names: tuple[str, ...]
    reference: ReferencePoints
    options: RunOptions
    origin: np.ndarray
    source: str

    @property
    def model(self) -> NoiseModel:
        """The noise model of every measurement."""
        return self.options.noise

    @property
    def instrument(self) -> InstrumentProfile:
        return self.options.noise.instrument

    def station_xyz(self, plan_frame: bool = True) -> dict[str, np.ndarray]:
        """Position of every station (tracking or not), m: plan coordinates, or world."""
        off = self.origin if plan_frame else np.zeros(3)
        return {s: np.asarray(T.translation, dtype=float) + off
                for s, T in self.calibration.transforms.items()}

    def markers_per_station(self) -> dict[str, int]:
        """Markers each non-reference station shares with the reference in its fit."""
        ref = self.calibration.reference_station
        return {s: len(m) for s, m in self.calibration.markers_used.items() if s != ref}


def _check_tracking(stations: Sequence[str], prisms: Sequence[str],
                    reference: ReferencePoints) -> ReferencePoints:
    if len(stations) < 3:
        raise InputError(f"a pose needs three tracking stations, got {len(stations)}")
    if len(set(prisms)) != len(prisms):
        raise InputError(f"each station must track a different prism, got {list(prisms)}")
    missing = [p for p in prisms if p not in reference.names]
    if missing:
        raise InputError(f"no position on the robot for prism(s) {', '.join(missing)}; "
                         f"the rig has {', '.join(reference.names)}")
    return reference.select(list(prisms))


def _layout(name: str, data: DeploymentData, options: RunOptions, stations, prisms, rates,
            t_start: float, origin: np.ndarray, source: str) -> Layout:
    options = options.updated(noise=noise_model(data, options))
    reference = _check_tracking(stations, prisms, data.reference)
    calib = calibrate_stations(data, options, t_start)
    missing = [s for s in stations if s not in calib.transforms]
    if missing:
        raise InputError(f"station(s) {', '.join(missing)} track a prism but have no GCP "
                         "calibration")
    xyz, names = gcp_world_positions(data.gcp, calib.transforms)
    return Layout(name, tuple(stations), tuple(prisms), tuple(float(r) for r in rates), calib,
                  StationCoupling.from_calibration(calib),
                  np.zeros((0, 3)) if xyz is None else xyz, names, reference, options,
                  np.asarray(origin, dtype=float), source)


def layout_from_deployment(data: DeploymentData, options: RunOptions,
                           source: str = "deployment") -> Layout:
    """The layout of an existing deployment ``data`` (as :func:`rtsgt.io.deployment.load_deployment`
    reads it) with its run ``options`` (noise model, calibration and its Monte Carlo, GP,
    registration); ``source`` names it in the plan's outputs."""
    stations = [o.station for o in data.observations]
    prisms = [o.prism for o in data.observations]
    rates = []
    for o in data.observations:
        dt = np.diff(np.asarray(o.t, dtype=float))
        dt = dt[dt > 0]
        if dt.size == 0:
            raise InputError(f"station {o.station}: too few measurements for a rate", o.source)
        rates.append(1.0 / float(np.median(dt)))
    t_start = min(float(o.t[0]) for o in data.observations)
    return _layout(data.name, data, options, stations, prisms, rates, t_start, np.zeros(3),
                   source)


def synthetic_gcp_shots(station_xyz: Mapping[str, ArrayLike], gcp_xyz: ArrayLike,
                        gcp_names: Sequence[str]) -> GcpShots:
    """Noise-free shots of every marker ``gcp_xyz`` (K, 3; world, m) by every station
    (``station_xyz``: name -> (3,), world, the reference at the origin): station-major, additive
    constant 0, each station levelled (vertical turned by
    :func:`rtsgt.calibration.gcp.curvature_tilt`) with ``Hz = 0`` along world +y."""
    g = np.asarray(gcp_xyz, dtype=float).reshape(-1, 3)
    station, marker, hz, v, d = [], [], [], [], []
    for s, p in station_xyz.items():  # a handful of stations
        t = np.asarray(p, dtype=float)
        R = exp_so3(curvature_tilt(t))
        h, vv, dd = cartesian_to_polar((g - t) @ R)  # rows R^T (g - t)
        station += [s] * g.shape[0]
        marker += list(gcp_names)
        hz.append(h)
        v.append(vv)
        d.append(dd)
    return GcpShots(np.array(station), np.array(marker), np.concatenate(hz), np.concatenate(v),
                    np.concatenate(d), source="planned markers")


def layout_from_positions(
    name: str, stations: Mapping[str, PlannedStation], gcp_xyz: ArrayLike,
    reference: ReferencePoints, options: RunOptions, *, reference_station: str,
    instrument: InstrumentProfile, gcp_names: Sequence[str] | None = None,
    source: str = "planned positions",
) -> Layout:
    """A layout on paper: ``stations`` (name -> PlannedStation, plan coordinates, z up, m), the
    markers ``gcp_xyz`` (K, 3; named ``gcp_names``, default "1", "2", ...), the rig
    ``reference`` (body frame, by prism), the run ``options`` (``noise`` None: every source),
    the ``reference_station`` whose frame is the world's and the ``instrument`` of every station."""
    if reference_station not in stations:
        raise InputError(f"reference station {reference_station!r} is not among the stations "
                         f"({', '.join(stations)})")
    origin = np.asarray(stations[reference_station].xyz, dtype=float)
    g = np.asarray(gcp_xyz, dtype=float).reshape(-1, 3)
    names = tuple(str(i + 1) for i in range(g.shape[0])) if gcp_names is None else \
        tuple(gcp_names)
    shots = synthetic_gcp_shots({s: np.asarray(st.xyz, dtype=float) - origin
                                 for s, st in stations.items()}, g - origin, names)
    data = DeploymentData(name, instrument, (), shots, reference, reference_station)
    tracking = [s for s, st in stations.items() if st.prism is not None]
    return _layout(name, data, options, tracking, [stations[s].prism for s in tracking],
                   [stations[s].rate_hz for s in tracking], 0.0, origin, source)
