r"""Reality effects: errors of a real deployment that the estimator's noise model does not have.

Drawn by formulas of their own (independent of :mod:`rtsgt.noise`), each switched by
:class:`RealityEffects` and off by default, acting on the measured angles and distances, the
time stamps, the reported weather and the station set-ups over time. One random stream per
effect (:func:`effect_rng`). Models, sizes and units: docs/simulation.md#the-effects.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.choices import REALITY_EFFECTS  # in the order of their streams (effect_rng)
from rtsgt.errors import InputError
from rtsgt.measurement.instruments import ARCSEC

__all__ = [
    "REALITY_EFFECTS",
    "RealityEffects",
    "RealityTruth",
    "clock_sawtooth",
    "effect_rng",
    "first_order_lag",
    "gauss_markov",
    "prism_cyclic_error",
    "remote_weather",
    "settling_fraction",
    "settle_points",
]

#: Standard gravity, m/s^2 (CGPM 1901).
G_M_S2 = 9.80665
#: Molar mass of dry air, kg/mol (ICAO standard atmosphere, ISO 2533).
M_AIR_KG_MOL = 0.0289644
#: Molar gas constant, J/(mol K) (CODATA 2018).
R_J_MOL_K = 8.314462618
#: 0 degC in kelvin.
KELVIN = 273.15
#: Gauss-Laguerre nodes of the tracking lag (exact for paths polynomial to degree 47).
LAG_NODES = 24


@dataclass(frozen=True)
class RealityEffects:
    """Which reality effects a simulation applies, and their sizes (docs/simulation.md#the-effects).

    Every effect is off by default; with all off the simulation is the one without this record,
    draw for draw. Units in the names (s, m, rad, degC; rates s/s).
    """

    correlated_noise: bool = False
    correlated_time_s: float = 1.0
    correlated_sigma_angle_rad: float = 1.0 * ARCSEC
    correlated_sigma_distance_m: float = 1.0e-3
    prism_cyclic: bool = False
    prism_cyclic_range_m: float = 2.0e-3
    prism_cyclic_across_m: float = 1.0e-3
    prism_cyclic_period_rad: float = np.pi / 3.0
    tracking_lag: bool = False
    tracking_lag_s: float = 0.01
    clock_drift: bool = False
    clock_drift_rate: float = 50e-6
    clock_resync_interval_s: float = 60.0
    jerky_ramps: bool = False
    jerky_accel_m_s2: float = 4.0
    remote_weather: bool = False
    remote_temperature_bias_c: float = 3.0
    remote_altitude_difference_m: float = 50.0
    tripod_settling: bool = False
    settling_sink_m: float = 1.0e-3
    settling_twist_rad: float = 1.0e-4
    settling_time_s: float = 1800.0

    def __post_init__(self) -> None:
        for f in fields(self):
            val = getattr(self, f.name)
            if f.name in REALITY_EFFECTS:
                if not isinstance(val, (bool, np.bool_)):
                    raise InputError(f"Expected a bool for reality effect {f.name}, got {val!r}")
                continue
            if not (isinstance(val, (int, float, np.floating)) and np.isfinite(val)):
                raise InputError(f"Expected a finite number for {f.name}, got {val!r}")
        for name in ("correlated_time_s", "prism_cyclic_period_rad", "clock_resync_interval_s",
                     "jerky_accel_m_s2", "settling_time_s"):
            if not getattr(self, name) > 0:
                raise InputError(f"Expected {name} > 0, got {getattr(self, name)!r}")
        for name in ("correlated_sigma_angle_rad", "correlated_sigma_distance_m",
                     "prism_cyclic_range_m", "prism_cyclic_across_m", "tracking_lag_s",
                     "clock_drift_rate", "settling_sink_m", "settling_twist_rad"):
            if not getattr(self, name) >= 0:
                raise InputError(f"Expected {name} >= 0, got {getattr(self, name)!r}")
        if not self.clock_drift_rate < 1e-2:
            raise InputError(f"Expected clock_drift_rate < 1e-2 s/s, got {self.clock_drift_rate!r}")

    @property
    def enabled(self) -> tuple[str, ...]:
        """The effects switched on, in :data:`REALITY_EFFECTS` order."""
        return tuple(name for name in REALITY_EFFECTS if getattr(self, name))

    @classmethod
    def only(cls, effect: str, **sizes: Any) -> RealityEffects:
        """One effect on (default sizes unless given in ``sizes``), every other off."""
        if effect not in REALITY_EFFECTS:
            raise InputError(f"Expected one of {', '.join(REALITY_EFFECTS)}, got {effect!r}")
        return cls(**{effect: True}, **sizes)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: every switch and size."""
        return {k: (bool(v) if k in REALITY_EFFECTS else float(v)) for k, v in asdict(self).items()}


def effect_rng(entropy: int, effect: str) -> np.random.Generator:
    """The random stream of one reality effect: child ``REALITY_EFFECTS.index(effect)`` of
    ``SeedSequence(entropy)`` (the scheme of :func:`rtsgt.options.stage_rng`).
    """
    return np.random.default_rng(
        np.random.SeedSequence(int(entropy), spawn_key=(REALITY_EFFECTS.index(effect),)))


def gauss_markov(t: ArrayLike, tau_s: float, sigma: ArrayLike,
                 rng: np.random.Generator) -> np.ndarray:
    """First-order Gauss-Markov process (N, C) at non-decreasing times ``t`` (N,) s, correlation time
    ``tau_s``, per-channel sigma (C,): stationary, ``corr = exp(-|t_i - t_j| / tau)``.

    Summed in closed form by cumulative sums in blocks of ``300 tau`` (no loop over samples).
    """
    t = np.asarray(t, dtype=float)
    sigma = np.atleast_1d(np.asarray(sigma, dtype=float))
    if t.ndim != 1 or np.any(np.diff(t) < 0):
        raise InputError("Expected non-decreasing times of shape (N,)")
    n = t.size
    w = rng.standard_normal((n, sigma.size))
    x = np.zeros((n, sigma.size))
    if n == 0:
        return x
    # u_j: innovation of sample j; 1 - phi^2 = -expm1(-2 dt / tau)
    scale = np.concatenate([[1.0], np.sqrt(-np.expm1(-2.0 * np.diff(t) / tau_s))])
    u = w * scale[:, None] * sigma
    block = np.floor((t - t[0]) / (300.0 * tau_s)).astype(np.int64)
    starts = np.flatnonzero(np.concatenate([[True], block[1:] != block[:-1]]))
    ends = np.concatenate([starts[1:], [n]])
    carry, t_prev = np.zeros(sigma.size), t[0]
    for a, b in zip(starts, ends, strict=True):  # loop over blocks of 300 tau
        tb = t[a:b] - t[a]
        decay = np.exp(-tb / tau_s)[:, None]
        # x_i = exp(-(t_i - t_prev)/tau) x_prev + exp(-(t_i - t_a)/tau) sum_j exp((t_j - t_a)/tau) u_j
        x[a:b] = (np.exp(-(t[a] - t_prev) / tau_s) * carry * decay
                  + decay * np.cumsum(np.exp(tb / tau_s)[:, None] * u[a:b], axis=0))
        carry, t_prev = x[b - 1], t[b - 1]
    return x


def prism_cyclic_error(alpha_rad: ArrayLike, amplitude_m: float, period_rad: float,
                       phase_rad: float) -> np.ndarray:
    """Cyclic error of a 360-degree prism, ``a sin(2 pi alpha / P + phi)`` (...) m, for the viewing
    azimuth ``alpha_rad`` (...) in the robot's frame.
    """
    return amplitude_m * np.sin(2.0 * np.pi * np.asarray(alpha_rad, dtype=float) / period_rad
                                + phase_rad)


def first_order_lag(path: Callable[[np.ndarray], np.ndarray], t: ArrayLike,
                    lag_s: float, nodes: int = LAG_NODES) -> np.ndarray:
    """First-order lag (N, 3) m of ``path`` (times (N, M) -> (N, M, 3)) at ``t`` (N,) s:
    ``int_0^inf path(t - lag_s x) e^{-x} dx`` by Gauss-Laguerre with ``nodes`` nodes.
    """
    t = np.asarray(t, dtype=float)
    if lag_s == 0:
        return path(t[:, None])[:, 0]
    x, w = np.polynomial.laguerre.laggauss(nodes)
    p = path(t[:, None] - lag_s * x[None, :])
    return np.einsum("m,nmi->ni", w, p)


def clock_sawtooth(t: ArrayLike, rate: float, interval_s: float, phase_s: float) -> np.ndarray:
    """Clock error of a drifting clock re-synchronised every ``interval_s``, s.

    ``e(t) = rate * mod(t - phase_s, interval_s)``: 0 right after each re-synchronisation,
    ``rate * interval_s`` just before the next.
    """
    return rate * np.mod(np.asarray(t, dtype=float) - phase_s, interval_s)


def remote_weather(temperature_c: ArrayLike, pressure_hpa: ArrayLike,
                   temperature_bias_c: float, altitude_difference_m: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Temperature (degC) and pressure (hPa) a weather station ``dT`` warmer and ``dh`` higher
    reports, from the true ones at the site (module docstring, model 6)."""
    temperature_c = np.asarray(temperature_c, dtype=float)
    t_mean_k = temperature_c + 0.5 * temperature_bias_c + KELVIN
    # hypsometric equation, mean layer temperature (Wallace & Hobbs 2006, eq. 3.29)
    factor = np.exp(-G_M_S2 * M_AIR_KG_MOL * altitude_difference_m / (R_J_MOL_K * t_mean_k))
    return temperature_c + temperature_bias_c, np.asarray(pressure_hpa, dtype=float) * factor


def settling_fraction(t: ArrayLike, t_start_s: float, time_constant_s: float) -> np.ndarray:
    """``1 - exp(-(t - t_start) / T_s)`` from ``t_start`` on, 0 before."""
    dt = np.maximum(np.asarray(t, dtype=float) - t_start_s, 0.0)
    return -np.expm1(-dt / time_constant_s)


def settle_points(p_station: ArrayLike, sink_m: ArrayLike, twist_rad: ArrayLike) -> np.ndarray:
    """Points (N, 3) m of a station's initial frame in its settled frame ``[Rz(psi), (0, 0, -z)]``:
    ``p' = Rz(psi)^T (p + (0, 0, z))``, ``sink_m``, ``twist_rad`` (N,).
    """
    p = np.asarray(p_station, dtype=float)
    c, s = np.cos(twist_rad), np.sin(twist_rad)
    return np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1],
                     p[:, 2] + sink_m], axis=-1)


@dataclass(frozen=True, eq=False)
class RealityTruth:
    """What the reality effects drew, per station (S) in order: ``clock_rate`` (S,) signed s/s,
    ``clock_sync_phase_s`` (S,), ``settling_start_s`` (S,) (first GCP shot), ``settling_twist_rad``
    and ``settling_sink_m`` (S,) signed finals, ``prism_phase_rad`` (S, 2) ``(phi_r, phi_c)``;
    zeros for effects off.
    """

    effects: RealityEffects
    station_ids: tuple[str, ...]
    clock_rate: np.ndarray
    clock_sync_phase_s: np.ndarray
    settling_start_s: np.ndarray
    settling_twist_rad: np.ndarray
    settling_sink_m: np.ndarray
    prism_phase_rad: np.ndarray

    def clock_error_s(self, k: int, t: ArrayLike) -> np.ndarray:
        """Drift part of station ``k``'s clock error (``t_true - t_recorded``) at ``t``, s."""
        return clock_sawtooth(t, self.clock_rate[k], self.effects.clock_resync_interval_s,
                              self.clock_sync_phase_s[k])

    def settling_at(self, k: int, t: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Sink (m) and twist (rad) of station ``k`` at times ``t``."""
        f = settling_fraction(t, self.settling_start_s[k], self.effects.settling_time_s)
        return self.settling_sink_m[k] * f, self.settling_twist_rad[k] * f

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the effects and the per-station draws."""
        per = {sid: {"clock_drift_rate": float(self.clock_rate[k]),
                     "clock_sync_phase_s": float(self.clock_sync_phase_s[k]),
                     "settling_start_s": float(self.settling_start_s[k]),
                     "settling_sink_m": float(self.settling_sink_m[k]),
                     "settling_twist_rad": float(self.settling_twist_rad[k]),
                     "prism_phase_rad": self.prism_phase_rad[k].tolist()}
               for k, sid in enumerate(self.station_ids)}
        return {"enabled": list(self.effects.enabled), "effects": self.effects.to_dict(),
                "stations": per}
