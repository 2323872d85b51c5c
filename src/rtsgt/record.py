"""The run record: what one run of the pipeline produced, as one typed record.

:func:`rtsgt.pipeline.run_pipeline` returns a :class:`RunRecord` (or a
:class:`PositionRunRecord` for one or two tracked prisms); :mod:`rtsgt.io.run_dir` writes it as a
run directory and reads it back into the same record (docs/file-formats.md#run-directory). The
analysis, the report and the continuous ground truth take a record, computed or read; what only
exists in memory is in :attr:`RunRecord.computation` (None when read from files). World frame
(the reference station's), m, m^2, s; pose covariances as :mod:`rtsgt.types`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from rtsgt.calibration import CalibrationResult
from rtsgt.deployment import DeploymentData
from rtsgt.filtering.gates import GateReport
from rtsgt.filtering.modules import RemovedMeasurements
from rtsgt.interpolation import GPTrack
from rtsgt.interpolation.prisms import PrismsAtTimes
from rtsgt.joint.estimate import JointResult
from rtsgt.noise import NoiseModel
from rtsgt.noise.coupling import StationCoupling
from rtsgt.noise.sources import NOISE_SOURCES
from rtsgt.options import RunOptions
from rtsgt.pose import PoseEstimate
from rtsgt.pose.reference import ReferencePoints
from rtsgt.shared import SharedFactor
from rtsgt.types import PoseTrajectory, PrismTrack

__all__ = ["MIN_POSE_PRISMS", "RUN_SCHEMA_NAME", "RUN_SCHEMA_VERSION", "PositionRunRecord",
           "RunComputation", "RunRecord", "no_removed_measurements", "ordered_sources"]

#: Name and version of the run record's layout on disk (``summary.json`` ``schema``). A reader
#: refuses a newer version; a summary without the key is of the layout before it (version 0).
RUN_SCHEMA_NAME = "rtsgt-run"
RUN_SCHEMA_VERSION = 1


def ordered_sources(names) -> tuple[str, ...]:
    """Noise source names in :data:`~rtsgt.types.NOISE_SOURCES` order, unknown ones after."""
    names = set(names)
    known = [s for s in NOISE_SOURCES if s in names]
    return tuple(known + sorted(names - set(known)))


def no_removed_measurements() -> RemovedMeasurements:
    """An empty :class:`~rtsgt.filtering.modules.RemovedMeasurements` (a run without the file)."""
    text = np.empty(0, dtype=str)
    return RemovedMeasurements(np.empty(0), text, text, np.empty((0, 3)), text, text)


@dataclass(frozen=True)
class RunComputation:
    """What a run computed in memory besides its record (None in a record read from files).

    ``tracks`` are the propagated tracks as the GPs were fitted to them (``cov``: the noise
    engine's total); ``prisms`` has the joint covariance the pose engine took; ``keep`` and
    ``gate_report`` are per query time.
    """

    data: DeploymentData
    calibration: CalibrationResult
    noise_model: NoiseModel
    filter_reports: dict[str, object]
    tracks: dict[str, PrismTrack]
    gps: dict[str, GPTrack]
    prisms: PrismsAtTimes
    #: The poses; None for a position-only run (:class:`PositionRunRecord`).
    estimate: PoseEstimate | None
    keep: np.ndarray
    #: Module 4's report; None for a position-only run.
    gate_report: GateReport | None
    timings_s: dict[str, float]
    qc_info: dict[str, dict] = field(default_factory=dict)
    #: The joint engine's result (:class:`rtsgt.joint.estimate.JointResult`); None for the
    #: per-prism engines.
    joint: JointResult | None = None


@dataclass(frozen=True)
class RunRecord:
    """One run: its options, measured tracks, prisms at the query times, poses and checks.

    - ``name``; ``prism_ids`` (n,), the order of the ``n`` axis of the ``prisms_*`` arrays;
      ``measurements``: each prism's filtered track (station, ``range_m``, ``cov_by_source``;
      ``cov`` their sum); ``measurements_gp_cov``: the covariance each GP was given (N, 3, 3).
    - ``prisms_t`` (T,) every query time; ``prisms_xyz`` (T, n, 3); ``prisms_cov`` (T, n, 3, 3)
      the blocks the pose engine used; ``prisms_cov_by_source``; ``prisms_cov_gp`` the GP's alone.
    - ``groundtruth``: the kept poses with their 6x6 covariance; ``groundtruth_split``: their
      error's varying and shared parts (:mod:`rtsgt.shared`; None for an older run or
      ``gp_noise = "all"``); ``rejected_t``, ``rejected_reason`` (R,): the gated times and gate;
      ``uncertainty_measure``: the uncertainty gate's.
    - ``reference``: every reference prism (body frame, joint covariance); ``stations``: each
      station's position, m; ``gcp_xyz`` (G, 3), ``gcp_names``; ``coupling``: the correlation of
      the calibrations (None for an older run).
    - ``qc``: each prism's PSD; ``qc_scale``: per prism whose Qc follows the motion, the scale of
      each interval (:mod:`rtsgt.interpolation.motion`); ``prior``: each prism's ``"wnoa"`` /
      ``"wnoj"`` (absent: wnoa); ``intervals`` (K, 2) the tracked intervals, s.
    - ``options`` (``noise`` None when read from files); ``schema_version``; ``removed``: what
      the filters removed; ``warnings``; ``weather_coverage``; ``distance_check``: tracked against
      surveyed inter-prism distances; ``self_checks``: JSON-ready results of :mod:`rtsgt.checks`
      (empty for an older run); ``correlated_noise``: how the run carried the time-correlated
      noise (:func:`rtsgt.noise.correlated.correlated_noise_plan`); ``joint``: what the joint
      engine estimated besides the poses (:func:`rtsgt.stages.joint.joint_summary`; empty for
      a per-prism engine).
    - ``summary``: ``summary.json`` as read; ``path``: the directory read; ``computation``: what
      only exists in memory.
    """

    name: str
    prism_ids: tuple[str, ...]
    measurements: dict[str, PrismTrack]
    prisms_t: np.ndarray
    prisms_xyz: np.ndarray
    prisms_cov: np.ndarray
    prisms_cov_by_source: dict[str, np.ndarray]
    groundtruth: PoseTrajectory
    rejected_t: np.ndarray
    rejected_reason: np.ndarray
    reference: ReferencePoints
    options: RunOptions = field(default_factory=RunOptions)
    schema_version: int = RUN_SCHEMA_VERSION
    stations: dict[str, np.ndarray] = field(default_factory=dict)
    prisms_cov_gp: np.ndarray | None = None
    gcp_xyz: np.ndarray | None = None
    gcp_names: tuple[str, ...] = ()
    qc: dict[str, np.ndarray] = field(default_factory=dict)
    qc_scale: dict[str, np.ndarray] = field(default_factory=dict)
    prior: dict[str, str] = field(default_factory=dict)
    intervals: np.ndarray | None = None
    uncertainty_measure: str = "max_std"
    coupling: StationCoupling | None = None
    removed: RemovedMeasurements = field(default_factory=no_removed_measurements)
    measurements_gp_cov: dict[str, np.ndarray] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    weather_coverage: dict | None = None
    distance_check: dict = field(default_factory=dict)
    self_checks: dict = field(default_factory=dict)
    correlated_noise: dict = field(default_factory=dict)
    groundtruth_split: SharedFactor | None = None
    joint: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)
    path: Path | None = None
    computation: RunComputation | None = None

    def __post_init__(self) -> None:
        _check_prism_arrays(self)
        missing = [p for p in self.prism_ids if p not in self.reference.names]
        if missing:
            raise ValueError(f"No reference point for prism(s) {', '.join(missing)}")
        split = self.groundtruth_split
        if split is not None and split.t.shape != self.groundtruth.t.shape:
            raise ValueError(f"Expected the split of the {len(self.groundtruth.t)} kept poses, "
                             f"got {split.t.shape[0]}")
        if self.rejected_t.shape != self.rejected_reason.shape:
            raise ValueError("Expected one rejection reason per rejected time")

    @cached_property
    def tracked_reference(self) -> ReferencePoints:
        """The reference points of the tracked prisms, in the order of ``prism_ids`` (selected
        once: ``reference_xyz`` and ``reference_cov`` are read many times)."""
        return self.reference.select(list(self.prism_ids))

    @property
    def reference_xyz(self) -> np.ndarray:
        """Reference prisms of ``prism_ids`` in the body frame, (n, 3) m."""
        return self.tracked_reference.xyz

    @property
    def reference_cov(self) -> np.ndarray:
        """Their joint covariance, (3n, 3n) m^2."""
        return self.tracked_reference.cov

    @property
    def sources(self) -> tuple[str, ...]:
        """Noise sources present in the measurements, in :data:`NOISE_SOURCES` order."""
        return _sources(self.measurements)


#: Why a run gives positions only: a pose needs at least this many tracked prisms.
MIN_POSE_PRISMS = 3


@dataclass(frozen=True)
class PositionRunRecord:
    """A run of a deployment with one or two tracked prisms: each prism's positions with
    covariance (a 3-DOF ground truth, :mod:`rtsgt.evaluation.positions`), no pose.

    The fields of :class:`RunRecord` a run without poses has, with the same meaning (no
    ``groundtruth``, gates, reference survey or inter-prism checks; ``prisms_*`` at every query
    time); ``computation``'s ``estimate`` and ``gate_report`` are None.
    """

    name: str
    prism_ids: tuple[str, ...]
    measurements: dict[str, PrismTrack]
    prisms_t: np.ndarray
    prisms_xyz: np.ndarray
    prisms_cov: np.ndarray
    prisms_cov_by_source: dict[str, np.ndarray]
    prisms_cov_gp: np.ndarray | None = None
    options: RunOptions = field(default_factory=RunOptions)
    schema_version: int = RUN_SCHEMA_VERSION
    stations: dict[str, np.ndarray] = field(default_factory=dict)
    gcp_xyz: np.ndarray | None = None
    gcp_names: tuple[str, ...] = ()
    qc: dict[str, np.ndarray] = field(default_factory=dict)
    qc_scale: dict[str, np.ndarray] = field(default_factory=dict)
    prior: dict[str, str] = field(default_factory=dict)
    intervals: np.ndarray | None = None
    coupling: StationCoupling | None = None
    removed: RemovedMeasurements = field(default_factory=no_removed_measurements)
    measurements_gp_cov: dict[str, np.ndarray] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    weather_coverage: dict | None = None
    self_checks: dict = field(default_factory=dict)
    correlated_noise: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)
    path: Path | None = None
    computation: RunComputation | None = None

    def __post_init__(self) -> None:
        n = len(self.prism_ids)
        if not 1 <= n < MIN_POSE_PRISMS:
            raise ValueError(f"Expected 1 or 2 prisms in a position-only run, got {n}")
        _check_prism_arrays(self)

    @property
    def sources(self) -> tuple[str, ...]:
        """Noise sources present in the measurements, in :data:`NOISE_SOURCES` order."""
        return _sources(self.measurements)



def _check_prism_arrays(record: RunRecord | PositionRunRecord) -> None:
    """The prisms' positions and covariances of a record: one row per time and prism."""
    n = len(record.prism_ids)
    T = record.prisms_t.shape[0]
    for what, arr, shape in (("prisms_xyz", record.prisms_xyz, (T, n, 3)),
                             ("prisms_cov", record.prisms_cov, (T, n, 3, 3)),
                             ("prisms_cov_gp", record.prisms_cov_gp, (T, n, 3, 3)),
                             *((f"prisms_cov_by_source[{s!r}]", c, (T, n, 3, 3))
                               for s, c in record.prisms_cov_by_source.items())):
        if arr is not None and arr.shape != shape:
            raise ValueError(f"Expected {what} of shape {shape}, got {arr.shape}")


def _sources(measurements: dict[str, PrismTrack]) -> tuple[str, ...]:
    """Noise sources present in the measurements, in :data:`NOISE_SOURCES` order."""
    present = set()
    for tr in measurements.values():
        present |= set(tr.cov_by_source)
    return ordered_sources(present)
