r"""Self-check of the measurement noise on the run's own static stretches.

While the robot stands, a prism does not move, so the scatter of its measurements about their
mean is the measurement noise itself: a Type A evaluation (GUM) of the white part of the noise
model that the GP is given, the sources ``instrument`` and ``tilt`` of
:attr:`~rtsgt.types.PrismTrack.cov_by_source`. The systematic sources (calibration,
atmosphere) are constant over a stretch and go with its mean; the clock error moves nothing
when nothing moves. The check studies the noise of this run; it changes nothing in the run
(no constant is fitted that every deployment would then carry).

Static stretches
----------------
:func:`static_stretches`: runs of kept poses in which every prism is slower than
:data:`~rtsgt.interpolation.motion.STANDING_SPEED_M_S` (the motion prior's standing robot;
every prism, so that a robot turning on the spot is not standing), a gap between poses ending
a run, with :data:`EDGE_MARGIN_S` cut from both ends and kept if at least
:data:`MIN_STATIC_S` remain. The margin is needed: 0.05 m/s is a standing robot for the motion
prior but 20 mm per 0.4 s measurement interval here, and a robot that starts off stays below it
for up to a second while it moves by millimetres (a quintic start to 1 m/s at 0.5 m/s^2 spends
0.6 s below 0.05 m/s and moves 8 mm meanwhile), which the GP's speed shows late. Without the
margin the stretches of simulated runs overran the true stops by 0.3-1.0 s (docs/self-checks.md).

Statistics
----------
Each measurement ``x_i`` of a prism inside a stretch is split along its station's line of sight
``u_i`` (``range``) and across it (``horizontal``: ``h_i = z x u_i`` normalised; ``vertical``:
``u_i x h_i``); the stretch's mean is removed and each component is divided by its predicted
white sigma ``sqrt(e_i^T C_i e_i)`` (``C_i``: the white covariance, ``e_i`` the direction):
``z_i``, white noise of unit variance if the model is right. Per prism and component, with
``N`` samples in ``K`` stretches of ``n_k`` samples, ``m = N - K``:

- **level**: the variance ratio ``s^2 = sum z_i^2 / m``, distributed as ``chi2_m / m`` if the
  model is right. Where the noise is correlated, ``m`` is lowered in the ratio of
  :func:`~rtsgt.checks.distances.effective_sample_size` to ``N``. Above the interval the
  model's noise is too small (``optimistic``), below too large (``pessimistic``).
- **correlation**: the lag-one autocorrelation from the von Neumann ratio of successive samples
  within each stretch, ``r_1 = 1 - sum (z_{i+1} - z_i)^2 / (2 sum z_i^2)``. For white noise
  (mean removed per stretch) it has mean 0 and variance ``sum_k (n_k - 2) / (m (m + 2))``
  (``sum dz^2 - 2 sum z^2`` has mean 0 and variance ``4 sum (n_k - 2)``, and the ratio is
  independent of ``sum z^2``), and ``(1 - r_1) / 2`` is close to a symmetric beta
  distribution of that variance (von Neumann 1941; the beta approximation matches the
  simulated tail probabilities to a few per cent down to 0.3 %). Above the interval the noise
  wanders: the GP, which takes the measurements as independent, averages errors that do not
  average out (``optimistic``); below, successive errors alternate (``pessimistic``).
- **correlation time**: the noise modelled as white plus a first-order Gauss-Markov process,
  ``cov(z_i, z_j) = v ((1 - f) delta_ij + f exp(-|t_i - t_j| / tau))``, fitted by restricted
  maximum likelihood (the mean of each stretch unknown; ``v`` in closed form; ``f`` and
  ``log tau`` on a grid, then on a grid four times finer around its best point), at the
  measurements' own irregular times, with the 95 % profile-likelihood interval of ``tau``
  (open above where the noise wanders over the whole stretch). ``f`` is the correlated share
  of the variance, overstated on stretches of a few tens of samples. Both are given only
  where the correlation test finds correlation: for white noise ``f`` and ``tau`` trade off (a short ``tau`` with a large ``f``
  is white noise too) and the fit has nothing to measure. Stretches longer than
  :data:`FIT_BLOCK` samples are fitted in blocks of that size.

The family of tests (two per prism and component) is held at :data:`FAMILY_FALSE_ALARM` by
Bonferroni: each test's interval has confidence ``1 - FAMILY_FALSE_ALARM / M`` for the ``M``
tests with a verdict in the run (18 for three prisms: 99.72 %), so that a run whose noise model
is right is flagged at most 5 % of the time. Fewer than :data:`MIN_SAMPLES` samples of a prism
give no verdict (``too few samples``); without a static stretch the check says so.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

from rtsgt.checks.distances import effective_sample_size, pose_speed
from rtsgt.errors import RtsgtWarning
from rtsgt.interpolation.motion import STANDING_SPEED_M_S
from rtsgt.measurement.polar import SIGHT_COMPONENTS, sight_frames
from rtsgt.noise.sources import WHITE_NOISE_SOURCES
from rtsgt.stats import ratio_interval, ratio_verdict
from rtsgt.types import PrismTrack

__all__ = ["COMPONENTS", "EDGE_MARGIN_S", "FAMILY_FALSE_ALARM", "MIN_SAMPLES", "MIN_STATIC_S",
           "WHITE_SOURCES", "gauss_markov_fit", "lag_one_test", "static_noise_check",
           "static_stretches"]

#: Cut from both ends of a run of standing poses, s.
EDGE_MARGIN_S = 2.0
#: Shortest static stretch the check uses (after the margins), s.
MIN_STATIC_S = 5.0
#: The sources whose errors change from one measurement to the next.
WHITE_SOURCES = WHITE_NOISE_SOURCES
#: Fewest samples of a prism (over its stretches) for a verdict.
MIN_SAMPLES = 20
#: Probability that a run whose noise model is right gets any verdict but consistent.
FAMILY_FALSE_ALARM = 0.05
#: The components of a measurement: along the line of sight and across it
#: (:func:`~rtsgt.measurement.polar.sight_frames`).
COMPONENTS = SIGHT_COMPONENTS
#: Largest block of samples in the correlation-time fit.
FIT_BLOCK = 64
#: Largest correlated share ``f`` of the fit.
F_MAX = 0.99
#: Grid of the correlated share ``f``.
_F_GRID = np.linspace(0.0, F_MAX, 12)
#: Points of the ``tau`` grid (log-spaced between its bounds).
_TAU_POINTS = 24


def static_stretches(t: ArrayLike, prisms_xyz: ArrayLike) -> np.ndarray:
    """Intervals (K, 2), s, in which the robot stands (module docstring).

    Parameters
    ----------
    t : array_like, shape (T,)
        Times of the kept poses, s, increasing.
    prisms_xyz : array_like, shape (T, n, 3)
        The prisms at those times, m (a robot turning on the spot moves its prisms, not its
        origin).

    Returns
    -------
    ndarray, shape (K, 2)
        Runs of poses where every prism is slower than ``STANDING_SPEED_M_S`` (no gap of more
        than 1.5 median pose intervals inside), shortened by ``EDGE_MARGIN_S`` at both ends,
        those at least ``MIN_STATIC_S`` long.
    """
    t = np.asarray(t, dtype=float)
    q = np.asarray(prisms_xyz, dtype=float).reshape(t.size, -1, 3)
    if t.size < 2:
        return np.zeros((0, 2))
    speed = np.max([pose_speed(t, q[:, i]) for i in range(q.shape[1])], axis=0)
    still = speed < STANDING_SPEED_M_S  # NaN (a pose alone between gaps): not still
    dt = np.diff(t)
    joined = still[:-1] & still[1:] & (dt <= 1.5 * float(np.median(dt)))
    first = np.flatnonzero(still & ~np.r_[False, joined])
    last = np.flatnonzero(still & ~np.r_[joined, False])
    iv = np.column_stack([t[first] + EDGE_MARGIN_S, t[last] - EDGE_MARGIN_S])
    return iv[iv[:, 1] - iv[:, 0] >= MIN_STATIC_S]


def lag_one_test(z: ArrayLike, group: ArrayLike, confidence: float = 0.95,
                 ) -> tuple[float, tuple[float, float]]:
    """Lag-one autocorrelation of mean-removed series from their von Neumann ratio, and the
    interval it falls in with probability ``confidence`` if they are white (module docstring).

    Parameters
    ----------
    z : array_like, shape (N,)
        The series one after the other, each with its mean removed.
    group : array_like of int, shape (N,)
        Series of each sample (the samples of one series contiguous, in time order).
    confidence : float

    Returns
    -------
    r1 : float
    interval : (float, float)
    """
    z = np.asarray(z, dtype=float)
    g = np.asarray(group)
    same = g[1:] == g[:-1]
    n = np.unique(g, return_counts=True)[1]
    m = z.size - n.size
    r1 = 1.0 - float(np.sum(np.diff(z)[same] ** 2) / (2.0 * np.sum(z * z)))
    var = float(np.sum(n - 2)) / (m * (m + 2.0))
    a = 0.5 * (1.0 / var - 1.0)
    lo, hi = stats.beta.ppf([0.5 - 0.5 * confidence, 0.5 + 0.5 * confidence], a, a)
    return r1, (float(1.0 - 2.0 * hi), float(1.0 - 2.0 * lo))


def _blocks(t: np.ndarray, group: np.ndarray) -> list[np.ndarray]:
    """Index arrays of the fit's blocks: each series cut into pieces of at most FIT_BLOCK."""
    starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    ends = np.r_[starts[1:], t.size]
    return [np.arange(a, b)[k:k + FIT_BLOCK] for a, b in zip(starts, ends, strict=True)
            for k in range(0, b - a, FIT_BLOCK)]


