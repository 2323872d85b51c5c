r"""Poses with a 6x6 covariance from three or more prisms: Monte Carlo, unscented, linear.

Model (one for the three engines)
---------------------------------
At each pose time k the prisms' world positions ``q_ki`` (m) are Gaussian with a 3x3
covariance each, independent between prisms and between times (what the GP interpolation
gives); the reference positions ``r_i`` of the same prisms in the body frame (the static
survey) are Gaussian with a full ``(3n, 3n)`` covariance (correlated between prisms when the
body frame is defined by surveyed points), the same draw for every pose. The pose is the
least-squares rigid fit, ``registration="weighted"`` (:mod:`rtsgt.pose.weighted`)::

    T_world_body,k = argmin_T  e_k^T W_k e_k,   e_k = (q_ki - T r_i)_i  stacked (3n)

with ``W_k`` the inverse of the residual's covariance ``Sigma_q,k + (I (x) R_k) Sigma_r
(I (x) R_k)^T``, evaluated once per pose at the closed-form rotation of the mean inputs and
held fixed for every sample and sigma point of that pose; or ``registration="unweighted"``,
the paper's point-to-point fit (:func:`rtsgt.pose.registration.register`)::

    T_world_body,k = argmin_T  sum_i || q_ki - T r_i ||^2

Reported mean: the fit of the mean inputs (one documented choice for every engine). Reported
covariance: the second moment of the left perturbation ``xi = (dt, dtheta)`` of the fit of the
perturbed inputs about that mean, 6x6 ordered (x, y, z, rx, ry, rz), world frame, the
convention of :mod:`rtsgt.geometry.transform` (``t = t_mean + dt``,
``R = exp([dtheta]x) R_mean``).

Engines
-------
``"mc"``
    The paper's Monte Carlo: ``M`` samples of every prism (Cholesky factor of each covariance)
    and of the stacked reference (Cholesky factor of the full covariance, one draw per sample
    m shared by all poses), each solved with the registration (the closed form; the weighted
    fit by chord steps from its first-order prediction,
    :func:`rtsgt.pose.weighted.refine_samples`), vectorised over poses and samples in chunks
    of a few poses (memory bounded by the chunk). ``mean_offset`` reports the sample mean of
    ``xi``: the
    one-step estimate of the SE(3) mean of the samples about the reported pose (it differs from
    it by a second-order bias, far below the noise).
``"ut"``
    Unscented transform over the stacked vector ``(q_k1..q_kn, r_1..r_n)`` of dimension 6n
    (Julier and Uhlmann 2004, symmetric set with ``alpha = 1, kappa = 0``: ``2 L`` points at
    ``+- sqrt(L)`` times the columns of the block Cholesky factor, weights ``1 / (2 L)``, the
    centre weight 0). ``mean_offset`` is the weighted mean of the sigma points' ``xi``.
``"linear"``
    First order: ``cov = J_q Sigma_q J_q^T + J_r Sigma_r J_r^T`` with the analytic Jacobian of
    the fit (:func:`rtsgt.pose.registration.registration_jacobian`, or
    :func:`rtsgt.pose.weighted.weighted_registration_jacobian`; implicit function theorem).

Degenerate poses (reported, never silently solved): a prism or its covariance is not finite
(``"missing_prism"``), or the world prisms are nearly collinear (:func:`shape_ratio` below
``min_shape``, ``"collinear"``). Their pose and covariance are NaN.
"""

from __future__ import annotations

import os
import warnings
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import GeometryError, RtsgtWarning
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.geometry.transform import check_covariance
from rtsgt.pose.reference import ReferencePoints, block_diagonal
from rtsgt.pose.registration import (
    DEFAULT_CHUNK,
    MIN_SHAPE,
    _register_flat,
    register,
    registration_jacobian,
    shape_ratio,
    small_rotation_vector,
)
from rtsgt.pose.weighted import (
    GLS_MAX_ITER,
    gls_weights,
    newton_inverse_at,
    refine_batches,
    refine_samples,
    weighted_registration_jacobian,
)

