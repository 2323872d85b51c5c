"""Poses with covariance from three or more prisms (docs/pose.md).

- :mod:`rtsgt.pose.registration`: fast closed-form batched rigid registration and its Jacobian.
- :mod:`rtsgt.pose.weighted`: the weighted (generalised least squares) registration and its
  Jacobian.
- :mod:`rtsgt.pose.reference`: the reference prisms in the chosen body frame.
- :mod:`rtsgt.pose.estimate`: poses and 6x6 covariances by Monte Carlo, unscented or linear
  propagation.
"""

from rtsgt.pose.estimate import (
    DEFAULT_REGISTRATION,
    POSE_ENGINES,
    REASON_COLLINEAR,
    REASON_MISSING,
    REASON_OK,
    REGISTRATIONS,
    PoseEngine,
    PoseEstimate,
    Registration,
    estimate_poses,
    pose_jacobians,
    pose_weights,
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
from rtsgt.pose.weighted import (
    gls_weights,
    register_weighted,
    weighted_registration_jacobian,
)

__all__ = [
    "DEFAULT_REGISTRATION",
    "MIN_SHAPE",
    "POSE_ENGINES",
    "REASON_COLLINEAR",
    "REASON_MISSING",
    "REASON_OK",
    "REGISTRATIONS",
    "PoseEngine",
    "PoseEstimate",
    "ReferencePoints",
    "Registration",
    "RegistrationInfo",
    "check_reference_geometry",
    "estimate_poses",
    "frame_from_points",
    "gls_weights",
    "pose_jacobians",
    "pose_weights",
    "psd_factor",
    "reference_from_survey",
    "register",
    "register_weighted",
    "registration_jacobian",
    "shape_ratio",
    "triangle_geometry",
    "weighted_registration_jacobian",
]
