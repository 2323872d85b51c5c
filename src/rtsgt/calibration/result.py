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
    """Inter-station residuals of the GCPs after calibration, (K,) each: the marker, its two
    stations (``station_a`` sorts first) and ``|T_world_a p_a - T_world_b p_b|``, m."""

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
    """A station's GCP residuals against their predicted covariance
    (docs/self-checks.md#gcp-fit): K ``markers``, ``dof = 3 K - 6``, the ``variance_factor``
    ``s0^2`` (1 if the model is right; NaN without dof), ``axis_factors`` (3,) per world axis
    and the ``interval_95`` where ``s0^2`` falls 95 % of the time if the model is right."""

    markers: int
    dof: int
    variance_factor: float
    axis_factors: np.ndarray
    interval_95: tuple[float, float]

    @property
    def verdict(self) -> str:
        """:func:`rtsgt.stats.ratio_verdict`, or ``no redundancy`` (3 markers)."""
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
    """Whether a station's frame is levelled with the reference's
    (docs/noise-model.md#levelled-stations-4-dof): the free fit's tilt about world x and y
    beyond the curvature's, ``tilt_rad`` (2,), its ``sigma_rad`` (2,) (the fit's covariance and
    ``2 sigma_tilt^2`` of the compensators), ``chi2`` (2 dof if levelled) and ``p_value``."""

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
    """What the dynamic or joint fit found besides the transforms (docs/calibration.md).

    ``samples``/``rejected``: sample times used / left out by the gate; ``pairs`` ``"a-b"``;
    ``stations``: the non-reference ones, the order of ``covariance`` (their left
    perturbations, 6 each, then the clock offsets); ``clock_offset_s``/``clock_sigma_s``:
    ``e_s - e_ref`` (``e = t_true - t_stamped``) and its sigma, s; ``variance_factor``,
    ``dof``, ``interval_95``: the distance residuals' check (docs/calibration.md#self-checks);
    ``pair_mean_mm``/``pair_rms_mm`` per pair; ``worst_sigma_m``: the observability check's
    sigma per station, m; ``iterations`` of the last solve; ``height_margin``: ``-2 log``
    likelihood of the best mirrored-heights fit above the best (``inf``: none, or joint);
    ``shot_sigma_m``: the joint fit's GCP variance components (horizontal, vertical), m.
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
        """:func:`rtsgt.stats.ratio_verdict` of the variance factor."""
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

    ``transforms``: ``T_world_station`` per station (the reference: identity, zero
    covariance), each with its 6x6 covariance (x, y, z, rx, ry, rz; m^2, rad^2) and M Monte
    Carlo samples (None when ``samples == 0``); ``residuals`` per marker and station pair;
    ``markers_used`` per station (the reference: any fit's); ``markers_skipped`` (shot validly
    by fewer than 2 stations); ``excluded_shots`` (status not 0); ``weighting``,
    ``fit_checks``, ``extra_shot_sigma_m`` (variance components, horizontal and vertical, m),
    ``model`` and ``levelling`` of the GCP fit (docs/noise-model.md#extrinsic-calibration);
    ``method`` "gcp", "dynamic" or "joint" and ``dynamic`` its :class:`DynamicFit` (None for
    "gcp"; the GCP fields are empty for "dynamic").
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
