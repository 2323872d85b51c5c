"""The ground-truth pipeline: from a deployment's data to poses with covariance.

Stages (data flows one way; nothing here reads files or prints)::

    observations per station --module 1--> filtered observations
    GCP shots --> extrinsic calibration (+ Monte Carlo samples of every station transform)
      (or: filtered observations in the stations' frames --module 2, GP per prism--> the
      inter-prism distances --> dynamic calibration, with or without the GCP shots)
    filtered observations + calibration + weather --noise model--> prism tracks (world frame)
    prism tracks --module 2--> common intervals --GP per prism--> prisms at the query times
    prisms + reference prisms on the robot --registration--> poses with 6x6 covariance
    poses --module 4 gates--> kept poses
    (poses off the survey's distances --> their measurements out of the GPs --> GP again ...)

How the noise sources enter the GP
----------------------------------
The GP treats measurement noise as independent from one measurement to the next. That is true
of the instrument and tilt-compensator errors ("white" sources), but not of the others: the
extrinsic calibration error is one draw for the whole deployment, a station's clock offset is
constant, and the atmospheric error changes over hours. Feeding those into the GP as if they
were independent would let the smoother average them away over many measurements and report
an over-confident track. rtsgt therefore fits the GP with the white covariance only and adds
the covariance of the *systematic* sources (interpolated at the query time from the
neighbouring measurements) to the interpolated position afterwards. ``gp_noise="all"``
reproduces the paper, which fed the total covariance to the GP.

Qc is chosen by leave-one-out cross-validation per axis (:mod:`rtsgt.interpolation.loo`):
the ground truth is an interpolation, and the marginal likelihood, which scores predictions,
overstates its error.

Qc is fitted on the measurements the gates keep: the measurements inside the windows of the
poses that the distance gate rejects (a station tracking another prism) are left out of the
GP fits, which are fitted again (:mod:`rtsgt.filtering.gates`; ``outlier_windows = "keep"``
keeps them, as the paper did). A run without such a pose is not touched.

Time-correlated measurement noise
---------------------------------
The static-stretch self-check (:mod:`rtsgt.checks.static`) needs the poses (the robot's
standing stretches come from them), so it runs on the first fit. Where it finds a prism's
noise correlated in time (a component whose lag-one correlation is ``optimistic``), the white
covariance of that component is inflated by the loss of independent samples
(:mod:`rtsgt.noise.correlated`) and everything from the GPs to the gates (the Qc search and
the refits without the outlier windows included) is done once more on the inflated tracks;
the other self-checks judge that final run. The static check reported stays the one on the
measurements as given: what the data say about the noise model. ``correlated_noise =
"ignore"`` (the paper) keeps the first fit; where nothing is found, both are the same run.

Errors shared between prisms
----------------------------
Two stations calibrated from the same reference shots have correlated calibration errors
(:class:`StationCoupling`); the pose engines get the joint (3n x 3n) covariance of the prisms
(:func:`joint_prism_covariance`), since errors that move the prisms together are not averaged
out by the registration. On simulated deployments this took the position NEES / dof from
1.15-1.25 to 1.11-1.12 (docs/honesty.md#simulated-deployments).

Fewer than three prisms
-----------------------
A pose needs three tracked prisms. With one or two (a deployment of one or two stations,
:data:`rtsgt.record.MIN_POSE_PRISMS`) the run stops after the GPs: each prism's positions at
the query times with their covariance (GP posterior plus the systematic sources), the
static-stretch check (and the inflation of time-correlated noise it may call for), the block
cross-validation and the GCP fit; no pose, no gate, no inter-prism check. It returns a
:class:`~rtsgt.record.PositionRunRecord`, the position-only ground truth of
:mod:`rtsgt.evaluation.positions`.

Checks that warn
----------------
A run says what it cannot vouch for as :class:`~rtsgt.errors.RtsgtWarning` (recorded in
:attr:`rtsgt.record.RunRecord.warnings`, hence ``summary.json``): a weather record that does not cover the
measurement times (:func:`rtsgt.measurement.weather.check_weather_coverage`), a surveyed inter-prism
distance that the tracked distances disagree with beyond its predicted sigma
(:func:`rtsgt.filtering.gates.surveyed_distance_check`), rate gates that reject motion.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import fields, replace
from typing import NamedTuple

import numpy as np

from rtsgt.calibration import CalibrationResult, calibrate
from rtsgt.calibration.dynamic import (
    SAMPLE_STEP_S,
    DistanceSamples,
    calibrate_dynamic,
    distance_samples,
    sample_times,
)
from rtsgt.calibration.gcp import gcp_atmospheric_correction, gcp_world_positions
from rtsgt.checks import (
    block_cv_check,
    dynamic_calibration_check,
    gcp_fit_check,
    inter_prism_check,
    run_structure_check,
    static_noise_check,
    static_stretches,
)
from rtsgt.deployment import DeploymentData
from rtsgt.errors import GeometryError, InputError, RtsgtWarning
from rtsgt.filtering import module1, module2
from rtsgt.filtering.gates import (
    MAX_OUTLIER_REFITS,
    REASON_DISTANCE_WINDOW,
    GateReport,
    OutlierWindowReport,
    apply_gates,
    distance_outliers,
    in_windows,
    outlier_windows,
    prism_distances,
    surveyed_distance_check,
)
from rtsgt.filtering.modules import RemovedMeasurements, removed_measurements, warn_tight_rate_gates
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.interpolation import GPTrack
from rtsgt.interpolation.prisms import (
    PrismsAtTimes,
    fit_gps,
    gp_covariance,
    gp_velocities,
    query_grid,
    query_prisms,
)
from rtsgt.measurement.weather import check_weather_coverage
from rtsgt.noise import NoiseModel, propagate
from rtsgt.noise.correlated import correlated_noise_plan, inflate_tracks
from rtsgt.noise.coupling import StationCoupling
from rtsgt.options import RunOptions, stage_rng
from rtsgt.pose import PoseEstimate, ReferencePoints, estimate_poses
from rtsgt.record import (
    MIN_POSE_PRISMS,
    PositionRunRecord,
    RunComputation,
    RunRecord,
    ordered_sources,
)
from rtsgt.shared import SharedFactor, select_prisms, split_ground_truth
from rtsgt.types import Observations, PoseTrajectory, PrismTrack

Progress = Callable[[str], None]


def run_pipeline(
    data: DeploymentData, options: RunOptions | None = None, progress: Progress | None = None
) -> RunRecord | PositionRunRecord:
    """Compute the ground truth of a deployment.

    Parameters
    ----------
    data : DeploymentData
    options : RunOptions, optional
    progress : callable, optional
        Called with the name of each stage as it starts (for progress displays).

    Returns
    -------
    RunRecord or PositionRunRecord
        The run record (:mod:`rtsgt.record`; a :class:`~rtsgt.record.PositionRunRecord` for a
        deployment with fewer than three tracked prisms, module docstring), with :attr:`~rtsgt.record.RunRecord.computation`
        (what only exists in memory) and :attr:`~rtsgt.record.RunRecord.warnings`: every :class:`UserWarning` (the
        :class:`~rtsgt.errors.RtsgtWarning` of the checks included) the stages raised, once
        each. They are recorded while the stages run and then issued again, once each, so a
        caller (the CLI's ``warning: ...`` lines) sees every one once, even if the run fails.
    """
    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")  # a second run must record what the first did
            result = _run_stages(data, options, progress)
    finally:
        said = _reissue(caught)
    return replace(result, warnings=tuple(said))


def noise_model(data: DeploymentData, options: RunOptions) -> NoiseModel:
    """The noise model of a run: the options' one, or every source with the deployment's
    instrument."""
    return options.noise if options.noise is not None else NoiseModel(instrument=data.instrument)


def calibrate_stations(data: DeploymentData, options: RunOptions,
                       t_start: float) -> CalibrationResult:
    """The extrinsic calibration of a run (its own random stream, ``"calibration"``): the GCP
    shots with the atmospheric correction (the weather at ``t_start``, the start of tracking,
    for shots outside the weather series), fitted by :func:`rtsgt.calibration.calibrate`.
    ``rtsgt plan`` calls it to get the very calibration a run of the deployment gets."""
    gcp = gcp_atmospheric_correction(data.gcp, noise_model(data, options), data.weather, t_start)
    return calibrate(gcp, reference_station=data.reference_station,
                     instrument=data.instrument, samples=options.pose.samples,
                     rng=stage_rng(options.seed, "calibration"),
                     model=options.calibration.model,
                     weighting=options.calibration.weighting)


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


class _Front(NamedTuple):
    """What the stages before the GPs compute (module 1 to module 2), for either kind of run."""

    reports: dict[str, object]
    weather_coverage: dict | None
    model: NoiseModel
    calib: CalibrationResult
    gcp_world: dict[str, np.ndarray]
    tracks: dict[str, PrismTrack]
    intervals: np.ndarray
    removal: tuple
    removed: RemovedMeasurements
    filtered: list
    #: the GCP calibration beside a dynamic or joint one (:func:`calibrate_by_method`), or None
    gcp_calib: CalibrationResult | None


def _front(data: DeploymentData, options: RunOptions, say: Progress,
           lap: Callable[[str], None]) -> _Front:
    """Module 1, the calibration, the noise model and module 2 (the stages of every run)."""
    say("filtering (module 1)")
    fparams = options.filter
    filtered, reports, reports1 = [], {}, []
    if data.input_report is not None:  # what the reader removed (a bag's statuses)
        reports["input"] = data.input_report
    for obs in data.observations:
        kept, rep = module1(obs, fparams)
        if len(kept) < 2:
            raise InputError(
                f"station {obs.station}: fewer than 2 measurements left after module 1", obs.source
            )
        filtered.append(kept)
        reports[f"module1_station{obs.station}"] = rep
        reports1.append(rep)
        warn_tight_rate_gates(obs, rep, fparams)
    weather_coverage = None if data.weather is None else check_weather_coverage(
        data.weather, np.concatenate([o.t for o in filtered]))
    lap("filter_module1")

    say("extrinsic calibration")
    model = noise_model(data, options)
    calib, gcp_calib = calibrate_by_method(data, options, filtered)
    gcp_xyz, gcp_names = gcp_world_positions(data.gcp, calib.transforms)
    gcp_world = {} if gcp_xyz is None else dict(zip(gcp_names, gcp_xyz, strict=True))
    lap("calibration")

    say("noise model")
    tracks: dict[str, PrismTrack] = {}
    noise_rng = stage_rng(options.seed, "noise")
    for obs in filtered:
        if obs.station not in calib.transforms:
            raise InputError(
                f"station {obs.station} tracks prism {obs.prism} but has no GCP calibration; "
                f"calibrated stations: {', '.join(sorted(calib.transforms))}", obs.source
            )
        tracks[obs.prism] = propagate(
            obs, model, T_world_station=calib.transforms[obs.station], weather=data.weather,
            engine=options.noise_engine, samples=options.pose.samples, rng=noise_rng,
        )
    lap("noise_model")

    say("common intervals (module 2)")
    kept_tracks, intervals, rep2 = module2(list(tracks.values()), fparams)
    reports["module2"] = rep2
    # module 2's masks per prism (one prism per station), indexed like module 1's kept
    kept2 = dict(zip(tracks, zip(rep2.kept_masks, rep2.reasons, strict=True), strict=True))
    removal = (data.observations, reports1, [kept2[o.prism][0] for o in filtered],
               [kept2[o.prism][1] for o in filtered], calib.transforms)
    removed = removed_measurements(*removal)
    tracks = {tr.prism: tr for tr in kept_tracks}
    lap("filter_module2")
    return _Front(reports, weather_coverage, model, calib, gcp_world, tracks, intervals,
                  removal, removed, filtered, gcp_calib)


def _run_stages(
    data: DeploymentData, options: RunOptions | None, progress: Progress | None
) -> RunRecord | PositionRunRecord:
    """The stages of :func:`run_pipeline` (their warnings not yet recorded)."""
    options = RunOptions() if options is None else options
    say = progress or (lambda stage: None)
    timings: dict[str, float] = {}
    tick = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal tick
        now = time.perf_counter()
        timings[name] = now - tick
        tick = now

    front = _front(data, options, say, lap)
    if len(data.observations) < MIN_POSE_PRISMS:
        return _position_stages(data, options, front, say, timings)
    reports, weather_coverage, model, calib, gcp_world = front[:5]
    tracks, intervals, removal, removed, filtered, gcp_calib = front[5:]

    coupling = StationCoupling.from_calibration(calib)
    reference = data.reference.select(list(tracks))
    origins = {s: np.asarray(T.translation, dtype=float) for s, T in calib.transforms.items()}
    fit = _fit_to_gates(options, data.query_times, intervals, tracks, coupling, reference, say)
    timings.update(fit.timings)
    tick = time.perf_counter()

    # the noise on the static stretches, with the measurements taken as independent: what
    # the data say about the noise model; where it wanders, the white covariance is inflated
    # and the GPs fitted again (rtsgt.noise.correlated)
    say("self-check: static stretches")
    static = static_noise_check(fit.tracks, origins,
                                static_stretches(fit.groundtruth.t, fit.prisms.xyz[fit.keep]))
    correlated = correlated_noise_plan(
        static, tracks, apply=options.interpolation.correlated_noise == "inflate")
    lap("static_noise")
    if correlated["applied"]:
        start = time.perf_counter()
        fit = _fit_to_gates(options, data.query_times, intervals,
                            inflate_tracks(tracks, origins, correlated), coupling, reference,
                            lambda stage: say(f"{stage}, correlated noise inflated"))
        timings["correlated_noise"] = time.perf_counter() - start
        tick = time.perf_counter()
    tracks, gps, qc_info, prisms, est, keep, gt = (
        fit.tracks, fit.gps, fit.qc_info, fit.prisms, fit.estimate, fit.keep, fit.groundtruth)
    if fit.outliers is not None:
        masks, reports["module4"] = fit.outliers
        removed = removed_measurements(*removal, [masks[o.prism] for o in filtered])

    say("shared errors")
    split = _split(options, prisms, gps, tracks, calib, coupling, reference, est, keep)
    lap("shared_errors")

    say("self-checks")
    self_checks = {"gcp_fit": gcp_fit_check(calib if gcp_calib is None else gcp_calib),
                   "inter_prism_distances": inter_prism_check(
        gt.t, gt.position, prisms.xyz[keep], prisms.pose_covariance[keep],
        prisms.nearest_dt[keep], reference.xyz, reference.cov, reference.names,
        varying_cov=prisms.cov_gp[keep]),
        "block_cv": block_cv_check(tracks, gps, gp_noise=options.interpolation.gp_noise,
                                   max_gap_s=options.interpolation.max_gap_s),
        "static_noise": static}
    if calib.dynamic is not None:
        self_checks["dynamic_calibration"] = dynamic_calibration_check(calib, gcp_calib)
    self_checks["inter_prism_structure"] = run_structure_check(
        prisms, gps, tracks, calib, coupling, reference, keep, model,
        options.interpolation.gp_noise)
    lap("self_checks")
    computation = RunComputation(data, calib, model, reports, tracks, gps, prisms, est, keep,
                                 fit.gate_report, timings, qc_info)
    record = _record(computation, options, intervals, coupling, removed, gt, gcp_world,
                     weather_coverage, fit.distance_check, self_checks)
    return replace(record, groundtruth_split=split, correlated_noise=correlated)


# ------------------------------------------------------------------------------------------
# a run with one or two tracked prisms: positions, no pose
# ------------------------------------------------------------------------------------------


class _PositionFit(NamedTuple):
    """The GPs of the tracks and the prisms at the query times (a position-only run)."""

    tracks: dict[str, PrismTrack]
    gps: dict[str, GPTrack]
    qc_info: dict[str, dict]
    prisms: PrismsAtTimes


def _query_times(query_times: np.ndarray | None, intervals: np.ndarray, rate_hz: float,
                 gps: dict[str, GPTrack]) -> np.ndarray:
    """The query times of a run: the given ones inside the common intervals, else the grid;
    those across a gap of some GP (longer than ``max_gap_s``) left out."""
    if query_times is not None:
        t_query = np.asarray(query_times, dtype=float)
        inside = np.zeros(t_query.shape, bool)
        for a, b in intervals:
            inside |= (t_query >= a) & (t_query <= b)
        t_query = t_query[inside]
    else:
        t_query = query_grid(intervals, rate_hz)
    ok = np.ones(t_query.shape, bool)
    for g in gps.values():
        ok &= g.supported(t_query)
    t_query = t_query[ok]
    if t_query.size == 0:
        raise InputError("No query time falls inside the intervals common to all prisms")
    return t_query


def _fit_positions(options: RunOptions, query_times: np.ndarray | None, intervals: np.ndarray,
                   tracks: dict[str, PrismTrack], coupling: StationCoupling,
                   say: Progress) -> _PositionFit:
    """The GPs (Qc search included) and the prisms at the query times."""
    say("GP interpolation")
    qc_info: dict[str, dict] = {}
    gps = fit_gps(tracks, options.interpolation, info=qc_info)
    t_query = _query_times(query_times, intervals, options.interpolation.rate_hz, gps)
    prisms = query_prisms(tracks, gps, t_query, options.interpolation, coupling)
    return _PositionFit(tracks, gps, qc_info, prisms)


def _position_stages(data: DeploymentData, options: RunOptions, front: _Front,
                     say: Progress, timings: dict[str, float]) -> PositionRunRecord:
    """A run with fewer than :data:`~rtsgt.record.MIN_POSE_PRISMS` tracked prisms: each
    prism's GP at the query times (positions with covariance), the static-stretch check (and
    the inflation of time-correlated noise, as in a pose run), the block cross-validation and
    the GCP fit; no pose, no gate, no inter-prism check."""
    tick = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal tick
        now = time.perf_counter()
        timings[name] = now - tick
        tick = now

    calib, tracks = front.calib, front.tracks
    coupling = StationCoupling.from_calibration(calib)
    origins = {s: np.asarray(T.translation, dtype=float) for s, T in calib.transforms.items()}
    fit = _fit_positions(options, data.query_times, front.intervals, tracks, coupling, say)
    lap("interpolation")
    say("self-check: static stretches")
    static = static_noise_check(fit.tracks, origins,
                                static_stretches(fit.prisms.t, fit.prisms.xyz))
    correlated = correlated_noise_plan(
        static, tracks, apply=options.interpolation.correlated_noise == "inflate")
    lap("static_noise")
    if correlated["applied"]:
        fit = _fit_positions(options, data.query_times, front.intervals,
                             inflate_tracks(tracks, origins, correlated), coupling,
                             lambda stage: say(f"{stage}, correlated noise inflated"))
        lap("correlated_noise")
    say("self-checks")
    self_checks = {"gcp_fit": gcp_fit_check(calib if front.gcp_calib is None
                                            else front.gcp_calib),
                   "block_cv": block_cv_check(fit.tracks, fit.gps,
                                              gp_noise=options.interpolation.gp_noise,
                                              max_gap_s=options.interpolation.max_gap_s),
                   "static_noise": static}
    lap("self_checks")
    pr = fit.prisms
    computation = RunComputation(data, calib, front.model, front.reports, fit.tracks, fit.gps,
                                 pr, None, np.ones(pr.t.shape, bool), None, timings,
                                 fit.qc_info)
    measurements, gp_cov = _measurements(fit.tracks, calib, options)
    gcp_names = tuple(front.gcp_world)
    return PositionRunRecord(
        name=data.name, prism_ids=tuple(fit.tracks), measurements=measurements,
        prisms_t=pr.t, prisms_xyz=pr.xyz, prisms_cov=pr.cov,
        prisms_cov_by_source={s: pr.cov_by_source[s] for s in ordered_sources(pr.cov_by_source)},
        prisms_cov_gp=pr.cov_gp, options=options,
        stations={s: np.asarray(T.translation, dtype=float)
                  for s, T in calib.transforms.items()},
        gcp_xyz=np.array([front.gcp_world[n] for n in gcp_names]) if gcp_names else None,
        gcp_names=gcp_names, qc={pid: np.asarray(g.qc) for pid, g in fit.gps.items()},
        qc_scale={pid: np.asarray(g.qc_scale) for pid, g in fit.gps.items()
                  if g.qc_scale is not None}, prior={pid: g.prior for pid, g in fit.gps.items()},
        intervals=front.intervals, coupling=coupling, removed=front.removed,
        measurements_gp_cov=gp_cov, weather_coverage=front.weather_coverage,
        self_checks=self_checks, correlated_noise=correlated, computation=computation)


def _measurements(tracks: dict[str, PrismTrack], calib: CalibrationResult,
                  options: RunOptions) -> tuple[dict[str, PrismTrack], dict[str, np.ndarray]]:
    """The measured tracks as a record keeps them (``cov``: the sum of the per-source
    covariances; the range from the station where the track has none) and the covariance
    each GP was given."""
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


class _Fit(NamedTuple):
    """What :func:`_fit_to_gates` computes from the tracks."""

    tracks: dict[str, PrismTrack]
    gps: dict[str, GPTrack]
    qc_info: dict[str, dict]
    prisms: PrismsAtTimes
    estimate: PoseEstimate
    keep: np.ndarray
    gate_report: GateReport
    groundtruth: PoseTrajectory
    distance_check: dict
    #: The measurements left out of the GPs per prism and module 4's report, or None.
    outliers: tuple[dict[str, np.ndarray], OutlierWindowReport] | None
    timings: dict[str, float]


def _fit_to_gates(options: RunOptions, query_times: np.ndarray | None, intervals: np.ndarray,
                  tracks: dict[str, PrismTrack], coupling: StationCoupling,
                  reference: ReferencePoints, say: Progress) -> _Fit:
    """The GPs of the tracks (Qc search included), the prisms at the query times, the poses
    and module 4's gates, with the GPs fitted again without the windows of distance
    rejections (``outlier_windows = "remove"``); ``tracks`` are those the gates' windows
    leave measurements out of (``outliers``). ``timings`` has the stages ``interpolation``,
    ``pose``, ``gates`` and, where the windows were refitted, ``outlier_windows``, s."""
    timings: dict[str, float] = {}
    tick = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal tick
        now = time.perf_counter()
        timings[name] = now - tick
        tick = now

    say("GP interpolation")
    qc_info: dict[str, dict] = {}
    gps = fit_gps(tracks, options.interpolation, info=qc_info)
    # queries across a gap longer than max_gap_s in any prism are not poses we can vouch for
    t_query = _query_times(query_times, intervals, options.interpolation.rate_hz, gps)
    prisms = query_prisms(tracks, gps, t_query, options.interpolation, coupling)
    lap("interpolation")

    say("poses")
    # the poses the distance gate will reject, from the prisms alone: when their windows are
    # refitted, only they keep this fit's poses, and the others are estimated once, from the
    # fit that stands (_refit_outlier_windows)
    flagged = distance_outliers(prism_distances(prisms.xyz), reference,
                                options.pose.distance_gate_m)
    refit_due = (options.interpolation.outlier_windows == "remove" and bool(flagged.any())
                 and not flagged.all())
    est = _poses(options, reference, _take(prisms, flagged) if refit_due else prisms)
    lap("pose")

    say("quality gates (module 4)")
    outliers = None
    if refit_due:
        start = time.perf_counter()
        refit = _refit_outlier_windows(options, tracks, prisms, flagged, est, reference,
                                       coupling, say)
        if refit is None:  # the refit failed: this fit stands, every pose of it
            est = _poses(options, reference, prisms)
        else:
            tracks, gps, qc_info, prisms, est, keep, gate_report, masks, report = refit
            t_query = prisms.t
            outliers = (masks, report)
        timings["outlier_windows"] = time.perf_counter() - start
        tick += timings["outlier_windows"]  # its own stage, not counted in "gates"
    if outliers is None:
        keep, gate_report = apply_gates(
            est, reference, distance_gate_m=options.pose.distance_gate_m,
            uncertainty_gate_m=options.pose.uncertainty_gate_m,
        )
    gt = PoseTrajectory(
        t_query[keep], est.t[keep], matrix_to_quat_xyzw(est.R[keep]), est.cov[keep]
    )
    # a surveyed distance the tracking disagrees with biases every pose: say so
    distance_check = surveyed_distance_check(
        prisms.xyz[keep], prisms.pose_covariance[keep], reference.xyz, reference.cov,
        reference.names)
    lap("gates")
    return _Fit(tracks, gps, qc_info, prisms, est, keep, gate_report, gt, distance_check,
                outliers, timings)


def calibration_samples(data: DeploymentData, filtered: list[Observations], model: NoiseModel,
                        options: RunOptions, step_s: float = SAMPLE_STEP_S) -> DistanceSamples:
    """The observations of the dynamic calibration (:mod:`rtsgt.calibration.dynamic`): each
    station's filtered observations as a track in its own frame (first-order noise model, the
    instrument, tilt and atmosphere sources: no calibration yet, and the clock offsets are
    estimated), module 2's common intervals, each track's GP (the run's interpolation options,
    given the white sources), sampled every ``step_s`` seconds
    (:data:`~rtsgt.calibration.dynamic.SAMPLE_STEP_S`). The scale error shared by the tracks is the atmosphere source's: its variance
    ``tr(C_atm) / d^2`` averaged over the measurements."""
    station_model = model.with_sources(
        [s for s in model.sources if s in ("instrument", "tilt", "atmosphere")])
    tracks = {obs.prism: propagate(obs, station_model, weather=data.weather) for obs in filtered}
    kept, intervals, _ = module2(list(tracks.values()), options.filter)
    tracks = {tr.prism: tr for tr in kept}
    gps = fit_gps(tracks, replace(options.interpolation, gp_noise="white"))
    t = sample_times(gps, intervals, step_s)
    scale = [np.trace(tr.cov_by_source["atmosphere"], axis1=1, axis2=2) / tr.range_m ** 2
             for tr in tracks.values() if "atmosphere" in tr.cov_by_source]
    return distance_samples(gps, {o.prism: o.station for o in filtered}, data.reference, t,
                            scale_variance=float(np.mean(np.concatenate(scale))) if scale else 0.0)


def calibrate_by_method(
    data: DeploymentData, options: RunOptions, filtered: list[Observations],
) -> tuple[CalibrationResult, CalibrationResult | None]:
    """The stations' calibration of a run by ``options.calibration.method``, from the stage's
    random stream: :func:`calibrate_stations` for ``"gcp"``; for ``"dynamic"`` and ``"joint"``,
    :func:`rtsgt.calibration.dynamic.calibrate_dynamic` on :func:`calibration_samples` of the
    filtered observations (the GCP shots with the atmospheric correction, as
    :func:`calibrate_stations` has them, for ``"joint"``).

    Returns the calibration the run uses and, for ``"dynamic"`` and ``"joint"``, the GCP
    calibration of the same deployment (``"dynamic"``: with its Monte Carlo covariance, for the
    agreement check; None when the GCP shots cannot calibrate the stations); None for
    ``"gcp"``.
    """
    opt = options.calibration
    t_start = min(float(o.t[0]) for o in filtered)
    if opt.method == "gcp":
        return calibrate_stations(data, options, t_start), None
    model = noise_model(data, options)
    rng = stage_rng(options.seed, "calibration")
    gcp = gcp_atmospheric_correction(data.gcp, model, data.weather, t_start)
    kw = {"reference_station": data.reference_station, "instrument": data.instrument,
          "model": opt.model}
    samples = calibration_samples(data, filtered, model, options)
    dyn = {"engine": options.noise_engine, "n_samples": options.pose.samples,
           "gate_m": options.pose.distance_gate_m, **kw}
    if opt.method == "joint":
        gcp_calib = calibrate(gcp, samples=0, weighting=opt.weighting, **kw)
        return calibrate_dynamic(samples, gcp=gcp, gcp_calibration=gcp_calib, rng=rng,
                                 **dyn), gcp_calib
    try:
        gcp_calib = calibrate(gcp, samples=options.pose.samples, rng=rng,
                              weighting=opt.weighting, **kw)
    except (InputError, GeometryError) as exc:
        warnings.warn(f"dynamic calibration: the GCP shots cannot calibrate the stations "
                      f"({exc}); no comparison with the GCP calibration", RtsgtWarning,
                      stacklevel=2)
        gcp_calib = None
    return calibrate_dynamic(samples, rng=rng, **dyn), gcp_calib


class _Refit(NamedTuple):
    """What :func:`_refit_outlier_windows` changes in a run."""

    tracks: dict[str, PrismTrack]
    gps: dict[str, GPTrack]
    qc_info: dict[str, dict]
    prisms: PrismsAtTimes
    estimate: PoseEstimate
    keep: np.ndarray
    gate_report: GateReport
    left_out: dict[str, np.ndarray]
    report: OutlierWindowReport


def _poses(options: RunOptions, reference: ReferencePoints,
           prisms: PrismsAtTimes) -> PoseEstimate:
    """The poses of prisms at their times (the run's pose options and its ``"pose"`` random
    stream, drawn afresh: a call's Monte Carlo draws follow its poses in order)."""
    return estimate_poses(prisms.xyz, prisms.pose_covariance, reference,
                          engine=options.pose.engine, registration=options.pose.registration,
                          samples=options.pose.samples, rng=stage_rng(options.seed, "pose"))


def _refit_outlier_windows(options: RunOptions, tracks: dict[str, PrismTrack],
                           prisms: PrismsAtTimes, flagged: np.ndarray, est: PoseEstimate,
                           reference: ReferencePoints, coupling: StationCoupling,
                           say: Progress) -> _Refit | None:
    """The GPs fitted again without the measurements inside the windows of the poses that
    disagree with the survey beyond the distance gate, and what follows from them
    (:mod:`rtsgt.filtering.gates`, section on the windows).

    ``flagged`` (T,): the poses of ``prisms`` that disagree (at least one, not all); ``est``:
    their poses only, in order. The poses inside a window keep the values of the fit that
    flagged them (they fail the gate); the others are queried and flagged again (from the
    prisms' distances, :func:`~rtsgt.filtering.gates.prism_distances`) at each fit, and
    estimated and gated once, from the fit that stands: the poses of a fit that flags more
    would be replaced by the next fit's, and only those it flags are estimated. A pose the
    new GPs cannot answer (a window left a gap longer than ``max_gap_s``) is dropped.
    ``left_out``: per prism, indexed like its track, the measurements left out. A fit that
    fails (a window took nearly all of a track) ends the refits with a warning: the last good
    one stands, or none (None).
    """
    gate = options.pose.distance_gate_m
    flagged = np.array(flagged, dtype=bool)
    say("outlier windows (module 4)")
    t_all = prisms.t
    present = np.arange(t_all.size)  # the poses still queried, indices into t_all
    kept_est = est  # the poses of the flagged poses among ``present``, in order
    last = None  # the fit that stands, its poses not yet estimated
    fits, dropped = 0, 0
    while fits < MAX_OUTLIER_REFITS:
        windows = outlier_windows(t_all, flagged)
        left_out = {pid: in_windows(tr.t, windows) for pid, tr in tracks.items()}
        clean = {pid: tr.select(~left_out[pid]) for pid, tr in tracks.items()}
        qc_info: dict[str, dict] = {}
        try:
            gps = fit_gps(clean, options.interpolation, info=qc_info)
        except InputError as exc:
            warnings.warn(f"outlier windows: the GPs cannot be fitted without the "
                          f"measurements of {windows.shape[0]} windows of distance rejections "
                          f"({exc.bare_message}); "
                          + ("they stay in the fits" if last is None else
                             "the windows of the previous fit stand"),
                          RtsgtWarning, stacklevel=2)
            break
        fits += 1
        supported = np.ones(present.size, bool)
        for g in gps.values():
            supported &= g.supported(t_all[present])
        old = flagged[present]  # flagged by an earlier fit: its values stay
        fresh = present[~old & supported]
        dropped += int(np.sum(~old & ~supported))
        present = present[old | supported]
        prisms = _take(prisms, old)
        from_old = flagged[present]
        more = np.zeros(0, bool)
        new_prisms = None
        if fresh.size:
            new_prisms = query_prisms(clean, gps, t_all[fresh], options.interpolation, coupling)
            prisms = _assemble(prisms, new_prisms, from_old)
            more = distance_outliers(prism_distances(new_prisms.xyz), reference, gate)
            flagged[fresh[more]] = True
        per_prism = [{REASON_DISTANCE_WINDOW: int(m.sum())} for m in left_out.values()]
        n_in = sum(len(tr) for tr in tracks.values())
        n_out = sum(c[REASON_DISTANCE_WINDOW] for c in per_prism)
        summary = OutlierWindowReport(
            "module4", n_in, n_in - n_out, {REASON_DISTANCE_WINDOW: n_out}, tuple(per_prism),
            int(windows.shape[0]), tuple(~m for m in left_out.values()),
            tuple(np.where(m, REASON_DISTANCE_WINDOW, "") for m in left_out.values()),
            windows=windows, fits=fits, converged=not more.any(),
            poses_flagged=int(flagged[present].sum()), poses_dropped=dropped)
        last = (clean, gps, qc_info, prisms, kept_est, new_prisms, from_old, left_out, summary)
        if not more.any() or fits == MAX_OUTLIER_REFITS:
            break
        # the poses flagged now keep this fit's values; the others get the next fit's
        kept_est = _assemble(kept_est, _poses(options, reference, _take(new_prisms, more)),
                             from_old[flagged[present]])
    if last is None:
        return None
    clean, gps, qc_info, prisms, kept_est, new_prisms, from_old, left_out, summary = last
    est = kept_est if new_prisms is None else _assemble(
        kept_est, _poses(options, reference, new_prisms), from_old)
    keep, report = apply_gates(est, reference, distance_gate_m=gate,
                               uncertainty_gate_m=options.pose.uncertainty_gate_m)
    return _Refit(clean, gps, qc_info, prisms, est, keep, report, left_out, summary)


def _take(result, idx: np.ndarray):
    """The rows ``idx`` of a per-time result (:class:`PrismsAtTimes`, :class:`PoseEstimate`):
    every array field, and every array in a dict field, is indexed along its first axis."""
    def rows(v):
        if isinstance(v, np.ndarray):
            return v[idx]
        return {k: rows(x) for k, x in v.items()} if isinstance(v, dict) else v
    return type(result)(**{f.name: rows(getattr(result, f.name)) for f in fields(result)})


def _assemble(first, second, from_first: np.ndarray):
    """Two per-time results of one type merged: row ``i`` from ``first`` (in order) where
    ``from_first[i]``, else from ``second``; their other fields must agree."""
    def merge(a, b):
        if isinstance(a, np.ndarray):
            out = np.empty((from_first.size,) + a.shape[1:], dtype=np.result_type(a, b))
            out[from_first], out[~from_first] = a, b
            return out
        if isinstance(a, dict):
            return {k: merge(a[k], b[k]) for k in a}
        if a != b:
            raise ValueError(f"cannot merge results that differ in {a!r} and {b!r}")
        return a
    return type(first)(**{f.name: merge(getattr(first, f.name), getattr(second, f.name))
                          for f in fields(first)})


def _split(options: RunOptions, prisms: PrismsAtTimes, gps: dict[str, GPTrack],
           tracks: dict[str, PrismTrack], calib: CalibrationResult, coupling: StationCoupling,
           reference: ReferencePoints, est: PoseEstimate,
           keep: np.ndarray) -> SharedFactor | None:
    """The kept poses' error split into varying and shared parts (:mod:`rtsgt.shared`); None
    when the GP was given the total covariance (``gp_noise = "all"``: no separate shared
    sources)."""
    if options.interpolation.gp_noise != "white":
        return None
    idx = np.flatnonzero(keep)
    kept = select_prisms(prisms, idx)
    velocity = gp_velocities({p: gps[p] for p in tracks}, kept.t)
    origins = {s: np.asarray(T.translation, dtype=float) for s, T in calib.transforms.items()}
    return split_ground_truth(
        kept, velocity, [tracks[p].station for p in tracks], origins, coupling, reference,
        est.R[idx], registration=options.pose.registration)


def _record(c: RunComputation, options: RunOptions, intervals: np.ndarray,
            coupling: StationCoupling, removed: RemovedMeasurements, groundtruth: PoseTrajectory,
            gcp_world: dict[str, np.ndarray], weather_coverage: dict | None,
            distance_check: dict, self_checks: dict) -> RunRecord:
    """The run record of what the stages computed (the prisms in the order of the tracks)."""
    ids = tuple(c.tracks)
    stations = {s: np.asarray(T.translation, dtype=float)
                for s, T in c.calibration.transforms.items()}
    measurements, gp_cov = _measurements(c.tracks, c.calibration, options)
    pr = c.prisms
    reject = ~c.keep
    gcp_names = tuple(gcp_world)
    return RunRecord(
        name=c.data.name, prism_ids=ids, measurements=measurements,
        prisms_t=pr.t, prisms_xyz=pr.xyz, prisms_cov=pr.cov,
        prisms_cov_by_source={s: pr.cov_by_source[s] for s in ordered_sources(pr.cov_by_source)},
        groundtruth=groundtruth, rejected_t=pr.t[reject],
        rejected_reason=np.asarray(c.gate_report.reason, dtype=str)[reject],
        reference=c.data.reference, options=options, stations=stations,
        prisms_cov_gp=pr.cov_gp,
        gcp_xyz=np.array([gcp_world[n] for n in gcp_names]) if gcp_names else None,
        gcp_names=gcp_names, qc={pid: np.asarray(g.qc) for pid, g in c.gps.items()},
        qc_scale={pid: np.asarray(g.qc_scale) for pid, g in c.gps.items()
                  if g.qc_scale is not None}, prior={pid: g.prior for pid, g in c.gps.items()},
        intervals=intervals, uncertainty_measure=c.gate_report.uncertainty_measure,
        coupling=coupling, removed=removed,
        measurements_gp_cov=gp_cov,
        weather_coverage=weather_coverage, distance_check=distance_check,
        self_checks=self_checks, computation=c,
    )
