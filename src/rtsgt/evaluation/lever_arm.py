r"""The lever arm from an estimated sensor pose to a tracked point (a prism) on the robot.

A position-only ground truth (one prism tracked by one total station) gives the position of a
point ``P`` on the robot; a SLAM or odometry method estimates the pose of its own sensor
``S``. With ``l`` the position of ``P`` in the sensor frame (the lever arm, m), the estimate's
point is

.. math::

    p_P = p_S + R_S\, l ,

with ``(p_S, R_S)`` the sensor pose in the world frame (after the alignment). Every
comparison of an estimate with a position-only ground truth goes through this one function
(:func:`lever_arm_points`), with its Jacobians:

- with respect to the sensor pose, in the left-perturbation convention of
  :mod:`rtsgt.geometry.transform` (``p_S -> p_S + dt``, ``R_S -> exp([dtheta]x) R_S``):
  ``dp_P = dt - [R_S l]x dtheta``, so ``J_pose = [I, -[R_S l]x]`` (3 x 6). The estimate's
  rotation error enters the point through it: ``Sigma_P = J_pose Sigma_S J_pose^T``;
- with respect to the lever arm: ``dp_P = R_S dl``, ``J_lever = R_S`` (3 x 3). A lever arm
  known with covariance ``Sigma_l`` (estimated, :func:`lever_arm_factor`) is **one** error
  for the whole trajectory: its contribution ``R_S Sigma_l R_S^T`` to each point is shared by
  all of them (a factor ``R_S A_l`` with ``A_l A_l^T = Sigma_l``, not a varying error).

This module imports only numpy and rtsgt.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.errors import InputError
from rtsgt.geometry.so3 import hat

__all__ = ["LeverArmPoints", "lever_arm_factor", "lever_arm_points", "parse_lever_arm",
           "point_covariance"]


@dataclass(frozen=True)
class LeverArmPoints:
    """The point ``p_S + R_S l`` of N sensor poses, with its Jacobians.

    Attributes
    ----------
    position : ndarray, shape (N, 3)
        ``p_S + R_S l``, m.
    jacobian_pose : ndarray, shape (N, 3, 6)
        ``d p / d (dt, dtheta)``: ``[I, -[R_S l]x]``.
    jacobian_lever : ndarray, shape (N, 3, 3)
        ``d p / d l``: ``R_S``.
    """

    position: np.ndarray
    jacobian_pose: np.ndarray
    jacobian_lever: np.ndarray


def lever_arm_points(position: ArrayLike, rotation: ArrayLike,
                     lever_arm: ArrayLike) -> LeverArmPoints:
    """The point at ``lever_arm`` in the sensor frame of each pose, and its Jacobians.

    Parameters
    ----------
    position : array_like, shape (N, 3)
        ``p_S``, sensor positions, m.
    rotation : array_like, shape (N, 3, 3)
        ``R_S``, sensor orientations (sensor to world).
    lever_arm : array_like, shape (3,)
        ``l``, the point in the sensor frame, m.

    Returns
    -------
    LeverArmPoints
    """
    p = np.asarray(position, dtype=float)
    R = np.asarray(rotation, dtype=float)
    lever = np.asarray(lever_arm, dtype=float).reshape(3)
    arm = R @ lever  # R_S l, (N, 3)
    J = np.zeros(p.shape[:-1] + (3, 6))
    J[..., :3] = np.eye(3)
    J[..., 3:] = -hat(arm)
    return LeverArmPoints(p + arm, J, R.copy())


def point_covariance(points: LeverArmPoints, pose_cov: ArrayLike | None) -> np.ndarray | None:
    """``J_pose Sigma_S J_pose^T`` (N, 3, 3): the point's covariance from the sensor pose's
    6x6 covariance (world-frame left perturbation); None without one."""
    if pose_cov is None:
        return None
    J = points.jacobian_pose
    C = J @ np.asarray(pose_cov, dtype=float) @ np.swapaxes(J, -1, -2)
    return 0.5 * (C + np.swapaxes(C, -1, -2))


def lever_arm_factor(points: LeverArmPoints, lever_cov: ArrayLike) -> np.ndarray:
    """``R_S A_l`` (N, 3, 3): the points' sensitivity to the whitened error of a lever arm
    known with covariance ``lever_cov`` (3x3, m^2; ``A_l`` its lower Cholesky factor, or
    eigen-factor when singular). One draw for the whole trajectory (module docstring)."""
    C = np.asarray(lever_cov, dtype=float).reshape(3, 3)
    try:
        A = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        w, U = np.linalg.eigh(0.5 * (C + C.T))
        A = U * np.sqrt(np.clip(w, 0.0, None))
    return points.jacobian_lever @ A


def parse_lever_arm(text: str | ArrayLike | None) -> np.ndarray:
    """A lever arm from ``"x,y,z"`` (m; spaces allowed) or three numbers; zero for None.

    Raises
    ------
    InputError
        Not three finite numbers.
    """
    if text is None:
        return np.zeros(3)
    if isinstance(text, str):
        parts = [p for p in text.replace(",", " ").split() if p]
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise InputError(f"Expected a lever arm 'x,y,z' in m, got {text!r}") from None
    else:
        values = list(np.asarray(text, dtype=float).ravel())
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise InputError(f"Expected a lever arm of three finite numbers 'x,y,z' (m), got {text!r}")
    return np.asarray(values, dtype=float)
