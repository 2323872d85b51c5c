"""Module 4 of Vaidis et al. (2022): quality gates on poses, the surveyed distances against
the tracking, and the windows of distance rejections whose measurements are left out of a
refit.

A pose is kept when it is not degenerate, passes the distance gate (every inter-prism
distance within ``distance_gate_m`` of the survey's) and the uncertainty gate (position
uncertainty, by default ``sqrt(lambda_max(cov[:3, :3]))``, at most ``uncertainty_gate_m``);
:class:`GateReport` counts each gate and gives each rejected pose its first failing gate.
:func:`surveyed_distance_check` (median deviation per pair over its fully correlated sigma),
:func:`distance_outliers`, :func:`outlier_windows` and :func:`in_windows` (the refit of
``outlier_windows = "remove"``). docs/filtering.md#module-4-quality-gates,
docs/filtering.md#surveyed-distances-against-the-tracking,
docs/filtering.md#measurements-inside-the-windows-of-distance-rejections.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import RtsgtWarning
from rtsgt.filtering.modules import MODULE4_REASONS, FilterReport
from rtsgt.pose.reference import block_diagonal

#: The paper's distance gate, m.
DEFAULT_DISTANCE_GATE_M = 0.10
#: The paper's uncertainty gate, m (applied to the measure of :func:`position_uncertainty`).
DEFAULT_UNCERTAINTY_GATE_M = 0.20
#: Measures of the uncertainty gate.
UNCERTAINTY_MEASURES = ("max_std", "sqrt_trace", "sqrt_frobenius")

REASON_KEPT = ""
REASON_DEGENERATE = "degenerate"
REASON_DISTANCE = "distance"
REASON_UNCERTAINTY = "uncertainty"

#: Reason of a measurement left out of the GP fits as inside a window of distance rejections.
REASON_DISTANCE_WINDOW = MODULE4_REASONS[0]
#: Most GP fits that leave out the windows of distance rejections.
MAX_OUTLIER_REFITS = 3


def position_uncertainty(cov: ArrayLike, measure: str = "max_std") -> np.ndarray:
    """Scalar position uncertainty (T,), m, of pose (T, 6, 6; x, y, z, rx, ry, rz) or position
    (T, 3, 3) covariances, m^2: ``sqrt(lambda_max)``, ``sqrt(trace)`` or ``sqrt(Frobenius norm)``
    of the position block by ``measure``; NaN where the covariance is not finite."""
    c = np.asarray(cov, dtype=float)
    if c.ndim < 2 or c.shape[-2:] not in ((6, 6), (3, 3)):
        raise ValueError(f"Expected covariances of shape (..., 6, 6) or (..., 3, 3), got {c.shape}")
    if measure not in UNCERTAINTY_MEASURES:
        raise ValueError(f"Expected measure in {UNCERTAINTY_MEASURES}, got {measure!r}")
    p = c[..., :3, :3]
    finite = np.all(np.isfinite(p), axis=(-1, -2))
    p = np.where(finite[..., None, None], p, 0.0)
    if measure == "max_std":
        val = np.sqrt(np.clip(np.linalg.eigvalsh(p)[..., -1], 0.0, None))
    elif measure == "sqrt_trace":
        val = np.sqrt(np.clip(np.trace(p, axis1=-2, axis2=-1), 0.0, None))
    else:
        val = np.sqrt(np.linalg.norm(p, axis=(-2, -1)))
    return np.where(finite, val, np.nan)


@dataclass(frozen=True)
class GateReport:
    """Outcome of the module 4 gates, per pose (T,): ``keep``, ``reason`` (``""`` or the first
    failing gate: ``"degenerate"``, ``"distance"``, ``"uncertainty"``), ``distance_error``
    (``max_ij |d_ij - d_ij(reference)|``, m, NaN where degenerate) and ``uncertainty`` (m);
    ``counts`` (``total``, ``kept``, ``rejected`` and the poses failing each gate; a pose can
    fail both distance and uncertainty), ``rejected_by`` (by first failing gate) and the gates."""

    keep: np.ndarray
    reason: np.ndarray
    distance_error: np.ndarray
    uncertainty: np.ndarray
    counts: dict[str, int]
    rejected_by: dict[str, int]
    distance_gate_m: float
    uncertainty_gate_m: float
    uncertainty_measure: str

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (parameters, counts, medians), for ``summary.json``."""
        def med(x):
            x = x[np.isfinite(x)]
            return None if x.size == 0 else float(np.median(x))

        return {
            "distance_gate_m": self.distance_gate_m,
            "uncertainty_gate_m": self.uncertainty_gate_m,
            "uncertainty_measure": self.uncertainty_measure,
            "counts": dict(self.counts),
            "rejected_by": dict(self.rejected_by),
            "median_distance_error_m": med(self.distance_error),
            "median_uncertainty_m": med(self.uncertainty),
        }


