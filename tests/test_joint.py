"""The joint engine (rtsgt.joint, issue 23 step 2): SE(3) Jacobians against finite
differences, the arrow solver against a dense solve, Gauss-Newton on a noise-free problem,
the covariance convention, and poses on simulated deployments against their truth."""

from __future__ import annotations

import tracemalloc
import warnings
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from rtsgt.clocks import walk_prior_info
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.geometry.so3 import exp_so3, hat, quat_xyzw_to_matrix
from rtsgt.geometry.transform import perturbation
from rtsgt.io.deployment import load_deployment
from rtsgt.joint import engine as engine_module
from rtsgt.joint import estimate as estimate_module
from rtsgt.joint import estimate_joint, sparse
from rtsgt.joint import gm as gmn
from rtsgt.joint.clock import clock_model, report_times
from rtsgt.joint.deviation import ORDERS as DEVIATION_ORDERS
from rtsgt.joint.deviation import n_coefficients
from rtsgt.joint.engine import (
    HYPOTHESIS_MAX_ITER,
    UNDECIDED_COST,
    JointProblem,
    JointState,
    assemble,
    carry_alternatives,
    difference,
    gauss_newton,
    measurement_hsh,
    measurement_terms,
    retract,
    snoop_prisms,
    solve_with_qc,
    undecided,
)
from rtsgt.joint.estimate import RUN_PER_SOLVE, body_to_world_cov
from rtsgt.joint.interpolate import interpolate_poses_gp
from rtsgt.joint.knots import build_knots, qc_from_prisms
from rtsgt.joint.measurements import PolarMeasurements, predict, residual
from rtsgt.joint.prior import prior_terms, wnoa_q_inv
from rtsgt.joint.prisms import blind_moves, prism_tests, stability_factor
from rtsgt.joint.qc import (
    N_CLASSES,
    QC_FLOOR,
    VCE_TOL,
    class_members,
    prior_components,
    qc_per_class,
    with_gaps,
)
from rtsgt.joint.rocking import (
    add_rocking_prior,
    bridge_variance,
    pivot_map,
    rocked_knots,
    rocking_moments,
    start_rocking,
)
from rtsgt.joint.se3 import (
    curly,
    exp_se3,
    jacobians_inv,
    left_jacobian,
    log_se3,
    so3_left_jacobian,
)
from rtsgt.joint.settling import (
    HOUR_DRIFT_SIGMA,
    HOUR_S,
    HOUR_WALK_SIGMA,
    settle_model,
    settle_start,
)
from rtsgt.joint.slow import LevelRate
from rtsgt.joint.sparse import ArrowSystem, knot_rows, solve_arrow, solve_bytes
from rtsgt.measurement.polar import cartesian_to_polar
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.presets import preset_config
from rtsgt.simulation.reality import RealityEffects

EPS = 1e-6


def _compose(R1, t1, R2, t2):
    return R1 @ R2, np.einsum("...ij,...j->...i", R1, t2) + t1


def _right(R, t, d):
    """``T exp(d^)`` for a right perturbation ``d`` (..., 6)."""
    dR, dt = exp_se3(d)
    return _compose(R, t, dR, dt)


def test_se3_exp_log_round_trip_and_left_jacobian_against_finite_differences():
    rng = np.random.default_rng(1)
    xi = rng.normal(size=(20, 6)) * np.r_[1.0, 1.0, 1.0, 0.6, 0.6, 0.6]
    xi[0, 3:] = 1e-5  # the small-angle branch
    R, t = exp_se3(xi)
    np.testing.assert_allclose(log_se3(R, t), xi, atol=1e-10)
    jl = left_jacobian(xi)
    for j in range(6):
        e = np.zeros(6)
        e[j] = EPS
        # exp(xi + e) = exp(J_l(xi) e) exp(xi) to first order
        Rp, tp = exp_se3(xi + e)
        Rm, tm = exp_se3(xi - e)
        Ri = np.swapaxes(R, 1, 2)
        num = (log_se3(*_compose(Rp, tp, Ri, -np.einsum("kij,kj->ki", Ri, t)))
               - log_se3(*_compose(Rm, tm, Ri, -np.einsum("kij,kj->ki", Ri, t)))) / (2 * EPS)
        np.testing.assert_allclose(num, jl[:, :, j], atol=1e-7)
    jli, jri = jacobians_inv(xi)
    np.testing.assert_allclose(jli @ jl, np.broadcast_to(np.eye(6), jl.shape), atol=1e-10)
    np.testing.assert_allclose(jri @ left_jacobian(-xi), np.broadcast_to(np.eye(6), jl.shape),
                               atol=1e-10)
    phi = xi[:, 3:]
    np.testing.assert_allclose(so3_left_jacobian(phi, inverse=True) @ so3_left_jacobian(phi),
                               np.broadcast_to(np.eye(3), (20, 3, 3)), atol=1e-12)


def _trajectory(K, rng, scale=1.0):
    t = np.cumsum(rng.uniform(0.1, 0.4, K))
    w = rng.normal(size=(K, 6)) * np.r_[1.0, 0.3, 0.1, 0.02, 0.02, 0.3] * scale
    R = exp_so3(rng.normal(size=(K, 3)) * 0.5)
    p = rng.normal(size=(K, 3)) * 5.0
    return t, R, p, w


def test_prior_jacobians_against_finite_differences():
    """The pose rows exactly; the velocity rows' d(J_r^-1 w)/d xi is first order in xi."""
    rng = np.random.default_rng(2)
    t, R, p, w = _trajectory(2, rng)
    # a second pose near the first one's constant-velocity prediction
    R[1], p[1] = _right(R[0], p[0], 0.25 * w[0] + 0.01 * rng.normal(size=6))
    dt = np.diff(t)
    e0, E, F = prior_terms(R, p, w, dt)
    for knot, Jac in ((0, E), (1, F)):
        for j in range(12):
            d = np.zeros((2, 12))
            d[knot, j] = EPS
            out = []
            for s in (1.0, -1.0):
                Rk, pk = _right(R, p, s * d[:, :6])
                out.append(prior_terms(Rk, pk, w + s * d[:, 6:], dt)[0])
            num = (out[0] - out[1]) / (2 * EPS)
            np.testing.assert_allclose(num[0, :6], Jac[0, :6, j], atol=1e-7)
            np.testing.assert_allclose(num[0, 6:], Jac[0, 6:, j], atol=0.05)


def test_measurement_jacobians_against_finite_differences():
    rng = np.random.default_rng(3)
    M = 7
    _, R, p, w = _trajectory(M, rng)
    tau = rng.uniform(-0.05, 0.05, M)  # clock offsets of tens of ms: the second order counts
    pb = rng.normal(size=(M, 3))
    R_s = exp_so3(rng.normal(size=(M, 3)) * 0.1)
    t_s = p + rng.normal(size=(M, 3)) * 30.0
    h, Hk, Hs, Hkap, Htau, Bp = predict(R, p, w, tau, pb, R_s, t_s, 2.0)
    for j in range(12):
        d = np.zeros((M, 12))
        d[:, j] = EPS
        hs = [predict(*_right(R, p, s * d[:, :6]), w + s * d[:, 6:], tau, pb, R_s, t_s, 2.0)[0]
              for s in (1.0, -1.0)]
        np.testing.assert_allclose(residual(hs[0], hs[1]) / (2 * EPS), Hk[:, :, j], atol=1e-7)
    for j in range(6):
        d = np.zeros((M, 6))
        d[:, j] = EPS
        hs = [predict(R, p, w, tau, pb, exp_so3(s * d[:, 3:]) @ R_s, t_s + s * d[:, :3], 2.0)[0]
              for s in (1.0, -1.0)]
        np.testing.assert_allclose(residual(hs[0], hs[1]) / (2 * EPS), Hs[:, :, j], atol=1e-7)
    hs = [predict(R, p, w, tau, pb, R_s, t_s, 2.0 + s * 1e-3)[0] for s in (1.0, -1.0)]
    np.testing.assert_allclose((hs[0] - hs[1]) / 2e-3, Hkap, atol=1e-12)
    hs = [predict(R, p, w, tau + s * EPS, pb, R_s, t_s, 2.0)[0] for s in (1.0, -1.0)]
    np.testing.assert_allclose(residual(hs[0], hs[1]) / (2 * EPS), Htau, atol=1e-7)
    for j in range(3):
        d = np.zeros((M, 3))
        d[:, j] = EPS
        hs = [predict(R, p, w, tau, pb + s * d, R_s, t_s, 2.0)[0] for s in (1.0, -1.0)]
        np.testing.assert_allclose(residual(hs[0], hs[1]) / (2 * EPS), (Hk[:, :, :3] @ Bp)[:, :, j],
                                   atol=1e-7)


def test_measured_point_is_the_constant_velocity_motion_to_third_order():
    """The prism carried from its knot by ``tau``: ``T_k exp(tau w^) p`` (the WNOA prior's
    motion at the knot's velocity), wrong by O(tau^3): the error falls 8x when tau halves."""
    rng = np.random.default_rng(4)
    M = 50
    _, R, p, w = _trajectory(M, rng)
    w[:, 3:] = rng.normal(size=(M, 3))  # turning at about 1 rad/s
    pb = rng.normal(size=(M, 3))
    R_s, t_s = np.broadcast_to(np.eye(3), (M, 3, 3)), p + rng.normal(size=(M, 3)) * 30.0

    def error(tau):
        h = predict(R, p, w, np.full(M, tau), pb, R_s, t_s, 0.0)[0]
        hz, v, d = h.T
        q = d[:, None] * np.stack([np.sin(v) * np.sin(hz), np.sin(v) * np.cos(hz), np.cos(v)], 1)
        Rm, tm = _right(R, p, tau * w)
        exact = np.einsum("mij,mj->mi", Rm, pb) + tm - t_s
        return np.linalg.norm(q - exact, axis=1)

    big, small = error(0.04), error(0.02)
    u = w[:, :3] + np.cross(w[:, 3:], pb)
    second = 0.5 * 0.04**2 * np.linalg.norm(np.cross(w[:, 3:], u), axis=1)  # a first order's
    assert np.all(big < 0.1 * second)
    ratio = np.median(big / small)
    assert 6.5 < ratio < 9.5


def _apparent_shift(q, coef):
    """Station-frame points ``q`` (K, 3) seen displaced by the deviation ``coef`` (K, 3):
    range, across (towards a larger Hz) and vertical (up), m; rtsgt.joint.deviation's
    components built here from the geometry, not from its Jacobian."""
    los = q / np.linalg.norm(q, axis=1, keepdims=True)
    across = np.stack([q[:, 1], -q[:, 0], 0 * q[:, 0]], axis=1)  # d q / d Hz, Hz = atan2(x, y)
    across /= np.linalg.norm(across, axis=1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0]) - los[:, 2:] * los
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    return q + coef[:, :1] * los + coef[:, 1:2] * across + coef[:, 2:] * up


#: The synthetic rig's prisms in the body frame, m (:func:`_synthetic`).
SURVEY = np.array([[0.5, 0.3, 0.4], [-0.4, 0.35, 0.45], [0.0, -0.4, 0.5]])


def _in_plane_move(size: float = 0.02):
    """The synthetic rig's unit normal (3,) and a move (3,) of ``size`` m of prism 1 in the
    prisms' plane (along x, the normal's part taken out)."""
    n = np.cross(SURVEY[1] - SURVEY[0], SURVEY[2] - SURVEY[0])
    n /= np.linalg.norm(n)
    d = np.array([1.0, 0.0, 0.0]) - n[0] * n
    return n, d * size / np.linalg.norm(d)


