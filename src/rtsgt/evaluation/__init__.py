r"""Evaluation of SLAM / odometry trajectories against an uncertain ground truth.

:func:`evaluate` runs the whole chain, in evo's order::

    associate (time offset, max_dt)  ->  align (none | se3 | sim3 | 4dof | scale | origin)
      ->  APE, RPE (evo's definitions and statistics)
      ->  NEES (3 and 6 dof), consistency verdicts, noise floor, RPE with relative covariance

and returns an immutable :class:`EvaluationResult` whose :meth:`EvaluationResult.to_dict` is
the JSON layout of ``rtsgt evaluate --json``::

    {"ape": {"translation_m": {rmse, mean, median, std, min, max},
             "rotation_deg": {...}, "full": {...}, "n": N},
     "rpe": {"translation_m": {...}, "rotation_deg": {...}, "full": {...},
             "n_pairs": K, "delta": d, "delta_unit": "m", "all_pairs": false,
             "absent_reason": null},
     "nees": {"position": {mean, dof, fraction_inside_95, consistent, ...},
              "pose": {...}, "relative_position": {...}, "relative_pose": {...},
              "covariance": "...", "rpe_correlations": "..."},
     "noise_floor": {"ape_translation_m": ..., "ape_translation_rmse_floor_removed_m": ...,
                     "ape_rotation_deg": ..., "ape_rotation_rmse_floor_removed_deg": ...,
                     "rpe_translation_m": ..., "rpe_translation_rmse_floor_removed_m": ...,
                     "rpe_rotation_deg": ..., "rpe_rotation_rmse_floor_removed_deg": ...},
     "alignment": {"method", "weighted", "n_used", "scale", "yaw_deg", "matrix_sim3"},
     "association": {"n_estimate", "n_associated", "n_outside_ground_truth", "n_in_gaps",
                     "n_dropped", "dropped_by_reason": {reason: count},
                     "ground_truth": "continuous" | "discrete" | "query",
                     "ground_truth_detail": {...},
                     "n_covariance_interpolated", "time_offset_s", "max_dt_s",
                     "max_dt_nearest_s"},
     "warnings": ["..."]}

``warnings`` is added by ``rtsgt evaluate``: every :class:`~rtsgt.errors.RtsgtWarning` that
reading the files and evaluating emitted (each also shown as a ``warning: ...`` line).

When no RPE pair exists (a robot that moved less than ``delta``), the APE and the NEES of the
poses are still given; ``rpe`` then holds ``null`` statistics, ``n_pairs`` 0 and
``absent_reason`` (why, and what to change), and the relative NEES and the RPE noise floor are
``null``. RPE pairs that span a gap of the ground truth are kept (the RPE stays evo's) and
counted in a warning (:func:`evaluate`).

The ground truth is best a :class:`~rtsgt.evaluation.groundtruth.ContinuousGroundTruth`
(``ContinuousGroundTruth.from_run_dir(run)``): the pose and covariance at each estimate time
from the run's GP tracks, with a reason for every estimate pose it cannot vouch for.

The four sections ``ape``, ``rpe``, ``nees``, ``noise_floor`` and the keys the issue names
(``translation_m`` / ``rotation_deg`` with the six statistics; ``mean, dof,
fraction_inside_95, consistent``) are the stable interface; the other keys add detail
(NEES objects also give ``n``, ``n_eff``, ``mean_interval``, ``fraction_interval``,
``quantile_95``, ``alpha``).

NEES objects hold ``null`` values (and the noise floor ``null`` numbers) when the ground truth
has no covariance. This module imports only numpy, scipy and rtsgt.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.evaluation.align import ALIGN_METHODS, Alignment, align_trajectories
from rtsgt.evaluation.associate import (
    Association,
    GroundTruthQuery,
    GroundTruthSample,
    ValidatedGroundTruth,
    associate,
)
from rtsgt.evaluation.groundtruth import ContinuousGroundTruth
from rtsgt.evaluation.metrics import (
    DELTA_UNITS,
    STATISTICS,
    NeesResult,
    ape_errors,
    chain_cross_covariance,
    error_statistics,
    nees_consistency,
    noise_floor,
    pose_error,
    relative_pose_covariance,
    relative_pose_error_vector,
    remove_floor,
    rpe_errors,
    rpe_pairs,
    squared_mahalanobis,
)
from rtsgt.types import PoseTrajectory

__all__ = [
    "ALIGN_METHODS",
    "DELTA_UNITS",
    "STATISTICS",
    "Alignment",
    "Association",
    "ErrorStatistics",
    "EvaluationResult",
    "GroundTruthQuery",
    "GroundTruthSample",
    "NeesResult",
    "NeesSection",
    "NoiseFloor",
    "PoseErrors",
    "ValidatedGroundTruth",
    "associate",
    "evaluate",
]


def __getattr__(name: str):
    # imported lazily: it needs the pipeline, which the rest of this package does not
    if name == "ContinuousGroundTruth":

        return ContinuousGroundTruth
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@dataclass(frozen=True)
class ErrorStatistics:
    """evo's statistics of one error array (units of the array)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float

    @classmethod
    def from_errors(cls, errors: ArrayLike) -> ErrorStatistics:
        return cls(**error_statistics(errors))

    def to_dict(self) -> dict[str, float]:
        return {k: float(getattr(self, k)) for k in STATISTICS}


