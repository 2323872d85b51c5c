r"""Per-measurement uncertainty of total-station observations: five sources, two engines.

:func:`propagate` turns the observations of one prism by one station into a
:class:`~rtsgt.types.PrismTrack` in the world frame: nominal positions (with the additive
constant and the atmospheric correction from the weather at each time), the total 3x3
covariance and one covariance per noise source alone. The model is in
:mod:`rtsgt.noise.model`; the engines are the paper's Monte Carlo
(:mod:`rtsgt.noise.montecarlo`) and first-order propagation (:mod:`rtsgt.noise.linear`),
validated against each other in the tests. :mod:`rtsgt.noise.analysis` has the paper's
per-source analysis (square root of the Frobenius norm, by range bin).
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
from rtsgt.noise.model import NOISE_SOURCES, NoiseModel, prism_velocity
from rtsgt.noise.perturb import sample_polar_errors
from rtsgt.noise.propagation import ENGINES, propagate

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
