"""Weather readers: Environment and Climate Change Canada (ECCC) hourly files (French or
English, decimal commas read field by field, local standard time, station pressure kPa ->
hPa) and rtsgt's CSV ``t_s,temperature_c,pressure_hpa,humidity_pct``. Whether a record
covers the measurements is :func:`rtsgt.measurement.weather.check_weather_coverage`'s.
docs/file-formats.md#weather.
"""

from __future__ import annotations

import csv
import io
import re
import warnings
from os import PathLike

import numpy as np

from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.io._parse import (
    ENCODINGS,
    atomic_write_text,
    check_increasing,
    find_columns,
    fmt_float,
    read_lines,
    read_text,
    split_rows,
    to_float,
)
from rtsgt.types import WeatherSeries

#: Columns of the native weather CSV, in the order written.
WEATHER_CSV_COLUMNS = ("t_s", "temperature_c", "pressure_hpa", "humidity_pct")

#: Header patterns of the ECCC columns (matched on the lower-cased, space-normalised header;
#: ``.*`` where an accent or a degree sign may have been mangled by a wrong encoding).
_ECCC_PATTERNS = {
    "time": re.compile(r"^date/(heure \(hnl\)|time \(lst\))$"),
    "temperature": re.compile(r"^temp \(.{0,3}c\)$"),
    "humidity": re.compile(r"^(hum\. rel|rel hum) \(%\)$"),
    "pressure": re.compile(r"^(pression .{1,3} la station|stn press) \(kpa\)$"),
}

#: Plausible ranges, to catch a wrong column or unit early (degC, hPa, %).
_RANGES = {
    "temperature": (-90.0, 60.0, "degC"),
    "pressure": (300.0, 1100.0, "hPa"),
    "humidity": (0.0, 100.0, "%"),
}


def _normalise(header: str) -> str:
    return " ".join(header.strip().lower().split())


def _check_ranges(values: dict[str, np.ndarray], numbers, path, names: dict[str, str]) -> None:
    for key, (lo, hi, unit) in _RANGES.items():
        a = values[key]
        bad = np.flatnonzero((a < lo) | (a > hi))
        if bad.size:
            i = bad[0]
            raise InputError(
                f"implausible {key} {a[i]:g} {unit} in column {names[key]!r} "
                f"(expected {lo:g} to {hi:g} {unit}): wrong column or unit?",
                path, numbers[i],
            )


