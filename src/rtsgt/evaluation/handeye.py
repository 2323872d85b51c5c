r"""The error model of a drifting odometry, and the coarse search of its clock.

An odometry's pose error is a drift (random walks with the distance driven: of the position,
isotropic, and of the yaw about the vertical, which turns every later step) plus white noise
of each pose (position and rotation). After the alignment and the mounting, the error of pose
``k`` of :func:`~rtsgt.evaluation.mounting.fit_mounting`'s residual is ``r_k = H_k s_k + w_k``
with the drift state ``s_k = (e_k, psi_k)`` (position error, m; yaw error, rad; zero at the
first pose), ``s_{k+1} = F_k s_k + q_k`` (``e`` moved by ``psi [u]x`` of the step), ``w_k`` the
white errors and the ground truth's. The weighted least squares over the mounting, the clock
and the alignment with that covariance is a banded system (the states eliminated by a banded
Cholesky factorisation: no loop over poses); the four levels are estimated by restricted
maximum likelihood (REML) on the same factorisation. The clock is first searched over +-1 s
by correlating the rotation angle over 1 s of both trajectories (invariant to the mounting and
the alignment). Derivation and numbers: docs/evaluating.md#a-drifting-odometry. The noisy
rotations also enter the Jacobian (errors in variables): the gradient's expectation at the
truth, :func:`score_bias`, is removed by the position-only fit (docs/evaluating.md#errors-in-variables).

References: F. C. Park, B. J. Martin, IEEE Trans. Robotics and Automation 10(5), 1994 (the
hand-eye start); H. D. Patterson, R. Thompson, Biometrika 58(3), 1971 (REML); L. A.
Stefanski, Commun. Statist. Theory Meth. 18(12), 1989 (corrected score); R. N. Kackar,
D. A. Harville, JASA 79(388), 1984 (the levels' error in the covariance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.optimize import minimize

from rtsgt.errors import InputError
from rtsgt.geometry.so3 import hat, log_so3

__all__ = [
    "CLOCK_SEARCH_S",
    "ODOMETRY_COMPONENTS",
    "DriftModel",
    "coarse_clock_shift",
    "drift_model",
    "fit_levels",
    "level_covariance",
    "profile_normal",
    "score_bias",
]

#: The clock search: offsets within +-CLOCK_SEARCH_S of the given one, on a grid of
#: CLOCK_GRID_S, comparing rotation angles over CLOCK_WINDOW_S.
CLOCK_SEARCH_S = 1.0
CLOCK_GRID_S = 0.01
CLOCK_WINDOW_S = 1.0
#: The odometry's error levels estimated (standard deviations): white noise of a pose's
#: position (m) and rotation (rad, per axis); random walks of the position (m per sqrt(m)
#: driven) and of the yaw (rad per sqrt(m)).
ODOMETRY_COMPONENTS = ("white_position", "white_rotation", "drift_position", "drift_yaw")
#: Bounds of the levels (the smallest keeps the covariance positive definite).
LEVEL_BOUNDS = ((1e-5, 1.0), (1e-6, 0.2), (1e-6, 0.2), (1e-7, 0.02))
#: A step shorter than this counts as this, m (a robot standing still drifts little, not
#: nothing: the random walks stay regular).
MIN_STEP_M = 1e-3


def _window_series(t: np.ndarray, R: np.ndarray | None, p: np.ndarray | None) -> np.ndarray:
    """The rotation angle (rad) over ``CLOCK_WINDOW_S`` from each pose, or without rotations
    the distance travelled (chord)."""
    j = np.minimum(np.searchsorted(t, t + CLOCK_WINDOW_S), t.size - 1)
    if R is not None:
        return np.linalg.norm(log_so3(np.swapaxes(R, 1, 2) @ R[j]), axis=1)
    return np.linalg.norm(p[j] - p, axis=1)


def coarse_clock_shift(t: np.ndarray, gt_rotation: np.ndarray | None,
                       est_rotation: np.ndarray | None, gt_position: np.ndarray | None = None,
                       est_position: np.ndarray | None = None) -> float:
    """The shift ``s`` (s, within +-:data:`CLOCK_SEARCH_S`) to add to the clock offset: the
    maximum of the correlation of the rotation angles over 1 s (or the distances travelled,
    without rotations) of the ground truth at ``t + offset + s`` and of the estimate at ``t``.

    ``t``: (N,) the estimate's times; the ground truth's poses are at ``t + offset``. Angles
    and distances do not depend on the mounting rotation or the alignment (a Sim(3) scale
    does not change a correlation). 0 when neither series varies."""
    t = np.asarray(t, dtype=float)
    a_g = _window_series(t, gt_rotation, gt_position)
    a_e = _window_series(t, est_rotation, est_position)
    shifts = np.arange(-CLOCK_SEARCH_S, CLOCK_SEARCH_S + 0.5 * CLOCK_GRID_S, CLOCK_GRID_S)
    tq = t[None, :] + shifts[:, None]
    ok = (tq >= t[0]) & (tq <= t[-1] - CLOCK_WINDOW_S)
    g = np.interp(tq, t, a_g)
    e = np.broadcast_to(a_e, g.shape)
    cnt = ok.sum(axis=1).astype(float)
    valid = cnt > 10

    def centred(x):
        mean = np.sum(np.where(ok, x, 0.0), axis=1) / np.maximum(cnt, 1.0)
        return np.where(ok, x - mean[:, None], 0.0)

    gc, ec = centred(g), centred(e)
    den = np.sqrt(np.sum(gc * gc, axis=1) * np.sum(ec * ec, axis=1))
    corr = np.where(valid & (den > 0), np.sum(gc * ec, axis=1) / np.where(den > 0, den, 1.0),
                    -np.inf)
    k = int(np.argmax(corr))
    if not np.isfinite(corr[k]):
        return 0.0
    s = float(shifts[k])
    if 0 < k < shifts.size - 1 and np.all(np.isfinite(corr[k - 1:k + 2])):
        c0, c1, c2 = corr[k - 1:k + 2]
        curv = c0 - 2 * c1 + c2
        if curv < 0:
            s += 0.5 * CLOCK_GRID_S * (c0 - c2) / curv
    return s


# ------------------------------------------------------------------------------------------
# the odometry's error model
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DriftModel:
    """The geometry of the odometry's error at a solution (module docstring).

    Attributes
    ----------
    S : ndarray, shape (N, d, d)
        The covariance known beside it (the ground truth's, the estimate's given one); ``d``
        6 for poses, 3 for positions (the rows below cut to ``d``).
    B : ndarray, shape (N, 2, 6, 6)
        The white errors' covariance per unit level: position (m^2), rotation (rad^2), the
        latter through the lever arm too.
    H : ndarray, shape (N, 6, 4)
        ``d r_k / d s_k``.
    F : ndarray, shape (N - 1, 4, 4)
        ``s_{k+1} = F_k s_k + q_k``.
    step : ndarray, shape (N - 1,)
        Distance driven between poses, m (at least :data:`MIN_STEP_M`).
    E : ndarray, shape (N, 2, d, 3)
        ``d r_k`` per unit white error (position; rotation): ``B = E E^T``.
    """

    S: np.ndarray
    B: np.ndarray
    H: np.ndarray
    F: np.ndarray
    step: np.ndarray
    E: np.ndarray


def drift_model(S: np.ndarray, R_hat: np.ndarray, lever: np.ndarray, q: np.ndarray,
                scale: float = 1.0, up: np.ndarray | None = None) -> DriftModel:
    """The model at a solution: ``S`` (N, d, d) the covariance known, ``R_hat`` (N, 3, 3)
    the predicted body rotations, ``lever`` (3,) m, ``q`` (N, 3) the aligned sensor
    positions, m, ``scale`` the estimate's, ``up`` the vertical (world z by default)."""
    u = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=float)
    N = q.shape[0]
    arm = R_hat @ np.asarray(lever, dtype=float)
    E = np.zeros((N, 2, 6, 3))
    E[:, 0, :3] = scale * np.eye(3)
    E[:, 1, :3] = hat(arm)
    E[:, 1, 3:] = np.eye(3)
    B = E @ np.swapaxes(E, 2, 3)
    H = np.zeros((N, 6, 4))
    H[:, :3, :3] = np.eye(3)
    H[:, :3, 3] = -np.cross(u, arm)
    H[:, 3:, 3] = u
    dq = np.diff(q, axis=0)
    F = np.broadcast_to(np.eye(4), (N - 1, 4, 4)).copy()
    F[:, :3, 3] = np.cross(u, dq)
    step = np.maximum(np.linalg.norm(dq, axis=1), MIN_STEP_M)
    d = S.shape[1]
    return DriftModel(S, B[:, :, :d, :d], H[:, :d], F, step, E[:, :, :d])


