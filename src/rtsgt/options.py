"""Processing options of a run: typed, nested records, each default written once.

:class:`RunOptions` holds ``seed`` (the stages' streams, :func:`stage_rng`), ``filter``
(:class:`~rtsgt.filtering.FilterParams`), ``noise`` (None: the instrument's default model),
``calibration``, ``interpolation`` and ``pose``: one record per table of the deployment's TOML
(docs/file-formats.md#deployment-toml). The TOML and the command line (the flat names of
:meth:`RunOptions.updated`) map onto them; each record's ``__post_init__`` is the one check.
:data:`PROFILES` names presets of the switches (``"paper"``: the published method).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import numpy as np

from rtsgt.choices import (
    CALIBRATION_METHODS,
    CALIBRATION_MODELS,
    CALIBRATION_WEIGHTINGS,
    DEFAULT_WEIGHTING,
    JOINT_ENGINE,
)
from rtsgt.errors import InputError
from rtsgt.filtering import FilterParams
from rtsgt.filtering.gates import DEFAULT_DISTANCE_GATE_M, DEFAULT_UNCERTAINTY_GATE_M
from rtsgt.interpolation.options import (
    CORRELATED_NOISE,
    GP_NOISE,
    MOTION_PRIORS,
    OUTLIER_WINDOWS,
    PRIOR_CHOICES,
    QC_METHODS,
    InterpolationOptions,
    one_of,
)
from rtsgt.noise import NoiseModel
from rtsgt.pose.estimate import (
    DEFAULT_REGISTRATION,
    POSE_ENGINES,
    REGISTRATIONS,
    PoseEngine,
    Registration,
)

#: The stages that draw random numbers. Each draws from its own stream of the run's seed
#: (:func:`stage_rng`), so that a stage's draws do not depend on how many the stages before it
#: made, and a later reader of the run (the continuous ground truth of
#: :mod:`rtsgt.evaluation.groundtruth`) can reproduce one stage's draws alone.
RANDOM_STAGES = ("calibration", "noise", "pose", "analysis", "joint")

__all__ = ["CORRELATED_NOISE", "GP_NOISE", "JOINT_START_ENGINE", "MOTION_PRIORS",
           "OUTLIER_WINDOWS", "PRIOR_CHOICES", "PROFILES", "QC_METHODS", "RANDOM_STAGES",
           "RUN_ENGINES",
           "InterpolationOptions", "PoseOptions", "RunOptions", "stage_rng"]

#: Presets of the switches, by name (:meth:`RunOptions.updated`): ``"paper"`` is the method of
#: Vaidis et al. (2023) (docs/paper-figures.md); the defaults are rtsgt's.
PROFILES: dict[str, dict[str, str]] = {
    "paper": {"model": "6dof", "weighting": "none", "method": "gcp", "gp_noise": "all",
              "motion_prior": "constant", "outlier_windows": "keep", "prior": "wnoa",
              "correlated_noise": "ignore", "registration": "unweighted"},
}


#: The engines of a run's ``[pose] engine``: the per-prism ones and the joint engine.
RUN_ENGINES: tuple[str, ...] = (*POSE_ENGINES, JOINT_ENGINE)
#: The per-prism engine whose poses the joint engine starts from (and whose poses the
#: continuous ground truth of a joint run recomputes): docs/pipeline.md#the-joint-engine.
JOINT_START_ENGINE = "linear"


def stage_rng(seed: int, stage: str) -> np.random.Generator:
    """The random generator of one stage of a run with ``seed``.

    Stream ``i`` of :data:`RANDOM_STAGES` is the ``i``-th child of
    ``numpy.random.SeedSequence(seed)`` (what ``SeedSequence(seed).spawn(...)[i]`` gives):
    independent streams, the same on every machine, one per stage.
    """
    return np.random.default_rng(
        np.random.SeedSequence(int(seed), spawn_key=(RANDOM_STAGES.index(stage),)))


@dataclass(frozen=True)
class CalibrationOptions:
    """The stations' calibration (TOML ``[calibration]``; docs/noise-model.md): ``model``
    ``"6dof"`` (the paper) or ``"4dof"`` (levelled stations); ``weighting`` of the markers
    ``"gls"``, ``"trace"`` or ``"none"`` (the paper); ``method``: fitted to the GCPs (``"gcp"``),
    the robot's motion (``"dynamic"``) or both (``"joint"``)."""

    model: str = "6dof"
    weighting: str = DEFAULT_WEIGHTING
    method: str = "gcp"

    def __post_init__(self) -> None:
        one_of("a calibration model", self.model, CALIBRATION_MODELS)
        one_of("a calibration weighting", self.weighting, CALIBRATION_WEIGHTINGS)
        one_of("a calibration method", self.method, CALIBRATION_METHODS)