def quality_gates(
    inter_prism_distance: ArrayLike,
    cov: ArrayLike,
    reference_distances: ArrayLike,
    *,
    degenerate: ArrayLike | None = None,
    distance_gate_m: float = DEFAULT_DISTANCE_GATE_M,
    uncertainty_gate_m: float = DEFAULT_UNCERTAINTY_GATE_M,
    uncertainty_measure: str = "max_std",
) -> GateReport:
    """The module 4 gates on ``inter_prism_distance`` (T, P), m, pose or position covariances
    ``cov`` (T, 6, 6) or (T, 3, 3), m^2, and the reference's ``reference_distances`` (P,), m.
    ``degenerate`` (T,) bool: poses known to be degenerate (by default those with a non-finite
    distance or covariance). Returns the :class:`GateReport`."""
    d = np.asarray(inter_prism_distance, dtype=float)
    ref = np.asarray(reference_distances, dtype=float)
    if d.ndim != 2:
        raise ValueError(f"Expected inter_prism_distance of shape (T, P), got {d.shape}")
    T, P = d.shape
    if ref.shape != (P,):
        raise ValueError(f"Expected reference_distances of shape ({P},), got {ref.shape}")
    c = np.asarray(cov, dtype=float)
    if c.shape[:1] != (T,):
        raise ValueError(f"Expected {T} covariances, got shape {c.shape}")
    gates = (("distance_gate_m", distance_gate_m), ("uncertainty_gate_m", uncertainty_gate_m))
    for name, g in gates:
        if not g > 0:
            raise ValueError(f"Expected a positive {name}, got {g!r}")
    unc = position_uncertainty(c, uncertainty_measure)
    err = np.max(np.abs(d - ref), axis=1) if P else np.zeros(T)
    if degenerate is None:
        degen = ~np.isfinite(err) | ~np.isfinite(unc)
    else:
        degen = np.asarray(degenerate, dtype=bool)
        if degen.shape != (T,):
            raise ValueError(f"Expected degenerate of shape ({T},), got {degen.shape}")
        degen = degen | ~np.isfinite(err) | ~np.isfinite(unc)
    with np.errstate(invalid="ignore"):
        fail_d = ~degen & ~(err <= distance_gate_m)
        fail_u = ~degen & ~(unc <= uncertainty_gate_m)
    keep = ~degen & ~fail_d & ~fail_u
    reason = np.full(T, REASON_KEPT, dtype="<U12")
    reason[fail_u] = REASON_UNCERTAINTY
    reason[fail_d] = REASON_DISTANCE
    reason[degen] = REASON_DEGENERATE
    err = np.where(degen, np.nan, err)
    counts = {
        "total": int(T),
        "kept": int(keep.sum()),
        "rejected": int(T - keep.sum()),
        REASON_DEGENERATE: int(degen.sum()),
        REASON_DISTANCE: int(fail_d.sum()),
        REASON_UNCERTAINTY: int(fail_u.sum()),
    }
    rejected_by = {
        r: int(np.sum(reason == r))
        for r in (REASON_DEGENERATE, REASON_DISTANCE, REASON_UNCERTAINTY)
    }
    return GateReport(keep, reason, err, unc, counts, rejected_by, float(distance_gate_m),
                      float(uncertainty_gate_m), uncertainty_measure)


