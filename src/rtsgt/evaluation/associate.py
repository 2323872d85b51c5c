r"""Association of estimated poses with the (uncertain) ground truth, in time.

The ground truth at ``tau = t + time_offset`` of each estimate pose: a discrete
:class:`~rtsgt.types.PoseTrajectory` (interpolated, covariance flagged), a continuous query
``gt(times) -> PoseTrajectory`` (or with ``cross_next`` (M - 1, 6, 6)), or a
:class:`ValidatedGroundTruth` that says why it drops a time. Poses outside the ground truth or
farther than ``max_dt`` from its measurements are dropped, counted per reason
(docs/evaluation.md#association).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.evaluation.metrics import chain_cross_covariance
from rtsgt.geometry.so3 import exp_so3, log_so3, matrix_to_quat_xyzw
from rtsgt.types import PoseTrajectory, PositionTrajectory

#: Signature of a continuous-time ground truth: times (M,) s -> poses at those times, with
#: ``cov``, optionally with the (M - 1, 6, 6) cross-covariances of consecutive poses.
GroundTruthQuery = Callable[[np.ndarray], "PoseTrajectory | tuple[PoseTrajectory, np.ndarray]"]

#: Times closer than this (s) are the same time (snapping onto ground-truth samples).
TIME_EPS = 1e-9

#: Drop reason: before the first or after the last ground-truth time.
REASON_OUTSIDE = "outside_ground_truth"
#: Drop reason: farther than ``max_dt`` from the nearest ground-truth measurement.
REASON_FAR = "far_from_measurement"


@dataclass(frozen=True)
class GroundTruthSample:
    """A validated continuous-time ground truth at M query times ``t`` (s, ground-truth clock).

    ``position`` (M, 3) m and ``quat_xyzw`` (M, 4) (None for positions), NaN where no pose;
    ``cov`` (M, 6, 6) or (M, 3, 3) or None; ``reason`` (M,) str, "" where valid; ``nearest_dt``
    (M,) s to the farthest track's nearest measurement; ``cross_next`` (V - 1, 6, 6) of
    consecutive valid poses, or None.
    """

    t: np.ndarray
    position: np.ndarray
    quat_xyzw: np.ndarray | None
    cov: np.ndarray | None
    reason: np.ndarray
    nearest_dt: np.ndarray
    cross_next: np.ndarray | None = None

    def __len__(self) -> int:
        return self.t.shape[0]

    @property
    def valid(self) -> np.ndarray:
        """Boolean mask of the valid poses, shape (M,)."""
        return self.reason == ""

    def trajectory(self) -> PoseTrajectory:
        """The valid poses as a trajectory."""
        v = self.valid
        return PoseTrajectory(
            self.t[v], self.position[v], self.quat_xyzw[v], None if self.cov is None else self.cov[v]
        )

    def counts(self) -> dict[str, int]:
        """Number of invalid times per reason (reasons in order of first appearance)."""
        bad = self.reason[~self.valid]
        names, first = np.unique(bad, return_index=True)
        return {str(n): int(np.count_nonzero(bad == n)) for n in names[np.argsort(first)]}


@runtime_checkable
class ValidatedGroundTruth(Protocol):
    """A continuous-time ground truth that says, per time, whether it can vouch for a pose."""

    def query_poses(self, times: np.ndarray, *, max_gap_s: float | None = None) -> GroundTruthSample:
        """Poses at ``times`` with a drop reason per time (``max_gap_s``: distance to the
        nearest measurement beyond which a time is dropped, None: no limit)."""
        ...


@runtime_checkable
class PairCovarianceGroundTruth(Protocol):
    """A ground truth that knows the covariances of pairs of its poses, cross-covariance
    included (e.g. :class:`rtsgt.evaluation.groundtruth.ContinuousGroundTruth`: the errors two
    poses share, from one first-order model). The RPE's relative-pose covariance then uses
    them instead of assuming independent poses or chaining ``cross_next``."""

    def pair_covariances(
        self, tau_a: ArrayLike, tau_b: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``Cov(xi(tau_a))``, ``Cov(xi(tau_b))`` and ``Cov(xi(tau_a), xi(tau_b))``, each of
        shape (K, d, d) (``d``: the ground truth's dof, 6 or 3), at ground-truth times (the
        ground truth's clock)."""
        ...


