r"""Evaluation of SLAM / odometry trajectories against an uncertain ground truth of poses (6 dof)
or of one tracked point's positions (3 dof, with a lever arm).

:func:`evaluate` runs the chain in evo's order (associate, [mounting and clock], align, APE,
RPE, NEES, noise floor, drift) with :class:`EvaluationOptions` and returns an immutable
:class:`EvaluationResult` (:class:`PositionEvaluationResult`) whose ``to_dict`` is the JSON of
``rtsgt evaluate --json`` (docs/evaluation.md#json-layout). Records in, never files; this module
only re-exports.
"""

from __future__ import annotations

from rtsgt.evaluation.align import ALIGN_METHODS, Alignment
from rtsgt.evaluation.associate import (
    Association,
    GroundTruthQuery,
    GroundTruthSample,
    PairCovarianceGroundTruth,
    ValidatedGroundTruth,
    associate,
)
from rtsgt.evaluation.evaluator import evaluate, evaluate_positions, gap_per_step
from rtsgt.evaluation.groundtruth import ContinuousGroundTruth, ContinuousPositionGroundTruth
from rtsgt.evaluation.metrics import DELTA_UNITS, STATISTICS, NeesResult
from rtsgt.evaluation.mounting import MountingFit, fit_mounting
from rtsgt.evaluation.options import EvaluationOptions
from rtsgt.evaluation.positions import POSITION_ALIGN_METHODS
from rtsgt.evaluation.result import (
    ErrorStatistics,
    EvaluationResult,
    NeesSection,
    NoiseFloor,
    PoseErrors,
    PositionEvaluationResult,
)

__all__ = [
    "ALIGN_METHODS",
    "DELTA_UNITS",
    "STATISTICS",
    "Alignment",
    "Association",
    "ContinuousGroundTruth",
    "ContinuousPositionGroundTruth",
    "ErrorStatistics",
    "EvaluationOptions",
    "EvaluationResult",
    "MountingFit",
    "GroundTruthQuery",
    "GroundTruthSample",
    "NeesResult",
    "NeesSection",
    "NoiseFloor",
    "POSITION_ALIGN_METHODS",
    "PairCovarianceGroundTruth",
    "PoseErrors",
    "PositionEvaluationResult",
    "ValidatedGroundTruth",
    "associate",
    "evaluate",
    "evaluate_positions",
    "fit_mounting",
    "gap_per_step",
]
