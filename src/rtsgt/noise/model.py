"""The per-measurement noise model shared by the two engines: parameters and nominal values.

Owns :class:`NoiseModel` (which sources, their parameters), the validation of observations,
the prism velocity the clock error acts along, and the nominal quantities both engines start
from. The model: docs/noise-model.md#the-perturbed-measurement.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError
from rtsgt.measurement.atmosphere import VAPOUR_FORMULAS, instrument_correction_ppm
from rtsgt.measurement.instruments import InstrumentProfile
from rtsgt.measurement.polar import polar_to_cartesian
from rtsgt.noise.sources import NOISE_SOURCES

__all__ = ["NOISE_SOURCES", "NoiseModel", "prism_velocity", "check_strictly_increasing"]


@dataclass(frozen=True)
class NoiseModel:
    """Which noise sources to propagate, and their parameters (docs/noise-model.md).

    ``instrument``: the station's accuracies and EDM reference atmosphere; ``sources``: a
    subset of :data:`rtsgt.noise.sources.NOISE_SOURCES`, kept in its order;
    ``time_sync_mean_s``, ``time_sync_std_s``: of the clock error's magnitude, s (the authors'
    values); the weather errors' uniform half-widths, degC, hPa, %; the ``vapour_formula``
    "magnus" or "buck"; ``max_velocity_gap_s``: the longest gap a velocity differences, s.
    """

    instrument: InstrumentProfile
    sources: tuple[str, ...] = NOISE_SOURCES
    time_sync_mean_s: float = 1.157e-3
    time_sync_std_s: float = 0.815e-3
    temperature_halfwidth_c: float = 1.0
    pressure_halfwidth_hpa: float = 10.0
    humidity_halfwidth_pct: float = 2.0
    vapour_formula: str = "magnus"
    max_velocity_gap_s: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.instrument, InstrumentProfile):
            raise InputError(
                f"Expected an InstrumentProfile, got {type(self.instrument).__name__}"
            )
        srcs = (self.sources,) if isinstance(self.sources, str) else tuple(self.sources)
        unknown = [s for s in srcs if s not in NOISE_SOURCES]
        if unknown:
            raise InputError(
                f"Unknown noise source(s) {', '.join(map(repr, unknown))}; "
                f"known: {', '.join(NOISE_SOURCES)}"
            )
        if len(set(srcs)) != len(srcs):
            raise InputError(f"Expected distinct noise sources, got {srcs}")
        object.__setattr__(self, "sources", tuple(s for s in NOISE_SOURCES if s in srcs))
        for name in (
            "time_sync_mean_s", "time_sync_std_s", "temperature_halfwidth_c",
            "pressure_halfwidth_hpa", "humidity_halfwidth_pct",
        ):
            val = getattr(self, name)
            if isinstance(val, bool) or not np.isfinite(val) or val < 0:
                raise InputError(f"Expected {name} >= 0, got {val!r}")
            object.__setattr__(self, name, float(val))
        if not self.max_velocity_gap_s > 0:
            raise InputError(f"Expected max_velocity_gap_s > 0, got {self.max_velocity_gap_s!r}")
        f = str(self.vapour_formula).lower()
        if f not in VAPOUR_FORMULAS:
            raise InputError(
                f"Unknown vapour_formula {self.vapour_formula!r}; known: {', '.join(VAPOUR_FORMULAS)}"
            )
        object.__setattr__(self, "vapour_formula", f)

    def with_sources(self, sources) -> NoiseModel:
        """A copy restricted to (or extended with) ``sources`` (a name or an iterable)."""
        srcs = (sources,) if isinstance(sources, str) else tuple(sources)
        return replace(self, sources=srcs)

    @property
    def time_sync_second_moment_s2(self) -> float:
        """``E[e_ts^2] = mu^2 + sigma^2`` (s^2), the variance of the zero-mean clock error."""
        return self.time_sync_mean_s**2 + self.time_sync_std_s**2

    @property
    def weather_variances(self) -> tuple[float, float, float]:
        """Variances of the uniform weather errors, ``h^2 / 3`` (degC^2, hPa^2, %^2)."""
        return (
            self.temperature_halfwidth_c**2 / 3.0,
            self.pressure_halfwidth_hpa**2 / 3.0,
            self.humidity_halfwidth_pct**2 / 3.0,
        )


def check_strictly_increasing(t: np.ndarray, source: str | None = None) -> None:
    """Raise :class:`InputError` at the first time that does not increase strictly."""
    t = np.asarray(t, dtype=float)
    bad = ~np.isfinite(t)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise InputError(f"Expected finite times, got t[{i}] = {float(t[i])!r}", source)
    if t.shape[0] > 1:
        dt = np.diff(t)
        if np.any(dt <= 0):
            i = int(np.argmax(dt <= 0)) + 1
            what = "duplicated" if dt[i - 1] == 0 else "decreasing"
            raise InputError(
                f"Expected strictly increasing times, got {what} t[{i}] = {float(t[i])!r} after "
                f"t[{i - 1}] = {float(t[i - 1])!r}; sort the observations by time and drop repeated "
                "time stamps before propagating",
                source,
            )


def prism_velocity(
    t: ArrayLike, xyz: ArrayLike, max_gap_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Velocity (N, 3), m/s, of a prism at times ``t`` (N,), s, strictly increasing, from its
    positions ``xyz`` (N, 3), m (any frame): central differences, one-sided at a block's end,
    never across a gap over ``max_gap_s``; and ``valid`` (N,) (False, ``v = 0``: isolated)
    (docs/noise-model.md#time-synchronisation). Raises :class:`InputError` for bad shapes or
    times.
    """
    t = np.asarray(t, dtype=float)
    p = np.asarray(xyz, dtype=float)
    if t.ndim != 1:
        raise InputError(f"Expected t of shape (N,), got {t.shape}")
    n = t.shape[0]
    if p.shape != (n, 3):
        raise InputError(f"Expected xyz of shape ({n}, 3), got {p.shape}")
    if not max_gap_s > 0:
        raise InputError(f"Expected max_gap_s > 0, got {max_gap_s!r}")
    check_strictly_increasing(t)
    v = np.zeros((n, 3))
    valid = np.zeros(n, dtype=bool)
    if n < 2:
        return v, valid
    idx_prev, idx_next, _ = difference_stencil(t, max_gap_s)
    valid = idx_prev != idx_next
    dt = t[idx_next] - t[idx_prev]
    safe = np.where(valid, dt, 1.0)
    v = (p[idx_next] - p[idx_prev]) / safe[:, None]
    v[~valid] = 0.0
    return v, valid