def _synthetic(rng, K=40, noise=0.0, speed=1.0, clock_s=None, moved=None, settle_rate=None,
               deviation=None, jump=None):
    """Noise-free (or noisy) polar measurements of three prisms on a constant-velocity
    trajectory (its velocity times ``speed``) by three stations, the first fixed, the others
    with a prior; with ``clock_s`` (3,) each station's clock ``t_recorded - t_true``, s, and
    clock states in the problem; with ``moved`` (3,) m the first prism is
    measured there away from its survey, and the prisms are parameters with the survey
    (1 mm per axis) as prior; with ``settle_rate`` (3, 2) each station's height (m/s) and yaw
    (rad/s, about the vertical) change from t = 0 on, and settling states in the problem
    (calibrated at t = 0, their prior 100 times the default); with ``deviation`` (3, C) each
    prism's deviation coefficients (rtsgt.joint.deviation.ORDERS) applied to its
    measurements and deviation states in the problem (prior sigma 1 m: the data alone); with
    ``jump`` ``(k, shift)`` the robot is moved by ``shift`` (3,) m (world) from knot ``k``
    on."""
    w0 = np.array([1.0, 0.1, 0.0, 0.0, 0.0, 0.15]) * speed
    t = np.arange(K) * 0.4
    R0, p0 = exp_so3(np.array([0.0, 0.0, 0.3])), np.array([2.0, -1.0, 0.5])
    R, p = _compose(R0, p0, *exp_se3(t[:, None] * w0))
    if jump is not None:
        p[jump[0]:] += np.asarray(jump[1], dtype=float)
    lag = np.zeros(K) if clock_s is None else np.asarray(clock_s)[np.arange(K) % 3]
    Rm, pm = _compose(R0, p0, *exp_se3((t - lag)[:, None] * w0))  # where it was measured
    if jump is not None:
        pm[jump[0]:] += np.asarray(jump[1], dtype=float)
    pb = SURVEY.copy()
    t_s = np.array([[0.0, 0.0, 0.0], [25.0, 5.0, 0.3], [-5.0, 22.0, -0.2]])
    R_s = exp_so3(np.array([[0.0, 0.0, 0.0], [0.001, -0.002, 1.0], [0.0, 0.001, -2.0]]))
    sid = np.arange(K) % 3
    k = np.arange(K)
    pt = pb.copy()
    if moved is not None:
        pt[0] += moved
    pw = np.einsum("kij,kj->ki", Rm, pt[sid]) + pm
    R_st, t_st = R_s[sid], t_s[sid].copy()
    if settle_rate is not None:  # the set-up at the measurement's time
        rate = np.asarray(settle_rate, dtype=float)[sid]
        t_st[:, 2] += rate[:, 0] * t
        R_st = exp_so3(np.stack([0 * t, 0 * t, rate[:, 1] * t], axis=1)) @ R_st
    q = np.einsum("kji,kj->ki", R_st, pw - t_st)
    if deviation is not None:  # the harmonics of the azimuth of the station in the body frame
        los_b = np.einsum("kji,kj->ki", Rm, t_st - pw)
        ka = np.arctan2(los_b[:, 1], los_b[:, 0])[:, None] * np.asarray(DEVIATION_ORDERS)
        c = np.asarray(deviation).reshape(3, len(DEVIATION_ORDERS), 2, 3)[sid]
        q = _apparent_shift(q, np.einsum("ko,kot->kt", np.cos(ka), c[:, :, 0])
                            + np.einsum("ko,kot->kt", np.sin(ka), c[:, :, 1]))
    y = np.stack(cartesian_to_polar(q), axis=1)
    sig = np.array([3e-5, 3e-5, 1e-3])
    y = y + noise * rng.normal(size=y.shape) * sig
    info = np.broadcast_to(np.diag(1.0 / sig**2), (K, 3, 3)).copy()
    meas = PolarMeasurements(t, sid, sid, y, info, 1.0, np.broadcast_to(sig**2, (K, 3)).copy(),
                             np.broadcast_to(np.eye(3), (K, 3, 3)).copy())
    cov_s = np.diag([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8])
    info_s = np.stack([np.eye(6), np.linalg.inv(cov_s), np.linalg.inv(cov_s)])
    ck = None if clock_s is None else clock_model(sid, 3, 0)
    p_info = None if moved is None else np.eye(9) / 1e-6
    st = None if settle_rate is None else settle_model(0.0, np.zeros(3), scale=(100.0, 100.0))
    prob = JointProblem(t, k, np.zeros(K), meas, pb, R_s, t_s, info_s, np.array([1, 2]),
                        np.array([0.1, 0.1, 0.01, 1e-3, 1e-3, 0.01]), ck, p_info,
                        None if moved is None else np.eye(9) * 1e-6, settle=st,
                        deviation_orders=() if deviation is None else DEVIATION_ORDERS,
                        deviation_sigma=None if deviation is None
                        else np.ones((3, n_coefficients())))
    clock = None
    if ck is not None:  # each station's level, no rate
        clock = np.zeros((K, ck.size))
        clock[:, 0::2] = np.asarray(clock_s)[1:]
    settle = None
    if st is not None:  # per station and kind the change and its rate: linear in time
        rate = np.asarray(settle_rate, dtype=float).ravel()
        settle = np.zeros((K, st.size))
        settle[:, 0::2], settle[:, 1::2] = t[:, None] * rate, rate
    truth = JointState(R, p, np.broadcast_to(w0, (K, 6)).copy(), R_s, t_s, 0.0, clock,
                       None if moved is None else pt, settle=settle,
                       deviation=None if deviation is None else np.asarray(deviation, float))
    return prob, truth


def test_a_gap_between_knots_takes_the_loosest_qc_of_the_others():
    """An interval longer than ``max_gap_s`` gets the largest ``Qc`` of the moving intervals
    whose ``Qc`` the data determine, per axis (of every moving one on an axis none is); the
    others keep theirs; without a gap (or all gaps) nothing changes."""
    prob, _ = _synthetic(np.random.default_rng(5), K=6)
    t = np.array([0.0, 0.4, 0.8, 4.8, 5.2, 5.6])
    prob = replace(prob, t_knot=t, max_gap_s=3.0)
    qc = np.random.default_rng(7).uniform(0.1, 1.0, (5, 6))
    out = prob.with_qc(qc).qc
    np.testing.assert_array_equal(prob.gaps, [False, False, True, False, False])
    np.testing.assert_array_equal(np.delete(out, 2, axis=0), np.delete(qc, 2, axis=0))
    np.testing.assert_array_equal(out[2], np.delete(qc, 2, axis=0).max(axis=0))
    np.testing.assert_array_equal(replace(prob, max_gap_s=np.inf).with_qc(qc).qc, qc)
    np.testing.assert_array_equal(with_gaps(qc, np.ones(5, bool)), qc)
    # only the moving intervals whose Qc the data determine count; an axis determined on
    # none of them: every moving interval's
    moving = np.array([False, True, False, True, True])
    trusted = np.ones((5, 6), bool)
    trusted[4, :3] = False
    trusted[:, 5] = False
    qc[4] = 10.0  # an undetermined class's wild value
    qc[0] = 20.0  # standing: never the gap's
    out = prob.with_qc(qc, trusted, moving).qc[2]
    np.testing.assert_array_equal(out[:3], qc[[1, 3], :3].max(axis=0))
    np.testing.assert_array_equal(out[3:5], np.full(2, 10.0))
    np.testing.assert_array_equal(out[5], 10.0)


def _moved_in_a_gap(noise: float = 0.0, stiff: float = 1e-8):
    """A standing robot moved by 1.5 m while no station measured (4 s, knots 25-34 dropped),
    its motion prior's ``Qc`` ``stiff`` (a standing class's) but for a few intervals where it
    moved elsewhere in the run (``Qc`` 1 there): the problem and the truth at its knots."""
    prob, truth = _synthetic(np.random.default_rng(6), K=60, speed=0.0, noise=noise,
                             jump=(30, [1.5, 0.5, 0.0]))
    keep = np.r_[0:25, 35:60]
    m = prob.meas
    sel = PolarMeasurements(m.t[keep], m.station[keep], m.prism[keep], m.y[keep],
                            m.info[keep], m.kappa_sigma_ppm, m.var_white[keep], m.corr[keep])
    qc = np.full((keep.size - 1, 6), stiff)
    qc[5:8] = 1.0
    prob = replace(prob, t_knot=prob.t_knot[keep], of_meas=np.arange(keep.size),
                   tau=prob.tau[keep], meas=sel, qc=qc)
    return prob, replace(truth, R=truth.R[keep], t=truth.t[keep], w=truth.w[keep])


def test_a_robot_moved_while_no_station_tracked_it_is_not_tied_across_the_gap():
    """The robot moved untracked (:func:`_moved_in_a_gap`): with the gap's prior the loosest
    of the run's (``max_gap_s`` 3 s) both sides come out where they are (noise-free: 1e-6
    m); tied by the standing prior across the gap, they are pulled off by decimetres."""
    prob, truth = _moved_in_a_gap()
    start = replace(truth, t=truth.t + 0.01)
    err = {}
    for gap in (3.0, np.inf):
        _, est, _, info, _ = solve_with_qc(replace(prob, max_gap_s=gap), start, False, 30, 1e-12)
        err[gap] = np.max(np.abs(est.t - truth.t))
    assert err[3.0] < 1e-6, err
    assert err[np.inf] > 0.1, err


def test_a_gap_counts_in_its_class_variance_components_only_between_moving_ends():
    """The robot moved untracked (:func:`_moved_in_a_gap`, noisy): its gap enters its
    class's ``Qc`` estimate where its ends move, not where they stand. The update's table is
    the variance components over the intervals :func:`class_members` keeps, recomputed
    here from the prior's terms, and the gap's 1.6 m raises the moving class's along-track
    ``Qc`` a hundredfold over the standing class's, which never sees it."""
    prob, truth = _moved_in_a_gap(noise=0.1, stiff=1e-4)
    prob, est, sol, _, _ = solve_with_qc(replace(prob, max_gap_s=3.0), truth, False, 30, 1e-12)
    dt = np.diff(prob.t_knot)
    e, E, F = prior_terms(est.R, est.t, est.w, dt)
    quad, red = prior_components(e, E, F, dt, prob.qc, sol.cov[:, :12, :12],
                                 sol.cov_next[:, :12, :12])
    table = np.ones((N_CLASSES, 6))
    rows = {}
    for cls in (0, 1):
        classes = np.full(dt.size, cls)
        on = class_members(classes, prob.gaps)
        np.testing.assert_array_equal(on, ~prob.gaps if cls == 0 else np.ones(dt.size, bool))
        _, new, _, _, _ = engine_module._qc_step(prob, est, sol, classes, table, None)
        ref, _ = qc_per_class(quad[on], red[on], classes[on])
        np.testing.assert_allclose(new[cls], ref[cls], rtol=1e-12)
        rows[cls] = new[cls]
    assert rows[1][0] > 100.0 * rows[0][0], rows


@pytest.mark.parametrize("order", ["sorted", "shuffled"])
def test_knot_rows_sum_each_knots_products_as_add_at_does(order):
    """Knots with several measurements, none or one (a run of equal indices, a gap): the
    batched product of the knots' rows equals ``np.add.at`` of each item's product."""
    rng = np.random.default_rng(41)
    empty = np.array([7, 8, 20])  # knots no measurement falls on
    index = np.sort(rng.choice(np.setdiff1d(np.arange(30), empty), size=200))
    index[:5] = 0  # a run at the first row
    if order == "shuffled":
        index = rng.permutation(index)
    A, B = rng.normal(size=(200, 3, 4)), rng.normal(size=(200, 3, 5))
    out = np.swapaxes(knot_rows(index, 30, A), 1, 2) @ knot_rows(index, 30, B)
    ref = np.zeros((30, 4, 5))
    np.add.at(ref, index, np.swapaxes(A, 1, 2) @ B)
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-12)
    assert np.all(out[empty] == 0.0)


def test_arrow_solver_gives_the_same_numbers_on_any_number_of_threads(monkeypatch):
    """The reduction's products split between threads (sparse._bmm, here in parts of two
    blocks and more, three threads) give the solution and every covariance bit for bit as
    one thread does: each block's product is its own."""
    rng = np.random.default_rng(5)
    prob, truth = _synthetic(rng, K=29, noise=1.0)
    system, _ = assemble(prob, truth)
    monkeypatch.setattr(sparse, "_MIN_PER_THREAD", 2)
    sols = []
    for cores in (1, 3):
        monkeypatch.setattr(sparse, "_CORES", cores)
        sols.append((solve_arrow(system), solve_arrow(system, want_cov=True)))
    for one, many in zip(*sols, strict=True):
        for name in ("x", "g", "cov", "cov_next", "cov_g", "cov_var", "cov_var_next", "factor"):
            a, b = getattr(one, name), getattr(many, name)
            assert (a is None) == (b is None) and (a is None or np.array_equal(a, b)), name


@pytest.mark.parametrize(("K", "d", "G"), [(1500, 12, 13), (1501, 30, 40), (1500, 43, 82)])
def test_a_solves_memory_is_what_solve_bytes_says(K, d, G):
    """rtsgt.joint.sparse.solve_bytes, the floor of the joint engine's memory
    (docs/joint.md#an-hours-floor): the system's arrays plus the peak that one solve with
    covariances allocates (numpy's allocations, traced), within 15 % of it, from the
    trajectory's 12 states to the field preset's 43 with its 82 globals."""
    rng = np.random.default_rng(5)
    M = rng.standard_normal((K, d, d)) / np.sqrt(d)
    system = ArrowSystem(M @ np.swapaxes(M, 1, 2) + 3.0 * np.eye(d),
                         0.3 * rng.standard_normal((K - 1, d, d)) / np.sqrt(d),
                         0.3 * rng.standard_normal((K, d, G)) / np.sqrt(d * G),
                         (1.0 + 0.1 * K) * np.eye(G), rng.standard_normal((K, d)),
                         rng.standard_normal(G))
    del M
    held = system.D.nbytes + system.U.nbytes + system.B.nbytes
    tracemalloc.start()
    try:
        sol = solve_arrow(system, want_cov=True, overwrite=True)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert sol.cov.shape == (K, d, d)
    ratio = (held + peak) / solve_bytes(K, d, G)
    assert 0.85 < ratio < 1.15, ratio


