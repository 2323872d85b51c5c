"""The station's clock error against the robot's (docs/noise-model.md#time-synchronisation)."""

from __future__ import annotations

import numpy as np

from rtsgt.noise.packed import small_matmul
from rtsgt.noise.sources.base import FirstOrder, NoiseSource


class TimeSync(NoiseSource):
    """``e_ts = s |e|``, random sign, ``|e| ~ N(mu, sigma)``: ``e_ts v`` along the velocity.
    The first-order engine adds its interaction with the differenced velocity's noise."""

    name = "time_sync"
    label = "time synchronisation"

    def first_order(self, f: FirstOrder) -> np.ndarray:
        """``(mu^2 + sigma^2) v v^T``."""
        vel = small_matmul(f.nom.R, f.nom.velocity.T)
        return f.outer([(vel, f.model.time_sync_second_moment_s2)])