def difference_stencil(t: np.ndarray, max_gap_s: float):
    """Indices ``(prev, next)`` of the difference used at each time, and ``dt`` (internal).

    ``prev == next`` marks an isolated measurement.
    """
    n = t.shape[0]
    i = np.arange(n)
    gap = np.diff(t)
    ok_prev = np.zeros(n, dtype=bool)
    ok_next = np.zeros(n, dtype=bool)
    ok_prev[1:] = gap <= max_gap_s
    ok_next[:-1] = gap <= max_gap_s
    idx_prev = np.where(ok_prev, i - 1, i)
    idx_next = np.where(ok_next, i + 1, i)
    return idx_prev, idx_next, t[idx_next] - t[idx_prev]


# --------------------------------------------------------------------------------------------
# Nominal values shared by both engines
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Nominal:
    """Validated nominal quantities of one set of observations (internal to the engines).

    All arrays have N rows; angles in rad, lengths in m, the station frame of the
    measuring station.
    """

    t: np.ndarray
    hz: np.ndarray
    v: np.ndarray
    d: np.ndarray  # slope distance with the additive constant, before the atmospheric correction
    temperature_c: np.ndarray
    pressure_hpa: np.ndarray
    humidity_pct: np.ndarray
    ppm: np.ndarray  # nominal first-velocity correction K
    d_corr: np.ndarray  # d (1 + 1e-6 ppm)
    xyz_station: np.ndarray  # (N, 3)
    velocity: np.ndarray  # (N, 3) station frame, zero where invalid
    velocity_valid: np.ndarray  # (N,)
    R: np.ndarray  # (3, 3) R_world_station
    t_ws: np.ndarray  # (3,) t_world_station
    frame: str


def _bad_index(mask: np.ndarray) -> int:
    return int(np.argmax(mask))


