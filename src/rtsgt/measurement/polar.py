"""Polar (total-station) to Cartesian coordinates, their Jacobians and sight frames.

The station-frame convention (``hz`` clockwise from +y, ``v`` the zenith angle, ``d`` with the
additive constant; survey variants) is docs/conventions.md#station-polar-convention.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

#: Rotation taking tracking-frame coordinates to survey (manual-shot) coordinates,
#: ``p_survey = R_SURVEY_TRACKING @ p_tracking``: -90 deg about z.
R_SURVEY_TRACKING = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
R_SURVEY_TRACKING.setflags(write=False)
#: The rows of :func:`sight_frames`: along the line of sight and across it.
SIGHT_COMPONENTS = ("range", "horizontal", "vertical")


def polar_to_cartesian(hz: ArrayLike, v: ArrayLike, d: ArrayLike) -> np.ndarray:
    """Station-frame ``(x, y, z)`` (..., 3), m, of polar measurements: clockwise horizontal
    direction ``hz`` and zenith angle ``v``, rad, slope distance ``d``, m (additive constant
    applied), broadcastable (docs/conventions.md#station-polar-convention)."""
    hz = np.asarray(hz, dtype=float)
    v = np.asarray(v, dtype=float)
    d = np.asarray(d, dtype=float)
    sv = np.sin(v)
    return np.stack(np.broadcast_arrays(d * sv * np.sin(hz), d * sv * np.cos(hz), d * np.cos(v)), axis=-1)


def cartesian_to_polar(p: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`polar_to_cartesian`: ``(hz in [0, 2pi), v in [0, pi], d)``."""
    p = np.asarray(p, dtype=float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    d = np.sqrt(x * x + y * y + z * z)
    hz = np.mod(np.arctan2(x, y), 2 * np.pi)
    v = np.arccos(np.clip(z / np.where(d > 0, d, 1.0), -1.0, 1.0))
    return hz, v, d


def polar_jacobian(hz: ArrayLike, v: ArrayLike, d: ArrayLike) -> np.ndarray:
    """Jacobian (..., 3, 3) of :func:`polar_to_cartesian`: ``J[..., i, j] = d p_i / d (hz, v,
    d)_j``."""
    hz, v, d = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (hz, v, d)))
    sh, ch, sv, cv = np.sin(hz), np.cos(hz), np.sin(v), np.cos(v)
    J = np.empty(hz.shape + (3, 3))
    J[..., 0, 0] = d * sv * ch
    J[..., 0, 1] = d * cv * sh
    J[..., 0, 2] = sv * sh
    J[..., 1, 0] = -d * sv * sh
    J[..., 1, 1] = d * cv * ch
    J[..., 1, 2] = sv * ch
    J[..., 2, 0] = 0.0
    J[..., 2, 1] = -d * sv
    J[..., 2, 2] = cv
    return J


def survey_polar_to_cartesian(hz: ArrayLike, v: ArrayLike, d: ArrayLike) -> np.ndarray:
    """Survey-frame ``(x, y, z)`` (..., 3), m, of manual shots: ``x = d cos(hz) sin(v)``,
    ``y = -d sin(hz) sin(v)``, ``z = d cos(v)`` (docs/conventions.md#station-polar-convention)."""
    return polar_to_cartesian(hz, v, d) @ R_SURVEY_TRACKING.T


def cartesian_to_survey_polar(p: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`survey_polar_to_cartesian`: ``(hz in [0, 2pi), v in [0, pi], d)`` of
    survey-frame points ``p`` (..., 3), m."""
    return cartesian_to_polar(np.asarray(p, dtype=float) @ R_SURVEY_TRACKING)


def survey_polar_jacobian(hz: ArrayLike, v: ArrayLike, d: ArrayLike) -> np.ndarray:
    """Jacobian (..., 3, 3) of :func:`survey_polar_to_cartesian` in ``(hz, v, d)``."""
    return R_SURVEY_TRACKING @ polar_jacobian(hz, v, d)


def sight_frames(xyz: ArrayLike, station: ArrayLike) -> np.ndarray:
    """Each measurement's own frame (N, 3, 3), rows named by :data:`SIGHT_COMPONENTS`: the line
    of sight ``u`` from ``station`` (3,) to each point of ``xyz`` (N, 3), m, the horizontal
    ``h = z x u`` (normalised) and the vertical ``u x h`` across it (the directions of a
    horizontal- and a zenith-angle error of a levelled station)."""
    u = np.asarray(xyz, dtype=float) - np.asarray(station, dtype=float)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    h = np.cross([0.0, 0.0, 1.0], u)
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    return np.stack([u, h, np.cross(u, h)], axis=1)
