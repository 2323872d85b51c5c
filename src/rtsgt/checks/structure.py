r"""Self-check of the structure of the inter-prism distance residuals: clocks and prism errors.

The inter-prism distance check (:mod:`rtsgt.checks.distances`) looks at the size of
``r_ij(t) = |q_i - q_j| - |r_i - r_j|`` (tracked minus surveyed distance) against its
predicted variance. Two errors of a real deployment hide in the *structure* of ``r`` rather
than in its size, and this check tests for them by regression: it estimates their parameters
by generalised least squares (GLS) with the run's own covariance of the residuals, and asks
whether the estimates are what the noise model predicts.

Residuals and their covariance
------------------------------
To first order, with ``u_ij`` the unit vector from prism ``j`` to prism ``i`` (``u^r_ij`` in
the survey), a displacement ``dq`` of the tracked prisms and ``dr`` of the surveyed ones move
the residual by

    dr_ij(t) = u_ij(t) . (dq_i - dq_j) - u^r_ij . (dr_i - dr_j) = H(t) dq - H_r dr .

The run predicts the errors of ``q`` and ``r`` in two parts (:mod:`rtsgt.shared`):

- **varying**: the GP posterior of each prism, correlated from pose to pose over a few
  measurements. Its covariance between any two times is exact
  (:func:`rtsgt.interpolation.cross.gp_joint_covariance`); the prisms' GPs are independent.
  Within a window of ``WINDOW_S`` the covariance ``S_w`` of the stacked residuals is that of
  the GPs mapped by ``H``; between windows it is neglected (the GP correlation lasts a few
  measurement intervals, a window is tens of them).
- **shared**: one draw for the run, ``theta ~ N(0, I)`` whitened parameters (the station
  calibrations, each station's clock offset and atmospheric scale, the survey), each moving
  the prisms by the sensitivity ``F(t)`` of :func:`rtsgt.shared.prism_shared_factor` and the
  survey by :func:`rtsgt.shared.reference_factor`: ``r`` gets ``G(t) theta``,
  ``G = [H F, -H_r A_r]``, the same ``theta`` at every pose.

So the residuals ``y`` of a run (all poses and pairs) have, if the run's covariance is honest,
``y ~ N(0, V)`` with ``V = S + G G^T`` (``S`` block-diagonal by window). The GLS products
``X^T V^-1 y`` are computed by whitening each window with its Cholesky factor ``L_w``
(``y~ = L^-1 y``, ``G~``, ``X~`` alike) and Woodbury's identity,
``V^-1 = L^-T (I - G~ (I + G~^T G~)^-1 G~^T) L^-1``: the shared errors enter exactly, as the
``k`` columns of ``G``, with no time-correlation model to choose.

The test
--------
For regressors ``X`` (columns: the effect's parameters) the GLS estimate and its covariance
under the run's model are ``b = N^+ X^T V^-1 y``, ``Cov b = N^+`` with ``N = X^T V^-1 X``; the
score statistic ``c = b^T N b`` is ``chi2_p`` distributed if ``y ~ N(0, V)``, with ``p`` the
rank of ``N`` (the directions the data determine: eigenvalues of the scaled ``N`` above
``RANK_TOL`` of the largest). The regressors soak up whatever part of the shared errors
resembles them, and ``V`` says how much: a shared error that looks like the effect raises
``Cov b`` instead of raising a false alarm. ``c / p`` is compared with
``chi2_p(a / 2) / p`` and ``chi2_p(1 - a / 2) / p``: ``consistent`` inside, ``optimistic``
above (the residuals have structure the covariance does not allow: it is too small),
``pessimistic`` below (less than the covariance predicts: it is too large). The two tests
share the family level ``1 - alpha = 95 %`` by Bonferroni (``a = alpha / 2`` each), so an
honest run fails the check in at most 5 % of deployments.

Clock offsets (``clock``)
-------------------------
A station's clock off by ``delta_s`` (``t_true - t_recorded``) moves the prism it tracks by
``v_i delta_s`` (``v_i``: the GP velocity), so ``r_ij`` gets
``u_ij . (v_i delta_s(i) - v_j delta_s(j))``. A common offset of all clocks does not change a
distance (a rigid motion has ``u_ij . (v_i - v_j) = 0``): only the offsets relative to the
first station, ``delta_s - delta_1``, are estimated, one pair per window of ``WINDOW_S``
(columns ``X_w,s = H v_s`` on the poses of window ``w``, zero elsewhere). The noise model has
one constant offset per station, zero-mean with variance ``E[e_ts^2] = mu^2 + sigma^2``
(:mod:`rtsgt.noise.model`), which is in ``V`` through the shared ``time_sync`` parameters;
the test therefore asks at once whether the offsets are as large as the model allows and
constant over the run. A clock that drifts, or is re-synchronised during the run, gives
offsets that change from window to window. Windows where the robot stands carry no
information (``v = 0``) and are left out: a window enters if the robot moves (speed
``STATIC_SPEED_M_S`` or more, :func:`rtsgt.checks.distances.pose_speed`) over at least half of
its length (its moving kept poses times the median pose interval). The estimates are reported per window and for the whole run, in ms, with their
sigma, both with the model's clock prior left out of ``V`` (so they are the data's own
estimates of the relative offsets).

Prism orientation (``prism_orientation``)
-----------------------------------------
A 360-degree prism is several corner cubes glued around a vertical axis; where its apparent
centre lies depends on which cube faces the station, so its error is periodic in the angle
``alpha_i`` between the station's line of sight and the prism's orientation (the robot's
heading: ``alpha_i`` is the azimuth, in the body frame of the pose, of the direction from the
prism to its station). The error is regressed, per prism, on the harmonics ``HARMONICS`` of
``alpha_i`` (6 cycles per turn: six cubes, a 60-degree period, e.g. Lackner & Lienhart 2016,
"Impact of prism type and prism orientation on the accuracy of automated total station
measurements", JISDM; and 1 per turn: an eccentric or tilted mounting), along the line of sight
``l_i`` (range) and across it horizontally ``c_i``: four columns per harmonic and prism,
``H (l_i sin k alpha_i)``, ``H (l_i cos k alpha_i)``, ``H (c_i sin k alpha_i)``,
``H (c_i cos k alpha_i)``. The harmonics are fixed by the prism's construction, not fitted to
a deployment. A harmonic ``k`` of a prism enters only if the prism's viewing angles cover at
least one period, ``360 / k`` degrees (else it is a constant, the survey's business). The
estimated amplitudes (mm) are reported per prism and harmonic.

Neither effect changes a common translation of the robot, and neither test sees a first-order
lag common to all instruments (it moves every prism by nearly the same amount).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats
from scipy.linalg import solve_triangular

from rtsgt.checks.distances import STATIC_SPEED_M_S, pose_speed
from rtsgt.errors import RtsgtWarning
from rtsgt.stats import ratio_verdict

__all__ = ["FAMILY_LEVEL", "HARMONICS", "RANK_TOL", "WINDOW_S", "GlsTest", "gls_test",
           "inter_prism_structure_check", "pair_jacobian", "run_structure_check",
           "viewing_azimuth"]

#: Length of the windows of the clock offsets, s.
WINDOW_S = 10.0
#: Harmonics of the prism's viewing angle, cycles per turn (six corner cubes; a mounting).
HARMONICS = (1, 6)
#: Family level of the check's two tests (Bonferroni: each at ``1 - (1 - level) / 2``).
FAMILY_LEVEL = 0.95
#: Directions of the information matrix below this fraction of its largest (scaled)
#: eigenvalue are not determined by the data.
RANK_TOL = 1e-9
#: A window's clock offsets are estimated if the robot moves over at least this share of its
#: length (counting the kept poses at the median pose interval).
MOVING_SHARE = 0.5


class GlsTest:
    """GLS estimate of regression coefficients under ``y ~ N(0, V)`` and its score test.

    Attributes
    ----------
    beta : ndarray, shape (p,)
        ``N^+ X^T V^-1 y`` (module docstring).
    cov : ndarray, shape (p, p)
        ``N^+``.
    chi2 : float
        ``beta^T N beta``.
    dof : int
        Rank of ``N``.
    """

    def __init__(self, beta: np.ndarray, cov: np.ndarray, chi2: float, dof: int) -> None:
        self.beta, self.cov, self.chi2, self.dof = beta, cov, chi2, dof

    def interval(self, level: float) -> tuple[float, float]:
        """Where ``chi2 / dof`` falls with probability ``level`` if ``y ~ N(0, V)``."""
        a = 1.0 - level
        return (float(stats.chi2.ppf(a / 2, self.dof) / self.dof),
                float(stats.chi2.ppf(1 - a / 2, self.dof) / self.dof))

    def p_value(self) -> float:
        """Upper-tail probability of ``chi2`` (``chi2_dof`` distribution)."""
        return float(stats.chi2.sf(self.chi2, self.dof))


def whiten(blocks: Sequence[np.ndarray], a: ArrayLike) -> np.ndarray:
    """``L^-1 a`` (rows in the order of the blocks), ``L`` the block-diagonal lower Cholesky
    factor of ``blockdiag(blocks)``."""
    a = np.asarray(a, dtype=float)
    out = np.empty_like(a)
    start = 0
    for S in blocks:  # loop over windows
        n = S.shape[0]
        out[start:start + n] = solve_triangular(_cholesky(S), a[start:start + n], lower=True)
        start += n
    return out


def _cholesky(S: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor, with a jitter of 1e-12 of the mean variance where rounding
    leaves a covariance of nearly coincident times indefinite."""
    try:
        return np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        jitter = 1e-12 * max(float(np.trace(S)) / S.shape[0], np.finfo(float).tiny)
        return np.linalg.cholesky(S + jitter * np.eye(S.shape[0]))