@pytest.mark.parametrize(("chunk", "K"), [(4, 13), (2048, 14)])
def test_arrow_solver_matches_a_dense_solve_of_the_same_normal_equations(chunk, K,
                                                                        monkeypatch):
    """With the covariances and without (the Schur complement from the forward pass alone),
    an odd and an even number of knots."""
    monkeypatch.setattr(sparse, "CHUNK", chunk)  # the globals' share in blocks of knots
    rng = np.random.default_rng(4)
    prob, truth = _synthetic(rng, K=K, noise=1.0)
    start = retract(prob, truth, 1e-3 * rng.normal(size=(K, 12)), 1e-4 * rng.normal(size=13))
    system, _ = assemble(prob, start)
    sol = solve_arrow(system, want_cov=True)
    x, g, cov, cov_g = sol.x, sol.g, sol.cov, sol.cov_g
    M, b = system.dense()
    ref = np.linalg.solve(M, b)
    scale = np.abs(ref).max()
    np.testing.assert_allclose(np.concatenate([x.ravel(), g]), ref, atol=1e-9 * scale)
    bare = solve_arrow(system)
    assert bare.cov is None
    np.testing.assert_allclose(np.concatenate([bare.x.ravel(), bare.g]), ref, atol=1e-9 * scale)
    # consumed in place: the same numbers bit for bit, a, B, C and c as they were
    kept = {k: getattr(system, k).copy() for k in ("a", "B", "C", "c")}
    for want_cov, copied in ((True, sol), (False, bare)):
        used = ArrowSystem(*(getattr(system, k).copy() for k in ("D", "U", "B", "C", "a", "c")))
        out = solve_arrow(used, want_cov=want_cov, overwrite=True)
        for name in ("x", "g", "cov", "cov_next", "cov_g", "cov_var", "factor"):
            a, b = getattr(out, name), getattr(copied, name)
            assert (a is None) == (b is None) and (a is None or np.array_equal(a, b)), name
        assert all(np.array_equal(getattr(used, k), v) for k, v in kept.items())
    inv = np.linalg.inv(M)
    n = x.size
    for k in range(K):
        blk = inv[12 * k:12 * k + 12, 12 * k:12 * k + 12]
        np.testing.assert_allclose(cov[k], blk, atol=1e-9 * np.abs(blk).max())
    for k in range(K - 1):  # consecutive knots' cross covariance
        blk = inv[12 * k:12 * k + 12, 12 * k + 12:12 * k + 24]
        np.testing.assert_allclose(sol.cov_next[k], blk, atol=1e-9 * np.abs(blk).max())
    np.testing.assert_allclose(cov_g, inv[n:, n:], atol=1e-9 * np.abs(inv[n:, n:]).max())
    # the split: A^-1's blocks (the knots given the globals) and Cov(x_k, g) = L_k chol_g^T
    inv_a = np.linalg.inv(M[:n, :n])
    cross = np.einsum("kig,hg->kih", sol.factor, sol.chol_g).reshape(n, -1)
    np.testing.assert_allclose(cross, inv[:n, n:], atol=1e-9 * np.abs(inv[:n, n:]).max())
    np.testing.assert_allclose(sol.chol_g @ sol.chol_g.T, cov_g, rtol=1e-12, atol=0)
    for k in range(K):
        blk = inv_a[12 * k:12 * k + 12, 12 * k:12 * k + 12]
        np.testing.assert_allclose(sol.cov_var[k], blk, atol=1e-9 * np.abs(blk).max())
        if k < K - 1:
            blk = inv_a[12 * k:12 * k + 12, 12 * k + 12:12 * k + 24]
            np.testing.assert_allclose(sol.cov_var_next[k], blk, atol=1e-9 * np.abs(blk).max())


def test_a_mixture_of_solutions_is_the_weighted_covariances_plus_the_spread():
    """Two solutions of different normal equations (another state, another ``Qc``), mixed
    with weights 0.3 / 0.7 about the first's estimate (sparse.mix_solutions): the knots' and
    the globals' covariances and their cross covariance are those of the dense
    ``sum_i w_i (M_i^-1 + delta_i delta_i^T)``, and the split still adds up (``cov =
    cov_var + L L^T``, ``Cov(x_k, g) = L_k chol_g^T``, ``cov_var`` the weighted knots'
    given the globals)."""
    rng = np.random.default_rng(5)
    K = 6
    prob, truth = _synthetic(rng, K=K, noise=1.0)
    states = [retract(prob, truth, 1e-3 * rng.normal(size=(K, 12)), 1e-4 * rng.normal(size=13))
              for _ in range(2)]
    probs = [prob, replace(prob, qc=3.0 * prob.qc)]
    systems = [assemble(p, st)[0] for p, st in zip(probs, states, strict=True)]
    sols = [sparse.solve_arrow(sy, want_cov=True) for sy in systems]
    w = np.array([0.3, 0.7])
    dx = np.stack([np.zeros((K, 12)), 1e-3 * rng.normal(size=(K, 12))])
    dg = np.stack([np.zeros(13), 1e-3 * rng.normal(size=13)])
    mix = sparse.mix_solutions(sols, w, dx[1:], dg[1:])
    n = 12 * K
    dense = sum(wi * (np.linalg.inv(sy.dense()[0]) + np.outer(d, d))
                for wi, sy, d in zip(w, systems, np.concatenate([dx.reshape(2, -1), dg], 1),
                                     strict=True))
    given = sum(wi * np.linalg.inv(sy.dense()[0][:n, :n]) for wi, sy in zip(w, systems,
                                                                            strict=True))
    tol = 1e-9 * np.abs(dense).max()
    np.testing.assert_allclose(mix.x, sols[0].x)
    np.testing.assert_allclose(mix.g, sols[0].g)
    for k in range(K):
        sl = slice(12 * k, 12 * k + 12)
        np.testing.assert_allclose(mix.cov[k], dense[sl, sl], atol=tol)
        np.testing.assert_allclose(mix.cov_var[k], given[sl, sl], atol=tol)
        np.testing.assert_allclose(mix.cov_var[k] + mix.factor[k] @ mix.factor[k].T,
                                   dense[sl, sl], atol=tol)
        if k < K - 1:
            nx = slice(12 * k + 12, 12 * k + 24)
            np.testing.assert_allclose(mix.cov_next[k], dense[sl, nx], atol=tol)
            np.testing.assert_allclose(mix.cov_var_next[k], given[sl, nx], atol=tol)
    np.testing.assert_allclose(mix.cov_g, dense[n:, n:], atol=tol)
    np.testing.assert_allclose(mix.chol_g @ mix.chol_g.T, dense[n:, n:], atol=tol)
    cross = np.einsum("kig,hg->kih", mix.factor, mix.chol_g).reshape(n, -1)
    np.testing.assert_allclose(cross, dense[:n, n:], atol=tol)


def test_gauss_newton_recovers_a_noise_free_trajectory_from_a_perturbed_start():
    rng = np.random.default_rng(5)
    prob, truth = _synthetic(rng)
    dx = rng.normal(size=(40, 12)) * np.r_[[0.02] * 3, [0.01] * 3, [0.05] * 6]
    start = retract(prob, truth, dx, rng.normal(size=13) * 1e-3)
    est, sol, info = gauss_newton(prob, start, max_iter=10, tol=1e-10)
    cov, cov_g = sol.cov, sol.cov_g
    assert info.converged and info.iterations <= 6, info
    np.testing.assert_allclose(est.t, truth.t, atol=1e-7)
    np.testing.assert_allclose(est.R, truth.R, atol=1e-8)
    np.testing.assert_allclose(est.t_s, truth.t_s, atol=1e-7)
    assert info.costs[-1] < 1e-8
    assert np.all(np.linalg.eigvalsh(cov) > 0) and np.all(np.linalg.eigvalsh(cov_g) > 0)


def test_a_common_turn_of_every_knots_frame_leaves_the_prior_exact():
    """A constant-velocity trajectory has a prior error of zero. Every knot turned by one
    right perturbation ``d`` with the velocities' first-order step ``-d^curly w`` is the same
    motion in another frame: ``retract`` adds the second orders of the frame change, so the
    error stays zero (to round-off); the velocities plus the step alone leave an error of
    second order in ``d`` (what the floor ``Qc``'s stiff axes saw as a cost of thousands,
    docs/joint.md#the-knots-origin). ``difference`` still inverts ``retract``."""
    rng = np.random.default_rng(21)
    prob, truth = _synthetic(rng, K=12)
    dt = np.diff(prob.t_knot)
    assert np.abs(prior_terms(truth.R, truth.t, truth.w, dt)[0]).max() < 1e-12
    d = np.r_[0.01, -0.02, 0.005, 0.006, -0.004, 0.002]
    x = np.zeros((12, 12))
    x[:, :6] = d
    x[:, 6:] = -truth.w @ curly(d).T
    g = np.zeros(prob.n_globals)
    turned = retract(prob, truth, x, g)
    assert np.abs(prior_terms(turned.R, turned.t, turned.w, dt)[0]).max() < 1e-12
    first = replace(turned, w=truth.w + x[:, 6:])
    assert np.abs(prior_terms(first.R, first.t, first.w, dt)[0]).max() > 1e-6
    back = difference(prob, truth, turned)
    np.testing.assert_allclose(back[0], x, atol=1e-12)


def test_gauss_newton_recovers_the_clock_offsets_of_a_noise_free_problem():
    """Stations 2 and 3 record 8 ms late and 5 ms early: the clock states take it (station 1
    is the reference), the poses stay the truth's; without clock states they cannot."""
    rng = np.random.default_rng(8)
    prob, truth = _synthetic(rng, clock_s=[0.0, 0.008, -0.005])
    start = replace(truth, clock=np.zeros_like(truth.clock))
    est, sol, info = gauss_newton(prob, start, max_iter=10, tol=1e-12)
    assert info.converged, info
    np.testing.assert_allclose(est.clock, truth.clock, atol=5e-6)  # first order in the offset
    np.testing.assert_allclose(est.t, truth.t, atol=1e-5)
    assert info.costs[-1] < 1e-3, info.costs
    sig = np.sqrt(np.einsum("kii->ki", sol.cov)[:, prob.clock_col:prob.settle_col])
    assert sig.shape == (40, 4) and np.all(np.isfinite(sig) & (sig > 0)), sig
    blind = replace(prob, clock=None)
    _, _, info0 = gauss_newton(blind, replace(start, clock=None), max_iter=10, tol=1e-12)
    assert info0.costs[-1] > 1e3 * max(info.costs[-1], 1e-6), info0.costs


def test_settling_stations_are_carried_by_their_states():
    """The non-reference stations sink and twist (0.6-1 mm and 6-10" over the 16 s,
    noise-free; docs/joint.md#settling-tripods): with settling states the measurements are
    fitted, the states' errors lie inside their posterior sigmas and the poses' errors inside
    their covariance (a constant-velocity robot can turn slowly about two prisms' line, so the
    data alone do not separate a settling from the motion: the prior and the covariance say
    how much; the field preset measures what they are worth: docs/joint.md#settling-tripods).
    The settling's columns of the
    gradient equal finite differences of the cost."""
    rate = np.array([[0.0, 0.0], [-4e-5, 3e-6], [6e-5, -5e-6]])  # m/s, rad/s
    prob, truth = _synthetic(np.random.default_rng(6), settle_rate=rate)
    start = replace(truth, settle=np.zeros_like(truth.settle))
    est, sol, info = gauss_newton(prob, start, max_iter=20, tol=1e-12)
    assert info.converged and info.costs[-1] < 1.0, info.costs
    sig = np.sqrt(np.einsum("kii->ki", sol.cov)[:, prob.settle_col:])
    # the moving stations' changes after the start (their rates are not the truth's: a walk
    # explains a short steady sinking more cheaply than a drift from rest)
    z = ((est.settle - truth.settle) / sig)[1:, 4::2]
    assert np.abs(z).max() < 3.0, z
    err = log_se3(*_compose(np.swapaxes(truth.R, 1, 2),
                            -np.einsum("kji,kj->ki", truth.R, truth.t), est.R, est.t))
    nees = np.einsum("ki,kij,kj->k", err, np.linalg.inv(sol.cov[:, :6, :6]), err)
    assert nees.max() < chi2.ppf(0.99, 6), nees.max()
    half = replace(truth, settle=truth.settle * 0.5)
    system, _ = assemble(prob, half)
    step = (1e-9, 1e-12, 1e-11, 1e-14)  # height m, m/s; yaw rad, rad/s
    for knot, col in ((0, 4), (3, 5), (20, 6), (20, 7), (39, 10), (39, 11)):
        d = np.zeros_like(truth.settle)
        d[knot, col] = step[col % 4]
        cp, cm = (assemble(prob, replace(half, settle=half.settle + sgn * d))[1]
                  for sgn in (1.0, -1.0))
        assert (cp - cm) / (2 * d[knot, col]) == pytest.approx(
            -2 * system.a[knot, prob.settle_col + col], rel=1e-4, abs=1e-3), (knot, col)