#: The pose engines, as a type: Monte Carlo, unscented transform, first order.
PoseEngine = Literal["mc", "ut", "linear"]
#: Their names (the one list every option, command and reader checks against).
POSE_ENGINES: tuple[str, ...] = get_args(PoseEngine)
#: The registrations, as a type: weighted by the residual's covariance, or the paper's.
Registration = Literal["weighted", "unweighted"]
#: Their names.
REGISTRATIONS: tuple[str, ...] = get_args(Registration)
#: The registration of every engine unless told otherwise (the default of ``[pose]``).
DEFAULT_REGISTRATION: Registration = "weighted"

#: Reason codes of :attr:`PoseEstimate.reason` ("" for a valid pose).
REASON_OK = ""
REASON_MISSING = "missing_prism"
REASON_COLLINEAR = "collinear"

#: Default number of registrations per Monte Carlo chunk (bounds the memory to ~10 MB).
DEFAULT_MC_CHUNK = 1 << 14
#: Threads of the Monte Carlo chunks when not given (None: the cores available, at most
#: :data:`MAX_MC_THREADS`; :func:`mc_threads`). The result does not depend on it.
MC_THREADS: int | None = None
#: The most threads the default takes (the chunks are small; more threads gain little).
MAX_MC_THREADS = 4


@dataclass(frozen=True)
class PoseEstimate:
    """Poses ``T_world_body`` with covariance, one per query time (time-agnostic).

    Attributes
    ----------
    R : ndarray, shape (T, 3, 3)
        ``R_world_body``; NaN for degenerate poses.
    t : ndarray, shape (T, 3)
        ``t_world_body``, m; NaN for degenerate poses.
    cov : ndarray, shape (T, 6, 6)
        Left-perturbation covariance in the world frame, ordered (x, y, z, rx, ry, rz),
        m^2 / rad^2 (:mod:`rtsgt.geometry.transform`); NaN for degenerate poses.
    degenerate : ndarray of bool, shape (T,)
    reason : ndarray of str, shape (T,)
        ``""`` (valid), ``"missing_prism"`` or ``"collinear"``.
    inter_prism_distance : ndarray, shape (T, n (n - 1) / 2)
        ``|q_i - q_j|`` of the mean world prisms for the pairs :attr:`pairs` (m); NaN where a
        prism is missing.
    rms_residual : ndarray, shape (T,)
        ``sqrt(mean_i |q_i - R r_i - t|^2)`` of the mean fit, m.
    shape : ndarray, shape (T,)
        Shape ratio of the world prisms (:func:`rtsgt.pose.registration.shape_ratio`).
    pairs : tuple of (int, int)
        Prism index pairs of :attr:`inter_prism_distance`: (0, 1), (0, 2), ..., (1, 2), ...
    engine : str
    samples : int or None
        Monte Carlo samples (``"mc"``) or sigma points (``"ut"``); None for ``"linear"``.
    mean_offset : ndarray, shape (T, 6), or None
        Mean perturbation of the samples (sigma points) about the reported pose: how far the
        SE(3) mean of the samples is from the fit of the mean inputs. None for ``"linear"``.
    registration : {"weighted", "unweighted"}
        The fit of every pose, sample and sigma point (module docstring).
    """

    R: np.ndarray
    t: np.ndarray
    cov: np.ndarray
    degenerate: np.ndarray
    reason: np.ndarray
    inter_prism_distance: np.ndarray
    rms_residual: np.ndarray
    shape: np.ndarray
    pairs: tuple[tuple[int, int], ...]
    engine: str
    samples: int | None = None
    mean_offset: np.ndarray | None = None
    registration: str = "unweighted"

    def __len__(self) -> int:
        return self.t.shape[0]

    @property
    def position(self) -> np.ndarray:
        """``t_world_body``, shape (T, 3), m."""
        return self.t

    @property
    def quat_xyzw(self) -> np.ndarray:
        """Orientation as unit quaternions (qx, qy, qz, qw), shape (T, 4); NaN if degenerate."""
        out = np.full((len(self), 4), np.nan)
        ok = ~self.degenerate
        if ok.any():
            out[ok] = matrix_to_quat_xyzw(self.R[ok])
        return out

    @property
    def counts(self) -> dict[str, int]:
        """Poses per reason: ``{"valid": ..., "missing_prism": ..., "collinear": ...}``."""
        return {
            "valid": int(np.sum(~self.degenerate)),
            REASON_MISSING: int(np.sum(self.reason == REASON_MISSING)),
            REASON_COLLINEAR: int(np.sum(self.reason == REASON_COLLINEAR)),
        }


