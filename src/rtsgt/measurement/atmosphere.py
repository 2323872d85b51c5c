"""Atmospheric first-velocity correction of EDM distances (IAG 1999 resolution, Rueger 2002).

Owns the group refractivity, the saturation vapour pressure (Magnus, Buck), the correction
``K`` in ppm at a weather for an instrument's reference atmosphere, and its analytic gradient.
Formulas, tags ([IAG99-1], [R02-K], ...) and checks: docs/noise-model.md#atmosphere.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError

#: Saturation vapour pressure formulas, for ``formula=``.
VAPOUR_FORMULAS = ("magnus", "buck")

#: 0 degC in kelvin.
KELVIN = 273.15
#: Standard pressure, hPa.
P0_HPA = 1013.25
#: Coefficient of the water-vapour term of [IAG99-2], K/hPa.
WATER_VAPOUR_COEFF = 11.27

_LN10 = np.log(10.0)


def _check(name: str, a: np.ndarray, lo: float, hi: float = np.inf, lo_open: bool = False):
    bad = ~np.isfinite(a) | (a < lo) | (a > hi)
    if lo_open:
        bad |= a <= lo
    if np.any(bad):
        idx = np.argwhere(bad)[0]
        i = tuple(int(j) for j in idx) if a.ndim > 1 else (int(idx[0]) if a.ndim == 1 else None)
        where = "" if i is None else f" at index {i}"
        rng = f"({lo}, {hi}]" if lo_open else f"[{lo}, {hi}]"
        raise InputError(f"Expected {name} in {rng}, got {float(a[bad].flat[0])!r}{where}")


def _check_formula(formula: str) -> str:
    f = str(formula).lower()
    if f not in VAPOUR_FORMULAS:
        raise InputError(
            f"Unknown vapour-pressure formula {formula!r}; known: {', '.join(VAPOUR_FORMULAS)}"
        )
    return f


def group_refractivity(wavelength_um: ArrayLike) -> np.ndarray:
    """``N_gr = (n_gr - 1) 1e6`` of standard air ([IAG99-1]) at the carrier wavelength
    ``wavelength_um``, um (0.658 Leica's red EDM, 0.905 Trimble's S series)."""
    lam = np.asarray(wavelength_um, dtype=float)
    _check("wavelength_um", lam, 0.0, lo_open=True)
    lam2 = lam * lam
    # [IAG99-1]
    return 287.6155 + 4.88660 / lam2 + 0.06800 / (lam2 * lam2)


def saturation_vapour_pressure(
    temperature_c: ArrayLike, pressure_hpa: ArrayLike | None = None, formula: str = "magnus"
) -> np.ndarray:
    """Saturation water-vapour pressure over water ``E_w``, hPa, at ``temperature_c`` degC by
    the "magnus" or "buck" ``formula`` (the latter needs ``pressure_hpa``, hPa)."""
    f = _check_formula(formula)
    t = np.asarray(temperature_c, dtype=float)
    if f == "magnus":
        # [MAG]
        return 6.1078 * np.exp(_LN10 * 7.5 * t / (237.3 + t))
    if pressure_hpa is None:
        raise InputError("The Buck vapour-pressure formula needs pressure_hpa, got None")
    p = np.asarray(pressure_hpa, dtype=float)
    # [BUCK]
    return (1.0007 + 3.46e-6 * p) * 6.1121 * np.exp(17.502 * t / (240.94 + t))


def _saturation_and_derivatives(t, p, f):
    """E_w, dE_w/dt, dE_w/dp for the chosen formula (internal, no validation)."""
    if f == "magnus":
        den = 237.3 + t
        E = 6.1078 * np.exp(_LN10 * 7.5 * t / den)
        # d/dt [7.5 t / (237.3 + t)] = 7.5 * 237.3 / (237.3 + t)^2
        dE_dt = E * _LN10 * 7.5 * 237.3 / (den * den)
        dE_dp = np.zeros(np.broadcast(t, p).shape)
        return E, dE_dt, dE_dp
    den = 240.94 + t
    ex = 6.1121 * np.exp(17.502 * t / den)
    enh = 1.0007 + 3.46e-6 * p
    E = enh * ex
    dE_dt = E * 17.502 * 240.94 / (den * den)
    dE_dp = 3.46e-6 * ex
    return E, dE_dt, dE_dp


def refractivity(
    temperature_c: ArrayLike,
    pressure_hpa: ArrayLike,
    humidity_pct: ArrayLike,
    wavelength_um: ArrayLike,
    formula: str = "magnus",
) -> np.ndarray:
    """``N_L = (n_L - 1) 1e6`` of moist air ([IAG99-2]) at degC (> -273.15), hPa (> 0) and
    % RH in [0, 100] (broadcastable), the wavelength in um, the "magnus" or "buck" formula."""
    f = _check_formula(formula)
    t = np.asarray(temperature_c, dtype=float)
    p = np.asarray(pressure_hpa, dtype=float)
    rh = np.asarray(humidity_pct, dtype=float)
    _check("temperature_c", t, -KELVIN, lo_open=True)
    _check("pressure_hpa", p, 0.0, lo_open=True)
    _check("humidity_pct", rh, 0.0, 100.0)
    return _refractivity(t, p, rh, group_refractivity(wavelength_um), f)


def _refractivity(t, p, rh, n_gr, f):
    T = t + KELVIN
    e = rh / 100.0 * saturation_vapour_pressure(t, p, f)
    # [IAG99-2]
    return (KELVIN / P0_HPA) * n_gr * p / T - WATER_VAPOUR_COEFF * e / T


def correction_ppm(
    temperature_c: ArrayLike,
    pressure_hpa: ArrayLike,
    humidity_pct: ArrayLike,
    *,
    wavelength_um: float,
    reference: tuple[float, float, float] = (12.0, 1013.25, 60.0),
    formula: str = "magnus",
) -> np.ndarray:
    """First-velocity correction ``K``, ppm ([R02-K]; the distance becomes ``D' (1 + 1e-6 K)``),
    at degC, station hPa and % RH along the line of sight (broadcastable), against the
    ``reference`` (degC, hPa, %) of zero ppm (default Leica's; :func:`instrument_correction_ppm`
    takes an instrument's), the same vapour ``formula`` for both (docs/noise-model.md#atmosphere).
    """
    f = _check_formula(formula)
    t_ref, p_ref, rh_ref = reference
    n_ref = refractivity(t_ref, p_ref, rh_ref, wavelength_um, f)
    n_l = refractivity(temperature_c, pressure_hpa, humidity_pct, wavelength_um, f)
    # [R02-K]
    return (n_ref - n_l) / (1.0 + 1e-6 * n_l)


def correction_ppm_gradient(
    temperature_c: ArrayLike,
    pressure_hpa: ArrayLike,
    humidity_pct: ArrayLike,
    *,
    wavelength_um: float,
    reference: tuple[float, float, float] = (12.0, 1013.25, 60.0),
    formula: str = "magnus",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Analytic partial derivatives of :func:`correction_ppm`, ppm per degC, per hPa and per % RH
    (``dK/dx = -(dN_L/dx) (1 + 1e-6 N_REF) / (1 + 1e-6 N_L)^2`` through [IAG99-2])."""
    f = _check_formula(formula)
    t = np.asarray(temperature_c, dtype=float)
    p = np.asarray(pressure_hpa, dtype=float)
    rh = np.asarray(humidity_pct, dtype=float)
    _check("temperature_c", t, -KELVIN, lo_open=True)
    _check("pressure_hpa", p, 0.0, lo_open=True)
    _check("humidity_pct", rh, 0.0, 100.0)
    n_gr = group_refractivity(wavelength_um)
    t_ref, p_ref, rh_ref = reference
    n_ref = refractivity(t_ref, p_ref, rh_ref, wavelength_um, f)
    return _gradient(t, p, rh, n_gr, n_ref, f)


def _gradient(t, p, rh, n_gr, n_ref, f):
    T = t + KELVIN
    D = (KELVIN / P0_HPA) * n_gr
    E, dE_dt, dE_dp = _saturation_and_derivatives(t, p, f)
    e = rh / 100.0 * E
    n_l = D * p / T - WATER_VAPOUR_COEFF * e / T
    dN_dt = -D * p / T**2 - WATER_VAPOUR_COEFF * (rh / 100.0 * dE_dt) / T + WATER_VAPOUR_COEFF * e / T**2
    dN_dp = D / T - WATER_VAPOUR_COEFF * (rh / 100.0 * dE_dp) / T
    dN_drh = -WATER_VAPOUR_COEFF * E / (100.0 * T)
    scale = -(1.0 + 1e-6 * n_ref) / (1.0 + 1e-6 * n_l) ** 2
    return scale * dN_dt, scale * dN_dp, scale * dN_drh


def apply_correction(distance_m: ArrayLike, ppm: ArrayLike) -> np.ndarray:
    """Corrected distance ``D = D' (1 + 1e-6 K)`` ([R02-D]), m."""
    return np.asarray(distance_m, dtype=float) * (1.0 + 1e-6 * np.asarray(ppm, dtype=float))


def reference_atmosphere(profile) -> tuple[float, float, float]:
    """``(temperature_c, pressure_hpa, humidity_pct)`` at which ``profile`` reads 0 ppm."""
    return (
        float(profile.reference_temperature_c),
        float(profile.reference_pressure_hpa),
        float(profile.reference_humidity_pct),
    )


def instrument_correction_ppm(
    profile,
    temperature_c: ArrayLike,
    pressure_hpa: ArrayLike,
    humidity_pct: ArrayLike,
    formula: str = "magnus",
) -> np.ndarray:
    """:func:`correction_ppm` with the wavelength and reference atmosphere of ``profile``
    (an :class:`~rtsgt.measurement.instruments.InstrumentProfile`)."""
    return correction_ppm(
        temperature_c, pressure_hpa, humidity_pct,
        wavelength_um=profile.wavelength_um, reference=reference_atmosphere(profile),
        formula=formula,
    )
