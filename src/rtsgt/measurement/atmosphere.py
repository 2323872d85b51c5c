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
    """Group refractivity ``N_gr`` of standard air (0 degC, 1013.25 hPa, 0.0375 % CO2, dry).

    Parameters
    ----------
    wavelength_um : array_like
        Carrier wavelength in micrometres (e.g. 0.658 for Leica's red EDM, 0.905 for the
        Trimble S-series pulsed laser diode).

    Returns
    -------
    ndarray
        ``N_gr = (n_gr - 1) * 1e6`` (dimensionless).
    """
    lam = np.asarray(wavelength_um, dtype=float)
    _check("wavelength_um", lam, 0.0, lo_open=True)
    lam2 = lam * lam
    # [IAG99-1]
    return 287.6155 + 4.88660 / lam2 + 0.06800 / (lam2 * lam2)


def saturation_vapour_pressure(
    temperature_c: ArrayLike, pressure_hpa: ArrayLike | None = None, formula: str = "magnus"
) -> np.ndarray:
    """Saturation water-vapour pressure over water ``E_w``, hPa.

    Parameters
    ----------
    temperature_c : array_like
        Dry-bulb temperature, degC.
    pressure_hpa : array_like, optional
        Air pressure, hPa; required by ``formula="buck"`` (enhancement factor).
    formula : {"magnus", "buck"}
    """
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


def water_vapour_pressure(
    temperature_c: ArrayLike,
    humidity_pct: ArrayLike,
    pressure_hpa: ArrayLike | None = None,
    formula: str = "magnus",
) -> np.ndarray:
    """Partial water-vapour pressure ``e = RH / 100 * E_w(t)``, hPa."""
    rh = np.asarray(humidity_pct, dtype=float)
    return rh / 100.0 * saturation_vapour_pressure(temperature_c, pressure_hpa, formula)


def refractivity(
    temperature_c: ArrayLike,
    pressure_hpa: ArrayLike,
    humidity_pct: ArrayLike,
    wavelength_um: ArrayLike,
    formula: str = "magnus",
) -> np.ndarray:
    """Ambient group refractivity ``N_L = (n_L - 1) * 1e6`` of moist air ([IAG99-2]).

    Parameters
    ----------
    temperature_c, pressure_hpa, humidity_pct : array_like, broadcastable
        degC (> -273.15), hPa (> 0), % in [0, 100].
    wavelength_um : array_like
        EDM carrier wavelength, um.
    formula : {"magnus", "buck"}
        Saturation vapour pressure formula.
    """
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
    """First-velocity correction ``K`` (ppm) relative to an instrument's reference atmosphere.

    Parameters
    ----------
    temperature_c, pressure_hpa, humidity_pct : array_like, broadcastable
        Ambient conditions along the line of sight: degC, hPa (station pressure, not
        sea-level), % relative humidity.
    wavelength_um : float
        EDM carrier wavelength, um.
    reference : (float, float, float)
        The instrument's zero-ppm temperature (degC), pressure (hPa) and humidity (%).
        The default is Leica's 12 degC, 1013.25 hPa, 60 %; use :func:`instrument_correction_ppm`
        to take them from an :class:`~rtsgt.measurement.instruments.InstrumentProfile`.
    formula : {"magnus", "buck"}
        Saturation vapour-pressure formula (used for the reference and the ambient air).

    Returns
    -------
    ndarray
        ``K`` in ppm; the corrected distance is ``D' (1 + 1e-6 K)`` ([R02-D]).
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
    """Analytic partial derivatives of :func:`correction_ppm`.

    With ``K = (N_REF - N_L) / (1 + 1e-6 N_L)``:
    ``dK/dx = -(dN_L/dx) (1 + 1e-6 N_REF) / (1 + 1e-6 N_L)^2`` and, from [IAG99-2] with
    ``T = t + 273.15``, ``D = 273.15 / 1013.25 N_gr`` and ``e = RH/100 E_w``:

    - ``dN_L/dt = -D p / T^2 - 11.27 (de/dt) / T + 11.27 e / T^2``
    - ``dN_L/dp = D / T - 11.27 (de/dp) / T`` (``de/dp`` is zero for Magnus)
    - ``dN_L/dRH = -11.27 E_w / (100 T)``

    Returns
    -------
    dK_dT, dK_dp, dK_dRH : ndarray
        ppm per degC, ppm per hPa, ppm per % RH.
    """
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
    """:func:`correction_ppm` with the wavelength and reference atmosphere of ``profile``.

    Parameters
    ----------
    profile : InstrumentProfile
        Supplies ``wavelength_um`` and the reference (zero-ppm) atmosphere.
    """
    return correction_ppm(
        temperature_c, pressure_hpa, humidity_pct,
        wavelength_um=profile.wavelength_um, reference=reference_atmosphere(profile),
        formula=formula,
    )