def gls_test(y: ArrayLike, blocks: Sequence[np.ndarray], G: ArrayLike, X: ArrayLike,
             Z: ArrayLike | None = None) -> GlsTest:
    """Regress ``y`` on ``X`` by GLS with ``V = blockdiag(blocks) + G G^T`` (module docstring).

    Parameters
    ----------
    y : array_like, shape (N,)
        Residuals.
    blocks : sequence of ndarray (n_w, n_w)
        Covariance of the varying part, consecutive diagonal blocks of ``N`` rows in all.
    G : array_like, shape (N, k)
        Sensitivity of ``y`` to ``k`` shared parameters ``N(0, I)``.
    X : array_like, shape (N, p)
        Regressors.
    Z : array_like, shape (N, m), optional
        Nuisance regressors, estimated along (no prior) and projected out of the test: the
        statistic then tests ``X`` whatever the coefficients of ``Z``.

    Returns
    -------
    GlsTest
        For ``X`` alone (the coefficients of ``Z`` are not returned).
    """
    y = np.asarray(y, dtype=float)
    N = y.shape[0]
    parts = [y[:, None], np.asarray(G, dtype=float).reshape(N, -1),
             np.asarray(X, dtype=float).reshape(N, -1),
             np.zeros((N, 0)) if Z is None else np.asarray(Z, dtype=float).reshape(N, -1)]
    w = whiten(blocks, np.concatenate(parts, axis=1))
    k, p = parts[1].shape[1], parts[2].shape[1]
    return whitened_gls_test(w[:, 0], w[:, 1:1 + k], w[:, 1 + k:1 + k + p], w[:, 1 + k + p:])