@dataclass(frozen=True)
class PoseErrors:
    """APE or RPE: per-pose (per-pair) errors and their statistics.

    Attributes
    ----------
    translation_m, rotation_deg, full : ErrorStatistics
        evo's translation part (m), rotation angle (deg) and full transformation (unitless).
    translation_error : ndarray, shape (K,)
        m.
    rotation_error_deg : ndarray, shape (K,)
    full_error : ndarray, shape (K,)
    pairs : ndarray of int, shape (K, 2) or None
        RPE index pairs into the associated poses (None for the APE).
    """

    translation_m: ErrorStatistics
    rotation_deg: ErrorStatistics
    full: ErrorStatistics
    translation_error: np.ndarray
    rotation_error_deg: np.ndarray
    full_error: np.ndarray
    pairs: np.ndarray | None = None

    @classmethod
    def from_errors(
        cls, errs: dict[str, np.ndarray], pairs: np.ndarray | None = None
    ) -> PoseErrors:
        rot_deg = np.degrees(errs["rotation_rad"])
        return cls(
            ErrorStatistics.from_errors(errs["translation"]),
            ErrorStatistics.from_errors(rot_deg),
            ErrorStatistics.from_errors(errs["full"]),
            errs["translation"],
            rot_deg,
            errs["full"],
            pairs,
        )

    def to_dict(self) -> dict:
        return {
            "translation_m": self.translation_m.to_dict(),
            "rotation_deg": self.rotation_deg.to_dict(),
            "full": self.full.to_dict(),
        }


@dataclass(frozen=True)
class NeesSection:
    """Normalised estimation error squared of positions, poses and relative poses.

    Each field is None when the covariances needed are not available.
    ``covariance`` says which covariances entered ``S``; ``rpe_correlations`` whether the
    relative-pose covariance used known cross-covariances between the two ground-truth poses.
    """

    position: NeesResult | None
    pose: NeesResult | None
    relative_position: NeesResult | None
    relative_pose: NeesResult | None
    covariance: str
    rpe_correlations: str

    def to_dict(self) -> dict:
        def one(r: NeesResult | None, dof: int) -> dict:
            if r is None:
                return {"mean": None, "dof": dof, "fraction_inside_95": None, "consistent": None}
            return r.to_dict()

        return {
            "position": one(self.position, 3),
            "pose": one(self.pose, 6),
            "relative_position": one(self.relative_position, 3),
            "relative_pose": one(self.relative_pose, 6),
            "covariance": self.covariance,
            "rpe_correlations": self.rpe_correlations,
        }


