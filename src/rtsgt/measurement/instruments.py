"""Instrument profiles: a total station's datasheet accuracies, and at what confidence.

A profile stores the numbers as published with ``confidence_sigma``; its ``sigma_*`` methods
return one-standard-deviation values. The built-in profiles (:data:`INSTRUMENTS`, tracking
mode) and their sources: docs/noise-model.md#instrument.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import ConfigError, InputError

#: One arc second, rad.
ARCSEC = np.pi / (180.0 * 3600.0)

_DICT_REQUIRED = (
    "name", "distance_constant_mm", "distance_ppm", "angle_arcsec", "tilt_arcsec",
    "confidence_sigma", "wavelength_um", "reference_temperature_c", "reference_pressure_hpa",
    "reference_humidity_pct",
)
_DICT_OPTIONAL = ("description",)


@dataclass(frozen=True)
class InstrumentProfile:
    """Accuracy and EDM parameters of a total station, as its datasheet gives them
    (docs/noise-model.md#instrument).

    ``name`` (lower case, e.g. ``"trimble-s7"``); the distance accuracy ``a + b ppm`` as
    ``distance_constant_m`` (m) and ``distance_ppm``; ``angle_rad`` of the direction and zenith
    angle and ``tilt_rad`` of the compensator; ``confidence_sigma``: how many sigmas those are
    quoted at; ``wavelength_um`` of the EDM; the reference atmosphere of zero ppm (degC, hPa,
    %); ``description``: the mode and datasheet.
    """

    name: str
    distance_constant_m: float
    distance_ppm: float
    angle_rad: float
    tilt_rad: float
    confidence_sigma: float
    wavelength_um: float
    reference_temperature_c: float
    reference_pressure_hpa: float
    reference_humidity_pct: float
    description: str = ""

    def __post_init__(self) -> None:
        for f in ("distance_constant_m", "distance_ppm", "angle_rad", "tilt_rad"):
            val = getattr(self, f)
            if not np.isfinite(val) or val < 0:
                raise InputError(f"Instrument {self.name!r}: expected {f} >= 0, got {val}")
        for f, ok, bound in (
            ("confidence_sigma", self.confidence_sigma > 0, "> 0"),
            ("wavelength_um", self.wavelength_um > 0, "> 0"),
            ("reference_temperature_c", self.reference_temperature_c > -273.15, "> -273.15"),
            ("reference_pressure_hpa", self.reference_pressure_hpa > 0, "> 0"),
            ("reference_humidity_pct", 0 <= self.reference_humidity_pct <= 100, "in [0, 100]"),
        ):
            if not ok:
                raise InputError(f"Instrument {self.name!r}: expected {f} {bound}, "
                                 f"got {getattr(self, f)}")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> InstrumentProfile:
        """A user-defined profile from a configuration table of the keys ``_DICT_REQUIRED``
        (and ``description``), in datasheet units (mm, arc seconds); raises
        :class:`ConfigError` naming a missing or unknown key or a value not a number."""
        if not isinstance(d, Mapping):
            raise ConfigError(f"Expected an instrument table (mapping), got {type(d).__name__}")
        missing = [k for k in _DICT_REQUIRED if k not in d]
        unknown = sorted(set(d) - set(_DICT_REQUIRED) - set(_DICT_OPTIONAL))
        if unknown:
            raise ConfigError(
                f"Instrument profile has unknown key(s) {', '.join(unknown)}; "
                f"known: {', '.join(_DICT_REQUIRED + _DICT_OPTIONAL)}"
            )
        if missing:
            raise ConfigError(
                f"Instrument profile {d.get('name', '?')!r} is missing the key(s) "
                f"{', '.join(missing)}"
            )
        vals = {}
        for k in _DICT_REQUIRED[1:]:
            v = d[k]
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise ConfigError(f"Instrument profile key {k} must be a number, got {v!r}")
            vals[k] = float(v)
        name = d["name"]
        if not isinstance(name, str) or not name.strip():
            raise ConfigError(f"Instrument profile key name must be a non-empty string, got {name!r}")
        description = d.get("description", "user-defined profile")
        try:
            return cls(
                name=name.strip().lower(),
                distance_constant_m=vals["distance_constant_mm"] * 1e-3,
                distance_ppm=vals["distance_ppm"],
                angle_rad=vals["angle_arcsec"] * ARCSEC,
                tilt_rad=vals["tilt_arcsec"] * ARCSEC,
                confidence_sigma=vals["confidence_sigma"],
                wavelength_um=vals["wavelength_um"],
                reference_temperature_c=vals["reference_temperature_c"],
                reference_pressure_hpa=vals["reference_pressure_hpa"],
                reference_humidity_pct=vals["reference_humidity_pct"],
                description=str(description),
            )
        except ConfigError:
            raise
        except InputError as exc:
            raise ConfigError(exc.bare_message) from None

    def to_dict(self) -> dict[str, Any]:
        """The inverse of :meth:`from_dict` (datasheet units: mm, arc seconds)."""
        return {
            "name": self.name,
            "distance_constant_mm": self.distance_constant_m * 1e3,
            "distance_ppm": self.distance_ppm,
            "angle_arcsec": self.angle_rad / ARCSEC,
            "tilt_arcsec": self.tilt_rad / ARCSEC,
            "confidence_sigma": self.confidence_sigma,
            "wavelength_um": self.wavelength_um,
            "reference_temperature_c": self.reference_temperature_c,
            "reference_pressure_hpa": self.reference_pressure_hpa,
            "reference_humidity_pct": self.reference_humidity_pct,
            "description": self.description,
        }

    def sigma_distance(self, d: ArrayLike) -> np.ndarray:
        """One-sigma distance noise (m) at slope distance ``d`` (m): ``(a + b 1e-6 d) / k``."""
        d = np.asarray(d, dtype=float)
        return (self.distance_constant_m + self.distance_ppm * 1e-6 * d) / self.confidence_sigma

    @property
    def sigma_angle(self) -> float:
        """One-sigma noise of each angle (Hz and V), rad."""
        return self.angle_rad / self.confidence_sigma

    @property
    def sigma_tilt(self) -> float:
        """One-sigma noise of the tilt compensator, rad."""
        return self.tilt_rad / self.confidence_sigma


TRIMBLE_S7 = InstrumentProfile(
    name="trimble-s7",
    distance_constant_m=0.004,
    distance_ppm=2.0,
    angle_rad=2.0 * ARCSEC,
    tilt_rad=0.5 * ARCSEC,
    confidence_sigma=2.0,
    wavelength_um=0.905,
    reference_temperature_c=20.0,
    reference_pressure_hpa=1013.25,
    reference_humidity_pct=60.0,
    description=(
        "Trimble S7 2\", prism tracking mode 4 mm + 2 ppm, angles 2\", compensator 0.5\", "
        "as used by Vaidis et al. 2023, stated at 2 sigma (ISO 17123-3); EDM pulsed laser "
        "diode 0.905 um (the authors' value)"
    ),
)

TRIMBLE_S9 = InstrumentProfile(
    name="trimble-s9",
    distance_constant_m=0.004,
    distance_ppm=2.0,
    angle_rad=1.0 * ARCSEC,
    tilt_rad=0.5 * ARCSEC,
    confidence_sigma=1.0,
    wavelength_um=0.905,
    reference_temperature_c=20.0,
    reference_pressure_hpa=1013.25,
    reference_humidity_pct=60.0,
    description=(
        "Trimble S9 1\" datasheet: prism tracking mode 4 mm + 2 ppm, angles 1\", "
        "centred dual-axis compensator 0.5\", quoted as standard deviation (1 sigma, "
        "ISO 17123-3); pulsed laser diode 0.905 um"
    ),
)

LEICA_MS60 = InstrumentProfile(
    name="leica-ms60",
    distance_constant_m=0.003,
    distance_ppm=1.5,
    angle_rad=1.0 * ARCSEC,
    tilt_rad=0.5 * ARCSEC,
    confidence_sigma=1.0,
    wavelength_um=0.658,
    reference_temperature_c=12.0,
    reference_pressure_hpa=1013.25,
    reference_humidity_pct=60.0,
    description=(
        "Leica Nova MS60 datasheet: prism continuous (tracking) mode 3 mm + 1.5 ppm, "
        "angles 1\" (0.3 mgon), compensator setting accuracy 0.5\", standard deviation "
        "ISO 17123-3 / 17123-4 (1 sigma); EDM 658 nm; zero ppm at 12 degC, 1013.25 hPa, 60 %"
    ),
)

LEICA_TS16 = InstrumentProfile(
    name="leica-ts16",
    distance_constant_m=0.003,
    distance_ppm=1.5,
    angle_rad=1.0 * ARCSEC,
    tilt_rad=0.5 * ARCSEC,
    confidence_sigma=1.0,
    wavelength_um=0.658,
    reference_temperature_c=12.0,
    reference_pressure_hpa=1013.25,
    reference_humidity_pct=60.0,
    description=(
        "Leica Viva TS16 1\" datasheet: prism tracking mode 3 mm + 1.5 ppm, angles 1\" "
        "(0.3 mgon), compensator setting accuracy 0.5\", standard deviation ISO 17123-3 / "
        "17123-4 (1 sigma); EDM 658 nm; zero ppm at 12 degC, 1013.25 hPa, 60 %"
    ),
)

#: Built-in profiles by name.
INSTRUMENTS: dict[str, InstrumentProfile] = {
    p.name: p for p in (TRIMBLE_S7, TRIMBLE_S9, LEICA_MS60, LEICA_TS16)
}


def get_instrument(name: str) -> InstrumentProfile:
    """Look up a built-in profile by name (case-insensitive)."""
    key = str(name).strip().lower()
    if key not in INSTRUMENTS:
        raise InputError(f"Unknown instrument {name!r}; known: {', '.join(sorted(INSTRUMENTS))}")
    return INSTRUMENTS[key]


def instrument_from_config(table: Mapping[str, Any]) -> InstrumentProfile:
    """The profile an ``[instrument]`` table describes: ``profile`` alone, a built-in one; with
    keys of :meth:`InstrumentProfile.from_dict`, it with those overridden (named
    ``"<profile>-custom"`` unless ``name`` is given); without ``profile``, a user-defined one
    (docs/file-formats.md#deployment-toml). Raises :class:`ConfigError` for an unknown
    profile or key."""
    if not isinstance(table, Mapping):
        raise ConfigError(f"Expected an [instrument] table, got {type(table).__name__}")
    table = dict(table)
    base_name = table.pop("profile", None)
    if base_name is None:
        return InstrumentProfile.from_dict(table)
    try:
        base = get_instrument(base_name)
    except InputError as exc:
        raise ConfigError(exc.bare_message) from None
    if not table:
        return base
    merged = base.to_dict()
    merged["name"] = f"{base.name}-custom"
    merged["description"] = f"{base.description}; overridden: {', '.join(sorted(table))}"
    unknown = sorted(set(table) - set(_DICT_REQUIRED) - set(_DICT_OPTIONAL))
    if unknown:
        raise ConfigError(
            f"[instrument] has unknown key(s) {', '.join(unknown)}; "
            f"known: profile, {', '.join(_DICT_REQUIRED + _DICT_OPTIONAL)}"
        )
    merged.update(table)
    return InstrumentProfile.from_dict(merged)
