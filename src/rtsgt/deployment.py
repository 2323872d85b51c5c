"""What a deployment provides, read and validated: the input record of the pipeline.

:func:`rtsgt.io.deployment.load_deployment` builds it from a deployment's files; nothing reads a
file after it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.filtering.modules import FilterReport
from rtsgt.measurement.instruments import InstrumentProfile
from rtsgt.pose import ReferencePoints
from rtsgt.types import GcpShots, Observations, WeatherSeries

__all__ = ["DeploymentData"]


@dataclass(frozen=True)
class DeploymentData:
    """Everything a deployment provides, already read and validated (no file access after).

    Attributes
    ----------
    name : str
    instrument : InstrumentProfile
    observations : tuple of Observations
        One per station; station ``obs.station`` tracks prism ``obs.prism``.
    gcp : GcpShots
    reference : ReferencePoints or None
        Reference prisms in the body frame, with covariance; None for a deployment with fewer
        than 3 tracked prisms (its run gives positions only,
        :class:`rtsgt.record.PositionRunRecord`).
    reference_station : str
        The world frame is this station's frame.
    weather : WeatherSeries, optional
    query_times : ndarray, optional
        Times (s) at which to compute poses; otherwise a regular grid at ``rate_hz``.
    input_report : FilterReport, optional
        What the reader of the measurements removed before module 1, by reason and station
        (:class:`rtsgt.io.rts_bag.InputReport`: the statuses of a bag's messages); recorded as
        ``filters.input`` of ``summary.json``. None for prism files.
    """

    name: str
    instrument: InstrumentProfile
    observations: tuple[Observations, ...]
    gcp: GcpShots
    reference: ReferencePoints | None
    reference_station: str = "1"
    weather: WeatherSeries | None = None
    query_times: np.ndarray | None = None
    input_report: FilterReport | None = None
