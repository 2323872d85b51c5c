"""A motion prior whose strength follows the motion: ``Qc`` scaled per class of the robot's
motion (standing, and half-decades of acceleration), each scale by leave-one-out.

Owns the classes (:data:`CLASS_NAMES`, :data:`STANDING_SPEED_M_S`,
:data:`ACCELERATION_EDGES_M_S2`), the robot's motion from the pilot GPs of every prism
(:func:`motion_events`), each interval's class and the fit and choice of the scales
(:func:`fit_motion_prior`). Model, thresholds and evidence: docs/interpolation.md#motion-prior.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.interpolation.gp import QC_BOUNDS, GPTrack
from rtsgt.interpolation.loo import LooScorer, maximise

__all__ = ["ACCELERATION_EDGES_M_S2", "CLASS_NAMES", "MIN_INTERVALS", "STANDING_SPEED_M_S",
           "MotionEvents", "MotionPriorFit", "fit_motion_prior", "interval_classes",
           "motion_events"]

#: Below this speed the robot stands, m/s.
STANDING_SPEED_M_S = 0.05
#: Edges of the acceleration classes of a moving robot, m/s^2 (half-decades).
ACCELERATION_EDGES_M_S2 = (0.1, 0.3, 1.0)
#: The motion classes, in order (index = class number).
CLASS_NAMES = ("standing", "below 0.1 m/s^2", "0.1-0.3 m/s^2", "0.3-1 m/s^2", "above 1 m/s^2")
#: Fewest intervals for a class to get its own scale.
MIN_INTERVALS = 5
#: Log predictive density a class model must gain per added scale to replace the constant Qc.
GAIN_PER_SCALE = 1.0
#: Largest |log| of a class's scale: a class's Qc stays within a factor e^14 (1.2e6) of the
#: track's, and the largest axis of every class above the floor of QC_BOUNDS.
SCALE_RANGE = 14.0


@dataclass(frozen=True)
class MotionEvents:
    """The robot's motion class at the measurement times of all prisms, in time order.

    Attributes
    ----------
    t : ndarray, shape (E,)
        Times, s (every knot of every pilot GP), sorted.
    motion_class : ndarray of int, shape (E,)
        Class at each time (index into :data:`CLASS_NAMES`).
    """

    t: np.ndarray
    motion_class: np.ndarray


def _knot_classes(gp: GPTrack) -> np.ndarray:
    v = gp.velocity
    speed = np.linalg.norm(v, axis=1)
    acc = np.zeros(speed.shape)
    if len(gp) > 1:
        a = np.linalg.norm(np.diff(v, axis=0), axis=1) / np.diff(gp.t)
        acc[:-1] = a
        acc[1:] = np.maximum(acc[1:], a)
    moving = 1 + np.searchsorted(np.asarray(ACCELERATION_EDGES_M_S2), acc, side="right")
    return np.where(speed < STANDING_SPEED_M_S, 0, moving)


def motion_events(pilots: Mapping[str, GPTrack]) -> MotionEvents:
    """The robot's motion class at every knot of every pilot GP (module docstring)."""
    t = np.concatenate([g.t for g in pilots.values()])
    c = np.concatenate([_knot_classes(g) for g in pilots.values()])
    order = np.argsort(t, kind="stable")
    return MotionEvents(t[order], c[order])


def interval_classes(t: ArrayLike, events: MotionEvents) -> np.ndarray:
    """Class of each interval ``[t_k, t_k+1]`` of a track: the fastest class of the robot at
    any event inside it, ends included (module docstring).

    Parameters
    ----------
    t : array_like, shape (N,)
        The track's measurement times, s, increasing.
    events : MotionEvents

    Returns
    -------
    ndarray of int, shape (N-1,)
        0 (standing) for an interval without any event (cannot happen for a pilot's own
        track, whose knots are events).
    """
    t = np.asarray(t, dtype=float)
    if t.size < 2:
        return np.zeros(0, dtype=int)
    lab = np.append(events.motion_class, 0)  # a sentinel: reduceat may index one past the end
    i0 = np.searchsorted(events.t, t[:-1], side="left")
    i1 = np.searchsorted(events.t, t[1:], side="right")
    empty = i1 <= i0
    idx = np.minimum(np.ravel(np.column_stack([i0, np.maximum(i1, i0 + 1)])), lab.size - 1)
    out = np.maximum.reduceat(lab, idx)[0::2]
    return np.where(empty, 0, out).astype(int)


