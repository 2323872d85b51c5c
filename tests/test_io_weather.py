"""Weather readers: the raw ECCC hourly file (French/English) and the native CSV."""

from __future__ import annotations

import csv
import io
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest

from _paths import EXCERPT as DATA
from rtsgt.errors import InputError
from rtsgt.io.weather import read_weather_csv, read_weather_eccc, write_weather_csv
from rtsgt.types import WeatherSeries

ECCC = DATA / "weather_ECCC_raw_excerpt.csv"
SORTED = DATA / "weather_sorted_excerpt.txt"

EN_HEADERS = {
    "Date/Heure (HNL)": "Date/Time (LST)",
    "Hum. rel (%)": "Rel Hum (%)",
    "Pression à la station (kPa)": "Stn Press (kPa)",
}


def raw_rows() -> list[list[str]]:
    return list(csv.reader(io.StringIO(ECCC.read_text(encoding="utf-8-sig"))))


def write_rows(path: Path, rows, encoding="utf-8") -> Path:
    buf = io.StringIO()
    csv.writer(buf, quoting=csv.QUOTE_ALL, lineterminator="\n").writerows(rows)
    path.write_text(buf.getvalue(), encoding=encoding)
    return path


def test_real_eccc_excerpt():
    w = read_weather_eccc(ECCC)
    assert len(w.t) == 24
    # 2022-11-10 00:00 HNL = 05:00 UTC
    assert w.t[0] == 1668056400.0
    assert w.t[0] == datetime(2022, 11, 10, 5, 0, tzinfo=timezone.utc).timestamp()
    np.testing.assert_array_equal(np.diff(w.t), 3600.0)
    # forest station at ~640 m: station pressure 93.49-94.06 kPa, not ~103 kPa
    assert w.pressure_hpa[0] == pytest.approx(940.6)
    assert w.pressure_hpa[2] == pytest.approx(939.6)  # "93,96", the reference code's 1026
    assert np.all((w.pressure_hpa > 934.0) & (w.pressure_hpa < 941.0))
    np.testing.assert_allclose(w.temperature_c[:4], [1.9, 1.2, 1.6, 2.2])
    np.testing.assert_allclose(w.humidity_pct[:4], [63, 81, 86, 92])
    assert w.source == str(ECCC)
    # at the deployment (10:44 HNL = 15:44 UTC) the interpolated weather is sensible
    temperature, pressure, humidity = w.at(1668095037.0)
    assert 2.0 < temperature < 3.0 and 937.0 < pressure < 937.5 and 90 < humidity <= 96


def reference_bug_hpa(field: str) -> float:
    """The reference code's digit-wise parse: "93,96" -> 93 + 96/10 = 102.6 kPa (SOURCE.md)."""
    whole, frac = field.split(",")
    return 10.0 * (int(whole) + int(frac) / 10.0)


def test_differs_from_reference_sorted_file_exactly_where_it_is_wrong():
    w = read_weather_eccc(ECCC)
    ref = np.loadtxt(SORTED, usecols=(0, 1, 2, 3))
    t_ref, temp_ref, hum_ref, p_ref = ref.T
    # the reference took local standard time as UTC-4 instead of UTC-5: its epochs are 1 h early
    idx = np.searchsorted(t_ref, w.t - 3600.0)
    np.testing.assert_array_equal(t_ref[idx], w.t - 3600.0)
    j = np.flatnonzero(t_ref == w.t[0])[0]  # at rtsgt's 00:00 HNL the reference has 01:00
    assert (temp_ref[j], hum_ref[j]) == (w.temperature_c[1], w.humidity_pct[1]) == (1.2, 81.0)
    # temperature and humidity agree once the epochs are aligned
    np.testing.assert_array_equal(temp_ref[idx], w.temperature_c)
    np.testing.assert_array_equal(hum_ref[idx], w.humidity_pct)
    # pressure: the reference's garbled values are exactly its digit-wise decimal-comma parse
    rows = raw_rows()
    col = rows[0].index("Pression à la station (kPa)")
    fields = [r[col] for r in rows[1:]]
    np.testing.assert_allclose(p_ref[idx], [reference_bug_hpa(f) for f in fields])
    # ... while rtsgt reads the whole field: 10 x the kPa value, and differs on every row
    np.testing.assert_allclose(w.pressure_hpa, [10 * float(f.replace(",", ".")) for f in fields])
    assert np.all(np.abs(p_ref[idx] - w.pressure_hpa) > 0.5)
    assert p_ref[idx].max() > 1000.0 > w.pressure_hpa.max()


