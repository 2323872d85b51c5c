"""Self-check of the ground truth where the robot stands: relative poses over 1, 10 and 60 s.

Where the robot stands its true motion is none, so the ground truth's relative pose between two
times of a static stretch is all error; its NEES against the covariance the run claims for that
difference (the two poses' covariances less their cross-covariance, the shared errors
cancelling) tests the claimed uncertainty at each time scale. Noise correlated over seconds but
carried as white shows as a NEES that grows with the lag. Method and measurements:
docs/self-checks.md#relative-poses-on-static-stretches.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import RtsgtWarning
from rtsgt.evaluation.groundtruth import ContinuousGroundTruth
from rtsgt.evaluation.joint_truth import JointGroundTruth
from rtsgt.geometry.so3 import log_so3, quat_xyzw_to_matrix
from rtsgt.stats import failed, ratio_interval, ratio_verdict, verdict_meaning

__all__ = ["MIN_PAIRS", "STATIC_LAGS_S", "static_pairs", "static_relative_check"]

#: The lags of the check, s.
STATIC_LAGS_S = (1.0, 10.0, 60.0)
#: Fewest pairs of poses at one lag for a verdict.
MIN_PAIRS = 10


def static_pairs(stretches: ArrayLike, lag: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of times ``lag`` s apart inside the static ``stretches`` (K, 2) s, one pair every
    ``2 lag`` (so that two pairs share no pose): ``(t_a, t_b, stretch)``, each (N,)."""
    iv = np.asarray(stretches, dtype=float).reshape(-1, 2)
    count = np.maximum(np.floor((iv[:, 1] - iv[:, 0] + lag) / (2.0 * lag)), 0).astype(int)
    which = np.repeat(np.arange(iv.shape[0]), count)
    i = np.arange(which.size) - np.repeat(np.cumsum(count) - count, count)
    t_a = iv[which, 0] + 2.0 * lag * i
    return t_a, t_a + lag, which


def _differences(gt: ContinuousGroundTruth, t_a: np.ndarray, t_b: np.ndarray):
    """The relative-pose errors (N, 6) (world frame: ``p_b - p_a``, ``log(R_b R_a^T)``), their
    covariance (N, 6, 6) and which pairs have both poses."""
    sample = gt.query_poses(np.concatenate([t_a, t_b]))
    n = t_a.size
    ok = sample.valid[:n] & sample.valid[n:]
    d = np.zeros((n, 6))
    cov = np.zeros((n, 6, 6))
    if not ok.any():
        return d, cov, ok
    a, b = np.flatnonzero(ok), n + np.flatnonzero(ok)
    Ra, Rb = (quat_xyzw_to_matrix(sample.quat_xyzw[i]) for i in (a, b))
    d[ok, :3] = sample.position[b] - sample.position[a]
    d[ok, 3:] = log_so3(Rb @ np.swapaxes(Ra, 1, 2))
    Caa, Cbb, Cab = gt.pair_covariances(t_a[ok], t_b[ok])
    cov[ok] = Caa + Cbb - Cab - np.swapaxes(Cab, 1, 2)
    return d, cov, ok


def _neighbour_var(gt: ContinuousGroundTruth, t_a, t_b, which, info) -> float:
    """Covariance of the NEES of consecutive pairs of one stretch, summed: ``4 tr(W_i S_ij W_j
    S_ji)`` per neighbour (Gaussian quadratic forms), ``S_ij`` the two differences' cross-
    covariance from the run's first-order model."""
    nb = np.flatnonzero(which[:-1] == which[1:])
    if nb.size == 0:
        return 0.0
    i, j = nb, nb + 1
    cc = gt.cross_covariance
    S = cc(t_b[i], t_b[j]) - cc(t_b[i], t_a[j]) - cc(t_a[i], t_b[j]) + cc(t_a[i], t_a[j])
    M = info[i] @ S @ info[j] @ np.swapaxes(S, 1, 2)
    return float(4.0 * np.trace(M, axis1=1, axis2=2).sum())