def whitened_gls_test(yw: np.ndarray, Gw: np.ndarray, Xw: np.ndarray,
                      Zw: np.ndarray | None = None) -> GlsTest:
    """:func:`gls_test` on whitened arrays (:func:`whiten`): ``V = I + Gw Gw^T``."""
    p = Xw.shape[1]
    if p == 0:
        return GlsTest(np.zeros(0), np.zeros((0, 0)), 0.0, 0)
    XZ = Xw if Zw is None or Zw.shape[1] == 0 else np.concatenate([Xw, Zw], axis=1)
    M = np.eye(Gw.shape[1]) + Gw.T @ Gw
    GX, Gy = Gw.T @ XZ, Gw.T @ yw
    N = XZ.T @ XZ - GX.T @ np.linalg.solve(M, GX)
    s = XZ.T @ yw - GX.T @ np.linalg.solve(M, Gy)
    if XZ.shape[1] > p:  # the Schur complement: Z projected out
        Nzz_inv, _ = _pinv(N[p:, p:])
        s = s[:p] - N[:p, p:] @ Nzz_inv @ s[p:]
        N = N[:p, :p] - N[:p, p:] @ Nzz_inv @ N[p:, :p]
    cov, rank = _pinv(N)
    beta = cov @ s
    return GlsTest(beta, cov, float(s @ beta), rank)


