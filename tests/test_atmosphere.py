"""Atmospheric first-velocity correction (IAG 1999 / Rueger), against published values."""

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.measurement.atmosphere import (
    apply_correction,
    correction_ppm,
    correction_ppm_gradient,
    group_refractivity,
    instrument_correction_ppm,
    refractivity,
    saturation_vapour_pressure,
)
from rtsgt.measurement.instruments import LEICA_MS60, TRIMBLE_S7

LEICA_REF = (12.0, 1013.25, 60.0)


@pytest.mark.parametrize("formula", ["buck", "magnus"])
def test_geodepy_worked_example(formula):
    # GeodePy test_survey.py (first velocity correction): 1117.8517 m observed at 6.8 degC,
    # 960.8 hPa, 58.6 % RH with a 0.850 um EDM referenced to 12 degC / 1013.25 hPa / 60 %
    # corrects to 1117.8624 m, i.e. +9.53 ppm. GeodePy uses the Buck/Rueger vapour pressure;
    # Magnus differs by 4e-4 ppm here.
    K = correction_ppm(6.8, 960.8, 58.6, wavelength_um=0.850, reference=LEICA_REF, formula=formula)
    assert float(K) == pytest.approx(9.53, abs=0.005)
    assert round(float(apply_correction(1117.8517, K)), 4) == 1117.8624


def test_leica_reference_group_index():
    # Leica manuals (TS16 / MS60 generation) give the reference group index of their 658 nm
    # EDM at 12 degC, 1013.25 hPa, 60 % RH as n = 1.0002863.
    n = 1.0 + 1e-6 * refractivity(12.0, 1013.25, 60.0, 0.658)
    assert round(float(n), 7) == 1.0002863
    # the correction is zero at the reference atmosphere, for any instrument
    assert float(instrument_correction_ppm(LEICA_MS60, 12.0, 1013.25, 60.0)) == pytest.approx(0, abs=1e-12)
    assert float(instrument_correction_ppm(TRIMBLE_S7, 20.0, 1013.25, 60.0)) == pytest.approx(0, abs=1e-12)


def test_group_refractivity_formula():
    # IAG 1999: N_gr = 287.6155 + 4.88660 / l^2 + 0.06800 / l^4
    assert float(group_refractivity(1.0)) == pytest.approx(287.6155 + 4.88660 + 0.06800)
    assert float(group_refractivity(0.905)) == pytest.approx(293.6833, abs=1e-4)
    with pytest.raises(InputError):
        group_refractivity(0.0)


def test_vapour_pressure_formulas():
    # Magnus at 0 degC is its constant; Buck at 0 degC: (1.0007 + 3.46e-6 p) 6.1121
    assert float(saturation_vapour_pressure(0.0)) == pytest.approx(6.1078)
    assert float(saturation_vapour_pressure(0.0, 1000.0, "buck")) == pytest.approx(
        (1.0007 + 3.46e-3) * 6.1121
    )
    # both agree within 1.2 % over the field range (Buck carries the ~0.4 % enhancement factor
    # of moist air), and give ~23.4 hPa at 20 degC
    t = np.linspace(-20, 35, 12)
    m = saturation_vapour_pressure(t)
    b = saturation_vapour_pressure(t, 1013.25, "buck")
    np.testing.assert_allclose(m, b, rtol=1.2e-2)
    assert np.all(b > m)
    assert float(saturation_vapour_pressure(20.0)) == pytest.approx(23.38, abs=0.01)
    with pytest.raises(InputError, match="pressure_hpa"):
        saturation_vapour_pressure(10.0, None, "buck")
    with pytest.raises(InputError, match="Unknown vapour-pressure formula"):
        saturation_vapour_pressure(10.0, formula="goff")


def test_zero_degrees_and_zero_humidity_are_valid():
    # the `if temperature:` bug of some survey codes: 0 degC and 0 % are values, not "missing"
    k0 = correction_ppm(0.0, 1013.25, 0.0, wavelength_um=0.658, reference=LEICA_REF)
    k1 = correction_ppm(1e-9, 1013.25, 1e-9, wavelength_um=0.658, reference=LEICA_REF)
    assert np.isfinite(k0) and float(k0) == pytest.approx(float(k1), abs=1e-6)
    assert float(k0) < 0  # colder than the 12 degC reference: denser air, negative correction


def test_sensitivities_near_standard_conditions():
    # often quoted: "about +0.9 ppm per degC and -0.26 ppm per hPa"; the exact values at
    # 15 degC / 1013 hPa / 60 % are +0.99 and -0.275 (the rounded figures fit ~25 degC;
    # docs/noise-model.md#checks)
    for lam in (0.658, 0.905):
        dT, dp, dR = correction_ppm_gradient(15.0, 1013.0, 60.0, wavelength_um=lam, reference=LEICA_REF)
        assert 0.85 < float(dT) < 1.05
        assert -0.30 < float(dp) < -0.24
        assert 0.0 < float(dR) < 0.02  # humidity: ~0.01 ppm per %
    dT, dp, _ = correction_ppm_gradient(25.0, 1013.0, 60.0, wavelength_um=0.905, reference=LEICA_REF)
    assert float(dT) == pytest.approx(0.9, abs=0.05)
    assert float(dp) == pytest.approx(-0.26, abs=0.01)


@pytest.mark.parametrize("formula", ["magnus", "buck"])
def test_gradient_matches_central_differences(formula):
    rng = np.random.default_rng(3)
    t = rng.uniform(-20, 35, 20)
    p = rng.uniform(700, 1050, 20)
    rh = rng.uniform(5, 95, 20)
    kw = dict(wavelength_um=0.905, reference=(20.0, 1013.25, 60.0), formula=formula)
    g = correction_ppm_gradient(t, p, rh, **kw)
    for i, h in enumerate((1e-4, 1e-3, 1e-3)):
        args_p = [t, p, rh]
        args_m = [t, p, rh]
        args_p[i] = args_p[i] + h
        args_m[i] = args_m[i] - h
        num = (correction_ppm(*args_p, **kw) - correction_ppm(*args_m, **kw)) / (2 * h)
        np.testing.assert_allclose(g[i], num, rtol=1e-6, atol=1e-9)


def test_vectorised_and_validated():
    K = correction_ppm(np.array([[0.0], [20.0]]), np.array([900.0, 1000.0, 1013.25]), 50.0,
                       wavelength_um=0.905, reference=(20.0, 1013.25, 60.0))
    assert K.shape == (2, 3)
    # lower pressure -> positive correction (thinner air, faster light)
    assert K[1, 0] > K[1, 1] > K[1, 2]
    with pytest.raises(InputError, match=r"humidity_pct in \[0.0, 100.0\], got 101.0 at index 1"):
        correction_ppm(10.0, 1000.0, [50.0, 101.0], wavelength_um=0.9)
    with pytest.raises(InputError, match="pressure_hpa"):
        correction_ppm(10.0, 0.0, 50.0, wavelength_um=0.9)
    with pytest.raises(InputError, match="temperature_c"):
        correction_ppm(np.nan, 1000.0, 50.0, wavelength_um=0.9)
