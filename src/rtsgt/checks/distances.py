"""Self-check of a run's uncertainty: the tracked inter-prism distances against the survey.

The three prisms are bolted to the robot, so the distance between two of them is known from
the static survey, whatever the robot does. At every kept pose the tracked distance
``d_t = |q_i - q_j|`` differs from the surveyed ``d_r = |r_i - r_j|`` by the errors of the
two tracks and of the survey, whose variance the run predicts, first order: with ``u`` the unit
vector between the prisms,

    var_t = u^T (C_ii + C_jj - C_ij - C_ji) u  +  u_r^T (R_ii + R_jj - R_ij - R_ji) u_r

from the joint covariance ``C`` of the prisms at that time (the calibration errors two stations
share included) and the reference covariance ``R``
(:func:`rtsgt.filtering.gates.pair_distance_variance`). If the covariance is honest,
``z_t = (d_t - d_r) / sqrt(var_t)`` has unit variance and the mean of ``z^2`` is 1: below 1 the
run is pessimistic, above 1 optimistic. This is a Type A evaluation (GUM): the data's own
verdict on the uncertainty, independent of the noise model. It sees the errors that change the
distance between prisms (not a common translation of the robot), which the instrument, the
GP, the clock offsets and the calibrations all do.

Regimes
-------
The model can be right in one regime and wrong in another, so the statistic is given overall
and per regime of the kept poses: ``static`` (robot speed below 0.05 m/s), ``manoeuvring``
(0.05 to 0.8 m/s: starting, stopping, turning on the spot), ``cruising`` (0.8 m/s and above),
and, overlapping those, ``far`` (the nearest measurement of some prism at least 0.3 s away:
the GP bridges a gap). The speed is that of the pose positions, by central differences within
runs of consecutive poses. These are fixed descriptive bins (a robot's walking pace, a total
station's 0.1-0.3 s measurement interval), not fitted to any data.

Effective sample size
---------------------
The ``z_t`` are strongly correlated in time (a calibration error is one draw for the whole
run; the GP smooths the rest), so ``T`` poses carry far fewer than ``T`` independent checks.
For Gaussian ``z`` with autocorrelation ``rho_k``, the mean of ``z^2`` over ``T`` poses has
variance ``2 / n_eff`` with ``n_eff = T / (1 + 2 sum_k rho_k^2)``
(:func:`effective_sample_size`). The autocorrelation is taken about zero, the mean ``z``
has if the covariance is right, so an error shared by the whole run (it moves every ``z`` the
same way) keeps ``rho_k`` high at every lag and ``n_eff`` small: one deployment cannot tell
much about a shared error, and the check says so rather than trusting ``T``. The mean of
``z^2`` is then compared with ``chi2_{n_eff}(0.025, 0.975) / n_eff``, what it falls in 95 %
of the time if the covariance is right: ``consistent`` inside, ``pessimistic`` below,
``optimistic`` above.

The data cannot show a shared error that the run happened to draw small: ``z`` is then small
and uncorrelated, and ``n_eff`` from the data alone is large. So ``n_eff`` is bounded by what
the predicted shared fraction ``f`` of ``var_t`` allows (the calibrations, the survey, the
atmosphere and the clock offsets are one draw for the run; the GP's part changes from pose to
pose): for ``z = sqrt(f) a + sqrt(1 - f) e_t`` the mean of ``z^2`` has
``n_eff = 1 / (f^2 + (1 - f^2) / n_e)``, with ``n_e`` the data's. Lags run over the kept poses in time order, across gaps; the pairs enter
with their cross-correlations (they share prisms).
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
    """Speed of the poses, m/s: central differences within runs of consecutive poses.

    Parameters
    ----------
    t : array_like, shape (T,)
        Pose times, s, increasing.
    position : array_like, shape (T, 3)
        Positions, m.
    max_step_s : float, optional
        Poses further apart than this start a new run (default: 1.5 times the median step).
        A pose alone in its run gets NaN.
    """
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
    """Normalised deviations of the tracked inter-prism distances (module docstring).

    Parameters
    ----------
    xyz : array_like, shape (T, n, 3)
        World prism positions, m.
    cov : array_like, shape (T, 3n, 3n) or (T, n, 3, 3)
        Their joint covariance, or the per-prism blocks, m^2.
    reference_xyz : array_like, shape (n, 3)
    reference_cov : array_like, shape (3n, 3n)
        Surveyed prisms (body frame) and their covariance, m and m^2.
    varying_cov : array_like, shape (T, n, 3, 3), optional
        The part of ``cov`` that changes from pose to pose (the GP's); the rest, and the
        survey, is shared by the run. Without it, everything is taken as shared.

    Returns
    -------
    z : ndarray, shape (T, P)
        ``(d_t - d_r) / sqrt(var_t)`` for each of the ``P = n (n - 1) / 2`` pairs.
    shared : ndarray, shape (T, P)
        The fraction of ``var_t`` that is shared by the run.
    pairs : list of (i, j)
    """
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
    """Effective number of independent samples in the mean of ``z^2`` (module docstring).

    Parameters
    ----------
    z : array_like, shape (T,) or (T, P)
        Normalised deviations in time order (``P`` series measured together, e.g. the prism
        pairs), each of mean 0 and variance 1 if the covariance is honest.

    Returns
    -------
    float
        ``T P^2 / sum_{p,q} (rho_pq(0)^2 + 2 sum_{k=1}^{K-1} rho_pq(k)^2)``, between 1 and
        ``T P``: for Gaussian ``z`` with cross-correlations ``rho_pq(k)`` (lag ``k``), the
        variance of the mean of ``z^2`` is ``2 / n_eff``. The correlations are taken about
        zero (the mean under the hypothesis), so an error shared by the whole run, which moves
        every ``z`` the same way, keeps them up at every lag and ``n_eff`` small. The sum is
        cut at the lag ``K`` where Geyer's initial positive sequence of the mean
        autocorrelation (``rho_2m + rho_2m+1 > 0``) ends. ``P`` independent white series give
        about ``T P``, identical ones ``T``; an AR(1) series ``T (1 - phi^2) / (1 + phi^2)``.
    """
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
    """The inter-prism distance self-check of a run, overall and per regime.

    Parameters
    ----------
    t : array_like, shape (T,)
        Times of the kept poses, s.
    position : array_like, shape (T, 3)
        Their positions (for the speed), m.
    xyz, cov : array_like
        The prisms at those times and their joint covariance (:func:`inter_prism_z`).
    nearest_dt : array_like, shape (T, n)
        Time from each pose to the nearest measurement of each prism, s.
    reference_xyz, reference_cov : array_like
        The surveyed prisms.
    names : sequence of str
        Prism names (for the pairs' keys).
    varying_cov : array_like, shape (T, n, 3, 3), optional
        The part of the prisms' covariance that changes from pose to pose
        (:func:`inter_prism_z`).
    warn : bool
        One :class:`~rtsgt.errors.RtsgtWarning` per regime (or overall) judged optimistic
        or pessimistic.

    Returns
    -------
    dict
        JSON-ready: ``overall`` and ``regimes`` (each: ``poses``, ``mean_z2``,
        ``shared_fraction``, ``n_eff``, ``interval_95``, ``verdict``), ``pairs`` (mean ``z^2`` and mean ``z`` per pair:
        a mean ``z`` far from 0 is a bias, e.g. a mis-surveyed prism), and the thresholds.
    """
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