def validate_observations(obs) -> None:
    """Raise :class:`InputError` naming the first bad value: NaN or negative distances, zenith
    angles outside (0, pi), non-finite directions, invalid status, non-increasing times."""
    src = getattr(obs, "source", None)
    n = len(obs)
    if n == 0:
        raise InputError("Expected at least one observation, got none", src)
    d = np.asarray(obs.d, dtype=float)
    bad = ~np.isfinite(d)
    if np.any(bad):
        i = _bad_index(bad)
        raise InputError(f"Expected finite distances, got d[{i}] = {float(d[i])!r}", src)
    bad = d < 0
    if np.any(bad):
        i = _bad_index(bad)
        raise InputError(f"Expected non-negative distances, got d[{i}] = {float(d[i])!r} m", src)
    dc = d + float(obs.additive_constant)
    bad = dc <= 0
    if np.any(bad):
        i = _bad_index(bad)
        raise InputError(
            f"Expected positive distances after the additive constant, got d[{i}] + "
            f"{obs.additive_constant!r} = {float(dc[i])!r} m", src,
        )
    v = np.asarray(obs.v, dtype=float)
    bad = ~np.isfinite(v) | (v <= 0) | (v >= np.pi)
    if np.any(bad):
        i = _bad_index(bad)
        raise InputError(
            f"Expected zenith angles in (0, pi) rad, got v[{i}] = {float(v[i])!r} rad; V is the zenith "
            "angle (pi/2 = horizontal), not an elevation", src,
        )
    hz = np.asarray(obs.hz, dtype=float)
    bad = ~np.isfinite(hz)
    if np.any(bad):
        i = _bad_index(bad)
        raise InputError(f"Expected finite horizontal directions, got hz[{i}] = {float(hz[i])!r}", src)
    status = np.asarray(obs.status)
    bad = status != 0
    if np.any(bad):
        i = _bad_index(bad)
        raise InputError(
            f"Observation {i} has instrument status {status[i]} (0 = valid); keep the valid "
            "ones first, e.g. obs.select(obs.status == 0)", src,
        )
    check_strictly_increasing(obs.t, src)


def prepare_nominal(obs, model: NoiseModel, T_world_station=None, weather=None) -> Nominal:
    """Validate the inputs and compute the nominal quantities both engines start from.

    Without ``weather`` the atmosphere is the instrument's reference atmosphere (0 ppm); the
    ``atmosphere`` source then still accounts for the unknown weather within the half-widths.
    """

    validate_observations(obs)
    src = getattr(obs, "source", None)
    prof = model.instrument
    n = len(obs)
    t = np.asarray(obs.t, dtype=float)
    if weather is None:
        temp = np.full(n, float(prof.reference_temperature_c))
        pres = np.full(n, float(prof.reference_pressure_hpa))
        hum = np.full(n, float(prof.reference_humidity_pct))
    else:
        temp, pres, hum = (np.asarray(a, dtype=float) for a in weather.at(t))
        wsrc = getattr(weather, "source", None)
        for name, a, lo, hi in (
            ("temperature_c", temp, -80.0, 70.0),
            ("pressure_hpa", pres, 300.0, 1200.0),
            ("humidity_pct", hum, 0.0, 100.0),
        ):
            bad = ~np.isfinite(a) | (a < lo) | (a > hi)
            if np.any(bad):
                i = _bad_index(bad)
                raise InputError(
                    f"Expected weather {name} in [{lo}, {hi}] at the observation times, got "
                    f"{float(a[i])!r} at t = {float(t[i])!r} (observation {i})", wsrc,
                )
    ppm = np.asarray(
        instrument_correction_ppm(prof, temp, pres, hum, model.vapour_formula), dtype=float
    )
    if weather is None:
        ppm = np.zeros(n)  # exactly the reference atmosphere
    d = np.asarray(obs.d, dtype=float) + float(obs.additive_constant)
    d_corr = d * (1.0 + 1e-6 * ppm)
    hz = np.asarray(obs.hz, dtype=float)
    v = np.asarray(obs.v, dtype=float)
    xyz = polar_to_cartesian(hz, v, d_corr)
    if "time_sync" in model.sources:
        vel, valid = prism_velocity(t, xyz, model.max_velocity_gap_s)
    else:
        vel, valid = np.zeros((n, 3)), np.zeros(n, dtype=bool)
    if T_world_station is None:
        R, tws, frame = np.eye(3), np.zeros(3), f"station_{obs.station}"
    else:
        R = np.asarray(T_world_station.rotation, dtype=float)
        tws = np.asarray(T_world_station.translation, dtype=float)
        frame = T_world_station.frame_to
    del src
    return Nominal(t, hz, v, d, temp, pres, hum, ppm, d_corr, xyz, vel, valid, R, tws, frame)