def _banded(M: DriftModel, Qi: np.ndarray, HWH: np.ndarray) -> np.ndarray:
    """The states' normal matrix (block tridiagonal, 4 x 4 blocks, states 1..N-1) in the
    upper banded storage of :func:`scipy.linalg.cholesky_banded` (7 superdiagonals)."""
    m = Qi.shape[0]  # states
    Ft = np.swapaxes(M.F, 1, 2)
    diag = HWH[1:] + Qi[:, None, :] * np.eye(4)
    diag[:-1] += Ft[1:] @ (Qi[1:, :, None] * M.F[1:])
    off = -Ft[1:] * Qi[1:, None, :]  # block (k, k + 1) = -F_k^T Q_k^-1
    ab = np.zeros((8, 4 * m))
    cols = 4 * np.arange(m)
    for i in range(4):
        for j in range(4):
            if j >= i:
                ab[7 + i - j, cols + j] = diag[:, i, j]
            ab[3 + i - j, cols[1:] + j] = off[:, i, j]
    return ab


def profile_normal(M: DriftModel, levels: np.ndarray, r: np.ndarray,
                   J: np.ndarray | None = None, L: np.ndarray | None = None, *,
                   score: bool = False):
    """The weighted least squares with the drift states eliminated: ``J^T C^-1 J``,
    ``J^T C^-1 r``, ``r^T C^-1 r`` and ``log det C`` for the levels
    (:data:`ODOMETRY_COMPONENTS`, standard deviations); ``C`` also holds ``L L^T``, the
    errors all poses share (Woodbury). ``r`` (N, d), ``J`` (N, d, P), ``L`` (N, d, k). With
    ``score``, also each pose's share of the gradient, ``J_k^T (C^-1 r)_k`` (N, P)."""
    sp, sr, qp, qy = np.asarray(levels, dtype=float)
    W = M.S + sp * sp * M.B[:, 0] + sr * sr * M.B[:, 1]
    Lw = np.linalg.cholesky(0.5 * (W + np.swapaxes(W, 1, 2)))
    logdet = 2.0 * float(np.sum(np.log(np.diagonal(Lw, axis1=1, axis2=2))))
    Wi = np.linalg.inv(W)
    J = np.zeros(r.shape + (0,)) if J is None else J
    P, k = J.shape[2], 0 if L is None else L.shape[2]
    X = np.concatenate([J] + ([] if L is None else [L]) + [r[:, :, None]], axis=2)
    WiX = Wi @ X
    m = X.shape[2]
    G = X.reshape(-1, m).T @ WiX.reshape(-1, m)  # sum_k X_k^T W_k^-1 X_k
    Qvar = M.step[:, None] * np.array([qp * qp] * 3 + [qy * qy])
    logdet += float(np.sum(np.log(Qvar)))
    HWH = np.swapaxes(M.H, 1, 2) @ Wi @ M.H
    cb = cholesky_banded(_banded(M, 1.0 / Qvar, HWH), lower=False, check_finite=False)
    logdet += 2.0 * float(np.sum(np.log(cb[7])))
    Z = (np.swapaxes(M.H, 1, 2) @ WiX)[1:].reshape(-1, X.shape[2])
    Y = cho_solve_banded((cb, False), Z, check_finite=False)  # the states' response
    G -= Z.T @ Y
    a, b, c = slice(0, P), slice(P, P + k), P + k
    Mk = np.eye(k) + G[b, b]
    logdet += float(np.linalg.slogdet(Mk)[1]) if k else 0.0
    T = np.linalg.solve(Mk, G[b, :]) if k else np.zeros((0, G.shape[1]))
    Gs = G - G[:, b] @ T  # Woodbury: C^-1 = C0^-1 - C0^-1 L (I + L^T C0^-1 L)^-1 L^T C0^-1
    out = (Gs[a, a], Gs[a, c], float(Gs[c, c]), logdet)
    if not score:
        return out
    Hs = np.concatenate([np.zeros((1,) + X.shape[1:]),
                         M.H[1:] @ Y.reshape(-1, 4, X.shape[2])], axis=0)
    U = WiX - Wi @ Hs  # C0^-1 applied to every column, pose by pose
    u = U[:, :, c] - (U[:, :, b] @ T[:, c] if k else 0.0)
    return (*out, np.einsum("nip,ni->np", J, u))