@dataclass(frozen=True)
class PoseOptions:
    """Pose engine, samples and module 4's gates (TOML ``[pose]``; docs/pose.md): ``engine`` of
    :data:`RUN_ENGINES` (a per-prism one of :data:`~rtsgt.pose.POSE_ENGINES`, also the
    per-measurement engine, :attr:`RunOptions.noise_engine`; or ``"joint"``,
    docs/pipeline.md#the-joint-engine); ``samples`` of every Monte Carlo stage, at least 10;
    ``distance_gate_m``, ``uncertainty_gate_m``, m (``inf``: off); ``registration``
    ``"weighted"`` or ``"unweighted"`` (the paper's); ``clocks``: whether the joint engine
    estimates the stations' clock offsets (docs/joint.md#clock-offsets)."""

    engine: PoseEngine = "mc"
    samples: int = 1000
    distance_gate_m: float = DEFAULT_DISTANCE_GATE_M
    uncertainty_gate_m: float = DEFAULT_UNCERTAINTY_GATE_M
    registration: Registration = DEFAULT_REGISTRATION
    clocks: bool = True

    def __post_init__(self) -> None:
        if self.engine not in RUN_ENGINES:
            raise InputError(f"Expected engine {', '.join(RUN_ENGINES)}, got {self.engine!r}")
        if not isinstance(self.clocks, (bool, np.bool_)):
            raise InputError(f"Expected clocks true or false, got {self.clocks!r}")
        one_of("registration", self.registration, REGISTRATIONS)
        if isinstance(self.samples, bool) or not isinstance(self.samples, (int, np.integer)) \
                or self.samples < 10:
            raise InputError(f"Expected an integer of at least 10 samples, got {self.samples!r}")
        for name in ("distance_gate_m", "uncertainty_gate_m"):
            value = getattr(self, name)
            if not value > 0:  # infinity switches the gate off; nan is refused
                raise InputError(f"Expected {name} > 0, got {value!r}")


#: The nested records of :class:`RunOptions`, by field name.
_NESTED = {"calibration": CalibrationOptions, "interpolation": InterpolationOptions,
           "pose": PoseOptions}


@dataclass(frozen=True)
class RunOptions:
    """Processing parameters of one run (defaults: the paper's where it has one)."""

    seed: int = 0
    filter: FilterParams = field(default_factory=FilterParams)
    noise: NoiseModel | None = None
    calibration: CalibrationOptions = field(default_factory=CalibrationOptions)
    interpolation: InterpolationOptions = field(default_factory=InterpolationOptions)
    pose: PoseOptions = field(default_factory=PoseOptions)

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) \
                or self.seed < 0:
            raise InputError(f"Expected a seed that is an integer >= 0, got {self.seed!r}")

    def updated(self, profile: str | None = None, **changes) -> RunOptions:
        """A copy with ``changes`` keyed by the command line's flat names (``seed``, ``filter``,
        ``noise`` or a field of a nested record), after the switches of ``profile`` (a name of
        :data:`PROFILES`; ``changes`` win over it); each value meets its record's rule
        (:class:`~rtsgt.errors.InputError` otherwise)."""
        if profile is not None:
            one_of("profile", profile, tuple(PROFILES))
            changes = {**PROFILES[profile], **changes}
        top = {k: v for k, v in changes.items() if k in _TOP_FIELDS}
        for part, record in _NESTED.items():
            mine = {k: v for k, v in changes.items() if k in _FIELDS[record]}
            if mine:
                top[part] = replace(getattr(self, part), **mine)
        unknown = set(changes) - _TOP_FIELDS - set().union(*_FIELDS.values())
        if unknown:
            raise TypeError(f"unknown option(s): {', '.join(sorted(unknown))}")
        return replace(self, **top)

    @property
    def noise_engine(self) -> str:
        """The per-measurement engine: Monte Carlo for the MC pose engine, else first order."""
        return "mc" if self.pose.engine == "mc" else "linear"

    @property
    def joint(self) -> bool:
        """Whether the run's poses are the joint engine's."""
        return self.pose.engine == JOINT_ENGINE

    @property
    def prism_engine(self) -> str:
        """The per-prism pose engine: the run's, or for the joint engine the one it starts
        from (:data:`JOINT_START_ENGINE`)."""
        return JOINT_START_ENGINE if self.joint else self.pose.engine


_FIELDS = {record: {f.name for f in fields(record)} for record in _NESTED.values()}
_TOP_FIELDS = {f.name for f in fields(RunOptions)} - set(_NESTED)
