"""The ground-truth pipeline: the stages of a run, in order, timed, their warnings recorded.

The stages are in :mod:`rtsgt.stages` (module 1, calibration, noise model, module 2; the GPs;
the chain prisms -> poses -> gates with the refit without the windows of distance rejections;
the joint engine's poses after the per-prism ones, ``[pose] engine = "joint"``; the
self-checks; the shared errors and the record). This module holds no mathematics: it orders
them, once more from the GPs on where the static stretches find time-correlated noise
to inflate, and stops after the GPs for a deployment with fewer than three tracked prisms (a
:class:`~rtsgt.record.PositionRunRecord`). The order and its rules: docs/pipeline.md.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import replace

import numpy as np

from rtsgt.checks.static import static_stretches
from rtsgt.deployment import DeploymentData
from rtsgt.errors import RtsgtWarning
from rtsgt.evaluation.groundtruth import ContinuousGroundTruth
from rtsgt.evaluation.joint_truth import JointGroundTruth
from rtsgt.evaluation.static_poses import static_relative_check
from rtsgt.interpolation.prisms import gp_velocity_z2
from rtsgt.noise.correlated import inflate_tracks
from rtsgt.options import RunOptions
from rtsgt.record import MIN_POSE_PRISMS, PositionRunRecord, RunComputation, RunRecord
from rtsgt.stages.checks import run_checks, static_noise
from rtsgt.stages.front import (
    Front,
    calibrate_by_method,
    calibrate_stations,
    calibration_samples,
    noise_model,
    run_front,
)
from rtsgt.stages.joint import JointFit, joint_fit
from rtsgt.stages.poses import fit_to_gates
from rtsgt.stages.prisms import fit_prisms
from rtsgt.stages.records import pose_record, position_record, shared_errors
from rtsgt.stages.timing import Progress, Stopwatch, silent

# the front's calibration and noise model, as other commands (rtsgt calibrate, rtsgt plan) call
# them: their home is rtsgt.stages.front
__all__ = ["calibrate_by_method", "calibrate_stations", "calibration_samples", "noise_model",
           "run_pipeline"]


def run_pipeline(
    data: DeploymentData, options: RunOptions | None = None, progress: Progress | None = None
) -> RunRecord | PositionRunRecord:
    """Compute the ground truth of a deployment.

    ``progress`` is called with the name of each stage as it starts. Returns the run record
    (:mod:`rtsgt.record`; a :class:`~rtsgt.record.PositionRunRecord` for fewer than three
    tracked prisms) with its ``computation`` (what exists only in memory) and ``warnings``:
    every :class:`UserWarning` the stages raised, once each. They are recorded while the
    stages run and then issued again, once each, so that a caller (the CLI's ``warning: ...``
    lines) sees every one once, even if the run fails.
    """
    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")  # a second run must record what the first did
            result = _run_stages(data, RunOptions() if options is None else options,
                                 progress or silent)
    finally:
        said = _reissue(caught)
    return replace(result, warnings=tuple(said))


def _reissue(caught: list[warnings.WarningMessage]) -> list[str]:
    """Issue recorded warnings again, once each; the texts of the user warnings among them."""
    seen: set[tuple[type, str]] = set()
    said: list[str] = []
    for w in caught:
        key = (w.category, str(w.message))
        if key in seen:
            continue
        seen.add(key)
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
        if issubclass(w.category, UserWarning):
            said.append(str(w.message))
    return said


def _run_stages(data: DeploymentData, options: RunOptions,
                say: Progress) -> RunRecord | PositionRunRecord:
    """The stages of :func:`run_pipeline` (their warnings not yet recorded)."""
    clock = Stopwatch()
    front = run_front(data, options, say, clock)
    if len(data.observations) < MIN_POSE_PRISMS:
        return _position_stages(data, options, front, say, clock)
    return _pose_stages(data, options, front, say, clock)


def _inflated(stage: str) -> str:
    return f"{stage}, correlated noise inflated"


def _pose_stages(data: DeploymentData, options: RunOptions, front: Front, say: Progress,
                 clock: Stopwatch) -> RunRecord:
    """From module 2's tracks to the record of a run with poses."""
    reference = data.reference.select(list(front.tracks))
    fit = fit_to_gates(options, data.query_times, front.intervals, front.tracks,
                       front.coupling, reference, say)
    clock.timings.update(fit.timings)
    clock.restart()
    static, correlated = static_noise(options, front, fit.tracks, fit.groundtruth.t,
                                      fit.prisms.xyz[fit.keep], fit.gps, say, clock)
    if correlated["applied"]:
        start = time.perf_counter()
        fit = fit_to_gates(options, data.query_times, front.intervals,
                           inflate_tracks(front.tracks, front.origins, correlated),
                           front.coupling, reference, lambda stage: say(_inflated(stage)))
        clock.timings["correlated_noise"] = time.perf_counter() - start
        clock.restart()
    removed = front.removed
    if fit.window_report is not None:
        front.reports["module4"] = fit.window_report
        removed = front.removal.measurements([fit.left_out[o.prism] for o in front.filtered])
    joint = None
    if reference.stability > 0 and not options.joint:
        warnings.warn("[reference] prism_stability_mm: only the joint engine carries a prism's "
                      "move that no station sees; the per-prism engine takes the survey as "
                      "it is (docs/joint.md#what-no-station-sees)", RtsgtWarning, stacklevel=2)
    if options.joint:
        joint = joint_fit(options, front.filtered, front.calibration, front.model,
                          data.weather, fit, reference, say, data.gcp)
        fit = joint.fit
        clock.lap("joint")

    say("shared errors")
    split = shared_errors(options, front, fit, reference, joint)
    clock.lap("shared_errors")

    say("self-checks")
    self_checks = run_checks(options, front, static, fit, reference)
    if joint is not None:
        self_checks["raw_block_cv"] = joint.result.raw_block_cv
    clock.lap("self_checks")
    computation = RunComputation(data, front.calibration, front.model, front.reports,
                                 fit.tracks, fit.gps, fit.prisms, fit.estimate, fit.keep,
                                 fit.gate_report, clock.timings, fit.qc_info,
                                 None if joint is None else joint.result)
    record = pose_record(options, computation, front, fit, removed, self_checks, split,
                         correlated, joint)
    say("self-check: relative poses on the static stretches")
    record = _static_relative(record, joint)
    clock.lap("static_relative")
    return record