def psd_factor(cov: ArrayLike) -> np.ndarray:
    """A factor ``L`` with ``L @ L^T == cov`` for (batches of) PSD matrices.

    Cholesky where it succeeds for the whole batch; otherwise (a singular covariance, e.g. a
    reference known exactly) ``V diag(sqrt(max(w, 0)))`` from ``eigh``, scaling the *columns*
    of the eigenvector matrix (the reference code used its rows: pitfall 1 of
    docs/noise-model.md#reference-code-pitfalls).

    Parameters
    ----------
    cov : array_like, shape (..., d, d)

    Returns
    -------
    ndarray, shape (..., d, d)
    """
    cov = np.asarray(cov, dtype=float)
    try:
        return np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
        return V * np.sqrt(np.clip(w, 0.0, None))[..., None, :]


def _reference_inputs(r_body, cov_r) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(r_body, ReferencePoints):
        if cov_r is not None:
            raise ValueError("Expected cov_r=None when r_body is a ReferencePoints (it has one)")
        return r_body.xyz, r_body.cov
    r = np.asarray(r_body, dtype=float)
    if r.ndim != 2 or r.shape[1] != 3:
        raise ValueError(f"Expected r_body of shape (n, 3), got {r.shape}")
    n = r.shape[0]
    if cov_r is None:
        raise ValueError("Expected cov_r of shape (3n, 3n) or (n, 3, 3), got None")
    c = np.asarray(cov_r, dtype=float)
    if c.shape == (n, 3, 3):
        full = np.zeros((3 * n, 3 * n))
        for i in range(n):
            full[3 * i:3 * i + 3, 3 * i:3 * i + 3] = c[i]
        c = full
    if c.shape != (3 * n, 3 * n):
        raise ValueError(
            f"Expected cov_r of shape ({3 * n}, {3 * n}) or ({n}, 3, 3), got {c.shape}"
        )
    if not np.all(np.isfinite(r)):
        raise ValueError("Expected finite reference positions r_body")
    return r, check_covariance(c, 3 * n, "cov_r")


