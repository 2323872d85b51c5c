"""Poses with covariance from three or more prisms (docs/pose.md): the closed-form and the
weighted registration and their Jacobians (:mod:`~rtsgt.pose.registration`,
:mod:`~rtsgt.pose.weighted`), the reference prisms (:mod:`~rtsgt.pose.reference`), the engines
(:mod:`~rtsgt.pose.engines`) and :func:`estimate_poses` (:mod:`~rtsgt.pose.estimate`).
"""

from rtsgt.pose.engines import ENGINES, Linear, MonteCarlo, Unscented
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
    pose_engine,
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
    "ENGINES",
    "MIN_SHAPE",
    "Linear",
    "MonteCarlo",
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
    "pose_engine",
    "pose_jacobians",
    "pose_weights",
    "psd_factor",
    "reference_from_survey",
    "register",
    "register_weighted",
    "registration_jacobian",
    "shape_ratio",
    "triangle_geometry",
    "Unscented",
    "weighted_registration_jacobian",
]