@dataclass(frozen=True)
class MotionPriorFit:
    """A track's motion prior (:func:`fit_motion_prior`).

    Attributes
    ----------
    qc_scale : ndarray, shape (N-1,) or None
        Scale of each interval's ``Qc``; None when the constant ``Qc`` was kept.
    scales : dict str -> float
        Scale per class name (classes with intervals only; merged classes share a scale).
    intervals : dict str -> int
        Intervals per class name.
    loo_constant, loo_classes : float
        Leave-one-out log predictive density of the constant ``Qc`` and of the classes.
    chosen : str
        ``"classes"`` or ``"constant"``.
    """

    qc_scale: np.ndarray | None
    scales: dict[str, float]
    intervals: dict[str, int]
    loo_constant: float
    loo_classes: float
    chosen: str

    def as_dict(self) -> dict:
        """JSON-ready."""
        return {"chosen": self.chosen, "scales": self.scales, "intervals": self.intervals,
                "loo_log_predictive_constant": self.loo_constant,
                "loo_log_predictive_classes": self.loo_classes}


def _merged(classes: np.ndarray) -> np.ndarray:
    """Each class with fewer than MIN_INTERVALS intervals joins the next slower populated one
    (the fastest ones may join down to ``standing``; a lone slow class joins upwards)."""
    counts = np.bincount(classes, minlength=len(CLASS_NAMES))
    target = np.arange(len(CLASS_NAMES))
    populated = [c for c in range(len(CLASS_NAMES)) if counts[c] >= MIN_INTERVALS]
    if not populated:
        return np.zeros_like(classes)
    for c in range(len(CLASS_NAMES)):
        if c not in populated:
            lower = [p for p in populated if p < c]
            target[c] = lower[-1] if lower else populated[0]
    return target[classes]


def fit_motion_prior(
    track, qc: ArrayLike, events: MotionEvents, *, max_gap_s: float,
    loo_constant: float | None = None, prior: str = "wnoa",
) -> MotionPriorFit:
    """Scale of ``Qc`` per motion class of a track, by leave-one-out (module docstring).

    Parameters
    ----------
    track : (t, xyz, cov)
        The measurements as given to the GP (times s, positions m, covariances m^2).
    qc : array_like, shape (3, 3)
        The track's constant ``Qc``, m^2/s^3.
    events : MotionEvents
        The robot's motion (:func:`motion_events` of the pilot GPs).
    max_gap_s : float
        Knots next to a longer gap are not scored (as for the constant ``Qc``).
    loo_constant : float, optional
        The constant ``Qc``'s leave-one-out score, if already known.
    prior : {"wnoa", "wnoj"}
        The GP's motion prior (:mod:`rtsgt.interpolation.gp`).

    Returns
    -------
    MotionPriorFit
    """
    t = np.asarray(track[0], dtype=float)
    qc = np.asarray(qc, dtype=float)
    raw = interval_classes(t, events)
    cls = _merged(raw)
    present = np.unique(cls)
    score = LooScorer(track, max_gap_s, prior)
    if loo_constant is None:
        loo_constant = score(qc)[0]
    counts = {CLASS_NAMES[c]: int(np.sum(raw == c)) for c in np.unique(raw)}
    if present.size < 2:
        return MotionPriorFit(None, {}, counts, float(loo_constant), float(loo_constant),
                              "constant")
    q = np.diag(qc)
    lo = max(float(np.log(QC_BOUNDS[0] / q.max())), -SCALE_RANGE)
    hi = min(float(np.log(QC_BOUNDS[1] / q.min())), SCALE_RANGE)
    pos = np.searchsorted(present, cls)

    def scale_of(x: np.ndarray) -> np.ndarray:
        return np.exp(np.clip(x, lo, hi))[pos]

    res = maximise(lambda points: [v[0] for v in score.scores([qc] * len(points),
                                                              [scale_of(p) for p in points])],
                   np.zeros(present.size), lo, hi)
    loo_classes = -float(res.fun)
    s = np.exp(np.clip(res.x, lo, hi))
    scales = {CLASS_NAMES[c]: float(s[np.searchsorted(present, cls[raw == c][0])])
              for c in np.unique(raw)}
    better = loo_classes - loo_constant > GAIN_PER_SCALE * (present.size - 1)
    return MotionPriorFit(scale_of(res.x) if better else None, scales, counts,
                          float(loo_constant), loo_classes, "classes" if better else "constant")
