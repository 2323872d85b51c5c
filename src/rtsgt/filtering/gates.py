r"""Module 4 quality gates on poses (Vaidis et al. 2022; docs/filtering.md).

A pose is kept when

1. it is not degenerate (every prism present, prisms not collinear: see
   :class:`rtsgt.pose.PoseEstimate`);
2. **distance gate**: every inter-prism distance of the world prisms agrees with the same
   distance of the reference prisms within ``distance_gate_m`` (default 0.10 m, the paper's):
   ``max_ij | |q_i - q_j| - |r_i - r_j| | <= distance_gate_m``;
3. **uncertainty gate**: the pose's position uncertainty is at most ``uncertainty_gate_m``
   (default 0.20 m, the paper's value). The paper does not say what the 20 cm bound applies
   to; rtsgt applies it by default to the standard deviation along the worst direction of the
   position covariance, ``sqrt(lambda_max(cov[:3, :3]))`` (1 sigma, m), which bounds the
   standard deviation of every position component and of any horizontal or vertical
   projection. Other measures: ``"sqrt_trace"`` (``sqrt(tr cov[:3, :3])``, the RMS of the
   position error) and ``"sqrt_frobenius"`` (``sqrt(||cov[:3, :3]||_F)``, the measure of the
   paper's per-source figures).

Every rejected pose is counted: :attr:`GateReport.counts` says how many poses fail each gate
(a pose may fail both the distance and the uncertainty gate), :attr:`GateReport.rejected_by`
assigns each rejected pose to the first gate it fails, in the order above.

Surveyed distances against the tracking
---------------------------------------
The distance gate catches gross errors of single poses (10 cm). A surveyed distance that is
wrong by a few cm (a prism moved after the survey, a mis-pointed shot) passes it at every
pose, and biases every pose. :func:`surveyed_distance_check` compares, per prism pair, the
tracked distances ``|q_i - q_j|`` of the kept poses with the surveyed one, against the
predicted standard deviation of the difference, first order: with ``u`` the unit vector from
``q_j`` to ``q_i``, ``var = u^T (C_ii + C_jj - C_ij - C_ji) u`` from the joint covariance of
the two prisms at that time (the shared calibration errors included), plus the same for the
survey (``u_r`` from ``r_j`` to ``r_i`` through the reference covariance).

The statistic is the **median deviation over the run** (robust to a few bad poses) divided by
``sigma = sqrt(median_t var_t + var_survey)``: the standard deviation of the median of errors
that are *fully* correlated over the run. The errors are strongly correlated in time (the
calibration, the atmosphere, a clock offset are one draw for the run; the GP smooths the
rest), so the median does not average them down by ``sqrt(T)``; taking them as fully
correlated can only overstate sigma, so the ratio is a lower bound of the disagreement in
sigmas, and a warning is not an artefact of the time correlation. A ratio above
:data:`SURVEY_DISTANCE_WARNING_SIGMA` (3, the usual three-sigma rule; about 0.3 % of
consistent pairs for Gaussian errors, fewer here as sigma is overstated) is warned about.
The price of that safety: the part of the error that does average out over the run (the GP's,
from the instrument noise) is counted in full, so a disagreement is flagged from three
per-time sigmas of the distance on (on the real excerpt, 3-4.5 mm per pair: about 1 cm).

Measurements inside the windows of distance rejections
------------------------------------------------------
A pose whose inter-prism distances disagree with the survey by more than the distance gate
(10 cm, a hundred times the noise) was built from a wrong measurement: a station tracking
another prism, a reflection. The gate rejects the pose, but the measurement stays in the GP of
its prism, where it inflates the Qc that leave-one-out finds (a jump of a metre is a huge
acceleration) and bends the track next to the window. So the pipeline
(:func:`rtsgt.pipeline.run_pipeline`, ``[interpolation] outlier_windows = "remove"``) leaves the
measurements of those windows out of the GP fits and fits again:

- :func:`distance_outliers`: the poses whose finite inter-prism distances disagree with the
  survey beyond the gate, whatever the gate's reason (a station locked on another prism of the
  robot makes two prisms coincide: such a pose is rejected as ``"collinear"`` before the
  distance gate, and is as wrong).
- :func:`outlier_windows`: each flagged query time ``t_i`` stands for the open interval
  ``(t_i - a_i, t_i + b_i)``, padded on each side up to the neighbouring query time but by at
  most one sampling interval of the queries (their median spacing). A wrong measurement at a
  time ``t_m`` gives a wrong pose at ``t_m`` (the GP follows measurements of millimetre noise),
  so a flagged run of poses contains every wrong measurement up to the neighbouring query
  times, which passed the gate; the padding reaches, but not includes, them. The intervals
  are merged.
- Every prism's measurements inside a window are left out (:func:`in_windows`): the gate says
  the geometry is wrong, not which station was; the poses inside are rejected anyway, so the
  other prisms lose nothing but a few seconds of their Qc fit.

The refit is gated again; a pose flagged now (a wrong measurement the first fit hid) adds its
window, up to :data:`MAX_OUTLIER_REFITS` fits after the first. The poses of a window stay
rejected, with the values and the reason of the fit that flagged them. A pose outside the windows that the new
GPs cannot vouch for (the window left a gap longer than ``max_gap_s``) is dropped, as every
query across such a gap is. :class:`OutlierWindowReport` counts what was removed (stage
``"module4"``, reason ``"distance_window"`` in the run's removed measurements).
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
#: Most GP fits that leave out the windows of distance rejections (module docstring).
MAX_OUTLIER_REFITS = 3


def position_uncertainty(cov: ArrayLike, measure: str = "max_std") -> np.ndarray:
    """Scalar position uncertainty (m) of pose or position covariances.

    Parameters
    ----------
    cov : array_like, shape (T, 6, 6) or (T, 3, 3)
        Pose covariance ordered (x, y, z, rx, ry, rz) (its position block is used) or position
        covariance, m^2.
    measure : {"max_std", "sqrt_trace", "sqrt_frobenius"}
        ``sqrt(lambda_max)``, ``sqrt(trace)`` or ``sqrt(Frobenius norm)`` of the 3x3 block.

    Returns
    -------
    ndarray, shape (T,)
        NaN where the covariance is not finite.
    """
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
    """Outcome of the module 4 gates.

    Attributes
    ----------
    keep : ndarray of bool, shape (T,)
    reason : ndarray of str, shape (T,)
        ``""`` for a kept pose, else the first gate it fails: ``"degenerate"``,
        ``"distance"``, ``"uncertainty"``.
    distance_error : ndarray, shape (T,)
        ``max_ij | d_ij - d_ij(reference) |``, m (NaN for a degenerate pose).
    uncertainty : ndarray, shape (T,)
        :func:`position_uncertainty` of each pose, m.
    counts : dict str -> int
        ``total``, ``kept``, ``rejected``, and per gate the number of poses failing it:
        ``degenerate``, ``distance``, ``uncertainty`` (non-degenerate poses only; a pose can
        fail both of the last two).
    rejected_by : dict str -> int
        Rejected poses by their first failing gate (sums to ``counts["rejected"]``).
    distance_gate_m, uncertainty_gate_m : float
    uncertainty_measure : str
    """

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
    """Apply the module 4 gates to arrays.

    Parameters
    ----------
    inter_prism_distance : array_like, shape (T, P)
        Distances between the world prisms at each pose, m.
    cov : array_like, shape (T, 6, 6) or (T, 3, 3)
        Pose (or position) covariances, m^2.
    reference_distances : array_like, shape (P,)
        The same distances between the reference prisms, m.
    degenerate : array_like of bool, shape (T,), optional
        Poses already known to be degenerate; by default, poses with a non-finite distance or
        covariance.
    distance_gate_m, uncertainty_gate_m : float
        Gates, m (module docstring).
    uncertainty_measure : str
        See :func:`position_uncertainty`.

    Returns
    -------
    GateReport
    """
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
    """Apply the module 4 gates to a :class:`rtsgt.pose.PoseEstimate`.

    Parameters
    ----------
    estimate : PoseEstimate
        Uses ``inter_prism_distance``, ``pairs``, ``cov`` and ``degenerate``.
    reference : ReferencePoints, array_like (n, 3) or array_like (P,)
        The reference prisms (same order as the estimate's prisms), or directly their
        distances for ``estimate.pairs``.
    distance_gate_m, uncertainty_gate_m, uncertainty_measure
        See :func:`quality_gates`.

    Returns
    -------
    keep : ndarray of bool, shape (T,)
    report : GateReport
    """
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
    """Poses whose inter-prism distances disagree with the reference beyond the gate.

    Unlike the distance gate, a degenerate pose counts when its distances are finite: a
    station tracking another prism of the robot makes two prisms coincide, and the pose is
    rejected as collinear before the distance gate is tried (module docstring).

    Parameters
    ----------
    estimate : PoseEstimate or PrismDistances
        Uses ``inter_prism_distance`` and ``pairs`` (:func:`prism_distances`: no pose needed).
    reference : ReferencePoints, array_like (n, 3) or array_like (P,)
        As for :func:`apply_gates`.
    distance_gate_m : float
        The distance gate, m.

    Returns
    -------
    ndarray of bool, shape (T,)
        True where every distance is finite and one disagrees by more than the gate.
    """
    d = np.asarray(estimate.inter_prism_distance, dtype=float)
    err = np.abs(d - _reference_distances(estimate, reference))
    with np.errstate(invalid="ignore"):  # a row with a NaN is not flagged
        return np.all(np.isfinite(err), axis=1) & (np.max(err, axis=1, initial=0.0)
                                                   > distance_gate_m)


def outlier_windows(t: ArrayLike, flagged: ArrayLike, step: float | None = None) -> np.ndarray:
    """The open time windows of flagged poses, padded towards their neighbours.

    Parameters
    ----------
    t : array_like, shape (T,)
        Query times, s, increasing.
    flagged : array_like of bool, shape (T,)
        The poses whose measurements are outliers (:func:`distance_outliers`).
    step : float, optional
        Largest padding on each side, s: by default the sampling interval of the queries, the
        median of ``diff(t)``.

    Returns
    -------
    ndarray, shape (K, 2)
        Disjoint open intervals ``(start, end)``, s, sorted: each flagged ``t_i`` padded by
        ``min(t_i - t_i-1, step)`` before and ``min(t_i+1 - t_i, step)`` after (``step`` at
        either end), overlapping or touching ones merged.
    """
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
    """What leaving the windows of distance rejections out of the GP fits removed.

    The counts of :class:`~rtsgt.filtering.modules.FilterReport` (``module = "module4"``, one
    series per prism, reason :data:`REASON_DISTANCE_WINDOW`, ``n_blocks`` the windows), and:

    Attributes
    ----------
    windows : ndarray, shape (K, 2)
        The windows, open intervals of time, s.
    fits : int
        GP fits without the windows (at most :data:`MAX_OUTLIER_REFITS`).
    converged : bool
        Whether the last fit flagged no new pose.
    poses_flagged : int
        Poses inside the windows (rejected).
    poses_dropped : int
        Poses outside the windows dropped because the new GPs cannot answer them (a window
        left a gap longer than ``max_gap_s``).
    """

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
#: sigmas, above which a run warns (module docstring).
SURVEY_DISTANCE_WARNING_SIGMA = 3.0


def pair_distance_variance(u: np.ndarray, cov: np.ndarray, i: int, j: int) -> np.ndarray:
    """``u^T (C_ii + C_jj - C_ij - C_ji) u`` for (..., 3) unit vectors and (..., 3n, 3n)."""
    a, b = slice(3 * i, 3 * i + 3), slice(3 * j, 3 * j + 3)
    S = cov[..., a, a] + cov[..., b, b] - cov[..., a, b] - np.swapaxes(cov[..., a, b], -1, -2)
    return np.einsum("...i,...ij,...j->...", u, S, u)


def pair_distance_terms(
    q: np.ndarray, cov: np.ndarray, r: np.ndarray, reference_cov: np.ndarray, i: int, j: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """The tracked and surveyed distances of prisms ``i`` and ``j`` and their variances.

    Parameters
    ----------
    q : ndarray, shape (T, n, 3)
        World prism positions, m.
    cov : ndarray, shape (T, 3n, 3n)
        Their joint covariance, m^2.
    r : ndarray, shape (n, 3)
        Surveyed prisms (body frame), m.
    reference_cov : ndarray, shape (3n, 3n)
        Their covariance, m^2.

    Returns
    -------
    d : ndarray, shape (T,)
        Tracked distances ``|q_i - q_j|``, m.
    u : ndarray, shape (T, 3)
        Unit vectors from ``q_j`` to ``q_i``.
    var_t : ndarray, shape (T,)
        Variance of ``d`` (:func:`pair_distance_variance`), m^2.
    d_ref, var_r : float
        The surveyed distance and its variance, m and m^2.
    """
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
    """Compare the tracked inter-prism distances with the surveyed ones (module docstring).

    Parameters
    ----------
    xyz : array_like, shape (T, n, 3)
        World prism positions at the kept poses, m.
    cov : array_like, shape (T, 3n, 3n) or (T, n, 3, 3)
        Their joint covariance, or the per-prism blocks (prisms then independent), m^2.
    reference_xyz : array_like, shape (n, 3)
        Surveyed prisms (body frame), same order, m.
    reference_cov : array_like, shape (3n, 3n)
        Their covariance, m^2.
    names : sequence of str, length n
        Prism identifiers (for the keys and messages).
    threshold_sigma : float
        Ratio above which to warn.
    warn : bool
        Emit one :class:`~rtsgt.errors.RtsgtWarning` per pair above the threshold.

    Returns
    -------
    dict ``"i-j"`` -> dict
        JSON-ready, per pair: ``surveyed_m``, ``median_tracked_m``, ``median_deviation_mm``
        (tracked minus surveyed), ``predicted_sigma_mm`` (the total), ``tracking_sigma_mm``,
        ``survey_sigma_mm``, ``ratio`` (median deviation / predicted sigma, signed) and
        ``poses``. Empty without poses.
    """
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
