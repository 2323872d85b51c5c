"""What :func:`rtsgt.evaluation.evaluate` returns: APE / RPE statistics, NEES, noise floor and
:class:`EvaluationResult` (whose :meth:`~EvaluationResult.to_dict` is the JSON layout of
``rtsgt evaluate --json``, described in :mod:`rtsgt.evaluation`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rtsgt.evaluation.align import Alignment
from rtsgt.evaluation.associate import Association
from rtsgt.evaluation.drift import Drift
from rtsgt.evaluation.metrics import STATISTICS, NeesResult, error_statistics
from rtsgt.evaluation.mounting import MountingFit
from rtsgt.types import PoseTrajectory, PositionTrajectory

__all__ = ["ROTATION_NOT_REPORTED", "ErrorStatistics", "EvaluationResult", "NeesSection",
           "NoiseFloor", "PoseErrors", "PositionEvaluationResult"]

#: What the result of a position ground truth says about rotations (``rotation`` of the JSON).
ROTATION_NOT_REPORTED = ("not reported: the ground truth has positions only; the estimate's "
                         "rotation enters the position errors through the lever arm")


@dataclass(frozen=True)
class ErrorStatistics:
    """evo's statistics of one error array (units of the array)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float

    @classmethod
    def from_errors(cls, errors: ArrayLike) -> ErrorStatistics:
        return cls(**error_statistics(errors))

    def to_dict(self) -> dict[str, float]:
        return {k: float(getattr(self, k)) for k in STATISTICS}


@dataclass(frozen=True)
class PoseErrors:
    """APE or RPE: per-pose (per-pair) errors (K,) and their :class:`ErrorStatistics`:
    ``translation_m``/``translation_error`` (m), ``rotation_deg``/``rotation_error_deg`` and
    ``full``/``full_error`` (None for positions), ``pairs`` (K, 2) for the RPE (None for the APE).
    """

    translation_m: ErrorStatistics
    rotation_deg: ErrorStatistics | None
    full: ErrorStatistics | None
    translation_error: np.ndarray
    rotation_error_deg: np.ndarray | None
    full_error: np.ndarray | None
    pairs: np.ndarray | None = None

    @classmethod
    def from_errors(
        cls, errs: dict[str, np.ndarray], pairs: np.ndarray | None = None
    ) -> PoseErrors:
        rot_deg = np.degrees(errs["rotation_rad"])
        return cls(
            ErrorStatistics.from_errors(errs["translation"]),
            ErrorStatistics.from_errors(rot_deg),
            ErrorStatistics.from_errors(errs["full"]),
            errs["translation"],
            rot_deg,
            errs["full"],
            pairs,
        )

    @classmethod
    def of_positions(cls, norms: np.ndarray, pairs: np.ndarray | None = None) -> PoseErrors:
        """The errors of positions: their norms ``norms`` (K,) m, no rotation."""
        return cls(ErrorStatistics.from_errors(norms), None, None, norms, None, None, pairs)

    def to_dict(self) -> dict:
        return {
            "translation_m": self.translation_m.to_dict(),
            "rotation_deg": None if self.rotation_deg is None else self.rotation_deg.to_dict(),
            "full": None if self.full is None else self.full.to_dict(),
        }


@dataclass(frozen=True)
class NeesSection:
    """Normalised estimation error squared of positions, poses and relative poses.

    Each field is None when the covariances needed are not available.
    ``covariance`` says which covariances entered ``S``; ``rpe_correlations`` whether the
    relative-pose covariance used known cross-covariances between the two ground-truth poses.
    """

    position: NeesResult | None
    pose: NeesResult | None
    relative_position: NeesResult | None
    relative_pose: NeesResult | None
    covariance: str
    rpe_correlations: str

    def to_dict(self) -> dict:
        def one(r: NeesResult | None, dof: int) -> dict:
            if r is None:
                return {"mean": None, "dof": dof, "fraction_inside_95": None, "consistent": None}
            return r.to_dict()

        return {
            "position": one(self.position, 3),
            "pose": one(self.pose, 6),
            "relative_position": one(self.relative_position, 3),
            "relative_pose": one(self.relative_pose, 6),
            "covariance": self.covariance,
            "rpe_correlations": self.rpe_correlations,
        }


