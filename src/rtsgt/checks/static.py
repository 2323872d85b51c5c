"""Self-check of the measurement noise on the run's own static stretches.

While the robot stands, a prism does not move, so the scatter of its measurements about their
mean is the measurement noise itself: the white part the GP is given (instrument and tilt
compensator; the systematic sources are constant over a stretch, and the clock error moves
nothing when nothing moves). For each prism the measurements inside the static stretches of
the run (every prism slower than :data:`~rtsgt.checks.distances.STATIC_SPEED_M_S` for at least
:data:`MIN_STATIC_S`, a gap between poses ending a stretch) are detrended per stretch (the
best quadratic in time removed: a robot below the speed limit may still creep) and split along
the line of sight of their station (``range``) and across it (``horizontal``, ``vertical``), and compared with the
predicted white covariance projected the same way:

- the **variance ratio** (observed / predicted, 1 if the model is right), with the
  ``n - 3 k`` degrees of freedom of ``n`` samples detrended over ``k`` stretches, reduced for
  the correlation between neighbours to ``(n - 3 k) (1 - rho^2) / (1 + rho^2)``
  (``rho``: the lag-one autocorrelation), and its chi-square 95 % interval;
- the **correlation time** ``-dt / ln(rho)`` (``dt``: the median sampling interval), 0 for
  uncorrelated noise. The GP takes the measurements as independent; errors that wander over
  seconds are averaged by it as if they were not, which makes its own sigma too small.

A Type A evaluation (GUM), from the run's own data. Without a static stretch of
:data:`MIN_STATIC_S`, the check says so.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

from rtsgt.checks.distances import STATIC_SPEED_M_S, pose_speed
from rtsgt.errors import RtsgtWarning
from rtsgt.types import PrismTrack

__all__ = ["MIN_STATIC_S", "WHITE_SOURCES", "static_noise_check", "static_stretches"]

#: Shortest static stretch the check uses, s.
MIN_STATIC_S = 10.0
#: The sources whose errors change from one measurement to the next.
WHITE_SOURCES = ("instrument", "tilt")
#: Fewest samples for a verdict.
MIN_SAMPLES = 20
_COMPONENTS = ("range", "horizontal", "vertical")


def static_stretches(t: ArrayLike, prisms_xyz: ArrayLike) -> np.ndarray:
    """Intervals (K, 2), s, in which every prism stands for at least :data:`MIN_STATIC_S`.

    ``prisms_xyz`` (T, n, 3): the prisms at the pose times ``t``, m (a robot turning on the
    spot moves its prisms, not its origin). A prism stands while its speed is below
    :data:`~rtsgt.checks.distances.STATIC_SPEED_M_S`.
    """
    t = np.asarray(t, dtype=float)
    q = np.asarray(prisms_xyz, dtype=float).reshape(t.size, -1, 3)
    speed = np.max([pose_speed(t, q[:, i]) for i in range(q.shape[1])], axis=0,
                   initial=0.0) if t.size else np.zeros(0)
    still = speed < STATIC_SPEED_M_S
    if t.size > 1:  # a gap between poses ends a stretch: the robot may move in it
        step = 1.5 * float(np.median(np.diff(t)))
        gap_after = np.r_[np.diff(t) > step, False]
    else:
        gap_after = np.zeros(t.shape, bool)
    out = []
    start = None
    for k in range(t.size):  # one pass over the poses (not a hot path: a few thousand)
        if still[k] and start is None:
            start = k
        if start is not None and (not still[k] or gap_after[k] or k == t.size - 1):
            end = k if still[k] else k - 1
            if end >= start and t[end] - t[start] >= MIN_STATIC_S:
                out.append((t[start], t[end]))
            start = None
    return np.asarray(out, dtype=float).reshape(-1, 2)


def _frame(u: np.ndarray) -> np.ndarray:
    """Rows: the line of sight ``u`` and two unit vectors across it, horizontal and vertical."""
    h = np.cross([0.0, 0.0, 1.0], u)
    h /= np.linalg.norm(h)
    return np.stack([u, h, np.cross(u, h)])


def _component(r: np.ndarray, pred_var: np.ndarray, window: np.ndarray, dt: float,
               dof_lost: int) -> dict[str, Any]:
    n = r.size
    same = window[1:] == window[:-1]
    a, b = r[1:][same], r[:-1][same]
    rho = float(np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b))) if a.size > 2 else 0.0
    dof = max(n - dof_lost, 1)
    ratio = float(np.sum(r * r) / dof / np.mean(pred_var))
    n_eff = max(dof * (1 - rho ** 2) / (1 + rho ** 2), 1.0)
    tau = float(-dt / np.log(rho)) if 0.0 < rho < 1.0 else 0.0
    out = {"observed_sigma_mm": float(np.sqrt(np.sum(r * r) / dof)) * 1e3,
           "predicted_sigma_mm": float(np.sqrt(np.mean(pred_var))) * 1e3,
           "variance_ratio": ratio, "lag1_correlation": rho, "correlation_time_s": tau,
           "n_eff": round(n_eff, 1)}
    if n < MIN_SAMPLES:
        out.update(interval_95=None, verdict="too few samples")
        return out
    lo, hi = (float(stats.chi2.ppf(q, n_eff) / n_eff) for q in (0.025, 0.975))
    out.update(interval_95=[lo, hi], verdict="consistent" if lo <= ratio <= hi else
               ("pessimistic" if ratio < lo else "optimistic"))
    return out


def static_noise_check(
    tracks: dict[str, PrismTrack], stations: dict[str, ArrayLike], stretches: ArrayLike, *,
    warn: bool = True,
) -> dict[str, Any]:
    """The measurement noise on the static stretches, per prism and component.

    Parameters
    ----------
    tracks : dict str -> PrismTrack
        The filtered measured tracks (world frame), with their station and per-source
        covariances.
    stations : dict str -> array_like (3,)
        Station positions (world frame), m.
    stretches : array_like, shape (K, 2)
        Static intervals (:func:`static_stretches`), s.
    warn : bool
        One :class:`~rtsgt.errors.RtsgtWarning` per prism and component judged optimistic or
        pessimistic.

    Returns
    -------
    dict
        JSON-ready: ``stretches_s`` and, per prism, ``station``, ``samples`` and for
        ``range``, ``horizontal`` and ``vertical``: ``observed_sigma_mm``,
        ``predicted_sigma_mm``, ``variance_ratio``, ``lag1_correlation``,
        ``correlation_time_s``, ``n_eff``, ``interval_95``, ``verdict``.
    """
    iv = np.asarray(stretches, dtype=float).reshape(-1, 2)
    out: dict[str, Any] = {"stretches_s": iv.tolist(), "min_stretch_s": MIN_STATIC_S,
                           "prisms": {}}
    for pid, tr in tracks.items():
        window = np.full(len(tr), -1)
        for k, (a, b) in enumerate(iv):
            window[(tr.t >= a) & (tr.t <= b)] = k
        sel = window >= 0
        white = [tr.cov_by_source[s] for s in WHITE_SOURCES if s in tr.cov_by_source]
        if not sel.any() or not white or tr.station not in stations:
            continue
        xyz, w = tr.xyz[sel], window[sel]
        C = np.sum(white, axis=0)[sel]
        # per stretch, the best quadratic in time is removed: a robot "standing" below the
        # speed limit may still creep, and that motion is not noise
        centred = np.empty_like(xyz)
        tt = tr.t[sel]
        for k in np.unique(w):
            m = w == k
            x = tt[m] - tt[m].mean()
            A = np.column_stack([np.ones_like(x), x, x * x])[:, : min(3, int(m.sum()))]
            centred[m] = xyz[m] - A @ np.linalg.lstsq(A, xyz[m], rcond=None)[0]
        E = _frame((xyz.mean(axis=0) - np.asarray(stations[tr.station], dtype=float))
                   / np.linalg.norm(xyz.mean(axis=0) - np.asarray(stations[tr.station])))
        r = centred @ E.T
        pred = np.einsum("ci,kij,cj->kc", E, C, E)
        dt = float(np.median(np.diff(tr.t[sel]))) if sel.sum() > 1 else 0.0
        entry = {"station": tr.station, "samples": int(sel.sum())}
        for c, name in enumerate(_COMPONENTS):
            entry[name] = _component(r[:, c], pred[:, c], w, dt, 3 * len(np.unique(w)))
        out["prisms"][pid] = entry
        for name in _COMPONENTS:
            v = entry[name]
            if warn and v["verdict"] in ("optimistic", "pessimistic"):
                lo, hi = v["interval_95"]
                warnings.warn(
                    f"self-check, static stretches: prism {pid} (station {tr.station}), "
                    f"{name} scatter {v['observed_sigma_mm']:.2f} mm against "
                    f"{v['predicted_sigma_mm']:.2f} mm predicted (variance ratio "
                    f"{v['variance_ratio']:.2f} outside [{lo:.2f}, {hi:.2f}], 95 %; correlation"
                    f" time {v['correlation_time_s']:.1f} s): the instrument model is "
                    + ("too small" if v["verdict"] == "optimistic" else "too large")
                    + " for this deployment's noise", RtsgtWarning, stacklevel=2)
    return out
