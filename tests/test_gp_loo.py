"""Qc by leave-one-out cross-validation (rtsgt.interpolation.loo)."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.interpolation import gp, loo
from rtsgt.interpolation.gp import fit_qc, fit_track
from rtsgt.interpolation.loo import fit_qc_loo, loo_predictive
from test_gp import measure, random_spd, simulate_prior  # helpers of the GP tests


def _track(rng, n, q_true, sigma2=9e-6):
    t = 1.668e9 + np.cumsum(rng.uniform(0.3, 0.5, n))
    R = random_spd(rng, n, sigma2, cond=10)
    x = simulate_prior(rng, t, q_true, np.array([10.0, -5, 2, 0.5, 0.1, 0]))
    return t, measure(rng, x[:, :3], R), R, x


def test_leave_one_out_predictive_equals_a_refit_without_the_measurement():
    """The information-form shortcut is exact: refit the GP without y_k, query it at t_k."""
    rng = np.random.default_rng(3)
    t, y, R, _ = _track(rng, 40, 0.02)
    qc = 0.02
    used, resid, S = loo_predictive((t, y, R), qc, max_gap_s=10.0)
    assert used.sum() == 38 and not used[0] and not used[-1]
    for k in np.flatnonzero(used)[::7]:
        keep = np.arange(t.size) != k
        gp = fit_track((t[keep], y[keep], R[keep]), qc=qc, max_gap_s=10.0)
        q = gp.query([t[k]])
        i = int(np.flatnonzero(np.flatnonzero(used) == k)[0])
        np.testing.assert_allclose(resid[i], y[k] - q.position[0], rtol=0, atol=1e-10)
        np.testing.assert_allclose(S[i], q.position_cov[0] + R[k], rtol=1e-7)


@pytest.mark.parametrize("prior", ["wnoa", "wnoj"])
def test_candidates_scored_together_score_as_each_alone(prior):
    """The search's batches (K systems solved as one, uncoupled) give each candidate's own
    score: isotropic, per-axis, scaled per interval, and a very stiff Qc."""
    rng = np.random.default_rng(21)
    t, y, R, _ = _track(rng, 120, 0.02)
    scorer = loo.LooScorer((t, y, R), 3.0, prior)
    qcs = [0.02, np.diag([0.01, 0.03, 1e-4]), 0.05, 1e-6]
    scales = [None, None, rng.uniform(0.1, 3.0, t.size - 1), None]
    together = scorer.scores(qcs, scales)
    for (ll, nees, n), q, s in zip(together, qcs, scales, strict=True):
        ll1, nees1, n1 = scorer(q, s)
        assert n == n1 == 118
        assert ll == pytest.approx(ll1, rel=1e-10, abs=1e-8)
        assert nees == pytest.approx(nees1, rel=1e-8)
    # and each alone is the dense refit's (test above) through loo_predictive
    ll, _, _ = loo.loo_score((t, y, R), 0.02, 3.0, prior=prior)
    assert together[0][0] == pytest.approx(ll, rel=1e-10)


@pytest.mark.parametrize("prior", ["wnoa", "wnoj"])
def test_candidates_solved_in_parts_give_the_whole_system_bit_for_bit(prior, monkeypatch):
    """The stacked systems solved in parts of at most _STACK_BLOCKS blocks (each part
    eliminated in the order of the whole) give the numbers of one reduction of all, exactly:
    the search's path, and so the fitted Qc, does not depend on the parts."""
    rng = np.random.default_rng(22)
    t, y, R, _ = _track(rng, 37, 0.02)
    data = gp.prepare_track((t, y, R), prior=prior)
    qcs = [np.diag(rng.uniform(1e-3, 0.1, 3)) for _ in range(5)]
    scales = [None, rng.uniform(0.2, 3.0, 36), None, None, rng.uniform(0.2, 3.0, 36)]
    monkeypatch.setattr(gp, "_STACK_BLOCKS", 1 << 20)
    whole = gp.posteriors(data, qcs, scales)
    for blocks in (1, 37, 73, 111):
        monkeypatch.setattr(gp, "_STACK_BLOCKS", blocks)
        parts = gp.posteriors(data, qcs, scales)
        for a, b in zip(whole, parts, strict=True):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(("prior", "dim"), [("wnoa", 6), ("wnoj", 9)])
def test_the_search_holds_few_blocks_per_knot_and_candidate(prior, dim):
    """Memory of the search's unit of work (issue 25): the cyclic reduction frees each level
    once reduced, updates in place, solves long tracks in parts and keeps the position
    covariances only: 12.8 blocks of d x d per knot and candidate at the peak before, 2.8
    now."""
    rng = np.random.default_rng(8)
    n = 3000
    t, y, R, _ = _track(rng, n, 0.02)
    scorer = loo.LooScorer((t, y, R), 3.0, prior)
    qcs = [np.diag([0.01, 0.02, 0.03]) * f for f in (1.0, 1.1, 1.2, 1.3)]
    tracemalloc.start()
    try:
        scorer.scores(qcs)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4 * len(qcs) * n * dim * dim * 8


