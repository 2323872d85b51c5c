r"""Extrinsic calibration of total stations from ground control points (GCPs).

Every station shoots the same markers; the shots of station s give marker positions
``p_s`` in the frame of s (:func:`rtsgt.measurement.polar.polar_to_cartesian`, additive constant
applied), and the transform ``T_world_s`` into the frame of the reference station (the world
frame) is the rigid fit, without scale, of the markers s shares with the reference:

.. math::

    (R, t) = \arg\min_{R \in SO(3), t} \sum_i w_i \| p_{ref,i} - (R p_{s,i} + t) \|^2

solved in closed form by :func:`rtsgt.geometry.kabsch` (Kabsch 1976 / Umeyama 1991, reflection
guarded). Markers are matched by their identifier, never by time (station clocks may be wrong:
in the RTS_project data of 2022-11-10 station 1 is months off).

Weights (``weighting``, :data:`CALIBRATION_WEIGHTINGS`). Each point carries the first-order
covariance of its polar measurement, ``C = J S J^T`` with ``J`` =
:func:`rtsgt.measurement.polar.polar_jacobian` and ``S`` the covariance of ``(Hz, V, d)`` under
the instrument and tilt model of :mod:`rtsgt.noise.perturb` (``V^ = V + e_V + e_tilt``,
``Hz^ = Hz + e_Hz + e_tilt cot V``)::

    S = [[sa^2 + st^2 cot^2 V, st^2 cot V, 0],
         [st^2 cot V,          sa^2 + st^2, 0],
         [0,                   0,           sd(d)^2]]

The residual of marker i, ``p_ref,i - R p_s,i - t``, has covariance ``C_i = C_ref,i + R C_s,i
R^T`` (the variance components below included).

- ``"gls"``: the generalised least-squares fit, ``min sum_i r_i^T C_i^-1 r_i``,
  the best linear unbiased fit: a shot known well across its line of sight and poorly along
  it (or the reverse, at short range) counts for what it is worth in each direction. ``C_i``
  is evaluated once, at the rotation of the trace-weighted fit, and held fixed (the same
  choice as the pose's weighted registration); the 6-DOF fit is the Newton iteration on SO(3)
  of :mod:`rtsgt.pose.weighted` (one solver for both), the 4-DOF fit a Gauss-Newton iteration
  on the yaw and the translation (:func:`_gls_yaw`). Every Monte Carlo sample is fitted with
  the same weights, starting from the nominal fit.
- ``"trace"``: the isotropic approximation ``w_i = 1 / tr(C_ref,i + R C_s,i R^T) = 1 / (tr
  C_ref,i + tr C_s,i)``, which does not depend on R (the trace is rotation invariant): a
  closed-form weighted Kabsch. It down-weights the far markers, whose angular noise grows
  with range, but not by direction.
- ``"none"`` (the default, :data:`DEFAULT_WEIGHTING`): every marker alike (the paper's Kabsch
  fit).

Uncertainty (:func:`calibrate`). As in Vaidis et al. 2023 (section III-E), every GCP shot of
every station is perturbed with the instrument and tilt noise
(:func:`rtsgt.noise.perturb.sample_polar_errors`), and the fit is repeated for each of M
samples, all samples at once (batched SVD). The sampled transforms are kept (sample m is
used by sample m of the prism Monte Carlo) and summarised by the sample covariance (ddof 1)
of their left perturbations about the nominal fit, in the convention of
:mod:`rtsgt.geometry.transform` (world frame, ordered x, y, z, rx, ry, rz). The samples are
not re-centred: their mean offset from the nominal fit is a second-order bias, far below the
spread. The reference station is perturbed too, so the
samples of different stations are correlated through the reference's shots, as they should be.

Residuals. For every marker and every pair of stations that both shot it, the distance between
the two stations' positions of the marker after mapping both into the world frame.

Fit check (:class:`FitCheck`, a Type A evaluation). The residuals of each station's fit,
``r_i = p_ref,i - R p_s,i - t``, are compared with their predicted covariance
``C_i = C_ref,i + R C_s,i R^T`` (the instrument and tilt model above). The residuals are those
of the generalised least-squares fit (weights ``C_i^-1``; one Gauss-Newton step from the
Kabsch fit, in the left perturbation): those of the Kabsch fit itself are not chi-square with
``3 K - 6`` degrees of freedom, since its unweighted rotation leaks the large range errors into
the directions where ``C_i`` is small (twice the expected sum on simulated shots). The
a-posteriori variance factor is ``s0^2 = sum_i r_i^T C_i^-1 r_i / (3 K - 6)`` over the
station's ``K`` markers, and per world axis ``sum_i r_ia^2 / C_i,aa / (K - 2)`` (the 6
parameters shared evenly among the 3 axes), with the chi-square test of ``s0^2``: consistent
when it lies inside ``chi2_dof(0.025, 0.975) / dof``.
A factor well above 1 says the shots disagree more than the instrument model predicts
(centring and height of the prism poles, marker stability, refraction), so the calibration
covariance, which the Monte Carlo draws from the same model, is too small by about that
factor.

Variance components (:func:`extra_shot_variance`). Where the residuals show it, the
calibration's Monte Carlo adds to every shot, in each station's levelled frame, a horizontal
and a vertical variance component: the values that bring the pooled per-axis variance factors
of the fits (all stations, ``K - 2`` degrees of freedom per station and axis) to 1, found by
bisection with the generalised least-squares residuals. A group (horizontal, vertical) gets a
component only when its factor is above its chi-square 95 % interval, so a deployment that
agrees with the instrument model keeps it unchanged. These are the errors the instrument model
does not have (pole heights and centring of the GCP prisms, marker stability, refraction); the
estimate is the deployment's own (Type A), nothing is carried from one deployment to another.
Being two numbers for all stations, it is a variance-component estimate in the sense of
Helmert and Foerstner, not a bootstrap over markers: with 10-12 markers a bootstrap of six
parameters per station is too noisy, and the residuals say where the model fails (the
vertical) well enough to carry it.

Models (``model``). ``"6dof"`` (the paper) fits the rotation freely. ``"4dof"`` is for
levelled instruments: a station's dual-axis compensator refers every angle to its local
vertical, so its frame has no free tilt and only ``x, y, z`` and the yaw are fitted (fewer
parameters from the same shots: a smaller covariance, and the tilt no longer absorbs the shots'
vertical errors). The verticals of two stations are not parallel, though: on a sphere of radius
:data:`EARTH_RADIUS_M` a station ``d`` (horizontal, in the reference's frame) from the
reference has its vertical turned by ``omega = e_z x d / R_E`` (16 microradians, 3.2 arcsec,
per 100 m: 1.6 mm of height at 100 m range, more than the compensator's error), so the 4-DOF
transform is ``T_world_s = (exp([omega]x) R_z(psi), t)``: the yaw and translation are the
closed-form weighted fit (:func:`rtsgt.geometry.kabsch.kabsch_yaw`) of the shots against the
reference's shots turned by ``exp(-[omega]x)``, with ``omega`` from the fitted translation
(twice: a millimetre of ``t`` moves ``omega`` by 1e-10 rad). The deflection of the vertical
between stations (under an arcsecond over a few hundred metres, except in mountains) is not
modelled. The compensator's own error (:attr:`InstrumentProfile.sigma_tilt`) is a tilt of each
station's frame about its vertical: the Monte Carlo draws one per station and sample
(reference included, whose frame is the world's), so the tilt of a station against the world
has a variance of ``2 sigma_tilt^2`` and stations are correlated through the reference; the fit
of each sample is conditioned on its drawn tilt. Whichever the model, every station's
levelling is tested (:class:`LevellingCheck`): one 6-DOF Gauss-Newton step from the levelled
transform gives the tilt the shots ask for beyond the curvature, with its covariance (the
generalised least-squares fit's, variance components included, plus ``2 sigma_tilt^2``), and
``chi2 = tilt^T Sigma^-1 tilt`` has 2 degrees of freedom if the stations are levelled; where it
is not, the 4-DOF model is wrong for that deployment (a compensator off, a station not
levelled). The fit check and the variance components count 4 parameters: ``3 K - 4`` degrees of freedom, ``K - 1.5`` per horizontal axis (3
parameters on 2 axes) and ``K - 1`` on the vertical.

This module reads no files: the shots come from :mod:`rtsgt.io`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from itertools import combinations
from typing import TYPE_CHECKING

import numpy as np

# CALIBRATION_METHODS and DEFAULT_WEIGHTING (the weighting of calibrate and of a run's
# [calibration]) are defined in rtsgt.choices, which the command line reads without numpy
from rtsgt.choices import CALIBRATION_METHODS as CALIBRATION_METHODS
from rtsgt.choices import DEFAULT_WEIGHTING
from rtsgt.errors import GeometryError, InputError, RtsgtWarning
from rtsgt.geometry.kabsch import kabsch, kabsch_yaw
from rtsgt.geometry.so3 import exp_so3, hat
from rtsgt.geometry.transform import RigidTransform, perturbation
from rtsgt.measurement.atmosphere import instrument_correction_ppm
from rtsgt.measurement.instruments import TRIMBLE_S7, InstrumentProfile
from rtsgt.measurement.polar import polar_jacobian, polar_to_cartesian
from rtsgt.noise.model import NoiseModel
from rtsgt.noise.perturb import sample_polar_errors
from rtsgt.pose.reference import block_diagonal
from rtsgt.pose.weighted import gls_weights, refine_batches
from rtsgt.stats import ratio_interval, ratio_verdict
from rtsgt.types import GcpShots, WeatherSeries

if TYPE_CHECKING:
    from rtsgt.calibration.dynamic import DynamicFit

#: The models of a station's transform (module docstring, section Models).
CALIBRATION_MODELS = ("6dof", "4dof")
#: What each model is, in words (for tables and reports).
CALIBRATION_MODEL_NAMES = {"6dof": "6 DOF: free rotation",
                           "4dof": "4 DOF: levelled stations, yaw only"}
#: What each method is, in words (for tables and reports).
CALIBRATION_METHOD_NAMES = {"gcp": "ground control points",
                            "dynamic": "the robot's motion (inter-prism distances)",
                            "joint": "ground control points and the robot's motion"}
#: How the markers of a station's fit are weighted (module docstring, section Weights).
CALIBRATION_WEIGHTINGS = ("gls", "trace", "none")
#: What each weighting is, in words (for tables and reports).
CALIBRATION_WEIGHTING_NAMES = {"gls": "generalised least squares (full covariance)",
                               "trace": "trace-weighted", "none": "unweighted"}
#: Mean radius of the Earth (IUGG), m: the verticals of two levelled instruments ``d`` metres
#: apart differ by ``d / EARTH_RADIUS_M`` rad (16 microradians per 100 m).
EARTH_RADIUS_M = 6_371_000.0

#: A station's markers must stand off their best-fit line by more than this many times the
#: point noise (1 sigma), or the rotation about that line is undetermined.
COLLINEARITY_FACTOR = 3.0


@dataclass(frozen=True)
class MarkerResiduals:
    """Inter-station residuals of the GCPs after calibration.

    Attributes
    ----------
    marker : ndarray of str, shape (K,)
    station_a, station_b : ndarray of str, shape (K,)
        The two stations of each residual (``station_a`` sorts before ``station_b``).
    distance_m : ndarray, shape (K,)
        ``|T_world_a p_a - T_world_b p_b|``, m, world frame.
    """

    marker: np.ndarray
    station_a: np.ndarray
    station_b: np.ndarray
    distance_m: np.ndarray

    def __len__(self) -> int:
        return self.distance_m.shape[0]

    @property
    def median_m(self) -> float:
        """Median residual, m (NaN when there is none)."""
        return float(np.median(self.distance_m)) if len(self) else float("nan")

    @property
    def max_m(self) -> float:
        """Largest residual, m (NaN when there is none)."""
        return float(np.max(self.distance_m)) if len(self) else float("nan")


@dataclass(frozen=True)
class FitCheck:
    """What a station's GCP residuals say of the predicted covariance (module docstring).

    Attributes
    ----------
    markers : int
        Markers of the fit, K.
    dof : int
        ``3 K - 6``.
    variance_factor : float
        ``s0^2``, 1 if the instrument model is right (NaN without degrees of freedom).
    axis_factors : ndarray, shape (3,)
        The same per world axis x, y, z.
    interval_95 : tuple of float
        Where ``s0^2`` falls 95 % of the time if the model is right.
    """

    markers: int
    dof: int
    variance_factor: float
    axis_factors: np.ndarray
    interval_95: tuple[float, float]

    @property
    def verdict(self) -> str:
        """``consistent``, ``optimistic`` (residuals larger than predicted: the covariance is
        too small), ``pessimistic``, or ``no redundancy`` (3 markers: no degrees of
        freedom)."""
        if not self.dof > 0:
            return "no redundancy"
        return ratio_verdict(self.variance_factor, self.interval_95)

    def as_dict(self) -> dict:
        """JSON-ready."""
        return {"markers": self.markers, "dof": self.dof,
                "variance_factor": self.variance_factor,
                "axis_factors_xyz": [float(x) for x in self.axis_factors],
                "interval_95": list(self.interval_95), "verdict": self.verdict}


@dataclass(frozen=True)
class CalibrationResult:
    """Extrinsic calibration of all stations into the reference station's frame.

    Attributes
    ----------
    reference_station : str
    transforms : dict str -> RigidTransform
        ``T_world_station`` for every station (world = frame of the reference station; the
        reference itself is the identity with zero covariance). Each carries ``covariance``
        (6x6, left perturbation in the world frame, ordered x, y, z, rx, ry, rz; m^2, rad^2)
        and the Monte Carlo samples ``samples_rotation`` (M, 3, 3) and
        ``samples_translation`` (M, 3), or None for both when ``samples == 0``.
    residuals : MarkerResiduals
        For every marker and pair of stations, the distance between the two positions.
    markers_used : dict str -> tuple of str
        Markers used in the fit of each station (for the reference: those used by any fit).
    markers_skipped : tuple of str
        Markers left out because fewer than 2 stations shot them validly.
    excluded_shots : int
        Shots left out because their status was not 0.
    samples : int
        Number of Monte Carlo samples M (0: no uncertainty computed).
    weighting : {"gls", "trace", "none"}
        How the markers were weighted (module docstring, section Weights).
    fit_checks : dict str -> FitCheck
        For every station but the reference, its residuals against their predicted
        covariance (module docstring).
    extra_shot_sigma_m : (float, float)
        The variance components added to every shot, horizontal and vertical, as standard
        deviations, m (module docstring; zeros when the residuals agree with the model).
    model : {"6dof", "4dof"}
        The model of each station's transform (module docstring, section Models).
    levelling : dict str -> LevellingCheck
        For every station but the reference, whether the shots agree with a levelled frame
        (whichever the model).
    method : {"gcp", "dynamic", "joint"}
        What the transforms were fitted to: the GCPs (this module), the robot's motion, or
        both (:mod:`rtsgt.calibration.dynamic`; the GCP fields then hold the GCP fit's
        checks, and are empty for ``"dynamic"``).
    dynamic : DynamicFit or None
        The dynamic or joint fit's own results (:class:`rtsgt.calibration.dynamic.DynamicFit`:
        clock offsets, variance factor), None for ``"gcp"``.
    """

    reference_station: str
    transforms: dict[str, RigidTransform]
    residuals: MarkerResiduals
    markers_used: dict[str, tuple[str, ...]]
    markers_skipped: tuple[str, ...]
    excluded_shots: int
    samples: int
    weighting: str
    fit_checks: dict[str, FitCheck] = field(default_factory=dict)
    extra_shot_sigma_m: tuple[float, float] = (0.0, 0.0)
    model: str = "6dof"
    levelling: dict[str, LevellingCheck] = field(default_factory=dict)
    method: str = "gcp"
    dynamic: DynamicFit | None = None


def polar_point_covariance(
    hz: np.ndarray, v: np.ndarray, d: np.ndarray, instrument: InstrumentProfile
) -> np.ndarray:
    """First-order covariance of station-frame points from instrument and tilt noise.

    Parameters
    ----------
    hz, v, d : ndarray, shape (N,)
        Clockwise direction (rad), zenith angle (rad), slope distance (m, constant applied).
    instrument : InstrumentProfile

    Returns
    -------
    ndarray, shape (N, 3, 3)
        ``J S J^T``, m^2, station frame (model in the module docstring).
    """
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


def _natural_key(s: str) -> tuple:
    return (0, int(s), s) if s.isdigit() else (1, 0, s)


@dataclass(frozen=True)
class _Setup:
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


def _setup(shots: GcpShots, reference_station: str, instrument: InstrumentProfile) -> _Setup:
    if not isinstance(shots, GcpShots):
        raise TypeError(f"Expected GcpShots, got {type(shots).__name__}")
    ref = str(reference_station)
    known = sorted({str(s) for s in shots.station}, key=_natural_key)
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
        sorted((m for m, ss in stations_of.items() if len(ss) < 2), key=_natural_key)
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
            sorted((m for (st, m) in shot if st == s and (ref, m) in shot), key=_natural_key)
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
    return _Setup(known, hz, v, d, points, shot, pairs, used, skipped, excluded)


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


def _weights(setup: _Setup, idx_s, idx_r, instrument) -> np.ndarray:
    """``w_i = 1 / (tr C_ref,i + tr C_s,i)`` (1/m^2), see the module docstring."""
    C = polar_point_covariance(setup.hz, setup.v, setup.d, instrument)
    tr = np.trace(C, axis1=-2, axis2=-1)
    return 1.0 / (tr[idx_s] + tr[idx_r])


def curvature_tilt(t_world_station: np.ndarray) -> np.ndarray:
    """Rotation vector ``omega = e_z x d / R_E`` (rad) that turns the reference's vertical into
    that of a levelled station at ``t_world_station`` (``d``: its horizontal part), module
    docstring, section Models. Shape (..., 3)."""
    t = np.asarray(t_world_station, dtype=float)
    return np.stack([-t[..., 1], t[..., 0], np.zeros(t.shape[:-1])], axis=-1) / EARTH_RADIUS_M


def _fit_4dof(p: np.ndarray, q: np.ndarray, w, tilt: np.ndarray | None = None, *,
              check: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``q ~ exp([omega + tilt]x) R_z(psi) p + t`` with ``omega`` the curvature tilt of ``t``
    (module docstring, section Models); batched over leading axes of ``p``, ``q``, ``tilt``."""
    t = kabsch_yaw(p, q, w, check=check)[1]
    return _levelled(t, tilt, lambda T, _: kabsch_yaw(p, q @ T, w, check=check))


