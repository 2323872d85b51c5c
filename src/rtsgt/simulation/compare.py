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
    """Errors of estimated poses with respect to the true ones.

    Attributes
    ----------
    error : ndarray, shape (N, 6)
        Left perturbation taking the true pose to the estimate, world frame,
        (x, y, z, rx, ry, rz), m / rad.
    nees_position, nees_pose : NeesResult
        Squared Mahalanobis distance of the position (3 dof) and pose (6 dof) errors with the
        estimate's own covariance.
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
    """Errors and NEES of ``estimate`` (with covariance) against the true poses at its times.

    Parameters
    ----------
    estimate : PoseTrajectory
        With ``cov`` (N, 6, 6) in the convention of :mod:`rtsgt.geometry.transform`.
    position_true : ndarray, shape (N, 3)
    quat_xyzw_true : ndarray, shape (N, 4)
    split : SharedFactor, optional
        The estimate's error split into varying and shared parts at the same times
        (:attr:`rtsgt.record.RunRecord.groundtruth_split`). With it, the verdicts are the
        split test's (:func:`~rtsgt.evaluation.metrics.with_split_verdict`): the errors one
        simulated deployment draws once (calibration, clocks, weather, survey) are tested as
        one draw, not as N; without it, the autocorrelation test of the NEES series, which
        ignores them (it accepts an estimate too often or too rarely, by the deployment's draw).
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