def _pinv(N: np.ndarray) -> tuple[np.ndarray, int]:
    """Pseudo-inverse of an information matrix and its rank: the directions whose scaled
    eigenvalue is below ``RANK_TOL`` of the largest are left out (not determined by the
    data)."""
    d = np.sqrt(np.clip(np.diag(N), 0.0, None))
    d = np.where(d > 0, d, 1.0)
    w, U = np.linalg.eigh(0.5 * (N + N.T) / np.outer(d, d))
    keep = w > RANK_TOL * max(float(w.max(initial=0.0)), np.finfo(float).tiny)
    return ((U[:, keep] / w[keep]) @ U[:, keep].T) / np.outer(d, d), int(keep.sum())


def pair_jacobian(xyz: ArrayLike) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """Distances of every pair of prisms and their sensitivity to the prisms.

    Parameters
    ----------
    xyz : array_like, shape (T, n, 3)

    Returns
    -------
    d : ndarray, shape (T, P)
        ``|q_i - q_j|`` for the ``P = n (n - 1) / 2`` pairs ``i < j``, m.
    H : ndarray, shape (T, P, 3n)
        ``d d / d q``: ``u_ij`` in the columns of prism ``i``, ``-u_ij`` in those of ``j``.
    pairs : list of (i, j)
    """
    q = np.asarray(xyz, dtype=float)
    T, n, _ = q.shape
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    d = np.empty((T, len(pairs)))
    H = np.zeros((T, len(pairs), 3 * n))
    for k, (i, j) in enumerate(pairs):
        diff = q[:, i] - q[:, j]
        d[:, k] = np.linalg.norm(diff, axis=-1)
        u = diff / d[:, k, None]
        H[:, k, 3 * i:3 * i + 3] = u
        H[:, k, 3 * j:3 * j + 3] = -u
    return d, H, pairs


def viewing_azimuth(xyz: ArrayLike, R_world_body: ArrayLike, station_xyz: ArrayLike
                    ) -> np.ndarray:
    """Azimuth, in the body frame, of the direction from each prism to its station, rad.

    Parameters
    ----------
    xyz : array_like, shape (T, n, 3)
        World prism positions, m.
    R_world_body : array_like, shape (T, 3, 3)
    station_xyz : array_like, shape (n, 3)
        World position of the station tracking each prism, m.

    Returns
    -------
    ndarray, shape (T, n)
    """
    los = np.asarray(station_xyz, dtype=float)[None] - np.asarray(xyz, dtype=float)
    body = np.einsum("tji,tnj->tni", np.asarray(R_world_body, dtype=float), los)
    return np.arctan2(body[..., 1], body[..., 0])


def _covered(alpha: np.ndarray) -> float:
    """Angle covered by the directions ``alpha`` (rad): a turn minus the largest gap."""
    a = np.sort(np.mod(alpha, 2 * np.pi))
    if a.size < 2:
        return 0.0
    gaps = np.diff(np.concatenate([a, [a[0] + 2 * np.pi]]))
    return float(2 * np.pi - gaps.max())


