"""The predicted uncertainty over an area (:func:`plan_area`: a grid of points, each with
:data:`DEFAULT_HEADINGS` headings) or along a path (:func:`plan_path`: the heading the
direction of travel, or the path's own poses), and the paper's advice checked
(:func:`check_advice`: ranges under :data:`RANGE_LIMIT_M`, markers around the area, at least
:data:`MIN_MARKERS` per station). A failed advice is an :class:`~rtsgt.errors.RtsgtWarning`;
results are JSON-ready. docs/planning.md#areas-headings-and-paths,
docs/planning.md#the-papers-advice.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import ConvexHull, QhullError

from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.planning.layout import Layout
from rtsgt.planning.predict import RobotMotion, heading_poses, predict_poses

__all__ = ["DEFAULT_HEADINGS", "MAX_POINTS", "MIN_MARKERS", "RANGE_LIMIT_M", "PlanResult",
           "check_advice", "inside_polygon", "plan_area", "plan_path", "waypoint_path"]

#: Headings of the robot at each point of an area.
DEFAULT_HEADINGS = 8
#: The paper's advice on the range from a station to its prism, m.
RANGE_LIMIT_M = 75.0
#: Fewest markers per station (shared with the reference): redundancy twice the parameters.
MIN_MARKERS = 6
#: Most points of an area's grid (the grid step is refused below it).
MAX_POINTS = 40000
#: Poses predicted in one vectorised batch (bounds the memory to a few hundred MB).
POSE_CHUNK = 16384


def inside_polygon(xy: ArrayLike, polygon: ArrayLike) -> np.ndarray:
    """Whether each point (P, 2) is inside the polygon (V, 2) (even-odd rule, vectorised)."""
    p = np.asarray(xy, dtype=float).reshape(-1, 2)
    v = np.asarray(polygon, dtype=float).reshape(-1, 2)
    a, b = v, np.roll(v, -1, axis=0)
    x, y = p[:, :1], p[:, 1:]
    crosses = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return np.sum(crosses & (x < xc), axis=1) % 2 == 1


def horizontal_hull(xy: np.ndarray) -> np.ndarray | None:
    """The horizontal convex hull of points (K, 2) as a polygon, or None (fewer than 3, or
    collinear)."""
    if xy.shape[0] < 3:
        return None
    try:
        return xy[ConvexHull(xy).vertices]
    except QhullError:
        return None


def check_advice(layout: Layout, points_world: np.ndarray, max_range_m: np.ndarray) -> dict:
    """The paper's advice on ``layout`` for the points the robot will be at (the prisms' centroid
    ``points_world`` (P, 3), world, m, and the largest prism-to-station range ``max_range_m``
    (P,), m): ``ranges``, ``gcp_hull``, ``gcp_markers``, each with its numbers, ``advice`` in
    words and ``verdict`` (``"met"``, ``"not met"``). Warns for each advice not met."""
    ok = np.isfinite(max_range_m)
    beyond = float(np.mean(max_range_m[ok] > RANGE_LIMIT_M)) if ok.any() else float("nan")
    ranges = {"limit_m": RANGE_LIMIT_M, "fraction_beyond": beyond,
              "max_m": float(np.max(max_range_m[ok])) if ok.any() else float("nan"),
              "advice": f"every prism within {RANGE_LIMIT_M:g} m of its station "
                        "(Vaidis et al. 2023)",
              "verdict": "met" if beyond == 0 else "not met"}
    hull = horizontal_hull(layout.gcp_xyz[:, :2])
    outside = 1.0 if hull is None else float(np.mean(~inside_polygon(points_world[:, :2], hull)))
    gcp_hull = {"fraction_outside": outside, "markers": int(layout.gcp_xyz.shape[0]),
                "advice": "the markers' horizontal convex hull encloses where the robot drives",
                "verdict": "met" if outside == 0 else "not met"}
    per = layout.markers_per_station()
    few = {s: k for s, k in per.items() if k < MIN_MARKERS}
    markers = {"minimum": MIN_MARKERS, "per_station": per,
               "advice": f"at least {MIN_MARKERS} markers per station shared with the "
                         "reference (fit redundancy 3K - 6 at least twice its 6 parameters)",
               "verdict": "met" if not few else "not met"}
    if ranges["verdict"] != "met":
        warnings.warn(f"plan: {100 * beyond:.0f} % of the points have a prism more than "
                      f"{RANGE_LIMIT_M:g} m from its station (the paper's advice: under "
                      f"{RANGE_LIMIT_M:g} m)", RtsgtWarning, stacklevel=2)
    if gcp_hull["verdict"] != "met":
        warnings.warn(f"plan: {100 * outside:.0f} % of the points lie outside the markers' "
                      "horizontal convex hull (the calibration extrapolates there)",
                      RtsgtWarning, stacklevel=2)
    if few:
        warnings.warn("plan: station(s) " + ", ".join(f"{s} ({k})" for s, k in few.items())
                      + f" share fewer than {MIN_MARKERS} markers with the reference",
                      RtsgtWarning, stacklevel=2)
    return {"ranges": ranges, "gcp_hull": gcp_hull, "gcp_markers": markers}


@dataclass(frozen=True)
class PlanResult:
    """A plan's prediction over an area or along a path (``kind``): the ``points`` (P, 3; the
    prisms' centroid, plan coordinates, m), ``sigma_m`` and ``rotation_sigma_rad`` (P, H; per
    point and heading, NaN where not predicted), ``max_range_m`` (P,), the area's
    ``headings_deg`` (H,) and grid (``grid_x``, ``grid_y``, ``grid_mask`` (ny, nx), ``polygon``
    (V, 2)) or the path's times ``t`` (P,) (None where not applicable), ``source_sigma_mm`` (per
    source, per prism, the median ``sqrt(tr Sigma)``, mm) and the ``advice``."""

    name: str
    kind: str
    layout: Layout
    motion: RobotMotion
    points: np.ndarray
    sigma_m: np.ndarray
    rotation_sigma_rad: np.ndarray
    max_range_m: np.ndarray
    headings_deg: np.ndarray | None
    t: np.ndarray | None
    grid_x: np.ndarray | None
    grid_y: np.ndarray | None
    grid_mask: np.ndarray | None
    polygon: np.ndarray | None
    source_sigma_mm: dict[str, list[float]]
    advice: dict

    @property
    def sigma_median_m(self) -> np.ndarray:
        """Median over the headings, m, shape (P,) (what the map shows)."""
        return _nan_stat(np.nanmedian, self.sigma_m)

    @property
    def sigma_worst_m(self) -> np.ndarray:
        """Largest over the headings, m, shape (P,)."""
        return _nan_stat(np.nanmax, self.sigma_m)

    def summary(self) -> dict:
        """JSON-ready numbers: the points, the statistic, the sigma's distribution over the
        points (median, 90th percentile, largest), the sources, the advice."""
        med, worst = self.sigma_median_m, self.sigma_worst_m
        rot = _nan_stat(np.nanmedian, self.rotation_sigma_rad)
        ok = np.isfinite(med)

        def dist(x, scale):
            x = x[np.isfinite(x)] * scale
            if not x.size:
                return {"median": None, "p90": None, "max": None}
            return {"median": float(np.median(x)), "p90": float(np.percentile(x, 90)),
                    "max": float(np.max(x))}

        return {
            "kind": self.kind,
            "points": int(self.points.shape[0]), "points_predicted": int(ok.sum()),
            "headings": None if self.headings_deg is None else int(self.headings_deg.size),
            "statistic": ("median over the headings (sigma_mm); largest (sigma_worst_mm)"
                          if self.kind == "area" else "the path's own heading"),
            "sigma_mm": dist(med, 1e3), "sigma_worst_mm": dist(worst, 1e3),
            "rotation_sigma_mrad": dist(rot, 1e3),
            "source_sigma_mm": self.source_sigma_mm, "advice": self.advice,
        }


def _nan_stat(fn, a: np.ndarray) -> np.ndarray:
    out = np.full(a.shape[0], np.nan)
    ok = np.any(np.isfinite(a), axis=1)
    if ok.any():
        out[ok] = fn(a[ok], axis=1)
    return out


def _predict(layout: Layout, motion: RobotMotion, R: np.ndarray, t: np.ndarray,
             vel: np.ndarray, P: int, H: int):
    """Predict the (P H) poses, :data:`POSE_CHUNK` at a time (each chunk one vectorised
    batch; the memory stays bounded); sigmas (P, H), the max range (P,), the per-source
    medians."""
    N = P * H
    sig, rot, max_range = np.full(N, np.nan), np.full(N, np.nan), np.empty(N)
    norms: dict[str, list[np.ndarray]] = {}
    for lo in range(0, N, POSE_CHUNK):  # chunks of poses, not single poses
        sl = slice(lo, min(lo + POSE_CHUNK, N))
        pred = predict_poses(layout, R[sl], t[sl], vel[sl], motion)
        sig[sl] = np.where(pred.valid, pred.sigma_m, np.nan)
        rot[sl] = np.where(pred.valid, pred.rotation_sigma_rad, np.nan)
        max_range[sl] = np.max(pred.ranges_m, axis=1)
        for name, c in pred.prism_cov_by_source.items():
            norms.setdefault(name, []).append(
                np.sqrt(np.trace(c, axis1=-2, axis2=-1))[pred.valid])
    sources = {}
    for name, parts in norms.items():
        v = np.concatenate(parts)
        sources[name] = [float(x) for x in np.median(v, axis=0) * 1e3] if v.size else []
    return (sig.reshape(P, H), rot.reshape(P, H), max_range.reshape(P, H).max(axis=1),
            sources)


def plan_area(layout: Layout, motion: RobotMotion, polygon: ArrayLike, step_m: float,
              z_m: float, *, headings: int = DEFAULT_HEADINGS, forward_deg: float = 0.0,
              name: str | None = None) -> PlanResult:
    """Predicted uncertainty over the area inside ``polygon`` (V, 2; plan coordinates, m), on a
    grid of ``step_m`` at the centroid height ``z_m``, each point with ``headings`` headings
    over the turn (``forward_deg``: the robot's forward axis from the body's x,
    counter-clockwise)."""
    poly = np.asarray(polygon, dtype=float).reshape(-1, 2)
    if poly.shape[0] < 3 or not np.all(np.isfinite(poly)):
        raise InputError("an area needs a polygon of at least 3 finite corners")
    if not (step_m > 0 and np.isfinite(step_m)):
        raise InputError(f"Expected a grid step > 0 m, got {step_m!r}")
    if int(headings) != headings or headings < 1:
        raise InputError(f"Expected headings >= 1, got {headings!r}")
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    n = np.floor((hi - lo) / step_m + 1e-9).astype(int) + 1
    if n[0] * n[1] > MAX_POINTS:
        raise InputError(f"a grid step of {step_m:g} m gives {n[0] * n[1]} points over the "
                         f"area ({hi[0] - lo[0]:.0f} m x {hi[1] - lo[1]:.0f} m), more than "
                         f"{MAX_POINTS}; take a larger step")
    gx = lo[0] + step_m * np.arange(n[0]) + 0.5 * (hi[0] - lo[0] - step_m * (n[0] - 1))
    gy = lo[1] + step_m * np.arange(n[1]) + 0.5 * (hi[1] - lo[1] - step_m * (n[1] - 1))
    X, Y = np.meshgrid(gx, gy)
    mask = inside_polygon(np.column_stack([X.ravel(), Y.ravel()]), poly).reshape(X.shape)
    if not mask.any():
        raise InputError("no grid point inside the area; take a smaller step")
    pts = np.column_stack([X[mask], Y[mask], np.full(int(mask.sum()), float(z_m))])
    P, H = pts.shape[0], int(headings)
    travel = 2.0 * np.pi * np.arange(H) / H
    world = pts - layout.origin
    xyz = np.repeat(world, H, axis=0)
    trav = np.tile(travel, P)
    R, t = heading_poses(layout, xyz, trav - np.radians(forward_deg))
    vel = motion.speed_m_s * np.column_stack([np.cos(trav), np.sin(trav), np.zeros(P * H)])
    sig, rot, max_range, sources = _predict(layout, motion, R, t, vel, P, H)
    advice = check_advice(layout, world, max_range)
    return PlanResult(name or layout.name, "area", layout, motion, pts, sig, rot, max_range,
                      np.degrees(travel), None, gx, gy, mask, poly, sources, advice)


def waypoint_path(waypoints: ArrayLike, step_m: float) -> np.ndarray:
    """Points every ``step_m`` along the polyline through ``waypoints`` (W, 2 or 3), m (the
    last waypoint included)."""
    w = np.asarray(waypoints, dtype=float)
    if w.ndim != 2 or w.shape[0] < 2 or w.shape[1] not in (2, 3):
        raise InputError("a path needs at least 2 waypoints (x, y) or (x, y, z)")
    if not (step_m > 0):
        raise InputError(f"Expected a path step > 0 m, got {step_m!r}")
    seg = np.linalg.norm(np.diff(w, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    q = np.append(np.arange(0.0, s[-1], step_m), s[-1])
    return np.column_stack([np.interp(q, s, w[:, j]) for j in range(w.shape[1])])


def _tangent(xyz: np.ndarray) -> np.ndarray:
    """Unit tangents (P, 3) by central differences (one-sided at the ends); 0 where the path
    does not move."""
    if xyz.shape[0] < 2:
        return np.zeros_like(xyz)
    d = np.gradient(xyz, axis=0)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return np.where(n > 0, d / np.where(n > 0, n, 1.0), 0.0)


def plan_path(layout: Layout, motion: RobotMotion, xyz: ArrayLike, *,
              t: ArrayLike | None = None, R: ArrayLike | None = None, forward_deg: float = 0.0,
              name: str | None = None) -> PlanResult:
    """Predicted uncertainty along a path: the prisms' centroid ``xyz`` (P, 3; plan coordinates,
    m), or with ``R`` (P, 3, 3) the body frame's poses; times ``t`` (P,), s, give the path's
    own velocity; ``forward_deg`` as :func:`plan_area` (without ``R``)."""
    p = np.asarray(xyz, dtype=float).reshape(-1, 3)
    if p.shape[0] < 1 or not np.all(np.isfinite(p)):
        raise InputError("a path needs finite points")
    world = p - layout.origin
    if R is not None:
        Rm = np.asarray(R, dtype=float).reshape(-1, 3, 3)
        tb = world
        centroid = Rm @ layout.reference.xyz.mean(axis=0) + tb
    else:
        centroid = world
    tan = _tangent(centroid)
    if t is not None:
        tt = np.asarray(t, dtype=float).reshape(-1)
        if tt.shape[0] != p.shape[0] or np.any(np.diff(tt) <= 0):
            raise InputError("a path's times must be one per point and increasing")
        vel = np.gradient(centroid, tt, axis=0) if p.shape[0] > 1 else np.zeros_like(p)
    else:
        tt = None
        vel = motion.speed_m_s * tan
    if R is None:
        travel = np.arctan2(tan[:, 1], tan[:, 0])
        Rm, tb = heading_poses(layout, centroid, travel - np.radians(forward_deg))
    sig, rot, max_range, sources = _predict(layout, motion, Rm, tb, vel, p.shape[0], 1)
    advice = check_advice(layout, centroid, max_range)
    return PlanResult(name or layout.name, "path", layout, motion, centroid + layout.origin,
                      sig, rot, max_range, None, tt, None, None, None, None, sources, advice)
