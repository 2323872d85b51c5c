"""Simulation presets: named deployments, ``rtsgt simulate --preset NAME``.

``field-hour``: an hour with one far station, the field noise, clocks and moved prism of
:mod:`rtsgt.simulation.field`, the 360-degree prisms' deviation and the tripods settling
(docs/simulation.md#the-field-hour-preset).
"""

from __future__ import annotations

from rtsgt.choices import SIMULATION_PRESETS
from rtsgt.errors import InputError
from rtsgt.measurement.instruments import ARCSEC
from rtsgt.simulation.deployment import SimulationConfig
from rtsgt.simulation.field import FieldEffects
from rtsgt.simulation.reality import RealityEffects

__all__ = ["SIMULATION_PRESETS", "FIELD_SETTLING_TWIST_RAD", "preset_config"]

#: Final twist of a settling tripod under the field-hour preset, rad (5").
FIELD_SETTLING_TWIST_RAD = 5.0 * ARCSEC


def preset_config(name: str, *, duration_s: float | None = None, n_stations: int = 3,
                  reality: tuple[str, ...] = ()) -> SimulationConfig:
    """The :class:`SimulationConfig` of preset ``name`` (:data:`SIMULATION_PRESETS`).

    ``duration_s``: None for the preset's own; ``reality``: further reality effects on at
    their default sizes (:data:`rtsgt.simulation.reality.REALITY_EFFECTS`).
    """
    if name not in SIMULATION_PRESETS:
        raise InputError(f"Expected a preset among {', '.join(SIMULATION_PRESETS)}, got {name!r}")
    duration = SIMULATION_PRESETS[name] if duration_s is None else duration_s
    switches = dict.fromkeys(("prism_cyclic", "tripod_settling", *reality), True)
    return SimulationConfig(
        duration_s=duration, n_stations=n_stations, far_stations=1, field=FieldEffects(),
        reality=RealityEffects(**switches, settling_twist_rad=FIELD_SETTLING_TWIST_RAD))
