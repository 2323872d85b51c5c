"""Exact Gaussian-process interpolation of a prism track, white noise on the acceleration
(WNOA, the paper's) or on the jerk (WNOJ) (Barfoot, Tong and Särkkä 2014).

Owns the prior (``Phi``, ``Q``, their inverses), the block-tridiagonal posterior solved by block
cyclic reduction (:func:`_bcr`), the marginal likelihood and ``Qc`` by its maximum
(:func:`fit_qc`), the queries between and beyond knots, and :class:`GPTrack`. The model, the
diffuse prior on the first state, the solver, the likelihood (with its identity to the diffuse
Kalman filter's prediction-error decomposition) and the query formulas are in
docs/interpolation.md (#wnoa-prior, #wnoj-prior, #posterior, #queries,
#qc-by-marginal-likelihood).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike
from scipy import optimize

from rtsgt.choices import DEFAULT_MAX_GAP_S  # the longest gap a query is answered across, s
from rtsgt.errors import ExtrapolationError, InputError, RtsgtError
from rtsgt.parallel import available_cores
from rtsgt.types import PrismTrack

__all__ = [
    "DEFAULT_MAX_GAP_S",
    "QC_BOUNDS",
    "GPQuery",
    "GPTrack",
    "QcFitInfo",
    "as_qc",
    "fit_qc",
    "fit_track",
    "log_marginal_likelihood",
    "PRIORS",
    "wnoa_phi",
    "wnoa_q",
    "wnoa_q_inv",
    "wnoj_phi",
    "wnoj_q",
    "wnoj_q_inv",
]

#: Search interval of a fitted Qc (each diagonal entry), m^2/s^3 (WNOA) or m^2/s^5 (WNOJ).
QC_BOUNDS = (1e-12, 1e6)

#: The motion priors: white noise on the acceleration (state ``[p; v]``, the paper's) and
#: white noise on the jerk (state ``[p; v; a]``).
PRIORS = ("wnoa", "wnoj")

_LOG_2PI = math.log(2.0 * math.pi)
_EYE3 = np.eye(3)
_QUERY_CHUNK = 1 << 16
#: Most blocks of the candidates' systems that the leave-one-out search solves at once
#: (:func:`posteriors`; its result does not depend on it, only its memory, about 5 blocks of
#: 6x6 or 9x9 per knot and candidate, and the fixed cost per call of a short track's).
_STACK_BLOCKS = 1 << 13
#: Threads that solve the parts of :func:`posteriors`.
_CORES = available_cores()


# --------------------------------------------------------------------------------------------
# WNOA building blocks
# --------------------------------------------------------------------------------------------


def _kron2(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``kron(a, m)`` for a batch of rxr ``a`` (..., r, r) and a 3x3 ``m``: shape
    (..., 3r, 3r) (r = 2 for WNOA, 3 for WNOJ)."""
    out = a[..., :, None, :, None] * m[..., None, :, None, :]
    size = 3 * a.shape[-1]
    return out.reshape(out.shape[:-4] + (size, size))


def _sym(a: np.ndarray) -> np.ndarray:
    """``0.5 (a + a^T)`` over the last two axes (one temporary: ``x * 0.5`` is ``0.5 * x``)."""
    out = a + np.swapaxes(a, -1, -2)
    out *= 0.5
    return out