def estimate_poses(
    q_world: ArrayLike,
    cov_q: ArrayLike,
    r_body: ArrayLike | ReferencePoints,
    cov_r: ArrayLike | None = None,
    *,
    engine: PoseEngine = "mc",
    registration: Registration = DEFAULT_REGISTRATION,
    weight_cov_q: ArrayLike | None = None,
    weight_cov_r: ArrayLike | None = None,
    samples: int = 1000,
    rng: np.random.Generator | None = None,
    chunk_size: int | None = None,
    min_shape: float = MIN_SHAPE,
    threads: int | None = None,
) -> PoseEstimate:
    """Poses ``T_world_body`` and their 6x6 covariances from prism positions.

    Parameters
    ----------
    q_world : array_like, shape (T, n, 3)
        Mean world positions of the n prisms at each pose time, m. NaN marks a missing prism.
    cov_q : array_like, shape (T, n, 3, 3) or (T, 3n, 3n)
        Their covariances, m^2, world frame: per prism (independent between prisms), or the
        joint covariance of the stacked ``(q_1x, q_1y, q_1z, q_2x, ...)`` at each time, for
        errors shared between prisms (e.g. two stations calibrated from the same GCP shots).
        Poses are independent between times either way.
    r_body : array_like, shape (n, 3), or ReferencePoints
        Reference positions of the same prisms, in the same order, in the body frame, m.
    cov_r : array_like, shape (3n, 3n) or (n, 3, 3)
        Covariance of the stacked reference ``(r_1x, r_1y, r_1z, r_2x, ...)``, m^2, body frame
        (None when ``r_body`` is a :class:`ReferencePoints`).
    engine : {"mc", "ut", "linear"}
        Uncertainty engine (module docstring).
    registration : {"weighted", "unweighted"}
        The fit: weighted by the inverse covariance of the residual
        (:mod:`rtsgt.pose.weighted`), or the paper's unweighted point-to-point fit.
    weight_cov_q, weight_cov_r : array_like, optional
        The covariances the weights are built from (``"weighted"`` only), shaped like
        ``cov_q`` and ``cov_r``; default ``cov_q`` and ``cov_r``. Give the total covariances
        here when ``cov_q`` and ``cov_r`` are a part of them to propagate (one source, the
        varying part): the fit is then the same as the total's, and only the propagated
        covariance changes.
    samples : int
        Monte Carlo samples M (``"mc"`` only).
    rng : numpy.random.Generator
        Required by ``"mc"``. Draws: the reference ``(M, 3n)`` first, then the prisms
        ``(T_valid, M, n, 3)`` in pose order, so results do not depend on ``chunk_size`` (nor
        on whether a block-diagonal covariance is given per prism or jointly).
    chunk_size : int, optional
        Registrations per Monte Carlo chunk (default 16384), bounds the memory.
    min_shape : float
        Collinearity threshold on the shape ratio (:data:`MIN_SHAPE`).
    threads : int, optional
        Threads fitting the Monte Carlo chunks (default :func:`mc_threads`: the cores
        available, at most 4); the draws stay in order, the result is the same bit for bit.

    Returns
    -------
    PoseEstimate

    Raises
    ------
    ValueError
        Bad shapes, a non-PSD covariance, an unknown engine, a missing generator.
    GeometryError
        Fewer than 3 prisms, or a nearly collinear reference.
    """
    q = np.asarray(q_world, dtype=float)
    cq = np.asarray(cov_q, dtype=float)
    if q.ndim != 3 or q.shape[2] != 3:
        raise ValueError(f"Expected q_world of shape (T, n, 3), got {q.shape}")
    T, n, _ = q.shape
    if cq.shape == (T, n, 3, 3):
        cq = block_diagonal(cq)
    elif cq.shape != (T, 3 * n, 3 * n):
        raise ValueError(
            f"Expected cov_q of shape ({T}, {n}, 3, 3) or ({T}, {3 * n}, {3 * n}), got {cq.shape}")
    r, cr = _reference_inputs(r_body, cov_r)
    if r.shape[0] != n:
        raise ValueError(f"Expected {n} reference points (one per prism), got {r.shape[0]}")
    if n < 3:
        raise GeometryError(f"A pose needs at least 3 prisms, got {n}")
    if engine not in POSE_ENGINES:
        raise ValueError(f"Expected engine in {POSE_ENGINES}, got {engine!r}")
    if registration not in REGISTRATIONS:
        raise ValueError(f"Expected registration in {REGISTRATIONS}, got {registration!r}")
    weighted = registration == "weighted"
    wq, wr = cq, cr
    if weighted and weight_cov_q is not None:
        wq = np.asarray(weight_cov_q, dtype=float)
        if wq.shape == (T, n, 3, 3):
            wq = block_diagonal(wq)
        elif wq.shape != (T, 3 * n, 3 * n):
            raise ValueError(f"Expected weight_cov_q of shape ({T}, {n}, 3, 3) or "
                             f"({T}, {3 * n}, {3 * n}), got {wq.shape}")
    if weighted and weight_cov_r is not None:
        wr = _reference_inputs(r, weight_cov_r)[1]
    if engine == "mc":
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"Expected a numpy.random.Generator for engine 'mc', got {rng!r}")
        if int(samples) != samples or samples < 2:
            raise ValueError(f"Expected an integer number of samples >= 2, got {samples}")
        samples = int(samples)
        threads = mc_threads(threads)
    chunk = DEFAULT_MC_CHUNK if chunk_size is None else int(chunk_size)
    if chunk < 1:
        raise ValueError(f"Expected a positive chunk_size, got {chunk_size}")
    shape_ref = float(shape_ratio(r))
    if not shape_ref >= min_shape:
        raise GeometryError(
            f"The reference prisms are nearly collinear (shape ratio {shape_ref:.3g} < "
            f"{min_shape}): the rotation about their line is not determined"
        )

    # per-pose validity
    finite = np.all(np.isfinite(q), axis=(1, 2)) & np.all(np.isfinite(cq), axis=(1, 2))
    if wq is not cq:
        finite &= np.all(np.isfinite(wq), axis=(1, 2))
    if finite.any():
        check_covariance(cq[finite], 3 * n, "cov_q")
        if wq is not cq:
            check_covariance(wq[finite], 3 * n, "weight_cov_q")
    shape = shape_ratio(q)
    collinear = finite & ~(shape >= min_shape)
    reason = np.full(T, REASON_OK, dtype="<U16")
    reason[~finite] = REASON_MISSING
    reason[collinear] = REASON_COLLINEAR
    degenerate = reason != REASON_OK
    valid = np.flatnonzero(~degenerate)

    pairs = tuple((i, j) for i in range(n) for j in range(i + 1, n))
    ii = np.array([a for a, _ in pairs])
    jj = np.array([b for _, b in pairs])
    dist = np.linalg.norm(q[:, ii] - q[:, jj], axis=-1)

    R = np.full((T, 3, 3), np.nan)
    t = np.full((T, 3), np.nan)
    cov = np.full((T, 6, 6), np.nan)
    rms = np.full(T, np.nan)
    offset = None if engine == "linear" else np.full((T, 6), np.nan)
    n_samples: int | None = None
    if engine == "mc":
        n_samples = samples
    elif engine == "ut":
        n_samples = 12 * n

    qv, cqv = q[valid], cq[valid]
    gls = None
    unconverged = 0
    if valid.size:
        rb = np.broadcast_to(r, qv.shape)
        Rv, tv = register(rb, qv)
        if weighted:
            W = gls_weights(wq[valid], wr, Rv)
            Rv, tv, conv, _ = refine_batches(rb[:, None], qv[:, None], W, Rv[:, None],
                                             tv[:, None])
            Rv, tv = Rv[:, 0], tv[:, 0]
            unconverged += int(np.sum(~conv))
            J_q, J_r = weighted_registration_jacobian(rb, qv, W, Rv, tv)
            gls = (W, J_q.reshape(valid.size, 6, 3 * n), J_r.reshape(valid.size, 6, 3 * n))
        res = qv - (np.einsum("kij,nj->kni", Rv, r) + tv[:, None, :])
        rms[valid] = np.sqrt(np.mean(np.sum(res * res, axis=-1), axis=-1))
        R[valid], t[valid] = Rv, tv
    if engine == "mc":
        Lr = psd_factor(cr)
        z_r = rng.standard_normal((samples, 3 * n))  # drawn even when no pose is valid
        if valid.size:
            r_samples = (r.reshape(3 * n) + z_r @ Lr.T).reshape(samples, n, 3)
            c, o, u = _mc(qv, psd_factor(cqv), r_samples, r, Rv, tv, rng, chunk, gls,
                          threads)
            cov[valid], offset[valid] = c, o
            unconverged += u
    elif valid.size and engine == "ut":
        c, o, u = _ut(qv, psd_factor(cqv), r, psd_factor(cr), Rv, tv, gls)
        cov[valid], offset[valid] = c, o
        unconverged += u
    elif valid.size:
        if gls is None:
            J_q, J_r = registration_jacobian(np.broadcast_to(r, qv.shape), qv, Rv)
            Jq = J_q.reshape(valid.size, 6, 3 * n)
            Jr = J_r.reshape(valid.size, 6, 3 * n)
        else:
            Jq, Jr = gls[1], gls[2]
        c = Jq @ cqv @ np.swapaxes(Jq, 1, 2)
        c = c + np.einsum("kai,ij,kbj->kab", Jr, cr, Jr)
        cov[valid] = c
    if unconverged:
        warnings.warn(f"The weighted registration did not converge for {unconverged} fits "
                      f"(poses, samples or sigma points) in {GLS_MAX_ITER} Newton steps",
                      RtsgtWarning, stacklevel=2)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    return PoseEstimate(R, t, cov, degenerate, reason, dist, rms, shape, pairs, engine,
                        n_samples, offset, registration)