@runtime_checkable
class SharedFactorGroundTruth(Protocol):
    """A ground truth that splits its pose errors into a varying part and a part shared by
    the whole deployment (:class:`rtsgt.shared.SharedFactor`), e.g.
    :class:`rtsgt.evaluation.groundtruth.ContinuousGroundTruth` of a run that wrote it. The
    NEES verdict then tests the two apart (:func:`rtsgt.evaluation.metrics.shared_error_test`).
    """

    def shared_split(self, times: ArrayLike):
        """The split at ground-truth times (valid poses): a :class:`rtsgt.shared.SharedFactor`
        (6 dof) or a :class:`PositionSplit` (3 dof), or None when it is not known."""
        ...


@dataclass(frozen=True)
class Association:
    """Estimate poses paired with the ground truth at the same (offset) times.

    ``index`` (M,) into the estimate; ``est``; ``gt`` at ``est.t + time_offset`` stored with the
    estimate's times; ``dt_nearest`` (M,) s; ``cov_interpolated`` (M,) bool; ``cross_next``
    (M - 1, 6, 6) or None; ``time_offset``, ``max_dt`` s; counts ``n_est``, ``n_outside``,
    ``n_gap`` (every drop neither outside nor a gate) and ``dropped`` per reason;
    ``ground_truth`` "discrete", "query" or "continuous", ``ground_truth_detail`` its ``info``.
    """

    index: np.ndarray
    est: PoseTrajectory
    gt: PoseTrajectory
    dt_nearest: np.ndarray
    cov_interpolated: np.ndarray
    cross_next: np.ndarray | None
    time_offset: float
    max_dt: float | None
    n_est: int
    n_outside: int
    n_gap: int
    dropped: dict[str, int] = field(default_factory=dict)
    ground_truth: str = "discrete"
    ground_truth_detail: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return self.index.shape[0]

    def to_dict(self) -> dict:
        """JSON-ready summary."""
        return {
            "n_estimate": int(self.n_est),
            "n_associated": int(len(self)),
            "n_outside_ground_truth": int(self.n_outside),
            "n_in_gaps": int(self.n_gap),
            "n_dropped": int(self.n_est - len(self)),
            "dropped_by_reason": {k: int(v) for k, v in self.dropped.items()},
            "ground_truth": self.ground_truth,
            "ground_truth_detail": dict(self.ground_truth_detail),
            "n_covariance_interpolated": int(np.count_nonzero(self.cov_interpolated)),
            "time_offset_s": float(self.time_offset),
            "max_dt_s": None if self.max_dt is None else float(self.max_dt),
            "max_dt_nearest_s": (
                float(np.nanmax(self.dt_nearest))
                if len(self) and np.any(np.isfinite(self.dt_nearest))
                else None
            ),
        }


