"""Poses ``T_world_body`` with a 6x6 covariance from three or more prisms (docs/pose.md).

:func:`estimate_poses` checks the inputs, marks the degenerate poses (a prism or its covariance
not finite: ``"missing_prism"``; nearly collinear prisms: ``"collinear"``; their pose and
covariance NaN), fits the mean inputs (the closed form, or the weighted fit) and hands the
valid poses to an engine of :mod:`rtsgt.pose.engines` (Monte Carlo, unscented, linear).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import GeometryError, RtsgtWarning
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.geometry.transform import check_covariance
from rtsgt.pose.engines import ENGINES, Linear, MonteCarlo, PoseFits, Unscented, psd_factor
from rtsgt.pose.reference import ReferencePoints, block_diagonal
from rtsgt.pose.registration import MIN_SHAPE, register, registration_jacobian, shape_ratio
from rtsgt.pose.weighted import (
    GLS_MAX_ITER,
    gls_weights,
    refine_batches,
    weighted_registration_jacobian,
)

__all__ = ["DEFAULT_REGISTRATION", "POSE_ENGINES", "REASON_COLLINEAR", "REASON_MISSING",
           "REASON_OK", "REGISTRATIONS", "PoseEngine", "PoseEstimate", "Registration",
           "estimate_poses", "pose_engine", "pose_jacobians", "pose_weights", "psd_factor"]

#: The pose engines' names, as a type (the engines: :data:`rtsgt.pose.engines.ENGINES`).
PoseEngine = Literal["mc", "ut", "linear"]
#: Their names (the one list every option, command and reader checks against).
POSE_ENGINES: tuple[str, ...] = tuple(ENGINES)
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


@dataclass(frozen=True)
class PoseEstimate:
    """Poses ``T_world_body`` with covariance, one per query time.

    ``R`` (T, 3, 3), ``t`` (T, 3) m, ``cov`` (T, 6, 6) the left-perturbation covariance,
    world frame, (x, y, z, rx, ry, rz) (:mod:`rtsgt.geometry.transform`), NaN where
    ``degenerate`` (T,); ``reason`` (T,): ``""``, ``"missing_prism"`` or ``"collinear"``;
    ``inter_prism_distance`` (T, n (n - 1) / 2) m, of the mean prisms for ``pairs`` ((0, 1),
    (0, 2), ..., (1, 2), ...); ``rms_residual`` (T,) m of the mean fit; ``shape`` (T,) the
    prisms' shape ratio; ``engine`` its name; ``samples`` Monte Carlo samples or sigma points
    (None for ``"linear"``); ``mean_offset`` (T, 6) the mean perturbation of the samples about
    the reported pose (None for ``"linear"``); ``registration`` the fit.
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


def pose_engine(engine, *, samples: int = 1000, rng: np.random.Generator | None = None,
                chunk_size: int | None = None, threads: int | None = None):
    """The engine named ``engine`` (:data:`rtsgt.pose.engines.ENGINES`) built from the arguments
    it takes; an engine object (``MonteCarlo(rng, ...)``, ``Unscented()``, ``Linear()``) as
    it is."""
    if isinstance(engine, tuple(ENGINES.values())):
        return engine
    if engine not in ENGINES:
        raise ValueError(f"Expected engine in {POSE_ENGINES}, got {engine!r}")
    return ENGINES[engine].build(samples=samples, rng=rng, chunk_size=chunk_size,
                                 threads=threads)


def _reference_inputs(r_body, cov_r) -> tuple[np.ndarray, np.ndarray]:
    """The reference (n, 3) and its joint covariance (3n, 3n), checked."""
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
        c = block_diagonal(c)
    if c.shape != (3 * n, 3 * n):
        raise ValueError(
            f"Expected cov_r of shape ({3 * n}, {3 * n}) or ({n}, 3, 3), got {c.shape}"
        )
    if not np.all(np.isfinite(r)):
        raise ValueError("Expected finite reference positions r_body")
    return r, check_covariance(c, 3 * n, "cov_r")


def _prism_cov(cov, T: int, n: int, name: str) -> np.ndarray:
    """A prisms' covariance (T, n, 3, 3) or (T, 3n, 3n) as the joint (T, 3n, 3n)."""
    c = np.asarray(cov, dtype=float)
    if c.shape == (T, n, 3, 3):
        return block_diagonal(c)
    if c.shape != (T, 3 * n, 3 * n):
        raise ValueError(f"Expected {name} of shape ({T}, {n}, 3, 3) or "
                         f"({T}, {3 * n}, {3 * n}), got {c.shape}")
    return c


def _inputs(q_world, cov_q, r_body, cov_r, weight_cov_q, weight_cov_r, registration):
    """The checked inputs ``q, cq, r, cr`` and the covariances ``wq, wr`` of the weights
    (``cq``, ``cr`` themselves unless the weighted fit is given others)."""
    q = np.asarray(q_world, dtype=float)
    if q.ndim != 3 or q.shape[2] != 3:
        raise ValueError(f"Expected q_world of shape (T, n, 3), got {q.shape}")
    T, n, _ = q.shape
    cq = _prism_cov(cov_q, T, n, "cov_q")
    r, cr = _reference_inputs(r_body, cov_r)
    if r.shape[0] != n:
        raise ValueError(f"Expected {n} reference points (one per prism), got {r.shape[0]}")
    if n < 3:
        raise GeometryError(f"A pose needs at least 3 prisms, got {n}")
    if registration not in REGISTRATIONS:
        raise ValueError(f"Expected registration in {REGISTRATIONS}, got {registration!r}")
    weighted = registration == "weighted"
    wq, wr = cq, cr
    if weighted and weight_cov_q is not None:
        wq = _prism_cov(weight_cov_q, T, n, "weight_cov_q")
    if weighted and weight_cov_r is not None:
        wr = _reference_inputs(r, weight_cov_r)[1]
    return q, cq, r, cr, wq, wr


