"""The stations' clock offsets as global parameters of the joint engine: each non-reference
station's ``e_s(t) = t_recorded - t_true`` against the reference, piecewise linear with knots
every :data:`rtsgt.clocks.KNOT_SPACING_S`, and its random-walk prior (the model of
:mod:`rtsgt.clocks`): docs/joint.md#clock-offsets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.clocks import KNOT_SPACING_S, walk_prior_info


@dataclass(frozen=True)
class ClockModel:
    """``station`` (C,) the indices of the stations with a clock state; ``knots`` (J,) s;
    ``info`` (J, J) the prior information of one station's knots (s^-2); per measurement
    ``row`` (M,) its station's index into ``station`` (-1: the reference), ``j`` (M,) its
    interval's left knot, ``u`` (M,) its position in the interval (0-1)."""

    station: np.ndarray
    knots: np.ndarray
    info: np.ndarray
    row: np.ndarray
    j: np.ndarray
    u: np.ndarray

    @property
    def size(self) -> int:
        return self.station.size * self.knots.size

    def offsets(self, clock: np.ndarray) -> np.ndarray:
        """Each measurement's offset ``e`` (M,) s from the knots' offsets ``clock`` (C, J)."""
        has = self.row >= 0
        r = np.where(has, self.row, 0)
        e = (1.0 - self.u) * clock[r, self.j] + self.u * clock[r, self.j + 1]
        return np.where(has, e, 0.0)


def clock_knots(t0: float, t1: float, spacing: float = KNOT_SPACING_S) -> np.ndarray:
    """Knots (J >= 2,) from ``t0`` every ``spacing`` s, the last at or after ``t1``."""
    n = max(1, int(np.ceil((t1 - t0) / spacing - 1e-9)))
    return t0 + spacing * np.arange(n + 1)


def clock_model(t: np.ndarray, station: np.ndarray, n_stations: int, reference: int,
                spacing: float = KNOT_SPACING_S) -> ClockModel:
    """The clock states of every station but ``reference`` for measurements at recorded times
    ``t`` (M,) s of stations ``station`` (M,) (indices below ``n_stations``)."""
    knots = clock_knots(float(t.min()), float(t.max()), spacing)
    with_clock = np.array([s for s in range(n_stations) if s != reference], dtype=int)
    row_of = np.full(n_stations, -1)
    row_of[with_clock] = np.arange(with_clock.size)
    j, u = knot_intervals(knots, t)
    return ClockModel(with_clock, knots, walk_prior_info(knots), row_of[station], j, u)


def knot_intervals(knots: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each time's interval of ``knots`` (J,): its left knot ``j`` (M,) (the first or last
    interval for times outside) and its position ``u`` (M,) in it (0-1 inside), for
    piecewise linear states on the knots."""
    j = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, knots.size - 2)
    return j, (t - knots[j]) / (knots[j + 1] - knots[j])


__all__ = ["ClockModel", "clock_knots", "clock_model", "knot_intervals"]
