"""The registry of noise sources: each a small class in a module of its own, listed once here.

Adding a source is one new module (a :class:`~rtsgt.noise.sources.base.NoiseSource` subclass)
plus its line in :data:`SOURCES`; docs/noise-model.md#adding-a-noise-source.
"""

from __future__ import annotations

from rtsgt.noise.sources.atmosphere import Atmosphere
from rtsgt.noise.sources.base import FirstOrder, NoiseSource
from rtsgt.noise.sources.calibration import Calibration
from rtsgt.noise.sources.instrument import Instrument
from rtsgt.noise.sources.tilt import Tilt
from rtsgt.noise.sources.time_sync import TimeSync

__all__ = ["CORRELATED_NOISE_SOURCE", "NOISE_SOURCES", "SOURCES", "SYSTEMATIC_NOISE_SOURCES",
           "WHITE_NOISE_SOURCES", "FirstOrder", "NoiseSource"]

#: Every source by name, in the order of reports (the paper's).
SOURCES: dict[str, NoiseSource] = {
    s.name: s for s in (Instrument(), Tilt(), Atmosphere(), TimeSync(), Calibration())
}
#: Their names.
NOISE_SOURCES = tuple(SOURCES)
#: The sources whose errors change from one measurement to the next (the GP's white noise).
WHITE_NOISE_SOURCES = tuple(n for n, s in SOURCES.items() if s.white)
#: The others, added after the GP at their full value (docs/noise-model.md).
SYSTEMATIC_NOISE_SOURCES = tuple(n for n, s in SOURCES.items() if not s.white)
#: The covariance added to the white sources where their noise is correlated in time
#: (:mod:`rtsgt.noise.correlated`), an entry of ``cov_by_source`` beside the registered ones.
CORRELATED_NOISE_SOURCE = "correlated_noise"
