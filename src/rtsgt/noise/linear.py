r"""First-order (Jacobian) propagation of the per-measurement noise model.

The same model as :mod:`rtsgt.noise.model` and the Monte Carlo engine, linearised at the
nominal measurement. With ``J = d p / d(Hz, V, d)`` the polar Jacobian
(:func:`rtsgt.measurement.polar.polar_jacobian`) at the corrected distance
``d_c = d (1 + alpha_0)`` and ``u = J[:, 2]`` the unit line of sight (station frame):

``instrument``
    ``J diag(sigma_a^2, sigma_a^2, sigma_d^2 (1 + alpha_0)^2) J^T``
    (``d^ = (d + e_d)(1 + alpha)``, so ``d d^ / d e_d = 1 + alpha_0``).
``tilt``
    ``V^ = V + e_t`` and ``Hz^ = Hz + e_t cot V^``: the tilt moves the point along
    ``g = J[:, 0] cot V + J[:, 1]``, covariance ``sigma_t^2 g g^T``.
``atmosphere``
    ``p = u d (1 + 1e-6 K(T, p, RH))``: ``d^2 u u^T 1e-12 sum_k (dK/dx_k)^2 h_k^2 / 3`` with the
    analytic gradient of :func:`rtsgt.measurement.atmosphere.correction_ppm_gradient` and the
    variance ``h^2 / 3`` of a zero-mean uniform error of half-width ``h``.
``time_sync``
    Zero-mean clock error with second moment ``m2 = mu^2 + sigma^2`` (see
    :mod:`rtsgt.noise.model`): ``m2 v v^T``. The velocity is estimated by differencing noisy
    positions, ``v^ = v + dv``; the displacement is ``e_ts v^`` and, ``e_ts`` being independent of
    ``dv`` and zero-mean, ``Cov(e_ts v^) = m2 (v v^T + Cov(dv))`` exactly. The second term is an
    interaction between the clock and the measurement noise (second order: about 5 um for
    2 mm noise at 0.4 s sampling), so it belongs to the **total** only; ``Cov(dv)`` is
    ``(Sigma_next + Sigma_prev) / dt^2`` from the covariances of the two positions the
    difference uses (the instrument, tilt and atmosphere sources of the model, taken
    independent between measurements). The Monte Carlo engine uses the measured velocity for
    every sample and omits this term.
``calibration``
    Left perturbation of ``T_world_station`` (:mod:`rtsgt.geometry.transform`):
    ``p_w = exp([dtheta]x) R p_s + t + dt ~= R p_s + t + dt - [R p_s]x dtheta``, so
    ``J_c = [I, -[R p_s]x]`` and the covariance is ``J_c Sigma_6 J_c^T``. ``Sigma_6`` is the
    transform's covariance, or the sample covariance of the left perturbations of its Monte
    Carlo samples when it has only samples.

Every term is a sum of weighted outer products of vectors (Jacobian columns, ``g``, ``u``,
``v``); the vectors are rotated to the world frame first (``R w``), which is the same as
``R Sigma R^T``. The total is the sum of the sources (plus the time-sync interaction term).
"""

from __future__ import annotations

import numpy as np

from rtsgt.geometry.so3 import hat
from rtsgt.geometry.transform import perturbation
from rtsgt.measurement.atmosphere import correction_ppm_gradient
from rtsgt.noise.model import NoiseModel, Nominal, _difference_stencil

_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
_SYM_INDEX = np.array([0, 3, 4, 3, 1, 5, 4, 5, 2])  # (i, j) row-major -> packed component


