"""Dynamic self-calibration of the stations from the robot's motion, alone or with the GCPs.

Owns the fit of the stations' transforms and relative clock offsets to the surveyed
inter-prism distances of the GP-interpolated tracks (Vaidis et al., ICRA 2023), weighted by
the GPs' joint covariance per window, with the shared errors (survey, scale, compensators) as
nuisance parameters; its covariance (first order or Monte Carlo) and refusals. Model,
weights, checks and measured numbers: docs/calibration.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from scipy.linalg import lapack

from rtsgt.calibration.result import CalibrationResult, DynamicFit, MarkerResiduals
from rtsgt.calibration.shots import (
    check_args,
    curvature_tilt,
    marker_residuals,
    natural_key,
    polar_point_covariance,
    setup_shots,
    with_extra_variance,
)
from rtsgt.errors import GeometryError, InputError
from rtsgt.geometry.so3 import exp_so3, hat
from rtsgt.geometry.transform import RigidTransform, perturb, perturbation
from rtsgt.interpolation.cross import gp_joint_covariance
from rtsgt.interpolation.gp import GPTrack
from rtsgt.interpolation.prisms import query_grid
from rtsgt.measurement.instruments import TRIMBLE_S7, InstrumentProfile
from rtsgt.measurement.polar import polar_to_cartesian
from rtsgt.noise.montecarlo import sample_gaussian
from rtsgt.noise.perturb import sample_polar_errors
from rtsgt.pose.reference import ReferencePoints
from rtsgt.stats import ratio_interval
from rtsgt.types import GcpShots

__all__ = ["DYNAMIC_ENGINES", "DistanceSamples", "MAX_SIGMA_M", "SAMPLE_STEP_S", "WINDOW_S",
           "calibrate_dynamic", "distance_samples", "sample_times"]

#: How the covariance of a dynamic calibration is computed (docs/calibration.md).
DYNAMIC_ENGINES = ("linear", "mc")
#: Time between the samples of the tracks, s (the choice: docs/calibration.md#weights).
SAMPLE_STEP_S = 1.0
#: Length of the windows whose samples are weighted jointly, s.
WINDOW_S = 60.0
#: The largest standard deviation of a station's prism positions due to the calibration that
#: the fit accepts, m (docs/calibration.md#refusals).
MAX_SIGMA_M = 0.01
#: The fit with the heights of some stations mirrored must be worse than the best by at least
#: this much in ``-2 log`` likelihood (docs/calibration.md#solution).
HEIGHT_MARGIN = 100.0
#: Gauss-Newton steps of each Monte Carlo refit (from the solution, with its Jacobian).
MC_ITERATIONS = 4
#: Relative jitter added to each variance of a window's joint covariance.
_JITTER = 1e-8
#: Largest condition number of the (Jacobi-scaled) normal matrix taken as regular.
_MAX_CONDITION = 1e12


# ------------------------------------------------------------------------------ observations


@dataclass(frozen=True)
class DistanceSamples:
    """The tracked prisms at the sample times ``t`` (K,), s (docs/calibration.md#observations).

    ``prisms``, ``stations`` (n,): each prism and its station; ``xyz``, ``velocity``
    (K, n, 3): GP posterior mean, m and m/s, station frames; ``windows``: sample indices of
    each window weighted jointly, ``window_cov`` per window (n, m, m, 3, 3) each prism's joint
    GP covariance at its m samples, m^2; ``pairs`` ``(i, j)``, ``i < j``, their surveyed
    ``reference_distance`` (P,), m, and its covariance (P, P), m^2; ``scale_variance``: of the
    scale error common to all tracked distances (the atmospheric correction's).
    """

    t: np.ndarray
    prisms: tuple[str, ...]
    stations: tuple[str, ...]
    xyz: np.ndarray
    velocity: np.ndarray
    windows: tuple[np.ndarray, ...]
    window_cov: tuple[np.ndarray, ...]
    pairs: tuple[tuple[int, int], ...]
    reference_distance: np.ndarray
    reference_distance_cov: np.ndarray
    scale_variance: float = 0.0

    def __len__(self) -> int:
        return self.t.shape[0]

    def select(self, keep: np.ndarray) -> DistanceSamples:
        """The samples where ``keep`` (bool, (K,)), windows and their covariances cut to them."""
        keep = np.asarray(keep, bool)
        new_index = np.cumsum(keep) - 1
        windows, covs = [], []
        for idx, cov in zip(self.windows, self.window_cov, strict=True):
            k = keep[idx]
            if k.any():
                windows.append(new_index[idx[k]])
                covs.append(cov[:, k][:, :, k])
        return replace(self, t=self.t[keep], xyz=self.xyz[keep], velocity=self.velocity[keep],
                       windows=tuple(windows), window_cov=tuple(covs))


def sample_times(gps: dict[str, GPTrack], intervals: np.ndarray,
                 step_s: float = SAMPLE_STEP_S) -> np.ndarray:
    """Times every ``step_s`` seconds inside the ``intervals`` (K, 2)
    (:func:`rtsgt.interpolation.prisms.query_grid`) where every GP answers
    (:meth:`rtsgt.interpolation.gp.GPTrack.supported`), s."""
    t = query_grid(intervals, 1.0 / step_s)
    ok = np.ones(t.shape, bool)
    for g in gps.values():
        ok &= g.supported(t)
    return t[ok]


def _windows(t: np.ndarray, window_s: float) -> tuple[np.ndarray, ...]:
    """Consecutive samples, cut at gaps longer than 1.5 sample steps and every ``window_s``."""
    if t.size == 0:
        return ()
    step = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    cuts = [0]
    for k in np.flatnonzero(np.diff(t) > 1.5 * step) + 1:
        cuts.append(int(k))
    cuts.append(t.size)
    out = []
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        start = a
        while start < b:
            stop = start + int(np.searchsorted(t[start:b], t[start] + window_s, side="left"))
            stop = max(stop, start + 1)
            out.append(np.arange(start, stop))
            start = stop
    return tuple(out)


def distance_samples(
    gps: dict[str, GPTrack], stations: dict[str, str], reference: ReferencePoints,
    t: np.ndarray, *, scale_variance: float = 0.0, window_s: float = WINDOW_S,
) -> DistanceSamples:
    """The observations of the dynamic fit (docs/calibration.md#observations): each prism's GP
    ``gps`` (station frame, white sources only) at the times ``t`` (K,) s where all answer
    (:func:`sample_times`), ``stations`` the station of each prism, ``reference`` the survey of
    the prisms on the robot, ``scale_variance`` of the common scale error, ``window_s`` the
    length of the windows weighted jointly, s."""
    prisms = tuple(gps)
    t = np.asarray(t, dtype=float)
    if t.size < 2:
        raise InputError(f"the dynamic calibration needs tracks common to all prisms: "
                         f"{t.size} sample time(s) where every prism's GP answers")
    ref = reference.select(prisms)
    xyz = np.empty((t.size, len(prisms), 3))
    vel = np.empty_like(xyz)
    for i, pid in enumerate(prisms):
        q = gps[pid].query(t, with_velocity=True)
        xyz[:, i], vel[:, i] = q.position, q.velocity
    windows = _windows(t, window_s)
    covs = tuple(np.stack([gp_joint_covariance(gps[pid], t[idx]) for pid in prisms])
                 for idx in windows)
    n = len(prisms)
    pairs = tuple((i, j) for i in range(n) for j in range(i + 1, n))
    D = np.zeros((len(pairs), 3 * n))
    d_ref = np.empty(len(pairs))
    for k, (i, j) in enumerate(pairs):
        diff = ref.xyz[i] - ref.xyz[j]
        d_ref[k] = np.linalg.norm(diff)
        D[k, 3 * i:3 * i + 3] = diff / d_ref[k]
        D[k, 3 * j:3 * j + 3] = -diff / d_ref[k]
    return DistanceSamples(t, prisms, tuple(str(stations[p]) for p in prisms), xyz, vel, windows,
                           covs, pairs, d_ref, D @ ref.cov @ D.T, float(scale_variance))


# ------------------------------------------------------------------------------ the problem


def _inverse_cholesky(c: np.ndarray) -> np.ndarray:
    """``L^-1`` for ``c = L L^T`` (lower triangular; LAPACK's triangular inverse)."""
    inv, info = lapack.dtrtri(np.linalg.cholesky(c), lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"singular Cholesky factor (dtrtri info {info})")
    return inv


@dataclass
class _State:
    """Batched unknowns (leading axis M)."""

    R: np.ndarray  # (M, S, 3, 3)
    t: np.ndarray  # (M, S, 3)
    psi: np.ndarray  # (M, S), 4dof
    clock: np.ndarray  # (M, S), s
    x: np.ndarray  # (M, G, 3) markers (joint)
    z: np.ndarray  # (M, k) whitened nuisance parameters

    def copy(self) -> _State:
        return _State(*(a.copy() for a in (self.R, self.t, self.psi, self.clock, self.x,
                                           self.z)))


def _yaw(R: np.ndarray) -> np.ndarray:
    return np.arctan2(R[..., 1, 0] - R[..., 0, 1], R[..., 0, 0] + R[..., 1, 1])


@dataclass
class _Data:
    """What the residuals are computed from (leading axis M or 1)."""

    p: np.ndarray  # (M, K, n, 3)
    d_ref: np.ndarray  # (M, P)
    shots: np.ndarray  # (M, G_shots, 3) GCP points, station frames
    z_obs: np.ndarray  # (M, k) the nuisance parameters' prior observation (0; drawn in MC)


class _Problem:
    """The layout of the unknowns (stations, clocks, markers, then the whitened nuisance
    parameters ``z``, with ``c = L z`` the survey errors, the scale and the compensators' tilts
    and ``z ~ N(0, I)`` a priori) and the residuals."""

    def __init__(self, samples: DistanceSamples | None, stations: list[str], ref: str,
                 model: str, gcp: dict | None, sigma_tilt: float):
        self.samples = samples
        self.stations = stations
        self.S = len(stations)
        self.ref = stations.index(ref)
        self.model = model
        self.width = 6 if model == "6dof" else 4
        cols = 0
        self.pose_col = np.full(self.S, -1)
        for s in range(self.S):
            if s != self.ref:
                self.pose_col[s] = cols
                cols += self.width
        self.clock_col = np.full(self.S, -1)
        if samples is not None:
            self.prism_station = np.array([stations.index(s) for s in samples.stations])
            for s in sorted(set(self.prism_station.tolist())):
                if s != self.ref:
                    self.clock_col[s] = cols
                    cols += 1
            self.pairs = np.array(samples.pairs, dtype=int).reshape(-1, 2)
        self.gcp = gcp
        self.marker_col = cols
        if gcp is not None:
            cols += 3 * gcp["markers"]
        self.p = cols  # the parameters of interest (and the markers)
        # nuisance parameters c: survey distances, the scale, the compensators (4dof)
        c, blocks = 0, []
        self.survey_col = self.scale_col = self.tilt_col = -1
        if samples is not None:
            self.survey_col, self.scale_col = 0, len(samples.pairs)
            c = len(samples.pairs) + 1
            blocks += [samples.reference_distance_cov, np.array([[samples.scale_variance]])]
        if model == "4dof":
            self.tilt_col = c
            c += 2 * self.S
            blocks.append(sigma_tilt ** 2 * np.eye(2 * self.S))
        self.c = c
        Cc = np.zeros((c, c))
        k = 0
        for b in blocks:
            Cc[k:k + b.shape[0], k:k + b.shape[0]] = b
            k += b.shape[0]
        self.Cc = Cc
        w, V = np.linalg.eigh(0.5 * (Cc + Cc.T)) if c else (np.zeros(0), np.zeros((0, 0)))
        keep = w > 1e-12 * max(float(w.max(initial=0.0)), 1e-300)
        self.L = V[:, keep] * np.sqrt(w[keep])  # c = L z
        self.k = int(keep.sum())
        self.z_col = cols
        self.n_par = cols + self.k
        self.whiten = None  # per window: inverse Cholesky factors (distances)
        self.shot_whiten = None  # (G_shots, 3, 3) (GCP)

    # -- state ---------------------------------------------------------------------------

    def nuisance(self, st: _State) -> np.ndarray:
        """``c = L z`` (M, c)."""
        return st.z @ self.L.T

    def rotations(self, st: _State) -> None:
        """Under 4dof, ``R = exp([omega(t) + tau_s - tau_ref]x) R_z(psi)`` (the reference
        stays I)."""
        if self.model != "4dof":
            return
        c, s = np.cos(st.psi), np.sin(st.psi)
        Rz = np.zeros(st.psi.shape + (3, 3))
        Rz[..., 0, 0], Rz[..., 0, 1], Rz[..., 1, 0], Rz[..., 1, 1] = c, -s, s, c
        Rz[..., 2, 2] = 1.0
        st.R = exp_so3(curvature_tilt(st.t) + self.tilts(st)) @ Rz
        st.R[:, self.ref] = np.eye(3)

    def tilts(self, st: _State) -> np.ndarray:
        """Each station's tilt against the reference, ``tau_s - tau_ref`` (M, S, 3), z = 0."""
        out = np.zeros(st.t.shape)
        if self.tilt_col >= 0:
            tau = self.nuisance(st)[:, self.tilt_col:self.tilt_col + 2 * self.S]
            tau = tau.reshape(-1, self.S, 2)
            out[..., :2] = tau - tau[:, self.ref:self.ref + 1]
        return out

    def update(self, st: _State, step: np.ndarray) -> _State:
        """The state moved by ``step`` (M, n_par)."""
        new = st.copy()
        new.z += step[:, self.z_col:self.z_col + self.k]
        for s in range(self.S):
            a = self.pose_col[s]
            if a < 0:
                continue
            new.t[:, s] += step[:, a:a + 3]
            if self.model == "6dof":
                new.R[:, s] = exp_so3(step[:, a + 3:a + 6]) @ st.R[:, s]
            else:
                new.psi[:, s] += step[:, a + 3]
            if self.clock_col[s] >= 0:
                new.clock[:, s] += step[:, self.clock_col[s]]
        if self.gcp is not None:
            G = self.gcp["markers"]
            new.x += step[:, self.marker_col:self.marker_col + 3 * G].reshape(-1, G, 3)
        self.rotations(new)
        return new

    # -- residuals -----------------------------------------------------------------------

    def distance_rows(self, st: _State, data: _Data, jac: bool):
        """Unwhitened distance residuals (M, K, P) and their Jacobian (M, K, P, n_par)."""
        smp = self.samples
        ps = self.prism_station
        c = self.nuisance(st)
        alpha = c[:, self.scale_col] if self.c else np.zeros(st.t.shape[0])
        R = st.R[:, ps]  # (M, n, 3, 3)
        pt = data.p * (1.0 + alpha[:, None, None, None]) \
            - st.clock[:, ps][:, None, :, None] * smp.velocity[None]
        w = np.einsum("mnij,mknj->mkni", R, pt)  # R p~ (M, K, n, 3)
        q = w + st.t[:, ps][:, None]
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        diff = q[:, :, i] - q[:, :, j]  # (M, K, P, 3)
        dist = np.linalg.norm(diff, axis=-1)
        P = diff.shape[2]
        r = dist - data.d_ref[:, None, :] - c[:, None, self.survey_col:self.survey_col + P]
        if not jac:
            return r, None
        u = diff / dist[..., None]
        M, K = r.shape[:2]
        J = np.zeros((M, K, P, self.n_par))
        B = np.zeros((M, K, P, self.c))
        B[..., self.survey_col:self.survey_col + P] = -np.eye(P)
        Rp = np.einsum("mnij,mknj->mkni", R, data.p)
        for k in range(P):
            for end, sign in ((i[k], 1.0), (j[k], -1.0)):
                B[:, :, k, self.scale_col] += sign * np.sum(u[:, :, k] * Rp[:, :, end], axis=-1)
                s = ps[end]
                if s == self.ref:
                    continue
                g = sign * u[:, :, k]  # (M, K, 3)
                wxg = np.cross(w[:, :, end], g)
                a = self.pose_col[s]
                J[:, :, k, a:a + 3] += g
                if self.model == "6dof":
                    J[:, :, k, a + 3:a + 6] += wxg
                else:
                    J[:, :, k, a + 3] += np.einsum("mki,mi->mk", wxg, st.R[:, s, :, 2])
                    t0, r0 = self.tilt_col + 2 * s, self.tilt_col + 2 * self.ref
                    B[:, :, k, t0:t0 + 2] += wxg[..., :2]
                    B[:, :, k, r0:r0 + 2] -= wxg[..., :2]
                rv = np.einsum("mij,kj->mki", st.R[:, s], smp.velocity[:, end])
                J[:, :, k, self.clock_col[s]] -= np.sum(g * rv, axis=-1)
        J[..., self.z_col:] = B @ self.L
        return r, J

    def distance_covariance(self, st: _State, data: _Data) -> list[np.ndarray]:
        """Per window, the covariance of the residuals (m P, m P) from the GPs' (at ``st``)."""
        smp = self.samples
        ps = self.prism_station
        R = st.R[0, ps]
        pt = data.p[0] - st.clock[0, ps][None, :, None] * smp.velocity
        q = np.einsum("nij,knj->kni", R, pt) + st.t[0, ps][None]
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        diff = q[:, i] - q[:, j]
        u = diff / np.linalg.norm(diff, axis=-1, keepdims=True)  # (K, P, 3)
        out = []
        for idx, G in zip(smp.windows, smp.window_cov, strict=True):
            m, P = idx.size, self.pairs.shape[0]
            cov = np.zeros((m, P, m, P))
            for e in range(len(ps)):
                coef = np.zeros((m, P, 3))
                coef[:, i == e] += u[idx][:, i == e]
                coef[:, j == e] -= u[idx][:, j == e]
                coef = coef @ R[e]  # station frame: c^T = u^T R
                cov += np.einsum("aki,abij,blj->akbl", coef, G[e], coef)
            cov = cov.reshape(m * P, m * P)
            cov = 0.5 * (cov + cov.T)
            cov[np.diag_indices_from(cov)] *= 1.0 + _JITTER
            out.append(cov)
        return out

    def set_weights(self, st: _State, data: _Data, unit: float | None = None) -> None:
        """The whitening of the residuals at ``st`` (``unit``: identity scaled by it, m)."""
        if self.samples is not None:
            if unit is not None:
                self.whiten = [np.eye(idx.size * len(self.samples.pairs)) / unit
                               for idx in self.samples.windows]
            else:
                self.whiten = [_inverse_cholesky(c) for c in self.distance_covariance(st, data)]
        if self.gcp is not None:
            R = st.R[0, self.gcp["station"]]  # (G, 3, 3)
            if unit is not None:
                self.shot_whiten = np.broadcast_to(np.eye(3) / unit, R.shape).copy()
            else:
                L = np.linalg.cholesky(self.gcp["cov"])
                self.shot_whiten = np.linalg.inv(L) @ np.swapaxes(R, 1, 2)

    def gcp_rows(self, st: _State, data: _Data, jac: bool):
        """Unwhitened GCP residuals (M, G, 3) and their Jacobian (M, G, 3, n_par)."""
        g = self.gcp
        s_of = g["station"]
        R = st.R[:, s_of]
        w = np.einsum("mgij,mgj->mgi", R, data.shots)
        r = st.x[:, g["marker"]] - w - st.t[:, s_of]
        if not jac:
            return r, None
        M, Gs = r.shape[:2]
        W = hat(w)  # d r / d dphi = [R p]x
        J = np.zeros((M, Gs, 3, self.n_par))
        B = np.zeros((M, Gs, 3, self.c))
        rows = np.arange(Gs)
        for a in range(3):
            J[:, rows, a, self.marker_col + 3 * g["marker"] + a] = 1.0
        for s in range(self.S):
            c0 = self.pose_col[s]
            sel = s_of == s
            if c0 < 0 or not sel.any():
                continue
            J[:, sel, :, c0:c0 + 3] = -np.eye(3)
            if self.model == "6dof":
                J[:, sel, :, c0 + 3:c0 + 6] = W[:, sel]
            else:
                J[..., c0 + 3][:, sel] = np.einsum("mgij,mj->mgi", W[:, sel],
                                                   st.R[:, s, :, 2])
                a, r0 = self.tilt_col + 2 * s, self.tilt_col + 2 * self.ref
                B[:, sel, :, a:a + 2] += W[:, sel, :, :2]
                B[:, sel, :, r0:r0 + 2] -= W[:, sel, :, :2]
        J[..., self.z_col:] = B @ self.L
        return r, J

    def evaluate(self, st: _State, data: _Data, jac: bool = True):
        """Whitened residuals (M, n) and Jacobian (M, n, n_par): the distance rows, the GCP
        rows, then the nuisance parameters' prior rows ``z - z_obs``."""
        rs, Js = [], []
        M = st.t.shape[0]
        if self.samples is not None:
            r, J = self.distance_rows(st, data, jac)
            P = r.shape[2]
            for idx, L in zip(self.samples.windows, self.whiten, strict=True):
                rs.append(r[:, idx].reshape(M, -1) @ L.T)
                if jac:
                    Js.append(L @ J[:, idx].reshape(M, idx.size * P, -1))
        if self.gcp is not None:
            r, J = self.gcp_rows(st, data, jac)
            Wh = self.shot_whiten
            rs.append(np.einsum("gij,mgj->mgi", Wh, r).reshape(M, -1))
            if jac:
                Js.append(np.einsum("gij,mgjp->mgip", Wh, J).reshape(M, -1, self.n_par))
        rs.append(st.z - data.z_obs)
        if jac:
            prior = np.zeros((M, self.k, self.n_par))
            prior[:, :, self.z_col:] = np.eye(self.k)
            Js.append(prior)
        return np.concatenate(rs, axis=1), (np.concatenate(Js, axis=1) if jac else None)

    @property
    def distance_rows_count(self) -> int:
        if self.samples is None:
            return 0
        return len(self.samples) * len(self.samples.pairs)

    # -- the transforms' errors ------------------------------------------------------------

    def output_map(self, st: _State) -> np.ndarray:
        """Linear map (6 S' + S'', n_par) from the parameters' errors to the stacked left
        perturbations of the non-reference stations (x, y, z, rx, ry, rz each) followed by
        their clock offsets (under ``4dof`` the estimated tilts enter the rotations)."""
        free = [s for s in range(self.S) if s != self.ref]
        clocks = [s for s in free if self.clock_col[s] >= 0]
        n_out = 6 * len(free) + len(clocks)
        A = np.zeros((n_out, self.n_par))
        Ac = np.zeros((n_out, self.c))
        for k, s in enumerate(free):
            a = self.pose_col[s]
            A[6 * k:6 * k + 3, a:a + 3] = np.eye(3)
            if self.model == "6dof":
                A[6 * k + 3:6 * k + 6, a + 3:a + 6] = np.eye(3)
            else:
                A[6 * k + 3:6 * k + 6, a + 3] = st.R[0, s, :, 2]
                t0, r0 = self.tilt_col + 2 * s, self.tilt_col + 2 * self.ref
                Ac[6 * k + 3:6 * k + 5, t0:t0 + 2] += np.eye(2)
                Ac[6 * k + 3:6 * k + 5, r0:r0 + 2] -= np.eye(2)
        A[:, self.z_col:] = Ac @ self.L
        for k, s in enumerate(clocks):
            A[6 * len(free) + k, self.clock_col[s]] = 1.0
        return A


# ------------------------------------------------------------------------------ solving


def _lm(problem: _Problem, st: _State, data: _Data, max_iter: int = 100) -> tuple[_State, int]:
    """Levenberg-Marquardt on the whitened residuals (M = 1)."""
    r, J = problem.evaluate(st, data)
    cost = float(np.sum(r * r))
    lam = 1e-3
    for it in range(max_iter):
        N = J[0].T @ J[0]
        g = J[0].T @ r[0]
        D = np.diag(np.maximum(np.diag(N), 1e-30))
        try:
            step = np.linalg.solve(N + lam * D, -g)
        except np.linalg.LinAlgError:
            lam *= 10.0
            continue
        new = problem.update(st, step[None])
        r2, J2 = problem.evaluate(new, data)
        cost2 = float(np.sum(r2 * r2))
        if cost2 <= cost:
            done = cost - cost2 <= 1e-12 * max(cost, 1e-30) or float(
                np.max(np.abs(step))) < 1e-11
            st, r, J, cost = new, r2, J2, cost2
            lam = max(lam / 10.0, 1e-12)
            if done:
                return st, it + 1
        else:
            lam *= 10.0
            if lam > 1e12:
                return st, it + 1
    return st, max_iter


def _solve(problem: _Problem, st: _State, data: _Data) -> tuple[_State, int, float]:
    """The fit from ``st``: unweighted, then weighted twice (docs/calibration.md#solution); returns the state, the last solve's iterations and ``-2 log`` of the
    likelihood (whitened cost plus the log-determinant of the residuals' covariance)."""
    problem.set_weights(st, data, unit=1e-3)
    st, _ = _lm(problem, st, data)
    for _ in range(2):
        problem.set_weights(st, data)
        st, iterations = _lm(problem, st, data)
    r, _ = problem.evaluate(st, data, jac=False)
    logdet = -2.0 * sum(float(np.sum(np.log(np.abs(np.diag(L))))) for L in problem.whiten or ())
    return st, iterations, float(np.sum(r * r)) + logdet


def _distinct(a: _State, b: _State) -> bool:
    """Whether two solutions differ by more than the calibration's accepted uncertainty."""
    return bool(np.max(np.abs(a.t[0] - b.t[0])) > MAX_SIGMA_M)


def _heights(problem: _Problem, st: _State, data: _Data,
             nll: float) -> tuple[tuple[float, _State], tuple[float, _State] | None]:
    """The fits from ``st`` with the heights of every subset of the stations mirrored
    (docs/calibration.md#solution): the best ``(-2 log likelihood, state)``, and the best of
    those distinct from it (None if none is)."""
    smp = problem.samples
    ps = problem.prism_station
    q = np.einsum("nij,knj->kni", st.R[0, ps], smp.xyz - st.clock[0, ps][None, :, None]
                  * smp.velocity) + st.t[0, ps][None]
    ref_prism = int(np.flatnonzero(ps == problem.ref)[0])
    free = [s for s in range(problem.S) if s != problem.ref and np.any(ps == s)]
    height = {s: float(np.mean(q[:, np.flatnonzero(ps == s)[0], 2] - q[:, ref_prism, 2]))
              for s in free}
    fits = [(nll, st)]
    for flips in range(1, 2 ** len(free)):
        cand = st.copy()
        for b, s in enumerate(free):
            if flips >> b & 1:
                cand.t[:, s, 2] -= 2.0 * height[s]
        problem.rotations(cand)
        c_st, _, c_nll = _solve(problem, cand, data)
        fits.append((c_nll, c_st))
    fits.sort(key=lambda f: f[0])
    other = [f for f in fits[1:] if _distinct(f[1], fits[0][1])]
    return fits[0], (other[0] if other else None)


def _gauss_newton(problem: _Problem, st: _State, data: _Data, iterations: int,
                  gain: np.ndarray) -> _State:
    """Batched Gauss-Newton steps with the solution's Jacobian (the Monte Carlo refits): each
    step is ``-gain r`` with ``gain = N^-1 J^T`` of the solution, the residuals ``r`` those of
    each sample's perturbed data at its current state (a modified Newton iteration: it
    converges to each sample's own least-squares solution, linearly, at the rate of the
    Jacobian's change, tiny for perturbations of millimetres)."""
    for _ in range(iterations):
        r, _ = problem.evaluate(st, data, jac=False)
        st = problem.update(st, -(r @ gain.T))
    return st


# ------------------------------------------------------------------------------ result


def _circle_fits(psi: np.ndarray, p: np.ndarray, q: np.ndarray):
    """For each yaw ``psi`` (N,), the horizontal circle through ``c_k = q_k - R_z(psi) p_k``
    (Kasa's algebraic fit): its RMS geometric residual (N,), centre (N, 2), radius (N,), the
    mean height of the ``c_k`` (N,) and the condition number of the fit (N,)."""
    c, s = np.cos(psi), np.sin(psi)
    x = q[None, :, 0] - (c[:, None] * p[None, :, 0] - s[:, None] * p[None, :, 1])
    y = q[None, :, 1] - (s[:, None] * p[None, :, 0] + c[:, None] * p[None, :, 1])
    x0, y0 = x.mean(axis=1, keepdims=True), y.mean(axis=1, keepdims=True)
    x, y = x - x0, y - y0  # centred: a well-conditioned fit
    A = np.stack([2 * x, 2 * y, np.ones_like(x)], -1)  # (N, K, 3)
    AtA = np.einsum("nki,nkj->nij", A, A)
    cond = np.linalg.cond(AtA)
    ridge = 1e-12 * np.trace(AtA, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    sol = np.linalg.solve(AtA + ridge, np.einsum("nki,nk->ni", A, x * x + y * y)[..., None])[..., 0]
    radius = np.sqrt(np.maximum(sol[:, 2] + np.sum(sol[:, :2] ** 2, axis=1), 0.0))
    dist = np.hypot(x - sol[:, :1], y - sol[:, 1:2])
    centre = sol[:, :2] + np.concatenate([x0, y0], axis=1)
    cost = np.sqrt(np.mean((dist - radius[:, None]) ** 2, axis=1))
    cz = np.mean(q[None, :, 2] - (p[None, :, 2]), axis=1) * np.ones_like(psi)
    return cost, centre, radius, cz, cond


def _initial(samples: DistanceSamples, stations: list[str], ref: str):
    """``{station: (R_z(psi), t)}``: each station's levelled start from the circle its prism
    traces about it at the surveyed distance from the reference station's
    (docs/calibration.md#solution), the height's sign left to :func:`_heights`."""
    st_of = list(samples.stations)
    if ref not in st_of:
        raise InputError(f"the dynamic calibration needs the reference station {ref} to track "
                         "a prism (its frame is the world frame)")
    i_ref = st_of.index(ref)
    q = samples.xyz[:, i_ref]
    out = {ref: (np.eye(3), np.zeros(3))}
    for s in stations:
        if s == ref:
            continue
        if s not in st_of:
            raise InputError(f"station {s} tracks no prism: the robot's motion cannot "
                             "calibrate it (use [calibration] method = \"gcp\" or \"joint\")")
        i_s = st_of.index(s)
        k = list(samples.pairs).index((min(i_ref, i_s), max(i_ref, i_s)))
        d = float(samples.reference_distance[k])
        p = samples.xyz[:, i_s]
        psi = np.radians(np.arange(-180.0, 180.0, 0.5))
        best = psi[np.argmin(_circle_fits(psi, p, q)[0])]
        psi = best + np.radians(np.arange(-0.5, 0.5001, 0.025))
        cost, centre, radius, cz, cond = _circle_fits(psi, p, q)
        j = int(np.argmin(cost))
        if not cond[j] < _MAX_CONDITION:
            raise GeometryError(
                f"dynamic calibration of station {s}: the trajectory does not determine the "
                "stations' transforms (the robot does not turn: the distance between the "
                "prisms never changes direction); drive a path that turns and changes "
                "direction, or calibrate from the GCPs (method \"gcp\" or \"joint\")")
        height = np.sqrt(max(d * d - radius[j] ** 2, 0.0))
        c, sn = np.cos(psi[j]), np.sin(psi[j])
        R = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        out[s] = (R, np.array([centre[j, 0], centre[j, 1], cz[j] + height]))
    return out


def _start(problem: _Problem, init: dict) -> tuple[_State, _Data]:
    """The state at the transforms ``init`` (``{station: (R, t)}``; the markers, under the joint
    fit, at the mean of their shots) and the data of ``problem``'s samples and shots."""
    stations, smp, layout = problem.stations, problem.samples, problem.gcp
    S = len(stations)
    x = np.zeros((0, 3)) if layout is None else _marker_start(layout, init, stations)
    st = _State(np.stack([init[s][0] for s in stations])[None],
                np.stack([init[s][1] for s in stations])[None], np.zeros((1, S)),
                np.zeros((1, S)), x[None], np.zeros((1, problem.k)))
    st.psi = _yaw(st.R)
    problem.rotations(st)
    data = _Data(np.zeros((1, 0, 0, 3)) if smp is None else smp.xyz[None],
                 np.zeros((1, 0)) if smp is None else smp.reference_distance[None],
                 np.zeros((1, 0, 3)) if layout is None else layout["points"][None],
                 np.zeros((1, problem.k)))
    return st, data


def _levelled_start(samples: DistanceSamples, stations: list[str], ref: str,
                    sigma_tilt: float) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The levelled (4-DOF) fit from :func:`_initial`, its heights settled by :func:`_heights`
    (docs/calibration.md#solution): the start of a 6-DOF dynamic fit."""
    problem = _Problem(samples, stations, ref, "4dof", None, sigma_tilt)
    st, data = _start(problem, _initial(samples, stations, ref))
    st, _, nll = _solve(problem, st, data)
    best = _heights(problem, st, data, nll)[0][1]
    return {s: (best.R[0, k], best.t[0, k]) for k, s in enumerate(stations)}


def _gcp_layout(shots: GcpShots, ref: str, stations: list[str], instrument: InstrumentProfile,
                extra: np.ndarray) -> tuple[dict, object]:
    """The valid GCP shots of the markers shared with the reference, as
    :func:`rtsgt.calibration.gcp.calibrate` uses them."""
    setup = setup_shots(shots, ref, instrument)
    markers = sorted(setup.used_markers, key=natural_key)
    idx, st, mk = [], [], []
    for (s, m), k in setup.shot.items():
        if m in setup.used_markers and s in stations:
            idx.append(k)
            st.append(stations.index(s))
            mk.append(markers.index(m))
    idx = np.array(idx)
    C = polar_point_covariance(setup.hz[idx], setup.v[idx], setup.d[idx], instrument)
    return {"index": idx, "station": np.array(st), "marker": np.array(mk),
            "markers": len(markers), "points": setup.points[idx], "instrument_cov": C,
            "cov": with_extra_variance(C, extra), "hz": setup.hz[idx], "v": setup.v[idx],
            "d": setup.d[idx]}, setup


def _gcp_horizontal_component(layout: dict, extra: np.ndarray, stations: list[str], ref: str,
                              model: str, sigma_tilt: float, init: dict) -> np.ndarray:
    """The shots' variance components for the joint fit (docs/calibration.md#the-joint-calibration):
    the GCP calibration's ``(horizontal, vertical)``, with the horizontal one raised, where the
    generalised least-squares fit of the GCPs alone has a variance factor above its 95 %
    interval, to the value that brings it to 1 (bisection on the variance)."""

    def factor(h: float) -> float:
        e = np.array([extra[0] + h, extra[1]])
        lay = {**layout, "cov": with_extra_variance(layout["instrument_cov"], e)}
        problem = _Problem(None, stations, ref, model, lay, sigma_tilt)
        st, data = _start(problem, init)
        st, _, _ = _solve(problem, st, data)
        r, _ = problem.evaluate(st, data, jac=False)
        return float(np.sum(r * r)) / (r.size - problem.n_par), r.size - problem.n_par

    f0, dof = factor(0.0)
    if f0 <= ratio_interval(dof)[1]:
        return extra
    hi = 1e-8
    while factor(hi)[0] > 1.0 and hi < 1.0:
        hi *= 4.0
    lo = 0.0
    for _ in range(40):  # bisection on the variance, to 1e-12 relative
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if factor(mid)[0] > 1.0 else (lo, mid)
    return np.array([extra[0] + hi, extra[1]])


def _marker_start(layout: dict, init: dict, stations: list[str]) -> np.ndarray:
    """Each marker's world position, the mean of its shots mapped by ``init``."""
    R = np.stack([init[s][0] for s in stations])[layout["station"]]
    t = np.stack([init[s][1] for s in stations])[layout["station"]]
    w = np.einsum("gij,gj->gi", R, layout["points"]) + t
    x = np.zeros((layout["markers"], 3))
    np.add.at(x, layout["marker"], w)
    return x / np.bincount(layout["marker"], minlength=layout["markers"])[:, None]


def _check_dynamic(samples, gcp, gcp_calibration, model, instrument, engine, n_samples) -> None:
    """Raise :class:`InputError` for the arguments :func:`calibrate_dynamic` refuses."""
    check_args(instrument, "none", model)
    if engine not in DYNAMIC_ENGINES:
        raise InputError(f"Expected engine {' or '.join(map(repr, DYNAMIC_ENGINES))}, "
                         f"got {engine!r}")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) \
            or n_samples < 2:
        raise InputError(f"Expected n_samples >= 2, got {n_samples!r}")
    if gcp is not None and gcp_calibration is None:
        raise InputError("the joint calibration needs the GCP calibration of the same shots")
    if samples is None and gcp is None:
        raise InputError("nothing to calibrate from: no distance samples and no GCPs")


def _joint_layout(gcp: GcpShots, gcp_calibration: CalibrationResult, ref: str,
                  stations: list[str], instrument: InstrumentProfile, model: str):
    """The GCP shots of the joint fit (:func:`_gcp_layout`), their :class:`ShotSetup` and the
    variance components ``(horizontal, vertical)`` (:func:`_gcp_horizontal_component`), m^2."""
    extra = np.array(gcp_calibration.extra_shot_sigma_m) ** 2
    layout, setup = _gcp_layout(gcp, ref, stations, instrument, extra)
    extra = _gcp_horizontal_component(layout, extra, stations, ref, model,
                                      instrument.sigma_tilt, _transforms_of(gcp_calibration))
    layout["cov"] = with_extra_variance(layout["instrument_cov"], extra)
    return layout, setup, extra


def _transforms_of(calibration: CalibrationResult) -> dict:
    """``{station: (R, t)}`` of a calibration."""
    return {s: (T.rotation, T.translation) for s, T in calibration.transforms.items()}


class _Solution(NamedTuple):
    """The gated fit: the problem and data it ended with, the state, the samples kept, the last
    solve's iterations, the height ambiguity (``-2 log`` likelihood margin) and the samples
    left out."""

    problem: _Problem
    st: _State
    data: _Data
    samples: DistanceSamples | None
    iterations: int
    ambiguity: float
    rejected: int


def _gated_fit(samples: DistanceSamples | None, stations: list[str], ref: str, model: str,
               layout: dict | None, sigma_tilt: float, gcp_calibration: CalibrationResult | None,
               gate_m: float) -> _Solution:
    """The fit, then again from the start without the samples whose pair residual exceeds
    ``gate_m`` (m), at most four fits."""
    rejected = 0
    for _ in range(4):
        problem = _Problem(samples, stations, ref, model, layout, sigma_tilt)
        if layout is not None:
            init = _transforms_of(gcp_calibration)
        else:
            init = (_levelled_start(samples, stations, ref, sigma_tilt)
                    if model == "6dof" else _initial(samples, stations, ref))
        st, data = _start(problem, init)
        st, iterations, nll = _solve(problem, st, data)
        ambiguity = float("inf")
        if layout is None:  # the mirrored heights
            (nll, st), alternative = _heights(problem, st, data, nll)
            problem.set_weights(st, data)
            if alternative is not None:
                ambiguity = alternative[0] - nll
        if samples is None:
            break
        r = problem.distance_rows(st, data, False)[0][0]
        bad = np.any(np.abs(r) > gate_m, axis=1)
        if not bad.any():
            break
        if bad.all() or len(samples) - bad.sum() < 2:
            raise GeometryError(f"dynamic calibration: every sample disagrees with the surveyed "
                                f"distances by more than {gate_m} m after the fit: the fit did "
                                "not converge, or the tracks are not of the surveyed prisms")
        rejected += int(bad.sum())
        samples = samples.select(~bad)
    return _Solution(problem, st, data, samples, iterations, ambiguity, rejected)


def _linearise(problem: _Problem, st: _State, data: _Data):
    """At the solution: the whitened residuals (n,), Jacobian (n, n_par), ``N^-1`` (n_par,
    n_par), the output map ``A`` (:meth:`_Problem.output_map`) and ``A N^-1 A^T``; raises
    :class:`GeometryError` where the normal matrix is singular."""
    r, J = problem.evaluate(st, data)
    r, J = r[0], J[0]
    N = J.T @ J
    d = np.sqrt(np.maximum(np.diag(N), 1e-300))
    cond = np.linalg.cond(N / np.outer(d, d))
    if not np.isfinite(cond) or cond > _MAX_CONDITION:
        raise GeometryError(
            f"dynamic calibration: the trajectory does not determine the stations' transforms "
            f"(normal matrix singular, condition number {cond:.3g}); drive a path that turns "
            "and changes direction, or calibrate from the GCPs (method \"gcp\" or \"joint\")")
    Ninv = np.linalg.inv(N)
    Ninv = 0.5 * (Ninv + Ninv.T)
    A = problem.output_map(st)
    cov_out = A @ Ninv @ A.T
    return r, J, Ninv, A, 0.5 * (cov_out + cov_out.T)


def _worst_sigma(problem: _Problem, st: _State, samples: DistanceSamples, cov_out: np.ndarray,
                 free: list[str], clocks: list[str]) -> dict[str, float]:
    """Per free station tracking a prism, the largest standard deviation of its prisms'
    positions due to the calibration over the samples, m (docs/calibration.md#refusals)."""
    worst = {}
    for k, s in enumerate(free):
        si = problem.stations.index(s)
        mine = np.flatnonzero(problem.prism_station == si)
        if mine.size == 0:
            continue
        Rs = st.R[0, si]
        p = samples.xyz[:, mine] - st.clock[0, si] * samples.velocity[:, mine]
        w = p @ Rs.T  # (K, k, 3)
        rows = [6 * k + a for a in range(6)]
        if s in clocks:
            rows.append(6 * len(free) + clocks.index(s))
        C = cov_out[np.ix_(rows, rows)]
        Jq = np.concatenate([np.broadcast_to(np.eye(3), w.shape + (3,)), -hat(w)], axis=-1)
        if s in clocks:
            Jq = np.concatenate([Jq, -(samples.velocity[:, mine] @ Rs.T)[..., None]], axis=-1)
        Cq = Jq @ C @ np.swapaxes(Jq, -1, -2)
        worst[s] = float(np.sqrt(np.max(np.linalg.eigvalsh(Cq))))
    return worst


def _refuse(worst: dict[str, float], max_sigma_m: float, joint: bool, ambiguity: float) -> None:
    """Raise :class:`GeometryError` for a station determined worse than ``max_sigma_m`` (m; not
    under the joint fit) or heights ambiguous (docs/calibration.md#refusals)."""
    bad = {s: v for s, v in worst.items() if v > max_sigma_m}
    if bad and not joint:
        s, v = max(bad.items(), key=lambda kv: kv[1])
        raise GeometryError(
            f"dynamic calibration: the trajectory does not determine station {s}'s transform "
            f"well enough (its prism positions uncertain by {v * 1e3:.3g} mm from the "
            f"calibration, more than {max_sigma_m * 1e3:.3g} mm); drive a path that turns "
            "and changes direction, or calibrate from the GCPs (method \"gcp\" or \"joint\")")
    if ambiguity < HEIGHT_MARGIN:
        raise GeometryError(
            f"dynamic calibration: the heights of the stations are ambiguous (the fit with "
            f"mirrored heights is worse by only {ambiguity:.3g} in -2 log likelihood, less "
            f"than {HEIGHT_MARGIN:g}): the robot drove on (nearly) flat ground, where the "
            "distances cannot tell a prism above another from one below it; calibrate from "
            "the GCPs (method \"gcp\" or \"joint\")")


def _station_transforms(problem: _Problem, st: _State, z: np.ndarray, cov_out: np.ndarray,
                        free: list[str]) -> dict[str, RigidTransform]:
    """``T_world_station`` of every station, with its 6x6 block of ``cov_out`` and the samples
    moved by ``z`` (M, 6 S' + clocks)."""
    M = z.shape[0]
    transforms = {}
    for si, s in enumerate(problem.stations):
        if si == problem.ref:
            transforms[s] = RigidTransform(
                np.eye(3), np.zeros(3), np.zeros((6, 6)), "world", f"station_{s}",
                np.broadcast_to(np.eye(3), (M, 3, 3)).copy(), np.zeros((M, 3)))
            continue
        k = free.index(s)
        Rm, tm = perturb(st.R[0, si], st.t[0, si], z[:, 6 * k:6 * k + 6])
        transforms[s] = RigidTransform(st.R[0, si], st.t[0, si],
                                       cov_out[6 * k:6 * k + 6, 6 * k:6 * k + 6], "world",
                                       f"station_{s}", Rm, tm)
    return transforms


def _dynamic_fit(sol: _Solution, r: np.ndarray, cov_out: np.ndarray, engine: str,
                 worst: dict[str, float], free: list[str], clocks: list[str],
                 extra: np.ndarray | None) -> DynamicFit:
    """The :class:`DynamicFit` record of the solution (``extra``: the joint fit's variance
    components, m^2; None for the dynamic one)."""
    problem, st, samples = sol.problem, sol.st, sol.samples
    n_free = 6 * len(free)
    clock = {s: float(st.clock[0, problem.stations.index(s)]) for s in clocks}
    clock_sigma = {s: float(np.sqrt(cov_out[n_free + k, n_free + k]))
                   for k, s in enumerate(clocks)}
    pair_mean, pair_rms, pair_names = {}, {}, ()
    dof = float(r.size - problem.n_par)
    vf = float(r @ r) / dof if dof > 0 else float("nan")
    if samples is not None:
        rd = problem.distance_rows(st, sol.data, False)[0][0]
        pair_names = tuple(f"{samples.prisms[i]}-{samples.prisms[j]}" for i, j in samples.pairs)
        pair_mean = {p: float(1e3 * rd[:, k].mean()) for k, p in enumerate(pair_names)}
        pair_rms = {p: float(1e3 * np.sqrt(np.mean(rd[:, k] ** 2)))
                    for k, p in enumerate(pair_names)}
    return DynamicFit("joint" if extra is not None else "dynamic", engine,
                      0 if samples is None else len(samples), sol.rejected, pair_names,
                      tuple(free), clock, clock_sigma, cov_out, vf, dof,
                      ratio_interval(dof) if np.isfinite(dof) else (float("nan"), float("nan")),
                      pair_mean, pair_rms, worst, sol.iterations, sol.ambiguity,
                      None if extra is None else (float(np.sqrt(extra[0])),
                                                  float(np.sqrt(extra[1]))))


def calibrate_dynamic(
    samples: DistanceSamples | None,
    *,
    reference_station: str = "1",
    model: str = "6dof",
    instrument: InstrumentProfile = TRIMBLE_S7,
    gcp: GcpShots | None = None,
    gcp_calibration: CalibrationResult | None = None,
    engine: str = "linear",
    n_samples: int = 1000,
    rng: np.random.Generator | None = None,
    gate_m: float = 0.10,
    max_sigma_m: float = MAX_SIGMA_M,
) -> CalibrationResult:
    """Calibrate the stations from the inter-prism distances ``samples``
    (:func:`distance_samples`; None: the GCPs alone), or jointly with the GCP shots ``gcp``
    and their calibration ``gcp_calibration`` (the start, variance components and checks).

    ``model`` "6dof" or "4dof"; ``engine`` "linear" or "mc" computes the covariance from
    ``n_samples`` (>= 2) draws of ``rng``; samples with a pair residual beyond ``gate_m`` (m)
    are left out; a station whose prisms the calibration leaves uncertain by more than
    ``max_sigma_m`` (m; ``inf``: no refusal) is refused. Returns a :class:`CalibrationResult`
    (``method`` "dynamic" or "joint", ``dynamic`` its :class:`DynamicFit`); raises
    :class:`GeometryError` where the trajectory does not determine the transforms and
    :class:`InputError` for a station tracking no prism, too few samples or bad arguments
    (docs/calibration.md).
    """
    _check_dynamic(samples, gcp, gcp_calibration, model, instrument, engine, n_samples)
    rng = np.random.default_rng() if rng is None else rng
    ref = str(reference_station)
    joint = gcp is not None
    names = set() if samples is None else set(samples.stations)
    if joint:
        names |= set(gcp_calibration.transforms)
    stations = sorted(names | {ref}, key=natural_key)
    layout, setup, extra = (_joint_layout(gcp, gcp_calibration, ref, stations, instrument, model)
                            if joint else (None, None, np.zeros(2)))
    sol = _gated_fit(samples, stations, ref, model, layout, instrument.sigma_tilt,
                     gcp_calibration, gate_m)
    problem, st, data = sol.problem, sol.st, sol.data
    r, J, Ninv, A, cov_out = _linearise(problem, st, data)
    free = [s for s in stations if s != ref]
    clocks = [s for s in free if problem.clock_col[stations.index(s)] >= 0]
    worst = {} if sol.samples is None else _worst_sigma(problem, st, sol.samples, cov_out, free,
                                                         clocks)
    _refuse(worst, max_sigma_m, joint, sol.ambiguity)
    M = int(n_samples)
    if engine == "linear":
        z = sample_gaussian(Ninv, M, rng) @ A.T  # (M, 6 S' + clocks)
    else:
        z = _monte_carlo(problem, st, data, layout, extra, instrument, M, rng, free,
                         Ninv @ J.T)
        cov_out = np.cov(z, rowvar=False)
        cov_out = 0.5 * (cov_out + cov_out.T)
    transforms = _station_transforms(problem, st, z, cov_out, free)
    fit = _dynamic_fit(sol, r, cov_out, engine, worst, free, clocks, extra if joint else None)
    if joint:
        R = {s: st.R[0, k] for k, s in enumerate(stations)}
        t = {s: st.t[0, k] for k, s in enumerate(stations)}
        return replace(gcp_calibration, transforms=transforms,
                       residuals=marker_residuals(setup, R, t), samples=M, method="joint",
                       dynamic=fit)
    return CalibrationResult(
        reference_station=ref, transforms=transforms,
        residuals=MarkerResiduals(*(np.zeros(0, dtype=object),) * 3, np.zeros(0)),
        markers_used={s: () for s in stations}, markers_skipped=(), excluded_shots=0,
        samples=M, weighting="none", model=model, method="dynamic", dynamic=fit)


def _monte_carlo(problem: _Problem, st: _State, data: _Data, layout: dict | None,
                 extra: np.ndarray, instrument: InstrumentProfile, M: int,
                 rng: np.random.Generator, free: list[str], gain: np.ndarray) -> np.ndarray:
    """(M, 6 S' + clocks) left perturbations and clock-offset errors of the refitted samples
    (docs/calibration.md#covariance)."""
    smp = problem.samples
    stations = problem.stations
    # every draw first, in a fixed order: the GP errors per window and prism, the nuisance
    # parameters' prior observations, the GCP shots
    p = data.p
    if smp is not None:
        e = np.zeros((M,) + smp.xyz.shape)
        for idx, G in zip(smp.windows, smp.window_cov, strict=True):
            m = idx.size
            for i in range(G.shape[0]):
                cov = np.swapaxes(G[i], 1, 2).reshape(3 * m, 3 * m)  # (a, x), (b, y)
                e[:, idx, i] = sample_gaussian(cov, M, rng).reshape(M, m, 3)
        p = data.p + e
    z_obs = rng.standard_normal((M, problem.k))
    shots = data.shots
    if layout is not None:
        hz, v, d = sample_polar_errors(layout["hz"], layout["v"], layout["d"], instrument, M, rng)
        shots = polar_to_cartesian(hz, v, d)
        if extra.any():
            shots = shots + rng.standard_normal(shots.shape) * np.sqrt(extra[[0, 0, 1]])
    # refits, in chunks that keep the residuals' intermediate arrays near 2e7 numbers
    rows = problem.distance_rows_count + (0 if layout is None else 3 * layout["index"].size)
    chunk = max(1, int(2e7 // max(1, rows * 12)))
    out = []
    for a in range(0, M, chunk):
        sl = slice(a, min(M, a + chunk))
        m = sl.stop - sl.start
        s0 = _State(*(np.repeat(x, m, axis=0) for x in (st.R, st.t, st.psi, st.clock, st.x,
                                                         st.z)))
        dm = _Data(p[sl] if p.shape[0] > 1 else p, data.d_ref,
                   shots[sl] if shots.shape[0] > 1 else shots, z_obs[sl])
        sm = _gauss_newton(problem, s0, dm, MC_ITERATIONS, gain)
        parts = []
        for s in free:
            si = stations.index(s)
            parts.append(perturbation(st.R[0, si], st.t[0, si], sm.R[:, si], sm.t[:, si]))
        for s in free:
            si = stations.index(s)
            if problem.clock_col[si] >= 0:
                parts.append(sm.clock[:, si:si + 1] - st.clock[0, si])
        out.append(np.concatenate(parts, axis=1))
    return np.concatenate(out, axis=0)