def _lag_check(gt: ContinuousGroundTruth, stretches: np.ndarray, lag: float) -> dict[str, Any]:
    t_a, t_b, which = static_pairs(stretches, lag)
    d, cov, ok = _differences(gt, t_a, t_b)
    t_a, t_b, which, d, cov = t_a[ok], t_b[ok], which[ok], d[ok], cov[ok]
    n = int(t_a.size)
    out: dict[str, Any] = {"lag_s": lag, "pairs": n}
    if n == 0:
        out.update(nees_per_dof=None, position_nees_per_dof=None,
                   rotation_nees_per_dof=None, n_eff=None, interval_95=None,
                   verdict="too few pairs")
        return out
    info = np.linalg.inv(cov)
    nees = np.einsum("ni,nij,nj->n", d, info, d)
    parts = {}
    for name, sl in (("position", slice(0, 3)), ("rotation", slice(3, 6))):
        q = np.einsum("ni,nij,nj->n", d[:, sl], np.linalg.inv(cov[:, sl, sl]), d[:, sl])
        parts[f"{name}_nees_per_dof"] = float(q.sum() / (3 * n))
    out.update(nees_per_dof=float(nees.sum() / (6 * n)), **parts)
    if n < MIN_PAIRS:
        out.update(n_eff=None, interval_95=None, verdict="too few pairs")
        return out
    dof = 6.0 * n
    var = 2.0 * dof + _neighbour_var(gt, t_a, t_b, which, info)
    n_eff = 2.0 * dof * dof / var
    interval = ratio_interval(n_eff)
    out.update(n_eff=round(n_eff, 1), interval_95=list(interval),
               verdict=ratio_verdict(out["nees_per_dof"], interval))
    return out


def static_relative_check(gt: ContinuousGroundTruth | JointGroundTruth, stretches: ArrayLike,
                          lags: tuple[float, ...] = STATIC_LAGS_S,
                          warn: bool = True) -> dict[str, Any]:
    """Relative poses of the ground truth ``gt`` (a per-prism run's continuous ground truth or a
    joint run's) over each of ``lags`` (s) inside the static
    ``stretches`` (K, 2) s (:func:`rtsgt.checks.static_stretches`), against the covariance the
    run claims for them. Returns, JSON-ready, per lag (``"1"``, ``"10"``, ``"60"``): ``pairs``,
    ``nees_per_dof`` (6 dof per pair; ``position_`` and ``rotation_nees_per_dof`` of their
    3x3 blocks), ``n_eff`` (effective samples, neighbouring pairs' correlation included),
    ``interval_95`` and ``verdict``; ``overall``: the pairs of every lag pooled (``pairs``,
    ``nees_per_dof``, ``verdict``: the lags' verdicts, ``consistent`` if each is). ``warn``: one
    warning per lag whose verdict is not consistent."""
    iv = np.asarray(stretches, dtype=float).reshape(-1, 2)
    per_lag = {f"{lag:g}": _lag_check(gt, iv, float(lag)) for lag in lags}
    judged = [v for v in per_lag.values() if v["interval_95"] is not None]
    pairs = sum(v["pairs"] for v in per_lag.values())
    pooled = (sum(v["nees_per_dof"] * v["pairs"] for v in per_lag.values() if v["pairs"])
              / pairs) if pairs else None
    bad = [v["verdict"] for _, v in failed(per_lag.items())]
    verdict = ("too few pairs" if not judged else "consistent" if not bad else
               bad[0] if len(set(bad)) == 1 else "mixed")
    out = {
        "statistic": "NEES / dof of the ground truth's relative pose between two times of a "
                     "static stretch (its truth: no motion), against the run's covariance of "
                     "the difference; 1 if the covariance is honest at that time scale",
        "lags": per_lag,
        "overall": {"pairs": pairs, "nees_per_dof": pooled, "verdict": verdict},
        "stretches": int(iv.shape[0]),
        "static_s": float(np.sum(iv[:, 1] - iv[:, 0])) if iv.size else 0.0,
    }
    if warn:
        for name, v in failed(per_lag.items()):
            lo, hi = v["interval_95"]
            warnings.warn(
                f"self-check, static relative poses over {name} s: NEES / dof "
                f"{v['nees_per_dof']:.2f} outside [{lo:.2f}, {hi:.2f}] ({v['pairs']} pairs); "
                f"95 % interval, {v['n_eff']:.0f} effective samples; the predicted "
                f"uncertainty of motion over {name} s is {verdict_meaning(v['verdict'])}",
                RtsgtWarning, stacklevel=2)
    return out
