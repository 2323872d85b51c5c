"""Honest uncertainty end to end: simulated deployments with known truth.

The ground truth's covariance must describe its error: pooled over many simulated deployments,
NEES / dof should average to 1 (issue: within 15 %) and the 95 % regions should hold the truth
95 % of the time (within 3 %). Errors are correlated along one deployment (a station's
calibration or clock offset is drawn once per deployment), so the statistics are pooled over
deployments, each a fresh draw of every systematic error, rather than over more poses of one.

``benchmarks/honesty.py`` measures the claim on 120 deployments (spread about +-0.04 on
NEES / dof): Monte Carlo 1.03 (position) / 1.02 (pose), 95 % regions 95.3 % / 94.4 %; linear
and unscented 1.01 / 0.99, 95.6 % / 95.0 % (docs/honesty.md#simulated-deployments, the
weighted registration). This test pools 40
deployments (spread about +-0.06), so its bounds add two spreads to the issue's tolerances on
the means, and one point to those on the 95 % regions; the per-prism check uses the issue's
tolerances as they are (each prism is pooled over all 40 deployments and is far from them).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.stats import chi2

from rtsgt.filtering.gates import apply_gates
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.io.deployment import load_deployment
from rtsgt.pipeline import run_pipeline
from rtsgt.pose import estimate_poses
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth
from rtsgt.types import PoseTrajectory

pytestmark = pytest.mark.slow  # every test shares the 40 deployments

SEEDS = range(1000, 1040)
DURATION_S = 150.0


def _run(tmp, seed, **options):
    sim = simulate_deployment(SimulationConfig(duration_s=DURATION_S), np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, tmp / f"dep{seed}"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # markers seen by one station only, by design
        result = run_pipeline(data, opts.updated(seed=seed, **options))
    p, q = sim.truth_at(result.groundtruth.t)
    return (result, compare_to_truth(result.groundtruth, p, q)), sim


@pytest.fixture(scope="module")
def pooled(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("honesty")
    return [_run(tmp, s, engine="mc", samples=500) for s in SEEDS]


def test_every_interpolated_prism_is_consistent(pooled):
    """Per prism, with every source: the issue's criteria, +-15 % on NEES / dof, +-3 % on the
    95 % region."""
    nees = {}
    for result, sim in ((r, s) for (r, _), s in pooled):
        ids = list(sim.truth.prism_ids)
        P = result.computation.prisms
        for i, pid in enumerate(result.computation.tracks):
            e = P.xyz[:, i] - sim.truth.model.prisms_at(P.t)[:, ids.index(pid)]
            d2 = np.einsum("ni,nij,nj->n", e, np.linalg.inv(P.cov[:, i]), e)
            nees.setdefault(pid, []).append(d2)
    for pid, parts in nees.items():
        d2 = np.concatenate(parts)
        assert abs(d2.mean() / 3.0 - 1.0) < 0.15, (pid, d2.mean() / 3.0)
        assert abs(np.mean(d2 <= chi2.ppf(0.95, 3)) - 0.95) < 0.03, pid


def test_pose_nees_for_the_monte_carlo_engine(pooled):
    n6 = np.concatenate([c.nees_pose.values for (_, c), _ in pooled])
    n3 = np.concatenate([c.nees_position.values for (_, c), _ in pooled])
    assert n6.size > 10_000  # several thousand poses, from 40 independent deployments
    spread = 0.06  # of NEES / dof over 40 deployments (module docstring)
    assert abs(n6.mean() / 6.0 - 1.0) < 0.15 + 2 * spread, n6.mean() / 6.0
    assert abs(n3.mean() / 3.0 - 1.0) < 0.15 + 2 * spread, n3.mean() / 3.0
    assert abs(np.mean(n6 <= chi2.ppf(0.95, 6)) - 0.95) < 0.03 + 0.01
    assert abs(np.mean(n3 <= chi2.ppf(0.95, 3)) - 0.95) < 0.03 + 0.01


def test_errors_are_millimetric_and_the_engines_agree(pooled, tmp_path):
    err = np.concatenate([c.position_error_m for (_, c), _ in pooled])
    assert np.median(err) < 3e-3
    # the three pose engines on the same deployment: covariances within 10 % (Frobenius)
    seed = SEEDS[0]
    covs = {e: _run(tmp_path / e, seed, engine=e, samples=2000)[0][0].groundtruth.cov
            for e in ("mc", "ut", "linear")}
    for a, b in (("mc", "linear"), ("ut", "linear")):
        rel = np.linalg.norm(covs[a] - covs[b], axis=(1, 2)) / np.linalg.norm(covs[b], axis=(1, 2))
        assert np.median(rel) < 0.10, (a, b, np.median(rel))


def test_the_static_noise_check_rarely_flags_an_honest_run(pooled):
    """The static-stretch noise check (rtsgt.checks.static) on the same 40 deployments: the
    measurement noise is the model's, so the scatter pooled over every static stretch matches
    the predicted white variance per component, and a run is flagged (any verdict but
    consistent, on any prism) about 5 % of the time (the check's Bonferroni level)."""
    from rtsgt.checks.static import COMPONENTS

    ratio, dof, checked, flagged = np.zeros(3), 0, 0, 0
    for (result, _), _ in pooled:
        out = result.self_checks["static_noise"]
        if not out["prisms"]:
            continue  # line-of-sight losses cut the first stop short
        checked += 1
        verdicts = set()
        for e in out["prisms"].values():
            m = e["samples"] - e["stretches"]
            ratio += [e[c]["level"]["variance_ratio"] * m for c in COMPONENTS]
            dof += m
            verdicts |= {e[c][t]["verdict"] for c in COMPONENTS for t in ("level", "correlation")}
        flagged += bool(verdicts & {"optimistic", "pessimistic"})
    assert checked >= 30
    # about 2500 degrees of freedom per component: +-0.03 at one sigma
    np.testing.assert_allclose(ratio / dof, 1.0, atol=0.08)
    assert flagged / checked <= 0.1, (flagged, checked)


def _poses_with(result, registration):
    """The run's pose stage redone on its prisms with the linear engine and a registration
    (the gates as the run's)."""
    o, c, ref = result.options, result.computation, result.tracked_reference
    est = estimate_poses(c.prisms.xyz, c.prisms.pose_covariance, ref, engine="linear",
                         registration=registration)
    keep, _ = apply_gates(est, ref, distance_gate_m=o.pose.distance_gate_m,
                          uncertainty_gate_m=o.pose.uncertainty_gate_m)
    return PoseTrajectory(c.prisms.t[keep], est.t[keep], matrix_to_quat_xyzw(est.R[keep]),
                          est.cov[keep])


def test_the_weighted_registration_is_honest_and_cuts_the_variance(pooled):
    """The weighted fit on the same 40 deployments (linear engine): NEES and coverage within
    the bounds above, and the issue's gain: the median over poses of the variance (trace of
    each 3x3 block) cut by at least 20 % in position and 40 % in rotation against the paper's
    unweighted fit (benchmarks/registration.py measures it on 60 fresh deployments)."""
    n3, n6, cut_t, cut_r = [], [], [], []
    for (result, _), sim in pooled:
        w, u = _poses_with(result, "weighted"), _poses_with(result, "unweighted")
        p, q = sim.truth_at(w.t)
        c = compare_to_truth(w, p, q)
        n3.append(c.nees_position.values)
        n6.append(c.nees_pose.values)
        _, iw, iu = np.intersect1d(w.t, u.t, return_indices=True)
        for blk, out in ((slice(0, 3), cut_t), (slice(3, 6), cut_r)):
            out.append(np.trace(w.cov[iw][:, blk, blk], axis1=1, axis2=2)
                       / np.trace(u.cov[iu][:, blk, blk], axis1=1, axis2=2))
    n3, n6 = np.concatenate(n3), np.concatenate(n6)
    spread = 0.06
    assert abs(n6.mean() / 6.0 - 1.0) < 0.15 + 2 * spread, n6.mean() / 6.0
    assert abs(n3.mean() / 3.0 - 1.0) < 0.15 + 2 * spread, n3.mean() / 3.0
    assert abs(np.mean(n6 <= chi2.ppf(0.95, 6)) - 0.95) < 0.03 + 0.01
    assert abs(np.mean(n3 <= chi2.ppf(0.95, 3)) - 0.95) < 0.03 + 0.01
    assert 1 - np.median(np.concatenate(cut_t)) >= 0.20
    assert 1 - np.median(np.concatenate(cut_r)) >= 0.40
