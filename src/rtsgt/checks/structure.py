"""Self-check of the structure of the inter-prism distance residuals: clocks and prism errors.

The residuals ``r_ij(t) = |q_i - q_j| - |r_i - r_j|`` are regressed, by generalised least
squares with the run's own covariance ``V = S + G G^T`` (the GPs' block-diagonal part and
the errors shared by the run), on clock offsets per window of motion (``clock``) and on
harmonics of each prism's viewing angle against placebo harmonics (``prism_orientation``).
Both tests are one-sided at ``TEST_LEVEL``. The viewing angles come from the closed-form
registration, never from the weighted one. Method, derivation and measurements:
docs/self-checks.md#inter-prism-residual-structure.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats
from scipy.linalg import solve_triangular

from rtsgt.checks.distances import MIN_POSES as DISTANCE_MIN_POSES
from rtsgt.checks.distances import STATIC_SPEED_M_S, pose_speed
from rtsgt.errors import RtsgtWarning
from rtsgt.interpolation.cross import gp_joint_covariance
from rtsgt.interpolation.prisms import gp_velocities
from rtsgt.parallel import available_cores
from rtsgt.pose.registration import register
from rtsgt.shared import prism_shared_factor, reference_factor, select_prisms

__all__ = ["BLOCK_S", "FAMILY_LEVEL", "HARMONICS", "PLACEBO_HARMONICS", "RANK_TOL", "TEST_LEVEL",
           "WINDOW_S", "GlsTest", "gls_test", "whiten", "whitened_gls_test",
           "inter_prism_structure_check", "pair_jacobian", "run_structure_check",
           "viewing_azimuth", "viewing_span"]

#: Length of the windows of the clock offsets, s.
WINDOW_S = 10.0
#: Length of the blocks of the varying covariance where the robot moves too little for a
#: clock window, s; otherwise the blocks are the windows.
BLOCK_S = 60.0
#: Harmonics of the prism's viewing angle, cycles per turn: six corner cubes repeat every
#: 60 degrees, and the fundamental of that period and its first overtone.
HARMONICS = (6, 12)
#: Harmonics beside them that no prism of six cubes has: the scale of the smooth residuals.
PLACEBO_HARMONICS = (4, 5, 7, 8)
#: Family level of the check's two tests.
FAMILY_LEVEL = 0.95
#: The level of each (Bonferroni), one-sided.
TEST_LEVEL = 1.0 - (1.0 - FAMILY_LEVEL) / 2.0
#: Directions of the information matrix below this fraction of its largest (scaled)
#: eigenvalue are not determined by the data (well above the round-off of a Schur complement,
#: about 1e-8: docs/self-checks.md#tests-and-verdicts).
RANK_TOL = 1e-6
#: A last clock window with less motion than this share of ``WINDOW_S`` joins the one before.
MOVING_SHARE = 0.5
#: Fewest kept poses for a verdict (those of the inter-prism distance check).
MIN_POSES = DISTANCE_MIN_POSES


class GlsTest:
    """GLS estimate under ``y ~ N(0, V)`` and its score test: ``beta`` (p,) ``= N^+ s``,
    ``cov`` (p, p) ``= N^+``, ``chi2 = beta^T N beta``, ``dof`` the rank of ``N``."""

    def __init__(self, beta: np.ndarray, cov: np.ndarray, chi2: float, dof: int) -> None:
        self.beta, self.cov, self.chi2, self.dof = beta, cov, chi2, dof

    def critical(self, level: float) -> float:
        """The ``level`` quantile of ``chi2 / dof`` if ``y ~ N(0, V)``."""
        return float(stats.chi2.ppf(level, self.dof) / self.dof)


def whiten(blocks: Sequence[np.ndarray], a: ArrayLike) -> np.ndarray:
    """``L^-1 a`` (rows in the order of the blocks), ``L`` the block-diagonal lower Cholesky
    factor of ``blockdiag(blocks)``."""
    a = np.asarray(a, dtype=float)
    out = np.empty_like(a)
    start = 0
    for S in blocks:  # loop over blocks
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
    """Regress residuals ``y`` (N,) on ``X`` (N, p) by GLS with
    ``V = blockdiag(blocks) + G G^T``: ``blocks`` consecutive diagonal covariances of N rows
    in all, ``G`` (N, k) the sensitivity to k shared parameters ``N(0, I)``; nuisance ``Z``
    (N, m) is estimated along without a prior and projected out. The test of ``X`` alone."""
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
    return _schur_test(N, s, p)


def _gram_gls_test(K: np.ndarray, y: int, g: np.ndarray, x: np.ndarray,
                   z: np.ndarray | None = None) -> GlsTest:
    """:func:`whitened_gls_test` from the Gram matrix ``K = W^T W`` of the whitened columns
    ``W``: ``y``, ``g``, ``x``, ``z`` are the indices of the residuals, the shared columns, the
    regressors and the nuisance regressors in ``W`` (every product the test needs is an entry
    of ``K``)."""
    p = len(x)
    if p == 0:
        return GlsTest(np.zeros(0), np.zeros((0, 0)), 0.0, 0)
    xz = np.asarray(x) if z is None or len(z) == 0 else np.r_[x, z]
    M = np.eye(len(g)) + K[np.ix_(g, g)]
    GX, Gy = K[np.ix_(g, xz)], K[g, y]
    N = K[np.ix_(xz, xz)] - GX.T @ np.linalg.solve(M, GX)
    s = K[xz, y] - GX.T @ np.linalg.solve(M, Gy)
    return _schur_test(N, s, p)


def _schur_test(N: np.ndarray, s: np.ndarray, p: int) -> GlsTest:
    """The test of the first ``p`` coefficients from the information ``N`` and the score ``s``
    of ``[X Z]``: ``Z`` projected out (the Schur complement)."""
    if N.shape[0] > p:  # the Schur complement: Z projected out
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
    """Distances ``d`` (T, P) of the ``P = n (n - 1) / 2`` prism pairs ``i < j`` of ``xyz``
    (T, n, 3), m, their Jacobian ``H = dd/dq`` (T, P, 3n) and the ``pairs``."""
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
    """Azimuth (T, n), rad, in the body frame ``R_world_body`` (T, 3, 3), of the direction
    from each prism ``xyz`` (T, n, 3) to its station ``station_xyz`` (n, 3), m."""
    los = np.asarray(station_xyz, dtype=float)[None] - np.asarray(xyz, dtype=float)
    body = np.einsum("tji,tnj->tni", np.asarray(R_world_body, dtype=float), los)
    return np.arctan2(body[..., 1], body[..., 0])


def viewing_span(alpha: ArrayLike) -> float:
    """Span of the viewing angles ``alpha`` (rad, in time order), unwrapped along the time:
    what the angle swept, more than a turn when the robot turned more than once."""
    a = np.unwrap(np.asarray(alpha, dtype=float))
    return float(a.max() - a.min()) if a.size else 0.0


def _runs(t: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive) indices of the poses in consecutive intervals of
    ``length`` from the first pose."""
    if t.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    k = np.floor((t - t[0]) / length).astype(int)
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    return starts, np.r_[starts[1:], t.size].astype(int)