def as_qc(qc: ArrayLike, name: str = "qc") -> np.ndarray:
    """Power spectral density ``Qc`` as a 3x3 SPD matrix, m^2/s^3.

    Parameters
    ----------
    qc : float, array_like of shape (3,) or (3, 3)
        A scalar ``q`` (``Qc = q I``, isotropic), the diagonal of ``Qc`` (one value per axis),
        or the full symmetric positive definite matrix.

    Returns
    -------
    ndarray, shape (3, 3)

    Raises
    ------
    InputError
        Not finite, not positive, not symmetric or not positive definite.
    """
    a = np.asarray(qc, dtype=float)
    if a.ndim == 0:
        a = a * _EYE3
    elif a.shape == (3,):
        a = np.diag(a)
    elif a.shape != (3, 3):
        raise InputError(f"Expected {name} as a scalar, shape (3,) or (3, 3), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"Expected a finite {name}, got {a.tolist()}")
    scale = np.abs(a).max()
    if np.any(np.abs(a - a.T) > 1e-12 * scale):
        raise InputError(f"Expected a symmetric {name}, got {a.tolist()}")
    try:
        np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        raise InputError(
            f"Expected a positive definite {name} (m^2/s^3), got {a.tolist()}"
        ) from None
    return _sym(a)


def _as_dt(dt: ArrayLike, positive: bool) -> np.ndarray:
    d = np.asarray(dt, dtype=float)
    if not np.all(np.isfinite(d)):
        raise InputError("Expected finite time steps dt (s)")
    if positive and np.any(d <= 0):
        raise InputError(f"Expected time steps dt > 0 s, got min {float(d.min())!r}")
    return d


def wnoa_phi(dt: ArrayLike) -> np.ndarray:
    """Transition matrix ``Phi(dt) = [[I, dt I], [0, I]]`` of the WNOA prior.

    Parameters
    ----------
    dt : float or array_like, shape (...)
        Time step, s (may be negative: ``Phi(-dt)`` is the inverse of ``Phi(dt)``).

    Returns
    -------
    ndarray, shape (..., 6, 6)
        Acts on the state ``[p; v]``.
    """
    d = _as_dt(dt, positive=False)
    a = np.zeros(d.shape + (2, 2))
    a[..., 0, 0] = a[..., 1, 1] = 1.0
    a[..., 0, 1] = d
    return _kron2(a, _EYE3)


def _q_coef(d: np.ndarray) -> np.ndarray:
    a = np.empty(d.shape + (2, 2))
    a[..., 0, 0] = d**3 / 3.0
    a[..., 0, 1] = a[..., 1, 0] = d**2 / 2.0
    a[..., 1, 1] = d
    return a


def _qinv_coef(d: np.ndarray) -> np.ndarray:
    a = np.empty(d.shape + (2, 2))
    a[..., 0, 0] = 12.0 / d**3
    a[..., 0, 1] = a[..., 1, 0] = -6.0 / d**2
    a[..., 1, 1] = 4.0 / d
    return a


def wnoa_q(dt: ArrayLike, qc: ArrayLike) -> np.ndarray:
    """Process-noise covariance ``Q(dt)`` of the WNOA prior (docs/interpolation.md).

    ``Q(dt) = [[dt^3/3 Qc, dt^2/2 Qc], [dt^2/2 Qc, dt Qc]]``.

    Parameters
    ----------
    dt : float or array_like, shape (...)
        Time step, s, >= 0.
    qc : float, array_like (3,) or (3, 3)
        Power spectral density, m^2/s^3 (see :func:`as_qc`).

    Returns
    -------
    ndarray, shape (..., 6, 6)
        Covariance of ``[p; v]``, m^2, m^2/s, m^2/s^2.
    """
    d = _as_dt(dt, positive=False)
    if np.any(d < 0):
        raise InputError(f"Expected time steps dt >= 0 s, got min {float(d.min())!r}")
    return _kron2(_q_coef(d), as_qc(qc))


def wnoa_q_inv(dt: ArrayLike, qc: ArrayLike) -> np.ndarray:
    """Inverse of :func:`wnoa_q`, in closed form.

    ``Q(dt)^-1 = [[12/dt^3 Qc^-1, -6/dt^2 Qc^-1], [-6/dt^2 Qc^-1, 4/dt Qc^-1]]``.

    Parameters
    ----------
    dt : float or array_like, shape (...)
        Time step, s, > 0.
    qc : float, array_like (3,) or (3, 3)
        Power spectral density, m^2/s^3.

    Returns
    -------
    ndarray, shape (..., 6, 6)
    """
    d = _as_dt(dt, positive=True)
    return _kron2(_qinv_coef(d), _spd_inv(as_qc(qc)))


# --------------------------------------------------------------------------------------------
# WNOJ building blocks (white noise on jerk: state [p; v; a])
# --------------------------------------------------------------------------------------------


def _phi3_coef(d: np.ndarray) -> np.ndarray:
    a = np.zeros(d.shape + (3, 3))
    a[..., 0, 0] = a[..., 1, 1] = a[..., 2, 2] = 1.0
    a[..., 0, 1] = a[..., 1, 2] = d
    a[..., 0, 2] = d * d / 2.0
    return a


def _q3_coef(d: np.ndarray) -> np.ndarray:
    a = np.empty(d.shape + (3, 3))
    a[..., 0, 0] = d**5 / 20.0
    a[..., 0, 1] = a[..., 1, 0] = d**4 / 8.0
    a[..., 0, 2] = a[..., 2, 0] = d**3 / 6.0
    a[..., 1, 1] = d**3 / 3.0
    a[..., 1, 2] = a[..., 2, 1] = d**2 / 2.0
    a[..., 2, 2] = d
    return a


def _q3inv_coef(d: np.ndarray) -> np.ndarray:
    a = np.empty(d.shape + (3, 3))
    a[..., 0, 0] = 720.0 / d**5
    a[..., 0, 1] = a[..., 1, 0] = -360.0 / d**4
    a[..., 0, 2] = a[..., 2, 0] = 60.0 / d**3
    a[..., 1, 1] = 192.0 / d**3
    a[..., 1, 2] = a[..., 2, 1] = -36.0 / d**2
    a[..., 2, 2] = 9.0 / d
    return a


def wnoj_phi(dt: ArrayLike) -> np.ndarray:
    """Transition matrix of the WNOJ prior, ``[[1, dt, dt^2/2], [0, 1, dt], [0, 0, 1]] (x) I3``.

    Parameters
    ----------
    dt : float or array_like, shape (...)
        Time step, s (may be negative: ``Phi(-dt)`` is the inverse of ``Phi(dt)``).

    Returns
    -------
    ndarray, shape (..., 9, 9)
        Acts on the state ``[p; v; a]``.
    """
    return _kron2(_phi3_coef(_as_dt(dt, positive=False)), _EYE3)


def wnoj_q(dt: ArrayLike, qc: ArrayLike) -> np.ndarray:
    """Process-noise covariance ``Q(dt)`` of the WNOJ prior (docs/interpolation.md).

    ``Q(dt) = [[dt^5/20, dt^4/8, dt^3/6], [dt^4/8, dt^3/3, dt^2/2], [dt^3/6, dt^2/2, dt]]
    (x) Qc``.

    Parameters
    ----------
    dt : float or array_like, shape (...)
        Time step, s, >= 0.
    qc : float, array_like (3,) or (3, 3)
        Power spectral density of the jerk, m^2/s^5 (see :func:`as_qc`).

    Returns
    -------
    ndarray, shape (..., 9, 9)
    """
    d = _as_dt(dt, positive=False)
    if np.any(d < 0):
        raise InputError(f"Expected time steps dt >= 0 s, got min {float(d.min())!r}")
    return _kron2(_q3_coef(d), as_qc(qc))


def wnoj_q_inv(dt: ArrayLike, qc: ArrayLike) -> np.ndarray:
    """Inverse of :func:`wnoj_q`, in closed form.

    ``Q(dt)^-1 = [[720/dt^5, -360/dt^4, 60/dt^3], [-360/dt^4, 192/dt^3, -36/dt^2],
    [60/dt^3, -36/dt^2, 9/dt]] (x) Qc^-1``.

    Parameters
    ----------
    dt : float or array_like, shape (...)
        Time step, s, > 0.
    qc : float, array_like (3,) or (3, 3)
        Power spectral density, m^2/s^5.

    Returns
    -------
    ndarray, shape (..., 9, 9)
    """
    d = _as_dt(dt, positive=True)
    return _kron2(_q3inv_coef(d), _spd_inv(as_qc(qc)))


def _check_prior(prior: str) -> int:
    """The order ``r`` of a prior (2: WNOA, 3: WNOJ); the state has ``3 r`` components."""
    if prior not in PRIORS:
        raise InputError(f"Expected prior {' or '.join(map(repr, PRIORS))}, got {prior!r}")
    return 2 if prior == "wnoa" else 3


def _phi_coef(prior: str, d: np.ndarray) -> np.ndarray:
    """Coefficients ``(..., r, r)`` of ``Phi(d)`` (``Phi = coef (x) I3``)."""
    if prior == "wnoj":
        return _phi3_coef(d)
    a = np.zeros(d.shape + (2, 2))
    a[..., 0, 0] = a[..., 1, 1] = 1.0
    a[..., 0, 1] = d
    return a


def _prior_q_coef(prior: str, d: np.ndarray) -> np.ndarray:
    """Coefficients ``(..., r, r)`` of ``Q(d)`` (``Q = coef (x) Qc``)."""
    return _q3_coef(d) if prior == "wnoj" else _q_coef(d)


def _spd_inv(a: np.ndarray) -> np.ndarray:
    """Inverse of one SPD matrix through its Cholesky factor."""
    L = np.linalg.cholesky(a)
    Li = np.linalg.solve(L, np.eye(a.shape[-1]))
    return _sym(Li.T @ Li)


# --------------------------------------------------------------------------------------------
# Input validation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Data:
    """Validated measurements, centred on ``y_ref`` for conditioning."""

    t: np.ndarray  # (N,)
    y: np.ndarray  # (N, 3), centred
    y_ref: np.ndarray  # (3,)
    r_inv: np.ndarray  # (N, 3, 3)
    logdet_r: float  # sum_k log|Sigma_k|
    prior_inv: np.ndarray | None  # (d, d) P0^-1 or None (diffuse); d = 6 (WNOA) or 9 (WNOJ)
    prior_mean: np.ndarray | None  # (d,) m0, centred
    logdet_p0: float
    prism: str
    frame: str
    n_obs: int | None = None  # measurements with weight (None: all; see _held_out)
    prior: str = "wnoa"  # the motion prior (PRIORS)

    @property
    def dim(self) -> int:
        """Size of the state: 6 (WNOA) or 9 (WNOJ)."""
        return 3 * _check_prior(self.prior)


def track_arrays(track) -> tuple[np.ndarray, np.ndarray, np.ndarray, str, str]:
    if isinstance(track, PrismTrack):
        return track.t, track.xyz, track.cov, track.prism, track.frame
    if isinstance(track, Sequence) and len(track) == 3:
        t, xyz, cov = track
        try:
            t = np.asarray(t, dtype=float)
            xyz = np.asarray(xyz, dtype=float)
            cov = np.asarray(cov, dtype=float)
        except (TypeError, ValueError) as exc:
            raise InputError(f"Expected numeric arrays (t, xyz, cov), got {exc}") from None
        return t, xyz, cov, "1", "world"
    raise InputError(
        f"Expected a PrismTrack or a tuple (t, xyz, cov), got {type(track).__name__}"
    )


def _check_measurements(t, xyz, cov) -> np.ndarray:
    """Validate a track; return the (N, 3, 3) Cholesky factors of the covariances."""
    if t.ndim != 1:
        raise InputError(f"Expected t of shape (N,), got {t.shape}")
    n = t.shape[0]
    if n < 2:
        raise InputError(f"Expected at least 2 measurements to fit a track, got {n}")
    if xyz.shape != (n, 3):
        raise InputError(f"Expected xyz of shape ({n}, 3), got {xyz.shape}")
    if cov.shape != (n, 3, 3):
        raise InputError(f"Expected cov of shape ({n}, 3, 3), got {cov.shape}")
    for name, a in (("t", t), ("xyz", xyz), ("cov", cov)):
        bad = ~np.isfinite(a.reshape(n, -1)).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"Expected finite values, got NaN or inf in {name} of measurement {i} "
                f"(t = {float(t[i])!r} s)"
            )
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        i = int(bad[0])
        what = "duplicated" if dt[i] == 0 else "unsorted"
        raise InputError(
            f"Expected strictly increasing times, got {what} times: measurement {i + 1} "
            f"(t = {float(t[i + 1])!r} s) after measurement {i} (t = {float(t[i])!r} s)"
        )
    scale = np.abs(cov).max(axis=(1, 2))
    asym = np.abs(cov - np.swapaxes(cov, 1, 2)).max(axis=(1, 2))
    bad = np.flatnonzero(asym > 1e-9 * scale)
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"Expected a symmetric covariance, got {cov[i].tolist()} for measurement {i} "
            f"(t = {float(t[i])!r} s)"
        )
    try:
        return np.linalg.cholesky(_sym(cov))
    except np.linalg.LinAlgError:
        eig = np.linalg.eigvalsh(_sym(cov))
        i = int(np.flatnonzero(~(eig[:, 0] > 0))[0])
        raise InputError(
            f"Expected a positive definite covariance (m^2), got eigenvalues "
            f"{eig[i].tolist()} for measurement {i} (t = {float(t[i])!r} s)"
        ) from None


