"""The static relative-pose self-check (rtsgt.evaluation.static_poses): its pairs, and that it
passes where the simulated noise is the model's and catches noise correlated over seconds that
the run carries as white."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from rtsgt.checks.static import static_stretches
from rtsgt.checks.verdict import run_verdict
from rtsgt.evaluation.groundtruth import ContinuousGroundTruth
from rtsgt.evaluation.static_poses import static_pairs, static_relative_check
from rtsgt.interpolation.prisms import gp_velocity_z2
from rtsgt.io.deployment import load_deployment
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.reality import RealityEffects


def test_pairs_fill_each_stretch_and_share_no_pose():
    t_a, t_b, which = static_pairs([[0.0, 10.0], [20.0, 23.0], [30.0, 30.5]], 1.0)
    np.testing.assert_allclose(t_a, [0, 2, 4, 6, 8, 20, 22])
    np.testing.assert_allclose(t_b - t_a, 1.0)
    np.testing.assert_array_equal(which, [0, 0, 0, 0, 0, 1, 1])
    t_a, t_b, which = static_pairs([[0.0, 10.0], [20.0, 23.0]], 10.0)
    np.testing.assert_allclose(np.c_[t_a, t_b], [[0.0, 10.0]])
    assert static_pairs(np.zeros((0, 2)), 1.0)[0].shape == (0,)


def _check(tmp_path, seed, reality):
    # a long stop at the start, no line-of-sight losses: about 100 s standing
    cfg = SimulationConfig(duration_s=120.0, initial_stop_s=(110.0, 115.0), dropouts=False,
                           reality=reality)
    sim = simulate_deployment(cfg, np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, tmp_path / f"d{seed}"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        record = run_pipeline(data, opts.updated(seed=seed, engine="linear"))
    c = record.computation
    t = c.prisms.t[c.keep]  # the pipeline's rule: the GPs' velocity tested too
    stretches = static_stretches(t, c.prisms.xyz[c.keep], gp_velocity_z2(c.gps, t))
    assert stretches[:, 1].max() - stretches[:, 0].min() > 90.0
    return static_relative_check(ContinuousGroundTruth.from_record(record), stretches,
                                 lags=(1.0, 10.0), warn=False)


@pytest.mark.slow
def test_white_noise_passes_and_correlated_noise_carried_as_white_is_caught(tmp_path):
    white = _check(tmp_path, 5101, RealityEffects())
    assert white["lags"]["1"]["pairs"] >= 45 and white["lags"]["10"]["pairs"] >= 4
    for v in white["lags"].values():
        assert v["nees_per_dof"] < 1.3, white
    # Gauss-Markov noise of 5 s beside the white: averaged over a stretch as if white, it is
    # not; relative poses over 10 s then move far more than the run says
    gm = RealityEffects.only("correlated_noise", correlated_time_s=5.0,
                             correlated_sigma_angle_rad=2.0 * 4.848e-6,
                             correlated_sigma_distance_m=2e-3)
    out = _check(tmp_path, 5102, gm)
    ten = out["lags"]["10"]
    assert ten["nees_per_dof"] > 3.0 * white["lags"]["10"]["nees_per_dof"], out
    assert ten["nees_per_dof"] > 2.0, out


def test_an_optimistic_lag_is_a_caveat_of_the_verdict_and_a_pessimistic_one_a_note():
    lags = {"1": {"pairs": 50, "nees_per_dof": 0.4, "interval_95": [0.8, 1.2],
                  "verdict": "pessimistic"},
            "10": {"pairs": 12, "nees_per_dof": 5.2, "interval_95": [0.7, 1.4],
                   "verdict": "optimistic"},
            "60": {"pairs": 2, "nees_per_dof": 9.0, "interval_95": None,
                   "verdict": "too few pairs"}}
    v = run_verdict({"static_relative": {"lags": lags}}, kept=10, queried=10)
    assert v.level == "usable, with caveats"
    assert [(f.severity, f.check) for f in v.findings] == [(1, "static relative poses"),
                                                          (0, "static relative poses")]
    assert "10 s (NEES/dof 5.20 > 1.40)" in v.line() and "60 s" not in v.line()


def test_the_raw_block_cross_validation_of_a_joint_run_enters_the_verdict():
    whole = {"blocks": 300, "nees_per_dof": 2.4, "interval_95": [0.9, 1.1],
             "verdict": "optimistic"}
    one = {"blocks": 100, "nees_per_dof": 3.1, "interval_95": [0.8, 1.2],
           "verdict": "optimistic"}
    fine = {"blocks": 100, "nees_per_dof": 1.0, "interval_95": [0.8, 1.2],
            "verdict": "consistent"}
    v = run_verdict({"raw_block_cv": {"overall": whole, "stations": {"2": one, "1": fine}}},
                    kept=10, queried=10)
    assert v.level == "not usable as is"
    assert [(f.severity, f.check) for f in v.findings] == [
        (2, "raw block cross-validation"), (1, "raw block cross-validation")]
    assert "NEES/dof 2.40 above [0.90, 1.10] (300 blocks)" in v.line()
    assert "station 2 (NEES/dof 3.10 > 1.20)" in v.findings[1].text
