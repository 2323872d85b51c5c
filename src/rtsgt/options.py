"""Processing options of a run: one set of typed, nested records, each default written once.

Layout (each record is what one stage takes, and one table of the deployment's TOML)::

    RunOptions
        seed                              the run's random streams (:func:`stage_rng`)
        filter         FilterParams       [filter]         filtering modules 1 and 2
        noise          NoiseModel | None  [noise]          None: the default model of the
                                                           deployment's instrument
        calibration    CalibrationOptions [calibration]    the model of the stations' transforms
        interpolation  InterpolationOptions [interpolation] query grid, Qc, gaps, GP noise
        pose           PoseOptions        [pose]           engine, registration, Monte Carlo
                                                           samples, gates

The command line and the TOML both map onto these records (:meth:`RunOptions.updated` takes
the flat names the command line uses); the ``__post_init__`` of each is the one check every
value meets, wherever it came from.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Literal, get_args

import numpy as np

from rtsgt.choices import (
    CALIBRATION_METHODS,
    CALIBRATION_MODELS,
    CALIBRATION_WEIGHTINGS,
    DEFAULT_PRIOR,
    DEFAULT_QC,
    DEFAULT_WEIGHTING,
)
from rtsgt.errors import InputError
from rtsgt.filtering import FilterParams
from rtsgt.filtering.gates import DEFAULT_DISTANCE_GATE_M, DEFAULT_UNCERTAINTY_GATE_M
from rtsgt.interpolation.gp import DEFAULT_MAX_GAP_S
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
RANDOM_STAGES = ("calibration", "noise", "pose", "analysis")

#: How Qc is chosen when not given as a number (see :func:`rtsgt.interpolation.prisms.fit_gps`).
QcMethod = Literal["loo", "likelihood"]
QC_METHODS: tuple[str, ...] = get_args(QcMethod)
#: What the GP is given: the white noise sources only (rtsgt), or every source (the paper).
GpNoise = Literal["white", "all"]
GP_NOISE: tuple[str, ...] = get_args(GpNoise)
MotionPrior = Literal["classes", "constant"]
MOTION_PRIORS: tuple[str, ...] = get_args(MotionPrior)
#: What the GPs do with the measurements inside the windows of distance rejections: leave them
#: out and fit again (rtsgt), or keep them (the paper).
OutlierWindows = Literal["remove", "keep"]
OUTLIER_WINDOWS: tuple[str, ...] = get_args(OutlierWindows)
#: The GP's motion prior: white noise on the acceleration (the paper's), on the jerk, or the
#: one of the two whose held-out windows each track predicts better.
MotionModel = Literal["select", "wnoa", "wnoj"]
PRIOR_CHOICES: tuple[str, ...] = get_args(MotionModel)

#: What the GPs do with the time-correlated noise the static-stretch check finds: inflate the
#: white covariance by the loss of independent samples (rtsgt), or take the measurements as
#: independent (the paper).
CorrelatedNoise = Literal["inflate", "ignore"]
CORRELATED_NOISE: tuple[str, ...] = get_args(CorrelatedNoise)

__all__ = ["CORRELATED_NOISE", "GP_NOISE", "MOTION_PRIORS", "OUTLIER_WINDOWS", "PRIOR_CHOICES",
           "QC_METHODS", "RANDOM_STAGES",
           "InterpolationOptions", "PoseOptions", "RunOptions", "stage_rng"]


def stage_rng(seed: int, stage: str) -> np.random.Generator:
    """The random generator of one stage of a run with ``seed``.

    Stream ``i`` of :data:`RANDOM_STAGES` is the ``i``-th child of
    ``numpy.random.SeedSequence(seed)`` (what ``SeedSequence(seed).spawn(...)[i]`` gives):
    independent streams, the same on every machine, one per stage.
    """
    return np.random.default_rng(
        np.random.SeedSequence(int(seed), spawn_key=(RANDOM_STAGES.index(stage),)))


def _one_of(name: str, value, choices: tuple[str, ...]) -> None:
    """Refuse ``value`` unless it is one of ``choices``, naming them."""
    if value not in choices:
        raise InputError(f"Expected {name} {' or '.join(map(repr, choices))}, got {value!r}")


@dataclass(frozen=True)
class InterpolationOptions:
    """Query times and the GP of each prism (TOML ``[interpolation]``).

    Attributes
    ----------
    rate_hz : float
        Rate of the query grid over the common intervals, Hz (used when the deployment gives
        no query times).
    qc : float or {"loo", "likelihood"}
        The GP's power spectral density, m^2/s^3, or how to choose it per prism
        (:func:`rtsgt.interpolation.prisms.fit_prism_gp`): by leave-one-out, the default of every
        command, or by the marginal likelihood.
    max_gap_s : float
        No pose across a gap between measurements longer than this, s (``inf``: no limit).
    gp_noise : {"white", "all"}
        What the GP is given: the white sources (rtsgt; the systematic ones are added after the
        GP) or every source (the paper).
    motion_prior : {"classes", "constant"}
        With ``qc = "loo"``: scale ``Qc`` per class of the robot's motion (standing, then by
        acceleration) where that predicts held-out measurements better
        (:mod:`rtsgt.interpolation.motion`), or one ``Qc`` per track (the paper).
    outlier_windows : {"remove", "keep"}
        The measurements inside the windows of poses the distance gate rejects (a station
        tracking another prism): left out of the GP fits, which are fitted again
        (:mod:`rtsgt.filtering.gates`), or kept in them (the paper).
    prior : {"wnoa", "select", "wnoj"}
        The GP's motion prior: white noise on the acceleration (``"wnoa"``, the paper's and
        the default), on the jerk (``"wnoj"``), or per track the one of the two whose held-out
        windows of 1-2 s it predicts better (``"select"``;
        :func:`rtsgt.interpolation.prisms.fit_gps`; with a ``qc`` given as a number,
        ``"select"`` is WNOA: the number is a WNOA PSD). docs/interpolation.md says why
        ``"select"`` is not the default.
    correlated_noise : {"inflate", "ignore"}
        Where the static-stretch check finds time-correlated measurement noise (a prism's
        component whose lag-one correlation is ``optimistic``), its white covariance inflated
        by the loss of independent samples and the GPs fitted again
        (:mod:`rtsgt.noise.correlated`), or the measurements taken as independent (the
        paper). Elsewhere nothing changes.
    """

    rate_hz: float = 5.0
    qc: float | QcMethod = DEFAULT_QC
    max_gap_s: float = DEFAULT_MAX_GAP_S
    gp_noise: GpNoise = "white"
    motion_prior: MotionPrior = "classes"
    outlier_windows: OutlierWindows = "remove"
    prior: MotionModel = DEFAULT_PRIOR
    correlated_noise: CorrelatedNoise = "ignore"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise InputError(f"Expected a finite rate_hz > 0 Hz, got {self.rate_hz!r}")
        if not self.max_gap_s > 0:  # infinity switches the limit off; nan is refused
            raise InputError(f"Expected max_gap_s > 0, got {self.max_gap_s!r}")
        if isinstance(self.qc, str) and self.qc not in QC_METHODS:
            raise InputError(
                f"Expected qc {', '.join(QC_METHODS)} or a number (m^2/s^3), got {self.qc!r}")
        if not isinstance(self.qc, str) and not (np.isfinite(self.qc) and self.qc > 0):
            raise InputError(f"Expected qc > 0 m^2/s^3, got {self.qc!r}")
        _one_of("gp_noise", self.gp_noise, GP_NOISE)
        _one_of("motion_prior", self.motion_prior, MOTION_PRIORS)
        _one_of("outlier_windows", self.outlier_windows, OUTLIER_WINDOWS)
        _one_of("prior", self.prior, PRIOR_CHOICES)
        _one_of("correlated_noise", self.correlated_noise, CORRELATED_NOISE)


@dataclass(frozen=True)
class CalibrationOptions:
    """The extrinsic calibration of the stations (TOML ``[calibration]``).

    Attributes
    ----------
    model : {"6dof", "4dof"}
        Each station's transform: a free rotation (the paper), or levelled stations (yaw only,
        the tilt that of the Earth's curvature and the compensators' errors;
        :mod:`rtsgt.calibration.gcp`, section Models).
    weighting : {"gls", "trace", "none"}
        The markers' weights in each station's fit: the inverse of the full covariance of its
        residuals (generalised least squares), the inverse of its trace, or none (the paper)
        (:mod:`rtsgt.calibration.gcp`, section Weights).
    method : {"gcp", "dynamic", "joint"}
        What the transforms are fitted to: the ground control points
        (:mod:`rtsgt.calibration.gcp`), the robot's motion through the surveyed inter-prism
        distances, or both (:mod:`rtsgt.calibration.dynamic`).
    """

    model: str = "6dof"
    weighting: str = DEFAULT_WEIGHTING
    method: str = "gcp"

    def __post_init__(self) -> None:
        _one_of("a calibration model", self.model, CALIBRATION_MODELS)
        _one_of("a calibration weighting", self.weighting, CALIBRATION_WEIGHTINGS)
        _one_of("a calibration method", self.method, CALIBRATION_METHODS)


@dataclass(frozen=True)
class PoseOptions:
    """Pose engine, Monte Carlo samples and the quality gates of module 4 (TOML ``[pose]``).

    Attributes
    ----------
    engine : {"mc", "ut", "linear"}
        Pose engine (:func:`rtsgt.pose.estimate_poses`); it also picks the per-measurement
        engine (:attr:`RunOptions.noise_engine`).
    samples : int
        Monte Carlo samples of every sampling stage (calibration, noise, pose), at least 10.
    distance_gate_m, uncertainty_gate_m : float
        Module 4's gates, m (``inf``: off).
    registration : {"weighted", "unweighted"}
        The fit of the prisms onto the reference: weighted by the inverse covariance of the
        residual (generalised least squares, :mod:`rtsgt.pose.weighted`), or the paper's
        unweighted point-to-point fit.
    """

    engine: PoseEngine = "mc"
    samples: int = 1000
    distance_gate_m: float = DEFAULT_DISTANCE_GATE_M
    uncertainty_gate_m: float = DEFAULT_UNCERTAINTY_GATE_M
    registration: Registration = DEFAULT_REGISTRATION

    def __post_init__(self) -> None:
        if self.engine not in POSE_ENGINES:
            raise InputError(f"Expected engine {', '.join(POSE_ENGINES)}, got {self.engine!r}")
        _one_of("registration", self.registration, REGISTRATIONS)
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

    def updated(self, **changes) -> RunOptions:
        """A copy with ``changes``, keyed by the flat names of the command line: ``seed``,
        ``filter``, ``noise``, or a field of a nested record (``model``, ``method``, ``engine``,
        ``registration``, ``samples``, ``rate_hz``, ``qc``, ``max_gap_s``, ``gp_noise``,
        ``motion_prior``, ``outlier_windows``, ``prior``, ``correlated_noise``, the gates); each
        value meets its record's rule (:class:`~rtsgt.errors.InputError` otherwise)."""
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


_FIELDS = {record: {f.name for f in fields(record)} for record in _NESTED.values()}
_TOP_FIELDS = {f.name for f in fields(RunOptions)} - set(_NESTED)
