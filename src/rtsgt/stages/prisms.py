"""The GPs of a run's tracks (Qc search included) and the prisms at the query times: the stage
of every run after module 2. docs/interpolation.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.errors import InputError
from rtsgt.interpolation import GPTrack
from rtsgt.interpolation.prisms import PrismsAtTimes, fit_gps, query_grid, query_prisms
from rtsgt.noise.coupling import StationCoupling
from rtsgt.options import RunOptions
from rtsgt.stages.timing import Progress
from rtsgt.types import PrismTrack

__all__ = ["PrismFit", "fit_prisms", "query_times"]


@dataclass(frozen=True)
class PrismFit:
    """The tracks the GPs were fitted to, by prism, their ``gps``, each search's ``qc_info``
    and the ``prisms`` at the query times."""

    tracks: dict[str, PrismTrack]
    gps: dict[str, GPTrack]
    qc_info: dict[str, dict]
    prisms: PrismsAtTimes


def query_times(given: np.ndarray | None, intervals: np.ndarray, rate_hz: float,
                gps: dict[str, GPTrack]) -> np.ndarray:
    """The query times of a run, s: the ``given`` ones inside the common ``intervals`` (K, 2),
    else the grid at ``rate_hz``; those across a gap of some GP (longer than ``max_gap_s``)
    left out. InputError when none is left."""
    if given is not None:
        t_query = np.asarray(given, dtype=float)
        inside = np.zeros(t_query.shape, bool)
        for a, b in intervals:
            inside |= (t_query >= a) & (t_query <= b)
        t_query = t_query[inside]
    else:
        t_query = query_grid(intervals, rate_hz)
    ok = np.ones(t_query.shape, bool)
    for g in gps.values():
        ok &= g.supported(t_query)
    t_query = t_query[ok]
    if t_query.size == 0:
        raise InputError("No query time falls inside the intervals common to all prisms")
    return t_query


def fit_prisms(options: RunOptions, given_times: np.ndarray | None, intervals: np.ndarray,
               tracks: dict[str, PrismTrack], coupling: StationCoupling,
               say: Progress) -> PrismFit:
    """The GPs of ``tracks`` (the run's interpolation options) and the prisms at the query
    times (:func:`query_times`), with their joint covariance through ``coupling``."""
    say("GP interpolation")
    qc_info: dict[str, dict] = {}
    gps = fit_gps(tracks, options.interpolation, info=qc_info)
    # queries across a gap longer than max_gap_s in any prism are not poses we can vouch for
    t_query = query_times(given_times, intervals, options.interpolation.rate_hz, gps)
    prisms = query_prisms(tracks, gps, t_query, options.interpolation, coupling)
    return PrismFit(tracks, gps, qc_info, prisms)
