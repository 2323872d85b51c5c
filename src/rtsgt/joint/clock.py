"""The stations' clock offsets in the joint engine: each non-reference station's
``e_s(t) = t_recorded - t_true`` against the reference, a level and its rate at every knot
(:mod:`rtsgt.joint.slow`) with the random-walk prior of :mod:`rtsgt.clocks`, reported every
:data:`rtsgt.clocks.KNOT_SPACING_S`: docs/joint.md#clock-offsets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.clocks import (
    KNOT_SPACING_S,
    LEVEL_SIGMA_S,
    RATE_SIGMA,
    RATE_WALK_S2_PER_S3,
    WALK_S2_PER_S,
)
from rtsgt.joint.slow import LevelRate

#: Sigma (s) holding a clock's level at the first knot at 0 when the stations' constant
#: offsets are parameters of their own (the clock states are then their drift): 0.1 us.
ANCHOR_SIGMA_S = 1e-7


@dataclass(frozen=True)
class ClockModel:
    """``station`` (C,) the indices of the stations with a clock state; per measurement
    ``row`` (M,) its station's index into ``station`` (-1: the reference); ``prior`` the
    processes' (:class:`rtsgt.joint.slow.LevelRate`, one per station of ``station``). A
    knot's clock states (``2 C``) are each station's offset (s) and rate (s/s)."""

    station: np.ndarray
    row: np.ndarray
    prior: LevelRate

    @property
    def size(self) -> int:
        """States per knot."""
        return self.prior.size

    def offsets(self, z: np.ndarray, knot: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """Each measurement's offset ``e`` (M,) s, ``level + tau rate`` of its knot ``knot``
        (M,) at ``tau`` (M,) s from it, from the knots' states ``z`` (K, 2 C)."""
        has = self.row >= 0
        r = np.where(has, self.row, 0)
        e = z[knot, 2 * r] + tau * z[knot, 2 * r + 1]
        return np.where(has, e, 0.0)

    def jacobian(self, tau: np.ndarray) -> np.ndarray:
        """``d e / d z_k`` (M, 2 C) of each measurement's offset (:meth:`offsets`): ``1`` and
        ``tau`` on its station's level and rate (zero for the reference's)."""
        M = self.row.size
        J = np.zeros((M, self.size))
        rows = np.flatnonzero(self.row >= 0)
        J[rows, 2 * self.row[rows]] = 1.0
        J[rows, 2 * self.row[rows] + 1] = tau[rows]
        return J


def clock_model(station: np.ndarray, n_stations: int, reference: int,
                anchored: bool = False) -> ClockModel:
    """The clock states of every station but ``reference`` for measurements of stations
    ``station`` (M,) (indices below ``n_stations``); with ``anchored`` each level starts at
    0 (sigma :data:`ANCHOR_SIGMA_S`: the stations' constant offsets are estimated apart)."""
    with_clock = np.array([s for s in range(n_stations) if s != reference], dtype=int)
    row_of = np.full(n_stations, -1)
    row_of[with_clock] = np.arange(with_clock.size)
    n = with_clock.size
    level = ANCHOR_SIGMA_S if anchored else LEVEL_SIGMA_S
    start = np.broadcast_to(np.diag([level**2, RATE_SIGMA**2]), (n, 2, 2)).copy()
    prior = LevelRate(np.full(n, WALK_S2_PER_S), np.full(n, RATE_WALK_S2_PER_S3), start)
    return ClockModel(with_clock, row_of[station], prior)


def report_times(t0: float, t1: float, spacing: float = KNOT_SPACING_S) -> np.ndarray:
    """Times (J >= 2,) from ``t0`` every ``spacing`` s, the last at or before ``t1`` (``t1``
    itself where the spacing leaves more than half of one): where a run reports its slowly
    varying states."""
    n = max(1, int(np.floor((t1 - t0) / spacing + 1e-9)))
    t = t0 + spacing * np.arange(n + 1)
    if t[-1] < t1 - 0.5 * spacing or t.size < 2:
        t = np.append(t, t1)
    return np.minimum(t, t1)


__all__ = ["ANCHOR_SIGMA_S", "ClockModel", "clock_model", "report_times"]
