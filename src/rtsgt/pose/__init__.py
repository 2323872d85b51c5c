"""Poses with covariance from three or more prisms (docs/pose.md).

- :mod:`rtsgt.pose.registration`: fast closed-form batched rigid registration and its Jacobian.
- :mod:`rtsgt.pose.reference`: the reference prisms in the chosen body frame.
- :mod:`rtsgt.pose.estimate`: poses and 6x6 covariances by Monte Carlo, unscented or linear
  propagation.
"""

from rtsgt.pose.estimate import (
    POSE_ENGINES,
    REASON_COLLINEAR,
    REASON_MISSING,
    REASON_OK,
    PoseEngine,
    PoseEstimate,
    estimate_poses,
    psd_factor,
)
from rtsgt.pose.reference import (
    ReferencePoints,
    check_reference_geometry,
    frame_from_points,
    reference_from_survey,
    triangle_geometry,
)
from rtsgt.pose.registration import (
    MIN_SHAPE,
    RegistrationInfo,
    register,
    registration_jacobian,
    shape_ratio,
)

__all__ = [
    "MIN_SHAPE",
    "POSE_ENGINES",
    "REASON_COLLINEAR",
    "REASON_MISSING",
    "REASON_OK",
    "PoseEngine",
    "PoseEstimate",
    "ReferencePoints",
    "RegistrationInfo",
    "check_reference_geometry",
    "estimate_poses",
    "frame_from_points",
    "psd_factor",
    "reference_from_survey",
    "register",
    "registration_jacobian",
    "shape_ratio",
    "triangle_geometry",
]