def weather_format(path: str | PathLike) -> str | None:
    """The weather format of a file, from its first line: ``"eccc"`` (an ECCC hourly file:
    its time and temperature columns), ``"csv"`` (the native CSV: its four columns), or None
    (neither, or a file that cannot be read). Reads the first 64 kB only."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
    except OSError:
        return None
    for enc in ENCODINGS:
        try:
            text = head.decode(enc)
            break
        except UnicodeDecodeError:
            continue
    else:
        return None
    lines = [s for s in text.splitlines() if s.strip() and not s.lstrip().startswith("#")]
    if not lines:
        return None
    header = [_normalise(h) for h in next(csv.reader([lines[0]]))]
    if all(any(_ECCC_PATTERNS[k].match(h) for h in header) for k in ("time", "temperature")):
        return "eccc"
    if set(WEATHER_CSV_COLUMNS) <= set(header):
        return "csv"
    return None


def read_weather_eccc(path: str | PathLike, *, utc_offset_hours: float = -5.0) -> WeatherSeries:
    """Read a raw ECCC hourly weather file (French or English headers) into a
    :class:`~rtsgt.types.WeatherSeries` (Unix s, degC, station hPa, %), its local standard time
    ``utc_offset_hours`` from UTC (Quebec: -5). Incomplete rows are skipped with a warning
    naming them; bad input raises :class:`~rtsgt.errors.InputError` naming the file and line."""
    off = float(utc_offset_hours)
    if not (np.isfinite(off) and -14.0 <= off <= 14.0):
        raise InputError(f"Expected utc_offset_hours in [-14, 14], got {utc_offset_hours!r}")
    text = read_text(path)
    numbers_all = []
    rows = []
    reader = csv.reader(io.StringIO(text))
    for row in reader:
        if any(s.strip() for s in row):
            numbers_all.append(reader.line_num)
            rows.append(row)
    if not rows:
        raise InputError("empty file: expected an ECCC hourly weather CSV", path)
    header = rows[0]
    norm = [_normalise(h) for h in header]
    cols: dict[str, int] = {}
    for key, pattern in _ECCC_PATTERNS.items():
        hits = [j for j, h in enumerate(norm) if pattern.match(h)]
        if not hits:
            raise InputError(
                f"no {key} column in the header (expected e.g. "
                f"{'Date/Heure (HNL)' if key == 'time' else pattern.pattern!r}); "
                "is this an ECCC hourly file?",
                path, numbers_all[0],
            )
        cols[key] = hits[0]
    names = {k: header[j].strip() for k, j in cols.items()}
    numbers, kept, skipped = [], [], []
    for row, number in zip(rows[1:], numbers_all[1:], strict=True):
        if len(row) != len(header):
            raise InputError(
                f"expected {len(header)} comma-separated fields as in the header, got {len(row)}",
                path, number,
            )
        fields = [row[cols[k]].strip() for k in ("time", "temperature", "pressure", "humidity")]
        if any(f == "" for f in fields):
            skipped.append(number)
            continue
        numbers.append(number)
        kept.append(fields)
    if skipped:
        shown = ", ".join(map(str, skipped[:10])) + (", ..." if len(skipped) > 10 else "")
        warnings.warn(
            f"{path}: skipped {len(skipped)} row(s) with a missing time, temperature, pressure "
            f"or humidity (lines {shown})",
            RtsgtWarning, stacklevel=2,
        )
    if not kept:
        raise InputError("no row with time, temperature, pressure and humidity all present", path)
    tokens = np.array(kept, dtype=object)
    stamps = tokens[:, 0].astype(str)
    try:
        local = stamps.astype("datetime64[s]").astype(np.int64)
    except ValueError:
        for s, number in zip(stamps, numbers, strict=True):
            try:
                np.datetime64(s, "s")
            except ValueError:
                raise InputError(
                    f"expected a date 'YYYY-MM-DD HH:MM' in column {names['time']!r}, got {s!r}",
                    path, number,
                ) from None
        raise  # pragma: no cover
    # local standard time = UTC + offset  =>  UTC epoch = local "as if UTC" - offset
    t = local.astype(float) - off * 3600.0
    values = to_float(
        tokens[:, 1:], numbers, path,
        (names["temperature"], names["pressure"], names["humidity"]), decimal_comma=True,
    )
    temperature, pressure_kpa, humidity = values.T
    pressure = pressure_kpa * 10.0  # kPa -> hPa
    _check_ranges(
        {"temperature": temperature, "pressure": pressure, "humidity": humidity},
        numbers, path, names,
    )
    check_increasing(t, numbers, path)
    return WeatherSeries(t, temperature, pressure, humidity, source=str(path))


def read_weather_csv(path: str | PathLike) -> WeatherSeries:
    """Read the native weather CSV ``t_s,temperature_c,pressure_hpa,humidity_pct``.

    Raises
    ------
    InputError
        Naming the file and line: empty file, missing column, wrong column count,
        non-numeric or non-finite value, implausible value, times not strictly increasing,
        times that look like ms, us or ns (not seconds).
    """
    numbers, lines = read_lines(path, "a header " + ",".join(WEATHER_CSV_COLUMNS) + " and rows")
    header = [h.strip() for h in lines[0].split(",")]
    pos = find_columns(header, WEATHER_CSV_COLUMNS, path, numbers[0])
    numbers, lines = numbers[1:], lines[1:]
    if not lines:
        raise InputError("no weather record after the header", path)
    tokens = split_rows(lines, numbers, path, header, ",")
    order = [pos[c] for c in WEATHER_CSV_COLUMNS]
    values = to_float(tokens[:, order], numbers, path, WEATHER_CSV_COLUMNS)
    t, temperature, pressure, humidity = values.T
    _check_ranges(
        {"temperature": temperature, "pressure": pressure, "humidity": humidity},
        numbers, path,
        {"temperature": "temperature_c", "pressure": "pressure_hpa", "humidity": "humidity_pct"},
    )
    check_increasing(t, numbers, path, "t_s")
    return WeatherSeries(t, temperature, pressure, humidity, source=str(path))


def write_weather_csv(path: str | PathLike, weather: WeatherSeries) -> None:
    """Write a weather series as native CSV, atomically, with exact float representations."""
    atomic_write_text(path, weather_csv_text(weather))


def weather_csv_text(weather: WeatherSeries) -> str:
    """Text of a native weather CSV (header and one line per record)."""
    cols = (weather.t, weather.temperature_c, weather.pressure_hpa, weather.humidity_pct)
    if not all(np.all(np.isfinite(a)) for a in cols):
        raise ValueError("Expected finite weather values to write, got NaN or inf")
    body = "".join(",".join(fmt_float(x) for x in row) + "\n" for row in zip(*cols, strict=True))
    return ",".join(WEATHER_CSV_COLUMNS) + "\n" + body
