r"""Self-check of a run's uncertainty: block cross-validation of each prism track, by regime.

Why windows, and why not leave-one-out
--------------------------------------
The run's ``Qc`` (and the scale of each motion class) maximises a leave-one-out predictive
density (:mod:`rtsgt.interpolation.loo`, :mod:`rtsgt.interpolation.motion`). Maximising a
likelihood over a scale drives the mean leave-one-out NEES towards 1 by construction, so a
leave-one-out NEES of 1 is no evidence: it cannot show miscalibration. This check holds out
*windows* of measurements instead, 1 s and 2 s long: what the GP then bridges is a gap of
about 1.4 s and 2.4 s at the 2.5 Hz of a tracking total station, the gaps the run's poses
bridge up to ``max_gap_s`` (3 s by default) where a station lost its prism, and not what
``Qc`` was fitted on (single points, 0.8 s gaps). The prediction is judged against what the
station measured there, so it tests what the ground truth does between measurements and
across gaps.

Windows
-------
The windows and their prediction without refitting belong to the GP
(:mod:`rtsgt.interpolation.windows`, which also ranks the motion priors of a track by them);
this check judges the run's covariance by them. Each segment of a track (split where consecutive measurements are more than ``max_gap_s``
apart) is cut from its first measurement into windows of alternating length,
:data:`BLOCK_LENGTHS_S` = 1 s, 2 s, 1 s, 2 s, ... Each window is held out in turn and predicted
from *all* the other measurements (leave-one-window-out), with the run's ``Qc`` and its
per-interval motion-class scales fixed: no new search, the check judges the run's model. A
window is scored when the measurements on either side of it are at most ``max_gap_s`` apart
(interpolation the run vouches for; the ends of the segments would be extrapolation).

Prediction without refitting
----------------------------
A held-out measurement is ``y_i = p(t_i) + n_i`` and the GP's prediction
``mu_i = p(t_i) + g_i``, so the error ``e_i = y_i - mu_i = n_i - g_i`` is the measurement's
white noise minus the GP's error. The systematic sources (atmosphere, time synchronisation,
calibration) are common to the measurement and to the track of the same station over seconds
and cancel: the predicted covariance of the ``m`` measurements of a window, jointly (they
share the GP's error), is ``Sigma_w = P'_w + blockdiag(R_1 .. R_m)``, the GP's joint
covariance at those times from the others plus the white covariance the GP is given
(:func:`rtsgt.interpolation.prisms.gp_covariance`). With ``3m`` degrees of freedom,
``NEES_w = e^T Sigma_w^-1 e``.

The GP is a linear Gaussian model, so none of this needs a refit: for the fit with every
measurement (the run's GP), residuals ``r = y - mean`` and posterior covariance ``P`` of the
positions, the residuals of a window have covariance ``M_w = R_w - P_w`` (``R_w`` the
block-diagonal white covariance, ``P_w`` the posterior's joint covariance at the window's
knots), and conditioning the joint Gaussian of the measurements gives

    ``e_w = R_w M_w^-1 r_w``,   ``Sigma_w = R_w M_w^-1 R_w``,   so   ``NEES_w = r_w^T M_w^-1 r_w``

exactly the refit without the window (Rasmussen & Williams 2006, section 5.4.2, for a block;
:func:`rtsgt.interpolation.gp.fit_track` with ``held_out`` checks it in the tests). ``P_w``
comes from the smoothed marginals ``S`` and lag-one cross-covariances ``C`` of the knots,
``Cov(x_a, x_b) = Cov(x_a, x_b-1) S_b-1^-1 C_b-1`` (:mod:`rtsgt.interpolation.cross`), as one
band of the posterior covariance, a few batched steps for every knot at once: O(N), and no
refit of the track at all.

Statistic, its variance, verdict
--------------------------------
The statistic of a set of windows is ``NEES / dof = sum_w NEES_w / sum_w 3 m_w``: 1 if the
covariance is honest, below it pessimistic, above optimistic. The windows' errors are
correlated (a window's measurements support the prediction of its neighbours), which the
model gives exactly: ``Cov(r_a, r_b) = -P_ab`` for two windows, so for Gaussian errors

    ``Var(sum_w NEES_w) = sum_w 2 (3 m_w) + sum_(a<b) 4 |M_a^-1/2 P_ab M_b^-1/2|_F^2``

(the pairs with the next :data:`PAIR_LAGS` scored windows; farther pairs add less than 1 %).
The tracks' errors are independent, so their variances add. The statistic is compared with
``chi2_n(0.025, 0.975) / n`` with ``n = 2 dof^2 / Var`` (the chi-square of the same mean and
variance; :func:`rtsgt.stats.ratio_interval`): ``consistent`` inside, ``pessimistic`` below,
``optimistic`` above, ``too few blocks`` under :data:`MIN_BLOCKS` windows. The variance is
that of the model, not estimated from the data: the check asks whether the data are what the
model predicts, and an error the model lacks (noise correlated over seconds, a lag) is a
failure of it, not a reason to trust the data less.

Regimes
-------
Overall, and per regime of the windows:

- the robot's motion over the bridged span (from the measurement before the window to the one
  after it): the fastest motion class of :mod:`rtsgt.interpolation.motion` at any
  measurement of any prism in it (the run's GPs,
  :func:`~rtsgt.interpolation.motion.motion_events`): ``standing`` (below
  :data:`~rtsgt.interpolation.motion.STANDING_SPEED_M_S` throughout), ``steady`` (moving,
  every acceleration below the first edge of
  :data:`~rtsgt.interpolation.motion.ACCELERATION_EDGES_M_S2`, 0.1 m/s^2) and
  ``accelerating`` (0.1 m/s^2 or more: starting, braking, turning);
- the distance into the gap: ``near`` when the centre of the window (midway between its first
  and last measurement) is less than :data:`FAR_INTO_GAP_S` (1 s) from the nearest kept
  measurement, ``far`` otherwise (mostly the 1 s and the 2 s windows).

Per track the statistic is given too, without a verdict (six verdicts per run already; every
added test adds false alarms). The window lengths, the 1 s edge and the 30 windows are round
numbers fixed by the design (the gaps a 2.5 Hz track bridges, ``max_gap_s``), not fitted to any
deployment.
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
    """NEES / dof of some windows of several tracks, its effective sample size, 95 % interval
    and verdict (module docstring).

    Parameters
    ----------
    windows : list of dict
        :func:`cv_windows` of each track.
    masks : list of ndarray of bool
        The windows of each track to count.
    with_verdict : bool
        Give the verdict (else only the statistic and its interval).
    """
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
    """Block cross-validation of every prism track of a run, overall and by regime.

    Parameters
    ----------
    tracks : mapping str -> PrismTrack
        The run's prism tracks (world frame), as the GPs were fitted to them.
    gps : mapping str -> GPTrack
        The run's GP of each track (its ``qc`` and ``qc_scale`` are kept).
    gp_noise : {"white", "all"}
        What the GP was given (:func:`rtsgt.interpolation.prisms.gp_covariance`).
    max_gap_s : float
        Longest gap the run bridges, s.
    warn : bool
        One :class:`~rtsgt.errors.RtsgtWarning` for the whole run and per regime judged
        optimistic or pessimistic.

    Returns
    -------
    dict
        JSON-ready: ``overall`` and ``regimes`` (``standing``, ``steady``, ``accelerating``,
        ``near``, ``far``), each with ``blocks`` (windows), ``measurements``,
        ``nees_per_dof``, ``n_eff``, ``interval_95`` and ``verdict``; ``tracks`` (per prism,
        the same without a verdict); ``block_lengths_s`` and ``regime_limits``.
    """
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
