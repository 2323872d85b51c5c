"""The evaluation chain of :func:`evaluate`, one function per step (evo's order)::

    check inputs -> [mounting and clock] -> associate -> mounting -> align -> APE -> RPE
      (+ gap warning) -> error covariances, relative-pose covariance -> NEES -> noise floor
      -> [the mounting's effect on APE / RPE] -> drift by segment length -> result

The mounting step (:func:`mounting_step`, when something is estimated) fits the mounting
``T_body_sensor`` and the clock offset jointly with an alignment
(:func:`~rtsgt.evaluation.mounting.fit_mounting`), re-associating the ground truth at each new
clock offset; the estimate's sensor poses are then moved to the body frame by the mounting
(given or estimated) and the chain goes on as evo would on that transformed trajectory.

The ground truth's kinds (:mod:`rtsgt.evaluation.associate`) differ in what they give: a
:class:`~rtsgt.evaluation.associate.PairCovarianceGroundTruth` computes the covariances of
pairs of its poses (the RPE's covariance); otherwise ``cross_next`` of the association is
chained, or the poses are taken as independent.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.evaluation.align import Alignment, align_trajectories
from rtsgt.evaluation.associate import (
    Association,
    GroundTruthQuery,
    GroundTruthRates,
    PairCovarianceGroundTruth,
    SharedFactorGroundTruth,
    ValidatedGroundTruth,
    associate,
    ground_truth_rates,
)
from rtsgt.evaluation.drift import Drift, drift_metrics, kitti_errors
from rtsgt.evaluation.handeye import coarse_clock_shift
from rtsgt.evaluation.metrics import (
    NeesResult,
    alignment_sensitivity,
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
    with_split_verdict,
)
from rtsgt.evaluation.mounting import (
    CLOCK_TOLERANCE_S,
    MountingFit,
    fit_mounting,
    mounting_sensitivity,
)
from rtsgt.evaluation.options import EvaluationOptions
from rtsgt.evaluation.result import EvaluationResult, NeesSection, NoiseFloor, PoseErrors
from rtsgt.geometry.so3 import exp_so3, hat, matrix_to_quat_xyzw, quat_xyzw_to_matrix
from rtsgt.types import PoseTrajectory

__all__ = ["EvaluationOptions", "evaluate", "gap_per_step"]

#: Ground-truth kinds :func:`evaluate` accepts.
GroundTruth = PoseTrajectory | GroundTruthQuery | ValidatedGroundTruth


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
    """NEES of errors ``e`` with covariances ``S`` and its consistency test (a covariance that
    is not positive definite is an InputError naming ``what`` and the times ``t``)."""
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



@dataclass(frozen=True)
class RelativeCovariance:
    """Covariance of the ground truth's relative poses of the RPE pairs.

    Attributes
    ----------
    cov : ndarray, shape (K, 6, 6)
        In the frame of the ground-truth pose ``i`` of each pair ``(i, j)``.
    correlations : str
        Where the cross-covariances of the two poses came from (``rpe_correlations``).
    """

    cov: np.ndarray
    correlations: str


def associate_step(
    gt: GroundTruth,
    est: PoseTrajectory,
    options: EvaluationOptions,
    gt_measurement_times: ArrayLike | None,
    gt_cross_next: ArrayLike | None,
) -> tuple[Association, PoseTrajectory]:
    """Check the inputs and pair each estimate pose with the ground truth at its offset time.

    Returns the association and the associated ground truth, checked (finite, unit
    quaternions, renormalised; for a discrete ground truth that check comes first)."""
    est = _check_trajectory(est, "estimate")
    if isinstance(gt, PoseTrajectory):
        gt = _check_trajectory(gt, "ground-truth")
    assoc = associate(
        gt,
        est,
        time_offset=options.time_offset,
        max_dt=options.max_dt,
        measurement_times=gt_measurement_times,
        gt_cross_next=gt_cross_next,
    )
    if isinstance(gt, PoseTrajectory):
        return assoc, assoc.gt
    return assoc, _check_trajectory(assoc.gt, "ground-truth")


def body_trajectory(
    est: PoseTrajectory, rotation: np.ndarray, lever: np.ndarray, scale: float = 1.0
) -> PoseTrajectory:
    r"""The estimate's sensor poses moved to the body frame: ``T_E_body = T_E_sensor
    T_body_sensor^-1``, i.e. ``R = R_e R_bs^T``, ``p = p_e - R l / scale`` (the lever arm
    ``l`` is metric; ``scale`` is the alignment's, so that it is metric after a Sim(3)).

    The estimate's covariance (left perturbation in its frame) follows: ``dp = dp_e +
    [R l / scale]x dtheta_e``, ``dtheta = dtheta_e``.
    """
    R = est.rotation @ np.asarray(rotation, dtype=float).T
    arm = R @ np.asarray(lever, dtype=float) / scale
    cov = None
    if est.cov is not None:
        J = np.zeros((len(est), 6, 6))
        J[:, :3, :3] = np.eye(3)
        J[:, :3, 3:] = hat(arm)
        J[:, 3:, 3:] = np.eye(3)
        cov = J @ est.cov @ np.swapaxes(J, 1, 2)
    return PoseTrajectory(est.t, est.position - arm, matrix_to_quat_xyzw(R), cov)


def _align_body(
    g: PoseTrajectory, est: PoseTrajectory, options: EvaluationOptions, mounting: MountingFit | None
) -> tuple[Alignment, PoseTrajectory]:
    """Move ``est`` to the body frame by ``mounting`` (if any) and align it onto ``g``. With a
    scale in the alignment, the metric lever arm needs the scale: a fixed point (the lever arm
    is small against the trajectory, so it converges in a few steps)."""
    scale = 1.0
    for _ in range(20):
        body = est if mounting is None else body_trajectory(
            est, mounting.rotation, mounting.lever, scale)
        alignment = align_trajectories(
            g, body, method=options.align, n_align=options.n_align, weighted=options.weighted,
        )
        if mounting is None or abs(alignment.scale - scale) <= 1e-12 * scale:
            break
        scale = alignment.scale
    return alignment, alignment.apply(body)


def align_step(
    g: PoseTrajectory,
    assoc: Association,
    options: EvaluationOptions,
    mounting: MountingFit | None = None,
) -> tuple[Alignment, PoseTrajectory]:
    """The alignment of the associated estimate onto the associated ground truth ``g``, and
    the aligned estimate (world frame, ``cov`` mapped too); with a ``mounting``, of the
    estimate moved to the body frame (:func:`body_trajectory`)."""
    return _align_body(g, assoc.est, options, mounting)


def given_mounting(options: EvaluationOptions) -> MountingFit | None:
    """The mounting of ``options.mounting`` (None when there is none)."""
    if options.mounting is None:
        return None
    m = np.asarray(options.mounting)
    return MountingFit.given(quat_xyzw_to_matrix(m[3:]), m[:3], options.time_offset)


def _fit_at(
    gt: GroundTruth, g: PoseTrajectory, assoc: Association, options: EvaluationOptions,
    start: MountingFit, rates: GroundTruthRates | None,
) -> MountingFit:
    """One fit of :func:`~rtsgt.evaluation.mounting.fit_mounting` on an association."""
    if g.cov is None:
        raise InputError(
            f"Estimating {', '.join(options.estimate)} needs a ground truth with covariances "
            "(the weights of the least squares)"
        )
    S, L = g.cov, None
    if isinstance(gt, SharedFactorGroundTruth):
        split = gt.shared_split(g.t + assoc.time_offset)
        if split is not None:
            S, L = split.varying_cov, split.factor
    return fit_mounting(
        g.position, g.rotation, S, assoc.est.position, assoc.est.rotation,
        estimate=options.estimate, align=options.align, rotation=start.rotation,
        lever=start.lever, clock_offset=assoc.time_offset,
        gt_velocity=None if rates is None else rates.v,
        gt_angular_velocity=None if rates is None else rates.w,
        gt_rate_cov=None if rates is None else rates.cov,
        est_cov=assoc.est.cov, shared=L,
    )


#: Associations of the clock's fixed point at most (:func:`mounting_step`).
MAX_CLOCK_ASSOCIATIONS = 10


def mounting_step(
    gt: GroundTruth,
    est: PoseTrajectory,
    options: EvaluationOptions,
    gt_measurement_times: ArrayLike | None,
    gt_cross_next: ArrayLike | None,
) -> tuple[MountingFit, Association, PoseTrajectory]:
    """Estimate what ``options.estimate`` asks for, jointly with the alignment, and the
    association at the final clock offset.

    The ground truth is associated at the offset, the mounting and the clock step fitted with
    the ground truth's velocities there (:func:`~rtsgt.evaluation.associate.
    ground_truth_rates`), and the ground truth associated again at the new offset, until the
    step is below :data:`~rtsgt.evaluation.mounting.CLOCK_TOLERANCE_S` (at most
    :data:`MAX_CLOCK_ASSOCIATIONS` times; a warning says when it did not settle).
    """
    start = given_mounting(options) or MountingFit.given(clock_offset=options.time_offset)
    offset = options.time_offset
    clock = "clock" in options.estimate
    if clock:  # the coarse search over +-1 s (rotation angles over 1 s correlated)
        assoc, g = associate_step(gt, est, options, gt_measurement_times, gt_cross_next)
        offset += coarse_clock_shift(assoc.est.t, g.rotation, assoc.est.rotation)
    for _ in range(MAX_CLOCK_ASSOCIATIONS):
        assoc, g = associate_step(gt, est, dataclasses.replace(options, time_offset=offset),
                                  gt_measurement_times, gt_cross_next)
        rates = ground_truth_rates(gt, assoc, measurement_times=gt_measurement_times) \
            if clock else None
        fit = _fit_at(gt, g, assoc, options, start, rates)
        if not clock:
            return fit, assoc, g
        step = fit.clock_offset - offset
        offset = fit.clock_offset
        if abs(step) < CLOCK_TOLERANCE_S:
            break
    else:
        warnings.warn(
            f"The clock offset did not settle in {MAX_CLOCK_ASSOCIATIONS} associations (last "
            f"step {step:.3g} s); its estimate is that of the last association",
            RtsgtWarning,
            stacklevel=3,
        )
    assoc, g = associate_step(gt, est, dataclasses.replace(options, time_offset=offset),
                              gt_measurement_times, gt_cross_next)
    return fit, assoc, g


def _mounting_rates(
    gt: GroundTruth, assoc: Association, fit: MountingFit | None,
    gt_measurement_times: ArrayLike | None,
) -> GroundTruthRates | None:
    """The ground truth's velocities at the final association when the clock was estimated."""
    if fit is None or "clock" not in fit.estimated:
        return None
    return ground_truth_rates(gt, assoc, measurement_times=gt_measurement_times)


def _shifted(g: PoseTrajectory, rates: GroundTruthRates | None, delta: float) -> PoseTrajectory:
    """The ground truth moved by a small clock step along its velocity (first order)."""
    if rates is None or delta == 0.0:
        return g
    R = exp_so3(delta * rates.w) @ g.rotation
    return PoseTrajectory(g.t, g.position + delta * rates.v, matrix_to_quat_xyzw(R), g.cov)


def mounting_effect(
    fit: MountingFit | None,
    g: PoseTrajectory,
    assoc: Association,
    options: EvaluationOptions,
    rates: GroundTruthRates | None,
    pairs: np.ndarray,
) -> dict[str, float | None] | None:
    r"""How much the rmse of the APE and RPE would move within the uncertainty of the estimated
    mounting and clock (None when nothing was estimated).

    With ``c_i`` the columns of a square root of the parameters' covariance and ``f`` the rmse
    as a function of the parameters (the whole chain: mounting, alignment, errors; the clock
    moves the ground truth along its velocity; the RPE pairs are kept), ``a_i = (f(+c_i) -
    f(-c_i)) / 2`` and ``b_i = (f(+c_i) + f(-c_i)) / 2 - f(0)`` give the first- and second-order
    terms, and

    .. math:: u^2 = \sum a_i^2 + 2 \sum b_i^2 + (\sum b_i)^2

    is the rms of ``f(true) - f(estimate)`` for a quadratic ``f`` whose curvature is diagonal
    in those directions (the rmse is near a minimum in the mounting, so that the second-order
    term matters). ``2 p`` evaluations (p <= 7 parameters), each vectorised.

    Returns
    -------
    dict
        ``ape_translation_m``, ``ape_rotation_deg``, ``rpe_translation_m``,
        ``rpe_rotation_deg`` (the RPE's None without pairs).
    """
    if fit is None or fit.covariance is None:
        return None
    C = fit.covariance
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    cols = V * np.sqrt(np.clip(w, 0.0, None))
    names = fit.names

    def rmse(theta: np.ndarray) -> np.ndarray:
        val = dict(zip(names, theta, strict=True))
        psi = np.array([val.get(f"rotation_{a}", 0.0) for a in "xyz"])
        dl = np.array([val.get(f"lever_{a}", 0.0) for a in "xyz"])
        moved = dataclasses.replace(fit, rotation=exp_so3(psi) @ fit.rotation,
                                    lever=fit.lever + dl)
        gt_k = _shifted(g, rates, float(val.get("clock", 0.0)))
        _, e = _align_body(gt_k, assoc.est, options, moved)
        ape = ape_errors(gt_k.rotation, gt_k.position, e.rotation, e.position)
        out = [error_statistics(ape["translation"])["rmse"],
               np.degrees(error_statistics(ape["rotation_rad"])["rmse"]), np.nan, np.nan]
        if pairs.shape[0]:
            rpe = rpe_errors(gt_k.rotation, gt_k.position, e.rotation, e.position, pairs)
            out[2] = error_statistics(rpe["translation"])["rmse"]
            out[3] = np.degrees(error_statistics(rpe["rotation_rad"])["rmse"])
        return np.array(out)

    f0 = rmse(np.zeros(len(names)))
    fp = np.array([rmse(c) for c in cols.T])  # 2 p sigma points (p <= 7), not samples
    fm = np.array([rmse(-c) for c in cols.T])
    a = 0.5 * (fp - fm)
    b = 0.5 * (fp + fm) - f0
    u = np.sqrt(np.sum(a * a, axis=0) + 2 * np.sum(b * b, axis=0) + np.sum(b, axis=0) ** 2)
    keys = ("ape_translation_m", "ape_rotation_deg", "rpe_translation_m", "rpe_rotation_deg")
    return {k: (None if not np.isfinite(x) else float(x)) for k, x in zip(keys, u, strict=True)}


def compute_ape(g: PoseTrajectory, e: PoseTrajectory) -> PoseErrors:
    """evo's absolute pose errors of the aligned estimate ``e`` against the ground truth ``g``."""
    return PoseErrors.from_errors(ape_errors(g.rotation, g.position, e.rotation, e.position))


def compute_rpe(
    g: PoseTrajectory, e: PoseTrajectory, options: EvaluationOptions
) -> tuple[np.ndarray, PoseErrors | None, str | None]:
    """evo's RPE pairs, relative pose errors and, when there is no pair, why.

    Returns
    -------
    pairs : ndarray of int, shape (K, 2)
        Index pairs into the associated poses (K may be 0).
    rpe : PoseErrors or None
        None when K is 0.
    absent_reason : str or None
        Why there is no pair and what to change (None when there is one).
    """
    source = g if options.pairs_from_reference else e
    pairs = rpe_pairs(
        source.position, source.t, options.delta, options.delta_unit,
        all_pairs=options.all_pairs, rel_tol=options.rel_delta_tol,
    )
    if pairs.shape[0] == 0:
        return pairs, None, _no_pair_reason(source, float(options.delta), options.delta_unit)
    errs = rpe_errors(g.rotation, g.position, e.rotation, e.position, pairs)
    return pairs, PoseErrors.from_errors(errs, pairs), None


def gap_support(gt: GroundTruth, gt_measurement_times: ArrayLike | None) -> np.ndarray | None:
    """The sorted times the ground truth rests on, for the gap warning (:func:`gap_per_step`):
    a discrete ground truth's samples, a query's measurement times; None for a validated
    ground truth (its association already drops the poses in gaps)."""
    if isinstance(gt, PoseTrajectory):
        return np.asarray(gt.t, dtype=float)
    if gt_measurement_times is not None and not isinstance(gt, ValidatedGroundTruth):
        return np.sort(np.asarray(gt_measurement_times, dtype=float))
    return None


def error_covariance(g: PoseTrajectory, e: PoseTrajectory) -> np.ndarray | None:
    """``S_k`` of the NEES: ground-truth covariance plus the estimate's when it has one; None
    when the ground truth has none."""
    if g.cov is None:
        return None
    return g.cov + (0.0 if e.cov is None else e.cov)


def relative_covariance(
    gt: GroundTruth, g: PoseTrajectory, assoc: Association, pairs: np.ndarray
) -> RelativeCovariance:
    """Covariance of the ground truth's relative poses of the RPE ``pairs`` (ground truth
    with covariances, at least one pair).

    A :class:`~rtsgt.evaluation.associate.PairCovarianceGroundTruth` computes the marginals
    and the cross-covariance of each pair from one first-order model (so that the difference
    of two strongly correlated poses stays positive definite); else the association's
    ``cross_next`` are chained where known; else the two poses are taken as independent.
    """
    i, j = pairs[:, 0], pairs[:, 1]
    if isinstance(gt, PairCovarianceGroundTruth):
        ti, tj = g.t[i] + assoc.time_offset, g.t[j] + assoc.time_offset
        P_i, P_j, cross = gt.pair_covariances(ti, tj)
        correl = "computed by the ground truth (shared systematic errors, GP correlation)"
    else:
        P_i, P_j = g.cov[i], g.cov[j]
        cross, correl = _chained_cross_covariance(g.cov, assoc.cross_next, pairs)
    cov = relative_pose_covariance(g.rotation[i], g.position[i], g.position[j], P_i, P_j, cross)
    return RelativeCovariance(cov, correl)


def _chained_cross_covariance(
    cov: np.ndarray, cross_next: np.ndarray | None, pairs: np.ndarray
) -> tuple[np.ndarray | None, str]:
    """Cross-covariances of the pairs chained from ``cross_next`` (0 where unknown), and what
    ``rpe_correlations`` says about them."""
    if cross_next is None:
        return None, "assumed independent (no cross-covariance between ground-truth poses given)"
    cross = chain_cross_covariance(cov, cross_next, pairs)
    known = np.all(np.isfinite(cross), axis=(1, 2))
    cross = np.where(known[:, None, None], cross, 0.0)
    n_known = int(np.count_nonzero(known))
    if n_known == pairs.shape[0]:
        return cross, "provided"
    return cross, f"provided for {n_known} of {pairs.shape[0]} pairs, others assumed independent"


def absolute_nees(
    xi: np.ndarray, S: np.ndarray, t: np.ndarray
) -> tuple[NeesResult, NeesResult]:
    """NEES of the positions (3 dof) and of the poses (6 dof) for errors ``xi`` (N, 6) with
    covariances ``S`` (N, 6, 6) at times ``t``."""
    return _nees(xi[:, :3], S[:, :3, :3], 3, "position", t), _nees(xi, S, 6, "pose", t)


def split_nees(
    gt: GroundTruth,
    g: PoseTrajectory,
    e: PoseTrajectory,
    assoc: Association,
    xi: np.ndarray,
    absolute: tuple[NeesResult, NeesResult],
    align: str,
    absorbed: np.ndarray | None = None,
) -> tuple[NeesResult, NeesResult]:
    """The absolute NEES with the split verdict when the ground truth gives its shared factor
    (:func:`~rtsgt.evaluation.metrics.shared_error_test`; ``consistent`` becomes its verdict,
    ``mean`` and ``fraction_inside_95`` stay those of the NEES against the total covariance);
    unchanged otherwise (the verdict of the NEES series' autocorrelation). For an estimate
    without covariance the tests are one-sided: is the error significant against the ground
    truth's own uncertainty? ``absorbed`` (N, 6, m): further directions the evaluation fitted
    (the mounting and clock, :func:`~rtsgt.evaluation.mounting.mounting_sensitivity`),
    projected out with the alignment's."""
    if not isinstance(gt, SharedFactorGroundTruth):
        return absolute
    split = gt.shared_split(g.t + assoc.time_offset)
    if split is None:
        return absolute
    D = split.varying_cov + (0.0 if e.cov is None else e.cov)
    K = alignment_sensitivity(g.position, align)
    if absorbed is not None:
        K = absorbed if K is None else np.concatenate([K, absorbed], axis=2)
    try:
        return with_split_verdict(absolute, xi, D, split.factor, K, names=split.names,
                                  upper=e.cov is None)
    except ValueError as exc:
        raise InputError(f"Cannot test the errors against the shared factor: {exc}") from None


def nees_section(
    g: PoseTrajectory,
    e: PoseTrajectory,
    absolute: tuple[NeesResult, NeesResult] | None,
    pairs: np.ndarray,
    relative: RelativeCovariance | None,
) -> NeesSection:
    """The NEES section: the absolute NEES (None without ground-truth covariances) and the
    relative NEES of the RPE pairs against ``relative`` (None without pairs)."""
    if absolute is None:
        return NeesSection(
            None, None, None, None, "none: the ground truth has no covariance", "not applicable"
        )
    what = "ground truth" + (" + estimate" if e.cov is not None else "")
    if relative is None:
        return NeesSection(*absolute, None, None, what, "not applicable (no RPE pair)")
    t_i = g.t[pairs[:, 0]]
    xi_rel = relative_pose_error_vector(g.rotation, g.position, e.rotation, e.position, pairs)
    S_rel = relative.cov
    nees_rpos = _nees(xi_rel[:, :3], S_rel[:, :3, :3], 3, "relative position", t_i)
    nees_rpose = _nees(xi_rel, S_rel, 6, "relative pose", t_i)
    return NeesSection(
        *absolute,
        nees_rpos,
        nees_rpose,
        what + (" (relative: ground truth only)" if e.cov is not None else ""),
        relative.correlations,
    )


def noise_floor_section(
    g: PoseTrajectory,
    ape: PoseErrors,
    rpe: PoseErrors | None,
    relative: RelativeCovariance | None,
) -> NoiseFloor:
    """The errors a perfect estimate would show against this ground truth (APE: from the
    ground-truth covariances; RPE: from the relative covariance), and the rmse with that floor
    removed; None values without covariances (or, for the RPE, without pairs)."""
    if g.cov is None:
        return NoiseFloor()
    f_t = noise_floor(g.cov[:, :3, :3])
    f_r = float(np.degrees(noise_floor(g.cov[:, 3:, 3:])))
    floor = NoiseFloor(
        f_t,
        remove_floor(ape.translation_m.rmse, f_t),
        f_r,
        remove_floor(ape.rotation_deg.rmse, f_r),
    )
    if relative is None or rpe is None:
        return floor
    fr_t = noise_floor(relative.cov[:, :3, :3])
    fr_r = float(np.degrees(noise_floor(relative.cov[:, 3:, 3:])))
    return dataclasses.replace(
        floor,
        rpe_translation_m=fr_t,
        rpe_translation_rmse_floor_removed_m=remove_floor(rpe.translation_m.rmse, fr_t),
        rpe_rotation_deg=fr_r,
        rpe_rotation_rmse_floor_removed_deg=remove_floor(rpe.rotation_deg.rmse, fr_r),
    )


def drift_step(gt: GroundTruth, g: PoseTrajectory, e: PoseTrajectory,
               assoc: Association) -> Drift:
    """Drift by segment length of the aligned estimate ``e`` against the associated ground
    truth ``g`` (:func:`~rtsgt.evaluation.drift.drift_metrics`, the devkit's errors), with
    the ground truth's floor from its relative covariance over the segments
    (:func:`relative_covariance`) when it has covariances."""

    def errors(first: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return kitti_errors(g.rotation, g.position, e.rotation, e.position, first, last)

    def covariance(first: np.ndarray, last: np.ndarray) -> np.ndarray:
        return relative_covariance(gt, g, assoc, np.column_stack([first, last])).cov

    return drift_metrics(assoc.est.t, g.position, errors,
                         None if g.cov is None else covariance)


def evaluate(
    gt: GroundTruth,
    est: PoseTrajectory,
    options: EvaluationOptions | None = None,
    *,
    gt_measurement_times: ArrayLike | None = None,
    gt_cross_next: ArrayLike | None = None,
    **overrides,
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
        floor; a :class:`~rtsgt.evaluation.associate.PairCovarianceGroundTruth` also gives
        the RPE's relative-pose covariance its correlations.
    est : PoseTrajectory
        Estimate in its own frame, strictly increasing times; an optional ``cov`` (6x6, the
        left-perturbation convention in the estimate's frame) enters the NEES.
    options : EvaluationOptions, optional
        Alignment, RPE pairs, time offset, ``max_dt``, the mounting given (``mounting``) and
        what to estimate with the alignment (``estimate``: the mounting's rotation and lever
        arm, the clock; docs/evaluation.md#mounting-and-clock) (default:
        ``EvaluationOptions()``). ``est`` is then the sensor's pose, moved to the body
        frame by the mounting before the alignment.
    gt_measurement_times : array_like, optional
        Measurement times supporting a query ground truth (support and ``max_dt``).
    gt_cross_next : array_like, shape (N_gt - 1, 6, 6), optional
        Cross-covariances of consecutive samples of a discrete ground truth.
    **overrides
        Fields of :class:`EvaluationOptions` (``align="sim3", delta=10, delta_unit="f"``,
        ...) replacing those of ``options``.

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
    ExcitationError
        Something asked for in ``estimate`` that the trajectory does not excite (its
        standard deviation above :data:`~rtsgt.evaluation.mounting.MAX_SIGMA`).
    InputError
        No time overlap, too few associated poses for the alignment, bad values, an estimate
        asked of a ground truth without covariances.
    GeometryError
        Degenerate alignment geometry.
    TypeError
        An override that is no field of :class:`EvaluationOptions`.
    """
    options = dataclasses.replace(
        EvaluationOptions() if options is None else options, **overrides
    )
    if options.estimate:
        fit, assoc, g = mounting_step(gt, est, options, gt_measurement_times, gt_cross_next)
    else:
        assoc, g = associate_step(gt, est, options, gt_measurement_times, gt_cross_next)
        fit = given_mounting(options)
    alignment, e = align_step(g, assoc, options, fit)
    ape = compute_ape(g, e)
    pairs, rpe, no_rpe = compute_rpe(g, e, options)
    if rpe is not None:
        _warn_gaps(assoc, pairs, gap_support(gt, gt_measurement_times))
    xi = pose_error(g.rotation, g.position, e.rotation, e.position)
    S = error_covariance(g, e)
    rates = _mounting_rates(gt, assoc, fit, gt_measurement_times)
    absolute = None if S is None else absolute_nees(xi, S, g.t)
    if absolute is not None:
        absorbed = None
        if fit is not None and fit.estimated:
            absorbed = mounting_sensitivity(fit, e.rotation, *(
                (None, None) if rates is None else (rates.v, rates.w)))
        absolute = split_nees(gt, g, e, assoc, xi, absolute, options.align, absorbed)
    relative = None if S is None or rpe is None else relative_covariance(gt, g, assoc, pairs)
    return EvaluationResult(
        t=assoc.est.t,
        gt=g,
        est=e,
        alignment=alignment,
        association=assoc,
        ape=ape,
        rpe=rpe,
        nees=nees_section(g, e, absolute, pairs, relative),
        noise_floor=noise_floor_section(g, ape, rpe, relative),
        pose_error=xi,
        cov_error=S,
        rpe_delta=float(options.delta),
        rpe_delta_unit=options.delta_unit,
        rpe_all_pairs=bool(options.all_pairs),
        rpe_absent_reason=no_rpe,
        mounting=fit,
        mounting_effect=mounting_effect(fit, g, assoc, options, rates, pairs),
        drift=drift_step(gt, g, e, assoc),
    )
