"""The typed records of measured data that flow through the pipeline (docs/conventions.md).

float64 arrays; seconds (Unix epoch where the input has it), metres, radians, covariances in
m^2 and, for poses, 6x6 in the order (x, y, z, rx, ry, rz) of :mod:`rtsgt.geometry.transform`.
Each record checks its shapes at construction and is immutable (read-only arrays).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from rtsgt.errors import InputError
from rtsgt.geometry.so3 import quat_xyzw_to_matrix
from rtsgt.measurement.polar import survey_polar_jacobian, survey_polar_to_cartesian


def _frozen(a, dtype=float) -> np.ndarray:
    a = np.array(a, dtype=dtype, copy=True)
    a.setflags(write=False)
    return a


def _check_len(name: str, a: np.ndarray, n: int, where: str | None) -> None:
    if a.shape[0] != n:
        raise InputError(f"Expected {n} values of {name}, got {a.shape[0]}", where)


@dataclass(frozen=True)
class Observations:
    """Polar observations of one prism by one station, in time order.

    ``t`` (N,) s (Unix epoch); ``hz`` (N,) clockwise horizontal direction and ``v`` (N,) zenith
    angle, rad; ``d`` (N,) slope distance as measured, m, **without** ``additive_constant`` (m,
    0.01 for RTS_project); ``status`` (N,) int, 0 valid; ``station``, ``prism`` identifiers;
    ``source`` the file (for messages).
    """

    t: np.ndarray
    hz: np.ndarray
    v: np.ndarray
    d: np.ndarray
    status: np.ndarray | None = None
    station: str = "1"
    prism: str = "1"
    additive_constant: float = 0.0
    source: str | None = None

    def __post_init__(self) -> None:
        t = _frozen(self.t)
        n = t.shape[0] if t.ndim == 1 else -1
        if t.ndim != 1:
            raise InputError(f"Expected t of shape (N,), got {t.shape}", self.source)
        for name in ("hz", "v", "d"):
            a = _frozen(getattr(self, name))
            if a.ndim != 1:
                raise InputError(f"Expected {name} of shape (N,), got {a.shape}", self.source)
            _check_len(name, a, n, self.source)
            object.__setattr__(self, name, a)
        status = np.zeros(n, dtype=int) if self.status is None else self.status
        status = _frozen(status, dtype=int)
        _check_len("status", status, n, self.source)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "status", status)
        object.__setattr__(self, "station", str(self.station))
        object.__setattr__(self, "prism", str(self.prism))

    def __len__(self) -> int:
        return self.t.shape[0]

    @property
    def distance(self) -> np.ndarray:
        """Slope distance with the additive constant applied, m."""
        return self.d + self.additive_constant

    def select(self, mask: np.ndarray) -> Observations:
        """A new object holding the rows where ``mask`` is true (or at the given indices)."""
        return Observations(
            self.t[mask], self.hz[mask], self.v[mask], self.d[mask], self.status[mask],
            self.station, self.prism, self.additive_constant, self.source,
        )


@dataclass(frozen=True)
class PrismTrack:
    """Positions of one prism over time with a covariance each.

    ``t`` (N,) s, increasing; ``xyz`` (N, 3) m and ``cov`` (N, 3, 3) m^2 (total) in ``frame``
    (``"world"``: the common frame); ``cov_by_source`` each noise source's alone (N, 3, 3);
    ``prism``; ``station`` that measured it; ``range_m`` (N,) slope distance from it, m.
    """

    t: np.ndarray
    xyz: np.ndarray
    cov: np.ndarray
    cov_by_source: Mapping[str, np.ndarray] = field(default_factory=dict)
    prism: str = "1"
    frame: str = "world"
    station: str | None = None
    range_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = _frozen(self.t)
        n = t.shape[0]
        xyz = _frozen(self.xyz)
        cov = _frozen(self.cov)
        if t.ndim != 1:
            raise ValueError(f"Expected t of shape (N,), got {t.shape}")
        if xyz.shape != (n, 3):
            raise ValueError(f"Expected xyz of shape ({n}, 3), got {xyz.shape}")
        if cov.shape != (n, 3, 3):
            raise ValueError(f"Expected cov of shape ({n}, 3, 3), got {cov.shape}")
        by_source = {}
        for k, c in dict(self.cov_by_source).items():
            c = _frozen(c)
            if c.shape != (n, 3, 3):
                raise ValueError(f"Expected cov_by_source[{k!r}] of shape ({n}, 3, 3), got {c.shape}")
            by_source[k] = c
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "cov", cov)
        object.__setattr__(self, "cov_by_source", by_source)
        object.__setattr__(self, "prism", str(self.prism))
        if self.range_m is not None:
            r = _frozen(self.range_m)
            if r.shape != (n,):
                raise ValueError(f"Expected range_m of shape ({n},), got {r.shape}")
            object.__setattr__(self, "range_m", r)

    def __len__(self) -> int:
        return self.t.shape[0]

    def select(self, mask: np.ndarray) -> PrismTrack:
        """A new track holding the rows where ``mask`` is true (or at the given indices)."""
        return PrismTrack(
            self.t[mask], self.xyz[mask], self.cov[mask],
            {k: c[mask] for k, c in self.cov_by_source.items()},
            self.prism, self.frame, self.station,
            None if self.range_m is None else self.range_m[mask],
        )


@dataclass(frozen=True)
class WeatherSeries:
    """Weather over time for the atmospheric correction: ``t`` (N,) s (Unix epoch, UTC),
    ``temperature_c`` (N,) dry-bulb, degC; ``pressure_hpa`` (N,) station pressure, hPa;
    ``humidity_pct`` (N,) relative humidity, %; ``source``."""

    t: np.ndarray
    temperature_c: np.ndarray
    pressure_hpa: np.ndarray
    humidity_pct: np.ndarray
    source: str | None = None

    def __post_init__(self) -> None:
        t = _frozen(self.t)
        for name in ("temperature_c", "pressure_hpa", "humidity_pct"):
            a = _frozen(getattr(self, name))
            _check_len(name, a, t.shape[0], self.source)
            object.__setattr__(self, name, a)
        object.__setattr__(self, "t", t)
        if t.shape[0] == 0:
            raise InputError("Expected at least one weather record, got none", self.source)
        if np.any(np.diff(t) <= 0):
            raise InputError("Expected strictly increasing weather times", self.source)

    def at(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Temperature (degC), pressure (hPa), humidity (%) linearly interpolated at ``t``.

        Times before the first or after the last record take the nearest record's values.
        """
        t = np.asarray(t, dtype=float)
        return tuple(
            np.interp(t, self.t, a) for a in (self.temperature_c, self.pressure_hpa, self.humidity_pct)
        )


