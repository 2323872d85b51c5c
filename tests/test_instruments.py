"""Instrument profiles: built-ins, confidence levels, user-defined profiles from a config."""

from pathlib import Path

import numpy as np
import pytest

from _paths import EXAMPLE_TOML as EXAMPLE
from _paths import EXCERPT
from rtsgt.errors import ConfigError, InputError
from rtsgt.measurement.instruments import (
    ARCSEC,
    INSTRUMENTS,
    TRIMBLE_S7,
    InstrumentProfile,
    get_instrument,
    instrument_from_config,
)

FULL = {
    "name": "My-RTS",
    "distance_constant_mm": 2.0,
    "distance_ppm": 2.0,
    "angle_arcsec": 1.0,
    "tilt_arcsec": 0.5,
    "confidence_sigma": 1,
    "wavelength_um": 0.658,
    "reference_temperature_c": 12,
    "reference_pressure_hpa": 1013.25,
    "reference_humidity_pct": 60,
}


def test_trimble_s7_is_the_paper_profile():
    # Vaidis et al. 2023, Table I: 4 mm + 2 ppm, 2", 0.5", at 2 sigma; authors' 0.905 um
    p = get_instrument("Trimble-S7")
    assert p is TRIMBLE_S7
    assert p.confidence_sigma == 2.0
    assert p.wavelength_um == 0.905
    assert float(p.sigma_distance(100.0)) == pytest.approx((0.004 + 2e-6 * 100) / 2)
    assert p.sigma_angle == pytest.approx(1.0 * ARCSEC)
    assert p.sigma_tilt == pytest.approx(0.25 * ARCSEC)


def test_at_least_three_builtins_with_stated_confidence_and_atmosphere():
    assert len(INSTRUMENTS) >= 3
    for name, p in INSTRUMENTS.items():
        assert p.name == name
        assert p.confidence_sigma in (1.0, 2.0)
        assert 0.5 < p.wavelength_um < 1.6
        assert 0 <= p.reference_humidity_pct <= 100
        assert "sigma" in p.description  # the confidence is stated where the numbers come from
    leica = [p for p in INSTRUMENTS.values() if p.name.startswith("leica")]
    assert leica and all(
        (p.reference_temperature_c, p.reference_pressure_hpa, p.reference_humidity_pct)
        == (12.0, 1013.25, 60.0) for p in leica
    )


def test_unknown_instrument_lists_known():
    with pytest.raises(InputError, match="known: .*trimble-s7"):
        get_instrument("theodolite-3000")


def test_from_dict_round_trip_and_units():
    p = InstrumentProfile.from_dict(FULL)
    assert p.name == "my-rts"
    assert p.distance_constant_m == pytest.approx(0.002)
    assert p.angle_rad == pytest.approx(ARCSEC)
    assert InstrumentProfile.from_dict(p.to_dict()) == p
    for q in INSTRUMENTS.values():
        assert InstrumentProfile.from_dict(q.to_dict()) == q


def test_from_dict_missing_and_unknown_keys():
    d = dict(FULL)
    del d["tilt_arcsec"], d["wavelength_um"]
    with pytest.raises(ConfigError, match="missing the key\\(s\\) tilt_arcsec, wavelength_um"):
        InstrumentProfile.from_dict(d)
    with pytest.raises(ConfigError, match="unknown key\\(s\\) angle_deg"):
        InstrumentProfile.from_dict({**FULL, "angle_deg": 1.0})
    with pytest.raises(ConfigError, match="must be a number, got '1'"):
        InstrumentProfile.from_dict({**FULL, "angle_arcsec": "1"})
    with pytest.raises(ConfigError, match="must be a number"):
        InstrumentProfile.from_dict({**FULL, "angle_arcsec": True})
    with pytest.raises(ConfigError, match="reference_humidity_pct in \\[0, 100\\]"):
        InstrumentProfile.from_dict({**FULL, "reference_humidity_pct": 120})
    with pytest.raises(ConfigError, match="distance_ppm >= 0"):
        InstrumentProfile.from_dict({**FULL, "distance_ppm": -1})
    with pytest.raises(ConfigError, match="mapping"):
        InstrumentProfile.from_dict([1, 2])