def test_the_prisms_deviation_with_their_viewing_angle_is_recovered():
    """Each prism seen displaced by harmonics of the azimuth its station sees it under (3, 6
    and 12 per turn, 0.5-3 mm each, the displacement built from the geometry in the test),
    noise-free, the robot turning three times: the deviation states fit the measurements and
    recover the coefficients and the poses; without them the poses are off by millimetres.
    The deviation's columns of the gradient equal finite differences of the cost
    (docs/joint.md#prism-deviation)."""
    rng = np.random.default_rng(12)
    coef = rng.uniform(0.5e-3, 3e-3, (3, n_coefficients())) * rng.choice([-1.0, 1.0],
                                                                        (3, n_coefficients()))
    prob, truth = _synthetic(rng, K=300, speed=0.5, deviation=coef)
    prob = replace(prob, qc=prob.qc * 1e-2)
    start = replace(truth, deviation=np.zeros_like(coef))
    est, sol, info = gauss_newton(prob, start, max_iter=20, tol=1e-12)
    assert info.converged and info.costs[-1] < 1e-3, info.costs
    sl = slice(prob.deviation_col, prob.deviation_col + prob.n_deviation)
    sig = np.sqrt(np.diag(sol.cov_g)[sl]).reshape(coef.shape)
    # to 1 % of their sigmas (the displacement enters the polar values to first order);
    # the vertical part of the 3 per turn is the worst determined (3-4 mm: the body's tilt)
    assert np.abs((est.deviation - coef) / sig).max() < 0.01, (est.deviation - coef) / sig
    assert np.median(sig) < 1e-3 and sig.max() < 5e-3, sig
    np.testing.assert_allclose(est.t, truth.t, atol=1e-4)
    blind = replace(prob, deviation_orders=())
    e0, _, i0 = gauss_newton(blind, replace(start, deviation=None), 20, 1e-12)
    assert np.abs(e0.t - truth.t).max() > 5e-3 and i0.costs[-1] > 300, i0.costs[-1]
    # the gradient against finite differences of the cost, off the truth (half the
    # deviation, the prisms as parameters): the deviation's columns, and the knots', the
    # stations' and the prisms' with the deviation's slope in the viewing azimuth
    prob, truth = _synthetic(np.random.default_rng(12), K=60, speed=0.5, deviation=coef,
                             moved=np.zeros(3))
    half = replace(truth, deviation=0.5 * coef)
    system, _ = assemble(prob, half)
    cols = [*range(6), *range(prob.kappa_col + 1, prob.kappa_col + 4),
            *range(prob.deviation_col, prob.deviation_col + prob.n_deviation, 5)]
    for col in cols:
        g = np.zeros(prob.n_globals)
        g[col] = 1e-8
        cp, cm = (assemble(prob, retract(prob, half, np.zeros((60, 12)), sgn * g))[1]
                  for sgn in (1.0, -1.0))
        assert (cp - cm) / 2e-8 == pytest.approx(-2 * system.c[col], rel=1e-4, abs=1e-2), col
    _assert_knot_gradient(prob, half, ((3, 0), (3, 4), (30, 5), (59, 3)), 1e-8)


def test_the_settling_prior_is_the_covariance_of_its_two_processes():
    """The settling's chain prior (its start 10 min after the calibration and its
    transitions between knots 10-70 min after it, rtsgt.joint.slow) has the covariance of
    sampled random walks plus drifts from rest (an independent engine: 20,000 paths summed
    at 1 s), to the sampling error; at 1 h its sigma is the two hour sigmas in quadrature."""
    rng = np.random.default_rng(3)
    knots = np.arange(600.0, 4201.0, 600.0)
    walk, drift = HOUR_WALK_SIGMA[1], HOUR_DRIFT_SIGMA[1]
    q_w, q_d = walk**2 / HOUR_S, 3.0 * drift**2 / HOUR_S**3
    prior = LevelRate(np.array([q_w]), np.array([q_d]),
                      settle_start(walk, drift, knots[0], 1e-12)[None])
    K = knots.size
    D, U, a = np.zeros((K, 2, 2)), np.zeros((K - 1, 2, 2)), np.zeros((K, 2))
    prior.add_prior(D, U, a, np.zeros((K, 2)), np.diff(knots), 0)
    info, _ = ArrowSystem(D, U, np.zeros((K, 2, 0)), np.zeros((0, 0)), a, np.zeros(0)).dense()
    cov = np.linalg.inv(info)[0::2, 0::2]  # the changes (the rates between)
    n, dt = 20000, 1.0
    steps = int(knots[-1] / dt)
    x = np.zeros(n)
    rate = np.zeros(n)
    out = []
    for i in range(1, steps + 1):  # 4200 steps of all paths at once
        rate += rng.normal(0.0, np.sqrt(q_d * dt), n)
        x += rate * dt + rng.normal(0.0, np.sqrt(q_w * dt), n)
        if i * dt in knots:
            out.append(x.copy())
    sample = np.cov(np.array(out))
    sd = np.sqrt(np.diag(cov))
    corr_err = np.abs(sample - cov) / np.outer(sd, sd)
    assert corr_err.max() < 5 * np.sqrt(2.0 / n), corr_err.max()  # ~ 0.05 at 5 sigma
    hour = np.searchsorted(knots, 3600.0)
    assert np.sqrt(cov[hour, hour]) == pytest.approx(np.hypot(walk, drift), rel=1e-3)


def test_the_clocks_chain_prior_marginalised_is_the_per_prism_estimates_prior():
    """The joint engine's clock states (offset and rate at every knot, rtsgt.joint.slow)
    with their rates marginalised at a 60 s grid give the information of
    rtsgt.clocks.walk_prior_info (the per-prism clock estimate's, the same processes) to
    round-off; the report times cover the knots' span every 60 s."""
    knots = np.array([0.0, 60.0, 120.0, 180.0, 240.0, 290.0])
    model = clock_model(np.zeros(3, dtype=int), 2, 1)
    K = knots.size
    D, U, a = np.zeros((K, 2, 2)), np.zeros((K - 1, 2, 2)), np.zeros((K, 2))
    model.prior.add_prior(D, U, a, np.zeros((K, 2)), np.diff(knots), 0)
    info, _ = ArrowSystem(D, U, np.zeros((K, 2, 0)), np.zeros((0, 0)), a, np.zeros(0)).dense()
    e, r = np.arange(0, 2 * K, 2), np.arange(1, 2 * K, 2)
    marg = info[np.ix_(e, e)] - info[np.ix_(e, r)] @ np.linalg.solve(info[np.ix_(r, r)],
                                                                      info[np.ix_(r, e)])
    ref = walk_prior_info(knots)
    np.testing.assert_allclose(marg, ref, rtol=1e-7, atol=1e-9 * np.abs(ref).max())
    np.testing.assert_allclose(report_times(10.0, 130.0), [10.0, 70.0, 130.0])
    np.testing.assert_allclose(report_times(0.0, 100.0), [0.0, 60.0, 100.0])
    np.testing.assert_allclose(report_times(0.0, 20.0), [0.0, 20.0])


def test_a_prism_moved_after_its_survey_is_found_and_estimated():
    """Prism 1 measured 2 cm (in the prisms' plane) away from its survey, noise-free: the
    prisms as parameters with the survey as prior (1 mm) find it (its test beyond the
    critical value, docs/joint.md#prism-positions), free its survey where the data determine
    it and recover the move within its sigma and the poses exactly; held at the survey, the
    poses are biased by centimetres; an unmoved rig frees nothing."""
    n, d = _in_plane_move()
    prob, truth = _synthetic(np.random.default_rng(9), moved=d)
    prob = replace(prob, qc=prob.qc * 1e-4)  # a smooth robot: the rig's shape is determined
    start = replace(truth, p_body=prob.p_body.copy())
    prob2, est, sol, info, _ = solve_with_qc(prob, start, False, 20, 1e-12)
    assert info.converged and [f[0] for f in prob2.prism_found] == [0], prob2.prism_found
    assert all(w == 0 and above >= UNDECIDED_COST  # no other explains it: decided, listed
               for _, above, w in prob2.prism_alternatives), prob2.prism_alternatives
    assert prob2.prism_found[0][1] > 10 * chi2.ppf(1 - 1e-3 / 3, prob2.prism_found[0][2])
    sig = np.sqrt(np.diag(sol.cov_g)[prob.kappa_col + 1:prob.kappa_col + 4])
    assert np.all(np.abs(est.p_body[0] - prob.p_body[0] - d) < sig), (est.p_body[0], sig)
    # the direction the data cannot determine (the normal: the rotation about the other two
    # prisms' line moves prism 1 along it) keeps the survey's 1 mm plus the move found, 2 cm
    c1 = sol.cov_g[prob.kappa_col + 1:prob.kappa_col + 4, prob.kappa_col + 1:prob.kappa_col + 4]
    assert 0.98 < np.sqrt(n @ c1 @ n) / np.sqrt(1e-6 + 0.02**2) < 1.02, n @ c1 @ n
    plane = np.linalg.svd(n[None, :])[2][1:]  # (2, 3) orthonormal, in the prisms' plane
    assert np.all(np.sqrt(np.diag(plane @ c1 @ plane.T)) < 2e-3), plane @ c1 @ plane.T
    np.testing.assert_allclose(est.t, truth.t, atol=1e-5)
    # the move with a part along the normal as well: the poses' rotation about the line is
    # off by it and their covariance carries it (with the survey's 1 mm there: 20-30 sigma)
    prob_n, truth_n = _synthetic(np.random.default_rng(9), moved=d + 0.01 * n)
    prob_n = replace(prob_n, qc=prob_n.qc * 1e-4)
    prob_n, est_n, sol_n, info_n, _ = solve_with_qc(
        prob_n, replace(truth_n, p_body=prob_n.p_body.copy()), False, 20, 1e-12)
    assert info_n.converged and [f[0] for f in prob_n.prism_found] == [0]
    err = log_se3(*_compose(np.swapaxes(truth_n.R, 1, 2),
                            -np.einsum("kji,kj->ki", truth_n.R, truth_n.t), est_n.R, est_n.t))
    nees = np.einsum("ki,kij,kj->k", err, np.linalg.inv(sol_n.cov[:, :6, :6]), err)
    assert np.linalg.norm(err[:, 3:], axis=1).min() > 0.01, err[:, 3:]  # 1 cm / ~0.6 m
    assert nees.max() < chi2.ppf(0.99, 6), nees.max()
    blind = replace(prob, prism_info=None)
    e0, _, i0 = gauss_newton(blind, replace(start, p_body=None), 20, 1e-12)
    assert np.abs(e0.t - truth.t).max() > 0.01 and i0.costs[-1] > 100, i0.costs[-1]
    prob, truth = _synthetic(np.random.default_rng(9), moved=np.zeros(3))
    prob3, est, _, info, _ = solve_with_qc(replace(prob, qc=prob.qc * 1e-4), truth, False, 20,
                                           1e-12)
    assert prob3.prism_found == () and info.converged
    np.testing.assert_allclose(est.p_body, prob.p_body, atol=1e-9)
    # the prisms' columns of the gradient against finite differences of the cost (off the
    # knots' times: tau != 0)
    prob = replace(prob, tau=np.random.default_rng(1).uniform(-1e-3, 1e-3, prob.tau.size))
    system, _ = assemble(prob, replace(truth, p_body=truth.p_body + 1e-3))
    for j in range(9):
        dp = np.zeros(9)
        dp[j] = 1e-7
        cp, cm = (assemble(prob, replace(truth, p_body=truth.p_body + 1e-3 + s * dp.reshape(3, 3)))[1]
                  for s in (1.0, -1.0))
        assert (cp - cm) / 2e-7 == pytest.approx(-2 * system.c[prob.kappa_col + 1 + j], rel=1e-5)


def test_a_moved_prism_surveyed_more_tightly_than_the_others_is_still_found():
    """As above (prism 1 moved 2 cm in the prisms' plane), with prism 1 surveyed to 1 um
    against the others' 1 mm (as a prism that defines the survey's frame): judged against
    its own survey the data would determine no direction of its move (held-out seed 4001);
    on the survey's common scale (its least precise direction) prism 1 is tested, found and
    freed, and the poses come back."""
    n, d = _in_plane_move()
    prob, truth = _synthetic(np.random.default_rng(9), moved=d)
    var = np.r_[[1e-12] * 3, [1e-6] * 6]
    prob = replace(prob, qc=prob.qc * 1e-4, prism_info=np.diag(1.0 / var),
                   prism_cov=np.diag(var))
    start = replace(truth, p_body=prob.p_body.copy())
    prob2, est, sol, info, _ = solve_with_qc(prob, start, False, 20, 1e-12)
    assert info.converged and [f[0] for f in prob2.prism_found] == [0], prob2.prism_found
    assert prob2.prism_found[0][2] >= 2, prob2.prism_found  # its in-plane directions
    np.testing.assert_allclose(est.t, truth.t, atol=1e-5)


def test_what_no_station_sees_of_a_prisms_move():
    """blind_moves: with three prisms each one's blind direction is the normal of their plane
    (largest component positive) and the poses turn by ``1 / h`` rad per m of move along it,
    ``h`` its distance from the other two's line: the rotation by ``e`` about that line moves
    it by ``e h`` along the normal to first order (the test's own rotation, exact) and keeps
    the other two; a fourth prism off the plane leaves none; with two prisms each has the
    two directions across their line, each at ``1 / L``."""
    n, _ = _in_plane_move()
    out = blind_moves(SURVEY)
    for j, (g, turn) in enumerate(out):
        a, b = SURVEY[[k for k in range(3) if k != j]]
        u = (b - a) / np.linalg.norm(b - a)
        v = SURVEY[j] - a
        h = np.linalg.norm(v - (v @ u) * u)
        assert g.shape == (3, 1) and turn.shape == (1,)
        assert abs(abs(g[:, 0] @ n) - 1.0) < 1e-12 and g[np.argmax(np.abs(g[:, 0])), 0] > 0
        assert turn[0] == pytest.approx(1.0 / h, rel=1e-9)
        e = 1e-6  # the rotation about the others' line through a
        step = a + exp_so3(e * u[None])[0] @ (SURVEY[j] - a) - SURVEY[j]
        along = np.sign(step @ g[:, 0]) * e * h * g[:, 0]  # (either sense of the turn)
        assert np.linalg.norm(step - along) < 1e-3 * e * h
    four = np.vstack([SURVEY, [0.1, 0.0, 1.2]])
    assert all(g.shape == (3, 0) and t.size == 0 for g, t in blind_moves(four))
    two = blind_moves(SURVEY[:2])
    L = np.linalg.norm(SURVEY[1] - SURVEY[0])
    for g, turn in two:
        assert g.shape == (3, 2)
        np.testing.assert_allclose(g.T @ (SURVEY[1] - SURVEY[0]), 0.0, atol=1e-12)
        np.testing.assert_allclose(turn, 1.0 / L, rtol=1e-9)