def test_knots_next_to_long_gaps_are_not_scored():
    rng = np.random.default_rng(4)
    t, y, R, _ = _track(rng, 30, 0.02)
    t = t.copy()
    t[15:] += 20.0  # a 20 s gap between knots 14 and 15
    used, _, _ = loo_predictive((t, y, R), 0.02, max_gap_s=3.0)
    assert not used[14] and not used[15] and used[13] and used[16]


@pytest.mark.parametrize("q_true", [1e-3, 0.05])
def test_on_a_white_noise_acceleration_track_both_criteria_find_the_true_qc(q_true):
    """When the motion follows the prior, leave-one-out and the likelihood agree (within the
    20 % of the likelihood's own recovery test, a little wider for the noisier LOO)."""
    rng = np.random.default_rng(int(q_true * 1e5) + 1)
    t, y, R, _ = _track(rng, 1500, q_true)
    loo = fit_qc_loo((t, y, R))
    ml, _, _ = fit_qc((t, y, R))
    assert abs(loo.qc / q_true - 1) < 0.3, loo.qc
    assert abs(loo.qc / ml[0, 0] - 1) < 0.3
    assert loo.n_used == t.size - 2
    assert abs(loo.nees_mean - 1.0) < 0.1  # the predictive is calibrated at the optimum


def test_smooth_motion_gets_a_smaller_qc_and_calibrated_interpolation():
    """A smooth path (sinusoid, no white acceleration): the likelihood overstates Qc for
    interpolation; leave-one-out gives a smaller Qc whose midpoint queries are calibrated."""
    rng = np.random.default_rng(8)
    n = 1200
    t = np.cumsum(rng.uniform(0.35, 0.45, n))
    w = 2 * np.pi / 40.0
    truth = lambda s: np.stack([8 * np.sin(w * s), 5 * np.cos(0.7 * w * s), 0.3 * s], -1)  # noqa: E731
    R = random_spd(rng, n, 4e-6, cond=5)
    y = measure(rng, truth(t), R)
    loo = fit_qc_loo((t, y, R))
    ml, _, _ = fit_qc((t, y, R))
    assert loo.qc < ml[0, 0]
    mid = 0.5 * (t[1:] + t[:-1])
    nees = {}
    for name, q in (("loo", loo.qc), ("likelihood", ml[0, 0])):
        g = fit_track((t, y, R), qc=q).query(mid)
        e = g.position - truth(mid)
        nees[name] = np.mean(np.einsum("ni,nij,nj->n", e, np.linalg.inv(g.position_cov), e)) / 3
    assert abs(nees["loo"] - 1.0) < 0.2, nees
    assert nees["likelihood"] < nees["loo"]


def test_too_few_interior_knots_is_a_clear_error():
    rng = np.random.default_rng(9)
    t, y, R, _ = _track(rng, 6, 0.02)
    with pytest.raises(InputError, match="at least 5 measurements"):
        fit_qc_loo((t, y, R), max_gap_s=0.1)


def test_pipeline_falls_back_to_the_likelihood_on_a_track_too_short_to_cross_validate():
    from rtsgt.interpolation.prisms import fit_gps
    from rtsgt.options import InterpolationOptions
    from rtsgt.types import PrismTrack

    rng = np.random.default_rng(12)
    t, y, R, _ = _track(rng, 6, 0.02)
    long_ = _track(rng, 60, 0.02)
    tracks = {"1": PrismTrack(t, y, R, prism="1"), "2": PrismTrack(*long_[:3], prism="2")}
    info = {}
    opts = InterpolationOptions(max_gap_s=0.45)  # knots 0.3-0.5 s apart: track 1 keeps < 5 to score
    with pytest.warns(UserWarning, match="prism 1: .* marginal likelihood instead"):
        gps = fit_gps(tracks, opts, info=info)
    assert info["1"]["method"] == "likelihood" and info["2"]["method"] == "loo"
    ml, _, _ = fit_qc((t, y, R))
    np.testing.assert_allclose(gps["1"].qc, ml, rtol=1e-9)


def test_the_per_axis_search_stays_inside_the_bounds(monkeypatch):
    """A static track drives every q towards 0: the search never tries a q below the floor
    of QC_BOUNDS (it tried 4e-20 m^2/s^3 on a real static deployment) and ends on it."""
    from rtsgt.interpolation import QC_BOUNDS

    tried = []
    scores = loo.LooScorer.scores

    def recording(self, qcs, scales=None):
        tried.extend(np.diag(q) if np.ndim(q) == 2 else np.full(3, q) for q in qcs)
        return scores(self, qcs, scales)

    monkeypatch.setattr(loo.LooScorer, "scores", recording)
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.3, 0.5, 300))
    xyz = np.array([3.0, 1.5, 0.9]) + rng.normal(0.0, 1e-3, (300, 3))
    info = loo.fit_qc_loo((t, xyz, np.tile(1e-6 * np.eye(3), (300, 1, 1))), mode="per-axis")
    assert np.min(tried) >= QC_BOUNDS[0] * (1 - 1e-9) and np.max(tried) <= QC_BOUNDS[1]
    assert np.min(np.diag(info.qc)) == pytest.approx(QC_BOUNDS[0], rel=1e-6)
