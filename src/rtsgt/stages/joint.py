"""The joint engine's stage (``[pose] engine = "joint"``): after the per-prism poses, every
raw polar measurement to the robot's trajectory, the stations and (optionally) their clocks at
once (:func:`rtsgt.joint.estimate_joint`, docs/joint.md), its poses gated as the per-prism
ones, and the summary of what it estimated. docs/pipeline.md#the-joint-engine.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from rtsgt.allocator import available_memory, keep_freed_memory
from rtsgt.calibration import CalibrationResult
from rtsgt.choices import DEFAULT_MAX_GAP_S
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.geometry.so3 import log_so3, matrix_to_quat_xyzw
from rtsgt.geometry.transform import RigidTransform
from rtsgt.interpolation.motion import CLASS_NAMES
from rtsgt.joint import estimate_joint
from rtsgt.joint.axes import AXES_SIGMA
from rtsgt.joint.deviation import COMPONENTS as DEVIATION_COMPONENTS
from rtsgt.joint.deviation import TRIG as DEVIATION_TRIG
from rtsgt.joint.deviation import DeviationFit
from rtsgt.joint.estimate import JointResult
from rtsgt.joint.gm import GaussMarkov
from rtsgt.joint.knots import qc_from_prisms
from rtsgt.joint.noise import CHANNELS as NOISE_CHANNELS
from rtsgt.joint.noise import NoiseFit
from rtsgt.joint.prisms import PrismFit
from rtsgt.measurement.instruments import ARCSEC
from rtsgt.measurement.units import MGON
from rtsgt.noise import NoiseModel
from rtsgt.options import RunOptions, stage_rng
from rtsgt.pose import PoseEstimate, ReferencePoints
from rtsgt.pose.estimate import REASON_MISSING
from rtsgt.shared import SharedFactor
from rtsgt.stages.poses import PoseFit, gate_poses
from rtsgt.stages.timing import Progress
from rtsgt.types import GcpShots, Observations, PoseTrajectory, WeatherSeries

__all__ = ["JointFit", "joint_fit", "joint_poses", "joint_split", "joint_summary"]

#: Oldest a GCP shot's time stamp may be, before the first measurement, to be taken as its
#: station's calibration time (the set-up the tracking uses), s.
MAX_CALIBRATION_AGE_S = 3600.0
#: The reason of a query time the joint engine does not answer (outside the measurements'
#: span): the per-prism engines' reason for a pose without every prism.
REASON_UNANSWERED = REASON_MISSING


def joint_poses(observations: Sequence[Observations], calibration: CalibrationResult,
                reference: ReferencePoints, model: NoiseModel, weather: WeatherSeries | None,
                start_t: np.ndarray, start_R: np.ndarray, start_p: np.ndarray,
                qc_prisms: np.ndarray, query_times: np.ndarray, *,
                clocks: bool = True, max_gap_s: float = DEFAULT_MAX_GAP_S,
                calibrated_at: dict[str, float] | None = None,
                rng: np.random.Generator | None = None) -> JointResult:
    """The joint engine's poses at ``query_times`` (Q,) s, those inside the measurements' span.

    ``observations``: each station's measurements the run keeps (module 1 and 2, the windows
    of distance rejections out); ``calibration``: the stations' prior (its
    ``reference_station`` the clocks' reference); ``reference``: the prisms' body positions;
    ``model``, ``weather``: the noise model and the weather of the distance correction;
    ``start_t`` (T,), ``start_R`` (T, 3, 3), ``start_p`` (T, 3): the per-prism poses to start
    from; ``qc_prisms`` (P, 3, 3): the per-prism GPs' WNOA ``Qc`` (m^2/s^3), the start of the prior's ``Qc`` (:func:`rtsgt.joint.knots.qc_from_prisms`);
    ``clocks``: estimate each station's clock offset; ``max_gap_s``: the run's longest gap
    bridged (the raw block cross-validation's segments); ``calibrated_at``: each station's
    calibration time, s (:func:`calibration_times`), from which its set-up settles
    (docs/joint.md#settling-tripods). The prisms' body positions are
    estimated with the survey as their prior (docs/joint.md#prism-positions), their
    deviation with the viewing angle (docs/joint.md#prism-deviation), the white
    noise per station and channel with the noise model's as its prior
    (docs/joint.md#noise-identification) and its Gauss-Markov part
    (docs/joint.md#gauss-markov-noise; ``rng`` the draws of its observed information).
    InputError when no query time falls inside the measurements' span, or when one solve
    needs more memory than the machine has available (:func:`rtsgt.allocator.available_memory`;
    docs/joint.md#an-hours-floor).
    """
    lo = min(float(o.t[0]) for o in observations)
    hi = max(float(o.t[-1]) for o in observations)
    tq = np.asarray(query_times, dtype=float)
    tq = tq[(tq >= lo) & (tq <= hi)]
    if tq.size == 0:
        raise InputError(f"joint engine: no query time inside the measurements' span "
                         f"{lo:.3f}-{hi:.3f} s")
    qc = qc_from_prisms(qc_prisms, reference.xyz)
    return estimate_joint(observations, calibration, reference, model, tq, start_t, start_R,
                          start_p, qc, weather=weather, clocks=clocks, prisms=True,
                          noise=True, settling=True, calibrated_at=calibrated_at,
                          deviation=True, gauss_markov=True, max_gap_s=max_gap_s, rng=rng,
                          motion_axes=True, rocking=True, memory_bytes=available_memory())


def calibration_times(gcp: GcpShots | None, calibration: CalibrationResult,
                      t_first: float) -> dict[str, float]:
    """Each station's calibration time, s: the median time of its valid shots of a GCP
    calibration, where it lies within :data:`MAX_CALIBRATION_AGE_S` before the first
    measurement ``t_first`` s (older stamps are another clock's: the shipped excerpt's are
    13-125 days before its tracking); empty for a dynamic calibration (the tracking is the
    calibration) or shots without times. A station left out settles from ``t_first`` on."""
    if calibration.method != "gcp" or gcp is None or gcp.t is None:
        return {}
    ok = np.ones(gcp.t.size, bool) if gcp.status is None else gcp.status == 0
    ok &= np.isfinite(gcp.t)
    st = np.asarray(gcp.station).astype(str)
    out = {}
    for sid in calibration.transforms:  # a handful of stations
        mine = ok & (st == sid)
        if np.any(mine):
            t = float(np.median(gcp.t[mine]))
            if t_first - MAX_CALIBRATION_AGE_S <= t:
                out[sid] = t
    return out


@dataclass(frozen=True)
class JointFit:
    """The per-prism fit with the joint engine's poses in place of its own (``fit``: its
    ``estimate`` at every query time, ``keep``, ``gate_report`` and ``groundtruth`` the joint
    engine's; its prisms, GPs and tracks the per-prism ones) and the engine's ``result``."""

    fit: PoseFit
    result: JointResult


def joint_fit(options: RunOptions, filtered: Sequence[Observations],
              calibration: CalibrationResult, model: NoiseModel,
              weather: WeatherSeries | None, fit: PoseFit, reference: ReferencePoints,
              say: Progress, gcp: GcpShots | None = None) -> JointFit:
    """The joint engine after the per-prism ``fit`` (:func:`rtsgt.stages.poses.fit_to_gates`):
    its measurements are ``filtered``'s (module 1) at the times of the tracks the GPs were
    fitted to, its start the per-prism kept poses and the GPs' ``Qc``, its query times the
    per-prism fit's; then module 4's gates on its poses (a query time it does not answer is
    rejected as a pose without every prism); ``gcp``: the calibration's shots (their times
    the stations' calibration times). Keeps the process's freed memory from here on
    (:func:`rtsgt.allocator.keep_freed_memory`)."""
    say("joint engine")
    keep_freed_memory()  # its solves' large arrays reused, not faulted in afresh
    obs = [o.select(np.isin(o.t, fit.tracks[o.prism].t)) for o in filtered
           if o.prism in fit.tracks]
    keep0 = fit.keep
    if int(keep0.sum()) < 2:
        raise InputError(f"joint engine: it starts from the per-prism poses, and "
                         f"{int(keep0.sum())} passed the gates (at least 2 needed)")
    est0 = fit.estimate
    wnoa = [p for p in reference.names if fit.gps[p].prior == "wnoa"]
    if not wnoa:
        raise InputError("joint engine: its motion prior starts from the Qc of the per-prism "
                         "GPs with the WNOA prior, and none has it ([interpolation] prior)")
    qc_prisms = np.stack([np.asarray(fit.gps[p].qc, dtype=float) for p in wnoa])
    tq = fit.prisms.t
    jr = joint_poses(obs, calibration, reference, model, weather, tq[keep0], est0.R[keep0],
                     est0.t[keep0], qc_prisms, tq, clocks=options.pose.clocks,
                     max_gap_s=options.interpolation.max_gap_s,
                     calibrated_at=calibration_times(
                         gcp, calibration, min(float(o.t[0]) for o in obs)),
                     rng=stage_rng(options.seed, "joint"))
    if not jr.qc.converged:
        parts = ", ".join(f"{k} {100 * v:.0f} %" for k, v in jr.qc.changes)
        warnings.warn(f"joint engine: its variance components did not converge in "
                      f"{jr.qc.iterations} updates (the last one's largest changes: {parts}): "
                      f"their estimates are where the loop stopped "
                      f"(docs/joint.md#the-variance-components-loop)", RtsgtWarning, stacklevel=2)
    est = _on_every_time(jr.estimate, np.isin(tq, jr.t))
    keep, report = gate_poses(est, reference, options)
    gt = PoseTrajectory(tq[keep], est.t[keep], matrix_to_quat_xyzw(est.R[keep]), est.cov[keep])
    return JointFit(replace(fit, estimate=est, keep=keep, gate_report=report, groundtruth=gt),
                    jr)


def _on_every_time(est: PoseEstimate, answered: np.ndarray) -> PoseEstimate:
    """``est`` (its rows the ``answered`` times) on every time of ``answered`` (T,): the others
    degenerate (NaN), with :data:`REASON_UNANSWERED`."""
    if answered.all():
        return est
    T = answered.size

    def spread(a: np.ndarray, fill) -> np.ndarray:
        out = np.full((T,) + a.shape[1:], fill, dtype=a.dtype)
        out[answered] = a
        return out

    eye = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
    eye[answered] = est.R
    return replace(est, R=eye, t=spread(est.t, np.nan), cov=spread(est.cov, np.nan),
                   degenerate=~answered,
                   reason=np.where(answered, spread(est.reason, ""), REASON_UNANSWERED),
                   inter_prism_distance=spread(est.inter_prism_distance, np.nan),
                   rms_residual=spread(est.rms_residual, np.nan),
                   shape=spread(est.shape, np.nan))


def joint_split(joint: JointFit) -> SharedFactor | None:
    """The joint engine's kept poses' error split into varying and shared parts
    (:mod:`rtsgt.shared`, ``JointResult.shared``: the part given the global parameters and the
    part shared through them, docs/joint.md#the-shared-error); None where it has none."""
    shared = joint.result.shared
    if shared is None:
        return None
    fit = joint.fit
    return shared.select(fit.keep[np.isin(fit.prisms.t, joint.result.t)])


def joint_summary(jr: JointResult, calibration: CalibrationResult) -> dict[str, Any]:
    """``joint`` of ``summary.json``: what the joint engine estimated besides the poses, JSON
    ready (docs/file-formats.md#summaryjson). ``qc``: the prior's ``Qc`` per motion class
    (m^2/s^3 and rad^2/s^3, the body frame's axes: the reference prisms' frame) with its
    redundancy; ``qc_iterations`` of the variance components' loop (``Qc``, noise, chains,
    rocking), ``qc_converged`` whether it converged and ``qc_last_change`` its last update's
    largest relative change of each (docs/joint.md#the-variance-components-loop);
    ``kappa_ppm`` with its sigma; ``stations``: each station's posterior shift from its
    calibration (mm, mrad, and in the calibration's sigmas per axis); ``clocks``: per
    station but the reference its offset (ms) at the start and the end, the largest
    ``|offset|`` and the median sigma; ``time_sync``: the constant clock offsets against the
    robot's (ms, with sigma); ``prisms``: each prism's shift from its survey (mm, with its
    sigma), its test statistic in sigmas and whether it was found moved; ``noise``: the
    white noise's components per station and channel where identified; ``gauss_markov``:
    the correlated noise's sigma (mgon, mm) and correlation time (s) per station and channel,
    with their sigmas, redundancy and whether the data determined them
    (docs/joint.md#gauss-markov-noise); ``settling``: per
    station its height (mm) and yaw (arc seconds) change since its calibration at the first
    and the last knot, with their sigmas (docs/joint.md#settling-tripods); ``deviation``: the
    prisms' deviation with their viewing angle per prism, harmonic and component (mm, with
    sigma and whether the data determine it; docs/joint.md#prism-deviation); ``motion_axes``:
    the motion prior's axes' rotation from the body frame about its x, y, z (mrad, with
    sigma and in sigmas of their prior; docs/joint.md#the-motion-axes); ``rocking``: the
    vehicle's rocking per axis, its sigma (mm, mrad) and correlation time (s) with their
    sigmas, redundancy and whether the data determined it
    (docs/joint.md#the-vehicles-rocking); ``rocking_pivot_m``: the point its rotations are
    about, body frame (None: the prisms' centroid; docs/joint.md#the-rockings-pivot);
    ``prism_stability_mm``: the moves since the survey no station sees, carried (1 sigma;
    docs/joint.md#what-no-station-sees); the solve's iterations, convergence, chi^2 per
    row, knots and measurements."""
    q = jr.qc
    used = np.bincount(q.classes, minlength=len(CLASS_NAMES))
    return {
        "qc": {CLASS_NAMES[c]: {"qc": q.table[c].tolist(), "redundancy": q.redundancy[c].tolist(),
                                "intervals": int(used[c])}
               for c in range(len(CLASS_NAMES)) if used[c] > 0},
        "qc_axes": ["x", "y", "z", "rx", "ry", "rz"],
        "qc_iterations": int(q.iterations), "qc_converged": bool(q.converged),
        "qc_last_change": dict(q.changes),
        "kappa_ppm": float(jr.kappa_ppm), "kappa_sigma_ppm": float(jr.kappa_sigma_ppm),
        "stations": {sid: _station_shift(calibration.transforms[sid], T)
                     for sid, T in jr.stations.items()},
        "clocks": {sid: _clock_summary(kn, off, cov) for sid, (kn, off, cov)
                   in jr.clocks.items()},
        "clock_reference": calibration.reference_station if jr.clocks else None,
        "time_sync": {sid: {"offset_ms": 1e3 * v, "sigma_ms": 1e3 * sd}
                      for sid, (v, sd) in jr.time_sync.items()},
        "prisms": None if jr.prisms is None else _prisms_summary(jr.prisms),
        "noise": None if jr.noise is None else _noise_summary(jr.noise),
        "gauss_markov": None if jr.gauss_markov is None else _gm_summary(jr.gauss_markov),
        "settling": {sid: _settling_summary(*v) for sid, v in jr.settling.items()},
        "deviation": None if jr.deviation is None else _deviation_summary(jr.deviation),
        "motion_axes": None if jr.motion_axes is None else _axes_summary(*jr.motion_axes),
        "rocking": None if jr.rocking is None else _rocking_summary(jr.rocking),
        "rocking_pivot_m": None if jr.rocking_pivot is None else jr.rocking_pivot.tolist(),
        "prism_stability_mm": 1e3 * jr.prism_stability,
        "iterations": int(jr.solve.iterations), "converged": bool(jr.solve.converged),
        "chi2_per_dof": float(jr.chi2_per_dof), "knots": int(jr.n_knots),
        "measurements": int(jr.n_measurements), "poses": int(jr.t.size),
    }


def _axes_summary(phi: np.ndarray, cov: np.ndarray) -> dict[str, Any]:
    """The motion axes' rotation vector ``phi`` (3,) rad with covariance ``cov`` (3, 3):
    ``rotation_mrad``, ``sigma_mrad`` and ``prior_sigmas`` (each axis over its prior sigma)."""
    return {"axes": ["rx", "ry", "rz"], "rotation_mrad": (1e3 * phi).tolist(),
            "sigma_mrad": (1e3 * np.sqrt(np.diag(cov))).tolist(),
            "prior_sigmas": (phi / AXES_SIGMA).tolist()}


def _settling_summary(knots, height, yaw, sd) -> dict[str, Any]:
    """A station's settling at its first and last knot: height mm, yaw arc seconds, sigmas."""
    ends = [0, -1]
    return {"t_s": knots[ends].tolist(), "height_mm": (1e3 * height[ends]).tolist(),
            "height_sigma_mm": (1e3 * sd[ends, 0]).tolist(),
            "yaw_arcsec": (yaw[ends] / ARCSEC).tolist(),
            "yaw_sigma_arcsec": (sd[ends, 1] / ARCSEC).tolist()}


def _deviation_summary(fit: DeviationFit) -> dict[str, Any]:
    """The prisms' deviation: per prism, ``coefficients_mm``, ``sigma_mm`` and ``determined``
    as (order, term, component) nested lists, ``amplitude_mm`` as (order, component),
    ``held`` per order (the viewing azimuth swept too few of its periods)."""
    shape = (len(fit.orders), len(DEVIATION_TRIG), len(DEVIATION_COMPONENTS))
    amp = fit.amplitude()
    sd = fit.sigma
    return {"orders": list(fit.orders), "terms": list(DEVIATION_TRIG),
            "components": list(DEVIATION_COMPONENTS),
            "prisms": {p: {"coefficients_mm": (1e3 * fit.coef[i]).reshape(shape).tolist(),
                           "sigma_mm": (1e3 * sd[i]).reshape(shape).tolist(),
                           "determined": fit.determined[i].reshape(shape).tolist(),
                           "held": fit.held[i].reshape(shape)[:, 0, 0].tolist(),
                           "amplitude_mm": (1e3 * amp[i]).tolist()}
                       for i, p in enumerate(fit.names)}}


def _prisms_summary(pf: PrismFit) -> dict[str, Any]:
    """Each prism's estimate against its survey (body frame), mm, its sigma per axis and
    along its least determined direction, the weight of the hypothesis that it moved
    (with the cost above the found one's of another prism's hypothesis carried beside it),
    and the directions of a move no station sees (body frame, unit) with the poses' turn
    per mm of move along each (mrad)."""
    largest, blind = pf.largest_sigma, pf.blind
    return {p: {"shift_mm": (1e3 * pf.shift[i]).tolist(), "sigma_mm": (1e3 * pf.sigma[i]).tolist(),
                "largest_sigma_mm": float(1e3 * largest[i]),
                "blind_directions": blind[i][0].T.tolist(),
                "blind_turn_mrad_per_mm": blind[i][1].tolist(),
                "test_sigmas": float(pf.shift_sigma[i]), "moved": bool(pf.moved[i]),
                "moved_weight": float(pf.weight[i]),
                "cost_above_found": None if np.isnan(pf.cost_above[i])
                else float(pf.cost_above[i])}
            for i, p in enumerate(pf.names)}


def _noise_summary(nf: NoiseFit) -> dict[str, Any]:
    """Each station's white-noise components per channel: the datasheet's factor and the
    range part (angles: mgon at 100 m; distance: ppm) with their sigmas, whether the data
    determined them (else the prior, kept) and the factor pooled over the stations, and the white sigma they give at the station's
    median range (angles mgon, distance mm) with its sigma (first order)."""
    out = {}
    v, sd = (None, None) if nf.median_basis is None else nf.median_variance()
    for i, sid in enumerate(nf.stations or range(nf.theta.shape[0])):
        per = out[str(sid)] = {}
        for j, c in enumerate(NOISE_CHANNELS):
            per[c] = {"factor": float(nf.theta[i, j, 0]),
                      "factor_sigma": float(nf.sigma[i, j, 0]),
                      "range_part": float(nf.range_sigma[i, j] / (1.0 if c == "d" else MGON)),
                      "determined": [bool(x) for x in nf.determined[i, j]],
                      "pooled": bool(nf.pooled is not None and nf.pooled[i, j])}
            if v is None:
                continue
            unit = 1e-3 if c == "d" else MGON  # sigma = sqrt(v), its sd sd(v) / (2 sigma)
            sig = float(np.sqrt(max(v[i, j], 0.0)))
            per[c].update(median_range_m=float(nf.median_range_m[i]), sigma_at_median=sig / unit,
                          sigma_at_median_sigma=float(sd[i, j] / (2.0 * sig) / unit)
                          if sig > 0 else 0.0)
    return out


def _gm_summary(fit: GaussMarkov) -> dict[str, Any]:
    """Each station's Gauss-Markov noise per channel: sigma (angles mgon, distance mm) and
    correlation time (s) with their sigmas, the chain's redundancy, whether the data
    determined it (else it was left out of the last solve, its sigma at the floor) and the
    correlation of the two estimates."""
    out = {}
    for i, sid in enumerate(fit.stations or range(fit.sigma.shape[0])):
        out[str(sid)] = {}
        for j, c in enumerate(NOISE_CHANNELS):
            unit = 1e-3 if c == "d" else MGON
            out[str(sid)][c] = {
                "sigma": float(fit.sigma[i, j] / unit),
                "sigma_sigma": float(fit.sigma_sd[i, j] / unit),
                "tau_s": float(fit.tau_s[i, j]), "tau_sigma_s": float(fit.tau_sd[i, j]),
                "correlation": float(0.0 if fit.corr is None else fit.corr[i, j]),
                "redundancy": float(0.0 if fit.redundancy is None else fit.redundancy[i, j]),
                "determined": bool(fit.determined[i, j])}
    return out


def _rocking_summary(fit: GaussMarkov) -> dict[str, Any]:
    """The vehicle's rocking per axis (shifts x, y, z in mm, rotations rx, ry, rz in mrad):
    sigma and correlation time (s) with their sigmas, redundancy, whether determined."""
    out = {}
    for i, axis in enumerate(("x", "y", "z", "rx", "ry", "rz")):
        r, c = divmod(i, 3)
        out[axis] = {"sigma": float(1e3 * fit.sigma[r, c]),
                     "sigma_sigma": float(1e3 * fit.sigma_sd[r, c]),
                     "tau_s": float(fit.tau_s[r, c]), "tau_sigma_s": float(fit.tau_sd[r, c]),
                     "redundancy": float(0.0 if fit.redundancy is None else fit.redundancy[r, c]),
                     "determined": bool(fit.determined[r, c])}
    return out


def _station_shift(prior: RigidTransform, post: RigidTransform) -> dict[str, Any]:
    """A station's posterior shift from its calibration: translation (mm), rotation (mrad,
    world frame, ``R_post = exp(dtheta^) R_prior``), each axis in the calibration's sigmas
    (None where the calibration holds it: the reference station)."""
    shift = np.concatenate([post.translation - prior.translation,
                            log_so3(post.rotation @ prior.rotation.T)])
    cov = np.zeros((6, 6)) if prior.covariance is None else prior.covariance
    sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    post_sig = np.sqrt(np.clip(np.diag(post.covariance), 0.0, None))
    held = bool(np.all(sig == 0))
    return {
        "shift_mm": (shift[:3] * 1e3).tolist(), "shift_mrad": (shift[3:] * 1e3).tolist(),
        "shift_sigmas": None if held else
        np.where(sig > 0, shift / np.where(sig > 0, sig, 1.0), 0.0).tolist(),
        "posterior_sigma_mm": (post_sig[:3] * 1e3).tolist(),
        "posterior_sigma_mrad": (post_sig[3:] * 1e3).tolist(),
        "held": held,
    }


def _clock_summary(knots: np.ndarray, offset: np.ndarray, cov: np.ndarray) -> dict[str, Any]:
    """One station's clock offset against the reference at its report times ``knots``
    (:func:`rtsgt.joint.clock.report_times`), ms."""
    sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return {
        "start_ms": float(offset[0] * 1e3), "end_ms": float(offset[-1] * 1e3),
        "max_abs_ms": float(np.max(np.abs(offset)) * 1e3),
        "median_sigma_ms": float(np.median(sig) * 1e3),
        "knots": int(knots.size),
        "span_s": [float(knots[0]), float(knots[-1])],
    }
