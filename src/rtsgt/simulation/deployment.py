r"""Simulation of a robotic-total-station deployment with known truth (numeric core).

Stations, GCP shots, a robot path, tracking measurements, weather and a static survey, drawn
from ``SimulationConfig`` with one seeded Generator. Frames, clocks and the measurement model:
docs/simulation.md#the-model; the reality effects (:mod:`rtsgt.simulation.reality`) and the
field preset (:mod:`rtsgt.simulation.field`) are applied on top.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from scipy.interpolate import CubicHermiteSpline

from rtsgt.errors import InputError
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.geometry.transform import RigidTransform
from rtsgt.measurement.atmosphere import instrument_correction_ppm
from rtsgt.measurement.instruments import ARCSEC, TRIMBLE_S7, InstrumentProfile
from rtsgt.measurement.polar import cartesian_to_polar, cartesian_to_survey_polar
from rtsgt.noise.perturb import sample_polar_errors
from rtsgt.simulation.field import (
    FieldEffects,
    FieldTruth,
    draw_displacement,
    draw_field_truth,
    draw_rocking,
    field_noise,
    field_rng,
)
from rtsgt.simulation.reality import (
    RealityEffects,
    RealityTruth,
    effect_rng,
    first_order_lag,
    gauss_markov,
    prism_cyclic_error,
    remote_weather,
    settle_points,
    settling_fraction,
)
from rtsgt.types import GcpShots, Observations, PoseTrajectory, SurveyShots, WeatherSeries

__all__ = [
    "SimulationConfig",
    "SimulatedDeployment",
    "SimulationTruth",
    "ObservationTruth",
    "SurveyShots",
    "TruthModel",
    "simulate_deployment",
    "atmospheric_ppm",
]

#: Warthog-like prism positions in the robot frame (m): prisms 1-3 at different heights with
#: inter-prism distances 0.738, 0.899 and 1.020 m (the real ones: 0.736, 0.903, 1.030 m).
#: Positions 4 and 5 are used only when more than three stations are simulated.
WARTHOG_PRISMS_ROBOT_M = (
    (0.40, 0.30, 0.80),
    (0.40, -0.42, 0.64),
    (-0.45, 0.05, 0.95),
    (-0.45, -0.45, 0.70),
    (0.00, 0.45, 1.05),
)

#: GNSS antenna positions in the robot frame (m), surveyed after the prisms like in the real
#: ``calibration_raw.csv`` (rows 4-6 there).
WARTHOG_GNSS_ROBOT_M = (
    (0.30, 0.00, 1.10),
    (-0.45, 0.20, 1.05),
    (-0.30, -0.30, 1.08),
)


#: Fields of :class:`SimulationConfig` that must be finite and > 0.
_POSITIVE = ("duration_s", "rate_hz", "truth_rate_hz", "speed_min_m_s", "speed_max_m_s",
             "accel_max_m_s2", "site_size_m", "min_turn_radius_m", "station_clearance_m",
             "weather_interval_s", "pressure_hpa")
#: Fields that must be finite and >= 0.
_NON_NEGATIVE = ("dropout_rate_per_min", "common_dropout_rate_per_min", "time_sync_std_s",
                 "time_sync_jitter_s", "sampling_jitter_s", "temperature_halfwidth_c",
                 "pressure_halfwidth_hpa", "humidity_halfwidth_pct", "temperature_amplitude_c",
                 "pressure_trend_hpa_h", "humidity_amplitude_pct", "terrain_max_slope_deg",
                 "survey_tilt_deg", "station_spread_m", "gcp_lead_time_s")
#: Ranges ``(a, b)`` that must have ``0 <= a <= b``, finite.
_INTERVALS = ("initial_stop_s", "drive_segment_s", "stop_duration_s", "instrument_height_m",
              "far_distance_m",
              "gcp_height_m", "gcp_shot_interval_s", "dropout_duration_s", "survey_distance_m",
              "survey_instrument_height_m", "survey_sigma_angle_rad", "survey_sigma_distance_m")
#: Probabilities, in [0, 1).
_PROBABILITIES = ("stop_probability", "single_loss_probability", "outlier_probability")


def _require(ok, message: str) -> None:
    """Raise :class:`~rtsgt.errors.InputError` with ``message`` unless ``ok``."""
    if not ok:
        raise InputError(message)


@dataclass(frozen=True)
class SimulationConfig:
    """Parameters of a simulated deployment; units in the names (docs/simulation.md#configuration).
    """

    duration_s: float = 600.0
    n_stations: int = 3
    rate_hz: float = 2.5
    start_time_s: float = 1668092400.0
    truth_rate_hz: float = 100.0
    # robot motion
    speed_min_m_s: float = 0.5
    speed_max_m_s: float = 2.0
    accel_max_m_s2: float = 0.5
    initial_stop_s: tuple[float, float] = (10.0, 20.0)
    drive_segment_s: tuple[float, float] = (20.0, 90.0)
    stop_probability: float = 0.3
    stop_duration_s: tuple[float, float] = (3.0, 15.0)
    # site
    site_size_m: float = 120.0
    min_turn_radius_m: float = 8.0
    terrain_max_slope_deg: float = 4.0
    station_clearance_m: float = 8.0
    station_spread_m: float = 30.0
    far_stations: int = 0
    far_distance_m: tuple[float, float] = (250.0, 450.0)
    instrument_height_m: tuple[float, float] = (1.4, 1.7)
    n_gcp: int = 10
    gcp_blocked_max: int = 2
    gcp_min_common: int = 5
    gcp_height_m: tuple[float, float] = (0.0, 1.5)
    gcp_lead_time_s: float = 1800.0
    gcp_shot_interval_s: tuple[float, float] = (30.0, 60.0)
    # instruments and time
    instrument: InstrumentProfile = TRIMBLE_S7
    additive_constant_m: float = 0.01
    time_sync_mean_s: float = 1.157e-3
    time_sync_std_s: float = 0.815e-3
    time_sync_jitter_s: float = 0.05e-3
    sampling_jitter_s: float = 3e-3
    # weather
    temperature_c: float = 2.0
    pressure_hpa: float = 937.0
    humidity_pct: float = 70.0
    temperature_amplitude_c: float = 3.0
    pressure_trend_hpa_h: float = 0.8
    humidity_amplitude_pct: float = 10.0
    weather_interval_s: float = 3600.0
    temperature_halfwidth_c: float = 1.0
    pressure_halfwidth_hpa: float = 10.0
    humidity_halfwidth_pct: float = 2.0
    # line of sight
    dropouts: bool = True
    dropout_rate_per_min: float = 0.5
    common_dropout_rate_per_min: float = 0.05
    dropout_duration_s: tuple[float, float] = (1.0, 15.0)
    single_loss_probability: float = 0.02
    outlier_probability: float = 0.0
    # robot geometry and static survey
    prism_positions_robot_m: tuple[tuple[float, float, float], ...] = WARTHOG_PRISMS_ROBOT_M
    gnss_positions_robot_m: tuple[tuple[float, float, float], ...] = WARTHOG_GNSS_ROBOT_M
    survey_distance_m: tuple[float, float] = (9.5, 11.5)
    survey_tilt_deg: float = 2.0
    survey_instrument_height_m: tuple[float, float] = (0.7, 1.2)
    survey_sigma_angle_rad: tuple[float, float] = (1.0 * ARCSEC, 10.0 * ARCSEC)
    survey_sigma_distance_m: tuple[float, float] = (0.5e-3, 0.8e-3)
    # switches
    noise_instrument: bool = True
    noise_tilt: bool = True
    noise_weather: bool = True
    noise_time_sync: bool = True
    noise_survey: bool = True
    atmosphere: bool = True
    reality: RealityEffects = field(default_factory=RealityEffects)
    field: FieldEffects | None = None

    def __post_init__(self) -> None:
        """Check every parameter; raises :class:`~rtsgt.errors.InputError` (a ValueError)."""
        for name in _POSITIVE:
            val = getattr(self, name)
            _require(np.isfinite(val) and val > 0, f"Expected {name} > 0, got {val!r}")
        _require(np.isfinite(self.additive_constant_m), "Expected a finite additive_constant_m")
        for name in _INTERVALS:
            a, b = getattr(self, name)
            _require(np.isfinite(a) and np.isfinite(b) and 0.0 <= a <= b,
                     f"Expected {name} = (a, b) with 0.0 <= a <= b, got {(a, b)!r}")
        _require(self.drive_segment_s[0] > 0,
                 f"Expected drive_segment_s > 0, got {self.drive_segment_s!r}")
        _require(self.survey_sigma_angle_rad[0] > 0 and self.survey_sigma_distance_m[0] > 0,
                 "Expected positive survey sigmas")
        _require(self.speed_min_m_s <= self.speed_max_m_s,
                 f"Expected speed_min_m_s <= speed_max_m_s, got {self.speed_min_m_s} > "
                 f"{self.speed_max_m_s}")
        _require(int(self.n_stations) == self.n_stations and self.n_stations >= 3,
                 f"Expected n_stations >= 3 (a pose needs 3 prisms), got {self.n_stations!r}")
        prisms = np.asarray(self.prism_positions_robot_m, dtype=float)
        _require(prisms.ndim == 2 and prisms.shape[1] == 3,
                 f"Expected prism_positions_robot_m of shape (P, 3), got {prisms.shape}")
        _require(self.n_stations <= prisms.shape[0],
                 f"Expected at most {prisms.shape[0]} stations (one per prism position in "
                 f"prism_positions_robot_m), got {self.n_stations}")
        gnss = np.asarray(self.gnss_positions_robot_m, dtype=float)
        _require(gnss.size % 3 == 0 and np.all(np.isfinite(gnss)),
                 f"Expected finite gnss_positions_robot_m of shape (G, 3), got {gnss.shape}")
        _require(int(self.n_gcp) == self.n_gcp and self.n_gcp >= 4,
                 f"Expected n_gcp >= 4, got {self.n_gcp!r}")
        _require(3 <= self.gcp_min_common <= self.n_gcp,
                 f"Expected 3 <= gcp_min_common <= n_gcp, got {self.gcp_min_common} "
                 f"(n_gcp = {self.n_gcp})")
        _require(0 <= self.gcp_blocked_max <= self.n_gcp - self.gcp_min_common,
                 f"Expected 0 <= gcp_blocked_max <= n_gcp - gcp_min_common, got "
                 f"{self.gcp_blocked_max}")
        for name in _PROBABILITIES:
            p = getattr(self, name)
            _require(0.0 <= p < 1.0, f"Expected 0 <= {name} < 1, got {p!r}")
        for name in _NON_NEGATIVE:
            val = getattr(self, name)
            _require(np.isfinite(val) and val >= 0, f"Expected {name} >= 0, got {val!r}")
        _require(self.sampling_jitter_s * 6 < 1.0 / self.rate_hz,
                 "Expected sampling_jitter_s well below the measurement interval")
        _require(self.terrain_max_slope_deg < 30,
                 f"Expected terrain_max_slope_deg < 30, got {self.terrain_max_slope_deg}")
        _require(isinstance(self.reality, RealityEffects),
                 f"Expected reality to be a RealityEffects, got {type(self.reality).__name__}")
        _require(self.field is None or isinstance(self.field, FieldEffects),
                 f"Expected field to be a FieldEffects or None, got {type(self.field).__name__}")
        _require(int(self.far_stations) == self.far_stations
                 and 0 <= self.far_stations < self.n_stations,
                 f"Expected 0 <= far_stations < n_stations, got {self.far_stations!r}")

    def without_noise(self) -> SimulationConfig:
        """The same deployment with every noise source off (dropouts and atmosphere kept)."""
        return replace(self, noise_instrument=False, noise_tilt=False, noise_weather=False,
                       noise_time_sync=False, noise_survey=False)

    @property
    def noise_sources(self) -> tuple[str, ...]:
        """Noise sources of :data:`rtsgt.types.NOISE_SOURCES` present in the simulated data.

        ``calibration`` is present when the GCP shots are noisy (instrument or tilt noise).
        """
        on = {
            "instrument": self.noise_instrument,
            "tilt": self.noise_tilt,
            "atmosphere": self.noise_weather,
            "time_sync": self.noise_time_sync,
            "calibration": self.noise_instrument or self.noise_tilt,
        }
        return tuple(k for k, v in on.items() if v)


@dataclass(frozen=True, eq=False)
class ObservationTruth:
    """What really happened at each of one station's N measurements.

    ``t_true`` (N,) s and ``clock_error_s = t_true - t_recorded`` (N,) s; ``hz, v, d`` (N,) the
    noise-free readings (rad, rad, m; ``d`` without the additive constant, at 0 ppm); ``ppm`` (N,)
    the true atmospheric correction; ``xyz_world`` (N, 3) the true prism, m; ``outlier`` (N,) bool.
    """

    t_true: np.ndarray
    clock_error_s: np.ndarray
    hz: np.ndarray
    v: np.ndarray
    d: np.ndarray
    ppm: np.ndarray
    xyz_world: np.ndarray
    outlier: np.ndarray


def _smoothstep(x: np.ndarray) -> np.ndarray:
    """Quintic smoothstep ``S(x) = 10x^3 - 15x^4 + 6x^5`` on [0, 1] (0 before, 1 after)."""
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (10.0 - 15.0 * x + 6.0 * x * x)


def _smoothstep_integral(x: np.ndarray) -> np.ndarray:
    """``int_0^x S``: 0 before 0, ``2.5x^4 - 3x^5 + x^6`` on [0, 1], ``x - 1/2`` after."""
    xc = np.clip(x, 0.0, 1.0)
    inside = xc**4 * (2.5 - 3.0 * xc + xc * xc)
    return np.where(x > 1.0, x - 0.5, inside)


def _rotation(axis: int, angle) -> np.ndarray:
    """Rotations (..., 3, 3) about axis ``axis`` (0: x, 1: y, 2: z) by ``angle`` (...), rad.

    numpy's cos/sin rather than scipy's Rotation (last bits differ): seeds stay byte-identical.
    """
    angle = np.asarray(angle, dtype=float)
    c, s = np.cos(angle), np.sin(angle)
    i, j = (axis + 1) % 3, (axis + 2) % 3
    R = np.zeros(angle.shape + (3, 3))
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def _loop_points(loop, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Loop point and derivative with respect to ``u``, site frame, shapes (..., 2).

    ``loop`` has the loop fields of :class:`TruthModel` (``radius``, ``harmonics``, ``scale``,
    ``theta``): a :class:`TruthModel` or the :class:`_Loop` it is built from.
    """
    order, amp, phase = loop.harmonics.T
    arg = order * u[..., None] + phase
    rho = loop.radius * (1.0 + np.sum(amp * np.cos(arg), axis=-1))
    drho = -loop.radius * np.sum(amp * order * np.sin(arg), axis=-1)
    cu, su = np.cos(u), np.sin(u)
    p = np.stack([loop.scale[0] * rho * cu, loop.scale[1] * rho * su], axis=-1)
    dp = np.stack([loop.scale[0] * (drho * cu - rho * su),
                   loop.scale[1] * (drho * su + rho * cu)], axis=-1)
    c, s = np.cos(loop.theta), np.sin(loop.theta)
    rot = np.array([[c, -s], [s, c]])
    return p @ rot.T, dp @ rot.T


def _ground_points(terrain: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Terrain height (m) and gradient (..., 2) at site-frame points (..., 2).

    ``terrain`` rows are plane waves ``(A, kx, ky, psi)``: ``h = sum A sin(k . xy + psi)``.
    """
    amp, kx, ky, psi = terrain.T
    arg = xy[..., :1] * kx + xy[..., 1:2] * ky + psi
    h = np.sum(amp * np.sin(arg), axis=-1)
    c = amp * np.cos(arg)
    grad = np.stack([np.sum(c * kx, axis=-1), np.sum(c * ky, axis=-1)], axis=-1)
    return h, grad


def atmospheric_ppm(
    temperature_c: np.ndarray, pressure_hpa: np.ndarray, humidity_pct: np.ndarray,
    profile: InstrumentProfile,
) -> np.ndarray:
    """Atmospheric correction K (ppm) of ``instrument`` at the given weather: ``D = D' (1 + K 1e-6)``
    (docs/noise-model.md#atmosphere).
    """
    return np.asarray(
        instrument_correction_ppm(profile, temperature_c, pressure_hpa, humidity_pct), dtype=float
    )


@dataclass(frozen=True, eq=False)
class TruthModel:
    """Analytic truth of a simulated deployment: robot path, attitude, weather.

    A smooth closed loop travelled at a speed of plateaus and quintic ramps, on a sum-of-sines
    terrain (z along its normal, x along the travel); evaluated exactly at any Unix times (...)
    by :meth:`robot_at`, :meth:`body_at`, :meth:`prisms_at`, :meth:`weather_at`.
    """

    t0: float
    # speed profile: ramps k start at ramp_t[k] (s after t0), last ramp_len[k] s, go from
    # level[k] to level[k + 1] (m/s); s_base[k] is the arc length at ramp_t[k] (m).
    ramp_t: np.ndarray
    ramp_len: np.ndarray
    level: np.ndarray
    s_base: np.ndarray
    # loop
    radius: float
    harmonics: np.ndarray  # (K, 3): order, relative amplitude, phase
    scale: np.ndarray  # (2,) sx, sy
    theta: float
    direction: float
    u0: float
    loop_length: float
    w_of_s: CubicHermiteSpline
    # terrain: rows (A, kx, ky, psi)
    terrain: np.ndarray
    # site -> world
    R_world_site: np.ndarray
    t_world_site: np.ndarray
    # robot geometry
    prisms_robot: np.ndarray  # (P, 3)
    R_robot_body: np.ndarray
    t_robot_body: np.ndarray
    # weather: (mean, amplitude, phase, trend per hour) for T, P, RH
    weather_params: np.ndarray  # (3, 4)
    # the vehicle's rocking at full speed (field preset, rtsgt.simulation.field.draw_rocking):
    # rows (axis, amplitude, frequency Hz, phase), scaled by the speed over rocking_speed_m_s
    rocking: np.ndarray | None = None
    rocking_speed_m_s: float = 1.0
    rocking_speed_exponent: float = 1.0

    # -- robot motion ------------------------------------------------------------------------
    def speed_at(self, t) -> np.ndarray:
        """Horizontal speed of the robot centre, m/s."""
        tau = np.asarray(t, dtype=float) - self.t0
        k = np.clip(np.searchsorted(self.ramp_t, tau, side="right") - 1, 0, None)
        x = (tau - self.ramp_t[k]) / self.ramp_len[k]
        return self.level[k] + (self.level[k + 1] - self.level[k]) * _smoothstep(x)

    def arc_at(self, t) -> np.ndarray:
        """Horizontal arc length travelled since ``t0``, m (0 before the first ramp)."""
        tau = np.asarray(t, dtype=float) - self.t0
        k = np.clip(np.searchsorted(self.ramp_t, tau, side="right") - 1, 0, None)
        dt = tau - self.ramp_t[k]
        x = dt / self.ramp_len[k]
        s = (self.s_base[k] + self.level[k] * dt
             + (self.level[k + 1] - self.level[k]) * self.ramp_len[k] * _smoothstep_integral(x))
        return np.where(tau < self.ramp_t[0], 0.0, s)

    def robot_at(self, t) -> tuple[np.ndarray, np.ndarray]:
        """``T_world_robot`` at times ``t``: rotation (..., 3, 3) and translation (..., 3), m."""
        s = self.arc_at(t)
        u = self.u0 + self.direction * self.w_of_s(np.mod(s, self.loop_length))
        xy, dxy = _loop_points(self, u)
        tangent = self.direction * dxy / np.linalg.norm(dxy, axis=-1, keepdims=True)
        h, grad = _ground_points(self.terrain, xy)
        # x axis: direction of travel on the ground; z axis: terrain normal
        x_axis = np.concatenate([tangent, np.sum(grad * tangent, -1, keepdims=True)], axis=-1)
        x_axis /= np.linalg.norm(x_axis, axis=-1, keepdims=True)
        z_axis = np.concatenate([-grad, np.ones(grad.shape[:-1] + (1,))], axis=-1)
        z_axis /= np.linalg.norm(z_axis, axis=-1, keepdims=True)
        y_axis = np.cross(z_axis, x_axis)
        # columns of R_world_robot = the robot axes expressed in the world frame
        R = np.stack([a @ self.R_world_site.T for a in (x_axis, y_axis, z_axis)], axis=-1)
        p_site = np.concatenate([xy, h[..., None]], axis=-1)
        p = p_site @ self.R_world_site.T + self.t_world_site
        if self.rocking is not None:
            R, p = self._rocked(t, R, p)
        return R, p

    def rocking_at(self, t) -> np.ndarray:
        """The vehicle's rocking (..., 6) at times ``t``: rotations about the robot's x, y, z
        (rad) and shifts along them (m), each its sinusoids' sum times the speed over
        ``rocking_speed_m_s`` to the power ``rocking_speed_exponent`` (none where the robot
        stands)."""
        tau = np.asarray(t, dtype=float) - self.t0
        out = np.zeros(tau.shape + (6,))
        for k in range(6):  # six axes, each a few dozen sinusoids
            a, f, ph = self.rocking[self.rocking[:, 0] == k, 1:].T
            out[..., k] = np.sin(np.multiply.outer(tau, 2.0 * np.pi * f) + ph) @ a
        v = np.asarray(self.speed_at(t), dtype=float)
        scale = np.where(v > 0.0, (np.maximum(v, 1e-300) / self.rocking_speed_m_s)
                         ** self.rocking_speed_exponent, 0.0)
        return out * scale[..., None]

    def _rocked(self, t, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``T_world_robot T_rock``: the path's pose (``R``, ``p``) turned and shifted by the
        rocking (:meth:`rocking_at`) about the robot's origin on the ground."""
        x = self.rocking_at(t)
        R_rock = _rotation(2, x[..., 2]) @ _rotation(1, x[..., 1]) @ _rotation(0, x[..., 0])
        return R @ R_rock, p + np.einsum("...ij,...j->...i", R, x[..., 3:])

    def body_from_robot(self, R_wr: np.ndarray, t_wr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``T_world_body = T_world_robot T_robot_body``: R (..., 3, 3), t (..., 3)."""
        R = np.einsum("...ij,jk->...ik", R_wr, self.R_robot_body)
        p = np.einsum("...ij,j->...i", R_wr, self.t_robot_body) + t_wr
        return R, p

    def prisms_from_robot(self, R_wr: np.ndarray, t_wr: np.ndarray) -> np.ndarray:
        """Prism positions ``T_world_robot p_robot``, shape (..., P, 3), m."""
        return np.einsum("...ij,pj->...pi", R_wr, self.prisms_robot) + t_wr[..., None, :]

    def body_at(self, t) -> tuple[np.ndarray, np.ndarray]:
        """``T_world_body`` at times ``t``: rotation (..., 3, 3) and translation (..., 3), m."""
        return self.body_from_robot(*self.robot_at(t))

    def prisms_at(self, t) -> np.ndarray:
        """True prism positions in the world frame, shape (..., P, 3), m."""
        return self.prisms_from_robot(*self.robot_at(t))

    # -- weather -----------------------------------------------------------------------------
    def weather_at(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True temperature (degC), station pressure (hPa) and relative humidity (%)."""
        hours = (np.asarray(t, dtype=float) - self.t0) / 3600.0
        mean, amp, phase, trend = self.weather_params.T
        day = 2.0 * np.pi * hours[..., None] / 24.0
        vals = mean + amp * np.sin(day + phase) + trend * hours[..., None]
        return vals[..., 0], vals[..., 1], np.clip(vals[..., 2], 0.0, 100.0)


@dataclass(frozen=True, eq=False)
class SimulationTruth:
    """Everything true about a simulated deployment (P prisms, G GNSS points, N truth samples).

    ``t`` (N,) s; ``body`` PoseTrajectory ``T_world_body``; ``prisms_world`` (N, P, 3) m;
    ``prism_ids``; ``T_world_station`` (station "1" the identity; before any settling);
    ``station_prism``; ``clock_offset_s`` (constant part of ``t_true - t_recorded``, s);
    ``reference_body`` (P, 3) and ``gnss_body`` (G, 3) m in the body frame (with ``field``: where the
    prisms are, one moved); ``T_body_robot``; ``gcp_markers``, ``gcp_world`` (n_gcp, 3) m;
    ``observations`` per station; ``additive_constant`` m; ``model`` TruthModel; ``reality``
    RealityTruth and ``field`` FieldTruth (None when off).
    """

    t: np.ndarray
    body: PoseTrajectory
    prisms_world: np.ndarray
    prism_ids: tuple[str, ...]
    T_world_station: dict[str, RigidTransform]
    station_prism: dict[str, str]
    clock_offset_s: dict[str, float]
    reference_body: np.ndarray
    gnss_body: np.ndarray
    T_body_robot: RigidTransform
    gcp_markers: tuple[str, ...]
    gcp_world: np.ndarray
    observations: dict[str, ObservationTruth]
    additive_constant: float
    model: TruthModel = field(repr=False)
    reality: RealityTruth | None = None
    field: FieldTruth | None = None


@dataclass(frozen=True, eq=False)
class SimulatedDeployment:
    """A simulated deployment: the data a real one yields (station-clock times, raw distances
    without the additive constant, survey rows ``prism1..P, gnss1..G``, true weather per minute and
    reported hourly), its ``truth``, ``config`` and ``seed`` (None when given a Generator).
    """

    observations: list[Observations]
    gcp: GcpShots
    survey: SurveyShots
    weather_true: WeatherSeries
    weather_reported: WeatherSeries
    truth: SimulationTruth
    config: SimulationConfig
    seed: int | None = None

    def truth_at(self, t, frame: str = "robot") -> tuple[np.ndarray, np.ndarray]:
        """Exact pose at any times: positions (..., 3) m, quat_xyzw (..., 4); ``frame`` "robot"
        (``T_world_robot``, truth.tum) or "body" (``T_world_body``).
        """
        if frame == "robot":
            R, p = self.truth.model.robot_at(t)
        elif frame == "body":
            R, p = self.truth.model.body_at(t)
        else:
            raise InputError(f"Expected frame 'robot' or 'body', got {frame!r}")
        return p, matrix_to_quat_xyzw(R)


# --------------------------------------------------------------------------------------------
# generation
# --------------------------------------------------------------------------------------------


class _Speed(NamedTuple):
    """Speed profile: the ramp fields of :class:`TruthModel` (see there)."""

    ramp_t: np.ndarray
    ramp_len: np.ndarray
    level: np.ndarray
    s_base: np.ndarray


class _Loop(NamedTuple):
    """Closed path of the robot centre: the loop fields of :class:`TruthModel` (see there)."""

    radius: float
    harmonics: np.ndarray
    scale: np.ndarray
    theta: float
    direction: float
    u0: float
    loop_length: float
    w_of_s: CubicHermiteSpline


class _Stations(NamedTuple):
    """True station set-ups (levelled) and the site frame.

    ``R_world``, ``t_world`` (S, 3, 3), (S, 3): ``T_world_station`` of each station (station 1
    is the identity); ``R_world_site``, ``t_world_site``: ``T_world_site``; ``radius`` (S,):
    horizontal distance of each station from the site centre, m.
    """

    ids: tuple[str, ...]
    R_world: np.ndarray
    t_world: np.ndarray
    R_world_site: np.ndarray
    t_world_site: np.ndarray
    radius: np.ndarray


class _Robot(NamedTuple):
    """Points on the robot and the body (survey) frame.

    ``prisms_robot`` (P, 3) and the body-frame points ``reference_body`` (P, 3), ``gnss_body``
    (G, 3), m; ``T_body_robot = (R_body_robot, t_body_robot)``.
    """

    prisms_robot: np.ndarray
    R_body_robot: np.ndarray
    t_body_robot: np.ndarray
    reference_body: np.ndarray
    gnss_body: np.ndarray


class _Gcp(NamedTuple):
    """GCP shots (station clocks), marker names, true marker positions (world, m), the true
    time of the first shot (s), and per shot its true time (s), station and marker indices."""

    shots: GcpShots
    markers: tuple[str, ...]
    world: np.ndarray
    first_shot_s: float
    t_true: np.ndarray
    station: np.ndarray
    marker: np.ndarray


def _speed_profile(cfg: SimulationConfig, rng: np.random.Generator) -> _Speed:
    """Plateaus and ramps of the speed, covering ``[0, duration]`` (s after the start)."""
    ramp_t, ramp_len, level = [], [], [0.0]
    tau = rng.uniform(*cfg.initial_stop_s)
    moving = False
    # loop over segments (a few per minute), not measurements; at least one ramp
    while not ramp_t or tau <= cfg.duration_s:
        if moving and rng.random() < cfg.stop_probability:
            target, hold = 0.0, rng.uniform(*cfg.stop_duration_s)
        else:
            target, hold = rng.uniform(cfg.speed_min_m_s, cfg.speed_max_m_s), rng.uniform(
                *cfg.drive_segment_s)
        # quintic smoothstep: peak acceleration 15/8 dv / T
        length = max(1.0, 1.875 * abs(target - level[-1]) / cfg.accel_max_m_s2)
        ramp_t.append(tau)
        ramp_len.append(length)
        level.append(target)
        tau += length + hold
        moving = target > 0
    ramp_t = np.asarray(ramp_t)
    ramp_len = np.asarray(ramp_len)
    level = np.asarray(level)
    return _Speed(ramp_t, ramp_len, level, _ramp_arc_lengths(ramp_t, ramp_len, level))


def _ramp_arc_lengths(ramp_t: np.ndarray, ramp_len: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Arc length at each ramp start, m (closed form; the ramps do not overlap)."""
    span = np.diff(ramp_t)
    dv = np.diff(level)
    inc = level[:-2] * span + dv[:-1] * (span - 0.5 * ramp_len[:-1])
    return np.concatenate([[0.0], np.cumsum(inc)])


def _jerky_ramps(speed: _Speed, accel_m_s2: float) -> _Speed:
    """The speed profile with its starts and stops (ramps from or to 0) at the peak
    acceleration ``accel_m_s2`` (reality effect ``jerky_ramps``); same ramp start times, so
    the plateaus that follow are longer. No random draw."""
    level = speed.level
    dv = np.abs(np.diff(level))
    start_stop = (level[:-1] == 0.0) | (level[1:] == 0.0)
    # quintic smoothstep: peak acceleration 15/8 dv / T
    ramp_len = np.where(start_stop, np.maximum(1.875 * dv / accel_m_s2, 1e-3), speed.ramp_len)
    ramp_len = np.minimum(ramp_len, speed.ramp_len)
    return _Speed(speed.ramp_t, ramp_len, level,
                  _ramp_arc_lengths(speed.ramp_t, ramp_len, level))


def _loop_shape(cfg: SimulationConfig, rng: np.random.Generator) -> _Loop:
    """Random smooth closed loop meeting the curvature limit (rejection sampling)."""
    radius = cfg.site_size_m / 4.0
    u = np.linspace(0.0, 2.0 * np.pi, 8193)
    for _ in range(200):
        orders = np.array([2.0, 3.0, 4.0])
        amps = rng.uniform(0.0, [0.15, 0.08, 0.04])
        phases = rng.uniform(0.0, 2.0 * np.pi, 3)
        harmonics = np.stack([orders, amps, phases], axis=-1)
        stretch = rng.uniform(1.0, 1.3)
        scale = np.array([stretch, 1.0 / stretch])
        theta = rng.uniform(0.0, 2.0 * np.pi)
        arg = orders * u[:, None] + phases
        rho = radius * (1.0 + np.sum(amps * np.cos(arg), -1))
        d1 = -radius * np.sum(amps * orders * np.sin(arg), -1)
        d2 = -radius * np.sum(amps * orders**2 * np.cos(arg), -1)
        cu, su = np.cos(u), np.sin(u)
        x1 = scale[0] * (d1 * cu - rho * su)
        y1 = scale[1] * (d1 * su + rho * cu)
        x2 = scale[0] * (d2 * cu - 2 * d1 * su - rho * cu)
        y2 = scale[1] * (d2 * su + 2 * d1 * cu - rho * su)
        speed = np.hypot(x1, y1)
        curvature = np.abs(x1 * y2 - y1 * x2) / speed**3
        if 1.0 / curvature.max() >= cfg.min_turn_radius_m:
            break
    else:  # pragma: no cover - the defaults always succeed
        raise InputError(
            f"Could not draw a loop with turn radius >= {cfg.min_turn_radius_m} m in a site of "
            f"{cfg.site_size_m} m; lower min_turn_radius_m or enlarge site_size_m"
        )
    # start point and direction of travel: u = u0 + direction * w, w in [0, 2 pi]
    direction = float(rng.choice([-1.0, 1.0]))
    u0 = rng.uniform(0.0, 2.0 * np.pi)
    arg = orders * (u0 + direction * u)[:, None] + phases
    rho = radius * (1.0 + np.sum(amps * np.cos(arg), -1))
    d1 = -radius * np.sum(amps * orders * np.sin(arg), -1)
    cw, sw = np.cos(u0 + direction * u), np.sin(u0 + direction * u)
    speed_w = np.hypot(scale[0] * (d1 * cw - rho * sw), scale[1] * (d1 * sw + rho * cw))
    # arc-length table s(w) and its inverse w(s) (cubic Hermite with the exact derivative)
    seg = 0.5 * (speed_w[1:] + speed_w[:-1]) * np.diff(u)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    w_of_s = CubicHermiteSpline(s, u, 1.0 / speed_w)
    return _Loop(radius, harmonics, scale, theta, direction, u0, float(s[-1]), w_of_s)


def _terrain(cfg: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """Three plane waves with a total slope below ``terrain_max_slope_deg``."""
    n = 3
    wavelength = rng.uniform(60.0, 200.0, n)
    k = 2.0 * np.pi / wavelength
    heading = rng.uniform(0.0, 2.0 * np.pi, n)
    slope = np.tan(np.radians(cfg.terrain_max_slope_deg)) / n * rng.uniform(0.5, 1.0, n)
    amp = slope / k
    return np.stack([amp, k * np.cos(heading), k * np.sin(heading),
                     rng.uniform(0.0, 2.0 * np.pi, n)], axis=-1)


def _weather_params(cfg: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """Rows ``(mean, amplitude, phase, trend per hour)`` of the true T, P and RH."""
    phase = rng.uniform(0.0, 2.0 * np.pi, 3)
    p_trend = rng.uniform(-cfg.pressure_trend_hpa_h, cfg.pressure_trend_hpa_h)
    p_amp = rng.uniform(0.0, 1.0)
    return np.array([
        [cfg.temperature_c, cfg.temperature_amplitude_c, phase[0], 0.0],
        [cfg.pressure_hpa, p_amp, phase[1], p_trend],
        [cfg.humidity_pct, cfg.humidity_amplitude_pct, phase[2], 0.0],
    ])


def _true_ppm(cfg: SimulationConfig, model: TruthModel, t: np.ndarray) -> np.ndarray:
    """True atmospheric correction at times ``t``, ppm (0 with ``atmosphere`` off)."""
    if not cfg.atmosphere:
        return np.zeros_like(t)
    return atmospheric_ppm(*model.weather_at(t), cfg.instrument)


def _measure(cfg: SimulationConfig, rng: np.random.Generator, p_station: np.ndarray,
             ppm: np.ndarray):
    """Noise-free and noisy raw polar values of station-frame points (N, 3)."""
    hz0, v0, dist = cartesian_to_polar(p_station)
    d_ref = dist / (1.0 + ppm * 1e-6)  # what a 0-ppm instrument reports (constant included)
    datasheet = cfg.field is None  # the field effects draw their own noise (_field)
    hz_s, v_s, d_s = sample_polar_errors(
        hz0, v0, d_ref, cfg.instrument, 1, rng,
        instrument=cfg.noise_instrument and datasheet, tilt=cfg.noise_tilt and datasheet,
    )
    c = cfg.additive_constant_m
    return (hz0, v0, d_ref - c), (np.mod(hz_s[0], 2.0 * np.pi), v_s[0], d_s[0] - c)


def _gaps_mask(t: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """True where ``t`` falls in one of the intervals ``[start, start + length)``."""
    if starts.size == 0:
        return np.zeros(t.shape, dtype=bool)
    inside = (t[:, None] >= starts) & (t[:, None] < starts + lengths)
    return inside.any(axis=1)


def _draw_gaps(cfg: SimulationConfig, rng: np.random.Generator, rate_per_min: float):
    """Starts (s after the start of tracking) and lengths (s) of Poisson line-of-sight losses."""
    n = rng.poisson(rate_per_min * cfg.duration_s / 60.0)
    return rng.uniform(0.0, cfg.duration_s, n), rng.uniform(*cfg.dropout_duration_s, n)


#: Radius of the sphere whose verticals the levelled stations follow, m (mean Earth radius).
EARTH_RADIUS_M = 6_371_000.0


def _local_vertical(t_world_st: np.ndarray) -> np.ndarray:
    """Rotations (S, 3, 3) taking station 1's vertical to each station's: the vertical at a
    point of a sphere of radius ``EARTH_RADIUS_M`` whose centre is below station 1, turned
    about ``e_z x up`` by the angle between ``e_z`` and ``up`` (Rodrigues)."""
    up = np.concatenate([t_world_st[:, :2], EARTH_RADIUS_M + t_world_st[:, 2:]], axis=1)
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    axis = np.stack([-up[:, 1], up[:, 0], np.zeros(len(up))], axis=1)  # e_z x up
    s = np.linalg.norm(axis, axis=1)
    c = up[:, 2]
    k = np.divide(axis, s[:, None], out=np.zeros_like(axis), where=s[:, None] > 0)
    K = np.zeros((len(up), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K -= np.swapaxes(K, 1, 2)
    return np.eye(3) + s[:, None, None] * K + (1.0 - c)[:, None, None] * (K @ K)


def _place_stations(
    cfg: SimulationConfig, rng: np.random.Generator, loop: _Loop, terrain: np.ndarray
) -> _Stations:
    """Levelled stations around the path, beyond ``station_clearance_m``; world = station 1."""
    n_st = int(cfg.n_stations)
    loop_xy, _ = _loop_points(loop, np.linspace(0.0, 2.0 * np.pi, 2048, endpoint=False))
    loop_r = np.linalg.norm(loop_xy, axis=-1)
    loop_ang = np.arctan2(loop_xy[:, 1], loop_xy[:, 0])
    alpha = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n_st) / n_st \
        + rng.uniform(-0.35, 0.35, n_st)
    # radius of the loop in each station's direction, then stand beyond it
    diff = np.abs(np.angle(np.exp(1j * (loop_ang[None, :] - alpha[:, None]))))
    reach = np.where(diff < 0.3, loop_r[None, :], 0.0).max(axis=1)
    spread = rng.uniform(0.0, cfg.station_spread_m, n_st)
    st_r = reach + cfg.station_clearance_m + spread
    if cfg.far_stations:  # the same draw, placed in the far range
        far = slice(n_st - int(cfg.far_stations), None)
        frac = spread[far] / cfg.station_spread_m if cfg.station_spread_m > 0 else 0.5
        st_r[far] = cfg.far_distance_m[0] + frac * np.diff(cfg.far_distance_m)
    st_xy = _clear_of_path(
        np.stack([st_r * np.cos(alpha), st_r * np.sin(alpha)], axis=-1), loop_xy,
        cfg.station_clearance_m,
    )
    st_h, _ = _ground_points(terrain, st_xy)
    st_z = st_h + rng.uniform(*cfg.instrument_height_m, n_st)
    st_p = np.concatenate([st_xy, st_z[:, None]], axis=-1)
    R_site_st = _rotation(2, rng.uniform(0.0, 2.0 * np.pi, n_st))
    R_world_site = R_site_st[0].T
    t_world_site = -R_world_site @ st_p[0]
    R_world_st = R_world_site @ R_site_st
    t_world_st = st_p @ R_world_site.T + t_world_site
    R_world_st[0] = np.eye(3)
    t_world_st[0] = 0.0
    R_world_st = _local_vertical(t_world_st) @ R_world_st
    ids = tuple(str(k + 1) for k in range(n_st))
    return _Stations(ids, R_world_st, t_world_st, R_world_site, t_world_site, st_r)


def _clear_of_path(
    st_xy: np.ndarray, loop_xy: np.ndarray, clearance: float, max_pushes: int = 50
) -> np.ndarray:
    """Push stations (S, 2) outwards until each is ``clearance`` (m) from the path points; InputError
    if still too close after ``max_pushes``.
    """
    for push in range(max_pushes + 1):
        dmin = np.linalg.norm(st_xy[:, None, :] - loop_xy[None], axis=-1).min(axis=1)
        close = ~(dmin >= clearance)  # NaN (a station at the site centre) is not clear
        if not close.any():
            return st_xy
        if push == max_pushes:
            break
        st_xy[close] *= 1.0 + (clearance - dmin[close, None]) / np.linalg.norm(
            st_xy[close], axis=-1, keepdims=True) + 0.01
    raise InputError(
        f"Could not place station(s) {', '.join(str(k + 1) for k in np.flatnonzero(close))} "
        f"at station_clearance_m = {clearance} m or more from the path in {max_pushes} pushes; "
        "lower station_clearance_m or enlarge site_size_m"
    )


def _robot_geometry(cfg: SimulationConfig, rng: np.random.Generator) -> _Robot:
    """Prisms and GNSS antennas on the robot, and the robot's pose in the survey (body) frame."""
    prisms_robot = np.asarray(cfg.prism_positions_robot_m, dtype=float)[:int(cfg.n_stations)]
    gnss_robot = np.asarray(cfg.gnss_positions_robot_m, dtype=float).reshape(-1, 3)
    tilt = np.radians(cfg.survey_tilt_deg)
    R_body_robot = (_rotation(2, rng.uniform(0.0, 2.0 * np.pi))
                    @ _rotation(1, rng.uniform(-tilt, tilt))
                    @ _rotation(0, rng.uniform(-tilt, tilt)))
    t_body_robot = np.array([rng.uniform(*cfg.survey_distance_m), rng.uniform(-0.5, 0.5),
                             -rng.uniform(*cfg.survey_instrument_height_m)])
    return _Robot(prisms_robot, R_body_robot, t_body_robot,
                  prisms_robot @ R_body_robot.T + t_body_robot,
                  gnss_robot @ R_body_robot.T + t_body_robot)


def _clock_offsets(cfg: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """Constant clock error of each station, s (zeros without ``noise_time_sync``).

    ``|e| ~ N(mu, sigma)`` as the authors measured it; each station synchronises on its own,
    leading or lagging: a random sign per station (the noise model's assumption).
    """
    n_st = int(cfg.n_stations)
    if not cfg.noise_time_sync:
        return np.zeros(n_st)
    magnitude = np.abs(rng.normal(cfg.time_sync_mean_s, cfg.time_sync_std_s, n_st))
    return rng.choice([-1.0, 1.0], n_st) * magnitude


def _clock_errors(
    cfg: SimulationConfig, rng: np.random.Generator, offsets: np.ndarray, station: np.ndarray
) -> np.ndarray:
    """``t_true - t_recorded`` of measurements by stations ``station`` (indices): offset plus
    jitter, s (zeros without ``noise_time_sync``)."""
    if not cfg.noise_time_sync:
        return np.zeros(station.shape)
    return offsets[station] + rng.normal(0.0, cfg.time_sync_jitter_s, station.shape)


def _in_station_frames(stations: _Stations, station: np.ndarray, p_world: np.ndarray):
    """World points (N, 3) in the frames of the stations ``station`` (N,) (indices), m."""
    return np.einsum("nji,nj->ni", stations.R_world[station],
                     p_world - stations.t_world[station])


def _line_of_sight(cfg: SimulationConfig, rng: np.random.Generator, tau: np.ndarray):
    """Measurements (S, N) at ``tau`` (s after the start) not lost: common and per-station
    line-of-sight losses, then single losses."""
    c_start, c_len = _draw_gaps(cfg, rng, cfg.common_dropout_rate_per_min)
    keep = []
    for k in range(tau.shape[0]):  # loop over stations
        s_start, s_len = _draw_gaps(cfg, rng, cfg.dropout_rate_per_min)
        keep.append(~_gaps_mask(tau[k], np.concatenate([s_start, c_start]),
                                np.concatenate([s_len, c_len])))
    return np.stack(keep) & (rng.random(tau.shape) >= cfg.single_loss_probability)


def _tracking_epochs(cfg: SimulationConfig, rng: np.random.Generator):
    """True epochs of the tracking measurements: station indices and Unix times (s), sorted by
    station then time. Staggered stations, jittered sampling, line-of-sight losses."""
    n_st = int(cfg.n_stations)
    n_nom = int(np.floor(cfg.duration_s * cfg.rate_hz)) + 1
    period = 1.0 / cfg.rate_hz
    phase = (np.arange(n_st) + rng.uniform(-0.25, 0.25, n_st)) * period / n_st
    phase = np.mod(phase, period)
    tau = phase[:, None] + np.arange(n_nom)[None, :] * period
    tau = tau + np.clip(rng.normal(0.0, cfg.sampling_jitter_s, tau.shape),
                        -3 * cfg.sampling_jitter_s, 3 * cfg.sampling_jitter_s)
    keep = (tau >= 0.0) & (tau <= cfg.duration_s)
    if cfg.dropouts:
        keep &= _line_of_sight(cfg, rng, tau)
    station = np.broadcast_to(np.arange(n_st)[:, None], tau.shape)[keep]
    t_true = float(cfg.start_time_s) + tau[keep]
    order = np.lexsort((t_true, station))
    return station[order], t_true[order]


def _track(
    cfg: SimulationConfig, rng: np.random.Generator, model: TruthModel, stations: _Stations,
    offsets: np.ndarray,
) -> tuple[list[Observations], dict[str, ObservationTruth]]:
    """Tracking measurements of every station (station k tracks prism k) and their truth."""
    station, t_true = _tracking_epochs(cfg, rng)
    t_rec = t_true - _clock_errors(cfg, rng, offsets, station)
    clock = t_true - t_rec  # exactly what the stored numbers imply
    p_world = model.prisms_at(t_true)[np.arange(t_true.size), station]
    ppm = _true_ppm(cfg, model, t_true)
    (hz0, v0, d0), (hz, v, d) = _measure(
        cfg, rng, _in_station_frames(stations, station, p_world), ppm)
    outlier = rng.random(t_true.shape) < cfg.outlier_probability
    d = d + outlier * rng.choice([-1.0, 1.0], t_true.shape) * rng.uniform(1.0, 5.0, t_true.shape)
    observations, truth = [], {}
    for k, sid in enumerate(stations.ids):  # loop over stations
        m = station == k
        observations.append(Observations(t_rec[m], hz[m], v[m], d[m], None, sid, sid,
                                          cfg.additive_constant_m, None))
        truth[sid] = ObservationTruth(t_true[m], clock[m], hz0[m], v0[m], d0[m], ppm[m],
                                      p_world[m], outlier[m])
    return observations, truth


def _gcp_visibility(
    cfg: SimulationConfig, rng: np.random.Generator, max_draws: int = 1000
) -> np.ndarray:
    """Markers each station sees (S, n_gcp), by rejection sampling (InputError after ``max_draws``).
    """
    n_st, n_gcp = int(cfg.n_stations), int(cfg.n_gcp)
    for _ in range(max_draws):
        visible = np.ones((n_st, n_gcp), dtype=bool)
        for k in range(n_st):  # loop over stations
            nb = rng.integers(0, cfg.gcp_blocked_max + 1)
            visible[k, rng.choice(n_gcp, nb, replace=False)] = False
        if np.all((visible & visible[0]).sum(axis=1) >= cfg.gcp_min_common):
            return visible
    raise InputError(
        f"Could not hide up to gcp_blocked_max = {cfg.gcp_blocked_max} of the {n_gcp} markers "
        f"per station and keep gcp_min_common = {cfg.gcp_min_common} in common with station 1 "
        f"in {max_draws} draws; lower gcp_blocked_max or gcp_min_common"
    )


def _gcp_times(cfg: SimulationConfig, rng: np.random.Generator, station: np.ndarray):
    """True times (s) of GCP shots by ``station`` (indices, station-major): each station's
    session starts 120 s after the previous one's, the first ``gcp_lead_time_s`` before
    tracking; one shot every ``gcp_shot_interval_s``."""
    intervals = rng.uniform(*cfg.gcp_shot_interval_s, station.size)
    session_start = float(cfg.start_time_s) - cfg.gcp_lead_time_s + 120.0 * station
    first = np.concatenate([[True], station[1:] != station[:-1]])
    csum = np.cumsum(np.where(first, 0.0, intervals))
    csum -= np.maximum.accumulate(np.where(first, csum, 0.0))
    return session_start + csum


def _gcp(
    cfg: SimulationConfig, rng: np.random.Generator, model: TruthModel, stations: _Stations,
    offsets: np.ndarray,
) -> _Gcp:
    """Markers on the ground inside the station ring, shot by every station that sees them."""
    n_gcp = int(cfg.n_gcp)
    g_ang = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n_gcp) / n_gcp \
        + rng.uniform(-0.2, 0.2, n_gcp)
    g_rad = rng.uniform(0.3, 1.0, n_gcp) * stations.radius.min()
    g_xy = np.stack([g_rad * np.cos(g_ang), g_rad * np.sin(g_ang)], axis=-1)
    g_h, _ = _ground_points(model.terrain, g_xy)
    g_site = np.concatenate([g_xy, (g_h + rng.uniform(*cfg.gcp_height_m, n_gcp))[:, None]], -1)
    gcp_world = g_site @ stations.R_world_site.T + stations.t_world_site
    g_st, g_mk = np.nonzero(_gcp_visibility(cfg, rng))  # station-major, like the real GCP.txt
    t_true = _gcp_times(cfg, rng, g_st)
    t_rec = t_true - _clock_errors(cfg, rng, offsets, g_st)
    p_station = _in_station_frames(stations, g_st, gcp_world[g_mk])
    _, (hz, v, d) = _measure(cfg, rng, p_station, _true_ppm(cfg, model, t_true))
    markers = tuple(str(i + 1) for i in range(n_gcp))
    shots = GcpShots(np.asarray(stations.ids, dtype=object)[g_st], np.asarray(markers)[g_mk],
                     hz, v, d, t_rec, None, cfg.additive_constant_m)
    return _Gcp(shots, markers, gcp_world, float(t_true.min()), t_true, g_st, g_mk)


def _survey(cfg: SimulationConfig, rng: np.random.Generator, robot: _Robot) -> SurveyShots:
    """Static survey of the prisms then the GNSS antennas, in the body (survey) frame."""
    hz, v, d = cartesian_to_survey_polar(np.concatenate([robot.reference_body, robot.gnss_body]))
    lo, hi = np.log(cfg.survey_sigma_angle_rad)
    sig_hz = np.exp(rng.uniform(lo, hi, d.size))
    sig_v = np.exp(rng.uniform(lo, hi, d.size))
    sig_d = rng.uniform(*cfg.survey_sigma_distance_m, d.size)
    if cfg.noise_survey:
        e = rng.standard_normal((3, d.size))
        hz = np.mod(hz + sig_hz * e[0], 2 * np.pi)
        v = v + sig_v * e[1]
        d = d + sig_d * e[2]
    names = tuple(f"prism{i + 1}" for i in range(robot.reference_body.shape[0])) + tuple(
        f"gnss{i + 1}" for i in range(robot.gnss_body.shape[0]))
    return SurveyShots(names, hz, sig_hz, v, sig_v, d, sig_d)


def _weather(
    cfg: SimulationConfig, rng: np.random.Generator, model: TruthModel, t_first: float
) -> tuple[WeatherSeries, WeatherSeries]:
    """True weather every minute and reported weather (true plus uniform errors) every
    ``weather_interval_s``, from before ``t_first`` to after the end of tracking."""
    t_last = float(cfg.start_time_s) + cfg.duration_s
    step = cfg.weather_interval_s
    w_t = np.arange(np.floor(t_first / step) - 1, np.ceil(t_last / step) + 2) * step
    T, P, H = model.weather_at(w_t)
    if cfg.noise_weather:
        T = T + rng.uniform(-cfg.temperature_halfwidth_c, cfg.temperature_halfwidth_c, w_t.size)
        P = P + rng.uniform(-cfg.pressure_halfwidth_hpa, cfg.pressure_halfwidth_hpa, w_t.size)
        H = np.clip(H + rng.uniform(-cfg.humidity_halfwidth_pct, cfg.humidity_halfwidth_pct,
                                    w_t.size), 0.0, 100.0)
    wt_t = np.arange(w_t[0], w_t[-1] + 1.0, 60.0)
    return (WeatherSeries(wt_t, *model.weather_at(wt_t), "simulated (true)"),
            WeatherSeries(w_t, T, P, H, "simulated (reported)"))


def _polar_change(p_station: np.ndarray, q_station: np.ndarray, ppm: np.ndarray):
    """Change of the raw polar values (rad, rad, m at 0 ppm) when a station sees ``q``
    instead of ``p`` (station frame, (N, 3), m)."""
    hz0, v0, d0 = cartesian_to_polar(p_station)
    hz1, v1, d1 = cartesian_to_polar(q_station)
    return np.angle(np.exp(1j * (hz1 - hz0))), v1 - v0, (d1 - d0) / (1.0 + ppm * 1e-6)


def _reality_draws(
    cfg: SimulationConfig, rng: np.random.Generator, ids: tuple[str, ...], gcp: _Gcp
) -> tuple[RealityTruth, dict[str, np.random.Generator]]:
    """The per-station draws of the reality effects that are on, and each effect's stream."""
    fx = cfg.reality
    n_st = int(cfg.n_stations)
    entropy = int(rng.integers(0, 2**63 - 1))  # after every stage: the base draws are unchanged
    draw = {name: effect_rng(entropy, name) for name in fx.enabled}
    zeros = np.zeros(n_st)
    clock_rate, sync_phase, twist, sink = zeros, zeros, zeros, zeros
    if fx.clock_drift:
        g = draw["clock_drift"]
        clock_rate = fx.clock_drift_rate * g.choice([-1.0, 1.0], n_st)
        sync_phase = g.uniform(0.0, fx.clock_resync_interval_s, n_st)
    if fx.tripod_settling:
        twist = fx.settling_twist_rad * draw["tripod_settling"].choice([-1.0, 1.0], n_st)
        sink = np.full(n_st, float(fx.settling_sink_m))
    phase = (draw["prism_cyclic"].uniform(0.0, 2.0 * np.pi, (n_st, 2)) if fx.prism_cyclic
             else np.zeros((n_st, 2)))
    setup = np.full(n_st, np.inf)
    np.minimum.at(setup, gcp.station, gcp.t_true)  # a station is set up at its first GCP shot
    setup = np.where(np.isfinite(setup), setup, float(cfg.start_time_s))
    return RealityTruth(fx, ids, clock_rate, sync_phase, setup, twist, sink, phase), draw


def _reality_track(
    cfg: SimulationConfig, reality: RealityTruth, draw: dict[str, np.random.Generator],
    model: TruthModel, stations: _Stations, k: int, obs: Observations, ot: ObservationTruth,
) -> tuple[Observations, ObservationTruth]:
    """One station's tracking measurements with the reality effects (vectorised over them)."""
    fx = cfg.reality
    t, p_world = ot.t_true, ot.xyz_world
    R, t_station = stations.R_world[k], stations.t_world[k]
    zero = np.zeros(t.shape)
    dhz, dv, dd = zero, zero, zero
    if fx.tracking_lag or fx.tripod_settling:
        q_world = p_world
        if fx.tracking_lag:
            q_world = first_order_lag(lambda tt: model.prisms_at(tt)[..., k, :], t,
                                      fx.tracking_lag_s)
        q_station = (q_world - t_station) @ R
        if fx.tripod_settling:
            q_station = settle_points(q_station, *reality.settling_at(k, t))
        dhz, dv, dd = _polar_change((p_world - t_station) @ R, q_station, ot.ppm)
    if fx.prism_cyclic:
        R_world_robot, _ = model.robot_at(t)
        # azimuth, in the robot frame, of the line of sight from the prism to the station
        los_robot = np.einsum("nji,nj->ni", R_world_robot, t_station - p_world)
        alpha = np.arctan2(los_robot[:, 1], los_robot[:, 0])
        _, v0, d0 = cartesian_to_polar((p_world - t_station) @ R)
        e_range = prism_cyclic_error(alpha, fx.prism_cyclic_range_m, fx.prism_cyclic_period_rad,
                                     reality.prism_phase_rad[k, 0])
        e_across = prism_cyclic_error(alpha, fx.prism_cyclic_across_m,
                                      fx.prism_cyclic_period_rad, reality.prism_phase_rad[k, 1])
        dd = dd + e_range / (1.0 + ot.ppm * 1e-6)
        dhz = dhz + e_across / (d0 * np.sin(v0))
    if fx.correlated_noise:
        x = gauss_markov(t, fx.correlated_time_s,
                         [fx.correlated_sigma_angle_rad, fx.correlated_sigma_angle_rad,
                          fx.correlated_sigma_distance_m], draw["correlated_noise"])
        dhz, dv, dd = dhz + x[:, 0], dv + x[:, 1], dd + x[:, 2]
    t_rec = obs.t - reality.clock_error_s(k, t) if fx.clock_drift else obs.t
    return (Observations(t_rec, np.mod(obs.hz + dhz, 2.0 * np.pi), obs.v + dv, obs.d + dd,
                         obs.status, obs.station, obs.prism, obs.additive_constant, obs.source),
            replace(ot, clock_error_s=t - t_rec))


def _reality(
    cfg: SimulationConfig, rng: np.random.Generator, model: TruthModel, stations: _Stations,
    observations: list[Observations], observations_truth: dict[str, ObservationTruth],
    gcp: _Gcp, weather_reported: WeatherSeries,
):
    """Apply the reality effects of ``cfg.reality`` (:mod:`rtsgt.simulation.reality`) to the
    tracking measurements and their stamps, the GCP shots (tripod settling) and the reported
    weather. Returns them in the same form, with the :class:`RealityTruth`."""
    fx = cfg.reality
    reality, draw = _reality_draws(cfg, rng, stations.ids, gcp)
    new_obs, new_truth = [], {}
    for k, obs in enumerate(observations):  # loop over stations
        o, ot = _reality_track(cfg, reality, draw, model, stations, k, obs,
                               observations_truth[obs.station])
        new_obs.append(o)
        new_truth[obs.station] = ot
    if fx.tripod_settling:
        shots = gcp.shots
        p_station = _in_station_frames(stations, gcp.station, gcp.world[gcp.marker])
        f = settling_fraction(gcp.t_true, reality.settling_start_s[gcp.station],
                              fx.settling_time_s)
        q_station = settle_points(p_station, reality.settling_sink_m[gcp.station] * f,
                                  reality.settling_twist_rad[gcp.station] * f)
        dhz, dv, dd = _polar_change(p_station, q_station, _true_ppm(cfg, model, gcp.t_true))
        gcp = gcp._replace(shots=replace(shots, hz=np.mod(shots.hz + dhz, 2.0 * np.pi),
                                         v=shots.v + dv, d=shots.d + dd))
    if fx.remote_weather:
        w = weather_reported
        T, P = remote_weather(w.temperature_c, w.pressure_hpa, fx.remote_temperature_bias_c,
                              fx.remote_altitude_difference_m)
        weather_reported = WeatherSeries(w.t, T, P, w.humidity_pct, w.source)
    return new_obs, new_truth, gcp, weather_reported, reality


def _displaced(robot: _Robot, prism: int, displacement_robot_m: np.ndarray) -> _Robot:
    """The robot with prism ``prism`` moved by ``displacement_robot_m`` (robot frame, m)."""
    prisms = robot.prisms_robot.copy()
    prisms[prism] += displacement_robot_m
    return robot._replace(prisms_robot=prisms,
                          reference_body=prisms @ robot.R_body_robot.T + robot.t_body_robot)


def _field(
    cfg: SimulationConfig, field_truth: FieldTruth, entropy: int,
    observations: list[Observations], observations_truth: dict[str, ObservationTruth],
    gcp: _Gcp,
):
    """Apply the field noise (GCP shots and tracking of a station: one process over both) and
    the clocks' drift and walk (tracking stamps) of ``field_truth``
    (:mod:`rtsgt.simulation.field`); returns the observations, their truth and the GCP."""
    g = field_rng(entropy, "noise")
    ft, c = field_truth, cfg.additive_constant_m
    shots = gcp.shots
    gcp_err = np.zeros((shots.d.size, 3))
    new_obs, new_truth = [], {}
    for k, obs in enumerate(observations):  # loop over stations
        ot = observations_truth[obs.station]
        mine = np.flatnonzero(gcp.station == k)
        e = field_noise(np.concatenate([gcp.t_true[mine], ot.t_true]),
                        np.concatenate([shots.d[mine], obs.d]) + c, ft.white[k],
                        ft.range_coef[k], ft.gm_sigma[k], ft.gm_tau_s[k], g)
        gcp_err[mine], e = e[:mine.size], e[mine.size:]
        t_rec = obs.t - ft.drift_walk_s(k, ot.t_true)
        new_obs.append(replace(obs, t=t_rec, hz=np.mod(obs.hz + e[:, 0], 2.0 * np.pi),
                               v=obs.v + e[:, 1], d=obs.d + e[:, 2]))
        new_truth[obs.station] = replace(ot, clock_error_s=ot.t_true - t_rec)
    shots = replace(shots, hz=np.mod(shots.hz + gcp_err[:, 0], 2.0 * np.pi),
                    v=shots.v + gcp_err[:, 1], d=shots.d + gcp_err[:, 2])
    return new_obs, new_truth, gcp._replace(shots=shots)


def _truth(
    cfg: SimulationConfig, model: TruthModel, stations: _Stations, robot: _Robot,
    offsets: np.ndarray, gcp: _Gcp, observations: dict[str, ObservationTruth],
    reality: RealityTruth | None = None, field_truth: FieldTruth | None = None,
) -> SimulationTruth:
    """The exported truth: ``T_world_body`` and the prisms at ``truth_rate_hz``, and the rest."""
    n_truth = int(np.floor(cfg.duration_s * cfg.truth_rate_hz + 1e-9)) + 1
    t = model.t0 + np.arange(n_truth) / cfg.truth_rate_hz
    R_wr, t_wr = model.robot_at(t)
    R_wb, p_wb = model.body_from_robot(R_wr, t_wr)
    ids = stations.ids
    return SimulationTruth(
        t=t,
        body=PoseTrajectory(t, p_wb, matrix_to_quat_xyzw(R_wb)),
        prisms_world=model.prisms_from_robot(R_wr, t_wr),
        prism_ids=ids,
        T_world_station={
            sid: RigidTransform(stations.R_world[k], stations.t_world[k], None, "world",
                                f"station{sid}")
            for k, sid in enumerate(ids)
        },
        station_prism={sid: sid for sid in ids},
        clock_offset_s={sid: float(offsets[k]) for k, sid in enumerate(ids)},
        reference_body=robot.reference_body,
        gnss_body=robot.gnss_body,
        T_body_robot=RigidTransform(robot.R_body_robot, robot.t_body_robot, None, "body",
                                    "robot"),
        gcp_markers=gcp.markers,
        gcp_world=gcp.world,
        observations=observations,
        additive_constant=cfg.additive_constant_m,
        model=model,
        reality=reality,
        field=field_truth,
    )


def simulate_deployment(
    config: SimulationConfig, rng: np.random.Generator | int
) -> SimulatedDeployment:
    """Simulate a deployment with known truth (``rng``: Generator or int seed); nothing is written.

    Draw order: path, terrain, speed, stations, robot and survey frame (``config.field``: one integer
    seeding its streams), weather, clocks, tracking, GCPs, survey, reported weather; then, only with
    a reality effect on, one integer seeding the effects' streams. InputError on a bad ``config`` or
    ``rng``, or when no valid path, set-up or GCP visibility exists.
    """
    if not isinstance(config, SimulationConfig):
        raise InputError(f"Expected a SimulationConfig, got {type(config).__name__}")
    seed = None
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
        seed = int(rng)
        rng = np.random.default_rng(seed)
    if not isinstance(rng, np.random.Generator):
        raise InputError(f"Expected a numpy.random.Generator or an int seed, got {rng!r}")
    cfg = config
    loop = _loop_shape(cfg, rng)
    terrain = _terrain(cfg, rng)
    speed = _speed_profile(cfg, rng)
    if cfg.reality.jerky_ramps:
        speed = _jerky_ramps(speed, cfg.reality.jerky_accel_m_s2)
    stations = _place_stations(cfg, rng, loop, terrain)
    robot = _robot_geometry(cfg, rng)
    true_robot, displaced, entropy, rocking = robot, None, 0, None
    if cfg.field is not None:  # a prism moved after the survey: the survey keeps `robot`
        entropy = int(rng.integers(0, 2**63 - 1))
        displaced = draw_displacement(cfg.field, robot.prisms_robot.shape[0],
                                      field_rng(entropy, "displacement"))
        true_robot = _displaced(robot, *displaced)
        rocking = draw_rocking(cfg.field, field_rng(entropy, "rocking"))
    R_robot_body = robot.R_body_robot.T
    model = TruthModel(
        t0=float(cfg.start_time_s), **speed._asdict(), **loop._asdict(), terrain=terrain,
        R_world_site=stations.R_world_site, t_world_site=stations.t_world_site,
        prisms_robot=true_robot.prisms_robot, R_robot_body=R_robot_body,
        t_robot_body=-R_robot_body @ robot.t_body_robot, weather_params=_weather_params(cfg, rng),
        rocking=rocking, rocking_speed_m_s=float(np.max(speed.level, initial=0.0)) or 1.0,
        rocking_speed_exponent=1.0 if cfg.field is None else cfg.field.rocking_speed_exponent,
    )
    offsets = _clock_offsets(cfg, rng)
    observations, observations_truth = _track(cfg, rng, model, stations, offsets)
    gcp = _gcp(cfg, rng, model, stations, offsets)
    survey = _survey(cfg, rng, robot)
    weather_true, weather_reported = _weather(
        cfg, rng, model, min(gcp.first_shot_s, float(cfg.start_time_s)))
    field_truth = None
    if cfg.field is not None:
        field_truth = draw_field_truth(cfg.field, stations.ids, offsets, float(cfg.start_time_s),
                                       cfg.duration_s, displaced, robot.R_body_robot, entropy,
                                       rocking)
        observations, observations_truth, gcp = _field(cfg, field_truth, entropy, observations,
                                                       observations_truth, gcp)
    reality = None
    if cfg.reality.enabled:
        observations, observations_truth, gcp, weather_reported, reality = _reality(
            cfg, rng, model, stations, observations, observations_truth, gcp, weather_reported)
    truth = _truth(cfg, model, stations, true_robot, offsets, gcp, observations_truth, reality,
                   field_truth)
    return SimulatedDeployment(observations, gcp.shots, survey, weather_true, weather_reported,
                               truth, cfg, seed)
