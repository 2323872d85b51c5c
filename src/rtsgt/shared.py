"""The ground truth's error split into a part that varies and a part shared by the deployment.

``xi_i = nu_i + L_i theta`` per pose ``i`` (left perturbation, world frame, (x, y, z, rx, ry,
rz)): ``Cov(nu_i) = V_i``, the prisms' GP part through the fit's Jacobian; ``theta ~ N(0,
I_k)``, the whitened shared parameters (station calibrations, clocks, atmospheric scales, the
reference survey), one draw per deployment; ``L_i = J_q,i F_i + J_r,i A_r``. Model and
accuracy: docs/pose.md#the-error-shared-by-the-deployment; the parameters' names:
docs/file-formats.md#run-directory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.geometry.so3 import hat
from rtsgt.interpolation.prisms import PrismsAtTimes
from rtsgt.noise.coupling import StationCoupling
from rtsgt.pose.estimate import DEFAULT_REGISTRATION, pose_jacobians, psd_factor
from rtsgt.pose.reference import ReferencePoints, block_diagonal

__all__ = ["POSE_COMPONENTS", "SharedFactor", "first_order_covariance", "prism_shared_factor",
           "rank_one_factor", "reference_factor", "select_prisms", "split_ground_truth"]

#: Components of a pose error, in the covariance order of :mod:`rtsgt.geometry.transform`.
POSE_COMPONENTS = ("x", "y", "z", "rx", "ry", "rz")


@dataclass(frozen=True)
class SharedFactor:
    """The split of pose errors: ``t`` (T,) s; ``factor`` (T, 6, k) ``L_i``, rows (x, y, z, rx,
    ry, rz), m and rad per unit parameter; ``names`` (k,) its columns' parameters;
    ``varying_cov`` (T, 6, 6) ``V_i``, m^2 / m rad / rad^2."""

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
    """``F_i`` (T, 3n, k_q) and the names (k_q,) of the shared prism parameters.

    ``prisms``: at the pose times, with ``cov_by_source`` (``gp_noise = "white"``);
    ``velocity`` (T, n, 3) m/s, the GP's (the clock's direction); ``stations`` (n,) the station
    of each prism; ``origins`` each station's world position, m; ``coupling`` the stations'
    joint calibration covariance, or None: each prism's calibration factored on its own
    (``calibration_prism<i>_<j>``, shared over time, not between prisms).
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


def first_order_covariance(J_q: np.ndarray, cov_q: np.ndarray) -> np.ndarray:
    """``J_q C J_q^T`` (T, 6, 6), symmetrised: the prisms' covariance ``cov_q`` (m^2; per prism
    (T, n, 3, 3), or joint (T, 3n, 3n)) through the fit's Jacobian ``J_q`` (T, 6, 3n), with the
    linear engine's arithmetic (:func:`rtsgt.pose.estimate_poses`)."""
    C = np.asarray(cov_q, dtype=float)
    if C.ndim == 4:
        C = block_diagonal(C)
    V = J_q @ C @ np.swapaxes(J_q, 1, 2)
    return 0.5 * (V + np.swapaxes(V, 1, 2))


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
    """The :class:`SharedFactor` of valid poses (prisms not collinear): ``L_i = J_q,i F_i +
    J_r,i A_r`` and ``V_i = J_q,i C_gp,i J_q,i^T``, one Jacobian per pose (the run's
    ``registration``, its weights from the total covariances).

    ``prisms`` (T poses, n prisms; ``gp_noise = "white"``), ``velocity``, ``stations``,
    ``origins``, ``coupling``: as :func:`prism_shared_factor`; ``reference``: the tracked
    reference prisms in the prisms' order; ``R_world_body`` (T, 3, 3) the poses' rotations.
    """
    F, names_q = prism_shared_factor(prisms, velocity, stations, origins, coupling)
    A_r, names_r = reference_factor(reference)
    J_q, J_r = pose_jacobians(prisms.xyz, reference.xyz, R_world_body,
                              registration=registration, cov_q=prisms.pose_covariance,
                              cov_r=reference.cov)
    L = np.concatenate([J_q @ F, J_r @ A_r], axis=2)
    return SharedFactor(np.asarray(prisms.t, dtype=float), L, names_q + names_r,
                        first_order_covariance(J_q, prisms.cov_gp))
