"""Drift by segment length: KITTI's translational and rotational errors (Geiger et al. 2012) over
segments of ground-truth path and of time, beside the ground truth's own drift (its floor).
Definitions: docs/evaluating.md#drift-by-segment-length.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.evaluation.metrics import relative_poses

__all__ = ["POSITION_DRIFT_DEFINITION", "ROTATION_DRIFT_NOT_ESTIMABLE", "Drift", "SegmentDrift", "drift_metrics", "distance_lengths", "kitti_errors",
           "path_distances", "segments"]

#: The KITTI odometry benchmark's segment lengths, m.
KITTI_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
#: The devkit's step between first frames of segments, frames.
KITTI_STEP_FRAMES = 10
#: A path at least this many times the shortest KITTI length gets KITTI's lengths; a shorter
#: one gets them scaled (:func:`distance_lengths`).
PATH_PER_SHORTEST = 10.0
#: Time segments of the per-second drift, s.
TIME_LENGTHS_S = (1.0, 10.0, 60.0)
#: Segments per length whose ground-truth floor is computed (evenly spaced; the floor is an
#: rms over them).
FLOOR_SEGMENTS = 50

#: Why a position-only ground truth reports no rotational drift.
ROTATION_DRIFT_NOT_ESTIMABLE = (
    "not estimable: a position-only ground truth has no orientation to compare the "
    "estimate's relative rotations with (the estimate's rotation enters the translational "
    "drift only through the lever arm)")
#: The translational drift of a position-only ground truth.
POSITION_DRIFT_DEFINITION = (
    "|(y_est,l - y_est,f) - (y_gt,l - y_gt,f)| / L of the compared points (the estimate's "
    "p + R l) in the world frame after the alignment, averaged over the devkit's segments: "
    "the devkit's translation error with both relative positions in one frame (the devkit "
    "takes each in its own pose's frame at f, so that a heading error at f adds L times its "
    "angle; without the ground truth's orientation that part is not measured)")

#: errors(first, last) -> (translation error (K,) m, rotation angle (K,) rad or None).
ErrorsFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray | None]]
#: covariance(first, last) -> the ground truth's relative pose (K, 6, 6) or position (K, 3, 3)
#: covariance over the segments, translation first.
CovarianceFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def path_distances(position: ArrayLike) -> np.ndarray:
    """Cumulative path length from the first position, m, shape (N,) (the devkit's
    ``trajectoryDistances``)."""
    p = np.asarray(position, dtype=float)
    if p.shape[0] == 0:
        return np.zeros(0)
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def distance_lengths(path_m: float) -> tuple[np.ndarray, str]:
    """Segment lengths (m) for a ground-truth path of ``path_m`` metres, and where they come
    from: KITTI's 100-800 m for a path of at least :data:`PATH_PER_SHORTEST` x 100 m; else
    ``k s`` for k = 1..8, ``s`` the largest 1-2-5 step at most a tenth of the path (empty for
    a path of zero)."""
    if not np.isfinite(path_m) or path_m <= 0:
        return np.zeros(0), "none: the ground truth does not move"
    if path_m >= PATH_PER_SHORTEST * KITTI_LENGTHS_M[0]:
        return np.asarray(KITTI_LENGTHS_M), "KITTI"
    top = path_m / PATH_PER_SHORTEST
    dec = 10.0 ** np.floor(np.log10(top))
    step = max(m * dec for m in (1.0, 2.0, 5.0) if m * dec <= top)
    lengths = step * np.arange(1, len(KITTI_LENGTHS_M) + 1)
    return lengths, (f"scaled to the path ({path_m:.4g} m): {len(KITTI_LENGTHS_M)} steps of "
                     f"{step:g} m, the largest 1-2-5 step at most a tenth of the path")


@dataclass(frozen=True)
class Segments:
    """Segments (the devkit's): ``first``, ``last`` (K,) pose indices, ``which`` (K,) index into
    ``lengths`` (B,) (m of path, or s).
    """

    first: np.ndarray
    last: np.ndarray
    which: np.ndarray
    lengths: np.ndarray


def segments(along: ArrayLike, lengths: ArrayLike, step: int = KITTI_STEP_FRAMES) -> Segments:
    """The devkit's :class:`Segments`: for first frames ``0, step, 2 step, ...`` and each length ``L``
    of ``lengths`` (B,), the first frame with ``along[last] > along[first] + L``; ``along`` (N,)
    non-decreasing path length (m) or time (s).
    """
    a = np.asarray(along, dtype=float)
    L = np.asarray(lengths, dtype=float).reshape(-1)
    first = np.arange(0, a.size, int(step))
    parts = [(first, np.searchsorted(a, a[first] + length, side="right"), b)
             for b, length in enumerate(L)]
    f = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, int)
    last = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0, int)
    which = np.concatenate([np.full(p[0].size, p[2]) for p in parts]) if parts else f
    keep = last < a.size
    return Segments(f[keep], last[keep], which[keep].astype(int), L)


def kitti_errors(
    R_gt: ArrayLike, t_gt: ArrayLike, R_est: ArrayLike, t_est: ArrayLike,
    first: np.ndarray, last: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The devkit's segment errors: ``E = (Q_f^-1 Q_l)^-1 (P_f^-1 P_l)``, its translation's
    norm (m) and its rotation angle ``acos(clip((tr R_E - 1) / 2, -1, 1))`` (rad), shape (K,).

    ``R_*`` (N, 3, 3) and ``t_*`` (N, 3): ground-truth poses ``Q`` and estimate poses ``P``.
    """
    pairs = np.column_stack([first, last])
    RQ, tQ = relative_poses(np.asarray(R_gt, float), np.asarray(t_gt, float), pairs)
    RP, tP = relative_poses(np.asarray(R_est, float), np.asarray(t_est, float), pairs)
    RQT = np.swapaxes(RQ, -1, -2)
    R_E = RQT @ RP
    t_E = np.einsum("kab,kb->ka", RQT, tP - tQ)
    c = 0.5 * (np.trace(R_E, axis1=-2, axis2=-1) - 1.0)
    return np.linalg.norm(t_E, axis=-1), np.arccos(np.clip(c, -1.0, 1.0))


def _mean_by(which: np.ndarray, values: np.ndarray, n_bins: int) -> np.ndarray:
    """Mean of ``values`` per bin (NaN for an empty bin)."""
    n = np.bincount(which, minlength=n_bins)
    s = np.bincount(which, weights=values, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, s / np.maximum(n, 1), np.nan)


def floor_sample(which: np.ndarray, n_bins: int, per_bin: int = FLOOR_SEGMENTS) -> np.ndarray:
    """Indices of at most ``per_bin`` segments of each bin, evenly spaced among its own."""
    order = np.argsort(which, kind="stable")
    n = np.bincount(which, minlength=n_bins)
    start = np.concatenate([[0], np.cumsum(n)[:-1]])
    take = np.minimum(n, per_bin)
    rank = np.concatenate([np.floor(np.arange(k) * (m / k)).astype(int) if k else
                           np.zeros(0, int) for k, m in zip(take, n, strict=True)])
    base = np.repeat(start, take)
    return order[base + rank]


@dataclass(frozen=True)
class SegmentDrift:
    """Drift over segments of one ``kind`` ("distance", m of ground-truth path, or "time", s).

    Per length (B,) and pooled (``*_all``, KITTI's average): the mean of ``error / L``, translation
    in m per unit, rotation in rad per unit (None: not estimable), and the ground truth's floors
    ``sqrt(mean tr Sigma_rel / L^2)`` (None without covariances); ``n`` (B,), ``lengths_from``,
    ``segments`` and the per-segment ``translation_error``, ``rotation_error`` (K,).
    """

    kind: str
    lengths: np.ndarray
    lengths_from: str
    n: np.ndarray
    translation: np.ndarray
    rotation: np.ndarray | None
    translation_floor: np.ndarray | None
    rotation_floor: np.ndarray | None
    translation_all: float | None
    rotation_all: float | None
    translation_floor_all: float | None
    rotation_floor_all: float | None
    segments: Segments
    translation_error: np.ndarray
    rotation_error: np.ndarray | None

    def to_dict(self) -> dict:
        """JSON: ``%`` and ``deg/m`` for path segments, ``m/s`` and ``deg/s`` for time; a
        drift is ``below_floor`` when it does not exceed the ground truth's own."""
        dist = self.kind == "distance"
        unit, t_unit, t_scale = ("m", "pct", 100.0) if dist else ("s", "m_per_s", 1.0)
        r_unit, r_scale = ("deg_per_m" if dist else "deg_per_s"), float(np.degrees(1.0))

        def num(v, scale):
            return None if v is None or not np.isfinite(v) else float(scale * v)

        def entries(t, tf, r, rf) -> dict:
            return {f"translation_{t_unit}": num(t, t_scale),
                    f"translation_floor_{t_unit}": num(tf, t_scale),
                    f"rotation_{r_unit}": num(r, r_scale),
                    f"rotation_floor_{r_unit}": num(rf, r_scale),
                    "translation_below_floor": _below(t, tf),
                    "rotation_below_floor": _below(r, rf)}

        def at(a, k):
            return None if a is None else a[k]

        rows = [{f"length_{unit}": float(L), "n": int(self.n[k]),
                 **entries(self.translation[k], at(self.translation_floor, k),
                           at(self.rotation, k), at(self.rotation_floor, k))}
                for k, L in enumerate(self.lengths)]
        return {
            f"lengths_{unit}": [float(v) for v in self.lengths],
            "lengths_from": self.lengths_from,
            "n_segments": int(self.segments.first.size),
            **entries(self.translation_all, self.translation_floor_all, self.rotation_all,
                      self.rotation_floor_all),
            "by_length": rows,
        }


def _below(value: float | None, floor: float | None) -> bool | None:
    """Whether a drift does not exceed the floor (None when either is missing)."""
    if value is None or floor is None or not (np.isfinite(value) and np.isfinite(floor)):
        return None
    return bool(value <= floor)


def _floors(seg: Segments, cov: np.ndarray, sample: np.ndarray, n: np.ndarray,
            rotation: bool) -> tuple:
    """Per-length and pooled floors from the relative covariances ``cov`` of the sampled
    segments (the pooled one weights each length by its number of segments)."""
    B = seg.lengths.size
    L2 = seg.lengths[seg.which[sample]] ** 2
    out = []
    for block in (slice(0, 3), slice(3, 6)) if rotation else (slice(0, 3),):
        tr = np.trace(cov[:, block, block], axis1=-2, axis2=-1) / L2
        per = _mean_by(seg.which[sample], tr, B)
        ok = n > 0
        pooled = float(np.sqrt(np.sum(n[ok] * per[ok]) / np.sum(n[ok]))) if ok.any() else None
        out += [np.sqrt(per), pooled]
    return tuple(out) if rotation else (*out, None, None)


def segment_drift(kind: str, seg: Segments, lengths_from: str, errors: ErrorsFn,
                  covariance: CovarianceFn | None = None) -> SegmentDrift:
    """The drift of the segments ``seg`` (:class:`SegmentDrift`): ``errors`` of every
    segment, ``covariance`` of at most :data:`FLOOR_SEGMENTS` per length for the floor."""
    B = seg.lengths.size
    L = seg.lengths[seg.which]
    t_err, r_err = errors(seg.first, seg.last)
    te = np.asarray(t_err, float) / L
    re = None if r_err is None else np.asarray(r_err, float) / L
    n = np.bincount(seg.which, minlength=B)
    floors = (None, None, None, None)
    if covariance is not None and seg.first.size:
        sample = floor_sample(seg.which, B)
        cov = np.asarray(covariance(seg.first[sample], seg.last[sample]), float)
        floors = _floors(seg, cov, sample, n, re is not None and cov.shape[-1] == 6)
    any_ = seg.first.size > 0
    return SegmentDrift(
        kind, seg.lengths, lengths_from, n, _mean_by(seg.which, te, B),
        None if re is None else _mean_by(seg.which, re, B), floors[0], floors[2],
        float(te.mean()) if any_ else None,
        float(re.mean()) if any_ and re is not None else None, floors[1], floors[3],
        seg, te, re)


@dataclass(frozen=True)
class Drift:
    """Drift by segment length: ``distance`` and ``time`` :class:`SegmentDrift` (None: no motion, or
    a run shorter than the shortest), ``rotation`` why rotational drift is absent (None: it is
    not), ``definition`` of the translation error.
    """

    distance: SegmentDrift | None
    time: SegmentDrift | None
    rotation: str | None = None
    definition: str = ("KITTI devkit: E = (Q_f^-1 Q_l)^-1 (P_f^-1 P_l), |t_E| / L and "
                       "acos((tr R_E - 1) / 2) / L, averaged over segments")

    def to_dict(self) -> dict:
        return {
            "definition": self.definition,
            "step_frames": KITTI_STEP_FRAMES,
            "distance": None if self.distance is None else self.distance.to_dict(),
            "time": None if self.time is None else self.time.to_dict(),
            "rotation": self.rotation,
        }


def drift_metrics(
    t: ArrayLike, gt_position: ArrayLike, errors: ErrorsFn,
    covariance: CovarianceFn | None = None, *, distance: ArrayLike | None = None,
    time: ArrayLike | None = TIME_LENGTHS_S, rotation: str | None = None,
    definition: str | None = None,
) -> Drift:
    """:class:`Drift` over segments of ground-truth path and of time, for poses at ``t`` (N,) s with
    ground-truth positions (N, 3) m. ``errors(first, last)``: each segment's translation error (m)
    and rotation angle (rad or None) (:func:`kitti_errors`); ``covariance(first, last)``: the
    ground truth's relative covariance (K, 6, 6) or (K, 3, 3) (None: no floor); ``distance`` (m,
    default :func:`distance_lengths`) and ``time`` (s) lengths; ``rotation``, ``definition`` as
    :class:`Drift`.
    """
    tt = np.asarray(t, dtype=float)
    along = path_distances(gt_position)
    path = float(along[-1]) if along.size else 0.0
    if distance is None:
        lengths, source = distance_lengths(path)
    else:
        lengths, source = np.asarray(distance, dtype=float).reshape(-1), "given"
    d = None
    if lengths.size:
        d = segment_drift("distance", segments(along, lengths), source, errors, covariance)
    span = float(tt[-1] - tt[0]) if tt.size else 0.0
    tl = np.asarray([] if time is None else time, dtype=float).reshape(-1)
    tl = tl[tl < span]
    ts = None
    if tl.size:
        ts = segment_drift("time", segments(tt, tl), "per-second drift", errors, covariance)
    out = Drift(d, ts, rotation)
    return out if definition is None else Drift(d, ts, rotation, definition)