def _verdict(test: GlsTest, level: float) -> dict[str, Any]:
    """The JSON of a test and its verdict."""
    if test.dof == 0:
        return {"dof": 0, "chi2": None, "chi2_per_dof": None, "p_value": None,
                "level": level, "interval": None, "verdict": None}
    lo, hi = test.interval(level)
    ratio = test.chi2 / test.dof
    return {"dof": test.dof, "chi2": round(test.chi2, 3), "chi2_per_dof": round(ratio, 4),
            "p_value": test.p_value(), "level": level, "interval": [lo, hi],
            "verdict": ratio_verdict(ratio, (lo, hi))}


def inter_prism_structure_check(
    t: ArrayLike, xyz: ArrayLike, R_world_body: ArrayLike, velocity: ArrayLike,
    station_xyz: ArrayLike, stations: Sequence[str], varying_cov: Callable[[int, np.ndarray],
                                                                           np.ndarray],
    shared_factor: ArrayLike, shared_names: Sequence[str], reference_xyz: ArrayLike,
    reference_factor: ArrayLike, names: Sequence[str], *, time_sync_sigma_s: float,
    warn: bool = True,
) -> dict[str, Any]:
    """The structure self-check of a run's inter-prism distances (module docstring).

    Parameters
    ----------
    t : array_like, shape (T,)
        Times of the kept poses, s, increasing.
    xyz : array_like, shape (T, n, 3)
        The prisms at those times (world), m.
    R_world_body : array_like, shape (T, 3, 3)
        The poses' rotations.
    velocity : array_like, shape (T, n, 3)
        The prisms' GP velocities, m/s.
    station_xyz : array_like, shape (n, 3)
        World position of the station tracking each prism, m.
    stations : sequence of str, length n
        The station tracking each prism.
    varying_cov : callable
        ``varying_cov(i, times)`` -> (m, m, 3, 3): the joint covariance of prism ``i``'s
        varying (GP) error at ``times`` (:func:`rtsgt.interpolation.cross.gp_joint_covariance`).
    shared_factor : array_like, shape (T, 3n, k)
        Sensitivity of the stacked prisms to the shared parameters
        (:func:`rtsgt.shared.prism_shared_factor`).
    shared_names : sequence of str, length k
        Their names (the clock parameters start with ``time_sync``).
    reference_xyz : array_like, shape (n, 3)
        Surveyed prisms (body frame), m.
    reference_factor : array_like, shape (3n, k_r)
        ``A_r A_r^T`` = the survey's covariance (:func:`rtsgt.shared.reference_factor`).
    names : sequence of str
        Prism names.
    time_sync_sigma_s : float
        The noise model's ``sqrt(E[e_ts^2])``, s (0 without the ``time_sync`` source).
    warn : bool
        One :class:`~rtsgt.errors.RtsgtWarning` per test judged optimistic or pessimistic.

    Returns
    -------
    dict
        JSON-ready: ``clock`` and ``prism_orientation`` (each: ``dof``, ``chi2``,
        ``chi2_per_dof``, ``p_value``, ``interval``, ``verdict`` and the estimates), and the
        settings.
    """
    t = np.asarray(t, dtype=float)
    q = np.asarray(xyz, dtype=float)
    T, n, _ = q.shape
    stations = [str(s) for s in stations]
    out: dict[str, Any] = {
        "statistic": "GLS regression of the inter-prism distance residuals on clock offsets "
                     "per window and on harmonics of each prism's viewing angle; chi2 / dof "
                     "is 1 if the covariance is honest",
        "window_s": WINDOW_S, "harmonics_per_turn": list(HARMONICS),
        "family_level": FAMILY_LEVEL, "poses": int(T),
    }
    level = 1.0 - (1.0 - FAMILY_LEVEL) / 2.0
    d, H, pairs = pair_jacobian(q)
    P = len(pairs)
    r = np.asarray(reference_xyz, dtype=float)
    _, Hr, _ = pair_jacobian(r[None])
    y = (d - np.linalg.norm(r[[i for i, _ in pairs]] - r[[j for _, j in pairs]], axis=1)).ravel()
    # the shared parameters: prisms' and survey's
    F = np.asarray(shared_factor, dtype=float)
    A = np.asarray(reference_factor, dtype=float)
    is_ts = np.array([s.startswith("time_sync") for s in shared_names], dtype=bool)
    # the clock offsets' prior along the GP velocity, as the regressors (module docstring)
    v = np.asarray(velocity, dtype=float)
    per_station = {s: sum(np.einsum("tpx,tx->tp", H[:, :, 3 * i:3 * i + 3], v[:, i])
                          for i, si in enumerate(stations) if si == s)
                   for s in dict.fromkeys(stations)}
    clock_prior = time_sync_sigma_s * np.stack(list(per_station.values()), axis=-1)
    G = np.concatenate([H @ F[:, :, ~is_ts], np.broadcast_to(-(Hr[0] @ A), (T, P, A.shape[1])),
                        clock_prior], axis=2).reshape(T * P, -1)
    is_ts = np.r_[np.zeros(G.shape[1] - clock_prior.shape[2], bool),
                  np.ones(clock_prior.shape[2], bool)]
    # windows and the varying covariance, block by block
    window = np.floor((t - t[0]) / WINDOW_S).astype(int) if T else np.zeros(0, int)
    starts = np.flatnonzero(np.r_[True, window[1:] != window[:-1]]) if T else np.zeros(0, int)
    ends = np.r_[starts[1:], T].astype(int)
    blocks = []
    for a, b in zip(starts, ends, strict=True):  # loop over windows
        S = np.zeros((b - a, P, b - a, P))
        for i in range(n):
            C = varying_cov(i, t[a:b])
            Hi = H[a:b, :, 3 * i:3 * i + 3]
            S += np.einsum("apx,abxq->apbq", Hi, C @ np.swapaxes(Hi, 1, 2)[None])
        blocks.append(S.reshape((b - a) * P, (b - a) * P))
    Xc, clock_info = _clock_regressors(t, q, H, per_station, starts, ends)
    Xo, orient_info, labels = _orientation_regressors(q, H, R_world_body, station_xyz, names)
    # whiten once: the residuals, the shared columns and both sets of regressors
    k, pc = G.shape[1], Xc.shape[1]
    w = whiten(blocks, np.concatenate([y[:, None], G, Xc, Xo], axis=1))
    yw, Gw, Xcw, Xow = w[:, 0], w[:, 1:1 + k], w[:, 1 + k:1 + k + pc], w[:, 1 + k + pc:]
    out["clock"] = _clock(t, starts, ends, per_station, yw, Gw, is_ts, Xcw, Xow, clock_info,
                          time_sync_sigma_s, level)
    out["prism_orientation"] = _orientation(yw, Gw, Xow, Xcw, orient_info, labels, level)
    if warn:
        for key, what in (("clock", "clock offsets"),
                          ("prism_orientation", "prism-orientation harmonics")):
            v = out[key]
            if v["verdict"] in ("optimistic", "pessimistic"):
                lo, hi = v["interval"]
                tail = ("the residuals have structure the covariance does not allow: it is too "
                        "small" if v["verdict"] == "optimistic" else
                        "less than the covariance predicts: it is too large")
                warnings.warn(
                    f"self-check, inter-prism residual structure ({what}): chi2 / dof = "
                    f"{v['chi2_per_dof']:.2f}, outside [{lo:.2f}, {hi:.2f}] ({level:.1%}, "
                    f"{v['dof']} dof); {tail}", RtsgtWarning, stacklevel=2)
    return out