def _reml(z: np.ndarray, t: np.ndarray, blocks: list[np.ndarray], f: np.ndarray,
          tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """-2 restricted log-likelihood (up to a constant) at the pairs ``(f, tau)`` (G,), the
    variance profiled out: ``(N - K) log(sum z^T P z) + sum (log |Q| + log 1^T Q^-1 1)``
    (``Q``: the correlation matrix of a block, ``P = Q^-1 - Q^-1 1 1^T Q^-1 / 1^T Q^-1 1``),
    and ``sum z^T P z``."""
    f = f[:, None, None]
    quad = np.zeros(f.shape[0])
    logs = np.zeros(f.shape[0])
    for idx in blocks:  # a few blocks per prism, each solved for every (f, tau) at once
        n = idx.size
        lag = np.abs(t[idx, None] - t[None, idx])
        Q = (1.0 - f) * np.eye(n) + f * np.exp(-lag / tau[:, None, None])
        rhs = np.broadcast_to(np.column_stack([z[idx], np.ones(n)]), (f.shape[0], n, 2))
        y = np.linalg.solve(Q, rhs)
        a = np.einsum("i,gi->g", z[idx], y[:, :, 0])
        b = y[:, :, 1].sum(axis=1)
        c = np.einsum("i,gi->g", z[idx], y[:, :, 1])
        quad += a - c * c / b
        logs += np.linalg.slogdet(Q)[1] + np.log(b)
    dof = t.size - len(blocks)
    return dof * np.log(quad) + logs, quad


def gauss_markov_fit(z: ArrayLike, t: ArrayLike, group: ArrayLike,
                     ) -> tuple[float, float, float | None, tuple[float, float | None] | None]:
    """White plus first-order Gauss-Markov noise fitted to mean-removed series (REML).

    Parameters
    ----------
    z : array_like, shape (N,)
        The series one after the other (each with an unknown mean).
    t : array_like, shape (N,)
        Their times, s.
    group : array_like of int, shape (N,)
        Series of each sample (contiguous, in time order).

    Returns
    -------
    v : float
        Total variance.
    f : float
        Share of it that is correlated, in [0, ``F_MAX``].
    tau : float or None
        Correlation time, s, between a quarter of the median sampling interval and the
        longest block; None where ``f = 0``.
    tau_95 : (float, float or None) or None
        Its 95 % profile-likelihood interval (the correlation times whose best ``f`` is
        within ``chi2_1(0.95) = 3.84`` of the optimum of -2 log L, on the grid); the upper
        end None where the interval reaches the longest block: the noise wanders over the
        whole stretch, and the data set no upper limit. None where ``f = 0``.
    """
    z = np.asarray(z, dtype=float)
    t = np.asarray(t, dtype=float)
    g = np.asarray(group)
    blocks = _blocks(t, g)
    same = g[1:] == g[:-1]
    dt = float(np.median(np.diff(t)[same]))
    span = max(float(t[idx[-1]] - t[idx[0]]) for idx in blocks)
    lo, hi = np.log(0.25 * dt), np.log(max(span, dt))
    f_grid, l_grid = _F_GRID, np.linspace(lo, hi, _TAU_POINTS)
    F, L = np.meshgrid(f_grid, l_grid, indexing="ij")
    cost, quad = _reml(z, t, blocks, F.ravel(), np.exp(L.ravel()))
    # the profile over f on the grid: the interval of the correlation time
    profile = cost.reshape(F.shape).min(axis=0)
    inside = np.flatnonzero(profile <= profile.min() + stats.chi2.ppf(0.95, 1))
    tau_95 = (float(np.exp(l_grid[inside[0]])),
              None if inside[-1] == l_grid.size - 1 else float(np.exp(l_grid[inside[-1]])))
    # the estimate: a grid four times finer around the grid's best point
    best = int(np.argmin(cost))
    f, log_tau = float(F.ravel()[best]), float(L.ravel()[best])
    F, L = np.meshgrid(np.clip(f + (f_grid[1] - f_grid[0]) * np.linspace(-1, 1, 9), 0.0, F_MAX),
                       np.clip(log_tau + (l_grid[1] - l_grid[0]) * np.linspace(-1, 1, 9), lo, hi),
                       indexing="ij")
    fine, fine_quad = _reml(z, t, blocks, F.ravel(), np.exp(L.ravel()))
    if fine.min() < cost[best]:
        best = int(np.argmin(fine))
        f, log_tau, quad = float(F.ravel()[best]), float(L.ravel()[best]), fine_quad
    v = float(quad[best]) / (t.size - len(blocks))  # the profiled variance
    if f == 0.0:
        return v, f, None, None
    return v, f, float(np.exp(log_tau)), tau_95


def _residuals(tr: PrismTrack, station: np.ndarray, iv: np.ndarray):
    """The prism's samples inside the stretches: times, stretch index, components z (N, 3)
    and the predicted white variances (N, 3); stretches with fewer than 3 samples left out."""
    k = np.searchsorted(iv[:, 0], tr.t, side="right") - 1
    inside = (k >= 0) & (tr.t <= iv[np.maximum(k, 0), 1])
    counts = np.bincount(k[inside], minlength=iv.shape[0])
    inside &= counts[np.maximum(k, 0)] >= 3
    t, k, xyz = tr.t[inside], k[inside], tr.xyz[inside]
    C = np.sum([tr.cov_by_source[s][inside] for s in WHITE_SOURCES if s in tr.cov_by_source],
               axis=0)
    # the mean of each stretch removed (the samples of a stretch are contiguous)
    _, first, n = np.unique(k, return_index=True, return_counts=True)
    mean = np.add.reduceat(xyz, first, axis=0) / n[:, None] if t.size else xyz
    E = sight_frames(xyz, station)
    r = np.einsum("nci,ni->nc", E, xyz - np.repeat(mean, n, axis=0))
    pred = np.einsum("nci,nij,ncj->nc", E, C, E)
    return t, k, r / np.sqrt(pred), pred


def _component(z: np.ndarray, pred: np.ndarray, t: np.ndarray, k: np.ndarray,
               confidence: float | None) -> dict[str, Any]:
    """One component of one prism: level, correlation and, where correlation is found, its
    time (module docstring)."""
    N, K = z.size, np.unique(k).size
    ratio = float(np.sum(z * z) / (N - K))
    n_eff = (N - K) * effective_sample_size(z) / N
    r1, r1_interval = lag_one_test(z, k, confidence or 0.95)
    out = {"observed_sigma_mm": float(np.sqrt(ratio * np.mean(pred))) * 1e3,
           "predicted_sigma_mm": float(np.sqrt(np.mean(pred))) * 1e3,
           "level": {"variance_ratio": ratio, "n_eff": round(float(n_eff), 1)},
           "correlation": {"lag1": r1, "correlated_fraction": None, "correlation_time_s": None,
                           "correlation_time_95_s": None}}
    if confidence is None:
        for name in ("level", "correlation"):
            out[name].update(interval=None, verdict="too few samples")
        return out
    interval = ratio_interval(n_eff, 0.5 * (1.0 - confidence))
    verdict = ratio_verdict(r1, r1_interval)
    out["level"].update(interval=list(interval), verdict=ratio_verdict(ratio, interval))
    out["correlation"].update(interval=list(r1_interval), verdict=verdict)
    if verdict != "consistent":  # white noise has no correlation time to estimate
        _, f, tau, tau_95 = gauss_markov_fit(z, t, k)
        out["correlation"].update(correlated_fraction=round(f, 3), correlation_time_s=tau,
                                  correlation_time_95_s=None if tau_95 is None else
                                  list(tau_95))
    return out


def static_noise_check(
    tracks: dict[str, PrismTrack], stations: dict[str, ArrayLike], stretches: ArrayLike, *,
    warn: bool = True,
) -> dict[str, Any]:
    """The measurement noise on the static stretches against the white noise model, per prism
    and component (module docstring).

    Parameters
    ----------
    tracks : dict str -> PrismTrack
        The measured tracks (world frame), with their station and per-source covariances.
    stations : dict str -> array_like (3,)
        Station positions (world frame), m.
    stretches : array_like, shape (K, 2)
        Static intervals (:func:`static_stretches`), s, in time order and disjoint.
    warn : bool
        One :class:`~rtsgt.errors.RtsgtWarning` per prism with a verdict other than
        consistent.

    Returns
    -------
    dict
        JSON-ready: ``stretches_s``, the limits, ``tests`` (``M``) and ``confidence`` (of
        each test's interval), and per prism ``station``, ``samples``, ``stretches`` and for
        each of ``range``, ``horizontal``, ``vertical``: ``observed_sigma_mm``,
        ``predicted_sigma_mm``, ``level`` (``variance_ratio``, ``n_eff``, ``interval``,
        ``verdict``) and ``correlation`` (``lag1``, ``interval``, ``verdict``, and where
        correlation is found ``correlated_fraction``, ``correlation_time_s`` and
        ``correlation_time_95_s``). ``note`` says why no prism has a
        result.
    """
    iv = np.asarray(stretches, dtype=float).reshape(-1, 2)
    out: dict[str, Any] = {
        "stretches_s": iv.tolist(), "standing_below_m_s": STANDING_SPEED_M_S,
        "edge_margin_s": EDGE_MARGIN_S, "min_stretch_s": MIN_STATIC_S,
        "family_false_alarm": FAMILY_FALSE_ALARM, "tests": 0, "confidence": None, "prisms": {}}
    data = {}
    for pid, tr in tracks.items():
        if (not iv.size or tr.station not in stations
                or not any(s in tr.cov_by_source for s in WHITE_SOURCES)):
            continue
        res = _residuals(tr, np.asarray(stations[tr.station], dtype=float), iv)
        if res[0].size:
            data[pid] = res
    tested = [p for p, res in data.items() if res[0].size >= MIN_SAMPLES]
    M = 2 * len(COMPONENTS) * len(tested)
    confidence = 1.0 - FAMILY_FALSE_ALARM / M if M else None
    out.update(tests=M, confidence=confidence)
    if not data:
        out["note"] = ("no static stretch" if not iv.size else
                       "no measurement inside the static stretches")
    for pid, (t, k, z, pred) in data.items():
        entry: dict[str, Any] = {"station": tracks[pid].station, "samples": int(t.size),
                                 "stretches": int(np.unique(k).size)}
        for c, name in enumerate(COMPONENTS):
            entry[name] = _component(z[:, c], pred[:, c], t, k,
                                     confidence if pid in tested else None)
        out["prisms"][pid] = entry
        bad = [f"{name} {test} {entry[name][test]['verdict']}" for name in COMPONENTS
               for test in ("level", "correlation")
               if entry[name][test]["verdict"] in ("optimistic", "pessimistic")]
        if warn and bad:
            sig = ", ".join(f"{name} {entry[name]['observed_sigma_mm']:.2f} / "
                            f"{entry[name]['predicted_sigma_mm']:.2f}" for name in COMPONENTS)
            warnings.warn(
                f"self-check, static stretches: prism {pid} (station {tracks[pid].station}, "
                f"{t.size} samples): {'; '.join(bad)} ({100 * confidence:.2f} % intervals); "
                f"scatter / predicted white sigma, mm: {sig}", RtsgtWarning, stacklevel=2)
    return out
