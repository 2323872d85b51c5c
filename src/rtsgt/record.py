"""The run record: what one run of the pipeline produced, as one typed record.

:func:`rtsgt.pipeline.run_pipeline` returns a :class:`RunRecord`;
:func:`rtsgt.io.run_dir.write_run` writes it as a run directory and
:func:`rtsgt.io.run_dir.read_run` reads one back into the same record (the only reader and
writer of those files). The analysis (:mod:`rtsgt.report.analysis`), the figures, the report
and the continuous ground truth (:meth:`rtsgt.evaluation.ContinuousGroundTruth.from_record`)
take a record, whether it was just computed or read from files.

A record read back has every field a run writes; what only exists in memory (the deployment's
inputs, the calibration's Monte Carlo samples, the fitted GPs, the filter and gate reports) is
in :attr:`RunRecord.computation`, None for a record read from files.

Conventions: positions and covariances in the world frame (the reference station's), m and
m^2; times in s; pose covariances 6x6 in the order (x, y, z, rx, ry, rz), left perturbation in
the world frame (:mod:`rtsgt.types`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from rtsgt.calibration import CalibrationResult
from rtsgt.calibration.coupling import StationCoupling
from rtsgt.deployment import DeploymentData
from rtsgt.filtering.gates import GateReport
from rtsgt.filtering.modules import RemovedMeasurements
from rtsgt.interpolation import GPTrack
from rtsgt.interpolation.prisms import PrismsAtTimes
from rtsgt.noise import NoiseModel
from rtsgt.options import RunOptions
from rtsgt.pose import PoseEstimate
from rtsgt.pose.reference import ReferencePoints
from rtsgt.shared import SharedFactor
from rtsgt.types import NOISE_SOURCES, PoseTrajectory, PrismTrack

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


@dataclass(frozen=True)
class RunRecord:
    """One run: its options, measured tracks, prisms at the query times, poses and checks.

    Attributes
    ----------
    name : str
        Deployment name (or the run directory's name).
    prism_ids : tuple of str, length n
        Prisms in the order of the ``n`` axis of the ``prisms_*`` arrays.
    measurements : dict str -> PrismTrack
        The filtered measured track of each prism, with its station, ``range_m`` and
        ``cov_by_source``; ``cov`` is the sum of the per-source covariances (the total of
        independent sources).
    prisms_t : ndarray, shape (T,)
        Query times (every pose time, kept or rejected).
    prisms_xyz : ndarray, shape (T, n, 3)
        Interpolated prism positions.
    prisms_cov : ndarray, shape (T, n, 3, 3)
        Their total covariance (the blocks the pose engine used).
    prisms_cov_by_source : dict str -> ndarray (T, n, 3, 3)
        Each source's covariance at the query times.
    groundtruth : PoseTrajectory
        The kept poses with their 6x6 covariance.
    rejected_t : ndarray, shape (R,)
    rejected_reason : ndarray of str, shape (R,)
        The query times whose pose a gate rejected, and the gate.
    reference : ReferencePoints
        Every reference prism of the deployment in the body frame, with the joint covariance.
    options : RunOptions
        The run's options (``noise`` is None in a record read from files: ``summary.json``
        keeps the sources, not the model).
    schema_version : int
        :data:`RUN_SCHEMA_VERSION` for a new run; that of the files for a record read back.
    stations : dict str -> ndarray (3,)
        Station positions (translations of ``T_world_station``), m.
    prisms_cov_gp : ndarray, shape (T, n, 3, 3), optional
        The GP posterior covariance alone.
    gcp_xyz : ndarray, shape (G, 3), optional
        Ground control points in the world frame, m, named by ``gcp_names``.
    gcp_names : tuple of str
    qc : dict str -> ndarray
        Each prism's GP power spectral density Qc, m^2/s^3.
    qc_scale : dict str -> ndarray (N-1,)
        Per prism whose ``Qc`` follows the motion, the scale of each interval between its
        measurements (:mod:`rtsgt.interpolation.motion`); absent: one ``Qc``.
    prior : dict str -> str
        Each prism's GP motion prior, ``"wnoa"`` or ``"wnoj"`` (:mod:`rtsgt.interpolation.gp`;
        its ``qc`` is then m^2/s^5); absent: ``"wnoa"`` (a run written before the choice).
    intervals : ndarray, shape (K, 2), optional
        The intervals every prism is tracked in (module 2), s; None for an older run.
    uncertainty_measure : str
        The measure module 4's uncertainty gate used.
    coupling : StationCoupling, optional
        The correlation of the station calibrations (None for an older run).
    removed : RemovedMeasurements
        What the filters removed, with the module and the reason.
    measurements_gp_cov : dict str -> ndarray (N, 3, 3)
        Per prism, the covariance the GP was given (white sources, or the total with
        ``gp_noise = "all"``).
    warnings : tuple of str
        Every warning of the run, once each.
    weather_coverage : dict, optional
        How the weather record covers the measurements (None without weather).
    distance_check : dict
        Tracked inter-prism distances against the surveyed ones, per prism pair.
    self_checks : dict
        What the data say about the run's uncertainty (:mod:`rtsgt.checks`), JSON-ready:
        ``gcp_fit`` (:func:`rtsgt.checks.gcp_fit_check`), ``inter_prism_distances``
        (:func:`rtsgt.checks.inter_prism_check`), ``block_cv``
        (:func:`rtsgt.checks.block_cv_check`), ``static_noise``
        (:func:`rtsgt.checks.static_noise_check`) and ``inter_prism_structure``
        (:func:`rtsgt.checks.inter_prism_structure_check`). Empty for a run written before rtsgt made
        them.
    correlated_noise : dict
        How the run carried the time-correlated noise the static-stretch check found
        (:func:`rtsgt.noise.correlated.correlated_noise_plan`, JSON-ready: per prism and
        component the correlated share, the correlation time, ``rho``, the factor and whether
        it was applied). Empty for a run written before rtsgt carried it.
    groundtruth_split : SharedFactor, optional
        The kept poses' error split into the part that varies from pose to pose and the part
        the whole deployment shares (:mod:`rtsgt.shared`): the varying covariance and the
        low-rank factor of the shared one, with the names of its parameters. None for a run
        written before rtsgt made it, or with ``gp_noise = "all"``.
    summary : dict
        The run's ``summary.json`` as read (empty for a record not read from files).
    path : Path, optional
        The run directory it was read from.
    computation : RunComputation, optional
        What only exists in memory (None for a record read from files).
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

    The fields are those of :class:`RunRecord` that a run without poses has, with the same
    meaning: no ``groundtruth``, no gates (``rejected_*``), no reference survey (a pose's), no
    inter-prism checks. ``prisms_*`` hold every query time (none is rejected).

    Attributes
    ----------
    name : str
    prism_ids : tuple of str, length n (1 or 2)
    measurements : dict str -> PrismTrack
    prisms_t : ndarray, shape (T,)
    prisms_xyz : ndarray, shape (T, n, 3)
    prisms_cov : ndarray, shape (T, n, 3, 3)
        Total covariance (GP posterior plus the systematic sources), m^2.
    prisms_cov_by_source : dict str -> ndarray (T, n, 3, 3)
    prisms_cov_gp : ndarray, shape (T, n, 3, 3), optional
    options, schema_version, stations, gcp_xyz, gcp_names, qc, qc_scale, prior, intervals,
    coupling, removed, measurements_gp_cov, warnings, weather_coverage, self_checks,
    correlated_noise, summary, path :
        As :class:`RunRecord`.
    computation : RunComputation, optional
        What only exists in memory (``estimate`` and ``gate_report`` None); None for a record
        read from files.
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
