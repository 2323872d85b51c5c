"""Angle units to and from radians: degrees, arc seconds, DMS, gon, mgon (vectorised).

rtsgt works in radians inside; readers convert with :func:`to_radians` and
:func:`dms_to_rad`, writers with :func:`from_radians` (docs/conventions.md#units).
"""

from __future__ import annotations

import re

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError

#: One degree, rad.
DEGREE = np.pi / 180.0
#: One arc second, rad.
ARCSEC = DEGREE / 3600.0
#: One gon (grad, 1/400 of a turn), rad.
GON = np.pi / 200.0
#: One milligon, rad.
MGON = GON / 1000.0

#: Unit names accepted by :func:`to_radians` and :func:`from_radians`.
ANGLE_UNITS = ("rad", "deg", "arcsec", "gon", "mgon", "dms")

_SCALE = {"rad": 1.0, "deg": DEGREE, "arcsec": ARCSEC, "gon": GON, "mgon": MGON}


def _first_bad(mask: np.ndarray):
    idx = tuple(int(i) for i in np.argwhere(mask)[0])
    return idx[0] if len(idx) == 1 else idx


def dms_to_rad(d: ArrayLike, m: ArrayLike = 0.0, s: ArrayLike = 0.0) -> np.ndarray:
    """Degrees ``d``, minutes ``m``, seconds ``s`` (broadcastable) to radians: negative when any
    is (``d = -0.0`` included), ``|d| + |m|/60 + |s|/3600`` in magnitude. Raises
    :class:`InputError` naming the first non-finite value or minutes/seconds outside [0, 60).
    """
    d, m, s = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (d, m, s)))
    for name, a in (("degrees", d), ("minutes", m), ("seconds", s)):
        bad = ~np.isfinite(a)
        if np.any(bad):
            i = _first_bad(bad)
            raise InputError(f"Expected finite DMS {name}, got {float(a[i])!r} at index {i}")
    for name, a in (("minutes", m), ("seconds", s)):
        bad = np.abs(a) >= 60.0
        if np.any(bad):
            i = _first_bad(bad)
            raise InputError(f"Expected DMS {name} in [0, 60), got {float(a[i])!r} at index {i}")
    negative = np.signbit(d) | (m < 0) | (s < 0)
    magnitude = np.abs(d) + np.abs(m) / 60.0 + np.abs(s) / 3600.0
    return np.where(negative, -magnitude, magnitude) * DEGREE


