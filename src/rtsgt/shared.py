r"""The ground truth's error split into a part that varies and a part shared by the deployment.

Model
-----
The error ``xi_i`` (6-vector, left perturbation in the world frame, ordered
``(x, y, z, rx, ry, rz)``, :mod:`rtsgt.geometry.transform`) of the ground-truth pose ``i`` is,
to first order,

.. math::

    \xi_i = \nu_i + L_i \theta, \qquad \theta \sim N(0, I_k), \qquad
    \mathrm{Cov}(\nu_i) = V_i,

where ``nu_i`` is the **varying** error (the GP posterior of the prisms: measurement noise
smoothed over a few seconds, correlated between nearby poses only) and ``theta`` the ``k``
whitened **shared** parameters, one draw for the whole deployment:

``calibration_station<s>_<x|y|z|rx|ry|rz>``
    The left perturbations of every calibrated station's ``T_world_station`` (translation m,
    rotation rad), correlated between stations (:class:`~rtsgt.calibration.coupling.
    StationCoupling`), whitened by the lower Cholesky factor of their joint ``(6S, 6S)``
    covariance: parameter ``j`` is the part of station-parameter ``j`` not explained by the
    ones before it. A prism at ``p`` seen from a station at ``o`` moves by
    ``dp = dt - [p - o]x dphi`` (:func:`rtsgt.noise.linear.calibration_covariance`).
``time_sync_station<s>``
    The station's clock offset over ``sqrt(E[e_ts^2])``: ``dp = v tau`` with ``v`` the GP
    velocity of its prism (:mod:`rtsgt.noise.model`).
``atmosphere_station<s>``
    The station's error of the atmospheric scale ``dk`` (from the errors of the weather):
    ``dp = (p - o) dk``. As in the joint prism covariance the pose engines use, the weather
    errors of two stations are taken independent.
``reference_<prism>_<x|y|z>`` (or ``reference_<j>``)
    The surveyed reference prisms on the robot (body frame), whitened by the Cholesky factor of
    their ``(3n, 3n)`` covariance (by its eigen-factor, parameters ``reference_<j>``, when it is
    singular).

The size of a station's clock and atmosphere parameters at time ``t`` is read from the
per-source covariance the noise model gave (interpolated at ``t``): both sources are rank one
(``E[e_ts^2] v v^T``, ``d^2 var(k) u u^T``), so ``dp = sqrt(tr C_source(t)) * direction``
(:func:`rank_one_factor`, the factor :meth:`~rtsgt.evaluation.ContinuousGroundTruth.
cross_covariance` uses). Stacking the prisms, ``dq_i = F_i theta_q`` with ``F_i`` of shape
``(3n, k_q)``; the pose follows the prisms and the reference through the registration's
Jacobian (:func:`rtsgt.pose.estimate.pose_jacobians`, the linear engine's, for the run's
weighted or unweighted fit):

.. math::

    L_i = J_{q,i} F_i + J_{r,i} A_r, \qquad A_r A_r^T = \Sigma_r .

The shared covariance of pose ``i`` is ``L_i L_i^T``, the cross-covariance of poses ``i`` and
``j`` through the shared errors ``L_i L_j^T``. The varying covariance ``V_i`` is the prisms'
GP part alone (``cov_gp``, without the survey's covariance) propagated through the same
Jacobian, ``V_i = J_{q,i} C_{gp,i} J_{q,i}^T``, whatever the run's pose engine: the linear
engine's covariance of that part, with the weights of the whole (the fit is the run's: only
what is propagated through it changes). The fit's nonlinearity over the GP part's
millimetres is of relative size ``(sigma / lever arm)^2`` (the unscented engine's ``V_i``
differs by at most 8e-5 of ``sigma_a sigma_b`` over a simulated hour), far below the sampling
error ``sqrt(2 / M)`` a Monte Carlo of it would add (tests/test_shared_cov.py).

``V_i + L_i L_i^T`` is the linear engine's total covariance exactly where ``F_i F_i^T`` is the
systematic part of the joint prism covariance the engine took; the two differ only by the
factor's choices (tests/test_shared_cov.py, a simulated deployment): the calibration and
atmosphere blocks at the query position instead of interpolated between measurements
(relative difference below 2e-3 of the source), the time-sync block along the GP velocity
instead of the differenced measurements' (median 2e-3 of the source; up to its own size where
the prism stops, below 3e-2 of the prism's total covariance). Over the poses ``V + L L^T`` is
within 2 % of the linear and unscented engines' total (median 2e-3), and within the Monte
Carlo error of the Monte Carlo engine's.

This module imports only numpy and rtsgt's calibration, interpolation and pose records.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.calibration.coupling import StationCoupling
from rtsgt.geometry.so3 import hat
from rtsgt.interpolation.prisms import PrismsAtTimes
from rtsgt.pose.estimate import DEFAULT_REGISTRATION, estimate_poses, pose_jacobians, psd_factor
from rtsgt.pose.reference import ReferencePoints, block_diagonal

__all__ = ["POSE_COMPONENTS", "SharedFactor", "first_order_covariance", "prism_shared_factor",
           "rank_one_factor", "reference_factor", "select_prisms", "shared_pose_factor",
           "split_ground_truth", "varying_pose_covariance"]

#: Components of a pose error, in the covariance order of :mod:`rtsgt.geometry.transform`.
POSE_COMPONENTS = ("x", "y", "z", "rx", "ry", "rz")


@dataclass(frozen=True)
class SharedFactor:
    """The split of ground-truth pose errors into varying and shared parts (module docstring).

    Attributes
    ----------
    t : ndarray, shape (T,)
        Pose times, s.
    factor : ndarray, shape (T, 6, k)
        ``L_i``: the pose error's sensitivity to the whitened shared parameters, world frame,
        rows ``(x, y, z, rx, ry, rz)``, m and rad per unit parameter.
    names : tuple of str, length k
        The shared parameters, in the order of the columns.
    varying_cov : ndarray, shape (T, 6, 6)
        ``V_i``: covariance of the varying part, m^2 / m rad / rad^2.
    """

    t: np.ndarray
    factor: np.ndarray
    names: tuple[str, ...]
    varying_cov: np.ndarray

    def __post_init__(self) -> None:
        T = self.t.shape[0]
        k = len(self.names)
        if self.factor.shape != (T, 6, k):
            raise ValueError(f"Expected factor of shape ({T}, 6, {k}), got {self.factor.shape}")
        if self.varying_cov.shape != (T, 6, 6):
            raise ValueError(
                f"Expected varying_cov of shape ({T}, 6, 6), got {self.varying_cov.shape}")

    def __len__(self) -> int:
        return self.t.shape[0]

    @property
    def shared_cov(self) -> np.ndarray:
        """``L_i L_i^T``, shape (T, 6, 6)."""
        return self.factor @ np.swapaxes(self.factor, 1, 2)

    @property
    def total_cov(self) -> np.ndarray:
        """``V_i + L_i L_i^T``, shape (T, 6, 6)."""
        return self.varying_cov + self.shared_cov

    def select(self, mask: np.ndarray) -> SharedFactor:
        """The poses of a boolean mask or an index array."""
        return SharedFactor(self.t[mask], self.factor[mask], self.names, self.varying_cov[mask])


def rank_one_factor(cov: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """``f`` with ``f f^T`` the rank-one ``cov`` (K, 3, 3): ``sqrt(tr cov)`` along the unit
    ``direction`` (K, 3); zero where the direction is zero."""
    norm = np.linalg.norm(direction, axis=-1, keepdims=True)
    u = np.divide(direction, norm, out=np.zeros_like(direction), where=norm > 0)
    return np.sqrt(np.clip(np.trace(cov, axis1=-2, axis2=-1), 0.0, None))[..., None] * u


def _lower_factor(cov: np.ndarray) -> tuple[np.ndarray, bool]:
    """Lower Cholesky factor of a PSD matrix, or its eigen-factor (rank-trimmed) when it is
    singular; the flag says which."""
    try:
        return np.linalg.cholesky(cov), True
    except np.linalg.LinAlgError:
        w, U = np.linalg.eigh(0.5 * (cov + cov.T))
        keep = w > 1e-12 * max(float(w.max()), np.finfo(float).tiny)
        return U[:, keep] * np.sqrt(w[keep]), False


def prism_shared_factor(
    prisms: PrismsAtTimes,
    velocity: np.ndarray,
    stations: list[str],
    origins: dict[str, np.ndarray],
    coupling: StationCoupling | None,
) -> tuple[np.ndarray, tuple[str, ...]]:
    """``F_i`` (T, 3n, k_q): the stacked prisms' sensitivity to the shared prism parameters.

    Parameters
    ----------
    prisms : PrismsAtTimes
        The prisms at the pose times, with ``cov_by_source`` (``gp_noise = "white"``).
    velocity : ndarray, shape (T, n, 3)
        GP velocity of each prism, m/s (the time-sync direction).
    stations : list of str, length n
        The station tracking each prism.
    origins : dict str -> ndarray (3,)
        World position of each station, m (the lever arm of its rotation and scale).
    coupling : StationCoupling, optional
        The joint covariance of the station calibrations. Without it the calibration source
        of each prism is factored on its own (Cholesky factor of its covariance at each time,
        parameters ``calibration_prism<i>_<j>``): shared over time, not between prisms.

    Returns
    -------
    F : ndarray, shape (T, 3n, k_q)
    names : tuple of str, length k_q
    """
    T, n, _ = prisms.xyz.shape
    cols: list[np.ndarray] = []
    names: list[str] = []
    by_src = prisms.cov_by_source
    rel = np.stack([prisms.xyz[:, i] - origins.get(s, np.zeros(3))
                    for i, s in enumerate(stations)], axis=1)  # (T, n, 3)
    if "calibration" in by_src:
        known = [] if coupling is None else sorted(
            {s for s in stations if coupling.block(s, s) is not None
             and np.any(coupling.block(s, s))})
        if known:
            joint = np.block([[coupling.block(a, b) if coupling.block(a, b) is not None
                               else np.zeros((6, 6)) for b in known] for a in known])
            # parameters with a variance (a station known exactly has none)
            d = np.diag(joint)
            free = np.flatnonzero(d > 1e-15 * d.max())
            A, chol = _lower_factor(joint[np.ix_(free, free)])  # (p, r)
            A_all = np.zeros((joint.shape[0], A.shape[1]))
            A_all[free] = A  # a parameter without variance: a zero row
            # dq_i = [I, -[q_i]x] xi_{s_i}: the rows of prism i from its station's rows of A
            f = np.zeros((T, 3 * n, A.shape[1]))
            for i, s in enumerate(stations):
                if s in known:
                    a = 6 * known.index(s)
                    f[:, 3 * i:3 * i + 3] = A_all[a:a + 3] - hat(rel[:, i]) @ A_all[a + 3:a + 6]
            cols.append(f)
            labels = [f"calibration_station{s}_{c}" for s in known for c in POSE_COMPONENTS]
            names += ([labels[j] for j in free] if chol
                      else [f"calibration_{j}" for j in range(A.shape[1])])
        for i, s in enumerate(stations):
            if s in known:
                continue
            c = by_src["calibration"][:, i]
            if not np.any(c):
                continue
            f = np.zeros((T, 3 * n, 3))
            f[:, 3 * i:3 * i + 3] = psd_factor(c)
            cols.append(f)
            names += [f"calibration_prism{i}_{j}" for j in range(3)]
    for src, direction in (("time_sync", velocity), ("atmosphere", rel)):
        if src not in by_src:
            continue
        for s in dict.fromkeys(stations):
            f = np.zeros((T, 3 * n, 1))
            for i in (i for i, si in enumerate(stations) if si == s):
                f[:, 3 * i:3 * i + 3, 0] = rank_one_factor(by_src[src][:, i], direction[:, i])
            cols.append(f)
            names.append(f"{src}_station{s}")
    F = np.concatenate(cols, axis=2) if cols else np.zeros((T, 3 * n, 0))
    return F, tuple(names)


def reference_factor(reference: ReferencePoints) -> tuple[np.ndarray, tuple[str, ...]]:
    """``A_r`` (3n, k_r) with ``A_r A_r^T`` the reference covariance, and the parameter names
    (``reference_<prism>_<x|y|z>`` for a Cholesky factor, ``reference_<j>`` otherwise; none
    for a reference known exactly)."""
    cov = np.asarray(reference.cov, dtype=float)
    if not np.any(cov):
        return np.zeros((cov.shape[0], 0)), ()
    A, chol = _lower_factor(cov)
    if chol:
        return A, tuple(f"reference_{p}_{c}" for p in reference.names for c in "xyz")
    return A, tuple(f"reference_{j}" for j in range(A.shape[1]))


def shared_pose_factor(
    prisms: PrismsAtTimes,
    velocity: np.ndarray,
    stations: list[str],
    origins: dict[str, np.ndarray],
    coupling: StationCoupling | None,
    reference: ReferencePoints,
    R_world_body: np.ndarray,
    registration: str = DEFAULT_REGISTRATION,
) -> tuple[np.ndarray, tuple[str, ...]]:
    """``L_i = J_q,i F_i + J_r,i A_r`` (T, 6, k) and the parameter names (module docstring).

    ``R_world_body`` (T, 3, 3): the poses' rotations (the fit of the mean prisms);
    ``registration``: the fit's (:func:`rtsgt.pose.estimate.pose_jacobians`, its weights from
    the prisms' ``pose_covariance`` and the reference's). The poses must not be degenerate
    (the Jacobian raises :class:`~rtsgt.errors.GeometryError` for collinear prisms).
    """
    L, names, _ = _pose_factor(prisms, velocity, stations, origins, coupling, reference,
                               R_world_body, registration)
    return L, names


def _pose_factor(prisms, velocity, stations, origins, coupling, reference, R_world_body,
                 registration):
    """:func:`shared_pose_factor`, and the Jacobian ``J_q`` (T, 6, 3n) it used."""
    F, names_q = prism_shared_factor(prisms, velocity, stations, origins, coupling)
    A_r, names_r = reference_factor(reference)
    J_q, J_r = pose_jacobians(prisms.xyz, reference.xyz, R_world_body,
                              registration=registration, cov_q=prisms.pose_covariance,
                              cov_r=reference.cov)
    return np.concatenate([J_q @ F, J_r @ A_r], axis=2), names_q + names_r, J_q


def first_order_covariance(J_q: np.ndarray, cov_q: np.ndarray) -> np.ndarray:
    """``J_q C J_q^T`` (T, 6, 6), symmetrised: the prisms' covariance ``cov_q`` (m^2; per prism
    (T, n, 3, 3), or joint (T, 3n, 3n)) through the fit's Jacobian ``J_q`` (T, 6, 3n), with the
    linear engine's arithmetic (:func:`rtsgt.pose.estimate_poses`)."""
    C = np.asarray(cov_q, dtype=float)
    if C.ndim == 4:
        C = block_diagonal(C)
    V = J_q @ C @ np.swapaxes(J_q, 1, 2)
    return 0.5 * (V + np.swapaxes(V, 1, 2))


