"""Per-measurement uncertainty of total-station observations: the sources, two engines.

:func:`propagate` turns the observations of one prism by one station into a
:class:`~rtsgt.types.PrismTrack` with the total and per-source covariances; the sources are
registered in :mod:`rtsgt.noise.sources`; the engines are the Monte Carlo
(:mod:`rtsgt.noise.montecarlo`) and first order (:mod:`rtsgt.noise.linear`);
:mod:`rtsgt.noise.analysis` has the paper's per-source analysis. docs/noise-model.md.
"""

from __future__ import annotations

from rtsgt.noise.analysis import (
    PAPER_RANGE_EDGES,
    RangeBins,
    authors_source_norms_mm,
    bin_by_range,
    frobenius_norm_mm,
    source_norms_mm,
    summarize_sources,
)
from rtsgt.noise.model import NoiseModel, prism_velocity
from rtsgt.noise.perturb import sample_polar_errors
from rtsgt.noise.propagation import ENGINES, propagate
from rtsgt.noise.sources import NOISE_SOURCES

__all__ = [
    "ENGINES",
    "NOISE_SOURCES",
    "PAPER_RANGE_EDGES",
    "NoiseModel",
    "RangeBins",
    "authors_source_norms_mm",
    "bin_by_range",
    "frobenius_norm_mm",
    "prism_velocity",
    "propagate",
    "sample_polar_errors",
    "source_norms_mm",
    "summarize_sources",
]
