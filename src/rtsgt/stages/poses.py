"""The one chain from prisms at times to gated poses, and the refit without the windows of
distance rejections.

:func:`pose_estimate` (the run's engine, registration and ``"pose"`` random stream, drawn
afresh at each call) and :func:`gate_poses` (module 4 with the run's gates) are the steps;
:func:`gated_poses` chains them (the continuous ground truth's queries); :func:`fit_to_gates`
runs the GPs, the chain and the refit of :func:`refit_outlier_windows` for the pipeline.
docs/pose.md, docs/filtering.md (module 4 and its windows).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError, RtsgtWarning
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
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.interpolation import GPTrack
from rtsgt.interpolation.prisms import PrismsAtTimes, fit_gps, query_prisms
from rtsgt.noise.coupling import StationCoupling
from rtsgt.options import RunOptions, stage_rng
from rtsgt.pose import PoseEstimate, ReferencePoints, estimate_poses
from rtsgt.stages.prisms import fit_prisms
from rtsgt.stages.timing import Progress, Stopwatch
from rtsgt.types import PoseTrajectory, PrismTrack

__all__ = ["GatedPoses", "PoseFit", "Refit", "assemble_rows", "fit_to_gates", "gate_poses",
           "gated_poses", "pose_estimate", "refit_outlier_windows", "take_rows"]


def pose_estimate(xyz: ArrayLike, cov: ArrayLike, reference: ReferencePoints,
                  options: RunOptions, engine: str | None = None) -> PoseEstimate:
    """The poses of prisms ``xyz`` (T, n, 3), m, with their covariance ``cov`` (T, n, 3, 3) or
    joint (T, 3n, 3n), m^2: the run's pose options, its ``"pose"`` random stream drawn afresh
    (a call's Monte Carlo draws follow its poses in order); ``engine`` overrides the run's
    per-prism engine (:attr:`~rtsgt.options.RunOptions.prism_engine`; the planner's
    ``"linear"``)."""
    opt = options.pose
    return estimate_poses(xyz, cov, reference,
                          engine=options.prism_engine if engine is None else engine,
                          registration=opt.registration, samples=opt.samples,
                          rng=stage_rng(options.seed, "pose"))


def gate_poses(estimate: PoseEstimate, reference: ReferencePoints, options: RunOptions,
               uncertainty_measure: str | None = None) -> tuple[np.ndarray, GateReport]:
    """Module 4's gates with the run's thresholds: ``(keep (T,), report)``
    (``uncertainty_measure``: the gates' own default where None)."""
    measure = {} if uncertainty_measure is None else {"uncertainty_measure": uncertainty_measure}
    return apply_gates(estimate, reference, distance_gate_m=options.pose.distance_gate_m,
                       uncertainty_gate_m=options.pose.uncertainty_gate_m, **measure)


@dataclass(frozen=True)
class GatedPoses:
    """The poses of prisms at their times, and module 4's ``keep`` (T,) and ``report``."""

    estimate: PoseEstimate
    keep: np.ndarray
    report: GateReport


def gated_poses(prisms: PrismsAtTimes, reference: ReferencePoints, options: RunOptions,
                uncertainty_measure: str | None = None) -> GatedPoses:
    """Prisms at their times -> poses (:func:`pose_estimate`) -> gates (:func:`gate_poses`)."""
    est = pose_estimate(prisms.xyz, prisms.pose_covariance, reference, options)
    return GatedPoses(est, *gate_poses(est, reference, options, uncertainty_measure))


def take_rows(result, idx: np.ndarray):
    """The rows ``idx`` of a per-time result (:class:`PrismsAtTimes`, :class:`PoseEstimate`):
    every array field, and every array in a dict field, is indexed along its first axis."""
    def rows(v):
        if isinstance(v, np.ndarray):
            return v[idx]
        return {k: rows(x) for k, x in v.items()} if isinstance(v, dict) else v
    return type(result)(**{f.name: rows(getattr(result, f.name)) for f in fields(result)})


def assemble_rows(first, second, from_first: np.ndarray):
    """Two per-time results of one type merged: row ``i`` from ``first`` (in order) where
    ``from_first[i]``, else from ``second``; their other fields must agree (ValueError)."""
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


@dataclass(frozen=True)
class Refit:
    """What :func:`refit_outlier_windows` changes in a run: the tracks without the windows'
    measurements, their GPs, ``qc_info``, the prisms and poses that stand, module 4's ``keep``
    and ``gate_report``, ``left_out`` (per prism, indexed like its track) and the windows'
    ``report``."""

    tracks: dict[str, PrismTrack]
    gps: dict[str, GPTrack]
    qc_info: dict[str, dict]
    prisms: PrismsAtTimes
    estimate: PoseEstimate
    keep: np.ndarray
    gate_report: GateReport
    left_out: dict[str, np.ndarray]
    report: OutlierWindowReport


@dataclass
class _Windows:
    """The refit's state over the first fit's times ``t`` (T,): the poses ``flagged`` so far
    (T,), the indices of those still queried (``present``), their ``prisms`` (rows of
    ``present``), the poses of the flagged among them (``kept``, in order), fits, drops."""

    t: np.ndarray
    flagged: np.ndarray
    present: np.ndarray
    prisms: PrismsAtTimes
    kept: PoseEstimate
    fits: int = 0
    dropped: int = 0


@dataclass(frozen=True)
class _WindowFit:
    """One fit without the windows: the ``clean`` tracks, ``gps``, ``qc_info``, the ``prisms``
    and ``kept`` poses at that fit, the prisms queried afresh (``fresh``; None if none), which
    rows of ``prisms`` come from earlier fits (``from_old``), the poses newly flagged
    (``more``, over ``fresh``), ``left_out`` and the windows' ``report``."""

    clean: dict[str, PrismTrack]
    gps: dict[str, GPTrack]
    qc_info: dict[str, dict]
    prisms: PrismsAtTimes
    kept: PoseEstimate
    fresh: PrismsAtTimes | None
    from_old: np.ndarray
    more: np.ndarray
    left_out: dict[str, np.ndarray]
    report: OutlierWindowReport


def _window_report(tracks: dict[str, PrismTrack], left_out: dict[str, np.ndarray],
                   windows: np.ndarray, s: _Windows, converged: bool) -> OutlierWindowReport:
    """Module 4's report of the measurements ``left_out`` of ``tracks`` by the ``windows``."""
    per_prism = [{REASON_DISTANCE_WINDOW: int(m.sum())} for m in left_out.values()]
    n_in = sum(len(tr) for tr in tracks.values())
    n_out = sum(c[REASON_DISTANCE_WINDOW] for c in per_prism)
    return OutlierWindowReport(
        "module4", n_in, n_in - n_out, {REASON_DISTANCE_WINDOW: n_out}, tuple(per_prism),
        int(windows.shape[0]), tuple(~m for m in left_out.values()),
        tuple(np.where(m, REASON_DISTANCE_WINDOW, "") for m in left_out.values()),
        windows=windows, fits=s.fits, converged=converged,
        poses_flagged=int(s.flagged[s.present].sum()), poses_dropped=s.dropped)


def _fit_without_windows(options: RunOptions, tracks: dict[str, PrismTrack], s: _Windows,
                         reference: ReferencePoints, coupling: StationCoupling,
                         first: bool) -> _WindowFit | None:
    """One fit of the GPs without the windows of ``s.flagged`` (``s`` updated); None, with a
    warning, when the GPs cannot be fitted."""
    windows = outlier_windows(s.t, s.flagged)
    left_out = {pid: in_windows(tr.t, windows) for pid, tr in tracks.items()}
    clean = {pid: tr.select(~left_out[pid]) for pid, tr in tracks.items()}
    qc_info: dict[str, dict] = {}
    try:
        gps = fit_gps(clean, options.interpolation, info=qc_info)
    except InputError as exc:
        warnings.warn(f"outlier windows: the GPs cannot be fitted without the "
                      f"measurements of {windows.shape[0]} windows of distance rejections "
                      f"({exc.bare_message}); "
                      + ("they stay in the fits" if first else
                         "the windows of the previous fit stand"),
                      RtsgtWarning, stacklevel=3)
        return None
    s.fits += 1
    supported = np.ones(s.present.size, bool)
    for g in gps.values():
        supported &= g.supported(s.t[s.present])
    old = s.flagged[s.present]  # flagged by an earlier fit: its values stay
    fresh = s.present[~old & supported]
    s.dropped += int(np.sum(~old & ~supported))
    s.present = s.present[old | supported]
    s.prisms = take_rows(s.prisms, old)
    from_old = s.flagged[s.present]
    more = np.zeros(0, bool)
    new_prisms = None
    if fresh.size:
        new_prisms = query_prisms(clean, gps, s.t[fresh], options.interpolation, coupling)
        s.prisms = assemble_rows(s.prisms, new_prisms, from_old)
        more = distance_outliers(prism_distances(new_prisms.xyz), reference,
                                 options.pose.distance_gate_m)
        s.flagged[fresh[more]] = True
    report = _window_report(tracks, left_out, windows, s, converged=not more.any())
    return _WindowFit(clean, gps, qc_info, s.prisms, s.kept, new_prisms, from_old, more,
                      left_out, report)


def refit_outlier_windows(options: RunOptions, tracks: dict[str, PrismTrack],
                          prisms: PrismsAtTimes, flagged: np.ndarray, est: PoseEstimate,
                          reference: ReferencePoints, coupling: StationCoupling,
                          say: Progress) -> Refit | None:
    """The GPs fitted again without the measurements inside the windows of the poses that
    disagree with the survey beyond the distance gate, and what follows from them
    (docs/filtering.md, module 4's windows).

    ``flagged`` (T,): the poses of ``prisms`` that disagree (at least one, not all); ``est``:
    their poses only, in order. The poses inside a window keep the values of the fit that
    flagged them; the others are queried and flagged again at each fit (at most
    :data:`~rtsgt.filtering.gates.MAX_OUTLIER_REFITS`), and estimated and gated once, from
    the fit that stands. A pose the new GPs cannot answer (a gap longer than ``max_gap_s``)
    is dropped. A fit that fails ends the refits with a warning: the last good one stands,
    or none (None).
    """
    say("outlier windows (module 4)")
    s = _Windows(prisms.t, np.array(flagged, dtype=bool), np.arange(prisms.t.size), prisms, est)
    last = None  # the fit that stands, its poses not yet estimated
    while s.fits < MAX_OUTLIER_REFITS:
        fit = _fit_without_windows(options, tracks, s, reference, coupling, last is None)
        if fit is None:
            break
        last = fit
        if not fit.more.any() or s.fits == MAX_OUTLIER_REFITS:
            break
        # the poses flagged now keep this fit's values; the others get the next fit's
        more = take_rows(fit.fresh, fit.more)
        s.kept = assemble_rows(s.kept, pose_estimate(more.xyz, more.pose_covariance, reference,
                                                     options), fit.from_old[s.flagged[s.present]])
    if last is None:
        return None
    est = last.kept if last.fresh is None else assemble_rows(
        last.kept, pose_estimate(last.fresh.xyz, last.fresh.pose_covariance, reference, options),
        last.from_old)
    keep, report = gate_poses(est, reference, options)
    return Refit(last.clean, last.gps, last.qc_info, last.prisms, est, keep, report,
                 last.left_out, last.report)


@dataclass(frozen=True)
class PoseFit:
    """What :func:`fit_to_gates` computes from the tracks: the tracks the GPs were fitted to,
    ``gps``, ``qc_info``, ``prisms`` at the query times, their poses (``estimate``), module 4's
    ``keep`` and ``gate_report``, the kept poses (``groundtruth``), the surveyed distance
    check, the measurements left out per prism and module 4's report (None without a refit),
    and ``timings`` (s)."""

    tracks: dict[str, PrismTrack]
    gps: dict[str, GPTrack]
    qc_info: dict[str, dict]
    prisms: PrismsAtTimes
    estimate: PoseEstimate
    keep: np.ndarray
    gate_report: GateReport
    groundtruth: PoseTrajectory
    distance_check: dict
    left_out: dict[str, np.ndarray] | None
    window_report: OutlierWindowReport | None
    timings: dict[str, float]


def fit_to_gates(options: RunOptions, given_times: np.ndarray | None, intervals: np.ndarray,
                 tracks: dict[str, PrismTrack], coupling: StationCoupling,
                 reference: ReferencePoints, say: Progress) -> PoseFit:
    """The GPs of the tracks, the prisms at the query times, the poses and module 4's gates,
    with the GPs fitted again without the windows of distance rejections
    (``outlier_windows = "remove"``, :func:`refit_outlier_windows`). ``timings`` has the
    stages ``interpolation``, ``pose``, ``gates`` and, with a refit, ``outlier_windows``."""
    clock = Stopwatch()
    pf = fit_prisms(options, given_times, intervals, tracks, coupling, say)
    gps, qc_info, prisms = pf.gps, pf.qc_info, pf.prisms
    clock.lap("interpolation")

    say("poses")
    # the poses the distance gate will reject, from the prisms alone: when their windows are
    # refitted, only they keep this fit's poses, the others are estimated from the fit that
    # stands
    flagged = distance_outliers(prism_distances(prisms.xyz), reference,
                                options.pose.distance_gate_m)
    refit_due = (options.interpolation.outlier_windows == "remove" and bool(flagged.any())
                 and not flagged.all())
    first = take_rows(prisms, flagged) if refit_due else prisms
    est = pose_estimate(first.xyz, first.pose_covariance, reference, options)
    clock.lap("pose")

    say("quality gates (module 4)")
    refit = None
    if refit_due:
        start = time.perf_counter()
        refit = refit_outlier_windows(options, tracks, prisms, flagged, est, reference,
                                      coupling, say)
        if refit is None:  # the refit failed: this fit stands, every pose of it
            est = pose_estimate(prisms.xyz, prisms.pose_covariance, reference, options)
        else:
            tracks, gps, qc_info, prisms, est = (refit.tracks, refit.gps, refit.qc_info,
                                                 refit.prisms, refit.estimate)
        clock.timings["outlier_windows"] = time.perf_counter() - start
        clock.tick += clock.timings["outlier_windows"]  # its own stage, not in "gates"
    keep, gate_report = (gate_poses(est, reference, options) if refit is None
                         else (refit.keep, refit.gate_report))
    gt = PoseTrajectory(prisms.t[keep], est.t[keep], matrix_to_quat_xyzw(est.R[keep]),
                        est.cov[keep])
    # a surveyed distance the tracking disagrees with biases every pose: say so
    distance_check = surveyed_distance_check(
        prisms.xyz[keep], prisms.pose_covariance[keep], reference.xyz, reference.cov,
        reference.names)
    clock.lap("gates")
    return PoseFit(tracks, gps, qc_info, prisms, est, keep, gate_report, gt, distance_check,
                   None if refit is None else refit.left_out,
                   None if refit is None else refit.report, clock.timings)