def _reference_distances(estimate: Any, reference: Any) -> np.ndarray:
    """The reference distances of ``estimate.pairs`` (see :func:`apply_gates`)."""
    x = np.asarray(getattr(reference, "xyz", reference), dtype=float)
    pairs = tuple(estimate.pairs)
    if x.ndim == 2 and x.shape[1] == 3:
        return np.array([np.linalg.norm(x[i] - x[j]) for i, j in pairs])
    if x.ndim == 1 and x.shape[0] == len(pairs):
        return x
    raise ValueError(
        f"Expected reference points (n, 3) or {len(pairs)} distances, got shape {x.shape}"
    )


def apply_gates(
    estimate: Any,
    reference: Any,
    *,
    distance_gate_m: float = DEFAULT_DISTANCE_GATE_M,
    uncertainty_gate_m: float = DEFAULT_UNCERTAINTY_GATE_M,
    uncertainty_measure: str = "max_std",
) -> tuple[np.ndarray, GateReport]:
    """:func:`quality_gates` on a :class:`rtsgt.pose.PoseEstimate` (``inter_prism_distance``,
    ``pairs``, ``cov``, ``degenerate``) against ``reference`` (ReferencePoints, (n, 3) points in
    the estimate's prism order, or the (P,) distances of ``estimate.pairs``): ``(keep, report)``."""
    report = quality_gates(
        estimate.inter_prism_distance, estimate.cov, _reference_distances(estimate, reference),
        degenerate=estimate.degenerate,
        distance_gate_m=distance_gate_m, uncertainty_gate_m=uncertainty_gate_m,
        uncertainty_measure=uncertainty_measure,
    )
    return report.keep, report


class PrismDistances(NamedTuple):
    """The inter-prism distances of prisms at a series of times, as a
    :class:`~rtsgt.pose.PoseEstimate` has them (what :func:`distance_outliers` reads)."""

    #: ``|q_i - q_j|`` per time and pair, m, shape (T, P) (NaN where a prism is missing).
    inter_prism_distance: np.ndarray
    #: The pairs ``(i, j)``, ``i < j``, in the order of the columns.
    pairs: tuple[tuple[int, int], ...]


def prism_distances(xyz: ArrayLike) -> PrismDistances:
    """The inter-prism distances of prisms (T, n, 3), m, without estimating a pose: the very
    numbers :func:`rtsgt.pose.estimate_poses` computes (the same pairs, the same operations),
    so :func:`distance_outliers` flags the same poses from either."""
    q = np.asarray(xyz, dtype=float)
    if q.ndim != 3 or q.shape[2] != 3:
        raise ValueError(f"Expected prism positions of shape (T, n, 3), got {q.shape}")
    n = q.shape[1]
    pairs = tuple((i, j) for i in range(n) for j in range(i + 1, n))
    ii = np.array([a for a, _ in pairs], dtype=int)
    jj = np.array([b for _, b in pairs], dtype=int)
    return PrismDistances(np.linalg.norm(q[:, ii] - q[:, jj], axis=-1), pairs)


def distance_outliers(
    estimate: Any, reference: Any, distance_gate_m: float = DEFAULT_DISTANCE_GATE_M
) -> np.ndarray:
    """Poses (T,) bool whose distances are all finite and one disagrees with ``reference`` (as for
    :func:`apply_gates`) by more than ``distance_gate_m``, m; a degenerate pose counts (a station
    on another prism makes two prisms coincide). ``estimate``: a PoseEstimate or
    :class:`PrismDistances`."""
    d = np.asarray(estimate.inter_prism_distance, dtype=float)
    err = np.abs(d - _reference_distances(estimate, reference))
    with np.errstate(invalid="ignore"):  # a row with a NaN is not flagged
        return np.all(np.isfinite(err), axis=1) & (np.max(err, axis=1, initial=0.0)
                                                   > distance_gate_m)