def varying_pose_covariance(
    prisms: PrismsAtTimes, reference: ReferencePoints, engine: str = "linear",
    samples: int = 1000, rng: np.random.Generator | None = None,
    registration: str = DEFAULT_REGISTRATION,
) -> np.ndarray:
    """``V_i`` (T, 6, 6): the pose engine run on the prisms' GP covariance alone, the reference
    taken as exact (:func:`rtsgt.pose.estimate_poses`; ``rng`` for ``engine="mc"``); the
    weighted fit keeps the weights of the total covariance (the run's fit).

    :func:`split_ground_truth` takes the first order (``engine="linear"``, without running the
    engine again: :func:`first_order_covariance` of the Jacobian it already has); the other
    engines here measure what that leaves out (their sampling error, the fit's nonlinearity).
    """
    n = prisms.xyz.shape[1]
    est = estimate_poses(prisms.xyz, prisms.cov_gp, reference.xyz, np.zeros((3 * n, 3 * n)),
                         engine=engine, registration=registration,
                         weight_cov_q=prisms.pose_covariance, weight_cov_r=reference.cov,
                         samples=samples, rng=rng)
    return est.cov


def select_prisms(prisms: PrismsAtTimes, idx: np.ndarray) -> PrismsAtTimes:
    """The prisms at some of the times (a boolean mask or an index array); ``prisms`` itself
    (no copy) when that is every time in order."""
    sel = np.asarray(idx)
    T = prisms.t.shape[0]
    if sel.shape == (T,) and (np.all(sel) if sel.dtype == bool
                              else np.array_equal(sel, np.arange(T))):
        return prisms
    return PrismsAtTimes(prisms.t[idx], prisms.xyz[idx], prisms.cov[idx], prisms.cov_gp[idx],
                         {s: c[idx] for s, c in prisms.cov_by_source.items()},
                         prisms.nearest_dt[idx],
                         None if prisms.cov_joint is None else prisms.cov_joint[idx])