def prepare_track(track, initial_state_cov=None, initial_state_mean=None,
             prior: str = "wnoa") -> _Data:
    order = _check_prior(prior)
    dim = 3 * order
    t, xyz, cov, prism, frame = track_arrays(track)
    L = _check_measurements(t, xyz, cov)
    if initial_state_cov is None and t.shape[0] < order:
        raise InputError(f"Expected at least {order} measurements to fit a track with the "
                         f"{prior.upper()} prior and a diffuse initial state, got {t.shape[0]}")
    li = np.linalg.inv(L)  # lower-triangular inverses, (N, 3, 3)
    r_inv = _sym(np.swapaxes(li, 1, 2) @ li)
    logdet_r = 2.0 * float(np.log(np.diagonal(L, axis1=1, axis2=2)).sum())
    y_ref = xyz[0].copy()
    y = xyz - y_ref
    prior_inv = prior_mean = None
    logdet_p0 = 0.0
    if initial_state_cov is not None:
        p0 = np.asarray(initial_state_cov, dtype=float)
        if p0.shape != (dim, dim) or not np.all(np.isfinite(p0)):
            raise InputError(f"Expected a finite initial_state_cov of shape ({dim}, {dim}) "
                             f"for the {prior.upper()} prior, got {p0.shape}")
        if np.any(np.abs(p0 - p0.T) > 1e-12 * np.abs(p0).max()):
            raise InputError("Expected a symmetric initial_state_cov")
        try:
            lp = np.linalg.cholesky(_sym(p0))
        except np.linalg.LinAlgError:
            raise InputError("Expected a positive definite initial_state_cov") from None
        logdet_p0 = 2.0 * float(np.log(np.diag(lp)).sum())
        prior_inv = _spd_inv(p0)
        if initial_state_mean is None:
            m0 = np.concatenate([xyz[0], np.zeros(dim - 3)])
        else:
            m0 = np.asarray(initial_state_mean, dtype=float)
            if m0.shape != (dim,) or not np.all(np.isfinite(m0)):
                raise InputError(
                    f"Expected a finite initial_state_mean of shape ({dim},), got {m0.shape}"
                )
        prior_mean = m0 - np.concatenate([y_ref, np.zeros(dim - 3)])
    elif initial_state_mean is not None:
        raise InputError(
            "initial_state_mean needs initial_state_cov (the default prior is diffuse)"
        )
    return _Data(t, y, y_ref, r_inv, logdet_r, prior_inv, prior_mean, logdet_p0, prism, frame,
                 prior=prior)


def check_scale(data: _Data, qc_scale: ArrayLike | None) -> np.ndarray | None:
    """``qc_scale`` (:func:`fit_track`) as an array of one positive factor per interval."""
    if qc_scale is None:
        return None
    scale = np.asarray(qc_scale, dtype=float)
    if scale.shape != (data.t.shape[0] - 1,) or not np.all(np.isfinite(scale) & (scale > 0)):
        raise InputError(f"Expected qc_scale of shape ({data.t.shape[0] - 1},), finite and "
                         f"> 0, got shape {scale.shape}")
    return scale


def _held_out(data: _Data, held_out: ArrayLike, cov: np.ndarray) -> _Data:
    """The same knots, the measurements in ``held_out`` given no weight (zero information)."""
    mask = np.asarray(held_out)
    n = data.t.shape[0]
    if mask.shape != (n,) or mask.dtype != bool:
        raise InputError(f"Expected held_out as a boolean mask of shape ({n},), got "
                         f"{mask.dtype} of shape {mask.shape}")
    kept = n - int(mask.sum())
    need = _check_prior(data.prior)  # 2 (WNOA) or 3 (WNOJ) fix the state
    if kept < need:
        raise InputError(f"Expected at least {need} measurements left after holding out, "
                         f"got {kept}")
    logdet = float(np.linalg.slogdet(cov[~mask])[1].sum())
    return replace(data, r_inv=np.where(mask[:, None, None], 0.0, data.r_inv),
                   logdet_r=logdet, n_obs=kept)


# --------------------------------------------------------------------------------------------
# Block-tridiagonal system and its solution by block cyclic reduction
# --------------------------------------------------------------------------------------------


