"""Processing options of a run (one owner of their defaults and of the rule they meet).

The command line and the deployment's TOML both map onto :class:`RunOptions`; its
``__post_init__`` is the one check every value meets, wherever it came from.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np

from rtsgt.errors import InputError
from rtsgt.filtering import FilterParams
from rtsgt.filtering.gates import DEFAULT_DISTANCE_GATE_M, DEFAULT_UNCERTAINTY_GATE_M
from rtsgt.interpolation.gp import DEFAULT_MAX_GAP_S
from rtsgt.noise import NoiseModel
from rtsgt.pose.estimate import POSE_ENGINES, PoseEngine

#: The stages that draw random numbers. Each draws from its own stream of the run's seed
#: (:func:`stage_rng`), so that a stage's draws do not depend on how many the stages before it
#: made, and a later reader of the run (the continuous ground truth of
#: :mod:`rtsgt.evaluation.groundtruth`) can reproduce one stage's draws alone.
RANDOM_STAGES = ("calibration", "noise", "pose", "analysis")

#: How Qc is chosen when not given as a number (see :func:`rtsgt.interpolation.prisms.fit_gps`).
QcMethod = Literal["loo", "likelihood"]
QC_METHODS: tuple[str, ...] = get_args(QcMethod)
#: What the GP is given: the white noise sources only (rtsgt), or every source (the paper).
GpNoise = Literal["white", "all"]
GP_NOISE: tuple[str, ...] = get_args(GpNoise)

__all__ = ["RunOptions", "QC_METHODS", "GP_NOISE", "RANDOM_STAGES", "stage_rng"]


def stage_rng(seed: int, stage: str) -> np.random.Generator:
    """The random generator of one stage of a run with ``seed``.

    Stream ``i`` of :data:`RANDOM_STAGES` is the ``i``-th child of
    ``numpy.random.SeedSequence(seed)`` (what ``SeedSequence(seed).spawn(...)[i]`` gives):
    independent streams, the same on every machine, one per stage.
    """
    return np.random.default_rng(
        np.random.SeedSequence(int(seed), spawn_key=(RANDOM_STAGES.index(stage),)))


@dataclass(frozen=True)
class RunOptions:
    """Processing parameters of one run (defaults: the paper's where it has one)."""

    engine: PoseEngine = "mc"
    samples: int = 1000
    seed: int = 0
    rate_hz: float = 5.0
    qc: float | QcMethod = "loo"
    max_gap_s: float = DEFAULT_MAX_GAP_S
    noise: NoiseModel | None = None
    filter: FilterParams = field(default_factory=FilterParams)
    distance_gate_m: float = DEFAULT_DISTANCE_GATE_M
    uncertainty_gate_m: float = DEFAULT_UNCERTAINTY_GATE_M
    gp_noise: GpNoise = "white"

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) \
                or self.seed < 0:
            raise InputError(f"Expected a seed that is an integer >= 0, got {self.seed!r}")
        if self.engine not in POSE_ENGINES:
            raise InputError(f"Expected engine {', '.join(POSE_ENGINES)}, got {self.engine!r}")
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
        if self.gp_noise not in GP_NOISE:
            raise InputError(f"Expected gp_noise {' or '.join(map(repr, GP_NOISE))}, got "
                             f"{self.gp_noise!r}")

    @property
    def noise_engine(self) -> str:
        """The per-measurement engine: Monte Carlo for the MC pose engine, else first order."""
        return "mc" if self.engine == "mc" else "linear"
