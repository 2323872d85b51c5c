"""Gauss-Newton on the manifold for the joint trajectory, stations and atmosphere.

State, factors, update and covariance: docs/joint.md#the-solver.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.stats import chi2

from rtsgt.geometry.so3 import exp_so3, hat, log_so3
from rtsgt.joint import gm as gmn
from rtsgt.joint.axes import AXES_HELD_SIGMA, AXES_SIGMA, axes_prior, body_rotation
from rtsgt.joint.clock import ClockModel
from rtsgt.joint.deviation import (
    deviation_chain,
    deviation_jacobian,
    n_coefficients,
    viewing_azimuth_body,
)
from rtsgt.joint.measurements import PolarMeasurements, predict, residual
from rtsgt.joint.noise import (
    PRIOR,
    NoiseFit,
    component_sums,
    measurement_cov,
    noise_basis,
    update_components,
)
from rtsgt.joint.prior import TRAJECTORY_DIM, prior_terms, wnoa_q_inv
from rtsgt.joint.prisms import TEST_ALPHA, free_prism, gauge_directions, prism_tests
from rtsgt.joint.qc import (
    MIN_REDUNDANCY,
    N_CLASSES,
    QC_FLOOR,
    VCE_GN_ITER,
    VCE_MAX_ITER,
    VCE_TOL,
    class_members,
    motion_classes,
    prior_components,
    qc_per_class,
    with_gaps,
)
from rtsgt.joint.relative import chain_gains, knot_cross_covariance
from rtsgt.joint.rocking import ROCKING_DIM, add_rocking_prior, rocking_moments
from rtsgt.joint.se3 import adjoint, curly, exp_se3, log_se3, so3_left_jacobian
from rtsgt.joint.settling import KIND_COLUMNS, SettleModel
from rtsgt.joint.sparse import (
    ArrowSolution,
    ArrowSystem,
    add_transitions,
    chunks,
    knot_rows,
    mix_solutions,
    solve_arrow,
)

#: Prior standard deviation (m, rad) given to a station direction its calibration fixes
#: exactly (a zero variance, e.g. the reference station).
FIXED_SIGMA = 1e-7
#: Gauss-Newton has converged when the predicted decrease of the cost is below this (chi^2
#: units: the squared Mahalanobis length of the step left, under the posterior's information;
#: the estimate is within 0.03 of its own sigma of the minimum, which further iterations would
#: only polish; docs/joint.md#the-solver).
DECREASE_TOL = 1e-3
#: Gauss-Newton has converged when a step changes the cost by less than this fraction of it
#: (the prior's Jacobian is first order in the interval's motion, so the predicted decrease
#: need not vanish at the minimum).
STALL_REL = 1e-9
#: A step whose predicted decrease of the cost is below this (chi^2 units: the state moves
#: by a tenth of its sigma in all) is taken whole even where the cost rises: near the
#: solution the rise is the first-order Jacobians' error (the prior's, the settling's), and
#: halving the step would only creep towards the same point.
WHOLE_STEP_DECREASE = 1e-2
#: Halvings of a step that raises the cost before the solve stops where it is (a step of
#: 1/2^8 that still raises it: Gauss-Newton's model no longer describes the cost there).
MAX_HALVINGS = 8
#: Of several prisms whose move explains the data, another's hypothesis stays beside the
#: chosen one's (:func:`carry_alternatives`) unless its final solve ends at a cost (plus
#: freed directions) higher by at least this (and its trial did not end below the chosen
#: one's: :func:`undecided`): the likelihood ratio of the two beyond its critical value at
#: the prisms' test rate (``chi2(1).ppf(1 - TEST_ALPHA)``, 10.8;
#: docs/joint.md#which-prism-moved).
UNDECIDED_COST = float(chi2.ppf(1.0 - TEST_ALPHA, 1))
#: Sigma (s) holding the mean of the stations' constant clock offsets at its prior's zero
#: while Gauss-Newton iterates. It is a time shift of the whole trajectory, which the
#: stations cannot see; only the prediction of each measurement from its own knot does (an
#: artefact whose pull grows with the run's length: a simulated hour went to -10 ms against
#: a prior of 0.8 ms). Its estimate is therefore the prior's; the covariances leave it free
#: to that prior (:func:`covariance_solve`, docs/joint.md#clock-offsets).
COMMON_SYNC_HOLD_S = 1e-6
#: Most Gauss-Newton iterations of a prism hypothesis's solve (:func:`snoop_prisms`,
#: :func:`carry_alternatives`): they run to convergence, their costs compared; a move along
#: the direction the data hardly see takes more than the final solve's 10 (13 on the field
#: preset, docs/joint.md#which-prism-moved).
HYPOTHESIS_MAX_ITER = 30
#: Gauss-Newton of a prism hypothesis's trial (:func:`snoop_prisms`) has converged when the
#: predicted decrease of the cost is below this (chi^2 units). The trials are scored by
#: their cost alone, compared at :data:`UNDECIDED_COST` (10.8): a cost within about this
#: of its minimum ranks them as one at :data:`DECREASE_TOL` does, in fewer iterations
#: (their final solves, whose state may become the estimate, still run to
#: :data:`DECREASE_TOL`; docs/joint.md#which-prism-moved).
TRIAL_DECREASE_TOL = 0.1


@dataclass(frozen=True)
class JointState:
    """Knot poses ``R`` (K, 3, 3), ``t`` (K, 3) (``T_world_body``), body velocities ``w``
    (K, 6); stations ``R_s`` (S, 3, 3), ``t_s`` (S, 3) (``T_world_station``); ``kappa_ppm``;
    ``clock`` (K, 2 C) the clocks' offsets, s, and rates at the knots
    (:class:`rtsgt.joint.clock.ClockModel`; None without clocks); ``p_body`` (P, 3) the
    prisms' body positions, m (None: the problem's survey, held); ``sync`` (N,) the stations'
    constant clock offsets against the robot's, s (None: not estimated); ``settle`` (K, 4 S)
    the stations' settling since their calibration and its rate at the knots
    (:class:`rtsgt.joint.settling.SettleModel`; None: not estimated); ``deviation`` (P, C)
    the prisms' deviation coefficients, m (:mod:`rtsgt.joint.deviation`; None: not
    estimated); ``gm`` (K, n) the Gauss-Markov
    noise's chains at the knots (:mod:`rtsgt.joint.gm`; None: not estimated); ``R_mb`` (3, 3)
    the motion prior's axes (:mod:`rtsgt.joint.axes`: the knots are then motion-frame poses,
    a prism at ``R_mb p_body``; None: the body frame's); ``rocking`` (K, 6) the vehicle's
    rocking at the knots (:mod:`rtsgt.joint.rocking`; None: not estimated)."""

    R: np.ndarray
    t: np.ndarray
    w: np.ndarray
    R_s: np.ndarray
    t_s: np.ndarray
    kappa_ppm: float
    clock: np.ndarray | None = None
    p_body: np.ndarray | None = None
    sync: np.ndarray | None = None
    settle: np.ndarray | None = None
    deviation: np.ndarray | None = None
    gm: np.ndarray | None = None
    R_mb: np.ndarray | None = None
    rocking: np.ndarray | None = None


@dataclass(frozen=True)
class JointProblem:
    """What is fixed during the solve: knot times ``t_knot`` (K,), each measurement's knot
    ``of_meas`` and offset ``tau`` (M,), the measurements, the prisms' body positions
    ``p_body`` (P, 3), the stations' prior means ``R_prior``, ``t_prior`` and information
    ``info_prior`` (S, 6, 6) of ``(dt, dtheta)``, the free stations ``free`` (F,) indices,
    ``qc`` (6,) or one per interval (K-1, 6), the clock states (None: no clocks) and the
    information ``prism_info`` (3P, 3P) of the survey ``p_body`` as the prior of the prisms'
    body positions (None: held at the survey) and the survey's covariance ``prism_cov``, and the prisms found moved ``prism_found``
    (index, test statistic, dof at detection; docs/joint.md#prism-positions), and the white
    noise's components where estimated (``noise``; ``meas.info`` follows them), the
    stations' constant clock offsets against the robot's (``sync_column`` (S,) each station's
    column, -1 none, with the prior variance ``sync_var`` s^2; docs/joint.md#clock-offsets),
    the stations' settling states (``settle``; None: none, docs/joint.md#settling-tripods),
    the harmonics of the prisms' deviation ``deviation_orders`` (empty: none) with the prior
    sigma ``deviation_sigma`` (P, C) m of each coefficient (docs/joint.md#prism-deviation),
    the Gauss-Markov noise's chains (``gm``; None: none, docs/joint.md#gauss-markov-noise;
    each knot's state is then its trajectory's, its chains', its clocks' and its settling's
    values: :attr:`knot_dim`), and the other
    prisms whose move explains the data as well as the one found's
    (``prism_alternatives``: index, score above the chosen's, weight; every other
    hypothesis solved at the end, those not carried with weight 0;
    docs/joint.md#which-prism-moved), and whether the motion prior's axes are estimated
    (``motion_axes``, with the prior sigma ``axes_sigma`` rad, docs/joint.md#the-motion-axes),
    and the vehicle's rocking (``rocking``: its chains, states of every knot after the
    settling's; None: none, docs/joint.md#the-vehicles-rocking; the knots' states the rocked
    pose's perturbation, the chains the process about the vehicle's ``pivot`` (3,) m in the
    knots' frame, None: their origin, docs/joint.md#the-rockings-pivot).
    Globals: the free stations' ``(dt, dtheta)``, ``kappa``, the prisms' positions (3P), the
    constant clock offsets, the prisms' deviation (P, C), the motion axes (3)."""

    t_knot: np.ndarray
    of_meas: np.ndarray
    tau: np.ndarray
    meas: PolarMeasurements
    p_body: np.ndarray
    R_prior: np.ndarray
    t_prior: np.ndarray
    info_prior: np.ndarray
    free: np.ndarray
    qc: np.ndarray
    clock: ClockModel | None = None
    prism_info: np.ndarray | None = None
    prism_cov: np.ndarray | None = None
    prism_found: tuple[tuple[int, float, int], ...] = ()
    noise: NoiseFit | None = None
    sync_column: np.ndarray | None = None
    sync_var: float = 0.0
    settle: SettleModel | None = None
    deviation_orders: tuple[int, ...] = ()
    deviation_sigma: np.ndarray | None = None
    gm: gmn.GaussMarkov | None = None
    prism_alternatives: tuple[tuple[int, float, float], ...] = ()
    motion_axes: bool = False
    axes_sigma: float = AXES_SIGMA
    max_gap_s: float = np.inf
    rocking: gmn.GaussMarkov | None = None
    pivot: np.ndarray | None = None

    @property
    def gaps(self) -> np.ndarray:
        """Which intervals between knots (K-1,) are longer than ``max_gap_s``: no station
        measured there; their motion prior is the loosest of the run's
        (:func:`rtsgt.joint.qc.with_gaps`), not a motion class's, and only those between
        moving ends count in their class's variance components
        (:func:`rtsgt.joint.qc.class_members`; docs/joint.md#gaps)."""
        return np.diff(self.t_knot) > self.max_gap_s

    @property
    def carried_alternatives(self) -> tuple[tuple[int, float, float], ...]:
        """The entries of ``prism_alternatives`` carried in the covariance (weight above 0;
        the others are listed with their score only, docs/joint.md#which-prism-moved)."""
        return tuple(a for a in self.prism_alternatives if a[2] > 0)

    def with_qc(self, qc: np.ndarray, trusted: np.ndarray | None = None,
                moving: np.ndarray | None = None) -> JointProblem:
        """The problem with ``Qc`` ``qc`` (K-1, 6) per interval, the gaps' the loosest of the
        moving intervals' (``moving`` (K-1,), None: all) that the data determine
        (``trusted`` (K-1, 6), None: all; :func:`rtsgt.joint.qc.with_gaps`)."""
        return replace(self, qc=with_gaps(qc, self.gaps, trusted, moving))

    @property
    def n_gm(self) -> int:
        """Gauss-Markov chains at each knot (0: none)."""
        return 0 if self.gm is None else self.gm.n

    @property
    def clock_col(self) -> int:
        """Column of the first clock state in a knot's (after the Gauss-Markov chains')."""
        return TRAJECTORY_DIM + self.n_gm

    @property
    def settle_col(self) -> int:
        """Column of the first settling state in a knot's (after the clocks')."""
        return self.clock_col + (0 if self.clock is None else self.clock.size)

    @property
    def rocking_col(self) -> int:
        """Column of the first rocking state in a knot's (after the settling's)."""
        return self.settle_col + (0 if self.settle is None else self.settle.size)

    @property
    def knot_dim(self) -> int:
        """A knot's state: its trajectory's, then its Gauss-Markov chains', its clocks', its
        settling's (docs/joint.md#slowly-varying-states) and the rocking's
        (docs/joint.md#the-vehicles-rocking)."""
        return self.rocking_col + (0 if self.rocking is None else ROCKING_DIM)

    @property
    def kappa_col(self) -> int:
        """Column of ``kappa`` among the globals (after the free stations')."""
        return 6 * self.free.size

    @property
    def n_prism(self) -> int:
        """Prism position globals (3 per prism, or 0 when held)."""
        return 0 if self.prism_info is None else self.p_body.size

    @property
    def n_sync(self) -> int:
        """Constant clock offsets estimated (0: none)."""
        return 0 if self.sync_column is None else int(self.sync_column.max(initial=-1)) + 1

    @property
    def sync_col(self) -> int:
        """Column of the first constant clock offset among the globals."""
        return self.kappa_col + 1 + self.n_prism

    @property
    def n_deviation(self) -> int:
        """The prisms' deviation coefficients estimated (0: none)."""
        if not self.deviation_orders:
            return 0
        return self.p_body.shape[0] * n_coefficients(self.deviation_orders)

    @property
    def deviation_col(self) -> int:
        """Column of the first deviation coefficient among the globals."""
        return self.sync_col + self.n_sync

    @property
    def axes_col(self) -> int:
        """Column of the motion axes' first (after the deviation's)."""
        return self.deviation_col + self.n_deviation

    @property
    def n_axes(self) -> int:
        """The motion axes' globals (3, or 0 where they are the body frame's)."""
        return 3 if self.motion_axes else 0

    @property
    def n_globals(self) -> int:
        """The globals: the free stations', ``kappa``, the prisms', the constant clock
        offsets, the prisms' deviation and the motion axes."""
        return self.axes_col + self.n_axes


def station_prior_info(cov: np.ndarray) -> np.ndarray:
    """Information (6, 6) of a station's calibration covariance, directions of zero variance
    held at :data:`FIXED_SIGMA`."""
    return np.linalg.inv(cov + FIXED_SIGMA**2 * np.eye(6))


def measurement_terms(prob: JointProblem, s: JointState):
    """Residuals (M, 3), Jacobians wrt the knots (M, 3, d) (:attr:`JointProblem.knot_dim`: the
    trajectory's 12, the measurement's station's Gauss-Markov chains, clock and settling,
    the rocking: the pose's columns)
    and wrt the globals (M, 3, G). The settling enters to first order (its sizes:
    millimetres and arc seconds); the prisms' deviation
    (``prob.deviation_orders``) at the knot's pose, its slope in the viewing azimuth in the
    knots', the stations' and the prisms' columns (docs/joint.md#prism-deviation)."""
    m = prob.meas
    k = prob.of_meas
    ck = prob.clock
    tau = prob.tau if ck is None else prob.tau - ck.offsets(s.clock, k, prob.tau)
    sc = None if prob.n_sync == 0 else prob.sync_column[m.station]
    if sc is not None:  # recorded at t, measured at t - e: the offset from its knot shifts
        tau = tau - np.where(sc >= 0, s.sync[np.maximum(sc, 0)], 0.0)
    pb = prob.p_body if s.p_body is None else s.p_body
    R_mb = np.eye(3) if s.R_mb is None else s.R_mb
    h, Hk, Hs, Hkap, Htau, Bp = predict(s.R[k], s.t[k], s.w[k], tau, pb[m.prism] @ R_mb.T,
                                        s.R_s[m.station], s.t_s[m.station], s.kappa_ppm)
    r = residual(m.y, h)
    PR = Hk[:, :, :3]  # d h / d (a point in the knots' frame), without the deviation's slope
    Hdev = da_p = None
    if prob.n_deviation:  # the deviation at the knot's pose, with its slope in the azimuth
        alpha, da_xi, da_st, da_p = viewing_azimuth_body(s.R[k] @ R_mb, s.t[k], pb[m.prism],
                                                          s.t_s[m.station])
        Hdev, dH = deviation_jacobian(alpha, h[:, 1], h[:, 2], prob.deviation_orders)
        coef = s.deviation[m.prism]
        dev = np.einsum("mic,mc->mi", Hdev, coef)
        r = r - dev
        L = deviation_chain(dev, h[:, 1], h[:, 2])
        Hk, Hs = L @ Hk, L @ Hs
        Hkap, Htau = (np.einsum("mij,mj->mi", L, x) for x in (Hkap, Htau))
        PR = Hk[:, :, :3].copy()
        slope = np.einsum("mic,mc->mi", dH, coef)  # d deviation / d alpha
        Hk[:, :, :6] += slope[:, :, None] * (da_xi @ body_rotation(R_mb))[:, None, :]
        Hs[:, :, :3] += slope[:, :, None] * da_st[:, None, :]
    if prob.rocking is not None:  # the rocked pose: d h / d (the knot's pose) moves it
        Hpose = Hk[:, :, :6].copy()
        r = r - np.einsum("mij,mj->mi", Hpose, s.rocking[k])
    if prob.gm is not None:  # the station's chains add to its measurements
        r = r - gmn.chain_values(s.gm, k, m.station)
        Hk = np.concatenate([Hk, gmn.chain_jacobian(m.station, prob.n_gm)], axis=2)
    if ck is not None:  # recorded at t, measured at t - e
        Hk = np.concatenate([Hk, -Htau[:, :, None] * ck.jacobian(prob.tau)[:, None, :]], 2)
    st = prob.settle
    if st is not None:
        Hkind = Hs[:, :, KIND_COLUMNS]  # (M, 3, 2)
        r = r - np.einsum("mik,mk->mi", Hkind, st.at(s.settle, k, m.station, prob.tau))
        Hk = np.concatenate([Hk, Hkind @ st.jacobian(m.station, prob.tau)], axis=2)
    if prob.rocking is not None:
        Hk = np.concatenate([Hk, Hpose], axis=2)
    Hg = np.zeros(r.shape + (prob.n_globals,))
    col = np.full(len(s.R_s), -1)
    col[prob.free] = np.arange(prob.free.size)
    c = col[m.station]
    rows = np.nonzero(c >= 0)[0]
    for j in range(6):  # six columns of each free station
        Hg[rows, :, 6 * c[rows] + j] = Hs[rows, :, j]
    Hg[:, :, prob.kappa_col] = Hkap
    if prob.n_prism or prob.n_axes:  # d h / d (the prism in the knots' frame, R_mb p_body)
        Hpm = PR @ Bp
    if prob.n_prism:  # (and the deviation's slope)
        Hp = Hpm @ R_mb
        if da_p is not None:
            Hp = Hp + slope[:, :, None] * da_p[:, None, :]
        cols = prob.kappa_col + 1 + 3 * m.prism[:, None] + np.arange(3)
        np.put_along_axis(Hg, np.broadcast_to(cols[:, None, :], Hp.shape), Hp, axis=2)
    if prob.n_axes:  # R_mb exp(a^) p = R_mb p - R_mb p^ a; the body pose R R_mb exp(a^)
        Ha = -Hpm @ (R_mb @ hat(pb[m.prism]))
        if da_p is not None:
            Ha = Ha + slope[:, :, None] * da_xi[:, None, 3:]
        Hg[:, :, prob.axes_col:prob.axes_col + 3] = Ha
    if sc is not None:
        rows = np.nonzero(sc >= 0)[0]
        Hg[rows, :, prob.sync_col + sc[rows]] = -Htau[rows]
    if Hdev is not None:
        n_c = Hdev.shape[2]
        cols = prob.deviation_col + n_c * m.prism[:, None] + np.arange(n_c)
        np.put_along_axis(Hg, np.broadcast_to(cols[:, None, :], Hdev.shape), Hdev, axis=2)
    return r, Hk, Hg


def measurement_global_factor(prob: JointProblem, sol, terms) -> np.ndarray:
    """``Z = Hk L_k + Hg chol_g`` (M, 3, G): each measurement's fitted value per unit
    whitened global error (knots' share through the globals and its own global columns;
    :class:`rtsgt.joint.sparse.ArrowSolution`'s split), from the Jacobians ``terms``
    (``Hk, Hg``) of :func:`measurement_terms`."""
    Hk, Hg = terms
    Z = np.empty(Hk.shape[:2] + (sol.chol_g.shape[1],))
    for sl in chunks(Hk.shape[0]):  # the knots' factor, a few thousand rows at a time
        Z[sl] = Hk[sl] @ sol.factor[prob.of_meas[sl]] + Hg[sl] @ sol.chol_g
    return Z


def measurement_hsh(prob: JointProblem, s: JointState, sol, terms=None) -> np.ndarray:
    """Covariance (M, 3, 3) of the measurements' fitted values, ``H Sigma H^T`` with the
    knot's marginal and its cross covariance with the globals: ``Hk V_k Hk^T + Z Z^T``
    (:func:`measurement_global_factor`); ``terms`` the Jacobians of :func:`measurement_terms`
    at ``s`` where already computed."""
    terms = measurement_terms(prob, s)[1:] if terms is None else terms
    Hk, k = terms[0], prob.of_meas
    Z = measurement_global_factor(prob, sol, terms)
    out = Z @ np.swapaxes(Z, 1, 2)
    for sl in chunks(k.size):
        out[sl] += Hk[sl] @ sol.cov_var[k[sl]] @ np.swapaxes(Hk[sl], 1, 2)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def _station_terms(prob: JointProblem, s: JointState):
    """Residuals (F, 6) and Jacobians (F, 6, 6) of the free stations' priors."""
    f = prob.free
    phi = log_so3(s.R_s[f] @ np.swapaxes(prob.R_prior[f], 1, 2))
    e = np.concatenate([s.t_s[f] - prob.t_prior[f], phi], axis=1)
    J = np.zeros((f.size, 6, 6))
    J[:, :3, :3] = np.eye(3)
    J[:, 3:, 3:] = so3_left_jacobian(phi, inverse=True)
    return e, J


def assemble(prob: JointProblem, s: JointState) -> tuple[ArrowSystem, float]:
    """The normal equations at ``s`` and the cost (sum of squared whitened errors)."""
    K = prob.t_knot.size
    d, n = prob.knot_dim, TRAJECTORY_DIM
    D = np.zeros((K, d, d))
    U = np.zeros((K - 1, d, d))
    a = np.zeros((K, d))
    dt = np.diff(prob.t_knot)
    e, E, F = prior_terms(s.R, s.t, s.w, dt)
    cost = add_transitions(D, U, a, slice(0, n), e, E, F, wnoa_q_inv(dt, prob.qc))
    if prob.gm is not None:
        cost += gmn.add_prior(D, U, a, s.gm, dt, prob.gm, n)
    if prob.clock is not None:
        cost += prob.clock.prior.add_prior(D, U, a, s.clock, dt, prob.clock_col)
    if prob.settle is not None:
        cost += prob.settle.prior.add_prior(D, U, a, s.settle, dt, prob.settle_col)
    if prob.rocking is not None:
        cost += add_rocking_prior(D, U, a, s.rocking, dt, prob.rocking, prob.rocking_col,
                                  prob.pivot)
    r, Hk, Hg = measurement_terms(prob, s)
    info = prob.meas.info
    # each knot's rows (K, 3 R, .) of H, W H, W Hg and W r, gathered at once
    rows = knot_rows(prob.of_meas, K, np.concatenate(
        [Hk, info @ Hk, info @ Hg, (info @ r[:, :, None])], axis=2))
    Ht = np.swapaxes(rows[:, :, :d], 1, 2)  # (K, d, 3 R)
    D += Ht @ rows[:, :, d:2 * d]
    B = Ht @ rows[:, :, 2 * d:-1]
    a += (Ht @ rows[:, :, -1:])[:, :, 0]
    GtW = np.swapaxes(Hg, 1, 2) @ info
    C = np.tensordot(GtW, Hg, axes=([0, 2], [0, 1]))
    c = np.einsum("mgi,mi->g", GtW, r)
    cost += float(np.einsum("mi,mij,mj->", r, info, r))
    es, Js = _station_terms(prob, s)
    Wp = prob.info_prior[prob.free]
    JtW = np.swapaxes(Js, 1, 2) @ Wp
    for i in range(prob.free.size):  # a handful of stations
        sl = slice(6 * i, 6 * i + 6)
        C[sl, sl] += JtW[i] @ Js[i]
        c[sl] -= JtW[i] @ es[i]
    cost += float(np.einsum("fi,fij,fj->", es, Wp, es))
    sk = prob.meas.kappa_sigma_ppm
    kc = prob.kappa_col
    C[kc, kc] += 1.0 / sk**2 if sk > 0 else 1.0 / FIXED_SIGMA**2
    c[kc] -= s.kappa_ppm / sk**2 if sk > 0 else 0.0
    cost += (s.kappa_ppm / sk) ** 2 if sk > 0 else 0.0
    if prob.n_prism:  # the survey as the prisms' prior
        ep = (s.p_body - prob.p_body).ravel()
        sl = slice(kc + 1, kc + 1 + prob.n_prism)
        C[sl, sl] += prob.prism_info
        c[sl] -= prob.prism_info @ ep
        cost += float(ep @ prob.prism_info @ ep)
    if prob.n_sync:  # the clock error's prior: the noise model's time_sync second moment,
        sl, hold = _common_sync_hold(prob)  # its mean held at zero (COMMON_SYNC_HOLD_S)
        W = np.eye(prob.n_sync) / prob.sync_var + hold
        C[sl, sl] += W
        c[sl] -= W @ s.sync
        cost += float(s.sync @ W @ s.sync)
    if prob.n_deviation:  # zero mean, deviation_sigma each
        sl = slice(prob.deviation_col, prob.deviation_col + prob.n_deviation)
        w = 1.0 / prob.deviation_sigma.ravel() ** 2
        C[sl, sl] += np.diag(w)
        c[sl] -= w * s.deviation.ravel()
        cost += float(w @ s.deviation.ravel() ** 2)
    if prob.n_axes:  # the motion axes' prior about the body frame's
        sl = slice(prob.axes_col, prob.axes_col + 3)
        Wa, ga, ca = axes_prior(s.R_mb, prob.axes_sigma)
        C[sl, sl] += Wa
        c[sl] -= ga
        cost += ca
    return ArrowSystem(D, U, B, C, a, c), cost


def _common_sync_hold(prob: JointProblem) -> tuple[slice, np.ndarray]:
    """The constant clock offsets' columns and the information (N, N) holding their mean at
    zero with :data:`COMMON_SYNC_HOLD_S`."""
    n = prob.n_sync
    return (slice(prob.sync_col, prob.sync_col + n),
            np.full((n, n), 1.0 / (n * COMMON_SYNC_HOLD_S) ** 2))


def covariance_solve(prob: JointProblem, system: ArrowSystem) -> ArrowSolution:
    """:func:`rtsgt.joint.sparse.solve_arrow` with covariances of ``system`` (assembled at
    the solution by :func:`assemble`), the constant clock offsets' mean released to its
    prior (modifies ``system``)."""
    if prob.n_sync:
        sl, hold = _common_sync_hold(prob)
        system.C[sl, sl] -= hold
    return solve_arrow(system, want_cov=True, overwrite=True)


def _frame_change(dR: np.ndarray, dp: np.ndarray, d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The second and higher orders (K, 6) of body velocities ``w`` (K, 6) under the knots'
    right perturbations ``d`` (K, 6) (``exp(d^) = (dR, dp)``) taken as a change of frame,
    ``Ad(exp(-d^)) w - w + d^curly w``: added to the velocities' steps, a rotation of every
    knot's frame (the motion axes' step) turns their velocities exactly, and the motion
    prior's stiffest axes see no error of second order (docs/joint.md#the-knots-origin)."""
    dRt = np.swapaxes(dR, 1, 2)
    Ad = adjoint(dRt, -np.einsum("kij,kj->ki", dRt, dp))
    return np.einsum("kij,kj->ki", Ad - np.eye(6) + curly(d), w)


def retract(prob: JointProblem, s: JointState, x: np.ndarray, g: np.ndarray) -> JointState:
    """``T_k exp(d_k^)``, ``w_k + dw_k`` (plus the second orders of the change of frame,
    :func:`_frame_change`), ``t_s + dt``, ``exp(dtheta) R_s``, ``kappa + dk``,
    the prisms, the constant clock offsets, the deviation, ``R_mb exp(a^)``, the clock and
    the Gauss-Markov chains, the clocks and the settling plus their steps."""
    dR, dp = exp_se3(x[:, :6])
    R = s.R @ dR
    t = s.t + np.einsum("kij,kj->ki", s.R, dp)
    R_s, t_s = s.R_s.copy(), s.t_s.copy()
    kc = prob.kappa_col
    gs = g[:kc].reshape(-1, 6)
    t_s[prob.free] += gs[:, :3]
    R_s[prob.free] = exp_so3(gs[:, 3:]) @ R_s[prob.free]
    pb = s.p_body
    if prob.n_prism:
        pb = s.p_body + g[kc + 1:kc + 1 + prob.n_prism].reshape(s.p_body.shape)
    sync = s.sync
    if prob.n_sync:
        sync = s.sync + g[prob.sync_col:prob.sync_col + prob.n_sync]
    dev = s.deviation
    if prob.n_deviation:
        dc = prob.deviation_col
        dev = s.deviation + g[dc:dc + prob.n_deviation].reshape(s.deviation.shape)
    R_mb = s.R_mb
    if prob.n_axes:
        R_mb = s.R_mb @ exp_so3(g[prob.axes_col:prob.axes_col + 3])
    n, cc, sc = TRAJECTORY_DIM, prob.clock_col, prob.settle_col
    chains = None if prob.gm is None else s.gm + x[:, n:cc]
    clock = None if s.clock is None else s.clock + x[:, cc:sc]
    settle = None if s.settle is None else s.settle + x[:, sc:prob.rocking_col]
    rock = None if s.rocking is None else s.rocking + x[:, prob.rocking_col:prob.knot_dim]
    w = s.w + x[:, 6:n] + _frame_change(dR, dp, x[:, :6], s.w)
    return JointState(R, t, w, R_s, t_s, s.kappa_ppm + float(g[kc]), clock, pb,
                      sync, settle, dev, chains, R_mb, rock)


def difference(prob: JointProblem, a: JointState, b: JointState
               ) -> tuple[np.ndarray, np.ndarray]:
    """The steps ``x`` (K, :attr:`JointProblem.knot_dim`), ``g`` (G,) from ``a`` to ``b``:
    the inverse of :func:`retract` (``retract(prob, a, x, g)`` is ``b``)."""
    x = np.zeros((a.R.shape[0], prob.knot_dim))
    dR, dp = np.swapaxes(a.R, 1, 2) @ b.R, np.einsum("kji,kj->ki", a.R, b.t - a.t)
    x[:, :6] = log_se3(dR, dp)
    n = TRAJECTORY_DIM
    x[:, 6:n] = b.w - a.w - _frame_change(dR, dp, x[:, :6], a.w)
    if prob.gm is not None:
        x[:, n:prob.clock_col] = b.gm - a.gm
    if prob.clock is not None:
        x[:, prob.clock_col:prob.settle_col] = b.clock - a.clock
    if prob.settle is not None:
        x[:, prob.settle_col:prob.rocking_col] = b.settle - a.settle
    if prob.rocking is not None:
        x[:, prob.rocking_col:] = b.rocking - a.rocking
    g = np.zeros(prob.n_globals)
    kc, f = prob.kappa_col, prob.free
    g[:kc] = np.concatenate([b.t_s[f] - a.t_s[f],
                             log_so3(b.R_s[f] @ np.swapaxes(a.R_s[f], 1, 2))], axis=1).ravel()
    g[kc] = b.kappa_ppm - a.kappa_ppm
    if prob.n_prism:
        g[kc + 1:kc + 1 + prob.n_prism] = (b.p_body - a.p_body).ravel()
    if prob.n_sync:
        g[prob.sync_col:prob.sync_col + prob.n_sync] = b.sync - a.sync
    if prob.n_deviation:
        dc = prob.deviation_col
        g[dc:dc + prob.n_deviation] = (b.deviation - a.deviation).ravel()
    if prob.n_axes:
        g[prob.axes_col:prob.axes_col + 3] = log_so3(a.R_mb.T @ b.R_mb)
    return x, g


@dataclass(frozen=True)
class SolveInfo:
    """``iterations``, ``converged``, ``costs`` (one per iteration, the first at the start)."""

    iterations: int
    converged: bool
    costs: tuple[float, ...]


def gauss_newton(prob: JointProblem, s: JointState, max_iter: int = 10,
                 tol: float = DECREASE_TOL, want_cov: bool = True):
    """Gauss-Newton from ``s`` until the predicted decrease of the cost is below ``tol`` or a
    step changes the cost by less than :data:`STALL_REL` of it (a step that raises the cost is
    halved, up to :data:`MAX_HALVINGS` times, unless its predicted decrease is below
    :data:`WHOLE_STEP_DECREASE`; where the last halving still raises it, the solve stops at
    the state it has, converged where the predicted decrease was below ``tol``). Returns the
    state, the
    :class:`rtsgt.joint.sparse.ArrowSolution` at it (with its covariances; None without
    ``want_cov``: a trial scored by its cost alone) and a :class:`SolveInfo`."""
    system, cost = assemble(prob, s)
    costs = [cost]
    converged = False
    for _ in range(max_iter):
        sol = solve_arrow(system, overwrite=True)  # (its a and c read below)
        x, g = sol.x, sol.g
        decrease = float(np.sum(x * system.a) + g @ system.c)
        del system, sol  # the trial's system replaces it: one (K, d, G) B at a time
        step = 1.0
        for _ in range(MAX_HALVINGS):
            trial = retract(prob, s, step * x, step * g)
            trial_system, trial_cost = assemble(prob, trial)
            if trial_cost <= cost + 1e-9 * abs(cost) or decrease < WHOLE_STEP_DECREASE:
                break
            step *= 0.5
        else:  # no step along Gauss-Newton's direction lowers the cost: its model's limit
            del trial, trial_system  # (one (K, d, G) B at a time, as above)
            system = assemble(prob, s)[0] if want_cov else None  # (the state kept)
            converged = decrease < tol
            break
        s, system, cost = trial, trial_system, trial_cost
        costs.append(cost)
        if decrease < tol or abs(costs[-2] - cost) <= STALL_REL * abs(cost):
            converged = True
            break
    info = SolveInfo(len(costs) - 1, converged, tuple(costs))
    return s, covariance_solve(prob, system) if want_cov else None, info


@dataclass(frozen=True)
class QcFit:
    """``table`` (N_CLASSES, 6) the ``Qc`` of each motion class (m^2/s^3, rad^2/s^3),
    ``classes`` (K-1,) each interval's, ``redundancy`` (N_CLASSES, 6) each group's,
    ``iterations`` of the variance components (0: ``Qc`` given, not estimated);
    ``changes`` the last update's largest relative change of each part of their loop
    (``("qc" | "white" | "chains" | "rocking", change)``: ``Qc``, the white noise, its chains,
    the rocking; a log change where the part is in logs), whose largest below
    :data:`rtsgt.joint.qc.VCE_TOL` means the loop converged rather than stopping at its
    last update (docs/joint.md#the-variance-components-loop)."""

    table: np.ndarray
    classes: np.ndarray
    redundancy: np.ndarray
    iterations: int
    changes: tuple[tuple[str, float], ...] = ()

    @property
    def change(self) -> float:
        """The last update's largest change of any part (0: none made)."""
        return max((v for _, v in self.changes), default=0.0)

    @property
    def converged(self) -> bool:
        """Whether the loop's last update changed every part by less than ``VCE_TOL``."""
        return self.change < VCE_TOL


def solve_with_qc(prob: JointProblem, s: JointState, estimate: bool = True,
                  max_iter: int = 10, tol: float = DECREASE_TOL, estimate_noise: bool = False,
                  rng: np.random.Generator | None = None, max_updates: int | None = None):
    """Gauss-Newton with the prior's ``Qc`` per motion class by iterated variance components
    (docs/joint.md#qc-from-the-data), starting from ``prob.qc`` (6,) for every class, with
    (``estimate_noise``) the white noise's components (docs/joint.md#noise-identification;
    the problem's ``noise``) and the Gauss-Markov chains' (where the problem has them;
    ``rng`` their draws, docs/joint.md#gauss-markov-noise) and the prisms' tests (where they
    are parameters; with the noise estimated, from its first update on) in the same loop;
    each iteration re-solves from the last state, at most ``max_updates`` of them (None:
    :data:`VCE_MAX_ITER`, read at the call; the :class:`QcFit` says whether the loop
    converged first); other prisms' moves that explain
    the data as well as the one found are carried at the end (:func:`carry_alternatives`).
    The motion axes (where estimated) are held at the body frame's through the loop, so that
    the prisms' tests have the motion prior's frame, and freed with ``prob.axes_sigma`` for a
    last solve (docs/joint.md#the-motion-axes). Returns the problem with the final ``qc``
    per interval, the state, the
    :class:`rtsgt.joint.sparse.ArrowSolution`, the last :class:`SolveInfo` and a
    :class:`QcFit`."""
    n = prob.t_knot.size - 1
    max_updates = VCE_MAX_ITER if max_updates is None else max_updates
    trial_tol = max(tol, TRIAL_DECREASE_TOL)  # the prisms' trials: scored, solved again
    qc0 = np.asarray(prob.qc, dtype=float)
    axes_sigma = prob.axes_sigma  # held at the body frame's until the last solve
    prob = replace(prob, axes_sigma=AXES_HELD_SIGMA if prob.n_axes else axes_sigma
                   ).with_qc(np.broadcast_to(qc0, (n, 6)))
    s, sol, info = gauss_newton(prob, s, max_iter, tol)
    classes = motion_classes(prob.t_knot, s.R, s.w, prob.p_body)
    table = np.tile(qc0, (N_CLASSES, 1))
    red_g = np.zeros_like(table)
    own = None
    it = 0
    freed = False
    alternatives = ()
    changes = {}
    snooped = not estimate_noise  # else after the noise's first update: weighted by the
    if snooped:  # datasheet, another prism can explain a move better (docs/joint.md)
        prob, freed, alternatives = snoop_prisms(prob, s, sol, trial_tol)
    while (estimate or estimate_noise or freed) and it < max_updates:
        it += 1
        changes = {}
        if estimate:
            prob, table, own, red_g, changes["qc"] = _qc_step(prob, s, sol, classes, table, own)
        if estimate_noise:
            prob, changes["white"] = noise_step(prob, s, sol, it)
        if estimate_noise and prob.gm is not None:
            prob, changes["chains"] = gm_step(prob, s, sol, rng)
        if estimate_noise and prob.rocking is not None:
            prob, changes["rocking"] = rocking_step(prob, s, sol, rng)
        change = max(changes.values(), default=0.0)
        last = (change < VCE_TOL and not freed and snooped) or it == max_updates
        if last and estimate_noise and prob.gm is not None:  # the last solve without them
            prob = replace(prob, gm=gmn.without_undetermined(prob.gm))
        full = last or not (estimate or estimate_noise)  # a freed prism alone: to the end
        sol = None  # (its covariances' memory for the next solve's)
        s, sol, info = gauss_newton(prob, s, max_iter if full else VCE_GN_ITER, tol)
        if last:
            break
        prob, freed, alts = snoop_prisms(prob, s, sol, trial_tol)
        alternatives = alts if freed else alternatives
        snooped = True
    if prob.n_axes:  # the axes free: the covariance does not rest on the motion prior's tilt
        prob = replace(prob, axes_sigma=axes_sigma)
        sol = None
        s, sol, info = gauss_newton(prob, s, max_iter, tol)
    if alternatives:
        prob, s, sol, info = carry_alternatives(prob, s, sol, info, alternatives, tol)
    return prob, s, sol, info, QcFit(table, classes, red_g, it if estimate else 0,
                                     tuple((k, float(v)) for k, v in changes.items()))


def _qc_step(prob: JointProblem, s: JointState, sol, classes, table, own):
    """One variance-component update of ``Qc`` per class: the problem with it, the table,
    the groups with their own, their redundancy and the largest relative change."""
    dt = np.diff(prob.t_knot)
    e, E, F = prior_terms(s.R, s.t, s.w, dt)
    n = TRAJECTORY_DIM
    quad, red = prior_components(e, E, F, dt, prob.qc, sol.cov[:, :n, :n],
                                 sol.cov_next[:, :n, :n])
    on = class_members(classes, prob.gaps)
    new, own = qc_per_class(quad[on], red[on], classes[on], own)
    red_g = np.zeros_like(table)
    np.add.at(red_g, classes[on], red[on])
    # a group the data no longer inform (sinking to 0, its redundancy gone) may go on
    moving = own & (red_g >= MIN_REDUNDANCY) & (new > 1.01 * QC_FLOOR)
    change = float(np.max(np.abs(np.log(new / table))[moving], initial=0.0))
    return prob.with_qc(new[classes], own[classes], classes > 0), new, own, red_g, change


def noise_step(prob: JointProblem, s: JointState, sol, iteration: int = 1):
    """One REML update of the white noise's components (:mod:`rtsgt.joint.noise`) from the
    residuals at ``s``: the problem with the new weights and its ``noise``
    (:class:`rtsgt.joint.noise.NoiseFit`), and the largest change of a determined channel's
    sigma at its station's median range (relative)."""
    m = prob.meas
    S = prob.R_prior.shape[0]
    Q = noise_basis(m.var_white, m.y[:, 2])
    e, Hk, Hg = measurement_terms(prob, s)
    HSH = measurement_hsh(prob, s, sol, (Hk, Hg))
    old = prob.noise
    theta = np.tile(PRIOR, (S, 3, 1)) if old is None else old.theta
    cov = measurement_cov(m.corr, Q, m.station, theta)
    q, r, F = component_sums(e, m.info, HSH, Q, cov * (1.0 - np.eye(3)), m.station, S)
    new, sigma, det, share, cov_th, pooled = update_components(
        theta, q, r, F, *((None, None) if old is None else (old.determined, old.pooled)))
    med = np.stack([np.median(Q[m.station == i], axis=0) if np.any(m.station == i)
                    else np.ones((3, 2)) for i in range(S)])  # a handful of stations
    v_old = np.einsum("sck,sck->sc", theta, med)
    v_new = np.einsum("sck,sck->sc", new, med)
    changed = 0.5 * np.abs(np.log(np.maximum(v_new, 1e-300) / np.maximum(v_old, 1e-300)))
    change = float(np.max(changed[det.any(axis=2)], initial=0.0))
    info = np.linalg.inv(measurement_cov(m.corr, Q, m.station, new))
    fit = NoiseFit(new, sigma, det, share, iteration, cov=cov_th, median_basis=med,
                   pooled=pooled)
    return replace(prob, meas=replace(m, info=info), noise=fit), change


def gm_step(prob: JointProblem, s: JointState, sol,
            rng: np.random.Generator | None = None) -> tuple[JointProblem, float]:
    """One update of the Gauss-Markov chains' sigma and tau (:func:`rtsgt.joint.gm.update`,
    ``rng`` its draws) from the posterior at ``s``: the problem with them and the largest
    change of a determined one's log."""
    old = prob.gm
    gains = chain_gains(sol)
    moments = []
    for i in range(old.sigma.shape[0]):  # a handful of stations
        k = np.unique(prob.of_meas[prob.meas.station == i])
        if k.size < 2:
            moments.append(None)
            continue
        j = TRAJECTORY_DIM + 3 * i + np.arange(3)
        cross = knot_cross_covariance(sol, gains, k[:-1], k[1:])[:, j, j]
        moments.append((s.gm[k][:, j - TRAJECTORY_DIM], sol.cov[k[:, None], j, j], cross,
                        np.diff(prob.t_knot[k])))
    new = gmn.update(old, moments, old.determined if old.iterations else None, rng,
                     follow=True)
    return replace(prob, gm=new), gmn.log_change(old, new)


def rocking_step(prob: JointProblem, s: JointState, sol,
                 rng: np.random.Generator | None = None) -> tuple[JointProblem, float]:
    """One update of the rocking's chains' sigma and tau (:func:`rtsgt.joint.gm.update`,
    ``rng`` its draws) from the posterior at ``s`` at every knot, the process's about the
    vehicle's pivot (:func:`rtsgt.joint.rocking.rocking_moments`): the problem with them and
    the largest change of a determined one's log (docs/joint.md#the-vehicles-rocking)."""
    old = prob.rocking
    j = slice(prob.rocking_col, prob.rocking_col + ROCKING_DIM)
    # consecutive knots: Cov(x_k, x_k+1) is the solution's own block, no chain to walk
    moments = rocking_moments(s.rocking, sol.cov[:, j, j], sol.cov_next[:, j, j],
                              np.diff(prob.t_knot), prob.pivot)
    new = gmn.update(old, moments, old.determined if old.iterations else None, rng)
    return replace(prob, rocking=new), gmn.log_change(old, new)


def snoop_prisms(prob: JointProblem, s: JointState, sol, tol: float = TRIAL_DECREASE_TOL
                 ) -> tuple[JointProblem, bool, tuple[tuple[JointProblem, float], ...]]:
    """Test each trusted prism against its survey (:func:`rtsgt.joint.prisms.prism_tests`);
    where one is beyond its critical value (and at least two would stay trusted) a move is
    detected, and one prism has its survey freed where the data determine its move: of the
    trusted prisms whose move the data determine (its test's own verdict aside: most of a
    move can lie where the data hardly see it), the one whose Gauss-Newton solve with it
    freed (from ``s``, to convergence: ``tol``, :data:`HYPOTHESIS_MAX_ITER`) ends at the
    lowest cost plus freed directions (the tests rank to first order only: two prisms' moves
    can explain the data alike, docs/joint.md#which-prism-moved). Returns the problem,
    whether a prism was freed and each other candidate's hypothesis, ``(problem, above)``:
    the problem with it freed instead and its trial's score above the chosen one's (its
    alternatives, solved again with the final noise by :func:`carry_alternatives`: the
    trials' weights are an early update's, and the order can turn)."""
    if prob.prism_info is None:
        return prob, False, ()
    sl = slice(prob.kappa_col + 1, prob.kappa_col + 1 + prob.n_prism)
    found = [f[0] for f in prob.prism_found]
    trusted = np.ones(prob.p_body.shape[0], bool)
    trusted[found] = False
    tests = prism_tests(prob.p_body, prob.prism_info, s.p_body, sol.cov_g[sl, sl], trusted)
    open_ = tests.dof > 0
    open_[found] = False
    ratio = np.where(open_, tests.stat / tests.critical(), 0.0)
    if not np.any(ratio > 1.0) or len(found) + 3 > prob.p_body.shape[0]:
        return prob, False, ()
    candidates = [int(j) for j in np.argsort(-ratio) if open_[j]]
    freed = [_freed(prob, tests, found, j) for j in candidates]
    if len(freed) == 1:
        return freed[0], True, ()
    score = np.array([_hypothesis_score(p, gauss_newton(p, s, HYPOTHESIS_MAX_ITER, tol,
                                                        want_cov=False)[2])
                      for p in freed])  # a handful of prisms
    best = int(np.argmin(score))
    return freed[best], True, tuple((p, float(score[i] - score[best]))
                                    for i, p in enumerate(freed) if i != best)


def carry_alternatives(prob: JointProblem, s: JointState, sol, info: SolveInfo,
                       alternatives: tuple[tuple[JointProblem, float], ...],
                       tol: float = DECREASE_TOL):
    """The solve ``prob``, ``s``, ``sol``, ``info`` with the hypotheses of other prisms'
    moves carried (docs/joint.md#which-prism-moved): each of ``alternatives`` (``(problem,
    above)``: the problem with another prism freed instead of the last one found and its
    trial's score above the found one's, :func:`snoop_prisms`) solved with ``prob``'s final
    noise and ``Qc`` from ``s`` (to convergence, as the trials); of them all the lowest
    cost plus freed directions is the estimate (the trials' noise weights were an earlier
    update's: the order can turn), and the others stay unless both scores decide against
    them (:func:`undecided`), with equal weights ``w``: the solution is the mixture of
    theirs about the estimate (:func:`rtsgt.joint.sparse.mix_solutions`: each one's
    covariances, solved at its own state, and its state's difference from the estimate's,
    :func:`difference`). Returns the problem (its ``prism_alternatives``), state, solution
    and :class:`SolveInfo` of the estimate."""
    runs = [(prob, s, sol, info)]
    for alt, _ in alternatives:  # a handful of prisms, scored by their cost alone
        p = replace(prob, prism_info=alt.prism_info, prism_found=alt.prism_found)
        runs.append((p, *gauss_newton(p, s, HYPOTHESIS_MAX_ITER, tol, want_cov=False)))
    score = np.array([_hypothesis_score(r[0], r[3]) for r in runs])
    trial = np.array([0.0] + [above for _, above in alternatives])
    best, kept = undecided(trial, score)
    prob, s, _, info = runs[best]
    sols = [runs[i][2] if runs[i][2] is not None  # an alternative's: at its own state
            else covariance_solve(runs[i][0], assemble(runs[i][0], runs[i][1])[0])
            for i in [best] + kept]
    runs = [r[:2] for r in runs]  # (the others' covariances' memory)
    w = np.full(len(kept) + 1, 1.0 / (len(kept) + 1))
    prob = replace(prob, prism_alternatives=tuple(
        (runs[i][0].prism_found[-1][0], float(score[i] - score[best]),
         float(w[0]) if i in kept else 0.0) for i in range(len(runs)) if i != best))
    if not kept:
        return prob, s, sols[0], info
    steps = [difference(prob, s, runs[i][1]) for i in kept]
    dx = np.stack([x for x, _ in steps])
    dg = np.stack([g for _, g in steps])
    return prob, s, mix_solutions(sols, w, dx, dg), info


def undecided(trial: np.ndarray, final: np.ndarray) -> tuple[int, list[int]]:
    """Which prism hypotheses the data have decided against: of the scores (cost plus freed
    directions) of each hypothesis's ``trial`` (H,) solve (weighted by an early update of
    the noise) and ``final`` (H,) solve (the final noise, chains and ``Qc``), the estimate
    is the lowest final score's, and another hypothesis is kept beside it where its final
    score is within :data:`UNDECIDED_COST` of the estimate's or its trial scored below the
    estimate's: an order that the noise's update turns is not the data's
    (docs/joint.md#which-prism-moved). Returns the estimate's index and the kept ones'."""
    best = int(np.argmin(final))
    kept = [i for i in range(final.size) if i != best and (
        final[i] - final[best] < UNDECIDED_COST or trial[i] < trial[best])]
    return best, kept


def _hypothesis_score(prob: JointProblem, info: SolveInfo) -> float:
    """A prism hypothesis's score: the final cost of its solve plus the directions its
    freed prism (the last found) frees (the expected decrease of freeing an unmoved one)."""
    return info.costs[-1] + prob.prism_found[-1][2]


def _freed(prob: JointProblem, tests, found: list[int], j: int) -> JointProblem:
    """The problem with prism ``j``'s survey freed (:func:`rtsgt.joint.prisms.free_prism`)."""
    trusted = np.ones(prob.p_body.shape[0], bool)
    trusted[found + [j]] = False
    gauge = gauge_directions(prob.p_body, trusted, j)
    cov = np.linalg.inv(prob.prism_info) if prob.prism_cov is None else prob.prism_cov
    info = free_prism(prob.prism_info, cov, j, tests, gauge)
    entry = (j, float(tests.stat[j]), int(tests.dof[j]))
    return replace(prob, prism_info=info, prism_found=prob.prism_found + (entry,))


__all__ = ["DECREASE_TOL", "HYPOTHESIS_MAX_ITER", "TRIAL_DECREASE_TOL", "UNDECIDED_COST",
           "JointProblem", "JointState", "QcFit", "SolveInfo", "assemble", "carry_alternatives",
           "covariance_solve", "difference",
           "gauss_newton", "gm_step", "measurement_global_factor", "measurement_hsh",
           "measurement_terms", "noise_step", "rocking_step", "snoop_prisms", "solve_with_qc",
           "undecided"]