def _mm(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``A @ X`` for a small ``A`` (k, m) and a wide ``X`` (m, N), single-threaded.

    (A BLAS call would start its thread pool for a product this skinny and burn the other
    cores for nothing.)
    """
    return np.einsum("ij,jn->in", A, X)


def _packed_outer(terms, n: int) -> np.ndarray:
    """Packed ``sum_k w_k v_k v_k^T``: rows xx, yy, zz, xy, xz, yz, shape (6, N).

    ``terms``: iterable of ``(v, w)`` with ``v`` (3, N) (structure of arrays, contiguous rows)
    and ``w`` a scalar or (N,) array.
    """
    acc = np.zeros((6, n))
    for v, w in terms:
        vw = v * w
        for k, (i, j) in enumerate(_SYM):
            acc[k] += vw[i] * v[j]
    return acc


def _unpack(acc: np.ndarray) -> np.ndarray:
    """(6, N) packed symmetric matrices -> (N, 3, 3)."""
    return acc.T[:, _SYM_INDEX].reshape(-1, 3, 3)  # fancy indexing: a fresh C-ordered copy


def transform_covariance(T_world_station) -> np.ndarray | None:
    """The 6x6 covariance (x, y, z, rx, ry, rz) of a transform, from its samples if needed."""
    if T_world_station is None:
        return None
    if T_world_station.covariance is not None:
        return np.asarray(T_world_station.covariance, dtype=float)
    Rs, ts = T_world_station.samples_rotation, T_world_station.samples_translation
    if Rs is None or ts is None:
        return None
    xi = perturbation(T_world_station.rotation, T_world_station.translation, Rs, ts)
    xi = xi - xi.mean(axis=0)
    return xi.T @ xi / (xi.shape[0] - 1)


def calibration_covariance(q_world: np.ndarray, cov6: np.ndarray) -> np.ndarray:
    """``J_c Sigma_6 J_c^T`` with ``J_c = [I, -[q]x]``, ``q = R p_station``, for every point.

    With ``Sigma_6 = [[A, B], [B^T, C]]`` and ``Q = [q]x`` (``Q^T = -Q``):
    ``J_c Sigma_6 J_c^T = A + B Q + (B Q)^T + Q C Q^T``. ``Q = sum_l q_l E_l`` with
    ``E_l = [e_l]x``, so ``B Q = sum_l q_l (B E_l)`` and ``Q C Q^T = sum_lm q_l q_m E_l C E_m^T``
    are small matrix products, vectorised over the points.

    Parameters
    ----------
    q_world : ndarray, shape (N, 3)
        ``R_world_station p_station`` (the point relative to the station, world axes), m.
    cov6 : ndarray, shape (6, 6)
        Left-perturbation covariance of ``T_world_station``, ordered (x, y, z, rx, ry, rz).

    Returns
    -------
    ndarray, shape (N, 3, 3)
    """
    return _unpack(_calibration_packed(np.ascontiguousarray(np.asarray(q_world, float).T), cov6))


def _calibration_packed(q: np.ndarray, cov6: np.ndarray) -> np.ndarray:
    """Packed (6, N) form of :func:`calibration_covariance` for ``q`` given as (3, N)."""
    A, B, C = cov6[:3, :3], cov6[:3, 3:], cov6[3:, 3:]
    E = hat(np.eye(3))  # E[l] = [e_l]x
    G = np.einsum("ik,lkj->lij", B, E)  # B E_l, (3, 3, 3)
    H = np.einsum("lik,km,njm->lnij", E, C, E)  # E_l C E_n^T, (3, 3, 3, 3)
    sym_i = [i for i, _ in _SYM]
    sym_j = [j for _, j in _SYM]
    # packed rows of B Q + (B Q)^T and of Q C Q^T
    GG = (G[:, sym_i, sym_j] + G[:, sym_j, sym_i])  # (3, 6)
    qq = np.stack([q[a] * q[b] for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))])
    Hp = H[:, :, sym_i, sym_j]  # (3, 3, 6)
    Hq = np.stack([Hp[0, 0], Hp[1, 1], Hp[2, 2], Hp[0, 1] + Hp[1, 0], Hp[0, 2] + Hp[2, 0],
                   Hp[1, 2] + Hp[2, 1]])  # (6 products, 6 components)
    out = _mm(GG.T, q)
    out += _mm(Hq.T, qq)
    out += A[sym_i, sym_j][:, None]
    return out


def linear_covariances(
    nom: Nominal, model: NoiseModel, T_world_station=None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """World-frame total and per-source covariances by first-order propagation.

    Parameters
    ----------
    nom : Nominal
        From :func:`rtsgt.noise.model.prepare_nominal`.
    model : NoiseModel
    T_world_station : RigidTransform, optional
        Its covariance (or samples) feeds the calibration source.

    Returns
    -------
    total : ndarray, shape (N, 3, 3)
    by_source : dict str -> ndarray (N, 3, 3)
    """
    prof = model.instrument
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
    j_hz = _mm(R, np.stack([dsv * ch, -dsv * sh, np.zeros(N)]))
    dcv = d * cv
    j_v = _mm(R, np.stack([dcv * sh, dcv * ch, -dsv]))
    u = _mm(R, np.stack([sv * sh, sv * ch, cv]))
    packed: dict[str, np.ndarray] = {}
    if "instrument" in srcs:
        sa2 = prof.sigma_angle**2
        sd2 = (prof.sigma_distance(nom.d) * (1.0 + 1e-6 * nom.ppm)) ** 2
        packed["instrument"] = _packed_outer([(j_hz, sa2), (j_v, sa2), (u, sd2)], N)
    if "tilt" in srcs:
        g = j_hz * (cv / sv) + j_v  # d p / d e_tilt = J_Hz cot V + J_V
        packed["tilt"] = _packed_outer([(g, prof.sigma_tilt**2)], N)
    if "atmosphere" in srcs:
        gT, gp, gR = correction_ppm_gradient(
            nom.temperature_c, nom.pressure_hpa, nom.humidity_pct,
            wavelength_um=prof.wavelength_um,
            reference=(prof.reference_temperature_c, prof.reference_pressure_hpa,
                       prof.reference_humidity_pct),
            formula=model.vapour_formula,
        )
        vT, vp, vR = model.weather_variances
        var_ppm = gT**2 * vT + gp**2 * vp + gR**2 * vR
        packed["atmosphere"] = _packed_outer([(u, nom.d**2 * 1e-12 * var_ppm)], N)
    interaction = None
    if "time_sync" in srcs:
        m2 = model.time_sync_second_moment_s2
        vel = _mm(R, nom.velocity.T)
        packed["time_sync"] = _packed_outer([(vel, m2)], N)
        meas = [packed[s] for s in ("instrument", "tilt", "atmosphere") if s in packed]
        if meas and np.any(nom.velocity_valid):
            sig = np.sum(meas, axis=0)
            prev, nxt, dt = _difference_stencil(nom.t, model.max_velocity_gap_s)
            valid = nom.velocity_valid
            w = np.where(valid, m2 / np.where(valid, dt, 1.0) ** 2, 0.0)
            interaction = sig[:, nxt] + sig[:, prev]
            interaction *= w
    if "calibration" in srcs:
        cov6 = transform_covariance(T_world_station)
        if cov6 is None:
            packed["calibration"] = np.zeros((6, N))
        else:
            q = _mm(R, nom.xyz_station.T)
            packed["calibration"] = _calibration_packed(q, cov6)
    total = np.zeros((6, N))
    for c in packed.values():
        total += c
    if interaction is not None:
        total += interaction
    by_source = {s: _unpack(packed[s]) for s in srcs}
    return _unpack(total), by_source
