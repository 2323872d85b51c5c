"""Angle units: degrees, arc seconds, gon, DMS (numbers and strings), with robust signs."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rtsgt.errors import InputError
from rtsgt.measurement.units import (
    ARCSEC,
    GON,
    dms_to_rad,
    format_dms,
    from_radians,
    parse_dms,
    rad_to_dms,
    to_radians,
)


def test_unit_constants_and_simple_conversions():
    assert to_radians(180.0, "deg") == pytest.approx(np.pi)
    assert np.rad2deg(np.pi / 2) == pytest.approx(90.0)
    assert to_radians(400.0, "gon") == pytest.approx(2 * np.pi)
    assert from_radians(np.pi, "gon") == pytest.approx(200.0)
    assert GON == pytest.approx(np.pi / 200)
    assert ARCSEC * 3600 * 180 == pytest.approx(np.pi)
    # 1 mgon = 3.24 arc seconds (surveyor's rule)
    assert to_radians(1.0, "mgon") / ARCSEC == pytest.approx(3.24)
    np.testing.assert_allclose(to_radians([0, 100, 300], "gon"), [0, np.pi / 2, 1.5 * np.pi])


def test_dms_signs():
    # the sign applies to the whole angle, whichever component carries it
    assert np.rad2deg(dms_to_rad(-12, 30, 0)) == pytest.approx(-12.5)
    assert np.rad2deg(dms_to_rad(-0.0, 30, 0)) == pytest.approx(-0.5)
    assert np.rad2deg(dms_to_rad(0, -30, 0)) == pytest.approx(-0.5)
    assert np.rad2deg(dms_to_rad(0, 0, -36)) == pytest.approx(-0.01)
    assert np.rad2deg(dms_to_rad(12, 30, 0)) == pytest.approx(12.5)
    np.testing.assert_allclose(
        np.rad2deg(dms_to_rad([1, -1, -0.0], [30, 30, 30], [0, 0, 0])), [1.5, -1.5, -0.5]
    )


@pytest.mark.parametrize(
    "text, deg",
    [
        ("-12 30 15.5", -(12 + 30 / 60 + 15.5 / 3600)),
        ("12°30'15.5\"", 12 + 30 / 60 + 15.5 / 3600),
        ("12:30:15.5", 12 + 30 / 60 + 15.5 / 3600),
        ("12d30m15.5s", 12 + 30 / 60 + 15.5 / 3600),
        ("-0 30 0", -0.5),
        ("+5", 5.0),
        ("12 30", 12.5),
        ("45 00 00 S", -45.0),
        ("45°00'00\" W", -45.0),
        ("10 0 0 N", 10.0),
        ("−3 0 0", -3.0),  # Unicode minus
        ("359 59 59.9999", 359 + 59 / 60 + 59.9999 / 3600),
    ],
)
def test_parse_dms_forms(text, deg):
    assert np.rad2deg(parse_dms(text)) == pytest.approx(deg, abs=1e-12)


def test_parse_dms_array_keeps_shape():
    out = parse_dms(np.array([["1 0 0", "-2 0 0"], ["0 30 0", "0 0 36"]]))
    np.testing.assert_allclose(np.rad2deg(out), [[1, -2], [0.5, 0.01]])
    np.testing.assert_allclose(to_radians(["90 0 0"], "dms"), [np.pi / 2])
    np.testing.assert_allclose(to_radians([[90, 0, 0], [-0.0, 30, 0]], "dms"),
                               [np.pi / 2, -np.pi / 360])


@pytest.mark.parametrize("bad", ["", "abc", "12 60 00", "12 30 60", "1 2 3 4", "12 -30 0"])
def test_parse_dms_errors_name_the_value(bad):
    with pytest.raises(InputError) as exc:
        parse_dms(["0 0 0", bad])
    assert "index 1" in str(exc.value)


def test_dms_numeric_errors_name_value_and_index():
    with pytest.raises(InputError, match=r"minutes in \[0, 60\), got 61.0 at index 1"):
        dms_to_rad([1, 2], [0, 61], [0, 0])
    with pytest.raises(InputError, match="finite"):
        dms_to_rad([np.nan], [0], [0])
    with pytest.raises(InputError, match="Unknown angle unit"):
        to_radians(1.0, "furlong")


@settings(max_examples=200, deadline=None)
@given(a=st.floats(-4 * np.pi, 4 * np.pi, allow_nan=False))
def test_dms_round_trip(a):
    d, m, s = rad_to_dms(a)
    assert 0 <= m < 60 and 0 <= s < 60
    assert float(dms_to_rad(d, m, s)) == pytest.approx(a, abs=1e-14)
    # through strings, at 1e-4 arc second
    back = parse_dms(format_dms(a, decimals=4))
    assert abs(back - a) <= 0.51e-4 * ARCSEC + 1e-15


def test_rad_to_dms_carries_rounded_seconds():
    a = dms_to_rad(10, 59, 59.99996)
    d, m, s = rad_to_dms(a, decimals=4)
    assert (float(d), float(m), float(s)) == (11.0, 0.0, 0.0)
    assert format_dms(a, decimals=4) == "11°00'00.0000\""
    assert format_dms(-np.radians(0.5)) == "-0°30'00.0\""
    assert from_radians(np.pi, "gon") == pytest.approx(200.0)
