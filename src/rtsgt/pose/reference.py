"""The reference prisms on the robot, with covariance, in the body frame the user chooses.

From the static survey of the robot: the survey's frame, a frame given by a transform
``T_survey_body``, or one defined by three or more surveyed points (:func:`frame_from_points`);
the covariance propagated to first order through the frame (docs/pose.md#body-frame).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import GeometryError
from rtsgt.geometry.so3 import exp_so3
from rtsgt.geometry.transform import RigidTransform, check_covariance
from rtsgt.pose.registration import MIN_SHAPE, shape_ratio

#: Finite-difference step of the covariance propagation (m for points, rad for rotations).
_FD_STEP = 1e-6


def triangle_geometry(xyz: ArrayLike) -> tuple[float, float]:
    """Area (m^2) and smallest angle (deg) of the largest triangle of ``xyz`` (n, 3), n >= 3."""
    x = np.asarray(xyz, dtype=float)
    best_area, best_angle = -1.0, 0.0
    for i, j, k in combinations(range(x.shape[0]), 3):
        a, b, c = x[i], x[j], x[k]
        area = 0.5 * float(np.linalg.norm(np.cross(b - a, c - a)))
        if area > best_area:
            angles = []
            for u, v, w in ((a, b, c), (b, c, a), (c, a, b)):
                e1, e2 = v - u, w - u
                den = np.linalg.norm(e1) * np.linalg.norm(e2)
                cosang = np.dot(e1, e2) / den if den > 0 else 1.0
                angles.append(np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0))))
            best_area, best_angle = area, float(min(angles))
    return best_area, best_angle


def check_reference_geometry(xyz: ArrayLike, min_shape: float = MIN_SHAPE) -> None:
    """Raise :class:`GeometryError` for fewer than 3 reference points ``xyz`` (n, 3) m, or a set
    whose :func:`~rtsgt.pose.registration.shape_ratio` is below ``min_shape`` (naming its largest
    triangle's area and smallest angle)."""
    x = np.asarray(xyz, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"Expected reference points of shape (n, 3), got {x.shape}")
    if x.shape[0] < 3:
        raise GeometryError(
            f"A pose needs at least 3 reference prisms, got {x.shape[0]}"
        )
    ratio = float(shape_ratio(x))
    if not ratio >= min_shape:
        area, angle = triangle_geometry(x)
        raise GeometryError(
            "The reference prisms are nearly collinear: largest triangle area "
            f"{area:.4g} m^2, smallest angle {angle:.3g} deg, shape ratio {ratio:.3g} < "
            f"{min_shape} (the rotation about their line would not be determined)"
        )


@dataclass(frozen=True)
class ReferencePoints:
    """Reference prisms in the body frame with their joint covariance: ``names`` (n,), ``xyz``
    (n, 3) m, ``cov`` (3n, 3n) m^2 of the stacked ``(x1, y1, z1, x2, ...)`` (or (n, 3, 3) per
    point), ``frame`` the body frame's name; ``pivot`` (3,) m the point the vehicle rocks
    about, its suspension's roll centre, in the body frame (None: not given; the joint
    engine's rocking, docs/joint.md#the-rockings-pivot); ``stability`` m how far (1 sigma per
    axis) a prism may have moved since the survey where no station sees it (0: the survey
    trusted; the joint engine carries it, docs/joint.md#what-no-station-sees). Raises
    GeometryError for fewer than 3 points or nearly collinear ones."""

    names: tuple[str, ...]
    xyz: np.ndarray
    cov: np.ndarray
    frame: str = "body"
    pivot: np.ndarray | None = None
    stability: float = 0.0

    def __post_init__(self) -> None:
        names = tuple(str(s) for s in self.names)
        xyz = np.array(self.xyz, dtype=float)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"Expected xyz of shape (n, 3), got {xyz.shape}")
        n = xyz.shape[0]
        if len(names) != n:
            raise ValueError(f"Expected {n} names, got {len(names)}")
        if len(set(names)) != n:
            raise ValueError(f"Expected distinct names, got {names}")
        if not np.all(np.isfinite(xyz)):
            raise ValueError("Expected finite reference positions")
        cov = np.array(self.cov, dtype=float)
        if cov.shape == (n, 3, 3):
            cov = block_diagonal(cov)
        cov = np.array(check_covariance(cov, 3 * n, "reference covariance"), dtype=float)
        cov = 0.5 * (cov + cov.T)
        check_reference_geometry(xyz)
        if not (np.isfinite(self.stability) and self.stability >= 0.0):
            raise ValueError(f"Expected a finite stability >= 0 m, got {self.stability!r}")
        object.__setattr__(self, "stability", float(self.stability))
        if self.pivot is not None:
            pivot = np.array(self.pivot, dtype=float)
            if pivot.shape != (3,) or not np.all(np.isfinite(pivot)):
                raise ValueError(f"Expected a finite pivot of shape (3,), got {self.pivot!r}")
            pivot.setflags(write=False)
            object.__setattr__(self, "pivot", pivot)
        xyz.setflags(write=False)
        cov.setflags(write=False)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "cov", cov)

    def __len__(self) -> int:
        return self.xyz.shape[0]

    @property
    def pairs(self) -> tuple[tuple[int, int], ...]:
        """Index pairs ``(i, j), i < j`` in the order of :meth:`distances`."""
        n = len(self)
        return tuple((i, j) for i in range(n) for j in range(i + 1, n))

    def distances(self) -> np.ndarray:
        """Inter-prism distances ``|r_i - r_j|`` for :attr:`pairs` (d12, d13, d23 for 3), m."""
        return np.array([np.linalg.norm(self.xyz[i] - self.xyz[j]) for i, j in self.pairs])

    def cov_blocks(self) -> np.ndarray:
        """The per-point 3x3 covariances (diagonal blocks), shape (n, 3, 3)."""
        n = len(self)
        return np.stack([self.cov[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(n)])

    def select(self, names: Sequence[str]) -> ReferencePoints:
        """The points named ``names``, in that order (with their joint covariance)."""
        idx = []
        for s in names:
            if str(s) not in self.names:
                raise ValueError(f"Expected a prism among {self.names}, got {s!r}")
            idx.append(self.names.index(str(s)))
        rows = np.concatenate([[3 * k, 3 * k + 1, 3 * k + 2] for k in idx])
        return ReferencePoints(tuple(str(s) for s in names), self.xyz[idx],
                               self.cov[np.ix_(rows, rows)], self.frame, self.pivot,
                               self.stability)


def block_diagonal(blocks: np.ndarray) -> np.ndarray:
    """(..., n, 3, 3) per-point blocks -> (..., 3n, 3n) block-diagonal joint matrices."""
    n = blocks.shape[-3]
    out = np.zeros(blocks.shape[:-3] + (3 * n, 3 * n))
    for i in range(n):
        out[..., 3 * i:3 * i + 3, 3 * i:3 * i + 3] = blocks[..., i, :, :]
    return out


def frame_from_points(points: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """``R_survey_body`` (..., 3, 3) (columns: the body axes) and ``t_survey_body`` (..., 3) of
    the frame of three or more surveyed points ``points`` (..., k, 3): origin at their centroid, x
    from the first towards the second, z along ``(s2 - s1) x (s3 - s1)``, y completing it. Raises
    GeometryError for fewer than 3 points or the first three (nearly) collinear."""
    s = np.asarray(points, dtype=float)
    if s.ndim < 2 or s.shape[-1] != 3:
        raise ValueError(f"Expected points of shape (..., k, 3), got {s.shape}")
    if s.shape[-2] < 3:
        raise GeometryError(f"A frame from points needs at least 3 points, got {s.shape[-2]}")
    e1 = s[..., 1, :] - s[..., 0, :]
    e2 = s[..., 2, :] - s[..., 0, :]
    nz = np.cross(e1, e2)
    l1 = np.linalg.norm(e1, axis=-1)
    lz = np.linalg.norm(nz, axis=-1)
    l2 = np.linalg.norm(e2, axis=-1)
    # |e1 x e2| / (|e1| |e2|) = sin of the angle at the first point
    if np.any(~(lz > 1e-3 * l1 * l2)):
        raise GeometryError("The frame's first three points are (nearly) collinear")
    x = e1 / l1[..., None]
    z = nz / lz[..., None]
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=-1)
    return R, s.mean(axis=-2)


def _body_points(X, xi, prism_rows, body_frame, R0, t0):
    """Map survey points X (B, K, 3) (and transform perturbations xi (B, 6)) to the body."""
    P = X[:, prism_rows]
    if isinstance(body_frame, str):
        return P
    if isinstance(body_frame, RigidTransform):
        R = exp_so3(xi[:, 3:]) @ R0
        t = t0 + xi[:, :3]
    else:
        R, t = frame_from_points(X[:, list(body_frame)])
    return np.einsum("bji,bnj->bni", R, P - t[:, None, :])


def reference_from_survey(
    points_survey: ArrayLike,
    cov_survey: ArrayLike,
    prism_rows: Sequence[int],
    *,
    body_frame: str | RigidTransform | Sequence[int] = "survey",
    names: Sequence[str] | None = None,
    pivot: ArrayLike | None = None,
) -> ReferencePoints:
    """Reference prisms in the chosen body frame, with covariance, from a static survey.

    ``points_survey`` (K, 3) m and ``cov_survey`` (K, 3, 3) or (3K, 3K) m^2, survey frame;
    ``prism_rows``: the **0-based** rows of the prisms, in prism order; ``body_frame``:
    ``"survey"``, a ``RigidTransform`` ``T_survey_body`` (its covariance propagated), or 0-based
    rows of sensor points (:func:`frame_from_points`); ``names`` default ``"1", "2", ...``;
    ``pivot`` (3,) m the vehicle's rocking pivot in the survey frame (None: not given), put
    in the body frame as the prisms are (its uncertainty not carried). Raises
    GeometryError (fewer than 3 prisms, a collinear set or frame) or ValueError (shapes, rows, a
    non-PSD covariance).
    """
    X = np.asarray(points_survey, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"Expected points_survey of shape (K, 3), got {X.shape}")
    K = X.shape[0]
    C = np.asarray(cov_survey, dtype=float)
    if C.shape == (K, 3, 3):
        C = block_diagonal(C)
    if C.shape != (3 * K, 3 * K):
        raise ValueError(
            f"Expected cov_survey of shape ({K}, 3, 3) or ({3 * K}, {3 * K}), got {C.shape}"
        )
    C = check_covariance(C, 3 * K, "cov_survey")
    rows = [int(i) for i in prism_rows]
    if len(rows) < 3:
        raise GeometryError(f"A pose needs at least 3 reference prisms, got {len(rows)}")
    for i in rows:
        if not 0 <= i < K:
            raise ValueError(f"Expected 0-based prism rows in [0, {K}), got {i}")
    if len(set(rows)) != len(rows):
        raise ValueError(f"Expected distinct prism rows, got {rows}")
    check_reference_geometry(X[rows])
    names = tuple(str(i + 1) for i in range(len(rows))) if names is None else tuple(names)
    if len(names) != len(rows):
        raise ValueError(f"Expected {len(rows)} names, got {len(names)}")
    body_frame, R0, t0, C_T, frame = _frame_spec(body_frame, X)
    xyz = _body_points(X[None], np.zeros((1, 6)), rows, body_frame, R0, t0)[0]
    cov = _propagated_cov(X, C, rows, body_frame, R0, t0, C_T)
    if pivot is not None:  # one more point, after the survey's rows (the frame's stay theirs)
        Xp = np.concatenate([X, np.asarray(pivot, dtype=float).reshape(1, 3)])
        pivot = _body_points(Xp[None], np.zeros((1, 6)), [K], body_frame, R0, t0)[0, 0]
    return ReferencePoints(names, xyz, 0.5 * (cov + cov.T), frame, pivot)


def _frame_spec(body_frame, X: np.ndarray):
    """``body_frame`` checked against the survey ``X`` (K, 3): ``(spec, R0, t0, C_T, name)``,
    ``spec`` for :func:`_body_points`, ``R0``, ``t0``, ``C_T`` a transform's (else None)."""
    K = X.shape[0]
    if isinstance(body_frame, RigidTransform):
        return (body_frame, body_frame.rotation, body_frame.translation, body_frame.covariance,
                body_frame.frame_from)
    if isinstance(body_frame, str):
        if body_frame != "survey":
            raise ValueError(
                "Expected body_frame 'survey', a RigidTransform T_survey_body or a sequence of "
                f"survey rows, got {body_frame!r}"
            )
        return body_frame, None, None, None, "survey"
    srows = [int(i) for i in body_frame]
    for i in srows:
        if not 0 <= i < K:
            raise ValueError(f"Expected 0-based sensor rows in [0, {K}), got {i}")
    frame_from_points(X[srows])  # raises GeometryError for a degenerate frame
    return srows, None, None, None, "points(" + ",".join(str(i) for i in srows) + ")"


def _propagated_cov(X, C, rows, body_frame, R0, t0, C_T) -> np.ndarray:
    """The reference's covariance (3n, 3n): the survey's ``C`` (3K, 3K) and the transform's
    ``C_T`` (6, 6, or None) through central differences of :func:`_body_points`."""
    K = X.shape[0]
    n = len(rows)
    E = np.eye(3 * K).reshape(3 * K, K, 3) * _FD_STEP
    Xs = np.concatenate([X + E, X - E])
    fx = _body_points(Xs, np.zeros((6 * K, 6)), rows, body_frame, R0, t0)
    J_X = ((fx[:3 * K] - fx[3 * K:]) / (2 * _FD_STEP)).reshape(3 * K, 3 * n).T
    cov = J_X @ C @ J_X.T
    if C_T is not None:
        D = np.eye(6) * _FD_STEP
        xis = np.concatenate([D, -D])
        fxi = _body_points(np.broadcast_to(X, (12, K, 3)), xis, rows, body_frame, R0, t0)
        J_T = ((fxi[:6] - fxi[6:]) / (2 * _FD_STEP)).reshape(6, 3 * n).T
        cov = cov + J_T @ C_T @ J_T.T
    return cov
