"""Raw polar measurements (Hz, V, d) of the prisms, their white covariance and their model.

The prediction ``h(T_k, w_k, T_world_station, kappa)`` and its Jacobians, and each
measurement's covariance from the per-prism noise model (:mod:`rtsgt.noise`) mapped to
(Hz, V, d): docs/joint.md#the-measurements.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.errors import InputError
from rtsgt.geometry.so3 import hat
from rtsgt.measurement.atmosphere import correction_ppm_gradient
from rtsgt.noise.linear import linear_covariances
from rtsgt.noise.model import NoiseModel, prepare_nominal

#: Noise sources the joint engine carries as estimated parameters, not as white noise.
GLOBAL_SOURCES = ("calibration", "atmosphere")


@dataclass(frozen=True)
class PolarMeasurements:
    """M measurements: ``t`` (M,) s; ``station``, ``prism`` (M,) indices into the problem's
    stations and prisms; ``y`` (M, 3) ``(hz, v, d)`` rad, rad, m (``d`` with the additive
    constant and the atmospheric correction, as :func:`rtsgt.noise.model.prepare_nominal`);
    ``info`` (M, 3, 3) the inverse of their white covariance (rad, rad, m);
    ``kappa_sigma_ppm`` the prior sigma of the weather's error of the correction, ppm;
    ``var_white`` (M, 3) the noise model's (datasheet) white variances of (Hz, V, d) and
    ``corr`` (M, 3, 3) their correlation (``info`` the inverse of their covariance, until
    the noise is identified: docs/joint.md#noise-identification)."""

    t: np.ndarray
    station: np.ndarray
    prism: np.ndarray
    y: np.ndarray
    info: np.ndarray
    kappa_sigma_ppm: float
    var_white: np.ndarray | None = None
    corr: np.ndarray | None = None


def polar_jacobian_inverse(q: np.ndarray) -> np.ndarray:
    """``d (hz, v, d) / d q`` (M, 3, 3) of :func:`rtsgt.measurement.polar.cartesian_to_polar`
    at station-frame points ``q`` (M, 3), m."""
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    r2 = x * x + y * y
    r = np.sqrt(r2)
    d2 = r2 + z * z
    d = np.sqrt(d2)
    P = np.empty(q.shape[:1] + (3, 3))
    P[:, 0] = np.stack([y / r2, -x / r2, np.zeros_like(x)], axis=1)
    P[:, 1] = np.stack([x * z / (r * d2), y * z / (r * d2), -r / d2], axis=1)
    P[:, 2] = q / d[:, None]
    return P


def white_model(model: NoiseModel, carried: tuple[str, ...] = GLOBAL_SOURCES) -> NoiseModel:
    """The noise model's sources the joint engine carries as white noise (all but
    ``carried``, those it estimates as parameters)."""
    srcs = tuple(s for s in model.sources if s not in carried)
    if "instrument" not in srcs:
        raise InputError(f"Expected the 'instrument' noise source, got {model.sources}")
    return model.with_sources(srcs)


def polar_measurements(observations, station_ids, prism_ids, model: NoiseModel,
                       weather=None, carried: tuple[str, ...] = GLOBAL_SOURCES
                       ) -> PolarMeasurements:
    """Stack every station's observations (one :class:`rtsgt.types.Observations` each, valid,
    strictly increasing times) with their white covariance in (Hz, V, d) (the model's
    sources but ``carried``)."""
    white = white_model(model, carried)
    parts = []
    var_ppm = []
    for obs in observations:
        if obs.station not in station_ids:
            raise InputError(f"Observations of station {obs.station!r}: no such station in "
                             f"the calibration ({', '.join(station_ids)})", obs.source)
        if obs.prism not in prism_ids:
            raise InputError(f"Observations of prism {obs.prism!r}: no such reference prism "
                             f"({', '.join(prism_ids)})", obs.source)
        nom = prepare_nominal(obs, white, None, weather)
        cov_station, _ = linear_covariances(nom, white)
        P = polar_jacobian_inverse(nom.xyz_station)
        cov = P @ cov_station @ np.swapaxes(P, 1, 2)
        var_w = np.einsum("mii->mi", cov)
        sd = np.sqrt(var_w)
        y = np.stack([nom.hz, nom.v, nom.d_corr], axis=1)
        n = y.shape[0]
        parts.append((nom.t, np.full(n, station_ids.index(obs.station)),
                      np.full(n, prism_ids.index(obs.prism)), y, np.linalg.inv(cov), var_w,
                      cov / (sd[:, :, None] * sd[:, None, :])))
        prof = model.instrument
        g = correction_ppm_gradient(
            nom.temperature_c, nom.pressure_hpa, nom.humidity_pct,
            wavelength_um=prof.wavelength_um, formula=model.vapour_formula,
            reference=(prof.reference_temperature_c, prof.reference_pressure_hpa,
                       prof.reference_humidity_pct))
        var_ppm.append(sum(np.mean(gi) ** 2 * v for gi, v in zip(g, model.weather_variances, strict=True)))
    t, st, pr, y, info, var_i, rest = (np.concatenate(a) for a in zip(*parts, strict=True))
    order = np.argsort(t, kind="stable")
    sigma = float(np.sqrt(np.mean(var_ppm))) if "atmosphere" in model.sources else 0.0
    return PolarMeasurements(t[order], st[order], pr[order], y[order], info[order], sigma,
                             var_i[order], rest[order])


def predict(R_k, t_k, w_k, tau, p_body, R_s, t_s, kappa_ppm):
    """Predicted ``(hz, v, d)`` (M, 3) and Jacobians of M measurements.

    Inputs per measurement: its knot's pose ``R_k`` (M, 3, 3), ``t_k`` (M, 3) and body velocity
    ``w_k`` (M, 6), its offset from the knot ``tau`` (M,) s, its prism's body position
    ``p_body`` (M, 3), its station ``R_s`` (M, 3, 3), ``t_s`` (M, 3), and ``kappa_ppm``.
    The prism is carried from the knot at the knot's constant body velocity to second order
    in ``tau`` (docs/joint.md#the-measurements).
    Returns ``h``, ``H_knot`` (M, 3, 12) with respect to ``(d_k, dw_k)`` (right perturbation),
    ``H_station`` (M, 3, 6) with respect to ``(dt, dtheta)`` of the station (world frame, left),
    ``H_kappa`` (M, 3), ``H_tau`` (M, 3) with respect to ``tau`` (the rate of ``h``, 1/s) and
    ``B_point`` (M, 3, 3), the carried point's derivative with respect to ``p_body`` (``d h /
    d p_body`` is ``H_knot[:, :, :3] @ B_point``).
    """
    # body point at the measurement time: b = p + tau u + tau^2 / 2 omega x u, u = v + omega x p
    # (exp(tau w^) p to second order in tau)
    om = w_k[:, 3:]
    u = w_k[:, :3] + np.cross(om, p_body)
    wu = np.cross(om, u)
    tt = tau[:, None]
    b = p_body + tt * u + 0.5 * tt * tt * wu
    p_w = np.einsum("mij,mj->mi", R_k, b) + t_k
    Rst = np.swapaxes(R_s, 1, 2)
    q = np.einsum("mij,mj->mi", Rst, p_w - t_s)
    P = polar_jacobian_inverse(q)
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    dist = np.sqrt(x * x + y * y + z * z)
    scale = 1.0 + 1e-6 * kappa_ppm
    h = np.stack([np.mod(np.arctan2(x, y), 2 * np.pi), np.arctan2(np.hypot(x, y), z),
                  dist * scale], axis=1)
    P[:, 2] *= scale
    PR = P @ Rst @ R_k  # d h / d (body point)
    M = q.shape[0]
    t3 = tau[:, None, None]
    W = hat(om)
    half = 0.5 * t3 * t3
    H_knot = np.empty((M, 3, 12))
    H_knot[:, :, :3] = PR
    H_knot[:, :, 3:6] = -PR @ hat(b)
    H_knot[:, :, 6:9] = PR @ (t3 * np.eye(3) + half * W)  # d b / d v
    H_knot[:, :, 9:] = -PR @ (t3 * hat(p_body) + half * (hat(u) + W @ hat(p_body)))
    H_station = np.empty((M, 3, 6))
    PRs = P @ Rst
    H_station[:, :, :3] = -PRs
    H_station[:, :, 3:] = PRs @ hat(p_w - t_s)
    H_kappa = np.zeros((M, 3))
    H_kappa[:, 2] = 1e-6 * dist
    B_point = np.eye(3) + t3 * W + half * (W @ W)
    return h, H_knot, H_station, H_kappa, np.einsum("mij,mj->mi", PR, u + tt * wu), B_point


def residual(y: np.ndarray, h: np.ndarray) -> np.ndarray:
    """``y - h`` (M, 3) with the horizontal direction wrapped to (-pi, pi]."""
    r = y - h
    r[:, 0] = np.mod(r[:, 0] + np.pi, 2 * np.pi) - np.pi
    return r
