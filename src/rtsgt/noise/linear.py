"""First-order (Jacobian) propagation of the per-measurement noise model.

The total and per-source covariances of every measurement, each source's term from its class
in :mod:`rtsgt.noise.sources` (a sum of weighted outer products of vectors rotated to the
world frame), plus the interaction of the clock error with the noise of the differenced
velocity, which belongs to the total only. Formulas: docs/noise-model.md (each source's
section, and #first-order).
"""

from __future__ import annotations

import numpy as np

from rtsgt.noise.model import NoiseModel, Nominal, difference_stencil
from rtsgt.noise.packed import small_matmul, unpack
from rtsgt.noise.sources import SOURCES, FirstOrder


def linear_covariances(
    nom: Nominal, model: NoiseModel, T_world_station=None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """World-frame total (N, 3, 3) and per-source covariances (dict of (N, 3, 3)), m^2, by
    first-order propagation from ``nom`` (:func:`rtsgt.noise.model.prepare_nominal`);
    ``T_world_station``'s covariance (or samples) feeds the calibration source."""
    srcs = model.sources
    N = nom.d.shape[0]
    R = nom.R
    sh, ch = np.sin(nom.hz), np.cos(nom.hz)
    sv, cv = np.sin(nom.v), np.cos(nom.v)
    d = nom.d_corr
    # columns of polar_jacobian(hz, v, d) (measurement/polar.py), rotated to the world frame,
    # as (3, N) arrays: d p / d Hz = d sV (cH, -sH, 0), d p / d V = d (cV sH, cV cH, -sV),
    # d p / d d = u (unit line of sight)
    dsv = d * sv
    j_hz = small_matmul(R, np.stack([dsv * ch, -dsv * sh, np.zeros(N)]))
    dcv = d * cv
    j_v = small_matmul(R, np.stack([dcv * sh, dcv * ch, -dsv]))
    u = small_matmul(R, np.stack([sv * sh, sv * ch, cv]))
    f = FirstOrder(nom, model, j_hz, j_v, u, T_world_station)
    packed = {s: SOURCES[s].first_order(f) for s in srcs}
    total = np.zeros((6, N))
    for c in packed.values():
        total += c
    interaction = _time_sync_interaction(nom, model, packed)
    if interaction is not None:
        total += interaction
    by_source = {s: unpack(packed[s]) for s in srcs}
    return unpack(total), by_source


def _time_sync_interaction(nom: Nominal, model: NoiseModel, packed: dict) -> np.ndarray | None:
    """``m2 (Sigma_next + Sigma_prev) / dt^2``, packed (6, N): the clock error times the noise
    of the differenced velocity, from the sources that displace the readings
    (docs/noise-model.md#time-synchronisation); None when it does not apply."""
    if "time_sync" not in packed:
        return None
    meas = [c for s, c in packed.items() if SOURCES[s].displaces_reading]
    if not meas or not np.any(nom.velocity_valid):
        return None
    m2 = model.time_sync_second_moment_s2
    sig = np.sum(meas, axis=0)
    prev, nxt, dt = difference_stencil(nom.t, model.max_velocity_gap_s)
    valid = nom.velocity_valid
    w = np.where(valid, m2 / np.where(valid, dt, 1.0) ** 2, 0.0)
    interaction = sig[:, nxt] + sig[:, prev]
    interaction *= w
    return interaction