def test_english_headers_decimal_points_and_cp1252(tmp_path):
    rows = raw_rows()
    rows[0] = [EN_HEADERS.get(h, h) for h in rows[0]]
    rows[1:] = [[f.replace(",", ".") for f in r] for r in rows[1:]]
    en = read_weather_eccc(write_rows(tmp_path / "en.csv", rows))
    fr = read_weather_eccc(ECCC)
    for name in ("t", "temperature_c", "pressure_hpa", "humidity_pct"):
        np.testing.assert_array_equal(getattr(en, name), getattr(fr, name))
    latin = read_weather_eccc(write_rows(tmp_path / "cp.csv", raw_rows(), encoding="cp1252"))
    np.testing.assert_array_equal(latin.pressure_hpa, fr.pressure_hpa)
    bom = read_weather_eccc(write_rows(tmp_path / "bom.csv", raw_rows(), encoding="utf-8-sig"))
    np.testing.assert_array_equal(bom.t, fr.t)


def test_utc_offset_is_applied():
    a = read_weather_eccc(ECCC)
    b = read_weather_eccc(ECCC, utc_offset_hours=0.0)
    c = read_weather_eccc(ECCC, utc_offset_hours=-4.0)
    np.testing.assert_array_equal(a.t - b.t, 5 * 3600.0)
    np.testing.assert_array_equal(a.t - c.t, 3600.0)
    with pytest.raises(InputError, match="utc_offset_hours"):
        read_weather_eccc(ECCC, utc_offset_hours=20)


def test_rows_with_missing_values_are_skipped_and_counted(tmp_path):
    rows = raw_rows()
    h = rows[0]
    rows[3][h.index("Pression à la station (kPa)")] = ""
    rows[5][h.index("Temp (°C)")] = ""
    p = write_rows(tmp_path / "gaps.csv", rows)
    with pytest.warns(UserWarning, match=r"skipped 2 row\(s\) .* \(lines 4, 6\)"):
        w = read_weather_eccc(p)
    assert len(w.t) == 22
    full = read_weather_eccc(ECCC)
    np.testing.assert_array_equal(w.t, np.delete(full.t, [2, 4]))
    for r in rows[1:]:
        r[h.index("Hum. rel (%)")] = ""
    with pytest.warns(UserWarning), pytest.raises(InputError, match="no row with"):
        read_weather_eccc(write_rows(tmp_path / "none.csv", rows))


def _edit(rows, line, header, value):
    rows = [list(r) for r in rows]
    rows[line - 1][rows[0].index(header)] = value
    return rows


@pytest.mark.parametrize(
    "edit, line, pattern",
    [
        (lambda r: _edit(r, 4, "Pression à la station (kPa)", "93,x"),
         4, r"number in column 'Pression à la station \(kPa\)', got '93,x'"),
        (lambda r: _edit(r, 5, "Date/Heure (HNL)", "10/11/2022 03:00"), 5, r"date 'YYYY-MM-DD"),
        (lambda r: _edit(r, 6, "Temp (°C)", "nan"), 6, r"finite number in column 'Temp"),
        (lambda r: _edit(r, 7, "Pression à la station (kPa)", "940,6"), 7,
         r"implausible pressure 9406 hPa .* wrong column or unit"),
        (lambda r: _edit(r, 8, "Hum. rel (%)", "181"), 8, r"implausible humidity 181"),
        (lambda r: _edit(r, 9, "Date/Heure (HNL)", "2022-11-10 06:00"), 9,
         r"duplicated timestamp .* remove the duplicate line 9"),
        (lambda r: _edit(r, 9, "Date/Heure (HNL)", "2022-11-10 02:00"), 9, r"sort the file"),
        (lambda r: r[:5] + [r[5][:-1]] + r[6:], 6, r"expected 30 comma-separated fields"),
        (lambda r: [[h for h in r[0] if not h.startswith("Pression")]], 1,
         r"no pressure column in the header"),
    ],
)
def test_eccc_bad_input_names_file_and_line(tmp_path, edit, line, pattern):
    p = write_rows(tmp_path / "bad.csv", edit(raw_rows()))
    with pytest.raises(InputError, match=pattern) as info:
        read_weather_eccc(p)
    assert info.value.path == str(p) and info.value.line == line


def test_eccc_empty_and_missing(tmp_path):
    (tmp_path / "e.csv").write_text("\n\n")
    with pytest.raises(InputError, match="empty file"):
        read_weather_eccc(tmp_path / "e.csv")
    with pytest.raises(InputError, match="file not found"):
        read_weather_eccc(tmp_path / "missing.csv")


def test_native_csv_round_trip(tmp_path):
    w = read_weather_eccc(ECCC)
    out = tmp_path / "weather.csv"
    write_weather_csv(out, w)
    assert out.read_text().splitlines()[0] == "t_s,temperature_c,pressure_hpa,humidity_pct"
    back = read_weather_csv(out)
    for name in ("t", "temperature_c", "pressure_hpa", "humidity_pct"):
        np.testing.assert_array_equal(getattr(back, name), getattr(w, name))
    rng = np.random.default_rng(0)
    r = WeatherSeries(np.cumsum(rng.uniform(1, 10, 50)), rng.normal(10, 5, 50),
                      rng.uniform(900, 1030, 50), rng.uniform(10, 100, 50))
    write_weather_csv(out, r)
    np.testing.assert_array_equal(read_weather_csv(out).pressure_hpa, r.pressure_hpa)


