r"""Evaluation of SLAM / odometry trajectories against an uncertain ground truth.

:func:`evaluate` runs the whole chain, in evo's order, with :class:`EvaluationOptions`::

    associate (time offset, max_dt)  ->  [mounting T_body_sensor and clock: given or
      estimated with the alignment]  ->  align (none | se3 | sim3 | 4dof | scale | origin)
      ->  APE, RPE (evo's definitions and statistics)
      ->  NEES (3 and 6 dof), consistency verdicts, noise floor, RPE with relative covariance

and returns an immutable :class:`EvaluationResult` whose :meth:`EvaluationResult.to_dict` is
the JSON layout of ``rtsgt evaluate --json``::

    {"ape": {"translation_m": {rmse, mean, median, std, min, max},
             "rotation_deg": {...}, "full": {...}, "n": N},
     "rpe": {"translation_m": {...}, "rotation_deg": {...}, "full": {...},
             "n_pairs": K, "delta": d, "delta_unit": "m", "all_pairs": false,
             "absent_reason": null},
     "nees": {"position": {mean, dof, fraction_inside_95, consistent, ...},
              "pose": {...}, "relative_position": {...}, "relative_pose": {...},
              "covariance": "...", "rpe_correlations": "..."},
     "noise_floor": {"ape_translation_m": ..., "ape_translation_rmse_floor_removed_m": ...,
                     "ape_rotation_deg": ..., "ape_rotation_rmse_floor_removed_deg": ...,
                     "rpe_translation_m": ..., "rpe_translation_rmse_floor_removed_m": ...,
                     "rpe_rotation_deg": ..., "rpe_rotation_rmse_floor_removed_deg": ...},
     "alignment": {"method", "weighted", "n_used", "scale", "yaw_deg", "matrix_sim3"},
     "association": {"n_estimate", "n_associated", "n_outside_ground_truth", "n_in_gaps",
                     "n_dropped", "dropped_by_reason": {reason: count},
                     "ground_truth": "continuous" | "discrete" | "query",
                     "ground_truth_detail": {...},
                     "n_covariance_interpolated", "time_offset_s", "max_dt_s",
                     "max_dt_nearest_s"},
     "mounting": null | {"estimated", "given", "T_body_sensor", "quat_xyzw",
                  "rotation_angle_deg", "rotation_axis", "rotation_sigma_deg", "lever_m",
                  "lever_sigma_m", "clock_offset_s", "clock_sigma_s", "names", "covariance",
                  "fit": {...}, "effect": {"ape_translation_m", "ape_rotation_deg",
                  "rpe_translation_m", "rpe_rotation_deg"}},
     "drift": {"definition", "step_frames", "rotation": null | why not estimable,
               "distance": {"lengths_m", "lengths_from", "n_segments", "translation_pct",
                            "translation_floor_pct", "rotation_deg_per_m",
                            "rotation_floor_deg_per_m", "translation_below_floor",
                            "rotation_below_floor", "by_length": [{"length_m", "n", ...}]},
               "time": {"lengths_s", ..., "translation_m_per_s", "rotation_deg_per_s", ...}},
     "warnings": ["..."]}

Against a position-only ground truth (one tracked prism), :func:`evaluate_positions`
(:mod:`rtsgt.evaluation.positions`) gives a :class:`PositionEvaluationResult` whose
``to_dict`` has the same sections with the rotation statistics and the pose NEES ``null``,
and ``ground_truth`` (``"positions"``), ``rotation`` (why rotations are not reported) and
``lever_arm``.

``mounting`` (docs/evaluation.md#mounting-and-clock) is ``null`` unless a mounting was given
(``mounting=``, ``--mounting``) or something estimated (``estimate=``, ``--estimate``,
:mod:`~rtsgt.evaluation.mounting`); the sigmas of what was given are ``null``.

``warnings`` is added by ``rtsgt evaluate``: every :class:`~rtsgt.errors.RtsgtWarning` that
reading the files and evaluating emitted (each also shown as a ``warning: ...`` line).

When no RPE pair exists (a robot that moved less than ``delta``), the APE and the NEES of the
poses are still given; ``rpe`` then holds ``null`` statistics, ``n_pairs`` 0 and
``absent_reason`` (why, and what to change), and the relative NEES and the RPE noise floor are
``null``. RPE pairs that span a gap of the ground truth are kept (the RPE stays evo's) and
counted in a warning (:func:`evaluate`).

The ground truth is best a :class:`~rtsgt.evaluation.groundtruth.ContinuousGroundTruth`
(``rtsgt.app.read_ground_truth(run)``): the pose and covariance at each estimate time
from the run's GP tracks, with a reason for every estimate pose it cannot vouch for.

The four sections ``ape``, ``rpe``, ``nees``, ``noise_floor`` and the keys the issue names
(``translation_m`` / ``rotation_deg`` with the six statistics; ``mean, dof,
fraction_inside_95, consistent``) are the stable interface; the other keys add detail
(NEES objects also give ``n``, ``n_eff``, ``mean_interval``, ``fraction_interval``,
``quantile_95``, ``alpha``).

NEES objects hold ``null`` values (and the noise floor ``null`` numbers) when the ground truth
has no covariance. This package imports only numpy, scipy and rtsgt.

Layout: :mod:`~rtsgt.evaluation.evaluator` (:func:`evaluate`, one function per step),
:mod:`~rtsgt.evaluation.options` (:class:`EvaluationOptions`, the options of an evaluation and
their rules), :mod:`~rtsgt.evaluation.result` (:class:`EvaluationResult` and its sections),
:mod:`~rtsgt.evaluation.associate`, :mod:`~rtsgt.evaluation.align`,
:mod:`~rtsgt.evaluation.metrics`, :mod:`~rtsgt.evaluation.mounting`, :mod:`~rtsgt.evaluation.groundtruth`,
:mod:`~rtsgt.evaluation.positions` and :mod:`~rtsgt.evaluation.lever_arm` (the position-only
ground truth); this module only re-exports.
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
from rtsgt.evaluation.evaluator import evaluate, gap_per_step
from rtsgt.evaluation.groundtruth import ContinuousGroundTruth, ContinuousPositionGroundTruth
from rtsgt.evaluation.metrics import DELTA_UNITS, STATISTICS, NeesResult
from rtsgt.evaluation.mounting import MountingFit, fit_mounting
from rtsgt.evaluation.options import EvaluationOptions
from rtsgt.evaluation.positions import (
    POSITION_ALIGN_METHODS,
    PositionEvaluationResult,
    evaluate_positions,
)
from rtsgt.evaluation.result import (
    ErrorStatistics,
    EvaluationResult,
    NeesSection,
    NoiseFloor,
    PoseErrors,
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
