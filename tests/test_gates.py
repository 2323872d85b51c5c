"""Module 4 quality gates: inter-prism distance, uncertainty, degenerate poses."""

import numpy as np
import pytest

from rtsgt.filtering.gates import apply_gates, position_uncertainty, quality_gates
from rtsgt.pose import ReferencePoints, estimate_poses

REF_D = np.array([0.73555, 0.90303, 1.03046])


def test_position_uncertainty_measures():
    cov = np.zeros((2, 6, 6))
    cov[0, :3, :3] = np.diag([0.01, 0.04, 0.09])
    cov[0, 3:, 3:] = np.eye(3)  # rotation does not count
    R = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
    cov[1, :3, :3] = R @ np.diag([0.01, 0.04, 0.09]) @ R.T
    np.testing.assert_allclose(position_uncertainty(cov), [0.3, 0.3])
    np.testing.assert_allclose(position_uncertainty(cov, "sqrt_trace"), np.sqrt(0.14) * np.ones(2))
    np.testing.assert_allclose(position_uncertainty(cov[:, :3, :3], "sqrt_frobenius"),
                               np.sqrt(np.sqrt(0.01**2 + 0.04**2 + 0.09**2)) * np.ones(2))
    cov[1, 0, 0] = np.nan
    assert np.isnan(position_uncertainty(cov)[1])
    with pytest.raises(ValueError, match="measure"):
        position_uncertainty(cov, "max")


def test_gates_keep_mask_reasons_and_counts():
    d = np.tile(REF_D, (6, 1))
    d[1, 2] += 0.11  # distance gate
    d[2, 0] -= 0.0999  # inside the gate
    d[3, 1] += 0.5  # both gates
    d[4] = np.nan  # degenerate (missing prism)
    cov = np.tile(np.eye(6) * 1e-6, (6, 1, 1))
    cov[3, :3, :3] = np.eye(3) * 0.25**2
    cov[5, :3, :3] = np.diag([1e-6, 0.21**2, 1e-6])  # uncertainty gate (worst axis 0.21 m)
    cov[4] = np.nan
    rep = quality_gates(d, cov, REF_D)
    np.testing.assert_array_equal(rep.keep, [True, False, True, False, False, False])
    assert list(rep.reason) == ["", "distance", "", "distance", "degenerate", "uncertainty"]
    assert rep.counts == {"total": 6, "kept": 2, "rejected": 4, "degenerate": 1,
                          "distance": 2, "uncertainty": 2}
    assert rep.rejected_by == {"degenerate": 1, "distance": 2, "uncertainty": 1}
    assert sum(rep.rejected_by.values()) == rep.counts["rejected"]
    np.testing.assert_allclose(rep.distance_error[[0, 1, 2]], [0.0, 0.11, 0.0999], atol=1e-12)
    assert np.isnan(rep.distance_error[4])
    # a tighter gate rejects more
    rep2 = quality_gates(d, cov, REF_D, distance_gate_m=0.05, uncertainty_gate_m=0.3)
    np.testing.assert_array_equal(rep2.keep, [True, False, False, False, False, True])
    summary = rep.as_dict()
    assert summary["distance_gate_m"] == 0.10 and summary["uncertainty_gate_m"] == 0.20
    assert summary["counts"]["kept"] == 2
    with pytest.raises(ValueError, match="positive"):
        quality_gates(d, cov, REF_D, distance_gate_m=0.0)
    with pytest.raises(ValueError, match="reference_distances"):
        quality_gates(d, cov, REF_D[:2])


def test_apply_gates_on_a_pose_estimate():
    rng = np.random.default_rng(3)
    d12, d13, d23 = REF_D
    x = (d12**2 + d13**2 - d23**2) / (2 * d12)
    r = np.array([[0.0, 0.0, 0.5], [d12, 0.0, 0.5], [x, np.sqrt(d13**2 - x**2), 0.5]])
    T = 8
    q = r[None] + rng.normal(size=(T, 1, 3)) * 20 + rng.normal(size=(T, 3, 3)) * 0.002
    cov_q = np.tile(np.eye(3) * 0.002**2, (T, 3, 1, 1))
    q[2, 1] += [0.3, 0.0, 0.0]  # a wrong prism position: distance gate
    cov_q[4] *= 0.3**2 / 0.002**2  # a very uncertain pose: uncertainty gate
    q[6, 0] = np.nan  # a missing prism: degenerate
    ref = ReferencePoints(("1", "2", "3"), r, np.eye(9) * 1e-7)
    est = estimate_poses(q, cov_q, ref, engine="linear")
    keep, rep = apply_gates(est, ref)
    assert list(np.flatnonzero(~keep)) == [2, 4, 6]
    assert rep.reason[2] == "distance" and rep.reason[4] == "uncertainty"
    assert rep.reason[6] == "degenerate"
    # the same with the reference positions as an array, or its distances
    keep2, _ = apply_gates(est, r)
    keep3, _ = apply_gates(est, REF_D)
    np.testing.assert_array_equal(keep, keep2)
    np.testing.assert_array_equal(keep, keep3)
    with pytest.raises(ValueError, match="distances"):
        apply_gates(est, REF_D[:2])
