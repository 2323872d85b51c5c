"""The GCP shots a calibration fits: validation, pairing with the reference, covariance.

Owns what the GCP fit (:mod:`rtsgt.calibration.gcp`) and the joint fit
(:mod:`rtsgt.calibration.dynamic`) share: the valid shots and each station's markers shared
with the reference (:func:`setup_shots`), the shots' first-order covariance, the Earth's
curvature between levelled stations, and the inter-station residuals (docs/noise-model.md,
section Extrinsic calibration).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from rtsgt.calibration.result import MarkerResiduals
from rtsgt.choices import CALIBRATION_MODELS, CALIBRATION_WEIGHTINGS
from rtsgt.errors import GeometryError, InputError, RtsgtWarning
from rtsgt.measurement.instruments import InstrumentProfile
from rtsgt.measurement.polar import polar_jacobian, polar_to_cartesian
from rtsgt.types import GcpShots

__all__ = ["COLLINEARITY_FACTOR", "EARTH_RADIUS_M", "ShotSetup", "check_args", "curvature_tilt",
           "marker_residuals", "natural_key", "polar_point_covariance", "setup_shots",
           "with_extra_variance"]

#: Mean radius of the Earth (IUGG), m: the verticals of two levelled instruments ``d`` metres
#: apart differ by ``d / EARTH_RADIUS_M`` rad (16 microradians per 100 m).
EARTH_RADIUS_M = 6_371_000.0

#: A station's markers must stand off their best-fit line by more than this many times the
#: point noise (1 sigma), or the rotation about that line is undetermined.
COLLINEARITY_FACTOR = 3.0


def polar_point_covariance(
    hz: np.ndarray, v: np.ndarray, d: np.ndarray, instrument: InstrumentProfile
) -> np.ndarray:
    """``J S J^T`` (N, 3, 3), m^2, station frame: the first-order covariance of the points of
    polar shots ``hz``, ``v`` (rad), ``d`` (m, constant applied), (N,), under the
    ``instrument``'s angle, tilt and distance noise (docs/noise-model.md#weights-of-the-gcps)."""
    sa2 = instrument.sigma_angle**2
    st2 = instrument.sigma_tilt**2
    cot = 1.0 / np.tan(v)
    S = np.zeros(np.shape(hz) + (3, 3))
    S[..., 0, 0] = sa2 + st2 * cot**2  # Hz: e_Hz + e_tilt cot V
    S[..., 0, 1] = S[..., 1, 0] = st2 * cot
    S[..., 1, 1] = sa2 + st2  # V: e_V + e_tilt
    S[..., 2, 2] = instrument.sigma_distance(d) ** 2
    J = polar_jacobian(hz, v, d)
    return J @ S @ np.swapaxes(J, -1, -2)


def natural_key(s: str) -> tuple:
    return (0, int(s), s) if s.isdigit() else (1, 0, s)


@dataclass(frozen=True)
class ShotSetup:
    """Valid shots, the station list and, for each station, the indices of its fit pairs."""

    stations: list[str]
    hz: np.ndarray
    v: np.ndarray
    d: np.ndarray  # additive constant applied
    points: np.ndarray  # (N, 3) nominal station-frame points of the valid shots
    shot: dict[tuple[str, str], int]  # (station, marker) -> index into the valid shots
    pairs: dict[str, tuple[np.ndarray, np.ndarray, tuple[str, ...]]]  # idx_s, idx_ref, markers
    used_markers: set[str]
    skipped: tuple[str, ...]
    excluded: int


def _where(shots: GcpShots, k: int) -> str:
    return f"line {int(shots.lines[k])}" if shots.lines is not None else f"shot {k}"