def _reasons(q, cq, wq, min_shape: float) -> tuple[np.ndarray, np.ndarray]:
    """Each pose's reason code (T,) and its prisms' shape ratio (T,)."""
    T, n, _ = q.shape
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
    return reason, shape


def _fit_means(q, cq, r, cr, wq, wr, weighted: bool) -> tuple[PoseFits, int]:
    """The fits of the K valid poses' mean inputs (the weights from ``wq`` (K, 3n, 3n) and
    ``wr`` (3n, 3n)) and the count of weighted fits that did not converge."""
    K, n, _ = q.shape
    if K == 0:
        return PoseFits(q, cq, r, cr, np.empty((0, 3, 3)), np.empty((0, 3)), None), 0
    rb = np.broadcast_to(r, q.shape)
    R, t = register(rb, q)
    if not weighted:
        return PoseFits(q, cq, r, cr, R, t, None), 0
    W = gls_weights(wq, wr, R)
    R, t, conv, _ = refine_batches(rb[:, None], q[:, None], W, R[:, None], t[:, None])
    R, t = R[:, 0], t[:, 0]
    J_q, J_r = weighted_registration_jacobian(rb, q, W, R, t)
    gls = (W, J_q.reshape(K, 6, 3 * n), J_r.reshape(K, 6, 3 * n))
    return PoseFits(q, cq, r, cr, R, t, gls), int(np.sum(~conv))


def estimate_poses(
    q_world: ArrayLike,
    cov_q: ArrayLike,
    r_body: ArrayLike | ReferencePoints,
    cov_r: ArrayLike | None = None,
    *,
    engine: PoseEngine | MonteCarlo | Unscented | Linear = "mc",
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

    ``q_world`` (T, n, 3) m, NaN for a missing prism; ``cov_q`` (T, n, 3, 3) per prism or
    (T, 3n, 3n) joint, m^2; ``r_body`` (n, 3) m, the reference in the same order, with
    ``cov_r`` (3n, 3n) or (n, 3, 3) (or a :class:`ReferencePoints`, ``cov_r`` None).
    ``engine``: a name of :data:`POSE_ENGINES` built with ``samples``, ``rng`` (required by
    ``"mc"``; draws the reference (M, 3n), then the prisms (T_valid, M, n, 3) in pose order),
    ``chunk_size`` (fits per chunk, default 16384) and ``threads`` (:func:`rtsgt.pose.engines.
    mc_threads`), or an engine object. ``weight_cov_q``, ``weight_cov_r``: the covariances the
    weighted fit's weights are built from when ``cov_q``, ``cov_r`` are a part of them (default
    those). ``min_shape``: the collinearity threshold on the shape ratio. Raises ValueError (bad
    shapes or covariance, unknown engine, no generator) or GeometryError (fewer than 3 prisms,
    a nearly collinear reference).
    """
    q, cq, r, cr, wq, wr = _inputs(q_world, cov_q, r_body, cov_r, weight_cov_q, weight_cov_r,
                                   registration)
    engine = pose_engine(engine, samples=samples, rng=rng, chunk_size=chunk_size,
                         threads=threads)
    shape_ref = float(shape_ratio(r))
    if not shape_ref >= min_shape:
        raise GeometryError(
            f"The reference prisms are nearly collinear (shape ratio {shape_ref:.3g} < "
            f"{min_shape}): the rotation about their line is not determined"
        )
    T, n, _ = q.shape
    reason, shape = _reasons(q, cq, wq, min_shape)
    degenerate = reason != REASON_OK
    valid = np.flatnonzero(~degenerate)
    pairs = tuple((i, j) for i in range(n) for j in range(i + 1, n))
    ii = np.array([a for a, _ in pairs])
    jj = np.array([b for _, b in pairs])
    dist = np.linalg.norm(q[:, ii] - q[:, jj], axis=-1)

    fits, unconverged = _fit_means(q[valid], cq[valid], r, cr, wq[valid], wr,
                                   registration == "weighted")
    R = np.full((T, 3, 3), np.nan)
    t = np.full((T, 3), np.nan)
    rms = np.full(T, np.nan)
    if valid.size:
        res = fits.q - (np.einsum("kij,nj->kni", fits.R, r) + fits.t[:, None, :])
        rms[valid] = np.sqrt(np.mean(np.sum(res * res, axis=-1), axis=-1))
        R[valid], t[valid] = fits.R, fits.t
    c, o, u = engine.propagate(fits)
    cov = np.full((T, 6, 6), np.nan)
    cov[valid] = c
    offset = None
    if o is not None:
        offset = np.full((T, 6), np.nan)
        offset[valid] = o
    if unconverged + u:
        warnings.warn(f"The weighted registration did not converge for {unconverged + u} fits "
                      f"(poses, samples or sigma points) in {GLS_MAX_ITER} Newton steps",
                      RtsgtWarning, stacklevel=2)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    return PoseEstimate(R, t, cov, degenerate, reason, dist, rms, shape, pairs, engine.name,
                        engine.sample_count(n), offset, registration)


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