def _clock_regressors(t, q, H, per_station, starts, ends) -> tuple[np.ndarray, dict]:
    """Columns of the offsets relative to the first station, per moving window, (T P, W S')."""
    T, P = H.shape[:2]
    ids = list(per_station)
    moving = pose_speed(t, q.mean(axis=1)) >= STATIC_SPEED_M_S
    step = float(np.median(np.diff(t))) if T > 1 else 0.0
    used = [w for w, (a, b) in enumerate(zip(starts, ends, strict=True))
            if step * np.count_nonzero(moving[a:b]) >= MOVING_SHARE * WINDOW_S]
    X = np.zeros((T, P, len(used), len(ids) - 1))
    for c, w in enumerate(used):  # loop over windows
        a, b = starts[w], ends[w]
        for m, s in enumerate(ids[1:]):
            X[a:b, :, c, m] = per_station[s][a:b]
    info = {"reference_station": ids[0], "windows": int(len(starts)),
            "windows_used": len(used), "used": used}
    return X.reshape(T * P, -1), info


def _clock(t, starts, ends, per_station, yw, Gw, is_ts, Xw, Xow, info, sigma_ts,
           level) -> dict[str, Any]:
    """The clock-offset test (module docstring), on whitened arrays; ``per_station``: ``H v``
    of each station's prisms, (T, P); ``Xow``: the orientation regressors (nuisance)."""
    ids = list(per_station)
    base, others, used = ids[0], ids[1:], info["used"]
    out: dict[str, Any] = {"model_sigma_ms": 1e3 * sigma_ts,
                           **{k: v for k, v in info.items() if k != "used"}}
    test = whitened_gls_test(yw, Gw, Xw, Xow)
    out.update(_verdict(test, level))
    if test.dof == 0:
        out["verdict"] = "too few moving windows"
        return out
    # the data's own estimates: the model's clock prior left out
    est = whitened_gls_test(yw, Gw[:, ~is_ts], Xw, Xow)
    est_run = whitened_gls_test(yw, Gw[:, ~is_ts],
                                Xw.reshape(-1, len(used), len(others)).sum(axis=1), Xow)
    # contrasts of every pair of stations from the offsets relative to the first
    combos = [(s, base) for s in others] + [(others[b], others[a])
                                            for a in range(len(others))
                                            for b in range(a + 1, len(others))]

    def contrast(beta, cov, offset):
        res = {}
        for s1, s0 in combos:
            g = np.zeros(beta.size)
            g[offset + others.index(s1)] = 1.0
            if s0 != base:
                g[offset + others.index(s0)] = -1.0
            res[f"{s1}-{s0}"] = (1e3 * float(g @ beta), 1e3 * float(np.sqrt(g @ cov @ g)))
        return res

    run = contrast(est_run.beta, est_run.cov, 0)
    out["offsets_ms"] = {k: {"run": round(b, 3), "sigma": round(s, 3)} for k, (b, s) in run.items()}
    rows = []
    for c, w in enumerate(used):
        a, b = starts[w], ends[w]
        cw = contrast(est.beta, est.cov, c * len(others))
        rows.append({"t_start": float(t[a]), "t_end": float(t[b - 1]),
                     "offsets_ms": {k: round(x, 3) for k, (x, _) in cw.items()},
                     "sigma_ms": {k: round(s, 3) for k, (_, s) in cw.items()}})
    out["by_window"] = rows
    return out


