"""The joint engine's poses as a ground truth queryable at any time inside its knots, with the
covariance between two times (the relative pose): what the static relative-pose check and a
relative-pose error need of it. The mathematics: docs/joint.md#poses-at-two-times.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.evaluation.associate import REASON_OUTSIDE, GroundTruthSample
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.joint.relative import JointPosterior

__all__ = ["JointGroundTruth"]


@dataclass(frozen=True)
class JointGroundTruth:
    """Poses of a joint run (:class:`rtsgt.joint.relative.JointPosterior`) at any time inside
    its knots' span; a time outside gets :data:`rtsgt.evaluation.associate.REASON_OUTSIDE`."""

    posterior: JointPosterior

    def query_poses(self, times: ArrayLike) -> GroundTruthSample:
        """:class:`GroundTruthSample` at ``times`` (M,) s (no gate: the run's own gates judged
        its grid)."""
        tau = np.atleast_1d(np.asarray(times, dtype=float))
        lo, hi = self.posterior.span
        inside = (tau >= lo) & (tau <= hi)
        M = tau.size
        position, quat = np.full((M, 3), np.nan), np.full((M, 4), np.nan)
        cov = np.full((M, 6, 6), np.nan)
        if inside.any():
            R, p, c = self.posterior.poses(tau[inside])
            position[inside], quat[inside], cov[inside] = p, matrix_to_quat_xyzw(R), c
        reason = np.where(inside, "", REASON_OUTSIDE)
        return GroundTruthSample(tau, position, quat, cov, reason, np.zeros(M), None)

    def cross_covariance(self, tau_a: ArrayLike, tau_b: ArrayLike) -> np.ndarray:
        """``Cov(xi(tau_a), xi(tau_b))`` (K, 6, 6), ``tau_a < tau_b`` pairwise."""
        return self.posterior.cross_covariance(np.asarray(tau_a, dtype=float),
                                               np.asarray(tau_b, dtype=float))

    def pair_covariances(self, tau_a: ArrayLike, tau_b: ArrayLike):
        """``Cov(xi(tau_a))``, ``Cov(xi(tau_b))`` and their cross covariance."""
        return (self.posterior.poses(tau_a)[2], self.posterior.poses(tau_b)[2],
                self.cross_covariance(tau_a, tau_b))
