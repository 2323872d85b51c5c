r"""The lever arm from an estimated sensor pose to a tracked point (a prism) on the robot:
``p_P = p_S + R_S l`` and its Jacobians, the one function every comparison with a
position-only ground truth goes through (docs/evaluation.md#position-only-ground-truth).
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
    """``position`` (N, 3) m of ``p_S + R_S l``; ``jacobian_pose`` (N, 3, 6) ``[I, -[R_S l]x]`` (left
    perturbation); ``jacobian_lever`` (N, 3, 3) ``R_S``.
    """

    position: np.ndarray
    jacobian_pose: np.ndarray
    jacobian_lever: np.ndarray


def lever_arm_points(position: ArrayLike, rotation: ArrayLike,
                     lever_arm: ArrayLike) -> LeverArmPoints:
    """:class:`LeverArmPoints` of sensor positions (N, 3) m, rotations (N, 3, 3) sensor to world, and
    ``lever_arm`` (3,) m in the sensor frame.
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
