"""Self-check of a run's uncertainty: block cross-validation of each prism track, by regime.

Windows of measurements (1 s, 2 s alternately, :data:`BLOCK_LENGTHS_S`) are held out one at a
time and predicted from all the others with the run's ``Qc`` fixed; the prediction needs no
refit (``NEES_w = r_w^T M_w^-1 r_w`` from the run's own residuals and posterior,
Rasmussen & Williams 2006, section 5.4.2). ``NEES / dof`` is judged against the model's own
variance (neighbouring windows' correlation included), overall and per regime (``standing``,
``steady``, ``accelerating``; ``near``, ``far`` into the gap). The windows belong to
:mod:`rtsgt.interpolation.windows`. Method and measurements:
docs/self-checks.md#block-cross-validation-of-the-tracks.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any

import numpy as np

from rtsgt.errors import RtsgtWarning
from rtsgt.interpolation.gp import GPTrack
from rtsgt.interpolation.motion import (
    ACCELERATION_EDGES_M_S2,
    CLASS_NAMES,
    STANDING_SPEED_M_S,
    motion_events,
)
from rtsgt.interpolation.prisms import gp_covariance
from rtsgt.interpolation.windows import BLOCK_LENGTHS_S, PAIR_LAGS, cv_blocks, cv_windows
from rtsgt.stats import failed_regimes, ratio_interval, ratio_verdict, verdict_meaning
from rtsgt.types import PrismTrack

__all__ = ["BLOCK_LENGTHS_S", "FAR_INTO_GAP_S", "MIN_BLOCKS", "PAIR_LAGS", "REGIMES", "block_cv_check",
           "cv_blocks", "cv_windows", "nees_verdict"]

#: A window whose centre is at least this far from the nearest kept measurement is "far", s.
FAR_INTO_GAP_S = 1.0
#: Fewest windows for a verdict.
MIN_BLOCKS = 30
#: The regimes of the check, in order (module docstring).
REGIMES = ("standing", "steady", "accelerating", "near", "far")
#: Motion classes (index into CLASS_NAMES) from which the robot "accelerates": the first edge
#: of the acceleration classes, 0.1 m/s^2.
_ACCELERATING_CLASS = 2


def nees_verdict(windows: list[dict[str, np.ndarray]], masks: list[np.ndarray],
                 with_verdict: bool = True) -> dict[str, Any]:
    """NEES / dof of the windows ``masks`` selects of each track's :func:`cv_windows`, with its
    effective sample size, 95 % interval and (``with_verdict``) verdict."""
    nees = dof = var = 0.0
    blocks = meas = 0
    for w, mask in zip(windows, masks, strict=True):
        nees += float(w["nees"][mask].sum())
        d = 3 * w["measurements"][mask]
        dof += float(d.sum())
        blocks += int(mask.sum())
        meas += int(w["measurements"][mask].sum())
        # 2 dof per window, and each pair of counted windows' covariance (tracks independent)
        var += 2.0 * float(d.sum())
        for lag in range(1, PAIR_LAGS + 1):
            both = mask[:-lag] & mask[lag:]
            var += float(w["pair_var"][:-lag, lag - 1][both].sum())
    out: dict[str, Any] = {"blocks": blocks, "measurements": meas,
                           "nees_per_dof": nees / dof if dof else None}
    if blocks < MIN_BLOCKS:
        out.update(n_eff=None, interval_95=None)
        if with_verdict:
            out["verdict"] = "too few blocks"
        return out
    n_eff = 2.0 * dof * dof / var
    interval = ratio_interval(n_eff)
    out.update(n_eff=round(n_eff, 1), interval_95=list(interval))
    if with_verdict:
        out["verdict"] = ratio_verdict(out["nees_per_dof"], interval)
    return out


def block_cv_check(
    tracks: Mapping[str, PrismTrack], gps: Mapping[str, GPTrack], *, gp_noise: str = "white",
    max_gap_s: float, warn: bool = True,
) -> dict[str, Any]:
    """Block cross-validation of every prism track of a run, overall and by regime, from the run's
    ``tracks`` (world frame, as fitted), their ``gps`` (``qc`` and ``qc_scale`` kept), what the
    GPs were given (``gp_noise``) and the longest gap bridged ``max_gap_s``, s. Returns,
    JSON-ready, ``overall`` and ``regimes`` (``blocks``, ``measurements``, ``nees_per_dof``,
    ``n_eff``, ``interval_95``, ``verdict``), ``tracks`` (per prism, no verdict) and the limits;
    ``warn``: one warning per verdict not consistent."""
    ids = [p for p in tracks if p in gps]
    windows = [cv_windows((tracks[p].t, tracks[p].xyz, gp_covariance(tracks[p], gp_noise)),
                          gps[p], max_gap_s) for p in ids]
    events = motion_events({p: gps[p] for p in ids}) if ids else None
    masks: dict[str, list[np.ndarray]] = {r: [] for r in REGIMES}
    for w in windows:
        cls = _span_classes(w["t_before"], w["t_after"], events)
        masks["standing"].append(cls == 0)
        masks["steady"].append((cls > 0) & (cls < _ACCELERATING_CLASS))
        masks["accelerating"].append(cls >= _ACCELERATING_CLASS)
        masks["near"].append(w["into_gap"] < FAR_INTO_GAP_S)
        masks["far"].append(w["into_gap"] >= FAR_INTO_GAP_S)
    everything = [np.ones(w["nees"].shape, bool) for w in windows]
    out: dict[str, Any] = {
        "statistic": "NEES / dof of windows of measurements, each predicted by the GP from all "
                     "the others (the run's Qc); 1 if the covariance is honest",
        "overall": nees_verdict(windows, everything),
        "regimes": {r: nees_verdict(windows, masks[r]) for r in REGIMES},
        "tracks": {p: nees_verdict([w], [m], with_verdict=False)
                   for p, w, m in zip(ids, windows, everything, strict=True)},
        "block_lengths_s": list(BLOCK_LENGTHS_S),
        "regime_limits": {"standing_below_m_s": STANDING_SPEED_M_S,
                          "accelerating_from_m_s2": ACCELERATION_EDGES_M_S2[0],
                          "far_into_gap_from_s": FAR_INTO_GAP_S},
    }
    if warn:
        for name, v in failed_regimes(out, "windows"):
            lo, hi = v["interval_95"]
            warnings.warn(
                f"self-check, block cross-validation over {name} ({v['blocks']} held-out "
                f"windows): NEES / dof = {v['nees_per_dof']:.2f}, outside [{lo:.2f}, "
                f"{hi:.2f}] (95 %, {v['n_eff']:.0f} effective samples); the predicted "
                f"uncertainty of the track across gaps of 1-3 s is "
                f"{verdict_meaning(v['verdict'])} there (poses bridging such gaps inherit it; "
                f"poses near a measurement are tested by the inter-prism distances)",
                RtsgtWarning, stacklevel=2)
    return out


def _span_classes(a: np.ndarray, b: np.ndarray, events) -> np.ndarray:
    """Fastest motion class of the robot at any event in each span ``[a, b]`` (0 if none)."""
    cls = np.zeros(a.shape, int)
    if events is None or a.size == 0:
        return cls
    i0 = np.searchsorted(events.t, a, side="left")
    i1 = np.searchsorted(events.t, b, side="right")
    for c in range(1, len(CLASS_NAMES)):
        count = np.r_[0, np.cumsum(events.motion_class >= c)]
        cls += (count[i1] - count[i0]) > 0
    return cls
