r"""Reality effects: errors of a real deployment that the estimator's noise model does not have.

The simulator draws its standard errors with the estimator's own model
(:func:`rtsgt.noise.perturb.sample_polar_errors`, the same clock and weather assumptions), so
a run on such data can only confirm the algebra. The effects here are drawn by formulas of
their own, independent of :mod:`rtsgt.noise`, each switched by :class:`RealityEffects` and off
by default. They act on what the simulated files hold: the measured angles and distances, the
time stamps, the reported weather and the station set-ups over time.

Models (``t`` true time, s; station ``k``; the sizes are fields of :class:`RealityEffects`)
------------------------------------------------------------------------------------------

1. ``correlated_noise``: a first-order Gauss-Markov process per station and channel
   (Hz, V, d), added to the white noise. Exact discretisation at the (irregular) measurement
   times (e.g. Gelb 1974, *Applied Optimal Estimation*, table 3.8-1)::

       x_0 = sigma w_0,   x_i = phi_i x_{i-1} + sigma sqrt(1 - phi_i^2) w_i,
       phi_i = exp(-(t_i - t_{i-1}) / tau),   w_i ~ N(0, 1)

   so that ``var x_i = sigma^2`` and ``corr(x_i, x_j) = exp(-|t_i - t_j| / tau)``.
2. ``prism_cyclic``: the cyclic error of a 360-degree prism (six prisms glued together): with
   ``alpha`` the azimuth, in the robot's frame, under which the prism sees the station, the
   range is off by ``a_r sin(2 pi alpha / P + phi_r)`` and the point is off across the line of
   sight (horizontally) by ``a_c sin(2 pi alpha / P + phi_c)``, period ``P = 60 deg``,
   phases drawn per prism (how it is mounted).
3. ``tracking_lag``: the station reports a first-order (exponential) lag of the prism path,
   ``y(t) = int_0^inf p(t - tau_l x) e^{-x} dx`` (the response of ``tau_l y' + y = p``),
   computed by Gauss-Laguerre quadrature. At constant velocity ``y(t) = p(t - tau_l)``, an
   error ``|v| tau_l`` along the track; accelerations add ``tau_l^2 a``.
4. ``clock_drift``: each station's clock drifts at ``s_k r`` (s/s, random sign ``s_k``) and
   is re-synchronised every ``N`` s (random phase ``c_k``): a sawtooth clock error
   ``e_k(t) = s_k r mod(t - c_k, N)`` added to the offset, ``t_recorded = t - e``.
5. ``jerky_ramps``: starts and stops (speed ramps from or to standstill) reach the peak
   acceleration ``a_j`` instead of the profile's ``accel_max_m_s2`` (shorter ramps, same
   schedule).
6. ``remote_weather``: the weather is reported by a station ``dT`` warmer and ``dh`` higher:
   ``T_rep = T + dT`` and, by the hypsometric equation with the layer's mean temperature
   ``T_m`` (K) (e.g. Wallace & Hobbs 2006, eq. 3.29),
   ``p_rep = p exp(-g M dh / (R T_m))``.
7. ``tripod_settling``: each station sinks by ``z_k(t) = s (1 - exp(-(t - t_k)/T_s))`` and its
   horizontal circle twists about the vertical by ``psi_k(t) = +-psi (1 - exp(-(t - t_k)/T_s))``
   from its set-up ``t_k`` (its first GCP shot) on. The tilt of the standing axis is what the
   compensator measures and removes, so only the sink and the twist are modelled:
   ``T_world_station(t) = T_world_station(t_k) [Rz(psi_k(t)), (0, 0, -z_k(t))]``.

Units: s, m, rad, degC, hPa; rates in s/s. Random draws come from one stream per effect
(:func:`effect_rng`), so that turning an effect on does not change another's draws.
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
    """Which reality effects a simulation applies, and their sizes (module docstring).

    Every effect is off by default; with all off the simulation is the one without this
    record, draw for draw.

    Attributes
    ----------
    correlated_noise : bool
        Time-correlated angle and distance noise (Gauss-Markov), added to the white noise.
    correlated_time_s : float
        Its correlation time ``tau``, s.
    correlated_sigma_angle_rad : float
        Its standard deviation on Hz and on V, rad (default 1", the S7's one-sigma angle).
    correlated_sigma_distance_m : float
        Its standard deviation on the distance, m.
    prism_cyclic : bool
        Orientation-dependent offset of the 360-degree prisms.
    prism_cyclic_range_m : float
        Amplitude ``a_r`` of the range error, m.
    prism_cyclic_across_m : float
        Amplitude ``a_c`` of the horizontal error across the line of sight, m.
    prism_cyclic_period_rad : float
        Period ``P`` of the error in the viewing azimuth, rad (60 deg: six prisms).
    tracking_lag : bool
        First-order lag of the tracked position.
    tracking_lag_s : float
        Its time constant ``tau_l``, s.
    clock_drift : bool
        Linear clock drift between periodic re-synchronisations (sawtooth).
    clock_drift_rate : float
        Drift rate ``r``, s/s (50e-6: 50 ppm, a free-running crystal).
    clock_resync_interval_s : float
        Time ``N`` between re-synchronisations, s.
    jerky_ramps : bool
        Starts and stops at a much higher acceleration.
    jerky_accel_m_s2 : float
        Peak acceleration ``a_j`` of those ramps, m/s^2.
    remote_weather : bool
        Weather reported by a station elsewhere.
    remote_temperature_bias_c : float
        ``dT``, degC (reported minus true).
    remote_altitude_difference_m : float
        ``dh``, height of the weather station above the site, m (negative: below).
    tripod_settling : bool
        Stations sink and twist after their set-up.
    settling_sink_m : float
        Final sink ``s``, m.
    settling_twist_rad : float
        Final twist ``psi`` about the vertical, rad (sign drawn per station).
    settling_time_s : float
        Time constant ``T_s``, s.
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
    """The random stream of one reality effect.

    Child ``i`` (the index of ``effect`` in :data:`REALITY_EFFECTS`) of
    ``numpy.random.SeedSequence(entropy)``, the scheme of :func:`rtsgt.options.stage_rng`:
    independent streams, the same on every machine. ``entropy`` is drawn once from the
    simulation's generator after its own stages.
    """
    return np.random.default_rng(
        np.random.SeedSequence(int(entropy), spawn_key=(REALITY_EFFECTS.index(effect),)))


def gauss_markov(t: ArrayLike, tau_s: float, sigma: ArrayLike,
                 rng: np.random.Generator) -> np.ndarray:
    """First-order Gauss-Markov process sampled exactly at increasing times.

    Parameters
    ----------
    t : array_like, shape (N,)
        Times, s, non-decreasing.
    tau_s : float
        Correlation time, s (> 0).
    sigma : array_like, shape (C,)
        Standard deviation of each of ``C`` independent channels.
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (N, C)
        ``x`` with ``var x = sigma^2`` and ``corr(x(t_i), x(t_j)) = exp(-|t_i - t_j| / tau)``
        (module docstring, model 1), started in its stationary distribution.

    Notes
    -----
    The recursion is summed in closed form, ``x_i = sum_{j <= i} exp(-(t_i - t_j)/tau) u_j``
    with ``u_0 = sigma w_0`` and ``u_j = sigma sqrt(1 - phi_j^2) w_j``, by a cumulative sum in
    blocks of ``300 tau`` (the factors ``exp(+-300)`` stay finite): a loop over blocks, not
    over samples.
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
    """Cyclic error of a 360-degree prism, ``a sin(2 pi alpha / P + phi)``, m.

    Parameters
    ----------
    alpha_rad : array_like, shape (...)
        Azimuth of the line of sight (prism to station) in the robot's frame, rad.
    amplitude_m, period_rad, phase_rad : float
    """
    return amplitude_m * np.sin(2.0 * np.pi * np.asarray(alpha_rad, dtype=float) / period_rad
                                + phase_rad)


def first_order_lag(path: Callable[[np.ndarray], np.ndarray], t: ArrayLike,
                    lag_s: float, nodes: int = LAG_NODES) -> np.ndarray:
    """First-order lag of a path: ``int_0^inf path(t - lag x) e^{-x} dx`` (Gauss-Laguerre).

    Parameters
    ----------
    path : callable
        ``path(times)`` for times of shape (N, M) returns positions of shape (N, M, 3), m.
    t : array_like, shape (N,)
        Times, s.
    lag_s : float
        Time constant, s (0: the path itself).
    nodes : int
        Quadrature nodes.

    Returns
    -------
    ndarray, shape (N, 3)
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
    """Points (N, 3) of a station's initial frame in its settled frame.

    The settled frame is ``[Rz(psi), (0, 0, -z)]`` in the initial one (sunk by ``z``, twisted
    by ``psi`` about the vertical), so ``p' = Rz(psi)^T (p + (0, 0, z))``.

    Parameters
    ----------
    p_station : array_like, shape (N, 3)
        m.
    sink_m, twist_rad : array_like, shape (N,)
    """
    p = np.asarray(p_station, dtype=float)
    c, s = np.cos(twist_rad), np.sin(twist_rad)
    return np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1],
                     p[:, 2] + sink_m], axis=-1)


@dataclass(frozen=True, eq=False)
class RealityTruth:
    """What the reality effects of a simulation drew (per station, in station order).

    Attributes
    ----------
    effects : RealityEffects
    station_ids : tuple of str
    clock_rate : ndarray, shape (S,)
        Signed drift rate ``s_k r`` of each clock, s/s (zeros without ``clock_drift``).
    clock_sync_phase_s : ndarray, shape (S,)
        Re-synchronisation phase ``c_k``, s (Unix time modulo the interval).
    settling_start_s : ndarray, shape (S,)
        Set-up time ``t_k`` of each station (its first GCP shot), s.
    settling_twist_rad : ndarray, shape (S,)
        Signed final twist, rad (zeros without ``tripod_settling``).
    settling_sink_m : ndarray, shape (S,)
        Final sink, m (zeros without ``tripod_settling``).
    prism_phase_rad : ndarray, shape (S, 2)
        Phases ``(phi_r, phi_c)`` of the cyclic error of the prism each station tracks.
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
