"""The weather's error in the first-velocity correction (docs/noise-model.md#atmosphere)."""

from __future__ import annotations

import numpy as np

from rtsgt.measurement.atmosphere import correction_ppm_gradient
from rtsgt.noise.sources.base import FirstOrder, NoiseSource


class Atmosphere(NoiseSource):
    """Zero-mean uniform errors of temperature, pressure and humidity, along the line of
    sight."""

    name = "atmosphere"
    label = "atmosphere"
    displaces_reading = True

    def first_order(self, f: FirstOrder) -> np.ndarray:
        """``d^2 1e-12 var(K) u u^T``, ``var(K)`` through the analytic gradient of ``K``."""
        nom, model = f.nom, f.model
        prof = model.instrument
        gT, gp, gR = correction_ppm_gradient(
            nom.temperature_c, nom.pressure_hpa, nom.humidity_pct,
            wavelength_um=prof.wavelength_um,
            reference=(prof.reference_temperature_c, prof.reference_pressure_hpa,
                       prof.reference_humidity_pct),
            formula=model.vapour_formula,
        )
        vT, vp, vR = model.weather_variances
        var_ppm = gT**2 * vT + gp**2 * vp + gR**2 * vR
        return f.outer([(f.u, nom.d**2 * 1e-12 * var_ppm)])