def _blocks(t: np.ndarray, starts: np.ndarray, ends: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive) indices of the blocks of the varying covariance: the clock
    test's windows (``starts``, ``ends``: every pose is in one), or intervals of ``BLOCK_S``
    where there are none."""
    return (starts, ends) if starts.size else _runs(t, BLOCK_S)


def _settings(poses: int) -> dict[str, Any]:
    """The JSON head of the check: what it computes and its settings."""
    return {"statistic": "GLS regression of the inter-prism distance residuals on clock "
                         "offsets per window of motion (chi2 / dof, 1 if the covariance is "
                         "honest) and on harmonics of each prism's viewing angle against "
                         "placebo harmonics (F, 1 without a prism error)",
            "window_s": WINDOW_S, "blocks": f"the clock windows ({BLOCK_S:g} s without them)",
            "harmonics_per_turn": list(HARMONICS),
            "placebo_harmonics_per_turn": list(PLACEBO_HARMONICS),
            "family_level": FAMILY_LEVEL, "poses": int(poses)}


def _without_verdicts(clock: str | None, orientation: str | None) -> dict[str, Any]:
    """Both tests without a verdict, saying why."""
    empty = _verdict(GlsTest(np.zeros(0), np.zeros((0, 0)), 0.0, 0), TEST_LEVEL)
    return {"clock": {**empty, "verdict": clock},
            "prism_orientation": {**empty, "verdict": orientation}}


def _verdict(test: GlsTest, level: float) -> dict[str, Any]:
    """The JSON of a chi-square test and its one-sided verdict at ``level``."""
    if test.dof == 0:
        return {"dof": 0, "chi2": None, "chi2_per_dof": None, "p_value": None,
                "level": level, "critical": None, "verdict": None}
    crit = test.critical(level)
    ratio = test.chi2 / test.dof
    # the p-value of the rounded chi2: its last bits follow the BLAS's order of summation
    # (threads), and a run's summary must not
    chi2 = round(test.chi2, 3)
    return {"dof": test.dof, "chi2": chi2, "chi2_per_dof": round(ratio, 4),
            "p_value": float(stats.chi2.sf(chi2, test.dof)), "level": level, "critical": crit,
            "verdict": "optimistic" if ratio > crit else "consistent"}


def inter_prism_structure_check(
    t: ArrayLike, xyz: ArrayLike, R_world_body: ArrayLike, velocity: ArrayLike,
    station_xyz: ArrayLike, stations: Sequence[str], varying_cov: Callable[[int, np.ndarray],
                                                                           np.ndarray],
    shared_factor: ArrayLike, shared_names: Sequence[str], reference_xyz: ArrayLike,
    reference_factor: ArrayLike, names: Sequence[str], *, time_sync_sigma_s: float,
    warn: bool = True,
) -> dict[str, Any]:
    """The structure self-check of a run's inter-prism distances.

    Takes the kept poses' times ``t`` (T,), s; the prisms ``xyz`` (T, n, 3), m, world; the
    rotations ``R_world_body`` (T, 3, 3) the viewing angles are read from (not a function of
    the residuals: the closed-form fit, or the truth); the GP ``velocity`` (T, n, 3), m/s;
    each prism's station position ``station_xyz`` (n, 3) and id ``stations``;
    ``varying_cov(i, times)`` -> (m, m, 3, 3), prism ``i``'s joint GP covariance;
    ``shared_factor`` (T, 3n, k) with its ``shared_names`` (clock ones start with
    ``time_sync``); the surveyed prisms ``reference_xyz`` (n, 3) and ``reference_factor``
    (3n, k_r); the prism ``names``; the model's clock sigma ``time_sync_sigma_s``, s.
    Returns the JSON-ready ``clock`` and ``prism_orientation`` tests (statistic, dof,
    critical value, verdict ``consistent`` / ``optimistic`` or why there is none, offsets per
    station pair and window, harmonic amplitudes) and the settings; ``warn``: one
    :class:`~rtsgt.errors.RtsgtWarning` per optimistic test.
    """
    t = np.asarray(t, dtype=float)
    q = np.asarray(xyz, dtype=float)
    T, n, _ = q.shape
    stations = [str(s) for s in stations]
    out, level = _settings(T), TEST_LEVEL
    if T < MIN_POSES:
        return out | _without_verdicts("too few poses", "too few poses")
    if len(set(stations)) < 2:  # one clock: nothing to compare it with
        return out | _without_verdicts("too few stations", None)
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
    Vc, window, clock_info, starts, ends = _clock_regressors(t, q, H, per_station)
    Xo, orient_info, labels = _orientation_regressors(q, H, R_world_body, station_xyz, names,
                                                      HARMONICS)
    Xp, _, _ = _orientation_regressors(q, H, R_world_body, station_xyz, names,
                                       PLACEBO_HARMONICS)
    # whiten once, block by block: the residuals, the shared columns, the three sets of
    # regressors; the tests need only the Gram matrix of the whitened columns
    dense = np.concatenate([y[:, None], G, Xo, Xp], axis=1)
    K = _whitened_gram(t, H, _blocks(t, starts, ends), varying_cov, n, dense, Vc, window)
    k, po, pp, nd, m = G.shape[1], Xo.shape[1], Xp.shape[1], dense.shape[1], Vc.shape[1]
    cols = {"g": 1 + np.arange(k), "o": 1 + k + np.arange(po), "p": 1 + k + po + np.arange(pp),
            "c": nd + np.arange(starts.size * m)}
    cols["run"] = nd + starts.size * m + np.arange(m)  # the clock columns summed over windows
    out["prism_orientation"] = _orientation(K, cols, orient_info, labels, level)
    # the prisms' harmonics leave the clock test only where the orientation test found them
    found = out["prism_orientation"]["verdict"] == "optimistic"
    out["clock"] = _clock(t, starts, ends, per_station, K, cols, is_ts,
                          cols["o"] if found else None, clock_info, time_sync_sigma_s, level)
    if warn:
        _warn(out, level)
    return out


def _warn(out: dict[str, Any], level: float) -> None:
    """One warning per test of ``out`` judged optimistic (at the check's caller)."""
    ck, po = out["clock"], out["prism_orientation"]
    if ck["verdict"] == "optimistic":
        warnings.warn(
            f"self-check, inter-prism residual structure: the clock offsets change over the "
            f"run or exceed the noise model (chi2 / dof = {ck['chi2_per_dof']:.2f} over "
            f"{ck['dof']} dof, above {ck['critical']:.2f}, its {level:.1%} quantile): a "
            "drifting or re-synchronised clock; the covariance is too small",
            RtsgtWarning, stacklevel=3)
    if po["verdict"] == "optimistic":
        warnings.warn(
            f"self-check, inter-prism residual structure: the residuals follow the prisms' "
            f"orientation (F = {po['f']:.2f} over {po['dof']} and {po['placebo_dof']} dof, "
            f"above {po['critical']:.2f}, its {level:.1%} quantile): an orientation-"
            "dependent prism error; the covariance is too small", RtsgtWarning,
            stacklevel=3)


def _whitened_gram(t, H, bounds, varying_cov, n, dense, Vc, window) -> np.ndarray:
    """Gram matrix ``W^T W`` of the whitened columns ``W = L^-1 [dense, X_c, X_run]``,
    block by block of the varying covariance (``bounds``: their first and last (exclusive)
    poses); ``X_c``: the clock columns, ``Vc`` (T P, m) on the poses of each window
    (``window``: (T,) index of each pose's window, or None without windows), zero elsewhere;
    ``X_run``: their sum over the windows. A window's columns are whitened only on the blocks
    it touches (for the windows, its own), so no (T P, windows m) array is made."""
    T, P = H.shape[:2]
    nd, m = dense.shape[1], Vc.shape[1]
    nw = 0 if window is None else int(window.max(initial=-1)) + 1
    K = np.zeros((nd + nw * m, nd + nw * m))

    def block(a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        S = np.zeros((b - a, b - a, P, P))  # H_a C_ab H_b^T, summed over the prisms
        for i in range(n):
            Hi = H[a:b, :, 3 * i:3 * i + 3]
            S += Hi[:, None] @ varying_cov(i, t[a:b]) @ np.swapaxes(Hi, 1, 2)[None]
        L = _cholesky(S.transpose(0, 2, 1, 3).reshape((b - a) * P, (b - a) * P))
        cs = np.zeros(0, int) if window is None else np.unique(window[a:b])
        Xc = np.zeros((b - a, P, cs.size, m))
        for j, c in enumerate(cs):
            on = window[a:b] == c
            Xc[on, :, j] = Vc.reshape(T, P, m)[a:b][on]
        W = solve_triangular(L, np.concatenate(
            [dense[a * P:b * P], Xc.reshape((b - a) * P, -1)], axis=1), lower=True)
        idx = np.r_[np.arange(nd), nd + (cs[:, None] * m + np.arange(m)).ravel()].astype(int)
        return idx, W.T @ W

    # the blocks in threads (numpy releases the interpreter lock), summed in their order
    with ThreadPoolExecutor(max_workers=available_cores()) as ex:
        for idx, gram in ex.map(block, *bounds):
            K[np.ix_(idx, idx)] += gram
    # the columns summed over the windows: K E and E^T K E, E the sum
    E = np.zeros((K.shape[0], m))
    E[nd:] = np.tile(np.eye(m), (nw, 1))
    KE = K @ E
    return np.block([[K, KE], [KE.T, E.T @ KE]])


def _clock_regressors(t, q, H, per_station):
    """The offsets relative to the first station, one pair per window of ``WINDOW_S`` of
    motion (module docstring): their columns in compact form, ``H v`` of each other station,
    (T P, S - 1), with each pose's window ((T,), or None without windows; the column of window
    ``c`` and station ``s`` is that of ``s`` on the window's poses, zero elsewhere), and the
    windows' first and last (exclusive) poses."""
    T, P = H.shape[:2]
    ids = list(per_station)
    moving = pose_speed(t, q.mean(axis=1)) >= STATIC_SPEED_M_S
    step = float(np.median(np.diff(t))) if T > 1 else 0.0
    motion = np.cumsum(moving * step)  # time in motion up to each pose
    window = np.floor(np.maximum(motion - 0.5 * step, 0.0) / WINDOW_S).astype(int)
    n = int(window.max(initial=-1)) + 1
    if n and motion[-1] - (n - 1) * WINDOW_S < MOVING_SHARE * WINDOW_S:
        window[window == n - 1] = n - 2  # a last window short of motion joins the one before
        n -= 1
    if n <= 0 or motion[-1] < MOVING_SHARE * WINDOW_S:
        starts = ends = np.zeros(0, int)
    else:
        starts = np.flatnonzero(np.r_[True, window[1:] != window[:-1]])
        ends = np.r_[starts[1:], T].astype(int)
    which = (np.searchsorted(starts, np.arange(T), side="right") - 1) if starts.size else None
    V = np.zeros((T, P, len(ids) - 1))
    for m, s in enumerate(ids[1:]):
        V[:, :, m] = per_station[s]
    info = {"reference_station": ids[0], "windows": int(starts.size),
            "moving_s": round(float(motion[-1]) if T else 0.0, 1)}
    return V.reshape(T * P, -1), which, info, starts, ends


def _clock(t, starts, ends, per_station, K, cols, is_ts, Xo, info, sigma_ts,
           level) -> dict[str, Any]:
    """The clock-offset test (module docstring), on the Gram matrix ``K`` of the whitened
    columns (:func:`_whitened_gram`; ``cols``: the indices of each kind); ``per_station``:
    ``H v`` of each station's prisms, (T, P); ``Xo``: the indices of the orientation
    regressors (nuisance), or None."""
    ids = list(per_station)
    base, others = ids[0], ids[1:]
    out: dict[str, Any] = {"model_sigma_ms": 1e3 * sigma_ts, **info,
                           "prism_harmonics_removed": Xo is not None}
    test = _gram_gls_test(K, 0, cols["g"], cols["c"], Xo)
    out.update(_verdict(test, level))
    if test.dof == 0:
        out["verdict"] = "too few moving windows"
        return out
    # the data's own estimates: the model's clock prior left out
    est = _gram_gls_test(K, 0, cols["g"][~is_ts], cols["c"], Xo)
    est_run = _gram_gls_test(K, 0, cols["g"][~is_ts], cols["run"], Xo)
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
    per = [contrast(est.beta, est.cov, c * len(others)) for c in range(len(starts))]
    out["by_window"] = {  # columns: one value per window
        "t_start": [float(t[a]) for a in starts], "t_end": [float(t[b - 1]) for b in ends],
        "offsets_ms": {k: [round(w[k][0], 3) for w in per] for k in run},
        "sigma_ms": {k: [round(w[k][1], 3) for w in per] for k in run}}
    return out


def _orientation_regressors(q, H, R_world_body, station_xyz, names, harmonics):
    """Columns of the ``harmonics`` of each prism's viewing angle, (T P, m), with the spans
    of the angles and the columns' labels."""
    T, P = H.shape[:2]
    n = q.shape[1]
    o = np.asarray(station_xyz, dtype=float)
    alpha = viewing_azimuth(q, R_world_body, o)
    los = q - o[None]
    los /= np.linalg.norm(los, axis=-1, keepdims=True)
    across = np.cross(np.array([0.0, 0.0, 1.0]), los)
    across /= np.maximum(np.linalg.norm(across, axis=-1, keepdims=True), np.finfo(float).tiny)
    cols, labels = [], []
    span = {}
    for i in range(n):
        cov_i = viewing_span(alpha[:, i])
        span[str(names[i])] = round(float(np.degrees(cov_i)), 1)
        Hi = H[:, :, 3 * i:3 * i + 3]
        if cov_i < 2 * np.pi / min(HARMONICS):
            continue  # not one period of the prism's pattern
        for k in harmonics:
            for trig, f in (("sin", np.sin), ("cos", np.cos)):
                for comp, e in (("range", los[:, i]), ("across", across[:, i])):
                    cols.append(np.einsum("tpx,tx->tp", Hi, e * f(k * alpha[:, i])[:, None]))
                    labels.append((str(names[i]), k, comp, trig))
    X = np.stack(cols, axis=-1).reshape(T * P, -1) if cols else np.zeros((T * P, 0))
    return X, {"viewing_span_deg": span}, labels


def _orientation(K, cols, info, labels, level) -> dict[str, Any]:
    """The prism-orientation test (module docstring), on the Gram matrix ``K`` of the
    whitened columns (``cols``: the indices of each kind): the clock regressors as nuisance,
    the placebo harmonics as the scale."""
    out: dict[str, Any] = dict(info)
    test = _gram_gls_test(K, 0, cols["g"], cols["o"], cols["c"])
    placebo = _gram_gls_test(K, 0, cols["g"], cols["p"], np.r_[cols["c"], cols["o"]])
    out.update(_verdict(test, level))
    if test.dof == 0 or placebo.dof == 0:
        out["verdict"] = "too few orientations"
        return out
    scale = placebo.chi2 / placebo.dof
    f = (test.chi2 / test.dof) / scale if scale > 0 else np.inf
    crit = float(stats.f.ppf(level, test.dof, placebo.dof))
    out.update(placebo_dof=placebo.dof, placebo_chi2_per_dof=round(scale, 4),
               f=round(float(f), 4), p_value=float(stats.f.sf(f, test.dof, placebo.dof)),
               critical=crit, verdict="optimistic" if f > crit else "consistent")
    inflate = max(1.0, scale)  # the residuals' own scale in the band, where larger
    amp: dict[str, dict[str, dict[str, float]]] = {}
    for m in range(0, len(labels), 4):  # the four columns of a prism and harmonic
        prism, k, _, _ = labels[m]
        entry = {}
        for c, comp in enumerate(("range", "across")):
            idx = [m + c, m + 2 + c]  # sin, cos
            b = test.beta[idx]
            entry[f"{comp}_mm"] = round(1e3 * float(np.hypot(*b)), 3)
            entry[f"{comp}_sigma_mm"] = round(1e3 * float(np.sqrt(
                inflate * np.trace(test.cov[np.ix_(idx, idx)]) / 2)), 3)
        amp.setdefault(prism, {})[f"k{k}"] = entry
    out["amplitudes"] = amp
    return out


def run_structure_check(prisms, gps, tracks, calibration, coupling, reference, keep,
                        noise_model, gp_noise: str = "white", *,
                        warn: bool = True) -> dict[str, Any]:
    """:func:`inter_prism_structure_check` on the pipeline's quantities: ``prisms``
    (PrismsAtTimes at every query time), their ``gps`` and ``tracks`` (dicts in that order),
    the ``calibration`` and its ``coupling`` (or None), the tracked ``reference``, ``keep``
    (T_all,) bool, the run's ``noise_model`` (its clock prior). Not made with
    ``gp_noise = "all"`` (the shared errors are inside the GPs' covariance)."""
    if gp_noise != "white":
        return {"verdict": None, "note": "not made: the GPs were given every noise source "
                                         "(gp_noise = 'all'), the shared errors are not apart"}
    idx = np.flatnonzero(keep)
    if idx.size < MIN_POSES:
        return _settings(idx.size) | _without_verdicts("too few poses", "too few poses")
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
    # the viewing angles from the closed-form fit, whatever the run's (module docstring)
    R_world_body, _ = register(np.broadcast_to(reference.xyz, kept.xyz.shape), kept.xyz)
    return inter_prism_structure_check(
        kept.t, kept.xyz, R_world_body, velocity,
        np.array([origins[s] for s in stations]), stations,
        lambda i, tau: gp_joint_covariance(gp_list[i], tau), F, f_names, reference.xyz, A,
        reference.names, time_sync_sigma_s=sigma, warn=warn)
