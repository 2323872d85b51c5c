"""The instrument: distance and angle errors of the datasheet (docs/noise-model.md#instrument)."""

from __future__ import annotations

import numpy as np

from rtsgt.noise.sources.base import FirstOrder, NoiseSource


class Instrument(NoiseSource):
    """``e_d ~ N(0, sigma_d(d)^2)``, ``e_Hz, e_V ~ N(0, sigma_angle^2)``."""

    name = "instrument"
    label = "instrument"
    white = True
    displaces_reading = True

    def first_order(self, f: FirstOrder) -> np.ndarray:
        """``J diag(sa^2, sa^2, sd^2 (1 + alpha0)^2) J^T``."""
        prof, nom = f.model.instrument, f.nom
        sa2 = prof.sigma_angle**2
        sd2 = (prof.sigma_distance(nom.d) * (1.0 + 1e-6 * nom.ppm)) ** 2
        return f.outer([(f.j_hz, sa2), (f.j_v, sa2), (f.u, sd2)])