def _build_system(data: _Data, w: np.ndarray, scale: np.ndarray | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blocks of the information matrix and information vector (module docstring).

    ``scale`` (N-1,), optional: interval ``k`` has ``Qc_k = scale_k Qc`` (:func:`fit_track`).
    Returns D (N, d, d), B (N-1, d, d) with ``B_k = J_k,k+1``, h (N, d), d the state size.
    """
    if data.prior == "wnoj":
        return _build_system_wnoj(data, w, scale)
    n = data.t.shape[0]
    dt = np.diff(data.t)
    a, b, c, e = 12.0 / dt**3, 6.0 / dt**2, 4.0 / dt, 2.0 / dt
    if scale is not None:
        a, b, c, e = a / scale, b / scale, c / scale, e / scale
    coef_d = np.zeros((n, 2, 2))
    # Qinv_{k-1} = kron([[a, -b], [-b, c]], W) enters D_k
    coef_d[1:, 0, 0] += a
    coef_d[1:, 0, 1] -= b
    coef_d[1:, 1, 0] -= b
    coef_d[1:, 1, 1] += c
    # Phi_k^T Qinv_k Phi_k = kron([[a, b], [b, c]], W) enters D_k
    coef_d[:-1, 0, 0] += a
    coef_d[:-1, 0, 1] += b
    coef_d[:-1, 1, 0] += b
    coef_d[:-1, 1, 1] += c
    D = _kron2(coef_d, w)
    D[:, :3, :3] += data.r_inv
    # J_k,k+1 = -Phi_k^T Qinv_k = -kron([[a, -b], [b, -2/dt]], W)
    coef_b = np.empty((n - 1, 2, 2))
    coef_b[:, 0, 0] = -a
    coef_b[:, 0, 1] = b
    coef_b[:, 1, 0] = -b
    coef_b[:, 1, 1] = e
    B = _kron2(coef_b, w)
    h = np.zeros((n, 6))
    h[:, :3] = np.einsum("nij,nj->ni", data.r_inv, data.y)
    if data.prior_inv is not None:
        D[0] += data.prior_inv
        h[0] += data.prior_inv @ data.prior_mean
    return D, B, h


def _pt_qinv3_coef(d: np.ndarray) -> np.ndarray:
    """Coefficients of ``Phi(d)^T Q(d)^-1`` of the WNOJ prior, in closed form."""
    a = np.empty(d.shape + (3, 3))
    a[..., 0, 0] = 720.0 / d**5
    a[..., 0, 1] = -360.0 / d**4
    a[..., 0, 2] = 60.0 / d**3
    a[..., 1, 0] = 360.0 / d**4
    a[..., 1, 1] = -168.0 / d**3
    a[..., 1, 2] = 24.0 / d**2
    a[..., 2, 0] = 60.0 / d**3
    a[..., 2, 1] = -24.0 / d**2
    a[..., 2, 2] = 3.0 / d
    return a


#: ``Phi(d)^T Q(d)^-1 Phi(d) = T Q(d)^-1 T`` with ``T = diag(1, -1, 1)`` (time reversal).
_FLIP3 = np.array([1.0, -1.0, 1.0])


def _build_system_wnoj(data: _Data, w: np.ndarray, scale: np.ndarray | None):
    """:func:`_build_system` for the WNOJ prior (9x9 blocks)."""
    n = data.t.shape[0]
    dt = np.diff(data.t)
    inv_s = 1.0 if scale is None else (1.0 / scale)[:, None, None]
    qi = _q3inv_coef(dt) * inv_s
    coef_d = np.zeros((n, 3, 3))
    coef_d[1:] += qi  # Qinv_{k-1} enters D_k
    coef_d[:-1] += qi * _FLIP3[:, None] * _FLIP3[None, :]  # Phi_k^T Qinv_k Phi_k
    D = _kron2(coef_d, w)
    D[:, :3, :3] += data.r_inv
    B = _kron2(-_pt_qinv3_coef(dt) * inv_s, w)  # J_k,k+1 = -Phi_k^T Qinv_k
    h = np.zeros((n, 9))
    h[:, :3] = np.einsum("nij,nj->ni", data.r_inv, data.y)
    if data.prior_inv is not None:
        D[0] += data.prior_inv
        h[0] += data.prior_inv @ data.prior_mean
    return D, B, h


def _chol_logdet(a: np.ndarray) -> float:
    try:
        L = np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        raise RtsgtError(
            "The information matrix of the track is not numerically positive definite "
            "(extreme time steps or covariances?)"
        ) from None
    return 2.0 * float(np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum())


def _chol_solver(a: np.ndarray):
    """``log|a|``, ``a^-1`` and a function ``X -> a^-1 X`` for a batch of SPD blocks, all
    from their Cholesky factors."""
    try:
        L = np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        raise RtsgtError(
            "The information matrix of the track is not numerically positive definite "
            "(extreme time steps or covariances?)"
        ) from None
    logdet = 2.0 * float(np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum())
    li = np.linalg.inv(L)
    lit = np.swapaxes(li, -1, -2)
    return logdet, _sym(lit @ li), lambda x: lit @ (li @ x)


def _bcr(system: list, want_cov: bool, cholesky: bool = False, want_logdet: bool = True,
         want_cross: bool = True, offset: int = 0):
    """Solve ``J x = h`` for a block-tridiagonal SPD ``J`` by block cyclic reduction
    (docs/interpolation.md#posterior): level by level the odd blocks are eliminated onto the
    even ones (:func:`_reduce_level`), then substituted back (:func:`_substitute_level`).

    ``system`` is ``[D, B, h]`` (D (N, d, d) the diagonal blocks, B (N-1, d, d) the blocks
    ``J_k,k+1``, h (N, d); d = 6 for WNOA, 9 for WNOJ), emptied here so that each level's
    blocks are freed once reduced (about 5 blocks per knot at the peak). ``cholesky`` applies
    the pivots through their Cholesky factors (WNOJ, whose blocks span more orders of
    magnitude); without ``want_logdet`` ``log|J|`` is 0. ``offset``: the system is the part,
    from block ``offset`` on, of a larger uncoupled one (:func:`posteriors`), eliminated in
    the order of the whole, so that it gets the whole's numbers bit for bit.

    Returns ``mean`` (N, d), ``log|J|``, ``S`` (N, d, d) the diagonal blocks of ``J^-1`` (None
    without ``want_cov``) and ``C`` (N-1, d, d) its blocks ``(J^-1)_k,k+1`` (None without
    ``want_cov`` or ``want_cross``).
    """
    dim = system[0].shape[-1]
    levels = []
    logdet = 0.0
    while system[0].shape[0] > 1:
        level, ld, offset = _reduce_level(system, offset, cholesky, want_logdet)
        levels.append(level)
        logdet += ld
    D, B, h = system
    system.clear()
    if cholesky:
        ld, s0, solve = _chol_solver(D)
        logdet += ld
        mean = solve(h[:, :, None])[..., 0]
    else:
        if want_logdet:
            logdet += _chol_logdet(D)
        s0 = _sym(np.linalg.inv(D))
        mean = np.einsum("nij,nj->ni", s0, h)
    del D, B, h
    state = [mean, s0 if want_cov else None, np.zeros((0, dim, dim)) if want_cov else None]
    del mean, s0
    while levels:
        _substitute_level(levels.pop(), state, want_cov, want_cross or bool(levels))
    mean, S, C = state
    if want_cov and not want_cross:
        C = None
    return mean, logdet, S, C


def _reduce_level(system: list, offset: int, cholesky: bool, want_logdet: bool):
    """One level of :func:`_bcr`'s reduction: the odd blocks of ``system = [D, B, h]``
    eliminated, the Schur complement onto the even blocks left in ``system`` (the old blocks
    dropped as soon as they are used). Returns the level's factors for the back substitution,
    its share of ``log|J|`` and the offset of the next level."""
    D, B, h = system
    system.clear()
    dim = D.shape[-1]
    logdet = 0.0
    lead = offset % 2 == 1  # the first block is odd in the whole: eliminated now
    if lead:
        D = np.concatenate([np.eye(dim)[None], D])
        B = np.concatenate([np.zeros((1, dim, dim)), B])
        h = np.concatenate([np.zeros((1, dim)), h])
    offset = (offset + 1) // 2  # the index of the first even block, at the next level
    n = D.shape[0]
    n_even = (n + 1) // 2
    n_odd = n // 2
    b_left = B[0::2]  # J_{i-1,i} for odd i
    b_right = B[1::2]  # J_{i,i+1} for odd i (none for the last odd when n is even)
    if n % 2 == 0:
        b_right = np.concatenate([b_right, np.zeros((1, dim, dim))])
    b_left_t = np.swapaxes(b_left, 1, 2)
    b_right_t = np.swapaxes(b_right, 1, 2)
    if cholesky:
        ld, d_inv, solve = _chol_solver(D[1::2])
        logdet += ld
        ga = solve(b_left_t)  # D_i^-1 J_{i,i-1}
        gb = solve(b_right)  # D_i^-1 J_{i,i+1}
        g = solve(h[1::2, :, None])[..., 0]
        del solve
    else:
        if want_logdet:
            logdet += _chol_logdet(D[1::2])
        d_inv = _sym(np.linalg.inv(D[1::2]))
        ga = d_inv @ b_left_t  # D_i^-1 J_{i,i-1}
        gb = d_inv @ b_right  # D_i^-1 J_{i,i+1}
        g = np.einsum("nij,nj->ni", d_inv, h[1::2])
    # Schur complement onto the even blocks
    d_even = D[0::2].copy()
    del D
    d_even[:n_odd] -= b_left @ ga
    d_even[1:] -= (b_right_t @ gb)[: n_even - 1]
    h_even = h[0::2].copy()
    h_even[:n_odd] -= np.einsum("nij,nj->ni", b_left, g)
    h_even[1:] -= np.einsum("nij,nj->ni", b_right_t, g)[: n_even - 1]
    b_even = b_left @ gb
    del B, b_left, b_right, b_left_t, b_right_t
    np.negative(b_even, out=b_even)
    D, B, h = _sym(d_even), b_even[: n_even - 1], h_even
    del d_even, b_even
    if lead:  # the stand-in block (kept, first) is not the system's
        D, B, h = D[1:], B[1:], h[1:]
    system.extend((D, B, h))
    return (d_inv, ga, gb, g, n, lead), logdet, offset


def _substitute_level(level: tuple, state: list, want_cov: bool, want_cross: bool) -> None:
    """One level of :func:`_bcr`'s back substitution: ``state = [mean, S, C]`` of the even
    blocks replaced by those of all the level's blocks (``S``, ``C`` None without
    ``want_cov``; ``C`` None without ``want_cross``)."""
    d_inv, ga, gb, g, n, lead = level
    del level
    mean, S, C = state
    state.clear()
    dim = mean.shape[-1]
    if lead:  # the stand-in block again, coupled to nothing (its values multiply zeros)
        mean = np.concatenate([np.zeros((1, dim)), mean])
        if want_cov:
            S = np.concatenate([np.eye(dim)[None], S])
            C = np.concatenate([np.zeros((1, dim, dim)), C])
    m_e = mean
    if n % 2 == 0:  # a zero neighbour to the right of the last odd block
        m_e = np.concatenate([m_e, np.zeros((1, dim))])
    m_o = g - np.einsum("nij,nj->ni", ga, m_e[:-1]) - np.einsum("nij,nj->ni", gb, m_e[1:])
    mean = np.empty((n, dim))
    mean[0::2] = m_e[: (n + 1) // 2]
    mean[1::2] = m_o
    del m_e, m_o, g
    if want_cov:
        factors = [d_inv, ga, gb, S, C]
        del d_inv, ga, gb, S, C
        S, C = _substitute_covariance(factors, n, want_cross)
        if lead:
            S = S[1:]
            C = None if C is None else C[1:]
    else:
        del d_inv, ga, gb
    if lead:
        mean = mean[1:]
    state.extend((mean, S, C))


def _substitute_covariance(factors: list, n: int, want_cross: bool):
    """The selected inverse of one level (:func:`_substitute_level`): the diagonal blocks
    ``S`` (n, d, d) and, with ``want_cross``, the blocks ``C`` (n-1, d, d) of ``J^-1`` from
    ``factors = [d_inv, ga, gb, s_e, c_e]`` (the level's factors and the even blocks' ``S``
    and ``C``; emptied here, so that each is freed once used). Rows i (odd) of
    ``J Sigma = I``, neighbours a = i-1 and b = i+1: ``Sigma_ia = -(G_a Sigma_aa + G_b
    Sigma_ba)``, ``Sigma_ib = -(G_a Sigma_ab + G_b Sigma_bb)``, ``Sigma_ii = D_i^-1 - G_a
    Sigma_ai - G_b Sigma_bi`` (in ``d_inv``, not needed again)."""
    d_inv, ga, gb, s_e, c_e = factors
    factors.clear()
    dim = s_e.shape[-1]
    if n % 2 == 0:
        s_e = np.concatenate([s_e, np.zeros((1, dim, dim))])
        c_e = np.concatenate([c_e, np.zeros((1, dim, dim))])
    s_ia = ga @ s_e[:-1]
    s_ia += gb @ np.swapaxes(c_e, 1, 2)
    np.negative(s_ia, out=s_ia)
    s_ib = ga @ c_e
    del c_e
    s_ib += gb @ s_e[1:]
    np.negative(s_ib, out=s_ib)
    s_ii = d_inv
    del d_inv
    s_ii -= ga @ np.swapaxes(s_ia, 1, 2)
    del ga
    s_ii -= gb @ np.swapaxes(s_ib, 1, 2)
    del gb
    S = np.empty((n, dim, dim))
    S[0::2] = s_e[: (n + 1) // 2]
    del s_e
    S[1::2] = _sym(s_ii)
    del s_ii
    C = None
    if want_cross:
        C = np.empty((n - 1, dim, dim))
        C[0::2] = np.swapaxes(s_ia, 1, 2)
        C[1::2] = s_ib[: (n - 1) // 2]
    return S, C


def _solve(data: _Data, qc: np.ndarray, want_cov: bool, scale: np.ndarray | None = None):
    """Posterior (centred) and log marginal likelihood for one Qc (times ``scale`` per
    interval, when given)."""
    w = _spd_inv(qc)
    mean, logdet_j, S, C = _bcr(list(_build_system(data, w, scale)), want_cov,
                                cholesky=data.prior == "wnoj")
    n = data.t.shape[0]
    n_obs = n if data.n_obs is None else data.n_obs
    dt = np.diff(data.t)
    inv_s = 1.0 if scale is None else 1.0 / scale
    # whitened residuals at the posterior mean: c - h^T J^-1 h
    r = data.y - mean[:, :3]
    quad = float(np.einsum("ni,nij,nj->", r, data.r_inv, r))
    if data.prior == "wnoj":
        # increments x_k+1 - Phi_k x_k, as (N-1, 3 derivatives, 3 axes)
        m3 = mean.reshape(n, 3, 3)
        e = m3[1:] - np.einsum("kab,kbj->kaj", _phi3_coef(dt), m3[:-1])
        ew = e @ w
        quad += float(np.einsum("k,kab,kai,kbi->", inv_s * np.ones(n - 1), _q3inv_coef(dt),
                                ew, e))
        # |Q| = |coef|^3 |Qc|^3 with |coef| = dt^9 / 8640; |Q(dt, s Qc)| = s^9 |Q(dt, Qc)|
        logdet_q = float(np.sum(3.0 * np.log(dt**9 / 8640.0))) + 3.0 * (n - 1) * _chol_logdet(qc)
        if scale is not None:
            logdet_q += 9.0 * float(np.sum(np.log(scale)))
    else:
        ep = mean[1:, :3] - mean[:-1, :3] - dt[:, None] * mean[:-1, 3:]
        ev = mean[1:, 3:] - mean[:-1, 3:]
        epw = ep @ w
        evw = ev @ w
        quad += float(
            np.sum(inv_s * 12.0 / dt**3 * np.einsum("ni,ni->n", epw, ep))
            - np.sum(inv_s * 12.0 / dt**2 * np.einsum("ni,ni->n", epw, ev))
            + np.sum(inv_s * 4.0 / dt * np.einsum("ni,ni->n", evw, ev))
        )
        logdet_q = float(np.sum(3.0 * np.log(dt**4 / 12.0))) + 2.0 * (n - 1) * _chol_logdet(qc)
        if scale is not None:  # |Q(dt, s Qc)| = s^6 |Q(dt, Qc)|
            logdet_q += 6.0 * float(np.sum(np.log(scale)))
    if data.prior_inv is None:
        # the flat density on the d components of x(t_0) integrates d/2 log(2 pi) back
        const = (0.5 * data.dim - 1.5 * n_obs) * _LOG_2PI
    else:
        e0 = mean[0] - data.prior_mean
        quad += float(e0 @ data.prior_inv @ e0)
        const = -1.5 * n_obs * _LOG_2PI - 0.5 * data.logdet_p0
    loglik = -0.5 * quad - 0.5 * data.logdet_r - 0.5 * logdet_q - 0.5 * logdet_j + const
    return mean, S, C, loglik


def posteriors(data: _Data, qcs: list[np.ndarray], scales: list[np.ndarray | None],
                ) -> tuple[np.ndarray, np.ndarray]:
    """Posterior means (K, N, d) and marginal position covariances (K, N, 3, 3), centred, of
    the same measurements under K candidate ``Qc`` (each times its ``scale`` per interval, or
    None).

    The K block-tridiagonal systems are solved as one, uncoupled (a zero block between them):
    one cyclic reduction for all, so that a short track's fixed cost per call (numpy's, not
    the arithmetic) is paid once instead of K times; a long track's in parts of at most
    :data:`_STACK_BLOCKS` blocks, each eliminated in the order of the whole (:func:`_bcr`'s
    ``offset``), which gives the same numbers, bit for bit, in less memory. Each solution is
    that of :func:`_solve` up to rounding (the blocks are eliminated in another order). The
    parts are solved by :data:`_CORES` threads at once, each part of at most
    ``_STACK_BLOCKS / _CORES`` blocks (the same memory at the peak).
    """
    k, n, d = len(qcs), data.t.shape[0], data.dim
    mean = np.empty((k, n, d))
    S = np.empty((k, n, 3, 3))
    workers = max(1, min(k, _CORES))
    per = max(1, _STACK_BLOCKS // (n * workers))  # systems solved at once, by each worker

    def solve(k0: int) -> None:
        k1 = min(k0 + per, k)
        if k1 == k0 + 1:  # one system: as built
            system = list(_build_system(data, _spd_inv(qcs[k0]), scales[k0]))
        else:
            D = np.empty(((k1 - k0) * n, d, d))
            B = np.zeros(((k1 - k0) * n - 1, d, d))  # a zero block between two systems
            h = np.empty(((k1 - k0) * n, d))
            for i in range(k1 - k0):
                D[i * n:(i + 1) * n], B[i * n:(i + 1) * n - 1], h[i * n:(i + 1) * n] = (
                    _build_system(data, _spd_inv(qcs[k0 + i]), scales[k0 + i]))
            system = [D, B, h]
            del D, B, h
        m, _, c, _ = _bcr(system, True, cholesky=data.prior == "wnoj", want_logdet=False,
                          want_cross=False, offset=k0 * n)
        mean[k0:k1] = m.reshape(k1 - k0, n, d)
        S[k0:k1] = c.reshape(k1 - k0, n, d, d)[..., :3, :3]

    parts = range(0, k, per)
    if len(parts) < 2 or workers < 2:
        for k0 in parts:
            solve(k0)
    else:  # the parts are independent (each its own slice of the result): numpy releases
        # the interpreter lock in their arithmetic, and a part's numbers do not depend on it
        with ThreadPoolExecutor(max_workers=workers) as ex:
            for done in [ex.submit(solve, k0) for k0 in parts]:
                done.result()
    return mean, S


# --------------------------------------------------------------------------------------------
# Qc estimation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class QcFitInfo:
    """Outcome of the maximum-marginal-likelihood estimation of ``Qc``.

    Attributes
    ----------
    mode : str
        ``"isotropic"`` (``Qc = q I``) or ``"per-axis"`` (``Qc = diag(q)``).
    qc : ndarray, shape (3, 3)
        Estimated power spectral density, m^2/s^3.
    log_likelihood : float
        Log marginal likelihood at ``qc``.
    converged : bool
        The optimiser met its tolerance and the estimate is not on a bound of
        :data:`QC_BOUNDS`.
    at_bound : bool
        The estimate sits on a bound (e.g. a static prism: no detectable acceleration).
    n_evaluations : int
        Number of likelihood evaluations.
    n_iterations : int
        Iterations of the final optimiser.
    message : str
    """

    mode: str
    qc: np.ndarray
    log_likelihood: float
    converged: bool
    at_bound: bool
    n_evaluations: int
    n_iterations: int
    message: str


def _fit_qc_data(
    data: _Data,
    mode: str,
    qc0,
    bounds: tuple[float, float],
    max_iter: int,
    tol: float,
) -> QcFitInfo:
    if mode not in ("isotropic", "per-axis"):
        raise InputError(f"Expected qc_mode 'isotropic' or 'per-axis', got {mode!r}")
    lo, hi = (float(b) for b in bounds)
    if not (0 < lo < hi < np.inf):
        raise InputError(f"Expected Qc bounds 0 < lo < hi, got {bounds!r}")
    if max_iter < 1 or not tol > 0:
        raise InputError(f"Expected max_iter >= 1 and tol > 0, got {max_iter!r}, {tol!r}")
    slo, shi = math.log(lo), math.log(hi)
    n_eval = 0

    def negll(s: np.ndarray) -> float:
        nonlocal n_eval
        n_eval += 1
        q = np.exp(np.clip(np.atleast_1d(s), slo, shi))
        qc = q[0] * _EYE3 if q.size == 1 else np.diag(q)
        return -_solve(data, qc, want_cov=False)[3]

    # isotropic: coarse grid over the decades, then bounded Brent in log space
    if qc0 is None:
        grid = np.linspace(slo, shi, int(round((shi - slo) / math.log(10.0))) + 1)
        vals = np.array([negll(np.array([s])) for s in grid])
        i = int(np.argmin(vals))
        a, b = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    else:
        s0 = math.log(float(np.clip(np.mean(np.diag(as_qc(qc0))), lo, hi)))
        a, b = max(s0 - 2 * math.log(10.0), slo), min(s0 + 2 * math.log(10.0), shi)
    res = optimize.minimize_scalar(
        lambda s: negll(np.array([s])),
        bounds=(a, b),
        method="bounded",
        options={"xatol": tol, "maxiter": max_iter},
    )
    s_iso = float(res.x)
    converged = bool(res.success)
    n_iter = int(getattr(res, "nit", 0))
    message = str(res.message)
    # the bracket may have cut the optimum: refuse an estimate on an inner bracket edge
    edge = min(abs(s_iso - a), abs(s_iso - b)) < 10 * tol
    inner_edge = edge and not (abs(s_iso - slo) < 10 * tol or abs(s_iso - shi) < 10 * tol)
    if inner_edge:
        converged = False
        message = "optimum on the edge of the search bracket; give a better qc0"
    s_best = np.array([s_iso])
    best = float(res.fun)
    if mode == "per-axis":
        res3 = optimize.minimize(
            negll,
            np.full(3, s_iso),
            method="L-BFGS-B",
            bounds=[(slo, shi)] * 3,
            options={"maxiter": max_iter, "ftol": tol * 1e-3, "gtol": tol},
        )
        s_best = np.asarray(res3.x, dtype=float)
        best = float(res3.fun)
        converged = bool(res3.success)
        n_iter = int(res3.nit)
        message = str(res3.message)
    q = np.exp(np.clip(s_best, slo, shi))
    log_q = np.log(q)
    at_bound = bool(np.any((np.abs(log_q - slo) < 10 * tol) | (np.abs(log_q - shi) < 10 * tol)))
    if at_bound:
        converged = False
        message = (
            f"Qc on the bound of the search interval {bounds!r} m^2/s^3: the data do not "
            "determine it (a static prism gives no acceleration to measure)"
        )
    qc = q[0] * _EYE3 if q.size == 1 else np.diag(q)
    return QcFitInfo(mode, _readonly(qc), -best, converged, at_bound, n_eval, n_iter, message)


def fit_qc(
    track,
    *,
    mode: str = "isotropic",
    qc0=None,
    initial_state_cov: ArrayLike | None = None,
    initial_state_mean: ArrayLike | None = None,
    bounds: tuple[float, float] = QC_BOUNDS,
    max_iter: int = 200,
    tol: float = 1e-4,
    prior: str = "wnoa",
) -> tuple[np.ndarray, float, QcFitInfo]:
    """Estimate ``Qc`` by maximising the marginal likelihood of a track.

    The parameters are optimised in log space: ``log q`` (isotropic, ``Qc = q I``) by a
    grid over the decades of ``bounds`` followed by bounded Brent search, or
    ``log q_x, log q_y, log q_z`` (per axis, ``Qc = diag(q)``) by L-BFGS-B started from the
    isotropic optimum. Each evaluation is one O(N) solve (module docstring).

    Parameters
    ----------
    track : PrismTrack or tuple (t, xyz, cov)
        Times (s, strictly increasing), positions (m) and 3x3 covariances (m^2).
    mode : {"isotropic", "per-axis"}
    qc0 : float or array_like, optional
        Initial guess; the isotropic search then looks within two decades of it instead of
        scanning all of ``bounds``.
    initial_state_cov, initial_state_mean : array_like (d, d) and (d,), optional
        Proper Gaussian prior on ``x(t_0)`` (d = 6 for WNOA, 9 for WNOJ); diffuse when None
        (module docstring).
    bounds : (float, float)
        Search interval of each ``q``, m^2/s^3 (WNOA) or m^2/s^5 (WNOJ).
    max_iter : int
        Iterations of the optimiser.
    tol : float
        Tolerance on ``log q`` (relative tolerance on ``q``).
    prior : {"wnoa", "wnoj"}
        The motion prior (module docstring).

    Returns
    -------
    qc : ndarray, shape (3, 3)
        Estimated power spectral density, m^2/s^3.
    log_likelihood : float
    info : QcFitInfo
        Convergence report; ``info.converged`` is False when the optimiser stopped early or the
        estimate sits on a bound.
    """
    data = prepare_track(track, initial_state_cov, initial_state_mean, prior)
    info = _fit_qc_data(data, mode, qc0, bounds, max_iter, tol)
    return np.array(info.qc), info.log_likelihood, info


def log_marginal_likelihood(
    track,
    qc,
    *,
    initial_state_cov: ArrayLike | None = None,
    initial_state_mean: ArrayLike | None = None,
    prior: str = "wnoa",
) -> float:
    """Log marginal likelihood of a track under the ``prior`` (WNOA or WNOJ) with power
    spectral density ``qc``.

    See the module docstring for the formula and the meaning with the diffuse prior.
    """
    data = prepare_track(track, initial_state_cov, initial_state_mean, prior)
    return _solve(data, as_qc(qc), want_cov=False)[3]


# --------------------------------------------------------------------------------------------
# Fitted track and queries
# --------------------------------------------------------------------------------------------


def _readonly(a: np.ndarray | None) -> np.ndarray | None:
    if a is None:
        return None
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class GPQuery:
    """Posterior of a track at query times.

    Attributes
    ----------
    t : ndarray, shape (Q,)
        Query times, s.
    position : ndarray, shape (Q, 3)
        Posterior mean position, m, frame of the track.
    position_cov : ndarray, shape (Q, 3, 3)
        Posterior covariance of the position, m^2.
    velocity : ndarray, shape (Q, 3) or None
        Posterior mean velocity, m/s (only with ``with_velocity=True``).
    velocity_cov : ndarray, shape (Q, 3, 3) or None
        m^2/s^2 (only with ``with_velocity=True``).
    state_cov : ndarray, shape (Q, d, d) or None
        Covariance of the whole state, ``[p; v]`` (d = 6, WNOA) or ``[p; v; a]`` (d = 9,
        WNOJ) (only with ``with_velocity=True``).
    nearest_measurement_dt : ndarray, shape (Q,)
        Time to the nearest measurement, s.
    across_gap : ndarray of bool, shape (Q,)
        The query is not supported by the data: inside a gap longer than ``max_gap_s`` or
        outside the track (only possible with ``allow_gaps=True``).
    extrapolated : ndarray of bool, shape (Q,)
        The query is before the first or after the last measurement (a subset of
        ``across_gap``).
    """

    t: np.ndarray
    position: np.ndarray
    position_cov: np.ndarray
    velocity: np.ndarray | None
    velocity_cov: np.ndarray | None
    state_cov: np.ndarray | None
    nearest_measurement_dt: np.ndarray
    across_gap: np.ndarray
    extrapolated: np.ndarray

    def __len__(self) -> int:
        return self.t.shape[0]

    @property
    def position_sigma(self) -> np.ndarray:
        """RMS per-axis position standard deviation ``sqrt(trace(cov) / 3)``, m, shape (Q,)."""
        return np.sqrt(np.trace(self.position_cov, axis1=1, axis2=2) / 3.0)


@dataclass(frozen=True)
class GPTrack:
    """Fitted posterior of one prism track (WNOA or WNOJ prior), queryable at any time.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Knot (measurement) times, s.
    mean : ndarray, shape (N, d)
        Posterior mean of the state at each knot: ``[p; v]`` (d = 6, WNOA) or ``[p; v; a]``
        (d = 9, WNOJ), m, m/s and m/s^2. The velocity is ``mean[:, 3:6]``.
    cov : ndarray, shape (N, d, d)
        Posterior marginal covariance of each knot.
    cross_cov : ndarray, shape (N-1, d, d)
        ``Cov(x_k, x_k+1)``.
    qc : ndarray, shape (3, 3)
        Power spectral density used, m^2/s^3 (WNOA, of the acceleration) or m^2/s^5 (WNOJ, of
        the jerk).
    log_likelihood : float
        Log marginal likelihood of the measurements under ``qc`` (module docstring).
    max_gap_s : float
        Longest gap between knots across which :meth:`query` answers without
        ``allow_gaps``, s.
    prism, frame : str
    diffuse_prior : bool
        Whether the prior on ``x(t_0)`` was diffuse.
    qc_fit : QcFitInfo or None
        The estimation report when ``qc`` was estimated.
    qc_scale : ndarray, shape (N-1,), or None
        Per-interval multiplier of ``qc`` (interval ``k`` between knots ``k`` and ``k+1`` has
        ``Qc_k = qc_scale[k] qc``); None: 1 everywhere. Extrapolation uses the scale of the
        first or the last interval.
    prior : {"wnoa", "wnoj"}
        The motion prior (module docstring).
    """

    t: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    cross_cov: np.ndarray
    qc: np.ndarray
    log_likelihood: float
    max_gap_s: float = DEFAULT_MAX_GAP_S
    prism: str = "1"
    frame: str = "world"
    diffuse_prior: bool = True
    qc_fit: QcFitInfo | None = field(default=None, repr=False)
    qc_scale: np.ndarray | None = None
    prior: str = "wnoa"

    @property
    def state_dim(self) -> int:
        """Size of the state: 6 (WNOA, ``[p; v]``) or 9 (WNOJ, ``[p; v; a]``)."""
        return 3 * _check_prior(self.prior)

    def transition(self, dt: ArrayLike) -> np.ndarray:
        """The prior's ``Phi(dt)``, shape (..., d, d) (:func:`wnoa_phi`, :func:`wnoj_phi`)."""
        return wnoj_phi(dt) if self.prior == "wnoj" else wnoa_phi(dt)

    def process_noise(self, dt: ArrayLike) -> np.ndarray:
        """The prior's ``Q(dt)`` with the track's ``qc`` (no ``qc_scale``), shape (..., d, d)."""
        return wnoj_q(dt, self.qc) if self.prior == "wnoj" else wnoa_q(dt, self.qc)

    @property
    def velocity(self) -> np.ndarray:
        """Posterior mean velocity at the knots, m/s, shape (N, 3)."""
        return self.mean[:, 3:6]

    def interval_scale(self, k: ArrayLike) -> np.ndarray:
        """The scale of ``qc`` on the intervals ``k`` (indices from 0 to N-2), shape of ``k``:
        ``qc_scale[k]``, or ones without a ``qc_scale``."""
        k = np.asarray(k, dtype=int)
        return np.ones(k.shape) if self.qc_scale is None else self.qc_scale[k]

    def __len__(self) -> int:
        return self.t.shape[0]

    @property
    def position(self) -> np.ndarray:
        """Posterior mean position at the knots, m, shape (N, 3)."""
        return self.mean[:, :3]

    @property
    def position_cov(self) -> np.ndarray:
        """Posterior position covariance at the knots, m^2, shape (N, 3, 3)."""
        return self.cov[:, :3, :3]

    def supported(self, times: ArrayLike) -> np.ndarray:
        """Whether each time lies inside the track and in no gap longer than ``max_gap_s``."""
        tau = np.asarray(times, dtype=float)
        k = np.searchsorted(self.t, tau, side="right") - 1
        inside = (tau >= self.t[0]) & (tau <= self.t[-1])
        kk = np.clip(k, 0, self.t.shape[0] - 2)
        on_knot = inside & (self.t[np.clip(k, 0, None)] == tau)
        gap = (self.t[kk + 1] - self.t[kk]) > self.max_gap_s
        return inside & (on_knot | ~gap)

    def query(
        self, times: ArrayLike, *, with_velocity: bool = False, allow_gaps: bool = False
    ) -> GPQuery:
        """Posterior mean and covariance at arbitrary times (vectorised).

        Parameters
        ----------
        times : array_like, shape (Q,)
            Query times, s, in any order.
        with_velocity : bool
            Also return the velocity and the covariance of the whole state (6x6 or 9x9).
        allow_gaps : bool
            Answer queries outside the track or inside a gap longer than ``max_gap_s``
            (flagged in ``across_gap`` / ``extrapolated``) instead of raising.

        Returns
        -------
        GPQuery

        Raises
        ------
        InputError
            Times not finite or not 1-D.
        ExtrapolationError
            A query outside the track or across a long gap, without ``allow_gaps``.
        """
        tau = np.asarray(times, dtype=float)
        if tau.ndim == 0:
            tau = tau[None]
        if tau.ndim != 1:
            raise InputError(f"Expected query times of shape (Q,), got {tau.shape}")
        if not np.all(np.isfinite(tau)):
            i = int(np.flatnonzero(~np.isfinite(tau))[0])
            raise InputError(f"Expected finite query times, got {float(tau[i])!r} at index {i}")
        t = self.t
        n = t.shape[0]
        k = np.searchsorted(t, tau, side="right") - 1
        before = k < 0
        after = (k == n - 1) & (tau > t[-1])
        extrap = before | after
        kc = np.clip(k, 0, n - 1)
        on_knot = ~before & (t[kc] == tau)
        interior = ~extrap & ~on_knot
        ki = np.clip(k, 0, n - 2)
        gap = interior & ((t[ki + 1] - t[ki]) > self.max_gap_s)
        unsupported = extrap | gap
        if not allow_gaps and unsupported.any():
            self._refuse(tau, ki, before, after, unsupported)
        full = self.state_dim
        dim = full if with_velocity else 3
        q = tau.shape[0]
        mean = np.empty((q, full))
        cov = np.empty((q, dim, dim))
        for lo in range(0, q, _QUERY_CHUNK):
            sl = slice(lo, min(lo + _QUERY_CHUNK, q))
            m_c, c_c = self._query_chunk(
                tau[sl], kc[sl], ki[sl], on_knot[sl], interior[sl], before[sl], after[sl], dim
            )
            mean[sl] = m_c
            cov[sl] = c_c
        near = np.minimum(np.abs(tau - t[ki]), np.abs(t[ki + 1] - tau))
        near = np.where(before, t[0] - tau, np.where(after, tau - t[-1], near))
        cov = _sym(cov)
        return GPQuery(
            t=_readonly(tau.copy()),
            position=_readonly(mean[:, :3]),
            position_cov=_readonly(cov[:, :3, :3]),
            velocity=_readonly(mean[:, 3:6]) if with_velocity else None,
            velocity_cov=_readonly(cov[:, 3:6, 3:6]) if with_velocity else None,
            state_cov=_readonly(cov) if with_velocity else None,
            nearest_measurement_dt=_readonly(near),
            across_gap=_readonly(unsupported),
            extrapolated=_readonly(extrap),
        )

    def _refuse(self, tau, ki, before, after, unsupported) -> None:
        """Raise the :class:`ExtrapolationError` of :meth:`query`, naming the first query time
        it cannot answer and why."""
        t = self.t
        i = int(np.flatnonzero(unsupported)[0])
        count = int(unsupported.sum())
        if before[i]:
            why = f"before the first measurement (t = {float(t[0])!r} s)"
        elif after[i]:
            why = f"after the last measurement (t = {float(t[-1])!r} s)"
        else:
            why = (
                f"inside a gap of {t[ki[i] + 1] - t[ki[i]]:.3f} s between measurements at "
                f"{float(t[ki[i]])!r} s and {float(t[ki[i] + 1])!r} s, longer than max_gap_s = "
                f"{self.max_gap_s!r} s"
            )
        raise ExtrapolationError(
            f"query time {float(tau[i])!r} s is {why} "
            f"({count} of {tau.size} queries unsupported); query inside the track, "
            "or pass allow_gaps=True to get a flagged answer"
        )

    def _query_chunk(self, tau, kc, ki, on_knot, interior, before, after, dim):
        t, S, C, m = self.t, self.cov, self.cross_cov, self.mean
        q = tau.shape[0]
        mean = np.empty((q, self.state_dim))
        cov = np.empty((q, dim, dim))
        # on a knot: the knot posterior itself
        idx = np.flatnonzero(on_knot)
        if idx.size:
            mean[idx] = m[kc[idx]]
            cov[idx] = S[kc[idx], :dim, :dim]
        # between two knots: conditional Gaussian given both knot states (closed form in s)
        idx = np.flatnonzero(interior)
        if idx.size:
            k = ki[idx]
            big_d = t[k + 1] - t[k]
            s = (tau[idx] - t[k]) / big_d
            if self.prior == "wnoj":
                lam, psi, qq = _bridge3(s, big_d)
            else:
                lam, psi, qq = _bridge2(s, big_d)
            x0, x1 = m[k], m[k + 1]
            mean[idx] = _kron_vec(lam, x0) + _kron_vec(psi, x1)
            wl = _kron2(lam, _EYE3)[:, :dim]
            wp = _kron2(psi, _EYE3)[:, :dim]
            s_k, s_k1, c_k = S[k], S[k + 1], C[k]
            t1 = wl @ s_k + wp @ np.swapaxes(c_k, 1, 2)
            t2 = wl @ c_k + wp @ s_k1
            cov[idx] = (
                t1 @ np.swapaxes(wl, 1, 2)
                + t2 @ np.swapaxes(wp, 1, 2)
                + (self.interval_scale(k)[:, None, None] * _kron2(qq, self.qc))[:, :dim, :dim]
            )
        # after the end: prediction from the last knot
        idx = np.flatnonzero(after)
        if idx.size:
            d = tau[idx] - t[-1]
            phi = self.transition(d)
            mean[idx] = np.einsum("nij,j->ni", phi, m[-1])
            last = self.interval_scale(np.full(idx.size, t.shape[0] - 2))[:, None, None]
            qd = _kron2(_prior_q_coef(self.prior, d), self.qc)
            full = phi @ S[-1] @ np.swapaxes(phi, 1, 2) + last * qd
            cov[idx] = full[:, :dim, :dim]
        # before the start: flat prior at the query time, conditioned on the first knot
        idx = np.flatnonzero(before)
        if idx.size:
            d = t[0] - tau[idx]
            phi_b = self.transition(-d)
            mean[idx] = np.einsum("nij,j->ni", phi_b, m[0])
            first = self.interval_scale(np.zeros(idx.size, int))[:, None, None]
            inner = S[0] + first * _kron2(_prior_q_coef(self.prior, d), self.qc)
            full = phi_b @ inner @ np.swapaxes(phi_b, 1, 2)
            cov[idx] = full[:, :dim, :dim]
        return mean, cov


