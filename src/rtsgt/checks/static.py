"""Self-check of the measurement noise on the run's own static stretches.

Where every prism stands (:func:`static_stretches`), the scatter of each prism's measurements
about the stretch's mean, per line-of-sight component and divided by the run's predicted
white sigma, is tested for its level (variance ratio against ``chi2_m / m``) and its lag-one
correlation (von Neumann 1941 ratio, beta approximation); where correlation is found, a
white plus Gauss-Markov correlation time is fitted by restricted maximum likelihood. The
family is held at :data:`FAMILY_FALSE_ALARM` by Bonferroni. Nothing in the run changes.
Method and measurements: docs/self-checks.md#static-stretches.
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
           "MOVING_Z2", "NOISE_FLOOR_FACTOR", "WHITE_SOURCES", "gauss_markov_fit", "lag_one_test",
           "static_noise_check", "static_stretches"]

#: Cut from both ends of a run of standing poses, s.
EDGE_MARGIN_S = 0.5
#: Shortest static stretch the checks use (after the margins), s: twice the shortest lag of
#: the relative-pose check.
MIN_STATIC_S = 2.0
#: A pose of a candidate run stands where its speed is at most this times the run's median
#: speed: the 99.9 % quantile of a chi distribution over its median, at one degree of freedom
#: (the largest such ratio: the speed's noise along one direction only).
NOISE_FLOOR_FACTOR = float(np.sqrt(stats.chi2.ppf(0.999, 1) / stats.chi2.ppf(0.5, 1)))
#: A candidate run whose median velocity z^2 (any prism's, against its predicted covariance)
#: is above this moves, however slowly: the 99.9 % quantile of a chi-square at three degrees
#: of freedom (a standing prism's velocity is noise).
MOVING_Z2 = float(stats.chi2.ppf(0.999, 3))
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


def _runs(mask: np.ndarray, joined: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last indices of the runs of ``mask`` (T,), consecutive poses counting as one
    run where ``joined`` (T - 1,) allows."""
    link = mask[:-1] & mask[1:] & joined
    return (np.flatnonzero(mask & ~np.r_[False, link]),
            np.flatnonzero(mask & ~np.r_[link, False]))


def static_stretches(t: ArrayLike, prisms_xyz: ArrayLike,
                     velocity_z2: ArrayLike | None = None) -> np.ndarray:
    """Intervals (K, 2), s, in which the robot stands, from the kept poses' times ``t`` (T,) and
    prisms ``prisms_xyz`` (T, n, 3), m: runs where every prism is slower than
    ``STANDING_SPEED_M_S`` (no gap over 1.5 median intervals), but for those whose median
    ``velocity_z2`` (T, n') (each prism's velocity against its predicted covariance,
    :func:`rtsgt.interpolation.prisms.gp_velocity_z2`; None: not tested) is above
    ``MOVING_Z2`` for a prism (a robot creeping through a whole run), within each the poses whose
    speed is at most ``NOISE_FLOOR_FACTOR`` times the run's median speed (its noise floor; at
    least ``STANDING_SPEED_M_S / 1000``), shortened by ``EDGE_MARGIN_S`` at both ends, kept
    if at least ``MIN_STATIC_S`` long (docs/self-checks.md#stretches)."""
    t = np.asarray(t, dtype=float)
    q = np.asarray(prisms_xyz, dtype=float).reshape(t.size, -1, 3)
    if t.size < 2:
        return np.zeros((0, 2))
    speed = np.max([pose_speed(t, q[:, i]) for i in range(q.shape[1])], axis=0)
    dt = np.diff(t)
    joined = dt <= 1.5 * float(np.median(dt))
    first, last = _runs(speed < STANDING_SPEED_M_S, joined)  # NaN (a pose alone): not still
    if velocity_z2 is not None and first.size:
        z2 = np.asarray(velocity_z2, dtype=float).reshape(t.size, -1)
        with warnings.catch_warnings():  # a run without a finite z^2 is not tested
            warnings.simplefilter("ignore", RuntimeWarning)
            level = np.array([np.nanmax(np.nanmedian(z2[a:b + 1], axis=0), initial=0.0)
                              for a, b in zip(first, last, strict=True)])  # a few runs
        still = ~(level > MOVING_Z2)
        first, last = first[still], last[still]
    if not first.size:
        return np.zeros((0, 2))
    # each candidate's own noise floor: its poses' median speed (a few runs, not samples)
    floor = np.array([np.median(speed[a:b + 1]) for a, b in zip(first, last, strict=True)])
    run = np.maximum(np.searchsorted(first, np.arange(t.size), side="right") - 1, 0)
    inside = (np.arange(t.size) >= first[run]) & (np.arange(t.size) <= last[run])
    # at least a thousandth of the standing speed: a noise-free run's speed is round-off
    limit = np.clip(NOISE_FLOOR_FACTOR * floor, 1e-3 * STANDING_SPEED_M_S, STANDING_SPEED_M_S)
    limit = np.where(inside, limit[run], -1.0)
    first, last = _runs(speed <= limit, joined)
    iv = np.column_stack([t[first] + EDGE_MARGIN_S, t[last] - EDGE_MARGIN_S])
    return iv[iv[:, 1] - iv[:, 0] >= MIN_STATIC_S]


def lag_one_test(z: ArrayLike, group: ArrayLike, confidence: float = 0.95,
                 ) -> tuple[float, tuple[float, float]]:
    """Lag-one autocorrelation ``r1`` of mean-removed series ``z`` (N,; series ``group`` (N,)
    contiguous, in time order) from their von Neumann ratio, and the interval it falls in with
    probability ``confidence`` if they are white (docs/self-checks.md#statistics)."""
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
    """White plus first-order Gauss-Markov noise fitted by REML to series ``z`` (N,) at times ``t``
    (N,), s (series ``group`` contiguous, each with an unknown mean). Returns the total variance
    ``v``, its correlated share ``f`` in [0, ``F_MAX``], the correlation time ``tau`` (s) and its
    95 % profile-likelihood interval (upper end None where it reaches the longest block); both
    None where ``f = 0``."""
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
    """The measurement noise on the static ``stretches`` (K, 2), s, against the white noise model,
    per prism of ``tracks`` (world frame, with per-source covariances) and component (range,
    horizontal, vertical from ``stations``' positions). Returns, JSON-ready, the stretches,
    limits, number of ``tests`` and ``confidence``, and per prism and component the observed and
    predicted sigmas (mm), ``level`` and ``correlation`` (``lag1``, interval, verdict, and where
    correlation is found its share and time); ``note`` says why no prism has a result."""
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
