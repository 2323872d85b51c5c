"""Extrinsic calibration of the total stations from ground control points (GCPs)."""

from rtsgt.calibration.gcp import (
    CalibrationResult,
    MarkerResiduals,
    calibrate,
    fit_stations,
    polar_point_covariance,
)

__all__ = [
    "CalibrationResult",
    "MarkerResiduals",
    "calibrate",
    "fit_stations",
    "polar_point_covariance",
]