def _static_relative(record: RunRecord, joint: JointFit | None) -> RunRecord:
    """The record with its static relative-pose check (``self_checks.static_relative``), on
    the static stretches of its kept poses, from the continuous ground truth of its GPs or of
    the joint engine's knots."""
    c = record.computation
    gt = record.groundtruth
    stretches = static_stretches(gt.t, c.prisms.xyz[c.keep], gp_velocity_z2(c.gps, gt.t))
    # the linear engine's poses: the check's covariances are its first-order model anyway
    truth = (ContinuousGroundTruth.from_record(record, engine="linear") if joint is None
             else JointGroundTruth(joint.result.posterior))
    check = static_relative_check(truth, stretches)
    return replace(record, self_checks={**record.self_checks, "static_relative": check})


def _position_stages(data: DeploymentData, options: RunOptions, front: Front, say: Progress,
                     clock: Stopwatch) -> PositionRunRecord:
    """A run with fewer than :data:`~rtsgt.record.MIN_POSE_PRISMS` tracked prisms: each
    prism's GP at the query times, the static-stretch check (and the inflation of
    time-correlated noise, as in a pose run), the block cross-validation and the GCP fit; no
    pose, no gate, no inter-prism check."""
    clock.restart()
    fit = fit_prisms(options, data.query_times, front.intervals, front.tracks, front.coupling,
                     say)
    clock.lap("interpolation")
    static, correlated = static_noise(options, front, fit.tracks, fit.prisms.t, fit.prisms.xyz,
                                      fit.gps, say, clock)
    if correlated["applied"]:
        fit = fit_prisms(options, data.query_times, front.intervals,
                         inflate_tracks(front.tracks, front.origins, correlated),
                         front.coupling, lambda stage: say(_inflated(stage)))
        clock.lap("correlated_noise")
    say("self-checks")
    self_checks = run_checks(options, front, static, fit)
    clock.lap("self_checks")
    computation = RunComputation(data, front.calibration, front.model, front.reports,
                                 fit.tracks, fit.gps, fit.prisms, None,
                                 np.ones(fit.prisms.t.shape, bool), None, clock.timings,
                                 fit.qc_info)
    return position_record(options, computation, front, fit, self_checks, correlated)