def test_the_stability_is_a_move_along_the_blind_directions_that_the_stations_cannot_see():
    """stability_factor: the prisms' moves sigma^2 n n^T per prism of three (n their plane's
    normal), independent between prisms, and the body frame's turn that keeps every prism
    where the stations see it exactly (rho + phi x p_j + dp_j = 0); nothing for four prisms
    off one plane, zero for a sigma of 0 (docs/joint.md#what-no-station-sees)."""
    n, _ = _in_plane_move()
    dxi, dp, owner = stability_factor(SURVEY, 2e-3)
    assert dxi.shape == (6, 3) and dp.shape == (9, 3) and owner.tolist() == [0, 1, 2]
    C = dp @ dp.T
    for j in range(3):
        for k in range(3):
            want = 4e-6 * np.outer(n, n) if j == k else np.zeros((3, 3))
            np.testing.assert_allclose(C[3 * j:3 * j + 3, 3 * k:3 * k + 3], want, atol=1e-18)
        seen = dxi[:3] + np.cross(dxi[3:].T, SURVEY[j]).T + dp[3 * j:3 * j + 3]
        np.testing.assert_allclose(seen, 0.0, atol=1e-15)
    # a move of one prism alone turns the body about the other two's line by 1 / h (blind_moves)
    np.testing.assert_allclose(np.linalg.norm(dxi[3:], axis=0),
                               2e-3 * np.concatenate([t for _, t in blind_moves(SURVEY)]),
                               rtol=1e-9)
    dxi4, dp4, owner4 = stability_factor(np.vstack([SURVEY, [0.1, 0.0, 1.2]]), 2e-3)
    assert dxi4.shape == (6, 0) and dp4.shape == (12, 0) and owner4.size == 0
    assert not np.any(stability_factor(SURVEY, 0.0)[0])


def test_a_prisms_move_along_its_gauge_is_not_tested():
    """A move of prism 1 along the normal to the prisms' plane turns the body about the other
    two prisms' line (prism 1's gauge): no measurement sees it, only a motion model does
    (its anisotropic ``Qc`` places the body's tilt; under a rocking body wrongly,
    docs/joint.md#which-prism-moved). With the data's information strong in every direction
    (as a motion prior's can be), 2 cm along the normal are not tested (the directions
    tested are the plane's two) and 2 cm in the plane are found; with prism 1 freed (its
    survey gone where the data see it), the others' tests are judged on the trusted prisms'
    survey scale: each one direction (its distance to the other), no move found."""
    n, d = _in_plane_move()
    info = np.eye(9) * 1e6  # the survey: 1 mm
    data = np.eye(9) * 1e8  # the data: 0.1 mm in every direction, the gauge's included

    def tests(move, info=info, trusted=None):
        cov = np.linalg.inv(info + data)
        xyz = SURVEY + (cov @ data @ np.r_[move, np.zeros(6)]).reshape(3, 3)  # noise-free
        return prism_tests(SURVEY, info, xyz, cov, trusted)

    along = tests(0.02 * n)
    assert along.dof[0] == 2 and along.stat[0] < 1e-12, (along.dof, along.stat)
    assert np.all(np.abs(n @ along.directions[0][:, along.determined[0]]) < 1e-9)
    alone = tests(d, trusted=np.zeros(3, bool))  # no other prism trusted: every move is a
    assert alone.dof[0] == 0  # rigid motion of the body, prism 1's gauge
    inplane = tests(d)
    assert inplane.stat[0] > 10 * inplane.critical()[0], inplane.stat
    freed = info.copy()
    freed[:3, :] = freed[:, :3] = 0.0
    after = tests(np.zeros(3), freed, np.array([False, True, True]))
    assert np.all(after.dof[1:] == 1) and np.all(after.stat[1:] < 1e-12), (after.dof, after.stat)


def test_a_move_two_prisms_explain_alike_is_carried_as_both_hypotheses():
    """Prism 1 moved 2 cm in the prisms' plane across its line to prism 3: to first order
    only its distance to prism 2 changes, so a move of prism 2 explains the data as well
    (docs/joint.md#which-prism-moved). The solve carries the other prism's hypothesis beside
    the one it chose (costs within UNDECIDED_COST, weights 1/2, the states' difference a
    shared error of the solution): over three noisy deployments the poses' errors stay
    within their covariance (NEES/dof below 1, where the chosen hypothesis alone misses the
    truth by NEES/dof above 20 on the two that chose prism 2). ``difference`` inverts
    ``retract``."""
    pb = SURVEY
    n = np.cross(pb[1] - pb[0], pb[2] - pb[0])
    d = np.cross(n, pb[0] - pb[2])
    d *= 0.02 / np.linalg.norm(d)
    wrong = 0
    for seed in (9, 10, 11):
        prob, truth = _synthetic(np.random.default_rng(seed), noise=1.0, moved=d)
        prob = replace(prob, qc=prob.qc * 1e-4)
        out, est, sol, info, _ = solve_with_qc(prob, replace(truth, p_body=prob.p_body.copy()),
                                               False, 20, 1e-12)
        chosen = out.prism_found[-1][0]
        assert info.converged and chosen in (0, 1), out.prism_found
        (other, above, w), = out.carried_alternatives
        assert other == 1 - chosen and 0 <= above < UNDECIDED_COST and w == 0.5, above
        err = log_se3(*_compose(np.swapaxes(truth.R, 1, 2),
                                -np.einsum("kji,kj->ki", truth.R, truth.t), est.R, est.t))
        nees = np.einsum("ki,kij,kj->k", err, np.linalg.inv(sol.cov[:, :6, :6]), err)
        assert nees.mean() / 6 < 1.0, nees.mean() / 6
        if chosen == 1:  # the chosen hypothesis alone: the globals' own columns
            wrong += 1
            L = sol.factor[:, :6, :prob.n_globals]
            alone = sol.cov_var[:, :6, :6] + L @ np.swapaxes(L, 1, 2)
            nees1 = np.einsum("ki,kij,kj->k", err, np.linalg.inv(alone), err)
            assert nees1.mean() / 6 > 20, nees1.mean() / 6
    assert wrong == 2, wrong
    rng = np.random.default_rng(3)
    b = retract(out, est, 1e-2 * rng.normal(size=(40, 12)), 1e-3 * rng.normal(size=sol.g.size))
    x, g = difference(out, est, b)
    back = retract(out, est, x, g)
    for a in ("R", "t", "w", "R_s", "t_s", "p_body"):
        np.testing.assert_allclose(getattr(back, a), getattr(b, a), atol=1e-12)


def test_the_hypotheses_carried_do_not_depend_on_which_was_found_first():
    """The two prisms' hypotheses of the move above, each as the one found with the other
    carried beside it (rtsgt.joint.engine.carry_alternatives; the alternatives are solved
    without covariances and the estimate's taken at its state): the same estimate, the same
    covariance and the same hypotheses kept, whichever order; the third prism's hypothesis,
    solved again beside them, is dropped."""
    pb = SURVEY
    n = np.cross(pb[1] - pb[0], pb[2] - pb[0])
    d = np.cross(n, pb[0] - pb[2])
    d *= 0.02 / np.linalg.norm(d)
    prob, truth = _synthetic(np.random.default_rng(9), noise=1.0, moved=d)
    prob = replace(prob, qc=prob.qc * 1e-4)
    s0, sol0, _ = gauss_newton(prob, replace(truth, p_body=prob.p_body.copy()), 20, 1e-12)
    first, freed, alts = snoop_prisms(prob, s0, sol0, 1e-12)
    assert freed and len(alts) == 2, (freed, alts)  # every other candidate, to be solved again
    alike = [a for a in alts if a[0].prism_found[-1][0] in (0, 1)]
    assert first.prism_found[-1][0] in (0, 1) and len(alike) == 1, first.prism_found
    (other, trial_above), = alike
    out = []  # each as the one found, the other's trial score above it
    for p, alt in ((first, (other, trial_above)), (other, (first, -trial_above))):
        s, sol, info = gauss_newton(p, s0, HYPOTHESIS_MAX_ITER, 1e-12)
        out.append(carry_alternatives(p, s, sol, info, (alt,), 1e-12))
    (pa, sa, sola, _), (pb_, sb, solb, _) = out
    assert pa.prism_found[-1][0] == pb_.prism_found[-1][0]
    assert len(pa.prism_alternatives) == len(pb_.prism_alternatives) == 1
    # with the third prism's hypothesis as well: solved again, far above, not carried
    s, sol, info = gauss_newton(first, s0, HYPOTHESIS_MAX_ITER, 1e-12)
    pc, sc, _, _ = carry_alternatives(first, s, sol, info, alts, 1e-12)
    assert [a[0] for a in pc.carried_alternatives] == [a[0] for a in pa.prism_alternatives]
    (_, above, w), = [a for a in pc.prism_alternatives if a[2] == 0]  # listed: by how much
    assert above >= UNDECIDED_COST, above
    np.testing.assert_allclose(sc.t, sa.t, atol=1e-6)
    np.testing.assert_allclose(sa.t, sb.t, atol=1e-6)
    np.testing.assert_allclose(sola.cov[:, :6, :6], solb.cov[:, :6, :6], rtol=1e-4,
                               atol=1e-6 * np.abs(sola.cov[:, :6, :6]).max())


def test_a_hypothesis_is_dropped_only_where_the_data_decide_against_it():
    """rtsgt.joint.engine.undecided: the estimate is the final solve's lowest score; another
    hypothesis is dropped where its final score is at least UNDECIDED_COST above the
    estimate's, unless its trial scored below the estimate's: the noise's update turned the
    order (docs/joint.md#which-prism-moved)."""
    c = UNDECIDED_COST
    decided = undecided(np.array([0.0, 0.5]), np.array([0.0, c + 0.5]))
    assert decided == (0, []), decided
    turned = undecided(np.array([0.0, 77.0]), np.array([40.0, 0.0]))  # the update turns it
    assert turned == (1, [0]), turned
    barely = undecided(np.array([0.0, 0.5, 3 * c]), np.array([c + 0.5, 0.0, 50.0]))
    assert barely == (1, [0]), barely  # any turn keeps it; the third, decided, is dropped
    final_near = undecided(np.array([0.0, 30.0, 80.0]), np.array([c - 0.5, 0.0, 50.0]))
    assert final_near == (1, [0]), final_near


def test_with_the_noise_estimated_a_moved_prism_is_found_after_its_first_update():
    """The prisms' test waits for the noise's first update (weighted by the datasheet, the
    field preset freed the wrong prism of two whose moves explain the data alike:
    docs/joint.md#prism-positions) and still finds the moved prism, here with noise."""
    n, d = _in_plane_move()
    prob, truth = _synthetic(np.random.default_rng(9), K=40, noise=1.0, moved=d)
    prob = replace(prob, qc=prob.qc * 1e-4)
    out, est, sol, info, _ = solve_with_qc(prob, replace(truth, p_body=prob.p_body.copy()),
                                           False, 20, 1e-9, estimate_noise=True)
    assert [f[0] for f in out.prism_found] == [0] and out.noise is not None, out.prism_found
    assert info.converged and out.noise.iterations >= 2, out.noise.iterations
    sig = np.sqrt(np.diag(sol.cov_g)[prob.kappa_col + 1:prob.kappa_col + 4])
    assert np.all(np.abs(est.p_body[0] - prob.p_body[0] - d) < 4 * sig), (est.p_body[0], sig)


def test_gauss_markov_chains_are_estimated_with_the_trajectory():
    """Each station's channels carry a Gauss-Markov noise (sigma 1.5 times the datasheet's,
    tau 2, 5 and 10 s) over a white noise of half the datasheet's: with the chains as knot
    states (rtsgt.joint.gm) the solve with the noise estimated, up to 30 updates (the
    default stops after VCE_MAX_ITER, short of the chains' convergence here: docs/joint.md),
    determines every chain, whose last update moved them by less than VCE_TOL; over the 18
    estimates of sigma and tau the mean squared error in their sigmas is below 3 (one
    deployment: a loose check of their honesty, the benchmark's is the statistical one),
    each sigma within a factor 1.6 and each tau within a factor 3 of the truth (the start:
    0.33 and 0.3-1.5), and the chains' columns of the gradient equal finite differences of
    the cost (docs/joint.md#gauss-markov-noise). (The white factors'
    sigmas ignore their trade with the chains' sigma: the near reference station's Hz factor
    reads 1.0 against 0.25, docs/joint.md.)"""
    rng = np.random.default_rng(31)
    K = 900
    prob, truth = _synthetic(rng, K=K, noise=0.0)
    sig = np.sqrt(prob.meas.var_white[0])
    tau = np.array([2.0, 5.0, 10.0])
    g_true = np.zeros((K, 9))
    for st in range(3):  # each station's chains at its own measurements' times
        on = prob.meas.station == st
        t = prob.meas.t[on]
        x = np.zeros((t.size, 3))
        x[0] = rng.standard_normal(3)
        phi = np.exp(-np.diff(t)[:, None] / tau)
        for i in range(1, t.size):  # the process's recursion, in the test's own code
            x[i] = phi[i - 1] * x[i - 1] + np.sqrt(1 - phi[i - 1] ** 2) * rng.standard_normal(3)
        g_true[on, 3 * st:3 * st + 3] = 1.5 * sig * x
    y = prob.meas.y + np.einsum("mij,mj->mi", gmn.chain_jacobian(prob.meas.station, 9), g_true)
    y = y + 0.5 * sig * rng.standard_normal(y.shape)
    model = gmn.start_model(prob.meas.var_white, prob.meas.station, 3)
    prob = replace(prob, meas=replace(prob.meas, y=y), qc=prob.qc * 1e-4, gm=model)
    start = replace(truth, gm=np.zeros((K, 9)))
    out, est, sol, info, loop = solve_with_qc(prob, start, True, 10, 1e-9, estimate_noise=True,
                                              rng=np.random.default_rng(32), max_updates=30)
    fit = out.gm
    assert info.converged and fit.determined.all() and fit.iterations < 30, (info, fit)
    assert dict(loop.changes)["chains"] < VCE_TOL and loop.iterations < 30, loop
    err = np.stack([np.log(fit.sigma / (1.5 * sig)), np.log(fit.tau_s / tau)], axis=-1)
    assert np.mean((err / fit.sd_log) ** 2) < 3.0, (err, fit.sd_log)
    assert np.all(np.abs(err[..., 0]) < np.log(1.6)), fit.sigma / (1.5 * sig)
    assert np.all(np.abs(err[..., 1]) < np.log(3.0)), fit.tau_s
    # the chains' columns of the gradient against finite differences of the cost
    _assert_knot_gradient(replace(prob, gm=fit), replace(truth, gm=0.5 * g_true),
                          ((0, 12), (3, 13), (301, 20), (K - 1, 17), (450, 3)), 1e-9)