def pose_weights(q_world: ArrayLike, cov_q: ArrayLike, r_body: ArrayLike,
                 cov_r: ArrayLike) -> np.ndarray:
    """The weights ``W`` (T, 3n, 3n) the weighted fit gives each pose (:func:`estimate_poses`):
    :func:`rtsgt.pose.weighted.gls_weights` at the rotation of the closed-form fit of the mean
    inputs. ``q_world`` (T, n, 3) and ``cov_q`` (T, 3n, 3n) or (T, n, 3, 3), valid poses only;
    ``r_body`` (n, 3), ``cov_r`` (3n, 3n)."""
    q = np.asarray(q_world, dtype=float)
    T, n, _ = q.shape
    cq = np.asarray(cov_q, dtype=float)
    if cq.shape == (T, n, 3, 3):
        cq = block_diagonal(cq)
    r = np.asarray(r_body, dtype=float)
    R0 = register(np.broadcast_to(r, q.shape), q)[0]
    return gls_weights(cq, np.asarray(cov_r, dtype=float), R0)


def pose_jacobians(
    q_world: ArrayLike, r_body: ArrayLike, R_world_body: ArrayLike, *,
    registration: Registration = DEFAULT_REGISTRATION, cov_q: ArrayLike | None = None,
    cov_r: ArrayLike | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``J_q, J_r`` (T, 6, 3n): the first-order sensitivity of the poses' fit to the stacked
    prisms and reference, for either registration (the linear engine's Jacobians).

    ``q_world`` (T, n, 3), ``r_body`` (n, 3), ``R_world_body`` (T, 3, 3) the poses' rotations;
    ``cov_q`` (T, 3n, 3n) or (T, n, 3, 3) and ``cov_r`` (3n, 3n): the total covariances the
    weights are built from (:func:`pose_weights`), ``"weighted"`` only. The poses must be
    valid (not degenerate).
    """
    q = np.asarray(q_world, dtype=float)
    T, n, _ = q.shape
    rb = np.broadcast_to(np.asarray(r_body, dtype=float), q.shape)
    if registration == "weighted":
        if cov_q is None or cov_r is None:
            raise ValueError("The weighted registration's Jacobian needs cov_q and cov_r")
        W = pose_weights(q, cov_q, r_body, cov_r)
        J_q, J_r = weighted_registration_jacobian(rb, q, W, R_world_body)
    elif registration == "unweighted":
        J_q, J_r = registration_jacobian(rb, q, R_world_body)
    else:
        raise ValueError(f"Expected registration in {REGISTRATIONS}, got {registration!r}")
    return J_q.reshape(T, 6, 3 * n), J_r.reshape(T, 6, 3 * n)


def _perturbations(R: np.ndarray, t: np.ndarray, R0: np.ndarray, t0: np.ndarray) -> np.ndarray:
    """Left perturbations (..., S, 6) of solutions (..., S) about means (..., 3, 3)/(..., 3)."""
    dR = R @ np.swapaxes(R0, -1, -2)[..., None, :, :]
    xi = np.empty(t.shape[:-1] + (6,))
    xi[..., :3] = t - t0[..., None, :]
    xi[..., 3:] = small_rotation_vector(dR)
    return xi


def _fit_samples(P, Q, q, r, R0, t0, gls):
    """The fits of (K, S) perturbed problems ``P`` (body, may be broadcast) and ``Q`` (world),
    (K, S, n, 3), of the poses ``q`` (K, n, 3) / ``r`` (n, 3) fitted at ``R0``, ``t0``.

    Unweighted: the closed form of each. Weighted (``gls = (W, J_q, J_r)`` of the poses):
    Newton from the first-order prediction ``exp(J_q dq + J_r dr) (R0, t0)`` of each, which
    is within the square of the perturbation of the sample's own fit (two steps instead of
    three from the closed form). Returns ``R`` (K, S, 3, 3), ``t`` (K, S, 3) and the number
    of fits that did not converge.
    """
    K, S, n, _ = Q.shape
    if gls is None:
        Pb = np.broadcast_to(P, Q.shape)
        Rs, ts, _ = _register_flat(Pb.reshape(-1, n, 3), Q.reshape(-1, n, 3), DEFAULT_CHUNK)
        return Rs.reshape(K, S, 3, 3), ts.reshape(K, S, 3), 0
    W, J_q, J_r = gls
    dq = (Q - q[:, None]).reshape(K, S, 3 * n)
    dr = (P - r).reshape(P.shape[:-2] + (3 * n,))
    xi0 = dq @ np.swapaxes(J_q, 1, 2) + dr @ np.swapaxes(J_r, 1, 2)
    Rs, ts, conv, _ = refine_batches(P, Q, W, R0[:, None], t0[:, None], xi0)
    return Rs, ts, int(np.sum(~conv))


def mc_threads(threads: int | None = None) -> int:
    """The number of threads of the Monte Carlo engine's chunks: ``threads`` if given, else
    :data:`MC_THREADS` if set, else the cores this process may run on
    (``os.sched_getaffinity``, or ``os.cpu_count``), at most :data:`MAX_MC_THREADS`."""
    if threads is None:
        threads = MC_THREADS
    if threads is None:
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # not on every platform
            cores = os.cpu_count() or 1
        threads = min(cores, MAX_MC_THREADS)
    if int(threads) != threads or threads < 1:
        raise ValueError(f"Expected a positive integer number of threads, got {threads}")
    return int(threads)


def _mc(q, Lq, r_samples, r, R0, t0, rng, chunk, gls, threads=1):
    """Monte Carlo second moment and mean of the perturbations, chunked over poses.

    ``Lq`` (K, 3n, 3n) factors the joint prism covariance of each pose; ``gls``: the weights
    and Jacobians of the weighted fit, or None (:func:`_fit_samples`). The draws of a chunk
    of poses are the next rows of the one array ``(K, M, n, 3)`` (row-major fill), so the
    result does not depend on the chunk size; the memory is bounded by it. With ``threads``
    > 1 the chunks' fits run on a pool of that many threads (numpy releases the GIL in its
    kernels); the draws stay on the calling thread, in chunk order, at most ``threads + 1``
    chunks of them alive, and each chunk's arithmetic is its own: the result is the same,
    bit for bit, for every number of threads.
    """
    K, n, _ = q.shape
    M = r_samples.shape[0]
    m = 3 * n
    per = max(1, chunk // M)
    cov = np.empty((K, 6, 6))
    off = np.empty((K, 6))
    if gls is not None:
        W, J_q, J_r = gls
        X = np.ascontiguousarray(np.moveaxis(r_samples, 0, -1))  # (n, 3, M)
        dr = np.ascontiguousarray((r_samples - r).reshape(M, m).T)  # (3n, M)
        shifted = (q - t0[:, None, :]).reshape(K, m, 1)

    def work(s: int, e: int, z: np.ndarray) -> int:
        """Fit chunk ``[s, e)`` from its draws ``z`` (e - s, M, 3n); fill ``cov``, ``off``
        there; return its number of unconverged fits."""
        if gls is None:
            qs = q[s:e, None] + np.einsum("kab,kmb->kma", Lq[s:e], z).reshape(e - s, M, n, 3)
            Rs, ts, u = _fit_samples(r_samples[None], qs, q[s:e], r, R0[s:e], t0[s:e], None)
            xi = _perturbations(Rs, ts, R0[s:e], t0[s:e])
            cov[s:e] = np.einsum("kmi,kmj->kij", xi, xi) / M
            off[s:e] = xi.mean(axis=1)
            return u
        u = 0
        dq = Lq[s:e] @ np.swapaxes(z, 1, 2)  # (k, 3n, M)
        xi0 = J_q[s:e] @ dq + J_r[s:e] @ dr  # first-order prediction
        Wt, P, N_inv = newton_inverse_at(np.broadcast_to(r, q[s:e].shape), q[s:e], W[s:e],
                                         R0[s:e], t0[s:e])
        xi, conv = refine_samples(shifted[s:e] + dq, X, Wt, P, N_inv, R0[s:e], xi0)
        if not conv.all():  # far samples: Newton's steps from their first-order prediction
            kk, mm = np.nonzero(~conv)
            pb = r_samples[mm][:, None]
            qb = (q[s + kk] + np.swapaxes(dq, 1, 2)[kk, mm].reshape(-1, n, 3))[:, None]
            Rb, tb, cb, _ = refine_batches(pb, qb, W[s + kk], R0[s + kk, None],
                                           t0[s + kk, None], xi0[kk, :, mm][:, None])
            xi[kk, :, mm] = _perturbations(Rb, tb, R0[s + kk], t0[s + kk])[:, 0]
            u += int(np.sum(~cb))
        cov[s:e] = xi @ np.swapaxes(xi, 1, 2) / M
        off[s:e] = xi.mean(axis=2)
        return u

    def draws():  # (s, e, z) in chunk order, each drawn when asked for
        for s in range(0, K, per):
            e = min(K, s + per)
            yield s, e, rng.standard_normal((e - s, M, n, 3)).reshape(e - s, M, m)

    starts = range(0, K, per)
    threads = min(threads, len(starts))
    if threads <= 1:
        return cov, off, sum(work(*chunk_) for chunk_ in draws())
    unconverged = 0
    pending: deque[Future] = deque()
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="rtsgt-pose-mc") as pool:
        try:
            for chunk_ in draws():
                pending.append(pool.submit(work, *chunk_))
                del chunk_
                while len(pending) > threads:  # threads running, one queued, one drawing
                    unconverged += pending.popleft().result()
            while pending:
                unconverged += pending.popleft().result()
        finally:
            for f in pending:
                f.cancel()
    return cov, off, unconverged


def _ut(q, Lq, r, Lr, R0, t0, gls):
    """Unscented transform over (q_1..q_n, r_1..r_n): 2 L sigma points, L = 6 n."""
    K, n, _ = q.shape
    L = 6 * n
    gamma = np.sqrt(L)  # alpha = 1, kappa = 0: sigma points at +- sqrt(L) columns
    # prism part: column j of the joint factor moves the prisms along it
    dq = gamma * np.swapaxes(Lq, -1, -2).reshape(K, 3 * n, n, 3)  # rows = columns of L
    q_sig = np.concatenate([q[:, None] + dq, q[:, None] - dq], axis=1)  # (K, 6n, n, 3)
    p_sig_q = np.broadcast_to(r, q_sig.shape)
    dr = gamma * Lr.T.reshape(3 * n, n, 3)  # row k = column k of Lr
    r_sig = np.concatenate([r + dr, r - dr], axis=0)  # (6n, n, 3)
    p_sig_r = np.broadcast_to(r_sig, (K,) + r_sig.shape)
    q_sig_r = np.broadcast_to(q[:, None], p_sig_r.shape)
    P = np.concatenate([p_sig_q, p_sig_r], axis=1)
    Q = np.concatenate([q_sig, q_sig_r], axis=1)
    Rs, ts, unconverged = _fit_samples(P, Q, q, r, R0, t0, gls)
    xi = _perturbations(Rs, ts, R0, t0)
    w = 1.0 / (2 * L)
    return w * np.einsum("kmi,kmj->kij", xi, xi), w * xi.sum(axis=1), unconverged
