"""Whether a weather record covers the measurement times it serves.

A time is covered when a record lies within one sampling interval (the records' median
spacing) of it; a single record covers every time (docs/file-formats.md, the weather file).
"""

from __future__ import annotations

import warnings
from datetime import datetime, timezone

import numpy as np

from rtsgt.errors import RtsgtWarning

__all__ = ["weather_coverage", "check_weather_coverage"]


def _utc(t: float) -> str:
    return datetime.fromtimestamp(float(t), timezone.utc).strftime("%Y-%m-%d %H:%M:%S")


def _duration(seconds: float) -> str:
    """A duration for messages: ``"3.0 h"``, ``"25 min"``, ``"40 s"``."""
    s = abs(float(seconds))
    if s >= 2 * 3600.0:
        return f"{s / 3600.0:.1f} h"
    if s >= 120.0:
        return f"{s / 60.0:.0f} min"
    return f"{s:.0f} s"


def weather_coverage(weather, t) -> dict:
    """How well a weather record (a :class:`~rtsgt.types.WeatherSeries`) covers the finite
    measurement times ``t`` (M,), s (Unix): a time is covered with a record within the median
    spacing of the records (the module docstring). JSON-ready: the record's ``file``,
    ``records``, span (s and UTC text) and ``sampling_interval_s``; the measurements' count and
    span, ``before_first_s``/``after_last_s`` outside the record, ``max_distance_to_record_s``,
    ``uncovered_measurements`` and ``covered``.
    """
    tw = np.asarray(weather.t, dtype=float)
    t = np.asarray(t, dtype=float).ravel()
    t = t[np.isfinite(t)]
    interval = float(np.median(np.diff(tw))) if tw.size > 1 else None
    info = {
        "file": weather.source, "records": int(tw.size),
        "first_t_s": float(tw[0]), "last_t_s": float(tw[-1]),
        "first_utc": _utc(tw[0]), "last_utc": _utc(tw[-1]),
        "sampling_interval_s": interval, "measurements": int(t.size),
        "measurements_first_t_s": float(t.min()) if t.size else None,
        "measurements_last_t_s": float(t.max()) if t.size else None,
        "before_first_s": 0.0, "after_last_s": 0.0, "max_distance_to_record_s": 0.0,
        "uncovered_measurements": 0, "covered": True,
    }
    if t.size == 0:
        return info
    k = np.searchsorted(tw, t)
    left = tw[np.clip(k - 1, 0, tw.size - 1)]
    right = tw[np.clip(k, 0, tw.size - 1)]
    distance = np.minimum(np.abs(t - left), np.abs(t - right))
    uncovered = 0 if interval is None else int(np.sum(distance > interval))
    info.update({
        "before_first_s": float(max(0.0, tw[0] - t.min())),
        "after_last_s": float(max(0.0, t.max() - tw[-1])),
        "max_distance_to_record_s": float(distance.max()),
        "uncovered_measurements": uncovered, "covered": uncovered == 0,
    })
    return info


def check_weather_coverage(weather, t) -> dict:
    """:func:`weather_coverage`, with a :class:`~rtsgt.errors.RtsgtWarning` when the record
    does not cover every time: it names the file, the record's span and interval, how many
    measurements lie outside and how far (before the first record, after the last one, or in
    a gap of the record)."""
    info = weather_coverage(weather, t)
    if info["covered"]:
        return info
    where = []
    if info["before_first_s"] > info["sampling_interval_s"]:
        where.append(f"{_duration(info['before_first_s'])} before the first record")
    if info["after_last_s"] > info["sampling_interval_s"]:
        where.append(f"{_duration(info['after_last_s'])} after the last record")
    if not where:
        where.append(f"{_duration(info['max_distance_to_record_s'])} from the nearest record, "
                     "in a gap of the record")
    warnings.warn(
        f"weather {info['file'] or '(no file)'}: {info['uncovered_measurements']} of "
        f"{info['measurements']} measurement times lie more than one record interval "
        f"({_duration(info['sampling_interval_s'])}) from any weather record (records "
        f"{info['first_utc']} to {info['last_utc']} UTC; measurements "
        f"{_utc(info['measurements_first_t_s'])} to {_utc(info['measurements_last_t_s'])} UTC, "
        f"up to {' and '.join(where)}): the atmospheric correction there uses the nearest "
        "record's weather; give a weather file that covers the deployment",
        RtsgtWarning, stacklevel=2,
    )
    return info