def _assert_knot_gradient(prob, state, cases, h):
    """The knots' columns ``cases`` ((knot, column), ...) of the gradient of ``assemble``'s
    cost at ``state`` against its central finite differences with step ``h``."""
    system, _ = assemble(prob, state)
    for knot, j in cases:
        x = np.zeros((prob.t_knot.size, prob.knot_dim))
        x[knot, j] = h
        cp, cm = (assemble(prob, retract(prob, state, sgn * x, np.zeros(prob.n_globals)))[1]
                  for sgn in (1.0, -1.0))
        assert (cp - cm) / (2 * h) == pytest.approx(-2 * system.a[knot, j], rel=1e-4,
                                                     abs=1e-2), (knot, j)


def _with_knots_at(prob, s, sol, tq):
    """The same problem with knots of their own at ``tq`` (no measurement there), started at
    the GP's interpolation, solved again: (state, solution, indices of the query knots)."""
    K = prob.t_knot.size
    Rq, pq, _ = interpolate_poses_gp(tq, prob.t_knot, s.R, s.t, s.w, prob.qc, sol.cov,
                                     sol.cov_next)
    t2 = np.sort(np.concatenate([prob.t_knot, tq]))
    of, qi = np.searchsorted(t2, prob.t_knot), np.searchsorted(t2, tq)
    k = np.clip(np.searchsorted(prob.t_knot, t2, side="right") - 1, 0, K - 2)
    R2, p2, w2 = np.empty((t2.size, 3, 3)), np.empty((t2.size, 3)), np.empty((t2.size, 6))
    R2[of], p2[of], w2[of] = s.R, s.t, s.w
    R2[qi], p2[qi], w2[qi] = Rq, pq, s.w[k[qi]]
    prob2 = replace(prob, t_knot=t2, of_meas=of[prob.of_meas], qc=prob.qc[k[:-1]])
    s2, sol2, _ = gauss_newton(prob2, replace(s, R=R2, t=p2, w=w2), 20, 1e-14)
    return s2, sol2, qi


@pytest.mark.parametrize("speed, tol", [(1e-4, 1e-6), (1.0, 1e-2)])
def test_interpolation_between_knots_equals_a_knot_at_the_query_time(speed, tol):
    """The GP's pose and covariance between knots are those of a knot placed there, to
    ``tol`` relative: exactly in the limit of slow motion (1e-4 of the synthetic's speed:
    40 um and 6 urad per interval), to first order in the interval's motion at its full
    speed (0.4 m and 0.06 rad per interval), where the two linearisations differ."""
    rng = np.random.default_rng(7)
    prob, truth = _synthetic(rng, K=30, noise=1e-3, speed=speed)
    prob = replace(prob, qc=np.broadcast_to(prob.qc, (29, 6)).copy())
    s, sol, _ = gauss_newton(prob, truth, 20, 1e-14)
    tq = prob.t_knot[:-1] + np.tile([0.13, 0.2, 0.31], 10)[:29]
    Rq, pq, cq = interpolate_poses_gp(tq, prob.t_knot, s.R, s.t, s.w, prob.qc, sol.cov,
                                      sol.cov_next)
    s2, sol2, qi = _with_knots_at(prob, s, sol, tq)
    c2 = sol2.cov[qi, :6, :6]
    scale = np.sqrt(np.einsum("kii->k", c2))
    d = perturbation(s2.R[qi], s2.t[qi], Rq, pq)
    assert np.abs(d).max() < tol * scale.min(), (np.abs(d).max(), scale.min())
    rel = np.abs(cq - c2).max(axis=(1, 2)) / np.abs(c2).max(axis=(1, 2))
    assert rel.max() < tol, rel.max()
    # at a knot's time the interpolation is the knot's marginal
    Rk, pk, ck = interpolate_poses_gp(prob.t_knot[3:5], prob.t_knot, s.R, s.t, s.w, prob.qc,
                                      sol.cov, sol.cov_next)
    np.testing.assert_allclose(pk, s.t[3:5], atol=1e-12)
    np.testing.assert_allclose(ck, sol.cov[3:5, :6, :6], rtol=1e-9, atol=1e-20)
    with pytest.raises(InputError, match="outside the measurements' span"):
        interpolate_poses_gp(prob.t_knot[-1:] + 0.1, prob.t_knot, s.R, s.t, s.w, prob.qc,
                             sol.cov, sol.cov_next)


def test_prior_redundancy_numbers_match_a_dense_inverse():
    """Each interval's and axis' redundancy ``2 - tr(Q_i^-1 (J Sigma J^T)_i)`` and unit
    quadratic form (rtsgt.joint.qc.prior_components) against the dense normal matrix's
    inverse; all redundancies of a problem add to its rows minus its unknowns."""
    rng = np.random.default_rng(4)
    prob, truth = _synthetic(rng, K=13, noise=1.0)
    qc = np.broadcast_to(prob.qc, (12, 6)) * rng.uniform(0.5, 2.0, (12, 6))
    prob = replace(prob, qc=qc)
    s, sol, _ = gauss_newton(prob, truth, 10, 1e-12)
    M, _ = assemble(prob, s)[0].dense()
    inv = np.linalg.inv(M)
    dt = np.diff(prob.t_knot)
    e, E, F = prior_terms(s.R, s.t, s.w, dt)
    quad, red = prior_components(e, E, F, dt, qc, sol.cov, sol.cov_next)
    W = wnoa_q_inv(dt, qc)
    for k in range(12):
        J = np.zeros((12, inv.shape[0]))
        J[:, 12 * k:12 * k + 24] = np.concatenate([E[k], F[k]], axis=1)
        Mk = J @ inv @ J.T
        for i in range(6):
            rows = np.ix_([i, 6 + i], [i, 6 + i])
            assert red[k, i] == pytest.approx(2 - np.trace(W[k][rows] @ Mk[rows]), abs=1e-9)
            assert quad[k, i] == pytest.approx(e[k, [i, 6 + i]] @ W[k][rows] @ e[k, [i, 6 + i]]
                                               * qc[k, i], rel=1e-9)
    assert 0 < red.min() and red.max() < 2


def test_measurement_redundancy_numbers_match_a_dense_inverse():
    """Each measurement's ``H Sigma H^T`` (rtsgt.joint.engine.measurement_hsh: the knot's
    marginal and its covariance with the globals, stations, prisms and clocks) against the
    dense normal matrix's inverse; the redundancy numbers of all rows and priors add to the
    rows minus the unknowns."""
    rng = np.random.default_rng(12)
    prob, truth = _synthetic(rng, K=14, noise=1.0, clock_s=[0.0, 0.004, -0.002],
                             moved=np.zeros(3))
    prob = replace(prob, tau=rng.uniform(-1e-3, 1e-3, 14))
    s, sol, _ = gauss_newton(prob, truth, 10, 1e-12)
    system, _ = assemble(prob, s)
    M, _ = system.dense()
    inv = np.linalg.inv(M)
    _, Hk, Hg = measurement_terms(prob, s)
    d = prob.knot_dim
    n = d * 14
    H = np.zeros((14, 3, M.shape[0]))
    for m in range(14):
        H[m, :, d * m:d * m + d] = Hk[m]  # one measurement per knot
        H[m, :, n:] = Hg[m]
    ref = np.einsum("mia,ab,mjb->mij", H, inv, H)
    got = measurement_hsh(prob, s, sol)
    np.testing.assert_allclose(got, ref, atol=1e-9 * np.abs(ref).max())
    red = 3 * 14 - np.einsum("mij,mji->", prob.meas.info, got)
    assert 0 < red < 3 * 14, red


def test_noise_components_of_a_solved_problem_recover_the_truth():
    """Noise 0.6, 1 and 1.4 times the datasheet's sigma on (Hz, V, d): the joint solve with
    the white noise estimated (rtsgt.joint.engine.noise_step in the solve's loop) recovers
    each station's variance factors within 3 sigma (9 groups of ~130 measurements); no range
    part enters (none simulated)."""
    rng = np.random.default_rng(21)
    prob, truth = _synthetic(rng, K=400, noise=0.0)
    sig = np.sqrt(prob.meas.var_white[0])
    scale = np.array([0.6, 1.0, 1.4])
    y = prob.meas.y + rng.normal(size=prob.meas.y.shape) * sig * scale
    prob = replace(prob, meas=replace(prob.meas, y=y), qc=prob.qc * 1e-4)
    prob2, _, _, info, loop = solve_with_qc(prob, truth, True, 10, 1e-9, estimate_noise=True)
    nf = prob2.noise
    assert info.converged and nf.determined[:, :, 0].all() and not nf.determined[:, :, 1].any()
    z = (nf.theta[:, :, 0] - scale**2) / nf.sigma[:, :, 0]
    assert np.all(np.abs(z) < 3), z
    assert np.all(nf.sigma[:, :, 0] / nf.theta[:, :, 0] < 0.2), nf.sigma
    # the loop says how far each part moved at its last update: the white noise's settles,
    # stopped after one update it has not (the factors 0.36 and 1.96 move from the
    # datasheet's 1 by far more than VCE_TOL)
    assert dict(loop.changes)["white"] < VCE_TOL, loop
    one = solve_with_qc(prob, truth, True, 10, 1e-9, estimate_noise=True, max_updates=1)[4]
    assert dict(one.changes)["white"] > 0.3 and not one.converged and one.iterations == 1, one


def test_qc_per_class_pools_the_uninformed_groups_and_holds_the_floor():
    quad = np.array([[4.0, 1e-14, 1.0, 1.0, 1.0, 1.0]] * 30 + [[9.0, 1e-14, 1.0, 1.0, 1.0, 1.0]] * 3)
    red = np.ones_like(quad)
    classes = np.array([1] * 30 + [3] * 3)
    table, own = qc_per_class(quad, red, classes)
    assert own[1].all() and not own[3].any() and not own[0].any()
    assert table[1, 0] == pytest.approx(4.0) and table[3, 0] == pytest.approx(9.0)
    assert table[0, 0] == pytest.approx(9.0)  # the axis' pool of the groups not own
    assert table[1, 1] == QC_FLOOR


def test_body_covariance_maps_to_the_project_convention():
    """A right (body) perturbation d of T is the world-frame (dt, dtheta) of
    rtsgt.geometry.transform.perturbation, A d with A = diag(R, R), to first order."""
    rng = np.random.default_rng(6)
    R = exp_so3(rng.normal(size=(5, 3)))
    t = rng.normal(size=(5, 3))
    d = rng.normal(size=(5, 6)) * 1e-7
    world = perturbation(R, t, *_right(R, t, d))
    A = body_to_world_cov(R, np.broadcast_to(np.eye(6), (5, 6, 6)))  # A A^T = A I A^T
    L = np.linalg.cholesky(A)  # A A^T of an orthogonal block matrix is I: check the map
    np.testing.assert_allclose(L, np.broadcast_to(np.eye(6), L.shape), atol=1e-12)
    np.testing.assert_allclose(world[:, :3], np.einsum("kij,kj->ki", R, d[:, :3]), atol=1e-13)
    np.testing.assert_allclose(world[:, 3:], np.einsum("kij,kj->ki", R, d[:, 3:]), atol=1e-13)
    cov = rng.normal(size=(5, 6, 6))
    cov = cov @ np.swapaxes(cov, 1, 2)
    mapped = body_to_world_cov(R, cov)
    Ab = np.zeros((5, 6, 6))
    Ab[:, :3, :3] = R
    Ab[:, 3:, 3:] = R
    np.testing.assert_allclose(mapped, Ab @ cov @ np.swapaxes(Ab, 1, 2), atol=1e-12)