def _bridge2(s: np.ndarray, big_d: np.ndarray):
    """WNOA: ``Lambda``, ``Psi`` and the bridge coefficients ``q`` (each (Q, 2, 2)) at the
    fractions ``s`` of intervals of length ``big_d`` (module docstring, Queries)."""
    n = s.shape[0]
    s2, s3 = s * s, s * s * s
    lam = np.empty((n, 2, 2))
    psi = np.empty((n, 2, 2))
    lam[:, 0, 0] = 1.0 - 3.0 * s2 + 2.0 * s3
    lam[:, 0, 1] = big_d * (s - 2.0 * s2 + s3)
    lam[:, 1, 0] = -6.0 * (s - s2) / big_d
    lam[:, 1, 1] = 1.0 - 4.0 * s + 3.0 * s2
    psi[:, 0, 0] = 3.0 * s2 - 2.0 * s3
    psi[:, 0, 1] = big_d * (s3 - s2)
    psi[:, 1, 0] = 6.0 * (s - s2) / big_d
    psi[:, 1, 1] = 3.0 * s2 - 2.0 * s
    u = 1.0 - s
    qq = np.empty((n, 2, 2))
    qq[:, 0, 0] = big_d**3 * s3 * u**3 / 3.0
    qq[:, 0, 1] = qq[:, 1, 0] = big_d**2 * s2 * u * u * (1.0 - 2.0 * s) / 2.0
    qq[:, 1, 1] = big_d * s * u * (1.0 - 3.0 * s + 3.0 * s2)
    return lam, psi, qq