def setup_shots(shots: GcpShots, reference_station: str, instrument: InstrumentProfile) -> ShotSetup:
    if not isinstance(shots, GcpShots):
        raise TypeError(f"Expected GcpShots, got {type(shots).__name__}")
    ref = str(reference_station)
    known = sorted({str(s) for s in shots.station}, key=natural_key)
    if ref not in known:
        raise InputError(
            f"unknown reference station {ref!r}; "
            f"stations in the file: {', '.join(known) or 'none'}",
            shots.source,
        )
    if len(known) < 2:
        raise InputError(
            f"only one station ({known[0]}) in the GCP shots: calibration needs at least two",
            shots.source,
        )
    valid = np.flatnonzero(shots.status == 0)
    excluded = len(shots) - valid.size
    shot: dict[tuple[str, str], int] = {}
    for j, k in enumerate(valid):
        key = (shots.station[k], shots.marker[k])
        if key in shot:
            first = valid[shot[key]]
            raise InputError(
                f"station {key[0]} shot marker {key[1]} twice with status 0 "
                f"({_where(shots, first)} and {_where(shots, k)}): keep one shot per station "
                "and marker (delete one, or average them into one line)",
                shots.source, None if shots.lines is None else int(shots.lines[k]),
            )
        shot[key] = j
    stations_of: dict[str, set[str]] = {}
    for s, m in shot:
        stations_of.setdefault(m, set()).add(s)
    skipped = tuple(
        sorted((m for m, ss in stations_of.items() if len(ss) < 2), key=natural_key)
    )
    if skipped:
        warnings.warn(
            f"{shots.source or 'GCP shots'}: marker(s) {', '.join(skipped)} shot validly by "
            "fewer than 2 stations are not used",
            RtsgtWarning, stacklevel=3,
        )
    hz = np.asarray(shots.hz[valid])
    v = np.asarray(shots.v[valid])
    d = np.asarray(shots.distance[valid])
    bad = np.flatnonzero(~(np.isfinite(hz) & (v > 0) & (v < np.pi) & (d > 0)))
    if bad.size:
        k = valid[bad[0]]
        raise InputError(
            f"invalid valid-status shot of marker {shots.marker[k]} by station "
            f"{shots.station[k]} ({_where(shots, k)}): expected finite Hz, zenith in (0, pi) "
            f"and a positive distance, got hz={float(shots.hz[k])!r}, v={float(shots.v[k])!r}, "
            f"d={float(shots.distance[k])!r}",
            shots.source, None if shots.lines is None else int(shots.lines[k]),
        )
    points = polar_to_cartesian(hz, v, d)
    origin = f"{shots.source}: " if shots.source else ""  # geometry errors name the file
    pairs = {}
    used: set[str] = set()
    for s in known:
        if s == ref:
            continue
        markers = tuple(
            sorted((m for (st, m) in shot if st == s and (ref, m) in shot), key=natural_key)
        )
        if len(markers) < 3:
            raise GeometryError(
                f"{origin}station {s} shares {len(markers)} valid marker(s) with reference "
                f"station {ref}{' (' + ', '.join(markers) + ')' if markers else ''}: a rigid "
                "fit needs at least 3 markers, not collinear"
            )
        idx_s = np.array([shot[(s, m)] for m in markers])
        idx_r = np.array([shot[(ref, m)] for m in markers])
        _check_spread(points[idx_s], hz[idx_s], v[idx_s], d[idx_s], instrument, s, markers,
                      origin)
        pairs[s] = (idx_s, idx_r, markers)
        used.update(markers)
    return ShotSetup(known, hz, v, d, points, shot, pairs, used, skipped, excluded)


def _check_spread(p, hz, v, d, instrument, station, markers, origin: str = "") -> None:
    """Refuse markers whose spread off their best-fit line is within the point noise."""
    c = p - p.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    off_line_rms = float(np.sqrt((s[1] ** 2 + s[2] ** 2) / p.shape[0]))
    cov = polar_point_covariance(hz, v, d, instrument)
    sigma = float(np.sqrt(np.trace(cov, axis1=-2, axis2=-1).mean() / 3.0))
    if off_line_rms <= COLLINEARITY_FACTOR * sigma or s[1] <= 1e-9 * max(s[0], 1e-300):
        raise GeometryError(
            f"{origin}station {station}: markers {', '.join(markers)} are (nearly) collinear "
            f"(rms distance to their best-fit line {off_line_rms * 1e3:.3g} mm, point noise "
            f"{sigma * 1e3:.3g} mm): the rotation about that line is undetermined; "
            "add markers off the line"
        )


def curvature_tilt(t_world_station: np.ndarray) -> np.ndarray:
    """Rotation vector ``omega = e_z x d / R_E`` (rad) that turns the reference's vertical into
    that of a levelled station at ``t_world_station`` (``d``: its horizontal part),
    shape (..., 3) (docs/noise-model.md#levelled-stations-4-dof)."""
    t = np.asarray(t_world_station, dtype=float)
    return np.stack([-t[..., 1], t[..., 0], np.zeros(t.shape[:-1])], axis=-1) / EARTH_RADIUS_M


def check_args(instrument, weighting, model: str = "6dof") -> None:
    if model not in CALIBRATION_MODELS:
        raise InputError("Expected a calibration model "
                         f"{' or '.join(map(repr, CALIBRATION_MODELS))}, got {model!r}")
    if weighting not in CALIBRATION_WEIGHTINGS:
        raise InputError("Expected a calibration weighting "
                         f"{' or '.join(map(repr, CALIBRATION_WEIGHTINGS))}, got {weighting!r}")
    if not isinstance(instrument, InstrumentProfile):
        raise TypeError(f"Expected an InstrumentProfile, got {type(instrument).__name__}")


def with_extra_variance(C: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """Shot covariances plus the extra variances ``(horizontal, vertical)`` (station frame)."""
    return C + np.diag([extra[0], extra[0], extra[1]])


def marker_residuals(setup: ShotSetup, R: dict, t: dict) -> MarkerResiduals:
    markers, sa, sb, dist = [], [], [], []
    for a, b in combinations(setup.stations, 2):
        common = sorted(
            (m for (st, m) in setup.shot if st == a and (b, m) in setup.shot), key=natural_key
        )
        if not common:
            continue
        ia = np.array([setup.shot[(a, m)] for m in common])
        ib = np.array([setup.shot[(b, m)] for m in common])
        qa = setup.points[ia] @ R[a].T + t[a]
        qb = setup.points[ib] @ R[b].T + t[b]
        markers += common
        sa += [a] * len(common)
        sb += [b] * len(common)
        dist.append(np.linalg.norm(qa - qb, axis=-1))
    return MarkerResiduals(
        np.array(markers, dtype=object), np.array(sa, dtype=object), np.array(sb, dtype=object),
        np.concatenate(dist) if dist else np.zeros(0),
    )