def outlier_windows(t: ArrayLike, flagged: ArrayLike, step: float | None = None) -> np.ndarray:
    """Disjoint sorted open windows (K, 2), s, of the ``flagged`` (T,) query times ``t`` (T,):
    each ``t_i`` padded towards its neighbours by at most ``step`` (default: the median of
    ``diff(t)``) on each side, overlapping or touching windows merged."""
    t = np.asarray(t, dtype=float)
    flag = np.asarray(flagged, dtype=bool)
    if t.ndim != 1 or flag.shape != t.shape:
        raise ValueError(f"Expected t and flagged of one shape (T,), got {t.shape}, {flag.shape}")
    if not flag.any():
        return np.zeros((0, 2))
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError("Expected increasing query times")
    if step is None:
        step = float(np.median(dt)) if dt.size else 0.0
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"Expected a sampling interval > 0 s, got {step!r}")
    gap = np.minimum(np.concatenate([[np.inf], dt, [np.inf]]), step)
    idx = np.flatnonzero(flag)
    lo, hi = t[idx] - gap[idx], t[idx] + gap[idx + 1]  # both increasing
    first = np.concatenate([[True], lo[1:] > hi[:-1]])  # touching intervals merge
    starts = np.flatnonzero(first)
    ends = np.append(starts[1:], idx.size) - 1
    return np.stack([lo[starts], hi[ends]], axis=1)


def in_windows(t: ArrayLike, windows: ArrayLike) -> np.ndarray:
    """Whether each time lies strictly inside one of the windows of :func:`outlier_windows`."""
    t = np.asarray(t, dtype=float)
    w = np.asarray(windows, dtype=float).reshape(-1, 2)
    if w.shape[0] == 0:
        return np.zeros(t.shape, dtype=bool)
    k = np.searchsorted(w[:, 0], t, side="right") - 1
    kk = np.clip(k, 0, None)
    return (k >= 0) & (t > w[kk, 0]) & (t < w[kk, 1])


@dataclass(frozen=True)
class OutlierWindowReport(FilterReport):
    """What leaving the windows of distance rejections out of the GP fits removed: the counts of
    :class:`~rtsgt.filtering.modules.FilterReport` (``module = "module4"``, one series per prism,
    ``n_blocks`` the windows), the ``windows`` (K, 2), s, the number of ``fits`` without them,
    whether the last flagged nothing new (``converged``), ``poses_flagged`` (inside the windows)
    and ``poses_dropped`` (outside them, across a gap the new GPs do not bridge)."""

    windows: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False,
                                compare=False)
    fits: int = 0
    converged: bool = True
    poses_flagged: int = 0
    poses_dropped: int = 0

    def as_dict(self) -> dict[str, Any]:
        """The counts, the windows (s) and the fits, for ``summary.json`` ``filters``."""
        return {**super().as_dict(), "windows_s": self.windows.tolist(), "fits": self.fits,
                "converged": self.converged, "poses_flagged": self.poses_flagged,
                "poses_dropped": self.poses_dropped}


#: Median deviation of a tracked inter-prism distance from the surveyed one, in predicted
#: sigmas, above which a run warns.
SURVEY_DISTANCE_WARNING_SIGMA = 3.0


def pair_distance_variance(u: np.ndarray, cov: np.ndarray, i: int, j: int) -> np.ndarray:
    """``u^T (C_ii + C_jj - C_ij - C_ji) u`` for (..., 3) unit vectors and (..., 3n, 3n)."""
    a, b = slice(3 * i, 3 * i + 3), slice(3 * j, 3 * j + 3)
    S = cov[..., a, a] + cov[..., b, b] - cov[..., a, b] - np.swapaxes(cov[..., a, b], -1, -2)
    return np.einsum("...i,...ij,...j->...", u, S, u)