def _state_covariances(cb: np.ndarray) -> np.ndarray:
    """The diagonal 4 x 4 blocks of the inverse of the states' normal matrix from its upper
    banded Cholesky factor ``U`` (:func:`_banded`): ``X_k = A_k X_{k+1} A_k^T + Q_k`` with
    ``A_k = D_k^-1 E_k``, ``Q_k = D_k^-1 D_k^-T`` (``D``, ``E`` the diagonal and upper
    blocks of ``U``), solved by doubling (log2 of the states' count vectorised steps)."""
    m = cb.shape[1] // 4
    cols = 4 * np.arange(m)
    D = np.zeros((m, 4, 4))
    E = np.zeros((m, 4, 4))
    for i in range(4):
        for j in range(4):
            if j >= i:
                D[:, i, j] = cb[7 + i - j, cols + j]
            E[:-1, i, j] = cb[3 + i - j, cols[1:] + j]
    Di = np.linalg.inv(D)
    A, Q = Di @ E, Di @ np.swapaxes(Di, 1, 2)
    s = 1
    while s < m:  # compose each map with the one s states later
        Q = np.concatenate([A[:-s] @ Q[s:] @ np.swapaxes(A[:-s], 1, 2) + Q[:-s], Q[-s:]])
        A = np.concatenate([A[:-s] @ A[s:], A[-s:]])
        s *= 2
    return Q


