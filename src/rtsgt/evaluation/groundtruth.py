r"""Continuous-time ground truth: the poses of a run at any time, from its GP prism tracks.

An ``rtsgt run`` directory stores poses on a regular grid (``groundtruth_covariance.csv``), but
an estimate to evaluate has its own times. Picking the nearest stored pose is wrong by up to
half a grid period times the robot's speed (centimetres at 5 Hz), and interpolating stored
poses gives a covariance that is not the posterior between them. :class:`ContinuousGroundTruth`
instead redoes, at the requested times, what the pipeline did on its grid
(:mod:`rtsgt.pipeline`):

1. refit each prism's GP from ``measurements/prism<i>.csv`` (the filtered measured track in the
   world frame with the covariance the GP was given) with the ``Qc`` the run found
   (``summary.json``): the same posterior, since the GP with a given ``Qc`` is exact;
2. query every prism at the times (:func:`rtsgt.interpolation.prisms.query_prisms`: GP posterior plus the
   systematic sources interpolated from the measurements when ``gp_noise = "white"``);
3. compute the poses and their 6x6 covariances with the run's pose engine, samples and seed
   (:func:`rtsgt.pose.estimate_poses`), or another engine (``"linear"`` is the fastest);
4. apply the run's quality gates (:func:`rtsgt.filtering.gates.apply_gates`).

At the run's own grid times this reproduces ``groundtruth_covariance.csv``, for the Monte
Carlo engine too: its draws come from the run's pose stream (:func:`rtsgt.options.stage_rng`,
``"pose"``), the stream the run itself drew its poses from, at every call (a query is
reproducible; at other sets of times the draws differ, since they depend on the set).

Every time gets a reason when no pose is given there (``GroundTruthSample.reason``), checked in
this order:

``outside_ground_truth``
    before the first or after the last interval the run kept;
``between_intervals``
    between two of the intervals where every prism was tracked (module 2 of the pipeline);
``gp_gap``
    inside a gap of a prism's measurements longer than the run's ``max_gap_s``;
``far_from_measurement``
    the nearest measurement of some prism is farther than ``max_gap_s`` of the query (the
    evaluation's ``--max-gap``);
``gate_degenerate``, ``gate_distance``, ``gate_uncertainty``
    the pose fails the run's quality gate of that name.

Correlations between the poses at different times, which the relative pose of the RPE
needs, come from :meth:`ContinuousGroundTruth.cross_covariance` (first order: the GP's
posterior cross-covariance, the systematic sources shared by both times, the calibration
coupling between stations and the reference survey); :func:`rtsgt.evaluation.evaluate` uses
it for the RPE NEES. Two ground-truth poses 1 s apart are typically 75-97 % correlated.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.calibration.coupling import StationCoupling
from rtsgt.errors import InputError
from rtsgt.evaluation.associate import (
    REASON_FAR,
    REASON_OUTSIDE,
    GroundTruthSample,
    _nearest_distance,
)
from rtsgt.filtering.gates import apply_gates
from rtsgt.interpolation import GPTrack
from rtsgt.interpolation.cross import gp_cross_covariance
from rtsgt.interpolation.prisms import fit_gps, gp_velocities, query_prisms
from rtsgt.io.run_dir import read_run
from rtsgt.options import RunOptions, stage_rng
from rtsgt.pose import POSE_ENGINES, ReferencePoints, estimate_poses
from rtsgt.pose.estimate import pose_jacobians
from rtsgt.record import RunRecord
from rtsgt.shared import SharedFactor, rank_one_factor, split_ground_truth
from rtsgt.types import PrismTrack

__all__ = [
    "DROP_REASONS",
    "REASON_BETWEEN",
    "REASON_GP_GAP",
    "ContinuousGroundTruth",
]

#: Drop reason: inside the ground-truth span but outside every interval common to all prisms.
REASON_BETWEEN = "between_intervals"
#: Drop reason: inside a gap of a prism's measurements longer than the run's ``max_gap_s``.
REASON_GP_GAP = "gp_gap"
#: Prefix of the drop reasons of the quality gates (``gate_`` + the gate's reason).
GATE_PREFIX = "gate_"
#: Every drop reason, in the order they are checked.
DROP_REASONS = (
    REASON_OUTSIDE,
    REASON_BETWEEN,
    REASON_GP_GAP,
    REASON_FAR,
    GATE_PREFIX + "degenerate",
    GATE_PREFIX + "distance",
    GATE_PREFIX + "uncertainty",
)



@dataclass(frozen=True)
class ContinuousGroundTruth:
    """The ground truth of a run, queryable at any time (module docstring).

    Build it with :meth:`from_run_dir` (a written run) or :meth:`from_result` (in memory).
    It is a :class:`~rtsgt.evaluation.associate.ValidatedGroundTruth`: pass it as the ground
    truth of :func:`rtsgt.evaluation.evaluate`.

    Attributes
    ----------
    tracks : dict str -> PrismTrack
        Measured track of every prism (world frame) with its per-source covariances.
    gps : dict str -> GPTrack
        Their GP posteriors (the run's ``Qc``).
    intervals : ndarray, shape (K, 2)
        Intervals where every prism was tracked (the run's module 2), s.
    reference : ReferencePoints
        Reference prisms in the body frame, in the order of ``tracks``.
    options : RunOptions
        Engine, samples, seed, ``gp_noise``, ``max_gap_s`` and gates used for the poses.
    uncertainty_measure : str
        Measure of the uncertainty gate (:func:`rtsgt.filtering.gates.position_uncertainty`).
    source : str
        Where it comes from (for messages).
    coupling : StationCoupling, optional
        Correlation of the station calibrations (the run's), for the joint prism covariance.
    station_origins : dict str -> ndarray (3,)
        World position of each station, m (the lever arm of the shared errors).
    split : bool
        Whether the run split its errors into varying and shared parts (it wrote
        ``groundtruth_shared.csv``); :meth:`shared_split` then gives the split at any time.
    """

    tracks: dict[str, PrismTrack]
    gps: dict[str, GPTrack]
    intervals: np.ndarray
    reference: ReferencePoints
    options: RunOptions
    uncertainty_measure: str = "max_std"
    source: str = ""
    coupling: StationCoupling | None = None
    station_origins: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    split: bool = False

    def __post_init__(self) -> None:
        if not self.tracks:
            raise InputError("Expected at least 3 prism tracks, got none")
        if set(self.tracks) != set(self.gps):
            raise ValueError("Expected one GP per track")
        if tuple(self.reference.names) != tuple(self.tracks):
            raise ValueError(
                f"Expected reference prisms {tuple(self.tracks)}, got {self.reference.names}"
            )
        iv = np.asarray(self.intervals, dtype=float).reshape(-1, 2)
        if iv.shape[0] == 0:
            raise InputError(f"{self.source or 'ground truth'}: no interval where every prism "
                             "was tracked")
        object.__setattr__(self, "intervals", iv[np.argsort(iv[:, 0])])

    # ---------------------------------------------------------------------------------------
    # construction
    # ---------------------------------------------------------------------------------------

    @classmethod
    def from_tracks(
        cls,
        tracks: dict[str, PrismTrack],
        qc: dict[str, ArrayLike],
        intervals: ArrayLike,
        reference: ReferencePoints,
        options: RunOptions,
        *,
        uncertainty_measure: str = "max_std",
        source: str = "",
        coupling: StationCoupling | None = None,
        qc_scale: dict[str, ArrayLike] | None = None,
        station_origins: dict[str, np.ndarray] | None = None,
        split: bool = False,
        prior: dict[str, str] | None = None,
    ) -> ContinuousGroundTruth:
        """Fit the GPs of ``tracks`` with the given per-prism ``Qc`` (m^2/s^3, or m^2/s^5 for
        a WNOJ prior) and, where given, its scale per interval between measurements and its
        motion prior (default WNOA)."""
        missing = [p for p in tracks if p not in qc]
        if missing:
            raise InputError(f"{source or 'ground truth'}: no Qc for prism(s) {', '.join(missing)}")
        gps = fit_gps(tracks, options.interpolation, qc={p: qc[p] for p in tracks},
                      qc_scale=qc_scale, prior=prior)
        return cls(dict(tracks), gps, np.asarray(intervals, dtype=float),
                   reference.select(list(tracks)), options, uncertainty_measure, source,
                   coupling, dict(station_origins or {}), split)

    @classmethod
    def from_record(
        cls,
        record: RunRecord,
        *,
        engine: str | None = None,
        samples: int | None = None,
        seed: int | None = None,
    ) -> ContinuousGroundTruth:
        """From a run record: one just computed by :func:`rtsgt.pipeline.run_pipeline` (its
        GPs are reused as fitted) or one read back by :func:`rtsgt.io.run_dir.read_run` (the
        GPs fitted again to the measured tracks, with the covariance and the Qc the run gave
        them: the same GPs).

        ``engine``, ``samples``, ``seed``: override the run's.

        Raises
        ------
        InputError
            A prism without its measured track or its Qc, a bad engine.
        """
        opts = _override(record.options, engine, samples, seed)
        source = record.name if record.path is None else str(record.path)
        summary_path = None if record.path is None else record.path / "summary.json"
        tracks: dict[str, PrismTrack] = {}
        for pid in record.prism_ids:
            tr = record.measurements.get(pid)
            if tr is None:
                raise InputError(f"no measured track of prism {pid}",
                                 None if record.path is None
                                 else record.path / "measurements" / f"prism{pid}.csv")
            if opts.interpolation.gp_noise == "all" and pid in record.measurements_gp_cov:
                # the GP was given the total covariance (the file's cov_* columns)
                tr = dataclasses.replace(tr, cov=record.measurements_gp_cov[pid])
            tracks[pid] = tr
        intervals = record.intervals
        if intervals is None:
            # an older summary: the span every prism covers
            lo = max(float(tr.t[0]) for tr in tracks.values())
            hi = min(float(tr.t[-1]) for tr in tracks.values())
            intervals = np.asarray([[lo, hi]] if hi > lo else [], dtype=float).reshape(-1, 2)
        reference = record.tracked_reference
        split = record.groundtruth_split is not None
        if record.computation is not None:
            gps = record.computation.gps
            return cls(tracks, {p: gps[p] for p in tracks}, np.asarray(intervals), reference,
                       opts, record.uncertainty_measure, source, record.coupling,
                       dict(record.stations), split)
        for pid in tracks:
            if pid not in record.qc:
                raise InputError(f"no qc_m2_s3 for prism {pid} under 'prisms'", summary_path)
        return cls.from_tracks(tracks, record.qc, intervals, reference, opts,
                               uncertainty_measure=record.uncertainty_measure, source=source,
                               coupling=record.coupling, qc_scale=record.qc_scale,
                               station_origins=record.stations, split=split,
                               prior=record.prior)

    @classmethod
    def from_run_dir(
        cls,
        run_dir: str | PathLike,
        *,
        engine: str | None = None,
        samples: int | None = None,
        seed: int | None = None,
    ) -> ContinuousGroundTruth:
        """From a run directory: :meth:`from_record` of :func:`rtsgt.io.run_dir.read_run`
        (the only reader of its files), which needs ``measurements/prism<i>.csv`` and
        ``summary.json`` with each prism's ``qc_m2_s3``.

        Raises
        ------
        InputError
            A missing or malformed file, no Qc in ``summary.json``, a bad engine.
        """
        root = Path(run_dir)
        if not (root / "measurements").is_dir():
            raise InputError(
                "no measurements/ folder: not an rtsgt run directory with measured tracks", root
            )
        record = read_run(root)
        if not record.summary:
            raise InputError("missing or empty summary.json (the run's Qc and options)",
                             root / "summary.json")
        return cls.from_record(record, engine=engine, samples=samples, seed=seed)

    # ---------------------------------------------------------------------------------------
    # queries
    # ---------------------------------------------------------------------------------------

    @property
    def prism_ids(self) -> tuple[str, ...]:
        return tuple(self.tracks)

    @property
    def info(self) -> dict:
        """JSON-ready description (source, engine, samples, seed, prisms, run limits)."""
        o, p = self.options, self.options.pose
        return {
            "source": self.source,
            "engine": p.engine,
            "registration": p.registration,
            "samples": p.samples if p.engine == "mc" else None,
            "seed": o.seed if p.engine == "mc" else None,
            "prisms": list(self.prism_ids),
            "intervals": int(self.intervals.shape[0]),
            "run_max_gap_s": float(o.interpolation.max_gap_s),
            "distance_gate_m": float(p.distance_gate_m),
            "uncertainty_gate_m": float(p.uncertainty_gate_m),
        }

    @property
    def span(self) -> tuple[float, float]:
        """First and last time at which a pose can be given, s."""
        return float(self.intervals[0, 0]), float(self.intervals[-1, 1])

    @property
    def measurement_times(self) -> np.ndarray:
        """Sorted times of every prism measurement, s."""
        return np.unique(np.concatenate([tr.t for tr in self.tracks.values()]))

    def nearest_measurement_dt(self, times: ArrayLike) -> np.ndarray:
        """Largest over the prisms of the distance to that prism's nearest measurement, s."""
        tau = np.asarray(times, dtype=float)
        return np.max([_nearest_distance(tr.t, tau) for tr in self.tracks.values()], axis=0)

    def cross_covariance(self, tau_a: ArrayLike, tau_b: ArrayLike) -> np.ndarray:
        """``Cov(xi(tau_a), xi(tau_b))`` (K, 6, 6) of the poses at pairs of times, first order.

        What the relative pose between two ground-truth times needs (the RPE's covariance):
        the errors the two poses share. Per prism, the GP posterior's cross-covariance between
        the two times (:func:`rtsgt.interpolation.cross.gp_cross_covariance`); a station's
        clock offset and atmosphere are one draw for both times (rank-one factors along the
        velocity and the line of sight); the calibrations through :class:`StationCoupling`
        (across prisms too); the reference survey is the same at both times. All times must
        be valid (:meth:`query_poses`).
        """
        return self._between(self._linearise(tau_a), self._linearise(tau_b))

    def pair_covariances(
        self, tau_a: ArrayLike, tau_b: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``Cov(xi(tau_a))``, ``Cov(xi(tau_b))`` and ``Cov(xi(tau_a), xi(tau_b))`` of the same
        first-order model (:meth:`cross_covariance`), each time linearised once."""
        sa, sb = self._linearise(tau_a), self._linearise(tau_b)
        return self._between(sa, sa), self._between(sb, sb), self._between(sa, sb)

    def shared_split(self, times: ArrayLike) -> SharedFactor | None:
        """The poses' error split into varying and shared parts at valid times (first order,
        :func:`rtsgt.shared.split_ground_truth`, the varying covariance by the linear engine);
        None when the run did not split its errors (an older run, ``gp_noise = "all"``).

        The shared parameters are the run's (``groundtruth_shared.csv``): the same names, and
        at the run's own times the same factor to first order.
        """
        if not self.split or self.options.interpolation.gp_noise != "white":
            return None
        tau = np.atleast_1d(np.asarray(times, dtype=float))
        pr = query_prisms(self.tracks, self.gps, tau, self.options.interpolation, self.coupling)
        registration = self.options.pose.registration
        est = estimate_poses(pr.xyz, pr.pose_covariance, self.reference, engine="linear",
                             registration=registration)
        velocity = gp_velocities({p: self.gps[p] for p in self.tracks}, tau)
        origins = dict(self.station_origins)
        if self.coupling is not None:
            origins.update(self.coupling.origin)
        return split_ground_truth(pr, velocity, [tr.station for tr in self.tracks.values()],
                                  origins, self.coupling, self.reference, est.R,
                                  registration=registration)

    def _linearise(self, tau: ArrayLike) -> _Linearised:
        tau = np.atleast_1d(np.asarray(tau, dtype=float))
        pr = query_prisms(self.tracks, self.gps, tau, self.options.interpolation, self.coupling)
        registration = self.options.pose.registration
        est = estimate_poses(pr.xyz, pr.pose_covariance, self.reference, engine="linear",
                             registration=registration)
        J_q, J_r = pose_jacobians(pr.xyz, self.reference.xyz, est.R, registration=registration,
                                  cov_q=pr.pose_covariance, cov_r=self.reference.cov)
        velocity = list(np.moveaxis(gp_velocities({p: self.gps[p] for p in self.tracks}, tau),
                                    1, 0))
        return _Linearised(tau, pr, J_q, J_r, velocity)

    def _between(self, a: _Linearised, b: _Linearised) -> np.ndarray:
        ids = list(self.tracks)
        n, K = len(ids), a.t.size
        stations = [self.tracks[p].station for p in ids]
        C = np.zeros((K, 3 * n, 3 * n))
        systematic = self.options.interpolation.gp_noise == "white"
        for i, pid in enumerate(ids):
            blk = gp_cross_covariance(self.gps[pid], a.t, b.t)[:, :3, :3]
            if systematic:
                origin = (self.coupling.origin.get(stations[i], np.zeros(3))
                          if self.coupling is not None else np.zeros(3))
                for src, da, db in (
                    ("time_sync", a.velocity[i], b.velocity[i]),
                    ("atmosphere", a.prisms.xyz[:, i] - origin, b.prisms.xyz[:, i] - origin),
                ):
                    if src not in a.prisms.cov_by_source:
                        continue
                    fa = rank_one_factor(a.prisms.cov_by_source[src][:, i], da)
                    fb = rank_one_factor(b.prisms.cov_by_source[src][:, i], db)
                    blk = blk + fa[:, :, None] * fb[:, None, :]
            C[:, 3 * i:3 * i + 3, 3 * i:3 * i + 3] = blk
        if systematic and self.coupling is not None and "calibration" in a.prisms.cov_by_source:
            C += self.coupling.prism_covariance(a.prisms.xyz, b.prisms.xyz, stations)
        cr = self.reference.cov
        return a.J_q @ C @ np.swapaxes(b.J_q, 1, 2) + a.J_r @ cr @ np.swapaxes(b.J_r, 1, 2)

    def query_poses(
        self, times: ArrayLike, *, max_gap_s: float | None = None
    ) -> GroundTruthSample:
        """Poses, covariances and validity at arbitrary times.

        Parameters
        ----------
        times : array_like, shape (M,)
            Query times on the ground truth's clock, s, any order.
        max_gap_s : float, optional
            Drop the times whose nearest measurement of some prism is farther than this, s
            (``far_from_measurement``); None: only the run's own limits apply.

        Returns
        -------
        GroundTruthSample
            ``reason`` is ``""`` for a valid pose, else a code of :data:`DROP_REASONS`.
        """
        tau = np.asarray(times, dtype=float)
        if tau.ndim != 1:
            raise InputError(f"Expected query times of shape (M,), got {tau.shape}")
        if not np.all(np.isfinite(tau)):
            raise InputError("Expected finite query times, got NaN or inf")
        if max_gap_s is not None and not max_gap_s > 0:
            raise InputError(f"Expected a positive max_gap_s, got {max_gap_s}")
        M = tau.size
        reason = np.full(M, "", dtype="<U24")
        a, b = self.span
        outside = (tau < a) | (tau > b)
        in_iv = np.zeros(M, dtype=bool)
        for lo, hi in self.intervals:
            in_iv |= (tau >= lo) & (tau <= hi)
        supported = np.ones(M, dtype=bool)
        for g in self.gps.values():
            supported &= g.supported(tau)
        nearest = self.nearest_measurement_dt(tau) if M else np.empty(0)
        far = np.zeros(M, dtype=bool) if max_gap_s is None else nearest > max_gap_s
        reason[far] = REASON_FAR
        reason[~supported] = REASON_GP_GAP
        reason[~in_iv] = REASON_BETWEEN
        reason[outside] = REASON_OUTSIDE
        nearest = np.where(outside, np.nan, nearest)

        position = np.full((M, 3), np.nan)
        quat = np.full((M, 4), np.nan)
        cov = np.full((M, 6, 6), np.nan)
        idx = np.flatnonzero(reason == "")
        if idx.size:
            prisms = query_prisms(self.tracks, self.gps, tau[idx], self.options.interpolation,
                                  self.coupling)
            opt = self.options.pose
            est = estimate_poses(
                prisms.xyz, prisms.pose_covariance, self.reference, engine=opt.engine,
                registration=opt.registration, samples=opt.samples,
                rng=stage_rng(self.options.seed, "pose") if opt.engine == "mc" else None,
            )
            keep, report = apply_gates(
                est, self.reference, distance_gate_m=opt.distance_gate_m,
                uncertainty_gate_m=opt.uncertainty_gate_m,
                uncertainty_measure=self.uncertainty_measure,
            )
            position[idx] = est.position
            quat[idx] = est.quat_xyzw
            cov[idx] = est.cov
            gated = idx[~keep]
            reason[gated] = np.char.add(GATE_PREFIX, report.reason[~keep].astype(str))
        return GroundTruthSample(tau.copy(), position, quat, cov, reason, nearest, None)


def _override(options: RunOptions, engine: str | None, samples: int | None,
              seed: int | None) -> RunOptions:
    if engine is not None and engine not in POSE_ENGINES:
        raise InputError(f"Expected a ground-truth engine in {POSE_ENGINES}, got {engine!r}")
    changes = {"engine": engine, "samples": None if samples is None else int(samples),
               "seed": None if seed is None else int(seed)}
    return options.updated(**{k: v for k, v in changes.items() if v is not None})


@dataclass(frozen=True)
class _Linearised:
    """The ground truth at some times, with what the first-order cross-covariance needs."""

    t: np.ndarray
    prisms: object  # rtsgt.pipeline.PrismsAtTimes
    J_q: np.ndarray  # (K, 6, 3n) pose Jacobian on the stacked prisms
    J_r: np.ndarray  # (K, 6, 3n) pose Jacobian on the stacked reference
    velocity: list  # per prism, (K, 3) GP velocity, m/s