def pair_distance_terms(
    q: np.ndarray, cov: np.ndarray, r: np.ndarray, reference_cov: np.ndarray, i: int, j: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """For prisms ``i``, ``j`` of ``q`` (T, n, 3), m, with joint covariance ``cov`` (T, 3n, 3n) and
    the survey ``r`` (n, 3) with ``reference_cov`` (3n, 3n): the tracked distances ``d`` (T,),
    unit vectors ``u`` (T, 3) from ``q_j`` to ``q_i``, ``var_t`` (T,), and the surveyed distance
    and its variance (m, m^2)."""
    diff = q[:, i] - q[:, j]
    d = np.linalg.norm(diff, axis=-1)
    u = diff / d[:, None]
    dr = r[i] - r[j]
    d_ref = float(np.linalg.norm(dr))
    return (d, u, pair_distance_variance(u, cov, i, j), d_ref,
            float(pair_distance_variance(dr / d_ref, reference_cov, i, j)))


def surveyed_distance_check(
    xyz: ArrayLike, cov: ArrayLike, reference_xyz: ArrayLike, reference_cov: ArrayLike,
    names: Sequence[str], *, threshold_sigma: float = SURVEY_DISTANCE_WARNING_SIGMA,
    warn: bool = True,
) -> dict[str, dict[str, Any]]:
    """The tracked inter-prism distances of the kept poses against the surveyed ones, per pair
    ``"i-j"`` (docs/filtering.md#surveyed-distances-against-the-tracking). Takes ``xyz`` (T, n,
    3), m, their joint ``cov`` (T, 3n, 3n) or per-prism blocks (T, n, 3, 3), the survey
    ``reference_xyz`` (n, 3) and ``reference_cov`` (3n, 3n), and the prism ``names``. Returns,
    JSON-ready per pair, ``surveyed_m``, ``median_tracked_m``, ``median_deviation_mm``,
    ``predicted_sigma_mm``, ``tracking_sigma_mm``, ``survey_sigma_mm``, the signed ``ratio`` and
    ``poses`` (empty without poses); warns per pair above ``threshold_sigma``."""
    q = np.asarray(xyz, dtype=float)
    c = np.asarray(cov, dtype=float)
    r = np.asarray(reference_xyz, dtype=float)
    rc = np.asarray(reference_cov, dtype=float)
    T, n = q.shape[0], r.shape[0]
    if q.ndim != 3 or q.shape[1:] != (n, 3) or len(names) != n:
        raise ValueError(f"Expected xyz of shape (T, {n}, 3) and {n} names, got {q.shape}")
    if c.shape == (T, n, 3, 3):
        c = block_diagonal(c)
    if c.shape != (T, 3 * n, 3 * n) or rc.shape != (3 * n, 3 * n):
        raise ValueError(f"Expected cov (T, {3 * n}, {3 * n}) and reference_cov "
                         f"({3 * n}, {3 * n}), got {c.shape} and {rc.shape}")
    out: dict[str, dict[str, Any]] = {}
    if T == 0:
        return out
    for i in range(n):
        for j in range(i + 1, n):
            d, _, var_t, d_ref, var_r = pair_distance_terms(q, c, r, rc, i, j)
            sigma = float(np.sqrt(max(float(np.median(var_t)) + var_r, 0.0)))
            dev = float(np.median(d - d_ref))
            ratio = dev / sigma if sigma > 0 else (0.0 if dev == 0 else np.copysign(np.inf, dev))
            key = f"{names[i]}-{names[j]}"
            out[key] = {
                "surveyed_m": d_ref, "median_tracked_m": float(np.median(d)),
                "median_deviation_mm": dev * 1e3, "predicted_sigma_mm": sigma * 1e3,
                "tracking_sigma_mm": float(np.sqrt(max(np.median(var_t), 0.0))) * 1e3,
                "survey_sigma_mm": float(np.sqrt(max(var_r, 0.0))) * 1e3,
                "ratio": float(ratio), "poses": int(T),
            }
            if warn and abs(ratio) > threshold_sigma:
                warnings.warn(
                    f"prisms {key}: the surveyed distance {d_ref:.4f} m disagrees with the "
                    f"tracking: median tracked distance {np.median(d):.4f} m over {T} kept "
                    f"poses, {dev * 1e3:+.1f} mm = {ratio:+.1f} predicted sigma "
                    f"({sigma * 1e3:.1f} mm; threshold {threshold_sigma:g}): was prism "
                    f"{names[i]} or {names[j]} moved after the survey, or mis-surveyed? Every "
                    "pose is biased by it; check the survey of the reference prisms",
                    RtsgtWarning, stacklevel=2,
                )
    return out