def _orientation_regressors(q, H, R_world_body, station_xyz, names):
    """Columns of the harmonics of each prism's viewing angle, (T P, m), with the angles
    covered and the columns' labels."""
    T, P = H.shape[:2]
    n = q.shape[1]
    o = np.asarray(station_xyz, dtype=float)
    alpha = viewing_azimuth(q, R_world_body, o)
    los = q - o[None]
    los /= np.linalg.norm(los, axis=-1, keepdims=True)
    across = np.cross(np.array([0.0, 0.0, 1.0]), los)
    across /= np.maximum(np.linalg.norm(across, axis=-1, keepdims=True), np.finfo(float).tiny)
    cols, labels = [], []
    covered = {}
    for i in range(n):
        cov_i = _covered(alpha[:, i])
        covered[str(names[i])] = round(float(np.degrees(cov_i)), 1)
        Hi = H[:, :, 3 * i:3 * i + 3]
        for k in HARMONICS:
            if cov_i < 2 * np.pi / k:
                continue
            for trig, f in (("sin", np.sin), ("cos", np.cos)):
                for comp, e in (("range", los[:, i]), ("across", across[:, i])):
                    cols.append(np.einsum("tpx,tx->tp", Hi, e * f(k * alpha[:, i])[:, None]))
                    labels.append((str(names[i]), k, comp, trig))
    X = np.stack(cols, axis=-1).reshape(T * P, -1) if cols else np.zeros((T * P, 0))
    return X, {"covered_deg": covered}, labels