@dataclass(frozen=True)
class NoiseFloor:
    """What a perfect estimate would show against this ground truth (``sqrt(mean tr Sigma)``, m or
    deg, APE and RPE) and the rmse with it removed, ``sqrt(max(rmse^2 - floor^2, 0))``
    (docs/evaluation.md#noise-floor).
    """

    ape_translation_m: float | None = None
    ape_translation_rmse_floor_removed_m: float | None = None
    ape_rotation_deg: float | None = None
    ape_rotation_rmse_floor_removed_deg: float | None = None
    rpe_translation_m: float | None = None
    rpe_translation_rmse_floor_removed_m: float | None = None
    rpe_rotation_deg: float | None = None
    rpe_rotation_rmse_floor_removed_deg: float | None = None

    def to_dict(self) -> dict:
        return {k: (None if v is None else float(v)) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class EvaluationResult:
    """Everything :func:`evaluate` computed against a pose ground truth.

    ``t`` (N,) s (estimate clock); ``gt`` and aligned ``est`` (world frame, covariances);
    ``alignment``, ``association``; ``ape``, ``rpe`` (None: ``rpe_absent_reason``) with
    ``rpe_delta``, ``rpe_delta_unit``, ``rpe_all_pairs``; ``nees``; ``noise_floor``; ``pose_error``
    (N, 6) m, rad; ``cov_error`` (N, 6, 6) the NEES's ``S_k``; ``mounting`` (MountingFit or None),
    ``mounting_effect``; ``drift`` (:mod:`rtsgt.evaluation.drift`).
    """

    t: np.ndarray
    gt: PoseTrajectory
    est: PoseTrajectory
    alignment: Alignment
    association: Association
    ape: PoseErrors
    rpe: PoseErrors | None
    nees: NeesSection
    noise_floor: NoiseFloor
    pose_error: np.ndarray
    cov_error: np.ndarray | None
    rpe_delta: float
    rpe_delta_unit: str
    rpe_all_pairs: bool
    rpe_absent_reason: str | None = None
    mounting: MountingFit | None = None
    mounting_effect: dict | None = None
    drift: Drift | None = None

    def to_dict(self) -> dict:
        """The JSON layout of ``rtsgt evaluate --json`` (module docstring)."""
        return {
            **common_sections(self),
            "mounting": None if self.mounting is None else {
                **self.mounting.to_dict(), "effect": self.mounting_effect},
            "drift": None if self.drift is None else self.drift.to_dict(),
        }


def common_sections(result, rpe_definition: str | None = None) -> dict:
    """The sections of the JSON layout every result has, in order: ``ape``, ``rpe``
    (:func:`error_sections`; with ``rpe_definition`` as its ``definition``), ``nees``,
    ``noise_floor``, ``alignment``, ``association``."""
    ape, rpe = error_sections(result)
    if rpe_definition is not None:
        rpe["definition"] = rpe_definition
    return {"ape": ape, "rpe": rpe, "nees": result.nees.to_dict(),
            "noise_floor": result.noise_floor.to_dict(),
            "alignment": result.alignment.to_dict(),
            "association": result.association.to_dict()}


def error_sections(result) -> tuple[dict, dict]:
    """The ``ape`` and ``rpe`` sections of the JSON layout (module docstring) of a result
    with the fields of :class:`EvaluationResult` named ``t``, ``ape``, ``rpe`` and
    ``rpe_*`` (it and :class:`PositionEvaluationResult`)."""
    ape = result.ape.to_dict()
    ape["n"] = int(result.t.shape[0])
    if result.rpe is None:
        rpe = {"translation_m": None, "rotation_deg": None, "full": None}
    else:
        rpe = result.rpe.to_dict()
    rpe.update(
        n_pairs=0 if result.rpe is None else int(result.rpe.pairs.shape[0]),
        delta=float(result.rpe_delta),
        delta_unit=result.rpe_delta_unit,
        all_pairs=bool(result.rpe_all_pairs),
        absent_reason=result.rpe_absent_reason,
    )
    return ape, rpe


@dataclass(frozen=True)
class PositionEvaluationResult:
    """What :func:`evaluate` computed against a ground truth of positions (3 dof): the fields of
    :class:`EvaluationResult` without rotations (``drift`` translational only), and ``est`` the
    aligned points ``p_S + R_S l``, ``est_poses`` the aligned sensor poses, ``position_error``
    (N, 3) m, ``cov_error`` (N, 3, 3), ``lever_arm`` (3,) m with ``lever_arm_source`` and
    ``lever_arm_cov`` (3, 3) m^2.
    """

    t: np.ndarray
    gt: PositionTrajectory
    est: PositionTrajectory
    est_poses: PoseTrajectory
    lever_arm: np.ndarray
    alignment: Alignment
    association: Association
    ape: PoseErrors
    rpe: PoseErrors | None
    nees: NeesSection
    noise_floor: NoiseFloor
    position_error: np.ndarray
    cov_error: np.ndarray | None
    rpe_delta: float
    rpe_delta_unit: str
    rpe_all_pairs: bool
    rpe_absent_reason: str | None = None
    lever_arm_source: str = "given"
    lever_arm_cov: np.ndarray | None = None
    drift: Drift | None = None
    mounting: MountingFit | None = None  # the lever arm and the clock, when estimated

    def to_dict(self) -> dict:
        """The JSON layout of ``rtsgt evaluate --json`` (:meth:`EvaluationResult.to_dict`'s,
        rotations ``null``), with ``ground_truth`` ``"positions"``, ``lever_arm`` and
        ``rotation`` (and ``mounting``: :meth:`MountingFit.to_prism_dict`, or null)."""
        return {
            "ground_truth": "positions",
            "rotation": ROTATION_NOT_REPORTED,
            "lever_arm": {"m": [float(v) for v in self.lever_arm], "frame": "sensor (estimate)",
                          "source": self.lever_arm_source,
                          "cov_m2": (None if self.lever_arm_cov is None
                                     else self.lever_arm_cov.tolist())},
            **common_sections(
                self, "|(p_est,j - p_est,i) - (p_gt,j - p_gt,i)|, world frame"),
            "drift": None if self.drift is None else self.drift.to_dict(),
            "mounting": None if self.mounting is None else self.mounting.to_prism_dict(),
        }