def split_ground_truth(
    prisms: PrismsAtTimes,
    velocity: np.ndarray,
    stations: list[str],
    origins: dict[str, np.ndarray],
    coupling: StationCoupling | None,
    reference: ReferencePoints,
    R_world_body: np.ndarray,
    *,
    registration: str = DEFAULT_REGISTRATION,
) -> SharedFactor:
    """The :class:`SharedFactor` of poses (valid ones: the prisms not collinear).

    Parameters
    ----------
    prisms : PrismsAtTimes
        The prisms at the pose times (T poses, n prisms), systematic sources separate from the
        GP (``gp_noise = "white"``).
    velocity : ndarray, shape (T, n, 3)
        GP velocity of each prism, m/s.
    stations : list of str
        The station of each prism.
    origins : dict str -> ndarray (3,)
        Station positions in the world frame, m.
    coupling : StationCoupling, optional
    reference : ReferencePoints
        The tracked reference prisms, in the order of the prisms.
    R_world_body : ndarray, shape (T, 3, 3)
        The poses' rotations.
    registration : {"weighted", "unweighted"}
        The fit of the poses (the run's).

    Returns
    -------
    SharedFactor
        The factor ``L`` (:func:`shared_pose_factor`) and the varying covariance through the
        same Jacobian (:func:`first_order_covariance` of ``cov_gp``): one Jacobian per pose,
        no Monte Carlo, memory ``O(T n^2 + T k)``.
    """
    L, names, J_q = _pose_factor(prisms, velocity, stations, origins, coupling, reference,
                                 R_world_body, registration)
    return SharedFactor(np.asarray(prisms.t, dtype=float), L, names,
                        first_order_covariance(J_q, prisms.cov_gp))
