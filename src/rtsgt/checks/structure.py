r"""Self-check of the structure of the inter-prism distance residuals: clocks and prism errors.

The inter-prism distance check (:mod:`rtsgt.checks.distances`) looks at the size of
``r_ij(t) = |q_i - q_j| - |r_i - r_j|`` (tracked minus surveyed distance) against its
predicted variance. Two errors of a real deployment hide in the *structure* of ``r`` rather
than in its size: a station clock that drifts, and a 360-degree prism whose error follows
its orientation. This check tests for them by regression: it estimates their parameters by
generalised least squares (GLS) with the run's own covariance of the residuals, and asks
whether the estimates are what the noise model allows.

Residuals and their covariance
------------------------------
To first order, with ``u_ij`` the unit vector from prism ``j`` to prism ``i`` (``u^r_ij`` in
the survey), a displacement ``dq`` of the tracked prisms and ``dr`` of the surveyed ones move
the residual by

    dr_ij(t) = u_ij(t) . (dq_i - dq_j) - u^r_ij . (dr_i - dr_j) = H(t) dq - H_r dr .

The run predicts the errors of ``q`` and ``r`` in two parts (:mod:`rtsgt.shared`):

- **varying**: the GP posterior of each prism, correlated from pose to pose over a few
  measurements (a few seconds). Its covariance between any two times is exact
  (:func:`rtsgt.interpolation.cross.gp_joint_covariance`); the prisms' GPs are independent.
  Within a block the covariance ``S_b`` of the stacked residuals is that of the GPs mapped by
  ``H``; between blocks it is neglected. The blocks are the clock test's windows (below; ``BLOCK_S``
  where the robot does not move enough for one). Not longer: the clock regressors are constant
  within a window and jump between windows, and a covariance that carries the GP's smoothness
  across a window's edge reads that jump as information (the GP's error cannot jump), so that
  each window's offset is fixed by its edges, where the residuals are continuous, rather than
  by its poses. With blocks of 60 s the windows of one block came out with nearly the same
  offset, a drifting clock passed for a constant one, and the statistic of honest runs was far
  below its distribution (pooled ``chi2 / dof`` 0.58 with the white-noise-on-acceleration
  prior, 0.22 with the jerk prior, whose errors are smoother); with a block per window, 1.02
  and 0.98 (20 simulated deployments of 150 s each, docs/self-checks.md). The correlation of
  the GP's errors across a window's edge, over a few seconds against a window of ``WINDOW_S``
  of motion, is what is neglected.
- **shared**: one draw for the run, ``theta ~ N(0, I)`` whitened parameters (the station
  calibrations, each station's clock offset and atmospheric scale, the survey), each moving
  the prisms by the sensitivity ``F(t)`` of :func:`rtsgt.shared.prism_shared_factor` and the
  survey by :func:`rtsgt.shared.reference_factor`: ``r`` gets ``G(t) theta``,
  ``G = [H F, -H_r A_r]``, the same ``theta`` at every pose. The clock offsets' columns are
  taken along the GP velocity, ``sqrt(E[e_ts^2]) H v_s``, the same vectors as the clock
  regressors below (the factor's own, scaled from the measurements' differenced velocity,
  differ from them by noise that the GP's smooth covariance would take for information).

So the residuals ``y`` of a run (all poses and pairs) have, if the run's covariance is honest,
``y ~ N(0, V)`` with ``V = S + G G^T``. The GLS products ``X^T V^-1 y`` are computed by
whitening each block with its Cholesky factor ``L_b`` (``y~ = L^-1 y``, ``G~``, ``X~`` alike)
and Woodbury's identity, ``V^-1 = L^-T (I - G~ (I + G~^T G~)^-1 G~^T) L^-1``: the shared
errors enter exactly, as the ``k`` columns of ``G``, with no time-correlation model to choose.

The tests
---------
For regressors ``X`` (the effect's parameters) and nuisance regressors ``Z`` (estimated along,
without a prior) the GLS estimate and its covariance under the run's model are
``b = N^+ s``, ``Cov b = N^+``, with ``N`` and ``s`` the information and the score of ``X``
once ``Z`` is projected out (the Schur complement of ``[X Z]^T V^-1 [X Z]``); the statistic
``c = b^T N b`` is ``chi2_p`` if ``y ~ N(0, V)``, with ``p`` the rank of ``N`` (eigenvalues of
the scaled ``N`` above ``RANK_TOL`` of the largest). The regressors soak up whatever part of
the shared errors resembles them, and ``V`` says how much: a shared error that looks like the
effect raises ``Cov b`` instead of raising a false alarm.

Both tests are one-sided: they look for structure that the covariance does not allow
(``optimistic``: the covariance is too small); a covariance too large is the size check's
business (:mod:`rtsgt.checks.distances`). Each is made at ``1 - alpha / 2`` with
``alpha = 1 - FAMILY_LEVEL`` (Bonferroni), so an honest run fails the check in at most 5 % of
deployments.

Clock offsets (``clock``)
-------------------------
A station's clock off by ``delta_s`` (``t_true - t_recorded``) moves the prism it tracks by
``v_i delta_s`` (``v_i``: the GP velocity), so ``r_ij`` gets
``u_ij . (v_i delta_s(i) - v_j delta_s(j))``. A common offset of all clocks does not change a
distance (a rigid motion has ``u_ij . (v_i - v_j) = 0``): only the offsets relative to the
first station, ``delta_s - delta_1``, are estimated, one pair per window (columns
``X_w,s = H v_s`` on the poses of window ``w``, zero elsewhere). A window is ``WINDOW_S`` of
*motion*: the poses are cut where the time the robot has moved (speed ``STATIC_SPEED_M_S`` or
more, :func:`rtsgt.checks.distances.pose_speed`, counted at the median pose interval) passes a
multiple of ``WINDOW_S``, so every moving pose is in a window and standstills, which carry no
information (``v = 0``), cost none; a last window with less than half of ``WINDOW_S`` of motion
joins the one before. The noise model has one constant offset per station, zero-mean with
variance ``E[e_ts^2] = mu^2 + sigma^2`` (:mod:`rtsgt.noise.model`), in ``V`` through the
clock columns of ``G``; the test therefore asks at once whether the offsets stay within what
the model allows and whether they are constant over the run. A clock that drifts, or is
re-synchronised during the run, gives offsets that change from window to window. The
estimates are reported per window and for the whole run, in ms, with their sigma, with the
model's clock prior left out of ``V`` (the data's own estimates of the relative offsets).

Prism orientation (``prism_orientation``)
-----------------------------------------
A 360-degree prism is several corner cubes glued around a vertical axis; where its apparent
centre lies depends on which cube faces the station, so its error is periodic in the angle
``alpha_i`` between the station's line of sight and the prism's orientation (the robot's
heading: ``alpha_i`` is the azimuth, in the body frame of the pose, of the direction from the
prism to its station). A prism of six corner cubes (the usual 360-degree prism) repeats
itself every 60 degrees, so its error is a Fourier series in multiples of 6 cycles per turn
(orientation-dependent errors of 360-degree prisms of a few millimetres: Lackner & Lienhart
2016, "Impact of prism type and prism orientation on the accuracy of automated total station
measurements", JISDM, Vienna). The check regresses the residuals on the fundamental (6 per
turn) and its first overtone (12 per turn: the pattern is not a pure sine), ``HARMONICS``,
along the line of sight ``l_i`` (range) and across it horizontally ``c_i``: four columns per
harmonic and prism, ``H (l_i sin k alpha_i)``, ``H (l_i cos k alpha_i)``,
``H (c_i sin k alpha_i)``, ``H (c_i cos k alpha_i)``. The harmonics are fixed by the prism's
construction, not fitted to a deployment. One cycle per turn (an eccentric mounting) is left
out on purpose: along the line of sight it holds a constant and a term in the robot's heading,
which the clock offsets and the survey produce as well. A prism enters only if its viewing
angle swept at least one period of the pattern, 60 degrees (its span, unwrapped along the
time, :func:`viewing_span`).

Over a short span a harmonic is a smooth trend in time, and a smooth error that the GP's
covariance understates (a start or a stop: the motion prior's weak point) shows up in any
smooth regressor. The test therefore compares the harmonics with harmonics that no prism of
six cubes has, ``PLACEBO_HARMONICS`` (4, 5, 7, 8 per turn: as smooth, in the same band),
fitted with the prism's harmonics and the clock offsets as nuisance:
``F = (c / p) / (c_0 / p_0)``, which is ``F(p, p_0)`` distributed if the residuals have no
structure at the prism's harmonics beyond what they have beside them, whatever the scale of
the covariance in that band; the verdict is ``optimistic`` above its ``1 - alpha / 2``
quantile. The amplitudes (mm) of each prism and harmonic are reported, with sigmas scaled by
``c_0 / p_0`` where that exceeds 1.

The rotation the viewing angles are read from must not be a function of the residuals
``y`` it is regressed against: a regressor that moves with ``y`` correlates with ``y`` whatever
the prisms do. :func:`run_structure_check` therefore takes the closed-form (unweighted) fit of
the kept prisms onto the survey (:func:`rtsgt.pose.registration.register`), whatever the run's
registration. Its rotation does not move with the prisms' shape: with ``a_i = R r_i`` the
fitted survey, any displacement ``e`` of the prisms orthogonal to the rigid motions
(``sum_i e_i = 0``, ``sum_i a_i x e_i = 0``: the normal equations of the fit) leaves the fit's
cross-covariance matrix ``R^T M`` symmetric, hence the rotation exactly where it was; its own
residual is such a displacement. The distances, on the other hand, see only that part (the
distances of three or more prisms fix their shape, ``H`` vanishes on the rigid motions): the
rotation and ``y`` are read from orthogonal parts of the same data. The weighted fit
(:mod:`rtsgt.pose.weighted`) is not: with ``e_u`` the closed form's residual (the prisms'
misfit to the survey, to first order a linear function of ``y``), its rotation is the closed
form's plus the rotation part of ``K_w e_u``, ``K_w = (H_p^T W H_p)^-1 H_p^T W``, with
weights ``W`` that change from pose to pose with the time to the nearest measurement. Its
viewing angles then carry a term proportional to the residuals, and the harmonic regressors
``k cos(k alpha)`` times it: the higher the harmonic ``k``, the more, so the prism's harmonics
(up to 12 per turn) pick up more of the residuals than the placebo's (up to 8), and F grows
with the square of the misfit. Where the residuals are as small as the model says (a
millimetre) this is negligible; where they are not, it is a false alarm of exactly the kind a
self-check must not give (the figures of the real excerpt: docs/self-checks.md).

The clock test takes the prisms' harmonics out as nuisance where the orientation test finds
them (``prism_harmonics_removed``): a prism error then does not pass for clock offsets, and
where there is none the clock test keeps its power. The orientation test always takes the
clock offsets out.

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

from rtsgt.checks.distances import MIN_POSES as DISTANCE_MIN_POSES
from rtsgt.checks.distances import STATIC_SPEED_M_S, pose_speed
from rtsgt.errors import RtsgtWarning

__all__ = ["BLOCK_S", "FAMILY_LEVEL", "HARMONICS", "PLACEBO_HARMONICS", "RANK_TOL", "TEST_LEVEL",
           "WINDOW_S", "GlsTest", "gls_test", "whiten", "whitened_gls_test",
           "inter_prism_structure_check", "pair_jacobian", "run_structure_check",
           "viewing_azimuth", "viewing_span"]

#: Length of the windows of the clock offsets, s.
WINDOW_S = 10.0
#: Length of the blocks of the varying covariance (their correlation between blocks is
#: neglected) where the robot moves too little for a clock window, s; otherwise the blocks
#: are the windows (module docstring).
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
#: eigenvalue are not determined by the data. The matrix is a Schur complement, a difference
#: of nearly equal sums: its scaled eigenvalues below about 1e-8 are round-off (on the real
#: excerpt, the placebo's 48 x 48 matrix has eigenvalues from 7e-12 to 1e-8 that differ by up
#: to 4x between one and two BLAS threads, and one of them crossed the 1e-9 used before, which
#: moved its F from 1.33 to 1.36), those above 1e-7 agree to 1e-3; the rank is taken well above
#: the round-off.
RANK_TOL = 1e-6
#: A last clock window with less motion than this share of ``WINDOW_S`` joins the one before.
MOVING_SHARE = 0.5
#: Fewest kept poses for a verdict (those of the inter-prism distance check).
MIN_POSES = DISTANCE_MIN_POSES


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
    where there are none (module docstring, section Residuals and their covariance)."""
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
    """The structure self-check of a run's inter-prism distances (module docstring).

    Parameters
    ----------
    t : array_like, shape (T,)
        Times of the kept poses, s, increasing.
    xyz : array_like, shape (T, n, 3)
        The prisms at those times (world), m.
    R_world_body : array_like, shape (T, 3, 3)
        The rotations the viewing angles are read from: not a function of the residuals
        (the closed-form fit of the prisms, or the truth; not the weighted fit, module
        docstring).
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
        One :class:`~rtsgt.errors.RtsgtWarning` per test judged optimistic.

    Returns
    -------
    dict
        JSON-ready (module docstring): ``clock`` (``dof``, ``chi2``, ``chi2_per_dof``,
        ``p_value``, ``level``, ``critical`` (of ``chi2_per_dof``), ``verdict``, the windows,
        ``offsets_ms`` of the whole run per station pair (``run``, ``sigma``) and
        ``by_window``, columns of one value per window: ``t_start``, ``t_end``, and per
        station pair ``offsets_ms`` and ``sigma_ms``) and
        ``prism_orientation`` (the same for the prisms' harmonics, and ``placebo_dof``,
        ``placebo_chi2_per_dof``, ``f``, whose ``p_value`` and ``critical`` the verdict
        uses, ``viewing_span_deg`` and ``amplitudes``), and the settings. A verdict is
        ``consistent`` or ``optimistic``; ``too few moving windows`` or
        ``too few orientations`` where the data cannot tell (a robot that never moves or
        never turns).
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
        ck, po = out["clock"], out["prism_orientation"]
        if ck["verdict"] == "optimistic":
            warnings.warn(
                f"self-check, inter-prism residual structure: the clock offsets change over the "
                f"run or exceed the noise model (chi2 / dof = {ck['chi2_per_dof']:.2f} over "
                f"{ck['dof']} dof, above {ck['critical']:.2f}, its {level:.1%} quantile): a "
                "drifting or re-synchronised clock; the covariance is too small",
                RtsgtWarning, stacklevel=2)
        if po["verdict"] == "optimistic":
            warnings.warn(
                f"self-check, inter-prism residual structure: the residuals follow the prisms' "
                f"orientation (F = {po['f']:.2f} over {po['dof']} and {po['placebo_dof']} dof, "
                f"above {po['critical']:.2f}, its {level:.1%} quantile): an orientation-"
                "dependent prism error; the covariance is too small", RtsgtWarning,
                stacklevel=2)
    return out


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
    for a, b in zip(*bounds, strict=True):  # loop over blocks
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
        K[np.ix_(idx, idx)] += W.T @ W
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
    from rtsgt.pose.registration import register
    from rtsgt.shared import prism_shared_factor, reference_factor, select_prisms

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