@dataclass(frozen=True)
class GcpShots:
    """Shots of ground control points (markers) by several stations.

    ``station``, ``marker`` (N,) str; ``hz``, ``v``, ``d`` (N,) polar measurements (rad, rad, m
    without ``additive_constant``), tracking convention; ``t`` (N,) s (may be wrong where a
    station's clock was off); ``status`` (N,) 0 valid; ``source``; ``lines`` (N,) the line of each
    shot in ``source``.
    """

    station: np.ndarray
    marker: np.ndarray
    hz: np.ndarray
    v: np.ndarray
    d: np.ndarray
    t: np.ndarray | None = None
    status: np.ndarray | None = None
    additive_constant: float = 0.0
    source: str | None = None
    lines: np.ndarray | None = None

    def __post_init__(self) -> None:
        station = _frozen(np.asarray(self.station).astype(str), dtype=object)
        n = station.shape[0]
        object.__setattr__(self, "station", station)
        object.__setattr__(self, "marker", _frozen(np.asarray(self.marker).astype(str), dtype=object))
        for name in ("hz", "v", "d"):
            a = _frozen(getattr(self, name))
            _check_len(name, a, n, self.source)
            object.__setattr__(self, name, a)
        object.__setattr__(self, "t", _frozen(np.full(n, np.nan) if self.t is None else self.t))
        object.__setattr__(
            self, "status", _frozen(np.zeros(n, int) if self.status is None else self.status, int)
        )
        if self.lines is not None:
            object.__setattr__(self, "lines", _frozen(self.lines, int))

    def __len__(self) -> int:
        return self.station.shape[0]

    @property
    def distance(self) -> np.ndarray:
        """Slope distance with the additive constant applied, m."""
        return self.d + self.additive_constant


