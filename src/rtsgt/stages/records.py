"""The last stages of a run: the kept poses' shared errors, and the run record of what the
stages computed (:mod:`rtsgt.record`). docs/honesty.md, docs/file-formats.md#run-directory.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rtsgt.calibration import CalibrationResult
from rtsgt.interpolation.prisms import gp_covariance, gp_velocities
from rtsgt.options import RunOptions
from rtsgt.pose import ReferencePoints
from rtsgt.record import PositionRunRecord, RunComputation, RunRecord, ordered_sources
from rtsgt.shared import SharedFactor, select_prisms, split_ground_truth
from rtsgt.stages.front import Front
from rtsgt.stages.joint import JointFit, joint_split, joint_summary
from rtsgt.stages.poses import PoseFit
from rtsgt.stages.prisms import PrismFit
from rtsgt.types import PrismTrack

__all__ = ["measured_tracks", "pose_record", "position_record", "shared_errors"]


def shared_errors(options: RunOptions, front: Front, fit: PoseFit,
                  reference: ReferencePoints, joint: JointFit | None = None
                  ) -> SharedFactor | None:
    """The kept poses' error split into varying and shared parts (:mod:`rtsgt.shared`); None
    when the GP was given the total covariance (``gp_noise = "all"``: no separate shared
    sources). For the ``joint`` engine, its own split (:func:`rtsgt.stages.joint.joint_split`)."""
    if joint is not None:
        return joint_split(joint)
    if options.interpolation.gp_noise != "white":
        return None
    idx = np.flatnonzero(fit.keep)
    kept = select_prisms(fit.prisms, idx)
    velocity = gp_velocities({p: fit.gps[p] for p in fit.tracks}, kept.t)
    return split_ground_truth(
        kept, velocity, [fit.tracks[p].station for p in fit.tracks], front.origins,
        front.coupling, reference, fit.estimate.R[idx], registration=options.pose.registration)


def measured_tracks(tracks: dict[str, PrismTrack], calib: CalibrationResult,
                    options: RunOptions) -> tuple[dict[str, PrismTrack], dict[str, np.ndarray]]:
    """The measured tracks as a record keeps them (``cov``: the sum of the per-source
    covariances; the range from the station where the track has none) and the covariance
    each GP was given (N, 3, 3) by prism."""
    stations = {s: np.asarray(T.translation, dtype=float) for s, T in calib.transforms.items()}
    measurements = {}
    for pid, tr in tracks.items():
        rng_m = tr.range_m
        if rng_m is None and tr.station in stations:
            rng_m = np.linalg.norm(tr.xyz - stations[tr.station], axis=1)
        cov = np.sum(list(tr.cov_by_source.values()), axis=0) if tr.cov_by_source else tr.cov
        measurements[pid] = PrismTrack(tr.t, tr.xyz, cov, tr.cov_by_source, pid, tr.frame,
                                       tr.station, rng_m)
    gp_cov = {pid: gp_covariance(tr, options.interpolation.gp_noise)
              for pid, tr in tracks.items()}
    return measurements, gp_cov


def _common(options: RunOptions, front: Front, fit: PoseFit | PrismFit) -> dict[str, Any]:
    """The fields both kinds of record have, from the front and the fit that stands."""
    measurements, gp_cov = measured_tracks(fit.tracks, front.calibration, options)
    pr, gps = fit.prisms, fit.gps
    gcp_names = tuple(front.gcp_world)
    return dict(
        prism_ids=tuple(fit.tracks), measurements=measurements,
        prisms_t=pr.t, prisms_xyz=pr.xyz, prisms_cov=pr.cov,
        prisms_cov_by_source={s: pr.cov_by_source[s] for s in ordered_sources(pr.cov_by_source)},
        prisms_cov_gp=pr.cov_gp, options=options, stations=front.origins,
        gcp_xyz=np.array([front.gcp_world[n] for n in gcp_names]) if gcp_names else None,
        gcp_names=gcp_names, qc={pid: np.asarray(g.qc) for pid, g in gps.items()},
        qc_scale={pid: np.asarray(g.qc_scale) for pid, g in gps.items()
                  if g.qc_scale is not None}, prior={pid: g.prior for pid, g in gps.items()},
        intervals=front.intervals, coupling=front.coupling, measurements_gp_cov=gp_cov,
        weather_coverage=front.weather_coverage)


def pose_record(options: RunOptions, c: RunComputation, front: Front, fit: PoseFit,
                removed: Any, self_checks: dict, split: SharedFactor | None,
                correlated: dict, joint: JointFit | None = None) -> RunRecord:
    """The run record of a pose run (the prisms in the order of the tracks): ``c`` what exists
    only in memory, ``removed`` the measurements modules 1, 2 and 4 removed, ``joint`` the
    joint engine's fit (its summary in :attr:`~rtsgt.record.RunRecord.joint`)."""
    reject = ~fit.keep
    return RunRecord(
        name=c.data.name, **_common(options, front, fit), groundtruth=fit.groundtruth,
        rejected_t=fit.prisms.t[reject],
        rejected_reason=np.asarray(fit.gate_report.reason, dtype=str)[reject],
        reference=c.data.reference, uncertainty_measure=fit.gate_report.uncertainty_measure,
        removed=removed, distance_check=fit.distance_check, self_checks=self_checks,
        computation=c, groundtruth_split=split, correlated_noise=correlated,
        joint={} if joint is None else joint_summary(joint.result, front.calibration))


def position_record(options: RunOptions, c: RunComputation, front: Front, fit: PrismFit,
                    self_checks: dict, correlated: dict) -> PositionRunRecord:
    """The run record of a position-only run (fewer than
    :data:`~rtsgt.record.MIN_POSE_PRISMS` tracked prisms)."""
    return PositionRunRecord(
        name=c.data.name, **_common(options, front, fit), removed=front.removed,
        self_checks=self_checks, correlated_noise=correlated, computation=c)
