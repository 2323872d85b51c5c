"""What a calibration returns: the transforms with their checks (docs/calibration.md).

The records of :mod:`rtsgt.calibration.gcp` and :mod:`rtsgt.calibration.dynamic`, in a module
that imports neither, so that readers of a calibration need not import the fits.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rtsgt.geometry.transform import RigidTransform
from rtsgt.stats import ratio_verdict

__all__ = ["CALIBRATION_METHOD_NAMES", "CALIBRATION_MODEL_NAMES", "CALIBRATION_WEIGHTING_NAMES",
           "CalibrationResult", "DynamicFit", "FitCheck", "LevellingCheck", "MarkerResiduals"]

#: What each model is, in words (for tables and reports).
CALIBRATION_MODEL_NAMES = {"6dof": "6 DOF: free rotation",
                           "4dof": "4 DOF: levelled stations, yaw only"}
#: What each method is, in words (for tables and reports).
CALIBRATION_METHOD_NAMES = {"gcp": "ground control points",
                            "dynamic": "the robot's motion (inter-prism distances)",
                            "joint": "ground control points and the robot's motion"}
#: What each weighting is, in words (for tables and reports).
CALIBRATION_WEIGHTING_NAMES = {"gls": "generalised least squares (full covariance)",
                               "trace": "trace-weighted", "none": "unweighted"}


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
    """What a station's GCP residuals say of the predicted covariance (docs/self-checks.md#gcp-fit).

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
class LevellingCheck:
    """Whether a station's frame is levelled with the reference's (docs/noise-model.md#levelled-stations-4-dof): the tilt that a free rotation fits beyond the Earth's curvature, tested against
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


@dataclass(frozen=True)
class DynamicFit:
    """What the dynamic (or joint) fit found besides the transforms (docs/calibration.md).

    Attributes
    ----------
    method : {"dynamic", "joint"}
    engine : {"linear", "mc"}
    samples : int
        Sample times used.
    rejected : int
        Sample times left out (a pair residual beyond the gate).
    pairs : tuple of str
        The prism pairs, ``"a-b"``.
    stations : tuple of str
        The non-reference stations, in the order of ``covariance``.
    clock_offset_s, clock_sigma_s : dict str -> float
        Each non-reference station's clock offset relative to the reference's
        (``e_s - e_ref``, ``e = t_true - t_stamped``) and its standard deviation, s.
    covariance : ndarray
        Joint covariance of the stations' left perturbations (6 each, in ``stations``' order)
        and the clock offsets.
    variance_factor : float
        ``s0^2`` of the distance residuals (docs/calibration.md#self-checks).
    dof : float
        Its effective degrees of freedom.
    interval_95 : (float, float)
    pair_mean_mm, pair_rms_mm : dict str -> float
        Mean and RMS of each pair's residual, mm (a mean far from 0: a surveyed distance the
        tracking disagrees with).
    worst_sigma_m : dict str -> float
        Each station's largest standard deviation of its prism positions due to the
        calibration (the observability check), m.
    iterations : int
        Levenberg-Marquardt iterations of the last solve.
    height_margin : float
        How much worse (``-2 log`` likelihood) the best fit with mirrored station heights is
        (``inf``: none, or the joint fit, whose GCPs fix the heights).
    shot_sigma_m : (float, float) or None
        The joint fit's variance components of the GCP shots, horizontal and vertical, as
        standard deviations, m (docs/calibration.md#the-joint-calibration); None for ``"dynamic"``.
    """

    method: str
    engine: str
    samples: int
    rejected: int
    pairs: tuple[str, ...]
    stations: tuple[str, ...]
    clock_offset_s: dict[str, float]
    clock_sigma_s: dict[str, float]
    covariance: np.ndarray
    variance_factor: float
    dof: float
    interval_95: tuple[float, float]
    pair_mean_mm: dict[str, float] = field(default_factory=dict)
    pair_rms_mm: dict[str, float] = field(default_factory=dict)
    worst_sigma_m: dict[str, float] = field(default_factory=dict)
    iterations: int = 0
    height_margin: float = float("inf")
    shot_sigma_m: tuple[float, float] | None = None

    @property
    def verdict(self) -> str:
        """``consistent``, ``optimistic`` or ``pessimistic`` (:func:`rtsgt.stats.ratio_verdict`)."""
        return ratio_verdict(self.variance_factor, self.interval_95)

    def as_dict(self) -> dict:
        """JSON-ready (clock offsets in ms)."""
        return {"method": self.method, "engine": self.engine, "samples": self.samples,
                "rejected_samples": self.rejected,
                "clock_offset_ms": {s: 1e3 * v for s, v in self.clock_offset_s.items()},
                "clock_sigma_ms": {s: 1e3 * v for s, v in self.clock_sigma_s.items()},
                "variance_factor": self.variance_factor, "dof": self.dof,
                "interval_95": list(self.interval_95), "verdict": self.verdict,
                "pairs": {p: {"mean_mm": self.pair_mean_mm[p], "rms_mm": self.pair_rms_mm[p]}
                          for p in self.pairs},
                "worst_sigma_mm": {s: 1e3 * v for s, v in self.worst_sigma_m.items()},
                "iterations": self.iterations,
                "height_margin": None if not np.isfinite(self.height_margin)
                else self.height_margin,
                "gcp_shot_sigma_mm": None if self.shot_sigma_m is None
                else {"horizontal": 1e3 * self.shot_sigma_m[0],
                      "vertical": 1e3 * self.shot_sigma_m[1]}}


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
        How the markers were weighted (docs/noise-model.md#weights-of-the-gcps).
    fit_checks : dict str -> FitCheck
        For every station but the reference, its residuals against their predicted
        covariance (docs/self-checks.md#gcp-fit).
    extra_shot_sigma_m : (float, float)
        The variance components added to every shot, horizontal and vertical, as standard
        deviations, m (docs/self-checks.md#variance-components-the-model-changed-where-the-check-fails; zeros when the residuals agree with the model).
    model : {"6dof", "4dof"}
        The model of each station's transform (docs/noise-model.md#levelled-stations-4-dof).
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