def _levelled(t: np.ndarray, tilt: np.ndarray | None, fit_tilted) -> tuple[np.ndarray, np.ndarray]:
    """The 4-DOF transform from the fit of the yaw and translation in the frame turned by the
    curvature tilt of ``t`` (plus the compensators' ``tilt``), twice (module docstring, section
    Models): ``fit_tilted(T, t)`` returns ``R_z`` and ``t'`` of ``T^T q ~ R_z p + t'`` (rows
    ``q T = (T^T q)^T``); then ``R = T R_z``, ``t = T t'``."""
    for _ in range(2):
        omega = curvature_tilt(t)
        if tilt is not None:
            omega = omega + tilt
        T = exp_so3(omega)
        Rz, t_tilted = fit_tilted(T, t)
        t = np.einsum("...ij,...j->...i", T, t_tilted)
    return T @ Rz, t


def _fit(setup: _Setup, s: str, p: np.ndarray, q: np.ndarray, w, model: str,
         tilt: np.ndarray | None = None, check: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The fit of station ``s``'s points ``p`` onto the reference's ``q`` under ``model``."""
    try:
        if model == "4dof":
            return _fit_4dof(p, q, w, tilt, check=check)
        return kabsch(p, q, w, check=check)
    except GeometryError as exc:
        raise GeometryError(f"station {s} (markers {', '.join(setup.pairs[s][2])}): {exc}"
                            ) from None


def _nominal(setup: _Setup, weighting: str, instrument, model: str) -> dict[str, tuple]:
    """Closed-form fit of each non-reference station: ``{s: (R, t, weights or None)}``; trace
    weights for ``"gls"`` too (its start and the rotation its weights are evaluated at)."""
    out = {}
    for s, (idx_s, idx_r, _) in setup.pairs.items():
        w = _weights(setup, idx_s, idx_r, instrument) if weighting != "none" else None
        R, t = _fit(setup, s, setup.points[idx_s], setup.points[idx_r], w, model)
        out[s] = (R, t, w)
    return out


def _gls_station_weights(setup: _Setup, s: str, R: np.ndarray, C: np.ndarray) -> np.ndarray:
    """``W = C^-1`` of station ``s``'s stacked residuals, ``C_i = C_ref,i + R C_s,i R^T``
    (module docstring, section Weights), (3K, 3K)."""
    idx_s, idx_r, _ = setup.pairs[s]
    return gls_weights(block_diagonal(C[idx_r]), block_diagonal(C[idx_s]), R)


def _gls_yaw(p: np.ndarray, y: np.ndarray, W: np.ndarray, psi: np.ndarray, t: np.ndarray,
             steps: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton of ``min e^T W e``, ``e = y - (R_z(psi) p + t)`` stacked, over the yaw and
    the translation; ``p, y`` (S, K, 3), ``W`` (3K, 3K), the start ``psi`` (S,), ``t``
    (S, 3). The problem is linear in ``t`` and nearly so in ``psi`` (a start within
    milliradians): the steps fall quadratically, to round-off in three or four."""
    S, K, _ = p.shape
    psi, t = psi.astype(float).copy(), t.astype(float).copy()
    J = np.zeros((S, K, 3, 4))
    J[..., 1:] = np.eye(3)
    for _ in range(steps):
        c, sn = np.cos(psi)[:, None], np.sin(psi)[:, None]
        a = np.stack([c * p[..., 0] - sn * p[..., 1], sn * p[..., 0] + c * p[..., 1],
                      p[..., 2]], axis=-1)
        e = (y - a - t[:, None, :]).reshape(S, 3 * K)
        J[..., 0, 0], J[..., 1, 0] = -a[..., 1], a[..., 0]  # d(R_z p)/dpsi = e_z x R_z p
        Jf = J.reshape(S, 3 * K, 4)
        JW = np.swapaxes(Jf, 1, 2) @ W
        step = np.linalg.solve(JW @ Jf, (JW @ e[..., None]))[..., 0]
        psi += step[:, 0]
        t += step[:, 1:]
    return psi, t


def _gls_fit(p: np.ndarray, q: np.ndarray, W: np.ndarray, R0: np.ndarray, t0: np.ndarray,
             model: str, tilt: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The generalised least-squares fit of station points ``p`` onto the reference's ``q``
    (S, K, 3) with the weights ``W`` (3K, 3K), from the start ``R0, t0`` (a station's nominal
    fit), under ``model`` (the 4-DOF one with the compensators' ``tilt`` (S, 3), as
    :func:`_fit_4dof`). Returns ``R`` (S, 3, 3), ``t`` (S, 3) and whether each converged (S,)
    (else its last iterate: shots far from any rigid fit, e.g. a mirrored station)."""
    S = q.shape[0]
    if model == "6dof":
        R, t, conv, _ = refine_batches(p[None], q[None], W[None], R0[None, None],
                                       t0[None, None])
        return R[0], t[0], conv[0]
    # 4 DOF: R = exp([omega + tilt]x) R_z(psi); the weights, evaluated at the nominal rotation,
    # are held as they are in the tilted frame (the tilt is microradians)
    psi = np.full(S, np.arctan2(R0[1, 0], R0[0, 0]))

    def yaw_fit(T, t):
        nonlocal psi  # each pass starts from the last one's yaw
        psi, t_tilted = _gls_yaw(p, q @ T, W, psi, np.einsum("sji,sj->si", T, t))
        return exp_so3(psi[:, None] * np.array([0.0, 0.0, 1.0])), t_tilted

    R, t = _levelled(np.broadcast_to(t0, (S, 3)), tilt, yaw_fit)
    return R, t, np.ones(S, dtype=bool)


def _check_args(instrument, weighting, model: str = "6dof") -> None:
    if model not in CALIBRATION_MODELS:
        raise InputError("Expected a calibration model "
                         f"{' or '.join(map(repr, CALIBRATION_MODELS))}, got {model!r}")
    if weighting not in CALIBRATION_WEIGHTINGS:
        raise InputError("Expected a calibration weighting "
                         f"{' or '.join(map(repr, CALIBRATION_WEIGHTINGS))}, got {weighting!r}")
    if not isinstance(instrument, InstrumentProfile):
        raise TypeError(f"Expected an InstrumentProfile, got {type(instrument).__name__}")


def fit_stations(
    shots: GcpShots,
    *,
    reference_station: str = "1",
    weighting: str = DEFAULT_WEIGHTING,
    instrument: InstrumentProfile = TRIMBLE_S7,
    model: str = "6dof",
) -> dict[str, RigidTransform]:
    """Rigid fit of every station into the reference station's frame, matched by marker.

    Parameters
    ----------
    shots : GcpShots
        Shots of all stations; those with a non-zero status are left out.
    reference_station : str
        Station whose frame is the world frame.
    weighting : {"gls", "trace", "none"}
        The markers' weights (module docstring, section Weights): their full covariance under
        the instrument model, ``1 / (tr C_ref + tr C_s)``, or none.
    instrument : InstrumentProfile
        Noise model for the weights and the collinearity check.
    model : {"6dof", "4dof"}
        Free rotation, or levelled stations (module docstring, section Models).

    Returns
    -------
    dict str -> RigidTransform
        ``T_world_station`` for every station (the reference is the identity); no
        covariance on the fitted ones (use :func:`calibrate` for it).

    Raises
    ------
    InputError
        Unknown reference station (the message lists the known ones), a single station,
        a marker shot twice by one station.
    GeometryError
        A station sharing fewer than 3 valid markers with the reference, or (nearly)
        collinear markers.
    """
    _check_args(instrument, weighting, model)
    ref = str(reference_station)
    setup = _setup(shots, ref, instrument)
    R, t, _, _ = _fits(setup, ref, weighting, instrument, model,
                    polar_point_covariance(setup.hz, setup.v, setup.d, instrument), False)
    out = {ref: RigidTransform(np.eye(3), np.zeros(3), np.zeros((6, 6)), "world", f"station_{ref}")}
    for s in setup.stations:
        if s != ref:
            out[s] = RigidTransform(R[s], t[s], None, "world", f"station_{s}")
    return out


def _fits(setup: _Setup, ref: str, weighting: str, instrument, model: str, C: np.ndarray,
          variance_components: bool) -> tuple[dict, dict, dict, np.ndarray]:
    """The nominal fit of every station (the reference ``ref``'s identity included): ``R, t``
    and the fit's weights by station (trace weights (K,), ``W`` (3K, 3K) under ``"gls"``, or
    None), and the variance components (:func:`extra_shot_variance`, from the generalised
    least-squares residuals, which do not depend on the fit they start from) when
    ``variance_components``, else zeros; under ``"gls"`` they enter the weights."""
    R, t, w = {ref: np.eye(3)}, {ref: np.zeros(3)}, {}
    for s, (Rs, ts, ws) in _nominal(setup, weighting, instrument, model).items():
        R[s], t[s], w[s] = Rs, ts, ws
    extra = extra_shot_variance(setup, R, t, C, model) if variance_components else np.zeros(2)
    if weighting == "gls":
        Cx = _with_extra(C, extra)
        for s, (idx_s, idx_r, _) in setup.pairs.items():
            w[s] = _gls_station_weights(setup, s, R[s], Cx)
            Rs, ts, ok = _gls_fit(setup.points[idx_s][None], setup.points[idx_r][None], w[s],
                                  R[s], t[s], model)
            if ok[0]:
                R[s], t[s] = Rs[0], ts[0]
            else:
                warnings.warn(f"station {s}: the generalised least-squares fit of the GCPs did "
                              "not converge (shots far from any rigid fit: check the "
                              "residuals); the trace-weighted fit stands", RtsgtWarning,
                              stacklevel=3)
    return R, t, w, extra


def _gls_step(setup: _Setup, R: dict, t: dict, C: np.ndarray, s: str, model: str = "6dof"):
    """One Gauss-Newton step of station ``s``'s generalised least-squares fit from the fit
    ``R, t`` (in the left perturbation: ``R p ~ R p - [R p]x dphi``, ``t ~ t + dt``; under
    ``"4dof"`` ``dphi`` along the station's vertical only), from the shots' covariance ``C``.

    Returns the residuals after the step, their covariance ``C_ref,i + R C_s,i R^T``, the step
    ``(dphi, dt)`` (``(dpsi, dt)`` under ``"4dof"``) and the normal matrix ``J^T C^-1 J``, whose
    inverse is the covariance of the fitted parameters."""
    idx_s, idx_r, _ = setup.pairs[s]
    Ci = C[idx_r] + R[s] @ C[idx_s] @ R[s].T
    W = np.linalg.inv(Ci)
    Rp = setup.points[idx_s] @ R[s].T
    r = setup.points[idx_r] - Rp - t[s]
    rot = hat(Rp) if model == "6dof" else hat(Rp) @ R[s][:, 2:3]
    J = np.concatenate([rot, np.broadcast_to(-np.eye(3), Rp.shape + (3,))], axis=2)
    JW = np.swapaxes(J, 1, 2) @ W
    N = np.sum(JW @ J, axis=0)
    step = np.linalg.lstsq(N, -np.sum(JW @ r[..., None], axis=0), rcond=None)[0]
    return r + (J @ step)[..., 0], Ci, step[:, 0], N


def _gls_residuals(setup: _Setup, R: dict, t: dict, C: np.ndarray,
                   s: str, model: str = "6dof") -> tuple[np.ndarray, np.ndarray]:
    """Residuals of station ``s``'s generalised least-squares fit and their covariance
    (:func:`_gls_step`)."""
    r, Ci, _, _ = _gls_step(setup, R, t, C, s, model)
    return r, Ci


@dataclass(frozen=True)
class LevellingCheck:
    """Whether a station's frame is levelled with the reference's (module docstring, section
    Models): the tilt that a free rotation fits beyond the Earth's curvature, tested against
    the fit's covariance and the compensators' errors.

    Attributes
    ----------
    tilt_rad : ndarray, shape (2,)
        The free fit's tilt about the world x and y axes minus the curvature's, rad.
    sigma_rad : ndarray, shape (2,)
        Its standard deviations (the generalised least-squares fit with the run's shot
        covariance, variance components included, and ``2 sigma_tilt^2`` of the
        compensators), rad.
    chi2 : float
        ``tilt^T Sigma^-1 tilt``, chi-square with 2 degrees of freedom if levelled.
    p_value : float
    """

    tilt_rad: np.ndarray
    sigma_rad: np.ndarray
    chi2: float
    p_value: float

    def as_dict(self) -> dict:
        """JSON-ready (microradians)."""
        return {"tilt_urad": [float(x) * 1e6 for x in self.tilt_rad],
                "sigma_urad": [float(x) * 1e6 for x in self.sigma_rad],
                "chi2": self.chi2, "p_value": self.p_value}


def _levelling_checks(setup: _Setup, R: dict, t: dict, C: np.ndarray,
                      sigma_tilt: float) -> dict[str, LevellingCheck]:
    """:class:`LevellingCheck` of every fitted station: one 6-DOF Gauss-Newton step from the
    fit ``R, t`` with the curvature's tilt (a 4-DOF fit, or a 6-DOF one turned to it)."""
    out = {}
    for s in setup.pairs:
        yaw = np.arctan2(R[s][1, 0] - R[s][0, 1], R[s][0, 0] + R[s][1, 1])
        Rl = {s: exp_so3(curvature_tilt(t[s])) @ exp_so3(np.array([0.0, 0.0, yaw]))}
        _, _, step, N = _gls_step(setup, Rl, t, C, s)
        cov = np.linalg.inv(N)[:2, :2] + 2.0 * sigma_tilt**2 * np.eye(2)
        tilt = step[:2]
        chi2 = float(tilt @ np.linalg.solve(cov, tilt))
        out[s] = LevellingCheck(tilt, np.sqrt(np.diag(cov)), chi2, float(np.exp(-0.5 * chi2)))
    return out


def _axis_dof(markers: int, model: str) -> np.ndarray:
    """Degrees of freedom per world axis of a fit of ``markers`` markers: the 6 parameters
    shared evenly among the axes, or the 4 of ``"4dof"`` (x, y and the yaw on the
    horizontal axes, z on the vertical)."""
    return markers - (np.full(3, 2.0) if model == "6dof" else np.array([1.5, 1.5, 1.0]))


def _fit_checks(setup: _Setup, R: dict, t: dict, C: np.ndarray,
                model: str = "6dof") -> dict[str, FitCheck]:
    """:class:`FitCheck` of every fitted station (module docstring), shots' covariance ``C``."""
    out = {}
    for s, (_, _, markers) in setup.pairs.items():
        r, Ci = _gls_residuals(setup, R, t, C, s, model)
        K = len(markers)
        dof = 3 * K - (6 if model == "6dof" else 4)
        chi2 = float(np.einsum("ki,kij,kj->", r, np.linalg.inv(Ci), r))
        axes = np.sum(r ** 2 / np.diagonal(Ci, axis1=-2, axis2=-1), axis=0)
        if dof > 0:
            out[s] = FitCheck(K, dof, chi2 / dof, axes / _axis_dof(K, model),
                              ratio_interval(dof))
        else:
            out[s] = FitCheck(K, dof, float("nan"), np.full(3, np.nan), (np.nan, np.nan))
    return out


def _with_extra(C: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """Shot covariances plus the extra variances ``(horizontal, vertical)`` (station frame)."""
    return C + np.diag([extra[0], extra[0], extra[1]])


def extra_shot_variance(setup: _Setup, R: dict, t: dict, C: np.ndarray,
                        model: str = "6dof") -> np.ndarray:
    """Variance components (m^2) to add to every shot, horizontal and vertical, so that the
    pooled per-axis variance factors of the fits are 1 (module docstring, section Variance
    components); 0 for a group whose factor is inside its 95 % interval."""
    extra = np.zeros(2)
    checks = [(0, [0, 1]), (1, [2])]
    dof = sum(_axis_dof(len(m), model) for (_, _, m) in setup.pairs.values())
    if np.any(dof <= 0):
        return extra

    def factor(group: int, x: float) -> float:
        e = extra.copy()
        e[group] = x
        Cx = _with_extra(C, e)
        total = 0.0
        for s in setup.pairs:
            r, Ci = _gls_residuals(setup, R, t, Cx, s, model)
            total += float(np.sum(r[:, axes] ** 2 / np.diagonal(Ci, axis1=-2, axis2=-1)[:, axes]))
        return total / float(dof[axes].sum())

    for _ in range(3):  # the two groups interact a little through the fit: alternate
        for group, axes in checks:
            if factor(group, 0.0) <= ratio_interval(float(dof[axes].sum()))[1]:
                extra[group] = 0.0
                continue
            hi = 1e-8
            while factor(group, hi) > 1.0 and hi < 1.0:
                hi *= 4.0
            lo = 0.0
            for _ in range(50):  # bisection on the variance, to 1e-15 relative
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if factor(group, mid) > 1.0 else (lo, mid)
            extra[group] = hi
    return extra


def _residuals(setup: _Setup, R: dict, t: dict) -> MarkerResiduals:
    markers, sa, sb, dist = [], [], [], []
    for a, b in combinations(setup.stations, 2):
        common = sorted(
            (m for (st, m) in setup.shot if st == a and (b, m) in setup.shot), key=_natural_key
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


def calibrate(
    shots: GcpShots,
    *,
    reference_station: str = "1",
    instrument: InstrumentProfile = TRIMBLE_S7,
    samples: int = 1000,
    rng: np.random.Generator | None = None,
    weighting: str = DEFAULT_WEIGHTING,
    variance_components: bool = True,
    model: str = "6dof",
) -> CalibrationResult:
    """Calibrate all stations from GCP shots, with a Monte Carlo 6x6 covariance per station.

    Parameters
    ----------
    shots : GcpShots
    reference_station : str
        Station whose frame is the world frame.
    instrument : InstrumentProfile
        Instrument and tilt noise model of every station.
    samples : int
        M, number of Monte Carlo samples (0: fit only, no covariance and no samples).
    rng : numpy.random.Generator, optional
        Source of every random draw (a fresh unseeded one when None).
    weighting : {"gls", "trace", "none"}
        The markers' weights (module docstring, section Weights), for the nominal fit and
        every sample.
    variance_components : bool
        Add to every shot the variance the residuals show beyond the instrument model
        (module docstring, section Variance components); False: the instrument model alone,
        as the paper.
    model : {"6dof", "4dof"}
        Free rotation (the paper), or levelled stations (module docstring, section Models).

    Returns
    -------
    CalibrationResult

    Raises
    ------
    InputError, GeometryError
        As :func:`fit_stations`.
    """
    _check_args(instrument, weighting, model)
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)):
        raise TypeError(f"Expected an integer number of samples, got {samples!r}")
    if samples < 0 or samples == 1:
        raise ValueError(f"Expected samples = 0 or >= 2, got {samples}")
    rng = np.random.default_rng() if rng is None else rng
    ref = str(reference_station)
    setup = _setup(shots, ref, instrument)
    C = polar_point_covariance(setup.hz, setup.v, setup.d, instrument)
    R, t, weights, extra = _fits(setup, ref, weighting, instrument, model, C,
                                 variance_components)

    M = int(samples)
    if M:
        # Perturb every valid shot of every station: (M, N) -> points (M, N, 3)
        hz_m, v_m, d_m = sample_polar_errors(setup.hz, setup.v, setup.d, instrument, M, rng)
        points_m = polar_to_cartesian(hz_m, v_m, d_m)
        if extra.any():  # the variance components, in each station's (levelled) frame
            points_m += rng.standard_normal(points_m.shape) * np.sqrt(extra[[0, 0, 1]])
        if model == "4dof":  # each compensator's error, a tilt of its station's frame
            comp = rng.standard_normal((M, len(setup.stations), 2)) * instrument.sigma_tilt
            comp = np.concatenate([comp, np.zeros((M, len(setup.stations), 1))], axis=2)
            tilt_of = {st: comp[:, k] - comp[:, setup.stations.index(ref)]
                       for k, st in enumerate(setup.stations)}
    transforms = {}
    for s in setup.stations:
        if s == ref:
            cov = np.zeros((6, 6))
            Rm = np.broadcast_to(np.eye(3), (M, 3, 3)).copy() if M else None
            tm = np.zeros((M, 3)) if M else None
        elif M:
            idx_s, idx_r, _ = setup.pairs[s]
            tilt = tilt_of[s] if model == "4dof" else None
            if weighting == "gls":
                Rm, tm, ok = _gls_fit(points_m[:, idx_s], points_m[:, idx_r], weights[s], R[s],
                                      t[s], model, tilt)
                if not ok.all():
                    warnings.warn(f"station {s}: the generalised least-squares fit did not "
                                  f"converge for {int((~ok).sum())} of {M} Monte Carlo "
                                  "samples (shots far from any rigid fit: check the "
                                  "residuals); their last iterates are kept", RtsgtWarning,
                                  stacklevel=2)
            else:
                Rm, tm = _fit(setup, s, points_m[:, idx_s], points_m[:, idx_r], weights[s],
                              model, tilt, check=False)
            xi = perturbation(R[s], t[s], Rm, tm)  # (M, 6), (x, y, z, rx, ry, rz)
            cov = np.cov(xi, rowvar=False)
            cov = 0.5 * (cov + cov.T)
        else:
            cov = Rm = tm = None
        transforms[s] = RigidTransform(
            R[s], t[s], cov, "world", f"station_{s}", Rm, tm
        )
    used = {s: setup.pairs[s][2] for s in setup.pairs}
    used[ref] = tuple(sorted(setup.used_markers, key=_natural_key))
    return CalibrationResult(
        reference_station=ref,
        transforms=transforms,
        residuals=_residuals(setup, R, t),
        markers_used={s: used[s] for s in setup.stations},
        markers_skipped=setup.skipped,
        excluded_shots=setup.excluded,
        samples=M,
        weighting=weighting,
        fit_checks=_fit_checks(setup, R, t, C, model),
        extra_shot_sigma_m=(float(np.sqrt(extra[0])), float(np.sqrt(extra[1]))),
        model=model,
        levelling=_levelling_checks(setup, R, t, _with_extra(C, extra), instrument.sigma_tilt),
    )


def gcp_atmospheric_correction(
    gcp: GcpShots, model: NoiseModel, weather: WeatherSeries | None, fallback_t: float
) -> GcpShots:
    """GCP shots with the first-velocity correction applied to their distances.

    The GCP distances need the same atmospheric correction as the tracking distances: at
    100 m, the 5-10 ppm of a cold, high site is 0.5-1 mm of scale between stations, a bias of
    the calibration that no covariance accounts for. Each shot takes the weather at its time
    when that time lies inside the weather series, else the weather at ``fallback_t`` (the
    start of tracking): a station whose clock was off (the GCP shots of station 1 in the
    2022-11-10 data are months off) must not pick the weather of another season. Without
    weather, the shots are returned unchanged (reference atmosphere, as for the tracks).
    """
    if weather is None:
        return gcp
    n = len(gcp.d)
    t = np.full(n, float(fallback_t)) if gcp.t is None else np.asarray(gcp.t, dtype=float)
    inside = np.isfinite(t) & (t >= weather.t[0]) & (t <= weather.t[-1])
    t = np.where(inside, t, float(fallback_t))
    temp, pres, hum = weather.at(t)
    ppm = np.asarray(instrument_correction_ppm(model.instrument, temp, pres, hum,
                                               model.vapour_formula), dtype=float)
    c = float(gcp.additive_constant)
    d = (np.asarray(gcp.d, dtype=float) + c) * (1.0 + 1e-6 * ppm) - c
    return replace(gcp, d=d)


def gcp_world_positions(
    gcp: GcpShots | None, transforms: dict[str, RigidTransform]
) -> tuple[np.ndarray | None, tuple[str, ...]]:
    """World position of every ground control point, and the marker names.

    Each valid shot (status 0) of a calibrated station is converted to Cartesian coordinates
    (additive constant included) and mapped into the world frame by its station's transform;
    a marker's position is the mean over its shots. Returns ``(None, ())`` without GCPs.
    Markers are in natural order (``"2"`` before ``"10"``): by length, then by name.
    """
    if gcp is None or len(gcp) == 0:
        return None, ()
    ok = (np.asarray(gcp.status) == 0) & np.isin(gcp.station, list(transforms))
    if not ok.any():
        return None, ()
    p_station = polar_to_cartesian(gcp.hz[ok], gcp.v[ok], gcp.distance[ok])
    p_world = np.empty_like(p_station)
    stations = gcp.station[ok]
    for s in np.unique(stations):  # one transform per station (a handful)
        m = stations == s
        p_world[m] = transforms[str(s)].apply(p_station[m])
    markers = gcp.marker[ok]
    names = tuple(sorted(set(markers.tolist()), key=lambda x: (len(x), x)))
    xyz = np.array([p_world[markers == k].mean(axis=0) for k in names])
    return xyz, names
