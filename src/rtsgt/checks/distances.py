"""Self-check of a run's uncertainty: the tracked inter-prism distances against the survey.

At every kept pose ``z_t = (d_t - d_r) / sqrt(var_t)``, the tracked minus the surveyed
distance of a prism pair over its predicted sigma (both prisms' joint covariance and the
survey's, :func:`rtsgt.filtering.gates.pair_distance_variance`); the mean of ``z^2`` is 1 for
an honest covariance. It is judged against ``chi2_{n_eff} / n_eff`` with the effective sample
size of the correlated series, bounded by the run's shared fraction of the variance, overall
and per regime (``static``, ``manoeuvring``, ``cruising``, ``far``). Method and measurements:
docs/self-checks.md#inter-prism-distances.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import RtsgtWarning
from rtsgt.filtering.gates import pair_distance_terms, pair_distance_variance
from rtsgt.pose.reference import block_diagonal
from rtsgt.stats import failed_regimes, ratio_interval, ratio_verdict, verdict_meaning

__all__ = ["REGIMES", "STATIC_SPEED_M_S", "CRUISING_SPEED_M_S", "FAR_FROM_MEASUREMENT_S",
           "effective_sample_size", "inter_prism_check", "inter_prism_z", "mean_z2_verdict",
           "pose_speed"]

#: Below this speed the robot stands, m/s.
STATIC_SPEED_M_S = 0.05
#: From this speed on the robot cruises, m/s.
CRUISING_SPEED_M_S = 0.8
#: A pose whose nearest measurement (of some prism) is at least this far is "far", s.
FAR_FROM_MEASUREMENT_S = 0.3
#: The regimes of the check, in order.
REGIMES = ("static", "manoeuvring", "cruising", "far")
#: Fewest poses for a regime's verdict.
MIN_POSES = 30


def pose_speed(t: ArrayLike, position: ArrayLike, max_step_s: float | None = None) -> np.ndarray:
    """Speed (T,), m/s, of poses at times ``t`` (T,) and ``position`` (T, 3), m: central
    differences within runs of consecutive poses (a gap over ``max_step_s``, default 1.5 median
    steps, starts a run; a pose alone gets NaN)."""
    t = np.asarray(t, dtype=float)
    p = np.asarray(position, dtype=float)
    v = np.full(t.shape, np.nan)
    if t.size < 2:
        return v
    dt = np.diff(t)
    step = 1.5 * float(np.median(dt)) if max_step_s is None else float(max_step_s)
    starts = np.r_[0, np.flatnonzero(dt > step) + 1, t.size]
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        if b - a >= 2:
            v[a:b] = np.linalg.norm(np.gradient(p[a:b], t[a:b], axis=0), axis=1)
    return v


def inter_prism_z(xyz: ArrayLike, cov: ArrayLike, reference_xyz: ArrayLike,
                  reference_cov: ArrayLike, varying_cov: ArrayLike | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """``z`` (T, P) ``= (d_t - d_r) / sqrt(var_t)`` of the ``P = n (n - 1) / 2`` prism pairs, the
    shared fraction of ``var_t`` (T, P) and the ``pairs``, from the prisms ``xyz`` (T, n, 3), m,
    their joint ``cov`` (T, 3n, 3n) or blocks (T, n, 3, 3), the survey ``reference_xyz`` (n, 3)
    and ``reference_cov`` (3n, 3n), and ``varying_cov`` (T, n, 3, 3), the GP's part (without
    it, everything is shared)."""
    q = np.asarray(xyz, dtype=float)
    c = np.asarray(cov, dtype=float)
    r = np.asarray(reference_xyz, dtype=float)
    rc = np.asarray(reference_cov, dtype=float)
    T, n = q.shape[0], r.shape[0]
    if c.shape == (T, n, 3, 3):
        c = block_diagonal(c)
    v = None if varying_cov is None else block_diagonal(np.asarray(varying_cov, dtype=float))
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    z = np.empty((T, len(pairs)))
    shared = np.ones((T, len(pairs)))
    for k, (i, j) in enumerate(pairs):
        d, u, var_t, d_ref, var_r = pair_distance_terms(q, c, r, rc, i, j)
        var = np.maximum(var_t + var_r, np.finfo(float).tiny)
        z[:, k] = (d - d_ref) / np.sqrt(var)
        if v is not None:
            shared[:, k] = np.clip(1.0 - pair_distance_variance(u, v, i, j) / var, 0.0, 1.0)
    return z, shared, pairs


def effective_sample_size(z: ArrayLike) -> float:
    """Effective number of independent samples ``n_eff`` in the mean of ``z^2``, ``z`` (T,) or
    (T, P) in time order: ``T P^2 / sum_pq (rho_pq(0)^2 + 2 sum_{k<K} rho_pq(k)^2)``, the
    correlations taken about zero and cut where Geyer's initial positive sequence ends; between
    1 and ``T P`` (docs/self-checks.md#effective-sample-size-and-verdict)."""
    z = np.asarray(z, dtype=float)
    z = z.reshape(z.shape[0], -1)
    T, P = z.shape
    if T < 3:
        return float(T * P)
    power = np.sum(z * z, axis=0)
    if np.any(power <= 0):
        return float(T)
    f = np.fft.rfft(z, n=2 * T, axis=0)
    # rho[k, p, q] = sum_t z_p(t) z_q(t + k) / sqrt(power_p power_q), lags 0 .. T - 1
    rho = np.fft.irfft(np.conj(f)[:, :, None] * f[:, None, :], n=2 * T, axis=0)[:T]
    rho /= np.sqrt(power[:, None] * power[None, :])
    auto = np.einsum("kpp->k", rho) / P
    pairs = auto[: 2 * (T // 2)].reshape(-1, 2).sum(axis=1)
    stop = np.flatnonzero(pairs <= 0)
    K = 2 * int(stop[0]) if stop.size else 2 * pairs.size  # lags 1 .. K - 1
    S = float(np.sum(rho[0] ** 2) + 2.0 * np.sum(rho[1:K] ** 2))
    return float(np.clip(T * P * P / S, 1.0, T * P))


def mean_z2_verdict(z: np.ndarray, shared: np.ndarray) -> dict[str, Any]:
    """Mean of ``z^2`` (``z``: (T, P), in time order) with its effective sample size, its 95 %
    interval and the verdict (module docstring); ``shared``: the predicted shared fraction of
    the variance of each ``z``."""
    n = int(z.shape[0])
    out: dict[str, Any] = {"poses": n, "mean_z2": float(np.mean(z ** 2)) if n else None,
                           "shared_fraction": float(np.mean(shared)) if n else None}
    if n < MIN_POSES:
        out.update(n_eff=None, interval_95=None, verdict="too few poses")
        return out
    # a shared error the run happened to draw small leaves no trace in the correlations of
    # z: bound n_eff by what the predicted shared fraction f allows (module docstring)
    f = float(np.mean(shared))
    n_data = effective_sample_size(z)
    n_eff = min(n_data, 1.0 / (f * f + (1.0 - f * f) / n_data))
    interval = ratio_interval(n_eff)
    out.update(n_eff=round(n_eff, 1), interval_95=list(interval),
               verdict=ratio_verdict(out["mean_z2"], interval))
    return out


def inter_prism_check(
    t: ArrayLike, position: ArrayLike, xyz: ArrayLike, cov: ArrayLike, nearest_dt: ArrayLike,
    reference_xyz: ArrayLike, reference_cov: ArrayLike, names: Sequence[str], *,
    varying_cov: ArrayLike | None = None, warn: bool = True,
) -> dict[str, Any]:
    """The inter-prism distance self-check of a run, overall and per regime: from the kept poses'
    times ``t`` (T,) and ``position`` (T, 3), the prisms and covariances as
    :func:`inter_prism_z`, ``nearest_dt`` (T, n) to each prism's nearest measurement, s, and the
    prism ``names``. Returns, JSON-ready, ``overall`` and ``regimes`` (``poses``, ``mean_z2``,
    ``shared_fraction``, ``n_eff``, ``interval_95``, ``verdict``), ``pairs`` (mean ``z^2`` and
    ``z``) and the thresholds; ``warn``: one warning per regime not consistent."""
    t = np.asarray(t, dtype=float)
    z, shared, pairs = inter_prism_z(xyz, cov, reference_xyz, reference_cov, varying_cov)
    speed = pose_speed(t, position)
    far = np.max(np.asarray(nearest_dt, dtype=float), axis=1, initial=0.0) \
        >= FAR_FROM_MEASUREMENT_S
    masks = {
        "static": speed < STATIC_SPEED_M_S,
        "manoeuvring": (speed >= STATIC_SPEED_M_S) & (speed < CRUISING_SPEED_M_S),
        "cruising": speed >= CRUISING_SPEED_M_S,
        "far": far,
    }
    out: dict[str, Any] = {
        "statistic": "mean of z^2, z = (tracked - surveyed inter-prism distance) / predicted "
                     "sigma; 1 if the covariance is honest",
        "overall": mean_z2_verdict(z, shared),
        "regimes": {k: mean_z2_verdict(z[m], shared[m]) for k, m in masks.items()},
        "pairs": {f"{names[i]}-{names[j]}": {"mean_z2": float(np.mean(z[:, k] ** 2)),
                                              "mean_z": float(np.mean(z[:, k]))}
                  for k, (i, j) in enumerate(pairs)} if t.size else {},
        "regime_limits": {"static_below_m_s": STATIC_SPEED_M_S,
                          "cruising_from_m_s": CRUISING_SPEED_M_S,
                          "far_from_s": FAR_FROM_MEASUREMENT_S},
    }
    if warn:
        for name, v in failed_regimes(out, "poses"):
            lo, hi = v["interval_95"]
            warnings.warn(
                f"self-check, inter-prism distances over {name} ({v['poses']} poses): "
                f"mean z^2 = {v['mean_z2']:.2f}, outside [{lo:.2f}, {hi:.2f}] (95 %, "
                f"{v['n_eff']:.0f} effective samples); the predicted uncertainty is "
                f"{verdict_meaning(v['verdict'])} there", RtsgtWarning, stacklevel=2)
    return out