def test_knots_merge_close_times_and_keep_query_times_exact():
    kn = build_knots(np.array([0.1, 0.1004, 0.3, 0.5003]), np.array([0.2, 0.5]), 1e-3)
    np.testing.assert_allclose(kn.t, [0.1, 0.2, 0.3, 0.5])
    np.testing.assert_array_equal(kn.of_measurement, [0, 0, 2, 3])
    np.testing.assert_allclose(kn.tau, [0.0, 4e-4, 0.0, 3e-4], atol=1e-15)
    np.testing.assert_array_equal(kn.of_query, [1, 3])


# ------------------------------------------------------------------ simulated deployments


def _run(tmp, seed):
    sim = simulate_deployment(SimulationConfig(duration_s=60.0, noise_time_sync=False,
                                               noise_survey=False), np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, tmp / f"dep{seed}"))
    srcs = tuple(s for s in opts.noise.sources if s != "time_sync")
    opts = replace(opts.updated(seed=seed, engine="linear"), noise=opts.noise.with_sources(srcs))
    res = run_pipeline(data, opts)
    comp = res.computation
    est, keep = comp.estimate, comp.keep
    tq = comp.prisms.t[keep]
    obs = [o.select(np.isin(o.t, comp.tracks[o.prism].t)) for o in data.observations]
    qc = qc_from_prisms(np.stack([res.qc[p] for p in data.reference.names]), data.reference.xyz)
    jr = estimate_joint(obs, comp.calibration, data.reference, comp.noise_model, tq, tq,
                        est.R[keep], est.t[keep], qc, weather=data.weather)
    p, q = sim.truth_at(tq)
    err = perturbation(quat_xyzw_to_matrix(q), p, jr.estimate.R, jr.estimate.t)
    nees = np.einsum("ki,kij,kj->k", err, np.linalg.inv(jr.estimate.cov), err)
    ratio = np.sqrt(np.einsum("kii->k", jr.estimate.cov[:, :3, :3])
                    / np.einsum("kii->k", est.cov[keep][:, :3, :3]))
    return jr, nees, ratio, (obs, comp, data, tq, est, keep, qc)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("joint")
    return [_run(tmp, seed) for seed in (11, 12)]


def test_joint_poses_are_within_their_covariance_and_more_precise(simulated):
    """Qc per motion class from the data (docs/joint.md#qc-from-the-data): the position sigma
    falls to about half the per-prism engine's (0.78 with the Qc of the per-prism GPs on
    seed 11), the NEES stays near 1 (two 60 s runs: little power, the 600 s benchmark has
    the numbers)."""
    for jr, _, _, _ in simulated:
        assert jr.solve.converged and jr.solve.iterations <= 8, jr.solve
        # the shared split (docs/joint.md#the-shared-error) adds up to the pose covariance
        sh = jr.shared
        total = jr.estimate.cov
        assert np.abs(sh.total_cov - total).max() < 1e-9 * np.abs(total).max()
        np.testing.assert_array_equal(sh.t, jr.t)
        assert sh.names[:6] == tuple(f"calibration_station{sh.names[0][19]}_{c}"
                                     for c in ("x", "y", "z", "rx", "ry", "rz"))
        assert sh.names[-1] == "atmosphere_ppm" and len(sh.names) % 6 == 1, sh.names
        # the stations' calibration is a large share of the position variance (docs)
        frac = np.einsum("kii->k", sh.shared_cov[:, :3, :3]) / np.einsum("kii->k",
                                                                        total[:, :3, :3])
        assert 0.05 < np.median(frac) < 0.95, np.median(frac)
        assert jr.qc.iterations >= 2 and jr.n_knots <= jr.n_measurements, jr.qc
    nees = np.concatenate([s[1] for s in simulated])
    ratio = np.concatenate([s[2] for s in simulated])
    assert 0.6 < nees.mean() / 6 < 1.5, nees.mean() / 6
    assert np.median(ratio) < 0.65, np.median(ratio)


def test_the_joint_poses_do_not_depend_on_the_survey_frames_origin(simulated):
    """The survey's body frame moved 10 m away (the prisms' coordinates plus ``b``, the
    poses to start from turned with it): the knots' frame is the prisms' centroid whichever
    the body frame's origin (docs/joint.md#the-knots-origin), so the poses are the same body
    motion, ``t - R b``, and their covariances the same, carried to the new origin
    (``A = [[I, (R b)^], [0, I]]``) to round-off; at the body frame's origin the motion
    prior's ``Qc`` (the prisms' own, :func:`qc_from_prisms`) would be the wrong one there."""
    jr, _, _, (obs, comp, data, tq, est, keep, qc) = simulated[0]
    b = np.array([8.0, -6.0, 1.0])
    ref = replace(data.reference, xyz=data.reference.xyz + b)
    R0, t0 = est.R[keep], est.t[keep] - np.einsum("kij,j->ki", est.R[keep], b)
    moved = estimate_joint(obs, comp.calibration, ref, comp.noise_model, tq, tq, R0, t0, qc,
                           weather=data.weather)  # qc_from_prisms: the centroid's, the same
    R, t = jr.estimate.R, jr.estimate.t
    Rb = np.einsum("kij,j->ki", R, b)
    np.testing.assert_allclose(moved.estimate.R, R, atol=1e-9)
    np.testing.assert_allclose(moved.estimate.t, t - Rb, atol=1e-8)
    A = np.broadcast_to(np.eye(6), (R.shape[0], 6, 6)).copy()
    A[:, :3, 3:] = hat(Rb)
    cov = A @ jr.estimate.cov @ np.swapaxes(A, 1, 2)
    np.testing.assert_allclose(moved.estimate.cov, cov, rtol=1e-6, atol=1e-6 * np.abs(cov).max())


def test_prisms_and_noise_estimated_on_a_simulated_deployment(simulated):
    """The standard simulator (no prism moved, noise the datasheet's): with the prisms and
    the white noise estimated no prism is found, the shared split names the prisms' columns
    and still adds up, and the distances' factors are 1 within 3 sigma (the angles' are
    biased low by the motion model: docs/joint.md#noise-identification)."""
    _, _, _, (obs, comp, data, tq, est, keep, _) = simulated[0]
    qc = np.array([0.1, 0.1, 0.01, 1e-3, 1e-3, 0.01])
    jr = estimate_joint(obs, comp.calibration, data.reference, comp.noise_model, tq, tq,
                        est.R[keep], est.t[keep], qc, weather=data.weather, prisms=True,
                        noise=True)
    pf, nf, sh = jr.prisms, jr.noise, jr.shared
    assert not pf.moved.any() and pf.names == data.reference.names, pf.shift_sigma
    assert np.all(pf.shift_sigma**2 < chi2.ppf(1 - 1e-3 / 3, np.maximum(pf.dof, 1)))
    assert [n for n in sh.names if n.startswith("reference_")] == [
        f"reference_{p}_{c}" for p in data.reference.names for c in "xyz"]
    assert np.abs(sh.total_cov - jr.estimate.cov).max() < 1e-9 * np.abs(jr.estimate.cov).max()
    det = nf.determined[:, 2, 0]
    assert nf.stations == tuple(comp.calibration.transforms) and det.sum() >= 2, nf.redundancy
    np.testing.assert_array_equal(nf.theta[~det, 2, 0], 1.0)  # too little redundancy: prior
    z = (nf.theta[det, 2, 0] - 1.0) / nf.sigma[det, 2, 0]
    assert np.all(np.abs(z) < 3), z


def test_a_tie_of_two_prisms_hypotheses_is_carried_into_the_shared_split(simulated):
    """The survey of the first prism off by 6 mm in the prisms' plane across its line to the
    second (a move of the first or of the third explains the data alike to first order, and
    at 6 mm the second order is within the noise: docs/joint.md#which-prism-moved): one of
    the two is found and the other carried at weight 1/2; the shared
    split names, per hypothesis carried, its own columns of every shared parameter and its
    difference (file-formats.md), and still adds up to the poses' covariance."""
    _, _, _, (obs, comp, data, tq, est, keep, _) = simulated[0]
    pb = data.reference.xyz
    d = np.cross(np.cross(pb[1] - pb[0], pb[2] - pb[0]), pb[0] - pb[1])
    xyz = pb.copy()
    xyz[0] += 0.006 * d / np.linalg.norm(d)
    qc = np.array([0.1, 0.1, 0.01, 1e-3, 1e-3, 0.01])
    jr = estimate_joint(obs, comp.calibration, replace(data.reference, xyz=xyz),
                        comp.noise_model, tq, tq, est.R[keep], est.t[keep], qc,
                        weather=data.weather, prisms=True)
    pf, sh = jr.prisms, jr.shared
    names = data.reference.names
    (found,), (other,) = np.flatnonzero(pf.moved), np.flatnonzero((pf.weight > 0) & ~pf.moved)
    assert {found, other} == {0, 2} and pf.weight[found] == pf.weight[other] == 0.5, pf.weight
    own = [n for n in sh.names if not n.startswith("moved_")]
    assert sh.names == tuple(own) + tuple(f"moved_{names[other]}_{n}" for n in own) + (
        f"moved_{names[other]}",), sh.names
    assert np.abs(sh.total_cov - jr.estimate.cov).max() < 1e-9 * np.abs(jr.estimate.cov).max()


def test_clock_offsets_of_a_field_deployment_within_two_sigma(tmp_path):
    """The field-hour preset's clocks (drifting 10-20 ms/h plus a random walk) and white
    noise of its own with a far station; its moved prism, Gauss-Markov noise, reality effects
    and survey noise off (the joint engine does not estimate the prisms nor the correlated
    noise yet; they alias into the clocks, docs/joint.md#clock-offsets). Each non-reference
    station's offset against the reference at 1 Hz within 2 sigma of the truth: >= 80 % of
    the samples pooled over three 120 s runs (measured 84 %; 93-100 % on 600 s runs,
    benchmarks/joint.py --field --clocks)."""
    cfg = preset_config("field-hour", duration_s=120.0)
    cfg = replace(cfg, field=replace(cfg.field, prism_displacement_m=(0.0, 0.0),
                                     angle_gm_rad=(0.0, 0.0), distance_gm_m=(0.0, 0.0)),
                  reality=RealityEffects(), noise_survey=False)
    within = []
    for seed in (21, 22, 23):
        sim = simulate_deployment(cfg, np.random.default_rng(seed))
        data, opts = load_deployment(write_deployment(sim, tmp_path / f"field{seed}"))
        res = run_pipeline(data, opts.updated(seed=seed, engine="linear"))
        comp = res.computation
        est, keep = comp.estimate, comp.keep
        tq = comp.prisms.t[keep]
        obs = [o.select(np.isin(o.t, comp.tracks[o.prism].t)) for o in data.observations]
        qc = qc_from_prisms(np.stack([res.qc[p] for p in data.reference.names]),
                            data.reference.xyz)
        jr = estimate_joint(obs, comp.calibration, data.reference, comp.noise_model, tq, tq,
                            est.R[keep], est.t[keep], qc, weather=data.weather, clocks=True)
        f = sim.truth.field
        t = np.arange(np.ceil(tq[0]), tq[-1], 1.0)
        assert set(jr.clocks) == set(f.station_ids[1:])
        for sid, (kn, off, cov) in jr.clocks.items():
            W = np.stack([np.interp(t, kn, e) for e in np.eye(kn.size)], axis=1)
            true = -(f.clock_error_s(f.station_ids.index(sid), t) - f.clock_error_s(0, t))
            sig = np.sqrt(np.einsum("ti,ij,tj->t", W, cov, W))
            within.append(np.abs(W @ off - true) < 2 * sig)
            assert np.all(sig < 1e-3), sig.max()
    assert np.mean(np.concatenate(within)) >= 0.8, np.mean(np.concatenate(within))


