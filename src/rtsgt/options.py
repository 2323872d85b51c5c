"""Processing options of a run (one owner of their defaults and of the rule they meet).

The command line and the deployment's TOML both map onto :class:`RunOptions`; its
``__post_init__`` is the one check every value meets, wherever it came from.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rtsgt.errors import InputError
from rtsgt.filtering import FilterParams
from rtsgt.noise import NoiseModel

#: How Qc is chosen when not given as a number (see :func:`rtsgt.interpolation.prisms.fit_gps`).
QC_METHODS = ("loo", "likelihood")

__all__ = ["RunOptions", "QC_METHODS"]


@dataclass(frozen=True)
class RunOptions:
    """Processing parameters of one run (defaults: the paper's where it has one)."""

    engine: str = "mc"
    samples: int = 1000
    seed: int = 0
    rate_hz: float = 5.0
    qc: float | str = "loo"
    max_gap_s: float = 3.0
    noise: NoiseModel | None = None
    filter: FilterParams = field(default_factory=FilterParams)
    distance_gate_m: float = 0.10
    uncertainty_gate_m: float = 0.20
    gp_noise: str = "white"

    def __post_init__(self) -> None:
        if self.engine not in ("mc", "ut", "linear"):
            raise InputError(f"Expected engine mc, ut or linear, got {self.engine!r}")
        if isinstance(self.samples, bool) or not isinstance(self.samples, (int, np.integer)) \
                or self.samples < 10:
            raise InputError(f"Expected an integer of at least 10 samples, got {self.samples!r}")
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise InputError(f"Expected a finite rate_hz > 0 Hz, got {self.rate_hz!r}")
        for name in ("max_gap_s", "distance_gate_m", "uncertainty_gate_m"):
            value = getattr(self, name)
            if not value > 0:  # infinity switches the limit off; nan is refused
                raise InputError(f"Expected {name} > 0, got {value!r}")
        if isinstance(self.qc, str) and self.qc not in QC_METHODS:
            raise InputError(
                f"Expected qc {', '.join(QC_METHODS)} or a number (m^2/s^3), got {self.qc!r}")
        if not isinstance(self.qc, str) and not (np.isfinite(self.qc) and self.qc > 0):
            raise InputError(f"Expected qc > 0 m^2/s^3, got {self.qc!r}")
        if self.gp_noise not in ("white", "all"):
            raise InputError(f"Expected gp_noise 'white' or 'all', got {self.gp_noise!r}")

    @property
    def noise_engine(self) -> str:
        """The per-measurement engine: Monte Carlo for the MC pose engine, else first order."""
        return "mc" if self.engine == "mc" else "linear"