def rad_to_dms(a: ArrayLike, decimals: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Radians ``a`` to whole degrees ``d`` (signed, ``-0.0`` under one degree), whole minutes
    and seconds (non-negative), the seconds first rounded to ``decimals`` with the carries
    (``59.99996"`` never prints as ``60.0000"``); ``dms_to_rad(*rad_to_dms(a))`` is ``a``."""
    a = np.asarray(a, dtype=float)
    negative = np.signbit(a)
    total_s = np.abs(a) / ARCSEC
    if decimals is not None:
        total_s = np.round(total_s, decimals)
    d = np.floor(total_s / 3600.0)
    rest = total_s - d * 3600.0
    m = np.floor(rest / 60.0)
    s = rest - m * 60.0
    # floating-point guard: rest may round to exactly 3600 or s to 60
    carry = s >= 60.0
    m = np.where(carry, m + 1, m)
    s = np.where(carry, s - 60.0, s)
    carry = m >= 60.0
    d = np.where(carry, d + 1, d)
    m = np.where(carry, m - 60.0, m)
    if decimals is not None:
        s = np.round(s, decimals)
    d = np.where(negative, -d, d)  # -0.0 keeps the sign of angles under one degree
    return d, m, s


_DMS_SPLIT = re.compile(r"[\s:°º˚'’′\"”″dDmMsS]+")
_HEMI = {"N": 1.0, "E": 1.0, "S": -1.0, "W": -1.0}


def _parse_one_dms(text: str, index) -> float:
    raw = str(text).strip()
    if not raw:
        raise InputError(f"Expected a DMS angle, got an empty string at index {index}")
    body = raw
    sign = 1.0
    last, before = body[-1], body[-2:-1]
    # a trailing N/E/W, or an S after a blank or a seconds mark, is a hemisphere letter;
    # "15s" / "15S" right after digits is the seconds unit
    if last in "NEW" or (last == "S" and before in (" ", "\t", '"', "”", "″")):
        sign = _HEMI[last]
        body = body[:-1].strip()
    if body[:1] in "+-−":
        if body[0] in "-−":
            sign = -sign
        body = body[1:].strip()
    parts = [p for p in _DMS_SPLIT.split(body) if p != ""]
    if not 1 <= len(parts) <= 3:
        raise InputError(f"Expected a DMS angle 'd m s', got {raw!r} at index {index}")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise InputError(f"Expected a DMS angle 'd m s', got {raw!r} at index {index}") from None
    vals += [0.0] * (3 - len(vals))
    d, m, s = vals
    if any(v < 0 for v in vals) or not all(np.isfinite(vals)):
        raise InputError(
            f"Expected DMS components to be non-negative after the sign, got {raw!r} at index {index}"
        )
    if m >= 60 or s >= 60:
        raise InputError(f"Expected DMS minutes and seconds in [0, 60), got {raw!r} at index {index}")
    return sign * (d + m / 60.0 + s / 3600.0) * DEGREE


def parse_dms(text: str | ArrayLike) -> np.ndarray | float:
    """Radians of DMS strings ``text`` (a str, or array_like of them: the same shape), in the
    forms of docs/conventions.md#units."""
    if isinstance(text, str):
        return _parse_one_dms(text, 0)
    arr = np.asarray(text, dtype=object)
    out = np.empty(arr.shape)
    for idx in np.ndindex(arr.shape):  # strings: parsing is inherently per element
        out[idx] = _parse_one_dms(arr[idx], idx if len(idx) != 1 else idx[0])
    return out


def format_dms(a: ArrayLike, decimals: int = 1) -> np.ndarray | str:
    """Radians to DMS strings ``"-12°30'15.5\""`` (the inverse of :func:`parse_dms`)."""
    arr = np.asarray(a, dtype=float)
    d, m, s = rad_to_dms(arr, decimals)
    width = 3 + decimals if decimals > 0 else 2

    def one(di, mi, si):
        sign = "-" if np.signbit(di) else ""
        return f"{sign}{abs(di):.0f}°{mi:02.0f}'{si:0{width}.{decimals}f}\""

    if arr.ndim == 0:
        return one(float(d), float(m), float(s))
    out = np.empty(arr.shape, dtype=object)
    for idx in np.ndindex(arr.shape):
        out[idx] = one(d[idx], m[idx], s[idx])
    return out


def to_radians(value, unit: str) -> np.ndarray:
    """Angles ``value`` in ``unit`` ("rad", "deg", "arcsec", "gon", "mgon" or "dms": strings
    or (..., 3) numbers ``(d, m, s)``) to radians."""
    unit = unit.lower()
    if unit == "dms":
        arr = np.asarray(value)
        if isinstance(value, str) or arr.dtype.kind in "UO":
            return parse_dms(value)
        arr = np.asarray(value, dtype=float)
        if arr.shape[-1:] != (3,):
            raise InputError(f"Expected DMS tuples of shape (..., 3), got {arr.shape}")
        return dms_to_rad(arr[..., 0], arr[..., 1], arr[..., 2])
    if unit not in _SCALE:
        raise InputError(f"Unknown angle unit {unit!r}; known: {', '.join(ANGLE_UNITS)}")
    return np.asarray(value, dtype=float) * _SCALE[unit]


def from_radians(value: ArrayLike, unit: str, decimals: int = 1):
    """Convert radians to ``unit``; ``"dms"`` gives strings with ``decimals`` on the seconds."""
    unit = unit.lower()
    if unit == "dms":
        return format_dms(value, decimals)
    if unit not in _SCALE:
        raise InputError(f"Unknown angle unit {unit!r}; known: {', '.join(ANGLE_UNITS)}")
    return np.asarray(value, dtype=float) / _SCALE[unit]
