"""The evaluation chain of :func:`evaluate`, one function per step (evo's order)::

    check inputs -> [mounting and clock] -> associate -> mounting -> align -> APE -> RPE
      (+ gap warning) -> error covariances, relative-pose covariance -> NEES -> noise floor
      -> [the mounting's effect on APE / RPE] -> drift by segment length -> result

A ground truth of positions (3 dof) goes through the same steps with the estimate's points
``p_S + R_S l`` in place of its poses (no mounting). docs/evaluation.md.
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
    ValidatedPositionGroundTruth,
    associate,
    check_trajectory,
    gap_per_step,
    gap_support,
    ground_truth_dof,
    ground_truth_rates,
    positions_as_poses,
    warn_gaps,
)
from rtsgt.evaluation.drift import (
    POSITION_DRIFT_DEFINITION,
    ROTATION_DRIFT_NOT_ESTIMABLE,
    Drift,
    drift_metrics,
    kitti_errors,
)
from rtsgt.evaluation.handeye import ODOMETRY_COMPONENTS, coarse_clock_shift
from rtsgt.evaluation.lever_arm import lever_arm_points, parse_lever_arm, point_covariance
from rtsgt.evaluation.metrics import (
    NeesResult,
    alignment_sensitivity,
    ape_errors,
    chain_cross_covariance,
    error_statistics,
    nees_test,
    no_pair_reason,
    noise_floor,
    pose_error,
    relative_pose_covariance,
    relative_pose_error_vector,
    remove_floor,
    rpe_errors,
    rpe_pairs,
    with_split_verdict,
)
from rtsgt.evaluation.mounting import (
    CLOCK_TOLERANCE_S,
    MountingFit,
    check_position_only,
    fit_mounting,
    mounting_sensitivity,
    prism_lever_arm,
)
from rtsgt.evaluation.options import EvaluationOptions
from rtsgt.evaluation.positions import align_step as align_points_step
from rtsgt.evaluation.positions import (
    check_position_alignment,
    lever_arm_shared,
    relative_position_covariance,
)
from rtsgt.evaluation.result import (
    EvaluationResult,
    NeesSection,
    NoiseFloor,
    PoseErrors,
    PositionEvaluationResult,
)
from rtsgt.geometry.so3 import exp_so3, hat, matrix_to_quat_xyzw, quat_xyzw_to_matrix
from rtsgt.types import PoseTrajectory, PositionTrajectory

__all__ = ["EvaluationOptions", "evaluate", "evaluate_positions", "gap_per_step"]

#: Ground-truth kinds :func:`evaluate` accepts: poses (6 dof) or positions (3 dof).
GroundTruth = (PoseTrajectory | GroundTruthQuery | ValidatedGroundTruth | PositionTrajectory
               | ValidatedPositionGroundTruth)


@dataclass(frozen=True)
class RelativeCovariance:
    """Covariance of the ground truth's relative poses of the RPE pairs: ``cov`` (K, 6, 6) in
    the frame of the ground-truth pose ``i`` of each pair ``(i, j)`` (of positions: (K, 3, 3),
    of their displacement); ``correlations``: where the cross-covariances of the two came from
    (``rpe_correlations``)."""

    cov: np.ndarray
    correlations: str


def associate_step(
    gt: GroundTruth,
    est: PoseTrajectory,
    options: EvaluationOptions,
    gt_measurement_times: ArrayLike | None,
    gt_cross_next: ArrayLike | None,
) -> tuple[Association, PoseTrajectory | PositionTrajectory]:
    """Check the inputs and pair each estimate pose with the ground truth at its offset time.

    Returns the association and the associated ground truth, checked (finite, unit
    quaternions, renormalised; for a discrete ground truth that check comes first); for a
    ground truth of positions (:func:`~rtsgt.evaluation.associate.ground_truth_dof` 3), its
    positions as a :class:`~rtsgt.types.PositionTrajectory`."""
    est = check_trajectory(est, "estimate")
    if ground_truth_dof(gt) == 3:
        assoc = associate(positions_as_poses(gt), est, time_offset=options.time_offset,
                          max_dt=options.max_dt, measurement_times=gt_measurement_times,
                          gt_cross_next=gt_cross_next)
        a = assoc.gt
        return assoc, PositionTrajectory(a.t, a.position, None if a.cov is None
                                         else a.cov[:, :3, :3], getattr(gt, "name", ""))
    if isinstance(gt, PoseTrajectory):
        gt = check_trajectory(gt, "ground-truth")
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
    return assoc, check_trajectory(assoc.gt, "ground-truth")


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
    rotation = getattr(g, "rotation", None)  # None: a ground truth of positions
    if rotation is None:
        check_position_only(options.estimate)
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
    d = 6 if rotation is not None else 3
    return fit_mounting(
        g.position, rotation, S, assoc.est.position, assoc.est.rotation,
        estimate=options.estimate, align=options.align, rotation=start.rotation,
        lever=start.lever, clock_offset=assoc.time_offset,
        gt_velocity=None if rates is None else rates.v,
        gt_angular_velocity=None if rates is None or d == 3 else rates.w,
        gt_rate_cov=None if rates is None or rates.cov is None else rates.cov[:, :d, :d],
        est_cov=assoc.est.cov, shared=L, odometry_levels=None if start.odometry is None
        else [start.odometry[c] for c in ODOMETRY_COMPONENTS],
    )


#: Associations of the clock's fixed point at most (:func:`mounting_step`).
MAX_CLOCK_ASSOCIATIONS = 10


def mounting_step(
    gt: GroundTruth,
    est: PoseTrajectory,
    options: EvaluationOptions,
    gt_measurement_times: ArrayLike | None,
    gt_cross_next: ArrayLike | None,
    start: MountingFit | None = None,
) -> tuple[MountingFit, Association, PoseTrajectory]:
    """Fit what ``options.estimate`` asks for jointly with the alignment, re-associating the ground
    truth at each new clock offset until the step is below ``CLOCK_TOLERANCE_S`` (at most
    :data:`MAX_CLOCK_ASSOCIATIONS` times, else a warning); returns the fit and the association.
    ``start``: the mounting to start from (default: ``options``'); against a ground truth of
    positions, the body frame is the tracked point's with the sensor's axes.
    """
    start = start or given_mounting(options) or MountingFit.given(
        clock_offset=options.time_offset)
    offset = options.time_offset
    clock = "clock" in options.estimate
    positions = ground_truth_dof(gt) == 3
    rate_gt = positions_as_poses(gt) if positions else gt
    if clock:  # the coarse search over +-1 s (rotation angles over 1 s correlated)
        assoc, g = associate_step(gt, est, options, gt_measurement_times, gt_cross_next)
        offset += (coarse_clock_shift(assoc.est.t, None, None, g.position, assoc.est.position)
                   if positions else
                   coarse_clock_shift(assoc.est.t, g.rotation, assoc.est.rotation))
    for _ in range(MAX_CLOCK_ASSOCIATIONS):
        assoc, g = associate_step(gt, est, dataclasses.replace(options, time_offset=offset),
                                  gt_measurement_times, gt_cross_next)
        rates = ground_truth_rates(rate_gt, assoc, measurement_times=gt_measurement_times) \
            if clock else None
        fit = _fit_at(gt, g, assoc, options, start, rates)
        if not clock:
            return fit, assoc, g
        start = dataclasses.replace(start, odometry=fit.odometry)  # the next levels start there
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
    mounting and clock (docs/evaluation.md#mounting-and-clock): dict ``ape_translation_m``,
    ``ape_rotation_deg``, ``rpe_translation_m``, ``rpe_rotation_deg`` (RPE None without pairs), or
    None when nothing was estimated. ``2 p`` vectorised evaluations (p <= 7).
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


def rpe_pair_step(g, e, options: EvaluationOptions) -> tuple[np.ndarray, str | None]:
    """evo's RPE pairs (K, 2) of the associated poses, from the aligned estimate ``e`` (the
    estimate's points against positions) or the ground truth ``g`` (``pairs_from_reference``),
    and, when there is none (K = 0), why and what to change."""
    source = g if options.pairs_from_reference else e
    pairs = rpe_pairs(
        source.position, source.t, options.delta, options.delta_unit,
        all_pairs=options.all_pairs, rel_tol=options.rel_delta_tol,
    )
    if pairs.shape[0]:
        return pairs, None
    return pairs, no_pair_reason(source.position, source.t, float(options.delta),
                                 options.delta_unit)


def compute_rpe(
    g: PoseTrajectory, e: PoseTrajectory, options: EvaluationOptions
) -> tuple[np.ndarray, PoseErrors | None, str | None]:
    """evo's RPE pairs (:func:`rpe_pair_step`), the relative pose errors (None without a
    pair) and, without a pair, why."""
    pairs, reason = rpe_pair_step(g, e, options)
    if reason is not None:
        return pairs, None, reason
    errs = rpe_errors(g.rotation, g.position, e.rotation, e.position, pairs)
    return pairs, PoseErrors.from_errors(errs, pairs), None


def error_covariance(g_cov: np.ndarray | None, e_cov: np.ndarray | None) -> np.ndarray | None:
    """``S_k`` of the NEES: the ground truth's covariance plus the estimate's when it has one;
    None when the ground truth has none."""
    if g_cov is None:
        return None
    return g_cov + (0.0 if e_cov is None else e_cov)


def relative_covariance(
    gt: GroundTruth, g: PoseTrajectory | PositionTrajectory, assoc: Association,
    pairs: np.ndarray
) -> RelativeCovariance:
    """Covariance of the ground truth's relative poses (displacements for positions) of the RPE
    ``pairs``: a :class:`~rtsgt.evaluation.associate.PairCovarianceGroundTruth`'s own pair model,
    else the association's chained ``cross_next``, else independent poses.
    """
    if isinstance(g, PositionTrajectory):
        return RelativeCovariance(*relative_position_covariance(gt, g, assoc, pairs))
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


def absolute_nees(xi: np.ndarray, S: np.ndarray, t: np.ndarray,
                  what: str = "") -> tuple[NeesResult, ...]:
    """NEES of the positions (3 dof) and, for pose errors, of the poses (6 dof): errors ``xi``
    (N, 6) or (N, 3) with covariances ``S`` (N, d, d) at times ``t`` (``what``: a prefix of
    the names in the messages)."""
    position = nees_test(xi[:, :3], S[:, :3, :3], 3, f"{what}position", t)
    if xi.shape[1] == 3:
        return (position,)
    return position, nees_test(xi, S, 6, f"{what}pose", t)


def split_nees(
    gt: GroundTruth,
    g: PoseTrajectory | PositionTrajectory,
    est_cov: np.ndarray | None,
    assoc: Association,
    xi: np.ndarray,
    absolute: tuple[NeesResult, ...],
    align: str,
    absorbed: np.ndarray | None = None,
    extra: tuple[np.ndarray, tuple[str, ...]] | None = None,
    *,
    upper: bool,
) -> tuple[NeesResult, ...]:
    """The absolute NEES with the split verdict when the ground truth gives its shared factor (on the
    ``d`` rows of ``xi`` (N, d); ``mean`` and ``fraction_inside_95`` stay the total's); unchanged
    otherwise. ``est_cov`` (N, d, d) the estimate's varying covariance; ``upper`` one-sided;
    ``absorbed`` (N, d, m) further fitted directions (mounting, clock); ``extra`` a further shared
    factor (N, d, k) with its names (an estimated lever arm).
    """
    if not isinstance(gt, SharedFactorGroundTruth):
        return absolute
    split = gt.shared_split(g.t + assoc.time_offset)
    if split is None:
        return absolute
    D = split.varying_cov + (0.0 if est_cov is None else est_cov)
    K = alignment_sensitivity(g.position, align)
    K = None if K is None else K[:, :xi.shape[1]]
    if absorbed is not None:
        K = absorbed if K is None else np.concatenate([K, absorbed], axis=2)
    factor, names = split.factor, split.names
    if extra is not None:
        factor, names = np.concatenate([factor, extra[0]], axis=2), (*names, *extra[1])
    try:
        return with_split_verdict(absolute, xi, D, factor, K, names=names, upper=upper)
    except ValueError as exc:
        raise InputError(f"Cannot test the errors against the shared factor: {exc}") from None


def nees_section(
    absolute: tuple[NeesResult, ...] | None,
    xi_rel: np.ndarray | None,
    relative: RelativeCovariance | None,
    t_rel: np.ndarray | None,
    estimate: str | None,
) -> NeesSection:
    """The NEES section: the absolute NEES (None without ground-truth covariances) and the
    relative NEES of the RPE pairs, errors ``xi_rel`` (K, d) at times ``t_rel`` against
    ``relative`` (None without pairs). ``estimate``: what of the estimate entered the
    absolute NEES (None: no covariance)."""
    if absolute is None:
        return NeesSection(
            None, None, None, None, "none: the ground truth has no covariance", "not applicable"
        )
    what = "ground truth" + ("" if estimate is None else f" + {estimate}")
    absolute = (*absolute, None)[:2]
    if relative is None:
        return NeesSection(*absolute, None, None, what, "not applicable (no RPE pair)")
    rel = absolute_nees(xi_rel, relative.cov, t_rel, "relative ")
    return NeesSection(
        *absolute,
        *(*rel, None)[:2],
        what + (" (relative: ground truth only)" if estimate is not None else ""),
        relative.correlations,
    )


def noise_floor_section(
    g: PoseTrajectory | PositionTrajectory,
    ape: PoseErrors,
    rpe: PoseErrors | None,
    relative: RelativeCovariance | None,
) -> NoiseFloor:
    """The errors a perfect estimate would show against this ground truth (APE: from the
    ground-truth covariances; RPE: from the relative covariance), and the rmse with that floor
    removed; None values without covariances (or, for the RPE, without pairs; the rotation's
    against positions)."""
    if g.cov is None:
        return NoiseFloor()
    rotation = g.cov.shape[-1] == 6
    f_t = noise_floor(g.cov[:, :3, :3])
    floor = NoiseFloor(f_t, remove_floor(ape.translation_m.rmse, f_t))
    if rotation:
        f_r = float(np.degrees(noise_floor(g.cov[:, 3:, 3:])))
        floor = dataclasses.replace(floor, ape_rotation_deg=f_r,
                                    ape_rotation_rmse_floor_removed_deg=remove_floor(
                                        ape.rotation_deg.rmse, f_r))
    if relative is None or rpe is None:
        return floor
    fr_t = noise_floor(relative.cov[:, :3, :3])
    floor = dataclasses.replace(
        floor, rpe_translation_m=fr_t,
        rpe_translation_rmse_floor_removed_m=remove_floor(rpe.translation_m.rmse, fr_t))
    if not rotation:
        return floor
    fr_r = float(np.degrees(noise_floor(relative.cov[:, 3:, 3:])))
    return dataclasses.replace(
        floor, rpe_rotation_deg=fr_r,
        rpe_rotation_rmse_floor_removed_deg=remove_floor(rpe.rotation_deg.rmse, fr_r))


def drift_step(gt: GroundTruth, g: PoseTrajectory | PositionTrajectory, assoc: Association,
               errors) -> Drift:
    """Drift by segment length (:func:`~rtsgt.evaluation.drift.drift_metrics`) of the segment
    errors ``errors(first, last)`` (the devkit's of poses; the norm of the displacement error
    of positions, whose rotational drift is not estimable), with the ground truth's floor from
    its relative covariance over the segments (:func:`relative_covariance`) when it has
    covariances."""

    def covariance(first: np.ndarray, last: np.ndarray) -> np.ndarray:
        return relative_covariance(gt, g, assoc, np.column_stack([first, last])).cov

    positions = {} if isinstance(g, PoseTrajectory) else {
        "rotation": ROTATION_DRIFT_NOT_ESTIMABLE, "definition": POSITION_DRIFT_DEFINITION}
    return drift_metrics(assoc.est.t, g.position, errors,
                         None if g.cov is None else covariance, **positions)


def evaluate(
    gt: GroundTruth,
    est: PoseTrajectory,
    options: EvaluationOptions | None = None,
    *,
    lever_arm: ArrayLike | str | None = None,
    lever_arm_cov: ArrayLike | None = None,
    lever_arm_source: str = "given",
    gt_measurement_times: ArrayLike | None = None,
    gt_cross_next: ArrayLike | None = None,
    **overrides,
) -> EvaluationResult | PositionEvaluationResult:
    """Evaluate an estimated trajectory against an (uncertain) ground truth of poses (6 dof) or of
    one tracked point's positions (3 dof); docs/evaluation.md.

    ``gt``: world frame, discrete (PoseTrajectory, PositionTrajectory), validated continuous
    (:mod:`rtsgt.evaluation.groundtruth`) or a query ``gt(times)``; covariances enable the NEES and
    the noise floor, its dof chooses the result. ``est``: own frame, increasing times, optional
    ``cov`` (N, 6, 6). ``options`` (or ``**overrides`` of its fields): alignment, RPE, offset,
    ``max_dt``, mounting. Positions only: ``lever_arm`` (3,) m or "x,y,z", its ``lever_arm_cov``
    (3, 3) m^2 and ``lever_arm_source``. ``gt_measurement_times`` and ``gt_cross_next`` as for
    :func:`~rtsgt.evaluation.associate.associate`. Returns an EvaluationResult or
    PositionEvaluationResult (``rpe`` None with ``rpe_absent_reason``); warns about RPE pairs over
    gaps; ExcitationError, InputError or GeometryError on what cannot be evaluated.
    """
    options = dataclasses.replace(
        EvaluationOptions() if options is None else options, **overrides
    )
    if ground_truth_dof(gt) == 3:
        return _evaluate_positions(gt, est, options, lever_arm, lever_arm_cov, lever_arm_source,
                                   gt_measurement_times)
    if lever_arm is not None or lever_arm_cov is not None:
        raise InputError("A lever arm is that of a ground truth of positions; a pose ground "
                         "truth takes the mounting (mounting=, estimate=)")
    return _evaluate_poses(gt, est, options, gt_measurement_times, gt_cross_next)


def _evaluate_poses(gt, est: PoseTrajectory, options: EvaluationOptions, gt_measurement_times,
                    gt_cross_next) -> EvaluationResult:
    """:func:`evaluate` against a ground truth of poses."""
    if options.estimate:
        fit, assoc, g = mounting_step(gt, est, options, gt_measurement_times, gt_cross_next)
    else:
        assoc, g = associate_step(gt, est, options, gt_measurement_times, gt_cross_next)
        fit = given_mounting(options)
    alignment, e = align_step(g, assoc, options, fit)
    ape = compute_ape(g, e)
    pairs, rpe, no_rpe = compute_rpe(g, e, options)
    if rpe is not None:
        warn_gaps(assoc, pairs, gap_support(gt, gt_measurement_times))
    xi = pose_error(g.rotation, g.position, e.rotation, e.position)
    S = error_covariance(g.cov, e.cov)
    rates = _mounting_rates(gt, assoc, fit, gt_measurement_times)
    absolute = None if S is None else absolute_nees(xi, S, g.t)
    if absolute is not None:
        absorbed = None
        if fit is not None and fit.estimated:
            absorbed = mounting_sensitivity(fit, e.rotation, *(
                (None, None) if rates is None else (rates.v, rates.w)))
        absolute = split_nees(gt, g, e.cov, assoc, xi, absolute, options.align, absorbed,
                              upper=e.cov is None)
    relative = None if S is None or rpe is None else relative_covariance(gt, g, assoc, pairs)
    xi_rel = None if relative is None else relative_pose_error_vector(
        g.rotation, g.position, e.rotation, e.position, pairs)

    def errors(first: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return kitti_errors(g.rotation, g.position, e.rotation, e.position, first, last)

    return EvaluationResult(
        t=assoc.est.t, gt=g, est=e, alignment=alignment, association=assoc, ape=ape, rpe=rpe,
        nees=nees_section(absolute, xi_rel, relative, g.t[pairs[:, 0]],
                          None if e.cov is None else "estimate"),
        noise_floor=noise_floor_section(g, ape, rpe, relative), pose_error=xi, cov_error=S,
        rpe_delta=float(options.delta), rpe_delta_unit=options.delta_unit,
        rpe_all_pairs=bool(options.all_pairs), rpe_absent_reason=no_rpe, mounting=fit,
        mounting_effect=mounting_effect(fit, g, assoc, options, rates, pairs),
        drift=drift_step(gt, g, assoc, errors),
    )


def _evaluate_positions(gt, est: PoseTrajectory, options: EvaluationOptions, lever_arm,
                        lever_arm_cov, lever_arm_source: str,
                        gt_measurement_times) -> PositionEvaluationResult:
    """:func:`evaluate` against a ground truth of positions: the estimate's points ``p_S +
    R_S l`` (:mod:`~rtsgt.evaluation.lever_arm`) take the place of its poses, their alignment
    is :func:`~rtsgt.evaluation.positions.align_step`'s; the rest of the chain is the poses'
    (docs/evaluation.md#position-only-ground-truth)."""
    check_position_alignment(options.align)
    if options.mounting is not None:
        raise InputError("A ground truth of positions gives no rotation to fit a mounting to "
                         "(mounting=): give the lever arm (estimate= lever, lever-xy, clock)")
    lever = parse_lever_arm(lever_arm)
    fit = None
    if options.estimate:  # the lever arm and the clock (docs/evaluating.md#a-drifting-odometry)
        fit = mounting_step(gt, est, options, gt_measurement_times, None,
                            MountingFit.given(np.eye(3), -lever, options.time_offset))[0]
        lever, lever_arm_cov = prism_lever_arm(fit)
        lever_arm_source = "estimated"
        options = dataclasses.replace(options, time_offset=fit.clock_offset)
    assoc, g = associate_step(gt, est, options, gt_measurement_times, None)
    alignment = align_points_step(g, assoc.est, lever, options)
    e = alignment.apply(assoc.est)
    pts = lever_arm_points(e.position, e.rotation, lever)
    own_cov = point_covariance(pts, e.cov)
    est_cov, shared = own_cov, None
    if lever_arm_cov is not None:
        shared = lever_arm_shared(pts, lever_arm_cov)
        marginal = shared[0] @ np.swapaxes(shared[0], 1, 2)
        est_cov = marginal if own_cov is None else own_cov + marginal
    err = pts.position - g.position
    ape = PoseErrors.of_positions(np.linalg.norm(err, axis=1))
    points = PositionTrajectory(e.t, pts.position, est_cov, "estimate")
    pairs, no_rpe = rpe_pair_step(g, points, options)
    rpe = None
    if no_rpe is None:
        warn_gaps(assoc, pairs, gap_support(gt, None))
        rpe = PoseErrors.of_positions(
            np.linalg.norm(err[pairs[:, 1]] - err[pairs[:, 0]], axis=1), pairs)
    S = error_covariance(g.cov, est_cov)
    absolute = None if S is None else split_nees(
        gt, g, own_cov, assoc, err, absolute_nees(err, S, g.t), options.align, extra=shared,
        upper=e.cov is None and shared is None)
    relative = None if S is None or rpe is None else relative_covariance(gt, g, assoc, pairs)
    d_err = err[pairs[:, 1]] - err[pairs[:, 0]]

    def errors(first: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, None]:
        return np.linalg.norm(err[last] - err[first], axis=1), None

    return PositionEvaluationResult(
        t=assoc.est.t, gt=g, est=points, est_poses=e, lever_arm=lever, alignment=alignment,
        association=assoc, ape=ape, rpe=rpe,
        nees=nees_section(absolute, d_err, relative, g.t[pairs[:, 0]],
                          None if est_cov is None else "estimate (through the lever arm)"),
        noise_floor=noise_floor_section(g, ape, rpe, relative), position_error=err,
        cov_error=S, rpe_delta=float(options.delta), rpe_delta_unit=options.delta_unit,
        rpe_all_pairs=bool(options.all_pairs), rpe_absent_reason=no_rpe,
        lever_arm_source=lever_arm_source,
        lever_arm_cov=None if lever_arm_cov is None else np.asarray(lever_arm_cov, float),
        drift=drift_step(gt, g, assoc, errors), mounting=fit)


def evaluate_positions(gt, est: PoseTrajectory, lever_arm=None,
                       options: EvaluationOptions | None = None,
                       **kwargs) -> PositionEvaluationResult:
    """:func:`evaluate` against a ground truth of positions, the lever arm third (the keyword
    arguments and overrides as :func:`evaluate`'s)."""
    if ground_truth_dof(gt) != 3:
        raise TypeError(f"Expected a ground truth of positions, got {type(gt).__name__}")
    return evaluate(gt, est, options, lever_arm=lever_arm, **kwargs)
