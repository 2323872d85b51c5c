"""The joint engine's entry point: every raw polar measurement to poses with covariance.

:func:`estimate_joint` builds the problem (knots, measurements, station priors), runs
Gauss-Newton from another engine's poses and reports poses at the query times in the
project's convention: docs/joint.md.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from rtsgt.choices import DEFAULT_MAX_GAP_S
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.geometry.so3 import log_so3
from rtsgt.geometry.transform import RigidTransform
from rtsgt.joint import deviation as pdev
from rtsgt.joint import gm as gmn
from rtsgt.joint.axes import body_qc, body_rotation, body_solution, velocities_in_body
from rtsgt.joint.blockcv import raw_block_cv, raw_block_summary
from rtsgt.joint.clock import clock_model, report_times
from rtsgt.joint.engine import (
    DECREASE_TOL,
    JointProblem,
    JointState,
    QcFit,
    SolveInfo,
    solve_with_qc,
    station_prior_info,
)
from rtsgt.joint.interpolate import interpolate_split_gp
from rtsgt.joint.knots import (
    DEFAULT_MERGE_S,
    body_velocities,
    build_knots,
    interpolate_poses,
)
from rtsgt.joint.measurements import GLOBAL_SOURCES, polar_measurements
from rtsgt.joint.noise import NoiseFit
from rtsgt.joint.prisms import (
    PrismFit,
    prism_prior_info,
    prism_tests,
    stability_factor,
)
from rtsgt.joint.relative import (
    JointPosterior,
    body_to_world,
    chain_gains,
    linear_covariance,
    origin_adjoint,
    world_covariance,
)
from rtsgt.joint.rocking import (
    ROCKING_DIM,
    bridge_variance,
    pivot_map,
    rocked_knots,
    start_rocking,
)
from rtsgt.joint.settling import settle_model
from rtsgt.joint.slow import at_times
from rtsgt.joint.sparse import add_shared_columns, solve_bytes
from rtsgt.noise.model import NoiseModel
from rtsgt.pose.estimate import PoseEstimate
from rtsgt.pose.registration import shape_ratio
from rtsgt.shared import POSE_COMPONENTS, SharedFactor

#: A whole run of the joint engine holds up to this many times one solve's memory
#: (:func:`rtsgt.joint.sparse.solve_bytes`): the field preset's runs measured 1.4-1.8 times
#: it in peak resident size (600 s, 1800 s and the hours, 2026-12-01: the interpreter, its
#: measurements, the solution it keeps, the prisms' hypotheses;
#: docs/joint.md#an-hours-floor).
RUN_PER_SOLVE = 1.8


@dataclass(frozen=True)
class JointResult:
    """Poses of the joint engine at the query times ``t`` (Q,) s.

    ``estimate``: a :class:`rtsgt.pose.estimate.PoseEstimate` (``engine = "joint"``; its 6x6
    covariances in the convention of :mod:`rtsgt.geometry.transform`); ``stations``: each
    station's estimated ``T_world_station`` with its covariance; ``kappa_ppm``,
    ``kappa_sigma_ppm``: the weather's error of the distance correction; ``qc``: the prior's
    ``Qc`` per motion class (:class:`rtsgt.joint.engine.QcFit`); ``clocks``: per
    non-reference station its clock knots' times, offsets and covariance; ``n_knots``,
    ``n_measurements``; ``solve``: iterations, convergence, costs; ``chi2_per_dof``: the
    final cost over the measurements' rows; ``shared``: the poses' error split
    (:class:`rtsgt.shared.SharedFactor`, ``total_cov`` = ``estimate.cov``) into the part
    given the global parameters and the part shared through them, one column per whitened
    global (:func:`global_names`; docs/joint.md#the-shared-error); ``prisms``: the prisms'
    estimated body positions and each one's test against its survey
    (:class:`rtsgt.joint.prisms.PrismFit`; None where they are held at the survey);
    ``noise``: the white noise's components per station and channel
    (:class:`rtsgt.joint.noise.NoiseFit`; None where the datasheet's is used as is);
    ``posterior``: the knots and the solution's covariances, for poses and their covariance
    between two times anywhere inside the knots (:class:`rtsgt.joint.relative.JointPosterior`);
    ``raw_block_cv``: the block cross-validation of the raw measurements
    (:func:`rtsgt.joint.blockcv.raw_block_summary`, JSON-ready); ``time_sync``: each
    station's constant clock offset against the robot's (``t_recorded - t_true``),
    ``(offset, sigma)`` s, by station (with the clock states, at their first knot);
    ``settling``: by station, its settling knots' times (J,), height change (J,) m, yaw change
    (J,) rad and their sigmas (J, 2) (docs/joint.md#settling-tripods; empty where not
    estimated); ``deviation``: the prisms' deviation with their viewing angle
    (:class:`rtsgt.joint.deviation.DeviationFit`, docs/joint.md#prism-deviation; None where
    not estimated); ``gauss_markov``: the Gauss-Markov noise's sigma and correlation time per
    station and channel (:class:`rtsgt.joint.gm.GaussMarkov`, docs/joint.md#gauss-markov-noise;
    None where not estimated); ``motion_axes``: the motion prior's axes as a rotation vector
    from the body frame's, ``log(R_mb)`` (3,) rad, and its covariance (3, 3) rad^2
    (docs/joint.md#the-motion-axes; None where not estimated); ``rocking``: the vehicle's
    rocking's sigma and correlation time per axis (:class:`rtsgt.joint.gm.GaussMarkov`, rows
    the shifts and the rotations; docs/joint.md#the-vehicles-rocking; None where not
    estimated) and ``rocking_pivot`` (3,) m the point its rotations are about, body frame
    (docs/joint.md#the-rockings-pivot; None: the prisms' centroid, or no rocking);
    ``prism_stability`` m the prisms' moves since the survey no station sees, 1 sigma,
    carried in the covariances (docs/joint.md#what-no-station-sees).
    """

    t: np.ndarray
    estimate: PoseEstimate
    stations: dict[str, RigidTransform]
    kappa_ppm: float
    kappa_sigma_ppm: float
    qc: QcFit
    clocks: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    n_knots: int
    n_measurements: int
    solve: SolveInfo
    chi2_per_dof: float
    shared: SharedFactor | None = None
    prisms: PrismFit | None = None
    noise: NoiseFit | None = None
    posterior: JointPosterior | None = None
    raw_block_cv: dict | None = None
    time_sync: dict[str, tuple[float, float]] = field(default_factory=dict)
    settling: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = field(
        default_factory=dict)
    deviation: pdev.DeviationFit | None = None
    gauss_markov: gmn.GaussMarkov | None = None
    motion_axes: tuple[np.ndarray, np.ndarray] | None = None
    rocking: gmn.GaussMarkov | None = None
    rocking_pivot: np.ndarray | None = None
    prism_stability: float = 0.0


def _stations(calibration):
    ids = tuple(calibration.transforms)
    T = [calibration.transforms[s] for s in ids]
    R = np.stack([x.rotation for x in T])
    t = np.stack([x.translation for x in T])
    cov = np.stack([np.zeros((6, 6)) if x.covariance is None else x.covariance for x in T])
    free = np.array([i for i in range(len(ids)) if np.trace(cov[i]) > 0], dtype=int)
    return ids, R, t, cov, free


def estimate_joint(observations, calibration, reference, model: NoiseModel, query_times,
                   init_t, init_R, init_p, qc, *, weather=None,
                   merge_s: float = DEFAULT_MERGE_S, max_iter: int = 10,
                   tol: float = DECREASE_TOL,
                   estimate_qc: bool = True, query_knots: bool = False,
                   clocks: bool = False, prisms: bool = False,
                   noise: bool = False, settling: bool = False,
                   calibrated_at: dict[str, float] | None = None, deviation: bool = False,
                   gauss_markov: bool = False, rng: np.random.Generator | None = None,
                   max_gap_s: float = DEFAULT_MAX_GAP_S, motion_axes: bool = False,
                   rocking: bool = False, memory_bytes: int | None = None) -> JointResult:
    """Poses ``T_world_body`` at ``query_times`` (Q,) s from every station's observations.

    ``observations``: one :class:`rtsgt.types.Observations` per station (valid, increasing
    times); ``calibration``: a :class:`rtsgt.calibration.result.CalibrationResult` (the
    stations' prior, its reference held); ``reference``: the prisms' body positions
    (:class:`rtsgt.pose.ReferencePoints`; with ``prisms`` estimated, its covariance their
    prior, docs/joint.md#prism-positions; else held); ``model``: the noise model (its white
    sources per measurement, its atmosphere as one parameter); ``init_t`` (T,), ``init_R``
    (T, 3, 3), ``init_p`` (T, 3): poses to start from (another engine's); ``qc`` (6,) the
    prior's diagonal PSD (m^2/s^3, rad^2/s^3; e.g. :func:`rtsgt.joint.knots.qc_from_prisms`),
    the start of its estimate per motion class (``estimate_qc``) or used as is. The poses at
    ``query_times`` are the GP's interpolation between the knots (at the measurement times),
    or with ``query_knots`` knots of their own (docs/joint.md#queries-between-knots). With
    ``clocks``, each station's clock offset against the calibration's reference station is
    estimated (docs/joint.md#clock-offsets) and the model's ``time_sync`` source is not
    carried as white noise. With ``noise``, the white noise per station and channel is
    estimated from the residuals, the model's white part its prior
    (docs/joint.md#noise-identification). With ``settling``, each station's height and yaw
    change since its calibration are estimated (docs/joint.md#settling-tripods; the
    reference station's from their prior alone), from rest at ``calibrated_at`` (s, by
    station; a station not in it, or None: at its first measurement). With ``deviation``,
    each prism's deviation with the azimuth its station sees it under is estimated, low
    harmonics with a prior of a few millimetres (docs/joint.md#prism-deviation). With
    ``gauss_markov`` (and ``noise``), each station's channels carry a first-order
    Gauss-Markov noise as states of the knots, its sigma and correlation time estimated
    (docs/joint.md#gauss-markov-noise; ``rng`` the draws of their observed information,
    None: approximated without draws). With ``rocking`` (and ``noise``), the vehicle's rocking
    is a first-order Gauss-Markov process per axis of the knots' pose, its sigma and
    correlation time estimated as the chains' (docs/joint.md#the-vehicles-rocking), its
    rotations about ``reference.pivot`` where given (else the prisms' centroid;
    docs/joint.md#the-rockings-pivot), and the poses are the rocked ones, with its variance
    between the knots.
    ``max_gap_s``: a longer gap between a station's measurements starts new blocks of the
    raw block cross-validation (docs/joint.md#block-cross-validation-of-the-measurements),
    and a longer interval between knots (no station measured) has a motion prior of its own,
    the loosest of the run's moving classes' (docs/joint.md#gaps).
    With ``motion_axes``, the motion prior is written in axes of its own, their rotation from
    the body frame estimated (docs/joint.md#the-motion-axes); the poses are the body frame's.
    ``memory_bytes``: the memory the run may take (None: not checked); an InputError, before
    any solve, where one solve of the problem needs more
    (:func:`rtsgt.joint.sparse.solve_bytes`, docs/joint.md#an-hours-floor).
    """
    init_t = np.asarray(init_t, dtype=float)
    if init_t.size < 2:
        raise InputError(f"Expected at least 2 initial poses, got {init_t.size}")
    ids, R_s, t_s, cov_s, free = _stations(calibration)
    names = tuple(reference.names)
    sync = "time_sync" in model.sources and model.time_sync_second_moment_s2 > 0
    carried = GLOBAL_SOURCES + (("time_sync",) if clocks or sync else ())
    meas = polar_measurements(observations, ids, names, model, weather, carried)
    tq = np.asarray(query_times, dtype=float)
    knots = build_knots(meas.t, tq if query_knots else np.zeros(0), merge_s)
    survey = np.asarray(reference.xyz, dtype=float)
    origin = survey.mean(axis=0)  # the knots' frame's origin (docs/joint.md#the-knots-origin)
    survey = survey - origin
    R0, p0 = interpolate_poses(knots.t, init_t, init_R, init_p)
    p0 = p0 + R0 @ origin
    qc = np.asarray(qc, dtype=float)
    if qc.shape != (6,) or not np.all(qc > 0):
        raise InputError(f"Expected qc of shape (6,), positive, got {qc!r}")
    info = np.stack([station_prior_info(c) for c in cov_s])
    ck = None
    ref = ids.index(calibration.reference_station)
    # each station's constant clock offset against the robot's (the time_sync source, once
    # per deployment); with the clock states, those are its drift from the first knot on
    sync_col = np.arange(len(ids)) if sync else None
    if clocks and len(ids) > 1:  # a lone station has no clock to estimate against
        ck = clock_model(meas.station, len(ids), ref, anchored=sync)
    p_info = prism_prior_info(reference.cov) if prisms else None
    prob = JointProblem(knots.t, knots.of_measurement, knots.tau, meas, survey, R_s, t_s, info,
                        free, qc, ck, p_info, np.asarray(reference.cov, dtype=float),
                        sync_column=sync_col, sync_var=model.time_sync_second_moment_s2,
                        settle=_settle(knots.t[0], ids, calibrated_at) if settling else None,
                        deviation_orders=pdev.ORDERS if deviation else (),
                        deviation_sigma=_deviation_sigma(knots, meas, R0, p0, survey, t_s)
                        if deviation else None,
                        gm=gmn.start_model(meas.var_white, meas.station, len(ids))
                        if gauss_markov and noise else None, motion_axes=motion_axes,
                        max_gap_s=max_gap_s, rocking=start_rocking() if rocking and noise else None,
                        pivot=None if reference.pivot is None else reference.pivot - origin)
    K = knots.t.size
    _check_memory(K, prob.knot_dim, prob.n_globals, memory_bytes)
    state = JointState(R0, p0, body_velocities(knots.t, R0, p0), R_s, t_s, 0.0,
                       None if ck is None else np.zeros((K, ck.size)),
                       None if p_info is None else survey.copy(),
                       None if sync_col is None else np.zeros(prob.n_sync),
                       None if not settling else np.zeros((K, prob.settle.size)),
                       None if not deviation else np.zeros((len(names),
                                                            pdev.n_coefficients(pdev.ORDERS))),
                       None if prob.gm is None else np.zeros((K, prob.n_gm)),
                       np.eye(3) if motion_axes else None,
                       None if prob.rocking is None else np.zeros((K, ROCKING_DIM)))
    prob, state, sol, solve, qc_fit = solve_with_qc(prob, state, estimate_qc, max_iter, tol,
                                                    noise, rng)
    block_cv = raw_block_summary(raw_block_cv(prob, state, sol, max_gap_s), ids)
    body = _body_knots(prob, state, sol)
    body, cov_g, blind = _with_stability(prob, body, sol.cov_g, reference.stability, names)
    pfit = None if p_info is None else _prism_fit(names, prob, state, cov_g, origin)
    bridge = _rocking_bridge(prob, state)
    slow = prob.clock is not None or prob.settle is not None  # reported along the chain
    gains = chain_gains(body[4]) if slow else None
    posterior = JointPosterior(knots.t, *body[:4], body[4], bridge, origin)
    R, t, cov_pose = posterior.poses(tq)
    globals_ = global_names(prob, ids, names)
    moved = tuple(f"moved_{names[j]}" for j, _, _ in prob.carried_alternatives)
    shared = _shared(tq, knots.t, body,  # the columns of engine.carry_alternatives' mixture
                     globals_ + tuple(f"{m}_{g}" for m in moved for g in globals_) + moved
                     + blind, bridge, origin)
    est = _pose_estimate(R, t, cov_pose, survey if pfit is None else pfit.xyz)
    return JointResult(tq, est, _station_results(ids, free, state, cov_g), state.kappa_ppm,
                       meas.kappa_sigma_ppm, qc_fit, _clocks(prob, state, body[4], gains, ids, ref),
                       knots.t.size, meas.t.size, solve,
                       solve.costs[-1] / (3 * meas.t.size), shared, pfit,
                       None if prob.noise is None else replace(prob.noise, stations=ids),
                       posterior, block_cv,
                       _time_sync(prob, state, cov_g, globals_),
                       _settling(prob, state, body[4], gains, ids), _deviation(prob, state, cov_g, names),
                       None if prob.gm is None else replace(prob.gm, stations=ids),
                       _motion_axes(prob, state, cov_g), prob.rocking,
                       None if prob.rocking is None or prob.pivot is None
                       else prob.pivot + origin, reference.stability)


def _check_memory(K: int, d: int, G: int, memory_bytes: int | None) -> None:
    """InputError where one solve of ``K`` knots of ``d`` states and ``G`` globals needs more
    than ``memory_bytes`` (:func:`rtsgt.joint.sparse.solve_bytes`); a warning where a whole
    run, :data:`RUN_PER_SOLVE` times that, may (None: not checked)."""
    if memory_bytes is None:
        return
    need = solve_bytes(K, d, G)
    size = f"{K} knots of {d} states and {G} globals"
    remedy = "run a shorter deployment, or a per-prism engine (--engine linear)"
    if need > memory_bytes:
        raise InputError(f"joint engine: {size} need at least {need / 1e9:.1f} GB for one "
                         f"solve, {memory_bytes / 1e9:.1f} GB is available: {remedy}")
    if RUN_PER_SOLVE * need > memory_bytes:
        warnings.warn(f"joint engine: {size} may need up to {RUN_PER_SOLVE * need / 1e9:.1f} "
                      f"GB, {memory_bytes / 1e9:.1f} GB is available; if the run is stopped "
                      f"for memory: {remedy}", RtsgtWarning, stacklevel=3)


def _with_stability(prob: JointProblem, body, cov_g: np.ndarray, sigma: float, names):
    """The knots ``body`` (:func:`_body_knots`) and the globals' covariance ``cov_g`` with
    the prisms' moves since the survey that no station sees carried, ``sigma`` m along
    each one's blind directions (:func:`rtsgt.joint.prisms.stability_factor`, a consider
    parameter: it moves no estimate) as shared columns of the solution, and their names
    (``blind_<prism>``, with ``_<i>`` where a prism has several); unchanged for 0
    (docs/joint.md#what-no-station-sees)."""
    if sigma <= 0.0:
        return body, cov_g, ()
    dxi, dp, owner = stability_factor(prob.p_body, sigma)
    sol = body[4]
    r = dxi.shape[1]
    dx = np.zeros((r,) + sol.x.shape)
    dx[:, :, :6] = dxi.T[:, None, :]  # the same body-frame turn at every knot
    dg = np.zeros((r, sol.g.size))
    if prob.n_prism:
        sl = slice(prob.kappa_col + 1, prob.kappa_col + 1 + prob.n_prism)
        dg[:, sl] = dp.T
    per = np.bincount(owner, minlength=len(names))
    out = tuple(f"blind_{names[j]}" + (f"_{i}" if per[j] > 1 else "")
                for j in range(len(names)) for i in range(per[j]))
    return (*body[:4], add_shared_columns(sol, dx, dg)), cov_g + dg.T @ dg, out


def _motion_axes(prob: JointProblem, state: JointState, cov_g):
    """The motion axes' rotation from the body frame, ``log(R_mb)`` (3,) rad, with its
    covariance (3, 3) rad^2; None where they are not estimated."""
    if not prob.n_axes:
        return None
    sl = slice(prob.axes_col, prob.axes_col + 3)
    c = cov_g[sl, sl]
    return log_so3(state.R_mb), 0.5 * (c + c.T)


def _settle(t0, ids, calibrated_at):
    """The settling model from rest at each station's calibration time (``t0`` the first
    knot's)."""
    cal = calibrated_at or {}
    return settle_model(t0, np.array([cal.get(sid, t0) for sid in ids]))


def _report(prob: JointProblem, sol, gains, z: np.ndarray, col: int,
            Ag: np.ndarray | None = None):
    """The levels of slowly varying processes (:mod:`rtsgt.joint.slow`; ``z`` (K, 2 n) the
    knots' states, at knot columns ``col`` on) at the report times (J,)
    (:func:`rtsgt.joint.clock.report_times`): the times, the levels (J, n) and their
    covariance (n J, n J), process-major, with ``Ag`` (n, G) adding globals to each level
    (``gains`` the chain's of ``sol``, :func:`rtsgt.joint.relative.chain_gains`)."""
    t = report_times(float(prob.t_knot[0]), float(prob.t_knot[-1]))
    lv, k, w = at_times(z, prob.t_knot, t)
    n, J = z.shape[1] // 2, t.size
    Ax = np.zeros((n, J, prob.knot_dim))
    for i in range(n):  # a handful of processes
        Ax[i, :, col + 2 * i:col + 2 * i + 2] = w
    Ag = np.zeros((n, prob.n_globals)) if Ag is None else Ag
    cov = linear_covariance(sol, gains, np.tile(k, n), Ax.reshape(n * J, -1), np.repeat(Ag, J, 0))
    return t, lv, cov


def _settling(prob: JointProblem, state: JointState, sol, gains, ids) -> dict:
    """Each station's settling at the report times: the times, height and yaw changes and
    their sigmas (J, 2)."""
    st = prob.settle
    if st is None:
        return {}
    t, lv, cov = _report(prob, sol, gains, state.settle, prob.settle_col)
    J = t.size
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None)).reshape(-1, J)  # (2 S, J)
    return {sid: (t, lv[:, 2 * i].copy(), lv[:, 2 * i + 1].copy(),
                  sd[2 * i:2 * i + 2].T.copy()) for i, sid in enumerate(ids)}


def _deviation_sigma(knots, meas, R0, p0, survey, t_s) -> np.ndarray:
    """The deviation's prior sigmas from the viewing azimuths of the poses to start from."""
    k = knots.of_measurement
    alpha = pdev.viewing_azimuth_body(R0[k], p0[k], survey[meas.prism], t_s[meas.station])[0]
    return pdev.deviation_prior_sigma(alpha, meas.prism, survey.shape[0])


def _deviation(prob: JointProblem, state: JointState, cov_g, names) -> pdev.DeviationFit | None:
    """The prisms' deviation coefficients, their covariance and which the data determine."""
    if not prob.n_deviation:
        return None
    sl = slice(prob.deviation_col, prob.deviation_col + prob.n_deviation)
    cov = 0.5 * (cov_g[sl, sl] + cov_g[sl, sl].T)
    return pdev.DeviationFit(tuple(names), prob.deviation_orders, state.deviation.copy(), cov,
                             prob.deviation_sigma)


def _time_sync(prob: JointProblem, state: JointState, cov_g, names) -> dict:
    """Each constant clock offset's estimate and sigma, s, by station (``names``: the
    globals', :func:`global_names`)."""
    if not prob.n_sync:
        return {}
    out = {}
    for j in range(prob.n_sync):
        c = prob.sync_col + j
        sid = names[c].removeprefix("time_sync_station")
        out[sid] = (float(state.sync[j]), float(np.sqrt(max(cov_g[c, c], 0.0))))
    return out


def _prism_fit(names, prob: JointProblem, state: JointState, cov_g, origin) -> PrismFit:
    """The prisms' estimates and tests in the body frame (``origin`` (3,) m the knots'
    frame's): a prism found moved keeps its statistic at detection."""
    sl = slice(prob.kappa_col + 1, prob.kappa_col + 1 + prob.n_prism)
    cov = cov_g[sl, sl]
    moved = np.zeros(len(names), bool)
    moved[[j for j, _, _ in prob.prism_found]] = True
    tests = prism_tests(prob.p_body, prob.prism_info, state.p_body, cov, ~moved)
    stat, dof = tests.stat.copy(), tests.dof.copy()
    for j, st, df in prob.prism_found:
        stat[j], dof[j] = st, df
    weight = moved.astype(float)
    above = np.full(len(names), np.nan)
    for j, cost, w in prob.prism_alternatives:
        weight[j], above[j] = w, cost
    if prob.carried_alternatives:  # the found one shares the weights
        weight[prob.prism_found[-1][0]] = prob.carried_alternatives[0][2]
    return PrismFit(names, state.p_body + origin, 0.5 * (cov + cov.T), prob.p_body + origin,
                    moved, np.sqrt(stat), dof, weight, above)


def _station_results(ids, free, state, cov_g) -> dict[str, RigidTransform]:
    stations = {}
    for i, sid in enumerate(ids):
        j = np.nonzero(free == i)[0]
        c = cov_g[6 * j[0]:6 * j[0] + 6, 6 * j[0]:6 * j[0] + 6] if j.size else np.zeros((6, 6))
        stations[sid] = RigidTransform(state.R_s[i], state.t_s[i], 0.5 * (c + c.T),
                                       "world", f"station_{sid}")
    return stations


def global_names(prob: JointProblem, ids, prisms=()) -> tuple[str, ...]:
    """Names of the problem's global parameters in their order: the free stations'
    ``calibration_station<id>_<x|y|z|rx|ry|rz>`` (world frame, as the per-prism pipeline's
    shared columns), ``atmosphere_ppm``, the prisms' ``reference_<prism>_<x|y|z>`` (where
    estimated; ``prisms`` their names), the stations' constant clock offsets
    ``time_sync_station<id>``, the prisms' deviation
    ``deviation_<prism>_<order>_<cos|sin>_<range|across|vertical>``, the motion axes'
    ``motion_axes_<rx|ry|rz>`` (where estimated)."""
    names = [f"calibration_station{ids[i]}_{c}" for i in prob.free for c in POSE_COMPONENTS]
    names.append("atmosphere_ppm")
    if prob.n_prism:
        names += [f"reference_{p}_{c}" for p in prisms for c in "xyz"]
    if prob.n_sync:
        names += [f"time_sync_station{s}" for s in ids]
    if prob.n_deviation:
        names += [f"deviation_{p}_{k}_{trig}_{comp}" for p in prisms
                  for k in prob.deviation_orders for trig in pdev.TRIG
                  for comp in pdev.COMPONENTS]
    if prob.n_axes:
        names += [f"motion_axes_{c}" for c in POSE_COMPONENTS[3:]]
    return tuple(names)


def _body_knots(prob: JointProblem, s: JointState, sol):
    """The knots as body-frame poses: ``R`` (K, 3, 3), ``t`` (K, 3), velocities ``w`` (K, 6),
    the prior's ``qc`` per interval and the :class:`rtsgt.joint.sparse.ArrowSolution`
    (with the vehicle's rocking where it is estimated, :func:`rtsgt.joint.rocking.rocked_knots`;
    turned from the motion axes where they are estimated, :mod:`rtsgt.joint.axes`)."""
    R, t = s.R, s.t
    if prob.rocking is not None:
        R, t, sol = rocked_knots(R, t, s.rocking, sol, prob.rocking_col)
    if not prob.n_axes:
        return R, t, s.w, prob.qc, sol
    w = velocities_in_body(s.w, s.R_mb)
    return (R @ s.R_mb, t, w, body_qc(prob.qc, s.R_mb),
            body_solution(sol, s.R_mb, w, prob.axes_col))


def _rocking_bridge(prob: JointProblem, s: JointState):
    """The rocking's variance between the knots with the body's axes, at the knots' origin,
    ``t`` (Q,) -> (Q, 6, 6) (:func:`rtsgt.joint.rocking.bridge_variance`, the process's about
    the pivot (:func:`rtsgt.joint.rocking.pivot_map`), turned from the motion axes; to the
    body's origin by :class:`rtsgt.joint.relative.JointPosterior`); None without the
    rocking."""
    if prob.rocking is None:
        return None
    A = (np.eye(6) if s.R_mb is None else body_rotation(s.R_mb)) @ pivot_map(prob.pivot)
    return lambda t: (A * bridge_variance(t, prob.t_knot, prob.rocking)[:, None, :]) @ A.T


def _shared(tq, t_knot, body, names, bridge=None, origin=None) -> SharedFactor:
    """The query poses' :class:`SharedFactor` in the world frame (columns: the globals'
    Cholesky factor, named by ``names``) from the knots ``body`` (:func:`_body_knots`), the
    rocking's ``bridge`` variance (:func:`_rocking_bridge`) in the varying part, turned to
    the body frame's origin from the knots' ``origin``
    (:func:`rtsgt.joint.relative.origin_adjoint`)."""
    R_k, t_k, w_k, qc, sol = body
    R, _, var, L = interpolate_split_gp(tq, t_knot, R_k, t_k, w_k, qc, sol.cov_var,
                                        sol.cov_var_next, sol.factor)
    if bridge is not None:
        var = var + bridge(tq)
    A = origin_adjoint(origin)
    return SharedFactor(tq, body_to_world(R) @ A @ L, names, body_to_world_cov(R, A @ var @ A.T))


def _clocks(prob, state, sol, gains, ids, reference: int):
    """Each non-reference station's clock offset against the ``reference`` station at the
    report times: its drift (the clock states) plus, where estimated, the difference of the
    two stations' constant offsets; ``(times, offsets (J,), covariance (J, J))``."""
    ck = prob.clock
    if ck is None:
        return {}
    C = ck.station.size
    Ag = np.zeros((C, prob.n_globals))
    if prob.n_sync:
        Ag[np.arange(C), prob.sync_col + ck.station] += 1.0
        Ag[:, prob.sync_col + reference] -= 1.0
    t, lv, cov = _report(prob, sol, gains, state.clock, prob.clock_col, Ag)
    if prob.n_sync:
        lv = lv + state.sync[ck.station] - state.sync[reference]
    J = t.size
    return {ids[sidx]: (t, lv[:, i].copy(), cov[i * J:(i + 1) * J, i * J:(i + 1) * J].copy())
            for i, sidx in enumerate(ck.station)}


def body_to_world_cov(R: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariance (Q, 6, 6) of a right (body) perturbation ``T exp(d^)`` of poses ``R``
    (Q, 3, 3) as the world-frame ``(dt, dtheta)`` of :mod:`rtsgt.geometry.transform`:
    ``A cov A^T``, ``A = diag(R, R)`` (``dt = R rho``, ``dtheta = R phi`` to first order),
    symmetrised (:func:`rtsgt.joint.relative.world_covariance`)."""
    out = world_covariance(R, cov)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def _pose_estimate(R, t, cov, p_body) -> PoseEstimate:
    n = p_body.shape[0]
    pairs = tuple((i, j) for i in range(n) for j in range(i + 1, n))
    dist = np.array([np.linalg.norm(p_body[i] - p_body[j]) for i, j in pairs])
    Q = R.shape[0]
    return PoseEstimate(
        R=R, t=t, cov=cov, degenerate=np.zeros(Q, bool), reason=np.full(Q, ""),
        inter_prism_distance=np.broadcast_to(dist, (Q, dist.size)).copy(),
        rms_residual=np.full(Q, np.nan), shape=np.full(Q, float(shape_ratio(p_body))),
        pairs=pairs, engine="joint", registration="joint",
    )
