"""Rigid-body geometry: SO(3)/SE(3) maps, the pose-covariance convention, rigid fits."""

from rtsgt.geometry.kabsch import kabsch, kabsch_yaw
from rtsgt.geometry.so3 import exp_so3, hat, log_so3, matrix_to_quat_xyzw, quat_xyzw_to_matrix
from rtsgt.geometry.transform import RigidTransform

__all__ = [
    "RigidTransform",
    "exp_so3",
    "hat",
    "kabsch",
    "kabsch_yaw",
    "log_so3",
    "matrix_to_quat_xyzw",
    "quat_xyzw_to_matrix",
]