@pytest.mark.parametrize(
    "text, line, pattern",
    [
        ("t_s,temperature_c,pressure_hpa\n1,2,900\n", 1, r"missing column\(s\) humidity_pct"),
        ("t_s,temperature_c,pressure_hpa,humidity_pct\n1,2,900\n", 2, r"expected 4 ,-sep"),
        ("t_s,temperature_c,pressure_hpa,humidity_pct\n1,2,9x0,50\n", 2, r"'pressure_hpa'"),
        ("t_s,temperature_c,pressure_hpa,humidity_pct\n1,2,900,50\n1,2,900,50\n", 3,
         r"duplicated timestamp"),
        ("t_s,temperature_c,pressure_hpa,humidity_pct\n1,2,94,50\n", 2, r"implausible pressure"),
        ("t_s,temperature_c,pressure_hpa,humidity_pct\n", None, r"no weather record"),
        ("", None, r"empty file"),
    ],
)
def test_native_csv_bad_input(tmp_path, text, line, pattern):
    p = tmp_path / "w.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=pattern) as info:
        read_weather_csv(p)
    assert info.value.path == str(p) and info.value.line == line


# -- coverage of the measurement times ---------------------------------------------------------

HOURLY = WeatherSeries(1668056400.0 + 3600.0 * np.arange(6), np.full(6, 2.0), np.full(6, 937.0),
                       np.full(6, 80.0), source="hourly.csv")


def test_coverage_tolerance_is_the_record_interval():
    """A time is covered when a record lies within one sampling interval (the median spacing
    of the records: 1 h for hourly files) of it."""
    from rtsgt.measurement.weather import weather_coverage

    last = HOURLY.t[-1]
    near = weather_coverage(HOURLY, last + 20 * 60.0 + np.arange(10.0))
    assert near["covered"] and near["uncovered_measurements"] == 0
    assert near["sampling_interval_s"] == 3600.0
    assert near["after_last_s"] == pytest.approx(20 * 60.0 + 9.0)
    far = weather_coverage(HOURLY, last + 3 * 3600.0 + np.arange(10.0))
    assert not far["covered"] and far["uncovered_measurements"] == 10
    assert far["after_last_s"] == pytest.approx(3 * 3600.0 + 9.0)
    assert far["before_first_s"] == 0.0
    assert (far["first_t_s"], far["last_t_s"], far["records"]) == (HOURLY.t[0], last, 6)
    assert far["first_utc"] == "2022-11-10 05:00:00" and far["file"] == "hourly.csv"
    early = weather_coverage(HOURLY, HOURLY.t[0] - np.array([7200.0, 0.0]))
    assert not early["covered"] and early["before_first_s"] == 7200.0
    assert early["uncovered_measurements"] == 1
    # one record has no interval: it is the deployment's constant weather (module docstring)
    one = WeatherSeries(HOURLY.t[:1], HOURLY.temperature_c[:1], HOURLY.pressure_hpa[:1],
                        HOURLY.humidity_pct[:1], source="one.csv")
    single = weather_coverage(one, one.t[0] + 5 * 3600.0 + np.arange(3.0))
    assert single["sampling_interval_s"] is None and single["covered"]
    assert single["after_last_s"] == 5 * 3600.0 + 2.0


def test_coverage_sees_a_gap_inside_the_record():
    from rtsgt.measurement.weather import weather_coverage

    hours = np.array([0, 1, 2, 3, 7, 8, 9])  # hours 4-6 missing: 4 h between two records
    w = WeatherSeries(1668056400.0 + 3600.0 * hours, np.full(7, 2.0), np.full(7, 937.0),
                      np.full(7, 80.0), source="gappy.csv")
    mid = weather_coverage(w, np.array([w.t[3] + 2 * 3600.0]))
    assert mid["sampling_interval_s"] == 3600.0
    assert not mid["covered"] and mid["max_distance_to_record_s"] == 2 * 3600.0
    assert mid["before_first_s"] == mid["after_last_s"] == 0.0
    assert weather_coverage(w, np.array([w.t[3] + 0.5 * 3600.0]))["covered"]


def test_check_warns_naming_the_file_and_how_far():
    from rtsgt.errors import RtsgtWarning
    from rtsgt.measurement.weather import check_weather_coverage

    with pytest.warns(RtsgtWarning, match=r"hourly\.csv.*3\.0 h after the last record"):
        info = check_weather_coverage(HOURLY, HOURLY.t[-1] + 3 * 3600.0 + np.arange(60.0))
    assert not info["covered"]
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_weather_coverage(HOURLY, HOURLY.t[2] + np.arange(60.0))["covered"]