def score_bias(M: DriftModel, levels: np.ndarray, G: np.ndarray, Gs: np.ndarray,
               L: np.ndarray | None = None) -> np.ndarray:
    """The expectation of the weighted least squares' gradient ``J^T C^-1 r`` at the truth
    when the Jacobian ``J`` is itself noisy (errors in variables: the estimate's rotations
    turn the lever arm, its positions the alignment): ``J_k = J0_k + G_k eps_k + Gs_k s_k``
    with ``eps_k`` the white errors per unit level (of :attr:`DriftModel.E`) and ``s_k`` the
    drift state. ``G`` (N, 2, d, 3, P), ``Gs`` (N, d, 4, P), ``L`` as in
    :func:`profile_normal`. Returns (P,): ``sum_k level_c^2 tr(G_ck^T (C^-1)_kk E_ck) +
    tr(Gs_k^T (C^-1 H P)_kk)`` (``P`` the states' prior covariance). A root of the gradient
    minus it is consistent (the corrected score, docs/evaluating.md#errors-in-variables)."""
    sp, sr, qp, qy = np.asarray(levels, dtype=float)
    W = M.S + sp * sp * M.B[:, 0] + sr * sr * M.B[:, 1]
    Wi = np.linalg.inv(W)
    Qvar = M.step[:, None] * np.array([qp * qp] * 3 + [qy * qy])
    HWH = np.swapaxes(M.H, 1, 2) @ Wi @ M.H
    cb = cholesky_banded(_banded(M, 1.0 / Qvar, HWH), lower=False, check_finite=False)
    X = _state_covariances(cb)  # (N - 1, 4, 4), states 1..N-1
    WiH = Wi @ M.H
    A = Wi.copy()  # (C^-1)_kk
    A[1:] -= WiH[1:] @ X @ np.swapaxes(WiH[1:], 1, 2)
    T = np.zeros(M.H.shape)  # (C^-1 H P)_kk
    T[1:] = WiH[1:] @ X
    if L is not None and L.shape[2]:
        k = L.shape[2]
        Z = (np.swapaxes(M.H, 1, 2) @ Wi @ L)[1:].reshape(-1, k)
        Y = cho_solve_banded((cb, False), Z, check_finite=False).reshape(-1, 4, k)
        U = Wi @ L
        U[1:] -= WiH[1:] @ Y  # C0^-1 L, pose by pose
        Mk = np.eye(k) + np.einsum("nia,nib->ab", L, U)
        UM = U @ np.linalg.inv(Mk)
        A -= UM @ np.swapaxes(U, 1, 2)
        T[1:] -= UM[1:] @ np.swapaxes(Y, 1, 2)
    AE = A[:, None] @ M.E
    return (np.einsum("ncdep,ncde,c->p", G, AE, np.array([sp * sp, sr * sr]))
            + np.einsum("ndsp,nds->p", Gs, T))


