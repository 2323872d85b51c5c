r"""Evaluation of SLAM / odometry trajectories against an uncertain ground truth of poses (6
dof) or of one tracked point's positions (3 dof, with a lever arm).

:func:`evaluate` runs the whole chain, in evo's order, with :class:`EvaluationOptions`::

    associate (time offset, max_dt)  ->  [mounting T_body_sensor and clock: given or
      estimated with the alignment]  ->  align (none | se3 | sim3 | 4dof | scale | origin)
      ->  APE, RPE (evo's definitions and statistics)
      ->  NEES (3 and 6 dof), consistency verdicts, noise floor, RPE with relative covariance
      ->  drift by segment length

and returns an immutable :class:`EvaluationResult` (:class:`PositionEvaluationResult` for
positions) whose ``to_dict`` is the JSON layout of ``rtsgt evaluate --json``
(docs/evaluation.md#json-layout). It takes records, never files, and imports only numpy,
scipy and rtsgt.

Layout: :mod:`~rtsgt.evaluation.evaluator` (:func:`evaluate`, one function per step),
:mod:`~rtsgt.evaluation.options` (:class:`EvaluationOptions`, the options of an evaluation and
their rules), :mod:`~rtsgt.evaluation.result` (:class:`EvaluationResult` and its sections),
:mod:`~rtsgt.evaluation.associate`, :mod:`~rtsgt.evaluation.align`,
:mod:`~rtsgt.evaluation.metrics`, :mod:`~rtsgt.evaluation.mounting`, :mod:`~rtsgt.evaluation.groundtruth`,
:mod:`~rtsgt.evaluation.positions` and :mod:`~rtsgt.evaluation.lever_arm` (what is specific
to a ground truth of positions: the alignment of points, the lever arm); this module only
re-exports.
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