def nearest_distance(times: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Distance of each of ``tau`` (M,) to the nearest of the sorted ``times`` (K >= 1), s."""
    k = np.clip(np.searchsorted(times, tau), 1, times.size - 1) if times.size > 1 else None
    if k is None:
        return np.abs(tau - times[0])
    return np.minimum(np.abs(tau - times[k - 1]), np.abs(times[k] - tau))


def interpolate_trajectory(
    gt: PoseTrajectory, tau: ArrayLike
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """Interpolate ``gt`` (>= 2 poses, increasing times) at ``tau`` (M,) inside its span: position
    (M, 3), rotation (M, 3, 3), linear cov (M, 6, 6) or None, ``exact`` (M,) index of a coinciding
    sample or -1, ``frac`` (M,) between the neighbours.
    """
    tau = np.asarray(tau, dtype=float)
    t = gt.t
    n = t.size
    a = np.clip(np.searchsorted(t, tau, side="right") - 1, 0, n - 2)
    b = a + 1
    f = (tau - t[a]) / (t[b] - t[a])
    at_a = np.abs(tau - t[a]) <= TIME_EPS
    at_b = np.abs(t[b] - tau) <= TIME_EPS
    exact = np.where(at_a, a, np.where(at_b, b, -1))
    f = np.where(at_a, 0.0, np.where(at_b, 1.0, f))
    pos = gt.position[a] + f[:, None] * (gt.position[b] - gt.position[a])
    Ra, Rb = gt.rotation[a], gt.rotation[b]
    rot = exp_so3(f[:, None] * log_so3(Rb @ np.swapaxes(Ra, -1, -2))) @ Ra
    cov = None
    if gt.cov is not None:
        cov = (1.0 - f)[:, None, None] * gt.cov[a] + f[:, None, None] * gt.cov[b]
    snap = exact >= 0
    if np.any(snap):
        e = exact[snap]
        pos[snap] = gt.position[e]
        rot[snap] = gt.rotation[e]
        if cov is not None:
            cov[snap] = gt.cov[e]
    return pos, rot, cov, exact, f


def _check_times(t: np.ndarray, what: str) -> None:
    if t.size and not np.all(np.isfinite(t)):
        raise InputError(f"Expected finite {what} times, got NaN or inf")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        k = int(np.argmax(np.diff(t) <= 0)) + 1
        raise InputError(
            f"Expected strictly increasing {what} times, got {t[k]!r} after {t[k - 1]!r} "
            f"(pose {k}); sort the trajectory and remove duplicates"
        )


def associate(
    gt: PoseTrajectory | GroundTruthQuery,
    est: PoseTrajectory,
    *,
    time_offset: float = 0.0,
    max_dt: float | None = 0.5,
    measurement_times: ArrayLike | None = None,
    gt_cross_next: ArrayLike | None = None,
) -> Association:
    """Pair each estimate pose (increasing times) with the ground truth ``gt`` at its time plus
    ``time_offset`` s; returns :class:`Association`.

    ``max_dt`` s (None: no check) to the nearest of ``measurement_times`` (K,) (for a query: also
    its support; for a discrete truth: its own times by default); ``gt_cross_next``
    (N_gt - 1, 6, 6) for a discrete truth, chained between samples. InputError when nothing
    overlaps, every overlapping pose is in a gap, or on bad shapes or times.
    """
    t_est = np.asarray(est.t, dtype=float)
    _check_times(t_est, "estimate")
    if len(est) == 0:
        raise InputError("The estimate has no poses")
    if not np.isfinite(time_offset):
        raise InputError(f"Expected a finite time offset, got {time_offset}")
    if max_dt is not None and not max_dt > 0:
        raise InputError(f"Expected a positive max_dt, got {max_dt}")
    tau_all = t_est + float(time_offset)
    if not isinstance(gt, PoseTrajectory) and isinstance(gt, ValidatedGroundTruth):
        return _associate_validated(gt, est, tau_all, float(time_offset), max_dt)
    discrete = isinstance(gt, PoseTrajectory)
    mt, span = _support(gt, measurement_times)
    inside = (tau_all >= span[0] - TIME_EPS) & (tau_all <= span[1] + TIME_EPS)
    dt_all = np.full(tau_all.shape, np.nan)
    if mt is not None and mt.size:
        dt_all = nearest_distance(mt, tau_all)
    near = np.ones_like(inside) if max_dt is None or mt is None else dt_all <= max_dt
    keep = inside & near
    n_outside = int(np.count_nonzero(~inside))
    n_gap = int(np.count_nonzero(inside & ~near))
    if not np.any(inside):
        raise InputError(
            f"No time overlap: the estimate spans [{t_est[0]:.6f}, {t_est[-1]:.6f}] s "
            f"(+ time offset {time_offset} s) and the ground truth [{span[0]:.6f}, "
            f"{span[1]:.6f}] s; check the clocks or pass a time offset"
        )
    if not np.any(keep):
        raise InputError(
            f"None of the {np.count_nonzero(inside)} estimate poses inside the ground-truth span "
            f"is within max_dt = {max_dt} s of a ground-truth measurement; raise --max-dt"
        )
    index = np.flatnonzero(keep)
    est_k = PoseTrajectory(
        est.t[index],
        est.position[index],
        est.quat_xyzw[index],
        None if est.cov is None else est.cov[index],
    )
    if discrete:
        gt_k, interp, cross = _discrete_at(gt, tau_all[index], est_k.t, gt_cross_next)
    else:
        gt_k, interp, cross = _query_at(gt, tau_all[index], est_k.t)
    return Association(
        index=index,
        est=est_k,
        gt=gt_k,
        dt_nearest=dt_all[index],
        cov_interpolated=interp,
        cross_next=cross,
        time_offset=float(time_offset),
        max_dt=None if max_dt is None else float(max_dt),
        n_est=len(est),
        n_outside=n_outside,
        n_gap=n_gap,
        dropped={
            k: v for k, v in ((REASON_OUTSIDE, n_outside), (REASON_FAR, n_gap)) if v
        },
        ground_truth="discrete" if discrete else "query",
    )


def _support(gt, measurement_times) -> tuple[np.ndarray | None, tuple[float, float]]:
    """Measurement times (sorted, or None) and time span of a discrete or query ground truth."""
    if isinstance(gt, PoseTrajectory):
        _check_times(np.asarray(gt.t), "ground-truth")
        if len(gt) < 2:
            raise InputError(f"Expected a ground truth with at least 2 poses, got {len(gt)}")
        mt = np.asarray(gt.t if measurement_times is None else measurement_times, dtype=float)
        return mt, (float(gt.t[0]), float(gt.t[-1]))
    if callable(gt):
        mt = None if measurement_times is None else np.sort(np.asarray(measurement_times, float))
        span = (-np.inf, np.inf) if mt is None or mt.size == 0 else (float(mt[0]), float(mt[-1]))
        return mt, span
    raise TypeError(f"Expected a PoseTrajectory or a callable ground truth, got {type(gt)}")


def _discrete_at(gt: PoseTrajectory, tau: np.ndarray, t_est: np.ndarray, gt_cross_next):
    """A discrete ground truth at ``tau`` (M,), stored at ``t_est``: the poses, which
    covariances were interpolated (M,), and the chained ``cross_next`` (M - 1, 6, 6) or None."""
    pos, rot, cov, exact, _ = interpolate_trajectory(gt, tau)
    interp = (exact < 0) if gt.cov is not None else np.zeros(tau.size, dtype=bool)
    cross = None
    if gt_cross_next is not None:
        C = np.asarray(gt_cross_next, dtype=float)
        if C.shape != (len(gt) - 1, 6, 6):
            raise ValueError(
                f"Expected gt_cross_next of shape ({len(gt) - 1}, 6, 6), got {C.shape}"
            )
        if gt.cov is None:
            raise ValueError("gt_cross_next needs a ground truth with covariances")
        cross = np.full((tau.size - 1, 6, 6), np.nan)
        ok = (exact[:-1] >= 0) & (exact[1:] >= 0) & (exact[1:] > exact[:-1])
        if np.any(ok):
            pairs = np.stack([exact[:-1][ok], exact[1:][ok]], axis=1)
            cross[ok] = chain_cross_covariance(gt.cov, C, pairs)
    return PoseTrajectory(t_est, pos, matrix_to_quat_xyzw(rot), cov), interp, cross


def _query_at(gt, tau: np.ndarray, t_est: np.ndarray):
    """A query ground truth at ``tau`` (M,), stored at ``t_est``, as :func:`_discrete_at`."""
    out = gt(tau)
    cross = None
    if isinstance(out, tuple):
        if len(out) != 2:
            raise ValueError(
                "Expected the ground-truth query to return a PoseTrajectory or a pair"
            )
        traj, cross = out[0], None if out[1] is None else np.asarray(out[1], dtype=float)
    else:
        traj = out
    if not isinstance(traj, PoseTrajectory) or len(traj) != tau.size:
        raise ValueError(
            f"Expected the ground-truth query to return a PoseTrajectory of {tau.size} poses"
        )
    if cross is not None and cross.shape != (tau.size - 1, 6, 6):
        raise ValueError(
            f"Expected query cross-covariances of shape ({tau.size - 1}, 6, 6), "
            f"got {cross.shape}"
        )
    interp = np.zeros(tau.size, dtype=bool)
    return PoseTrajectory(t_est, traj.position, traj.quat_xyzw, traj.cov), interp, cross


def _associate_validated(
    gt: ValidatedGroundTruth,
    est: PoseTrajectory,
    tau_all: np.ndarray,
    time_offset: float,
    max_dt: float | None,
) -> Association:
    """:func:`associate` for a :class:`ValidatedGroundTruth`: one query at every offset time."""
    s = gt.query_poses(tau_all, max_gap_s=max_dt)
    if not isinstance(s, GroundTruthSample) or len(s) != tau_all.size:
        raise ValueError(
            f"Expected query_poses to return a GroundTruthSample of {tau_all.size} times"
        )
    reason = np.asarray(s.reason)
    keep = reason == ""
    counts = s.counts()
    n_outside = counts.get(REASON_OUTSIDE, 0)
    n_gate = sum(v for k, v in counts.items() if k.startswith("gate_"))
    n_gap = int(np.count_nonzero(~keep)) - n_outside - n_gate
    t_est = est.t
    if n_outside == tau_all.size:
        span = getattr(gt, "span", None)
        where = (
            f"[{span[0]:.6f}, {span[1]:.6f}] s" if span is not None else "a disjoint interval"
        )
        raise InputError(
            f"No time overlap: the estimate spans [{t_est[0]:.6f}, {t_est[-1]:.6f}] s "
            f"(+ time offset {time_offset} s) and the ground truth {where}; check the clocks "
            "or pass a time offset"
        )
    if not np.any(keep):
        why = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in counts.items())
        raise InputError(
            f"None of the {tau_all.size} estimate poses could be associated with the ground "
            f"truth ({why}); check the time offset or raise --max-gap (now {max_dt} s)"
        )
    index = np.flatnonzero(keep)
    est_k = PoseTrajectory(
        est.t[index],
        est.position[index],
        est.quat_xyzw[index],
        None if est.cov is None else est.cov[index],
    )
    cross = None if s.cross_next is None else np.asarray(s.cross_next, dtype=float)
    if cross is not None and cross.shape != (index.size - 1, 6, 6):
        raise ValueError(
            f"Expected cross-covariances of shape ({index.size - 1}, 6, 6), got {cross.shape}"
        )
    gt_k = PoseTrajectory(
        est_k.t, s.position[index], s.quat_xyzw[index], None if s.cov is None else s.cov[index]
    )
    return Association(
        index=index,
        est=est_k,
        gt=gt_k,
        dt_nearest=np.asarray(s.nearest_dt, dtype=float)[index],
        cov_interpolated=np.zeros(index.size, dtype=bool),
        cross_next=cross,
        time_offset=time_offset,
        max_dt=None if max_dt is None else float(max_dt),
        n_est=len(est),
        n_outside=n_outside,
        n_gap=n_gap,
        dropped=counts,
        ground_truth="continuous",
        ground_truth_detail=dict(getattr(gt, "info", None) or {}),
    )


#: Half step (s) of the central differences of :func:`ground_truth_rates`: short against the
#: time over which a robot's velocity changes (the difference's error is about
#: ``jerk step^2 / 6``, 1 cm/s for 1 m/s^3), long against the time over which a ground truth's
#: noise changes (its noise in the difference is ``sigma / (sqrt 2 step)``).
RATE_STEP_S = 0.25


@dataclass(frozen=True)
class GroundTruthRates:
    """World-frame velocities of the ground truth at the associated times: ``v`` (M, 3) m/s, ``w``
    (M, 3) rad/s (``R(tau + dt) = exp(w dt) R(tau)``), ``cov`` (M, 6, 6) of ``(v, w)`` or None.
    """

    v: np.ndarray
    w: np.ndarray
    cov: np.ndarray | None


def ground_truth_rates(
    gt: PoseTrajectory | GroundTruthQuery | ValidatedGroundTruth,
    assoc: Association,
    *,
    measurement_times: ArrayLike | None = None,
    step: float = RATE_STEP_S,
) -> GroundTruthRates:
    r""":class:`GroundTruthRates` of ``gt`` (any kind) at ``assoc``'s times by central differences of
    ``step`` s (docs/evaluation.md#association); ``measurement_times`` as for :func:`associate`.
    """
    tau = assoc.est.t + assoc.time_offset
    M = tau.size
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (M, 1))
    p0, R0, P0 = assoc.gt.position, assoc.gt.rotation, assoc.gt.cov
    side = {}
    for sign in (-1.0, 1.0):
        probe = PoseTrajectory(tau + sign * step, np.zeros((M, 3)), quat)
        ok = np.zeros(M, dtype=bool)
        p, R = p0.copy(), R0.copy()
        P = None if P0 is None else P0.copy()
        try:
            a = associate(gt, probe, time_offset=0.0, max_dt=None,
                          measurement_times=measurement_times)
        except InputError:  # no time of this side inside the ground truth
            a = None
        if a is not None:
            ok[a.index] = True
            p[a.index] = a.gt.position
            R[a.index] = a.gt.rotation
            if P is not None and a.gt.cov is not None:
                P[a.index] = a.gt.cov
        side[sign] = (ok, p, R, P, np.where(ok, tau + sign * step, tau))
    (_, pm, Rm, Pm, tm), (_, pp, Rp, Pp, tp) = side[-1.0], side[1.0]
    span = tp - tm
    moved = span > 0
    safe = np.where(moved, span, 1.0)
    v = np.where(moved[:, None], (pp - pm) / safe[:, None], 0.0)
    w = np.where(moved[:, None], log_so3(Rp @ np.swapaxes(Rm, 1, 2)) / safe[:, None], 0.0)
    cov = None
    if P0 is not None:
        cov = np.where(moved[:, None, None], Pm + Pp, 0.0) / (safe * safe)[:, None, None]
    return GroundTruthRates(v, w, cov)


# ------------------------------------------------------------------------------------------
# ground truths of positions (3 dof): one tracked point, seen by the association as poses
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PositionSplit:
    """A position ground truth's error split at some times, ``e_i = nu_i + F_i theta``:
    ``varying_cov`` (N, 3, 3) m^2, ``factor`` (N, 3, k) m per unit of the whitened shared
    parameters ``theta ~ N(0, I_k)``, ``names`` (k,) (docs/evaluation.md#position-only-ground-truth)."""

    varying_cov: np.ndarray
    factor: np.ndarray
    names: tuple[str, ...]


@runtime_checkable
class ValidatedPositionGroundTruth(Protocol):
    """A continuous-time position ground truth that says, per time, whether it can vouch for a
    position (:class:`GroundTruthSample` with ``quat_xyzw`` None, ``cov`` (M, 3, 3))."""

    def query_positions(self, times: np.ndarray, *,
                        max_gap_s: float | None = None) -> GroundTruthSample:
        """Positions at ``times`` with a drop reason per time."""
        ...


def ground_truth_dof(gt: object) -> int:
    """The degrees of freedom a ground truth gives: 3 for positions (a
    :class:`~rtsgt.types.PositionTrajectory`, a :class:`ValidatedPositionGroundTruth`, one
    whose ``dof`` is 3), else 6 (poses)."""
    if isinstance(gt, PositionTrajectory):
        return 3
    dof = getattr(gt, "dof", None)
    if dof is not None:
        return int(dof)
    return 3 if isinstance(gt, ValidatedPositionGroundTruth) else 6


_IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


def _embed(cov3: np.ndarray | None) -> np.ndarray | None:
    """(N, 3, 3) position covariances as (N, 6, 6) with a zero rotation block (never read)."""
    if cov3 is None:
        return None
    out = np.zeros(cov3.shape[:-2] + (6, 6))
    out[..., :3, :3] = cov3
    return out


class _AsPoses:
    """A continuous position ground truth seen by the association of poses: a placeholder
    orientation (identity, never read), the covariance in the position block."""

    def __init__(self, gt: ValidatedPositionGroundTruth):
        self._gt = gt
        self.span = getattr(gt, "span", None)
        self.info = getattr(gt, "info", None) or {}

    def query_poses(self, times: np.ndarray, *,
                    max_gap_s: float | None = None) -> GroundTruthSample:
        s = self._gt.query_positions(times, max_gap_s=max_gap_s)
        if not isinstance(s, GroundTruthSample) or s.t.shape != np.shape(times):
            raise ValueError("Expected query_positions to return a GroundTruthSample per time")
        quat = np.broadcast_to(_IDENTITY, (s.t.size, 4)).copy()
        return GroundTruthSample(s.t, s.position, quat, _embed(s.cov), s.reason, s.nearest_dt)


def positions_as_poses(gt: PositionTrajectory | ValidatedPositionGroundTruth):
    """A ground truth of positions as the association takes poses: a placeholder orientation
    (identity, never read), the covariance in the position block of a 6x6 one.

    Raises
    ------
    InputError
        Positions or covariances of a discrete ground truth not finite.
    """
    if isinstance(gt, PositionTrajectory):
        if not np.all(np.isfinite(gt.position)):
            k = int(np.argmax(~np.all(np.isfinite(gt.position), axis=1)))
            raise InputError(f"Expected finite ground-truth positions, got NaN or inf at "
                             f"position {k} (t = {gt.t[k]})")
        if gt.cov is not None and not np.all(np.isfinite(gt.cov)):
            raise InputError("Expected finite ground-truth covariances, got NaN or inf")
        quat = np.broadcast_to(_IDENTITY, (len(gt), 4))
        return PoseTrajectory(gt.t, gt.position, quat, _embed(gt.cov))
    if isinstance(gt, ValidatedPositionGroundTruth):
        return _AsPoses(gt)
    raise TypeError(f"Expected a PositionTrajectory or a ValidatedPositionGroundTruth, got "
                    f"{type(gt).__name__}")


# ------------------------------------------------------------------------------------------
# the inputs' check and the gaps of the ground truth (both kinds)
# ------------------------------------------------------------------------------------------


def check_trajectory(traj: PoseTrajectory, what: str) -> PoseTrajectory:
    """``traj`` with finite values and unit quaternions (renormalised within 1e-3); an
    InputError naming ``what`` and the pose otherwise."""
    for name in ("position", "quat_xyzw"):
        a = getattr(traj, name)
        if not np.all(np.isfinite(a)):
            k = int(np.argmax(~np.all(np.isfinite(a), axis=1)))
            raise InputError(
                f"Expected finite {what} {name}, got NaN or inf at pose {k} (t = {traj.t[k]})"
            )
    norm = np.linalg.norm(traj.quat_xyzw, axis=1)
    bad = np.abs(norm - 1.0) > 1e-3
    if np.any(bad):
        k = int(np.argmax(bad))
        raise InputError(
            f"Expected unit {what} quaternions, got norm {norm[k]:.6g} at pose {k} "
            f"(t = {traj.t[k]})"
        )
    if traj.cov is not None and not np.all(np.isfinite(traj.cov)):
        k = int(np.argmax(~np.all(np.isfinite(traj.cov), axis=(1, 2))))
        raise InputError(f"Expected finite {what} covariances, got NaN or inf at pose {k}")
    return PoseTrajectory(traj.t, traj.position, traj.quat_xyzw / norm[:, None], traj.cov)


def _range_max(values: np.ndarray, start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """``max(values[start_k:stop_k])`` for every k (``start_k < stop_k <= values.size``)."""
    v = np.append(values, 0.0)  # reduceat needs every index < size
    return np.maximum.reduceat(v, np.ravel(np.column_stack([start, stop])))[::2]


def gap_per_step(
    tau: np.ndarray, index: np.ndarray, support: np.ndarray | None, limit: float
) -> np.ndarray:
    """Ground-truth gap (M - 1,) s between consecutive associated poses (0 where none).

    For ground-truth times ``tau`` (M,) and estimate ``index`` (M,): the larger of ``tau[k+1] -
    tau[k]`` when poses were dropped between and it exceeds ``limit``, and the longest spacing of
    ``support`` (sorted) over ``[tau[k], tau[k+1]]`` when it exceeds ``2 limit``.
    """
    dropped = np.diff(index) > 1
    step = np.diff(tau)
    gap = np.where(dropped & (step > limit), step, 0.0)
    if support is not None and support.size > 1 and tau.size > 1:
        spacing = np.diff(support)
        last = spacing.size - 1
        a = np.clip(np.searchsorted(support, tau[:-1], side="right") - 1, 0, last)
        b = np.clip(np.searchsorted(support, tau[1:], side="left"), a + 1, last + 1)
        longest = _range_max(spacing, a, b)
        gap = np.maximum(gap, np.where(longest > 2.0 * limit, longest, 0.0))
    return gap


def warn_gaps(assoc: Association, pairs: np.ndarray, support: np.ndarray | None) -> None:
    """A :class:`~rtsgt.errors.RtsgtWarning` counting the RPE pairs across ground-truth gaps."""
    limit = assoc.max_dt
    if limit is None or pairs.shape[0] == 0 or len(assoc) < 2:
        return
    gap = gap_per_step(assoc.est.t + assoc.time_offset, assoc.index, support, limit)
    over = gap > 0
    if not np.any(over):
        return
    span = _range_max(over.astype(float), pairs[:, 0], pairs[:, 1]) > 0
    n = int(np.count_nonzero(span))
    if n == 0:
        return
    covered = np.zeros(gap.size + 1, dtype=int)
    np.add.at(covered, pairs[span, 0], 1)
    np.add.at(covered, pairs[span, 1], -1)
    inside = (np.cumsum(covered)[:-1] > 0) & over
    k = int(np.flatnonzero(inside)[np.argmax(gap[inside])])
    warnings.warn(
        f"{n} of {pairs.shape[0]} RPE pairs span a gap of the ground truth (gap limit "
        f"{limit:g} s; longest {gap[k]:.3g} s, after the estimate pose at t = "
        f"{assoc.est.t[k]:.6f} s): their relative errors include the motion through the gap",
        RtsgtWarning,
        stacklevel=3,
    )


def gap_support(gt: object, gt_measurement_times: ArrayLike | None) -> np.ndarray | None:
    """The sorted times the ground truth rests on, for the gap warning (:func:`gap_per_step`):
    a discrete ground truth's samples, a query's measurement times; None for a validated
    ground truth (its association already drops the poses in gaps)."""
    if isinstance(gt, (PoseTrajectory, PositionTrajectory)):
        return np.asarray(gt.t, dtype=float)
    validated = isinstance(gt, (ValidatedGroundTruth, ValidatedPositionGroundTruth))
    if gt_measurement_times is not None and not validated:
        return np.sort(np.asarray(gt_measurement_times, dtype=float))
    return None