def _reml(z: np.ndarray, M: DriftModel, r: np.ndarray, J: np.ndarray,
          L: np.ndarray | None) -> float:
    """-2 log of the restricted likelihood (up to a constant) at the log levels ``z``."""
    try:
        H, g, chi2, logdet = profile_normal(M, np.exp(z), r, J, L)
    except np.linalg.LinAlgError:
        return np.inf
    d = np.sqrt(np.clip(np.diagonal(H), np.finfo(float).tiny, None))
    w, V = np.linalg.eigh(H / np.outer(d, d))
    keep = w > 1e-12 * max(float(w.max()), np.finfo(float).tiny)
    gs = V[:, keep].T @ (g / d)
    return (logdet + chi2 - float(gs @ (gs / w[keep])) + float(np.sum(np.log(w[keep])))
            + 2.0 * float(np.sum(np.log(d))))


def level_covariance(M: DriftModel, r: np.ndarray, J: np.ndarray, levels: np.ndarray,
                     L: np.ndarray | None = None, h: float = 0.05) -> np.ndarray:
    """The covariance (4, 4) of the log levels of :func:`fit_levels` at its optimum
    ``levels``: twice the inverse of the restricted likelihood's Hessian (-2 log, central
    differences of step ``h`` in the log levels), with the levels at a bound of
    :data:`LEVEL_BOUNDS` held (zero rows) and directions it does not curve left out (all,
    should a step leave the positive definite covariances)."""
    z = np.log(np.asarray(levels, dtype=float))
    bounds = np.log(np.array(LEVEL_BOUNDS))
    free = np.flatnonzero((z > bounds[:, 0] + h) & (z < bounds[:, 1] - h))
    n = free.size
    out = np.zeros((4, 4))
    if n == 0:
        return out
    steps = h * np.eye(4)[free]

    def f(dz):
        return _reml(z + dz, M, r, J, L)

    f0 = f(np.zeros(4))
    fp = np.array([f(e) for e in steps])
    fm = np.array([f(-e) for e in steps])
    Hs = np.diag((fp - 2 * f0 + fm) / h**2)
    for i in range(n):
        for j in range(i + 1, n):
            a, b = steps[i], steps[j]
            Hs[i, j] = Hs[j, i] = (f(a + b) - f(a - b) - f(b - a) + f(-a - b)) / (4 * h * h)
    if not np.all(np.isfinite(Hs)):  # a step left the positive definite covariances
        return out
    w, V = np.linalg.eigh(0.5 * (Hs + Hs.T))
    keep = w > 1e-9 * max(float(w.max()), np.finfo(float).tiny)
    out[np.ix_(free, free)] = 2.0 * (V[:, keep] / w[keep]) @ V[:, keep].T
    return out


def fit_levels(M: DriftModel, r: np.ndarray, J: np.ndarray, start: np.ndarray,
               L: np.ndarray | None = None) -> np.ndarray:
    """The levels (:data:`ODOMETRY_COMPONENTS`) of restricted maximum likelihood, for the
    residuals ``r`` (N, 6) linear in the parameters through ``J`` (N, 6, P), the shared
    factor ``L`` (N, 6, k) beside, from ``start``, within :data:`LEVEL_BOUNDS`."""
    bounds = np.log(np.array(LEVEL_BOUNDS))
    z0 = np.clip(np.log(np.asarray(start, dtype=float)), bounds[:, 0], bounds[:, 1])
    res = minimize(_reml, z0, args=(M, r, J, L), method="L-BFGS-B", bounds=bounds,
                   options={"eps": 1e-6, "maxiter": 200, "ftol": 1e-12, "gtol": 1e-8})
    if not np.isfinite(res.fun):
        raise InputError("Expected positive definite covariances to estimate the mounting of "
                         "a drifting odometry")
    return np.exp(res.x)