def _bridge3(s: np.ndarray, big_d: np.ndarray):
    """WNOJ: ``Lambda``, ``Psi`` and the bridge coefficients (each (Q, 3, 3)), computed on the
    unit interval and scaled (module docstring, Queries): with ``T = diag(D^2, D, 1)``,
    ``Phi(s D) = T Phi_1(s) T^-1`` and ``Q(s D) = D T Q_1(s) T``, so
    ``Psi = T Psi_1 T^-1``, ``Lambda = T Lambda_1 T^-1`` and the bridge is ``D T q_1 T``."""
    def unit(s):
        q_s = _q3_coef(s)
        phi_u = _phi3_coef(1.0 - s)
        psi1 = q_s @ np.swapaxes(phi_u, 1, 2) @ _q3inv_coef(np.ones(1))
        return q_s, phi_u, psi1

    q_s, phi_u, psi1 = unit(s)
    lam1 = _phi3_coef(s) - psi1 @ _phi3_coef(np.ones(1))
    # the bridge is a difference of two terms of order s^5 (position); past the middle it is
    # evaluated from the other end (time reversal flips the sign of the velocity), so it never
    # loses more than a few digits to cancellation
    near = np.minimum(s, 1.0 - s)
    q_n, phi_n, psi_n = unit(near)
    qq1 = _sym(q_n - psi_n @ phi_n @ q_n)
    qq1 = np.where((s > 0.5)[:, None, None], qq1 * _FLIP3[:, None] * _FLIP3[None, :], qq1)
    scale = np.stack([big_d * big_d, big_d, np.ones_like(big_d)], axis=1)  # diag of T
    ratio = scale[:, :, None] / scale[:, None, :]
    return lam1 * ratio, psi1 * ratio, big_d[:, None, None] * qq1 * scale[:, :, None] * scale[:, None, :]


