"""Extrinsic calibration of the total stations (docs/calibration.md)."""

from rtsgt.calibration.gcp import calibrate, fit_stations
from rtsgt.calibration.result import CalibrationResult, MarkerResiduals
from rtsgt.calibration.shots import polar_point_covariance

__all__ = [
    "CalibrationResult",
    "MarkerResiduals",
    "calibrate",
    "fit_stations",
    "polar_point_covariance",
]
