"""The tilt compensator's residual error (docs/noise-model.md#tilt-compensator)."""

from __future__ import annotations

import numpy as np

from rtsgt.noise.sources.base import FirstOrder, NoiseSource


class Tilt(NoiseSource):
    """``e_tilt ~ N(0, sigma_tilt^2)``, entering V and ``Hz`` by ``e_tilt cot V``."""

    name = "tilt"
    label = "tilt compensator"
    white = True
    displaces_reading = True

    def first_order(self, f: FirstOrder) -> np.ndarray:
        """``sigma_t^2 g g^T``, ``g = J_Hz cot V + J_V``."""
        cv, sv = np.cos(f.nom.v), np.sin(f.nom.v)
        g = f.j_hz * (cv / sv) + f.j_v
        return f.outer([(g, f.model.instrument.sigma_tilt**2)])
