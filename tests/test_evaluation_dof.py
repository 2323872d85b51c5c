"""One evaluation for 3 and 6 DOF (issue 27): the ground truth says its degrees of freedom and
``rtsgt.evaluation.evaluate`` takes both; a lever arm belongs to positions, a mounting to poses.
"""

from __future__ import annotations

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.evaluation import PositionEvaluationResult, evaluate, evaluate_positions
from rtsgt.evaluation.associate import ground_truth_dof
from rtsgt.types import PoseTrajectory, PositionTrajectory
from test_evaluation_positions import LEVER, _gt, _truth
from test_evaluation_synth import trajectory


def test_evaluate_takes_a_ground_truth_of_positions():
    """The same result through evaluate(lever_arm=) as through evaluate_positions, 3 dof
    (the split verdict's and the NEES's numbers included)."""
    rng = np.random.default_rng(4)
    t, p, R = _truth(400)
    gt, _ = _gt(t, p, R, rng)
    est = trajectory(t, p, R)
    assert ground_truth_dof(gt) == 3 and ground_truth_dof(trajectory(t, p, R)) == 6
    one = evaluate(gt, est, lever_arm=LEVER, align="se3", weighted=True)
    other = evaluate_positions(gt, est, LEVER, align="se3", weighted=True)
    assert isinstance(one, PositionEvaluationResult)
    assert one.to_dict() == other.to_dict()
    d = one.to_dict()
    assert d["nees"]["position"]["dof"] == 3 and d["nees"]["pose"]["mean"] is None
    assert d["ape"]["rotation_deg"] is None and d["noise_floor"]["ape_rotation_deg"] is None
    # an exact estimate against errors drawn from the covariance: NEES / dof near 1
    assert 0.7 < d["nees"]["position"]["mean"] / 3 < 1.3


def test_a_lever_arm_or_a_mounting_of_the_wrong_kind_is_refused():
    t, p, R = _truth(200)
    est = trajectory(t, p, R)
    poses = PoseTrajectory(t, p, est.quat_xyzw)
    with pytest.raises(InputError, match="lever arm is that of a ground truth of positions"):
        evaluate(poses, est, lever_arm=LEVER)
    points = PositionTrajectory(t, p + R @ LEVER)
    with pytest.raises(InputError, match="no rotation to fit a mounting"):
        evaluate(points, est, lever_arm=LEVER, mounting=(0, 0, 0, 0, 0, 0, 1))
    with pytest.raises(TypeError, match="ground truth of positions"):
        evaluate_positions(poses, est, LEVER)
