r"""The pose uncertainty a run would report, predicted from a layout before any measurement.

For a pose of the robot ``T_world_body = (R, t)`` moving at velocity ``v`` (world, m/s),
:func:`predict_poses` goes through the stages of a run (:mod:`rtsgt.pipeline`) with the linear
engines and no data:

1. **Prisms**: ``q_i = R r_i + t`` for the rig's prisms ``r_i`` (body frame).
2. **Measurements**: each prism's covariance as its station measures it, by the noise model's
   first-order engine (:func:`rtsgt.noise.propagate`, ``engine="linear"``, the run's own code)
   on three synthetic measurements ``q_i - v h``, ``q_i``, ``q_i + v h`` at ``-h, 0, h``
   (``h = 1 / rate`` of the station) without weather (the instrument's reference atmosphere;
   the atmosphere source still counts the weather's uncertainty). The middle measurement's
   central difference is ``v`` exactly, so the time-synchronisation source is
   ``(mu^2 + sigma^2) v v^T`` plus its interaction with the measurement noise, as in a run;
   the calibration source is the one of the layout's calibration (:mod:`rtsgt.planning.layout`).
3. **GP**: the white sources (instrument, tilt; what a run gives the GP) become the GP's
   posterior on a stationary uniform track at the station's rate with the robot's ``Qc``,
   averaged over the query's position between two measurements
   (:func:`rtsgt.planning.gp_factor.gp_posterior_covariance`); the systematic sources
   (atmosphere, time synchronisation, calibration) are added at their value at the pose, as
   a run adds them (``gp_noise = "all"``: the GP takes every source, nothing is added, as in
   a run with that option).
4. **Joint covariance**: the calibration errors the stations share through the reference's
   shots (:func:`rtsgt.noise.coupling.joint_prism_covariance`, the run's own).
5. **Pose**: :func:`rtsgt.pose.estimate_poses` with the linear engine and the run's
   registration (weighted by default) against the rig's survey and its covariance.

The pose sigma is ``sqrt(tr Sigma_t)`` of the 3x3 position block (m), the quantity of
``rtsgt run``'s summary ("median sigma translation (sqrt trace)"); the rotation sigma is the
same of the rotation block (rad).

``Qc`` (:class:`RobotMotion`): the GP's prior depends on how rough the robot's motion is,
which only measurements tell. A run's leave-one-out ``Qc``
(:mod:`rtsgt.interpolation.loo`) per world axis and its scale per motion class
(:mod:`rtsgt.interpolation.motion`) give it for the same robot (:func:`qc_from_run`); without
one the plan takes :data:`DEFAULT_QC_M2_S3` and says so. The horizontal axes share one value
(the mean of a run's x and y: the plan's horizontal axes are not the run's).

What it neglects (docs/planning.md#what-the-prediction-neglects): line-of-sight losses and the
gaps they leave (the GP's variance grows in a gap), the ends of a track, a ``Qc`` that follows
the motion within a class, the gates of module 4, the weather's own correction (0 ppm), the
variance components of a calibration from noise-free shots (:mod:`rtsgt.planning.layout`).
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
from rtsgt.pose import estimate_poses
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
    """What a plan assumes of the robot's motion.

    Attributes
    ----------
    speed_m_s : float
        Speed where the plan gives no times, m/s.
    qc_m2_s3 : ndarray, shape (3, 3)
        The GP's ``Qc`` while the robot moves (world axes, horizontal ones equal).
    qc_standing_m2_s3 : ndarray, shape (3, 3), or None
        While it stands (speed below
        :data:`rtsgt.interpolation.motion.STANDING_SPEED_M_S`); None: the same as moving.
    qc_source : str
        Where ``Qc`` comes from, in words.
    """

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
    """The robot's ``Qc`` as a run found it: ``summary.json``'s ``prisms`` (per prism its
    ``qc_m2_s3`` and ``qc_fit``).

    Per prism, ``Qc`` while moving is the run's ``Qc`` times the mean scale of the moving
    classes weighted by their intervals (the GP's variance between measurements is about
    proportional to ``Qc``), and while standing times the standing class's scale (the run's
    ``Qc`` where it kept one constant); the prisms are averaged, and the horizontal value is
    the mean of x and y.

    Parameters
    ----------
    prisms : mapping str -> mapping
        ``{"qc_m2_s3": 3x3, "qc_fit": {"motion_prior": {"chosen", "scales", "intervals"}}}``
        per prism.
    speed_m_s : float
    source : str
    """
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
    """Predicted uncertainty of poses (:func:`predict_poses`).

    Attributes
    ----------
    R, t : ndarray, shape (P, 3, 3), (P, 3)
        The poses ``T_world_body`` predicted for.
    prisms_xyz : ndarray, shape (P, n, 3)
        The prisms, world frame, m.
    cov : ndarray, shape (P, 6, 6)
        Pose covariance (left perturbation, x, y, z, rx, ry, rz), m^2 / rad^2; NaN where not
        predicted.
    prism_cov : ndarray, shape (P, n, 3, 3)
        Each prism's total covariance after the GP, m^2.
    prism_cov_by_source : dict str -> ndarray (P, n, 3, 3)
        ``"gp"`` (the GP's posterior of what it is given) and each systematic source added.
    ranges_m : ndarray, shape (P, n)
        Distance from each prism to its station, m.
    valid : ndarray of bool, shape (P,)
        Predicted (no prism nearer than :data:`MIN_RANGE_M` to its station, a
        non-degenerate pose).
    """

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
    """The linear engine's covariances of station ``k``'s measurements of its prism at the
    world points ``q`` (P, 3) moving at ``v`` (P, 3): the middle one of three synthetic
    measurements per point (module docstring, step 2)."""
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
    """Predicted covariance of the poses ``(R, t)`` of a robot moving at ``velocity``
    (module docstring).

    Parameters
    ----------
    layout : Layout
    R : array_like, shape (P, 3, 3)
        ``R_world_body``.
    t : array_like, shape (P, 3)
        ``t_world_body``, world frame (the reference station's), m.
    velocity : array_like, shape (P, 3)
        World velocity of the robot, m/s (the prisms share it).
    motion : RobotMotion
        The GP's ``Qc`` (moving or standing, by the speed).

    Returns
    -------
    PosePrediction
    """
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
        est = estimate_poses(q[idx], pose_cov, layout.reference, engine="linear",
                             registration=layout.options.pose.registration)
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
