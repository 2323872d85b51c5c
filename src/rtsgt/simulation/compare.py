"""Compare a computed ground truth with the truth of a simulation: errors and consistency."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.evaluation.metrics import (
    NeesResult,
    nees_consistency,
    squared_mahalanobis,
    with_split_verdict,
)
from rtsgt.geometry.so3 import quat_xyzw_to_matrix
from rtsgt.geometry.transform import perturbation
from rtsgt.shared import SharedFactor
from rtsgt.types import PoseTrajectory


@dataclass(frozen=True)
class TruthComparison:
    """Errors of estimated poses against the true ones: ``error`` (N, 6) left perturbation, world
    frame (x, y, z, rx, ry, rz) m / rad; ``nees_position`` (3 dof), ``nees_pose`` (6 dof).
    """

    error: np.ndarray
    nees_position: NeesResult
    nees_pose: NeesResult

    @property
    def position_error_m(self) -> np.ndarray:
        return np.linalg.norm(self.error[:, :3], axis=1)

    @property
    def rotation_error_rad(self) -> np.ndarray:
        return np.linalg.norm(self.error[:, 3:], axis=1)

    def to_dict(self) -> dict:
        pe = self.position_error_m
        return {
            "poses": int(self.error.shape[0]),
            "position_error_mm": {
                "rmse": float(np.sqrt(np.mean(pe**2)) * 1e3),
                "median": float(np.median(pe) * 1e3),
                "max": float(np.max(pe) * 1e3),
            },
            "rotation_error_mrad": {
                "rmse": float(np.sqrt(np.mean(self.rotation_error_rad**2)) * 1e3),
                "median": float(np.median(self.rotation_error_rad) * 1e3),
            },
            "nees_position": self.nees_position.to_dict(),
            "nees_pose": self.nees_pose.to_dict(),
        }


def compare_to_truth(
    estimate: PoseTrajectory, position_true: np.ndarray, quat_xyzw_true: np.ndarray,
    split: SharedFactor | None = None,
) -> TruthComparison:
    """Errors and NEES of ``estimate`` (``cov`` (N, 6, 6)) against true positions (N, 3) and
    quat_xyzw (N, 4) at its times. With ``split`` (the estimate's shared/varying error split) the
    verdicts are the split test's (docs/evaluation.md#errors-shared-by-the-deployment); without,
    the NEES series' autocorrelation test.
    """
    if estimate.cov is None:
        raise ValueError("Expected an estimate with covariances")
    if len(estimate) == 0:
        raise ValueError("Expected at least one pose to compare")
    e = perturbation(quat_xyzw_to_matrix(quat_xyzw_true), position_true, estimate.rotation,
                     estimate.position)
    n3 = squared_mahalanobis(e[:, :3], estimate.cov[:, :3, :3])
    n6 = squared_mahalanobis(e, estimate.cov)
    nees = (nees_consistency(n3, 3), nees_consistency(n6, 6))
    if split is not None:
        if split.t.shape != estimate.t.shape or not np.allclose(split.t, estimate.t):
            raise ValueError("Expected the shared factor at the estimate's times")
        nees = with_split_verdict(nees, e, split.varying_cov, split.factor, names=split.names)
    return TruthComparison(e, *nees)
