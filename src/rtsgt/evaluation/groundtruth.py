r"""Continuous-time ground truth: the poses (or one prism's positions) of a run at any time.

:class:`ContinuousGroundTruth` redoes at the requested times what the pipeline did on its
grid: the prisms' GPs refitted with the run's ``Qc``, queried with the systematic sources, turned
into poses by the run's engine and gated; each dropped time gets a reason (:data:`DROP_REASONS`).
:class:`ContinuousPositionGroundTruth` does it for one prism (3 dof). Both give the
covariance between two times (the RPE) and the error split. docs/evaluation.md#association.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError
from rtsgt.evaluation.associate import (
    REASON_FAR,
    REASON_OUTSIDE,
    GroundTruthSample,
    PositionSplit,
    nearest_distance,
)
from rtsgt.interpolation import GPTrack
from rtsgt.interpolation.cross import gp_cross_covariance
from rtsgt.interpolation.prisms import PrismsAtTimes, fit_gps, gp_velocities, query_prisms
from rtsgt.noise.coupling import StationCoupling
from rtsgt.options import RunOptions
from rtsgt.pose import POSE_ENGINES, ReferencePoints, estimate_poses
from rtsgt.pose.estimate import pose_jacobians
from rtsgt.record import RunRecord
from rtsgt.shared import SharedFactor, prism_shared_factor, rank_one_factor, split_ground_truth
from rtsgt.stages.poses import gated_poses
from rtsgt.types import PrismTrack

__all__ = [
    "ContinuousPositionGroundTruth",
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
    """The ground truth of a run, queryable at any time; build it with :meth:`from_record`.

    A :class:`~rtsgt.evaluation.associate.ValidatedGroundTruth`: ``tracks`` and their ``gps`` per
    prism, ``intervals`` (K, 2) s, ``reference`` prisms in the body frame, ``options`` (engine,
    samples, seed, ``gp_noise``, ``max_gap_s``, gates), ``uncertainty_measure``, ``source`` (for
    messages), ``coupling`` of the calibrations, ``station_origins`` (3,) m, ``split`` (the run
    wrote ``groundtruth_shared.csv``).
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
    #: The degrees of freedom it gives (poses).
    dof: ClassVar[int] = 6

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
        """From a run record, just computed (its GPs reused) or read back (GPs refitted with the run's
        covariance and Qc: the same); ``engine``, ``samples``, ``seed`` override the run's. InputError
        for a prism without track or Qc, or a bad engine.
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
        return np.max([nearest_distance(tr.t, tau) for tr in self.tracks.values()], axis=0)

    def cross_covariance(self, tau_a: ArrayLike, tau_b: ArrayLike) -> np.ndarray:
        """``Cov(xi(tau_a), xi(tau_b))`` (K, 6, 6) of the poses at pairs of valid times, first order
        (docs/evaluation.md#relative-pose-covariance).
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
            C[:, 3 * i:3 * i + 3, 3 * i:3 * i + 3] = prism_cross_covariance(
                self.gps[pid], a.t, b.t, a.prisms, b.prisms, i, a.velocity[i], b.velocity[i],
                _origin(self.coupling, stations[i]) if systematic else None)
        if systematic and self.coupling is not None and "calibration" in a.prisms.cov_by_source:
            C += self.coupling.prism_covariance(a.prisms.xyz, b.prisms.xyz, stations)
        cr = self.reference.cov
        return a.J_q @ C @ np.swapaxes(b.J_q, 1, 2) + a.J_r @ cr @ np.swapaxes(b.J_r, 1, 2)

    def query_poses(
        self, times: ArrayLike, *, max_gap_s: float | None = None
    ) -> GroundTruthSample:
        """:class:`GroundTruthSample` at ``times`` (M,) s (ground-truth clock, any order); ``max_gap_s``
        drops times farther from some prism's nearest measurement (None: the run's limits only).
        """
        tau, reason, nearest = _query_times(
            times, max_gap_s, self.intervals, list(self.gps.values()),
            self.nearest_measurement_dt)
        M = tau.size
        position = np.full((M, 3), np.nan)
        quat = np.full((M, 4), np.nan)
        cov = np.full((M, 6, 6), np.nan)
        idx = np.flatnonzero(reason == "")
        if idx.size:
            prisms = query_prisms(self.tracks, self.gps, tau[idx], self.options.interpolation,
                                  self.coupling)
            gated = gated_poses(prisms, self.reference, self.options, self.uncertainty_measure)
            est, keep, report = gated.estimate, gated.keep, gated.report
            position[idx] = est.position
            quat[idx] = est.quat_xyzw
            cov[idx] = est.cov
            gated = idx[~keep]
            reason[gated] = np.char.add(GATE_PREFIX, report.reason[~keep].astype(str))
        return GroundTruthSample(tau.copy(), position, quat, cov, reason, nearest, None)


@dataclass(frozen=True)
class ContinuousPositionGroundTruth:
    """One prism of a run, queryable at any time: the position-only ground truth (3 dof,
    docs/evaluation.md#position-only-ground-truth).

    The prism's GP posterior plus the systematic sources; drop reasons as for poses, without the
    gates. ``prism``, ``track``, ``gp``, ``intervals`` (K, 2) s, ``options``, ``source``,
    ``coupling``, ``station_origins`` as in :class:`ContinuousGroundTruth`.
    """

    prism: str
    track: PrismTrack
    gp: GPTrack
    intervals: np.ndarray
    options: RunOptions
    source: str = ""
    coupling: StationCoupling | None = None
    station_origins: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    #: The degrees of freedom it gives (positions).
    dof: ClassVar[int] = 3

    def __post_init__(self) -> None:
        iv = np.asarray(self.intervals, dtype=float).reshape(-1, 2)
        if iv.shape[0] == 0:
            raise InputError(f"{self.source or 'ground truth'}: no interval where the prism "
                             "was tracked")
        object.__setattr__(self, "intervals", iv[np.argsort(iv[:, 0])])

    @classmethod
    def from_record(cls, record, prism: str | None = None) -> ContinuousPositionGroundTruth:
        """From a pose or position-only run record (GP reused, or refitted with the run's Qc); ``prism``
        may be left out when the run tracked one. InputError for an unknown or unchosen prism, or no
        track or Qc.
        """
        ids = tuple(record.prism_ids)
        source = record.name if record.path is None else str(record.path)
        if prism is None:
            if len(ids) != 1:
                raise InputError(f"{source}: the run tracked prisms {', '.join(ids)}; choose "
                                 "one (--prism)")
            prism = ids[0]
        prism = str(prism)
        if prism not in ids:
            raise InputError(f"{source}: no prism {prism!r}; the run tracked "
                             f"{', '.join(ids)}")
        track = record.measurements.get(prism)
        if track is None:
            raise InputError(f"no measured track of prism {prism}",
                             None if record.path is None
                             else record.path / "measurements" / f"prism{prism}.csv")
        opts = record.options
        if opts.interpolation.gp_noise == "all" and prism in record.measurements_gp_cov:
            track = dataclasses.replace(track, cov=record.measurements_gp_cov[prism])
        intervals = record.intervals
        if intervals is None:  # an older summary: the span of the track
            intervals = np.asarray([[track.t[0], track.t[-1]]], dtype=float)
        origins = dict(record.stations)
        if record.coupling is not None:
            origins.update(record.coupling.origin)
        computation = record.computation
        if computation is not None:
            gp = computation.gps[prism]
        else:
            if prism not in record.qc:
                raise InputError(f"no qc_m2_s3 for prism {prism} under 'prisms'",
                                 None if record.path is None else record.path / "summary.json")
            gp = fit_gps({prism: track}, opts.interpolation, qc={prism: record.qc[prism]},
                         qc_scale={p: v for p, v in record.qc_scale.items() if p == prism},
                         prior={prism: record.prior.get(prism, "wnoa")})[prism]
        return cls(prism, track, gp, np.asarray(intervals, dtype=float), opts, source,
                   record.coupling, origins)

    @property
    def name(self) -> str:
        return f"prism {self.prism}"

    @property
    def info(self) -> dict:
        """JSON-ready description."""
        return {"source": self.source, "kind": "positions", "prism": self.prism,
                "station": self.track.station, "intervals": int(self.intervals.shape[0]),
                "run_max_gap_s": float(self.options.interpolation.max_gap_s),
                "gp_noise": self.options.interpolation.gp_noise}

    @property
    def span(self) -> tuple[float, float]:
        """First and last time at which a position can be given, s."""
        return float(self.intervals[0, 0]), float(self.intervals[-1, 1])

    @property
    def measurement_times(self) -> np.ndarray:
        return np.asarray(self.track.t)

    def _prisms(self, tau: np.ndarray) -> PrismsAtTimes:
        return query_prisms({self.prism: self.track}, {self.prism: self.gp}, tau,
                            self.options.interpolation, self.coupling)

    def query_positions(self, times: ArrayLike, *, max_gap_s: float | None = None):
        """:class:`GroundTruthSample` of positions (``quat_xyzw`` None, ``cov`` (M, 3, 3)) at ``times``;
        ``max_gap_s`` as :meth:`ContinuousGroundTruth.query_poses`.
        """
        tau, reason, nearest = _query_times(
            times, max_gap_s, self.intervals, [self.gp],
            lambda tau: nearest_distance(np.asarray(self.track.t), tau))
        M = tau.size
        position = np.full((M, 3), np.nan)
        cov = np.full((M, 3, 3), np.nan)
        idx = np.flatnonzero(reason == "")
        if idx.size:
            pr = self._prisms(tau[idx])
            position[idx] = pr.xyz[:, 0]
            cov[idx] = pr.cov[:, 0]
        return GroundTruthSample(tau.copy(), position, None, cov, reason, nearest)

    def pair_covariances(
        self, tau_a: ArrayLike, tau_b: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``Cov(y(a))``, ``Cov(y(b))`` and ``Cov(y(a), y(b))`` (K, 3, 3) of one first-order
        model (class docstring) at valid times."""
        ta = np.atleast_1d(np.asarray(tau_a, dtype=float))
        tb = np.atleast_1d(np.asarray(tau_b, dtype=float))
        pa, pb = self._prisms(ta), self._prisms(tb)
        va = self.gp.query(ta, with_velocity=True, allow_gaps=True).velocity
        vb = self.gp.query(tb, with_velocity=True, allow_gaps=True).velocity
        systematic = self.options.interpolation.gp_noise == "white"
        origin = (self.station_origins.get(self.track.station, np.zeros(3))
                  if systematic else None)

        def between(p, q, tp, tq, vp, vq):
            C = prism_cross_covariance(self.gp, tp, tq, p, q, 0, vp, vq, origin)
            if (systematic and self.coupling is not None
                    and "calibration" in p.cov_by_source):
                C = C + self.coupling.prism_covariance(p.xyz, q.xyz, [self.track.station])
            return C

        return (between(pa, pa, ta, ta, va, va), between(pb, pb, tb, tb, vb, vb),
                between(pa, pb, ta, tb, va, vb))

    def shared_split(self, times: ArrayLike):
        """The error split at valid times (GP posterior varying; station calibration, clock and
        atmosphere shared, :func:`rtsgt.shared.prism_shared_factor`), or None with ``gp_noise = "all"``.
        """
        if self.options.interpolation.gp_noise != "white":
            return None
        tau = np.atleast_1d(np.asarray(times, dtype=float))
        pr = self._prisms(tau)
        velocity = self.gp.query(tau, with_velocity=True, allow_gaps=True).velocity[:, None]
        F, names = prism_shared_factor(pr, velocity, [self.track.station],
                                       self.station_origins, self.coupling)
        return PositionSplit(pr.cov_gp[:, 0], F, names)


def _query_times(times: ArrayLike, max_gap_s: float | None, intervals: np.ndarray,
                 gps: list[GPTrack], nearest_dt) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Query times checked, with the reason each cannot be answered (``""``: it can) and
    the distance to the nearest measurement (``nearest_dt(tau)``; NaN outside the span).

    The reasons, weakest first (a later one overrides): farther than ``max_gap_s`` from a
    measurement, across a gap of one of the ``gps``, between the run's ``intervals``, outside
    their span.
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
    outside = (tau < intervals[0, 0]) | (tau > intervals[-1, 1])
    in_iv = np.zeros(M, dtype=bool)
    for lo, hi in intervals:
        in_iv |= (tau >= lo) & (tau <= hi)
    supported = np.ones(M, dtype=bool)
    for g in gps:
        supported &= g.supported(tau)
    nearest = nearest_dt(tau) if M else np.empty(0)
    far = np.zeros(M, dtype=bool) if max_gap_s is None else nearest > max_gap_s
    reason[far] = REASON_FAR
    reason[~supported] = REASON_GP_GAP
    reason[~in_iv] = REASON_BETWEEN
    reason[outside] = REASON_OUTSIDE
    return tau, reason, np.where(outside, np.nan, nearest)


def _origin(coupling: StationCoupling | None, station: str | None) -> np.ndarray:
    """A station's world position as the calibration coupling has it (zero without one)."""
    if coupling is None:
        return np.zeros(3)
    return np.asarray(coupling.origin.get(station, np.zeros(3)), dtype=float)


def prism_cross_covariance(gp: GPTrack, t_a: np.ndarray, t_b: np.ndarray,
                           prisms_a: PrismsAtTimes, prisms_b: PrismsAtTimes, i: int,
                           velocity_a: np.ndarray, velocity_b: np.ndarray,
                           origin: np.ndarray | None) -> np.ndarray:
    """``Cov(q_i(a), q_i(b))`` (K, 3, 3) of prism ``i`` at pairs of times, first order, without the
    calibration: the GP's cross-covariance plus, with ``origin`` (None under ``gp_noise = "all"``),
    rank-one factors of the clock offset and atmosphere from ``prisms_a``, ``prisms_b``.
    """
    blk = gp_cross_covariance(gp, t_a, t_b)[:, :3, :3]
    if origin is None:
        return blk
    for src, da, db in (
        ("time_sync", velocity_a, velocity_b),
        ("atmosphere", prisms_a.xyz[:, i] - origin, prisms_b.xyz[:, i] - origin),
    ):
        if src not in prisms_a.cov_by_source:
            continue
        fa = rank_one_factor(prisms_a.cov_by_source[src][:, i], da)
        fb = rank_one_factor(prisms_b.cov_by_source[src][:, i], db)
        blk = blk + fa[:, :, None] * fb[:, None, :]
    return blk


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
