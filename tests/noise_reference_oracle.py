r"""Plain reference Monte Carlo of the per-measurement noise model, for testing the engine.

Perturb, convert, correct, take the sample covariance: the model of :mod:`rtsgt.noise.model`
written sample by sample with the measurement model's own functions, for ``M`` samples of
``N`` measurements at once (arrays of shape (M, N)):

.. math::

    \hat d &= (d + e_d)(1 + 10^{-6} K(T + e_T, p + e_p, \mathrm{clip}(RH + e_{RH}, 0, 100))) \\
    \hat V &= V + e_V + e_{tilt},\qquad \hat{Hz} = Hz + e_{Hz} + e_{tilt} \cot \hat V \\
    p_{world} &= R_m (\mathrm{polar}(\hat{Hz}, \hat V, \hat d) + e_{ts}\, v) + t_m

with the polar errors of :func:`rtsgt.noise.perturb.sample_polar_errors`, ``K`` from
:func:`rtsgt.measurement.atmosphere.instrument_correction_ppm` (the nominal ``K`` when the
``atmosphere`` source is off), :func:`~rtsgt.measurement.polar.polar_to_cartesian`,
``e_ts = s |e|`` (random sign ``s``, ``e ~ N(mu, sigma)``) and transform sample ``m``: the
transform's own Monte Carlo sample ``m``, or :func:`rtsgt.geometry.transform.perturb` by a
draw of its 6x6 covariance (``R, t`` when the ``calibration`` source is off). The result is
the sample mean and the sample covariance (``ddof = 1``) of the points, with every source
alone and with all together.

None of the fast engine's devices (:mod:`rtsgt.noise.montecarlo`): no displacement algebra,
no truncated series, no in-place float32 arithmetic, no closed-form shortcut per source, no
shared draws between sources. It is slower and holds ``M x N x 3`` points in memory:
a second engine for the tests (tests/test_noise_reference.py), not for production.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.errors import InputError
from rtsgt.geometry.transform import perturb
from rtsgt.measurement.atmosphere import apply_correction, instrument_correction_ppm
from rtsgt.measurement.polar import polar_to_cartesian
from rtsgt.noise.model import NoiseModel, Nominal, prepare_nominal
from rtsgt.noise.perturb import sample_polar_errors


@dataclass(frozen=True)
class ReferenceResult:
    """Sample mean and covariance of the reference Monte Carlo (world frame, or the station
    frame without a transform).

    Attributes
    ----------
    mean : ndarray, shape (N, 3)
    cov : ndarray, shape (N, 3, 3)
        All the model's sources together.
    mean_by_source, cov_by_source : dict str -> ndarray (N, 3) / (N, 3, 3)
        Each source alone (independent draws).
    samples : int
    """

    mean: np.ndarray
    cov: np.ndarray
    mean_by_source: dict[str, np.ndarray]
    cov_by_source: dict[str, np.ndarray]
    samples: int


def sample_points(
    nom: Nominal, model: NoiseModel, T_world_station, samples: int, rng: np.random.Generator
) -> np.ndarray:
    """``samples`` Monte Carlo points of every measurement with ``model.sources`` active.

    Returns
    -------
    ndarray, shape (M, N, 3)
        World frame (station frame with ``nom.R = I``, ``nom.t_ws = 0``).
    """
    srcs = model.sources
    prof = model.instrument
    shape = (int(samples), nom.d.shape[0])
    hz, v, d = sample_polar_errors(nom.hz, nom.v, nom.d, prof, shape[0], rng,
                                   instrument="instrument" in srcs, tilt="tilt" in srcs)
    ppm = nom.ppm
    if "atmosphere" in srcs:
        h_t, h_p, h_rh = (model.temperature_halfwidth_c, model.pressure_halfwidth_hpa,
                          model.humidity_halfwidth_pct)
        T = nom.temperature_c + rng.uniform(-h_t, h_t, shape)
        p = nom.pressure_hpa + rng.uniform(-h_p, h_p, shape)
        rh = nom.humidity_pct + rng.uniform(-h_rh, h_rh, shape)
        ppm = instrument_correction_ppm(prof, T, p, np.clip(rh, 0.0, 100.0),
                                        model.vapour_formula)
    xyz = polar_to_cartesian(hz, v, apply_correction(d, ppm))
    if "time_sync" in srcs:
        e = rng.normal(model.time_sync_mean_s, model.time_sync_std_s, shape)
        sign = np.where(rng.random(shape) < 0.5, -1.0, 1.0)
        xyz = xyz + (sign * np.abs(e))[:, :, None] * nom.velocity
    Rs, ts = _transform_samples(T_world_station, shape[0], rng, "calibration" in srcs, nom)
    if Rs.ndim == 2:
        return np.einsum("ij,mnj->mni", Rs, xyz) + ts
    return np.einsum("mij,mnj->mni", Rs, xyz) + ts[:, None, :]


def _transform_samples(T_world_station, samples: int, rng: np.random.Generator, active: bool,
                      nom: Nominal) -> tuple[np.ndarray, np.ndarray]:
    """``(R_m, t_m)`` (M, 3, 3), (M, 3) of the calibration source, or the nominal ``(R, t)``
    (3, 3), (3,) when it is off or the transform carries no uncertainty."""
    T = T_world_station
    if not active or T is None:
        return nom.R, nom.t_ws
    if T.samples_rotation is not None and T.samples_translation is not None:
        if min(len(T.samples_rotation), len(T.samples_translation)) < samples:
            raise InputError(f"The transform carries fewer than the {samples} samples requested")
        return T.samples_rotation[:samples], T.samples_translation[:samples]
    if T.covariance is None:
        return nom.R, nom.t_ws
    xi = rng.multivariate_normal(np.zeros(6), T.covariance, size=samples, method="eigh")
    return perturb(T.rotation, T.translation, xi)


def reference_propagate(
    obs,
    model: NoiseModel,
    *,
    T_world_station=None,
    weather=None,
    samples: int = 1000,
    rng: np.random.Generator,
) -> ReferenceResult:
    """Sample mean and covariance of every measurement, all sources and each alone.

    Same inputs as :func:`rtsgt.noise.propagate` (nominal values from
    :func:`rtsgt.noise.model.prepare_nominal`); every source alone and the total draw their own
    samples from ``rng``.
    """
    M = int(samples)
    if M < 2:
        raise InputError(f"Expected samples >= 2, got {samples!r}")
    nom = prepare_nominal(obs, model, T_world_station, weather)
    means, covs = {}, {}
    for key in model.sources + ("total",):
        sub = model if key == "total" else model.with_sources((key,))
        pts = sample_points(nom, sub, T_world_station, M, rng)
        means[key] = pts.mean(axis=0)
        dev = pts - means[key]
        covs[key] = np.einsum("mni,mnj->nij", dev, dev) / (M - 1)
    mean, cov = means.pop("total"), covs.pop("total")
    return ReferenceResult(mean, cov, means, covs, M)