def test_bad_inputs_are_named(simulated):
    _, _, _, (obs, comp, data, tq, est, keep, _) = simulated[0]
    with pytest.raises(InputError, match="qc of shape"):
        estimate_joint(obs, comp.calibration, data.reference, comp.noise_model, tq, tq,
                       est.R[keep], est.t[keep], np.ones(3))
    moved = [replace(obs[0], station="9")] + obs[1:]
    with pytest.raises(InputError, match="station '9'"):
        estimate_joint(moved, comp.calibration, data.reference, comp.noise_model, tq, tq,
                       est.R[keep], est.t[keep], np.ones(6))
    # a run that may not fit: warned of; one that fits: silent
    need = solve_bytes(20000, 43, 82)
    with pytest.warns(RtsgtWarning, match=r"20000 knots of 43 states and 82 globals may "
                      r"need up to 7.8 GB, 6.0 GB is available"):
        estimate_module._check_memory(20000, 43, 82, int(6e9))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        estimate_module._check_memory(20000, 43, 82, int(RUN_PER_SOLVE * need) + 1)
        estimate_module._check_memory(20000, 43, 82, None)
    # more memory than the machine has for one solve: said before any solve, with the sizes
    need = solve_bytes(tq.size, 12, 13)  # at least: as many knots as queries, 12 states
    with pytest.raises(InputError, match=r"joint engine: \d+ knots of 12 states and \d+ "
                       r"globals need at least [\d.]+ GB for one solve, 0.0 GB is available"):
        estimate_joint(obs, comp.calibration, data.reference, comp.noise_model, tq, tq,
                       est.R[keep], est.t[keep], np.ones(6), memory_bytes=need // 1000)


@pytest.mark.parametrize("depth", [0.0, 0.6])
def test_the_vehicles_rocking_is_estimated_with_the_trajectory(depth):
    """The knots' poses rocked by a first-order Gauss-Markov process per axis (shifts 2 mm,
    rotations 1 mrad about a pivot ``depth`` m below the knots' origin, tau 1 s; the
    measurements see the rocked pose, composed exactly by the test) over a
    white noise of half the datasheet's: with the rocking as knot states
    (rtsgt.joint.rocking) the solve with the noise estimated determines every axis's chain;
    the shifts' sigma within 10 % and tau within a factor 2 of the truth, the rotations'
    sigma within a factor 2, the yaw's about the pivot below within 3 (their correlated
    part, 0.6 mm at the prisms, is shared with the trajectory's turning, the yaw's most:
    their tau reads 0.1-0.2 s; the yaw's sigma 0.6 of the truth about the origin, 0.4 about
    the pivot below), with
    the pivot given to the model (docs/joint.md#the-rockings-pivot); the knots' poses with
    their rocking (rocked_knots) are the rocked truth's to NEES/dof 0.7-1.3 (about the
    pivot, of the position, roll and pitch: the yaw's reads z^2 4.9 there, 2.3 about the
    origin, its rocking taken for the trajectory's turning); the rocking's columns of the
    gradient equal finite differences of the cost (docs/joint.md#the-vehicles-rocking)."""
    rng = np.random.default_rng(41)
    K = 600
    prob, truth = _synthetic(rng, K=K, noise=0.0)
    sigma = np.array([2e-3, 2e-3, 2e-3, 1e-3, 1e-3, 1e-3])
    tau = 1.0
    x = np.zeros((K, 6))
    x[0] = rng.standard_normal(6)
    phi = np.exp(-np.diff(prob.t_knot) / tau)
    for i in range(1, K):  # the process's recursion, in the test's own code
        x[i] = phi[i - 1] * x[i - 1] + np.sqrt(1 - phi[i - 1] ** 2) * rng.standard_normal(6)
    rock = sigma * x
    # the rocked truth: T exp(rho^) about the knot, then the rotation about the pivot p
    Rr = exp_so3(rock[:, 3:])
    pivot = np.array([0.0, 0.0, -depth])
    dp = rock[:, :3] + pivot - Rr @ pivot
    R_true, t_true = truth.R @ Rr, truth.t + np.einsum("kij,kj->ki", truth.R, dp)
    rocked_truth = replace(truth, R=R_true, t=t_true)
    y = prob.meas.y - measurement_terms(prob, rocked_truth)[0]  # h(rocked)
    rocked = replace(prob, rocking=start_rocking(), pivot=None if depth == 0 else pivot)
    sig = np.sqrt(prob.meas.var_white[0])
    y = y + 0.5 * sig * rng.standard_normal(y.shape)
    prob = replace(rocked, meas=replace(prob.meas, y=y), qc=prob.qc * 1e-4)
    start = replace(truth, rocking=np.zeros((K, 6)))
    out, est, sol, info, _ = solve_with_qc(prob, start, True, 10, 1e-9, estimate_noise=True,
                                           rng=np.random.default_rng(42), max_updates=30)
    fit = out.rocking
    assert info.converged and fit.determined.all(), (info, fit)
    ratio = fit.sigma.ravel() / sigma
    assert np.all(np.abs(ratio[:3] - 1) < 0.1), ratio
    yaw_bound = np.log(2) if depth == 0 else np.log(3)  # about the pivot, the yaw's: above
    assert np.all(np.abs(np.log(ratio[3:5])) < np.log(2)) and abs(np.log(ratio[5])) < yaw_bound, ratio
    assert np.all(np.abs(np.log(fit.tau_s[0] / tau)) < np.log(2)), fit.tau_s
    # the knots' poses with their rocking against the rocked truth
    c = out.rocking_col
    R_est, t_est, rsol = rocked_knots(est.R, est.t, est.rocking, sol, c)
    err = log_se3(*_compose(np.swapaxes(R_true, 1, 2),
                            -np.einsum("kji,kj->ki", R_true, t_true), R_est, t_est))
    ax = np.arange(6 if depth == 0 else 5)  # about the pivot, the yaw's: docs/joint.md
    cov = rsol.cov[:, ax][:, :, ax]
    nees = np.einsum("ki,kij,kj->k", err[:, ax], np.linalg.inv(cov), err[:, ax]).mean() / ax.size
    assert 0.7 < nees < 1.3, nees
    # the rocking's columns of the gradient against finite differences of the cost
    _assert_knot_gradient(out, replace(truth, rocking=0.5 * rock),
                          ((0, c), (3, c + 1), (301, c + 5), (K - 1, c + 3), (450, c + 2)), 1e-9)


def test_the_rockings_bridge_variance_and_the_rocked_knots():
    """Between two knots the rocking's variance given its values there
    (rtsgt.joint.rocking.bridge_variance) is the Gauss-Markov process's conditional variance
    from its dense covariance at the three times (the test's own), zero at the knots; the
    rocked knots' covariances (rocked_knots) are ``J Sigma J^T`` with the pose's rows the
    pose's plus the rocking's, their shared factor ``J L``, their poses ``T exp(r^)``."""
    model = start_rocking()
    model = replace(model, sigma=np.array([[1e-3, 2e-3, 3e-3], [4e-3, 5e-3, 6e-3]]),
                    tau_s=np.array([[0.1, 0.3, 1.0], [2.0, 0.05, 0.5]]))
    t_knot = np.array([0.0, 0.2, 0.5, 1.5])
    tq = np.array([0.0, 0.05, 0.2, 0.31, 0.49, 1.0, 1.5])
    got = bridge_variance(tq, t_knot, model)
    sig, tau = model.sigma.ravel(), model.tau_s.ravel()
    for q, t in enumerate(tq):
        k = min(np.searchsorted(t_knot, t, side="right") - 1, t_knot.size - 2)
        times = np.array([t_knot[k], t, t_knot[k + 1]])
        for a in range(6):
            C = sig[a] ** 2 * np.exp(-np.abs(times[:, None] - times[None, :]) / tau[a])
            ends = [0, 2]
            cond = C[1, 1] - C[1, ends] @ np.linalg.solve(C[np.ix_(ends, ends)], C[ends, 1])
            assert got[q, a] == pytest.approx(cond, rel=1e-6, abs=1e-12 * sig[a] ** 2), (t, a)
    assert np.all(got[[0, 2, 6]] < 1e-20)
    rng = np.random.default_rng(5)
    K, d, G, col = 4, 20, 3, 14
    A = rng.standard_normal((K * d + G, K * d + G))
    full = A @ A.T
    cov = np.stack([full[k * d:(k + 1) * d, k * d:(k + 1) * d] for k in range(K)])
    nxt = np.stack([full[k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d] for k in range(K - 1)])
    factor = rng.standard_normal((K, d, G))
    sol = sparse.ArrowSolution(np.zeros((K, d)), np.zeros(G), cov.copy(), nxt.copy(),
                               np.eye(G), cov.copy(), nxt.copy(), factor.copy(), np.eye(G))
    R = exp_so3(rng.normal(0, 0.3, (K, 3)))
    t = rng.standard_normal((K, 3))
    r = rng.normal(0, 1e-3, (K, 6))
    Rr, tr, out = rocked_knots(R, t, r, sol, col)  # (in place)
    J = np.eye(d)
    J[:6, col:col + 6] += np.eye(6)
    np.testing.assert_allclose(out.cov, J @ cov @ J.T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out.cov_next, J @ nxt @ J.T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out.cov_var, J @ cov @ J.T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out.cov_var_next, J @ nxt @ J.T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out.factor, J @ factor, rtol=1e-12, atol=1e-12)
    dR, dp = exp_se3(r)
    np.testing.assert_allclose(Rr, R @ dR, atol=1e-15)
    np.testing.assert_allclose(tr, t + np.einsum("kij,kj->ki", R, dp), atol=1e-15)


def test_the_rocking_about_a_pivot_and_its_prior():
    """Rotations ``phi`` about a pivot (pivot_map) are the exact rotation about it to second
    order in ``phi``; the rocking's prior in the
    knots' columns (add_rocking_prior) is the inverse of the rocked perturbations' dense
    covariance, ``P Sigma_u P^T`` with each process axis ``sigma^2 exp(-|dt| / tau)`` (the
    test's own), its cost, gradient and the chains' moments (rocking_moments) those of the
    process ``u = P^-1 r``."""
    rng = np.random.default_rng(6)
    K = 5
    phi = rng.normal(0.0, 1e-3, (K, 3))
    pv = np.array([0.1, -0.05, -0.7])
    dp_exact = pv - exp_so3(phi) @ pv
    M = pivot_map(pv)
    dR, dp = exp_se3(np.concatenate([np.zeros((K, 3)), phi], axis=1) @ M.T)
    np.testing.assert_allclose(dR, exp_so3(phi), atol=1e-15)
    err = np.linalg.norm(dp - dp_exact, axis=1)  # second order: at most |p| |phi|^2
    assert np.all(err < np.linalg.norm(pv) * np.sum(phi**2, axis=1)), err
    assert np.all(np.linalg.norm(dp_exact, axis=1) > 100 * err)
    np.testing.assert_allclose(pivot_map(-pv) @ M, np.eye(6), atol=1e-15)
    np.testing.assert_array_equal(pivot_map(None), np.eye(6))
    # the prior against the dense covariance
    model = replace(start_rocking(), sigma=np.array([[1e-3, 2e-3, 3e-3], [4e-3, 5e-3, 6e-3]]),
                    tau_s=np.array([[0.1, 0.3, 1.0], [2.0, 0.05, 0.5]]))
    t = np.cumsum(rng.uniform(0.05, 0.5, K))
    d, col = 9, 2
    D, U, a = np.zeros((K, d, d)), np.zeros((K - 1, d, d)), np.zeros((K, d))
    r = rng.normal(0.0, 1e-3, (K, 6))
    cost = add_rocking_prior(D, U, a, r, np.diff(t), model, col, pv)
    sig, tau = model.sigma.ravel(), model.tau_s.ravel()
    cov_u = np.zeros((6 * K, 6 * K))  # knot-major
    for ax in range(6):
        cov_u[ax::6, ax::6] = sig[ax] ** 2 * np.exp(-np.abs(t[:, None] - t[None, :]) / tau[ax])
    Pk = np.kron(np.eye(K), M)
    info = np.linalg.inv(Pk @ cov_u @ Pk.T)
    j = slice(col, col + 6)
    big = np.abs(info).max()
    for k in range(K):
        np.testing.assert_allclose(D[k, j, j], info[6 * k:6 * k + 6, 6 * k:6 * k + 6],
                                   rtol=1e-8, atol=1e-8 * big)
    for k in range(K - 1):
        np.testing.assert_allclose(U[k, j, j], info[6 * k:6 * k + 6, 6 * k + 6:6 * k + 12],
                                   rtol=1e-8, atol=1e-8 * big)
    assert cost == pytest.approx(r.ravel() @ info @ r.ravel(), rel=1e-8)
    grad = info @ r.ravel()
    np.testing.assert_allclose(a[:, j].ravel(), -grad, rtol=1e-8, atol=1e-8 * np.abs(grad).max())
    # the chains' moments: the process u = P^-1 r's means, variances and lag-one covariances
    A = rng.standard_normal((6 * K, 6 * K))
    cov_r = A @ A.T
    blk = [slice(6 * k, 6 * k + 6) for k in range(K)]
    moments = rocking_moments(r, np.stack([cov_r[b, b] for b in blk]),
                              np.stack([cov_r[blk[k], blk[k + 1]] for k in range(K - 1)]),
                              np.diff(t), pv)
    Pinv = np.kron(np.eye(K), np.linalg.inv(M))
    u, cov_uu = (Pinv @ r.ravel()).reshape(K, 6), Pinv @ cov_r @ Pinv.T
    for row, (g, var, cross, dt) in enumerate(moments):  # shifts, rotations
        ax = 3 * row + np.arange(3)
        np.testing.assert_allclose(g, u[:, ax], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(var, [np.diag(cov_uu[b, b])[ax] for b in blk], rtol=1e-10)
        np.testing.assert_allclose(cross, [np.diag(cov_uu[blk[k], blk[k + 1]])[ax]
                                           for k in range(K - 1)], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(dt, np.diff(t))


def test_gauss_newton_stops_where_no_halved_step_lowers_the_cost(monkeypatch):
    """Every state but the start made to cost more than the start (as a wrong linearisation
    sees it): each of the 8 halvings of the first step raises the cost, so the solve
    stops at its start, unconverged, instead of taking the last halving and going on (an
    hour's hypothesis solve ran 30 such iterations, 215 assemblies, its cost creeping up)."""
    rng = np.random.default_rng(5)
    prob, truth = _synthetic(rng)
    dx = rng.normal(size=(40, 12)) * np.r_[[0.02] * 3, [0.01] * 3, [0.05] * 6]
    start = retract(prob, truth, dx, rng.normal(size=13) * 1e-3)
    calls = []
    cost0 = assemble(prob, start)[1]

    def costlier(p, s):
        system, cost = assemble(p, s)
        calls.append(s is start)
        return system, cost if s is start else cost0 + 1.0 + cost

    monkeypatch.setattr(engine_module, "assemble", costlier)
    est, sol, info = gauss_newton(prob, start, max_iter=10, tol=1e-10)
    assert est is start and not info.converged
    assert info.iterations == 0 and len(info.costs) == 1
    assert calls.count(False) == engine_module.MAX_HALVINGS  # the halved trials
    assert sol is not None and sol.cov.shape[0] == prob.t_knot.size  # at the start