@dataclass(frozen=True)
class PoseTrajectory:
    """Poses ``T_world_body`` over time: ``t`` (N,) s, ``position`` (N, 3) m, ``quat_xyzw``
    (N, 4) unit quaternions scalar last, ``cov`` (N, 6, 6) optional left-perturbation covariance,
    world frame."""

    t: np.ndarray
    position: np.ndarray
    quat_xyzw: np.ndarray
    cov: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = _frozen(self.t)
        n = t.shape[0]
        p = _frozen(self.position)
        q = _frozen(self.quat_xyzw)
        if p.shape != (n, 3):
            raise ValueError(f"Expected position of shape ({n}, 3), got {p.shape}")
        if q.shape != (n, 4):
            raise ValueError(f"Expected quat_xyzw of shape ({n}, 4), got {q.shape}")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "quat_xyzw", q)
        if self.cov is not None:
            c = _frozen(self.cov)
            if c.shape != (n, 6, 6):
                raise ValueError(f"Expected cov of shape ({n}, 6, 6), got {c.shape}")
            object.__setattr__(self, "cov", c)

    def __len__(self) -> int:
        return self.t.shape[0]

    @property
    def rotation(self) -> np.ndarray:
        """``R_world_body``, shape (N, 3, 3)."""

        return quat_xyzw_to_matrix(self.quat_xyzw)


@dataclass(frozen=True)
class PositionTrajectory:
    """Positions of one point (a prism) over time, a position-only ground truth: ``t`` (N,) s,
    ``position`` (N, 3) m, ``cov`` (N, 3, 3) m^2 optional, ``name`` (a prism id, a topic)."""

    t: np.ndarray
    position: np.ndarray
    cov: np.ndarray | None = None
    name: str = ""

    def __post_init__(self) -> None:
        t = _frozen(self.t)
        n = t.shape[0]
        p = _frozen(self.position)
        if t.ndim != 1:
            raise ValueError(f"Expected t of shape (N,), got {t.shape}")
        if p.shape != (n, 3):
            raise ValueError(f"Expected position of shape ({n}, 3), got {p.shape}")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "position", p)
        if self.cov is not None:
            c = _frozen(self.cov)
            if c.shape != (n, 3, 3):
                raise ValueError(f"Expected cov of shape ({n}, 3, 3), got {c.shape}")
            object.__setattr__(self, "cov", c)

    def __len__(self) -> int:
        return self.t.shape[0]

    def select(self, mask) -> PositionTrajectory:
        """The rows where ``mask`` is true (or at the given indices)."""
        return PositionTrajectory(self.t[mask], self.position[mask],
                                  None if self.cov is None else self.cov[mask], self.name)


@dataclass(frozen=True)
class SurveyShots:
    """Static survey of points on the robot by one station, in the manual-shot convention of
    ``calibration_raw.csv`` (:func:`rtsgt.measurement.polar.survey_polar_to_cartesian`).

    ``names`` (K,); ``hz``, ``v`` (K,) rad and ``d`` (K,) m with their standard deviations
    ``sigma_*``; ``source``; computed: ``xyz`` (K, 3) m and ``cov`` (K, 3, 3) m^2, the first-order
    ``J diag(s_hz^2, s_v^2, s_d^2) J^T``, points independent.
    """

    names: tuple[str, ...]
    hz: np.ndarray
    sigma_hz: np.ndarray
    v: np.ndarray
    sigma_v: np.ndarray
    d: np.ndarray
    sigma_d: np.ndarray
    source: str = ""
    xyz: np.ndarray = field(init=False, repr=False)
    cov: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        names = tuple(str(s) for s in self.names)
        object.__setattr__(self, "names", names)
        for name in ("hz", "sigma_hz", "v", "sigma_v", "d", "sigma_d"):
            a = _frozen(getattr(self, name))
            _check_len(name, a, len(names), self.source or None)
            object.__setattr__(self, name, a)
        J = survey_polar_jacobian(self.hz, self.v, self.d)
        var = np.stack([self.sigma_hz**2, self.sigma_v**2, self.sigma_d**2], axis=-1)
        object.__setattr__(self, "xyz", _frozen(survey_polar_to_cartesian(self.hz, self.v, self.d)))
        object.__setattr__(self, "cov", _frozen(np.einsum("kij,kj,klj->kil", J, var, J)))

    def __len__(self) -> int:
        return len(self.names)

    def cov_stacked(self) -> np.ndarray:
        """Covariance of the stacked points ``(x1, y1, z1, x2, ...)``, shape (3K, 3K)."""
        k = len(self)
        out = np.zeros((k, 3, k, 3))
        out[np.arange(k), :, np.arange(k), :] = self.cov
        return out.reshape(3 * k, 3 * k)

    def index(self, name: str) -> int:
        """0-based row of the point called ``name``."""
        if name not in self.names:
            raise InputError(
                f"Expected a point among {self.names}, got {name!r}", self.source or None
            )
        return self.names.index(name)