@dataclass(frozen=True)
class NoiseFloor:
    """The errors a perfect estimate would show against this ground truth, and the APE/RPE
    with that floor removed (``sqrt(max(rmse^2 - floor^2, 0))``). None without covariances.

    Attributes
    ----------
    ape_translation_m : float
        ``sqrt(mean tr Sigma_gt,pos)``, m.
    ape_translation_rmse_floor_removed_m : float
    ape_rotation_deg : float
        ``sqrt(mean tr Sigma_gt,rot)`` in degrees (small-angle rms of the rotation angle).
    ape_rotation_rmse_floor_removed_deg : float
    rpe_translation_m : float
        ``sqrt(mean tr Sigma_rel,pos)`` over the RPE pairs, m.
    rpe_translation_rmse_floor_removed_m : float
    rpe_rotation_deg, rpe_rotation_rmse_floor_removed_deg : float
    """

    ape_translation_m: float | None = None
    ape_translation_rmse_floor_removed_m: float | None = None
    ape_rotation_deg: float | None = None
    ape_rotation_rmse_floor_removed_deg: float | None = None
    rpe_translation_m: float | None = None
    rpe_translation_rmse_floor_removed_m: float | None = None
    rpe_rotation_deg: float | None = None
    rpe_rotation_rmse_floor_removed_deg: float | None = None

    def to_dict(self) -> dict:
        return {k: (None if v is None else float(v)) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class EvaluationResult:
    """Everything :func:`evaluate` computed.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Times of the associated estimate poses, s (estimate clock).
    gt : PoseTrajectory
        Ground truth at those times (world frame, with ``cov`` when available).
    est : PoseTrajectory
        The associated estimate after alignment (world frame; ``cov`` mapped too).
    alignment : Alignment
    association : Association
    ape : PoseErrors
    rpe : PoseErrors or None
        None when no RPE pair exists (``rpe_absent_reason`` says why).
    nees : NeesSection
    noise_floor : NoiseFloor
    pose_error : ndarray, shape (N, 6)
        ``perturbation(gt, est)``: (x, y, z, rx, ry, rz), m and rad, world frame.
    cov_error : ndarray, shape (N, 6, 6) or None
        ``S_k`` used for the NEES (ground truth + estimate when it has one).
    rpe_delta : float
    rpe_delta_unit : str
    rpe_all_pairs : bool
    rpe_absent_reason : str or None
        Why there is no RPE (None when there is one).
    """

    t: np.ndarray
    gt: PoseTrajectory
    est: PoseTrajectory
    alignment: Alignment
    association: Association
    ape: PoseErrors
    rpe: PoseErrors | None
    nees: NeesSection
    noise_floor: NoiseFloor
    pose_error: np.ndarray
    cov_error: np.ndarray | None
    rpe_delta: float
    rpe_delta_unit: str
    rpe_all_pairs: bool
    rpe_absent_reason: str | None = None

    def to_dict(self) -> dict:
        """The JSON layout of ``rtsgt evaluate --json`` (module docstring)."""
        ape = self.ape.to_dict()
        ape["n"] = int(self.t.shape[0])
        if self.rpe is None:
            rpe = {"translation_m": None, "rotation_deg": None, "full": None}
        else:
            rpe = self.rpe.to_dict()
        rpe.update(
            n_pairs=0 if self.rpe is None else int(self.rpe.pairs.shape[0]),
            delta=float(self.rpe_delta),
            delta_unit=self.rpe_delta_unit,
            all_pairs=bool(self.rpe_all_pairs),
            absent_reason=self.rpe_absent_reason,
        )
        return {
            "ape": ape,
            "rpe": rpe,
            "nees": self.nees.to_dict(),
            "noise_floor": self.noise_floor.to_dict(),
            "alignment": self.alignment.to_dict(),
            "association": self.association.to_dict(),
        }


def _check_trajectory(traj: PoseTrajectory, what: str) -> PoseTrajectory:
    """Finite values and unit quaternions (renormalised within 1e-3)."""
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


def _nees(e: np.ndarray, S: np.ndarray, dof: int, what: str, t: np.ndarray) -> NeesResult:
    try:
        d2 = squared_mahalanobis(e, S)
    except ValueError as exc:
        raise InputError(f"Cannot compute the {what} NEES: {exc} (t = {t})") from None
    return nees_consistency(d2, dof)


def _no_pair_reason(source: PoseTrajectory, delta: float, unit: str) -> str:
    """Why :func:`~rtsgt.evaluation.metrics.rpe_pairs` found no pair, and what to change."""
    n = len(source)
    if unit == "m":
        path = float(np.sum(np.linalg.norm(np.diff(source.position, axis=0), axis=1)))
        have, want = f"{path:.3g} m of path", f"{delta:g} m"
    elif unit == "s":
        span = float(source.t[-1] - source.t[0]) if n else 0.0
        have, want = f"{span:.3g} s", f"{delta:g} s"
    else:
        have, want = f"{n} associated poses", f"{int(delta)} frames"
    return (
        f"no pose pair {want} apart: the {n} associated poses span {have}; "
        "use a smaller RPE delta"
    )


def _range_max(values: np.ndarray, start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """``max(values[start_k:stop_k])`` for every k (``start_k < stop_k <= values.size``)."""
    v = np.append(values, 0.0)  # reduceat needs every index < size
    return np.maximum.reduceat(v, np.ravel(np.column_stack([start, stop])))[::2]


def gap_per_step(
    tau: np.ndarray, index: np.ndarray, support: np.ndarray | None, limit: float
) -> np.ndarray:
    """Ground-truth gap between consecutive associated poses, s, shape (M - 1,); 0 where none.

    Parameters
    ----------
    tau : ndarray, shape (M,)
        Ground-truth times of the associated poses (estimate time + offset), increasing.
    index : ndarray of int, shape (M,)
        Their indices in the estimate.
    support : ndarray, shape (K,), optional
        Times the ground truth rests on (discrete samples, measurement times), sorted.
    limit : float
        The gap limit ``max_dt``, s.

    Returns
    -------
    ndarray
        The larger of: ``tau[k+1] - tau[k]`` when the association dropped estimate poses
        between k and k + 1 and it exceeds ``limit``; the longest spacing of ``support`` over
        ``[tau[k], tau[k+1]]`` when it exceeds ``2 limit`` (a stretch farther than ``limit``
        from both samples: where the association would drop a pose).
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


def _warn_gaps(assoc: Association, pairs: np.ndarray, support: np.ndarray | None) -> None:
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


def evaluate(
    gt: PoseTrajectory | GroundTruthQuery | ValidatedGroundTruth,
    est: PoseTrajectory,
    *,
    align: str = "se3",
    n_align: int | None = None,
    weighted: bool = False,
    delta: float = 1.0,
    delta_unit: str = "m",
    all_pairs: bool = False,
    rel_delta_tol: float = 0.1,
    pairs_from_reference: bool = False,
    time_offset: float = 0.0,
    max_dt: float | None = 0.5,
    gt_measurement_times: ArrayLike | None = None,
    gt_cross_next: ArrayLike | None = None,
) -> EvaluationResult:
    """Evaluate an estimated trajectory against an (uncertain) ground truth.

    Parameters
    ----------
    gt : PoseTrajectory, ValidatedGroundTruth or callable
        Ground truth in the world frame: a discrete trajectory (interpolated at the estimate's
        times), a validated continuous-time ground truth such as
        :class:`~rtsgt.evaluation.groundtruth.ContinuousGroundTruth` (the run's GP tracks
        turned into poses at the estimate's times, with a drop reason per time), or a plain
        query ``gt(times) -> PoseTrajectory`` (optionally ``(PoseTrajectory, cross_next)``);
        see :mod:`rtsgt.evaluation.associate`. Covariances (``cov``) enable NEES and noise
        floor.
    est : PoseTrajectory
        Estimate in its own frame, strictly increasing times; an optional ``cov`` (6x6, the
        left-perturbation convention in the estimate's frame) enters the NEES.
    align : str
        ``none``, ``se3``, ``sim3``, ``4dof``, ``scale`` or ``origin``
        (:mod:`rtsgt.evaluation.align`).
    n_align : int, optional
        Align on the first ``n_align`` associated poses only.
    weighted : bool
        Covariance-weighted alignment (weights ``1 / tr Sigma_pos``).
    delta, delta_unit, all_pairs, rel_delta_tol, pairs_from_reference :
        RPE pair selection as evo (:func:`~rtsgt.evaluation.metrics.rpe_pairs`); units
        ``m`` (path), ``s``, ``f`` (frames); pairs from the aligned estimate unless
        ``pairs_from_reference``.
    time_offset : float
        s added to the estimate's times (evo ``--t_offset``).
    max_dt : float or None
        Max distance (s) to the nearest ground-truth measurement time (for a continuous ground
        truth: to the nearest measurement of every prism, ``--max-gap``); also the gap limit
        of the RPE warning below (None: no limit).
    gt_measurement_times : array_like, optional
        Measurement times supporting a query ground truth (support and ``max_dt``).
    gt_cross_next : array_like, shape (N_gt - 1, 6, 6), optional
        Cross-covariances of consecutive samples of a discrete ground truth.

    Returns
    -------
    EvaluationResult
        ``rpe`` is None, with ``rpe_absent_reason``, when no RPE pair exists (the APE and
        the NEES are still computed).

    Warns
    -----
    RtsgtWarning
        RPE pairs that span a gap of the ground truth, a stretch it cannot vouch for within
        the gap limit ``max_dt``: between the pair's poses, two consecutive associated poses
        more than ``max_dt`` apart with dropped estimate poses between them, or two
        consecutive samples of a discrete ground truth (measurement times of a query ground
        truth) more than ``2 max_dt`` apart, i.e. with a stretch farther than ``max_dt`` from
        both (:func:`gap_per_step`). They are kept, so that the RPE stays evo's; the warning
        counts them and gives the longest gap. No check with ``max_dt=None``.

    Raises
    ------
    InputError
        No time overlap, too few associated poses for the alignment, bad values.
    GeometryError
        Degenerate alignment geometry.
    """
    if align not in ALIGN_METHODS:
        raise InputError(f"Expected an alignment in {ALIGN_METHODS}, got {align!r}")
    if delta_unit not in DELTA_UNITS:
        raise InputError(f"Expected a delta unit in {DELTA_UNITS}, got {delta_unit!r}")
    if not (np.isfinite(delta) and delta > 0):
        raise InputError(f"Expected a positive RPE delta, got {delta}")
    if delta_unit == "f" and float(delta) != int(delta):
        raise InputError(f"Expected an integer RPE delta in frames, got {delta}")
    est = _check_trajectory(est, "estimate")
    if isinstance(gt, PoseTrajectory):
        gt = _check_trajectory(gt, "ground-truth")
    assoc = associate(
        gt,
        est,
        time_offset=time_offset,
        max_dt=max_dt,
        measurement_times=gt_measurement_times,
        gt_cross_next=gt_cross_next,
    )
    g = assoc.gt
    if not isinstance(gt, PoseTrajectory):
        g = _check_trajectory(g, "ground-truth")
    alignment = align_trajectories(g, assoc.est, method=align, n_align=n_align, weighted=weighted)
    e = alignment.apply(assoc.est)
    Rg, Re = g.rotation, e.rotation

    # APE and RPE with evo's definitions
    ape = PoseErrors.from_errors(ape_errors(Rg, g.position, Re, e.position))
    source = g if pairs_from_reference else e
    pairs = rpe_pairs(
        source.position, source.t, delta, delta_unit, all_pairs=all_pairs, rel_tol=rel_delta_tol
    )
    rpe = None
    no_rpe = None
    if pairs.shape[0] == 0:
        no_rpe = _no_pair_reason(source, float(delta), delta_unit)
    else:
        rpe = PoseErrors.from_errors(rpe_errors(Rg, g.position, Re, e.position, pairs), pairs)
        if isinstance(gt, PoseTrajectory):
            support = np.asarray(gt.t, dtype=float)
        elif gt_measurement_times is not None and not isinstance(gt, ValidatedGroundTruth):
            support = np.sort(np.asarray(gt_measurement_times, dtype=float))
        else:
            support = None
        _warn_gaps(assoc, pairs, support)

    # Uncertainty-aware metrics
    xi = pose_error(Rg, g.position, Re, e.position)
    S = None
    nees = NeesSection(
        None, None, None, None, "none: the ground truth has no covariance", "not applicable"
    )
    floor = NoiseFloor()
    if g.cov is not None:
        S = g.cov + (0.0 if e.cov is None else e.cov)
        what = "ground truth" + (" + estimate" if e.cov is not None else "")
        nees_pos = _nees(xi[:, :3], S[:, :3, :3], 3, "position", g.t)
        nees_pose = _nees(xi, S, 6, "pose", g.t)
        f_t = noise_floor(g.cov[:, :3, :3])
        f_r = float(np.degrees(noise_floor(g.cov[:, 3:, 3:])))
        floor = NoiseFloor(
            f_t,
            remove_floor(ape.translation_m.rmse, f_t),
            f_r,
            remove_floor(ape.rotation_deg.rmse, f_r),
        )
        nees = NeesSection(nees_pos, nees_pose, None, None, what, "not applicable (no RPE pair)")
    if g.cov is not None and rpe is not None:
        # Relative pose covariance of the ground truth (frame of the ground truth at i)
        i, j = pairs[:, 0], pairs[:, 1]
        cross = None
        P_i, P_j = g.cov[i], g.cov[j]
        correl = "assumed independent (no cross-covariance between ground-truth poses given)"
        if hasattr(gt, "pair_covariances"):
            # a continuous ground truth computes the errors its poses share directly; the
            # marginals come from the same first-order model, so that the difference of two
            # strongly correlated poses stays positive definite
            ti, tj = g.t[i] + assoc.time_offset, g.t[j] + assoc.time_offset
            P_i, P_j, cross = gt.pair_covariances(ti, tj)
            correl = "computed by the ground truth (shared systematic errors, GP correlation)"
        elif assoc.cross_next is not None:
            cross = chain_cross_covariance(g.cov, assoc.cross_next, pairs)
            known = np.all(np.isfinite(cross), axis=(1, 2))
            cross = np.where(known[:, None, None], cross, 0.0)
            n_known = int(np.count_nonzero(known))
            correl = (
                "provided"
                if n_known == pairs.shape[0]
                else f"provided for {n_known} of {pairs.shape[0]} pairs, others assumed independent"
            )
        S_rel = relative_pose_covariance(Rg[i], g.position[i], g.position[j], P_i, P_j, cross)
        xi_rel = relative_pose_error_vector(Rg, g.position, Re, e.position, pairs)
        nees_rpos = _nees(xi_rel[:, :3], S_rel[:, :3, :3], 3, "relative position", g.t[i])
        nees_rpose = _nees(xi_rel, S_rel, 6, "relative pose", g.t[i])
        nees = NeesSection(
            nees_pos,
            nees_pose,
            nees_rpos,
            nees_rpose,
            what + (" (relative: ground truth only)" if e.cov is not None else ""),
            correl,
        )
        fr_t = noise_floor(S_rel[:, :3, :3])
        fr_r = float(np.degrees(noise_floor(S_rel[:, 3:, 3:])))
        floor = dataclasses.replace(
            floor,
            rpe_translation_m=fr_t,
            rpe_translation_rmse_floor_removed_m=remove_floor(rpe.translation_m.rmse, fr_t),
            rpe_rotation_deg=fr_r,
            rpe_rotation_rmse_floor_removed_deg=remove_floor(rpe.rotation_deg.rmse, fr_r),
        )
    return EvaluationResult(
        t=assoc.est.t,
        gt=g,
        est=e,
        alignment=alignment,
        association=assoc,
        ape=ape,
        rpe=rpe,
        nees=nees,
        noise_floor=floor,
        pose_error=xi,
        cov_error=S,
        rpe_delta=float(delta),
        rpe_delta_unit=delta_unit,
        rpe_all_pairs=bool(all_pairs),
        rpe_absent_reason=no_rpe,
    )
