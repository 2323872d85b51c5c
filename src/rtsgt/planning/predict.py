"""The pose uncertainty a run would report, predicted from a layout before any measurement.

:func:`predict_poses` goes through a run's stages with the linear engines and no data, each
stage the run's own code: prisms at the pose, their measurement covariance
(:func:`rtsgt.noise.propagate`), the GP's posterior on a uniform track
(:mod:`rtsgt.planning.gp_factor`) plus the systematic sources, the stations' shared
calibration errors, and the pose fit. ``Qc`` comes from a run (:func:`qc_from_run`) or
:data:`DEFAULT_QC_M2_S3`. Sigmas are ``sqrt(tr)`` of the position and rotation blocks.
docs/planning.md#the-prediction-step-by-step, docs/planning.md#what-the-prediction-neglects.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError
from rtsgt.interpolation.motion import CLASS_NAMES, STANDING_SPEED_M_S
from rtsgt.interpolation.prisms import SYSTEMATIC_SOURCES, gp_covariance
from rtsgt.measurement.polar import cartesian_to_polar
from rtsgt.noise import propagate
from rtsgt.noise.coupling import joint_prism_covariance
from rtsgt.planning.gp_factor import gp_posterior_covariance
from rtsgt.planning.layout import Layout
from rtsgt.stages.poses import pose_estimate
from rtsgt.types import Observations, PrismTrack

__all__ = ["DEFAULT_QC_M2_S3", "DEFAULT_SPEED_M_S", "MIN_RANGE_M", "PosePrediction",
           "RobotMotion", "heading_poses", "measurement_track", "predict_poses", "qc_from_run"]

#: The robot's speed when the plan does not say, m/s (a walking pace).
DEFAULT_SPEED_M_S = 1.0
#: ``Qc`` of the GP when the plan gives neither a value nor an earlier run, m^2/s^3
#: (horizontal, vertical): the simulator's default robot, the decade nearest to the median of
#: its leave-one-out ``Qc`` while moving (docs/planning.md#the-gp-and-qc).
DEFAULT_QC_M2_S3 = (1e-4, 1e-7)
#: Poses with a prism nearer than this to its station are not predicted, m (a robot does not
#: drive into a tripod).
MIN_RANGE_M = 2.0


def _qc_matrix(horizontal: float, vertical: float) -> np.ndarray:
    if not (horizontal > 0 and vertical > 0 and np.isfinite(horizontal)
            and np.isfinite(vertical)):
        raise InputError(f"Expected Qc > 0 (horizontal, vertical), got {horizontal!r}, "
                         f"{vertical!r} m^2/s^3")
    return np.diag([float(horizontal), float(horizontal), float(vertical)])


@dataclass(frozen=True)
class RobotMotion:
    """What a plan assumes of the robot's motion: ``speed_m_s`` where the plan gives no times,
    the GP's ``qc_m2_s3`` (3, 3; world axes, horizontal ones equal) while moving and
    ``qc_standing_m2_s3`` while standing (None: the same), and ``qc_source`` in words."""

    speed_m_s: float = DEFAULT_SPEED_M_S
    qc_m2_s3: np.ndarray = field(default_factory=lambda: _qc_matrix(*DEFAULT_QC_M2_S3))
    qc_standing_m2_s3: np.ndarray | None = None
    qc_source: str = "default"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.speed_m_s) and self.speed_m_s >= 0):
            raise InputError(f"Expected a speed >= 0 m/s, got {self.speed_m_s!r}")

    @classmethod
    def given(cls, qc_horizontal: float, qc_vertical: float | None = None,
              speed_m_s: float = DEFAULT_SPEED_M_S, source: str = "given") -> RobotMotion:
        """One ``Qc`` (m^2/s^3; the vertical defaults to the horizontal) for all motion."""
        v = qc_horizontal if qc_vertical is None else qc_vertical
        return cls(float(speed_m_s), _qc_matrix(qc_horizontal, v), None, source)

    def qc_at(self, speed: np.ndarray) -> np.ndarray:
        """``Qc`` (P, 3, 3) at the speeds (P,) m/s."""
        speed = np.asarray(speed, dtype=float)
        out = np.broadcast_to(self.qc_m2_s3, speed.shape + (3, 3)).copy()
        if self.qc_standing_m2_s3 is not None:
            out[speed < STANDING_SPEED_M_S] = self.qc_standing_m2_s3
        return out

    def to_dict(self) -> dict:
        """JSON-ready."""
        d = {"speed_m_s": self.speed_m_s, "qc_source": self.qc_source,
             "qc_moving_m2_s3": {"horizontal": float(self.qc_m2_s3[0, 0]),
                                 "vertical": float(self.qc_m2_s3[2, 2])}}
        if self.qc_standing_m2_s3 is not None:
            d["qc_standing_m2_s3"] = {"horizontal": float(self.qc_standing_m2_s3[0, 0]),
                                      "vertical": float(self.qc_standing_m2_s3[2, 2])}
        return d


def qc_from_run(prisms: Mapping[str, Mapping], speed_m_s: float = DEFAULT_SPEED_M_S,
                source: str = "an earlier run") -> RobotMotion:
    """The robot's ``Qc`` as a run found it, from ``summary.json``'s ``prisms`` (per prism
    ``qc_m2_s3`` and ``qc_fit.motion_prior``): moving, the run's ``Qc`` times the moving
    classes' mean scale weighted by their intervals; standing, times the standing class's; the
    prisms averaged, the horizontal value the mean of x and y (docs/planning.md#the-gp-and-qc)."""
    moving, standing, any_standing = [], [], False
    for pid, info in prisms.items():
        qc = np.asarray(info.get("qc_m2_s3"), dtype=float)
        if qc.shape != (3, 3) or not np.all(np.isfinite(qc)):
            raise InputError(f"prism {pid}: expected a 3x3 qc_m2_s3 in the run's summary")
        mp = (info.get("qc_fit") or {}).get("motion_prior") or {}
        scale_move, scale_stand = 1.0, 1.0
        if mp.get("chosen") == "classes":
            scales, counts = mp.get("scales", {}), mp.get("intervals", {})
            moving_classes = [c for c in CLASS_NAMES[1:] if c in scales and counts.get(c)]
            if moving_classes:
                w = np.array([counts[c] for c in moving_classes], dtype=float)
                scale_move = float(np.sum(w * [scales[c] for c in moving_classes]) / w.sum())
            if CLASS_NAMES[0] in scales:
                scale_stand, any_standing = float(scales[CLASS_NAMES[0]]), True
        moving.append(qc * scale_move)
        standing.append(qc * scale_stand)
    if not moving:
        raise InputError("the run's summary has no prism with a Qc")

    def hv(m):
        m = np.mean(m, axis=0)
        return _qc_matrix(0.5 * (m[0, 0] + m[1, 1]), m[2, 2])

    return RobotMotion(float(speed_m_s), hv(moving), hv(standing) if any_standing else None,
                       source)


@dataclass(frozen=True)
class PosePrediction:
    """Predicted uncertainty of P poses ``R`` (P, 3, 3), ``t`` (P, 3): the prisms ``prisms_xyz``
    (P, n, 3), world, m; the pose ``cov`` (P, 6, 6; left perturbation, x, y, z, rx, ry, rz; NaN
    where not predicted); each prism's total ``prism_cov`` (P, n, 3, 3) and by source
    (``prism_cov_by_source``: ``"gp"`` and each systematic source); ``ranges_m`` (P, n) to the
    stations; ``valid`` (P,): no prism nearer than :data:`MIN_RANGE_M`, not degenerate."""

    R: np.ndarray
    t: np.ndarray
    prisms_xyz: np.ndarray
    cov: np.ndarray
    prism_cov: np.ndarray
    prism_cov_by_source: dict[str, np.ndarray]
    ranges_m: np.ndarray
    valid: np.ndarray

    @property
    def sigma_m(self) -> np.ndarray:
        """``sqrt(tr Sigma_t)``, m, shape (P,) (the run's "sigma translation")."""
        return np.sqrt(np.trace(self.cov[:, :3, :3], axis1=1, axis2=2))

    @property
    def rotation_sigma_rad(self) -> np.ndarray:
        """``sqrt(tr Sigma_theta)``, rad, shape (P,)."""
        return np.sqrt(np.trace(self.cov[:, 3:, 3:], axis1=1, axis2=2))


def measurement_track(layout: Layout, k: int, q: np.ndarray, v: np.ndarray) -> PrismTrack:
    """The linear engine's covariances of station ``k``'s measurements of its prism at the world
    points ``q`` (P, 3) moving at ``v`` (P, 3): the middle one of three synthetic measurements
    per point (docs/planning.md#the-prediction-step-by-step, step 2)."""
    station = layout.stations[k]
    T = layout.calibration.transforms[station]
    h = 1.0 / layout.rate_hz[k]
    R, tw = np.asarray(T.rotation, dtype=float), np.asarray(T.translation, dtype=float)
    P = q.shape[0]
    offsets = np.array([-1.0, 0.0, 1.0])
    pts = q[:, None, :] + offsets[None, :, None] * h * v[:, None, :]  # (P, 3, 3) world
    p_st = (pts.reshape(-1, 3) - tw) @ R  # rows R^T (p - t)
    hz, zen, d = cartesian_to_polar(p_st)
    block = 2.0 * h + 2.0 * layout.model.max_velocity_gap_s + 1.0  # no stencil across points
    times = (np.arange(P)[:, None] * block + offsets[None, :] * h).ravel()
    obs = Observations(times, hz, zen, d, None, station, layout.prisms[k], 0.0, "plan")
    track = propagate(obs, layout.model, T_world_station=T, engine="linear")
    mid = slice(1, None, 3)
    return PrismTrack(track.t[mid], track.xyz[mid], track.cov[mid],
                      {s: c[mid] for s, c in track.cov_by_source.items()}, track.prism,
                      track.frame, station, track.range_m[mid])


def predict_poses(layout: Layout, R: ArrayLike, t: ArrayLike, velocity: ArrayLike,
                  motion: RobotMotion) -> PosePrediction:
    """Predicted covariance of the poses ``R`` (P, 3, 3), ``t`` (P, 3; world, m) of a robot moving
    at ``velocity`` (P, 3), m/s, under ``motion`` (the GP's ``Qc`` by speed)."""
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    t = np.asarray(t, dtype=float).reshape(-1, 3)
    vel = np.broadcast_to(np.asarray(velocity, dtype=float), t.shape)
    P, n = t.shape[0], len(layout.stations)
    q = np.einsum("pij,nj->pni", R, layout.reference.xyz) + t[:, None, :]
    origins = layout.station_xyz(plan_frame=False)
    ranges = np.linalg.norm(q - np.stack([origins[s] for s in layout.stations]), axis=-1)
    ok = np.all(ranges >= MIN_RANGE_M, axis=1) & np.all(np.isfinite(q), axis=(1, 2))
    idx = np.flatnonzero(ok)
    gp_noise = layout.options.interpolation.gp_noise
    qc = motion.qc_at(np.linalg.norm(vel[idx], axis=1))
    cov = np.full((idx.size, n, 3, 3), np.nan)
    by_source: dict[str, np.ndarray] = {}
    for k in range(n):  # a loop over the stations (3 to 5), vectorised over poses
        track = measurement_track(layout, k, q[idx, k], vel[idx])
        gp = gp_posterior_covariance(gp_covariance(track, gp_noise), qc, 1.0 / layout.rate_hz[k])
        by_source.setdefault("gp", np.zeros_like(cov))[:, k] = gp
        cov[:, k] = gp
        for s in SYSTEMATIC_SOURCES if gp_noise == "white" else ():
            if s in track.cov_by_source:
                by_source.setdefault(s, np.zeros_like(cov))[:, k] = track.cov_by_source[s]
                cov[:, k] += track.cov_by_source[s]
    pose_cov = cov
    if layout.coupling.cross and "calibration" in by_source and gp_noise == "white":
        pose_cov = joint_prism_covariance(q[idx], cov, by_source["calibration"],
                                          list(layout.stations), layout.coupling)
    out_cov = np.full((P, 6, 6), np.nan)
    valid = np.zeros(P, bool)
    if idx.size:
        est = pose_estimate(q[idx], pose_cov, layout.reference, layout.options, engine="linear")
        out_cov[idx] = est.cov
        valid[idx] = ~est.degenerate

    def full(a):
        o = np.full((P,) + a.shape[1:], np.nan)
        o[idx] = a
        return o

    return PosePrediction(R, t, q, out_cov, full(cov), {s: full(c) for s, c in by_source.items()},
                          ranges, valid)


def heading_poses(layout: Layout, xyz: ArrayLike, yaw: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Poses of the rig with its prisms' centroid at ``xyz`` (P, 3) world, m, turned by
    ``yaw`` (P,) rad about the vertical from the body frame's own orientation (the body's z
    taken as vertical)."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    yaw = np.broadcast_to(np.asarray(yaw, dtype=float), xyz.shape[:1])
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros(xyz.shape[:1] + (3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    centroid = layout.reference.xyz.mean(axis=0)
    return R, xyz - R @ centroid