def test_instrument_from_config_forms():
    assert instrument_from_config({"profile": "leica-ms60"}) is INSTRUMENTS["leica-ms60"]
    custom = instrument_from_config({"profile": "trimble-s7", "angle_arcsec": 4.0})
    assert custom.name == "trimble-s7-custom"
    assert custom.angle_rad == pytest.approx(4 * ARCSEC)
    assert custom.confidence_sigma == TRIMBLE_S7.confidence_sigma
    assert instrument_from_config(FULL).name == "my-rts"
    with pytest.raises(ConfigError, match="Unknown instrument"):
        instrument_from_config({"profile": "nope"})
    with pytest.raises(ConfigError, match="unknown key"):
        instrument_from_config({"profile": "trimble-s7", "angle": 1})


def test_sigma_distance_is_vectorised():
    d = np.array([0.0, 100.0, 1000.0])
    p = INSTRUMENTS["leica-ms60"]
    np.testing.assert_allclose(p.sigma_distance(d), 0.003 + 1.5e-6 * d)


# ---------------------------------------------------------------- through a deployment file

MY_RTS_TOML = """[instrument]
name = "My-RTS"
distance_constant_mm = 2.0
distance_ppm = 2.0
angle_arcsec = 1.0
tilt_arcsec = 0.5
confidence_sigma = 1
wavelength_um = 0.658
reference_temperature_c = 12
reference_pressure_hpa = 1013.25
reference_humidity_pct = 60
description = "our instrument, tracking mode"
"""


def real_config(tmp_path: Path, instrument_table: str) -> Path:
    """The real-excerpt configuration with absolute data paths and another [instrument]."""
    text = EXAMPLE.read_text().replace('"data/', f'"{EXCERPT}/')
    text = text.replace('[instrument]\nprofile = "trimble-s7"\n', instrument_table)
    assert instrument_table in text
    cfg = tmp_path / "deployment.toml"
    cfg.write_text(text)
    return cfg


def test_deployment_with_a_user_defined_instrument(tmp_path):
    from rtsgt.io.deployment import load_deployment

    data, opts = load_deployment(real_config(tmp_path, MY_RTS_TOML))
    expected = InstrumentProfile.from_dict({**FULL, "description": "our instrument, tracking mode"})
    assert data.instrument == expected and data.instrument.name == "my-rts"
    assert opts.noise.instrument == expected  # the noise model uses it
    data, opts = load_deployment(
        real_config(tmp_path, '[instrument]\nprofile = "leica-ms60"\ndistance_ppm = 1.0\n'))
    assert opts.noise.instrument.name == "leica-ms60-custom"
    assert opts.noise.instrument.distance_ppm == 1.0
    assert opts.noise.instrument.wavelength_um == INSTRUMENTS["leica-ms60"].wavelength_um


@pytest.mark.parametrize(
    "table, message",
    [
        ('[instrument]\nprofile = "theodolite-3000"\n', r"\[instrument\] Unknown instrument"),
        (MY_RTS_TOML.replace("tilt_arcsec = 0.5\n", ""), r"missing the key\(s\) tilt_arcsec"),
        (MY_RTS_TOML.replace("confidence_sigma = 1", "confidence_sigma = 0"),
         r"confidence_sigma > 0"),
        ('[instrument]\nprofile = "trimble-s7"\nangle = 1.0\n', r"unknown key\(s\) angle"),
    ],
)
def test_bad_instrument_tables_name_the_configuration(tmp_path, table, message):
    from rtsgt.io.deployment import load_deployment

    cfg = real_config(tmp_path, table)
    with pytest.raises(ConfigError, match=message) as info:
        load_deployment(cfg)
    assert info.value.path == str(cfg)