def _kron_vec(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``kron(a, I3) @ x`` for a (Q, r, r) and x (Q, 3r)."""
    r = a.shape[-1]
    xr = x.reshape(-1, r, 3)
    return np.einsum("qab,qbj->qaj", a, xr).reshape(-1, 3 * r)


def fit_track(
    track,
    *,
    qc=None,
    fit_qc: bool = False,
    qc_mode: str = "isotropic",
    initial_state_cov: ArrayLike | None = None,
    initial_state_mean: ArrayLike | None = None,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    qc_bounds: tuple[float, float] = QC_BOUNDS,
    max_iter: int = 200,
    tol: float = 1e-4,
    qc_scale: ArrayLike | None = None,
    held_out: ArrayLike | None = None,
    prior: str = "wnoa",
) -> GPTrack:
    """Fit the exact GP posterior of one prism track (WNOA or WNOJ prior).

    Parameters
    ----------
    track : PrismTrack or tuple (t, xyz, cov)
        ``t`` (N,) s strictly increasing, ``xyz`` (N, 3) m, ``cov`` (N, 3, 3) m^2 symmetric
        positive definite, N >= 2.
    qc : float, array_like (3,) or (3, 3), optional
        Power spectral density, m^2/s^3 for WNOA, m^2/s^5 for WNOJ (scalar: ``q I``; (3,):
        diagonal; (3, 3): full). When None, ``Qc`` is estimated (``fit_qc`` is implied).
    fit_qc : bool
        Estimate ``Qc`` by maximum marginal likelihood (``qc``, if given, is the initial guess).
    qc_mode : {"isotropic", "per-axis"}
        Parametrisation of the estimated ``Qc``.
    initial_state_cov : array_like, shape (d, d), optional
        Covariance of a proper Gaussian prior on ``x(t_0)`` (``[p; v]``, d = 6, or
        ``[p; v; a]``, d = 9). Default: diffuse prior (zero prior information; module
        docstring).
    initial_state_mean : array_like, shape (d,), optional
        Mean of that prior (default: first measurement, zero velocity and acceleration).
    max_gap_s : float
        Longest gap between measurements across which queries are answered, s.
    qc_bounds, max_iter, tol
        Passed to :func:`fit_qc`.
    qc_scale : array_like, shape (N-1,), optional
        A prior whose strength follows the motion: interval ``k`` (between measurements ``k``
        and ``k+1``) gets ``Qc_k = qc_scale[k] Qc``, each > 0 (e.g. a smaller ``Qc`` while
        the robot stands; :mod:`rtsgt.interpolation.motion`). Needs a given ``qc``.
    held_out : array_like of bool, shape (N,), optional
        Measurements given no weight (cross-validation): their times stay knots, so the
        intervals of ``qc_scale`` and the prior between the others are unchanged, but their
        values are ignored; the posterior at such a knot is the prediction from the other
        measurements, and ``log_likelihood`` is that of the others alone. At least 2 must be
        left; ``qc`` is then estimated (if asked) from those.
    prior : {"wnoa", "wnoj"}
        White noise on the acceleration (state ``[p; v]``, the paper's) or on the jerk (state
        ``[p; v; a]``; the posterior is proper from 3 measurements with the diffuse prior).

    Returns
    -------
    GPTrack

    Raises
    ------
    InputError
        Fewer than 2 measurements, non-finite values, times not strictly increasing,
        covariances not symmetric positive definite, a bad ``qc``.

    Examples
    --------
    >>> gp = fit_track((t, xyz, cov), qc=0.1)          # doctest: +SKIP
    >>> res = gp.query(np.arange(t[0], t[-1], 0.2))    # doctest: +SKIP
    >>> res.position, res.position_cov                 # doctest: +SKIP
    """
    mg = float(max_gap_s)
    if not mg > 0:
        raise InputError(f"Expected max_gap_s > 0 s, got {max_gap_s!r}")
    data = prepare_track(track, initial_state_cov, initial_state_mean, prior)
    if held_out is not None:
        data = _held_out(data, held_out, track_arrays(track)[2])
    if qc_scale is not None and (qc is None or fit_qc):
        raise InputError("qc_scale needs a given qc (it scales that Qc per interval)")
    scale = check_scale(data, qc_scale)
    info = None
    if qc is None or fit_qc:
        info = _fit_qc_data(data, qc_mode, qc, qc_bounds, max_iter, tol)
        qc_m = np.array(info.qc)
    else:
        qc_m = as_qc(qc)
    mean, S, C, loglik = _solve(data, qc_m, want_cov=True, scale=scale)
    mean[:, :3] += data.y_ref
    return GPTrack(
        t=_readonly(data.t.copy()),
        mean=_readonly(mean),
        cov=_readonly(S),
        cross_cov=_readonly(C),
        qc=_readonly(qc_m),
        log_likelihood=float(loglik),
        max_gap_s=mg,
        prism=data.prism,
        frame=data.frame,
        diffuse_prior=data.prior_inv is None,
        qc_fit=info,
        qc_scale=_readonly(None if scale is None else scale.copy()),
        prior=data.prior,
    )