def _orientation(yw, Gw, Xw, Xcw, info, labels, level) -> dict[str, Any]:
    """The prism-orientation test (module docstring), on whitened arrays; ``Xcw``: the clock
    regressors (nuisance)."""
    out: dict[str, Any] = dict(info)
    test = whitened_gls_test(yw, Gw, Xw, Xcw)
    out.update(_verdict(test, level))
    if test.dof == 0:
        out["verdict"] = "too few orientations"
        return out
    amp: dict[str, dict[str, dict[str, float]]] = {}
    for m in range(0, len(labels), 4):  # the four columns of a prism and harmonic
        prism, k, _, _ = labels[m]
        entry = {}
        for c, comp in enumerate(("range", "across")):
            idx = [m + c, m + 2 + c]  # sin, cos
            b = test.beta[idx]
            entry[f"{comp}_mm"] = round(1e3 * float(np.hypot(*b)), 3)
            entry[f"{comp}_sigma_mm"] = round(1e3 * float(np.sqrt(
                np.trace(test.cov[np.ix_(idx, idx)]) / 2)), 3)
        amp.setdefault(prism, {})[f"k{k}"] = entry
    out["amplitudes"] = amp
    return out


def run_structure_check(prisms, gps, tracks, calibration, coupling, reference, R_world_body,
                        keep, noise_model, gp_noise: str = "white", *,
                        warn: bool = True) -> dict[str, Any]:
    """:func:`inter_prism_structure_check` on the quantities of a run (the pipeline's).

    Parameters
    ----------
    prisms : rtsgt.interpolation.prisms.PrismsAtTimes
        The prisms at every query time.
    gps : dict str -> GPTrack
        The prisms' GPs, in the order of ``prisms``.
    tracks : dict str -> PrismTrack
        The prism tracks (for the station of each prism), in the same order.
    calibration : rtsgt.calibration.CalibrationResult
        The station set-ups (their positions).
    coupling : StationCoupling or None
        The joint covariance of the calibrations.
    reference : ReferencePoints
        The tracked reference prisms, in the order of the prisms.
    R_world_body : ndarray, shape (T_all, 3, 3)
        The poses' rotations at every query time.
    keep : ndarray of bool, shape (T_all,)
        The kept poses.
    noise_model : rtsgt.noise.NoiseModel
        The model of the run (its clock prior).
    gp_noise : {"white", "all"}
        What the GPs were given. With ``"all"`` the systematic sources are inside the GPs'
        covariance and cannot be told from the varying part: the check is not made.
    warn : bool
    """
    from rtsgt.interpolation.cross import gp_joint_covariance
    from rtsgt.interpolation.prisms import gp_velocities
    from rtsgt.shared import prism_shared_factor, reference_factor, select_prisms

    if gp_noise != "white":
        return {"verdict": None, "note": "not made: the GPs were given every noise source "
                                         "(gp_noise = 'all'), the shared errors are not apart"}
    idx = np.flatnonzero(keep)
    kept = select_prisms(prisms, idx)
    stations = [tracks[p].station for p in tracks]
    origins = {s: np.asarray(T.translation, dtype=float)
               for s, T in calibration.transforms.items()}
    velocity = gp_velocities(gps, kept.t)
    F, f_names = prism_shared_factor(kept, velocity, stations, origins, coupling)
    A, _ = reference_factor(reference)
    gp_list = list(gps.values())
    sigma = (float(np.sqrt(noise_model.time_sync_second_moment_s2))
             if "time_sync" in noise_model.sources else 0.0)
    return inter_prism_structure_check(
        kept.t, kept.xyz, np.asarray(R_world_body)[idx], velocity,
        np.array([origins[s] for s in stations]), stations,
        lambda i, tau: gp_joint_covariance(gp_list[i], tau), F, f_names, reference.xyz, A,
        reference.names, time_sync_sigma_s=sigma, warn=warn)
