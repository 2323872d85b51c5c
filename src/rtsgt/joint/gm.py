"""First-order Gauss-Markov measurement noise, carried as states of the joint trajectory's knots.

Per station and channel (Hz, V, d) a chain ``g(t)``, ``E[g(t) g(t + h)] = sigma^2
exp(-|h| / tau)``, sampled at every knot and added to that station's measurements; ``sigma`` and
``tau`` from the joint posterior (Newton's steps with Louis' observed information):
docs/joint.md#gauss-markov-noise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import solve_banded

from rtsgt.joint.noise import CHANNELS, MIN_REDUNDANCY

#: A chain's starting sigma, as a share of its channel's datasheet sigma (median over the
#: station's measurements): the datasheet's white sigma covers the white and the correlated
#: parts together.
START_SHARE = 0.5
#: A chain's starting correlation time, s.
START_TAU_S = 3.0
#: Correlation times searched (log-spaced grid), s.
TAU_RANGE_S = (0.05, 600.0)
TAU_GRID = 97
#: Largest change of ``log sigma^2`` or ``log tau`` in one update.
MAX_LOG_STEP = float(np.log(4.0))
#: Posterior draws of each chain for its observed information (Louis' identity).
N_DRAWS = 200
#: Smallest sigma of a chain, as a share of its start (a chain the data drive to 0 stays a
#: stiff, positive definite prior).
SIGMA_FLOOR_SHARE = 1e-3


@dataclass(frozen=True)
class GaussMarkov:
    """The chains' parameters: ``sigma`` (S, 3) in the channels' units (rad, rad, m),
    ``tau_s`` (S, 3) s, per station (the problem's order) and channel (:data:`CHANNELS`);
    ``start`` (S, 3) the starting sigmas; ``determined`` (S, 3) the chains estimated (the others
    follow EM's steps while the loop runs, :func:`update`, and are left out of its last solve,
    :func:`without_undetermined`; flagged); ``sd_log`` (S, 3, 2) the standard deviations of ``log sigma``
    and ``log tau`` and ``corr`` (S, 3) their correlation (0 where not determined);
    ``redundancy`` (S, 3) each chain's prior's redundancy; ``iterations`` the updates made;
    ``stations`` (S,) their ids (where known).
    Chain ``j = 3 s + c`` is column ``j`` of the knots' Gauss-Markov states."""

    sigma: np.ndarray
    tau_s: np.ndarray
    start: np.ndarray
    determined: np.ndarray
    sd_log: np.ndarray | None = None
    corr: np.ndarray | None = None
    redundancy: np.ndarray | None = None
    iterations: int = 0
    stations: tuple[str, ...] = ()

    @property
    def n(self) -> int:
        """Number of chains (3 per station)."""
        return self.sigma.size

    @property
    def sigma_sd(self) -> np.ndarray:
        """Standard deviations (S, 3) of ``sigma`` (first order from ``log sigma``'s)."""
        sd = np.zeros_like(self.sigma) if self.sd_log is None else self.sd_log[..., 0]
        return self.sigma * sd

    @property
    def tau_sd(self) -> np.ndarray:
        """Standard deviations (S, 3) of ``tau_s``."""
        sd = np.zeros_like(self.tau_s) if self.sd_log is None else self.sd_log[..., 1]
        return self.tau_s * sd


def start_model(var_white: np.ndarray, station: np.ndarray, n_stations: int) -> GaussMarkov:
    """Starting chains from the datasheet's white variances ``var_white`` (M, 3) of
    measurements of stations ``station`` (M,): sigma :data:`START_SHARE` of the channel's
    median datasheet sigma, tau :data:`START_TAU_S` (a station without measurements: its
    chains start at 1 and are never determined)."""
    sig = np.ones((n_stations, 3))
    for s in range(n_stations):  # a handful of stations
        on = station == s
        if on.any():
            sig[s] = START_SHARE * np.sqrt(np.median(var_white[on], axis=0))
    return GaussMarkov(sig, np.full((n_stations, 3), START_TAU_S), sig.copy(),
                       np.zeros((n_stations, 3), bool))


def chain_jacobian(station: np.ndarray, n_chains: int) -> np.ndarray:
    """``d h / d g`` (M, 3, n_chains) of measurements of stations ``station`` (M,): one on
    their station's chain of each channel."""
    J = np.zeros((station.size, 3, n_chains))
    c = np.arange(3)
    J[np.arange(station.size)[:, None], c, 3 * station[:, None] + c] = 1.0
    return J


def chain_values(g: np.ndarray, knot: np.ndarray, station: np.ndarray) -> np.ndarray:
    """The chains' values (M, 3) at measurements' knots ``knot`` (M,) of stations
    ``station`` (M,), from the knots' states ``g`` (K, n)."""
    return g[knot[:, None], 3 * station[:, None] + np.arange(3)]


def transition(dt: np.ndarray, tau: np.ndarray):
    """``phi = exp(-dt / tau)`` and ``1 - phi^2`` (K-1, n) of intervals ``dt`` (K-1,) s and
    correlation times ``tau`` (n,) s."""
    x = dt[:, None] / tau[None, :]
    return np.exp(-x), -np.expm1(-2.0 * x)


def add_prior(D: np.ndarray, U: np.ndarray, a: np.ndarray, g: np.ndarray, dt: np.ndarray,
              model: GaussMarkov, col: int) -> float:
    """Adds the chains' prior to the knots' normal equations ``D`` (K, d, d), ``U``
    (K-1, d, d), ``a`` (K, d) (in place; the chains at columns ``col + j``) and returns its
    cost: ``g_0 ~ N(0, sigma^2)``, ``g_k+1 - phi_k g_k ~ N(0, sigma^2 (1 - phi_k^2))``."""
    sigma, tau = model.sigma.ravel(), model.tau_s.ravel()
    phi, c = transition(dt, tau)
    w = 1.0 / (sigma**2 * c)
    e = g[1:] - phi * g[:-1]
    j = col + np.arange(sigma.size)
    D[:-1, j, j] += w * phi**2
    D[1:, j, j] += w
    U[:, j, j] -= w * phi
    a[:-1, j] += w * phi * e
    a[1:, j] -= w * e
    w0 = 1.0 / sigma**2
    D[0, j, j] += w0
    a[0, j] -= w0 * g[0]
    return float(np.sum(w * e**2) + np.sum(w0 * g[0] ** 2))


def _expected(g, var, cross, phi):
    """Posterior means of the squared innovations ``E[(g_k+1 - phi g_k)^2]`` (K-1, n) and of
    their posterior variances."""
    e = g[1:] - phi * g[:-1]
    v = var[1:] - 2.0 * phi * cross + phi**2 * var[:-1]
    return e**2 + v, v


def _q(log_s2, log_tau, g, var, cross, dt):
    """The expected complete-data log-likelihood of the chains (n,) (constants dropped) at
    ``log sigma^2``, ``log tau`` (n,)."""
    s2 = np.exp(log_s2)
    phi, c = transition(dt, np.exp(log_tau))
    ee, _ = _expected(g, var, cross, phi)
    return -0.5 * (np.sum(np.log(s2 * c) + ee / (s2 * c), axis=0)
                   + np.log(s2) + (g[0] ** 2 + var[0]) / s2)


def _log_params(model: GaussMarkov) -> np.ndarray:
    """``(log sigma^2, log tau)`` (n, 2) of the chains."""
    return np.stack([2.0 * np.log(model.sigma.ravel()), np.log(model.tau_s.ravel())], axis=1)


def _derivatives(x, g, var, cross, dt, h: float = 1e-3):
    """Gradient (n, 2) and Hessian (n, 2, 2) of :func:`_q` in ``x`` (n, 2) (central
    differences, step ``h``)."""
    f = {(a, b): _q(x[:, 0] + a * h, x[:, 1] + b * h, g, var, cross, dt)
         for a in (-1, 0, 1) for b in (-1, 0, 1)}  # the 3x3 stencil
    grad = np.stack([f[1, 0] - f[-1, 0], f[0, 1] - f[0, -1]], axis=1) / (2.0 * h)
    H = np.empty((x.shape[0], 2, 2))
    H[:, 0, 0] = (f[1, 0] - 2.0 * f[0, 0] + f[-1, 0]) / h**2
    H[:, 1, 1] = (f[0, 1] - 2.0 * f[0, 0] + f[0, -1]) / h**2
    H[:, 0, 1] = H[:, 1, 0] = (f[1, 1] - f[1, -1] - f[-1, 1] + f[-1, -1]) / (4.0 * h**2)
    return grad, H


def _positive(info: np.ndarray) -> np.ndarray:
    """Which 2x2 matrices (n, 2, 2) are positive definite."""
    return (info[:, 0, 0] > 0) & (info[:, 0, 0] * info[:, 1, 1] - info[:, 0, 1] ** 2 > 0)


def _em_target(g, var, cross, dt) -> np.ndarray:
    """The maximum (3, 2) of the expected complete-data log-likelihood :func:`_q` in ``(log
    sigma^2, log tau)``: ``tau`` on a log grid (:data:`TAU_RANGE_S`, :data:`TAU_GRID`) with
    ``sigma^2`` profiled out, refined by a parabola through the grid's best three."""
    n = g.shape[1]
    N = g.shape[0]
    grid = np.geomspace(*TAU_RANGE_S, TAU_GRID)
    prof = np.empty((TAU_GRID, n))
    for i, tg in enumerate(grid):  # a grid of correlation times, each vectorised
        ph, cg = transition(dt, np.full(n, tg))
        ee, _ = _expected(g, var, cross, ph)
        s2 = (np.sum(ee / cg, axis=0) + g[0] ** 2 + var[0]) / N
        prof[i] = -0.5 * (np.sum(np.log(cg), axis=0) + N * np.log(s2))
    best = np.clip(np.argmax(prof, axis=0), 1, TAU_GRID - 2)
    cols = np.arange(n)
    y0, y1, y2 = prof[best - 1, cols], prof[best, cols], prof[best + 1, cols]
    den = y0 - 2.0 * y1 + y2
    off = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
    log_tau = np.log(grid[best]) + np.clip(off, -1.0, 1.0) * np.log(grid[1] / grid[0])
    ph, cg = transition(dt, np.exp(log_tau))
    ee, _ = _expected(g, var, cross, ph)
    log_s2 = np.log((np.sum(ee / cg, axis=0) + g[0] ** 2 + var[0]) / N)
    return np.stack([log_s2, log_tau], axis=1)


def _posterior_draws(g, var, cross, rng: np.random.Generator, n_draws: int) -> np.ndarray:
    """Draws (N, n, R) of the chains at their knots from the posterior as a Gauss-Markov
    sequence with means ``g`` (N, n), variances ``var`` (N, n) and consecutive covariances
    ``cross`` (N-1, n): ``d_i+1 = a_i d_i + sqrt(q_i) eps``, ``a_i = C_i / V_i``, ``q_i =
    V_i+1 - a_i C_i``, one bidiagonal solve per chain (compiled, the draws its columns)."""
    N, n = g.shape
    a = cross / np.maximum(var[:-1], 1e-300)
    q = np.maximum(var[1:] - a * cross, 1e-12 * var[1:])
    sd = np.sqrt(np.concatenate([var[:1], q]))  # (N, n)
    eps = rng.standard_normal((N, n, n_draws))
    out = np.empty((N, n, n_draws))
    ab = np.zeros((2, N))
    ab[0] = 1.0
    for j in range(n):  # three chains
        ab[1, :-1] = -a[:, j]
        out[:, j] = solve_banded((1, 0), ab, sd[:, j, None] * eps[:, j])
    return g[:, :, None] + out


def _complete_score(x, g, dt) -> np.ndarray:
    """The complete data's score (n, 2) in ``(log sigma^2, log tau)`` of chains known at their
    knots, ``g`` (N, n), ``x`` (n, 2) (closed form of :func:`_q`'s gradient at no posterior
    variance; ``u = dt / tau``, ``d phi = phi u``, ``d c = -2 phi^2 u``)."""
    s2, tau = np.exp(x[:, 0]), np.exp(x[:, 1])
    phi, c = transition(dt, tau)
    u = dt[:, None] / tau
    e = g[1:] - phi * g[:-1]
    w = e**2 / (s2 * c)
    d_s2 = -0.5 * (np.sum(1.0 - w, axis=0) + 1.0 - g[0] ** 2 / s2)
    d_tau = np.sum(phi**2 * u / c * (1.0 - w) + e * g[:-1] * phi * u / (s2 * c), axis=0)
    return np.stack([d_s2, d_tau], axis=1)


def _observed_information(x, g, var, cross, dt, H, rng, n_draws):
    """Louis' observed information (n, 2, 2) of ``(log sigma^2, log tau)``: the complete
    data's, ``-H``, less the posterior variance of the complete data's score (over
    :func:`_posterior_draws`)."""
    n = g.shape[1]
    draws = _posterior_draws(g, var, cross, rng, n_draws)  # (N, n, R)
    flat = draws.reshape(g.shape[0], n * n_draws)
    score = _complete_score(np.repeat(x, n_draws, axis=0), flat, dt).reshape(n, n_draws, 2)
    dev = score - score.mean(axis=1, keepdims=True)
    return -H - np.einsum("nri,nrj->nij", dev, dev) / (n_draws - 1)


def update(model: GaussMarkov, moments, determined: np.ndarray | None = None,
           rng: np.random.Generator | None = None, n_draws: int = N_DRAWS,
           follow: bool = False) -> GaussMarkov:
    """One step of the chains' ``(log sigma^2, log tau)`` on their marginal likelihood, from
    the posterior at the current parameters: ``moments`` one per station (None: fewer than
    two measurements, its chains stay as they are), the posterior of its three chains at its
    measurements' knots (the complete data: the chains between them are the prior's
    interpolation and carry no information of their own), their means ``g`` (N, 3),
    variances ``var`` (N, 3), covariances of consecutive ones ``cross`` (N-1, 3) and
    intervals ``dt`` (N-1,) s.

    Newton's step on the exact score (Fisher's identity: the gradient of the expected
    complete-data log-likelihood at the current parameters) with Louis' observed information
    (``rng``'s ``n_draws`` posterior draws of each chain); where that is not positive
    definite, or without ``rng``, EM's step (:func:`_em_target`, sigma^2 by Förstner's
    variance component) and the complete data's information times the observed share (the
    prior's redundancy over its number of factors). A step is at most
    :data:`MAX_LOG_STEP`. A chain is determined once its prior's redundancy (Förstner's
    ``sum 1 - Var_post(e) / Var_prior(e)``) reaches
    :data:`rtsgt.joint.noise.MIN_REDUNDANCY` (``determined`` the chains already determined;
    None: none); the others keep their start or, with ``follow``, take EM's step (it follows
    the data however little they inform a chain and cannot overshoot; a chain started too
    small enters once its redundancy at its new sigma suffices). The standard deviations
    are the information's (0 where not determined; docs/joint.md#gauss-markov-noise)."""
    S = model.sigma.shape[0]
    sigma, tau = model.sigma.ravel(), model.tau_s.ravel()
    x = _log_params(model)
    n = sigma.size
    red, share = np.zeros(n), np.ones(n)
    H = np.broadcast_to(-np.eye(2), (n, 2, 2)).copy()
    score = np.zeros((n, 2))
    obs = np.full((n, 2, 2), np.nan)
    target = x.copy()
    for i, mom in enumerate(moments):  # a handful of stations
        if mom is None:
            continue
        g, var, cross, dt = mom
        j = slice(3 * i, 3 * i + 3)
        phi, c = transition(dt, tau[j])
        _, v = _expected(g, var, cross, phi)
        red[j] = np.sum(1.0 - v / (sigma[j] ** 2 * c), axis=0) + 1.0 - var[0] / sigma[j] ** 2
        share[j] = np.clip(red[j] / g.shape[0], 1e-3, 1.0)
        score[j], H[j] = _derivatives(x[j], g, var, cross, dt)
        known = red[j] >= MIN_REDUNDANCY
        if determined is not None:
            known |= determined.ravel()[j]
        if rng is not None:
            obs[j] = _observed_information(x[j], g, var, cross, dt, H[j], rng, n_draws)
            if _positive(obs[j]).all() and (known.all() or not follow):
                continue  # Newton's steps: EM's target is not needed
        target[j] = _em_target(g, var, cross, dt)
        e = g[1:] - phi * g[:-1]  # sigma^2 by Förstner's variance component at this tau
        quad = np.sum(e**2 / c, axis=0) + g[0] ** 2
        target[j, 0] = np.where(red[j] > 0, np.log(np.maximum(quad, 1e-300)
                                                      / np.maximum(red[j], 1e-300)), x[j, 0])
    det = red >= MIN_REDUNDANCY
    if determined is not None:
        det |= determined.ravel()
    louis = _positive(np.nan_to_num(obs, nan=-1.0))
    info = np.where(louis[:, None, None], obs, -H * share[:, None, None])
    ok = _positive(info)
    cov = np.where(ok[:, None, None], np.linalg.inv(np.where(ok[:, None, None], info,
                                                             np.eye(2))), 0.0)
    newton = np.einsum("nij,nj->ni", cov, score)
    # a chain not (yet) determined takes EM's step: it follows the data however little they
    # inform it and cannot overshoot, and enters once its redundancy at the new sigma suffices
    step = np.clip(np.where((louis & det)[:, None], newton, target - x), -MAX_LOG_STEP,
                   MAX_LOG_STEP)
    sd = np.sqrt(np.clip(np.einsum("nii->ni", cov), 0.0, None)) * np.array([0.5, 1.0])
    corr = np.where(det & ok, cov[:, 0, 1] / np.maximum(
        np.sqrt(cov[:, 0, 0] * cov[:, 1, 1]), 1e-300), 0.0)
    sd[~det] = 0.0
    moved = det | follow
    new = _with_log_params(replace(model, determined=det.reshape(S, 3)), x + step, moved)
    return replace(new, sd_log=sd.reshape(S, 3, 2), corr=corr.reshape(S, 3),
                   redundancy=red.reshape(S, 3), iterations=model.iterations + 1)


def _with_log_params(model: GaussMarkov, x: np.ndarray, moved: np.ndarray) -> GaussMarkov:
    """``model`` with the ``moved`` (n,) chains' ``(log sigma^2, log tau)`` (n, 2) set to
    ``x`` (within :data:`TAU_RANGE_S` and above the sigma floor)."""
    s2 = np.maximum(x[:, 0], 2.0 * np.log(SIGMA_FLOOR_SHARE * model.start.ravel()))
    lt = np.clip(x[:, 1], *np.log(TAU_RANGE_S))
    sigma = np.where(moved, np.exp(0.5 * s2), model.sigma.ravel()).reshape(model.sigma.shape)
    tau = np.where(moved, np.exp(lt), model.tau_s.ravel()).reshape(model.tau_s.shape)
    return replace(model, sigma=sigma, tau_s=tau)


def without_undetermined(model: GaussMarkov) -> GaussMarkov:
    """``model`` with the chains the data did not determine left out (their sigma at the
    floor): the white noise's prior, the datasheet, stands for both parts there."""
    sigma = np.where(model.determined, model.sigma, SIGMA_FLOOR_SHARE * model.start)
    return replace(model, sigma=sigma)


def log_change(old: GaussMarkov, new: GaussMarkov) -> float:
    """Largest change of a determined chain's ``log sigma`` or ``log tau``."""
    d = np.stack([np.log(new.sigma / old.sigma), np.log(new.tau_s / old.tau_s)])
    return float(np.max(np.abs(d)[:, new.determined], initial=0.0))


__all__ = ["CHANNELS", "GaussMarkov", "START_SHARE", "START_TAU_S", "TAU_RANGE_S", "add_prior",
           "chain_jacobian", "chain_values", "log_change", "start_model", "transition", "update",
           "without_undetermined"]
