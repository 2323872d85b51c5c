r"""Field effects: measurement noise, clocks and a moved prism drawn as a real hour is.

Under ``SimulationConfig(field=FieldEffects())`` (``--preset field-hour``): per station and
channel a white sigma growing with range plus a Gauss-Markov part, drifting and random-walking
clocks, one prism off its survey, the vehicle rocking on its suspension as it drives;
:class:`FieldTruth` records every draw. Models and values:
docs/simulation.md#the-field-hour-preset.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError
from rtsgt.simulation.reality import gauss_markov

__all__ = [
    "CHANNELS",
    "FIELD_STREAMS",
    "MGON",
    "FieldEffects",
    "FieldTruth",
    "clock_walk",
    "draw_displacement",
    "draw_field_truth",
    "draw_rocking",
    "field_noise",
    "field_rng",
    "white_sigma",
]

#: One milligon, rad.
MGON = np.pi / 200.0 * 1e-3
#: The measurement channels, in the order of every (..., 3) array here.
CHANNELS = ("hz", "v", "d")
#: The field effects' random streams, in the order of their spawn keys (:func:`field_rng`).
FIELD_STREAMS = ("displacement", "parameters", "clock", "noise", "rocking")
#: Sinusoids per axis of the vehicle's rocking (:func:`draw_rocking`).
ROCKING_TERMS = 24
#: Range at which the angular range coefficient is stated, m.
RANGE_UNIT_M = 100.0


@dataclass(frozen=True)
class FieldEffects:
    """Ranges ``(low, high)`` the field effects' sizes are drawn from (uniform; correlation times
    log-uniform); units in the names (docs/simulation.md#the-field-hour-preset). The
    rocking's size while driving goes as ``(v / top speed) ** rocking_speed_exponent`` (1:
    proportional to the speed, the preset's; 0: one size, what both real deployments show,
    docs/simulation.md#the-vehicles-rocking); none where the robot stands.
    """

    angle_white_rad: tuple[float, float] = (0.10 * MGON, 0.25 * MGON)
    angle_range_rad: tuple[float, float] = (0.05 * MGON, 0.15 * MGON)
    angle_gm_rad: tuple[float, float] = (0.10 * MGON, 0.30 * MGON)
    distance_white_m: tuple[float, float] = (0.5e-3, 0.7e-3)
    distance_ppm: tuple[float, float] = (0.5, 1.5)
    distance_gm_m: tuple[float, float] = (0.2e-3, 0.5e-3)
    gm_time_s: tuple[float, float] = (1.0, 12.0)
    clock_drift_s_per_h: tuple[float, float] = (10e-3, 20e-3)
    clock_walk_s_per_sqrt_h: float = 1.0e-3
    prism_displacement_m: tuple[float, float] = (0.01, 0.03)
    rocking_angle_rad: tuple[float, float] = (0.7e-3, 2.8e-3)
    rocking_shift_m: tuple[float, float] = (1.0e-3, 5.0e-3)
    rocking_heave_m: tuple[float, float] = (0.35e-3, 1.4e-3)
    rocking_hz: tuple[float, float] = (0.5, 3.0)
    rocking_speed_exponent: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            val = np.asarray(getattr(self, f.name), dtype=float)
            if not (np.all(np.isfinite(val)) and np.all(val >= 0)):
                raise InputError(f"Expected finite values >= 0 for {f.name}, got "
                                 f"{getattr(self, f.name)!r}")
            if val.ndim == 1 and not (val.shape == (2,) and val[0] <= val[1]):
                raise InputError(f"Expected {f.name} = (low, high) with low <= high, got "
                                 f"{getattr(self, f.name)!r}")
        if not self.gm_time_s[0] > 0:
            raise InputError(f"Expected gm_time_s > 0, got {self.gm_time_s!r}")
        if not self.rocking_hz[0] > 0:
            raise InputError(f"Expected rocking_hz > 0, got {self.rocking_hz!r}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: every range."""
        return {k: (list(map(float, v)) if isinstance(v, tuple) else float(v))
                for k, v in asdict(self).items()}


def field_rng(entropy: int, stream: str) -> np.random.Generator:
    """The random stream ``stream`` (:data:`FIELD_STREAMS`) of the field effects: child ``i``
    of ``numpy.random.SeedSequence(entropy)``, like :func:`rtsgt.simulation.reality.effect_rng`."""
    return np.random.default_rng(
        np.random.SeedSequence(int(entropy), spawn_key=(FIELD_STREAMS.index(stream),)))


def white_sigma(d_m: ArrayLike, white: ArrayLike, range_coef: ArrayLike) -> np.ndarray:
    """White sigma of (Hz, V, d) at ranges ``d_m`` (N,), shape (N, 3): rad, rad, m.

    ``sigma_angle = sqrt(w^2 + s^2 d / 100 m)`` and ``sigma_d = w_d + ppm 1e-6 d``, with
    ``white = (w_hz, w_v, w_d)`` and ``range_coef = (s_hz, s_v, ppm)``.
    """
    d = np.asarray(d_m, dtype=float)[:, None]
    w = np.asarray(white, dtype=float)
    c = np.asarray(range_coef, dtype=float)
    angle = np.sqrt(w[:2] ** 2 + c[:2] ** 2 * d / RANGE_UNIT_M)
    return np.concatenate([angle, w[2] + 1e-6 * c[2] * d], axis=1)


def field_noise(t: ArrayLike, d_m: ArrayLike, white: ArrayLike, range_coef: ArrayLike,
                gm_sigma: ArrayLike, gm_tau_s: ArrayLike, rng: np.random.Generator) -> np.ndarray:
    """Errors (N, 3) of one station's measurements (Hz rad, V rad, d m) at true times ``t``
    (N,, any order) and ranges ``d_m`` (N,): white (:func:`white_sigma`) plus a first-order
    Gauss-Markov process per channel (:func:`rtsgt.simulation.reality.gauss_markov`, sigma
    ``gm_sigma``, correlation time ``gm_tau_s``, each (3,)), started stationary."""
    t = np.asarray(t, dtype=float)
    order = np.argsort(t, kind="stable")
    e = rng.standard_normal((t.size, 3)) * white_sigma(d_m, white, range_coef)
    gm = np.empty((t.size, 3))
    for c in range(3):  # loop over the three channels
        gm[order, c] = gauss_markov(t[order], float(gm_tau_s[c]), [gm_sigma[c]], rng)[:, 0]
    return e + gm


def clock_walk(n_steps: int, step_s: float, drift_s_per_s: float, walk_s2_per_s: float,
               rng: np.random.Generator) -> np.ndarray:
    """A clock error sampled every ``step_s`` from 0: ``r t + W(t)``, ``W`` a random walk
    (Wiener process of intensity ``walk_s2_per_s``, ``var W(t) = q t``), ``W(0) = 0``;
    shape (n_steps + 1,), s."""
    steps = rng.standard_normal(int(n_steps)) * np.sqrt(walk_s2_per_s * step_s)
    return drift_s_per_s * step_s * np.arange(n_steps + 1) + np.concatenate(
        [[0.0], np.cumsum(steps)])


def draw_rocking(fx: FieldEffects, rng: np.random.Generator) -> np.ndarray:
    """The vehicle's rocking as it drives, relative to its path at full speed: per axis of the
    robot frame (rotations about x, y, z, then shifts along x, y, z) :data:`ROCKING_TERMS`
    sinusoids, rows ``(axis, amplitude, frequency Hz, phase rad)`` (6 x terms, 4): each axis's
    RMS drawn uniform in ``rocking_angle_rad`` (rotations), ``rocking_shift_m`` (along and
    across the travel) or ``rocking_heave_m`` (up), shared equally by its sinusoids (a sum of
    many random-phase sinusoids: nearly Gaussian), frequencies log-uniform in ``rocking_hz``
    (docs/simulation.md#the-field-hour-preset)."""
    n = ROCKING_TERMS
    rms = np.concatenate([rng.uniform(*fx.rocking_angle_rad, 3), rng.uniform(*fx.rocking_shift_m, 2),
                          rng.uniform(*fx.rocking_heave_m, 1)])
    lo, hi = np.log(fx.rocking_hz)
    freq = np.exp(rng.uniform(lo, hi, (6, n)))
    phase = rng.uniform(0.0, 2.0 * np.pi, (6, n))
    axis = np.repeat(np.arange(6.0), n).reshape(6, n)
    amp = np.repeat(rms * np.sqrt(2.0 / n), n).reshape(6, n)
    return np.stack([axis, amp, freq, phase], axis=-1).reshape(6 * n, 4)


def draw_displacement(fx: FieldEffects, n_prisms: int,
                      rng: np.random.Generator) -> tuple[int, np.ndarray]:
    """Which prism moved (index) and its displacement in the robot frame (3,), m: size
    uniform in ``prism_displacement_m``, direction uniform on the sphere."""
    k = int(rng.integers(0, n_prisms))
    u = rng.standard_normal(3)
    return k, rng.uniform(*fx.prism_displacement_m) * u / np.linalg.norm(u)


@dataclass(frozen=True, eq=False)
class FieldTruth:
    """What the field effects drew (S stations in order, the first the reference; channels
    :data:`CHANNELS`): per-channel ``white``, ``range_coef``, ``gm_sigma``, ``gm_tau_s`` (S, 3);
    ``clock_drift_s_per_s``, ``clock_walk_s2_per_s``, ``clock_offset_s`` (S,); drift plus walk
    ``clock_drift_walk_s`` (S, M) at ``clock_t0_s + clock_step_s k`` (linear between);
    ``displaced_prism`` and its ``displacement_robot_m``, ``displacement_body_m`` (3,);
    ``rocking`` the vehicle's rocking at full speed (:func:`draw_rocking`)
    (docs/simulation.md#the-field-truth-truthjson-section-field).
    """

    effects: FieldEffects
    station_ids: tuple[str, ...]
    white: np.ndarray
    range_coef: np.ndarray
    gm_sigma: np.ndarray
    gm_tau_s: np.ndarray
    clock_drift_s_per_s: np.ndarray
    clock_walk_s2_per_s: np.ndarray
    clock_t0_s: float
    clock_step_s: float
    clock_drift_walk_s: np.ndarray
    clock_offset_s: np.ndarray
    displaced_prism: int
    displacement_robot_m: np.ndarray
    displacement_body_m: np.ndarray
    rocking: np.ndarray | None = None

    @property
    def rocking_rms(self) -> np.ndarray:
        """The rocking's RMS (6,) per axis at full speed (rotations about the robot's x, y, z,
        rad, then shifts along them, m; zero without it): ``sqrt(sum a^2 / 2)``."""
        if self.rocking is None:
            return np.zeros(6)
        return np.sqrt(np.bincount(self.rocking[:, 0].astype(int), self.rocking[:, 1] ** 2 / 2.0,
                                   minlength=6))

    @property
    def clock_t(self) -> np.ndarray:
        """Times of the clock samples, s, shape (M,)."""
        return self.clock_t0_s + self.clock_step_s * np.arange(self.clock_drift_walk_s.shape[1])

    def drift_walk_s(self, k: int, t: ArrayLike) -> np.ndarray:
        """Drift plus walk of station ``k``'s clock at true times ``t`` (0 before
        ``clock_t0_s``, held after the last sample), s."""
        return np.interp(np.asarray(t, dtype=float), self.clock_t, self.clock_drift_walk_s[k],
                         left=0.0)

    def clock_error_s(self, k: int, t: ArrayLike) -> np.ndarray:
        """``t_true - t_recorded`` of station ``k`` at true times ``t``, without the
        per-measurement jitter, s."""
        return self.clock_offset_s[k] + self.drift_walk_s(k, t)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the ranges, every draw per station and the clocks sampled."""
        per = {}
        for k, sid in enumerate(self.station_ids):
            noise = {ch: {"white_sigma": float(self.white[k, c]),
                          "gm_sigma": float(self.gm_sigma[k, c]),
                          "gm_tau_s": float(self.gm_tau_s[k, c])}
                     for c, ch in enumerate(CHANNELS)}
            for c, ch in enumerate(CHANNELS[:2]):
                noise[ch]["range_sigma_at_100m"] = float(self.range_coef[k, c])
            noise["d"]["ppm"] = float(self.range_coef[k, 2])
            per[sid] = {"noise": noise,
                        "clock": {"offset_s": float(self.clock_offset_s[k]),
                                  "drift_s_per_h": float(3600.0 * self.clock_drift_s_per_s[k]),
                                  "walk_s2_per_s": float(self.clock_walk_s2_per_s[k]),
                                  "error_s": (self.clock_offset_s[k]
                                              + self.clock_drift_walk_s[k]).tolist()}}
        return {
            "effects": self.effects.to_dict(),
            "reference_station": self.station_ids[0],
            "clock_t0_s": float(self.clock_t0_s),
            "clock_step_s": float(self.clock_step_s),
            "stations": per,
            "displaced_prism": {"index": int(self.displaced_prism),
                                "robot_m": self.displacement_robot_m.tolist(),
                                "body_m": self.displacement_body_m.tolist(),
                                "size_m": float(np.linalg.norm(self.displacement_robot_m))},
            "rocking_rms_at_top_speed": dict(zip(
                ("roll_rad", "pitch_rad", "yaw_rad", "surge_m", "sway_m", "heave_m"),
                map(float, self.rocking_rms), strict=True)),
        }


def draw_field_truth(fx: FieldEffects, station_ids: tuple[str, ...], clock_offset_s: ArrayLike,
                     t0_s: float, duration_s: float, displaced: tuple[int, np.ndarray],
                     R_body_robot: np.ndarray, entropy: int,
                     rocking: np.ndarray | None = None) -> FieldTruth:
    """Draw the noise parameters (stream ``parameters``) and the clocks (stream ``clock``, sampled
    at 1 Hz over ``[t0_s, t0_s + duration_s]`` and one step beyond) of a deployment;
    ``displaced`` from :func:`draw_displacement`, ``rocking`` from :func:`draw_rocking` (kept
    as drawn)."""
    n = len(station_ids)
    g = field_rng(entropy, "parameters")
    white = np.stack([g.uniform(*fx.angle_white_rad, n), g.uniform(*fx.angle_white_rad, n),
                      g.uniform(*fx.distance_white_m, n)], axis=1)
    range_coef = np.stack([g.uniform(*fx.angle_range_rad, n), g.uniform(*fx.angle_range_rad, n),
                           g.uniform(*fx.distance_ppm, n)], axis=1)
    gm_sigma = np.stack([g.uniform(*fx.angle_gm_rad, n), g.uniform(*fx.angle_gm_rad, n),
                         g.uniform(*fx.distance_gm_m, n)], axis=1)
    gm_tau = np.exp(g.uniform(*np.log(fx.gm_time_s), (n, 3)))
    c = field_rng(entropy, "clock")
    drift = np.concatenate([[0.0], c.choice([-1.0, 1.0], n - 1)
                            * c.uniform(*fx.clock_drift_s_per_h, n - 1)]) / 3600.0
    walk = np.concatenate([[0.0], np.full(n - 1, fx.clock_walk_s_per_sqrt_h ** 2 / 3600.0)])
    step = 1.0
    n_steps = int(np.ceil(duration_s / step)) + 1
    clocks = np.stack([clock_walk(n_steps, step, drift[k], walk[k], c) for k in range(n)])
    k_prism, disp = displaced
    return FieldTruth(fx, tuple(station_ids), white, range_coef, gm_sigma, gm_tau, drift, walk,
                      float(t0_s), step, clocks, np.asarray(clock_offset_s, dtype=float),
                      k_prism, disp, R_body_robot @ disp, rocking)
