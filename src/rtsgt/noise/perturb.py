"""Sampling of the instrument and tilt-compensator errors of polar measurements.

``d^ = d + e_d``, ``V^ = V + e_V + e_tilt``, ``Hz^ = Hz + e_Hz + e_tilt cot V^``
(docs/noise-model.md#instrument, #tilt-compensator).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.measurement.instruments import InstrumentProfile


def sample_polar_errors(
    hz: ArrayLike,
    v: ArrayLike,
    d: ArrayLike,
    profile: InstrumentProfile,
    n_samples: int,
    rng: np.random.Generator,
    *,
    instrument: bool = True,
    tilt: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """M = ``n_samples`` perturbed draws (M, N) each of the polar measurements ``hz``, ``v``
    (rad, clockwise direction and zenith angle) and ``d`` (m, additive constant applied), (N,),
    with ``profile``'s ``instrument`` and/or ``tilt`` errors, drawn from ``rng``."""
    hz = np.asarray(hz, dtype=float)
    v = np.asarray(v, dtype=float)
    d = np.asarray(d, dtype=float)
    shape = (int(n_samples),) + hz.shape
    hz_s = np.broadcast_to(hz, shape).copy()
    v_s = np.broadcast_to(v, shape).copy()
    d_s = np.broadcast_to(d, shape).copy()
    if instrument:
        d_s += rng.standard_normal(shape) * profile.sigma_distance(d)
        v_s += rng.standard_normal(shape) * profile.sigma_angle
        hz_s += rng.standard_normal(shape) * profile.sigma_angle
    if tilt:
        e_tilt = rng.standard_normal(shape) * profile.sigma_tilt
        v_s += e_tilt
        hz_s += e_tilt / np.tan(v_s)
    return hz_s, v_s, d_s
